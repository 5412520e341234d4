//! Eight-lane AVX2 helpers of the packet kernels: horizontal folds, loads and stores of lane
//! arrays, masks, and the per-lane forms of the walk's scalar helpers. Each needs a CPU with
//! AVX2 (`unsafe`).

#![allow(unsafe_code)]

use super::*;
use std::arch::x86_64::*;

/// `f` (a minimum or maximum: exact, in any order) over the eight lanes of `v`.
///
/// # Safety
/// The CPU must have AVX2.
#[inline]
#[target_feature(enable = "avx2")]
pub(super) unsafe fn fold_ps(
    v: std::arch::x86_64::__m256,
    f: unsafe fn(std::arch::x86_64::__m256, std::arch::x86_64::__m256) -> std::arch::x86_64::__m256,
) -> f32 {
    use std::arch::x86_64::*;
    let v = f(v, _mm256_permute2f128_ps::<1>(v, v));
    let v = f(v, _mm256_shuffle_ps::<0b01_00_11_10>(v, v));
    _mm256_cvtss_f32(f(v, _mm256_shuffle_ps::<0b10_11_00_01>(v, v)))
}

/// [`fold_ps`] of eight integers.
///
/// # Safety
/// The CPU must have AVX2.
#[inline]
#[target_feature(enable = "avx2")]
pub(super) unsafe fn fold_epi32(
    v: std::arch::x86_64::__m256i,
    f: unsafe fn(
        std::arch::x86_64::__m256i,
        std::arch::x86_64::__m256i,
    ) -> std::arch::x86_64::__m256i,
) -> i32 {
    use std::arch::x86_64::*;
    let v = f(v, _mm256_permute2x128_si256::<1>(v, v));
    let v = f(v, _mm256_shuffle_epi32::<0b01_00_11_10>(v));
    _mm256_cvtsi256_si32(f(v, _mm256_shuffle_epi32::<0b10_11_00_01>(v)))
}

/// The eight lanes of `a` (unaligned load of eight 4-byte values).
#[inline]
#[target_feature(enable = "avx2")]
pub(super) unsafe fn load(a: &F) -> __m256 {
    _mm256_loadu_ps(a.as_ptr())
}

/// The eight lanes of `a`.
#[inline]
#[target_feature(enable = "avx2")]
pub(super) unsafe fn load_i(a: &I) -> __m256i {
    _mm256_loadu_si256(a.as_ptr().cast())
}

/// `v`'s eight lanes as an array (unaligned store of eight 4-byte values).
#[inline]
#[target_feature(enable = "avx2")]
pub(super) unsafe fn lanes_of(v: __m256) -> F {
    let mut a = [0.0; 8];
    _mm256_storeu_ps(a.as_mut_ptr(), v);
    a
}

/// `v`'s eight lanes as an array.
#[inline]
#[target_feature(enable = "avx2")]
pub(super) unsafe fn lanes_of_i(v: __m256i) -> I {
    let mut a = [0; 8];
    _mm256_storeu_si256(a.as_mut_ptr().cast(), v);
    a
}

/// All bits set in the lanes whose bit is set in `bits`.
#[inline]
#[target_feature(enable = "avx2")]
pub(super) unsafe fn lanes_mask(bits: u32) -> __m256 {
    let lane_bits = _mm256_setr_epi32(1, 2, 4, 8, 16, 32, 64, 128);
    _mm256_castsi256_ps(_mm256_cmpeq_epi32(
        _mm256_and_si256(_mm256_set1_epi32(bits as i32), lane_bits),
        lane_bits,
    ))
}

/// [`super::super::greater`] per lane: `a` where `a > b`, else `b`.
#[inline]
#[target_feature(enable = "avx2")]
pub(super) unsafe fn greater(a: __m256, b: __m256) -> __m256 {
    _mm256_blendv_ps(b, a, _mm256_cmp_ps::<_CMP_GT_OQ>(a, b))
}

/// [`super::super::lesser`] per lane: `a` where `a < b`, else `b`.
#[inline]
#[target_feature(enable = "avx2")]
pub(super) unsafe fn lesser(a: __m256, b: __m256) -> __m256 {
    _mm256_blendv_ps(b, a, _mm256_cmp_ps::<_CMP_LT_OQ>(a, b))
}

/// [`super::super::Segment::w_at`] per lane: `w1` where `u ≥ 1`, else `w0 + dw·u`.
#[inline]
#[target_feature(enable = "avx2")]
pub(super) unsafe fn w_at(w0: __m256, w1: __m256, dw: __m256, u: __m256) -> __m256 {
    let w = _mm256_add_ps(w0, _mm256_mul_ps(dw, u));
    _mm256_blendv_ps(w, w1, _mm256_cmp_ps::<_CMP_GE_OQ>(u, _mm256_set1_ps(1.0)))
}
