//! ADIOS2 output read through ADIOS2's C library (the wheel `adios2` from PyPI ships it, as do
//! Spack and the distributions), behind the `adios2` feature: BP4/BP5 files written by any
//! ADIOS2 writer (`insitu render --volume run.bp`, `insitu replay --series run.bp`), and live
//! SST streams a generator-node reads step by step ([`Stream`]).
//!
//! What is read: a **global array** of three dimensions, named by `--var` (else the first
//! such variable), one time step per ADIOS2 step. Its Shape is the grid: ADIOS2 presents it
//! row-major to this reader (a Fortran writer's dimensions come reversed), so the last
//! dimension is x, the fastest, and the first is z. The blocks the writer's ranks `Put` are
//! the library's business: a selection of the global array is read whole, whichever blocks
//! hold it. Spacing and origin come from attributes where the writer stores them —
//! `VAR/spacing` and `VAR/origin`, else `spacing` and `origin`, three numbers each in x, y, z
//! order — and are otherwise a unit grid at the origin (said in [`crate::Dataset::notes`]).
//!
//! Types: every integer and float type, kept as the core keeps them (u8, u16, i16, f32,
//! f64; others converted to f32); strings, complex numbers and long doubles are refused by
//! name, as is a variable that is not 3-D or not a global array, and a selection outside the
//! Shape.
//!
//! The C library is called only here and in `ffi`; each call's soundness is argued beside it.

#![allow(unsafe_code)]

mod ffi;
pub mod openpmd;
mod stream;

pub use stream::{Engine, Step, Stream, Variable};

use crate::{Dataset, Options, ReadError, Source};
use glam::Vec3;
use insitu_core::Volume;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// A BP file opened for reading any step: the engine, behind a lock (reads are serial; each
/// runs on a thread of its own, so that a read ADIOS2 never finishes is abandoned on time).
#[derive(Debug)]
pub struct File {
    stream: Arc<Mutex<Stream>>,
    path: PathBuf,
    var: String,
    /// For an openPMD mesh: where each iteration lies and how its samples are ordered.
    openpmd: Option<(Vec<openpmd::Iteration>, openpmd::Layout)>,
}

/// Whether `path` looks like a BP file or directory (`.bp`, `.bp4`, `.bp5`).
pub fn is_bp(path: &Path) -> bool {
    path.extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase())
        .is_some_and(|e| matches!(e.as_str(), "bp" | "bp4" | "bp5"))
}

/// "iteration 7" or "iterations 0, 100, 200", for the notes.
fn iterations(numbers: impl ExactSizeIterator<Item = u64>) -> String {
    let plural = if numbers.len() == 1 { "" } else { "s" };
    let list: Vec<String> = numbers.map(|n| n.to_string()).collect();
    format!("iteration{plural} {}", list.join(", "))
}

/// Whether `path` names a series of BP files by openPMD's pattern: `%T` (or `%0NT`, padded)
/// standing for the iteration number (`run_%T.bp5`).
pub fn is_series(path: &Path) -> bool {
    series_pattern(path).is_some()
}

/// The text before and after the `%T` (or `%0NT`) of `path`'s file name.
fn series_pattern(path: &Path) -> Option<(String, String)> {
    let name = path.file_name()?.to_str()?;
    let (before, rest) = name.split_once('%')?;
    let width = rest.find('T')?;
    rest[..width]
        .bytes()
        .all(|b| b.is_ascii_digit())
        .then(|| (before.to_owned(), rest[width + 1..].to_owned()))
}

/// A series of BP files, one iteration each (openPMD's file-based iteration encoding), read
/// as the steps of one dataset.
#[derive(Debug)]
pub struct Series {
    /// The files, by iteration ascending.
    files: Vec<PathBuf>,
}

/// Opens the files `path`'s pattern matches (`run_%T.bp5`: `run_0.bp5`, `run_100.bp5`, …;
/// iteration numbers in any width) as one dataset, a step per file by iteration, each file
/// read as [`open`] reads it with `options`.
///
/// # Errors
/// [`ReadError`] naming the pattern or a file: no file matches, the first file cannot be
/// read (as [`open`]), or holds more than one step.
pub fn open_series(path: &Path, options: &Options) -> Result<Dataset, ReadError> {
    let Some((before, after)) = series_pattern(path) else {
        return open(path, options);
    };
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let entries = std::fs::read_dir(&dir).map_err(crate::ReadError::io(&dir))?;
    let mut files: Vec<(u64, PathBuf)> = entries
        .filter_map(Result::ok)
        .filter_map(|e| {
            let name = e.file_name().into_string().ok()?;
            let digits = name.strip_prefix(&before)?.strip_suffix(&after)?;
            let n = (!digits.is_empty() && digits.bytes().all(|b| b.is_ascii_digit()))
                .then(|| digits.parse::<u64>().ok())??;
            Some((n, e.path()))
        })
        .collect();
    files.sort();
    let Some((_, first)) = files.first() else {
        return Err(ReadError::invalid(
            path,
            format!(
                "no file in {} matches {before}<iteration>{after} (%T stands for the iteration)",
                dir.display()
            ),
        ));
    };
    let d = open(first, options)?;
    if d.steps != 1 {
        return Err(ReadError::invalid(
            first,
            format!(
                "holds {} steps; in a series named by %T each file holds one iteration",
                d.steps
            ),
        ));
    }
    let mut notes = d.notes;
    notes.push(format!(
        "{} file{} for {}",
        files.len(),
        if files.len() == 1 { "" } else { "s" },
        iterations(files.iter().map(|f| f.0))
    ));
    Ok(Dataset {
        path: path.to_owned(),
        dims: d.dims,
        steps: files.len(),
        spacing: d.spacing,
        origin: d.origin,
        field: d.field,
        fields: d.fields,
        notes,
        source: Source::Adios2Series(Series {
            files: files.into_iter().map(|f| f.1).collect(),
        }),
    })
}

impl Series {
    /// Step `t` of `series`: its file's only step, which must lie on the series' grid.
    pub(crate) fn read_step(&self, t: usize, series: &Dataset) -> Result<Volume, ReadError> {
        let Some(file) = self.files.get(t) else {
            return Err(ReadError::invalid(&series.path, format!("no step {t}")));
        };
        let options = Options {
            field: Some(series.field.clone()),
            ..Options::default()
        };
        let d = open(file, &options)?;
        if (d.dims, d.spacing, d.origin) != (series.dims, series.spacing, series.origin) {
            return Err(ReadError::invalid(
                file,
                format!(
                    "{} on a grid of {:?} points, spacing {}, origin {}, where the series' first \
                     file has {:?}, {}, {}",
                    d.field,
                    d.dims,
                    d.spacing,
                    d.origin,
                    series.dims,
                    series.spacing,
                    series.origin
                ),
            ));
        }
        d.read_step(0)
    }
}

/// Opens a BP file (BP4 or BP5: a directory; BP3: a file) as a dataset of the global array
/// `options.field` (else the first 3-D global array by name), one step per ADIOS2 step.
///
/// # Errors
/// [`ReadError`] naming the file: ADIOS2 cannot open it, no 3-D global array, or the chosen
/// variable absent, not 3-D, of a type not taken, or without steps.
pub fn open(path: &Path, options: &Options) -> Result<Dataset, ReadError> {
    if !path.exists() {
        return Err(ReadError::invalid(path, "no such BP file or directory"));
    }
    let stream = Stream::open_mode(
        path,
        Engine::File,
        &[],
        Duration::from_secs(1),
        ffi::MODE_READ_RANDOM_ACCESS,
    )?;
    if openpmd::is_openpmd(&stream) {
        return open_openpmd(path, stream, options);
    }
    let fields = stream.volumes();
    let var = match &options.field {
        Some(v) => v.clone(),
        None => fields.first().cloned().ok_or_else(|| {
            ReadError::invalid(
                path,
                format!(
                    "no 3-D global array; variables here: {}",
                    stream.variables().join(", ")
                ),
            )
        })?,
    };
    let v = stream.variable(&var)?;
    let steps = stream.steps(&var)?;
    if steps == 0 {
        return Err(ReadError::invalid(
            path,
            format!("variable {var} has no step"),
        ));
    }
    let (spacing, origin, note) = stream.grid(&var);
    crate::check_grid(path, v.dims, spacing, origin)?;
    Ok(Dataset {
        path: path.to_owned(),
        dims: v.dims,
        steps,
        spacing,
        origin,
        field: var.clone(),
        fields,
        notes: note.into_iter().collect(),
        source: Source::Adios2(Box::new(File {
            stream: Arc::new(Mutex::new(stream)),
            path: path.to_owned(),
            var,
            openpmd: None,
        })),
    })
}

/// [`open`] for an openPMD series: the mesh `options.field` (else the first 3-D one by name),
/// one step per iteration.
fn open_openpmd(path: &Path, stream: Stream, options: &Options) -> Result<Dataset, ReadError> {
    let meshes = openpmd::meshes(&stream, |var| stream.steps(var).unwrap_or(0));
    let is_volume = |m: &openpmd::Mesh| {
        m.iterations
            .first()
            .is_some_and(|i| stream.variable(&i.var).is_ok())
    };
    let fields: Vec<String> = meshes
        .iter()
        .filter(|m| is_volume(m))
        .map(|m| m.name.clone())
        .collect();
    let names = || {
        let all: Vec<&str> = meshes.iter().map(|m| m.name.as_str()).collect();
        if all.is_empty() {
            "none".to_owned()
        } else {
            all.join(", ")
        }
    };
    let name = match &options.field {
        Some(f) => f.clone(),
        None => fields.first().cloned().ok_or_else(|| {
            ReadError::invalid(
                path,
                format!(
                    "openPMD series without a 3-D mesh; meshes here: {}",
                    names()
                ),
            )
        })?,
    };
    let Some(mesh) = meshes.iter().find(|m| m.name == name) else {
        return Err(ReadError::invalid(
            path,
            format!("no openPMD mesh {name:?}; meshes here: {}", names()),
        ));
    };
    let Some(first) = mesh.iterations.first() else {
        return Err(ReadError::invalid(
            path,
            format!("openPMD mesh {name} has no iteration"),
        ));
    };
    let layout = openpmd::layout(&stream, &name, &first.var)?;
    crate::check_grid(path, layout.dims, layout.spacing, layout.origin)?;
    let numbers = iterations(mesh.iterations.iter().map(|i| i.number));
    let mut notes = vec![format!("openPMD mesh {name}: {numbers}")];
    notes.extend(layout.notes.iter().cloned());
    Ok(Dataset {
        path: path.to_owned(),
        dims: layout.dims,
        steps: mesh.iterations.len(),
        spacing: layout.spacing,
        origin: layout.origin,
        field: name,
        fields,
        notes,
        source: Source::Adios2(Box::new(File {
            stream: Arc::new(Mutex::new(stream)),
            path: path.to_owned(),
            var: first.var.clone(),
            openpmd: Some((mesh.iterations.clone(), layout)),
        })),
    })
}

impl File {
    /// Step `t` as a volume of `dims` at `spacing`.
    pub(crate) fn read_step(
        &self,
        t: usize,
        dims: [usize; 3],
        spacing: Vec3,
    ) -> Result<Volume, ReadError> {
        let stream = self.stream.clone();
        let (var, openpmd) = (self.var.clone(), self.openpmd.clone());
        let read = move || {
            let mut s = stream.lock().unwrap_or_else(|e| e.into_inner());
            let Some((iterations, layout)) = &openpmd else {
                return s.read(&var, [0; 3], dims, Some(t), spacing);
            };
            let Some(it) = iterations.get(t) else {
                return Err(ReadError::invalid(
                    &s.name,
                    format!("openPMD mesh: no step {t}"),
                ));
            };
            let step = match it.step {
                Some(step) => step,
                None => s.first_step(&it.var)?,
            };
            s.read_mesh(&it.var, layout, [0; 3], dims, Some(step), spacing)
        };
        let (tx, rx) = std::sync::mpsc::sync_channel(1);
        std::thread::spawn(move || {
            let _ = tx.send(read());
        });
        // ADIOS2 waits at the end of a data file for the rest, as if its writer were still
        // writing: a file cut short would hold the read forever.
        let bytes = dims.iter().product::<usize>() * 8;
        let limit = READ_WAIT + Duration::from_secs_f64(bytes as f64 / READ_RATE);
        rx.recv_timeout(limit).unwrap_or_else(|_| {
            Err(ReadError::invalid(
                &self.path,
                format!(
                    "step {t} of {}: no data from ADIOS2 within {:.0} s; a data file \
                     (data.N) is shorter than the metadata says (cut short?), and ADIOS2 waits \
                     for the rest as if a writer were still writing",
                    self.var,
                    limit.as_secs_f64()
                ),
            ))
        })
    }
}

/// How long a step's read from a BP file may take before it is given up as waiting on data
/// that is not there, beyond the time to read its bytes at [`READ_RATE`].
pub const READ_WAIT: Duration = Duration::from_secs(15);

/// The slowest read rate a BP file's step is allowed, bytes per second (a parallel file
/// system under load).
const READ_RATE: f64 = 50e6;
