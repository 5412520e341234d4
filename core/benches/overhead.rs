//! VDI generation's cost over the reference DVR pass, the target of issue 3: generation at
//! r = 768 ≤ 1.15× the DVR at 768² (teapot, step 0.5, `../shared/tf/teapot.json`), for
//! γ = 0.013 and, to show what a finer γ costs, 0.001 and 0.26.
//!
//! A bench binary rather than criterion: on a shared machine both passes drift by tens of
//! percent within minutes, and a ratio of two separately timed criterion groups carries that
//! drift. Here each ratio is of a generation and a DVR run back to back (their order alternating),
//! so the drift cancels; the table gives medians and quartiles of `INSITU_BENCH_PAIRS` pairs
//! (default 20) after one warm-up of each. Run: `cargo bench -p insitu-core --bench overhead`.

#![allow(clippy::expect_used)] // a benchmark without its data or parameters cannot run

use insitu_core::vdi::{generate::generate, VdiParams};
use insitu_core::{dvr, Camera, RaycastParams, Raycaster};
use std::hint::black_box;
use std::time::Instant;

mod common;

const SIZE: u32 = 768;

/// Seconds taken by `f`.
fn seconds(f: impl FnOnce()) -> f64 {
    let start = Instant::now();
    f();
    start.elapsed().as_secs_f64()
}

/// First quartile, median and third quartile.
fn quartiles(mut v: Vec<f64>) -> [f64; 3] {
    v.sort_by(f64::total_cmp);
    let at = |q: f64| v[((v.len() - 1) as f64 * q).round() as usize];
    [at(0.25), at(0.5), at(0.75)]
}

fn main() {
    let (volume, tf) = match common::teapot() {
        Ok(scene) => scene,
        Err(e) => {
            eprintln!("overhead bench skipped: {e}");
            return;
        }
    };
    let pairs: usize = std::env::var("INSITU_BENCH_PAIRS")
        .ok()
        .and_then(|s| s.parse().ok())
        .filter(|&n| n > 0)
        .unwrap_or(20);
    let rc = Raycaster::new(&volume, &tf, RaycastParams::default()).expect("valid params");
    let cam = Camera::default_for_box(&volume.world_box());
    let dvr_pass = || seconds(|| drop(black_box(dvr::render(&rc, &cam, SIZE, SIZE))));
    println!(
        "teapot {SIZE}², step 0.5, {} threads, {pairs} pairs (ms: q1 / median / q3)",
        rayon::current_num_threads()
    );
    for gamma in [0.013, 0.001, 0.26] {
        let params = VdiParams {
            resolution: SIZE,
            gamma,
        };
        let gen_pass = || {
            seconds(|| {
                drop(black_box(
                    generate(&rc, &cam, params, 0, "teapot").expect("valid"),
                ))
            })
        };
        let (_, _) = (dvr_pass(), gen_pass());
        let (mut dvr_s, mut gen_s, mut ratio) = (Vec::new(), Vec::new(), Vec::new());
        for k in 0..pairs {
            let (d, g) = if k % 2 == 0 {
                let d = dvr_pass();
                (d, gen_pass())
            } else {
                let g = gen_pass();
                (dvr_pass(), g)
            };
            dvr_s.push(d * 1e3);
            gen_s.push(g * 1e3);
            ratio.push(g / d);
        }
        let [d1, d2, d3] = quartiles(dvr_s);
        let [g1, g2, g3] = quartiles(gen_s);
        let [r1, r2, r3] = quartiles(ratio);
        println!(
            "γ = {gamma:<6} DVR {d1:6.1} / {d2:6.1} / {d3:6.1}   generation r = {SIZE} \
             {g1:6.1} / {g2:6.1} / {g3:6.1}   generation/DVR {r1:.3} / {r2:.3} / {r3:.3} \
             (target ≤ 1.15)"
        );
    }
}
