//! The Fortran client for real: the module `client-c/fortran/insitu.f90` and the heat
//! equation of `examples/mpi-heat-fortran` compiled with Open MPI's `mpifort` (gfortran)
//! against the C library, run with `mpirun -np 4` and `-np 1` against real daemons. Every
//! (step, rank) arrives, every step composes and is scored, and the 4-rank picture matches the
//! one-process run of the same simulation.

use crate::common::{generator, index, small_config, viz};
use crate::mpi_runs::{assert_same_picture, run, SMALL};
use insitu_e2e::{build_fortran, mpi_tool};
use std::process::Command;

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
    let (four, _) = run(&mpirun, &[exe.as_os_str()], 4, tmp.path(), "heat", SMALL);
    let (one, _) = run(&mpirun, &[exe.as_os_str()], 1, tmp.path(), "heat", SMALL);
    assert_same_picture(
        &four,
        &one,
        "fortran heat",
        SMALL.r,
        (SMALL.r * SMALL.r / 50) as usize,
    );
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
    let g = generator(&small_config(&v.addr, "block", 4), tmp.path(), &[]);
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
