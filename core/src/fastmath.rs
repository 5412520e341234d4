//! Small numerical helpers for the marching and merging loops' per-sample work.
//!
//! Neither calls libm: on the baseline x86-64 target (no SSE4.1, no FMA) `f32::ceil` and
//! `f32::exp` are calls, and a call in a hot loop costs more than the function, because every
//! vector register is caller-saved and the loop's live values are spilled around it.

/// `1 − e^(−x)` for `x ≥ 0` (`+∞` and NaN give 1), relative error < 1e-6, without
/// cancellation near 0 and without a libm call or a branch.
///
/// `e^(−x) = 2^y` with `y = −x·log₂e = n + f`, `n` an integer and `|f| ≤ 1/2`;
/// `2^f − 1 = f·q(f)` with `q` the Taylor polynomial of `(2^f − 1)/f` to degree 5
/// (truncation < 3e-7 of `q` at `|f| = 1/2`), so `1 − e^(−x) = (1 − 2^n) − 2^n·f·q(f)`: for
/// `n = 0` (x < 0.35) that is `−f·q(f)`, no subtraction of nearly equal numbers. `y` is
/// floored at −126 (`e^(−87)` < 2e-38, below the resolution of the result), which also maps
/// NaN to 1. The steps form a short dependency chain (one clamp, Estrin's scheme): VDI
/// generation's interrupt test waits on it.
#[inline(always)]
pub fn one_minus_exp_neg(x: f32) -> f32 {
    debug_assert!(
        x >= 0.0 || x.is_nan(),
        "one_minus_exp_neg({x}): x must be >= 0"
    );
    let y = (-x * std::f32::consts::LOG2_E).max(-126.0);
    let shifted = y + ROUND;
    let n = shifted - ROUND;
    let f = y - n;
    // 2^n from the integer in the low bits of `shifted` (n ≥ −126: a normal number).
    let n_bits = shifted.to_bits().wrapping_sub(ROUND.to_bits());
    let scale = f32::from_bits(n_bits.wrapping_add(127) << 23);
    let f2 = f * f;
    const C: [f32; 6] = EXP2_TAYLOR;
    let q = (C[0] + f * C[1]) + f2 * (C[2] + f * C[3]) + (f2 * f2) * (C[4] + f * C[5]);
    (1.0 - scale) - scale * (f * q)
}

/// `ln2^k / k!` for `k = 1…6`: the Taylor coefficients of `2^f − 1`.
pub(crate) const EXP2_TAYLOR: [f32; 6] = [
    std::f32::consts::LN_2,
    0.240_226_5,
    0.055_504_11,
    0.009_618_129,
    0.001_333_355_8,
    0.000_154_035_3,
];

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
pub(crate) const ROUND: f32 = 12_582_912.0;

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
        assert!(worst < 1e-6, "worst relative error {worst:e}");
        assert_eq!(one_minus_exp_neg(0.0), 0.0);
        assert_eq!(one_minus_exp_neg(f32::INFINITY), 1.0);
        assert_eq!(one_minus_exp_neg(f32::NAN), 1.0);
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
