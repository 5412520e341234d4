// Shared by every kernel: constants, the NaN test, the slab test and the supersegment layout.
//
// WGSL lets implementations assume finite floats, so NaN is tested on the bit pattern and
// "infinity" is the largest finite float.

const BIG: f32 = 3.0e38;

fn is_nan_f(x: f32) -> bool {
    return (bitcast<u32>(x) & 0x7fffffffu) > 0x7f800000u;
}

// Slab test; returns (t_near, t_far), empty when t_near > t_far. Zero direction components
// are parallel slabs (inside or out for every t), never a division by zero.
fn intersect_box(o: vec3<f32>, d: vec3<f32>, lo: vec3<f32>, hi: vec3<f32>) -> vec2<f32> {
    var t_near = -BIG;
    var t_far = BIG;
    for (var a = 0; a < 3; a++) {
        if (d[a] == 0.0) {
            if (o[a] < lo[a] || o[a] > hi[a]) {
                return vec2<f32>(1.0, 0.0);
            }
            continue;
        }
        let inv = 1.0 / d[a];
        let t0 = (lo[a] - o[a]) * inv;
        let t1 = (hi[a] - o[a]) * inv;
        t_near = max(t_near, min(t0, t1));
        t_far = min(t_far, max(t0, t1));
    }
    return vec2<f32>(t_near, t_far);
}

// One supersegment, the layout of `vdi::Supersegment` (six f32, 24 bytes).
struct Segment {
    z_start: f32,
    z_end: f32,
    r: f32,
    g: f32,
    b: f32,
    alpha: f32,
};
