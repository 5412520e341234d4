//! What the benchmarks share: the teapot scene of issue 3 (256×256×178 u8 from
//! `../shared/data`, `../shared/tf/teapot.json`; `INSITU_DATA_DIR` and `INSITU_TF_DIR`
//! override the folders).

use insitu_core::volume::RawFormat;
use insitu_core::{TransferFunction, Volume};
use std::path::PathBuf;

fn dir(var: &str, default: &str) -> PathBuf {
    std::env::var_os(var)
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join(default))
}

/// The teapot volume and its transfer function, or why they could not be loaded.
pub fn teapot() -> Result<(Volume, TransferFunction), String> {
    let path = dir("INSITU_DATA_DIR", "../../shared/data").join("teapot_256x256x178_uint8.raw");
    let tf_path = dir("INSITU_TF_DIR", "../../shared/tf").join("teapot.json");
    let tf = TransferFunction::load(&tf_path)
        .map_err(|e| format!("needs {}: {e}", tf_path.display()))?;
    let volume = RawFormat::from_file_name(&path)
        .and_then(|f| f.load(&path, 0, glam::Vec3::ONE))
        .map_err(|e| format!("needs {}: {e}", path.display()))?;
    Ok((volume, tf))
}
