//! The on-disk study cache (Sec. 5.5: "we first collect and cache all result data"). One JSON
//! file per scene identity — a hash of everything that determines a measurement except `P_M`
//! (volume content, transfer function, camera, test views, image size, ray-casting step,
//! termination, shading, codec, and the code version) — holding one row per `P_M`. A file that
//! does not parse, or whose recorded identity differs, is never trusted: it is rebuilt with a
//! warning.

use crate::grid::Candidate;
use crate::measure::Measurement;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use tracing::warn;

/// Bumped whenever a change to generation, codec, rendering or metrics changes measurements.
pub const MEASUREMENT_VERSION: u32 = 2;

/// Errors writing the cache.
#[derive(Debug, thiserror::Error)]
#[error("cache file {path}: {source}")]
pub struct CacheError {
    /// The file.
    pub path: PathBuf,
    /// Why.
    pub source: std::io::Error,
}

#[derive(Serialize, Deserialize)]
struct CacheFile {
    version: u32,
    code: String,
    key: String,
    scene: String,
    entries: Vec<Measurement>,
}

/// Rows of one scene, keyed by `P_M`.
pub struct Cache {
    path: Option<PathBuf>,
    key: u64,
    scene: String,
    entries: BTreeMap<(u32, u32, u32), Measurement>,
    unsaved: usize,
}

fn slot(c: Candidate) -> (u32, u32, u32) {
    c.key()
}

impl Cache {
    /// A cache that lives only in memory.
    pub fn in_memory(key: u64) -> Self {
        Self {
            path: None,
            key,
            scene: String::new(),
            entries: BTreeMap::new(),
            unsaved: 0,
        }
    }

    /// The cache of scene `key` in `dir` (`scene` describes it for people reading the file).
    /// A missing file starts empty; a corrupt or mismatched one is rebuilt with a warning.
    pub fn open(dir: &Path, key: u64, scene: &str) -> Self {
        let path = dir.join(format!("study-{key:016x}.json"));
        let mut cache = Self {
            path: Some(path.clone()),
            key,
            scene: scene.to_owned(),
            entries: BTreeMap::new(),
            unsaved: 0,
        };
        let Ok(text) = std::fs::read(&path) else {
            return cache;
        };
        match serde_json::from_slice::<CacheFile>(&text) {
            Ok(f)
                if f.version == MEASUREMENT_VERSION
                    && f.key == format!("{key:016x}")
                    && f.code == code_version() =>
            {
                for m in f.entries {
                    cache.entries.insert(slot(m.candidate()), m);
                }
            }
            Ok(_) => {
                warn!(path = %path.display(), "cache file is for another scene or code version; rebuilding it")
            }
            Err(e) => {
                warn!(path = %path.display(), error = %e, "cache file is corrupt; rebuilding it")
            }
        }
        cache
    }

    /// The identity this cache is for.
    pub fn key(&self) -> u64 {
        self.key
    }

    /// A cached row.
    pub fn get(&self, c: Candidate) -> Option<&Measurement> {
        self.entries.get(&slot(c))
    }

    /// Adds a row; saves every 16 new rows.
    ///
    /// # Errors
    /// [`CacheError`] when saving fails.
    pub fn insert(&mut self, m: Measurement) -> Result<(), CacheError> {
        self.entries.insert(slot(m.candidate()), m);
        self.unsaved += 1;
        if self.unsaved >= 16 {
            self.save()?;
        }
        Ok(())
    }

    /// All rows, by r then γ.
    pub fn rows(&self) -> Vec<Measurement> {
        self.entries.values().cloned().collect()
    }

    /// Writes the file atomically (temp file + rename), if this cache has one.
    ///
    /// # Errors
    /// [`CacheError`].
    pub fn save(&mut self) -> Result<(), CacheError> {
        let Some(path) = &self.path else {
            return Ok(());
        };
        let err = |source| CacheError {
            path: path.clone(),
            source,
        };
        let file = CacheFile {
            version: MEASUREMENT_VERSION,
            code: code_version(),
            key: format!("{:016x}", self.key),
            scene: self.scene.clone(),
            entries: self.rows(),
        };
        let json = serde_json::to_vec_pretty(&file).map_err(|e| err(std::io::Error::other(e)))?;
        let dir = path.parent().unwrap_or(Path::new("."));
        std::fs::create_dir_all(dir).map_err(err)?;
        // A cache: losing it to a power cut costs a re-measurement, not worth an fsync.
        insitu_core::file::write_atomic(path, &json, insitu_core::file::Durability::Crash)
            .map_err(err)?;
        self.unsaved = 0;
        Ok(())
    }
}

/// The code identity recorded in cache files.
pub fn code_version() -> String {
    format!(
        "insitu-tuner {} / measurements v{MEASUREMENT_VERSION}",
        env!("CARGO_PKG_VERSION")
    )
}
