//! Many ranks on one machine (docs/scale.md): a Gray–Scott 256³ field cut in x, y and z into
//! 16, 64 or 256 bricks, each pushed by a rank (a task of this process with its own client,
//! as an MPI rank links one) to one of 1, 4 or 8 generator-nodes (processes, ranks placed in
//! blocks as MPI places them on hosts), which ship to one viz-node on loopback. Every run goes
//! twice: the nodes composing their ranks before shipping (two levels, the default) and
//! shipping each rank's VDI (one level, `[host] compose = false`).
//!
//! Steps go in lockstep, as a simulation's do: every rank pushes step s, then the bench waits
//! until the viz-node has stored and scored the composed step before the ranks push s + 1.
//! Per step it prints: the ranks' push time (median and slowest), τ (the slowest rank's
//! generation), the bytes that reached the viz-node (VDI files and reference frames), the
//! compose time at each level (the nodes' total, the viz-node's), and the latency from the
//! last push returning to the composed step stored and scored. Per run: the peak RSS of each
//! daemon, and the reduction in bytes into the viz-node.
//!
//! First it measures the constants of the scale model: bytes per supersegment, compose time
//! per supersegment at each level (64 sub-VDIs of the field, one level and 8 hosts of 8), the
//! viz-node's ingest of 1-rank VDIs over 8 streams (files written and fsync'd, index rows
//! committed), the index's rows per second alone, and the disk's fsync'd write speed.
//!
//! `cargo bench -p insitu-e2e --bench scale`. Environment: `INSITU_SCALE` a comma list of
//! RANKSxNODES runs (default `16x1,64x4,256x8,256x1`; empty: the constants alone), `INSITU_SCALE_STEPS` steps per run (3),
//! `INSITU_SCALE_R` the VDI resolution (256), `INSITU_SCALE_N` the grid side (256). The field
//! is simulated once and kept in `target/tmp/scale/`.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use insitu_client::{f32_bytes, ScalarType, SimClient, Step};
use insitu_core::compose::compose_vdis;
use insitu_core::vdi::codec::{encode, Codec};
use insitu_core::vdi::generate::generate;
use insitu_core::volume::bricks::{grid_bricks, split_ranks, Brick};
use insitu_core::volume::{GrayScott, GrayScottParams};
use insitu_core::{Camera, RaycastParams, Raycaster, TransferFunction, Vdi, VdiParams, Volume};
use insitu_e2e::{rt, start_viz, Daemon};
use insitu_recording::store::{Entry, StepEntry};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

fn env_or<T: std::str::FromStr>(key: &str, default: T) -> T {
    std::env::var(key)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

fn work_dir() -> PathBuf {
    let d = Path::new(env!("CARGO_TARGET_TMPDIR")).join("scale");
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// `steps` fields of Gray–Scott `n³` (V), 2000 steps in (the pattern fills most of the grid)
/// and 20 apart, cached on disk.
fn fields(n: usize, steps: usize) -> Vec<Vec<f32>> {
    let path = work_dir().join(format!("gray_scott_2000_{n}x{n}x{n}x{steps}_float32.raw"));
    let len = n * n * n;
    if !path.exists() {
        eprintln!("simulating Gray–Scott {n}³ (once) …");
        let mut sim = GrayScott::new(n, GrayScottParams::default()).unwrap();
        sim.advance(2000);
        let mut bytes = Vec::with_capacity(len * 4 * steps);
        for _ in 0..steps {
            bytes.extend(f32_bytes(&sim.v_volume().data()));
            sim.advance(20);
        }
        std::fs::write(&path, bytes).unwrap();
    }
    let bytes = std::fs::read(&path).unwrap();
    bytes
        .chunks_exact(len * 4)
        .map(|c| {
            c.chunks_exact(4)
                .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                .collect()
        })
        .collect()
}

/// Brick `b` of the `n³` field `f`, x fastest.
fn brick_of(f: &[f32], n: usize, b: &Brick) -> Vec<f32> {
    let mut out = Vec::with_capacity(b.dims.iter().product());
    for z in b.offset[2]..b.offset[2] + b.dims[2] {
        for y in b.offset[1]..b.offset[1] + b.dims[1] {
            let row = (z * n + y) * n + b.offset[0];
            out.extend_from_slice(&f[row..row + b.dims[0]]);
        }
    }
    out
}

fn node_config(viz: &str, tf: &Path, r: u32, ranks_here: usize, two_level: bool) -> String {
    format!(
        r#"listen = "127.0.0.1:0"
viz = "{viz}"
drain_timeout_secs = 60.0
[queue]
max_items = {queue}
max_bytes = 4294967296
policy = "block"
[outbox]
max_items = {queue}
max_bytes = 4294967296
policy = "block"
[generation]
resolution = {r}
gamma = 0.013
codec = "zstd"
reference_every = 1
reference_size = 128
view_angles_deg = [0.0, 60.0]
tf = "{tf}"
[host]
compose = {two_level}
"#,
        // Every rank's push is queued at once (a push returns when its step is queued).
        queue = ranks_here + 1,
        tf = tf.display(),
    )
}

/// One step's numbers.
struct StepRow {
    push_median: f64,
    push_max: f64,
    tau: f64,
    vdi_bytes: u64,
    frame_bytes: u64,
    host_compose: f64,
    viz_compose: f64,
    latency: f64,
    q: f64,
}

/// One run's numbers.
struct Run {
    label: String,
    steps: Vec<StepRow>,
    rss_nodes_max: f64,
    rss_viz: f64,
}

fn index(rec: &Path) -> (Vec<Entry>, Vec<StepEntry>) {
    insitu_recording::index::read(rec).unwrap_or_default()
}

fn host_compose_secs(rt: &tokio::runtime::Runtime, addrs: &[String]) -> f64 {
    rt.block_on(async {
        let mut sum = 0.0;
        for a in addrs {
            let mut c = SimClient::connect(a, None).await.unwrap();
            sum += c.status().await.unwrap().host_compose_secs;
        }
        sum
    })
}

/// The runs' transfer function: the default ramp over the first step's range.
fn tf_of(data: &[Vec<f32>]) -> TransferFunction {
    let (lo, hi) = data[0]
        .iter()
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(a, b), &v| {
            (a.min(v), b.max(v))
        });
    TransferFunction::default_named(lo, hi).tf
}

fn run(n: usize, r: u32, ranks: usize, nodes: usize, two_level: bool, data: &[Vec<f32>]) -> Run {
    let label = format!(
        "{ranks} ranks / {nodes} nodes, {}",
        if two_level { "two levels" } else { "one level" }
    );
    eprintln!("{label} …");
    let dir = tempfile::tempdir_in(work_dir()).unwrap();
    let rec = dir.path().join("rec");
    let tf_path = dir.path().join("tf.json");
    std::fs::write(&tf_path, serde_json::to_string(&tf_of(data)).unwrap()).unwrap();
    let global = [n; 3];
    let split = split_ranks(ranks, global).unwrap();
    let bricks = grid_bricks(global, split).unwrap();
    let viz = start_viz(&rec, "127.0.0.1:0", &[], dir.path());
    // Ranks in blocks, as MPI places them on hosts: rank k on node k·nodes/ranks.
    let node_of = |k: usize| k * nodes / ranks;
    let hosts: Vec<Daemon> = (0..nodes)
        .map(|h| {
            let here = (0..ranks).filter(|&k| node_of(k) == h).count();
            let cfg = node_config(&viz.addr, &tf_path, r, here, two_level);
            let path = dir.path().join(format!("node-{h}.toml"));
            std::fs::write(&path, cfg).unwrap();
            Daemon::start(
                "generator-node",
                &["--config", path.to_str().unwrap()],
                &[],
                dir.path(),
            )
        })
        .collect();
    let addrs: Vec<String> = hosts.iter().map(|h| h.addr.clone()).collect();
    // One runtime for the run: a client's connection lives on the runtime that made it.
    let rt = rt();
    let clients: Vec<Arc<tokio::sync::Mutex<SimClient>>> = rt.block_on(async {
        let mut out = Vec::new();
        for k in 0..ranks {
            let c = SimClient::connect(&addrs[node_of(k)], None).await.unwrap();
            out.push(Arc::new(tokio::sync::Mutex::new(c)));
        }
        out
    });
    let mut rows = Vec::new();
    let mut composed_before = 0.0;
    for (step, field) in data.iter().enumerate() {
        let pushes: Vec<(u32, Step)> = bricks
            .iter()
            .enumerate()
            .map(|(k, b)| {
                let d = |v: [usize; 3]| v.map(|x| x as u32);
                (
                    k as u32,
                    Step {
                        step: step as u64,
                        sim_time: step as f64,
                        dtype: ScalarType::F32,
                        global_dims: d(global),
                        brick_offset: d(b.offset),
                        brick_dims: d(b.dims),
                        rank: k as u32,
                        world_size: ranks as u32,
                        spacing: [1.0; 3],
                        origin: [0.0; 3],
                        data: f32_bytes(&brick_of(field, n, b)),
                        fields: Vec::new(),
                    },
                )
            })
            .collect();
        let times: Vec<f64> = rt.block_on(async {
            let tasks: Vec<_> = pushes
                .into_iter()
                .map(|(k, s)| {
                    let c = clients[k as usize].clone();
                    tokio::spawn(async move {
                        let t = Instant::now();
                        c.lock().await.push_step(s).await.unwrap();
                        t.elapsed().as_secs_f64()
                    })
                })
                .collect();
            let mut out = Vec::new();
            for t in tasks {
                out.push(t.await.unwrap());
            }
            out
        });
        let last_push = Instant::now();
        let stored = loop {
            let (_, steps) = index(&rec);
            if let Some(s) = steps
                .into_iter()
                .find(|s| s.step == step as u64 && s.quality.is_some())
            {
                break s;
            }
            assert!(
                last_push.elapsed() < Duration::from_secs(600),
                "{label}: step {step} not composed within 10 minutes"
            );
            std::thread::sleep(Duration::from_millis(10));
        };
        let latency = last_push.elapsed().as_secs_f64();
        let (entries, _) = index(&rec);
        let parts: Vec<&Entry> = entries.iter().filter(|e| e.step == step as u64).collect();
        let size = |name: &Option<String>| {
            name.as_ref()
                .and_then(|f| std::fs::metadata(rec.join(f)).ok())
                .map_or(0, |m| m.len())
        };
        let composed_now = host_compose_secs(&rt, &addrs);
        let mut sorted = times.clone();
        sorted.sort_by(f64::total_cmp);
        rows.push(StepRow {
            push_median: sorted[sorted.len() / 2],
            push_max: sorted[sorted.len() - 1],
            tau: stored.sizing.tau_secs,
            vdi_bytes: parts.iter().map(|e| e.sizing.sigma_bytes).sum(),
            frame_bytes: parts.iter().map(|e| size(&e.references)).sum(),
            host_compose: composed_now - composed_before,
            viz_compose: stored.compose_secs,
            latency,
            q: stored.quality.as_ref().map_or(f64::NAN, |q| q.q_db.0),
        });
        composed_before = composed_now;
    }
    drop(clients);
    let rss_nodes_max = hosts.iter().map(Daemon::peak_rss_mib).fold(0.0, f64::max);
    let rss_viz = viz.peak_rss_mib();
    for h in hosts {
        h.terminate();
    }
    viz.terminate();
    Run {
        label,
        steps: rows,
        rss_nodes_max,
        rss_viz,
    }
}

fn print(run: &Run) {
    println!("\n{}", run.label);
    println!(
        "{:>4} {:>9} {:>9} {:>7} {:>10} {:>11} {:>9} {:>9} {:>8} {:>7}",
        "step",
        "push med",
        "push max",
        "τ",
        "VDI MB",
        "frames MB",
        "host cmp",
        "viz cmp",
        "latency",
        "q dB"
    );
    for (s, r) in run.steps.iter().enumerate() {
        println!(
            "{s:>4} {:>8.3}s {:>8.3}s {:>6.3}s {:>10.2} {:>11.2} {:>8.3}s {:>8.3}s {:>7.2}s {:>7.2}",
            r.push_median,
            r.push_max,
            r.tau,
            r.vdi_bytes as f64 / 1e6,
            r.frame_bytes as f64 / 1e6,
            r.host_compose,
            r.viz_compose,
            r.latency,
            r.q
        );
    }
    println!(
        "peak RSS: generator-node (largest) {:.0} MiB, viz-node {:.0} MiB",
        run.rss_nodes_max, run.rss_viz
    );
}

fn bytes_in(run: &Run) -> f64 {
    run.steps
        .iter()
        .map(|s| (s.vdi_bytes + s.frame_bytes) as f64)
        .sum::<f64>()
        / run.steps.len() as f64
}

/// Sub-VDIs of `ranks` bricks of the `n³` field `f` at resolution `r` under `tf`.
fn sub_vdis(f: &[f32], n: usize, r: u32, ranks: usize, tf: &TransferFunction) -> Vec<Vdi> {
    let global = [n; 3];
    let whole = Volume::new(global, glam::Vec3::ONE, f.to_vec()).unwrap();
    let camera = Camera::default_for_box(&whole.world_box());
    let params = VdiParams {
        resolution: r,
        gamma: 0.013,
        precision: Default::default(),
    };
    grid_bricks(global, split_ranks(ranks, global).unwrap())
        .unwrap()
        .iter()
        .map(|b| {
            let brick = whole.brick(b).unwrap();
            let rc = Raycaster::new(&brick, tf, RaycastParams::default()).unwrap();
            generate(&rc, &camera, params, tf.identity_hash(), "scale").unwrap()
        })
        .collect()
}

/// The constants of the scale model (docs/scale.md), printed.
fn constants(data: &[Vec<f32>], n: usize, r: u32) {
    println!("\nconstants (Gray–Scott {n}³, r {r}, zstd)");
    let parts = sub_vdis(&data[0], n, r, 64, &tf_of(data));
    let refs: Vec<&Vdi> = parts.iter().collect();
    let supersegments: usize = parts.iter().map(|v| v.supersegments().len()).sum();
    let best_of = |mut work: Box<dyn FnMut() -> Vdi>| {
        (0..5)
            .map(|_| {
                let t = Instant::now();
                std::hint::black_box(work());
                t.elapsed().as_secs_f64()
            })
            .fold(f64::INFINITY, f64::min)
    };
    let one = best_of(Box::new(|| compose_vdis(&refs).unwrap()));
    let hosts: Vec<Vdi> = refs.chunks(8).map(|h| compose_vdis(h).unwrap()).collect();
    let host = best_of(Box::new(|| compose_vdis(&refs[..8]).unwrap())) * 8.0;
    let host_refs: Vec<&Vdi> = hosts.iter().collect();
    let top = best_of(Box::new(|| compose_vdis(&host_refs).unwrap()));
    let composed = compose_vdis(&refs).unwrap();
    let file = encode(&composed, Codec::Zstd).unwrap();
    let encode_secs = (0..5)
        .map(|_| {
            let t = Instant::now();
            std::hint::black_box(encode(&composed, Codec::Zstd).unwrap());
            t.elapsed().as_secs_f64()
        })
        .fold(f64::INFINITY, f64::min);
    let per_rank: usize = parts
        .iter()
        .map(|v| encode(v, Codec::Zstd).unwrap().len())
        .sum();
    let per_host: usize = hosts
        .iter()
        .map(|v| encode(v, Codec::Zstd).unwrap().len())
        .sum();
    let ns = |secs: f64| secs * 1e9 / supersegments as f64;
    println!(
        "  {supersegments} supersegments in 64 sub-VDIs: {:.2} B each in the composed file ({} B); the 64 files {} B, 8 host parts {} B",
        file.len() as f64 / supersegments as f64,
        file.len(),
        per_rank,
        per_host
    );
    println!(
        "  zstd encoding of the composed VDI ({:.2} MB in memory): {:.1} ms, {:.0} MB/s of file",
        composed.memory_bytes() as f64 / 1e6,
        encode_secs * 1e3,
        file.len() as f64 / encode_secs / 1e6
    );
    println!(
        "  compose, one level (64 parts): {:.1} ms, {:.1} ns per supersegment; hosts (8 × 8): {:.1} ms in all, {:.1} ns; viz-node over 8 host parts: {:.1} ms, {:.1} ns",
        one * 1e3,
        ns(one),
        host * 1e3,
        ns(host),
        top * 1e3,
        ns(top)
    );
    ingest();
}

/// The viz-node's ingest of 256 one-rank VDIs of about 1 MB over 8 streams, the index's rows
/// per second alone, and the disk's fsync'd writes, printed.
fn ingest() {
    use insitu_proto::pb::viz_client::VizClient;
    use insitu_proto::{chunk, pb, transport};
    let dir = tempfile::tempdir_in(work_dir()).unwrap();
    // About 1 MB: a 96³ blob field's VDI at r 512, stored uncompressed.
    let v = Volume::from_fn([96; 3], |x, y, z| {
        let d = [x, y, z].map(|c| c as f32 - 48.0);
        (1.0 - (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt() / 40.0).max(0.0)
    })
    .unwrap();
    let tf = TransferFunction::default_named(0.0, 1.0).tf;
    let rc = Raycaster::new(&v, &tf, RaycastParams::default()).unwrap();
    let params = VdiParams {
        resolution: 512,
        gamma: 0.05,
        precision: Default::default(),
    };
    let vdi = generate(
        &rc,
        &Camera::default_for_box(&v.world_box()),
        params,
        tf.identity_hash(),
        "ingest",
    )
    .unwrap();
    let file = bytes::Bytes::from(encode(&vdi, Codec::None).unwrap());
    let (count, streams) = (256usize, 8usize);
    let viz = start_viz(&dir.path().join("rec"), "127.0.0.1:0", &[], dir.path());
    let rt = rt();
    let secs = rt.block_on(async {
        let channel = transport::connect(&transport::uri(&viz.addr))
            .await
            .unwrap();
        let t = Instant::now();
        let tasks: Vec<_> = (0..streams)
            .map(|s| {
                let mut c = VizClient::new(channel.clone())
                    .max_encoding_message_size(transport::MAX_MESSAGE_BYTES);
                let file = file.clone();
                tokio::spawn(async move {
                    for step in (s..count).step_by(streams) {
                        let header = pb::VdiHeader {
                            step: step as u64,
                            world_size: 1,
                            resolution: 512,
                            gamma: 0.05,
                            codec: pb::Codec::None as i32,
                            total_bytes: file.len() as u64,
                            ..Default::default()
                        };
                        let msgs = chunk::split::<pb::VdiChunk>(header, file.clone());
                        c.ship_vdi(tokio_stream::iter(msgs)).await.unwrap();
                    }
                })
            })
            .collect();
        for t in tasks {
            t.await.unwrap();
        }
        t.elapsed().as_secs_f64()
    });
    viz.terminate();
    let bytes = (count * file.len()) as f64;
    println!(
        "  viz-node ingest: {count} VDIs of {:.2} MB over {streams} streams in {secs:.2} s: {:.2} GB/s, {:.0} rows/s",
        file.len() as f64 / 1e6,
        bytes / secs / 1e9,
        count as f64 / secs
    );
    let db = insitu_recording::index::IndexDb::open(dir.path(), true).unwrap();
    let rows = 2000u64;
    let t = Instant::now();
    for k in 0..rows {
        db.put_entry(&Entry::empty(k, 0)).unwrap();
    }
    println!(
        "  index alone: {:.0} rows/s (one committed transaction per row, synchronous = FULL)",
        rows as f64 / t.elapsed().as_secs_f64()
    );
    let block = vec![7u8; 64 << 20];
    let t = Instant::now();
    for k in 0..4 {
        insitu_core::file::write_atomic(
            &dir.path().join(format!("block-{k}")),
            &block,
            insitu_core::file::Durability::PowerLoss,
        )
        .unwrap();
    }
    println!(
        "  disk: 4 × 64 MiB written and fsync'd at {:.2} GB/s",
        4.0 * block.len() as f64 / t.elapsed().as_secs_f64() / 1e9
    );
}

fn main() {
    let n: usize = env_or("INSITU_SCALE_N", 256);
    let r: u32 = env_or("INSITU_SCALE_R", 256);
    let steps: usize = env_or("INSITU_SCALE_STEPS", 3);
    let runs: String = env_or("INSITU_SCALE", "16x1,64x4,256x8,256x1".to_owned());
    insitu_e2e::ensure_built();
    let data = fields(n, steps);
    constants(&data, n, r);
    println!("Gray–Scott {n}³, r {r}, {steps} steps per run, reference frames 2 views of 128² every step");
    // INSITU_SCALE= (empty): the constants alone.
    for spec in runs.split(',').filter(|s| !s.is_empty()) {
        let (ranks, nodes) = spec
            .split_once('x')
            .map(|(a, b)| (a.parse::<usize>().unwrap(), b.parse::<usize>().unwrap()))
            .unwrap_or_else(|| panic!("INSITU_SCALE: {spec} is not RANKSxNODES"));
        let two = run(n, r, ranks, nodes, true, &data);
        let one = run(n, r, ranks, nodes, false, &data);
        print(&two);
        print(&one);
        let (b1, b2) = (bytes_in(&one), bytes_in(&two));
        println!(
            "{ranks} ranks / {nodes} nodes: {:.2} MB a step into the viz-node with two levels, {:.2} MB with one: {:.1}× less (ranks per node {})",
            b2 / 1e6,
            b1 / 1e6,
            b1 / b2,
            ranks / nodes
        );
    }
}
