#![allow(clippy::unwrap_used)]

//! The `generator-node` binary refuses bad configurations with a clear message and a
//! non-zero exit, before serving anything.

use std::process::Command;

fn run(args: &[&str]) -> (bool, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_generator-node"))
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
fn a_public_address_without_a_token_is_refused() {
    let (ok, err) = run(&["--listen", "0.0.0.0:0"]);
    assert!(!ok);
    assert!(err.contains("without a token"), "{err}");
}

#[test]
fn bad_values_are_named() {
    let (ok, err) = run(&["--listen", "127.0.0.1:0", "--gamma", "-1"]);
    assert!(!ok);
    assert!(err.contains("gamma"), "{err}");
    let (ok, err) = run(&["--config", "/no/such.toml"]);
    assert!(!ok);
    assert!(err.contains("/no/such.toml"), "{err}");
    let (ok, err) = run(&["--policy", "drop-newest"]);
    assert!(!ok);
    assert!(err.contains("drop-newest"), "{err}");
}
