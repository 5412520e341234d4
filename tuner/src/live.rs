//! Tuning while a simulation runs (Sec. 6.2 and 7, made incremental): the maths of the tuner
//! service, free of networking.
//!
//! - [`Tracker`]: characteristic time steps chosen as the steps arrive, with the offline rule of
//!   [`crate::series`]: a step is characteristic when its histogram is farther than `threshold`
//!   (total-variation distance) from every characteristic step so far, the first step always
//!   is. This is farthest-first traversal in arrival order: every step seen is within
//!   `threshold` of a characteristic step at the time it was seen. At most `max` are kept; when
//!   one more would exceed it, the most redundant one is evicted (see [`Tracker::observe`]).
//! - [`WorstCase`]: an [`Oracle`] whose measurement of a candidate is its worst case over the
//!   characteristic steps (σ and τ the largest, q the smallest). For the built-in utilities, ν of
//!   that worst case is the worst ν over the steps, so a search over it finds the
//!   conservative choice of [`crate::series::conservative`] (meets the budget on every step,
//!   best worst-case utility) while measuring only what the search asks for.
//! - [`combine_ranks`]: what a budget means for a world of ranks: σ of a step sums over its
//!   ranks' VDIs, τ is the slowest rank's, q is that of the summed MSE of the ranks' views
//!   (the composed step's error, estimated from the bricks' own).

use crate::grid::Candidate;
use crate::measure::Measurement;
use crate::series::{distance, BINS};
use crate::study::{Oracle, StudyError};
use insitu_core::budget::Budgets;
use insitu_core::evaluate::Sizing;
use insitu_core::metrics::{mse_from_psnr, psnr_from_mse, Db};
pub use insitu_core::volume::histogram;
use serde::{Deserialize, Serialize};

/// Errors of live summaries.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum LiveError {
    /// A histogram with the wrong number of bins.
    #[error("a step summary needs exactly {BINS} histogram bins, got {0}")]
    Bins(usize),
    /// Nothing to combine.
    #[error("no measurements to combine")]
    Empty,
}

/// Bin counts → a normalised histogram (all zero when no value was counted).
///
/// # Errors
/// [`LiveError::Bins`] unless there are exactly [`BINS`] counts.
pub fn normalise(counts: &[u64]) -> Result<[f64; BINS], LiveError> {
    if counts.len() != BINS {
        return Err(LiveError::Bins(counts.len()));
    }
    let n: u64 = counts.iter().sum();
    let mut h = [0.0; BINS];
    if n > 0 {
        for (h, &c) in h.iter_mut().zip(counts) {
            *h = c as f64 / n as f64;
        }
    }
    Ok(h)
}

/// A characteristic step: its index and normalised histogram.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Characteristic {
    /// Step index.
    pub step: u64,
    /// Normalised histogram ([`BINS`] values).
    pub histogram: Vec<f64>,
}

impl Characteristic {
    fn hist(&self) -> [f64; BINS] {
        let mut h = [0.0; BINS];
        for (d, s) in h.iter_mut().zip(&self.histogram) {
            *d = *s;
        }
        h
    }
}

/// What [`Tracker::observe`] decided about a step.
#[derive(Clone, Debug, PartialEq)]
pub enum Verdict {
    /// Within the threshold of characteristic step `nearest`.
    Alike {
        /// The nearest characteristic step.
        nearest: u64,
        /// Its distance, in [0, 1].
        distance: f64,
    },
    /// A new characteristic step.
    New {
        /// Distance to the nearest earlier characteristic step (`None` for the first).
        distance: Option<f64>,
        /// A characteristic step evicted to stay within `max`, with the distance to its
        /// nearest remaining neighbour (what coverage its removal costs).
        evicted: Option<(u64, f64)>,
    },
}

/// Characteristic steps, chosen live (see the module docs).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Tracker {
    /// Distance above which a step is characteristic, in [0, 1].
    pub threshold: f64,
    /// Most characteristic steps kept (≥ 1).
    pub max: usize,
    /// The characteristic steps, in the order they were chosen.
    pub steps: Vec<Characteristic>,
}

impl Tracker {
    /// An empty tracker.
    pub fn new(threshold: f64, max: usize) -> Self {
        Self {
            threshold,
            max: max.max(1),
            steps: Vec::new(),
        }
    }

    /// The characteristic steps' indices, in the order chosen.
    pub fn step_indices(&self) -> Vec<u64> {
        self.steps.iter().map(|c| c.step).collect()
    }

    /// The nearest characteristic step to `h` and its distance.
    pub fn nearest(&self, h: &[f64; BINS]) -> Option<(u64, f64)> {
        self.steps
            .iter()
            .map(|c| (c.step, distance(h, &c.hist())))
            .min_by(|a, b| a.1.total_cmp(&b.1))
    }

    /// Classifies `step` by its histogram `h`; a new characteristic step is added. When that
    /// makes more than `max`, the earlier characteristic step whose nearest other
    /// characteristic step is closest (the most redundant: removing it loses the least
    /// coverage) is evicted; ties evict the older. The new step is never the one evicted.
    pub fn observe(&mut self, step: u64, h: &[f64; BINS]) -> Verdict {
        match self.nearest(h) {
            Some((nearest, d)) if d <= self.threshold => Verdict::Alike {
                nearest,
                distance: d,
            },
            near => Verdict::New {
                distance: near.map(|n| n.1),
                evicted: self.add(step, h),
            },
        }
    }

    /// Makes `step` characteristic whatever its distance (a production step that broke the
    /// budget); returns what was evicted, as [`Tracker::observe`].
    pub fn force(&mut self, step: u64, h: &[f64; BINS]) -> Option<(u64, f64)> {
        if self.steps.iter().any(|c| c.step == step) {
            return None;
        }
        self.add(step, h)
    }

    /// Forgets `step` (its data is gone); whether it was characteristic.
    pub fn remove(&mut self, step: u64) -> bool {
        let n = self.steps.len();
        self.steps.retain(|c| c.step != step);
        self.steps.len() != n
    }

    fn add(&mut self, step: u64, h: &[f64; BINS]) -> Option<(u64, f64)> {
        self.steps.push(Characteristic {
            step,
            histogram: h.to_vec(),
        });
        if self.steps.len() <= self.max {
            return None;
        }
        let hists: Vec<[f64; BINS]> = self.steps.iter().map(Characteristic::hist).collect();
        let last = self.steps.len() - 1;
        let (victim, d) = (0..last)
            .map(|i| {
                let nearest = (0..hists.len())
                    .filter(|&j| j != i)
                    .map(|j| distance(&hists[i], &hists[j]))
                    .fold(f64::INFINITY, f64::min);
                (i, nearest)
            })
            .min_by(|a, b| a.1.total_cmp(&b.1).then(a.0.cmp(&b.0)))?;
        let gone = self.steps.remove(victim);
        Some((gone.step, d))
    }
}

/// The worst case of `ms` (one measurement per step of the same candidate): σ, τ and the
/// other times the largest, q the smallest (its per-view values from the step with the
/// smallest q), SSIM the smallest.
///
/// # Errors
/// [`LiveError::Empty`] when `ms` is empty.
pub fn worst_case(ms: &[Measurement]) -> Result<Measurement, LiveError> {
    let worst_q = ms
        .iter()
        .min_by(|a, b| a.q().total_cmp(&b.q()))
        .ok_or(LiveError::Empty)?;
    let max_f = |f: fn(&Measurement) -> f64| ms.iter().map(f).fold(f64::NEG_INFINITY, f64::max);
    Ok(Measurement {
        r: worst_q.r,
        gamma: worst_q.gamma,
        precision: worst_q.precision,
        sizing: Sizing::worst(ms.iter().map(|m| &m.sizing)),
        tau_render_secs: max_f(|m| m.tau_render_secs),
        q_db: worst_q.q_db,
        view_q_db: worst_q.view_q_db.clone(),
        ssim: ms
            .iter()
            .map(|m| m.ssim)
            .try_fold(f64::INFINITY, |acc, s| s.map(|s| acc.min(s))),
        sigma_paper_bytes: ms
            .iter()
            .map(|m| m.sigma_paper_bytes)
            .try_fold(0, |acc, s| s.map(|s| acc.max(s))),
    })
}

/// One step's measurement from its ranks' (same candidate, one per rank): σ and the
/// supersegments summed (a step's VDIs together), τ and the other times of the slowest rank
/// (the step is done when its last rank is), SSIM the mean, and q the estimate of the
/// composed step's: per view the PSNR of the *sum* of the ranks' MSEs, pooled over the views
/// as the PSNR of their mean MSE. A rank's trial renders its own brick against that brick's
/// reference, each a whole frame, so its errors lie in the brick's footprint and its MSE is
/// diluted by the rest of the frame; the composed frame carries all of them. Where
/// footprints overlap, the front brick attenuates the back one's error, so the sum is the
/// conservative side. (On the ocean series, 2 and 4 ranks: the sum predicted 35.11, 37.20 and
/// 36.74 dB where the viz-node measured 35.10, 37.80 and 37.55 dB on the composed steps; the
/// mean, 38.12, 40.21 and 42.76 dB.)
///
/// # Errors
/// [`LiveError::Empty`] when `ranks` is empty.
pub fn combine_ranks(ranks: &[Measurement]) -> Result<Measurement, LiveError> {
    let first = ranks.first().ok_or(LiveError::Empty)?;
    if ranks.len() == 1 {
        return Ok(first.clone());
    }
    let mse = |q: &Db| mse_from_psnr(q.0);
    let views = ranks.iter().map(|m| m.view_q_db.len()).min().unwrap_or(0);
    let view_mse: Vec<f64> = (0..views)
        .map(|v| ranks.iter().map(|m| mse(&m.view_q_db[v])).sum::<f64>())
        .collect();
    let pooled = if views == 0 {
        ranks.iter().map(|m| mse(&m.q_db)).sum::<f64>()
    } else {
        view_mse.iter().sum::<f64>() / views as f64
    };
    let max_f = |f: fn(&Measurement) -> f64| ranks.iter().map(f).fold(0.0, f64::max);
    let ssims: Option<Vec<f64>> = ranks.iter().map(|m| m.ssim).collect();
    Ok(Measurement {
        r: first.r,
        gamma: first.gamma,
        precision: first.precision,
        sizing: Sizing::of_ranks(ranks.iter().map(|m| &m.sizing)),
        tau_render_secs: max_f(|m| m.tau_render_secs),
        q_db: Db(psnr_from_mse(pooled)),
        view_q_db: view_mse.into_iter().map(|m| Db(psnr_from_mse(m))).collect(),
        ssim: ssims.map(|s| s.iter().sum::<f64>() / s.len() as f64),
        sigma_paper_bytes: ranks
            .iter()
            .map(|m| m.sigma_paper_bytes)
            .try_fold(0, |acc, s| s.map(|s| acc + s)),
    })
}

/// An [`Oracle`] over several steps, each with its own oracle: a candidate's measurement is
/// its [`worst_case`] over them (see the module docs). Generations and their seconds add up.
pub struct WorstCase<'o> {
    steps: Vec<Box<dyn Oracle + 'o>>,
    /// σ_target (bytes) and τ_target (seconds): a size probe that breaks either on one step is
    /// not run on the others.
    budgets: Budgets,
    /// σ (bytes) and τ (seconds) of each step at the last size probe that reached it (0
    /// before any).
    last: Vec<(u64, f64)>,
}

impl<'o> WorstCase<'o> {
    /// Over one oracle per characteristic step.
    pub fn new(steps: Vec<Box<dyn Oracle + 'o>>) -> Self {
        let n = steps.len();
        Self {
            steps,
            budgets: Budgets::NONE,
            last: vec![(0, 0.0); n],
        }
    }

    /// The same, for a search under `budgets` (σ_target and/or τ_target):
    /// a size probe visits the steps largest σ first (under a size budget, else largest τ
    /// first; as the last probe found them) and stops at the first step whose σ or τ reaches
    /// its budget. The candidate is then infeasible whatever the other steps give, and the σ
    /// and τ returned are those measured so far (lower bounds of the worst case, one at or over
    /// its budget). On drifting data the newest characteristic step is usually the largest by
    /// far, so a re-tune's probes over the budget cost one step instead of all of them.
    pub fn with_budgets(mut self, budgets: Budgets) -> Self {
        self.budgets = budgets;
        self
    }
}

impl Oracle for WorstCase<'_> {
    fn measure(&mut self, c: Candidate) -> Result<Measurement, StudyError> {
        let ms = self
            .steps
            .iter_mut()
            .map(|o| o.measure(c))
            .collect::<Result<Vec<_>, _>>()?;
        worst_case(&ms).map_err(|e| StudyError::Invalid(e.to_string()))
    }

    /// The largest σ and τ over the steps (as [`worst_case`] takes them); under a budget, up
    /// to the first step that breaks it ([`WorstCase::with_budgets`]).
    fn measure_sizing(&mut self, c: Candidate) -> Result<Sizing, StudyError> {
        let (size, time) = (self.budgets.size_bytes, self.budgets.time_secs);
        let mut order: Vec<usize> = (0..self.steps.len()).collect();
        if size.is_some() {
            order.sort_by_key(|&i| std::cmp::Reverse(self.last[i].0));
        } else if time.is_some() {
            order.sort_by(|&a, &b| self.last[b].1.total_cmp(&self.last[a].1));
        }
        let mut all = Vec::with_capacity(order.len());
        for i in order {
            let s = self.steps[i].measure_sizing(c)?;
            self.last[i] = (s.sigma_bytes, s.tau_secs);
            let over =
                size.is_some_and(|b| s.sigma_bytes >= b) || time.is_some_and(|b| s.tau_secs >= b);
            all.push(s);
            if over {
                break;
            }
        }
        Ok(Sizing::worst(&all))
    }

    fn generations(&self) -> u64 {
        self.steps.iter().map(|o| o.generations()).sum()
    }

    fn generation_secs(&self) -> f64 {
        self.steps.iter().map(|o| o.generation_secs()).sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::ParamGrid;
    use crate::search::{adaptive_search, adaptive_search_near, grid_search};
    use crate::series::{characteristic_steps, conservative, histograms};
    use crate::study::TableOracle;
    use crate::utility::UtilitySpec;

    fn series() -> Vec<Vec<f32>> {
        // Regimes: steps 0–4 near 0, 5–9 near 5, 10–14 near 10, 15–19 near 0 again.
        (0..20)
            .map(|t| {
                let base = [0.0, 5.0, 10.0, 0.0][t / 5];
                (0..400)
                    .map(|i| base + (i % 11) as f32 * 0.02 + t as f32 * 1e-3)
                    .collect()
            })
            .collect()
    }

    #[test]
    fn live_choice_agrees_with_the_offline_rule_and_covers_every_step() {
        let s = series();
        let refs: Vec<&[f32]> = s.iter().map(Vec::as_slice).collect();
        let offline = histograms(&refs);
        let picked = characteristic_steps(&offline, 0.1, 8);
        // Live: bin over a range fixed in advance (here the series' range, as offline).
        let mut t = Tracker::new(0.1, 8);
        let mut verdicts = Vec::new();
        for (i, v) in s.iter().enumerate() {
            let binned = histogram(v, 0.0, 10.2);
            assert_eq!(binned.nan, 0);
            let h = normalise(&binned.counts).unwrap();
            let verdict = t.observe(i as u64, &h);
            if let Verdict::Alike { distance, .. } = verdict {
                assert!(distance <= 0.1);
            }
            verdicts.push(verdict);
        }
        assert_eq!(t.steps.len(), picked.len(), "{picked:?}");
        assert_eq!(
            t.step_indices(),
            vec![0, 5, 10],
            "the return to regime 0 is alike"
        );
        assert!(matches!(verdicts[0], Verdict::New { distance: None, .. }));
        assert!(matches!(verdicts[15], Verdict::Alike { nearest: 0, .. }));
    }

    #[test]
    fn the_most_redundant_step_is_evicted_never_the_new_one() {
        let one_hot = |b: usize, w: f64| {
            let mut h = [0.0; BINS];
            h[b] = w;
            h[b + 1] = 1.0 - w;
            h
        };
        let mut t = Tracker::new(0.05, 3);
        assert!(matches!(
            t.observe(0, &one_hot(0, 1.0)),
            Verdict::New { .. }
        ));
        assert!(matches!(
            t.observe(1, &one_hot(10, 1.0)),
            Verdict::New { .. }
        ));
        // Step 2 is 0.3 from step 1: characteristic, and steps 1 and 2 are the closest pair.
        assert!(matches!(
            t.observe(2, &one_hot(10, 0.7)),
            Verdict::New { .. }
        ));
        match t.observe(3, &one_hot(30, 1.0)) {
            Verdict::New {
                evicted: Some((1, d)),
                ..
            } => assert!((d - 0.3).abs() < 1e-12, "{d}"),
            v => panic!("{v:?}"),
        }
        assert_eq!(t.step_indices(), vec![0, 2, 3]);
        assert_eq!(
            t.force(3, &one_hot(30, 1.0)),
            None,
            "already characteristic"
        );
        assert!(t.remove(2) && !t.remove(2));
    }

    #[test]
    fn binning_clamps_and_skips_nan() {
        let h = histogram(
            &[-5.0, 0.0, 0.5, 1.0, 9.0, f32::NAN, f32::INFINITY],
            0.0,
            1.0,
        );
        let c = h.counts;
        assert_eq!(h.nan, 1);
        assert_eq!(
            h.finite_range,
            Some((-5.0, 9.0)),
            "the same pass finds the finite range"
        );
        assert_eq!(histogram(&[f32::NAN], 0.0, 1.0).finite_range, None);
        assert_eq!((c[0], c[32], c[63]), (2, 1, 3));
        assert_eq!(c.iter().sum::<u64>(), 6);
        assert_eq!(normalise(&[1; 63]), Err(LiveError::Bins(63)));
        assert_eq!(normalise(&[0; 64]).unwrap(), [0.0; BINS]);
    }

    fn table(step: u64, grid: &ParamGrid) -> Vec<Measurement> {
        // Monotone like real VDIs: σ rises with r and falls with γ; q falls with γ. Each step
        // scales σ differently, so the steps disagree on their optimum.
        let scale = [1.0, 1.7, 0.6][step as usize];
        grid.candidates()
            .into_iter()
            .map(|c| Measurement {
                r: c.r,
                gamma: c.gamma,
                precision: c.precision,
                sigma_paper_bytes: None,
                sizing: Sizing {
                    sigma_bytes: (scale * f64::from(c.r * c.r) / (1.0 + 40.0 * f64::from(c.gamma)))
                        as u64,
                    // τ rises with r, falls a little with γ, and differs between steps.
                    tau_secs: 1e-4
                        * f64::from(c.r)
                        * (1.0 + 0.1 * step as f64)
                        * (1.0 - 0.2 * f64::from(c.gamma)),
                    ..Sizing::default()
                },
                tau_render_secs: 0.0,
                q_db: Db(20.0 + f64::from(c.r) / 40.0 - 30.0 * f64::from(c.gamma) - step as f64),
                view_q_db: vec![],
                ssim: None,
            })
            .collect()
    }

    fn oracles(t: &[Vec<Measurement>]) -> Vec<Box<dyn Oracle + '_>> {
        t.iter()
            .map(|rows| Box::new(TableOracle::new(rows)) as Box<dyn Oracle + '_>)
            .collect()
    }

    #[test]
    fn the_worst_case_search_finds_the_conservative_choice() {
        let grid = ParamGrid::parse("64:512:32", "0.001:0.26:0.008").unwrap();
        let tables: Vec<Vec<Measurement>> = (0..3).map(|s| table(s, &grid)).collect();
        for target in [
            UtilitySpec::Size(60_000),
            UtilitySpec::Quality(24.0),
            UtilitySpec::Time(0.035),
            UtilitySpec::SizeAndTime(80_000, 0.035),
        ] {
            let u = target.utility();
            let (expected, worst) = conservative(&tables, u.as_ref()).unwrap();
            let mut all = WorstCase::new(oracles(&tables));
            let exhaustive = grid_search(&mut all, &grid, u.as_ref()).unwrap();
            let best = exhaustive.best.unwrap();
            assert_eq!(exhaustive.value, worst, "{target:?}");
            assert_eq!(best.candidate(), expected, "{target:?}");
            // The adaptive search reaches the same worst-case utility with far fewer trials.
            let mut all = WorstCase::new(oracles(&tables));
            let adaptive = adaptive_search(&mut all, &grid, target).unwrap();
            assert_eq!(adaptive.value, worst, "{target:?}");
            assert!(
                adaptive.generations < grid.len() as u64 * 3 / 4,
                "{}",
                adaptive.generations
            );
            // Under budgets, probes over them on one step skip the others: the same answer,
            // fewer generations, from scratch and (size budgets) from a P_M in force.
            if !matches!(target, UtilitySpec::Quality(_)) {
                let near = Some(Candidate {
                    r: 128,
                    gamma: 0.041,
                    precision: Default::default(),
                });
                for near in [None, near] {
                    let mut all = WorstCase::new(oracles(&tables));
                    let plain = adaptive_search_near(&mut all, &grid, target, near).unwrap();
                    let mut all = WorstCase::new(oracles(&tables)).with_budgets(target.budgets());
                    let cut = adaptive_search_near(&mut all, &grid, target, near).unwrap();
                    assert_eq!(cut.value, worst, "{target:?} from {near:?}");
                    assert!(
                        cut.generations < plain.generations,
                        "{target:?} from {near:?}: {} generations with the budget, {} without",
                        cut.generations,
                        plain.generations
                    );
                }
            }
        }
    }

    fn m(sigma: u64, tau: f64, views: &[f64]) -> Measurement {
        Measurement {
            r: 64,
            gamma: 0.01,
            precision: Default::default(),
            sigma_paper_bytes: None,
            sizing: Sizing {
                sigma_bytes: sigma,
                supersegments: 10,
                tau_secs: tau,
                ..Sizing::default()
            },
            tau_render_secs: 0.0,
            q_db: Db(insitu_core::metrics::pooled_psnr(
                &views.iter().map(|&q| mse_from_psnr(q)).collect::<Vec<_>>(),
            )),
            view_q_db: views.iter().map(|&q| Db(q)).collect(),
            ssim: Some(0.9),
        }
    }

    #[test]
    fn ranks_sum_sigma_and_the_views_mse_and_take_the_slowest_tau() {
        let c = combine_ranks(&[m(100, 0.2, &[30.0, 40.0]), m(50, 0.5, &[30.0, 20.0])]).unwrap();
        assert_eq!(
            (
                c.sizing.sigma_bytes,
                c.sizing.supersegments,
                c.sizing.tau_secs
            ),
            (150, 20, 0.5)
        );
        // View 0: both 30 dB (MSE 1e-3 each) → their sum, 10·log10(2) dB lower; view 1: the
        // sum of 1e-4 and 1e-2.
        assert!((c.view_q_db[0].0 - (30.0 - 10.0 * 2f64.log10())).abs() < 1e-9);
        assert!((c.view_q_db[1].0 - psnr_from_mse(1e-4 + 1e-2)).abs() < 1e-9);
        let all = ((1e-3 + 1e-3) + (1e-4 + 1e-2)) / 2.0;
        assert!((c.q() - psnr_from_mse(all)).abs() < 1e-9);
        // One rank is its own measurement.
        let one = m(100, 0.2, &[30.0, 40.0]);
        assert_eq!(combine_ranks(std::slice::from_ref(&one)).unwrap(), one);
        assert_eq!(combine_ranks(&[]), Err(LiveError::Empty));
        let w = worst_case(&[m(100, 0.2, &[30.0]), m(50, 0.5, &[20.0])]).unwrap();
        assert_eq!(
            (w.sizing.sigma_bytes, w.sizing.tau_secs, w.q()),
            (100, 0.5, 20.0)
        );
    }
}
