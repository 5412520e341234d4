//! `insitu render`: reference DVR to a PNG.

use crate::output::write_png;
use crate::scene::SceneArgs;
use anyhow::Result;
use insitu_core::backend::TimeSource;
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
    /// Render this many times and report the first (a cold render: the thread pool's start,
    /// the ray-caster's occupancy bits) and the median of the others (a warm render, as a
    /// renderer that stays up pays per frame; `bench/vtk_compare.sh` compares these with
    /// VTK's warm renders).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=1000))]
    repeat: u32,
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
    let prepared = backend.prepare(&rc)?;
    let image = prepared.dvr(&camera, w, h)?;
    let mut again = Vec::new();
    for _ in 1..a.repeat {
        again.push(prepared.dvr(&camera, w, h)?.seconds);
    }
    let repeated = super::warm_median(again);
    write_png(&a.out, &image.value)?;
    // The whole call's wall time only where the time reported is another (GPU timestamps).
    let source = match image.source {
        TimeSource::WallClock => image.source.to_string(),
        other => format!("{other}; {:.3} s wall", image.wall_s),
    };
    println!(
        "rendered {} at {}x{} ({}°, sample distance {}) in {:.3} s ({source}){repeated} -> {}",
        scene.volume_name,
        w,
        h,
        a.angle,
        scene.params.sample_distance,
        image.seconds,
        a.out.display()
    );
    Ok(())
}
