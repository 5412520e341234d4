//! What every reader needs: a bounded cursor over a header, and typed samples turned into a
//! [`Volume`] in the type the core keeps (u8, u16, i16 as they are; the rest as f32).

use crate::ReadError;
use glam::Vec3;
use insitu_core::volume::{FieldAssembler, ScalarType};
use insitu_core::Volume;
use std::io::Read;
use std::path::{Path, PathBuf};

/// A sample type as files store it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Sample {
    /// Signed byte.
    I8,
    /// Unsigned byte.
    U8,
    /// Signed 16-bit.
    I16,
    /// Unsigned 16-bit.
    U16,
    /// Signed 32-bit.
    I32,
    /// Unsigned 32-bit.
    U32,
    /// Signed 64-bit.
    I64,
    /// Unsigned 64-bit.
    U64,
    /// IEEE single.
    F32,
    /// IEEE double.
    F64,
}

impl Sample {
    /// Bytes per sample.
    pub fn size(self) -> usize {
        match self {
            Self::I8 | Self::U8 => 1,
            Self::I16 | Self::U16 => 2,
            Self::I32 | Self::U32 | Self::F32 => 4,
            Self::I64 | Self::U64 | Self::F64 => 8,
        }
    }
}

/// Byte order of the samples.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Endian {
    /// Least significant byte first.
    Little,
    /// Most significant byte first.
    Big,
}

/// The `i`-th sample of `bytes` as f64.
pub(crate) fn value(bytes: &[u8], i: usize, t: Sample, e: Endian) -> f64 {
    let n = t.size();
    let mut b = [0u8; 8];
    b[..n].copy_from_slice(&bytes[i * n..(i + 1) * n]);
    if e == Endian::Big {
        b[..n].reverse();
    }
    match t {
        Sample::I8 => f64::from(b[0] as i8),
        Sample::U8 => f64::from(b[0]),
        Sample::I16 => f64::from(i16::from_le_bytes([b[0], b[1]])),
        Sample::U16 => f64::from(u16::from_le_bytes([b[0], b[1]])),
        Sample::I32 => f64::from(i32::from_le_bytes([b[0], b[1], b[2], b[3]])),
        Sample::U32 => f64::from(u32::from_le_bytes([b[0], b[1], b[2], b[3]])),
        Sample::I64 => i64::from_le_bytes(b) as f64,
        Sample::U64 => u64::from_le_bytes(b) as f64,
        Sample::F32 => f64::from(f32::from_le_bytes([b[0], b[1], b[2], b[3]])),
        Sample::F64 => f64::from_le_bytes(b),
    }
}

/// Bytes read from a file per piece while streaming samples into a volume.
pub const PIECE: usize = 4 << 20;

/// Samples streamed into a volume piece by piece: big-endian ones swapped, the types the core
/// does not keep (i8, 32- and 64-bit integers) converted to f32, f64 narrowed to f32. Reading a
/// field so costs the volume and one piece, not the file's bytes besides.
pub struct Samples {
    path: PathBuf,
    asm: FieldAssembler,
    t: Sample,
    e: Endian,
    /// The bytes of a sample split between two pieces.
    carry: Vec<u8>,
    scratch: Vec<u8>,
}

impl Samples {
    /// Room for `n` samples of `t` stored `e`, read from `path`: the volume's memory is
    /// checked against the read limit ([`crate::limit`]) and `reserve` samples of it (those
    /// the file's bytes justify: all `n` for data whose length was checked against the file,
    /// fewer for a compressed body, which grows as it decodes) are allocated now.
    ///
    /// # Errors
    /// [`ReadError::Invalid`] naming `path`: the volume over the read limit, or the memory
    /// not to be had (naming the size).
    pub fn new(
        path: &Path,
        t: Sample,
        e: Endian,
        n: usize,
        reserve: usize,
    ) -> Result<Self, ReadError> {
        let kept = match t {
            Sample::U8 => ScalarType::U8,
            Sample::U16 => ScalarType::U16,
            Sample::I16 => ScalarType::I16,
            Sample::F64 => ScalarType::F64,
            _ => ScalarType::F32,
        };
        crate::limit::check(path, n, FieldAssembler::kept_bytes_per_sample(kept))?;
        let mut s = Self {
            path: path.to_owned(),
            asm: FieldAssembler::new(kept, 0),
            t,
            e,
            carry: Vec::new(),
            scratch: Vec::new(),
        };
        s.reserve(reserve.min(n))?;
        Ok(s)
    }

    /// Room for `n` more samples, or an error naming the size the allocator refused.
    fn reserve(&mut self, n: usize) -> Result<(), ReadError> {
        self.asm.try_reserve(n).map_err(|_| {
            let held = self.asm.received_bytes();
            ReadError::invalid(
                &self.path,
                format!(
                    "out of memory: {n} more samples after {} could not be allocated",
                    crate::limit::human(held)
                ),
            )
        })
    }

    /// Whether the pieces pass to the core unchanged (little-endian, a type it takes).
    fn as_is(&self) -> bool {
        (self.e == Endian::Little || self.t.size() == 1)
            && matches!(
                self.t,
                Sample::U8 | Sample::U16 | Sample::I16 | Sample::F32 | Sample::F64
            )
    }

    /// Appends the next bytes of the field (a piece may split a sample anywhere).
    ///
    /// # Errors
    /// [`ReadError::Invalid`] naming the file when the memory for them cannot be had.
    pub fn push(&mut self, bytes: &[u8]) -> Result<(), ReadError> {
        self.reserve(bytes.len() / self.t.size() + 1)?;
        if self.as_is() {
            self.asm.push(bytes);
            return Ok(());
        }
        let size = self.t.size();
        let mut data = bytes;
        if !self.carry.is_empty() {
            let need = size - self.carry.len();
            let take = need.min(data.len());
            self.carry.extend_from_slice(&data[..take]);
            data = &data[take..];
            if self.carry.len() < size {
                return Ok(());
            }
            let sample = std::mem::take(&mut self.carry);
            self.convert(&sample);
        }
        let whole = data.len() / size * size;
        self.convert(&data[..whole]);
        self.carry.extend_from_slice(&data[whole..]);
        Ok(())
    }

    /// Whole samples, swapped or converted, to the core in its little-endian layout.
    fn convert(&mut self, whole: &[u8]) {
        let size = self.t.size();
        self.scratch.clear();
        let keeps_type = matches!(
            self.t,
            Sample::U16 | Sample::I16 | Sample::F32 | Sample::F64
        );
        if keeps_type {
            // Big-endian samples of a kept type: their bytes reversed.
            for s in whole.chunks_exact(size) {
                self.scratch.extend(s.iter().rev());
            }
        } else {
            for k in 0..whole.len() / size {
                let v = value(whole, k, self.t, self.e) as f32;
                self.scratch.extend_from_slice(&v.to_le_bytes());
            }
        }
        self.asm.push(&self.scratch);
    }

    /// Reads exactly `len` bytes of samples from `from`, a piece at a time; with `exact`,
    /// `from` must end there.
    ///
    /// # Errors
    /// [`ReadError::Invalid`] naming `path` when the data ends early.
    pub fn read_from(
        &mut self,
        path: &Path,
        mut from: impl Read,
        len: usize,
        exact: bool,
    ) -> Result<(), ReadError> {
        let mut buf = vec![0u8; PIECE.min(len)];
        let mut left = len;
        while left > 0 {
            let n = left.min(buf.len());
            from.read_exact(&mut buf[..n]).map_err(|e| {
                ReadError::invalid(path, format!("the data ends {} bytes early: {e}", left))
            })?;
            self.push(&buf[..n])?;
            left -= n;
        }
        if exact && from.read(&mut [0u8; 1]).is_ok_and(|k| k > 0) {
            return Err(ReadError::invalid(
                path,
                format!("the data holds more than the {len} bytes the header says"),
            ));
        }
        Ok(())
    }

    /// The volume of `dims` at `spacing`.
    ///
    /// # Errors
    /// [`ReadError::Invalid`] naming `path` when the samples pushed are not `dims` of them.
    pub fn finish(self, path: &Path, dims: [usize; 3], spacing: Vec3) -> Result<Volume, ReadError> {
        if !self.carry.is_empty() {
            return Err(ReadError::invalid(path, "the data ends within a sample"));
        }
        self.asm
            .finish(dims, spacing)
            .map_err(|e| ReadError::invalid(path, e.to_string()))
    }
}

/// A number written as text, as a sample of type `t` is kept: f32 samples parsed straight to
/// the nearest f32 (as VTK reads them; through f64 could round twice), others through f64.
pub fn parse_text(s: &str, t: Sample) -> Option<f32> {
    if t == Sample::F32 {
        s.parse::<f32>().ok()
    } else {
        s.parse::<f64>().ok().map(|v| v as f32)
    }
}

/// `bytes` (samples of `t`) as f64 values, for readers that scale or mask them.
pub fn values(bytes: &[u8], t: Sample, e: Endian) -> Vec<f64> {
    (0..bytes.len() / t.size())
        .map(|i| value(bytes, i, t, e))
        .collect()
}

/// A cursor over a header held in memory; every read names what it reads when the bytes run
/// out.
pub struct Cursor<'a> {
    path: &'a Path,
    bytes: &'a [u8],
    pos: usize,
}

impl<'a> Cursor<'a> {
    /// At the start of `bytes`, the file `path`.
    pub fn new(path: &'a Path, bytes: &'a [u8]) -> Self {
        Self {
            path,
            bytes,
            pos: 0,
        }
    }

    /// Bytes read so far.
    pub fn pos(&self) -> usize {
        self.pos
    }

    /// The next `n` bytes.
    ///
    /// # Errors
    /// [`ReadError::Invalid`]: the file ends before `what`.
    pub fn take(&mut self, n: usize, what: &str) -> Result<&'a [u8], ReadError> {
        let end = self.pos.checked_add(n).filter(|&e| e <= self.bytes.len());
        let Some(end) = end else {
            return Err(ReadError::invalid(
                self.path,
                format!(
                    "truncated: {what} needs {n} bytes at offset {}, {} left",
                    self.pos,
                    self.bytes.len() - self.pos
                ),
            ));
        };
        let out = &self.bytes[self.pos..end];
        self.pos = end;
        Ok(out)
    }

    /// A big-endian u32.
    ///
    /// # Errors
    /// As [`Cursor::take`].
    pub fn be_u32(&mut self, what: &str) -> Result<u32, ReadError> {
        let b = self.take(4, what)?;
        Ok(u32::from_be_bytes([b[0], b[1], b[2], b[3]]))
    }

    /// A big-endian u64.
    ///
    /// # Errors
    /// As [`Cursor::take`].
    pub fn be_u64(&mut self, what: &str) -> Result<u64, ReadError> {
        let b = self.take(8, what)?;
        let mut a = [0u8; 8];
        a.copy_from_slice(b);
        Ok(u64::from_be_bytes(a))
    }
}
