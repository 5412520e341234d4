//! Tests whose assertions read wall-clock timings: τ against a time budget, and the budget
//! kept on series replayed at a simulation's pace.
//!
//! They live in their own binary because `cargo test` runs test binaries one after another,
//! so nothing else of the workspace's tests runs beside them, and within it they run one at
//! a time ([`alone`]); `.config/nextest.toml` tells nextest the same. Beside the end-to-end
//! tests (each with its own daemons busy on 2 cores) a generation took three times as long:
//! in one CI run a 10 ms budget was missed by every candidate of the grid, and three busy
//! loops beside this test do the same.

#![allow(clippy::unwrap_used, clippy::expect_used)]

#[allow(dead_code)]
#[path = "../e2e/common.rs"]
mod common;
#[allow(dead_code)]
#[path = "../e2e/tuned.rs"]
mod tuned;
// The budget kept on series replayed at a simulation's pace: whether a tuning lands before the
// steps it is for depends on how fast the trials run, which a busy neighbour halves.
#[path = "../e2e/drift.rs"]
mod drift;

use std::sync::{Mutex, MutexGuard};
use tuned::{as_found, decision, decision_trial, state, tuned_ocean, tuner_status};

/// Held for the whole of each test here, so that no two run at once.
fn alone() -> MutexGuard<'static, ()> {
    static ONE: Mutex<()> = Mutex::new(());
    ONE.lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// (r, γ, τ in ms) of every persisted size probe, then of every trial, each in the order run.
fn timed(state: &serde_json::Value) -> Vec<(u64, f64, f64)> {
    let row = |c: &serde_json::Value, tau: &serde_json::Value| {
        let r = c["r"].as_u64().unwrap_or(0);
        let gamma = c["gamma"].as_f64().unwrap_or(f64::NAN);
        (r, gamma, tau.as_f64().unwrap_or(f64::NAN) * 1e3)
    };
    let list = |key: &str| state[key].as_array().map_or(&[][..], Vec::as_slice);
    // A probe's sizing is flattened into it; a trial's candidate and sizing are its measurement.
    list("size_probes")
        .iter()
        .map(|p| row(&p["candidate"], &p["tau_secs"]))
        .chain(
            list("trials")
                .iter()
                .map(|t| row(&t["measurement"], &t["measurement"]["tau_secs"])),
        )
        .collect()
}

/// A time budget is searched adaptively too: the decision arrives after a fraction of the
/// grid's trials (each r probed on each characteristic step, then a bisection over γ), and
/// meets the budget (less the headroom) on every step it was tuned on, as its persisted trials
/// timed it.
#[test]
fn a_tuned_ocean_replay_meets_a_time_budget_with_a_fraction_of_the_grid() {
    // In these debug-profile daemons, beside the replay, size probes of an ocean step took
    // 4–13 ms at r = 64 (30 ms for the very first), 7–20 ms at r = 128 and 11–20 ms at
    // r = 256 (47 ms for its first): the budget lies near the top of the grid (r 64–256),
    // with room for a CI machine twice as slow at r = 64 (10 ms, the earlier budget, was
    // within the noise of r = 64 here).
    const BUDGET_SECS: f64 = 0.02;
    let _alone = alone();
    let Some(o) = tuned_ocean(
        &format!("time:{BUDGET_SECS}"),
        &["--sample-every", "4", "--step-interval", "1.0"],
    ) else {
        return;
    };
    let (st, t) = (&o.st, &o.t);
    let s = tuner_status(&t.addr);
    assert!(
        s.pm_version >= 1,
        "the tuner pushed no P_M: {s:?}; (r, γ, τ) timed: {:?}",
        timed(&state(st))
    );
    let d = decision(&t.addr, s.pm_version).unwrap();
    let plan = BUDGET_SECS * 0.95;
    // Planned within the budget, unless the controller found no candidate that meets it
    // under the forecast (τ of the production steps ran slow on a busy machine: a correction,
    // or a tuning's answer chosen for when it lands) and says so, pushing the grid's coarsest.
    let infeasible = d
        .reason
        .ends_with("no candidate meets the plan under this forecast: the coarsest");
    assert!(d.predicted_tau_secs < plan || infeasible, "{d:?}");
    // The search's own answer met the budget in its trial on every step it was tuned on
    // (the decision in force may be a correction or coarsened, of a candidate never trialled).
    let state = state(st);
    if let Some(found) = as_found(&t.addr, s.pm_version) {
        for step in &found.characteristic_steps {
            let trial = decision_trial(&state, *step, &found);
            assert!(trial["measurement"]["tau_secs"].as_f64().unwrap() < plan);
        }
    }
    // The grid is 4 r × 17 γ per characteristic step. How the trials split between probes and
    // the bisection depends on how many r meet the budget on this machine: where all four do
    // (a Zen-5 VM), 4 probes and 4 bisection trials a step, an even split; so only
    // that probes ran on every characteristic step is asserted of them.
    let steps = s.characteristic_steps.len() as u64;
    let grid = 68 * steps;
    assert!(
        s.trials_run * 2 < grid && s.size_probes >= steps,
        "{} trials ({} size probes) for a grid of {grid}: {s:?}; (r, γ, τ) timed: {:?}",
        s.trials_run,
        s.size_probes,
        timed(&state)
    );
    eprintln!(
        "ocean, time:{BUDGET_SECS}: decision v{} r {} γ {} on steps {:?} (predicted τ {:.4} s, q {:.2} dB); {} trials of which {} size probes, grid {grid}",
        d.pm_version,
        d.resolution,
        d.gamma,
        d.characteristic_steps,
        d.predicted_tau_secs,
        d.predicted_q_db,
        s.trials_run,
        s.size_probes
    );
    o.stop();
}
