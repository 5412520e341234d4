//! The transfer functions a recording's VDIs were made with, one file each under `tf/`, named
//! by identity hash (`tf/<16 hex digits>.json`, [`TransferFunction::identity_hash`]): each
//! VDI's header carries its transfer function, kept the first time its hash is seen. The
//! viewer's colour legend reads them (`GET /api/tf`), a steered one included.

use insitu_core::TransferFunction;
use insitu_proto::pb;
use std::path::{Path, PathBuf};

/// The recording's folder of transfer functions.
pub const TF_DIR: &str = "tf";

/// Why a VDI's transfer function was not kept.
#[derive(Debug, thiserror::Error)]
pub enum TfKeepError {
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
    /// It could not be written as JSON.
    #[error("transfer function as JSON: {0}")]
    Json(#[from] serde_json::Error),
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

/// Keeps `tf`, the transfer function whose identity is `hash` (a VDI header's, as it came
/// over the wire), as JSON in the recording at `dir` unless it holds it already; returns
/// whether it wrote it.
///
/// # Errors
/// [`TfKeepError`]: invalid, a hash that does not match, or the write failing.
pub fn keep(dir: &Path, hash: u64, tf: &pb::TransferFunction) -> Result<bool, TfKeepError> {
    let file = path(dir, hash);
    if file.is_file() {
        return Ok(false);
    }
    let tf = TransferFunction::try_from(tf)?;
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
        serde_json::to_string(&tf)?.as_bytes(),
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
        let wire = pb::TransferFunction::from(&tf);
        assert!(read(dir.path(), hash).is_none());
        assert!(keep(dir.path(), hash, &wire).unwrap());
        assert!(!keep(dir.path(), hash, &wire).unwrap(), "kept once");
        assert_eq!(read(dir.path(), hash), Some(tf.clone()));
        assert!(matches!(
            keep(dir.path(), hash ^ 1, &wire),
            Err(TfKeepError::Mismatch { .. })
        ));
        let mut bad = wire.clone();
        bad.domain_lo = 10.0;
        assert!(matches!(
            keep(dir.path(), 7, &bad),
            Err(TfKeepError::Invalid(_))
        ));
        assert!(!dir
            .path()
            .join(TF_DIR)
            .join(format!("{:016x}.json", hash ^ 1))
            .exists());
    }
}
