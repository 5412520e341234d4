//! `insitu view`: render a VDI file, or a stored step of a recording (composed over its
//! ranks, or one rank), from any camera to a PNG.

use crate::output::write_png;
use anyhow::{Context, Result};
use insitu_core::vdi::codec::{decode, DecodeLimits};
use insitu_core::vdi::Vdi;
use insitu_viz_node::view::{self, View};
use std::path::PathBuf;

#[derive(clap::Args, Debug)]
pub struct Args {
    /// VDI file written by `insitu generate`.
    #[arg(
        long,
        required_unless_present = "recording",
        conflicts_with = "recording"
    )]
    vdi: Option<PathBuf>,
    /// A viz-node's recording directory (with --time-step): renders a stored step, composed over
    /// its ranks unless --rank. Works while a viz-node is writing it.
    #[arg(long, requires = "time_step")]
    recording: Option<PathBuf>,
    /// The stored time step to render (with --recording).
    #[arg(long = "time-step")]
    time_step: Option<u64>,
    /// One rank of the step (with --recording); default: the step composed over its ranks.
    #[arg(long, requires = "recording")]
    rank: Option<u32>,
    /// Orbit angle about +y relative to the generation camera, degrees.
    #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
    angle: f32,
    /// Orbit elevation (positive: from above), degrees in [-89, 89].
    #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
    elevation: f32,
    /// Eye distance over the generation camera's (> 1 moves away).
    #[arg(long, default_value_t = 1.0)]
    zoom: f32,
    /// Image size `N` or `WxH`.
    #[arg(long, default_value = "768")]
    size: String,
    /// Early ray termination threshold; default: the one the VDI was made with.
    #[arg(long)]
    termination: Option<f32>,
    /// Render from the coarsest level of the VDI (halved, `r/2`, `r/4`, ...) that still has
    /// the image's resolution, as the web viewer does while the camera moves: faster, at a
    /// cost in accuracy the viewer table of docs/viewer.md measures.
    #[arg(long)]
    lod: bool,
    /// Render this many times and report the first (which builds the VDI's walk tables and
    /// level) and the median of the others (what a viewer pays per frame).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=1000))]
    repeat: u32,
    /// Output PNG.
    #[arg(long, default_value = "view.png")]
    out: PathBuf,
    #[command(flatten)]
    backend: super::BackendArgs,
}

pub fn run(a: Args) -> Result<()> {
    let (width, height) = super::parse_size(&a.size)?;
    let (vdi, what) = source(&a)?;
    let termination = a.termination.unwrap_or(vdi.meta().termination);
    if !(termination > 0.0 && termination <= 1.0) {
        anyhow::bail!("--termination {termination} must be in (0, 1]");
    }
    let v = View {
        angle_deg: a.angle,
        elevation_deg: a.elevation,
        zoom: a.zoom,
        width,
        height,
    };
    v.check(u64::MAX)?;
    let backend = a.backend.open()?;
    let t = std::time::Instant::now();
    let level = view::level(&vdi, &v, a.lod);
    let level_secs = t.elapsed().as_secs_f64();
    let (image, secs) = view::render(&backend, level, &v, termination, None)?;
    let mut again = Vec::new();
    for _ in 1..a.repeat {
        again.push(view::render(&backend, level, &v, termination, None)?.1);
    }
    write_png(&a.out, &image)?;
    let lod = if a.lod {
        format!(
            " from its level r={} ({} supersegments, built in {:.3} s)",
            level.resolution(),
            level.supersegments().len(),
            level_secs
        )
    } else {
        String::new()
    };
    let repeated = super::warm_median(again);
    println!(
        "rendered {what} (r={}, {} supersegments, {}){lod} at {}°, elevation {}°, zoom {} {}x{} in {:.3} s{repeated} -> {}",
        vdi.resolution(),
        vdi.supersegments().len(),
        vdi.meta().params.precision,
        a.angle,
        a.elevation,
        a.zoom,
        width,
        height,
        secs,
        a.out.display()
    );
    Ok(())
}

/// The VDI to view and how to name it: `--vdi FILE`, or `--time-step N` (`--rank R`, else the
/// composed VDI or the step's only rank) of `--recording DIR`.
fn source(a: &Args) -> Result<(Vdi, String)> {
    Ok(match (&a.vdi, &a.recording, a.time_step) {
        (Some(path), _, _) => {
            let bytes =
                std::fs::read(path).with_context(|| format!("cannot read {}", path.display()))?;
            let vdi = decode(&bytes, &DecodeLimits::default())
                .with_context(|| format!("{} is not a usable VDI", path.display()))?;
            (vdi, path.display().to_string())
        }
        (None, Some(dir), Some(step)) => {
            let (entries, steps) = insitu_recording::index::read(dir)
                .with_context(|| format!("{} is not a readable recording", dir.display()))?;
            let (ranks, others): (Vec<_>, Vec<_>) =
                entries.into_iter().partition(|e| e.step == step);
            let composed = steps.into_iter().find(|s| s.step == step);
            // Before `vdi_file`, which has only this step's entries: here the others are at
            // hand to say what the recording does hold.
            if ranks.is_empty() && composed.is_none() {
                anyhow::bail!(
                    "step {step} is not in {}: it holds {}",
                    dir.display(),
                    steps_held(others.iter().map(|e| e.step).collect())
                );
            }
            let file = view::vdi_file(step, a.rank, &ranks, composed.as_ref())?;
            let what = match a.rank {
                Some(r) => format!("step {step} rank {r} of {}", dir.display()),
                None => format!("step {step} of {}", dir.display()),
            };
            (view::load_vdi(dir, &file)?, what)
        }
        _ => anyhow::bail!("give --vdi FILE, or --recording DIR with --time-step N"),
    })
}

/// The steps a recording holds, for an error: their count and range, and where to list them.
fn steps_held(steps: std::collections::BTreeSet<u64>) -> String {
    match (steps.first(), steps.last()) {
        (Some(first), Some(last)) => format!(
            "{} steps from {first} to {last} (`insitu export` lists them)",
            steps.len()
        ),
        _ => "no steps yet".to_owned(),
    }
}
