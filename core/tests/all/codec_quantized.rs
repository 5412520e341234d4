//! The quantised format (version 4): every value within its stated bound, re-encoding a
//! decoded file gives the same bytes, hostile edits are refused, and on a generated VDI the
//! picture moves by far less than the VDI's own error.

use glam::Vec3;
use insitu_core::metrics::psnr;
use insitu_core::vdi::codec::quantized::DepthGrid;
use insitu_core::vdi::codec::{decode, encode, Codec, CodecError, DecodeLimits, FORMAT_VERSION};
use insitu_core::vdi::{generate::generate, render::render};
use insitu_core::vdi::{Precision, Supersegment, Vdi, VdiMeta, VdiParams};
use insitu_core::volume::{Aabb, GrayScott, GrayScottParams};
use insitu_core::{Camera, RaycastParams, Raycaster, TransferFunction};
use proptest::prelude::*;

use crate::common::{fix_checksum, smooth_lists};

/// The ray-casting step of the random VDIs: a depth quantum of 1/256.
const STEP: f32 = 0.05;

fn meta(resolution: u32, precision: Precision) -> VdiMeta {
    VdiMeta {
        camera: Camera {
            eye: Vec3::new(0.0, 0.0, 10.0),
            target: Vec3::ZERO,
            up: Vec3::Y,
            fov_y_deg: 30.0,
        },
        params: VdiParams {
            resolution,
            gamma: 0.01,
            precision,
        },
        sample_distance: STEP,
        termination: 0.99,
        shaded: false,
        volume_box: Aabb {
            min: Vec3::ZERO,
            max: Vec3::ONE,
        },
        tf_hash: 3,
        tf_name: "q".into(),
    }
}

/// A random VDI (r in 1..8, up to 5 supersegments a pixel, each and each gap at least a
/// depth quantum long; opacities including 0 and 1) at a random precision.
fn arb_vdi() -> impl Strategy<Value = Vdi> {
    (1u32..8, Precision::MIN_BITS..=Precision::MAX_BITS).prop_flat_map(|(r, bits)| {
        let seg = (
            0.0f32..2.0,
            0.004f32..3.0,
            [0.0f32..=1.0, 0.0f32..=1.0, 0.0f32..=1.0],
            prop_oneof![Just(0.0f32), Just(1.0f32), 0.0f32..=1.0],
        );
        prop::collection::vec(prop::collection::vec(seg, 0..5), (r * r) as usize).prop_map(
            move |lists| {
                let mut offsets = vec![0u32];
                let mut segs = Vec::new();
                for list in lists {
                    let mut z = 5.0f32;
                    for (gap, len, color, alpha) in list {
                        let start = z + gap;
                        segs.push(Supersegment {
                            z_start: start,
                            z_end: start + len,
                            color,
                            alpha,
                        });
                        z = start + len;
                    }
                    offsets.push(segs.len() as u32);
                }
                Vdi::from_parts(meta(r, Precision::Bits(bits)), offsets, segs).unwrap()
            },
        )
    })
}

/// Opacity over the depth extent, what the format stores.
fn extent_opacity(s: &Supersegment) -> f64 {
    let extent = f64::from(s.z_end) - f64::from(s.z_start);
    -(extent * (-f64::from(s.alpha)).ln_1p()).exp_m1()
}

fn arb_codec() -> impl Strategy<Value = Codec> {
    prop::sample::select(Codec::ALL.to_vec())
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    #[test]
    fn every_value_is_within_its_bound(vdi in arb_vdi(), codec in arb_codec()) {
        let bytes = encode(&vdi, codec).unwrap();
        prop_assert_eq!(u16::from_le_bytes([bytes[8], bytes[9]]), FORMAT_VERSION);
        let back = decode(&bytes, &DecodeLimits::default()).unwrap();
        prop_assert_eq!(back.meta(), vdi.meta());
        prop_assert_eq!(back.offsets(), vdi.offsets());
        let max_z = vdi.supersegments().iter().fold(0.0f32, |m, s| m.max(s.z_end));
        let half = DepthGrid::new(STEP, max_z).quantum() / 2.0;
        prop_assert!(half <= f64::from(STEP) / 16.0);
        let color = f64::from(vdi.meta().params.precision.color_bound()) + 1e-6;
        for (a, b) in vdi.supersegments().iter().zip(back.supersegments()) {
            for (x, y) in [(a.z_start, b.z_start), (a.z_end, b.z_end)] {
                prop_assert!(f64::from((x - y).abs()) <= half + 1e-6, "depth {x} → {y}");
            }
            for k in 0..3 {
                prop_assert!(f64::from((a.color[k] - b.color[k]).abs()) <= color);
            }
            let (oa, ob) = (extent_opacity(a), extent_opacity(b));
            prop_assert!((oa - ob).abs() <= color + 1e-5, "opacity {oa} → {ob}");
            if a.alpha == 1.0 {
                prop_assert_eq!(b.alpha, 1.0, "an opaque supersegment stays opaque");
            }
        }
    }

    #[test]
    fn a_decoded_vdi_encodes_to_itself(vdi in arb_vdi(), codec in arb_codec()) {
        let bytes = encode(&vdi, codec).unwrap();
        let back = decode(&bytes, &DecodeLimits::default()).unwrap();
        let again = encode(&back, codec).unwrap();
        prop_assert_eq!(decode(&again, &DecodeLimits::default()).unwrap(), back);
    }

    #[test]
    fn truncation_and_bit_flips_are_errors(
        vdi in arb_vdi(),
        codec in arb_codec(),
        at in any::<prop::sample::Index>(),
        bit in 0u8..8,
    ) {
        let bytes = encode(&vdi, codec).unwrap();
        let i = at.index(bytes.len());
        prop_assert!(decode(&bytes[..i], &DecodeLimits::default()).is_err());
        let mut flipped = bytes.clone();
        flipped[i] ^= 1 << bit;
        prop_assert!(decode(&flipped, &DecodeLimits::default()).is_err());
    }
}

/// A VDI of 64² pixels of `per` supersegments each, with smoothly varying values.
fn large_vdi(per: u32, precision: Precision) -> Vdi {
    let (offsets, segs) = smooth_lists(64, per, 6.0, 0.1);
    Vdi::from_parts(meta(64, precision), offsets, segs).unwrap()
}

/// Where the part table starts in a file without provenance.
const TABLE: usize = 36;

/// Each part's `(start, length)` in a file of codec `none`.
fn parts(bytes: &[u8]) -> Vec<(usize, usize)> {
    let count = u32::from_le_bytes(bytes[TABLE..TABLE + 4].try_into().unwrap()) as usize;
    let mut at = TABLE + 4 + 16 * count;
    (0..count)
        .map(|i| {
            let o = TABLE + 4 + 16 * i;
            let len = u64::from_le_bytes(bytes[o..o + 8].try_into().unwrap()) as usize;
            at += len;
            (at - len, len)
        })
        .collect()
}

#[test]
fn large_vdis_are_coded_in_bands_that_decode_in_parallel() {
    // 64² × 40 = 163 840 supersegments: three bands and the head.
    let vdi = large_vdi(40, Precision::Bits(10));
    for codec in Codec::ALL {
        let bytes = encode(&vdi, codec).unwrap();
        assert_eq!(parts(&bytes).len(), 4, "{codec}");
        let back = decode(&bytes, &DecodeLimits::default()).unwrap();
        assert_eq!(back.offsets(), vdi.offsets());
        let again = encode(&back, codec).unwrap();
        assert!(
            decode(&again, &DecodeLimits::default()).unwrap() == back,
            "{codec}: re-encoded"
        );
    }
    // Against the float file: about 4 bytes a supersegment instead of 24.
    let float = large_vdi(40, Precision::Float32);
    let f = encode(&float, Codec::Zstd).unwrap().len();
    let q = encode(&vdi, Codec::Zstd).unwrap().len();
    assert!(f > 3 * q, "float {f} bytes, 10-bit {q}");
}

#[test]
fn an_empty_vdi_and_one_pixel_round_trip() {
    for (r, lists) in [(3u32, vec![0u32; 10]), (1, vec![0, 0])] {
        let vdi = Vdi::from_parts(meta(r, Precision::Bits(8)), lists, vec![]).unwrap();
        let bytes = encode(&vdi, Codec::Zstd).unwrap();
        assert_eq!(decode(&bytes, &DecodeLimits::default()).unwrap(), vdi);
    }
}

#[test]
fn hostile_heads_and_bands_are_refused_by_name() {
    let vdi = large_vdi(2, Precision::Bits(10));
    let bytes = encode(&vdi, Codec::None).unwrap();
    let p = parts(&bytes);
    let (head, head_len) = p[0];
    let band = p[1].0;
    // The head ends with: bits, exponent, n (u64), band count (u32), one band (u32 + u64).
    let bits_at = head + head_len - 26;
    assert_eq!(bytes[bits_at], 10);
    let n = 2 * 64 * 64;
    let forge = |edit: &dyn Fn(&mut Vec<u8>)| {
        let mut forged = bytes.clone();
        edit(&mut forged);
        fix_checksum(&mut forged);
        decode(&forged, &DecodeLimits::default())
            .map(|_| ())
            .unwrap_err()
            .to_string()
    };
    type Case<'a> = (&'a str, &'a dyn Fn(&mut Vec<u8>), &'a str);
    let cases: [Case<'_>; 6] = [
        ("precision 0", &|b| b[bits_at] = 0, "precision of 0 bits"),
        ("precision 17", &|b| b[bits_at] = 17, "precision of 17 bits"),
        (
            "a depth quantum of 2^127",
            &|b| b[bits_at + 1] = 127,
            "depth quantum",
        ),
        (
            "a band claiming more supersegments than its bytes hold",
            &|b| b[head + head_len - 8..head + head_len].copy_from_slice(&u64::MAX.to_le_bytes()),
            "claims",
        ),
        (
            "a pixel count over the band's",
            &|b| b[band] = 0x7f,
            "counts add up",
        ),
        (
            // The high byte plane of the red levels (10 bits: at most 3).
            "a colour level above 2^10 − 1",
            &|b| {
                let red_high = p[1].0 + p[1].1 - 7 * n;
                b[red_high] = 4;
            },
            "colour level",
        ),
    ];
    for (what, edit, expected) in cases {
        let err = forge(edit);
        assert!(err.contains(expected), "{what}: {err}");
    }
    // A decoded VDI's memory is bounded like a version 3 payload.
    let tiny = DecodeLimits {
        max_payload_bytes: 1000,
    };
    assert!(matches!(
        decode(&bytes, &tiny),
        Err(CodecError::TooLarge { .. })
    ));
}

/// On a generated VDI (Gray–Scott 48³, r 128, rendered at 200²), 8 bits move the renders by far less than the
/// VDI differs from the direct render, at the generation view and 30° and 60° off it.
#[test]
fn eight_bits_cost_no_visible_quality_on_a_generated_vdi() {
    let mut sim = GrayScott::new(48, GrayScottParams::default()).unwrap();
    sim.advance(1500);
    let volume = sim.v_volume();
    let tf = TransferFunction::default_for_volume(&volume).tf;
    let rc = Raycaster::new(&volume, &tf, RaycastParams::default()).unwrap();
    let camera = Camera::default_for_box(&volume.world_box());
    let params = VdiParams {
        resolution: 128,
        gamma: 0.02,
        precision: Precision::Float32,
    };
    let float = generate(&rc, &camera, params, 0, "gs").unwrap();
    let mut quantised = float.clone();
    quantised.set_precision(Precision::Bits(8));
    let f_bytes = encode(&float, Codec::Bzip2).unwrap().len();
    let bytes = encode(&quantised, Codec::Zstd).unwrap();
    assert!(
        f_bytes > 3 * bytes.len(),
        "{f_bytes} against {}",
        bytes.len()
    );
    let decoded = decode(&bytes, &DecodeLimits::default()).unwrap();
    for angle in [0.0, 30.0, 60.0] {
        let cam = camera.orbit_y(angle);
        let reference = insitu_core::dvr::render(&rc, &cam, 200, 200);
        let exact = render(&float, &cam, 200, 200, 0.99);
        let coded = render(&decoded, &cam, 200, 200, 0.99);
        let q_float = psnr(&exact, &reference).unwrap();
        let q_coded = psnr(&coded, &reference).unwrap();
        assert!(
            q_float - q_coded <= 0.2,
            "{angle}°: {q_float:.2} → {q_coded:.2} dB"
        );
        assert!(psnr(&coded, &exact).unwrap() > q_float + 15.0, "{angle}°");
    }
}
