// Exclusive prefix sums of a band's per-ray supersegment counts, on the device: the offsets of
// the compact list layout (counts + prefix offsets + one flat array). Blocks of 1024 counts
// are scanned one per workgroup, the block totals by one workgroup, then each block's offset
// is added back. `values` holds n counts on entry and n + 1 offsets on exit; u32 arithmetic
// wraps, which the host detects as a decrease of the offsets.

struct ScanParams {
    n: u32,        // counts
    blocks: u32,   // ⌈n / BLOCK⌉
    groups_x: u32, // workgroups per row of the block grid
    pad: u32,
};

@group(0) @binding(0) var<uniform> S: ScanParams;
@group(0) @binding(1) var<storage, read_write> values: array<u32>;
@group(0) @binding(2) var<storage, read_write> sums: array<u32>;

const THREADS: u32 = 256u;
const PER_THREAD: u32 = 4u;
const BLOCK: u32 = 1024u;

var<workgroup> partial: array<u32, 256>;

// Inclusive sum of `x` over threads 0..=t of the workgroup (Hillis–Steele).
fn workgroup_scan(t: u32, x: u32) -> u32 {
    var v = x;
    partial[t] = v;
    workgroupBarrier();
    for (var d = 1u; d < THREADS; d *= 2u) {
        var add = 0u;
        if (t >= d) {
            add = partial[t - d];
        }
        workgroupBarrier();
        v += add;
        partial[t] = v;
        workgroupBarrier();
    }
    return v;
}

@compute @workgroup_size(256)
fn scan_blocks(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) t: u32) {
    let block = wg.x + wg.y * S.groups_x;
    let base = block * BLOCK + t * PER_THREAD;
    var before: array<u32, 4>;
    var sum = 0u;
    for (var k = 0u; k < PER_THREAD; k++) {
        before[k] = sum;
        if (base + k < S.n) {
            sum += values[base + k];
        }
    }
    let inclusive = workgroup_scan(t, sum);
    let start = inclusive - sum;
    for (var k = 0u; k < PER_THREAD; k++) {
        if (base + k < S.n) {
            values[base + k] = start + before[k];
        }
    }
    if (t == THREADS - 1u && block < S.blocks) {
        sums[block] = inclusive;
    }
}

// One workgroup: thread t scans a run of consecutive block totals.
@compute @workgroup_size(256)
fn scan_sums(@builtin(local_invocation_index) t: u32) {
    let per = (S.blocks + THREADS - 1u) / THREADS;
    let first = t * per;
    var sum = 0u;
    for (var k = 0u; k < per; k++) {
        if (first + k < S.blocks) {
            sum += sums[first + k];
        }
    }
    let inclusive = workgroup_scan(t, sum);
    var at = inclusive - sum;
    for (var k = 0u; k < per; k++) {
        if (first + k < S.blocks) {
            let c = sums[first + k];
            sums[first + k] = at;
            at += c;
        }
    }
    if (t == THREADS - 1u) {
        values[S.n] = inclusive;
    }
}

@compute @workgroup_size(256)
fn scan_add(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) t: u32) {
    let block = wg.x + wg.y * S.groups_x;
    if (block >= S.blocks) {
        return;
    }
    let add = sums[block];
    let base = block * BLOCK + t * PER_THREAD;
    for (var k = 0u; k < PER_THREAD; k++) {
        if (base + k < S.n) {
            values[base + k] += add;
        }
    }
}
