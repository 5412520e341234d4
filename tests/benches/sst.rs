//! Ingest throughput of an ADIOS2 SST stream into a generator-node, beside our own client's
//! push of the same steps: 256³ float32 steps (64 MiB), written by ADIOS2's Python API (the
//! PyPI wheel, `tests/scripts/adios2_writer.py --synthetic`) over SST on loopback and read by a
//! generator-node in this process (its ADIOS2 input), then pushed through the Rust client to a
//! node alike. The nodes do no work beyond taking the step (r = 1, no references, the
//! latest-only queue of one), so the figure is the transport's and the node's reading. GB/s
//! over the steps after the first, timed at the node (its count of received steps).
//!
//! `ADIOS2_DIR=… cargo bench -p insitu-e2e --features adios2 --bench sst`; the Python with
//! the wheel comes from `scripts/write-fixtures.sh` (`target/fixtures-venv`).

#![allow(clippy::unwrap_used, clippy::expect_used)]

use insitu_client::{SimClient, Step};
use insitu_core::BackendChoice;
use insitu_e2e::rt;
use insitu_generator_node::config::{Adios2Input, GenerationConfig};
use insitu_generator_node::{start, Config, Policy, RunningNode};
use std::net::SocketAddr;
use std::path::Path;
use std::time::{Duration, Instant};

/// Grid side and steps (the first is not timed).
const N: usize = 256;
const STEPS: u64 = 17;

fn ingest_config(adios2: Option<Adios2Input>) -> Config {
    let mut cfg = Config {
        listen: SocketAddr::from(([127, 0, 0, 1], 0)),
        backend: BackendChoice::Cpu,
        generation: GenerationConfig {
            resolution: 1,
            reference_every: 0,
            ..GenerationConfig::default()
        },
        adios2,
        ..Config::default()
    };
    cfg.queue.policy = Policy::LatestOnly;
    cfg.queue.max_items = 1;
    cfg
}

/// Seconds from the node's first received step to its `STEPS`-th.
fn timed_at_node(node: &RunningNode, limit: Duration) -> f64 {
    let stats = &node.shared().stats;
    let deadline = Instant::now() + limit;
    while stats.get().received < 1 {
        assert!(Instant::now() < deadline, "no step arrived");
        std::thread::sleep(Duration::from_micros(200));
    }
    let first = Instant::now();
    while stats.get().received < STEPS {
        assert!(
            Instant::now() < deadline,
            "{} of {STEPS} steps arrived",
            stats.get().received
        );
        std::thread::sleep(Duration::from_micros(200));
    }
    first.elapsed().as_secs_f64()
}

fn report(what: &str, secs: f64) {
    let bytes = (N * N * N * 4) as f64;
    let n = (STEPS - 1) as f64;
    println!(
        "ingest ({what}): {n:.0} steps of {:.0} MiB in {secs:.2} s = {:.2} GB/s",
        bytes / (1 << 20) as f64,
        n * bytes / secs / 1e9
    );
}

fn sst(python: &Path, tmp: &Path, params: &[&str]) {
    static RUNS: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
    let run = RUNS.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let stream = tmp.join(format!("bench-{run}"));
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/adios2_writer.py");
    let n = N.to_string();
    let mut writer = std::process::Command::new(python)
        .arg(script)
        .arg(&stream)
        .arg(tmp)
        .args([&n, &n, &n, &STEPS.to_string()])
        .args(["--synthetic", "--blocks", "1"])
        .args(params.iter().flat_map(|p| ["--param", p]))
        .stdout(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let mut input = Adios2Input::new(stream);
    input.open_timeout_secs = 60.0;
    let runtime = rt();
    let node = runtime.block_on(start(ingest_config(Some(input)))).unwrap();
    let secs = timed_at_node(&node, Duration::from_secs(300));
    assert!(writer.wait().unwrap().success(), "the writer failed");
    runtime.block_on(node.shutdown());
    report(&format!("ADIOS2 SST, one writer block {params:?}"), secs);
}

fn client() {
    let runtime = rt();
    let node = runtime.block_on(start(ingest_config(None))).unwrap();
    let field: Vec<f32> = (0..N * N * N).map(|i| (i % 977) as f32).collect();
    let addr = node.local_addr().to_string();
    // The client on a runtime of its own, as a simulation's process would have.
    let pushing = std::thread::spawn(move || {
        rt().block_on(async {
            let mut c = SimClient::connect(&addr, None).await.unwrap();
            c.set_shared_memory(false);
            for k in 0..STEPS {
                c.push_step(Step::whole_f32(k, k as f64, [N as u32; 3], &field))
                    .await
                    .unwrap();
            }
        });
    });
    let secs = timed_at_node(&node, Duration::from_secs(300));
    pushing.join().unwrap();
    runtime.block_on(node.shutdown());
    report("Rust client, streamed", secs);
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    // One SST measurement in a process of its own, as a generator-node reads one stream in its
    // life (EVPath keeps state per process).
    if let Some(i) = args.iter().position(|a| a == "--sst-child") {
        let python = std::path::PathBuf::from(&args[i + 1]);
        let params: Vec<&str> = args[i + 2..].iter().map(String::as_str).collect();
        let tmp = tempfile::tempdir().unwrap();
        sst(&python, tmp.path(), &params);
        return;
    }
    // `cargo bench` passes --bench; `cargo test --benches` passes nothing: run only for bench.
    if !args.iter().any(|a| a == "--bench") {
        return;
    }
    let Some(python) = insitu_testenv::fixture_python() else {
        println!("ingest (ADIOS2 SST): skipped, run scripts/write-fixtures.sh");
        return;
    };
    // SST's data plane over TCP: EVPath's sockets (the default) and ENet; each beside a push.
    for _ in 0..2 {
        for params in [&[][..], &["WANDataTransport=enet"][..]] {
            let out = std::process::Command::new(std::env::current_exe().unwrap())
                .arg("--sst-child")
                .arg(&python)
                .args(params)
                .output()
                .unwrap();
            print!("{}", insitu_e2e::succeeded("the SST measurement", out));
        }
        client();
    }
}
