//! `insitu replay`: feeds a recorded time series (a NetCDF variable over time, a 4-D raw file,
//! or one volume of any format `insitu-readers` takes) through the simulation
//! client, as a simulation would, optionally split into a grid of bricks over several ranks. Without
//! `--generator` it starts a generator-node and a viz-node in this process (like the demo);
//! with it, it pushes to a running generator-node and sets its config first.

use crate::pipeline::{Defaults, LocalNodes, PipelineArgs};
use anyhow::{bail, Context, Result};
use insitu_client::{f32_bytes, Peer, ScalarType, SimClient, Step};
use insitu_core::vdi::codec::Codec;
use insitu_core::volume::bricks::{block_bricks, grid_bricks, split_ranks, Brick};
use insitu_core::{TransferFunction, Volume};
use insitu_proto::auth::Token;
use insitu_proto::pb;
use std::path::PathBuf;
use std::time::{Duration, Instant};

#[derive(clap::Args, Debug)]
pub struct Args {
    /// The series: a NetCDF or HDF5 file whose variable or dataset has a time dimension
    /// (`--var`, `--dataset`), an XDMF temporal collection, an ADIOS2 BP file or openPMD
    /// series (`run.bp5`, `run_%T.bp5`; feature `adios2`), a raw file
    /// `<name>_<X>x<Y>x<Z>x<T>_<type>.raw`, or any volume file (`.vti`, `.vtk`, `.nrrd`: one
    /// step); docs/data.md.
    #[arg(long)]
    series: PathBuf,
    /// The variable, array, dataset or attribute to push (default: the file's first volume).
    #[arg(long, visible_aliases = ["var", "dataset"])]
    field: Option<String>,
    /// How an uneven NetCDF axis is taken (`resample` or `index`; see `insitu render --help`).
    #[arg(long, value_enum, default_value_t = crate::scene::UnevenAxis::Resample)]
    uneven: crate::scene::UnevenAxis,
    /// Transfer function JSON. Default: a ramp over the first step's range (all ranks share it).
    #[arg(long)]
    tf: Option<PathBuf>,
    /// Split each step into this many bricks, one rank each, cut in x, y and z as evenly as
    /// the grid allows (like MPI_Dims_create); bricks share their boundary planes so that the
    /// ranks' boxes abut.
    #[arg(long, default_value_t = 1)]
    ranks: u32,
    /// Cut the grid SXxSYxSZ times instead (e.g. 2x2x1); --ranks must then be SX·SY·SZ or 1.
    #[arg(long, value_parser = parse_split)]
    split: Option<[usize; 3]>,
    /// Cut the bricks as one splits an array, each point in one brick and no plane shared
    /// (as ADIOS2 writers lay out blocks); the generator-node grows them by their
    /// neighbours' first planes before it makes them.
    #[arg(long)]
    blocks: bool,
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
    /// TLS for --generator.
    #[command(flatten)]
    tls: super::ClientTlsArgs,
    #[command(flatten)]
    pipeline: PipelineArgs,
}

/// A replay's defaults: the paper's σ (bzip2), and a tuner budget of 1 MB per step
/// (`--codec`, `--utility` to choose others).
pub const DEFAULTS: Defaults = Defaults {
    utility: "size:1MB",
    codec: Codec::Bzip2,
};

pub fn run(a: Args) -> Result<()> {
    if a.step_interval
        .is_some_and(|s| !(s.is_finite() && (0.0..=86_400.0).contains(&s)))
    {
        bail!("--step-interval must be seconds in [0, 86400]");
    }
    if a.tls.tls_ca.is_some() && a.generator.is_none() {
        bail!("--tls-ca is for --generator: local nodes started by replay speak clear text on loopback");
    }
    if a.pipeline.size_max.is_some() && a.generator.is_some() {
        bail!("--size-max is for the local nodes: a running generator-node takes generation.size_max from its config");
    }
    if a.pipeline.size_guard != insitu_generator_node::config::DEFAULT_SIZE_GUARD
        && a.generator.is_some()
    {
        bail!("--size-guard is for the local nodes: a running generator-node takes generation.size_guard from its config");
    }
    if a.pipeline.time_max.is_some() && a.generator.is_some() {
        bail!("--time-max is for the local nodes: a running generator-node takes generation.time_max from its config");
    }
    let data = crate::scene::open_dataset(&a.series, a.field.as_deref(), a.uneven)?;
    let bricks = bricks_for(&a, data.dims)?;
    tokio::runtime::Runtime::new()?.block_on(replay(a, data, bricks))
}

fn parse_split(s: &str) -> Result<[usize; 3], String> {
    let v: Vec<usize> = s
        .split('x')
        .map(|p| p.trim().parse::<usize>())
        .collect::<Result<_, _>>()
        .map_err(|e| format!("{s:?}: {e} (want SXxSYxSZ, e.g. 2x2x1)"))?;
    match v[..] {
        [x, y, z] if x * y * z >= 1 => Ok([x, y, z]),
        _ => Err(format!("{s:?}: want three factors ≥ 1, e.g. 2x2x1")),
    }
}

/// The bricks of `--ranks` / `--split` on a grid of `dims`.
fn bricks_for(a: &Args, dims: [usize; 3]) -> Result<Vec<Brick>> {
    let split = match a.split {
        Some(s) if a.ranks == 1 || a.ranks as usize == s.iter().product::<usize>() => s,
        Some(s) => bail!(
            "--split {}x{}x{} makes {} ranks, not --ranks {}",
            s[0],
            s[1],
            s[2],
            s.iter().product::<usize>(),
            a.ranks
        ),
        None => split_ranks(a.ranks as usize, dims).with_context(|| {
            format!(
                "--ranks {}: the grid {dims:?} cannot be cut into that many bricks of at least one cell",
                a.ranks
            )
        })?,
    };
    let cut = if a.blocks { block_bricks } else { grid_bricks };
    cut(dims, split).with_context(|| {
        format!(
            "--split {}x{}x{}: the grid {dims:?} has fewer cells than that on some axis",
            split[0], split[1], split[2]
        )
    })
}

fn brick_step(v: &Volume, step: u64, b: &Brick, rank: u32, world_size: u32) -> Result<Step> {
    let u = |d: [usize; 3]| d.map(|x| x as u32);
    let brick = v.brick(b)?;
    Ok(Step {
        step,
        sim_time: step as f64,
        dtype: ScalarType::F32,
        global_dims: u(v.dims()),
        brick_offset: u(b.offset),
        brick_dims: u(b.dims),
        rank,
        world_size,
        spacing: v.spacing().to_array(),
        // The file's origin: the whole grid's, which every brick is placed from.
        origin: v.origin().to_array(),
        data: f32_bytes(&brick.data()),
        fields: Vec::new(),
    })
}

async fn replay(a: Args, data: insitu_readers::Dataset, bricks: Vec<Brick>) -> Result<()> {
    let started = Instant::now();
    let first = data.read_step(0)?;
    let config = scene_config(&a, &first)?;
    let local = match &a.generator {
        Some(_) => None,
        None => Some(LocalNodes::start(&a.pipeline, DEFAULTS, |_| {}).await?),
    };
    // The local nodes' token when they are ours, else the one given for --generator.
    let token = match &local {
        Some(n) => n.token.clone(),
        None => Token::load(a.token_file.as_deref())?,
    };
    let addr = match (&a.generator, &local) {
        (Some(g), _) => g.clone(),
        (None, Some(n)) => n.generator_addr(),
        (None, None) => bail!("no generator-node"),
    };
    let tls = a.tls.files();
    let mut client =
        SimClient::connect_with(Peer::new(&addr, token, tls.client()?, false)?).await?;
    client.set_config(config).await?;
    let printer = match &local {
        Some(n) => Some(n.printer().await?),
        None => None,
    };
    let world_size = bricks.len() as u32;
    let line = format!(
        "replay: {} ({} steps, {:?}), {} rank(s), pushing to {addr}{}",
        a.series.display(),
        data.steps,
        data.dims,
        world_size,
        local
            .as_ref()
            .and_then(|n| n.tuner.as_ref())
            .map_or_else(String::new, |t| format!(
                "; tuner {} optimising {}",
                t.local_addr(),
                t.engine().utility_description()
            ))
    );
    if a.pipeline.json {
        eprintln!("{line}");
    } else {
        println!("{line}");
    }
    let pushed = push_series(&a, &data, &bricks, first, &mut client, local.is_none()).await?;
    let status = crate::pipeline::flush_saying_why(client).await?;
    match (local, printer) {
        (Some(nodes), Some(printer)) => nodes.finish(printer, &status, pushed, started).await,
        _ => print_flushed(a.pipeline.json, pushed, &status),
    }
    Ok(())
}

/// The generator-node's configuration for the series: `--tf` (else the default ramp over the
/// first step's range, which all ranks then share), P_M, codec and the reference frames' period.
fn scene_config(a: &Args, first: &Volume) -> Result<pb::GenerationConfig> {
    let (tf, tf_name) = match &a.tf {
        Some(p) => (
            TransferFunction::load(p)?,
            p.file_name()
                .map_or_else(String::new, |n| n.to_string_lossy().into_owned()),
        ),
        None => {
            let named = TransferFunction::default_for_volume(first);
            (named.tf, named.name)
        }
    };
    Ok(pb::GenerationConfig {
        resolution: a.pipeline.pm.r,
        gamma: a.pipeline.pm.gamma,
        codec: pb::Codec::from(a.pipeline.codec(DEFAULTS)) as i32,
        tf: Some(pb::TransferFunction::from(&tf)),
        tf_name: Some(tf_name),
        reference_every: Some(
            u32::try_from(a.sample_every).context("--sample-every is too large")?,
        ),
        ..Default::default()
    })
}

/// Pushes the series' steps (each split into `bricks`, one rank each), paced by
/// `--step-interval`; with `report` (no local nodes to report on the VDIs), says each push's
/// reply. Returns the pushes made.
async fn push_series(
    a: &Args,
    data: &insitu_readers::Dataset,
    bricks: &[Brick],
    first: Volume,
    client: &mut SimClient,
    report: bool,
) -> Result<u64> {
    let world_size = bricks.len() as u32;
    let mut pushed = 0;
    let mut next = Instant::now();
    for t in 0..a.steps.unwrap_or(data.steps).min(data.steps) {
        if let Some(secs) = a.step_interval {
            tokio::time::sleep_until(next.into()).await;
            next += Duration::from_secs_f64(secs);
        }
        let v = if t == 0 {
            first.clone()
        } else {
            data.read_step(t)?
        };
        for (rank, b) in bricks.iter().enumerate() {
            let reply = client
                .push_step(brick_step(&v, t as u64, b, rank as u32, world_size)?)
                .await?;
            pushed += 1;
            if report && a.pipeline.json {
                println!(
                    "{}",
                    serde_json::json!({"pushed": {"step": t, "rank": rank, "queue": reply.queue_depth, "dropped_by_push": reply.dropped_by_push}})
                );
            } else if report {
                println!(
                    "pushed step {t} rank {rank}: queue {}, dropped by this push {}",
                    reply.queue_depth, reply.dropped_by_push
                );
            }
        }
    }
    Ok(pushed)
}

/// The generator-node's counts after the last push, as JSON or text.
fn print_flushed(json: bool, pushed: u64, status: &pb::GeneratorStatus) {
    if json {
        println!(
            "{}",
            serde_json::json!({ "summary": crate::pipeline::counts_json(pushed, status) })
        );
        return;
    }
    println!(
        "flushed: received {}, generated {}, shipped {}, dropped {} (queue {}, outbox {}), failed {}; P_M version {}",
        status.steps_received,
        status.steps_generated,
        status.steps_shipped,
        status.dropped_queue + status.dropped_outbox,
        status.dropped_queue,
        status.dropped_outbox,
        status.failed,
        status.pm_version
    );
}

#[cfg(test)]
mod tests {
    use super::parse_split;

    #[test]
    fn splits_parse_and_bad_ones_say_why() {
        assert_eq!(parse_split("2x2x1"), Ok([2, 2, 1]));
        assert!(parse_split("2x2").is_err_and(|e| e.contains("three factors")));
        assert!(parse_split("0x1x1").is_err());
        assert!(parse_split("axbxc").is_err_and(|e| e.contains("SXxSYxSZ")));
    }
}
