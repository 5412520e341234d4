//! Packets of eight neighbouring rays walked together over the generation image.
//!
//! Rays through pixels on one epipolar line of the new image (the line through the pixel
//! and the generation eye's image) lie in one plane with the generation eye, so they project
//! onto one line of the generation image. A packet is a block of eight pixels laid along
//! those lines ([`shape`]: 8×1, 4×2, 2×4 or 1×8 per 16-pixel tile), so its rays cross nearly
//! the same generation pixels. Those pixels are visited once for all of them: in rows (along
//! the axis the projections cross least) and, within a row, along the other axis, both in the
//! direction every projection steps. Each projection is a monotone staircase, so each ray
//! still meets its pixels in its own order and composites front to back. A packet whose
//! projections step both ways along an axis (around the epipole) is walked ray by ray
//! ([`Walker::walk_segment`]).
//!
//! A pixel's tile, occupancy and list are loaded once; the lanes' spans in the row, their
//! depth bins and occupancy tests, their exact spans (the single walk's crossings, [`cross`])
//! and their compositing (each supersegment into all lanes at once, one exponential for eight)
//! run eight lanes wide with AVX2 where the CPU has it (chosen at run time; the set-up of the
//! eight segments too). The portable path does the same per lane: both give the same image
//! bit for bit, and the single walk's to rounding (spans taken as the maximum of the entries
//! and the minimum of the exits instead of in the order a DDA meets them); the tests pin both.

// Calling the kernel compiled for AVX2 is `unsafe` (a `#[target_feature]` function); it is
// called only behind an [`Avx2`] token, proof of the CPU's support. Nothing else here is.
#![allow(unsafe_code)]

use super::{
    composite_span, cross, ending_after, greater, lesser, starting_before, Accum, Axis, DepthBins,
    Lin, Segment, Supersegment, Walker, DEGENERATE_PX, DEPTH_BINS, NEAR_DEPTH, SKIP_SHIFT,
    SKIP_TILE,
};
use crate::camera::ViewFrame;
#[cfg(test)]
use crate::image::Image;
use crate::raycast::FrontToBack;
use glam::Vec3;

/// Rays per packet.
pub(super) const LANES: usize = 8;

/// A packet's pixels in the new image: lane `k` is pixel `(i0 + k mod w, j0 + ⌊k / w⌋)`, the
/// block `w = 2^shift` (1, 2, 4 or 8) pixels wide and `8 / w` tall.
#[derive(Clone, Copy, Debug)]
pub(super) struct Block {
    i0: u32,
    j0: u32,
    shift: u32,
}

impl Block {
    /// The block at `(i0, j0)`, `w` wide (a power of two dividing [`LANES`]).
    pub(super) fn new(i0: u32, j0: u32, w: u32) -> Self {
        debug_assert!(w.is_power_of_two() && LANES as u32 % w == 0);
        Self {
            i0,
            j0,
            shift: w.trailing_zeros(),
        }
    }

    /// Lane `k`'s pixel.
    #[inline]
    fn pixel(self, k: usize) -> (u32, u32) {
        let k = k as u32;
        (
            self.i0 + (k & ((1 << self.shift) - 1)),
            self.j0 + (k >> self.shift),
        )
    }
}

/// The packet shape `(w, h)` for the 16-pixel tile at `(x0, y0)` of `frame`: the one that
/// lies most nearly along the epipolar line there (through the tile's centre and the
/// generation eye's image, `gen_eye` in `frame`'s eye space), 8×1, 4×2, 2×4 or 1×8. Rays
/// through pixels on one epipolar line of the new image project onto one line of the
/// generation image, so a packet along it shares nearly all of its generation pixels.
pub(super) fn shape(frame: &ViewFrame, gen_eye: Vec3, x0: u32, y0: u32) -> (u32, u32) {
    let half = crate::dvr::TILE as f32 / 2.0;
    let sx = (2.0 * (x0 as f32 + half) / frame.width as f32 - 1.0) * frame.tan_half_x;
    let sy = (1.0 - 2.0 * (y0 as f32 + half) / frame.height as f32) * frame.tan_half_y;
    // The line from the pixel to the epipole `gen_eye.xy / gen_eye.z`, times `gen_eye.z`
    // (whose sign does not matter; 0 where the lines are parallel), in pixels.
    let dx = (sx * gen_eye.z - gen_eye.x) * frame.width as f32 / frame.tan_half_x;
    let dy = (sy * gen_eye.z - gen_eye.y) * frame.height as f32 / frame.tan_half_y;
    let (dx, dy) = (dx.abs(), dy.abs());
    // tan 22.5° and tan 67.5°.
    const FLAT: f32 = 0.414_213_57;
    const STEEP: f32 = 2.414_213_6;
    if !(dx > 0.0 || dy > 0.0) {
        (4, 2)
    } else if dy < FLAT * dx {
        (8, 1)
    } else if dy <= dx {
        (4, 2)
    } else if dy <= STEEP * dx {
        (2, 4)
    } else {
        (1, 8)
    }
}

type F = [f32; LANES];
type I = [i32; LANES];

/// The lanes of a packet as arrays (structure of arrays): what the row spans, the occupancy
/// tests, the exact spans and the compositing read, a lane's values at one index.
struct Lanes {
    /// Lanes with a segment and not yet done: −1 (all bits set), else 0.
    live: I,
    /// Outer axis: where the projection starts, `1/(p1 − p0)`, 1 when stepping up.
    o_p0: F,
    o_inv: F,
    o_ahead: I,
    /// The first and last row, in walk order (multiplied by the rows' direction).
    first: I,
    last: I,
    /// Inner axis: as the outer, with `p1 − p0`, whether it steps (−1, else 0) and the
    /// pixel it stays in when it does not.
    i_p0: F,
    i_inv: F,
    i_d: F,
    i_ahead: I,
    i_steps: I,
    i_cell: I,
    /// Inverse depth at both ends, their difference and the occupancy tests' margin.
    w0: F,
    w1: F,
    dw: F,
    margin: F,
    /// The ray's generation eye-space coordinates along the outer and inner axes and its
    /// depth, `f0 + f1·t` each, over `[t0, t1]`: what the exact crossings solve.
    o0: F,
    o1: F,
    i0: F,
    i1: F,
    z0: F,
    z1: F,
    t0: F,
    t1: F,
    /// The lanes whose depth grows along the ray (`z1 > 0`), and those where it falls.
    deeper: u32,
    shallower: u32,
    /// Whether the inner axis is x (else y); `tan` of the generation's half field of view
    /// along the outer and inner axes; the generation resolution.
    inner_x: bool,
    o_tan: f32,
    i_tan: f32,
    r: f32,
}

impl Lanes {
    /// Where lane `k`'s ray crosses boundary `b` of the inner axis (`inner`) or the outer
    /// one ([`cross`]).
    #[inline(always)]
    fn cross(&self, k: usize, inner: bool, b: i32) -> f32 {
        let (x_axis, tan, f0, f1) = if inner {
            (self.inner_x, self.i_tan, self.i0[k], self.i1[k])
        } else {
            (!self.inner_x, self.o_tan, self.o0[k], self.o1[k])
        };
        let z = Lin {
            f0: self.z0[k],
            f1: self.z1[k],
        };
        let limits = [self.t0[k], self.t1[k]];
        cross(x_axis, b as f32, self.r, tan, Lin { f0, f1 }, z, limits)
    }
}

/// Per lane, its `u` range in the current row, its first and last pixel there (in walk
/// order; `first > last` for a lane not in the row) and its exact span of the row.
struct Row {
    u_in: F,
    u_out: F,
    c_in: I,
    c_out: I,
    /// The exact ray parameters where the lane enters and leaves the row.
    t_in: F,
    t_out: F,
}

impl Walker<'_> {
    /// Composited colours of the rays of `block`'s pixels of `frame` into `out` (lane order,
    /// which is the block's row-major order; pixels outside the frame are left black).
    pub(super) fn integrate_packet(
        &self,
        frame: &ViewFrame,
        block: Block,
        termination: f32,
        out: &mut [[f32; 3]],
    ) {
        let segs = match self.avx2 {
            // SAFETY: the token proves that this CPU has AVX2.
            Some(_) => unsafe { segments_avx2(self, frame, block) },
            None => self.segments(frame, block),
        };
        out.fill([0.0; 3]);
        if segs.iter().all(Option::is_none) {
            return;
        }
        let walked = match self.avx2 {
            // SAFETY: the token proves that this CPU has AVX2.
            Some(_) => unsafe { self.walk_packet_avx2(&segs, termination, out) },
            None => self.walk_packet::<false>(&segs, termination, out),
        };
        if !walked {
            // Projections stepping both ways along an axis: no order of pixels suits all of
            // them; each is walked on its own.
            for (seg, o) in segs.iter().zip(out) {
                if let Some(seg) = seg {
                    let mut acc = Accum::new(termination);
                    self.walk_segment(seg, &mut acc);
                    *o = acc.ray.finish().0;
                }
            }
        }
    }

    /// [`Walker::segment`] of the rays through `block`'s pixels of `frame` (`None` outside
    /// the frame).
    fn segments(&self, frame: &ViewFrame, block: Block) -> [Option<Segment>; LANES] {
        let mut segs = [None; LANES];
        for (k, seg) in segs.iter_mut().enumerate() {
            let (i, j) = block.pixel(k);
            if i < frame.width && j < frame.height {
                *seg = self.segment(&frame.pixel_ray(i, j));
            }
        }
        segs
    }

    /// [`Self::walk_packet`] compiled for AVX2.
    ///
    /// # Safety
    /// The CPU must have AVX2.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn walk_packet_avx2(
        &self,
        segs: &[Option<Segment>; LANES],
        termination: f32,
        out: &mut [[f32; 3]],
    ) -> bool {
        self.walk_packet::<true>(segs, termination, out)
    }

    /// Walks `segs` together, each stopping at accumulated opacity `termination`, and writes
    /// their colours to `out`; false, having done nothing, when they step in opposite
    /// directions along an axis.
    #[inline(always)]
    fn walk_packet<const AVX2: bool>(
        &self,
        segs: &[Option<Segment>; LANES],
        termination: f32,
        out: &mut [[f32; 3]],
    ) -> bool {
        // Rows along the axis the projections cross least.
        let (dx, dy) = segs.iter().flatten().fold((0.0, 0.0), |(dx, dy), s| {
            (dx + (s.px1 - s.px0).abs(), dy + (s.py1 - s.py0).abs())
        });
        if dy > dx {
            self.walk_rows::<true, AVX2>(segs, termination, out)
        } else {
            self.walk_rows::<false, AVX2>(segs, termination, out)
        }
    }

    /// [`Self::walk_packet`] in rows along y (columns of x when `TRANSPOSE`): the lanes set
    /// up ([`Lanes::new`]), then each row's span of pixels walked ([`Self::walk_row`]) until
    /// every lane is done or past its last row.
    #[inline(always)]
    fn walk_rows<const TRANSPOSE: bool, const AVX2: bool>(
        &self,
        segs: &[Option<Segment>; LANES],
        termination: f32,
        out: &mut [[f32; 3]],
    ) -> bool {
        let Some((so, si)) = directions::<TRANSPOSE>(segs) else {
            return false;
        };
        let tan = (self.gen.tan_half_x, self.gen.tan_half_y);
        let mut l = Lanes::new::<TRANSPOSE>(segs, so, self.r, tan);
        // How far each lane has composited.
        let mut t_done = segs.map(|s| s.map_or(0.0, |s| s.t0));
        let mut acc = Accums {
            rgb: [[0.0; LANES]; 3],
            transmittance: [1.0; LANES],
        };
        let r_top = (self.r - 1) as f32;
        let start = *l.first.iter().min().unwrap_or(&0);
        let end = *l.last.iter().max().unwrap_or(&-1);
        for ord in start..=end {
            if l.live.iter().all(|&x| x == 0) {
                break;
            }
            let (mut row, ks, ws) = if AVX2 {
                // SAFETY: `AVX2` is set only by `walk_packet_avx2`, which needs AVX2.
                unsafe { row_spans_avx2(&l, ord, so as i32, si as i32, r_top) }
            } else {
                row_spans(&l, ord, so as i32, si as i32, r_top)
            };
            let o = so as i32 * ord;
            let lanes = (&mut l, &mut row, &mut acc, &mut t_done);
            self.walk_row::<TRANSPOSE, AVX2>(lanes, (o, si as i32), (ks, ws), termination);
        }
        for (k, o) in out.iter_mut().enumerate() {
            let mut ray = FrontToBack::new(termination);
            ray.color = [acc.rgb[0][k], acc.rgb[1][k], acc.rgb[2][k]];
            ray.transmittance = acc.transmittance[k];
            *o = ray.finish().0;
        }
        true
    }

    /// The pixels `k_first … k_last` (in walk order, `c = si·k`) of row `o` (column when
    /// `TRANSPOSE`), whose depths the lanes' spans there meet between inverse depths `w_lo`
    /// and `w_hi`: an 8×8 tile whose depths miss those is passed in one jump, a pixel whose
    /// depth-occupancy bins miss them at once; the others are tested per lane
    /// ([`pixel_tests`]), their exact spans found ([`pixel_spans`]) and their lists
    /// composited into the lanes ([`composite_lanes`]); lanes that reach `termination` are
    /// done.
    #[inline(always)]
    fn walk_row<const TRANSPOSE: bool, const AVX2: bool>(
        &self,
        (l, row, acc, t_done): (&mut Lanes, &mut Row, &mut Accums, &mut F),
        (o, si): (i32, i32),
        ([k_first, k_last], [w_lo, w_hi]): ([i32; 2], [f32; 2]),
        termination: f32,
    ) {
        if k_first > k_last {
            return;
        }
        let bins = self.tables.bins;
        let offsets = self.vdi.offsets();
        let top = (DEPTH_BINS - 1) as f32;
        let bin = |w: f32| lesser(greater((w - bins.w0) * bins.per_unit, 0.0), top) as i32;
        // The row's depth bins: a pixel whose occupancy misses them is passed at once.
        let row_bins = super::bits(bin(w_lo) as u32, bin(w_hi) as u32);
        let r = self.r;
        let mut walking = -1i64;
        let mut kk = k_first;
        while kk <= k_last {
            let c = si * kk;
            let (ix, iy) = if TRANSPOSE {
                (i64::from(o), i64::from(c))
            } else {
                (i64::from(c), i64::from(o))
            };
            let tile = (ix >> SKIP_SHIFT) + self.tables.tiles_x * (iy >> SKIP_SHIFT);
            if tile != walking {
                let [t_lo, t_hi] = self.tables.tile_w[tile as usize];
                if w_lo > t_hi || w_hi < t_lo {
                    // Nothing of the tile's depths in the row's: on to the next tile.
                    let tile_last = if si > 0 {
                        c | (SKIP_TILE as i32 - 1)
                    } else {
                        c & !(SKIP_TILE as i32 - 1)
                    };
                    kk = si * tile_last + 1;
                    continue;
                }
                walking = tile;
            }
            let p = (ix + r * iy) as usize;
            let occupied = self.tables.pixel_bins[p];
            if occupied & row_bins == 0 {
                kk += 1;
                continue;
            }
            let pass = if AVX2 {
                // SAFETY: `AVX2` is set only by `walk_packet_avx2`, which needs AVX2.
                unsafe { pixel_tests_avx2(l, row, c, kk, occupied, bins) }
            } else {
                pixel_tests(l, row, c, kk, occupied, bins)
            };
            if pass == 0 {
                kk += 1;
                continue;
            }
            let spans = if AVX2 {
                // SAFETY: `AVX2` is set only by `walk_packet_avx2`, which needs AVX2.
                unsafe { pixel_spans_avx2(l, row, c, kk, pass, t_done) }
            } else {
                pixel_spans(l, row, c, kk, pass, t_done)
            };
            if spans.lanes != 0 {
                let range = offsets[p] as usize..offsets[p + 1] as usize;
                let (list, keys) = (
                    &self.vdi.supersegments()[range.clone()],
                    &self.tables.keys[range],
                );
                let done = if AVX2 {
                    // SAFETY: `AVX2` is set only by `walk_packet_avx2`, which needs AVX2.
                    unsafe { composite_lanes_avx2(list, keys, l, &spans, acc, termination) }
                } else {
                    composite_lanes(list, keys, l, &spans, acc, termination)
                };
                for k in 0..LANES {
                    if done & (1 << k) != 0 {
                        l.live[k] = 0;
                        row.c_in[k] = i32::MAX;
                        row.c_out[k] = i32::MIN;
                    }
                }
            }
            kk += 1;
        }
    }
}

/// A segment's axes as (outer, inner) with the projection's extent along each: rows along y
/// (the outer axis y), or along x when `TRANSPOSE`.
#[inline(always)]
fn axes<const TRANSPOSE: bool>(s: &Segment) -> (Axis, Axis, f32, f32) {
    if TRANSPOSE {
        (s.ax, s.ay, s.px1 - s.px0, s.py1 - s.py0)
    } else {
        (s.ay, s.ax, s.py1 - s.py0, s.px1 - s.px0)
    }
}

/// The direction of rows, and of pixels in a row, that every stepping projection of `segs`
/// takes (+1 where none steps); `None` when two step opposite ways along an axis.
#[inline(always)]
fn directions<const TRANSPOSE: bool>(segs: &[Option<Segment>; LANES]) -> Option<(i64, i64)> {
    let (mut so, mut si) = (0i64, 0i64);
    for s in segs.iter().flatten() {
        let (o, i, _, _) = axes::<TRANSPOSE>(s);
        for (dir, step) in [(&mut so, o.step), (&mut si, i.step)] {
            if step != 0 {
                if *dir == 0 {
                    *dir = step;
                } else if *dir != step {
                    return None;
                }
            }
        }
    }
    Some((if so == 0 { 1 } else { so }, if si == 0 { 1 } else { si }))
}

impl Lanes {
    /// The lanes of `segs` walked in rows of direction `so` (along x when `TRANSPOSE`) at
    /// generation resolution `r` with `tan` of the half field of view along x and y.
    #[inline(always)]
    fn new<const TRANSPOSE: bool>(
        segs: &[Option<Segment>; LANES],
        so: i64,
        r: i64,
        (tan_x, tan_y): (f32, f32),
    ) -> Self {
        let mut l = Lanes {
            live: [0; LANES],
            o_p0: [0.0; LANES],
            o_inv: [0.0; LANES],
            o_ahead: [0; LANES],
            first: [i32::MAX; LANES],
            last: [i32::MIN; LANES],
            i_p0: [0.0; LANES],
            i_inv: [0.0; LANES],
            i_d: [0.0; LANES],
            i_ahead: [0; LANES],
            i_steps: [0; LANES],
            i_cell: [0; LANES],
            w0: [0.0; LANES],
            w1: [0.0; LANES],
            dw: [0.0; LANES],
            margin: [0.0; LANES],
            o0: [0.0; LANES],
            o1: [0.0; LANES],
            i0: [0.0; LANES],
            i1: [0.0; LANES],
            z0: [0.0; LANES],
            z1: [0.0; LANES],
            t0: [0.0; LANES],
            t1: [0.0; LANES],
            inner_x: !TRANSPOSE,
            deeper: 0,
            shallower: 0,
            o_tan: if TRANSPOSE { tan_x } else { tan_y },
            i_tan: if TRANSPOSE { tan_y } else { tan_x },
            r: r as f32,
        };
        for (k, s) in segs.iter().enumerate() {
            let Some(s) = s else { continue };
            let (o, i, o_d, i_d) = axes::<TRANSPOSE>(s);
            let last = if o.step == 0 {
                o.cell
            } else {
                o.cell_at(1.0, o_d, [0, r])
            };
            l.live[k] = -1;
            l.o_p0[k] = o.p0;
            l.o_inv[k] = o.inv_d;
            l.o_ahead[k] = o.ahead as i32;
            l.first[k] = (so * o.cell) as i32;
            l.last[k] = (so * last) as i32;
            l.i_p0[k] = i.p0;
            l.i_inv[k] = i.inv_d;
            l.i_d[k] = i_d;
            l.i_ahead[k] = i.ahead as i32;
            l.i_steps[k] = -i32::from(i.step != 0);
            l.i_cell[k] = i.cell as i32;
            l.w0[k] = s.w0;
            l.w1[k] = s.w1;
            l.dw[k] = s.w1 - s.w0;
            l.margin[k] = s.rounding + s.ax.depth_error + s.ay.depth_error;
            let (outer, inner) = if TRANSPOSE { (s.x, s.y) } else { (s.y, s.x) };
            (l.o0[k], l.o1[k], l.i0[k], l.i1[k]) = (outer.f0, outer.f1, inner.f0, inner.f1);
            (l.z0[k], l.z1[k], l.t0[k], l.t1[k]) = (s.z.f0, s.z.f1, s.t0, s.t1);
            l.deeper |= u32::from(s.z.f1 > 0.0) << k;
            l.shallower |= u32::from(s.z.f1 < 0.0) << k;
        }
        l
    }
}

/// The packet's accumulators (structure of arrays): each lane's premultiplied colour and
/// transmittance, as its [`FrontToBack`]'s.
struct Accums {
    rgb: [F; 3],
    transmittance: F,
}

/// The spans the lanes composite at one pixel: ray parameters `[ta, tb]`, for the lanes
/// whose bits `lanes` holds.
struct Spans {
    ta: F,
    tb: F,
    lanes: u32,
}

/// Composites each lane of `spans` through the pixel list `list` (with its `keys`) as
/// [`composite_span`] does; returns the bits of the lanes that reached `termination`.
fn composite_lanes(
    list: &[Supersegment],
    keys: &[[f32; 2]],
    l: &Lanes,
    spans: &Spans,
    acc: &mut Accums,
    termination: f32,
) -> u32 {
    let mut done = 0;
    for k in 0..LANES {
        if spans.lanes & (1 << k) == 0 {
            continue;
        }
        let mut a = Accum::new(termination);
        a.ray.color = [acc.rgb[0][k], acc.rgb[1][k], acc.rgb[2][k]];
        a.ray.transmittance = acc.transmittance[k];
        let z = Lin {
            f0: l.z0[k],
            f1: l.z1[k],
        };
        if composite_span(list, keys, z, spans.ta[k], spans.tb[k], &mut a) {
            done |= 1 << k;
        }
        for (c, v) in acc.rgb.iter_mut().zip(a.ray.color) {
            c[k] = v;
        }
        acc.transmittance[k] = a.ray.transmittance;
    }
    done
}

/// [`composite_lanes`] with AVX2: where every lane's depth runs the same way along its ray,
/// the list is traversed once for all of them, each supersegment composited into the eight
/// lanes at once (a lane outside it gets length 0, which composites nothing); else lane by
/// lane. The same operations per lane in the same order, so the same result.
///
/// # Safety
/// The CPU must have AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn composite_lanes_avx2(
    list: &[Supersegment],
    keys: &[[f32; 2]],
    l: &Lanes,
    spans: &Spans,
    acc: &mut Accums,
    termination: f32,
) -> u32 {
    use crate::vdi::generate::one_minus_exp_neg_avx2;
    use lanes8::*;
    use std::arch::x86_64::*;
    let lanes = spans.lanes;
    let forward = l.deeper & lanes == lanes;
    if !forward && l.shallower & lanes != lanes {
        return composite_lanes(list, keys, l, spans, acc, termination);
    }
    let (ta, tb, z0, z1) = (load(&spans.ta), load(&spans.tb), load(&l.z0), load(&l.z1));
    let za = _mm256_add_ps(z0, _mm256_mul_ps(z1, ta));
    let zb = _mm256_add_ps(z0, _mm256_mul_ps(z1, tb));
    let span = _mm256_sub_ps(tb, ta);
    let mut live = lanes_mask(lanes);
    let (mut r, mut g, mut b) = (load(&acc.rgb[0]), load(&acc.rgb[1]), load(&acc.rgb[2]));
    let mut t = load(&acc.transmittance);
    let threshold = _mm256_set1_ps(Accum::new(termination).threshold);
    let zero = _mm256_setzero_ps();
    // The lanes' extreme depths: where the traversal starts and ends.
    let (big, small) = (_mm256_set1_ps(f32::MAX), _mm256_set1_ps(-f32::MAX));
    let z_lo = fold_ps(_mm256_blendv_ps(big, za, live), _mm256_min_ps);
    let z_hi = fold_ps(_mm256_blendv_ps(small, za, live), _mm256_max_ps);
    let z_min_b = fold_ps(_mm256_blendv_ps(big, zb, live), _mm256_min_ps);
    let z_max_b = fold_ps(_mm256_blendv_ps(small, zb, live), _mm256_max_ps);
    // One supersegment into every live lane, with `len` its length on each lane's ray.
    let mut add = |s: &Supersegment, kappa: f32, len: __m256| -> bool {
        // `len.clamp(0, span)`.
        let len = _mm256_blendv_ps(len, zero, _mm256_cmp_ps::<_CMP_LT_OQ>(len, zero));
        let len = _mm256_blendv_ps(len, span, _mm256_cmp_ps::<_CMP_GT_OQ>(len, span));
        let m = _mm256_and_ps(live, _mm256_cmp_ps::<_CMP_GT_OQ>(len, zero));
        if s.alpha > 0.0 && _mm256_movemask_ps(m) != 0 {
            let alpha = one_minus_exp_neg_avx2(_mm256_mul_ps(len, _mm256_set1_ps(kappa)));
            let w = _mm256_mul_ps(t, alpha);
            let c = s.color;
            r = _mm256_blendv_ps(
                r,
                _mm256_add_ps(r, _mm256_mul_ps(w, _mm256_set1_ps(c[0]))),
                m,
            );
            g = _mm256_blendv_ps(
                g,
                _mm256_add_ps(g, _mm256_mul_ps(w, _mm256_set1_ps(c[1]))),
                m,
            );
            b = _mm256_blendv_ps(
                b,
                _mm256_add_ps(b, _mm256_mul_ps(w, _mm256_set1_ps(c[2]))),
                m,
            );
            t = _mm256_blendv_ps(
                t,
                _mm256_mul_ps(t, _mm256_sub_ps(_mm256_set1_ps(1.0), alpha)),
                m,
            );
            // Lanes done: opaque enough.
            let done = _mm256_and_ps(m, _mm256_cmp_ps::<_CMP_LE_OQ>(t, threshold));
            live = _mm256_andnot_ps(done, live);
        }
        _mm256_movemask_ps(live) == 0
    };
    if forward {
        // From the first supersegment ending after the nearest entry, up to the farthest exit.
        let first = ending_after(keys, z_lo);
        for (s, k) in list[first..].iter().zip(&keys[first..]) {
            if s.z_start >= z_max_b {
                break;
            }
            let len = _mm256_div_ps(
                _mm256_sub_ps(
                    _mm256_min_ps(_mm256_set1_ps(s.z_end), zb),
                    _mm256_max_ps(_mm256_set1_ps(s.z_start), za),
                ),
                z1,
            );
            if add(s, k[1], len) {
                break;
            }
        }
    } else {
        // From the last supersegment starting before the farthest entry, down to the
        // nearest exit.
        let end = starting_before(list, z_hi);
        let neg_z1 = _mm256_xor_ps(z1, _mm256_set1_ps(-0.0));
        for (s, k) in list[..end].iter().zip(&keys[..end]).rev() {
            if s.z_end <= z_min_b {
                break;
            }
            let len = _mm256_div_ps(
                _mm256_sub_ps(
                    _mm256_min_ps(_mm256_set1_ps(s.z_end), za),
                    _mm256_max_ps(_mm256_set1_ps(s.z_start), zb),
                ),
                neg_z1,
            );
            if add(s, k[1], len) {
                break;
            }
        }
    }
    acc.rgb = [lanes_of(r), lanes_of(g), lanes_of(b)];
    acc.transmittance = lanes_of(t);
    lanes & !(_mm256_movemask_ps(live) as u32)
}

/// The lanes that test pixel `c` (walk-order index `kk`, occupancy mask `occupied`) of the
/// current row: bit `k` set where lane `k` crosses the pixel and the depth bins of its span
/// there meet the occupancy (the single walk's test, [`super::between`]).
#[inline(always)]
fn pixel_tests(l: &Lanes, row: &Row, c: i32, kk: i32, occupied: u64, bins: DepthBins) -> u32 {
    let mut pass = 0;
    for k in 0..LANES {
        let entry = (c + 1 - l.i_ahead[k]) as f32;
        let exit = (c + l.i_ahead[k]) as f32;
        let u_a = greater((entry - l.i_p0[k]) * l.i_inv[k], row.u_in[k]);
        let u_b = lesser((exit - l.i_p0[k]) * l.i_inv[k], row.u_out[k]);
        let u_a = if kk == row.c_in[k] { row.u_in[k] } else { u_a };
        let u_b = if kk == row.c_out[k] {
            row.u_out[k]
        } else {
            u_b
        };
        let w_at = |u: f32| {
            if u >= 1.0 {
                l.w1[k]
            } else {
                l.w0[k] + l.dw[k] * u
            }
        };
        let (wa, wb) = (w_at(u_a), w_at(u_b));
        let lo = bins.bin(lesser(wa, wb) - l.margin[k]);
        let hi = bins.bin(greater(wa, wb) + l.margin[k]);
        let covers = row.c_in[k] <= kk && kk <= row.c_out[k];
        if covers && occupied & super::bits(lo, hi) != 0 {
            pass |= 1 << k;
        }
    }
    pass
}

/// [`pixel_tests`], eight lanes at once with AVX2; the same operations in the same order,
/// so the same result.
///
/// # Safety
/// The CPU must have AVX2.
#[cfg(target_arch = "x86_64")]
#[inline]
#[target_feature(enable = "avx2")]
unsafe fn pixel_tests_avx2(
    l: &Lanes,
    row: &Row,
    c: i32,
    kk: i32,
    occupied: u64,
    bins: DepthBins,
) -> u32 {
    use lanes8::*;
    use std::arch::x86_64::*;
    const _: () = assert!(LANES == 8);
    let c = _mm256_set1_epi32(c);
    let kk = _mm256_set1_epi32(kk);
    let ahead = load_i(&l.i_ahead);
    let entry = _mm256_cvtepi32_ps(_mm256_sub_epi32(
        _mm256_add_epi32(c, _mm256_set1_epi32(1)),
        ahead,
    ));
    let exit = _mm256_cvtepi32_ps(_mm256_add_epi32(c, ahead));
    let (p0, inv) = (load(&l.i_p0), load(&l.i_inv));
    let (u_in, u_out) = (load(&row.u_in), load(&row.u_out));
    let (c_in, c_out) = (load_i(&row.c_in), load_i(&row.c_out));
    let u_a = greater(_mm256_mul_ps(_mm256_sub_ps(entry, p0), inv), u_in);
    let u_b = lesser(_mm256_mul_ps(_mm256_sub_ps(exit, p0), inv), u_out);
    let u_a = _mm256_blendv_ps(u_a, u_in, _mm256_castsi256_ps(_mm256_cmpeq_epi32(kk, c_in)));
    let u_b = _mm256_blendv_ps(
        u_b,
        u_out,
        _mm256_castsi256_ps(_mm256_cmpeq_epi32(kk, c_out)),
    );
    let (w0, w1, dw) = (load(&l.w0), load(&l.w1), load(&l.dw));
    let w_at = |u| w_at(w0, w1, dw, u);
    let (wa, wb) = (w_at(u_a), w_at(u_b));
    let margin = load(&l.margin);
    let (b0, per_unit) = (_mm256_set1_ps(bins.w0), _mm256_set1_ps(bins.per_unit));
    let top = _mm256_set1_ps((DEPTH_BINS - 1) as f32);
    // `DepthBins::bin`: clamped as floats (NaN to 0), then truncated.
    let bin = |w| {
        let x = _mm256_mul_ps(_mm256_sub_ps(w, b0), per_unit);
        _mm256_cvttps_epi32(lesser(greater(x, _mm256_setzero_ps()), top))
    };
    let lo = bin(_mm256_sub_ps(lesser(wa, wb), margin));
    let hi = bin(_mm256_add_ps(greater(wa, wb), margin));
    // `bits(lo, hi) & occupied != 0`, four 64-bit lanes at a time.
    let ones = _mm256_set1_epi64x(-1);
    let occ = _mm256_set1_epi64x(occupied as i64);
    let hits = |lo: __m128i, hi: __m128i| {
        let (lo, hi) = (_mm256_cvtepu32_epi64(lo), _mm256_cvtepu32_epi64(hi));
        let top = _mm256_sub_epi64(_mm256_set1_epi64x(i64::from(DEPTH_BINS - 1)), hi);
        let m = _mm256_and_si256(_mm256_srlv_epi64(ones, top), _mm256_sllv_epi64(ones, lo));
        let none = _mm256_cmpeq_epi64(_mm256_and_si256(m, occ), _mm256_setzero_si256());
        (!_mm256_movemask_pd(_mm256_castsi256_pd(none))) as u32 & 0xf
    };
    let hit = hits(_mm256_castsi256_si128(lo), _mm256_castsi256_si128(hi))
        | hits(
            _mm256_extracti128_si256::<1>(lo),
            _mm256_extracti128_si256::<1>(hi),
        ) << 4;
    // Crossing the pixel: c_in ≤ kk ≤ c_out.
    let outside = _mm256_or_si256(_mm256_cmpgt_epi32(c_in, kk), _mm256_cmpgt_epi32(kk, c_out));
    let covers = !(_mm256_movemask_ps(_mm256_castsi256_ps(outside)) as u32) & 0xff;
    hit & covers
}

/// Each lane's span of row `ord` (walk order; rows step by `so`, pixels by `si`), the
/// first and last pixel any lane crosses there, and the inverse depths the lanes span there
/// (with their margins).
#[inline(always)]
fn row_spans(l: &Lanes, ord: i32, so: i32, si: i32, r_top: f32) -> (Row, [i32; 2], [f32; 2]) {
    let o = so * ord;
    let mut row = Row {
        u_in: [0.0; LANES],
        u_out: [0.0; LANES],
        c_in: [i32::MAX; LANES],
        c_out: [i32::MIN; LANES],
        t_in: [0.0; LANES],
        t_out: [0.0; LANES],
    };
    let (mut k_first, mut k_last) = (i32::MAX, i32::MIN);
    let (mut w_lo, mut w_hi) = (f32::MAX, -f32::MAX);
    for k in 0..LANES {
        let entry = (o + 1 - l.o_ahead[k]) as f32;
        let exit = (o + l.o_ahead[k]) as f32;
        let unit = |u: f32| lesser(greater(u, 0.0), 1.0);
        let u_in = unit((entry - l.o_p0[k]) * l.o_inv[k]);
        let u_out = unit((exit - l.o_p0[k]) * l.o_inv[k]);
        let u_in = if ord == l.first[k] { 0.0 } else { u_in };
        let u_out = if ord == l.last[k] { 1.0 } else { u_out };
        row.u_in[k] = u_in;
        row.u_out[k] = u_out;
        let cell = |u: f32| {
            let p = l.i_p0[k] + l.i_d[k] * u;
            // The pixel holding p, the one ahead when p is on a boundary.
            let c = if l.i_ahead[k] == 0 {
                p.ceil() - 1.0
            } else {
                p.floor()
            };
            lesser(greater(c, 0.0), r_top) as i32
        };
        let (c_in, c_out) = if l.i_steps[k] != 0 {
            (cell(u_in), cell(u_out))
        } else {
            (l.i_cell[k], l.i_cell[k])
        };
        if l.live[k] != 0 && l.first[k] <= ord && ord <= l.last[k] {
            row.c_in[k] = si * c_in;
            row.c_out[k] = si * c_out;
            k_first = k_first.min(row.c_in[k]);
            k_last = k_last.max(row.c_out[k]);
            let w_at = |u: f32| {
                if u >= 1.0 {
                    l.w1[k]
                } else {
                    l.w0[k] + l.dw[k] * u
                }
            };
            let (wa, wb) = (w_at(u_in), w_at(u_out));
            w_lo = lesser(w_lo, lesser(wa, wb) - l.margin[k]);
            w_hi = greater(w_hi, greater(wa, wb) + l.margin[k]);
            row.t_in[k] = if ord == l.first[k] {
                l.t0[k]
            } else {
                l.cross(k, false, o + 1 - l.o_ahead[k])
            };
            row.t_out[k] = if ord == l.last[k] {
                l.t1[k]
            } else {
                l.cross(k, false, o + l.o_ahead[k])
            };
        }
    }
    (row, [k_first, k_last], [w_lo, w_hi])
}

/// [`row_spans`] with AVX2, eight lanes at once; the same operations, the same result.
///
/// # Safety
/// The CPU must have AVX2.
#[cfg(target_arch = "x86_64")]
#[inline]
#[target_feature(enable = "avx2")]
unsafe fn row_spans_avx2(
    l: &Lanes,
    ord: i32,
    so: i32,
    si: i32,
    r_top: f32,
) -> (Row, [i32; 2], [f32; 2]) {
    use lanes8::*;
    use std::arch::x86_64::*;
    let (zero, one) = (_mm256_setzero_ps(), _mm256_set1_ps(1.0));
    let ordv = _mm256_set1_epi32(ord);
    let o = _mm256_set1_epi32(so * ord);
    let ahead = load_i(&l.o_ahead);
    let entry = _mm256_cvtepi32_ps(_mm256_sub_epi32(
        _mm256_add_epi32(o, _mm256_set1_epi32(1)),
        ahead,
    ));
    let exit = _mm256_cvtepi32_ps(_mm256_add_epi32(o, ahead));
    let (p0, inv) = (load(&l.o_p0), load(&l.o_inv));
    let unit = |u| lesser(greater(u, zero), one);
    let u_in = unit(_mm256_mul_ps(_mm256_sub_ps(entry, p0), inv));
    let u_out = unit(_mm256_mul_ps(_mm256_sub_ps(exit, p0), inv));
    let (first, last) = (load_i(&l.first), load_i(&l.last));
    let u_in = _mm256_blendv_ps(
        u_in,
        zero,
        _mm256_castsi256_ps(_mm256_cmpeq_epi32(ordv, first)),
    );
    let u_out = _mm256_blendv_ps(
        u_out,
        one,
        _mm256_castsi256_ps(_mm256_cmpeq_epi32(ordv, last)),
    );
    let (i_p0, i_d) = (load(&l.i_p0), load(&l.i_d));
    let behind = _mm256_castsi256_ps(_mm256_cmpeq_epi32(
        load_i(&l.i_ahead),
        _mm256_setzero_si256(),
    ));
    let top = _mm256_set1_ps(r_top);
    let cell = |u| {
        let p = _mm256_add_ps(i_p0, _mm256_mul_ps(i_d, u));
        let c = _mm256_blendv_ps(
            _mm256_floor_ps(p),
            _mm256_sub_ps(_mm256_ceil_ps(p), one),
            behind,
        );
        _mm256_cvttps_epi32(lesser(greater(c, zero), top))
    };
    let steps = load_i(&l.i_steps);
    let i_cell = load_i(&l.i_cell);
    let c_in = _mm256_blendv_epi8(i_cell, cell(u_in), steps);
    let c_out = _mm256_blendv_epi8(i_cell, cell(u_out), steps);
    // In the row: live, and first ≤ ord ≤ last.
    let outside = _mm256_or_si256(
        _mm256_cmpgt_epi32(first, ordv),
        _mm256_cmpgt_epi32(ordv, last),
    );
    let here = _mm256_andnot_si256(outside, load_i(&l.live));
    let dir = _mm256_set1_epi32(si);
    let c_in = _mm256_blendv_epi8(
        _mm256_set1_epi32(i32::MAX),
        _mm256_sign_epi32(c_in, dir),
        here,
    );
    let c_out = _mm256_blendv_epi8(
        _mm256_set1_epi32(i32::MIN),
        _mm256_sign_epi32(c_out, dir),
        here,
    );
    let (w0, w1, dw) = (load(&l.w0), load(&l.w1), load(&l.dw));
    let w_at = |u| w_at(w0, w1, dw, u);
    let (wa, wb) = (w_at(u_in), w_at(u_out));
    let margin = load(&l.margin);
    let here_ps = _mm256_castsi256_ps(here);
    let lo = _mm256_blendv_ps(
        _mm256_set1_ps(f32::MAX),
        _mm256_sub_ps(lesser(wa, wb), margin),
        here_ps,
    );
    let hi = _mm256_blendv_ps(
        _mm256_set1_ps(-f32::MAX),
        _mm256_add_ps(greater(wa, wb), margin),
        here_ps,
    );
    let (t0, t1) = (load(&l.t0), load(&l.t1));
    let cross_o = |b| cross_avx2(l, false, b);
    let t_in = _mm256_blendv_ps(
        cross_o(_mm256_sub_epi32(
            _mm256_add_epi32(o, _mm256_set1_epi32(1)),
            ahead,
        )),
        t0,
        _mm256_castsi256_ps(_mm256_cmpeq_epi32(ordv, first)),
    );
    let t_out = _mm256_blendv_ps(
        cross_o(_mm256_add_epi32(o, ahead)),
        t1,
        _mm256_castsi256_ps(_mm256_cmpeq_epi32(ordv, last)),
    );
    let row = Row {
        u_in: lanes_of(u_in),
        u_out: lanes_of(u_out),
        c_in: lanes_of_i(c_in),
        c_out: lanes_of_i(c_out),
        t_in: lanes_of(t_in),
        t_out: lanes_of(t_out),
    };
    (
        row,
        [
            fold_epi32(c_in, _mm256_min_epi32),
            fold_epi32(c_out, _mm256_max_epi32),
        ],
        [fold_ps(lo, _mm256_min_ps), fold_ps(hi, _mm256_max_ps)],
    )
}

/// An [`Axis`] of each of eight segments: the lanes stepping up (`up`) and down (`down`) as
/// bits, the first pixel as a float.
struct AxisLanes {
    p0: F,
    inv_d: F,
    up: u32,
    down: u32,
    cell: F,
    depth_error: F,
}

/// [`Walker::segment`] of the rays through `block`'s pixels of `frame`, eight at once with
/// AVX2: the same operations in the same order, so the same segments, bit for bit. Lanes
/// outside the frame are `None`. In steps: the rays ([`pixel_rays_avx2`]), their span in the
/// volume box ([`box_span_avx2`]) and in the generation's frustum ([`frustum_span_avx2`]),
/// their projections' ends and inverse depths, the axes ([`axis_lanes_avx2`]), then each
/// lane's [`Segment`].
///
/// # Safety
/// The CPU must have AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn segments_avx2(
    walker: &Walker<'_>,
    frame: &ViewFrame,
    block: Block,
) -> [Option<Segment>; LANES] {
    use lanes8::lanes_of;
    use std::arch::x86_64::*;
    let (splat, add, sub, mul, div) = (
        _mm256_set1_ps,
        _mm256_add_ps,
        _mm256_sub_ps,
        _mm256_mul_ps,
        _mm256_div_ps,
    );
    let max = |a, b| _mm256_max_ps(a, b);
    // SAFETY: the helpers need AVX2 only, which this function's caller guarantees.
    let d = unsafe { pixel_rays_avx2(frame, block) };
    let o = frame.eye;
    // SAFETY: as above.
    let (t0, t1) = unsafe { box_span_avx2(&walker.vdi.meta().volume_box, o, d) };
    let g = &walker.gen;
    let e0 = g.to_eye(o);
    // SAFETY: as above.
    let ((t0, t1, valid), [x1, y1, z1]) = unsafe { frustum_span_avx2(g, e0, d, (t0, t1)) };
    let (x0, y0, z0) = (splat(e0.x), splat(e0.y), splat(e0.z));
    let (tx, ty) = (splat(g.tan_half_x), splat(g.tan_half_y));
    let r = walker.r as f32;
    let at = |f0, f1, t| add(f0, mul(f1, t));
    let px = |t| {
        mul(
            mul(
                add(div(at(x0, x1, t), mul(at(z0, z1, t), tx)), splat(1.0)),
                splat(0.5),
            ),
            splat(r),
        )
    };
    let py = |t| {
        mul(
            mul(
                sub(splat(1.0), div(at(y0, y1, t), mul(at(z0, z1, t), ty))),
                splat(0.5),
            ),
            splat(r),
        )
    };
    let (px0, py0, px1, py1) = (px(t0), py(t0), px(t1), py(t1));
    let inverse_depth = |z| div(splat(1.0), max(z, splat(NEAR_DEPTH)));
    let (w0, w1) = (inverse_depth(at(z0, z1, t0)), inverse_depth(at(z0, z1, t1)));
    let abs = |v| _mm256_andnot_ps(splat(-0.0), v);
    let dw = abs(sub(w1, w0));
    let rounding = mul(splat(1e-4), max(abs(w0), abs(w1)));
    // SAFETY: as above.
    let (ax, ay) = unsafe {
        (
            axis_lanes_avx2(px0, px1, dw, r),
            axis_lanes_avx2(py0, py1, dw, r),
        )
    };
    let [x1, y1, z1, t0, t1, px0, py0, px1, py1, w0, w1, rounding] =
        [x1, y1, z1, t0, t1, px0, py0, px1, py1, w0, w1, rounding].map(|v| lanes_of(v));
    let mut segs = [None; LANES];
    for (k, seg) in segs.iter_mut().enumerate() {
        let (i, j) = block.pixel(k);
        if valid & (1 << k) == 0 || i >= frame.width || j >= frame.height {
            continue;
        }
        let lane_axis = |a: &AxisLanes| {
            let step = if a.up & (1 << k) != 0 {
                1
            } else if a.down & (1 << k) != 0 {
                -1
            } else {
                0
            };
            Axis {
                p0: a.p0[k],
                inv_d: a.inv_d[k],
                step,
                ahead: i64::from(step > 0),
                cell: (a.cell[k] as i64).clamp(0, walker.r - 1),
                depth_error: a.depth_error[k],
            }
        };
        let lin = |f0: f32, f1: &F| Lin { f0, f1: f1[k] };
        *seg = Some(Segment {
            x: lin(e0.x, &x1),
            y: lin(e0.y, &y1),
            z: lin(e0.z, &z1),
            t0: t0[k],
            t1: t1[k],
            px0: px0[k],
            py0: py0[k],
            px1: px1[k],
            py1: py1[k],
            w0: w0[k],
            w1: w1[k],
            ax: lane_axis(&ax),
            ay: lane_axis(&ay),
            rounding: rounding[k],
        });
    }
    segs
}

/// The directions of `frame.pixel_ray` through `block`'s eight pixels (x, y, z lanes):
/// through each pixel's centre, normalised.
///
/// # Safety
/// The CPU must have AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn pixel_rays_avx2(frame: &ViewFrame, block: Block) -> [std::arch::x86_64::__m256; 3] {
    use std::arch::x86_64::*;
    const _: () = assert!(LANES == 8);
    let (splat, add, sub, mul, div) = (
        _mm256_set1_ps,
        _mm256_add_ps,
        _mm256_sub_ps,
        _mm256_mul_ps,
        _mm256_div_ps,
    );
    let lane = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
    let a = _mm256_and_si256(lane, _mm256_set1_epi32((1 << block.shift) - 1));
    let b = _mm256_srl_epi32(lane, _mm_cvtsi32_si128(block.shift as i32));
    let (i0, j0) = (block.i0, block.j0);
    let px = add(
        _mm256_cvtepi32_ps(_mm256_add_epi32(_mm256_set1_epi32(i0 as i32), a)),
        splat(0.5),
    );
    let py = add(
        _mm256_cvtepi32_ps(_mm256_add_epi32(_mm256_set1_epi32(j0 as i32), b)),
        splat(0.5),
    );
    let sx = mul(
        sub(
            div(mul(splat(2.0), px), splat(frame.width as f32)),
            splat(1.0),
        ),
        splat(frame.tan_half_x),
    );
    let sy = mul(
        sub(
            splat(1.0),
            div(mul(splat(2.0), py), splat(frame.height as f32)),
        ),
        splat(frame.tan_half_y),
    );
    let (f, rt, up) = (frame.forward, frame.right, frame.up);
    let comp = |f: f32, r: f32, u: f32| add(add(splat(f), mul(sx, splat(r))), mul(sy, splat(u)));
    let (dx, dy, dz) = (
        comp(f.x, rt.x, up.x),
        comp(f.y, rt.y, up.y),
        comp(f.z, rt.z, up.z),
    );
    let len = _mm256_sqrt_ps(add(add(mul(dx, dx), mul(dy, dy)), mul(dz, dz)));
    let len_recip = div(splat(1.0), len);
    [mul(dx, len_recip), mul(dy, len_recip), mul(dz, len_recip)]
}

/// `Aabb::intersect` of the eight rays from `o` along `d` with `aabb` (its reciprocal
/// directions, its `(1, 0)` for a ray outside a slab it runs along), the entry clamped to 0:
/// `(t0, t1)` per lane.
///
/// # Safety
/// The CPU must have AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn box_span_avx2(
    aabb: &crate::volume::Aabb,
    o: Vec3,
    [dx, dy, dz]: [std::arch::x86_64::__m256; 3],
) -> (std::arch::x86_64::__m256, std::arch::x86_64::__m256) {
    use std::arch::x86_64::*;
    let (splat, sub, mul, div) = (_mm256_set1_ps, _mm256_sub_ps, _mm256_mul_ps, _mm256_div_ps);
    // f32::max / f32::min for operands that are never NaN.
    let max = |a, b| _mm256_max_ps(a, b);
    let min = |a, b| _mm256_min_ps(a, b);
    let mut t_near = splat(f32::NEG_INFINITY);
    let mut t_far = splat(f32::INFINITY);
    let mut empty = _mm256_setzero_ps();
    for (d, o, lo, hi) in [
        (dx, o.x, aabb.min.x, aabb.max.x),
        (dy, o.y, aabb.min.y, aabb.max.y),
        (dz, o.z, aabb.min.z, aabb.max.z),
    ] {
        let inv = div(splat(1.0), d);
        let parallel =
            _mm256_cmp_ps::<_CMP_EQ_OQ>(_mm256_andnot_ps(splat(-0.0), inv), splat(f32::INFINITY));
        if o < lo || o > hi {
            empty = _mm256_or_ps(empty, parallel);
        }
        let t0 = mul(sub(splat(lo), splat(o)), inv);
        let t1 = mul(sub(splat(hi), splat(o)), inv);
        t_near = _mm256_blendv_ps(max(t_near, min(t0, t1)), t_near, parallel);
        t_far = _mm256_blendv_ps(min(t_far, max(t0, t1)), t_far, parallel);
    }
    let t0 = _mm256_blendv_ps(t_near, splat(1.0), empty);
    let t1 = _mm256_blendv_ps(t_far, splat(0.0), empty);
    (max(t0, splat(0.0)), t1)
}

/// The spans `(t0, t1)` of the eight rays from generation eye-space point `e0` along `d`
/// clipped to the generation frustum `g` (its four side planes and the near depth), the lanes
/// with a span left as bits, and the rays' eye-space directions (`x1, y1, z1`).
///
/// # Safety
/// The CPU must have AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn frustum_span_avx2(
    g: &ViewFrame,
    e0: Vec3,
    [dx, dy, dz]: [std::arch::x86_64::__m256; 3],
    (mut t0, mut t1): (std::arch::x86_64::__m256, std::arch::x86_64::__m256),
) -> (
    (std::arch::x86_64::__m256, std::arch::x86_64::__m256, u32),
    [std::arch::x86_64::__m256; 3],
) {
    use std::arch::x86_64::*;
    let (splat, add, sub, mul, div) = (
        _mm256_set1_ps,
        _mm256_add_ps,
        _mm256_sub_ps,
        _mm256_mul_ps,
        _mm256_div_ps,
    );
    let max = |a, b| _mm256_max_ps(a, b);
    let min = |a, b| _mm256_min_ps(a, b);
    let dot = |v: Vec3| {
        add(
            add(mul(dx, splat(v.x)), mul(dy, splat(v.y))),
            mul(dz, splat(v.z)),
        )
    };
    let (x1, y1, z1) = (dot(g.right), dot(g.up), dot(g.forward));
    let (x0, y0, z0) = (splat(e0.x), splat(e0.y), splat(e0.z));
    let (tx, ty) = (splat(g.tan_half_x), splat(g.tan_half_y));
    let planes = [
        (sub(mul(tx, z0), x0), sub(mul(tx, z1), x1)),
        (add(mul(tx, z0), x0), add(mul(tx, z1), x1)),
        (sub(mul(ty, z0), y0), sub(mul(ty, z1), y1)),
        (add(mul(ty, z0), y0), add(mul(ty, z1), y1)),
        (sub(z0, splat(NEAR_DEPTH)), z1),
    ];
    let mut outside = _mm256_setzero_ps();
    for (f0, f1) in planes {
        let t = div(_mm256_xor_ps(f0, splat(-0.0)), f1);
        let rising = _mm256_cmp_ps::<_CMP_GT_OQ>(f1, splat(0.0));
        let falling = _mm256_cmp_ps::<_CMP_LT_OQ>(f1, splat(0.0));
        t0 = _mm256_blendv_ps(t0, max(t0, t), rising);
        t1 = _mm256_blendv_ps(t1, min(t1, t), falling);
        let along = _mm256_andnot_ps(
            _mm256_or_ps(rising, falling),
            _mm256_cmp_ps::<_CMP_LT_OQ>(f0, splat(0.0)),
        );
        outside = _mm256_or_ps(outside, along);
    }
    // `t1.is_nan() || t0.is_nan() || t1 <= t0`: not `t0 < t1` (NaN compares false).
    let valid = _mm256_andnot_ps(outside, _mm256_cmp_ps::<_CMP_LT_OQ>(t0, t1));
    ((t0, t1, _mm256_movemask_ps(valid) as u32), [x1, y1, z1])
}

/// One axis of eight projections from `p0` to `p1` (pixels; `dw` their inverse depths'
/// difference, `r` the generation resolution): `u = (b − p0)/(p1 − p0)`'s step, the first
/// pixel and the depth error, as [`Walker::segment`]'s axis.
///
/// # Safety
/// The CPU must have AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn axis_lanes_avx2(
    p0: std::arch::x86_64::__m256,
    p1: std::arch::x86_64::__m256,
    dw: std::arch::x86_64::__m256,
    r: f32,
) -> AxisLanes {
    use lanes8::lanes_of;
    use std::arch::x86_64::*;
    let (splat, sub, mul, div) = (_mm256_set1_ps, _mm256_sub_ps, _mm256_mul_ps, _mm256_div_ps);
    let d = sub(p1, p0);
    let up = _mm256_cmp_ps::<_CMP_GT_OQ>(d, splat(DEGENERATE_PX));
    let down = _mm256_cmp_ps::<_CMP_LT_OQ>(d, splat(-DEGENERATE_PX));
    let steps = _mm256_or_ps(up, down);
    let cell = _mm256_blendv_ps(
        _mm256_xor_ps(_mm256_ceil_ps(_mm256_xor_ps(p0, splat(-0.0))), splat(-0.0)),
        sub(_mm256_ceil_ps(p0), splat(1.0)),
        down,
    );
    let inv_d = _mm256_and_ps(div(splat(1.0), d), steps);
    let abs_inv_d = _mm256_andnot_ps(splat(-0.0), inv_d);
    let error = mul(
        _mm256_min_ps(mul(splat(1e-5 * (r + 1.0)), abs_inv_d), splat(1.0)),
        dw,
    );
    AxisLanes {
        p0: lanes_of(p0),
        inv_d: lanes_of(inv_d),
        up: _mm256_movemask_ps(up) as u32,
        down: _mm256_movemask_ps(down) as u32,
        cell: lanes_of(cell),
        depth_error: lanes_of(error),
    }
}

/// Each passing lane's exact span of pixel `c` (walk-order index `kk`) of the current row, as
/// the single walk solves it: the later of the row's and the pixel's entries, the earlier of
/// their exits, never before what the lane has composited (`t_done`, advanced here). `pass`
/// holds the lanes' bits; the spans hold those of positive length.
#[inline(always)]
fn pixel_spans(l: &Lanes, row: &Row, c: i32, kk: i32, pass: u32, t_done: &mut F) -> Spans {
    let mut spans = Spans {
        ta: [0.0; LANES],
        tb: [0.0; LANES],
        lanes: 0,
    };
    for (k, done) in t_done.iter_mut().enumerate() {
        if pass & (1 << k) == 0 {
            continue;
        }
        let ta = if kk == row.c_in[k] {
            row.t_in[k]
        } else {
            l.cross(k, true, c + 1 - l.i_ahead[k]).max(row.t_in[k])
        };
        let tb = if kk == row.c_out[k] {
            row.t_out[k]
        } else {
            l.cross(k, true, c + l.i_ahead[k]).min(row.t_out[k])
        };
        let ta = ta.max(*done);
        let tb = tb.max(ta);
        *done = tb;
        if tb > ta {
            spans.ta[k] = ta;
            spans.tb[k] = tb;
            spans.lanes |= 1 << k;
        }
    }
    spans
}

/// [`pixel_spans`] with AVX2, eight lanes at once; the same operations (`f32::max` and
/// `f32::min` with their NaN rule), the same result.
///
/// # Safety
/// The CPU must have AVX2.
#[cfg(target_arch = "x86_64")]
#[inline]
#[target_feature(enable = "avx2")]
unsafe fn pixel_spans_avx2(
    l: &Lanes,
    row: &Row,
    c: i32,
    kk: i32,
    pass: u32,
    t_done: &mut F,
) -> Spans {
    use lanes8::*;
    use std::arch::x86_64::*;
    // `f32::max(a, b)` / `f32::min(a, b)`: the other operand where one is NaN.
    let max = |a, b| _mm256_blendv_ps(_mm256_max_ps(a, b), a, _mm256_cmp_ps::<_CMP_UNORD_Q>(b, b));
    let min = |a, b| _mm256_blendv_ps(_mm256_min_ps(a, b), a, _mm256_cmp_ps::<_CMP_UNORD_Q>(b, b));
    let passing = lanes_mask(pass);
    let cross_i = |b| cross_avx2(l, true, b);
    let cv = _mm256_set1_epi32(c);
    let ahead = load_i(&l.i_ahead);
    let entry = cross_i(_mm256_sub_epi32(
        _mm256_add_epi32(cv, _mm256_set1_epi32(1)),
        ahead,
    ));
    let exit = cross_i(_mm256_add_epi32(cv, ahead));
    let kv = _mm256_set1_epi32(kk);
    let (t_in, t_out) = (load(&row.t_in), load(&row.t_out));
    let first = _mm256_castsi256_ps(_mm256_cmpeq_epi32(kv, load_i(&row.c_in)));
    let last = _mm256_castsi256_ps(_mm256_cmpeq_epi32(kv, load_i(&row.c_out)));
    let ta = _mm256_blendv_ps(max(entry, t_in), t_in, first);
    let tb = _mm256_blendv_ps(min(exit, t_out), t_out, last);
    let done = load(t_done);
    let ta = max(ta, done);
    let tb = max(tb, ta);
    let active = _mm256_and_ps(passing, _mm256_cmp_ps::<_CMP_GT_OQ>(tb, ta));
    *t_done = lanes_of(_mm256_blendv_ps(done, tb, passing));
    Spans {
        ta: lanes_of(ta),
        tb: lanes_of(tb),
        lanes: _mm256_movemask_ps(active) as u32,
    }
}

/// [`Lanes::cross`] in eight lanes (boundaries `b`, of the inner axis where `inner`, else of
/// the outer one): [`super::cross`] step for step.
///
/// # Safety
/// The CPU must have AVX2.
#[cfg(target_arch = "x86_64")]
#[inline]
#[target_feature(enable = "avx2")]
unsafe fn cross_avx2(
    l: &Lanes,
    inner: bool,
    b: std::arch::x86_64::__m256i,
) -> std::arch::x86_64::__m256 {
    use lanes8::load;
    use std::arch::x86_64::*;
    let (x_axis, tan, c0, c1) = if inner {
        (l.inner_x, l.i_tan, load(&l.i0), load(&l.i1))
    } else {
        (!l.inner_x, l.o_tan, load(&l.o0), load(&l.o1))
    };
    let (z0, z1, t0, t1, r) = (load(&l.z0), load(&l.z1), load(&l.t0), load(&l.t1), l.r);
    let q = _mm256_div_ps(
        _mm256_mul_ps(_mm256_set1_ps(2.0), _mm256_cvtepi32_ps(b)),
        _mm256_set1_ps(r),
    );
    let one = _mm256_set1_ps(1.0);
    let s = _mm256_mul_ps(
        if x_axis {
            _mm256_sub_ps(q, one)
        } else {
            _mm256_sub_ps(one, q)
        },
        _mm256_set1_ps(tan),
    );
    let t = _mm256_div_ps(
        _mm256_sub_ps(_mm256_mul_ps(s, z0), c0),
        _mm256_sub_ps(c1, _mm256_mul_ps(s, z1)),
    );
    // `f32::clamp(t0, t1)`.
    let t = _mm256_blendv_ps(t, t0, _mm256_cmp_ps::<_CMP_LT_OQ>(t, t0));
    _mm256_blendv_ps(t, t1, _mm256_cmp_ps::<_CMP_GT_OQ>(t, t1))
}

/// `f` (a minimum or maximum: exact, in any order) over the eight lanes of `v`.
///
/// # Safety
/// The CPU must have AVX2.
#[cfg(target_arch = "x86_64")]
#[inline]
#[target_feature(enable = "avx2")]
unsafe fn fold_ps(
    v: std::arch::x86_64::__m256,
    f: unsafe fn(std::arch::x86_64::__m256, std::arch::x86_64::__m256) -> std::arch::x86_64::__m256,
) -> f32 {
    use std::arch::x86_64::*;
    let v = f(v, _mm256_permute2f128_ps::<1>(v, v));
    let v = f(v, _mm256_shuffle_ps::<0b01_00_11_10>(v, v));
    _mm256_cvtss_f32(f(v, _mm256_shuffle_ps::<0b10_11_00_01>(v, v)))
}

/// [`fold_ps`] of eight integers.
///
/// # Safety
/// The CPU must have AVX2.
#[cfg(target_arch = "x86_64")]
#[inline]
#[target_feature(enable = "avx2")]
unsafe fn fold_epi32(
    v: std::arch::x86_64::__m256i,
    f: unsafe fn(
        std::arch::x86_64::__m256i,
        std::arch::x86_64::__m256i,
    ) -> std::arch::x86_64::__m256i,
) -> i32 {
    use std::arch::x86_64::*;
    let v = f(v, _mm256_permute2x128_si256::<1>(v, v));
    let v = f(v, _mm256_shuffle_epi32::<0b01_00_11_10>(v));
    _mm256_cvtsi256_si32(f(v, _mm256_shuffle_epi32::<0b10_11_00_01>(v)))
}

/// Eight-lane AVX2 helpers of the packet kernels. Each needs a CPU with AVX2 (`unsafe`).
#[cfg(target_arch = "x86_64")]
mod lanes8 {
    use super::{F, I};
    use std::arch::x86_64::*;

    /// The eight lanes of `a` (unaligned load of eight 4-byte values).
    #[inline]
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn load(a: &F) -> __m256 {
        _mm256_loadu_ps(a.as_ptr())
    }

    /// The eight lanes of `a`.
    #[inline]
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn load_i(a: &I) -> __m256i {
        _mm256_loadu_si256(a.as_ptr().cast())
    }

    /// `v`'s eight lanes as an array (unaligned store of eight 4-byte values).
    #[inline]
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn lanes_of(v: __m256) -> F {
        let mut a = [0.0; 8];
        _mm256_storeu_ps(a.as_mut_ptr(), v);
        a
    }

    /// `v`'s eight lanes as an array.
    #[inline]
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn lanes_of_i(v: __m256i) -> I {
        let mut a = [0; 8];
        _mm256_storeu_si256(a.as_mut_ptr().cast(), v);
        a
    }

    /// All bits set in the lanes whose bit is set in `bits`.
    #[inline]
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn lanes_mask(bits: u32) -> __m256 {
        let lane_bits = _mm256_setr_epi32(1, 2, 4, 8, 16, 32, 64, 128);
        _mm256_castsi256_ps(_mm256_cmpeq_epi32(
            _mm256_and_si256(_mm256_set1_epi32(bits as i32), lane_bits),
            lane_bits,
        ))
    }

    /// [`super::greater`] per lane: `a` where `a > b`, else `b`.
    #[inline]
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn greater(a: __m256, b: __m256) -> __m256 {
        _mm256_blendv_ps(b, a, _mm256_cmp_ps::<_CMP_GT_OQ>(a, b))
    }

    /// [`super::lesser`] per lane: `a` where `a < b`, else `b`.
    #[inline]
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn lesser(a: __m256, b: __m256) -> __m256 {
        _mm256_blendv_ps(b, a, _mm256_cmp_ps::<_CMP_LT_OQ>(a, b))
    }

    /// [`super::Segment::w_at`] per lane: `w1` where `u ≥ 1`, else `w0 + dw·u`.
    #[inline]
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn w_at(w0: __m256, w1: __m256, dw: __m256, u: __m256) -> __m256 {
        let w = _mm256_add_ps(w0, _mm256_mul_ps(dw, u));
        _mm256_blendv_ps(w, w1, _mm256_cmp_ps::<_CMP_GE_OQ>(u, _mm256_set1_ps(1.0)))
    }
}

#[cfg(test)]
mod tests {
    use super::super::tests::{blobs, views};
    use super::*;
    use crate::raycast::Avx2;

    /// Packets give the single walk's image to rounding (the same crossings, taken as a
    /// maximum of entries and a minimum of exits), in every shape, from every test view (those
    /// from inside the volume include packets whose rays step both ways, walked one by one),
    /// on frames whose sides are not multiples of the packets' and on frames smaller than one;
    /// and the shapes chosen along the epipolar lines ([`Walker::render`]) likewise.
    #[test]
    fn packets_match_the_single_walk() {
        let (vdi, cam) = blobs();
        let walker = Walker::new(&vdi);
        let mut seen = 0;
        for (w, h) in [(61, 37), (1, 1), (7, 3)] {
            for view in views(cam) {
                let f = view.frame(w, h);
                let mut single = Image::new(w, h);
                for j in 0..h {
                    for i in 0..w {
                        single.pixels_mut()[(i + w * j) as usize] =
                            walker.integrate(&f.pixel_ray(i, j), 0.99);
                    }
                }
                seen += single.pixels().iter().filter(|c| **c != [0.0; 3]).count();
                let shaped = [(8, 1), (4, 2), (2, 4), (1, 8)].map(|shape| {
                    crate::dvr::render_blocks(
                        &f,
                        |_, _| shape,
                        |i0, j0, (bw, _), out| {
                            walker.integrate_packet(&f, Block::new(i0, j0, bw), 0.99, out)
                        },
                    )
                });
                let chosen = walker.render(&view, w, h, 0.99);
                for packed in shaped.iter().chain([&chosen]) {
                    for (k, (c, p)) in single.pixels().iter().zip(packed.pixels()).enumerate() {
                        for ch in 0..3 {
                            assert!(
                                (c[ch] - p[ch]).abs() <= 1e-4,
                                "pixel {k} of {w}x{h} from {view:?}: single {c:?}, packet {p:?}"
                            );
                        }
                    }
                    let q = crate::metrics::psnr(packed, &single).unwrap_or(f64::INFINITY);
                    assert!(q >= 100.0, "PSNR {q} dB");
                }
            }
        }
        assert!(seen > 400, "the blobs must be seen ({seen} pixels)");
    }

    /// Whether this CPU has AVX2; says so when it does not (the AVX2 tests then have nothing
    /// to compare: only the portable path runs here).
    fn has_avx2() -> bool {
        let has = Avx2::detect().is_some();
        if !has {
            eprintln!("this CPU has no AVX2: only the portable packets run here");
        }
        has
    }

    /// The AVX2 set-up gives [`Walker::segment`]'s segments bit for bit, on every packet of
    /// every test view (frame sides not multiples of the packet's).
    #[test]
    fn avx2_segments_equal_scalar_segments() {
        if !has_avx2() {
            return;
        }
        let (vdi, cam) = blobs();
        let walker = Walker::new(&vdi);
        let bits = |s: &Option<Segment>| -> Option<Vec<u64>> {
            s.map(|s| {
                let f = [
                    s.x.f0, s.x.f1, s.y.f0, s.y.f1, s.z.f0, s.z.f1, s.t0, s.t1, s.px0, s.py0,
                    s.px1, s.py1, s.w0, s.w1, s.rounding,
                ];
                let mut v: Vec<u64> = f.iter().map(|x| u64::from(x.to_bits())).collect();
                for a in [s.ax, s.ay] {
                    v.extend(
                        [a.p0.to_bits(), a.inv_d.to_bits(), a.depth_error.to_bits()].map(u64::from),
                    );
                    v.extend([a.step, a.ahead, a.cell].map(|i| i as u64));
                }
                v
            })
        };
        let (w, h) = (61, 37);
        let mut some = 0;
        for view in views(cam) {
            let f = view.frame(w, h);
            for (j0, i0, bw) in (0..h).flat_map(|j| (0..w).map(move |i| (j, i, 1 << (i % 4)))) {
                {
                    let block = Block::new(i0, j0, bw);
                    // SAFETY: AVX2 was detected above.
                    let simd = unsafe { segments_avx2(&walker, &f, block) };
                    let scalar = walker.segments(&f, block);
                    for (a, b) in simd.iter().zip(&scalar) {
                        assert_eq!(bits(a), bits(b), "packet ({i0}, {j0}) of {view:?}");
                        some += usize::from(a.is_some());
                    }
                }
            }
        }
        assert!(some > 5000, "{some} segments");
    }

    /// The AVX2 row spans and lane tests give the portable ones' results: the images are
    /// bit-identical.
    #[test]
    fn avx2_packets_equal_portable_packets() {
        if !has_avx2() {
            return;
        }
        let (vdi, cam) = blobs();
        let simd = Walker::new(&vdi);
        let portable = Walker {
            avx2: None,
            ..Walker::new(&vdi)
        };
        for view in views(cam) {
            let (a, b) = (
                simd.render(&view, 61, 37, 0.99),
                portable.render(&view, 61, 37, 0.99),
            );
            let bits = |i: &Image| -> Vec<u32> {
                i.pixels().iter().flatten().map(|v| v.to_bits()).collect()
            };
            assert_eq!(bits(&a), bits(&b), "view {view:?}");
        }
    }
}
