//! `generator-node`: the daemon. Reads a TOML config (see `deploy/generator-node.toml`),
//! applies flag overrides, serves until SIGINT/SIGTERM, then drains and prints a summary.

use anyhow::Result;
use clap::Parser;
use insitu_generator_node::{start, Config, Policy};
use insitu_proto::daemon::{run_main, shutdown_signal, CommonArgs, DaemonConfig};
use std::path::PathBuf;

#[derive(Parser, Debug)]
#[command(
    name = "generator-node",
    version,
    about = "Makes VDIs beside a simulation and ships them to a viz-node",
    after_help = "Every config key is documented in deploy/generator-node.toml."
)]
struct Args {
    #[command(flatten)]
    common: CommonArgs,
    /// The viz-node, host:port.
    #[arg(long)]
    viz: Option<String>,
    /// The tuner service, host:port (the node dials out to it).
    #[arg(long)]
    tuner: Option<String>,
    /// Input queue policy: block, drop-oldest or latest-only.
    #[arg(long)]
    policy: Option<Policy>,
    /// Input queue length, steps.
    #[arg(long)]
    queue_steps: Option<usize>,
    /// VDI resolution r.
    #[arg(long)]
    resolution: Option<u32>,
    /// Interrupt threshold gamma.
    #[arg(long, allow_negative_numbers = true)]
    gamma: Option<f32>,
    /// bzip2, zstd or none.
    #[arg(long, value_parser = |s: &str| s.parse::<insitu_core::vdi::codec::Codec>())]
    codec: Option<insitu_core::vdi::codec::Codec>,
    /// Transfer function file.
    #[arg(long)]
    tf: Option<PathBuf>,
    /// Ship reference frames every k-th step (0 = never).
    #[arg(long)]
    reference_every: Option<u64>,
    /// Side of the reference frames, pixels (0 = the VDI resolution).
    #[arg(long)]
    reference_size: Option<u32>,
    /// The field to render from steps that carry named fields (default: each step's first).
    #[arg(long)]
    field: Option<String>,
    /// Where VDIs and references are made: cpu, gpu or auto (a hardware GPU if found, else
    /// the CPU).
    #[arg(long)]
    backend: Option<insitu_core::BackendChoice>,
    /// Read steps from this ADIOS2 stream (SST: the name the writer opened; or a `.bp` file)
    /// besides any pushes; the variable is `--field` (else the first 3-D global array).
    #[arg(long, value_name = "STREAM")]
    adios2: Option<PathBuf>,
    /// This node's part of the ADIOS2 array: `I/N`, part I of N nodes reading it (default
    /// 0/1, the whole array).
    #[arg(long, value_name = "I/N", requires = "adios2", value_parser = part)]
    adios2_part: Option<[u32; 2]>,
    /// Read the one block the ADIOS2 writer put in each step as it lies, as rank I of N
    /// (`--adios2-part`): a writer that opens a stream of its own; neighbours on other nodes
    /// exchange their planes through the viz-node.
    #[arg(long, requires = "adios2")]
    adios2_as_written: bool,
    /// CPU threads for generation, references and trials (0: one per core).
    #[arg(long)]
    threads: Option<usize>,
    /// Nice level of those threads, 0–19 (0: the process's own priority).
    #[arg(long)]
    nice: Option<i32>,
}

/// `I/N` as `[I, N]`.
fn part(s: &str) -> Result<[u32; 2], String> {
    let bad = || format!("{s:?}: a part is I/N, e.g. 0/2");
    let (i, n) = s.split_once('/').ok_or_else(bad)?;
    Ok([
        i.trim().parse().map_err(|_| bad())?,
        n.trim().parse().map_err(|_| bad())?,
    ])
}

fn config(a: Args) -> Result<Config> {
    let mut c: Config = a.common.config()?;
    if a.viz.is_some() {
        c.viz = a.viz;
    }
    if a.tuner.is_some() {
        c.tuner = a.tuner;
    }
    if let Some(v) = a.policy {
        c.queue.policy = v;
    }
    if let Some(v) = a.backend {
        c.backend = v;
    }
    if let Some(v) = a.threads {
        c.threads = v;
    }
    if let Some(v) = a.nice {
        c.nice = v;
    }
    if let Some(stream) = a.adios2 {
        let mut input = c
            .adios2
            .take()
            .unwrap_or_else(|| insitu_generator_node::config::Adios2Input::new(stream.clone()));
        input.stream = stream;
        if let Some(p) = a.adios2_part {
            input.part = p;
        }
        input.as_written |= a.adios2_as_written;
        c.adios2 = Some(input);
    }
    if let Some(v) = a.queue_steps {
        c.queue.max_items = v;
    }
    let g = &mut c.generation;
    if let Some(v) = a.resolution {
        g.resolution = v;
    }
    if let Some(v) = a.gamma {
        g.gamma = v;
    }
    if let Some(v) = a.codec {
        g.codec = v;
    }
    if a.tf.is_some() {
        g.tf = a.tf;
    }
    if let Some(v) = a.reference_every {
        g.reference_every = v;
    }
    if let Some(v) = a.reference_size {
        g.reference_size = v;
    }
    if a.field.is_some() {
        g.field = a.field;
    }
    c.validate()?;
    Ok(c)
}

/// The daemon's allocator: mimalloc instead of the C library's. Each 2 MiB chunk of a pushed
/// step passes through buffers that the C library's allocator handed back to the system and
/// faulted in again (page faults were, after the copies themselves, the largest item in a
/// profile of the ingest bench); mimalloc keeps and reuses them. 64 MiB pushes on loopback:
/// median 1.12 GB/s over ten runs against 0.94 over nine (`--bench pipeline -- ingest_rust`,
/// alternating builds); peak RSS 247–314 MiB against 229–249.
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn main() -> std::process::ExitCode {
    insitu_core::backend::quiet_vulkan_layers();
    run_main(async {
        let node = start(config(Args::parse())?).await?;
        // Scripts and tests read the actual address from this line.
        println!("listening on {}", node.local_addr());
        shutdown_signal().await;
        eprintln!("generator-node: shutting down, draining");
        let summary = node.shutdown().await;
        println!("summary: {summary}");
        anyhow::Ok(())
    })
}
