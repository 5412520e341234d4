//! NetCDF classic files (CDF-1, the 64-bit-offset CDF-2 and the 64-bit-data CDF-5; the
//! format NetCDF-3 and most ocean and climate archives write) with the CF conventions.
//!
//! A variable of three dimensions `(z, y, x)` is one volume; of four, `(t, z, y, x)` a series
//! whose first dimension (the record dimension or any other) gives the steps. The last
//! dimension is x (C order, x fastest). Values are big-endian; `scale_factor` and
//! `add_offset` are applied (`v · scale + offset`), and `_FillValue`, `missing_value` and
//! values outside `valid_min`/`valid_max`/`valid_range` become NaN (missing data, which the
//! renderer treats as empty). The axes come from the coordinate variables (a 1-D variable named
//! as its dimension): an even axis gives the spacing and origin; an uneven one (an ocean
//! model's depth levels) is resampled to an even grid at its smallest gap, linearly between
//! levels, and the resampling is stated in [`crate::Dataset::notes`] ([`Options`] may keep the
//! levels by index instead). A variable without coordinates is on a unit grid.
//!
//! Layout (Unidata's "NetCDF Classic and 64-bit Offset Format" and CDF-5 specification):
//! `CDF` version, record count, dimension list, global attributes, variable list (name,
//! dimension ids, attributes, type, size, begin), then the data.

use crate::bytes::{Cursor, Endian, Sample};
use crate::cf::{self, Axis, Coordinate, Decode, Packing};
use crate::{samples, Dataset, Options, ReadError, Source};
use glam::Vec3;
use insitu_core::Volume;
use std::io::{Read, Seek, SeekFrom};
use std::path::Path;

/// The header is read whole: larger headers are refused.
const MAX_HEADER: u64 = 64 << 20;
#[derive(Clone, Debug)]
struct Dim {
    name: String,
    len: u64,
}

#[derive(Clone, Debug)]
struct Attr {
    name: String,
    values: Vec<f64>,
    text: Option<String>,
}

#[derive(Clone, Debug)]
struct Var {
    name: String,
    dims: Vec<usize>,
    attrs: Vec<Attr>,
    sample: Sample,
    begin: u64,
}

/// A variable chosen for reading: where its samples lie and how they become the field.
#[derive(Debug)]
pub struct Variable {
    decode: Decode,
    begin: u64,
    /// Bytes between steps (a record's size for a record variable, else one step's bytes).
    stride: u64,
}

fn nc_type(path: &Path, t: u32) -> Result<(Sample, bool), ReadError> {
    Ok(match t {
        1 => (Sample::I8, false),
        2 => (Sample::U8, true), // char
        3 => (Sample::I16, false),
        4 => (Sample::I32, false),
        5 => (Sample::F32, false),
        6 => (Sample::F64, false),
        7 => (Sample::U8, false),
        8 => (Sample::U16, false),
        9 => (Sample::U32, false),
        10 => (Sample::I64, false),
        11 => (Sample::U64, false),
        other => return Err(ReadError::invalid(path, format!("unknown nc_type {other}"))),
    })
}

struct Header<'a> {
    c: Cursor<'a>,
    path: &'a Path,
    /// CDF-5: counts and sizes are 8 bytes.
    wide: bool,
    /// CDF-2 and CDF-5: `begin` is 8 bytes.
    long_offsets: bool,
}

impl Header<'_> {
    fn count(&mut self, what: &str) -> Result<u64, ReadError> {
        if self.wide {
            self.c.be_u64(what)
        } else {
            self.c.be_u32(what).map(u64::from)
        }
    }

    fn name(&mut self, what: &str) -> Result<String, ReadError> {
        let n = self.count(what)?;
        let n = usize::try_from(n)
            .ok()
            .filter(|&n| n <= 1 << 16)
            .ok_or_else(|| ReadError::invalid(self.path, format!("{what} of {n} bytes")))?;
        let bytes = self.c.take(n, what)?;
        self.c.take((4 - n % 4) % 4, what)?;
        String::from_utf8(bytes.to_vec())
            .map_err(|_| ReadError::invalid(self.path, format!("{what} is not UTF-8")))
    }

    /// A list's tag and length: `(0, 0)` when absent.
    fn list(&mut self, tag: u32, what: &str) -> Result<u64, ReadError> {
        let t = self.c.be_u32(what)?;
        let n = self.count(what)?;
        if t == 0 && n == 0 {
            return Ok(0);
        }
        if t != tag {
            return Err(ReadError::invalid(
                self.path,
                format!("{what}: tag {t:#x} where {tag:#x} was expected"),
            ));
        }
        Ok(n)
    }

    fn attrs(&mut self, what: &str) -> Result<Vec<Attr>, ReadError> {
        let n = self.list(0x0C, what)?;
        let mut out = Vec::new();
        for _ in 0..n {
            let name = self.name("attribute name")?;
            let (sample, is_char) = nc_type(self.path, self.c.be_u32("attribute type")?)?;
            let count = self.count("attribute length")?;
            let bytes = usize::try_from(count)
                .ok()
                .and_then(|c| c.checked_mul(sample.size()))
                .ok_or_else(|| {
                    ReadError::invalid(self.path, format!("attribute {name}: {count} values"))
                })?;
            let data = self.c.take(bytes, "attribute values")?;
            self.c.take((4 - bytes % 4) % 4, "attribute padding")?;
            let (values, text) = if is_char {
                (
                    Vec::new(),
                    Some(
                        String::from_utf8_lossy(data)
                            .trim_end_matches('\0')
                            .to_owned(),
                    ),
                )
            } else {
                (crate::bytes::values(data, sample, Endian::Big), None)
            };
            out.push(Attr { name, values, text });
        }
        Ok(out)
    }
}

/// The header of a classic file in `head`: the record count, the dimensions and the numeric
/// variables (character variables left out).
///
/// # Errors
/// [`ReadError`] naming the file: no CDF magic, an unknown version, a truncated header, a
/// dimension id out of range, an unknown type.
fn parse_header(path: &Path, head: &[u8]) -> Result<(u64, Vec<Dim>, Vec<Var>), ReadError> {
    let mut h = Header {
        c: Cursor::new(path, head),
        path,
        wide: false,
        long_offsets: false,
    };
    let magic = h.c.take(4, "magic")?;
    if &magic[..3] != b"CDF" {
        return Err(ReadError::invalid(path, "not a NetCDF file (no CDF magic)"));
    }
    match magic[3] {
        1 => {}
        2 => h.long_offsets = true,
        5 => (h.wide, h.long_offsets) = (true, true),
        v => {
            return Err(ReadError::invalid(
                path,
                format!("NetCDF classic version {v} is not 1, 2 or 5"),
            ))
        }
    }
    let numrecs = h.count("record count")?;
    let ndims = h.list(0x0A, "dimension list")?;
    let mut dims = Vec::new();
    for _ in 0..ndims.min(1 << 16) {
        let name = h.name("dimension name")?;
        let len = h.count("dimension length")?;
        dims.push(Dim { name, len });
    }
    h.attrs("global attributes")?;
    let nvars = h.list(0x0B, "variable list")?;
    let mut vars = Vec::new();
    for _ in 0..nvars.min(1 << 16) {
        let name = h.name("variable name")?;
        let n = h.count("variable rank")?;
        let mut ids = Vec::new();
        for _ in 0..n.min(64) {
            let id = h.count("dimension id")?;
            let id = usize::try_from(id)
                .ok()
                .filter(|&i| i < dims.len())
                .ok_or_else(|| {
                    ReadError::invalid(
                        path,
                        format!("variable {name}: dimension id {id} of {}", dims.len()),
                    )
                })?;
            ids.push(id);
        }
        let attrs = h.attrs("variable attributes")?;
        let (sample, is_char) = nc_type(path, h.c.be_u32("variable type")?)?;
        let _vsize = h.count("variable size")?;
        let begin = if h.long_offsets {
            h.c.be_u64("variable begin")?
        } else {
            u64::from(h.c.be_u32("variable begin")?)
        };
        if !is_char {
            vars.push(Var {
                name,
                dims: ids,
                attrs,
                sample,
                begin,
            });
        }
    }
    Ok((numrecs, dims, vars))
}

/// The variable to read: `field`, else the first of `volumes` (those of three or four
/// dimensions that are not coordinates).
///
/// # Errors
/// [`ReadError`] naming the file: no such variable (the volumes listed), none of three or four
/// dimensions, or the one named has another number of dimensions.
fn choose<'v>(
    path: &Path,
    vars: &'v [Var],
    volumes: &[&'v Var],
    field: Option<&str>,
) -> Result<&'v Var, ReadError> {
    let var = match field {
        Some(name) => vars.iter().find(|v| v.name == name).ok_or_else(|| {
            ReadError::invalid(
                path,
                format!(
                    "no variable {name:?}; volumes here: {}",
                    volumes
                        .iter()
                        .map(|v| v.name.as_str())
                        .collect::<Vec<_>>()
                        .join(", ")
                ),
            )
        })?,
        None => volumes
            .first()
            .copied()
            .ok_or_else(|| ReadError::invalid(path, "no variable of three or four dimensions"))?,
    };
    if !(3..=4).contains(&var.dims.len()) {
        return Err(ReadError::invalid(
            path,
            format!(
                "variable {} has {} dimensions: a volume has (z, y, x) or (t, z, y, x)",
                var.name,
                var.dims.len()
            ),
        ));
    }
    Ok(var)
}

/// The grid's axes, x first, each with its coordinate variable's values where the file has
/// one (`cv` named as its dimension).
///
/// # Errors
/// [`ReadError`] naming the file when a coordinate variable cannot be read.
fn axes(
    file: &mut std::fs::File,
    path: &Path,
    (vars, dims): (&[Var], &[Dim]),
    var: &Var,
    file_dims: [usize; 3],
) -> Result<[Axis; 3], ReadError> {
    let k = var.dims.len();
    let is_coord = |v: &Var| v.dims.len() == 1 && dims[v.dims[0]].name == v.name;
    // The axes from the coordinate variables, x first.
    let mut axes = Vec::with_capacity(3);
    for (a, &n) in file_dims.iter().enumerate() {
        let d = var.dims[k - 1 - a];
        let coordinate = match vars.iter().find(|v| is_coord(v) && v.dims[0] == d) {
            Some(cv) => Some(Coordinate {
                name: cv.name.clone(),
                values: read_coords(file, path, cv, n)?,
                units: cv
                    .attrs
                    .iter()
                    .find(|a| a.name == "units")
                    .and_then(|a| a.text.clone()),
            }),
            None => None,
        };
        axes.push(Axis {
            dim: dims[d].name.clone(),
            coordinate,
        });
    }
    axes.try_into()
        .map_err(|_| ReadError::invalid(path, "three axes"))
}

/// Opens a NetCDF classic file, choosing `options.field` (else the first variable of three or
/// four dimensions that is not a coordinate).
///
/// # Errors
/// [`ReadError`] naming the file: not a classic NetCDF file (a netCDF-4/HDF5 one is named as
/// such), a truncated header, an unknown or absent variable, a variable of other than three
/// or four dimensions, non-numeric data.
pub fn open(path: &Path, options: &Options) -> Result<Dataset, ReadError> {
    let mut file = crate::open_file(path)?;
    let len = file.metadata().map_err(ReadError::io(path))?.len();
    let mut head = Vec::new();
    (&mut file)
        .take(len.min(MAX_HEADER))
        .read_to_end(&mut head)
        .map_err(ReadError::io(path))?;
    if head.starts_with(b"\x89HDF") {
        return Err(ReadError::invalid(
            path,
            "a netCDF-4 (HDF5) file: this build reads NetCDF classic (CDF-1, 2, 5) only",
        ));
    }
    let (numrecs, dims, vars) = parse_header(path, &head)?;
    // A record's size: every record variable's slab, padded to 4 bytes unless it is the only one.
    let is_record = |v: &Var| v.dims.first().is_some_and(|&d| dims[d].len == 0);
    let slab = |v: &Var| -> u64 {
        v.dims
            .iter()
            .skip(usize::from(is_record(v)))
            .map(|&d| dims[d].len)
            .product::<u64>()
            .saturating_mul(v.sample.size() as u64)
    };
    let record_vars: Vec<&Var> = vars.iter().filter(|v| is_record(v)).collect();
    let recsize: u64 = if record_vars.len() == 1 {
        slab(record_vars[0])
    } else {
        record_vars.iter().map(|v| slab(v).div_ceil(4) * 4).sum()
    };
    let is_coord = |v: &Var| v.dims.len() == 1 && dims[v.dims[0]].name == v.name;
    let volumes: Vec<&Var> = vars
        .iter()
        .filter(|v| (3..=4).contains(&v.dims.len()) && !is_coord(v))
        .collect();
    let var = choose(path, &vars, &volumes, options.field.as_deref())?;
    let len_of = |d: usize| -> u64 {
        if dims[d].len == 0 {
            numrecs
        } else {
            dims[d].len
        }
    };
    let k = var.dims.len();
    let to_usize = |v: u64| usize::try_from(v).unwrap_or(usize::MAX);
    let file_dims = [
        to_usize(len_of(var.dims[k - 1])),
        to_usize(len_of(var.dims[k - 2])),
        to_usize(len_of(var.dims[k - 3])),
    ];
    let steps = if k == 4 {
        to_usize(len_of(var.dims[0]))
    } else {
        1
    };
    let step_bytes = samples(path, &file_dims)?
        .checked_mul(var.sample.size())
        .ok_or_else(|| ReadError::invalid(path, "variable size overflows"))?
        as u64;
    let stride = if is_record(var) { recsize } else { step_bytes };
    let last = var
        .begin
        .checked_add(stride.saturating_mul(steps.saturating_sub(1) as u64))
        .and_then(|b| b.checked_add(step_bytes));
    if steps == 0 || last.is_none_or(|end| end > len) {
        return Err(ReadError::invalid(
            path,
            format!(
                "truncated: variable {} needs {} bytes from offset {}, the file holds {len}",
                var.name,
                last.map_or("more".to_owned(), |l| l.to_string()),
                var.begin
            ),
        ));
    }
    let packing = Packing::from_attrs(
        |name| {
            var.attrs
                .iter()
                .find(|a| a.name == name)
                .map(|a| a.values.clone())
        },
        var.sample,
    );
    let axes = axes(&mut file, path, (&vars, &dims), var, file_dims)?;
    let grid = cf::grid(
        path,
        file_dims,
        axes,
        var.sample,
        Endian::Big,
        packing,
        options.uneven,
    )?;
    let fields = volumes.iter().map(|v| v.name.clone()).collect();
    Ok(
        grid.dataset(path, steps, var.name.clone(), fields, |decode| {
            Source::NetCdf(Box::new(Variable {
                decode,
                begin: var.begin,
                stride,
            }))
        }),
    )
}

/// The `n` values of the coordinate variable `cv`.
fn read_coords(
    file: &mut std::fs::File,
    path: &Path,
    cv: &Var,
    n: usize,
) -> Result<Vec<f64>, ReadError> {
    let len = file.metadata().map_err(ReadError::io(path))?.len();
    let size = n.saturating_mul(cv.sample.size());
    if cv.begin.saturating_add(size as u64) > len {
        return Err(ReadError::invalid(
            path,
            format!(
                "truncated: coordinate variable {} needs {size} bytes from offset {}",
                cv.name, cv.begin
            ),
        ));
    }
    let mut bytes = vec![0u8; size];
    file.seek(SeekFrom::Start(cv.begin))
        .and_then(|_| file.read_exact(&mut bytes))
        .map_err(|e| ReadError::invalid(path, format!("coordinate variable {}: {e}", cv.name)))?;
    Ok(crate::bytes::values(&bytes, cv.sample, Endian::Big))
}

impl Variable {
    /// Step `t` as a volume of `dims` (after resampling) at `spacing`.
    pub(crate) fn read_step(
        &self,
        path: &Path,
        t: usize,
        dims: [usize; 3],
        spacing: Vec3,
    ) -> Result<Volume, ReadError> {
        let size = self.decode.sample_size();
        let n = self.decode.stored_samples(path)?;
        let at = self.begin + self.stride * t as u64;
        let mut file = crate::open_file(path)?;
        file.seek(SeekFrom::Start(at))
            .map_err(|e| ReadError::invalid(path, format!("step {t} at offset {at}: {e}")))?;
        // Open checked that the file holds every step's bytes; read a piece at a time.
        self.decode.volume(path, dims, spacing, |push| {
            let mut piece = vec![0u8; (crate::bytes::PIECE / size * size).min(n * size)];
            let mut left = n * size;
            while left > 0 {
                let k = left.min(piece.len());
                file.read_exact(&mut piece[..k]).map_err(|e| {
                    ReadError::invalid(path, format!("step {t} at offset {at}: {e}"))
                })?;
                push(&piece[..k]);
                left -= k;
            }
            Ok(())
        })
    }
}
