//! `insitu generate`: make a VDI and write it compressed.

use crate::output::write_atomic;
use crate::scene::SceneArgs;
use anyhow::Result;
use insitu_core::vdi::codec::{self, Codec};
use insitu_core::Raycaster;
use std::path::PathBuf;
use std::time::Instant;

#[derive(clap::Args, Debug)]
pub struct Args {
    #[command(flatten)]
    scene: SceneArgs,
    #[command(flatten)]
    pm: super::PmArgs,
    #[command(flatten)]
    backend: super::BackendArgs,
    /// Generation camera orbit angle about +y, degrees.
    #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
    angle: f32,
    /// Codec: bzip2 (the paper's sigma), zstd or none.
    #[arg(long, default_value = "bzip2", value_parser = super::codec_arg)]
    codec: Codec,
    /// Output VDI file.
    #[arg(long, default_value = "out.vdi")]
    out: PathBuf,
    /// Print one JSON object instead of text.
    #[arg(long)]
    json: bool,
}

pub fn run(a: Args) -> Result<()> {
    let codec_kind = a.codec;
    let params = a.pm.params()?;
    let scene = a.scene.load()?;
    let backend = a.backend.open()?;
    let rc = Raycaster::new(&scene.volume, &scene.tf, scene.params)?;
    let camera = SceneArgs::camera(&scene).orbit_y(a.angle);
    let generated = backend.prepare(&rc)?.generate(
        &camera,
        params,
        scene.tf.identity_hash(),
        &scene.tf_name,
    )?;
    let (vdi, tau) = (&generated.value, generated.seconds);
    let t = Instant::now();
    let bytes = codec::encode(vdi, codec_kind)?;
    let tau_compress = t.elapsed().as_secs_f64();
    write_atomic(&a.out, &bytes)?;
    if a.json {
        println!(
            "{}",
            serde_json::json!({
                "r": a.pm.r, "gamma": insitu_core::json::f32_number(a.pm.gamma), "codec": codec_kind.name(),
                "precision": params.precision.name(),
                "sigma_bytes": bytes.len(), "supersegments": vdi.supersegments().len(),
                "tau_s": tau, "tau_source": generated.source, "tau_wall_s": generated.wall_s,
                "backend": backend.describe(),
                "tau_compress_s": tau_compress, "out": a.out,
            })
        );
    } else {
        println!(
            "VDI r={} gamma={} of {}: {} supersegments, sigma = {} bytes ({}, {}), tau = {:.3} s ({}), compression {:.3} s -> {}",
            a.pm.r,
            a.pm.gamma,
            scene.volume_name,
            vdi.supersegments().len(),
            bytes.len(),
            codec_kind,
            params.precision,
            tau,
            generated.source,
            tau_compress,
            a.out.display()
        );
    }
    Ok(())
}
