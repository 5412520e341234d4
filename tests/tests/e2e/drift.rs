//! The tuner keeps a size budget while the data drifts: a deterministic series whose
//! structure grows at every step, through `insitu replay` with the tuner, judged by σ (a
//! size, not a timing, so the outcome does not hang on this machine's speed).

use insitu_core::adherence::Adherence;
use insitu_e2e::bin;
use insitu_e2e::drift::{growing_structure, write_series, RunLines};
use std::process::Command;

/// Grid side and steps of the series.
const N: usize = 40;
const STEPS: usize = 24;

fn replay(series: &std::path::Path, rec: &std::path::Path, extra: &[&str]) -> RunLines {
    let out = Command::new(bin("insitu"))
        .args(["replay", "--series", series.to_str().unwrap()])
        .args(["--recording", rec.to_str().unwrap()])
        .args([
            "--codec",
            "zstd",
            "--sample-every",
            "4",
            "--json",
            "--no-http",
        ])
        .args(["--step-interval", "0.4"])
        .args(extra)
        .env_remove("INSITU_TOKEN")
        .output()
        .unwrap();
    let text = crate::common::replayed(out);
    RunLines::parse(&text)
}

#[test]
fn a_growing_series_keeps_its_size_budget_after_the_first_decision() {
    let tmp = tempfile::tempdir().unwrap();
    let series = write_series(tmp.path(), "growing", N, STEPS, |t| {
        growing_structure(N, t, STEPS)
    });
    let budget = 60_000.0;
    let run = replay(
        &series,
        &tmp.path().join("rec"),
        &["--utility", "size:60kB"],
    );
    for s in &run.steps {
        eprintln!("{s:?}");
    }
    for d in &run.decisions {
        eprintln!("{d}");
    }
    assert_eq!(run.steps.len(), STEPS, "{:?}", run.summary);
    // The field grows: at one P_M the last step's VDI is much larger than the first's.
    let a = Adherence::of(
        run.steps
            .iter()
            .map(|s| (s.pm_version, s.sigma_bytes as f64)),
        budget,
    );
    eprintln!("{}", a.describe());
    assert!(a.steps >= STEPS / 2, "the first decision came late: {a:?}");
    assert!(
        a.share() >= 0.9 && a.worst_ratio <= 1.25,
        "{}",
        a.describe()
    );
    // The summary reports the same adherence.
    let s = &run.summary["tuner"]["sigma_adherence"];
    assert_eq!(s["within"].as_u64(), Some(a.within as u64), "{s}");
}
