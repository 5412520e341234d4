//! The lines a run prints as it goes: one per stored VDI (the viz-node's quality report) and one
//! per decision of the tuner, as text or as JSON objects.

use super::*;

/// A P_M change as text.
pub fn decision_line(d: &pb::PmDecision) -> String {
    if d.steered {
        return format!(
            "scene {} from step {} (P_M v{}, r {} γ {:.4} kept): {}",
            d.scene.as_ref().map_or(0, |s| s.version),
            d.from_step,
            d.pm_version,
            d.resolution,
            d.gamma,
            d.reason
        );
    }
    if d.provisional {
        return format!(
            "P_M v{} (provisional) from step {}: r {} → r {} γ {:.4} ({})",
            d.pm_version, d.from_step, d.old_resolution, d.resolution, d.gamma, d.reason
        );
    }
    let precision = |bits: Option<u32>| {
        bits.and_then(|b| insitu_core::Precision::from_bits(b).ok())
            .map_or_else(String::new, |p| format!(" {p}"))
    };
    // The precision is named where it changes (or where the old one is not known).
    let new_precision = if d.precision_bits == d.old_precision_bits {
        String::new()
    } else {
        precision(d.precision_bits)
    };
    let old = if d.old_resolution == 0 {
        "the configured P_M".to_owned()
    } else {
        format!(
            "r {} γ {:.4}{}",
            d.old_resolution,
            d.old_gamma,
            if new_precision.is_empty() {
                String::new()
            } else {
                precision(d.old_precision_bits)
            }
        )
    };
    let kind = if d.corrects_version > 0 {
        format!(" (correction of v{})", d.corrects_version)
    } else {
        String::new()
    };
    format!(
        "P_M v{}{kind} from step {}: {old} → r {} γ {:.4}{new_precision} ({}); tuned on steps {:?}; predicted σ {:.1} kB, q {} dB, τ {:.3} s; {} trials, {:.1} s",
        d.pm_version,
        d.from_step,
        d.resolution,
        d.gamma,
        d.reason,
        d.characteristic_steps,
        d.predicted_sigma_bytes as f64 / 1e3,
        crate::cmd::q_text(d.predicted_q_db),
        d.predicted_tau_secs,
        d.trials,
        d.trial_secs
    )
}

/// A P_M change as the JSON event of `--json`.
pub fn decision_json(d: &pb::PmDecision) -> serde_json::Value {
    serde_json::json!({
        "event": "pm_change",
        "step": d.trigger_step,
        "from_step": d.from_step,
        "pm_version": d.pm_version,
        "provisional": d.provisional,
        "old": {"r": d.old_resolution, "gamma": f32_number(d.old_gamma), "precision_bits": d.old_precision_bits},
        "new": {"r": d.resolution, "gamma": f32_number(d.gamma), "precision_bits": d.precision_bits},
        "characteristic_steps": d.characteristic_steps,
        "predicted": {
            "sigma_bytes": d.predicted_sigma_bytes,
            "q_db": crate::cmd::q_json(d.predicted_q_db),
            "tau_s": d.predicted_tau_secs,
        },
        "trials": d.trials,
        "trial_secs": d.trial_secs,
        "reason": d.reason,
        "utility": d.utility_description,
        "corrects_version": (d.corrects_version > 0).then_some(d.corrects_version),
        "forecast_ratio": (d.forecast_ratio > 0.0).then_some(d.forecast_ratio),
        "scene_version": d.scene.as_ref().map_or(0, |s| s.version),
        "steered": d.steered,
    })
}

/// The tuner's budgets as its status carries them (none without a tuner or where its
/// utility has none): what every step is shown against.
pub fn budgets_of(s: &pb::TunerStatus) -> Budgets {
    Budgets::from_wire(s.sigma_target_bytes, s.tau_target_secs)
}

/// σ and τ of a report over `budgets`.
fn ratios(budgets: &Budgets, r: &pb::QualityReport) -> (Option<f64>, Option<f64>) {
    budgets.ratios(r.sigma_bytes as f64, r.tau_secs)
}

/// Adherence of the stored VDIs (one per step, or the composed step of several ranks) to
/// σ_target and τ_target.
pub(super) fn adherence(
    budgets: &Budgets,
    reports: &[pb::QualityReport],
) -> (Option<Adherence>, Option<Adherence>) {
    let mut steps: Vec<&pb::QualityReport> = reports
        .iter()
        .filter(|r| r.composed || r.world_size <= 1)
        .collect();
    // In step order: the P_M changes are counted between consecutive steps.
    steps.sort_by_key(|r| r.step);
    let of = |b: Option<f64>, v: fn(&pb::QualityReport) -> f64| {
        b.map(|b| {
            let of = |r: &&pb::QualityReport| (r.pm_version, (r.resolution, r.gamma), v(r));
            Adherence::of(steps.iter().map(of), b)
        })
    };
    (
        of(budgets.size_bytes.map(|b| b as f64), |r| {
            r.sigma_bytes as f64
        }),
        of(budgets.time_secs, |r| r.tau_secs),
    )
}

/// A stored VDI as the JSON line of `--json`, with σ and τ over the budgets.
pub fn report_json(r: &pb::QualityReport, budgets: Budgets) -> serde_json::Value {
    let (sigma_ratio, tau_ratio) = ratios(&budgets, r);
    serde_json::json!({
        "step": r.step,
        "rank": r.rank,
        "r": r.resolution,
        "gamma": f32_number(r.gamma),
        "pm_version": r.pm_version,
        "sigma_bytes": r.sigma_bytes,
        "tau_s": r.tau_secs,
        "q_db": r.q_db.map(crate::cmd::q_json),
        "world_size": r.world_size,
        "composed": r.composed,
        "missing_ranks": r.missing_ranks,
        "error": (!r.error.is_empty()).then_some(&r.error),
        "sigma_budget_ratio": sigma_ratio,
        "tau_budget_ratio": tau_ratio,
    })
}

/// A step's line, from a quality report, the budgets and the generator's queue state.
pub fn report_line(r: &pb::QualityReport, budgets: Budgets, queue: Option<(u32, u64)>) -> String {
    let q = r.q_db.map_or_else(
        || "    -   ".to_owned(),
        |q| format!("{:>5} dB", crate::cmd::q_text(q)),
    );
    let queue = queue.map_or_else(String::new, |(depth, drops)| {
        format!("  queue {depth}  drops {drops}")
    });
    let who = if !r.composed {
        format!("rank {}", r.rank)
    } else if !r.error.is_empty() {
        return format!("step {:>6}  not composed: {}", r.step, r.error);
    } else if r.missing_ranks.is_empty() {
        format!("all {} ranks", r.world_size)
    } else {
        format!(
            "{} of {} ranks (partial: {:?} missing)",
            r.world_size as usize - r.missing_ranks.len(),
            r.world_size,
            r.missing_ranks
        )
    };
    // Shares of the budgets where the tuner has them (a ! marks a step over one).
    let share = |x: Option<f64>| {
        x.map_or_else(String::new, |x| {
            let mark = if x >= 1.0 { "!" } else { "" };
            format!(" ({:.0} %{mark})", 100.0 * x)
        })
    };
    let (sigma_ratio, tau_ratio) = ratios(&budgets, r);
    format!(
        "step {:>6}  {who}  v{}  r {:>4}  γ {:.4}  σ {:>9.1} kB{}  τ {:.3} s{}  q {q}{queue}",
        r.step,
        r.pm_version,
        r.resolution,
        r.gamma,
        r.sigma_bytes as f64 / 1e3,
        share(sigma_ratio),
        r.tau_secs,
        share(tau_ratio),
    )
}

/// What the printer has seen (for the summary).
#[derive(Default)]
pub(super) struct Seen {
    pub(super) reports: Vec<pb::QualityReport>,
    pub(super) decisions: Vec<pb::PmDecision>,
}

/// The task printing reports and decisions, and what it has seen.
pub struct Printer {
    task: JoinHandle<()>,
    seen: Arc<Mutex<Seen>>,
}

impl Printer {
    /// Whether every one of `n` stored VDIs has been reported and, for steps of several
    /// ranks, the step's composition too.
    fn all_in(&self, n: u64) -> bool {
        let seen = self.seen.lock().unwrap_or_else(|e| e.into_inner());
        let (composed, ranks): (Vec<_>, Vec<_>) = seen.reports.iter().partition(|r| r.composed);
        let multi: std::collections::BTreeSet<u64> = ranks
            .iter()
            .filter(|r| r.world_size > 1)
            .map(|r| r.step)
            .collect();
        ranks.len() as u64 >= n && composed.len() >= multi.len()
    }

    /// Waits (up to a minute) until every stored VDI has been reported (scoring may lag
    /// storing) and multi-rank steps composed, then stops printing.
    pub(super) async fn finish(self, n: u64) -> Seen {
        let deadline = Instant::now() + Duration::from_secs(60);
        while Instant::now() < deadline && !self.all_in(n) {
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        self.task.abort();
        let _ = self.task.await;
        std::mem::take(&mut *self.seen.lock().unwrap_or_else(|e| e.into_inner()))
    }
}

/// Subscribes to the viz-node's reports (and the tuner's decisions, when there is a tuner) and
/// prints a line per report and per P_M change (JSON objects with `json`).
///
/// # Errors
/// When the viz-node cannot be reached.
pub async fn print_reports(
    (viz, token): (SocketAddr, Option<&Token>),
    generator: Option<Arc<gen::shared::Shared>>,
    tuner: Option<&insitu_tuner_node::RunningTuner>,
    json: bool,
) -> Result<Printer> {
    let channel = transport::connect(&transport::uri(&viz.to_string())).await?;
    let mut stream = VizClient::with_interceptor(channel, AttachToken::new(token))
        .subscribe(pb::SubscribeRequest {})
        .await
        .map_err(|e| local_refusal(&e, "the viz-node"))?
        .into_inner();
    let mut decisions = tuner.map(|t| t.engine().subscribe());
    let budgets = tuner.map_or_else(Budgets::default, |t| budgets_of(&t.engine().status()));
    // Said once, at the first step made before any decision: a run that ends before the
    // first tuning learns it from its first lines.
    let mut untuned_notice =
        tuner.map(|t| untuned_notice(&t.engine().utility_description(), budgets));
    let seen = Arc::new(Mutex::new(Seen::default()));
    let c = seen.clone();
    let task = tokio::spawn(async move {
        loop {
            tokio::select! {
                r = stream.next() => {
                    let Some(Ok(r)) = r else { break };
                    if r.pm_version == 0 && !json {
                        if let Some(notice) = untuned_notice.take() {
                            println!("{notice}");
                        }
                    } else if r.pm_version > 0 {
                        untuned_notice = None;
                    }
                    if json {
                        println!("{}", report_json(&r, budgets));
                    } else {
                        let queue = generator.as_ref().map(|g| {
                            let s = g.status();
                            (s.queue_depth, s.dropped_queue + s.dropped_outbox)
                        });
                        println!("{}", report_line(&r, budgets, queue));
                    }
                    c.lock().unwrap_or_else(|e| e.into_inner()).reports.push(r);
                }
                d = async { match decisions.as_mut() { Some(rx) => rx.recv().await.ok(), None => std::future::pending().await } } => {
                    let Some(d) = d else { decisions = None; continue };
                    if json {
                        println!("{}", decision_json(&d));
                    } else {
                        println!("{}", decision_line(&d));
                    }
                    c.lock().unwrap_or_else(|e| e.into_inner()).decisions.push(d);
                }
            }
        }
    });
    Ok(Printer { task, seen })
}

/// What a run's first lines say while no decision is in force: where `P_M` comes from until
/// the tuner's first one, and what keeps a size or time budget meanwhile (`utility`: its
/// description).
pub fn untuned_notice(utility: &str, budgets: Budgets) -> String {
    let first = "P_M v0 is the generator-node's configured one until the tuner's first decision, which follows its first tuning (trials on the first characteristic step, seconds)";
    if !budgets.is_none() {
        format!("{first}; until then a step over the budget ({utility}) lowers r for the steps after it (by the node that holds all of a world's ranks, else by the tuner)")
    } else {
        format!("{first} ({utility})")
    }
}
