//! What the tuner persists (`tuner-state.json` in its state directory): the characteristic
//! steps with their histograms, every trial's measurement, and every decision with its version.
//! Written atomically (a temporary file in the same directory, fsync'd, renamed over the old
//! one, directory fsync'd) after each change, so a crash leaves the previous or the new state,
//! never half of one. A restarted tuner resumes from it: finished trials are not run again and
//! versions continue.

use crate::steer::{SceneState, SteerRecord};
use insitu_core::evaluate::Sizing;
use insitu_proto::pb;
use insitu_tuner::control::{Point, Surface};
use insitu_tuner::live::{Tracker, Verdict};
use insitu_tuner::series::BINS;
use insitu_tuner::{Candidate, Measurement};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// The state file's name.
pub const STATE_FILE: &str = "tuner-state.json";
const FORMAT: u32 = 1;

/// Errors reading or writing the state.
#[derive(Debug, thiserror::Error)]
pub enum StateError {
    /// Reading or writing failed.
    #[error("tuner state {path}: {source}")]
    Io {
        /// The file or directory.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// The file is not a state of this format.
    #[error("tuner state {path} is not valid (move it away to start afresh): {problem}")]
    Invalid {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        problem: String,
    },
}

/// One trial: a candidate measured on a characteristic step (combined over its ranks).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Trial {
    /// Step index.
    pub step: u64,
    /// σ, q, τ of the candidate on the step.
    pub measurement: Measurement,
    /// Ranks it was measured on.
    pub ranks: u32,
    /// Wall clock on the nodes (the slowest rank), seconds.
    pub trial_secs: f64,
    /// The tuner process that ran it (its start time, ms since the epoch).
    pub run_by: u64,
}

/// A size probe: σ (and τ) of a candidate on a characteristic step, without its q.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SizeProbe {
    /// Step index.
    pub step: u64,
    /// The candidate.
    pub candidate: Candidate,
    /// The step's ranks' [`Sizing::of_ranks`] (flattened: σ summed over them, τ of the
    /// slowest).
    #[serde(flatten)]
    pub sizing: Sizing,
    /// Wall clock on the nodes (the slowest rank), seconds.
    pub trial_secs: f64,
    /// The tuner process that ran it.
    pub run_by: u64,
    /// A production step's own measurement, not a trial's ([`State::add_production`]): its σ
    /// is what a trial would measure, its τ is not (see [`State::surface`]).
    #[serde(default)]
    pub production: bool,
}

/// A decision, as pushed.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Decision {
    /// Version (≥ 1).
    pub pm_version: u64,
    /// The P_M.
    pub candidate: Candidate,
    /// The P_M it replaced (for the first: the one the nodes reported, if any).
    pub old: Option<Candidate>,
    /// The steps it was tuned on.
    pub characteristic_steps: Vec<u64>,
    /// The worst case over those steps.
    pub predicted: Measurement,
    /// Why it was made.
    pub reason: String,
    /// The step that triggered it.
    pub trigger_step: u64,
    /// Trials run for it.
    pub trials: u64,
    /// Their seconds on the nodes.
    pub trial_secs: f64,
    /// The utility it optimised, in words (`utility` in state files written before).
    #[serde(alias = "utility")]
    pub utility_description: String,
    /// The first step made with it (see `PmDecision.from_step`); 0 in states written before.
    #[serde(default)]
    pub from_step: u64,
    /// For a correction between tunings (`insitu_tuner::control`): the version of the tuned
    /// decision it adjusts; `None` for a tuning's own decision.
    #[serde(default)]
    pub corrects: Option<u64>,
    /// For a tuning's decision that was adjusted for the forecast before it was pushed: the
    /// search's best on the characteristic steps (the finest `P_M` corrections may return to).
    #[serde(default)]
    pub tuned: Option<Candidate>,
    /// Production σ over the measured σ at the same `P_M`, forecast for `from_step`; `None`
    /// when no production step had been measured.
    #[serde(default)]
    pub forecast_ratio: Option<f64>,
    /// The steered scene version in force with it (0: the configured scene; set when it is
    /// published).
    #[serde(default)]
    pub scene_version: u64,
    /// A decision that carries a scene change (the `P_M` in force, unchanged): neither a
    /// tuning's nor a correction.
    #[serde(default)]
    pub steered: bool,
    /// A decision made before the first tuning's from a production step's σ and τ alone, for
    /// a world spread over several nodes ([`insitu_core::budget::lowered_resolution`]):
    /// neither a tuning's nor a correction of one, and nothing predicted.
    #[serde(default)]
    pub provisional: bool,
}

impl Decision {
    /// The finest `P_M` the controller may use under this tuning's decision: the search's
    /// best, whether or not it was pushed as found.
    pub fn ceiling(&self) -> Candidate {
        self.tuned.unwrap_or(self.candidate)
    }
}

/// Everything persisted.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct State {
    /// File format.
    pub format: u32,
    /// Characteristic steps.
    pub tracker: Tracker,
    /// Ranks per characteristic step.
    pub world_sizes: BTreeMap<u64, u32>,
    /// Every trial.
    pub trials: Vec<Trial>,
    /// Every size probe.
    #[serde(default)]
    pub size_probes: Vec<SizeProbe>,
    /// Every decision, oldest first.
    pub decisions: Vec<Decision>,
    /// The highest version any node has reported (a node may be ahead of a lost state).
    pub highest_seen: u64,
    /// The characteristic steps the decision in force was last found best on (by the tuning
    /// that made it, or a later one that kept it). While they are the tracker's steps, the
    /// production steps are watched against the budget; when they differ, a tuning is due.
    #[serde(default)]
    pub validated: Vec<u64>,
    /// Every steered scene, oldest first (what each decision's `scene_version` stands for;
    /// the last is in force).
    #[serde(default)]
    pub scenes: Vec<SceneState>,
    /// Every steering change, oldest first.
    #[serde(default)]
    pub steering: Vec<SteerRecord>,
    /// The utility as last steered, as a spec (`size:1MB`; `None`: the configured one).
    #[serde(default)]
    pub utility: Option<String>,
}

impl State {
    /// For tests: a state whose one characteristic step is step 0 (threshold 0.15, at most 4).
    #[cfg(test)]
    pub(crate) fn with_step_zero() -> Self {
        let mut state = Self::new(Tracker::new(0.15, 4));
        let mut h = [0.0; BINS];
        h[3] = 1.0;
        assert!(matches!(state.tracker.observe(0, &h), Verdict::New { .. }));
        state
    }

    /// An empty state.
    pub fn new(tracker: Tracker) -> Self {
        Self {
            format: FORMAT,
            tracker,
            world_sizes: BTreeMap::new(),
            trials: Vec::new(),
            size_probes: Vec::new(),
            decisions: Vec::new(),
            highest_seen: 0,
            validated: Vec::new(),
            scenes: Vec::new(),
            steering: Vec::new(),
            utility: None,
        }
    }

    /// The steered scene in force (version 0, nothing set: never steered).
    pub fn scene(&self) -> SceneState {
        self.scenes.last().cloned().unwrap_or_default()
    }

    /// The version of the steered scene in force (0: never steered).
    pub fn scene_version(&self) -> u64 {
        self.scenes.last().map_or(0, |s| s.version)
    }

    /// A decision as pushed, with the steered scene it carries.
    pub fn message(&self, d: &Decision) -> pb::PmDecision {
        let mut m = decision_pb(d);
        m.scene = self
            .scenes
            .iter()
            .find(|s| s.version == d.scene_version)
            .map(SceneState::to_pb);
        m
    }

    /// The decision in force.
    pub fn current(&self) -> Option<&Decision> {
        self.decisions.last()
    }

    /// The newest decision a tuning made (corrections between tunings, steering and
    /// provisional decisions left out).
    pub fn tuned(&self) -> Option<&Decision> {
        self.decisions
            .iter()
            .rev()
            .find(|d| d.corrects.is_none() && !d.steered && !d.provisional)
    }

    /// The candidate a decision version stands for (`None`: unknown or version 0).
    pub fn candidate_of(&self, version: u64) -> Option<Candidate> {
        self.decisions
            .iter()
            .rev()
            .find(|d| d.pm_version == version)
            .map(|d| d.candidate)
    }

    /// The version for the next decision.
    pub fn next_version(&self) -> u64 {
        self.current()
            .map_or(0, |d| d.pm_version)
            .max(self.highest_seen)
            + 1
    }

    /// Classifies `step` (with `world_size` ranks) by its histogram (see [`Tracker::observe`]);
    /// the ranks of the characteristic steps are kept beside them.
    pub fn observe(&mut self, step: u64, h: &[f64; BINS], world_size: u32) -> Verdict {
        let v = self.tracker.observe(step, h);
        if let Verdict::New { evicted, .. } = &v {
            self.characteristic_added(step, world_size, *evicted);
        }
        v
    }

    /// Makes `step` characteristic whatever its histogram (see [`Tracker::force`]); returns
    /// the step evicted, if any.
    pub fn force(&mut self, step: u64, h: &[f64; BINS], world_size: u32) -> Option<(u64, f64)> {
        let evicted = self.tracker.force(step, h);
        self.characteristic_added(step, world_size, evicted);
        evicted
    }

    /// Forgets characteristic step `step`; whether it was one.
    pub fn forget(&mut self, step: u64) -> bool {
        self.world_sizes.remove(&step);
        self.tracker.remove(step)
    }

    fn characteristic_added(&mut self, step: u64, world_size: u32, evicted: Option<(u64, f64)>) {
        self.world_sizes.insert(step, world_size);
        if let Some((gone, _)) = evicted {
            self.world_sizes.remove(&gone);
        }
    }

    /// A finished trial of `c` on `step`.
    pub fn trial(&self, step: u64, c: Candidate) -> Option<&Trial> {
        self.trials
            .iter()
            .find(|t| t.step == step && t.measurement.candidate().key() == c.key())
    }

    /// Records a trial and returns its measurement as recorded: with τ lowered to that of an
    /// earlier size probe of the same candidate on the same step where the probe was faster.
    /// The simulation's and production's work on a node only ever add to a timing, and the
    /// adaptive search must not drop a candidate whose probe met a time budget because the
    /// second timing of the same generation was slowed down.
    pub fn add_trial(&mut self, mut t: Trial) -> Measurement {
        if let Some(p) = self.probe(t.step, t.measurement.candidate()) {
            let tau = &mut t.measurement.sizing.tau_secs;
            *tau = tau.min(p.sizing.tau_secs);
        }
        let m = t.measurement.clone();
        self.trials.push(t);
        m
    }

    /// σ and τ of `c` on `step` from a size probe or a trial, if either was run.
    pub fn sizing(&self, step: u64, c: Candidate) -> Option<Sizing> {
        self.probe(step, c)
            .map(|p| p.sizing)
            .or_else(|| self.trial(step, c).map(|t| t.measurement.sizing))
    }

    /// A production step made with `c`, kept as a size probe of `c` on `step` (the step's own
    /// measurement: the search then need not probe the `P_M` in force on it) unless `c` was
    /// measured on it before.
    pub fn add_production(&mut self, step: u64, c: Candidate, sizing: Sizing, run_by: u64) {
        if self.sizing(step, c).is_none() {
            self.size_probes.push(SizeProbe {
                step,
                candidate: c,
                sizing,
                trial_secs: 0.0,
                run_by,
                production: true,
            });
        }
    }

    /// The σ/τ surface measured on `steps` (size probes and trials): each candidate's worst
    /// case over the steps, from the candidates measured on all of them (on any of them when
    /// none was); with q where the trials scored a candidate on every step (its worst).
    ///
    /// τ comes from the trials alone. A trial is timed on a node that has just run another
    /// (one after another, its threads awake and its caches warm); a production step after
    /// the node waited for the step (at 64³ on a 2-core VM, a generation after 0.5–1 s idle
    /// takes 1.6–2.2× as long as the same one back to back). Mixed into one surface, a
    /// production τ at one resolution beside trials' τ at the others would make the others
    /// look faster than production will find them; kept out, the controller's τ ratio
    /// (production τ over the trials' τ at its `P_M`) carries that difference to every
    /// candidate, the first decision included.
    ///
    /// Each precision is a layer of its own (σ at another precision is another quantity, and
    /// a correction keeps the precision of the decision it corrects), and "measured on all of
    /// the steps" is asked of each precision apart.
    pub fn surface(&self, steps: &[u64]) -> Surface {
        // By candidate (r, γ's bits): the candidate, its worst σ and τ, the steps measured.
        type Worst = (Candidate, f64, f64, Vec<u64>);
        let mut by: BTreeMap<(u32, u32, u32), Worst> = BTreeMap::new();
        let measured = self
            .size_probes
            .iter()
            .map(|p| {
                let sizing = if p.production {
                    Sizing {
                        tau_secs: 0.0,
                        ..p.sizing
                    }
                } else {
                    p.sizing
                };
                (p.step, p.candidate, sizing)
            })
            .chain(
                self.trials
                    .iter()
                    .map(|t| (t.step, t.measurement.candidate(), t.measurement.sizing)),
            );
        for (step, c, sizing) in measured.filter(|m| steps.contains(&m.0)) {
            let e = by.entry(c.key()).or_insert((c, 0.0, 0.0, Vec::new()));
            e.1 = e.1.max(sizing.sigma_bytes as f64);
            e.2 = e.2.max(sizing.tau_secs);
            if !e.3.contains(&step) {
                e.3.push(step);
            }
        }
        // The precisions with a candidate measured on every step.
        let whole: Vec<u32> = by
            .values()
            .filter(|e| e.3.len() == steps.len())
            .map(|e| e.0.precision.bits())
            .collect();
        // q: the worst over the steps of the candidates the trials scored on every step.
        // By candidate: the candidate, its worst q, the steps scored.
        type Scored = (Candidate, f64, Vec<u64>);
        let mut scored: BTreeMap<(u32, u32, u32), Scored> = BTreeMap::new();
        for t in self.trials.iter().filter(|t| steps.contains(&t.step)) {
            let c = t.measurement.candidate();
            let e = scored
                .entry(c.key())
                .or_insert((c, f64::INFINITY, Vec::new()));
            e.1 = e.1.min(t.measurement.q());
            if !e.2.contains(&t.step) {
                e.2.push(t.step);
            }
        }
        Surface::new(
            by.into_values()
                .filter(|e| !whole.contains(&e.0.precision.bits()) || e.3.len() == steps.len())
                .map(|(candidate, sigma_bytes, tau_secs, _)| Point {
                    candidate,
                    sigma_bytes,
                    tau_secs,
                }),
        )
        .with_q(
            scored
                .into_values()
                .filter(|e| e.2.len() == steps.len())
                .map(|e| (e.0, e.1)),
        )
    }

    /// A size probe of `c` on `step`, if one was run.
    fn probe(&self, step: u64, c: Candidate) -> Option<&SizeProbe> {
        self.size_probes
            .iter()
            .find(|p| p.step == step && p.candidate.key() == c.key())
    }

    /// Loads `dir/tuner-state.json`; `None` when there is none.
    ///
    /// # Errors
    /// [`StateError`] when it cannot be read or parsed (it is left alone).
    pub fn load(dir: &Path) -> Result<Option<Self>, StateError> {
        let path = dir.join(STATE_FILE);
        let text = match std::fs::read_to_string(&path) {
            Ok(t) => t,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(source) => return Err(StateError::Io { path, source }),
        };
        let state: Self = serde_json::from_str(&text).map_err(|e| StateError::Invalid {
            path: path.clone(),
            problem: e.to_string(),
        })?;
        if state.format != FORMAT {
            return Err(StateError::Invalid {
                path,
                problem: format!("format {} (this tuner reads {FORMAT})", state.format),
            });
        }
        Ok(Some(state))
    }

    /// Writes `dir/tuner-state.json` atomically.
    ///
    /// # Errors
    /// [`StateError::Io`]; the previous file is then untouched.
    pub fn save(&self, dir: &Path) -> Result<(), StateError> {
        let io = |path: &Path| {
            let path = path.to_owned();
            move |source| StateError::Io { path, source }
        };
        std::fs::create_dir_all(dir).map_err(io(dir))?;
        let bytes = serde_json::to_vec(self).map_err(|e| StateError::Invalid {
            path: dir.join(STATE_FILE),
            problem: e.to_string(),
        })?;
        let path = dir.join(STATE_FILE);
        insitu_core::file::write_atomic(&path, &bytes, insitu_core::file::Durability::PowerLoss)
            .map_err(io(&path))
    }
}

/// A decision as a wire message, without its scene (see [`State::message`]).
fn decision_pb(d: &Decision) -> pb::PmDecision {
    pb::PmDecision {
        pm_version: d.pm_version,
        resolution: d.candidate.r,
        gamma: d.candidate.gamma,
        characteristic_steps: d.characteristic_steps.clone(),
        predicted_sigma_bytes: d.predicted.sizing.sigma_bytes,
        predicted_q_db: d.predicted.q(),
        predicted_tau_secs: d.predicted.sizing.tau_secs,
        reason: d.reason.clone(),
        trials: d.trials,
        trial_secs: d.trial_secs,
        old_resolution: d.old.map_or(0, |c| c.r),
        old_gamma: d.old.map_or(0.0, |c| c.gamma),
        trigger_step: d.trigger_step,
        utility_description: d.utility_description.clone(),
        from_step: d.from_step,
        corrects_version: d.corrects.unwrap_or(0),
        forecast_ratio: d.forecast_ratio.unwrap_or(0.0),
        scene: None,
        steered: d.steered,
        provisional: d.provisional,
        precision_bits: Some(d.candidate.precision.bits()),
        old_precision_bits: d.old.map(|c| c.precision.bits()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use insitu_core::metrics::Db;

    #[test]
    fn state_round_trips_and_a_bad_file_is_refused_not_replaced() {
        let dir = tempfile::tempdir().unwrap();
        assert!(State::load(dir.path()).unwrap().is_none());
        let mut s = State::new(Tracker::new(0.1, 4));
        let m = Measurement {
            r: 64,
            gamma: 0.01,
            precision: Default::default(),
            sigma_paper_bytes: None,
            sizing: Sizing {
                sigma_bytes: 10,
                supersegments: 1,
                tau_secs: 0.1,
                ..Sizing::default()
            },
            tau_render_secs: 0.0,
            q_db: Db(f64::INFINITY),
            view_q_db: vec![Db(40.0)],
            ssim: None,
        };
        s.trials.push(Trial {
            step: 3,
            measurement: m.clone(),
            ranks: 1,
            trial_secs: 0.2,
            run_by: 1,
        });
        s.decisions.push(Decision {
            pm_version: 4,
            candidate: m.candidate(),
            old: None,
            characteristic_steps: vec![3],
            predicted: m.clone(),
            reason: "test".into(),
            trigger_step: 3,
            trials: 1,
            trial_secs: 0.2,
            utility_description: "max q with σ < 1.0 MB".into(),
            from_step: 4,
            corrects: None,
            tuned: None,
            forecast_ratio: None,
            scene_version: 0,
            steered: false,
            provisional: false,
        });
        s.highest_seen = 4;
        assert_eq!(s.next_version(), 5);
        s.save(dir.path()).unwrap();
        let back = State::load(dir.path()).unwrap().unwrap();
        assert_eq!(back, s);
        // A state file written when a decision's utility description was keyed `utility`.
        let text = std::fs::read_to_string(dir.path().join(STATE_FILE)).unwrap();
        assert_eq!(text.matches("\"utility_description\"").count(), 1);
        let old = text.replace("\"utility_description\"", "\"utility\"");
        std::fs::write(dir.path().join(STATE_FILE), old).unwrap();
        assert_eq!(State::load(dir.path()).unwrap().unwrap(), s);
        s.save(dir.path()).unwrap();
        assert!(back.trial(3, m.candidate()).is_some());
        assert!(back.trial(4, m.candidate()).is_none());
        // Only the state file is left behind (no temporaries).
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
        std::fs::write(
            dir.path().join(STATE_FILE),
            b"{\"format\": 1, \"trials\": [",
        )
        .unwrap();
        let e = State::load(dir.path()).unwrap_err().to_string();
        assert!(e.contains(STATE_FILE) && e.contains("not valid"), "{e}");
    }

    /// A production step gives the surface its σ but not its τ, so the controller sees how much
    /// slower production is than the trials (here 1.5×) and a decision allows for it: the
    /// tuned r 448, whose trials' τ fits a 10 ms budget, forecasts 12 ms in production, and the
    /// finest resolution that fits is chosen instead: r 384 (τ from r 448's by r², 8.8 ms).
    #[test]
    fn production_tau_reaches_the_plan_as_a_ratio_not_through_the_surface() {
        use insitu_tuner::control::{Controller, Observation};
        use insitu_tuner::utility::Budgets;
        use insitu_tuner::ParamGrid;
        let mut s = State::new(Tracker::new(0.1, 4));
        let c = |r, gamma| Candidate {
            r,
            gamma,
            precision: Default::default(),
        };
        let probe = |candidate: Candidate, sigma_bytes: u64, tau_secs: f64, production| SizeProbe {
            step: 0,
            candidate,
            sizing: Sizing {
                sigma_bytes,
                tau_secs,
                ..Sizing::default()
            },
            trial_secs: if production { 0.0 } else { tau_secs },
            run_by: 1,
            production,
        };
        // Trials at r 256, 320, 448 (τ ∝ r² from 3 ms); the run's first P_M made step 0 in
        // 4.5 ms at r 256.
        for (r, tau) in [(256, 0.003), (320, 0.0047), (448, 0.008)] {
            s.size_probes
                .push(probe(c(r, 0.001), u64::from(r) * 1000, tau, false));
        }
        let first = c(256, 0.013);
        s.add_production(
            0,
            first,
            Sizing {
                sigma_bytes: 100_000,
                tau_secs: 0.0045,
                ..Sizing::default()
            },
            1,
        );
        let surface = s.surface(&[0]);
        assert!((surface.tau(c(256, 0.013)).unwrap() - 0.003).abs() < 1e-12);
        assert!((surface.sigma(first).unwrap() - 100_000.0).abs() < 1e-6);
        let grid = ParamGrid {
            rs: vec![256, 320, 384, 448],
            gammas: vec![0.001, 0.013],
            precisions: vec![Default::default()],
        };
        let mut ctl = Controller::new(Budgets::time(0.01), 0.05, grid);
        ctl.observe(Observation {
            step: 0,
            candidate: first,
            sigma_bytes: 100_000,
            tau_secs: 0.0045,
            planned_sigma_bytes: None,
        });
        let plan = ctl.choose(&surface, c(448, 0.001), 2).unwrap();
        assert!(
            (plan.forecast.tau - 1.5).abs() < 1e-9,
            "{:?}",
            plan.forecast
        );
        assert_eq!(plan.candidate, c(384, 0.001), "{plan:?}");
        assert!(plan.feasible && plan.tau_secs <= 0.0095, "{plan:?}");
    }

    /// A trial's τ is the faster of its own timing and an earlier size probe's of the same
    /// candidate on the same step; σ and q are the trial's, other steps and candidates unused.
    #[test]
    fn a_trial_keeps_the_faster_of_its_timing_and_its_probes() {
        let mut s = State::new(Tracker::new(0.1, 4));
        let sizing = |tau_secs| Sizing {
            sigma_bytes: 10,
            tau_secs,
            ..Sizing::default()
        };
        let c = Candidate {
            r: 64,
            gamma: 0.01,
            precision: Default::default(),
        };
        let probe = |step, candidate, tau| SizeProbe {
            step,
            candidate,
            sizing: sizing(tau),
            trial_secs: tau,
            run_by: 1,
            production: false,
        };
        s.size_probes.push(probe(3, c, 0.012));
        s.size_probes.push(probe(4, c, 0.001));
        s.size_probes.push(probe(
            3,
            Candidate {
                r: 64,
                gamma: 0.02,
                precision: Default::default(),
            },
            0.001,
        ));
        let trial = |step, tau| Trial {
            step,
            measurement: Measurement {
                r: c.r,
                gamma: c.gamma,
                sizing: sizing(tau),
                tau_render_secs: 0.0,
                q_db: Db(40.0),
                view_q_db: vec![Db(40.0)],
                ssim: None,
                precision: Default::default(),
                sigma_paper_bytes: None,
            },
            ranks: 1,
            trial_secs: tau,
            run_by: 1,
        };
        assert_eq!(s.add_trial(trial(3, 0.034)).sizing.tau_secs, 0.012);
        assert_eq!(s.add_trial(trial(3, 0.005)).sizing.tau_secs, 0.005);
        assert_eq!(s.add_trial(trial(5, 0.034)).sizing.tau_secs, 0.034);
        assert_eq!(s.trials.len(), 3);
        assert_eq!(s.trial(3, c).unwrap().measurement.sizing.tau_secs, 0.012);
        assert_eq!(s.trial(3, c).unwrap().measurement.q(), 40.0);
    }
}
