//! `insitu export`: the index of a recording (`index.sqlite`) as JSON or CSV, for people who
//! want a file. Reads only; safe while a viz-node is writing the recording.

use anyhow::{bail, Context, Result};
use insitu_viz_node::index::IndexDb;
use std::path::PathBuf;

#[derive(clap::Args, Debug)]
pub struct Args {
    /// The recording directory (a viz-node's `recording_dir`).
    #[arg(long)]
    recording: PathBuf,
    /// `json` (every row: `{"entries": [...], "steps": [...]}`) or `csv` (one line per step
    /// and rank, and per composed step with an empty rank).
    #[arg(long, default_value = "json")]
    format: String,
    /// Write here instead of standard output.
    #[arg(long)]
    out: Option<PathBuf>,
}

pub fn run(a: Args) -> Result<()> {
    let db = IndexDb::open(&a.recording, false)
        .with_context(|| format!("{} is not a recording", a.recording.display()))?;
    let text = match a.format.as_str() {
        "json" => serde_json::to_string_pretty(&db.export()?)? + "\n",
        "csv" => db.export_csv()?,
        other => bail!("--format {other:?}: use json or csv"),
    };
    match &a.out {
        Some(path) => crate::output::write_atomic(path, text.as_bytes())?,
        None => print!("{text}"),
    }
    Ok(())
}
