//! Composing a step's sub-VDIs against the number of ranks: a Gray–Scott field of `N³`
//! (default 256³, `INSITU_BENCH_N`) after `INSITU_BENCH_STEPS` steps (default 1000), cut into
//! 1, 4, 16 and 64 bricks (sharing boundary planes), each brick's VDI generated at r = 512 with
//! the global camera, then `compose_vdis` timed (median of `INSITU_BENCH_ROUNDS`, default 7).
//! The cost should follow the total number of supersegments, not the number of ranks: the
//! table gives both, and nanoseconds per supersegment. Composited reference frames are timed
//! beside it (4 ranks' frames at 512², per view).
//!
//! Run: `cargo bench -p insitu-core --bench compose`.

#![allow(clippy::expect_used)] // a benchmark without its parameters cannot run

use insitu_core::compose::{compose_frames, compose_vdis, BrickFrame};
use insitu_core::vdi::generate::generate;
use insitu_core::vdi::VdiParams;
use insitu_core::volume::bricks::{grid_bricks, split_ranks};
use insitu_core::volume::{GrayScott, GrayScottParams};
use insitu_core::{dvr, Camera, RaycastParams, Raycaster, TransferFunction, Vdi};
use std::time::Instant;

mod common;
use common::{env, median};

fn main() {
    let n = env("INSITU_BENCH_N", 256);
    let steps = env("INSITU_BENCH_STEPS", 1000) as u64;
    let rounds = env("INSITU_BENCH_ROUNDS", 7).max(1);
    let r = 512;
    let t = Instant::now();
    let mut sim = GrayScott::new(n, GrayScottParams::default()).expect("grid size");
    sim.advance(steps);
    let whole = sim.v_volume();
    let (lo, hi) = whole.finite_range().expect("finite field");
    let tf = TransferFunction::default_for_range(lo, hi);
    let camera = Camera::default_for_box(&whole.world_box());
    let params = VdiParams {
        resolution: r,
        gamma: 0.01,
        precision: Default::default(),
    };
    println!(
        "Gray–Scott {n}³ after {steps} steps ({:.1} s), r = {r}, γ = 0.01, {} threads",
        t.elapsed().as_secs_f64(),
        rayon::current_num_threads()
    );
    println!(
        "| ranks | split | supersegments | compose ms (median of {rounds}) | ns / supersegment |"
    );
    println!("|---:|---|---:|---:|---:|");
    for ranks in [1usize, 4, 16, 64] {
        let split = split_ranks(ranks, whole.dims()).expect("split");
        let parts: Vec<Vdi> = grid_bricks(whole.dims(), split)
            .expect("bricks")
            .iter()
            .map(|b| {
                let brick = whole.brick(b).expect("brick");
                let rc = Raycaster::new(&brick, &tf, RaycastParams::default()).expect("raycaster");
                generate(&rc, &camera, params, tf.identity_hash(), "bench").expect("generate")
            })
            .collect();
        let refs: Vec<&Vdi> = parts.iter().collect();
        let mut times = Vec::with_capacity(rounds);
        let mut total = 0;
        for _ in 0..rounds {
            let t = Instant::now();
            let v = compose_vdis(&refs).expect("compose");
            times.push(t.elapsed().as_secs_f64());
            total = v.supersegments().len();
        }
        let m = median(times);
        println!(
            "| {ranks} | {}×{}×{} | {total} | {:.1} | {:.2} |",
            split[0],
            split[1],
            split[2],
            m * 1e3,
            m * 1e9 / total.max(1) as f64
        );
    }
    // Reference frames: 4 ranks at 512², one view.
    let split = split_ranks(4, whole.dims()).expect("split");
    let frames: Vec<_> = grid_bricks(whole.dims(), split)
        .expect("bricks")
        .iter()
        .map(|b| {
            let brick = whole.brick(b).expect("brick");
            let rc = Raycaster::new(&brick, &tf, RaycastParams::default()).expect("raycaster");
            let (image, opacity) = dvr::render_with_opacity(&rc, &camera, r, r);
            (image, opacity, brick.world_box())
        })
        .collect();
    let bf: Vec<BrickFrame> = frames.iter().map(BrickFrame::from).collect();
    let times: Vec<f64> = (0..rounds)
        .map(|_| {
            let t = Instant::now();
            compose_frames(&camera, (r, r), &bf).expect("frames");
            t.elapsed().as_secs_f64()
        })
        .collect();
    println!(
        "compositing 4 ranks' reference frames at {r}²: {:.1} ms per view (median)",
        median(times) * 1e3
    );
}
