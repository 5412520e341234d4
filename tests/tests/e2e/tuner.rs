//! The tuner service with every daemon a real process on 127.0.0.1: a tuned ocean replay, a
//! change of character, a tuner restart, a generator-node killed during trials, and bad input.

use crate::common::{finish, flush, free_port, index, status, steps, viz};
use crate::tuned::{
    client, decision, decision_trial, replay, state, tuned_generator, tuned_generator_from,
    tuned_ocean, tuner_paced, tuner_status,
};
use insitu_client::{SimClient, Step};
use insitu_e2e::{bin, rt, wait_until, Daemon};
use insitu_proto::pb;
use insitu_proto::pb::node_message::Msg as Up;
use insitu_proto::pb::tuner_message::Msg as Down;
use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::process::Command;

/// Trials may use 10 % of the wall clock and nothing more: a tuning then takes seconds, long
/// enough to kill something in the middle of it.
const PACED: &str = "timeout_secs = 60.0\nshare = 0.1\nburst_secs = 0.0";

/// The budget of the two-node run, as the utility writes it and in bytes.
const BLOB_BUDGET: &str = "20kB";
const BLOB_BUDGET_BYTES: u64 = 20_000;

/// (step, r, γ bits, precision) of every persisted trial.
fn trials(dir: &Path) -> Vec<(u64, u64, u64, String)> {
    state(dir)["trials"]
        .as_array()
        .unwrap()
        .iter()
        .map(|t| {
            let m = &t["measurement"];
            (
                t["step"].as_u64().unwrap(),
                m["r"].as_u64().unwrap(),
                (m["gamma"].as_f64().unwrap() as f32).to_bits().into(),
                m["precision"].as_str().unwrap_or("f32").to_owned(),
            )
        })
        .collect()
}

/// A 32³ series of `steps` steps whose character changes at `switch`: a small Gaussian blob
/// drifting (most voxels near 0), then slowly drifting waves (values spread over [0, 1]);
/// alike steps are within 0.1 (histogram distance) of their regime's first step, the regimes 0.85 apart.
fn two_regime_series(dir: &Path, steps: usize, switch: usize) -> PathBuf {
    let n = 32usize;
    let path = dir.join(format!("regimes_{n}x{n}x{n}x{steps}_float32.raw"));
    let mut bytes = Vec::with_capacity(n * n * n * steps * 4);
    for t in 0..steps {
        for i in 0..n * n * n {
            let (x, y, z) = ((i % n) as f32, ((i / n) % n) as f32, (i / (n * n)) as f32);
            let v = if t < switch {
                let c = 12.0 + t as f32 * 0.5;
                let d2 = (x - c).powi(2) + (y - 16.0).powi(2) + (z - 16.0).powi(2);
                (-d2 / 40.0).exp()
            } else {
                0.5 + 0.25 * ((0.3 * x + 0.005 * t as f32).sin() + (0.2 * y + 0.3 * z).sin())
            };
            bytes.extend_from_slice(&v.to_le_bytes());
        }
    }
    std::fs::write(&path, bytes).unwrap();
    path
}

#[test]
fn a_tuned_ocean_replay_meets_the_size_budget() {
    let Some(o) = tuned_ocean(
        "size:60kB",
        &["--sample-every", "2", "--step-interval", "1.5"],
    ) else {
        return;
    };
    let (rec, st, t, g) = (&o.rec, &o.st, &o.t, &o.g);
    let s = tuner_status(&t.addr);
    assert!(s.pm_version >= 1, "the tuner pushed no P_M: {s:?}");
    // The trials' CPU time is counted on the node, and what the tuner heard of it is the
    // node's count (all trials answered; the node counts any it ran after, too).
    let node = status(&g.addr);
    assert!(
        s.trial_cpu_secs > 0.0
            && s.size_probe_cpu_secs <= s.trial_cpu_secs
            && s.trial_cpu_secs <= node.trial_cpu_secs + 1e-6
            && node.trial_cpu_secs < node.cpu_secs,
        "tuner {} s ({} s size probes), node {} s of {} s",
        s.trial_cpu_secs,
        s.size_probe_cpu_secs,
        node.trial_cpu_secs,
        node.cpu_secs
    );
    let d = decision(&t.addr, 1).unwrap();
    assert!(d.characteristic_steps.contains(&0), "{d:?}");
    assert!(d.predicted_sigma_bytes < 60_000, "{d:?}");
    // The decision meets σ_target on every step it was tuned on (trials, persisted).
    let state = state(st);
    for step in &d.characteristic_steps {
        let trial = decision_trial(&state, *step, &d);
        assert!(trial["measurement"]["sigma_bytes"].as_u64().unwrap() < 60_000);
    }
    // The log names the characteristic steps.
    let log = std::fs::read_to_string(&t.log).unwrap();
    assert!(
        log.contains("step 0 is the first characteristic step"),
        "{log}"
    );
    // Production steps made with the tuned P_M: stamped with its version, and within budget.
    let entries = index(rec);
    assert_eq!(entries.len(), 12);
    let tuned: Vec<_> = entries.iter().filter(|e| e.pm_version >= 1).collect();
    assert!(
        tuned.len() >= 3,
        "only {} steps after the push",
        tuned.len()
    );
    for e in &tuned {
        assert_eq!((e.resolution, e.gamma), (d.resolution, d.gamma));
        assert!(
            e.sizing.sigma_bytes < 60_000,
            "step {} σ {}",
            e.step,
            e.sizing.sigma_bytes
        );
    }
    let before: Vec<_> = entries.iter().filter(|e| e.pm_version == 0).collect();
    eprintln!(
        "ocean, size:60kB: decision r {} γ {} on steps {:?} (predicted σ {} B, q {:.2} dB), {} trials {:.1} s; \
         before: {} steps, σ {}–{} B; after: {} steps, σ {}–{} B, all < 60 kB",
        d.resolution,
        d.gamma,
        d.characteristic_steps,
        d.predicted_sigma_bytes,
        d.predicted_q_db,
        d.trials,
        d.trial_secs,
        before.len(),
        before.iter().map(|e| e.sizing.sigma_bytes).min().unwrap_or(0),
        before.iter().map(|e| e.sizing.sigma_bytes).max().unwrap_or(0),
        tuned.len(),
        tuned.iter().map(|e| e.sizing.sigma_bytes).min().unwrap_or(0),
        tuned.iter().map(|e| e.sizing.sigma_bytes).max().unwrap_or(0),
    );
    assert_eq!(status(&g.addr).pm_version, s.pm_version);
    o.stop();
}

/// A world of 4 ranks on one node: every step composes, the one the decision lands in too
/// (its ranks keep one P_M), and the decision's predicted q is the composed step's q, which
/// the viz-node measures on the composed VDI, to within 1.5 dB, so no step is re-tuned for
/// falling short of it. (A decision once landing between the ranks of a step left it
/// uncomposed, and q pooled as the mean of the bricks' MSEs was 5 dB too high here.)
#[test]
fn with_four_ranks_the_predicted_q_is_the_composed_steps() {
    let Some(o) = tuned_ocean("size:600kB", &["--ranks", "4", "--step-interval", "2"]) else {
        return;
    };
    let (rec, t) = (&o.rec, &o.t);
    let summary = || {
        steps(rec)
            .iter()
            .map(|s| (s.step, s.pm_version, s.quality.as_ref().map(|q| q.q_db.0)))
            .collect::<Vec<_>>()
    };
    let scored = wait_until(60.0, || {
        summary().iter().filter(|s| s.2.is_some()).count() == 12
    });
    assert!(
        scored,
        "not every step was composed and scored: {:?}",
        summary()
    );
    let d = decision(&t.addr, 1).unwrap_or_else(|e| {
        panic!(
            "no decision: {e}\n{}",
            std::fs::read_to_string(&t.log).unwrap_or_default()
        )
    });
    let composed: Vec<(u64, f64)> = summary()
        .into_iter()
        .filter(|s| s.1 == 1)
        .filter_map(|(step, _, q)| Some((step, q?)))
        .collect();
    assert!(!composed.is_empty(), "no step made with v1");
    for (step, q) in &composed {
        assert!(
            (q - d.predicted_q_db).abs() < 1.5,
            "step {step}: composed q {q:.2} dB, predicted {:.2} dB",
            d.predicted_q_db
        );
    }
    let log = std::fs::read_to_string(&t.log).unwrap();
    assert!(!log.contains("below the predicted"), "{log}");
    eprintln!(
        "4 ranks, size:600kB: v1 r {} γ {} from step {}, predicted q {:.2} dB; composed {composed:?}",
        d.resolution, d.gamma, d.from_step, d.predicted_q_db
    );
    o.stop();
}

/// A world of two ranks (the 64³ blob's z-halves) pushed to two generator-nodes, one rank each,
/// a step every 0.2 s, under a budget step 0 breaks ≥ 2.5× at r 256: no node sees a
/// whole step, so the tuner lowers r in a provisional decision from step 0's σ summed over both
/// nodes. Every step made under a provisional decision keeps the budget, every step composes
/// (its ranks share one P_M), and each node's summary counts the steps.
#[test]
fn a_world_spread_over_two_nodes_keeps_the_budget_before_the_first_tuning() {
    let tmp = tempfile::tempdir().unwrap();
    let rec = tmp.path().join("rec");
    let v = viz(&rec, "127.0.0.1:0", tmp.path());
    let listen = format!("127.0.0.1:{}", free_port());
    let t = tuner_paced(
        &tmp.path().join("state"),
        &listen,
        &v.addr,
        &format!("size:{BLOB_BUDGET}"),
        // Trials at 2 % of the wall clock: the first tuning outlasts the run.
        "timeout_secs = 60.0\nshare = 0.02\nburst_secs = 0.0",
        tmp.path(),
    );
    let toml = crate::common::small_config(&v.addr, "block", 16)
        .replace("resolution = 32", "resolution = 256");
    let nodes = [0, 1].map(|_| tuned_generator_from(&toml, &t.addr, tmp.path()));
    // A step every 0.2 s: the first step waits up to the host's 2 s for ranks that go to the
    // other node, so the provisional decision applies some ten steps later.
    const STEPS: u64 = 30;
    rt().block_on(async {
        let mut clients = Vec::new();
        for g in &nodes {
            clients.push(SimClient::connect(&g.addr, None).await.unwrap());
        }
        for step in 0..STEPS {
            for (c, s) in clients.iter_mut().zip(crate::common::blob_halves(step)) {
                c.push_step(s).await.unwrap();
            }
            tokio::time::sleep(std::time::Duration::from_millis(200)).await;
        }
        for c in clients {
            c.close(std::time::Duration::from_secs(120)).await.unwrap();
        }
    });
    assert!(wait_until(60.0, || steps(&rec).len() == STEPS as usize));
    let provisional: BTreeSet<u64> = (1..=tuner_status(&t.addr).pm_version)
        .filter_map(|v| decision(&t.addr, v).ok())
        .filter(|d| d.provisional)
        .map(|d| d.pm_version)
        .collect();
    let logs = nodes.map(Daemon::terminate);
    let rows: Vec<(u64, u64, u32, u64)> = steps(&rec)
        .iter()
        .map(|s| {
            assert!(
                s.error.is_none() && s.vdi.is_some(),
                "step {} did not compose: {s:?}",
                s.step
            );
            (s.step, s.pm_version, s.resolution, s.sizing.sigma_bytes)
        })
        .collect();
    assert!(
        rows[0].2 == 256 && rows[0].3 * 10 >= BLOB_BUDGET_BYTES * 25,
        "step 0 must break the budget 2.5× or more: {rows:?}"
    );
    let lowered: Vec<&(u64, u64, u32, u64)> =
        rows.iter().filter(|r| provisional.contains(&r.1)).collect();
    assert!(
        !lowered.is_empty(),
        "no step made under a provisional decision: {rows:?}\n{}",
        std::fs::read_to_string(&t.log).unwrap_or_default()
    );
    for r in &lowered {
        assert!(
            r.2 < 256 && r.3 <= BLOB_BUDGET_BYTES,
            "step {}: {rows:?}",
            r.0
        );
    }
    for log in &logs {
        assert!(
            log.contains("made at r lowered by the tuner's provisional decisions"),
            "{log}"
        );
    }
    eprintln!(
        "two nodes, size:{BLOB_BUDGET}: provisional versions {provisional:?}, steps {rows:?}"
    );
    t.terminate();
    v.terminate();
}

#[test]
fn a_change_of_character_retunes_once_and_alike_steps_never() {
    let tmp = tempfile::tempdir().unwrap();
    let series = two_regime_series(tmp.path(), 12, 6);
    let out = Command::new(bin("insitu"))
        .args(["replay", "--series", series.to_str().unwrap()])
        .args(["--r", "128", "--codec", "zstd", "--sample-every", "3"])
        .args(["--utility", "size:40kB", "--step-interval", "1.2", "--json"])
        .arg("--recording")
        .arg(tmp.path().join("rec"))
        .env_remove("INSITU_TOKEN")
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(
        out.status.success(),
        "{}\n{text}",
        String::from_utf8_lossy(&out.stderr)
    );
    let lines: Vec<serde_json::Value> = text
        .lines()
        .map(|l| serde_json::from_str(l).unwrap_or_else(|e| panic!("{l:?}: {e}")))
        .collect();
    let vdis: Vec<_> = lines.iter().filter(|l| l.get("rank").is_some()).collect();
    assert_eq!(vdis.len(), 12, "{text}");
    for v in &vdis {
        for k in [
            "step",
            "r",
            "gamma",
            "pm_version",
            "sigma_bytes",
            "tau_s",
            "q_db",
        ] {
            assert!(v.get(k).is_some(), "{k} missing in {v}");
        }
    }
    let changes: Vec<_> = lines.iter().filter(|l| l["event"] == "pm_change").collect();
    assert!(!changes.is_empty(), "{text}");
    let summary = &lines.last().unwrap()["summary"];
    let t = &summary["tuner"];
    // Exactly the two regimes are characteristic, and only they started a tuning.
    assert_eq!(
        t["characteristic_steps"],
        serde_json::json!([0, 6]),
        "{text}"
    );
    assert_eq!(t["retunes"], 2, "{text}");
    // Each P_M is used from its from_step on, past the step that triggered it (unless a
    // later decision replaced it before its step began: the nodes then keep the P_M before
    // it until the later one's step; or the series ended before its step: a correction after
    // the last step cannot know it was the last).
    let last = vdis
        .iter()
        .filter_map(|v| v["step"].as_u64())
        .max()
        .unwrap();
    for c in &changes {
        let (v, from) = (c["pm_version"].as_u64(), c["from_step"].as_u64().unwrap());
        assert!(from > c["step"].as_u64().unwrap(), "{c}");
        let mut made = lines
            .iter()
            .filter(|l| l.get("event").is_none() && l["pm_version"].as_u64() == v);
        let replaced = changes.iter().any(|l| l["pm_version"].as_u64() > v);
        assert!(made.clone().count() > 0 || replaced || from > last, "{c}");
        assert!(
            made.all(|l| l["step"].as_u64().unwrap() >= from),
            "{c}\n{text}"
        );
    }
    // A tuning's decision ran trials and meets the budget on its steps; a correction between
    // tunings (the second regime's steps are 12× larger at the P_M in force) runs none and
    // corrects an earlier version: the coarsest P_M of the grid when nothing meets the plan.
    for c in &changes {
        let steps = c["characteristic_steps"].as_array().unwrap();
        assert!(!steps.is_empty(), "{c}");
        match c["corrects_version"].as_u64() {
            None => {
                assert!(c["trials"].as_u64().unwrap() > 0, "{c}");
                assert!(
                    c["predicted"]["sigma_bytes"].as_u64().unwrap() < 40_000,
                    "{c}"
                );
            }
            Some(v) => {
                assert!(v < c["pm_version"].as_u64().unwrap(), "{c}");
                assert_eq!(c["trials"].as_u64(), Some(0), "{c}");
                assert!(
                    c["reason"]
                        .as_str()
                        .unwrap()
                        .starts_with("correction after step"),
                    "{c}"
                );
            }
        }
    }
    eprintln!(
        "{} P_M change(s): {changes:?}; summary {summary}",
        changes.len()
    );
}

/// Waits for the first decision, then for the tuning after it (the second regime) to have run
/// a trial and still be under way; returns the status at the first decision.
fn second_tuning_under_way(t: &Daemon) -> pb::TunerStatus {
    assert!(wait_until(90.0, || tuner_status(&t.addr).pm_version >= 1));
    let first = tuner_status(&t.addr);
    assert!(
        wait_until(90.0, || {
            let s = tuner_status(&t.addr);
            s.tuning && s.trials_run > first.trials_run
        }),
        "no second tuning: {:?}\n{}",
        tuner_status(&t.addr),
        std::fs::read_to_string(&t.log).unwrap_or_default()
    );
    first
}

/// Pushes `steps` of `series` (32³) as two z-bricks, rank 0 to `a` and rank 1 to `b`, one
/// step every `interval` seconds; stops pushing to `b` at its first failure or hang.
fn push_two_ranks(series: &Path, steps: std::ops::Range<usize>, a: &str, b: &str, interval: f64) {
    let format = insitu_core::volume::RawFormat::from_file_name(series).unwrap();
    rt().block_on(async {
        let mut ca = SimClient::connect(a, None).await.unwrap();
        let mut cb = SimClient::connect(b, None).await.ok();
        for t in steps {
            let v = format.load(series, t, glam::Vec3::ONE).unwrap();
            let plane = 32 * 32;
            for (rank, (z0, z1)) in [(0u32, (0usize, 16usize)), (1, (16, 31))] {
                let data = &v.data()[z0 * plane..(z1 + 1) * plane];
                let step = Step {
                    step: t as u64,
                    sim_time: t as f64,
                    dtype: insitu_client::ScalarType::F32,
                    global_dims: [32, 32, 32],
                    brick_offset: [0, 0, z0 as u32],
                    brick_dims: [32, 32, (z1 - z0 + 1) as u32],
                    rank,
                    world_size: 2,
                    spacing: [1.0; 3],
                    origin: [0.0; 3],
                    data: insitu_client::f32_bytes(data),
                    fields: Vec::new(),
                };
                if rank == 0 {
                    ca.push_step(step).await.unwrap();
                } else if let Some(c) = cb.as_mut() {
                    // A hung node does not answer: give it up like a dead one.
                    let pushed =
                        tokio::time::timeout(std::time::Duration::from_secs(2), c.push_step(step))
                            .await;
                    if !matches!(pushed, Ok(Ok(_))) {
                        cb = None;
                    }
                }
            }
            tokio::time::sleep(std::time::Duration::from_secs_f64(interval)).await;
        }
    });
}

#[test]
fn a_restarted_tuner_resumes_without_repeating_trials() {
    let tmp = tempfile::tempdir().unwrap();
    let (rec, st) = (tmp.path().join("rec"), tmp.path().join("state"));
    let series = two_regime_series(tmp.path(), 30, 6);
    let v = viz(&rec, "127.0.0.1:0", tmp.path());
    let listen = format!("127.0.0.1:{}", free_port());
    let slow = |listen: &str| tuner_paced(&st, listen, &v.addr, "size:40kB", PACED, tmp.path());
    let t = slow(&listen);
    let g = tuned_generator(&v.addr, &t.addr, tmp.path());
    let run = replay(
        &series,
        &g.addr,
        &["--sample-every", "3", "--step-interval", "1.5"],
    );
    second_tuning_under_way(&t);
    let before = trials(&st);
    t.kill();
    // While the tuner is away the generator keeps its P_M and keeps producing.
    let (received, kept) = (status(&g.addr).steps_received, status(&g.addr).pm_version);
    assert!(kept >= 1);
    assert!(wait_until(20.0, || status(&g.addr).steps_received > received));
    assert_eq!(status(&g.addr).pm_version, kept);
    assert!(!status(&g.addr).tuner_connected);
    let t = slow(&listen);
    finish(run);
    assert!(wait_until(60.0, || {
        let s = tuner_status(&t.addr);
        !s.tuning && s.retunes >= 1
    }));
    let s = tuner_status(&t.addr);
    let after = trials(&st);
    let unique: BTreeSet<_> = after.iter().collect();
    assert_eq!(unique.len(), after.len(), "a finished trial ran twice");
    assert!(after.len() >= before.len() && after[..before.len()] == before[..]);
    assert!(
        s.trials_reused > 0,
        "the resumed search did not use the persisted trials: {s:?}"
    );
    assert_eq!(
        s.characteristic_steps,
        vec![0, 6],
        "{}",
        std::fs::read_to_string(&t.log).unwrap_or_default()
    );
    eprintln!(
        "restart: {} trials before the kill, {} after; the new process ran {} and reused {}",
        before.len(),
        after.len(),
        s.trials_run,
        s.trials_reused
    );
    flush(&g.addr);
    g.terminate();
    t.terminate();
    v.terminate();
}

#[test]
fn a_generator_that_hangs_then_dies_during_trials_leaves_the_decision_in_force() {
    let tmp = tempfile::tempdir().unwrap();
    let (rec, st) = (tmp.path().join("rec"), tmp.path().join("state"));
    let series = two_regime_series(tmp.path(), 12, 6);
    let v = viz(&rec, "127.0.0.1:0", tmp.path());
    let paced_fast_timeout = PACED.replace("timeout_secs = 60.0", "timeout_secs = 3.0");
    let t = tuner_paced(
        &st,
        "127.0.0.1:0",
        &v.addr,
        "size:100kB",
        &paced_fast_timeout,
        tmp.path(),
    );
    let a = tuned_generator(&v.addr, &t.addr, tmp.path());
    let b = tuned_generator(&v.addr, &t.addr, tmp.path());
    assert!(wait_until(20.0, || tuner_status(&t.addr).nodes_connected == 2));
    let (a_addr, b_addr) = (a.addr.clone(), b.addr.clone());
    let s2 = series.clone();
    let pusher = std::thread::spawn(move || push_two_ranks(&s2, 0..12, &a_addr, &b_addr, 1.5));
    let first = second_tuning_under_way(&t);
    // Node B hangs (SIGSTOP): its trial times out, the tuning is abandoned, the decision in
    // force stays, and the tuning is tried again later.
    let stopped = Command::new("kill")
        .args(["-STOP", &b.child.id().to_string()])
        .status()
        .unwrap();
    assert!(stopped.success());
    assert!(
        wait_until(60.0, || tuner_status(&t.addr).trials_failed >= 1),
        "{:?}",
        tuner_status(&t.addr)
    );
    // No tuning made a decision since (corrections from the production steps may have).
    let tuned = |s: &pb::TunerStatus| s.decisions - s.corrections - s.provisional_decisions;
    assert_eq!(tuned(&tuner_status(&t.addr)), tuned(&first));
    let log = std::fs::read_to_string(&t.log).unwrap();
    assert!(log.contains("timed out after 3 s"), "{log}");
    // Then it dies: its fields are gone, so step 6 (half of it was on B) leaves the set when
    // the re-tuning needs a trial of it (so may step 0, unless every candidate the search asks
    // for on it was measured before), keeping its decision.
    b.kill();
    assert!(
        wait_until(60.0, || {
            let s = tuner_status(&t.addr);
            !s.tuning
                && !s.characteristic_steps.contains(&6)
                && s.characteristic_steps.len() <= 1
                && s.nodes_connected == 1
        }),
        "{:?}\n{}",
        tuner_status(&t.addr),
        std::fs::read_to_string(&t.log).unwrap_or_default()
    );
    pusher.join().unwrap();
    // A tuning on the steps left may decide (it walks from the P_M in force at the chosen
    // precision, not from where the first tuning started); none decided on step 6, whose
    // trials failed and whose node died.
    let s = tuner_status(&t.addr);
    let persisted = state(&st);
    for d in persisted["decisions"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|d| {
            d["pm_version"].as_u64() > Some(first.pm_version)
                && d["corrects"].is_null()
                && d["provisional"] != true
        })
    {
        let steps = d["characteristic_steps"].as_array().unwrap();
        assert!(
            !steps.iter().any(|x| x.as_u64() == Some(6)),
            "{d}\n{s:?}\n{}",
            std::fs::read_to_string(&t.log).unwrap_or_default()
        );
    }
    let ga = status(&a.addr);
    assert_eq!(ga.pm_version, s.pm_version);
    assert!(ga.tuner_connected);
    a.terminate();
    t.terminate();
    v.terminate();
}

#[test]
fn bad_input_is_refused_clearly_and_nothing_is_persisted() {
    let tmp = tempfile::tempdir().unwrap();
    // A bad utility or grid: the daemon does not start and names the key.
    for (flag, problem) in [
        (vec!["--utility", "size:0"], "utility"),
        (vec!["--utility", "size:-2MB"], "utility"),
        (vec!["--utility", "quality:40,size:1MB"], "utility"),
    ] {
        let out = Command::new(bin("tuner-node"))
            .args(["--listen", "127.0.0.1:0", "--state-dir"])
            .arg(tmp.path().join("never"))
            .args(&flag)
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(
            !out.status.success() && err.contains(problem),
            "{flag:?}: {err}"
        );
    }
    let cfg = tmp.path().join("empty-grid.toml");
    std::fs::write(&cfg, "[grid]\nr = \"\"\n").unwrap();
    let out = Command::new(bin("tuner-node"))
        .args(["--config", cfg.to_str().unwrap()])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("grid"), "{err}");
    assert!(!tmp.path().join("never").exists());

    // A node that sends a summary with 63 bins gets an error naming it; nothing is persisted.
    let st = tmp.path().join("state");
    let t = Daemon::start(
        "tuner-node",
        &[
            "--listen",
            "127.0.0.1:0",
            "--state-dir",
            st.to_str().unwrap(),
        ],
        &[],
        tmp.path(),
    );
    let before = std::fs::read(st.join("tuner-state.json")).unwrap();
    let reply = rt().block_on(async {
        let (tx, rx) = tokio::sync::mpsc::channel(8);
        let up = |m: Up| pb::NodeMessage { msg: Some(m) };
        tx.send(up(Up::Hello(pb::NodeHello {
            node_id: "fake".into(),
            ..Default::default()
        })))
        .await
        .unwrap();
        tx.send(up(Up::Summary(pb::StepSummary {
            step: 4,
            world_size: 1,
            histogram: vec![1; 63],
            range_lo: 0.0,
            range_hi: 1.0,
            ..Default::default()
        })))
        .await
        .unwrap();
        let mut c = client(&t.addr).await;
        let mut down = c
            .attach(tokio_stream::wrappers::ReceiverStream::new(rx))
            .await
            .unwrap()
            .into_inner();
        // The budget comes first, at the hello; then the refusal.
        let mut m = down.message().await.unwrap().unwrap();
        if matches!(m.msg, Some(Down::Budget(_))) {
            m = down.message().await.unwrap().unwrap();
        }
        drop(tx);
        m
    });
    match reply.msg {
        Some(Down::Error(e)) => assert!(e.message.contains("63 bins"), "{}", e.message),
        other => panic!("{other:?}"),
    }
    // A stream that does not start with a hello is refused.
    let e = rt().block_on(async {
        let first = pb::NodeMessage {
            msg: Some(Up::Ack(pb::DecisionAck::default())),
        };
        client(&t.addr)
            .await
            .attach(tokio_stream::iter(vec![first]))
            .await
            .unwrap_err()
    });
    assert_eq!(e.code(), tonic::Code::FailedPrecondition, "{e:?}");
    // A decision that was never issued.
    let e = decision(&t.addr, 7).unwrap_err();
    assert_eq!(e.code(), tonic::Code::NotFound);
    assert!(e.message().contains("version 7"), "{}", e.message());
    let s = tuner_status(&t.addr);
    assert_eq!((s.summaries, s.pm_version), (0, 0));
    assert!(s.characteristic_steps.is_empty());
    assert_eq!(std::fs::read(st.join("tuner-state.json")).unwrap(), before);
    t.terminate();
}
