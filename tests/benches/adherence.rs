//! How well the tuner keeps its budget while the data drifts, scenario by scenario:
//! `insitu replay --json` of a series (the tuner, generator-node and viz-node in one process,
//! as `insitu demo` runs them) with a `size:` or `time:` budget, read back step by step.
//!
//! Per run it prints: steps made with a tuned `P_M` (after the first decision), the share of
//! them within the budget and the worst overshoot, mean q of the sampled steps, the q regret
//! against the best `P_M` per step in hindsight (size budgets; see [`hindsight`]), which
//! counts the q given away to headroom, the mean share of the budget used, the trials' node
//! seconds as a share of the run's wall clock, the corrections between tunings, the `P_M`
//! changes per 100 tuned steps and the retries under the hard limit. Size scenarios run once
//! more with `--size-max` at the budget, time scenarios with `--time-max`.
//!
//! Scenarios (the series are written once into `target/tmp/adherence/`):
//! - `gs128`: Gray–Scott 128³ after 1500 steps, a push every 20 steps, 60 pushes (the demo
//!   settings that overshot), `size:1MB` and `time:0.03`;
//! - `gs128-switch`: the same, 40 pushes, F/k switched half-way (as the tuning bench does),
//!   `size:1MB`;
//! - `gs256`: Gray–Scott 256³ after 500 steps, a push every 20, 20 pushes, `size:200kB`;
//! - `ocean`: the shared ocean series (12 monthly steps), `size:150kB` (skipped without data);
//! - `growing`: [`insitu_e2e::drift::growing_structure`] 64³, 30 steps, `size:300kB` and
//!   `time:0.01`;
//! - `character`: [`insitu_e2e::drift::changing_character`] 64³, 16 steps (a smooth orbital,
//!   then from step 8 a wave pattern of several times its σ), `size:300kB`.
//!
//! `cargo bench -p insitu-e2e --bench adherence`. Environment: `INSITU_BIN` the `insitu`
//! binary to measure (default: this build's), `INSITU_ADHERENCE` a comma list of scenarios
//! (default all), `INSITU_ADHERENCE_REGRET=0` skips the hindsight search,
//! `INSITU_BENCH_STEP_SECS` the pace of the pushes (default 1 s, a simulation's step time).

#![allow(clippy::unwrap_used, clippy::expect_used)]

use glam::Vec3;
use insitu_core::adherence::Adherence;
use insitu_core::evaluate::{evaluate, generate_encoded, render_references, DEFAULT_VIEW_ANGLES};
use insitu_core::vdi::codec::Codec;
use insitu_core::volume::{GrayScott, GrayScottParams, RawFormat};
use insitu_core::{
    Backend, Camera, Precision, RaycastParams, Raycaster, TfIdentity, TransferFunction, VdiParams,
};
use insitu_e2e::drift::{changing_character, growing_structure, write_series, RunLines, StepLine};
use insitu_tuner::ParamGrid;
use std::path::{Path, PathBuf};
use std::process::Command;

/// The precisions the tuner searches by default (the tuner-node's `[grid] precision`).
const PRECISIONS: [Precision; 2] = [Precision::Bits(6), Precision::Bits(8)];

/// A series to replay and the budgets to keep.
struct Scenario {
    name: &'static str,
    series: PathBuf,
    utilities: Vec<&'static str>,
}

/// The best q of a stored step in hindsight (see [`hindsight`]).
type Hindsight<'a> = &'a dyn Fn(&StepLine) -> Option<(f64, VdiParams)>;

/// What one run of one scenario gave.
struct Row {
    label: String,
    adherence: Adherence,
    mean_q: f64,
    regret: Option<f64>,
    trial_share: f64,
    corrections: u64,
    limit_retries: u64,
    /// Steps not stored (a hard limit that could not be kept; any other failure).
    lost: u64,
}

fn work_dir() -> PathBuf {
    let d = Path::new(env!("CARGO_TARGET_TMPDIR")).join("adherence");
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// Gray–Scott `n³` after `warmup` steps, a push every `every` steps, F/k switched before
/// push `switch` when given.
fn gray_scott(
    name: &str,
    n: usize,
    warmup: u64,
    every: u64,
    pushes: usize,
    switch: Option<usize>,
) -> PathBuf {
    let path = work_dir().join(format!("{name}_{n}x{n}x{n}x{pushes}_float32.raw"));
    if path.exists() {
        return path;
    }
    eprintln!("writing {} …", path.display());
    let mut sim = GrayScott::new(n, GrayScottParams::default()).unwrap();
    sim.advance(warmup);
    let mut steps = Vec::with_capacity(pushes);
    for t in 0..pushes {
        if Some(t) == switch {
            sim.set_params(GrayScottParams {
                f: 0.022,
                k: 0.051,
                ..sim.params()
            });
        }
        steps.push(sim.v_volume().data().into_owned());
        sim.advance(every);
    }
    let tmp = work_dir().join("writing");
    std::fs::create_dir_all(&tmp).unwrap();
    let written = write_series(&tmp, name, n, pushes, |t| steps[t].clone());
    std::fs::rename(written, &path).unwrap();
    path
}

/// The series `name` of `steps` steps on an `n³` grid, written once from `field(n, t, steps)`.
fn made(name: &str, n: usize, steps: usize, field: fn(usize, usize, usize) -> Vec<f32>) -> PathBuf {
    let path = work_dir().join(format!("{name}_{n}x{n}x{n}x{steps}_float32.raw"));
    if !path.exists() {
        write_series(&work_dir(), name, n, steps, |t| field(n, t, steps));
    }
    path
}

/// The transfer function of a run: the default ramp over the first step's range, written
/// into the bench's folder (the shared data may be read-only) under the series' name (the
/// replay and the hindsight search use the same one).
fn tf_for(series: &Path) -> (PathBuf, TransferFunction) {
    let format = RawFormat::from_file_name(series).unwrap();
    let first = format.load(series, 0, Vec3::ONE).unwrap();
    let tf = TransferFunction::default_for_volume(&first).tf;
    let path = work_dir()
        .join(series.file_name().unwrap())
        .with_extension("tf.json");
    std::fs::write(&path, serde_json::to_string(&tf).unwrap()).unwrap();
    (path, tf)
}

/// σ_target as a float of bytes and τ_target in seconds, of `utility`.
fn budgets(utility: &str) -> (Option<f64>, Option<f64>) {
    let b = insitu_tuner::utility::UtilitySpec::parse(utility)
        .unwrap()
        .budgets();
    (b.size_bytes.map(|b| b as f64), b.time_secs)
}

fn run(bin: &Path, series: &Path, tf: &Path, utility: &str, extra: &[&str]) -> RunLines {
    let rec = tempfile::tempdir().unwrap();
    let pace = std::env::var("INSITU_BENCH_STEP_SECS").unwrap_or_else(|_| "1".into());
    let out = Command::new(bin)
        .args(["replay", "--series", series.to_str().unwrap()])
        .args(["--tf", tf.to_str().unwrap(), "--utility", utility])
        .args([
            "--codec",
            "zstd",
            "--sample-every",
            "2",
            "--json",
            "--no-http",
        ])
        .args(["--step-interval", &pace])
        .args(["--recording", rec.path().join("rec").to_str().unwrap()])
        .args(extra)
        .env_remove("INSITU_TOKEN")
        .output()
        .unwrap();
    RunLines::parse(&insitu_e2e::succeeded("replay", out))
}

/// The best q at step `t` of `series` under σ < `budget` over the tuner's default grid and
/// precisions, in hindsight: at every r and precision the smallest γ whose σ meets the budget
/// (σ falls as γ grows: bisection), scored as the viz-node scores a step (references at side
/// r, the default test views, zstd); the best of those q. `None` when no candidate meets the
/// budget.
fn hindsight(
    series: &Path,
    t: usize,
    tf: &TransferFunction,
    budget: f64,
) -> Option<(f64, VdiParams)> {
    let grid = ParamGrid::parse("64:512:64", "0.001:0.26:0.008").unwrap();
    let format = RawFormat::from_file_name(series).unwrap();
    let volume = format.load(series, t, Vec3::ONE).unwrap();
    let rc = Raycaster::new(&volume, tf, RaycastParams::default()).unwrap();
    let backend = Backend::Cpu;
    let scene = backend.prepare(&rc).unwrap();
    let camera = Camera::default_for_box(&volume.world_box());
    let tfid = TfIdentity {
        hash: tf.identity_hash(),
        name: "bench",
    };
    let mut spare = None;
    let mut best: Option<(f64, VdiParams)> = None;
    for (&r, &precision) in grid
        .rs
        .iter()
        .flat_map(|r| PRECISIONS.iter().map(move |p| (r, p)))
    {
        let fits = |g: f32, spare: &mut Option<_>| {
            let p = VdiParams {
                resolution: r,
                gamma: g,
                precision,
            };
            let (_, s) = generate_encoded(&scene, &camera, p, Codec::Zstd, tfid, spare).unwrap();
            (s.sigma_bytes as f64) < budget
        };
        let n = grid.gammas.len();
        if !fits(grid.gammas[n - 1], &mut spare) {
            continue;
        }
        let (mut lo, mut hi) = (0, n - 1);
        while lo < hi {
            let mid = (lo + hi) / 2;
            if fits(grid.gammas[mid], &mut spare) {
                hi = mid;
            } else {
                lo = mid + 1;
            }
        }
        let refs = render_references(&scene, &camera, &DEFAULT_VIEW_ANGLES, r).unwrap();
        let p = VdiParams {
            resolution: r,
            gamma: grid.gammas[lo],
            precision,
        };
        let (e, _) = evaluate(
            &scene,
            &camera,
            p,
            Codec::Zstd,
            &DEFAULT_VIEW_ANGLES,
            &refs,
            tfid,
            &mut spare,
        )
        .unwrap();
        if best.is_none_or(|b| e.q_db > b.0) {
            best = Some((e.q_db, p));
        }
    }
    best
}

fn row(label: String, lines: &RunLines, utility: &str, hindsight_of: Option<Hindsight<'_>>) -> Row {
    let (size, time) = budgets(utility);
    let tuned: Vec<&StepLine> = lines.steps.iter().collect();
    let adherence = match (size, time) {
        (Some(b), _) => Adherence::of(
            tuned
                .iter()
                .map(|s| (s.pm_version, s.pm(), s.sigma_bytes as f64)),
            b,
        ),
        (None, Some(b)) => {
            Adherence::of(tuned.iter().map(|s| (s.pm_version, s.pm(), s.tau_secs)), b)
        }
        _ => Adherence::default(),
    };
    let scored: Vec<&StepLine> = tuned
        .iter()
        .copied()
        .filter(|s| s.pm_version > 0 && s.q_db.is_some_and(f64::is_finite))
        .collect();
    let mean_q = scored.iter().filter_map(|s| s.q_db).sum::<f64>() / scored.len().max(1) as f64;
    // Hindsight on at most six sampled steps spread over the run (each costs a search).
    let regret = hindsight_of.map(|h| {
        let pick: Vec<&StepLine> = scored
            .iter()
            .copied()
            .enumerate()
            .filter(|(i, _)| scored.len() <= 6 || i % scored.len().div_ceil(6) == 0)
            .map(|x| x.1)
            .collect();
        let verbose = std::env::var("INSITU_ADHERENCE_VERBOSE").is_ok_and(|v| v == "1");
        let gaps: Vec<f64> = pick
            .iter()
            .filter_map(|s| {
                let (q, p) = h(s)?;
                if verbose {
                    println!(
                        "  step {}: run r {} γ {:.3} σ {} B q {:.2} dB; hindsight r {} γ {:.3} q {q:.2} dB",
                        s.step, s.r, s.gamma, s.sigma_bytes, s.q_db?, p.resolution, p.gamma
                    );
                }
                Some((q - s.q_db?).max(0.0))
            })
            .collect();
        gaps.iter().sum::<f64>() / gaps.len().max(1) as f64
    });
    let t = &lines.summary["tuner"];
    let wall = lines.summary["wall_s"].as_f64().unwrap_or(f64::NAN);
    Row {
        label,
        adherence,
        mean_q,
        regret,
        trial_share: t["trial_secs"].as_f64().unwrap_or(0.0) / wall,
        corrections: t["corrections"].as_u64().unwrap_or(0),
        limit_retries: lines.summary["limit_retries"].as_u64().unwrap_or(0),
        lost: lines.summary["failed"].as_u64().unwrap_or(0),
    }
}

fn main() {
    let bin =
        std::env::var_os("INSITU_BIN").map_or_else(|| insitu_e2e::bin("insitu"), PathBuf::from);
    let only: Option<Vec<String>> = std::env::var("INSITU_ADHERENCE")
        .ok()
        .map(|s| s.split(',').map(str::to_owned).collect());
    let wanted = |name: &str| only.as_ref().is_none_or(|o| o.iter().any(|x| x == name));
    let with_regret = std::env::var("INSITU_ADHERENCE_REGRET").map_or(true, |v| v != "0");
    let mut scenarios = Vec::new();
    if wanted("gs128") {
        scenarios.push(Scenario {
            name: "gs128",
            series: gray_scott("gs128", 128, 1500, 20, 60, None),
            utilities: vec!["size:1MB", "time:0.03"],
        });
    }
    if wanted("gs128-switch") {
        scenarios.push(Scenario {
            name: "gs128-switch",
            series: gray_scott("gs128switch", 128, 1500, 20, 40, Some(20)),
            utilities: vec!["size:1MB"],
        });
    }
    if wanted("gs256") {
        scenarios.push(Scenario {
            name: "gs256",
            series: gray_scott("gs256", 256, 500, 20, 20, None),
            utilities: vec!["size:200kB"],
        });
    }
    if wanted("ocean") {
        // The ocean series as the data tests find it; the bench skips the ocean without it.
        match insitu_e2e::ocean() {
            Some(series) => scenarios.push(Scenario {
                name: "ocean",
                series,
                utilities: vec!["size:150kB"],
            }),
            None => eprintln!("ocean: skipped (no data directory)"),
        }
    }
    if wanted("growing") {
        scenarios.push(Scenario {
            name: "growing",
            series: made("growing", 64, 30, growing_structure),
            utilities: vec!["size:300kB", "time:0.01"],
        });
    }
    if wanted("character") {
        scenarios.push(Scenario {
            name: "character",
            series: made("character", 64, 16, changing_character),
            utilities: vec!["size:300kB"],
        });
    }
    println!("binary: {}", bin.display());
    println!(
        "{:<34} {:>6} {:>7} {:>7} {:>6} {:>7} {:>8} {:>8} {:>6} {:>8} {:>7}",
        "run",
        "steps",
        "within",
        "worst",
        "use",
        "mean q",
        "regret",
        "trials",
        "corr.",
        "chg/100",
        "retr/lost"
    );
    for s in &scenarios {
        let (tf_path, tf) = tf_for(&s.series);
        for &utility in &s.utilities {
            let (size, time) = budgets(utility);
            let mut variants: Vec<(String, Vec<String>)> = vec![(String::new(), vec![])];
            if std::env::var("INSITU_ADHERENCE_HARD").map_or(true, |v| v != "0") {
                if let Some(b) = size {
                    variants.push((
                        " +size_max".into(),
                        vec!["--size-max".into(), format!("{}", b as u64)],
                    ));
                }
                if let Some(t) = time {
                    variants.push((
                        " +time_max".into(),
                        vec!["--time-max".into(), format!("{t}")],
                    ));
                }
            }
            for (suffix, extra) in variants {
                let extra: Vec<&str> = extra.iter().map(String::as_str).collect();
                let lines = run(&bin, &s.series, &tf_path, utility, &extra);
                let h = |st: &StepLine| hindsight(&s.series, st.step as usize, &tf, size?);
                let hind: Option<Hindsight<'_>> =
                    (with_regret && size.is_some()).then_some(&h as _);
                let r = row(
                    format!("{} {utility}{suffix}", s.name),
                    &lines,
                    utility,
                    hind,
                );
                println!(
                    "{:<34} {:>6} {:>6.0}% {:>6.2}× {:>5.0}% {:>7.2} {:>8} {:>7.1}% {:>6} {:>8.1} {:>7}",
                    r.label,
                    r.adherence.steps,
                    100.0 * r.adherence.share(),
                    r.adherence.worst_ratio,
                    100.0 * r.adherence.mean_ratio,
                    r.mean_q,
                    r.regret.map_or_else(|| "-".into(), |g| format!("{g:.2}")),
                    100.0 * r.trial_share,
                    r.corrections,
                    r.adherence.changes_per_100(),
                    format!("{}/{}", r.limit_retries, r.lost)
                );
            }
        }
    }
}
