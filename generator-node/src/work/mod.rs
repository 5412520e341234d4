//! The CPU-bound part of a step (run on the blocking pool): VDI generation
//! `R(S_A, P_A, P_M)` (Sec. 3.2), compression (σ), and on sampled steps the reference frames
//! of the test views from the original data (Alg. 1, line 9).

use crate::config::Generation;
use crate::ingest::{RawStep, StepInfo};
use bytes::Bytes;
use insitu_core::backend::{Attempt, BackendError, PreparedVolume};
use insitu_core::compose::frame_to_le_bytes;
use insitu_core::evaluate::{render_references, render_references_with_opacity};
use insitu_core::vdi::codec;
use insitu_core::vdi::generate::Progress;
use insitu_core::vdi::provenance::Provenance;
use insitu_core::volume::bricks::Brick;
use insitu_core::{Backend, Camera, Image, NamedTf, Precision, Raycaster, Vdi, VdiParams};
use insitu_proto::pb;
use std::sync::Arc;
use std::time::Instant;
use tracing::info_span;

mod guard;
pub use guard::{Guard, MAX_GUARD_RETRIES};

/// A finished step, ready to ship.
#[derive(Debug, Clone)]
pub struct Product {
    /// VDI metadata (σ, τ, `P_M`, …).
    pub vdi_header: pb::VdiHeader,
    /// The compressed VDI file.
    pub vdi: Bytes,
    /// Reference frames, on sampled steps.
    pub references: Option<(pb::ReferenceHeader, Bytes)>,
    /// The step's file in the spool and its field bytes (each rank's, for a host's part),
    /// removed once the VDI is settled.
    pub spool: Vec<(String, u64)>,
    /// Generations made again at a coarser `P_M` because σ came out over the hard limit
    /// (`generation.size_max`) or the guard (`generation.size_guard`), or τ would have
    /// overrun `generation.time_max`, and their seconds
    /// (generation and compression of the VDIs thrown away, the stopped generations' time).
    pub limit_retries: (u32, f64),
    /// The step's first try, when it was made again coarser for its size (the hard limit or
    /// the guard): what the decided `P_M` came to on this step, which the tuner is told.
    pub first_try: Option<FirstTry>,
}

/// What a step's first try came to: the decided `P_M`, σ of its file (bytes) and its
/// generation's seconds.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FirstTry {
    /// The `P_M` the step was decided at.
    pub params: VdiParams,
    /// σ of the first try's file, bytes.
    pub sigma_bytes: u64,
    /// Its generation's seconds.
    pub tau_secs: f64,
}

impl Product {
    /// The ranks whose steps this product settles: those of a host's part, else its rank.
    pub fn ranks(&self) -> Vec<u32> {
        let h = &self.vdi_header;
        if h.covers.is_empty() {
            vec![h.rank]
        } else {
            h.covers.clone()
        }
    }

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
    /// σ stayed over the hard limit at the coarsest `P_M` the step may take.
    #[error("σ {sigma} B of step {step} stays over the hard limit of {limit} B for this rank even at r {r}, γ {gamma}: the VDI is not shipped")]
    OverLimit {
        /// The step.
        step: u64,
        /// σ at the coarsest `P_M` tried, bytes.
        sigma: u64,
        /// The limit for this rank, bytes.
        limit: u64,
        /// That `P_M`.
        r: u32,
        /// That `P_M`.
        gamma: f32,
    },
    /// τ would overrun the hard limit and no coarser `P_M` fits the time left.
    #[error("τ of step {step} would overrun the hard limit of {limit} s at r {r}, γ {gamma} ({spent:.3} s spent; {why}): the VDI is not shipped")]
    OverTime {
        /// The step.
        step: u64,
        /// Seconds of generation spent on the step.
        spent: f64,
        /// The limit, seconds.
        limit: f64,
        /// The `P_M` of the last try.
        r: u32,
        /// The `P_M` of the last try.
        gamma: f32,
        /// Why no try is left.
        why: &'static str,
    },
}

/// γ is raised up to this when a VDI comes out over the hard limit (far above any γ worth
/// tuning: at 2 nearly every ray closes one supersegment per run of visible samples).
pub const MAX_LIMIT_GAMMA: f32 = 2.0;

/// Tries a step may take to come under the hard limit (generations, and encodings at a
/// coarser precision).
pub const MAX_LIMIT_RETRIES: u32 = 8;

/// The fewest colour bits the hard limit lowers a file's precision to: at 6 bits q stayed
/// within 0.62 dB of the float VDI's on the shared volumes (docs/performance.md).
pub const MIN_LIMIT_BITS: u8 = 6;

/// Share of the time left that a generation made again under the time limit plans for: the
/// rate the stopped one measured spreads on a busy machine.
pub const TIME_RETRY_SHARE: f64 = 0.6;

/// The coarsest resolution a generation is made again at under the time limit.
pub const MIN_LIMIT_RESOLUTION: u32 = 8;

/// Whether a generation at `progress`, after `spent` seconds of the step's earlier tries,
/// stops under the time limit `limit`: at the limit; and, when a try is left (`can_retry`),
/// as soon as the time it projects for the whole ([`Progress::projected`]: its set-up plus its
/// marching scaled to the whole) would overrun it, once a fifth of the work is done or half
/// the time gone, so a retry has time. Before any work is done nothing is projected.
pub fn must_stop(limit: f64, spent: f64, can_retry: bool, progress: Progress) -> bool {
    let now = spent + progress.seconds;
    let over = progress
        .projected()
        .is_some_and(|whole| spent + whole > limit);
    now >= limit || (can_retry && (progress.done >= 0.2 || now >= 0.5 * limit) && over)
}

/// The `P_M` a generation stopped at `progress` under the time limit is made again with,
/// `left` seconds before the limit: the resolution whose r² rays the marching rate it measured
/// fits into [`TIME_RETRY_SHARE`] of the time left less a set-up like its own (without the
/// work done once per ray-caster; τ ∝ r² beyond the set-up: a ray is as long at any r), at
/// most ⅞ of its r; `None` for a world of several ranks (`may_shrink_r`: they must share r),
/// below [`MIN_LIMIT_RESOLUTION`] or with no time left.
pub fn faster(
    p: VdiParams,
    progress: Progress,
    left: f64,
    may_shrink_r: bool,
) -> Option<VdiParams> {
    if !may_shrink_r || left <= 0.0 {
        return None;
    }
    // A try stopped before any band finished is taken to have done one band (1/32).
    let marching = (progress.seconds - progress.setup) / progress.done.max(1.0 / 32.0);
    let room = TIME_RETRY_SHARE * left - (progress.setup - progress.setup_once);
    if room <= 0.0 {
        return None;
    }
    let scale = (room / marching.max(1e-9)).sqrt().min(0.875);
    let r = (f64::from(p.resolution) * scale).floor() as u32;
    (r >= MIN_LIMIT_RESOLUTION).then_some(VdiParams { resolution: r, ..p })
}

/// The `P_M` a VDI whose σ is `over` times the limit is made again with. First the file's
/// precision, which costs no generation (the same VDI encoded again): floats and more than 8
/// bits to 8 bits (σ 1.4–4.3× smaller for ≤ 0.06 dB), then 8 or 7 bits to [`MIN_LIMIT_BITS`]
/// (σ 15–42 % smaller). Then γ raised by the factor and 15 % more (σ falls about as 1/γ, Sec.
/// 6.1), at least by a quarter, up to [`MAX_LIMIT_GAMMA`] (a step just over the limit loses
/// little q, one far over needs few retries); from there the resolution shrunk by the
/// factor's square root (σ ∝ r²), at least by an eighth, when `may_shrink_r` (a world of one
/// rank: the ranks of a step must share r to be composed). `None` when none can go further.
pub fn coarser(p: VdiParams, over: f64, may_shrink_r: bool) -> Option<VdiParams> {
    let fewer = match p.precision {
        Precision::Float32 => Some(8),
        Precision::Bits(b) if b > 8 => Some(8),
        Precision::Bits(b) if b > MIN_LIMIT_BITS => Some(MIN_LIMIT_BITS),
        Precision::Bits(_) => None,
    };
    if let Some(bits) = fewer {
        return Some(VdiParams {
            precision: Precision::Bits(bits),
            ..p
        });
    }
    let factor = (over * 1.15).max(1.25) as f32;
    if p.gamma < MAX_LIMIT_GAMMA {
        let gamma = (p.gamma.max(1e-3) * factor).min(MAX_LIMIT_GAMMA);
        return Some(VdiParams { gamma, ..p });
    }
    shrunk(p, over, may_shrink_r)
}

/// `p` with r shrunk by the square root of `over` (σ ∝ r²), at least by an eighth, where
/// `may_shrink_r`; `None` where it may not or r would not shrink.
fn shrunk(p: VdiParams, over: f64, may_shrink_r: bool) -> Option<VdiParams> {
    let r = (f64::from(p.resolution) / over.max(1.0).sqrt()).min(f64::from(p.resolution) * 0.875);
    let r = r.floor() as u32;
    (may_shrink_r && r >= 1 && r < p.resolution).then_some(VdiParams { resolution: r, ..p })
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
    tf: &NamedTf,
    with_references: bool,
    spare: Option<Vdi>,
) -> Result<(Product, Vdi), WorkError> {
    let raycaster = Raycaster::new(&raw.field, &tf.tf, gen.raycast)?;
    let id = tf.identity();
    let scene = backend.prepare(&raycaster)?;
    let camera = gen.camera_for(&raw.info);
    let info = &raw.info;
    // The hard limit is the step's; each rank keeps its share.
    let own = gen.limits.share(info.world_size);
    let (limit, time_limit) = (own.size_bytes, own.time_secs);
    let one_rank = info.world_size <= 1;
    let guard = Guard::of(gen, info.world_size);
    // The step's tries (`P_M`, σ), for the guard's next; the first for the tuner.
    let (mut first_try, mut tries) = (None, Vec::new());
    let (mut params, mut spare, mut retries) = (gen.params, spare, (0u32, 0.0));
    let (generated, file, tau_secs, tau_compress_secs) = 'generate: loop {
        let can_retry = one_rank && retries.0 < MAX_LIMIT_RETRIES;
        let spent = retries.1;
        let stop = |p: Progress| time_limit.is_some_and(|t| must_stop(t, spent, can_retry, p));
        let attempt = info_span!("generate", r = params.resolution, gamma = params.gamma)
            .in_scope(|| {
                scene.generate_until(&camera, params, id.hash, id.name, spare.take(), &stop)
            })?;
        let generated = match attempt {
            Attempt::Done(generated) => generated,
            Attempt::Stopped { spare: s, progress } => {
                retries = (retries.0 + 1, retries.1 + progress.seconds);
                let limit = time_limit.unwrap_or(0.0);
                params = after_overrun(info, params, progress, (limit, retries.1), can_retry)?;
                spare = Some(s);
                continue;
            }
        };
        // τ counts every generation of the step, the ones thrown away too. A band that ran
        // past the limit, or the GPU's kernel that runs whole:
        let why = "the last try finished over it";
        within_time(
            info.step,
            time_limit,
            generated.seconds + retries.1,
            params,
            why,
        )?;
        let mut generated = generated;
        // This generation's encodings: a coarser precision is tried on the same VDI.
        loop {
            let t = Instant::now();
            let provenance = provenance(info, gen.pm_version, gen.scene_version);
            let file = info_span!("compress", codec = %gen.codec).in_scope(|| {
                codec::encode_with_provenance(&generated.value, gen.codec, Some(&provenance))
            })?;
            let compress = t.elapsed().as_secs_f64();
            let sigma = file.len() as u64;
            // What the step's first try (the decided `P_M`) came to, for the tuner.
            first_try.get_or_insert(FirstTry {
                params,
                sigma_bytes: sigma,
                tau_secs: generated.seconds,
            });
            tries.push((params, sigma));
            let sizes = (limit, guard, one_rank);
            let Some(next) = after_try(info.step, &tries, sizes, retries.0)? else {
                let tau = generated.seconds + retries.1;
                // Encodings thrown away for the size limit count in τ too.
                let why = "encoding again for the size limit took it over";
                within_time(info.step, time_limit, tau, params, why)?;
                break 'generate (generated, file, tau, compress);
            };
            retries.0 += 1;
            if (next.resolution, next.gamma) == (params.resolution, params.gamma) {
                generated.value.set_precision(next.precision);
                // An encoding thrown away counts in τ, as a generation thrown away does.
                retries.1 += compress;
                params = next;
                continue;
            }
            retries.1 += generated.seconds + compress;
            params = next;
            spare = Some(generated.value);
            continue 'generate;
        }
    };
    let references = with_references
        .then(|| references(&scene, &camera, raw, gen))
        .transpose()?;
    let taus = (tau_secs, tau_compress_secs);
    let vdi_header = header(backend, raw, gen, tf, &generated, (params, &file), taus);
    let product = Product {
        vdi_header: pb::VdiHeader {
            with_references: references.is_some(),
            ..vdi_header
        },
        vdi: Bytes::from(file),
        references,
        spool: raw.spooled().into_iter().collect(),
        limit_retries: retries,
        first_try: first_try.filter(|f| f.params != params),
    };
    Ok((product, generated.value))
}

/// After the try of step `step` that made the last of `tries` (`P_M`, σ in bytes), under
/// the hard limit, the guard and whether r may shrink (`sizes`), `retries` tries made again
/// so far: the `P_M` to make it again with (logged), or `None` to ship it. Over the hard
/// limit it is [`coarser`]; over the guard's trigger, the guard's next (which ships the last
/// try when it has none).
///
/// # Errors
/// [`WorkError::OverLimit`] when σ is over the hard limit and no try is left.
fn after_try(
    step: u64,
    tries: &[(VdiParams, u64)],
    (limit, guard, one_rank): (Option<u64>, Option<Guard>, bool),
    retries: u32,
) -> Result<Option<VdiParams>, WorkError> {
    let Some(&(params, sigma)) = tries.last() else {
        return Ok(None);
    };
    let hard = limit.filter(|&l| sigma >= l);
    let guarded = guard.filter(|g| sigma > g.trigger && retries < MAX_GUARD_RETRIES);
    let (next, toward, why) = match (hard, guarded) {
        (None, None) => return Ok(None),
        (Some(l), _) => {
            let next = coarser(params, sigma as f64 / l as f64, one_rank);
            let next = next.filter(|_| retries < MAX_LIMIT_RETRIES);
            (next, l, "σ over the hard limit")
        }
        (None, Some(g)) => (
            g.next(tries, one_rank),
            g.aim,
            "σ over the guard on the tuner's budget",
        ),
    };
    let Some(next) = next else {
        return match hard {
            // The guard ships the last try, whatever it came to.
            None => Ok(None),
            Some(limit) => Err(WorkError::OverLimit {
                step,
                sigma,
                limit,
                r: params.resolution,
                gamma: params.gamma,
            }),
        };
    };
    if (next.resolution, next.gamma) == (params.resolution, params.gamma) {
        let precision = next.precision;
        tracing::info!(step, sigma, toward, %precision, "{why}: encoded again at a coarser precision");
    } else {
        let (r, gamma) = (next.resolution, next.gamma);
        tracing::info!(
            step,
            sigma,
            toward,
            r,
            gamma,
            "{why}: made again at a coarser P_M"
        );
    }
    Ok(Some(next))
}

/// [`WorkError::OverTime`] for step `step` when `tau` seconds (every try counted) exceed the
/// hard limit `time_limit`, the last try at `params`; `why` says how it came over.
fn within_time(
    step: u64,
    time_limit: Option<f64>,
    tau: f64,
    params: VdiParams,
    why: &'static str,
) -> Result<(), WorkError> {
    match time_limit.filter(|&t| tau > t) {
        Some(limit) => Err(WorkError::OverTime {
            step,
            spent: tau,
            limit,
            r: params.resolution,
            gamma: params.gamma,
            why,
        }),
        None => Ok(()),
    }
}

/// The P_M to make `info`'s step again with after a generation stopped at `progress` because
/// τ would overrun the hard limit: `(limit, spent)` seconds, `spent` by every try so far.
///
/// # Errors
/// [`WorkError::OverTime`] when no retry is left (or the ranks of a step share r) or no
/// resolution fits the time left.
fn after_overrun(
    info: &StepInfo,
    params: VdiParams,
    progress: Progress,
    (limit, spent): (f64, f64),
    can_retry: bool,
) -> Result<VdiParams, WorkError> {
    let one_rank = info.world_size <= 1;
    let over = |why| WorkError::OverTime {
        step: info.step,
        spent,
        limit,
        r: params.resolution,
        gamma: params.gamma,
        why,
    };
    if !can_retry {
        return Err(over(if one_rank {
            "no retry left"
        } else {
            "the ranks of a step share r"
        }));
    }
    let next = faster(params, progress, limit - spent, one_rank)
        .ok_or_else(|| over("no resolution fits the time left"))?;
    tracing::info!(
        step = info.step,
        done = progress.done,
        seconds = progress.seconds,
        setup = progress.setup,
        limit,
        r = next.resolution,
        "τ would overrun the hard limit: made again at a lower resolution"
    );
    Ok(next)
}

/// The header of the VDI `file` made of `raw` at `params`: τ and τ_compress as `taus`, no
/// reference frames.
fn header(
    backend: &Backend,
    raw: &RawStep,
    gen: &Generation,
    tf: &NamedTf,
    generated: &insitu_core::backend::Timed<Vdi>,
    (params, file): (VdiParams, &[u8]),
    (tau_secs, tau_compress_secs): (f64, f64),
) -> pb::VdiHeader {
    let info = &raw.info;
    // Every field named: a field added to the header is a compile error here until it is set.
    pb::VdiHeader {
        step: info.step,
        sim_time: info.sim_time,
        rank: info.rank,
        world_size: info.world_size,
        resolution: params.resolution,
        gamma: params.gamma,
        codec: pb::Codec::from(gen.codec) as i32,
        total_bytes: file.len() as u64,
        supersegments: generated.value.supersegments().len() as u64,
        tau_secs,
        tau_compress_secs,
        // As the VDI records them (its provenance, which the viz-node checks against these).
        tf_hash: generated.value.meta().tf_hash,
        tf_name: generated.value.meta().tf_name.clone(),
        // A few hundred bytes beside a VDI of kilobytes to megabytes.
        tf: Some(pb::TransferFunction::from(&tf.tf)),
        tau_source: pb::TauSource::from(generated.source) as i32,
        backend: backend.describe(),
        pm_version: gen.pm_version,
        global_dims: Some(pb::Dims3::from(info.global_dims)),
        brick_offset: Some(pb::Dims3::from(info.brick_offset)),
        brick_dims: Some(pb::Dims3::from(info.brick_dims)),
        with_references: false,
        covers: Vec::new(),
        scene_version: gen.scene_version,
    }
}

/// Where the VDI of `info`'s step and rank comes from, as its file carries it.
fn provenance(info: &StepInfo, pm_version: u64, scene_version: u64) -> Provenance {
    Provenance {
        scene_version,
        step: info.step,
        rank: info.rank,
        world_size: info.world_size.max(1),
        pm_version,
        sim_time: if info.sim_time.is_finite() {
            info.sim_time
        } else {
            0.0
        },
        // Ingest checked the brick against the grid; one that does not fit is left unsaid
        // rather than making the file unreadable.
        placement: (0..3)
            .all(|a| {
                info.brick_dims[a] >= 1
                    && info.brick_offset[a] + info.brick_dims[a] <= info.global_dims[a]
            })
            .then_some((
                info.global_dims,
                Brick {
                    offset: info.brick_offset,
                    dims: info.brick_dims,
                },
            )),
        covers: Vec::new(),
    }
}

/// The reference frames of a sampled step: each test view rendered from the original data
/// on `scene`, as `views × h × w × (3 | 4)` little-endian f32 (see `ReferenceHeader`), with
/// their header.
fn references(
    scene: &PreparedVolume,
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
                .flat_map(|(image, alpha)| frame_to_le_bytes(image, alpha))
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
        camera: Some(pb::Camera::from(camera)),
        view_angles_deg: views.clone(),
        total_bytes: bytes.len() as u64,
        opacity,
        covers: Vec::new(),
    };
    Ok((header, Bytes::from(bytes)))
}

/// The tuner's view of a finished production step: its summary (64-bin histogram over the
/// transfer function's domain, min/max, NaN count, and the production σ, τ, P_M) and the field
/// with its scene, to hold for trials.
pub fn for_tuner(
    raw: RawStep,
    gen: &Generation,
    tf: &NamedTf,
    product: &Product,
) -> (pb::StepSummary, crate::hold::HeldStep) {
    let [lo, hi] = tf.tf.domain;
    let domain = raw.info.global_box();
    let volume = raw.field;
    let h = insitu_core::volume::histogram(&volume.data(), lo, hi);
    let (min, max) = h
        .finite_range
        .map_or((f64::NAN, f64::NAN), |(a, b)| (f64::from(a), f64::from(b)));
    // What the decided P_M came to, where the step was made again coarser for its size: the
    // decision's evidence (a step over the budget makes a tuning due, one far over its plan
    // is characteristic), which the VDI shipped would hide.
    let (resolution, gamma, sigma_bytes, tau_secs) = match product.first_try {
        Some(f) => (
            f.params.resolution,
            f.params.gamma,
            f.sigma_bytes,
            f.tau_secs,
        ),
        None => {
            let h = &product.vdi_header;
            (h.resolution, h.gamma, h.total_bytes, h.tau_secs)
        }
    };
    let summary = pb::StepSummary {
        precision_bits: gen.params.precision.bits(),
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
        // The P_M the VDI was made with (coarser than the version's after a time limit).
        resolution,
        gamma,
        sigma_bytes,
        tau_secs,
        sampled: product.references.is_some(),
        // Set when it is sent (`Tuning::after_step`).
        begun: 0,
        received: 0,
        scene_version: gen.scene_version,
        fields: raw.fields.clone(),
        box_min: Some(pb::Vec3::from(domain.min)),
        box_max: Some(pb::Vec3::from(domain.max)),
    };
    let held = crate::hold::HeldStep {
        camera: gen.camera_for(&raw.info),
        volume: Arc::new(volume),
        tf: Arc::new(tf.clone()),
        raycast: gen.raycast,
        codec: gen.codec,
        precision: gen.params.precision,
        view_angles_deg: gen.view_angles_deg.clone(),
        reference_size: gen.reference_size,
        references: Default::default(),
        sizes: Default::default(),
    };
    (summary, held)
}

#[cfg(test)]
mod tests;
