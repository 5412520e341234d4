//! The merge of eight neighbouring rays at once with AVX2: the same supersegments as
//! [`super::Builder`], bit for bit, for a fraction of its per-sample cost.
//!
//! The scalar merge spends about 35 cycles per sample (an exponential, two reciprocals, the
//! interrupt test), most of it in instructions that a vector unit does eight at a time. Here
//! eight rays of a row are marched one after another into a lane-interleaved buffer (position
//! `p` holds each lane's `p`-th sample), then merged in lock step: step `p` tests and merges
//! every lane's `p`-th sample in vector registers, and only the lanes that close a
//! supersegment leave them, to append it to their own list. Lanes whose rays have fewer
//! samples idle until the longest is done.
//!
//! Every lane does [`super::Open`]'s operations in its order (products and sums, never fused;
//! [`one_minus_exp_neg`]'s steps; NaN handled as `f32::max` and the comparisons do), so the
//! result is identical to the scalar merge's, which stays the reference and the fallback on
//! CPUs without AVX2; the tests compare them bit for bit.

// The intrinsics are `unsafe`: the module runs them only behind an `Avx2` token (proof of
// detection), on arrays of exactly eight lanes.
#![allow(unsafe_code)]

use super::{generation_ray, Limits, Open, CHUNK};
use crate::camera::ViewFrame;
use crate::raycast::{Avx2, Raycaster, Sample};
use crate::vdi::Supersegment;

/// Rays merged together.
pub(super) const LANES: usize = 8;

/// One position of the lanes' sample buffers: the fields of each lane's sample that the merge
/// reads ([`Sample`], with `κ·len` multiplied out as the scalar merge does).
#[derive(Clone, Copy, Default)]
struct Position {
    index: [u32; LANES],
    t_start: [f32; LANES],
    t_end: [f32; LANES],
    /// `κ·len`: the sample's optical depth.
    depth: [f32; LANES],
    alpha: [f32; LANES],
    alpha_unit: [f32; LANES],
    rgb: [[f32; LANES]; 3],
}

impl Position {
    #[inline(always)]
    fn set(&mut self, l: usize, s: &Sample) {
        self.index[l] = s.index;
        self.t_start[l] = s.t_start;
        self.t_end[l] = s.t_end;
        self.depth[l] = s.kappa * s.len;
        self.alpha[l] = s.alpha;
        self.alpha_unit[l] = s.alpha_unit;
        for c in 0..3 {
            self.rgb[c][l] = s.rgb[c];
        }
    }
}

/// Each lane's open supersegment: [`Open`]'s fields, one element per lane, and whether the
/// lane has one (all bits set) or not (0).
#[derive(Clone, Copy, Default)]
struct OpenLanes {
    open: [u32; LANES],
    last_index: [u32; LANES],
    t_start: [f32; LANES],
    t_end: [f32; LANES],
    color: [[f32; LANES]; 3],
    total: [f32; LANES],
    transmittance: [f32; LANES],
    optical_depth: [f32; LANES],
    unit: [f32; LANES],
    unit_over_total: [f32; LANES],
}

impl OpenLanes {
    /// Lane `l`'s supersegment as the scalar merge holds it.
    #[inline]
    fn lane(&self, l: usize) -> Open {
        Open {
            last_index: self.last_index[l],
            t_start: self.t_start[l],
            t_end: self.t_end[l],
            color: glam::Vec3A::new(self.color[0][l], self.color[1][l], self.color[2][l]),
            total: self.total[l],
            transmittance: self.transmittance[l],
            optical_depth: self.optical_depth[l],
            unit: self.unit[l],
            unit_over_total: self.unit_over_total[l],
        }
    }
}

/// Scratch of [`Lanes::generate`], kept by a worker from one group of rays to the next.
pub(super) struct Lanes {
    avx2: Avx2,
    positions: Vec<Position>,
    out: [Vec<Supersegment>; LANES],
}

impl Lanes {
    /// Lanes on a CPU with AVX2 (`None` without: the scalar merge runs there).
    pub(super) fn new(avx2: Option<Avx2>) -> Option<Self> {
        Some(Self {
            avx2: avx2?,
            positions: Vec::new(),
            out: Default::default(),
        })
    }

    /// The supersegments of pixels `i0 … i0 + width − 1` (`width ≤ LANES`) of row `j`: each
    /// pixel's list appended to `segs` and its length to `counts`, exactly as
    /// [`super::generate_ray`] per pixel would.
    pub(super) fn generate(
        &mut self,
        raycaster: &Raycaster,
        frame: &ViewFrame,
        (i0, j, width): (u32, u32, usize),
        limits: Limits,
        segs: &mut Vec<Supersegment>,
        counts: &mut Vec<u32>,
    ) {
        let gamma_sq = limits.gamma_sq;
        let mut lanes = OpenLanes::default();
        let mut n = [0usize; LANES];
        let mut z_per_t = [0.0f32; LANES];
        let Self {
            avx2,
            positions,
            out,
        } = self;
        let width = width.min(LANES);
        for l in 0..width {
            out[l].clear();
            let (ray, z) = generation_ray(frame, i0 + l as u32, j);
            z_per_t[l] = z;
            let mut transmittance = 1.0f32;
            let mut count = 0usize;
            // Inlined into the marcher's loop (a call there would spill its registers around
            // every sample); the merge of a full buffer is a call, out of the way.
            raycaster.march(
                &ray,
                #[inline(always)]
                |s: &Sample| {
                    if count == positions.len() {
                        // The buffer grows to the longest ray's samples, up to `CHUNK`.
                        if count < CHUNK {
                            grow(positions);
                        } else {
                            flush(*avx2, l, &mut lanes, positions, gamma_sq, &z_per_t, out);
                            count = 0;
                        }
                    }
                    if let Some(at) = positions.get_mut(count) {
                        at.set(l, s);
                        count += 1;
                    }
                    limits.stop(&mut transmittance, s.alpha)
                },
            );
            n[l] = count;
        }
        merge(*avx2, &mut lanes, positions, &n, gamma_sq, &z_per_t, out);
        for (l, out) in out.iter_mut().enumerate().take(width) {
            if lanes.open[l] != 0 {
                out.push(lanes.lane(l).close(z_per_t[l]));
            }
            segs.extend_from_slice(out);
            counts.push(out.len() as u32);
        }
    }
}

/// Doubles the sample buffer (up to [`CHUNK`] positions). Cold and not inlined, as [`flush`].
#[cold]
#[inline(never)]
fn grow(positions: &mut Vec<Position>) {
    let len = (2 * positions.len()).clamp(64, CHUNK);
    positions.resize(len, Position::default());
}

/// Merges lane `l`'s samples of a full buffer on their own. Cold and not inlined, so that the
/// marcher's visitor stays small enough to be inlined into its loop.
#[cold]
#[inline(never)]
fn flush(
    avx2: Avx2,
    l: usize,
    lanes: &mut OpenLanes,
    positions: &[Position],
    gamma_sq: f32,
    z_per_t: &[f32; LANES],
    out: &mut [Vec<Supersegment>; LANES],
) {
    let mut only = [0; LANES];
    only[l] = positions.len();
    merge(avx2, lanes, positions, &only, gamma_sq, z_per_t, out);
}

/// Merges positions `0 … n[l] − 1` of `positions` into each lane `l` of `lanes`, appending
/// the supersegments it closes to `out[l]`.
#[inline]
fn merge(
    avx2: Avx2,
    lanes: &mut OpenLanes,
    positions: &[Position],
    n: &[usize; LANES],
    gamma_sq: f32,
    z_per_t: &[f32; LANES],
    out: &mut [Vec<Supersegment>; LANES],
) {
    let _ = avx2;
    #[cfg(target_arch = "x86_64")]
    // SAFETY: the token proves AVX2.
    unsafe {
        merge_avx2(lanes, positions, n, gamma_sq, z_per_t, out)
    }
    // No token exists elsewhere ([`Avx2::detect`]), so no `Lanes` either.
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (lanes, positions, n, gamma_sq, z_per_t, out);
}

/// [`merge`].
///
/// # Safety
/// The CPU must have AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn merge_avx2(
    lanes: &mut OpenLanes,
    positions: &[Position],
    n: &[usize; LANES],
    gamma_sq: f32,
    z_per_t: &[f32; LANES],
    out: &mut [Vec<Supersegment>; LANES],
) {
    use std::arch::x86_64::*;
    // SAFETY: the caller guarantees AVX2 (this function's contract); every load and store
    // below is an unaligned access of a whole `[_; 8]` array of 4-byte elements.
    unsafe {
        let load = |a: &[f32; LANES]| _mm256_loadu_ps(a.as_ptr());
        let load_i = |a: &[u32; LANES]| _mm256_loadu_si256(a.as_ptr().cast());
        let splat = _mm256_set1_ps;
        let zero = _mm256_setzero_ps();
        let one = splat(1.0);
        let floor = splat(f32::MIN_POSITIVE);
        let g2 = splat(gamma_sq);
        let counts: [u32; LANES] = n.map(|c| c.min(i32::MAX as usize) as u32);
        let counts = load_i(&counts);
        let mut open = _mm256_castsi256_ps(load_i(&lanes.open));
        let mut last = load_i(&lanes.last_index);
        let mut t_start = load(&lanes.t_start);
        let mut t_end = load(&lanes.t_end);
        let mut color = lanes.color.map(|c| load(&c));
        let mut total = load(&lanes.total);
        let mut transmittance = load(&lanes.transmittance);
        let mut depth = load(&lanes.optical_depth);
        let mut unit = load(&lanes.unit);
        let mut unit_over_total = load(&lanes.unit_over_total);
        // `1 / max(v, MIN_POSITIVE)`, as `ratio` (a NaN `v` gives the floor, as `f32::max`).
        let recip_floored = |v: __m256| _mm256_div_ps(one, _mm256_max_ps(v, floor));
        // `(x² + y²) + z²` of `r·C − ac`, as glam's `length_squared`.
        let distance_sq = |r: __m256, color: &[__m256; 3], ac: &[__m256; 3]| {
            let d = [0, 1, 2].map(|c| _mm256_sub_ps(_mm256_mul_ps(r, color[c]), ac[c]));
            _mm256_add_ps(
                _mm256_add_ps(_mm256_mul_ps(d[0], d[0]), _mm256_mul_ps(d[1], d[1])),
                _mm256_mul_ps(d[2], d[2]),
            )
        };
        // `Vec3A::clamp(ZERO, ONE)` as glam computes it: `min_ps(max_ps(v, 0), 1)` (a NaN
        // gives 0).
        let clamp_unit_glam = |v: __m256| _mm256_min_ps(_mm256_max_ps(v, zero), one);
        let z = load(z_per_t);
        let longest = n.iter().copied().max().unwrap_or(0).min(positions.len());
        for (p, s) in positions[..longest].iter().enumerate() {
            let active =
                _mm256_castsi256_ps(_mm256_cmpgt_epi32(counts, _mm256_set1_epi32(p as i32)));
            let (a, au) = (load(&s.alpha), load(&s.alpha_unit));
            let rgb = s.rgb.map(|c| load(&c));
            let ac = rgb.map(|c| _mm256_mul_ps(c, au));
            let live = _mm256_and_ps(active, open);
            // The interrupt test ([`Open::accepts`]).
            let gap = _mm256_castsi256_ps(_mm256_cmpgt_epi32(
                load_i(&s.index),
                _mm256_add_epi32(last, _mm256_set1_epi32(1)),
            ));
            let near = _mm256_cmp_ps::<_CMP_LT_OQ>(distance_sq(unit_over_total, &color, &ac), g2);
            let gaps = _mm256_and_ps(live, gap);
            // After a run of transparent samples (in 4 % of the steps on the teapot).
            let ok = if _mm256_movemask_ps(gaps) == 0 {
                near
            } else {
                let first_ok = _mm256_cmp_ps::<_CMP_NGE_UQ>(
                    distance_sq(unit_over_total, &color, &[zero; 3]),
                    g2,
                );
                let x = _mm256_and_ps(
                    gaps,
                    _mm256_div_ps(depth, _mm256_sub_ps(load(&s.t_start), t_start)),
                );
                let stretched = _mm256_mul_ps(one_minus_exp_neg(x), recip_floored(total));
                let stretched_ok =
                    _mm256_cmp_ps::<_CMP_LT_OQ>(distance_sq(stretched, &color, &ac), g2);
                _mm256_blendv_ps(near, _mm256_and_ps(first_ok, stretched_ok), gaps)
            };
            let accept = _mm256_and_ps(live, ok);
            let close = _mm256_movemask_ps(_mm256_andnot_ps(ok, live)) as u32;
            if close != 0 {
                // [`Open::close`] in every lane at once; the lanes that close their
                // supersegment take theirs out of the vector registers here.
                let inv = recip_floored(total);
                let closed = [
                    _mm256_mul_ps(t_start, z),
                    _mm256_mul_ps(t_end, z),
                    clamp_unit_glam(_mm256_mul_ps(color[0], inv)),
                    clamp_unit_glam(_mm256_mul_ps(color[1], inv)),
                    clamp_unit_glam(_mm256_mul_ps(color[2], inv)),
                    // `f32::clamp(0, 1)`: a NaN stays NaN (`max_ps` and `min_ps` return
                    // their second operand when either is NaN).
                    _mm256_min_ps(one, _mm256_max_ps(zero, unit)),
                ];
                let mut held = [[0.0f32; LANES]; 6];
                for (held, v) in held.iter_mut().zip(closed) {
                    _mm256_storeu_ps(held.as_mut_ptr(), v);
                }
                let mut bits = close;
                while bits != 0 {
                    let l = bits.trailing_zeros() as usize;
                    bits &= bits - 1;
                    out[l].push(Supersegment {
                        z_start: held[0][l],
                        z_end: held[1][l],
                        color: [held[2][l], held[3][l], held[4][l]],
                        alpha: held[5][l],
                    });
                }
            }
            // Merged ([`Open::merge`]) where accepted.
            let w = _mm256_mul_ps(transmittance, a);
            let merged_total = _mm256_add_ps(total, w);
            let sample_depth = load(&s.depth);
            let merged_depth = _mm256_add_ps(depth, sample_depth);
            let s_t_end = load(&s.t_end);
            let inv_len = _mm256_div_ps(one, _mm256_sub_ps(s_t_end, t_start));
            let merged_unit =
                one_minus_exp_neg(_mm256_and_ps(accept, _mm256_mul_ps(merged_depth, inv_len)));
            let merged_ratio = _mm256_mul_ps(merged_unit, recip_floored(merged_total));
            // Opened ([`Open::new`]) where an active lane does not accept.
            let start = _mm256_andnot_ps(accept, active);
            let pick = |old: __m256, merged: __m256, new: __m256| {
                _mm256_blendv_ps(_mm256_blendv_ps(old, new, start), merged, accept)
            };
            for c in 0..3 {
                color[c] = pick(
                    color[c],
                    _mm256_add_ps(color[c], _mm256_mul_ps(w, rgb[c])),
                    _mm256_mul_ps(rgb[c], a),
                );
            }
            let not_a = _mm256_sub_ps(one, a);
            total = pick(total, merged_total, a);
            transmittance = pick(transmittance, _mm256_mul_ps(transmittance, not_a), not_a);
            depth = pick(depth, merged_depth, sample_depth);
            unit = pick(unit, merged_unit, au);
            unit_over_total = pick(
                unit_over_total,
                merged_ratio,
                _mm256_mul_ps(au, recip_floored(a)),
            );
            t_start = _mm256_blendv_ps(t_start, load(&s.t_start), start);
            t_end = _mm256_blendv_ps(t_end, s_t_end, active);
            last = _mm256_castps_si256(_mm256_blendv_ps(
                _mm256_castsi256_ps(last),
                _mm256_castsi256_ps(load_i(&s.index)),
                active,
            ));
            open = _mm256_or_ps(open, active);
        }
        _mm256_storeu_si256(lanes.open.as_mut_ptr().cast(), _mm256_castps_si256(open));
        _mm256_storeu_si256(lanes.last_index.as_mut_ptr().cast(), last);
        _mm256_storeu_ps(lanes.t_start.as_mut_ptr(), t_start);
        _mm256_storeu_ps(lanes.t_end.as_mut_ptr(), t_end);
        for (held, color) in lanes.color.iter_mut().zip(color) {
            _mm256_storeu_ps(held.as_mut_ptr(), color);
        }
        _mm256_storeu_ps(lanes.total.as_mut_ptr(), total);
        _mm256_storeu_ps(lanes.transmittance.as_mut_ptr(), transmittance);
        _mm256_storeu_ps(lanes.optical_depth.as_mut_ptr(), depth);
        _mm256_storeu_ps(lanes.unit.as_mut_ptr(), unit);
        _mm256_storeu_ps(lanes.unit_over_total.as_mut_ptr(), unit_over_total);
    }
}

/// [`crate::fastmath::one_minus_exp_neg`] in each lane, step for step (`x ≥ 0` or NaN).
///
/// # Safety
/// The CPU must have AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
pub(crate) unsafe fn one_minus_exp_neg(x: std::arch::x86_64::__m256) -> std::arch::x86_64::__m256 {
    use crate::fastmath::{EXP2_TAYLOR as C, ROUND};
    use std::arch::x86_64::*;
    let splat = _mm256_set1_ps;
    // `(−x·log₂e).max(−126)`: `max_ps` returns its second operand for a NaN, as `f32::max`.
    let neg_x = _mm256_xor_ps(x, splat(-0.0));
    let y = _mm256_max_ps(
        _mm256_mul_ps(neg_x, splat(std::f32::consts::LOG2_E)),
        splat(-126.0),
    );
    let shifted = _mm256_add_ps(y, splat(ROUND));
    let n = _mm256_sub_ps(shifted, splat(ROUND));
    let f = _mm256_sub_ps(y, n);
    let n_bits = _mm256_sub_epi32(
        _mm256_castps_si256(shifted),
        _mm256_set1_epi32(ROUND.to_bits() as i32),
    );
    let scale = _mm256_castsi256_ps(_mm256_slli_epi32::<23>(_mm256_add_epi32(
        n_bits,
        _mm256_set1_epi32(127),
    )));
    let f2 = _mm256_mul_ps(f, f);
    let pair = |a: f32, b: f32| _mm256_add_ps(splat(a), _mm256_mul_ps(f, splat(b)));
    let q = _mm256_add_ps(
        _mm256_add_ps(pair(C[0], C[1]), _mm256_mul_ps(f2, pair(C[2], C[3]))),
        _mm256_mul_ps(_mm256_mul_ps(f2, f2), pair(C[4], C[5])),
    );
    _mm256_sub_ps(
        _mm256_sub_ps(splat(1.0), scale),
        _mm256_mul_ps(scale, _mm256_mul_ps(f, q)),
    )
}

#[cfg(test)]
mod tests {
    use crate::raycast::{RaycastParams, Raycaster};
    use crate::tf::TransferFunction;
    use crate::vdi::generate::generate;
    use crate::vdi::VdiParams;
    use crate::volume::Volume;
    use crate::Camera;

    /// The lanes' VDI equals the scalar merge's bit for bit: rays longer than the buffer
    /// (merged in several parts), runs of transparent samples inside supersegments, NaN
    /// data, opacity 1, early termination, rows whose last group has fewer than eight rays,
    /// views from behind.
    #[test]
    fn lanes_merge_like_the_scalar_merge() {
        let tf = TransferFunction::from_json(
            r#"{"domain": [0, 1], "points": [[0, 1, 0, 0, 0.04], [0.3, 0, 0, 0, 0],
                [0.45, 0, 0, 0, 0], [0.5, 0, 1, 0, 0.3], [1, 0, 0, 1, 0.9]]}"#,
            "gaps",
        )
        .unwrap();
        let long = Volume::from_fn([6, 7, 700], |x, y, z| {
            ((z as f32 * 0.37).sin() * 0.5 + 0.5) * (0.8 + 0.03 * (x + y) as f32)
        })
        .unwrap();
        let blobs = Volume::from_fn([37, 29, 41], |x, y, z| {
            if (x * 7 + y * 3 + z) % 97 == 0 {
                f32::NAN
            } else {
                ((x as f32 * 0.4).sin() * (y as f32 * 0.3).cos() + (z as f32 * 0.2).sin()) * 0.3
                    + 0.5
            }
        })
        .unwrap();
        // Opacity 1 above 0.7 (`κ = ∞`), a huge dynamic range below it.
        let opaque = TransferFunction::from_json(
            r#"{"domain": [0, 1], "points": [[0, 1, 1, 1, 1e-7], [0.3, 0, 0, 0, 0],
                [0.5, 0, 1, 0, 0.001], [0.69, 1, 0, 0, 0.5], [0.7, 1, 1, 0, 1], [1, 1, 1, 1, 1]]}"#,
            "opaque",
        )
        .unwrap();
        let (mut compared, mut opaque_seen) = (0, false);
        for (volume, tf, step, termination) in [
            (&long, &tf, 0.1, None),
            (&blobs, &tf, 0.5, None),
            (&blobs, &tf, 0.3, Some(0.9)),
            (&blobs, &opaque, 0.5, None),
            (&long, &opaque, 0.7, Some(1.0)),
        ] {
            let params = RaycastParams {
                sample_distance: step,
                generation_termination: termination,
                ..Default::default()
            };
            let rc = Raycaster::new(volume, tf, params).unwrap();
            let scalar = rc.clone().without_simd();
            let cam = Camera::default_for_box(&volume.world_box());
            for (angle, resolution, gamma) in
                [(0.0, 21, 0.01), (37.0, 32, 0.002), (180.0, 19, 0.05)]
            {
                let camera = cam.orbit_y(angle);
                let p = VdiParams {
                    resolution,
                    gamma,
                    precision: Default::default(),
                };
                let lanes = generate(&rc, &camera, p, 0, "").unwrap();
                let reference = generate(&scalar, &camera, p, 0, "").unwrap();
                assert_eq!(lanes, reference, "{angle}°, r = {resolution}, step {step}");
                compared += reference.supersegments().len();
                opaque_seen |= reference.supersegments().iter().any(|s| s.alpha == 1.0);
            }
        }
        assert!(compared > 5_000, "{compared} supersegments compared");
        assert!(
            opaque_seen,
            "the opaque cases must close opaque supersegments"
        );
        if !Raycaster::new(&blobs, &tf, RaycastParams::default())
            .unwrap()
            .uses_simd()
        {
            eprintln!("no AVX2 here: the lanes were not run, only the scalar merge");
        }
    }
}
