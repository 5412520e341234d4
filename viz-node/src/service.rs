//! The `Viz` gRPC service: store VDIs and reference frames, score and report, render.

use crate::score::score;
use crate::store::{Entry, Recording, References};
use insitu_core::vdi::codec::{self, DecodeLimits};
use insitu_core::{Backend, Vdi};
use insitu_proto::convert::{camera_from_pb, codec_from_pb, codec_to_pb};
use insitu_proto::pb::viz_server::Viz;
use insitu_proto::{chunk, pb};
use std::pin::Pin;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use tokio::sync::{broadcast, mpsc};
use tokio_stream::wrappers::BroadcastStream;
use tokio_stream::{Stream, StreamExt};
use tonic::{Request, Response, Status, Streaming};
use tracing::{info, warn};

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
    /// Steps to score.
    pub to_score: mpsc::UnboundedSender<(u64, u32)>,
    /// Largest VDI file, bytes.
    pub max_vdi_bytes: u64,
    /// Largest set of reference frames, bytes.
    pub max_reference_bytes: u64,
    /// Early termination for rendering.
    pub termination: f32,
    /// Where VDIs are rendered (scoring and `Render`).
    pub backend: Backend,
    /// VDIs stored.
    pub vdis_stored: AtomicU64,
    /// Reference sets stored.
    pub references_stored: AtomicU64,
    /// Reports sent.
    pub reports_sent: AtomicU64,
    /// Streams rejected.
    pub rejected: AtomicU64,
}

/// The report for an entry.
pub fn report(e: &Entry) -> pb::QualityReport {
    let q = e.quality.as_ref();
    pb::QualityReport {
        step: e.step,
        rank: e.rank,
        resolution: e.resolution,
        gamma: e.gamma,
        codec: e.codec.parse().map_or(pb::Codec::Unspecified, codec_to_pb) as i32,
        sigma_bytes: e.sigma_bytes,
        tau_secs: e.tau_secs,
        supersegments: e.supersegments,
        q_db: q.map(|q| q.q_db.0),
        view_q_db: q.map_or_else(Vec::new, |q| q.view_q_db.iter().map(|d| d.0).collect()),
        ssim: q.and_then(|q| q.ssim),
        path: e.vdi.clone().unwrap_or_default(),
        pm_version: e.pm_version,
        world_size: e.world_size,
    }
}

impl Shared {
    fn publish(&self, e: &Entry) {
        self.reports_sent.fetch_add(1, Ordering::Relaxed);
        // No subscribers is fine: the index has it all.
        let _ = self.reports.send(report(e));
    }

    fn after_store(&self, e: &Entry) {
        if e.vdi.is_some() && e.references.is_some() {
            // The scoring task lives as long as the node.
            let _ = self.to_score.send((e.step, e.rank));
        } else if e.vdi.is_some() {
            self.publish(e);
        }
    }

    fn load_vdi(&self, e: &Entry) -> Result<Vdi, Status> {
        let name = e.vdi.as_ref().ok_or_else(|| {
            Status::not_found(format!("step {} rank {} has no VDI yet", e.step, e.rank))
        })?;
        let path = self.recording.dir().join(name);
        let bytes = std::fs::read(&path)
            .map_err(|err| Status::internal(format!("{}: {err}", path.display())))?;
        codec::decode(&bytes, &DecodeLimits::default())
            .map_err(|err| Status::data_loss(format!("{}: {err}", path.display())))
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
        let vdi = self.load_vdi(&e)?;
        let refs_name = e
            .references
            .as_ref()
            .ok_or_else(|| Status::not_found("no references"))?;
        let refs = References::read(&self.recording.dir().join(refs_name))
            .map_err(|err| Status::data_loss(err.to_string()))?;
        let q = score(&self.backend, &vdi, &refs, self.termination)
            .map_err(|err| Status::invalid_argument(err.to_string()))?;
        let e = self
            .recording
            .set_quality(step, rank, q)
            .map_err(|err| Status::internal(err.to_string()))?;
        self.publish(&e);
        Ok(e)
    }
}

/// Scores queued steps one at a time on the blocking pool.
pub async fn scorer(shared: Arc<Shared>, mut rx: mpsc::UnboundedReceiver<(u64, u32)>) {
    while let Some((step, rank)) = rx.recv().await {
        let s = shared.clone();
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
        let (h, bytes) = chunk::receive(&mut stream, self.0.max_vdi_bytes, |h: &pb::VdiHeader| {
            codec_from_pb(h.codec)?
                .ok_or_else(|| Status::invalid_argument("codec is unspecified"))?;
            Ok(())
        })
        .await?;
        let s = self.0.clone();
        let entry = tokio::task::spawn_blocking(move || {
            let what = format!("VDI of step {} rank {}", h.step, h.rank);
            let vdi = codec::decode(&bytes, &DecodeLimits::default())
                .map_err(|e| Status::invalid_argument(format!("{what}: {e}")))?;
            let p = vdi.meta().params;
            if p.resolution != h.resolution || p.gamma.to_bits() != h.gamma.to_bits() {
                return Err(Status::invalid_argument(format!(
                    "{what}: header says r = {}, γ = {} but the file holds r = {}, γ = {}",
                    h.resolution, h.gamma, p.resolution, p.gamma
                )));
            }
            let codec = codec_from_pb(h.codec)?.map_or_else(String::new, |c| c.name().to_owned());
            let meta = Entry {
                step: h.step,
                rank: h.rank,
                world_size: h.world_size,
                sim_time: h.sim_time,
                vdi: None,
                references: None,
                resolution: h.resolution,
                gamma: h.gamma,
                codec,
                sigma_bytes: bytes.len() as u64,
                supersegments: vdi.supersegments().len() as u64,
                tau_secs: h.tau_secs,
                tau_compress_secs: h.tau_compress_secs,
                tf_name: vdi.meta().tf_name.clone(),
                tf_hash: vdi.meta().tf_hash,
                quality: None,
                pm_version: h.pm_version,
            };
            s.recording
                .store_vdi(meta, &bytes)
                .map_err(|e| Status::internal(e.to_string()))
        })
        .await
        .map_err(join_error)??;
        self.0.vdis_stored.fetch_add(1, Ordering::Relaxed);
        self.0.after_store(&entry);
        Ok(entry)
    }

    async fn ship_references_inner(
        &self,
        mut stream: Streaming<pb::ReferenceChunk>,
    ) -> Result<Entry, Status> {
        let (h, bytes) = chunk::receive(
            &mut stream,
            self.0.max_reference_bytes,
            |h: &pb::ReferenceHeader| {
                let side_ok = |v: u32| (1..=MAX_IMAGE_SIDE).contains(&v);
                if !side_ok(h.width) || !side_ok(h.height) {
                    return Err(Status::invalid_argument(format!(
                        "reference frames of {}×{}: sides must be in 1..={MAX_IMAGE_SIDE}",
                        h.width, h.height
                    )));
                }
                let views = h.view_angles_deg.len();
                if views == 0
                    || views > MAX_VIEWS
                    || h.view_angles_deg.iter().any(|a| !a.is_finite())
                {
                    return Err(Status::invalid_argument(format!(
                        "{views} view angles: need 1..={MAX_VIEWS} finite angles"
                    )));
                }
                let expected = views as u64 * u64::from(h.width) * u64::from(h.height) * 12;
                if h.total_bytes != expected {
                    return Err(Status::invalid_argument(format!(
                        "total_bytes {} does not match {views} views of {}×{} RGB f32 ({expected})",
                        h.total_bytes, h.width, h.height
                    )));
                }
                camera_from_pb(
                    h.camera
                        .as_ref()
                        .ok_or_else(|| Status::invalid_argument("camera is missing"))?,
                )?;
                Ok(())
            },
        )
        .await?;
        let camera = camera_from_pb(
            h.camera
                .as_ref()
                .ok_or_else(|| Status::invalid_argument("camera is missing"))?,
        )?;
        let s = self.0.clone();
        let entry = tokio::task::spawn_blocking(move || {
            let refs = References::from_bytes(camera, h.view_angles_deg, h.width, h.height, &bytes)
                .map_err(|e| {
                    Status::invalid_argument(format!(
                        "references of step {} rank {}: {e}",
                        h.step, h.rank
                    ))
                })?;
            s.recording
                .store_references(h.step, h.rank, &refs)
                .map_err(|e| Status::internal(e.to_string()))
        })
        .await
        .map_err(join_error)??;
        self.0.references_stored.fetch_add(1, Ordering::Relaxed);
        self.0.after_store(&entry);
        Ok(entry)
    }
}

type ReportStream = Pin<Box<dyn Stream<Item = Result<pb::QualityReport, Status>> + Send>>;

#[tonic::async_trait]
impl Viz for VizService {
    async fn ship_vdi(
        &self,
        request: Request<Streaming<pb::VdiChunk>>,
    ) -> Result<Response<pb::ShipReply>, Status> {
        let e = self.rejected(self.ship_vdi_inner(request.into_inner()).await)?;
        Ok(Response::new(pb::ShipReply {
            path: e.vdi.unwrap_or_default(),
        }))
    }

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
        Ok(Response::new(pb::VizStatus {
            vdis_stored: s.vdis_stored.load(Ordering::Relaxed),
            references_stored: s.references_stored.load(Ordering::Relaxed),
            reports: s.reports_sent.load(Ordering::Relaxed),
            rejected: s.rejected.load(Ordering::Relaxed),
            recording_dir: s.recording.dir().display().to_string(),
        }))
    }

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
        let camera = r.camera.as_ref().map(camera_from_pb).transpose()?;
        let s = self.0.clone();
        let png = tokio::task::spawn_blocking(move || {
            let e = s.recording.entry(r.step, r.rank).ok_or_else(|| {
                Status::not_found(format!(
                    "step {} rank {} is not in the recording",
                    r.step, r.rank
                ))
            })?;
            let vdi = s.load_vdi(&e)?;
            let cam = camera.unwrap_or(vdi.meta().camera);
            let image = s
                .backend
                .prepare_vdi(&vdi)
                .and_then(|v| v.render(&cam, r.width, r.height, s.termination))
                .map_err(|e| Status::internal(format!("rendering: {e}")))?
                .value;
            let rgb = image::RgbImage::from_raw(r.width, r.height, image.to_rgb8())
                .ok_or_else(|| Status::internal("image size mismatch"))?;
            let mut png = std::io::Cursor::new(Vec::new());
            rgb.write_to(&mut png, image::ImageFormat::Png)
                .map_err(|e| Status::internal(format!("PNG encoding: {e}")))?;
            Ok::<_, Status>(png.into_inner())
        })
        .await
        .map_err(join_error)??;
        Ok(Response::new(pb::RenderReply { png: png.into() }))
    }
}
