//! What the benchmarks share: the shared volumes and their transfer functions, above all the
//! teapot scene (256×256×178 u8 with `teapot.json`, found by `insitu_testenv`: docs/data.md),
//! and the reading of their parameters and timings.

use insitu_core::volume::RawFormat;
use insitu_core::{TransferFunction, Volume};

/// The teapot volume and its transfer function, or why they could not be loaded.
#[allow(dead_code)] // the `volumes` bench loads every shared volume through `shared`
pub fn teapot() -> Result<(Volume, TransferFunction), String> {
    shared("teapot_256x256x178_uint8.raw", Some("teapot.json"))
}

/// The shared volume `file` with the transfer function `tf` from the TF folder, or without
/// one the default ramp over its data range (what `insitu` uses without `--tf`); or why they
/// could not be loaded.
pub fn shared(file: &str, tf: Option<&str>) -> Result<(Volume, TransferFunction), String> {
    let path = insitu_testenv::data_file(file)
        .ok_or_else(|| format!("needs {file} (scripts/fetch-data.sh; docs/data.md)"))?;
    let volume = RawFormat::from_file_name(&path)
        .and_then(|f| f.load(&path, 0, glam::Vec3::ONE))
        .map_err(|e| format!("needs {}: {e}", path.display()))?;
    let tf = match tf {
        Some(name) => {
            let tf_path = insitu_testenv::tf_file(name)
                .ok_or_else(|| format!("needs the transfer function {name} (docs/data.md)"))?;
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

/// The environment variable `name` as a count, else `default` (unset or not a number).
#[allow(dead_code)] // not every bench takes parameters
pub fn env(name: &str, default: usize) -> usize {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

/// The median of `v` (the upper one of an even count); `v` must not be empty.
#[allow(dead_code)] // not every bench takes medians of its own
pub fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}
