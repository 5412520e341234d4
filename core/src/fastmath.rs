//! Inline replacements for the libm functions that the marching loops call per sample.
//!
//! On the baseline x86-64 target `expf` and `ceilf` are calls into libm; a call in
//! the marching loop costs more than the function itself, because every vector register is
//! caller-saved and the loop's live values are spilled around it. These versions are a few
//! inlined floating-point operations with documented error bounds (tested against `std`).

use std::f64::consts::LN_2;

/// `1.5 · 2^52`: adding and subtracting it rounds an `f64` of magnitude < 2^51 to the nearest
/// integer without a call to `round`.
const ROUND: f64 = 6_755_399_441_055_744.0;

/// `2^(j/32)` for `j = 0..32`.
const EXP2_TABLE: [f64; 32] = [
    1.0,
    1.0218971486541166,
    1.0442737824274138,
    1.0671404006768237,
    1.0905077326652577,
    1.1143867425958924,
    1.1387886347566916,
    1.1637248587775775,
    1.189207115002721,
    1.215247359980469,
    1.241857812073484,
    1.2690509571917332,
    1.2968395546510096,
    1.3252366431597413,
    1.3542555469368927,
    1.383909881963832,
    std::f64::consts::SQRT_2,
    1.4451808069770467,
    1.4768261459394993,
    1.5091644275934228,
    1.5422108254079407,
    1.5759808451078865,
    1.6104903319492543,
    1.645755478153965,
    1.681792830507429,
    1.718619298122478,
    1.7562521603732995,
    1.7947090750031072,
    1.8340080864093424,
    1.8741676341103,
    1.9152065613971474,
    1.9571441241754002,
];

/// `e^(−x)` for `x ≥ 0` with relative error < 1e-7 (the `f32` rounding of a result computed
/// to ~1e-9 in `f64`); 0 for `x ≥ 87` (where the result would be subnormal), for `+∞` and for NaN.
///
/// In `f64`: `e^(−x) = 2^m · 2^(j/32) · e^r` with `32·m + j = round(−32·x/ln 2)` and
/// `|r| ≤ ln 2/64`; `2^(j/32)` from a table, `e^r` by its Taylor polynomial of degree 3
/// (truncation error < 6e-10), `2^m` from bits. The scheme of glibc's `expf`, inlined.
#[inline(always)]
pub fn exp_neg(x: f32) -> f32 {
    // Branch-free (the marching loops call it with unpredictable arguments): the value for
    // the clamped argument, then a select.
    let y = -f64::from(x.clamp(0.0, 87.0)) * (32.0 / LN_2);
    let shifted = y + ROUND;
    let n = shifted - ROUND;
    let r = (y - n) * (LN_2 / 32.0);
    // The low bits of `shifted` hold n in two's complement (no saturating float-to-int
    // conversion). k ∈ [−4017, 0], so m = ⌊k/32⌋ ∈ [−126, 0]: a normal biased exponent.
    let k = shifted.to_bits() as i32;
    let scale = f64::from_bits((((k >> 5) + 1023) as u64) << 52);
    let p = 1.0 + r + r * r * (0.5 + r * (1.0 / 6.0));
    let v = (EXP2_TABLE[(k & 31) as usize] * p * scale) as f32;
    if x < 87.0 {
        v
    } else {
        0.0
    }
}

/// `1 − e^(−x)` for `x ≥ 0` (`+∞` gives 1) without cancellation: its Taylor polynomial below
/// 1/64 (truncation error < `x⁵/120`, relative < 1e-9), else `1 − e^(−x)` by [`exp_neg`]
/// (relative error < 1e-5 at `x = 1/64`, falling as `x` grows).
#[inline(always)]
pub fn one_minus_exp_neg(x: f32) -> f32 {
    let series = one_minus_exp_neg_series(x);
    let complement = 1.0 - exp_neg(x);
    if x < 1.0 / 64.0 {
        series
    } else {
        complement
    }
}

/// The Taylor polynomial of `1 − e^(−x)` to degree 4, for `0 ≤ x < 1/64` (relative error
/// < 1e-9 there): the branch of [`one_minus_exp_neg`] without cancellation.
#[inline(always)]
pub fn one_minus_exp_neg_series(x: f32) -> f32 {
    x * (1.0 - x * (0.5 - x * (1.0 / 6.0 - x * (1.0 / 24.0))))
}

/// The smallest integer `≥ v`: `f32::ceil` without the libm call. Below 2^22 in magnitude
/// (every ray's step count here) by rounding with [`ROUND_F32`] and a correction; beyond it,
/// and for NaN and infinities, by `f32::ceil`.
#[inline(always)]
pub fn ceil(v: f32) -> f32 {
    if v.is_nan() || v.abs() >= 4_194_304.0 {
        return v.ceil();
    }
    let nearest = (v + ROUND_F32) - ROUND_F32;
    // An addition, not a branch: whether rounding went down is unpredictable.
    nearest + f32::from(u8::from(nearest < v))
}

/// `1.5 · 2^23`: adding and subtracting it rounds an `f32` of magnitude < 2^22 to the nearest
/// integer.
const ROUND_F32: f32 = 12_582_912.0;

#[cfg(test)]
mod tests {
    use super::*;

    /// Points over [0, 100] dense near 0 (where cancellation would show) and at the edges.
    fn sweep() -> impl Iterator<Item = f32> {
        (0..200_000)
            .map(|i| (i as f32 / 2_000.0).powi(2) / 1.0e2)
            .chain([0.0, 1.0 / 64.0, 1e-30, 1e-8, 86.9, 87.0, 88.0, 1e30])
    }

    #[test]
    fn exp_neg_matches_std_within_its_bound() {
        let mut worst = 0.0f64;
        for x in sweep() {
            let exact = (-f64::from(x)).exp();
            let got = f64::from(exp_neg(x));
            if x < 87.0 {
                worst = worst.max(((got - exact) / exact).abs());
            } else {
                assert_eq!(got, 0.0, "e^-{x}");
            }
        }
        assert!(worst < 1e-7, "worst relative error {worst:e}");
        assert_eq!(exp_neg(f32::INFINITY), 0.0);
        assert_eq!(exp_neg(f32::NAN), 0.0);
        assert_eq!(exp_neg(0.0), 1.0);
    }

    #[test]
    fn one_minus_exp_neg_has_no_cancellation() {
        let mut worst = 0.0f64;
        for x in sweep().filter(|&x| x > 0.0) {
            let exact = -(-f64::from(x)).exp_m1();
            let got = f64::from(one_minus_exp_neg(x));
            worst = worst.max(((got - exact) / exact).abs());
        }
        assert!(worst < 1e-5, "worst relative error {worst:e}");
        assert_eq!(one_minus_exp_neg(0.0), 0.0);
        assert_eq!(one_minus_exp_neg(f32::INFINITY), 1.0);
    }

    #[test]
    fn ceil_matches_std() {
        for v in [
            -3.5f32, -3.0, -0.5, -0.0, 0.0, 1e-7, 0.5, 1.0, 1.000_001, 2.5, 1e6, 123_456.7,
        ] {
            assert_eq!(ceil(v), v.ceil(), "ceil({v})");
        }
        for i in -100_000..100_000 {
            let v = i as f32 * 0.013_7;
            assert_eq!(ceil(v), v.ceil(), "ceil({v})");
        }
        for v in [
            4_194_303.5f32,
            4_194_304.5,
            -4_194_303.5,
            8_388_607.5,
            1e10,
            -1e10,
            f32::INFINITY,
            f32::NEG_INFINITY,
        ] {
            assert_eq!(ceil(v), v.ceil(), "ceil({v})");
        }
        assert!(ceil(f32::NAN).is_nan());
    }
}
