//! VTK XML ImageData (`.vti`) as VTK writes it: one piece, point data, arrays in `ascii`,
//! inline `binary` (base64) or `appended` (`raw` or `base64`) format, uncompressed or in
//! zlib blocks (`vtkZLibDataCompressor`), with a `UInt32` or `UInt64` header, either byte order.
//! `--field` picks a point-data array by name (default: the active scalars, else the first).
//! `Origin` and `Spacing` place the grid; a `Direction` other than the identity, several
//! pieces, several components and other compressors are refused, naming what was found.
//!
//! A data block is `[byte count][data]`, or compressed `[blocks][block size][last block
//! size][compressed size per block][blocks…]`, each header word of `header_type`.

use crate::bytes::{Endian, Sample, Samples};
use crate::{check_grid, chosen, numbers, samples, Dataset, Options, ReadError, Source};
use base64::Engine as _;
use glam::Vec3;
use insitu_core::Volume;
use quick_xml::events::{BytesStart, Event};
use std::io::Read;
use std::path::Path;

/// The grid a block fills, and its bytes.
struct Grid {
    dims: [usize; 3],
    spacing: Vec3,
    want: usize,
}

/// Where the chosen array is, and how it is encoded.
#[derive(Debug)]
pub struct Vti {
    sample: Sample,
    endian: Endian,
    wide_header: bool,
    zlib: bool,
    data: ArrayData,
}

#[derive(Debug)]
enum ArrayData {
    /// Whitespace-separated numbers.
    Ascii(String),
    /// Base64 of the block (inline `binary`, or appended `base64` from its offset).
    Base64(String),
    /// The block's bytes start at this file offset (appended `raw`).
    Raw(u64),
}

struct Array {
    name: String,
    sample: Sample,
    components: usize,
    format: String,
    offset: Option<u64>,
    text: String,
}

fn sample_type(name: &str) -> Option<Sample> {
    Some(match name {
        "Int8" => Sample::I8,
        "UInt8" => Sample::U8,
        "Int16" => Sample::I16,
        "UInt16" => Sample::U16,
        "Int32" => Sample::I32,
        "UInt32" => Sample::U32,
        "Int64" => Sample::I64,
        "UInt64" => Sample::U64,
        "Float32" => Sample::F32,
        "Float64" => Sample::F64,
        _ => return None,
    })
}

fn attr(e: &BytesStart, key: &str) -> Option<String> {
    e.attributes()
        .flatten()
        .find(|a| a.key.as_ref() == key.as_bytes())
        .and_then(|a| a.unescape_value().ok().map(|v| v.into_owned()))
}

/// The `VTKFile` element's byte order, header width and compression.
///
/// # Errors
/// [`ReadError`] naming the file for another dataset type or an unknown compressor.
fn file_attributes(path: &Path, e: &BytesStart) -> Result<(Endian, bool, bool), ReadError> {
    let bad = |m: String| ReadError::invalid(path, m);
    let kind = attr(e, "type").unwrap_or_default();
    if kind != "ImageData" {
        return Err(bad(format!("a VTK {kind:?} file: only ImageData is read")));
    }
    let endian = match attr(e, "byte_order").as_deref() {
        Some("BigEndian") => Endian::Big,
        _ => Endian::Little,
    };
    let wide_header = attr(e, "header_type").as_deref() == Some("UInt64");
    let zlib = match attr(e, "compressor").as_deref() {
        None | Some("") => false,
        Some("vtkZLibDataCompressor") => true,
        Some(other) => return Err(bad(format!("compressor {other}: only zlib is read"))),
    };
    Ok((endian, wide_header, zlib))
}

/// An `ImageData` element's whole extent, and its origin and spacing where it gives them.
type ImageGrid = (Vec<f64>, Option<Vec3>, Option<Vec3>);

/// The `ImageData` element's [`ImageGrid`].
///
/// # Errors
/// [`ReadError`] naming the file for a missing extent, bad numbers or a rotated grid.
fn image_data(path: &Path, e: &BytesStart) -> Result<ImageGrid, ReadError> {
    let bad = |m: String| ReadError::invalid(path, m);
    let ext = attr(e, "WholeExtent").ok_or_else(|| bad("ImageData has no WholeExtent".into()))?;
    let extent = numbers(path, "WholeExtent", &ext, 6)?;
    let triple = |name: &str| -> Result<Option<Vec3>, ReadError> {
        attr(e, name)
            .map(|o| {
                let v = numbers(path, name, &o, 3)?;
                Ok(Vec3::new(v[0] as f32, v[1] as f32, v[2] as f32))
            })
            .transpose()
    };
    let (origin, spacing) = (triple("Origin")?, triple("Spacing")?);
    if let Some(d) = attr(e, "Direction") {
        let v = numbers(path, "Direction", &d, 9)?;
        if v != [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0] {
            return Err(bad(format!(
                "Direction {d:?}: only axis-aligned grids (the identity) are read"
            )));
        }
    }
    Ok((extent, origin, spacing))
}

/// A point-data `DataArray` element, its text not read yet.
///
/// # Errors
/// [`ReadError`] naming the file and the array for an unknown type.
fn data_array(path: &Path, e: &BytesStart) -> Result<Array, ReadError> {
    let name = attr(e, "Name").unwrap_or_default();
    let t = attr(e, "type").unwrap_or_default();
    let sample = sample_type(&t)
        .ok_or_else(|| ReadError::invalid(path, format!("array {name}: unknown type {t:?}")))?;
    Ok(Array {
        name,
        sample,
        components: attr(e, "NumberOfComponents")
            .and_then(|c| c.parse().ok())
            .unwrap_or(1),
        format: attr(e, "format").unwrap_or_else(|| "ascii".into()),
        offset: attr(e, "offset").and_then(|o| o.parse().ok()),
        text: String::new(),
    })
}

/// Opens a `.vti` file, choosing `options.field`.
///
/// # Errors
/// [`ReadError`] naming the file: not ImageData, malformed XML, a missing attribute, a
/// rotated grid, several pieces, an unknown type or compressor, no array of that name.
pub fn open(path: &Path, options: &Options) -> Result<Dataset, ReadError> {
    let bad = |m: String| ReadError::invalid(path, m);
    // The XML ends where appended raw data begins (which is not XML): only that much is read.
    let (bytes, appended) = read_to_appended(path)?;
    let xml = &bytes[..appended.unwrap_or(bytes.len())];
    let mut reader = quick_xml::Reader::from_reader(xml);
    let mut buf = Vec::new();
    let (mut endian, mut wide_header, mut zlib) = (Endian::Little, false, false);
    let (mut extent, mut origin, mut spacing) = (None, Vec3::ZERO, Vec3::ONE);
    let (mut in_points, mut pieces, mut active) = (false, 0, None);
    let mut arrays: Vec<Array> = Vec::new();
    let mut open_array: Option<Array> = None;
    loop {
        let event = match reader.read_event_into(&mut buf) {
            Ok(e) => e,
            // The header cut at <AppendedData may leave the document unfinished.
            Err(_) if appended.is_some() => break,
            Err(e) => return Err(bad(format!("XML: {e}"))),
        };
        match &event {
            Event::Start(e) | Event::Empty(e) => match e.name().as_ref() {
                b"VTKFile" => (endian, wide_header, zlib) = file_attributes(path, e)?,
                b"ImageData" => {
                    let grid = image_data(path, e)?;
                    extent = Some(grid.0);
                    origin = grid.1.unwrap_or(origin);
                    spacing = grid.2.unwrap_or(spacing);
                }
                b"Piece" => {
                    pieces += 1;
                    if pieces > 1 {
                        return Err(bad("several pieces: only one-piece files are read".into()));
                    }
                    if let (Some(p), Some(w)) = (attr(e, "Extent"), &extent) {
                        if numbers(path, "Extent", &p, 6)? != *w {
                            return Err(bad(format!("piece extent {p:?} is not the whole extent")));
                        }
                    }
                }
                b"PointData" => {
                    in_points = matches!(event, Event::Start(_));
                    active = attr(e, "Scalars");
                }
                b"DataArray" if in_points => {
                    let a = data_array(path, e)?;
                    if matches!(event, Event::Start(_)) {
                        open_array = Some(a);
                    } else {
                        arrays.push(a);
                    }
                }
                _ => {}
            },
            Event::Text(t) => {
                if let Some(a) = open_array.as_mut() {
                    a.text.push_str(&String::from_utf8_lossy(t.as_ref()));
                }
            }
            Event::End(e) => match e.name().as_ref() {
                b"DataArray" => arrays.extend(open_array.take()),
                b"PointData" => in_points = false,
                _ => {}
            },
            Event::Eof => break,
            _ => {}
        }
        buf.clear();
    }
    let extent = extent.ok_or_else(|| bad("no ImageData element".into()))?;
    let dims = extent_dims(path, &extent)?;
    // VTK places the sample (i, j, k) of the extent at origin + (i, j, k) · spacing.
    let origin = origin + Vec3::new(extent[0] as f32, extent[2] as f32, extent[4] as f32) * spacing;
    check_grid(path, dims, spacing, origin)?;
    let names: Vec<String> = arrays.iter().map(|a| a.name.clone()).collect();
    let wanted = options.field.clone().or(active);
    let chosen = chosen(path, &names, wanted.as_deref(), "point-data array")?;
    let a = arrays.swap_remove(chosen);
    if a.components != 1 {
        return Err(bad(format!(
            "array {} has {} components: one is read",
            a.name, a.components
        )));
    }
    let data = match a.format.as_str() {
        "ascii" => ArrayData::Ascii(a.text),
        "binary" => ArrayData::Base64(a.text),
        "appended" => appended_data(path, &bytes, appended, &a)?,
        other => return Err(bad(format!("array {}: format {other:?}", a.name))),
    };
    Ok(Dataset {
        path: path.to_owned(),
        dims,
        steps: 1,
        spacing,
        origin,
        field: a.name,
        fields: names,
        notes: Vec::new(),
        source: Source::Vti(Vti {
            sample: a.sample,
            endian,
            wide_header,
            zlib,
            data,
        }),
    })
}

/// The grid's points per axis of a `WholeExtent` (`x0 x1 y0 y1 z0 z1`).
///
/// # Errors
/// [`ReadError`] naming the file when an axis is not a count of points.
fn extent_dims(path: &Path, extent: &[f64]) -> Result<[usize; 3], ReadError> {
    let mut dims = [0usize; 3];
    for a in 0..3 {
        let n = extent[2 * a + 1] - extent[2 * a] + 1.0;
        if !((1.0..1e9).contains(&n) && n.fract() == 0.0) {
            return Err(ReadError::invalid(
                path,
                format!("WholeExtent {extent:?} is not a grid"),
            ));
        }
        dims[a] = n as usize;
    }
    Ok(dims)
}

/// Where array `a`'s data lies in the `<AppendedData>` block that starts at `appended` in
/// `bytes`: raw from an offset, or base64 text.
///
/// # Errors
/// [`ReadError`] naming the file and the array: no block, an unclosed tag, no `_` mark, no
/// offset.
fn appended_data(
    path: &Path,
    bytes: &[u8],
    appended: Option<usize>,
    a: &Array,
) -> Result<ArrayData, ReadError> {
    let bad = |m: String| ReadError::invalid(path, m);
    let at = appended.ok_or_else(|| {
        bad(format!(
            "array {} is appended, but there is no AppendedData",
            a.name
        ))
    })?;
    let head = &bytes[at..];
    let tag_end = find(head, b">").ok_or_else(|| bad("AppendedData is not closed".into()))?;
    let tag = String::from_utf8_lossy(&head[..tag_end]);
    let underscore =
        find(&head[tag_end..], b"_").ok_or_else(|| bad("AppendedData has no '_' mark".into()))?;
    let start = (at + tag_end + underscore + 1) as u64;
    let offset = a
        .offset
        .ok_or_else(|| bad(format!("array {} has no offset", a.name)))?;
    if tag.contains("encoding=\"base64\"") {
        let all = crate::read_file(path)?;
        let from = usize::try_from(start + offset)
            .unwrap_or(usize::MAX)
            .min(all.len());
        let text: String = all[from..]
            .iter()
            .take_while(|&&b| b != b'<')
            .map(|&b| b as char)
            .collect();
        Ok(ArrayData::Base64(text))
    } else {
        Ok(ArrayData::Raw(start + offset))
    }
}

/// The file's bytes up to a little past `<AppendedData …>_` (all of it when there is none),
/// and where `<AppendedData` starts.
fn read_to_appended(path: &Path) -> Result<(Vec<u8>, Option<usize>), ReadError> {
    const MARK: &[u8] = b"<AppendedData";
    let mut file = crate::open_file(path)?;
    let mut bytes = Vec::new();
    let mut chunk = vec![0u8; 1 << 20];
    let mut at = None;
    loop {
        let n = file.read(&mut chunk).map_err(ReadError::io(path))?;
        let from = bytes.len().saturating_sub(MARK.len());
        bytes.extend_from_slice(&chunk[..n]);
        if at.is_none() {
            at = find(&bytes[from..], MARK).map(|p| from + p);
        }
        if let Some(a) = at {
            if n == 0 || find(&bytes[a..], b"_").is_some() {
                return Ok((bytes, at));
            }
        }
        if n == 0 {
            return Ok((bytes, None));
        }
    }
}

/// Where the appended data ends: the offset of the last `</AppendedData>`, found in the
/// file's last 64 KiB (VTK closes the element and the document right after the data).
///
/// # Errors
/// [`ReadError::Invalid`] naming `path` when there is none: the file was cut short.
fn appended_end(path: &Path, f: &mut std::fs::File, len: u64) -> Result<u64, ReadError> {
    const CLOSE: &[u8] = b"</AppendedData>";
    let from = len.saturating_sub(64 << 10);
    std::io::Seek::seek(f, std::io::SeekFrom::Start(from)).map_err(ReadError::io(path))?;
    let mut tail = Vec::new();
    f.read_to_end(&mut tail).map_err(ReadError::io(path))?;
    tail.windows(CLOSE.len())
        .rposition(|w| w == CLOSE)
        .map(|p| from + p as u64)
        .ok_or_else(|| {
            ReadError::invalid(
                path,
                "truncated: no </AppendedData> after the appended data (the file was cut short)",
            )
        })
}

fn find(hay: &[u8], needle: &[u8]) -> Option<usize> {
    hay.windows(needle.len()).position(|w| w == needle)
}

impl Vti {
    fn word(&self) -> usize {
        if self.wide_header {
            8
        } else {
            4
        }
    }

    fn words(&self, bytes: &[u8]) -> Vec<u64> {
        bytes
            .chunks_exact(self.word())
            .map(|c| {
                let mut b = [0u8; 8];
                b[..c.len()].copy_from_slice(c);
                if self.endian == Endian::Big {
                    b[..c.len()].reverse();
                }
                u64::from_le_bytes(b)
            })
            .collect()
    }

    pub(crate) fn read(
        &self,
        path: &Path,
        dims: [usize; 3],
        spacing: Vec3,
    ) -> Result<Volume, ReadError> {
        let n = samples(path, &dims)?;
        let want = n
            .checked_mul(self.sample.size())
            .ok_or_else(|| ReadError::invalid(path, "array size overflows"))?;
        let grid = Grid {
            dims,
            spacing,
            want,
        };
        match &self.data {
            ArrayData::Ascii(text) => {
                let v: Vec<f32> = text
                    .split_whitespace()
                    .map(|s| crate::bytes::parse_text(s, self.sample).ok_or(()))
                    .collect::<Result<_, _>>()
                    .map_err(|()| {
                        ReadError::invalid(path, "an ascii array holds something not a number")
                    })?;
                if v.len() != n {
                    return Err(ReadError::invalid(
                        path,
                        format!("{} ascii values where {dims:?} needs {n}", v.len()),
                    ));
                }
                Volume::new(dims, spacing, v).map_err(|e| ReadError::invalid(path, e.to_string()))
            }
            ArrayData::Base64(text) => self.decode_base64(path, text, &grid),
            ArrayData::Raw(at) => {
                let mut f = crate::open_file(path)?;
                let len = f.metadata().map_err(ReadError::io(path))?.len();
                // The block ends before `</AppendedData>`: what follows it is not samples.
                let end = appended_end(path, &mut f, len)?;
                std::io::Seek::seek(&mut f, std::io::SeekFrom::Start((*at).min(end)))
                    .map_err(ReadError::io(path))?;
                let left = end.saturating_sub(*at);
                self.read_block(path, std::io::BufReader::new(f), left, &grid)
            }
        }
    }

    /// A data block read from `from` (which holds `left` more bytes) and streamed into the
    /// volume: uncompressed samples as they come, zlib blocks one at a time.
    fn read_block(
        &self,
        path: &Path,
        mut from: impl Read,
        left: u64,
        grid: &Grid,
    ) -> Result<Volume, ReadError> {
        let (want, w) = (grid.want, self.word());
        let short = |what: &str| ReadError::invalid(path, format!("truncated: the array's {what}"));
        let read_words = |from: &mut dyn Read, k: usize, what: &str| {
            let mut b = vec![0u8; k.checked_mul(w).ok_or_else(|| short(what))?];
            from.read_exact(&mut b).map_err(|_| short(what))?;
            Ok::<_, ReadError>(self.words(&b))
        };
        let n = want / self.sample.size();
        if !self.zlib {
            let count = read_words(&mut from, 1, "byte count")?[0];
            if count != want as u64 {
                return Err(ReadError::invalid(
                    path,
                    format!("the array holds {count} bytes where the extent needs {want}"),
                ));
            }
            if left < (w + want) as u64 {
                return Err(short("samples"));
            }
            let mut s = Samples::new(path, self.sample, self.endian, n, n)?;
            s.read_from(path, from, want, false)?;
            return s.finish(path, grid.dims, grid.spacing);
        }
        let head = read_words(&mut from, 3, "block header")?;
        let (blocks, size, last) = (head[0], head[1], head[2]);
        let blocks = usize::try_from(blocks)
            .ok()
            .filter(|&b| b <= want / size.max(1) as usize + 1 && (b * w) as u64 <= left)
            .ok_or_else(|| {
                ReadError::invalid(path, format!("{blocks} compressed blocks for {want} bytes"))
            })?;
        let sizes = read_words(&mut from, blocks, "block sizes")?;
        let total = if blocks == 0 {
            0
        } else {
            size * (blocks as u64 - 1) + if last == 0 { size } else { last }
        };
        if total != want as u64 {
            return Err(ReadError::invalid(
                path,
                format!("compressed blocks of {total} bytes where the extent needs {want}"),
            ));
        }
        let compressed: u64 = sizes.iter().fold(0u64, |a, &c| a.saturating_add(c));
        if compressed > left {
            return Err(short("compressed blocks"));
        }
        // Reserved as the data decompresses (at most 1032:1, deflate's limit).
        let bound = usize::try_from(compressed.saturating_mul(1032)).unwrap_or(usize::MAX)
            / self.sample.size();
        let mut s = Samples::new(path, self.sample, self.endian, n, bound)?;
        let (mut packed, mut plain) = (Vec::new(), Vec::new());
        for (k, &c) in sizes.iter().enumerate() {
            packed.resize(c as usize, 0);
            from.read_exact(&mut packed)
                .map_err(|_| short("compressed blocks"))?;
            let expect = if k + 1 == blocks && last != 0 {
                last
            } else {
                size
            };
            plain.clear();
            flate2::read::ZlibDecoder::new(&packed[..])
                .take(expect + 1)
                .read_to_end(&mut plain)
                .map_err(|e| ReadError::invalid(path, format!("zlib block {k}: {e}")))?;
            if plain.len() as u64 != expect {
                return Err(ReadError::invalid(
                    path,
                    format!("zlib block {k} holds {} bytes, not {expect}", plain.len()),
                ));
            }
            s.push(&plain)?;
        }
        s.finish(path, grid.dims, grid.spacing)
    }

    /// A base64 block (text that may run on into other arrays' blocks): the header and the
    /// data encoded as one stream, or (as VTK writes them) each on its own.
    fn decode_base64(&self, path: &Path, text: &str, grid: &Grid) -> Result<Volume, ReadError> {
        let clean: String = text.chars().filter(|c| !c.is_ascii_whitespace()).collect();
        let b64 = base64::engine::general_purpose::STANDARD;
        let chars = |bytes: usize| bytes.div_ceil(3).saturating_mul(4);
        let decode = |from: usize, len: usize| -> Option<Vec<u8>> {
            let end = from.checked_add(len)?;
            b64.decode(clean.get(from..end)?).ok()
        };
        let (want, w) = (grid.want, self.word());
        // The first word says how many bytes (uncompressed) or blocks follow.
        let first = decode(0, chars(w))
            .filter(|b| b.len() >= w)
            .ok_or_else(|| {
                ReadError::invalid(path, "base64: the array's header does not decode")
            })?;
        let count = usize::try_from(self.words(&first[..w])[0]).unwrap_or(usize::MAX);
        let header = if self.zlib {
            count.min(want / 2 + 2).saturating_add(3).saturating_mul(w)
        } else {
            w
        };
        // The data's length, from the header's words.
        let data_len = |head: &[u8]| -> usize {
            if self.zlib {
                self.words(head.get(3 * w..header).unwrap_or_default())
                    .iter()
                    .fold(0usize, |s, &c| {
                        s.saturating_add(usize::try_from(c).unwrap_or(usize::MAX))
                    })
            } else {
                count
            }
        };
        let block = |bytes: &[u8]| self.read_block(path, bytes, bytes.len() as u64, grid);
        let mut tried = Vec::new();
        // One stream: the header's words, then the data, without padding between them.
        if let Some(head) = decode(0, chars(header)).filter(|h| h.len() >= header) {
            let total = header.saturating_add(data_len(&head));
            if let Some(all) = decode(0, chars(total)) {
                match block(&all) {
                    Ok(v) => return Ok(v),
                    Err(e) => tried.push(e.to_string()),
                }
            }
        }
        // Apart: the header padded on its own, then the data.
        if let Some(head) = decode(0, chars(header)) {
            if let Some(data) = decode(chars(header), chars(data_len(&head))) {
                let mut joined = head;
                joined.extend_from_slice(&data);
                return block(&joined);
            }
        }
        Err(ReadError::invalid(
            path,
            format!(
                "base64 data does not decode as one block {}",
                tried.join("; ")
            ),
        ))
    }
}
