//! The recording directory: one file per VDI (`step_SSSSSSSS_rank_RRRR.vdi`, the core codec
//! format as shipped), one per set of reference frames (`….refs`), composed steps'
//! `step_SSSSSSSS_composed.*`, and the index ([`crate::index`], `index.sqlite`) with a row per
//! step and rank (σ, τ, `P_M`, and once scored q) and per composed step. Every file is written
//! to a temporary name in the same directory, synced, and renamed before its row is committed,
//! so a crash never leaves a half file under a final name and the index never names a file
//! that is not complete; [`Recording::recover`] tidies what a crash leaves on the next start.

use crate::index::{with_recovery_advice, IndexDb, INDEX_DB};
pub use crate::rows::{
    composed_refs_name, composed_vdi_name, refs_name, vdi_name, Entry, Placement, Quality,
    StepEntry, StoreError,
};
pub use insitu_core::metrics::Db;
use insitu_core::{Camera, Image};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Mutex;

/// The JSON index of recordings made before the SQLite index: imported once, then renamed
/// `index.json.imported`.
pub const LEGACY_INDEX: &str = "index.json";
/// The legacy JSON index's format version.
pub const LEGACY_INDEX_VERSION: u32 = 1;
/// Reference frames as written now: header, frames, and a CRC-32 of all before it.
const REFS_MAGIC: &[u8; 8] = b"INSREF2\n";
/// As written before the checksum (still read, unchecked).
const REFS_MAGIC_V1: &[u8; 8] = b"INSREF1\n";

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> StoreError + '_ {
    move |source| StoreError::Io {
        path: path.to_owned(),
        source,
    }
}

/// The legacy JSON index.
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
    /// The step the frames belong to (none in files written before it was kept).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    step: Option<u64>,
    /// Their rank (none for a composed step's frames).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    rank: Option<u32>,
}

/// Whose reference frames a `.refs` file holds: the step, and the rank (none: the step
/// composed over its ranks).
pub type RefsOrigin = (u64, Option<u32>);

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

    /// Memory held by the frames and opacity planes, bytes.
    pub fn memory_bytes(&self) -> usize {
        let frames: usize = self.frames.iter().map(|f| size_of_val(f.pixels())).sum();
        let planes: usize = self
            .opacity
            .iter()
            .flatten()
            .map(|p| size_of_val(&p[..]))
            .sum();
        frames + planes
    }

    /// The `.refs` file layout: magic, JSON header length and header (with `origin`, whose
    /// frames they are), then the frames, then a CRC-32 of all before it.
    pub fn to_file_bytes(&self, origin: RefsOrigin) -> Vec<u8> {
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
            step: Some(origin.0),
            rank: origin.1,
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
        let crc = crc32fast::hash(&out);
        out.extend_from_slice(&crc.to_le_bytes());
        out
    }

    /// Reads a `.refs` file; its checksum must match (files written before the checksum are
    /// read unchecked).
    ///
    /// # Errors
    /// [`StoreError`] for I/O or a malformed file, or one whose checksum does not match.
    pub fn read(path: &Path) -> Result<Self, StoreError> {
        Self::read_with_origin(path).map(|(refs, _)| refs)
    }

    /// As [`References::read`], with whose frames the file says they are (none in files
    /// written before it said).
    ///
    /// # Errors
    /// As [`References::read`].
    pub fn read_with_origin(path: &Path) -> Result<(Self, Option<RefsOrigin>), StoreError> {
        let mut bytes = std::fs::read(path).map_err(io(path))?;
        let corrupt = |problem: String| StoreError::Corrupt {
            path: path.to_owned(),
            problem,
        };
        let checked = bytes.get(..8) == Some(REFS_MAGIC.as_slice());
        if bytes.len() < 16 || !(checked || &bytes[..8] == REFS_MAGIC_V1) {
            return Err(corrupt("not a reference-frames file".into()));
        }
        if checked {
            let Some(body) = bytes.len().checked_sub(4).filter(|&b| b >= 16) else {
                return Err(corrupt("too short for its checksum".into()));
            };
            let mut stored = [0u8; 4];
            stored.copy_from_slice(&bytes[body..]);
            let (stored, computed) = (u32::from_le_bytes(stored), crc32fast::hash(&bytes[..body]));
            if stored != computed {
                return Err(corrupt(format!(
                    "checksum mismatch (stored CRC-32 {stored:08x}, computed {computed:08x}): the file is damaged"
                )));
            }
            bytes.truncate(body);
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
        let origin = h.step.map(|step| (step, h.rank));
        let refs = Self::from_bytes(
            camera,
            h.view_angles_deg,
            (h.width, h.height),
            h.opacity,
            &bytes[16 + n..],
        )
        .map_err(corrupt)?;
        Ok((refs, origin))
    }
}

/// The recording directory and its index (rows cached in memory, each change committed to
/// the database before the cache takes it).
pub struct Recording {
    dir: PathBuf,
    index: Mutex<Index>,
}

struct Index {
    db: IndexDb,
    entries: BTreeMap<(u64, u32), Entry>,
    steps: BTreeMap<u64, StepEntry>,
}

/// What [`Recording::recover`] found on start (after a crash: temporary files, payloads whose
/// row was never committed, rows whose file was removed, steps stored but not scored or
/// composed).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Recovery {
    /// Temporary files removed.
    pub temp_removed: Vec<String>,
    /// Payload files no row names (kept, reported).
    pub files_without_rows: Vec<String>,
    /// Rows naming files that are missing (kept, reported).
    pub rows_without_files: Vec<String>,
    /// Single-rank (step, rank) with a VDI and references but no q: to score.
    pub unscored: Vec<(u64, u32)>,
    /// Multi-rank steps with ranks stored but no composition: to compose.
    pub uncomposed: Vec<u64>,
}

fn is_payload(name: &str) -> bool {
    name.starts_with("step_") && (name.ends_with(".vdi") || name.ends_with(".refs"))
}

/// Writes `bytes` to `dir/name` atomically and durably
/// ([`insitu_core::file::write_atomic`]: temporary file, fsync, rename, directory fsync).
///
/// # Errors
/// [`StoreError::Io`] naming the file.
pub fn write_atomic(dir: &Path, name: &str, bytes: &[u8]) -> Result<(), StoreError> {
    let path = dir.join(name);
    insitu_core::file::write_atomic(&path, bytes, insitu_core::file::Durability::PowerLoss)
        .map_err(io(&path))
}

impl Recording {
    /// Opens (creating) `dir`, continuing an existing index; a legacy `index.json` is
    /// imported once (and renamed `index.json.imported`).
    ///
    /// # Errors
    /// [`StoreError`] when the directory cannot be created, the index is corrupt (it is never
    /// silently replaced), or the directory holds payload files but no index (it is never
    /// silently orphaned by a new recording beside them).
    pub fn open(dir: &Path) -> Result<Self, StoreError> {
        std::fs::create_dir_all(dir).map_err(io(dir))?;
        // An empty index file (truncated, say) is no index: were it taken as a new one, the next
        // steps' files would replace the old steps' files of the same names.
        let fresh = !crate::index::holds_index(dir).map_err(|e| with_recovery_advice(e, dir))?;
        let legacy = dir.join(LEGACY_INDEX);
        let imported = if fresh && legacy.exists() {
            let text = std::fs::read(&legacy).map_err(io(&legacy))?;
            let file: IndexFile =
                serde_json::from_slice(&text).map_err(|e| StoreError::Corrupt {
                    path: legacy.clone(),
                    problem: format!("{e}; move it away to start a new recording here"),
                })?;
            if file.version != LEGACY_INDEX_VERSION {
                return Err(StoreError::Corrupt {
                    path: legacy,
                    problem: format!(
                        "index version {} is not {LEGACY_INDEX_VERSION}; move it away to start a new recording here",
                        file.version
                    ),
                });
            }
            Some(file)
        } else {
            None
        };
        if fresh && imported.is_none() {
            let payloads = std::fs::read_dir(dir)
                .map_err(io(dir))?
                .filter_map(Result::ok)
                .filter(|d| is_payload(&d.file_name().to_string_lossy()))
                .count();
            if payloads > 0 {
                return Err(StoreError::Corrupt {
                    path: dir.join(INDEX_DB),
                    problem: format!(
                        "missing or empty, but the directory holds {payloads} VDI or reference files: restore the index, rebuild it from the files with `insitu recover --recording {}`, or record into another directory (a new index here would orphan them, and the next steps would replace their files)",
                        dir.display()
                    ),
                });
            }
        }
        let db = IndexDb::open(dir, true)
            .and_then(|db| db.check().map(|()| db))
            .map_err(|e| with_recovery_advice(e, dir))?;
        if let Some(file) = imported {
            for e in &file.entries {
                db.put_entry(e)?;
            }
            for st in &file.steps {
                db.put_step(st)?;
            }
            let done = dir.join(format!("{LEGACY_INDEX}.imported"));
            std::fs::rename(&legacy, &done).map_err(io(&legacy))?;
            tracing::info!(
                entries = file.entries.len(),
                "imported the legacy index.json"
            );
        }
        Self::over(dir, db)
    }

    /// Opens the recording in `dir` for reading only: nothing is created, tidied or written
    /// beside it ([`IndexDb::open`] read-only; immutable when no viz-node is writing it), so a
    /// recording on read-only media or owned by another user opens. Storing into it fails.
    /// A directory of shards (`shard-0`, `shard-1`, … each a viz-node's recording, docs/scale.md)
    /// opens as one recording of all their steps.
    ///
    /// # Errors
    /// [`StoreError::Corrupt`] naming the index when there is none (no recording here) or it
    /// cannot be read.
    pub fn open_read_only(dir: &Path) -> Result<Self, StoreError> {
        let shards = crate::index::shards(dir);
        if let Some((first, _)) = shards.first() {
            // A recording shared by step among viz-nodes: every shard's rows, their files
            // named under the shard's directory; nothing is ever written through `db`.
            let all = crate::index::export_shards(&shards)?;
            let db = IndexDb::open(first, false)?;
            return Ok(Self::with_rows(dir, db, all.entries, all.steps));
        }
        if !crate::index::holds_index(dir).map_err(|e| with_recovery_advice(e, dir))? {
            return Err(StoreError::Corrupt {
                path: dir.join(INDEX_DB),
                problem: "missing or empty: no recording to serve here".into(),
            });
        }
        let db = IndexDb::open(dir, false)?;
        Self::over(dir, db)
    }

    /// The recording in `dir` over its opened index, its rows cached.
    fn over(dir: &Path, db: IndexDb) -> Result<Self, StoreError> {
        let (entries, steps) = (db.entries()?, db.steps()?);
        Ok(Self::with_rows(dir, db, entries, steps))
    }

    /// The recording in `dir` over `db`, with `entries` and `steps` as its cached rows.
    fn with_rows(dir: &Path, db: IndexDb, entries: Vec<Entry>, steps: Vec<StepEntry>) -> Self {
        Self {
            dir: dir.to_owned(),
            index: Mutex::new(Index {
                db,
                entries: entries.into_iter().map(|e| ((e.step, e.rank), e)).collect(),
                steps: steps.into_iter().map(|st| (st.step, st)).collect(),
            }),
        }
    }

    /// Tidies what a crash left and says what is left to do: removes temporary files, lists
    /// payload files no row names and rows whose files are missing (both kept: a person
    /// decides), and the steps stored but not yet scored or composed.
    ///
    /// # Errors
    /// [`StoreError::Io`] when the directory cannot be read.
    pub fn recover(&self) -> Result<Recovery, StoreError> {
        let mut r = self.left_to_do();
        let index = self.lock();
        let mut named = std::collections::HashSet::new();
        for e in index.entries.values() {
            named.extend(e.vdi.iter().chain(&e.references).cloned());
        }
        for st in index.steps.values() {
            named.extend(st.vdi.iter().chain(&st.references).cloned());
        }
        for name in &named {
            if !self.dir.join(name).exists() {
                r.rows_without_files.push(name.clone());
            }
        }
        for d in std::fs::read_dir(&self.dir).map_err(io(&self.dir))? {
            let Ok(d) = d else { continue };
            let name = d.file_name().to_string_lossy().into_owned();
            if name.starts_with(insitu_core::file::TEMP_PREFIX) {
                if std::fs::remove_file(d.path()).is_ok() {
                    r.temp_removed.push(name);
                }
            } else if is_payload(&name) && !named.contains(&name) {
                r.files_without_rows.push(name);
            }
        }
        r.temp_removed.sort();
        r.files_without_rows.sort();
        r.rows_without_files.sort();
        Ok(r)
    }

    /// The steps stored but not yet scored or composed (`unscored`, `uncomposed`; the other
    /// fields empty), read from the index alone: unlike [`Recording::recover`] it touches no
    /// file, so it may be polled while a viz-node writes to the recording.
    pub fn left_to_do(&self) -> Recovery {
        let mut r = Recovery::default();
        let index = self.lock();
        for e in index.entries.values() {
            if e.world_size <= 1 && e.vdi.is_some() && e.references.is_some() && e.quality.is_none()
            {
                r.unscored.push((e.step, e.rank));
            }
            if e.world_size > 1
                && !index.steps.contains_key(&e.step)
                && r.uncomposed.last() != Some(&e.step)
            {
                r.uncomposed.push(e.step);
            }
        }
        r
    }

    /// The whole index (see [`IndexDb::export`]).
    ///
    /// # Errors
    /// As [`IndexDb::export`].
    pub fn export(&self) -> Result<crate::index::Export, StoreError> {
        self.lock().db.export()
    }

    /// The directory.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Index> {
        self.index.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Applies `f` to the entry of `key` and commits its row (one transaction); the cache
    /// takes the change only once it is committed.
    fn update(&self, key: (u64, u32), f: impl FnOnce(&mut Entry)) -> Result<Entry, StoreError> {
        let mut index = self.lock();
        let mut next = index
            .entries
            .get(&key)
            .cloned()
            .unwrap_or_else(|| Entry::empty(key.0, key.1));
        f(&mut next);
        index.db.put_entry(&next)?;
        index.entries.insert(key, next.clone());
        Ok(next)
    }

    /// [`Recording::update`] for a payload `name` just written: when the row cannot be
    /// committed (e.g. the disk filled up), the file is removed again, so that a refused item
    /// leaves nothing behind and its retry starts clean.
    fn update_or_unlink(
        &self,
        name: &str,
        key: (u64, u32),
        f: impl FnOnce(&mut Entry),
    ) -> Result<(Entry, bool), StoreError> {
        match self.update(key, f) {
            Ok(e) => Ok((e, true)),
            Err(err) => {
                let _ = std::fs::remove_file(self.dir.join(name));
                Err(err)
            }
        }
    }

    /// Records a composed step (replacing an earlier composition of it).
    ///
    /// # Errors
    /// [`StoreError`]; the cache is left as it was.
    pub fn set_step(&self, step: StepEntry) -> Result<(), StoreError> {
        let mut index = self.lock();
        index.db.put_step(&step)?;
        index.steps.insert(step.step, step);
        Ok(())
    }

    /// Whether `name` (a payload of `step`/`rank`) already holds exactly `bytes`: a retry
    /// after a lost acknowledgement. `Err(AlreadyExists)` when it holds something else.
    fn duplicate(
        &self,
        existing: Option<&String>,
        (step, rank, what): (u64, u32, &'static str),
        bytes: &[u8],
    ) -> Result<bool, StoreError> {
        let Some(name) = existing else {
            return Ok(false);
        };
        let path = self.dir.join(name);
        match std::fs::read(&path) {
            Ok(old) if old == bytes => Ok(true),
            Ok(_) => Err(StoreError::AlreadyExists { step, rank, what }),
            // The row names a file that is gone: store it again.
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(false),
            Err(source) => Err(StoreError::Io { path, source }),
        }
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
    /// disk before the index names it. Returns the entry and whether it is new: the same
    /// (step, rank) with identical bytes is an idempotent success (`false`).
    ///
    /// # Errors
    /// [`StoreError::AlreadyExists`] when the same (step, rank) holds a different VDI;
    /// [`StoreError`] for I/O and the index.
    pub fn store_vdi(&self, meta: Entry, file: &[u8]) -> Result<(Entry, bool), StoreError> {
        let existing = self.entry(meta.step, meta.rank);
        let key = (meta.step, meta.rank, "VDI");
        if self.duplicate(existing.as_ref().and_then(|e| e.vdi.as_ref()), key, file)? {
            return Ok((existing.unwrap_or(meta), false));
        }
        let name = vdi_name(meta.step, meta.rank);
        write_atomic(&self.dir, &name, file)?;
        self.update_or_unlink(&name, (meta.step, meta.rank), |e| {
            let references = e.references.take();
            *e = Entry {
                vdi: Some(name.clone()),
                references,
                quality: None,
                ..meta
            };
        })
    }

    /// Records reference frames; returns the entry and whether they are new (identical
    /// frames stored again are an idempotent success).
    ///
    /// # Errors
    /// [`StoreError::AlreadyExists`] when different frames are stored for the same step and
    /// rank; [`StoreError`] for I/O and the index.
    pub fn store_references(
        &self,
        step: u64,
        rank: u32,
        refs: &References,
    ) -> Result<(Entry, bool), StoreError> {
        let bytes = refs.to_file_bytes((step, Some(rank)));
        let existing = self.entry(step, rank);
        let key = (step, rank, "reference frames");
        if self.duplicate(
            existing.as_ref().and_then(|e| e.references.as_ref()),
            key,
            &bytes,
        )? {
            return Ok((existing.unwrap_or_else(|| Entry::empty(step, rank)), false));
        }
        let name = refs_name(step, rank);
        write_atomic(&self.dir, &name, &bytes)?;
        self.update_or_unlink(&name, (step, rank), |e| {
            e.references = Some(name.clone());
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

    /// The newest stored step, without copying the index.
    pub fn latest_step(&self) -> Option<u64> {
        self.lock()
            .entries
            .keys()
            .next_back()
            .map(|&(step, _)| step)
    }

    /// All entries, by step then rank.
    pub fn entries(&self) -> Vec<Entry> {
        self.lock().entries.values().cloned().collect()
    }
}

#[cfg(test)]
mod tests;
