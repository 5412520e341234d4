//! Helpers shared by the integration tests.

use insitu_core::volume::RawFormat;
use insitu_core::{Image, TransferFunction, Volume};

/// The CT teapot, the issues' benchmark volume.
pub const TEAPOT: &str = "teapot_256x256x178_uint8.raw";

/// Loads a real volume by file name, time step `t`, from wherever `insitu_testenv` finds it;
/// `None` (the test skips) where it is in none of the data folders.
pub fn shared_volume(name: &str, t: usize) -> Option<Volume> {
    let path = insitu_testenv::data_file(name)?;
    let format = RawFormat::from_file_name(&path).expect("shared data names carry their layout");
    Some(
        format
            .load(&path, t, glam::Vec3::ONE)
            .expect("shared volume loads"),
    )
}

/// Loads a transfer function of the real volumes by file name; `None` (the test skips) where
/// it is in none of the TF folders.
pub fn shared_tf(name: &str) -> Option<TransferFunction> {
    let path = insitu_testenv::tf_file(name)?;
    Some(TransferFunction::load(&path).expect("shared TF loads"))
}

/// Asserts that no channel of the image is NaN or infinite, and all lie in [0, 1].
pub fn assert_valid(image: &Image, what: &str) {
    assert!(
        image.is_valid(),
        "{what}: image has NaN, Inf or out-of-range values"
    );
}

/// The shared volumes with their transfer function (a ramp over the data range where
/// the TF folders have none).
pub fn shared_scenes() -> Vec<(&'static str, Volume, TransferFunction)> {
    let cases = [
        (TEAPOT, 0, Some("teapot.json")),
        ("stent_128x128x256_int16.raw", 0, None),
        ("hydrogen_64x64x64_float32.raw", 0, Some("hydrogen.json")),
        ("neghip_66x66x66_uint8.raw", 0, None),
        ("ocean_temp_ts_180x90x19x12_float32.raw", 5, None),
    ];
    let mut out = Vec::new();
    for (name, t, tf) in cases {
        let Some(volume) = shared_volume(name, t) else {
            continue;
        };
        let tf = match tf {
            Some(f) => match shared_tf(f) {
                Some(tf) => tf,
                None => continue,
            },
            None => {
                let (lo, hi) = volume.finite_range().expect("volume has data");
                TransferFunction::default_for_range(lo, hi)
            }
        };
        out.push((name, volume, tf));
    }
    out
}

/// The AVX2 path and the portable scalar path give bit-identical DVR images (the reference
/// frame and three orbit views, one from behind) and, with `vdi`, bit-identical VDIs. Where
/// the CPU lacks AVX2 both are the scalar path and the check is trivially met; it says so.
pub fn assert_simd_matches_scalar(
    rc: &insitu_core::Raycaster,
    cam: &insitu_core::Camera,
    vdi: Option<insitu_core::vdi::VdiParams>,
    what: &str,
) {
    use insitu_core::{dvr, vdi::generate::generate};
    if !rc.uses_simd() {
        eprintln!("{what}: this CPU has no AVX2; the SIMD path is not compared");
        return;
    }
    let scalar = rc.clone().without_simd();
    for angle in [0.0, 37.0, 180.0, 250.0] {
        let view = cam.orbit_y(angle);
        let (a, b) = (
            dvr::render(rc, &view, 40, 40),
            dvr::render(&scalar, &view, 40, 40),
        );
        assert!(a == b, "{what}: SIMD and scalar DVR differ at {angle}°");
    }
    if let Some(vp) = vdi {
        let a = generate(rc, cam, vp, 0, what).expect("generates");
        let b = generate(&scalar, cam, vp, 0, what).expect("generates");
        assert!(a == b, "{what}: SIMD and scalar VDIs differ");
    }
}
