//! One measurement of Alg. 1 (lines 11–18): generate a VDI for `P_M`, compress it (σ), render
//! it at the test views and compare with reference renders of the original data (q).
//!
//! Reference images depend only on the scene and the views, so they are rendered once
//! ([`render_references`]) and reused across candidates ([`evaluate`]).

use crate::backend::{BackendError, PreparedVdi, PreparedVolume, TimeSource, Timed};
use crate::camera::Camera;
use crate::image::Image;
use crate::metrics::{self, MetricError};
use crate::tf::TfIdentity;
use crate::vdi::codec::{self, Codec, CodecError, DecodeLimits};
use crate::vdi::{Precision, Vdi, VdiParams};
use std::time::Instant;

/// The paper's test views: the generation camera orbited by 0°, 10°, …, 60° (Sec. 6.1).
pub const DEFAULT_VIEW_ANGLES: [f32; 7] = [0.0, 10.0, 20.0, 30.0, 40.0, 50.0, 60.0];

/// Errors of an evaluation.
#[derive(Debug, thiserror::Error)]
pub enum EvalError {
    /// Encoding or decoding failed.
    #[error(transparent)]
    Codec(#[from] CodecError),
    /// Images could not be compared.
    #[error(transparent)]
    Metric(#[from] MetricError),
    /// The backend failed (bad parameters on any backend; GPU limits or device).
    #[error(transparent)]
    Backend(#[from] BackendError),
    /// Reference images do not match the views.
    #[error("{references} reference images for {views} views")]
    ReferenceCount {
        /// References given.
        references: usize,
        /// Views asked for.
        views: usize,
    },
    /// A VDI scored as a size probe's is not the one that probe made.
    #[error("the VDI holds {held} supersegments, not the {probed} its size probe measured")]
    NotTheProbes {
        /// Supersegments of the VDI given.
        held: u64,
        /// Supersegments the probe measured.
        probed: u64,
    },
}

/// Quality at one test view.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ViewScore {
    /// Orbit angle about +y, degrees.
    pub angle_deg: f32,
    /// Mean squared error against the reference.
    pub mse: f64,
    /// PSNR, dB (`+∞` when identical).
    pub q_db: f64,
    /// SSIM (see [`metrics::ssim`]); `None` when the image is under 11×11.
    pub ssim: Option<f64>,
}

/// The performance indicators (σ, q, τ) of one `P_M` (Sec. 5.3), with details.
#[derive(Clone, Debug, PartialEq)]
pub struct Evaluation {
    /// `P_M`.
    pub params: VdiParams,
    /// Codec σ was measured with.
    pub codec: Codec,
    /// σ and τ: what generating and encoding cost ([`generate_encoded`]).
    pub sizing: Sizing,
    /// Wall-clock seconds to decode the file again.
    pub tau_decode_secs: f64,
    /// Mean seconds to render the VDI at one test view (same source as τ).
    pub tau_render_secs: f64,
    /// q: PSNR of the mean MSE over the views, dB.
    pub q_db: f64,
    /// Per-view scores.
    pub views: Vec<ViewScore>,
}

/// Renders the reference (direct ray-casting) image at each view angle, `size × size`, on
/// the scene's backend.
///
/// # Errors
/// [`BackendError`] from the GPU path.
pub fn render_references(
    scene: &PreparedVolume,
    camera: &Camera,
    angles: &[f32],
    size: u32,
) -> Result<Vec<Image>, BackendError> {
    angles
        .iter()
        .map(|&a| Ok(scene.dvr(&camera.orbit_y(a), size, size)?.value))
        .collect()
}

/// [`render_references`] with each frame's accumulated opacity (see
/// [`crate::dvr::render_with_opacity`]): the frames of one rank's brick, to be composited
/// with the other ranks' ([`crate::compose::compose_frames`]). Rendered on the CPU whatever
/// the scene's backend (the GPU kernels write colour only).
pub fn render_references_with_opacity(
    scene: &PreparedVolume,
    camera: &Camera,
    angles: &[f32],
    size: u32,
) -> Vec<(Image, Vec<f32>)> {
    angles
        .iter()
        .map(|&a| {
            crate::dvr::render_with_opacity(scene.raycaster(), &camera.orbit_y(a), size, size)
        })
        .collect()
}

/// Renders `vdi` at each test view (`camera` orbited by each angle, at its reference's size)
/// and scores it against `references` (Alg. 1, lines 13–17). Returns the per-view scores,
/// the renders, and the total render time in seconds (kernel time on a GPU with timestamps).
/// The renders run one after another (each on every thread of the pool); the views' MSE and
/// SSIM, each one image's work on one thread, run side by side once all are rendered (the
/// same values: each view's scores are computed as alone).
///
/// # Errors
/// [`EvalError::ReferenceCount`] when there is not one reference per angle;
/// [`EvalError::Metric`] when images cannot be compared; [`EvalError::Backend`] from the GPU.
pub fn score_views(
    vdi: &PreparedVdi,
    camera: &Camera,
    angles: &[f32],
    references: &[Image],
    termination: f32,
) -> Result<(Vec<ViewScore>, Vec<Image>, f64), EvalError> {
    use rayon::prelude::*;
    one_reference_per_view(angles, references)?;
    let mut images = Vec::with_capacity(angles.len());
    let mut render_secs = 0.0;
    for (&angle_deg, reference) in angles.iter().zip(references) {
        let (w, h) = (reference.width(), reference.height());
        let rendered = vdi.render(&camera.orbit_y(angle_deg), w, h, termination)?;
        render_secs += rendered.seconds;
        images.push(rendered.value);
    }
    let views = angles
        .par_iter()
        .zip(images.par_iter().zip(references))
        .map(|(&angle_deg, (image, reference))| {
            let mse = metrics::mse(image, reference)?;
            Ok(ViewScore {
                angle_deg,
                mse,
                q_db: metrics::psnr_from_mse(mse),
                ssim: metrics::ssim(image, reference).ok(),
            })
        })
        .collect::<Result<Vec<_>, MetricError>>()?;
    Ok((views, images, render_secs))
}

/// Mean SSIM over the views, `None` when any view has none (images under 11×11).
pub fn mean_ssim(views: &[ViewScore]) -> Option<f64> {
    let ssims: Vec<f64> = views.iter().filter_map(|v| v.ssim).collect();
    (!ssims.is_empty() && ssims.len() == views.len())
        .then(|| ssims.iter().sum::<f64>() / ssims.len() as f64)
}

/// What generating and encoding `P_M` costs, without scoring it: the cheap half of a
/// measurement, enough to decide whether a candidate meets a size or time budget (the adaptive
/// search's probes: `Oracle::measure_sizing` in `insitu-tuner`; [`generate_encoded`]).
///
/// The one σ/τ record of the workspace: the tuner's measurements and probes and the
/// viz-node's index rows carry it (flattened in their JSON: the keys below). σ and τ are
/// required; records written before the others were kept everywhere read them as 0 and
/// `wall-clock`.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Sizing {
    /// σ: bytes of the compressed VDI file.
    pub sigma_bytes: u64,
    /// Supersegments in the VDI.
    #[serde(default)]
    pub supersegments: u64,
    /// τ: seconds of VDI generation, from `tau_source`.
    pub tau_secs: f64,
    /// Where τ comes from: wall clock (CPU) or GPU timestamps (kernel time, Sec. 5.3).
    #[serde(default)]
    pub tau_source: TimeSource,
    /// Wall-clock seconds of compression (reported apart from τ).
    #[serde(default)]
    pub tau_compress_secs: f64,
}

impl Sizing {
    /// One step of a world of ranks from its ranks' VDIs (docs/conventions.md, "A world of ranks"):
    /// σ and the supersegments summed (the step's VDIs together), τ and the compression time of
    /// the slowest rank (the step is done when its last rank is), the first rank's τ source.
    /// All zero for no ranks.
    pub fn of_ranks<'a>(ranks: impl IntoIterator<Item = &'a Sizing>) -> Sizing {
        Self::fold(ranks, u64::saturating_add)
    }

    /// The worst case of several (the same candidate on several steps): each field's largest,
    /// the first one's τ source. All zero for none.
    pub fn worst<'a>(all: impl IntoIterator<Item = &'a Sizing>) -> Sizing {
        Self::fold(all, u64::max)
    }

    /// `all` folded into one: σ and the supersegments by `sizes`, the times by their largest,
    /// the first one's τ source.
    fn fold<'a>(all: impl IntoIterator<Item = &'a Sizing>, sizes: fn(u64, u64) -> u64) -> Sizing {
        let mut all = all.into_iter().peekable();
        let tau_source = all.peek().map(|s| s.tau_source).unwrap_or_default();
        all.fold(
            Sizing {
                tau_source,
                ..Sizing::default()
            },
            |acc, s| Sizing {
                sigma_bytes: sizes(acc.sigma_bytes, s.sigma_bytes),
                supersegments: sizes(acc.supersegments, s.supersegments),
                tau_secs: acc.tau_secs.max(s.tau_secs),
                tau_source,
                tau_compress_secs: acc.tau_compress_secs.max(s.tau_compress_secs),
            },
        )
    }
}

/// Generates and encodes `params` without decoding, rendering or scoring: the file and its
/// σ and τ (the same as [`evaluate`]'s, at a fraction of its cost).
///
/// The VDI is generated into `spare`'s allocations when it holds one (the VDI of an earlier
/// call) and left there for the next call, as a generator-node generates each step into the
/// last step's VDI ([`PreparedVolume::generate_reusing`]): τ then counts what production pays per
/// step, not the first touch of a fresh VDI's memory (about 7–14 % of τ on the teapot at
/// r = 768, nothing measurable at r ≤ 256). `&mut None` generates afresh.
///
/// # Errors
/// [`EvalError`] for bad parameters, a codec failure or a GPU failure.
pub fn generate_encoded(
    scene: &PreparedVolume,
    camera: &Camera,
    params: VdiParams,
    codec_kind: Codec,
    tf: TfIdentity<'_>,
    spare: &mut Option<Vdi>,
) -> Result<(Vec<u8>, Sizing), EvalError> {
    let generated = scene.generate_reusing(camera, params, tf.hash, tf.name, spare.take())?;
    let encoded = encoded(&generated, codec_kind);
    *spare = Some(generated.value);
    encoded
}

/// The file of a generated VDI and its sizing: σ its length, τ the generation's, and the
/// encoding's own time.
fn encoded(generated: &Timed<Vdi>, codec_kind: Codec) -> Result<(Vec<u8>, Sizing), EvalError> {
    let t = Instant::now();
    let bytes = codec::encode(&generated.value, codec_kind)?;
    let size = Sizing {
        sigma_bytes: bytes.len() as u64,
        supersegments: generated.value.supersegments().len() as u64,
        tau_secs: generated.seconds,
        tau_source: generated.source,
        tau_compress_secs: t.elapsed().as_secs_f64(),
    };
    Ok((bytes, size))
}

/// Measures `params`: generate, encode, decode, render at each angle and compare with
/// `references` (one per angle, from [`render_references`]), generation and rendering on the
/// scene's backend. The VDI is rendered from the decoded file, so what is scored is what a
/// viz-node would see. Returns the VDI renders too. `tf` is the TF's identity (recorded in the
/// VDI); `spare` as in [`generate_encoded`].
///
/// # Errors
/// [`EvalError`] for bad parameters, a codec failure, references that do not match, or a
/// GPU failure.
#[allow(clippy::too_many_arguments)]
pub fn evaluate(
    scene: &PreparedVolume,
    camera: &Camera,
    params: VdiParams,
    codec_kind: Codec,
    angles: &[f32],
    references: &[Image],
    tf: TfIdentity<'_>,
    spare: &mut Option<Vdi>,
) -> Result<(Evaluation, Vec<Image>), EvalError> {
    one_reference_per_view(angles, references)?;
    let (bytes, size) = generate_encoded(scene, camera, params, codec_kind, tf, spare)?;
    let t = Instant::now();
    let decoded = codec::decode(&bytes, &DecodeLimits::default())?;
    let tau_decode_secs = t.elapsed().as_secs_f64();
    scored(
        scene,
        camera,
        (params, codec_kind),
        (size, tau_decode_secs),
        &decoded,
        angles,
        references,
    )
}

/// [`evaluate`] of a candidate whose σ was measured moments before on the same data: a size
/// probe of the same `P_M` on the same step, whose [`Sizing`] is `known`. At
/// [`Precision::Float32`] the VDI is generated and rendered but not encoded and decoded
/// again: that codec is lossless (a file decodes to the VDI it was made from, bit for bit),
/// so the renders, MSE and q are [`evaluate`]'s, without the codec's time (with bzip2
/// 30–60 ms of a 190–220 ms trial on the ocean: docs/performance.md, "The tuner's cost"),
/// and `tau_decode_secs` is 0. A quantised precision is scored on the decoded file, as the
/// viz-node scores it, written and read without the entropy coder (which is lossless, so the
/// decoded VDI is the same; `tau_decode_secs` is that file's). The result carries `known`'s σ and compression time with this
/// generation's τ. A VDI that does not hold `known.supersegments` supersegments (not the
/// data or the `P_M` `known` was measured on) is encoded after all, and its own σ reported.
///
/// # Errors
/// As [`evaluate`].
#[allow(clippy::too_many_arguments)]
pub fn evaluate_sized(
    scene: &PreparedVolume,
    camera: &Camera,
    params: VdiParams,
    codec_kind: Codec,
    angles: &[f32],
    references: &[Image],
    tf: TfIdentity<'_>,
    spare: &mut Option<Vdi>,
    known: Sizing,
) -> Result<(Evaluation, Vec<Image>), EvalError> {
    one_reference_per_view(angles, references)?;
    let generated = scene.generate_reusing(camera, params, tf.hash, tf.name, spare.take())?;
    let sized = generated.value.supersegments().len() as u64 == known.supersegments;
    let result = if sized {
        Ok(Sizing {
            tau_secs: generated.seconds,
            tau_source: generated.source,
            ..known
        })
    } else {
        encoded(&generated, codec_kind).map(|(_, size)| size)
    }
    .and_then(|sizing| {
        scored_as_decoded(
            scene,
            camera,
            (params, codec_kind),
            sizing,
            &generated.value,
            angles,
            references,
        )
    });
    *spare = Some(generated.value);
    result
}

/// [`evaluate_sized`] of the VDI its size probe made moments before: `vdi`, generated with
/// `params` from the same data and camera by the probe whose sizing is `known` (a trial's
/// spare VDI, left there by [`generate_encoded`]). It is scored without being generated again,
/// with the probe's σ and τ: generation is deterministic, so the renders, MSE and q are those
/// [`evaluate_sized`] gives (tested), without a second generation's time (a fifth to a
/// quarter of a trial's scoring at r ≥ 320). A VDI that does not hold `known.supersegments`
/// supersegments is refused as not the probe's.
///
/// # Errors
/// [`EvalError::ReferenceCount`]; [`EvalError::NotTheProbes`] for a VDI the probe did not
/// make; as [`evaluate`] for the codec and the backend.
pub fn evaluate_probed(
    scene: &PreparedVolume,
    camera: &Camera,
    (params, codec_kind): (VdiParams, Codec),
    angles: &[f32],
    references: &[Image],
    vdi: &Vdi,
    known: Sizing,
) -> Result<(Evaluation, Vec<Image>), EvalError> {
    one_reference_per_view(angles, references)?;
    let held = vdi.supersegments().len() as u64;
    if held != known.supersegments {
        return Err(EvalError::NotTheProbes {
            held,
            probed: known.supersegments,
        });
    }
    scored_as_decoded(
        scene,
        camera,
        (params, codec_kind),
        known,
        vdi,
        angles,
        references,
    )
}

/// The scoring of [`evaluate_sized`] and [`evaluate_probed`]: `vdi` scored as the viz-node
/// sees its file, with `sizing` measured before.
fn scored_as_decoded(
    scene: &PreparedVolume,
    camera: &Camera,
    (params, codec_kind): (VdiParams, Codec),
    sizing: Sizing,
    vdi: &Vdi,
    angles: &[f32],
    references: &[Image],
) -> Result<(Evaluation, Vec<Image>), EvalError> {
    // A quantised file is scored as the viz-node sees it: decoded. What decoding
    // changes is the quantisation alone (the entropy coder is lossless), so the file is
    // written and read without one: the same VDI, without the codec's time.
    let (decoded, tau_decode_secs) = match params.precision {
        Precision::Float32 => (None, 0.0),
        Precision::Bits(_) => {
            let bytes = codec::encode(vdi, Codec::None)?;
            let t = Instant::now();
            let decoded = codec::decode(&bytes, &DecodeLimits::default())?;
            (Some(decoded), t.elapsed().as_secs_f64())
        }
    };
    scored(
        scene,
        camera,
        (params, codec_kind),
        (sizing, tau_decode_secs),
        decoded.as_ref().unwrap_or(vdi),
        angles,
        references,
    )
}

/// [`EvalError::ReferenceCount`] unless there is one reference per view angle (checked before
/// anything is generated or rendered).
fn one_reference_per_view(angles: &[f32], references: &[Image]) -> Result<(), EvalError> {
    if references.len() == angles.len() {
        Ok(())
    } else {
        Err(EvalError::ReferenceCount {
            references: references.len(),
            views: angles.len(),
        })
    }
}

/// The scoring shared by [`evaluate`] and [`evaluate_sized`]: `vdi` rendered at each angle
/// and compared with `references`, with the sizing and decoding time measured before.
fn scored(
    scene: &PreparedVolume,
    camera: &Camera,
    (params, codec): (VdiParams, Codec),
    (sizing, tau_decode_secs): (Sizing, f64),
    vdi: &Vdi,
    angles: &[f32],
    references: &[Image],
) -> Result<(Evaluation, Vec<Image>), EvalError> {
    let (views, images, render_secs) = score_views(
        &scene.prepare_vdi(vdi)?,
        camera,
        angles,
        references,
        scene.raycaster().params().termination,
    )?;
    let tau_render_secs = render_secs / angles.len().max(1) as f64;
    let mses: Vec<f64> = views.iter().map(|v| v.mse).collect();
    Ok((
        Evaluation {
            params,
            codec,
            sizing,
            tau_decode_secs,
            tau_render_secs,
            q_db: metrics::pooled_psnr(&mses),
            views,
        },
        images,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::raycast::{RaycastParams, Raycaster};
    use crate::tf::{NamedTf, TransferFunction};
    use crate::volume::Volume;

    fn sizing(sigma_bytes: u64, supersegments: u64, tau_secs: f64, compress: f64) -> Sizing {
        Sizing {
            sigma_bytes,
            supersegments,
            tau_secs,
            tau_source: TimeSource::GpuTimestamps,
            tau_compress_secs: compress,
        }
    }

    /// A 20×18×16 field (a soft cylinder whose density rises and falls along z) and the ramp
    /// over its range: a few hundred supersegments at the resolutions the tests use.
    fn small_scene() -> (Volume, TransferFunction) {
        let volume = Volume::from_fn([20, 18, 16], |x, y, z| {
            let d = ((x as f32 - 9.5).powi(2) + (y as f32 - 8.5).powi(2)).sqrt();
            (1.0 - d / 9.0).max(0.0) * (0.6 + 0.4 * (z as f32 * 0.5).sin())
        })
        .unwrap();
        (volume, TransferFunction::default_for_range(0.0, 1.0))
    }

    /// A spare VDI changes where the VDI is built, never what it holds: generating into the
    /// VDI of another `P_M` (larger, then smaller) gives the file generated afresh, byte for
    /// byte, and leaves the new VDI as the next spare.
    #[test]
    fn generating_into_a_spare_gives_the_file_generated_afresh() {
        let (volume, tf) = small_scene();
        let rc = Raycaster::new(&volume, &tf, RaycastParams::default()).unwrap();
        let scene = PreparedVolume::Cpu(&rc);
        let camera = Camera::default_for_box(&volume.world_box()).orbit_y(25.0);
        let named = NamedTf::new(tf, "ramp");
        let tf = named.identity();
        let at = |resolution, gamma| VdiParams {
            resolution,
            gamma,
            precision: Default::default(),
        };
        let mut spare = None;
        for params in [at(40, 0.01), at(24, 0.05), at(48, 0.002)] {
            let (fresh, fresh_size) =
                generate_encoded(&scene, &camera, params, Codec::Zstd, tf, &mut None).unwrap();
            let had_spare = spare.is_some();
            let (reused, reused_size) =
                generate_encoded(&scene, &camera, params, Codec::Zstd, tf, &mut spare).unwrap();
            assert!(
                fresh_size.supersegments > 0,
                "{params:?}: an empty VDI tests nothing"
            );
            assert_eq!(reused, fresh, "{params:?}, into a spare: {had_spare}");
            assert_eq!(
                (reused_size.sigma_bytes, reused_size.supersegments),
                (fresh_size.sigma_bytes, fresh_size.supersegments)
            );
            let left = spare
                .as_ref()
                .map(|v| (v.resolution(), v.supersegments().len()));
            assert_eq!(
                left,
                Some((params.resolution, fresh_size.supersegments as usize))
            );
        }
    }

    /// A candidate whose σ a size probe measured is scored from the VDI itself, without
    /// encoding it again: the same views, MSE and q as the full evaluation (from the decoded
    /// file), with the probe's σ; a probe of other data (its supersegment count differs) is not
    /// trusted, and σ is measured.
    #[test]
    fn a_sized_candidate_scores_as_the_full_evaluation_without_the_codec() {
        let (volume, tf) = small_scene();
        let rc = Raycaster::new(&volume, &tf, RaycastParams::default()).unwrap();
        let scene = PreparedVolume::Cpu(&rc);
        let camera = Camera::default_for_box(&volume.world_box());
        let named = NamedTf::new(tf, "ramp");
        let tf = named.identity();
        let angles = [0.0, 40.0, 160.0];
        let refs = render_references(&scene, &camera, &angles, 32).unwrap();
        for precision in [Precision::Float32, Precision::Bits(8)] {
            sized_against_full(&scene, &camera, (&angles, &refs), tf, precision);
        }
    }

    /// [`a_sized_candidate_scores_as_the_full_evaluation_without_the_codec`] at `precision`.
    fn sized_against_full(
        scene: &PreparedVolume,
        camera: &Camera,
        (angles, refs): (&[f32], &[Image]),
        tf: TfIdentity<'_>,
        precision: Precision,
    ) {
        let params = VdiParams {
            resolution: 36,
            gamma: 0.01,
            precision,
        };
        let mut spare = None;
        let (_, probe) =
            generate_encoded(scene, camera, params, Codec::Bzip2, tf, &mut spare).unwrap();
        let (full, full_images) = evaluate(
            scene,
            camera,
            params,
            Codec::Bzip2,
            angles,
            refs,
            tf,
            &mut spare,
        )
        .unwrap();
        let (sized, sized_images) = evaluate_sized(
            scene,
            camera,
            params,
            Codec::Bzip2,
            angles,
            refs,
            tf,
            &mut spare,
            probe,
        )
        .unwrap();
        assert!(probe.supersegments > 0, "an empty VDI tests nothing");
        assert_eq!(sized_images, full_images);
        let mse = |e: &Evaluation| e.views.iter().map(|v| v.mse.to_bits()).collect::<Vec<_>>();
        assert_eq!(mse(&sized), mse(&full));
        assert_eq!(sized.q_db.to_bits(), full.q_db.to_bits());
        assert_eq!(
            (sized.sizing.sigma_bytes, sized.sizing.supersegments),
            (full.sizing.sigma_bytes, full.sizing.supersegments)
        );
        assert_eq!(sized.sizing.tau_compress_secs, probe.tau_compress_secs);
        if precision == Precision::Float32 {
            assert_eq!(sized.tau_decode_secs, 0.0);
        }
        // A probe that does not describe this VDI: σ is measured, not copied.
        let stale = Sizing {
            sigma_bytes: 1,
            supersegments: probe.supersegments + 1,
            ..probe
        };
        let (measured, _) = evaluate_sized(
            scene,
            camera,
            params,
            Codec::Bzip2,
            angles,
            refs,
            tf,
            &mut spare,
            stale,
        )
        .unwrap();
        assert_eq!(measured.sizing.sigma_bytes, full.sizing.sigma_bytes);
        assert_eq!(measured.sizing.supersegments, full.sizing.supersegments);
        // The probe's own VDI, scored without generating it again: the same renders and q,
        // with the probe's σ and τ; a VDI the probe did not make is refused.
        let (_, again) =
            generate_encoded(scene, camera, params, Codec::Bzip2, tf, &mut spare).unwrap();
        let vdi = spare.as_ref().unwrap();
        let key = (params, Codec::Bzip2);
        let (probed, probed_images) =
            evaluate_probed(scene, camera, key, angles, refs, vdi, again).unwrap();
        assert_eq!(probed_images, full_images);
        assert_eq!(mse(&probed), mse(&full));
        assert_eq!(probed.q_db.to_bits(), full.q_db.to_bits());
        assert_eq!(probed.sizing, again);
        let refused = evaluate_probed(scene, camera, key, angles, refs, vdi, stale);
        assert!(
            matches!(refused, Err(EvalError::NotTheProbes { held, probed })
                if held == again.supersegments && probed == stale.supersegments),
            "{refused:?}"
        );
    }

    #[test]
    fn ranks_add_sizes_and_wait_for_the_slowest_the_worst_takes_each_largest() {
        let a = sizing(100, 7, 0.5, 0.02);
        let b = sizing(40, 3, 0.9, 0.01);
        let world = Sizing::of_ranks([&a, &b]);
        assert_eq!(world, sizing(140, 10, 0.9, 0.02));
        assert_eq!(Sizing::worst([&a, &b]), sizing(100, 7, 0.9, 0.02));
        assert_eq!(Sizing::of_ranks([&a]), a);
        assert_eq!(Sizing::of_ranks(std::iter::empty()), Sizing::default());
        assert_eq!(Sizing::worst(std::iter::empty()), Sizing::default());
    }

    #[test]
    fn records_without_the_later_keys_still_read_and_sigma_tau_are_required() {
        let old: Sizing = serde_json::from_str(r#"{"sigma_bytes": 12, "tau_secs": 0.25}"#).unwrap();
        assert_eq!(
            old,
            Sizing {
                sigma_bytes: 12,
                tau_secs: 0.25,
                ..Sizing::default()
            }
        );
        assert_eq!(old.tau_source, TimeSource::WallClock);
        let full = sizing(1, 2, 3.0, 4.0);
        let json = serde_json::to_value(full).unwrap();
        assert_eq!(json["tau_source"], "gpu-timestamps");
        assert_eq!(serde_json::from_value::<Sizing>(json).unwrap(), full);
        assert!(serde_json::from_str::<Sizing>(r#"{"tau_secs": 0.25}"#).is_err());
        assert!(serde_json::from_str::<Sizing>(r#"{"sigma_bytes": 12}"#).is_err());
        for source in [TimeSource::WallClock, TimeSource::GpuTimestamps] {
            assert_eq!(TimeSource::from_name(source.name()), Some(source));
            assert_eq!(serde_json::to_value(source).unwrap(), source.name());
        }
        assert_eq!(TimeSource::from_name("wall clock"), None);
    }
}
