//! The viewer's renders when clients go away: a still or a movie whose client hangs up stops
//! (counted in `/api/stats` as cancelled), its ffmpeg is gone, its lane is free, and a movie
//! past the lane's queue is answered 503 with `Retry-After`.

use crate::common::{generator, small_config};
use crate::viewer::{http, viz_with_http};
use insitu_e2e::wait_until;
use insitu_testenv::{tool, Need};
use serde_json::Value;
use std::io::{Read, Write};
use std::net::TcpStream;
use std::time::Duration;

/// A request sent and left unread: the client that will hang up.
fn hold(addr: &str, target: &str) -> TcpStream {
    let mut s = TcpStream::connect(addr).unwrap();
    write!(
        s,
        "GET {target} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n"
    )
    .unwrap();
    s
}

fn stats(addr: &str) -> Value {
    serde_json::from_str(&http(addr, "/api/stats", &[]).1).unwrap()
}

/// Process ids of the `ffmpeg` children of `parent`.
fn ffmpeg_children(parent: u32) -> Vec<u32> {
    let Ok(dir) = std::fs::read_dir("/proc") else {
        return Vec::new();
    };
    dir.flatten()
        .filter_map(|e| {
            let stat = std::fs::read_to_string(e.path().join("stat")).ok()?;
            // pid (comm) state ppid ...
            let (comm, rest) = stat.split_once(") ")?;
            let ppid: u32 = rest.split_whitespace().nth(1)?.parse().ok()?;
            (comm.ends_with("(ffmpeg") && ppid == parent)
                .then(|| e.file_name().to_string_lossy().parse().ok())
                .flatten()
        })
        .collect()
}

#[test]
fn abandoned_stills_and_movies_stop_and_free_their_lane() {
    let tmp = tempfile::tempdir().unwrap();
    let (v, url) = viz_with_http(&tmp.path().join("rec"), tmp.path(), &[]);
    let addr = url
        .trim_start_matches("http://")
        .trim_end_matches('/')
        .to_owned();
    let g = generator(&small_config(&v.addr, "block", 4), tmp.path(), &[]);
    insitu_e2e::drift::push_dense(&g.addr, 3);
    assert!(wait_until(60.0, || stats(&addr)["vdis_stored"] == 3));

    // A 4096² still whose client hangs up while it renders: it stops, counted as cancelled.
    let s = hold(&addr, "/api/render?step=0&size=4096");
    assert!(
        wait_until(20.0, || stats(&addr)["rendering"] == 1),
        "the still never started: {}",
        stats(&addr)
    );
    drop(s);
    assert!(
        wait_until(20.0, || stats(&addr)["rendering"] == 0),
        "the abandoned still kept rendering: {}",
        stats(&addr)
    );
    let st = stats(&addr);
    assert_eq!(
        (st["cancelled"].as_u64(), st["rendered"].as_u64()),
        (Some(1), Some(0)),
        "{st}"
    );

    // Movies: one renders, four wait, the sixth is turned away with Retry-After.
    if tool("ffmpeg", Need::Ffmpeg).is_some() {
        let movie = "/api/movie?size=512&frames_per_step=40";
        let held: Vec<TcpStream> = (0..5).map(|_| hold(&addr, movie)).collect();
        assert!(wait_until(20.0, || stats(&addr)["rendering"] == 1));
        let mut sixth = hold(&addr, movie);
        sixth
            .set_read_timeout(Some(Duration::from_secs(20)))
            .unwrap();
        let mut answer = String::new();
        let _ = sixth.read_to_string(&mut answer);
        assert!(
            answer.starts_with("HTTP/1.1 503")
                && answer.to_ascii_lowercase().contains("retry-after: 1"),
            "{answer}"
        );
        // The running movie starts its encoder with its first frame, which a loaded machine
        // may not have rendered by the time the sixth is turned away.
        assert!(
            wait_until(20.0, || !ffmpeg_children(v.child.id()).is_empty()),
            "no ffmpeg for the running movie"
        );
        drop(held);
        assert!(
            wait_until(20.0, || stats(&addr)["rendering"] == 0
                && ffmpeg_children(v.child.id()).is_empty()),
            "abandoned movies kept rendering: {} (ffmpeg {:?})",
            stats(&addr),
            ffmpeg_children(v.child.id())
        );
        // The running movie is cancelled; a waiting one may take the freed lane before the
        // server has read its client's hang-up, and is then cancelled too, never finished.
        let cancelled = stats(&addr)["cancelled"].as_u64().unwrap_or(0);
        assert!((2..=6).contains(&cancelled), "{}", stats(&addr));
    }

    // The lane is free: a 2048² still is rendered, not refused.
    let (status, _) = http(&addr, "/api/render?step=0&size=2048&format=jpeg", &[]);
    assert_eq!(status, 200);
    assert_eq!(stats(&addr)["rendering"], 0);
    v.terminate();
}
