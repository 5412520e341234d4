//! The reference DVR on each shared volume, render time alone (the marcher against
//! VTK's, whose side of the comparison is `bench/vtk_compare.sh`): the teapot and hydrogen with
//! their TFs, neghip and the stent with the default ramp over their data range (as
//! `vtk_compare.sh` without `--tf`), 768², 30° and 10°; the ray-caster's set-up for the
//! volume and TF (macro cells, and the occupancy bits that the first 768² render builds:
//! `Raycaster::prepare`) timed apart.
//!
//! A bench binary: the minimum and the median of `INSITU_BENCH_ROUNDS` renders (default 9)
//! after one warm-up. Run: `cargo bench -p insitu-core --bench volumes`.

#![allow(clippy::expect_used)] // a benchmark without its data cannot run

use insitu_core::{dvr, Camera, RaycastParams, Raycaster};
use std::hint::black_box;
use std::time::Instant;

mod common;

const SIZE: u32 = 768;

/// Minimum and median of `v`.
fn min_median(mut v: Vec<f64>) -> (f64, f64) {
    v.sort_by(f64::total_cmp);
    (v[0], v[v.len() / 2])
}

fn main() {
    let rounds: usize = std::env::var("INSITU_BENCH_ROUNDS")
        .ok()
        .and_then(|r| r.parse().ok())
        .unwrap_or(9)
        .max(1);
    println!(
        "DVR {SIZE}², step 0.5, {} threads, {rounds} rounds: set-up, then min / median render",
        rayon::current_num_threads()
    );
    for (file, tf) in [
        ("teapot_256x256x178_uint8.raw", Some("teapot.json")),
        ("hydrogen_64x64x64_float32.raw", Some("hydrogen.json")),
        ("neghip_66x66x66_uint8.raw", None),
        ("stent_128x128x256_int16.raw", None),
    ] {
        let (volume, tf) = common::shared(file, tf).expect("the shared volumes");
        let setup = min_median(
            (0..rounds)
                .map(|_| {
                    let start = Instant::now();
                    let rc = Raycaster::new(&volume, &tf, RaycastParams::default());
                    // With the occupancy bits a 768² render builds on its first call.
                    if let Ok(rc) = &rc {
                        rc.prepare((SIZE * SIZE) as usize);
                    }
                    black_box(rc.ok());
                    start.elapsed().as_secs_f64()
                })
                .collect(),
        );
        let rc = Raycaster::new(&volume, &tf, RaycastParams::default()).expect("valid params");
        let cells = rc.macro_grid().cells();
        for angle in [30.0, 10.0] {
            let cam = Camera::default_for_box(&volume.world_box()).orbit_y(angle);
            black_box(dvr::render(&rc, &cam, SIZE, SIZE));
            let (min, median) = min_median(
                (0..rounds)
                    .map(|_| {
                        let start = Instant::now();
                        black_box(dvr::render(&rc, &cam, SIZE, SIZE));
                        start.elapsed().as_secs_f64()
                    })
                    .collect(),
            );
            println!(
                "{file:32} {angle:>4}°  set-up {:6.1} ms ({} macro cells of {}³)  DVR {:.3} / {:.3} s",
                setup.0 * 1e3,
                cells.iter().product::<usize>(),
                rc.macro_grid().cell_size(),
                min,
                median
            );
        }
    }
}
