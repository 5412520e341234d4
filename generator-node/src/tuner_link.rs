//! The link to the tuner service (docs/conventions.md, "The system"): the node dials out (compute nodes
//! often accept no inbound connections) and keeps one `Attach` stream open, reconnecting with
//! back-off. Up the stream go a summary per production step and the results of trials; down it
//! come claims on held fields, trial requests and P_M decisions.
//!
//! Trials run at lower priority than production: production and trials take turns on one
//! compute lane, and a trial starts only when no production step waits in the queue, or, when
//! production alone keeps the node busy (exactly when a cheaper P_M is most needed), after
//! `trial_interleave` production steps since the last trial. So a step waits for one trial at
//! most, and under load trials take at most one turn in `trial_interleave + 1`. A trial's CPU
//! time is counted on the compute pool while it holds the lane ([`crate::cpu`]). Production
//! VDIs keep the P_M in force until a decision arrives; it applies from its `from_step`, or
//! from the node's first step not begun if that is later ([`apply_decision`]). Each summary
//! says which step the node has not begun yet, so that the tuner can name the next one.

use crate::hold::HeldStep;
use crate::shared::Shared;
use crate::tuning::Tuning;
use insitu_core::evaluate::{
    evaluate, evaluate_probed, evaluate_sized, generate_encoded, render_references,
};
use insitu_core::{Precision, Raycaster, VdiParams};
use insitu_proto::pb;
use insitu_proto::pb::node_message::Msg as Up;
use insitu_proto::pb::tuner_client::TunerClient;
use insitu_proto::pb::tuner_message::Msg as Down;
use insitu_proto::peer::{error_chain, Backoff, Peer};
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::sync::mpsc::{self, error::TrySendError};
use tokio_stream::wrappers::ReceiverStream;
use tracing::{info, warn};

/// Applies a tuner's decision to the node's settings ([`crate::settings::decided`]), from its
/// `from_step` or the first step no rank of which this node has begun, whichever is later:
/// every rank of a step keeps the `P_M` and scene its first rank was made with, and nodes
/// agree on the step (see `PmDecision`).
///
/// # Errors
/// As [`crate::settings::decided`].
pub fn apply_decision(shared: &Shared, d: &pb::PmDecision) -> Result<(), String> {
    let mut g = shared.generation.write().unwrap_or_else(|e| e.into_inner());
    let begun = shared.begun.load(Ordering::SeqCst);
    let next = crate::settings::decided(&g, d, begun)?;
    if next.scene_version != g.scene_version {
        info!(scene_version = next.scene_version, from_step = next.from_step, tf = ?next.tf.as_ref().map(|t| &t.name), field = ?next.field, "applying the steered scene");
    }
    info!(
        pm_version = d.pm_version,
        from_step = next.from_step,
        r = next.params.resolution,
        gamma = next.params.gamma,
        old_r = g.params.resolution,
        old_gamma = g.params.gamma,
        "applying the tuner's P_M"
    );
    *g = next;
    drop(g);
    shared.save_run();
    Ok(())
}

/// Measures one candidate on one held rank of a step (Alg. 1, lines 11–18, with the same
/// scoring code as the viz-node: [`insitu_core::evaluate::score_views`]). The step's
/// reference frames are rendered on its first trial and kept. A size probe
/// (`size_only`) generates and compresses only.
fn run_trial(
    shared: &Shared,
    tuning: &Tuning,
    rank: u32,
    h: HeldStep,
    req: &pb::TrialRequest,
) -> pb::TrialResult {
    let t = Instant::now();
    let mut out = pb::TrialResult {
        trial_id: req.trial_id,
        step: req.step,
        rank,
        resolution: req.resolution,
        gamma: req.gamma,
        ..Default::default()
    };
    if let Err(e) = measure(shared, tuning, rank, &h, req, &mut out) {
        out.error = e;
    }
    out.trial_secs = t.elapsed().as_secs_f64();
    tracing::debug!(
        step = out.step,
        rank,
        r = out.resolution,
        gamma = out.gamma,
        size_only = req.size_only,
        sigma = out.sigma_bytes,
        tau = out.tau_secs,
        trial_secs = out.trial_secs,
        error = %out.error,
        "trial measured"
    );
    out
}

/// [`run_trial`]'s measurement of `req` on the held step `h`, written into `out`: σ, τ and
/// the supersegments, and unless `size_only` the views' MSE and q, SSIM and the render time.
///
/// # Errors
/// The failure, in words (a bad `P_M`, the backend's, the codec's).
fn measure(
    shared: &Shared,
    tuning: &Tuning,
    rank: u32,
    h: &HeldStep,
    req: &pb::TrialRequest,
    out: &mut pb::TrialResult,
) -> Result<(), String> {
    let raycaster = Raycaster::new(&h.volume, &h.tf.tf, h.raycast).map_err(|e| e.to_string())?;
    let scene = shared
        .backend
        .prepare(&raycaster)
        .map_err(|e| e.to_string())?;
    let params = VdiParams {
        resolution: req.resolution,
        gamma: req.gamma,
        precision: match req.precision_bits {
            Some(bits) => Precision::from_bits(bits).map_err(|e| e.to_string())?,
            None => h.precision,
        },
    };
    let tf = h.tf.identity();
    let mut spare = tuning.spare.lock().unwrap_or_else(|e| e.into_inner());
    let this = Some((req.step, rank, params));
    let probed = std::mem::take(&mut spare.probed) == this && req.reuse_probe;
    let size = if req.size_only {
        let size = generate_encoded(&scene, &h.camera, params, h.codec, tf, &mut spare.vdi)
            .map_err(|e| e.to_string())?
            .1;
        spare.probed = this;
        tuning.holds.set_sizing((req.step, rank), params, size);
        size
    } else {
        let refs = references(tuning, &scene, (req.step, rank), h, req.resolution, out)?;
        let views = &h.view_angles_deg;
        // A candidate probed on this step already: its σ is known, so its VDI is scored
        // without being encoded and decoded again (the codec is lossless), and where the
        // probe was the last trial and the tuner lets its τ stand, without being generated
        // again.
        let known = h.sizes.get(&crate::hold::size_key(params));
        let (e, _) = match (known, &mut spare.vdi) {
            (Some(&known), Some(vdi)) if probed => {
                let key = (params, h.codec);
                evaluate_probed(&scene, &h.camera, key, views, &refs, vdi, known)
            }
            (Some(&known), vdi) => evaluate_sized(
                &scene, &h.camera, params, h.codec, views, &refs, tf, vdi, known,
            ),
            (None, vdi) => evaluate(&scene, &h.camera, params, h.codec, views, &refs, tf, vdi),
        }
        .map_err(|e| e.to_string())?;
        out.tau_render_secs = e.tau_render_secs;
        out.view_mse = e.views.iter().map(|v| v.mse).collect();
        out.view_q_db = e.views.iter().map(|v| v.q_db).collect();
        out.ssim = insitu_core::evaluate::mean_ssim(&e.views);
        e.sizing
    };
    out.sigma_bytes = size.sigma_bytes;
    out.supersegments = size.supersegments;
    out.tau_secs = size.tau_secs;
    out.tau_compress_secs = size.tau_compress_secs;
    Ok(())
}

/// The reference frames of held step `key` at its reference size (`resolution` where the
/// step sets none): those kept from an earlier trial, else rendered now, kept, and their
/// time written to `out.reference_secs`.
///
/// # Errors
/// The backend's failure, in words.
fn references(
    tuning: &Tuning,
    scene: &insitu_core::backend::PreparedVolume,
    key: (u64, u32),
    h: &HeldStep,
    resolution: u32,
    out: &mut pb::TrialResult,
) -> Result<Arc<Vec<insitu_core::Image>>, String> {
    let side = if h.reference_size == 0 {
        resolution
    } else {
        h.reference_size
    };
    if let Some(r) = h.references.get(&side) {
        return Ok(r.clone());
    }
    let t = Instant::now();
    let r = Arc::new(
        render_references(scene, &h.camera, &h.view_angles_deg, side).map_err(|e| e.to_string())?,
    );
    out.reference_secs = t.elapsed().as_secs_f64();
    tuning.holds.set_references(key, side, r.clone());
    Ok(r)
}

/// Runs trial requests one at a time, after production.
async fn trials(
    shared: Arc<Shared>,
    tuning: Arc<Tuning>,
    mut requests: mpsc::Receiver<(u64, pb::TrialRequest)>,
    results: mpsc::Sender<(u64, pb::TrialResult)>,
) {
    while let Some((epoch, req)) = requests.recv().await {
        if epoch != tuning.epoch.load(Ordering::Relaxed) {
            continue; // asked on a stream that is gone: the tuner abandoned it
        }
        let ranks = tuning.holds.ranks(req.step);
        if ranks.is_empty() {
            let error = format!(
                "step {} is not held by this node (released or never held)",
                req.step
            );
            let not_held = pb::TrialResult {
                not_held: true,
                ..refusal(&req, error)
            };
            let _ = results.send((epoch, not_held)).await;
            continue;
        }
        for (rank, held) in ranks {
            // Production first: wait while steps are queued (unless production has had its
            // `interleave` turns), then take the lane.
            let turn = |t: &Tuning| {
                t.interleave > 0 && t.since_trial.load(Ordering::Relaxed) >= t.interleave
            };
            while !shared.queue.is_empty() && !turn(&tuning) {
                tokio::time::sleep(Duration::from_millis(10)).await;
            }
            let _lane = shared.lane.lock().await;
            tuning.since_trial.store(0, Ordering::Relaxed);
            let (s, t, r) = (shared.clone(), tuning.clone(), req);
            let result = tokio::task::spawn_blocking(move || {
                let (mut result, cpu) =
                    crate::cpu::on_pool_counted(&s.pool, || run_trial(&s, &t, rank, held, &r));
                result.trial_cpu_secs = cpu;
                s.stats.update(|c| c.trial_cpu_secs += cpu);
                result
            })
            .await
            .unwrap_or_else(|e| pb::TrialResult {
                trial_id: req.trial_id,
                step: req.step,
                rank,
                error: format!("trial task failed: {e}"),
                ..Default::default()
            });
            let _ = results.send((epoch, result)).await;
        }
    }
}

/// Acts on one message from the tuner (of stream `epoch`) and returns the reply it needs now:
/// a hold answered; a trial queued for the worker, or refused at once when more than
/// `TRIAL_BACKLOG` wait (the tuner fails that trial) instead of queued without bound; a
/// decision applied or refused, and acknowledged either way; a preview rendered
/// ([`crate::preview`]), its frames sent to `previews`.
fn answer(
    shared: &Arc<Shared>,
    tuning: &Arc<Tuning>,
    trial_tx: &mpsc::Sender<(u64, pb::TrialRequest)>,
    previews: &mpsc::Sender<pb::PreviewFrame>,
    epoch: u64,
    m: Option<Down>,
) -> Option<Up> {
    match m? {
        Down::Preview(p) => {
            // Interactive and rare: rendered at once beside production, not queued behind it.
            let (tuning, tx) = (tuning.clone(), previews.clone());
            tokio::task::spawn_blocking(move || {
                for f in crate::preview::render(&tuning.holds, &p) {
                    if tx.blocking_send(f).is_err() {
                        break;
                    }
                }
            });
            None
        }
        Down::Hold(h) => {
            tuning.holds.answer(h.step, h.keep);
            None
        }
        Down::Trial(t) => match trial_tx.try_send((epoch, t)) {
            Err(TrySendError::Full((_, t))) => Some(Up::Trial(refusal(
                &t,
                format!("{TRIAL_BACKLOG} trials already wait on this node"),
            ))),
            _ => None,
        },
        Down::Decision(d) => {
            if d.provisional {
                tuning.correction.provisional(&d);
            }
            let error = apply_decision(shared, &d).err().unwrap_or_default();
            if !error.is_empty() {
                warn!(%error, "refused a decision");
            }
            let ack = pb::DecisionAck {
                pm_version: d.pm_version,
                error,
            };
            Some(Up::Ack(ack))
        }
        Down::Error(e) => {
            warn!(error = %e.message, "the tuner refused a message");
            None
        }
        Down::Budget(b) => {
            tuning.correction.set_budget(b);
            None
        }
    }
}

/// The result of a trial `req` that is not run, saying why.
fn refusal(req: &pb::TrialRequest, error: String) -> pb::TrialResult {
    pb::TrialResult {
        trial_id: req.trial_id,
        step: req.step,
        resolution: req.resolution,
        gamma: req.gamma,
        error,
        ..Default::default()
    }
}

/// Trials waiting on a node at most (a tuner keeps a few in flight, paced by its trial
/// budget); more are answered with an error at once.
const TRIAL_BACKLOG: usize = 64;

/// The dialling side of the stream.
pub struct Link {
    peer: Peer,
    max_backoff: Duration,
    node_id: String,
}

impl Link {
    /// A link to the tuner `peer`.
    pub fn new(peer: Peer, max_backoff: Duration, node_id: String) -> Self {
        Self {
            peer,
            max_backoff,
            node_id,
        }
    }

    /// Keeps the stream up until the node shuts down (the task is aborted then).
    pub async fn run(
        self,
        shared: Arc<Shared>,
        tuning: Arc<Tuning>,
        mut summaries: mpsc::Receiver<pb::StepSummary>,
    ) {
        let (trial_tx, trial_rx) = mpsc::channel(TRIAL_BACKLOG);
        let (result_tx, mut result_rx) = mpsc::channel(TRIAL_BACKLOG);
        tokio::spawn(trials(shared.clone(), tuning.clone(), trial_rx, result_tx));
        let mut backoff = Backoff::new(self.max_backoff);
        loop {
            let epoch = tuning.epoch.fetch_add(1, Ordering::Relaxed) + 1;
            let r = self
                .session(
                    &shared,
                    &tuning,
                    &mut summaries,
                    &trial_tx,
                    &mut result_rx,
                    epoch,
                )
                .await;
            let was = tuning.connected();
            tuning.set_connected(false);
            match r {
                Ok(()) => return, // the node is shutting down
                Err(e) if was => {
                    warn!(uri = %self.peer.uri(), error = %e, "tuner stream lost; keeping the current P_M and reconnecting");
                    backoff.reset();
                }
                Err(e) => tracing::debug!(uri = %self.peer.uri(), error = %e, "tuner unreachable"),
            }
            backoff.wait().await;
        }
    }

    /// What this node says first on a stream: its identity, the `P_M` in force, and the
    /// steps it still holds for trials from before a reconnection.
    fn hello(&self, shared: &Shared, tuning: &Tuning) -> pb::NodeHello {
        let g = shared.generation();
        pb::NodeHello {
            node_id: self.node_id.clone(),
            pm_version: g.pm_version,
            resolution: g.params.resolution,
            gamma: g.params.gamma,
            precision_bits: g.params.precision.bits(),
            held: tuning
                .holds
                .claimed_after_reconnect()
                .into_iter()
                .map(|(step, rank)| pb::StepRank { step, rank })
                .collect(),
        }
    }

    async fn session(
        &self,
        shared: &Arc<Shared>,
        tuning: &Arc<Tuning>,
        summaries: &mut mpsc::Receiver<pb::StepSummary>,
        trial_tx: &mpsc::Sender<(u64, pb::TrialRequest)>,
        result_rx: &mut mpsc::Receiver<(u64, pb::TrialResult)>,
        epoch: u64,
    ) -> Result<(), String> {
        let channel = self
            .peer
            .connect()
            .await
            .map_err(|e| format!("tuner {}: {}", self.peer.uri(), error_chain(&e)))?;
        let mut client = TunerClient::with_interceptor(channel, self.peer.auth());
        let (out, out_rx) = mpsc::channel::<pb::NodeMessage>(256);
        let hello = self.hello(shared, tuning);
        let send = |m: Up| pb::NodeMessage { msg: Some(m) };
        out.send(send(Up::Hello(hello)))
            .await
            .map_err(|e| e.to_string())?;
        let mut incoming = client
            .attach(ReceiverStream::new(out_rx))
            .await
            .map_err(|e| format!("tuner {}: {}", self.peer.uri(), e.message()))?
            .into_inner();
        tuning.set_connected(true);
        info!(uri = %self.peer.uri(), "connected to the tuner");
        let closed = |_| "tuner stream closed".to_owned();
        let (previews, mut preview_rx) = mpsc::channel(16);
        loop {
            tokio::select! {
                s = summaries.recv() => match s {
                    Some(s) => out.send(send(Up::Summary(s))).await.map_err(closed)?,
                    None => return Ok(()),
                },
                Some((e, r)) = result_rx.recv() => {
                    if e == epoch {
                        out.send(send(Up::Trial(r))).await.map_err(closed)?;
                    }
                }
                Some(f) = preview_rx.recv() => out.send(send(Up::Preview(f))).await.map_err(closed)?,
                m = incoming.message() => {
                    let m = m.map_err(|e| e.message().to_owned())?.ok_or("the tuner ended the stream")?;
                    if let Some(reply) = answer(shared, tuning, trial_tx, &previews, epoch, m.msg) {
                        out.send(send(reply)).await.map_err(closed)?;
                    }
                }
            }
        }
    }
}
