//! Pipeline benchmarks, with the daemons as real processes on loopback:
//!
//! 1. ingest: field data pushed through the client (a push returns once the step is queued),
//!    GB/s, for 64 MiB steps, with the Rust client (streamed, then through shared memory), the
//!    C client
//!    (`client-c/bench/push_throughput.c`, compiled with `cc` against `libinsitu.a`), the
//!    Fortran module (`client-c/fortran/bench/push_throughput.f90`, gfortran) and the Python
//!    package (`python/bench/push_throughput.py`, which also pushes a 1 GiB array once and
//!    reports how much the process's peak RSS grew: the zero-copy check);
//! 2. the simulation's time per step with a generator-node attached versus without
//!    (Gray–Scott 128³ and 256³, `INSITU_OVERHEAD_SIZES`, pushing every 10th step through
//!    shared memory, streamed, through shared memory to a node on one thread, and to a node
//!    below the simulation's priority), in alternating rounds (`INSITU_OVERHEAD_ROUNDS`,
//!    default 5): the median ratio and its range, and the node's lag behind the simulation;
//! 3. end-to-end latency from push to the viz-node's report of the stored VDI;
//! 4. the exchange of faces through the viz-node for bricks split across generator-nodes.
//!
//! `cargo bench -p insitu-e2e --bench pipeline [-- PART]` (only the parts whose name holds
//! `PART`: `ingest_rust`, `ingest_c`, `ingest_fortran`, `ingest_python`, `simulation_overhead`,
//! `latency`, `faces`). Numbers depend on
//! the cores the simulation and the generator-node share: on a 2-core machine they compete.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use insitu_client::{SimClient, Step};
use insitu_core::volume::{GrayScott, GrayScottParams};
use insitu_e2e::{rt, Daemon};
use insitu_proto::pb::viz_client::VizClient;
use insitu_proto::{pb, transport};
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio_stream::StreamExt;

fn generator(tmp: &std::path::Path, args: &[&str]) -> Daemon {
    let mut all = vec!["--listen", "127.0.0.1:0"];
    all.extend_from_slice(args);
    Daemon::start("generator-node", &all, &[], tmp)
}

/// A generator-node that takes pushes as fast as the transport brings them: r = 1 and no
/// references, so its work per step is converting the bytes; latest-only keeps memory bounded.
fn ingest_node(tmp: &std::path::Path) -> Daemon {
    generator(
        tmp,
        &[
            "--resolution",
            "1",
            "--reference-every",
            "0",
            "--policy",
            "latest-only",
            "--queue-steps",
            "1",
        ],
    )
}

fn ingest(tmp: &std::path::Path) {
    let g = ingest_node(tmp);
    let n = 256u32;
    let field: Vec<f32> = (0..n * n * n).map(|i| (i % 977) as f32).collect();
    let step = Step::whole_f32(0, 0.0, [n; 3], &field);
    let bytes = step.data.len() as f64;
    // Streamed (as from another host), then through shared memory (the default on one host).
    for shared_memory in [false, true] {
        let (secs, pushes) = rt().block_on(async {
            let mut c = SimClient::connect(&g.addr, None).await.unwrap();
            c.set_shared_memory(shared_memory);
            c.push_step(step.clone()).await.unwrap();
            let t = Instant::now();
            let pushes = 16;
            for k in 0..pushes {
                let mut s = step.clone();
                s.step = k + 1;
                c.push_step(s).await.unwrap();
            }
            (t.elapsed().as_secs_f64(), pushes)
        });
        println!(
            "ingest ({}): {pushes} pushes of {:.0} MiB in {secs:.2} s = {:.2} GB/s; generator-node RSS {:.0} MiB, peak {:.0} MiB, {} page faults",
            if shared_memory { "shared memory" } else { "streamed" },
            bytes / (1 << 20) as f64,
            pushes as f64 * bytes / secs / 1e9,
            g.rss_mib(),
            g.peak_rss_mib(),
            g.minor_faults()
        );
    }
    g.terminate();
}

fn ingest_c(tmp: &std::path::Path) {
    let exe = tmp.join("push_throughput");
    insitu_e2e::build_c(
        std::path::Path::new("cc"),
        "client-c/bench/push_throughput.c",
        &exe,
        &[],
    );
    ingest_with(tmp, &[exe.as_os_str()], &[]);
}

/// Runs `program` against an ingest node as `program ADDR 256 16 [extra]` and prints its
/// output.
fn ingest_with(tmp: &std::path::Path, program: &[&std::ffi::OsStr], extra: &[&str]) {
    let g = ingest_node(tmp);
    let out = std::process::Command::new(program[0])
        .args(&program[1..])
        .args([g.addr.as_str(), "256", "16"])
        .args(extra)
        .output()
        .unwrap();
    print!("{}", insitu_e2e::succeeded("the ingest client", out));
    g.terminate();
}

fn ingest_fortran(tmp: &std::path::Path) {
    let exe = tmp.join("push_throughput_f");
    insitu_e2e::build_fortran(
        std::path::Path::new("gfortran"),
        &[
            "client-c/fortran/insitu.f90",
            "client-c/fortran/bench/push_throughput.f90",
        ],
        &exe,
        &[],
    );
    ingest_with(tmp, &[exe.as_os_str()], &[]);
}

fn ingest_python(tmp: &std::path::Path) {
    let Some(python) = insitu_testenv::python_package() else {
        println!("ingest (Python client): skipped, run scripts/build-python.sh");
        return;
    };
    let script = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../python/bench/push_throughput.py"
    );
    ingest_with(
        tmp,
        &[python.as_os_str(), std::ffi::OsStr::new(script)],
        &["1024"],
    );
}

/// Rounds of each configuration in [`simulation_overhead`] (`INSITU_OVERHEAD_ROUNDS`, default 5).
fn overhead_rounds() -> usize {
    std::env::var("INSITU_OVERHEAD_ROUNDS")
        .ok()
        .and_then(|v| v.parse().ok())
        .filter(|&r| r >= 1)
        .unwrap_or(5)
}

/// Grid sides of [`simulation_overhead`] (`INSITU_OVERHEAD_SIZES`, comma-separated, default
/// `128,256`).
fn overhead_sizes() -> Vec<usize> {
    let sizes: Vec<usize> = std::env::var("INSITU_OVERHEAD_SIZES")
        .unwrap_or_default()
        .split(',')
        .filter_map(|s| s.trim().parse().ok())
        .filter(|&n| n >= 16)
        .collect();
    if sizes.is_empty() {
        vec![128, 256]
    } else {
        sizes
    }
}

/// Median, lowest and highest of `v` (not empty).
fn spread(mut v: Vec<f64>) -> (f64, f64, f64) {
    v.sort_by(f64::total_cmp);
    (v[v.len() / 2], v[0], v[v.len() - 1])
}

/// Step `k` of `sim`: its field V copied, as f32, into the simulation's staging buffer
/// (memory kept between pushes, given back by the client once a push returns) and sent from
/// there without another copy.
fn copied_out(sim: &GrayScott, k: u64, staging: &mut Arc<Vec<f32>>) -> Step {
    sim.copy_v_into(Arc::make_mut(staging));
    let n = sim.size() as u32;
    Step::whole_f32_shared(k, k as f64, [n; 3], staging.clone())
}

/// The simulation's time per step alone and with a generator-node attached, in rounds that
/// alternate the two (alone, attached, alone, …) so that whatever else the machine does
/// falls on both: each round's ratio is taken against the run alone just before it, and the
/// median ratio and its range over the rounds are printed. Four nodes stay up (idle, they cost
/// nothing) and take turns within each round: the default settings (threads = 0: a pool over
/// every core, which the simulation shares; nice 0), the client pushing through shared memory
/// (the default on one host); the same with the client kept to streaming, as from another
/// host; the node on one thread; and the node below the simulation's priority (nice 10). What
/// a lower priority costs is the node's lag: how long the last push's VDI took to come after
/// the simulation's last step (the flush), and the steps the queue dropped.
fn simulation_overhead(tmp: &std::path::Path) {
    let rounds = overhead_rounds();
    for n in overhead_sizes() {
        // A push every 10th step; a run of 200 steps at 128³, 60 at 256³ (a step of 256³
        // takes about 10× one of 128³: 6 s and 18 s a run on two cores).
        let (steps, every) = if n >= 256 { (60u64, 10u64) } else { (200, 10) };
        // Seconds per step, the simulation's own push calls per step, the flush's wait, the
        // node's dropped steps so far and the first (set-up) push's seconds.
        let run = |addr: Option<&str>, shared_memory: bool| {
            rt().block_on(async {
                let mut client = match addr {
                    Some(a) => {
                        let mut c = SimClient::connect(a, None).await.unwrap();
                        c.set_shared_memory(shared_memory);
                        Some(c)
                    }
                    None => None,
                };
                let mut sim = GrayScott::new(n, GrayScottParams::default()).unwrap();
                sim.advance(20);
                // The simulation's set-up: a first push of its initial state, waited for,
                // before the timing starts. It pays what a run pays once (the shared-memory
                // file's pages, the node's first field and VDI buffers), which in a 200-step
                // round would weigh as much as the steady pushes (reported apart).
                let (mut first, mut staging) = (0.0, Arc::new(Vec::new()));
                if let Some(c) = client.as_mut() {
                    let f = Instant::now();
                    c.push_step(copied_out(&sim, 0, &mut staging))
                        .await
                        .unwrap();
                    first = f.elapsed().as_secs_f64();
                    c.flush(Duration::from_secs(600)).await.unwrap();
                }
                let t = Instant::now();
                // The simulation's own part of a push: the copy out of its field and the call.
                let mut pushing = Duration::ZERO;
                for k in 1..=steps {
                    sim.advance(1);
                    if k % every == 0 {
                        if let Some(c) = client.as_mut() {
                            let p = Instant::now();
                            c.push_step(copied_out(&sim, k, &mut staging))
                                .await
                                .unwrap();
                            pushing += p.elapsed();
                        }
                    }
                }
                let secs = t.elapsed().as_secs_f64();
                let (mut lag, mut dropped) = (0.0, 0);
                if let Some(c) = client.as_mut() {
                    assert_eq!(
                        c.shared_memory(),
                        Some(shared_memory && insitu_client::shm::host_id().is_some())
                    );
                    let f = Instant::now();
                    let status = c.flush(Duration::from_secs(600)).await.unwrap();
                    lag = f.elapsed().as_secs_f64();
                    dropped = status.dropped_queue;
                }
                (
                    secs / steps as f64,
                    pushing.as_secs_f64() / steps as f64,
                    lag,
                    dropped,
                    first,
                )
            })
        };
        struct Setting {
            label: &'static str,
            node: Daemon,
            shared_memory: bool,
            alone: Vec<f64>,
            with: Vec<f64>,
            pushes: Vec<f64>,
            lags: Vec<f64>,
            firsts: Vec<f64>,
            dropped: u64,
        }
        let mut settings: Vec<Setting> = [
            (
                "default settings (threads = 0, nice 0), pushed through shared memory",
                "0",
                "0",
                true,
            ),
            ("threads = 0, nice 0, streamed", "0", "0", false),
            (
                "threads = 1, nice 0, pushed through shared memory",
                "1",
                "0",
                true,
            ),
            (
                "threads = 0, nice 10 (below the simulation), pushed through shared memory",
                "0",
                "10",
                true,
            ),
        ]
        .into_iter()
        .map(|(label, threads, nice, shared_memory)| Setting {
            label,
            node: generator(
                tmp,
                &[
                    "--resolution",
                    "256",
                    "--reference-every",
                    "0",
                    "--codec",
                    "zstd",
                    "--threads",
                    threads,
                    "--nice",
                    nice,
                ],
            ),
            shared_memory,
            alone: Vec::new(),
            with: Vec::new(),
            pushes: Vec::new(),
            lags: Vec::new(),
            firsts: Vec::new(),
            dropped: 0,
        })
        .collect();
        for _ in 0..rounds {
            for s in &mut settings {
                let (a, ..) = run(None, s.shared_memory);
                let (w, p, lag, dropped, first) = run(Some(&s.node.addr), s.shared_memory);
                s.alone.push(a);
                s.with.push(w);
                s.pushes.push(p);
                s.lags.push(lag);
                s.firsts.push(first);
                s.dropped = dropped;
            }
        }
        for s in settings {
            s.node.terminate();
            let added: Vec<f64> = s.with.iter().zip(&s.alone).map(|(w, a)| w - a).collect();
            let ratios: Vec<f64> = s.with.iter().zip(&s.alone).map(|(w, a)| w / a).collect();
            let (a, w, (r, lo, hi)) = (spread(s.alone).0, spread(s.with).0, spread(ratios));
            let (added, pushing, (lag, _, lag_max), first) = (
                spread(added).0,
                spread(s.pushes).0,
                spread(s.lags),
                spread(s.firsts).0,
            );
            println!(
                "simulation step, Gray–Scott {n}³, push every {every}th, {rounds} alternating rounds of {steps} steps, generator-node at r = 256, zstd, {}: median {:.2} ms alone, {:.2} ms with the node; ratio median {r:.3}× (range {lo:.3}–{hi:.3}×, aim ≤ 1.05×); added per step (median over rounds) {:.2} ms, the simulation's own copy and push calls {:.2} ms per step (the set-up push before the timing: {:.0} ms); the node's lag after the last step (flush) median {:.0} ms, max {:.0} ms; steps dropped {}",
                s.label,
                a * 1e3,
                w * 1e3,
                added * 1e3,
                pushing * 1e3,
                first * 1e3,
                lag * 1e3,
                lag_max * 1e3,
                s.dropped,
            );
        }
    }
}

fn latency(tmp: &std::path::Path) {
    let rec = tmp.join("rec");
    let v = insitu_e2e::start_viz(&rec, "127.0.0.1:0", &[], tmp);
    let g = generator(
        tmp,
        &[
            "--viz",
            &v.addr,
            "--resolution",
            "256",
            "--reference-every",
            "0",
            "--codec",
            "zstd",
        ],
    );
    let lat = rt().block_on(async {
        let channel = transport::connect(&transport::uri(&v.addr)).await.unwrap();
        let mut reports = VizClient::new(channel)
            .subscribe(pb::SubscribeRequest {})
            .await
            .unwrap()
            .into_inner();
        let mut c = SimClient::connect(&g.addr, None).await.unwrap();
        let mut sim = GrayScott::new(64, GrayScottParams::default()).unwrap();
        let mut lat = Vec::new();
        for k in 0..10u64 {
            sim.advance(100);
            let field = sim.v_volume().data().to_vec();
            let t = Instant::now();
            c.push_step(Step::whole_f32(k, 0.0, [64; 3], &field))
                .await
                .unwrap();
            let r = reports.next().await.unwrap().unwrap();
            assert_eq!(r.step, k);
            lat.push(t.elapsed().as_secs_f64());
        }
        lat
    });
    let mut sorted = lat.clone();
    sorted.sort_by(f64::total_cmp);
    println!(
        "latency push → stored VDI (Gray–Scott 64³, r = 256, zstd): median {:.1} ms, max {:.1} ms over {} steps",
        sorted[sorted.len() / 2] * 1e3,
        sorted[sorted.len() - 1] * 1e3,
        lat.len()
    );
    g.terminate();
    v.terminate();
}

/// 4. The exchange of faces across generator-nodes (`Viz.ExchangeFaces`) for a 256³ f32 field
///    split into z-halves without a shared plane: each step, two clients post at once as two
///    nodes would, the lower half's brick (it grows, and waits for the answer) and the upper
///    half's with its low face (256 × 256 f32, 256 KiB); the time until both answers.
fn faces_exchange(tmp: &std::path::Path) {
    let rec = tmp.join("rec-faces");
    let v = insitu_e2e::start_viz(&rec, "127.0.0.1:0", &[], tmp);
    let n = 256u32;
    let dims = |x, y, z| Some(pb::Dims3 { x, y, z });
    let half = |rank: u32| pb::BrickFaces {
        rank,
        offset: dims(0, 0, 128 * rank),
        dims: dims(n, n, 128),
        faces: if rank == 1 {
            vec![pb::Face {
                offset: dims(0, 0, 128),
                dims: dims(n, n, 1),
                dtype: pb::ScalarType::F32 as i32,
                values: vec![7u8; (n * n * 4) as usize].into(),
            }]
        } else {
            Vec::new()
        },
    };
    let times = rt().block_on(async {
        let channel = transport::connect(&transport::uri(&v.addr)).await.unwrap();
        let client = VizClient::new(channel)
            .max_decoding_message_size(transport::MAX_MESSAGE_BYTES)
            .max_encoding_message_size(transport::MAX_MESSAGE_BYTES);
        let mut times = Vec::new();
        for step in 0..40u64 {
            let offer = |rank: u32| pb::FacesOffer {
                step,
                world_size: 2,
                global_dims: dims(n, n, n),
                bricks: vec![half(rank)],
                wait_secs: 10.0,
            };
            let (mut a, mut b) = (client.clone(), client.clone());
            let t = Instant::now();
            let (lower, upper) =
                tokio::join!(a.exchange_faces(offer(0)), b.exchange_faces(offer(1)));
            let elapsed = t.elapsed().as_secs_f64();
            assert_eq!(lower.unwrap().into_inner().bricks.len(), 2);
            assert_eq!(upper.unwrap().into_inner().bricks.len(), 2);
            times.push(elapsed);
        }
        times
    });
    let mut sorted = times[5..].to_vec();
    sorted.sort_by(f64::total_cmp);
    println!(
        "exchange of faces, 256³ f32 in two z-halves (the upper half's 256 KiB face posted and relayed to the lower half): median {:.2} ms, max {:.2} ms over {} steps (after 5 warm-up)",
        sorted[sorted.len() / 2] * 1e3,
        sorted[sorted.len() - 1] * 1e3,
        sorted.len()
    );
    v.terminate();
}

/// One part of the benchmark, run in a temporary directory.
type Part = fn(&std::path::Path);

fn main() {
    // `cargo bench` passes --bench; `cargo test --benches` passes nothing: run only for bench.
    if !std::env::args().any(|a| a == "--bench") {
        return;
    }
    // `cargo bench -p insitu-e2e --bench pipeline -- ingest` runs the parts whose name holds
    // "ingest" only.
    let filter = std::env::args()
        .skip(1)
        .find(|a| !a.starts_with("--"))
        .unwrap_or_default();
    let tmp = tempfile::tempdir().unwrap();
    let parts: [(&str, Part); 7] = [
        ("ingest_rust", ingest),
        ("ingest_c", ingest_c),
        ("ingest_fortran", ingest_fortran),
        ("ingest_python", ingest_python),
        ("simulation_overhead", simulation_overhead),
        ("latency", latency),
        ("faces", faces_exchange),
    ];
    for (name, part) in parts {
        if name.contains(&filter) {
            part(tmp.path());
        }
    }
}
