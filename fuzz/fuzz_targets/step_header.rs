//! The generator-node's step-header checks on arbitrary protobuf bytes (the first message of
//! `PushStep`): a header is accepted only if its brick fits its grid, its rank its world, and
//! its byte count its brick; the spool's reader takes the same path.
#![no_main]

use insitu_generator_node::ingest::check_header;
use insitu_proto::pb;
use libfuzzer_sys::fuzz_target;
use prost::Message;

fuzz_target!(|data: &[u8]| {
    let Ok(h) = pb::StepHeader::decode(data) else {
        return;
    };
    if let Ok(raw) = check_header(&h) {
        for a in 0..3 {
            assert!(raw.brick_offset[a] + raw.brick_dims[a] <= raw.global_dims[a]);
        }
        assert!(raw.rank < raw.world_size);
        let voxels: u64 = raw.brick_dims.iter().map(|&d| d as u64).product();
        assert_eq!(voxels * raw.dtype.size_bytes() as u64, h.total_bytes);
    }
});
