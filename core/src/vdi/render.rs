//! VDI rendering `I(M, P_I) → O` from any camera (Sec. 3.2, Fig. 2b; DESIGN.md, "Rendering a
//! VDI from a new camera").
//!
//! A ray of the new camera is clipped to the volume box and to the generation camera's
//! frustum. Its projection into the generation image is a line segment, walked pixel by pixel
//! with a 2D DDA (Amanatides–Woo, with crossing parameters solved on the projective line), so
//! pixels come in ray order. In each pixel the ray spans a depth interval; the supersegments
//! of that pixel's depth-sorted list that overlap it are found by binary search and
//! composited front to back with `α' = 1 − (1 − â)^ℓ`, `ℓ` the world length of the ray inside
//! the frustum. Views from behind traverse the lists backwards; rays perpendicular to the
//! generation view direction (constant depth) take the one supersegment that contains them.

use super::{Supersegment, Vdi};
use crate::camera::{Camera, Ray, ViewFrame};
use crate::dvr::render_tiles;
use crate::fastmath::{self, one_minus_exp_neg};
use crate::image::Image;
use glam::Vec3;
use rayon::prelude::*;

/// Renders `vdi` seen by `camera` at `width × height`, stopping each ray once its accumulated
/// opacity reaches `termination` (in (0, 1]); background black. For several views of one VDI,
/// build a [`Walker`] once and call [`Walker::render`].
pub fn render(vdi: &Vdi, camera: &Camera, width: u32, height: u32, termination: f32) -> Image {
    Walker::new(vdi).render(camera, width, height, termination)
}

/// Side, in generation pixels, of the tiles the walk skips when they hold no supersegment
/// (the 2D analogue of macro-cell empty-space skipping).
pub const SKIP_TILE: i64 = 8;

/// Depth range `[z_min, z_max]` of the supersegments in each `SKIP_TILE × SKIP_TILE` tile of
/// the generation image, row-major, `⌈r / SKIP_TILE⌉²` entries; `[f32::MAX, −f32::MAX]` for an
/// empty tile (shared with the GPU walk). The walk skips a tile whose depth range the ray's
/// depth over the tile does not meet: empty tiles, and content the ray passes in front of or
/// behind.
pub fn tile_depth_ranges(vdi: &Vdi) -> Vec<[f32; 2]> {
    let r = vdi.resolution() as usize;
    let tile = SKIP_TILE as usize;
    let tiles_x = r.div_ceil(tile);
    let mut ranges = vec![[f32::MAX, -f32::MAX]; tiles_x * tiles_x];
    // A row of tiles per task.
    ranges
        .par_chunks_mut(tiles_x.max(1))
        .enumerate()
        .for_each(|(ty, row)| {
            for j in ty * tile..((ty + 1) * tile).min(r) {
                for i in 0..r {
                    let list = vdi.pixel(i as u32, j as u32);
                    if let (Some(first), Some(last)) = (list.first(), list.last()) {
                        let range = &mut row[i / tile];
                        range[0] = range[0].min(first.z_start);
                        range[1] = range[1].max(last.z_end);
                    }
                }
            }
        });
    ranges
}

/// The per-VDI constants of the walk: tile depth ranges and packed search keys (8 bytes per
/// supersegment, 8 per tile), built once per VDI and kept with it ([`Vdi`]'s derived data).
#[derive(Clone)]
pub(crate) struct WalkTables {
    /// Tiles per row of the generation image.
    tiles_x: i64,
    /// Depth range of each `SKIP_TILE²` tile's supersegments ([`tile_depth_ranges`]).
    tile_depth: Vec<[f32; 2]>,
    /// Per supersegment, packed: `z_end` (the depth searches touch two cache lines where the
    /// 24-byte supersegments would take four) and the extinction `κ = −ln(1 − â)` per unit
    /// length (so `α' = 1 − e^(−ℓ·κ)` costs one call-free [`one_minus_exp_neg`], not a `powf`;
    /// `â = 1` gives `κ = ∞` and `α' = 1`).
    keys: Vec<[f32; 2]>,
}

impl WalkTables {
    /// One pass over `vdi`'s pixels and supersegments.
    pub(crate) fn new(vdi: &Vdi) -> Self {
        let ri = i64::from(vdi.resolution());
        Self {
            tiles_x: (ri + SKIP_TILE - 1) / SKIP_TILE,
            tile_depth: tile_depth_ranges(vdi),
            keys: vdi
                .supersegments()
                .par_iter()
                .map(|s| [s.z_end, s.extinction()])
                .collect(),
        }
    }
}

/// A VDI prepared for rendering from many cameras: its generation frame and its walk tables
/// (built on the VDI's first render and kept with it).
pub struct Walker<'a> {
    vdi: &'a Vdi,
    gen: ViewFrame,
    r: i64,
    tables: &'a WalkTables,
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
        }
    }

    /// Renders the VDI seen by `camera` at `width × height`, stopping rays at accumulated
    /// opacity `termination` (in (0, 1]); background black.
    pub fn render(&self, camera: &Camera, width: u32, height: u32, termination: f32) -> Image {
        let frame = camera.frame(width, height);
        render_tiles(&frame, |i, j| {
            self.integrate(&frame.pixel_ray(i, j), termination)
        })
    }

    /// Composited colour along `ray`.
    fn integrate(&self, ray: &Ray, termination: f32) -> [f32; 3] {
        let mut acc = Accum {
            color: [0.0; 3],
            transmittance: 1.0,
            threshold: 1.0 - termination,
        };
        self.walk(ray, &mut acc);
        acc.color.map(|c| c.clamp(0.0, 1.0))
    }

    fn walk(&self, ray: &Ray, acc: &mut Accum) {
        let g = &self.gen;
        let (mut t0, mut t1) = self
            .vdi
            .meta()
            .volume_box
            .intersect(ray.origin, ray.dir.recip());
        t0 = t0.max(0.0);
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
        // Frustum: |x| ≤ tx·z, |y| ≤ ty·z, z > 0.
        let planes = [
            Lin {
                f0: tx * z.f0 - x.f0,
                f1: tx * z.f1 - x.f1,
            },
            Lin {
                f0: tx * z.f0 + x.f0,
                f1: tx * z.f1 + x.f1,
            },
            Lin {
                f0: ty * z.f0 - y.f0,
                f1: ty * z.f1 - y.f1,
            },
            Lin {
                f0: ty * z.f0 + y.f0,
                f1: ty * z.f1 + y.f1,
            },
            Lin {
                f0: z.f0 - 1e-6,
                f1: z.f1,
            },
        ];
        for p in planes {
            if p.f1 > 0.0 {
                t0 = t0.max(-p.f0 / p.f1);
            } else if p.f1 < 0.0 {
                t1 = t1.min(-p.f0 / p.f1);
            } else if p.f0 < 0.0 {
                return;
            }
        }
        if t1.is_nan() || t0.is_nan() || t1 <= t0 {
            return;
        }
        let r = self.r as f32;
        // Pixel coordinates: px = (x/(z·tx) + 1)·r/2, py = (1 − y/(z·ty))·r/2.
        let px = |t: f32| (x.at(t) / (z.at(t) * tx) + 1.0) * 0.5 * r;
        let py = |t: f32| (1.0 - y.at(t) / (z.at(t) * ty)) * 0.5 * r;
        let (px0, py0, px1, py1) = (px(t0), py(t0), px(t1), py(t1));
        // A projection shorter than this (pixels) is a point: the ray passes through the
        // generation eye, as every ray of the generation view does.
        const DEGENERATE_PX: f32 = 1e-3;
        let direction = |d: f32| -> i64 {
            if d > DEGENERATE_PX {
                1
            } else if d < -DEGENERATE_PX {
                -1
            } else {
                0
            }
        };
        let (step_x, step_y) = (direction(px1 - px0), direction(py1 - py0));
        let start_cell = |p: f32, step: i64| -> i64 {
            let c = if step < 0 {
                fastmath::ceil(p) as i64 - 1
            } else {
                -fastmath::ceil(-p) as i64
            };
            c.clamp(0, self.r - 1)
        };
        let mut ix = start_cell(px0, step_x);
        let mut iy = start_cell(py0, step_y);
        // Ray parameter where px (or py) reaches pixel boundary `b`.
        let cross_x = |b: i64| {
            let s = (2.0 * b as f32 / r - 1.0) * tx;
            (s * z.f0 - x.f0) / (x.f1 - s * z.f1)
        };
        let cross_y = |b: i64| {
            let s = (1.0 - 2.0 * b as f32 / r) * ty;
            (s * z.f0 - y.f0) / (y.f1 - s * z.f1)
        };
        // Where the ray leaves the current pixel column / row; recomputed only for the axis
        // that stepped (one division per pixel crossed).
        let next_x = |ix: i64| {
            if step_x == 0 {
                f32::INFINITY
            } else {
                cross_x(ix + i64::from(step_x > 0))
            }
        };
        let next_y = |iy: i64| {
            if step_y == 0 {
                f32::INFINITY
            } else {
                cross_y(iy + i64::from(step_y > 0))
            }
        };
        let (mut raw_x, mut raw_y) = (next_x(ix), next_y(iy));
        let mut t = t0;
        // The tile whose pixels are being walked (its depth range meets the ray's).
        let mut walking = -1i64;
        for _ in 0..(2 * self.r + 4) {
            // The projective line can meet a boundary behind the clipped segment (through
            // z < 0): such solutions before t0 are no crossing. A real crossing lies in
            // [t0, t1]; one a rounding error behind t counts as immediate. NaN never wins.
            let guard = |tc: f32| {
                if tc.is_nan() || tc < t0 {
                    f32::INFINITY
                } else {
                    tc.max(t)
                }
            };
            let tile = ix / SKIP_TILE + self.tables.tiles_x * (iy / SKIP_TILE);
            if tile != walking {
                // Entering a tile: where does the ray leave it, and does its depth over the
                // tile meet the tile's supersegments?
                let (x0t, y0t) = (ix / SKIP_TILE * SKIP_TILE, iy / SKIP_TILE * SKIP_TILE);
                // The tile's far boundary along each axis (its low one when stepping down).
                let far = |step: i64, lo: i64| if step > 0 { lo + SKIP_TILE } else { lo };
                let ex = if step_x == 0 {
                    f32::INFINITY
                } else {
                    guard(cross_x(far(step_x, x0t)))
                };
                let ey = if step_y == 0 {
                    f32::INFINITY
                } else {
                    guard(cross_y(far(step_y, y0t)))
                };
                let t_next = ex.min(ey).min(t1);
                let [z_min, z_max] = self.tables.tile_depth[tile as usize];
                let (za, zb) = (z.at(t), z.at(t_next));
                let margin = 1e-5 * za.abs().max(zb.abs());
                if !(za.min(zb) > z_max + margin || za.max(zb) < z_min - margin) {
                    walking = tile;
                } else {
                    // Nothing to meet here: jump to the next tile, entering it at the pixel
                    // that holds the ray there.
                    if t_next >= t1 {
                        return;
                    }
                    let inside = |p: f32, step: i64, lo: i64| {
                        start_cell(p, step).clamp(lo, lo + SKIP_TILE - 1)
                    };
                    if ex <= ey {
                        ix = if step_x > 0 { x0t + SKIP_TILE } else { x0t - 1 };
                        iy = inside(py(t_next), step_y, y0t);
                    } else {
                        iy = if step_y > 0 { y0t + SKIP_TILE } else { y0t - 1 };
                        ix = inside(px(t_next), step_x, x0t);
                    }
                    if !(0..self.r).contains(&ix) || !(0..self.r).contains(&iy) {
                        return;
                    }
                    t = t_next;
                    (raw_x, raw_y) = (next_x(ix), next_y(iy));
                    continue;
                }
            }
            let (tnx, tny) = (guard(raw_x), guard(raw_y));
            let t_next = tnx.min(tny).min(t1);
            if t_next > t {
                let p = (ix + self.r * iy) as usize;
                let offsets = self.vdi.offsets();
                let range = offsets[p] as usize..offsets[p + 1] as usize;
                if !range.is_empty()
                    && composite_span(
                        &self.vdi.supersegments()[range.clone()],
                        &self.tables.keys[range],
                        z,
                        t,
                        t_next,
                        acc,
                    )
                {
                    return;
                }
            }
            if t_next >= t1 {
                return;
            }
            if tnx <= tny {
                ix += step_x;
                raw_x = next_x(ix);
            } else {
                iy += step_y;
                raw_y = next_y(iy);
            }
            if !(0..self.r).contains(&ix) || !(0..self.r).contains(&iy) {
                return;
            }
            t = t_next;
        }
    }
}

/// Front-to-back accumulator of one ray.
struct Accum {
    color: [f32; 3],
    transmittance: f32,
    /// Stop once transmittance falls to this.
    threshold: f32,
}

impl Accum {
    /// Adds a frustum of extinction `kappa` = `−ln(1 − â)` passed over world length `len`;
    /// returns true when the ray is done.
    #[inline]
    fn add(&mut self, s: &Supersegment, kappa: f32, len: f32) -> bool {
        if len > 0.0 && s.alpha > 0.0 {
            // â = 1 gives κ = ∞ and α' = 1.
            let alpha = one_minus_exp_neg(len * kappa);
            let w = self.transmittance * alpha;
            for k in 0..3 {
                self.color[k] += w * s.color[k];
            }
            self.transmittance *= 1.0 - alpha;
        }
        self.transmittance <= self.threshold
    }
}

/// Composites the supersegments of one pixel list met by the ray over `[ta, tb]`, where the
/// generation depth is `z(t)`; `keys` holds the list's `[z_end, −ln(1 − â)]`. Returns true when the ray
/// is done.
#[inline]
fn composite_span(
    list: &[Supersegment],
    keys: &[[f32; 2]],
    z: Lin,
    ta: f32,
    tb: f32,
    acc: &mut Accum,
) -> bool {
    let span = tb - ta;
    let (za, zb) = (z.at(ta), z.at(tb));
    // The first supersegment ending after za; lists are sorted and disjoint.
    let first = keys.partition_point(|k| k[0] <= za);
    if z.f1 > 0.0 {
        for (s, k) in list[first..].iter().zip(&keys[first..]) {
            if s.z_start >= zb {
                break;
            }
            let len = ((s.z_end.min(zb) - s.z_start.max(za)) / z.f1).clamp(0.0, span);
            if acc.add(s, k[1], len) {
                return true;
            }
        }
    } else if z.f1 < 0.0 {
        // Those starting before za: up to `first`, and `first` itself if it contains za.
        let end = first + usize::from(list.get(first).is_some_and(|s| s.z_start < za));
        for (s, k) in list[..end].iter().zip(&keys[..end]).rev() {
            if s.z_end <= zb {
                break;
            }
            let len = ((s.z_end.min(za) - s.z_start.max(zb)) / -z.f1).clamp(0.0, span);
            if acc.add(s, k[1], len) {
                return true;
            }
        }
    } else if let (Some(s), Some(k)) = (list.get(first), keys.get(first)) {
        if s.z_start <= za && acc.add(s, k[1], span) {
            return true;
        }
    }
    false
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::raycast::{RaycastParams, Raycaster};
    use crate::tf::TransferFunction;
    use crate::vdi::{generate::generate, VdiParams};
    use crate::volume::Volume;

    /// Skipping tiles by depth range is an optimisation: it must not change the image.
    #[test]
    fn tile_skipping_leaves_the_image_unchanged() {
        // Two blobs at different depths with empty space around and between them.
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
            },
            0,
            "t",
        )
        .unwrap();
        let skipping = Walker::new(&vdi);
        let mut all = vdi.walk_tables().clone();
        all.tile_depth.fill([-f32::MAX, f32::MAX]);
        let walking_all = Walker {
            tables: &all,
            ..Walker::new(&vdi)
        };
        let inside = Camera {
            eye: Vec3::new(24.0, 20.0, 22.0),
            ..cam.orbit_y(35.0)
        };
        let mut seen = 0;
        for view in [
            cam,
            cam.orbit_y(30.0),
            cam.orbit_y(90.0),
            cam.orbit_y(180.0),
            inside,
        ] {
            let f = view.frame(64, 64);
            for j in 0..64 {
                for i in 0..64 {
                    let ray = f.pixel_ray(i, j);
                    let (a, b) = (
                        skipping.integrate(&ray, 0.99),
                        walking_all.integrate(&ray, 0.99),
                    );
                    for k in 0..3 {
                        assert!(
                            (a[k] - b[k]).abs() < 1e-6,
                            "pixel ({i}, {j}): {a:?} vs {b:?}"
                        );
                    }
                    seen += usize::from(a != [0.0; 3]);
                }
            }
        }
        assert!(seen > 1000, "the blobs must be seen ({seen} pixels)");
    }
}
