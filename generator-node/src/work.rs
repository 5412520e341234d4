//! The CPU-bound part of a step (run on the blocking pool): VDI generation
//! `R(S_A, P_A, P_M)` (Sec. 3.2), compression (σ), and on sampled steps the reference frames
//! of the test views from the original data (Alg. 1, line 9).

use crate::config::Generation;
use crate::ingest::RawStep;
use bytes::Bytes;
use insitu_core::backend::{BackendError, Scene};
use insitu_core::evaluate::{render_references, render_references_with_opacity};
use insitu_core::vdi::codec;
use insitu_core::{Backend, Camera, Image, Raycaster, TransferFunction, Vdi};
use insitu_proto::convert::{camera_to_pb, codec_to_pb};
use insitu_proto::pb;
use std::sync::Arc;
use std::time::Instant;
use tracing::info_span;

/// A finished step, ready to ship.
#[derive(Debug, Clone)]
pub struct Product {
    /// VDI metadata (σ, τ, `P_M`, …).
    pub vdi_header: pb::VdiHeader,
    /// The compressed VDI file.
    pub vdi: Bytes,
    /// Reference frames, on sampled steps.
    pub references: Option<(pb::ReferenceHeader, Bytes)>,
    /// The step's file in the spool and its field bytes, removed once the VDI is settled.
    pub spool: Option<(String, u64)>,
}

impl Product {
    /// Bytes held (for the outbox's byte limit).
    pub fn bytes(&self) -> u64 {
        (self.vdi.len() + self.references.as_ref().map_or(0, |(_, b)| b.len())) as u64
    }
}

/// Why a step could not be turned into a VDI.
#[derive(Debug, thiserror::Error)]
pub enum WorkError {
    /// Ray-casting parameters were rejected.
    #[error(transparent)]
    Raycast(#[from] insitu_core::raycast::RaycastError),
    /// Encoding failed.
    #[error(transparent)]
    Codec(#[from] codec::CodecError),
    /// The backend failed (bad `P_M` or camera on any backend; GPU limits or device).
    #[error(transparent)]
    Backend(#[from] BackendError),
}

/// Generates, compresses and (if `with_references`) renders the references for one step on
/// `backend`. Returns the product and the VDI,
/// whose memory the next step reuses when handed back as `spare` (a VDI of tens of MB in
/// fresh memory costs a page fault per 4 KiB).
///
/// # Errors
/// [`WorkError`] from the core or the backend.
pub fn run(
    backend: &Backend,
    raw: &RawStep,
    gen: &Generation,
    tf: &(TransferFunction, String),
    with_references: bool,
    spare: Option<Vdi>,
) -> Result<(Product, Vdi), WorkError> {
    let raycaster = Raycaster::new(&raw.field, &tf.0, gen.raycast)?;
    let scene = backend.prepare(&raycaster)?;
    let camera = gen.camera_for(&raw.info);
    let tf_hash = tf.0.identity_hash();
    let generated = info_span!(
        "generate",
        r = gen.params.resolution,
        gamma = gen.params.gamma
    )
    .in_scope(|| scene.generate_reusing(&camera, gen.params, tf_hash, &tf.1, spare))?;
    let vdi = &generated.value;
    let t = Instant::now();
    let file =
        info_span!("compress", codec = %gen.codec).in_scope(|| codec::encode(vdi, gen.codec))?;
    let tau_compress_secs = t.elapsed().as_secs_f64();
    let references = if with_references {
        Some(references(&scene, &camera, raw, gen)?)
    } else {
        None
    };
    // Every field named: a field added to the header is a compile error here until it is set.
    let info = &raw.info;
    let product = Product {
        vdi_header: pb::VdiHeader {
            step: info.step,
            sim_time: info.sim_time,
            rank: info.rank,
            world_size: info.world_size,
            resolution: gen.params.resolution,
            gamma: gen.params.gamma,
            codec: codec_to_pb(gen.codec) as i32,
            total_bytes: file.len() as u64,
            supersegments: vdi.supersegments().len() as u64,
            tau_secs: generated.seconds,
            tau_compress_secs,
            tf_hash,
            tf_name: tf.1.clone(),
            tau_source: generated.source.name().into(),
            backend: backend.describe(),
            pm_version: gen.pm_version,
            global_dims: Some(dims_to_pb(info.global_dims)),
            brick_offset: Some(dims_to_pb(info.brick_offset)),
            brick_dims: Some(dims_to_pb(info.brick_dims)),
            with_references: references.is_some(),
        },
        vdi: Bytes::from(file),
        references,
        spool: raw.spooled(),
    };
    Ok((product, generated.value))
}

/// The reference frames of a sampled step: each test view rendered from the original data
/// on `scene`, as `views × h × w × (3 | 4)` little-endian f32 (see `ReferenceHeader`), with
/// their header.
fn references(
    scene: &Scene,
    camera: &Camera,
    raw: &RawStep,
    gen: &Generation,
) -> Result<(pb::ReferenceHeader, Bytes), WorkError> {
    let size = gen.reference_side();
    // One rank of several: each pixel carries its opacity too, so that the viz-node can
    // composite the ranks' frames into the whole domain's (`ReferenceHeader.opacity`).
    let opacity = raw.info.world_size > 1;
    let views = &gen.view_angles_deg;
    let span = info_span!("references", views = views.len(), size, opacity);
    let bytes: Vec<u8> = span.in_scope(|| -> Result<_, WorkError> {
        Ok(if opacity {
            render_references_with_opacity(scene, camera, views, size)
                .iter()
                .flat_map(|(image, alpha)| rgba_f32_le(image, alpha))
                .collect()
        } else {
            render_references(scene, camera, views, size)?
                .iter()
                .flat_map(Image::to_f32_le)
                .collect()
        })
    })?;
    let header = pb::ReferenceHeader {
        step: raw.info.step,
        rank: raw.info.rank,
        width: size,
        height: size,
        camera: Some(camera_to_pb(camera)),
        view_angles_deg: views.clone(),
        total_bytes: bytes.len() as u64,
        opacity,
    };
    Ok((header, Bytes::from(bytes)))
}

fn dims_to_pb(d: [usize; 3]) -> pb::Dims3 {
    pb::Dims3 {
        x: d[0] as u32,
        y: d[1] as u32,
        z: d[2] as u32,
    }
}

/// RGB and opacity as little-endian f32 RGBA, row-major (16 bytes per pixel).
fn rgba_f32_le<'a>(image: &'a Image, alpha: &'a [f32]) -> impl Iterator<Item = u8> + 'a {
    image
        .pixels()
        .iter()
        .zip(alpha)
        .flat_map(|(c, a)| [c[0], c[1], c[2], *a])
        .flat_map(f32::to_le_bytes)
}

/// The tuner's view of a finished production step: its summary (64-bin histogram over the
/// transfer function's domain, min/max, NaN count, and the production σ, τ, P_M) and the field
/// with its scene, to hold for trials.
pub fn for_tuner(
    raw: RawStep,
    gen: &Generation,
    tf: &(TransferFunction, String),
    product: &Product,
) -> (pb::StepSummary, crate::hold::HeldStep) {
    let [lo, hi] = tf.0.domain;
    let volume = raw.field;
    let h = insitu_core::volume::histogram(&volume.data(), lo, hi);
    let (min, max) = h
        .finite_range
        .map_or((f64::NAN, f64::NAN), |(a, b)| (f64::from(a), f64::from(b)));
    let summary = pb::StepSummary {
        step: raw.info.step,
        rank: raw.info.rank,
        world_size: raw.info.world_size,
        histogram: h.counts.to_vec(),
        range_lo: lo,
        range_hi: hi,
        min,
        max,
        nan_count: h.nan,
        voxels: volume.voxels().len() as u64,
        held: false,
        pm_version: gen.pm_version,
        resolution: gen.params.resolution,
        gamma: gen.params.gamma,
        sigma_bytes: product.vdi_header.total_bytes,
        tau_secs: product.vdi_header.tau_secs,
        sampled: product.references.is_some(),
        // Set when it is sent (`Tuning::after_step`).
        begun: 0,
    };
    let held = crate::hold::HeldStep {
        camera: gen.camera_for(&raw.info),
        volume: Arc::new(volume),
        tf: Arc::new(tf.clone()),
        raycast: gen.raycast,
        codec: gen.codec,
        view_angles_deg: gen.view_angles_deg.clone(),
        reference_size: gen.reference_size,
        references: Default::default(),
    };
    (summary, held)
}

/// Runs `f` on `pool` when there is one (every rayon loop inside uses its threads), else on
/// rayon's global pool (one thread per core). The `threads` key of the config sets the pool.
pub fn on_pool<R: Send>(pool: Option<&rayon::ThreadPool>, f: impl FnOnce() -> R + Send) -> R {
    match pool {
        Some(p) => p.install(f),
        None => f(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn work_runs_on_the_configured_threads() {
        let one = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap();
        assert_eq!(on_pool(Some(&one), rayon::current_num_threads), 1);
        let three = rayon::ThreadPoolBuilder::new()
            .num_threads(3)
            .build()
            .unwrap();
        assert_eq!(on_pool(Some(&three), rayon::current_num_threads), 3);
        assert_eq!(
            on_pool(None, rayon::current_num_threads),
            rayon::current_num_threads()
        );
    }
}
