//! Composed equals whole: the sub-VDIs and brick frames of a decomposed volume, composed,
//! reproduce the VDI and the frame of the whole volume, for slab, pencil and grid splits and
//! from every side (the order of the bricks changes with the view).

use insitu_core::compose::{compose_frames, compose_vdis, frame_window, BrickFrame, ComposeError};
use insitu_core::metrics::psnr;
use insitu_core::vdi::{generate::generate, render::render, window::VdiWindow, VdiParams};
use insitu_core::volume::bricks::{box_groups, grid_bricks, Brick};
use insitu_core::{dvr, Camera, RaycastParams, Raycaster, TransferFunction, Vdi, Volume};

const R: u32 = 128;

/// Three soft blobs and a zero-valued (transparent) corner region.
fn field() -> Volume {
    let blob = |x: f32, y: f32, z: f32, c: [f32; 3], s: f32| {
        let d2 = (x - c[0]).powi(2) + (y - c[1]).powi(2) + (z - c[2]).powi(2);
        (-d2 / (2.0 * s * s)).exp()
    };
    Volume::from_fn([48, 40, 36], |x, y, z| {
        let (x, y, z) = (x as f32, y as f32, z as f32);
        blob(x, y, z, [16.0, 14.0, 12.0], 7.0)
            + 0.8 * blob(x, y, z, [30.0, 24.0, 22.0], 9.0)
            + 0.6 * blob(x, y, z, [24.0, 30.0, 10.0], 5.0)
    })
    .unwrap()
}

fn tf() -> TransferFunction {
    TransferFunction::default_for_range(0.0, 1.6)
}

fn vdi_of(v: &Volume, camera: &Camera) -> Vdi {
    let rc = Raycaster::new(v, &tf(), RaycastParams::default()).unwrap();
    let params = VdiParams {
        resolution: R,
        gamma: 0.01,
        precision: Default::default(),
    };
    generate(&rc, camera, params, tf().identity_hash(), "test").unwrap()
}

fn bricks(v: &Volume, split: [usize; 3]) -> Vec<Volume> {
    grid_bricks(v.dims(), split)
        .unwrap()
        .iter()
        .map(|b| v.brick(b).unwrap())
        .collect()
}

#[test]
fn composed_sub_vdis_render_like_the_whole_vdi() {
    let whole = field();
    let camera = Camera::default_for_box(&whole.world_box());
    let whole_vdi = vdi_of(&whole, &camera);
    for split in [[1, 1, 4], [2, 2, 1], [2, 2, 2], [3, 1, 2]] {
        let parts: Vec<Vdi> = bricks(&whole, split)
            .iter()
            .map(|b| vdi_of(b, &camera))
            .collect();
        let composed = compose_vdis(&parts.iter().collect::<Vec<_>>()).unwrap();
        assert_eq!(composed.meta().volume_box, whole.world_box());
        // Cropped to their footprints (as a host holds its waiting ranks), the sub-VDIs are
        // the same lists in less memory, and compose to the same VDI bit for bit.
        let windows: Vec<VdiWindow> = parts.iter().map(VdiWindow::crop).collect();
        for (w, p) in windows.iter().zip(&parts) {
            assert_eq!(&w.to_vdi(), p, "{split:?}");
            let (_, _, width, height) = w.rect();
            assert_eq!(
                w.memory_bytes(),
                (width * height + 1) * 4 + std::mem::size_of_val(p.supersegments())
            );
        }
        assert_eq!(
            compose_vdis(&windows.iter().collect::<Vec<_>>()).unwrap(),
            composed,
            "{split:?}"
        );
        let held: usize = windows.iter().map(VdiWindow::memory_bytes).sum();
        let whole_held: usize = parts.iter().map(Vdi::memory_bytes).sum();
        assert!(held < whole_held, "{split:?}: {held} ≥ {whole_held} bytes");
        assert_eq!(
            composed.supersegments().len(),
            parts.iter().map(|p| p.supersegments().len()).sum::<usize>()
        );
        // Valid as a VDI file: it survives the codec's full validation.
        let bytes =
            insitu_core::vdi::codec::encode(&composed, insitu_core::vdi::codec::Codec::Zstd)
                .unwrap();
        let decoded = insitu_core::vdi::codec::decode(&bytes, &Default::default()).unwrap();
        assert_eq!(decoded, composed);
        for (angle, floor) in [(0.0, 55.0), (30.0, 40.0), (60.0, 40.0), (180.0, 40.0)] {
            let cam = camera.orbit_y(angle);
            let a = render(&composed, &cam, R, R, 0.99);
            let b = render(&whole_vdi, &cam, R, R, 0.99);
            let q = psnr(&a, &b).unwrap();
            assert!(q >= floor, "{split:?} at {angle}°: {q:.1} dB < {floor}");
        }
    }
}

#[test]
fn composed_brick_frames_match_the_whole_frame_from_every_side() {
    let whole = field();
    let camera = Camera::default_for_box(&whole.world_box());
    let whole_rc = Raycaster::new(&whole, &tf(), RaycastParams::default()).unwrap();
    let parts = bricks(&whole, [2, 2, 2]);
    for angle in [0.0, 30.0, 60.0, 135.0, 180.0, 270.0] {
        let cam = camera.orbit_y(angle);
        let (want, want_opacity) = dvr::render_with_opacity(&whole_rc, &cam, R, R);
        let frames: Vec<(insitu_core::Image, Vec<f32>, _)> = parts
            .iter()
            .map(|b| {
                let rc = Raycaster::new(b, &tf(), RaycastParams::default()).unwrap();
                let (i, o) = dvr::render_with_opacity(&rc, &cam, R, R);
                (i, o, b.world_box())
            })
            .collect();
        let bf: Vec<BrickFrame> = frames.iter().map(BrickFrame::from).collect();
        let (got, got_opacity) = compose_frames(&cam, (R, R), &bf).unwrap();
        // Each brick's frame cut to the window it covers composites to the same frame, bit
        // for bit (as a host composites its ranks' frames).
        let windows: Vec<_> = frames
            .iter()
            .map(|(image, opacity, _)| {
                frame_window((R, R), |p| {
                    let [r, g, b] = image.pixels()[p];
                    [r, g, b, opacity[p]]
                })
            })
            .collect();
        let wf: Vec<BrickFrame> = windows
            .iter()
            .zip(&frames)
            .map(|((origin, image, opacity), (_, _, world_box))| BrickFrame {
                image,
                opacity,
                origin: *origin,
                world_box: *world_box,
            })
            .collect();
        assert!(wf.iter().all(|f| f.image.pixels().len() < (R * R) as usize));
        assert_eq!(
            compose_frames(&cam, (R, R), &wf).unwrap(),
            (got.clone(), got_opacity.clone()),
            "windows at {angle}°"
        );
        let q = psnr(&got, &want).unwrap();
        assert!(q >= 45.0, "at {angle}°: {q:.1} dB");
        let worst = got_opacity
            .iter()
            .zip(&want_opacity)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        assert!(worst < 0.02, "opacity off by {worst} at {angle}°");
        // The order matters: compositing back to front would not match.
        let reversed: Vec<BrickFrame> = bf
            .iter()
            .map(|f| BrickFrame {
                world_box: insitu_core::volume::Aabb {
                    min: -f.world_box.max,
                    max: -f.world_box.min,
                },
                ..*f
            })
            .collect();
        let (wrong, _) = compose_frames(&cam, (R, R), &reversed).unwrap();
        assert!(
            psnr(&wrong, &want).unwrap() < q,
            "order must count at {angle}°"
        );
    }
}

/// Two-level composition (hosts compose their ranks into box-shaped parts, then the parts
/// are composed) gives the VDI of one-level composition bit for bit, and its frames within
/// rounding, for hosts whose ranks form boxes and hosts whose ranks do not.
#[test]
fn hosts_composing_first_give_the_one_level_picture() {
    let whole = field();
    let camera = Camera::default_for_box(&whole.world_box());
    let grid = grid_bricks(whole.dims(), [2, 2, 2]).unwrap();
    let volumes = bricks(&whole, [2, 2, 2]);
    let vdis: Vec<Vdi> = volumes.iter().map(|b| vdi_of(b, &camera)).collect();
    let one_level = compose_vdis(&vdis.iter().collect::<Vec<_>>()).unwrap();
    let views = [0.0, 30.0, 135.0, 270.0];
    let frames: Vec<Vec<(insitu_core::Image, Vec<f32>, _)>> = views
        .iter()
        .map(|&angle| {
            let cam = camera.orbit_y(angle);
            volumes
                .iter()
                .map(|b| {
                    let rc = Raycaster::new(b, &tf(), RaycastParams::default()).unwrap();
                    let (i, o) = dvr::render_with_opacity(&rc, &cam, R, R);
                    (i, o, b.world_box())
                })
                .collect()
        })
        .collect();
    // Ranks per host, in rank order (MPI's block placement): [3, 3, 2] leaves L-shaped hosts.
    // With the parts each split gives (an L is two boxes).
    for (hosts, boxes) in [
        (vec![4, 4], 2),
        (vec![3, 3, 2], 5),
        (vec![2, 2, 2, 2], 4),
        (vec![8], 1),
    ] {
        let mut parts: Vec<(Vec<usize>, Vdi)> = Vec::new();
        let mut start = 0;
        for n in &hosts {
            let members: Vec<usize> = (start..start + n).collect();
            start += n;
            let host_bricks: Vec<Brick> = members.iter().map(|&k| grid[k]).collect();
            for (group, _) in box_groups(&host_bricks) {
                let ranks: Vec<usize> = group.iter().map(|&i| members[i]).collect();
                let sub: Vec<&Vdi> = ranks.iter().map(|&k| &vdis[k]).collect();
                parts.push((ranks, compose_vdis(&sub).unwrap()));
            }
        }
        assert_eq!(parts.len(), boxes, "{hosts:?}");
        let two_level = compose_vdis(&parts.iter().map(|(_, v)| v).collect::<Vec<_>>()).unwrap();
        assert_eq!(two_level, one_level, "hosts {hosts:?}");
        for (v, per_view) in views.iter().zip(&frames) {
            let cam = camera.orbit_y(*v);
            let all: Vec<BrickFrame> = per_view.iter().map(BrickFrame::from).collect();
            let (want, want_opacity) = compose_frames(&cam, (R, R), &all).unwrap();
            let host_frames: Vec<(insitu_core::Image, Vec<f32>, _)> = parts
                .iter()
                .map(|(ranks, part)| {
                    let members: Vec<BrickFrame> = ranks.iter().map(|&k| all[k]).collect();
                    let (i, o) = compose_frames(&cam, (R, R), &members).unwrap();
                    (i, o, part.meta().volume_box)
                })
                .collect();
            let hf: Vec<BrickFrame> = host_frames.iter().map(BrickFrame::from).collect();
            let (got, got_opacity) = compose_frames(&cam, (R, R), &hf).unwrap();
            let q = psnr(&got, &want).unwrap();
            assert!(q >= 60.0, "hosts {hosts:?} at {v}°: {q:.1} dB");
            let worst = got_opacity
                .iter()
                .zip(&want_opacity)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0f32, f32::max);
            assert!(worst < 1e-5, "opacity off by {worst} at {v}°");
        }
    }
}

#[test]
fn a_transparent_brick_adds_nothing_and_mismatches_are_refused() {
    let whole = field();
    let camera = Camera::default_for_box(&whole.world_box());
    let zeros = Volume::new([8, 8, 8], glam::Vec3::ONE, vec![0.0; 512])
        .unwrap()
        .with_origin(glam::Vec3::new(60.0, 0.0, 0.0))
        .unwrap();
    let empty = vdi_of(&zeros, &camera);
    assert!(empty.supersegments().is_empty());
    let whole_vdi = vdi_of(&whole, &camera);
    let composed = compose_vdis(&[&whole_vdi, &empty]).unwrap();
    assert_eq!(composed.offsets(), whole_vdi.offsets());
    assert_eq!(composed.supersegments(), whole_vdi.supersegments());
    // An empty VDI's window holds nothing, and is the empty VDI again.
    let window = VdiWindow::crop(&empty);
    assert_eq!((window.rect(), window.memory_bytes()), ((0, 0, 0, 0), 4));
    assert_eq!(window.to_vdi(), empty);
    let whole_window = VdiWindow::crop(&whole_vdi);
    assert_eq!(
        compose_vdis(&[&whole_window, &window])
            .unwrap()
            .supersegments(),
        whole_vdi.supersegments()
    );

    let other_camera = vdi_of(&whole, &camera.orbit_y(10.0));
    assert_eq!(
        compose_vdis(&[&whole_vdi, &other_camera]),
        Err(ComposeError::Mismatch {
            part: 1,
            what: "generation camera"
        })
    );
    assert_eq!(compose_vdis::<Vdi>(&[]), Err(ComposeError::Empty));
    let b = Brick {
        offset: [0, 0, 0],
        dims: [4, 4, 4],
    };
    assert!(whole.brick(&b).is_ok());
}

/// A frame window must lie inside the frame and carry one opacity per pixel; an all-black
/// frame's window is empty and adds nothing.
#[test]
fn frame_windows_outside_the_frame_are_refused() {
    let camera = Camera::default_for_box(&field().world_box());
    let image = insitu_core::Image::new(4, 4);
    let opacity = vec![0.5; 16];
    let world_box = field().world_box();
    let at = |origin| BrickFrame {
        image: &image,
        opacity: &opacity,
        origin,
        world_box,
    };
    assert!(compose_frames(&camera, (8, 8), &[at([4, 4])]).is_ok());
    for origin in [[5, 0], [0, 5], [u32::MAX, 0]] {
        let err = compose_frames(&camera, (8, 8), &[at([4, 4]), at(origin)]).unwrap_err();
        assert!(
            matches!(&err, ComposeError::Frame { part: 1, problem } if problem.contains("outside 8×8")),
            "{origin:?}: {err}"
        );
    }
    let short = BrickFrame {
        opacity: &opacity[..15],
        ..at([0, 0])
    };
    assert!(matches!(
        compose_frames(&camera, (8, 8), &[short]),
        Err(ComposeError::Frame { part: 0, .. })
    ));
    let (origin, empty, planes) = frame_window((8, 8), |_| [0.0; 4]);
    assert_eq!((origin, empty.pixels().len(), planes.len()), ([0, 0], 0, 0));
    let (origin, one, planes) = frame_window((8, 8), |p| {
        if p == 8 * 3 + 5 {
            [0.0, 0.0, 0.0, 0.25]
        } else {
            [0.0; 4]
        }
    });
    assert_eq!(
        (origin, one.width(), one.height(), planes),
        ([5, 3], 1, 1, vec![0.25])
    );
}
