//! What `insitu demo` and `insitu replay` share: a generator-node, a viz-node and (unless
//! `--no-tune`) a tuner started in this process on 127.0.0.1 with ephemeral ports (the same
//! libraries the daemons run), a printer of the viz-node's quality reports (one line per stored
//! VDI) and of the tuner's decisions (one line per change of P_M), and the summary. With
//! `--json` every line is a JSON object instead.

use anyhow::{Context, Result};
use insitu_client::SimClient;
use insitu_core::adherence::Adherence;
use insitu_core::json::f32_number;
use insitu_core::vdi::codec::Codec;
use insitu_generator_node::{self as gen, Policy};
use insitu_proto::auth::{AttachToken, Token};
use insitu_proto::pb::viz_client::VizClient;
use insitu_proto::peer::Peer;
use insitu_proto::{pb, transport};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tokio::task::JoinHandle;
use tokio_stream::StreamExt;

/// Settings of the local pipeline that the commands expose as flags.
#[derive(clap::Args, Debug, Clone)]
pub struct PipelineArgs {
    #[command(flatten)]
    pub pm: crate::cmd::PmArgs,
    #[command(flatten)]
    pub backend: crate::cmd::BackendArgs,
    /// Codec: bzip2 (the paper's sigma), zstd or none. Default: the command's (see its help).
    #[arg(long, value_parser = crate::cmd::codec_arg)]
    pub codec: Option<Codec>,
    /// Input queue policy of the generator-node: block, drop-oldest or latest-only.
    #[arg(long, default_value = "block")]
    pub policy: Policy,
    /// Input queue length, steps.
    #[arg(long, default_value_t = 2)]
    pub queue_steps: usize,
    /// Recording directory of the viz-node (default: a new insitu-recording-<time> here). The
    /// tuner's state goes to its `tuner-state/`.
    #[arg(long)]
    pub recording: Option<PathBuf>,
    /// Precisions the tuner chooses among with r and gamma (P_M's third parameter): colour
    /// bits 4–16 and f32, a list; give --precision's alone to keep it.
    #[arg(long, default_value = insitu_tuner_node::config::DEFAULT_PRECISIONS)]
    pub tune_precisions: String,
    /// The tuner's utility: size:BYTES (Eq. 1), time:SECS (Eq. 2), size:BYTES,time:SECS, or
    /// quality:DB. Default: the command's (see its help).
    #[arg(long)]
    pub utility: Option<String>,
    /// Keep P_M fixed: start no tuner.
    #[arg(long)]
    pub no_tune: bool,
    /// Hard limit on a step's sigma (e.g. 1MB): a VDI over it is made again at a coarser P_M
    /// before it ships, so no stored step exceeds it (the summary counts the retries).
    #[arg(long, value_parser = size_max_arg)]
    pub size_max: Option<u64>,
    /// Hard limit on a step's tau, seconds (e.g. 0.05): a generation that would overrun it is
    /// stopped and made again at a lower resolution, so no stored step's tau exceeds it (a
    /// step that cannot fit is not stored; the summary counts the retries).
    #[arg(long, value_parser = time_max_arg)]
    pub time_max: Option<f64>,
    /// Print one JSON object per line (per stored VDI, per P_M change, and a final summary).
    #[arg(long)]
    pub json: bool,
    /// Address of the viz-node's web viewer (port 0: ephemeral); its URL is printed at start.
    #[arg(long, default_value = "127.0.0.1:0")]
    pub http: SocketAddr,
    /// Start no web viewer.
    #[arg(long)]
    pub no_http: bool,
    /// After the run, keep the viz-node and its web viewer serving the recording until Ctrl-C.
    #[arg(long)]
    pub keep_serving: bool,
}

/// `--size-max`: bytes, with an optional unit (B, kB, MB, GB).
fn size_max_arg(s: &str) -> Result<u64, String> {
    insitu_tuner::utility::parse_bytes(s)
        .filter(|&b| b > 0)
        .ok_or_else(|| format!("{s:?} is not a size in bytes (e.g. 1MB, 500kB)"))
}

/// `--time-max`: seconds, finite and > 0.
fn time_max_arg(s: &str) -> Result<f64, String> {
    s.parse::<f64>()
        .ok()
        .filter(|t| t.is_finite() && *t > 0.0)
        .ok_or_else(|| format!("{s:?} is not a time in seconds > 0 (e.g. 0.05)"))
}

/// What a command chooses when its flags do not.
#[derive(Clone, Copy, Debug)]
pub struct Defaults {
    /// The tuner's utility.
    pub utility: &'static str,
    /// The codec.
    pub codec: Codec,
}

impl PipelineArgs {
    /// `--codec`, else the command's default.
    pub fn codec(&self, defaults: Defaults) -> Codec {
        self.codec.unwrap_or(defaults.codec)
    }
}

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
        "utility": d.utility,
        "corrects_version": (d.corrects_version > 0).then_some(d.corrects_version),
        "forecast_ratio": (d.forecast_ratio > 0.0).then_some(d.forecast_ratio),
        "scene_version": d.scene.as_ref().map_or(0, |s| s.version),
        "steered": d.steered,
    })
}

/// The tuner's budgets, σ_target in bytes and τ_target in seconds (none without a tuner or
/// where its utility has none): what every step is shown against.
#[derive(Clone, Copy, Debug, Default)]
pub struct Budgets {
    /// σ_target, bytes.
    pub sigma_bytes: Option<f64>,
    /// τ_target, seconds.
    pub tau_secs: Option<f64>,
}

impl Budgets {
    /// The budgets of a tuner's status (0 there: none).
    pub fn of(s: &pb::TunerStatus) -> Self {
        Self {
            sigma_bytes: (s.sigma_target_bytes > 0).then_some(s.sigma_target_bytes as f64),
            tau_secs: (s.tau_target_secs > 0.0).then_some(s.tau_target_secs),
        }
    }

    /// σ and τ of a report over their budgets.
    fn ratios(&self, r: &pb::QualityReport) -> (Option<f64>, Option<f64>) {
        (
            self.sigma_bytes.map(|b| r.sigma_bytes as f64 / b),
            self.tau_secs.map(|b| r.tau_secs / b),
        )
    }

    /// Adherence of the stored VDIs (one per step, or the composed step of several ranks) to
    /// σ_target and τ_target.
    fn adherence(&self, reports: &[pb::QualityReport]) -> (Option<Adherence>, Option<Adherence>) {
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
            of(self.sigma_bytes, |r| r.sigma_bytes as f64),
            of(self.tau_secs, |r| r.tau_secs),
        )
    }
}

/// A stored VDI as the JSON line of `--json`, with σ and τ over the budgets.
pub fn report_json(r: &pb::QualityReport, budgets: Budgets) -> serde_json::Value {
    let (sigma_ratio, tau_ratio) = budgets.ratios(r);
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
    let (sigma_ratio, tau_ratio) = budgets.ratios(r);
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
struct Seen {
    reports: Vec<pb::QualityReport>,
    decisions: Vec<pb::PmDecision>,
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
    async fn finish(self, n: u64) -> Seen {
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
    let budgets = tuner.map_or_else(Budgets::default, |t| Budgets::of(&t.engine().status()));
    // Said once, at the first step made before any decision: a run that ends before the
    // first tuning learns it from its first lines.
    let mut untuned_notice = tuner.map(|t| untuned_notice(&t.engine().utility(), budgets));
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
    if budgets.sigma_bytes.is_some() || budgets.tau_secs.is_some() {
        format!("{first}; until then a step over the budget ({utility}) lowers r for the steps after it, on a node that holds all of its world's ranks")
    } else {
        format!("{first} ({utility})")
    }
}

/// A refusal by the local `link` ("the viz-node"), naming it and, for a token refused, what
/// to check.
fn local_refusal(e: &tonic::Status, link: &str) -> anyhow::Error {
    let hint = if e.code() == tonic::Code::Unauthenticated {
        " (the local nodes take INSITU_TOKEN from this environment: unset it or set it to a printable token)"
    } else {
        ""
    };
    anyhow::anyhow!("subscribing to {link}'s reports: {}{hint}", e.message())
}

/// The two nodes, in process.
pub struct LocalNodes {
    /// The generator-node.
    pub generator: gen::RunningNode,
    /// The viz-node.
    pub viz: insitu_viz_node::RunningViz,
    /// The tuner (none with `--no-tune`).
    pub tuner: Option<insitu_tuner_node::RunningTuner>,
    /// The token the nodes took from `INSITU_TOKEN`, sent by the clients here.
    pub token: Option<Token>,
    /// Print JSON lines.
    pub json: bool,
    /// Where the viz-node records.
    pub recording: PathBuf,
    /// Serve the recording after the run until Ctrl-C.
    pub keep_serving: bool,
}

/// A tuner on loopback watching the viz-node at `viz`, with its state in `recording`, and the
/// adaptive search over `precisions` (a list) for `utility`.
async fn start_tuner(
    (utility, precisions): (String, String),
    recording: &std::path::Path,
    viz: SocketAddr,
) -> Result<insitu_tuner_node::RunningTuner> {
    let mut cfg = insitu_tuner_node::Config {
        listen: SocketAddr::from(([127, 0, 0, 1], 0)),
        state_dir: recording.join("tuner-state"),
        viz: Some(viz.to_string()),
        utility,
        ..Default::default()
    };
    cfg.grid.precision = precisions;
    insitu_tuner_node::start(cfg)
        .await
        .context("starting the tuner")
}

/// A fresh recording directory name.
pub fn default_recording() -> PathBuf {
    let secs = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs());
    PathBuf::from(format!("insitu-recording-{secs}"))
}

impl LocalNodes {
    /// Starts a viz-node recording into `a.recording`, a tuner watching it (unless
    /// `--no-tune`; utility `--utility`, else the command's default) and a generator-node shipping
    /// to the viz-node and dialling the tuner.
    ///
    /// # Errors
    /// Bad settings, or a node failing to start.
    pub async fn start(
        a: &PipelineArgs,
        defaults: Defaults,
        tweak: impl FnOnce(&mut gen::Config),
    ) -> Result<Self> {
        let recording = a.recording.clone().unwrap_or_else(default_recording);
        // The nodes below read INSITU_TOKEN as daemons do, so the clients here send it too.
        let token = Token::load(None).context("reading INSITU_TOKEN for the local nodes")?;
        let viz = insitu_viz_node::start(insitu_viz_node::Config {
            listen: SocketAddr::from(([127, 0, 0, 1], 0)),
            recording_dir: recording.clone(),
            backend: a.backend.backend,
            http_listen: (!a.no_http).then_some(a.http),
            ..Default::default()
        })
        .await
        .context("starting the viz-node")?;
        if let Some(url) = viz.viewer_url() {
            // With --json, stdout holds JSON lines only: the address goes to stderr.
            let line = format!("web viewer: {url}");
            if a.json {
                eprintln!("{line}");
            } else {
                println!("{line}");
            }
        }
        let tuner = if a.no_tune {
            None
        } else {
            let utility = a
                .utility
                .clone()
                .unwrap_or_else(|| defaults.utility.to_owned());
            let precisions = a.tune_precisions.clone();
            Some(start_tuner((utility, precisions), &recording, viz.local_addr()).await?)
        };
        if let (Some(t), Some(h)) = (&tuner, viz.http()) {
            h.watch_tuner(Peer::new(
                &t.local_addr().to_string(),
                token.clone(),
                None,
                false,
            )?);
        }
        let mut cfg = gen::Config {
            listen: SocketAddr::from(([127, 0, 0, 1], 0)),
            viz: Some(viz.local_addr().to_string()),
            tuner: tuner.as_ref().map(|t| t.local_addr().to_string()),
            ..Default::default()
        };
        cfg.backend = a.backend.backend;
        cfg.queue.policy = a.policy;
        cfg.queue.max_items = a.queue_steps;
        cfg.generation.resolution = a.pm.r;
        cfg.generation.gamma = a.pm.gamma;
        cfg.generation.codec = a.codec(defaults);
        cfg.generation.precision = a.pm.precision;
        cfg.generation.size_max = a.size_max.unwrap_or(0);
        cfg.generation.time_max = a.time_max.unwrap_or(0.0);
        // A pool of its own, as the daemon in its own process has (0 would be rayon's global
        // pool, where a generation's jobs queue behind the viz-node's scoring, or a built-in
        // simulation's steps, and τ counts their time).
        cfg.threads = std::thread::available_parallelism().map_or(1, |n| n.get());
        tweak(&mut cfg);
        let generator = gen::start(cfg)
            .await
            .context("starting the generator-node")?;
        if tuner.is_some() {
            // Steps made before the stream to the tuner is up are not summarised: wait for it,
            // so the first step counts.
            let stats = generator.shared().stats.clone();
            tokio::time::timeout(
                Duration::from_secs(10),
                stats.wait_for(|c| c.tuner_connected),
            )
            .await
            .context("the generator-node did not reach the tuner within 10 s")?;
        }
        Ok(Self {
            generator,
            viz,
            tuner,
            token,
            json: a.json,
            recording,
            keep_serving: a.keep_serving,
        })
    }

    /// A client of the local generator-node, sending the token the nodes were started with.
    ///
    /// # Errors
    /// When it cannot be reached.
    pub async fn generator_client(&self) -> Result<SimClient> {
        Ok(SimClient::connect(&self.generator_addr(), self.token.as_ref()).await?)
    }

    /// The generator-node's address.
    pub fn generator_addr(&self) -> String {
        self.generator.local_addr().to_string()
    }

    /// Subscribes the printer to the viz-node (and the tuner).
    ///
    /// # Errors
    /// When the viz-node cannot be reached.
    pub async fn printer(&self) -> Result<Printer> {
        print_reports(
            (self.viz.local_addr(), self.token.as_ref()),
            Some(self.generator.shared().clone()),
            self.tuner.as_ref(),
            self.json,
        )
        .await
    }

    /// Prints reports until one per stored VDI has arrived, shuts the nodes down, and prints
    /// the summary.
    pub async fn finish(
        self,
        printer: Printer,
        status: &pb::GeneratorStatus,
        pushed: u64,
        started: Instant,
    ) {
        // A host's part (ranks composed on their node) is one stored VDI for all its ranks.
        let stored = status.steps_shipped.saturating_sub(status.host_ranks) + status.host_parts;
        let seen = printer.finish(stored).await;
        let tuner = self.tuner.as_ref().map(|t| t.engine().status());
        let summary = self.generator.shutdown().await;
        let run = Run {
            pushed,
            elapsed_secs: started.elapsed().as_secs_f64(),
            status,
            seen: &seen,
            tuner: tuner.as_ref(),
            recording: &self.recording,
        };
        if self.json {
            println!(
                "{}",
                serde_json::json!({ "summary": run.json(&summary.to_string()) })
            );
        } else {
            run.print();
            println!("  generator: {summary}");
        }
        // The viewer keeps the tuner's budget while it serves.
        if let (true, Some(url)) = (self.keep_serving, self.viz.viewer_url()) {
            eprintln!("serving the recording at {url} until Ctrl-C");
            insitu_proto::daemon::shutdown_signal().await;
        }
        if let Some(t) = self.tuner {
            t.shutdown().await;
        }
        self.viz.shutdown().await;
    }
}

/// What the summary is made of.
struct Run<'a> {
    pushed: u64,
    elapsed_secs: f64,
    status: &'a pb::GeneratorStatus,
    seen: &'a Seen,
    tuner: Option<&'a pb::TunerStatus>,
    recording: &'a Path,
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
    fn json(&self, generator: &str) -> serde_json::Value {
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
                    let (sigma, tau) = Budgets::of(t).adherence(reports);
                    serde_json::json!({
                    "utility": t.utility,
                    "sigma_adherence": sigma.as_ref().map(Adherence::json),
                    "tau_adherence": tau.as_ref().map(Adherence::json),
                    "corrections": t.corrections,
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

    fn print(&self) {
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
                "  hard limit: {} generation(s) made again at a coarser P_M, {:.3} s of generation thrown away (steps that could not keep it are counted as failed)",
                s.limit_retries, s.limit_retry_secs
            );
        }
        println!("  wall clock {:.1} s", self.elapsed_secs);
        println!("  recording: {}", self.recording.display());
        if let Some(t) = self.tuner {
            println!(
                "  tuner ({}): {} decision(s), {} changing P_M, characteristic steps {:?}, {} trials of which {} size probes ({:.1} s on the nodes), {} answered from earlier trials, {} failed",
                t.utility,
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
            let (sigma, tau) = Budgets::of(t).adherence(reports);
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

/// Flushes `client` (within 600 s) and disconnects, saying on stderr, as soon as it is known
/// and whenever it changes, why steps are not stored yet (the viz-node away, or unable to
/// store: the generator-node's `ship_error`) instead of waiting in silence.
///
/// # Errors
/// As [`SimClient::flush`]: a refusal, or steps still not stored after 600 s.
pub async fn flush_saying_why(
    mut client: insitu_client::SimClient,
) -> Result<pb::GeneratorStatus, insitu_client::ClientError> {
    const EVERY: Duration = Duration::from_secs(3);
    let deadline = std::time::Instant::now() + Duration::from_secs(600);
    let mut said = String::new();
    loop {
        let left = deadline.saturating_duration_since(std::time::Instant::now());
        match client.flush(left.min(EVERY)).await {
            Err(insitu_client::ClientError::Refused {
                code: insitu_client::Code::DeadlineExceeded,
                ..
            }) if left > EVERY => {
                let why = client.status().await?.ship_error;
                if !why.is_empty() && why != said {
                    eprintln!("warning: steps not stored yet, still trying: {why}");
                    said = why;
                }
            }
            other => return other,
        }
    }
}
