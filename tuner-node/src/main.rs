//! `tuner-node`: the daemon. Reads a TOML config (see `deploy/tuner-node.toml`), applies flag
//! overrides, serves until SIGINT/SIGTERM.

use anyhow::Result;
use clap::Parser;
use insitu_proto::daemon::{run_main, shutdown_signal, CommonArgs, DaemonConfig};
use insitu_tuner_node::{start, Config};
use std::path::PathBuf;

#[derive(Parser, Debug)]
#[command(
    name = "tuner-node",
    version,
    about = "Tunes the VDI parameters (r, gamma) of running generator-nodes",
    after_help = "Every config key is documented in deploy/tuner-node.toml."
)]
struct Args {
    #[command(flatten)]
    common: CommonArgs,
    /// Directory of the persisted state.
    #[arg(long)]
    state_dir: Option<PathBuf>,
    /// The viz-node whose quality reports are watched, host:port.
    #[arg(long)]
    viz: Option<String>,
    /// Utility: size:BYTES, time:SECS, size:BYTES,time:SECS or quality:DB.
    #[arg(long)]
    utility: Option<String>,
}

fn config(a: Args) -> Result<Config> {
    let mut c: Config = a.common.config()?;
    if let Some(v) = a.state_dir {
        c.state_dir = v;
    }
    if a.viz.is_some() {
        c.viz = a.viz;
    }
    if let Some(v) = a.utility {
        c.utility = v;
    }
    c.validate()?;
    Ok(c)
}

fn main() -> std::process::ExitCode {
    insitu_core::backend::quiet_vulkan_layers();
    run_main(async {
        let node = start(config(Args::parse())?).await?;
        // Scripts and tests read the actual address from this line.
        println!("listening on {}", node.local_addr());
        shutdown_signal().await;
        eprintln!("tuner-node: shutting down");
        node.shutdown().await;
        anyhow::Ok(())
    })
}
