//! A small frame's latency while large renders run: 64² stills (PNG) asked one after another
//! over HTTP while nothing else runs, while 1 and 4 clients each ask for 4096² stills without
//! pause, and while a movie (512², 120 frames) encodes, on a viz-node process on the CPU
//! backend serving a dense semi-transparent 64³ field at r = 256. Prints the median and 95th
//! percentile of the 64² latency beside the aim (p95 ≤ 0.3 s) and what the large renders took;
//! then what a 4096² still waits for when asked right after another's client hung up.
//!
//! `cargo bench -p insitu-e2e --bench lanes` (`INSITU_BENCH_VIZ_NODE=path` measures another
//! viz-node binary, e.g. an older build).

#![allow(clippy::unwrap_used, clippy::expect_used)]

use insitu_e2e::{bin, wait_until, Daemon};
use std::io::{Read, Write};
use std::net::TcpStream;
use std::process::Command;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// One GET to its end: the status code and the seconds it took.
fn get(addr: &str, target: &str) -> (u16, f64) {
    let t = Instant::now();
    let Ok(mut s) = TcpStream::connect(addr) else {
        return (0, t.elapsed().as_secs_f64());
    };
    let _ = write!(
        s,
        "GET {target} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n"
    );
    let mut out = Vec::new();
    let _ = s.read_to_end(&mut out);
    let status = String::from_utf8_lossy(&out[..out.len().min(12)])
        .split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or(0);
    (status, t.elapsed().as_secs_f64())
}

fn stat(addr: &str, key: &str) -> u64 {
    let mut s = TcpStream::connect(addr).unwrap();
    write!(
        s,
        "GET /api/stats HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n"
    )
    .unwrap();
    let mut out = String::new();
    s.read_to_string(&mut out).unwrap();
    let body = out.split_once("\r\n\r\n").map_or("", |(_, b)| b);
    let v: serde_json::Value = serde_json::from_str(body).unwrap_or_default();
    v[key].as_u64().unwrap_or(0)
}

fn percentile(v: &mut [f64], p: f64) -> f64 {
    v.sort_by(f64::total_cmp);
    v[((v.len() as f64 - 1.0) * p).round() as usize]
}

/// 64² latencies (seconds) while `load` clients each repeat `target` without pause; the
/// loads' own times.
fn measure(addr: &str, load: usize, target: &str) -> (Vec<f64>, Vec<f64>) {
    let stop = Arc::new(AtomicBool::new(false));
    let loads = Arc::new(Mutex::new(Vec::new()));
    let workers: Vec<_> = (0..load)
        .map(|_| {
            let (stop, loads, addr, target) = (
                stop.clone(),
                loads.clone(),
                addr.to_owned(),
                target.to_owned(),
            );
            std::thread::spawn(move || {
                while !stop.load(Ordering::Relaxed) {
                    let (status, secs) = get(&addr, &target);
                    if status == 200 {
                        loads.lock().unwrap().push(secs);
                    } else {
                        std::thread::sleep(Duration::from_millis(200));
                    }
                }
            })
        })
        .collect();
    if load > 0 {
        // The load under way (an older build without the gauge: a second's head start).
        if !wait_until(30.0, || stat(addr, "rendering") >= 1) {
            std::thread::sleep(Duration::from_secs(1));
        }
    }
    let mut small = Vec::new();
    for i in 0..40 {
        let (status, secs) = get(addr, &format!("/api/render?step=1&size=64&angle={}", i * 9));
        assert_eq!(status, 200, "a 64² frame was refused");
        small.push(secs);
        std::thread::sleep(Duration::from_millis(50));
    }
    stop.store(true, Ordering::Relaxed);
    for w in workers {
        w.join().unwrap();
    }
    let l = loads.lock().unwrap().clone();
    (small, l)
}

fn main() {
    if !std::env::args().any(|a| a == "--bench") {
        return;
    }
    insitu_e2e::ensure_built();
    let tmp = tempfile::tempdir().unwrap();
    let viz_bin =
        std::env::var_os("INSITU_BENCH_VIZ_NODE").map_or_else(|| bin("viz-node"), Into::into);
    let mut cmd = Command::new(&viz_bin);
    cmd.args(["--recording-dir"])
        .arg(tmp.path().join("rec"))
        .args([
            "--listen",
            "127.0.0.1:0",
            "--http",
            "127.0.0.1:0",
            "--backend",
            "cpu",
        ])
        .env_remove("INSITU_TOKEN");
    let mut v = Daemon::spawn("viz-node", cmd, tmp.path());
    let url = v.read_line().replace("web viewer on ", "");
    let addr = url
        .trim_start_matches("http://")
        .trim_end_matches('/')
        .to_owned();
    let g = Daemon::start(
        "generator-node",
        &[
            "--listen",
            "127.0.0.1:0",
            "--viz",
            &v.addr,
            "--backend",
            "cpu",
            "--codec",
            "zstd",
        ],
        &[],
        tmp.path(),
    );
    insitu_e2e::drift::push_dense(&g.addr, 3);
    assert!(
        wait_until(120.0, || stat(&addr, "vdis_stored") == 3),
        "the VDIs were not stored"
    );
    let still = "/api/render?step=0&size=4096&format=jpeg";
    let movie = "/api/movie?size=512&frames_per_step=40";
    let ffmpeg = Command::new("ffmpeg").arg("-version").output().is_ok();
    let mut cases = vec![
        ("idle", 0, still),
        ("1 × 4096² still", 1, still),
        ("4 × 4096² stills", 4, still),
    ];
    if ffmpeg {
        cases.push(("1 movie 512² × 120", 1, movie));
    }
    for (name, load, target) in cases {
        let (mut small, mut large) = measure(&addr, load, target);
        let large_note = if large.is_empty() {
            String::new()
        } else {
            format!(
                "; the load's own requests: {} done, median {:.2} s",
                large.len(),
                percentile(&mut large, 0.5)
            )
        };
        println!(
            "64² while {name:<20}: median {:7.1} ms, p95 {:7.1} ms (aim: p95 ≤ 300 ms){large_note}",
            percentile(&mut small, 0.5) * 1e3,
            percentile(&mut small, 0.95) * 1e3,
        );
    }
    // An abandoned still: what the next large still waits for after its client hung up.
    let (_, alone) = get(&addr, still);
    let mut s = TcpStream::connect(&addr).unwrap();
    write!(
        s,
        "GET {still} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n"
    )
    .unwrap();
    std::thread::sleep(Duration::from_millis(300));
    drop(s);
    let (status, next) = get(&addr, still);
    println!(
        "a 4096² still asked 0.3 s after another's client hung up: {next:.2} s (status {status}; one alone: {alone:.2} s)"
    );
    v.terminate();
}
