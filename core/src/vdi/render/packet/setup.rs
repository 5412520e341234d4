//! A packet's set-up: the eight rays' segments in the generation image (their pixels' rays,
//! box and frustum spans, axes), portable and AVX2.

#![allow(unsafe_code)]

use super::*;

impl Lanes {
    /// The lanes of `segs` walked in rows of direction `so` (along x when `TRANSPOSE`) at
    /// generation resolution `r` with `tan` of the half field of view along x and y.
    #[inline(always)]
    pub(super) fn new<const TRANSPOSE: bool>(
        segs: &[Option<Segment>; LANES],
        so: i64,
        r: i64,
        (tan_x, tan_y): (f32, f32),
    ) -> Self {
        let mut l = Lanes {
            live: [0; LANES],
            o_p0: [0.0; LANES],
            o_inv: [0.0; LANES],
            o_ahead: [0; LANES],
            first: [i32::MAX; LANES],
            last: [i32::MIN; LANES],
            i_p0: [0.0; LANES],
            i_inv: [0.0; LANES],
            i_d: [0.0; LANES],
            i_ahead: [0; LANES],
            i_steps: [0; LANES],
            i_cell: [0; LANES],
            w0: [0.0; LANES],
            w1: [0.0; LANES],
            dw: [0.0; LANES],
            margin: [0.0; LANES],
            o0: [0.0; LANES],
            o1: [0.0; LANES],
            i0: [0.0; LANES],
            i1: [0.0; LANES],
            z0: [0.0; LANES],
            z1: [0.0; LANES],
            t0: [0.0; LANES],
            t1: [0.0; LANES],
            inner_x: !TRANSPOSE,
            deeper: 0,
            shallower: 0,
            o_tan: if TRANSPOSE { tan_x } else { tan_y },
            i_tan: if TRANSPOSE { tan_y } else { tan_x },
            r: r as f32,
        };
        for (k, s) in segs.iter().enumerate() {
            let Some(s) = s else { continue };
            let (o, i, o_d, i_d) = axes::<TRANSPOSE>(s);
            let last = if o.step == 0 {
                o.cell
            } else {
                o.cell_at(1.0, o_d, [0, r])
            };
            l.live[k] = -1;
            l.o_p0[k] = o.p0;
            l.o_inv[k] = o.inv_d;
            l.o_ahead[k] = o.ahead as i32;
            l.first[k] = (so * o.cell) as i32;
            l.last[k] = (so * last) as i32;
            l.i_p0[k] = i.p0;
            l.i_inv[k] = i.inv_d;
            l.i_d[k] = i_d;
            l.i_ahead[k] = i.ahead as i32;
            l.i_steps[k] = -i32::from(i.step != 0);
            l.i_cell[k] = i.cell as i32;
            l.w0[k] = s.w0;
            l.w1[k] = s.w1;
            l.dw[k] = s.w1 - s.w0;
            l.margin[k] = s.rounding + s.ax.depth_error + s.ay.depth_error;
            let (outer, inner) = if TRANSPOSE { (s.x, s.y) } else { (s.y, s.x) };
            (l.o0[k], l.o1[k], l.i0[k], l.i1[k]) = (outer.f0, outer.f1, inner.f0, inner.f1);
            (l.z0[k], l.z1[k], l.t0[k], l.t1[k]) = (s.z.f0, s.z.f1, s.t0, s.t1);
            l.deeper |= u32::from(s.z.f1 > 0.0) << k;
            l.shallower |= u32::from(s.z.f1 < 0.0) << k;
        }
        l
    }
}

/// An [`Axis`] of each of eight segments: the lanes stepping up (`up`) and down (`down`) as
/// bits, the first pixel as a float.
pub(super) struct AxisLanes {
    pub(super) p0: F,
    pub(super) inv_d: F,
    pub(super) up: u32,
    pub(super) down: u32,
    pub(super) cell: F,
    pub(super) depth_error: F,
}

/// [`Walker::segment`] of the rays through `block`'s pixels of `frame`, eight at once with
/// AVX2: the same operations in the same order, so the same segments, bit for bit. Lanes
/// outside the frame are `None`. In steps: the rays ([`pixel_rays_avx2`]), their span in the
/// volume box ([`box_span_avx2`]) and in the generation's frustum ([`frustum_span_avx2`]),
/// their projections' ends and inverse depths, the axes ([`axis_lanes_avx2`]), then each
/// lane's [`Segment`].
///
/// # Safety
/// The CPU must have AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
pub(super) unsafe fn segments_avx2(
    walker: &Walker<'_>,
    frame: &ViewFrame,
    block: Block,
) -> [Option<Segment>; LANES] {
    use lanes8::lanes_of;
    use std::arch::x86_64::*;
    let (splat, add, sub, mul, div) = (
        _mm256_set1_ps,
        _mm256_add_ps,
        _mm256_sub_ps,
        _mm256_mul_ps,
        _mm256_div_ps,
    );
    let max = |a, b| _mm256_max_ps(a, b);
    // SAFETY: the helpers need AVX2 only, which this function's caller guarantees.
    let d = unsafe { pixel_rays_avx2(frame, block) };
    let o = frame.eye;
    // SAFETY: as above.
    let (t0, t1) = unsafe { box_span_avx2(&walker.vdi.meta().volume_box, o, d) };
    let g = &walker.gen;
    let e0 = g.to_eye(o);
    // SAFETY: as above.
    let ((t0, t1, valid), [x1, y1, z1]) = unsafe { frustum_span_avx2(g, e0, d, (t0, t1)) };
    let (x0, y0, z0) = (splat(e0.x), splat(e0.y), splat(e0.z));
    let (tx, ty) = (splat(g.tan_half_x), splat(g.tan_half_y));
    let r = walker.r as f32;
    let at = |f0, f1, t| add(f0, mul(f1, t));
    let px = |t| {
        mul(
            mul(
                add(div(at(x0, x1, t), mul(at(z0, z1, t), tx)), splat(1.0)),
                splat(0.5),
            ),
            splat(r),
        )
    };
    let py = |t| {
        mul(
            mul(
                sub(splat(1.0), div(at(y0, y1, t), mul(at(z0, z1, t), ty))),
                splat(0.5),
            ),
            splat(r),
        )
    };
    let (px0, py0, px1, py1) = (px(t0), py(t0), px(t1), py(t1));
    let inverse_depth = |z| div(splat(1.0), max(z, splat(NEAR_DEPTH)));
    let (w0, w1) = (inverse_depth(at(z0, z1, t0)), inverse_depth(at(z0, z1, t1)));
    let abs = |v| _mm256_andnot_ps(splat(-0.0), v);
    let dw = abs(sub(w1, w0));
    let rounding = mul(splat(1e-4), max(abs(w0), abs(w1)));
    // SAFETY: as above.
    let (ax, ay) = unsafe {
        (
            axis_lanes_avx2(px0, px1, dw, r),
            axis_lanes_avx2(py0, py1, dw, r),
        )
    };
    let [x1, y1, z1, t0, t1, px0, py0, px1, py1, w0, w1, rounding] =
        [x1, y1, z1, t0, t1, px0, py0, px1, py1, w0, w1, rounding].map(|v| lanes_of(v));
    let mut segs = [None; LANES];
    for (k, seg) in segs.iter_mut().enumerate() {
        let (i, j) = block.pixel(k);
        if valid & (1 << k) == 0 || i >= frame.width || j >= frame.height {
            continue;
        }
        let lane_axis = |a: &AxisLanes| {
            let step = if a.up & (1 << k) != 0 {
                1
            } else if a.down & (1 << k) != 0 {
                -1
            } else {
                0
            };
            Axis {
                p0: a.p0[k],
                inv_d: a.inv_d[k],
                step,
                ahead: i64::from(step > 0),
                cell: (a.cell[k] as i64).clamp(0, walker.r - 1),
                depth_error: a.depth_error[k],
            }
        };
        let lin = |f0: f32, f1: &F| Lin { f0, f1: f1[k] };
        *seg = Some(Segment {
            x: lin(e0.x, &x1),
            y: lin(e0.y, &y1),
            z: lin(e0.z, &z1),
            t0: t0[k],
            t1: t1[k],
            px0: px0[k],
            py0: py0[k],
            px1: px1[k],
            py1: py1[k],
            w0: w0[k],
            w1: w1[k],
            ax: lane_axis(&ax),
            ay: lane_axis(&ay),
            rounding: rounding[k],
        });
    }
    segs
}

/// The directions of `frame.pixel_ray` through `block`'s eight pixels (x, y, z lanes):
/// through each pixel's centre, normalised.
///
/// # Safety
/// The CPU must have AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
pub(super) unsafe fn pixel_rays_avx2(
    frame: &ViewFrame,
    block: Block,
) -> [std::arch::x86_64::__m256; 3] {
    use std::arch::x86_64::*;
    const _: () = assert!(LANES == 8);
    let (splat, add, sub, mul, div) = (
        _mm256_set1_ps,
        _mm256_add_ps,
        _mm256_sub_ps,
        _mm256_mul_ps,
        _mm256_div_ps,
    );
    let lane = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
    let a = _mm256_and_si256(lane, _mm256_set1_epi32((1 << block.shift) - 1));
    let b = _mm256_srl_epi32(lane, _mm_cvtsi32_si128(block.shift as i32));
    let (i0, j0) = (block.i0, block.j0);
    let px = add(
        _mm256_cvtepi32_ps(_mm256_add_epi32(_mm256_set1_epi32(i0 as i32), a)),
        splat(0.5),
    );
    let py = add(
        _mm256_cvtepi32_ps(_mm256_add_epi32(_mm256_set1_epi32(j0 as i32), b)),
        splat(0.5),
    );
    let sx = mul(
        sub(
            div(mul(splat(2.0), px), splat(frame.width as f32)),
            splat(1.0),
        ),
        splat(frame.tan_half_x),
    );
    let sy = mul(
        sub(
            splat(1.0),
            div(mul(splat(2.0), py), splat(frame.height as f32)),
        ),
        splat(frame.tan_half_y),
    );
    let (f, rt, up) = (frame.forward, frame.right, frame.up);
    let comp = |f: f32, r: f32, u: f32| add(add(splat(f), mul(sx, splat(r))), mul(sy, splat(u)));
    let (dx, dy, dz) = (
        comp(f.x, rt.x, up.x),
        comp(f.y, rt.y, up.y),
        comp(f.z, rt.z, up.z),
    );
    let len = _mm256_sqrt_ps(add(add(mul(dx, dx), mul(dy, dy)), mul(dz, dz)));
    let len_recip = div(splat(1.0), len);
    [mul(dx, len_recip), mul(dy, len_recip), mul(dz, len_recip)]
}

/// `Aabb::intersect` of the eight rays from `o` along `d` with `aabb` (its reciprocal
/// directions, its `(1, 0)` for a ray outside a slab it runs along), the entry clamped to 0:
/// `(t0, t1)` per lane.
///
/// # Safety
/// The CPU must have AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
pub(super) unsafe fn box_span_avx2(
    aabb: &crate::volume::Aabb,
    o: Vec3,
    [dx, dy, dz]: [std::arch::x86_64::__m256; 3],
) -> (std::arch::x86_64::__m256, std::arch::x86_64::__m256) {
    use std::arch::x86_64::*;
    let (splat, sub, mul, div) = (_mm256_set1_ps, _mm256_sub_ps, _mm256_mul_ps, _mm256_div_ps);
    // f32::max / f32::min for operands that are never NaN.
    let max = |a, b| _mm256_max_ps(a, b);
    let min = |a, b| _mm256_min_ps(a, b);
    let mut t_near = splat(f32::NEG_INFINITY);
    let mut t_far = splat(f32::INFINITY);
    let mut empty = _mm256_setzero_ps();
    for (d, o, lo, hi) in [
        (dx, o.x, aabb.min.x, aabb.max.x),
        (dy, o.y, aabb.min.y, aabb.max.y),
        (dz, o.z, aabb.min.z, aabb.max.z),
    ] {
        let inv = div(splat(1.0), d);
        let parallel =
            _mm256_cmp_ps::<_CMP_EQ_OQ>(_mm256_andnot_ps(splat(-0.0), inv), splat(f32::INFINITY));
        if o < lo || o > hi {
            empty = _mm256_or_ps(empty, parallel);
        }
        let t0 = mul(sub(splat(lo), splat(o)), inv);
        let t1 = mul(sub(splat(hi), splat(o)), inv);
        t_near = _mm256_blendv_ps(max(t_near, min(t0, t1)), t_near, parallel);
        t_far = _mm256_blendv_ps(min(t_far, max(t0, t1)), t_far, parallel);
    }
    let t0 = _mm256_blendv_ps(t_near, splat(1.0), empty);
    let t1 = _mm256_blendv_ps(t_far, splat(0.0), empty);
    (max(t0, splat(0.0)), t1)
}

/// The spans `(t0, t1)` of the eight rays from generation eye-space point `e0` along `d`
/// clipped to the generation frustum `g` (its four side planes and the near depth), the lanes
/// with a span left as bits, and the rays' eye-space directions (`x1, y1, z1`).
///
/// # Safety
/// The CPU must have AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
pub(super) unsafe fn frustum_span_avx2(
    g: &ViewFrame,
    e0: Vec3,
    [dx, dy, dz]: [std::arch::x86_64::__m256; 3],
    (mut t0, mut t1): (std::arch::x86_64::__m256, std::arch::x86_64::__m256),
) -> (
    (std::arch::x86_64::__m256, std::arch::x86_64::__m256, u32),
    [std::arch::x86_64::__m256; 3],
) {
    use std::arch::x86_64::*;
    let (splat, add, sub, mul, div) = (
        _mm256_set1_ps,
        _mm256_add_ps,
        _mm256_sub_ps,
        _mm256_mul_ps,
        _mm256_div_ps,
    );
    let max = |a, b| _mm256_max_ps(a, b);
    let min = |a, b| _mm256_min_ps(a, b);
    let dot = |v: Vec3| {
        add(
            add(mul(dx, splat(v.x)), mul(dy, splat(v.y))),
            mul(dz, splat(v.z)),
        )
    };
    let (x1, y1, z1) = (dot(g.right), dot(g.up), dot(g.forward));
    let (x0, y0, z0) = (splat(e0.x), splat(e0.y), splat(e0.z));
    let (tx, ty) = (splat(g.tan_half_x), splat(g.tan_half_y));
    let planes = [
        (sub(mul(tx, z0), x0), sub(mul(tx, z1), x1)),
        (add(mul(tx, z0), x0), add(mul(tx, z1), x1)),
        (sub(mul(ty, z0), y0), sub(mul(ty, z1), y1)),
        (add(mul(ty, z0), y0), add(mul(ty, z1), y1)),
        (sub(z0, splat(NEAR_DEPTH)), z1),
    ];
    let mut outside = _mm256_setzero_ps();
    for (f0, f1) in planes {
        let t = div(_mm256_xor_ps(f0, splat(-0.0)), f1);
        let rising = _mm256_cmp_ps::<_CMP_GT_OQ>(f1, splat(0.0));
        let falling = _mm256_cmp_ps::<_CMP_LT_OQ>(f1, splat(0.0));
        t0 = _mm256_blendv_ps(t0, max(t0, t), rising);
        t1 = _mm256_blendv_ps(t1, min(t1, t), falling);
        let along = _mm256_andnot_ps(
            _mm256_or_ps(rising, falling),
            _mm256_cmp_ps::<_CMP_LT_OQ>(f0, splat(0.0)),
        );
        outside = _mm256_or_ps(outside, along);
    }
    // `t1.is_nan() || t0.is_nan() || t1 <= t0`: not `t0 < t1` (NaN compares false).
    let valid = _mm256_andnot_ps(outside, _mm256_cmp_ps::<_CMP_LT_OQ>(t0, t1));
    ((t0, t1, _mm256_movemask_ps(valid) as u32), [x1, y1, z1])
}

/// One axis of eight projections from `p0` to `p1` (pixels; `dw` their inverse depths'
/// difference, `r` the generation resolution): `u = (b − p0)/(p1 − p0)`'s step, the first
/// pixel and the depth error, as [`Walker::segment`]'s axis.
///
/// # Safety
/// The CPU must have AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
pub(super) unsafe fn axis_lanes_avx2(
    p0: std::arch::x86_64::__m256,
    p1: std::arch::x86_64::__m256,
    dw: std::arch::x86_64::__m256,
    r: f32,
) -> AxisLanes {
    use lanes8::lanes_of;
    use std::arch::x86_64::*;
    let (splat, sub, mul, div) = (_mm256_set1_ps, _mm256_sub_ps, _mm256_mul_ps, _mm256_div_ps);
    let d = sub(p1, p0);
    let up = _mm256_cmp_ps::<_CMP_GT_OQ>(d, splat(DEGENERATE_PX));
    let down = _mm256_cmp_ps::<_CMP_LT_OQ>(d, splat(-DEGENERATE_PX));
    let steps = _mm256_or_ps(up, down);
    let cell = _mm256_blendv_ps(
        _mm256_xor_ps(_mm256_ceil_ps(_mm256_xor_ps(p0, splat(-0.0))), splat(-0.0)),
        sub(_mm256_ceil_ps(p0), splat(1.0)),
        down,
    );
    let inv_d = _mm256_and_ps(div(splat(1.0), d), steps);
    let abs_inv_d = _mm256_andnot_ps(splat(-0.0), inv_d);
    let error = mul(
        _mm256_min_ps(mul(splat(1e-5 * (r + 1.0)), abs_inv_d), splat(1.0)),
        dw,
    );
    AxisLanes {
        p0: lanes_of(p0),
        inv_d: lanes_of(inv_d),
        up: _mm256_movemask_ps(up) as u32,
        down: _mm256_movemask_ps(down) as u32,
        cell: lanes_of(cell),
        depth_error: lanes_of(error),
    }
}
