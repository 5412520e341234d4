//! Min/max macro-cell grid for empty-space skipping.
//!
//! Cell `c` along an axis owns the samples whose (clamped) lower voxel index lies in
//! `[c·B, c·B + B − 1]`; trilinear interpolation there reads voxels `c·B ..= c·B + B`, so the
//! cell's range is taken over those `B + 1` voxels (NaN ignored). A cell is visible when the
//! transfer function gives any value in its range non-zero opacity ([`Lut::any_visible`]).
//!
//! Each invisible cell also knows its chessboard (L∞) distance, in cells, to the nearest
//! visible one, so a ray can leap the whole empty cube of cells around it at once (a
//! "proximity cloud", Cohen & Sheffer 1994): on the teapot most rays cross only empty space,
//! and leaping cube by cube instead of cell by cell takes far fewer steps.
//!
//! The side `B` is 16 voxels for volumes of at least 128 voxels on every axis, else 8
//! ([`cell_size_for`]): a ray pays per macro cell it enters or leaps (the DDA, the run set-up),
//! and, since the AVX2 kernel passes over invisible 2³-voxel blocks inside visible cells
//! almost for free (`occupancy`), larger cells cost little in wasted samples. Measured on
//! this 2-core machine (768², DVR): the teapot 0.113 → 0.101 s from 10° with 16, but
//! hydrogen (64³) 0.063 → 0.065 s and neghip (66³) 0.074 → 0.076 s, where 16 leaves four
//! cells per axis.

use crate::tf::Lut;
use crate::volume::{Volume, Voxel, VoxelSlice};
use glam::Vec3;
use rayon::prelude::*;

/// Side of a macro cell in voxels, the smaller choice of [`cell_size_for`].
pub const MACRO_CELL: usize = 8;
/// The larger choice of [`cell_size_for`].
pub const LARGE_MACRO_CELL: usize = 16;
/// Voxels on every axis from which a volume gets [`LARGE_MACRO_CELL`]s.
const LARGE_FROM: usize = 128;

/// The macro-cell side for a volume of `dims` voxels (a power of two).
pub fn cell_size_for(dims: [usize; 3]) -> usize {
    if dims.iter().all(|&n| n >= LARGE_FROM) {
        LARGE_MACRO_CELL
    } else {
        MACRO_CELL
    }
}

/// Per-cell visibility for one transfer function.
#[derive(Clone)]
pub struct MacroGrid {
    /// Side of a cell, voxels (a power of two).
    size: usize,
    cells: [usize; 3],
    visible: Vec<bool>,
    /// Per cell: 0 when visible, else the L∞ distance in cells to the nearest visible cell
    /// (capped at [`u8::MAX`]); the cells within `distance − 1` of it are all invisible.
    distance: Vec<u8>,
}

impl MacroGrid {
    /// Builds the grid for `volume` classified by `lut`.
    pub fn new(volume: &Volume, lut: &Lut) -> Self {
        Self::with_cell_size(volume, lut, cell_size_for(volume.dims()))
    }

    /// [`MacroGrid::new`] with cells of `size` voxels a side (a power of two).
    pub(crate) fn with_cell_size(volume: &Volume, lut: &Lut, size: usize) -> Self {
        debug_assert!(size.is_power_of_two());
        let dims = volume.dims();
        let cells = cells_of(dims, size);
        let visible: Vec<bool> = match volume.voxels() {
            VoxelSlice::U8(d) => visibility(d, dims, size, lut),
            VoxelSlice::U16(d) => visibility(d, dims, size, lut),
            VoxelSlice::I16(d) => visibility(d, dims, size, lut),
            VoxelSlice::F32(d) => visibility(d, dims, size, lut),
        };
        let distance = chessboard_distance(cells, &visible);
        Self {
            size,
            cells,
            visible,
            distance,
        }
    }

    /// Whether the cell that owns lower voxel index `(ix, iy, iz)` can contribute.
    #[inline(always)]
    pub fn visible(&self, ix: usize, iy: usize, iz: usize) -> bool {
        self.visible[self.flat(self.cell_of([ix, iy, iz]))]
    }

    /// Side of a cell, voxels (a power of two: 8 or 16, `cell_size_for`).
    pub fn cell_size(&self) -> usize {
        self.size
    }

    /// Cells per axis.
    pub fn cells(&self) -> [usize; 3] {
        self.cells
    }

    /// Visibility per cell, x fastest.
    pub fn visibility(&self) -> &[bool] {
        &self.visible
    }

    /// The visible cells: flat index (as [`MacroGrid::visibility`]) and coordinates.
    pub fn visible_cells(&self) -> impl Iterator<Item = (usize, [usize; 3])> + '_ {
        let [cx, cy, _] = self.cells;
        self.visible
            .iter()
            .enumerate()
            .filter(|&(_, &v)| v)
            .map(move |(i, _)| (i, [i % cx, i / cx % cy, i / (cx * cy)]))
    }

    /// Fraction of cells that are visible (for reports).
    pub fn visible_fraction(&self) -> f32 {
        self.visible.iter().filter(|&&v| v).count() as f32 / self.visible.len().max(1) as f32
    }

    /// For an invisible cell owning lower voxel index `voxel`: where the ray `o_v + t·d_v` (voxel space,
    /// `inv_d_v = 1/d_v`) leaves the invisible cells it crosses from there on. A cell next to
    /// a visible one (distance 1) is walked cell by cell (3-D DDA); one at distance `d > 1`
    /// is left through the cube of cells within `d − 1` of it, all invisible, which ends the
    /// walk. The walk also ends, at the current cell's exit, where the ray's next cell is not
    /// clear from the face it leaves through (two faces met within `tolerance(t)` of each
    /// other, far above the rounding of `t`): every point of the ray before the returned exit
    /// lies in an invisible cell, up to that rounding, which the caller's margin covers.
    #[inline]
    pub fn empty_run_exit(
        &self,
        voxel: [usize; 3],
        o_v: Vec3,
        inv_d_v: Vec3,
        tolerance: impl Fn(f32) -> f32,
    ) -> f32 {
        let mut cell = self.cell_of(voxel);
        loop {
            let d = self.distance[self.flat(cell)];
            if d != 1 {
                return box_exit(
                    cell,
                    self.size,
                    usize::from(d.saturating_sub(1)),
                    o_v,
                    inv_d_v,
                );
            }
            let (axis, exit, second) = self.exit_faces(cell, o_v, inv_d_v);
            if exit == f32::INFINITY || second - exit <= tolerance(exit) {
                return exit;
            }
            match self.neighbour(cell, axis, inv_d_v) {
                Some(next) if !self.visible[self.flat(next)] => cell = next,
                _ => return exit,
            }
        }
    }

    /// For a visible cell owning lower voxel index `(ix, iy, iz)`: where the ray `o_v + t·d_v` (voxel space,
    /// `inv_d_v = 1/d_v`) leaves the run of visible cells that it crosses from there on,
    /// walked cell by cell (3-D DDA over the macro cells) until a cell is invisible or the
    /// grid ends. Sampling every step up to here never skips a visible one, whatever the
    /// rounding of the walk: it only decides how many steps go to the kernel in one run.
    ///
    /// Kept out of the march loop: inlined there, the loop ran about 3 % slower (and so did
    /// passing the voxel as an array, which goes through memory to an out-of-line call).
    #[inline(never)]
    pub fn visible_run_exit(
        &self,
        ix: usize,
        iy: usize,
        iz: usize,
        o_v: Vec3,
        inv_d_v: Vec3,
    ) -> f32 {
        let mut cell = self.cell_of([ix, iy, iz]);
        let mut t = f32::NEG_INFINITY;
        loop {
            let (axis, exit, _) = self.exit_faces(cell, o_v, inv_d_v);
            if exit == f32::INFINITY {
                return exit;
            }
            t = t.max(exit);
            match self.neighbour(cell, axis, inv_d_v) {
                Some(next) if self.visible[self.flat(next)] => cell = next,
                _ => return t,
            }
        }
    }

    /// The faces of `cell` the ray `o_v + t·d_v` meets on its way out: the axis of the first
    /// and the ray parameters of the first and of the second (zero directions give ±∞ or NaN,
    /// never either; ∞ where there is none).
    #[inline(always)]
    fn exit_faces(&self, cell: [usize; 3], o_v: Vec3, inv_d_v: Vec3) -> (usize, f32, f32) {
        let (mut axis, mut exit, mut second) = (0, f32::INFINITY, f32::INFINITY);
        for a in 0..3 {
            let face = if inv_d_v[a] >= 0.0 {
                cell[a] + 1
            } else {
                cell[a]
            };
            let e = ((face * self.size) as f32 - o_v[a]) * inv_d_v[a];
            if e < exit {
                (axis, exit, second) = (a, e, exit);
            } else if e < second {
                second = e;
            }
        }
        (axis, exit, second)
    }

    /// The cell after `cell` across its exit face on `axis` (for a ray of direction sign
    /// `inv_d_v`), or `None` past the grid.
    #[inline(always)]
    fn neighbour(&self, mut cell: [usize; 3], axis: usize, inv_d_v: Vec3) -> Option<[usize; 3]> {
        let next = if inv_d_v[axis] >= 0.0 {
            cell[axis] + 1
        } else {
            cell[axis].wrapping_sub(1)
        };
        (next < self.cells[axis]).then(|| {
            cell[axis] = next;
            cell
        })
    }

    /// The cell that owns lower voxel index `voxel`.
    #[inline(always)]
    fn cell_of(&self, voxel: [usize; 3]) -> [usize; 3] {
        voxel.map(|v| v >> self.size.trailing_zeros())
    }

    /// Flat index of cell coordinates `[cx, cy, cz]`.
    #[inline(always)]
    fn flat(&self, [cx, cy, cz]: [usize; 3]) -> usize {
        cx + self.cells[0] * (cy + self.cells[1] * cz)
    }
}

/// Cells of side `size` per axis: cell `c` owns the samples whose lower voxel lies in
/// `[c·size, c·size + size − 1]` (the lower voxel is at most `n − 2`).
pub(crate) fn cells_of(dims: [usize; 3], size: usize) -> [usize; 3] {
    dims.map(|n| n.saturating_sub(2) / size + 1)
}

/// Where the ray `o_v + t·d_v` (voxel space, `inv_d_v = 1/d_v`) leaves the box of cells (of
/// side `size`) within L∞ distance `grow` of `cell`.
#[inline(always)]
fn box_exit(cell: [usize; 3], size: usize, grow: usize, o_v: Vec3, inv_d_v: Vec3) -> f32 {
    let lo = Vec3::from(cell.map(|c| (c.saturating_sub(grow) * size) as f32));
    let hi = Vec3::from(cell.map(|c| ((c + grow + 1) * size) as f32));
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

/// Whether each cell can contribute: the value range over its `B + 1` voxels per axis (NaN
/// ignored) meets the transfer function's visible values.
///
/// Per row of cells (one `(cy, cz)`), the `(B + 1)²` voxel rows it spans are folded
/// element-wise into one row of minima and maxima (long contiguous loops the compiler
/// vectorises), and only that row is split into cells: each voxel is read about
/// `((B + 1) / B)²` times, not `((B + 1) / B)³`, with no per-voxel branch.
fn visibility<T: Voxel>(data: &[T], dims: [usize; 3], size: usize, lut: &Lut) -> Vec<bool> {
    let [nx, ny, _] = dims;
    let cells = cells_of(dims, size);
    let span = |c: usize, n: usize| c * size..=(c * size + size).min(n - 1);
    let mut visible = vec![false; cells[0] * cells[1] * cells[2]];
    visible
        .par_chunks_mut(cells[0])
        .enumerate()
        .for_each(|(j, out)| {
            let (cy, cz) = (j % cells[1], j / cells[1]);
            let mut lo = vec![f32::INFINITY; nx];
            let mut hi = vec![f32::NEG_INFINITY; nx];
            for z in span(cz, dims[2]) {
                for y in span(cy, ny) {
                    let row = &data[nx * (y + ny * z)..][..nx];
                    for ((l, h), v) in lo.iter_mut().zip(hi.iter_mut()).zip(row) {
                        // NaN compares false both ways: ignored.
                        let v = v.value();
                        *l = if v < *l { v } else { *l };
                        *h = if v > *h { v } else { *h };
                    }
                }
            }
            for (cx, o) in out.iter_mut().enumerate() {
                let x = span(cx, nx);
                let l = lo[x.clone()].iter().fold(f32::INFINITY, |a, &b| a.min(b));
                let h = hi[x].iter().fold(f32::NEG_INFINITY, |a, &b| a.max(b));
                *o = lut.any_visible(l, h);
            }
        });
    visible
}

/// L∞ (chessboard) distance from each cell to the nearest visible cell, in cells, capped at
/// 255; 0 for visible cells. Exact with two raster passes over the 26-neighbourhood (forward
/// over the 13 neighbours already visited, then backward over the other 13). A grid without
/// visible cells gets 255 everywhere. A 2-D grid is `[nx, ny, 1]` (the VDI walk's tiles).
pub(crate) fn chessboard_distance(cells: [usize; 3], visible: &[bool]) -> Vec<u8> {
    let [cx, cy, cz] = cells.map(|c| c as isize);
    let mut d: Vec<u8> = visible
        .iter()
        .map(|&v| if v { 0 } else { u8::MAX })
        .collect();
    let at = |x: isize, y: isize, z: isize| (x + cx * (y + cy * z)) as usize;
    // The 13 neighbours that precede a cell in raster order (z, then y, then x slowest last).
    let before: Vec<[isize; 3]> = (-1..=1)
        .flat_map(|z| (-1..=1).flat_map(move |y| (-1..=1).map(move |x| [x, y, z])))
        .filter(|&[x, y, z]| (z, y, x) < (0, 0, 0))
        .collect();
    let pass = |d: &mut Vec<u8>, sign: isize| {
        let order: Box<dyn Iterator<Item = isize>> = if sign > 0 {
            Box::new(0..cx * cy * cz)
        } else {
            Box::new((0..cx * cy * cz).rev())
        };
        for c in order {
            let (x, y, z) = (c % cx, (c / cx) % cy, c / (cx * cy));
            let mut best = d[c as usize];
            for &[ox, oy, oz] in &before {
                let (nx, ny, nz) = (x + sign * ox, y + sign * oy, z + sign * oz);
                if (0..cx).contains(&nx) && (0..cy).contains(&ny) && (0..cz).contains(&nz) {
                    best = best.min(d[at(nx, ny, nz)].saturating_add(1));
                }
            }
            d[c as usize] = best;
        }
    };
    pass(&mut d, 1);
    pass(&mut d, -1);
    d
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Brute force: the smallest L∞ distance to any visible cell.
    fn brute(cells: [usize; 3], visible: &[bool]) -> Vec<u8> {
        let idx = |c: usize| {
            [
                c % cells[0],
                (c / cells[0]) % cells[1],
                c / (cells[0] * cells[1]),
            ]
        };
        (0..visible.len())
            .map(|c| {
                let a = idx(c);
                (0..visible.len())
                    .filter(|&o| visible[o])
                    .map(|o| {
                        let b = idx(o);
                        (0..3).map(|k| a[k].abs_diff(b[k])).max().unwrap_or(0)
                    })
                    .min()
                    .map_or(u8::MAX, |m| m.min(255) as u8)
            })
            .collect()
    }

    /// The cell ranges taken voxel by voxel over each cell's `(B + 1)³` block.
    fn visibility_brute<T: Voxel>(
        data: &[T],
        dims: [usize; 3],
        size: usize,
        lut: &Lut,
    ) -> Vec<bool> {
        let cells = cells_of(dims, size);
        let span = |c: usize, n: usize| c * size..=(c * size + size).min(n - 1);
        let mut out = Vec::new();
        for cz in 0..cells[2] {
            for cy in 0..cells[1] {
                for cx in 0..cells[0] {
                    let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
                    for z in span(cz, dims[2]) {
                        for y in span(cy, dims[1]) {
                            for x in span(cx, dims[0]) {
                                let v = data[x + dims[0] * (y + dims[1] * z)].value();
                                if !v.is_nan() {
                                    lo = lo.min(v);
                                    hi = hi.max(v);
                                }
                            }
                        }
                    }
                    out.push(lut.any_visible(lo, hi));
                }
            }
        }
        out
    }

    /// Sparse visible values (one voxel in a few hundred, NaN sprinkled in) on grids whose
    /// sides are and are not multiples of the cell, for both cell sizes: a single voxel on a
    /// cell border must make both cells that share it visible.
    #[test]
    fn visibility_matches_brute_force() {
        let tf = crate::tf::TransferFunction::from_json(
            r#"{"domain": [0, 255], "points": [[0.0, 0,0,0,0], [0.6, 0,0,0,0], [0.7, 1,1,1,0.5], [1.0, 1,1,1,0.5]]}"#,
            "test",
        )
        .unwrap();
        let lut = Lut::new(&tf, 1.0);
        let mut seen = [[0usize; 2]; 2];
        for (s, dims) in [
            [17, 9, 25],
            [16, 16, 16],
            [2, 3, 40],
            [33, 1, 2],
            [70, 35, 50],
        ]
        .into_iter()
        .flat_map(|d| [(0, d), (1, d)])
        {
            let size = [MACRO_CELL, LARGE_MACRO_CELL][s];
            let n: usize = dims.iter().product();
            let mut f: Vec<f32> = (0..n)
                .map(|i| match (i * 7919) % 311 {
                    1 => f32::NAN,
                    k => (k % 150) as f32,
                })
                .collect();
            let at = |[x, y, z]: [usize; 3]| x + dims[0] * (y + dims[1] * z);
            // A visible voxel on a cell border in x and z, and one inside a cell.
            f[at([size.min(dims[0] - 1), 0, (2 * size).min(dims[2] - 1)])] = 230.0;
            f[at([1, dims[1] - 1, 3.min(dims[2] - 1)])] = 230.0;
            let b: Vec<u8> = f
                .iter()
                .map(|&v| if v.is_nan() { 0 } else { v as u8 })
                .collect();
            let want = visibility_brute(&f, dims, size, &lut);
            for v in &want {
                seen[s][usize::from(*v)] += 1;
            }
            assert_eq!(
                visibility(&f, dims, size, &lut),
                want,
                "f32 {dims:?}, {size}"
            );
            assert_eq!(
                visibility(&b, dims, size, &lut),
                visibility_brute(&b, dims, size, &lut),
                "u8 {dims:?}, {size}"
            );
        }
        assert!(
            seen.iter().flatten().all(|&n| n > 0),
            "visible and invisible cells of both sizes: {seen:?}"
        );
    }

    #[test]
    fn chessboard_distance_matches_brute_force() {
        // A 3-D grid of macro cells and a flat one (the VDI walk's tiles).
        for cells in [[9, 7, 5], [23, 23, 1]] {
            let n = cells.iter().product::<usize>();
            for seed in 0..6u64 {
                // A few scattered visible cells (and none at all for seed 0).
                let visible: Vec<bool> = (0..n as u64)
                    .map(|c| seed > 0 && (c * 2654435761 + seed * 97) % (13 + seed * 7) == 0)
                    .collect();
                assert_eq!(
                    chessboard_distance(cells, &visible),
                    brute(cells, &visible),
                    "{cells:?}, seed {seed}"
                );
            }
        }
    }
}
