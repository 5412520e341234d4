//! `viz-node`: the daemon. Reads a TOML config (see `deploy/viz-node.toml`), applies flag
//! overrides, serves until SIGINT/SIGTERM.

use clap::Parser;
use insitu_proto::daemon::{run_main, shutdown_signal, CommonArgs, DaemonConfig};
use insitu_viz_node::{start, Config};
use std::net::SocketAddr;
use std::path::PathBuf;

#[derive(Parser, Debug)]
#[command(
    name = "viz-node",
    version,
    about = "Records, renders and scores VDIs shipped by generator-nodes",
    after_help = "Every config key is documented in deploy/viz-node.toml."
)]
struct Args {
    #[command(flatten)]
    common: CommonArgs,
    /// Recording directory.
    #[arg(long)]
    recording_dir: Option<PathBuf>,
    /// Serve the recording as a read-only archive: nothing written, shipped items refused.
    #[arg(long)]
    read_only: bool,
    /// Where VDIs are rendered: cpu, gpu or auto (a hardware GPU if found, else the CPU).
    #[arg(long)]
    backend: Option<insitu_core::BackendChoice>,
    /// Address of the web viewer (port 0: ephemeral; the URL is printed).
    #[arg(long)]
    http: Option<SocketAddr>,
    /// The tuner-node whose budget the viewer's charts draw, host:port.
    #[arg(long)]
    tuner: Option<String>,
    /// Seconds a step of several ranks waits for its last rank before it is composed without
    /// it (marked partial).
    #[arg(long)]
    compose_timeout_secs: Option<f64>,
}

fn main() -> std::process::ExitCode {
    insitu_core::backend::quiet_vulkan_layers();
    run_main(async {
        let a = Args::parse();
        let mut cfg: Config = a.common.config()?;
        if let Some(v) = a.recording_dir {
            cfg.recording_dir = v;
        }
        cfg.read_only |= a.read_only;
        if let Some(v) = a.backend {
            cfg.backend = v;
        }
        if let Some(v) = a.compose_timeout_secs {
            cfg.compose_timeout_secs = v;
        }
        if a.http.is_some() {
            cfg.http_listen = a.http;
        }
        if a.tuner.is_some() {
            cfg.tuner = a.tuner;
        }
        cfg.validate()?;
        let node = start(cfg).await?;
        println!("listening on {}", node.local_addr());
        if let Some(url) = node.viewer_url() {
            println!("web viewer on {url}");
        }
        shutdown_signal().await;
        node.shutdown().await;
        anyhow::Ok(())
    })
}
