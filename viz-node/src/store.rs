//! The recording directory: one file per VDI (`step_SSSSSSSS_rank_RRRR.vdi`, the core codec
//! format as shipped), one per set of reference frames (`….refs`), and `index.json` listing
//! every step and rank with σ, τ, `P_M` and, once scored, q. Every file is written to a
//! temporary name in the same directory, synced, and renamed, so a crash never leaves a half
//! file under a final name (and the index never names a file that is not complete).

pub use insitu_core::metrics::Db;
use insitu_core::{Camera, Image};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Mutex;

/// The index file's name.
pub const INDEX: &str = "index.json";
/// The index file's format version.
pub const INDEX_VERSION: u32 = 1;
const REFS_MAGIC: &[u8; 8] = b"INSREF1\n";

/// Errors of the recording; each names the file.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// A file could not be read or written.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// A file is not what it should be.
    #[error("{path}: {problem}")]
    Corrupt {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        problem: String,
    },
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> StoreError + '_ {
    move |source| StoreError::Io {
        path: path.to_owned(),
        source,
    }
}

/// Quality of a stored VDI against its step's reference frames.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Quality {
    /// Pooled PSNR (of the mean MSE), dB.
    pub q_db: Db,
    /// Per-view PSNR, dB, in the references' order.
    pub view_q_db: Vec<Db>,
    /// Per-view MSE.
    pub view_mse: Vec<f64>,
    /// Mean SSIM over the views (none for frames under 11×11).
    pub ssim: Option<f64>,
}

/// One step and rank in the recording.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Entry {
    /// Step index.
    pub step: u64,
    /// Rank.
    pub rank: u32,
    /// Number of ranks.
    pub world_size: u32,
    /// Simulation time.
    pub sim_time: f64,
    /// VDI file, relative to the recording directory.
    pub vdi: Option<String>,
    /// Reference frames file, relative to the recording directory.
    pub references: Option<String>,
    /// `r`.
    pub resolution: u32,
    /// `γ`.
    pub gamma: f32,
    /// Codec name.
    pub codec: String,
    /// σ, bytes.
    pub sigma_bytes: u64,
    /// Supersegments.
    pub supersegments: u64,
    /// τ, seconds.
    pub tau_secs: f64,
    /// Compression time, seconds.
    pub tau_compress_secs: f64,
    /// Transfer function name and identity.
    pub tf_name: String,
    /// [`insitu_core::TransferFunction::identity_hash`].
    pub tf_hash: u64,
    /// q, once scored.
    pub quality: Option<Quality>,
    /// The tuner's P_M version the VDI was made with (0: not from a tuner).
    #[serde(default)]
    pub pm_version: u64,
}

impl Entry {
    fn empty(step: u64, rank: u32) -> Self {
        Self {
            step,
            rank,
            world_size: 1,
            sim_time: 0.0,
            vdi: None,
            references: None,
            resolution: 0,
            gamma: 0.0,
            codec: String::new(),
            sigma_bytes: 0,
            supersegments: 0,
            tau_secs: 0.0,
            tau_compress_secs: 0.0,
            tf_name: String::new(),
            tf_hash: 0,
            quality: None,
            pm_version: 0,
        }
    }
}

/// The index as written: entries borrowed, by step then rank.
#[derive(Serialize)]
struct IndexRef<'a> {
    version: u32,
    entries: Vec<&'a Entry>,
}

#[derive(Deserialize)]
struct IndexFile {
    version: u32,
    entries: Vec<Entry>,
}

/// Reference frames of one step and rank: the generation camera, the views, the images.
#[derive(Clone, Debug, PartialEq)]
pub struct References {
    /// Generation camera; view `k` is `camera.orbit_y(view_angles_deg[k])`.
    pub camera: Camera,
    /// Orbit angles, degrees.
    pub view_angles_deg: Vec<f32>,
    /// One image per view.
    pub frames: Vec<Image>,
}

#[derive(Serialize, Deserialize)]
struct RefsHeader {
    eye: [f32; 3],
    target: [f32; 3],
    up: [f32; 3],
    fov_y_deg: f32,
    width: u32,
    height: u32,
    view_angles_deg: Vec<f32>,
}

impl References {
    /// Builds from the wire layout: `views × h × w × 3` little-endian f32.
    ///
    /// # Errors
    /// A message naming the mismatch (length, non-finite or out-of-range values).
    pub fn from_bytes(
        camera: Camera,
        view_angles_deg: Vec<f32>,
        width: u32,
        height: u32,
        bytes: &[u8],
    ) -> Result<Self, String> {
        let per = width as usize * height as usize;
        let expected = per * 12 * view_angles_deg.len();
        if width == 0 || height == 0 || view_angles_deg.is_empty() || bytes.len() != expected {
            return Err(format!(
                "{} bytes for {} views of {width}×{height} (need {expected}, width, height and views ≥ 1)",
                bytes.len(),
                view_angles_deg.len()
            ));
        }
        let frames = bytes
            .chunks_exact(per * 12)
            .map(|f| Image::from_f32_le(width, height, f))
            .collect::<Option<Vec<_>>>()
            .ok_or("reference pixels must be finite and in [0, 1]")?;
        Ok(Self {
            camera,
            view_angles_deg,
            frames,
        })
    }

    fn to_file_bytes(&self) -> Vec<u8> {
        let (w, h) = self
            .frames
            .first()
            .map_or((0, 0), |f| (f.width(), f.height()));
        let header = RefsHeader {
            eye: self.camera.eye.into(),
            target: self.camera.target.into(),
            up: self.camera.up.into(),
            fov_y_deg: self.camera.fov_y_deg,
            width: w,
            height: h,
            view_angles_deg: self.view_angles_deg.clone(),
        };
        // Serialising a plain struct of numbers cannot fail.
        let json = serde_json::to_vec(&header).unwrap_or_default();
        let mut out =
            Vec::with_capacity(16 + json.len() + self.frames.len() * (w * h) as usize * 12);
        out.extend_from_slice(REFS_MAGIC);
        out.extend_from_slice(&(json.len() as u64).to_le_bytes());
        out.extend_from_slice(&json);
        for f in &self.frames {
            out.extend_from_slice(&f.to_f32_le());
        }
        out
    }

    /// Reads a `.refs` file.
    ///
    /// # Errors
    /// [`StoreError`] for I/O or a malformed file.
    pub fn read(path: &Path) -> Result<Self, StoreError> {
        let bytes = std::fs::read(path).map_err(io(path))?;
        let corrupt = |problem: String| StoreError::Corrupt {
            path: path.to_owned(),
            problem,
        };
        if bytes.len() < 16 || &bytes[..8] != REFS_MAGIC {
            return Err(corrupt("not a reference-frames file".into()));
        }
        let mut n = [0u8; 8];
        n.copy_from_slice(&bytes[8..16]);
        let n = usize::try_from(u64::from_le_bytes(n)).unwrap_or(usize::MAX);
        let json = bytes
            .get(16..16usize.saturating_add(n))
            .ok_or_else(|| corrupt("header runs past the end".into()))?;
        let h: RefsHeader = serde_json::from_slice(json).map_err(|e| corrupt(e.to_string()))?;
        let camera = Camera {
            eye: h.eye.into(),
            target: h.target.into(),
            up: h.up.into(),
            fov_y_deg: h.fov_y_deg,
        };
        Self::from_bytes(
            camera,
            h.view_angles_deg,
            h.width,
            h.height,
            &bytes[16 + n..],
        )
        .map_err(corrupt)
    }
}

/// The recording directory and its index.
pub struct Recording {
    dir: PathBuf,
    entries: Mutex<BTreeMap<(u64, u32), Entry>>,
}

/// Writes `bytes` to `dir/name` atomically (temp file in `dir`, fsync, rename).
///
/// # Errors
/// [`StoreError::Io`].
pub fn write_atomic(dir: &Path, name: &str, bytes: &[u8]) -> Result<(), StoreError> {
    let path = dir.join(name);
    let mut tmp = tempfile::Builder::new()
        .prefix(".tmp-")
        .tempfile_in(dir)
        .map_err(io(&path))?;
    tmp.write_all(bytes).map_err(io(&path))?;
    tmp.as_file().sync_all().map_err(io(&path))?;
    tmp.persist(&path).map_err(|e| StoreError::Io {
        path: path.clone(),
        source: e.error,
    })?;
    Ok(())
}

/// The file name of a step's VDI.
pub fn vdi_name(step: u64, rank: u32) -> String {
    format!("step_{step:08}_rank_{rank:04}.vdi")
}

/// The file name of a step's reference frames.
pub fn refs_name(step: u64, rank: u32) -> String {
    format!("step_{step:08}_rank_{rank:04}.refs")
}

impl Recording {
    /// Opens (creating) `dir`, continuing an existing index.
    ///
    /// # Errors
    /// [`StoreError`] when the directory cannot be created or the index is corrupt (it is
    /// never silently replaced).
    pub fn open(dir: &Path) -> Result<Self, StoreError> {
        std::fs::create_dir_all(dir).map_err(io(dir))?;
        let index = dir.join(INDEX);
        let mut entries = BTreeMap::new();
        if index.exists() {
            let text = std::fs::read(&index).map_err(io(&index))?;
            let file: IndexFile =
                serde_json::from_slice(&text).map_err(|e| StoreError::Corrupt {
                    path: index.clone(),
                    problem: format!("{e}; move it away to start a new recording here"),
                })?;
            if file.version != INDEX_VERSION {
                return Err(StoreError::Corrupt {
                    path: index,
                    problem: format!(
                        "index version {} is not {INDEX_VERSION}; move it away to start a new recording here",
                        file.version
                    ),
                });
            }
            for e in file.entries {
                entries.insert((e.step, e.rank), e);
            }
        }
        Ok(Self {
            dir: dir.to_owned(),
            entries: Mutex::new(entries),
        })
    }

    /// The directory.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, BTreeMap<(u64, u32), Entry>> {
        self.entries.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Applies `f` to the entry of `key` and rewrites the index; on failure the in-memory
    /// index is left as it was.
    fn update(&self, key: (u64, u32), f: impl FnOnce(&mut Entry)) -> Result<Entry, StoreError> {
        let mut entries = self.lock();
        let mut next = entries
            .get(&key)
            .cloned()
            .unwrap_or_else(|| Entry::empty(key.0, key.1));
        f(&mut next);
        let previous = entries.insert(key, next.clone());
        let written = serde_json::to_vec_pretty(&IndexRef {
            version: INDEX_VERSION,
            entries: entries.values().collect(),
        })
        .map_err(|e| StoreError::Corrupt {
            path: self.dir.join(INDEX),
            problem: e.to_string(),
        })
        .and_then(|json| write_atomic(&self.dir, INDEX, &json));
        if let Err(e) = written {
            match previous {
                Some(p) => entries.insert(key, p),
                None => entries.remove(&key),
            };
            return Err(e);
        }
        Ok(next)
    }

    /// Records a VDI file (already validated by the caller) and its metadata; the file is on
    /// disk before the index names it.
    ///
    /// # Errors
    /// [`StoreError`].
    pub fn store_vdi(&self, meta: Entry, file: &[u8]) -> Result<Entry, StoreError> {
        let name = vdi_name(meta.step, meta.rank);
        write_atomic(&self.dir, &name, file)?;
        self.update((meta.step, meta.rank), |e| {
            let references = e.references.take();
            *e = Entry {
                vdi: Some(name),
                references,
                quality: None,
                ..meta
            };
        })
    }

    /// Records reference frames.
    ///
    /// # Errors
    /// [`StoreError`].
    pub fn store_references(
        &self,
        step: u64,
        rank: u32,
        refs: &References,
    ) -> Result<Entry, StoreError> {
        let name = refs_name(step, rank);
        write_atomic(&self.dir, &name, &refs.to_file_bytes())?;
        self.update((step, rank), |e| {
            e.references = Some(name);
            e.quality = None;
        })
    }

    /// Records the quality of a step's VDI.
    ///
    /// # Errors
    /// [`StoreError`].
    pub fn set_quality(&self, step: u64, rank: u32, q: Quality) -> Result<Entry, StoreError> {
        self.update((step, rank), |e| e.quality = Some(q))
    }

    /// One entry.
    pub fn entry(&self, step: u64, rank: u32) -> Option<Entry> {
        self.lock().get(&(step, rank)).cloned()
    }

    /// All entries, by step then rank.
    pub fn entries(&self) -> Vec<Entry> {
        self.lock().values().cloned().collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn entry(step: u64) -> Entry {
        Entry {
            resolution: 4,
            gamma: 0.5,
            codec: "zstd".into(),
            ..Entry::empty(step, 0)
        }
    }

    #[test]
    fn the_index_survives_a_reopen_and_names_only_complete_files() {
        let dir = tempfile::tempdir().unwrap();
        let rec = Recording::open(dir.path()).unwrap();
        rec.store_vdi(entry(3), b"vdi bytes").unwrap();
        let refs = References {
            camera: Camera::default_for_box(&insitu_core::volume::Aabb {
                min: glam_vec(0.0),
                max: glam_vec(1.0),
            }),
            view_angles_deg: vec![0.0, 30.0],
            frames: vec![Image::new(2, 3), Image::new(2, 3)],
        };
        rec.store_references(3, 0, &refs).unwrap();
        rec.set_quality(
            3,
            0,
            Quality {
                q_db: Db(f64::INFINITY),
                view_q_db: vec![Db(f64::INFINITY), Db(40.0)],
                view_mse: vec![0.0, 1e-4],
                ssim: None,
            },
        )
        .unwrap();
        drop(rec);
        let rec = Recording::open(dir.path()).unwrap();
        let e = rec.entry(3, 0).unwrap();
        assert_eq!(e.quality.unwrap().q_db, Db(f64::INFINITY));
        assert_eq!(
            References::read(&dir.path().join(e.references.unwrap())).unwrap(),
            refs
        );
        assert_eq!(
            std::fs::read(dir.path().join(e.vdi.unwrap())).unwrap(),
            b"vdi bytes"
        );
        let names: Vec<String> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|d| d.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        assert!(names.iter().all(|n| !n.starts_with(".tmp-")), "{names:?}");
    }

    #[test]
    fn a_corrupt_index_is_refused_not_replaced() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join(INDEX), b"{ half").unwrap();
        let e = Recording::open(dir.path()).err().unwrap().to_string();
        assert!(e.contains("index.json"), "{e}");
        assert_eq!(std::fs::read(dir.path().join(INDEX)).unwrap(), b"{ half");
    }

    #[test]
    fn malformed_reference_bytes_are_refused() {
        let cam = Camera {
            eye: glam_vec(5.0),
            target: glam_vec(0.0),
            up: glam::Vec3::Y,
            fov_y_deg: 30.0,
        };
        assert!(References::from_bytes(cam, vec![0.0], 2, 2, &[0u8; 47]).is_err());
        let nan: Vec<u8> = std::iter::repeat_n(f32::NAN.to_le_bytes(), 12)
            .flatten()
            .collect();
        assert!(References::from_bytes(cam, vec![0.0], 2, 2, &nan).is_err());
        assert!(References::from_bytes(cam, vec![], 2, 2, &[]).is_err());
    }

    fn glam_vec(v: f32) -> glam::Vec3 {
        glam::Vec3::splat(v)
    }
}
