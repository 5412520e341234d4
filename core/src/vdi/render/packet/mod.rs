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

mod composite;
#[cfg(target_arch = "x86_64")]
mod lanes8;
mod occupancy;
mod rows;
mod setup;
mod spans;

use composite::*;
use occupancy::*;
use rows::*;
use setup::*;
use spans::*;

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
