//! Which lanes test a pixel of the current row: those that cross it and whose depth bins
//! there meet its occupancy mask, portable and AVX2.

#![allow(unsafe_code)]

use super::*;

/// The lanes that test pixel `c` (walk-order index `kk`, occupancy mask `occupied`) of the
/// current row: bit `k` set where lane `k` crosses the pixel and the depth bins of its span
/// there meet the occupancy (the single walk's test, [`super::super::between`]).
#[inline(always)]
pub(super) fn pixel_tests(
    l: &Lanes,
    row: &Row,
    c: i32,
    kk: i32,
    occupied: u64,
    bins: DepthBins,
) -> u32 {
    let mut pass = 0;
    for k in 0..LANES {
        let entry = (c + 1 - l.i_ahead[k]) as f32;
        let exit = (c + l.i_ahead[k]) as f32;
        let u_a = greater((entry - l.i_p0[k]) * l.i_inv[k], row.u_in[k]);
        let u_b = lesser((exit - l.i_p0[k]) * l.i_inv[k], row.u_out[k]);
        let u_a = if kk == row.c_in[k] { row.u_in[k] } else { u_a };
        let u_b = if kk == row.c_out[k] {
            row.u_out[k]
        } else {
            u_b
        };
        let w_at = |u: f32| {
            if u >= 1.0 {
                l.w1[k]
            } else {
                l.w0[k] + l.dw[k] * u
            }
        };
        let (wa, wb) = (w_at(u_a), w_at(u_b));
        let lo = bins.bin(lesser(wa, wb) - l.margin[k]);
        let hi = bins.bin(greater(wa, wb) + l.margin[k]);
        let covers = row.c_in[k] <= kk && kk <= row.c_out[k];
        if covers && occupied & super::super::bits(lo, hi) != 0 {
            pass |= 1 << k;
        }
    }
    pass
}

/// [`pixel_tests`], eight lanes at once with AVX2; the same operations in the same order,
/// so the same result.
///
/// # Safety
/// The CPU must have AVX2.
#[cfg(target_arch = "x86_64")]
#[inline]
#[target_feature(enable = "avx2")]
pub(super) unsafe fn pixel_tests_avx2(
    l: &Lanes,
    row: &Row,
    c: i32,
    kk: i32,
    occupied: u64,
    bins: DepthBins,
) -> u32 {
    use lanes8::*;
    use std::arch::x86_64::*;
    const _: () = assert!(LANES == 8);
    let c = _mm256_set1_epi32(c);
    let kk = _mm256_set1_epi32(kk);
    let ahead = load_i(&l.i_ahead);
    let entry = _mm256_cvtepi32_ps(_mm256_sub_epi32(
        _mm256_add_epi32(c, _mm256_set1_epi32(1)),
        ahead,
    ));
    let exit = _mm256_cvtepi32_ps(_mm256_add_epi32(c, ahead));
    let (p0, inv) = (load(&l.i_p0), load(&l.i_inv));
    let (u_in, u_out) = (load(&row.u_in), load(&row.u_out));
    let (c_in, c_out) = (load_i(&row.c_in), load_i(&row.c_out));
    let u_a = greater(_mm256_mul_ps(_mm256_sub_ps(entry, p0), inv), u_in);
    let u_b = lesser(_mm256_mul_ps(_mm256_sub_ps(exit, p0), inv), u_out);
    let u_a = _mm256_blendv_ps(u_a, u_in, _mm256_castsi256_ps(_mm256_cmpeq_epi32(kk, c_in)));
    let u_b = _mm256_blendv_ps(
        u_b,
        u_out,
        _mm256_castsi256_ps(_mm256_cmpeq_epi32(kk, c_out)),
    );
    let (w0, w1, dw) = (load(&l.w0), load(&l.w1), load(&l.dw));
    let w_at = |u| w_at(w0, w1, dw, u);
    let (wa, wb) = (w_at(u_a), w_at(u_b));
    let margin = load(&l.margin);
    let (b0, per_unit) = (_mm256_set1_ps(bins.w0), _mm256_set1_ps(bins.per_unit));
    let top = _mm256_set1_ps((DEPTH_BINS - 1) as f32);
    // `DepthBins::bin`: clamped as floats (NaN to 0), then truncated.
    let bin = |w| {
        let x = _mm256_mul_ps(_mm256_sub_ps(w, b0), per_unit);
        _mm256_cvttps_epi32(lesser(greater(x, _mm256_setzero_ps()), top))
    };
    let lo = bin(_mm256_sub_ps(lesser(wa, wb), margin));
    let hi = bin(_mm256_add_ps(greater(wa, wb), margin));
    // `bits(lo, hi) & occupied != 0`, four 64-bit lanes at a time.
    let ones = _mm256_set1_epi64x(-1);
    let occ = _mm256_set1_epi64x(occupied as i64);
    let hits = |lo: __m128i, hi: __m128i| {
        let (lo, hi) = (_mm256_cvtepu32_epi64(lo), _mm256_cvtepu32_epi64(hi));
        let top = _mm256_sub_epi64(_mm256_set1_epi64x(i64::from(DEPTH_BINS - 1)), hi);
        let m = _mm256_and_si256(_mm256_srlv_epi64(ones, top), _mm256_sllv_epi64(ones, lo));
        let none = _mm256_cmpeq_epi64(_mm256_and_si256(m, occ), _mm256_setzero_si256());
        (!_mm256_movemask_pd(_mm256_castsi256_pd(none))) as u32 & 0xf
    };
    let hit = hits(_mm256_castsi256_si128(lo), _mm256_castsi256_si128(hi))
        | hits(
            _mm256_extracti128_si256::<1>(lo),
            _mm256_extracti128_si256::<1>(hi),
        ) << 4;
    // Crossing the pixel: c_in ≤ kk ≤ c_out.
    let outside = _mm256_or_si256(_mm256_cmpgt_epi32(c_in, kk), _mm256_cmpgt_epi32(kk, c_out));
    let covers = !(_mm256_movemask_ps(_mm256_castsi256_ps(outside)) as u32) & 0xff;
    hit & covers
}
