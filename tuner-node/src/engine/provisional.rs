//! Before the first tuning's decision, for a world whose ranks push to several
//! generator-nodes: a production step's σ or τ far over the budget lowers r in a provisional
//! decision that every node applies from one step (docs/tuning.md, "Before the first
//! decision"). A node that holds a whole world does this itself
//! (generator-node/src/correct.rs); for a spread world none can, since no node sees a step's σ
//! summed over its ranks, and the ranks must share one `P_M` to compose.

use super::*;
use insitu_core::budget::{lowered_resolution, GROWTH, HEADROOM};

impl Loop {
    /// After production step `step` (all its ranks in, `p`): when no tuning has decided yet,
    /// the step's ranks came from several nodes with the `P_M` in force, and its σ (summed over
    /// the ranks) or τ (the slowest rank's) is [`insitu_core::budget::MIN_EXCESS`] over the
    /// budget or more, publishes a provisional decision at the lowered r
    /// ([`lowered_resolution`]), γ and precision kept. Returns whether it did.
    pub(super) fn provisional(&mut self, step: u64, p: &Pending) -> bool {
        if p.nodes.len() < 2 {
            return false;
        }
        let e = self.engine.clone();
        let (in_force, pm_version) = {
            let s = e.state();
            if s.tuned().is_some() {
                return false;
            }
            (s.current().map_or(0, |d| d.pm_version), s.next_version())
        };
        if p.pm_version != in_force {
            return false;
        }
        let budgets = e.resolved().budgets();
        let Some(r) = lowered_resolution(p.candidate.r, p.sigma_bytes, p.tau_secs, &budgets) else {
            return false;
        };
        let candidate = Candidate { r, ..p.candidate };
        let utility_description = e.utility_description();
        let reason = format!(
            "no tuning has decided yet: step {step} ({} ranks on {} nodes) made σ {} B and τ {:.4} s at r {} under {utility_description}; r lowered to {r} for the steps after it, as if σ and τ grew as r^{GROWTH}, aiming at {:.0} % of the budget",
            p.ranks,
            p.nodes.len(),
            p.sigma_bytes,
            p.tau_secs,
            p.candidate.r,
            HEADROOM * 100.0
        );
        e.publish(Decision {
            pm_version,
            candidate,
            old: Some(p.candidate),
            characteristic_steps: Vec::new(),
            predicted: unmeasured(candidate),
            reason,
            trigger_step: step,
            trials: 0,
            trial_secs: 0.0,
            utility_description,
            from_step: e.spread_start(),
            corrects: None,
            tuned: None,
            forecast_ratio: None,
            scene_version: 0,
            steered: false,
            provisional: true,
        });
        true
    }
}
