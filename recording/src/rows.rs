//! What the recording's index holds, and how the recording fails: a row per step and rank
//! ([`Entry`]), a row per composed step ([`StepEntry`]), and [`StoreError`]. The index
//! ([`crate::index`]) reads and writes these rows; the recording ([`crate::store`]) keeps the
//! files they name.

use insitu_core::evaluate::Sizing;
use insitu_core::metrics::Db;
use insitu_core::vdi::codec::Codec;
use insitu_core::vdi::Precision;
use insitu_core::volume::bricks::Brick;
use serde::{Deserialize, Serialize};
use std::path::PathBuf;

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
    /// The same step and rank was stored before with different bytes.
    #[error("step {step} rank {rank}: {what} already stored with different content")]
    AlreadyExists {
        /// The step.
        step: u64,
        /// The rank.
        rank: u32,
        /// `VDI` or `reference frames`.
        what: &'static str,
    },
}

impl StoreError {
    /// Whether the storage refused the write for a reason an operator can fix and that
    /// retrying outlasts: no space or quota left, a read-only file system (a remount), access
    /// denied, or an I/O error of the device (EIO, SQLite's I/O failure). The item is then
    /// kept by its sender and retried, not counted as failed.
    pub fn is_storage_fault(&self) -> bool {
        use std::io::ErrorKind::*;
        let StoreError::Io { source, .. } = self else {
            return false;
        };
        matches!(
            source.kind(),
            StorageFull | QuotaExceeded | ReadOnlyFilesystem | PermissionDenied
        ) || source.raw_os_error() == Some(EIO)
    }
}

/// EIO, the device's I/O error (5 on Linux and the BSDs).
pub const EIO: i32 = 5;

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
    /// The precision the VDI file holds its supersegments at, `P_M`'s third parameter (read
    /// from the file; absent in entries recorded before: 32-bit floats).
    #[serde(default)]
    pub precision: Precision,
    /// The codec of the VDI file (`None`: the generator-node did not say; `""` in the JSON).
    #[serde(with = "codec_name")]
    pub codec: Option<Codec>,
    /// σ, τ (and its source) and the supersegments, as the generator-node reported them
    /// (flattened: their keys sit in the entry's JSON).
    #[serde(flatten)]
    pub sizing: Sizing,
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
    /// A host's part: the ranks its generator-node composed into this VDI (ascending, `rank`
    /// first; the placement is their box). Empty: `rank` alone.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub covers: Vec<u32>,
    /// The steered scene version the VDI was made with (docs/steering.md; 0: the configured
    /// scene).
    #[serde(default)]
    pub scene_version: u64,
}

impl Entry {
    /// The ranks this entry's VDI holds: [`Self::covers`], or `rank` alone.
    pub fn ranks(&self) -> Vec<u32> {
        if self.covers.is_empty() {
            vec![self.rank]
        } else {
            self.covers.clone()
        }
    }

    /// Whether this entry's VDI holds `rank`.
    pub fn holds(&self, rank: u32) -> bool {
        if self.covers.is_empty() {
            self.rank == rank
        } else {
            self.covers.binary_search(&rank).is_ok()
        }
    }
}

/// A rank's brick in the whole grid, voxels (docs/conventions.md, "A world of ranks").
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
    /// The ranks' [`Sizing::of_ranks`]: σ summed over their files, τ the slowest rank's; the
    /// supersegments the composed VDI's once it is composed, the ranks' sum before
    /// (flattened, as in [`Entry`]; a step stored before the compression time was kept reads
    /// it as 0).
    #[serde(flatten)]
    pub sizing: Sizing,
    /// `r`, `γ` and the P_M version of the ranks.
    pub resolution: u32,
    /// `γ`.
    pub gamma: f32,
    /// P_M version.
    pub pm_version: u64,
    /// The steered scene version of the ranks.
    #[serde(default)]
    pub scene_version: u64,
    /// Codec of the ranks' files (the composed file uses it too; as in [`Entry`]).
    #[serde(with = "codec_name")]
    pub codec: Option<Codec>,
    /// q of the composed VDI against the composed references.
    pub quality: Option<Quality>,
    /// Why it could not be composed.
    pub error: Option<String>,
    /// Seconds this viz-node spent composing: the parts' VDIs merged, the result encoded and
    /// written, their frames composited (scoring not included; a measurement, like τ: 0 when
    /// not composed, or composed before it was kept).
    #[serde(default)]
    pub compose_secs: f64,
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
            precision: Precision::Float32,
            codec: None,
            sizing: Sizing::default(),
            tf_name: String::new(),
            tf_hash: 0,
            quality: None,
            pm_version: 0,
            placement: None,
            with_references: false,
            covers: Vec::new(),
            scene_version: 0,
        }
    }
}

/// An entry's codec in JSON: its name, `""` for none (as the index held it when it was a
/// string); an unknown name is an error that names it.
mod codec_name {
    use insitu_core::vdi::codec::Codec;
    use serde::{Deserialize, Deserializer, Serializer};

    pub fn serialize<S: Serializer>(codec: &Option<Codec>, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(codec.map_or("", Codec::name))
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Option<Codec>, D::Error> {
        let name = String::deserialize(d)?;
        match name.as_str() {
            "" => Ok(None),
            name => name.parse().map(Some).map_err(serde::de::Error::custom),
        }
    }
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

/// Keeps `name` where it is `own` (the file the row's step and rank name), else drops it into
/// `dropped`: a row never makes the recording read a file by another name (an absolute path, a
/// `../` path, another step's file).
fn confine(name: &mut Option<String>, own: String, dropped: &mut Vec<String>) {
    if name.as_ref().is_some_and(|n| *n != own) {
        dropped.extend(name.take());
    }
}

impl Entry {
    /// Drops the file names of this row that are not its step's and rank's own
    /// ([`vdi_name`], [`refs_name`]); returns them (for a warning). The step then reads as
    /// having no such file.
    pub fn confine_names(&mut self) -> Vec<String> {
        let mut dropped = Vec::new();
        confine(&mut self.vdi, vdi_name(self.step, self.rank), &mut dropped);
        let own = refs_name(self.step, self.rank);
        confine(&mut self.references, own, &mut dropped);
        dropped
    }
}

impl StepEntry {
    /// A step's entry from its ranks: their [`Sizing::of_ranks`] (σ and supersegments summed, τ of
    /// the slowest), `P_M` and codec of the first; nothing composed yet (no files, no q, no error).
    pub fn of_ranks(step: u64, world_size: u32, ranks: &[&Entry], missing: Vec<u32>) -> Self {
        let first = ranks.first();
        Self {
            step,
            world_size,
            ranks: {
                let mut all: Vec<u32> = ranks.iter().flat_map(|e| e.ranks()).collect();
                all.sort_unstable();
                all
            },
            missing,
            vdi: None,
            references: None,
            sizing: Sizing::of_ranks(ranks.iter().map(|e| &e.sizing)),
            resolution: first.map_or(0, |e| e.resolution),
            gamma: first.map_or(0.0, |e| e.gamma),
            pm_version: first.map_or(0, |e| e.pm_version),
            scene_version: first.map_or(0, |e| e.scene_version),
            codec: first.and_then(|e| e.codec),
            quality: None,
            error: None,
            compose_secs: 0.0,
        }
    }

    /// As [`Entry::confine_names`], for a composed step's files ([`composed_vdi_name`],
    /// [`composed_refs_name`]).
    pub fn confine_names(&mut self) -> Vec<String> {
        let mut dropped = Vec::new();
        confine(&mut self.vdi, composed_vdi_name(self.step), &mut dropped);
        let own = composed_refs_name(self.step);
        confine(&mut self.references, own, &mut dropped);
        dropped
    }
}
