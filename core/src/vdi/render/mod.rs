//! VDI rendering `I(M, P_I) → O` from any camera (Sec. 3.2, Fig. 2b; docs/conventions.md, "Rendering a
//! VDI from a new camera").
//!
//! A ray of the new camera is clipped to the volume box and to the generation camera's
//! frustum. Its projection into the generation image is a line segment, walked pixel by pixel
//! with a 2D DDA (Amanatides–Woo) in the segment's own parameter `u`, so pixels come in ray
//! order and a step costs no division; inverse depth is affine in `u` (perspective-correct
//! interpolation), so each pixel's depth span is known without solving for the ray (the depth
//! bins are uniform in inverse depth, so a crossing's bin is a multiply-add away). 8×8 tiles
//! whose depth range that span misses are leapt (an empty one with the square of empty tiles
//! around it), and pixels whose 64-bin depth-occupancy mask misses it are passed untouched.
//! Where a pixel's list is searched, the exact ray parameters of its crossings are solved on
//! the projective line, the supersegments overlapping the span found by a scan (short
//! lists) or a binary search and composited front to back with `α' = 1 − (1 − â)^ℓ`, `ℓ`
//! the world length of the ray inside the frustum. Views from behind traverse the lists
//! backwards; rays perpendicular to the generation view direction (constant depth) take the
//! one supersegment that contains them.
//!
//! [`Walker::render`] walks the rays in packets of eight along the new image's epipolar
//! lines (`packet`): the generation pixels they share are visited once, and the per-ray work
//! (spans, occupancy tests, compositing) runs eight lanes wide. The single-ray walk below is
//! what each lane does, and the reference the packets are tested against.

mod composite;
mod packet;
mod tables;

use composite::*;
pub(crate) use tables::WalkTables;
use tables::*;
pub use tables::{tile_depth_ranges, SKIP_TILE};

use super::{Supersegment, Vdi};
use crate::camera::{Camera, Ray, ViewFrame};
use crate::cancel::{Cancel, Cancelled};
use crate::dvr::render_blocks_until;
use crate::fastmath;
use crate::image::Image;
use crate::raycast::Avx2;
use glam::Vec3;

/// Renders `vdi` seen by `camera` at `width × height`, stopping each ray once its accumulated
/// opacity reaches `termination` (in (0, 1]); background black. For several views of one VDI,
/// build a [`Walker`] once and call [`Walker::render`].
pub fn render(vdi: &Vdi, camera: &Camera, width: u32, height: u32, termination: f32) -> Image {
    Walker::new(vdi).render(camera, width, height, termination)
}

/// A projection shorter than this (generation pixels) along an axis does not step along it
/// (a point where both are: the ray passes through the generation eye, as every ray of the
/// generation view does).
const DEGENERATE_PX: f32 = 1e-3;

/// A VDI prepared for rendering from many cameras: its generation frame and its walk tables
/// (built on the VDI's first render and kept with it).
pub struct Walker<'a> {
    vdi: &'a Vdi,
    gen: ViewFrame,
    r: i64,
    tables: &'a WalkTables,
    /// Proof of AVX2, where the CPU has it: packets' lanes are then tested eight at once.
    avx2: Option<Avx2>,
}

/// A linear function `f0 + f1·t` of the ray parameter.
#[derive(Clone, Copy)]
struct Lin {
    f0: f32,
    f1: f32,
}

impl Lin {
    #[inline]
    fn at(self, t: f32) -> f32 {
        self.f0 + self.f1 * t
    }

    /// `a·self + sign·other`, coefficient by coefficient.
    #[inline]
    fn scaled_plus(self, a: f32, sign: f32, other: Lin) -> Lin {
        Lin {
            f0: a * self.f0 + sign * other.f0,
            f1: a * self.f1 + sign * other.f1,
        }
    }
}

/// The part `t0 … t1` of a ray with generation eye coordinates `x, y, z` (linear in t)
/// inside the generation frustum `|x| ≤ tx·z`, `|y| ≤ ty·z`, `z ≥ NEAR_DEPTH`; `None` where
/// nothing is left (or a bound is NaN).
fn frustum_span(
    [x, y, z]: [Lin; 3],
    (tx, ty): (f32, f32),
    (mut t0, mut t1): (f32, f32),
) -> Option<(f32, f32)> {
    let planes = [
        z.scaled_plus(tx, -1.0, x),
        z.scaled_plus(tx, 1.0, x),
        z.scaled_plus(ty, -1.0, y),
        z.scaled_plus(ty, 1.0, y),
        Lin {
            f0: z.f0 - NEAR_DEPTH,
            f1: z.f1,
        },
    ];
    for p in planes {
        if p.f1 > 0.0 {
            t0 = t0.max(-p.f0 / p.f1);
        } else if p.f1 < 0.0 {
            t1 = t1.min(-p.f0 / p.f1);
        } else if p.f0 < 0.0 {
            return None;
        }
    }
    if t1.is_nan() || t0.is_nan() || t1 <= t0 {
        return None;
    }
    Some((t0, t1))
}

impl<'a> Walker<'a> {
    /// Prepares `vdi` (its tables: one pass over its pixels and supersegments the first time).
    pub fn new(vdi: &'a Vdi) -> Self {
        let r = vdi.resolution();
        Self {
            vdi,
            gen: vdi.meta().camera.frame(r, r),
            r: i64::from(r),
            tables: vdi.walk_tables(),
            avx2: Avx2::detect(),
        }
    }

    /// Renders the VDI seen by `camera` at `width × height`, stopping rays at accumulated
    /// opacity `termination` (in (0, 1]); background black.
    pub fn render(&self, camera: &Camera, width: u32, height: u32, termination: f32) -> Image {
        self.render_until(camera, width, height, termination, None)
            .unwrap_or_else(|_| Image::new(width, height))
    }

    /// [`Walker::render`], stopped between tiles when `cancel` is set.
    ///
    /// # Errors
    /// [`Cancelled`] when it was.
    pub fn render_until(
        &self,
        camera: &Camera,
        width: u32,
        height: u32,
        termination: f32,
        cancel: Option<&Cancel>,
    ) -> Result<Image, Cancelled> {
        let frame = camera.frame(width, height);
        // The generation eye seen from the new camera: where the epipolar lines meet.
        let gen_eye = frame.to_eye(self.gen.eye);
        render_blocks_until(
            &frame,
            |x0, y0| packet::shape(&frame, gen_eye, x0, y0),
            |i0, j0, (w, _), out| {
                let block = packet::Block::new(i0, j0, w);
                self.integrate_packet(&frame, block, termination, out)
            },
            cancel,
        )
    }

    /// Composited colour along `ray`, walked on its own: the reference the packets are
    /// tested against.
    #[cfg(test)]
    fn integrate(&self, ray: &Ray, termination: f32) -> [f32; 3] {
        let mut acc = Accum::new(termination);
        self.walk(ray, &mut acc);
        acc.ray.finish().0
    }

    /// The part of `ray` the walk covers: clipped to the volume box and to the generation
    /// frustum and projected into the generation image; `None` where nothing is left.
    fn segment(&self, ray: &Ray) -> Option<Segment> {
        let g = &self.gen;
        let (t0, t1) = self
            .vdi
            .meta()
            .volume_box
            .intersect(ray.origin, ray.dir.recip());
        let t0 = t0.max(0.0);
        // Eye-space coordinates of the ray in the generation camera, linear in t.
        let e0 = g.to_eye(ray.origin);
        let e1 = Vec3::new(
            ray.dir.dot(g.right),
            ray.dir.dot(g.up),
            ray.dir.dot(g.forward),
        );
        let x = Lin { f0: e0.x, f1: e1.x };
        let y = Lin { f0: e0.y, f1: e1.y };
        let z = Lin { f0: e0.z, f1: e1.z };
        let (tx, ty) = (g.tan_half_x, g.tan_half_y);
        let (t0, t1) = frustum_span([x, y, z], (tx, ty), (t0, t1))?;
        let r = self.r as f32;
        // Pixel coordinates: px = (x/(z·tx) + 1)·r/2, py = (1 − y/(z·ty))·r/2.
        let px = |t: f32| (x.at(t) / (z.at(t) * tx) + 1.0) * 0.5 * r;
        let py = |t: f32| (1.0 - y.at(t) / (z.at(t) * ty)) * 0.5 * r;
        let (px0, py0, px1, py1) = (px(t0), py(t0), px(t1), py(t1));
        // The projection is walked as a straight segment `P(u) = P0 + u·(P1 − P0)`, u in
        // [0, 1], pixel boundaries met at `u = (b − p0)/(p1 − p0)`: no division per pixel.
        // Inverse depth is affine in u (perspective-correct interpolation), which gives the
        // depth bins at each crossing for the occupancy test; the exact ray parameter `t` of
        // a crossing (its own division) is solved only where a list is composited.
        let (w0, w1) = (inverse_depth(z.at(t0)), inverse_depth(z.at(t1)));
        let dw = w1 - w0;
        let axis = |p0: f32, p1: f32| Axis::new(p0, p1, self.r, dw);
        Some(Segment {
            x,
            y,
            z,
            t0,
            t1,
            px0,
            py0,
            px1,
            py1,
            w0,
            w1,
            ax: axis(px0, px1),
            ay: axis(py0, py1),
            rounding: 1e-4 * w0.abs().max(w1.abs()),
        })
    }

    #[cfg(test)]
    fn walk(&self, ray: &Ray, acc: &mut Accum) {
        if let Some(seg) = self.segment(ray) {
            self.walk_segment(&seg, acc);
        }
    }

    /// Walks `seg` pixel by pixel (the 2-D DDA), compositing into `acc`: a tile whose depths
    /// the ray's miss is left in one jump ([`Self::enter_tile`]), a pixel whose depth bins
    /// miss the ray's is passed, the others are composited over the ray's exact span of them
    /// ([`Self::walk_pixel`]), until the ray leaves the image or its end or `acc` is opaque.
    fn walk_segment(&self, seg: &Segment, acc: &mut Accum) {
        let mut walk = SegmentWalk::new(seg, self.tables.bins);
        for _ in 0..(2 * self.r + 4) {
            // Cells are never negative here (the walk stops when one leaves the image), so
            // a shift is the division.
            let (ix, iy) = (walk.ax.cell, walk.ay.cell);
            let tile = (ix >> SKIP_SHIFT) + self.tables.tiles_x * (iy >> SKIP_SHIFT);
            if tile != walk.walking {
                match self.enter_tile(&mut walk, tile) {
                    TileEntry::Walk => walk.walking = tile,
                    TileEntry::Jumped => continue,
                    TileEntry::Left => return,
                }
            }
            if !self.walk_pixel(&mut walk, acc) {
                return;
            }
        }
    }

    /// Entering tile `tile` (its flat index) at `walk`'s pixel: where does the ray leave it,
    /// and does its depth over the tile meet the tile's supersegments? Where it does, its
    /// pixels are walked; else the walk jumps past the tile and the square of empty tiles
    /// around it ([`WalkTables::tile_reach`]) to the pixel that holds the ray there, unless
    /// that leaves the image or passes the ray's end.
    #[inline]
    fn enter_tile(&self, walk: &mut SegmentWalk, tile: i64) -> TileEntry {
        let seg = walk.seg;
        let (ax, ay) = (&mut walk.ax, &mut walk.ay);
        let (ix, iy) = (ax.cell, ay.cell);
        let (x0t, y0t) = (ix & !(SKIP_TILE - 1), iy & !(SKIP_TILE - 1));
        let beyond = (i64::from(self.tables.tile_reach[tile as usize]) - 1).max(0) * SKIP_TILE;
        let (xs, ys) = (
            [x0t - beyond, x0t + SKIP_TILE + beyond],
            [y0t - beyond, y0t + SKIP_TILE + beyond],
        );
        let (ex, ey) = (ax.exit(xs), ay.exit(ys));
        let u_exit = greater(lesser(lesser(ex, ey), 1.0), walk.u);
        let w_exit = seg.w_at(u_exit);
        let exit_error = if ex <= ey {
            ax.depth_error
        } else {
            ay.depth_error
        };
        let margin = seg.rounding + walk.enter_error + exit_error;
        let [w_min, w_max] = self.tables.tile_w[tile as usize];
        if !(walk.w_u.min(w_exit) > w_max + margin || walk.w_u.max(w_exit) < w_min - margin) {
            return TileEntry::Walk;
        }
        // Nothing to meet here. A jump that lands outside the image ends the ray: it has
        // left the image, for good.
        if u_exit >= 1.0 {
            return TileEntry::Left;
        }
        if ex <= ey {
            let b = if ax.step > 0 { xs[1] } else { xs[0] };
            ax.cell = b - 1 + ax.ahead;
            ay.cell = ay.cell_at(u_exit, seg.py1 - seg.py0, ys);
            walk.enter = Crossing::X(b);
            walk.enter_error = ax.depth_error;
        } else {
            let b = if ay.step > 0 { ys[1] } else { ys[0] };
            ay.cell = b - 1 + ay.ahead;
            ax.cell = ax.cell_at(u_exit, seg.px1 - seg.px0, xs);
            walk.enter = Crossing::Y(b);
            walk.enter_error = ay.depth_error;
        }
        if !(0..self.r).contains(&ax.cell) || !(0..self.r).contains(&ay.cell) {
            return TileEntry::Left;
        }
        walk.u = u_exit;
        walk.w_u = w_exit;
        walk.enter_bins = self
            .tables
            .bins
            .around(walk.w_u, seg.rounding + walk.enter_error);
        walk.entered_solved = false;
        (walk.ux, walk.uy) = (walk.ax.next(), walk.ay.next());
        TileEntry::Jumped
    }

    /// `walk`'s pixel: composited into `acc` over the ray's exact span of it where its
    /// depth bins meet those between the ray's crossings, then the walk steps to the next
    /// pixel. False when the ray is done (`acc` opaque, its end reached, the image left).
    #[inline]
    fn walk_pixel(&self, walk: &mut SegmentWalk, acc: &mut Accum) -> bool {
        let seg = walk.seg;
        let (ix, iy) = (walk.ax.cell, walk.ay.cell);
        let (ux, uy) = (walk.ux, walk.uy);
        // The crossings' u are never NaN (`Axis::at`: finite, or +∞ on an axis that does
        // not step), so comparisons do for `f32::min`/`max`.
        let u_next = greater(lesser(lesser(ux, uy), 1.0), walk.u);
        let w_next = seg.w_at(u_next);
        let p = (ix + self.r * iy) as usize;
        let exit_error = if ux <= uy {
            walk.ax.depth_error
        } else {
            walk.ay.depth_error
        };
        // The pixel's depth span lies between its two crossings' bins: a list whose bins
        // miss them is passed untouched.
        let exit_bins = self.tables.bins.around(w_next, seg.rounding + exit_error);
        if self.tables.pixel_bins[p] & between(walk.enter_bins, exit_bins) != 0 {
            let exit = if u_next >= 1.0 {
                seg.t1
            } else if ux <= uy {
                self.cross(seg, true, ix + walk.ax.ahead)
            } else {
                self.cross(seg, false, iy + walk.ay.ahead)
            };
            // Never before what was composited: where two crossings are nearly simultaneous
            // their order in u and in t can differ by rounding. A pixel that follows one
            // composited up to the crossing between them has `t_done` at or past that
            // crossing's `t`, without the crossing's division.
            let ta = if walk.entered_solved {
                walk.t_done
            } else {
                let entry = match walk.enter {
                    Crossing::Start => seg.t0,
                    Crossing::X(b) => self.cross(seg, true, b),
                    Crossing::Y(b) => self.cross(seg, false, b),
                };
                entry.max(walk.t_done)
            };
            let tb = exit.max(ta);
            walk.t_done = tb;
            walk.entered_solved = true;
            let offsets = self.vdi.offsets();
            let range = offsets[p] as usize..offsets[p + 1] as usize;
            if tb > ta
                && composite_span(
                    &self.vdi.supersegments()[range.clone()],
                    &self.tables.keys[range],
                    seg.z,
                    ta,
                    tb,
                    acc,
                )
            {
                return false;
            }
        } else {
            walk.entered_solved = false;
        }
        if u_next >= 1.0 {
            return false;
        }
        // Only the axis stepped can have left the image.
        walk.enter = if ux <= uy {
            Crossing::X(ix + walk.ax.ahead)
        } else {
            Crossing::Y(iy + walk.ay.ahead)
        };
        let (axis, u_axis) = if ux <= uy {
            (&mut walk.ax, &mut walk.ux)
        } else {
            (&mut walk.ay, &mut walk.uy)
        };
        walk.enter_error = axis.depth_error;
        axis.cell += axis.step;
        *u_axis = axis.next();
        if !(0..self.r).contains(&axis.cell) {
            return false;
        }
        walk.u = u_next;
        walk.w_u = w_next;
        walk.enter_bins = exit_bins;
        true
    }
}

/// What entering a tile does to a walk ([`Walker::enter_tile`]).
enum TileEntry {
    /// The ray's depths meet the tile's: its pixels are walked.
    Walk,
    /// They do not: the walk jumped to the pixel after the tile (and the empty ones around it).
    Jumped,
    /// The jump left the image or passed the ray's end: the walk is over.
    Left,
}

/// Where a walk along one segment's projection is ([`Walker::walk_segment`]): its axes'
/// pixels and next crossings, the `u` and inverse depth where it entered the current pixel,
/// how it entered it, and how far it has composited.
struct SegmentWalk<'s> {
    seg: &'s Segment,
    ax: Axis,
    ay: Axis,
    /// `u` of the next crossing along x and along y.
    ux: f32,
    uy: f32,
    /// `u` and inverse depth where the current pixel was entered.
    u: f32,
    w_u: f32,
    /// How far the ray has composited.
    t_done: f32,
    /// Whether the current pixel follows one composited up to the crossing between them
    /// (`t_done` is then at or past that crossing's `t`).
    entered_solved: bool,
    /// The crossing the current pixel was entered by, its depth error and the bins it may
    /// lie in.
    enter: Crossing,
    enter_error: f32,
    enter_bins: [u32; 2],
    /// The tile whose pixels are being walked (its depths meet the ray's); −1 before any.
    walking: i64,
}

impl<'s> SegmentWalk<'s> {
    /// At `seg`'s start, depth bins `bins` (the walker's).
    fn new(seg: &'s Segment, bins: DepthBins) -> Self {
        let (ax, ay) = (seg.ax, seg.ay);
        Self {
            seg,
            ax,
            ay,
            ux: ax.next(),
            uy: ay.next(),
            u: 0.0,
            w_u: seg.w0,
            t_done: seg.t0,
            entered_solved: false,
            enter: Crossing::Start,
            enter_error: 0.0,
            enter_bins: bins.around(seg.w0, seg.rounding),
            walking: -1,
        }
    }
}

impl Walker<'_> {
    /// Ray parameter, within `[seg.t0, seg.t1]`, where `seg`'s projection reaches pixel
    /// boundary `b` of x (`x_axis`) or y ([`cross`]).
    #[inline]
    fn cross(&self, seg: &Segment, x_axis: bool, b: i64) -> f32 {
        let (tan, coord) = if x_axis {
            (self.gen.tan_half_x, seg.x)
        } else {
            (self.gen.tan_half_y, seg.y)
        };
        let r = self.r as f32;
        cross(x_axis, b as f32, r, tan, coord, seg.z, [seg.t0, seg.t1])
    }
}

/// The smaller of `a` and `b`, for operands that are never NaN (one comparison, where
/// `f32::min` also handles NaN).
#[inline]
fn lesser(a: f32, b: f32) -> f32 {
    if a < b {
        a
    } else {
        b
    }
}

/// The larger of `a` and `b`, for operands that are never NaN.
#[inline]
fn greater(a: f32, b: f32) -> f32 {
    if a > b {
        a
    } else {
        b
    }
}

/// A ray of the new camera as the walk sees it ([`Walker::segment`]): its generation
/// eye-space coordinates, linear in the ray parameter `t`, over `[t0, t1]` (clipped to the
/// volume box and the generation frustum), and its projection into the generation image,
/// `P(u) = P0 + u·(P1 − P0)` for `u` in [0, 1], with the inverse depth at both ends.
#[derive(Clone, Copy)]
struct Segment {
    x: Lin,
    y: Lin,
    z: Lin,
    t0: f32,
    t1: f32,
    /// The projection's ends, generation pixels.
    px0: f32,
    py0: f32,
    px1: f32,
    py1: f32,
    /// Inverse depth at `t0` and `t1`.
    w0: f32,
    w1: f32,
    ax: Axis,
    ay: Axis,
    /// The relative rounding of inverse depths computed in `u` against those of `t` (the
    /// occupancy test's margin, with the axes' [`Axis::depth_error`]).
    rounding: f32,
}

impl Segment {
    /// Inverse depth at `u` (perspective-correct: affine in `u`). With
    /// [`Segment::rounding`] and the axes' [`Axis::depth_error`] as margins, the depth bins
    /// of a crossing found in `u` cover those of its exact `t` (the occupancy test must not
    /// skip a list the exact span meets).
    #[inline]
    fn w_at(&self, u: f32) -> f32 {
        if u >= 1.0 {
            self.w1
        } else {
            self.w0 + (self.w1 - self.w0) * u
        }
    }
}

/// The ray parameter, within `[t0, t1]`, where a ray whose generation eye-space coordinate
/// along an axis is `coord(t)` and whose depth is `z(t)` crosses pixel boundary `b` of that
/// axis (x when `x_axis`, else y; `tan` of the half field of view along it, `r` pixels): the
/// plane `coord = s·z` through the generation eye, `s = (2b/r − 1)·tan` for x and
/// `(1 − 2b/r)·tan` for y (rows from the top).
#[inline(always)]
fn cross(x_axis: bool, b: f32, r: f32, tan: f32, coord: Lin, z: Lin, [t0, t1]: [f32; 2]) -> f32 {
    let q = 2.0 * b / r;
    let s = if x_axis {
        (q - 1.0) * tan
    } else {
        (1.0 - q) * tan
    };
    ((s * z.f0 - coord.f0) / (coord.f1 - s * z.f1)).clamp(t0, t1)
}

/// Where a pixel of the walk was entered: the ray's start, or a pixel boundary (column `b`
/// for `X`, row `b` for `Y`) whose ray parameter is solved only if the pixel is composited.
#[derive(Clone, Copy)]
enum Crossing {
    Start,
    X(i64),
    Y(i64),
}

/// One axis of the walk over the projected segment: pixel boundaries along it are met at
/// `u = (b − p0) / (p1 − p0)`.
#[derive(Clone, Copy)]
struct Axis {
    /// Where the segment starts, pixels.
    p0: f32,
    /// `1 / (p1 − p0)`; 0 when the axis does not step.
    inv_d: f32,
    /// −1, 0 or +1.
    step: i64,
    /// 1 when stepping up (the boundary ahead of cell `c` is `c + 1`), else 0.
    ahead: i64,
    /// The current pixel along this axis.
    cell: i64,
    /// How far, in generation depth, a crossing of this axis found in u may be from the
    /// exact one: the rounding of the pixel coordinates over the axis' extent, which a
    /// nearly degenerate projection (a fraction of a pixel) makes large.
    depth_error: f32,
}

impl Axis {
    /// The axis of a projection from `p0` to `p1` (pixels) in an image of `r` pixels a side,
    /// over a depth range `dw` (inverse depth).
    fn new(p0: f32, p1: f32, r: i64, dw: f32) -> Self {
        let d = p1 - p0;
        let step = if d > DEGENERATE_PX {
            1
        } else if d < -DEGENERATE_PX {
            -1
        } else {
            0
        };
        let cell = if step < 0 {
            fastmath::ceil(p0) as i64 - 1
        } else {
            -fastmath::ceil(-p0) as i64
        };
        let inv_d = if step == 0 { 0.0 } else { 1.0 / d };
        Axis {
            p0,
            inv_d,
            step,
            ahead: i64::from(step > 0),
            cell: cell.clamp(0, r - 1),
            // The pixel coordinates' rounding (a few ulp of r; 1e-5·(r + 1) taken) over the
            // axis' extent, times the depth range.
            depth_error: (1e-5 * (r as f32 + 1.0) * inv_d.abs()).min(1.0) * dw.abs(),
        }
    }

    /// `u` where the segment reaches boundary `b`.
    #[inline]
    fn at(&self, b: i64) -> f32 {
        if self.step == 0 {
            f32::INFINITY
        } else {
            (b as f32 - self.p0) * self.inv_d
        }
    }

    /// `u` where the segment leaves the current pixel.
    #[inline]
    fn next(&self) -> f32 {
        self.at(self.cell + self.ahead)
    }

    /// `u` where the segment leaves the pixel range `[lo, hi)`.
    #[inline]
    fn exit(&self, [lo, hi]: [i64; 2]) -> f32 {
        self.at(if self.step > 0 { hi } else { lo })
    }

    /// The pixel holding the segment at `u` (`d = p1 − p0`), kept inside the pixel range
    /// `[lo, hi)` (which the caller knows it is in, up to rounding).
    #[inline]
    fn cell_at(&self, u: f32, d: f32, [lo, hi]: [i64; 2]) -> i64 {
        let p = self.p0 + d * u;
        let c = if self.step < 0 {
            fastmath::ceil(p) as i64 - 1
        } else {
            -fastmath::ceil(-p) as i64
        };
        c.clamp(lo, hi - 1)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::raycast::{RaycastParams, Raycaster};
    use crate::tf::TransferFunction;
    use crate::vdi::{generate::generate, VdiParams};
    use crate::volume::Volume;

    /// A VDI of two blobs at different depths with empty space around and between them
    /// (r = 96), and the camera it was generated from.
    pub(super) fn blobs() -> (Vdi, Camera) {
        let v = Volume::from_fn([48, 40, 44], |x, y, z| {
            let blob = |c: [f32; 3], r: f32| {
                let d = ((x as f32 - c[0]).powi(2)
                    + (y as f32 - c[1]).powi(2)
                    + (z as f32 - c[2]).powi(2))
                .sqrt();
                (r - d).max(0.0)
            };
            blob([14.0, 20.0, 10.0], 7.0) + blob([33.0, 18.0, 32.0], 9.0)
        })
        .unwrap();
        let tf = TransferFunction::default_for_range(0.0, 9.0);
        let rc = Raycaster::new(&v, &tf, RaycastParams::default()).unwrap();
        let cam = Camera::default_for_box(&v.world_box());
        let vdi = generate(
            &rc,
            &cam,
            VdiParams {
                resolution: 96,
                gamma: 0.01,
                precision: Default::default(),
            },
            0,
            "t",
        )
        .unwrap();
        (vdi, cam)
    }

    /// The views the walk's tests take of [`blobs`] (generated from `cam`).
    pub(super) fn views(cam: Camera) -> [Camera; 8] {
        [
            cam,
            // Nearly the generation view: projections of a fraction of a pixel, crossings
            // whose u the pixel coordinates' rounding moves most.
            cam.orbit_y(0.02),
            cam.orbit_y(1.0),
            cam.orbit_y(30.0),
            cam.orbit(60.0, 30.0, 1.0),
            cam.orbit_y(90.0),
            cam.orbit_y(180.0),
            // From inside the volume: rays fanning out in every direction.
            Camera {
                eye: Vec3::new(24.0, 20.0, 22.0),
                ..cam.orbit_y(35.0)
            },
        ]
    }

    /// A render asked to stop stops: cancelled, it returns no image; never cancelled, it
    /// equals the plain render bit for bit.
    #[test]
    fn a_cancelled_render_stops_and_an_uncancelled_one_is_unchanged() {
        let (vdi, cam) = blobs();
        let w = Walker::new(&vdi);
        let plain = w.render(&cam, 96, 64, 0.99);
        let go = Cancel::new();
        let same = w.render_until(&cam, 96, 64, 0.99, Some(&go)).unwrap();
        assert_eq!(plain.pixels(), same.pixels());
        go.cancel();
        assert_eq!(
            w.render_until(&cam, 96, 64, 0.99, Some(&go)),
            Err(Cancelled)
        );
    }

    /// Skipping tiles by depth range, squares of empty tiles, and pixels by depth occupancy
    /// is an optimisation: it must not change the image, walked ray by ray or in packets.
    #[test]
    fn skipping_leaves_the_image_unchanged() {
        let (vdi, cam) = blobs();
        let skipping = Walker::new(&vdi);
        let mut all = vdi.walk_tables().clone();
        all.tile_w.fill([-f32::MAX, f32::MAX]);
        all.tile_reach.fill(0);
        all.pixel_bins.fill(u64::MAX);
        let walking_all = Walker {
            tables: &all,
            ..Walker::new(&vdi)
        };
        let mut seen = 0;
        for view in views(cam) {
            let f = view.frame(64, 64);
            let (packed, packed_all) = (
                skipping.render(&view, 64, 64, 0.99),
                walking_all.render(&view, 64, 64, 0.99),
            );
            for j in 0..64 {
                for i in 0..64 {
                    let ray = f.pixel_ray(i, j);
                    let (a, b) = (
                        skipping.integrate(&ray, 0.99),
                        walking_all.integrate(&ray, 0.99),
                    );
                    let k = (i + 64 * j) as usize;
                    let (c, d) = (packed.pixels()[k], packed_all.pixels()[k]);
                    for k in 0..3 {
                        assert!(
                            (a[k] - b[k]).abs() < 1e-6,
                            "pixel ({i}, {j}): {a:?} vs {b:?}"
                        );
                        assert!(
                            (c[k] - d[k]).abs() < 1e-6,
                            "packets, pixel ({i}, {j}): {c:?} vs {d:?}"
                        );
                    }
                    seen += usize::from(a != [0.0; 3]);
                }
            }
        }
        assert!(seen > 1000, "the blobs must be seen ({seen} pixels)");
    }
}
