//! Helpers shared by the integration tests.

use insitu_core::volume::RawFormat;
use insitu_core::{Image, Supersegment, TransferFunction, Volume};

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

/// `r²` pixels of `per` supersegments each, the first at depth `z0` and each `spacing` after
/// the last (jittered by up to 0.4 of it) and half of it long, colours and opacities varying
/// smoothly: lists that compress like a real VDI's, not to nothing. The offsets and the lists.
pub fn smooth_lists(r: u32, per: u32, z0: f32, spacing: f32) -> (Vec<u32>, Vec<Supersegment>) {
    let mut offsets = vec![0u32];
    let mut segs = Vec::new();
    for p in 0..r * r {
        for k in 0..per {
            let x = (p * per + k) as f32;
            let z = z0 + k as f32 * spacing + (x * 0.37).sin().abs() * 0.4 * spacing;
            segs.push(Supersegment {
                z_start: z,
                z_end: z + 0.5 * spacing,
                color: [
                    (x * 0.011).sin() * 0.5 + 0.5,
                    (x * 0.007).cos() * 0.5 + 0.5,
                    (x * 0.003).sin().abs(),
                ],
                alpha: ((x * 0.013).cos() * 0.5 + 0.5).min(1.0),
            });
        }
        offsets.push(segs.len() as u32);
    }
    (offsets, segs)
}

/// Recomputes a VDI file's header CRC after a deliberate edit, so that the edit reaches the
/// checks behind the checksum.
pub fn fix_checksum(bytes: &mut [u8]) {
    let mut h = crc32fast::Hasher::new();
    h.update(&bytes[..28]);
    h.update(&bytes[32..]);
    let crc = h.finalize().to_le_bytes();
    bytes[28..32].copy_from_slice(&crc);
}
