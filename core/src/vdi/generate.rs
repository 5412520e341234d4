//! VDI generation `R(S_A, P_A, P_M) → M` (Sec. 3.2, 5.2; DESIGN.md, "VDI").
//!
//! Each of the `r²` rays is marched with the same [`Raycaster`] as the reference DVR. Samples
//! are merged front to back into the open supersegment until the interrupt test fires:
//! `d = ‖â·ĉ − a·c‖₂ ≥ γ`, comparing the open supersegment's premultiplied colour per unit
//! length with the new sample's (`a`, `c` its per-unit-length opacity and colour). Then the
//! supersegment is closed and the sample opens a new one. Transparent samples never open one;
//! a run of them inside an open supersegment is tested once (the first one has the largest
//! `d`, since `â` only falls as the run lengthens) and trailing ones are cut off.

use super::{Supersegment, Vdi, VdiMeta, VdiParamError, VdiParams};
use crate::camera::Camera;
use crate::raycast::{Raycaster, Sample, Visit};
use rayon::prelude::*;
use std::ops::ControlFlow;

/// Generates the VDI of `raycaster`'s scene seen by `camera` with `params`.
///
/// `tf_hash` and `tf_name` identify the transfer function in the result's metadata.
///
/// # Errors
/// [`VdiParamError`] when `params` fail [`VdiParams::validate`] or the camera is degenerate.
pub fn generate(
    raycaster: &Raycaster,
    camera: &Camera,
    params: VdiParams,
    tf_hash: u64,
    tf_name: &str,
) -> Result<Vdi, VdiParamError> {
    params.validate()?;
    if !camera.is_valid() {
        return Err(VdiParamError::Camera(*camera));
    }
    let r = params.resolution;
    let frame = camera.frame(r, r);
    let termination = raycaster.params().termination;
    let rows: Vec<(Vec<u32>, Vec<Supersegment>)> = (0..r)
        .into_par_iter()
        .map(|j| {
            let mut counts = Vec::with_capacity(r as usize);
            let mut segs = Vec::new();
            for i in 0..r {
                let ray = frame.pixel_ray(i, j);
                let z_per_t = ray.dir.dot(frame.forward);
                let before = segs.len();
                let mut builder = Builder::new(params.gamma, termination, z_per_t, &mut segs);
                raycaster.march(&ray, &mut builder);
                builder.finish();
                counts.push((segs.len() - before) as u32);
            }
            (counts, segs)
        })
        .collect();
    let total: usize = rows.iter().map(|(_, s)| s.len()).sum();
    let mut offsets = Vec::with_capacity(r as usize * r as usize + 1);
    let mut supersegments = Vec::with_capacity(total);
    offsets.push(0u32);
    let mut acc = 0u32;
    for (counts, segs) in rows {
        for c in counts {
            acc = acc.saturating_add(c);
            offsets.push(acc);
        }
        supersegments.extend_from_slice(&segs);
    }
    let meta = meta_for(raycaster, camera, params, tf_hash, tf_name);
    // More than u32::MAX supersegments would saturate the offsets; from_parts rejects that.
    Vdi::from_parts(meta, offsets, supersegments).ok_or(VdiParamError::Resolution(r))
}

/// The metadata of a VDI generated from `raycaster`'s scene (shared with the GPU path).
pub(crate) fn meta_for(
    raycaster: &Raycaster,
    camera: &Camera,
    params: VdiParams,
    tf_hash: u64,
    tf_name: &str,
) -> VdiMeta {
    let rc_params = raycaster.params();
    VdiMeta {
        camera: *camera,
        params,
        step: rc_params.step,
        termination: rc_params.termination,
        shaded: rc_params.shading.is_some(),
        volume_box: *raycaster.bounds(),
        tf_hash,
        tf_name: tf_name.chars().take(256).collect(),
    }
}

/// `1 − e^(−x)` for `x ≥ 0` (`+∞` gives 1): a Taylor polynomial below 1/64 (truncation
/// error under `x⁵/120`, relative < 1e-9), else `1 − exp(−x)` (relative error < 1e-5, where
/// `exp_m1` would cost twice as much). The generation hot loop calls it twice per sample.
#[inline]
pub(crate) fn one_minus_exp_neg(x: f32) -> f32 {
    if x < 1.0 / 64.0 {
        x * (1.0 - x * (0.5 - x * (1.0 / 6.0 - x * (1.0 / 24.0))))
    } else {
        1.0 - (-x).exp()
    }
}

/// The supersegment being built.
struct Open {
    /// Index of the last merged (non-transparent) sample.
    last_index: u32,
    /// Ray parameter where it starts and where its last merged sample ends.
    t_start: f32,
    t_end: f32,
    /// Accumulated premultiplied colour `C` and local transmittance `1 − A`.
    color: [f32; 3],
    transmittance: f32,
    /// Optical depth `Σ κ·len`; `A = 1 − e^(−τ)` and `â = 1 − e^(−τ/L)`.
    optical_depth: f32,
    /// `â / A` of the current extent: `â·ĉ = (â/A)·C`.
    unit_over_total: f32,
}

impl Open {
    fn new(s: &Sample) -> Self {
        let mut open = Self {
            last_index: s.index,
            t_start: s.t_start,
            t_end: s.t_end,
            color: s.rgb.map(|c| c * s.alpha),
            transmittance: 1.0 - s.alpha,
            optical_depth: s.kappa * s.len,
            unit_over_total: 0.0,
        };
        open.update_ratio(open.t_end - open.t_start);
        open
    }

    /// Recomputes `â/A` for world length `len`. Only the interrupt test reads it, once per
    /// sample, so it uses [`one_minus_exp_neg`] (relative error < 1e-5); the stored `â` and
    /// `ĉ` are computed exactly in [`Open::close`].
    #[inline]
    fn update_ratio(&mut self, len: f32) {
        let total = one_minus_exp_neg(self.optical_depth);
        let unit = one_minus_exp_neg(self.optical_depth / len);
        self.unit_over_total = if total > 0.0 { unit / total } else { 1.0 / len };
    }

    /// `‖â·ĉ − a·c‖²` against a sample with per-unit premultiplied colour `ac`.
    #[inline]
    fn distance_sq(&self, ac: [f32; 3]) -> f32 {
        (0..3)
            .map(|k| {
                let d = self.unit_over_total * self.color[k] - ac[k];
                d * d
            })
            .sum()
    }

    #[inline]
    fn merge(&mut self, s: &Sample) {
        let w = self.transmittance * s.alpha;
        for k in 0..3 {
            self.color[k] += w * s.rgb[k];
        }
        self.transmittance *= 1.0 - s.alpha;
        self.optical_depth += s.kappa * s.len;
        self.last_index = s.index;
        self.t_end = s.t_end;
        self.update_ratio(self.t_end - self.t_start);
    }

    /// The finished supersegment, depths scaled to eye space by `z_per_t`.
    fn close(&self, z_per_t: f32) -> Supersegment {
        let len = (self.t_end - self.t_start).max(f32::MIN_POSITIVE);
        let total = -(-self.optical_depth).exp_m1();
        let alpha = (-(-self.optical_depth / len).exp_m1()).clamp(0.0, 1.0);
        let color = if total > 0.0 {
            self.color.map(|c| (c / total).clamp(0.0, 1.0))
        } else {
            [0.0; 3]
        };
        Supersegment {
            z_start: self.t_start * z_per_t,
            z_end: self.t_end * z_per_t,
            color,
            alpha,
        }
    }
}

impl Visit for &mut Builder<'_> {
    #[inline(always)]
    fn visit(&mut self, s: &Sample) -> ControlFlow<()> {
        self.push(s)
    }
}

/// Merges one ray's samples into supersegments.
struct Builder<'a> {
    gamma_sq: f32,
    termination: f32,
    z_per_t: f32,
    transmittance: f32,
    open: Option<Open>,
    out: &'a mut Vec<Supersegment>,
}

impl<'a> Builder<'a> {
    fn new(gamma: f32, termination: f32, z_per_t: f32, out: &'a mut Vec<Supersegment>) -> Self {
        Self {
            gamma_sq: gamma * gamma,
            termination,
            z_per_t,
            transmittance: 1.0,
            open: None,
            out,
        }
    }

    #[inline(always)]
    fn push(&mut self, s: &Sample) -> ControlFlow<()> {
        let ac = s.rgb.map(|c| c * s.alpha_unit);
        let keep = match &mut self.open {
            None => false,
            Some(open) => {
                if s.index > open.last_index + 1 {
                    // A run of transparent samples: the first compares a·c = 0.
                    if open.distance_sq([0.0; 3]) >= self.gamma_sq {
                        false
                    } else {
                        open.update_ratio(s.t_start - open.t_start);
                        open.distance_sq(ac) < self.gamma_sq
                    }
                } else {
                    open.distance_sq(ac) < self.gamma_sq
                }
            }
        };
        if keep {
            if let Some(open) = &mut self.open {
                open.merge(s);
            }
        } else {
            if let Some(open) = self.open.take() {
                self.out.push(open.close(self.z_per_t));
            }
            self.open = Some(Open::new(s));
        }
        self.transmittance *= 1.0 - s.alpha;
        if 1.0 - self.transmittance >= self.termination {
            ControlFlow::Break(())
        } else {
            ControlFlow::Continue(())
        }
    }

    fn finish(mut self) {
        if let Some(open) = self.open.take() {
            self.out.push(open.close(self.z_per_t));
        }
    }
}
