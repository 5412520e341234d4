//! What the benchmarks share: the shared volumes and their transfer functions, above all the
//! teapot scene (256×256×178 u8 from `../shared/data`, `../shared/tf/teapot.json`;
//! `INSITU_DATA_DIR` and `INSITU_TF_DIR` override the folders).

use insitu_core::volume::RawFormat;
use insitu_core::{TransferFunction, Volume};
use std::path::PathBuf;

fn dir(var: &str, default: &str) -> PathBuf {
    std::env::var_os(var)
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join(default))
}

/// The teapot volume and its transfer function, or why they could not be loaded.
#[allow(dead_code)] // the `volumes` bench loads every shared volume through `shared`
pub fn teapot() -> Result<(Volume, TransferFunction), String> {
    shared("teapot_256x256x178_uint8.raw", Some("teapot.json"))
}

/// The shared volume `file` with the transfer function `tf` from the TF folder, or without
/// one the default ramp over its data range (what `insitu` uses without `--tf`); or why they
/// could not be loaded.
pub fn shared(file: &str, tf: Option<&str>) -> Result<(Volume, TransferFunction), String> {
    let path = dir("INSITU_DATA_DIR", "../../shared/data").join(file);
    let volume = RawFormat::from_file_name(&path)
        .and_then(|f| f.load(&path, 0, glam::Vec3::ONE))
        .map_err(|e| format!("needs {}: {e}", path.display()))?;
    let tf = match tf {
        Some(name) => {
            let tf_path = dir("INSITU_TF_DIR", "../../shared/tf").join(name);
            TransferFunction::load(&tf_path)
                .map_err(|e| format!("needs {}: {e}", tf_path.display()))?
        }
        None => {
            let (lo, hi) = volume.finite_range().unwrap_or((0.0, 1.0));
            TransferFunction::default_for_range(lo, hi)
        }
    };
    Ok((volume, tf))
}
