//! Keeping a budget before any tuning: the resolution a step over its budget lowers `r` to,
//! from that step's σ and τ alone (docs/tuning.md, "Before the first decision"). A
//! generator-node that holds every rank of its world applies it itself; for a world spread
//! over several nodes the tuner does, as a provisional decision all of them apply from one
//! step.

use super::Budgets;

/// The part of the budget a corrected r aims at.
pub const HEADROOM: f64 = 0.9;

/// The exponent of r that σ and τ are taken to grow with. The rays grow as r², but
/// neighbouring lists compress together: on a 64³ blob σ fell 2.86× from r 256 to r 128
/// (r^1.52). The smaller exponent lowers r further, so the first correction lands within the
/// budget where σ grows as r², and below it where it grows slower.
pub const GROWTH: f64 = 1.5;

/// Corrected resolutions are multiples of this, pixels.
pub const R_STEP: u32 = 16;

/// The lowest resolution a correction goes to, pixels.
pub const MIN_R: u32 = 32;

/// The least excess over the budget the node corrects: a smaller miss is left to the tuner,
/// whose first decision follows. The node's correction knows nothing of q, and a step it makes
/// off the tuning's grid of r tells the tuner's forecast nothing (it leaves such steps out), so
/// on a growing series a corrected 1.2× miss took the first decision's view of the growth away.
pub const MIN_EXCESS: f64 = 1.25;

/// The resolution to make the next steps at after one of resolution `r` came out at `sigma`
/// bytes and `tau` seconds against `budget`: `None` when it missed the
/// budget by less than [`MIN_EXCESS`] (or r is at [`MIN_R`] already), else
/// `r · (HEADROOM / excess)^(1 / GROWTH)` rounded down to a multiple of [`R_STEP`], at least
/// [`MIN_R`], where the excess is the larger of σ and τ over their budgets.
pub fn lowered_resolution(r: u32, sigma: u64, tau: f64, budget: &Budgets) -> Option<u32> {
    let tau = if tau.is_finite() { tau } else { 0.0 };
    let (size, time) = budget.ratios(sigma as f64, tau);
    let excess = size.into_iter().chain(time).fold(0.0, f64::max);
    if excess < MIN_EXCESS {
        return None;
    }
    let scaled = f64::from(r) * (HEADROOM / excess).powf(1.0 / GROWTH);
    let next = ((scaled / f64::from(R_STEP)).floor() as u32 * R_STEP).max(MIN_R);
    (next < r).then_some(next)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Budgets as the wire carries them (0: none).
    fn budget(sigma_bytes: u64, tau_secs: f64) -> Budgets {
        Budgets::from_wire(sigma_bytes, tau_secs)
    }

    #[test]
    fn r_falls_as_sigma_would_grow_as_r_to_the_1_5_with_headroom() {
        // 4.2 MB against 1 MB: r 256 · (0.9 / 4.2)^(2/3) = 91.7 → 80.
        assert_eq!(
            lowered_resolution(256, 4_200_000, 0.1, &budget(1_000_000, 0.0)),
            Some(80)
        );
        // Growing as r^1.5 or as r², the next step lands within the budget.
        for growth in [GROWTH, 2.0] {
            let predicted = 4_200_000.0 * (80.0f64 / 256.0).powf(growth);
            assert!(predicted < 0.9 * 1_000_000.0, "{growth}: {predicted}");
        }
        // Within the budget: nothing to correct; no budget: nothing either.
        assert_eq!(
            lowered_resolution(256, 900_000, 0.1, &budget(1_000_000, 0.0)),
            None
        );
        assert_eq!(
            lowered_resolution(256, 9_000_000, 9.0, &budget(0, 0.0)),
            None
        );
        // A time budget: τ 2 s against 0.5 s → r 256 · (0.9 / 4)^(2/3) = 94.7 → 80.
        assert_eq!(lowered_resolution(256, 1, 2.0, &budget(0, 0.5)), Some(80));
        // Both: the larger excess wins (τ's 4× over σ's 2×).
        assert_eq!(
            lowered_resolution(256, 2_000_000, 2.0, &budget(1_000_000, 0.5)),
            Some(80)
        );
        // A small miss is the tuner's; from 1.25× the node steps down (r 256 · 0.806 = 206.4
        // → 192).
        assert_eq!(
            lowered_resolution(256, 1_200_000, 0.0, &budget(1_000_000, 0.0)),
            None
        );
        assert_eq!(
            lowered_resolution(256, 1_250_000, 0.0, &budget(1_000_000, 0.0)),
            Some(192)
        );
        // Never below the floor, and no change at it; NaN τ is no measurement.
        assert_eq!(
            lowered_resolution(64, 100_000_000, 0.0, &budget(1_000, 0.0)),
            Some(MIN_R)
        );
        assert_eq!(
            lowered_resolution(MIN_R, 100_000_000, 0.0, &budget(1_000, 0.0)),
            None
        );
        assert_eq!(lowered_resolution(256, 1, f64::NAN, &budget(0, 0.5)), None);
    }
}
