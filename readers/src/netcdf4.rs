//! netCDF-4 files (HDF5 underneath: chunked, compressed, any byte order) through Unidata's
//! netCDF-C library (the `netcdf` crate; Debian's `libnetcdf-dev`), behind the `netcdf4`
//! feature. The CF conventions are applied as for classic files ([`crate::netcdf3`]): a
//! variable of `(z, y, x)` or `(t, z, y, x)` in the root group, packing, missing values, axes
//! from coordinate variables, an uneven axis resampled or kept by index.
//!
//! A step is read in slabs of whole z-planes (about 4 MiB each) in the file's own type, so
//! memory stays near the field's size and decompression happens in the library.

use crate::bytes::{Endian, Sample};
use crate::cf::{self, Axis, Coordinate, Decode, Packing};
use crate::{Dataset, Options, ReadError, Source};
use glam::Vec3;
use insitu_core::Volume;
use netcdf::types::{FloatType, IntType, NcVariableType};
use netcdf::AttributeValue;
use std::path::Path;

/// A netCDF-4 variable chosen for reading.
#[derive(Debug)]
pub struct Variable {
    name: String,
    decode: Decode,
    /// Whether the variable has a time dimension first.
    series: bool,
}

fn library(path: &Path, what: &str, e: netcdf::Error) -> ReadError {
    ReadError::invalid(path, format!("{what}: {e}"))
}

fn sample_of(t: &NcVariableType) -> Option<Sample> {
    Some(match t {
        NcVariableType::Int(IntType::I8) => Sample::I8,
        NcVariableType::Int(IntType::U8) => Sample::U8,
        NcVariableType::Int(IntType::I16) => Sample::I16,
        NcVariableType::Int(IntType::U16) => Sample::U16,
        NcVariableType::Int(IntType::I32) => Sample::I32,
        NcVariableType::Int(IntType::U32) => Sample::U32,
        NcVariableType::Int(IntType::I64) => Sample::I64,
        NcVariableType::Int(IntType::U64) => Sample::U64,
        NcVariableType::Float(FloatType::F32) => Sample::F32,
        NcVariableType::Float(FloatType::F64) => Sample::F64,
        _ => return None,
    })
}

/// An attribute's numbers (none for text).
fn numbers(v: AttributeValue) -> Option<Vec<f64>> {
    use AttributeValue as A;
    Some(match v {
        A::Uchar(x) => vec![f64::from(x)],
        A::Uchars(x) => x.into_iter().map(f64::from).collect(),
        A::Schar(x) => vec![f64::from(x)],
        A::Schars(x) => x.into_iter().map(f64::from).collect(),
        A::Ushort(x) => vec![f64::from(x)],
        A::Ushorts(x) => x.into_iter().map(f64::from).collect(),
        A::Short(x) => vec![f64::from(x)],
        A::Shorts(x) => x.into_iter().map(f64::from).collect(),
        A::Uint(x) => vec![f64::from(x)],
        A::Uints(x) => x.into_iter().map(f64::from).collect(),
        A::Int(x) => vec![f64::from(x)],
        A::Ints(x) => x.into_iter().map(f64::from).collect(),
        A::Ulonglong(x) => vec![x as f64],
        A::Ulonglongs(x) => x.into_iter().map(|v| v as f64).collect(),
        A::Longlong(x) => vec![x as f64],
        A::Longlongs(x) => x.into_iter().map(|v| v as f64).collect(),
        A::Float(x) => vec![f64::from(x)],
        A::Floats(x) => x.into_iter().map(f64::from).collect(),
        A::Double(x) => vec![x],
        A::Doubles(x) => x,
        A::Str(_) | A::Strs(_) => return None,
    })
}

fn text(v: AttributeValue) -> Option<String> {
    match v {
        AttributeValue::Str(s) => Some(s),
        _ => None,
    }
}

/// Opens a netCDF-4 file, choosing `options.field` (else the first variable of three or four
/// dimensions in the root group that is not a coordinate).
///
/// # Errors
/// [`ReadError`] naming the file: what netCDF-C refuses (not a netCDF file, damaged), an
/// unknown or absent variable, a variable of other than three or four dimensions, a type that
/// is not a number, a coordinate variable that cannot be read.
pub fn open(path: &Path, options: &Options) -> Result<Dataset, ReadError> {
    let file = netcdf::open(path)
        .map_err(|e| library(path, "netCDF-C cannot open this netCDF-4 file", e))?;
    let is_coord = |v: &netcdf::Variable<'_>| {
        v.dimensions().len() == 1 && v.dimensions()[0].name() == v.name()
    };
    let volumes: Vec<String> = file
        .variables()
        .filter(|v| (3..=4).contains(&v.dimensions().len()) && !is_coord(v))
        .map(|v| v.name())
        .collect();
    let name = match &options.field {
        Some(name) => name.clone(),
        None => volumes
            .first()
            .cloned()
            .ok_or_else(|| ReadError::invalid(path, "no variable of three or four dimensions"))?,
    };
    let var = file.variable(&name).ok_or_else(|| {
        ReadError::invalid(
            path,
            format!(
                "no variable {name:?} in the root group; volumes here: {}",
                volumes.join(", ")
            ),
        )
    })?;
    let dims = var.dimensions();
    let k = dims.len();
    if !(3..=4).contains(&k) {
        return Err(ReadError::invalid(
            path,
            format!("variable {name} has {k} dimensions: a volume has (z, y, x) or (t, z, y, x)"),
        ));
    }
    let sample = sample_of(&var.vartype()).ok_or_else(|| {
        ReadError::invalid(
            path,
            format!("variable {name} holds {:?}, not numbers", var.vartype()),
        )
    })?;
    let file_dims = [dims[k - 1].len(), dims[k - 2].len(), dims[k - 3].len()];
    let steps = if k == 4 { dims[0].len() } else { 1 };
    if steps == 0 {
        return Err(ReadError::invalid(
            path,
            format!("variable {name} has no step"),
        ));
    }
    let attr = |v: &netcdf::Variable<'_>, a: &str| v.attribute(a).and_then(|a| a.value().ok());
    let packing = Packing::from_attrs(|a| attr(&var, a).and_then(numbers), sample);
    let mut axes = Vec::with_capacity(3);
    for (a, n) in file_dims.iter().enumerate() {
        let dim = dims[k - 1 - a].name();
        let coordinate = match file.variable(&dim).filter(is_coord) {
            Some(cv) => Some(Coordinate {
                values: cv
                    .get_values::<f64, _>(0..*n)
                    .map_err(|e| library(path, &format!("coordinate variable {dim}"), e))?,
                units: attr(&cv, "units").and_then(text),
                name: dim.clone(),
            }),
            None => None,
        };
        axes.push(Axis { dim, coordinate });
    }
    let axes: [Axis; 3] = axes
        .try_into()
        .map_err(|_| ReadError::invalid(path, "three axes"))?;
    let native = if cfg!(target_endian = "little") {
        Endian::Little
    } else {
        Endian::Big
    };
    let grid = cf::grid(
        path,
        file_dims,
        axes,
        sample,
        native,
        packing,
        options.uneven,
    )?;
    let series = k == 4;
    Ok(grid.dataset(path, steps, name.clone(), volumes, |decode| {
        Source::NetCdf4(Box::new(Variable {
            name,
            decode,
            series,
        }))
    }))
}

impl Variable {
    /// Step `t` as a volume of `dims` (after resampling) at `spacing`.
    pub(crate) fn read_step(
        &self,
        path: &Path,
        t: usize,
        dims: [usize; 3],
        spacing: Vec3,
    ) -> Result<Volume, ReadError> {
        let file = netcdf::open(path)
            .map_err(|e| library(path, "netCDF-C cannot open this netCDF-4 file", e))?;
        let var = file
            .variable(&self.name)
            .ok_or_else(|| ReadError::invalid(path, format!("variable {} is gone", self.name)))?;
        let [nx, ny, nz] = self.decode.stored_dims();
        let plane = nx * ny * self.decode.sample_size();
        let per_slab = (crate::bytes::PIECE / plane.max(1)).clamp(1, nz.max(1));
        self.decode.volume(path, dims, spacing, |push| {
            let mut buf = vec![0u8; per_slab * plane];
            let mut z = 0;
            while z < nz {
                let k = per_slab.min(nz - z);
                let mut extents = vec![z..z + k, 0..ny, 0..nx];
                if self.series {
                    extents.insert(0, t..t + 1);
                }
                var.get_raw_values_into(&mut buf[..k * plane], extents)
                    .map_err(|e| library(path, &format!("step {t}, planes {z}..{}", z + k), e))?;
                push(&buf[..k * plane]);
                z += k;
            }
            Ok(())
        })
    }
}
