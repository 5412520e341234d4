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
use insitu_tuner::series::{characteristic_steps, conservative, cross_table, distance, histograms};
use insitu_tuner::utility::{best, bytes_text, parse_utility};
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
    let steps = RawFormat::from_file_name(Path::new(source))?.steps;
    if steps < 2 {
        bail!("--volume {source}: a series needs at least 2 time steps, the name says {steps}");
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
            (s.tf, s.tf_name) = TransferFunction::default_named(lo, hi);
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
        let p = Prepared {
            scene: Scene {
                volume: scenes[t].volume.clone(),
                tf: scenes[t].tf.clone(),
                tf_name: scenes[t].tf_name.clone(),
                volume_name: format!("{} t={t}", scenes[t].volume_name),
                params: scenes[t].params,
            },
            grid: base.grid.clone(),
            views: base.views.clone(),
            size: base.size,
            codec: base.codec,
            backend: base.backend.clone(),
        };
        let rc = p.raycaster()?;
        let mut study = a.study.study(&p, &rc)?;
        per_step.push(run_grid(&mut study, &p.grid)?);
    }
    let optima: Vec<_> = per_step
        .iter()
        .map(|rows| best(rows, utility.as_ref()).map(|(m, _)| m.clone()))
        .collect();
    let cons = conservative(&per_step, utility.as_ref());
    let table = cross_table(&per_step, utility.as_ref());
    let nearest: Vec<(usize, f64)> = (0..scenes.len())
        .map(|i| {
            chosen
                .iter()
                .map(|&c| (c, distance(&hists[i], &hists[c])))
                .min_by(|x, y| x.1.total_cmp(&y.1))
                .unwrap_or((0, 0.0))
        })
        .collect();
    if a.json {
        let m = |m: &insitu_tuner::Measurement| serde_json::json!({"r": m.r, "gamma": m.gamma, "sigma_bytes": m.sizing.sigma_bytes, "q_db": super::q_json(m.q()), "tau_s": m.sizing.tau_secs});
        println!(
            "{}",
            serde_json::json!({
                "utility": utility.describe(),
                "characteristic_steps": chosen,
                "nearest": nearest.iter().map(|(c, d)| serde_json::json!({"step": c, "distance": d})).collect::<Vec<_>>(),
                "optima": optima.iter().map(|o| o.as_ref().map(m)).collect::<Vec<_>>(),
                "conservative": cons.map(|(c, _)| serde_json::json!({"r": c.r, "gamma": c.gamma})),
                "cross": table.iter().map(|x| serde_json::json!({
                    "tuned_on": chosen[x.tuned_on], "evaluated_on": chosen[x.evaluated_on],
                    "measurement": x.on_b.as_ref().map(m), "holds": x.holds,
                })).collect::<Vec<_>>(),
            })
        );
        return Ok(());
    }
    println!("{} steps; {}", scenes.len(), utility.describe());
    println!(
        "characteristic steps {chosen:?} (threshold {}, max {}); each step's nearest: {}",
        a.threshold,
        a.max_steps,
        nearest
            .iter()
            .enumerate()
            .map(|(i, (c, d))| format!("{i}→{c} ({d:.3})"))
            .collect::<Vec<_>>()
            .join(", ")
    );
    for (t, o) in chosen.iter().zip(&optima) {
        match o {
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
    match cons {
        Some((c, _)) => println!("conservative P_M (meets the constraint on every characteristic step, best worst case): r = {}, γ = {}", c.r, c.gamma),
        None => println!("no P_M of the grid meets the constraint on every characteristic step"),
    }
    println!("cross-evaluation (P_M tuned on A, measured on B):");
    println!(
        "{:>6} {:>6} | {:>5} {:>6} | {:>10} {:>8} {:>8} | holds",
        "A", "B", "r", "gamma", "sigma", "q dB", "tau s"
    );
    for x in &table {
        let (a_step, b_step) = (chosen[x.tuned_on], chosen[x.evaluated_on]);
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
    Ok(())
}
