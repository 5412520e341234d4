//! `insitu view`: render a VDI file from a camera to a PNG.

use crate::output::write_png;
use anyhow::{Context, Result};
use insitu_core::vdi::codec::{decode, DecodeLimits};
use std::path::PathBuf;

#[derive(clap::Args, Debug)]
pub struct Args {
    /// VDI file written by `insitu generate`.
    #[arg(long)]
    vdi: PathBuf,
    /// Orbit angle about +y relative to the generation camera, degrees.
    #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
    angle: f32,
    /// Image size `N` or `WxH`.
    #[arg(long, default_value = "768")]
    size: String,
    /// Early ray termination threshold; default: the one the VDI was made with.
    #[arg(long)]
    termination: Option<f32>,
    /// Output PNG.
    #[arg(long, default_value = "view.png")]
    out: PathBuf,
    #[command(flatten)]
    backend: super::BackendArgs,
}

pub fn run(a: Args) -> Result<()> {
    let (w, h) = super::parse_size(&a.size)?;
    let bytes =
        std::fs::read(&a.vdi).with_context(|| format!("cannot read {}", a.vdi.display()))?;
    let vdi = decode(&bytes, &DecodeLimits::default())
        .with_context(|| format!("{} is not a usable VDI", a.vdi.display()))?;
    let termination = a.termination.unwrap_or(vdi.meta().termination);
    if !(termination > 0.0 && termination <= 1.0) {
        anyhow::bail!("--termination {termination} must be in (0, 1]");
    }
    let camera = vdi.meta().camera.orbit_y(a.angle);
    let backend = a.backend.open()?;
    let image = backend
        .prepare_vdi(&vdi)?
        .render(&camera, w, h, termination)?;
    write_png(&a.out, &image.value)?;
    println!(
        "rendered VDI {} (r={}, {} supersegments) at {}° {}x{} in {:.3} s ({}) -> {}",
        a.vdi.display(),
        vdi.resolution(),
        vdi.supersegments().len(),
        a.angle,
        w,
        h,
        image.seconds,
        image.source,
        a.out.display()
    );
    Ok(())
}
