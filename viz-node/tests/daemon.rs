#![allow(clippy::unwrap_used)]

//! The `viz-node` binary refuses bad configurations with a clear message and a non-zero exit.

use std::process::Command;

#[test]
fn a_corrupt_index_or_public_address_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("index.json"), "not json").unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_viz-node"))
        .args(["--listen", "127.0.0.1:0", "--recording-dir"])
        .arg(dir.path())
        .env_remove("INSITU_TOKEN")
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("index.json"), "{err}");
    let out = Command::new(env!("CARGO_BIN_EXE_viz-node"))
        .args(["--listen", "0.0.0.0:0", "--recording-dir"])
        .arg(dir.path().join("fresh"))
        .env_remove("INSITU_TOKEN")
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("without a token"));
}

#[test]
fn a_directory_of_vdis_without_an_index_is_not_orphaned() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("step_00000001_rank_0000.vdi"), b"x").unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_viz-node"))
        .args(["--listen", "127.0.0.1:0", "--recording-dir"])
        .arg(dir.path())
        .env_remove("INSITU_TOKEN")
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("index.sqlite") && err.contains("1 VDI or reference files"),
        "{err}"
    );
    assert!(!dir.path().join("index.sqlite").exists());
}
