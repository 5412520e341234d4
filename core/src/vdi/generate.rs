//! VDI generation `R(S_A, P_A, P_M) → M` (Sec. 3.2, 5.2; docs/conventions.md, "VDI").
//!
//! Each of the `r²` rays is marched with the same [`Raycaster`] as the reference DVR (rows in
//! parallel); its samples are collected, then merged front to back in a separate loop into the
//! open supersegment until the interrupt test fires:
//! `d = ‖â·ĉ − a·c‖₂ ≥ γ`, comparing the open supersegment's premultiplied colour per unit
//! length with the new sample's (`a`, `c` its per-unit-length opacity and colour). Then the
//! supersegment is closed and the sample opens a new one. Transparent samples never open one;
//! a run of them inside an open supersegment is tested once (the first one has the largest
//! `d`, since `â` only falls as the run lengthens) and trailing ones are cut off. Where the
//! CPU has AVX2, eight neighbouring rays are merged at once (`generate/lanes.rs`),
//! bit-identical to this scalar merge, which stays the reference and the fallback.

use super::{Supersegment, Vdi, VdiMeta, VdiParamError, VdiParams};
use crate::camera::{Camera, Ray, ViewFrame};
use crate::fastmath::one_minus_exp_neg;
use crate::raycast::{Coverage, Raycaster, Sample};
use glam::Vec3A;
/// Eight lanes of [`crate::fastmath::one_minus_exp_neg`] with AVX2 (shared with the VDI walk).
#[cfg(target_arch = "x86_64")]
pub(crate) use lanes::one_minus_exp_neg as one_minus_exp_neg_avx2;
use lanes::{Lanes, LANES};
use rayon::prelude::*;
use std::ops::{ControlFlow, Range};

mod lanes;

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
    let mut vdi = blank(raycaster, camera, params, tf_hash, tf_name);
    generate_into(raycaster, camera, params, tf_hash, tf_name, &mut vdi)?;
    Ok(vdi)
}

/// A VDI with `params`' metadata and no lists yet, for [`generate_into`] to fill.
pub(crate) fn blank(
    raycaster: &Raycaster,
    camera: &Camera,
    params: VdiParams,
    tf_hash: u64,
    tf_name: &str,
) -> Vdi {
    Vdi {
        meta: meta_for(raycaster, camera, params, tf_hash, tf_name),
        offsets: Vec::new(),
        supersegments: Vec::new(),
        derived: Default::default(),
    }
}

/// [`generate`] into `vdi`, replacing its content and reusing its allocations.
///
/// A generator that makes one VDI after another (a time step each) keeps one `Vdi` for this:
/// a VDI of tens of MB in fresh memory costs a page fault per 4 KiB (the teapot at r = 768,
/// 37 MB: about 9 000, a few percent of the generation time); reused memory costs none.
/// Reused at the same resolution, the flat array keeps the room it had and no estimate of the
/// supersegments is marched (see `estimate_supersegments`).
///
/// # Errors
/// As [`generate`]. `vdi` is unchanged after a parameter or camera error, and left an empty VDI
/// after the overflow error (more than `u32::MAX` supersegments).
pub fn generate_into(
    raycaster: &Raycaster,
    camera: &Camera,
    params: VdiParams,
    tf_hash: u64,
    tf_name: &str,
    vdi: &mut Vdi,
) -> Result<(), VdiParamError> {
    generate_into_until(raycaster, camera, params, tf_hash, tf_name, vdi, &|_| false).map(|_| ())
}

/// How far a generation got, as the stop rule of [`generate_into_until`] sees it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Progress {
    /// Share of the generation's work done, in `[0, 1]`: covered tiles of the rows marched
    /// over all covered tiles (rays no visible cell covers cost nothing).
    pub done: f64,
    /// Seconds since the generation began.
    pub seconds: f64,
    /// Of those, the seconds before the first band (validation, the supersegment estimate,
    /// the occupancy bits, the coverage): a cost every generation pays whatever its r, which
    /// a projection of the whole from `done` must not scale.
    pub setup: f64,
    /// Of `setup`, the seconds of work done once per ray-caster (its occupancy bits), which a
    /// generation made again from the same ray-caster does not pay.
    pub setup_once: f64,
}

impl Progress {
    /// Seconds the whole generation would take at the rate of the bands marched so far: the
    /// set-up plus the marching scaled by `1 / done`; `None` before any work is done.
    pub fn projected(&self) -> Option<f64> {
        (self.done > 0.0).then(|| self.setup + (self.seconds - self.setup) / self.done)
    }
}

/// How a generation under a stop rule ended.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Outcome {
    /// Every ray was marched: the VDI is whole.
    Complete,
    /// The stop rule said stop; the VDI was left empty. The progress when it stopped.
    Stopped(Progress),
}

/// [`generate_into`], asking `stop` between bands of rows (1/32 of the rows each) whether to
/// give up: a generator with a deadline (`generation.time_max`) stops a generation that would
/// overrun and makes the step again coarser, using the rate this one measured. A band under
/// way is finished first, so a generation overruns the moment `stop` says yes by at most one
/// band. Stopped, `vdi` is left an empty VDI with the metadata of `params`.
///
/// # Errors
/// As [`generate_into`].
pub fn generate_into_until(
    raycaster: &Raycaster,
    camera: &Camera,
    params: VdiParams,
    tf_hash: u64,
    tf_name: &str,
    vdi: &mut Vdi,
    stop: &dyn Fn(Progress) -> bool,
) -> Result<Outcome, VdiParamError> {
    let began = std::time::Instant::now();
    params.validate()?;
    if !camera.is_valid() {
        return Err(VdiParamError::Camera(*camera));
    }
    let r = params.resolution;
    // The last VDI's room, where it had this resolution: the steps of a run are alike, so it
    // almost always suffices (growth doubles it when not).
    let roomy = vdi.meta.params.resolution == r && vdi.supersegments.capacity() > 0;
    vdi.lists_changed();
    if raycaster.macro_grid().visibility().iter().all(|v| !v) {
        // Nothing visible under the TF (e.g. a rank's brick away from the feature): the empty
        // VDI, for one look at the macro cells instead of r² rays.
        vdi.meta = meta_for(raycaster, camera, params, tf_hash, tf_name);
        vdi.empty_lists();
        return Ok(Outcome::Complete);
    }
    vdi.meta = meta_for(raycaster, camera, params, tf_hash, tf_name);
    vdi.offsets.clear();
    vdi.offsets.reserve((r as usize).pow(2) + 1);
    vdi.offsets.push(0);
    vdi.supersegments.clear();
    // The ray-caster's occupancy bits, where r² rays repay them (before the estimate's rays).
    let once = std::time::Instant::now();
    raycaster.prepare((r as usize).pow(2));
    let setup_once = once.elapsed().as_secs_f64();
    // Room for the whole flat array up front (a generous guess; pages not written cost no
    // memory): grown by doubling instead, each growth would copy it and, for a while, hold
    // both copies. A reservation the allocator refuses (an estimate beyond what fits) is
    // left to growth.
    if !roomy {
        let estimate = estimate_supersegments(raycaster, camera, params).min(u32::MAX as usize);
        let _ = vdi.supersegments.try_reserve(estimate);
    }
    // Rays that no visible macro cell covers get no supersegments, unmarched.
    let coverage = Coverage::new(raycaster, &camera.frame(r, r));
    let band = r.div_ceil(BANDS);
    let work = coverage.covered_tiles(0..r).max(1) as f64;
    // Band k + 1 is marched while band k is appended (a serial copy that would otherwise
    // leave a thread idle).
    let mut pending: Vec<(Vec<u32>, Vec<Supersegment>)> = Vec::new();
    let mut total = 0usize;
    let setup = began.elapsed().as_secs_f64();
    for start in (0..r).step_by(band as usize) {
        let progress = Progress {
            done: coverage.covered_tiles(0..start) as f64 / work,
            seconds: began.elapsed().as_secs_f64(),
            setup,
            setup_once,
        };
        if stop(progress) {
            vdi.empty_lists();
            return Ok(Outcome::Stopped(progress));
        }
        let (offsets, supersegments) = (&mut vdi.offsets, &mut vdi.supersegments);
        let done = std::mem::take(&mut pending);
        let (rows, ()) = rayon::join(
            || {
                let rows = start..(start + band).min(r);
                march_rows(raycaster, camera, params, &coverage, rows)
            },
            || append_rows(done, offsets, supersegments),
        );
        total += rows.iter().map(|(_, s)| s.len()).sum::<usize>();
        // More than u32::MAX supersegments would not fit the offsets.
        if total > u32::MAX as usize {
            vdi.empty_lists();
            return Err(VdiParamError::Resolution(r));
        }
        pending = rows;
    }
    append_rows(pending, &mut vdi.offsets, &mut vdi.supersegments);
    debug_assert_eq!(vdi.offsets.len(), (r as usize).pow(2) + 1);
    debug_assert_eq!(
        vdi.offsets.last().map(|&n| n as usize),
        Some(vdi.supersegments.len())
    );
    Ok(Outcome::Complete)
}

/// Bands of rows generated one after another: only two bands' per-row lists (the one being
/// marched, the one being appended) exist beside the flat array: they add about 1/16 of the
/// VDI to generation's peak, not a whole VDI (on small fields the VDI
/// dominates the peak). 32 bands instead of 8 cost nothing measurable in τ (teapot, r = 768:
/// min of 4 runs 0.189 vs 0.191 s).
const BANDS: u32 = 32;

/// Rays per side of the grid [`estimate_supersegments`] samples.
const ESTIMATE_SIDE: u32 = 64;

/// A generous estimate of the supersegments the VDI will hold: the count of an
/// `ESTIMATE_SIDE²` grid of its rays (every `r / ESTIMATE_SIDE`-th row and column, about 1 % of
/// the rays at r = 768 and 6 % at r = 256) scaled to `r²`, plus a quarter. 0 below r = 256,
/// where the sample would be a large share of the rays and the VDI is small anyway. Its rays
/// are marched one at a time: at r = 256 it took 7–9 % of the teapot's generation (one thread,
/// 31–44 ms), so a VDI reused at the same resolution skips it.
fn estimate_supersegments(raycaster: &Raycaster, camera: &Camera, params: VdiParams) -> usize {
    let r = params.resolution;
    let stride = r / ESTIMATE_SIDE;
    if stride < 4 {
        return 0;
    }
    let frame = camera.frame(r, r);
    let limits = Limits::new(raycaster, params);
    let sampled: usize = (0..ESTIMATE_SIDE)
        .into_par_iter()
        .map_init(
            || (Vec::new(), Vec::new()),
            |(samples, segs), row| {
                segs.clear();
                let j = row * stride + stride / 2;
                for column in 0..ESTIMATE_SIDE {
                    let (ray, z_per_t) = generation_ray(&frame, column * stride + stride / 2, j);
                    generate_ray(raycaster, &ray, z_per_t, limits, samples, segs);
                }
                segs.len()
            },
        )
        .sum();
    let scaled = sampled as f64 * f64::from(r).powi(2) / f64::from(ESTIMATE_SIDE).powi(2);
    (scaled * 1.25) as usize
}

/// Each of `rows`' `(counts, supersegments)`, rows in parallel; only the pixels in
/// `coverage` are marched, the others have none.
fn march_rows(
    raycaster: &Raycaster,
    camera: &Camera,
    params: VdiParams,
    coverage: &Coverage,
    rows: Range<u32>,
) -> Vec<(Vec<u32>, Vec<Supersegment>)> {
    let r = params.resolution;
    let frame = camera.frame(r, r);
    let limits = Limits::new(raycaster, params);
    // Each row's list is reserved at the size of the row before it on the same worker (and a
    // quarter more): neighbouring rows see similar content, so lists rarely grow by copying.
    // Eight rays at a time where the CPU has AVX2 ([`lanes`]), else one by one.
    rows.into_par_iter()
        .map_init(
            || (0usize, Lanes::new(raycaster.avx2()), Vec::new()),
            |(previous, lanes, samples), j| {
                let mut counts = Vec::with_capacity(r as usize);
                let mut segs = Vec::with_capacity(*previous + *previous / 4);
                if let Some(lanes) = lanes {
                    for i0 in (0..r).step_by(LANES) {
                        let width = ((r - i0) as usize).min(LANES);
                        if !coverage.covers_any(i0, i0 + width as u32, j) {
                            counts.resize(counts.len() + width, 0);
                            continue;
                        }
                        let group = (i0, j, width);
                        lanes.generate(raycaster, &frame, group, limits, &mut segs, &mut counts);
                    }
                } else {
                    for i in 0..r {
                        if !coverage.covers(i, j) {
                            counts.push(0);
                            continue;
                        }
                        let before = segs.len();
                        let (ray, z_per_t) = generation_ray(&frame, i, j);
                        generate_ray(raycaster, &ray, z_per_t, limits, samples, &mut segs);
                        counts.push((segs.len() - before) as u32);
                    }
                }
                *previous = segs.len();
                (counts, segs)
            },
        )
        .collect()
}

/// Appends per-row `(counts, supersegments)` to prefix offsets (which end with the count so
/// far) and the flat array, freeing each row's list once copied (the next band's lists reuse
/// that memory).
pub(super) fn append_rows(
    rows: Vec<(Vec<u32>, Vec<Supersegment>)>,
    offsets: &mut Vec<u32>,
    supersegments: &mut Vec<Supersegment>,
) {
    let mut acc = offsets.last().copied().unwrap_or(0);
    supersegments.reserve(rows.iter().map(|(_, s)| s.len()).sum());
    for (counts, segs) in rows {
        for c in counts {
            acc = acc.saturating_add(c);
            offsets.push(acc);
        }
        supersegments.extend_from_slice(&segs);
    }
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
        sample_distance: rc_params.sample_distance,
        termination: rc_params.termination,
        shaded: rc_params.shading.is_some(),
        volume_box: *raycaster.bounds(),
        tf_hash,
        tf_name: tf_name.chars().take(256).collect(),
    }
}

/// The supersegment being built.
struct Open {
    /// Index of the last merged (non-transparent) sample.
    last_index: u32,
    /// Ray parameter where it starts and where its last merged sample ends.
    t_start: f32,
    t_end: f32,
    /// Accumulated premultiplied colour `C`, accumulated opacity `A = Σ Tᵢ·αᵢ` (a sum of
    /// positive terms, so no cancellation where `A` is small) and local transmittance
    /// `T = Π (1 − αᵢ) = 1 − A`.
    color: Vec3A,
    total: f32,
    transmittance: f32,
    /// Optical depth `τ = Σ κ·len`.
    optical_depth: f32,
    /// Of the current extent `L = t_end − t_start`: unit-length opacity
    /// `â = 1 − e^(−τ/L)` and the ratio `â/A` (`â·ĉ = (â/A)·C`).
    unit: f32,
    unit_over_total: f32,
}

impl Open {
    /// A supersegment of one sample: `A` is its opacity `α` and `â` its opacity per unit
    /// length `a`, both from the classification table, so opening needs no exponential.
    #[inline(always)]
    fn new(s: &Sample) -> Self {
        Self {
            last_index: s.index,
            t_start: s.t_start,
            t_end: s.t_end,
            color: Vec3A::from(s.rgb) * s.alpha,
            total: s.alpha,
            transmittance: 1.0 - s.alpha,
            optical_depth: s.kappa * s.len,
            unit: s.alpha_unit,
            unit_over_total: ratio(s.alpha_unit, s.alpha),
        }
    }

    /// `‖r·C − a·c‖²` for ratio `r` against a sample with per-unit premultiplied colour `ac`.
    #[inline(always)]
    fn distance_sq(&self, ratio: f32, ac: Vec3A) -> f32 {
        (ratio * self.color - ac).length_squared()
    }

    /// Whether a sample at `s` with per-unit premultiplied colour `ac` joins this supersegment.
    /// After a run of transparent samples the first of them (`a·c = 0`, the largest distance,
    /// since `â` only falls as the run lengthens) is tested, then `s` against the extent
    /// stretched to its start.
    #[inline(always)]
    fn accepts(&self, s: &Sample, ac: Vec3A, gamma_sq: f32) -> bool {
        if s.index > self.last_index + 1 {
            if self.distance_sq(self.unit_over_total, Vec3A::ZERO) >= gamma_sq {
                return false;
            }
            let unit = one_minus_exp_neg(self.optical_depth / (s.t_start - self.t_start));
            self.distance_sq(ratio(unit, self.total), ac) < gamma_sq
        } else {
            self.distance_sq(self.unit_over_total, ac) < gamma_sq
        }
    }

    /// Adds `s` behind the merged samples and recomputes `â` and `â/A` with one
    /// exponential ([`one_minus_exp_neg`], relative error < 1e-6).
    #[inline(always)]
    fn merge(&mut self, s: &Sample) {
        let w = self.transmittance * s.alpha;
        self.color += w * Vec3A::from(s.rgb);
        self.total += w;
        self.transmittance *= 1.0 - s.alpha;
        self.optical_depth += s.kappa * s.len;
        self.last_index = s.index;
        self.t_end = s.t_end;
        // Reciprocals, not divisions: they do not depend on the exponential, so they are
        // computed beside it instead of lengthening the chain the next test waits on.
        let inv_len = 1.0 / (self.t_end - self.t_start);
        self.unit = one_minus_exp_neg(self.optical_depth * inv_len);
        self.unit_over_total = ratio(self.unit, self.total);
    }

    /// The finished supersegment, depths scaled to eye space by `z_per_t`: `â` as computed
    /// for the last merge, `ĉ = C/A`.
    #[inline]
    fn close(&self, z_per_t: f32) -> Supersegment {
        let inv = 1.0 / self.total.max(f32::MIN_POSITIVE);
        let color = (self.color * inv).clamp(Vec3A::ZERO, Vec3A::ONE).to_array();
        Supersegment {
            z_start: self.t_start * z_per_t,
            z_end: self.t_end * z_per_t,
            color,
            alpha: self.unit.clamp(0.0, 1.0),
        }
    }
}

/// `â/A`. `A ≥ α > 0` for every supersegment (transparent samples never open one); the
/// floor keeps the ratio finite regardless. `1/A` does not depend on `â` and is computed
/// beside it (see [`Open::merge`]).
#[inline(always)]
fn ratio(unit: f32, total: f32) -> f32 {
    unit * (1.0 / total.max(f32::MIN_POSITIVE))
}

/// Samples buffered per ray before they are merged: bounds the buffer (40 KiB) however long
/// the ray and however small the step.
const CHUNK: usize = 1024;

/// Marches `ray` (eye-space depth `z_per_t` per unit `t`) up to the generation's early
/// termination ([`Limits::stop`]) and appends its supersegments to `out`; `samples` is
/// scratch.
///
/// The marcher's closure only buffers samples; [`Builder::merge`] merges them in a separate
/// loop at the ray's end (and [`Builder::flush`] whenever [`CHUNK`] are buffered). That keeps
/// each loop's live values in registers: merging inside the marching loop spilled both loops'
/// state around every sample (half of generation's extra instructions over the DVR).
fn generate_ray(
    raycaster: &Raycaster,
    ray: &Ray,
    z_per_t: f32,
    limits: Limits,
    samples: &mut Vec<Sample>,
    out: &mut Vec<Supersegment>,
) {
    samples.clear();
    let mut builder = Builder {
        open: None,
        gamma_sq: limits.gamma_sq,
        z_per_t,
    };
    let mut transmittance = 1.0f32;
    raycaster.march(ray, |s: &Sample| {
        if samples.len() == CHUNK {
            builder.flush(samples, out);
        }
        samples.push(*s);
        limits.stop(&mut transmittance, s.alpha)
    });
    builder.merge(samples, out);
    builder.finish(out);
}

/// The ray through pixel `(i, j)` of the generation `frame` and its view-axis component (the
/// eye-space depth per unit `t` that scales its supersegments' depths).
#[inline]
fn generation_ray(frame: &ViewFrame, i: u32, j: u32) -> (Ray, f32) {
    let ray = frame.pixel_ray(i, j);
    let z_per_t = ray.dir.dot(frame.forward);
    (ray, z_per_t)
}

/// What ends a generation ray and what closes a supersegment, the same for every ray of a
/// VDI.
#[derive(Clone, Copy)]
struct Limits {
    /// Early termination: the accumulated opacity at which a ray stops (above 1: never).
    termination: f32,
    /// The interrupt threshold squared, `γ²`.
    gamma_sq: f32,
}

impl Limits {
    fn new(raycaster: &Raycaster, params: VdiParams) -> Self {
        Self {
            termination: raycaster.params().generation_stop(),
            gamma_sq: params.gamma * params.gamma,
        }
    }

    /// Takes a sample of opacity `alpha` into the ray's `transmittance`; `Break` once the
    /// accumulated opacity reaches the termination threshold.
    #[inline(always)]
    fn stop(self, transmittance: &mut f32, alpha: f32) -> ControlFlow<()> {
        *transmittance *= 1.0 - alpha;
        if 1.0 - *transmittance >= self.termination {
            ControlFlow::Break(())
        } else {
            ControlFlow::Continue(())
        }
    }
}

/// Merges a ray's samples, chunk after chunk, into supersegments.
struct Builder {
    /// The supersegment being built (none before the ray's first sample).
    open: Option<Open>,
    gamma_sq: f32,
    /// The ray direction's component along the view axis (eye-space depth per unit `t`).
    z_per_t: f32,
}

impl Builder {
    /// [`Self::merge`] of a full buffer from inside the marching loop, which it empties. Cold
    /// and not inlined: inlined there, the merging loop would crowd the marching loop's
    /// registers.
    #[cold]
    #[inline(never)]
    fn flush(&mut self, samples: &mut Vec<Sample>, out: &mut Vec<Supersegment>) {
        self.merge(samples, out);
        samples.clear();
    }

    /// Closes the ray's last supersegment, if it has one.
    fn finish(self, out: &mut Vec<Supersegment>) {
        if let Some(open) = self.open {
            out.push(open.close(self.z_per_t));
        }
    }

    /// Merges the next `samples` (front to back), appending closed supersegments to `out`.
    #[inline]
    fn merge(&mut self, samples: &[Sample], out: &mut Vec<Supersegment>) {
        let (mut open, rest) = match self.open.take() {
            Some(open) => (open, samples),
            None => match samples.split_first() {
                Some((first, rest)) => (Open::new(first), rest),
                None => return,
            },
        };
        for s in rest {
            let ac = Vec3A::from(s.rgb) * s.alpha_unit;
            if open.accepts(s, ac, self.gamma_sq) {
                open.merge(s);
            } else {
                out.push(open.close(self.z_per_t));
                open = Open::new(s);
            }
        }
        self.open = Some(open);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::raycast::RaycastParams;
    use crate::tf::TransferFunction;
    use crate::volume::Volume;
    use glam::Vec3;

    #[test]
    fn merging_in_chunks_equals_merging_whole_rays() {
        // A ray of ~4 000 samples (step 0.05 through 200 voxels), faint enough not to terminate
        // (transmittance > 1e-6 at its end), whose colour varies along it: several chunks, with
        // supersegments across their seams.
        let volume =
            Volume::from_fn([6, 6, 200], |_, _, z| (z as f32 * 0.37).sin() * 0.5 + 0.5).unwrap();
        let tf = TransferFunction::from_json(
            r#"{"domain": [0, 1], "points": [[0, 1, 0, 0, 0.04], [0.5, 0, 1, 0, 0.06],
                [1, 0, 0, 1, 0.04]]}"#,
            "faint",
        )
        .unwrap();
        let params = RaycastParams {
            sample_distance: 0.05,
            ..Default::default()
        };
        let rc = Raycaster::new(&volume, &tf, params).unwrap();
        let ray = Ray {
            origin: Vec3::new(2.5, 2.5, -10.0),
            dir: Vec3::Z,
        };
        let mut whole = Vec::new();
        rc.march(&ray, |s: &Sample| {
            whole.push(*s);
            ControlFlow::Continue(())
        });
        assert!(whole.len() > 3 * CHUNK, "{} samples", whole.len());
        let (gamma_sq, z_per_t) = (0.02f32.powi(2), 1.0);
        let mut reference = Vec::new();
        let mut builder = Builder {
            open: None,
            gamma_sq,
            z_per_t,
        };
        builder.merge(&whole, &mut reference);
        builder.finish(&mut reference);
        let mut chunked = Vec::new();
        let limits = Limits {
            termination: 1.0,
            gamma_sq,
        };
        generate_ray(&rc, &ray, z_per_t, limits, &mut Vec::new(), &mut chunked);
        assert!(reference.len() > 20, "{} supersegments", reference.len());
        assert_eq!(chunked, reference);
    }

    /// The reservation covers the VDI (no growth by copying) without being far above it.
    #[test]
    fn the_estimate_covers_the_supersegments_generated() {
        let volume = Volume::from_fn([40, 36, 32], |x, y, z| {
            let d = Vec3::new(x as f32 - 20.0, y as f32 - 18.0, z as f32 - 16.0).length();
            (d * 0.6).sin() * 0.5 + 0.5
        })
        .unwrap();
        let tf = TransferFunction::default_for_range(0.0, 1.0);
        let rc = Raycaster::new(&volume, &tf, RaycastParams::default()).unwrap();
        let cam = Camera::default_for_box(&volume.world_box());
        for (angle, resolution, gamma) in [(0.0, 256, 0.01), (35.0, 320, 0.002), (90.0, 256, 0.05)]
        {
            let params = VdiParams {
                resolution,
                gamma,
                precision: Default::default(),
            };
            let camera = cam.orbit_y(angle);
            let n = generate(&rc, &camera, params, 0, "")
                .unwrap()
                .supersegments()
                .len();
            let estimate = estimate_supersegments(&rc, &camera, params);
            assert!(n > 10_000, "{n} supersegments");
            assert!(
                estimate >= n && estimate <= 2 * n,
                "{angle}°, r = {resolution}: estimate {estimate} for {n}"
            );
        }
        assert_eq!(
            estimate_supersegments(
                &rc,
                &cam,
                VdiParams {
                    resolution: 128,
                    gamma: 0.01,
                    precision: Default::default()
                }
            ),
            0,
            "small VDIs are not sampled"
        );
    }

    #[test]
    fn generating_into_a_used_vdi_equals_generating_afresh() {
        let volume = Volume::from_fn([24, 20, 16], |x, y, z| {
            ((x * x + 2 * y + 3 * z) % 17) as f32 / 17.0
        })
        .unwrap();
        let tf = TransferFunction::default_for_range(0.0, 1.0);
        let rc = Raycaster::new(&volume, &tf, RaycastParams::default()).unwrap();
        let cam = Camera::default_for_box(&volume.world_box());
        let p = |resolution, gamma| VdiParams {
            resolution,
            gamma,
            precision: Default::default(),
        };
        let mut vdi = generate(&rc, &cam.orbit_y(40.0), p(48, 0.001), 1, "first").unwrap();
        // Shrinking (truncation), growing within the capacity (zeroed extension), growing
        // beyond it (a new array), and another camera; then at r = 256 (where a fresh VDI's
        // room is estimated) again at the same r with many more supersegments than the room
        // the first one left (no estimate: grown).
        for (camera, params) in [
            (cam, p(8, 0.2)),
            (cam, p(24, 0.02)),
            (cam, p(64, 0.001)),
            (cam.orbit_y(180.0), p(32, 0.05)),
            (cam, p(256, 0.5)),
            (cam.orbit_y(90.0), p(256, 0.001)),
        ] {
            let fresh = generate(&rc, &camera, params, 7, "next").unwrap();
            generate_into(&rc, &camera, params, 7, "next", &mut vdi).unwrap();
            assert_eq!(vdi, fresh, "{params:?}");
            assert!(!fresh.supersegments().is_empty());
        }
        let before = vdi.clone();
        assert!(generate_into(&rc, &cam, p(0, 0.1), 0, "", &mut vdi).is_err());
        assert!(generate_into(&rc, &cam, p(8, f32::NAN), 0, "", &mut vdi).is_err());
        assert_eq!(vdi, before, "a failed generation leaves the VDI as it was");
    }

    /// The stop rule sees progress that starts at 0 and only grows, within [0, 1]; a rule that stops at half the work leaves an empty VDI of the
    /// right resolution, and the VDI memory it hands back then makes the whole VDI exactly.
    #[test]
    fn a_generation_stops_where_its_rule_says_and_leaves_an_empty_vdi() {
        let volume = Volume::from_fn([32, 28, 24], |x, y, z| {
            ((x * 3 + y * 5 + z * 7) % 23) as f32 / 23.0
        })
        .unwrap();
        let tf = TransferFunction::default_for_range(0.0, 1.0);
        let rc = Raycaster::new(&volume, &tf, RaycastParams::default()).unwrap();
        let cam = Camera::default_for_box(&volume.world_box()).orbit_y(25.0);
        let params = VdiParams {
            resolution: 96,
            gamma: 0.01,
            precision: Default::default(),
        };
        let whole = generate(&rc, &cam, params, 3, "t").unwrap();
        let seen = std::sync::Mutex::new(Vec::new());
        let mut vdi = whole.clone();
        let outcome = generate_into_until(&rc, &cam, params, 3, "t", &mut vdi, &|p| {
            seen.lock().map(|mut s| s.push(p)).is_err()
        })
        .unwrap();
        assert_eq!(outcome, Outcome::Complete);
        assert_eq!(vdi, whole, "a rule that never stops changes nothing");
        let seen = seen.into_inner().unwrap_or_default();
        assert_eq!(seen.len(), BANDS as usize, "asked once per band");
        assert_eq!(seen[0].done, 0.0);
        assert!(seen
            .windows(2)
            .all(|w| w[0].done <= w[1].done && w[0].seconds <= w[1].seconds));
        assert!(seen
            .iter()
            .all(|p| p.done <= 1.0 && p.seconds >= p.setup && p.setup >= p.setup_once));
        assert!(seen.iter().all(|p| p.setup == seen[0].setup));
        assert_eq!(
            seen[0].projected(),
            None,
            "nothing to project from before any work"
        );

        let outcome =
            generate_into_until(&rc, &cam, params, 3, "t", &mut vdi, &|p| p.done >= 0.5).unwrap();
        let Outcome::Stopped(at) = outcome else {
            panic!("not stopped: {outcome:?}");
        };
        assert!((0.5..0.75).contains(&at.done), "stopped at {at:?}");
        assert_eq!(vdi.resolution(), 96);
        assert!(vdi.supersegments().is_empty());
        assert_eq!(vdi.offsets().len(), 96 * 96 + 1);
        generate_into(&rc, &cam, params, 3, "t", &mut vdi).unwrap();
        assert_eq!(vdi, whole);
    }
}
