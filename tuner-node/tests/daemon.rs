#![allow(clippy::unwrap_used)]

//! The `tuner-node` binary refuses bad configurations with a clear message and a non-zero
//! exit, before serving anything. (Also what makes `cargo test --workspace` build the binary
//! that the end-to-end tests start.)

use std::process::Command;

fn run(args: &[&str]) -> (bool, String) {
    let state = tempfile::tempdir().unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_tuner-node"))
        .arg("--state-dir")
        .arg(state.path())
        .args(args)
        .env_remove("INSITU_TOKEN")
        .output()
        .unwrap();
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
fn a_public_address_without_a_token_and_tls_is_refused() {
    let (ok, err) = run(&["--listen", "0.0.0.0:0"]);
    assert!(!ok);
    assert!(err.contains("without a token and TLS"), "{err}");
}

#[test]
fn bad_values_are_named() {
    let (ok, err) = run(&["--listen", "127.0.0.1:0", "--utility", "size:-1"]);
    assert!(!ok);
    assert!(err.contains("utility") && err.contains("size:-1"), "{err}");
    let (ok, err) = run(&["--config", "/no/such.toml"]);
    assert!(!ok);
    assert!(err.contains("/no/such.toml"), "{err}");
}
