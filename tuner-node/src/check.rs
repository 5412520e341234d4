//! What a node may send: its step summaries and trial results are checked here before they
//! reach the engine, the search or the persisted state. A number that is not finite where the
//! state needs one would not even survive a restart (JSON has no NaN), and a result for a
//! candidate or step other than the one asked would be filed under the wrong one.

use insitu_proto::pb;
use insitu_tuner::series::BINS;

/// Checks a summary: 64 bins, a finite range with lo < hi, 1 ≤ world_size, rank < world_size,
/// and a finite, non-negative τ.
///
/// # Errors
/// A message naming the field and the step.
pub fn check_summary(s: &pb::StepSummary) -> Result<(), String> {
    let what = format!("summary of step {} rank {}", s.step, s.rank);
    if s.histogram.len() != BINS {
        return Err(format!(
            "{what}: the histogram has {} bins, not {BINS}",
            s.histogram.len()
        ));
    }
    if !(s.range_lo.is_finite() && s.range_hi.is_finite() && s.range_lo < s.range_hi) {
        return Err(format!(
            "{what}: histogram range [{}, {}] must be finite with lo < hi",
            s.range_lo, s.range_hi
        ));
    }
    if s.world_size == 0 || s.rank >= s.world_size {
        return Err(format!(
            "{what}: need 0 ≤ rank < world_size (world_size {})",
            s.world_size
        ));
    }
    if let Err(e) = insitu_core::Precision::from_bits(s.precision_bits) {
        return Err(format!("{what}: precision_bits: {e}"));
    }
    seconds(&what, "tau_secs", s.tau_secs)
}

/// Checks a rank's successful result of the trial `asked`: the step, `r` and `γ` asked; σ > 0;
/// every time finite and non-negative; per view an MSE that is finite and non-negative and a q
/// that is not NaN (`+∞` for identical images); an SSIM in [−1, 1].
///
/// # Errors
/// A message naming the field and the trial.
pub fn check_trial_result(r: &pb::TrialResult, asked: &pb::TrialRequest) -> Result<(), String> {
    let what = format!("trial {} (step {} rank {})", r.trial_id, r.step, r.rank);
    if (r.step, r.resolution, r.gamma.to_bits())
        != (asked.step, asked.resolution, asked.gamma.to_bits())
    {
        return Err(format!(
            "{what}: answers step {} r {} γ {}, but step {} r {} γ {} was asked",
            r.step, r.resolution, r.gamma, asked.step, asked.resolution, asked.gamma
        ));
    }
    if r.sigma_bytes == 0 {
        return Err(format!(
            "{what}: sigma_bytes is 0 (a VDI file has a header)"
        ));
    }
    for (field, v) in [
        ("tau_secs", r.tau_secs),
        ("tau_compress_secs", r.tau_compress_secs),
        ("tau_render_secs", r.tau_render_secs),
        ("trial_secs", r.trial_secs),
        ("reference_secs", r.reference_secs),
        ("trial_cpu_secs", r.trial_cpu_secs),
    ] {
        seconds(&what, field, v)?;
    }
    if r.view_q_db.len() != r.view_mse.len() {
        return Err(format!(
            "{what}: {} view_q_db for {} view_mse",
            r.view_q_db.len(),
            r.view_mse.len()
        ));
    }
    if let Some(m) = r.view_mse.iter().find(|m| !(m.is_finite() && **m >= 0.0)) {
        return Err(format!(
            "{what}: view_mse {m} must be finite and non-negative"
        ));
    }
    if let Some(q) = r
        .view_q_db
        .iter()
        .find(|q| q.is_nan() || **q == f64::NEG_INFINITY)
    {
        return Err(format!("{what}: view_q_db {q} must be a number or +inf"));
    }
    if let Some(s) = r.ssim.filter(|s| !(-1.0..=1.0).contains(s)) {
        return Err(format!("{what}: ssim {s} must lie in [-1, 1]"));
    }
    Ok(())
}

/// `v` (seconds) as field `field` of `what`: finite and non-negative.
fn seconds(what: &str, field: &str, v: f64) -> Result<(), String> {
    if v.is_finite() && v >= 0.0 {
        Ok(())
    } else {
        Err(format!(
            "{what}: {field} {v} must be finite and non-negative"
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn summaries_are_checked_field_by_field() {
        let good = pb::StepSummary {
            step: 3,
            world_size: 1,
            histogram: vec![1; BINS],
            range_lo: 0.0,
            range_hi: 1.0,
            ..Default::default()
        };
        assert!(check_summary(&good).is_ok());
        let e = check_summary(&pb::StepSummary {
            histogram: vec![1; 63],
            ..good.clone()
        })
        .unwrap_err();
        assert!(e.contains("63 bins") && e.contains("step 3"), "{e}");
        for bad in [
            pb::StepSummary {
                range_hi: 0.0,
                ..good.clone()
            },
            pb::StepSummary {
                range_lo: f64::NAN,
                ..good.clone()
            },
            pb::StepSummary {
                world_size: 0,
                ..good.clone()
            },
            pb::StepSummary {
                rank: 1,
                ..good.clone()
            },
            pb::StepSummary {
                tau_secs: f64::NAN,
                ..good.clone()
            },
        ] {
            assert!(check_summary(&bad).is_err(), "{bad:?}");
        }
    }

    #[test]
    fn trial_results_are_checked_field_by_field() {
        let asked = pb::TrialRequest {
            precision_bits: None,
            trial_id: 9,
            step: 4,
            resolution: 64,
            gamma: 0.01,
            size_only: false,
            reuse_probe: false,
        };
        let good = pb::TrialResult {
            trial_id: 9,
            step: 4,
            resolution: 64,
            gamma: 0.01,
            sigma_bytes: 1000,
            tau_secs: 0.01,
            view_mse: vec![1e-4, 0.0],
            view_q_db: vec![40.0, f64::INFINITY],
            ssim: Some(0.99),
            ..Default::default()
        };
        assert_eq!(check_trial_result(&good, &asked), Ok(()));
        let bad = |f: fn(&mut pb::TrialResult), needle: &str| {
            let mut r = good.clone();
            f(&mut r);
            let e = check_trial_result(&r, &asked).unwrap_err();
            assert!(e.contains(needle) && e.contains("trial 9"), "{needle}: {e}");
        };
        bad(|r| r.gamma = 0.02, "0.01 was asked");
        bad(|r| r.step = 5, "step 4 r 64");
        bad(|r| r.resolution = 128, "r 64");
        bad(|r| r.sigma_bytes = 0, "sigma_bytes");
        bad(|r| r.tau_secs = f64::NAN, "tau_secs NaN");
        bad(|r| r.trial_secs = -1.0, "trial_secs");
        bad(|r| r.trial_cpu_secs = f64::NAN, "trial_cpu_secs");
        bad(|r| r.tau_render_secs = f64::INFINITY, "tau_render_secs");
        bad(|r| r.view_mse[1] = f64::NAN, "view_mse NaN");
        bad(|r| r.view_mse[0] = -1.0, "view_mse -1");
        bad(|r| r.view_q_db[0] = f64::NAN, "view_q_db NaN");
        bad(
            |r| r.view_q_db.pop().map_or((), drop),
            "1 view_q_db for 2 view_mse",
        );
        bad(|r| r.ssim = Some(f64::NAN), "ssim");
        bad(|r| r.ssim = Some(1.5), "ssim 1.5");
    }
}
