//! The GPU backend against the CPU path (issue: GPU parity). Runs on whatever adapter wgpu
//! finds (lavapipe in CI). No adapter fails the test unless `INSITU_SKIP_GPU_TESTS=1`.

use crate::common::{assert_valid, shared_scenes};
use insitu_core::gpu::{Gpu, GpuError, GpuScene, GpuVdi};
use insitu_core::vdi::{generate::generate, render, VdiParams};
use insitu_core::{dvr, metrics, Camera, RaycastParams, Raycaster};
use std::sync::OnceLock;

/// One device for the whole test binary.
pub fn gpu() -> Option<&'static Gpu> {
    static GPU: OnceLock<Option<Gpu>> = OnceLock::new();
    GPU.get_or_init(|| match Gpu::new(true) {
        Ok(g) => {
            eprintln!("GPU tests on {}", g.describe());
            Some(g)
        }
        Err(e @ GpuError::NoAdapter(_)) => {
            if std::env::var("INSITU_SKIP_GPU_TESTS").as_deref() == Ok("1") {
                eprintln!("SKIPPED: GPU tests need an adapter: {e}");
                None
            } else {
                panic!("GPU tests need an adapter (install mesa-vulkan-drivers, or set INSITU_SKIP_GPU_TESTS=1): {e}");
            }
        }
        Err(e) => panic!("opening the GPU failed: {e}"),
    })
    .as_ref()
}

#[test]
fn gpu_matches_cpu_on_real_data() {
    let Some(gpu) = gpu() else { return };
    const SIZE: u32 = 128;
    for (name, volume, tf) in shared_scenes() {
        let rc = Raycaster::new(&volume, &tf, RaycastParams::default()).unwrap();
        let cam = Camera::default_for_box(&volume.world_box());
        let scene = GpuScene::new(gpu, &rc).unwrap();
        let cpu_dvr = dvr::render(&rc, &cam, SIZE, SIZE);
        let gpu_dvr = scene.dvr(&cam, SIZE, SIZE).unwrap().value;
        assert_valid(&gpu_dvr, name);
        let q = metrics::psnr(&gpu_dvr, &cpu_dvr).unwrap();
        eprintln!("{name}: GPU DVR vs CPU DVR {q:.2} dB");
        assert!(q >= 50.0, "{name}: GPU DVR vs CPU DVR {q} dB");
        let params = VdiParams {
            resolution: SIZE,
            gamma: 0.013,
        };
        let cpu_vdi = generate(&rc, &cam, params, 0, name).unwrap();
        let gpu_vdi = scene.generate(&cam, params, 0, name).unwrap().value;
        let n = (SIZE * SIZE) as usize;
        let equal = (0..n)
            .filter(|&p| cpu_vdi.count(p) == gpu_vdi.count(p))
            .count();
        let share = equal as f64 / n as f64;
        eprintln!(
            "{name}: counts equal on {:.3}% of pixels ({} vs {} supersegments)",
            100.0 * share,
            cpu_vdi.supersegments().len(),
            gpu_vdi.supersegments().len()
        );
        assert!(share >= 0.99, "{name}: counts equal on {share}");
        let view = cam.orbit_y(30.0);
        let cpu_render = render::render(&cpu_vdi, &view, SIZE, SIZE, 0.99);
        let gpu_render_of_gpu_vdi = GpuVdi::new(gpu, &gpu_vdi)
            .unwrap()
            .render(&view, SIZE, SIZE, 0.99)
            .unwrap()
            .value;
        assert_valid(&gpu_render_of_gpu_vdi, name);
        let q30 = metrics::psnr(&gpu_render_of_gpu_vdi, &cpu_render).unwrap();
        eprintln!("{name}: renders at 30° {q30:.2} dB");
        assert!(q30 >= 45.0, "{name}: 30° renders {q30} dB");
        let at_gen = GpuVdi::new(gpu, &gpu_vdi)
            .unwrap()
            .render(&cam, SIZE, SIZE, 0.99)
            .unwrap()
            .value;
        let q0 = metrics::psnr(&at_gen, &gpu_dvr).unwrap();
        eprintln!("{name}: GPU VDI render at generation view vs GPU DVR {q0:.2} dB");
        assert!(q0 >= 60.0, "{name}: {q0} dB");
    }
}
