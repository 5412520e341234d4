//! Voxel storage in the data's own type: a byte volume stays one byte per voxel
//! instead of four, so the field costs what it costs the simulation or the file, and the
//! marcher reads a quarter of the memory. Values are the stored numbers as `f32` (exact for
//! u8, u16 and i16); f64, which f32 cannot hold exactly, is stored as f32.

use std::borrow::Cow;

/// Bytes past the last voxel of integer storage, zero: the AVX2 gathers read four bytes at
/// a voxel's address, so the last voxel's read runs up to three bytes past it.
pub(crate) const PAD: usize = 4;

/// The samples of a volume, x fastest, in their own type.
#[derive(Clone, Debug, PartialEq)]
pub(crate) enum Storage {
    /// Bytes, with [`PAD`] zero bytes after the last voxel.
    U8(Vec<u8>),
    /// 16-bit unsigned, with [`PAD`] / 2 zero values after the last voxel.
    U16(Vec<u16>),
    /// 16-bit signed, with [`PAD`] / 2 zero values after the last voxel.
    I16(Vec<i16>),
    /// Single precision (NaN marks missing data).
    F32(Vec<f32>),
}

/// A borrowed view of a volume's samples in their own type, without padding.
#[derive(Clone, Copy, Debug)]
pub enum VoxelSlice<'a> {
    /// Bytes.
    U8(&'a [u8]),
    /// 16-bit unsigned.
    U16(&'a [u16]),
    /// 16-bit signed.
    I16(&'a [i16]),
    /// Single precision.
    F32(&'a [f32]),
}

impl Storage {
    /// Bytes `data` (length `n`), padded.
    pub(crate) fn from_u8(mut data: Vec<u8>) -> Self {
        data.reserve_exact(PAD);
        data.extend_from_slice(&[0; PAD]);
        Self::U8(data)
    }

    /// 16-bit values, padded.
    pub(crate) fn from_u16(mut data: Vec<u16>) -> Self {
        data.reserve_exact(PAD / 2);
        data.extend_from_slice(&[0; PAD / 2]);
        Self::U16(data)
    }

    /// 16-bit signed values, padded.
    pub(crate) fn from_i16(mut data: Vec<i16>) -> Self {
        data.reserve_exact(PAD / 2);
        data.extend_from_slice(&[0; PAD / 2]);
        Self::I16(data)
    }

    /// Number of voxels.
    pub(crate) fn len(&self) -> usize {
        match self {
            Self::U8(d) => d.len() - PAD,
            Self::U16(d) => d.len() - PAD / 2,
            Self::I16(d) => d.len() - PAD / 2,
            Self::F32(d) => d.len(),
        }
    }

    /// The voxels without padding.
    pub(crate) fn slice(&self) -> VoxelSlice<'_> {
        let n = self.len();
        match self {
            Self::U8(d) => VoxelSlice::U8(&d[..n]),
            Self::U16(d) => VoxelSlice::U16(&d[..n]),
            Self::I16(d) => VoxelSlice::I16(&d[..n]),
            Self::F32(d) => VoxelSlice::F32(d),
        }
    }
}

impl<'a> VoxelSlice<'a> {
    /// Number of voxels.
    pub fn len(&self) -> usize {
        match self {
            Self::U8(d) => d.len(),
            Self::U16(d) => d.len(),
            Self::I16(d) => d.len(),
            Self::F32(d) => d.len(),
        }
    }

    /// Whether there are no voxels (never, for a valid volume).
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Bytes per voxel.
    pub fn bytes_per_voxel(&self) -> usize {
        match self {
            Self::U8(_) => 1,
            Self::U16(_) | Self::I16(_) => 2,
            Self::F32(_) => 4,
        }
    }

    /// The stored type.
    pub fn scalar_type(&self) -> super::ScalarType {
        match self {
            Self::U8(_) => super::ScalarType::U8,
            Self::U16(_) => super::ScalarType::U16,
            Self::I16(_) => super::ScalarType::I16,
            Self::F32(_) => super::ScalarType::F32,
        }
    }

    /// The samples as little-endian bytes of [`VoxelSlice::scalar_type`] (what
    /// [`super::Volume::from_le_bytes`] reads back): borrowed on little-endian machines.
    pub fn to_le_bytes(&self) -> Cow<'a, [u8]> {
        match *self {
            Self::U8(d) => Cow::Borrowed(d),
            #[cfg(target_endian = "little")]
            Self::U16(d) => Cow::Borrowed(bytemuck::cast_slice(d)),
            #[cfg(target_endian = "little")]
            Self::I16(d) => Cow::Borrowed(bytemuck::cast_slice(d)),
            #[cfg(target_endian = "little")]
            Self::F32(d) => Cow::Borrowed(bytemuck::cast_slice(d)),
            #[cfg(target_endian = "big")]
            Self::U16(d) => Cow::Owned(d.iter().flat_map(|v| v.to_le_bytes()).collect()),
            #[cfg(target_endian = "big")]
            Self::I16(d) => Cow::Owned(d.iter().flat_map(|v| v.to_le_bytes()).collect()),
            #[cfg(target_endian = "big")]
            Self::F32(d) => Cow::Owned(d.iter().flat_map(|v| v.to_le_bytes()).collect()),
        }
    }

    /// The values as f32: borrowed for f32 storage, converted otherwise.
    pub fn to_f32(&self) -> Cow<'a, [f32]> {
        match *self {
            Self::U8(d) => Cow::Owned(d.iter().map(|&v| f32::from(v)).collect()),
            Self::U16(d) => Cow::Owned(d.iter().map(|&v| f32::from(v)).collect()),
            Self::I16(d) => Cow::Owned(d.iter().map(|&v| f32::from(v)).collect()),
            Self::F32(d) => Cow::Borrowed(d),
        }
    }
}

/// A stored voxel type the marcher samples directly.
pub trait Voxel: Copy + Send + Sync + 'static {
    /// The value as f32 (exact for u8, u16, i16).
    fn value(self) -> f32;
}

impl Voxel for u8 {
    #[inline(always)]
    fn value(self) -> f32 {
        f32::from(self)
    }
}

impl Voxel for u16 {
    #[inline(always)]
    fn value(self) -> f32 {
        f32::from(self)
    }
}

impl Voxel for i16 {
    #[inline(always)]
    fn value(self) -> f32 {
        f32::from(self)
    }
}

impl Voxel for f32 {
    #[inline(always)]
    fn value(self) -> f32 {
        self
    }
}
