//! How DVR, VDI generation, peak memory and VDI size grow with the volume:
//! the teapot (with `teapot.json`; docs/data.md) resampled trilinearly to N³ for N = 128, 256,
//! 512 and 1024, as u8 (rounded) and as f32, rendered and generated at 768² / r = 768 from
//! 30°, step 0.5 voxel of the resampled grid, γ = 0.013, CPU backend.
//!
//! Each case runs in a child process of this binary, so its peak resident memory (`VmHWM`,
//! reset once the field is built and the teapot it was resampled from is dropped, less the
//! process's footprint without the field) is its own. Generation runs first: the table gives
//! its peak, the field's size in its own type, the VDI's in-memory size and the ratio
//! peak / (field + VDI) whose target is ≤ 1.3, then the process's peak once the DVR has run
//! too (its 768² image, 7 MiB, which the allocator may keep after it is freed). `@0.99/DVR`
//! is generation stopping its rays at opacity 0.99, as the DVR does, over the DVR: what the
//! default (rays to the box exit, no holes behind dense structures) costs. Times are medians
//! of 3 runs after a warm-up.
//! Run: `cargo bench -p insitu-core --bench scale` (`INSITU_SCALE_SIZES=128,256` for fewer
//! sizes; 1024³ f32 needs about 5 GiB).

#![allow(clippy::expect_used)] // a benchmark without its data or parameters cannot run

use insitu_core::vdi::generate::generate;
use insitu_core::vdi::VdiParams;
use insitu_core::{dvr, Camera, RaycastParams, Raycaster, Volume};
use rayon::prelude::*;
use std::time::Instant;

mod common;
use common::median;

const SIZE: u32 = 768;
const ROUNDS: usize = 3;

/// A status line of `/proc/self/status`, kB.
fn status_kb(key: &str) -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with(key))
                .and_then(|l| l.split_whitespace().nth(1)?.parse().ok())
        })
        .unwrap_or(0)
}

/// `src` resampled trilinearly to `n³` voxels, written straight into the new field in type
/// `T` (`convert` from the f32 value).
fn resample<T: Copy + Default + Send>(src: &Volume, n: usize, convert: fn(f32) -> T) -> Vec<T> {
    let probe = Raycaster::new(
        src,
        &insitu_core::TransferFunction::default_for_range(0.0, 1.0),
        RaycastParams::default(),
    )
    .expect("valid");
    let d = src.dims();
    let scale = d.map(|m| (m - 1) as f32 / (n - 1) as f32);
    // Room for the byte storage's padding: no reallocation (and copy) when it is added.
    let mut data = Vec::with_capacity(n * n * n + 4);
    data.resize(n * n * n, T::default());
    data.par_chunks_mut(n * n)
        .enumerate()
        .for_each(|(z, plane)| {
            for (i, v) in plane.iter_mut().enumerate() {
                let (x, y) = (i % n, i / n);
                *v = convert(probe.sample(glam::Vec3::new(
                    x as f32 * scale[0],
                    y as f32 * scale[1],
                    z as f32 * scale[2],
                )));
            }
        });
    data
}

/// One size and type, in this (child) process: prints one table row.
fn run(n: usize, bytes: bool) {
    let (teapot, tf) = common::teapot().expect("the teapot scene");
    let volume = if bytes {
        Volume::from_u8(
            [n; 3],
            glam::Vec3::ONE,
            resample(&teapot, n, |v| v.round() as u8),
        )
    } else {
        Volume::new([n; 3], glam::Vec3::ONE, resample(&teapot, n, |v| v))
    }
    .expect("valid field");
    drop(teapot);
    // The baseline is the process without the field and without the teapot it was resampled
    // from; the peak is counted from here on (writing 5 to `clear_refs` resets `VmHWM`).
    let field = volume.storage_bytes() as u64;
    let base_kb = status_kb("VmRSS:").saturating_sub(field / 1024);
    std::fs::write("/proc/self/clear_refs", "5").expect("VmHWM reset (Linux ≥ 4.0)");
    let rc = Raycaster::new(&volume, &tf, RaycastParams::default()).expect("valid");
    let cam = Camera::default_for_box(&volume.world_box()).orbit_y(30.0);
    let vp = VdiParams {
        resolution: SIZE,
        gamma: 0.013,
        precision: Default::default(),
    };
    let time = |f: &mut dyn FnMut()| {
        f();
        median(
            (0..ROUNDS)
                .map(|_| {
                    let t = Instant::now();
                    f();
                    t.elapsed().as_secs_f64()
                })
                .collect(),
        )
    };
    let mut vdi_bytes = 0u64;
    let gen_s = time(&mut || {
        let vdi = generate(&rc, &cam, vp, 0, "scale").expect("generates");
        vdi_bytes = (vdi.supersegments().len() * 24 + vdi.offsets().len() * 4) as u64;
    });
    let peak = status_kb("VmHWM:").saturating_sub(base_kb) * 1024;
    let dvr_s = time(&mut || {
        std::hint::black_box(dvr::render(&rc, &cam, SIZE, SIZE));
    });
    let with_dvr = status_kb("VmHWM:").saturating_sub(base_kb) * 1024;
    // What the default's rays to the box exit cost: generation stopping where the DVR stops.
    let stopping = RaycastParams {
        generation_termination: Some(RaycastParams::default().termination),
        ..RaycastParams::default()
    };
    let rc_stopping = Raycaster::new(&volume, &tf, stopping).expect("valid");
    let stopping_s = time(&mut || {
        std::hint::black_box(generate(&rc_stopping, &cam, vp, 0, "scale").expect("generates"));
    });
    let mib = |b: u64| b as f64 / (1024.0 * 1024.0);
    println!(
        "{n:>5}³ {:>4} {:>9.1}  {dvr_s:>8.3}  {gen_s:>8.3}  {:>6.2}  {:>7.2}  {:>9.1}  {:>9.1}  {:>5.2}  {:>9.1}",
        if bytes { "u8" } else { "f32" },
        mib(field),
        gen_s / dvr_s,
        stopping_s / dvr_s,
        mib(vdi_bytes),
        mib(peak),
        peak as f64 / (field + vdi_bytes) as f64,
        mib(with_dvr),
    );
}

fn main() {
    if let Ok(case) = std::env::var("INSITU_SCALE_CHILD") {
        let (n, ty) = case.split_once(':').expect("N:type");
        run(n.parse().expect("a size"), ty == "u8");
        return;
    }
    if let Err(e) = common::teapot() {
        eprintln!("scale bench skipped: {e}");
        return;
    }
    let sizes = std::env::var("INSITU_SCALE_SIZES").unwrap_or_else(|_| "128,256,512,1024".into());
    println!(
        "teapot resampled to N³, 768², 30°, step 0.5, r = 768, γ = 0.013, CPU ({} threads); medians of {ROUNDS}",
        rayon::current_num_threads()
    );
    println!(
        "    N  type field MiB    DVR s     gen s  gen/DVR  @0.99/DVR  VDI MiB   peak MiB  peak/(field+VDI)  +DVR MiB"
    );
    let exe = std::env::current_exe().expect("own path");
    for n in sizes
        .split(',')
        .filter_map(|s| s.trim().parse::<usize>().ok())
    {
        for ty in ["u8", "f32"] {
            let status = std::process::Command::new(&exe)
                .env("INSITU_SCALE_CHILD", format!("{n}:{ty}"))
                .status()
                .expect("runs itself");
            if !status.success() {
                println!("{n:>5}³ {ty:>4} failed: {status}");
            }
        }
    }
}
