//! Each lane's span of one row of the walk, portable and AVX2.

#![allow(unsafe_code)]

use super::*;

/// Each lane's span of row `ord` (walk order; rows step by `so`, pixels by `si`), the
/// first and last pixel any lane crosses there, and the inverse depths the lanes span there
/// (with their margins).
#[inline(always)]
pub(super) fn row_spans(
    l: &Lanes,
    ord: i32,
    so: i32,
    si: i32,
    r_top: f32,
) -> (Row, [i32; 2], [f32; 2]) {
    let o = so * ord;
    let mut row = Row {
        u_in: [0.0; LANES],
        u_out: [0.0; LANES],
        c_in: [i32::MAX; LANES],
        c_out: [i32::MIN; LANES],
        t_in: [0.0; LANES],
        t_out: [0.0; LANES],
    };
    let (mut k_first, mut k_last) = (i32::MAX, i32::MIN);
    let (mut w_lo, mut w_hi) = (f32::MAX, -f32::MAX);
    for k in 0..LANES {
        let entry = (o + 1 - l.o_ahead[k]) as f32;
        let exit = (o + l.o_ahead[k]) as f32;
        let unit = |u: f32| lesser(greater(u, 0.0), 1.0);
        let u_in = unit((entry - l.o_p0[k]) * l.o_inv[k]);
        let u_out = unit((exit - l.o_p0[k]) * l.o_inv[k]);
        let u_in = if ord == l.first[k] { 0.0 } else { u_in };
        let u_out = if ord == l.last[k] { 1.0 } else { u_out };
        row.u_in[k] = u_in;
        row.u_out[k] = u_out;
        let cell = |u: f32| {
            let p = l.i_p0[k] + l.i_d[k] * u;
            // The pixel holding p, the one ahead when p is on a boundary.
            let c = if l.i_ahead[k] == 0 {
                p.ceil() - 1.0
            } else {
                p.floor()
            };
            lesser(greater(c, 0.0), r_top) as i32
        };
        let (c_in, c_out) = if l.i_steps[k] != 0 {
            (cell(u_in), cell(u_out))
        } else {
            (l.i_cell[k], l.i_cell[k])
        };
        if l.live[k] != 0 && l.first[k] <= ord && ord <= l.last[k] {
            row.c_in[k] = si * c_in;
            row.c_out[k] = si * c_out;
            k_first = k_first.min(row.c_in[k]);
            k_last = k_last.max(row.c_out[k]);
            let w_at = |u: f32| {
                if u >= 1.0 {
                    l.w1[k]
                } else {
                    l.w0[k] + l.dw[k] * u
                }
            };
            let (wa, wb) = (w_at(u_in), w_at(u_out));
            w_lo = lesser(w_lo, lesser(wa, wb) - l.margin[k]);
            w_hi = greater(w_hi, greater(wa, wb) + l.margin[k]);
            row.t_in[k] = if ord == l.first[k] {
                l.t0[k]
            } else {
                l.cross(k, false, o + 1 - l.o_ahead[k])
            };
            row.t_out[k] = if ord == l.last[k] {
                l.t1[k]
            } else {
                l.cross(k, false, o + l.o_ahead[k])
            };
        }
    }
    (row, [k_first, k_last], [w_lo, w_hi])
}

/// [`row_spans`] with AVX2, eight lanes at once; the same operations, the same result.
///
/// # Safety
/// The CPU must have AVX2.
#[cfg(target_arch = "x86_64")]
#[inline]
#[target_feature(enable = "avx2")]
pub(super) unsafe fn row_spans_avx2(
    l: &Lanes,
    ord: i32,
    so: i32,
    si: i32,
    r_top: f32,
) -> (Row, [i32; 2], [f32; 2]) {
    use lanes8::*;
    use std::arch::x86_64::*;
    let (zero, one) = (_mm256_setzero_ps(), _mm256_set1_ps(1.0));
    let ordv = _mm256_set1_epi32(ord);
    let o = _mm256_set1_epi32(so * ord);
    let ahead = load_i(&l.o_ahead);
    let entry = _mm256_cvtepi32_ps(_mm256_sub_epi32(
        _mm256_add_epi32(o, _mm256_set1_epi32(1)),
        ahead,
    ));
    let exit = _mm256_cvtepi32_ps(_mm256_add_epi32(o, ahead));
    let (p0, inv) = (load(&l.o_p0), load(&l.o_inv));
    let unit = |u| lesser(greater(u, zero), one);
    let u_in = unit(_mm256_mul_ps(_mm256_sub_ps(entry, p0), inv));
    let u_out = unit(_mm256_mul_ps(_mm256_sub_ps(exit, p0), inv));
    let (first, last) = (load_i(&l.first), load_i(&l.last));
    let u_in = _mm256_blendv_ps(
        u_in,
        zero,
        _mm256_castsi256_ps(_mm256_cmpeq_epi32(ordv, first)),
    );
    let u_out = _mm256_blendv_ps(
        u_out,
        one,
        _mm256_castsi256_ps(_mm256_cmpeq_epi32(ordv, last)),
    );
    let (i_p0, i_d) = (load(&l.i_p0), load(&l.i_d));
    let behind = _mm256_castsi256_ps(_mm256_cmpeq_epi32(
        load_i(&l.i_ahead),
        _mm256_setzero_si256(),
    ));
    let top = _mm256_set1_ps(r_top);
    let cell = |u| {
        let p = _mm256_add_ps(i_p0, _mm256_mul_ps(i_d, u));
        let c = _mm256_blendv_ps(
            _mm256_floor_ps(p),
            _mm256_sub_ps(_mm256_ceil_ps(p), one),
            behind,
        );
        _mm256_cvttps_epi32(lesser(greater(c, zero), top))
    };
    let steps = load_i(&l.i_steps);
    let i_cell = load_i(&l.i_cell);
    let c_in = _mm256_blendv_epi8(i_cell, cell(u_in), steps);
    let c_out = _mm256_blendv_epi8(i_cell, cell(u_out), steps);
    // In the row: live, and first ≤ ord ≤ last.
    let outside = _mm256_or_si256(
        _mm256_cmpgt_epi32(first, ordv),
        _mm256_cmpgt_epi32(ordv, last),
    );
    let here = _mm256_andnot_si256(outside, load_i(&l.live));
    let dir = _mm256_set1_epi32(si);
    let c_in = _mm256_blendv_epi8(
        _mm256_set1_epi32(i32::MAX),
        _mm256_sign_epi32(c_in, dir),
        here,
    );
    let c_out = _mm256_blendv_epi8(
        _mm256_set1_epi32(i32::MIN),
        _mm256_sign_epi32(c_out, dir),
        here,
    );
    let (w0, w1, dw) = (load(&l.w0), load(&l.w1), load(&l.dw));
    let w_at = |u| w_at(w0, w1, dw, u);
    let (wa, wb) = (w_at(u_in), w_at(u_out));
    let margin = load(&l.margin);
    let here_ps = _mm256_castsi256_ps(here);
    let lo = _mm256_blendv_ps(
        _mm256_set1_ps(f32::MAX),
        _mm256_sub_ps(lesser(wa, wb), margin),
        here_ps,
    );
    let hi = _mm256_blendv_ps(
        _mm256_set1_ps(-f32::MAX),
        _mm256_add_ps(greater(wa, wb), margin),
        here_ps,
    );
    let (t0, t1) = (load(&l.t0), load(&l.t1));
    let cross_o = |b| cross_avx2(l, false, b);
    let t_in = _mm256_blendv_ps(
        cross_o(_mm256_sub_epi32(
            _mm256_add_epi32(o, _mm256_set1_epi32(1)),
            ahead,
        )),
        t0,
        _mm256_castsi256_ps(_mm256_cmpeq_epi32(ordv, first)),
    );
    let t_out = _mm256_blendv_ps(
        cross_o(_mm256_add_epi32(o, ahead)),
        t1,
        _mm256_castsi256_ps(_mm256_cmpeq_epi32(ordv, last)),
    );
    let row = Row {
        u_in: lanes_of(u_in),
        u_out: lanes_of(u_out),
        c_in: lanes_of_i(c_in),
        c_out: lanes_of_i(c_out),
        t_in: lanes_of(t_in),
        t_out: lanes_of(t_out),
    };
    (
        row,
        [
            fold_epi32(c_in, _mm256_min_epi32),
            fold_epi32(c_out, _mm256_max_epi32),
        ],
        [fold_ps(lo, _mm256_min_ps), fold_ps(hi, _mm256_max_ps)],
    )
}
