//! The tuner's decisions: which steps are characteristic, when to tune, and what to push.
//!
//! One task ([`Engine::run`]) takes the events in order (step summaries, quality reports,
//! nodes coming and going). A step is classified when the summaries of all its ranks are in
//! (their 64-bin counts add up to the step's histogram). A new characteristic step, or a
//! production step that broke the budget, marks the set *dirty*; when no tuning runs, a
//! dirty set starts one on the blocking pool (the `tune` module): the conservative choice over
//! the characteristic steps, from trials on the nodes or, when measured before, from the state.
//! A tuning that failed without losing a step is tried again after the trial timeout.

use crate::config::{Config, Resolved};
use crate::hub::Hub;
use crate::state::{Decision, State};
use crate::steer::{Domain, Standing, SteerRecord, StepHistogram};
use crate::trigger::{Cause, Trigger};
use insitu_core::metrics::{mse_from_psnr, psnr_from_mse};
use insitu_proto::pb;
use insitu_proto::pb::tuner_message::Msg as Down;
use insitu_tuner::control::{Controller, Observation, Plan};
use insitu_tuner::live::{normalise, Verdict};
use insitu_tuner::series::BINS;
use insitu_tuner::utility::UtilitySpec;
use insitu_tuner::Candidate;
use std::collections::{BTreeMap, VecDeque};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tokio::sync::{broadcast, mpsc, oneshot};
use tokio::task::JoinHandle;
use tracing::{debug, info, warn};

/// Steps kept waiting for their last rank or their q before they are given up.
const STALE_STEPS: u64 = 32;

/// Events queued for the engine at most; beyond, the streams that bring them wait (gRPC flow
/// control then holds the nodes and the viz-node back) instead of memory growing.
pub const EVENT_BACKLOG: usize = 1024;

/// What the engine is told.
#[derive(Debug)]
pub enum Event {
    /// A node's first message.
    Hello(u64, pb::NodeHello),
    /// A checked step summary from a connection.
    Summary(u64, pb::StepSummary),
    /// A quality report from the viz-node.
    Report(pb::QualityReport),
    /// A node's stream ended.
    Gone(u64),
    /// A steering request and where its answer goes (docs/steering.md).
    Steer(
        pb::SteerRequest,
        oneshot::Sender<Result<pb::SteerReply, tonic::Status>>,
    ),
}

/// Counters (for the status).
#[derive(Clone, Debug, Default)]
pub struct Counters {
    /// Summaries received.
    pub summaries: u64,
    /// Trials run by this process.
    pub trials_run: u64,
    /// Of `trials_run`, size probes (σ and τ only: no rendering or scoring).
    pub size_probes: u64,
    /// Trials answered from the state.
    pub trials_reused: u64,
    /// Trials that failed, timed out or lost their node.
    pub trials_failed: u64,
    /// Node seconds of the trials run.
    pub trial_secs: f64,
    /// `trial_secs` when the first tuning decided: from then on the burst is what that
    /// tuning used of it, the rest lapses (see `TrialConfig::burst_secs`).
    pub burst_used: Option<f64>,
    /// CPU seconds of the trials run, as the nodes counted them, summed over ranks.
    pub trial_cpu_secs: f64,
    /// Of `trial_cpu_secs`, the size probes'.
    pub size_probe_cpu_secs: f64,
    /// Tunings started.
    pub retunes: u64,
    /// Decisions made by this process (tunings' and corrections).
    pub decisions: u64,
    /// Of `decisions`, corrections between tunings (closed-loop control).
    pub corrections: u64,
    /// Tunings cut short for a newer characteristic step.
    pub tunings_superseded: u64,
    /// Quality reports received (from every viz-node shard watched).
    pub quality_reports: u64,
    /// Tunings that found no candidate within the budget on every characteristic step.
    pub tunings_infeasible: u64,
    /// Whether a tuning runs.
    pub tuning: bool,
}

/// The engine's shared part (the service, the search and the engine task use it).
pub struct Engine {
    pub(crate) cfg: Config,
    /// The configuration resolved with the utility in force (steering may replace it).
    resolved: std::sync::RwLock<Arc<Resolved>>,
    /// Persisted state.
    pub state: Mutex<State>,
    /// Connected nodes.
    pub hub: Arc<Hub>,
    pub(crate) counters: Mutex<Counters>,
    pub(crate) decisions: broadcast::Sender<pb::PmDecision>,
    pub(crate) started: Instant,
    pub(crate) process: u64,
    pub(crate) lost: Mutex<Vec<u64>>,
    /// The P_M the nodes last reported in their hello (what the first decision replaces).
    pub(crate) reported: Mutex<Option<Candidate>>,
    /// Set on shutdown: a tuning in progress gives up at its next trial.
    pub stopping: AtomicBool,
    /// The newest step summarised by any node and the stride of the step indices.
    pub(crate) progress: Mutex<Progress>,
    /// The closed-loop controller: production steps in, corrections and forecasts out.
    pub(crate) control: Mutex<Controller>,
    /// Set when a newer characteristic step overtakes the running tuning: it gives up at its
    /// next trial, and the tuning over the newer set starts (its trials so far are kept).
    pub(crate) superseded: AtomicBool,
    /// The domain as the newest summary describes it (what steering is checked against).
    domain: Mutex<Domain>,
    events: mpsc::Sender<Event>,
    /// What runs one tuning ([`crate::tune::tune`] in the daemon; the node wires it in).
    tuning: TuningFn,
}

/// One tuning for a trigger, blocking; returns whether the search finished (`false` when a
/// trial failed it).
pub type TuningFn = fn(&Arc<Engine>, &Trigger) -> bool;

/// How far the nodes have come: the newest step summarised by any node, the stride of the step
/// indices (a simulation may push every n-th step), and for the newest step the first step
/// index its nodes had not begun (`StepSummary.begun`) and how many nodes summarised it.
#[derive(Debug, Default)]
pub(crate) struct Progress {
    newest: Option<u64>,
    stride: u64,
    begun: u64,
    nodes: Vec<u64>,
}

impl Progress {
    /// Records a summarised step from connection `conn`, whose node had not begun step
    /// `begun` (0: unknown); returns the newest step.
    fn saw(&mut self, step: u64, begun: u64, conn: u64) -> u64 {
        match self.newest {
            Some(n) if step < n => return n,
            Some(n) if step == n => {}
            n => {
                if let Some(n) = n {
                    self.stride = step - n;
                }
                self.newest = Some(step);
                self.begun = 0;
                self.nodes.clear();
            }
        }
        self.begun = self.begun.max(begun);
        if !self.nodes.contains(&conn) {
            self.nodes.push(conn);
        }
        step
    }

    /// The first step a decision made now applies from (`PmDecision.from_step`): the first
    /// step on the stride past the newest step summarised and past every step its nodes had
    /// begun, one stride further when several nodes summarised it (one may begin the next
    /// step before the decision reaches it; a node applies a decision only from a step it
    /// has not begun, so all must agree on one no node can have begun). Without `begun`
    /// (older nodes) two strides past the newest step. 0 before any summary.
    pub(crate) fn decision_start(&self) -> u64 {
        let Some(n) = self.newest else { return 0 };
        let stride = self.stride.max(1);
        let strides = if self.begun == 0 {
            2
        } else {
            let past = self.begun.saturating_sub(n).max(1).div_ceil(stride);
            past + u64::from(self.nodes.len() > 1)
        };
        n.saturating_add(stride.saturating_mul(strides))
    }
}

impl Engine {
    /// An engine over `state`; events go to the returned receiver (for [`Engine::run`]).
    pub fn new(
        cfg: Config,
        resolved: Resolved,
        state: State,
        tuning: TuningFn,
    ) -> (Arc<Self>, mpsc::Receiver<Event>) {
        let (events, rx) = mpsc::channel(EVENT_BACKLOG);
        let process = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_millis() as u64);
        // A utility steered before a restart stays in force.
        let resolved = match state.utility.as_deref().map(|u| resolve_with(&cfg, u)) {
            Some(Ok(r)) => r,
            Some(Err(e)) => {
                warn!(error = %e, "the steered utility in the state no longer resolves; using the configured one");
                resolved
            }
            None => resolved,
        };
        (
            Arc::new(Self {
                state: Mutex::new(state),
                hub: Arc::new(Hub::default()),
                counters: Mutex::new(Counters::default()),
                decisions: broadcast::channel(64).0,
                started: Instant::now(),
                process,
                lost: Mutex::new(Vec::new()),
                reported: Mutex::new(None),
                stopping: AtomicBool::new(false),
                progress: Mutex::new(Progress::default()),
                control: Mutex::new(Controller::new(
                    resolved.budgets,
                    cfg.headroom,
                    resolved.grid.clone(),
                )),
                superseded: AtomicBool::new(false),
                domain: Mutex::new(Domain::default()),
                events,
                tuning,
                cfg,
                resolved: std::sync::RwLock::new(Arc::new(resolved)),
            }),
            rx,
        )
    }

    /// Sends an event to the engine task, waiting while [`EVENT_BACKLOG`] are queued (the
    /// engine loop itself never waits on a sender: it answers nodes with `try_send`, so the
    /// wait cannot close a cycle).
    pub async fn event(&self, e: Event) {
        let _ = self.events.send(e).await;
    }

    pub(crate) fn state(&self) -> std::sync::MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    pub(crate) fn counters(&self) -> std::sync::MutexGuard<'_, Counters> {
        self.counters.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// The configuration resolved with the utility in force.
    pub(crate) fn resolved(&self) -> Arc<Resolved> {
        self.resolved
            .read()
            .unwrap_or_else(|e| e.into_inner())
            .clone()
    }

    /// The controller between tunings afresh for the utility in force (after steering: what
    /// it learnt was for another budget or scene).
    fn restart_control(&self) {
        let r = self.resolved();
        *self.control() = Controller::new(r.budgets, self.cfg.headroom, r.grid.clone());
    }

    pub(crate) fn domain(&self) -> std::sync::MutexGuard<'_, Domain> {
        self.domain.lock().unwrap_or_else(|e| e.into_inner())
    }

    pub(crate) fn control(&self) -> std::sync::MutexGuard<'_, Controller> {
        self.control.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// The first step a decision made now applies from (see [`Progress::decision_start`]).
    pub(crate) fn decision_start(&self) -> u64 {
        self.progress
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .decision_start()
    }

    /// Records `d` as the decision in force (persisted), counts it and pushes it to every
    /// node and subscriber.
    pub(crate) fn publish(&self, mut d: Decision) {
        let m = {
            let mut s = self.state();
            d.scene_version = s.scene_version();
            s.decisions.push(d.clone());
            self.save(&s);
            s.message(&d)
        };
        {
            let mut c = self.counters();
            c.decisions += 1;
            c.corrections += u64::from(d.corrects.is_some());
        }
        info!(scene_version = d.scene_version, pm_version = d.pm_version, from_step = d.from_step, r = d.candidate.r, gamma = d.candidate.gamma, old = ?d.old, steps = ?d.characteristic_steps, sigma = d.predicted.sizing.sigma_bytes, q_db = d.predicted.q(), tau = d.predicted.sizing.tau_secs, forecast = ?d.forecast_ratio, trials = d.trials, trial_secs = d.trial_secs, reason = %d.reason, "new P_M");
        self.hub.broadcast(&Down::Decision(m.clone()));
        let _ = self.decisions.send(m);
    }

    /// Every new decision.
    pub fn subscribe(&self) -> broadcast::Receiver<pb::PmDecision> {
        self.decisions.subscribe()
    }

    /// The utility's description.
    pub fn utility(&self) -> String {
        self.resolved().utility.describe()
    }

    /// The budget the nodes keep until the first decision ([`pb::NodeBudget`]).
    pub fn node_budget(&self) -> pb::NodeBudget {
        let (sigma, tau) = self.resolved().budgets;
        pb::NodeBudget {
            sigma_bytes: sigma.unwrap_or(0),
            tau_secs: tau.unwrap_or(0.0),
            utility: self.utility(),
        }
    }

    pub(crate) fn save(&self, s: &State) {
        if let Err(e) = s.save(&self.cfg.state_dir) {
            warn!(error = %e, "could not persist the tuner state");
        }
    }

    /// The status message.
    pub fn status(&self) -> pb::TunerStatus {
        let s = self.state();
        let c = self.counters();
        let cur = s.current();
        let budgets = self.resolved().budgets;
        let spec = s.utility.as_deref().unwrap_or(&self.cfg.utility);
        let (fields, hist) = {
            let d = self.domain();
            (d.fields.clone(), d.histogram.clone().unwrap_or_default())
        };
        pb::TunerStatus {
            pm_version: cur.map_or(0, |d| d.pm_version),
            resolution: cur.map_or(0, |d| d.candidate.r),
            gamma: cur.map_or(0.0, |d| d.candidate.gamma),
            characteristic_steps: s.tracker.step_indices(),
            nodes_connected: self.hub.nodes() as u32,
            summaries: c.summaries,
            trials_run: c.trials_run,
            trials_reused: c.trials_reused,
            trials_failed: c.trials_failed,
            trial_secs: c.trial_secs,
            retunes: c.retunes,
            decisions: c.decisions,
            utility: self.utility(),
            tuning: c.tuning,
            size_probes: c.size_probes,
            tunings_infeasible: c.tunings_infeasible,
            corrections: c.corrections,
            tunings_superseded: c.tunings_superseded,
            quality_reports: c.quality_reports,
            trial_cpu_secs: c.trial_cpu_secs,
            size_probe_cpu_secs: c.size_probe_cpu_secs,
            sigma_target_bytes: budgets.0.unwrap_or(0),
            tau_target_secs: budgets.1.unwrap_or(0.0),
            q_target_db: match UtilitySpec::parse(spec) {
                Ok(UtilitySpec::Quality(q)) => q,
                _ => 0.0,
            },
            scene: Some(s.scene().to_pb()),
            steering: s.steering.iter().map(SteerRecord::to_pb).collect(),
            fields,
            histogram_step: hist.step,
            histogram: hist.counts,
            histogram_lo: hist.lo,
            histogram_hi: hist.hi,
        }
    }

    /// The current decision, as a message.
    pub fn current(&self) -> Option<pb::PmDecision> {
        let s = self.state();
        s.current().map(|d| s.message(d))
    }

    /// A decision by version.
    pub fn decision(&self, version: u64) -> Option<pb::PmDecision> {
        let s = self.state();
        s.decisions
            .iter()
            .find(|d| d.pm_version == version)
            .map(|d| s.message(d))
    }

    fn hello(&self, conn: u64, h: &pb::NodeHello) {
        for s in &h.held {
            self.hub.held(conn, s.step, s.rank);
        }
        *self.reported.lock().unwrap_or_else(|e| e.into_inner()) = Some(Candidate {
            r: h.resolution,
            gamma: h.gamma,
            precision: precision_of(h.precision_bits),
        });
        let (before, current) = {
            let mut s = self.state();
            if h.pm_version > s.highest_seen {
                s.highest_seen = h.pm_version;
                self.save(&s);
            }
            let before = s.decisions.len().checked_sub(2).map(|i| {
                let mut m = s.message(&s.decisions[i]);
                m.from_step = 0;
                m
            });
            (before, s.current().map(|d| s.message(d)))
        };
        info!(node = %h.node_id, pm_version = h.pm_version, r = h.resolution, gamma = h.gamma, held = h.held.len(), "node attached");
        self.hub.send(conn, Down::Budget(self.node_budget()));
        if let Some(d) = current.filter(|d| d.pm_version > h.pm_version) {
            // A node that holds neither (a restart): the decision before first, in force for
            // every step before the current one's switch, so that a step it receives late is
            // made with the P_M and scene its other ranks were made with.
            if let Some(b) = before.filter(|b| b.pm_version > h.pm_version && d.from_step > 0) {
                self.hub.send(conn, Down::Decision(b));
            }
            self.hub.send(conn, Down::Decision(d));
        }
    }
}

/// What the reason of a correction, or of a tuning's answer chosen for when it lands, ends
/// with when no candidate meets the plan under the forecast and the coarsest is pushed (its
/// step is expected to overshoot).
pub(crate) const INFEASIBLE: &str =
    "; no candidate meets the plan under this forecast: the coarsest";

/// A step whose summaries are coming in.
struct Pending {
    world_size: u32,
    counts: [u64; BINS],
    ranks: u32,
    sigma_bytes: u64,
    tau_secs: f64,
    pm_version: u64,
    /// The steered scene version they were made with.
    scene_version: u64,
    /// The range the counts cover (the transfer function's domain).
    range: (f64, f64),
    /// The `P_M` the production VDIs were made with (the first rank's).
    candidate: Candidate,
    sampled: bool,
}

impl Pending {
    /// The step's production σ and τ (σ summed over its ranks, τ of the slowest).
    fn sizing(&self) -> insitu_core::evaluate::Sizing {
        insitu_core::evaluate::Sizing {
            sigma_bytes: self.sigma_bytes,
            tau_secs: self.tau_secs,
            ..Default::default()
        }
    }
}

/// A step waiting for its q reports before its fields are released.
struct AwaitingQ {
    world_size: u32,
    mses: Vec<f64>,
    pm_version: u64,
}

/// The engine task's own state.
struct Loop {
    engine: Arc<Engine>,
    pending: BTreeMap<u64, Pending>,
    awaiting: BTreeMap<u64, AwaitingQ>,
    recent: VecDeque<(u64, [f64; BINS])>,
    dirty: Option<Trigger>,
    /// Evicted characteristic steps whose fields a running tuning may still ask trials of:
    /// released when it ends (unless characteristic again by then).
    deferred: Vec<u64>,
    /// The version of the tuned decision the last production step checked against the budget
    /// was made under, and how many steps made under it in a row ended with one whose τ broke
    /// τ_target.
    slow: (u64, u32),
    /// Whether the last tuning was cut short for a newer step (the next one is not: a field
    /// that changes character at every step would otherwise never be tuned for).
    cut_last: bool,
    /// The `P_M` of the last production step completed.
    last_candidate: Option<Candidate>,
}

/// How a production step broke the budget.
enum Break {
    /// σ ≥ σ_target.
    Size(String),
    /// τ ≥ τ_target.
    Time(String),
}

impl Loop {
    /// Lets the nodes drop an evicted step's field, after the running tuning if there is one
    /// (it searches over the steps it started with; dropping one under it would fail it, and
    /// a field that drifts faster than a tuning takes would never be tuned for).
    fn release_evicted(&mut self, step: u64) {
        if self.engine.counters().tuning {
            self.deferred.push(step);
        } else {
            self.engine.hub.hold(step, false);
        }
    }

    /// After a tuning: releases the fields [`Self::release_evicted`] kept for it.
    fn tuning_ended(&mut self) {
        let keep = self.engine.state().tracker.step_indices();
        for step in std::mem::take(&mut self.deferred) {
            if !keep.contains(&step) {
                self.engine.hub.hold(step, false);
            }
        }
    }

    fn summary(&mut self, conn: u64, s: pb::StepSummary) {
        let e = self.engine.clone();
        e.counters().summaries += 1;
        e.domain().saw(&s);
        if s.held {
            e.hub.held(conn, s.step, s.rank);
        }
        // Progress first: a decision made for this step applies past it.
        let newest = e
            .progress
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .saw(s.step, s.begun, conn);
        let p = self.pending.entry(s.step).or_insert(Pending {
            world_size: s.world_size,
            counts: [0; BINS],
            ranks: 0,
            sigma_bytes: 0,
            tau_secs: 0.0,
            pm_version: s.pm_version,
            scene_version: s.scene_version,
            range: (s.range_lo, s.range_hi),
            candidate: Candidate {
                r: s.resolution,
                gamma: s.gamma,
                precision: precision_of(s.precision_bits),
            },
            sampled: s.sampled,
        });
        for (c, &n) in p.counts.iter_mut().zip(&s.histogram) {
            *c += n;
        }
        p.ranks += 1;
        p.sigma_bytes += s.sigma_bytes;
        p.tau_secs = p.tau_secs.max(s.tau_secs);
        if p.ranks >= p.world_size {
            if let Some(p) = self.pending.remove(&s.step) {
                self.complete(s.step, p);
            }
        }
        let stale: Vec<u64> = self
            .pending
            .keys()
            .chain(self.awaiting.keys())
            .copied()
            .filter(|&k| k + STALE_STEPS < newest)
            .collect();
        for k in stale {
            if self.pending.remove(&k).is_some() {
                warn!(
                    step = k,
                    "not every rank of the step was summarised; it is left out"
                );
            }
            self.awaiting.remove(&k);
            e.hub.hold(k, false);
        }
    }

    /// σ and τ of a production step against the budget (σ summed over ranks, τ the slowest).
    fn over_budget(&self, p: &Pending) -> Option<Break> {
        let (size, time) = self.engine.resolved().budgets;
        if let Some(t) = size.filter(|&t| p.sigma_bytes >= t) {
            return Some(Break::Size(format!(
                "σ {} B ≥ σ_target {t} B",
                p.sigma_bytes
            )));
        }
        if let Some(t) = time.filter(|&t| p.tau_secs >= t) {
            return Some(Break::Time(format!(
                "τ {:.4} s ≥ τ_target {t} s",
                p.tau_secs
            )));
        }
        None
    }

    /// Why the production step `p` (made under the tuning whose decision is version
    /// `tuned`, or a correction of it) starts a re-tuning, if it does: a σ over the budget at
    /// once, a τ over it when it is the `time_breaks`-th such step in a row under that tuning.
    fn retunes(&mut self, tuned: u64, p: &Pending) -> Option<String> {
        let version = tuned;
        let streak = if self.slow.0 == version {
            self.slow.1
        } else {
            0
        };
        // The reason, if any, and the run of slow steps left behind (none after a re-tuning).
        let (why, run) = match self.over_budget(p) {
            Some(Break::Size(why)) => (Some(why), 0),
            Some(Break::Time(why)) => {
                let (n, needed) = (streak + 1, self.engine.cfg.time_breaks);
                if n < needed {
                    (None, n)
                } else if needed > 1 {
                    (Some(format!("{why}, {n} steps in a row")), 0)
                } else {
                    (Some(why), 0)
                }
            }
            None => (None, 0),
        };
        self.slow = (version, run);
        why
    }

    /// The version of the last tuning's decision, when no tuning is pending or running: a
    /// production step made with it or a later version (a correction of it) is held against
    /// what that tuning measured. `validated` also asks that the decision was found best on
    /// the characteristic steps as they are (after a forced step, the re-tuning that takes it
    /// into account must finish first; after a failed one, only a new characteristic step
    /// starts another).
    fn unforced_tuning(&self, validated: bool) -> Option<u64> {
        if self.dirty.is_some() || self.engine.counters().tuning {
            return None;
        }
        let s = self.engine.state();
        s.tuned()
            .filter(|_| !validated || s.validated == s.tracker.step_indices())
            .map(|d| d.pm_version)
    }

    /// Whether the production step made with version `v` has a size miss (see
    /// [`Cause::SizeMiss`]): σ at least `characteristic.sigma_miss` times `planned`, made under
    /// the last tuning (no tuning pending or running) with the `P_M` of the step before
    /// (`steady`). The plan for a `P_M` production has not made yet is the surface's
    /// interpolation, whose error at one candidate can be as large (on Gray–Scott 128³ a
    /// correction to r 192, γ 0.009 planned at 239 kB made 805 kB); the next step's plan
    /// rests on that step's own σ.
    fn size_miss(&self, v: u64, p: &Pending, planned: Option<f64>, steady: bool) -> Option<Cause> {
        let threshold = self.engine.cfg.characteristic.sigma_miss;
        let planned_bytes = planned.filter(|_| steady)?;
        let tuned = self.unforced_tuning(false)?;
        (v >= tuned && p.sigma_bytes as f64 >= threshold * planned_bytes).then_some(
            Cause::SizeMiss {
                sigma_bytes: p.sigma_bytes,
                planned_bytes,
                threshold,
            },
        )
    }

    fn force(
        &mut self,
        step: u64,
        h: &[f64; BINS],
        world_size: u32,
        production: Option<(Candidate, insitu_core::evaluate::Sizing)>,
        cause: Cause,
    ) {
        let e = self.engine.clone();
        let evicted = {
            let mut s = e.state();
            let ev = s.force(step, h, world_size);
            if let Some((c, sizing)) = production {
                s.add_production(step, c, sizing, e.process);
            }
            e.save(&s);
            ev
        };
        e.hub.hold(step, true);
        if let Some((gone, d)) = evicted {
            info!(
                evicted = gone,
                nearest = d,
                "evicted the most redundant characteristic step"
            );
            self.release_evicted(gone);
        }
        let trigger = Trigger { step, cause };
        info!(step, reason = %trigger, "step becomes characteristic");
        self.mark_dirty(trigger);
    }

    /// A tuning is due for `trigger`; a running one is cut short for it, unless the last one
    /// was or no decision is in force yet (the first decision, even on fewer steps, is worth
    /// more than a better one later: the nodes run on the configured P_M until it comes).
    fn mark_dirty(&mut self, trigger: Trigger) {
        let decided = self.engine.state().current().is_some();
        if decided && self.engine.counters().tuning && !self.cut_last {
            self.engine.superseded.store(true, Ordering::SeqCst);
        }
        self.dirty = Some(trigger);
    }

    /// Closed-loop control after production step `step` (all ranks in): the controller
    /// records it and, when the `P_M` in force misses the plan for the step a decision made
    /// now would apply from (or a finer one clears it), pushes a correction of the tuned
    /// decision. Nothing before the first tuning, without a budget, or while no candidate of
    /// the tuning was measured.
    fn control(&mut self, step: u64, p: &Pending, planned_sigma_bytes: Option<f64>) {
        let e = self.engine.clone();
        // A step made before any decision at an r the node lowered itself to keep the budget
        // (generator-node/src/correct.rs) is no plan of the tuner's, and its candidate lies off
        // the tuning's grid: its σ against the surface's interpolation would be read as
        // growth. Only steps at the configured P_M or a decision's inform the forecast.
        let configured = *e.reported.lock().unwrap_or_else(|p| p.into_inner());
        if p.pm_version == 0 && configured.is_some_and(|c| c != p.candidate) {
            return;
        }
        let mut ctl = e.control();
        if !ctl.active() {
            return;
        }
        ctl.observe(Observation {
            step,
            candidate: p.candidate,
            sigma_bytes: p.sigma_bytes,
            tau_secs: p.tau_secs,
            planned_sigma_bytes,
        });
        let at = e.decision_start();
        let (tuned, current, surface, next) = {
            let s = e.state();
            let (Some(t), Some(c)) = (s.tuned(), s.current()) else {
                return;
            };
            if t.scene_version != s.scene_version() {
                // Tuned under an earlier scene: its measurements say nothing of this one.
                return;
            }
            (
                t.clone(),
                c.candidate,
                s.surface(&t.characteristic_steps),
                s.next_version(),
            )
        };
        let Some(plan) = ctl.correct(&surface, tuned.ceiling(), current, at) else {
            return;
        };
        debug!(
            step,
            r = plan.candidate.r,
            gamma = plan.candidate.gamma,
            surface_sigma = surface.sigma(plan.candidate),
            planned_sigma = plan.sigma_bytes,
            k = plan.forecast.sigma,
            steps = ?tuned.characteristic_steps,
            "correction planned"
        );
        let miss = ctl.miss();
        let broke = ctl
            .sigma_target
            .filter(|&t| p.sigma_bytes as f64 >= t && p.pm_version > tuned.pm_version)
            .map(|t| {
                format!(
                    "; step {step} was over the budget (σ {} B ≥ {t:.0} B) under a correction: this correction takes it up, no tuning",
                    p.sigma_bytes
                )
            });
        drop(ctl);
        let k = plan.forecast;
        let mut notes = if miss >= 1.005 {
            format!(", planned {miss:.2}× below the budget for the model's last miss")
        } else {
            String::new()
        };
        if !plan.feasible {
            notes.push_str(INFEASIBLE);
        }
        notes.push_str(broke.as_deref().unwrap_or(""));
        let reason = format!(
            "correction after step {step}: production σ {:.2}× the tuning's measurements at its P_M, forecast {:.2}× by step {}; {} kB planned under {}{notes}",
            k.sigma_now,
            k.sigma,
            k.at,
            (plan.sigma_bytes / 1e3).round(),
            e.utility()
        );
        let q = q_on(&e.state(), &tuned.characteristic_steps, plan.candidate);
        e.publish(Decision {
            pm_version: next,
            candidate: plan.candidate,
            old: Some(current),
            characteristic_steps: tuned.characteristic_steps.clone(),
            predicted: planned(&plan, q),
            reason,
            trigger_step: step,
            trials: 0,
            trial_secs: 0.0,
            utility: e.utility(),
            from_step: at,
            corrects: Some(tuned.pm_version),
            tuned: None,
            forecast_ratio: Some(k.sigma),
            scene_version: 0,
            steered: false,
        });
    }

    fn complete(&mut self, step: u64, p: Pending) {
        let e = self.engine.clone();
        e.domain().histogram = Some(StepHistogram {
            step,
            counts: p.counts.to_vec(),
            lo: p.range.0,
            hi: p.range.1,
        });
        if !self.under_scene_in_force(step, &p) {
            e.hub.hold(step, false);
            return;
        }
        let Ok(h) = normalise(&p.counts) else { return };
        self.recent.push_back((step, h));
        if self.recent.len() > STALE_STEPS as usize {
            self.recent.pop_front();
        }
        // What the decision the step was made under planned for it.
        let planned = e
            .state()
            .decisions
            .iter()
            .rev()
            .find(|d| d.pm_version == p.pm_version && d.candidate == p.candidate)
            .map(|d| d.predicted.sizing.sigma_bytes as f64)
            .filter(|&b| b > 0.0);
        self.control(step, &p, planned);
        let production = Some((p.candidate, p.sizing()));
        let steady = self.last_candidate.replace(p.candidate) == Some(p.candidate);
        let cause = self
            .size_miss(p.pm_version, &p, planned, steady)
            .or_else(|| {
                // A broken budget re-tunes for a step made with the tuned decision itself; one
                // made under a correction is the forecast's miss, which the next correction
                // takes up (its reason says so).
                let tuned = self.unforced_tuning(true).filter(|&t| p.pm_version == t)?;
                let why = self.retunes(tuned, &p)?;
                Some(Cause::BrokeBudget { why })
            });
        if let Some(cause) = cause {
            self.force(step, &h, p.world_size, production, cause);
            return;
        }
        let verdict = {
            let mut s = e.state();
            let v = s.observe(step, &h, p.world_size);
            if matches!(v, Verdict::New { .. }) {
                s.add_production(step, p.candidate, p.sizing(), e.process);
                e.save(&s);
            }
            v
        };
        match verdict {
            Verdict::New { distance, evicted } => {
                e.hub.hold(step, true);
                if let Some((gone, d)) = evicted {
                    info!(evicted = gone, nearest = d, max = e.cfg.characteristic.max, "evicted the most redundant characteristic step (its nearest other one is closest)");
                    self.release_evicted(gone);
                }
                let cause = match distance {
                    None => Cause::First,
                    Some(d) => Cause::NewCharacter {
                        distance: d,
                        threshold: e.cfg.characteristic.threshold,
                    },
                };
                let trigger = Trigger { step, cause };
                info!(step, reason = %trigger, "characteristic step");
                self.mark_dirty(trigger);
            }
            Verdict::Alike { .. } if p.sampled && e.cfg.viz.is_some() => {
                // Keep the field until its q is known: a q far below the prediction makes
                // the step characteristic, and then its field is needed.
                self.awaiting.insert(
                    step,
                    AwaitingQ {
                        world_size: p.world_size,
                        mses: Vec::new(),
                        pm_version: p.pm_version,
                    },
                );
            }
            Verdict::Alike { .. } => e.hub.hold(step, false),
        }
    }

    fn report(&mut self, r: &pb::QualityReport) {
        let Some(q) = r.q_db else { return };
        let Some(a) = self.awaiting.get_mut(&r.step) else {
            return;
        };
        a.mses.push(mse_from_psnr(q));
        // A composed report is the whole step's q (the viz-node composes steps of several
        // ranks); otherwise (older viz-nodes) the ranks' MSEs are summed once all are in, as
        // `combine_ranks` estimates a composed step's error from its bricks'.
        if !r.composed && a.mses.len() < r.world_size.max(a.world_size) as usize {
            return;
        }
        let Some(a) = self.awaiting.remove(&r.step) else {
            return;
        };
        let q = psnr_from_mse(a.mses.iter().sum::<f64>());
        let e = self.engine.clone();
        let predicted = e
            .state()
            .current()
            .filter(|d| !d.steered)
            .map(|d| d.predicted.q());
        if let (Some(v), Some(pq)) = (self.unforced_tuning(true), predicted) {
            if a.pm_version >= v && q < pq - e.cfg.q_margin_db {
                let h = self.recent.iter().find(|(s, _)| *s == r.step).map(|x| x.1);
                if let Some(h) = h {
                    let why = format!(
                        "q {q:.2} dB is more than {} dB below the predicted {pq:.2} dB",
                        e.cfg.q_margin_db
                    );
                    self.force(r.step, &h, a.world_size, None, Cause::BrokeBudget { why });
                    return;
                }
            }
        }
        e.hub.hold(r.step, false);
    }
}

impl Loop {
    /// Whether production step `step` was made under the steered scene in force (its
    /// histogram and σ then say something of it); the first such step of a pending change
    /// marks the change applied (docs/steering.md).
    fn under_scene_in_force(&mut self, step: u64, p: &Pending) -> bool {
        let e = self.engine.clone();
        let mut s = e.state();
        if p.scene_version < s.scene_version() {
            return false;
        }
        let mut changed = false;
        for r in &mut s.steering {
            if r.standing == Standing::Pending && r.scene_version <= p.scene_version {
                r.standing = Standing::Applied;
                changed = true;
                info!(
                    scene_version = r.scene_version,
                    step, "steered scene applied"
                );
            }
        }
        if changed {
            e.save(&s);
        }
        true
    }

    /// A steering request (docs/steering.md): checked; a utility change re-tunes over the
    /// characteristic steps; a scene change becomes the next scene version, pushed at once in
    /// a decision of the `P_M` in force, supersedes a change not applied yet, and starts the
    /// tuner afresh for the new scene (the old scene's characteristic steps released, a
    /// running tuning cut short, the controller reset): the first step made under it is
    /// characteristic.
    fn steer(&mut self, req: pb::SteerRequest) -> Result<pb::SteerReply, tonic::Status> {
        let e = self.engine.clone();
        let scene = e.state().scene();
        let change = crate::steer::check(&req, &scene, &e.domain())
            .map_err(tonic::Status::invalid_argument)?;
        let resolved = change
            .utility
            .as_deref()
            .map(|u| resolve_with(&e.cfg, u))
            .transpose()
            .map_err(|err| tonic::Status::invalid_argument(format!("utility: {err}")))?;
        let carrier = {
            let s = e.state();
            s.current()
                .map(|d| d.candidate)
                .or(*e.reported.lock().unwrap_or_else(|p| p.into_inner()))
        };
        if change.scene.is_some() && carrier.is_none() {
            return Err(tonic::Status::failed_precondition(
                "no generator-node has attached yet: a scene change travels in a decision, and there is no P_M to carry it",
            ));
        }
        let at = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0.0, |d| d.as_secs_f64());
        let newest = self.recent.back().map_or(0, |(s, _)| *s);
        if let (Some(u), Some(r)) = (change.utility.clone(), resolved) {
            let retune_from = change.scene.is_none().then_some(newest);
            self.steer_utility(u, r, (&req.who, at), retune_from);
        }
        let Some((mut next, candidate)) = change.scene.zip(carrier) else {
            return Ok(pb::SteerReply {
                scene_version: scene.version,
                utility: e.utility(),
                ..Default::default()
            });
        };
        let from_step = e.decision_start();
        let (version, pm_version, superseded, released) = {
            let mut s = e.state();
            next.version = s.scene_version() + 1;
            let version = next.version;
            let pm_version = s.next_version();
            let mut superseded = Vec::new();
            for r in &mut s.steering {
                if r.standing == Standing::Pending && r.scene_version > 0 {
                    r.standing = Standing::Superseded;
                    superseded.push(r.scene_version);
                }
            }
            s.scenes.push(next);
            s.steering.push(SteerRecord {
                scene_version: version,
                pm_version,
                from_step,
                standing: Standing::Pending,
                change: change.words.clone(),
                who: req.who.clone(),
                at_unix_secs: at,
            });
            // The old scene's characteristic steps and validation say nothing of the new one.
            let released = s.tracker.step_indices();
            for step in &released {
                s.forget(*step);
            }
            s.validated.clear();
            // Saved with the decision (`publish`).
            (version, pm_version, superseded, released)
        };
        for step in released {
            self.release_evicted(step);
        }
        self.dirty = None;
        self.recent.clear();
        if e.counters().tuning {
            e.superseded.store(true, Ordering::SeqCst);
        }
        e.restart_control();
        let who = if req.who.is_empty() {
            String::new()
        } else {
            format!(" by {}", req.who)
        };
        e.publish(Decision {
            pm_version,
            candidate,
            old: Some(candidate),
            characteristic_steps: Vec::new(),
            predicted: unmeasured(candidate),
            reason: format!("scene {version} steered{who}: {}", change.words),
            trigger_step: newest,
            trials: 0,
            trial_secs: 0.0,
            utility: e.utility(),
            from_step,
            corrects: None,
            tuned: None,
            forecast_ratio: None,
            scene_version: version,
            steered: true,
        });
        info!(scene_version = version, pm_version, from_step, superseded = ?superseded, change = %change.words, "scene steered");
        Ok(pb::SteerReply {
            scene_version: version,
            pm_version,
            from_step,
            utility: e.utility(),
            superseded,
        })
    }

    /// A steered utility `u` (resolved as `r`) put in force: recorded, the nodes told their
    /// budget, and the characteristic steps re-tuned from `retune_from` where there are some
    /// (`None` when a scene change in the same request starts the tuner afresh anyway).
    fn steer_utility(
        &mut self,
        u: String,
        r: Resolved,
        (who, at): (&str, f64),
        retune_from: Option<u64>,
    ) {
        let e = self.engine.clone();
        *e.resolved.write().unwrap_or_else(|p| p.into_inner()) = Arc::new(r);
        e.restart_control();
        let mut s = e.state();
        s.utility = Some(u.clone());
        s.steering.push(SteerRecord {
            scene_version: 0,
            pm_version: 0,
            from_step: 0,
            standing: Standing::Applied,
            change: format!("utility {u}"),
            who: who.to_string(),
            at_unix_secs: at,
        });
        // The decision in force was found best for the old utility.
        s.validated.clear();
        e.save(&s);
        let retune = retune_from.filter(|_| !s.tracker.steps.is_empty());
        drop(s);
        info!(utility = %e.utility(), who = %who, "utility steered");
        e.hub.broadcast(&Down::Budget(e.node_budget()));
        if let Some(step) = retune {
            self.mark_dirty(Trigger {
                step,
                cause: Cause::Steered {
                    what: format!("utility {u}"),
                },
            });
        }
    }
}

/// `cfg` resolved with `utility` in place of its own.
///
/// # Errors
/// The configuration's error naming the utility.
fn resolve_with(cfg: &Config, utility: &str) -> Result<Resolved, crate::config::ConfigError> {
    let mut c = cfg.clone();
    utility.clone_into(&mut c.utility);
    c.resolve()
}

/// A node's precision from the wire (a bit count outside 4..=16 reads as `f32`: the
/// summaries and hellos were checked when they arrived).
fn precision_of(bits: u32) -> insitu_core::Precision {
    insitu_core::Precision::from_bits(bits).unwrap_or_default()
}

/// A candidate with nothing measured of it (a steering decision's prediction: σ and τ 0, q NaN).
fn unmeasured(c: Candidate) -> insitu_tuner::Measurement {
    insitu_tuner::Measurement {
        r: c.r,
        gamma: c.gamma,
        precision: c.precision,
        sigma_paper_bytes: None,
        sizing: insitu_core::evaluate::Sizing::default(),
        tau_render_secs: 0.0,
        q_db: insitu_core::metrics::Db(f64::NAN),
        view_q_db: Vec::new(),
        ssim: None,
    }
}

/// q of `c` on `steps`: its worst where a trial scored it on each step, else NaN.
pub(crate) fn q_on(s: &State, steps: &[u64], c: Candidate) -> f64 {
    if steps.is_empty() {
        return f64::NAN;
    }
    steps
        .iter()
        .map(|&step| s.trial(step, c).map(|t| t.measurement.q()))
        .try_fold(f64::INFINITY, |lo, q| q.map(|q| lo.min(q)))
        .unwrap_or(f64::NAN)
}

/// A plan as the predicted measurement of a decision: σ and τ forecast, q as measured (`q_db`).
pub(crate) fn planned(p: &Plan, q_db: f64) -> insitu_tuner::Measurement {
    insitu_tuner::Measurement {
        r: p.candidate.r,
        gamma: p.candidate.gamma,
        precision: p.candidate.precision,
        sigma_paper_bytes: None,
        sizing: insitu_core::evaluate::Sizing {
            sigma_bytes: p.sigma_bytes.round() as u64,
            tau_secs: if p.tau_secs.is_finite() {
                p.tau_secs
            } else {
                0.0
            },
            ..Default::default()
        },
        tau_render_secs: 0.0,
        q_db: insitu_core::metrics::Db(q_db),
        view_q_db: Vec::new(),
        ssim: None,
    }
}

impl Engine {
    /// After a restart: a tuning over the persisted characteristic steps, unless the decision
    /// in force was validated on exactly these.
    fn resume(&self) -> Option<Trigger> {
        let s = self.state();
        let steps = s.tracker.step_indices();
        (!steps.is_empty() && s.validated != steps).then(|| Trigger {
            step: steps.last().copied().unwrap_or(0),
            cause: Cause::Resume,
        })
    }

    /// A tuning for `trigger` on the blocking pool (trials wait on the nodes); it gives back
    /// whether it finished, and its trigger.
    fn start_tuning(self: &Arc<Self>, trigger: Trigger) -> JoinHandle<(bool, Trigger)> {
        {
            let mut c = self.counters();
            c.retunes += 1;
            c.tuning = true;
        }
        info!(reason = %trigger, "tuning");
        let (e, tune) = (self.clone(), self.tuning);
        tokio::task::spawn_blocking(move || (tune(&e, &trigger), trigger))
    }

    /// Removes the characteristic steps lost with their nodes during a tuning from the set
    /// (persisted); a tuning over the steps left when any were lost and some are left.
    fn forget_lost(&self) -> Option<Trigger> {
        let lost: Vec<u64> =
            std::mem::take(&mut *self.lost.lock().unwrap_or_else(|e| e.into_inner()));
        let first = *lost.first()?;
        let mut s = self.state();
        for step in &lost {
            if s.forget(*step) {
                info!(
                    step,
                    "no node holds this characteristic step any more: it leaves the set"
                );
            }
        }
        self.save(&s);
        (!s.tracker.steps.is_empty()).then_some(Trigger {
            step: first,
            cause: Cause::Lost { steps: lost },
        })
    }

    /// The engine task: takes events in order and tunes when the characteristic set changed.
    pub async fn run(self: Arc<Self>, mut events: mpsc::Receiver<Event>) {
        let resume = self.resume();
        let mut l = Loop {
            engine: self.clone(),
            pending: BTreeMap::new(),
            awaiting: BTreeMap::new(),
            recent: VecDeque::new(),
            dirty: resume,
            deferred: Vec::new(),
            slow: (0, 0),
            cut_last: false,
            last_candidate: None,
        };
        // The running tuning gives back its trigger and whether it finished.
        let mut tuning: Option<JoinHandle<(bool, Trigger)>> = None;
        // A tuning that failed without losing a step (a trial timed out) is tried again after
        // the trial timeout, unless something else starts one first.
        let mut retry: Option<(tokio::time::Instant, Trigger)> = None;
        loop {
            if l.dirty.is_some() {
                retry = None;
            }
            if tuning.is_none() {
                tuning = l.dirty.take().map(|trigger| self.start_tuning(trigger));
            }
            tokio::select! {
                ev = events.recv() => match ev {
                    None => return,
                    Some(Event::Hello(conn, h)) => self.hello(conn, &h),
                    Some(Event::Summary(conn, s)) => l.summary(conn, s),
                    Some(Event::Report(r)) => {
                        self.counters().quality_reports += 1;
                        l.report(&r);
                    }
                    Some(Event::Steer(req, answer)) => {
                        let _ = answer.send(l.steer(req));
                    }
                    Some(Event::Gone(conn)) => {
                        if let Some(id) = self.hub.disconnect(conn) {
                            info!(node = %id, "node detached; its trials in flight fail, its held fields are gone");
                        }
                    }
                },
                () = async { if let Some((at, _)) = &retry { tokio::time::sleep_until(*at).await } }, if tuning.is_none() && retry.is_some() => {
                    if let Some((_, trigger)) = retry.take() {
                        info!("trying the failed tuning again");
                        l.dirty = Some(trigger);
                    }
                }
                done = async { match tuning.as_mut() { Some(t) => t.await.ok(), None => None } }, if tuning.is_some() => {
                    tuning = None;
                    self.counters().tuning = false;
                    l.cut_last = self.superseded.swap(false, Ordering::SeqCst);
                    if l.cut_last {
                        self.counters().tunings_superseded += 1;
                    }
                    l.tuning_ended();
                    if let Some((false, trigger)) = done {
                        let wait = Duration::from_secs_f64(self.cfg.trials.timeout_secs);
                        retry = Some((tokio::time::Instant::now() + wait, trigger));
                    }
                    let again = self.forget_lost();
                    if l.dirty.is_none() {
                        l.dirty = again;
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use insitu_core::evaluate::Sizing;
    use insitu_core::metrics::Db;
    use insitu_tuner::Measurement;

    fn summary(step: u64, bin: usize, sigma: u64, version: u64) -> pb::StepSummary {
        let mut histogram = vec![0; BINS];
        histogram[bin] = 100;
        pb::StepSummary {
            step,
            world_size: 1,
            histogram,
            range_lo: 0.0,
            range_hi: 1.0,
            sampled: true,
            pm_version: version,
            sigma_bytes: sigma,
            ..Default::default()
        }
    }

    /// An engine whose decision v1 (r 64, γ 0.01, predicted q 40 dB) was tuned on step 0,
    /// for σ_target 1 000 B.
    fn tuned(dir: &std::path::Path) -> Loop {
        tuned_for(dir, "size:1000", 2)
    }

    /// As [`tuned`] for `utility`, with `time_breaks`.
    fn tuned_for(dir: &std::path::Path, utility: &str, time_breaks: u32) -> Loop {
        let cfg = Config {
            state_dir: dir.to_owned(),
            viz: Some("127.0.0.1:1".into()),
            utility: utility.into(),
            time_breaks,
            ..Default::default()
        };
        let resolved = cfg.resolve().unwrap();
        let mut state = State::with_step_zero();
        let c = Candidate {
            r: 64,
            gamma: 0.01,
            precision: Default::default(),
        };
        let predicted = Measurement {
            r: 64,
            gamma: 0.01,
            precision: Default::default(),
            sigma_paper_bytes: None,
            sizing: Sizing {
                sigma_bytes: 900,
                ..Sizing::default()
            },
            tau_render_secs: 0.0,
            q_db: Db(40.0),
            view_q_db: vec![],
            ssim: None,
        };
        state.decisions.push(Decision {
            pm_version: 1,
            candidate: c,
            old: None,
            characteristic_steps: vec![0],
            predicted,
            reason: "test".into(),
            trigger_step: 0,
            trials: 0,
            trial_secs: 0.0,
            utility: "size".into(),
            from_step: 0,
            corrects: None,
            tuned: None,
            forecast_ratio: None,
            scene_version: 0,
            steered: false,
        });
        state.validated = vec![0];
        let (engine, _rx) = Engine::new(cfg, resolved, state, |_, _| true);
        Loop {
            engine,
            pending: BTreeMap::new(),
            awaiting: BTreeMap::new(),
            recent: VecDeque::new(),
            dirty: None,
            deferred: Vec::new(),
            slow: (0, 0),
            cut_last: false,
            last_candidate: None,
        }
    }

    fn report(step: u64, q: f64) -> pb::QualityReport {
        pb::QualityReport {
            step,
            world_size: 1,
            pm_version: 1,
            q_db: Some(q),
            ..Default::default()
        }
    }

    #[test]
    fn a_production_step_far_below_the_predicted_q_becomes_characteristic() {
        let dir = tempfile::tempdir().unwrap();
        let mut l = tuned(dir.path());
        // Alike and within budget: waits for its q, which is close to the prediction.
        l.summary(1, summary(1, 3, 500, 1));
        assert!(l.dirty.is_none() && l.awaiting.contains_key(&1));
        l.report(&report(1, 38.5));
        assert!(l.dirty.is_none() && l.awaiting.is_empty());
        // 4 dB below (margin 3): characteristic, with the reason.
        l.summary(2, summary(2, 3, 500, 1));
        l.report(&report(2, 36.0));
        let d = l.dirty.clone().unwrap();
        assert_eq!(d.step, 2);
        assert!(
            matches!(&d.cause, Cause::BrokeBudget { why } if why.contains("below the predicted 40.00 dB")),
            "{d:?}"
        );
        assert_eq!(l.engine.state().tracker.step_indices(), vec![0, 2]);
        // Persisted; the decision in force is no longer validated on the set.
        let s = State::load(dir.path()).unwrap().unwrap();
        assert_eq!(
            (s.tracker.step_indices(), s.validated),
            (vec![0, 2], vec![0])
        );
    }

    #[test]
    fn a_step_evicted_during_a_tuning_is_released_after_it() {
        use insitu_proto::pb::tuner_message::Msg as Down;
        let dir = tempfile::tempdir().unwrap();
        let mut l = tuned(dir.path());
        let (tx, mut rx) = tokio::sync::mpsc::channel(16);
        let conn = l.engine.hub.connect("n", tx);
        l.engine.hub.held(conn, 5, 0);
        let released =
            |rx: &mut tokio::sync::mpsc::Receiver<Result<pb::TunerMessage, tonic::Status>>| {
                std::iter::from_fn(|| rx.try_recv().ok())
                    .filter_map(Result::ok)
                    .filter(|m| {
                        matches!(
                            m.msg,
                            Some(Down::Hold(pb::HoldRequest {
                                step: 5,
                                keep: false
                            }))
                        )
                    })
                    .count()
            };
        l.engine.counters().tuning = true;
        l.release_evicted(5);
        assert_eq!(
            released(&mut rx),
            0,
            "kept while the tuning may ask trials of it"
        );
        l.engine.counters().tuning = false;
        l.tuning_ended();
        assert_eq!(released(&mut rx), 1, "released once it ended");
        l.engine.hub.held(conn, 5, 0);
        l.release_evicted(5);
        assert_eq!(released(&mut rx), 1, "no tuning: released at once");
    }

    /// A production step of P_M v1 (r 64, γ 0.01) with σ `sigma`, its node idle after it.
    fn made_with_v1(step: u64, sigma: u64) -> pb::StepSummary {
        pb::StepSummary {
            resolution: 64,
            gamma: 0.01,
            begun: step + 1,
            ..summary(step, 3, sigma, 1)
        }
    }

    /// [`tuned`] with the tuning's size probes on step 0: σ(64, 0.01) = 900 B (the decision's
    /// prediction) and σ(64, 0.02) = 450 B.
    fn tuned_with_probes(dir: &std::path::Path) -> Loop {
        let l = tuned(dir);
        for (gamma, sigma_bytes) in [(0.01, 900), (0.02, 450)] {
            l.engine.state().size_probes.push(crate::state::SizeProbe {
                step: 0,
                candidate: Candidate {
                    r: 64,
                    gamma,
                    precision: Default::default(),
                },
                sizing: Sizing {
                    sigma_bytes,
                    tau_secs: 0.01,
                    ..Sizing::default()
                },
                trial_secs: 0.01,
                run_by: 0,
                production: false,
            });
        }
        l
    }

    #[test]
    fn still_data_keeps_the_p_m_and_drifting_data_gets_a_correction_from_the_next_step() {
        let dir = tempfile::tempdir().unwrap();
        let mut l = tuned_with_probes(dir.path());
        // Production as the tuning measured it: nothing changes, however long.
        for step in 1..=12 {
            l.summary(1, made_with_v1(step, 900));
        }
        assert_eq!(l.engine.state().decisions.len(), 1);
        assert_eq!(l.engine.status().corrections, 0);
        // σ grows 5 % a step: within the budget at first, then the P_M in force would miss
        // the 950 B plan by the next step, and a correction of v1 lands there.
        let mut sigma = 900.0;
        let mut step = 12;
        while l.engine.state().decisions.len() == 1 && step < 30 {
            step += 1;
            sigma *= 1.05;
            l.summary(1, made_with_v1(step, sigma as u64));
        }
        let s = l.engine.state();
        let d = s.current().unwrap();
        assert_eq!((d.pm_version, d.corrects), (2, Some(1)), "{d:?}");
        assert_eq!(
            d.from_step,
            step + 1,
            "the next step: the node had begun no later one"
        );
        assert_eq!(d.candidate.r, 64);
        assert!(d.candidate.gamma > 0.01, "{d:?}");
        // Planned for at least the latest ratio (the median growth of the window is still
        // that of the still steps): its σ forecast meets the plan.
        let k = d.forecast_ratio.unwrap();
        assert!(k >= (sigma as u64) as f64 / 900.0 - 1e-9, "forecast {k}");
        assert!(d.predicted.sizing.sigma_bytes < 950, "{d:?}");
        assert!(d.reason.contains("correction after step"), "{}", d.reason);
    }

    const STEERED_TF: &str = r#"{"domain":[0,1],"points":[[0,0,0,0,0],[1,1,0.5,0,0.8]]}"#;

    fn named(mut s: pb::StepSummary, scene_version: u64) -> pb::StepSummary {
        s.scene_version = scene_version;
        s.fields = vec!["u".into(), "v".into()];
        s
    }

    #[test]
    fn a_steered_scene_is_versioned_pushed_and_tuned_for_afresh_and_a_later_change_supersedes_it() {
        let dir = tempfile::tempdir().unwrap();
        let mut l = tuned(dir.path());
        let mut decisions = l.engine.subscribe();
        l.summary(1, named(summary(1, 3, 900, 1), 0));
        assert_eq!(l.engine.state().tracker.step_indices(), [0]);
        let reply = l
            .steer(pb::SteerRequest {
                tf_json: Some(STEERED_TF.into()),
                tf_name: Some("warm".into()),
                who: "test".into(),
                ..Default::default()
            })
            .unwrap();
        assert_eq!((reply.scene_version, reply.pm_version), (1, 2));
        assert_eq!(
            reply.from_step, 3,
            "two strides past the newest step (no node said `begun`)"
        );
        // Pushed: the P_M in force, carrying the scene.
        let m = decisions.try_recv().unwrap();
        assert_eq!((m.pm_version, m.resolution, m.from_step), (2, 64, 3));
        let scene = m.scene.unwrap();
        assert_eq!(scene.version, 1);
        assert_eq!(scene.tf_name.as_deref(), Some("warm"));
        assert!(m.reason.contains("scene 1 steered by test"), "{}", m.reason);
        {
            let s = l.engine.state();
            assert!(
                s.tracker.steps.is_empty(),
                "the old scene's steps are let go"
            );
            assert_eq!(s.steering.last().unwrap().standing, Standing::Pending);
            // Persisted: a restarted tuner carries the scene on.
            let back = State::load(dir.path()).unwrap().unwrap();
            assert_eq!(back.scene(), s.scene());
        }
        assert_eq!(l.engine.current().unwrap().scene.unwrap().version, 1);
        // Still under the old scene: neither characteristic nor a trigger.
        l.summary(1, named(summary(2, 40, 5000, 1), 0));
        assert!(l.dirty.is_none() && l.engine.state().tracker.steps.is_empty());
        // A second change before any step was made with the first supersedes it.
        let reply = l
            .steer(pb::SteerRequest {
                field: Some("v".into()),
                ..Default::default()
            })
            .unwrap();
        assert_eq!((reply.scene_version, reply.superseded), (2, vec![1]));
        let scene = decisions.try_recv().unwrap().scene.unwrap();
        assert_eq!(
            (
                scene.version,
                scene.field.as_deref(),
                scene.tf_name.as_deref()
            ),
            (2, Some("v"), Some("warm")),
            "cumulative: the transfer function stays"
        );
        // The first step under the new scene applies it and starts the tuning for it.
        l.summary(1, named(summary(4, 10, 700, 3), 2));
        let cause = &l.dirty.as_ref().unwrap().cause;
        assert_eq!(*cause, Cause::First);
        let st = l.engine.status();
        let standings: Vec<&str> = st.steering.iter().map(|r| r.state.as_str()).collect();
        assert_eq!(standings, ["superseded", "applied"]);
        assert_eq!(st.scene.unwrap().version, 2);
    }

    #[test]
    fn a_node_that_attaches_after_a_change_gets_the_decision_before_it_for_the_steps_before_its_switch(
    ) {
        use insitu_proto::pb::tuner_message::Msg as Down;
        let dir = tempfile::tempdir().unwrap();
        let mut l = tuned(dir.path());
        l.summary(1, named(summary(1, 3, 900, 1), 0));
        let reply = l
            .steer(pb::SteerRequest {
                field: Some("v".into()),
                ..Default::default()
            })
            .unwrap();
        assert!(reply.from_step > 0);
        let attach = |pm_version: u64| {
            let (tx, mut rx) = tokio::sync::mpsc::channel(16);
            let conn = l.engine.hub.connect("n", tx);
            l.engine.hello(
                conn,
                &pb::NodeHello {
                    pm_version,
                    ..Default::default()
                },
            );
            std::iter::from_fn(|| rx.try_recv().ok())
                .filter_map(|m| match m.ok()?.msg {
                    Some(Down::Decision(d)) => Some(d),
                    _ => None,
                })
                .map(|d| (d.pm_version, d.from_step, d.scene.map(|s| s.version)))
                .collect::<Vec<_>>()
        };
        // A restarted node: v1 for every step before the switch (no scene: the node's own),
        // then the steered v2 from its step.
        assert_eq!(attach(0), [(1, 0, None), (2, reply.from_step, Some(1))]);
        // A node that reconnects holding v1 needs only v2; one holding v2, nothing.
        assert_eq!(attach(1), [(2, reply.from_step, Some(1))]);
        assert_eq!(attach(2), []);
    }

    #[test]
    fn steering_refuses_what_it_cannot_apply_and_changes_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let mut l = tuned(dir.path());
        l.summary(1, named(summary(1, 3, 900, 1), 0));
        let before = l.engine.state().clone();
        let refused = |l: &mut Loop, req: pb::SteerRequest| l.steer(req).unwrap_err();
        let e = refused(
            &mut l,
            pb::SteerRequest {
                field: Some("w".into()),
                ..Default::default()
            },
        );
        assert_eq!(e.code(), tonic::Code::InvalidArgument);
        assert!(
            e.message().contains("\"w\" is not one of"),
            "{}",
            e.message()
        );
        let e = refused(
            &mut l,
            pb::SteerRequest {
                utility: Some("size:lots".into()),
                ..Default::default()
            },
        );
        assert!(e.message().starts_with("utility:"), "{}", e.message());
        assert_eq!(*l.engine.state(), before);
        // No node ever attached and no decision: no P_M to carry a scene.
        l.engine.state().decisions.clear();
        let e = refused(
            &mut l,
            pb::SteerRequest {
                tf_json: Some(STEERED_TF.into()),
                ..Default::default()
            },
        );
        assert_eq!(e.code(), tonic::Code::FailedPrecondition);
    }

    #[test]
    fn a_steered_utility_sets_the_budget_and_re_tunes_over_the_characteristic_steps() {
        let dir = tempfile::tempdir().unwrap();
        let mut l = tuned(dir.path());
        let reply = l
            .steer(pb::SteerRequest {
                utility: Some("size:2kB".into()),
                ..Default::default()
            })
            .unwrap();
        assert_eq!((reply.scene_version, reply.pm_version), (0, 0));
        assert!(
            reply.utility.contains("2.0 kB") || reply.utility.contains("2000"),
            "{}",
            reply.utility
        );
        assert_eq!(l.engine.status().sigma_target_bytes, 2000);
        assert!(matches!(
            l.dirty.as_ref().unwrap().cause,
            Cause::Steered { .. }
        ));
        // A restarted tuner keeps it.
        let state = State::load(dir.path()).unwrap().unwrap();
        assert_eq!(state.utility.as_deref(), Some("size:2kB"));
        let cfg = Config {
            state_dir: dir.path().to_owned(),
            utility: "size:1000".into(),
            ..Default::default()
        };
        let resolved = cfg.resolve().unwrap();
        let (engine, _rx) = Engine::new(cfg, resolved, state, |_, _| true);
        assert_eq!(engine.status().sigma_target_bytes, 2000);
    }

    #[test]
    fn a_newer_characteristic_step_cuts_a_running_tuning_short_but_not_twice_nor_the_first() {
        let cut = |decided: bool, cut_last: bool| {
            let dir = tempfile::tempdir().unwrap();
            let mut l = tuned(dir.path());
            if !decided {
                l.engine.state().decisions.clear();
            }
            l.cut_last = cut_last;
            l.engine.counters().tuning = true;
            // Far from step 0's histogram: characteristic.
            l.summary(1, summary(5, 40, 500, 1));
            assert!(l.dirty.is_some());
            l.engine.superseded.load(Ordering::SeqCst)
        };
        assert!(cut(true, false));
        assert!(!cut(true, true), "never twice in a row");
        assert!(!cut(false, false), "the first tuning runs to its decision");
    }

    #[test]
    fn a_budget_break_retunes_once_and_none_while_a_tuning_is_due() {
        let dir = tempfile::tempdir().unwrap();
        let mut l = tuned(dir.path());
        // σ 1 000 B ≥ σ_target 1 000 B: breaks the budget (strict, Eq. 1).
        l.summary(1, summary(1, 3, 1000, 1));
        assert!(matches!(
            l.dirty.as_ref().unwrap().cause,
            Cause::BrokeBudget { .. }
        ));
        l.dirty = None;
        // Breaking it again before the re-tuning has taken step 1 into account forces nothing.
        l.summary(2, summary(2, 3, 5000, 1));
        assert!(l.dirty.is_none());
        assert_eq!(l.engine.state().tracker.step_indices(), vec![0, 1]);
        // Steps made with an older version are not held against the budget.
        let dir = tempfile::tempdir().unwrap();
        let mut l = tuned(dir.path());
        l.summary(1, summary(1, 3, 5000, 0));
        assert!(l.dirty.is_none());
        // Nor while a tuning is pending: a new characteristic step is waiting for one.
        l.summary(2, summary(2, 40, 500, 1));
        let c = &l.dirty.as_ref().unwrap().cause;
        assert!(matches!(c, Cause::NewCharacter { .. }), "{c:?}");
        l.summary(3, summary(3, 3, 5000, 1));
        assert_eq!(l.engine.state().tracker.step_indices(), vec![0, 2]);
    }

    /// A step made with the tuned candidate (r 64, γ 0.01, planned at 900 B) and `sigma`
    /// bytes, made with `version`, in histogram bin 3.
    fn made(step: u64, sigma: u64, version: u64) -> pb::StepSummary {
        pb::StepSummary {
            resolution: 64,
            gamma: 0.01,
            ..summary(step, 3, sigma, version)
        }
    }

    /// A step whose σ is 1.5× what its decision planned is characteristic though its
    /// histogram is the characteristic step's and it is within the budget (a new character
    /// by structure); one at 1.44× is not; none while a tuning is due.
    #[test]
    fn a_step_far_over_its_plan_is_a_new_character_whatever_its_histogram() {
        let dir = tempfile::tempdir().unwrap();
        let mut l = tuned_for(dir.path(), "size:5000", 2);
        l.summary(1, made(1, 1300, 1));
        assert!(l.dirty.is_none(), "{:?}", l.dirty);
        l.summary(2, made(2, 1350, 1));
        let d = l.dirty.clone().unwrap();
        assert_eq!(
            (d.step, d.cause.clone()),
            (
                2,
                Cause::SizeMiss {
                    sigma_bytes: 1350,
                    planned_bytes: 900.0,
                    threshold: 1.5
                }
            )
        );
        assert_eq!(l.engine.state().tracker.step_indices(), vec![0, 2]);
        // The next step alike, while that tuning is due, changes nothing.
        l.summary(3, made(3, 4000, 1));
        assert_eq!(l.dirty.as_ref().map(|d| d.step), Some(2));
        assert_eq!(l.engine.state().tracker.step_indices(), vec![0, 2]);
    }

    /// A step made under a correction of the tuned decision that breaks the budget makes no
    /// tuning due (the next correction takes it up); one made with the tuned decision does.
    #[test]
    fn a_budget_broken_under_a_correction_is_left_to_the_corrections() {
        let dir = tempfile::tempdir().unwrap();
        let mut l = tuned(dir.path());
        {
            let mut s = l.engine.state();
            let mut d = s.current().unwrap().clone();
            d.pm_version = 2;
            d.candidate.gamma = 0.02;
            d.corrects = Some(1);
            d.predicted.sizing.sigma_bytes = 800;
            s.decisions.push(d);
        }
        l.summary(
            1,
            pb::StepSummary {
                gamma: 0.02,
                ..made(1, 1100, 2)
            },
        );
        assert!(l.dirty.is_none(), "{:?}", l.dirty);
        l.summary(2, made(2, 1100, 1));
        let d = l.dirty.clone().unwrap();
        assert!(
            matches!(&d.cause, Cause::BrokeBudget { why } if why.contains("σ 1100 B")),
            "{d:?}"
        );
    }

    /// A τ over τ_target re-tunes only as the `time_breaks`-th such step in a row (made with
    /// the version in force); a step within the budget between them starts the count again.
    #[test]
    fn a_time_break_retunes_only_when_it_repeats() {
        let timed = |step, tau_secs| pb::StepSummary {
            tau_secs,
            ..summary(step, 3, 500, 1)
        };
        let dir = tempfile::tempdir().unwrap();
        let mut l = tuned_for(dir.path(), "size:1000,time:0.05", 2);
        l.summary(1, timed(1, 0.08));
        assert!(l.dirty.is_none());
        l.summary(2, timed(2, 0.01));
        l.summary(3, timed(3, 0.05));
        assert!(l.dirty.is_none(), "one slow step after a fast one");
        l.summary(4, timed(4, 0.07));
        let t = l.dirty.as_ref().unwrap();
        assert_eq!(
            t.cause,
            Cause::BrokeBudget {
                why: "τ 0.0700 s ≥ τ_target 0.05 s, 2 steps in a row".into()
            }
        );
        assert_eq!(t.step, 4);
        assert_eq!(l.engine.state().tracker.step_indices(), vec![0, 4]);
        // Steps made with an older version neither count nor break a run.
        let dir = tempfile::tempdir().unwrap();
        let mut l = tuned_for(dir.path(), "size:1000,time:0.05", 2);
        l.summary(1, timed(1, 0.08));
        l.summary(
            2,
            pb::StepSummary {
                pm_version: 0,
                ..timed(2, 0.01)
            },
        );
        l.summary(3, timed(3, 0.09));
        assert_eq!(l.dirty.as_ref().map(|d| d.step), Some(3));
        // time_breaks = 1: every slow step re-tunes, as σ does.
        let dir = tempfile::tempdir().unwrap();
        let mut l = tuned_for(dir.path(), "time:0.05", 1);
        l.summary(1, timed(1, 0.06));
        let c = &l.dirty.as_ref().unwrap().cause;
        assert_eq!(
            c,
            &Cause::BrokeBudget {
                why: "τ 0.0600 s ≥ τ_target 0.05 s".into()
            }
        );
    }

    /// A decision applies from the first step on the stride that no node had begun when the
    /// newest step was summarised: one stride past it when one idle node serves the world,
    /// past the steps a node had begun, one stride more for several nodes, two strides
    /// without the nodes' `begun`; a late summary of an older step changes nothing.
    #[test]
    fn decisions_apply_from_the_first_step_no_node_had_begun() {
        let mut p = Progress::default();
        assert_eq!(p.decision_start(), 0);
        // An older node (no `begun`): two strides.
        assert_eq!(p.saw(2000, 0, 1), 2000);
        assert_eq!(p.decision_start(), 2002);
        // One node, idle after step 2100 (stride 100): the next step.
        assert_eq!(p.saw(2100, 2101, 1), 2100);
        assert_eq!(p.decision_start(), 2200);
        assert_eq!(p.saw(2000, 2001, 1), 2100, "another rank's older step");
        assert_eq!(p.decision_start(), 2200);
        // The node had begun step 2200 already: the one after.
        assert_eq!(p.saw(2100, 2201, 1), 2100);
        assert_eq!(p.decision_start(), 2300);
        // Two nodes summarised step 2200, neither had begun more: one stride of margin.
        p.saw(2200, 2201, 1);
        p.saw(2200, 2201, 2);
        assert_eq!(p.decision_start(), 2400);
        // Step indices are the nodes' to choose: a huge jump saturates, it does not wrap.
        assert_eq!(p.saw(u64::MAX - 1, u64::MAX, 1), u64::MAX - 1);
        assert_eq!(p.decision_start(), u64::MAX);
    }
}
