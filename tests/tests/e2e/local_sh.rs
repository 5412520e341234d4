//! `deploy/local.sh` as a newcomer runs it: the three daemons wired together, the viewer's URL
//! and the generator-node's address on stdout, a pushed step stored and shown, the viewer
//! drawing the tuner's budget, and everything stopped cleanly on SIGTERM.

use crate::common::push_steps;
use crate::viewer::http;
use insitu_e2e::{bin_dir, wait_until};
use serde_json::Value;
use std::io::{BufRead, BufReader, Read};
use std::path::Path;
use std::process::{Child, ChildStdout, Command, Stdio};

/// `deploy/local.sh` running from the test's binaries, once it has printed its addresses.
pub(crate) struct LocalSh {
    sh: Child,
    out: BufReader<ChildStdout>,
    /// The viewer's `host:port`.
    pub viewer: String,
    /// The generator-node's address.
    pub generator: String,
}

impl LocalSh {
    /// Runs the script as written on `recording`, with `env` set, and reads its address lines.
    pub fn start(recording: &Path, env: &[(&str, &str)]) -> Self {
        insitu_e2e::ensure_built();
        let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("../deploy/local.sh");
        let mut sh = Command::new("bash")
            .arg(&script)
            .arg(recording)
            .env("INSITU_BIN_DIR", bin_dir())
            .envs(env.iter().copied())
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
        let viewer = url
            .trim_start_matches("http://")
            .trim_end_matches('/')
            .to_owned();
        let generator = generator.expect("no generator-node line");
        Self {
            sh,
            out,
            viewer,
            generator,
        }
    }

    /// Sends SIGTERM and returns the rest of what the script printed; panics if it was killed.
    pub fn stop(mut self) -> String {
        let pid = self.sh.id().to_string();
        assert!(Command::new("kill")
            .args(["-TERM", &pid])
            .status()
            .unwrap()
            .success());
        let mut rest = String::new();
        self.out.read_to_string(&mut rest).unwrap();
        let status = self.sh.wait().unwrap();
        assert!(status.code().is_some(), "killed by a signal: {status:?}");
        rest
    }
}

#[test]
fn local_sh_starts_the_viewer_and_the_tuner_wired_and_stops_them() {
    let tmp = tempfile::tempdir().unwrap();
    let sh = LocalSh::start(&tmp.path().join("rec"), &[("TUNER_UTILITY", "size:200kB")]);
    let addr = sh.viewer.clone();
    push_steps(&sh.generator, 0..2);
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
    let rest = sh.stop();
    assert!(rest.contains("summary"), "{rest}");
    assert!(rest.contains("recording:"), "{rest}");
}

/// A run shorter than the first tuning, pushed as fast as the node takes it (the Rust example
/// of docs/own-simulation.md: 10 steps of 64³, about 60 kB a step at the configured r 256)
/// under a 20 kB budget: the node lowers r after the first step on its own, so every later
/// step made before the tuner's first decision keeps the budget, and the summary says so.
#[test]
fn a_short_fast_run_keeps_the_budget_from_its_second_step() {
    let tmp = tempfile::tempdir().unwrap();
    let rec = tmp.path().join("rec");
    let sh = LocalSh::start(&rec, &[("TUNER_UTILITY", "size:20kB")]);
    let out = Command::new(bin_dir().join("examples/blob"))
        .arg(&sh.generator)
        .env_remove("INSITU_TOKEN")
        .output()
        .unwrap();
    crate::common::succeeded("the Rust example", out);
    let rest = sh.stop();
    let rows: Vec<(u64, u64, u32, u64)> = crate::common::index(&rec)
        .iter()
        .map(|e| (e.step, e.pm_version, e.resolution, e.sizing.sigma_bytes))
        .collect();
    assert_eq!(rows.len(), 10, "{rows:?}");
    let untuned = kept_from_the_second_step(&rows, 20_000);
    assert!(
        rest.contains(&format!(
            "{} step(s) (1–{}) made at r lowered by the node",
            untuned.len(),
            untuned.last().unwrap()
        )),
        "{rest}"
    );
}

/// As above with two ranks on the one node (z-halves sharing the plane z = 32) pushed as fast
/// as the node takes them under a 20 kB budget: the node sums a step's σ over its ranks and
/// lowers r for whole steps, so every step composes and each after the first made before a
/// decision keeps the budget.
#[test]
fn two_ranks_on_one_node_keep_the_budget_from_their_second_step() {
    let tmp = tempfile::tempdir().unwrap();
    let rec = tmp.path().join("rec");
    let sh = LocalSh::start(&rec, &[("TUNER_UTILITY", "size:20kB")]);
    insitu_e2e::rt().block_on(async {
        let mut c = insitu_client::SimClient::connect(&sh.generator, None)
            .await
            .unwrap();
        for step in 0..8u64 {
            for s in crate::common::blob_halves(step) {
                c.push_step(s).await.unwrap();
            }
        }
        c.close(std::time::Duration::from_secs(120)).await.unwrap();
    });
    assert!(wait_until(60.0, || crate::common::steps(&rec).len() == 8));
    let rest = sh.stop();
    let steps = crate::common::steps(&rec);
    for s in &steps {
        assert!(
            s.error.is_none() && s.vdi.is_some(),
            "step {} did not compose: {s:?}",
            s.step
        );
    }
    let rows: Vec<(u64, u64, u32, u64)> = steps
        .iter()
        .map(|s| (s.step, s.pm_version, s.resolution, s.sizing.sigma_bytes))
        .collect();
    kept_from_the_second_step(&rows, 20_000);
    assert!(rest.contains("made at r lowered by the node"), "{rest}");
}

/// A run's steps as (step, P_M version, r, σ) under a budget of `budget` bytes: the first
/// broke it at the configured r 256, and every later one made before a decision kept it at a
/// lowered r. Returns those later steps (at least one).
fn kept_from_the_second_step(rows: &[(u64, u64, u32, u64)], budget: u64) -> Vec<u64> {
    assert!(
        rows[0].2 == 256 && rows[0].3 > budget,
        "the first step must break the budget: {rows:?}"
    );
    let untuned: Vec<u64> = rows[1..]
        .iter()
        .filter(|r| r.1 == 0)
        .map(|r| {
            assert!(r.2 < 256 && r.3 <= budget, "step {}: {rows:?}", r.0);
            r.0
        })
        .collect();
    assert!(
        !untuned.is_empty(),
        "no step before the first decision: {rows:?}"
    );
    untuned
}
