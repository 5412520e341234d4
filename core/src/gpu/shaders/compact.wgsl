// Packs the per-ray budget slots of a band into the compact list layout (counts + prefix
// offsets + one flat array), the layout of the CPU path.

struct CompactParams {
    rays: u32,
    budget: u32,
    groups_x: u32,
    pad: u32,
};

@group(0) @binding(0) var<uniform> C: CompactParams;
@group(0) @binding(1) var<storage, read> slots: array<Segment>;
@group(0) @binding(2) var<storage, read> offsets: array<u32>;
@group(0) @binding(3) var<storage, read_write> packed: array<Segment>;

@compute @workgroup_size(64)
fn compact_main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let ray = gid.x + gid.y * C.groups_x * 64u;
    if (ray >= C.rays) {
        return;
    }
    let start = offsets[ray];
    let count = offsets[ray + 1u] - start;
    for (var k = 0u; k < count; k++) {
        packed[start + k] = slots[ray * C.budget + k];
    }
}
