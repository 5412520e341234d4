//! Format version 4: supersegments quantised to stated error bounds, delta-coded along each
//! list and split into byte planes before the entropy stage (docs/conventions.md, "The VDI
//! file").
//!
//! **Depths** lie on a grid of quanta `Δ = 2^e` world units: `e = ⌊log₂ step⌋ −`
//! [`DEPTH_SUBSTEPS_LOG2`], raised while the deepest depth would need more than 2²³ quanta
//! (so every `q·Δ` is exact in `f32` and re-encoding a decoded VDI gives the same quanta).
//! Every depth is within `Δ / 2` of its float (a supersegment shorter than `Δ` keeps a length
//! of one quantum, moving the depths behind it by at most that much). The grid depends on the
//! step alone, so the ranks of a world share it and composing decoded ranks is exact.
//!
//! **Colour** `ĉ` is stored to `b` bits (`v = round(ĉ · M)`, `M = 2^b − 1`), within
//! `0.5 / M`. **Opacity** is stored as the opacity over the supersegment's depth extent
//! `A = 1 − (1 − â)^(z_end − z_start)`, to `b` bits within `0.5 / M`, and decoded to
//! `â = 1 − (1 − A)^(1 / (z_end − z_start))` on the stored depths: at the generation view a
//! pixel's supersegment keeps its opacity within `0.5 / (M · cos θ)` (`θ` the ray's angle to
//! the view direction, ≤ 21° at the default 30° field of view), and `â = 1` stays 1.
//!
//! The payload's parts (each compressed on its own, all in parallel): part 0, the head —
//! the metadata ([`super::write_meta`]), `b` (u8), `e` (i8), the supersegment count `n`
//! (u64), the band count (u32) and per band its pixel count (u32) and supersegment count
//! (u64); then one part per band (consecutive pixels, about [`BAND_SEGMENTS`] supersegments):
//!
//! ```text
//! counts         LEB128, one per pixel
//! widths         3 × u8: bytes of a first-depth delta, a gap, a length (0–4 each)
//! first          per non-empty pixel: its first start's quanta minus the previous non-empty
//!                pixel's (zigzag), width-many byte planes, low byte first
//! gap            per later supersegment: its start minus the previous one's end, quanta
//! length         per supersegment: its end minus its start minus one, quanta
//! r, g, b, A     per supersegment: 1 byte plane (b ≤ 8) or 2 (low, high)
//! ```
//!
//! Decoding checks every length against the table before allocating, every quantum sum
//! against the grid, every colour against `M`, and the lists' order, so a decoded VDI is as
//! safe to render as a version 3 one.

use super::{
    check_depth_order, compress, decompress, read_meta, write_meta, Codec, CodecError, Reader,
};
use crate::vdi::{Precision, Supersegment, Vdi};
use rayon::prelude::*;

/// Depth quanta per ray-casting step, log₂: `Δ` is at most 1/8 of the step, so a depth is
/// within 1/16 step of its float. Measured (`cargo bench -p insitu-core --bench codec`,
/// 8 bits): 1/64 of a step cost 5–10 % more bytes for no q (the renders' PSNR against the
/// float VDI's rose by 1–3 dB, from above 62 dB); 1/2 of a step saved 2–5 % more and lost up
/// to 0.2 dB of q.
pub const DEPTH_SUBSTEPS_LOG2: i32 = 3;
/// Supersegments a band holds (about 0.6 MB of planes at 10 bits): enough to compress well,
/// small enough that a 256² VDI still has parts for every core.
pub const BAND_SEGMENTS: usize = 1 << 16;
/// Most quanta the encoder lets the deepest depth take: below 2²⁴, so `q·Δ` is exact in
/// `f32`, with room for supersegments lengthened to one quantum.
const GRID_QUANTA: u64 = 1 << 23;
/// Most quanta a decoded depth may have.
const MAX_QUANTA: u64 = 1 << 24;
/// Exponents a file may state (`Δ` from 2⁻¹²⁶, the least normal `f32`, to 2¹⁰⁴).
const EXPONENTS: std::ops::RangeInclusive<i32> = -126..=104;
/// Fewest decompressed bytes a supersegment takes in a band (a length byte and four colour
/// bytes at width 0 for the rest): bounds a claimed count before anything is allocated.
const MIN_SEGMENT_BYTES: u64 = 4;

/// The depth grid `Δ = 2^exponent` world units.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct DepthGrid {
    /// `e`.
    pub exponent: i32,
}

impl DepthGrid {
    /// The grid for a VDI made with ray-casting step `step` whose deepest depth is `max_z`
    /// (both world units, finite, `step > 0`).
    pub fn new(step: f32, max_z: f32) -> Self {
        let mut exponent = (step.log2().floor() as i32 - DEPTH_SUBSTEPS_LOG2)
            .clamp(*EXPONENTS.start(), *EXPONENTS.end());
        while exponent < *EXPONENTS.end()
            && f64::from(max_z) / 2f64.powi(exponent) >= GRID_QUANTA as f64
        {
            exponent += 1;
        }
        Self { exponent }
    }

    /// `Δ`, world units.
    pub fn quantum(self) -> f64 {
        2f64.powi(self.exponent)
    }

    fn quanta(self, z: f32) -> u64 {
        (f64::from(z) / self.quantum()).round() as u64
    }

    fn depth(self, q: u64) -> f32 {
        (q as f64 * self.quantum()) as f32
    }
}

/// The parts of a version 4 payload, each compressed with `codec` (in parallel):
/// `(compressed bytes, decompressed length)`, the head first.
///
/// # Errors
/// [`CodecError::Compress`] if the compressor fails; [`CodecError::Invalid`] if `bits` is
/// outside 4..=16 or a list is too deep for its grid (more than 2²³ quanta of lengthened
/// supersegments).
pub(super) fn encode_parts(
    vdi: &Vdi,
    bits: u8,
    codec: Codec,
) -> Result<Vec<(Vec<u8>, u64)>, CodecError> {
    Precision::from_bits(u32::from(bits)).map_err(|e| CodecError::Invalid(e.to_string()))?;
    let segs = vdi.supersegments();
    let max_z = segs.iter().fold(0.0f32, |m, s| m.max(s.z_end));
    let grid = DepthGrid::new(vdi.meta().sample_distance, max_z);
    let bands = bands(vdi.offsets());
    let mut head = Vec::with_capacity(256 + 12 * bands.len());
    write_meta(&mut head, vdi.meta());
    head.push(bits);
    head.push(grid.exponent as i8 as u8);
    head.extend_from_slice(&(segs.len() as u64).to_le_bytes());
    head.extend_from_slice(&(bands.len() as u32).to_le_bytes());
    let offsets = vdi.offsets();
    for b in &bands {
        head.extend_from_slice(&((b.end - b.start) as u32).to_le_bytes());
        head.extend_from_slice(&u64::from(offsets[b.end] - offsets[b.start]).to_le_bytes());
    }
    let coder = Coder::new(bits, grid);
    let mut parts = vec![(compress(codec, &head)?, head.len() as u64)];
    parts.par_extend(
        bands
            .into_par_iter()
            .map(|b| {
                let raw = coder.encode_band(vdi, b)?;
                Ok((compress(codec, &raw)?, raw.len() as u64))
            })
            .collect::<Result<Vec<_>, CodecError>>()?,
    );
    Ok(parts)
}

/// Consecutive pixel ranges of about [`BAND_SEGMENTS`] supersegments each (at least one
/// band, so an empty VDI's counts are stored too).
fn bands(offsets: &[u32]) -> Vec<std::ops::Range<usize>> {
    let pixels = offsets.len() - 1;
    let mut out = Vec::new();
    let mut start = 0;
    for p in 1..=pixels {
        if (offsets[p] - offsets[start]) as usize >= BAND_SEGMENTS || p == pixels {
            out.push(start..p);
            start = p;
        }
    }
    if out.is_empty() {
        out.push(0..pixels);
    }
    out
}

/// The quantisers of one file: colour bits and depth grid.
#[derive(Clone, Copy)]
struct Coder {
    /// `M = 2^b − 1`.
    max: f64,
    /// Byte planes per colour value.
    color_bytes: usize,
    grid: DepthGrid,
}

impl Coder {
    fn new(bits: u8, grid: DepthGrid) -> Self {
        Self {
            max: f64::from((1u32 << bits) - 1),
            color_bytes: if bits <= 8 { 1 } else { 2 },
            grid,
        }
    }

    fn level(&self, v: f32) -> u16 {
        (f64::from(v) * self.max).round().clamp(0.0, self.max) as u16
    }

    /// Opacity over the extent of `extent` world units (a level).
    fn opacity_level(&self, alpha: f32, extent: f64) -> u16 {
        let a = -(extent * (-f64::from(alpha)).ln_1p()).exp_m1();
        self.level(if a.is_nan() { 1.0 } else { a as f32 })
    }

    /// The `â` of opacity `a` (in [0, 1]) over `extent` (> 0) world units: the nearest `f32`,
    /// moved by a few units in the last place where that is what makes it encode to the same
    /// level again, so that a decoded VDI re-encodes to itself (an `â` within a few ulps of 1
    /// over a short extent can hold fewer levels than `b` bits have: it then stays the
    /// nearest).
    fn alpha(&self, a: f64, extent: f64) -> f32 {
        let target = (a * self.max).round() as u16;
        if f64::from(target) >= self.max {
            return 1.0;
        }
        let nearest = (-((-a).ln_1p() / extent).exp_m1()).clamp(0.0, 1.0) as f32;
        // Rounding `â` to f32 moves `A` by at most 2⁻²⁴ where the extent is ≥ 1 and by
        // 2⁻²⁴ / (1 − â) below it (dA/dâ = L (1 − â)^(L − 1)): far from `1` it cannot reach
        // the next level's half-way mark, so only `â` near 1 is checked.
        if extent >= 1.0 || 1.0 - f64::from(nearest) > 4.0 * self.max / 16_777_216.0 {
            return nearest;
        }
        let mut alpha = nearest;
        for _ in 0..8 {
            let level = self.opacity_level(alpha, extent);
            if level == target {
                return alpha;
            }
            let bits = alpha.to_bits();
            alpha = match level > target {
                true if bits > 0 => f32::from_bits(bits - 1),
                false if alpha < 1.0 => f32::from_bits(bits + 1),
                _ => break,
            };
        }
        nearest
    }

    /// One band's raw bytes (the layout in the module doc).
    fn encode_band(&self, vdi: &Vdi, band: std::ops::Range<usize>) -> Result<Vec<u8>, CodecError> {
        let offsets = vdi.offsets();
        let segs = &vdi.supersegments()[offsets[band.start] as usize..offsets[band.end] as usize];
        let base = offsets[band.start] as usize;
        let n = segs.len();
        let mut counts = Vec::with_capacity(band.len() + n / 64);
        let mut first = Vec::with_capacity(band.len());
        let mut gap = Vec::with_capacity(n);
        let mut length = Vec::with_capacity(n);
        let mut color: [Vec<u16>; 4] = std::array::from_fn(|_| Vec::with_capacity(n));
        let mut prev_first = 0u64;
        for p in band {
            let list = &segs[offsets[p] as usize - base..offsets[p + 1] as usize - base];
            leb128(&mut counts, list.len() as u32);
            let mut prev_end = None;
            for s in list {
                let start = self.grid.quanta(s.z_start).max(prev_end.unwrap_or(0));
                let end = self.grid.quanta(s.z_end).max(start + 1);
                if end > MAX_QUANTA {
                    return Err(CodecError::Invalid(format!(
                        "a list reaches {end} depth quanta of {} (at most {MAX_QUANTA})",
                        self.grid.quantum()
                    )));
                }
                match prev_end {
                    None => {
                        first.push(zigzag(start as i64 - prev_first as i64));
                        prev_first = start;
                    }
                    Some(e) => gap.push((start - e) as u32),
                }
                length.push((end - start - 1) as u32);
                // Opacity over the depth extent (the float depths: the decoder inverts it on
                // the stored ones).
                let extent = f64::from(s.z_end) - f64::from(s.z_start);
                let levels = [
                    self.level(s.color[0]),
                    self.level(s.color[1]),
                    self.level(s.color[2]),
                    self.opacity_level(s.alpha, extent),
                ];
                for (plane, level) in color.iter_mut().zip(levels) {
                    plane.push(level);
                }
                prev_end = Some(end);
            }
        }
        let widths = [&first, &gap, &length].map(|v| width(v));
        let mut out = Vec::with_capacity(counts.len() + 3 + n * (3 + 4 * self.color_bytes));
        out.extend_from_slice(&counts);
        out.extend(widths.iter().map(|&w| w as u8));
        for (values, w) in [&first, &gap, &length].into_iter().zip(widths) {
            for byte in 0..w {
                out.extend(values.iter().map(|v| (v >> (8 * byte)) as u8));
            }
        }
        for plane in &color {
            for byte in 0..self.color_bytes {
                out.extend(plane.iter().map(|v| (v >> (8 * byte)) as u8));
            }
        }
        Ok(out)
    }

    /// One band's raw bytes into its `counts` (one per pixel) and `segs` (its supersegments),
    /// every value checked.
    fn decode_band(
        &self,
        raw: &[u8],
        counts: &mut [u32],
        segs: &mut [Supersegment],
    ) -> Result<(), CodecError> {
        let mut rd = Reader::new(raw);
        let n = segs.len();
        let mut total = 0usize;
        let mut nonempty = 0usize;
        for c in counts.iter_mut() {
            *c = read_leb128(&mut rd)?;
            total = total.saturating_add(*c as usize);
            nonempty += usize::from(*c > 0);
        }
        if total != n {
            return Err(CodecError::Invalid(format!(
                "a band's counts add up to {total}, its head entry says {n}"
            )));
        }
        let widths = rd.array::<3>("plane widths")?.map(usize::from);
        if let Some(w) = widths.iter().find(|&&w| w > 4) {
            return Err(CodecError::Invalid(format!("a plane width of {w} bytes")));
        }
        let lens = [nonempty, n - nonempty, n];
        let needed = (0..3).map(|k| widths[k] * lens[k]).sum::<usize>() + 4 * self.color_bytes * n;
        if needed != rd.remaining() {
            return Err(CodecError::Invalid(format!(
                "a band of {n} supersegments needs {needed} plane bytes, it holds {}",
                rd.remaining()
            )));
        }
        let first = planes(&mut rd, nonempty, widths[0])?;
        let gap = planes(&mut rd, n - nonempty, widths[1])?;
        let length = planes(&mut rd, n, widths[2])?;
        let color: Vec<Vec<&[u8]>> = (0..4)
            .map(|_| planes(&mut rd, n, self.color_bytes))
            .collect::<Result<_, _>>()?;
        let first = gather(&first, nonempty);
        let gap = gather(&gap, n - nonempty);
        let length = gather(&length, n);
        let color: Vec<Vec<u32>> = color.iter().map(|planes| gather(planes, n)).collect();
        let too_deep =
            |q: u64| CodecError::Invalid(format!("a depth of {q} quanta (at most {MAX_QUANTA})"));
        let (mut i, mut fi, mut gi) = (0usize, 0usize, 0usize);
        let mut prev_first = 0u64;
        for &c in counts.iter() {
            let mut prev_end = None;
            for _ in 0..c {
                let start = match prev_end {
                    None => {
                        let d = unzigzag(u64::from(first[fi]));
                        fi += 1;
                        let s = prev_first as i64 + d;
                        if !(0..=MAX_QUANTA as i64).contains(&s) {
                            return Err(too_deep(s.max(0) as u64));
                        }
                        prev_first = s as u64;
                        s as u64
                    }
                    Some(e) => {
                        gi += 1;
                        e + u64::from(gap[gi - 1])
                    }
                };
                let end = start + 1 + u64::from(length[i]);
                if end > MAX_QUANTA {
                    return Err(too_deep(end));
                }
                let mut levels = [0f64; 4];
                for (k, l) in levels.iter_mut().enumerate() {
                    let v = f64::from(color[k][i]);
                    if v > self.max {
                        return Err(CodecError::Invalid(format!(
                            "a colour level {v} above {} ({} bits)",
                            self.max,
                            self.max.log2().round()
                        )));
                    }
                    *l = v / self.max;
                }
                let extent = (end - start) as f64 * self.grid.quantum();
                segs[i] = Supersegment {
                    z_start: self.grid.depth(start),
                    z_end: self.grid.depth(end),
                    color: [levels[0] as f32, levels[1] as f32, levels[2] as f32],
                    alpha: self.alpha(levels[3], extent),
                };
                prev_end = Some(end);
                i += 1;
            }
        }
        Ok(())
    }
}

/// Decodes a version 4 payload from its parts (the head first), the bands decompressed and
/// decoded in parallel.
///
/// # Errors
/// [`CodecError`] for a part that does not decompress to its stated length, a head or band
/// whose counts disagree, a decoded VDI whose memory would exceed `limits`, or any value
/// out of range.
pub(super) fn decode_parts(
    codec: Codec,
    parts: &[(&[u8], u64)],
    limits: &super::DecodeLimits,
) -> Result<Vdi, CodecError> {
    let (head_input, head_len) = parts[0];
    let head = decompress(codec, head_input, head_len, ("the head", "the part table"))?;
    let mut rd = Reader::new(&head);
    let mut meta = read_meta(&mut rd)?;
    let bits = rd.u8("precision")?;
    let precision = Precision::from_bits(u32::from(bits))
        .ok()
        .filter(|p| *p != Precision::Float32)
        .ok_or_else(|| CodecError::Invalid(format!("precision of {bits} bits (4 to 16)")))?;
    meta.params.precision = precision;
    let exponent = i32::from(rd.u8("depth exponent")? as i8);
    if !EXPONENTS.contains(&exponent) {
        return Err(CodecError::Invalid(format!(
            "depth quantum 2^{exponent} outside 2^-126..=2^104"
        )));
    }
    let n = rd.u64("supersegment count")?;
    let band_count = rd.u32("band count")? as usize;
    if band_count + 1 != parts.len() || rd.remaining() != 12 * band_count {
        return Err(CodecError::Invalid(format!(
            "the head names {band_count} bands in {} bytes; the file has {} band parts",
            rd.remaining(),
            parts.len() - 1
        )));
    }
    let pixels = (meta.params.resolution as usize).pow(2);
    let mut table = Vec::with_capacity(band_count);
    let (mut pixel_sum, mut seg_sum) = (0u64, 0u64);
    for k in 0..band_count {
        let (band_pixels, band_segs) = (rd.u32("band pixels")?, rd.u64("band supersegments")?);
        // Each supersegment takes bytes of its band's decompressed part: a count the part
        // cannot hold is refused before anything is allocated for it.
        if band_segs.saturating_mul(MIN_SEGMENT_BYTES) > parts[k + 1].1 {
            return Err(CodecError::Invalid(format!(
                "band {k} claims {band_segs} supersegments in {} bytes",
                parts[k + 1].1
            )));
        }
        pixel_sum += u64::from(band_pixels);
        seg_sum = seg_sum.saturating_add(band_segs);
        table.push((band_pixels as usize, band_segs as usize));
    }
    if pixel_sum != pixels as u64 || seg_sum != n {
        return Err(CodecError::Invalid(format!(
            "the bands hold {pixel_sum} pixels and {seg_sum} supersegments; r² is {pixels} and \
             the head says {n}"
        )));
    }
    let memory = (pixels as u64 + 1) * 4 + n * std::mem::size_of::<Supersegment>() as u64;
    if memory > limits.max_payload_bytes {
        return Err(CodecError::TooLarge {
            claimed: memory,
            limit: limits.max_payload_bytes,
        });
    }
    let coder = Coder::new(bits, DepthGrid { exponent });
    let mut counts = vec![0u32; pixels];
    let mut segs = vec![Supersegment::default(); n as usize];
    let mut jobs = Vec::with_capacity(band_count);
    let (mut count_rest, mut seg_rest) = (&mut counts[..], &mut segs[..]);
    for (k, &(band_pixels, band_segs)) in table.iter().enumerate() {
        let (c, more_c) = std::mem::take(&mut count_rest).split_at_mut(band_pixels);
        let (s, more_s) = std::mem::take(&mut seg_rest).split_at_mut(band_segs);
        jobs.push((k, c, s));
        (count_rest, seg_rest) = (more_c, more_s);
    }
    jobs.into_par_iter().try_for_each(|(k, c, s)| {
        let (input, len) = parts[k + 1];
        let what = format!("band {k} of {band_count}");
        let raw = decompress(codec, input, len, (&what, "the part table"))?;
        coder.decode_band(&raw, c, s)
    })?;
    let mut offsets = Vec::with_capacity(pixels + 1);
    offsets.push(0u32);
    let mut total = 0u32;
    for c in counts {
        total += c;
        offsets.push(total);
    }
    check_depth_order(&offsets, &segs)?;
    Vdi::from_parts(meta, offsets, segs)
        .ok_or_else(|| CodecError::Invalid("offsets do not match the lists".into()))
}

/// The values of a stream from its byte planes (low byte first; none: all 0).
fn gather(planes: &[&[u8]], len: usize) -> Vec<u32> {
    let mut out = vec![0u32; len];
    for (k, plane) in planes.iter().enumerate() {
        for (v, &b) in out.iter_mut().zip(plane.iter()) {
            *v |= u32::from(b) << (8 * k);
        }
    }
    out
}

/// `w` byte planes of `len` bytes each.
fn planes<'a>(rd: &mut Reader<'a>, len: usize, w: usize) -> Result<Vec<&'a [u8]>, CodecError> {
    (0..w).map(|_| rd.take(len, "a byte plane")).collect()
}

/// Bytes a value of the stream needs (0 when all are 0).
fn width(values: &[u32]) -> usize {
    let max = values.iter().fold(0u32, |m, &v| m | v);
    (32 - max.leading_zeros() as usize).div_ceil(8)
}

fn zigzag(v: i64) -> u32 {
    ((v << 1) ^ (v >> 63)) as u32
}

fn unzigzag(v: u64) -> i64 {
    (v >> 1) as i64 ^ -((v & 1) as i64)
}

fn leb128(out: &mut Vec<u8>, mut v: u32) {
    while v >= 0x80 {
        out.push(v as u8 | 0x80);
        v >>= 7;
    }
    out.push(v as u8);
}

fn read_leb128(rd: &mut Reader<'_>) -> Result<u32, CodecError> {
    let mut v = 0u64;
    for shift in (0..35).step_by(7) {
        let b = rd.u8("a pixel count")?;
        v |= u64::from(b & 0x7f) << shift;
        if b & 0x80 == 0 {
            return u32::try_from(v)
                .map_err(|_| CodecError::Invalid(format!("a pixel count of {v}")));
        }
    }
    Err(CodecError::Invalid(
        "a pixel count longer than 5 bytes".into(),
    ))
}
