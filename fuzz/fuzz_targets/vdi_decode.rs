//! The VDI decoder on arbitrary bytes (what a viz-node receives in `ShipVdi`): it returns a
//! VDI or an error, never panics, never allocates past its limits. A decoded VDI re-encodes:
//! at `f32` (format 3) to itself; quantised (format 4) to the same lists and metadata with
//! every colour within its precision's bound (a hostile file's depths may lie on another grid
//! than the encoder's, and are put on its own).
#![no_main]

use insitu_core::vdi::codec::{decode, encode, Codec, DecodeLimits};
use insitu_core::vdi::Precision;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let limits = DecodeLimits {
        max_payload_bytes: 64 << 20,
    };
    if let Ok(vdi) = decode(data, &limits) {
        let Ok(again) = encode(&vdi, Codec::None) else {
            // Only a list deeper than the depth grid holds is refused.
            assert!(vdi.meta().params.precision != Precision::Float32);
            return;
        };
        let back = decode(&again, &limits).expect("a re-encoded VDI decodes");
        match vdi.meta().params.precision {
            Precision::Float32 => assert_eq!(back, vdi),
            p => {
                assert_eq!(back.meta(), vdi.meta());
                assert_eq!(back.offsets(), vdi.offsets());
                let bound = p.color_bound() + 1e-6;
                for (a, b) in vdi.supersegments().iter().zip(back.supersegments()) {
                    for k in 0..3 {
                        assert!((a.color[k] - b.color[k]).abs() <= bound);
                    }
                }
            }
        }
    }
});
