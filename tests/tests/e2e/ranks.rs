//! Many ranks, one picture: composed equals whole on the ocean series, one TF for a world
//! whose bricks have different ranges (kept across a generator-node restart), a missing rank
//! leaves a partial step, and bad decompositions are refused naming the step and ranks.

use crate::common::{generator, index, load_vdi, small_config, status, steps, viz, viz_status};
use insitu_client::{f32_bytes, ScalarType, SimClient, Step};
use insitu_core::metrics::psnr;
use insitu_core::vdi::codec::{decode, encode, Codec, DecodeLimits};
use insitu_core::vdi::{generate::generate, render, VdiParams};
use insitu_core::volume::bricks::Brick;
use insitu_core::{Camera, RaycastParams, Raycaster, TransferFunction, Vdi, Volume};
use insitu_e2e::{bin, ocean, rt, wait_until, Daemon};
use insitu_proto::pb::viz_client::VizClient;
use insitu_proto::{chunk, pb, transport};
use std::path::Path;
use std::process::Command;

fn decode_file(path: &Path) -> Vdi {
    decode(&std::fs::read(path).unwrap(), &DecodeLimits::default()).unwrap()
}

/// Replays 3 ocean steps at r = 128 with `split` (every rank on one generator-node, which
/// composes them into one part before shipping unless `one_level`) into a fresh recording;
/// returns it.
fn replay_split(split: &str, one_level: bool, tmp: &Path) -> std::path::PathBuf {
    let rec = tmp.join(format!("rec-{split}-{}", if one_level { 1 } else { 2 }));
    let v = viz(&rec, "127.0.0.1:0", tmp);
    let mut cfg = small_config(&v.addr, "block", 16);
    if one_level {
        cfg.push_str("[host]\ncompose = false\n");
    }
    let g = generator(&cfg, tmp, &[]);
    let series = ocean().unwrap();
    let out = Command::new(bin("insitu"))
        .args(["replay", "--series", series.to_str().unwrap()])
        .args(["--generator", &g.addr, "--split", split])
        .args(["--r", "128", "--gamma", "0.01", "--codec", "zstd"])
        .args(["--steps", "3", "--sample-every", "1"])
        .env_remove("INSITU_TOKEN")
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "replay --split {split}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    g.terminate();
    let multi = split != "1x1x1";
    let done = wait_until(60.0, || {
        if multi {
            let s = steps(&rec);
            s.len() == 3 && s.iter().all(|s| s.quality.is_some())
        } else {
            index(&rec).iter().filter(|e| e.quality.is_some()).count() == 3
        }
    });
    assert!(
        done,
        "--split {split}: steps were not all composed and scored"
    );
    // Every part's VDI and frames were decoded once, on receipt, and handed to the scorer
    // or composer from memory: a part per rank, or one per step when the node composed its
    // ranks (they tile the grid: one box).
    let ranks: u64 = split
        .split('x')
        .map(|n| n.parse::<u64>().unwrap())
        .product();
    let parts = if one_level { ranks } else { 1 };
    let status = viz_status(&v.addr);
    assert_eq!(
        (status.decoded_reused, status.decoded_again),
        (3 * parts * 2, 0),
        "--split {split}"
    );
    assert_eq!(index(&rec).len() as u64, 3 * parts, "--split {split}");
    v.terminate();
    rec
}

#[test]
fn composed_ocean_steps_render_and_score_like_the_whole_domain() {
    if ocean().is_none() {
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let whole = replay_split("1x1x1", false, tmp.path());
    let whole_entries = index(&whole);
    for split in ["2x2x1", "4x1x1", "1x1x3"] {
        let rec = replay_split(split, true, tmp.path());
        for s in steps(&rec) {
            assert!(s.missing.is_empty() && s.error.is_none(), "{s:?}");
            let composed = decode_file(&rec.join(s.vdi.as_ref().unwrap()));
            let e = whole_entries.iter().find(|e| e.step == s.step).unwrap();
            let one = load_vdi(&whole, e);
            assert_eq!(composed.meta().volume_box, one.meta().volume_box);
            let cam = one.meta().camera;
            for (angle, size, floor) in [(0.0, 128, 55.0), (30.0, 96, 40.0), (60.0, 96, 40.0)] {
                let view = cam.orbit_y(angle);
                let a = render::render(&composed, &view, size, size, 0.99);
                let b = render::render(&one, &view, size, size, 0.99);
                let q = psnr(&a, &b).unwrap();
                eprintln!(
                    "{split} step {} at {angle}° ({size}²): composed vs whole {q:.1} dB",
                    s.step
                );
                assert!(q >= floor, "{split} step {} at {angle}°: {q:.1} dB", s.step);
            }
            let q_multi = s.quality.as_ref().unwrap().q_db.0;
            let q_one = e.quality.as_ref().unwrap().q_db.0;
            eprintln!(
                "{split} step {}: q composed {q_multi:.2} dB, single rank {q_one:.2} dB",
                s.step
            );
            assert!(
                (q_multi - q_one).abs() < 1.0,
                "{split} step {}: composed q {q_multi:.2} vs single-rank {q_one:.2}",
                s.step
            );
        }
    }
}

/// Two-level composition: the node composes its 4 ranks into one part, the viz-node composes
/// parts; the stored picture and q are those of one-level composition (the viz-node composing
/// the 4 ranks itself), and the viz-node receives one part per step instead of four.
#[test]
fn hosts_composing_first_store_the_one_level_picture_and_q() {
    if ocean().is_none() {
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    for split in ["2x2x1", "1x2x2"] {
        let one = replay_split(split, true, tmp.path());
        let two = replay_split(split, false, tmp.path());
        let (parts_one, parts_two) = (index(&one), index(&two));
        for (a, b) in steps(&one).iter().zip(steps(&two)) {
            assert_eq!(
                (a.step, &a.ranks, &b.ranks),
                (b.step, &vec![0, 1, 2, 3], &b.ranks)
            );
            assert!(b.missing.is_empty() && b.error.is_none(), "{b:?}");
            // The parts that reached the viz-node: 4 VDIs of one rank, or 1 of all four.
            let of = |parts: &[insitu_recording::store::Entry]| -> Vec<Vec<u32>> {
                parts
                    .iter()
                    .filter(|e| e.step == a.step)
                    .map(|e| e.ranks())
                    .collect()
            };
            assert_eq!(of(&parts_one), [[0], [1], [2], [3]]);
            assert_eq!(of(&parts_two), [[0, 1, 2, 3]]);
            let va = decode_file(&one.join(a.vdi.as_ref().unwrap()));
            let vb = decode_file(&two.join(b.vdi.as_ref().unwrap()));
            let cam = va.meta().camera;
            let (ia, ib) = (
                render::render(&va, &cam, 128, 128, 0.99),
                render::render(&vb, &cam, 128, 128, 0.99),
            );
            let same = psnr(&ia, &ib).unwrap();
            let (qa, qb) = (
                a.quality.as_ref().unwrap().q_db.0,
                b.quality.as_ref().unwrap().q_db.0,
            );
            eprintln!(
                "{split} step {}: two-level vs one-level {same:.1} dB at the generation view, q {qb:.3} vs {qa:.3} dB",
                a.step
            );
            assert!(same >= 60.0, "{split} step {}: {same:.1} dB", a.step);
            assert!(
                (qa - qb).abs() <= 0.05,
                "{split} step {}: q {qb} vs {qa}",
                a.step
            );
            assert_eq!(va.supersegments().len(), vb.supersegments().len());
        }
    }
}

/// Rank `rank`'s brick `b` of a 33³ grid of soft blobs, as a simulation would push it.
pub(crate) fn blob_step(step: u64, rank: u32, world_size: u32, b: Brick) -> Step {
    let value = |x: usize, y: usize, z: usize| {
        let d2 = |c: [f32; 3], s: f32| {
            let d = [x as f32 - c[0], y as f32 - c[1], z as f32 - c[2]];
            (-(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]) / (2.0 * s * s)).exp()
        };
        d2([12.0, 14.0, 10.0], 6.0) + 0.8 * d2([22.0, 20.0, 21.0], 7.0) + 0.02 * step as f32
    };
    let mut data = Vec::with_capacity(b.dims.iter().product());
    for z in 0..b.dims[2] {
        for y in 0..b.dims[1] {
            for x in 0..b.dims[0] {
                data.push(value(b.offset[0] + x, b.offset[1] + y, b.offset[2] + z));
            }
        }
    }
    let d = |v: [usize; 3]| v.map(|x| x as u32);
    Step {
        step,
        sim_time: step as f64,
        dtype: ScalarType::F32,
        global_dims: [33; 3],
        brick_offset: d(b.offset),
        brick_dims: d(b.dims),
        rank,
        world_size,
        spacing: [1.0; 3],
        origin: [0.0; 3],
        data: f32_bytes(&data),
        fields: Vec::new(),
    }
}

/// 8 ranks (2 × 2 × 2 bricks) over two generator-nodes, ranks 0–2 on one and 3–7 on the
/// other: neither host's bricks form a box, so each ships two parts. The stored steps are
/// those of one-level composition (each rank's VDI shipped alone): the same picture at the
/// generation view and orbits of it, q within 0.05 dB; the viz-node receives 4 parts per step
/// instead of 8 VDIs.
#[test]
fn two_hosts_whose_ranks_are_not_boxes_store_the_one_level_steps() {
    let tmp = tempfile::tempdir().unwrap();
    let bricks = insitu_core::volume::bricks::grid_bricks([33; 3], [2, 2, 2]).unwrap();
    let run = |one_level: bool| {
        let rec = tmp.path().join(format!("rec-{one_level}"));
        let v = viz(&rec, "127.0.0.1:0", tmp.path());
        let mut cfg = small_config(&v.addr, "block", 16)
            .replace("reference_every = 0", "reference_every = 1")
            .replace("resolution = 32", "resolution = 64");
        if one_level {
            cfg.push_str("[host]\ncompose = false\n");
        }
        let hosts = [
            generator(&cfg, tmp.path(), &[]),
            generator(&cfg, tmp.path(), &[]),
        ];
        rt().block_on(async {
            let mut tasks = Vec::new();
            for (rank, b) in bricks.iter().enumerate() {
                let addr = hosts[usize::from(rank >= 3)].addr.clone();
                let b = *b;
                tasks.push(tokio::spawn(async move {
                    let mut c = SimClient::connect(&addr, None).await.unwrap();
                    for step in 0..2 {
                        c.push_step(blob_step(step, rank as u32, 8, b))
                            .await
                            .unwrap();
                    }
                    c.flush(std::time::Duration::from_secs(120)).await.unwrap();
                }));
            }
            for t in tasks {
                t.await.unwrap();
            }
        });
        let done = wait_until(60.0, || {
            let s = steps(&rec);
            s.len() == 2 && s.iter().all(|s| s.quality.is_some())
        });
        assert!(done, "{:?}", steps(&rec));
        for h in hosts {
            h.terminate();
        }
        v.terminate();
        rec
    };
    let (one, two) = (run(true), run(false));
    for (a, b) in steps(&one).iter().zip(steps(&two)) {
        assert_eq!((a.step, &a.ranks), (b.step, &b.ranks));
        assert!(b.missing.is_empty() && b.error.is_none(), "{b:?}");
        let parts = |rec: &Path| -> Vec<Vec<u32>> {
            index(rec)
                .iter()
                .filter(|e| e.step == a.step)
                .map(|e| e.ranks())
                .collect()
        };
        assert_eq!(parts(&one).len(), 8);
        // Host 0: ranks 0, 1 share a y-z face, rank 2 sits above rank 0 alone; host 1: rank 3
        // alone, ranks 4–7 the upper z layer.
        assert_eq!(
            parts(&two),
            [vec![0, 1], vec![2], vec![3], vec![4, 5, 6, 7]]
        );
        let va = decode_file(&one.join(a.vdi.as_ref().unwrap()));
        let vb = decode_file(&two.join(b.vdi.as_ref().unwrap()));
        for angle in [0.0, 30.0, 150.0] {
            let view = va.meta().camera.orbit_y(angle);
            let q = psnr(
                &render::render(&va, &view, 64, 64, 0.99),
                &render::render(&vb, &view, 64, 64, 0.99),
            )
            .unwrap();
            assert!(q >= 60.0, "step {} at {angle}°: {q:.1} dB", a.step);
        }
        let (qa, qb) = (
            a.quality.as_ref().unwrap().q_db.0,
            b.quality.as_ref().unwrap().q_db.0,
        );
        eprintln!(
            "step {}: q two-level {qb:.3} dB, one-level {qa:.3} dB",
            a.step
        );
        assert!((qa - qb).abs() <= 0.05, "step {}: q {qb} vs {qa}", a.step);
    }
}

/// Blocks laid out as one splits an array (each point in one block, no plane shared, as
/// ADIOS2 writers lay them out), pushed as ranks. All on one generator-node: the node grows
/// each block by its neighbours' first planes, the steps compose without seams, and the
/// picture is the whole field's (≥ 40 dB at four views, q within 1 dB, as for bricks that share
/// planes) and that of the bricks they grow into, bit for bit. Spread over two nodes: the
/// nodes exchange the faces through the viz-node, and the steps are the one node's, bit for
/// bit.
#[test]
fn blocks_without_shared_planes_compose_like_the_whole_field() {
    let tmp = tempfile::tempdir().unwrap();
    let global = [33; 3];
    // Pushes `bricks` as the ranks of 2 steps, rank k to node `host(k)` of `nodes`.
    let run = |name: &str, bricks: Vec<Brick>, nodes: usize| {
        let rec = tmp.path().join(name);
        let v = viz(&rec, "127.0.0.1:0", tmp.path());
        let cfg = small_config(&v.addr, "block", 16)
            .replace("reference_every = 0", "reference_every = 1")
            .replace("resolution = 32", "resolution = 64");
        let hosts: Vec<Daemon> = (0..nodes)
            .map(|_| generator(&cfg, tmp.path(), &[]))
            .collect();
        let world = bricks.len() as u32;
        rt().block_on(async {
            let mut tasks = Vec::new();
            for (rank, b) in bricks.into_iter().enumerate() {
                let addr = hosts[rank * nodes / world as usize].addr.clone();
                tasks.push(tokio::spawn(async move {
                    let mut c = SimClient::connect(&addr, None).await.unwrap();
                    for step in 0..2 {
                        c.push_step(blob_step(step, rank as u32, world, b))
                            .await
                            .unwrap();
                    }
                }));
            }
            for t in tasks {
                t.await.unwrap();
            }
        });
        // A world of one is stored as its rank's rows, a world of several as composed steps.
        let done = wait_until(60.0, || {
            if world == 1 {
                let e = index(&rec);
                return e.len() == 2 && e.iter().all(|e| e.quality.is_some());
            }
            let s = steps(&rec);
            s.len() == 2 && s.iter().all(|s| s.quality.is_some() || s.error.is_some())
        });
        assert!(done, "{name}: {:?}", steps(&rec));
        let statuses: Vec<_> = hosts.iter().map(|h| status(&h.addr)).collect();
        for h in hosts {
            h.terminate();
        }
        v.terminate();
        (rec, statuses)
    };
    let (whole, _) = run(
        "whole",
        vec![Brick {
            offset: [0; 3],
            dims: global,
        }],
        1,
    );
    let whole_steps = index(&whole);
    for split in [[1, 1, 2], [2, 2, 2]] {
        let blocks = insitu_core::volume::bricks::block_bricks(global, split).unwrap();
        let (rec, _) = run(&format!("blocks-{split:?}"), blocks, 1);
        // On 33 points, halving grows the blocks into exactly the bricks that share planes.
        let grid = insitu_core::volume::bricks::grid_bricks(global, split).unwrap();
        let (shared, _) = run(&format!("shared-{split:?}"), grid, 1);
        let shared_steps = steps(&shared);
        for s in steps(&rec) {
            assert!(s.missing.is_empty() && s.error.is_none(), "{s:?}");
            let e = whole_steps.iter().find(|e| e.step == s.step).unwrap();
            let one = load_vdi(&whole, e);
            let composed = decode_file(&rec.join(s.vdi.as_ref().unwrap()));
            assert_eq!(composed.meta().volume_box, one.meta().volume_box);
            for angle in [0.0, 30.0, 150.0, 240.0] {
                let view = one.meta().camera.orbit_y(angle);
                let q = psnr(
                    &render::render(&composed, &view, 96, 96, 0.99),
                    &render::render(&one, &view, 96, 96, 0.99),
                )
                .unwrap();
                eprintln!(
                    "{split:?} step {} at {angle}°: blocks vs whole {q:.1} dB",
                    s.step
                );
                assert!(
                    q >= 40.0,
                    "{split:?} step {} at {angle}°: {q:.1} dB",
                    s.step
                );
            }
            let (qb, qw) = (
                s.quality.as_ref().unwrap().q_db.0,
                e.quality.as_ref().unwrap().q_db.0,
            );
            eprintln!(
                "{split:?} step {}: q {qb:.2} dB (whole {qw:.2}), τ {:.4} s (whole {:.4})",
                s.step, s.sizing.tau_secs, e.sizing.tau_secs
            );
            assert!(
                (qb - qw).abs() < 1.0,
                "{split:?} step {}: q {qb} vs {qw}",
                s.step
            );
            let same = shared_steps.iter().find(|e| e.step == s.step).unwrap();
            let planes = decode_file(&shared.join(same.vdi.as_ref().unwrap()));
            assert_eq!(
                composed.supersegments(),
                planes.supersegments(),
                "{split:?}"
            );
            assert_eq!(s.quality, same.quality, "{split:?} step {}", s.step);
        }
    }
    // The two z-halves on two nodes: neither holds both sides of the seam, so each posts
    // its bricks' faces to the viz-node, and the lower half grows by the upper half's face
    // from the other node. The steps are those of the bricks they grow into pushed to the two
    // nodes, bit for bit, and the whole field's picture at four views.
    let halves = insitu_core::volume::bricks::block_bricks(global, [1, 1, 2]).unwrap();
    let (rec, nodes) = run("apart", halves, 2);
    let grid = insitu_core::volume::bricks::grid_bricks(global, [1, 1, 2]).unwrap();
    let (planes, _) = run("shared-apart", grid, 2);
    let on_planes = steps(&planes);
    for s in steps(&rec) {
        assert!(s.missing.is_empty() && s.error.is_none(), "{s:?}");
        let same = on_planes.iter().find(|e| e.step == s.step).unwrap();
        let apart = decode_file(&rec.join(s.vdi.as_ref().unwrap()));
        let shared = decode_file(&planes.join(same.vdi.as_ref().unwrap()));
        assert_eq!(
            apart.supersegments(),
            shared.supersegments(),
            "step {}",
            s.step
        );
        assert_eq!(s.quality, same.quality, "step {}", s.step);
        let e = whole_steps.iter().find(|e| e.step == s.step).unwrap();
        let one = load_vdi(&whole, e);
        for angle in [0.0, 30.0, 150.0, 240.0] {
            let view = one.meta().camera.orbit_y(angle);
            let q = psnr(
                &render::render(&apart, &view, 96, 96, 0.99),
                &render::render(&one, &view, 96, 96, 0.99),
            )
            .unwrap();
            eprintln!("two nodes, step {} at {angle}°: vs whole {q:.1} dB", s.step);
            assert!(
                q >= 40.0,
                "two nodes, step {} at {angle}°: {q:.1} dB",
                s.step
            );
        }
        eprintln!(
            "two nodes, step {}: q {:.2} dB, τ {:.4} s (shared planes: τ {:.4} s)",
            s.step,
            s.quality.as_ref().unwrap().q_db.0,
            s.sizing.tau_secs,
            same.sizing.tau_secs
        );
    }
    // The lower half grew on both steps from a face that came across; the upper half sent
    // its face (33 × 33 f32 samples) each step.
    let sent: u64 = nodes.iter().map(|n| n.faces_sent_bytes).sum();
    let grown: u64 = nodes.iter().map(|n| n.bricks_grown_across).sum();
    eprintln!("two nodes: {sent} bytes of faces sent, {grown} bricks grown across");
    assert_eq!(grown, 2);
    assert_eq!(nodes[1].faces_sent_bytes, 2 * 33 * 33 * 4);
}

/// A step of `world_size` ranks over z-slabs of a 16×16×(9·world − …) grid: rank `k` owns
/// z ∈ [8k, 8k + 8], all values `value(k)`.
pub(crate) fn slab(step: u64, rank: u32, world_size: u32, value: f32) -> Step {
    let nz = 8 * world_size + 1;
    Step {
        step,
        sim_time: step as f64,
        dtype: ScalarType::F32,
        global_dims: [16, 16, nz],
        brick_offset: [0, 0, 8 * rank],
        brick_dims: [16, 16, 9],
        rank,
        world_size,
        spacing: [1.0; 3],
        origin: [0.0; 3],
        data: f32_bytes(&vec![value; 16 * 16 * 9]),
        fields: Vec::new(),
    }
}

fn push(addr: &str, steps: Vec<Step>) {
    rt().block_on(async {
        let mut c = SimClient::connect(addr, None).await.unwrap();
        for s in steps {
            c.push_step(s).await.unwrap();
        }
    });
}

#[test]
fn ranks_with_different_ranges_share_one_tf_across_a_restart() {
    let tmp = tempfile::tempdir().unwrap();
    let rec = tmp.path().join("rec");
    let v = viz(&rec, "127.0.0.1:0", tmp.path());
    let cfg = small_config(&v.addr, "block", 16);
    let g0 = generator(&cfg, tmp.path(), &[]);
    let g1 = generator(&cfg, tmp.path(), &[]);
    // Rank 0 is all zeros, rank 1 all 1000: each alone would choose its own default.
    push(&g0.addr, vec![slab(0, 0, 2, 0.0)]);
    push(&g1.addr, vec![slab(0, 1, 2, 1000.0)]);
    assert!(
        wait_until(30.0, || index(&rec).len() == 2),
        "{:?}",
        index(&rec)
    );
    let first = index(&rec);
    assert_eq!(first[0].tf_hash, first[1].tf_hash, "{first:?}");
    assert_eq!(first[0].tf_name, "default[0, 1000]");
    // Rank 0's brick is transparent under that TF: an empty VDI.
    assert_eq!(first[0].sizing.supersegments, 0);
    assert!(first[1].sizing.supersegments > 0);
    // Rank 1's node dies and comes back; its next brick has another range, the TF stays.
    g1.kill();
    let g1 = generator(&cfg, tmp.path(), &[]);
    push(&g1.addr, vec![slab(1, 1, 2, 5000.0)]);
    push(&g0.addr, vec![slab(1, 0, 2, 3.0)]);
    assert!(wait_until(30.0, || index(&rec).len() == 4));
    assert!(
        index(&rec).iter().all(|e| e.tf_hash == first[0].tf_hash),
        "{:?}",
        index(&rec)
    );
    assert!(wait_until(30.0, || steps(&rec).len() == 2));
    assert!(steps(&rec)
        .iter()
        .all(|s| s.missing.is_empty() && s.error.is_none()));
    g0.terminate();
    g1.terminate();
    v.terminate();
}

#[test]
fn a_missing_rank_leaves_partial_steps_that_say_which() {
    let tmp = tempfile::tempdir().unwrap();
    let rec = tmp.path().join("rec");
    let v = Daemon::start(
        "viz-node",
        &[
            "--listen",
            "127.0.0.1:0",
            "--recording-dir",
            rec.to_str().unwrap(),
            "--compose-timeout-secs",
            "2",
        ],
        &[],
        tmp.path(),
    );
    // No TF configured: the world's default waits for rank 2's range as long as a step waits
    // for its VDI (2 s here), then is fixed over ranks 0 and 1.
    let cfg = small_config(&v.addr, "block", 16);
    let g = generator(&cfg, tmp.path(), &[]);
    // Rank 2 of 3 never reports (its process was killed before the step).
    push(
        &g.addr,
        vec![
            slab(0, 0, 3, 4.0),
            slab(0, 1, 3, 6.0),
            slab(1, 0, 3, 4.0),
            slab(1, 1, 3, 6.0),
        ],
    );
    let partial = wait_until(30.0, || {
        let s = steps(&rec);
        s.len() == 2 && s.iter().all(|s| s.missing == [2])
    });
    assert!(partial, "{:?}", steps(&rec));
    let scene: insitu_viz_node::scene::Agreed =
        serde_json::from_slice(&std::fs::read(rec.join("scene.json")).unwrap()).unwrap();
    assert_eq!(
        (scene.ranks.as_slice(), scene.tf_name.as_str()),
        (&[0, 1][..], "default[4, 6]")
    );
    for s in steps(&rec) {
        assert_eq!(s.ranks, [0, 1]);
        // The partial step is still a picture: rendered over the wire.
        let png = rt().block_on(async {
            let channel = transport::connect(&transport::uri(&v.addr)).await.unwrap();
            VizClient::new(channel)
                .render(pb::RenderRequest {
                    step: s.step,
                    composed: true,
                    width: 32,
                    height: 32,
                    ..Default::default()
                })
                .await
                .unwrap()
                .into_inner()
                .png
        });
        assert_eq!(&png[..4], b"\x89PNG");
    }
    let status = rt().block_on(async {
        let channel = transport::connect(&transport::uri(&v.addr)).await.unwrap();
        VizClient::new(channel)
            .get_status(pb::StatusRequest {})
            .await
            .unwrap()
            .into_inner()
    });
    assert_eq!((status.steps_partial, status.steps_composed), (2, 0));
    g.terminate();
    v.terminate();
}

/// The VDI of a constant brick `b` of a grid `global`, as a generator-node would ship it.
fn vdi_chunks(
    step: u64,
    rank: u32,
    world_size: u32,
    global: [usize; 3],
    b: Brick,
) -> Vec<pb::VdiChunk> {
    let whole = Volume::new(global, glam::Vec3::ONE, vec![5.0; global.iter().product()]).unwrap();
    let brick = whole.brick(&b).unwrap();
    let tf = TransferFunction::default_for_range(0.0, 10.0);
    let rc = Raycaster::new(&brick, &tf, RaycastParams::default()).unwrap();
    let cam = Camera::default_for_box(&whole.world_box());
    let params = VdiParams {
        resolution: 16,
        gamma: 0.01,
        precision: Default::default(),
    };
    let vdi = generate(&rc, &cam, params, tf.identity_hash(), "t").unwrap();
    let file = encode(&vdi, Codec::Zstd).unwrap();
    let d = |v: [usize; 3]| pb::Dims3 {
        x: v[0] as u32,
        y: v[1] as u32,
        z: v[2] as u32,
    };
    let header = pb::VdiHeader {
        step,
        rank,
        world_size,
        resolution: 16,
        gamma: 0.01,
        codec: pb::Codec::Zstd as i32,
        total_bytes: file.len() as u64,
        global_dims: Some(d(global)),
        brick_offset: Some(d(b.offset)),
        brick_dims: Some(d(b.dims)),
        ..Default::default()
    };
    chunk::split::<pb::VdiChunk>(header, bytes::Bytes::from(file))
}

#[test]
fn bad_decompositions_are_refused_naming_the_step_and_ranks() {
    let tmp = tempfile::tempdir().unwrap();
    let rec = tmp.path().join("rec");
    let v = viz(&rec, "127.0.0.1:0", tmp.path());
    let g = [16, 16, 17];
    let slab = |z0: usize, nz: usize| Brick {
        offset: [0, 0, z0],
        dims: [16, 16, nz],
    };
    rt().block_on(async {
        let channel = transport::connect(&transport::uri(&v.addr)).await.unwrap();
        let mut c = VizClient::new(channel);
        let ship = |chunks: Vec<pb::VdiChunk>| {
            let mut c = c.clone();
            async move { c.ship_vdi(tokio_stream::iter(chunks)).await }
        };
        // A rank outside the world.
        let e = ship(vdi_chunks(0, 2, 2, g, slab(0, 9))).await.unwrap_err();
        assert_eq!(e.code(), tonic::Code::InvalidArgument);
        assert!(e.message().contains("step 0 rank 2"), "{}", e.message());
        // Two world sizes for one step.
        ship(vdi_chunks(1, 0, 2, g, slab(0, 9))).await.unwrap();
        let e = ship(vdi_chunks(1, 1, 3, g, slab(8, 9))).await.unwrap_err();
        assert!(
            e.message().contains("step 1")
                && e.message().contains("world size 3")
                && e.message().contains("rank 0 said 2"),
            "{}",
            e.message()
        );
        // Overlapping bricks.
        ship(vdi_chunks(2, 0, 2, g, slab(0, 9))).await.unwrap();
        let e = ship(vdi_chunks(2, 1, 2, g, slab(4, 13))).await.unwrap_err();
        assert!(
            e.message().contains("step 2")
                && e.message().contains("ranks 0 and 1")
                && e.message().contains("overlap"),
            "{}",
            e.message()
        );
        // Bricks that leave a gap: stored, but the step is not composed, and says why.
        ship(vdi_chunks(3, 0, 2, g, slab(0, 8))).await.unwrap();
        ship(vdi_chunks(3, 1, 2, g, slab(8, 9))).await.unwrap();
        let _ = c.get_status(pb::StatusRequest {}).await.unwrap();
    });
    assert!(wait_until(30.0, || steps(&rec).iter().any(|s| s.step == 3)));
    let s3 = steps(&rec).into_iter().find(|s| s.step == 3).unwrap();
    let err = s3.error.unwrap_or_default();
    assert!(
        err.contains("step 3") && err.contains("[0, 1]") && err.contains("cover"),
        "{err}"
    );
    // Where the gap lies, and the fix.
    assert!(
        err.contains("the cells between z = 7 and z = 8 lie in no brick")
            && err.contains("let rank 0's brick include z = 8 (nz 9, not 8)"),
        "{err}"
    );
    assert!(s3.vdi.is_none());
    v.terminate();
}

/// r 32, γ 0.01 and a fixed transfer function over [0, 3] (the slabs' values): steps are
/// made without waiting for the world to agree one.
fn fixed_tf_config() -> pb::GenerationConfig {
    let tf = TransferFunction::default_named(0.0, 3.0).tf;
    pb::GenerationConfig {
        resolution: 32,
        gamma: 0.01,
        tf: Some(pb::TransferFunction::from(&tf)),
        tf_name: Some("fixed".into()),
        ..Default::default()
    }
}

/// With one client per rank, a flush reports the refusals of its own ranks' VDIs, once, and
/// not another rank's: rank 1 pushes a step under a world size the step's rank 0 contradicts,
/// rank 0's flush after that refusal is clean, rank 1's names it.
#[test]
fn each_rank_s_flush_reports_its_own_refusals() {
    let tmp = tempfile::tempdir().unwrap();
    let rec = tmp.path().join("rec");
    let v = viz(&rec, "127.0.0.1:0", tmp.path());
    let g = generator(&small_config(&v.addr, "block", 4), tmp.path(), &[]);
    // A fixed TF: no agreement over a world whose rank 1 never comes.
    let config = fixed_tf_config();
    let secs = std::time::Duration::from_secs(60);
    rt().block_on(async {
        let mut rank0 = SimClient::connect(&g.addr, None).await.unwrap();
        let mut rank1 = SimClient::connect(&g.addr, None).await.unwrap();
        rank0.set_config(config).await.unwrap();
        rank0.push_step(slab(1, 0, 2, 1.0)).await.unwrap();
        rank0.flush(secs).await.unwrap();
        rank1.push_step(slab(1, 1, 3, 2.0)).await.unwrap();
        rank0
            .flush(secs)
            .await
            .expect("rank 0's own steps were all stored");
        let e = rank1.flush(secs).await.unwrap_err().to_string();
        assert!(
            e.contains("refused 1 VDI(s) of rank(s) [1]") && e.contains("world size 3"),
            "{e}"
        );
        rank1.flush(secs).await.expect("a refusal is reported once");
    });
    g.terminate();
    v.terminate();
}

/// A rank whose brick overlaps another's, through the generator-node with reference frames on:
/// the viz-node refuses its VDI, so its frames never follow it there (before, they left a row
/// of world size 1 and r 0 that later ranks were checked against, with a false message); only
/// the refused rank's client hears of it.
#[test]
fn an_overlapping_rank_is_refused_without_leaving_a_row_behind() {
    let tmp = tempfile::tempdir().unwrap();
    let rec = tmp.path().join("rec");
    let v = viz(&rec, "127.0.0.1:0", tmp.path());
    let cfg =
        small_config(&v.addr, "block", 8).replace("reference_every = 0", "reference_every = 1");
    let g = generator(&cfg, tmp.path(), &[]);
    let secs = std::time::Duration::from_secs(120);
    rt().block_on(async {
        let mut clients = Vec::new();
        for rank in 0..4u32 {
            let mut c = SimClient::connect(&g.addr, None).await.unwrap();
            let mut s = slab(1, rank, 4, 1.0 + rank as f32);
            if rank == 1 {
                s.brick_offset = [0, 0, 4]; // over rank 0's z ∈ [0, 8]
            }
            c.push_step(s).await.unwrap();
            clients.push(c);
        }
        let e = clients[1].flush(secs).await.unwrap_err().to_string();
        assert!(e.contains("rank(s) [1]") && e.contains("overlap"), "{e}");
        for rank in [0, 2, 3] {
            clients[rank].flush(secs).await.unwrap();
        }
    });
    // Ranks 2 and 3 share a plane: their node ships them as one part. Rank 0's brick is not
    // a box with any other, so it ships alone.
    let entries = index(&rec);
    let rows: Vec<(u32, Vec<u32>, u32, u32)> = entries
        .iter()
        .map(|e| (e.rank, e.ranks(), e.world_size, e.resolution))
        .collect();
    assert_eq!(
        rows,
        vec![(0, vec![0], 4, 32), (2, vec![2, 3], 4, 32)],
        "{rows:?}"
    );
    g.terminate();
    v.terminate();
}

/// Bricks that leave a gap are stored, and the step cannot compose: each rank's client hears
/// why at its next flush, once (before, every push and close returned OK).
#[test]
fn a_step_that_cannot_compose_reaches_each_rank_s_flush() {
    let tmp = tempfile::tempdir().unwrap();
    let rec = tmp.path().join("rec");
    let v = viz(&rec, "127.0.0.1:0", tmp.path());
    let g = generator(&small_config(&v.addr, "block", 8), tmp.path(), &[]);
    let config = fixed_tf_config();
    let secs = std::time::Duration::from_secs(120);
    rt().block_on(async {
        let mut rank0 = SimClient::connect(&g.addr, None).await.unwrap();
        let mut rank1 = SimClient::connect(&g.addr, None).await.unwrap();
        rank0.set_config(config).await.unwrap();
        rank0.push_step(slab(1, 0, 2, 1.0)).await.unwrap();
        // Rank 1 starts two planes late: z ∈ [10, 16], leaving the points z = 9 out.
        let mut s = slab(1, 1, 2, 2.0);
        s.brick_offset = [0, 0, 10];
        s.brick_dims = [16, 16, 7];
        s.data = insitu_client::f32_bytes(&vec![2.0; 16 * 16 * 7]);
        rank1.push_step(s).await.unwrap();
        assert!(
            wait_until(30.0, || steps(&rec).iter().any(|s| s.error.is_some())),
            "{:?}",
            steps(&rec)
        );
        for (rank, c) in [(0, &mut rank0), (1, &mut rank1)] {
            let e = c.flush(secs).await.unwrap_err().to_string();
            assert!(
                e.contains("could not be composed") && e.contains("step 1") && e.contains("cover"),
                "rank {rank}: {e}"
            );
            c.flush(secs).await.expect("reported once");
        }
    });
    g.terminate();
    v.terminate();
}
