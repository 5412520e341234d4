//! What bricks laid out without a shared plane cost (`insitu_core::volume::tiling`): an `N³`
//! f32 field (default 256, `INSITU_BENCH_N`) split as an array is split into 2 and 8 blocks;
//! per block, the low faces a push leaves (`low_faces`) and the growth by its neighbours'
//! faces before it is made (`grow`), medians of `INSITU_BENCH_ROUNDS` (default 7), beside
//! the VDI generation of the same grown brick (r 512, γ 0.01), which τ also counts.
//!
//! Run: `cargo bench -p insitu-core --bench tiling`.

#![allow(clippy::expect_used)] // a benchmark without its parameters cannot run

use insitu_core::vdi::generate::generate;
use insitu_core::vdi::VdiParams;
use insitu_core::volume::bricks::{block_bricks, Brick};
use insitu_core::volume::tiling::{grow, low_faces, tiling, Tiling};
use insitu_core::{Camera, RaycastParams, Raycaster, TransferFunction, Volume};
use std::time::Instant;

mod common;
use common::{env, median};

fn timed<T>(rounds: usize, mut f: impl FnMut() -> T) -> (f64, T) {
    let mut out = None;
    let ms = (0..rounds)
        .map(|_| {
            let t = Instant::now();
            out = Some(f());
            t.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    (median(ms), out.expect("rounds ≥ 1"))
}

fn main() {
    let n = env("INSITU_BENCH_N", 256);
    let rounds = env("INSITU_BENCH_ROUNDS", 7).max(1);
    let c = n as f32 / 2.0;
    let whole = Volume::from_fn([n; 3], |x, y, z| {
        let d = [x as f32 - c, y as f32 - c, z as f32 - c];
        (-(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]) / (0.1 * c * c)).exp()
    })
    .expect("field");
    let tf = TransferFunction::default_for_range(0.0, 1.0);
    let camera = Camera::default_for_box(&whole.world_box());
    let params = VdiParams {
        resolution: 512,
        gamma: 0.01,
        precision: Default::default(),
    };
    println!(
        "{n}³ f32, {} threads; per block: faces, growth and generation (r 512, γ 0.01), ms (median of {rounds})",
        rayon::current_num_threads()
    );
    println!(
        "| blocks | block | faces ms | grow ms | grow GB/s | generation ms | grow / generation |"
    );
    println!("|---:|---|---:|---:|---:|---:|---:|");
    for split in [[1, 1, 2], [2, 2, 2]] {
        let blocks = block_bricks([n; 3], split).expect("split");
        let ranked: Vec<(u32, Brick)> = (0..).zip(blocks.iter().copied()).collect();
        let Ok(Tiling::Disjoint(grown)) = tiling([n; 3], &ranked) else {
            panic!("blocks tile the points")
        };
        let fields: Vec<Volume> = blocks
            .iter()
            .map(|b| whole.brick(b).expect("brick"))
            .collect();
        let (faces_ms, faces) = timed(rounds, || {
            fields
                .iter()
                .zip(&blocks)
                .map(|(f, b)| low_faces(f, b).expect("faces"))
                .collect::<Vec<_>>()
        });
        let pieces: Vec<(Brick, &Volume)> = faces
            .iter()
            .flat_map(|f| f.iter().map(|(b, v)| (*b, v)))
            .collect();
        // The first block grows on every axis that has a neighbour.
        // In the memory of the last round's brick, as the node reuses a settled field's.
        let mut made = None;
        let ms = (0..rounds)
            .map(|_| {
                let t = Instant::now();
                let grown_field = grow(&fields[0], &blocks[0], &grown[0], &pieces, made.take());
                let ms = t.elapsed().as_secs_f64() * 1e3;
                made = Some(grown_field.expect("grow"));
                ms
            })
            .collect();
        let (grow_ms, made) = (median(ms), made.expect("rounds ≥ 1"));
        let rc = Raycaster::new(&made, &tf, RaycastParams::default()).expect("raycaster");
        let (gen_ms, _) = timed(rounds.min(3), || generate(&rc, &camera, params, 0, ""));
        let bytes = made.storage_bytes() as f64;
        println!(
            "| {} | {:?} | {:.2} | {:.2} | {:.1} | {:.0} | {:.1} % |",
            blocks.len(),
            grown[0].dims,
            faces_ms / blocks.len() as f64,
            grow_ms,
            bytes / (grow_ms * 1e-3) / 1e9,
            gen_ms,
            100.0 * grow_ms / gen_ms
        );
    }
}
