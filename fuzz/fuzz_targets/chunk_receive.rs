//! The chunk assembler (`proto::chunk::receive`) on an arbitrary sequence of stream messages:
//! headers with arbitrary declared sizes, data chunks, empty messages, in any order. It either
//! assembles exactly the declared bytes or refuses; it never allocates more than its limit.
#![no_main]

use bytes::Bytes;
use insitu_proto::{chunk, pb};
use libfuzzer_sys::fuzz_target;

const LIMIT: u64 = 1 << 16;

fuzz_target!(|data: &[u8]| {
    // Each message: a tag byte, then (header) 2 bytes of declared size or (data) a length
    // byte and that many bytes.
    let mut msgs = Vec::new();
    let mut i = 0;
    while i < data.len() {
        let tag = data[i] % 3;
        i += 1;
        let part = match tag {
            0 => {
                let n = data
                    .get(i..i + 2)
                    .map_or(0, |b| u16::from_le_bytes([b[0], b[1]]));
                i = (i + 2).min(data.len());
                Some(pb::vdi_chunk::Part::Header(pb::VdiHeader {
                    total_bytes: u64::from(n) * if n % 7 == 0 { 1 << 20 } else { 1 },
                    ..Default::default()
                }))
            }
            1 => {
                let n = usize::from(data.get(i).copied().unwrap_or(0));
                i = (i + 1).min(data.len());
                let end = (i + n).min(data.len());
                let b = Bytes::copy_from_slice(&data[i..end]);
                i = end;
                Some(pb::vdi_chunk::Part::Data(b))
            }
            _ => None,
        };
        msgs.push(Ok(pb::VdiChunk { part }));
    }
    let rt = tokio::runtime::Builder::new_current_thread()
        .build()
        .expect("runtime");
    let mut stream = tokio_stream::iter(msgs);
    let got = rt.block_on(chunk::receive::<pb::VdiChunk, _>(
        &mut stream,
        LIMIT,
        |_| Ok(()),
    ));
    if let Ok((h, payload)) = got {
        assert_eq!(payload.len() as u64, h.total_bytes);
        assert!(h.total_bytes <= LIMIT);
    }
});
