//! One row of a study: the performance indicators (σ, q, τ) of one `P_M` (Sec. 5.3).

use crate::grid::Candidate;
use insitu_core::evaluate::{mean_ssim, Evaluation};
use insitu_core::metrics::Db;
use serde::{Deserialize, Serialize};

/// σ, q, τ and details of one candidate.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Measurement {
    /// `r`.
    pub r: u32,
    /// `γ`.
    pub gamma: f32,
    /// σ: compressed VDI bytes.
    pub sigma_bytes: u64,
    /// Supersegments in the VDI.
    pub supersegments: u64,
    /// τ: generation wall clock, seconds.
    pub tau_secs: f64,
    /// Compression wall clock, seconds.
    pub tau_compress_secs: f64,
    /// Mean render time of the VDI per test view, seconds.
    pub tau_render_secs: f64,
    /// q: pooled PSNR over the test views, dB (`"inf"` in JSON when identical).
    pub q_db: Db,
    /// PSNR per test view, dB.
    pub view_q_db: Vec<Db>,
    /// Mean SSIM over the views (none for images under 11×11).
    pub ssim: Option<f64>,
}

impl Measurement {
    /// The candidate measured.
    pub fn candidate(&self) -> Candidate {
        Candidate {
            r: self.r,
            gamma: self.gamma,
        }
    }

    /// q in dB.
    pub fn q(&self) -> f64 {
        self.q_db.0
    }

    /// From a core evaluation.
    pub fn from_evaluation(e: &Evaluation) -> Self {
        Self {
            r: e.params.resolution,
            gamma: e.params.gamma,
            sigma_bytes: e.sizing.sigma_bytes,
            supersegments: e.sizing.supersegments,
            tau_secs: e.sizing.tau_secs,
            tau_compress_secs: e.sizing.tau_compress_secs,
            tau_render_secs: e.tau_render_secs,
            q_db: Db(e.q_db),
            view_q_db: e.views.iter().map(|v| Db(v.q_db)).collect(),
            ssim: mean_ssim(&e.views),
        }
    }
}
