//! Bricks laid out without a shared plane (docs/conventions.md, "A world of ranks"): blocks
//! that tile the grid's **points** without overlap, as one splits an array and as ADIOS2
//! writers lay blocks out (z 0–31 and 32–63 of 64 points). Their boxes leave the cells between
//! neighbours (z = 31 to 32) in no brick, so before its brick is made each one is **grown** by
//! one point on every axis where a neighbour starts one point past its end, the new points
//! copied from that neighbour's first plane. The grown bricks share their boundary planes, as
//! [`super::bricks::check`] requires, and the picture is the whole field's: every cell is
//! sampled from the brick holding its lower corner, with the same eight corner values.
//!
//! What a brick gives its lower neighbours is its **low faces** ([`low_faces`]): its first
//! plane on each axis where it does not start at 0, cut into disjoint pieces, about
//! `3 n²` points of an `n³` brick.

use super::bricks::{check, Brick, DecompositionError, Hole};
use super::voxels::{Storage, PAD};
use super::{Volume, VolumeError, VoxelSlice};

/// How a step's bricks tile the grid ([`tiling`]).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Tiling {
    /// Neighbours share their boundary plane: the bricks are made as they are.
    Shared,
    /// The bricks' points tile the grid without overlap; `grown[i]` is brick `i` grown by one
    /// point on each axis where a neighbour starts one point past its end (the grown bricks
    /// share their boundary planes).
    Disjoint(Vec<Brick>),
}

impl Tiling {
    /// The brick of `i` as it is made: grown, or as pushed.
    pub fn made(&self, i: usize, pushed: Brick) -> Brick {
        match self {
            Tiling::Shared => pushed,
            Tiling::Disjoint(grown) => grown.get(i).copied().unwrap_or(pushed),
        }
    }
}

/// Points of a brick, per axis `[o, o + n)`.
fn points(b: &Brick, a: usize) -> (usize, usize) {
    (b.offset[a], b.offset[a] + b.dims[a])
}

fn meet((a0, a1): (usize, usize), (b0, b1): (usize, usize)) -> bool {
    a0.max(b0) < a1.min(b1)
}

/// Whether `b` lies beside `a` along `axis`: their points meet on the two other axes.
fn beside(a: &Brick, b: &Brick, axis: usize) -> bool {
    (0..3)
        .filter(|&k| k != axis)
        .all(|k| meet(points(a, k), points(b, k)))
}

fn count(b: &Brick) -> u128 {
    b.dims.iter().map(|&n| n as u128).product()
}

/// How `bricks` (rank, brick) tile `global`: sharing boundary planes ([`check`] passes), or
/// tiling its points without overlap (each brick then grown, [`Tiling::Disjoint`]).
///
/// # Errors
/// [`check`]'s error when some bricks share points (a layout of shared planes that does not
/// tile); [`DecompositionError::Missing`] when the bricks share no point but leave points of
/// the grid in no brick, naming the first hole found beside a brick.
pub fn tiling(global: [usize; 3], bricks: &[(u32, Brick)]) -> Result<Tiling, DecompositionError> {
    let shared = match check(global, bricks, true) {
        Ok(()) => return Ok(Tiling::Shared),
        Err(e @ DecompositionError::Outside { .. }) => return Err(e),
        Err(e) => e,
    };
    let share_points = bricks.iter().enumerate().any(|(i, (_, a))| {
        bricks[i + 1..]
            .iter()
            .any(|(_, b)| (0..3).all(|k| meet(points(a, k), points(b, k))))
    });
    if share_points {
        return Err(shared);
    }
    let total: u128 = global.iter().map(|&n| n as u128).product();
    let held: u128 = bricks.iter().map(|(_, b)| count(b)).sum();
    if held != total {
        return Err(DecompositionError::Missing {
            ranks: bricks.iter().map(|(r, _)| *r).collect(),
            held,
            total,
            hole: hole(global, bricks),
        });
    }
    let grown: Vec<Brick> = bricks
        .iter()
        .map(|(_, a)| {
            let mut g = *a;
            for (axis, &n) in global.iter().enumerate() {
                let end = a.offset[axis] + a.dims[axis];
                let neighbour = bricks
                    .iter()
                    .any(|(_, b)| b.offset[axis] == end && beside(a, b, axis));
                if end < n && neighbour {
                    g.dims[axis] += 1;
                }
            }
            g
        })
        .collect();
    // Points that tile make grown bricks that tile the cells (each cell goes to the brick
    // holding its lower corner); checked all the same.
    let placed: Vec<(u32, Brick)> = bricks
        .iter()
        .zip(&grown)
        .map(|((r, _), g)| (*r, *g))
        .collect();
    check(global, &placed, true)?;
    Ok(Tiling::Disjoint(grown))
}

/// The first brick whose next point on some axis lies in no brick beside it.
fn hole(global: [usize; 3], bricks: &[(u32, Brick)]) -> Option<Hole> {
    bricks.iter().find_map(|&(rank, a)| {
        (0..3).find_map(|axis| {
            let end = a.offset[axis] + a.dims[axis];
            if end >= global[axis] {
                return None;
            }
            let next = bricks
                .iter()
                .filter(|(_, b)| beside(&a, b, axis) && b.offset[axis] + b.dims[axis] > end)
                .map(|(_, b)| b.offset[axis])
                .min()
                .unwrap_or(global[axis]);
            (next > end).then_some(Hole {
                rank,
                axis,
                first: end,
                last: next - 1,
            })
        })
    })
}

/// What `field` (the brick `brick` of the grid, placed as pushed) gives its lower
/// neighbours: its first plane on each axis where it does not start at 0, in disjoint
/// pieces (the x-face whole, the y-face without the x-face's row, the z-face without
/// either), each with its place in the grid. Values keep the field's type.
///
/// # Errors
/// [`VolumeError::Invalid`] when `brick`'s size is not `field`'s.
pub fn low_faces(field: &Volume, brick: &Brick) -> Result<Vec<(Brick, Volume)>, VolumeError> {
    if field.dims() != brick.dims {
        return Err(VolumeError::Invalid(format!(
            "brick of {:?} points holds a field of {:?}",
            brick.dims,
            field.dims()
        )));
    }
    let mut start = [0usize; 3];
    let mut out = Vec::new();
    for a in 0..3 {
        if brick.offset[a] == 0 {
            continue;
        }
        let mut local = Brick {
            offset: start,
            dims: std::array::from_fn(|k| brick.dims[k] - start[k]),
        };
        local.offset[a] = 0;
        local.dims[a] = 1;
        if !local.dims.contains(&0) {
            let piece = field.brick(&local)?;
            let place = Brick {
                offset: std::array::from_fn(|k| brick.offset[k] + local.offset[k]),
                dims: local.dims,
            };
            out.push((place, piece));
        }
        start[a] = 1;
    }
    Ok(out)
}

/// `field` (the points of `own`) grown to `grown` with the points it lacks copied from its
/// neighbours' [`low_faces`] (`pieces`, each with its place in the grid; pieces that do not
/// reach into `grown`, or lie inside `own`, are passed over), built a row at a time in the
/// memory of `spare` (a volume no longer needed, of the same type) where there is one: fresh
/// memory costs a page fault per 4 KiB, more than the copy. The result lies at `field`'s
/// origin, in its type.
///
/// # Errors
/// [`VolumeError::Invalid`] when `grown` does not contain `own`, `field` is not `own`'s size,
/// a piece's type or size differs, or the pieces leave a point of the grown brick unfilled (a
/// neighbour's faces missing) or fill one twice.
pub fn grow(
    field: &Volume,
    own: &Brick,
    grown: &Brick,
    pieces: &[(Brick, &Volume)],
    spare: Option<Volume>,
) -> Result<Volume, VolumeError> {
    let inside = (0..3).all(|a| {
        grown.offset[a] <= own.offset[a]
            && own.offset[a] + own.dims[a] <= grown.offset[a] + grown.dims[a]
    });
    if !inside || field.dims() != own.dims {
        return Err(VolumeError::Invalid(format!(
            "brick at {:?} of {:?} (field {:?}) cannot grow to {:?} of {:?}",
            own.offset,
            own.dims,
            field.dims(),
            grown.offset,
            grown.dims
        )));
    }
    let spare = spare.map(Volume::into_storage);
    let n = grown.dims.iter().product::<usize>();
    // One arm per stored type: the spare's memory of that type, the pieces' samples of it.
    macro_rules! grow_as {
        ($d:expr, $variant:ident, $extra:expr, $build:path) => {{
            let out = reuse(spare, n + $extra, |s| match s {
                Storage::$variant(v) => Some(v),
                _ => None,
            });
            let data = fill($d, own, grown, pieces, out, |v| match v {
                VoxelSlice::$variant(p) => Some(p),
                _ => None,
            })?;
            $build(grown.dims, field.spacing(), data)
        }};
    }
    let grown_volume = match field.voxels() {
        VoxelSlice::U8(d) => grow_as!(d, U8, PAD, Volume::from_u8),
        VoxelSlice::U16(d) => grow_as!(d, U16, PAD / 2, Volume::from_u16),
        VoxelSlice::I16(d) => grow_as!(d, I16, PAD / 2, Volume::from_i16),
        VoxelSlice::F32(d) => grow_as!(d, F32, 0, Volume::new),
    }?;
    let shift = glam::Vec3::new(
        own.offset[0] as f32 - grown.offset[0] as f32,
        own.offset[1] as f32 - grown.offset[1] as f32,
        own.offset[2] as f32 - grown.offset[2] as f32,
    );
    grown_volume.with_origin(field.origin() - shift * field.spacing())
}

/// An empty vector with room for `n`: `spare`'s memory when `take` finds it of the type.
fn reuse<T>(spare: Option<Storage>, n: usize, take: impl Fn(Storage) -> Option<Vec<T>>) -> Vec<T> {
    let mut v = spare.and_then(take).unwrap_or_default();
    v.clear();
    v.reserve(n);
    v
}

/// The grown brick's samples, row by row (x fastest): each row's runs from `own` and from
/// the pieces that hold them, which must cover the row once. `slice` takes a piece's samples
/// when they are of `own`'s type.
fn fill<'a, T: Copy + 'a>(
    own_data: &'a [T],
    own: &Brick,
    grown: &Brick,
    pieces: &[(Brick, &'a Volume)],
    mut out: Vec<T>,
    slice: impl Fn(VoxelSlice<'a>) -> Option<&'a [T]>,
) -> Result<Vec<T>, VolumeError> {
    let mut sources: Vec<(Brick, &[T])> = vec![(*own, own_data)];
    for (place, piece) in pieces {
        let Some(region) = intersection(place, grown) else {
            continue;
        };
        if intersection(&region, own) == Some(region) {
            // The brick's own face.
            continue;
        }
        let data = slice(piece.voxels()).filter(|_| piece.dims() == place.dims);
        let Some(data) = data else {
            return Err(VolumeError::Invalid(format!(
                "the face at {:?} of {:?} is not of the brick's type and size",
                place.offset, place.dims
            )));
        };
        sources.push((*place, data));
    }
    let within = |b: &Brick, a: usize, v: usize| b.offset[a] <= v && v < b.offset[a] + b.dims[a];
    let (x0, x1) = (grown.offset[0], grown.offset[0] + grown.dims[0]);
    let mut runs: Vec<(usize, usize, usize)> = Vec::with_capacity(sources.len());
    for z in grown.offset[2]..grown.offset[2] + grown.dims[2] {
        let in_z: Vec<usize> = (0..sources.len())
            .filter(|&k| within(&sources[k].0, 2, z))
            .collect();
        for y in grown.offset[1]..grown.offset[1] + grown.dims[1] {
            runs.clear();
            for &k in &in_z {
                let b = &sources[k].0;
                let (lo, hi) = (b.offset[0].max(x0), (b.offset[0] + b.dims[0]).min(x1));
                if within(b, 1, y) && lo < hi {
                    runs.push((lo, hi, k));
                }
            }
            runs.sort_unstable();
            let (mut x, mut twice) = (x0, false);
            for &(lo, hi, k) in &runs {
                if lo != x {
                    twice = lo < x;
                    x = lo.min(x);
                    break;
                }
                let (b, data) = sources[k];
                let at = ((z - b.offset[2]) * b.dims[1] + (y - b.offset[1])) * b.dims[0]
                    + (lo - b.offset[0]);
                out.extend_from_slice(&data[at..at + (hi - lo)]);
                x = hi;
            }
            if x != x1 || twice {
                return Err(VolumeError::Invalid(format!(
                    "brick at {:?} of {:?}: its neighbours' faces {} the point ({x}, {y}, {z}) of the brick it grows to, {:?}",
                    own.offset,
                    own.dims,
                    if twice { "hold twice" } else { "do not hold" },
                    grown.dims
                )));
            }
        }
    }
    Ok(out)
}

/// The points both boxes hold.
fn intersection(a: &Brick, b: &Brick) -> Option<Brick> {
    let r: [(usize, usize); 3] = std::array::from_fn(|k| {
        let (lo, hi) = (
            a.offset[k].max(b.offset[k]),
            (a.offset[k] + a.dims[k]).min(b.offset[k] + b.dims[k]),
        );
        (lo, hi.max(lo))
    });
    (r.iter().all(|(lo, hi)| hi > lo)).then(|| Brick {
        offset: r.map(|(lo, _)| lo),
        dims: r.map(|(lo, hi)| hi - lo),
    })
}

#[cfg(test)]
mod tests;
