//! The VDI codec side by side: σ, q and encode/decode speed of today's float planes (bzip2,
//! zstd) against the quantised format at each precision, on the demo's Gray–Scott 64³, the
//! shared volumes at their TFs and the ocean's first step.
//!
//! For each scene and `P_M`: the VDI is generated once, encoded with each codec and
//! precision, decoded, and rendered at the generation view and orbited by 10°–60° (256², as
//! the tuner scores); q is the pooled PSNR against the DVR of each view, Δq its change against
//! the float VDI, and `q vs f32` the PSNR of the decoded VDI's renders against the float
//! VDI's (how far the quantisation alone moves the picture). Encoding and decoding are timed
//! as the median of `INSITU_BENCH_ROUNDS` (default 5) on all the pool's threads.
//!
//! With `INSITU_BENCH_PLANES=DIR`, each VDI's six float planes are also written there
//! (`<scene>.<plane>.f32`, little-endian) with `<scene>.json` giving `n` and the quantiser's
//! error bounds, for `bench/codec_compare.py` to code them with SZ3 and ZFP at the same
//! bounds. Run: `cargo bench -p insitu-core --bench codec`.

#![allow(clippy::expect_used)] // a benchmark without its data cannot run

use insitu_core::metrics::{mse, psnr_from_mse};
use insitu_core::vdi::codec::{decode, encode, quantized::DepthGrid, Codec, DecodeLimits};
use insitu_core::vdi::{generate::generate, render::render, Precision, Vdi, VdiParams};
use insitu_core::volume::{GrayScott, GrayScottParams, RawFormat};
use insitu_core::{dvr, Camera, Image, RaycastParams, Raycaster, TransferFunction, Volume};
use std::time::Instant;

mod common;

const SIZE: u32 = 256;
const ANGLES: [f32; 7] = [0.0, 10.0, 20.0, 30.0, 40.0, 50.0, 60.0];

fn median_ms(rounds: usize, mut f: impl FnMut()) -> f64 {
    let mut t: Vec<f64> = (0..rounds)
        .map(|_| {
            let s = Instant::now();
            f();
            s.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    t.sort_by(f64::total_cmp);
    t[t.len() / 2]
}

fn renders(vdi: &Vdi, camera: &Camera) -> Vec<Image> {
    ANGLES
        .iter()
        .map(|&a| render(vdi, &camera.orbit_y(a), SIZE, SIZE, vdi.meta().termination))
        .collect()
}

fn pooled(a: &[Image], b: &[Image]) -> f64 {
    let m: f64 = a
        .iter()
        .zip(b)
        .map(|(x, y)| mse(x, y).expect("same sizes"))
        .sum::<f64>()
        / a.len() as f64;
    psnr_from_mse(m)
}

/// `vdi` to be written at `precision`.
fn with_precision(vdi: &Vdi, precision: Precision) -> Vdi {
    let mut v = vdi.clone();
    v.set_precision(precision);
    v
}

fn write_planes(dir: &str, name: &str, vdi: &Vdi) {
    let segs = vdi.supersegments();
    type Plane = (&'static str, fn(&insitu_core::vdi::Supersegment) -> f32);
    let planes: [Plane; 6] = [
        ("z_start", |s| s.z_start),
        ("z_end", |s| s.z_end),
        ("red", |s| s.color[0]),
        ("green", |s| s.color[1]),
        ("blue", |s| s.color[2]),
        ("alpha", |s| s.alpha),
    ];
    for (plane, get) in planes {
        let bytes: Vec<u8> = segs.iter().flat_map(|s| get(s).to_le_bytes()).collect();
        std::fs::write(format!("{dir}/{name}.{plane}.f32"), bytes).expect("writable dir");
    }
    let max_z = segs.iter().fold(0.0f32, |m, s| m.max(s.z_end));
    let grid = DepthGrid::new(vdi.meta().sample_distance, max_z);
    let counts: Vec<u8> = vdi
        .offsets()
        .windows(2)
        .flat_map(|w| (w[1] - w[0]).to_le_bytes())
        .collect();
    std::fs::write(format!("{dir}/{name}.counts.u32"), counts).expect("writable dir");
    std::fs::write(
        format!("{dir}/{name}.json"),
        format!(
            "{{\"n\": {}, \"pixels\": {}, \"depth_bound\": {}, \"color_bound_8\": {}, \"sigma_bzip2_f32\": {}, \"sigma_8bit\": {}}}",
            segs.len(),
            vdi.offsets().len() - 1,
            grid.quantum() / 2.0,
            Precision::Bits(8).color_bound(),
            encode(vdi, Codec::Bzip2).expect("encodes").len(),
            encode(&with_precision(vdi, Precision::Bits(8)), Codec::Zstd)
                .expect("encodes")
                .len(),
        ),
    )
    .expect("writable dir");
}

fn scene(name: &str, volume: &Volume, tf: &TransferFunction, pm: &[(u32, f32)], rounds: usize) {
    let rc = Raycaster::new(volume, tf, RaycastParams::default()).expect("valid params");
    let camera = Camera::default_for_box(&volume.world_box());
    let references: Vec<Image> = ANGLES
        .iter()
        .map(|&a| dvr::render(&rc, &camera.orbit_y(a), SIZE, SIZE))
        .collect();
    let limits = DecodeLimits::default();
    for &(r, gamma) in pm {
        let params = VdiParams {
            resolution: r,
            gamma,
            precision: Precision::Float32,
        };
        let vdi = generate(&rc, &camera, params, 0, name).expect("valid params");
        if let Ok(dir) = std::env::var("INSITU_BENCH_PLANES") {
            write_planes(&dir, &format!("{name}-r{r}"), &vdi);
        }
        let exact = renders(&vdi, &camera);
        let q_float = pooled(&exact, &references);
        let mut baseline = None;
        println!(
            "\n{name}, r {r} γ {gamma}: {} supersegments, q {q_float:.2} dB (f32)",
            vdi.supersegments().len()
        );
        println!("| codec | precision | σ (kB) | × smaller than bzip2 f32 | q (dB) | Δq (dB) | q vs f32 (dB) | encode (ms) | decode (ms) | encode MB/s | decode MB/s |");
        println!("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
        for (codec, precision) in [
            (Codec::Bzip2, Precision::Float32),
            (Codec::Zstd, Precision::Float32),
            (Codec::Zstd, Precision::Bits(16)),
            (Codec::Zstd, Precision::Bits(12)),
            (Codec::Zstd, Precision::Bits(10)),
            (Codec::Zstd, Precision::Bits(8)),
            (Codec::Zstd, Precision::Bits(6)),
            (Codec::Bzip2, Precision::Bits(10)),
        ] {
            let v = with_precision(&vdi, precision);
            let bytes = encode(&v, codec).expect("encodes");
            let enc = median_ms(rounds, || {
                std::hint::black_box(encode(&v, codec).expect("encodes"));
            });
            let dec = median_ms(rounds, || {
                std::hint::black_box(decode(&bytes, &limits).expect("decodes"));
            });
            let decoded = decode(&bytes, &limits).expect("decodes");
            let images = renders(&decoded, &camera);
            let q = pooled(&images, &references);
            let sigma = bytes.len() as f64;
            let base = *baseline.get_or_insert(sigma);
            let mb = vdi.memory_bytes() as f64 / 1e6;
            println!(
                "| {codec} | {precision} | {:.1} | {:.2} | {q:.2} | {:+.2} | {:.1} | {enc:.1} | {dec:.1} | {:.0} | {:.0} |",
                sigma / 1e3,
                base / sigma,
                q - q_float,
                pooled(&images, &exact),
                mb / enc * 1e3,
                mb / dec * 1e3,
            );
        }
    }
}

/// Across time: each step's 8-bit file (entropy stage `none`) compressed with zstd alone and
/// with the previous step's as a raw-content dictionary, the most a predictor from the
/// previous step at the same `P_M` could find in what zstd can match.
fn across_time(name: &str, steps: &[Volume], tf: &TransferFunction, (r, gamma): (u32, f32)) {
    let params = VdiParams {
        resolution: r,
        gamma,
        precision: Precision::Bits(8),
    };
    let files: Vec<Vec<u8>> = steps
        .iter()
        .map(|v| {
            let rc = Raycaster::new(v, tf, RaycastParams::default()).expect("valid params");
            let camera = Camera::default_for_box(&v.world_box());
            let vdi = generate(&rc, &camera, params, 0, name).expect("valid params");
            encode(&vdi, Codec::None).expect("encodes")
        })
        .collect();
    let (mut alone, mut with_previous) = (0usize, 0usize);
    for w in files.windows(2) {
        alone += zstd::bulk::compress(&w[1], 3).expect("compresses").len();
        with_previous += zstd::bulk::Compressor::with_dictionary(3, &w[0])
            .and_then(|mut c| c.compress(&w[1]))
            .expect("compresses")
            .len();
    }
    println!(
        "{name}, r {r} γ {gamma}, 8 bits, {} steps after the first: {:.1} kB alone, {:.1} kB with the previous step as a dictionary ({:+.1} %)",
        files.len() - 1,
        alone as f64 / 1e3,
        with_previous as f64 / 1e3,
        (with_previous as f64 / alone as f64 - 1.0) * 100.0
    );
}

fn main() {
    let rounds: usize = std::env::var("INSITU_BENCH_ROUNDS")
        .ok()
        .and_then(|s| s.parse().ok())
        .filter(|&n| n > 0)
        .unwrap_or(5);
    println!(
        "{} threads; q pooled over 0°–60° at {SIZE}²",
        rayon::current_num_threads()
    );
    let mut sim = GrayScott::new(64, GrayScottParams::default()).expect("grid size");
    sim.advance(3000);
    let gs = sim.v_volume();
    let tf = TransferFunction::default_for_volume(&gs).tf;
    scene(
        "gray-scott-64",
        &gs,
        &tf,
        &[(256, 0.013), (128, 0.033)],
        rounds,
    );
    for (file, tf, pm) in [
        (
            "teapot_256x256x178_uint8.raw",
            Some("teapot.json"),
            (512, 0.013),
        ),
        (
            "hydrogen_64x64x64_float32.raw",
            Some("hydrogen.json"),
            (256, 0.013),
        ),
        ("neghip_66x66x66_uint8.raw", None, (256, 0.013)),
        ("stent_128x128x256_int16.raw", None, (256, 0.013)),
    ] {
        match common::shared(file, tf) {
            Ok((volume, tf)) => scene(file, &volume, &tf, &[pm], rounds),
            Err(e) => eprintln!("{file} skipped: {e}"),
        }
    }
    let file = "ocean_temp_ts_180x90x19x12_float32.raw";
    match insitu_testenv::data_file(file).map(|path| {
        RawFormat::from_file_name(&path).and_then(|f| f.load(&path, 0, glam::Vec3::ONE))
    }) {
        Some(Ok(ocean)) => {
            let tf = TransferFunction::default_for_volume(&ocean).tf;
            scene("ocean-step0", &ocean, &tf, &[(256, 0.02)], rounds);
        }
        _ => eprintln!("ocean skipped: needs {file} (docs/data.md)"),
    }

    println!();
    let mut sim = GrayScott::new(64, GrayScottParams::default()).expect("grid size");
    sim.advance(3000);
    let steps: Vec<Volume> = (0..6)
        .map(|_| {
            sim.advance(100);
            sim.v_volume()
        })
        .collect();
    across_time("gray-scott-64 every 100 steps", &steps, &tf, (256, 0.025));
    if let Some(path) = insitu_testenv::data_file(file) {
        let steps: Vec<Volume> = (0..6)
            .filter_map(|t| {
                RawFormat::from_file_name(&path)
                    .and_then(|f| f.load(&path, t, glam::Vec3::ONE))
                    .ok()
            })
            .collect();
        let tf = TransferFunction::default_for_volume(&steps[0]).tf;
        across_time("ocean months 0–5", &steps, &tf, (256, 0.02));
    }
}
