//! The engine's event loop driven by hand: summaries, reports, steering, tunings.

use super::*;
use insitu_core::evaluate::Sizing;
use insitu_core::metrics::Db;
use insitu_tuner::Measurement;

fn summary(step: u64, bin: usize, sigma: u64, version: u64) -> pb::StepSummary {
    let mut histogram = vec![0; BINS];
    histogram[bin] = 100;
    pb::StepSummary {
        step,
        world_size: 1,
        histogram,
        range_lo: 0.0,
        range_hi: 1.0,
        sampled: true,
        pm_version: version,
        sigma_bytes: sigma,
        ..Default::default()
    }
}

/// An engine whose decision v1 (r 64, γ 0.01, predicted q 40 dB) was tuned on step 0,
/// for σ_target 1 000 B.
fn tuned(dir: &std::path::Path) -> Loop {
    tuned_for(dir, "size:1000", 2)
}

/// As [`tuned`] for `utility`, with `time_breaks`.
fn tuned_for(dir: &std::path::Path, utility: &str, time_breaks: u32) -> Loop {
    let cfg = Config {
        state_dir: dir.to_owned(),
        viz: Some("127.0.0.1:1".into()),
        utility: utility.into(),
        time_breaks,
        ..Default::default()
    };
    let mut state = State::with_step_zero();
    let c = Candidate {
        r: 64,
        gamma: 0.01,
        precision: Default::default(),
    };
    let predicted = Measurement {
        r: 64,
        gamma: 0.01,
        precision: Default::default(),
        sigma_paper_bytes: None,
        sizing: Sizing {
            sigma_bytes: 900,
            ..Sizing::default()
        },
        tau_render_secs: 0.0,
        q_db: Db(40.0),
        view_q_db: vec![],
        ssim: None,
    };
    state.decisions.push(Decision {
        pm_version: 1,
        candidate: c,
        old: None,
        characteristic_steps: vec![0],
        predicted,
        reason: "test".into(),
        trigger_step: 0,
        trials: 0,
        trial_secs: 0.0,
        utility_description: "size".into(),
        from_step: 0,
        corrects: None,
        tuned: None,
        forecast_ratio: None,
        scene_version: 0,
        steered: false,
        provisional: false,
    });
    state.validated = vec![0];
    over(cfg, state)
}

/// The engine's loop under `cfg` over `state`, with nothing pending.
fn over(cfg: Config, state: State) -> Loop {
    let resolved = cfg.resolve().unwrap();
    let (engine, _rx) = Engine::new(cfg, resolved, state, |_, _| true);
    Loop {
        engine,
        pending: BTreeMap::new(),
        awaiting: BTreeMap::new(),
        recent: VecDeque::new(),
        dirty: None,
        deferred: Vec::new(),
        slow: (0, 0),
        cut_last: false,
        last_candidate: None,
        missed: None,
    }
}

fn report(step: u64, q: f64) -> pb::QualityReport {
    pb::QualityReport {
        step,
        world_size: 1,
        pm_version: 1,
        q_db: Some(q),
        ..Default::default()
    }
}

#[test]
fn a_production_step_far_below_the_predicted_q_becomes_characteristic() {
    let dir = tempfile::tempdir().unwrap();
    let mut l = tuned(dir.path());
    // Alike and within budget: waits for its q, which is close to the prediction.
    l.summary(1, summary(1, 3, 500, 1));
    assert!(l.dirty.is_none() && l.awaiting.contains_key(&1));
    l.report(&report(1, 38.5));
    assert!(l.dirty.is_none() && l.awaiting.is_empty());
    // 4 dB below (margin 3): characteristic, with the reason.
    l.summary(2, summary(2, 3, 500, 1));
    l.report(&report(2, 36.0));
    let d = l.dirty.clone().unwrap();
    assert_eq!(d.step, 2);
    assert!(
        matches!(&d.cause, Cause::BrokeBudget { why } if why.contains("below the predicted 40.00 dB")),
        "{d:?}"
    );
    assert_eq!(l.engine.state().tracker.step_indices(), vec![0, 2]);
    // Persisted; the decision in force is no longer validated on the set.
    let s = State::load(dir.path()).unwrap().unwrap();
    assert_eq!(
        (s.tracker.step_indices(), s.validated),
        (vec![0, 2], vec![0])
    );
}

#[test]
fn a_step_evicted_during_a_tuning_is_released_after_it() {
    use insitu_proto::pb::tuner_message::Msg as Down;
    let dir = tempfile::tempdir().unwrap();
    let mut l = tuned(dir.path());
    let (tx, mut rx) = tokio::sync::mpsc::channel(16);
    let conn = l.engine.hub.connect("n", tx);
    l.engine.hub.held(conn, 5, 0);
    let released =
        |rx: &mut tokio::sync::mpsc::Receiver<Result<pb::TunerMessage, tonic::Status>>| {
            std::iter::from_fn(|| rx.try_recv().ok())
                .filter_map(Result::ok)
                .filter(|m| {
                    matches!(
                        m.msg,
                        Some(Down::Hold(pb::HoldRequest {
                            step: 5,
                            keep: false
                        }))
                    )
                })
                .count()
        };
    l.engine.counters().tuning = true;
    l.release_evicted(5);
    assert_eq!(
        released(&mut rx),
        0,
        "kept while the tuning may ask trials of it"
    );
    l.engine.counters().tuning = false;
    l.tuning_ended();
    assert_eq!(released(&mut rx), 1, "released once it ended");
    l.engine.hub.held(conn, 5, 0);
    l.release_evicted(5);
    assert_eq!(released(&mut rx), 1, "no tuning: released at once");
}

/// A production step of P_M v1 (r 64, γ 0.01) with σ `sigma`, its node idle after it.
fn made_with_v1(step: u64, sigma: u64) -> pb::StepSummary {
    pb::StepSummary {
        resolution: 64,
        gamma: 0.01,
        begun: step + 1,
        ..summary(step, 3, sigma, 1)
    }
}

/// [`tuned`] with the tuning's size probes on step 0: σ(64, 0.01) = 900 B (the decision's
/// prediction) and σ(64, 0.02) = 450 B.
fn tuned_with_probes(dir: &std::path::Path) -> Loop {
    let l = tuned(dir);
    for (gamma, sigma_bytes) in [(0.01, 900), (0.02, 450)] {
        l.engine.state().size_probes.push(crate::state::SizeProbe {
            step: 0,
            candidate: Candidate {
                r: 64,
                gamma,
                precision: Default::default(),
            },
            sizing: Sizing {
                sigma_bytes,
                tau_secs: 0.01,
                ..Sizing::default()
            },
            trial_secs: 0.01,
            run_by: 0,
            production: false,
        });
    }
    l
}

#[test]
fn still_data_keeps_the_p_m_and_drifting_data_gets_a_correction_from_the_next_step() {
    let dir = tempfile::tempdir().unwrap();
    let mut l = tuned_with_probes(dir.path());
    // Production as the tuning measured it: nothing changes, however long.
    for step in 1..=12 {
        l.summary(1, made_with_v1(step, 900));
    }
    assert_eq!(l.engine.state().decisions.len(), 1);
    assert_eq!(l.engine.status().corrections, 0);
    // σ grows 5 % a step: within the budget at first, then the P_M in force would miss
    // the 950 B plan by the next step, and a correction of v1 lands there.
    let mut sigma = 900.0;
    let mut step = 12;
    while l.engine.state().decisions.len() == 1 && step < 30 {
        step += 1;
        sigma *= 1.05;
        l.summary(1, made_with_v1(step, sigma as u64));
    }
    let s = l.engine.state();
    let d = s.current().unwrap();
    assert_eq!((d.pm_version, d.corrects), (2, Some(1)), "{d:?}");
    assert_eq!(
        d.from_step,
        step + 1,
        "the next step: the node had begun no later one"
    );
    assert_eq!(d.candidate.r, 64);
    assert!(d.candidate.gamma > 0.01, "{d:?}");
    // Planned for at least the latest ratio (the median growth of the window is still
    // that of the still steps): its σ forecast meets the plan.
    let k = d.forecast_ratio.unwrap();
    assert!(k >= (sigma as u64) as f64 / 900.0 - 1e-9, "forecast {k}");
    assert!(d.predicted.sizing.sigma_bytes < 950, "{d:?}");
    assert!(d.reason.contains("correction after step"), "{}", d.reason);
}

const STEERED_TF: &str = r#"{"domain":[0,1],"points":[[0,0,0,0,0],[1,1,0.5,0,0.8]]}"#;

fn steered_tf() -> pb::TransferFunction {
    pb::TransferFunction::from(&insitu_core::TransferFunction::from_json(STEERED_TF, "t").unwrap())
}

fn named(mut s: pb::StepSummary, scene_version: u64) -> pb::StepSummary {
    s.scene_version = scene_version;
    s.fields = vec!["u".into(), "v".into()];
    s
}

#[test]
fn a_steered_scene_is_versioned_pushed_and_tuned_for_afresh_and_a_later_change_supersedes_it() {
    let dir = tempfile::tempdir().unwrap();
    let mut l = tuned(dir.path());
    let mut decisions = l.engine.subscribe();
    l.summary(1, named(summary(1, 3, 900, 1), 0));
    assert_eq!(l.engine.state().tracker.step_indices(), [0]);
    let reply = l
        .steer(pb::SteerRequest {
            tf: Some(steered_tf()),
            tf_name: Some("warm".into()),
            who: "test".into(),
            ..Default::default()
        })
        .unwrap();
    assert_eq!((reply.scene_version, reply.pm_version), (1, 2));
    assert_eq!(
        reply.from_step, 3,
        "two strides past the newest step (no node said `begun`)"
    );
    // Pushed: the P_M in force, carrying the scene.
    let m = decisions.try_recv().unwrap();
    assert_eq!((m.pm_version, m.resolution, m.from_step), (2, 64, 3));
    let scene = m.scene.unwrap();
    assert_eq!(scene.version, 1);
    assert_eq!(scene.tf_name.as_deref(), Some("warm"));
    assert!(m.reason.contains("scene 1 steered by test"), "{}", m.reason);
    {
        let s = l.engine.state();
        assert!(
            s.tracker.steps.is_empty(),
            "the old scene's steps are let go"
        );
        assert_eq!(s.steering.last().unwrap().standing, Standing::Pending);
        // Persisted: a restarted tuner carries the scene on.
        let back = State::load(dir.path()).unwrap().unwrap();
        assert_eq!(back.scene(), s.scene());
    }
    assert_eq!(l.engine.current().unwrap().scene.unwrap().version, 1);
    // Still under the old scene: neither characteristic nor a trigger.
    l.summary(1, named(summary(2, 40, 5000, 1), 0));
    assert!(l.dirty.is_none() && l.engine.state().tracker.steps.is_empty());
    // A second change before any step was made with the first supersedes it.
    let reply = l
        .steer(pb::SteerRequest {
            field: Some("v".into()),
            ..Default::default()
        })
        .unwrap();
    assert_eq!((reply.scene_version, reply.superseded), (2, vec![1]));
    let scene = decisions.try_recv().unwrap().scene.unwrap();
    assert_eq!(
        (
            scene.version,
            scene.field.as_deref(),
            scene.tf_name.as_deref()
        ),
        (2, Some("v"), Some("warm")),
        "cumulative: the transfer function stays"
    );
    // The first step under the new scene applies it and starts the tuning for it.
    l.summary(1, named(summary(4, 10, 700, 3), 2));
    let cause = &l.dirty.as_ref().unwrap().cause;
    assert_eq!(*cause, Cause::First);
    let st = l.engine.status();
    let standings: Vec<&str> = st.steering.iter().map(|r| r.state.as_str()).collect();
    assert_eq!(standings, ["superseded", "applied"]);
    assert_eq!(st.scene.unwrap().version, 2);
}

#[test]
fn a_node_that_attaches_after_a_change_gets_the_decision_before_it_for_the_steps_before_its_switch()
{
    use insitu_proto::pb::tuner_message::Msg as Down;
    let dir = tempfile::tempdir().unwrap();
    let mut l = tuned(dir.path());
    l.summary(1, named(summary(1, 3, 900, 1), 0));
    let reply = l
        .steer(pb::SteerRequest {
            field: Some("v".into()),
            ..Default::default()
        })
        .unwrap();
    assert!(reply.from_step > 0);
    let attach = |pm_version: u64| {
        let (tx, mut rx) = tokio::sync::mpsc::channel(16);
        let conn = l.engine.hub.connect("n", tx);
        l.engine.hello(
            conn,
            &pb::NodeHello {
                pm_version,
                ..Default::default()
            },
        );
        std::iter::from_fn(|| rx.try_recv().ok())
            .filter_map(|m| match m.ok()?.msg {
                Some(Down::Decision(d)) => Some(d),
                _ => None,
            })
            .map(|d| (d.pm_version, d.from_step, d.scene.map(|s| s.version)))
            .collect::<Vec<_>>()
    };
    // A restarted node: v1 for every step before the switch (no scene: the node's own),
    // then the steered v2 from its step.
    assert_eq!(attach(0), [(1, 0, None), (2, reply.from_step, Some(1))]);
    // A node that reconnects holding v1 needs only v2; one holding v2, nothing.
    assert_eq!(attach(1), [(2, reply.from_step, Some(1))]);
    assert_eq!(attach(2), []);
}

#[test]
fn steering_refuses_what_it_cannot_apply_and_changes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let mut l = tuned(dir.path());
    l.summary(1, named(summary(1, 3, 900, 1), 0));
    let before = l.engine.state().clone();
    let refused = |l: &mut Loop, req: pb::SteerRequest| l.steer(req).unwrap_err();
    let e = refused(
        &mut l,
        pb::SteerRequest {
            field: Some("w".into()),
            ..Default::default()
        },
    );
    assert_eq!(e.code(), tonic::Code::InvalidArgument);
    assert!(
        e.message().contains("\"w\" is not one of"),
        "{}",
        e.message()
    );
    let e = refused(
        &mut l,
        pb::SteerRequest {
            utility: Some("size:lots".into()),
            ..Default::default()
        },
    );
    assert!(e.message().starts_with("utility:"), "{}", e.message());
    assert_eq!(*l.engine.state(), before);
    // No node ever attached and no decision: no P_M to carry a scene.
    l.engine.state().decisions.clear();
    let e = refused(
        &mut l,
        pb::SteerRequest {
            tf: Some(steered_tf()),
            ..Default::default()
        },
    );
    assert_eq!(e.code(), tonic::Code::FailedPrecondition);
}

#[test]
fn a_steered_utility_sets_the_budget_and_re_tunes_over_the_characteristic_steps() {
    let dir = tempfile::tempdir().unwrap();
    let mut l = tuned(dir.path());
    let reply = l
        .steer(pb::SteerRequest {
            utility: Some("size:2kB".into()),
            ..Default::default()
        })
        .unwrap();
    assert_eq!((reply.scene_version, reply.pm_version), (0, 0));
    assert!(
        reply.utility_description.contains("2.0 kB") || reply.utility_description.contains("2000"),
        "{}",
        reply.utility_description
    );
    assert_eq!(l.engine.status().sigma_target_bytes, 2000);
    assert!(matches!(
        l.dirty.as_ref().unwrap().cause,
        Cause::Steered { .. }
    ));
    // A restarted tuner keeps it.
    let state = State::load(dir.path()).unwrap().unwrap();
    assert_eq!(state.utility.as_deref(), Some("size:2kB"));
    let cfg = Config {
        state_dir: dir.path().to_owned(),
        utility: "size:1000".into(),
        ..Default::default()
    };
    let resolved = cfg.resolve().unwrap();
    let (engine, _rx) = Engine::new(cfg, resolved, state, |_, _| true);
    assert_eq!(engine.status().sigma_target_bytes, 2000);
}

#[test]
fn a_newer_characteristic_step_cuts_a_running_tuning_short_but_not_twice_nor_the_first() {
    let cut = |decided: bool, cut_last: bool| {
        let dir = tempfile::tempdir().unwrap();
        let mut l = tuned(dir.path());
        if !decided {
            l.engine.state().decisions.clear();
        }
        l.cut_last = cut_last;
        l.engine.counters().tuning = true;
        // Far from step 0's histogram: characteristic.
        l.summary(1, summary(5, 40, 500, 1));
        assert!(l.dirty.is_some());
        l.engine.superseded.load(Ordering::SeqCst)
    };
    assert!(cut(true, false));
    assert!(!cut(true, true), "never twice in a row");
    assert!(!cut(false, false), "the first tuning runs to its decision");
}

#[test]
fn a_budget_break_retunes_once_and_none_while_a_tuning_is_due() {
    let dir = tempfile::tempdir().unwrap();
    let mut l = tuned(dir.path());
    // σ 1 000 B ≥ σ_target 1 000 B: breaks the budget (strict, Eq. 1).
    l.summary(1, summary(1, 3, 1000, 1));
    assert!(matches!(
        l.dirty.as_ref().unwrap().cause,
        Cause::BrokeBudget { .. }
    ));
    l.dirty = None;
    // Breaking it again before the re-tuning has taken step 1 into account forces nothing.
    l.summary(2, summary(2, 3, 5000, 1));
    assert!(l.dirty.is_none());
    assert_eq!(l.engine.state().tracker.step_indices(), vec![0, 1]);
    // Steps made with an older version are not held against the budget.
    let dir = tempfile::tempdir().unwrap();
    let mut l = tuned(dir.path());
    l.summary(1, summary(1, 3, 5000, 0));
    assert!(l.dirty.is_none());
    // Nor while a tuning is pending: a new characteristic step is waiting for one.
    l.summary(2, summary(2, 40, 500, 1));
    let c = &l.dirty.as_ref().unwrap().cause;
    assert!(matches!(c, Cause::NewCharacter { .. }), "{c:?}");
    l.summary(3, summary(3, 3, 5000, 1));
    assert_eq!(l.engine.state().tracker.step_indices(), vec![0, 2]);
}

/// A step made with the tuned candidate (r 64, γ 0.01, planned at 900 B) and `sigma`
/// bytes, made with `version`, in histogram bin 3.
fn made(step: u64, sigma: u64, version: u64) -> pb::StepSummary {
    pb::StepSummary {
        resolution: 64,
        gamma: 0.01,
        ..summary(step, 3, sigma, version)
    }
}

/// A step whose σ is 1.5× what its decision planned is characteristic though its
/// histogram is the characteristic step's and it is within the budget (a new character
/// by structure); one at 1.44× is not. While the tuning for it is due, a step within 1.5× of
/// its σ changes nothing, and one at 1.5× of it or more is characteristic too: the data
/// changed character again, which a tuning for the earlier step would not see.
#[test]
fn a_step_far_over_its_plan_is_a_new_character_whatever_its_histogram() {
    let dir = tempfile::tempdir().unwrap();
    let mut l = tuned_for(dir.path(), "size:5000", 2);
    l.summary(1, made(1, 1300, 1));
    assert!(l.dirty.is_none(), "{:?}", l.dirty);
    l.summary(2, made(2, 1350, 1));
    let d = l.dirty.clone().unwrap();
    assert_eq!(
        (d.step, d.cause.clone()),
        (
            2,
            Cause::SizeMiss {
                sigma_bytes: 1350,
                planned_bytes: 900.0,
                threshold: 1.5
            }
        )
    );
    assert_eq!(l.engine.state().tracker.step_indices(), vec![0, 2]);
    // The next step alike, while that tuning is due, changes nothing.
    l.summary(3, made(3, 2000, 1));
    assert_eq!(l.dirty.as_ref().map(|d| d.step), Some(2));
    assert_eq!(l.engine.state().tracker.step_indices(), vec![0, 2]);
    // One at 1.5× step 2's σ with the same P_M: a new character again, tuned for with it.
    l.summary(4, made(4, 2025, 1));
    let d = l.dirty.clone().unwrap();
    assert_eq!(
        (d.step, d.cause),
        (
            4,
            Cause::SizeJump {
                sigma_bytes: 2025,
                than_step: 2,
                than_bytes: 1350,
                threshold: 1.5
            }
        )
    );
    assert_eq!(l.engine.state().tracker.step_indices(), vec![0, 2, 4]);
    // Measured against the newest such step now: 1.49× of step 4's changes nothing.
    l.summary(5, made(5, 3000, 1));
    assert_eq!(l.dirty.as_ref().map(|d| d.step), Some(4));
}

/// A step made under a correction of the tuned decision that breaks the budget makes no
/// tuning due (the next correction takes it up); one made with the tuned decision does.
#[test]
fn a_budget_broken_under_a_correction_is_left_to_the_corrections() {
    let dir = tempfile::tempdir().unwrap();
    let mut l = tuned(dir.path());
    {
        let mut s = l.engine.state();
        let mut d = s.current().unwrap().clone();
        d.pm_version = 2;
        d.candidate.gamma = 0.02;
        d.corrects = Some(1);
        d.predicted.sizing.sigma_bytes = 800;
        s.decisions.push(d);
    }
    l.summary(
        1,
        pb::StepSummary {
            gamma: 0.02,
            ..made(1, 1100, 2)
        },
    );
    assert!(l.dirty.is_none(), "{:?}", l.dirty);
    l.summary(2, made(2, 1100, 1));
    let d = l.dirty.clone().unwrap();
    assert!(
        matches!(&d.cause, Cause::BrokeBudget { why } if why.contains("σ 1100 B")),
        "{d:?}"
    );
}

/// A τ over τ_target re-tunes only as the `time_breaks`-th such step in a row (made with
/// the version in force); a step within the budget between them starts the count again.
#[test]
fn a_time_break_retunes_only_when_it_repeats() {
    let timed = |step, tau_secs| pb::StepSummary {
        tau_secs,
        ..summary(step, 3, 500, 1)
    };
    let dir = tempfile::tempdir().unwrap();
    let mut l = tuned_for(dir.path(), "size:1000,time:0.05", 2);
    l.summary(1, timed(1, 0.08));
    assert!(l.dirty.is_none());
    l.summary(2, timed(2, 0.01));
    l.summary(3, timed(3, 0.05));
    assert!(l.dirty.is_none(), "one slow step after a fast one");
    l.summary(4, timed(4, 0.07));
    let t = l.dirty.as_ref().unwrap();
    assert_eq!(
        t.cause,
        Cause::BrokeBudget {
            why: "τ 0.0700 s ≥ τ_target 0.05 s, 2 steps in a row".into()
        }
    );
    assert_eq!(t.step, 4);
    assert_eq!(l.engine.state().tracker.step_indices(), vec![0, 4]);
    // Steps made with an older version neither count nor break a run.
    let dir = tempfile::tempdir().unwrap();
    let mut l = tuned_for(dir.path(), "size:1000,time:0.05", 2);
    l.summary(1, timed(1, 0.08));
    l.summary(
        2,
        pb::StepSummary {
            pm_version: 0,
            ..timed(2, 0.01)
        },
    );
    l.summary(3, timed(3, 0.09));
    assert_eq!(l.dirty.as_ref().map(|d| d.step), Some(3));
    // time_breaks = 1: every slow step re-tunes, as σ does.
    let dir = tempfile::tempdir().unwrap();
    let mut l = tuned_for(dir.path(), "time:0.05", 1);
    l.summary(1, timed(1, 0.06));
    let c = &l.dirty.as_ref().unwrap().cause;
    assert_eq!(
        c,
        &Cause::BrokeBudget {
            why: "τ 0.0600 s ≥ τ_target 0.05 s".into()
        }
    );
}

/// A decision applies from the first step on the stride that no node had begun when the
/// newest step was summarised: one stride past it when one idle node serves the world,
/// past the steps a node had begun, one stride more for several nodes and past every step any
/// of them had received, two strides without the nodes' `begun`; a late summary of an older
/// step changes nothing.
#[test]
fn decisions_apply_from_the_first_step_no_node_had_begun() {
    let mut p = Progress::default();
    assert_eq!(p.decision_start(), 0);
    // An older node (no `begun`): two strides.
    assert_eq!(p.saw(2000, 0, 0, 1), 2000);
    assert_eq!(p.decision_start(), 2002);
    // One node, idle after step 2100 (stride 100): the next step.
    assert_eq!(p.saw(2100, 2101, 0, 1), 2100);
    assert_eq!(p.decision_start(), 2200);
    assert_eq!(p.saw(2000, 2001, 0, 1), 2100, "another rank's older step");
    assert_eq!(p.decision_start(), 2200);
    // The node had begun step 2200 already: the one after.
    assert_eq!(p.saw(2100, 2201, 0, 1), 2100);
    assert_eq!(p.decision_start(), 2300);
    // Two nodes summarised step 2200, neither had begun more: one stride of margin.
    p.saw(2200, 2201, 0, 1);
    p.saw(2200, 2201, 0, 2);
    assert_eq!(p.decision_start(), 2400);
    // A provisional decision, right after a spread world's first step: 4 more strides for
    // what is pushed while it travels, and past every step received (queued behind a wait).
    assert_eq!(p.spread_start(), 2400 + 400);
    p.saw(2200, 2201, 2601, 2);
    assert_eq!(p.spread_start(), 2700 + 400);
    // The newest step summarised by one of the two nodes only: still a world of several.
    p.saw(2300, 2301, 2601, 1);
    assert_eq!(p.spread_start(), 2700 + 400);
    // A node alone applies from its own first step not begun: what it received is no matter.
    let mut one = Progress::default();
    one.saw(100, 101, 900, 1);
    one.saw(200, 201, 900, 1);
    assert_eq!(one.decision_start(), 300);
    assert_eq!(one.spread_start(), 300);
    // Step indices are the nodes' to choose: a huge jump saturates, it does not wrap.
    assert_eq!(p.saw(u64::MAX - 1, u64::MAX, 0, 1), u64::MAX - 1);
    assert_eq!(p.decision_start(), u64::MAX);
}

/// Rank `rank` of 2 of `step`, made at r `r` (γ 0.013) with decision `version`, from connection
/// `conn`, at σ `sigma` bytes.
fn rank_of_two(step: u64, rank: u32, r: u32, version: u64, sigma: u64) -> pb::StepSummary {
    pb::StepSummary {
        rank,
        world_size: 2,
        resolution: r,
        gamma: 0.013,
        precision_bits: 8,
        begun: step + 1,
        ..summary(step, 3, sigma, version)
    }
}

#[test]
fn a_world_spread_over_nodes_keeps_the_budget_before_the_first_tuning() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = Config {
        state_dir: dir.path().to_owned(),
        utility: "size:20000".into(),
        ..Default::default()
    };
    let mut l = over(cfg, State::new(insitu_tuner::live::Tracker::new(0.15, 4)));
    let current = |l: &Loop| l.engine.state().current().cloned();
    // Step 0's two ranks from two nodes: 63 kB against 20 kB (3.15×) at r 256 lowers r to
    // 256 · (0.9 / 3.15)^(2/3) = 111 → 96, γ and precision kept, from a step no node began.
    l.summary(1, rank_of_two(0, 0, 256, 0, 40_000));
    assert!(current(&l).is_none(), "one rank is not a step");
    l.summary(2, rank_of_two(0, 1, 256, 0, 23_000));
    let d = current(&l).expect("a provisional decision");
    assert!(d.provisional && d.corrects.is_none() && !d.steered, "{d:?}");
    assert_eq!(
        (d.pm_version, d.candidate.r, d.candidate.gamma),
        (1, 96, 0.013)
    );
    assert_eq!(d.candidate.precision.bits(), 8);
    assert_eq!(d.old.map(|c| c.r), Some(256));
    assert_eq!(d.from_step, l.engine.spread_start());
    assert!(d.from_step >= 2, "step 1 may have begun: {}", d.from_step);
    assert!(d.reason.contains("2 ranks on 2 nodes"), "{}", d.reason);
    assert!(l.engine.state().tuned().is_none());
    assert_eq!(l.engine.status().provisional_decisions, 1);
    // A step made before it applied, over the budget too: already taken up.
    l.summary(1, rank_of_two(1, 0, 256, 0, 40_000));
    l.summary(2, rank_of_two(1, 1, 256, 0, 23_000));
    assert_eq!(current(&l).map(|d| d.pm_version), Some(1));
    // Under it, 1.5× over: lowered again (96 · (0.9 / 1.5)^(2/3) = 68.3 → 64); 1.2× over
    // afterwards is left to the tuning.
    l.summary(1, rank_of_two(2, 0, 96, 1, 15_000));
    l.summary(2, rank_of_two(2, 1, 96, 1, 15_000));
    let d = current(&l).unwrap();
    assert_eq!((d.pm_version, d.candidate.r, d.provisional), (2, 64, true));
    l.summary(1, rank_of_two(3, 0, 64, 2, 12_000));
    l.summary(2, rank_of_two(3, 1, 64, 2, 12_000));
    assert_eq!(current(&l).map(|d| d.pm_version), Some(2));
    // The controller's forecast leaves the provisional steps out (their r is off the grid).
    let observed: Vec<u64> = l.engine.control().observations().map(|o| o.step).collect();
    assert_eq!(observed, vec![0, 1]);
    // A world whose ranks are all on one node: that node keeps the budget itself.
    l.summary(1, rank_of_two(4, 0, 64, 2, 40_000));
    l.summary(1, rank_of_two(4, 1, 64, 2, 40_000));
    assert_eq!(current(&l).map(|d| d.pm_version), Some(2));
    // After a tuning's decision, production steps are the controller's, not this rule's.
    let tuned = Decision {
        pm_version: 3,
        provisional: false,
        characteristic_steps: vec![0],
        reason: "tuned".into(),
        ..d
    };
    l.engine.state().decisions.push(tuned);
    l.summary(1, rank_of_two(5, 0, 64, 3, 40_000));
    l.summary(2, rank_of_two(5, 1, 64, 3, 40_000));
    assert!(current(&l).is_some_and(|d| d.pm_version >= 3 && !d.provisional));
    assert_eq!(l.engine.status().provisional_decisions, 2);
}
