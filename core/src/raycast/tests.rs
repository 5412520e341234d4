//! The marcher against analytic answers and the hard cases.

use super::*;
use crate::camera::Camera;

fn count_samples(rc: &Raycaster, ray: &Ray) -> (usize, f32) {
    let (mut n, mut len) = (0, 0.0);
    rc.march(ray, |s: &Sample| {
        n += 1;
        len += s.len;
        ControlFlow::Continue(())
    });
    (n, len)
}

#[test]
fn steps_add_up_to_the_length_inside_the_box() {
    let v = Volume::from_fn([11, 11, 11], |_, _, _| 1.0).unwrap();
    let tf = TransferFunction::constant(0.0, 2.0, [1.0, 1.0, 1.0, 0.1]);
    for step in [0.3f32, 0.5, 1.0, 7.0, 100.0] {
        let rc = Raycaster::new(
            &v,
            &tf,
            RaycastParams {
                sample_distance: step,
                ..Default::default()
            },
        )
        .unwrap();
        let ray = Ray {
            origin: Vec3::new(5.0, 5.0, -3.0),
            dir: Vec3::Z,
        };
        let (n, len) = count_samples(&rc, &ray);
        assert!((len - 10.0).abs() < 1e-4, "step {step}: length {len}");
        assert_eq!(n, (10.0 / step).ceil() as usize);
    }
}

#[test]
fn a_brick_with_an_origin_samples_like_the_same_region_of_the_whole() {
    // The brick is z ∈ [4, 10] of the whole grid (sharing the boundary plane), placed at
    // its world origin: a ray through it sees the same values as through the whole.
    let f = |x: usize, y: usize, z: usize| (x * 7 + y * 3 + z * z) as f32 * 0.01;
    let whole = Volume::from_fn([9, 8, 11], f).unwrap();
    let brick = Volume::from_fn([9, 8, 7], |x, y, z| f(x, y, z + 4))
        .unwrap()
        .with_origin(Vec3::new(0.0, 0.0, 4.0))
        .unwrap();
    assert_eq!(brick.world_box().min.z, 4.0);
    assert_eq!(brick.world_box().max.z, 10.0);
    let whole_rc = Raycaster::new(
        &whole,
        &TransferFunction::default_for_range(0.0, 3.0),
        RaycastParams::default(),
    )
    .unwrap();
    let brick_rc = Raycaster::new(
        &brick,
        &TransferFunction::default_for_range(0.0, 3.0),
        RaycastParams::default(),
    )
    .unwrap();
    for p in [
        Vec3::new(1.5, 2.25, 4.0),
        Vec3::new(7.9, 6.5, 9.75),
        Vec3::new(3.0, 3.0, 6.5),
    ] {
        let pw = whole_rc.sample(p);
        let pb = brick_rc.sample(p - Vec3::new(0.0, 0.0, 4.0));
        assert!((pw - pb).abs() < 1e-6, "{p}: {pw} vs {pb}");
    }
    let ray = Ray {
        origin: Vec3::new(3.3, 2.7, -5.0),
        dir: Vec3::Z,
    };
    let mut zs = Vec::new();
    brick_rc.march(&ray, |s: &Sample| {
        zs.push(-5.0 + s.t_start);
        ControlFlow::Continue(())
    });
    assert!((zs[0] - 4.0).abs() < 1e-5, "brick entered at z = {}", zs[0]);
    assert!(Volume::from_fn([2, 2, 2], f)
        .unwrap()
        .with_origin(Vec3::NAN)
        .is_err());
}

/// u8, u16 and i16 storage (padded for the AVX2 gathers) marches exactly like the same
/// values as f32, on the SIMD and the scalar path, down to volumes two voxels a side
/// (where the last voxel's gather reads into the padding); i16 over its whole range, so
/// a sign-extension slip (or a mask instead of it) shows.
#[test]
fn integer_storage_samples_like_f32() {
    for dims in [[2, 2, 2], [2, 5, 3], [17, 13, 11], [40, 3, 2]] {
        let n: usize = dims.iter().product();
        let value = |i: usize| ((i * 2654435761) % 65521) as u16;
        let u16s: Vec<u16> = (0..n).map(value).collect();
        let u8s: Vec<u8> = (0..n).map(|i| (value(i) % 256) as u8).collect();
        // About half the voxels negative, and both ends of the type.
        let i16s: Vec<i16> = (0..n)
            .map(|i| match i {
                0 => i16::MIN,
                1 => i16::MAX,
                _ => (i32::from(value(i)) - 32768) as i16,
            })
            .collect();
        let pairs = [
            (
                Volume::from_i16(dims, Vec3::ONE, i16s.clone()).unwrap(),
                Volume::new(
                    dims,
                    Vec3::ONE,
                    i16s.iter().map(|&v| f32::from(v)).collect(),
                )
                .unwrap(),
                (-32768.0, 32767.0),
            ),
            (
                Volume::from_u16(dims, Vec3::ONE, u16s.clone()).unwrap(),
                Volume::new(
                    dims,
                    Vec3::ONE,
                    u16s.iter().map(|&v| f32::from(v)).collect(),
                )
                .unwrap(),
                (0.0, 65535.0),
            ),
            (
                Volume::from_u8(dims, Vec3::ONE, u8s.clone()).unwrap(),
                Volume::new(dims, Vec3::ONE, u8s.iter().map(|&v| f32::from(v)).collect()).unwrap(),
                (0.0, 255.0),
            ),
        ];
        for (native, float, (lo, hi)) in &pairs {
            assert_eq!(native.content_hash(), float.content_hash());
            assert_eq!(native.finite_range(), float.finite_range());
            let tf = TransferFunction::default_for_range(*lo, *hi);
            let a = Raycaster::new(native, &tf, RaycastParams::default()).unwrap();
            let b = Raycaster::new(float, &tf, RaycastParams::default()).unwrap();
            a.prepare(usize::MAX);
            b.prepare(usize::MAX);
            let cam = Camera::default_for_box(&native.world_box());
            let mut samples = 0;
            for (a, b) in [(a.clone(), b.clone()), (a.without_simd(), b.without_simd())] {
                for angle in [0.0, 41.0, 180.0] {
                    let f = cam.orbit_y(angle).frame(24, 24);
                    for j in 0..24 {
                        for i in 0..24 {
                            let ray = f.pixel_ray(i, j);
                            let mut x = Vec::new();
                            a.march(&ray, |s: &Sample| {
                                x.push((s.index, s.alpha.to_bits(), s.rgb.map(f32::to_bits)));
                                ControlFlow::Continue(())
                            });
                            let mut y = Vec::new();
                            b.march(&ray, |s: &Sample| {
                                y.push((s.index, s.alpha.to_bits(), s.rgb.map(f32::to_bits)));
                                ControlFlow::Continue(())
                            });
                            assert_eq!(x, y, "{dims:?} at {angle}°, pixel ({i}, {j})");
                            samples += x.len();
                        }
                    }
                }
            }
            assert!(samples > 0, "{dims:?}: the rays must see the volume");
        }
    }
}

/// The SIMD path's visibility map: a group's bit is set exactly when one of its table
/// entries has `κ > 0` (so no visible sample is dropped, and a lane let through by a
/// group is the rare transparent neighbour of a visible entry).
#[test]
fn visible_groups_mark_exactly_the_groups_with_a_visible_entry() {
    let tf = TransferFunction::from_json(
        r#"{"domain": [0, 1], "points": [[0,0,0,0,0],[0.3,0,0,0,0],[0.31,1,0,0,0.5],[0.6,1,0,0,0.5],[0.61,0,0,0,0],[0.9,0,0,0,0],[1,1,1,1,1]]}"#,
        "t",
    )
    .unwrap();
    let lut = Lut::new(&tf, 0.5);
    let groups = simd::visible_groups(&lut);
    let group = crate::tf::LUT_SIZE / 256;
    let mut set = 0;
    for g in 0..256 {
        let bit = groups[g / 32] >> (g % 32) & 1 == 1;
        let any = lut.entries()[g * group..(g + 1) * group]
            .iter()
            .any(|e| e.kappa > 0.0);
        assert_eq!(bit, any, "group {g}");
        set += usize::from(bit);
    }
    assert!(set > 0 && set < 256, "{set} groups visible");
}

/// The occupancy bits are built for a render that samples at least about as many points
/// as the volume has voxels, once, and not for a handful of rays (a generator-node's
/// r = 1 VDIs); never on the scalar path or without skipping.
#[test]
fn occupancy_is_built_for_large_renders_only() {
    let v = Volume::from_fn([32, 24, 40], |x, y, z| ((x + y + z) % 7) as f32).unwrap();
    let tf = TransferFunction::default_for_range(0.0, 6.0);
    let rc = Raycaster::new(&v, &tf, RaycastParams::default()).unwrap();
    let voxels = 32 * 24 * 40;
    rc.prepare(1);
    rc.prepare(voxels / 40 - 1);
    assert!(rc.occupancy().is_none(), "built for too few rays");
    rc.prepare(voxels / 40);
    assert_eq!(rc.occupancy().is_some(), rc.uses_simd());
    let scalar = rc.clone().without_simd();
    scalar.prepare(usize::MAX);
    assert!(scalar.occupancy().is_none());
    let no_skipping = Raycaster::new(
        &v,
        &tf,
        RaycastParams {
            empty_space_skipping: false,
            ..Default::default()
        },
    )
    .unwrap();
    no_skipping.prepare(usize::MAX);
    assert!(no_skipping.occupancy().is_none());
}

#[test]
fn nan_is_transparent() {
    let v = Volume::from_fn([5, 5, 5], |x, _, _| if x < 2 { f32::NAN } else { 1.0 }).unwrap();
    let tf = TransferFunction::constant(0.0, 2.0, [1.0, 1.0, 1.0, 0.5]);
    let rc = Raycaster::new(&v, &tf, RaycastParams::default()).unwrap();
    let ray = Ray {
        origin: Vec3::new(-1.0, 2.0, 2.0),
        dir: Vec3::X,
    };
    rc.march(&ray, |s: &Sample| {
        let x = -1.0 + s.t_start + 0.5 * s.len;
        assert!(x >= 2.0, "NaN region at x = {x} gave a sample");
        assert!(s.alpha.is_finite() && s.rgb.iter().all(|c| c.is_finite()));
        ControlFlow::Continue(())
    });
}

#[test]
fn empty_space_skipping_visits_the_same_samples() {
    // Blocks of 12³ voxels, alternately 0 and 1, against macro cells of 8: cells wholly
    // inside zero blocks are invisible, and every value above 0 is visible, so a sample
    // just past an invisible cell's exit is visible and would be missed if skipping
    // overshot. Steps from a tenth of a voxel to more than one, views from several
    // sides and from far away (large t, where the rounding of the cell exit is largest).
    let blocks = Volume::from_fn([40, 33, 29], |x, y, z| {
        ((x / 12 + y / 12 + z / 12) % 2) as f32
    })
    .unwrap();
    // Single visible voxels scattered one in a few hundred: most invisible cells lie
    // next to a visible one, so rays walk them cell by cell; on a grid whose centre is a
    // cell corner, views at 0°, 45° and 90° send rays along cell faces and through cell
    // edges, where the next cell is ambiguous.
    let sparse = Volume::from_fn([48, 40, 48], |x, y, z| {
        f32::from(u8::from((x * 73 + y * 151 + z * 283) % 331 == 0))
    })
    .unwrap();
    // Blocks of 20³ on a grid large enough for 16³ macro cells (`cell_size_for`), whose
    // occupancy bits are sixteen words a cell.
    let large = Volume::from_fn([130, 128, 129], |x, y, z| {
        ((x / 20 + y / 20 + z / 20) % 2) as f32
    })
    .unwrap();
    // One small ball off the centre: its cells cover a small part of the volume's view.
    let ball = Volume::from_fn([50, 44, 40], |x, y, z| {
        let d = Vec3::new(x as f32 - 34.0, y as f32 - 12.0, z as f32 - 25.0).length();
        f32::from(u8::from(d < 5.0))
    })
    .unwrap();
    let tf = TransferFunction::from_json(
        r#"{"domain": [0, 1], "points": [[0,0,0,0,0],[0.001,1,0,0,0.2],[1,1,1,1,0.3]]}"#,
        "t",
    )
    .unwrap();
    let mut outside = 0;
    for (v, step, angle, zoom_out) in [
        (&large, 0.5, 33.0, 1.0),
        (&large, 0.7, 200.0, 1.0),
        (&blocks, 0.5, 33.0, 1.0),
        (&blocks, 0.1, 147.0, 1.0),
        (&blocks, 1.3, 250.0, 1.0),
        (&blocks, 0.37, 71.0, 400.0),
        (&sparse, 0.5, 0.0, 1.0),
        (&sparse, 0.5, 45.0, 1.0),
        (&sparse, 0.25, 90.0, 1.0),
        (&sparse, 1.0, 225.0, 1.0),
        (&sparse, 0.5, 163.0, 50.0),
        (&ball, 0.5, 20.0, 1.0),
        (&ball, 0.3, 200.0, 1.0),
        (&ball, 0.5, 290.0, 30.0),
    ] {
        let params = RaycastParams {
            sample_distance: step,
            ..Default::default()
        };
        let with = Raycaster::new(v, &tf, params).unwrap();
        // With the occupancy bits, as a large render has them.
        with.prepare(usize::MAX);
        assert_eq!(with.occupancy().is_some(), with.uses_simd());
        let cells = if std::ptr::eq(v, &large) { 16 } else { 8 };
        assert_eq!(with.macro_grid().cell_size(), cells);
        let without = Raycaster::new(
            v,
            &tf,
            RaycastParams {
                empty_space_skipping: false,
                ..params
            },
        )
        .unwrap();
        let mut cam = Camera::default_for_box(&v.world_box()).orbit_y(angle);
        cam.eye = cam.target + (cam.eye - cam.target) * zoom_out;
        cam.fov_y_deg /= zoom_out;
        let f = cam.frame(48, 48);
        // Pixels the visible cells do not cover are left unmarched by the renderers: the
        // marcher without skipping must find nothing along their rays.
        let coverage = Coverage::new(&with, &f);
        let everything = Coverage::new(&without, &f);
        assert!((0..48).all(|j| (0..48).all(|i| everything.covers(i, j))));
        let mut total = 0;
        for j in 0..48 {
            for i in 0..48 {
                let ray = f.pixel_ray(i, j);
                let mut a = Vec::new();
                with.march(&ray, |s: &Sample| {
                    a.push((s.index, s.alpha.to_bits()));
                    ControlFlow::Continue(())
                });
                let mut b = Vec::new();
                without.march(&ray, |s: &Sample| {
                    b.push((s.index, s.alpha.to_bits()));
                    ControlFlow::Continue(())
                });
                assert_eq!(a, b, "step {step}, {angle}°, pixel ({i}, {j})");
                let inside = coverage.covers(i, j);
                assert!(
                    inside || b.is_empty(),
                    "step {step}, {angle}°: pixel ({i}, {j}) is not covered"
                );
                outside += usize::from(!inside);
                total += a.len();
            }
        }
        assert!(
            total > 300,
            "step {step}, {angle}°: the blob must be hit ({total} samples)"
        );
    }
    assert!(outside > 5_000, "{outside} pixels not covered");
}
