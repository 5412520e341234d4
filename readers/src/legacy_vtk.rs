//! Legacy VTK files (`.vtk`) of `DATASET STRUCTURED_POINTS`: `DIMENSIONS`, `ORIGIN`,
//! `SPACING` (or `ASPECT_RATIO`), then `POINT_DATA n` with one or more `SCALARS name type [1]`
//! arrays (each after its `LOOKUP_TABLE`), in `ASCII` or `BINARY` (big-endian, as VTK writes
//! them). `--field` picks an array by name (default: the first). Other datasets, cell data
//! and vectors are refused, naming what was found.

use crate::bytes::{Endian, Sample, Samples};
use crate::{check_grid, samples, Dataset, Options, ReadError, Source};
use glam::Vec3;
use insitu_core::Volume;
use std::path::Path;

/// Where the chosen array's samples lie in the file.
#[derive(Debug)]
pub struct LegacyVtk {
    offset: usize,
    sample: Sample,
    binary: bool,
}

fn sample_type(name: &str) -> Option<Sample> {
    Some(match name {
        "char" | "signed_char" => Sample::I8,
        "unsigned_char" | "bit" => Sample::U8,
        "short" => Sample::I16,
        "unsigned_short" => Sample::U16,
        "int" => Sample::I32,
        "unsigned_int" => Sample::U32,
        "long" | "vtktypeint64" => Sample::I64,
        "unsigned_long" | "vtktypeuint64" => Sample::U64,
        "float" => Sample::F32,
        "double" => Sample::F64,
        _ => return None,
    })
}

/// A cursor over whitespace-separated words, which knows where it is in the bytes.
struct Words<'a> {
    bytes: &'a [u8],
    pos: usize,
}

impl<'a> Words<'a> {
    fn next(&mut self) -> Option<&'a str> {
        while self.pos < self.bytes.len() && self.bytes[self.pos].is_ascii_whitespace() {
            self.pos += 1;
        }
        let start = self.pos;
        while self.pos < self.bytes.len() && !self.bytes[self.pos].is_ascii_whitespace() {
            self.pos += 1;
        }
        (self.pos > start).then(|| std::str::from_utf8(&self.bytes[start..self.pos]).unwrap_or(""))
    }

    /// Past the end of the current line.
    fn end_line(&mut self) {
        while self.pos < self.bytes.len() && self.bytes[self.pos] != b'\n' {
            self.pos += 1;
        }
        self.pos = (self.pos + 1).min(self.bytes.len());
    }
}

/// A `SCALARS` array whose keyword `w` has just read: its name, type and where its values
/// start; `w` is left past them. `count` is the `POINT_DATA` count read before it.
///
/// # Errors
/// [`ReadError`] naming the file and the array: an unknown type, several components, no
/// `LOOKUP_TABLE` line, no `POINT_DATA` before it, or values cut short.
fn scalars(
    path: &Path,
    w: &mut Words,
    count: Option<usize>,
    binary: bool,
) -> Result<(String, Sample, usize), ReadError> {
    let bad = |m: String| ReadError::invalid(path, m);
    let name = w.next().unwrap_or_default().to_owned();
    let t = w.next().unwrap_or_default();
    let sample =
        sample_type(t).ok_or_else(|| bad(format!("SCALARS {name}: unknown type {t:?}")))?;
    // An optional component count, then LOOKUP_TABLE on its own line.
    let mut next = w.next();
    if let Some(c) = next.filter(|c| c.parse::<u32>().is_ok()) {
        if c != "1" {
            return Err(bad(format!("SCALARS {name}: {c} components (one is read)")));
        }
        next = w.next();
    }
    if next == Some("LOOKUP_TABLE") {
        w.next();
    } else {
        return Err(bad(format!("SCALARS {name}: no LOOKUP_TABLE line")));
    }
    w.end_line();
    let n = count.ok_or_else(|| bad("SCALARS before POINT_DATA".into()))?;
    let start = w.pos;
    // Past the array.
    if binary {
        let len = n
            .checked_mul(sample.size())
            .ok_or_else(|| bad("array size overflows".into()))?;
        w.pos = w
            .pos
            .checked_add(len)
            .filter(|&p| p <= w.bytes.len())
            .ok_or_else(|| bad(format!("truncated: SCALARS {name} needs {len} bytes")))?;
    } else {
        for k in 0..n {
            w.next()
                .ok_or_else(|| bad(format!("truncated: SCALARS {name} has {k} of {n} values")))?;
        }
    }
    Ok((name, sample, start))
}

/// Opens a legacy VTK structured-points file, choosing `options.field`.
///
/// # Errors
/// [`ReadError`] naming the file: no `# vtk DataFile` line, another dataset, a missing
/// keyword, an unknown type, a truncated array, or no array of that name.
pub fn open(path: &Path, options: &Options) -> Result<Dataset, ReadError> {
    let bytes = crate::read_file(path)?;
    let bad = |m: String| ReadError::invalid(path, m);
    if !bytes.starts_with(b"# vtk DataFile") {
        return Err(bad(
            "not a legacy VTK file (no '# vtk DataFile' line)".into()
        ));
    }
    let mut w = Words {
        bytes: &bytes,
        pos: 0,
    };
    w.end_line(); // version
    w.end_line(); // title
    let binary = match w.next() {
        Some("ASCII") => false,
        Some("BINARY") => true,
        other => return Err(bad(format!("{other:?} where ASCII or BINARY was expected"))),
    };
    match (w.next(), w.next()) {
        (Some("DATASET"), Some("STRUCTURED_POINTS")) => {}
        (a, b) => {
            return Err(bad(format!(
                "{} {}: only DATASET STRUCTURED_POINTS is read",
                a.unwrap_or(""),
                b.unwrap_or("")
            )))
        }
    }
    let mut dims = None;
    let mut spacing = Vec3::ONE;
    let mut origin = Vec3::ZERO;
    let number = |w: &mut Words, what: &str| -> Result<f64, ReadError> {
        w.next()
            .and_then(|s| s.parse::<f64>().ok())
            .ok_or_else(|| ReadError::invalid(path, format!("{what} needs numbers")))
    };
    let triple = |w: &mut Words, what: &str| -> Result<[f64; 3], ReadError> {
        Ok([number(w, what)?, number(w, what)?, number(w, what)?])
    };
    let as_vec = |v: [f64; 3]| Vec3::new(v[0] as f32, v[1] as f32, v[2] as f32);
    let mut arrays: Vec<(String, Sample, usize)> = Vec::new();
    let mut count = None;
    while let Some(word) = w.next() {
        match word {
            "DIMENSIONS" => {
                let d = triple(&mut w, "DIMENSIONS")?;
                if d.iter()
                    .any(|&n| !(n >= 1.0 && n.fract() == 0.0 && n < 1e9))
                {
                    return Err(bad(format!("DIMENSIONS {d:?} are not counts")));
                }
                dims = Some(d.map(|n| n as usize));
            }
            "ORIGIN" => origin = as_vec(triple(&mut w, "ORIGIN")?),
            "SPACING" | "ASPECT_RATIO" => spacing = as_vec(triple(&mut w, "SPACING")?),
            "POINT_DATA" => {
                let n = number(&mut w, "POINT_DATA")?;
                count = Some(n as usize);
            }
            "CELL_DATA" => return Err(bad("CELL_DATA: only point data is read".into())),
            "SCALARS" => arrays.push(scalars(path, &mut w, count, binary)?),
            "VECTORS"
            | "METADATA"
            | "NORMALS"
            | "TENSORS"
            | "COLOR_SCALARS"
            | "TEXTURE_COORDINATES"
            | "FIELD" => {
                // Arrays this reader does not render, or (format 5.1) the last array's metadata:
                // the arrays already found stay usable.
                break;
            }
            other => return Err(bad(format!("unexpected keyword {other:?}"))),
        }
    }
    let dims = dims.ok_or_else(|| bad("no DIMENSIONS".into()))?;
    check_grid(path, dims, spacing, origin)?;
    if count != Some(samples(path, &dims)?) {
        return Err(bad(format!(
            "POINT_DATA {count:?} is not DIMENSIONS {dims:?} multiplied out"
        )));
    }
    let names: Vec<String> = arrays.iter().map(|a| a.0.clone()).collect();
    let chosen = &arrays[crate::chosen(path, &names, options.field.as_deref(), "array")?];
    Ok(Dataset {
        path: path.to_owned(),
        dims,
        steps: 1,
        spacing,
        origin,
        field: chosen.0.clone(),
        fields: names,
        notes: Vec::new(),
        source: Source::LegacyVtk(LegacyVtk {
            offset: chosen.2,
            sample: chosen.1,
            binary,
        }),
    })
}

impl LegacyVtk {
    pub(crate) fn read(
        &self,
        path: &Path,
        dims: [usize; 3],
        spacing: Vec3,
    ) -> Result<Volume, ReadError> {
        let n = samples(path, &dims)?;
        if self.binary {
            // Streamed from the file (open checked that it holds the array).
            let len = n
                .checked_mul(self.sample.size())
                .ok_or_else(|| ReadError::invalid(path, "array size overflows"))?;
            let mut f = crate::open_file(path)?;
            std::io::Seek::seek(&mut f, std::io::SeekFrom::Start(self.offset as u64))
                .map_err(ReadError::io(path))?;
            let mut s = Samples::new(path, self.sample, Endian::Big, n, n)?;
            s.read_from(path, f, len, false)?;
            return s.finish(path, dims, spacing);
        }
        let bytes = crate::read_file(path)?;
        let rest = bytes.get(self.offset..).unwrap_or_default();
        let mut w = Words {
            bytes: rest,
            pos: 0,
        };
        // At most one value per two bytes of text.
        let mut data = Vec::with_capacity(n.min(rest.len() / 2 + 1));
        for k in 0..n {
            let v = w
                .next()
                .and_then(|s| crate::bytes::parse_text(s, self.sample))
                .ok_or_else(|| {
                    ReadError::invalid(path, format!("value {k} of {n} is missing or not a number"))
                })?;
            data.push(v);
        }
        Volume::new(dims, spacing, data).map_err(|e| ReadError::invalid(path, e.to_string()))
    }
}
