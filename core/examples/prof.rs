#[path = "../benches/common/mod.rs"]
mod common;
use insitu_core::vdi::generate::{generate, generate_into};
use insitu_core::vdi::VdiParams;
use insitu_core::{dvr, Camera, RaycastParams, Raycaster};
use std::time::Instant;
fn main() {
    let what = std::env::args().nth(1).unwrap();
    let name = std::env::args().nth(2).unwrap_or("teapot".into());
    let n: usize = std::env::args().nth(3).map_or(9, |s| s.parse().unwrap());
    let r = 768;
    let (volume, tf) = match name.as_str() {
        "teapot" => common::teapot().unwrap(),
        _ => common::shared(&name, None).unwrap(),
    };
    let mut params = RaycastParams::default();
    if std::env::var_os("TERM99").is_some() {
        params.generation_termination = Some(0.99);
    }
    let rc = Raycaster::new(&volume, &tf, params).unwrap();
    let cam = Camera::default_for_box(&volume.world_box()).orbit_y(30.0);
    let p = VdiParams {
        resolution: r,
        gamma: 0.013,
    };
    let mut vdi = generate(&rc, &cam, p, 0, "x").unwrap();
    let mut best = f64::MAX;
    for _ in 0..n {
        let t = Instant::now();
        if what == "dvr" {
            std::hint::black_box(dvr::render(&rc, &cam, r, r));
        } else {
            generate_into(&rc, &cam, p, 0, "x", &mut vdi).unwrap();
        }
        best = best.min(t.elapsed().as_secs_f64());
    }
    println!("{what} {name}: min {:.1} ms", best * 1e3);
}
