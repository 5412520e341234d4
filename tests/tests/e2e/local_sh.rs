//! `deploy/local.sh` as a newcomer runs it: the three daemons wired together, the viewer's URL
//! and the generator-node's address on stdout, a pushed step stored and shown, the viewer
//! drawing the tuner's budget, and everything stopped cleanly on SIGTERM.

use crate::common::push_steps;
use crate::viewer::http;
use insitu_e2e::{bin_dir, wait_until};
use serde_json::Value;
use std::io::{BufRead, BufReader};
use std::process::{Command, Stdio};

#[test]
fn local_sh_starts_the_viewer_and_the_tuner_wired_and_stops_them() {
    insitu_e2e::ensure_built();
    let tmp = tempfile::tempdir().unwrap();
    let rec = tmp.path().join("rec");
    let script = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../deploy/local.sh");
    let mut sh = Command::new("bash")
        .arg(&script)
        .arg(&rec)
        .env("INSITU_BIN_DIR", bin_dir())
        .env("TUNER_UTILITY", "size:200kB")
        .env_remove("INSITU_TOKEN")
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let mut out = BufReader::new(sh.stdout.take().unwrap());
    let (mut url, mut generator) = (None, None);
    let mut line = String::new();
    while generator.is_none() && out.read_line(&mut line).unwrap() > 0 {
        let words: Vec<&str> = line.split_whitespace().collect();
        match words.as_slice() {
            ["viewer", u, ..] => url = Some(u.to_string()),
            ["generator-node", a, ..] => generator = Some(a.to_string()),
            _ => {}
        }
        line.clear();
    }
    let url = url.expect("no viewer line");
    let generator = generator.expect("no generator-node line");
    let addr = url
        .trim_start_matches("http://")
        .trim_end_matches('/')
        .to_owned();
    push_steps(&generator, 0..2);
    assert!(
        wait_until(60.0, || http(&addr, "/api/steps", &[])
            .1
            .matches("\"step\"")
            .count()
            >= 2),
        "{}",
        http(&addr, "/api/steps", &[]).1
    );
    // The viewer reads the tuner's budget (what its charts draw).
    assert!(
        wait_until(20.0, || {
            let s: Value =
                serde_json::from_str(&http(&addr, "/api/series", &[]).1).unwrap_or_default();
            s["budget"]["sigma_bytes"] == 200_000
        }),
        "{}",
        http(&addr, "/api/series", &[]).1
    );
    let pid = sh.id().to_string();
    assert!(Command::new("kill")
        .args(["-TERM", &pid])
        .status()
        .unwrap()
        .success());
    let mut rest = String::new();
    std::io::Read::read_to_string(&mut out, &mut rest).unwrap();
    let status = sh.wait().unwrap();
    assert!(rest.contains("summary"), "{rest}");
    assert!(rest.contains("recording:"), "{rest}");
    assert!(status.code().is_some(), "killed by a signal: {status:?}");
}
