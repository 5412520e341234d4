//! `insitu replay`: feeds a recorded time series (a 4-D raw file) through the simulation
//! client, as a simulation would, optionally split into z-bricks over several ranks. Without
//! `--generator` it starts a generator-node and a viz-node in this process (like the demo);
//! with it, it pushes to a running generator-node and sets its config first.

use crate::pipeline::{Defaults, LocalNodes, PipelineArgs};
use anyhow::{bail, Context, Result};
use insitu_client::{f32_bytes, ScalarType, SimClient, Step};
use insitu_core::volume::RawFormat;
use insitu_core::{TransferFunction, Volume};
use insitu_proto::auth::Token;
use insitu_proto::convert::codec_to_pb;
use insitu_proto::pb;
use std::path::PathBuf;
use std::time::{Duration, Instant};

#[derive(clap::Args, Debug)]
pub struct Args {
    /// The series: `<name>_<X>x<Y>x<Z>x<T>_<type>.raw`.
    #[arg(long)]
    series: PathBuf,
    /// Transfer function JSON. Default: a ramp over the first step's range (all ranks share it).
    #[arg(long)]
    tf: Option<PathBuf>,
    /// Split each step into this many z-bricks, one rank each (bricks share their boundary
    /// plane so that the ranks' boxes abut).
    #[arg(long, default_value_t = 1)]
    ranks: u32,
    /// Replay only the first N steps (default: all).
    #[arg(long)]
    steps: Option<usize>,
    /// Ship reference frames (and so report q) on every m-th step (0 = never).
    #[arg(long, default_value_t = 1)]
    sample_every: u64,
    /// Pace the pushes like a simulation's step time: at most one step (all its ranks) every
    /// SECS seconds. Default: as fast as the pipeline takes them.
    #[arg(long)]
    step_interval: Option<f64>,
    /// Push to this running generator-node (host:port) instead of starting local nodes.
    #[arg(long)]
    generator: Option<String>,
    /// Bearer token file for --generator (else INSITU_TOKEN).
    #[arg(long)]
    token_file: Option<PathBuf>,
    #[command(flatten)]
    pipeline: PipelineArgs,
}

/// A replay's defaults: the paper's σ (bzip2), and a tuner budget of 1 MB per step
/// (`--codec`, `--utility` to choose others).
pub const DEFAULTS: Defaults = Defaults {
    utility: "size:1MB",
    codec: "bzip2",
};

pub fn run(a: Args) -> Result<()> {
    if a.step_interval
        .is_some_and(|s| !(s.is_finite() && (0.0..=86_400.0).contains(&s)))
    {
        bail!("--step-interval must be seconds in [0, 86400]");
    }
    let format = RawFormat::from_file_name(&a.series)?;
    if a.ranks == 0 || a.ranks as usize >= format.dims[2] {
        bail!(
            "--ranks {}: need 1 ≤ ranks < {} (the z size of {})",
            a.ranks,
            format.dims[2],
            a.series.display()
        );
    }
    tokio::runtime::Runtime::new()?.block_on(replay(a, format))
}

/// Splits `z ∈ [0, nz − 1]` into `ranks` bricks `[z0, z1]` (inclusive) that share boundary
/// planes, as even as integer planes allow.
pub fn z_bricks(nz: usize, ranks: usize) -> Vec<(usize, usize)> {
    (0..ranks)
        .map(|k| (k * (nz - 1) / ranks, (k + 1) * (nz - 1) / ranks))
        .collect()
}

fn brick_step(v: &Volume, step: u64, z: (usize, usize), rank: u32, world_size: u32) -> Step {
    let [nx, ny, nz] = v.dims();
    let plane = nx * ny;
    let data = &v.data()[z.0 * plane..(z.1 + 1) * plane];
    let dims = [nx as u32, ny as u32, nz as u32];
    Step {
        step,
        sim_time: step as f64,
        dtype: ScalarType::F32,
        global_dims: dims,
        brick_offset: [0, 0, z.0 as u32],
        brick_dims: [nx as u32, ny as u32, (z.1 - z.0 + 1) as u32],
        rank,
        world_size,
        spacing: v.spacing().to_array(),
        data: f32_bytes(data),
    }
}

async fn replay(a: Args, format: RawFormat) -> Result<()> {
    let started = Instant::now();
    let load = |t: usize| format.load(&a.series, t, glam::Vec3::ONE);
    let first = load(0)?;
    let (tf, tf_name) = match &a.tf {
        Some(p) => (
            TransferFunction::load(p)?,
            p.file_name()
                .map_or_else(String::new, |n| n.to_string_lossy().into_owned()),
        ),
        None => {
            let (lo, hi) = first.finite_range().unwrap_or((0.0, 1.0));
            (
                TransferFunction::default_for_range(lo, hi),
                format!("default[{lo}, {hi}]"),
            )
        }
    };
    let config = pb::GenerationConfig {
        resolution: a.pipeline.pm.r,
        gamma: a.pipeline.pm.gamma,
        codec: codec_to_pb(a.pipeline.codec(DEFAULTS).parse()?) as i32,
        tf_json: Some(serde_json::to_string(&tf)?),
        tf_name: Some(tf_name),
        reference_every: Some(
            u32::try_from(a.sample_every).context("--sample-every is too large")?,
        ),
        ..Default::default()
    };
    let local = match &a.generator {
        Some(_) => None,
        None => Some(LocalNodes::start(&a.pipeline, DEFAULTS, |_| {}).await?),
    };
    let token = Token::load(a.token_file.as_deref())?;
    let addr = match (&a.generator, &local) {
        (Some(g), _) => g.clone(),
        (None, Some(n)) => n.generator_addr(),
        (None, None) => bail!("no generator-node"),
    };
    let mut client = SimClient::connect(&addr, token.as_ref()).await?;
    client.set_config(config).await?;
    let printer = match &local {
        Some(n) => Some(n.printer().await?),
        None => None,
    };
    let bricks = z_bricks(format.dims[2], a.ranks as usize);
    let line = format!(
        "replay: {} ({} steps, {:?}), {} rank(s), pushing to {addr}{}",
        a.series.display(),
        format.steps,
        format.dims,
        a.ranks,
        local
            .as_ref()
            .and_then(|n| n.tuner.as_ref())
            .map_or_else(String::new, |t| format!(
                "; tuner {} optimising {}",
                t.local_addr(),
                t.engine().utility()
            ))
    );
    if a.pipeline.json {
        eprintln!("{line}");
    } else {
        println!("{line}");
    }
    let mut pushed = 0;
    let mut next = Instant::now();
    for t in 0..a.steps.unwrap_or(format.steps).min(format.steps) {
        if let Some(secs) = a.step_interval {
            tokio::time::sleep_until(next.into()).await;
            next += Duration::from_secs_f64(secs);
        }
        let v = if t == 0 { first.clone() } else { load(t)? };
        for (rank, &z) in bricks.iter().enumerate() {
            let reply = client
                .push_step(brick_step(&v, t as u64, z, rank as u32, a.ranks))
                .await?;
            pushed += 1;
            if local.is_none() && a.pipeline.json {
                println!(
                    "{}",
                    serde_json::json!({"pushed": {"step": t, "rank": rank, "queue": reply.queue_depth, "dropped_by_push": reply.dropped_by_push}})
                );
            } else if local.is_none() {
                println!(
                    "pushed step {t} rank {rank}: queue {}, dropped by this push {}",
                    reply.queue_depth, reply.dropped_by_push
                );
            }
        }
    }
    let status = client.close(Duration::from_secs(600)).await?;
    match (local, printer) {
        (Some(nodes), Some(printer)) => nodes.finish(printer, &status, pushed, started).await,
        _ if a.pipeline.json => println!(
            "{}",
            serde_json::json!({ "summary": crate::pipeline::counts_json(pushed, &status) })
        ),
        _ => println!(
            "flushed: received {}, generated {}, shipped {}, dropped {} (queue {}, outbox {}), failed {}; P_M version {}",
            status.steps_received,
            status.steps_generated,
            status.steps_shipped,
            status.dropped_queue + status.dropped_outbox,
            status.dropped_queue,
            status.dropped_outbox,
            status.failed,
            status.pm_version
        ),
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::z_bricks;

    #[test]
    fn bricks_cover_the_grid_and_share_boundaries() {
        for (nz, ranks) in [(19, 1), (19, 2), (19, 4), (5, 4), (256, 3)] {
            let b = z_bricks(nz, ranks);
            assert_eq!(b.first().map(|f| f.0), Some(0));
            assert_eq!(b.last().map(|l| l.1), Some(nz - 1));
            assert!(b.windows(2).all(|w| w[0].1 == w[1].0));
            assert!(b.iter().all(|&(z0, z1)| z1 > z0), "{b:?}");
        }
    }
}
