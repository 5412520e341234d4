//! A field that arrives in pieces (a gRPC stream's chunks, a file read in blocks) converted
//! into the volume's own storage as each piece comes: one pass over the
//! bytes, no intermediate buffer of the whole step.

use super::voxels::{Storage, PAD};
use super::{ScalarType, Volume, VolumeError};
use glam::Vec3;

/// Converts little-endian samples of one [`ScalarType`] into a volume's storage piece by
/// piece. Pieces may split a sample anywhere: the bytes of a partial sample wait for the next
/// piece. u8, u16, i16 and f32 stay in their type; f64 becomes f32 (as
/// [`ScalarType::decode`]).
#[derive(Debug)]
pub struct FieldAssembler {
    scalar: ScalarType,
    samples: Storage,
    /// Bytes of a sample split between two pieces.
    carry: [u8; 8],
    carry_len: usize,
    received: u64,
}

impl FieldAssembler {
    /// An empty field of `scalar` samples with room for `voxels` of them.
    pub fn new(scalar: ScalarType, voxels: usize) -> Self {
        Self::reusing(scalar, voxels, None)
    }

    /// [`FieldAssembler::new`] in the memory of `spare`, a volume no longer needed, when it
    /// holds the same storage type: a field of tens of MB in fresh memory costs a page fault
    /// per 4 KiB, in reused memory none.
    pub fn reusing(scalar: ScalarType, voxels: usize, spare: Option<Volume>) -> Self {
        fn emptied<T>(mut v: Vec<T>, n: usize) -> Vec<T> {
            v.clear();
            v.reserve(n);
            v
        }
        let samples = match (scalar, spare.map(Volume::into_storage)) {
            (ScalarType::U8, Some(Storage::U8(v))) => Storage::U8(emptied(v, voxels + PAD)),
            (ScalarType::U8, _) => Storage::U8(Vec::with_capacity(voxels + PAD)),
            (ScalarType::U16, Some(Storage::U16(v))) => Storage::U16(emptied(v, voxels + PAD / 2)),
            (ScalarType::U16, _) => Storage::U16(Vec::with_capacity(voxels + PAD / 2)),
            (ScalarType::I16, Some(Storage::I16(v))) => Storage::I16(emptied(v, voxels + PAD / 2)),
            (ScalarType::I16, _) => Storage::I16(Vec::with_capacity(voxels + PAD / 2)),
            (_, Some(Storage::F32(v))) => Storage::F32(emptied(v, voxels)),
            (_, _) => Storage::F32(Vec::with_capacity(voxels)),
        };
        Self {
            scalar,
            samples,
            carry: [0; 8],
            carry_len: 0,
            received: 0,
        }
    }

    /// Bytes one sample takes in memory (u8 1, u16 and i16 2, the rest 4 as f32).
    pub fn kept_bytes_per_sample(scalar: ScalarType) -> usize {
        match scalar {
            ScalarType::U8 => 1,
            ScalarType::U16 | ScalarType::I16 => 2,
            ScalarType::F32 | ScalarType::F64 => 4,
        }
    }

    /// Room for `voxels` more samples, or the allocator's refusal: a reader that grows a
    /// field as its data decompresses reports a failed allocation as an error naming the
    /// size instead of aborting. Growth is amortized as [`Vec::try_reserve`]'s.
    ///
    /// # Errors
    /// [`std::collections::TryReserveError`] when the memory cannot be had.
    pub fn try_reserve(&mut self, voxels: usize) -> Result<(), std::collections::TryReserveError> {
        match &mut self.samples {
            Storage::U8(v) => v.try_reserve(voxels),
            Storage::U16(v) => v.try_reserve(voxels),
            Storage::I16(v) => v.try_reserve(voxels),
            Storage::F32(v) => v.try_reserve(voxels),
        }
    }

    /// Bytes pushed so far.
    pub fn received_bytes(&self) -> u64 {
        self.received
    }

    /// Appends the next `bytes` of the field.
    pub fn push(&mut self, mut bytes: &[u8]) {
        self.received += bytes.len() as u64;
        let size = self.scalar.size_bytes();
        if self.carry_len > 0 {
            let take = (size - self.carry_len).min(bytes.len());
            self.carry[self.carry_len..self.carry_len + take].copy_from_slice(&bytes[..take]);
            self.carry_len += take;
            bytes = &bytes[take..];
            if self.carry_len < size {
                return;
            }
            let carry = self.carry;
            self.decode(&carry[..size]);
            self.carry_len = 0;
        }
        let whole = bytes.len() - bytes.len() % size;
        self.decode(&bytes[..whole]);
        let rest = &bytes[whole..];
        self.carry[..rest.len()].copy_from_slice(rest);
        self.carry_len = rest.len();
    }

    /// Appends whole samples.
    fn decode(&mut self, bytes: &[u8]) {
        match (&mut self.samples, self.scalar) {
            (Storage::U8(v), _) => v.extend_from_slice(bytes),
            (Storage::U16(v), _) => v.extend(
                bytes
                    .chunks_exact(2)
                    .map(|c| u16::from_le_bytes([c[0], c[1]])),
            ),
            (Storage::I16(v), _) => v.extend(
                bytes
                    .chunks_exact(2)
                    .map(|c| i16::from_le_bytes([c[0], c[1]])),
            ),
            (Storage::F32(v), scalar) => scalar.decode_into(bytes, v),
        }
    }

    /// The volume of `dims` voxels with `spacing`.
    ///
    /// # Errors
    /// [`VolumeError::Invalid`] when the bytes pushed are not exactly `dims` samples (naming
    /// both counts), and as [`Volume::new`] for bad dims or spacing.
    pub fn finish(self, dims: [usize; 3], spacing: Vec3) -> Result<Volume, VolumeError> {
        let expected = dims
            .iter()
            .try_fold(self.scalar.size_bytes() as u64, |a, &d| {
                a.checked_mul(d as u64)
            });
        if expected != Some(self.received) {
            return Err(VolumeError::Invalid(format!(
                "{} bytes of {} received for dimensions {dims:?} ({} bytes expected)",
                self.received,
                self.scalar.name(),
                expected.map_or_else(|| "overflowing".to_owned(), |e| e.to_string())
            )));
        }
        let samples = match self.samples {
            Storage::U8(v) => Storage::from_u8(v),
            Storage::U16(v) => Storage::from_u16(v),
            Storage::I16(v) => Storage::from_i16(v),
            f32s => f32s,
        };
        Volume::with_storage(dims, spacing, samples)
    }
}

impl Volume {
    /// A volume from the little-endian samples of a whole field in `bytes`: u8 taken in place
    /// (no copy), the others converted in one pass as [`FieldAssembler`] does.
    ///
    /// # Errors
    /// As [`FieldAssembler::finish`].
    pub fn from_le_bytes(
        dims: [usize; 3],
        spacing: Vec3,
        scalar: ScalarType,
        bytes: Vec<u8>,
    ) -> Result<Self, VolumeError> {
        if scalar == ScalarType::U8 {
            let n = dims.iter().try_fold(1usize, |a, &d| a.checked_mul(d));
            if n != Some(bytes.len()) {
                return Err(VolumeError::Invalid(format!(
                    "{} bytes of uint8 for dimensions {dims:?}",
                    bytes.len()
                )));
            }
            return Self::from_u8(dims, spacing, bytes);
        }
        let mut a = FieldAssembler::new(scalar, bytes.len() / scalar.size_bytes());
        a.push(&bytes);
        a.finish(dims, spacing)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn le(scalar: ScalarType, values: &[f64]) -> Vec<u8> {
        values
            .iter()
            .flat_map(|&v| match scalar {
                ScalarType::U8 => vec![v as u8],
                ScalarType::U16 => (v as u16).to_le_bytes().to_vec(),
                ScalarType::I16 => (v as i16).to_le_bytes().to_vec(),
                ScalarType::F32 => (v as f32).to_le_bytes().to_vec(),
                ScalarType::F64 => v.to_le_bytes().to_vec(),
            })
            .collect()
    }

    const TYPES: [ScalarType; 5] = [
        ScalarType::U8,
        ScalarType::U16,
        ScalarType::I16,
        ScalarType::F32,
        ScalarType::F64,
    ];

    /// Any split of the bytes into pieces (sizes 1, 3, 5, 7 and a whole) gives the volume that
    /// decoding the whole buffer at once gives, in the type the loader keeps.
    #[test]
    fn pieces_split_anywhere_give_the_whole_field() {
        let dims = [3, 4, 5];
        let values: Vec<f64> = (0..60).map(|i| f64::from((i * 37) % 251)).collect();
        for scalar in TYPES {
            let bytes = le(scalar, &values);
            let whole = Volume::from_le_bytes(dims, Vec3::ONE, scalar, bytes.clone()).unwrap();
            assert_eq!(whole.data(), scalar.decode(&bytes));
            for piece in [1, 3, 5, 7, bytes.len()] {
                let mut a = FieldAssembler::new(scalar, 60);
                for p in bytes.chunks(piece) {
                    a.push(p);
                }
                assert_eq!(a.received_bytes(), bytes.len() as u64);
                let v = a.finish(dims, Vec3::ONE).unwrap();
                assert_eq!(v.data(), whole.data(), "{scalar:?} in pieces of {piece}");
                assert_eq!(v.voxels().scalar_type(), whole.voxels().scalar_type());
                // What is stored reads back as itself.
                let again = Volume::from_le_bytes(
                    dims,
                    Vec3::ONE,
                    v.voxels().scalar_type(),
                    v.voxels().to_le_bytes().into_owned(),
                )
                .unwrap();
                assert_eq!(again, v);
            }
        }
    }

    /// A reused volume's memory holds the new field only: nothing of the old one shows,
    /// whatever the old size or type.
    #[test]
    fn reusing_a_spare_gives_the_same_field() {
        let old = Volume::new([4, 4, 4], Vec3::ONE, vec![7.0; 64]).unwrap();
        let small = Volume::from_u8([2, 2, 2], Vec3::ONE, vec![9; 8]).unwrap();
        for scalar in TYPES {
            let bytes = le(scalar, &[1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0]);
            let fresh = Volume::from_le_bytes([2, 2, 2], Vec3::ONE, scalar, bytes.clone()).unwrap();
            for spare in [old.clone(), small.clone()] {
                let mut a = FieldAssembler::reusing(scalar, 8, Some(spare));
                a.push(&bytes);
                assert_eq!(a.finish([2, 2, 2], Vec3::ONE).unwrap(), fresh, "{scalar:?}");
            }
        }
    }

    #[test]
    fn a_short_or_long_field_is_refused_with_both_counts() {
        for scalar in TYPES {
            let bytes = le(scalar, &[1.0; 8]);
            let mut a = FieldAssembler::new(scalar, 8);
            a.push(&bytes[..bytes.len() - 1]);
            let e = a.finish([2, 2, 2], Vec3::ONE).unwrap_err().to_string();
            assert!(e.contains(&format!("{} bytes", bytes.len() - 1)), "{e}");
            let e = Volume::from_le_bytes([2, 2, 1], Vec3::ONE, scalar, bytes)
                .unwrap_err()
                .to_string();
            assert!(e.contains("[2, 2, 1]"), "{e}");
        }
    }

    #[test]
    fn nan_and_extremes_survive_conversion() {
        let values = [f64::NAN, f64::INFINITY, -1e300, 1e-300, 3.5];
        let v = Volume::from_le_bytes(
            [5, 1, 1],
            Vec3::ONE,
            ScalarType::F64,
            le(ScalarType::F64, &values),
        )
        .unwrap();
        let d = v.data();
        assert!(d[0].is_nan());
        assert_eq!(&d[1..], &[f32::INFINITY, f32::NEG_INFINITY, 0.0, 3.5]);
    }
}
