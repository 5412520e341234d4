//! Steering (docs/steering.md) with every daemon a real process on 127.0.0.1: a viz-node
//! with a steering token in front of a tuner-node and a generator-node; the transfer function,
//! the field and the generation camera changed through the viewer's JSON API and the CLI,
//! applied from the step the tuner names, recorded with each step, kept by a generator-node
//! restarted after the change; bad requests refused with nothing changed.

use crate::common::{field, flush, free_port, index, load_vdi, status};
use crate::tuned::{tuned_generator, tuner, tuner_status};
use crate::viewer::{http, post};
use insitu_client::{Field, SimClient, Step};
use insitu_core::vdi::render::render;
use insitu_core::{Camera, Image};

use insitu_e2e::{bin, rt, wait_until, Daemon};
use serde_json::Value;
use std::path::Path;
use std::process::Command;

const STEER_TOKEN: &str = "steer-s3cret";
/// A transfer function unlike the world's default: warm and denser near the top.
const RED: &str = r#"{"domain":[0,1],"points":[[0,0,0,0,0],[0.4,1,0.2,0,0.05],[1,1,0.9,0.2,0.9]]}"#;

/// Pushes steps `range` carrying two named fields, `u` (the moving blob) and `v` (its
/// complement), to the generator at `addr`.
fn push_two_fields(addr: &str, range: std::ops::Range<u64>) {
    rt().block_on(async {
        let mut c = SimClient::connect(addr, None).await.unwrap();
        for s in range {
            let u = field(16, s);
            let v: Vec<f32> = u.iter().map(|x| 1.0 - x).collect();
            let step = Step::whole_f32(s, s as f64, [16; 3], &[])
                .with_fields(vec![Field::vertex_f32("u", &u), Field::vertex_f32("v", &v)]);
            c.push_step(step).await.unwrap();
        }
    });
}

fn steer(addr: &str, body: &str) -> (u16, Value) {
    let auth = format!("Authorization: Bearer {STEER_TOKEN}");
    let (code, text) = post(addr, "/api/steer", &[&auth], body);
    (
        code,
        serde_json::from_str(&text).unwrap_or(Value::String(text)),
    )
}

/// Steers with `body`, waits until the generator-node at `gen` applies the decision that
/// carries it, and returns the reply.
fn steered(http_addr: &str, gen: &str, body: &str) -> Value {
    let (code, reply) = steer(http_addr, body);
    assert_eq!(code, 200, "{reply}");
    let version = reply["pm_version"].as_u64().unwrap();
    assert!(
        wait_until(30.0, || status(gen).pm_version >= version),
        "the generator-node did not apply decision {version}: {:?}",
        status(gen)
    );
    reply
}

fn render_at(rec: &Path, step: u64, camera: &Camera) -> Image {
    let e = index(rec).into_iter().find(|e| e.step == step).unwrap();
    render(&load_vdi(rec, &e), camera, 64, 64, 0.99)
}

/// Mean absolute difference per channel.
fn difference(a: &Image, b: &Image) -> f64 {
    let (a, b) = (a.pixels(), b.pixels());
    a.iter()
        .flatten()
        .zip(b.iter().flatten())
        .map(|(x, y)| f64::from((x - y).abs()))
        .sum::<f64>()
        / (3 * a.len()) as f64
}

#[test]
fn the_scene_is_steered_from_the_viewer_applied_from_one_step_recorded_and_kept_across_a_restart() {
    let tmp = tempfile::tempdir().unwrap();
    let (logs, rec) = (tmp.path(), tmp.path().join("rec"));
    let viz_addr = format!("127.0.0.1:{}", free_port());
    let tuner_addr = format!("127.0.0.1:{}", free_port());
    let mut v = Daemon::start(
        "viz-node",
        &[
            "--listen",
            &viz_addr,
            "--recording-dir",
            rec.to_str().unwrap(),
            "--http",
            "127.0.0.1:0",
            "--tuner",
            &tuner_addr,
        ],
        &[("INSITU_STEER_TOKEN", STEER_TOKEN)],
        logs,
    );
    let web = v.read_line();
    let http_addr = web
        .trim()
        .rsplit("//")
        .next()
        .unwrap()
        .trim_end_matches('/')
        .to_owned();
    let t = tuner(
        &tmp.path().join("state"),
        &tuner_addr,
        &viz_addr,
        "size:10MB",
        logs,
    );
    let g = tuned_generator(&viz_addr, &tuner_addr, logs);
    push_two_fields(&g.addr, 0..4);
    flush(&g.addr);
    assert!(wait_until(20.0, || tuner_status(&tuner_addr).summaries >= 4));

    // What the page reads: steering on, nothing steered yet, the step's fields.
    let (code, scene) = http(&http_addr, "/api/scene", &[]);
    let scene: Value = serde_json::from_str(&scene).unwrap();
    assert_eq!(code, 200, "{scene}");
    assert_eq!(scene["steering"], true, "{scene}");
    assert_eq!(scene["scene"]["version"], 0, "{scene}");
    assert_eq!(scene["fields"], serde_json::json!(["u", "v"]), "{scene}");

    // Bad requests change nothing, and say what is wrong.
    for (body, code, says) in [
        ("{not json", 400, "malformed steering request"),
        (r#"{"colour": "red"}"#, 400, "unknown field"),
        (
            r#"{"tf": {"domain": [1, 0], "points": []}}"#,
            400,
            "tf_json",
        ),
        (
            r#"{"field": "w"}"#,
            400,
            "\"w\" is not one of the steps' fields (u, v)",
        ),
        (
            r#"{"camera": {"eye": [8, 8, 8], "target": [0, 0, 0]}}"#,
            400,
            "inside the domain's box",
        ),
        (
            r#"{"camera": {"eye": [1, 1, 1], "target": [1, 1, 1]}}"#,
            400,
            "degenerate",
        ),
        (r#"{"camera": {"step": 99, "angle": 10}}"#, 400, "step 99"),
        (r#"{"utility": "size:lots"}"#, 400, "utility"),
        ("{}", 400, "nothing to change"),
    ] {
        let (got, reply) = steer(&http_addr, body);
        assert_eq!(got, code, "{body}: {reply}");
        let text = reply["error"].as_str().unwrap_or_default();
        assert!(text.contains(says), "{body}: {reply}");
    }
    let (code, _) = post(&http_addr, "/api/steer", &[], r#"{"field": "v"}"#);
    assert_eq!(code, 403, "no steering token");
    assert_eq!(tuner_status(&tuner_addr).scene.unwrap().version, 0);

    // A transfer function through the API: one scene version, from one step on.
    let body = format!(r#"{{"tf": {RED}, "tf_name": "red"}}"#);
    let reply = steered(&http_addr, &g.addr, &body);
    assert_eq!(reply["scene_version"], 1, "{reply}");
    let from = reply["from_step"].as_u64().unwrap();
    assert!(from >= 4, "{reply}");
    push_two_fields(&g.addr, 4..from + 9);
    flush(&g.addr);
    let rows = index(&rec);
    for e in &rows {
        let steered = e.step >= from;
        assert_eq!(e.scene_version, u64::from(steered), "step {}", e.step);
        assert_eq!(
            e.tf_name == "red",
            steered,
            "step {}: {}",
            e.step,
            e.tf_name
        );
    }
    // The same data before and after the switch (the blob repeats every 8 steps): the
    // pictures differ by the transfer function alone.
    let camera = load_vdi(&rec, &rows[0]).meta().camera;
    let (old, new) = (from - 1, from + 7);
    let changed = difference(
        &render_at(&rec, old, &camera),
        &render_at(&rec, new, &camera),
    );
    assert!(changed > 0.01, "the steered TF shows: {changed}");
    let (code, scene) = http(&http_addr, "/api/scene", &[]);
    let scene: Value = serde_json::from_str(&scene).unwrap();
    assert_eq!(code, 200);
    assert_eq!(scene["scene"]["tf_name"], "red", "{scene}");
    assert_eq!(scene["history"][0]["state"], "applied", "{scene}");

    // The field, then "generate from here" from the newest step at 90°, through the CLI.
    let cli = |args: &[&str]| {
        let out = Command::new(bin("insitu"))
            .arg("steer")
            .args(["--viz", &http_addr])
            .args(args)
            .env("INSITU_STEER_TOKEN", STEER_TOKEN)
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        serde_json::from_slice::<Value>(&out.stdout).unwrap()
    };
    let reply = cli(&["--field", "v"]);
    assert_eq!(reply["scene_version"], 2, "{reply}");
    let version = reply["pm_version"].as_u64().unwrap();
    assert!(wait_until(30.0, || status(&g.addr).pm_version >= version));
    let newest = from + 8;
    let before = load_vdi(
        &rec,
        &index(&rec).into_iter().find(|e| e.step == newest).unwrap(),
    )
    .meta()
    .camera;
    let reply = cli(&["--camera", "view:90,0"]);
    assert_eq!(reply["scene_version"], 3, "{reply}");
    let version = reply["pm_version"].as_u64().unwrap();
    let from3 = reply["from_step"].as_u64().unwrap();
    assert!(wait_until(30.0, || status(&g.addr).pm_version >= version));
    push_two_fields(&g.addr, newest + 1..from3 + 2);
    flush(&g.addr);
    let last = index(&rec).into_iter().max_by_key(|e| e.step).unwrap();
    assert_eq!(last.scene_version, 3);
    let moved = load_vdi(&rec, &last).meta().camera;
    let expected = before.orbit(90.0, 0.0, 1.0);
    assert!(
        (moved.eye - expected.eye).length() < 1e-3 * expected.eye.length().max(1.0),
        "generated from the view: {moved:?} against {expected:?}"
    );
    assert_eq!(last.tf_name, "red", "the earlier parts stay");

    // A generator-node restarted after the changes comes back with the steered scene.
    g.kill();
    let g = tuned_generator(&viz_addr, &tuner_addr, logs);
    let current = tuner_status(&tuner_addr).pm_version;
    assert!(wait_until(30.0, || status(&g.addr).pm_version >= current));
    let next = last.step + 1;
    push_two_fields(&g.addr, next..next + 2);
    flush(&g.addr);
    for e in index(&rec).into_iter().filter(|e| e.step >= next) {
        assert_eq!(
            (e.scene_version, e.tf_name.as_str()),
            (3, "red"),
            "step {}",
            e.step
        );
        let cam = load_vdi(&rec, &e).meta().camera;
        assert!((cam.eye - expected.eye).length() < 1e-3 * expected.eye.length().max(1.0));
    }
    // The field's version came second and no step was made with it before the camera's
    // (cumulative: field and camera together) took over: it never applied as such.
    let s = tuner_status(&tuner_addr);
    let standings: Vec<&str> = s.steering.iter().map(|r| r.state.as_str()).collect();
    assert_eq!(standings, ["applied", "superseded", "applied"]);
    assert_eq!(s.scene.unwrap().field.as_deref(), Some("v"));
    g.terminate();
    t.terminate();
    v.terminate();
}
