//! One tuning (blocking, on the tokio blocking pool): a search ([`insitu_tuner::search`]) over
//! [`WorstCase`] of one [`StepOracle`] per characteristic step, which is the conservative
//! choice; a `StepOracle` answers a candidate from the persisted trials when it was measured
//! before, else asks the nodes holding the step for a trial (paced by the trial budget, given
//! up on timeout), combines the ranks' results and persists them. The winner is pushed as the
//! next decision when it differs from the P_M in force.

use crate::config::TrialConfig;
use crate::engine::Engine;
use crate::hub::TrialKind;
use crate::state::{Decision, SizeProbe, Trial};
use crate::trigger::{Cause, Trigger};
use insitu_core::backend::TimeSource;
use insitu_core::evaluate::Sizing;
use insitu_core::metrics::{pooled_psnr, Db};
use insitu_core::Precision;
use insitu_proto::pb;
use insitu_tuner::control::finer;
use insitu_tuner::live::{combine_ranks, WorstCase};
use insitu_tuner::search::{adaptive_search_near, grid_search, Outcome};
use insitu_tuner::study::{Oracle, StudyError};
use insitu_tuner::utility::Budgets;
use insitu_tuner::{Candidate, Measurement, ParamGrid};
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::sync::oneshot;
use tracing::{info, warn};

/// A trial result's σ and τ (trials report τ on the wall clock).
fn sizing(r: &pb::TrialResult) -> Sizing {
    Sizing {
        sigma_bytes: r.sigma_bytes,
        supersegments: r.supersegments,
        tau_secs: r.tau_secs,
        tau_source: TimeSource::WallClock,
        tau_compress_secs: r.tau_compress_secs,
    }
}

/// A trial result of `c` as a measurement (q pooled over its views, as the viz-node pools).
fn measurement(c: Candidate, r: &pb::TrialResult) -> Measurement {
    Measurement {
        r: r.resolution,
        gamma: r.gamma,
        precision: c.precision,
        sigma_paper_bytes: None,
        sizing: sizing(r),
        tau_render_secs: r.tau_render_secs,
        q_db: Db(pooled_psnr(&r.view_mse)),
        view_q_db: r.view_q_db.iter().map(|&q| Db(q)).collect(),
        ssim: r.ssim,
    }
}

/// Node seconds of trials allowed `elapsed` seconds after the start: the share of the wall
/// clock, or the burst where that is more (until the first tuning decides the whole burst,
/// then what that tuning used of it, `burst_used`). The burst is an advance on the share, not
/// an addition to it: trials after the first tuning wait until the share has caught up with
/// it, so over a run longer than `burst_used / share` the trials take the share, the first
/// tuning included.
fn allowance(t: &TrialConfig, burst_used: Option<f64>, elapsed: f64) -> f64 {
    let burst = burst_used.map_or(t.burst_secs, |b| b.clamp(0.0, t.burst_secs));
    burst.max(t.share * elapsed)
}

/// The measurements of one characteristic step, through the nodes that hold it.
struct StepOracle {
    engine: Arc<Engine>,
    step: u64,
    world_size: u32,
    generations: u64,
    generation_secs: f64,
    /// Trial seconds this tuning may run ahead of the allowance (see [`overdraft`]).
    overdraft: f64,
    /// Whether the target is a size budget alone: τ then decides nothing, and a full trial
    /// may score the VDI its size probe left ([`TrialKind::AfterProbe`]).
    size_alone: bool,
}

/// Trial seconds a tuning for `trigger` may run ahead of the allowance: a new character or a
/// steered utility starts its tuning at once (`trials.overdraft_secs`), and the trials after it
/// wait until the share has caught up. None for a broken budget (drift, which the corrections
/// keep up with meanwhile), a resumed or interrupted tuning, or the first (the burst is its).
fn overdraft(t: &TrialConfig, trigger: &Trigger) -> f64 {
    match trigger.cause {
        Cause::NewCharacter { .. }
        | Cause::SizeMiss { .. }
        | Cause::SizeJump { .. }
        | Cause::Steered { .. } => t.overdraft_secs,
        Cause::BrokeBudget { .. } | Cause::First | Cause::Lost { .. } | Cause::Resume => 0.0,
    }
}

impl StepOracle {
    /// Waits until the trials may spend more (the share of the wall clock, after the burst,
    /// which after the first tuning's decision is what that tuning used, and this tuning's
    /// overdraft).
    fn pace(&self) {
        let t = &self.engine.cfg.trials;
        while !self.engine.stopping.load(Ordering::Relaxed) {
            let (spent, burst_used) = {
                let c = self.engine.counters();
                (c.trial_secs, c.burst_used)
            };
            let allowed = allowance(t, burst_used, self.engine.started.elapsed().as_secs_f64())
                + self.overdraft;
            if spent <= allowed {
                return;
            }
            let wait = ((spent - allowed) / t.share).clamp(0.05, 1.0);
            std::thread::sleep(Duration::from_secs_f64(wait));
        }
    }

    fn fail(&self, step_lost: bool, problem: String) -> StudyError {
        self.engine.counters().trials_failed += 1;
        if step_lost {
            self.engine
                .lost
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .push(self.step);
        }
        StudyError::Invalid(problem)
    }
}

impl StepOracle {
    /// The kind of trial that measures σ and τ (`size_only`), or everything.
    fn kind(&self, size_only: bool) -> TrialKind {
        match (size_only, self.size_alone) {
            (true, _) => TrialKind::SizeProbe,
            (false, true) => TrialKind::AfterProbe,
            (false, false) => TrialKind::Full,
        }
    }

    /// Asks the nodes holding the step for a trial of `c` (paced by the trial budget) and
    /// waits for every rank's result; counts it and returns the results with their node
    /// seconds (the slowest rank's).
    fn run(
        &mut self,
        c: Candidate,
        size_only: bool,
    ) -> Result<(Vec<pb::TrialResult>, f64), StudyError> {
        let e = self.engine.clone();
        self.pace();
        let deadline = Instant::now() + Duration::from_secs_f64(e.cfg.trials.hold_wait_secs);
        let (id, rx) = loop {
            match e
                .hub
                .request_trial(self.step, self.world_size, c, self.kind(size_only))
            {
                Ok(x) => break x,
                Err(_) if Instant::now() < deadline => {
                    std::thread::sleep(Duration::from_millis(100))
                }
                Err(err) => return Err(self.fail(true, err.to_string())),
            }
        };
        let timeout = Duration::from_secs_f64(e.cfg.trials.timeout_secs);
        let kind = if size_only { "size probe" } else { "trial" };
        let what = format!("{kind} r = {}, γ = {} on step {}", c.r, c.gamma, self.step);
        // Polled (a trial takes milliseconds at least), so a runtime shutting down cannot
        // strand this thread in a timer.
        let mut rx = rx;
        let started = Instant::now();
        let results = loop {
            match rx.try_recv() {
                Ok(Ok(r)) => break r,
                Ok(Err(failure)) => {
                    return Err(
                        self.fail(failure.step_lost, format!("{what}: {}", failure.message))
                    );
                }
                Err(oneshot::error::TryRecvError::Closed) => {
                    return Err(self.fail(true, format!("{what}: abandoned")))
                }
                Err(oneshot::error::TryRecvError::Empty) => {}
            }
            if e.stopping.load(Ordering::Relaxed) {
                e.hub.abandon(id);
                return Err(StudyError::Invalid(format!(
                    "{what}: the tuner is stopping"
                )));
            }
            if e.superseded.load(Ordering::Relaxed) {
                e.hub.abandon(id);
                return Err(StudyError::Invalid(format!(
                    "{what}: a newer characteristic step overtook the tuning"
                )));
            }
            if started.elapsed() > timeout {
                e.hub.abandon(id);
                return Err(self.fail(
                    false,
                    format!("{what} timed out after {} s", timeout.as_secs_f64()),
                ));
            }
            std::thread::sleep(Duration::from_millis(5));
        };
        let secs = results.iter().map(|r| r.trial_secs).fold(0.0, f64::max);
        {
            let mut k = e.counters();
            k.trials_run += 1;
            k.size_probes += u64::from(size_only);
            k.trial_secs += secs;
            let cpu = results.iter().map(|r| r.trial_cpu_secs).sum::<f64>();
            k.trial_cpu_secs += cpu;
            if size_only {
                k.size_probe_cpu_secs += cpu;
            }
        }
        self.generations += 1;
        self.generation_secs += results.iter().map(|r| r.tau_secs).fold(0.0, f64::max);
        Ok((results, secs))
    }
}

impl Oracle for StepOracle {
    fn measure(&mut self, c: Candidate) -> Result<Measurement, StudyError> {
        let e = self.engine.clone();
        if let Some(t) = e.state().trial(self.step, c) {
            e.counters().trials_reused += 1;
            return Ok(t.measurement.clone());
        }
        let (results, secs) = self.run(c, false)?;
        let ms: Vec<Measurement> = results.iter().map(|r| measurement(c, r)).collect();
        let m = combine_ranks(&ms).map_err(|err| StudyError::Invalid(err.to_string()))?;
        let timed = m.sizing.tau_secs;
        let m = {
            let mut s = e.state();
            let m = s.add_trial(Trial {
                step: self.step,
                measurement: m,
                ranks: results.len() as u32,
                trial_secs: secs,
                run_by: e.process,
            });
            e.save(&s);
            m
        };
        info!(
            step = self.step,
            r = c.r,
            gamma = c.gamma,
            sigma = m.sizing.sigma_bytes,
            q_db = m.q(),
            tau = m.sizing.tau_secs,
            tau_timed = timed,
            secs,
            "trial"
        );
        Ok(m)
    }

    /// σ summed over the step's ranks and the slowest rank's τ, from a size probe on the
    /// nodes (generation and compression only) unless a probe or trial of `c` was run before.
    fn measure_sizing(&mut self, c: Candidate) -> Result<Sizing, StudyError> {
        let e = self.engine.clone();
        if let Some(sizing) = e.state().sizing(self.step, c) {
            e.counters().trials_reused += 1;
            return Ok(sizing);
        }
        let (results, secs) = self.run(c, true)?;
        let p = SizeProbe {
            step: self.step,
            candidate: c,
            sizing: Sizing::of_ranks(&results.iter().map(sizing).collect::<Vec<_>>()),
            trial_secs: secs,
            run_by: e.process,
            production: false,
        };
        info!(
            step = self.step,
            r = c.r,
            gamma = c.gamma,
            sigma = p.sizing.sigma_bytes,
            tau = p.sizing.tau_secs,
            secs = p.trial_secs,
            "size probe"
        );
        let mut s = e.state();
        s.size_probes.push(p.clone());
        e.save(&s);
        Ok(p.sizing)
    }

    fn generations(&self) -> u64 {
        self.generations
    }

    fn generation_secs(&self) -> f64 {
        self.generation_secs
    }
}

/// Runs one tuning over the characteristic steps (blocking: trials wait on the nodes).
/// Returns whether the search finished (a decision, P_M unchanged, or none feasible); `false`
/// when a trial failed it.
pub(crate) fn tune(engine: &Arc<Engine>, trigger: &Trigger) -> bool {
    let (steps, world_sizes, scene) = {
        let s = engine.state();
        (
            s.tracker.step_indices(),
            s.world_sizes.clone(),
            s.scene_version(),
        )
    };
    if steps.is_empty() {
        // Every characteristic step left with its node: nothing to tune on until a new one.
        info!(reason = %trigger, "no characteristic step left; the decision in force stays");
        return true;
    }
    let secs0 = engine.counters().trial_secs;
    let outcome = match search(engine, &steps, &world_sizes, trigger) {
        Ok(o) => o,
        Err(e) => {
            say_why_it_stopped(engine, &e);
            return false;
        }
    };
    let trial_secs = engine.counters().trial_secs - secs0;
    let Some(best) = outcome.best else {
        engine.counters().tunings_infeasible += 1;
        warn!(steps = ?steps, utility = %engine.utility_description(), "no candidate meets the budget on every characteristic step; the decision in force stays");
        return true;
    };
    if engine.state().scene_version() != scene {
        info!(steps = ?steps, "the scene was steered during the tuning: its outcome is dropped, the new scene is tuned for");
        return true;
    }
    decide(
        engine,
        trigger,
        steps,
        best,
        outcome.generations,
        trial_secs,
    );
    let mut c = engine.counters();
    c.burst_used = c.burst_used.or(Some(c.trial_secs));
    true
}

/// The search of the engine's grid (adaptive towards its target, from the `P_M` in force,
/// else the grid's plan) over the worst case of `steps` (with each step's world size, 1 when
/// unknown).
fn search(
    engine: &Arc<Engine>,
    steps: &[u64],
    world_sizes: &std::collections::BTreeMap<u64, u32>,
    trigger: &Trigger,
) -> Result<Outcome, StudyError> {
    let overdraft = overdraft(&engine.cfg.trials, trigger);
    let r = engine.resolved();
    let budgets = r.target.map_or(Budgets::NONE, |t| t.budgets());
    let size_alone = budgets.size_bytes.is_some() && budgets.time_secs.is_none();
    let oracles: Vec<Box<dyn Oracle>> = steps
        .iter()
        .map(|&step| {
            Box::new(StepOracle {
                engine: engine.clone(),
                step,
                world_size: world_sizes.get(&step).copied().unwrap_or(1),
                generations: 0,
                generation_secs: 0.0,
                overdraft,
                size_alone,
            }) as Box<dyn Oracle>
        })
        .collect();
    let mut oracle = WorstCase::new(oracles).with_budgets(budgets);
    // Size probes start at the P_M in force (before the first decision, the one the nodes
    // reported): the answer is most often near it. A re-tune searches at the precision the
    // last tuning chose (`grid_for`).
    let (current, tuned) = {
        let s = engine.state();
        (
            s.current().map(|d| d.candidate),
            s.tuned().map(|d| d.candidate.precision),
        )
    };
    let in_force = current.or(*engine.reported.lock().unwrap_or_else(|e| e.into_inner()));
    let grid = grid_for(&r.grid, tuned, &trigger.cause);
    match r.target {
        Some(t) => adaptive_search_near(&mut oracle, &grid, t, in_force),
        None => grid_search(&mut oracle, &grid, r.plan.as_ref()),
    }
}

/// The grid a tuning for `cause` searches: `grid` at the precision a tuning last chose
/// (`tuned`) for a re-tune, every precision of `grid` for the first tuning, one for a steered
/// utility (a new budget can make another precision the best buy), or while no tuning has
/// chosen one among them. A re-tune follows the data's character (its resolution and γ);
/// searching the other precisions again doubled its probes, so a re-tune for a new character
/// often did not finish within its share. The cost: where σ outgrows the budget, a coarser
/// precision may have become the better buy (docs/tuning.md, "Re-tunes at the chosen
/// precision").
fn grid_for(grid: &ParamGrid, tuned: Option<Precision>, cause: &Cause) -> ParamGrid {
    match tuned {
        Some(p)
            if !matches!(cause, Cause::First | Cause::Steered { .. })
                && grid.precisions.contains(&p) =>
        {
            grid.at(p)
        }
        _ => grid.clone(),
    }
}

/// Logs why a search ended without an outcome. A node that left (with a characteristic step)
/// or the tuner stopping ends a search as a matter of course: the tuning runs again on the
/// steps left (see `Engine::lost`); anything else is a failure worth a warning.
fn say_why_it_stopped(engine: &Engine, e: &StudyError) {
    let lost = !engine
        .lost
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .is_empty();
    if engine.stopping.load(Ordering::Relaxed) {
        info!(error = %e, "tuning stopped with the tuner; the decision in force stays");
    } else if engine.superseded.load(Ordering::Relaxed) {
        info!(error = %e, "tuning cut short for a newer characteristic step; it starts over on the new set, its trials kept");
    } else if lost {
        info!(error = %e, "tuning interrupted: a characteristic step left with its node; the decision in force stays");
    } else {
        warn!(error = %e, "tuning failed; the decision in force stays");
    }
}

/// Records `best` (found on `steps` with `trials` generations taking `trial_secs`): as a new
/// decision, persisted and pushed to every node, when it differs from the P_M in force;
/// else as a re-validation of the P_M in force on `steps`. The decision is chosen for the
/// step it will apply from: when the production steps measured so far forecast that `best`
/// would miss the budget there, the controller's coarser candidate is pushed instead, and
/// when they leave room for a finer γ at `best`'s resolution, that one (`best` kept as the
/// corrections' ceiling on r).
fn decide(
    engine: &Engine,
    trigger: &Trigger,
    steps: Vec<u64>,
    best: Measurement,
    trials: u64,
    trial_secs: f64,
) {
    let from_step = engine.decision_start();
    let surface = engine.state().surface(&steps);
    if matches!(
        trigger.cause,
        Cause::SizeMiss { .. } | Cause::SizeJump { .. }
    ) {
        // The data changed character at the trigger step, and this surface was measured on
        // it: production before it measured other data.
        engine.control().rebase(trigger.step);
    }
    // The P_M in force, where a tuning's answer may leave it (not the nodes' configured one
    // nor a provisional one, which no tuning chose, nor one of an earlier scene).
    let in_force = {
        let s = engine.state();
        s.current()
            .filter(|d| !d.steered && !d.provisional && d.scene_version == s.scene_version())
            .map(|d| d.candidate)
    };
    let plan = {
        let ctl = engine.control();
        let chosen = ctl.choose(&surface, best.candidate(), from_step);
        match (in_force, chosen) {
            // A tuning changes the P_M in force where the budget is at risk, where the change
            // is worth it as a correction's would be, or where its choice is finer (a
            // correction made on the old measurements may have gone far coarser than the new
            // ones need); else the P_M stays, under the new tuning's surface and ceiling.
            (Some(c), Some(p)) => ctl
                .correct(&surface, best.candidate(), c, from_step)
                .or_else(|| (finer(p.candidate, c) && p.feasible).then_some(p))
                .or_else(|| ctl.keep(&surface, c, from_step)),
            (_, chosen) => chosen,
        }
    }
    .filter(|p| p.candidate != best.candidate());
    let mut s = engine.state();
    let old = s
        .current()
        .map(|d| d.candidate)
        .or(*engine.reported.lock().unwrap_or_else(|e| e.into_inner()));
    let pushed = plan.map_or(best.candidate(), |p| p.candidate);
    // After a steered scene the decision in force predicts nothing: the tuning's is pushed.
    // After a correction, or a tuning on other steps, the tuning's decision is pushed too,
    // though the P_M is the same: the corrections that follow are made on its surface and
    // under its ceiling (a new version of the same r and γ changes no picture).
    if old == Some(pushed)
        && s.current()
            .is_some_and(|d| !d.steered && d.corrects.is_none() && d.characteristic_steps == steps)
    {
        info!(r = pushed.r, gamma = pushed.gamma, steps = ?steps, trials, "re-tuned: P_M unchanged");
        s.validated = steps;
        engine.save(&s);
        return;
    }
    let (predicted, reason, tuned, forecast) = match &plan {
        None => (best, trigger.to_string(), None, None),
        Some(p) => {
            let q = crate::engine::q_on(&s, &steps, p.candidate);
            let finer = p.candidate.r == best.r && p.candidate.gamma < best.gamma;
            let how = if Some(p.candidate) == in_force {
                "the P_M in force kept (the budget not at risk, the change not worth it)"
            } else if finer {
                "refined"
            } else {
                "coarsened"
            };
            let reason = format!(
                "{trigger}; tuned r {} γ {} (q {:.2} dB), {how} for production σ forecast {:.2}× the measured by step {}{}",
                best.r,
                best.gamma,
                best.q(),
                p.forecast.sigma,
                p.forecast.at,
                if p.feasible { "" } else { crate::engine::INFEASIBLE }
            );
            (
                crate::engine::planned(p, q),
                reason,
                Some(best.candidate()),
                Some(p.forecast.sigma),
            )
        }
    };
    let d = Decision {
        pm_version: s.next_version(),
        candidate: pushed,
        old,
        characteristic_steps: steps,
        predicted,
        reason,
        trigger_step: trigger.step,
        trials,
        trial_secs,
        utility_description: engine.utility_description(),
        from_step,
        corrects: None,
        tuned,
        forecast_ratio: forecast,
        scene_version: 0,
        steered: false,
        provisional: false,
    };
    s.validated = d.characteristic_steps.clone();
    drop(s);
    engine.publish(d);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::{Config, GridConfig};
    use crate::state::State;
    use insitu_tuner::control::Observation;

    /// An engine under `utility` over the grid r 64, 128 × γ 0.01, 0.02, 0.04, whose state
    /// holds a size probe of every candidate on step 0 with σ `sigma(candidate)` (τ 10 ms),
    /// with its state directory and its event channel (held for the engine's life).
    fn probed(
        utility: &str,
        sigma: impl Fn(Candidate) -> u64,
    ) -> (
        tempfile::TempDir,
        Arc<Engine>,
        tokio::sync::mpsc::Receiver<crate::engine::Event>,
    ) {
        let dir = tempfile::tempdir().unwrap();
        let cfg = Config {
            state_dir: dir.path().to_owned(),
            viz: Some("127.0.0.1:1".into()),
            utility: utility.into(),
            grid: GridConfig {
                r: "64,128".into(),
                gamma: "0.01,0.02,0.04".into(),
                precision: "f32".into(),
            },
            ..Default::default()
        };
        let resolved = cfg.resolve().unwrap();
        let mut state = State::with_step_zero();
        for candidate in resolved.grid.candidates() {
            state.size_probes.push(SizeProbe {
                step: 0,
                candidate,
                sizing: Sizing {
                    sigma_bytes: sigma(candidate),
                    tau_secs: 0.01,
                    ..Sizing::default()
                },
                trial_secs: 0.01,
                run_by: 0,
                production: false,
            });
        }
        let (engine, rx) = Engine::new(cfg, resolved, state, tune);
        (dir, engine, rx)
    }

    /// A budget no candidate meets ends the tuning without a decision, counted in the status
    /// (and warned of in the log); the trials were persisted ones, so no node is asked.
    #[test]
    fn a_tuning_without_a_feasible_candidate_keeps_the_p_m_and_says_so() {
        let (_dir, engine, _rx) = probed("size:1000", |c| 5000 + u64::from(c.r));
        let trigger = Trigger {
            step: 0,
            cause: Cause::First,
        };
        assert!(tune(&engine, &trigger), "the search finished");
        let s = engine.status();
        assert_eq!(
            (
                s.tunings_infeasible,
                s.decisions,
                s.pm_version,
                s.trials_run
            ),
            (1, 0, 0, 0),
            "{s:?}"
        );
        assert!(s.trials_reused > 0, "{s:?}");
        assert_eq!(
            engine.counters().burst_used,
            None,
            "no decision: the burst stays for the next tuning"
        );
    }

    /// A tuning's answer that the production steps since forecast no candidate can replace
    /// within the budget is pushed as the coarsest, and its reason says so, as a correction's
    /// does (its step is expected to overshoot).
    #[test]
    fn a_tuning_that_no_candidate_can_land_within_the_budget_says_so() {
        // σ on step 0: r² / 2 bytes at γ 0.01, halving with each doubling of γ (512–8192
        // bytes): every candidate within the 9500-byte plan.
        let sigma =
            |c: Candidate| (f64::from(c.r).powi(2) / 2.0 * 0.01 / f64::from(c.gamma)) as u64;
        let (_dir, engine, _rx) = probed("size:10000", sigma);
        let best = Candidate {
            r: 128,
            gamma: 0.01,
            precision: Default::default(),
        };
        // Production at the tuned candidate came out 100× its σ on step 0: even r 64 at
        // γ 0.04 is forecast at 51 kB.
        for step in 1..=2 {
            engine.control().observe(Observation {
                step,
                candidate: best,
                sigma_bytes: 100 * sigma(best),
                tau_secs: 0.01,
                planned_sigma_bytes: None,
            });
        }
        let trigger = Trigger {
            step: 0,
            cause: Cause::First,
        };
        let measured = Measurement {
            r: best.r,
            gamma: best.gamma,
            precision: Default::default(),
            sigma_paper_bytes: None,
            sizing: Sizing {
                sigma_bytes: sigma(best),
                tau_secs: 0.01,
                ..Sizing::default()
            },
            tau_render_secs: 0.0,
            q_db: Db(40.0),
            view_q_db: Vec::new(),
            ssim: None,
        };
        decide(&engine, &trigger, vec![0], measured, 1, 0.01);
        let d = engine
            .decision(1)
            .expect("the tuning's decision is published");
        assert_eq!((d.resolution, d.gamma), (64, 0.04), "{d:?}");
        assert!(
            d.reason.contains("coarsened") && d.reason.ends_with(crate::engine::INFEASIBLE),
            "{d:?}"
        );
    }

    /// A tuning for a new character (by histogram or by σ) or a steered utility may run ahead
    /// of the share by the overdraft; one for a broken budget, the first (which has the
    /// burst), a resumed one and one after a lost step may not.
    #[test]
    fn a_tuning_for_a_new_character_may_run_ahead_of_the_share() {
        let t = TrialConfig::default();
        let of = |cause| overdraft(&t, &Trigger { step: 1, cause });
        for cause in [
            Cause::NewCharacter {
                distance: 0.3,
                threshold: 0.15,
            },
            Cause::SizeMiss {
                sigma_bytes: 3,
                planned_bytes: 1.0,
                threshold: 1.5,
            },
            Cause::SizeJump {
                sigma_bytes: 3,
                than_step: 0,
                than_bytes: 1,
                threshold: 1.5,
            },
            Cause::Steered { what: "u".into() },
        ] {
            assert_eq!(of(cause), t.overdraft_secs);
        }
        for cause in [
            Cause::BrokeBudget { why: "σ".into() },
            Cause::First,
            Cause::Resume,
            Cause::Lost { steps: vec![1] },
        ] {
            assert_eq!(of(cause), 0.0);
        }
    }

    /// A re-tune searches the precision the last tuning chose; the first tuning, a steered
    /// one, and any before a tuning chose a precision of the grid search every precision.
    #[test]
    fn a_re_tune_searches_the_precision_a_tuning_chose() {
        let grid = ParamGrid::parse("64:512:64", "0.001:0.26:0.008")
            .unwrap()
            .with_precisions("6,8")
            .unwrap();
        let six = Some(Precision::Bits(6));
        let retunes = [
            Cause::NewCharacter {
                distance: 0.3,
                threshold: 0.15,
            },
            Cause::BrokeBudget { why: "σ".into() },
            Cause::Resume,
            Cause::Lost { steps: vec![1] },
        ];
        for cause in &retunes {
            let g = grid_for(&grid, six, cause);
            assert_eq!(g.precisions, vec![Precision::Bits(6)], "{cause:?}");
            assert_eq!(
                (g.rs.clone(), g.gammas.clone()),
                (grid.rs.clone(), grid.gammas.clone())
            );
            assert_eq!(grid_for(&grid, None, cause).precisions, grid.precisions);
            assert_eq!(
                grid_for(&grid, Some(Precision::Float32), cause).precisions,
                grid.precisions,
                "a precision off the grid"
            );
        }
        for cause in [Cause::First, Cause::Steered { what: "u".into() }] {
            assert_eq!(grid_for(&grid, six, &cause).precisions, grid.precisions);
        }
    }

    /// Before the first decision trials may use the whole burst; after it, what the first
    /// tuning used of it until the share has caught up, then the share alone.
    #[test]
    fn the_burst_is_an_advance_on_the_share() {
        let t = TrialConfig {
            share: 0.1,
            burst_secs: 15.0,
            ..TrialConfig::default()
        };
        assert_eq!(allowance(&t, None, 0.0), 15.0);
        assert_eq!(allowance(&t, None, 60.0), 15.0);
        assert!((allowance(&t, None, 200.0) - 20.0).abs() < 1e-12);
        assert_eq!(
            allowance(&t, Some(2.5), 10.0),
            2.5,
            "repaying the first tuning"
        );
        assert!((allowance(&t, Some(2.5), 60.0) - 6.0).abs() < 1e-12);
        assert_eq!(allowance(&t, Some(40.0), 60.0), 15.0);
        assert!((allowance(&t, Some(-1.0), 10.0) - 1.0).abs() < 1e-12);
    }
}
