//! `insitu recover`: rebuilds a recording's index from its files when the index is missing,
//! emptied or damaged beside stored steps (the viz-node refuses to start on such a recording),
//! then scores the steps that have reference frames and composes the steps of several ranks,
//! with the viz-node's own code, so that the recording reads as it did.

use super::BackendArgs;
use anyhow::{Context, Result};
use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::{Duration, Instant};

#[derive(clap::Args, Debug)]
pub struct Args {
    /// The recording directory (a viz-node's `recording_dir`); no viz-node may be writing it.
    #[arg(long)]
    recording: PathBuf,
    /// Rebuild the index only: leave scoring and composing to the viz-node's next start.
    #[arg(long)]
    no_score: bool,
    /// Longest wait for scoring and composing, seconds.
    #[arg(long, default_value_t = 600.0)]
    timeout: f64,
    #[command(flatten)]
    backend: BackendArgs,
}

pub fn run(a: Args) -> Result<()> {
    let dir = &a.recording;
    let done = insitu_recording::rebuild::rebuild(dir)
        .with_context(|| format!("rebuilding the index of {}", dir.display()))?;
    for (from, to) in &done.set_aside {
        println!("kept the damaged {from} as {to}");
    }
    println!(
        "rebuilt {} rows from the files of {} ({} with reference frames, {} steps of several ranks)",
        done.rows,
        dir.display(),
        done.with_references,
        done.multi_rank_steps
    );
    for (file, why) in &done.left_out {
        println!("left out {file}: {why}");
    }
    let todo = insitu_recording::store::Recording::open(dir)?.recover()?;
    let work = todo.unscored.len() + todo.uncomposed.len();
    if a.no_score || work == 0 {
        if work > 0 {
            println!(
                "{} steps to score and {} to compose when a viz-node next starts on it",
                todo.unscored.len(),
                todo.uncomposed.len()
            );
        }
        return Ok(());
    }
    tokio::runtime::Runtime::new()?.block_on(score(&a, todo))
}

/// Scores and composes what the rebuilt index lacks on a viz-node in this process (loopback,
/// no viewer), waiting until its recovery finds nothing left.
async fn score(a: &Args, todo: insitu_recording::store::Recovery) -> Result<()> {
    println!(
        "scoring {} steps and composing {} ...",
        todo.unscored.len(),
        todo.uncomposed.len()
    );
    let t0 = Instant::now();
    let viz = insitu_viz_node::start(insitu_viz_node::Config {
        listen: SocketAddr::from(([127, 0, 0, 1], 0)),
        recording_dir: a.recording.clone(),
        backend: a.backend.backend,
        ..Default::default()
    })
    .await
    .context("starting a viz-node on the recording")?;
    // Polled with the read-only query: `recover` removes temporary files, which would be
    // the viz-node's compositions in flight.
    let left = loop {
        let r = viz.shared().recording.left_to_do();
        let left = r.unscored.len() + r.uncomposed.len();
        if left == 0 || t0.elapsed().as_secs_f64() > a.timeout {
            break left;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    };
    viz.shutdown().await;
    if left > 0 {
        anyhow::bail!(
            "{left} steps still unscored or uncomposed after {} s; the viz-node's next start goes on with them",
            a.timeout
        );
    }
    println!("done in {:.1} s", t0.elapsed().as_secs_f64());
    Ok(())
}
