//! `insitu render`: reference DVR to a PNG.

use crate::output::write_png;
use crate::scene::SceneArgs;
use anyhow::Result;
use insitu_core::{dvr, Raycaster};
use std::path::PathBuf;
use std::time::Instant;

#[derive(clap::Args, Debug)]
pub struct Args {
    #[command(flatten)]
    scene: SceneArgs,
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
    let rc = Raycaster::new(&scene.volume, &scene.tf, scene.params)?;
    let camera = SceneArgs::camera(&scene).orbit_y(a.angle);
    let t = Instant::now();
    let image = dvr::render(&rc, &camera, w, h);
    let secs = t.elapsed().as_secs_f64();
    write_png(&a.out, &image)?;
    println!(
        "rendered {} at {}x{} ({}°, step {}) in {:.3} s -> {}",
        scene.volume_name,
        w,
        h,
        a.angle,
        scene.params.step,
        secs,
        a.out.display()
    );
    Ok(())
}
