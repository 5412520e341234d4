//! What the tuner service costs and how fast it reacts, with the daemons
//! as real processes on loopback and the simulation in this process:
//!
//! - the trials' CPU time as a share of the run, counted where it is spent: the CPU time of
//!   the generator-node's compute pool while trials hold its lane (`TunerStatus.trial_cpu_secs`, the sum of the nodes'
//!   `TrialResult.trial_cpu_secs`) over the CPU time (user + system, from `/proc`) of the
//!   simulation and all daemons, and over the generator-node's; beside it, for context, the
//!   difference from the same run without a tuner (which also differs in what the P_M made);
//! - production step latency (push → the viz-node's report of the stored VDI, steps without
//!   reference frames) with and without the tuner;
//! - when the first P_M lands (after how many characteristic steps' worth of trials), and how
//!   many production steps ran on an outdated P_M after a change of character.
//!
//! Two runs each: the ocean series (12 steps, one per `INSITU_BENCH_STEP_SECS`, default 1 s,
//! as a simulation's step time) and Gray–Scott 128³ after `INSITU_BENCH_GS_WARMUP` steps
//! (default 1500; a push every 20 simulation steps, F/k switched half-way). `cargo bench -p insitu-e2e --bench tuning`;
//! `INSITU_BENCH_TRIAL_BURST` sets the tuner's `trials.burst_secs` (default 15).

#![allow(clippy::unwrap_used, clippy::expect_used)]

use insitu_client::{SimClient, Step};
use insitu_core::volume::{GrayScott, GrayScottParams, RawFormat};
use insitu_e2e::{ocean, rt, Daemon};
use insitu_proto::pb::tuner_client::TunerClient;
use insitu_proto::pb::viz_client::VizClient;
use insitu_proto::{pb, transport};
use std::collections::BTreeMap;
use std::path::Path;
use std::sync::{Arc, Mutex};

/// Stored VDIs by step, and (P_M version, latency) of the steps without references.
type Seen = (BTreeMap<u64, pb::QualityReport>, Vec<(u64, f64)>);
use std::time::{Duration, Instant};
use tokio_stream::StreamExt;

/// CPU seconds (user + system) of a process so far.
fn cpu_secs(pid: u32) -> f64 {
    let ticks = std::process::Command::new("getconf")
        .arg("CLK_TCK")
        .output()
        .ok()
        .and_then(|o| {
            String::from_utf8_lossy(&o.stdout)
                .trim()
                .parse::<f64>()
                .ok()
        })
        .unwrap_or(100.0);
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).unwrap_or_default();
    // Fields after the command name (which may hold spaces): state is field 3; utime 14, stime 15.
    let rest = stat.rsplit_once(") ").map_or("", |r| r.1);
    let f: Vec<f64> = rest
        .split_whitespace()
        .map(|x| x.parse().unwrap_or(0.0))
        .collect();
    (f.get(11).copied().unwrap_or(0.0) + f.get(12).copied().unwrap_or(0.0)) / ticks
}

/// The field source of a run.
enum Source {
    Ocean(std::path::PathBuf),
    /// A simulation already warmed up (cloned for each run), pushed every `every` steps.
    GrayScott {
        start: Box<GrayScott>,
        every: u64,
        pushes: usize,
    },
}

struct Outcome {
    cpu: f64,
    /// The generator-node's CPU seconds.
    node_cpu: f64,
    latencies: Vec<(u64, f64)>,
    stored: BTreeMap<u64, pb::QualityReport>,
    decisions: Vec<pb::PmDecision>,
    status: Option<pb::TunerStatus>,
    switch_step: Option<u64>,
    wall: f64,
}

fn start(name: &str, args: &[&str], tmp: &Path) -> Daemon {
    Daemon::start(name, args, &[], tmp)
}

fn run(
    source: &Source,
    utility: Option<&str>,
    tmp: &Path,
    sample_every: u32,
    codec: &str,
) -> Outcome {
    let rec = tmp.join(format!("rec-{}", utility.is_some()));
    let _ = std::fs::remove_dir_all(&rec);
    let v = insitu_e2e::start_viz(&rec, "127.0.0.1:0", &[], tmp);
    let tuner = utility.map(|u| {
        let state = tmp.join("tuner-state");
        let _ = std::fs::remove_dir_all(&state);
        // The trials' budget's burst (the knob that trades the first decision's latency for
        // the trials' CPU time): `INSITU_BENCH_TRIAL_BURST` seconds, else the tuner's default.
        let config = tmp.join("tuner.toml");
        let burst = std::env::var("INSITU_BENCH_TRIAL_BURST").ok();
        let trials = burst.map_or(String::new(), |b| format!("[trials]\nburst_secs = {b}\n"));
        std::fs::write(&config, trials).unwrap();
        start(
            "tuner-node",
            &[
                "--config",
                config.to_str().unwrap(),
                "--listen",
                "127.0.0.1:0",
                "--viz",
                &v.addr,
                "--utility",
                u,
                "--state-dir",
                state.to_str().unwrap(),
            ],
            tmp,
        )
    });
    let mut args = vec![
        "--listen",
        "127.0.0.1:0",
        "--viz",
        &v.addr,
        "--resolution",
        "256",
        "--codec",
        codec,
        "--backend",
        "cpu",
    ];
    let every = sample_every.to_string();
    // Fixed-size reference frames (as the demo): trials then render one set per step, not one
    // per candidate resolution.
    args.extend(["--reference-every", &every, "--reference-size", "256"]);
    if let Some(t) = &tuner {
        args.extend(["--tuner", &t.addr]);
    }
    let g = start("generator-node", &args, tmp);
    let step_secs: f64 = std::env::var("INSITU_BENCH_STEP_SECS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(1.0);
    let t0 = Instant::now();
    let self_cpu0 = cpu_secs(std::process::id());
    let (stored, latencies, switch_step) = rt().block_on(async {
        let channel = transport::connect(&transport::uri(&v.addr)).await.unwrap();
        let mut reports = VizClient::new(channel)
            .subscribe(pb::SubscribeRequest {})
            .await
            .unwrap()
            .into_inner();
        let pushed: Arc<Mutex<BTreeMap<u64, Instant>>> = Default::default();
        let seen: Arc<Mutex<Seen>> = Default::default();
        let (p, c) = (pushed.clone(), seen.clone());
        let collector = tokio::spawn(async move {
            while let Some(Ok(r)) = reports.next().await {
                let mut seen = c.lock().unwrap();
                if r.q_db.is_none() {
                    if let Some(t) = p.lock().unwrap().get(&r.step) {
                        seen.1.push((r.pm_version, t.elapsed().as_secs_f64()));
                    }
                }
                seen.0.insert(r.step, r);
            }
        });
        let mut c = SimClient::connect(&g.addr, None).await.unwrap();
        let mut switch_step = None;
        match source {
            Source::Ocean(path) => {
                let format = RawFormat::from_file_name(path).unwrap();
                let mut next = Instant::now();
                for t in 0..format.steps {
                    tokio::time::sleep_until(next.into()).await;
                    next += Duration::from_secs_f64(step_secs);
                    let vol = format.load(path, t, glam::Vec3::ONE).unwrap();
                    let d = vol.dims().map(|x| x as u32);
                    pushed.lock().unwrap().insert(t as u64, Instant::now());
                    c.push_step(Step::whole_f32(t as u64, t as f64, d, &vol.data()))
                        .await
                        .unwrap();
                }
            }
            Source::GrayScott {
                start,
                every,
                pushes,
            } => {
                let mut sim = (**start).clone();
                let n = sim.size();
                for k in 0..*pushes {
                    if k == pushes / 2 {
                        // A change of regime: other feed and kill rates.
                        sim.set_params(GrayScottParams {
                            f: 0.022,
                            k: 0.051,
                            ..sim.params()
                        });
                        switch_step = Some(sim.step_index() + every);
                    }
                    sim = tokio::task::spawn_blocking({
                        let mut s = sim;
                        let e = *every;
                        move || {
                            s.advance(e);
                            s
                        }
                    })
                    .await
                    .unwrap();
                    let field = sim.v_volume().data().to_vec();
                    let i = sim.step_index();
                    pushed.lock().unwrap().insert(i, Instant::now());
                    c.push_step(Step::whole_f32(i, i as f64, [n as u32; 3], &field))
                        .await
                        .unwrap();
                }
            }
        }
        c.flush(Duration::from_secs(600)).await.unwrap();
        tokio::time::sleep(Duration::from_secs(3)).await; // the last scores
        collector.abort();
        let (stored, lat) = std::mem::take(&mut *seen.lock().unwrap());
        (stored, lat, switch_step)
    });
    let wall = t0.elapsed().as_secs_f64();
    let (sim, gen, viz) = (
        cpu_secs(std::process::id()) - self_cpu0,
        cpu_secs(g.child.id()),
        cpu_secs(v.child.id()),
    );
    let mut cpu = sim + gen + viz;
    let (decisions, status) = match &tuner {
        Some(t) => {
            let tc = cpu_secs(t.child.id());
            println!(
                "  CPU s: simulation/pushing {sim:.1}, generator-node {gen:.1}, viz-node {viz:.1}, tuner-node {tc:.1}"
            );
            cpu += tc;
            rt().block_on(async {
                let mut c =
                    TunerClient::new(transport::connect(&transport::uri(&t.addr)).await.unwrap());
                let s = c
                    .get_status(pb::StatusRequest {})
                    .await
                    .unwrap()
                    .into_inner();
                let mut d = Vec::new();
                for v in 1..=s.pm_version {
                    if let Ok(x) = c.get_decision(pb::DecisionRequest { pm_version: v }).await {
                        d.push(x.into_inner());
                    }
                }
                (d, Some(s))
            })
        }
        None => {
            println!(
                "  CPU s: simulation/pushing {sim:.1}, generator-node {gen:.1}, viz-node {viz:.1} (no tuner)"
            );
            (Vec::new(), None)
        }
    };
    g.terminate();
    if let Some(t) = tuner {
        let log = t.log.clone();
        t.terminate();
        // Why tunings ended without a decision (failed trials, nothing feasible).
        for line in std::fs::read_to_string(log)
            .unwrap_or_default()
            .lines()
            .filter(|l| l.contains("WARN") || l.contains("re-tuned") || l.contains("evict"))
        {
            println!("  tuner: {line}");
        }
    }
    v.terminate();
    Outcome {
        cpu,
        node_cpu: gen,
        latencies,
        stored,
        decisions,
        status,
        switch_step,
        wall,
    }
}

fn median(v: &[f64]) -> f64 {
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    s.get(s.len() / 2).copied().unwrap_or(f64::NAN)
}

fn report(name: &str, with: &Outcome, without: &Outcome) {
    let s = with.status.clone().unwrap_or_default();
    println!("== {name}");
    println!(
        "CPU time of the run (simulation + daemons): {:.1} s with the tuner, {:.1} s without (their difference, {:.1} % of the run, also differs in what the P_M made)",
        with.cpu,
        without.cpu,
        100.0 * (with.cpu - without.cpu) / with.cpu
    );
    println!(
        "trials' CPU time, counted on the node: {:.1} s = {:.1} % of the run's CPU time, {:.1} % of the generator-node's (aim ≤ 10 %); size probes {:.1} s ({} of them, {:.0} ms each), full trials with their references {:.1} s ({}, {:.0} ms each)",
        s.trial_cpu_secs,
        100.0 * s.trial_cpu_secs / with.cpu,
        100.0 * s.trial_cpu_secs / with.node_cpu,
        s.size_probe_cpu_secs,
        s.size_probes,
        1e3 * s.size_probe_cpu_secs / s.size_probes.max(1) as f64,
        s.trial_cpu_secs - s.size_probe_cpu_secs,
        s.trials_run - s.size_probes,
        1e3 * (s.trial_cpu_secs - s.size_probe_cpu_secs) / (s.trials_run - s.size_probes).max(1) as f64,
    );
    println!(
        "trials: {} run, {} of them size probes, {} failed ({:.1} s node wall clock = {:.1} % of the {:.1} s run), {} answered from earlier trials, {} tunings, {} decisions",
        s.trials_run,
        s.size_probes,
        s.trials_failed,
        s.trial_secs,
        100.0 * s.trial_secs / with.wall,
        with.wall,
        s.trials_reused,
        s.retunes,
        s.decisions
    );
    println!(
        "production latency push → stored (steps without references): median {:.1} ms with, {:.1} ms without; before the first push (same P_M, trials running) {:.1} ms with",
        median(&with.latencies.iter().map(|l| l.1).collect::<Vec<_>>()) * 1e3,
        median(&without.latencies.iter().map(|l| l.1).collect::<Vec<_>>()) * 1e3,
        median(&with.latencies.iter().filter(|l| l.0 == 0).map(|l| l.1).collect::<Vec<_>>()) * 1e3,
    );
    for d in &with.decisions {
        println!(
            "  v{}: step {} ({}), r {} γ {:.4} → predicted σ {:.1} kB q {:.2} dB τ {:.3} s; tuned on {:?}; {} trials {:.1} s",
            d.pm_version,
            d.trigger_step,
            d.reason,
            d.resolution,
            d.gamma,
            d.predicted_sigma_bytes as f64 / 1e3,
            d.predicted_q_db,
            d.predicted_tau_secs,
            d.characteristic_steps,
            d.trials,
            d.trial_secs
        );
    }
    if let Some(first) = with.decisions.first() {
        let landed = with
            .stored
            .values()
            .find(|r| r.pm_version == first.pm_version)
            .map(|r| r.step);
        println!(
            "first push after {} characteristic step(s) of trials; first step made with it: {landed:?}",
            first.characteristic_steps.len()
        );
    }
    if let Some(sw) = with.switch_step {
        let reacting = with.decisions.iter().find(|d| d.trigger_step >= sw);
        match reacting {
            Some(d) => {
                let outdated = with
                    .stored
                    .values()
                    .filter(|r| r.step >= sw && r.pm_version < d.pm_version)
                    .count();
                println!(
                    "change of character at step {sw}: re-tuned at step {} (v{}); {outdated} production step(s) ran on an outdated P_M",
                    d.trigger_step, d.pm_version
                );
            }
            None => println!("change of character at step {sw}: no new P_M was needed"),
        }
    }
    let sizes = |o: &Outcome| -> Vec<String> {
        o.stored
            .values()
            .map(|r| {
                format!(
                    "{}:v{}:{:.0}kB",
                    r.step,
                    r.pm_version,
                    r.sigma_bytes as f64 / 1e3
                )
            })
            .collect()
    };
    println!("σ per step with the tuner: {}", sizes(with).join(" "));
    // What the trials bought: the budget kept, and q, on the steps made after a decision.
    let decided: Vec<&pb::QualityReport> =
        with.stored.values().filter(|r| r.pm_version >= 1).collect();
    let target = s.sigma_target_bytes as f64;
    if !decided.is_empty() && target > 0.0 {
        let within = decided
            .iter()
            .filter(|r| r.sigma_bytes as f64 <= target)
            .count();
        let worst = decided
            .iter()
            .map(|r| r.sigma_bytes as f64 / target)
            .fold(0.0, f64::max);
        let q: Vec<f64> = decided
            .iter()
            .filter_map(|r| r.q_db)
            .filter(|q| q.is_finite())
            .collect();
        println!(
            "after the first decision: σ within the budget on {within} of {} steps (worst {worst:.2}×), median q {:.2} dB over {} scored steps",
            decided.len(),
            median(&q),
            q.len()
        );
    }
}

fn main() {
    if !std::env::args().any(|a| a == "--bench") {
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    // Build the daemons before anything is timed.
    insitu_e2e::ensure_built();
    if let Some(series) = ocean() {
        let ocean = Source::Ocean(series);
        let without = run(&ocean, None, tmp.path(), 2, "bzip2");
        let with = run(&ocean, Some("size:150kB"), tmp.path(), 2, "bzip2");
        report(
            "ocean 180×90×19, 12 steps, bzip2, size:150kB",
            &with,
            &without,
        );
    }
    // Warmed up past the start-up transient (the pattern fills the box by then), as a
    // simulation's characteristic behaviour is what a tuner should see.
    let warmup: u64 = std::env::var("INSITU_BENCH_GS_WARMUP")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(1500);
    let mut start = GrayScott::new(128, GrayScottParams::default()).unwrap();
    start.advance(warmup);
    let gs = Source::GrayScott {
        start: Box::new(start),
        every: 20,
        pushes: 60,
    };
    // zstd: with bzip2 the node cannot keep up with this simulation at r = 256 (the queue
    // stays full with or without a tuner), and trials only get the turns `trial_interleave`
    // gives them.
    let without = run(&gs, None, tmp.path(), 100, "zstd");
    let with = run(&gs, Some("size:1MB"), tmp.path(), 100, "zstd");
    report(
        &format!("Gray–Scott 128³ after {warmup} steps, push every 20 steps, 60 pushes, F/k switched half-way, zstd, size:1MB"),
        &with,
        &without,
    );
}
