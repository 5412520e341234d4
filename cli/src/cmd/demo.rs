//! `insitu demo`: the project's main job on an embedded default. The built-in Gray–Scott
//! simulation pushes every k-th step through the simulation client to a generator-node, which
//! ships compressed VDIs (and, on sampled steps, reference frames) to a viz-node, while a tuner
//! re-optimises P_M live over the characteristic steps (unless `--no-tune`); all run in this
//! process on 127.0.0.1 with ephemeral ports. One line per stored VDI and per P_M change, then
//! a summary.

use crate::pipeline::{Defaults, LocalNodes, PipelineArgs};
use anyhow::{bail, Result};
use insitu_client::Step;
use insitu_core::vdi::codec::Codec;
use insitu_core::volume::{GrayScott, GrayScottParams};
use std::sync::Arc;
use std::time::Instant;

/// The demo's defaults. Budget: the Gray–Scott VDIs at the default P_M (r = 256, γ = 0.013)
/// are 3–6 MB once the pattern fills the box, so 1 MB per step makes the tuner work. Codec:
/// zstd, whose σ is within a few per cent of bzip2's on these fields at a tenth of the time,
/// so that the generator-node keeps up with the simulation and has time for the trials
/// (`--codec bzip2` for the paper's σ: then compression is the bottleneck and the simulation
/// waits for it).
pub const DEFAULTS: Defaults = Defaults {
    utility: "size:1MB",
    codec: Codec::Zstd,
};

#[derive(clap::Args, Debug)]
pub struct Args {
    /// Gray–Scott grid side N (N³ cells).
    #[arg(long, default_value_t = 64)]
    size: usize,
    /// Simulation steps to run before the first push (lets the pattern fill the box, so the
    /// first characteristic step is like the ones that follow).
    #[arg(long, default_value_t = 2000)]
    warmup: u64,
    /// Push every k-th simulation step.
    #[arg(long, default_value_t = 100)]
    every: u64,
    /// Time steps to push.
    #[arg(long, default_value_t = 40)]
    pushes: u64,
    /// Ship reference frames (and so report q) on every m-th pushed step: those whose step
    /// number is a multiple of m × --every.
    #[arg(long, default_value_t = 5)]
    sample_every: u64,
    #[command(flatten)]
    pipeline: PipelineArgs,
}

pub fn run(a: Args) -> Result<()> {
    if a.every == 0 || a.pushes == 0 || a.sample_every == 0 {
        bail!("--every, --pushes and --sample-every must be ≥ 1");
    }
    let rt = tokio::runtime::Runtime::new()?;
    rt.block_on(demo(a))
}

async fn demo(a: Args) -> Result<()> {
    let started = Instant::now();
    let mut sim = GrayScott::new(a.size, GrayScottParams::default())?;
    // The simulation's own threads, as a simulation in its own process has (the
    // generator-node has its pool: `LocalNodes::start`). On rayon's global pool, shared with
    // the generator-node, a generation's jobs queued behind the simulation's, and τ counted
    // the simulation's time (3–5× the generation's own on 2 cores; docs/demo.md).
    // The pools still share the cores, as an in situ run does.
    let sim_pool = Arc::new(
        rayon::ThreadPoolBuilder::new()
            .thread_name(|i| format!("simulate-{i}"))
            .build()?,
    );
    let reference_every = a.every * a.sample_every;
    let nodes = LocalNodes::start(&a.pipeline, DEFAULTS, |c| {
        c.generation.reference_every = reference_every;
        // Small frames keep the demo quick; the VDI itself is r × r.
        c.generation.reference_size = a.pipeline.pm.r.min(256);
    })
    .await?;
    let say = |line: String| {
        if a.pipeline.json {
            eprintln!("{line}");
        } else {
            println!("{line}");
        }
    };
    say(format!(
        "demo: Gray–Scott {n}³, push every {} steps after {} warm-up steps, {} pushes; generator-node {}, viz-node {}",
        a.every,
        a.warmup,
        a.pushes,
        nodes.generator.local_addr(),
        nodes.viz.local_addr(),
        n = a.size,
    ));
    say(format!(
        "generating on {}{}",
        nodes.generator.shared().backend.describe(),
        nodes.tuner.as_ref().map_or_else(
            || "; P_M fixed (--no-tune)".to_owned(),
            |t| format!(
                "; tuner {} optimising {}",
                t.local_addr(),
                t.engine().utility_description()
            )
        )
    ));
    let printer = nodes.printer().await?;
    let mut client = nodes.generator_client().await?;
    let dims = [a.size as u32; 3];
    let mut sim_secs = 0.0;
    for k in 0..a.pushes {
        let steps = if k == 0 { a.warmup.max(1) } else { a.every };
        let t = Instant::now();
        let pool = Arc::clone(&sim_pool);
        let (s, field) = tokio::task::spawn_blocking(move || {
            pool.install(|| sim.advance(steps));
            let field: Vec<f32> = sim.v_volume().data().to_vec();
            (sim, field)
        })
        .await?;
        sim = s;
        sim_secs += t.elapsed().as_secs_f64();
        let index = sim.step_index();
        let step = Step::whole_f32_owned(
            index,
            index as f64 * GrayScottParams::default().dt,
            dims,
            field,
        );
        client.push_step(step).await?;
    }
    let status = crate::pipeline::flush_saying_why(client).await?;
    say(format!(
        "simulation compute time {sim_secs:.1} s (excluding pushes)"
    ));
    nodes.finish(printer, &status, a.pushes, started).await;
    Ok(())
}
