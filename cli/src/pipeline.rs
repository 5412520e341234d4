//! What `insitu demo` and `insitu replay` share: a generator-node and a viz-node started in
//! this process on 127.0.0.1 with ephemeral ports (the same libraries the daemons run), a
//! printer of the viz-node's quality reports (one line per stored VDI), and the summary.

use anyhow::{Context, Result};
use insitu_generator_node::{self as gen, Policy};
use insitu_proto::pb::viz_client::VizClient;
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
    /// Codec: bzip2 (the paper's sigma), zstd or none.
    #[arg(long, default_value = "bzip2")]
    pub codec: String,
    /// Input queue policy of the generator-node: block, drop-oldest or latest-only.
    #[arg(long, default_value = "block")]
    pub policy: Policy,
    /// Input queue length, steps.
    #[arg(long, default_value_t = 2)]
    pub queue_steps: usize,
    /// Recording directory of the viz-node (default: a new insitu-recording-<time> here).
    #[arg(long)]
    pub recording: Option<PathBuf>,
}

/// A step's line, from a quality report and the generator's queue state.
pub fn report_line(r: &pb::QualityReport, queue: Option<(u32, u64)>) -> String {
    let q = r.q_db.map_or_else(
        || "    -   ".to_owned(),
        |q| format!("{:>5} dB", crate::cmd::q_text(q)),
    );
    let queue = queue.map_or_else(String::new, |(depth, drops)| {
        format!("  queue {depth}  drops {drops}")
    });
    format!(
        "step {:>6}  rank {}  r {:>4}  γ {:.4}  σ {:>9.1} kB  τ {:.3} s  q {q}{queue}",
        r.step,
        r.rank,
        r.resolution,
        r.gamma,
        r.sigma_bytes as f64 / 1e3,
        r.tau_secs,
    )
}

/// The task printing reports, and the reports it has seen (for the summary).
pub struct Printer {
    task: JoinHandle<()>,
    reports: Arc<Mutex<Vec<pb::QualityReport>>>,
}

impl Printer {
    fn reports(&self) -> Vec<pb::QualityReport> {
        self.reports
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .clone()
    }

    /// Waits (up to a minute) until `n` reports have arrived (scoring may lag storing), then
    /// stops printing.
    async fn finish(self, n: u64) -> Vec<pb::QualityReport> {
        let deadline = Instant::now() + Duration::from_secs(60);
        while Instant::now() < deadline && (self.reports().len() as u64) < n {
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        self.task.abort();
        self.reports()
    }
}

/// Subscribes to the viz-node's reports and prints a line per report.
///
/// # Errors
/// When the viz-node cannot be reached.
pub async fn print_reports(
    viz: SocketAddr,
    generator: Option<Arc<gen::service::Shared>>,
) -> Result<Printer> {
    let channel = transport::connect(&transport::uri(&viz.to_string())).await?;
    let mut stream = VizClient::new(channel)
        .subscribe(pb::SubscribeRequest {})
        .await?
        .into_inner();
    let reports = Arc::new(Mutex::new(Vec::new()));
    let c = reports.clone();
    let task = tokio::spawn(async move {
        while let Some(Ok(r)) = stream.next().await {
            let queue = generator.as_ref().map(|g| {
                let s = g.status();
                (s.queue_depth, s.dropped_queue + s.dropped_outbox)
            });
            println!("{}", report_line(&r, queue));
            c.lock().unwrap_or_else(|e| e.into_inner()).push(r);
        }
    });
    Ok(Printer { task, reports })
}

/// The two nodes, in process.
pub struct LocalNodes {
    /// The generator-node.
    pub generator: gen::RunningNode,
    /// The viz-node.
    pub viz: insitu_viz_node::RunningViz,
    /// Where the viz-node records.
    pub recording: PathBuf,
}

/// A fresh recording directory name.
pub fn default_recording() -> PathBuf {
    let secs = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs());
    PathBuf::from(format!("insitu-recording-{secs}"))
}

impl LocalNodes {
    /// Starts a viz-node recording into `a.recording` and a generator-node shipping to it.
    ///
    /// # Errors
    /// Bad settings, or a node failing to start.
    pub async fn start(a: &PipelineArgs, tweak: impl FnOnce(&mut gen::Config)) -> Result<Self> {
        let recording = a.recording.clone().unwrap_or_else(default_recording);
        let viz = insitu_viz_node::start(insitu_viz_node::Config {
            listen: SocketAddr::from(([127, 0, 0, 1], 0)),
            recording_dir: recording.clone(),
            backend: a.backend.backend,
            ..Default::default()
        })
        .await
        .context("starting the viz-node")?;
        let mut cfg = gen::Config {
            listen: SocketAddr::from(([127, 0, 0, 1], 0)),
            viz: Some(viz.local_addr().to_string()),
            ..Default::default()
        };
        cfg.backend = a.backend.backend;
        cfg.queue.policy = a.policy;
        cfg.queue.max_items = a.queue_steps;
        cfg.generation.resolution = a.pm.r;
        cfg.generation.gamma = a.pm.gamma;
        cfg.generation.codec = a.codec.clone();
        tweak(&mut cfg);
        let generator = gen::start(cfg)
            .await
            .context("starting the generator-node")?;
        Ok(Self {
            generator,
            viz,
            recording,
        })
    }

    /// The generator-node's address.
    pub fn generator_addr(&self) -> String {
        self.generator.local_addr().to_string()
    }

    /// Prints reports until one per stored VDI has arrived, shuts both nodes down, and prints
    /// the summary.
    pub async fn finish(
        self,
        printer: Printer,
        status: &pb::GeneratorStatus,
        pushed: u64,
        started: Instant,
    ) {
        let reports = printer.finish(status.steps_shipped).await;
        let summary = self.generator.shutdown().await;
        self.viz.shutdown().await;
        print_summary(
            pushed,
            started.elapsed().as_secs_f64(),
            status,
            &reports,
            &self.recording,
        );
        println!("  generator: {summary}");
    }
}

/// Prints the closing summary of a run.
fn print_summary(
    pushed: u64,
    elapsed_secs: f64,
    final_status: &pb::GeneratorStatus,
    reports: &[pb::QualityReport],
    recording: &Path,
) {
    let n = reports.len().max(1) as f64;
    let sigma = reports.iter().map(|r| r.sigma_bytes as f64).sum::<f64>() / n;
    let tau = reports.iter().map(|r| r.tau_secs).sum::<f64>() / n;
    let sampled: Vec<f64> = reports.iter().filter_map(|r| r.q_db).collect();
    println!("summary:");
    println!(
        "  steps pushed {pushed}, received {}, generated {}, stored {}, dropped {} (queue {}, outbox {}), failed {}",
        final_status.steps_received,
        final_status.steps_generated,
        final_status.steps_shipped,
        final_status.dropped_queue + final_status.dropped_outbox,
        final_status.dropped_queue,
        final_status.dropped_outbox,
        final_status.failed
    );
    println!(
        "  mean σ {:.1} kB, mean τ {:.3} s over {} VDIs",
        sigma / 1e3,
        tau,
        reports.len()
    );
    if !sampled.is_empty() {
        let lo = sampled.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = sampled.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        println!(
            "  q on {} sampled steps: {} – {} dB",
            sampled.len(),
            crate::cmd::q_text(lo),
            crate::cmd::q_text(hi)
        );
    }
    println!("  wall clock {elapsed_secs:.1} s");
    println!("  recording: {}", recording.display());
}
