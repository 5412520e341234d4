//! The VDI decoder on arbitrary bytes (what a viz-node receives in `ShipVdi`): it returns a
//! VDI or an error, never panics, never allocates past its limits; a decoded VDI re-encodes
//! and decodes to itself.
#![no_main]

use insitu_core::vdi::codec::{decode, encode, Codec, DecodeLimits};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let limits = DecodeLimits {
        max_payload_bytes: 64 << 20,
    };
    if let Ok(vdi) = decode(data, &limits) {
        let again = encode(&vdi, Codec::None).expect("a decoded VDI encodes");
        assert_eq!(decode(&again, &limits).expect("and decodes again"), vdi);
    }
});
