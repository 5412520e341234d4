//! A recording shared by step among two viz-nodes (docs/scale.md): the generator-node routes
//! step s to shard s mod 2, each shard composes and scores its steps, the tuner watches both,
//! and `insitu view`, `insitu export` and a read-only viewer over the recording see every step.

use crate::common::{generator, small_config, succeeded};
use crate::ranks::slab;
use crate::viewer::{http, viz_with_http};
use insitu_e2e::{bin, rt, wait_until, Daemon};
use insitu_recording::index;
use std::process::Command;

#[test]
fn two_viz_nodes_share_a_recording_by_step() {
    let tmp = tempfile::tempdir().unwrap();
    let rec = tmp.path().join("rec");
    let shard = |k: u32| {
        insitu_e2e::start_viz(
            &rec.join(format!("shard-{k}")),
            "127.0.0.1:0",
            &[],
            tmp.path(),
        )
    };
    let (v0, v1) = (shard(0), shard(1));
    let tuner_cfg = tmp.path().join("tuner.toml");
    std::fs::write(
        &tuner_cfg,
        format!(
            "listen = \"127.0.0.1:0\"\nstate_dir = {:?}\nviz = \"{}\"\nviz_shards = [\"{}\"]\nutility = \"size:1MB\"\n",
            tmp.path().join("tuner-state").to_str().unwrap(),
            v0.addr,
            v1.addr
        ),
    )
    .unwrap();
    let t = Daemon::start(
        "tuner-node",
        &["--config", tuner_cfg.to_str().unwrap()],
        &[],
        tmp.path(),
    );
    let cfg = small_config(&v0.addr, "block", 16)
        .replace("reference_every = 0", "reference_every = 1")
        .replace(
            &format!("viz = \"{}\"", v0.addr),
            &format!("viz = \"{}\"\nviz_shards = [\"{}\"]", v0.addr, v1.addr),
        );
    let g = generator(&cfg, tmp.path(), &[]);
    rt().block_on(async {
        let mut c = insitu_client::SimClient::connect(&g.addr, None)
            .await
            .unwrap();
        for step in 0..4u64 {
            for rank in 0..4 {
                c.push_step(slab(step, rank, 4, 1.0 + rank as f32))
                    .await
                    .unwrap();
            }
        }
        let s = c.flush(std::time::Duration::from_secs(120)).await.unwrap();
        assert_eq!((s.steps_shipped, s.failed), (16, 0), "{s:?}");
    });
    // Each shard holds its steps, composed and scored.
    let scored = |k: u32| {
        index::read(&rec.join(format!("shard-{k}")))
            .map(|(_, steps)| {
                steps
                    .iter()
                    .filter(|s| s.quality.is_some() && s.missing.is_empty())
                    .map(|s| s.step)
                    .collect::<Vec<_>>()
            })
            .unwrap_or_default()
    };
    assert!(
        wait_until(60.0, || scored(0) == [0, 2] && scored(1) == [1, 3]),
        "{:?} {:?}",
        scored(0),
        scored(1)
    );
    // The tuner heard both shards: a part and a composed report per step.
    let reports = || crate::tuned::tuner_status(&t.addr).quality_reports;
    assert!(wait_until(30.0, || reports() >= 8), "{}", reports());
    // The recording read as one: every step, files named under their shard.
    let (entries, steps) = index::read(&rec).unwrap();
    assert_eq!(
        steps.iter().map(|s| s.step).collect::<Vec<_>>(),
        [0, 1, 2, 3]
    );
    assert_eq!(entries.len(), 4, "one part a step: {entries:?}");
    assert!(steps[3].vdi.as_deref().unwrap().starts_with("shard-1/"));
    let out = Command::new(bin("insitu"))
        .args([
            "view",
            "--recording",
            rec.to_str().unwrap(),
            "--time-step",
            "3",
        ])
        .args(["--out", tmp.path().join("s3.png").to_str().unwrap()])
        .args(["--size", "48"])
        .output()
        .unwrap();
    succeeded("insitu view", out);
    assert!(tmp.path().join("s3.png").exists());
    let out = Command::new(bin("insitu"))
        .args(["export", "--recording", rec.to_str().unwrap()])
        .output()
        .unwrap();
    let export: serde_json::Value = serde_json::from_str(&succeeded("insitu export", out)).unwrap();
    assert_eq!(export["steps"].as_array().unwrap().len(), 4);
    g.terminate();
    t.terminate();
    v0.terminate();
    v1.terminate();
    // A read-only viewer over the recording serves every shard's steps.
    let (v, url) = viz_with_http(&rec, tmp.path(), &["--read-only"]);
    let addr = url.trim_start_matches("http://").trim_end_matches('/');
    let (code, body) = http(addr, "/api/steps", &[]);
    assert_eq!(code, 200, "{body}");
    for step in 0..4 {
        assert!(body.contains(&format!("\"step\":{step}")), "{body}");
    }
    // Each step names the precision its file was written at (the node's 8 bits, or the 6
    // bits a tuning chose).
    let steps: serde_json::Value = serde_json::from_str(&body).unwrap();
    let steps = steps["steps"].as_array().unwrap();
    assert_eq!(steps.len(), 4, "{body}");
    for s in steps {
        assert!(matches!(s["precision"].as_str(), Some("8" | "6")), "{s}");
    }
    let (code, _) = http(addr, "/api/render?step=3&size=32&format=png", &[]);
    assert_eq!(code, 200);
    v.terminate();
}
