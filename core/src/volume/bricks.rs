//! Domain decomposition: a grid of `global` voxels cut into bricks, one per rank, and the
//! checks a step's bricks must pass before their pictures are composed (docs/conventions.md, "A world of ranks").
//!
//! Convention: neighbouring bricks **share their boundary plane of voxels** (a brick owning
//! voxels `o ..= o + n − 1` on an axis is followed by one starting at `o + n − 1`). A brick's
//! world box runs from its first to its last voxel centre, so with shared planes the bricks'
//! boxes tile the global box exactly; without them, the cell between two bricks would belong
//! to neither and show as a seam. A simulation with halo cells sends its owned voxels plus
//! the first halo plane on the upper side of each axis that has a neighbour. Bricks that tile
//! the points without sharing a plane (as arrays are split) are grown to this convention by
//! the generator-node that receives them ([`super::tiling`]) before they are made.

use super::{Volume, VolumeError, VoxelSlice};
use glam::Vec3;

/// One rank's part of the grid, voxels.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
pub struct Brick {
    /// First voxel in the whole grid.
    pub offset: [usize; 3],
    /// Size in voxels, each ≥ 1.
    pub dims: [usize; 3],
}

impl Brick {
    /// The brick's cells (between voxel centres) as half-open index ranges per axis:
    /// `[o, o + n − 1)`. Bricks that share only a boundary plane have disjoint cells.
    fn cells(&self) -> [(usize, usize); 3] {
        std::array::from_fn(|a| (self.offset[a], self.offset[a] + self.dims[a] - 1))
    }
}

/// A near-cubic split of `ranks` into `[sx, sy, sz]` with `sx·sy·sz = ranks`, like
/// `MPI_Dims_create` but weighted by the grid: each prime factor of `ranks`, largest first,
/// goes to the axis with the most cells per brick. Returns `None` when some axis would get
/// more bricks than it has cells (`dims − 1`).
pub fn split_ranks(ranks: usize, global: [usize; 3]) -> Option<[usize; 3]> {
    if ranks == 0 {
        return None;
    }
    let mut factors = Vec::new();
    let (mut n, mut p) = (ranks, 2);
    while n > 1 {
        if p * p > n {
            factors.push(n);
            break;
        }
        while n % p == 0 {
            factors.push(p);
            n /= p;
        }
        p += 1;
    }
    factors.sort_unstable_by(|a, b| b.cmp(a));
    let mut split = [1usize; 3];
    for f in factors {
        let axis = (0..3).max_by(|&a, &b| {
            let ca = global[a].saturating_sub(1) as f64 / split[a] as f64;
            let cb = global[b].saturating_sub(1) as f64 / split[b] as f64;
            ca.total_cmp(&cb).then(b.cmp(&a))
        })?;
        split[axis] *= f;
    }
    (0..3)
        .all(|a| split[a] <= global[a].saturating_sub(1).max(1))
        .then_some(split)
}

/// The bricks of `global` cut `split` times per axis, sharing boundary planes, as even as
/// integer planes allow; rank `k` is brick `(kx, ky, kz)` with `k = kx + sx·(ky + sy·kz)`.
/// Returns `None` when an axis is cut more often than it has cells.
pub fn grid_bricks(global: [usize; 3], split: [usize; 3]) -> Option<Vec<Brick>> {
    if (0..3).any(|a| split[a] == 0 || (split[a] > 1 && split[a] > global[a] - 1)) {
        return None;
    }
    // Brick k's points on an axis: from its first cut to the next, that plane included.
    Some(cut(split, |a, k| {
        if split[a] == 1 {
            (0, global[a])
        } else {
            let first = k * (global[a] - 1) / split[a];
            (first, (k + 1) * (global[a] - 1) / split[a] - first + 1)
        }
    }))
}

/// The `split[0]·split[1]·split[2]` bricks whose offset and size on axis `a` for the `k`-th
/// cut are `span(a, k)`, in rank order (x fastest).
fn cut(split: [usize; 3], span: impl Fn(usize, usize) -> (usize, usize)) -> Vec<Brick> {
    let mut out = Vec::with_capacity(split.iter().product());
    for kz in 0..split[2] {
        for ky in 0..split[1] {
            for kx in 0..split[0] {
                let r = [span(0, kx), span(1, ky), span(2, kz)];
                out.push(Brick {
                    offset: r.map(|(o, _)| o),
                    dims: r.map(|(_, n)| n),
                });
            }
        }
    }
    out
}

/// The blocks of `global` cut `split` times per axis **without** shared planes, as one splits
/// an array (and as ADIOS2 writers lay blocks out): each point in one block, as even as
/// integer planes allow, rank order as in [`grid_bricks`]. Such blocks are grown to share
/// their planes before they are made ([`super::tiling`]). Returns `None` when an axis is cut
/// more often than it has points.
pub fn block_bricks(global: [usize; 3], split: [usize; 3]) -> Option<Vec<Brick>> {
    if (0..3).any(|a| split[a] == 0 || split[a] > global[a]) {
        return None;
    }
    Some(cut(split, |a, k| {
        let first = k * global[a] / split[a];
        (first, (k + 1) * global[a] / split[a] - first)
    }))
}

/// A hole beside a brick: the points past its end on one axis, up to the next brick beside
/// it (or the grid's end), that no brick holds.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Hole {
    /// The rank whose brick the hole lies beside.
    pub rank: u32,
    /// The axis, 0–2 for x–y–z.
    pub axis: usize,
    /// The first point of the hole on that axis.
    pub first: usize,
    /// The last point of the hole.
    pub last: usize,
}

impl std::fmt::Display for Hole {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let axis = ["x", "y", "z"][self.axis.min(2)];
        write!(
            f,
            "beside rank {}'s brick, no brick holds the points {axis} = {}..={}",
            self.rank, self.first, self.last
        )
    }
}

/// What is wrong with a step's bricks.
#[derive(Debug, Clone, thiserror::Error, PartialEq, Eq)]
pub enum DecompositionError {
    /// A brick reaches outside the grid or has a zero size.
    #[error(
        "rank {rank}: brick at {offset:?} of {dims:?} voxels is not inside the grid of {global:?}"
    )]
    Outside {
        /// The rank.
        rank: u32,
        /// Its offset.
        offset: [usize; 3],
        /// Its size.
        dims: [usize; 3],
        /// The grid.
        global: [usize; 3],
    },
    /// Two bricks share more than a boundary plane.
    #[error("ranks {a} and {b}: bricks overlap (neighbours may share only their boundary plane)")]
    Overlap {
        /// One rank.
        a: u32,
        /// The other.
        b: u32,
    },
    /// The bricks leave part of the grid uncovered.
    #[error("the bricks of ranks {ranks:?} cover {covered} of the grid's {total} cells{}", .fix.as_ref().map(|f| format!(": {f}")).unwrap_or_default())]
    Gap {
        /// The ranks present.
        ranks: Vec<u32>,
        /// Cells covered.
        covered: u128,
        /// Cells of the grid.
        total: u128,
        /// Where the gap lies and how to close it, when it lies between two neighbouring
        /// bricks ([`GapFix`]).
        fix: Option<GapFix>,
    },
    /// Bricks that share no point (laid out without a shared plane) leave points of the grid
    /// in no brick ([`super::tiling::tiling`]).
    #[error("the bricks of ranks {ranks:?} hold {held} of the grid's {total} points{}", .hole.as_ref().map(|h| format!(": {h}")).unwrap_or_default())]
    Missing {
        /// The ranks present.
        ranks: Vec<u32>,
        /// Points held.
        held: u128,
        /// Points of the grid.
        total: u128,
        /// The first hole found beside a brick.
        hole: Option<Hole>,
    },
}

/// A gap between two neighbouring bricks that arrived apart: the lower brick ends one plane
/// short of its neighbour's first plane (blocks laid out without a shared plane, as array
/// splits and ADIOS2 writers lay them out). A generator-node that receives both fills it
/// ([`super::tiling`]); where they were made apart, the lower brick must repeat that plane.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct GapFix {
    /// The rank whose brick ends short.
    pub rank: u32,
    /// The axis, 0–2 for x–y–z.
    pub axis: usize,
    /// The brick's last point on that axis; the cells from it to the next point lie in no
    /// brick.
    pub last: usize,
    /// The brick's points on that axis now (it needs one more).
    pub points: usize,
}

impl std::fmt::Display for GapFix {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let axis = ["x", "y", "z"][self.axis.min(2)];
        write!(
            f,
            "the cells between {axis} = {} and {axis} = {} lie in no brick: a generator-node that receives both neighbours fills them, but these were made on different nodes; push them to one node, or let rank {}'s brick include {axis} = {} (n{axis} {}, not {})",
            self.last,
            self.last + 1,
            self.rank,
            self.last + 1,
            self.points + 1,
            self.points
        )
    }
}

/// The first brick that ends one point short of a neighbour: a brick starting at its last
/// point + 1 on one axis whose cells overlap it on the other two (`meet`: whether two bricks'
/// cells overlap along an axis, as [`check`] tests them).
fn gap_fix(
    bricks: &[(u32, Brick)],
    meet: impl Fn(&Brick, &Brick, usize) -> bool,
) -> Option<GapFix> {
    bricks.iter().find_map(|&(rank, a)| {
        (0..3).find_map(|axis| {
            let last = a.offset[axis] + a.dims[axis] - 1;
            let neighbour = bricks.iter().any(|(_, b)| {
                b.offset[axis] == last + 1 && (0..3).filter(|&k| k != axis).all(|k| meet(&a, b, k))
            });
            neighbour.then_some(GapFix {
                rank,
                axis,
                last,
                points: a.dims[axis],
            })
        })
    })
}

/// Checks that `bricks` (rank, brick) lie inside `global`, that their cells are disjoint
/// (neighbours share only a boundary plane) and, when `complete`, that they cover every
/// cell. A grid with a single voxel on some axis has no cells there; that axis is checked
/// on voxels instead.
///
/// # Errors
/// [`DecompositionError`] naming the ranks.
pub fn check(
    global: [usize; 3],
    bricks: &[(u32, Brick)],
    complete: bool,
) -> Result<(), DecompositionError> {
    for &(rank, b) in bricks {
        if (0..3).any(|a| b.dims[a] == 0 || b.offset[a] + b.dims[a] > global[a]) {
            return Err(DecompositionError::Outside {
                rank,
                offset: b.offset,
                dims: b.dims,
                global,
            });
        }
    }
    // Per axis: cells `[o, o + n − 1)`, or voxels `[o, o + n)` on a flat axis.
    let range = |b: &Brick, a: usize| {
        let (lo, hi) = b.cells()[a];
        if global[a] == 1 {
            (lo, hi + 1)
        } else {
            (lo, hi)
        }
    };
    let measure = |b: &Brick| -> u128 {
        (0..3)
            .map(|a| {
                let (lo, hi) = range(b, a);
                (hi - lo) as u128
            })
            .product()
    };
    // Whether two bricks' cells overlap along axis `k`.
    let meet = |a: &Brick, b: &Brick, k: usize| {
        let (a0, a1) = range(a, k);
        let (b0, b1) = range(b, k);
        a0.max(b0) < a1.min(b1)
    };
    for (i, (ra, a)) in bricks.iter().enumerate() {
        for (rb, b) in &bricks[i + 1..] {
            let overlaps = (0..3).all(|k| meet(a, b, k));
            if overlaps || (a == b && measure(a) == 0) {
                return Err(DecompositionError::Overlap { a: *ra, b: *rb });
            }
        }
    }
    if complete {
        let total: u128 = (0..3)
            .map(|a| global[a].saturating_sub(1).max(usize::from(global[a] == 1)) as u128)
            .product();
        let covered: u128 = bricks.iter().map(|(_, b)| measure(b)).sum();
        if covered != total {
            return Err(DecompositionError::Gap {
                ranks: bricks.iter().map(|(r, _)| *r).collect(),
                covered,
                total,
                fix: gap_fix(bricks, meet),
            });
        }
    }
    Ok(())
}

/// The brick covering `a` and `b` when together they are one box: equal on two axes and
/// sharing their boundary plane on the third (interiors disjoint, as [`check`] requires).
pub fn merged(a: &Brick, b: &Brick) -> Option<Brick> {
    (0..3).find_map(|axis| merged_along(a, b, axis))
}

/// [`merged`] when `a` and `b` meet across `axis`.
fn merged_along(a: &Brick, b: &Brick, axis: usize) -> Option<Brick> {
    let same = |k: usize| a.offset[k] == b.offset[k] && a.dims[k] == b.dims[k];
    if (0..3).any(|k| k != axis && !same(k)) {
        return None;
    }
    let (lo, hi) = if a.offset[axis] < b.offset[axis] {
        (a, b)
    } else {
        (b, a)
    };
    (lo.offset[axis] + lo.dims[axis] - 1 == hi.offset[axis]).then(|| {
        let mut dims = lo.dims;
        dims[axis] = hi.offset[axis] + hi.dims[axis] - lo.offset[axis];
        Brick {
            offset: lo.offset,
            dims,
        }
    })
}

/// The bricks of one host (several ranks on one generator-node) gathered into boxes: groups
/// that together form one box ([`merged`]) are merged across x first, then y, then z, and
/// again until no two merge. Each group is `(indices into bricks, ascending; its box)`,
/// groups ordered by their first index. A grid of `a × b × c` bricks (as [`grid_bricks`]
/// cuts) is one group, and a run of consecutive ranks of such a grid (MPI's block placement)
/// at most five (the partial row and partial layer at either end, the whole layers between);
/// a host whose bricks are not one box gets several groups. A box is what the next level of composition needs:
/// ray entry order per pixel is exact for disjoint convex boxes (`core::compose`).
///
/// Time `O(n³)` for `n` bricks (a host serves at most a few hundred ranks).
pub fn box_groups(bricks: &[Brick]) -> Vec<(Vec<usize>, Brick)> {
    let mut groups: Vec<(Vec<usize>, Brick)> = bricks
        .iter()
        .enumerate()
        .map(|(i, b)| (vec![i], *b))
        .collect();
    loop {
        let before = groups.len();
        for axis in 0..3 {
            while let Some((i, j, b)) = (0..groups.len()).find_map(|i| {
                (i + 1..groups.len())
                    .find_map(|j| merged_along(&groups[i].1, &groups[j].1, axis).map(|b| (i, j, b)))
            }) {
                let (members, _) = groups.remove(j);
                groups[i].0.extend(members);
                groups[i].0.sort_unstable();
                groups[i].1 = b;
            }
        }
        if groups.len() == before {
            break;
        }
    }
    groups.sort_by_key(|(members, _)| members[0]);
    groups
}

impl Volume {
    /// The brick `b` of this volume as a volume of its own, placed at its world position
    /// (origin + offset · spacing).
    ///
    /// # Errors
    /// [`VolumeError::Invalid`] when the brick is empty or reaches outside the volume.
    pub fn brick(&self, b: &Brick) -> Result<Volume, VolumeError> {
        let [nx, ny, _] = self.dims;
        if (0..3).any(|a| b.dims[a] == 0 || b.offset[a] + b.dims[a] > self.dims[a]) {
            return Err(VolumeError::Invalid(format!(
                "brick at {:?} of {:?} voxels is not inside {:?}",
                b.offset, b.dims, self.dims
            )));
        }
        // The brick's rows, in the volume's own type.
        fn rows<T: Copy>(d: &[T], b: &Brick, nx: usize, ny: usize) -> Vec<T> {
            let mut data = Vec::with_capacity(b.dims.iter().product());
            for z in b.offset[2]..b.offset[2] + b.dims[2] {
                for y in b.offset[1]..b.offset[1] + b.dims[1] {
                    let row = (z * ny + y) * nx;
                    data.extend_from_slice(&d[row + b.offset[0]..row + b.offset[0] + b.dims[0]]);
                }
            }
            data
        }
        let offset = Vec3::new(b.offset[0] as f32, b.offset[1] as f32, b.offset[2] as f32);
        let brick = match self.voxels() {
            VoxelSlice::U8(d) => Volume::from_u8(b.dims, self.spacing, rows(d, b, nx, ny)),
            VoxelSlice::U16(d) => Volume::from_u16(b.dims, self.spacing, rows(d, b, nx, ny)),
            VoxelSlice::I16(d) => Volume::from_i16(b.dims, self.spacing, rows(d, b, nx, ny)),
            VoxelSlice::F32(d) => Volume::new(b.dims, self.spacing, rows(d, b, nx, ny)),
        }?;
        brick.with_origin(self.origin + offset * self.spacing)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grid_bricks_tile_the_grid_and_pass_the_checks() {
        for (global, ranks) in [
            ([19, 17, 23], 1),
            ([19, 17, 23], 4),
            ([64, 64, 64], 8),
            ([64, 64, 64], 12),
            ([33, 9, 5], 6),
            ([256, 256, 256], 64),
        ] {
            let split = split_ranks(ranks, global).unwrap();
            assert_eq!(split.iter().product::<usize>(), ranks, "{global:?} {ranks}");
            let bricks = grid_bricks(global, split).unwrap();
            assert_eq!(bricks.len(), ranks);
            let ranked: Vec<(u32, Brick)> = bricks
                .iter()
                .enumerate()
                .map(|(k, b)| (k as u32, *b))
                .collect();
            check(global, &ranked, true).unwrap();
            // Dropping one brick leaves a gap; complete = false accepts the rest.
            if ranks > 1 {
                assert!(matches!(
                    check(global, &ranked[1..], true),
                    Err(DecompositionError::Gap { .. })
                ));
                check(global, &ranked[1..], false).unwrap();
            }
        }
        assert_eq!(split_ranks(4, [256, 256, 3]), Some([2, 2, 1]));
        assert_eq!(split_ranks(5, [4, 4, 4]), None, "5 bricks on 3 cells");
    }

    #[test]
    fn overlapping_outside_and_gapped_bricks_are_named() {
        let g = [10, 10, 10];
        let a = Brick {
            offset: [0, 0, 0],
            dims: [10, 10, 6],
        };
        let b = Brick {
            offset: [0, 0, 4],
            dims: [10, 10, 6],
        };
        assert_eq!(
            check(g, &[(0, a), (1, b)], true),
            Err(DecompositionError::Overlap { a: 0, b: 1 })
        );
        let c = Brick {
            offset: [0, 0, 6],
            dims: [10, 10, 5],
        };
        assert!(matches!(
            check(g, &[(0, a), (1, c)], true),
            Err(DecompositionError::Outside { rank: 1, .. })
        ));
        let d = Brick {
            offset: [0, 0, 6],
            dims: [10, 10, 4],
        };
        // Sharing the plane z = 5 is the convention, not an overlap.
        let e = Brick {
            offset: [0, 0, 5],
            dims: [10, 10, 5],
        };
        check(g, &[(0, a), (1, e)], true).unwrap();
        // Disjoint voxels leave the cells between z = 5 and z = 6 uncovered: rank 0's brick
        // must repeat z = 6.
        let gap = check(g, &[(0, a), (1, d)], true).unwrap_err();
        let DecompositionError::Gap { fix, covered, .. } = &gap else {
            panic!("{gap:?}")
        };
        assert_eq!(*covered, 9 * 9 * 8);
        assert_eq!(
            fix,
            &Some(GapFix {
                rank: 0,
                axis: 2,
                last: 5,
                points: 6
            })
        );
        assert!(
            gap.to_string().ends_with(
                "the cells between z = 5 and z = 6 lie in no brick: a generator-node that receives both neighbours fills them, but these were made on different nodes; push them to one node, or let rank 0's brick include z = 6 (nz 7, not 6)"
            ),
            "{gap}"
        );
        // The fix makes the bricks tile the grid.
        let fixed = Brick {
            dims: [10, 10, 7],
            ..a
        };
        check(g, &[(0, fixed), (1, d)], true).unwrap();
        // A missing brick (nothing starts where the last one ends) has no such fix.
        let half = Brick {
            offset: [0, 0, 0],
            dims: [10, 5, 10],
        };
        assert!(matches!(
            check(g, &[(0, half)], true),
            Err(DecompositionError::Gap { fix: None, .. })
        ));
        // Side by side on x with a gap, each half of y: the fix names the axis and the rank.
        let left = Brick {
            offset: [0, 0, 0],
            dims: [5, 10, 10],
        };
        let right = Brick {
            offset: [5, 0, 0],
            dims: [5, 10, 10],
        };
        let DecompositionError::Gap { fix, .. } =
            check(g, &[(3, left), (4, right)], true).unwrap_err()
        else {
            panic!()
        };
        assert_eq!(
            fix,
            Some(GapFix {
                rank: 3,
                axis: 0,
                last: 4,
                points: 5
            })
        );
    }

    #[test]
    fn a_host_s_bricks_gather_into_boxes_that_tile_what_they_cover() {
        let global = [33, 29, 41];
        for split in [[2, 2, 2], [4, 1, 1], [3, 2, 1], [1, 3, 4], [2, 3, 2]] {
            let bricks = grid_bricks(global, split).unwrap();
            // A whole grid of bricks is one box: the grid itself.
            let all = box_groups(&bricks);
            assert_eq!(all.len(), 1, "{split:?}");
            assert_eq!(all[0].0, (0..bricks.len()).collect::<Vec<_>>());
            let whole = Brick {
                offset: [0; 3],
                dims: global,
            };
            assert_eq!(all[0].1, whole);
            // Every run of consecutive ranks (a host of MPI's block placement), boxes or not.
            for start in 0..bricks.len() {
                for end in start + 1..=bricks.len() {
                    let host = &bricks[start..end];
                    let groups = box_groups(host);
                    let mut members: Vec<usize> =
                        groups.iter().flat_map(|(m, _)| m.clone()).collect();
                    members.sort_unstable();
                    assert_eq!(members, (0..host.len()).collect::<Vec<_>>());
                    for (m, b) in &groups {
                        // The group's box holds exactly its members: same cells, none twice.
                        let inner: Vec<(u32, Brick)> =
                            m.iter().map(|&i| (i as u32, host[i])).collect();
                        check(global, &inner, false).unwrap();
                        let cells = |b: &Brick| -> usize {
                            b.cells().iter().map(|(lo, hi)| hi - lo).product()
                        };
                        let sum: usize = m.iter().map(|&i| cells(&host[i])).sum();
                        assert_eq!(cells(b), sum, "{split:?} {start}..{end}");
                    }
                    // A run of consecutive ranks: a partial row, partial layer and whole
                    // layers before it and after it, at most 5 boxes.
                    assert!(groups.len() <= 5, "{split:?} {start}..{end}: {groups:?}");
                    // The groups' boxes are themselves a valid decomposition of that part.
                    let boxes: Vec<(u32, Brick)> =
                        groups.iter().map(|(m, b)| (m[0] as u32, *b)).collect();
                    check(global, &boxes, false).unwrap();
                }
            }
        }
        // Three of a 2 × 2 grid (an L) are two boxes; the lone brick stays alone.
        let quad = grid_bricks([9, 9, 2], [2, 2, 1]).unwrap();
        let l = box_groups(&[quad[0], quad[1], quad[2]]);
        assert_eq!(l.len(), 2);
        assert_eq!((l[0].0.clone(), l[1].0.clone()), (vec![0, 1], vec![2]));
        assert_eq!(box_groups(&quad[3..]), vec![(vec![0], quad[3])]);
        // Diagonal neighbours and bricks with a gap between them do not merge.
        assert_eq!(box_groups(&[quad[0], quad[3]]).len(), 2);
        assert_eq!(merged(&quad[0], &quad[0]), None);
    }

    #[test]
    fn a_brick_is_the_same_voxels_at_its_world_position() {
        let v = Volume::from_fn([5, 4, 3], |x, y, z| (x + 10 * y + 100 * z) as f32).unwrap();
        let b = v
            .brick(&Brick {
                offset: [1, 2, 1],
                dims: [3, 2, 2],
            })
            .unwrap();
        assert_eq!(b.origin(), Vec3::new(1.0, 2.0, 1.0));
        assert_eq!(b.data()[0], 121.0);
        assert_eq!(*b.data().last().unwrap(), 233.0);
        assert!(v
            .brick(&Brick {
                offset: [3, 0, 0],
                dims: [3, 1, 1]
            })
            .is_err());
    }
}
