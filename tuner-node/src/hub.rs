//! The connected generator-nodes: their streams, which (step, rank) fields each holds, and the
//! trials and previews in flight. A node's disconnection fails its trials at once (their data is gone with
//! it) instead of letting them run into the timeout.

use crate::check::check_trial_result;
use insitu_proto::pb;
use insitu_proto::pb::tuner_message::Msg as Down;
use insitu_tuner::Candidate;
use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;
use tokio::sync::{mpsc, oneshot};
use tonic::Status;
use tracing::info;

/// The sending half of a node's stream.
pub type NodeTx = mpsc::Sender<Result<pb::TunerMessage, Status>>;

/// What a trial measures ([`Hub::request_trial`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TrialKind {
    /// σ and τ alone: a size probe.
    SizeProbe,
    /// σ, τ and the views' scores, τ timed on a generation of its own.
    Full,
    /// A full trial that may score the VDI its size probe left on the node (τ the probe's):
    /// under a size budget alone, where τ decides nothing.
    AfterProbe,
}

/// Why a trial failed.
#[derive(Clone, Debug, PartialEq)]
pub struct TrialFailure {
    /// What happened, naming the node or the step and rank.
    pub message: String,
    /// Whether the step's field is gone from a node that held it (the node disconnected or no
    /// longer holds it), rather than the trial failing there.
    pub step_lost: bool,
}

/// What a finished trial sends back: every rank's result, or why it failed.
pub type TrialReply = Result<Vec<pb::TrialResult>, TrialFailure>;

/// Why a trial could not be started.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum NotHeld {
    /// Some ranks of the step are held by no connected node.
    #[error("step {step}: {held} of {world_size} ranks are held by connected nodes")]
    Ranks {
        /// The step.
        step: u64,
        /// Ranks held.
        held: usize,
        /// Ranks of the step.
        world_size: u32,
    },
}

struct Node {
    id: String,
    tx: NodeTx,
}

struct Pending {
    asked: pb::TrialRequest,
    /// rank → the connection asked for it.
    ranks: BTreeMap<u32, u64>,
    conns: BTreeSet<u64>,
    results: Vec<pb::TrialResult>,
    reply: oneshot::Sender<TrialReply>,
}

/// What a finished preview sends back: every rank's frame, or why it failed.
pub type PreviewReply = Result<Vec<pb::PreviewFrame>, String>;

struct PendingPreview {
    /// rank → the connection asked for it.
    ranks: BTreeMap<u32, u64>,
    frames: Vec<pb::PreviewFrame>,
    reply: oneshot::Sender<PreviewReply>,
}

#[derive(Default)]
struct Inner {
    nodes: HashMap<u64, Node>,
    next_conn: u64,
    /// step → rank → connection holding it.
    holders: BTreeMap<u64, BTreeMap<u32, u64>>,
    pending: HashMap<u64, Pending>,
    previews: HashMap<u64, PendingPreview>,
}

impl Inner {
    /// Sends `m` to each connection of `conns` still connected (a full or closed stream
    /// drops it: the node is leaving).
    fn send_to(&self, conns: &BTreeSet<u64>, m: &Down) {
        for c in conns {
            if let Some(n) = self.nodes.get(c) {
                let _ = n.tx.try_send(msg(m.clone()));
            }
        }
    }

    /// rank → connection for every rank of `step`.
    ///
    /// # Errors
    /// [`NotHeld`] when some of its `world_size` ranks are held by no connected node.
    fn held_whole(&self, step: u64, world_size: u32) -> Result<BTreeMap<u32, u64>, NotHeld> {
        let ranks = self.holders.get(&step).cloned().unwrap_or_default();
        if ranks.len() < world_size as usize {
            return Err(NotHeld::Ranks {
                step,
                held: ranks.len(),
                world_size,
            });
        }
        Ok(ranks)
    }
}

/// The registry.
#[derive(Default)]
pub struct Hub {
    inner: Mutex<Inner>,
    next_trial: AtomicU64,
}

fn msg(m: Down) -> Result<pb::TunerMessage, Status> {
    Ok(pb::TunerMessage { msg: Some(m) })
}

impl Hub {
    fn inner(&self) -> std::sync::MutexGuard<'_, Inner> {
        self.inner.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Registers a node's stream; returns its connection number.
    pub fn connect(&self, id: &str, tx: NodeTx) -> u64 {
        let mut i = self.inner();
        i.next_conn += 1;
        let conn = i.next_conn;
        i.nodes.insert(
            conn,
            Node {
                id: id.to_owned(),
                tx,
            },
        );
        conn
    }

    /// Forgets a node: its holds, and its trials in flight fail. Returns its id.
    pub fn disconnect(&self, conn: u64) -> Option<String> {
        let mut i = self.inner();
        let node = i.nodes.remove(&conn)?;
        for ranks in i.holders.values_mut() {
            ranks.retain(|_, c| *c != conn);
        }
        i.holders.retain(|_, r| !r.is_empty());
        let failed: Vec<u64> = i
            .pending
            .iter()
            .filter(|(_, p)| p.conns.contains(&conn))
            .map(|(&id, _)| id)
            .collect();
        for id in failed {
            if let Some(p) = i.pending.remove(&id) {
                let _ = p.reply.send(Err(TrialFailure {
                    message: format!("node {} disconnected during trial {id}", node.id),
                    step_lost: true,
                }));
            }
        }
        let lost: Vec<u64> = i
            .previews
            .iter()
            .filter(|(_, p)| p.ranks.values().any(|&c| c == conn))
            .map(|(&id, _)| id)
            .collect();
        for id in lost {
            if let Some(p) = i.previews.remove(&id) {
                let _ = p.reply.send(Err(format!(
                    "node {} disconnected during the preview",
                    node.id
                )));
            }
        }
        Some(node.id)
    }

    /// Connected nodes.
    pub fn nodes(&self) -> usize {
        self.inner().nodes.len()
    }

    /// Records that `conn` holds `(step, rank)`.
    pub fn held(&self, conn: u64, step: u64, rank: u32) {
        self.inner()
            .holders
            .entry(step)
            .or_default()
            .insert(rank, conn);
    }

    /// Sends one message to one node (a full or closed stream drops it: the node is leaving).
    pub fn send(&self, conn: u64, m: Down) {
        if let Some(n) = self.inner().nodes.get(&conn) {
            let _ = n.tx.try_send(msg(m));
        }
    }

    /// Sends one message to every node.
    pub fn broadcast(&self, m: &Down) {
        for n in self.inner().nodes.values() {
            let _ = n.tx.try_send(msg(m.clone()));
        }
    }

    /// Claims (`keep`) or releases `step` on the nodes holding it; a release forgets it.
    pub fn hold(&self, step: u64, keep: bool) {
        let mut i = self.inner();
        let conns: BTreeSet<u64> = i
            .holders
            .get(&step)
            .map(|r| r.values().copied().collect())
            .unwrap_or_default();
        i.send_to(&conns, &Down::Hold(pb::HoldRequest { step, keep }));
        if !keep {
            i.holders.remove(&step);
        }
    }

    /// Asks the nodes holding `step` (all `world_size` ranks of it) to measure `c`.
    ///
    /// # Errors
    /// [`NotHeld`] when some rank is held by no connected node.
    pub fn request_trial(
        &self,
        step: u64,
        world_size: u32,
        c: Candidate,
        kind: TrialKind,
    ) -> Result<(u64, oneshot::Receiver<TrialReply>), NotHeld> {
        let mut i = self.inner();
        let ranks = i.held_whole(step, world_size)?;
        let id = self.next_trial.fetch_add(1, Ordering::Relaxed) + 1;
        let conns: BTreeSet<u64> = ranks.values().copied().collect();
        let req = pb::TrialRequest {
            trial_id: id,
            step,
            resolution: c.r,
            gamma: c.gamma,
            size_only: kind == TrialKind::SizeProbe,
            precision_bits: Some(c.precision.bits()),
            reuse_probe: kind == TrialKind::AfterProbe,
        };
        i.send_to(&conns, &Down::Trial(req));
        let (reply, rx) = oneshot::channel();
        i.pending.insert(
            id,
            Pending {
                asked: req,
                ranks,
                conns,
                results: Vec::new(),
                reply,
            },
        );
        Ok((id, rx))
    }

    /// A rank's result from `conn`; the trial completes when every rank has answered, or
    /// fails at the first error or bad result ([`check_trial_result`], a rank not asked of
    /// `conn` or answered twice).
    ///
    /// # Errors
    /// A message for the node when the trial is unknown (finished, abandoned or never asked)
    /// or the result is bad.
    pub fn trial_result(&self, conn: u64, r: pb::TrialResult) -> Result<(), String> {
        let mut i = self.inner();
        let Some(p) = i.pending.get_mut(&r.trial_id) else {
            return Err(format!(
                "trial {} is unknown (finished, abandoned after a timeout, or never asked)",
                r.trial_id
            ));
        };
        if !p.conns.contains(&conn) {
            return Err(format!("trial {} was not asked of this node", r.trial_id));
        }
        let id = r.trial_id;
        if !r.error.is_empty() {
            let failure = TrialFailure {
                message: format!("step {} rank {}: {}", r.step, r.rank, r.error),
                step_lost: r.not_held,
            };
            if r.not_held {
                if let Some(ranks) = i.holders.get_mut(&r.step) {
                    ranks.retain(|_, c| *c != conn);
                }
            }
            if let Some(p) = i.pending.remove(&id) {
                let _ = p.reply.send(Err(failure));
            }
            return Ok(());
        }
        let bad = check_trial_result(&r, &p.asked).err().or_else(|| {
            if p.ranks.get(&r.rank) != Some(&conn) {
                Some(format!(
                    "trial {id}: rank {} of step {} was not asked of this node",
                    r.rank, r.step
                ))
            } else if p.results.iter().any(|x| x.rank == r.rank) {
                Some(format!("trial {id}: rank {} answered twice", r.rank))
            } else {
                None
            }
        });
        if let Some(problem) = bad {
            if let Some(p) = i.pending.remove(&id) {
                let _ = p.reply.send(Err(TrialFailure {
                    message: format!("a bad result: {problem}"),
                    step_lost: false,
                }));
            }
            return Err(problem);
        }
        p.results.push(r);
        if p.results.len() >= p.ranks.len() {
            if let Some(p) = i.pending.remove(&id) {
                let _ = p.reply.send(Ok(p.results));
            }
        }
        Ok(())
    }

    /// The newest step every one of whose `world_size` ranks a connected node holds.
    pub fn newest_whole(&self, world_size: u32) -> Option<u64> {
        self.inner()
            .holders
            .iter()
            .rev()
            .find(|(_, r)| r.len() >= world_size as usize)
            .map(|(&step, _)| step)
    }

    /// Asks the nodes holding `req.step` (all `world_size` ranks of it) to render the
    /// preview `req` (its `preview_id` is given here).
    ///
    /// # Errors
    /// [`NotHeld`] when some rank is held by no connected node.
    pub fn request_preview(
        &self,
        mut req: pb::PreviewRequest,
        world_size: u32,
    ) -> Result<(u64, oneshot::Receiver<PreviewReply>), NotHeld> {
        let step = req.step.unwrap_or_default();
        let mut i = self.inner();
        let ranks = i.held_whole(step, world_size)?;
        let id = self.next_trial.fetch_add(1, Ordering::Relaxed) + 1;
        req.preview_id = id;
        let conns: BTreeSet<u64> = ranks.values().copied().collect();
        i.send_to(&conns, &Down::Preview(req));
        let (reply, rx) = oneshot::channel();
        i.previews.insert(
            id,
            PendingPreview {
                ranks,
                frames: Vec::new(),
                reply,
            },
        );
        Ok((id, rx))
    }

    /// A rank's preview frame from `conn`; the preview completes when every rank has
    /// answered, or fails at the first error, a rank not asked of `conn` or answered twice.
    ///
    /// # Errors
    /// A message for the node when the preview is unknown (finished or abandoned) or the
    /// frame answers what was not asked.
    pub fn preview_frame(&self, conn: u64, f: pb::PreviewFrame) -> Result<(), String> {
        let mut i = self.inner();
        let id = f.preview_id;
        let Some(p) = i.previews.get_mut(&id) else {
            return Err(format!(
                "preview {id} is unknown (finished, or abandoned after a timeout)"
            ));
        };
        let problem = if !f.error.is_empty() {
            Some(format!("step {} rank {}: {}", f.step, f.rank, f.error))
        } else if p.ranks.get(&f.rank) != Some(&conn) {
            Some(format!(
                "preview {id}: rank {} was not asked of this node",
                f.rank
            ))
        } else if p.frames.iter().any(|x| x.rank == f.rank) {
            Some(format!("preview {id}: rank {} answered twice", f.rank))
        } else {
            None
        };
        if let Some(problem) = problem {
            if let Some(p) = i.previews.remove(&id) {
                let _ = p.reply.send(Err(problem));
            }
            return Ok(());
        }
        p.frames.push(f);
        if p.frames.len() >= p.ranks.len() {
            if let Some(p) = i.previews.remove(&id) {
                let _ = p.reply.send(Ok(p.frames));
            }
        }
        Ok(())
    }

    /// Gives up on a preview (timeout); a late frame is then refused as unknown.
    pub fn abandon_preview(&self, id: u64) {
        self.inner().previews.remove(&id);
    }

    /// Gives up on a trial (timeout); a late result is then refused as unknown.
    pub fn abandon(&self, id: u64) {
        if self.inner().pending.remove(&id).is_some() {
            info!(trial = id, "abandoned a trial");
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Rank `rank`'s answer to trial `id` of step 5 at r 64, γ 0.01 (a good one unless
    /// `error`).
    fn result(id: u64, rank: u32, error: &str) -> pb::TrialResult {
        pb::TrialResult {
            trial_id: id,
            step: 5,
            rank,
            resolution: 64,
            gamma: 0.01,
            sigma_bytes: 100,
            error: error.into(),
            not_held: error.contains("not held"),
            ..Default::default()
        }
    }

    #[test]
    fn a_trial_needs_every_rank_and_fails_with_its_node() {
        let hub = Hub::default();
        let (tx, mut rx) = mpsc::channel(16);
        let (tx2, _rx2) = mpsc::channel(16);
        let a = hub.connect("a", tx);
        let b = hub.connect("b", tx2);
        let c = Candidate {
            r: 64,
            gamma: 0.01,
            precision: Default::default(),
        };
        hub.held(a, 5, 0);
        assert_eq!(
            hub.request_trial(5, 2, c, TrialKind::Full).unwrap_err(),
            NotHeld::Ranks {
                step: 5,
                held: 1,
                world_size: 2
            }
        );
        hub.held(b, 5, 1);
        let (id, mut done) = hub.request_trial(5, 2, c, TrialKind::Full).unwrap();
        assert!(matches!(
            rx.try_recv().unwrap().unwrap().msg,
            Some(Down::Trial(pb::TrialRequest {
                step: 5,
                size_only: false,
                ..
            }))
        ));
        assert!(hub.trial_result(a, result(999, 0, "")).is_err());
        hub.trial_result(a, result(id, 0, "")).unwrap();
        assert!(done.try_recv().is_err(), "one rank is missing");
        hub.trial_result(b, result(id, 1, "")).unwrap();
        assert_eq!(done.try_recv().unwrap().unwrap().len(), 2);
        // A node that goes away fails the trial at once, and its holds are forgotten.
        let (id, mut done) = hub.request_trial(5, 2, c, TrialKind::Full).unwrap();
        assert_eq!(hub.disconnect(b).as_deref(), Some("b"));
        let failure = done.try_recv().unwrap().unwrap_err();
        assert!(failure.step_lost && failure.message.contains("disconnected"));
        assert!(hub.trial_result(a, result(id, 0, "")).is_err());
        assert!(hub.request_trial(5, 2, c, TrialKind::Full).is_err());
        // An error from a rank fails the trial; an abandoned trial refuses late results.
        let (id, mut done) = hub.request_trial(5, 1, c, TrialKind::Full).unwrap();
        hub.trial_result(a, result(id, 0, "step 5 is not held"))
            .unwrap();
        let failure = done.try_recv().unwrap().unwrap_err();
        assert!(failure.step_lost && failure.message.contains("not held"));
        assert!(
            hub.request_trial(5, 1, c, TrialKind::Full).is_err(),
            "the refusing node no longer holds it"
        );
        hub.held(a, 5, 0);
        let (id, _done) = hub.request_trial(5, 1, c, TrialKind::Full).unwrap();
        hub.abandon(id);
        assert!(hub.trial_result(a, result(id, 0, "")).is_err());
        assert_eq!(hub.nodes(), 1);
    }

    #[test]
    fn a_bad_result_fails_the_trial_at_once_and_the_node_hears_why() {
        let hub = Hub::default();
        let (tx, _rx) = mpsc::channel(16);
        let (tx2, _rx2) = mpsc::channel(16);
        let a = hub.connect("a", tx);
        let b = hub.connect("b", tx2);
        let c = Candidate {
            r: 64,
            gamma: 0.01,
            precision: Default::default(),
        };
        hub.held(a, 5, 0);
        hub.held(b, 5, 1);
        let bad: [(u64, pb::TrialResult, &str); 4] = [
            // A NaN τ (JSON could not even persist it).
            (
                a,
                pb::TrialResult {
                    tau_secs: f64::NAN,
                    ..result(0, 0, "")
                },
                "tau_secs NaN",
            ),
            // Another candidate than the one asked.
            (
                a,
                pb::TrialResult {
                    gamma: 0.02,
                    ..result(0, 0, "")
                },
                "was asked",
            ),
            // A rank that another node holds.
            (
                a,
                result(0, 1, ""),
                "rank 1 of step 5 was not asked of this node",
            ),
            // The same rank twice (after a good first answer).
            (a, result(0, 0, ""), "rank 0 answered twice"),
        ];
        for (conn, r, needle) in bad {
            let (id, mut done) = hub.request_trial(5, 2, c, TrialKind::Full).unwrap();
            let r = pb::TrialResult { trial_id: id, ..r };
            if needle.contains("twice") {
                hub.trial_result(conn, r.clone()).unwrap();
            }
            let e = hub.trial_result(conn, r).unwrap_err();
            assert!(e.contains(needle), "{needle}: {e}");
            let failure = done.try_recv().unwrap().unwrap_err();
            assert!(
                failure.message.contains(needle) && !failure.step_lost,
                "{failure:?}"
            );
            // The trial is over: the other rank's late answer is refused as unknown.
            assert!(hub.trial_result(b, result(id, 1, "")).is_err());
        }
    }
}
