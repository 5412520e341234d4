//! The GPU backend against the CPU path (issue: GPU parity). Runs on whatever adapter wgpu
//! finds (lavapipe in CI). Without an adapter they skip (`insitu_testenv`).

use crate::common::{assert_valid, shared_scenes};
use crate::hard_cases::assert_vdi_finite;
use glam::Vec3;
use insitu_core::gpu::{Gpu, GpuError, GpuVdi, GpuVolume};
use insitu_core::vdi::codec::{decode, encode, Codec, DecodeLimits};
use insitu_core::vdi::{generate::generate, render, VdiParams};
use insitu_core::{dvr, metrics, Camera, RaycastParams, Raycaster, TransferFunction, Vdi, Volume};
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
            insitu_testenv::skip(insitu_testenv::Need::Gpu, &format!("GPU tests: {e}"))
        }
        Err(e) => panic!("opening the GPU failed: {e}"),
    })
    .as_ref()
}

/// The GPU side of a hard case (`hard_cases::exercise`): DVR, generation and rendering at
/// 0°, 90°, 180°, 270° and 45° give finite images and VDIs, close to the CPU's, and the
/// CPU's VDI renders on the GPU.
pub fn exercise(rc: &Raycaster, cam: &Camera, vp: VdiParams, cpu_vdi: &Vdi, what: &str) {
    let Some(gpu) = gpu() else { return };
    let scene = GpuVolume::new(gpu, rc).unwrap();
    let vdi = scene.generate(cam, vp, 0, what).unwrap().value;
    assert_vdi_finite(&vdi, &format!("GPU {what}"));
    let on_gpu = GpuVdi::new(gpu, &vdi).unwrap();
    let cpu_vdi_on_gpu = GpuVdi::new(gpu, cpu_vdi).unwrap();
    let termination = rc.params().termination;
    for angle in [0.0, 90.0, 180.0, 270.0, 45.0] {
        let view = cam.orbit_y(angle);
        let gpu_dvr = scene.dvr(&view, 24, 24).unwrap().value;
        assert_valid(&gpu_dvr, &format!("GPU DVR {what} at {angle}°"));
        let cpu_dvr = dvr::render(rc, &view, 24, 24);
        let q = metrics::psnr(&gpu_dvr, &cpu_dvr).unwrap();
        assert!(q >= 40.0, "{what} at {angle}°: GPU vs CPU DVR {q} dB");
        for (image, which) in [
            (
                on_gpu.render(&view, 24, 24, termination).unwrap().value,
                "GPU VDI on GPU",
            ),
            (
                cpu_vdi_on_gpu
                    .render(&view, 24, 24, termination)
                    .unwrap()
                    .value,
                "CPU VDI on GPU",
            ),
        ] {
            assert_valid(&image, &format!("{which}, {what} at {angle}°"));
            let cpu = render::render(cpu_vdi, &view, 24, 24, termination);
            let q = metrics::psnr(&image, &cpu).unwrap();
            assert!(!q.is_nan(), "{which}, {what} at {angle}°: PSNR NaN");
        }
    }
}

/// The parity targets on the shared volumes, at 128² (`INSITU_GPU_PARITY_SIZE=768`
/// for the paper's size: same assertions, a minute on lavapipe).
#[test]
fn gpu_matches_cpu_on_real_data() {
    let Some(gpu) = gpu() else { return };
    let size: u32 = std::env::var("INSITU_GPU_PARITY_SIZE")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(128);
    let (size_u, n) = (size, (size * size) as usize);
    for (name, volume, tf) in shared_scenes() {
        let rc = Raycaster::new(&volume, &tf, RaycastParams::default()).unwrap();
        let cam = Camera::default_for_box(&volume.world_box());
        let scene = GpuVolume::new(gpu, &rc).unwrap();
        let cpu_dvr = dvr::render(&rc, &cam, size_u, size_u);
        let gpu_dvr = scene.dvr(&cam, size_u, size_u).unwrap().value;
        assert_valid(&gpu_dvr, name);
        let q = metrics::psnr(&gpu_dvr, &cpu_dvr).unwrap();
        eprintln!("{name}: GPU DVR vs CPU DVR {q:.2} dB");
        assert!(q >= 50.0, "{name}: GPU DVR vs CPU DVR {q} dB");
        let params = VdiParams {
            resolution: size_u,
            gamma: 0.013,
            precision: Default::default(),
        };
        let cpu_vdi = generate(&rc, &cam, params, 0, name).unwrap();
        let gpu_vdi = scene.generate(&cam, params, 0, name).unwrap().value;
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
        let cpu_render = render::render(&cpu_vdi, &view, size_u, size_u, 0.99);
        let gpu_render_of_gpu_vdi = GpuVdi::new(gpu, &gpu_vdi)
            .unwrap()
            .render(&view, size_u, size_u, 0.99)
            .unwrap()
            .value;
        assert_valid(&gpu_render_of_gpu_vdi, name);
        let q30 = metrics::psnr(&gpu_render_of_gpu_vdi, &cpu_render).unwrap();
        eprintln!("{name}: renders at 30° {q30:.2} dB");
        assert!(q30 >= 45.0, "{name}: 30° renders {q30} dB");
        let at_gen = GpuVdi::new(gpu, &gpu_vdi)
            .unwrap()
            .render(&cam, size_u, size_u, 0.99)
            .unwrap()
            .value;
        let q0 = metrics::psnr(&at_gen, &gpu_dvr).unwrap();
        eprintln!("{name}: GPU VDI render at generation view vs GPU DVR {q0:.2} dB");
        assert!(q0 >= 60.0, "{name}: {q0} dB");
        // Shading is compiled into the kernels only when a scene turns it on.
        let shaded = RaycastParams {
            shading: Some(insitu_core::Shading::default()),
            ..Default::default()
        };
        let rc = Raycaster::new(&volume, &tf, shaded).unwrap();
        let gpu_shaded = GpuVolume::new(gpu, &rc)
            .unwrap()
            .dvr(&cam, size_u, size_u)
            .unwrap()
            .value;
        let q = metrics::psnr(&gpu_shaded, &dvr::render(&rc, &cam, size_u, size_u)).unwrap();
        eprintln!("{name}: shaded GPU DVR vs CPU DVR {q:.2} dB");
        assert!(q >= 50.0, "{name}: shaded {q} dB");
    }
}

/// A 20×18×22 volume of diagonal stripes (a new value at nearly every sample), a ramp over
/// its range, and a camera 20° round from the default.
fn striped() -> (Volume, TransferFunction, Camera) {
    let v = Volume::from_fn([20, 18, 22], |x, y, z| {
        ((x * 7 + y * 3 + z * 5) % 13) as f32 / 12.0
    })
    .unwrap();
    let cam = Camera::default_for_box(&v.world_box()).orbit_y(20.0);
    (v, TransferFunction::default_for_range(0.0, 1.0), cam)
}

#[test]
fn bands_and_parts_give_the_same_result_as_one_pass() {
    let Some(shared) = gpu() else { return };
    // γ = 0 closes a supersegment at every sample: ~40 per ray.
    let (v, tf, cam) = striped();
    let rc = Raycaster::new(&v, &tf, RaycastParams::default()).unwrap();
    let params = VdiParams {
        resolution: 40,
        gamma: 0.0,
        precision: Default::default(),
    };
    let whole = GpuVolume::new(shared, &rc).unwrap();
    let reference_vdi = whole.generate(&cam, params, 0, "t").unwrap().value;
    let most = (0..40 * 40).map(|p| reference_vdi.count(p)).max().unwrap();
    assert!(
        most > insitu_core::gpu::INITIAL_BUDGET,
        "the case must have lists longer than the first slots ({most})"
    );
    // The second generation keeps every list in its slots (the budget grew): the same VDI.
    let again = whole.generate(&cam, params, 0, "t").unwrap().value;
    assert_eq!(again, reference_vdi, "lists copied from slots differ");
    // 64 KiB per binding: the rows' supersegments (~38 KiB a row) written one row a part.
    let mut mid = Gpu::new(true).unwrap();
    mid.cap_storage_binding(64 << 10);
    let vdi = GpuVolume::new(&mid, &rc)
        .unwrap()
        .generate(&cam, params, 0, "t")
        .unwrap()
        .value;
    assert_eq!(vdi, reference_vdi, "banded generation differs");
    let cpu = generate(&rc, &cam, params, 0, "t").unwrap();
    let equal = (0..40 * 40)
        .filter(|&p| cpu.count(p) == vdi.count(p))
        .count();
    assert!(
        equal >= 1584,
        "GPU and CPU counts equal on only {equal} of 1600 pixels"
    );
    // 4 KiB per binding: images of 40 × 40 in bands of 8 rows.
    let mut tiny = Gpu::new(true).unwrap();
    tiny.cap_storage_binding(4 << 10);
    let reference_dvr = whole.dvr(&cam, 40, 40).unwrap().value;
    let dvr_img = GpuVolume::new(&tiny, &rc)
        .unwrap()
        .dvr(&cam, 40, 40)
        .unwrap()
        .value;
    assert_eq!(
        dvr_img.pixels(),
        reference_dvr.pixels(),
        "banded DVR differs"
    );
    let coarse = whole
        .generate(
            &cam,
            VdiParams {
                resolution: 4,
                gamma: 0.26,
                precision: Default::default(),
            },
            0,
            "t",
        )
        .unwrap()
        .value;
    assert!(coarse.memory_bytes() < 4 << 10);
    let view = cam.orbit_y(30.0);
    let reference_render = GpuVdi::new(shared, &coarse)
        .unwrap()
        .render(&view, 40, 40, 0.99)
        .unwrap()
        .value;
    let render_img = GpuVdi::new(&tiny, &coarse)
        .unwrap()
        .render(&view, 40, 40, 0.99)
        .unwrap()
        .value;
    assert_eq!(
        render_img.pixels(),
        reference_render.pixels(),
        "banded render differs"
    );
    // A VDI over the binding limit is refused with the limit's name, not split.
    let err = GpuVdi::new(&tiny, &vdi).err().expect("over the limit");
    assert!(
        err.to_string().contains("max_storage_buffer_binding_size"),
        "{err}"
    );
    // So is a generation row whose supersegments cannot fit: 40 rays × ~40 × 24 bytes > 4 KiB.
    let err = GpuVolume::new(&tiny, &rc)
        .unwrap()
        .generate(&cam, params, 0, "t")
        .err()
        .expect("row over the limit");
    assert!(
        err.to_string().contains("max_storage_buffer_binding_size"),
        "{err}"
    );
}

/// A 24×20×16 volume of a ball of radius 8 (values falling from 8 at its centre), a ramp
/// over its range, and the default camera.
fn ball() -> (Volume, TransferFunction, Camera) {
    let v = Volume::from_fn([24, 20, 16], |x, y, z| {
        let d = Vec3::new(x as f32 - 12.0, y as f32 - 9.0, z as f32 - 8.0).length();
        (8.0 - d).max(0.0)
    })
    .unwrap();
    let cam = Camera::default_for_box(&v.world_box());
    (v, TransferFunction::default_for_range(0.0, 8.0), cam)
}

#[test]
fn counted_bands_join_into_the_vdi_of_one_band() {
    let Some(shared) = gpu() else { return };
    let (v, tf, cam) = ball();
    let rc = Raycaster::new(&v, &tf, RaycastParams::default()).unwrap();
    // γ = 10 merges every run of samples: at most one supersegment a ray (960 bytes a row).
    let params = VdiParams {
        resolution: 40,
        gamma: 10.0,
        precision: Default::default(),
    };
    let whole = GpuVolume::new(shared, &rc)
        .unwrap()
        .generate(&cam, params, 0, "t")
        .unwrap()
        .value;
    let rows_with_lists = (0..40)
        .filter(|&j| (0..40).any(|i| whole.count(i + 40 * j) > 0))
        .count();
    // Lists in at least three of the bands below.
    assert!(rows_with_lists >= 13, "{rows_with_lists} rows with lists");
    // 1 KiB per binding: the counts of 6 rows (and the total) a band, 7 bands.
    let mut small = Gpu::new(true).unwrap();
    small.cap_storage_binding(1 << 10);
    let banded = GpuVolume::new(&small, &rc)
        .unwrap()
        .generate(&cam, params, 0, "t")
        .unwrap()
        .value;
    assert_eq!(banded, whole, "generation in counted bands differs");
    let cpu = generate(&rc, &cam, params, 0, "t").unwrap();
    let equal = (0..40 * 40)
        .filter(|&p| cpu.count(p) == whole.count(p))
        .count();
    assert!(equal >= 1584, "GPU and CPU counts equal on {equal} of 1600");
}

#[test]
fn vdis_cross_between_backends_through_the_codec() {
    let Some(gpu) = gpu() else { return };
    let (v, tf, cam) = ball();
    let rc = Raycaster::new(&v, &tf, RaycastParams::default()).unwrap();
    let params = VdiParams {
        resolution: 48,
        gamma: 0.01,
        precision: Default::default(),
    };
    let gpu_vdi = GpuVolume::new(gpu, &rc)
        .unwrap()
        .generate(&cam, params, tf.identity_hash(), "blob")
        .unwrap()
        .value;
    let cpu_vdi = generate(&rc, &cam, params, tf.identity_hash(), "blob").unwrap();
    assert_eq!(gpu_vdi.meta(), cpu_vdi.meta());
    for codec in Codec::ALL {
        let from_gpu = decode(&encode(&gpu_vdi, codec).unwrap(), &DecodeLimits::default()).unwrap();
        assert_eq!(from_gpu, gpu_vdi, "{codec}: GPU VDI round trip");
        let from_cpu = decode(&encode(&cpu_vdi, codec).unwrap(), &DecodeLimits::default()).unwrap();
        let view = cam.orbit_y(30.0);
        // A GPU VDI rendered on the CPU against a CPU VDI rendered on the GPU.
        let a = render::render(&from_gpu, &view, 48, 48, 0.99);
        let b = GpuVdi::new(gpu, &from_cpu)
            .unwrap()
            .render(&view, 48, 48, 0.99)
            .unwrap()
            .value;
        let q = metrics::psnr(&a, &b).unwrap();
        assert!(q >= 45.0, "{codec}: {q} dB");
    }
}

/// Scratch and read-back buffers are kept between calls: results after larger calls (whose
/// buffers are reused, larger than asked for and holding their data) equal those of the
/// first calls on a fresh device, bit for bit.
#[test]
fn kept_buffers_leave_no_trace_in_later_results() {
    if gpu().is_none() {
        return;
    }
    let fresh = Gpu::new(true).unwrap();
    let (v, tf, cam) = striped();
    let rc = Raycaster::new(&v, &tf, RaycastParams::default()).unwrap();
    let view = cam.orbit_y(30.0);
    let scene = GpuVolume::new(&fresh, &rc).unwrap();
    let small = VdiParams {
        resolution: 24,
        gamma: 0.02,
        precision: Default::default(),
    };
    let run = |params: VdiParams, size: u32| {
        let vdi = scene.generate(&cam, params, 0, "t").unwrap().value;
        let dvr = scene.dvr(&cam, size, size).unwrap().value;
        let render = GpuVdi::new(&fresh, &vdi)
            .unwrap()
            .render(&view, size, size, 0.99)
            .unwrap()
            .value;
        (vdi, dvr, render)
    };
    let first = run(small, 20);
    // γ = 0: many more supersegments and a larger per-ray budget; larger images.
    let large = run(
        VdiParams {
            resolution: 64,
            gamma: 0.0,
            precision: Default::default(),
        },
        72,
    );
    assert!(large.0.supersegments().len() > 4 * first.0.supersegments().len());
    let again = run(small, 20);
    assert_eq!(again.0, first.0, "VDI after a larger generation");
    assert_eq!(again.1.pixels(), first.1.pixels(), "DVR after a larger one");
    assert_eq!(
        again.2.pixels(),
        first.2.pixels(),
        "render after a larger one"
    );
    assert!(
        first.1.pixels().iter().flatten().any(|&c| c > 0.0),
        "the DVR shows something"
    );
}
