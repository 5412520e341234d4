use super::*;
use crate::volume::bricks::{block_bricks, grid_bricks};
use glam::Vec3;

fn disjoint_bricks(global: [usize; 3], split: [usize; 3]) -> Vec<(u32, Brick)> {
    let blocks = block_bricks(global, split).unwrap();
    blocks
        .into_iter()
        .enumerate()
        .map(|(k, b)| (k as u32, b))
        .collect()
}

/// A field whose every point is distinct, so a copied point is checked by its value.
fn field(global: [usize; 3]) -> Volume {
    Volume::from_fn(global, |x, y, z| (x + 100 * y + 10_000 * z) as f32).unwrap()
}

#[test]
fn shared_planes_stay_and_disjoint_points_grow_into_a_tiling_of_the_cells() {
    let global = [17, 12, 9];
    for split in [[2, 1, 1], [1, 1, 2], [2, 2, 1], [3, 2, 2], [1, 3, 1]] {
        let shared: Vec<(u32, Brick)> = grid_bricks(global, split)
            .unwrap()
            .into_iter()
            .enumerate()
            .map(|(k, b)| (k as u32, b))
            .collect();
        assert_eq!(tiling(global, &shared), Ok(Tiling::Shared), "{split:?}");
        let disjoint = disjoint_bricks(global, split);
        let Ok(Tiling::Disjoint(grown)) = tiling(global, &disjoint) else {
            panic!("{split:?}: {:?}", tiling(global, &disjoint))
        };
        // Each brick grows by one point exactly on the axes where it does not reach the end.
        for ((_, b), g) in disjoint.iter().zip(&grown) {
            assert_eq!(g.offset, b.offset);
            for (a, &n) in global.iter().enumerate() {
                let inner = b.offset[a] + b.dims[a] < n;
                assert_eq!(g.dims[a], b.dims[a] + usize::from(inner), "{split:?} {b:?}");
            }
        }
        let placed: Vec<(u32, Brick)> = disjoint.iter().map(|(r, _)| *r).zip(grown).collect();
        check(global, &placed, true).unwrap();
    }
}

#[test]
fn grown_bricks_hold_the_whole_field_s_values_in_every_type() {
    let global = [13, 10, 7];
    let whole = field(global);
    for split in [[2, 1, 1], [2, 2, 2], [3, 1, 2]] {
        let disjoint = disjoint_bricks(global, split);
        let Ok(Tiling::Disjoint(grown)) = tiling(global, &disjoint) else {
            panic!("{split:?}")
        };
        let faces: Vec<(Brick, Volume)> = disjoint
            .iter()
            .flat_map(|(_, b)| low_faces(&whole.brick(b).unwrap(), b).unwrap())
            .collect();
        // The faces are each brick's low planes, without a point twice.
        let face_points: usize = faces
            .iter()
            .map(|(p, _)| p.dims.iter().product::<usize>())
            .sum();
        let low_points: usize = disjoint
            .iter()
            .map(|(_, b)| {
                let inner: [usize; 3] =
                    std::array::from_fn(|a| b.dims[a] - usize::from(b.offset[a] > 0));
                b.dims.iter().product::<usize>() - inner.iter().product::<usize>()
            })
            .sum();
        assert_eq!(face_points, low_points, "{split:?}");
        let pieces: Vec<(Brick, &Volume)> = faces.iter().map(|(b, v)| (*b, v)).collect();
        for ((_, b), g) in disjoint.iter().zip(&grown) {
            let made = grow(&whole.brick(b).unwrap(), b, g, &pieces, None).unwrap();
            assert_eq!(made, whole.brick(g).unwrap(), "{split:?} {b:?} → {g:?}");
            assert_eq!(made.origin(), Vec3::from_array(b.offset.map(|o| o as f32)));
        }
    }
    // Bytes stay bytes.
    let bytes = Volume::from_u8(
        global,
        Vec3::ONE,
        (0..13 * 10 * 7).map(|i| i as u8).collect(),
    )
    .unwrap();
    let halves = disjoint_bricks(global, [1, 1, 2]);
    let Ok(Tiling::Disjoint(grown)) = tiling(global, &halves) else {
        panic!()
    };
    let upper = low_faces(&bytes.brick(&halves[1].1).unwrap(), &halves[1].1).unwrap();
    assert_eq!(upper.len(), 1, "a z-face only");
    let made = grow(
        &bytes.brick(&halves[0].1).unwrap(),
        &halves[0].1,
        &grown[0],
        &[(upper[0].0, &upper[0].1)],
        Some(whole.clone()),
    )
    .unwrap();
    assert!(matches!(made.voxels(), VoxelSlice::U8(_)));
    assert_eq!(made, bytes.brick(&grown[0]).unwrap());
}

#[test]
fn a_missing_face_a_real_hole_and_shared_points_are_refused_by_name() {
    let global = [8, 8, 8];
    let halves = disjoint_bricks(global, [1, 1, 2]);
    let Ok(Tiling::Disjoint(grown)) = tiling(global, &halves) else {
        panic!()
    };
    let whole = field(global);
    let lower = whole.brick(&halves[0].1).unwrap();
    let err = grow(&lower, &halves[0].1, &grown[0], &[], None).unwrap_err();
    assert!(
        err.to_string()
            .contains("its neighbours' faces do not hold the point (0, 0, 4)"),
        "{err}"
    );
    // A face given twice fills its points twice.
    let upper = whole.brick(&halves[1].1).unwrap();
    let faces = low_faces(&upper, &halves[1].1).unwrap();
    let twice = [(faces[0].0, &faces[0].1), (faces[0].0, &faces[0].1)];
    let err = grow(&lower, &halves[0].1, &grown[0], &twice, None).unwrap_err();
    assert!(
        err.to_string().contains("hold twice the point (0, 0, 4)"),
        "{err}"
    );
    // A face of another type.
    let face = Volume::from_u8([8, 8, 1], Vec3::ONE, vec![0; 64]).unwrap();
    let place = Brick {
        offset: [0, 0, 4],
        dims: [8, 8, 1],
    };
    assert!(
        grow(&lower, &halves[0].1, &grown[0], &[(place, &face)], None)
            .unwrap_err()
            .to_string()
            .contains("not of the brick's type")
    );
    // z 0..=3 and 6..=7: the points z = 4..=5 lie in no brick.
    let holed = [
        halves[0],
        (
            1,
            Brick {
                offset: [0, 0, 6],
                dims: [8, 8, 2],
            },
        ),
    ];
    let err = tiling(global, &holed).unwrap_err();
    assert_eq!(
        err,
        DecompositionError::Missing {
            ranks: vec![0, 1],
            held: 8 * 8 * 6,
            total: 8 * 8 * 8,
            hole: Some(Hole {
                rank: 0,
                axis: 2,
                first: 4,
                last: 5
            }),
        }
    );
    assert!(err
        .to_string()
        .ends_with("beside rank 0's brick, no brick holds the points z = 4..=5"));
    // Bricks that share points but do not tile the cells get the shared-plane check's error.
    let overlapping = [
        halves[0],
        (
            1,
            Brick {
                offset: [0, 0, 2],
                dims: [8, 8, 6],
            },
        ),
    ];
    assert!(matches!(
        tiling(global, &overlapping),
        Err(DecompositionError::Overlap { a: 0, b: 1 })
    ));
    // A brick outside the grid is named as such.
    let outside = [(
        0,
        Brick {
            offset: [0, 0, 4],
            dims: [8, 8, 8],
        },
    )];
    assert!(matches!(
        tiling(global, &outside),
        Err(DecompositionError::Outside { rank: 0, .. })
    ));
}
