//! Tuning across a time series (Sec. 6.2, Table 1, Sec. 7): pick characteristic time steps,
//! tune on each, choose the `P_M` that meets the constraint on all of them, and cross-evaluate.
//!
//! **Rule for characteristic steps.** Each step is summarised by a 64-bin histogram of its
//! finite values over the range common to all steps (NaN, e.g. land in an ocean model, is left
//! out), normalised to sum 1. The distance of two steps is the total-variation distance of
//! their histograms, `½ Σ |h_a − h_b|` ∈ [0, 1]. Steps are chosen by farthest-first traversal
//! (greedy k-centre, a 2-approximation of the optimal covering radius) starting from the first
//! step: the step farthest from all chosen ones is added until every step is within
//! `threshold` of a chosen one, or `max_steps` are chosen.

use crate::grid::Candidate;
use crate::measure::Measurement;
use crate::utility::Utility;

/// Histogram bins.
pub const BINS: usize = insitu_core::volume::HISTOGRAM_BINS;

/// Normalised histograms of `steps` over their common finite range (all-NaN steps give an
/// all-zero histogram).
pub fn histograms(steps: &[&[f32]]) -> Vec<[f64; BINS]> {
    let (lo, hi) = steps
        .iter()
        .flat_map(|s| s.iter())
        .filter(|v| v.is_finite())
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), &v| {
            (lo.min(v), hi.max(v))
        });
    let width = if hi > lo { f64::from(hi - lo) } else { 1.0 };
    steps
        .iter()
        .map(|s| {
            let mut h = [0.0f64; BINS];
            let mut n = 0usize;
            for &v in s.iter().filter(|v| v.is_finite()) {
                let b = ((f64::from(v - lo) / width) * BINS as f64) as usize;
                h[b.min(BINS - 1)] += 1.0;
                n += 1;
            }
            if n > 0 {
                h.iter_mut().for_each(|x| *x /= n as f64);
            }
            h
        })
        .collect()
}

/// Total-variation distance of two normalised histograms, in [0, 1].
pub fn distance(a: &[f64; BINS], b: &[f64; BINS]) -> f64 {
    0.5 * a.iter().zip(b).map(|(x, y)| (x - y).abs()).sum::<f64>()
}

/// Characteristic steps by farthest-first traversal (see the module docs), ascending.
pub fn characteristic_steps(hists: &[[f64; BINS]], threshold: f64, max_steps: usize) -> Vec<usize> {
    if hists.is_empty() {
        return Vec::new();
    }
    let mut chosen = vec![0usize];
    let mut nearest: Vec<f64> = hists.iter().map(|h| distance(h, &hists[0])).collect();
    while chosen.len() < max_steps.max(1) {
        let (far, d) = nearest
            .iter()
            .copied()
            .enumerate()
            .max_by(|a, b| a.1.total_cmp(&b.1))
            .unwrap_or((0, 0.0));
        if d <= threshold {
            break;
        }
        chosen.push(far);
        for (i, n) in nearest.iter_mut().enumerate() {
            *n = n.min(distance(&hists[i], &hists[far]));
        }
    }
    chosen.sort_unstable();
    chosen
}

fn row(rows: &[Measurement], c: Candidate) -> Option<&Measurement> {
    rows.iter().find(|m| m.candidate().key() == c.key())
}

/// The conservative choice: among candidates measured on every step and feasible on all of
/// them, the one whose worst ν over the steps is best (for ν_size: the highest minimum q).
/// `None` when no candidate is feasible on all steps.
pub fn conservative(per_step: &[Vec<Measurement>], u: &dyn Utility) -> Option<(Candidate, f64)> {
    let first = per_step.first()?;
    first
        .iter()
        .filter_map(|m| {
            let c = m.candidate();
            let worst = per_step
                .iter()
                .map(|rows| row(rows, c).map_or(f64::INFINITY, |m| u.value(m)))
                .fold(f64::NEG_INFINITY, f64::max);
            (worst < f64::INFINITY).then_some((c, worst))
        })
        .min_by(|a, b| a.1.total_cmp(&b.1))
}

/// One cell of the cross-evaluation table: `P_M` tuned on step A, measured on step B.
#[derive(Clone, Debug, PartialEq)]
pub struct Cross {
    /// Index of the tuning step.
    pub tuned_on: usize,
    /// Index of the evaluation step.
    pub evaluated_on: usize,
    /// The measurement on B (`None` when A had no feasible `P_M`).
    pub on_b: Option<Measurement>,
    /// Whether the constraint still holds on B.
    pub holds: bool,
}

/// Table 1: for every pair of steps, the optimum of A measured on B.
pub fn cross_table(per_step: &[Vec<Measurement>], u: &dyn Utility) -> Vec<Cross> {
    let optima: Vec<Option<Candidate>> = per_step
        .iter()
        .map(|rows| crate::utility::best(rows, u).map(|(m, _)| m.candidate()))
        .collect();
    let mut out = Vec::new();
    for (a, opt) in optima.iter().enumerate() {
        for (b, rows) in per_step.iter().enumerate() {
            let on_b = opt.and_then(|c| row(rows, c).cloned());
            let holds = on_b.as_ref().is_some_and(|m| u.value(m) < f64::INFINITY);
            out.push(Cross {
                tuned_on: a,
                evaluated_on: b,
                on_b,
                holds,
            });
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::utility::SizeBudget;
    use insitu_core::evaluate::Sizing;
    use insitu_core::metrics::Db;

    #[test]
    fn farthest_first_picks_the_regimes_of_a_series() {
        // Three regimes: values near 0 (steps 0–3), near 5 (4–7), near 10 (8–11).
        let steps: Vec<Vec<f32>> = (0..12)
            .map(|t| {
                (0..500)
                    .map(|i| (t / 4) as f32 * 5.0 + (i % 7) as f32 * 0.01)
                    .collect()
            })
            .collect();
        let refs: Vec<&[f32]> = steps.iter().map(Vec::as_slice).collect();
        let h = histograms(&refs);
        assert!(distance(&h[0], &h[1]) < 1e-12);
        assert!((distance(&h[0], &h[11]) - 1.0).abs() < 1e-12);
        let picked = characteristic_steps(&h, 0.05, 8);
        assert_eq!(picked.len(), 3, "{picked:?}");
        let regimes: Vec<usize> = picked.iter().map(|&s| s / 4).collect();
        assert_eq!(regimes, vec![0, 1, 2]);
        assert_eq!(characteristic_steps(&h, 0.05, 2).len(), 2);
        assert_eq!(characteristic_steps(&h, 1.0, 8), vec![0]);
        // NaN is ignored, all-NaN is an empty histogram.
        let nan = [f32::NAN; 4];
        let h = histograms(&[&nan, &[1.0, f32::NAN]]);
        assert_eq!(h[0].iter().sum::<f64>(), 0.0);
        assert!((h[1].iter().sum::<f64>() - 1.0).abs() < 1e-12);
    }

    fn m(r: u32, sigma: u64, q: f64) -> Measurement {
        Measurement {
            r,
            gamma: 0.1,
            precision: Default::default(),
            sigma_paper_bytes: None,
            sizing: Sizing {
                sigma_bytes: sigma,
                ..Sizing::default()
            },
            tau_render_secs: 0.0,
            q_db: Db(q),
            view_q_db: vec![],
            ssim: None,
        }
    }

    #[test]
    fn the_conservative_choice_meets_the_budget_everywhere() {
        // Step 0 prefers r = 2 (σ 90 < 100); on step 1 r = 2 needs σ 120: over budget.
        let per_step = vec![
            vec![m(1, 50, 30.0), m(2, 90, 35.0)],
            vec![m(1, 60, 31.0), m(2, 120, 36.0)],
        ];
        let u = SizeBudget { sigma_target: 100 };
        let (c, worst) = conservative(&per_step, &u).unwrap();
        assert_eq!((c.r, worst), (1, -30.0));
        let t = cross_table(&per_step, &u);
        assert_eq!(t.len(), 4);
        let cell = |a, b| {
            t.iter()
                .find(|x| x.tuned_on == a && x.evaluated_on == b)
                .unwrap()
        };
        assert!(cell(0, 0).holds && !cell(0, 1).holds && cell(1, 0).holds && cell(1, 1).holds);
        assert!(conservative(&per_step, &SizeBudget { sigma_target: 55 }).is_none());
    }
}
