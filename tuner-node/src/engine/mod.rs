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
    /// Of `decisions`, provisional ones before the first tuning's (a world spread over nodes).
    pub provisional: u64,
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
    /// The first step past every step any node had received, as its summaries said.
    received: u64,
    /// Every connection that has summarised a step: a world served by several nodes may have
    /// the newest step summarised by one of them only.
    summarising: std::collections::BTreeSet<u64>,
}

/// Where several nodes serve a world, the strides a provisional decision applies beyond the
/// steps they had received: what the simulation may push while it travels to every node.
const LATENCY_STRIDES: u64 = 4;

impl Progress {
    /// Records a summarised step from connection `conn`, whose node had not begun step
    /// `begun` (0: unknown); returns the newest step.
    fn saw(&mut self, step: u64, begun: u64, received: u64, conn: u64) -> u64 {
        self.received = self.received.max(received);
        self.summarising.insert(conn);
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

    /// Where a decision made now applies for a world that may be in a burst of steps (the
    /// provisional decisions, made right after a spread world's first step): as
    /// [`Self::decision_start`], and where several nodes have summarised steps, past every
    /// step any of them had received (a node may begin those before the decision reaches it)
    /// and [`LATENCY_STRIDES`] more for what is pushed while the decision travels.
    pub(crate) fn spread_start(&self) -> u64 {
        let start = self.decision_start();
        let Some(n) = self.newest else { return start };
        if self.summarising.len() < 2 {
            return start;
        }
        let stride = self.stride.max(1);
        let received = self.received.saturating_sub(n).div_ceil(stride);
        let past = n.saturating_add(stride.saturating_mul(received));
        start
            .max(past)
            .saturating_add(stride.saturating_mul(LATENCY_STRIDES))
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
                    resolved.budgets(),
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
        *self.control() = Controller::new(r.budgets(), self.cfg.headroom, r.grid.clone());
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

    /// Where a provisional decision made now applies (see [`Progress::spread_start`]).
    pub(crate) fn spread_start(&self) -> u64 {
        self.progress
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .spread_start()
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
            c.provisional += u64::from(d.provisional);
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
    pub fn utility_description(&self) -> String {
        self.resolved().utility.describe()
    }

    /// The budget the nodes keep until the first decision ([`pb::NodeBudget`]).
    pub fn node_budget(&self) -> pb::NodeBudget {
        let (sigma_bytes, tau_secs) = self.resolved().budgets().to_wire();
        pb::NodeBudget {
            sigma_bytes,
            tau_secs,
            utility_description: self.utility_description(),
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
        let resolved = self.resolved();
        let (sigma_target_bytes, tau_target_secs) = resolved.budgets().to_wire();
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
            utility_description: self.utility_description(),
            tuning: c.tuning,
            size_probes: c.size_probes,
            tunings_infeasible: c.tunings_infeasible,
            corrections: c.corrections,
            provisional_decisions: c.provisional,
            tunings_superseded: c.tunings_superseded,
            quality_reports: c.quality_reports,
            trial_cpu_secs: c.trial_cpu_secs,
            size_probe_cpu_secs: c.size_probe_cpu_secs,
            sigma_target_bytes,
            tau_target_secs,
            q_target_db: match resolved.spec {
                UtilitySpec::Quality(q) => q,
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
    /// The connections (nodes) whose summaries these are.
    nodes: Vec<u64>,
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
    /// The last step made characteristic by σ evidence, with the version and `P_M` it was
    /// made with and its σ: while the tuning for it is due or running, a later step made
    /// with the same `P_M` far over this σ is a change of character again
    /// ([`crate::trigger::Cause::SizeJump`]).
    missed: Option<Missed>,
}

/// A step made characteristic because its σ missed its plan ([`Loop::missed`]).
#[derive(Clone, Copy, Debug, PartialEq)]
struct Missed {
    step: u64,
    pm_version: u64,
    candidate: Candidate,
    sigma_bytes: u64,
}

/// How a production step broke the budget.
enum Break {
    /// σ ≥ σ_target.
    Size(String),
    /// τ ≥ τ_target.
    Time(String),
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

/// A candidate with nothing measured of it (the prediction of a steering or provisional decision: σ and τ 0, q NaN).
pub(crate) fn unmeasured(c: Candidate) -> insitu_tuner::Measurement {
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
            missed: None,
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
                    // A tuning that decided with no newer one due has taken the missed step in.
                    if matches!(done, Some((true, _))) && l.dirty.is_none() {
                        l.missed = None;
                    }
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

mod production;
mod provisional;
mod steering;
#[cfg(test)]
mod tests;
