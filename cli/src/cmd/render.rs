//! `insitu render`: reference DVR to a PNG.

use crate::output::write_png;
use crate::scene::SceneArgs;
use anyhow::Result;
use insitu_core::Raycaster;
use std::path::PathBuf;

#[derive(clap::Args, Debug)]
pub struct Args {
    #[command(flatten)]
    scene: SceneArgs,
    #[command(flatten)]
    backend: super::BackendArgs,
    /// Camera orbit angle about +y, degrees.
    #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
    angle: f32,
    /// Image size `N` or `WxH`.
    #[arg(long, default_value = "768")]
    size: String,
    /// Output PNG.
    #[arg(long, default_value = "render.png")]
    out: PathBuf,
}

pub fn run(a: Args) -> Result<()> {
    let (w, h) = super::parse_size(&a.size)?;
    let scene = a.scene.load()?;
    let backend = a.backend.open()?;
    let rc = Raycaster::new(&scene.volume, &scene.tf, scene.params)?;
    let camera = SceneArgs::camera(&scene).orbit_y(a.angle);
    let image = backend.prepare(&rc)?.dvr(&camera, w, h)?;
    write_png(&a.out, &image.value)?;
    println!(
        "rendered {} at {}x{} ({}°, step {}) in {:.3} s ({}; {:.3} s wall) -> {}",
        scene.volume_name,
        w,
        h,
        a.angle,
        scene.params.step,
        image.seconds,
        image.source,
        image.wall_s,
        a.out.display()
    );
    Ok(())
}
