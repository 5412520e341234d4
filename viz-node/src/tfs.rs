//! The transfer functions a recording's VDIs were made with, one file each under `tf/`, named
//! by identity hash (`tf/<16 hex digits>.json`, [`TransferFunction::identity_hash`]): each
//! VDI's header carries its transfer function, kept the first time its hash is seen. The
//! viewer's colour legend reads them (`GET /api/tf`), a steered one included.

use insitu_core::TransferFunction;
use std::path::{Path, PathBuf};

/// The recording's folder of transfer functions.
pub const TF_DIR: &str = "tf";

/// Largest transfer function kept, bytes of JSON (as the generation config takes).
pub const MAX_TF_BYTES: usize = 1 << 20;

/// Why a VDI's transfer function was not kept.
#[derive(Debug, thiserror::Error)]
pub enum TfKeepError {
    /// Over [`MAX_TF_BYTES`].
    #[error("transfer function of {0} bytes is over the {MAX_TF_BYTES}-byte limit")]
    TooLarge(usize),
    /// Not a valid transfer function.
    #[error(transparent)]
    Invalid(#[from] insitu_core::tf::TfError),
    /// Its identity is not the hash the header gives.
    #[error("transfer function hashes to {found:016x}, the header says {said:016x}")]
    Mismatch {
        /// The header's.
        said: u64,
        /// The JSON's.
        found: u64,
    },
    /// The file could not be written.
    #[error("{}: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
}

fn path(dir: &Path, hash: u64) -> PathBuf {
    dir.join(TF_DIR).join(format!("{hash:016x}.json"))
}

/// Keeps `json`, the transfer function whose identity is `hash`, in the recording at `dir`
/// unless it holds it already; returns whether it wrote it.
///
/// # Errors
/// [`TfKeepError`]: too large, invalid, a hash that does not match, or the write failing.
pub fn keep(dir: &Path, hash: u64, json: &str) -> Result<bool, TfKeepError> {
    let file = path(dir, hash);
    if file.is_file() {
        return Ok(false);
    }
    if json.len() > MAX_TF_BYTES {
        return Err(TfKeepError::TooLarge(json.len()));
    }
    let tf = TransferFunction::from_json(json, "the VDI header's transfer function")?;
    let found = tf.identity_hash();
    if found != hash {
        return Err(TfKeepError::Mismatch { said: hash, found });
    }
    let io = |source| TfKeepError::Io {
        path: file.clone(),
        source,
    };
    std::fs::create_dir_all(dir.join(TF_DIR)).map_err(io)?;
    insitu_core::file::write_atomic(
        &file,
        json.as_bytes(),
        insitu_core::file::Durability::PowerLoss,
    )
    .map_err(io)?;
    Ok(true)
}

/// The transfer function `hash` names, if the recording at `dir` keeps it.
pub fn read(dir: &Path, hash: u64) -> Option<TransferFunction> {
    let file = path(dir, hash);
    let text = std::fs::read_to_string(&file).ok()?;
    TransferFunction::from_json(&text, &file.display().to_string())
        .ok()
        .filter(|tf| tf.identity_hash() == hash)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_transfer_function_is_kept_once_by_its_hash_and_a_wrong_one_refused() {
        let dir = tempfile::tempdir().unwrap();
        let tf = TransferFunction::default_for_range(-1.0, 3.0);
        let hash = tf.identity_hash();
        let json = serde_json::to_string(&tf).unwrap();
        assert!(read(dir.path(), hash).is_none());
        assert!(keep(dir.path(), hash, &json).unwrap());
        assert!(!keep(dir.path(), hash, &json).unwrap(), "kept once");
        assert_eq!(read(dir.path(), hash), Some(tf.clone()));
        assert!(matches!(
            keep(dir.path(), hash ^ 1, &json),
            Err(TfKeepError::Mismatch { .. })
        ));
        assert!(matches!(
            keep(dir.path(), 7, "{\"domain\": [1, 0], \"points\": []}"),
            Err(TfKeepError::Invalid(_))
        ));
        let huge = " ".repeat(MAX_TF_BYTES + 1);
        assert!(matches!(
            keep(dir.path(), 8, &huge),
            Err(TfKeepError::TooLarge(_))
        ));
        assert!(!dir
            .path()
            .join(TF_DIR)
            .join(format!("{:016x}.json", hash ^ 1))
            .exists());
    }
}
