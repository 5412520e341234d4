//! ADIOS2 writers feeding generator-nodes (feature `adios2`; `.ci/run` runs this binary with
//! it): ADIOS2's own Python API (the PyPI wheel) writes a field over SST while the nodes read
//! it live, each node its part of the global array; the composed picture equals the same field
//! pushed whole through our client. A writer that vanishes mid-run leaves every step it
//! finished in the recording, and the node's summary says where the stream stopped.

#![cfg(feature = "adios2")]
#![allow(clippy::unwrap_used, clippy::expect_used)]

use insitu_client::{ScalarType, SimClient, Step};
use insitu_core::metrics::psnr;
use insitu_core::vdi::codec::{decode, DecodeLimits};
use insitu_core::vdi::render;
use insitu_core::{BackendChoice, Vdi};
use insitu_e2e::{rt, start_viz, wait_until};
use insitu_generator_node::config::{Adios2Input, GenerationConfig};
use insitu_generator_node::{start, Config, RunningNode};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Child, Command};

const N: usize = 33;
const STEPS: u64 = 3;

/// A smooth field of `N³` points that moves with `step`, x fastest.
fn field(step: u64) -> Vec<f32> {
    let mut out = Vec::with_capacity(N * N * N);
    for z in 0..N {
        for y in 0..N {
            for x in 0..N {
                let d = |c: [f32; 3], s: f32| {
                    let d = [x as f32 - c[0], y as f32 - c[1], z as f32 - c[2]];
                    (-(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]) / (2.0 * s * s)).exp()
                };
                let c = 10.0 + 3.0 * step as f32;
                out.push(d([c, 14.0, 12.0], 6.0) + 0.8 * d([22.0, 20.0, 21.0], 7.0));
            }
        }
    }
    out
}

/// The steps' fields as raw files for the writer to read.
fn write_fields(dir: &Path) {
    for t in 0..STEPS {
        let bytes: Vec<u8> = field(t).iter().flat_map(|v| v.to_le_bytes()).collect();
        std::fs::write(dir.join(format!("step_{t}.raw")), bytes).unwrap();
    }
}

fn node_config(viz: &str, adios2: Option<Adios2Input>) -> Config {
    Config {
        listen: SocketAddr::from(([127, 0, 0, 1], 0)),
        viz: Some(viz.to_owned()),
        backend: BackendChoice::Cpu,
        threads: 1,
        max_backoff_secs: 0.2,
        drain_timeout_secs: 10.0,
        generation: GenerationConfig {
            resolution: 64,
            gamma: 0.01,
            reference_every: 0,
            ..GenerationConfig::default()
        },
        adios2,
        ..Config::default()
    }
}

fn writer(python: &Path, stream: &Path, dir: &Path, extra: &[&str]) -> Child {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/adios2_writer.py");
    let n = N.to_string();
    Command::new(python)
        .arg(script)
        .arg(stream)
        .arg(dir)
        .args([&n, &n, &n, &STEPS.to_string()])
        .args(extra)
        .spawn()
        .unwrap()
}

fn decode_file(path: &Path) -> Vdi {
    decode(&std::fs::read(path).unwrap(), &DecodeLimits::default()).unwrap()
}

/// Every step's VDI in a recording: a world of one's rows, or a world's composed steps.
fn recorded(rec: &Path, composed: bool) -> Vec<(u64, PathBuf)> {
    let Ok((entries, steps)) = insitu_recording::index::read(rec) else {
        return Vec::new();
    };
    if !composed {
        return entries
            .iter()
            .filter_map(|e| Some((e.step, rec.join(e.vdi.as_ref()?))))
            .collect();
    }
    steps
        .iter()
        .filter_map(|s| Some((s.step, rec.join(s.vdi.as_ref()?))))
        .collect()
}

fn shutdown(nodes: Vec<RunningNode>) -> Vec<String> {
    rt().block_on(async {
        let mut out = Vec::new();
        for n in nodes {
            out.push(n.shutdown().await.to_string());
        }
        out
    })
}

/// Pushes the steps' fields whole through our client to the generator-node at `addr`.
fn push_whole(addr: &str) {
    rt().block_on(async {
        let mut c = SimClient::connect(addr, None).await.unwrap();
        for t in 0..STEPS {
            let data: Vec<u8> = field(t).iter().flat_map(|v| v.to_le_bytes()).collect();
            c.push_step(Step {
                step: t,
                sim_time: t as f64,
                dtype: ScalarType::F32,
                global_dims: [N as u32; 3],
                brick_offset: [0; 3],
                brick_dims: [N as u32; 3],
                rank: 0,
                world_size: 1,
                spacing: [1.0; 3],
                origin: [0.0; 3],
                data: data.into(),
                fields: Vec::new(),
            })
            .await
            .unwrap();
        }
    });
}

/// The steps' fields written into `dir` for the writers, and pushed whole through our client
/// to a node of their own on `runtime` (which must outlive it): the recording, its viz-node
/// and the node.
fn pushed_whole(
    dir: &Path,
    runtime: &tokio::runtime::Runtime,
) -> (PathBuf, insitu_e2e::Daemon, RunningNode) {
    write_fields(dir);
    let pushed = dir.join("pushed");
    let v = start_viz(&pushed, "127.0.0.1:0", &[], dir);
    let node = runtime.block_on(start(node_config(&v.addr, None))).unwrap();
    push_whole(&node.local_addr().to_string());
    (pushed, v, node)
}

/// Each composed step of `streamed` draws as the step of `pushed` at four views (≥ 40 dB).
fn same_pictures(pushed: &Path, streamed: &Path, what: &str) {
    let (a, b) = (recorded(pushed, false), recorded(streamed, true));
    for (step, path) in &b {
        let whole = decode_file(&a.iter().find(|(s, _)| s == step).unwrap().1);
        let parts = decode_file(path);
        assert_eq!(parts.meta().volume_box, whole.meta().volume_box);
        for angle in [0.0, 30.0, 150.0, 240.0] {
            let view = whole.meta().camera.orbit_y(angle);
            let q = psnr(
                &render::render(&parts, &view, 96, 96, 0.99),
                &render::render(&whole, &view, 96, 96, 0.99),
            )
            .unwrap();
            eprintln!("step {step} at {angle}°: {what} vs pushed whole {q:.1} dB");
            assert!(q >= 40.0, "step {step} at {angle}°: {q:.1} dB");
        }
    }
}

/// The steps written by `writer_args`' writer as `stream`, read by two nodes half the array
/// each (`var`, else the first), drawn as the same field pushed whole through our client
/// (≥ 40 dB at four views, `what` in the log); returns the nodes' summaries.
fn two_nodes_draw_the_pushed_field(
    python: &Path,
    stream: &str,
    writer_args: &[&str],
    var: Option<&str>,
    what: &str,
) -> Vec<String> {
    let tmp = tempfile::tempdir().unwrap();
    let runtime = rt();
    let (pushed, v1, node) = pushed_whole(tmp.path(), &runtime);
    // The same field written as two blocks, read by two nodes, half the array each.
    let streamed = tmp.path().join("streamed");
    let v2 = start_viz(&streamed, "127.0.0.1:0", &[], tmp.path());
    let stream = tmp.path().join(stream);
    let mut args = vec!["--readers", "2"];
    args.extend_from_slice(writer_args);
    let mut w = writer(python, &stream, tmp.path(), &args);
    let nodes: Vec<RunningNode> = (0..2)
        .map(|part| {
            let mut input = Adios2Input::new(stream.clone());
            input.var = var.map(str::to_owned);
            input.part = [part, 2];
            input.open_timeout_secs = 60.0;
            runtime
                .block_on(start(node_config(&v2.addr, Some(input))))
                .unwrap()
        })
        .collect();
    assert!(w.wait().unwrap().success(), "the writer failed");
    let all = |rec: &Path, composed| recorded(rec, composed).len() == STEPS as usize;
    assert!(wait_until(90.0, || all(&pushed, false) && all(&streamed, true)));
    let summaries = shutdown(nodes);
    shutdown(vec![node]);
    same_pictures(&pushed, &streamed, what);
    v1.terminate();
    v2.terminate();
    summaries
}

#[test]
fn an_sst_stream_read_by_two_nodes_draws_as_the_field_pushed_whole() {
    let Some(python) = insitu_testenv::fixture_python() else {
        return;
    };
    let summaries =
        two_nodes_draw_the_pushed_field(&python, "simulation", &[], None, "SST in two parts");
    for s in &summaries {
        assert!(
            s.contains("3 step(s) read, the last step 2; the writer closed the stream"),
            "{s}"
        );
    }
}

/// Two writer processes, each opening a stream of its own and putting its own block (z
/// 0–15 and 16–32 of 33 points: no plane shared), read by two nodes as written: the nodes
/// exchange the seam's plane through the viz-node, and the composed picture is the field
/// pushed whole (≥ 40 dB at four views).
#[test]
fn writers_of_a_block_each_read_as_written_by_two_nodes_draw_the_pushed_field() {
    let Some(python) = insitu_testenv::fixture_python() else {
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    let runtime = rt();
    let (pushed, v1, node) = pushed_whole(tmp.path(), &runtime);
    let streamed = tmp.path().join("streamed");
    let v2 = start_viz(&streamed, "127.0.0.1:0", &[], tmp.path());
    let mut writers = Vec::new();
    let mut nodes = Vec::new();
    for block in 0..2u32 {
        let stream = tmp.path().join(format!("simulation.{block}"));
        let b = block.to_string();
        writers.push(writer(&python, &stream, tmp.path(), &["--own-block", &b]));
        let mut input = Adios2Input::new(stream);
        input.part = [block, 2];
        input.as_written = true;
        nodes.push(
            runtime
                .block_on(start(node_config(&v2.addr, Some(input))))
                .unwrap(),
        );
    }
    for mut w in writers {
        assert!(w.wait().unwrap().success(), "a writer failed");
    }
    let all = |rec: &Path, composed| recorded(rec, composed).len() == STEPS as usize;
    assert!(wait_until(90.0, || all(&pushed, false) && all(&streamed, true)));
    let grown: u64 = nodes
        .iter()
        .map(|n| n.shared().status().bricks_grown_across)
        .sum();
    let summaries = shutdown(nodes);
    shutdown(vec![node]);
    same_pictures(&pushed, &streamed, "two writers' blocks read as written");
    assert_eq!(
        grown, STEPS,
        "the lower block grows by the upper's plane every step"
    );
    for s in &summaries {
        assert!(
            s.contains("3 step(s) read, the last step 2; the writer closed the stream"),
            "{s}"
        );
    }
    v1.terminate();
    v2.terminate();
}

/// A stream of several blocks read as written is refused by name.
#[test]
fn a_stream_of_several_blocks_read_as_written_is_refused_by_name() {
    let Some(python) = insitu_testenv::fixture_python() else {
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    write_fields(tmp.path());
    let v = start_viz(&tmp.path().join("rec"), "127.0.0.1:0", &[], tmp.path());
    let stream = tmp.path().join("two-blocks.bp");
    let mut w = writer(&python, &stream, tmp.path(), &["--engine", "BP5"]);
    assert!(w.wait().unwrap().success(), "the writer failed");
    let mut input = Adios2Input::new(stream);
    input.as_written = true;
    let node = rt()
        .block_on(start(node_config(&v.addr, Some(input))))
        .unwrap();
    // The file is whole: its first step is read, and refused, at once.
    std::thread::sleep(std::time::Duration::from_secs(3));
    let summary = shutdown(vec![node]).remove(0);
    assert!(
        summary.contains("step 0 holds 2 blocks; as_written reads the one block"),
        "{summary}"
    );
    v.terminate();
}

/// An openPMD writer (openPMD-api over SST) whose mesh is labelled x, y, z in C order, stored
/// transposed from the volume's order: the nodes read its mesh by name, put x fastest, and draw
/// the field pushed whole.
#[test]
fn an_openpmd_stream_read_by_two_nodes_draws_as_the_field_pushed_whole() {
    let Some(python) = insitu_testenv::fixture_python() else {
        return;
    };
    let summaries = two_nodes_draw_the_pushed_field(
        &python,
        "pic",
        &["--openpmd"],
        Some("density"),
        "openPMD over SST in two parts",
    );
    for s in &summaries {
        assert!(s.contains("3 step(s) read, the last step 2;"), "{s}");
    }
}

#[test]
fn a_writer_that_vanishes_leaves_the_steps_it_finished() {
    let Some(python) = insitu_testenv::fixture_python() else {
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    write_fields(tmp.path());
    let runtime = rt();
    let rec = tmp.path().join("rec");
    let v = start_viz(&rec, "127.0.0.1:0", &[], tmp.path());
    let stream = tmp.path().join("crashing");
    let mut w = writer(&python, &stream, tmp.path(), &["--vanish-after", "2"]);
    let node = runtime
        .block_on(start(node_config(
            &v.addr,
            Some(Adios2Input::new(stream.clone())),
        )))
        .unwrap();
    assert!(w.wait().unwrap().success());
    assert!(
        wait_until(60.0, || recorded(&rec, false).len() == 2),
        "{:?}",
        recorded(&rec, false)
    );
    let summary = shutdown(vec![node]).remove(0);
    eprintln!("{summary}");
    assert!(
        summary.contains("2 step(s) read, the last step 1;"),
        "{summary}"
    );
    let steps: Vec<u64> = recorded(&rec, false).iter().map(|(s, _)| *s).collect();
    assert_eq!(steps, [0, 1]);
    v.terminate();
}
