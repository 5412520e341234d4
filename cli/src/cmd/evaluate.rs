//! `insitu evaluate`: σ, q and τ of one `P_M` at the test views (Alg. 1, lines 11–18), with
//! a PNG strip of VDI renders (top) over reference renders (bottom), like the paper's Fig. 3.

use super::{q_json, q_text};
use crate::output::write_png;
use crate::progress::bar;
use crate::scene::{Scene, SceneArgs};
use anyhow::{Context, Result};
use insitu_core::evaluate::{evaluate, Evaluation, DEFAULT_VIEW_ANGLES};
use insitu_core::vdi::codec::Codec;
use insitu_core::{Image, Raycaster, TfIdentity};
use std::path::PathBuf;

#[derive(clap::Args, Debug)]
pub struct Args {
    #[command(flatten)]
    scene: SceneArgs,
    #[command(flatten)]
    pm: super::PmArgs,
    #[command(flatten)]
    backend: super::BackendArgs,
    /// Test view angles about +y, degrees, comma-separated.
    #[arg(
        long,
        default_value = "0,10,20,30,40,50,60",
        allow_hyphen_values = true
    )]
    views: String,
    /// Output image size `N` (square, the paper's 768²) or `WxH`.
    #[arg(long, default_value = "768")]
    size: String,
    /// Codec for sigma: bzip2 (the paper's), zstd or none.
    #[arg(long, default_value = "bzip2", value_parser = super::codec_arg)]
    codec: Codec,
    /// PNG strip: VDI renders over reference renders.
    #[arg(long, default_value = "evaluate.png")]
    out: PathBuf,
    /// Print one JSON object instead of text.
    #[arg(long)]
    json: bool,
}

pub fn run(a: Args) -> Result<()> {
    let (w, h) = super::parse_size(&a.size)?;
    let angles = if a.views.is_empty() {
        DEFAULT_VIEW_ANGLES.to_vec()
    } else {
        super::parse_views(&a.views)?
    };
    let params = a.pm.params()?;
    let scene = a.scene.load()?;
    let backend = a.backend.open()?;
    let rc = Raycaster::new(&scene.volume, &scene.tf, scene.params)?;
    let prepared = backend.prepare(&rc)?;
    let camera = SceneArgs::camera(&scene);

    let pb = bar(angles.len() as u64 + 1, "reference renders");
    let mut tau_reference = 0.0;
    let mut references = Vec::with_capacity(angles.len());
    for &angle in &angles {
        let r = prepared.dvr(&camera.orbit_y(angle), w, h)?;
        tau_reference += r.seconds / angles.len() as f64;
        references.push(r.value);
        pb.inc(1);
    }
    pb.set_message("VDI generate, compress, render");
    let (eval, images) = evaluate(
        &prepared,
        &camera,
        params,
        a.codec,
        &angles,
        &references,
        TfIdentity {
            hash: scene.tf.identity_hash(),
            name: &scene.tf_name,
        },
        &mut None,
    )?;
    pb.finish_and_clear();

    let mut tiles: Vec<&Image> = images.iter().collect();
    tiles.extend(references.iter());
    let strip = Image::grid(&tiles, angles.len()).context("cannot assemble the strip")?;
    write_png(&a.out, &strip)?;

    let said = Said {
        scene: &scene,
        size: (w, h),
        eval: &eval,
        tau_reference,
        backend: backend.describe(),
    };
    if a.json {
        print_json(&a, &said);
    } else {
        print_text(&a, &said);
    }
    Ok(())
}

/// What `evaluate` reports beside its flags.
struct Said<'a> {
    scene: &'a Scene,
    /// Image width and height, pixels.
    size: (u32, u32),
    eval: &'a Evaluation,
    /// Mean seconds of a reference DVR per view.
    tau_reference: f64,
    /// The backend, described.
    backend: String,
}

/// The evaluation as one JSON object.
fn print_json(a: &Args, s: &Said) {
    let (scene, eval, (w, h)) = (s.scene, s.eval, s.size);
    let views: Vec<_> = eval
        .views
        .iter()
        .map(|v| serde_json::json!({"angle_deg": insitu_core::json::f32_number(v.angle_deg), "q_db": q_json(v.q_db), "ssim": v.ssim}))
        .collect();
    println!(
        "{}",
        serde_json::json!({
            "volume": scene.volume_name, "tf": scene.tf_name,
            "r": a.pm.r, "gamma": insitu_core::json::f32_number(a.pm.gamma), "codec": a.codec.name(), "precision": a.pm.precision.name(),
            "sample_distance": insitu_core::json::f32_number(scene.params.sample_distance), "size": [w, h],
            "sigma_bytes": eval.sizing.sigma_bytes, "supersegments": eval.sizing.supersegments,
            "tau_s": eval.sizing.tau_secs, "tau_compress_s": eval.sizing.tau_compress_secs,
            "tau_decode_s": eval.tau_decode_secs, "tau_render_s": eval.tau_render_secs,
            "tau_reference_s": s.tau_reference, "tau_source": eval.sizing.tau_source,
            "backend": s.backend,
            "q_db": q_json(eval.q_db), "views": views, "strip": a.out,
        })
    );
}

/// The evaluation as text: the scene, σ, τ, q per view and where the strip went.
fn print_text(a: &Args, s: &Said) {
    let (scene, eval, (w, h)) = (s.scene, s.eval, s.size);
    println!(
        "{} with {} | r = {}, gamma = {}, step = {}, {}x{}",
        scene.volume_name, scene.tf_name, a.pm.r, a.pm.gamma, scene.params.sample_distance, w, h
    );
    println!(
        "sigma = {} bytes ({}, {}), {} supersegments ({:.2} per ray)",
        eval.sizing.sigma_bytes,
        a.codec,
        a.pm.precision,
        eval.sizing.supersegments,
        eval.sizing.supersegments as f64 / (f64::from(a.pm.r) * f64::from(a.pm.r))
    );
    println!(
        "tau = {:.3} s generation, {:.3} s compression, {:.3} s decode; render {:.3} s/view (reference DVR {:.3} s/view)",
        eval.sizing.tau_secs, eval.sizing.tau_compress_secs, eval.tau_decode_secs, eval.tau_render_secs, s.tau_reference
    );
    println!(
        "backend {}: generation, render and DVR times from {}",
        s.backend, eval.sizing.tau_source
    );
    println!(
        "q = {} dB (pooled over {} views)",
        q_text(eval.q_db),
        eval.views.len()
    );
    println!("{:>8} {:>9} {:>7}", "angle", "q [dB]", "SSIM");
    for v in &eval.views {
        let ssim = v.ssim.map_or("-".to_owned(), |s| format!("{s:.4}"));
        println!("{:>7}° {:>9} {:>7}", v.angle_deg, q_text(v.q_db), ssim);
    }
    println!("strip (VDI top, reference bottom) -> {}", a.out.display());
}
