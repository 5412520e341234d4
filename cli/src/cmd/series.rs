//! `insitu series`: tune across a time series (Sec. 6.2, Table 1, Sec. 7). Picks
//! characteristic time steps (histogram distance, farthest-first; see
//! `insitu_tuner::series`), runs the study on each, and prints each step's optimum, the
//! conservative `P_M` that meets the constraint on all of them, and the cross-evaluation table.

use super::q_text;
use super::study::{run_grid, Prepared, StudyArgs};
use crate::scene::Scene;
use anyhow::{bail, Context, Result};
use insitu_core::volume::RawFormat;
use insitu_core::TransferFunction;
use insitu_tuner::series::{
    characteristic_steps, conservative, cross_table, distance, histograms, Cross,
};
use insitu_tuner::utility::{best, bytes_text, parse_utility};
use insitu_tuner::Candidate;
use std::path::Path;

#[derive(clap::Args, Debug)]
pub struct Args {
    /// The scene; --volume is the 4-D series (<name>_XxYxZxT_<type>.raw).
    #[command(flatten)]
    study: StudyArgs,
    /// Utility: size:2MB (Eq. 1), time:0.5 (Eq. 2), size:2MB,time:0.5, quality:40.
    #[arg(long, default_value = "size:1MB")]
    utility: String,
    /// Steps farther than this (total-variation distance of value histograms, 0..1) from
    /// every chosen step become characteristic.
    #[arg(long, default_value_t = 0.02)]
    threshold: f64,
    /// At most this many characteristic steps.
    #[arg(long, default_value_t = 4)]
    max_steps: usize,
    /// Print JSON instead of text.
    #[arg(long)]
    json: bool,
}

fn load_steps(a: &Args) -> Result<Vec<Scene>> {
    let source = a
        .study
        .scene
        .volume
        .as_deref()
        .context("--volume: give the 4-D series file")?;
    let scene = &a.study.scene;
    let steps = if Path::new(source)
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("raw"))
    {
        RawFormat::from_file_name(Path::new(source))?.steps
    } else {
        crate::scene::open_dataset(Path::new(source), scene.field.as_deref(), scene.uneven)?.steps
    };
    if steps < 2 {
        bail!("--volume {source}: a series needs at least 2 time steps, the file holds {steps}");
    }
    let mut scenes = (0..steps)
        .map(|t| {
            let mut s = a.study.scene.clone();
            s.t = t;
            s.load()
        })
        .collect::<Result<Vec<_>>>()?;
    if a.study.scene.tf.is_none() {
        // One transfer function for all steps: a ramp over the range of the whole series.
        let (lo, hi) = scenes
            .iter()
            .filter_map(|s| s.volume.finite_range())
            .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), (a, b)| {
                (lo.min(a), hi.max(b))
            });
        let (lo, hi) = if lo <= hi { (lo, hi) } else { (0.0, 1.0) };
        for s in &mut scenes {
            let named = TransferFunction::default_named(lo, hi);
            (s.tf, s.tf_name) = (named.tf, named.name);
        }
    }
    Ok(scenes)
}

pub fn run(a: Args) -> Result<()> {
    let utility = parse_utility(&a.utility)?;
    let base = a.study.prepare()?;
    let scenes = load_steps(&a)?;
    let values: Vec<_> = scenes.iter().map(|s| s.volume.data()).collect();
    let fields: Vec<&[f32]> = values.iter().map(|v| v.as_ref()).collect();
    let hists = histograms(&fields);
    let chosen = characteristic_steps(&hists, a.threshold, a.max_steps);
    let mut per_step = Vec::with_capacity(chosen.len());
    for &t in &chosen {
        per_step.push(study_step(&a, &base, &scenes[t], t)?);
    }
    let optima: Vec<_> = per_step
        .iter()
        .map(|rows| best(rows, utility.as_ref()).map(|(m, _)| m.clone()))
        .collect();
    let nearest: Vec<(usize, f64)> = (0..scenes.len())
        .map(|i| {
            chosen
                .iter()
                .map(|&c| (c, distance(&hists[i], &hists[c])))
                .min_by(|x, y| x.1.total_cmp(&y.1))
                .unwrap_or((0, 0.0))
        })
        .collect();
    let outcome = Outcome {
        steps: scenes.len(),
        utility: utility.describe(),
        conservative: conservative(&per_step, utility.as_ref()).map(|(c, _)| c),
        cross: cross_table(&per_step, utility.as_ref()),
        chosen,
        nearest,
        optima,
    };
    if a.json {
        print_json(&outcome);
    } else {
        print_text(&a, &outcome);
    }
    Ok(())
}

/// What a series' tuning found.
struct Outcome {
    /// Time steps in the series.
    steps: usize,
    /// The utility, described.
    utility: String,
    /// The characteristic steps.
    chosen: Vec<usize>,
    /// Per step of the series: the nearest characteristic step and its histogram distance.
    nearest: Vec<(usize, f64)>,
    /// Per characteristic step: its best measurement, if any is feasible.
    optima: Vec<Option<insitu_tuner::Measurement>>,
    /// The P_M that meets the constraint on every characteristic step, with the best worst case.
    conservative: Option<Candidate>,
    /// Each step's optimum measured on each other step.
    cross: Vec<Cross>,
}

/// The grid's measurements on step `t` of the series.
fn study_step(
    a: &Args,
    base: &Prepared,
    step: &Scene,
    t: usize,
) -> Result<Vec<insitu_tuner::Measurement>> {
    let p = Prepared {
        scene: Scene {
            volume: step.volume.clone(),
            tf: step.tf.clone(),
            tf_name: step.tf_name.clone(),
            volume_name: format!("{} t={t}", step.volume_name),
            params: step.params,
        },
        grid: base.grid.clone(),
        views: base.views.clone(),
        size: base.size,
        codec: base.codec,
        backend: base.backend.clone(),
    };
    let rc = p.raycaster()?;
    let mut study = a.study.study(&p, &rc)?;
    run_grid(&mut study, &p.grid)
}

/// [`Outcome`] as one JSON object.
fn print_json(o: &Outcome) {
    let m = |m: &insitu_tuner::Measurement| serde_json::json!({"r": m.r, "gamma": insitu_core::json::f32_number(m.gamma), "sigma_bytes": m.sizing.sigma_bytes, "q_db": super::q_json(m.q()), "tau_s": m.sizing.tau_secs});
    println!(
        "{}",
        serde_json::json!({
            "utility": o.utility,
            "characteristic_steps": o.chosen,
            "nearest": o.nearest.iter().map(|(c, d)| serde_json::json!({"step": c, "distance": d})).collect::<Vec<_>>(),
            "optima": o.optima.iter().map(|x| x.as_ref().map(m)).collect::<Vec<_>>(),
            "conservative": o.conservative.map(|c| serde_json::json!({"r": c.r, "gamma": insitu_core::json::f32_number(c.gamma)})),
            "cross": o.cross.iter().map(|x| serde_json::json!({
                "tuned_on": o.chosen[x.tuned_on], "evaluated_on": o.chosen[x.evaluated_on],
                "measurement": x.on_b.as_ref().map(m), "holds": x.holds,
            })).collect::<Vec<_>>(),
        })
    );
}

/// [`Outcome`] as text: the steps, each optimum, the conservative P_M, the cross table.
fn print_text(a: &Args, o: &Outcome) {
    println!("{} steps; {}", o.steps, o.utility);
    println!(
        "characteristic steps {:?} (threshold {}, max {}); each step's nearest: {}",
        o.chosen,
        a.threshold,
        a.max_steps,
        o.nearest
            .iter()
            .enumerate()
            .map(|(i, (c, d))| format!("{i}→{c} ({d:.3})"))
            .collect::<Vec<_>>()
            .join(", ")
    );
    for (t, optimum) in o.chosen.iter().zip(&o.optima) {
        match optimum {
            Some(m) => println!(
                "  step {t:>3}: best r = {}, γ = {}: σ {}, q {} dB, τ {:.3} s",
                m.r,
                m.gamma,
                bytes_text(m.sizing.sigma_bytes),
                q_text(m.q()),
                m.sizing.tau_secs
            ),
            None => println!("  step {t:>3}: infeasible"),
        }
    }
    match o.conservative {
        Some(c) => println!("conservative P_M (meets the constraint on every characteristic step, best worst case): r = {}, γ = {}", c.r, c.gamma),
        None => println!("no P_M of the grid meets the constraint on every characteristic step"),
    }
    println!("cross-evaluation (P_M tuned on A, measured on B):");
    println!(
        "{:>6} {:>6} | {:>5} {:>6} | {:>10} {:>8} {:>8} | holds",
        "A", "B", "r", "gamma", "sigma", "q dB", "tau s"
    );
    for x in &o.cross {
        let (a_step, b_step) = (o.chosen[x.tuned_on], o.chosen[x.evaluated_on]);
        match &x.on_b {
            Some(m) => println!(
                "{a_step:>6} {b_step:>6} | {:>5} {:>6.3} | {:>10} {:>8} {:>8.3} | {}",
                m.r,
                m.gamma,
                bytes_text(m.sizing.sigma_bytes),
                q_text(m.q()),
                m.sizing.tau_secs,
                if x.holds { "yes" } else { "NO" }
            ),
            None => println!("{a_step:>6} {b_step:>6} | (A infeasible)"),
        }
    }
}
