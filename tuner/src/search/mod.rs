//! Search strategies over a [`ParamGrid`]: the paper's exhaustive grid (Sec. 5.5) and an
//! adaptive search (the paper's future work, Sec. 5.5 and 7).
//!
//! The adaptive search exploits the monotonicity the paper observes (Sec. 6.1): σ falls and q
//! falls as γ grows, and σ rises with r. For a size budget, the best γ at a given r is the
//! smallest one whose σ is under the budget — one measurement at the smallest γ the
//! neighbouring resolutions allow (when it is under the budget it is the answer), else a
//! bisection over the γ axis (≈ log₂ of its length measurements). The best r is then found
//! by probing about five resolutions spread over the r axis and climbing to better
//! neighbours; resolutions above the first one where even the largest γ misses the budget are
//! skipped. Started from the `P_M` in force (a live tuning), the search walks instead from
//! its resolution outwards in both directions (strides 1, 1, 2, 4, …) while the answers
//! improve, then climbs from the best: the answer is usually near the `P_M` in force, and the
//! resolutions far above it are the dearest to measure. For a quality target it is the mirror
//! image: the largest γ whose q still meets the target, then the r with the smallest σ.
//!
//! A time budget (Eq. 2) has the size budget's shape: τ rises with r (r² rays) and falls a
//! little as γ grows (fewer supersegments to close and write), so at most resolutions either
//! the smallest γ meets it (one probe) or even the largest misses (two probes); only near the
//! resolution where τ crosses the budget does γ need searching. Resolutions being that cheap,
//! a time budget tries every one from the smallest up, until two in a row miss at every γ,
//! instead of climbing: τ is a timing, and a resolution near the budget may come out worse or
//! infeasible by noise alone, which would stop a climb, and q need not be unimodal in r. At
//! each r the smallest γ is probed first, then (where it missed) the largest: a resolution
//! that misses there too is done in two probes. Otherwise γ is probed upwards from the
//! smallest at growing strides rather than bisected over the whole axis: near the budget
//! each probe falls either side of it by chance, and a bisection would settle anywhere on
//! the axis, where galloping stops at the first γ that met it, near the smallest, where q is
//! best. Both budgets at once need both met.
//!
//! Under budgets the probes ask the oracle for σ and τ alone ([`Oracle::measure_sizing`]: a
//! generation and an encoding, no rendering or scoring); only each resolution's answer is
//! measured fully, and kept only if that measurement meets the budgets too.
//!
//! Under a size budget alone, σ is a measurement without noise that falls smoothly as γ grows
//! (close to a power of γ), so the γ where it crosses the budget is interpolated instead of
//! halved: between the nearest γ probed over the budget and the nearest under it, linearly in
//! (ln γ, ln σ) — regula falsi on the grid, with a halving step after any guess that did not
//! halve the bracket, so a narrowing takes at most twice the bisection's probes — and a
//! resolution's first probe is predicted from the nearest resolution already probed, its σ
//! scaled by the ratio of the two r squared. The answer is the bisection's (the smallest γ under
//! the budget, as σ is monotone); the probes are fewer. σ of each probe is kept for the search,
//! so no candidate is probed twice.

use crate::grid::{Candidate, ParamGrid};
use crate::measure::Measurement;
use crate::study::{Oracle, StudyError};
use crate::utility::{best, Utility, UtilitySpec};
use std::collections::BTreeMap;
use std::ops::Range;
use std::time::Instant;

/// The gain in q (dB) a resolution must show over the best so far for the walk along r and
/// the climb to go on from it. Below it neighbouring resolutions differ by less than q moves
/// between alike steps (the ocean's steps at one `P_M` span 0.7 dB): on the tiled orbital's
/// first step at 6 bits r 192, 256 and 320 scored 43.12, 43.10 and 43.18 dB (the precision's
/// ceiling), and the walk that followed 0.08 dB up measured r 384 (0.6 s of a 2.5 s tuning)
/// for 37.1 dB; on the ocean's first step r 320 scored 0.15 dB over r 256, and the walk on
/// to r 384 (its probes and a full trial with its references, 0.34 s of a 1.29 s tuning)
/// scored 1.0 dB less. The answer is still the best resolution measured.
pub const WALK_MARGIN_DB: f64 = 0.2;

/// What a search found and what it cost.
#[derive(Clone, Debug)]
pub struct Outcome {
    /// The best candidate, `None` when no candidate meets the constraint.
    pub best: Option<Measurement>,
    /// ν of the best candidate (`+∞` when none).
    pub value: f64,
    /// Candidates generated (cache hits excluded).
    pub generations: u64,
    /// Sum of τ over those generations, seconds.
    pub generation_secs: f64,
    /// Wall clock of the search, seconds.
    pub wall_secs: f64,
}

/// When a search started: the wall clock, and the oracle's generations and their seconds.
type Start = (Instant, u64, f64);

fn started(oracle: &dyn Oracle) -> Start {
    (
        Instant::now(),
        oracle.generations(),
        oracle.generation_secs(),
    )
}

fn outcome(found: Option<(Measurement, f64)>, oracle: &dyn Oracle, (t, g0, s0): Start) -> Outcome {
    Outcome {
        value: found.as_ref().map_or(f64::INFINITY, |(_, v)| *v),
        best: found.map(|(m, _)| m),
        generations: oracle.generations() - g0,
        generation_secs: oracle.generation_secs() - s0,
        wall_secs: t.elapsed().as_secs_f64(),
    }
}

/// Measures every candidate of `grid` and returns the one minimising `u` (Alg. 1).
///
/// # Errors
/// [`StudyError`] from a measurement; an empty grid.
pub fn grid_search(
    oracle: &mut dyn Oracle,
    grid: &ParamGrid,
    u: &dyn Utility,
) -> Result<Outcome, StudyError> {
    if grid.is_empty() {
        return Err(StudyError::Invalid("the grid is empty".into()));
    }
    let start = started(oracle);
    let rows = grid
        .candidates()
        .into_iter()
        .map(|c| oracle.measure(c))
        .collect::<Result<Vec<_>, _>>()?;
    let found = best(&rows, u).map(|(m, v)| (m.clone(), v));
    Ok(outcome(found, oracle, start))
}

/// σ of a search's size probes by (resolution index, γ index).
type ProbedSigma = BTreeMap<(usize, usize), u64>;

struct Adaptive<'o> {
    oracle: &'o mut dyn Oracle,
    grid: &'o ParamGrid,
    target: UtilitySpec,
    utility: Box<dyn Utility>,
    per_r: BTreeMap<usize, Option<(Measurement, f64)>>,
    /// Under a size budget, the grid point nearest the `P_M` in force: its resolution is
    /// searched first, from its γ (a re-tune's answer is most often near it, and the
    /// production steps have measured it already).
    first: Option<(usize, usize)>,
    /// Under a size budget alone, σ of every probe by (resolution index, γ index): a probe
    /// is not run twice.
    sigma: Option<ProbedSigma>,
    /// Whether the γ axis is searched by interpolation of those σ ([`Adaptive::guess`]).
    interpolate: bool,
}

impl Adaptive<'_> {
    fn candidate(&self, ri: usize, gi: usize) -> Candidate {
        Candidate {
            r: self.grid.rs[ri],
            gamma: self.grid.gammas[gi],
            precision: self.grid.precision(),
        }
    }

    fn measure(&mut self, ri: usize, gi: usize) -> Result<Measurement, StudyError> {
        self.oracle.measure(self.candidate(ri, gi))
    }

    fn feasible(&self, m: &Measurement) -> bool {
        self.utility.value(m) < f64::INFINITY
    }

    /// Whether candidate (`ri`, `gi`) meets the target. Under budgets σ and τ alone decide,
    /// so the probe costs a generation and an encoding but no rendering or scoring
    /// ([`Oracle::measure_sizing`]); a quality target needs the full measurement.
    fn probe(&mut self, ri: usize, gi: usize) -> Result<bool, StudyError> {
        if matches!(self.target, UtilitySpec::Quality(_)) {
            let m = self.measure(ri, gi)?;
            return Ok(self.feasible(&m));
        }
        let budgets = self.target.budgets();
        let (sigma_target, tau_target) = (budgets.size_bytes, budgets.time_secs);
        if let (Some(t), Some(known)) = (sigma_target, &self.sigma) {
            if let Some(&sigma) = known.get(&(ri, gi)) {
                return Ok(sigma < t);
            }
        }
        let s = self.oracle.measure_sizing(self.candidate(ri, gi))?;
        if let Some(known) = &mut self.sigma {
            known.insert((ri, gi), s.sigma_bytes);
        }
        Ok(sigma_target.is_none_or(|t| s.sigma_bytes < t)
            && tau_target.is_none_or(|t| s.tau_secs < t))
    }

    /// σ of this search's probes and the size budget, where the γ axis is interpolated.
    fn interpolation(&self) -> Option<(&ProbedSigma, f64)> {
        let known = self.sigma.as_ref().filter(|_| self.interpolate)?;
        Some((known, self.target.budgets().size_bytes? as f64))
    }

    fn ln_gamma(&self, k: usize) -> f64 {
        f64::from(self.grid.gammas[k].max(1e-9)).ln()
    }

    /// ln γ where σ crosses `budget` on the line in (ln γ, ln σ) through the probes at γ
    /// indices `ka` (σ `sa`, over the budget) and `kb` (σ `sb`, under it); `None` unless
    /// `sa > sb > 0`.
    fn crossing(&self, (ka, sa): (usize, f64), (kb, sb): (usize, f64), budget: f64) -> Option<f64> {
        if !(sa > sb && sb > 0.0) {
            return None;
        }
        let at = (sa.ln() - budget.ln()) / (sa.ln() - sb.ln());
        Some(self.ln_gamma(ka) + at * (self.ln_gamma(kb) - self.ln_gamma(ka)))
    }

    /// The first γ index of `range` at or past ln γ = `x`.
    fn first_past(&self, mut range: Range<usize>, x: f64) -> Option<usize> {
        range.find(|&k| self.ln_gamma(k) >= x)
    }

    /// Under a size budget alone, the γ index in `lo..hi` to probe next at resolution `ri`:
    /// where σ crosses the budget between the largest γ index probed at or below `lo` (over
    /// the budget) and `hi` (probed, under it), interpolated linearly in (ln γ, ln σ), rounded
    /// up to the grid (the first γ at or past the crossing). `None` without both probes.
    fn guess(&self, ri: usize, lo: usize, hi: usize) -> Option<usize> {
        let (known, budget) = self.interpolation()?;
        let (ka, sa) = known
            .range((ri, 0)..=(ri, lo))
            .next_back()
            .map(|(&(_, k), &s)| (k, s as f64))
            .filter(|&(_, s)| s >= budget)?;
        let sb = *known.get(&(ri, hi))? as f64;
        let x = self.crossing((ka, sa), (hi, sb), budget)?;
        Some(self.first_past(lo..hi, x).unwrap_or(hi - 1))
    }

    /// Under a size budget alone, the γ index in `lo..=hi` where σ at resolution `ri` is
    /// predicted to cross the budget: the probes of the nearest resolution probed, scaled by
    /// the ratio of the two resolutions squared (σ grows with the r² rays), interpolated as in
    /// [`Adaptive::guess`]. `None` when that resolution's probes do not straddle the budget.
    fn predict(&self, ri: usize, lo: usize, hi: usize) -> Option<usize> {
        let (known, budget) = self.interpolation()?;
        let rj = known
            .keys()
            .map(|&(r, _)| r)
            .filter(|&r| r != ri)
            .min_by_key(|&r| r.abs_diff(ri))?;
        let scale = (f64::from(self.grid.rs[ri]) / f64::from(self.grid.rs[rj])).powi(2);
        let probes: Vec<(usize, f64)> = known
            .range((rj, 0)..=(rj, usize::MAX))
            .map(|(&(_, k), &s)| (k, s as f64 * scale))
            .collect();
        let a = probes.iter().copied().rfind(|p| p.1 >= budget)?;
        let b = probes.iter().copied().find(|p| p.1 < budget && p.0 > a.0)?;
        let x = self.crossing(a, b, budget)?;
        let k = self.first_past(0..self.grid.gammas.len(), x).unwrap_or(b.0);
        Some(k.clamp(lo, hi))
    }

    /// Bounds on the γ index of resolution `ri`'s answer from the nearest resolutions already
    /// answered below and above it (the whole axis when there are none or they disagree).
    fn bracket(&self, ri: usize) -> (usize, usize) {
        let n = self.grid.gammas.len();
        let index = |v: &Option<(Measurement, f64)>| {
            v.as_ref().and_then(|(m, _)| {
                self.grid
                    .gammas
                    .iter()
                    .position(|g| g.to_bits() == m.gamma.to_bits())
            })
        };
        let lo = self
            .per_r
            .range(..ri)
            .rev()
            .find_map(|(_, v)| index(v))
            .unwrap_or(0);
        let hi = self
            .per_r
            .range(ri + 1..)
            .find_map(|(_, v)| index(v))
            .unwrap_or(n - 1);
        if lo <= hi {
            (lo, hi)
        } else {
            (0, n - 1)
        }
    }

    /// The best feasible γ at resolution `ri` (bisection), with its ν.
    fn best_at(&mut self, ri: usize) -> Result<Option<(Measurement, f64)>, StudyError> {
        if let Some(v) = self.per_r.get(&ri) {
            return Ok(v.clone());
        }
        // Search in "boundary order" k: feasibility is upward-closed in k and the best γ is
        // the smallest feasible k. For budgets k is the γ index (feasible for γ ≥ γ*,
        // smallest γ best); for a quality target it runs backwards (feasible for γ ≤ γ*,
        // largest γ best).
        let n = self.grid.gammas.len();
        let forward = !matches!(self.target, UtilitySpec::Quality(_));
        let gamma_index = |k: usize| if forward { k } else { n - 1 - k };
        let k = if self.target.budgets().time_secs.is_some() {
            self.gallop(ri)?
        } else {
            self.bisect(ri, forward)?
        };
        // The answer is measured fully (a quality target's probe already was: the oracle
        // answers it again from its cache or trials).
        let found = match k {
            Some(k) => {
                let m = self.measure(ri, gamma_index(k))?;
                let v = self.utility.value(&m);
                (v < f64::INFINITY).then_some((m, v))
            }
            None => None,
        };
        self.per_r.insert(ri, found.clone());
        Ok(found)
    }

    /// The smallest feasible k at resolution `ri`, by bisection. γ* grows with r, so the
    /// neighbouring resolutions' answers bracket it.
    fn bisect(&mut self, ri: usize, forward: bool) -> Result<Option<usize>, StudyError> {
        let n = self.grid.gammas.len();
        let gamma_index = |k: usize| if forward { k } else { n - 1 - k };
        let (blo, bhi) = self.bracket(ri);
        let (mut lo, mut hi) = if forward {
            (blo, bhi)
        } else {
            (n - 1 - bhi, n - 1 - blo)
        };
        // Starting at the P_M in force: its γ splits the axis, feasible ones below it (the
        // answer at or under it: itself when the γ below misses, as on a re-tune of data that
        // changed little) or not (the answer above it).
        if let Some((_, g)) = self.first.take_if(|f| forward && f.0 == ri) {
            if self.probe(ri, g)? {
                if g == 0 || !self.probe(ri, g - 1)? {
                    return Ok(Some(g));
                }
                (lo, hi) = (lo.min(g - 1), g - 1);
                if lo < hi && self.probe(ri, lo)? {
                    return Ok(Some(lo));
                }
                return self.narrow(ri, lo, hi, gamma_index).map(Some);
            }
            (lo, hi) = (g + 1, n - 1);
            if lo > hi || !self.probe(ri, hi)? {
                return Ok(None);
            }
            return self.narrow(ri, lo, hi, gamma_index).map(Some);
        }
        // Under a size budget alone, where the other resolutions' σ predict the answer: that γ
        // and the one below it, which settle it when the prediction is right.
        if let Some(k) = self.predict(ri, lo, hi) {
            if self.probe(ri, k)? {
                if k == lo || !self.probe(ri, k - 1)? {
                    return Ok(Some(k));
                }
                return self.narrow(ri, lo, k - 1, gamma_index).map(Some);
            }
            lo = (k + 1).min(hi);
        }
        // The bracket's best end first: when it is feasible it is the answer (one measurement
        // instead of a bisection; common when the budget is loose for this r).
        if self.probe(ri, gamma_index(lo))? {
            return Ok(Some(lo));
        }
        let mut feasible = self.probe(ri, gamma_index(hi))?;
        if !feasible && hi < n - 1 {
            (lo, hi) = (hi + 1, n - 1);
            feasible = self.probe(ri, gamma_index(hi))?;
        }
        if !feasible {
            return Ok(None);
        }
        self.narrow(ri, lo, hi, gamma_index).map(Some)
    }

    /// The smallest k in `lo..=hi` found feasible by bisection, `hi` known feasible; under a
    /// size budget alone by interpolation ([`Adaptive::guess`]), halving after any guess that
    /// did not halve the bracket.
    fn narrow(
        &mut self,
        ri: usize,
        mut lo: usize,
        mut hi: usize,
        gamma_index: impl Fn(usize) -> usize,
    ) -> Result<usize, StudyError> {
        let mut halve = false;
        while lo < hi {
            let width = hi - lo;
            let guess = (!halve).then(|| self.guess(ri, lo, hi)).flatten();
            let mid = guess.unwrap_or((lo + hi) / 2);
            if self.probe(ri, gamma_index(mid))? {
                hi = mid;
            } else {
                lo = mid + 1;
            }
            halve = guess.is_some() && 2 * (hi - lo) > width;
        }
        Ok(lo)
    }

    /// The smallest feasible γ index at resolution `ri` under a time budget: the smallest γ,
    /// and where it misses the largest; where that meets the budget, probes from the
    /// smallest up at growing strides (1, 3, 7, …) and a bisection of the last gap. τ falls
    /// only a little as γ grows, so where the largest γ misses every γ does (within the
    /// timing's noise): the resolution costs two probes, not a gallop over the axis that
    /// would stop at a timing that fell under the budget by chance. Timings near the budget
    /// fall either side of it by noise, so a bisection of the whole axis would settle
    /// anywhere; galloping stops at the first γ that met it, near the smallest, where q is
    /// best. The neighbours' answers are not trusted as a bracket: they are as noisy.
    fn gallop(&mut self, ri: usize) -> Result<Option<usize>, StudyError> {
        let last = self.grid.gammas.len() - 1;
        if self.probe(ri, 0)? {
            return Ok(Some(0));
        }
        if last == 0 || !self.probe(ri, last)? {
            return Ok(None);
        }
        let (mut missed, mut k, mut stride) = (0, 1, 2);
        while k < last && !self.probe(ri, k)? {
            missed = k;
            k = (k + stride).min(last);
            stride *= 2;
        }
        self.narrow(ri, missed + 1, k, |k| k).map(Some)
    }

    fn run(&mut self) -> Result<Option<(Measurement, f64)>, StudyError> {
        if self.target.budgets().time_secs.is_some() {
            return self.sweep();
        }
        let n = self.grid.rs.len();
        if let Some((ri, _)) = self.first {
            return self.gallop_r(ri);
        }
        let stride = (n / 5).max(1);
        let mut probes: Vec<usize> = (0..n).step_by(stride).collect();
        if probes.last() != Some(&(n - 1)) {
            probes.push(n - 1);
        }
        let mut best: Option<(usize, f64)> = None;
        for ri in probes {
            match self.best_at(ri)? {
                Some((_, v)) if best.is_none_or(|(_, b)| v < b) => best = Some((ri, v)),
                Some(_) => {}
                // σ and τ rise with r: no larger r can meet a budget this one misses.
                None if !matches!(self.target, UtilitySpec::Quality(_)) => break,
                None => {}
            }
        }
        self.climb_from(best)
    }

    /// Under a size budget, from the resolution of the `P_M` in force (`start`) along the r
    /// axis: in each direction at doubling strides after a second single step (1, 1, 2, 4, …
    /// resolutions) while each is better than the best so far by [`WALK_MARGIN_DB`] (upwards
    /// also ending at the first resolution that cannot meet the budget: σ rises with r), then
    /// by single resolutions to neighbours better by as much ([`Adaptive::climb_from`]). The
    /// answer of a re-tune is most often near the `P_M` in force, and the resolutions far above
    /// it are the dearest to measure (a full trial at r = 512 costs about five at r = 192), so
    /// the spread over the whole axis is not paid.
    fn gallop_r(&mut self, start: usize) -> Result<Option<(Measurement, f64)>, StudyError> {
        let last = self.grid.rs.len() - 1;
        let margin = self.margin();
        let mut best = self.best_at(start)?.map(|(_, v)| (start, v));
        // No larger r meets a budget that `start` misses at every γ.
        let directions: &[bool] = if best.is_some() {
            &[true, false]
        } else {
            &[false]
        };
        for &up in directions {
            let (mut at, mut taken) = (start, 0u32);
            loop {
                // Strides 1, 1, 2, 4, …: a second single step before doubling, so that an
                // answer one resolution past the first improvement (the common case) is not
                // overshot by a dearer resolution that the climb would not have measured.
                let stride = 1usize << taken.saturating_sub(1);
                let next = if up {
                    (at + stride).min(last)
                } else {
                    at.saturating_sub(stride)
                };
                if next == at {
                    break;
                }
                match self.best_at(next)? {
                    Some((_, v)) if best.is_none_or(|(_, b)| v < b - margin) => {
                        best = Some((next, v))
                    }
                    // Below a resolution that met nothing, keep walking down until one does
                    // (upwards, no larger r meets a budget this one misses).
                    None if !up && best.is_none() => {}
                    _ => break,
                }
                at = next;
                taken += 1;
            }
        }
        self.climb_from(best)
    }

    /// From the best resolution so far (its index and ν; `None`: no resolution met the
    /// target, and no answer), to a better neighbour while there is one; the best
    /// resolution's answer.
    fn climb_from(
        &mut self,
        best: Option<(usize, f64)>,
    ) -> Result<Option<(Measurement, f64)>, StudyError> {
        let Some((mut at, mut value)) = best else {
            return Ok(None);
        };
        let (n, margin) = (self.grid.rs.len(), self.margin());
        loop {
            let mut moved = false;
            for ri in [at.wrapping_sub(1), at + 1] {
                if ri >= n {
                    continue;
                }
                if let Some((_, v)) = self.best_at(ri)? {
                    if v < value - margin {
                        (at, value, moved) = (ri, v, true);
                    }
                }
            }
            if !moved {
                break;
            }
        }
        // The best answer measured: a neighbour better by less than the margin is kept.
        Ok(self
            .per_r
            .values()
            .flatten()
            .min_by(|a, b| a.1.total_cmp(&b.1))
            .cloned())
    }

    /// How much better (ν) a resolution must be for the walk or the climb to go on from it:
    /// [`WALK_MARGIN_DB`] under budgets (ν is −q in dB), none for a quality target (ν is σ).
    fn margin(&self) -> f64 {
        if matches!(self.target, UtilitySpec::Quality(_)) {
            0.0
        } else {
            WALK_MARGIN_DB
        }
    }

    /// Under a time budget: every resolution from the smallest up, until two in a row meet
    /// the budget at no γ (one could by the timing's noise alone), and the best of their
    /// answers. A resolution costs one or two probes there (τ hardly depends on γ), so
    /// trying each is cheap, and it does not rely on q being unimodal in r, which it need
    /// not be (a VDI at the test views' resolution matches their pixels at its own view).
    fn sweep(&mut self) -> Result<Option<(Measurement, f64)>, StudyError> {
        let mut best: Option<(usize, f64)> = None;
        let mut misses = 0;
        for ri in 0..self.grid.rs.len() {
            match self.best_at(ri)? {
                Some((_, v)) => {
                    misses = 0;
                    if best.is_none_or(|(_, b)| v < b) {
                        best = Some((ri, v));
                    }
                }
                None => {
                    misses += 1;
                    if misses == 2 {
                        break;
                    }
                }
            }
        }
        Ok(best.and_then(|(at, _)| self.per_r.get(&at).cloned().flatten()))
    }
}

/// The adaptive search for `target` (any built-in utility: size or time budgets, both, or a
/// quality target) over `grid` (see the module docs).
///
/// # Errors
/// [`StudyError`] from a measurement; an empty grid.
pub fn adaptive_search(
    oracle: &mut dyn Oracle,
    grid: &ParamGrid,
    target: UtilitySpec,
) -> Result<Outcome, StudyError> {
    adaptive_search_near(oracle, grid, target, None)
}

/// [`adaptive_search`] that, under a size budget, starts from `near` (the `P_M` in force,
/// whose σ the production steps have measured): the grid's resolution nearest its r is
/// searched first, from the γ nearest its own (on a log scale), then the resolutions
/// outwards from it in both directions at doubling strides while they improve, and the best
/// one's neighbours (instead of a spread over the whole r axis). Where q at each
/// resolution's answer rises to one peak and falls beyond it (the paper's Fig. 7), the
/// answer is the one [`adaptive_search`] finds; it costs fewer probes and far fewer full
/// trials, since the answer is usually near the `P_M` in force and the resolutions far above
/// it are the dearest to measure.
///
/// # Errors
/// As [`adaptive_search`].
pub fn adaptive_search_near(
    oracle: &mut dyn Oracle,
    grid: &ParamGrid,
    target: UtilitySpec,
    near: Option<Candidate>,
) -> Result<Outcome, StudyError> {
    adaptive(oracle, grid, target, near, true)
}

/// [`adaptive_search_near`], searching the γ axis by interpolation under a size budget alone
/// when `interpolate` (by bisection otherwise, as under the other targets). With several
/// precisions in `grid`, the (r, γ) search runs at each (the coarsest first; `near` at its
/// own precision) and the best answer wins: σ and q both change with the precision, so which
/// one buys the most picture within a budget is measured, not assumed.
fn adaptive(
    oracle: &mut dyn Oracle,
    grid: &ParamGrid,
    target: UtilitySpec,
    near: Option<Candidate>,
    interpolate: bool,
) -> Result<Outcome, StudyError> {
    if grid.is_empty() {
        return Err(StudyError::Invalid("the grid is empty".into()));
    }
    if grid.precisions.len() == 1 {
        return adaptive_at(oracle, grid, target, near, interpolate);
    }
    let start = started(oracle);
    let mut found: Option<(Measurement, f64)> = None;
    for &p in &grid.precisions {
        let sub = grid.at(p);
        let near = near.map(|c| Candidate { precision: p, ..c });
        let o = adaptive_at(oracle, &sub, target, near, interpolate)?;
        if let Some(m) = o.best {
            if found.as_ref().is_none_or(|(_, v)| o.value < *v) {
                found = Some((m, o.value));
            }
        }
    }
    Ok(outcome(found, oracle, start))
}

/// [`adaptive`] over a grid of one precision.
fn adaptive_at(
    oracle: &mut dyn Oracle,
    grid: &ParamGrid,
    target: UtilitySpec,
    near: Option<Candidate>,
    interpolate: bool,
) -> Result<Outcome, StudyError> {
    let start = started(oracle);
    let budgets = target.budgets();
    let size_only = budgets.size_bytes.is_some() && budgets.time_secs.is_none();
    let nearest = |xs: &[f64], x: f64| {
        (0..xs.len()).min_by(|&a, &b| (xs[a] - x).abs().total_cmp(&(xs[b] - x).abs()))
    };
    let first = near.filter(|_| size_only).and_then(|c| {
        let rs: Vec<f64> = grid.rs.iter().map(|&r| f64::from(r)).collect();
        let gs: Vec<f64> = grid
            .gammas
            .iter()
            .map(|&g| f64::from(g.max(1e-9)).ln())
            .collect();
        Some((
            nearest(&rs, f64::from(c.r))?,
            nearest(&gs, f64::from(c.gamma.max(1e-9)).ln())?,
        ))
    });
    let mut a = Adaptive {
        oracle,
        grid,
        target,
        utility: target.utility(),
        per_r: BTreeMap::new(),
        first,
        sigma: size_only.then(BTreeMap::new),
        interpolate,
    };
    let found = a.run()?;
    Ok(outcome(found, a.oracle, start))
}

/// The paper's ladder of size budgets (Fig. 8): from just above the smallest σ of `rows`,
/// each 1.5× the previous, up to the largest σ.
pub fn size_ladder(rows: &[Measurement]) -> Vec<u64> {
    let lo = rows.iter().map(|m| m.sizing.sigma_bytes).min().unwrap_or(0);
    let hi = rows.iter().map(|m| m.sizing.sigma_bytes).max().unwrap_or(0);
    let mut out = Vec::new();
    let mut t = (lo as f64 * 1.5).max(1.0);
    while t <= hi as f64 * 1.5 {
        out.push(t.round() as u64);
        t *= 1.5;
    }
    out
}

#[cfg(test)]
mod tests;
