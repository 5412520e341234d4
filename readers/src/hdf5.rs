//! HDF5 datasets through the HDF Group's library (the `hdf5-metno` crate; Debian's
//! `libhdf5-dev`), behind the `hdf5` feature: a dataset of `(z, y, x)` is one volume, of
//! `(t, z, y, x)` a series. HDF5 itself says nothing of a grid, so a bare `.h5` file is read on
//! a unit grid at the origin (said in [`crate::Dataset::notes`]); an XDMF description
//! ([`crate::xdmf`]) places its datasets and may give each step its own.
//!
//! A step is read in slabs of whole z-planes (about 4 MiB) in the dataset's own type, any byte
//! order or filter (deflate, shuffle) undone by the library.

use crate::bytes::{Endian, Sample, Samples};
use crate::{check_grid, samples, Dataset, Options, ReadError, Source};
use glam::Vec3;
use hdf5::types::{FloatSize, IntSize, TypeDescriptor};
use insitu_core::Volume;
use std::path::{Path, PathBuf};

/// One step's samples: a dataset, and its index along t when it is a series.
#[derive(Clone, Debug)]
pub struct Part {
    /// The HDF5 file.
    pub file: PathBuf,
    /// The dataset's path in it.
    pub dataset: String,
    /// The step's index along the dataset's first dimension (a 4-D dataset).
    pub index: Option<usize>,
}

/// The steps of a field held in HDF5 datasets.
#[derive(Debug)]
pub struct Parts {
    parts: Vec<Part>,
}

fn library(path: &Path, what: &str, e: hdf5::Error) -> ReadError {
    ReadError::invalid(path, format!("{what}: {e}"))
}

fn sample_of(t: &TypeDescriptor) -> Option<Sample> {
    Some(match t {
        TypeDescriptor::Integer(IntSize::U1) => Sample::I8,
        TypeDescriptor::Integer(IntSize::U2) => Sample::I16,
        TypeDescriptor::Integer(IntSize::U4) => Sample::I32,
        TypeDescriptor::Integer(IntSize::U8) => Sample::I64,
        TypeDescriptor::Unsigned(IntSize::U1) => Sample::U8,
        TypeDescriptor::Unsigned(IntSize::U2) => Sample::U16,
        TypeDescriptor::Unsigned(IntSize::U4) => Sample::U32,
        TypeDescriptor::Unsigned(IntSize::U8) => Sample::U64,
        TypeDescriptor::Float(FloatSize::U4) => Sample::F32,
        TypeDescriptor::Float(FloatSize::U8) => Sample::F64,
        _ => return None,
    })
}

/// A dataset's shape and sample type.
///
/// # Errors
/// [`ReadError`] naming `file`: it cannot be opened, has no such dataset, or holds other
/// than numbers.
pub fn describe(file: &Path, dataset: &str) -> Result<(Vec<usize>, Sample), ReadError> {
    // A FIFO or device refused by name; a missing file is the library's to report.
    if file.exists() {
        crate::regular(file)?;
    }
    let f = hdf5::File::open(file).map_err(|e| library(file, "HDF5 cannot open it", e))?;
    let ds = f.dataset(dataset).map_err(|e| {
        ReadError::invalid(
            file,
            format!(
                "no dataset {dataset:?} ({e}); volumes here: {}",
                volumes(&f).join(", ")
            ),
        )
    })?;
    let t = ds
        .dtype()
        .and_then(|d| d.to_descriptor())
        .map_err(|e| library(file, &format!("dataset {dataset}"), e))?;
    let sample = sample_of(&t).ok_or_else(|| {
        ReadError::invalid(file, format!("dataset {dataset} holds {t}, not numbers"))
    })?;
    Ok((ds.shape(), sample))
}

/// The paths of every dataset of three or four dimensions, depth first (at most 4 096
/// members looked at).
fn volumes(f: &hdf5::File) -> Vec<String> {
    let mut out = Vec::new();
    let mut todo = vec![String::from("/")];
    let mut seen = 0;
    while let Some(g) = todo.pop() {
        let Ok(group) = f.group(&g) else { continue };
        let mut names = group.member_names().unwrap_or_default();
        names.reverse();
        for name in names {
            seen += 1;
            if seen > 4096 {
                return out;
            }
            let full = format!("{}/{name}", g.trim_end_matches('/'));
            if let Ok(ds) = group.dataset(&name) {
                if (3..=4).contains(&ds.ndim()) {
                    out.push(full);
                }
            } else {
                todo.push(full);
            }
        }
    }
    out.sort();
    out
}

/// Opens an HDF5 file, choosing the dataset `options.field` (a path such as `/fields/rho`;
/// else the first of three or four dimensions by path).
///
/// # Errors
/// [`ReadError`] naming the file: not HDF5, no such dataset, a dataset of other than three or
/// four dimensions, or of other than numbers.
pub fn open(path: &Path, options: &Options) -> Result<Dataset, ReadError> {
    if path.exists() {
        crate::regular(path)?;
    }
    let f = hdf5::File::open(path).map_err(|e| library(path, "HDF5 cannot open it", e))?;
    let fields = volumes(&f);
    drop(f);
    let name = match &options.field {
        Some(n) => n.clone(),
        None => fields
            .first()
            .cloned()
            .ok_or_else(|| ReadError::invalid(path, "no dataset of three or four dimensions"))?,
    };
    let (shape, _) = describe(path, &name)?;
    let (dims, steps) = match shape.as_slice() {
        [z, y, x] => ([*x, *y, *z], 1),
        [t, z, y, x] => ([*x, *y, *z], *t),
        other => {
            return Err(ReadError::invalid(
                path,
                format!("dataset {name} is {other:?}: a volume is (z, y, x) or (t, z, y, x)"),
            ))
        }
    };
    if steps == 0 {
        return Err(ReadError::invalid(
            path,
            format!("dataset {name} has no step"),
        ));
    }
    check_grid(path, dims, Vec3::ONE, Vec3::ZERO)?;
    let series = shape.len() == 4;
    let parts = (0..steps)
        .map(|t| Part {
            file: path.to_owned(),
            dataset: name.clone(),
            index: series.then_some(t),
        })
        .collect();
    Ok(Dataset {
        path: path.to_owned(),
        dims,
        steps,
        spacing: Vec3::ONE,
        origin: Vec3::ZERO,
        field: name,
        fields,
        notes: vec![
            "HDF5 says nothing of the grid: unit spacing from the origin (an XDMF .xmf \
             describing the file places it)"
                .into(),
        ],
        source: Source::Hdf5(Parts { parts }),
    })
}

impl Parts {
    /// The steps' parts, each checked to hold `dims` (x, y, z) samples.
    ///
    /// # Errors
    /// [`ReadError`] naming the file and dataset whose shape is not `dims` (or `[t] + dims`
    /// with the index inside t).
    pub fn checked(parts: Vec<Part>, dims: [usize; 3]) -> Result<Self, ReadError> {
        let want = [dims[2], dims[1], dims[0]];
        for p in &parts {
            let (shape, _) = describe(&p.file, &p.dataset)?;
            let ok = match (p.index, shape.as_slice()) {
                (None, s) => s == want,
                (Some(t), [n, rest @ ..]) => t < *n && rest == want,
                (Some(_), []) => false,
            };
            if !ok {
                return Err(ReadError::invalid(
                    &p.file,
                    format!(
                        "dataset {} is {shape:?} where (z, y, x) = {want:?}{} was described",
                        p.dataset,
                        p.index.map_or(String::new(), |t| format!(" at step {t}"))
                    ),
                ));
            }
        }
        Ok(Self { parts })
    }

    /// The number of steps.
    pub fn len(&self) -> usize {
        self.parts.len()
    }

    /// Whether there is no step.
    pub fn is_empty(&self) -> bool {
        self.parts.is_empty()
    }

    /// Step `t` as a volume of `dims` at `spacing`.
    pub(crate) fn read_step(
        &self,
        path: &Path,
        t: usize,
        dims: [usize; 3],
        spacing: Vec3,
    ) -> Result<Volume, ReadError> {
        let part = self
            .parts
            .get(t)
            .ok_or_else(|| ReadError::invalid(path, format!("no step {t}")))?;
        read_part(part, dims, spacing)
    }
}

/// A sample type HDF5 converts to, written out little-endian.
trait Le: hdf5::H5Type + Copy {
    const SAMPLE: Sample;
    fn put(self, out: &mut Vec<u8>);
}

macro_rules! le {
    ($($t:ty => $s:ident),*) => {$(
        impl Le for $t {
            const SAMPLE: Sample = Sample::$s;
            fn put(self, out: &mut Vec<u8>) {
                out.extend_from_slice(&self.to_le_bytes());
            }
        }
    )*};
}
le!(i8 => I8, u8 => U8, i16 => I16, u16 => U16, i32 => I32, u32 => U32, i64 => I64,
    u64 => U64, f32 => F32, f64 => F64);

fn read_part(part: &Part, dims: [usize; 3], spacing: Vec3) -> Result<Volume, ReadError> {
    let (_, sample) = describe(&part.file, &part.dataset)?;
    match sample {
        Sample::I8 => read_as::<i8>(part, dims, spacing),
        Sample::U8 => read_as::<u8>(part, dims, spacing),
        Sample::I16 => read_as::<i16>(part, dims, spacing),
        Sample::U16 => read_as::<u16>(part, dims, spacing),
        Sample::I32 => read_as::<i32>(part, dims, spacing),
        Sample::U32 => read_as::<u32>(part, dims, spacing),
        Sample::I64 => read_as::<i64>(part, dims, spacing),
        Sample::U64 => read_as::<u64>(part, dims, spacing),
        Sample::F32 => read_as::<f32>(part, dims, spacing),
        Sample::F64 => read_as::<f64>(part, dims, spacing),
    }
}

fn read_as<T: Le>(part: &Part, dims: [usize; 3], spacing: Vec3) -> Result<Volume, ReadError> {
    use hdf5::SliceOrIndex as S;
    let path = &part.file;
    if path.exists() {
        crate::regular(path)?;
    }
    let f = hdf5::File::open(path).map_err(|e| library(path, "HDF5 cannot open it", e))?;
    let ds = f
        .dataset(&part.dataset)
        .map_err(|e| library(path, &format!("dataset {}", part.dataset), e))?;
    let [nx, ny, nz] = dims;
    let n = samples(path, &dims)?;
    let plane = nx * ny * std::mem::size_of::<T>();
    let per_slab = (crate::bytes::PIECE / plane.max(1)).clamp(1, nz.max(1));
    let mut s = Samples::new(path, T::SAMPLE, Endian::Little, n, n)?;
    let mut bytes = Vec::with_capacity(per_slab * plane);
    let all = |n: usize| S::SliceCount {
        start: 0,
        step: 1,
        count: n,
        block: 1,
    };
    let mut z = 0;
    while z < nz {
        let k = per_slab.min(nz - z);
        let mut sel = vec![
            S::SliceCount {
                start: z,
                step: 1,
                count: k,
                block: 1,
            },
            all(ny),
            all(nx),
        ];
        if let Some(t) = part.index {
            sel.insert(0, S::Index(t));
        }
        let slab = ds
            .read_slice::<T, _, ndarray::IxDyn>(hdf5::Hyperslab::from(sel))
            .map_err(|e| {
                library(
                    path,
                    &format!("dataset {}, planes {z}..{}", part.dataset, z + k),
                    e,
                )
            })?;
        bytes.clear();
        for v in slab.iter() {
            v.put(&mut bytes);
        }
        s.push(&bytes)?;
        z += k;
    }
    s.finish(path, dims, spacing)
}
