//! The CF conventions as both NetCDF readers apply them (classic in [`crate::netcdf3`], netCDF-4
//! in `netcdf4`): packed values unpacked (`v · scale_factor + add_offset`), missing values
//! masked to NaN (`_FillValue`, `missing_value`, outside `valid_min`/`valid_max`/`valid_range`),
//! and the grid placed by the coordinate variables, an uneven axis resampled to an even grid
//! or kept by index ([`Uneven`]).

use crate::bytes::{Endian, Sample, Samples};
use crate::{check_grid, samples, Dataset, ReadError, Source};
use glam::Vec3;
use insitu_core::Volume;
use std::path::Path;

/// An uneven axis is resampled to at most this many times its levels.
const MAX_RESAMPLE_FACTOR: usize = 8;

/// How an uneven axis (an ocean model's depth levels) is taken.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Uneven {
    /// Resampled to an even grid at its smallest gap (at most 8× its levels), linearly.
    #[default]
    Resample,
    /// Its levels kept as samples one unit apart (the raw layout's convention).
    Index,
}

/// How a variable's stored values become the field's: CF packing and missing values.
#[derive(Clone, Debug)]
pub(crate) struct Packing {
    scale: f64,
    offset: f64,
    /// Raw values that mean "missing".
    missing: Vec<f64>,
    valid: (f64, f64),
    /// The values are f32 (a missing value is compared as f32 too).
    single: bool,
}

impl Packing {
    /// From a variable's attributes (`attr(name)`: its numeric values, if any) for values
    /// stored as `sample`.
    pub(crate) fn from_attrs(attr: impl Fn(&str) -> Option<Vec<f64>>, sample: Sample) -> Self {
        let first = |name: &str| attr(name).and_then(|v| v.first().copied());
        let mut missing: Vec<f64> = ["_FillValue", "missing_value"]
            .iter()
            .filter_map(|n| attr(n))
            .flatten()
            .collect();
        missing.dedup();
        let valid = match attr("valid_range").as_deref() {
            Some([lo, hi]) => (*lo, *hi),
            _ => (
                first("valid_min").unwrap_or(f64::NEG_INFINITY),
                first("valid_max").unwrap_or(f64::INFINITY),
            ),
        };
        Self {
            scale: first("scale_factor").unwrap_or(1.0),
            offset: first("add_offset").unwrap_or(0.0),
            missing,
            valid,
            single: sample == Sample::F32,
        }
    }

    /// Whether stored values are the field's values unchanged.
    fn is_identity(&self) -> bool {
        self.scale == 1.0
            && self.offset == 0.0
            && self.missing.is_empty()
            && self.valid == (f64::NEG_INFINITY, f64::INFINITY)
    }

    /// A stored value as the field holds it: NaN where it means missing (a fill or missing
    /// value, outside the valid range), else `v · scale + offset`.
    fn unpack(&self, v: f64) -> f32 {
        let missing = v.is_nan()
            || self
                .missing
                .iter()
                .any(|&m| m == v || (self.single && m as f32 == v as f32))
            || v < self.valid.0
            || v > self.valid.1;
        if missing {
            f32::NAN
        } else if self.scale == 1.0 && self.offset == 0.0 {
            v as f32
        } else {
            (v * self.scale + self.offset) as f32
        }
    }
}

/// A coordinate variable's values along one axis.
#[derive(Clone, Debug)]
pub(crate) struct Coordinate {
    /// The variable's name.
    pub name: String,
    /// Its values, one per level.
    pub values: Vec<f64>,
    /// Its `units` attribute.
    pub units: Option<String>,
}

/// One axis of a variable (x, y or z): its dimension's name and coordinate variable, if any.
pub(crate) struct Axis {
    pub dim: String,
    pub coordinate: Option<Coordinate>,
}

#[derive(Clone, Debug)]
struct Resample {
    coords: Vec<f64>,
    start: f64,
    step: f64,
    count: usize,
}

/// The grid a variable is read onto, and how to turn its stored samples into the field.
#[derive(Clone, Debug)]
pub(crate) struct Decode {
    sample: Sample,
    endian: Endian,
    packing: Packing,
    /// Per axis (x, y, z): the coordinates to resample from, when uneven and resampled.
    resample: [Option<Resample>; 3],
    /// The file's dims (x, y, z) before resampling.
    file_dims: [usize; 3],
}

/// A variable's grid as read: dims after resampling, spacing, origin, what was done.
pub(crate) struct Grid {
    pub dims: [usize; 3],
    pub spacing: Vec3,
    pub origin: Vec3,
    pub notes: Vec<String>,
    pub decode: Decode,
}

/// Places a variable of `file_dims` (x, y, z) stored as `sample` in `endian` by its `axes`
/// (x, y, z), an uneven axis taken as `uneven` says.
///
/// # Errors
/// [`ReadError`] naming `path` when the grid holds no sample or its spacing is not positive.
pub(crate) fn grid(
    path: &Path,
    file_dims: [usize; 3],
    axes: [Axis; 3],
    sample: Sample,
    endian: Endian,
    packing: Packing,
    uneven: Uneven,
) -> Result<Grid, ReadError> {
    let mut notes = Vec::new();
    let mut spacing = [1.0f32; 3];
    let mut origin = [0.0f32; 3];
    let mut resample: [Option<Resample>; 3] = [None, None, None];
    let mut dims = file_dims;
    let mut units = Vec::new();
    for (a, axis) in axes.into_iter().enumerate() {
        let Some(cv) = axis.coordinate else {
            notes.push(format!(
                "{} has no coordinate variable: unit spacing",
                axis.dim
            ));
            continue;
        };
        let n = file_dims[a];
        let coords = cv.values;
        if coords.len() != n {
            return Err(ReadError::invalid(
                path,
                format!(
                    "coordinate variable {} holds {} values for {n} levels",
                    cv.name,
                    coords.len()
                ),
            ));
        }
        if let Some(u) = cv.units {
            units.push(format!("{}: {u}", cv.name));
        }
        if n < 2 {
            origin[a] = coords.first().copied().unwrap_or(0.0) as f32;
            continue;
        }
        let gaps: Vec<f64> = coords.windows(2).map(|w| w[1] - w[0]).collect();
        let (lo, hi) = gaps
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &g| {
                (l.min(g), h.max(g))
            });
        if lo.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater)
            || !coords.iter().all(|c| c.is_finite())
        {
            notes.push(format!(
                "{} does not increase: taken by index (unit spacing)",
                cv.name
            ));
            continue;
        }
        if hi - lo <= 1e-4 * hi {
            spacing[a] = ((coords[n - 1] - coords[0]) / (n - 1) as f64) as f32;
            origin[a] = coords[0] as f32;
            continue;
        }
        match uneven {
            Uneven::Index => notes.push(format!(
                "{} is uneven ({lo} to {hi} apart): its {n} levels taken by index, one unit apart",
                cv.name
            )),
            Uneven::Resample => {
                let extent = coords[n - 1] - coords[0];
                let count = ((extent / lo).round() as usize + 1).min(MAX_RESAMPLE_FACTOR * n);
                let step = extent / (count - 1) as f64;
                notes.push(format!(
                    "{} is uneven ({lo} to {hi} apart): resampled linearly from {n} levels to {count} at {step} apart",
                    cv.name
                ));
                spacing[a] = step as f32;
                origin[a] = coords[0] as f32;
                dims[a] = count;
                resample[a] = Some(Resample {
                    start: coords[0],
                    coords,
                    step,
                    count,
                });
            }
        }
    }
    if !units.is_empty() {
        notes.push(format!("world units per axis: {}", units.join(", ")));
    }
    let (spacing, origin) = (Vec3::from(spacing), Vec3::from(origin));
    check_grid(path, dims, spacing, origin)?;
    Ok(Grid {
        dims,
        spacing,
        origin,
        notes,
        decode: Decode {
            sample,
            endian,
            packing,
            resample,
            file_dims,
        },
    })
}

impl Grid {
    /// The dataset of `steps` steps of `field` (one of `fields`) in `path` on this grid, read
    /// by the source `source` makes of the grid's decoder.
    pub(crate) fn dataset(
        self,
        path: &Path,
        steps: usize,
        field: String,
        fields: Vec<String>,
        source: impl FnOnce(Decode) -> Source,
    ) -> Dataset {
        Dataset {
            path: path.to_owned(),
            dims: self.dims,
            steps,
            spacing: self.spacing,
            origin: self.origin,
            field,
            fields,
            notes: self.notes,
            source: source(self.decode),
        }
    }
}

impl Decode {
    /// Samples in one step, as stored.
    pub(crate) fn stored_samples(&self, path: &Path) -> Result<usize, ReadError> {
        samples(path, &self.file_dims)
    }

    /// The stored dims (x, y, z), before resampling.
    #[cfg_attr(not(feature = "netcdf4"), allow(dead_code))]
    pub(crate) fn stored_dims(&self) -> [usize; 3] {
        self.file_dims
    }

    /// Bytes per stored sample.
    pub(crate) fn sample_size(&self) -> usize {
        self.sample.size()
    }

    /// One step as a volume of `dims` (after resampling) at `spacing`; `fill` hands the step's
    /// stored bytes to its argument in order, in pieces of whole samples.
    ///
    /// # Errors
    /// What `fill` returns; [`ReadError`] naming `path` when the bytes handed over are not one
    /// step's.
    pub(crate) fn volume(
        &self,
        path: &Path,
        dims: [usize; 3],
        spacing: Vec3,
        fill: impl FnOnce(&mut dyn FnMut(&[u8])) -> Result<(), ReadError>,
    ) -> Result<Volume, ReadError> {
        let n = self.stored_samples(path)?;
        if self.packing.is_identity() && self.resample.iter().all(Option::is_none) {
            let mut s = Samples::new(path, self.sample, self.endian, n, n)?;
            let mut failed = None;
            fill(&mut |bytes| {
                if failed.is_none() {
                    failed = s.push(bytes).err();
                }
            })?;
            return match failed {
                Some(e) => Err(e),
                None => s.finish(path, self.file_dims, spacing),
            };
        }
        // Unpacked and masked a piece at a time: the f32 field and one piece in memory.
        crate::limit::check(path, n, std::mem::size_of::<f32>())?;
        let mut data: Vec<f32> = Vec::with_capacity(n);
        fill(&mut |bytes| {
            data.extend(
                crate::bytes::values(bytes, self.sample, self.endian)
                    .into_iter()
                    .map(|v| self.packing.unpack(v)),
            );
        })?;
        if data.len() != n {
            return Err(ReadError::invalid(
                path,
                format!("{} samples read for a step of {n}", data.len()),
            ));
        }
        let mut cur = self.file_dims;
        for (a, r) in self.resample.iter().enumerate() {
            if let Some(r) = r {
                data = resample_axis(&data, cur, a, r);
                cur[a] = r.count;
            }
        }
        Volume::new(dims, spacing, data).map_err(|e| ReadError::invalid(path, e.to_string()))
    }
}

/// `data` (dims `dims`, x fastest) resampled along axis `a` to `r.count` even positions,
/// linearly between the two levels around each (NaN where either is NaN, except at a level
/// itself).
fn resample_axis(data: &[f32], dims: [usize; 3], a: usize, r: &Resample) -> Vec<f32> {
    let mut out_dims = dims;
    out_dims[a] = r.count;
    let stride = |d: [usize; 3]| [1, d[0], d[0] * d[1]];
    let (si, so) = (stride(dims), stride(out_dims));
    // For each output position along the axis: the level below and the weight of the one above.
    let weights: Vec<(usize, f32)> = (0..r.count)
        .map(|j| {
            let x = r.start + r.step * j as f64;
            let i = r
                .coords
                .partition_point(|&c| c <= x)
                .saturating_sub(1)
                .min(r.coords.len() - 2);
            let w = ((x - r.coords[i]) / (r.coords[i + 1] - r.coords[i])).clamp(0.0, 1.0);
            (i, w as f32)
        })
        .collect();
    let mut out = vec![0.0f32; out_dims.iter().product()];
    for z in 0..out_dims[2] {
        for y in 0..out_dims[1] {
            for x in 0..out_dims[0] {
                let p = [x, y, z];
                let (i, w) = weights[p[a]];
                let mut q = p;
                q[a] = i;
                let lo = data[q[0] * si[0] + q[1] * si[1] + q[2] * si[2]];
                q[a] = i + 1;
                let hi = data[q[0] * si[0] + q[1] * si[1] + q[2] * si[2]];
                out[x * so[0] + y * so[1] + z * so[2]] = if w == 0.0 {
                    lo
                } else if w == 1.0 {
                    hi
                } else {
                    lo + (hi - lo) * w
                };
            }
        }
    }
    out
}
