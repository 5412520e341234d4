//! The Python client for real: the wheel `maturin build` makes of `python/`, installed in the
//! fixtures' venv (`scripts/build-python.sh`), runs `python/tests/client.py` against real
//! daemons (every dtype arrives, a 256 MiB field goes without a copy, bad input raises the
//! exception its stub names, a closed client and a dead daemon are errors), and the mpi4py
//! example runs under mpirun on 4 ranks and on 1 with the same picture.

use crate::common::{generator, index, small_config, steps, viz};
use crate::mpi_runs::{assert_same_picture, run, SMALL};
use insitu_e2e::wait_until;
use std::process::Command;

#[test]
fn the_python_client_pushes_numpy_fields_and_names_bad_input() {
    let Some(python) = insitu_testenv::python_package() else {
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    let rec = tmp.path().join("rec");
    let v = viz(&rec, "127.0.0.1:0", tmp.path());
    let cfg = small_config(&v.addr, "block", 4).replace(
        "max_backoff_secs",
        "max_step_bytes = 300000000\nmax_backoff_secs",
    );
    let g = generator(&cfg, tmp.path(), &[]);
    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/../python/tests/client.py");
    let out = Command::new(python)
        .arg(script)
        .arg(&g.addr)
        .arg(&rec)
        .env_remove("INSITU_TOKEN")
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(stdout.ends_with("ok\n"), "{stdout}");
    eprintln!("{stdout}");
    let stored: Vec<u64> = index(&rec).iter().map(|e| e.step).collect();
    assert_eq!(stored, vec![0, 1, 2, 3, 4, 10]);
    g.terminate();
    v.terminate();
}

/// The mpi4py example (`python/examples/gray_scott_mpi.py`: Gray–Scott in NumPy, halo
/// exchange over a periodic Cartesian communicator) under `mpirun -np 4` and `-np 1`: every
/// (step, rank) arrives, steps compose and are scored, and the pictures match.
#[test]
fn four_mpi4py_ranks_make_the_picture_one_makes() {
    let (Some(python), Some(mpirun)) = (
        insitu_testenv::python_package(),
        insitu_e2e::mpi_tool("mpirun"),
    ) else {
        return;
    };
    let has_mpi4py = Command::new(&python)
        .args(["-c", "import mpi4py"])
        .output()
        .is_ok_and(|o| o.status.success());
    if !has_mpi4py {
        let _: Option<()> = insitu_testenv::skip(
            insitu_testenv::Need::Python,
            "mpi4py does not import in the venv (scripts/build-python.sh)",
        );
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let script = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../python/examples/gray_scott_mpi.py"
    );
    let program = [python.as_os_str(), std::ffi::OsStr::new(script)];
    let (four, _) = run(&mpirun, &program, 4, tmp.path(), "mpi4py gray-scott", SMALL);
    let (one, _) = run(&mpirun, &program, 1, tmp.path(), "mpi4py gray-scott", SMALL);
    assert_same_picture(
        &four,
        &one,
        "mpi4py gray-scott",
        SMALL.r,
        (SMALL.r * SMALL.r / 50) as usize,
    );
}

/// The package's offline functions on NumPy arrays (`python/tests/offline.py`): direct
/// rendering, VDI generation close to it from its own camera, a saved VDI that loads back to
/// the same pictures with σ as evaluate measures it, bad input raised by name.
#[test]
fn the_python_offline_functions_keep_their_invariants() {
    let Some(python) = insitu_testenv::python_package() else {
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/../python/tests/offline.py");
    let out = Command::new(python)
        .arg(script)
        .arg(tmp.path())
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(stdout.ends_with("ok\n"), "{stdout}");
}

/// Two disjoint z-halves (as one splits an array) pushed as two ranks from Python: the node
/// grows the lower half by the upper's first plane and every step composes. Halves with a
/// plane of points between them: the push after the first whole step is refused, naming the
/// hole; leaving the `with` block raises that one error alone; the node's summary counts the
/// step, and the viewer's index says why it was not composed.
#[test]
fn disjoint_halves_compose_and_a_hole_is_named_at_the_next_push() {
    let Some(python) = insitu_testenv::python_package() else {
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    // Pushes 5 steps of a 32³ field as two z-slabs, the upper starting at `upper`.
    let run = |upper: usize| {
        let rec = tmp.path().join(format!("rec-{upper}"));
        let v = viz(&rec, "127.0.0.1:0", tmp.path());
        let g = generator(&small_config(&v.addr, "block", 4), tmp.path(), &[]);
        let script = r#"
import sys, numpy as np, insitu
n, upper = 32, int(sys.argv[2])
field = np.random.default_rng(1).random((n, n, n), dtype=np.float32)
with insitu.Client(sys.argv[1]) as c:
    for step in range(5):
        for rank, (z0, z1) in enumerate([(0, 16), (upper, n)]):
            c.push(step, np.ascontiguousarray(field[z0:z1]), offset=(0, 0, z0),
                   global_dims=(n, n, n), rank=rank, world_size=2)
        print("pushed", step, flush=True)
"#;
        let out = Command::new(&python)
            .args(["-c", script, &g.addr, &upper.to_string()])
            .env_remove("INSITU_TOKEN")
            .output()
            .unwrap();
        let summary = g.terminate();
        (out, summary, rec, v)
    };
    let (out, _, rec, v) = run(16);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(wait_until(30.0, || steps(&rec).len() == 5));
    for s in steps(&rec) {
        assert!(
            s.error.is_none() && s.missing.is_empty() && s.vdi.is_some(),
            "{s:?}"
        );
    }
    v.terminate();
    let (out, summary, rec, v) = run(17);
    let (stdout, stderr) = (
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr),
    );
    assert!(!out.status.success(), "{stdout}{stderr}");
    assert_eq!(stdout, "pushed 0\n", "{stderr}");
    assert_eq!(stderr.matches("Traceback").count(), 1, "{stderr}");
    for part in [
        "insitu.RefusedError",
        "step 1 rank 0: not taken",
        "found when step 0 had all its ranks",
        "hold 31744 of the grid's 32768 points",
        "beside rank 0's brick, no brick holds the points z = 16..=16",
    ] {
        assert!(stderr.contains(part), "{part}: {stderr}");
    }
    assert!(
        summary.contains("1 step(s) whose ranks' bricks cannot be composed (first: step 0)"),
        "{summary}"
    );
    assert!(wait_until(30.0, || steps(&rec).iter().any(|s| s.step == 0)));
    let s0 = steps(&rec).into_iter().find(|s| s.step == 0).unwrap();
    assert!(
        s0.error.as_deref().is_some_and(|e| e.contains("cover")),
        "{:?}",
        s0.error
    );
    v.terminate();
}

/// The `insitu` command the wheel installs: `view` draws a stored step as the core renders it
/// (≥ 40 dB, 8-bit PNG), `export` lists the stored steps, another command runs the Rust
/// `insitu` from `INSITU_BIN_DIR`, and without it the command says how to build it.
#[test]
fn the_package_s_insitu_command_views_exports_and_hands_the_rest_to_rust() {
    let Some(python) = insitu_testenv::python_package() else {
        return;
    };
    let command = python.with_file_name("insitu");
    let tmp = tempfile::tempdir().unwrap();
    let rec = tmp.path().join("rec");
    let v = viz(&rec, "127.0.0.1:0", tmp.path());
    let g = generator(&small_config(&v.addr, "block", 4), tmp.path(), &[]);
    crate::common::push_steps(&g.addr, 0..2);
    assert!(wait_until(30.0, || index(&rec).len() == 2));
    let run = |args: &[&str], bin_dir: &std::path::Path| {
        Command::new(&command)
            .args(args)
            .env("INSITU_BIN_DIR", bin_dir)
            .output()
            .unwrap()
    };
    let bins = insitu_e2e::bin_dir();
    let png = tmp.path().join("step1.png");
    let recording = rec.to_str().unwrap();
    let out = run(
        &[
            "view",
            "--recording",
            recording,
            "--time-step",
            "1",
            "--size",
            "64",
            "--angle",
            "30",
            "--out",
            png.to_str().unwrap(),
        ],
        &bins,
    );
    assert!(out.status.success(), "{out:?}");
    let shown = image::open(&png).unwrap().to_rgb8();
    let shown = insitu_core::Image::from_pixels(
        64,
        64,
        shown
            .pixels()
            .map(|p| p.0.map(|v| f32::from(v) / 255.0))
            .collect(),
    )
    .unwrap();
    let entry = index(&rec).into_iter().find(|e| e.step == 1).unwrap();
    let vdi = crate::common::load_vdi(&rec, &entry);
    let view = vdi.meta().camera.orbit_y(30.0);
    let core = insitu_core::vdi::render::render(&vdi, &view, 64, 64, 0.99);
    let q = insitu_core::metrics::psnr(&shown, &core).unwrap();
    assert!(q >= 40.0, "insitu view vs the core's render: {q:.1} dB");
    // export: the stored steps.
    let out = run(
        &["export", "--recording", recording, "--format", "json"],
        &bins,
    );
    assert!(out.status.success(), "{out:?}");
    let steps: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let listed: Vec<u64> = steps
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["step"].as_u64().unwrap())
        .collect();
    assert_eq!(listed, [0, 1]);
    // Another command is the Rust one's.
    let out = run(&["health", "--help"], &bins);
    assert!(
        String::from_utf8_lossy(&out.stdout).contains("gRPC health check"),
        "{out:?}"
    );
    let out = run(&["health", "--help"], tmp.path());
    assert_eq!(out.status.code(), Some(2), "{out:?}");
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("cargo build --release -p insitu-cli"),
        "{out:?}"
    );
    g.terminate();
    v.terminate();
}
