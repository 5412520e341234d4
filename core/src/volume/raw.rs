//! Headerless raw volumes: `<name>_<X>x<Y>x<Z>[x<T>]_<type>.raw`, little-endian, x fastest,
//! then y, z and t (docs/data.md).

use super::{FieldAssembler, Volume, VolumeError};
use glam::Vec3;
use std::io::{Read, Seek, SeekFrom};
use std::path::Path;

/// Voxel types of raw files; all little-endian.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ScalarType {
    /// Unsigned 8-bit.
    U8,
    /// Unsigned 16-bit.
    U16,
    /// Signed 16-bit.
    I16,
    /// IEEE-754 binary32.
    F32,
    /// IEEE-754 binary64 (converted to f32 on load; magnitudes beyond f32 become ±inf).
    F64,
}

impl ScalarType {
    /// Bytes per voxel.
    pub fn size_bytes(self) -> usize {
        match self {
            Self::U8 => 1,
            Self::U16 | Self::I16 => 2,
            Self::F32 => 4,
            Self::F64 => 8,
        }
    }

    /// Canonical name, as used in file names.
    pub fn name(self) -> &'static str {
        match self {
            Self::U8 => "uint8",
            Self::U16 => "uint16",
            Self::I16 => "int16",
            Self::F32 => "float32",
            Self::F64 => "float64",
        }
    }

    /// Converts little-endian samples of this type to `f32`; a trailing partial sample is
    /// ignored (callers check `bytes.len()` against the dims first).
    pub fn decode(self, bytes: &[u8]) -> Vec<f32> {
        let mut out = Vec::with_capacity(bytes.len() / self.size_bytes());
        self.decode_into(bytes, &mut out);
        out
    }

    /// [`ScalarType::decode`] appending to `out`.
    pub fn decode_into(self, bytes: &[u8], out: &mut Vec<f32>) {
        match self {
            Self::U8 => out.extend(bytes.iter().map(|&b| f32::from(b))),
            Self::U16 => out.extend(
                bytes
                    .chunks_exact(2)
                    .map(|c| f32::from(u16::from_le_bytes([c[0], c[1]]))),
            ),
            Self::I16 => out.extend(
                bytes
                    .chunks_exact(2)
                    .map(|c| f32::from(i16::from_le_bytes([c[0], c[1]]))),
            ),
            Self::F32 => out.extend(
                bytes
                    .chunks_exact(4)
                    .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])),
            ),
            Self::F64 => out.extend(bytes.chunks_exact(8).map(|c| {
                let mut b = [0u8; 8];
                b.copy_from_slice(c);
                f64::from_le_bytes(b) as f32
            })),
        }
    }
}

impl std::str::FromStr for ScalarType {
    type Err = VolumeError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Ok(match s.to_ascii_lowercase().as_str() {
            "u8" | "uint8" | "uchar" => Self::U8,
            "u16" | "uint16" | "ushort" => Self::U16,
            "i16" | "int16" | "short" => Self::I16,
            "f32" | "float32" | "float" => Self::F32,
            "f64" | "float64" | "double" => Self::F64,
            _ => return Err(VolumeError::UnknownType(s.to_owned())),
        })
    }
}

/// Bytes read per piece when a raw field is converted as it is read.
const READ_PIECE: usize = 4 << 20;

/// Layout of a raw file: spatial dims, number of time steps and voxel type.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct RawFormat {
    /// `[nx, ny, nz]`.
    pub dims: [usize; 3],
    /// Time steps stored one after the other (1 for a 3-D file).
    pub steps: usize,
    /// Voxel type.
    pub scalar: ScalarType,
}

impl RawFormat {
    /// Parses `<name>_<X>x<Y>x<Z>[x<T>]_<type>.raw`.
    ///
    /// # Errors
    /// [`VolumeError::UnknownLayout`] when the name does not carry dims and type, or
    /// [`VolumeError::UnknownType`] for a type name we do not read.
    pub fn from_file_name(path: &Path) -> Result<Self, VolumeError> {
        let layout_err = |reason: &str| VolumeError::UnknownLayout {
            path: path.to_owned(),
            reason: reason.to_owned(),
        };
        let stem = path
            .file_stem()
            .and_then(|s| s.to_str())
            .ok_or_else(|| layout_err("no file name"))?;
        let mut parts = stem.rsplitn(3, '_');
        let type_part = parts.next().ok_or_else(|| layout_err("no type suffix"))?;
        let dims_part = parts
            .next()
            .ok_or_else(|| layout_err("no dimensions before the type"))?;
        let nums: Vec<usize> = dims_part
            .split('x')
            .map(|d| d.parse::<usize>())
            .collect::<Result<_, _>>()
            .map_err(|_| layout_err(&format!("{dims_part:?} is not XxYxZ[xT]")))?;
        let (dims, steps) = match nums.as_slice() {
            [x, y, z] => ([*x, *y, *z], 1),
            [x, y, z, t] => ([*x, *y, *z], *t),
            _ => return Err(layout_err(&format!("{dims_part:?} is not XxYxZ[xT]"))),
        };
        let scalar = type_part.parse()?;
        Ok(Self {
            dims,
            steps,
            scalar,
        })
    }

    fn step_bytes(&self) -> Option<u64> {
        self.dims
            .iter()
            .try_fold(self.scalar.size_bytes() as u64, |acc, &d| {
                acc.checked_mul(d as u64)
            })
    }

    /// Reads time step `t` of the file at `path` as a volume with `spacing`.
    ///
    /// Only that step's bytes are read. Integer types are converted exactly; f64 is rounded
    /// (u8 and u16 kept in their own type, the others as f32).
    ///
    /// # Errors
    /// [`VolumeError::Io`] when the file cannot be read, [`VolumeError::SizeMismatch`] when
    /// its size is not `steps × dims × voxel size`, [`VolumeError::TimeStepOutOfRange`] when
    /// `t ≥ steps`, and [`VolumeError::Invalid`] for zero dims or a bad spacing.
    pub fn load(&self, path: &Path, t: usize, spacing: Vec3) -> Result<Volume, VolumeError> {
        let io = |source| VolumeError::Io {
            path: path.to_owned(),
            source,
        };
        if self.dims.contains(&0) || self.steps == 0 {
            return Err(VolumeError::Invalid(format!(
                "{}: dimensions {:?} x {} steps contain a zero",
                path.display(),
                self.dims,
                self.steps
            )));
        }
        let step_bytes = self
            .step_bytes()
            .ok_or_else(|| VolumeError::Invalid(format!("dimensions {:?} overflow", self.dims)))?;
        let expected = step_bytes.saturating_mul(self.steps as u64);
        let mut file = std::fs::File::open(path).map_err(io)?;
        let actual = file.metadata().map_err(io)?.len();
        if actual != expected {
            return Err(VolumeError::SizeMismatch {
                path: path.to_owned(),
                dims: self.dims,
                steps: self.steps,
                type_name: self.scalar.name(),
                expected,
                actual,
            });
        }
        if t >= self.steps {
            return Err(VolumeError::TimeStepOutOfRange {
                path: path.to_owned(),
                t,
                steps: self.steps,
            });
        }
        file.seek(SeekFrom::Start(step_bytes * t as u64))
            .map_err(io)?;
        let len = usize::try_from(step_bytes).map_err(|_| {
            VolumeError::Invalid(format!("{step_bytes} bytes do not fit in memory"))
        })?;
        if self.scalar == ScalarType::U8 {
            // Room for the byte storage's padding, so a byte volume is read in place.
            let mut bytes = Vec::with_capacity(len + 4);
            bytes.resize(len, 0u8);
            file.read_exact(&mut bytes).map_err(io)?;
            return Volume::from_le_bytes(self.dims, spacing, self.scalar, bytes);
        }
        // u16 and i16 kept in their own type (exact as f32 values), the others as f32: converted
        // a piece at a time, so reading costs the field and one piece, not the file's bytes too.
        let mut field = FieldAssembler::new(self.scalar, len / self.scalar.size_bytes());
        let mut piece = vec![0u8; READ_PIECE.min(len)];
        let mut left = len;
        while left > 0 {
            let n = left.min(piece.len());
            file.read_exact(&mut piece[..n]).map_err(io)?;
            field.push(&piece[..n]);
            left -= n;
        }
        field.finish(self.dims, spacing)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_names() {
        let f = RawFormat::from_file_name(Path::new("a/teapot_256x256x178_uint8.raw")).unwrap();
        assert_eq!(f.dims, [256, 256, 178]);
        assert_eq!((f.steps, f.scalar), (1, ScalarType::U8));
        let f =
            RawFormat::from_file_name(Path::new("ocean_temp_ts_180x90x19x12_float32.raw")).unwrap();
        assert_eq!(
            (f.dims, f.steps, f.scalar),
            ([180, 90, 19], 12, ScalarType::F32)
        );
        assert!(RawFormat::from_file_name(Path::new("volume.raw")).is_err());
        assert!(matches!(
            RawFormat::from_file_name(Path::new("v_2x2x2_int128.raw")),
            Err(VolumeError::UnknownType(_))
        ));
    }

    #[test]
    fn loads_each_type_and_time_step() {
        let dir = tempfile_dir();
        let path = dir.join("t_2x1x1x2_int16.raw");
        let vals: [i16; 4] = [-5, 7, 300, -32768];
        let bytes: Vec<u8> = vals.iter().flat_map(|v| v.to_le_bytes()).collect();
        std::fs::write(&path, bytes).unwrap();
        let f = RawFormat::from_file_name(&path).unwrap();
        let v1 = f.load(&path, 1, Vec3::ONE).unwrap();
        assert_eq!(*v1.data(), [300.0, -32768.0]);
        assert!(matches!(
            f.load(&path, 2, Vec3::ONE),
            Err(VolumeError::TimeStepOutOfRange { .. })
        ));
        let wrong = RawFormat {
            dims: [3, 1, 1],
            ..f
        };
        assert!(matches!(
            wrong.load(&path, 0, Vec3::ONE),
            Err(VolumeError::SizeMismatch { .. })
        ));
        let f64_path = dir.join("d_2x1x1_float64.raw");
        let bytes: Vec<u8> = [1e300f64, -0.5]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        std::fs::write(&f64_path, bytes).unwrap();
        let v = RawFormat::from_file_name(&f64_path)
            .unwrap()
            .load(&f64_path, 0, Vec3::ONE)
            .unwrap();
        assert_eq!(*v.data(), [f32::INFINITY, -0.5]);
        assert!(matches!(
            f.load(&dir.join("missing_2x1x1_uint8.raw"), 0, Vec3::ONE),
            Err(VolumeError::Io { .. })
        ));
        std::fs::remove_dir_all(dir).unwrap();
    }

    fn tempfile_dir() -> std::path::PathBuf {
        let dir = std::env::temp_dir().join(format!("insitu-raw-test-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }
}
