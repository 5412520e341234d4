//! NRRD (teem's "nearly raw raster data"): a text header, then the samples in the same file
//! (`.nrrd`) or in the one its `data file` names (`.nhdr`, detached). Read: three dimensions,
//! every scalar type, `raw` and `gzip` encodings, either `endian`, `line skip`/`byte skip`,
//! `spacings` or axis-aligned `space directions` (anything else — rotated or sheared axes — is
//! refused, naming the vectors), and `space origin`.

use crate::bytes::{Endian, Sample, Samples};
use crate::{check_grid, samples, Dataset, ReadError, Source};
use glam::Vec3;
use insitu_core::Volume;
use std::io::Read;
use std::path::{Path, PathBuf};

/// Longest header read, bytes.
const MAX_HEADER: usize = 1 << 20;

/// Where an NRRD's samples are and how they are stored.
#[derive(Debug)]
pub struct Nrrd {
    data: PathBuf,
    /// Bytes of the data file before the samples (`byte skip`, or after the header).
    offset: u64,
    line_skip: usize,
    sample: Sample,
    endian: Endian,
    gzip: bool,
}

fn sample_type(name: &str) -> Option<Sample> {
    Some(match name {
        "signed char" | "int8" | "int8_t" => Sample::I8,
        "uchar" | "unsigned char" | "uint8" | "uint8_t" => Sample::U8,
        "short" | "short int" | "signed short" | "signed short int" | "int16" | "int16_t" => {
            Sample::I16
        }
        "ushort" | "unsigned short" | "unsigned short int" | "uint16" | "uint16_t" => Sample::U16,
        "int" | "signed int" | "int32" | "int32_t" => Sample::I32,
        "uint" | "unsigned int" | "uint32" | "uint32_t" => Sample::U32,
        "longlong"
        | "long long"
        | "long long int"
        | "signed long long"
        | "signed long long int"
        | "int64"
        | "int64_t" => Sample::I64,
        "ulonglong" | "unsigned long long" | "unsigned long long int" | "uint64" | "uint64_t" => {
            Sample::U64
        }
        "float" => Sample::F32,
        "double" => Sample::F64,
        _ => return None,
    })
}

/// `(a,b,c)` vectors of a `space directions` or `space origin` line.
fn vectors(path: &Path, text: &str) -> Result<Vec<[f64; 3]>, ReadError> {
    let bad = || ReadError::invalid(path, format!("vectors {text:?} are not (x,y,z) triples"));
    text.split(')')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| {
            let inner = s.strip_prefix('(').ok_or_else(bad)?;
            let v: Vec<f64> = inner
                .split(',')
                .map(|c| c.trim().parse::<f64>())
                .collect::<Result<_, _>>()
                .map_err(|_| bad())?;
            <[f64; 3]>::try_from(v).map_err(|_| bad())
        })
        .collect()
}

/// The header's `field: value` lines (keys lower-cased; comments skipped) and where the
/// header ends: at the first empty line, or the end of `head` (a detached header).
///
/// # Errors
/// [`ReadError`] naming the file and a line that is not `field: value`.
fn header_fields(path: &Path, head: &[u8]) -> Result<(Vec<(String, String)>, usize), ReadError> {
    let mut end = head.len();
    let mut fields = Vec::new();
    let mut pos = 0;
    let mut first = true;
    while pos < head.len() {
        let line_end = head[pos..]
            .iter()
            .position(|&b| b == b'\n')
            .map_or(head.len(), |i| pos + i);
        let line = String::from_utf8_lossy(&head[pos..line_end]);
        let line = line.trim_end_matches('\r');
        pos = line_end + 1;
        if first {
            first = false;
            continue;
        }
        if line.is_empty() {
            end = pos.min(head.len());
            break;
        }
        if line.starts_with('#') {
            continue;
        }
        let (key, value) = line
            .split_once(": ")
            .or_else(|| line.split_once(":="))
            .ok_or_else(|| {
                ReadError::invalid(path, format!("header line {line:?} is not 'field: value'"))
            })?;
        fields.push((key.trim().to_ascii_lowercase(), value.trim().to_owned()));
    }
    Ok((fields, end))
}

/// The grid spacing from the `space directions` field (axis-aligned and positive), else the
/// `spacings` field, else 1 on every axis.
///
/// # Errors
/// [`ReadError`] naming the file and the field: not three vectors or numbers, or a rotated
/// or flipped grid.
fn spacing_of(
    path: &Path,
    directions: Option<&str>,
    spacings: Option<&str>,
) -> Result<[f64; 3], ReadError> {
    let mut spacing = [1.0f64; 3];
    if let Some(dirs) = directions {
        let v = vectors(path, dirs)?;
        if v.len() != 3 {
            return Err(ReadError::invalid(
                path,
                format!("space directions {dirs:?}: need three vectors"),
            ));
        }
        for (a, d) in v.iter().enumerate() {
            let off_axis = (0..3).any(|k| k != a && d[k] != 0.0);
            if off_axis || d[a].partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) {
                return Err(ReadError::invalid(
                    path,
                    format!("space directions {dirs:?} are not axis-aligned and positive: rotated or flipped grids are not read"),
                ));
            }
            spacing[a] = d[a];
        }
    } else if let Some(s) = spacings {
        let v: Vec<f64> = s
            .split_whitespace()
            .map(str::parse)
            .collect::<Result<_, _>>()
            .map_err(|_| ReadError::invalid(path, format!("spacings {s:?} are not numbers")))?;
        spacing = v
            .try_into()
            .map_err(|_| ReadError::invalid(path, "spacings must give three numbers"))?;
    }
    Ok(spacing)
}

/// Opens an NRRD file (`.nrrd`, or a detached `.nhdr`).
///
/// # Errors
/// [`ReadError`] naming the file: no `NRRD` magic, a missing or unknown field, other than
/// three dimensions, an encoding other than raw or gzip, axes that are not axis-aligned.
pub fn open(path: &Path) -> Result<Dataset, ReadError> {
    let mut file = crate::open_file(path)?;
    let mut head = Vec::new();
    (&mut file)
        .take(MAX_HEADER as u64)
        .read_to_end(&mut head)
        .map_err(ReadError::io(path))?;
    if !head.starts_with(b"NRRD000") {
        return Err(ReadError::invalid(
            path,
            "not an NRRD file (no NRRD000x magic)",
        ));
    }
    let (fields, end) = header_fields(path, &head)?;
    let get = |k: &str| fields.iter().find(|(f, _)| f == k).map(|(_, v)| v.as_str());
    let need = |k: &str| get(k).ok_or_else(|| ReadError::invalid(path, format!("no {k:?} field")));
    let sample = sample_type(need("type")?)
        .ok_or_else(|| ReadError::invalid(path, format!("unknown type {:?}", get("type"))))?;
    let dimension = need("dimension")?;
    if dimension != "3" {
        return Err(ReadError::invalid(
            path,
            format!("dimension {dimension}: a volume has 3"),
        ));
    }
    let sizes: Vec<usize> = need("sizes")?
        .split_whitespace()
        .map(str::parse)
        .collect::<Result<_, _>>()
        .map_err(|_| {
            ReadError::invalid(path, format!("sizes {:?} are not counts", get("sizes")))
        })?;
    let dims: [usize; 3] = sizes
        .try_into()
        .map_err(|_| ReadError::invalid(path, "sizes must give three counts"))?;
    let encoding = need("encoding")?;
    let gzip = match encoding {
        "raw" => false,
        "gzip" | "gz" => true,
        other => {
            return Err(ReadError::invalid(
                path,
                format!("encoding {other:?}: this reader takes raw and gzip"),
            ))
        }
    };
    let endian = match get("endian") {
        Some("big") => Endian::Big,
        Some("little") => Endian::Little,
        None if sample.size() == 1 => Endian::Little,
        other => {
            return Err(ReadError::invalid(
                path,
                format!("endian {other:?} is not little or big"),
            ))
        }
    };
    let spacing = spacing_of(path, get("space directions"), get("spacings"))?;
    let origin = match get("space origin") {
        Some(o) => match vectors(path, o)?.as_slice() {
            [v] => *v,
            _ => {
                return Err(ReadError::invalid(
                    path,
                    format!("space origin {o:?} is not one vector"),
                ))
            }
        },
        None => [0.0; 3],
    };
    let as_vec = |v: [f64; 3]| Vec3::new(v[0] as f32, v[1] as f32, v[2] as f32);
    let (spacing, origin) = (as_vec(spacing), as_vec(origin));
    check_grid(path, dims, spacing, origin)?;
    let skip = |k: &str| -> Result<usize, ReadError> {
        get(k).map_or(Ok(0), |v| {
            v.parse()
                .map_err(|_| ReadError::invalid(path, format!("{k} {v:?} is not a count")))
        })
    };
    let (line_skip, byte_skip) = (skip("line skip")?, skip("byte skip")?);
    let (data, offset) = match get("data file").or_else(|| get("datafile")) {
        Some(name) => {
            let dir = path.parent().unwrap_or(Path::new("."));
            (dir.join(name), byte_skip as u64)
        }
        None => (path.to_owned(), (end + byte_skip) as u64),
    };
    Ok(Dataset {
        path: path.to_owned(),
        dims,
        steps: 1,
        spacing,
        origin,
        field: "values".into(),
        fields: vec!["values".into()],
        notes: Vec::new(),
        source: Source::Nrrd(Nrrd {
            data,
            offset,
            line_skip,
            sample,
            endian,
            gzip,
        }),
    })
}

impl Nrrd {
    pub(crate) fn read(
        &self,
        path: &Path,
        dims: [usize; 3],
        spacing: Vec3,
    ) -> Result<Volume, ReadError> {
        let want = samples(path, &dims)?
            .checked_mul(self.sample.size())
            .ok_or_else(|| ReadError::invalid(path, "size overflows"))?;
        let file = crate::open_file(&self.data)?;
        let len = file.metadata().map_err(ReadError::io(&self.data))?.len();
        let mut from = std::io::BufReader::new(file);
        std::io::Seek::seek(&mut from, std::io::SeekFrom::Start(self.offset.min(len)))
            .map_err(ReadError::io(&self.data))?;
        let mut skipped = self.offset.min(len);
        for _ in 0..self.line_skip {
            let mut line = Vec::new();
            skipped += std::io::BufRead::read_until(&mut from, b'\n', &mut line)
                .map_err(ReadError::io(&self.data))? as u64;
        }
        let n = want / self.sample.size();
        let short = |have: u64| {
            ReadError::invalid(
                &self.data,
                format!(
                    "{have} bytes of samples where {dims:?} of {} bytes need {want}",
                    self.sample.size()
                ),
            )
        };
        let s = if self.gzip {
            // Reserved as the data decompresses (at most 1032:1, deflate's limit): a header
            // cannot make us allocate what is not there.
            let bound = (len - skipped).saturating_mul(1032) as usize / self.sample.size();
            let mut s = Samples::new(path, self.sample, self.endian, n, bound)?;
            let gz = flate2::read::MultiGzDecoder::new(from);
            s.read_from(&self.data, gz, want, true)?;
            s
        } else {
            if len - skipped < want as u64 {
                return Err(short(len - skipped));
            }
            let mut s = Samples::new(path, self.sample, self.endian, n, n)?;
            s.read_from(&self.data, from, want, false)?;
            s
        };
        s.finish(path, dims, spacing)
    }
}
