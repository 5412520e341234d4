//! The ocean series through `insitu replay` → generator-node → viz-node, all real processes.

use crate::common::{generator, index, load_vdi, local_q, replayed, viz};
use insitu_core::vdi::render;
use insitu_e2e::{bin, ocean, Daemon};
use insitu_proto::pb::viz_client::VizClient;
use insitu_proto::{pb, transport};
use std::process::Command;

pub fn replay(generator: &Daemon, ranks: u32, steps: usize, sample_every: u32) -> String {
    let series = ocean().unwrap();
    let out = Command::new(bin("insitu"))
        .args([
            "replay",
            "--series",
            series.to_str().unwrap(),
            "--generator",
            &generator.addr,
        ])
        .args(["--r", "64", "--codec", "zstd"])
        .args(["--ranks", &ranks.to_string(), "--steps", &steps.to_string()])
        .args(["--sample-every", &sample_every.to_string()])
        .env_remove("INSITU_TOKEN")
        .output()
        .unwrap();
    replayed(out)
}

#[test]
fn ocean_replay_is_stored_counted_and_scored_like_locally() {
    if ocean().is_none() {
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let rec = tmp.path().join("rec");
    let v = viz(&rec, "127.0.0.1:0", tmp.path());
    let g = generator(
        &crate::common::small_config(&v.addr, "block", 16),
        tmp.path(),
        &[],
    );
    replay(&g, 1, 12, 4);
    let summary = g.terminate();
    assert!(summary.contains("received 12"), "{summary}");
    let entries = index(&rec);
    // Every step is stored or counted as dropped: with `block`, nothing is dropped.
    assert!(summary.contains("dropped from queue 0"), "{summary}");
    assert_eq!(entries.len(), 12, "{summary}");
    let mut scored = 0;
    for e in &entries {
        let vdi = load_vdi(&rec, e);
        assert_eq!(vdi.resolution(), 64);
        let image = render::render(&vdi, &vdi.meta().camera.orbit_y(30.0), 48, 32, 0.99);
        assert!(image.is_valid());
        if e.step % 4 == 0 {
            // The viz-node scores asynchronously after storing; wait for it.
            let q_reported = insitu_e2e::wait_until(30.0, || {
                index(&rec)
                    .iter()
                    .any(|x| x.step == e.step && x.quality.is_some())
            });
            assert!(q_reported, "step {} was never scored", e.step);
            let e = index(&rec).into_iter().find(|x| x.step == e.step).unwrap();
            let local = local_q(&rec, &e);
            let reported = e.quality.unwrap().q_db.0;
            assert!(
                (local - reported).abs() < 1e-9 || (local.is_infinite() && reported.is_infinite()),
                "step {}: reported q {reported} vs local {local}",
                e.step
            );
            assert!(local > 20.0, "step {}: q {local}", e.step);
            scored += 1;
        }
    }
    assert_eq!(scored, 3);
    // Any stored step renders from any camera over the wire.
    let png = insitu_e2e::rt().block_on(async {
        let channel = transport::connect(&transport::uri(&v.addr)).await.unwrap();
        let camera = load_vdi(&rec, &entries[5]).meta().camera.orbit_y(90.0);
        let req = pb::RenderRequest {
            step: 5,
            rank: 0,
            camera: Some(pb::Camera::from(&camera)),
            width: 40,
            height: 24,
            composed: false,
        };
        let mut c = VizClient::new(channel);
        let missing = c
            .render(pb::RenderRequest { step: 99, ..req })
            .await
            .unwrap_err();
        assert_eq!(missing.code(), tonic::Code::NotFound);
        c.render(req).await.unwrap().into_inner().png
    });
    assert_eq!(&png[..8], b"\x89PNG\r\n\x1a\n");
    let dim = |at: usize| u32::from_be_bytes([png[at], png[at + 1], png[at + 2], png[at + 3]]);
    assert_eq!((dim(16), dim(20)), (40, 24));
    v.terminate();
}

#[test]
fn bricks_over_two_and_four_ranks_are_stored_and_render() {
    if ocean().is_none() {
        return;
    }
    for ranks in [2u32, 4] {
        let tmp = tempfile::tempdir().unwrap();
        let rec = tmp.path().join("rec");
        let v = viz(&rec, "127.0.0.1:0", tmp.path());
        // Each rank's VDI shipped as made (its node does not compose them), to see each.
        let cfg = crate::common::small_config(&v.addr, "block", 16) + "[host]\ncompose = false\n";
        let g = generator(&cfg, tmp.path(), &[]);
        replay(&g, ranks, 3, 0);
        g.terminate();
        let entries = index(&rec);
        assert_eq!(entries.len(), 3 * ranks as usize);
        for step in 0..3u64 {
            let boxes: Vec<insitu_core::volume::Aabb> = (0..ranks)
                .map(|rank| {
                    let e = entries
                        .iter()
                        .find(|e| e.step == step && e.rank == rank)
                        .unwrap();
                    assert_eq!(e.world_size, ranks);
                    let vdi = load_vdi(&rec, e);
                    let image = render::render(&vdi, &vdi.meta().camera, 64, 64, 0.99);
                    assert!(image.is_valid());
                    vdi.meta().volume_box
                })
                .collect();
            // The ranks' boxes tile the grid's box [0, 179] × [0, 89] × [0, 18]: their union
            // is it and their volumes add up to its volume (so they do not overlap).
            let union = insitu_core::compose::union_box(boxes.iter().copied()).unwrap();
            assert_eq!(union.min, glam::Vec3::ZERO);
            assert_eq!(union.max, glam::Vec3::new(179.0, 89.0, 18.0));
            let volume = |b: &insitu_core::volume::Aabb| (b.max - b.min).element_product();
            let sum: f32 = boxes.iter().map(volume).sum();
            assert!(
                (sum - volume(&union)).abs() < 1e-3 * volume(&union),
                "{boxes:?}"
            );
        }
        v.terminate();
    }
}
