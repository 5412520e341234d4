//! Decoded once: the recording's files as the node reads them, and the VDIs and reference
//! frames a stream has just delivered, kept decoded for the scorer and the composer.
//!
//! A VDI arrives compressed, is decoded to be checked, and is written to the recording as it
//! came; the scorer (single rank) or the composer (several) needs it decoded again moments
//! later. Decoding twice costs a whole decode per step: the teapot at r = 768 with bzip2
//! (18 MB, 1.58 M supersegments) takes about 1.0 s to decode on this project's 2-core
//! machine, its parts in parallel (2.0–2.3 s as one stream, before format version 2; the
//! zstd file, in 8 MB parts, 0.12 s).
//! Reference frames are parsed on receipt and written out, and were parsed again from disk
//! to score. [`Kept`] holds what was decoded on receipt until its one
//! reader takes it, within a byte budget per kind (oldest dropped first); whatever is not
//! there (dropped, or from before a restart) is read and decoded from the recording, so the
//! budget trades memory for time and never changes a result.
//!
//! Only files written once under their name (a rank's VDI and frames; see
//! [`crate::store::Recording::store_vdi`]) are kept; composed files, which a later complete
//! composition replaces, are always read from disk.

use crate::store::{Entry, References, StepEntry, StoreError};
use insitu_core::vdi::codec::{self, CodecError, DecodeLimits};
use insitu_core::Vdi;
use std::collections::VecDeque;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

/// A recording's VDI file that cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum LoadError {
    /// The file cannot be read.
    #[error("cannot read {path}: {source}")]
    Read {
        /// The file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// The file is a VDI, but not the one its index row describes (swapped or replaced).
    #[error("{path} holds {} bytes and {} supersegments, but its index row says {} bytes and {} supersegments: it is not this step's VDI", found.0, found.1, row.0, row.1)]
    Mismatch {
        /// The file.
        path: PathBuf,
        /// Its bytes and supersegments.
        found: (u64, u64),
        /// The row's.
        row: (u64, u64),
    },
    /// The file says it is the VDI of another step or rank than its row (swapped or replaced).
    #[error("{path} holds the VDI of step {} rank {}, but its index row is step {}{}: it is not this row's VDI", found.0, found.1, row.0, row.1.map(|r| format!(" rank {r}")).unwrap_or_default())]
    NotItsRow {
        /// The file.
        path: PathBuf,
        /// The step and rank its provenance names.
        found: (u64, u32),
        /// The row's step, and rank (none for a composed step).
        row: (u64, Option<u32>),
    },
    /// The file is not a VDI this node can decode.
    #[error("{path} is not a usable VDI: {source}")]
    Decode {
        /// The file.
        path: PathBuf,
        /// Why.
        source: CodecError,
    },
}

/// What an index row says of its VDI file, checked when the file is read: a file that
/// disagrees (another step's file, swapped or replaced) is refused rather than shown as this
/// step. A rank's row gives the file's bytes and supersegments; a composed step's row sums its
/// ranks', which says nothing of the composed file, so it checks nothing.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Expected {
    /// The file's length, bytes (σ of a rank's VDI).
    pub bytes: Option<u64>,
    /// Its supersegments.
    pub supersegments: Option<u64>,
    /// The row's step: a file whose provenance names another is refused.
    pub step: Option<u64>,
    /// The row's rank (none for a composed step, whose file is one VDI of the whole grid).
    pub rank: Option<u32>,
}

impl From<&Entry> for Expected {
    /// A count of 0 is a row that does not say (written before rows carried it, or by hand),
    /// and is not checked.
    fn from(e: &Entry) -> Self {
        let said = |v: u64| (v > 0).then_some(v);
        Self {
            bytes: said(e.sizing.sigma_bytes),
            supersegments: said(e.sizing.supersegments),
            step: Some(e.step),
            rank: Some(e.rank),
        }
    }
}

impl From<&StepEntry> for Expected {
    /// σ of a composed step is its ranks' sum, not the composed file's length: only the
    /// supersegments (the composed VDI's, once composed) and the step are checked.
    fn from(st: &StepEntry) -> Self {
        Self {
            bytes: None,
            supersegments: (st.vdi.is_some() && st.sizing.supersegments > 0)
                .then_some(st.sizing.supersegments),
            step: Some(st.step),
            rank: None,
        }
    }
}

/// Reads and decodes the VDI file `name` of the recording in `dir`, checked against what its
/// row says (`expected`).
///
/// # Errors
/// [`LoadError`] naming the file; [`LoadError::Mismatch`] when it disagrees with its row.
pub fn read_vdi(dir: &Path, name: &str, expected: Expected) -> Result<Vdi, LoadError> {
    let path = dir.join(name);
    let bytes = std::fs::read(&path).map_err(|source| LoadError::Read {
        path: path.clone(),
        source,
    })?;
    let (vdi, provenance) = codec::decode_with_provenance(&bytes, &DecodeLimits::default())
        .map_err(|source| LoadError::Decode {
            path: path.clone(),
            source,
        })?;
    if let Some(p) = provenance {
        let other_step = expected.step.is_some_and(|s| s != p.step);
        let other_rank = expected.rank.is_some_and(|r| r != p.rank);
        if other_step || other_rank {
            return Err(LoadError::NotItsRow {
                path,
                found: (p.step, p.rank),
                row: (expected.step.unwrap_or(p.step), expected.rank),
            });
        }
    }
    let found = (bytes.len() as u64, vdi.supersegments().len() as u64);
    let differs = |want: Option<u64>, got: u64| want.is_some_and(|w| w != got);
    if differs(expected.bytes, found.0) || differs(expected.supersegments, found.1) {
        return Err(LoadError::Mismatch {
            path,
            found,
            row: (
                expected.bytes.unwrap_or(found.0),
                expected.supersegments.unwrap_or(found.1),
            ),
        });
    }
    Ok(vdi)
}

/// Values decoded from files, by file name, taken once, within `budget_bytes`.
///
/// A few values at a time (the budget over a VDI's size), so a list searched by name serves.
pub struct Cache<T> {
    budget_bytes: u64,
    /// `(name, value, bytes)`, oldest first.
    held: Mutex<VecDeque<(String, Arc<T>, u64)>>,
}

impl<T> Cache<T> {
    /// An empty cache holding at most `budget_bytes` (0: none).
    pub fn new(budget_bytes: u64) -> Self {
        Self {
            budget_bytes,
            held: Mutex::new(VecDeque::new()),
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, VecDeque<(String, Arc<T>, u64)>> {
        self.held.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Keeps `value` (`bytes` of memory) as the content of file `name`, dropping the oldest
    /// values until it fits; a value larger than the whole budget is not kept.
    pub fn put(&self, name: &str, value: Arc<T>, bytes: u64) {
        if bytes > self.budget_bytes {
            return;
        }
        let mut held = self.lock();
        held.retain(|(n, _, _)| n != name);
        while held.iter().map(|(_, _, b)| b).sum::<u64>() + bytes > self.budget_bytes {
            held.pop_front();
        }
        held.push_back((name.to_owned(), value, bytes));
    }

    /// The value kept for `name`, removed from the cache.
    pub fn take(&self, name: &str) -> Option<Arc<T>> {
        let mut held = self.lock();
        let at = held.iter().position(|(n, _, _)| n == name)?;
        held.remove(at).map(|(_, value, _)| value)
    }

    /// Bytes held now.
    pub fn held_bytes(&self) -> u64 {
        self.lock().iter().map(|(_, _, b)| b).sum()
    }
}

/// The decoded VDIs and reference frames of ranks awaiting scoring or composition.
pub struct Kept {
    /// Decoded VDIs, by file name.
    pub vdis: Cache<Vdi>,
    /// Parsed reference frames, by file name.
    pub references: Cache<References>,
    /// Files taken as kept.
    reused: AtomicU64,
    /// Files read and decoded from disk again.
    again: AtomicU64,
}

impl Kept {
    /// Empty, each kind holding at most `budget_bytes` (0: nothing is kept, every read
    /// decodes from disk).
    pub fn new(budget_bytes: u64) -> Self {
        Self {
            vdis: Cache::new(budget_bytes),
            references: Cache::new(budget_bytes),
            reused: AtomicU64::new(0),
            again: AtomicU64::new(0),
        }
    }

    /// Files (VDIs and frame sets) taken as kept, and those read from disk again, so far.
    pub fn counts(&self) -> (u64, u64) {
        (
            self.reused.load(Ordering::Relaxed),
            self.again.load(Ordering::Relaxed),
        )
    }

    fn count<T>(&self, kept: Option<Arc<T>>) -> Option<Arc<T>> {
        let counter = if kept.is_some() {
            &self.reused
        } else {
            &self.again
        };
        counter.fetch_add(1, Ordering::Relaxed);
        kept
    }

    /// Keeps a rank's just-stored VDI file `name`, decoded.
    pub fn keep_vdi(&self, name: &str, vdi: Vdi) {
        let bytes = vdi.memory_bytes() as u64;
        self.vdis.put(name, Arc::new(vdi), bytes);
    }

    /// Keeps a rank's just-stored reference frames file `name`, parsed.
    pub fn keep_references(&self, name: &str, refs: References) {
        let bytes = refs.memory_bytes() as u64;
        self.references.put(name, Arc::new(refs), bytes);
    }

    /// The VDI file `name` of the recording in `dir`: as kept (and no longer kept), else
    /// read and decoded.
    ///
    /// # Errors
    /// [`LoadError`] naming the file.
    pub fn take_vdi(
        &self,
        dir: &Path,
        name: &str,
        expected: Expected,
    ) -> Result<Arc<Vdi>, LoadError> {
        match self.count(self.vdis.take(name)) {
            Some(vdi) => Ok(vdi),
            None => read_vdi(dir, name, expected).map(Arc::new),
        }
    }

    /// The reference frames file `name` of the recording in `dir`: as kept (and no longer
    /// kept), else read and parsed.
    ///
    /// # Errors
    /// [`StoreError`] naming the file.
    pub fn take_references(&self, dir: &Path, name: &str) -> Result<Arc<References>, StoreError> {
        match self.count(self.references.take(name)) {
            Some(refs) => Ok(refs),
            None => References::read(&dir.join(name)).map(Arc::new),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_value_is_taken_once_and_the_oldest_leave_first() {
        let cache = Cache::new(10);
        cache.put("a", Arc::new(1), 4);
        cache.put("b", Arc::new(2), 4);
        assert_eq!(cache.held_bytes(), 8);
        // "a" leaves to make room for "c".
        cache.put("c", Arc::new(3), 4);
        assert_eq!(cache.held_bytes(), 8);
        assert_eq!(cache.take("a"), None);
        assert_eq!(cache.take("b").as_deref(), Some(&2));
        assert_eq!(cache.take("b"), None, "taken once");
        assert_eq!(cache.held_bytes(), 4);
        // A taken name does not count; putting a name again replaces its value.
        cache.put("c", Arc::new(4), 6);
        assert_eq!(cache.held_bytes(), 6);
        assert_eq!(cache.take("c").as_deref(), Some(&4));
        assert_eq!(cache.held_bytes(), 0);
    }

    #[test]
    fn values_beyond_the_budget_are_not_kept() {
        let cache = Cache::new(10);
        cache.put("a", Arc::new(1), 3);
        cache.put("big", Arc::new(2), 11);
        assert_eq!(cache.take("big"), None);
        assert_eq!(cache.take("a").as_deref(), Some(&1), "and displace nothing");
        let none = Cache::new(0);
        none.put("a", Arc::new(1), 1);
        assert_eq!(none.take("a"), None);
        assert_eq!(none.held_bytes(), 0);
    }

    #[test]
    fn taken_values_leave_nothing_behind() {
        let cache = Cache::new(100);
        cache.put("kept", Arc::new(-1), 1);
        for k in 0..1000 {
            let name = format!("v{k}");
            cache.put(&name, Arc::new(k), 1);
            assert_eq!(cache.take(&name).as_deref(), Some(&k));
        }
        assert_eq!(cache.lock().len(), 1);
        assert_eq!(cache.take("kept").as_deref(), Some(&-1));
    }

    /// Two stored VDIs swapped on disk: each is refused as the other's step, naming the file
    /// and what it holds against what its row says; read as itself, each is accepted.
    #[test]
    fn a_vdi_that_disagrees_with_its_row_is_refused() {
        use insitu_core::{Camera, RaycastParams, Raycaster, TransferFunction, VdiParams, Volume};
        let dir = tempfile::tempdir().unwrap();
        let mut files = Vec::new();
        for (k, radius) in [(0, 5.0f32), (1, 9.0)] {
            let v = Volume::from_fn([16, 16, 16], |x, y, z| {
                let d = (x as f32 - 8.0).hypot(y as f32 - 8.0).hypot(z as f32 - 8.0);
                (radius - d).max(0.0)
            })
            .unwrap();
            let tf = TransferFunction::default_for_range(0.0, 9.0);
            let rc = Raycaster::new(&v, &tf, RaycastParams::default()).unwrap();
            let cam = Camera::default_for_box(&v.world_box());
            let params = VdiParams {
                resolution: 32,
                gamma: 0.01,
                precision: Default::default(),
            };
            let vdi = insitu_core::vdi::generate::generate(&rc, &cam, params, 0, "ramp").unwrap();
            let provenance = insitu_core::vdi::provenance::Provenance {
                step: k,
                rank: 0,
                world_size: 1,
                pm_version: 0,
                sim_time: 0.0,
                placement: None,
                covers: Vec::new(),
                scene_version: 0,
            };
            let bytes =
                codec::encode_with_provenance(&vdi, codec::Codec::None, Some(&provenance)).unwrap();
            let name = format!("v{k}.vdi");
            std::fs::write(dir.path().join(&name), &bytes).unwrap();
            let row = Expected {
                bytes: Some(bytes.len() as u64),
                supersegments: Some(vdi.supersegments().len() as u64),
                step: Some(k),
                rank: Some(0),
            };
            files.push((name, row));
        }
        for (name, row) in &files {
            assert!(read_vdi(dir.path(), name, *row).is_ok());
        }
        let (a, b) = (&files[0], &files[1]);
        assert_ne!(
            a.1, b.1,
            "the two VDIs must differ for the test to mean anything"
        );
        let sizes_of_b = Expected {
            step: a.1.step,
            ..b.1
        };
        let e = read_vdi(dir.path(), &a.0, sizes_of_b).unwrap_err();
        assert!(matches!(e, LoadError::Mismatch { .. }), "{e}");
        let text = e.to_string();
        assert!(
            text.contains("v0.vdi") && text.contains("index row says"),
            "{text}"
        );
        // Same size and count, but the file says it is another step's (a swap of two files
        // that happen to agree in size): refused by its provenance.
        let other_step = Expected {
            step: Some(1),
            ..a.1
        };
        let e = read_vdi(dir.path(), &a.0, other_step).unwrap_err();
        assert!(matches!(e, LoadError::NotItsRow { .. }), "{e}");
        assert!(
            e.to_string().contains("step 0 rank 0")
                && e.to_string().contains("row is step 1 rank 0"),
            "{e}"
        );
        // A row that says nothing checks nothing.
        assert!(read_vdi(dir.path(), &a.0, Expected::default()).is_ok());
    }

    #[test]
    fn a_value_not_kept_is_read_from_the_recording() {
        let dir = tempfile::tempdir().unwrap();
        let kept = Kept::new(1 << 20);
        let missing = kept
            .take_vdi(dir.path(), "no-such.vdi", Expected::default())
            .unwrap_err();
        assert!(matches!(missing, LoadError::Read { .. }), "{missing}");
        assert!(missing.to_string().contains("no-such.vdi"), "{missing}");
        std::fs::write(dir.path().join("bad.vdi"), b"not a VDI").unwrap();
        let bad = kept
            .take_vdi(dir.path(), "bad.vdi", Expected::default())
            .unwrap_err();
        assert!(matches!(bad, LoadError::Decode { .. }), "{bad}");
        assert!(bad.to_string().contains("bad.vdi"), "{bad}");
        assert_eq!(kept.counts(), (0, 2));
    }

    #[test]
    fn a_kept_vdi_is_taken_without_its_file_once() {
        use insitu_core::raycast::{RaycastParams, Raycaster};
        use insitu_core::vdi::{generate::generate, VdiParams};
        use insitu_core::{Camera, TransferFunction, Volume};
        let volume = Volume::from_fn([8, 8, 8], |x, y, z| ((x + y + z) % 5) as f32).unwrap();
        let tf = TransferFunction::default_for_range(0.0, 4.0);
        let rc = Raycaster::new(&volume, &tf, RaycastParams::default()).unwrap();
        let camera = Camera::default_for_box(&volume.world_box());
        let params = VdiParams {
            resolution: 16,
            gamma: 0.01,
            precision: Default::default(),
        };
        let vdi = generate(&rc, &camera, params, 0, "").unwrap();
        let dir = tempfile::tempdir().unwrap();
        let kept = Kept::new(1 << 20);
        kept.keep_vdi("s0.vdi", vdi.clone());
        assert_eq!(kept.vdis.held_bytes(), vdi.memory_bytes() as u64);
        // No file: the kept VDI is the one returned, once; then the disk is asked.
        assert_eq!(
            *kept
                .take_vdi(dir.path(), "s0.vdi", Expected::default())
                .unwrap(),
            vdi
        );
        assert!(kept
            .take_vdi(dir.path(), "s0.vdi", Expected::default())
            .is_err());
        assert_eq!(kept.counts(), (1, 1));
        assert_eq!(kept.vdis.held_bytes(), 0);
    }
}
