//! `insitu export`: the index of a recording (`index.sqlite`) as JSON or CSV, for people who
//! want a file; or its steps rendered into a Cinema database (`--cinema`, [`super::cinema`])
//! or a movie (`--movie`, [`super::movie`]). Reads only; safe while a viz-node is writing the
//! recording.

use anyhow::{Context, Result};
use insitu_core::adherence::Adherence;
use insitu_core::budget::Budgets;
use insitu_recording::index::IndexDb;
use std::path::PathBuf;

#[derive(clap::Args, Debug)]
pub struct Args {
    /// The recording directory (a viz-node's `recording_dir`).
    #[arg(long)]
    recording: PathBuf,
    /// `json` (every row: `{"entries": [...], "steps": [...]}`) or `csv` (one line per step
    /// and rank, and per composed step with an empty rank).
    #[arg(long, value_enum, default_value_t = Format::Json)]
    format: Format,
    /// Write here instead of standard output.
    #[arg(long)]
    out: Option<PathBuf>,
    /// The run's budget, as the tuner's utility states it (size:1MB, time:0.05 or both): the
    /// JSON then carries `adherence` (`sigma`, `tau`: steps made with a tuned P_M, within,
    /// share, worst_ratio), and the CSV a `sigma_budget_ratio` and `tau_budget_ratio` column.
    #[arg(long, value_parser = budget_arg)]
    budget: Option<Budgets>,
    /// Render every step (composed over its ranks) at the --phi × --theta grid into this
    /// Cinema database (Spec D: `data.csv` with `time,phi,theta`, the step's P_M and metrics,
    /// `FILE`; the PNGs under `image/`), e.g. `run.cdb`. It must not exist yet.
    #[arg(long, conflicts_with_all = ["format", "out", "budget", "movie"])]
    cinema: Option<PathBuf>,
    /// Orbit angles about +y for --cinema, degrees, comma-separated.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "0,45,90,135,180,225,270,315",
        allow_negative_numbers = true
    )]
    phi: Vec<f32>,
    /// Elevations for --cinema, degrees in [-89, 89], comma-separated.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "0",
        allow_negative_numbers = true
    )]
    theta: Vec<f32>,
    /// Render every step along an orbit into this H.264 movie (needs ffmpeg), e.g. `run.mp4`.
    #[arg(long, conflicts_with_all = ["format", "out", "budget"])]
    movie: Option<PathBuf>,
    /// Degrees the --movie camera orbits about +y per frame.
    #[arg(long, default_value_t = 3.0, allow_negative_numbers = true)]
    orbit: f32,
    /// Elevation of the --movie camera, degrees.
    #[arg(long, default_value_t = 15.0, allow_negative_numbers = true)]
    elevation: f32,
    /// --movie frames per step (the camera keeps orbiting while a step is shown).
    #[arg(long, default_value_t = 4)]
    frames_per_step: u32,
    /// --movie frames per second.
    #[arg(long, default_value_t = 24)]
    fps: u32,
    /// Image size of --cinema and --movie, `N` or `WxH`.
    #[arg(long, default_value = "512")]
    size: String,
    #[command(flatten)]
    backend: super::BackendArgs,
}

/// What `insitu export` writes.
#[derive(Clone, Copy, Debug, clap::ValueEnum)]
pub enum Format {
    /// Every row: `{"entries": [...], "steps": [...]}`.
    Json,
    /// One line per step and rank, and per composed step with an empty rank.
    Csv,
}

/// `--budget`: σ_target and τ_target of a utility spec with at least one of them.
fn budget_arg(s: &str) -> Result<Budgets, String> {
    let spec = insitu_tuner::utility::UtilitySpec::parse(s).map_err(|e| e.to_string())?;
    Some(spec.budgets())
        .filter(|b| !b.is_none())
        .ok_or_else(|| format!("{s:?} states no size or time budget"))
}

/// A step's `(P_M version, (r, γ), value)`, as `Adherence::of` takes it.
type Sample = (u64, (u32, f32), f64);

/// One value per step, in step order: single-rank entries and composed steps.
fn step_values(
    e: &insitu_recording::index::Export,
    value: fn(&insitu_core::evaluate::Sizing) -> f64,
) -> Vec<Sample> {
    let mut v: Vec<(u64, Sample)> = e
        .entries
        .iter()
        .filter(|x| x.world_size <= 1)
        .map(|x| {
            let pm = (x.resolution, x.gamma);
            (x.step, (x.pm_version, pm, value(&x.sizing)))
        })
        .chain(e.steps.iter().map(|x| {
            let pm = (x.resolution, x.gamma);
            (x.step, (x.pm_version, pm, value(&x.sizing)))
        }))
        .collect();
    // In step order: the P_M changes are counted between consecutive steps.
    v.sort_by_key(|x| x.0);
    v.into_iter().map(|x| x.1).collect()
}

pub fn run(a: Args) -> Result<()> {
    if a.cinema.is_some() || a.movie.is_some() {
        return render(&a);
    }
    // A recording shared by step among viz-nodes: every shard's rows (docs/scale.md).
    let shards = insitu_recording::index::shards(&a.recording);
    let e = if shards.is_empty() {
        IndexDb::open(&a.recording, false)
            .and_then(|db| db.export())
            .map_err(|e| insitu_recording::index::with_recovery_advice(e, &a.recording))
            .with_context(|| format!("{} is not a readable recording", a.recording.display()))?
    } else {
        insitu_recording::index::export_shards(&shards)?
    };
    let text = match a.format {
        Format::Json => {
            let adherence = a.budget.map(|b| {
                let of = |b: Option<f64>, f: fn(&insitu_core::evaluate::Sizing) -> f64| {
                    b.map(|b| Adherence::of(step_values(&e, f), b).json())
                };
                serde_json::json!({
                    "sigma": of(b.size_bytes.map(|b| b as f64), |s| s.sigma_bytes as f64),
                    "tau": of(b.time_secs, |s| s.tau_secs),
                })
            });
            // Serialised directly (γ as written: an f32 through a serde_json::Value would
            // print 0.013000000268220901).
            #[derive(serde::Serialize)]
            struct WithAdherence<'a> {
                #[serde(flatten)]
                export: &'a insitu_recording::index::Export,
                #[serde(skip_serializing_if = "Option::is_none")]
                adherence: Option<serde_json::Value>,
            }
            serde_json::to_string_pretty(&WithAdherence {
                export: &e,
                adherence,
            })? + "\n"
        }
        Format::Csv => with_ratios(&insitu_recording::index::csv(&e), a.budget),
    };
    match &a.out {
        Some(path) => crate::output::write_atomic(path, text.as_bytes())?,
        None => print!("{text}"),
    }
    Ok(())
}

/// `--cinema` or `--movie`: the steps rendered.
fn render(a: &Args) -> Result<()> {
    let (width, height) = super::parse_size(&a.size)?;
    let stored = super::stored::Stored::read(&a.recording)?;
    for why in &stored.left_out {
        eprintln!("note: left out: {why}");
    }
    if stored.steps.is_empty() {
        anyhow::bail!("{} holds no step to render", a.recording.display());
    }
    let backend = a.backend.open()?;
    if let Some(out) = &a.cinema {
        let grid = super::cinema::Grid {
            phi: a.phi.clone(),
            theta: a.theta.clone(),
            width,
            height,
        };
        let n = super::cinema::write(&stored, out, &grid, &backend)?;
        println!(
            "cinema: {} steps × {} views = {n} images → {}",
            stored.steps.len(),
            grid.phi.len() * grid.theta.len(),
            out.display()
        );
    }
    if let Some(out) = &a.movie {
        let orbit = insitu_viz_node::movie::Orbit {
            start: insitu_viz_node::view::View {
                elevation_deg: a.elevation,
                width,
                height,
                ..Default::default()
            },
            orbit_deg: a.orbit,
            frames_per_step: a.frames_per_step,
            fps: a.fps,
        };
        let n = super::movie::write(&stored, out, &orbit, &backend)?;
        println!(
            "movie: {} steps, {n} frames at {} fps → {}",
            stored.steps.len(),
            a.fps,
            out.display()
        );
    }
    Ok(())
}

/// The CSV with σ and τ over the budget appended to each line (empty without that budget).
fn with_ratios(csv: &str, budget: Option<Budgets>) -> String {
    let Some(budget) = budget else {
        return csv.to_owned();
    };
    let mut out = String::with_capacity(csv.len() * 5 / 4);
    for (i, line) in csv.lines().enumerate() {
        out.push_str(line);
        if i == 0 {
            out.push_str(",sigma_budget_ratio,tau_budget_ratio\n");
            continue;
        }
        // The 7th and 8th columns: sigma_bytes, tau_secs (no field before them holds a comma).
        let cols: Vec<&str> = line.split(',').collect();
        // A column that does not parse reads as NaN, and its ratio is left empty.
        let value = |col: usize| cols.get(col).and_then(|c| c.parse::<f64>().ok());
        let (sigma, tau) =
            budget.ratios(value(6).unwrap_or(f64::NAN), value(7).unwrap_or(f64::NAN));
        let text = |r: Option<f64>| {
            r.filter(|r| !r.is_nan())
                .map_or_else(String::new, |r| format!("{r}"))
        };
        out.push_str(&format!(",{},{}\n", text(sigma), text(tau)));
    }
    out
}
