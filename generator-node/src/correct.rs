//! Before the tuner's first decision the node keeps the tuner's budget itself: a simulation
//! that pushes fast, or a run shorter than the first tuning, would otherwise make every step at
//! the configured `P_M` (4× over a 1 MB budget at r 256 on a 64³ field). The tuner sends its
//! budget when the node attaches ([`pb::NodeBudget`]); after each whole step made while no
//! decision is in force (σ summed over its ranks, τ of the slowest), a σ or τ [`MIN_EXCESS`]
//! over the budget or more lowers r for the steps no rank of which has begun, as if both grew
//! as r^1.5 ([`GROWTH`]), with 10 % headroom, on multiples of 16 pixels. r only goes down here: spending headroom is
//! the tuner's, which measures q. The tuner's first decision takes over; the node's summary
//! counts the steps made under such a correction.
//!
//! Only a node that holds every rank of its world sees whole steps
//! ([`crate::layout::Layouts::whole_world_here`]); a world spread over several nodes is left
//! to the tuner, since its ranks must share one `P_M` to be composed.

use crate::config::Generation;
use insitu_core::budget::Budgets;
use insitu_proto::pb;
use std::sync::{Mutex, RwLock};
use tracing::info;

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
pub fn corrected_resolution(r: u32, sigma: u64, tau: f64, budget: &Budgets) -> Option<u32> {
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

/// Steps whose ranks are still being made, kept at most (older ones are forgotten).
const MAX_PENDING: usize = 64;

#[derive(Debug, Default)]
struct State {
    /// The tuner's budgets and its utility as it describes it.
    budget: Option<(Budgets, String)>,
    /// Steps of several ranks being made: ranks done, σ summed, τ of the slowest, r.
    pending: std::collections::BTreeMap<u64, (u32, u64, f64, u32)>,
    /// Steps made under a correction: how many, the first and the last.
    steps: u64,
    first: Option<u64>,
    last: u64,
    /// The resolution the node last corrected to, and from which step.
    corrected: Option<(u32, u64)>,
}

/// The node's own correction of `P_M` before the tuner's first decision.
#[derive(Debug, Default)]
pub struct Correction(Mutex<State>);

impl Correction {
    fn state(&self) -> std::sync::MutexGuard<'_, State> {
        self.0.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// The tuner's budget, as it sent it.
    pub fn set_budget(&self, budget: pb::NodeBudget) {
        info!(sigma_bytes = budget.sigma_bytes, tau_secs = budget.tau_secs, utility = %budget.utility_description, "the tuner's budget, kept by the node until its first decision");
        let budgets = Budgets::from_wire(budget.sigma_bytes, budget.tau_secs);
        self.state().budget = Some((budgets, budget.utility_description));
    }

    /// After a rank whose VDI has header `h` was made under settings of decision
    /// `pm_version` (0: none yet), on a node that holds every rank of its world
    /// (`whole_world`): once its step's ranks are all made, counts the step if it was made
    /// under a correction, and when it broke the budget lowers r in `generation` for the steps
    /// from `begun` (the first no rank of which has begun) on (logged). Returns whether it
    /// changed the settings (the caller records them).
    pub fn after_step(
        &self,
        generation: &RwLock<Generation>,
        begun: u64,
        h: &pb::VdiHeader,
        pm_version: u64,
        whole_world: bool,
    ) -> bool {
        let mut s = self.state();
        if pm_version != 0 || !whole_world {
            return false;
        }
        let (sigma, tau, r) = if h.world_size <= 1 {
            (h.total_bytes, h.tau_secs, h.resolution)
        } else {
            let e = s.pending.entry(h.step).or_insert((0, 0, 0.0, h.resolution));
            e.0 += 1;
            e.1 += h.total_bytes;
            e.2 = e.2.max(h.tau_secs);
            if e.0 < h.world_size {
                while s.pending.len() > MAX_PENDING {
                    s.pending.pop_first();
                }
                return false;
            }
            match s.pending.remove(&h.step) {
                Some((_, sigma, tau, r)) => (sigma, tau, r),
                None => return false,
            }
        };
        if s.corrected.is_some_and(|(_, from)| h.step >= from) {
            s.steps += 1;
            s.first.get_or_insert(h.step);
            s.last = s.last.max(h.step);
        }
        let Some((budget, utility)) = &s.budget else {
            return false;
        };
        let Some(next) = corrected_resolution(r, sigma, tau, budget) else {
            return false;
        };
        let mut g = generation.write().unwrap_or_else(|e| e.into_inner());
        if g.pm_version != 0 || g.params.resolution <= next {
            return false;
        }
        info!(
            step = h.step,
            sigma_bytes = sigma,
            tau_secs = tau,
            budget = %utility,
            r,
            next_r = next,
            from_step = begun,
            "no decision from the tuner yet: the node lowers r to keep the budget"
        );
        // From the first step no rank of which has begun: a step's ranks share one P_M.
        let mut lowered = g.clone();
        lowered.params.resolution = next;
        crate::settings::switch_at(&g, &mut lowered, begun, begun);
        *g = lowered;
        drop(g);
        s.corrected = Some((next, s.corrected.map_or(begun, |(_, from)| from.min(begun))));
        true
    }

    /// For the node's summary: the steps made under the node's correction, or `None`.
    pub fn summary(&self) -> Option<String> {
        let s = self.state();
        let (r, _) = s.corrected?;
        let first = s.first?;
        Some(format!(
            "{} step(s) ({first}–{}) made at r lowered by the node (last r {r}) to keep the tuner's budget before its first decision",
            s.steps, s.last
        ))
    }
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
            corrected_resolution(256, 4_200_000, 0.1, &budget(1_000_000, 0.0)),
            Some(80)
        );
        // Growing as r^1.5 or as r², the next step lands within the budget.
        for growth in [GROWTH, 2.0] {
            let predicted = 4_200_000.0 * (80.0f64 / 256.0).powf(growth);
            assert!(predicted < 0.9 * 1_000_000.0, "{growth}: {predicted}");
        }
        // Within the budget: nothing to correct; no budget: nothing either.
        assert_eq!(
            corrected_resolution(256, 900_000, 0.1, &budget(1_000_000, 0.0)),
            None
        );
        assert_eq!(
            corrected_resolution(256, 9_000_000, 9.0, &budget(0, 0.0)),
            None
        );
        // A time budget: τ 2 s against 0.5 s → r 256 · (0.9 / 4)^(2/3) = 94.7 → 80.
        assert_eq!(corrected_resolution(256, 1, 2.0, &budget(0, 0.5)), Some(80));
        // Both: the larger excess wins (τ's 4× over σ's 2×).
        assert_eq!(
            corrected_resolution(256, 2_000_000, 2.0, &budget(1_000_000, 0.5)),
            Some(80)
        );
        // A small miss is the tuner's; from 1.25× the node steps down (r 256 · 0.806 = 206.4
        // → 192).
        assert_eq!(
            corrected_resolution(256, 1_200_000, 0.0, &budget(1_000_000, 0.0)),
            None
        );
        assert_eq!(
            corrected_resolution(256, 1_250_000, 0.0, &budget(1_000_000, 0.0)),
            Some(192)
        );
        // Never below the floor, and no change at it; NaN τ is no measurement.
        assert_eq!(
            corrected_resolution(64, 100_000_000, 0.0, &budget(1_000, 0.0)),
            Some(MIN_R)
        );
        assert_eq!(
            corrected_resolution(MIN_R, 100_000_000, 0.0, &budget(1_000, 0.0)),
            None
        );
        assert_eq!(
            corrected_resolution(256, 1, f64::NAN, &budget(0, 0.5)),
            None
        );
    }
}
