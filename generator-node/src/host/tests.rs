//! A host's composition of its ranks' steps: parts, waits and ranks that pass through.

use super::*;
use insitu_core::volume::bricks::grid_bricks;
use insitu_core::Image;
use insitu_core::{dvr, RaycastParams, Raycaster, TransferFunction, VdiParams, Volume};

const GLOBAL: [usize; 3] = [17, 13, 11];

fn rgba_frame(bytes: &[u8], size: (u32, u32)) -> (Image, Vec<f32>) {
    frame_from_le_bytes(bytes, size).unwrap()
}

fn whole() -> Volume {
    Volume::from_fn(GLOBAL, |x, y, z| {
        let d = [x as f32 - 7.0, y as f32 - 6.0, z as f32 - 5.0];
        (-(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]) / 20.0).exp()
    })
    .unwrap()
}

/// Rank `rank`'s finished step over brick `b`, as the worker makes it (frames at 0° and
/// 90° with opacity when `frames`).
fn finished(step: u64, rank: u32, world: u32, b: Brick, frames: bool) -> Finished {
    let whole = whole();
    let tf = TransferFunction::default_for_range(0.0, 1.0);
    let brick = whole.brick(&b).unwrap();
    let rc = Raycaster::new(&brick, &tf, RaycastParams::default()).unwrap();
    let camera = Camera::default_for_box(&whole.world_box());
    let params = VdiParams {
        resolution: 32,
        gamma: 0.01,
        precision: Default::default(),
    };
    let vdi = insitu_core::vdi::generate::generate(&rc, &camera, params, 1, "t").unwrap();
    let provenance = insitu_core::vdi::provenance::Provenance {
        step,
        rank,
        world_size: world,
        pm_version: 0,
        sim_time: step as f64,
        placement: Some((GLOBAL, b)),
        covers: Vec::new(),
        scene_version: 0,
    };
    let file = codec::encode_with_provenance(&vdi, Codec::Zstd, Some(&provenance)).unwrap();
    let angles = vec![0.0, 90.0];
    let references = frames.then(|| {
        let bytes: Vec<u8> = angles
            .iter()
            .flat_map(|&a| {
                let (image, opacity) = dvr::render_with_opacity(&rc, &camera.orbit_y(a), 24, 24);
                frame_to_le_bytes(&image, &opacity).collect::<Vec<u8>>()
            })
            .collect();
        let header = pb::ReferenceHeader {
            step,
            rank,
            width: 24,
            height: 24,
            camera: Some(pb::Camera::from(&camera)),
            view_angles_deg: angles.clone(),
            total_bytes: bytes.len() as u64,
            opacity: true,
            covers: Vec::new(),
        };
        (header, Bytes::from(bytes))
    });
    Finished::new(
        Product {
            vdi_header: pb::VdiHeader {
                step,
                rank,
                world_size: world,
                resolution: 32,
                gamma: 0.01,
                codec: pb::Codec::Zstd as i32,
                total_bytes: file.len() as u64,
                tau_secs: 0.1 * f64::from(rank + 1),
                global_dims: Some(pb::Dims3::from(GLOBAL)),
                brick_offset: Some(pb::Dims3::from(b.offset)),
                brick_dims: Some(pb::Dims3::from(b.dims)),
                with_references: frames,
                ..Default::default()
            },
            vdi: Bytes::from(file),
            references,
            spool: vec![(format!("s{step}r{rank}"), 10)],
            limit_retries: (1, 0.5),
            first_try: None,
        },
        vdi,
    )
}

/// A part is the composition of its ranks, VDI and frames, and says so: its header and
/// file name every rank and their box, σ is its file, τ the slowest rank's, and it
/// carries every rank's spool entry and retries.
#[test]
fn a_part_is_its_ranks_composed_and_names_them() {
    let bricks = grid_bricks(GLOBAL, [2, 1, 2]).unwrap();
    let group: Vec<Finished> = bricks
        .iter()
        .enumerate()
        .map(|(k, b)| finished(3, k as u32, 4, *b, true))
        .collect();
    let whole_box = Brick {
        offset: [0; 3],
        dims: GLOBAL,
    };
    let part = compose_part(&group, whole_box).unwrap();
    let h = &part.vdi_header;
    assert_eq!((h.rank, h.covers.clone()), (0, vec![0, 1, 2, 3]));
    assert_eq!(h.total_bytes, part.vdi.len() as u64);
    assert!((h.tau_secs - 0.4).abs() < 1e-12);
    assert_eq!(
        h.brick_dims.as_ref().map(|d| [d.x, d.y, d.z]),
        Some([17, 13, 11])
    );
    assert_eq!(part.spool.len(), 4);
    assert_eq!(part.limit_retries.0, 4);
    let (vdi, provenance) = codec::decode_with_provenance(&part.vdi, &Default::default()).unwrap();
    let lists: Vec<&Lists> = group.iter().map(|f| &f.lists).collect();
    assert_eq!(vdi, compose_vdis(&lists).unwrap());
    let p = provenance.unwrap();
    assert_eq!(
        (p.covers, p.placement),
        (vec![0, 1, 2, 3], Some((GLOBAL, whole_box)))
    );
    // The frames: the ranks' composited per view, as the viz-node would.
    let (rh, bytes) = part.references.as_ref().unwrap();
    assert_eq!(
        (rh.covers.clone(), rh.total_bytes),
        (vec![0, 1, 2, 3], bytes.len() as u64)
    );
    let camera = Camera::try_from(rh.camera.as_ref().unwrap()).unwrap();
    for (v, &angle) in rh.view_angles_deg.iter().enumerate() {
        let per = 24 * 24 * 16;
        let (got, got_opacity) = rgba_frame(&bytes[v * per..(v + 1) * per], (24, 24));
        let frames: Vec<(Image, Vec<f32>)> = group
            .iter()
            .map(|f| {
                let b = &f.product.references.as_ref().unwrap().1;
                rgba_frame(&b[v * per..(v + 1) * per], (24, 24))
            })
            .collect();
        let bf: Vec<BrickFrame> = frames
            .iter()
            .zip(&group)
            .map(|((i, o), f)| BrickFrame {
                image: i,
                opacity: o,
                origin: [0, 0],
                world_box: f.lists.meta().volume_box,
            })
            .collect();
        let (want, want_opacity) = compose_frames(&camera.orbit_y(angle), (24, 24), &bf).unwrap();
        assert_eq!((got, got_opacity), (want, want_opacity), "view {v}");
    }
    // Packed while they wait, the ranks make the same part, and a rank that ships alone
    // gets its frames back byte for byte; a packed brick's frames are a fraction.
    let mut packed: Vec<Finished> = bricks
        .iter()
        .enumerate()
        .map(|(k, b)| finished(3, k as u32, 4, *b, true))
        .collect();
    for f in &mut packed {
        let raw = f.product.references.as_ref().unwrap().1.len();
        let made = f.pack().unwrap();
        assert!(f.product.references.is_none());
        // What the packed views hold in memory (their buffers' capacity), not only
        // what they say they hold.
        let held = f.packed.as_ref().unwrap().held_bytes();
        assert!(held * 4 < raw, "{held} of {raw} bytes");
        // The lists wait as the brick's window: the same lists without r² offsets.
        let Lists::Window(w) = &f.lists else {
            panic!(
                "rank {} waits with its whole VDI",
                f.product.vdi_header.rank
            )
        };
        assert_eq!(w.to_vdi(), made);
        assert!(w.memory_bytes() < made.memory_bytes());
        assert!(f.pack().is_none(), "packed twice");
    }
    let again = compose_part(&packed, whole_box).unwrap();
    assert_eq!(
        (&again.vdi, &again.references),
        (&part.vdi, &part.references)
    );
    let mut alone = finished(3, 0, 4, bricks[0], true);
    let want = alone.product.references.clone();
    alone.pack();
    assert_eq!(alone.into_product().references, want);
    // Ranks with frames beside ranks without cannot be one part.
    let mixed = vec![
        finished(3, 0, 4, bricks[0], true),
        finished(3, 1, 4, bricks[1], false),
    ];
    let err = compose_part(&mixed, bricks[0]).unwrap_err();
    assert!(err.to_string().contains("1 of 2 ranks"), "{err}");
}

fn gather(wait_secs: f64) -> Gather {
    Gather::new(&HostConfig {
        compose: true,
        wait_secs,
    })
}

fn ranks_of(due: &[Vec<Finished>]) -> Vec<Vec<u32>> {
    due.iter()
        .map(|s| s.iter().map(|f| f.product.vdi_header.rank).collect())
        .collect()
}

/// A step's ranks ship once every rank received is finished or settled; a rank served at
/// the last step and not received is waited for until `wait_secs` after the last
/// progress; closing ships everything.
#[test]
fn a_step_ships_when_its_received_ranks_are_in_or_its_wait_is_over() {
    let b = grid_bricks(GLOBAL, [2, 1, 1]).unwrap();
    let g = gather(0.2);
    let t0 = Instant::now();
    g.received(0, 0, 2);
    g.received(0, 1, 2);
    assert!(g.finish(finished(0, 0, 2, b[0], false)).is_none());
    let (due, next, _) = g.take_due(Instant::now());
    assert!(due.is_empty() && next.is_none(), "rank 1 was received");
    assert!(g.finish(finished(0, 1, 2, b[1], false)).is_none());
    let (due, _, _) = g.take_due(Instant::now());
    assert_eq!(ranks_of(&due), [[0, 1]]);
    // Step 1: rank 1 served at step 0 but not received; rank 0 waits for it, then ships.
    g.received(1, 0, 2);
    assert!(g.finish(finished(1, 0, 2, b[0], false)).is_none());
    let (due, next, _) = g.take_due(Instant::now());
    assert!(due.is_empty());
    let deadline = next.unwrap();
    assert!(deadline > t0 && deadline <= Instant::now() + Duration::from_secs_f64(0.2));
    let (due, _, _) = g.take_due(deadline);
    assert_eq!(ranks_of(&due), [[0]]);
    // Step 2: rank 1 dropped from the queue settles it without a VDI.
    g.received(2, 0, 2);
    g.received(2, 1, 2);
    g.settled(2, 1);
    assert!(g.finish(finished(2, 0, 2, b[0], false)).is_none());
    let (due, _, _) = g.take_due(Instant::now());
    assert_eq!(ranks_of(&due), [[0]]);
    // A node's first step waits for the whole world, then ships what it has.
    let first = gather(0.2);
    first.received(0, 0, 2);
    assert!(first.finish(finished(0, 0, 2, b[0], false)).is_none());
    let (due, next, _) = first.take_due(Instant::now());
    assert!(due.is_empty() && next.is_some());
    let (due, _, _) = first.take_due(next.unwrap());
    assert_eq!(ranks_of(&due), [[0]]);
    // Closing ships what waits.
    g.received(3, 0, 2);
    g.received(3, 1, 2);
    assert!(g.finish(finished(3, 1, 2, b[1], false)).is_none());
    g.close();
    let (due, _, finished_all) = g.take_due(Instant::now());
    assert_eq!((ranks_of(&due), finished_all), (vec![vec![1]], true));
}

/// What ships as it is: a world of one, a step from the spool, a rank never announced,
/// every rank with composition off.
#[test]
fn ranks_that_cannot_wait_for_their_host_pass_through() {
    let b = grid_bricks(GLOBAL, [2, 1, 1]).unwrap();
    let whole = Brick {
        offset: [0; 3],
        dims: GLOBAL,
    };
    let g = gather(1.0);
    assert!(g.finish(finished(0, 0, 1, whole, false)).is_some());
    g.received(1, 0, 2);
    g.alone(1, 0);
    assert!(g.finish(finished(1, 0, 2, b[0], false)).is_some());
    assert!(g.finish(finished(1, 1, 2, b[1], false)).is_some());
    let off = Gather::new(&HostConfig {
        compose: false,
        wait_secs: 1.0,
    });
    off.received(0, 0, 2);
    assert!(off.finish(finished(0, 0, 2, b[0], false)).is_some());
}
