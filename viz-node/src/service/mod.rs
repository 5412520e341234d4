//! The `Viz` gRPC service: store VDIs and reference frames, score and report, render.

mod admit;

use crate::scene::SceneAgreement;
use crate::score::score;
use admit::{placement, reference_camera, store_references, store_vdi};
use insitu_core::backend::TimeSource;
use insitu_core::evaluate::Sizing;
use insitu_core::vdi::codec::{self, Codec, DecodeLimits};
use insitu_core::vdi::provenance::Provenance;
use insitu_core::volume::bricks::{self, Brick};
use insitu_core::{Backend, Camera, Vdi};
use insitu_proto::convert::wire_enum;
use insitu_proto::pb::viz_server::Viz;
use insitu_proto::peer::Backoff;
use insitu_proto::{chunk, pb};
use insitu_recording::decoded::{read_vdi, Expected, Kept};
use insitu_recording::store::{
    Entry, Placement, Quality, Recording, References, StepEntry, StoreError,
};
use std::collections::HashSet;
use std::pin::Pin;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::sync::{broadcast, mpsc};
use tokio_stream::wrappers::BroadcastStream;
use tokio_stream::{Stream, StreamExt};
use tonic::{Request, Response, Status, Streaming};
use tracing::field::Empty;
use tracing::{info, warn, Span};

/// Largest reference frame or rendered image side, pixels.
pub const MAX_IMAGE_SIDE: u32 = 8192;
/// Most test views in one set of reference frames.
pub const MAX_VIEWS: usize = 360;

/// State shared by the service and the scoring task.
pub struct Shared {
    /// The recording.
    pub recording: Recording,
    /// Quality reports to subscribers.
    pub reports: broadcast::Sender<pb::QualityReport>,
    /// Steps to score or compose (bounded: `score_queue` jobs; storing waits when full).
    pub to_score: mpsc::Sender<Job>,
    /// Renders at once (`Render` beyond it: `RESOURCE_EXHAUSTED`).
    pub renders: Arc<tokio::sync::Semaphore>,
    /// Largest image of one `Render`, pixels.
    pub max_render_pixels: u64,
    /// The run's agreed scene.
    pub scene: SceneAgreement,
    /// How long a multi-rank step waits for its last rank before it is composed without it.
    pub compose_timeout: Duration,
    /// Multi-rank steps whose timeout is armed.
    pub timers: Mutex<HashSet<u64>>,
    /// Steps composed with every rank.
    pub steps_composed: AtomicU64,
    /// Steps composed without some ranks.
    pub steps_partial: AtomicU64,
    /// Steps that could not be composed.
    pub compose_errors: AtomicU64,
    /// Largest VDI file, bytes.
    pub max_vdi_bytes: u64,
    /// Largest set of reference frames, bytes.
    pub max_reference_bytes: u64,
    /// Early termination for rendering.
    pub termination: f32,
    /// Where VDIs are rendered (scoring and `Render`).
    pub backend: Backend,
    /// Ranks' VDIs and frames decoded on receipt, for the scorer and the composer.
    pub kept: Kept,
    /// VDIs stored.
    pub vdis_stored: AtomicU64,
    /// Reference sets stored.
    pub references_stored: AtomicU64,
    /// Reports sent.
    pub reports_sent: AtomicU64,
    /// Streams rejected.
    pub rejected: AtomicU64,
    /// Serving a read-only archive: every item shipped is refused.
    pub read_only: bool,
    /// The faces of bricks that grow across generator-nodes (`ExchangeFaces`).
    pub faces: crate::faces::Faces,
}

impl Shared {
    /// `FAILED_PRECONDITION` on a read-only archive (`what` is being shipped or proposed).
    fn writable(&self, what: &str) -> Result<(), Status> {
        if self.read_only {
            return Err(Status::failed_precondition(format!(
                "{what} refused: this viz-node serves {} as a read-only archive",
                self.recording.dir().display()
            )));
        }
        Ok(())
    }
}

/// Work for the scoring task, in arrival order.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Job {
    /// Score one rank of a single-rank step.
    Score(u64, u32),
    /// Compose a multi-rank step: when complete, or (`partial_ok`) after its timeout.
    Compose {
        /// The step.
        step: u64,
        /// Compose with the ranks present even if some are missing.
        partial_ok: bool,
    },
}

/// The report for a composed step (rank 0, `composed`).
pub fn step_report(s: &StepEntry) -> pb::QualityReport {
    pb::QualityReport {
        step: s.step,
        rank: 0,
        resolution: s.resolution,
        gamma: s.gamma,
        codec: s.codec.map_or(pb::Codec::Unspecified, pb::Codec::from) as i32,
        path: s.vdi.clone().unwrap_or_default(),
        pm_version: s.pm_version,
        scene_version: s.scene_version,
        world_size: s.world_size,
        composed: true,
        missing_ranks: s.missing.clone(),
        error: s.error.clone().unwrap_or_default(),
        ..measured(&s.sizing, s.quality.as_ref())
    }
}

/// The report for an entry.
pub fn report(e: &Entry) -> pb::QualityReport {
    pb::QualityReport {
        step: e.step,
        rank: e.rank,
        resolution: e.resolution,
        gamma: e.gamma,
        codec: e.codec.map_or(pb::Codec::Unspecified, pb::Codec::from) as i32,
        path: e.vdi.clone().unwrap_or_default(),
        pm_version: e.pm_version,
        scene_version: e.scene_version,
        world_size: e.world_size,
        ..measured(&e.sizing, e.quality.as_ref())
    }
}

/// A report's measured part, σ, τ and the supersegments, and q and SSIM where scored; the
/// other fields empty.
fn measured(sizing: &Sizing, quality: Option<&Quality>) -> pb::QualityReport {
    pb::QualityReport {
        sigma_bytes: sizing.sigma_bytes,
        tau_secs: sizing.tau_secs,
        supersegments: sizing.supersegments,
        q_db: quality.map(|q| q.q_db.0),
        view_q_db: quality.map_or_else(Vec::new, |q| q.view_q_db.iter().map(|d| d.0).collect()),
        ssim: quality.and_then(|q| q.ssim),
        ..Default::default()
    }
}

impl Shared {
    fn publish(&self, r: pb::QualityReport) {
        self.reports_sent.fetch_add(1, Ordering::Relaxed);
        // No subscribers is fine: the index has it all.
        let _ = self.reports.send(r);
    }

    /// What a stored VDI or set of frames sets off: scoring of a single-rank step; for a
    /// rank of several, the per-rank report (once its VDI is in) and the step's composition
    /// (now when every rank is ready, else after the timeout).
    async fn after_store(self: &Arc<Self>, e: &Entry, was_vdi: bool) {
        if e.world_size <= 1 {
            if e.vdi.is_some() && e.references.is_some() {
                // The scoring task lives as long as the node. A full queue holds this call
                // (and so the shipper's next item) until the scorer catches up.
                let _ = self.to_score.send(Job::Score(e.step, e.rank)).await;
            } else if e.vdi.is_some() && !e.with_references {
                // A VDI whose frames were announced is reported once scored, when they come.
                self.publish(report(e));
            }
            return;
        }
        if was_vdi {
            self.publish(report(e));
        }
        let step = e.step;
        let ranks = self.recording.ranks_of(step);
        if crate::compose::missing(&ranks, e.world_size).is_empty() {
            let _ = self
                .to_score
                .send(Job::Compose {
                    step,
                    partial_ok: false,
                })
                .await;
        } else if self
            .timers
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .insert(step)
        {
            let (tx, wait) = (self.to_score.clone(), self.compose_timeout);
            tokio::spawn(async move {
                tokio::time::sleep(wait).await;
                let _ = tx
                    .send(Job::Compose {
                        step,
                        partial_ok: true,
                    })
                    .await;
            });
        }
    }

    /// Composes `step` (see [`crate::compose::compose_step`]), records the result or the
    /// error in the step's entry, and publishes it. A step composed complete is not composed
    /// again.
    fn compose(&self, step: u64, partial_ok: bool) {
        if partial_ok {
            self.timers
                .lock()
                .unwrap_or_else(|p| p.into_inner())
                .remove(&step);
        }
        // Composed complete already (two last ranks arriving together, or the timeout
        // firing after the step completed).
        let done = self
            .recording
            .step(step)
            .is_some_and(|s| s.missing.is_empty() && s.error.is_none());
        if done {
            return;
        }
        let result = crate::compose::compose_step(
            &self.recording,
            &self.kept,
            &self.backend,
            self.termination,
            step,
            partial_ok,
        );
        let entry = match result {
            Ok(None) => return,
            Ok(Some(s)) => {
                let counter = if s.missing.is_empty() {
                    &self.steps_composed
                } else {
                    warn!(step, missing = ?s.missing, "composed a partial step: ranks missing after the timeout");
                    &self.steps_partial
                };
                counter.fetch_add(1, Ordering::Relaxed);
                let q = s.quality.as_ref().map_or(f64::NAN, |q| q.q_db.0);
                info!(step, ranks = s.ranks.len(), q_db = q, "composed");
                s
            }
            Err(err) => {
                self.compose_errors.fetch_add(1, Ordering::Relaxed);
                warn!(step, error = %err, "could not compose the step");
                let ranks = self.recording.ranks_of(step);
                let world_size = ranks.iter().map(|e| e.world_size).max().unwrap_or(1);
                let missing = crate::compose::missing(&ranks, world_size);
                StepEntry {
                    error: Some(err.to_string()),
                    ..StepEntry::of_ranks(
                        step,
                        world_size,
                        &ranks.iter().collect::<Vec<_>>(),
                        missing,
                    )
                }
            }
        };
        if let Err(err) = self.recording.set_step(entry.clone()) {
            warn!(step, error = %err, "could not record the composed step");
        }
        self.publish(step_report(&entry));
    }

    fn load_vdi(&self, e: &Entry) -> Result<Vdi, Status> {
        self.load_file(vdi_name(e)?, e.into())
    }

    fn load_file(&self, name: &str, expected: Expected) -> Result<Vdi, Status> {
        read_vdi(self.recording.dir(), name, expected)
            .map_err(|err| Status::data_loss(err.to_string()))
    }

    /// Scores a stored step against its stored references, records and publishes q.
    ///
    /// # Errors
    /// When either file cannot be read or decoded.
    pub fn score_stored(&self, step: u64, rank: u32) -> Result<Entry, Status> {
        let e = self
            .recording
            .entry(step, rank)
            .ok_or_else(|| Status::not_found(format!("step {step} rank {rank}")))?;
        let dir = self.recording.dir();
        let vdi = self.kept.take_vdi(dir, vdi_name(&e)?, (&e).into());
        let vdi = vdi.map_err(|err| Status::data_loss(err.to_string()))?;
        let refs_name = e
            .references
            .as_ref()
            .ok_or_else(|| Status::not_found("no references"))?;
        let refs = self.kept.take_references(dir, refs_name);
        let refs = refs.map_err(|err| Status::data_loss(err.to_string()))?;
        let q = score(&self.backend, &vdi, &refs, self.termination)
            .map_err(|err| Status::invalid_argument(err.to_string()))?;
        // A storage fault (full, read-only, access denied) delays q, it does not lose it: the
        // write is retried (the scorer waits, and with it the bounded queue of jobs behind it)
        // until the storage takes it again.
        let mut backoff = Backoff::new(Backoff::DEFAULT_MAX);
        let e = loop {
            match self.recording.set_quality(step, rank, q.clone()) {
                Ok(e) => break e,
                Err(err) if err.is_storage_fault() => {
                    warn!(step, rank, error = %err, "q not recorded yet; retrying");
                    std::thread::sleep(backoff.next_delay());
                }
                Err(err) => return Err(Status::internal(err.to_string())),
            }
        };
        self.publish(report(&e));
        Ok(e)
    }
}

/// The name of `e`'s VDI file; `NOT_FOUND` while it has none.
fn vdi_name(e: &Entry) -> Result<&str, Status> {
    e.vdi
        .as_deref()
        .ok_or_else(|| Status::not_found(format!("step {} rank {} has no VDI yet", e.step, e.rank)))
}

/// Scores and composes queued steps one at a time on the blocking pool.
pub async fn scorer(shared: Arc<Shared>, mut rx: mpsc::Receiver<Job>) {
    while let Some(job) = rx.recv().await {
        let s = shared.clone();
        let (step, rank) = match job {
            Job::Score(step, rank) => (step, rank),
            Job::Compose { step, partial_ok } => {
                if let Err(err) =
                    tokio::task::spawn_blocking(move || s.compose(step, partial_ok)).await
                {
                    warn!(step, error = %err, "composing task panicked");
                }
                continue;
            }
        };
        match tokio::task::spawn_blocking(move || s.score_stored(step, rank)).await {
            Ok(Ok(e)) => {
                let q = e.quality.map(|q| q.q_db.0).unwrap_or(f64::NAN);
                info!(step, rank, q_db = q, "scored");
            }
            Ok(Err(err)) => warn!(step, rank, error = %err.message(), "scoring failed"),
            Err(err) => warn!(step, rank, error = %err, "scoring task panicked"),
        }
    }
}

/// The gRPC service.
pub struct VizService(pub Arc<Shared>);

/// `ALREADY_EXISTS` for a (step, rank) stored with other content; `RESOURCE_EXHAUSTED` when
/// the storage refused the write for a reason an operator fixes (full, read-only, access
/// denied, failing: [`StoreError::is_storage_fault`]), which the generator-node waits out,
/// keeping the item; `INTERNAL` for other failures. Each names the file or the item.
fn store_status(e: StoreError) -> Status {
    match &e {
        StoreError::AlreadyExists { .. } => Status::already_exists(e.to_string()),
        _ if e.is_storage_fault() => Status::resource_exhausted(e.to_string()),
        _ => Status::internal(e.to_string()),
    }
}

/// A payload over `max_vdi_bytes`/`max_reference_bytes` as OUT_OF_RANGE, so that
/// RESOURCE_EXHAUSTED from `ShipVdi`/`ShipReferences` means only "the disk is full": a
/// condition the generator-node waits out, where an oversize item would never fit.
fn over_limit(s: Status) -> Status {
    if s.code() == tonic::Code::ResourceExhausted {
        Status::out_of_range(s.message())
    } else {
        s
    }
}

fn join_error(e: tokio::task::JoinError) -> Status {
    Status::internal(format!("storage task failed: {e}"))
}

impl VizService {
    fn rejected<T>(&self, r: Result<T, Status>) -> Result<T, Status> {
        if let Err(e) = &r {
            self.0.rejected.fetch_add(1, Ordering::Relaxed);
            warn!(code = ?e.code(), error = %e.message(), "rejected a stream");
        }
        r
    }

    async fn ship_vdi_inner(&self, mut stream: Streaming<pb::VdiChunk>) -> Result<Entry, Status> {
        self.0.writable("a VDI")?;
        let (h, bytes) = chunk::receive(&mut stream, self.0.max_vdi_bytes, |h: &pb::VdiHeader| {
            wire_enum::<pb::Codec>(h.codec, "codec")
                .map(Option::<Codec>::from)?
                .ok_or_else(|| Status::invalid_argument("codec is unspecified"))?;
            Ok(())
        })
        .await
        .map_err(over_limit)?;
        Span::current()
            .record("step", h.step)
            .record("rank", h.rank);
        if h.world_size == 0 || h.rank >= h.world_size {
            return Err(Status::invalid_argument(format!(
                "VDI of step {} rank {}: world size {} (need 0 ≤ rank < world_size)",
                h.step, h.rank, h.world_size
            )));
        }
        let placement = placement(&h)?;
        let s = self.0.clone();
        let (entry, new) =
            tokio::task::spawn_blocking(move || store_vdi(&s, &h, &bytes, placement))
                .await
                .map_err(join_error)??;
        if new {
            self.0.vdis_stored.fetch_add(1, Ordering::Relaxed);
            self.0.after_store(&entry, true).await;
        }
        Ok(entry)
    }

    async fn ship_references_inner(
        &self,
        mut stream: Streaming<pb::ReferenceChunk>,
    ) -> Result<Entry, Status> {
        self.0.writable("reference frames")?;
        let (h, bytes) = chunk::receive(&mut stream, self.0.max_reference_bytes, |h| {
            reference_camera(h).map(drop)
        })
        .await
        .map_err(over_limit)?;
        Span::current()
            .record("step", h.step)
            .record("rank", h.rank);
        let camera = reference_camera(&h)?;
        let s = self.0.clone();
        let (entry, new) =
            tokio::task::spawn_blocking(move || store_references(&s, h, camera, &bytes))
                .await
                .map_err(join_error)??;
        if new {
            self.0.references_stored.fetch_add(1, Ordering::Relaxed);
            self.0.after_store(&entry, false).await;
        }
        Ok(entry)
    }
}

type ReportStream = Pin<Box<dyn Stream<Item = Result<pb::QualityReport, Status>> + Send>>;

#[tonic::async_trait]
impl Viz for VizService {
    #[tracing::instrument(
        name = "ship_vdi",
        skip_all,
        fields(peer = ?request.remote_addr(), step = Empty, rank = Empty)
    )]
    async fn ship_vdi(
        &self,
        request: Request<Streaming<pb::VdiChunk>>,
    ) -> Result<Response<pb::ShipReply>, Status> {
        let e = self.rejected(self.ship_vdi_inner(request.into_inner()).await)?;
        Ok(Response::new(pb::ShipReply {
            path: e.vdi.unwrap_or_default(),
        }))
    }

    #[tracing::instrument(
        name = "ship_references",
        skip_all,
        fields(peer = ?request.remote_addr(), step = Empty, rank = Empty)
    )]
    async fn ship_references(
        &self,
        request: Request<Streaming<pb::ReferenceChunk>>,
    ) -> Result<Response<pb::ShipReply>, Status> {
        let e = self.rejected(self.ship_references_inner(request.into_inner()).await)?;
        Ok(Response::new(pb::ShipReply {
            path: e.references.unwrap_or_default(),
        }))
    }

    type SubscribeStream = ReportStream;

    async fn subscribe(
        &self,
        _: Request<pb::SubscribeRequest>,
    ) -> Result<Response<ReportStream>, Status> {
        let stream = BroadcastStream::new(self.0.reports.subscribe()).filter_map(|r| match r {
            Ok(report) => Some(Ok(report)),
            Err(tokio_stream::wrappers::errors::BroadcastStreamRecvError::Lagged(n)) => {
                warn!(skipped = n, "a subscriber fell behind; skipped reports");
                None
            }
        });
        Ok(Response::new(Box::pin(stream)))
    }

    async fn get_status(
        &self,
        _: Request<pb::StatusRequest>,
    ) -> Result<Response<pb::VizStatus>, Status> {
        let s = &self.0;
        let (decoded_reused, decoded_again) = s.kept.counts();
        Ok(Response::new(pb::VizStatus {
            vdis_stored: s.vdis_stored.load(Ordering::Relaxed),
            references_stored: s.references_stored.load(Ordering::Relaxed),
            reports: s.reports_sent.load(Ordering::Relaxed),
            rejected: s.rejected.load(Ordering::Relaxed),
            recording_dir: s.recording.dir().display().to_string(),
            steps_composed: s.steps_composed.load(Ordering::Relaxed),
            steps_partial: s.steps_partial.load(Ordering::Relaxed),
            compose_errors: s.compose_errors.load(Ordering::Relaxed),
            decoded_reused,
            decoded_again,
        }))
    }

    async fn step_outcomes(
        &self,
        request: Request<pb::StepOutcomesRequest>,
    ) -> Result<Response<pb::StepOutcomesReply>, Status> {
        let steps = request.into_inner().steps;
        if steps.len() > 100_000 {
            return Err(Status::invalid_argument(format!(
                "{} steps asked: at most 100000 per call",
                steps.len()
            )));
        }
        let outcomes = steps
            .into_iter()
            .filter_map(|step| self.0.recording.step(step))
            .filter(|s| s.vdi.is_some() || s.error.is_some())
            .map(|s| pb::StepOutcome {
                step: s.step,
                error: s.error.unwrap_or_default(),
                missing: s.missing,
            })
            .collect();
        Ok(Response::new(pb::StepOutcomesReply { outcomes }))
    }

    async fn exchange_faces(
        &self,
        request: Request<pb::FacesOffer>,
    ) -> Result<Response<pb::FacesReply>, Status> {
        self.0.writable("an exchange of faces")?;
        let bricks = self.0.faces.exchange(request.into_inner()).await?;
        Ok(Response::new(pb::FacesReply { bricks }))
    }

    async fn agree_scene(
        &self,
        request: Request<pb::SceneProposal>,
    ) -> Result<Response<pb::SceneAgreement>, Status> {
        self.0.writable("a scene proposal")?;
        let p = request.into_inner();
        let wait = if p.wait_secs > 0.0 && p.wait_secs.is_finite() {
            p.wait_secs.min(crate::scene::MAX_WAIT_SECS)
        } else {
            60.0
        };
        let a = self
            .0
            .scene
            .propose(&p, Duration::from_secs_f64(wait))
            .await?;
        Ok(Response::new(pb::SceneAgreement {
            tf: Some(pb::TransferFunction::from(&a.tf)),
            tf_name: a.tf_name,
            world_size: a.world_size,
        }))
    }

    #[tracing::instrument(name = "render", skip_all, fields(peer = ?request.remote_addr()))]
    async fn render(
        &self,
        request: Request<pb::RenderRequest>,
    ) -> Result<Response<pb::RenderReply>, Status> {
        let r = request.into_inner();
        let side_ok = |v: u32| (1..=MAX_IMAGE_SIDE).contains(&v);
        if !side_ok(r.width) || !side_ok(r.height) {
            return Err(Status::invalid_argument(format!(
                "image of {}×{}: sides must be in 1..={MAX_IMAGE_SIDE}",
                r.width, r.height
            )));
        }
        let pixels = u64::from(r.width) * u64::from(r.height);
        if pixels > self.0.max_render_pixels {
            return Err(Status::resource_exhausted(format!(
                "image of {}×{} = {pixels} pixels exceeds max_render_pixels {}",
                r.width, r.height, self.0.max_render_pixels
            )));
        }
        // At most `render_concurrency` renders at once; more are refused, not queued, so a
        // burst of large requests cannot hold memory for all of them.
        let permit = self.0.renders.clone().try_acquire_owned().map_err(|_| {
            Status::resource_exhausted(
                "every render slot is busy (render_concurrency); try again shortly",
            )
        })?;
        let camera = r.camera.as_ref().map(Camera::try_from).transpose()?;
        let s = self.0.clone();
        // Dropped with the call (its client went away): the render stops at its next tile.
        let cancel = insitu_core::cancel::Cancel::new();
        let _stop = cancel.on_drop();
        let png = tokio::task::spawn_blocking(move || {
            let _permit = permit;
            let vdi = if r.composed {
                let composed = s.recording.step(r.step);
                let name = composed
                    .as_ref()
                    .and_then(|c| c.vdi.clone())
                    .ok_or_else(|| {
                        Status::not_found(format!("step {} has no composed VDI", r.step))
                    })?;
                s.load_file(&name, Expected::default())?
            } else {
                let e = s.recording.entry(r.step, r.rank).ok_or_else(|| {
                    Status::not_found(format!(
                        "step {} rank {} is not in the recording",
                        r.step, r.rank
                    ))
                })?;
                s.load_vdi(&e)?
            };
            let cam = camera.unwrap_or(vdi.meta().camera);
            let image = s
                .backend
                .prepare_vdi(&vdi)
                .and_then(|v| v.render_until(&cam, r.width, r.height, s.termination, Some(&cancel)))
                .map_err(|e| Status::internal(format!("rendering: {e}")))?
                .value;
            crate::view::encode(&image, crate::view::Format::Png, 0)
                .map_err(|e| Status::internal(e.to_string()))
        })
        .await
        .map_err(join_error)??;
        Ok(Response::new(pb::RenderReply { png: png.into() }))
    }
}

#[cfg(test)]
mod tests;
