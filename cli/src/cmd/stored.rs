//! A recording's steps as the exports render them: each step's VDI (composed over its ranks,
//! or its one rank) with the tuned parameters and metrics its rows hold.

use anyhow::{Context, Result};
use insitu_core::vdi::Vdi;
use insitu_viz_node::view::{self, VdiFile};
use std::path::{Path, PathBuf};

/// One stored step.
pub struct StoredStep {
    /// Step index.
    pub step: u64,
    /// Simulation time.
    pub sim_time: f64,
    /// The `P_M` version it was made with.
    pub pm_version: u64,
    /// `r`.
    pub r: u32,
    /// `γ`.
    pub gamma: f32,
    /// σ, bytes (summed over ranks).
    pub sigma_bytes: u64,
    /// τ, seconds (the slowest rank's).
    pub tau_s: f64,
    /// q, dB, when the step was scored.
    pub q_db: Option<f64>,
    file: VdiFile,
}

/// The recording in `dir`: its steps in order, and the steps left out (not composed yet,
/// or no VDI yet), each with why.
pub struct Stored {
    dir: PathBuf,
    /// The steps that render.
    pub steps: Vec<StoredStep>,
    /// Steps that do not, and why.
    pub left_out: Vec<String>,
}

impl Stored {
    /// Reads the index of the recording in `dir` (read-only; a viz-node may be writing it).
    ///
    /// # Errors
    /// When `dir` is not a readable recording.
    pub fn read(dir: &Path) -> Result<Self> {
        let (entries, composed) = insitu_recording::index::read(dir)
            .with_context(|| format!("{} is not a readable recording", dir.display()))?;
        let mut numbers: Vec<u64> = entries.iter().map(|e| e.step).collect();
        numbers.sort_unstable();
        numbers.dedup();
        let (mut steps, mut left_out) = (Vec::new(), Vec::new());
        for step in numbers {
            let ranks: Vec<_> = entries.iter().filter(|e| e.step == step).cloned().collect();
            let whole = composed.iter().find(|c| c.step == step);
            let file = match view::vdi_file(step, None, &ranks, whole) {
                Ok(f) => f,
                Err(e) => {
                    left_out.push(e.to_string());
                    continue;
                }
            };
            let first = &ranks[0];
            let (sizing, quality, pm_version, r, gamma) = match (view::world_size(&ranks), whole) {
                (w, Some(c)) if w > 1 => {
                    (&c.sizing, &c.quality, c.pm_version, c.resolution, c.gamma)
                }
                _ => (
                    &first.sizing,
                    &first.quality,
                    first.pm_version,
                    first.resolution,
                    first.gamma,
                ),
            };
            steps.push(StoredStep {
                step,
                sim_time: first.sim_time,
                pm_version,
                r,
                gamma,
                sigma_bytes: sizing.sigma_bytes,
                tau_s: sizing.tau_secs,
                q_db: quality.as_ref().map(|q| q.q_db.0).filter(|q| q.is_finite()),
                file,
            });
        }
        Ok(Self {
            dir: dir.to_owned(),
            steps,
            left_out,
        })
    }

    /// The VDI of `s`, checked against its row.
    ///
    /// # Errors
    /// When the file cannot be read or is not the VDI its row describes.
    pub fn vdi(&self, s: &StoredStep) -> Result<Vdi> {
        Ok(view::load_vdi(&self.dir, &s.file)?)
    }
}
