//! Steering (docs/steering.md) with every daemon a real process on 127.0.0.1: a viz-node
//! with a steering token in front of a tuner-node and one or two generator-nodes; the
//! transfer function, the field, the generation camera, the sample distance and shading
//! changed through the viewer's JSON API, the CLI and the page, applied from the step the
//! tuner names on every rank, recorded with each step, kept by a generator-node restarted
//! after the change; bad requests refused with nothing changed.

use crate::common::{field, flush, free_port, index, load_vdi, status, steps};
use crate::ranks::blob_step;
use crate::tuned::{tuned_generator, tuner, tuner_status};
use crate::viewer::{http, post};
use insitu_client::{Field, SimClient, Step};
use insitu_core::metrics::psnr;
use insitu_core::vdi::render::render;
use insitu_core::{Camera, Image, RaycastParams, Raycaster, TransferFunction, Volume};

use insitu_e2e::{bin, rt, succeeded, wait_until, Daemon};
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

/// [`render_at`] of a composed step (every rank).
fn render_composed(rec: &Path, step: u64, camera: &Camera) -> Image {
    let s = steps(rec).into_iter().find(|s| s.step == step).unwrap();
    let bytes = std::fs::read(rec.join(s.vdi.unwrap())).unwrap();
    let vdi = insitu_core::vdi::codec::decode(&bytes, &Default::default()).unwrap();
    render(&vdi, camera, 64, 64, 0.99)
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

/// A viz-node with a steering token and its viewer, a tuner-node and a generator-node.
struct Run {
    g: Daemon,
    t: Daemon,
    v: Daemon,
    /// The viewer's `host:port`.
    http: String,
    tuner: String,
    viz: String,
    rec: std::path::PathBuf,
    /// Last: removed after the daemons are gone.
    tmp: tempfile::TempDir,
}

impl Run {
    fn start() -> Self {
        let tmp = tempfile::tempdir().unwrap();
        let (logs, rec) = (tmp.path(), tmp.path().join("rec"));
        let viz = format!("127.0.0.1:{}", free_port());
        let tuner_addr = format!("127.0.0.1:{}", free_port());
        let mut v = Daemon::start(
            "viz-node",
            &[
                "--listen",
                &viz,
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
        let http = web
            .trim()
            .rsplit("//")
            .next()
            .unwrap()
            .trim_end_matches('/')
            .to_owned();
        let t = tuner(&logs.join("state"), &tuner_addr, &viz, "size:10MB", logs);
        let g = tuned_generator(&viz, &tuner_addr, logs);
        Self {
            g,
            t,
            v,
            http,
            tuner: tuner_addr,
            viz,
            rec,
            tmp,
        }
    }

    fn stop(self) {
        self.g.terminate();
        self.t.terminate();
        self.v.terminate();
    }
}

#[test]
fn the_scene_is_steered_from_the_viewer_applied_from_one_step_recorded_and_kept_across_a_restart() {
    let Run {
        g,
        t,
        v,
        http: http_addr,
        tuner: tuner_addr,
        viz: viz_addr,
        rec,
        tmp,
    } = Run::start();
    let logs = tmp.path();
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
    // The newest step's histogram for the editor: 64 bins holding every voxel of the 16³ step.
    let counts = scene["histogram"]["counts"].as_array().unwrap();
    assert_eq!(counts.len(), 64, "{scene}");
    let voxels: u64 = counts.iter().map(|c| c.as_u64().unwrap()).sum();
    assert_eq!(voxels, 16 * 16 * 16);
    assert_eq!(scene["histogram"]["step"], 3, "{scene}");

    // Bad requests change nothing, and say what is wrong.
    for (body, code, says) in [
        ("{not json", 400, "malformed steering request"),
        (r#"{"colour": "red"}"#, 400, "unknown field"),
        (
            r#"{"tf": {"domain": [1, 0], "points": []}}"#,
            400,
            "tf: transfer function in the request: domain [1, 0]",
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
        // The sample distance has its own name; `step` is a time step.
        (r#"{"step": 0.25}"#, 400, "\"sample_distance\""),
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
    // Bad previews, likewise.
    let auth = format!("Authorization: Bearer {STEER_TOKEN}");
    for (body, code, says) in [
        ("{}", 400, "malformed preview request"),
        (
            &format!(r#"{{"tf": {RED}, "size": 4}}"#) as &str,
            400,
            "size 4 is not in 16..=512",
        ),
        (
            r#"{"tf": {"domain": [1, 0], "points": []}}"#,
            400,
            "tf: transfer function in the request: domain [1, 0]",
        ),
        (
            &format!(r#"{{"tf": {RED}, "step": 9999}}"#),
            409,
            "step 9999: 0 of 1 ranks are held",
        ),
        (
            &format!(r#"{{"tf": {RED}, "camera": {{"eye": [1, 1, 1], "target": [1, 1, 1]}}}}"#),
            400,
            "degenerate",
        ),
    ] {
        let (got, text) = post(&http_addr, "/api/preview", &[&auth], body);
        assert_eq!(got, code, "{body}: {text}");
        assert!(text.contains(says), "{body}: {text}");
    }
    let body = format!(r#"{{"tf": {RED}}}"#);
    let (code, _) = post(&http_addr, "/api/preview", &[], &body);
    assert_eq!(code, 403, "a preview without the steering token");
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
        serde_json::from_str::<Value>(&succeeded("insitu steer", out)).unwrap()
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

/// `POST /api/preview` with the steering token: the step rendered, the ranks composed and
/// the picture.
fn preview(addr: &str, body: &str) -> (u64, u32, Image) {
    use std::io::{Read, Write};
    let mut s = std::net::TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(std::time::Duration::from_secs(60)))
        .unwrap();
    write!(
        s,
        "POST /api/preview HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\nAuthorization: Bearer {STEER_TOKEN}\r\nContent-Type: application/json\r\nContent-Length: {}\r\n\r\n{body}",
        body.len()
    )
    .unwrap();
    let mut out = Vec::new();
    s.read_to_end(&mut out).unwrap();
    let split = out.windows(4).position(|w| w == b"\r\n\r\n").unwrap();
    let (head, png) = (String::from_utf8_lossy(&out[..split]), &out[split + 4..]);
    assert!(
        head.starts_with("HTTP/1.1 200"),
        "{head}\n{}",
        String::from_utf8_lossy(png)
    );
    let header = |name: &str| -> String {
        head.lines()
            .find_map(|l| {
                let (k, v) = l.split_once(':')?;
                k.eq_ignore_ascii_case(name).then(|| v.trim().to_owned())
            })
            .unwrap_or_else(|| panic!("no {name} in {head}"))
    };
    let rgb = image::load_from_memory(png).unwrap().to_rgb8();
    let (w, h) = rgb.dimensions();
    let px = rgb
        .pixels()
        .map(|p| p.0.map(|v| f32::from(v) / 255.0))
        .collect();
    (
        header("x-insitu-step").parse().unwrap(),
        header("x-insitu-ranks").parse().unwrap(),
        Image::from_pixels(w, h, px).unwrap(),
    )
}

/// The reference DVR of `volume` with the transfer function `tf_json` at `camera`
/// (`size`²), sampled as the VDI `like` was made.
fn dvr_like(
    volume: &Volume,
    tf_json: &str,
    like: &insitu_core::vdi::VdiMeta,
    camera: &Camera,
    size: u32,
) -> Image {
    let tf = TransferFunction::from_json(tf_json, "reference").unwrap();
    let params = RaycastParams {
        sample_distance: like.sample_distance,
        termination: like.termination,
        ..RaycastParams::default()
    };
    insitu_core::dvr::render(
        &Raycaster::new(volume, &tf, params).unwrap(),
        camera,
        size,
        size,
    )
}

/// Pushes steps `range` of the 33³ blobs from 4 ranks (2 × 2 × 1 bricks), ranks 0–1 to the
/// generator-node at `hosts[0]` and 2–3 to `hosts[1]`, each rank from its own client, and
/// flushes them.
fn push_four_ranks(hosts: [&str; 2], range: std::ops::Range<u64>) {
    let bricks = insitu_core::volume::bricks::grid_bricks([33; 3], [2, 2, 1]).unwrap();
    rt().block_on(async {
        let mut tasks = Vec::new();
        for (rank, b) in bricks.into_iter().enumerate() {
            let (addr, range) = (hosts[rank / 2].to_owned(), range.clone());
            tasks.push(tokio::spawn(async move {
                let mut c = SimClient::connect(&addr, None).await.unwrap();
                for step in range {
                    c.push_step(blob_step(step, rank as u32, 4, b))
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
}

/// Waits until steps `0..end` are stored whole (every rank composed) and returns them.
fn whole_steps(rec: &Path, end: u64) -> Vec<insitu_recording::rows::StepEntry> {
    let whole = |s: &insitu_recording::rows::StepEntry| {
        s.missing.is_empty() && s.error.is_none() && s.vdi.is_some()
    };
    let done = wait_until(60.0, || {
        let s = steps(rec);
        (0..end).all(|k| s.iter().any(|e| e.step == k && whole(e)))
    });
    assert!(done, "steps 0..{end} not all whole: {:?}", steps(rec));
    steps(rec)
}

/// 4 ranks on two generator-nodes (ranks 0–1 on one, 2–3 on the other): every rank switches
/// to a steered transfer function at the step the tuner names, so every step composes, and a
/// node killed after a second change (sample distance and shading) and restarted makes each
/// of its ranks' steps with the scene in force for that step, those received before the
/// switch included.
#[test]
fn four_ranks_on_two_nodes_switch_at_one_step_and_a_restarted_node_keeps_each_step_s_scene() {
    let run = Run::start();
    let (logs, rec) = (run.tmp.path(), &run.rec);
    let h2 = tuned_generator(&run.viz, &run.tuner, logs);
    push_four_ranks([&run.g.addr, &h2.addr], 0..3);
    whole_steps(rec, 3);
    assert!(wait_until(20.0, || tuner_status(&run.tuner).summaries >= 12));

    // A preview of the red transfer function before it is applied: the bricks of both nodes
    // composed are the whole field's DVR with it, unlike what is stored.
    let body = r#"{"eye": [16, 12, 95], "target": [16, 16, 16]}"#;
    let (step, ranks, shown) = preview(
        &run.http,
        &format!(r#"{{"tf": {RED}, "camera": {body}, "size": 64}}"#),
    );
    assert_eq!(ranks, 4);
    let whole = blob_step(
        step,
        0,
        1,
        insitu_core::volume::bricks::Brick {
            offset: [0; 3],
            dims: [33; 3],
        },
    );
    let data: Vec<f32> = whole
        .data
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect();
    let volume = Volume::new([33; 3], glam::Vec3::ONE, data).unwrap();
    let camera = Camera {
        eye: glam::Vec3::new(16.0, 12.0, 95.0),
        target: glam::Vec3::splat(16.0),
        up: glam::Vec3::Y,
        fov_y_deg: 30.0,
    };
    let stored = index(rec).into_iter().find(|e| e.step == step).unwrap();
    let meta = load_vdi(rec, &stored).meta().clone();
    let q = psnr(&shown, &dvr_like(&volume, RED, &meta, &camera, 64)).unwrap();
    let unlike = difference(&shown, &render_composed(rec, step, &camera));
    eprintln!("preview of step {step}: {q:.1} dB from the whole field's DVR with it; mean difference {unlike:.3} from the stored VDI");
    assert!(
        q >= 40.0,
        "the preview is {q:.1} dB from the whole field's DVR"
    );
    assert!(
        unlike > 0.01,
        "the preview shows the stored TF: {unlike:.3}"
    );
    assert_eq!(
        tuner_status(&run.tuner).scene.unwrap().version,
        0,
        "nothing steered"
    );

    let body = format!(r#"{{"tf": {RED}, "tf_name": "red"}}"#);
    let reply = steered(&run.http, &run.g.addr, &body);
    let version = reply["pm_version"].as_u64().unwrap();
    assert!(wait_until(30.0, || status(&h2.addr).pm_version >= version));
    let from = reply["from_step"].as_u64().unwrap();
    push_four_ranks([&run.g.addr, &h2.addr], 3..from + 3);
    for s in whole_steps(rec, from + 3) {
        let steered = s.step >= from;
        assert_eq!(s.scene_version, u64::from(steered), "step {}", s.step);
        assert_eq!(s.ranks, [0, 1, 2, 3], "step {}", s.step);
    }
    for e in index(rec) {
        assert_eq!(e.tf_name == "red", e.step >= from, "step {}", e.step);
    }

    // Sample distance and shading; the second node killed before any step is made with them.
    let reply = steered(
        &run.http,
        &run.g.addr,
        r#"{"sample_distance": 0.25, "shading": true}"#,
    );
    assert_eq!(reply["scene_version"], 2, "{reply}");
    let from2 = reply["from_step"].as_u64().unwrap();
    assert!(from2 > from + 3, "{reply}");
    h2.kill();
    let h2 = tuned_generator(&run.viz, &run.tuner, logs);
    let current = tuner_status(&run.tuner).pm_version;
    assert!(wait_until(30.0, || status(&h2.addr).pm_version >= current));
    push_four_ranks([&run.g.addr, &h2.addr], from + 3..from2 + 2);
    for s in whole_steps(rec, from2 + 2)
        .into_iter()
        .filter(|s| s.step >= from)
    {
        let version = if s.step >= from2 { 2 } else { 1 };
        assert_eq!(s.scene_version, version, "step {}", s.step);
    }
    for e in index(rec).into_iter().filter(|e| e.step >= from) {
        let meta = load_vdi(rec, &e).meta().clone();
        let steered = e.step >= from2;
        assert_eq!(
            (
                meta.shaded,
                meta.sample_distance == 0.25,
                meta.tf_name.as_str()
            ),
            (steered, steered, "red"),
            "step {} ranks {:?}",
            e.step,
            e.ranks()
        );
    }
    h2.terminate();
    run.stop();
}

/// The viewer's page of `run` in a browser with its own profile `profile`, once it shows a
/// still frame.
async fn open_page(
    driver: &insitu_e2e::browser::Driver,
    run: &Run,
    profile: &str,
) -> fantoccini::Client {
    let c = insitu_e2e::browser::browser(driver, &run.tmp.path().join(profile)).await;
    c.goto(&format!("http://{}/", run.http)).await.unwrap();
    crate::viewer::wait_frame(&c, 30.0, |d| d["kind"] == "still").await;
    c
}

/// Types the steering token into the page's panel (real key events).
async fn type_token(c: &fantoccini::Client) {
    c.find(fantoccini::Locator::Id("steer-token"))
        .await
        .unwrap()
        .send_keys(STEER_TOKEN)
        .await
        .unwrap();
}

/// Clicks the panel's button `id` and returns the tuner's answer the page shows once it names
/// scene `version`.
async fn apply(c: &fantoccini::Client, id: &str, version: u64) -> Value {
    crate::viewer::click(c, id).await;
    let reply = insitu_e2e::browser::js(
        c,
        &format!("for (let i = 0; i < 200; i++) {{ const r = JSON.parse(document.getElementById('steer').dataset.reply || '{{}}'); if (r.scene_version === {version}) {{ done(r); return; }} await new Promise(r => setTimeout(r, 50)); }} done(document.getElementById('steer-status').textContent);"),
    )
    .await;
    assert_eq!(reply["scene_version"], version, "{reply}");
    reply
}

/// The page's steering panel in Debian's Chromium, with real mouse and keyboard events: the
/// steering token typed in, the middle opacity point of the transfer-function editor dragged
/// up, previewed (nothing steered), applied; the steps from the switch step on are made with
/// the new transfer function (the page renders such a step as the VDI renders here, within
/// 40 dB), the earlier ones keep the old; then "generate from here" after orbiting the view
/// moves the generation camera, and q at that view rises.
#[test]
fn the_page_steers_the_transfer_function_by_dragging_and_generates_from_its_view() {
    use crate::viewer::{drag, image_of, screenshot, wait_frame};
    use fantoccini::Locator;
    use insitu_core::metrics::{mse, psnr_from_mse};
    use insitu_e2e::browser::{artefacts, js, start_driver};

    let Some(driver) = start_driver() else {
        return;
    };
    let run = Run::start();
    let (g, rec) = (&run.g, &run.rec);
    push_two_fields(&g.addr, 0..4);
    flush(&g.addr);
    assert!(wait_until(20.0, || tuner_status(&run.tuner).summaries >= 4));
    let shots = artefacts();
    let reply = rt().block_on(async {
        let c = open_page(&driver, &run, "profile").await;
        let shown = js(
            &c,
            "for (let i = 0; i < 200; i++) { if (!document.getElementById('steer').hidden && document.getElementById('tf-map').options.length) { done(true); return; } await new Promise(r => setTimeout(r, 50)); } done(false);",
        )
        .await;
        assert_eq!(shown, true, "the steering panel did not show");
        let bins = js(
            &c,
            "for (let i = 0; i < 200; i++) { const b = document.getElementById('tf-editor').dataset.histogram; if (b && b !== '0') { done(b); return; } await new Promise(r => setTimeout(r, 50)); } done('0');",
        )
        .await;
        assert_eq!(bins, "64", "the editor draws the newest step's histogram");
        // The token, typed.
        type_token(&c).await;
        // The middle point (x 0.5, opacity 0.05) dragged up to about 0.9. The canvas is
        // 360 × 130 CSS pixels; WebDriver's offsets are from its centre.
        let editor = c.find(Locator::Id("tf-editor")).await.unwrap();
        let before: Value =
            serde_json::from_str(&editor.attr("data-points").await.unwrap().unwrap()).unwrap();
        let y0 = (130.0 - 14.0 - 6.0) * (1.0 - 0.05) + 3.0 - 65.0;
        drag(&c, "tf-editor", (0.0, y0), (0.0, -95.0)).await;
        let after: Value =
            serde_json::from_str(&editor.attr("data-points").await.unwrap().unwrap()).unwrap();
        assert!(
            after[1][1].as_f64().unwrap() > 0.8 && before[1][1].as_f64().unwrap() < 0.1,
            "the drag did not raise the middle point: {before} → {after}"
        );
        // The preview: the nodes' DVR of the newest held step with the dragged curve, nothing
        // applied.
        crate::viewer::click(&c, "tf-preview").await;
        let previewed = js(
            &c,
            "for (let i = 0; i < 400; i++) { const f = document.getElementById('tf-preview-figure'); const img = document.getElementById('tf-preview-image'); if (!f.hidden && img.complete && img.naturalWidth) { done({step: f.dataset.step, width: img.naturalWidth}); return; } await new Promise(r => setTimeout(r, 50)); } done(document.getElementById('steer-status').textContent);",
        )
        .await;
        assert_eq!(previewed["width"], 256, "no preview: {previewed}");
        // Nothing steered by it: applying makes scene 1.
        js(
            &c,
            "document.getElementById('tf-preview-figure').scrollIntoView({block: 'end'}); done(true);",
        )
        .await;
        screenshot(&c, &shots, "steering.png").await;
        let reply = apply(&c, "tf-apply", 1).await;
        c.close().await.unwrap();
        reply
    });
    let from = reply["from_step"].as_u64().unwrap();
    let version = reply["pm_version"].as_u64().unwrap();
    assert!(wait_until(30.0, || status(&g.addr).pm_version >= version));
    push_two_fields(&g.addr, 4..from + 9);
    flush(&g.addr);
    let rows = index(rec);
    for e in &rows {
        let steered = e.step >= from;
        assert_eq!(e.scene_version, u64::from(steered), "step {}", e.step);
        assert_eq!(
            e.tf_name.ends_with("(steered)"),
            steered,
            "step {}: {}",
            e.step,
            e.tf_name
        );
    }
    let camera = load_vdi(rec, &rows[0]).meta().camera;
    let changed = difference(
        &render_at(rec, from - 1, &camera),
        &render_at(rec, from + 7, &camera),
    );
    assert!(changed > 0.01, "the dragged opacity shows: {changed}");
    // The page shows a steered step as the VDI renders it here.
    let shown_step = from + 7;
    let generated = rt().block_on(async {
        let c = open_page(&driver, &run, "profile2").await;
        let page = image_of(
            &c,
            &format!("/api/render?step={shown_step}&size=128&format=png"),
        )
        .await;
        let e = index(rec)
            .into_iter()
            .find(|e| e.step == shown_step)
            .unwrap();
        let vdi = load_vdi(rec, &e);
        let here = render(&vdi, &vdi.meta().camera, 128, 128, 0.99);
        let q = psnr_from_mse(mse(&page, &here).unwrap());
        assert!(
            q >= 40.0,
            "the page's frame of step {shown_step} is {q:.1} dB from the VDI's"
        );
        // "Generate from here": orbit the view by dragging, then ask.
        type_token(&c).await;
        drag(&c, "frame", (0.0, 0.0), (-120.0, 0.0)).await;
        let shown = wait_frame(&c, 20.0, |d| d["kind"] == "still" && d["angle"] != "0").await;
        let angle: f32 = shown["angle"].as_str().unwrap().parse().unwrap();
        // The page shows the volume zoomed to fit: the view generated from is that zoom's.
        let zoom: f32 = shown["zoom"].as_str().unwrap().parse().unwrap();
        let reply = apply(&c, "generate-here", 2).await;
        c.close().await.unwrap();
        (angle, zoom, reply)
    });
    let (angle, zoom, reply) = generated;
    let version = reply["pm_version"].as_u64().unwrap();
    let from2 = reply["from_step"].as_u64().unwrap();
    assert!(wait_until(30.0, || status(&g.addr).pm_version >= version));
    push_two_fields(&g.addr, from + 9..from2 + 2);
    flush(&g.addr);
    let last = index(rec).into_iter().max_by_key(|e| e.step).unwrap();
    assert_eq!(last.scene_version, 2);
    let moved = load_vdi(rec, &last).meta().camera;
    let expected = camera.orbit(angle, 0.0, zoom);
    assert!(
        (moved.eye - expected.eye).length() < 1e-2 * expected.eye.length().max(1.0),
        "generated from the page's view at {angle}° and zoom {zoom}: {moved:?} against {expected:?}"
    );
    // q at the new view rises: the same data (the blob repeats every 8 steps) generated from
    // the old view before the switch and from the new one after it, each rendered at the new
    // view and scored against the field's DVR there with the steered transfer function.
    let (_, scene) = http(&run.http, "/api/scene", &[]);
    let scene: Value = serde_json::from_str(&scene).unwrap();
    let tf_json = scene["scene"]["tf"].to_string();
    // At the resolution the VDIs were made with (there, at its own view, a VDI reproduces the
    // DVR; docs/conventions.md).
    let size = load_vdi(rec, &last).meta().params.resolution;
    let q_at = |step: u64| {
        let e = index(rec).into_iter().find(|e| e.step == step).unwrap();
        let vdi = load_vdi(rec, &e);
        let b = vdi.meta().volume_box;
        let volume = Volume::new([16; 3], (b.max - b.min) / 15.0, field(16, step))
            .unwrap()
            .with_origin(b.min)
            .unwrap();
        let reference = dvr_like(&volume, &tf_json, vdi.meta(), &moved, size);
        psnr(&render(&vdi, &moved, size, size, 0.99), &reference).unwrap()
    };
    let earlier = last.step - 8;
    assert!(
        (from..from2).contains(&earlier),
        "{earlier}: {from}..{from2}"
    );
    let (before, after) = (q_at(earlier), q_at(last.step));
    eprintln!(
        "q at the view generated from ({angle}°): step {earlier} (old camera) {before:.2} dB, step {} (new) {after:.2} dB",
        last.step
    );
    assert!(
        after > before + 1.0,
        "q at the new view did not rise: {before:.2} → {after:.2} dB"
    );
    run.stop();
}
