//! Which pixels of a view can see anything: the tiles of the image covered by the projection
//! of a visible macro cell.
//!
//! A sample contributes only inside a visible macro cell (its lower voxel's cell; interpolation
//! reads one voxel past the cell, `macrocell`), so a ray that crosses no visible cell
//! composites nothing and its pixel can be left empty without marching it. Each visible cell's
//! box, a voxel wider on every side, is projected ([`ViewFrame::footprint`]: the bounding
//! rectangle of its corners, a pixel wider) and the [`TILE`]² tiles it touches are marked.
//! Where the kernel's occupancy bits are built (`occupancy`: a bit per 2³ block of lower
//! voxels), each octant of a visible cell projects only the box of its blocks with a bit set:
//! a thin structure (the stent's wires) leaves most of its cells' rays unmarked.
//! Rays through unmarked tiles are the ones the macro-cell leaps would have carried through
//! empty space from the volume's entry to its exit. A cell with a corner not in front of the
//! eye covers the whole image.

use super::Raycaster;
use crate::camera::ViewFrame;
use crate::volume::Aabb;
use glam::Vec3;
use std::ops::Range;

/// Side of a coverage tile, pixels.
pub const TILE: u32 = 4;

/// The tiles of one view that a visible macro cell projects onto.
#[derive(Clone, Debug)]
pub struct Coverage {
    tiles_x: u32,
    /// Per tile, row-major: whether a ray through it can meet a visible cell.
    covered: Vec<bool>,
}

impl Coverage {
    /// The coverage of `frame` by `raycaster`'s visible macro cells (every tile without
    /// empty-space skipping, none when nothing is visible).
    pub fn new(raycaster: &Raycaster, frame: &ViewFrame) -> Self {
        let tiles_x = frame.width.div_ceil(TILE);
        let tiles_y = frame.height.div_ceil(TILE);
        let n = tiles_x as usize * tiles_y as usize;
        if !raycaster.params().empty_space_skipping {
            return Self {
                tiles_x,
                covered: vec![true; n],
            };
        }
        let mut covered = vec![false; n];
        let grid = raycaster.macro_grid();
        let size = grid.cell_size() as f32;
        let bounds = raycaster.bounds();
        let spacing = raycaster.volume().spacing();
        let mut cover = |lo: Vec3, hi: Vec3| {
            // Lower voxels in [lo, hi): samples between lo and hi (interpolation reads the
            // voxel after the lower one), a voxel more on each side against rounding.
            let b = Aabb {
                min: (bounds.min + (lo - Vec3::ONE) * spacing).max(bounds.min),
                max: (bounds.min + (hi + Vec3::ONE) * spacing).min(bounds.max),
            };
            let (xs, ys) = frame.footprint(&b);
            if xs.is_empty() || ys.is_empty() {
                return;
            }
            for ty in ys.start / TILE..=(ys.end - 1) / TILE {
                let row = ty as usize * tiles_x as usize;
                covered[row + (xs.start / TILE) as usize..=row + ((xs.end - 1) / TILE) as usize]
                    .fill(true);
            }
        };
        let voxels = |a: [usize; 3]| Vec3::from(a.map(|x| x as f32));
        for (i, cell) in grid.visible_cells() {
            let origin = voxels(cell) * size;
            match raycaster.occupancy() {
                // Where the kernel's block bits exist, the boxes of each octant's visible
                // blocks: in a visible cell of thin structures most rays miss them.
                Some(occupancy) => {
                    for (lo, hi) in occupancy.octant_boxes(i).into_iter().flatten() {
                        cover(origin + voxels(lo), origin + voxels(hi));
                    }
                }
                None => cover(origin, origin + Vec3::splat(size)),
            }
        }
        Self { tiles_x, covered }
    }

    /// Whether the ray through pixel `(i, j)` can meet a visible cell.
    #[inline]
    pub fn covers(&self, i: u32, j: u32) -> bool {
        let t = (j / TILE) as usize * self.tiles_x as usize + (i / TILE) as usize;
        self.covered.get(t).copied().unwrap_or(false)
    }

    /// Covered tiles in the tile rows that pixel rows `rows` fall in (all covered tiles for
    /// `0..height`): the work a generation of those rows has, for its progress.
    pub fn covered_tiles(&self, rows: Range<u32>) -> usize {
        let w = self.tiles_x as usize;
        let (a, b) = (
            rows.start.div_ceil(TILE) as usize,
            rows.end.div_ceil(TILE) as usize,
        );
        let (a, b) = (
            (a * w).min(self.covered.len()),
            (b * w).min(self.covered.len()),
        );
        self.covered[a..b].iter().filter(|&&c| c).count()
    }

    /// Whether any of pixels `i0 … i1 − 1` of row `j` is covered.
    #[inline]
    pub fn covers_any(&self, i0: u32, i1: u32, j: u32) -> bool {
        i1 > i0 && (i0 / TILE..=(i1 - 1) / TILE).any(|t| self.covers(t * TILE, j))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Camera;
    use crate::raycast::RaycastParams;
    use crate::tf::TransferFunction;
    use crate::volume::Volume;

    fn covered(c: &Coverage, w: u32, h: u32) -> usize {
        (0..h)
            .flat_map(|j| (0..w).map(move |i| (i, j)))
            .filter(|&(i, j)| c.covers(i, j))
            .count()
    }

    /// A small ball covers a small part of the view, all of it where its rays go; nothing
    /// visible covers nothing; an eye inside the ball (a visible cell around it, with corners
    /// behind it) covers everything. (That no uncovered ray meets a visible sample is pinned in
    /// `raycast::tests::empty_space_skipping_visits_the_same_samples`.)
    #[test]
    fn a_ball_covers_its_silhouette_and_little_else() {
        let centre = Vec3::new(34.0, 12.0, 25.0);
        let v = Volume::from_fn([50, 44, 40], |x, y, z| {
            f32::from(u8::from(
                (Vec3::new(x as f32, y as f32, z as f32) - centre).length() < 5.0,
            ))
        })
        .unwrap();
        let tf = TransferFunction::from_json(
            r#"{"domain": [0, 1], "points": [[0,0,0,0,0],[0.001,1,0,0,0.2],[1,1,1,1,0.3]]}"#,
            "t",
        )
        .unwrap();
        let rc = Raycaster::new(&v, &tf, RaycastParams::default()).unwrap();
        let cam = Camera::default_for_box(&v.world_box()).orbit_y(30.0);
        let (w, h) = (96, 64);
        let f = cam.frame(w, h);
        let c = Coverage::new(&rc, &f);
        let n = covered(&c, w, h);
        assert!(
            n > 0 && n < (w * h / 4) as usize,
            "{n} of {} pixels covered",
            w * h
        );
        // The ray at the ball's centre's pixel is covered.
        let (x, y) = f.project(centre).unwrap();
        assert!(c.covers(x as u32, y as u32));
        assert!(c.covers_any(0, w, y as u32) && !c.covers_any(0, 0, y as u32));

        let none = TransferFunction::constant(0.0, 1.0, [1.0, 1.0, 1.0, 0.0]);
        let dark = Raycaster::new(&v, &none, RaycastParams::default()).unwrap();
        assert_eq!(covered(&Coverage::new(&dark, &f), w, h), 0);

        let mut inside = cam;
        inside.eye = centre;
        inside.target = centre + Vec3::Z;
        let f = inside.frame(w, h);
        assert_eq!(covered(&Coverage::new(&rc, &f), w, h), (w * h) as usize);
    }
}
