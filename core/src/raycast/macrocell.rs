//! Min/max macro-cell grid for empty-space skipping.
//!
//! Cell `c` along an axis owns the samples whose (clamped) lower voxel index lies in
//! `[c·B, c·B + B − 1]`; trilinear interpolation there reads voxels `c·B ..= c·B + B`, so the
//! cell's range is taken over those `B + 1` voxels (NaN ignored). A cell is visible when the
//! transfer function gives any value in its range non-zero opacity ([`Lut::any_visible`]).

use crate::tf::Lut;
use crate::volume::Volume;
use glam::Vec3;
use rayon::prelude::*;

/// Side of a macro cell in voxels.
pub const MACRO_CELL: usize = 8;

/// Per-cell visibility for one transfer function.
pub struct MacroGrid {
    cells: [usize; 3],
    visible: Vec<bool>,
}

impl MacroGrid {
    /// Builds the grid for `volume` classified by `lut`.
    pub fn new(volume: &Volume, lut: &Lut) -> Self {
        let dims = volume.dims();
        let cells = dims.map(|n| n.saturating_sub(2) / MACRO_CELL + 1);
        let data = volume.data();
        let [nx, ny, _] = dims;
        let visible = (0..cells[0] * cells[1] * cells[2])
            .into_par_iter()
            .map(|c| {
                let idx = [
                    c % cells[0],
                    (c / cells[0]) % cells[1],
                    c / (cells[0] * cells[1]),
                ];
                let range = |a: usize| {
                    let lo = idx[a] * MACRO_CELL;
                    lo..=(lo + MACRO_CELL).min(dims[a] - 1)
                };
                let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
                for z in range(2) {
                    for y in range(1) {
                        let row = nx * (y + ny * z);
                        for &v in &data[row + *range(0).start()..=row + *range(0).end()] {
                            if !v.is_nan() {
                                lo = lo.min(v);
                                hi = hi.max(v);
                            }
                        }
                    }
                }
                lut.any_visible(lo, hi)
            })
            .collect();
        Self { cells, visible }
    }

    #[inline(always)]
    fn cell_index(&self, ix: usize, iy: usize, iz: usize) -> usize {
        ix / MACRO_CELL + self.cells[0] * (iy / MACRO_CELL + self.cells[1] * (iz / MACRO_CELL))
    }

    /// Whether the cell that owns lower voxel index `(ix, iy, iz)` can contribute.
    #[inline(always)]
    pub fn visible(&self, ix: usize, iy: usize, iz: usize) -> bool {
        self.visible[self.cell_index(ix, iy, iz)]
    }

    /// Cells per axis.
    pub fn cells(&self) -> [usize; 3] {
        self.cells
    }

    /// Visibility per cell, x fastest.
    pub fn visibility(&self) -> &[bool] {
        &self.visible
    }

    /// Fraction of cells that are visible (for reports).
    pub fn visible_fraction(&self) -> f32 {
        self.visible.iter().filter(|&&v| v).count() as f32 / self.visible.len().max(1) as f32
    }

    /// Ray parameter where the ray `o_v + t·d_v` (voxel space, `inv_d_v = 1/d_v`) leaves the
    /// box of the cell that owns `(ix, iy, iz)`.
    #[inline]
    pub fn cell_exit(&self, ix: usize, iy: usize, iz: usize, o_v: Vec3, inv_d_v: Vec3) -> f32 {
        let lo = Vec3::new(
            (ix / MACRO_CELL * MACRO_CELL) as f32,
            (iy / MACRO_CELL * MACRO_CELL) as f32,
            (iz / MACRO_CELL * MACRO_CELL) as f32,
        );
        let hi = lo + Vec3::splat(MACRO_CELL as f32);
        let mut t = f32::INFINITY;
        for a in 0..3 {
            let exit = if inv_d_v[a] >= 0.0 {
                (hi[a] - o_v[a]) * inv_d_v[a]
            } else {
                (lo[a] - o_v[a]) * inv_d_v[a]
            };
            t = t.min(exit);
        }
        t
    }
}
