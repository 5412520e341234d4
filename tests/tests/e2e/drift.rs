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
            .map(|s| (s.pm_version, s.pm(), s.sigma_bytes as f64)),
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

/// The hard limits are guarantees: with `--size-max` and `--time-max` below what the fixed
/// `P_M` gives, no stored step is over either (σ a size, exact; τ every try counted), steps
/// are made again to get there, and every step is stored or counted as failed.
#[test]
fn no_stored_step_exceeds_the_hard_limits() {
    let tmp = tempfile::tempdir().unwrap();
    let steps = 12;
    let series = write_series(tmp.path(), "growing", N, steps, |t| {
        growing_structure(N, t, steps)
    });
    let fixed = ["--no-tune", "--r", "256", "--gamma", "0.005"];
    let free = replay(&series, &tmp.path().join("free"), &fixed);
    assert_eq!(free.steps.len(), steps, "{:?}", free.summary);
    let median = |mut v: Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let size_max = (median(free.steps.iter().map(|s| s.sigma_bytes as f64).collect()) / 2.0) as u64;
    let time_max = median(free.steps.iter().map(|s| s.tau_secs).collect()) / 2.0;
    let (s, t) = (size_max.to_string(), format!("{time_max}"));
    let mut args = fixed.to_vec();
    args.extend(["--size-max", s.as_str(), "--time-max", t.as_str()]);
    let limited = replay(&series, &tmp.path().join("limited"), &args);
    for st in &limited.steps {
        assert!(st.sigma_bytes < size_max, "{st:?} over {size_max} B");
        assert!(st.tau_secs <= time_max, "{st:?} over {time_max} s");
    }
    let summary = &limited.summary;
    let failed = summary["failed"].as_u64().unwrap_or(u64::MAX);
    assert_eq!(
        limited.steps.len() as u64 + failed,
        steps as u64,
        "{summary}"
    );
    assert!(limited.steps.len() >= steps / 2, "{summary}");
    // The limits acted on at least half the steps: made again coarser, or refused.
    let retries = summary["limit_retries"].as_u64().unwrap_or(0);
    assert!(retries + failed >= steps as u64 / 2, "{summary}");
}
