//! One row of a study: the performance indicators (σ, q, τ) of one `P_M` (Sec. 5.3).

use crate::grid::Candidate;
use insitu_core::evaluate::{mean_ssim, Evaluation, Sizing};
use insitu_core::metrics::Db;
use insitu_core::vdi::Precision;
use serde::{Deserialize, Serialize};

/// σ, q, τ and details of one candidate.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Measurement {
    /// `r`.
    pub r: u32,
    /// `γ`.
    pub gamma: f32,
    /// The precision the file was written at (absent in records made before precision was a
    /// parameter: 32-bit floats).
    #[serde(default)]
    pub precision: Precision,
    /// σ, τ and the supersegments (flattened: their keys sit beside `r` and `gamma`).
    #[serde(flatten)]
    pub sizing: Sizing,
    /// Mean render time of the VDI per test view, seconds.
    pub tau_render_secs: f64,
    /// q: pooled PSNR over the test views, dB (`"inf"` in JSON when identical).
    pub q_db: Db,
    /// PSNR per test view, dB.
    pub view_q_db: Vec<Db>,
    /// Mean SSIM over the views (none for images under 11×11).
    pub ssim: Option<f64>,
    /// σ of the same VDI as 32-bit floats under bzip2, the paper's σ (Sec. 5.3), where an
    /// offline study measured it beside a file of another precision or codec.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sigma_paper_bytes: Option<u64>,
}

impl Measurement {
    /// The candidate measured.
    pub fn candidate(&self) -> Candidate {
        Candidate {
            r: self.r,
            gamma: self.gamma,
            precision: self.precision,
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
            precision: e.params.precision,
            sizing: e.sizing,
            tau_render_secs: e.tau_render_secs,
            q_db: Db(e.q_db),
            view_q_db: e.views.iter().map(|v| Db(v.q_db)).collect(),
            ssim: mean_ssim(&e.views),
            sigma_paper_bytes: None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use insitu_core::backend::TimeSource;

    /// The σ/τ keys stay at the top level of a measurement's JSON (cache files written before
    /// [`Sizing`] was shared still read, without a τ source: wall clock).
    #[test]
    fn sizing_keys_sit_beside_the_candidate_in_json() {
        let old = r#"{"r": 128, "gamma": 0.01, "sigma_bytes": 5000, "supersegments": 77,
            "tau_secs": 0.3, "tau_compress_secs": 0.02, "tau_render_secs": 0.1,
            "q_db": 41.5, "view_q_db": [41.5], "ssim": null}"#;
        let m: Measurement = serde_json::from_str(old).unwrap();
        assert_eq!(
            m.sizing,
            Sizing {
                sigma_bytes: 5000,
                supersegments: 77,
                tau_secs: 0.3,
                tau_source: TimeSource::WallClock,
                tau_compress_secs: 0.02,
            }
        );
        let json = serde_json::to_value(&m).unwrap();
        for key in [
            "sigma_bytes",
            "supersegments",
            "tau_secs",
            "tau_compress_secs",
            "tau_source",
        ] {
            assert!(json.get(key).is_some(), "{key} missing from {json}");
        }
        assert!(json.get("sizing").is_none());
        assert_eq!(serde_json::from_value::<Measurement>(json).unwrap(), m);
    }
}
