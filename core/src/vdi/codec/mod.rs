//! The VDI file format: versioned, compressed, checksummed, validated on decode.
//!
//! ```text
//! offset  size  field
//!  0       8    magic  89 'V' 'D' 'I' 0D 0A 1A 0A
//!  8       2    format version (u16 LE) = 3
//! 10       1    codec: 0 none, 1 bzip2, 2 zstd
//! 11       1    reserved = 0
//! 12       8    payload length after decompression (u64 LE)
//! 20       8    body length (u64 LE) = file length − 32
//! 28       4    CRC-32 of bytes 0..28 and the body
//! 32       …    body: the payload in parts, each compressed on its own with the codec
//! ```
//!
//! The body (version 3): the length of the provenance block (u32 LE, 0 when there is none) and
//! the block ([`super::provenance`]: step, rank, world, `P_M` version, brick), uncompressed;
//! then the part count `m` (u32 LE), per part its compressed and its decompressed length (u64
//! LE each), then the parts' compressed bytes back to back. The parts are consecutive pieces of
//! the payload, so they are compressed and decompressed in parallel (rayon): bzip2 in parts of
//! [`BZIP2_PART`] bytes, zstd in parts of [`ZSTD_PART`], `none` in one part. Version 2 files (no
//! provenance) and version 1 files (one stream of the whole payload, no table) are still read.
//!
//! The payload (all little-endian): `r` u32, γ f32, step f32, termination f32, shaded u8;
//! camera eye, target, up (3 × f32 each), fov_y_deg f32; volume box min, max (3 × f32 each);
//! TF hash u64, TF name length u16 and UTF-8 bytes; supersegment count `n` u64; `r²` per-pixel
//! counts (u32, row-major from the top); then six planes of `n` f32: `z_start`, `z_end`, red,
//! green, blue, `â`. Planes compress better than interleaved records.
//!
//! σ (Sec. 5.3) is the length of the whole file. Decoding checks the header, the checksum,
//! that the claimed size is under [`DecodeLimits`] before anything is allocated for it, that
//! counts agree with lengths, and that every number is finite and in range, so a decoded
//! [`Vdi`] is safe to render.

pub(super) mod format;
pub mod quantized;

use format::Reader;
pub use format::{Codec, CodecError, FORMAT_VERSION, MAGIC};

use super::provenance::Provenance;
use super::{Precision, Supersegment, Vdi, VdiMeta, VdiParams, MAX_RESOLUTION};
use crate::camera::Camera;
use crate::volume::Aabb;
use rayon::prelude::*;
use std::io::Read;

/// The version of 32-bit float planes, written for [`Precision::Float32`].
pub const FORMAT_VERSION_FLOAT: u16 = 3;
/// The version before provenance, still read.
const FORMAT_VERSION_PARTS: u16 = 2;
/// The version before parts (the body one stream), still read.
const FORMAT_VERSION_SINGLE: u16 = 1;
/// Longest provenance block read, bytes (this version writes [`super::provenance::LEN`] plus
/// 4 bytes per rank a host composed into the VDI, 4 and 8: room for 16 000 ranks in one part).
const MAX_PROVENANCE: usize = 65_536;
/// Payload bytes per bzip2 part: two blocks at bzip2's best compression (900 k each). σ stays
/// that of one stream within 0.2 % (teapot, r = 256 and 768: 2 139 358 against 2 143 794 bytes,
/// 18 047 709 against 18 050 853), where parts of one block cost up to 1.4 % (a part's last
/// block is seldom full); on two cores, encoding and decoding take 1.6× (r = 256) to 1.9×
/// (r = 768) less time.
pub const BZIP2_PART: usize = 1_800_000;
/// Payload bytes per zstd part (level 3, whose window is a few MB): σ within 0.2 % of one
/// frame's (teapot, r = 768: 22 267 140 against 22 231 607 bytes; 4 MB parts: 0.45 %), encoding
/// 1.6× and decoding 1.4× faster on two cores; smaller payloads (r = 256) stay one part.
pub const ZSTD_PART: usize = 8_000_000;
const HEADER_LEN: usize = 32;
const MAX_TF_NAME: usize = 1024;

/// Bounds applied while decoding untrusted bytes.
#[derive(Clone, Copy, Debug)]
pub struct DecodeLimits {
    /// Largest accepted payload after decompression, bytes.
    pub max_payload_bytes: u64,
}

impl Default for DecodeLimits {
    /// 4 GiB: a 16384² VDI with ~40 supersegments per pixel.
    fn default() -> Self {
        Self {
            max_payload_bytes: 4 << 30,
        }
    }
}

/// Serialises and compresses `vdi` with `codec`, its parts in parallel (on the calling
/// thread's rayon pool), without provenance; the result's length is σ.
///
/// # Errors
/// [`CodecError::Compress`] if the compressor fails.
pub fn encode(vdi: &Vdi, codec: Codec) -> Result<Vec<u8>, CodecError> {
    encode_with_provenance(vdi, codec, None)
}

/// As [`encode`], the file carrying `provenance` (where in a run the VDI comes from) when
/// given; the result's length is σ.
///
/// # Errors
/// [`CodecError::Compress`] if the compressor fails.
pub fn encode_with_provenance(
    vdi: &Vdi,
    codec: Codec,
    provenance: Option<&Provenance>,
) -> Result<Vec<u8>, CodecError> {
    let block = provenance.map(Provenance::to_bytes).unwrap_or_default();
    let (version, parts) = match vdi.meta().params.precision {
        Precision::Float32 => (FORMAT_VERSION_FLOAT, float_parts(vdi, codec)?),
        Precision::Bits(bits) => (FORMAT_VERSION, quantized::encode_parts(vdi, bits, codec)?),
    };
    Ok(assemble(version, codec, &block, &parts))
}

/// The version 3 payload ([`payload`]) in consecutive pieces, each compressed on its own, in
/// parallel: `(compressed bytes, payload bytes)` per part.
fn float_parts(vdi: &Vdi, codec: Codec) -> Result<Vec<(Vec<u8>, u64)>, CodecError> {
    let payload = payload(vdi);
    let part = match codec {
        Codec::Bzip2 => BZIP2_PART,
        Codec::Zstd => ZSTD_PART,
        Codec::None => payload.len().max(1),
    };
    payload
        .par_chunks(part)
        .map(|piece| Ok((compress(codec, piece)?, piece.len() as u64)))
        .collect()
}

/// A whole file: the header, then the body (the provenance block, the part table and the
/// parts), under one checksum.
fn assemble(version: u16, codec: Codec, block: &[u8], parts: &[(Vec<u8>, u64)]) -> Vec<u8> {
    let table = 4 + block.len() + 4 + 16 * parts.len();
    let mut body = Vec::with_capacity(table + parts.iter().map(|p| p.0.len()).sum::<usize>());
    body.extend_from_slice(&(block.len() as u32).to_le_bytes());
    body.extend_from_slice(block);
    body.extend_from_slice(&(parts.len() as u32).to_le_bytes());
    for (compressed, len) in parts {
        body.extend_from_slice(&(compressed.len() as u64).to_le_bytes());
        body.extend_from_slice(&len.to_le_bytes());
    }
    for (compressed, _) in parts {
        body.extend_from_slice(compressed);
    }
    let payload_len: u64 = parts.iter().map(|p| p.1).sum();
    let mut out = Vec::with_capacity(HEADER_LEN + body.len());
    out.extend_from_slice(&MAGIC);
    out.extend_from_slice(&version.to_le_bytes());
    out.push(codec.id());
    out.push(0);
    out.extend_from_slice(&payload_len.to_le_bytes());
    out.extend_from_slice(&(body.len() as u64).to_le_bytes());
    let crc = checksum(&out, &body);
    out.extend_from_slice(&crc.to_le_bytes());
    out.extend_from_slice(&body);
    out
}

/// One part of the payload compressed with `codec`.
pub(super) fn compress(codec: Codec, piece: &[u8]) -> Result<Vec<u8>, CodecError> {
    let err = |source| CodecError::Compress { codec, source };
    Ok(match codec {
        Codec::None => piece.to_vec(),
        Codec::Bzip2 => {
            let mut out = Vec::new();
            bzip2::read::BzEncoder::new(piece, bzip2::Compression::best())
                .read_to_end(&mut out)
                .map_err(err)?;
            out
        }
        Codec::Zstd => zstd::stream::encode_all(piece, 3).map_err(err)?,
    })
}

fn checksum(header: &[u8], body: &[u8]) -> u32 {
    let mut h = crc32fast::Hasher::new();
    h.update(header);
    h.update(body);
    h.finalize()
}

/// The version 3 payload: the metadata ([`write_meta`]), the supersegment count, the
/// per-pixel counts and the six float planes.
fn payload(vdi: &Vdi) -> Vec<u8> {
    let segs = vdi.supersegments();
    let r = vdi.resolution() as usize;
    let mut out = Vec::with_capacity(128 + MAX_TF_NAME + 4 * r * r + 24 * segs.len());
    write_meta(&mut out, vdi.meta());
    out.extend_from_slice(&(segs.len() as u64).to_le_bytes());
    for w in vdi.offsets().windows(2) {
        out.extend_from_slice(&(w[1] - w[0]).to_le_bytes());
    }
    let planes: [fn(&Supersegment) -> f32; 6] = [
        |s| s.z_start,
        |s| s.z_end,
        |s| s.color[0],
        |s| s.color[1],
        |s| s.color[2],
        |s| s.alpha,
    ];
    for get in planes {
        segs.iter()
            .for_each(|s| out.extend_from_slice(&get(s).to_le_bytes()));
    }
    out
}

/// The metadata every version's payload starts with: `r`, γ, the ray-casting step and
/// termination, shading, camera, volume box, TF hash and name ([`read_meta`] reads it).
pub(super) fn write_meta(out: &mut Vec<u8>, m: &VdiMeta) {
    let name = truncate_utf8(&m.tf_name, MAX_TF_NAME);
    let f = |out: &mut Vec<u8>, v: f32| out.extend_from_slice(&v.to_le_bytes());
    out.extend_from_slice(&m.params.resolution.to_le_bytes());
    f(out, m.params.gamma);
    f(out, m.sample_distance);
    f(out, m.termination);
    out.push(u8::from(m.shaded));
    for v in [m.camera.eye, m.camera.target, m.camera.up] {
        v.to_array().into_iter().for_each(|c| f(out, c));
    }
    f(out, m.camera.fov_y_deg);
    for v in [m.volume_box.min, m.volume_box.max] {
        v.to_array().into_iter().for_each(|c| f(out, c));
    }
    out.extend_from_slice(&m.tf_hash.to_le_bytes());
    out.extend_from_slice(&(name.len() as u16).to_le_bytes());
    out.extend_from_slice(name.as_bytes());
}

fn truncate_utf8(s: &str, max: usize) -> &str {
    let mut end = s.len().min(max);
    while !s.is_char_boundary(end) {
        end -= 1;
    }
    &s[..end]
}

/// Decodes and validates a VDI file.
///
/// # Errors
/// Any [`CodecError`]: wrong magic or version, unknown codec, a claimed size over `limits`,
/// checksum mismatch, a body that does not decompress to exactly the claimed length, counts
/// that disagree with lengths, a non-finite number, a depth range or colour out of range, or
/// lists that are not depth-sorted; a provenance block that is malformed.
pub fn decode(bytes: &[u8], limits: &DecodeLimits) -> Result<Vdi, CodecError> {
    decode_with_provenance(bytes, limits).map(|(vdi, _)| vdi)
}

/// As [`decode`], with the file's provenance (none in files before version 3, or written
/// without it).
///
/// # Errors
/// As [`decode`].
pub fn decode_with_provenance(
    bytes: &[u8],
    limits: &DecodeLimits,
) -> Result<(Vdi, Option<Provenance>), CodecError> {
    let file = File::read(bytes)?;
    if file.payload_len > limits.max_payload_bytes {
        return Err(CodecError::TooLarge {
            claimed: file.payload_len,
            limit: limits.max_payload_bytes,
        });
    }
    let computed = checksum(&bytes[..28], file.body);
    if computed != file.stored_crc {
        return Err(CodecError::Checksum {
            stored: file.stored_crc,
            computed,
        });
    }
    let payload = match file.version {
        FORMAT_VERSION => {
            let parts = part_table(file.parts, file.payload_len)?;
            let vdi = quantized::decode_parts(file.codec, &parts, limits)?;
            return Ok((vdi, file.provenance));
        }
        FORMAT_VERSION_SINGLE => decompress(
            file.codec,
            file.parts,
            file.payload_len,
            ("the body", "the header"),
        )?,
        _ => decompress_parts(file.codec, file.parts, file.payload_len)?,
    };
    Ok((parse_payload(&payload)?, file.provenance))
}

/// The provenance of a VDI file from its header and provenance block alone (nothing is
/// decompressed and the checksum is not computed: [`decode`] checks the whole file).
///
/// # Errors
/// As [`decode`] for the header and the block.
pub fn provenance(bytes: &[u8]) -> Result<Option<Provenance>, CodecError> {
    File::read(bytes).map(|f| f.provenance)
}

/// The codec a VDI file was compressed with, from its header alone.
///
/// # Errors
/// As [`decode`] for the header and the provenance block.
pub fn codec_of(bytes: &[u8]) -> Result<Codec, CodecError> {
    File::read(bytes).map(|f| f.codec)
}

/// A file's header and its body split into the provenance and the parts.
struct File<'a> {
    version: u16,
    codec: Codec,
    payload_len: u64,
    stored_crc: u32,
    /// The whole body, under the checksum.
    body: &'a [u8],
    provenance: Option<Provenance>,
    /// The part table and parts (version 1: the one stream).
    parts: &'a [u8],
}

impl<'a> File<'a> {
    fn read(bytes: &'a [u8]) -> Result<Self, CodecError> {
        let mut hdr = Reader::new(bytes);
        if hdr.take(8, "magic")? != MAGIC {
            return Err(CodecError::BadMagic);
        }
        let version = hdr.u16("version")?;
        if ![
            FORMAT_VERSION,
            FORMAT_VERSION_FLOAT,
            FORMAT_VERSION_PARTS,
            FORMAT_VERSION_SINGLE,
        ]
        .contains(&version)
        {
            return Err(CodecError::UnsupportedVersion(version));
        }
        let codec_id = hdr.u8("codec")?;
        let codec = Codec::from_id(codec_id).ok_or(CodecError::UnknownCodec(codec_id))?;
        if hdr.u8("reserved")? != 0 {
            return Err(CodecError::Invalid("reserved header byte is not 0".into()));
        }
        let payload_len = hdr.u64("payload length")?;
        let body_len = hdr.u64("body length")?;
        let stored_crc = hdr.u32("checksum")?;
        let body = hdr.rest();
        if body_len != body.len() as u64 {
            return Err(CodecError::Invalid(format!(
                "header says the body has {body_len} bytes, the file holds {}",
                body.len()
            )));
        }
        let mut rd = Reader::new(body);
        let provenance = if version >= FORMAT_VERSION_FLOAT {
            let len = rd.u32("provenance length")? as usize;
            if len > MAX_PROVENANCE {
                return Err(CodecError::Invalid(format!(
                    "a provenance block of {len} bytes (at most {MAX_PROVENANCE})"
                )));
            }
            let block = rd.take(len, "provenance")?;
            (len > 0)
                .then(|| Provenance::from_bytes(block))
                .transpose()?
        } else {
            None
        };
        Ok(Self {
            version,
            codec,
            payload_len,
            stored_crc,
            body,
            provenance,
            parts: rd.rest(),
        })
    }
}

/// The part table of a version 2–4 body checked against the body and the header's payload
/// length: each part's compressed bytes and its stated decompressed length.
pub(super) fn part_table(body: &[u8], payload_len: u64) -> Result<Vec<(&[u8], u64)>, CodecError> {
    let mut rd = Reader::new(body);
    let count = rd.u32("part count")? as usize;
    // At least a byte a part and 16 table bytes each: a count beyond what the body holds is
    // refused before anything is allocated for it.
    if count == 0 || count > body.len() / 16 {
        return Err(CodecError::Invalid(format!(
            "{count} parts in a body of {} bytes",
            body.len()
        )));
    }
    let mut table = Vec::with_capacity(count);
    for _ in 0..count {
        table.push((rd.u64("part length")?, rd.u64("part payload length")?));
    }
    let data = rd.rest();
    let total = |f: fn(&(u64, u64)) -> u64| {
        table
            .iter()
            .try_fold(0u64, |sum, part| sum.checked_add(f(part)))
            .unwrap_or(u64::MAX)
    };
    if total(|p| p.0) != data.len() as u64 || total(|p| p.1) != payload_len {
        return Err(CodecError::Invalid(format!(
            "the part table says {} compressed bytes making {} payload bytes; the body holds \
             {} after the table and the header says {payload_len}",
            total(|p| p.0),
            total(|p| p.1),
            data.len()
        )));
    }
    // The compressed lengths sum to the body's, so each split fits.
    let mut parts = Vec::with_capacity(count);
    let mut data = data;
    for &(compressed, len) in &table {
        let (input, more) = data.split_at(compressed as usize);
        parts.push((input, len));
        data = more;
    }
    Ok(parts)
}

/// The payload of a version 2 or 3 body: the parts decompressed in parallel, each to exactly
/// its stated length, back to back.
fn decompress_parts(codec: Codec, body: &[u8], payload_len: u64) -> Result<Vec<u8>, CodecError> {
    let parts = part_table(body, payload_len)?;
    let count = parts.len();
    // Each part's piece of the payload (the lengths sum to the payload's, under the limits).
    let mut out = vec![0u8; payload_len as usize];
    let mut jobs = Vec::with_capacity(count);
    let mut rest = &mut out[..];
    for &(input, len) in &parts {
        let (piece, tail) = std::mem::take(&mut rest).split_at_mut(len as usize);
        jobs.push((input, piece));
        rest = tail;
    }
    jobs.into_par_iter()
        .enumerate()
        .try_for_each(|(i, (input, piece))| {
            let what = format!("part {i} of {count}");
            let part = decompress(codec, input, piece.len() as u64, (&what, "the part table"))?;
            piece.copy_from_slice(&part);
            Ok::<_, CodecError>(())
        })?;
    Ok(out)
}

/// Decompresses at most `expected + 1` bytes, growing the buffer only as data arrives; an
/// error names `what` was decompressed and what `stated` the length.
pub(super) fn decompress(
    codec: Codec,
    body: &[u8],
    expected: u64,
    (what, stated): (&str, &str),
) -> Result<Vec<u8>, CodecError> {
    let err = |source| CodecError::Decompress { codec, source };
    let mut out = Vec::with_capacity(expected.min(1 << 20) as usize);
    match codec {
        Codec::None => out.extend_from_slice(body),
        Codec::Bzip2 => {
            bzip2::read::BzDecoder::new(body)
                .take(expected + 1)
                .read_to_end(&mut out)
                .map_err(err)?;
        }
        Codec::Zstd => {
            zstd::stream::read::Decoder::new(body)
                .map_err(err)?
                .take(expected + 1)
                .read_to_end(&mut out)
                .map_err(err)?;
        }
    }
    if out.len() as u64 != expected {
        return Err(CodecError::Invalid(format!(
            "{what} decompresses to {}{} bytes, {stated} says {expected}",
            out.len(),
            if out.len() as u64 > expected { "+" } else { "" }
        )));
    }
    Ok(out)
}

/// The payload: metadata, then the supersegment count, the per-pixel counts and the six
/// planes, each checked as it is read.
fn parse_payload(p: &[u8]) -> Result<Vdi, CodecError> {
    let mut rd = Reader::new(p);
    let meta = read_meta(&mut rd)?;
    let n = rd.u64("supersegment count")?;
    let pixels = u64::from(meta.params.resolution).pow(2);
    // Lengths first: nothing is allocated for a count the bytes cannot hold.
    let needed = (pixels * 4).saturating_add(n.saturating_mul(24));
    if needed != rd.remaining() as u64 {
        return Err(CodecError::Invalid(format!(
            "{pixels} counts and {n} supersegments need {needed} bytes, payload has {} left",
            rd.remaining()
        )));
    }
    let n = n as usize;
    let offsets = read_offsets(&mut rd, pixels as usize, n)?;
    let segs = read_supersegments(&mut rd, n)?;
    check_depth_order(&offsets, &segs)?;
    Vdi::from_parts(meta, offsets, segs)
        .ok_or_else(|| CodecError::Invalid("offsets do not match the lists".into()))
}

/// The metadata: `P_M`, the ray-casting step and termination, shading, camera, volume box,
/// TF hash and name, each checked for range.
pub(super) fn read_meta(rd: &mut Reader<'_>) -> Result<VdiMeta, CodecError> {
    let resolution = rd.u32("r")?;
    if !(1..=MAX_RESOLUTION).contains(&resolution) {
        return Err(CodecError::Invalid(format!(
            "r = {resolution} outside 1..={MAX_RESOLUTION}"
        )));
    }
    let gamma = rd.finite("gamma")?;
    let step = rd.finite("step")?;
    let termination = rd.finite("termination")?;
    if gamma < 0.0 || step <= 0.0 || !(termination > 0.0 && termination <= 1.0) {
        return Err(CodecError::Invalid(format!(
            "gamma {gamma}, step {step} or termination {termination} out of range"
        )));
    }
    let shaded = match rd.u8("shaded")? {
        0 => false,
        1 => true,
        v => {
            return Err(CodecError::Invalid(format!(
                "shaded flag {v} is not 0 or 1"
            )))
        }
    };
    let camera = Camera {
        eye: rd.vec3("camera eye")?,
        target: rd.vec3("camera target")?,
        up: rd.vec3("camera up")?,
        fov_y_deg: rd.finite("camera fov")?,
    };
    if !camera.is_valid() {
        return Err(CodecError::Invalid(format!("degenerate camera {camera:?}")));
    }
    let volume_box = Aabb {
        min: rd.vec3("box min")?,
        max: rd.vec3("box max")?,
    };
    if !volume_box.min.cmple(volume_box.max).all() {
        return Err(CodecError::Invalid(format!(
            "volume box {volume_box:?} is inverted"
        )));
    }
    let tf_hash = rd.u64("tf hash")?;
    let name_len = rd.u16("tf name length")? as usize;
    if name_len > MAX_TF_NAME {
        return Err(CodecError::Invalid(format!("tf name of {name_len} bytes")));
    }
    let tf_name = std::str::from_utf8(rd.take(name_len, "tf name")?)
        .map_err(|_| CodecError::Invalid("tf name is not UTF-8".into()))?
        .to_owned();
    Ok(VdiMeta {
        camera,
        params: VdiParams {
            resolution,
            gamma,
            precision: Precision::Float32,
        },
        sample_distance: step,
        termination,
        shaded,
        volume_box,
        tf_hash,
        tf_name,
    })
}

/// The prefix offsets (`pixels + 1`, from 0) of the per-pixel counts, which must add up to `n`.
fn read_offsets(rd: &mut Reader<'_>, pixels: usize, n: usize) -> Result<Vec<u32>, CodecError> {
    let counts = rd.take(pixels * 4, "counts")?;
    let mut offsets = Vec::with_capacity(pixels + 1);
    offsets.push(0u32);
    let mut total = 0u64;
    for c in counts.chunks_exact(4) {
        total += u64::from(u32::from_le_bytes([c[0], c[1], c[2], c[3]]));
        if total > n as u64 {
            return Err(CodecError::Invalid(format!(
                "pixel counts exceed the {n} supersegments"
            )));
        }
        offsets.push(total as u32);
    }
    if total != n as u64 {
        return Err(CodecError::Invalid(format!(
            "pixel counts add up to {total}, header says {n} supersegments"
        )));
    }
    Ok(offsets)
}

/// `n` supersegments from the six planes (`z_start`, `z_end`, r, g, b, α): finite, depths
/// `0 ≤ start ≤ end`, colour and opacity in [0, 1].
fn read_supersegments(rd: &mut Reader<'_>, n: usize) -> Result<Vec<Supersegment>, CodecError> {
    let mut planes = [(); 6].map(|_| Vec::new());
    for (k, plane) in planes.iter_mut().enumerate() {
        *plane = rd
            .take(n * 4, "supersegment plane")?
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect();
        if let Some(i) = plane.iter().position(|v| !v.is_finite()) {
            return Err(CodecError::Invalid(format!(
                "supersegment {i}: field {k} is not finite"
            )));
        }
    }
    let [zs, ze, cr, cg, cb, ca] = planes;
    let mut segs = Vec::with_capacity(n);
    for i in 0..n {
        let s = Supersegment {
            z_start: zs[i],
            z_end: ze[i],
            color: [cr[i], cg[i], cb[i]],
            alpha: ca[i],
        };
        if !(s.z_start >= 0.0 && s.z_start <= s.z_end) {
            return Err(CodecError::Invalid(format!(
                "supersegment {i}: depth range [{}, {}] is not 0 <= start <= end",
                s.z_start, s.z_end
            )));
        }
        if s.color
            .iter()
            .chain([&s.alpha])
            .any(|v| !(0.0..=1.0).contains(v))
        {
            return Err(CodecError::Invalid(format!(
                "supersegment {i}: colour {:?} or opacity {} outside [0, 1]",
                s.color, s.alpha
            )));
        }
        segs.push(s);
    }
    Ok(segs)
}

/// Each pixel's list (`offsets[p]..offsets[p + 1]` of `segs`) is depth-sorted without overlap.
pub(super) fn check_depth_order(offsets: &[u32], segs: &[Supersegment]) -> Result<(), CodecError> {
    for w in offsets.windows(2) {
        let list = &segs[w[0] as usize..w[1] as usize];
        if list.windows(2).any(|p| p[1].z_start < p[0].z_end) {
            return Err(CodecError::Invalid(format!(
                "supersegments {}..{} are not depth-sorted without overlap",
                w[0], w[1]
            )));
        }
    }
    Ok(())
}
