//! Where a tuner's size probe spends its time: the generator-node measures a candidate `P_M` on
//! a held step by preparing a ray-caster for the step, generating the VDI into the tuning's
//! spare VDI, and encoding it (σ is the file's length). Timed here piece by piece, as a probe
//! runs them, on the two runs of the tuning bench: Gray–Scott 128³ after 1500 steps (the
//! demo's settings, zstd) and the ocean's first step (bzip2).
//!
//! - *ray-caster*: `Raycaster::new` (classification table, macro cells) and `prepare` (the
//!   occupancy bits), paid by every probe unless the node keeps the held step's ray-caster;
//! - *generation after another r*: into a spare last used at another resolution, so its room is
//!   estimated again (as the search's probes alternate resolutions);
//! - *generation, same r*: into a spare of this resolution (no estimate);
//! - *encoding*: the codec, which is σ.
//!
//! A full trial is timed the same way: the references, the generation, the walker, the test
//! views' renders, MSE and SSIM, and the views rendered and scored as a trial runs them.
//!
//! Medians of `INSITU_BENCH_ROUNDS` (default 9). Run: `cargo bench -p insitu-core --bench probe`
//! (`INSITU_PROBE_PROXY=0` leaves out the codec table below).
//!
//! A second table asks whether a probe could measure σ with the fast codec and map it to the
//! run's: over a grid of candidates and two precisions, each VDI encoded with bzip2 and with
//! zstd, the ratio σ_bzip2 / σ_zstd, and the error of estimating every candidate's σ_bzip2 as
//! σ_zstd times the ratio of one calibration candidate (the first of the grid) of the same
//! step.

#![allow(clippy::expect_used)] // a benchmark without its data or parameters cannot run

use insitu_core::vdi::codec::{encode, Codec};
use insitu_core::vdi::generate::{generate, generate_into};
use insitu_core::vdi::{Precision, VdiParams};
use insitu_core::volume::{GrayScott, GrayScottParams, RawFormat};
use insitu_core::{Camera, RaycastParams, Raycaster, TransferFunction, Volume};
use std::hint::black_box;
use std::time::Instant;

/// Median milliseconds of `f` over `rounds` runs, `before` run untimed ahead of each.
fn median_ms(rounds: usize, mut before: impl FnMut(), mut f: impl FnMut()) -> f64 {
    let mut v: Vec<f64> = (0..rounds)
        .map(|_| {
            before();
            let t = Instant::now();
            f();
            t.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Times the pieces of a probe of each `(r, γ)` of `candidates` on `volume`.
fn probe(name: &str, volume: &Volume, codec: Codec, candidates: &[(u32, f32)], rounds: usize) {
    let (lo, hi) = volume.finite_range().unwrap_or((0.0, 1.0));
    let tf = TransferFunction::default_for_range(lo, hi);
    let camera = Camera::default_for_box(&volume.world_box());
    let rp = RaycastParams::default();
    println!("{name}, {codec:?}, medians of {rounds} (ms)");
    println!("| r | γ | ray-caster | generation after another r | generation, same r | encoding | probe as run | σ kB |");
    println!("|---:|---:|---:|---:|---:|---:|---:|---:|");
    for &(r, gamma) in candidates {
        let params = VdiParams {
            resolution: r,
            gamma,
            precision: Default::default(),
        };
        let other = VdiParams {
            resolution: r / 2,
            gamma,
            precision: Default::default(),
        };
        let setup = median_ms(
            rounds,
            || {},
            || {
                let rc = Raycaster::new(volume, &tf, rp).expect("valid params");
                rc.prepare((r as usize).pow(2));
                black_box(&rc);
            },
        );
        let rc = Raycaster::new(volume, &tf, rp).expect("valid params");
        let spare = std::cell::RefCell::new(generate(&rc, &camera, other, 0, "").expect("valid"));
        let into = |p: VdiParams| {
            generate_into(&rc, &camera, p, 0, "", &mut spare.borrow_mut()).expect("valid")
        };
        let after_other = median_ms(rounds, || into(other), || into(params));
        let same = median_ms(rounds, || {}, || into(params));
        let spare = spare.into_inner();
        let mut sigma = 0;
        let encoding = median_ms(
            rounds,
            || {},
            || sigma = encode(&spare, codec).expect("encodes").len(),
        );
        println!(
            "| {r} | {gamma} | {setup:.1} | {after_other:.1} | {same:.1} | {encoding:.1} | {:.1} | {:.0} |",
            setup + after_other + encoding,
            sigma as f64 / 1e3
        );
    }
}

/// Times the pieces of a full trial of each `(r, γ)` of `candidates` on `volume` at 8 bits, as
/// the generator-node runs one after a size probe of the same candidate: the reference frames
/// at side r (once per step and side, kept), the generation, the walker's set-up, the test
/// views' renders, MSE and SSIM each timed alone one view after another, and the views rendered
/// and scored as a trial runs them (`score_views`: the scores of the views side by side).
fn full_trial(name: &str, volume: &Volume, candidates: &[(u32, f32)], rounds: usize) {
    use insitu_core::evaluate::{render_references, score_views, DEFAULT_VIEW_ANGLES};
    use insitu_core::metrics::{self, MetricError};
    use insitu_core::{Backend, Image};
    let (lo, hi) = volume.finite_range().unwrap_or((0.0, 1.0));
    let tf = TransferFunction::default_for_range(lo, hi);
    let camera = Camera::default_for_box(&volume.world_box());
    let rc = Raycaster::new(volume, &tf, RaycastParams::default()).expect("valid params");
    let backend = Backend::Cpu;
    let scene = backend.prepare(&rc).expect("the CPU prepares");
    let views = DEFAULT_VIEW_ANGLES;
    println!(
        "{name}, a full trial at 8 bits, {} views, medians of {rounds} (ms)",
        views.len()
    );
    println!("| r | γ | references | generation | walker | renders | MSE | SSIM | views scored | trial without references |");
    println!("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    for &(r, gamma) in candidates {
        let params = VdiParams {
            resolution: r,
            gamma,
            precision: Precision::Bits(8),
        };
        let mut refs = Vec::new();
        let references = median_ms(
            rounds,
            || {},
            || refs = render_references(&scene, &camera, &views, r).expect("renders"),
        );
        let mut vdi = None;
        let generation = median_ms(
            rounds,
            || {},
            || vdi = Some(generate(&rc, &camera, params, 0, "").expect("valid")),
        );
        let vdi = vdi.expect("generated");
        let walker = median_ms(
            rounds,
            || {},
            || {
                black_box(scene.prepare_vdi(&vdi).expect("prepares"));
            },
        );
        let prepared = scene.prepare_vdi(&vdi).expect("prepares");
        let mut images = Vec::new();
        let renders = median_ms(
            rounds,
            || {},
            || {
                images = views
                    .iter()
                    .map(|&a| {
                        let frame = camera.orbit_y(a);
                        prepared
                            .render(&frame, r, r, rc.params().termination)
                            .expect("renders")
                            .value
                    })
                    .collect();
            },
        );
        // A metric over every view, one after another.
        let each_view = |metric: fn(&Image, &Image) -> Result<f64, MetricError>| {
            median_ms(
                rounds,
                || {},
                || {
                    for (a, b) in images.iter().zip(&refs) {
                        black_box(metric(a, b).expect("same size"));
                    }
                },
            )
        };
        let (mse, ssim) = (each_view(metrics::mse), each_view(metrics::ssim));
        let scored = median_ms(
            rounds,
            || {},
            || {
                let termination = rc.params().termination;
                black_box(
                    score_views(&prepared, &camera, &views, &refs, termination).expect("scores"),
                );
            },
        );
        println!(
            "| {r} | {gamma} | {references:.1} | {generation:.1} | {walker:.1} | {renders:.1} | {mse:.1} | {ssim:.1} | {scored:.1} | {:.1} |",
            generation + walker + scored
        );
    }
    println!();
}

/// σ with bzip2 against σ with zstd over a grid of candidates at `precision` (see the module's
/// docs), with the encodings' times.
fn proxy(name: &str, volume: &Volume, precision: Precision) {
    let (lo, hi) = volume.finite_range().unwrap_or((0.0, 1.0));
    let tf = TransferFunction::default_for_range(lo, hi);
    let camera = Camera::default_for_box(&volume.world_box());
    let rc = Raycaster::new(volume, &tf, RaycastParams::default()).expect("valid params");
    println!("{name}, {precision:?}: σ by bzip2 estimated from zstd");
    println!("| r | γ | σ bzip2 kB | bzip2 ms | σ zstd kB | zstd ms | ratio | estimate's error |");
    println!("|---:|---:|---:|---:|---:|---:|---:|---:|");
    let mut calibration = None;
    let mut worst: f64 = 0.0;
    for r in [256, 192, 128, 384] {
        for gamma in [0.01, 0.002, 0.005, 0.02, 0.04] {
            let params = VdiParams {
                resolution: r,
                gamma,
                precision,
            };
            let vdi = generate(&rc, &camera, params, 0, "").expect("valid");
            let timed = |codec| {
                let t = Instant::now();
                let n = encode(&vdi, codec).expect("encodes").len();
                (n as f64, t.elapsed().as_secs_f64() * 1e3)
            };
            let (b, tb) = timed(Codec::Bzip2);
            let (z, tz) = timed(Codec::Zstd);
            let ratio = b / z;
            let k = *calibration.get_or_insert(ratio);
            let error = k * z / b - 1.0;
            worst = worst.max(error.abs());
            println!(
                "| {r} | {gamma} | {:.0} | {tb:.1} | {:.0} | {tz:.1} | {ratio:.3} | {:+.1} % |",
                b / 1e3,
                z / 1e3,
                100.0 * error
            );
        }
    }
    println!("worst error {:.1} %\n", 100.0 * worst);
}

fn main() {
    let rounds: usize = std::env::var("INSITU_BENCH_ROUNDS")
        .ok()
        .and_then(|s| s.parse().ok())
        .filter(|&n| n > 0)
        .unwrap_or(9);
    println!("{} threads", rayon::current_num_threads());
    let mut sim = GrayScott::new(128, GrayScottParams::default()).expect("grid size");
    sim.advance(1500);
    let gs = sim.v_volume();
    probe(
        "Gray–Scott 128³ after 1500 steps",
        &gs,
        Codec::Zstd,
        &[(256, 0.04), (192, 0.03), (128, 0.01)],
        rounds,
    );
    full_trial(
        "Gray–Scott 128³ after 1500 steps",
        &gs,
        &[(192, 0.03), (320, 0.04), (448, 0.05)],
        rounds,
    );
    let file = "ocean_temp_ts_180x90x19x12_float32.raw";
    let Some(path) = insitu_testenv::data_file(file) else {
        eprintln!("ocean skipped: needs {file} (docs/data.md)");
        return;
    };
    let ocean = RawFormat::from_file_name(&path)
        .and_then(|f| f.load(&path, 0, glam::Vec3::ONE))
        .expect("the ocean's first step");
    probe(
        "ocean 180×90×19, first step",
        &ocean,
        Codec::Bzip2,
        &[(256, 0.02), (192, 0.01), (128, 0.005)],
        rounds,
    );
    full_trial(
        "ocean 180×90×19, first step",
        &ocean,
        &[(192, 0.01), (320, 0.03), (448, 0.06)],
        rounds,
    );
    if std::env::var("INSITU_PROBE_PROXY").is_ok_and(|v| v == "0") {
        return;
    }
    for precision in [Precision::Bits(8), Precision::Float32] {
        proxy("ocean 180×90×19, first step", &ocean, precision);
        proxy("Gray–Scott 128³ after 1500 steps", &gs, precision);
    }
}
