//! docs/own-simulation.md as a newcomer follows it: the page quotes each language's example
//! file as it is, and each example, built with the page's command and run against daemons
//! `deploy/local.sh` started, stores every step, and its picture is not blank and matches the
//! Rust example's (≥ 40 dB at three views).

use crate::common::{index, load_vdi, succeeded};
use crate::local_sh::LocalSh;
use insitu_core::metrics::psnr;
use insitu_core::vdi::{render, Vdi};
use insitu_e2e::{bin_dir, build_c, build_fortran, wait_until};
use insitu_testenv::{tool, Need};
use std::path::Path;
use std::process::Command;
use std::sync::OnceLock;

/// The page, read at compile time so that a moved page fails the build, not a skip.
const PAGE: &str = include_str!("../../../docs/own-simulation.md");

/// The marker before each quoted example: `<!-- example: PATH -->`.
const MARKER: &str = "<!-- example: ";

/// Steps each example pushes.
const STEPS: u64 = 10;

/// The page's quoted examples: (path from the repository root, the fenced block's text).
fn quoted() -> Vec<(String, String)> {
    let mut out = Vec::new();
    let mut rest = PAGE;
    while let Some(at) = rest.find(MARKER) {
        rest = &rest[at + MARKER.len()..];
        let (path, after) = rest.split_once(" -->").expect("an unclosed example marker");
        let fence = after.trim_start_matches('\n');
        let (open, body) = fence.split_once('\n').expect("a marker without a block");
        assert!(
            open.starts_with("```"),
            "{path}: no fenced block after the marker"
        );
        let end = body.find("\n```").expect("an unclosed fenced block");
        out.push((path.to_owned(), format!("{}\n", &body[..end])));
        rest = &body[end..];
    }
    out
}

#[test]
fn the_page_quotes_each_example_file_as_it_is() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let quoted = quoted();
    let paths: Vec<&str> = quoted.iter().map(|(p, _)| p.as_str()).collect();
    assert_eq!(
        paths,
        [
            "examples/own-simulation/blob.py",
            "examples/own-simulation/blob.c",
            "examples/own-simulation/blob.f90",
            "examples/own-simulation/blob.rs",
        ]
    );
    for (path, text) in quoted {
        let file = std::fs::read_to_string(root.join(&path)).unwrap();
        assert_eq!(text, file, "docs/own-simulation.md quotes {path} otherwise");
    }
}

/// Runs `program` (the example, built) with the generator-node's address against a fresh
/// `deploy/local.sh`, and returns step 0 as stored, once all steps are; checks what the
/// program and the script print.
fn run_example(what: &str, program: &[&std::ffi::OsStr]) -> Vdi {
    let tmp = tempfile::tempdir().unwrap();
    let rec = tmp.path().join("rec");
    let sh = LocalSh::start(&rec, &[]);
    let out = Command::new(program[0])
        .args(&program[1..])
        .arg(&sh.generator)
        .env_remove("INSITU_TOKEN")
        .output()
        .unwrap();
    let stdout = succeeded(what, out);
    assert!(
        stdout.contains("pushed 10 steps of 64^3"),
        "{what}: {stdout}"
    );
    // The program returned after its flush: every step is stored.
    assert!(
        wait_until(10.0, || index(&rec).len() as u64 == STEPS),
        "{what}: stored {:?}",
        index(&rec).iter().map(|e| e.step).collect::<Vec<_>>()
    );
    let first = index(&rec).into_iter().find(|e| e.step == 0).unwrap();
    let vdi = load_vdi(&rec, &first);
    let rest = sh.stop();
    assert!(
        rest.contains("received 10, generated 10, shipped 10"),
        "{what}: {rest}"
    );
    vdi
}

/// The Rust example's step 0, the others' reference: not blank, the blob off-centre towards
/// −x (its centre at x = 16 of 64).
fn rust_reference() -> &'static Vdi {
    static REFERENCE: OnceLock<Vdi> = OnceLock::new();
    REFERENCE.get_or_init(|| {
        insitu_e2e::ensure_built();
        let exe = bin_dir().join("examples/blob");
        let vdi = run_example("rust", &[exe.as_os_str()]);
        let view = vdi.meta().camera;
        let image = render::render(&vdi, &view, 64, 64, 0.99);
        let lit = image
            .pixels()
            .iter()
            .filter(|p| p.iter().sum::<f32>() > 0.05)
            .count();
        assert!(lit > 200, "rust: only {lit} lit pixels");
        vdi
    })
}

/// `vdi` looks as the Rust example's step 0 from the generation view and two orbits of it.
fn assert_as_rust(what: &str, vdi: &Vdi) {
    let reference = rust_reference();
    assert_eq!(vdi.meta().camera, reference.meta().camera, "{what}");
    for angle in [0.0, 30.0, 60.0] {
        let view = reference.meta().camera.orbit_y(angle);
        let a = render::render(vdi, &view, 128, 128, 0.99);
        let b = render::render(reference, &view, 128, 128, 0.99);
        let q = psnr(&a, &b).unwrap();
        eprintln!("{what} example vs rust at {angle}°: {q:.1} dB");
        assert!(q >= 40.0, "{what} vs rust at {angle}°: {q:.1} dB");
    }
}

#[test]
fn the_rust_example_stores_a_picture() {
    rust_reference();
}

#[test]
fn the_python_example_draws_the_rust_picture() {
    let Some(python) = insitu_testenv::python_package() else {
        return;
    };
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("../examples/own-simulation/blob.py");
    let vdi = run_example("python", &[python.as_os_str(), script.as_os_str()]);
    assert_as_rust("python", &vdi);
}

#[test]
fn the_c_example_draws_the_rust_picture() {
    let Some(cc) = tool("cc", Need::CTools) else {
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    let exe = tmp.path().join("blob");
    build_c(
        &cc,
        "examples/own-simulation/blob.c",
        &exe,
        &["-Wall", "-Werror"],
    );
    let vdi = run_example("c", &[exe.as_os_str()]);
    assert_as_rust("c", &vdi);
}

#[test]
fn the_fortran_example_draws_the_rust_picture() {
    let Some(gfortran) = tool("gfortran", Need::Fortran) else {
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    let exe = tmp.path().join("blob");
    build_fortran(
        &gfortran,
        &[
            "client-c/fortran/insitu.f90",
            "examples/own-simulation/blob.f90",
        ],
        &exe,
        &["-std=f2018", "-Wall", "-Werror"],
    );
    let vdi = run_example("fortran", &[exe.as_os_str()]);
    assert_as_rust("fortran", &vdi);
}
