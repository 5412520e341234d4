//! `insitu export`: the index of a recording (`index.sqlite`) as JSON or CSV, for people who
//! want a file. Reads only; safe while a viz-node is writing the recording.

use anyhow::{Context, Result};
use insitu_core::adherence::Adherence;
use insitu_viz_node::index::IndexDb;
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
    budget: Option<(Option<f64>, Option<f64>)>,
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
fn budget_arg(s: &str) -> Result<(Option<f64>, Option<f64>), String> {
    let spec = insitu_tuner::utility::UtilitySpec::parse(s).map_err(|e| e.to_string())?;
    match spec.budgets() {
        (None, None) => Err(format!("{s:?} states no size or time budget")),
        (size, time) => Ok((size.map(|b| b as f64), time)),
    }
}

/// One value per step: single-rank entries and composed steps.
fn step_values(
    e: &insitu_viz_node::index::Export,
    value: fn(&insitu_core::evaluate::Sizing) -> f64,
) -> Vec<(u64, f64)> {
    e.entries
        .iter()
        .filter(|x| x.world_size <= 1)
        .map(|x| (x.pm_version, value(&x.sizing)))
        .chain(e.steps.iter().map(|x| (x.pm_version, value(&x.sizing))))
        .collect()
}

pub fn run(a: Args) -> Result<()> {
    let db = IndexDb::open(&a.recording, false)
        .with_context(|| format!("{} is not a recording", a.recording.display()))?;
    let text = match a.format {
        Format::Json => {
            let e = db.export()?;
            let adherence = a.budget.map(|(size, time)| {
                let of = |b: Option<f64>, f: fn(&insitu_core::evaluate::Sizing) -> f64| {
                    b.map(|b| Adherence::of(step_values(&e, f), b).json())
                };
                serde_json::json!({
                    "sigma": of(size, |s| s.sigma_bytes as f64),
                    "tau": of(time, |s| s.tau_secs),
                })
            });
            // Serialised directly (γ as written: an f32 through a serde_json::Value would
            // print 0.013000000268220901).
            #[derive(serde::Serialize)]
            struct WithAdherence<'a> {
                #[serde(flatten)]
                export: &'a insitu_viz_node::index::Export,
                #[serde(skip_serializing_if = "Option::is_none")]
                adherence: Option<serde_json::Value>,
            }
            serde_json::to_string_pretty(&WithAdherence {
                export: &e,
                adherence,
            })? + "\n"
        }
        Format::Csv => with_ratios(&db.export_csv()?, a.budget),
    };
    match &a.out {
        Some(path) => crate::output::write_atomic(path, text.as_bytes())?,
        None => print!("{text}"),
    }
    Ok(())
}

/// The CSV with σ and τ over the budget appended to each line (empty without that budget).
fn with_ratios(csv: &str, budget: Option<(Option<f64>, Option<f64>)>) -> String {
    let Some((size, time)) = budget else {
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
        let ratio = |col: usize, b: Option<f64>| {
            let v = cols.get(col).and_then(|c| c.parse::<f64>().ok());
            v.zip(b)
                .map_or_else(String::new, |(v, b)| format!("{}", v / b))
        };
        out.push_str(&format!(",{},{}\n", ratio(6, size), ratio(7, time)));
    }
    out
}
