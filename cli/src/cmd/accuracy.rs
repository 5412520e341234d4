//! `insitu accuracy`: what accuracy costs in time on one scene — every knob that trades
//! quality for speed swept on its own, with q, τ and σ per setting (see
//! `insitu_tuner::accuracy` for what each row compares against).

use super::q_text;
use crate::scene::SceneArgs;
use anyhow::Result;
use insitu_core::vdi::codec::Codec;
use insitu_tuner::accuracy::{sweep, Sweep};
use insitu_tuner::utility::bytes_text;
use insitu_tuner::Candidate;

#[derive(clap::Args, Debug)]
pub struct Args {
    #[command(flatten)]
    scene: SceneArgs,
    #[command(flatten)]
    pm: super::PmArgs,
    #[command(flatten)]
    backend: super::BackendArgs,
    /// Test view angles about +y, degrees.
    #[arg(long, default_value = "0,30,60", allow_hyphen_values = true)]
    views: String,
    /// Image side, pixels.
    #[arg(long, default_value_t = 512)]
    size: u32,
    /// Base codec.
    #[arg(long, default_value = "bzip2", value_parser = super::codec_arg)]
    codec: Codec,
    /// Chart of q against tau per knob.
    #[arg(long, default_value = "accuracy.png")]
    chart: std::path::PathBuf,
    /// Print JSON instead of a table.
    #[arg(long)]
    json: bool,
}

pub fn run(a: Args) -> Result<()> {
    let views = super::parse_views(&a.views)?;
    let codec = a.codec;
    let (size, _) = super::parse_size(&a.size.to_string())?;
    let scene = a.scene.load()?;
    let backend = a.backend.open()?;
    let rows = sweep(&Sweep {
        volume: &scene.volume,
        tf: &scene.tf,
        tf_name: &scene.tf_name,
        base: scene.params,
        camera: SceneArgs::camera(&scene),
        views: &views,
        size,
        base_pm: Candidate {
            r: a.pm.r,
            gamma: a.pm.gamma,
            precision: Default::default(),
        },
        codec,
        backend: &backend,
    })?;
    let title = format!(
        "{} ({})",
        super::study::short_name(&scene.volume_name),
        scene.tf_name
    );
    insitu_tuner::charts::accuracy(&rows, &title, &a.chart)?;
    if a.json {
        let rows: Vec<_> = rows
            .iter()
            .map(|r| {
                serde_json::json!({
                    "knob": r.knob, "value": r.value, "q_db": r.q_db.map(super::q_json),
                    "tau_s": r.tau_secs, "tau_of": r.tau_of, "sigma_bytes": r.sigma_bytes,
                })
            })
            .collect();
        println!("{}", serde_json::Value::Array(rows));
        return Ok(());
    }
    println!(
        "{} with {} | base: step {}, termination {}, r = {}, γ = {}, {codec}; views {views:?} at {size}²",
        scene.volume_name, scene.tf_name, scene.params.sample_distance, scene.params.termination, a.pm.r, a.pm.gamma
    );
    println!(
        "{:<32} {:>12} {:>9} {:>10}  {:<16} {:>10}",
        "knob", "value", "q [dB]", "τ [s]", "τ of", "σ"
    );
    for r in &rows {
        println!(
            "{:<32} {:>12} {:>9} {:>10.4}  {:<16} {:>10}",
            r.knob,
            r.value,
            r.q_db.map_or_else(|| "-".to_owned(), q_text),
            r.tau_secs,
            r.tau_of,
            r.sigma_bytes.map_or_else(|| "-".to_owned(), bytes_text)
        );
    }
    println!("chart -> {}", a.chart.display());
    println!("q of step/termination rows: against a direct rendering at a quarter of the base step without early termination; of VDI rows: against the direct rendering at the base setting (Alg. 1).");
    Ok(())
}
