//! GPU against CPU for the three kernels: reference DVR, VDI generation (r = 768 and 256,
//! γ = 0.013) and VDI rendering from 30°, on the teapot (768², step 0.5,
//! `data/tf/teapot.json`) and on an analytic 256³ field, at 768² and 1920×1080; and
//! generation alone on the same field at 432³ for r = 160, 352 and 544, the volume size and
//! resolutions of the seed paper's generation times (Sec. 6, a GTX 980).
//!
//! A bench binary rather than criterion: each GPU row reports two times, the wall clock of
//! the call (uploads of the camera, read-back of the result) and the kernel time from GPU
//! timestamps where the adapter has them. Medians of `INSITU_BENCH_RUNS` runs (default 5)
//! after one warm-up. Run: `cargo bench -p insitu-core --features gpu --bench gpu`.
//! Uses any adapter, software ones too (`WGPU_ADAPTER_NAME` picks one).

#![allow(clippy::expect_used, clippy::unwrap_used)] // a benchmark without its inputs cannot run

use insitu_core::backend::{Backend, BackendChoice, Timed};
use insitu_core::{Camera, RaycastParams, Raycaster, TransferFunction, VdiParams, Volume};

mod common;

/// Median wall and median reported time (with its source) of `runs` calls after a warm-up.
fn time<T>(runs: usize, mut f: impl FnMut() -> Timed<T>) -> (f64, f64, &'static str) {
    let _ = f();
    let mut wall = Vec::with_capacity(runs);
    let mut reported = Vec::with_capacity(runs);
    let mut source = "";
    for _ in 0..runs {
        let t = f();
        wall.push(t.wall_s);
        reported.push(t.seconds);
        source = match t.source {
            insitu_core::backend::TimeSource::WallClock => "wall",
            insitu_core::backend::TimeSource::GpuTimestamps => "timestamps",
        };
    }
    let median = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    (median(&mut wall), median(&mut reported), source)
}

fn row(what: &str, cpu: (f64, f64, &str), gpu: (f64, f64, &str)) {
    println!(
        "{what:<36} {:>9.1} {:>9.1} {:>9.1} ({})  {:>6.2}×",
        cpu.0 * 1e3,
        gpu.0 * 1e3,
        gpu.1 * 1e3,
        gpu.2,
        cpu.0 / gpu.0
    );
}

fn bench_scene(
    name: &str,
    (volume, tf): (&Volume, &TransferFunction),
    sizes: &[(u32, u32)],
    resolutions: &[u32],
    backends: (&Backend, &Backend),
    runs: usize,
) {
    let rc = Raycaster::new(volume, tf, RaycastParams::default()).unwrap();
    let (cpu, gpu) = (
        backends.0.prepare(&rc).unwrap(),
        backends.1.prepare(&rc).unwrap(),
    );
    let cam = Camera::default_for_box(&volume.world_box());
    let side = cam.orbit_y(30.0);
    for &(w, h) in sizes {
        row(
            &format!("{name} DVR {w}×{h}"),
            time(runs, || cpu.dvr(&cam, w, h).unwrap()),
            time(runs, || gpu.dvr(&cam, w, h).unwrap()),
        );
    }
    for &r in resolutions {
        let p = VdiParams {
            resolution: r,
            gamma: 0.013,
            precision: Default::default(),
        };
        row(
            &format!("{name} generate r={r}"),
            time(runs, || cpu.generate(&cam, p, 0, name).unwrap()),
            time(runs, || gpu.generate(&cam, p, 0, name).unwrap()),
        );
        if sizes.is_empty() {
            continue;
        }
        let vdi = cpu.generate(&cam, p, 0, name).unwrap().value;
        let (cv, gv) = (
            cpu.prepare_vdi(&vdi).unwrap(),
            gpu.prepare_vdi(&vdi).unwrap(),
        );
        for &(w, h) in sizes {
            row(
                &format!("{name} render r={r} 30° {w}×{h}"),
                time(runs, || cv.render(&side, w, h, 0.99).unwrap()),
                time(runs, || gv.render(&side, w, h, 0.99).unwrap()),
            );
        }
    }
}

fn main() {
    let runs: usize = std::env::var("INSITU_BENCH_RUNS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(5);
    let cpu = Backend::select(BackendChoice::Cpu).unwrap();
    let gpu = match Backend::select(BackendChoice::Gpu) {
        Ok(g) => g,
        Err(e) => {
            eprintln!("GPU bench needs an adapter: {e}");
            return;
        }
    };
    println!(
        "CPU: {}\nGPU: {}\nmedians of {runs} runs, ms",
        cpu.describe(),
        gpu.describe()
    );
    println!(
        "{:<36} {:>9} {:>9} {:>9}              {:>7}",
        "kernel", "CPU wall", "GPU wall", "GPU kern", "CPU/GPU"
    );
    let sizes = [(768, 768), (1920, 1080)];
    match common::teapot() {
        Ok((v, tf)) => bench_scene("teapot", (&v, &tf), &sizes, &[768, 256], (&cpu, &gpu), runs),
        Err(e) => eprintln!("skipping the teapot: {e}"),
    }
    let tf = TransferFunction::from_json(
        r#"{"domain": [0, 3], "points": [[0,0,0,0,0],[0.45,0.1,0.3,0.9,0],[0.6,0.2,0.8,0.4,0.05],[0.8,1,0.8,0.2,0.2],[1,1,1,1,0.6]]}"#,
        "waves",
    )
    .unwrap();
    let field = waves(256);
    let backends = (&cpu, &gpu);
    bench_scene(
        "waves 256³",
        (&field, &tf),
        &sizes,
        &[768, 256],
        backends,
        runs,
    );
    drop(field);
    let field = waves(432);
    bench_scene(
        "waves 432³",
        (&field, &tf),
        &[],
        &[160, 352, 544],
        backends,
        runs,
    );
}

/// A smooth n³ field with structure at several scales (no data files needed).
fn waves(n: usize) -> Volume {
    Volume::from_fn([n, n, n], |x, y, z| {
        let p = [x, y, z].map(|c| c as f32 / n as f32 * std::f32::consts::TAU);
        (p[0] * 2.0).sin() * (p[1] * 3.0).cos() + (p[2] * 1.5).sin() * 0.5 + 1.5
    })
    .unwrap()
}
