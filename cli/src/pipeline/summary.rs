//! The summary at the end of a run: the nodes' counts, σ, τ and q, the tuner's work and the
//! budget's adherence, as text or as one JSON object.

use super::*;

/// What the summary is made of.
pub(super) struct Run<'a> {
    pub(super) pushed: u64,
    pub(super) elapsed_secs: f64,
    pub(super) status: &'a pb::GeneratorStatus,
    pub(super) seen: &'a Seen,
    pub(super) tuner: Option<&'a pb::TunerStatus>,
    pub(super) recording: &'a Path,
}

/// The generator-node's counts at the end of a run, for the JSON summaries.
pub fn counts_json(
    pushed: u64,
    s: &pb::GeneratorStatus,
) -> serde_json::Map<String, serde_json::Value> {
    let v = serde_json::json!({
        "pushed": pushed,
        "received": s.steps_received,
        "generated": s.steps_generated,
        "stored": s.steps_shipped,
        "dropped_queue": s.dropped_queue,
        "dropped_outbox": s.dropped_outbox,
        "failed": s.failed,
        "final_pm_version": s.pm_version,
        "limit_retries": s.limit_retries,
        "limit_retry_secs": s.limit_retry_secs,
    });
    v.as_object().cloned().unwrap_or_default()
}

/// Means and ranges over the stored VDIs' reports.
struct Totals {
    mean_sigma_bytes: f64,
    mean_tau_secs: f64,
    /// Sampled steps and their lowest and highest q.
    q: Option<(usize, f64, f64)>,
}

impl Totals {
    fn of(all: &[pb::QualityReport]) -> Self {
        // σ and τ per stored VDI; q where it was scored (composed steps carry it for ranks).
        let reports: Vec<&pb::QualityReport> = all.iter().filter(|r| !r.composed).collect();
        let n = reports.len().max(1) as f64;
        let q: Vec<f64> = all.iter().filter_map(|r| r.q_db).collect();
        Self {
            mean_sigma_bytes: reports.iter().map(|r| r.sigma_bytes as f64).sum::<f64>() / n,
            mean_tau_secs: reports.iter().map(|r| r.tau_secs).sum::<f64>() / n,
            q: (!q.is_empty()).then(|| {
                (
                    q.len(),
                    q.iter().copied().fold(f64::INFINITY, f64::min),
                    q.iter().copied().fold(f64::NEG_INFINITY, f64::max),
                )
            }),
        }
    }
}

/// The decisions among `decisions` that change r, γ or the precision: a re-tuning that keeps the
/// `P_M` in force is a new version (the corrections after it use its measurements) but no
/// change a viewer sees.
fn changes_of_pm(decisions: &[pb::PmDecision]) -> usize {
    decisions
        .iter()
        .filter(|d| {
            (d.resolution, d.gamma.to_bits(), d.precision_bits)
                != (
                    d.old_resolution,
                    d.old_gamma.to_bits(),
                    d.old_precision_bits,
                )
        })
        .count()
}

impl Run<'_> {
    pub(super) fn json(&self, generator: &str) -> serde_json::Value {
        let reports = &self.seen.reports;
        let t = Totals::of(reports);
        let composed = reports.iter().filter(|r| r.composed).count();
        let mut out = counts_json(self.pushed, self.status);
        out.extend(
            serde_json::json!({
                "vdis": reports.len() - composed,
                "composed_steps": composed,
                "mean_sigma_bytes": t.mean_sigma_bytes,
                "mean_tau_s": t.mean_tau_secs,
                "q_db_min": t.q.map(|q| crate::cmd::q_json(q.1)),
                "q_db_max": t.q.map(|q| crate::cmd::q_json(q.2)),
                "decisions_seen": self.seen.decisions.len(),
                "pm_changes": changes_of_pm(&self.seen.decisions),
                "tuner": self.tuner.map(|t| {
                    let (sigma, tau) = adherence(&budgets_of(t), reports);
                    serde_json::json!({
                    "utility": t.utility_description,
                    "sigma_adherence": sigma.as_ref().map(Adherence::json),
                    "tau_adherence": tau.as_ref().map(Adherence::json),
                    "corrections": t.corrections,
                    "provisional_decisions": t.provisional_decisions,
                    "tunings_superseded": t.tunings_superseded,
                    "characteristic_steps": t.characteristic_steps,
                    "trials_run": t.trials_run,
                    "size_probes": t.size_probes,
                    "trials_reused": t.trials_reused,
                    "trials_failed": t.trials_failed,
                    "trial_secs": t.trial_secs,
                    "retunes": t.retunes,
                    "decisions": t.decisions,
                    "tunings_infeasible": t.tunings_infeasible,
                    "tuning_at_end": t.tuning,
                })}),
                "wall_s": self.elapsed_secs,
                "recording": self.recording.display().to_string(),
                "generator": generator,
            })
            .as_object()
            .cloned()
            .unwrap_or_default(),
        );
        serde_json::Value::Object(out)
    }

    pub(super) fn print(&self) {
        let (s, reports) = (self.status, &self.seen.reports);
        let t = Totals::of(reports);
        println!("summary:");
        println!(
            "  steps pushed {}, received {}, generated {}, stored {}, dropped {} (queue {}, outbox {}), failed {}",
            self.pushed,
            s.steps_received,
            s.steps_generated,
            s.steps_shipped,
            s.dropped_queue + s.dropped_outbox,
            s.dropped_queue,
            s.dropped_outbox,
            s.failed
        );
        let composed = reports.iter().filter(|r| r.composed).count();
        println!(
            "  mean σ {:.1} kB, mean τ {:.3} s over {} VDIs{}",
            t.mean_sigma_bytes / 1e3,
            t.mean_tau_secs,
            reports.len() - composed,
            if composed > 0 {
                format!(" ({composed} steps composed over ranks)")
            } else {
                String::new()
            }
        );
        if let Some((n, lo, hi)) = t.q {
            println!(
                "  q on {n} sampled steps: {} – {} dB",
                crate::cmd::q_text(lo),
                crate::cmd::q_text(hi)
            );
        }
        if s.limit_retries > 0 {
            println!(
                "  hard limit and guard: {} generation(s) made again at a coarser P_M, {:.3} s of generation thrown away (steps that could not keep a hard limit are counted as failed)",
                s.limit_retries, s.limit_retry_secs
            );
        }
        println!("  wall clock {:.1} s", self.elapsed_secs);
        println!("  recording: {}", self.recording.display());
        if let Some(t) = self.tuner {
            println!(
                "  tuner ({}): {} decision(s), {} changing P_M, characteristic steps {:?}, {} trials of which {} size probes ({:.1} s on the nodes), {} answered from earlier trials, {} failed",
                t.utility_description,
                self.seen.decisions.len(),
                changes_of_pm(&self.seen.decisions),
                t.characteristic_steps,
                t.trials_run,
                t.size_probes,
                t.trial_secs,
                t.trials_reused,
                t.trials_failed
            );
            if t.corrections > 0 || t.tunings_superseded > 0 {
                println!(
                    "  of the decisions, {} correction(s) between tunings from the production steps; {} tuning(s) cut short for a newer characteristic step",
                    t.corrections, t.tunings_superseded
                );
            }
            if !reports.is_empty() && reports.iter().all(|r| r.pm_version == 0) {
                println!(
                    "  no stored step was made with a tuned P_M: a decision applies from the first step no node had begun when it was made (docs/tuning.md, \"When a decision applies\"), so a run needs steps after the first tuning; push more steps, or fewer between tunings"
                );
            }
            let (sigma, tau) = adherence(&budgets_of(t), reports);
            for (what, a) in [("σ", sigma), ("τ", tau)] {
                if let Some(a) = a.filter(|a| a.steps > 0) {
                    println!(
                        "  {what} budget, steps made with a tuned P_M: {}",
                        a.describe()
                    );
                }
            }
            if t.tunings_infeasible > 0 {
                println!(
                    "  {} tuning(s) found no candidate within the budget on every characteristic step; the P_M in force stayed",
                    t.tunings_infeasible
                );
            }
            if t.tuning {
                println!(
                    "  a tuning was under way when the run ended: it made no decision; its trials are kept in {}",
                    self.recording.join("tuner-state").display()
                );
            }
        }
    }
}
