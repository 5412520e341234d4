//! The web viewer in a real browser: Debian's Chromium, headless,
//! driven over WebDriver by chromedriver, against a viz-node process serving a recording that
//! a replay made, while more steps arrive. Screenshots go to `target/test-artifacts/`.

use crate::common::{generator, small_config};
use crate::replay::replay;
use base64::Engine as _;
use fantoccini::actions::{InputSource, MouseActions, PointerAction, MOUSE_BUTTON_LEFT};
use fantoccini::key::Key;
use fantoccini::{Client, Locator};
use insitu_client::{SimClient, Step};
use insitu_core::metrics::{mse, psnr_from_mse};
use insitu_core::volume::RawFormat;
use insitu_core::Image;
use insitu_e2e::browser::{artefacts, browser, js, start_driver};
use insitu_e2e::{bin, ocean, rt, Daemon};
use serde_json::{json, Value};
use std::io::{BufRead, BufReader, Read, Write};
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// Polls `attr` of `#frame` until `pred` holds, within `secs`.
pub(crate) async fn wait_frame(c: &Client, secs: f64, pred: impl Fn(&Value) -> bool) -> Value {
    let t = Instant::now();
    loop {
        let v = c
            .execute(
                "return Object.assign({}, document.getElementById('frame').dataset);",
                vec![],
            )
            .await
            .unwrap();
        if pred(&v) {
            return v;
        }
        assert!(
            t.elapsed().as_secs_f64() < secs,
            "the page did not show the expected frame within {secs} s; last: {v}"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// The image bytes behind `#frame` or `#reference`, or those of `url` fetched by the page,
/// decoded.
pub(crate) async fn image_of(c: &Client, what: &str) -> Image {
    let src = if what == "frame" || what == "reference" {
        format!("document.getElementById('{what}').src")
    } else {
        format!("{what:?}")
    };
    let v = js(
        c,
        &format!(
            "const r = await fetch({src}); if (!r.ok) {{ done({{error: await r.text()}}); return; }}
             const b = new Uint8Array(await r.arrayBuffer()); let s = '';
             for (let i = 0; i < b.length; i++) s += String.fromCharCode(b[i]);
             done({{b64: btoa(s)}});"
        ),
    )
    .await;
    let b64 = v["b64"]
        .as_str()
        .unwrap_or_else(|| panic!("fetching {what}: {v}"));
    let bytes = base64::engine::general_purpose::STANDARD
        .decode(b64)
        .unwrap();
    let rgb = image::load_from_memory(&bytes).unwrap().to_rgb8();
    let (w, h) = rgb.dimensions();
    let px = rgb
        .pixels()
        .map(|p| p.0.map(|v| f32::from(v) / 255.0))
        .collect();
    Image::from_pixels(w, h, px).unwrap()
}

fn not_blank(img: &Image) -> bool {
    let lit = img
        .pixels()
        .iter()
        .filter(|p| p.iter().any(|&v| v > 0.02))
        .count();
    lit > img.pixels().len() / 100
}

/// Pushes ocean step `t` as step index `step` straight to the generator-node.
async fn push_ocean(generator: &str, step: u64, t: usize) {
    let path = ocean().unwrap();
    let format = RawFormat::from_file_name(&path).unwrap();
    let vol = format.load(&path, t, glam::Vec3::ONE).unwrap();
    let d = vol.dims().map(|x| x as u32);
    let mut c = SimClient::connect(generator, None).await.unwrap();
    c.push_step(Step::whole_f32(step, step as f64, d, &vol.data()))
        .await
        .unwrap();
}

pub(crate) fn viz_with_http(rec: &Path, logs: &Path, extra: &[&str]) -> (Daemon, String) {
    let mut args = vec!["--http", "127.0.0.1:0", "--backend", "cpu"];
    args.extend_from_slice(extra);
    let mut v = insitu_e2e::start_viz(rec, "127.0.0.1:0", &args, logs);
    let line = v.read_line();
    let url = line
        .strip_prefix("web viewer on ")
        .unwrap_or_else(|| panic!("no viewer URL: {line:?}"))
        .to_owned();
    (v, url)
}

/// A viz-node with its viewer over an empty recording in `dir`; returns its HTTP address.
fn viewer_on(dir: &Path, extra: &[&str]) -> (Daemon, String) {
    let (v, url) = viz_with_http(&dir.join("rec"), dir, extra);
    let addr = url
        .trim_start_matches("http://")
        .trim_end_matches('/')
        .to_owned();
    (v, addr)
}

/// A viz-node serving the viewer on a recording replayed from the ocean series through a
/// generator-node (still attached, for later pushes), and chromedriver.
struct Recorded {
    url: String,
    driver: insitu_e2e::browser::Driver,
    generator: Daemon,
    _viz: Daemon,
    /// Last, so it is removed after the daemons are gone (fields drop in order).
    tmp: tempfile::TempDir,
}

impl Recorded {
    /// `None` without the ocean series (the test skips).
    fn replay(ranks: u32, steps: usize, sample_every: u32) -> Option<Self> {
        ocean()?;
        let driver = start_driver()?;
        let tmp = tempfile::tempdir().unwrap();
        let (v, url) = viz_with_http(&tmp.path().join("rec"), tmp.path(), &[]);
        // Rank by rank (the node does not compose its ranks), so each brick can be selected.
        let cfg = small_config(&v.addr, "block", 16) + "[host]\ncompose = false\n";
        let g = generator(&cfg, tmp.path(), &[]);
        replay(&g, ranks, steps, sample_every);
        Some(Self {
            driver,
            url,
            generator: g,
            _viz: v,
            tmp,
        })
    }

    /// A fresh browser on the viewer's page.
    async fn open(&self) -> Client {
        let c = browser(&self.driver, &self.tmp.path().join("profile")).await;
        c.goto(&self.url).await.unwrap();
        c
    }
}

#[test]
fn the_page_orbits_moves_in_time_follows_new_steps_and_matches_the_api() {
    let Some(r) = Recorded::replay(1, 6, 2) else {
        return;
    };
    let (g, shots) = (&r.generator, artefacts());
    rt().block_on(async {
        let c = r.open().await;
        let first = first_frame_and_charts(&c, &shots).await;
        orbit_matches_the_api(&c, &first, &shots).await;
        time_slider_and_reference(&c, &shots).await;
        follows_new_steps(&c, &g.addr, &shots).await;
        reconnects_without_holding_up_pushes(&c, &g.addr).await;
        camera_bursts_are_superseded(&c).await;
        c.close().await.unwrap();
    });
    r.generator.terminate();
}

/// A real mouse drag on the element with id `id`: pressed at `at` (CSS pixels from its
/// centre), moved by `by` over 300 ms, released.
pub(crate) async fn drag(c: &Client, id: &str, at: (f64, f64), by: (f64, f64)) {
    let element = c.find(Locator::Id(id)).await.unwrap();
    let mouse = MouseActions::new("mouse".into())
        .then(PointerAction::MoveToElement {
            element,
            duration: None,
            x: at.0,
            y: at.1,
        })
        .then(PointerAction::Down {
            button: MOUSE_BUTTON_LEFT,
        })
        .then(PointerAction::MoveBy {
            duration: Some(Duration::from_millis(300)),
            x: by.0,
            y: by.1,
        })
        .then(PointerAction::Up {
            button: MOUSE_BUTTON_LEFT,
        });
    c.perform_actions(mouse).await.unwrap();
}

/// Clicks the element with id `id`.
pub(crate) async fn click(c: &Client, id: &str) {
    c.find(Locator::Id(id))
        .await
        .unwrap()
        .click()
        .await
        .unwrap();
}

/// The points the chart with id `id` says it draws (its `data-points`).
async fn chart_points(c: &Client, id: &str) -> Option<String> {
    c.find(Locator::Id(id))
        .await
        .unwrap()
        .attr("data-points")
        .await
        .unwrap()
}

/// The page as it looks now, kept as `name` among the test's artefacts.
pub(crate) async fn screenshot(c: &Client, shots: &Path, name: &str) {
    std::fs::write(shots.join(name), c.screenshot().await.unwrap()).unwrap();
}

/// The first still frame is the latest step's, zoomed to fit (the box drawn over it reaches
/// 90 % of the way to the frame's edge, as the server's fit and the page's projection agree),
/// with its colour legend, and not blank; the charts hold one point per stored step (q on
/// the sampled ones); returns that frame.
async fn first_frame_and_charts(c: &Client, shots: &Path) -> Image {
    let first = wait_frame(c, 20.0, |d| d["kind"] == "still" && d["zoom"] != "1").await;
    assert_eq!(first["step"], "5", "follows the latest step: {first}");
    let img0 = image_of(c, "frame").await;
    assert!(not_blank(&img0), "the first frame is blank");
    let overlay = js(
        c,
        "const o = document.getElementById('overlay').dataset;
         done({edges: o.edges, reach: o.reach});",
    )
    .await;
    assert_eq!(overlay["edges"], "12", "{overlay}");
    let reach: f64 = overlay["reach"].as_str().unwrap().parse().unwrap();
    assert!(
        (0.87..=0.93).contains(&reach),
        "box reach {reach}: {overlay}"
    );
    let t = Instant::now();
    while js(
        c,
        "const b = document.getElementById('legend-bar').dataset.hash;
         done(b !== undefined && b === document.getElementById('frame').dataset.tf
              && document.getElementById('legend-lo').textContent !== '');",
    )
    .await
        != Value::Bool(true)
    {
        assert!(
            t.elapsed().as_secs() < 20,
            "no colour legend for the frame's TF"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    screenshot(c, shots, "viewer-first.png").await;

    // The charts hold one point per stored step.
    for id in ["chart-sigma", "chart-tau"] {
        assert_eq!(chart_points(c, id).await.as_deref(), Some("6"), "{id}");
    }
    assert_eq!(
        chart_points(c, "chart-q").await.as_deref(),
        Some("3"),
        "q on the sampled steps 0, 2, 4"
    );
    img0
}

/// Dragging orbits: the frame changes, and its still matches the API's render of that
/// camera.
async fn orbit_matches_the_api(c: &Client, img0: &Image, shots: &Path) {
    drag(c, "frame", (0.0, 0.0), (-120.0, 40.0)).await;
    let after = wait_frame(c, 20.0, |d| {
        d["kind"] == "still" && d["angle"] != "0" && d["elevation"] != "0"
    })
    .await;
    let shown = image_of(c, "frame").await;
    assert!(mse(&shown, img0).unwrap() > 0.0, "the frame did not change");
    let api = image_of(
        c,
        &format!(
            "/api/render?step={}&angle={}&elevation={}&zoom={}&size={}&format=png",
            after["step"].as_str().unwrap(),
            after["angle"].as_str().unwrap(),
            after["elevation"].as_str().unwrap(),
            after["zoom"].as_str().unwrap(),
            after["width"].as_str().unwrap()
        ),
    )
    .await;
    let q = psnr_from_mse(mse(&shown, &api).unwrap());
    assert!(q >= 40.0, "page vs API still: {q} dB");
    screenshot(c, shots, "viewer-orbit.png").await;
}

/// The time slider moves through the steps by keyboard; on a sampled step, the stored
/// reference appears beside the frame, byte for byte the API's, with the VDI shown from the
/// reference's camera.
async fn time_slider_and_reference(c: &Client, shots: &Path) {
    // The time slider: two steps back with the keyboard shows step 3.
    let slider = c.find(Locator::Id("slider")).await.unwrap();
    slider
        .send_keys(&format!("{}{}", Key::Left, Key::Left))
        .await
        .unwrap();
    wait_frame(c, 20.0, |d| d["step"] == "3" && d["kind"] == "still").await;

    // VDI vs reference on a sampled step (references on 0, 2, 4): the stored reference
    // appears beside the frame, byte for byte the API's, and the VDI is shown from the
    // reference's camera.
    slider.send_keys(&Key::Right.to_string()).await.unwrap();
    wait_frame(c, 20.0, |d| d["step"] == "4" && d["kind"] == "still").await;
    click(c, "compare").await;
    let t = Instant::now();
    while js(
        c,
        "const r = document.getElementById('reference');
         done(!r.hidden && r.complete && r.naturalWidth > 0 && r.src.startsWith('blob:'));",
    )
    .await
        != json!(true)
    {
        assert!(
            t.elapsed() < Duration::from_secs(20),
            "no reference frame shown"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let shown_ref = image_of(c, "reference").await;
    let api_ref = image_of(c, "/api/reference?step=4&view=0").await;
    assert!(
        shown_ref == api_ref,
        "the page's reference is not the API's"
    );
    assert!(not_blank(&shown_ref), "the reference frame is blank");
    let ref_angle = js(
        c,
        "const r = await fetch('/api/reference?step=4&view=0'); done(r.headers.get('x-angle'));",
    )
    .await;
    let ref_angle: f64 = ref_angle.as_str().unwrap().parse().unwrap();
    wait_frame(c, 20.0, |d| {
        d["kind"] == "still"
            && d["step"] == "4"
            && d["angle"].as_str().and_then(|a| a.parse::<f64>().ok()) == Some(ref_angle)
            && d["elevation"].as_str().and_then(|a| a.parse::<f64>().ok()) == Some(0.0)
    })
    .await;
    screenshot(c, shots, "viewer-compare.png").await;
    click(c, "compare").await;
}

/// With "follow latest", a step pushed to the generator at `generator` appears without a
/// reload, and the charts grow by it.
async fn follows_new_steps(c: &Client, generator: &str, shots: &Path) {
    click(c, "follow").await;
    push_ocean(generator, 40, 7).await;
    wait_frame(c, 30.0, |d| d["step"] == "40").await;
    let t = Instant::now();
    let mut p = chart_points(c, "chart-sigma").await;
    while p.as_deref() != Some("7") && t.elapsed() < Duration::from_secs(10) {
        tokio::time::sleep(Duration::from_millis(100)).await;
        p = chart_points(c, "chart-sigma").await;
    }
    assert_eq!(p.as_deref(), Some("7"), "the chart grew by the new step");
    screenshot(c, shots, "viewer-live.png").await;
}

/// The page's connection drops while the simulation pushes a step: the push is not held
/// up, and the page reconnects and shows that step.
async fn reconnects_without_holding_up_pushes(c: &Client, generator: &str) {
    let connections = || js(c, "done(document.body.dataset.connections || '0');");
    assert_eq!(connections().await, json!("1"));
    js(c, "window.insituViewer.dropConnection(); done(true);").await;
    let pushed = Instant::now();
    push_ocean(generator, 41, 8).await;
    let push_secs = pushed.elapsed().as_secs_f64();
    let t = Instant::now();
    while connections().await != json!("2") {
        assert!(
            t.elapsed() < Duration::from_secs(20),
            "the page did not reconnect"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    wait_frame(c, 30.0, |d| d["step"] == "41" && d["kind"] == "still").await;
    eprintln!("push while the page was away: {push_secs:.3} s");
    assert!(
        push_secs < 5.0,
        "the push waited {push_secs} s for the viewer"
    );
}

/// Fifty quick camera changes on one socket render the latest and supersede the rest; bad
/// requests get clear errors; the level of detail follows `lod`.
async fn camera_bursts_are_superseded(c: &Client) {
    let burst = js(
        c,
        "const before = await (await fetch('/api/stats')).json();
         const ws = new WebSocket(location.href.replace(/^http/, 'ws').replace(/\\/?(\\?.*)?$/, '/api/live'));
         ws.binaryType = 'arraybuffer';
         const frames = [], levels = {};
         let errors = [];
         ws.onmessage = (m) => { if (typeof m.data === 'string') { const j = JSON.parse(m.data);
           if (j.frame !== undefined) { frames.push(j.frame); levels[j.frame] = j.vdi_resolution; }
           if (j.error) errors.push(j.error); } };
         await new Promise(r => ws.onopen = r);
         ws.send('{not json');
         for (let i = 1; i <= 50; i++) ws.send(JSON.stringify({id: i, step: null, rank: null,
           angle: i * 3, elevation: 10, zoom: 1, width: 256, height: 256, format: 'jpeg'}));
         const t0 = Date.now();
         while (!frames.includes(50) && Date.now() - t0 < 20000) await new Promise(r => setTimeout(r, 50));
         // Bad requests one at a time (a newer request would supersede a waiting one).
         for (const bad of [{id: 51, step: 999999, width: 8, height: 8, format: 'png'},
                            {id: 52, step: null, width: 0, height: 8, format: 'png'}]) {
           const n = errors.length;
           ws.send(JSON.stringify(bad));
           while (errors.length === n && Date.now() - t0 < 30000) await new Promise(r => setTimeout(r, 20));
         }
         ws.send(JSON.stringify({id: 53, step: null, width: 64, height: 64, format: 'png'}));
         while (!frames.includes(53) && Date.now() - t0 < 30000) await new Promise(r => setTimeout(r, 50));
         // An 8² frame asked with and without the matching level of detail.
         for (const [id, lod] of [[54, true], [55, false]]) {
           ws.send(JSON.stringify({id, step: null, width: 8, height: 8, format: 'png', lod}));
           while (!frames.includes(id) && Date.now() - t0 < 30000) await new Promise(r => setTimeout(r, 50));
         }
         // The same through the still-image API.
         const rest = [];
         for (const lod of [true, false])
           rest.push((await fetch(`/api/render?size=8&lod=${lod}`)).headers.get('x-vdi-resolution'));
         const after = await (await fetch('/api/stats')).json();
         ws.close();
         done({frames, errors, levels, rest, before, after});",
    )
    .await;
    let frames = burst["frames"].as_array().unwrap();
    let rendered = burst["after"]["rendered"].as_u64().unwrap()
        - burst["before"]["rendered"].as_u64().unwrap();
    let superseded = burst["after"]["superseded"].as_u64().unwrap()
        - burst["before"]["superseded"].as_u64().unwrap();
    eprintln!("50 camera changes: {rendered} renders, {superseded} superseded, frames {frames:?}");
    assert!(
        frames.contains(&json!(50)) && frames.contains(&json!(53)),
        "{burst}"
    );
    // An 8² frame with `lod` walks the VDI halved down to r = 8, without it the VDI itself
    // (what the 64² still was rendered from).
    let full = burst["levels"]["53"].as_u64().unwrap();
    assert!(full >= 16, "{burst}");
    assert_eq!(burst["levels"]["54"], json!(8), "{burst}");
    assert_eq!(burst["levels"]["55"], json!(full), "{burst}");
    assert_eq!(burst["rest"], json!(["8", full.to_string()]), "{burst}");
    // Other sockets (the page's own) may render meanwhile; the burst's 50 requests must
    // not have queued 50 renders.
    assert!(rendered <= 12 && superseded >= 40, "{burst}");
    let errors: Vec<&str> = burst["errors"]
        .as_array()
        .unwrap()
        .iter()
        .filter_map(Value::as_str)
        .collect();
    assert!(errors.iter().any(|e| e.contains("malformed")), "{errors:?}");
    assert!(
        errors.iter().any(|e| e.contains("step 999999")),
        "{errors:?}"
    );
    assert!(errors.iter().any(|e| e.contains("width 0")), "{errors:?}");
}

/// A recording of two ranks: the page shows the step composed over both by default and one
/// rank when it is selected, each matching the API's still of the same camera and rank.
#[test]
fn the_rank_selection_shows_one_brick_or_the_composed_step() {
    let Some(r) = Recorded::replay(2, 2, 0) else {
        return;
    };
    let shots = artefacts();
    rt().block_on(async {
        let c = r.open().await;
        // The fitted still (the first one, at zoom 1, is replaced once its fit is known).
        let still_of = |rank: &'static str| {
            move |d: &Value| {
                d["kind"] == "still" && d["step"] == "1" && d["rank"] == rank && d["zoom"] != "1"
            }
        };
        let api_of = |d: &Value, rank: Option<u32>| {
            format!(
                "/api/render?step=1&angle={}&elevation={}&zoom={}&size={}&format=png{}",
                d["angle"].as_str().unwrap(),
                d["elevation"].as_str().unwrap(),
                d["zoom"].as_str().unwrap(),
                d["width"].as_str().unwrap(),
                rank.map_or(String::new(), |r| format!("&rank={r}"))
            )
        };
        let all = wait_frame(&c, 20.0, still_of("all")).await;
        let composed = image_of(&c, "frame").await;
        let q = psnr_from_mse(mse(&composed, &image_of(&c, &api_of(&all, None)).await).unwrap());
        assert!(q >= 40.0, "composed: page vs API {q} dB");
        c.find(Locator::Id("rank"))
            .await
            .unwrap()
            .select_by_value("1")
            .await
            .unwrap();
        let one = wait_frame(&c, 20.0, still_of("1")).await;
        let brick = image_of(&c, "frame").await;
        let q = psnr_from_mse(mse(&brick, &image_of(&c, &api_of(&one, Some(1))).await).unwrap());
        assert!(q >= 40.0, "rank 1: page vs API {q} dB");
        assert!(not_blank(&brick), "rank 1's frame is blank");
        if brick.width() == composed.width() {
            let apart = psnr_from_mse(mse(&brick, &composed).unwrap());
            assert!(
                apart < 30.0,
                "rank 1 alone looks like the composed step ({apart} dB)"
            );
        }
        screenshot(&c, &shots, "viewer-rank.png").await;
        c.close().await.unwrap();
    });
    r.generator.terminate();
}

/// One HTTP/1.1 request on loopback (`Host: addr` unless `headers` name one); returns the
/// status code and the body.
pub(crate) fn http(addr: &str, target: &str, headers: &[&str]) -> (u16, String) {
    request(addr, "GET", target, headers)
}

/// [`http`] with another method.
fn request(addr: &str, method: &str, target: &str, headers: &[&str]) -> (u16, String) {
    send(addr, method, target, headers, "")
}

/// A POST of the JSON `body`; the status code and the body of the answer.
pub(crate) fn post(addr: &str, target: &str, headers: &[&str], body: &str) -> (u16, String) {
    let length = format!("Content-Length: {}", body.len());
    let mut all = vec!["Content-Type: application/json", length.as_str()];
    all.extend_from_slice(headers);
    send(addr, "POST", target, &all, body)
}

/// One request with `body` after its head.
fn send(addr: &str, method: &str, target: &str, headers: &[&str], body: &str) -> (u16, String) {
    let mut s = std::net::TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(20))).unwrap();
    let mut req = format!("{method} {target} HTTP/1.1\r\n");
    if !headers.iter().any(|h| h.starts_with("Host:")) {
        req.push_str(&format!("Host: {addr}\r\n"));
    }
    if !headers.iter().any(|h| h.starts_with("Connection:")) {
        req.push_str("Connection: close\r\n");
    }
    for h in headers {
        req.push_str(h);
        req.push_str("\r\n");
    }
    req.push_str("\r\n");
    req.push_str(body);
    s.write_all(req.as_bytes()).unwrap();
    // To the end of the response (its content-length; an upgraded socket stays open, so
    // there it is the head alone).
    let mut out = Vec::new();
    let mut buf = [0u8; 8192];
    while let Ok(n @ 1..) = s.read(&mut buf) {
        out.extend_from_slice(&buf[..n]);
        let text = String::from_utf8_lossy(&out);
        if let Some((head, body)) = text.split_once("\r\n\r\n") {
            let length = head.lines().find_map(|l| {
                l.to_ascii_lowercase()
                    .strip_prefix("content-length:")
                    .and_then(|v| v.trim().parse::<usize>().ok())
            });
            if head.starts_with("HTTP/1.1 101")
                || length.is_some_and(|n| body.len() >= n || method == "HEAD")
            {
                break;
            }
        }
    }
    insitu_e2e::parse_http_response(&out)
}

/// Without a token (the loopback default) another site's page can neither read the API under a
/// rebound name nor open the live socket; the viewer's own page, scripts and configured names
/// can.
#[test]
fn foreign_hosts_and_origins_are_refused_token_or_not() {
    let tmp = tempfile::tempdir().unwrap();
    let (v, addr) = viewer_on(tmp.path(), &["--config", &hosts_config(tmp.path())]);
    let upgrade = [
        "Connection: Upgrade",
        "Upgrade: websocket",
        "Sec-WebSocket-Version: 13",
        "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==",
    ];
    // Its own address, with or without the page's origin; a configured name; localhost.
    assert_eq!(http(&addr, "/api/steps", &[]).0, 200);
    let own = format!("Origin: http://{addr}");
    assert_eq!(http(&addr, "/api/steps", &[&own]).0, 200);
    assert_eq!(
        http(&addr, "/api/steps", &["Host: viz.example.org:8080"]).0,
        200
    );
    let port = addr.rsplit(':').next().unwrap();
    let localhost = format!("Host: localhost:{port}");
    assert_eq!(http(&addr, "/api/steps", &[&localhost]).0, 200);
    let mut socket = upgrade.to_vec();
    socket.push(&own);
    assert_eq!(http(&addr, "/api/live", &socket).0, 101);
    // A rebound name, and another site's page: refused with a reason, the socket too.
    let (status, body) = http(&addr, "/api/steps", &["Host: evil.example:8080"]);
    assert_eq!(status, 421, "{body}");
    assert!(body.contains("http_hosts"), "{body}");
    let (status, body) = http(&addr, "/api/steps", &["Origin: https://evil.example"]);
    assert_eq!(status, 403, "{body}");
    let mut foreign = upgrade.to_vec();
    foreign.push("Origin: https://evil.example");
    assert_eq!(http(&addr, "/api/live", &foreign).0, 403);
    v.terminate();
}

/// HEAD on a render is refused without rendering; a number beyond f32 is named as given.
#[test]
fn head_renders_nothing_and_numbers_are_named_as_given() {
    let tmp = tempfile::tempdir().unwrap();
    let (v, addr) = viewer_on(tmp.path(), &[]);
    let (status, _) = request(&addr, "HEAD", "/api/render?size=4096", &[]);
    assert_eq!(status, 405);
    let (status, body) = http(&addr, "/api/render?elevation=1e308", &[]);
    assert_eq!(status, 400, "{body}");
    assert!(body.contains("1e308"), "{body}");
    let (status, body) = http(&addr, "/api/reference?step=3&rank=7&view=0", &[]);
    assert_eq!(status, 404, "{body}");
    assert!(body.contains("step 3 is not in the recording"), "{body}");
    let stats: Value = serde_json::from_str(&http(&addr, "/api/stats", &[]).1).unwrap();
    assert_eq!(stats["rendered"], 0, "{stats}");
    v.terminate();
}

/// A camera request far over the limit (100 kB) ends the socket with a close frame 1009
/// ("message too big") that says why, rather than a dropped connection.
#[test]
fn an_oversized_socket_message_is_closed_with_1009() {
    let tmp = tempfile::tempdir().unwrap();
    let (v, addr) = viewer_on(tmp.path(), &[]);
    let mut s = std::net::TcpStream::connect(&addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(20))).unwrap();
    write!(
        s,
        "GET /api/live HTTP/1.1\r\nHost: {addr}\r\nConnection: Upgrade\r\nUpgrade: websocket\r\nSec-WebSocket-Version: 13\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n\r\n"
    )
    .unwrap();
    // The handshake's head, to its blank line.
    let mut head = Vec::new();
    let mut byte = [0u8; 1];
    while !head.ends_with(b"\r\n\r\n") {
        s.read_exact(&mut byte).unwrap();
        head.push(byte[0]);
    }
    assert!(
        head.starts_with(b"HTTP/1.1 101"),
        "{}",
        String::from_utf8_lossy(&head)
    );
    // One masked text frame of 100 kB (a client's frames are masked; key 0 keeps the bytes).
    let payload = vec![b' '; 100_000];
    let mut frame = vec![0x81, 0x80 | 127];
    frame.extend_from_slice(&(payload.len() as u64).to_be_bytes());
    frame.extend_from_slice(&[0, 0, 0, 0]);
    frame.extend_from_slice(&payload);
    s.write_all(&frame).unwrap();
    // Frames until the close: opcode 8, its first two payload bytes the code.
    let close = loop {
        let mut h = [0u8; 2];
        s.read_exact(&mut h).unwrap();
        let len = match h[1] & 0x7f {
            126 => {
                let mut l = [0u8; 2];
                s.read_exact(&mut l).unwrap();
                u64::from(u16::from_be_bytes(l))
            }
            127 => {
                let mut l = [0u8; 8];
                s.read_exact(&mut l).unwrap();
                u64::from_be_bytes(l)
            }
            n => u64::from(n),
        };
        let mut body = vec![0u8; len as usize];
        s.read_exact(&mut body).unwrap();
        if h[0] & 0x0f == 8 {
            break body;
        }
    };
    assert_eq!(u16::from_be_bytes([close[0], close[1]]), 1009);
    let reason = String::from_utf8_lossy(&close[2..]);
    assert!(reason.contains("100000 bytes"), "{reason}");
    v.terminate();
}

/// Held connections do not hold the daemon: one that sends nothing is closed after the
/// header timeout, and a live socket whose peer never answers the pings after the idle time.
#[test]
fn silent_connections_and_sockets_that_miss_their_pings_are_closed() {
    let tmp = tempfile::tempdir().unwrap();
    let cfg = tmp.path().join("timeouts.toml");
    std::fs::write(
        &cfg,
        "http_header_timeout_secs = 1.0\nhttp_idle_secs = 1.5\n",
    )
    .unwrap();
    let (v, addr) = viewer_on(tmp.path(), &["--config", cfg.to_str().unwrap()]);
    let t0 = std::time::Instant::now();
    let mut silent = std::net::TcpStream::connect(&addr).unwrap();
    silent
        .set_read_timeout(Some(Duration::from_secs(20)))
        .unwrap();
    let mut rest = Vec::new();
    let _ = silent.read_to_end(&mut rest);
    let secs = t0.elapsed().as_secs_f64();
    assert!(
        (0.8..5.0).contains(&secs),
        "a silent connection held {secs} s"
    );
    let mut s = std::net::TcpStream::connect(&addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(20))).unwrap();
    write!(
        s,
        "GET /api/live HTTP/1.1\r\nHost: {addr}\r\nConnection: Upgrade\r\nUpgrade: websocket\r\nSec-WebSocket-Version: 13\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n\r\n"
    )
    .unwrap();
    let t0 = std::time::Instant::now();
    let mut rest = Vec::new();
    let _ = s.read_to_end(&mut rest);
    let secs = t0.elapsed().as_secs_f64();
    assert!(
        rest.starts_with(b"HTTP/1.1 101"),
        "{}",
        String::from_utf8_lossy(&rest)
    );
    // After the handshake's head: a ping (opcode 9) came before the socket was closed.
    let head = rest.windows(4).position(|w| w == b"\r\n\r\n").unwrap() + 4;
    assert!(
        rest[head..].first().is_some_and(|b| b & 0x0f == 9),
        "no ping first: {:?}",
        &rest[head..]
    );
    assert!(
        (1.2..6.0).contains(&secs),
        "an unanswering socket held {secs} s"
    );
    v.terminate();
}

/// In a real browser, a page of another origin (a second server on loopback) cannot open the
/// live socket, with no token set; the viewer's own page can.
#[test]
fn a_page_from_another_origin_cannot_open_the_live_socket() {
    let Some(driver) = start_driver() else {
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    let (v, addr) = viewer_on(tmp.path(), &[]);
    // The other origin: one page, whose script tries the viewer's socket.
    let other = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let other_url = format!("http://{}/", other.local_addr().unwrap());
    let page = "<!doctype html><title>another site</title><p>another site</p>";
    std::thread::spawn(move || {
        for s in other.incoming() {
            let Ok(mut s) = s else { break };
            let mut head = [0u8; 4096];
            let _ = s.read(&mut head);
            let _ = write!(
                s,
                "HTTP/1.1 200 OK\r\nContent-Type: text/html\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{page}",
                page.len()
            );
        }
    });
    // Resolves to "open" or "refused" (an error or a close before opening).
    let try_socket = format!(
        "const ws = new WebSocket('ws://{addr}/api/live');
         ws.onopen = () => {{ ws.close(); done('open'); }};
         ws.onerror = () => done('refused');
         ws.onclose = () => done('refused');"
    );
    let stats = || -> Value { serde_json::from_str(&http(&addr, "/api/stats", &[]).1).unwrap() };
    rt().block_on(async {
        let c = browser(&driver, &tmp.path().join("profile")).await;
        c.goto(&other_url).await.unwrap();
        assert_eq!(
            js(&c, &try_socket).await,
            json!("refused"),
            "from {other_url}"
        );
        assert_eq!(stats()["clients"], 0, "a foreign page's socket was served");
        c.goto(&format!("http://{addr}/")).await.unwrap();
        assert_eq!(
            js(&c, &try_socket).await,
            json!("open"),
            "from the viewer's page"
        );
        c.close().await.unwrap();
    });
    v.terminate();
}

/// Names, sizes and modification times of the files in `dir`.
fn listing(dir: &Path) -> Vec<(String, u64, std::time::SystemTime)> {
    let mut files: Vec<_> = std::fs::read_dir(dir)
        .unwrap()
        .map(|d| {
            let d = d.unwrap();
            let m = d.metadata().unwrap();
            (
                d.file_name().to_string_lossy().into_owned(),
                m.len(),
                m.modified().unwrap(),
            )
        })
        .collect();
    files.sort();
    files
}

/// A finished recording served as a read-only archive (`--read-only`), on a read-only bind
/// mount where the machine allows one (CI runs as root): the viewer lists and renders its
/// steps and makes a movie of them, shipping into it is refused, and nothing beside it is
/// written.
#[test]
fn an_archive_is_browsed_read_only_and_nothing_is_written() {
    let tmp = tempfile::tempdir().unwrap();
    let made = Command::new(bin("insitu"))
        .args([
            "demo", "--size", "24", "--warmup", "50", "--every", "10", "--pushes", "3",
        ])
        .args(["--r", "32", "--no-http", "--no-tune", "--recording"])
        .arg(tmp.path().join("rec"))
        .output()
        .unwrap();
    assert!(
        made.status.success(),
        "{}",
        String::from_utf8_lossy(&made.stderr)
    );
    let rec = tmp.path().join("rec");
    let before = listing(&rec);
    let _mount = ReadOnlyMount::over(&rec);
    let (v, addr) = viewer_on(tmp.path(), &["--read-only"]);
    let (status, body) = http(&addr, "/api/steps", &[]);
    let steps: Value = serde_json::from_str(&body).unwrap();
    assert_eq!(status, 200, "{body}");
    let listed = steps["steps"].as_array().map_or(0, Vec::len);
    assert_eq!(listed, 3, "{body}");
    let (status, png) = http(&addr, "/api/render?size=48&angle=30", &[]);
    assert_eq!(status, 200, "{png}");
    let refused = rt().block_on(async {
        let mut c = insitu_proto::pb::viz_client::VizClient::connect(format!("http://{}", v.addr))
            .await
            .unwrap();
        c.agree_scene(insitu_proto::pb::SceneProposal::default())
            .await
            .unwrap_err()
    });
    assert_eq!(
        refused.code(),
        tonic::Code::FailedPrecondition,
        "{refused:?}"
    );
    assert!(
        refused.message().contains("read-only archive"),
        "{refused:?}"
    );
    // The page's movie of the steps it shows: an MP4 from ffmpeg, or 501 saying it is missing.
    let (status, body) = http(&addr, "/api/movie?size=33&frames_per_step=2", &[]);
    assert_eq!(status, 400, "{body}");
    assert!(body.contains("even"), "{body}");
    let (status, body) = http(&addr, "/api/movie?size=32&frames_per_step=2&fps=4", &[]);
    match insitu_testenv::tool("ffmpeg", insitu_testenv::Need::Ffmpeg) {
        Some(_) => {
            assert_eq!(status, 200, "{body}");
            assert!(
                body.get(4..8) == Some("ftyp"),
                "not an MP4: {:?}",
                body.get(..16)
            );
        }
        None => assert_eq!(status, 501, "{body}"),
    }
    v.terminate();
    assert_eq!(listing(&rec), before, "the archive was written to");
}

/// A read-only bind mount of a directory over itself, unmounted on drop; `None` where this
/// machine does not allow mounting (not root).
struct ReadOnlyMount(std::path::PathBuf);

impl ReadOnlyMount {
    fn over(dir: &Path) -> Option<Self> {
        let mount = |args: &[&str]| {
            Command::new("mount")
                .args(args)
                .arg(dir)
                .stderr(Stdio::null())
                .status()
                .is_ok_and(|s| s.success())
        };
        if !mount(&["--bind", dir.to_str()?]) {
            return None;
        }
        let m = Self(dir.to_owned());
        mount(&["-o", "remount,bind,ro"]).then_some(m)
    }
}

impl Drop for ReadOnlyMount {
    fn drop(&mut self) {
        let _ = Command::new("umount").arg(&self.0).status();
    }
}

/// A viz-node config answering to `viz.example.org` besides addresses and localhost.
fn hosts_config(dir: &Path) -> String {
    let path = dir.join("hosts.toml");
    std::fs::write(&path, "http_hosts = [\"viz.example.org\"]\n").unwrap();
    path.to_string_lossy().into_owned()
}

/// A viz-node started with the config file `cfg`, and its viewer's `127.0.0.1:port`.
fn viewer_of(cfg: &Path, logs: &Path) -> (Daemon, String) {
    let mut v = Daemon::start("viz-node", &["--config", cfg.to_str().unwrap()], &[], logs);
    let line = v.read_line();
    let port = line.rsplit(':').next().unwrap().trim_end_matches('/');
    let addr = format!("127.0.0.1:{port}");
    (v, addr)
}

#[test]
fn a_token_guards_the_page_the_api_and_the_socket_and_bad_requests_get_clear_errors() {
    let tmp = tempfile::tempdir().unwrap();
    let rec = tmp.path().join("rec");
    let token_file = tmp.path().join("token");
    std::fs::write(&token_file, "s3cret-token\n").unwrap();
    // Off loopback plain HTTP needs a token and insecure: without insecure it is refused.
    let cfg = tmp.path().join("viz.toml");
    std::fs::write(
        &cfg,
        format!(
            "listen = \"127.0.0.1:0\"\nhttp_listen = \"0.0.0.0:0\"\nrecording_dir = {:?}\ntoken_file = {:?}\n",
            rec.display().to_string(),
            token_file.display().to_string()
        ),
    )
    .unwrap();
    let out = Command::new(insitu_e2e::bin("viz-node"))
        .args(["--config", cfg.to_str().unwrap()])
        .env_remove("INSITU_TOKEN")
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("http_listen"),
        "{err}"
    );
    let mut toml = std::fs::read_to_string(&cfg).unwrap();
    toml.push_str("insecure = true\n");
    std::fs::write(&cfg, toml).unwrap();
    let (v, addr) = viewer_of(&cfg, tmp.path());
    let ws = [
        "Upgrade: websocket",
        "Connection: Upgrade",
        "Sec-WebSocket-Version: 13",
        "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==",
    ];
    for target in ["/", "/api/steps", "/api/live"] {
        let (code, body) = http(&addr, target, &ws);
        assert_eq!(code, 401, "{target} without a token: {body}");
        assert!(body.contains("token"), "{body}");
        let (code, _) = http(&addr, &format!("{target}?token=wrong"), &ws);
        assert_eq!(code, 401, "{target} with a wrong token");
    }
    let (code, body) = http(&addr, "/?token=s3cret-token", &[]);
    assert!(code == 200 && body.contains("app.js"), "{code} {body}");
    let (code, _) = http(&addr, "/api/live?token=s3cret-token", &ws);
    assert_eq!(code, 101, "the socket upgrades with the token");
    let bearer = "Authorization: Bearer s3cret-token";
    let (code, body) = http(&addr, "/api/steps", &[bearer]);
    assert!(
        code == 200 && body.contains("\"steps\":[]"),
        "{code} {body}"
    );
    // Bad requests: clear JSON errors with the right status, and the node keeps serving.
    for (target, status, says) in [
        ("/api/render", 404, "no step yet"),
        ("/api/render?step=3", 404, "step 3 is not in the recording"),
        ("/api/render?step=0&size=0", 400, "width 0"),
        ("/api/render?step=0&angle=NaN", 400, "angle"),
        ("/api/render?step=0&size=9000", 400, "width 9000"),
        ("/api/render?step=0&format=gif", 400, "format"),
        ("/api/render?bogus=1", 400, "bogus"),
        ("/api/reference?step=1", 400, "view"),
        ("/nope", 404, "no such page"),
    ] {
        let (code, body) = http(&addr, target, &[bearer]);
        assert_eq!(code, status, "{target}: {body}");
        assert!(
            body.contains("\"error\"") && body.contains(says),
            "{target}: {body}"
        );
    }
    let (code, _) = http(&addr, "/api/stats", &[bearer]);
    assert_eq!(code, 200);
    // Steering is off without a steering token: the viewing token cannot steer.
    let (code, body) = post(&addr, "/api/steer", &[bearer], r#"{"field":"v"}"#);
    assert!(
        code == 403 && body.contains("steering is off"),
        "{code} {body}"
    );
    v.terminate();
    // With one: the viewing token still cannot; the steering token views too; without a
    // tuner-node there is no one to decide.
    let steer_file = tmp.path().join("steer-token");
    std::fs::write(&steer_file, "steer-s3cret\n").unwrap();
    let mut toml = std::fs::read_to_string(&cfg).unwrap();
    toml.push_str(&format!(
        "steer_token_file = {:?}\n",
        steer_file.display().to_string()
    ));
    std::fs::write(&cfg, toml).unwrap();
    let (_v, addr) = viewer_of(&cfg, tmp.path());
    let (code, body) = post(&addr, "/api/steer", &[], r#"{"field":"v"}"#);
    assert_eq!(code, 401, "no token: {body}");
    let (code, body) = post(&addr, "/api/steer", &[bearer], r#"{"field":"v"}"#);
    assert!(
        code == 403 && body.contains("may view but not steer"),
        "{code} {body}"
    );
    let steerer = "Authorization: Bearer steer-s3cret";
    let (code, _) = http(&addr, "/api/steps", &[steerer]);
    assert_eq!(code, 200, "the steering token views");
    let (code, body) = post(&addr, "/api/steer", &[steerer], r#"{"field":"v"}"#);
    assert!(
        code == 503 && body.contains("needs a tuner-node"),
        "{code} {body}"
    );
}

/// `insitu demo --keep-serving` (docs/viewer.md): once the run's summary is out, its
/// viewer still answers over the recording, until SIGINT (Ctrl-C); then the process exits
/// cleanly and the port is closed.
#[test]
fn the_demo_keeps_serving_its_recording_until_interrupted() {
    let tmp = tempfile::tempdir().unwrap();
    let mut child = Command::new(bin("insitu"))
        .args(["demo", "--size", "24", "--warmup", "50", "--every", "10"])
        .args([
            "--pushes",
            "2",
            "--r",
            "32",
            "--no-tune",
            "--recording",
            "rec",
        ])
        .arg("--keep-serving")
        .current_dir(tmp.path())
        .env_remove("INSITU_TOKEN")
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // The line that says it serves on, read on a thread: a run that never prints it fails the
    // test after the timeout instead of blocking it.
    let stderr = child.stderr.take().unwrap();
    let (tx, rx) = std::sync::mpsc::sync_channel(1);
    let reader = std::thread::spawn(move || {
        let mut seen = String::new();
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            let serving = line.strip_prefix("serving the recording at ");
            if let Some(url) = serving.and_then(|l| l.strip_suffix(" until Ctrl-C")) {
                let _ = tx.send(url.to_owned());
            }
            seen.push_str(&line);
            seen.push('\n');
        }
        seen
    });
    let Ok(url) = rx.recv_timeout(Duration::from_secs(120)) else {
        let _ = child.kill();
        panic!("no 'serving' line; stderr:\n{}", reader.join().unwrap());
    };
    let addr = url.trim_start_matches("http://").trim_end_matches('/');
    let (status, body) = http(addr, "/api/steps", &[]);
    assert_eq!(status, 200, "{body}");
    let steps: Value = serde_json::from_str(&body).unwrap();
    let listed: Vec<u64> = steps["steps"]
        .as_array()
        .unwrap()
        .iter()
        .filter_map(|s| s["step"].as_u64())
        .collect();
    assert_eq!(listed, [50, 60], "{body}");
    let (status, answer) = http(addr, "/api/render?step=60&size=64", &[]);
    assert_eq!(status, 200, "{answer}");

    let interrupted = Command::new("kill")
        .args(["-INT", &child.id().to_string()])
        .status()
        .is_ok_and(|s| s.success());
    assert!(interrupted, "kill -INT failed");
    let deadline = Instant::now() + Duration::from_secs(30);
    let exit = loop {
        if let Some(exit) = child.try_wait().unwrap() {
            break exit;
        }
        if Instant::now() > deadline {
            let _ = child.kill();
            panic!("still running 30 s after SIGINT");
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    let log = reader.join().unwrap();
    assert!(exit.success(), "{exit}; stderr:\n{log}");
    assert!(
        std::net::TcpStream::connect(addr).is_err(),
        "the viewer still accepts connections after the exit"
    );
}
