//! The ADIOS2 reader against BP5 files ADIOS2's own Python API wrote (`scripts/write-fixtures.sh`):
//! what it refuses, by name. The samples themselves are checked with every other reader's in
//! `fixtures.rs`.

#![cfg(feature = "adios2")]
#![allow(clippy::unwrap_used, clippy::expect_used)]

use insitu_readers::adios2::{Engine, Stream};
use insitu_readers::{open, Options};
use std::path::Path;
use std::time::Duration;

fn field(name: &str) -> Options {
    Options {
        field: Some(name.into()),
        ..Options::default()
    }
}

fn refusal(path: &Path, var: &str) -> String {
    open(path, &field(var)).unwrap_err().to_string()
}

#[test]
fn what_is_not_a_volume_is_refused_by_name() {
    let Some(dir) = insitu_testenv::fixture_dir() else {
        return;
    };
    let bad = dir.join("adios2_refused.bp");
    let e = refusal(&bad, "plane");
    assert!(e.contains("variable plane: 2-D"), "{e}");
    let e = refusal(&bad, "time");
    assert!(e.contains("variable time: not a global array"), "{e}");
    let e = refusal(&bad, "wave");
    assert!(e.contains("variable wave: of ADIOS2 type"), "{e}");
    let e = refusal(&bad, "rho");
    assert!(
        e.contains("no variable \"rho\"") && e.contains("plane, time, wave"),
        "{e}"
    );
    // None named: the file holds no 3-D global array of numbers.
    let e = open(&bad, &Options::default()).unwrap_err().to_string();
    assert!(e.contains("no 3-D global array"), "{e}");
}

#[test]
fn a_selection_outside_the_shape_is_refused_naming_both() {
    let Some(dir) = insitu_testenv::fixture_dir() else {
        return;
    };
    let path = dir.join("adios2_series.bp");
    let mut s = Stream::open(&path, Engine::File, &[], Duration::from_secs(1)).unwrap();
    assert!(matches!(
        s.begin_step(Some(Duration::from_secs(5))).unwrap(),
        insitu_readers::adios2::Step::Ready(0)
    ));
    let v = s.variable("rho").unwrap();
    assert_eq!(v.dims, [12, 10, 8]);
    let e = s
        .read_bytes("rho", [0, 0, 4], [12, 10, 5], None)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("variable rho")
            && e.contains("[0, 0, 4] of [12, 10, 5]")
            && e.contains("[12, 10, 8]"),
        "{e}"
    );
    // A box across the writer's two blocks reads as the whole field's box.
    let whole = s
        .read("rho", [0; 3], [12, 10, 8], None, glam::Vec3::ONE)
        .unwrap();
    let part = s
        .read("rho", [2, 1, 3], [5, 4, 3], None, glam::Vec3::ONE)
        .unwrap();
    for z in 0..3 {
        for y in 0..4 {
            for x in 0..5 {
                let (a, b) = (
                    part.data()[x + 5 * (y + 4 * z)],
                    whole.data()[(x + 2) + 12 * ((y + 1) + 10 * (z + 3))],
                );
                assert_eq!(a.to_bits(), b.to_bits(), "({x}, {y}, {z})");
            }
        }
    }
    s.end_step().unwrap();
    assert_eq!(
        s.begin_step(Some(Duration::from_secs(5))).unwrap(),
        insitu_readers::adios2::Step::Ready(1)
    );
}

#[test]
fn a_truncated_or_missing_file_and_a_stream_that_never_opens_are_named() {
    let Some(dir) = insitu_testenv::fixture_dir() else {
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    let cut_copy = |name: &str, file: &str, keep: fn(u64) -> u64| {
        let cut = tmp.path().join(name);
        std::fs::create_dir(&cut).unwrap();
        for f in std::fs::read_dir(dir.join("adios2_series.bp")).unwrap() {
            let f = f.unwrap();
            std::fs::copy(f.path(), cut.join(f.file_name())).unwrap();
        }
        let part = cut.join(file);
        let n = std::fs::metadata(&part).unwrap().len();
        std::fs::OpenOptions::new()
            .write(true)
            .open(&part)
            .unwrap()
            .set_len(keep(n))
            .unwrap();
        cut
    };
    let read_all = |path: &Path| {
        open(path, &field("rho"))
            .and_then(|d| (0..d.steps).try_for_each(|t| d.read_step(t).map(drop)))
            .unwrap_err()
            .to_string()
    };
    // The metadata cut to half: the index promises steps the file does not describe.
    let e = read_all(&cut_copy("cut.bp", "md.0", |n| n / 2));
    assert!(e.contains("cut.bp"), "{e}");
    // The data cut short, inside the last step: ADIOS2 waits for the rest as if a writer
    // were still writing; the read is given up on time and says why.
    let start = std::time::Instant::now();
    let e = read_all(&cut_copy("short.bp", "data.0", |n| n * 7 / 10));
    assert!(
        e.contains("short.bp: step 2 of rho: no data from ADIOS2 within")
            && e.contains("shorter than the metadata says"),
        "{e}"
    );
    assert!(start.elapsed() < insitu_readers::adios2::READ_WAIT * 2);
    let e = refusal(&tmp.path().join("none.bp"), "rho");
    assert!(e.contains("none.bp: no such BP file"), "{e}");
    // No writer: the timeout is named.
    let start = std::time::Instant::now();
    let e = Stream::open(
        &tmp.path().join("nobody"),
        Engine::Sst,
        &[],
        Duration::from_secs(1),
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("no SST writer opened it within 1 s"), "{e}");
    assert!(start.elapsed() < Duration::from_secs(30));
}

/// openPMD meshes are fields by record (and component), iterations are steps; what is not a
/// 3-D cartesian mesh labelled x, y, z is refused naming the mesh. The samples and grids are
/// checked with every other reader's in `fixtures.rs`.
#[test]
fn openpmd_meshes_are_fields_and_what_is_not_a_volume_is_refused_by_name() {
    let Some(dir) = insitu_testenv::fixture_dir() else {
        return;
    };
    let d = open(&dir.join("openpmd_groups.bp5"), &Options::default()).unwrap();
    assert_eq!(d.fields, ["E/x", "E/y", "E/z", "level_f", "rho"]);
    assert_eq!((d.field.as_str(), d.steps), ("E/x", 3));
    assert!(
        d.notes.iter().any(|n| n.contains("iterations 0, 100, 200")),
        "{:?}",
        d.notes
    );
    let steps = open(&dir.join("openpmd_steps.bp5"), &field("rho")).unwrap();
    assert_eq!(steps.steps, 3);
    let files = open(&dir.join("openpmd_files_%T.bp5"), &field("rho")).unwrap();
    assert_eq!(files.steps, 3);
    assert!(
        files
            .notes
            .iter()
            .any(|n| n.contains("3 files for iterations 0, 1, 2")),
        "{:?}",
        files.notes
    );
    let e = open(&dir.join("openpmd_none_%06T.bp5"), &field("rho"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("matches openpmd_none_<iteration>.bp5"), "{e}");

    let bad = dir.join("openpmd_refused.bp5");
    let e = refusal(&bad, "plane");
    assert!(e.contains("/data/0/meshes/plane: 2-D"), "{e}");
    let e = refusal(&bad, "Er");
    assert!(e.contains("openPMD mesh Er: geometry \"thetaMode\""), "{e}");
    let e = refusal(&bad, "odd");
    assert!(
        e.contains("openPMD mesh odd: axisLabels [\"a\", \"b\", \"c\"]"),
        "{e}"
    );
    let e = refusal(&bad, "nope");
    assert!(
        e.contains("no openPMD mesh \"nope\"; meshes here: Er, odd, plane"),
        "{e}"
    );
}

/// The blocks the writer put, as bricks of the grid: the fixture's two z-halves (8 points:
/// z 0–3 and 4–7) of every variable, in every step.
#[test]
fn the_blocks_written_read_back_as_bricks() {
    let Some(dir) = insitu_testenv::fixture_dir() else {
        return;
    };
    let path = dir.join("adios2_series.bp");
    let mut s = Stream::open(&path, Engine::File, &[], Duration::from_secs(1)).unwrap();
    let mut steps = 0;
    while let insitu_readers::adios2::Step::Ready(step) =
        s.begin_step(Some(Duration::from_secs(5))).unwrap()
    {
        for var in ["rho", "temp"] {
            let blocks = s.blocks(var, step).unwrap();
            let got: Vec<([usize; 3], [usize; 3])> =
                blocks.iter().map(|b| (b.offset, b.dims)).collect();
            assert_eq!(
                got,
                [([0, 0, 0], [12, 10, 4]), ([0, 0, 4], [12, 10, 4])],
                "{var} step {step}"
            );
        }
        s.end_step().unwrap();
        steps += 1;
    }
    assert!(steps >= 2, "{steps} steps");
    assert!(s
        .blocks("nothing", 0)
        .unwrap_err()
        .to_string()
        .contains("no variable"));
}
