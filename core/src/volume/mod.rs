//! Scalar volumes on a regular grid (docs/conventions.md, "Volume").
//!
//! A [`Volume`] holds `nx × ny × nz` samples, x fastest, in their own type (u8, u16 or f32:
//! [`VoxelSlice`]), with a voxel spacing.
//! Voxel centres sit at integer multiples of the spacing from an origin (0 unless the volume is
//! one rank's brick of a larger grid), so the world-space box is `origin + [0, (n − 1)·s]` per
//! axis. NaN marks missing data and is transparent everywhere.

mod assemble;
pub mod bricks;
mod gray_scott;
mod raw;
pub mod tiling;
mod voxels;

pub use assemble::FieldAssembler;
pub use gray_scott::{GrayScott, GrayScottParams};
pub use raw::{RawFormat, ScalarType};
pub(crate) use voxels::Storage;
pub use voxels::{Voxel, VoxelSlice};

use glam::Vec3;
use std::path::PathBuf;

/// Errors from building or loading a volume; each names the input and the problem.
#[derive(Debug, thiserror::Error)]
pub enum VolumeError {
    /// The file could not be read.
    #[error("cannot read volume file {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// Dimensions or type are neither in the file name nor given.
    #[error("cannot tell the layout of {path}: {reason} (name it <name>_<X>x<Y>x<Z>[x<T>]_<type>.raw or pass dims and type)")]
    UnknownLayout {
        /// The file.
        path: PathBuf,
        /// What is missing.
        reason: String,
    },
    /// A type name that is not one of u8, u16, i16, f32, f64.
    #[error("unknown voxel type {0:?} (expected one of uint8, uint16, int16, float32, float64)")]
    UnknownType(String),
    /// File size does not match `dims × T × voxel size`.
    #[error(
        "{path} has {actual} bytes but {dims:?} x {steps} steps of {type_name} need {expected}"
    )]
    SizeMismatch {
        /// The file.
        path: PathBuf,
        /// Spatial dimensions.
        dims: [usize; 3],
        /// Time steps in the file.
        steps: usize,
        /// Voxel type name.
        type_name: &'static str,
        /// Expected byte count.
        expected: u64,
        /// Actual byte count.
        actual: u64,
    },
    /// A time step beyond the file's count.
    #[error("time step {t} requested but {path} holds {steps} step(s)")]
    TimeStepOutOfRange {
        /// The file.
        path: PathBuf,
        /// Requested step.
        t: usize,
        /// Steps in the file.
        steps: usize,
    },
    /// Dimensions, spacing or a source description are not usable.
    #[error("invalid volume: {0}")]
    Invalid(String),
}

/// A scalar field on a regular grid, x fastest, with voxel spacing in world units.
#[derive(Clone, Debug, PartialEq)]
pub struct Volume {
    dims: [usize; 3],
    spacing: Vec3,
    origin: Vec3,
    data: Storage,
}

impl Volume {
    /// Wraps `data` (length `nx·ny·nz`, x fastest) with the given spacing.
    ///
    /// # Errors
    /// [`VolumeError::Invalid`] when a dimension is 0, the length does not match, or a
    /// spacing component is not finite and positive.
    pub fn new(dims: [usize; 3], spacing: Vec3, data: Vec<f32>) -> Result<Self, VolumeError> {
        Self::with_storage(dims, spacing, Storage::F32(data))
    }

    /// [`Volume::new`] for bytes, kept one byte per voxel.
    ///
    /// # Errors
    /// As [`Volume::new`].
    pub fn from_u8(dims: [usize; 3], spacing: Vec3, data: Vec<u8>) -> Result<Self, VolumeError> {
        Self::with_storage(dims, spacing, Storage::from_u8(data))
    }

    /// [`Volume::new`] for 16-bit unsigned values, kept two bytes per voxel.
    ///
    /// # Errors
    /// As [`Volume::new`].
    pub fn from_u16(dims: [usize; 3], spacing: Vec3, data: Vec<u16>) -> Result<Self, VolumeError> {
        Self::with_storage(dims, spacing, Storage::from_u16(data))
    }

    /// [`Volume::new`] for 16-bit signed values, kept two bytes per voxel.
    ///
    /// # Errors
    /// As [`Volume::new`].
    pub fn from_i16(dims: [usize; 3], spacing: Vec3, data: Vec<i16>) -> Result<Self, VolumeError> {
        Self::with_storage(dims, spacing, Storage::from_i16(data))
    }

    fn with_storage(dims: [usize; 3], spacing: Vec3, data: Storage) -> Result<Self, VolumeError> {
        if dims.contains(&0) {
            return Err(VolumeError::Invalid(format!(
                "dimensions {dims:?} contain a zero"
            )));
        }
        let n = dims
            .iter()
            .try_fold(1usize, |acc, &d| acc.checked_mul(d))
            .ok_or_else(|| VolumeError::Invalid(format!("dimensions {dims:?} overflow")))?;
        if n != data.len() {
            return Err(VolumeError::Invalid(format!(
                "dimensions {dims:?} need {n} values, got {}",
                data.len()
            )));
        }
        if !(spacing.is_finite() && spacing.min_element() > 0.0) {
            return Err(VolumeError::Invalid(format!(
                "spacing {spacing} must be finite and positive"
            )));
        }
        Ok(Self {
            dims,
            spacing,
            origin: Vec3::ZERO,
            data,
        })
    }

    /// Builds a volume by evaluating `f(x, y, z)` at every voxel index (unit spacing).
    ///
    /// # Errors
    /// As [`Volume::new`].
    pub fn from_fn(
        dims: [usize; 3],
        mut f: impl FnMut(usize, usize, usize) -> f32,
    ) -> Result<Self, VolumeError> {
        let mut data = Vec::with_capacity(dims.iter().product());
        for z in 0..dims[2] {
            for y in 0..dims[1] {
                for x in 0..dims[0] {
                    data.push(f(x, y, z));
                }
            }
        }
        Self::new(dims, Vec3::ONE, data)
    }

    /// Places the first voxel at world position `origin` (a brick of a larger grid starting at
    /// voxel offset `o` has origin `o · spacing`).
    ///
    /// # Errors
    /// [`VolumeError::Invalid`] when `origin` is not finite.
    pub fn with_origin(mut self, origin: Vec3) -> Result<Self, VolumeError> {
        if !origin.is_finite() {
            return Err(VolumeError::Invalid(format!(
                "origin {origin} must be finite"
            )));
        }
        self.origin = origin;
        Ok(self)
    }

    /// The same samples (in their own storage type) `spacing` apart.
    ///
    /// # Errors
    /// [`VolumeError::Invalid`] when a component is not finite and positive.
    pub fn with_spacing(mut self, spacing: Vec3) -> Result<Self, VolumeError> {
        if !(spacing.is_finite() && spacing.min_element() > 0.0) {
            return Err(VolumeError::Invalid(format!(
                "spacing {spacing} must be finite and positive"
            )));
        }
        self.spacing = spacing;
        Ok(self)
    }

    /// World position of the first voxel.
    pub fn origin(&self) -> Vec3 {
        self.origin
    }

    /// Grid dimensions `[nx, ny, nz]`.
    pub fn dims(&self) -> [usize; 3] {
        self.dims
    }

    /// Voxel spacing in world units per axis.
    pub fn spacing(&self) -> Vec3 {
        self.spacing
    }

    /// The samples as f32, x fastest, length `nx·ny·nz`: borrowed for f32 storage, a
    /// converted copy otherwise (the marcher reads [`Volume::voxels`] instead).
    pub fn data(&self) -> std::borrow::Cow<'_, [f32]> {
        self.data.slice().to_f32()
    }

    /// The samples in their own type, x fastest, length `nx·ny·nz`.
    pub fn voxels(&self) -> VoxelSlice<'_> {
        self.data.slice()
    }

    /// The storage, given up (for reuse of its memory).
    pub(crate) fn into_storage(self) -> Storage {
        self.data
    }

    /// The storage, padding included (the AVX2 gathers read past the last voxel).
    pub(crate) fn storage(&self) -> &Storage {
        &self.data
    }

    /// Bytes the samples take in memory (their own type; padding aside).
    pub fn storage_bytes(&self) -> usize {
        let v = self.voxels();
        v.len() * v.bytes_per_voxel()
    }

    /// The world-space box `origin + [0, (n − 1)·s]`.
    pub fn world_box(&self) -> Aabb {
        let [nx, ny, nz] = self.dims;
        Aabb {
            min: self.origin,
            max: self.origin
                + Vec3::new(
                    (nx - 1) as f32 * self.spacing.x,
                    (ny - 1) as f32 * self.spacing.y,
                    (nz - 1) as f32 * self.spacing.z,
                ),
        }
    }

    /// Minimum and maximum over the non-NaN samples, or `None` if all are NaN.
    pub fn finite_range(&self) -> Option<(f32, f32)> {
        fn range<T: Voxel>(d: &[T]) -> (f32, f32) {
            d.iter()
                .map(|v| v.value())
                .filter(|v| !v.is_nan())
                .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), v| {
                    (lo.min(v), hi.max(v))
                })
        }
        let (lo, hi) = match self.voxels() {
            VoxelSlice::U8(d) => range(d),
            VoxelSlice::U16(d) => range(d),
            VoxelSlice::I16(d) => range(d),
            VoxelSlice::F32(d) => range(d),
        };
        (lo <= hi).then_some((lo, hi))
    }

    /// A 64-bit FNV-1a hash of dims, spacing and the sample bits: the volume's identity.
    pub fn content_hash(&self) -> u64 {
        let mut h = Fnv1a::new();
        for d in self.dims {
            h.write(&(d as u64).to_le_bytes());
        }
        for s in self
            .spacing
            .to_array()
            .into_iter()
            .chain(self.origin.to_array())
        {
            h.write(&s.to_le_bytes());
        }
        // The values' f32 bits whatever the storage: a volume's identity does not depend on
        // how it is held.
        fn values<T: Voxel>(h: &mut Fnv1a, d: &[T]) {
            for v in d {
                h.write(&v.value().to_bits().to_le_bytes());
            }
        }
        match self.voxels() {
            VoxelSlice::U8(d) => values(&mut h, d),
            VoxelSlice::U16(d) => values(&mut h, d),
            VoxelSlice::I16(d) => values(&mut h, d),
            VoxelSlice::F32(d) => values(&mut h, d),
        }
        h.finish()
    }
}

/// An axis-aligned box in world space.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Aabb {
    /// Lower corner.
    pub min: Vec3,
    /// Upper corner.
    pub max: Vec3,
}

impl Aabb {
    /// Centre of the box.
    pub fn center(&self) -> Vec3 {
        0.5 * (self.min + self.max)
    }

    /// Half the length of the diagonal.
    pub fn half_diagonal(&self) -> f32 {
        0.5 * (self.max - self.min).length()
    }

    /// The eight corners, corner `k` taking `max` on x, y, z where bit 0, 1, 2 of `k` is set.
    pub fn corners(&self) -> [Vec3; 8] {
        std::array::from_fn(|k| {
            Vec3::new(
                if k & 1 == 0 { self.min.x } else { self.max.x },
                if k & 2 == 0 { self.min.y } else { self.max.y },
                if k & 4 == 0 { self.min.z } else { self.max.z },
            )
        })
    }

    /// Parameter interval `[t_near, t_far]` where `origin + t·dir` is inside the box
    /// (slab method; `inv_dir` is `1 / dir` per component, infinities allowed). Returns an
    /// empty interval (`t_near > t_far`) when the ray misses.
    #[inline]
    pub fn intersect(&self, origin: Vec3, inv_dir: Vec3) -> (f32, f32) {
        let mut t_near = f32::NEG_INFINITY;
        let mut t_far = f32::INFINITY;
        for a in 0..3 {
            let (o, inv) = (origin[a], inv_dir[a]);
            if inv.is_infinite() {
                // Ray parallel to this slab: inside or out for all t.
                if o < self.min[a] || o > self.max[a] {
                    return (1.0, 0.0);
                }
                continue;
            }
            let t0 = (self.min[a] - o) * inv;
            let t1 = (self.max[a] - o) * inv;
            t_near = t_near.max(t0.min(t1));
            t_far = t_far.min(t0.max(t1));
        }
        (t_near, t_far)
    }
}

/// 64-bit FNV-1a, used for content identities (not for security).
pub struct Fnv1a(u64);

impl Default for Fnv1a {
    fn default() -> Self {
        Self::new()
    }
}

impl Fnv1a {
    /// The FNV-1a 64-bit offset basis.
    pub fn new() -> Self {
        Self(0xcbf2_9ce4_8422_2325)
    }
    /// Mixes `bytes` in.
    pub fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.0 ^= u64::from(b);
            self.0 = self.0.wrapping_mul(0x0100_0000_01b3);
        }
    }
    /// The hash so far.
    pub fn finish(&self) -> u64 {
        self.0
    }
}

/// Bins of the summaries a generator-node sends its tuner (and of `insitu series`).
pub const HISTOGRAM_BINS: usize = 64;

/// A field's histogram over a fixed range, with what the same pass finds besides.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Histogram {
    /// Counts of the values that are not NaN in [`HISTOGRAM_BINS`] equal-width bins; values
    /// outside the range (±∞ too) count in the edge bins.
    pub counts: [u64; HISTOGRAM_BINS],
    /// NaN values.
    pub nan: u64,
    /// Smallest and largest finite value (`None` when there is none).
    pub finite_range: Option<(f32, f32)>,
}

/// The [`Histogram`] of `data` over `[lo, hi]`, in one pass. The range is fixed for a run (the
/// generator-node uses the transfer function's domain), so histograms of different steps and
/// ranks compare and add up.
pub fn histogram(data: &[f32], lo: f64, hi: f64) -> Histogram {
    let mut counts = [0u64; HISTOGRAM_BINS];
    let mut nan = 0;
    let (mut min, mut max) = (f32::INFINITY, f32::NEG_INFINITY);
    let scale = if hi > lo {
        HISTOGRAM_BINS as f64 / (hi - lo)
    } else {
        0.0
    };
    for &v in data {
        if v.is_nan() {
            nan += 1;
            continue;
        }
        if v.is_finite() {
            min = min.min(v);
            max = max.max(v);
        }
        let x = (f64::from(v) - lo) * scale;
        // `as` saturates: −∞ → 0, +∞ → usize::MAX.
        let b = if x <= 0.0 {
            0
        } else {
            (x as usize).min(HISTOGRAM_BINS - 1)
        };
        counts[b] += 1;
    }
    Histogram {
        counts,
        nan,
        finite_range: (min <= max).then_some((min, max)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn world_box_follows_vtk_convention() {
        let v = Volume::new([3, 4, 5], Vec3::new(1.0, 2.0, 0.5), vec![0.0; 60]).unwrap();
        let b = v.world_box();
        assert_eq!(b.min, Vec3::ZERO);
        assert_eq!(b.max, Vec3::new(2.0, 6.0, 2.0));
    }

    /// A new spacing moves the box and keeps the samples in their own type; a spacing that is
    /// not finite and positive is refused.
    #[test]
    fn a_new_spacing_keeps_the_samples_as_they_are() {
        let v = Volume::from_u8([3, 4, 5], Vec3::ONE, vec![7; 60])
            .unwrap()
            .with_origin(Vec3::new(1.0, 1.0, 1.0))
            .unwrap();
        let bytes = v.storage_bytes();
        let w = v.with_spacing(Vec3::new(2.0, 0.5, 1.0)).unwrap();
        assert_eq!(w.storage_bytes(), bytes, "still one byte a voxel");
        let b = w.world_box();
        assert_eq!((b.min, b.max), (Vec3::ONE, Vec3::new(5.0, 2.5, 5.0)));
        for bad in [Vec3::ZERO, Vec3::new(1.0, f32::NAN, 1.0), Vec3::splat(-1.0)] {
            assert!(w.clone().with_spacing(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn rejects_bad_shapes() {
        assert!(Volume::new([0, 1, 1], Vec3::ONE, vec![]).is_err());
        assert!(Volume::new([2, 2, 2], Vec3::ONE, vec![0.0; 7]).is_err());
        assert!(Volume::new([1, 1, 1], Vec3::new(1.0, 0.0, 1.0), vec![0.0]).is_err());
        assert!(Volume::new([1, 1, 1], Vec3::new(1.0, f32::NAN, 1.0), vec![0.0]).is_err());
    }

    #[test]
    fn finite_range_ignores_nan() {
        let v = Volume::new([3, 1, 1], Vec3::ONE, vec![f32::NAN, 2.0, -1.0]).unwrap();
        assert_eq!(v.finite_range(), Some((-1.0, 2.0)));
        let all_nan = Volume::new([2, 1, 1], Vec3::ONE, vec![f32::NAN; 2]).unwrap();
        assert_eq!(all_nan.finite_range(), None);
    }

    #[test]
    fn ray_box_intersection() {
        let b = Aabb {
            min: Vec3::ZERO,
            max: Vec3::splat(10.0),
        };
        let (t0, t1) = b.intersect(
            Vec3::new(5.0, 5.0, -5.0),
            Vec3::new(f32::INFINITY, f32::INFINITY, 1.0),
        );
        assert_eq!((t0, t1), (5.0, 15.0));
        let (t0, t1) = b.intersect(
            Vec3::new(11.0, 5.0, -5.0),
            Vec3::new(f32::INFINITY, f32::INFINITY, 1.0),
        );
        assert!(t0 > t1);
    }
}
