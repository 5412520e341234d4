//! Codec properties: lossless round trips; truncated, bit-flipped or oversized input errors.

use glam::Vec3;
use insitu_core::vdi::codec::{decode, encode, Codec, CodecError, DecodeLimits};
use insitu_core::vdi::{Supersegment, Vdi, VdiMeta, VdiParams};
use insitu_core::volume::Aabb;
use insitu_core::Camera;
use proptest::prelude::*;

use crate::common::{fix_checksum, smooth_lists};

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
                    precision: Default::default(),
                },
                sample_distance: 0.5,
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
    let vdi = Vdi::from_parts(meta(2, 1, "t"), vec![0, 0, 0, 0, 0], vec![]).unwrap();
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

/// A VDI of 16² pixels of `per` supersegments each (a payload of about `6 kB × per`), depths
/// and colours varying so that it compresses like a real one, not to nothing.
fn large_vdi(per: u32) -> Vdi {
    let (offsets, segs) = smooth_lists(16, per, 1.0, 0.01);
    Vdi::from_parts(meta(16, 7, "parts"), offsets, segs).unwrap()
}

/// The metadata of a VDI of resolution `r` seen from +z over the unit box, with TF `hash`
/// and `name`.
fn meta(resolution: u32, tf_hash: u64, tf_name: &str) -> VdiMeta {
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
            precision: Default::default(),
        },
        sample_distance: 0.5,
        termination: 0.99,
        shaded: false,
        volume_box: Aabb {
            min: Vec3::ZERO,
            max: Vec3::ONE,
        },
        tf_hash,
        tf_name: tf_name.into(),
    }
}

/// Where the part table starts in a file without provenance: the 32-byte header, then the
/// provenance block's length (0).
const TABLE: usize = 36;

/// The body's part table: `(compressed, payload)` lengths per part.
fn part_table(bytes: &[u8]) -> Vec<(u64, u64)> {
    let u64_at = |at: usize| u64::from_le_bytes(bytes[at..at + 8].try_into().unwrap());
    let count = u32::from_le_bytes(bytes[TABLE..TABLE + 4].try_into().unwrap()) as usize;
    (0..count)
        .map(|i| (u64_at(TABLE + 4 + 16 * i), u64_at(TABLE + 12 + 16 * i)))
        .collect()
}

#[test]
fn large_payloads_are_compressed_in_parts_and_round_trip() {
    // Three bzip2 parts; one zstd part, then two.
    let vdi = large_vdi(800);
    for codec in Codec::ALL {
        let bytes = encode(&vdi, codec).unwrap();
        let payload = u64::from_le_bytes(bytes[12..20].try_into().unwrap());
        let table = part_table(&bytes);
        let expected_parts = match codec {
            Codec::Bzip2 => payload.div_ceil(insitu_core::vdi::codec::BZIP2_PART as u64),
            Codec::Zstd => payload.div_ceil(insitu_core::vdi::codec::ZSTD_PART as u64),
            Codec::None => 1,
        };
        assert!(
            payload > 2 * insitu_core::vdi::codec::BZIP2_PART as u64,
            "{payload} bytes"
        );
        assert_eq!(table.len() as u64, expected_parts, "{codec}");
        assert_eq!(table.iter().map(|p| p.1).sum::<u64>(), payload, "{codec}");
        assert_eq!(
            decode(&bytes, &DecodeLimits::default()).unwrap(),
            vdi,
            "{codec}"
        );
    }
    let larger = large_vdi(1700);
    let bytes = encode(&larger, Codec::Zstd).unwrap();
    assert_eq!(part_table(&bytes).len(), 2);
    assert_eq!(decode(&bytes, &DecodeLimits::default()).unwrap(), larger);
}

#[test]
fn version_1_files_are_still_read() {
    // A version 1 file: the payload as one bzip2 stream, no part table. The payload is the
    // body of the `none` encoding after its one-part table.
    let vdi = large_vdi(800);
    let plain = encode(&vdi, Codec::None).unwrap();
    let payload = &plain[TABLE + 4 + 16..];
    let mut body = Vec::new();
    std::io::Read::read_to_end(
        &mut bzip2::read::BzEncoder::new(payload, bzip2::Compression::best()),
        &mut body,
    )
    .unwrap();
    let mut v1 = plain[..32].to_vec();
    v1[8..10].copy_from_slice(&1u16.to_le_bytes());
    v1[10] = 1; // bzip2
    v1[20..28].copy_from_slice(&(body.len() as u64).to_le_bytes());
    v1.extend_from_slice(&body);
    fix_checksum(&mut v1);
    assert_eq!(decode(&v1, &DecodeLimits::default()).unwrap(), vdi);
    // And a version from the future is refused by name.
    let mut v9 = v1.clone();
    v9[8..10].copy_from_slice(&9u16.to_le_bytes());
    fix_checksum(&mut v9);
    assert!(matches!(
        decode(&v9, &DecodeLimits::default()),
        Err(CodecError::UnsupportedVersion(9))
    ));
}

/// An edit of a file's bytes.
type Edit<'a> = dyn Fn(&mut Vec<u8>) + 'a;

#[test]
fn a_bad_part_table_is_refused() {
    let bytes = encode(&large_vdi(800), Codec::Bzip2).unwrap();
    let table = part_table(&bytes);
    let last = table.len() - 1;
    assert!(table[0].1 > table[last].1, "the last part is the short one");
    let forge = |edit: &Edit<'_>| {
        let mut forged = bytes.clone();
        edit(&mut forged);
        fix_checksum(&mut forged);
        decode(&forged, &DecodeLimits::default())
    };
    let put = |b: &mut Vec<u8>, at: usize, v: u64| b[at..at + 8].copy_from_slice(&v.to_le_bytes());
    let cases: [(&str, &Edit<'_>); 5] = [
        ("no parts", &|b| {
            b[TABLE..TABLE + 4].copy_from_slice(&0u32.to_le_bytes())
        }),
        ("more parts than the body holds", &|b| {
            b[TABLE..TABLE + 4].copy_from_slice(&u32::MAX.to_le_bytes())
        }),
        ("compressed lengths that miss the body", &|b| {
            put(b, TABLE + 4, table[0].0 + 1)
        }),
        ("payload lengths that miss the header's", &|b| {
            put(b, TABLE + 12, table[0].1 - 1)
        }),
        // The sums hold, but the first part no longer decompresses to its stated length.
        ("two parts' payload lengths swapped", &|b| {
            put(b, TABLE + 12, table[last].1);
            put(b, TABLE + 12 + 16 * last, table[0].1);
        }),
    ];
    for (what, edit) in cases {
        assert!(
            matches!(forge(edit), Err(CodecError::Invalid(_))),
            "{what}: {:?}",
            forge(edit).map(|_| ())
        );
    }
}

/// A codec in JSON is its name, the one `FromStr` reads.
#[test]
fn codecs_serialize_as_their_names() {
    for codec in Codec::ALL {
        let json = serde_json::to_value(codec).unwrap();
        assert_eq!(json, codec.name());
        assert_eq!(serde_json::from_value::<Codec>(json).unwrap(), codec);
        assert_eq!(codec.name().parse::<Codec>().unwrap(), codec);
    }
    assert!(serde_json::from_str::<Codec>(r#""lzma""#).is_err());
}

/// A file carries where it comes from, readable without decoding it; files of version 2 (no
/// provenance) still read, and a damaged block is caught by the checksum.
#[test]
fn provenance_travels_in_the_file_and_older_files_still_read() {
    use insitu_core::vdi::codec::{decode_with_provenance, encode_with_provenance, provenance};
    use insitu_core::vdi::provenance::Provenance;
    use insitu_core::volume::bricks::Brick;
    let vdi = large_vdi(40);
    let p = Provenance {
        step: 42,
        rank: 1,
        world_size: 2,
        pm_version: 5,
        sim_time: 4.2,
        placement: Some((
            [64, 64, 127],
            Brick {
                offset: [0, 0, 63],
                dims: [64, 64, 64],
            },
        )),
        covers: vec![],
        scene_version: 3,
    };
    let limits = DecodeLimits::default();
    let with = encode_with_provenance(&vdi, Codec::Zstd, Some(&p)).unwrap();
    assert_eq!(provenance(&with).unwrap(), Some(p.clone()));
    assert_eq!(
        decode_with_provenance(&with, &limits).unwrap(),
        (vdi.clone(), Some(p.clone()))
    );
    let without = encode(&vdi, Codec::Zstd).unwrap();
    assert_eq!(provenance(&without).unwrap(), None);
    assert_eq!(
        with.len() - without.len(),
        p.to_bytes().len(),
        "σ grows by the block alone"
    );
    // Version 2: the same body without the block's length.
    let mut v2 = without[..32].to_vec();
    v2[8..10].copy_from_slice(&2u16.to_le_bytes());
    v2[20..28].copy_from_slice(&((without.len() - TABLE) as u64).to_le_bytes());
    v2.extend_from_slice(&without[TABLE..]);
    fix_checksum(&mut v2);
    assert_eq!(decode_with_provenance(&v2, &limits).unwrap(), (vdi, None));
    // A flipped byte in the step: the checksum refuses the file.
    let mut damaged = with.clone();
    damaged[TABLE] ^= 1;
    assert!(matches!(
        decode(&damaged, &limits),
        Err(CodecError::Checksum { .. })
    ));
    // A block longer than any version writes is refused before it is read.
    let mut huge = with;
    huge[32..36].copy_from_slice(&1_000_000u32.to_le_bytes());
    assert!(provenance(&huge)
        .unwrap_err()
        .to_string()
        .contains("provenance block of 1000000 bytes"));
}
