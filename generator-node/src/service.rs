//! The `Generator` gRPC service: receive steps into the bounded queue, take configuration
//! pushed by a tuner or an operator, report status, flush.

use crate::config::Generation;
use crate::ingest::{check_header, RawStep};
use crate::queue::BoundedQueue;
use crate::stats::Stats;
use insitu_core::raycast::RaycastParams;
use insitu_core::{TransferFunction, VdiParams};
use insitu_proto::convert::{camera_from_pb, codec_from_pb};
use insitu_proto::pb::generator_server::Generator;
use insitu_proto::{chunk, pb};
use std::sync::{Arc, RwLock};
use std::time::Duration;
use tonic::{Request, Response, Status, Streaming};
use tracing::{info, info_span, Instrument};

/// Largest transfer function accepted over the wire, bytes.
pub const MAX_TF_JSON: usize = 1 << 20;

/// State shared by the service, the worker and the shipper.
pub struct Shared {
    /// Steps waiting for generation.
    pub queue: BoundedQueue<RawStep>,
    /// Current settings (a worker takes a snapshot per step).
    pub generation: RwLock<Generation>,
    /// Counters.
    pub stats: Arc<Stats>,
    /// Largest accepted step, bytes.
    pub max_step_bytes: u64,
    /// Whether a viz-node is configured.
    pub shipping: bool,
    /// Finished VDIs waiting to be shipped.
    pub outbox: Arc<BoundedQueue<crate::work::Product>>,
    /// Where VDIs and reference frames are made.
    pub backend: insitu_core::Backend,
    /// Production steps and the tuner's trials take turns on this lane.
    pub lane: tokio::sync::Mutex<()>,
    /// The link to the tuner, when one is configured.
    pub tuning: Option<Arc<crate::tuning::Tuning>>,
    /// `ship_failed` as of the last `Flush`: a flush reports the refusals since the previous.
    pub ship_failed_reported: std::sync::atomic::AtomicU64,
    /// The first step index no rank of which this node has begun to generate: a tuner's
    /// decision applies from it at the earliest.
    pub begun: std::sync::atomic::AtomicU64,
    /// The durable spool, when configured.
    pub spool: Option<Arc<crate::spool::Spool>>,
    /// This run's identity (`PushReply.epoch`).
    pub epoch: u64,
    /// Where the world's default transfer function is agreed (the viz-node), when one is
    /// configured and the config names no transfer function.
    pub scene: Option<Arc<crate::scene::SceneLink>>,
    /// The node's own worker threads (`threads` in the config); `None`: rayon's global pool.
    pub pool: Option<Arc<rayon::ThreadPool>>,
    /// Fields of settled steps (generated or dropped): the next pushes are received into
    /// their memory (beyond what the queue counts: one, and a second within the queue's
    /// `max_bytes`; see [`crate::spare`]).
    pub spare_fields: crate::spare::SpareFields,
}

impl Shared {
    /// Runs CPU work (generation, reference frames, trials) on the node's worker threads
    /// ([`crate::work::on_pool`]).
    pub fn compute<R: Send>(&self, f: impl FnOnce() -> R + Send) -> R {
        crate::work::on_pool(self.pool.as_deref(), f)
    }

    /// A snapshot of the current settings.
    pub fn generation(&self) -> Generation {
        self.generation
            .read()
            .unwrap_or_else(|e| e.into_inner())
            .clone()
    }

    /// The status message.
    pub fn status(&self) -> pb::GeneratorStatus {
        let c = self.stats.get();
        let g = self.generation();
        pb::GeneratorStatus {
            queue_depth: self.queue.len() as u32,
            queue_limit: self.queue.max_items() as u32,
            queue_bytes: self.queue.bytes(),
            queue_policy: self.queue.policy().name().to_owned(),
            outbox_depth: self.outbox.len() as u32,
            steps_received: c.received,
            steps_generated: c.generated,
            steps_shipped: c.shipped,
            dropped_queue: c.dropped_queue,
            dropped_outbox: c.dropped_outbox,
            failed: c.failed,
            resolution: g.params.resolution,
            gamma: g.params.gamma,
            viz_connected: c.viz_connected,
            pm_version: g.pm_version,
            tuner_connected: c.tuner_connected,
            ship_failed: c.ship_failed,
            ship_error: self.stats.ship_error(),
            epoch: self.epoch,
            recovered: c.recovered,
            spooled_bytes: self.spool.as_ref().map_or(0, |s| s.used()),
            limit_retries: c.limit_retries,
            limit_retry_secs: c.limit_retry_secs,
        }
    }

    /// One pushed step, its chunks converted into the brick's storage as they arrive (no
    /// copy of the bytes), into the spare field of an earlier step where there is one.
    ///
    /// # Errors
    /// The stream's rules broken ([`chunk::receive_into`]: a bad header, a step over
    /// `max_step_bytes`, chunks that do not fill it), or a transport error, as a status.
    async fn receive(&self, mut stream: Streaming<pb::StepChunk>) -> Result<RawStep, Status> {
        let (_, (info, field)) = chunk::receive_into(
            &mut stream,
            self.max_step_bytes,
            |h: &pb::StepHeader| {
                let info = check_header(h)?;
                Ok((info, info.assembler(self.spare_fields.take())))
            },
            |(_, field), bytes| field.push(bytes),
        )
        .await?;
        info.with_field(field)
    }

    /// With a spool: `raw` on disk (fsync'd when durable) before it is acknowledged, and its
    /// spool name recorded in it.
    ///
    /// # Errors
    /// `RESOURCE_EXHAUSTED` when the spool has no room for it, `UNAVAILABLE` when it cannot
    /// be written.
    async fn spool(&self, raw: &mut RawStep) -> Result<(), Status> {
        let Some(spool) = &self.spool else {
            return Ok(());
        };
        let name = spool.put(raw).await.map_err(|e| match e {
            crate::spool::SpoolError::TooLarge { .. } => Status::resource_exhausted(e.to_string()),
            crate::spool::SpoolError::Io { .. } => Status::unavailable(e.to_string()),
        })?;
        raw.spool = Some(name);
        Ok(())
    }

    /// Reports `raw`'s value range to the scene agreement while no TF is fixed.
    fn propose_scene(&self, raw: &RawStep) {
        let Some(scene) = &self.scene else {
            return;
        };
        // A read of one field, not a copy of the settings, on every push.
        let no_tf = self
            .generation
            .read()
            .unwrap_or_else(|e| e.into_inner())
            .tf
            .is_none();
        if no_tf {
            scene.propose(raw);
        }
    }

    /// Queues `raw` (waiting for room, or dropping by the queue's policy) and counts it:
    /// the steps it dropped and the steps received so far.
    ///
    /// # Errors
    /// `UNAVAILABLE` when the node is shutting down.
    async fn enqueue(&self, raw: RawStep) -> Result<(u64, u64), Status> {
        let (step, rank, n) = (raw.info.step, raw.info.rank, raw.bytes());
        let span = info_span!("receive", step, rank, bytes = n);
        let dropped = self
            .queue
            .push(raw, n)
            .instrument(span)
            .await
            .map_err(|_| Status::unavailable("the generator-node is shutting down"))?;
        let n_dropped = dropped.len() as u64;
        for d in dropped {
            info!(step = d.info.step, rank = d.info.rank, policy = %self.queue.policy(), "dropped a queued step");
            self.unspool(d.spooled().as_ref());
            self.spare_fields.put(d.field);
        }
        let mut received = 0;
        self.stats.update(|c| {
            c.received += 1;
            c.dropped_queue += n_dropped;
            received = c.received;
        });
        Ok((n_dropped, received))
    }

    /// Removes a settled step's file from the spool (no-op without one).
    pub fn unspool(&self, spool: Option<&(String, u64)>) {
        if let (Some(sp), Some((name, bytes))) = (&self.spool, spool) {
            sp.remove(name, *bytes);
        }
    }

    /// Records the current generation settings in the spool (no-op without one), so that a
    /// restarted node continues the same scene.
    pub fn save_run(&self) {
        if let Some(sp) = &self.spool {
            let g = self.generation();
            if let Err(e) = sp.save_run(g.pm_version, &to_pb(&g)) {
                tracing::warn!(error = %e, "could not record the run configuration");
            }
        }
    }
}

/// The gRPC service.
pub struct GeneratorService(pub Arc<Shared>);

/// The settings as a `GenerationConfig` (what [`apply_config`] reads back).
pub fn to_pb(g: &Generation) -> pb::GenerationConfig {
    pb::GenerationConfig {
        resolution: g.params.resolution,
        gamma: g.params.gamma,
        step: Some(g.raycast.step),
        termination: Some(g.raycast.termination),
        codec: insitu_proto::convert::codec_to_pb(g.codec) as i32,
        tf_json: g
            .tf
            .as_ref()
            .and_then(|(tf, _)| serde_json::to_string(tf).ok()),
        tf_name: g.tf.as_ref().map(|(_, n)| n.clone()),
        camera: g.camera.as_ref().map(insitu_proto::convert::camera_to_pb),
        view_angles_deg: g.view_angles_deg.clone(),
        reference_every: u32::try_from(g.reference_every).ok(),
        reference_size: Some(g.reference_size),
    }
}

/// Applies a pushed config to `g`; nothing changes unless all of it is valid.
///
/// # Errors
/// `INVALID_ARGUMENT` naming the field.
pub fn apply_config(g: &Generation, c: &pb::GenerationConfig) -> Result<Generation, Status> {
    let bad =
        |field: &str, e: &dyn std::fmt::Display| Status::invalid_argument(format!("{field}: {e}"));
    let mut next = g.clone();
    // An operator's P_M is not a tuner's decision, and applies from the next step.
    next.pm_version = 0;
    next.previous = None;
    next.params = VdiParams {
        resolution: c.resolution,
        gamma: c.gamma,
    };
    next.params
        .validate()
        .map_err(|e| bad("resolution/gamma", &e))?;
    next.raycast = RaycastParams {
        step: c.step.unwrap_or(g.raycast.step),
        termination: c.termination.unwrap_or(g.raycast.termination),
        ..g.raycast
    };
    next.raycast
        .validate()
        .map_err(|e| bad("step/termination", &e))?;
    if let Some(codec) = codec_from_pb(c.codec)? {
        next.codec = codec;
    }
    if let Some(json) = &c.tf_json {
        if json.len() > MAX_TF_JSON {
            return Err(bad(
                "tf_json",
                &format!("{} bytes exceeds {MAX_TF_JSON}", json.len()),
            ));
        }
        let name = c.tf_name.clone().unwrap_or_else(|| "pushed".into());
        let tf = TransferFunction::from_json(json, &name).map_err(|e| bad("tf_json", &e))?;
        next.tf = Some((tf, name));
    }
    if let Some(cam) = &c.camera {
        next.camera = Some(camera_from_pb(cam)?);
    }
    if !c.view_angles_deg.is_empty() {
        if c.view_angles_deg.iter().any(|a| !a.is_finite()) {
            return Err(bad("view_angles_deg", &"angles must be finite"));
        }
        next.view_angles_deg = c.view_angles_deg.clone();
    }
    if let Some(k) = c.reference_every {
        next.reference_every = u64::from(k);
    }
    if let Some(s) = c.reference_size {
        if s > insitu_core::vdi::MAX_RESOLUTION {
            return Err(bad("reference_size", &format!("{s} is too large")));
        }
        next.reference_size = s;
    }
    Ok(next)
}

#[tonic::async_trait]
impl Generator for GeneratorService {
    async fn push_step(
        &self,
        request: Request<Streaming<pb::StepChunk>>,
    ) -> Result<Response<pb::PushReply>, Status> {
        let s = &self.0;
        let mut raw = s.receive(request.into_inner()).await?;
        s.spool(&mut raw).await?;
        s.propose_scene(&raw);
        let (dropped, received) = s.enqueue(raw).await?;
        Ok(Response::new(pb::PushReply {
            queue_depth: s.queue.len() as u32,
            dropped_by_push: dropped,
            steps_received: received,
            epoch: s.epoch,
        }))
    }

    async fn set_config(
        &self,
        request: Request<pb::GenerationConfig>,
    ) -> Result<Response<pb::ConfigReply>, Status> {
        let c = request.into_inner();
        let reply = {
            let mut g = self.0.generation.write().unwrap_or_else(|e| e.into_inner());
            *g = apply_config(&g, &c)?;
            info!(r = g.params.resolution, gamma = g.params.gamma, codec = %g.codec, "new generation config");
            pb::ConfigReply {
                resolution: g.params.resolution,
                gamma: g.params.gamma,
            }
        };
        self.0.save_run();
        Ok(Response::new(reply))
    }

    async fn get_status(
        &self,
        _: Request<pb::StatusRequest>,
    ) -> Result<Response<pb::GeneratorStatus>, Status> {
        Ok(Response::new(self.0.status()))
    }

    async fn flush(
        &self,
        request: Request<pb::FlushRequest>,
    ) -> Result<Response<pb::GeneratorStatus>, Status> {
        let t = request.into_inner().timeout_secs;
        let timeout = if t.is_finite() && t > 0.0 {
            t.min(86_400.0)
        } else {
            600.0
        };
        let s = &self.0;
        let target = s.stats.get().received;
        let shipping = s.shipping;
        tokio::time::timeout(
            Duration::from_secs_f64(timeout),
            s.stats.wait_for(|c| c.settled(shipping) >= target),
        )
        .await
        .map_err(|_| {
            let why = s.stats.ship_error();
            Status::deadline_exceeded(format!(
                "flush: not all of {target} steps were shipped within {timeout} s ({})",
                if why.is_empty() {
                    "is the viz-node reachable?".to_owned()
                } else {
                    why
                }
            ))
        })?;
        // Refusals since the previous flush make this one fail, naming the last cause: the
        // steps were received, but the viz-node did not store their VDIs.
        let failed = s.stats.get().ship_failed;
        let before = s
            .ship_failed_reported
            .swap(failed, std::sync::atomic::Ordering::Relaxed);
        if failed > before {
            return Err(Status::failed_precondition(format!(
                "flush: the viz-node refused {} VDI(s) since the last flush; last: {}",
                failed - before,
                s.stats.ship_error()
            )));
        }
        Ok(Response::new(s.status()))
    }
}
