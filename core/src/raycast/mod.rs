//! Ray marching through a classified volume: the sampling code that the reference DVR
//! ([`crate::dvr`]) and VDI generation ([`crate::vdi::generate`]) share.
//!
//! A ray is clipped to the volume box and cut into steps of length `Δ` (the last one shorter,
//! so the steps add up to the exact length inside the box). Each step is sampled at its
//! midpoint with trilinear interpolation, classified through the transfer function's [`Lut`],
//! optionally shaded, and handed to a visitor with its opacity corrected for its length:
//! `α = 1 − (1 − a)^len`. Transparent samples (NaN data, zero opacity) are not handed over.
//! Empty-space skipping jumps over macro cells whose value range maps to zero opacity; it
//! never changes which non-transparent samples are visited: an invisible macro cell far from
//! visible ones is leapt over with the whole empty cube around it, one next to a visible cell
//! is walked cell by cell by 3-D DDA with the invisible cells after it
//! ([`MacroGrid::empty_run_exit`]); the steps of a run of visible cells (found by the same
//! DDA, [`MacroGrid::visible_run_exit`]) are sampled without further checks — eight at a time
//! with AVX2 where the CPU has it (`simd`, bit-identical to the scalar path, which stays the
//! reference and the fallback; [`Raycaster::without_simd`]), which passes over batches of
//! eight steps whose 2³-voxel blocks are all invisible (`occupancy`) without gathering them.

mod composite;
mod coverage;
mod macrocell;
mod occupancy;
mod shading;
mod simd;

pub use composite::FrontToBack;
pub use coverage::Coverage;
pub(crate) use macrocell::chessboard_distance;
pub use macrocell::MacroGrid;
use occupancy::Occupancy;
pub use shading::Shading;
pub(crate) use simd::Avx2;

use crate::camera::Ray;
use crate::fastmath;
use crate::tf::{Lut, LutEntry, TransferFunction};
use crate::volume::{Aabb, Storage, Volume, Voxel, VoxelSlice};
use glam::Vec3;
use std::ops::ControlFlow;
use std::sync::OnceLock;

/// Default ray-casting step, world units (docs/conventions.md: 0.5 voxel).
pub const DEFAULT_STEP: f32 = 0.5;
/// Shortest run of steps in a visible macro cell worth sampling eight lanes at a time.
#[cfg(target_arch = "x86_64")]
const SIMD_MIN_RUN: u32 = 3;
/// Most steps of a visible run classified before the first of them is visited (a multiple of
/// eight, at most 64: the bits of [`simd::Lanes::classify`]'s mask). 64 rather than 32: 2–4 %
/// faster on the shared volumes (teapot, hydrogen, neghip and the stent from 10°, 768²), the
/// longer batches of gathers outweighing the steps classified past a ray's termination.
#[cfg(target_arch = "x86_64")]
const SIMD_CHUNK: usize = 64;
#[cfg(target_arch = "x86_64")]
const _: () = assert!(SIMD_CHUNK % 8 == 0 && SIMD_CHUNK <= 64);
/// Default early-ray-termination threshold on accumulated opacity.
pub const DEFAULT_TERMINATION: f32 = 0.99;
/// Default early termination of VDI generation rays: off (chosen from the `accuracy` rows in
/// docs/performance.md: see [`RaycastParams::generation_termination`]).
pub const DEFAULT_GENERATION_TERMINATION: Option<f32> = None;

/// Errors for ray-casting parameters.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum RaycastError {
    /// A parameter outside its range.
    #[error("invalid ray-casting parameter: {0}")]
    Invalid(String),
}

/// Knobs of the ray-caster; each trades quality for time (see the `accuracy` report).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RaycastParams {
    /// Sample spacing along rays, world units (> 0).
    pub sample_distance: f32,
    /// Early ray termination: stop once accumulated opacity reaches this (in (0, 1]; 1 only
    /// stops at full opacity).
    pub termination: f32,
    /// Early termination while generating a VDI, separate from the DVR's: `Some(a)` stops a
    /// generation ray once its accumulated opacity reaches `a` (in (0, 1]); `None` never stops
    /// it, so the VDI keeps what lies behind dense structures for views that look past them
    /// (stopping at 0.99 left holes that showed as dark streaks from 10–30°). The
    /// `accuracy` report measures each choice; see [`DEFAULT_GENERATION_TERMINATION`].
    pub generation_termination: Option<f32>,
    /// Blinn–Phong gradient shading; `None` is pure emission–absorption.
    pub shading: Option<Shading>,
    /// Skip macro cells that the transfer function makes fully transparent.
    pub empty_space_skipping: bool,
}

impl Default for RaycastParams {
    fn default() -> Self {
        Self {
            sample_distance: DEFAULT_STEP,
            termination: DEFAULT_TERMINATION,
            generation_termination: DEFAULT_GENERATION_TERMINATION,
            shading: None,
            empty_space_skipping: true,
        }
    }
}

impl RaycastParams {
    /// Checks ranges.
    ///
    /// # Errors
    /// [`RaycastError::Invalid`] for a step that is not finite and positive or a termination
    /// threshold outside (0, 1].
    pub fn validate(&self) -> Result<(), RaycastError> {
        if !(self.sample_distance.is_finite() && self.sample_distance > 0.0) {
            return Err(RaycastError::Invalid(format!(
                "step {} must be finite and > 0",
                self.sample_distance
            )));
        }
        if !(self.termination > 0.0 && self.termination <= 1.0) {
            return Err(RaycastError::Invalid(format!(
                "early-termination threshold {} must be in (0, 1]",
                self.termination
            )));
        }
        if let Some(a) = self.generation_termination {
            if !(a > 0.0 && a <= 1.0) {
                return Err(RaycastError::Invalid(format!(
                    "generation early-termination threshold {a} must be in (0, 1] (or off)"
                )));
            }
        }
        Ok(())
    }

    /// The accumulated opacity at which a generation ray stops; above 1 (never reached) when
    /// generation termination is off.
    pub fn generation_stop(&self) -> f32 {
        self.generation_termination.unwrap_or(f32::INFINITY)
    }
}

/// One classified, non-transparent sample on a ray.
#[derive(Clone, Copy, Debug)]
pub struct Sample {
    /// Step index along the ray (consecutive steps differ by one; gaps are transparent).
    pub index: u32,
    /// Ray parameter where this step's interval starts, world units.
    pub t_start: f32,
    /// Ray parameter where the interval ends: exactly the next step's `t_start`, or the
    /// box exit for the last step.
    pub t_end: f32,
    /// Nominal length of the interval used for opacity correction, world units (`Δ`, or the
    /// remainder for the last step).
    pub len: f32,
    /// Colour (shaded if shading is on), in [0, 1].
    pub rgb: [f32; 3],
    /// Opacity per unit length `a`.
    pub alpha_unit: f32,
    /// Extinction per unit length `κ = −ln(1 − a)`, possibly `+∞`.
    pub kappa: f32,
    /// Opacity of this interval, `1 − (1 − a)^len`, in (0, 1].
    pub alpha: f32,
}

/// One ray's stepping: steps `k = 0 … n_samples − 1` start at `t_in + k·step`; voxel-space
/// position `o_v + t·d_v`.
struct Marching {
    t_in: f32,
    t_far: f32,
    step: f32,
    n_samples: u32,
    o_v: Vec3,
    d_v: Vec3,
}

/// What the marcher hands each non-transparent sample to: a closure
/// `FnMut(&Sample) -> ControlFlow<()>`, or a state and a closure that takes it
/// ([`Raycaster::march_fold`]). `Break` stops the ray.
pub(crate) trait Visit {
    fn visit(&mut self, s: &Sample) -> ControlFlow<()>;
}

impl<F: FnMut(&Sample) -> ControlFlow<()>> Visit for F {
    #[inline(always)]
    fn visit(&mut self, s: &Sample) -> ControlFlow<()> {
        self(s)
    }
}

/// A fold's state with its visitor: when the marcher's function holds this by value, the
/// state is one of its locals.
struct Folded<S, F> {
    state: S,
    visit: F,
}

impl<S, F: FnMut(&mut S, &Sample) -> ControlFlow<()>> Visit for Folded<S, F> {
    #[inline(always)]
    fn visit(&mut self, s: &Sample) -> ControlFlow<()> {
        (self.visit)(&mut self.state, s)
    }
}

/// A volume prepared for ray-casting with one transfer function and parameters: the
/// classification table and the macro-cell grid are built once here.
#[derive(Clone)]
pub struct Raycaster<'a> {
    volume: &'a Volume,
    lut: Lut,
    grid: MacroGrid,
    params: RaycastParams,
    bounds: Aabb,
    inv_spacing: Vec3,
    max_voxel: Vec3,
    strides: [usize; 3],
    /// The SIMD path's visibility map ([`simd::visible_groups`]).
    visible_groups: [u32; 8],
    /// The SIMD path's blocks of 2³ voxels that can contribute ([`occupancy`]): built by
    /// [`Raycaster::prepare`] for a render large enough to repay it, only with the SIMD path
    /// and empty-space skipping (`None` inside: none can be built for this volume).
    occupancy: OnceLock<Option<Occupancy>>,
    /// Sample visible cells eight steps at a time ([`simd`]) with this CPU's AVX2.
    simd: Option<simd::Avx2>,
}

impl<'a> Raycaster<'a> {
    /// Prepares `volume` with `tf` and `params`.
    ///
    /// # Errors
    /// [`RaycastError::Invalid`] when `params` fail [`RaycastParams::validate`].
    pub fn new(
        volume: &'a Volume,
        tf: &TransferFunction,
        params: RaycastParams,
    ) -> Result<Self, RaycastError> {
        params.validate()?;
        let lut = Lut::new(tf, params.sample_distance);
        let visible_groups = simd::visible_groups(&lut);
        let grid = MacroGrid::new(volume, &lut);
        let [nx, ny, nz] = volume.dims();
        let simd = simd::Avx2::detect();
        Ok(Self {
            occupancy: OnceLock::new(),
            volume,
            lut,
            grid,
            params,
            bounds: volume.world_box(),
            inv_spacing: volume.spacing().recip(),
            max_voxel: Vec3::new((nx - 1) as f32, (ny - 1) as f32, (nz - 1) as f32),
            visible_groups,
            simd,
            strides: [
                usize::from(nx > 1),
                nx * usize::from(ny > 1),
                nx * ny * usize::from(nz > 1),
            ],
        })
    }

    /// The same ray-caster on the portable scalar path only (the reference the SIMD path is
    /// tested against; also for measuring what the SIMD path buys).
    pub fn without_simd(mut self) -> Self {
        self.simd = None;
        self.occupancy = OnceLock::new();
        self
    }

    /// Readies the ray-caster for a render of `rays` rays: builds the occupancy bits
    /// (`occupancy`) when the render takes at least about as many samples as the volume has
    /// voxels (`rays` × its longest axis ≥ its voxels), once. The bits cost a pass over the
    /// visible cells' voxels (about 7 ms on the teapot, more on a large field where every
    /// cell is visible) and save time per sample marched: a 768² DVR repays them many times,
    /// a generator-node's r = 1 VDI or a handful of rays never does (a generator-node taking
    /// 64 MiB steps at r = 1 spent about 45 ms of CPU a step on them, a quarter of the
    /// machine's). Marching without them gives the same samples, only slower; calling this
    /// from inside a parallel render is safe (the first caller builds, the others wait).
    pub fn prepare(&self, rays: usize) {
        let dims = self.volume.dims();
        let voxels = dims.iter().product::<usize>();
        let longest = dims.iter().copied().max().unwrap_or(0);
        let wanted = self.simd.is_some() && self.params.empty_space_skipping;
        if wanted && rays.saturating_mul(longest) >= voxels {
            self.occupancy
                .get_or_init(|| Occupancy::new(self.volume, &self.lut, &self.grid));
        }
    }

    /// The occupancy bits, where [`Raycaster::prepare`] has built them.
    fn occupancy(&self) -> Option<&Occupancy> {
        self.occupancy.get().and_then(Option::as_ref)
    }

    /// Whether visible macro cells are sampled eight steps at a time (AVX2, detected at run
    /// time).
    pub fn uses_simd(&self) -> bool {
        self.simd.is_some()
    }

    /// The AVX2 token where this ray-caster uses AVX2 (for the work that follows its samples,
    /// such as VDI generation's merge), `None` on the scalar path.
    pub(crate) fn avx2(&self) -> Option<Avx2> {
        self.simd
    }

    /// The parameters this ray-caster was built with.
    pub fn params(&self) -> &RaycastParams {
        &self.params
    }

    /// The volume's world box.
    pub fn bounds(&self) -> &Aabb {
        &self.bounds
    }

    /// The volume being ray-cast.
    pub fn volume(&self) -> &Volume {
        self.volume
    }

    /// The classification table (transfer function with opacity correction for the step).
    pub fn lut(&self) -> &Lut {
        &self.lut
    }

    /// The macro-cell grid used for empty-space skipping.
    pub fn macro_grid(&self) -> &MacroGrid {
        &self.grid
    }

    /// Marches `ray` front to back, calling `visit` for each non-transparent sample until it
    /// returns `Break` or the ray leaves the volume.
    pub fn march(&self, ray: &Ray, visit: impl FnMut(&Sample) -> ControlFlow<()>) {
        self.march_visit(ray, visit);
    }

    /// [`Raycaster::march`] with the visitor's `state` handed to it at every sample and
    /// returned at the end. The state is a local of the marcher's own function (the one
    /// compiled for AVX2 where the CPU has it), so an accumulator such as [`FrontToBack`]
    /// stays in registers instead of being loaded and stored through a reference at every
    /// sample (the reference DVR 2–3 % faster).
    pub fn march_fold<S>(
        &self,
        ray: &Ray,
        state: S,
        visit: impl FnMut(&mut S, &Sample) -> ControlFlow<()>,
    ) -> S {
        self.march_visit(ray, Folded { state, visit }).state
    }

    /// The march for the voxel type of the storage (with its padding: the AVX2 gathers read a
    /// few bytes past the last voxel of integer types) and for whether it shades: the one
    /// place the eight monomorphic paths are chosen. `visit` comes back when the ray is done.
    fn march_visit<V: Visit>(&self, ray: &Ray, visit: V) -> V {
        match (self.volume.storage(), self.params.shading.is_some()) {
            (Storage::U8(d), false) => self.march_typed::<u8, false, V>(d, ray, visit),
            (Storage::U8(d), true) => self.march_typed::<u8, true, V>(d, ray, visit),
            (Storage::U16(d), false) => self.march_typed::<u16, false, V>(d, ray, visit),
            (Storage::U16(d), true) => self.march_typed::<u16, true, V>(d, ray, visit),
            (Storage::I16(d), false) => self.march_typed::<i16, false, V>(d, ray, visit),
            (Storage::I16(d), true) => self.march_typed::<i16, true, V>(d, ray, visit),
            (Storage::F32(d), false) => self.march_typed::<f32, false, V>(d, ray, visit),
            (Storage::F32(d), true) => self.march_typed::<f32, true, V>(d, ray, visit),
        }
    }

    /// The whole march compiled for AVX2 where the CPU has it (the loop's bookkeeping in AVX2
    /// encoding, the kernel called once per visible run), else the portable scalar path. The
    /// visitor goes in and comes back by value, so that it lives in that function.
    #[inline(always)]
    fn march_typed<T: simd::Gather, const SHADE: bool, V: Visit>(
        &self,
        data: &[T],
        ray: &Ray,
        mut visit: V,
    ) -> V {
        #[cfg(target_arch = "x86_64")]
        if let Some(avx2) = self.simd {
            return simd::march::<T, SHADE, V>(avx2, self, data, ray, visit);
        }
        self.march_impl::<T, SHADE>(data, ray, &mut visit, None);
        visit
    }

    #[inline(always)]
    fn march_impl<T: simd::Gather, const SHADE: bool>(
        &self,
        data: &[T],
        ray: &Ray,
        visit: &mut impl Visit,
        simd: Option<simd::Avx2>,
    ) {
        let inv_dir = ray.dir.recip();
        let (t_near, t_far) = self.bounds.intersect(ray.origin, inv_dir);
        let t_in = t_near.max(0.0);
        if t_far.is_nan() || t_in.is_nan() || t_far <= t_in {
            return;
        }
        let step = self.params.sample_distance;
        let length = t_far - t_in;
        let n_full_f = (length / step).floor().min(u32::MAX as f32 / 2.0);
        let n_full = n_full_f as u32;
        let rem = length - n_full_f * step;
        let n_samples = n_full + u32::from(rem > step * 1e-4);
        let o_v = (ray.origin - self.bounds.min) * self.inv_spacing;
        let d_v = ray.dir * self.inv_spacing;
        let inv_d_v = d_v.recip();
        // Step counts from distances (a multiplication, not a division, per cell): an ulp
        // either way only moves a step to the next pass of the loop, never past a sample.
        let inv_step = step.recip();
        let m = Marching {
            t_in,
            t_far,
            step,
            n_samples,
            o_v,
            d_v,
        };
        // The AVX2 kernel for this ray, checked once.
        #[cfg(target_arch = "x86_64")]
        let lanes = simd.and_then(|avx2| simd::Lanes::new(avx2, self, data, &m));
        // Steps 0 … n_full − 1 are full; the last one (k = n_full) is the remainder. Walked a
        // run of macro cells at a time: invisible cells are jumped over; in a run of visible
        // ones, the steps whose midpoints lie before the run's exit are sampled without
        // further checks (one that strays into an invisible neighbour is transparent there
        // anyway).
        let mut k = 0u32;
        while k < n_samples {
            let k_end = if self.params.empty_space_skipping {
                let len = if k < n_full { step } else { rem };
                let (_, [ix, iy, iz]) = self.locate(&m, k, len);
                if !self.grid.visible(ix, iy, iz) {
                    // Leap the invisible cells ahead, resuming at the first sample whose
                    // midpoint is not clearly inside them: the margin (an eighth of a step,
                    // and 1e-5 of the distance, far above the rounding of t and of the sample
                    // positions) keeps rounding from ever skipping a sample outside them; a
                    // sample inside the margin is skipped on the next pass.
                    let tolerance = |t: f32| 0.125 * step + 1e-5 * t.abs();
                    let t_exit = self
                        .grid
                        .empty_run_exit([ix, iy, iz], o_v, inv_d_v, tolerance);
                    let margin = tolerance(t_exit);
                    let k_first = fastmath::ceil((t_exit - margin - t_in) * inv_step - 0.5);
                    k = (k + 1).max(k_first.clamp(0.0, n_samples as f32) as u32);
                    continue;
                }
                let t_exit = self.grid.visible_run_exit(ix, iy, iz, o_v, inv_d_v);
                let k_last = fastmath::ceil((t_exit - t_in) * inv_step - 0.5);
                (k + 1).max(k_last.clamp(0.0, n_samples as f32) as u32)
            } else {
                n_samples
            };
            let full_end = k_end.min(n_full);
            #[cfg(target_arch = "x86_64")]
            if let Some(lanes) = lanes
                .as_ref()
                .filter(|_| full_end - k.min(full_end) >= SIMD_MIN_RUN)
            {
                // Up to `SIMD_CHUNK` steps classified before any is visited: the batches'
                // gathers do not wait on one another or on the visitor.
                let mut index = [[0i32; 8]; SIMD_CHUNK / 8];
                while k < full_end {
                    let n = (full_end - k).min(SIMD_CHUNK as u32);
                    let mut visible = lanes.classify(k, n, &mut index);
                    // Visible lanes only, in order: the transparent ones cost nothing more.
                    while visible != 0 {
                        let lane = visible.trailing_zeros();
                        visible &= visible - 1;
                        let e = self.lut.entry(index.as_flattened()[lane as usize] as usize);
                        if self.visit_entry::<SHADE>(&m, ray, k + lane, step, true, e, visit) {
                            return;
                        }
                    }
                    k += n;
                }
            }
            while k < full_end {
                if self.sample_step::<T, SHADE>(data, &m, ray, k, step, true, visit) {
                    return;
                }
                k += 1;
            }
            if k < k_end {
                // The remainder step (k = n_full).
                if self.sample_step::<T, SHADE>(data, &m, ray, k, rem, rem == step, visit) {
                    return;
                }
                k += 1;
            }
        }
    }

    /// Voxel-space midpoint of step `k` (length `len`) and its lower voxel: the same
    /// arithmetic wherever a step is located, so skipping never changes a sample's value.
    #[inline(always)]
    fn locate(&self, m: &Marching, k: u32, len: f32) -> (Vec3, [usize; 3]) {
        let t0 = m.t_in + k as f32 * m.step;
        let p = (m.o_v + (t0 + 0.5 * len) * m.d_v).clamp(Vec3::ZERO, self.max_voxel);
        let [nx, ny, nz] = self.volume.dims();
        (
            p,
            [
                (p.x as usize).min(nx.saturating_sub(2)),
                (p.y as usize).min(ny.saturating_sub(2)),
                (p.z as usize).min(nz.saturating_sub(2)),
            ],
        )
    }

    /// Samples, classifies and visits step `k` of length `len` (`full`: a whole `Δ`, whose
    /// corrected opacity is tabulated); returns true when the visitor stops the ray.
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn sample_step<T: Voxel, const SHADE: bool>(
        &self,
        data: &[T],
        m: &Marching,
        ray: &Ray,
        k: u32,
        len: f32,
        full: bool,
        visit: &mut impl Visit,
    ) -> bool {
        let v = self.step_value(data, m, k, len);
        if v.is_nan() {
            return false;
        }
        let e = self.lut.entry(self.lut.index(v));
        if e.kappa <= 0.0 {
            return false;
        }
        self.visit_entry::<SHADE>(m, ray, k, len, full, e, visit)
    }

    /// The trilinear value at step `k`'s midpoint (the scalar path).
    #[inline(always)]
    fn step_value<T: Voxel>(&self, data: &[T], m: &Marching, k: u32, len: f32) -> f32 {
        let (p, [ix, iy, iz]) = self.locate(m, k, len);
        let [nx, ny, _] = self.volume.dims();
        let (fx, fy, fz) = (p.x - ix as f32, p.y - iy as f32, p.z - iz as f32);
        trilinear(data, ix + nx * (iy + ny * iz), self.strides, fx, fy, fz)
    }

    /// Hands step `k`, classified as `e` (visible: `κ > 0`), to `visit`; returns true when the
    /// visitor stops the ray.
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn visit_entry<const SHADE: bool>(
        &self,
        m: &Marching,
        ray: &Ray,
        k: u32,
        len: f32,
        full: bool,
        e: &LutEntry,
        visit: &mut impl Visit,
    ) -> bool {
        let alpha = if full {
            e.alpha_step
        } else {
            -(-e.kappa * len).exp_m1()
        };
        if alpha <= 0.0 {
            return false;
        }
        let rgb = if SHADE {
            match self.params.shading {
                Some(s) => {
                    let (p, _) = self.locate(m, k, len);
                    s.shade(e.rgb, self.gradient(p), ray.dir, self.inv_spacing)
                }
                None => e.rgb,
            }
        } else {
            e.rgb
        };
        // The interval ends where the next one starts, or at the box exit.
        let t_end = if k + 1 < m.n_samples {
            m.t_in + (k + 1) as f32 * m.step
        } else {
            m.t_far
        };
        visit
            .visit(&Sample {
                index: k,
                t_start: m.t_in + k as f32 * m.step,
                t_end,
                len,
                rgb,
                alpha_unit: e.alpha_unit,
                kappa: e.kappa,
                alpha,
            })
            .is_break()
    }

    /// Trilinear value at voxel-space position `p` (clamped to the grid).
    #[inline]
    pub fn sample(&self, p: Vec3) -> f32 {
        let p = p.clamp(Vec3::ZERO, self.max_voxel);
        let [nx, ny, nz] = self.volume.dims();
        let ix = (p.x as usize).min(nx.saturating_sub(2));
        let iy = (p.y as usize).min(ny.saturating_sub(2));
        let iz = (p.z as usize).min(nz.saturating_sub(2));
        let (i, f) = (
            ix + nx * (iy + ny * iz),
            [p.x - ix as f32, p.y - iy as f32, p.z - iz as f32],
        );
        match self.volume.voxels() {
            VoxelSlice::U8(d) => trilinear(d, i, self.strides, f[0], f[1], f[2]),
            VoxelSlice::U16(d) => trilinear(d, i, self.strides, f[0], f[1], f[2]),
            VoxelSlice::I16(d) => trilinear(d, i, self.strides, f[0], f[1], f[2]),
            VoxelSlice::F32(d) => trilinear(d, i, self.strides, f[0], f[1], f[2]),
        }
    }

    /// Central-difference gradient of the trilinear field at voxel-space `p`, per voxel.
    fn gradient(&self, p: Vec3) -> Vec3 {
        let h = 0.5;
        let d = |axis: Vec3| self.sample(p + h * axis) - self.sample(p - h * axis);
        Vec3::new(d(Vec3::X), d(Vec3::Y), d(Vec3::Z)) / (2.0 * h)
    }
}

/// Trilinear interpolation of the 2×2×2 cell whose lowest corner has flat index `i`; any NaN
/// corner makes the result NaN (missing data is transparent).
#[inline(always)]
fn trilinear<T: Voxel>(
    data: &[T],
    i: usize,
    [sx, sy, sz]: [usize; 3],
    fx: f32,
    fy: f32,
    fz: f32,
) -> f32 {
    let c = &data[i..=i + sx + sy + sz];
    let at = |o: usize| c[o].value();
    let c00 = at(0) + fx * (at(sx) - at(0));
    let c10 = at(sy) + fx * (at(sy + sx) - at(sy));
    let c01 = at(sz) + fx * (at(sz + sx) - at(sz));
    let c11 = at(sz + sy) + fx * (at(sz + sy + sx) - at(sz + sy));
    let c0 = c00 + fy * (c10 - c00);
    let c1 = c01 + fy * (c11 - c01);
    c0 + fz * (c1 - c0)
}

#[cfg(test)]
mod tests;
