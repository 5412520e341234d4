//! Our raw layout: headerless samples, x fastest, dims and type in the file name
//! (`<name>_<X>x<Y>x<Z>[x<T>]_<type>.raw`, [`insitu_core::volume::RawFormat`]); spacing 1 and
//! origin 0 unless the caller says otherwise.

use crate::{Dataset, ReadError, Source};
use glam::Vec3;
use insitu_core::volume::RawFormat;
use insitu_core::Volume;
use std::path::Path;

/// A raw file's layout.
#[derive(Debug)]
pub struct Raw(RawFormat);

/// Opens a raw file by its name.
///
/// # Errors
/// [`ReadError::Invalid`] when the name does not carry dims and type.
pub fn open(path: &Path) -> Result<Dataset, ReadError> {
    let format =
        RawFormat::from_file_name(path).map_err(|e| ReadError::invalid(path, e.to_string()))?;
    Ok(Dataset {
        path: path.to_owned(),
        dims: format.dims,
        steps: format.steps,
        spacing: Vec3::ONE,
        origin: Vec3::ZERO,
        field: "values".into(),
        fields: vec!["values".into()],
        notes: Vec::new(),
        source: Source::Raw(Raw(format)),
    })
}

impl Raw {
    pub(crate) fn read_step(
        &self,
        path: &Path,
        t: usize,
        spacing: Vec3,
    ) -> Result<Volume, ReadError> {
        self.0
            .load(path, t, spacing)
            .map_err(|e| ReadError::invalid(path, e.to_string()))
    }
}
