//! Hard cases: never NaN or Inf anywhere (image, VDI, metric), never a panic.

use crate::common::assert_valid;
use glam::Vec3;
use insitu_core::vdi::codec::{decode, encode, Codec, DecodeLimits};
use insitu_core::vdi::{generate::generate, render, VdiParams};
use insitu_core::{dvr, metrics, Camera, RaycastParams, Raycaster, TransferFunction, Vdi, Volume};

pub fn assert_vdi_finite(vdi: &Vdi, what: &str) {
    for s in vdi.supersegments() {
        let vals = [
            s.z_start, s.z_end, s.color[0], s.color[1], s.color[2], s.alpha,
        ];
        assert!(
            vals.iter().all(|v| v.is_finite()),
            "{what}: non-finite supersegment {s:?}"
        );
        assert!(
            s.z_start <= s.z_end && (0.0..=1.0).contains(&s.alpha),
            "{what}: {s:?}"
        );
    }
}

/// Runs DVR, VDI generation, codec round trip and VDI rendering at 0°, 90° and 180°, and the
/// metrics between them; checks everything is finite.
fn exercise(
    volume: &Volume,
    tf: &TransferFunction,
    params: RaycastParams,
    vp: VdiParams,
    camera: Option<Camera>,
    what: &str,
) {
    let rc = Raycaster::new(volume, tf, params).unwrap();
    let cam = camera.unwrap_or_else(|| Camera::default_for_box(&volume.world_box()));
    let vdi = generate(&rc, &cam, vp, tf.identity_hash(), what).unwrap();
    assert_vdi_finite(&vdi, what);
    crate::common::assert_simd_matches_scalar(&rc, &cam, Some(vp), what);
    let bytes = encode(&vdi, Codec::Zstd).unwrap();
    let back = decode(&bytes, &DecodeLimits::default()).unwrap();
    assert_eq!(back, vdi, "{what}: codec round trip");
    for angle in [0.0, 90.0, 180.0, 270.0, 45.0] {
        let view = cam.orbit_y(angle);
        let reference = dvr::render(&rc, &view, 24, 24);
        let image = render::render(&vdi, &view, 24, 24, params.termination);
        assert_valid(&reference, what);
        assert_valid(&image, what);
        let q = metrics::psnr(&image, &reference).unwrap();
        assert!(!q.is_nan(), "{what}: PSNR NaN at {angle}°");
        let s = metrics::ssim(&image, &reference).unwrap();
        assert!(s.is_finite(), "{what}: SSIM {s} at {angle}°");
    }
    #[cfg(feature = "gpu")]
    crate::gpu::exercise(&rc, &cam, vp, &vdi, what);
}

fn ramp_tf() -> TransferFunction {
    TransferFunction::default_for_range(0.0, 1.0)
}

fn blob() -> Volume {
    Volume::from_fn([17, 13, 11], |x, y, z| {
        ((x * 7 + y * 3 + z) % 11) as f32 / 10.0
    })
    .unwrap()
}

const VP: VdiParams = VdiParams {
    resolution: 24,
    gamma: 0.01,
    precision: insitu_core::Precision::Float32,
};

#[test]
fn all_nan_volume() {
    let v = Volume::from_fn([8, 8, 8], |_, _, _| f32::NAN).unwrap();
    exercise(
        &v,
        &ramp_tf(),
        RaycastParams::default(),
        VP,
        None,
        "all NaN",
    );
}

#[test]
fn partly_nan_volume() {
    let v = Volume::from_fn(
        [12, 12, 12],
        |x, y, _| if (x + y) % 3 == 0 { f32::NAN } else { 0.8 },
    )
    .unwrap();
    exercise(
        &v,
        &ramp_tf(),
        RaycastParams::default(),
        VP,
        None,
        "part NaN",
    );
}

#[test]
fn zero_and_constant_volumes() {
    let zero = Volume::from_fn([8, 8, 8], |_, _, _| 0.0).unwrap();
    exercise(
        &zero,
        &ramp_tf(),
        RaycastParams::default(),
        VP,
        None,
        "all zero",
    );
    let constant = Volume::from_fn([8, 8, 8], |_, _, _| 0.7).unwrap();
    exercise(
        &constant,
        &ramp_tf(),
        RaycastParams::default(),
        VP,
        None,
        "constant",
    );
}

#[test]
fn huge_dynamic_range() {
    let v = Volume::from_fn([10, 10, 10], |x, y, z| {
        10f32.powi((x + y + z) as i32 % 15 - 6)
    })
    .unwrap();
    let tf = TransferFunction::default_for_range(1e-6, 1e8);
    exercise(&v, &tf, RaycastParams::default(), VP, None, "1e-6..1e8");
    // Infinities from f64 overflow clamp to the domain ends.
    let inf = Volume::from_fn([6, 6, 6], |x, _, _| {
        if x % 2 == 0 {
            f32::INFINITY
        } else {
            f32::NEG_INFINITY
        }
    })
    .unwrap();
    exercise(&inf, &ramp_tf(), RaycastParams::default(), VP, None, "±inf");
}

#[test]
fn opaque_and_transparent_transfer_functions() {
    let opaque = TransferFunction::constant(0.0, 1.0, [1.0, 0.5, 0.0, 1.0]);
    exercise(
        &blob(),
        &opaque,
        RaycastParams::default(),
        VP,
        None,
        "opacity 1",
    );
    let none = TransferFunction::constant(0.0, 1.0, [1.0, 1.0, 1.0, 0.0]);
    exercise(
        &blob(),
        &none,
        RaycastParams::default(),
        VP,
        None,
        "transparent",
    );
    let v = blob();
    let rc = Raycaster::new(&v, &none, RaycastParams::default()).unwrap();
    let cam = Camera::default_for_box(&blob().world_box());
    let vdi = generate(&rc, &cam, VP, 0, "").unwrap();
    assert!(
        vdi.supersegments().is_empty(),
        "a transparent TF makes no supersegments"
    );
}

#[test]
fn extreme_gamma_and_resolution() {
    for gamma in [0.0, 10.0] {
        exercise(
            &blob(),
            &ramp_tf(),
            RaycastParams::default(),
            VdiParams {
                resolution: 24,
                gamma,
                precision: Default::default(),
            },
            None,
            "gamma",
        );
    }
    exercise(
        &blob(),
        &ramp_tf(),
        RaycastParams::default(),
        VdiParams {
            resolution: 1,
            gamma: 0.01,
            precision: Default::default(),
        },
        None,
        "r = 1",
    );
    // γ = 10 never interrupts: at most one supersegment per pixel.
    let v = blob();
    let rc = Raycaster::new(&v, &ramp_tf(), RaycastParams::default()).unwrap();
    let cam = Camera::default_for_box(&blob().world_box());
    let vdi = generate(
        &rc,
        &cam,
        VdiParams {
            resolution: 16,
            gamma: 10.0,
            precision: Default::default(),
        },
        0,
        "",
    )
    .unwrap();
    assert!((0..256).all(|p| vdi.count(p) <= 1));
}

#[test]
fn step_larger_than_the_volume() {
    let params = RaycastParams {
        sample_distance: 1000.0,
        ..Default::default()
    };
    exercise(&blob(), &ramp_tf(), params, VP, None, "huge step");
}

#[test]
fn camera_inside_the_volume() {
    let v = blob();
    let b = v.world_box();
    let cam = Camera {
        eye: b.center() + Vec3::new(0.5, 0.2, 1.0),
        target: b.center() - Vec3::Z,
        up: Vec3::Y,
        fov_y_deg: 60.0,
    };
    exercise(
        &v,
        &ramp_tf(),
        RaycastParams::default(),
        VP,
        Some(cam),
        "camera inside",
    );
    // A VDI from outside, viewed from inside.
    let rc = Raycaster::new(&v, &ramp_tf(), RaycastParams::default()).unwrap();
    let outside = Camera::default_for_box(&b);
    let vdi = generate(&rc, &outside, VP, 0, "").unwrap();
    let image = render::render(&vdi, &cam, 24, 24, 0.99);
    assert_valid(&image, "inside view of an outside VDI");
}

#[test]
fn single_voxel_and_flat_volumes() {
    let one = Volume::from_fn([1, 1, 1], |_, _, _| 0.5).unwrap();
    exercise(
        &one,
        &ramp_tf(),
        RaycastParams::default(),
        VP,
        None,
        "1 voxel",
    );
    let flat = Volume::from_fn([9, 9, 1], |x, _, _| x as f32 / 8.0).unwrap();
    exercise(
        &flat,
        &ramp_tf(),
        RaycastParams::default(),
        VP,
        None,
        "flat",
    );
}

#[test]
fn shading_on_hard_data() {
    let params = RaycastParams {
        shading: Some(Default::default()),
        ..Default::default()
    };
    let v = Volume::from_fn([12, 12, 12], |x, _, _| {
        if x == 5 {
            f32::NAN
        } else {
            x as f32 / 11.0
        }
    })
    .unwrap();
    exercise(&v, &ramp_tf(), params, VP, None, "shaded with NaN");
}
