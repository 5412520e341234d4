//! Before the tuner's first decision the node keeps the tuner's budget itself: a simulation
//! that pushes fast, or a run shorter than the first tuning, would otherwise make every step at
//! the configured `P_M` (4× over a 1 MB budget at r 256 on a 64³ field). The tuner sends its
//! budget when the node attaches ([`pb::NodeBudget`]); after each whole step made while no
//! decision is in force (σ summed over its ranks, τ of the slowest), a σ or τ
//! [`insitu_core::budget::MIN_EXCESS`] over the budget or more lowers r for the steps no rank
//! of which has begun ([`insitu_core::budget::lowered_resolution`]). r only goes down here:
//! spending headroom is the tuner's, which measures q. The tuner's first decision takes over;
//! the node's summary counts the steps made under such a correction.
//!
//! Only a node that holds every rank of its world sees whole steps
//! ([`crate::layout::Layouts::whole_world_here`]). For a world spread over several nodes the
//! tuner, which sees every rank's summary, lowers r by the same rule in a provisional decision
//! (`PmDecision.provisional`) that all of them apply from one step, so the ranks share one
//! `P_M`; the summary counts the steps made under those too.

use crate::config::Generation;
use insitu_core::budget::{lowered_resolution, Budgets};
use insitu_proto::pb;
use std::collections::BTreeSet;
use std::sync::{Mutex, RwLock};
use tracing::info;

/// Steps whose ranks are still being made, kept at most (older ones are forgotten).
const MAX_PENDING: usize = 64;

#[derive(Debug, Default)]
struct State {
    /// The tuner's budgets and its utility as it describes it.
    budget: Option<(Budgets, String)>,
    /// Steps of several ranks being made: ranks done, σ summed, τ of the slowest, r.
    pending: std::collections::BTreeMap<u64, (u32, u64, f64, u32)>,
    /// Steps made under the node's own correction.
    by_node: Lowered,
    /// The step the node's correction applies from.
    corrected_from: Option<u64>,
    /// Steps made under the tuner's provisional decisions.
    by_tuner: Lowered,
    /// The versions of the tuner's provisional decisions.
    provisional: BTreeSet<u64>,
}

/// Steps made at a lowered r: how many, the first and the last, and the last r.
#[derive(Debug, Default)]
struct Lowered {
    steps: u64,
    first: Option<u64>,
    last: Option<u64>,
    r: u32,
}

impl Lowered {
    /// Counts `step` (made at `r`) once, however many of its ranks the node made: ranks arrive
    /// in step order but may interleave with the next step's, so a step is counted when it is
    /// newer than the last counted.
    fn count(&mut self, step: u64, r: u32) {
        if self.last.is_some_and(|l| step <= l) {
            return;
        }
        self.steps += 1;
        self.first.get_or_insert(step);
        self.last = Some(step);
        self.r = r;
    }

    /// "N step(s) (a–b) made at r lowered by `by` (last r R)", or `None` when none was.
    fn describe(&self, by: &str) -> Option<String> {
        let (first, last) = (self.first?, self.last?);
        Some(format!(
            "{} step(s) ({first}–{last}) made at r lowered by {by} (last r {})",
            self.steps, self.r
        ))
    }
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

    /// The tuner's size budget for a whole step, bytes, once it has sent one with a size term.
    pub fn size_budget(&self) -> Option<u64> {
        self.state().budget.as_ref().and_then(|(b, _)| b.size_bytes)
    }

    /// The tuner's provisional decision `d` (made before its first tuning, for a world spread
    /// over several nodes): the steps made under it are counted.
    pub fn provisional(&self, d: &pb::PmDecision) {
        let mut s = self.state();
        s.provisional.insert(d.pm_version);
        while s.provisional.len() > MAX_PENDING {
            s.provisional.pop_first();
        }
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
        if s.provisional.contains(&pm_version) {
            s.by_tuner.count(h.step, h.resolution);
        }
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
        if s.corrected_from.is_some_and(|from| h.step >= from) {
            s.by_node.count(h.step, r);
        }
        let Some((budget, utility)) = &s.budget else {
            return false;
        };
        let Some(next) = lowered_resolution(r, sigma, tau, budget) else {
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
        s.corrected_from = Some(s.corrected_from.map_or(begun, |from| from.min(begun)));
        true
    }

    /// For the node's summary: the steps made at an r lowered before the tuner's first
    /// decision, by the node or by the tuner, or `None`.
    pub fn summary(&self) -> Option<String> {
        let s = self.state();
        let node = s.by_node.describe("the node");
        let tuner = s.by_tuner.describe("the tuner's provisional decisions");
        let both: Vec<String> = node.into_iter().chain(tuner).collect();
        (!both.is_empty()).then(|| {
            format!(
                "{} to keep the tuner's budget before its first decision",
                both.join(", ")
            )
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn header(step: u64, rank: u32, world_size: u32, r: u32, sigma: u64) -> pb::VdiHeader {
        pb::VdiHeader {
            step,
            rank,
            world_size,
            resolution: r,
            total_bytes: sigma,
            tau_secs: 0.01,
            ..Default::default()
        }
    }

    fn budget(c: &Correction) {
        c.set_budget(pb::NodeBudget {
            sigma_bytes: 20_000,
            tau_secs: 0.0,
            utility_description: "max q with σ < 20.0 kB".into(),
        });
    }

    #[test]
    fn a_whole_world_is_lowered_by_the_node_and_its_steps_counted() {
        let c = Correction::default();
        budget(&c);
        let g = RwLock::new(crate::config::Config::default().generation().unwrap());
        let r0 = g.read().unwrap().params.resolution;
        // One rank of two is not a step; the second makes it whole: 63 kB against 20 kB.
        assert!(!c.after_step(&g, 1, &header(0, 0, 2, r0, 40_000), 0, true));
        assert!(c.after_step(&g, 1, &header(0, 1, 2, r0, 23_000), 0, true));
        let r = g.read().unwrap().params.resolution;
        assert_eq!(
            Some(r),
            lowered_resolution(r0, 63_000, 0.01, &Budgets::size(20_000))
        );
        // Steps from 1 on, made at the lowered r within the budget, are counted once each.
        for step in 1..4 {
            for rank in 0..2 {
                assert!(!c.after_step(&g, step + 1, &header(step, rank, 2, r, 9_000), 0, true));
            }
        }
        let s = c.summary().unwrap();
        assert!(
            s.starts_with(&format!(
                "3 step(s) (1–3) made at r lowered by the node (last r {r})"
            )),
            "{s}"
        );
        // A world not all here is left alone.
        let c = Correction::default();
        budget(&c);
        assert!(!c.after_step(&g, 1, &header(0, 0, 1, r, 90_000), 0, false));
        assert_eq!(c.summary(), None);
    }

    #[test]
    fn steps_under_the_tuner_s_provisional_decisions_are_counted_once_each() {
        let c = Correction::default();
        budget(&c);
        let g = RwLock::new(crate::config::Config::default().generation().unwrap());
        let before = g.read().unwrap().params;
        c.provisional(&pb::PmDecision {
            pm_version: 1,
            resolution: 96,
            provisional: true,
            ..Default::default()
        });
        // This node holds rank 1 of each step, then both ranks of step 4; version 2 is no
        // provisional decision, so step 5 is not counted.
        for (step, rank, v) in [(2, 1, 1), (3, 1, 1), (4, 0, 1), (4, 1, 1), (5, 1, 2)] {
            assert!(!c.after_step(&g, step + 1, &header(step, rank, 2, 96, 90_000), v, false));
        }
        assert_eq!(
            g.read().unwrap().params,
            before,
            "the node changes nothing itself"
        );
        assert_eq!(
            c.summary().as_deref(),
            Some("3 step(s) (2–4) made at r lowered by the tuner's provisional decisions (last r 96) to keep the tuner's budget before its first decision")
        );
    }
}
