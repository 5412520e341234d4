//! The controller's rules on made-up surfaces and series.

use super::*;
use insitu_core::vdi::Precision;

pub(super) fn c(r: u32, gamma: f32) -> Candidate {
    Candidate {
        r,
        gamma,
        precision: Default::default(),
    }
}

/// σ = 1e6 · (r / 256)² · (0.01 / γ) bytes: the power law the surface is built to follow.
pub(super) fn law(c: Candidate) -> f64 {
    1e6 * (f64::from(c.r) / 256.0).powi(2) * (0.01 / f64::from(c.gamma))
}

pub(super) fn surface_of(cs: &[Candidate]) -> Surface {
    Surface::new(cs.iter().map(|&c| Point {
        candidate: c,
        sigma_bytes: law(c),
        tau_secs: 0.1,
    }))
}

/// γ number `i` of [`grid`] (as the grid holds it, bit for bit).
pub(super) fn g(i: u8) -> f32 {
    f32::from(i) * 0.005
}

pub(super) fn grid() -> ParamGrid {
    ParamGrid {
        rs: vec![64, 128, 192, 256],
        gammas: (1..=40).map(g).collect(),
        precisions: vec![Default::default()],
    }
}

fn observed(ctl: &mut Controller, step: u64, at: Candidate, k: f64) {
    ctl.observe(Observation {
        planned_sigma_bytes: None,
        step,
        candidate: at,
        sigma_bytes: (law(at) * k) as u64,
        tau_secs: 0.1,
    });
}

#[test]
fn still_data_changes_nothing() {
    let s = surface_of(&[c(256, g(2)), c(256, g(4)), c(192, g(4))]);
    // Budget: the tuned P_M (256, g(2)) at 1 MB sits just under a 1.06 MB plan.
    let mut ctl = Controller::new(Budgets::size(1_120_000), 0.05, grid());
    let tuned = c(256, g(2));
    for step in 0..20 {
        observed(&mut ctl, step * 10, tuned, 1.0);
        assert_eq!(ctl.correct(&s, tuned, tuned, step * 10 + 10), None);
    }
    let f = ctl.forecast(&s, 400).unwrap();
    assert!(
        (f.sigma - 1.0).abs() < 1e-6 && f.sigma_growth_per_step == 1.0,
        "{f:?}"
    );
}

/// On slowly drifting data (σ at every candidate growing 1 % a step, with ±3 % of noise
/// per step) the `P_M` changes a few times per 100 steps and r fewer times than γ,
/// while every step keeps the budget.
#[test]
fn slow_drift_changes_the_p_m_rarely() {
    let rs = [64u32, 128, 192, 256];
    let s = surface_of(
        &rs.iter()
            .flat_map(|&r| [g(1), g(2), g(4), g(8), g(16), g(32)].map(|x| c(r, x)))
            .collect::<Vec<_>>(),
    );
    let budget = 1_120_000.0;
    let mut ctl = Controller::new(Budgets::size(budget as u64), 0.05, grid());
    let tuned = c(256, g(2));
    let mut current = tuned;
    let (mut changes, mut r_changes) = (0, 0);
    for step in 0..100u64 {
        // A fixed pattern of noise within ±3 %.
        let noise = 1.0 + 0.03 * ((step * 7919 % 13) as f64 / 6.0 - 1.0);
        let k = 1.01f64.powi(step as i32) * noise;
        assert!(
            law(current) * k < budget,
            "step {step}: {current:?} at k {k:.3}"
        );
        observed(&mut ctl, step, current, k);
        if let Some(p) = ctl.correct(&s, tuned, current, step + 1) {
            changes += 1;
            r_changes += usize::from(p.candidate.r != current.r);
            current = p.candidate;
        }
    }
    // σ grows 2.7× over the run: γ alone absorbs 1.33× at a resolution before r falls.
    assert!(changes <= 5, "{changes} changes");
    assert!(
        r_changes <= 2 && r_changes < changes,
        "{r_changes} of {changes}"
    );
}

/// A step over the budget makes the next plans allow for how far it exceeded what its
/// decision planned (the model's miss); each step within the budget halves the excess;
/// steps within the budget (still data) never set one, and a step without a known plan
/// does not either.
#[test]
fn a_step_over_the_budget_tightens_the_plans_until_steps_land_within_it() {
    let s = surface_of(&[c(256, g(2)), c(256, g(4)), c(128, g(2))]);
    let tuned = c(256, g(2));
    let step = |step, sigma_bytes, planned| Observation {
        step,
        candidate: tuned,
        sigma_bytes,
        tau_secs: 0.1,
        planned_sigma_bytes: planned,
    };
    let mut ctl = Controller::new(Budgets::size(1_120_000), 0.05, grid());
    let mut blind = Controller::new(Budgets::size(1_120_000), 0.05, grid());
    for k in 0..3 {
        ctl.observe(step(k, 1_000_000, Some(1_000_000.0)));
        blind.observe(step(k, 1_000_000, None));
        assert_eq!((ctl.miss(), blind.miss()), (1.0, 1.0));
    }
    // Planned at 1.0 MB (the model, law(tuned) = 1 MB), made 1.5 MB: a miss of 1.5.
    ctl.observe(step(3, 1_500_000, Some(1_000_000.0)));
    blind.observe(step(3, 1_500_000, None));
    assert!((ctl.miss() - 1.5).abs() < 1e-9, "{}", ctl.miss());
    assert_eq!(blind.miss(), 1.0, "no plan known: no miss");
    let plan = 0.95 * 1_120_000.0;
    let tight = ctl.correct(&s, tuned, tuned, 4).unwrap();
    let loose = blind.correct(&s, tuned, tuned, 4).unwrap();
    assert!(tight.sigma_bytes <= plan / 1.5, "{tight:?}");
    assert!(
        loose.sigma_bytes > plan / 1.5 && loose.sigma_bytes <= plan,
        "{loose:?}"
    );
    // Within the budget again: 1.25, then 1.125.
    ctl.observe(step(4, 700_000, Some(700_000.0)));
    assert!((ctl.miss() - 1.25).abs() < 1e-9);
    ctl.observe(step(5, 700_000, None));
    assert!((ctl.miss() - 1.125).abs() < 1e-9);
}

/// The miss is the model's: a step past the horizon its plan was made for sets none (its
/// excess is growth), and the `P_M` in force, read from its own σ, is not held to it.
#[test]
fn the_miss_is_the_models_not_the_growth_past_a_plan_nor_the_p_m_in_forces() {
    let s = surface_of(&[c(256, g(2)), c(256, g(4)), c(128, g(2))]);
    let tuned = c(256, g(2));
    let step = |step, sigma_bytes| Observation {
        step,
        candidate: tuned,
        sigma_bytes,
        tau_secs: 0.1,
        planned_sigma_bytes: Some(700_000.0),
    };
    let mut ctl = Controller::new(Budgets::size(1_120_000), 0.05, grid());
    for k in 0..HORIZON {
        ctl.observe(step(k, 700_000));
    }
    // The horizon's steps were planned at 700 kB; the next, over the budget, is past it.
    ctl.observe(step(HORIZON, 1_200_000));
    assert_eq!(ctl.miss(), 1.0);
    // A miss set by a new candidate's first step: the P_M in force at 70 % of the budget
    // is not at risk, though 70 % × 1.5 would be.
    let mut ctl = Controller::new(Budgets::size(1_000_000), 0.05, grid());
    let other = c(128, g(2));
    ctl.observe(Observation {
        candidate: other,
        ..step(0, 1_500_000)
    });
    ctl.observe(Observation {
        planned_sigma_bytes: None,
        ..step(1, 700_000)
    });
    assert!(ctl.miss() > 1.2);
    assert_eq!(ctl.correct(&s, tuned, tuned, 2), None);
}

#[test]
fn growth_is_forecast_and_the_p_m_stepped_to_meet_the_budget() {
    let s = surface_of(&[c(256, g(2)), c(256, g(4))]);
    let mut ctl = Controller::new(Budgets::size(1_120_000), 0.05, grid());
    let tuned = c(256, g(2));
    // σ grows 10 % per step of 10: k = 1.1^(n).
    for n in 0..4 {
        observed(&mut ctl, n * 10, tuned, 1.1f64.powi(n as i32));
    }
    let f = ctl.forecast(&s, 40).unwrap();
    assert!((f.sigma_now - 1.1f64.powi(3)).abs() < 1e-3, "{f:?}");
    assert!(
        (f.sigma - 1.1f64.powi(4)).abs() < 1e-3,
        "one step ahead: {f:?}"
    );
    // Planned for the next step alone (no horizon): at r 256, 1e6·0.01/γ·1.4641 ≤ 1.064e6
    // needs γ ≥ 0.0138: the grid's next γ, 0.015.
    ctl.horizon = 0;
    let p = ctl.correct(&s, tuned, tuned, 40).unwrap();
    assert_eq!(p.candidate, c(256, g(3)));
    assert!(p.feasible && p.sigma_bytes <= 0.95 * 1_120_000.0);
    // Planned to hold 8 steps (of 10), or until σ has grown 1.6×, whichever comes first: by
    // step 120 k would be 1.1^12 = 3.14, where only r 128 holds; σ grows 1.6× in
    // ln 1.6 / (ln 1.1 / 10) = 49.3 steps, so the plan is for step 90, k = 1.1^9 = 2.36:
    // r 256 would need γ ≥ 0.0222, beyond its span; r 192 γ 0.015 holds (884 kB).
    ctl.horizon = 8;
    let p = ctl.correct(&s, tuned, tuned, 40).unwrap();
    assert_eq!((p.candidate, p.forecast.at), (c(192, g(3)), 90), "{p:?}");
    let k = 1.1f64.powi(9);
    assert!(
        (p.sigma_bytes - 1e6 * 0.5625 * (0.01 / 0.015) * k).abs() < 1.0,
        "{p:?}"
    );
    // Without the bound on growth, the plan is for all 8 steps: r 256 and r 192 would need γ
    // beyond their spans, r 128 at the tuned γ holds (785 kB).
    ctl.plan_growth = f64::INFINITY;
    let p = ctl.correct(&s, tuned, tuned, 40).unwrap();
    assert_eq!((p.candidate, p.forecast.at), (c(128, g(2)), 120), "{p:?}");
    assert!(
        (p.sigma_bytes - 250_000.0 * 1.1f64.powi(12)).abs() < 1.0,
        "{p:?}"
    );
    // 3 % more than the model still fits the plan: no change.
    let mut ctl = Controller::new(Budgets::size(1_120_000), 0.05, grid());
    observed(&mut ctl, 0, tuned, 1.03);
    assert_eq!(ctl.correct(&s, tuned, tuned, 10), None);
}

/// The bound on growth shortens plans only where σ grows fast: 4–6 % a step (Gray–Scott 128³
/// in its bursts) grows at most 1.59× over the 8-step horizon, under `PLAN_GROWTH`, and the
/// plan is for 8 steps on; 12 % a step (the growing series) reaches 1.6× in
/// ln 1.6 / ln 1.12 = 4.1 steps, so the plan is for 5 steps on.
#[test]
fn slow_drift_plans_for_the_horizon_and_fast_growth_for_its_growth() {
    let s = surface_of(&[c(256, g(2)), c(256, g(4)), c(128, g(2))]);
    let tuned = c(256, g(2));
    for (rate, ahead) in [(1.04f64, HORIZON), (1.06, HORIZON), (1.12, 5)] {
        let mut ctl = Controller::new(Budgets::size(1_120_000), 0.05, grid());
        // Six steps growing up to the budget (1.12 MB) at the tuned P_M: the next is at risk.
        let steps = 6u64;
        let start = 1.12 / rate.powi(steps as i32 - 1);
        for n in 0..steps {
            observed(&mut ctl, n, tuned, start * rate.powi(n as i32));
        }
        let p = ctl.correct(&s, tuned, tuned, steps).unwrap();
        assert_eq!(p.forecast.at, steps + ahead, "{rate}: {p:?}");
    }
}

#[test]
fn the_resolution_drops_when_gamma_alone_would_go_too_far() {
    let s = surface_of(&[c(256, g(2)), c(256, g(4)), c(128, g(2))]);
    let mut ctl = Controller::new(Budgets::size(1_120_000), 0.05, grid());
    let tuned = c(256, g(2));
    // σ at 6× the model: with γ up to the grid's next (0.015), r 256 (needs γ 0.056) and
    // r 192 (0.032) miss the plan; r 128 (0.014) meets it.
    observed(&mut ctl, 0, tuned, 6.0);
    let p = ctl.correct(&s, tuned, tuned, 10).unwrap();
    assert_eq!(p.candidate, c(128, g(3)));
    // Beyond every span: the largest r with any γ that meets the plan (r 128, γ ≥ 0.141).
    let mut ctl = Controller::new(Budgets::size(1_120_000), 0.05, grid());
    observed(&mut ctl, 0, tuned, 60.0);
    let p = ctl.correct(&s, tuned, tuned, 10).unwrap();
    assert_eq!(p.candidate, c(128, g(29)), "{p:?}");
    // Far beyond: the coarsest candidate, flagged as not meeting the plan.
    observed(&mut ctl, 10, tuned, 1e6);
    let p = ctl.correct(&s, tuned, tuned, 20).unwrap();
    assert_eq!((p.candidate, p.feasible), (c(64, g(40)), false));
}

/// γ may rise by the factor r would fall to the next lower resolution: at r 128 of
/// 64…256 that is 2, so a field grown 25× keeps r 128 with γ 1.5× the tuned one instead
/// of halving r (a span of 1.3 at every resolution would choose r 64 at γ 0.015).
#[test]
fn gamma_absorbs_what_lies_between_a_resolution_and_the_next_lower() {
    let rs = grid().rs;
    let spans = rs.iter().map(|&r| gamma_span(&rs, r)).collect::<Vec<_>>();
    assert_eq!(spans, [2.0, 2.0, 1.5, 256.0 / 192.0]);
    assert_eq!(gamma_span(&[256], 256), GAMMA_SPAN);
    let s = surface_of(&[c(256, g(2)), c(256, g(8)), c(128, g(4)), c(64, g(2))]);
    let mut ctl = Controller::new(Budgets::size(1_120_000), 0.05, grid());
    let tuned = c(256, g(8));
    // k = 25 against a 1.064 MB plan: r 256 (γ ≤ 0.053) and r 192 (γ ≤ 0.06) miss it;
    // r 128 meets it from γ 0.0587 (≤ 0.08).
    observed(&mut ctl, 0, tuned, 25.0);
    let p = ctl.correct(&s, tuned, tuned, 10).unwrap();
    assert_eq!(p.candidate, c(128, g(12)), "{p:?}");
    assert!(p.feasible && p.sigma_bytes <= 1_064_000.0, "{p:?}");
}

#[test]
fn a_shrinking_field_steps_back_only_past_the_hysteresis_and_never_past_the_tuned_resolution() {
    let s = surface_of(&[c(256, g(2)), c(256, g(4)), c(192, g(1))]);
    let mut ctl = Controller::new(Budgets::size(1_120_000), 0.05, grid());
    let tuned = c(256, g(2));
    let current = c(256, g(4));
    // At γ 0.02 the field measures k = 1.05: the tuned γ 0.01 would forecast 1.05 MB, under
    // the 1.064 MB plan but not by the hysteresis: stay.
    observed(&mut ctl, 0, current, 1.05);
    assert_eq!(ctl.correct(&s, tuned, current, 10), None);
    // k = 0.5: the tuned γ fits with room; back to it, and no finer, as γ 0.01 is the
    // finest measured at r 256.
    observed(&mut ctl, 10, current, 0.5);
    let p = ctl.correct(&s, tuned, current, 20).unwrap();
    assert_eq!(p.candidate, tuned);
    // With γ 0.005 measured at r 256 too, and k = 0.4: the finer γ fits (0.4 × 2 MB), at
    // the tuned resolution, not a finer one.
    let s = surface_of(&[c(256, g(1)), c(256, g(2)), c(256, g(4))]);
    let mut ctl = Controller::new(Budgets::size(1_120_000), 0.05, grid());
    observed(&mut ctl, 0, current, 0.4);
    let p = ctl.correct(&s, tuned, current, 10).unwrap();
    assert_eq!(p.candidate, c(256, g(1)), "{p:?}");
}

#[test]
fn a_time_budget_is_planned_for_the_slowest_recent_step() {
    // τ = 0.1 s · (r / 256)², flat in γ.
    let tau = |r: u32| 0.1 * (f64::from(r) / 256.0).powi(2);
    let s = Surface::new([256, 128].map(|r| Point {
        candidate: c(r, g(2)),
        sigma_bytes: 1e3,
        tau_secs: tau(r),
    }));
    let mut ctl = Controller::new(Budgets::time(0.1), 0.05, grid());
    let tuned = c(256, g(2));
    for (step, t) in [(0, 0.08), (1, 0.12), (2, 0.09)] {
        ctl.observe(Observation {
            planned_sigma_bytes: None,
            step,
            candidate: tuned,
            sigma_bytes: 1000,
            tau_secs: t,
        });
    }
    let p = ctl.correct(&s, tuned, tuned, 3).unwrap();
    assert!((p.forecast.tau - 1.2).abs() < 1e-9, "{:?}", p.forecast);
    // r 256 at 1.2 × 0.1 s misses the 0.095 s plan whatever γ; r 192: 0.0675 s, at the
    // finest γ measured (0.01; nothing below it is extrapolated).
    assert_eq!(p.candidate, c(192, g(2)));
    assert!((p.tau_secs - 1.2 * tau(192)).abs() < 1e-9);
}

/// τ grows with the data, as far as σ shows it grows: the slowest step of the window is
/// carried forward to the step planned for by τ's own trend (the Theil–Sen slope over the
/// window), bounded by σ's growth; on still data a run of slower timings is noise and
/// is not extrapolated.
#[test]
fn a_time_budget_forecasts_growth_that_sigma_confirms_and_no_more() {
    let tuned = c(256, g(2));
    let s = Surface::new([Point {
        candidate: tuned,
        sigma_bytes: law(tuned),
        tau_secs: 0.05,
    }]);
    let run = |sigma_growth: f64, tau_of: &dyn Fn(u64) -> f64| {
        let mut ctl = Controller::new(Budgets::time(0.1), 0.05, grid());
        for step in 0..6 {
            ctl.observe(Observation {
                planned_sigma_bytes: None,
                step,
                candidate: tuned,
                sigma_bytes: (law(tuned) * sigma_growth.powi(step as i32)) as u64,
                tau_secs: tau_of(step),
            });
        }
        ctl.forecast(&s, 8).unwrap()
    };
    // σ grows 10 % a step, τ 5 %: τ's own growth, from the newest step (k 1.05⁵) three
    // steps on.
    let f = run(1.1, &|step| 0.05 * 1.05f64.powi(step as i32));
    assert!((f.tau_growth_per_step - 1.05).abs() < 1e-9, "{f:?}");
    assert!((f.tau - 1.05f64.powi(8)).abs() < 1e-9, "{f:?}");
    // The same with ±20 % of noise on τ: the slowest step, grown to step 8.
    let noise = [1.0, 1.2, 0.85, 1.15, 0.8, 1.0];
    let f = run(1.1, &|step| {
        0.05 * 1.05f64.powi(step as i32) * noise[step as usize]
    });
    assert!((1.0..1.1).contains(&f.tau_growth_per_step), "growth {f:?}");
    let slowest = (0..6u64)
        .map(|i| {
            1.05f64.powi(i as i32) * noise[i as usize] * f.tau_growth_per_step.powi(8 - i as i32)
        })
        .fold(0.0, f64::max);
    assert!((f.tau - slowest).abs() < 1e-9, "{f:?} vs {slowest}");
    // τ growing 20 % a step where σ grows 10 %: no more than σ's growth.
    let f = run(1.1, &|step| 0.05 * 1.2f64.powi(step as i32));
    assert!((f.tau_growth_per_step - 1.1).abs() < 1e-6, "{f:?}");
    // Still data (σ constant) with timings that happen to rise: no growth, the slowest.
    let f = run(1.0, &|step| {
        [0.04, 0.045, 0.05, 0.055, 0.06, 0.065][step as usize]
    });
    assert_eq!(f.tau_growth_per_step, 1.0, "{f:?}");
    assert!((f.tau - 0.065 / 0.05).abs() < 1e-9, "{f:?}");
}

/// A resolution left for a coarser one is taken back only when its own timing, grown as
/// σ has grown since, clears the plan: on a growing field the timing it had steps ago
/// says too little, also when the window's timings do not show the growth; on still data
/// the same timing takes it back.
#[test]
fn a_resolution_left_while_the_field_grew_is_not_taken_back_on_its_old_timing() {
    let (fine, coarse) = (c(128, g(2)), c(64, g(2)));
    let s = Surface::new(
        [(fine, 0.05), (coarse, 0.02)].map(|(candidate, tau_secs)| Point {
            candidate,
            sigma_bytes: law(candidate),
            tau_secs,
        }),
    );
    let run = |tau_growth: f64, sigma_growth: f64| {
        let mut ctl = Controller::new(Budgets::time(0.1), 0.05, grid());
        // r 128 at step 0 (k 1.6), then ten steps at r 64 (k 0.5, τ growing by
        // `tau_growth` a step, σ by `sigma_growth`): step 0 has left the window of 8.
        let at = |step: u64, candidate: Candidate, tau_secs: f64, sigma: f64| Observation {
            planned_sigma_bytes: None,
            step,
            candidate,
            sigma_bytes: (law(candidate) * sigma) as u64,
            tau_secs,
        };
        ctl.observe(at(0, fine, 0.08, 1.0));
        for step in 1..=10u64 {
            let tau = 0.01 * tau_growth.powi(step as i32);
            ctl.observe(at(step, coarse, tau, sigma_growth.powi(step as i32)));
        }
        ctl.correct(&s, fine, coarse, 12)
    };
    // Growing 10 % a step in τ, 15 % in σ: r 128's k of 1.6 is 8.6 by step 12, 0.43 s
    // against a 0.095 s plan; the window's r 64 steps alone would put it at 0.079 s.
    assert_eq!(run(1.1, 1.15), None);
    // Timings flat at r 64 while σ grows 8 % a step: the window shows no τ growth, but
    // r 128's old timing is carried forward as σ grew (0.08 s × 2.5), not taken as it was.
    assert_eq!(run(1.0, 1.08), None);
    // Still: 0.08 s clears the plan by the hysteresis (0.0855 s), and r 128 comes back.
    let back = run(1.0, 1.0).expect("r 128 comes back on still data");
    assert_eq!(back.candidate.r, 128, "{back:?}");
}

/// Production at a fine resolution ran slower against its trials than production at a
/// coarse one: a resolution between them, which production has not timed, is forecast with
/// the finer one's ratio, not taken up to on the coarse one's fast steps.
#[test]
fn a_resolution_production_has_not_timed_takes_the_ratio_of_a_finer_one() {
    let (fine, mid, coarse) = (c(256, g(2)), c(128, g(2)), c(64, g(2)));
    let s = Surface::new([(fine, 0.04), (mid, 0.02), (coarse, 0.01)].map(
        |(candidate, tau_secs)| Point {
            candidate,
            sigma_bytes: law(candidate),
            tau_secs,
        },
    ));
    let run = |fine_tau: f64| {
        let mut ctl = Controller::new(Budgets::time(0.1), 0.05, grid());
        let at = |step: u64, candidate: Candidate, tau_secs: f64| Observation {
            planned_sigma_bytes: None,
            step,
            candidate,
            sigma_bytes: law(candidate) as u64,
            tau_secs,
        };
        // r 256 at step 0, then ten still steps at r 64 at 0.6 of its trials' τ.
        ctl.observe(at(0, fine, fine_tau));
        for step in 1..=10u64 {
            ctl.observe(at(step, coarse, 0.006));
        }
        ctl.correct(&s, fine, coarse, 11)
    };
    // r 256 took 5× its trials: r 128 (trials 0.02 s) is forecast at 0.1 s and r 192 at
    // 0.11 s, over the 0.095 s plan, where r 64's ratio of 0.6 would put them at 0.012 s
    // and 0.014 s; r 64, timed by production itself, keeps its own ratio and stays.
    assert_eq!(run(0.2), None);
    // r 256 took 3× its trials: r 192 (0.0225 s by r² from r 256's trials) at 0.0675 s
    // clears the plan by the hysteresis, and is taken up to (r 256 at 0.12 s is not).
    let up = run(0.12).expect("a finer resolution is taken up to");
    assert_eq!(up.candidate.r, 192, "{up:?}");
}

/// Timings at one r that differ by noise (a fast one at a coarser γ) do not make the
/// controller raise γ: τ at a resolution is its slowest timing, whatever the γ, so the
/// time budget is kept by r and the finest γ stays.
#[test]
fn a_fast_timing_at_a_coarse_gamma_is_not_chased() {
    let point = |r: u32, gamma: f32, tau_secs: f64| Point {
        candidate: c(r, gamma),
        sigma_bytes: 1e3,
        tau_secs,
    };
    // r 256: 0.12 s at γ 0.04, 0.07 s at γ 0.05 (the same work, timed on a busy core).
    let s = Surface::new([
        point(256, g(8), 0.12),
        point(256, g(10), 0.07),
        point(128, g(8), 0.03),
    ]);
    for gamma in [g(1), g(8), g(9), g(10), g(40)] {
        assert!((s.tau(c(256, gamma)).unwrap() - 0.12).abs() < 1e-12);
    }
    assert!((s.tau(c(192, g(8))).unwrap() - 0.0675).abs() < 1e-12);
    let mut ctl = Controller::new(Budgets::time(0.1), 0.05, grid());
    let tuned = c(256, g(8));
    ctl.observe(Observation {
        planned_sigma_bytes: None,
        step: 0,
        candidate: tuned,
        sigma_bytes: 1000,
        tau_secs: 0.12,
    });
    // r 256 misses the 0.095 s plan at every γ (a curve through the two timings would
    // have taken γ 0.045 there, 0.090 s); r 192 meets it at the finest γ measured.
    let p = ctl.correct(&s, tuned, tuned, 1).unwrap();
    assert_eq!(p.candidate, c(192, g(8)), "{p:?}");
}

/// Under a time budget: a resolution whose own step was slow is not taken back on the
/// ratios of faster steps at another (fixed costs dominate a small r's timing, so its
/// ratio says little of a large r's); and when no candidate meets the plan, the lowest r
/// at its finest γ, not the coarsest γ.
#[test]
fn a_time_budget_keeps_a_slow_resolutions_own_timing_and_its_fallback_keeps_gamma() {
    let point = |r: u32, tau_secs: f64| Point {
        candidate: c(r, g(2)),
        sigma_bytes: 1e3,
        tau_secs,
    };
    let s = Surface::new([point(256, 0.05), point(128, 0.03)]);
    let mut ctl = Controller::new(Budgets::time(0.1), 0.05, grid());
    let tuned = c(256, g(2));
    let at = |ctl: &mut Controller, step: u64, candidate: Candidate, tau_secs: f64| {
        ctl.observe(Observation {
            planned_sigma_bytes: None,
            step,
            candidate,
            sigma_bytes: 1000,
            tau_secs,
        })
    };
    at(&mut ctl, 0, tuned, 0.12);
    let p = ctl.correct(&s, tuned, tuned, 1).unwrap();
    assert_eq!(p.candidate, c(192, g(2)), "{p:?}");
    // Eight fast steps at r 192 push step 0 out of the window (k 0.7 there): r 256 would
    // forecast 0.036 s on their ratio, but its own step took 0.12 s.
    for step in 1..=8 {
        at(&mut ctl, step, c(192, g(2)), 0.02);
    }
    assert!(ctl.observations().all(|o| o.candidate.r == 192));
    assert_eq!(ctl.correct(&s, tuned, c(192, g(2)), 9), None);
    // A step so slow that nothing meets the plan: r 64 at the finest γ of the grid.
    at(&mut ctl, 9, c(192, g(2)), 10.0);
    let p = ctl.correct(&s, tuned, c(192, g(2)), 10).unwrap();
    assert_eq!((p.candidate, p.feasible), (c(64, g(1)), false), "{p:?}");
}

#[test]
fn a_candidate_that_overshot_on_its_own_step_is_not_taken_back_on_others_ratios() {
    let s = surface_of(&[c(256, g(2)), c(256, g(4))]);
    let mut ctl = Controller::new(Budgets::size(1_120_000), 0.05, grid());
    let (tuned, coarse) = (c(256, g(2)), c(256, g(4)));
    // The tuned P_M measured 20 % over its model (over the plan); the coarser one then
    // measures 0.9 of its own: by the window's ratio the tuned one would fit again
    // (0.9 MB), by its own it does not, and the step back stops short of it.
    observed(&mut ctl, 0, tuned, 1.2);
    observed(&mut ctl, 1, coarse, 0.9);
    observed(&mut ctl, 2, coarse, 0.9);
    let back = ctl.correct(&s, tuned, coarse, 3).unwrap().candidate;
    assert_eq!(back, c(256, g(3)));
    // Once its memory has passed, the window's ratio rules again.
    for step in 3..40 {
        observed(&mut ctl, step, coarse, 0.8);
    }
    assert_eq!(
        ctl.correct(&s, tuned, coarse, 40).map(|p| p.candidate),
        Some(tuned)
    );
}

#[test]
fn a_surface_error_at_a_new_candidate_is_not_read_as_growth() {
    let s = surface_of(&[c(256, g(2)), c(256, g(4))]);
    let mut ctl = Controller::new(Budgets::size(1_120_000), 0.05, grid());
    for step in [0, 10, 20] {
        observed(&mut ctl, step, c(256, g(2)), 1.0);
    }
    // The next P_M measures 30 % above its model, and stays there: a level, not a trend.
    observed(&mut ctl, 30, c(256, g(3)), 1.3);
    observed(&mut ctl, 40, c(256, g(3)), 1.3);
    let f = ctl.forecast(&s, 100).unwrap();
    assert!((f.sigma - 1.3).abs() < 1e-5, "{f:?}");
    // Older steps than the newest are ignored.
    observed(&mut ctl, 5, c(256, g(2)), 9.0);
    assert_eq!(ctl.observations().count(), 5);
}

/// A production step made at another precision than the tuning chose (the nodes'
/// configured `P_M` before the first decision) gives the forecast its ratio, so the first
/// decision is planned for the growth seen since the characteristic step.
#[test]
fn growth_seen_at_another_precision_reaches_the_first_decision() {
    let at = |c: Candidate, precision| Candidate { precision, ..c };
    let cs = [c(64, g(1)), c(64, g(4)), c(128, g(1)), c(128, g(4))];
    let points = cs
        .iter()
        .flat_map(|&x| [Precision::Bits(6), Precision::Bits(8)].map(|p| at(x, p)))
        .map(|x| Point {
            candidate: x,
            sigma_bytes: law(x)
                * if x.precision == Precision::Bits(8) {
                    1.3
                } else {
                    1.0
                },
            tau_secs: 0.01,
        });
    let s = Surface::new(points);
    let configured = at(c(128, g(2)), Precision::Bits(8));
    let mut ctl = Controller::new(Budgets::size(1_000_000), 0.05, grid());
    // Made at 8 bits (whose points lie 1.3× the law), growing 10 % a step: 1.6× its
    // surface by the newest.
    for step in 0..6u64 {
        observed(&mut ctl, step, configured, 1.3 * 1.1f64.powi(step as i32));
    }
    let f = ctl
        .forecast(&s, 6)
        .expect("a forecast from the 8-bit steps");
    assert!(f.sigma_now > 1.4, "{f:?}");
    let tuned = at(c(128, g(1)), Precision::Bits(6));
    let p = ctl.choose(&s, tuned, 6).unwrap();
    assert_eq!(p.candidate.precision, Precision::Bits(6));
    assert!(p.sigma_bytes > s.sigma(p.candidate).unwrap() * 1.4, "{p:?}");
}

/// At the tuned resolution a γ finer than the tuned one is taken only where production came
/// in under the tuning's measurements by the hysteresis: else the tuning measured what
/// fits, and the surface between its probes is a guess at the budget's edge.
#[test]
fn the_tuned_gamma_is_refined_only_where_the_data_shrank() {
    let s = surface_of(&[c(256, g(1)), c(256, g(4))]);
    let tuned = c(256, g(4));
    let chosen = |k: f64| {
        let mut ctl = Controller::new(Budgets::size(1_120_000), 0.05, grid());
        observed(&mut ctl, 0, tuned, k);
        ctl.choose(&s, tuned, 1).map(|p| p.candidate)
    };
    // By the surface γ 0.01 (1.0 MB) would fit the 1.064 MB plan at k = 1.
    assert_eq!(chosen(1.0), Some(tuned));
    assert_eq!(chosen(0.95), Some(tuned), "within a step's noise");
    assert_eq!(chosen(0.5), Some(c(256, g(1))));
}

/// A finer resolution is taken back only after the `P_M` in force has held for the dwell:
/// the field that grew less than forecast for a few steps may grow again.
#[test]
fn a_finer_resolution_waits_for_the_dwell() {
    let tuned = c(256, g(2));
    let current = c(128, g(2));
    let s = surface_of(&[c(256, g(2)), c(256, g(4)), c(128, g(2)), c(128, g(4))]);
    let mut ctl = Controller::new(Budgets::size(1_120_000), 0.05, grid());
    // The field shrank to k = 0.5 after the coarsening: r 256 fits with room.
    for step in 0..DWELL {
        observed(&mut ctl, step, current, 0.5);
        let taken = ctl
            .correct(&s, tuned, current, step + 1)
            .map(|p| p.candidate);
        if step + 1 < DWELL {
            assert_eq!(taken, None, "after {} steps", step + 1);
        } else {
            assert_eq!(taken, Some(tuned), "after the dwell");
        }
    }
}

/// Not at risk, a finer `P_M` is taken only when it is worth a visible change: by q where
/// the trials scored both (0.5 dB at one resolution, 1 dB across), else by σ (20 %, 40 %).
#[test]
fn a_finer_p_m_is_taken_only_when_the_gain_is_worth_the_change() {
    let tuned = c(256, g(2));
    let current = c(256, g(3));
    let base = [c(256, g(2)), c(256, g(3)), c(256, g(4))];
    // The field shrank to k = 0.5: the tuned P_M fits with room.
    let with_q = |q_tuned: f64| {
        let s = surface_of(&base).with_q([(tuned, q_tuned), (current, 40.0)]);
        let mut ctl = Controller::new(Budgets::size(1_120_000), 0.05, grid());
        observed(&mut ctl, 0, current, 0.5);
        ctl.correct(&s, tuned, current, 10).map(|p| p.candidate)
    };
    assert_eq!(with_q(40.3), None, "0.3 dB is not worth a change");
    assert_eq!(with_q(40.6), Some(tuned));
    // Unscored: by σ, 1.5× the current's (γ 0.015 → 0.01) is worth it, 1.07× is not.
    let s = surface_of(&base);
    let mut ctl = Controller::new(Budgets::size(1_120_000), 0.05, grid());
    observed(&mut ctl, 0, current, 0.5);
    assert_eq!(
        ctl.correct(&s, tuned, current, 10).map(|p| p.candidate),
        Some(tuned)
    );
    let near = surface_of(&[c(256, 0.014), c(256, g(3))]);
    let mut ctl = Controller::new(Budgets::size(1_120_000), 0.05, grid());
    let tuned = c(256, 0.014);
    observed(&mut ctl, 0, current, 0.5);
    assert_eq!(ctl.correct(&near, tuned, current, 10), None);
    // Across resolutions 1 dB is needed: 0.8 dB more at the tuned r 256 is not enough.
    let s = surface_of(&[c(256, g(2)), c(192, g(2))])
        .with_q([(c(256, g(2)), 40.8), (c(192, g(2)), 40.0)]);
    let mut ctl = Controller::new(Budgets::size(1_120_000), 0.05, grid());
    observed(&mut ctl, 0, c(192, g(2)), 0.5);
    assert_eq!(ctl.correct(&s, c(256, g(2)), c(192, g(2)), 10), None);
}

/// At risk, a correction goes no finer in r than the `P_M` in force, and a change planned
/// for the horizon holds on data that keeps growing as forecast, where one planned for the
/// next step alone is outgrown at once.
#[test]
fn a_correction_planned_for_the_horizon_holds_while_the_growth_goes_on() {
    let s = surface_of(&[c(256, g(2)), c(256, g(4)), c(128, g(2))]);
    let tuned = c(256, g(2));
    // σ grows 5 % a step from k 1.
    let changes = |horizon: u64| {
        let mut ctl = Controller::new(Budgets::size(1_120_000), 0.05, grid());
        ctl.horizon = horizon;
        let mut current = tuned;
        let mut changes = 0;
        for step in 0..40u64 {
            observed(&mut ctl, step, current, 1.05f64.powi(step as i32));
            if let Some(p) = ctl.correct(&s, tuned, current, step + 1) {
                assert!(p.candidate.r <= current.r || p.feasible, "{p:?}");
                current = p.candidate;
                changes += 1;
            }
        }
        changes
    };
    let (next_only, lasting) = (changes(0), changes(HORIZON));
    assert!(lasting * 2 <= next_only, "{lasting} vs {next_only}");
}

/// After a change of character the steps before it and the model's miss are forgotten.
#[test]
fn a_rebase_forgets_the_steps_before_the_change() {
    let tuned = c(256, g(2));
    let mut ctl = Controller::new(Budgets::size(1_000_000), 0.05, grid());
    for step in 0..4 {
        ctl.observe(Observation {
            step,
            candidate: tuned,
            sigma_bytes: if step < 3 { 500_000 } else { 2_000_000 },
            tau_secs: 0.1,
            planned_sigma_bytes: Some(500_000.0),
        });
    }
    assert!(ctl.miss() > 1.0);
    ctl.rebase(3);
    assert_eq!(ctl.miss(), 1.0);
    assert_eq!(
        ctl.observations().map(|o| o.step).collect::<Vec<_>>(),
        vec![3]
    );
}

/// A re-tune on a growing field: the growth the steps before it showed (20 % a step at one
/// `P_M`) forecasts the steps after it until they show their own, and then theirs does.
#[test]
fn a_rebase_keeps_the_growth_until_the_new_steps_show_theirs() {
    let tuned = c(256, g(2));
    let mut ctl = Controller::new(Budgets::size(1_000_000), 0.05, grid());
    for step in 0..4 {
        observed(&mut ctl, step, tuned, 0.5 * 1.2f64.powi(step as i32));
    }
    ctl.rebase(3);
    // The tuning on step 3 measured its data: k = 1 there on the new surface.
    let s = Surface::new([Point {
        candidate: tuned,
        sigma_bytes: law(tuned) * 0.5 * 1.2f64.powi(3),
        tau_secs: 0.1,
    }]);
    let f = ctl.forecast(&s, 5).unwrap();
    assert!((f.sigma_now - 1.0).abs() < 1e-6, "{f:?}");
    assert!((f.sigma / f.sigma_now - 1.44).abs() < 0.01, "{f:?}");
    let trend = f.trend_per_step.unwrap();
    assert!((trend - 1.2).abs() < 0.01, "{f:?}");
    // Two steps of the new data at one P_M growing 5 % a step: theirs now.
    observed(&mut ctl, 4, tuned, 0.5 * 1.2f64.powi(3) * 1.05);
    let f = ctl.forecast(&s, 6).unwrap();
    assert!((f.sigma_growth_per_step - 1.05).abs() < 0.01, "{f:?}");
}

/// A forecast inside the headroom (over the plan, under the budget) changes nothing; one at
/// the budget is a risk, and the change aims at the plan.
#[test]
fn only_a_forecast_at_the_budget_puts_it_at_risk() {
    let s = surface_of(&[c(256, g(2)), c(256, g(4))]);
    let tuned = c(256, g(2));
    // law(tuned) = 1 MB; the plan is 0.95 × 1.1 MB = 1.045 MB, the budget 1.1 MB.
    let at = |k: f64| {
        let mut ctl = Controller::new(Budgets::size(1_100_000), 0.05, grid());
        observed(&mut ctl, 0, tuned, k);
        ctl.correct(&s, tuned, tuned, 1)
    };
    assert_eq!(at(1.07), None, "1.07 MB: over the plan, within the budget");
    let p = at(1.12).unwrap();
    assert_eq!(p.candidate, c(256, g(3)));
    assert!(p.sigma_bytes <= 1_045_000.0, "{p:?}");
}
