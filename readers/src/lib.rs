//! Volume readers for the files simulations and their tools write, each giving the grid's
//! dims, spacing, origin, its fields and (for a time series) its steps, and one step at a time
//! as an [`insitu_core::Volume`] placed at its origin (docs/data.md):
//!
//! | extension | format | module |
//! | --- | --- | --- |
//! | `.raw` | our raw layout, dims and type in the name | [`raw`] |
//! | `.nc` | NetCDF classic (CDF-1, CDF-2, CDF-5), CF conventions | [`netcdf3`] |
//! | `.nc`, `.nc4` (HDF5 inside) | netCDF-4, CF conventions (feature `netcdf4`) | `netcdf4` |
//! | `.nrrd`, `.nhdr` | NRRD, attached or detached, raw or gzip | [`nrrd`] |
//! | `.vti` | VTK XML ImageData: ASCII, base64, appended raw, zlib blocks | [`vti`] |
//! | `.vtk` | legacy VTK STRUCTURED_POINTS, ASCII or binary | [`legacy_vtk`] |
//! | `.h5`, `.hdf5` | an HDF5 dataset (feature `hdf5`) | `hdf5` |
//! | `.xmf`, `.xdmf` | XDMF: a 3DCoRectMesh over HDF5 datasets (reading: feature `hdf5`) | [`xdmf`] |
//! | `.bp`, `.bp4`, `.bp5` | ADIOS2 BP files: a 3-D global array per step (feature `adios2`) | `adios2` |
//!
//! The readers of netCDF-4 and HDF5 link Unidata's netCDF-C and the HDF Group's HDF5 (Debian's
//! `libnetcdf-dev`, `libhdf5-dev`) and are built only with their features; without them such a
//! file is refused with the feature to turn on. The rest are pure Rust (core never links a C
//! library), and every reader refuses a truncated file, a
//! size that does not add up, a layout it does not read or a bad attribute with a
//! [`ReadError`] naming the file and the problem; none panics on any input (fuzzed).

#![cfg_attr(test, allow(clippy::unwrap_used, clippy::expect_used))]

#[cfg(feature = "adios2")]
pub mod adios2;
pub mod bytes;
mod cf;
#[cfg(feature = "hdf5")]
pub mod hdf5;
pub mod legacy_vtk;
pub mod limit;
pub mod netcdf3;
#[cfg(feature = "netcdf4")]
pub mod netcdf4;
pub mod nrrd;
pub mod raw;
pub mod vti;
pub mod xdmf;

pub use cf::Uneven;
use glam::Vec3;
use insitu_core::Volume;
use std::path::{Path, PathBuf};

/// Why a file could not be read.
#[derive(Debug, thiserror::Error)]
pub enum ReadError {
    /// The file could not be read.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// The file is not what its format says, or not a layout this reader takes.
    #[error("{path}: {problem}")]
    Invalid {
        /// The file.
        path: PathBuf,
        /// What is wrong, naming the field or attribute.
        problem: String,
    },
}

impl ReadError {
    pub(crate) fn invalid(path: &Path, problem: impl Into<String>) -> Self {
        Self::Invalid {
            path: path.to_owned(),
            problem: problem.into(),
        }
    }

    pub(crate) fn io(path: &Path) -> impl FnOnce(std::io::Error) -> Self + '_ {
        move |source| Self::Io {
            path: path.to_owned(),
            source,
        }
    }
}

/// What to read from a file that holds several fields.
#[derive(Clone, Debug, Default)]
pub struct Options {
    /// The field (VTK array, NetCDF variable, raw: ignored); none: the first (NetCDF: the first
    /// variable with three or four dimensions that is not a coordinate).
    pub field: Option<String>,
    /// How an uneven NetCDF axis is taken.
    pub uneven: Uneven,
}

/// An opened file: its grid and fields, read one step at a time.
#[derive(Debug)]
pub struct Dataset {
    /// The file.
    pub path: PathBuf,
    /// Samples per axis (x, y, z).
    pub dims: [usize; 3],
    /// Steps (1 for a single volume).
    pub steps: usize,
    /// Distance between samples per axis, world units.
    pub spacing: Vec3,
    /// World position of the first sample.
    pub origin: Vec3,
    /// The field read.
    pub field: String,
    /// Every field the file holds (on this grid).
    pub fields: Vec<String>,
    /// What was done to fit the grid, for the user (e.g. an uneven axis taken by index).
    pub notes: Vec<String>,
    source: Source,
}

#[derive(Debug)]
enum Source {
    Raw(raw::Raw),
    NetCdf(Box<netcdf3::Variable>),
    #[cfg(feature = "netcdf4")]
    NetCdf4(Box<netcdf4::Variable>),
    #[cfg(feature = "hdf5")]
    Hdf5(hdf5::Parts),
    Nrrd(nrrd::Nrrd),
    Vti(vti::Vti),
    LegacyVtk(legacy_vtk::LegacyVtk),
    #[cfg(feature = "adios2")]
    Adios2(Box<adios2::File>),
    #[cfg(feature = "adios2")]
    Adios2Series(adios2::Series),
}

impl Dataset {
    /// Step `t` (from 0) as a volume at the file's origin and spacing.
    ///
    /// # Errors
    /// [`ReadError`] naming the file: `t` past the last step, a truncated or malformed body.
    pub fn read_step(&self, t: usize) -> Result<Volume, ReadError> {
        if t >= self.steps {
            return Err(ReadError::invalid(
                &self.path,
                format!(
                    "step {t} asked of {} steps (0 to {})",
                    self.steps,
                    self.steps - 1
                ),
            ));
        }
        let volume = match &self.source {
            Source::Raw(r) => r.read_step(&self.path, t, self.spacing)?,
            Source::NetCdf(v) => v.read_step(&self.path, t, self.dims, self.spacing)?,
            #[cfg(feature = "netcdf4")]
            Source::NetCdf4(v) => v.read_step(&self.path, t, self.dims, self.spacing)?,
            #[cfg(feature = "hdf5")]
            Source::Hdf5(p) => p.read_step(&self.path, t, self.dims, self.spacing)?,
            Source::Nrrd(n) => n.read(&self.path, self.dims, self.spacing)?,
            Source::Vti(v) => v.read(&self.path, self.dims, self.spacing)?,
            Source::LegacyVtk(v) => v.read(&self.path, self.dims, self.spacing)?,
            #[cfg(feature = "adios2")]
            Source::Adios2(f) => f.read_step(t, self.dims, self.spacing)?,
            #[cfg(feature = "adios2")]
            Source::Adios2Series(s) => s.read_step(t, self)?,
        };
        volume
            .with_origin(self.origin)
            .map_err(|e| ReadError::invalid(&self.path, e.to_string()))
    }
}

/// The formats [`open`] reads, by extension.
pub const EXTENSIONS: &[&str] = &[
    "raw", "nc", "nc4", "nrrd", "nhdr", "vti", "vtk", "h5", "hdf5", "xmf", "xdmf", "bp", "bp4",
    "bp5",
];

/// Opens `path`, choosing the reader by its extension.
///
/// # Errors
/// [`ReadError`] naming the file: an unknown extension (listing the known ones), or what the
/// format's reader finds wrong.
pub fn open(path: &Path, options: &Options) -> Result<Dataset, ReadError> {
    let ext = path
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default();
    // Each reader opens its files through `open_file` (FIFOs and devices refused by name); the
    // raw layout is read by the core.
    match ext.as_str() {
        "raw" => raw::open(path).and_then(|d| regular(path).map(|()| d)),
        "nc" | "nc4" if is_hdf5(path)? => open_netcdf4(path, options),
        "nc" => netcdf3::open(path, options),
        "nrrd" | "nhdr" => nrrd::open(path),
        "vti" => vti::open(path, options),
        "vtk" => legacy_vtk::open(path, options),
        "h5" | "hdf5" => open_hdf5(path, options),
        "xmf" | "xdmf" => xdmf::open(path, options),
        "bp" | "bp4" | "bp5" => open_adios2(path, options),
        other => Err(ReadError::invalid(
            path,
            format!(
                "unknown volume format {:?}: expected one of .{}",
                other,
                EXTENSIONS.join(", .")
            ),
        )),
    }
}

/// Opens `path` for reading if it is a regular file (a symlink to one included): a FIFO, a
/// socket or a device would block the reader or never end, a directory is no volume.
///
/// # Errors
/// [`ReadError::Io`] when it cannot be inspected or opened, [`ReadError::Invalid`] naming
/// what it is when it is not a regular file.
pub(crate) fn open_file(path: &Path) -> Result<std::fs::File, ReadError> {
    regular(path)?;
    std::fs::File::open(path).map_err(ReadError::io(path))
}

/// The whole of `path`, a regular file.
///
/// # Errors
/// As [`open_file`].
pub(crate) fn read_file(path: &Path) -> Result<Vec<u8>, ReadError> {
    let mut bytes = Vec::new();
    std::io::Read::read_to_end(&mut open_file(path)?, &mut bytes).map_err(ReadError::io(path))?;
    Ok(bytes)
}

/// Refuses what is not a regular file, naming what it is.
///
/// # Errors
/// As [`open_file`].
pub(crate) fn regular(path: &Path) -> Result<(), ReadError> {
    let kind = std::fs::metadata(path)
        .map_err(ReadError::io(path))?
        .file_type();
    if kind.is_file() {
        return Ok(());
    }
    let what = if kind.is_dir() {
        "a directory"
    } else if is_fifo(&kind) {
        "a FIFO (named pipe)"
    } else {
        "not a regular file (a device or socket)"
    };
    Err(ReadError::invalid(
        path,
        format!("{what}: volumes are read from regular files"),
    ))
}

#[cfg(unix)]
fn is_fifo(kind: &std::fs::FileType) -> bool {
    std::os::unix::fs::FileTypeExt::is_fifo(kind)
}

#[cfg(not(unix))]
fn is_fifo(_: &std::fs::FileType) -> bool {
    false
}

/// Whether the file starts with HDF5's signature (a netCDF-4 file does).
fn is_hdf5(path: &Path) -> Result<bool, ReadError> {
    let mut magic = [0u8; 8];
    let mut f = open_file(path)?;
    let n = std::io::Read::read(&mut f, &mut magic).map_err(ReadError::io(path))?;
    Ok(magic[..n] == *b"\x89HDF\r\n\x1a\n")
}

#[cfg(feature = "netcdf4")]
fn open_netcdf4(path: &Path, options: &Options) -> Result<Dataset, ReadError> {
    netcdf4::open(path, options)
}

#[cfg(not(feature = "netcdf4"))]
fn open_netcdf4(path: &Path, _: &Options) -> Result<Dataset, ReadError> {
    Err(ReadError::invalid(
        path,
        "a netCDF-4 (HDF5) file: this build reads NetCDF classic only; build with \
         `--features netcdf4` (needs Debian's libnetcdf-dev) to read it",
    ))
}

#[cfg(feature = "hdf5")]
fn open_hdf5(path: &Path, options: &Options) -> Result<Dataset, ReadError> {
    hdf5::open(path, options)
}

#[cfg(not(feature = "hdf5"))]
fn open_hdf5(path: &Path, _: &Options) -> Result<Dataset, ReadError> {
    Err(ReadError::invalid(
        path,
        "an HDF5 file: this build reads HDF5 only with `--features hdf5` (needs Debian's \
         libhdf5-dev)",
    ))
}

#[cfg(feature = "adios2")]
fn open_adios2(path: &Path, options: &Options) -> Result<Dataset, ReadError> {
    if adios2::is_series(path) {
        adios2::open_series(path, options)
    } else {
        adios2::open(path, options)
    }
}

#[cfg(not(feature = "adios2"))]
fn open_adios2(path: &Path, _: &Options) -> Result<Dataset, ReadError> {
    Err(ReadError::invalid(
        path,
        "an ADIOS2 BP file: this build reads ADIOS2 only with `--features adios2` (needs \
         ADIOS2's C library: `pip install adios2` and ADIOS2_DIR set to its package \
         directory, or an ADIOS2 install)",
    ))
}

/// Grid spacing as files give it: every component finite and positive.
pub(crate) fn check_grid(
    path: &Path,
    dims: [usize; 3],
    spacing: Vec3,
    origin: Vec3,
) -> Result<(), ReadError> {
    if dims.contains(&0) {
        return Err(ReadError::invalid(
            path,
            format!("dims {dims:?} hold no sample"),
        ));
    }
    if !spacing.is_finite() || spacing.min_element() <= 0.0 {
        return Err(ReadError::invalid(
            path,
            format!("spacing {spacing} must be finite and positive"),
        ));
    }
    if !origin.is_finite() {
        return Err(ReadError::invalid(
            path,
            format!("origin {origin} is not finite"),
        ));
    }
    Ok(())
}

/// Whitespace-separated numbers in `text` (an XML attribute or element), exactly `n` of them.
///
/// # Errors
/// [`ReadError`] naming `path` and `what` when one is not a number or the count differs.
pub(crate) fn numbers(
    path: &Path,
    what: &str,
    text: &str,
    n: usize,
) -> Result<Vec<f64>, ReadError> {
    let v: Vec<f64> = text
        .split_whitespace()
        .map(str::parse)
        .collect::<Result<_, _>>()
        .map_err(|_| ReadError::invalid(path, format!("{what} {text:?} is not numbers")))?;
    if v.len() != n {
        return Err(ReadError::invalid(
            path,
            format!("{what} {text:?} needs {n} numbers"),
        ));
    }
    Ok(v)
}

/// Which of `names` (a file's fields, in order) to read: `wanted`, else the first. `what` is
/// the fields' kind as the error names it ("point-data array", "SCALARS array").
///
/// # Errors
/// [`ReadError`] naming the file: `wanted` is not among `names` (which it lists), or there is
/// no field at all.
pub(crate) fn chosen(
    path: &Path,
    names: &[String],
    wanted: Option<&str>,
    what: &str,
) -> Result<usize, ReadError> {
    match wanted {
        Some(f) => names.iter().position(|n| n == f).ok_or_else(|| {
            ReadError::invalid(
                path,
                format!("no {what} {f:?}; {what}s here: {}", names.join(", ")),
            )
        }),
        None if names.is_empty() => Err(ReadError::invalid(path, format!("no {what}"))),
        None => Ok(0),
    }
}

/// `dims` multiplied out, or an error naming them when the count overflows.
pub(crate) fn samples(path: &Path, dims: &[usize]) -> Result<usize, ReadError> {
    dims.iter()
        .try_fold(1usize, |n, &d| n.checked_mul(d))
        .ok_or_else(|| ReadError::invalid(path, format!("dims {dims:?} overflow")))
}
