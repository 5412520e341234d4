//! Small numerical helpers for the marching loops' per-sample work.
//!
//! `ceil` replaces `f32::ceil`, which on the baseline x86-64 target (no SSE4.1) is a call
//! into libm: a call in the marching loop costs more than the function, because every vector
//! register is caller-saved and the loop's live values are spilled around it. `1 − e^(−x)`
//! keeps libm's `expf` (an inlined table-and-polynomial `e^(−x)` measured no faster here: its
//! longer dependency chain cost what the call saved) and adds the series where
//! `1 − e^(−x)` would cancel.

/// `1 − e^(−x)` for `x ≥ 0` (`+∞` gives 1) without cancellation: its Taylor polynomial below
/// 1/64 (relative error < 1e-9), else `1 − e^(−x)` (relative error < 1e-5 at `x = 1/64`,
/// falling as `x` grows). Both are computed and one selected: which applies is unpredictable.
#[inline(always)]
pub fn one_minus_exp_neg(x: f32) -> f32 {
    let series = one_minus_exp_neg_series(x);
    let complement = 1.0 - (-x).exp();
    if x < 1.0 / 64.0 {
        series
    } else {
        complement
    }
}

/// The Taylor polynomial of `1 − e^(−x)` to degree 4, for `0 ≤ x < 1/64` (truncation error
/// < `x⁵/120`, relative < 1e-9 there): the branch of [`one_minus_exp_neg`] without cancellation.
#[inline(always)]
pub fn one_minus_exp_neg_series(x: f32) -> f32 {
    x * (1.0 - x * (0.5 - x * (1.0 / 6.0 - x * (1.0 / 24.0))))
}

/// The smallest integer `≥ v`: `f32::ceil` without the libm call. Below 2^22 in magnitude
/// (every ray's step count here) by rounding with [`ROUND`] and a correction; beyond it,
/// and for NaN and infinities, by `f32::ceil`.
#[inline(always)]
pub fn ceil(v: f32) -> f32 {
    if v.is_nan() || v.abs() >= 4_194_304.0 {
        return v.ceil();
    }
    let nearest = (v + ROUND) - ROUND;
    // An addition, not a branch: whether rounding went down is unpredictable.
    nearest + f32::from(u8::from(nearest < v))
}

/// `1.5 · 2^23`: adding and subtracting it rounds an `f32` of magnitude < 2^22 to the nearest
/// integer.
const ROUND: f32 = 12_582_912.0;

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
