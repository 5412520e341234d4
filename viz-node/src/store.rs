//! The recording directory: one file per VDI (`step_SSSSSSSS_rank_RRRR.vdi`, the core codec
//! format as shipped), one per set of reference frames (`….refs`), and `index.json` listing
//! every step and rank with σ, τ, `P_M` and, once scored, q. Every file is written to a
//! temporary name in the same directory, synced, and renamed, so a crash never leaves a half
//! file under a final name (and the index never names a file that is not complete).

pub use insitu_core::metrics::Db;
use insitu_core::volume::bricks::Brick;
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
    /// Where the rank's brick lies in the whole grid (none from nodes that do not say).
    #[serde(default)]
    pub placement: Option<Placement>,
    /// Whether reference frames of this step and rank were announced with the VDI.
    #[serde(default)]
    pub with_references: bool,
}

/// A rank's brick in the whole grid, voxels (DESIGN.md, "A world of ranks").
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Placement {
    /// The whole grid.
    pub global_dims: [usize; 3],
    /// The brick.
    pub brick: Brick,
}

/// One step of a world of ranks, composed from its ranks' VDIs.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StepEntry {
    /// Step index.
    pub step: u64,
    /// Ranks of the world.
    pub world_size: u32,
    /// Ranks in the composition.
    pub ranks: Vec<u32>,
    /// Ranks missing (a partial step, composed after the timeout).
    pub missing: Vec<u32>,
    /// The composed VDI, relative to the recording directory.
    pub vdi: Option<String>,
    /// The composed reference frames.
    pub references: Option<String>,
    /// σ, bytes: the sum of the ranks' files.
    pub sigma_bytes: u64,
    /// τ, seconds: the slowest rank's.
    pub tau_secs: f64,
    /// Supersegments over all ranks.
    pub supersegments: u64,
    /// `r`, `γ` and the P_M version of the ranks.
    pub resolution: u32,
    /// `γ`.
    pub gamma: f32,
    /// P_M version.
    pub pm_version: u64,
    /// Codec name of the ranks' files (the composed file uses it too).
    pub codec: String,
    /// q of the composed VDI against the composed references.
    pub quality: Option<Quality>,
    /// Why it could not be composed.
    pub error: Option<String>,
}

impl Entry {
    /// An entry of `step` and `rank` with nothing stored yet.
    pub fn empty(step: u64, rank: u32) -> Self {
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
            placement: None,
            with_references: false,
        }
    }
}

/// The index as written: entries borrowed, by step then rank.
#[derive(Serialize)]
struct IndexRef<'a> {
    version: u32,
    entries: Vec<&'a Entry>,
    steps: Vec<&'a StepEntry>,
}

#[derive(Deserialize)]
struct IndexFile {
    version: u32,
    entries: Vec<Entry>,
    #[serde(default)]
    steps: Vec<StepEntry>,
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
    /// Accumulated opacity per pixel and view (ranks of a world of several send it, so that
    /// their frames can be composited).
    pub opacity: Option<Vec<Vec<f32>>>,
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
    #[serde(default)]
    opacity: bool,
}

impl References {
    /// Builds from the wire layout: `views × h × w × 3` little-endian f32, or `× 4` (RGB and
    /// opacity) when `opacity`.
    ///
    /// # Errors
    /// A message naming the mismatch (length, non-finite or out-of-range values).
    pub fn from_bytes(
        camera: Camera,
        view_angles_deg: Vec<f32>,
        (width, height): (u32, u32),
        opacity: bool,
        bytes: &[u8],
    ) -> Result<Self, String> {
        let per = width as usize * height as usize;
        let channels = if opacity { 4 } else { 3 };
        let expected = per * 4 * channels * view_angles_deg.len();
        if width == 0 || height == 0 || view_angles_deg.is_empty() || bytes.len() != expected {
            return Err(format!(
                "{} bytes for {} views of {width}×{height}×{channels} f32 (need {expected}, width, height and views ≥ 1)",
                bytes.len(),
                view_angles_deg.len()
            ));
        }
        let bad = || "reference pixels must be finite and in [0, 1]".to_owned();
        let mut frames = Vec::with_capacity(view_angles_deg.len());
        let mut planes = Vec::new();
        for f in bytes.chunks_exact(per * 4 * channels) {
            let values: Vec<f32> = f
                .chunks_exact(4)
                .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                .collect();
            if values.iter().any(|v| !(0.0..=1.0).contains(v)) {
                return Err(bad());
            }
            let rgb = values
                .chunks_exact(channels)
                .map(|p| [p[0], p[1], p[2]])
                .collect();
            frames.push(Image::from_pixels(width, height, rgb).ok_or_else(bad)?);
            if opacity {
                planes.push(values.chunks_exact(4).map(|p| p[3]).collect());
            }
        }
        Ok(Self {
            camera,
            view_angles_deg,
            frames,
            opacity: opacity.then_some(planes),
        })
    }

    /// The `.refs` file layout: magic, JSON header length and header, then the frames.
    pub fn to_file_bytes(&self) -> Vec<u8> {
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
            opacity: self.opacity.is_some(),
        };
        // Serialising a plain struct of numbers cannot fail.
        let json = serde_json::to_vec(&header).unwrap_or_default();
        let mut out =
            Vec::with_capacity(16 + json.len() + self.frames.len() * (w * h) as usize * 12);
        out.extend_from_slice(REFS_MAGIC);
        out.extend_from_slice(&(json.len() as u64).to_le_bytes());
        out.extend_from_slice(&json);
        match &self.opacity {
            None => {
                for f in &self.frames {
                    out.extend_from_slice(&f.to_f32_le());
                }
            }
            Some(planes) => {
                for (f, a) in self.frames.iter().zip(planes) {
                    for (c, a) in f.pixels().iter().zip(a) {
                        for v in [c[0], c[1], c[2], *a] {
                            out.extend_from_slice(&v.to_le_bytes());
                        }
                    }
                }
            }
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
            (h.width, h.height),
            h.opacity,
            &bytes[16 + n..],
        )
        .map_err(corrupt)
    }
}

/// The recording directory and its index.
pub struct Recording {
    dir: PathBuf,
    index: Mutex<Index>,
}

#[derive(Default)]
struct Index {
    entries: BTreeMap<(u64, u32), Entry>,
    steps: BTreeMap<u64, StepEntry>,
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

/// The file name of a step's composed VDI.
pub fn composed_vdi_name(step: u64) -> String {
    format!("step_{step:08}_composed.vdi")
}

/// The file name of a step's composed reference frames.
pub fn composed_refs_name(step: u64) -> String {
    format!("step_{step:08}_composed.refs")
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
        let mut all = Index::default();
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
                all.entries.insert((e.step, e.rank), e);
            }
            for s in file.steps {
                all.steps.insert(s.step, s);
            }
        }
        Ok(Self {
            dir: dir.to_owned(),
            index: Mutex::new(all),
        })
    }

    /// The directory.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Index> {
        self.index.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn write_index(&self, index: &Index) -> Result<(), StoreError> {
        serde_json::to_vec_pretty(&IndexRef {
            version: INDEX_VERSION,
            entries: index.entries.values().collect(),
            steps: index.steps.values().collect(),
        })
        .map_err(|e| StoreError::Corrupt {
            path: self.dir.join(INDEX),
            problem: e.to_string(),
        })
        .and_then(|json| write_atomic(&self.dir, INDEX, &json))
    }

    /// Applies `f` to the entry of `key` and rewrites the index; on failure the in-memory
    /// index is left as it was.
    fn update(&self, key: (u64, u32), f: impl FnOnce(&mut Entry)) -> Result<Entry, StoreError> {
        let mut index = self.lock();
        let mut next = index
            .entries
            .get(&key)
            .cloned()
            .unwrap_or_else(|| Entry::empty(key.0, key.1));
        f(&mut next);
        let previous = index.entries.insert(key, next.clone());
        if let Err(e) = self.write_index(&index) {
            match previous {
                Some(p) => index.entries.insert(key, p),
                None => index.entries.remove(&key),
            };
            return Err(e);
        }
        Ok(next)
    }

    /// Records a composed step (replacing an earlier composition of it).
    ///
    /// # Errors
    /// [`StoreError`]; the in-memory index is left as it was.
    pub fn set_step(&self, step: StepEntry) -> Result<(), StoreError> {
        let mut index = self.lock();
        let previous = index.steps.insert(step.step, step.clone());
        if let Err(e) = self.write_index(&index) {
            match previous {
                Some(p) => index.steps.insert(step.step, p),
                None => index.steps.remove(&step.step),
            };
            return Err(e);
        }
        Ok(())
    }

    /// A composed step.
    pub fn step(&self, step: u64) -> Option<StepEntry> {
        self.lock().steps.get(&step).cloned()
    }

    /// All composed steps, in order.
    pub fn steps(&self) -> Vec<StepEntry> {
        self.lock().steps.values().cloned().collect()
    }

    /// The entries of every rank of `step` stored so far, by rank.
    pub fn ranks_of(&self, step: u64) -> Vec<Entry> {
        self.lock()
            .entries
            .range((step, 0)..=(step, u32::MAX))
            .map(|(_, e)| e.clone())
            .collect()
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
        self.lock().entries.get(&(step, rank)).cloned()
    }

    /// All entries, by step then rank.
    pub fn entries(&self) -> Vec<Entry> {
        self.lock().entries.values().cloned().collect()
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
            opacity: Some(vec![vec![0.5; 6], vec![1.0; 6]]),
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
        assert!(References::from_bytes(cam, vec![0.0], (2, 2), false, &[0u8; 47]).is_err());
        assert!(References::from_bytes(cam, vec![0.0], (2, 2), true, &[0u8; 48]).is_err());
        assert!(References::from_bytes(cam, vec![0.0], (2, 2), true, &[0u8; 64]).is_ok());
        let nan: Vec<u8> = std::iter::repeat_n(f32::NAN.to_le_bytes(), 12)
            .flatten()
            .collect();
        assert!(References::from_bytes(cam, vec![0.0], (2, 2), false, &nan).is_err());
        assert!(References::from_bytes(cam, vec![], (2, 2), false, &[]).is_err());
    }

    fn glam_vec(v: f32) -> glam::Vec3 {
        glam::Vec3::splat(v)
    }
}
