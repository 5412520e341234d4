//! What `insitu demo` and `insitu replay` share: a generator-node, a viz-node and (unless
//! `--no-tune`) a tuner started in this process on 127.0.0.1 with ephemeral ports (the same
//! libraries the daemons run), a printer of the viz-node's quality reports (one line per stored
//! VDI) and of the tuner's decisions (one line per change of P_M), and the summary. With
//! `--json` every line is a JSON object instead.

mod print;
mod summary;

use anyhow::{Context, Result};
use insitu_client::SimClient;
use insitu_core::adherence::Adherence;
use insitu_core::budget::Budgets;
use insitu_core::json::f32_number;
use insitu_core::vdi::codec::Codec;
use insitu_generator_node::{self as gen, Policy};
use insitu_proto::auth::{AttachToken, Token};
use insitu_proto::pb::viz_client::VizClient;
use insitu_proto::peer::Peer;
use insitu_proto::{pb, transport};
pub use print::*;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
pub use summary::counts_json;
use summary::*;
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
    /// Guard on the tuner's size budget, a ratio (0: off): a step made under the tuner's
    /// decision whose sigma comes out over this many times the budget is made again toward it
    /// and shipped at its last try (none is lost).
    #[arg(long, default_value_t = gen::config::DEFAULT_SIZE_GUARD, value_parser = size_guard_arg)]
    pub size_guard: f64,
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

/// `--size-guard`: 0, or a finite ratio ≥ 1.
fn size_guard_arg(s: &str) -> Result<f64, String> {
    s.parse::<f64>()
        .ok()
        .filter(|&g| g == 0.0 || (g.is_finite() && g >= 1.0))
        .ok_or_else(|| format!("{s:?} is not a ratio ≥ 1 of the budget, nor 0 for off"))
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
        cfg.generation.size_max = a.size_max;
        cfg.generation.time_max = a.time_max;
        cfg.generation.size_guard = a.size_guard;
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
