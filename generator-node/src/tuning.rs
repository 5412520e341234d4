//! The tuner's side of a node's state ([`Tuning`]): the fields held for trials, the
//! summaries waiting to go up, whether the stream is up, and the turn-taking of trials with
//! production. [`crate::tuner_link`] acts on it.

use crate::hold::{HeldStep, Holds};
use crate::stats::Stats;
use insitu_proto::pb;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use tokio::sync::mpsc;
use tracing::warn;

/// Summaries waiting to go up; when the tuner is slow, newer summaries are dropped (logged)
/// rather than production waiting.
const SUMMARY_BACKLOG: usize = 1024;

/// The last trial's VDI, and what made it when that was a size probe.
#[derive(Default)]
pub(crate) struct TrialSpare {
    /// The VDI, or none before the first trial.
    pub(crate) vdi: Option<insitu_core::vdi::Vdi>,
    /// The held step (step, rank) and `P_M` of the size probe that made `vdi`; `None` when
    /// a full trial made it (or nothing has). A full trial of the same candidate scores it
    /// without generating it again ([`insitu_core::evaluate::evaluate_probed`]).
    pub(crate) probed: Option<(u64, u32, insitu_core::VdiParams)>,
}

/// The tuner side of a node's shared state.
pub struct Tuning {
    /// Fields held for trials.
    pub holds: Holds,
    pub(crate) summaries: mpsc::Sender<pb::StepSummary>,
    /// The node's counters; `tuner_connected` says whether the stream is up.
    pub(crate) stats: Arc<Stats>,
    /// Connection number; trial results of an older connection are discarded.
    pub(crate) epoch: AtomicU64,
    /// Production steps since the last trial.
    pub(crate) since_trial: AtomicU64,
    /// Under load, one trial per this many production steps (0: only when idle).
    pub(crate) interleave: u64,
    /// The last trial's VDI, whose allocations the next trial reuses, as production reuses
    /// the last step's: a trial's τ is then what production pays
    /// ([`insitu_core::evaluate::generate_encoded`]). Trials run one at a time.
    pub(crate) spare: Mutex<TrialSpare>,
    /// The tuner's budget, kept by the node until the first decision ([`crate::correct`]).
    pub correction: crate::correct::Correction,
}

impl Tuning {
    /// The state and the receiving end of the summaries (for [`crate::tuner_link::Link::run`]).
    pub fn new(
        hold_bytes: u64,
        interleave: u64,
        stats: Arc<Stats>,
    ) -> (Self, mpsc::Receiver<pb::StepSummary>) {
        let (summaries, rx) = mpsc::channel(SUMMARY_BACKLOG);
        (
            Self {
                holds: Holds::new(hold_bytes),
                summaries,
                stats,
                epoch: AtomicU64::new(0),
                since_trial: AtomicU64::new(0),
                interleave,
                spare: Mutex::new(TrialSpare::default()),
                correction: Default::default(),
            },
            rx,
        )
    }

    /// Whether the stream to the tuner is up.
    pub fn connected(&self) -> bool {
        self.stats.get().tuner_connected
    }

    pub(crate) fn set_connected(&self, up: bool) {
        self.stats.update(|c| c.tuner_connected = up);
    }

    /// After every production step, with its summary and field when the tuner listens (see
    /// [`crate::work::for_tuner`]), the first step no rank of which the node has begun and the
    /// first past every step it has received:
    /// holds the field (when there is room) and sends the summary.
    pub fn after_step(
        &self,
        for_tuner: Option<(pb::StepSummary, HeldStep)>,
        begun: u64,
        received: u64,
    ) {
        self.since_trial.fetch_add(1, Ordering::Relaxed);
        let Some((mut summary, held)) = for_tuner else {
            return;
        };
        summary.held = self.holds.offer((summary.step, summary.rank), held);
        summary.begun = begun;
        summary.received = received;
        if let Err(e) = self.summaries.try_send(summary) {
            warn!(error = %e, "step summary not sent to the tuner (backlog full)");
        }
    }
}
