//! Each passing lane's exact span of one pixel (the single walk's crossings), portable and
//! AVX2.

#![allow(unsafe_code)]

use super::*;

/// Each passing lane's exact span of pixel `c` (walk-order index `kk`) of the current row, as
/// the single walk solves it: the later of the row's and the pixel's entries, the earlier of
/// their exits, never before what the lane has composited (`t_done`, advanced here). `pass`
/// holds the lanes' bits; the spans hold those of positive length.
#[inline(always)]
pub(super) fn pixel_spans(
    l: &Lanes,
    row: &Row,
    c: i32,
    kk: i32,
    pass: u32,
    t_done: &mut F,
) -> Spans {
    let mut spans = Spans {
        ta: [0.0; LANES],
        tb: [0.0; LANES],
        lanes: 0,
    };
    for (k, done) in t_done.iter_mut().enumerate() {
        if pass & (1 << k) == 0 {
            continue;
        }
        let ta = if kk == row.c_in[k] {
            row.t_in[k]
        } else {
            l.cross(k, true, c + 1 - l.i_ahead[k]).max(row.t_in[k])
        };
        let tb = if kk == row.c_out[k] {
            row.t_out[k]
        } else {
            l.cross(k, true, c + l.i_ahead[k]).min(row.t_out[k])
        };
        let ta = ta.max(*done);
        let tb = tb.max(ta);
        *done = tb;
        if tb > ta {
            spans.ta[k] = ta;
            spans.tb[k] = tb;
            spans.lanes |= 1 << k;
        }
    }
    spans
}

/// [`pixel_spans`] with AVX2, eight lanes at once; the same operations (`f32::max` and
/// `f32::min` with their NaN rule), the same result.
///
/// # Safety
/// The CPU must have AVX2.
#[cfg(target_arch = "x86_64")]
#[inline]
#[target_feature(enable = "avx2")]
pub(super) unsafe fn pixel_spans_avx2(
    l: &Lanes,
    row: &Row,
    c: i32,
    kk: i32,
    pass: u32,
    t_done: &mut F,
) -> Spans {
    use lanes8::*;
    use std::arch::x86_64::*;
    // `f32::max(a, b)` / `f32::min(a, b)`: the other operand where one is NaN.
    let max = |a, b| _mm256_blendv_ps(_mm256_max_ps(a, b), a, _mm256_cmp_ps::<_CMP_UNORD_Q>(b, b));
    let min = |a, b| _mm256_blendv_ps(_mm256_min_ps(a, b), a, _mm256_cmp_ps::<_CMP_UNORD_Q>(b, b));
    let passing = lanes_mask(pass);
    let cross_i = |b| cross_avx2(l, true, b);
    let cv = _mm256_set1_epi32(c);
    let ahead = load_i(&l.i_ahead);
    let entry = cross_i(_mm256_sub_epi32(
        _mm256_add_epi32(cv, _mm256_set1_epi32(1)),
        ahead,
    ));
    let exit = cross_i(_mm256_add_epi32(cv, ahead));
    let kv = _mm256_set1_epi32(kk);
    let (t_in, t_out) = (load(&row.t_in), load(&row.t_out));
    let first = _mm256_castsi256_ps(_mm256_cmpeq_epi32(kv, load_i(&row.c_in)));
    let last = _mm256_castsi256_ps(_mm256_cmpeq_epi32(kv, load_i(&row.c_out)));
    let ta = _mm256_blendv_ps(max(entry, t_in), t_in, first);
    let tb = _mm256_blendv_ps(min(exit, t_out), t_out, last);
    let done = load(t_done);
    let ta = max(ta, done);
    let tb = max(tb, ta);
    let active = _mm256_and_ps(passing, _mm256_cmp_ps::<_CMP_GT_OQ>(tb, ta));
    *t_done = lanes_of(_mm256_blendv_ps(done, tb, passing));
    Spans {
        ta: lanes_of(ta),
        tb: lanes_of(tb),
        lanes: _mm256_movemask_ps(active) as u32,
    }
}

/// [`Lanes::cross`] in eight lanes (boundaries `b`, of the inner axis where `inner`, else of
/// the outer one): [`super::super::cross`] step for step.
///
/// # Safety
/// The CPU must have AVX2.
#[cfg(target_arch = "x86_64")]
#[inline]
#[target_feature(enable = "avx2")]
pub(super) unsafe fn cross_avx2(
    l: &Lanes,
    inner: bool,
    b: std::arch::x86_64::__m256i,
) -> std::arch::x86_64::__m256 {
    use lanes8::load;
    use std::arch::x86_64::*;
    let (x_axis, tan, c0, c1) = if inner {
        (l.inner_x, l.i_tan, load(&l.i0), load(&l.i1))
    } else {
        (!l.inner_x, l.o_tan, load(&l.o0), load(&l.o1))
    };
    let (z0, z1, t0, t1, r) = (load(&l.z0), load(&l.z1), load(&l.t0), load(&l.t1), l.r);
    let q = _mm256_div_ps(
        _mm256_mul_ps(_mm256_set1_ps(2.0), _mm256_cvtepi32_ps(b)),
        _mm256_set1_ps(r),
    );
    let one = _mm256_set1_ps(1.0);
    let s = _mm256_mul_ps(
        if x_axis {
            _mm256_sub_ps(q, one)
        } else {
            _mm256_sub_ps(one, q)
        },
        _mm256_set1_ps(tan),
    );
    let t = _mm256_div_ps(
        _mm256_sub_ps(_mm256_mul_ps(s, z0), c0),
        _mm256_sub_ps(c1, _mm256_mul_ps(s, z1)),
    );
    // `f32::clamp(t0, t1)`.
    let t = _mm256_blendv_ps(t, t0, _mm256_cmp_ps::<_CMP_LT_OQ>(t, t0));
    _mm256_blendv_ps(t, t1, _mm256_cmp_ps::<_CMP_GT_OQ>(t, t1))
}
