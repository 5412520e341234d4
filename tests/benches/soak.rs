//! Soak: thousands of 64³ steps through both daemons, as real processes on
//! loopback, while either daemon is killed with SIGKILL every 1–3 s and restarted on the
//! same port. The generator-node has a durable spool and a fixed transfer function; the
//! simulation (this program) pushes each step until it is acknowledged, reconnecting after a
//! kill. At the end: steps acknowledged, stored, lost (acknowledged, never stored) and
//! refused as duplicates; resident memory of both daemons and the index's size over time.
//!
//! `cargo bench -p insitu-e2e --bench soak -- [STEPS] [SEED]` (default 2000 steps, seed 1).

#![allow(clippy::unwrap_used, clippy::expect_used)]

use insitu_client::{SimClient, Step};
use insitu_core::TransferFunction;
use insitu_e2e::{rt, wait_until, Daemon};
use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

const N: u32 = 64;
const REFERENCE_EVERY: u64 = 20;

/// xorshift64*: reproducible kill times without another dependency.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> f64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        (self.0.wrapping_mul(0x2545_f491_4f6c_dd1d) >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// A smooth 64³ field: a blob whose centre and width change with `step`.
fn field(step: u64) -> Vec<f32> {
    let t = step as f32 * 0.05;
    let (cx, cy, cz) = (32.0 + 12.0 * t.sin(), 32.0 + 8.0 * (0.7 * t).cos(), 32.0);
    let w = 60.0 + 30.0 * (0.3 * t).sin();
    let n = N as usize;
    (0..n * n * n)
        .map(|i| {
            let (x, y, z) = ((i % n) as f32, ((i / n) % n) as f32, (i / (n * n)) as f32);
            let d2 = (x - cx).powi(2) + (y - cy).powi(2) + (z - cz).powi(2);
            (-d2 / w).exp()
        })
        .collect()
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

fn file_len(p: &Path) -> u64 {
    std::fs::metadata(p).map_or(0, |m| m.len())
}

/// Index size on disk: the database and its write-ahead log, bytes.
fn index_bytes(rec: &Path) -> u64 {
    file_len(&rec.join("index.sqlite")) + file_len(&rec.join("index.sqlite-wal"))
}

struct Nodes {
    viz_cfg: PathBuf,
    gen_cfg: PathBuf,
    logs: PathBuf,
    viz: Option<Daemon>,
    gen: Option<Daemon>,
}

impl Nodes {
    fn start(&self, name: &str, cfg: &Path) -> Option<Daemon> {
        let c = cfg.to_str().unwrap();
        Some(Daemon::start(name, &["--config", c], &[], &self.logs))
    }

    fn start_viz(&mut self) {
        self.viz = self.start("viz-node", &self.viz_cfg);
    }

    fn start_gen(&mut self) {
        self.gen = self.start("generator-node", &self.gen_cfg);
    }
}

struct Sample {
    t: f64,
    acked: u64,
    gen_rss: f64,
    viz_rss: f64,
    index_bytes: u64,
}

fn main() {
    let free: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with("--"))
        .collect();
    let steps: u64 = free.first().and_then(|s| s.parse().ok()).unwrap_or(2000);
    let seed: u64 = free.get(1).and_then(|s| s.parse().ok()).unwrap_or(1);

    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path();
    let rec = d.join("rec");
    let (pv, pg) = (free_port(), free_port());
    let tf = d.join("tf.json");
    std::fs::write(
        &tf,
        serde_json::to_string(&TransferFunction::default_for_range(0.0, 1.0)).unwrap(),
    )
    .unwrap();
    let viz_cfg = d.join("viz.toml");
    std::fs::write(
        &viz_cfg,
        format!(
            "listen = \"127.0.0.1:{pv}\"\nrecording_dir = {:?}\nbackend = \"cpu\"\n",
            rec.to_str().unwrap()
        ),
    )
    .unwrap();
    let gen_cfg = d.join("gen.toml");
    std::fs::write(
        &gen_cfg,
        format!(
            r#"listen = "127.0.0.1:{pg}"
viz = "127.0.0.1:{pv}"
backend = "cpu"
max_backoff_secs = 0.5
drain_timeout_secs = 2.0
[queue]
max_items = 4
max_bytes = 1073741824
policy = "block"
[outbox]
max_items = 16
max_bytes = 1073741824
policy = "block"
[generation]
resolution = 128
gamma = 0.013
codec = "zstd"
tf = {:?}
reference_every = {REFERENCE_EVERY}
[spool]
dir = {:?}
durable = true
"#,
            tf.to_str().unwrap(),
            d.join("spool").to_str().unwrap()
        ),
    )
    .unwrap();
    let mut nodes = Nodes {
        viz_cfg,
        gen_cfg,
        logs: d.to_owned(),
        viz: None,
        gen: None,
    };
    nodes.start_viz();
    nodes.start_gen();
    let nodes = Arc::new(Mutex::new(nodes));
    let done = Arc::new(AtomicBool::new(false));
    let acked_count = Arc::new(AtomicU64::new(0));
    let t0 = Instant::now();
    println!(
        "soak: {steps} steps of {N}³ f32 (1 MiB), r 128, references every {REFERENCE_EVERY}th step, durable spool; SIGKILL of either daemon every 1–3 s (seed {seed})"
    );

    // Kills: either daemon, every 1–3 s, restarted at once on the same port.
    let killer = std::thread::spawn({
        let (nodes, done) = (nodes.clone(), done.clone());
        move || {
            let mut rng = Rng(seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1);
            let (mut viz_kills, mut gen_kills) = (0u32, 0u32);
            loop {
                let wait = Duration::from_secs_f64(1.0 + 2.0 * rng.next());
                let until = Instant::now() + wait;
                while Instant::now() < until {
                    if done.load(Ordering::Relaxed) {
                        return (viz_kills, gen_kills);
                    }
                    std::thread::sleep(Duration::from_millis(50));
                }
                let mut n = nodes.lock().unwrap();
                if rng.next() < 0.5 {
                    n.viz.take().unwrap().kill();
                    n.start_viz();
                    viz_kills += 1;
                } else {
                    n.gen.take().unwrap().kill();
                    n.start_gen();
                    gen_kills += 1;
                }
            }
        }
    });
    // Resident memory and index size every second.
    let sampler = std::thread::spawn({
        let (nodes, done, acked, rec) = (
            nodes.clone(),
            done.clone(),
            acked_count.clone(),
            rec.clone(),
        );
        move || {
            let mut samples = Vec::new();
            while !done.load(Ordering::Relaxed) {
                {
                    let n = nodes.lock().unwrap();
                    samples.push(Sample {
                        t: t0.elapsed().as_secs_f64(),
                        acked: acked.load(Ordering::Relaxed),
                        gen_rss: n.gen.as_ref().map_or(0.0, Daemon::rss_mib),
                        viz_rss: n.viz.as_ref().map_or(0.0, Daemon::rss_mib),
                        index_bytes: index_bytes(&rec),
                    });
                }
                std::thread::sleep(Duration::from_secs(1));
            }
            samples
        }
    });

    // The simulation: every step pushed until acknowledged.
    let gen_addr = format!("127.0.0.1:{pg}");
    let mut acked = BTreeSet::new();
    let mut retries = 0u64;
    rt().block_on(async {
        let mut client: Option<SimClient> = None;
        for s in 0..steps {
            let data = field(s);
            loop {
                if client.is_none() {
                    client = SimClient::connect(&gen_addr, None).await.ok();
                }
                let r = match client.as_mut() {
                    Some(c) => c
                        .push_step(Step::whole_f32(s, s as f64, [N; 3], &data))
                        .await
                        .map_err(|e| e.to_string()),
                    None => Err("unreachable".into()),
                };
                match r {
                    Ok(_) => {
                        acked.insert(s);
                        acked_count.store(acked.len() as u64, Ordering::Relaxed);
                        break;
                    }
                    Err(_) => {
                        retries += 1;
                        client = None;
                        tokio::time::sleep(Duration::from_millis(100)).await;
                    }
                }
            }
        }
    });
    let push_secs = t0.elapsed().as_secs_f64();
    done.store(true, Ordering::Relaxed);
    let (viz_kills, gen_kills) = killer.join().unwrap();
    let samples = sampler.join().unwrap();

    // Drain: flush until the (last) generator-node has shipped all it holds, then wait for
    // the viz-node to score the sampled steps.
    let flushed = rt().block_on(async {
        for _ in 0..60 {
            if let Ok(mut c) = SimClient::connect(&gen_addr, None).await {
                if c.flush(Duration::from_secs(30)).await.is_ok() {
                    return true;
                }
            }
            tokio::time::sleep(Duration::from_secs(1)).await;
        }
        false
    });
    let read = || insitu_recording::index::read(&rec).map_or_else(|_| Vec::new(), |(e, _)| e);
    let sampled = acked.iter().filter(|s| *s % REFERENCE_EVERY == 0).count();
    wait_until(120.0, || {
        read()
            .iter()
            .filter(|e| e.step % REFERENCE_EVERY == 0 && e.quality.is_some())
            .count()
            >= sampled
    });
    let entries = read();
    let stored: BTreeSet<u64> = entries.iter().map(|e| e.step).collect();
    let lost: Vec<u64> = acked.difference(&stored).copied().collect();
    let scored = entries
        .iter()
        .filter(|e| e.step % REFERENCE_EVERY == 0 && e.quality.is_some())
        .count();
    let log = |name: &str| {
        std::fs::read_dir(d)
            .unwrap()
            .filter_map(|e| e.ok())
            .filter(|e| e.file_name().to_string_lossy().starts_with(name))
            .map(|e| std::fs::read_to_string(e.path()).unwrap_or_default())
            .collect::<String>()
    };
    let refused_duplicates = log("viz-node").matches("AlreadyExists").count();
    let recovered_runs = log("generator-node")
        .matches("were not delivered: generating them again")
        .count();
    let final_index = index_bytes(&rec);
    {
        let mut n = nodes.lock().unwrap();
        if let Some(g) = n.gen.take() {
            g.terminate();
        }
        if let Some(v) = n.viz.take() {
            v.terminate();
        }
    }

    println!(
        "kills: viz-node {viz_kills}, generator-node {gen_kills} (restarts that requeued spooled steps: {recovered_runs}); push retries {retries}; pushing took {push_secs:.0} s; final flush {}",
        if flushed { "ok" } else { "FAILED" }
    );
    println!(
        "acknowledged {}, stored {}, lost {} {:?}, duplicated 0 by construction ((step, rank) is the key), retries refused as different bytes (ALREADY_EXISTS) {refused_duplicates}",
        acked.len(),
        stored.len(),
        lost.len(),
        &lost[..lost.len().min(10)]
    );
    println!("sampled steps scored: {scored} of {sampled}");
    let closed = index_bytes(&rec);
    println!(
        "index: {:.2} MiB live for {} rows (database + write-ahead log, which SQLite checkpoints every ~4 MiB); {:.2} MiB ({:.0} B/row) after the viz-node's clean shutdown",
        final_index as f64 / (1 << 20) as f64,
        entries.len(),
        closed as f64 / (1 << 20) as f64,
        closed as f64 / entries.len().max(1) as f64,
    );
    println!("   t/s  acked  gen RSS MiB  viz RSS MiB  index MiB");
    let every = (samples.len() / 20).max(1);
    for s in samples.iter().step_by(every) {
        println!(
            "{:6.0} {:6} {:12.0} {:12.0} {:10.2}",
            s.t,
            s.acked,
            s.gen_rss,
            s.viz_rss,
            s.index_bytes as f64 / (1 << 20) as f64
        );
    }
    let max = |f: fn(&Sample) -> f64| samples.iter().map(f).fold(0.0, f64::max);
    println!(
        "max RSS: generator-node {:.0} MiB, viz-node {:.0} MiB",
        max(|s| s.gen_rss),
        max(|s| s.viz_rss)
    );
    if !lost.is_empty() || !flushed {
        std::process::exit(1);
    }
}
