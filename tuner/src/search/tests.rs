//! The searches against tables of measurements with known optima.

use super::*;
use insitu_core::evaluate::Sizing;
use insitu_core::metrics::Db;
use insitu_core::vdi::Precision;

/// A VDI's σ as a smooth model: r² per-pixel counts and supersegments per pixel falling as
/// `γ^−exponent`, times `1 + bumps·sin(40γ + r/50)` (σ of real fields is not exactly a
/// power of γ: with `bumps` > 0 it is not even monotone); q rising with r, falling with γ.
struct Model {
    exponent: f64,
    bumps: f64,
    /// τ = `tau_scale` · r² · (1.1 − γ) seconds: r² rays, a little less work as γ grows
    /// (0: no τ).
    tau_scale: f64,
    /// q capped at a ceiling (dB) plus a slope (dB per unit of r): a precision's ceiling,
    /// where neighbouring resolutions differ by hundredths of a dB (`None`: no ceiling).
    plateau: Option<(f64, f64)>,
    generations: u64,
    /// Every candidate probed or measured, in order.
    asked: Vec<Candidate>,
}

/// What a precision does to σ (a factor) and q (dB lost) against 8 bits (the grids'
/// default): the shape measured on real VDIs (docs/conventions.md, "The VDI file"):
/// floats 3.5× the bytes for 0.05 dB more, 6 bits 0.78× for 0.55 dB less.
fn precision_cost(c: Candidate) -> (f64, f64) {
    match c.precision {
        Precision::Float32 => (3.5, -0.05),
        Precision::Bits(b) if b <= 6 => (0.78, 0.55),
        Precision::Bits(_) => (1.0, 0.0),
    }
}

impl Model {
    fn new(exponent: f64, bumps: f64) -> Self {
        Self {
            exponent,
            bumps,
            tau_scale: 0.0,
            plateau: None,
            generations: 0,
            asked: Vec::new(),
        }
    }

    /// The model with q capped at `plateau` (see [`Model::plateau`]).
    fn on_plateau(plateau: (f64, f64)) -> Self {
        Self {
            plateau: Some(plateau),
            ..Self::new(0.8, 0.0)
        }
    }
}

impl Oracle for Model {
    fn measure(&mut self, c: Candidate) -> Result<Measurement, StudyError> {
        let (r, gamma) = (f64::from(c.r), f64::from(c.gamma));
        Ok(Measurement {
            r: c.r,
            gamma: c.gamma,
            sizing: self.measure_sizing(c)?,
            tau_render_secs: 0.0,
            q_db: Db(self.plateau.iter().fold(
                20.0 + 8.0 * (r / 64.0).ln() - 40.0 * gamma - precision_cost(c).1,
                |q, &(ceiling, slope)| q.min(ceiling) + slope * r,
            )),
            view_q_db: vec![],
            ssim: None,
            precision: c.precision,
            sigma_paper_bytes: None,
        })
    }

    fn measure_sizing(&mut self, c: Candidate) -> Result<Sizing, StudyError> {
        self.generations += 1;
        self.asked.push(c);
        let (r, gamma) = (f64::from(c.r), f64::from(c.gamma));
        let per_pixel = 4.0 + 1.2 * gamma.powf(-self.exponent);
        let bumps = 1.0 + self.bumps * (40.0 * gamma + r / 50.0).sin();
        Ok(Sizing {
            sigma_bytes: (0.6 * r * r * per_pixel * bumps * precision_cost(c).0) as u64,
            tau_secs: self.tau_scale * r * r * (1.1 - gamma),
            ..Sizing::default()
        })
    }

    fn generations(&self) -> u64 {
        self.generations
    }

    fn generation_secs(&self) -> f64 {
        0.0
    }
}

/// Budgets from tight to loose, a plain search and one from a `P_M` in force, for three
/// shapes of σ(γ): interpolating finds the bisection's answer (σ monotone) in fewer
/// probes; with σ a few percent from monotone it still answers a candidate within the
/// budget, with no more than twice the bisection's probes.
#[test]
fn interpolating_the_gamma_axis_finds_the_bisections_answer_in_fewer_probes() {
    let grid = ParamGrid::parse("128:768:32", "0.001:0.26:0.004").unwrap();
    for bumps in [0.0, 0.04] {
        let (mut bisected, mut interpolated) = (0, 0);
        for exponent in [0.4, 0.8, 1.5] {
            for budget in [150_000u64, 400_000, 1_000_000, 3_000_000, 10_000_000] {
                let near = [
                    None,
                    Some(Candidate {
                        r: 256,
                        gamma: 0.013,
                        precision: Default::default(),
                    }),
                ];
                for near in near {
                    let spec = UtilitySpec::Size(budget);
                    let mut b = Model::new(exponent, bumps);
                    let mut i = Model::new(exponent, bumps);
                    let by_halves = adaptive(&mut b, &grid, spec, near, false).unwrap();
                    let by_guess = adaptive(&mut i, &grid, spec, near, true).unwrap();
                    let answer = |o: &Outcome| o.best.as_ref().map(Measurement::candidate);
                    let case =
                        format!("σ ∝ γ^−{exponent}, bumps {bumps}, budget {budget}, from {near:?}");
                    if bumps == 0.0 {
                        assert_eq!(answer(&by_guess), answer(&by_halves), "{case}");
                    }
                    let best = by_guess.best.as_ref().expect(&case);
                    assert!(best.sizing.sigma_bytes < budget, "{case}");
                    assert!(by_guess.generations <= 2 * by_halves.generations, "{case}");
                    bisected += by_halves.generations;
                    interpolated += by_guess.generations;
                }
            }
        }
        eprintln!("bumps {bumps}: {interpolated} probes interpolating, {bisected} bisecting");
        assert!(
            interpolated * 4 < bisected * 3,
            "bumps {bumps}: {interpolated} probes interpolating, {bisected} bisecting"
        );
    }
}

/// From a `P_M` in force at a resolution that misses the budget at every γ (σ rises with
/// r), the search walks down only: no larger resolution is probed, and the answer is the
/// plain search's.
#[test]
fn a_search_from_a_resolution_that_cannot_meet_the_budget_probes_no_larger_one() {
    let grid = ParamGrid::parse("128:768:32", "0.001:0.26:0.004").unwrap();
    // σ(r, 0.257) = 0.6 r² (4 + 1.2 · 0.257^−0.8) ≈ 4.5 r²: r 416 meets 800 kB, r 448 not.
    let spec = UtilitySpec::Size(800_000);
    let near = Candidate {
        r: 512,
        gamma: 0.013,
        precision: Default::default(),
    };
    let mut from_near = Model::new(0.8, 0.0);
    let mut plain = Model::new(0.8, 0.0);
    let a = adaptive(&mut from_near, &grid, spec, Some(near), true).unwrap();
    let b = adaptive(&mut plain, &grid, spec, None, true).unwrap();
    let answer = |o: &Outcome| o.best.as_ref().map(Measurement::candidate);
    assert_eq!(answer(&a), answer(&b));
    assert!(answer(&a).is_some_and(|c| c.r <= 416), "{:?}", answer(&a));
    assert!(
        from_near.asked.iter().all(|c| c.r <= near.r),
        "{:?}",
        from_near.asked
    );
}

/// From a `P_M` in force one resolution below the answer, the walk up takes a second single
/// step before doubling: it finds the plain search's answer without measuring any resolution
/// more than one above it (with strides 1, 2, … it measured the one two above the answer,
/// the dearest of the walk, which the climb does not need).
#[test]
fn a_walk_from_just_below_the_answer_measures_nothing_two_resolutions_above_it() {
    let grid = ParamGrid::parse("128:768:32", "0.001:0.26:0.004").unwrap();
    let mut checked = 0;
    for budget in [150_000u64, 400_000, 1_000_000, 3_000_000] {
        let spec = UtilitySpec::Size(budget);
        let plain = adaptive(&mut Model::new(0.8, 0.0), &grid, spec, None, true).unwrap();
        let answer = plain.best.as_ref().map(Measurement::candidate).unwrap();
        let at = grid.rs.iter().position(|&r| r == answer.r).unwrap();
        if at == 0 || at + 2 >= grid.rs.len() {
            continue;
        }
        let near = Candidate {
            r: grid.rs[at - 1],
            ..answer
        };
        let mut walked = Model::new(0.8, 0.0);
        let found = adaptive(&mut walked, &grid, spec, Some(near), true).unwrap();
        assert_eq!(
            found.best.as_ref().map(Measurement::candidate),
            Some(answer),
            "{budget}"
        );
        let highest = walked.asked.iter().map(|c| c.r).max().unwrap();
        assert!(highest <= grid.rs[at + 1], "{budget}: {:?}", walked.asked);
        checked += 1;
    }
    assert!(
        checked >= 2,
        "only {checked} budgets had an answer inside the r axis"
    );
}

/// On a plateau of q (a precision's ceiling, neighbouring resolutions 0.032 dB apart), the
/// walk from the `P_M` in force does not follow gains below [`WALK_MARGIN_DB`] up the r axis
/// to the dearest resolutions: it measures one resolution above the start, and no neighbour
/// of its answer is better by the margin or more. Without the margin it walks to the top.
#[test]
fn on_a_plateau_of_q_the_walk_does_not_follow_gains_below_the_margin() {
    let grid = ParamGrid::parse("128:768:32", "0.001:0.26:0.004").unwrap();
    let spec = UtilitySpec::Size(3_000_000);
    let start = Candidate {
        r: 256,
        gamma: 0.009,
        precision: Precision::Bits(8),
    };
    let plateau = (30.0, 0.001);
    let mut model = Model::on_plateau(plateau);
    let found = adaptive(&mut model, &grid, spec, Some(start), true).unwrap();
    let highest = model.asked.iter().map(|c| c.r).max().unwrap();
    assert!(highest <= 288, "{:?}", model.asked);
    let best = found.best.unwrap();
    let q = |r: u32| {
        adaptive(
            &mut Model::on_plateau(plateau),
            &ParamGrid {
                rs: vec![r],
                ..grid.clone()
            },
            spec,
            None,
            true,
        )
        .unwrap()
        .best
        .map_or(f64::NEG_INFINITY, |b| b.q())
    };
    for r in [best.r - 32, best.r + 32] {
        assert!(q(r) < best.q() + WALK_MARGIN_DB, "r {r} against {best:?}");
    }
    // The plateau is one: the grid's best is far up the axis.
    let u = spec.utility();
    let top = grid_search(&mut Model::on_plateau(plateau), &grid, u.as_ref())
        .unwrap()
        .best
        .unwrap();
    assert!(top.r > 288 && top.q() > best.q(), "{top:?}");
}

/// Under a time budget: a resolution that misses at its smallest and its largest γ costs
/// those two probes, the sweep stops after two such in a row, and the answer is the
/// exhaustive grid's — also where τ crosses the budget inside a resolution's γ axis.
#[test]
fn a_time_budget_spends_two_probes_on_a_resolution_that_cannot_meet_it() {
    let grid = ParamGrid::parse("64:512:64", "0.001:0.26:0.008").unwrap();
    // τ(r, γ) = 1e-3 (r/64)² (1.1 − γ): at 20 ms r 256 meets at every γ, r 320 and up at
    // none; at 24 ms r 320 meets from γ ≈ 0.14 up.
    for (budget, crossing) in [(0.02, None), (0.024, Some(320))] {
        let mut model = Model::new(0.8, 0.0);
        model.tau_scale = 1e-3 / (64.0 * 64.0);
        let spec = UtilitySpec::Time(budget);
        let found = adaptive_search(&mut model, &grid, spec).unwrap();
        let mut all = Model::new(0.8, 0.0);
        all.tau_scale = model.tau_scale;
        let u = spec.utility();
        let exhaustive = grid_search(&mut all, &grid, u.as_ref()).unwrap();
        let answer = |o: &Outcome| o.best.as_ref().map(Measurement::candidate);
        assert_eq!(answer(&found), answer(&exhaustive), "{budget}");
        let probes_at = |r: u32| model.asked.iter().filter(|c| c.r == r).count();
        // Missing everywhere: the smallest and the largest γ, nothing else; the sweep
        // stops after two such resolutions.
        let missed = if crossing.is_some() {
            [384, 448]
        } else {
            [320, 384]
        };
        for r in missed {
            assert_eq!(probes_at(r), 2, "{budget}: r {r}: {:?}", model.asked);
        }
        assert_eq!(probes_at(missed[1] + 64), 0, "{budget}: {:?}", model.asked);
        if let Some(r) = crossing {
            let first = *grid
                .gammas
                .iter()
                .find(|&&g| model.tau_scale * f64::from(r * r) * (1.1 - f64::from(g)) < budget)
                .unwrap();
            // The first γ that meets the budget, probed and then measured in full.
            assert!(
                model.asked.contains(&Candidate {
                    r,
                    gamma: first,
                    precision: grid.precision()
                }),
                "{:?}",
                model.asked
            );
        }
    }
}

/// With several precisions the adaptive search answers at each and keeps the best: the
/// answer is the exhaustive grid's over all three, under a size and under a time budget.
#[test]
fn the_precision_is_searched_with_r_and_gamma() {
    let grid = ParamGrid::parse("64:512:64", "0.001:0.26:0.008")
        .unwrap()
        .with_precisions("f32,6,8")
        .unwrap();
    assert_eq!(
        grid.precisions,
        vec![Precision::Bits(6), Precision::Bits(8), Precision::Float32]
    );
    for spec in [UtilitySpec::Size(150_000), UtilitySpec::Size(40_000)] {
        let mut model = Model::new(0.8, 0.0);
        let found = adaptive_search(&mut model, &grid, spec).unwrap();
        let mut all = Model::new(0.8, 0.0);
        let exhaustive = grid_search(&mut all, &grid, spec.utility().as_ref()).unwrap();
        let answer = |o: &Outcome| o.best.as_ref().map(Measurement::candidate);
        assert_eq!(answer(&found), answer(&exhaustive), "{spec:?}");
        assert_ne!(
            answer(&found).map(|c| c.precision),
            Some(Precision::Float32),
            "{spec:?}: floats buy the least picture per byte"
        );
        assert!(model.generations < all.generations / 4, "{spec:?}");
    }
}
