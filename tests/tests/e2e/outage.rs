//! Kill the viz-node mid-run and restart it: the generator-node keeps running, reconnects, and
//! every step acknowledged before the outage is in the recording (and nothing is lost after).

use crate::common::{flush, generator, index, load_vdi, push_steps, small_config, status, viz};
use insitu_e2e::wait_until;

#[test]
fn a_viz_node_outage_loses_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    let rec = tmp.path().join("rec");
    let v = viz(&rec, "127.0.0.1:0", tmp.path());
    let viz_addr = v.addr.clone();
    let g = generator(&small_config(&viz_addr, "block", 16), tmp.path(), &[]);
    push_steps(&g.addr, 0..5);
    let s = flush(&g.addr);
    assert_eq!(s.steps_shipped, 5);
    let acknowledged: Vec<u64> = index(&rec).iter().map(|e| e.step).collect();
    assert_eq!(acknowledged, vec![0, 1, 2, 3, 4]);
    v.kill();
    push_steps(&g.addr, 5..10);
    // The generator keeps serving and notices the outage.
    assert!(wait_until(20.0, || !status(&g.addr).viz_connected));
    assert_eq!(status(&g.addr).steps_received, 10);
    let v = viz(&rec, &viz_addr, tmp.path());
    let s = flush(&g.addr);
    assert_eq!(
        (s.steps_shipped, s.dropped_outbox, s.failed),
        (10, 0, 0),
        "{s:?}"
    );
    let entries = index(&rec);
    assert_eq!(
        entries.iter().map(|e| e.step).collect::<Vec<_>>(),
        (0..10).collect::<Vec<_>>()
    );
    for e in &entries {
        assert_eq!(load_vdi(&rec, e).resolution(), 32);
    }
    let summary = g.terminate();
    assert!(summary.contains("shipped 10"), "{summary}");
    v.terminate();
}

/// `insitu replay` of a 3-step 16³ series written in `dir`, pushing to the generator-node at
/// `addr` without a tuner; its stderr piped, to read.
fn replay_blob(
    dir: &std::path::Path,
    addr: &str,
) -> (
    std::process::Child,
    std::io::BufReader<std::process::ChildStderr>,
) {
    let series = insitu_e2e::drift::write_series(dir, "blob", 16, 3, |t| {
        (0..16 * 16 * 16).map(|i| ((i + t) % 7) as f32).collect()
    });
    let mut replay = std::process::Command::new(insitu_e2e::bin("insitu"))
        .args(["replay", "--series"])
        .arg(&series)
        .args(["--generator", addr, "--no-tune"])
        .env_remove("INSITU_TOKEN")
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let err = std::io::BufReader::new(replay.stderr.take().unwrap());
    (replay, err)
}

/// `insitu replay` waiting for steps the generator-node cannot deliver (its viz-node down)
/// says so on stderr while it waits, then finishes once the viz-node is back.
#[test]
fn replay_says_why_it_waits_while_steps_cannot_be_stored() {
    use std::io::BufRead;
    let tmp = tempfile::tempdir().unwrap();
    let rec = tmp.path().join("rec");
    let viz_addr = format!("127.0.0.1:{}", insitu_e2e::free_port());
    let g = generator(&small_config(&viz_addr, "block", 16), tmp.path(), &[]);
    let (mut replay, mut err) = replay_blob(tmp.path(), &g.addr);
    let mut line = String::new();
    let warned = loop {
        line.clear();
        if err.read_line(&mut line).unwrap() == 0 {
            break None;
        }
        if line.starts_with("warning: steps not stored yet") {
            break Some(line.clone());
        }
    };
    let warned = warned.expect("replay never said why it waits");
    assert!(warned.contains("unreachable"), "{warned}");
    let v = viz(&rec, &viz_addr, tmp.path());
    assert!(replay.wait().unwrap().success());
    assert_eq!(index(&rec).len(), 3);
    g.terminate();
    v.terminate();
}

/// A generator-node killed under a running `insitu replay` (no spool): the replay ends with
/// an error that says the node went away and what to do, not a bare transport error.
#[test]
fn replay_says_the_generator_node_went_away_when_it_is_killed() {
    use std::io::{BufRead, Read};
    let tmp = tempfile::tempdir().unwrap();
    let viz_addr = format!("127.0.0.1:{}", insitu_e2e::free_port());
    let g = generator(&small_config(&viz_addr, "block", 16), tmp.path(), &[]);
    let (mut replay, mut err) = replay_blob(tmp.path(), &g.addr);
    let mut line = String::new();
    // Waiting for steps the absent viz-node cannot store: the node is then killed.
    while err.read_line(&mut line).unwrap() > 0 && !line.starts_with("warning: steps not stored") {
        line.clear();
    }
    g.kill();
    let mut rest = String::new();
    err.read_to_string(&mut rest).unwrap();
    let status = replay.wait().unwrap();
    assert!(!status.success(), "{rest}");
    assert!(rest.contains("the generator-node went away"), "{rest}");
    assert!(rest.contains("restart it"), "{rest}");
}
