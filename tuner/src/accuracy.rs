//! What accuracy costs in time: one scene, each knob that trades quality for speed swept on
//! its own from a base setting, with q, τ and σ per setting.
//!
//! - Ray-casting step and early-termination threshold: the direct rendering at each setting
//!   against a ground truth at a quarter of the base step without early termination; τ is the
//!   rendering time per view.
//! - Empty-space skipping and shading: τ of the direct rendering with each on and off (skipping
//!   must not change the image: its q against the rendering without it is reported).
//! - r, γ and generation's early termination (0.99, 0.999, 0.9999, off): the VDI (generated,
//!   compressed, decoded, rendered at the test views) against the direct rendering at the base
//!   setting, as in the paper; τ is generation time.
//! - Codec: σ and compression time (lossless: q does not change).
//!
//! Supersegments are stored as f32: there is no storage-precision knob yet.

use crate::grid::Candidate;
use crate::measure::Measurement;
use crate::study::{Oracle, Study, StudyError, StudySetup};
use insitu_core::backend::BackendError;
use insitu_core::evaluate::EvalError;
use insitu_core::metrics::{mse, pooled_psnr};
use insitu_core::raycast::RaycastError;
use insitu_core::vdi::codec::{self, Codec};
use insitu_core::vdi::VdiParams;
use insitu_core::{
    Backend, Camera, Image, RaycastParams, Raycaster, Shading, TransferFunction, Volume,
};
use std::time::Instant;

/// One setting of one knob.
#[derive(Clone, Debug, PartialEq)]
pub struct AccuracyRow {
    /// The knob.
    pub knob: &'static str,
    /// Its value, as text.
    pub value: String,
    /// q against the knob's reference, dB (`None` where quality is not what the row shows).
    pub q_db: Option<f64>,
    /// Time of what the knob affects, seconds.
    pub tau_secs: f64,
    /// What `tau_secs` measures.
    pub tau_of: &'static str,
    /// σ, bytes (VDI rows).
    pub sigma_bytes: Option<u64>,
}

/// Errors of a sweep.
#[derive(Debug, thiserror::Error)]
pub enum AccuracyError {
    /// Bad ray-casting parameters.
    #[error(transparent)]
    Raycast(#[from] RaycastError),
    /// A VDI measurement failed.
    #[error(transparent)]
    Study(#[from] StudyError),
    /// Generating or encoding the codec rows' VDI failed.
    #[error(transparent)]
    Eval(#[from] EvalError),
    /// The backend failed (GPU limits or device).
    #[error(transparent)]
    Backend(#[from] BackendError),
}

/// The scene and the base setting of a sweep.
pub struct Sweep<'a> {
    /// The volume.
    pub volume: &'a Volume,
    /// Its transfer function and name.
    pub tf: &'a TransferFunction,
    /// The transfer function's name.
    pub tf_name: &'a str,
    /// Base ray-casting parameters.
    pub base: RaycastParams,
    /// Generation camera; views orbit it.
    pub camera: Camera,
    /// Test views, degrees.
    pub views: &'a [f32],
    /// Image side, pixels.
    pub size: u32,
    /// Base `P_M`.
    pub base_pm: Candidate,
    /// Base codec.
    pub codec: Codec,
    /// Where rendering and generation run (τ is that backend's time).
    pub backend: &'a Backend,
}

fn dvr_at(s: &Sweep, params: RaycastParams) -> Result<(Vec<Image>, f64), AccuracyError> {
    let rc = Raycaster::new(s.volume, s.tf, params)?;
    let scene = s.backend.prepare(&rc)?;
    let mut secs = 0.0;
    let mut images = Vec::with_capacity(s.views.len());
    for &a in s.views {
        let r = scene.dvr(&s.camera.orbit_y(a), s.size, s.size)?;
        secs += r.seconds;
        images.push(r.value);
    }
    Ok((images, secs / s.views.len().max(1) as f64))
}

fn pooled(images: &[Image], references: &[Image]) -> f64 {
    let mses: Vec<f64> = images
        .iter()
        .zip(references)
        .map(|(a, b)| mse(a, b).unwrap_or(f64::INFINITY))
        .collect();
    pooled_psnr(&mses)
}

/// One row of a knob that changes only the direct rendering: rendered at `params`, scored
/// against `reference` when given.
fn dvr_row(
    s: &Sweep,
    knob: &'static str,
    value: String,
    params: RaycastParams,
    reference: Option<&[Image]>,
) -> Result<AccuracyRow, AccuracyError> {
    let (images, tau_secs) = dvr_at(s, params)?;
    Ok(AccuracyRow {
        knob,
        value,
        q_db: reference.map(|r| pooled(&images, r)),
        tau_secs,
        tau_of: "DVR per view",
        sigma_bytes: None,
    })
}

fn vdi_rows(
    study: &mut Study,
    knob: &'static str,
    cands: &[(String, Candidate)],
) -> Result<Vec<AccuracyRow>, StudyError> {
    cands
        .iter()
        .map(|(value, c)| {
            let m: Measurement = study.measure(*c)?;
            Ok(AccuracyRow {
                knob,
                value: value.clone(),
                q_db: Some(m.q()),
                tau_secs: m.sizing.tau_secs,
                tau_of: "VDI generation",
                sigma_bytes: Some(m.sizing.sigma_bytes),
            })
        })
        .collect()
}

/// A study of the sweep's scene as `rc` ray-casts it (uncached: each row is measured afresh).
fn study_of<'a>(s: &Sweep<'a>, rc: &'a Raycaster<'a>) -> Result<Study<'a>, AccuracyError> {
    let scene = StudySetup::new(
        s.backend.prepare(rc)?,
        s.volume.content_hash(),
        s.tf,
        s.tf_name,
        s.camera,
        s.views,
        (s.size, s.size),
        s.codec,
    )?;
    Ok(Study::new(scene, None))
}

/// Runs the sweep (see the module docs).
///
/// # Errors
/// [`AccuracyError`] for bad base parameters or a failed measurement.
pub fn sweep(s: &Sweep) -> Result<Vec<AccuracyRow>, AccuracyError> {
    let mut rows = dvr_rows(s)?;
    let rc = Raycaster::new(s.volume, s.tf, s.base)?;
    rows.extend(vdi_rows_of_knobs(s, &rc)?);
    rows.extend(codec_rows(s, &rc)?);
    Ok(rows)
}

/// The direct rendering's knobs: the step and early termination against a reference of a
/// quarter step without termination, empty-space skipping against the base rendering, and
/// shading (an effect, so no q).
fn dvr_rows(s: &Sweep) -> Result<Vec<AccuracyRow>, AccuracyError> {
    let mut rows = Vec::new();
    let truth_params = RaycastParams {
        sample_distance: s.base.sample_distance / 4.0,
        termination: 1.0,
        ..s.base
    };
    let (truth, _) = dvr_at(s, truth_params)?;
    let b = s.base.sample_distance;
    for step in [b / 2.0, b, 2.0 * b, 4.0 * b] {
        let p = RaycastParams {
            sample_distance: step,
            ..s.base
        };
        rows.push(dvr_row(
            s,
            "ray-casting step",
            format!("{step}"),
            p,
            Some(&truth),
        )?);
    }
    for termination in [0.9f32, 0.95, 0.99, 0.999, 1.0] {
        let p = RaycastParams {
            termination,
            ..s.base
        };
        rows.push(dvr_row(
            s,
            "early termination",
            format!("{termination}"),
            p,
            Some(&truth),
        )?);
    }
    let (base_images, _) = dvr_at(s, s.base)?;
    for skipping in [true, false] {
        let p = RaycastParams {
            empty_space_skipping: skipping,
            ..s.base
        };
        let value = if skipping { "on" } else { "off" };
        rows.push(dvr_row(
            s,
            "empty-space skipping",
            value.into(),
            p,
            Some(&base_images),
        )?);
    }
    for shading in [None, Some(Shading::default())] {
        let p = RaycastParams { shading, ..s.base };
        let value = if shading.is_some() {
            "Blinn-Phong"
        } else {
            "off"
        };
        rows.push(dvr_row(
            s,
            "shading (effect, not accuracy)",
            value.into(),
            p,
            None,
        )?);
    }
    Ok(rows)
}

/// The VDI's knobs, each around the base P_M: r, γ and generation's early termination.
fn vdi_rows_of_knobs(s: &Sweep, rc: &Raycaster) -> Result<Vec<AccuracyRow>, AccuracyError> {
    let mut study = study_of(s, rc)?;
    let pm = s.base_pm;
    let rs: Vec<(String, Candidate)> = [pm.r / 2, pm.r, pm.r * 2]
        .into_iter()
        .filter(|&r| r >= 1)
        .map(|r| (format!("{r}"), Candidate { r, ..pm }))
        .collect();
    let mut rows = vdi_rows(&mut study, "VDI resolution r", &rs)?;
    let gammas: Vec<(String, Candidate)> = [0.001f32, 0.013, 0.05, 0.13, 0.26]
        .into_iter()
        .map(|gamma| (format!("{gamma}"), Candidate { gamma, ..pm }))
        .collect();
    rows.extend(vdi_rows(&mut study, "VDI threshold γ", &gammas)?);
    // Generation's own early termination: the VDI at the base P_M with each threshold, scored
    // against the same direct renderings (their termination stays the base one).
    for generation_termination in [Some(0.99f32), Some(0.999), Some(0.9999), None] {
        let params = RaycastParams {
            generation_termination,
            ..s.base
        };
        let rc = Raycaster::new(s.volume, s.tf, params)?;
        let value = generation_termination.map_or("off".into(), |a| format!("{a}"));
        rows.extend(vdi_rows(
            &mut study_of(s, &rc)?,
            "generation early termination",
            &[(value, pm)],
        )?);
    }
    Ok(rows)
}

/// The codecs (lossless): one VDI at the base P_M, encoded by each; σ and the compression
/// time.
fn codec_rows(s: &Sweep, rc: &Raycaster) -> Result<Vec<AccuracyRow>, AccuracyError> {
    let pm = s.base_pm;
    let mut rows = Vec::new();
    let params = VdiParams {
        resolution: pm.r,
        gamma: pm.gamma,
        precision: Default::default(),
    };
    let vdi = s
        .backend
        .prepare(rc)?
        .generate(&s.camera, params, s.tf.identity_hash(), s.tf_name)
        .map_err(EvalError::from)?
        .value;
    for codec in Codec::ALL {
        let t = Instant::now();
        let bytes = codec::encode(&vdi, codec).map_err(EvalError::from)?;
        rows.push(AccuracyRow {
            knob: "codec (lossless)",
            value: codec.name().into(),
            q_db: None,
            tau_secs: t.elapsed().as_secs_f64(),
            tau_of: "compression",
            sigma_bytes: Some(bytes.len() as u64),
        });
    }
    Ok(rows)
}
