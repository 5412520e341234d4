//! The Fortran client for real: the module `client-c/fortran/insitu.f90` and the heat
//! equation of `examples/mpi-heat-fortran` compiled with Open MPI's `mpifort` (gfortran)
//! against the C library, run with `mpirun -np 4` and `-np 1` against real daemons. Every
//! (step, rank) arrives, every step composes and is scored, and the 4-rank picture matches the
//! one-process run of the same simulation.

use crate::common::{generator, index, steps, viz};
use insitu_core::metrics::psnr;
use insitu_core::vdi::codec::{decode, DecodeLimits};
use insitu_core::vdi::{render, Vdi};
use insitu_e2e::{build_fortran, mpi_tool, wait_until};
use std::path::Path;
use std::process::Command;

const N: usize = 32;
const STEPS: u64 = 60;
const EVERY: u64 = 20;
const R: u32 = 64;

/// Runs the example on `np` ranks into a recording of its own; the last step's composed VDI.
fn run(exe: &Path, mpirun: &Path, np: u32, dir: &Path) -> Vdi {
    let rec = dir.join(format!("rec{np}"));
    let v = viz(&rec, "127.0.0.1:0", dir);
    let cfg = format!(
        r#"listen = "127.0.0.1:0"
viz = "{}"
[generation]
resolution = {R}
gamma = 0.01
codec = "zstd"
reference_every = 1
"#,
        v.addr
    );
    let g = generator(&cfg, dir, &[]);
    let out = Command::new(mpirun)
        .args([
            "--allow-run-as-root",
            "--oversubscribe",
            "-np",
            &np.to_string(),
        ])
        .arg(exe)
        .arg(&g.addr)
        .args([N.to_string(), STEPS.to_string(), EVERY.to_string()])
        .env_remove("INSITU_TOKEN")
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "mpirun -np {np}: {stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(stdout.contains(&format!("{np} ranks")), "{stdout}");
    // Several ranks: composed steps; one rank: its steps as they are.
    let scored = |rec: &Path| -> Vec<(u64, Option<String>, Option<f64>)> {
        if np > 1 {
            steps(rec)
                .into_iter()
                .filter(|s| s.missing.is_empty() && s.error.is_none())
                .map(|s| (s.step, s.vdi, s.quality.map(|q| q.q_db.0)))
                .collect()
        } else {
            index(rec)
                .into_iter()
                .map(|e| (e.step, e.vdi, e.quality.map(|q| q.q_db.0)))
                .collect()
        }
    };
    let all = wait_until(60.0, || {
        let s = scored(&rec);
        s.len() == 3 && s.iter().all(|s| s.2.is_some())
    });
    assert!(
        all,
        "{np} ranks: not every step was stored and scored: {:?}",
        scored(&rec)
    );
    let entries = index(&rec);
    for step in (EVERY..=STEPS).step_by(EVERY as usize) {
        for rank in 0..np {
            assert!(
                entries
                    .iter()
                    .any(|e| e.step == step && e.rank == rank && e.world_size == np),
                "{np} ranks: step {step} rank {rank} missing"
            );
        }
    }
    let (_, vdi, q) = scored(&rec).into_iter().find(|s| s.0 == STEPS).unwrap();
    eprintln!(
        "fortran heat, {np} ranks: step {STEPS} q {:.2} dB",
        q.unwrap_or_default()
    );
    let bytes = std::fs::read(rec.join(vdi.unwrap())).unwrap();
    g.terminate();
    v.terminate();
    decode(&bytes, &DecodeLimits::default()).unwrap()
}

#[test]
fn four_fortran_ranks_make_the_picture_one_makes() {
    let (Some(mpifort), Some(mpirun)) = (mpi_tool("mpifort"), mpi_tool("mpirun")) else {
        return;
    };
    if insitu_testenv::tool("gfortran", insitu_testenv::Need::Fortran).is_none() {
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let exe = tmp.path().join("heat_mpi");
    build_fortran(
        &mpifort,
        &[
            "client-c/fortran/insitu.f90",
            "examples/mpi-heat-fortran/heat_mpi.f90",
        ],
        &exe,
        &["-std=f2018", "-Wall", "-Werror"],
    );
    let four = run(&exe, &mpirun, 4, tmp.path());
    let one = run(&exe, &mpirun, 1, tmp.path());
    assert_eq!(four.meta().camera, one.meta().camera);
    for angle in [0.0, 30.0, 60.0] {
        let view = one.meta().camera.orbit_y(angle);
        let a = render::render(&four, &view, R, R, 0.99);
        let b = render::render(&one, &view, R, R, 0.99);
        let lit = b
            .pixels()
            .iter()
            .filter(|p| p.iter().sum::<f32>() > 0.05)
            .count();
        assert!(
            lit > (R * R / 50) as usize,
            "only {lit} lit pixels at {angle}°"
        );
        let q = psnr(&a, &b).unwrap();
        eprintln!("fortran heat, 4 ranks vs 1 at {angle}°: {q:.1} dB, {lit} lit pixels");
        assert!(q >= 40.0, "4 ranks vs one at {angle}°: {q:.1} dB");
    }
}

/// Bad input through the Fortran module gets a status and a message, and the program goes on:
/// a dead daemon, a client never connected or already closed, a non-contiguous or empty
/// array (refused in Fortran before any call), a brick outside the grid and a bad rank
/// (refused by the node); good pushes of both kinds still go through.
#[test]
fn fortran_bad_input_gets_a_status_and_a_message() {
    let Some(gfortran) = insitu_testenv::tool("gfortran", insitu_testenv::Need::Fortran) else {
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    let exe = tmp.path().join("bad_input");
    build_fortran(
        &gfortran,
        &[
            "client-c/fortran/insitu.f90",
            "client-c/fortran/tests/bad_input.f90",
        ],
        &exe,
        &["-std=f2018", "-Wall", "-Werror"],
    );
    let rec = tmp.path().join("rec");
    let v = viz(&rec, "127.0.0.1:0", tmp.path());
    let g = generator(
        &crate::common::small_config(&v.addr, "block", 4),
        tmp.path(),
        &[],
    );
    let out = Command::new(&exe)
        .args([g.addr.as_str(), "127.0.0.1:1"])
        .env_remove("INSITU_TOKEN")
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{stdout}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        !String::from_utf8_lossy(&out.stderr).contains("panicked"),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let expect = [
        ("dead_daemon", 2, "127.0.0.1:1 is unreachable"),
        ("not_connected", 1, "not connected"),
        ("connect", 0, ""),
        ("non_contiguous", 1, "field is not contiguous"),
        ("outside_the_grid", 3, "does not fit in the grid"),
        ("bad_rank", 3, "rank 1 with world_size 1"),
        ("empty", 1, "field is empty"),
        ("real64", 0, ""),
        ("real32", 0, ""),
        ("close", 0, ""),
        ("after_close", 1, "not connected (or was closed)"),
        ("close_twice", 0, ""),
    ];
    let lines: Vec<&str> = stdout.lines().collect();
    assert_eq!(lines.len(), expect.len(), "{stdout}");
    for (line, (case, status, words)) in lines.iter().zip(expect) {
        let mut parts = line.splitn(3, ' ');
        assert_eq!(parts.next(), Some(case), "{line}");
        assert_eq!(parts.next(), Some(status.to_string().as_str()), "{line}");
        assert!(parts.next().unwrap_or("").contains(words), "{line}");
    }
    let stored: Vec<u64> = index(&rec).iter().map(|e| e.step).collect();
    assert_eq!(stored, vec![5, 6], "only the good pushes are stored");
    g.terminate();
    v.terminate();
}
