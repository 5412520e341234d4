//! Codec properties: lossless round trips; truncated, bit-flipped or oversized input errors.

use glam::Vec3;
use insitu_core::vdi::codec::{decode, encode, Codec, CodecError, DecodeLimits};
use insitu_core::vdi::{Supersegment, Vdi, VdiMeta, VdiParams};
use insitu_core::volume::Aabb;
use insitu_core::Camera;
use proptest::prelude::*;

/// A random valid VDI: r in 1..6, up to 4 depth-sorted supersegments per pixel.
fn arb_vdi() -> impl Strategy<Value = Vdi> {
    (1u32..6, 0.0f32..0.3, any::<u64>(), "[a-z.]{0,12}").prop_flat_map(|(r, gamma, hash, name)| {
        let pixels = (r * r) as usize;
        let list = prop::collection::vec(
            (
                0.01f32..5.0,
                0.01f32..5.0,
                [0.0f32..=1.0, 0.0f32..=1.0, 0.0f32..=1.0],
                0.0f32..=1.0,
            ),
            0..4,
        );
        prop::collection::vec(list, pixels).prop_map(move |lists| {
            let mut offsets = vec![0u32];
            let mut segs = Vec::new();
            for list in lists {
                let mut z = 10.0f32;
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
            let meta = VdiMeta {
                camera: Camera {
                    eye: Vec3::new(1.0, 2.0, 30.0),
                    target: Vec3::ONE,
                    up: Vec3::Y,
                    fov_y_deg: 30.0,
                },
                params: VdiParams {
                    resolution: r,
                    gamma,
                },
                step: 0.5,
                termination: 0.99,
                shaded: hash % 2 == 0,
                volume_box: Aabb {
                    min: Vec3::ZERO,
                    max: Vec3::splat(8.0),
                },
                tf_hash: hash,
                tf_name: name.clone(),
            };
            Vdi::from_parts(meta, offsets, segs).expect("valid by construction")
        })
    })
}

fn arb_codec() -> impl Strategy<Value = Codec> {
    prop::sample::select(Codec::ALL.to_vec())
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    #[test]
    fn round_trip_is_lossless(vdi in arb_vdi(), codec in arb_codec()) {
        let bytes = encode(&vdi, codec).unwrap();
        prop_assert_eq!(decode(&bytes, &DecodeLimits::default()).unwrap(), vdi);
    }

    #[test]
    fn truncation_is_an_error(vdi in arb_vdi(), codec in arb_codec(), cut in any::<prop::sample::Index>()) {
        let bytes = encode(&vdi, codec).unwrap();
        let n = cut.index(bytes.len());
        prop_assert!(decode(&bytes[..n], &DecodeLimits::default()).is_err());
    }

    #[test]
    fn any_bit_flip_is_an_error(vdi in arb_vdi(), codec in arb_codec(), at in any::<prop::sample::Index>(), bit in 0u8..8) {
        let mut bytes = encode(&vdi, codec).unwrap();
        let i = at.index(bytes.len());
        bytes[i] ^= 1 << bit;
        prop_assert!(decode(&bytes, &DecodeLimits::default()).is_err());
    }

    #[test]
    fn appended_bytes_are_an_error(vdi in arb_vdi(), extra in prop::collection::vec(any::<u8>(), 1..16)) {
        let mut bytes = encode(&vdi, Codec::Bzip2).unwrap();
        bytes.extend(extra);
        prop_assert!(decode(&bytes, &DecodeLimits::default()).is_err());
    }

    #[test]
    fn random_bytes_never_panic(bytes in prop::collection::vec(any::<u8>(), 0..256)) {
        let _ = decode(&bytes, &DecodeLimits::default());
    }
}

#[test]
fn oversized_claims_are_refused_before_decompression() {
    let vdi = Vdi::from_parts(
        VdiMeta {
            camera: Camera {
                eye: Vec3::new(0.0, 0.0, 10.0),
                target: Vec3::ZERO,
                up: Vec3::Y,
                fov_y_deg: 30.0,
            },
            params: VdiParams {
                resolution: 2,
                gamma: 0.01,
            },
            step: 0.5,
            termination: 0.99,
            shaded: false,
            volume_box: Aabb {
                min: Vec3::ZERO,
                max: Vec3::ONE,
            },
            tf_hash: 1,
            tf_name: "t".into(),
        },
        vec![0, 0, 0, 0, 0],
        vec![],
    )
    .unwrap();
    let bytes = encode(&vdi, Codec::Zstd).unwrap();
    let tiny = DecodeLimits {
        max_payload_bytes: 16,
    };
    assert!(matches!(
        decode(&bytes, &tiny),
        Err(CodecError::TooLarge { .. })
    ));
    // A header claiming 2^60 bytes (checksum fixed up) is refused, not allocated.
    let mut forged = bytes.clone();
    forged[12..20].copy_from_slice(&(1u64 << 60).to_le_bytes());
    fix_checksum(&mut forged);
    assert!(matches!(
        decode(&forged, &DecodeLimits::default()),
        Err(CodecError::TooLarge { .. })
    ));
    // A claim within limits but larger than the body: decompression stops at the real end.
    forged[12..20].copy_from_slice(&(1u64 << 20).to_le_bytes());
    fix_checksum(&mut forged);
    assert!(matches!(
        decode(&forged, &DecodeLimits::default()),
        Err(CodecError::Invalid(_))
    ));
    assert!(matches!(
        decode(
            b"not a vdi at all, really not one",
            &DecodeLimits::default()
        ),
        Err(CodecError::BadMagic)
    ));
}

/// Recomputes the header CRC after a deliberate edit, so the edit reaches the later checks.
fn fix_checksum(bytes: &mut [u8]) {
    let mut h = crc32fast::Hasher::new();
    h.update(&bytes[..28]);
    h.update(&bytes[32..]);
    let crc = h.finalize().to_le_bytes();
    bytes[28..32].copy_from_slice(&crc);
}
