//! `insitu`: the command line of the in situ VDI service.
//!
//! Subcommands: `render` (reference DVR → PNG), `generate` (VDI → file), `view` (VDI file +
//! camera → PNG), `evaluate` (σ, q, τ of one `P_M` at the test views, with a PNG strip),
//! `demo` (the in situ pipeline on the built-in simulation) and `replay` (a recorded series
//! through the pipeline).

// The arguments' doc comments are their `--help` text, where `<name>` reads as a placeholder;
// rustdoc would take it for an HTML tag.
#![allow(rustdoc::invalid_html_tags)]

mod cmd;
mod output;
mod pipeline;
mod progress;
mod scene;

use anyhow::Result;
use clap::{Parser, Subcommand};

#[derive(Parser, Debug)]
#[command(
    name = "insitu",
    version,
    about = "Volumetric Depth Images for in situ visualization"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Direct volume rendering of the original data (the reference) to a PNG.
    Render(cmd::render::Args),
    /// Generate a VDI for P_M = (r, gamma) and write it compressed; prints sigma and tau.
    Generate(cmd::generate::Args),
    /// Render a VDI file from a camera to a PNG.
    View(cmd::view::Args),
    /// Generate, compress and render a VDI at the test views; score it against direct renders.
    Evaluate(cmd::evaluate::Args),
    /// The in situ pipeline on the built-in Gray–Scott simulation: client → generator-node →
    /// viz-node on 127.0.0.1 with a tuner re-optimising (r, gamma) live, one line per step
    /// (P_M version, sigma, tau, q) and per P_M change, then a summary. Defaults: --utility
    /// size:1MB, --codec zstd.
    Demo(cmd::demo::Args),
    /// Feed a recorded time series (4-D raw file) through the pipeline, as a simulation would,
    /// with a tuner unless --no-tune or --generator. Defaults: --utility size:1MB, --codec bzip2.
    Replay(cmd::replay::Args),
    /// Whether a daemon serves (gRPC health check); --wait SECS waits for it. Exit 0: SERVING.
    Health(cmd::health::Args),
    /// Steer a running run through its viz-node: transfer function, field, generation camera
    /// or the tuner's utility, from the next steps on (docs/steering.md).
    Steer(cmd::steer::Args),
    /// A recording's index (steps, ranks, σ, τ, q, P_M versions) as JSON or CSV.
    Export(cmd::export::Args),
    /// Rebuild a recording's missing, emptied or damaged index from its files (every VDI and
    /// reference file says which step and rank it holds), then score and compose what lacks q.
    Recover(cmd::recover::Args),
    /// Parameter study over a grid of (r, gamma): sigma, q, tau per candidate, cached; CSV + JSON.
    Study(cmd::study::Args),
    /// The best (r, gamma) for a utility function (size or time budget, quality target).
    Tune(cmd::tune::Args),
    /// Tune across a time series: characteristic steps, conservative (r, gamma), cross-evaluation.
    Series(cmd::series::Args),
    /// What accuracy costs in time: q, tau and sigma for each knob that trades quality for speed.
    Accuracy(cmd::accuracy::Args),
}

fn main() -> std::process::ExitCode {
    insitu_core::backend::quiet_vulkan_layers();
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn")),
        )
        .with_writer(std::io::stderr)
        .init();
    let cli = Cli::parse();
    match run(cli) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(err) => {
            let mut messages = insitu_proto::peer::error_messages(err.as_ref()).into_iter();
            eprintln!("error: {}", messages.next().unwrap_or_default());
            for cause in messages {
                eprintln!("  caused by: {cause}");
            }
            std::process::ExitCode::FAILURE
        }
    }
}

fn run(cli: Cli) -> Result<()> {
    match cli.command {
        Command::Render(a) => cmd::render::run(a),
        Command::Generate(a) => cmd::generate::run(a),
        Command::View(a) => cmd::view::run(a),
        Command::Evaluate(a) => cmd::evaluate::run(a),
        Command::Demo(a) => cmd::demo::run(a),
        Command::Replay(a) => cmd::replay::run(a),
        Command::Export(a) => cmd::export::run(a),
        Command::Recover(a) => cmd::recover::run(a),
        Command::Health(a) => cmd::health::run(a),
        Command::Steer(a) => cmd::steer::run(a),
        Command::Study(a) => cmd::study::run(a),
        Command::Tune(a) => cmd::tune::run(a),
        Command::Series(a) => cmd::series::run(a),
        Command::Accuracy(a) => cmd::accuracy::run(a),
    }
}
