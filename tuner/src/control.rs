//! Closed-loop control of `P_M` between tunings: the tuner's rate control.
//!
//! A tuning measures σ and τ of candidates on the characteristic steps, which are past steps;
//! a drifting simulation outgrows what was measured before the decision lands. A video
//! encoder's rate control has the same problem (x264's ABR: a model of the frame size updated
//! from every frame's actual size), and the same answer serves here:
//!
//! - [`Surface`]: the measured σ(r, γ) and τ(r, γ) of the characteristic steps (their worst
//!   case), interpolated between measured candidates (log σ piecewise linear in log γ at a
//!   resolution; σ and τ ∝ r² across resolutions, as the rays are r²).
//! - Every production step is a free measurement of its own `P_M` on the newest data: its
//!   σ over the surface's σ at that `P_M` is the *ratio* k (1 when the production data is as
//!   the characteristic steps were). [`Controller::observe`] records it.
//! - [`Forecast`]: k at the step a new `P_M` will apply to, from the trend of k over recent
//!   production steps (the median slope between consecutive steps of one `P_M`, or of any
//!   while none repeats, so that an error of the surface at one candidate, a jump between two
//!   steps, does not read as growth; only growth is extrapolated, a shrinking field keeps its
//!   latest k). For τ, the slowest step of the window carried forward by τ's own growth (a
//!   Theil–Sen slope, no more than σ's: timings are noisy, σ is not).
//! - [`Controller::choose`]: the finest candidate, not finer than the tuned one, whose σ and τ
//!   scaled by the forecast meet the plan `(1 − headroom) × budget`: the tuned resolution with
//!   γ stepped up, and a lower resolution when γ alone would need more than
//!   [`gamma_span`] times the tuned γ. [`Controller::correct`] says when that warrants a
//!   change: at once when the `P_M` in force misses the plan, back towards the tuned one only
//!   when the finer candidate clears the plan by the hysteresis (so steps that hover near the
//!   budget do not flip the `P_M` back and forth, and still data changes nothing).

use crate::grid::{Candidate, ParamGrid};
use std::collections::{BTreeMap, VecDeque};

/// Production steps the controller remembers (the forecast's window).
pub const WINDOW: usize = 8;

/// How far γ may be raised above the tuned γ at a resolution before a lower resolution is
/// preferred, for a grid with one resolution (see [`gamma_span`]).
pub const GAMMA_SPAN: f32 = 1.3;

/// How far γ may be raised above the tuned γ at resolution `r` of `rs` (ascending) before the
/// next lower resolution is preferred: the factor by which r would fall to it (for the lowest,
/// the factor from it to the next higher; [`GAMMA_SPAN`] for a grid of one). γ absorbs what lies
/// between two resolutions, and no more: on drifting Gray–Scott 128³ the best `P_M` per step in
/// hindsight kept γ near the tuned one and lowered r (r 192, γ 0.033 where the tuned r 256 would
/// need γ 0.065 for the same σ: 2.1 dB more q; the span from 256 to 192 is 1.33); after the F/k
/// switch it raised γ at r 128 to 0.073 (1.8× the tuned 0.041) rather than halve r to 64, which
/// cost 5 dB (the span from 128 to 64 is 2).
pub fn gamma_span(rs: &[u32], r: u32) -> f32 {
    let below = rs.iter().copied().filter(|&x| x < r).max();
    let above = rs.iter().copied().filter(|&x| x > r).min();
    match (below, above) {
        (Some(b), _) if b > 0 => r as f32 / b as f32,
        (_, Some(a)) if r > 0 => a as f32 / r as f32,
        _ => GAMMA_SPAN,
    }
}

/// The most growth a forecast extrapolates (a factor on σ).
pub const MAX_GROWTH: f64 = 4.0;

/// Slope of ln σ over ln γ assumed at a resolution measured at one γ only, when no other
/// resolution has two (σ ∝ 1/γ: supersegments close at a rate set by γ).
const DEFAULT_SIGMA_SLOPE: f64 = -1.0;

/// Slope bounds of ln σ over ln γ (σ falls as γ grows; never faster than γ⁻⁴), and beyond the
/// measured γ never flatter than γ^−½: two probes of nearly equal σ give a flat end segment,
/// which would promise that no γ can lower σ (the error then shows in the next production
/// step's ratio and is corrected there).
const SIGMA_SLOPE: (f64, f64, f64) = (-4.0, 0.0, -0.5);

/// One measured candidate: its σ (bytes) and τ (seconds), worst case over the characteristic
/// steps (σ summed over a step's ranks, τ of its slowest rank).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Point {
    /// The candidate.
    pub candidate: Candidate,
    /// σ, bytes (> 0 to count).
    pub sigma_bytes: f64,
    /// τ, seconds (> 0 to count for τ).
    pub tau_secs: f64,
}

/// A measured `(ln γ, ln value)` curve at one resolution.
type Curve = Vec<(f64, f64)>;

/// σ, τ and q at one precision, by resolution.
#[derive(Clone, Debug, Default)]
struct Layer {
    sigma: BTreeMap<u32, Curve>,
    /// ln τ of the slowest timing at each resolution (see [`Surface::tau`]).
    tau: BTreeMap<u32, f64>,
    /// q (dB) over ln γ at each resolution where trials scored candidates (see
    /// [`Surface::q`]).
    q: BTreeMap<u32, Curve>,
}

/// σ and τ over the candidate plane, from measured points, each precision on its own: σ at
/// 8 bits says nothing of σ at 6 bits or as floats, so a candidate is read from the points of
/// its own precision only. A surface holds every precision its points came at, so that a
/// production step made at one precision (the nodes' configured `P_M`, say) gives the
/// controller its ratio while the tuning chose another.
#[derive(Clone, Debug, Default)]
pub struct Surface {
    layers: BTreeMap<u32, Layer>,
}

impl Surface {
    /// The surface through `points`; points with a σ or τ that is not a positive finite number
    /// leave that quantity out. The same candidate twice keeps the larger value.
    pub fn new(points: impl IntoIterator<Item = Point>) -> Self {
        let mut s = Self::default();
        for p in points {
            let (r, g) = (p.candidate.r, f64::from(p.candidate.gamma));
            if !(r > 0 && g > 0.0 && g.is_finite()) {
                continue;
            }
            let layer = s.layers.entry(p.candidate.precision.bits()).or_default();
            let valid = |v: f64| v > 0.0 && v.is_finite();
            if valid(p.sigma_bytes) {
                insert(
                    layer.sigma.entry(r).or_default(),
                    g.ln(),
                    p.sigma_bytes.ln(),
                );
            }
            if valid(p.tau_secs) {
                let slowest = layer.tau.entry(r).or_insert(f64::NEG_INFINITY);
                *slowest = slowest.max(p.tau_secs.ln());
            }
        }
        s
    }

    /// The surface with the q (dB) the trials scored: `(candidate, q)` pairs, the worst case
    /// over the characteristic steps; pairs with a q that is not finite are left out; the same
    /// candidate twice keeps the smaller q.
    pub fn with_q(mut self, scored: impl IntoIterator<Item = (Candidate, f64)>) -> Self {
        for (c, q) in scored {
            let g = f64::from(c.gamma);
            if !(c.r > 0 && g > 0.0 && g.is_finite() && q.is_finite()) {
                continue;
            }
            let layer = self.layers.entry(c.precision.bits()).or_default();
            let curve = layer.q.entry(c.r).or_default();
            match curve.binary_search_by(|p| p.0.total_cmp(&g.ln())) {
                Ok(i) => curve[i].1 = curve[i].1.min(q),
                Err(i) => curve.insert(i, (g.ln(), q)),
            }
        }
        self
    }

    fn layer(&self, c: Candidate) -> Option<&Layer> {
        self.layers.get(&c.precision.bits())
    }

    /// q of `c`, dB, where the trials scored its resolution on both sides of its γ (or at its
    /// γ), at its precision: interpolated linearly in ln γ between the two nearest scored;
    /// `None` elsewhere (q is not extrapolated, and across resolutions it is not one curve: it
    /// peaks at some r, Fig. 7).
    pub fn q(&self, c: Candidate) -> Option<f64> {
        let curve = self.layer(c)?.q.get(&c.r)?;
        let x = f64::from(c.gamma).ln();
        let i = curve.iter().position(|p| p.0 >= x)?;
        let b = curve[i];
        if b.0 == x {
            return Some(b.1);
        }
        let a = curve[i.checked_sub(1)?];
        Some(a.1 + (b.1 - a.1) * (x - a.0) / (b.0 - a.0))
    }

    /// Whether no σ was measured.
    pub fn is_empty(&self) -> bool {
        self.layers.values().all(|l| l.sigma.is_empty())
    }

    /// σ of `c`, bytes; `None` when nothing was measured at its precision.
    pub fn sigma(&self, c: Candidate) -> Option<f64> {
        predict(&self.layer(c)?.sigma, c, SIGMA_SLOPE, DEFAULT_SIGMA_SLOPE)
    }

    /// The smallest γ measured at `c`'s precision at the resolution that stands for `c.r`
    /// (the nearest measured, in ln r): below it σ is extrapolated.
    pub fn gamma_floor(&self, c: Candidate) -> Option<f32> {
        nearest(&self.layer(c)?.sigma, c.r)
            .and_then(|(_, c)| c.first())
            .map(|p| p.0.exp() as f32)
    }

    /// τ of `c`, seconds: the largest τ measured at its precision at the resolution nearest
    /// `c`'s (in ln r), whatever the γ, scaled by `(r / r_measured)²`; `None` when no τ was
    /// measured. τ falls only a little as γ grows (fewer supersegments to close and write),
    /// less than two timings of one candidate differ on a busy machine, so a curve through
    /// the timings at one r would have the controller raise γ — losing q — to chase a fast
    /// timing; it steps r for τ instead and keeps the finest γ there.
    pub fn tau(&self, c: Candidate) -> Option<f64> {
        if c.r == 0 {
            return None;
        }
        let (r0, &slowest) = nearest(&self.layer(c)?.tau, c.r)?;
        Some((slowest + 2.0 * (f64::from(c.r).ln() - f64::from(r0).ln())).exp())
    }
}

/// Adds `(x, y)` to a curve kept sorted by x; the same x keeps the larger y.
fn insert(curve: &mut Curve, x: f64, y: f64) {
    match curve.binary_search_by(|p| p.0.total_cmp(&x)) {
        Ok(i) => curve[i].1 = curve[i].1.max(y),
        Err(i) => curve.insert(i, (x, y)),
    }
}

/// The mean slope of every curve with two points or more, clamped; `default` when none has.
fn pooled_slope(curves: &BTreeMap<u32, Curve>, bounds: (f64, f64, f64), default: f64) -> f64 {
    let slopes: Vec<f64> = curves
        .values()
        .filter(|c| c.len() >= 2)
        .filter_map(|c| {
            let (a, b) = (c[0], c[c.len() - 1]);
            let s = (b.1 - a.1) / (b.0 - a.0);
            s.is_finite().then(|| s.clamp(bounds.0, bounds.1))
        })
        .collect();
    if slopes.is_empty() {
        default
    } else {
        slopes.iter().sum::<f64>() / slopes.len() as f64
    }
}

/// The measured resolution nearest `r` (in ln r) and what was measured there.
fn nearest<V>(by_r: &BTreeMap<u32, V>, r: u32) -> Option<(u32, &V)> {
    let lr = f64::from(r.max(1)).ln();
    let dist = |x: u32| (f64::from(x).ln() - lr).abs();
    by_r.iter()
        .min_by(|a, b| dist(*a.0).total_cmp(&dist(*b.0)))
        .map(|(&r, v)| (r, v))
}

/// A value at `c`: interpolated on the curve of the nearest measured resolution (in ln r),
/// scaled by `(r / r_measured)²`; beyond the curve's ends, extended with the end segment's
/// slope within `bounds` (lowest, highest, highest beyond the measured).
fn predict(
    curves: &BTreeMap<u32, Curve>,
    c: Candidate,
    bounds: (f64, f64, f64),
    default: f64,
) -> Option<f64> {
    let g = f64::from(c.gamma);
    if c.r == 0 || g.is_nan() || g <= 0.0 {
        return None;
    }
    let lr = f64::from(c.r).ln();
    let (r0, curve) = nearest(curves, c.r).filter(|(_, c)| !c.is_empty())?;
    let x = g.ln();
    let y = if curve.len() == 1 {
        curve[0].1 + pooled_slope(curves, bounds, default).min(bounds.2) * (x - curve[0].0)
    } else {
        // The segment containing x, or the end segment nearest it.
        let i = curve
            .iter()
            .position(|p| p.0 >= x)
            .unwrap_or(curve.len())
            .clamp(1, curve.len() - 1);
        let (a, b) = (curve[i - 1], curve[i]);
        let s = ((b.1 - a.1) / (b.0 - a.0)).clamp(bounds.0, bounds.2);
        if x <= b.0 && x >= a.0 {
            // Inside: straight interpolation (through both points).
            a.1 + (b.1 - a.1) * (x - a.0) / (b.0 - a.0)
        } else if x < a.0 {
            // Below the measured γ σ is taken to rise at least as 1/γ: the end segment may lie
            // where σ flattens, and a low guess there would overshoot.
            a.1 + s.min(default) * (x - a.0)
        } else {
            b.1 + s * (x - b.0)
        }
    };
    let scale = 2.0 * (lr - f64::from(r0).ln());
    Some((y + scale).exp())
}

/// A production step as the controller sees it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Observation {
    /// Step index.
    pub step: u64,
    /// The `P_M` it was made with.
    pub candidate: Candidate,
    /// σ of the step (summed over its ranks), bytes.
    pub sigma_bytes: u64,
    /// τ of the step (its slowest rank), seconds.
    pub tau_secs: f64,
    /// σ the decision it was made under planned for it (its prediction), bytes, when known.
    pub planned_sigma_bytes: Option<f64>,
}

/// The ratio of measured to modelled σ (and τ) expected at a step.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Forecast {
    /// k of σ at the newest production step.
    pub sigma_now: f64,
    /// k of σ forecast for the step planned for (≥ `sigma_now`).
    pub sigma: f64,
    /// Growth of σ per unit of step index (a factor; 1 when none was seen).
    pub sigma_growth_per_step: f64,
    /// k of τ forecast for the step planned for: the largest of the window's, each carried
    /// forward by `tau_growth_per_step` over the steps between. τ is a timing: production
    /// steps share the node with the simulation and the scorer, and at one `P_M` they spread
    /// ±50 % on a busy machine, so a budget kept on most steps must be planned for the slow
    /// ones, as the data has grown by then.
    pub tau: f64,
    /// Growth of τ per unit of step index (a factor, 1 when none was seen): the Theil–Sen
    /// slope of ln k_τ over the window's pairs of steps at one resolution, no more than σ's
    /// growth. A drifting field that needs more work per ray needs more supersegments too, so
    /// σ, which has no timing noise, bounds it; on still data σ does not grow, and the noise
    /// of the timings is not read as growth.
    pub tau_growth_per_step: f64,
    /// σ's growth per unit of step index as a trend to plan a horizon on (a factor): the
    /// Theil–Sen slope over every pair of the window's steps made with one `P_M`, no more
    /// than `sigma_growth_per_step`; `None` with fewer than three such pairs. Between steps
    /// of different `P_M` the growth carries the surface's error at each, after a change of
    /// character it is the jump, and between consecutive steps it is the noise of a step's σ
    /// (±4 % at one `P_M` on still data): none is a trend.
    pub trend_per_step: Option<f64>,
    /// The newest production step.
    pub newest: u64,
    /// The step planned for.
    pub at: u64,
}

/// What [`Controller::choose`] found for a step.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Plan {
    /// The candidate.
    pub candidate: Candidate,
    /// Its σ forecast for the step, bytes.
    pub sigma_bytes: f64,
    /// Its τ forecast for the step, seconds (`NaN` when τ was never measured).
    pub tau_secs: f64,
    /// The forecast behind it.
    pub forecast: Forecast,
    /// Whether it meets the plan (`false`: the candidate forecast nearest it was the best that
    /// could be done).
    pub feasible: bool,
}

/// The closed-loop controller: production observations and the rule that turns them into a
/// `P_M`.
#[derive(Clone, Debug)]
pub struct Controller {
    /// σ_target, bytes.
    pub sigma_target: Option<f64>,
    /// τ_target, seconds.
    pub tau_target: Option<f64>,
    /// Share of each target kept free: candidates are chosen for `(1 − headroom) × target`.
    pub headroom: f64,
    /// A step back towards the tuned `P_M` is taken only when its forecast clears the plan by
    /// this share.
    pub hysteresis: f64,
    /// Production steps (in strides of the step index) a change of `P_M` is planned to hold
    /// for: a new candidate is chosen for the forecast that many steps past the one it
    /// applies from, so that on growing data it is not outgrown at once (see
    /// [`Controller::choose`]). 0 plans for the first step alone.
    pub horizon: u64,
    /// Production steps in a row the `P_M` in force must have been made on before a correction
    /// takes a finer resolution (γ at its own resolution may change before): r changes less
    /// often than γ, and a resolution left for a coarser one on forecast growth is not taken
    /// back on the first steps that grew less than forecast. At most [`WINDOW`].
    pub dwell: u64,
    grid: ParamGrid,
    window: VecDeque<Observation>,
    /// The model's miss (≥ 1): after a step over the σ budget, its σ over what its decision
    /// planned for it. Plans are made for the budget divided by it, so the next `P_M` allows
    /// for the error the model has just shown (the forecast's ratio carries what one
    /// candidate measured to the others; where the data changed character, it carries that
    /// badly); each step within the budget halves its excess. A step made more than
    /// [`Self::horizon`] steps into its `P_M`'s run is past what its plan was made for: its
    /// excess is growth the next plan's forecast reads, not an error of the model.
    miss: f64,
    /// The candidate of the newest step and how many steps in a row were made with it.
    run: Option<(Candidate, u64)>,
    /// The last production step made with each candidate (by r, γ's bits and precision) within
    /// [`MEMORY`] steps of the newest: σ measured there is what that candidate gives on data
    /// like today's, whatever the surface says of it.
    seen: BTreeMap<(u32, u32, u32), Observation>,
}

/// Production steps (counted in observations) a candidate's own measurement is remembered.
pub const MEMORY: u64 = 32;

/// The default [`Controller::horizon`], steps: on Gray–Scott 128³ (σ growing 4 % a step at one
/// `P_M`, 60 steps under `size:1MB`) a change planned for the next step alone was outgrown two
/// to four steps later (8 changes of r or γ in 56 steps); planned for 8 steps, 5; for 16, 4,
/// but at 68 % of the budget used on average instead of 82 % and a q regret of 1.8 dB instead
/// of 0.2 (docs/tuning.md).
pub const HORIZON: u64 = 8;

/// The default [`Controller::dwell`], steps: on Gray–Scott 128³ under `size:1MB` a correction to
/// a coarser resolution planned for [`HORIZON`] steps of growth was taken back five steps
/// later, when the growth paused, and left again when it resumed.
pub const DWELL: u64 = HORIZON;

/// The least gain in predicted q (dB) that is worth a visible change of `P_M` towards a finer
/// one at the same resolution, where the trials scored both (see [`Controller::correct`]).
pub const Q_GAIN_DB: f64 = 0.5;

/// As [`Q_GAIN_DB`] for a change of resolution: r changes less often than γ.
pub const Q_GAIN_R_DB: f64 = 1.0;

/// Where the trials did not score both, the least growth of σ (a factor over the `P_M` in
/// force's forecast σ) that is worth a change towards a finer `P_M` at the same resolution:
/// q rises with the bytes a VDI spends, and a change that spends few more is not seen.
pub const SIGMA_GAIN: f64 = 1.2;

/// As [`SIGMA_GAIN`] for a change of resolution.
pub const SIGMA_GAIN_R: f64 = 1.4;

impl Controller {
    /// A controller for the budgets `(σ_target bytes, τ_target seconds)` over `grid`.
    pub fn new(budgets: (Option<u64>, Option<f64>), headroom: f64, grid: ParamGrid) -> Self {
        Self {
            sigma_target: budgets.0.map(|b| b as f64),
            tau_target: budgets.1,
            headroom,
            hysteresis: 0.1,
            horizon: HORIZON,
            dwell: DWELL,
            grid,
            window: VecDeque::with_capacity(WINDOW),
            miss: 1.0,
            run: None,
            seen: BTreeMap::new(),
        }
    }

    /// The model's miss that plans allow for now (1: none; see the field's doc).
    pub fn miss(&self) -> f64 {
        self.miss
    }

    /// Whether there is a budget to keep.
    pub fn active(&self) -> bool {
        self.sigma_target.is_some() || self.tau_target.is_some()
    }

    /// Records a production step (steps older than the newest are ignored: another rank's
    /// late summary).
    pub fn observe(&mut self, o: Observation) {
        if self.window.back().is_some_and(|b| o.step <= b.step) {
            return;
        }
        let run = match self.run {
            Some((c, n)) if c == o.candidate => n + 1,
            _ => 1,
        };
        self.run = Some((o.candidate, run));
        if let Some(target) = self.sigma_target {
            let sigma = o.sigma_bytes as f64;
            let planned = o
                .planned_sigma_bytes
                .filter(|p| p.is_finite() && *p > 0.0 && run <= self.horizon.max(1));
            self.miss = match planned {
                Some(p) if sigma > target => (sigma / p).clamp(1.0, MAX_GROWTH),
                _ => 1.0 + (self.miss - 1.0) / 2.0,
            };
        }
        if self.window.len() == WINDOW {
            self.window.pop_front();
        }
        self.window.push_back(o);
        self.seen.insert(o.candidate.key(), o);
        let oldest = self.seen.len().saturating_sub(MEMORY as usize);
        if oldest > 0 {
            // Forget the candidates seen longest ago.
            let mut by_age: Vec<((u32, u32, u32), u64)> =
                self.seen.iter().map(|(k, o)| (*k, o.step)).collect();
            by_age.sort_by_key(|x| x.1);
            for (k, _) in by_age.into_iter().take(oldest) {
                self.seen.remove(&k);
            }
        }
    }

    /// Forgets what production steps before `step` measured, and the model's miss: the data
    /// changed character at `step`, and a tuning on it has just replaced the surface, so the
    /// ratios of older steps to it (measured on other data) and the miss of the old surface
    /// say nothing of what comes next.
    pub fn rebase(&mut self, step: u64) {
        self.window.retain(|o| o.step >= step);
        self.seen.retain(|_, o| o.step >= step);
        self.miss = 1.0;
        self.run = None;
    }

    /// The production steps remembered, oldest first.
    pub fn observations(&self) -> impl Iterator<Item = &Observation> {
        self.window.iter()
    }

    /// The ratio of measured to modelled σ and τ forecast for step `at`, over `surface`;
    /// `None` before any production step with a modelled σ.
    pub fn forecast(&self, surface: &Surface, at: u64) -> Option<Forecast> {
        let ks: Vec<(u64, Candidate, f64)> = self
            .window
            .iter()
            .filter_map(|o| {
                let m = surface.sigma(o.candidate)?;
                let k = (o.sigma_bytes as f64 / m).ln();
                k.is_finite().then_some((o.step, o.candidate, k))
            })
            .collect();
        let &(newest, _, now) = ks.last()?;
        // Growth per step: the median slope between consecutive steps made with the same
        // P_M, which the surface's error does not touch; while every step has a P_M of its own
        // (corrections at each step), between any consecutive steps (an error of the surface
        // at one P_M is then a jump between two steps, which the median passes over).
        let slope = |same: bool| -> Vec<f64> {
            ks.windows(2)
                .filter(|w| w[1].0 > w[0].0 && (!same || w[0].1 == w[1].1))
                .map(|w| (w[1].2 - w[0].2) / (w[1].0 - w[0].0) as f64)
                .collect()
        };
        let mut slopes = slope(true);
        if slopes.is_empty() {
            slopes = slope(false);
        }
        // The trend: the Theil–Sen slope over every pair of the window's steps made with one
        // P_M (three pairs at least), no more than the slope above.
        let pairs: Vec<f64> = ks
            .iter()
            .enumerate()
            .flat_map(|(i, a)| ks[i + 1..].iter().map(move |b| (a, b)))
            .filter(|(a, b)| a.1 == b.1 && b.0 > a.0)
            .map(|(a, b)| (b.2 - a.2) / (b.0 - a.0) as f64)
            .collect();
        let trend = (pairs.len() >= 3).then(|| median(pairs));
        let slope = median(slopes).max(0.0);
        let grown = growth(slope, newest, at);
        // τ: ln k of each step of the window, carried forward to `at` by τ's growth, and the
        // largest (the slowest step, grown as the data has grown since).
        let taus: Vec<(u64, u32, f64)> = self
            .window
            .iter()
            .filter_map(|o| {
                let k = o.tau_secs / surface.tau(o.candidate)?;
                (k.is_finite() && k > 0.0).then_some((o.step, o.candidate.r, k.ln()))
            })
            .collect();
        let tau_slope = tau_growth(&taus).max(0.0).min(slope);
        let tau = taus
            .iter()
            .map(|&(step, _, k)| k + growth(tau_slope, step, at))
            .reduce(f64::max);
        Some(Forecast {
            sigma_now: now.exp(),
            sigma: (now + grown).exp(),
            sigma_growth_per_step: slope.exp(),
            tau: tau.map_or(1.0, f64::exp),
            tau_growth_per_step: tau_slope.exp(),
            trend_per_step: trend.map(|t| t.clamp(0.0, slope).exp()),
            newest,
            at,
        })
    }

    /// The ratios of σ and τ forecast at `c`: the window's, or where larger the ones measured
    /// when `c` itself was last made (for τ: any candidate at `c`'s resolution, τ being one
    /// whatever the γ, or where production has not made that resolution, at the nearest finer
    /// one it has; grown by the forecast's σ growth since), within [`MEMORY`] steps. The
    /// surface can be off at one candidate (measured on other steps, interpolated, or for τ
    /// scaled by r² from a resolution whose fixed costs dominate its timing), and a `P_M` that
    /// overshot on its own step is not taken back on the strength of other candidates' ratios.
    /// The third value says whether `c`'s σ was measured by production (its own ratio).
    fn ratios(&self, surface: &Surface, f: &Forecast, c: Candidate) -> (f64, f64, bool) {
        let memory = MEMORY * self.stride();
        let recent = |o: &&Observation| f.newest.saturating_sub(o.step) <= memory;
        let ratio = |measured: f64, modelled: Option<f64>| {
            modelled.map(|m| measured / m).filter(|k| k.is_finite())
        };
        let own_sigma = self
            .seen
            .get(&c.key())
            .filter(recent)
            .and_then(|o| ratio(o.sigma_bytes as f64, surface.sigma(c)));
        // τ measured at `c`'s resolution steps ago, grown as σ has grown since: a resolution
        // left for a coarser one while the field grew is not taken back on the timing it had
        // then. σ's growth, not τ's: the window's τ growth is measured at the resolutions the
        // window used, over its few steps, and is noise-bound there (a flat run of fast r 64
        // steps while σ grew 8 % a step); carried over the longer gap to another resolution,
        // the bound σ sets on it is the safe reading. On still data σ does not grow either.
        let grown = |o: &Observation| growth(f.sigma_growth_per_step.ln(), o.step, f.at).exp();
        // A resolution production has not timed takes the ratio of the nearest finer one it
        // has: production's slowdown against the trials grew with a generation's work in the
        // runs measured (likely a step's volume read cold where the trials find it in cache),
        // so a finer resolution's ratio bounds a coarser one's, and a step up is not taken on
        // the ratio of a coarser resolution's fast steps (on Gray–Scott 128³ under
        // `time:0.03`, r 64 steps of 3–5 ms put r 192 at 22 ms; it took 39 ms).
        // `seen` is ordered by r: the first recent entry from `c.r` up is the nearest timed.
        let mut timed = self
            .seen
            .range((c.r, 0, 0)..)
            .map(|(_, o)| o)
            .filter(recent)
            .peekable();
        let nearest = timed.peek().map(|o| o.candidate.r);
        let own_tau = timed
            .take_while(|o| Some(o.candidate.r) == nearest)
            .filter_map(|o| ratio(o.tau_secs, surface.tau(o.candidate)).map(|k| k * grown(o)))
            .reduce(f64::max);
        (
            own_sigma.map_or(f.sigma, |k| k.max(f.sigma)),
            own_tau.map_or(f.tau, |k| k.max(f.tau)),
            own_sigma.is_some(),
        )
    }

    /// The smallest gap between consecutive steps of the window (1 when unknown).
    fn stride(&self) -> u64 {
        self.window
            .iter()
            .zip(self.window.iter().skip(1))
            .map(|(a, b)| b.step - a.step)
            .min()
            .unwrap_or(1)
            .max(1)
    }

    /// σ and τ of `c` forecast with `f`, and its load: the larger of σ and τ over their plans
    /// scaled by `margin` (1: the plan itself); `c` meets the plan when the load is ≤ 1.
    fn forecast_at(
        &self,
        surface: &Surface,
        f: &Forecast,
        c: Candidate,
        margin: f64,
    ) -> (f64, f64, f64) {
        let (k_sigma, k_tau, measured) = self.ratios(surface, f, c);
        let sigma = surface.sigma(c).map_or(f64::INFINITY, |s| s * k_sigma);
        let tau = surface.tau(c).map_or(f64::NAN, |t| t * k_tau);
        let plan = |t: f64| (1.0 - self.headroom) * t * margin;
        // The model's miss is an error of the surface's reading of a candidate; one that
        // production made recently is read from its own σ.
        let miss = if measured { 1.0 } else { self.miss };
        let sigma_load = self.sigma_target.map_or(0.0, |t| sigma / (plan(t) / miss));
        let tau_load = match self.tau_target {
            Some(t) if !tau.is_nan() => tau / plan(t),
            _ => 0.0,
        };
        (sigma, tau, sigma_load.max(tau_load))
    }

    /// σ and τ of `c` forecast with `f`, and whether they meet the plan scaled by `margin`.
    fn fits(&self, surface: &Surface, f: &Forecast, c: Candidate, margin: f64) -> (f64, f64, bool) {
        let (sigma, tau, load) = self.forecast_at(surface, f, c, margin);
        (sigma, tau, load <= 1.0)
    }

    /// The `P_M` from step `at` on: the finest candidate at a resolution no finer than
    /// `tuned`'s whose forecast meets the plan, searched from `tuned`'s resolution down (γ
    /// from the finest measured at that resolution up to [`gamma_span`] times `tuned`'s),
    /// else the smallest γ that meets the plan at any lower resolution, else the candidate
    /// forecast nearest the plan (the finest γ of equal ones). The forecast is the one for
    /// [`Self::horizon`] steps past `at` by the trend ([`Forecast::trend_per_step`]), so
    /// that the choice holds that long, where there is a trend and some candidate holds that
    /// long; else the forecast for `at` alone.
    /// `None` before there is a forecast.
    pub fn choose(&self, surface: &Surface, tuned: Candidate, at: u64) -> Option<Plan> {
        self.choose_below(surface, tuned, tuned.r, at)
    }

    /// [`Self::choose`] at resolutions no finer than `r_max` (the `P_M` in force's, where a
    /// correction may not go finer).
    fn choose_below(
        &self,
        surface: &Surface,
        tuned: Candidate,
        r_max: u32,
        at: u64,
    ) -> Option<Plan> {
        let next = self.forecast(surface, at)?;
        let lasting = at.saturating_add(self.horizon.saturating_mul(self.stride()));
        if let Some(trend) = next.trend_per_step.filter(|_| lasting > at) {
            // The forecast for `at`, carried on by the trend to the horizon (τ by no more
            // than its own growth).
            let steps = (lasting - at) as f64;
            let grown = (trend.ln() * steps).min(MAX_GROWTH.ln());
            let tau_grown = (next.tau_growth_per_step.ln().min(trend.ln()) * steps).max(0.0);
            let f = Forecast {
                sigma: next.sigma * grown.exp(),
                tau: next.tau * tau_grown.min(MAX_GROWTH.ln()).exp(),
                at: lasting,
                ..next
            };
            let p = self.choose_for(surface, tuned, r_max, f);
            if p.feasible {
                return Some(p);
            }
        }
        Some(self.choose_for(surface, tuned, r_max, next))
    }

    /// [`Self::choose_below`] under the forecast `f`.
    fn choose_for(&self, surface: &Surface, tuned: Candidate, r_max: u32, f: Forecast) -> Plan {
        let plan = |c: Candidate, feasible: bool| {
            let (sigma_bytes, tau_secs, _) = self.fits(surface, &f, c, 1.0);
            Plan {
                candidate: c,
                sigma_bytes,
                tau_secs,
                forecast: f,
                feasible,
            }
        };
        let rs: Vec<u32> = self
            .grid
            .rs
            .iter()
            .rev()
            .copied()
            .filter(|&r| r <= tuned.r.min(r_max))
            .collect();
        let first_fit = |r: u32, lo: f32, hi: f32| {
            self.grid
                .gammas
                .iter()
                .copied()
                .filter(|&g| g >= lo && g <= hi)
                .map(|gamma| Candidate {
                    r,
                    gamma,
                    precision: tuned.precision,
                })
                .find(|&c| self.fits(surface, &f, c, 1.0).2)
        };
        // At least the grid's next γ above the tuned one (a coarse γ axis would otherwise
        // leave nothing within the span).
        let next = self.grid.gammas.iter().copied().find(|&g| g > tuned.gamma);
        let span = |r: u32| (tuned.gamma * gamma_span(&self.grid.rs, r)).max(next.unwrap_or(0.0));
        let found = rs
            .iter()
            .find_map(|&r| {
                // The finest γ measured at the resolution (or where its σ is modelled from),
                // not an extrapolation below it. At the tuned resolution too: there q only
                // rises as γ falls (Sec. 6.1), so a γ finer than the tuned one that the
                // forecast lets through is better on the data as it is now — under a size
                // budget, only where production came in under the tuning's measurements by
                // the hysteresis (k ≤ 0.9; a step's σ spreads ±4 % on still data): else the
                // tuning measured what fits, and a finer γ between its probes is the
                // surface's guess at the budget's edge.
                let at_r = Candidate { r, ..tuned };
                let mut floor = surface.gamma_floor(at_r).map_or(0.0, |g| g * (1.0 - 1e-6));
                if r == tuned.r && self.sigma_target.is_some() && f.sigma > 1.0 - self.hysteresis {
                    floor = floor.max(tuned.gamma * (1.0 - 1e-6));
                }
                first_fit(r, floor, span(r).max(floor))
            })
            .or_else(|| rs.iter().find_map(|&r| first_fit(r, 0.0, f32::INFINITY)));
        // Nothing meets the plan: the candidate forecast nearest it (the smallest load), the
        // finest γ of equal ones. Under a size budget that is the coarsest candidate (σ falls
        // with r and γ); under a time budget the lowest r at its finest γ (τ at a resolution is
        // one whatever the γ, so a coarser γ would lose q for nothing).
        let nearest = || {
            let mut best: Option<(Candidate, f64)> = None;
            for &r in rs.iter().rev() {
                for &gamma in &self.grid.gammas {
                    let c = Candidate {
                        r,
                        gamma,
                        precision: tuned.precision,
                    };
                    let load = self.forecast_at(surface, &f, c, 1.0).2;
                    if best.is_none_or(|(_, b)| load < b) {
                        best = Some((c, load));
                    }
                }
            }
            best.map_or(
                Candidate {
                    r: self.grid.rs.first().copied().unwrap_or(tuned.r),
                    gamma: self.grid.gammas.last().copied().unwrap_or(tuned.gamma),
                    precision: tuned.precision,
                },
                |(c, _)| c,
            )
        };
        match found {
            Some(c) => plan(c, true),
            None => plan(nearest(), false),
        }
    }

    /// A change of `P_M` from step `at`, when one is due. When the `P_M` in force (`current`)
    /// misses the budget under the forecast for `at` (the budget is at risk; the plan, the
    /// budget less the headroom, is what a new choice aims at): [`Self::choose`]'s candidate
    /// at a resolution no finer than `current`'s. Otherwise only towards a finer
    /// candidate, and only when it is worth a visible change: at a finer resolution only after
    /// `current` has held for [`Self::dwell`] steps, it clears the plan by the
    /// hysteresis for the whole horizon, and its predicted q exceeds `current`'s by
    /// [`Q_GAIN_DB`] ([`Q_GAIN_R_DB`] for another resolution) where the trials scored both,
    /// elsewhere its σ forecast is [`SIGMA_GAIN`] ([`SIGMA_GAIN_R`]) times `current`'s.
    /// `None` when `current` should stay.
    pub fn correct(
        &self,
        surface: &Surface,
        tuned: Candidate,
        current: Candidate,
        at: u64,
    ) -> Option<Plan> {
        let next = self.forecast(surface, at)?;
        // At risk: forecast at the budget itself (the headroom is there to absorb a step's
        // noise, and a forecast inside it breaks nothing).
        let budget = 1.0 / (1.0 - self.headroom).max(f64::EPSILON);
        if !self.fits(surface, &next, current, budget).2 {
            return self
                .choose_below(surface, tuned, current.r, at)
                .filter(|p| p.candidate != current);
        }
        let held = self
            .window
            .iter()
            .rev()
            .take_while(|o| o.candidate == current)
            .count() as u64;
        let r_max = if held >= self.dwell.min(WINDOW as u64) {
            tuned.r
        } else {
            current.r
        };
        let p = self.choose_below(surface, tuned, r_max, at)?;
        let finer = finer(p.candidate, current);
        let clears = self
            .fits(surface, &p.forecast, p.candidate, 1.0 - self.hysteresis)
            .2;
        (p.feasible && finer && clears && self.worth(surface, &p, current)).then_some(p)
    }

    /// `c` kept from step `at`: its σ and τ under the forecast for `at`, and whether they
    /// meet the plan. `None` before there is a forecast.
    pub fn keep(&self, surface: &Surface, c: Candidate, at: u64) -> Option<Plan> {
        let forecast = self.forecast(surface, at)?;
        let (sigma_bytes, tau_secs, feasible) = self.fits(surface, &forecast, c, 1.0);
        Some(Plan {
            candidate: c,
            sigma_bytes,
            tau_secs,
            forecast,
            feasible,
        })
    }

    /// Whether the finer `p` gains enough over `current` to be worth a visible change (see
    /// [`Self::correct`]).
    fn worth(&self, surface: &Surface, p: &Plan, current: Candidate) -> bool {
        let other_r = p.candidate.r != current.r;
        if let (Some(a), Some(b)) = (surface.q(p.candidate), surface.q(current)) {
            return a - b >= if other_r { Q_GAIN_R_DB } else { Q_GAIN_DB };
        }
        let now = self.forecast_at(surface, &p.forecast, current, 1.0).0;
        p.sigma_bytes >= now * if other_r { SIGMA_GAIN_R } else { SIGMA_GAIN }
    }
}

/// Whether `a` is finer than `b`: a higher resolution, or the same with a smaller γ.
pub fn finer(a: Candidate, b: Candidate) -> bool {
    a.r > b.r || (a.r == b.r && a.gamma < b.gamma)
}

/// The Theil–Sen slope of `ln k` over the step index: the median of the slopes between every
/// two observations `(step, r, ln k)` at one resolution and different steps (τ at a resolution
/// is one whatever the γ, and across resolutions the surface's r² law is a model, not a
/// measurement); 0 without such a pair. The median of all pairs, rather than of consecutive
/// ones, spans several steps per slope, so ±50 % of timing noise moves it far less.
fn tau_growth(taus: &[(u64, u32, f64)]) -> f64 {
    median(
        taus.iter()
            .enumerate()
            .flat_map(|(i, a)| taus[i + 1..].iter().map(move |b| (a, b)))
            .filter(|(a, b)| a.1 == b.1 && b.0 > a.0)
            .map(|(a, b)| (b.2 - a.2) / (b.0 - a.0) as f64)
            .collect(),
    )
}

/// The median of `slopes` (the upper one of an even count); 0 for none.
fn median(mut slopes: Vec<f64>) -> f64 {
    slopes.sort_by(f64::total_cmp);
    slopes.get(slopes.len() / 2).copied().unwrap_or(0.0)
}

/// The growth of `ln k` at `slope` per step from step `from` to step `to` (none backwards),
/// at most [`MAX_GROWTH`].
fn growth(slope: f64, from: u64, to: u64) -> f64 {
    (slope * to.saturating_sub(from) as f64).min(MAX_GROWTH.ln())
}

#[cfg(test)]
mod tests {
    use super::*;
    use insitu_core::vdi::Precision;

    fn c(r: u32, gamma: f32) -> Candidate {
        Candidate {
            r,
            gamma,
            precision: Default::default(),
        }
    }

    /// σ = 1e6 · (r / 256)² · (0.01 / γ) bytes: the power law the surface is built to follow.
    fn law(c: Candidate) -> f64 {
        1e6 * (f64::from(c.r) / 256.0).powi(2) * (0.01 / f64::from(c.gamma))
    }

    fn surface_of(cs: &[Candidate]) -> Surface {
        Surface::new(cs.iter().map(|&c| Point {
            candidate: c,
            sigma_bytes: law(c),
            tau_secs: 0.1,
        }))
    }

    /// γ number `i` of [`grid`] (as the grid holds it, bit for bit).
    fn g(i: u8) -> f32 {
        f32::from(i) * 0.005
    }

    fn grid() -> ParamGrid {
        ParamGrid {
            rs: vec![64, 128, 192, 256],
            gammas: (1..=40).map(g).collect(),
            precisions: vec![Default::default()],
        }
    }

    #[test]
    fn the_surface_reproduces_a_power_law_between_and_beyond_its_points() {
        let s = surface_of(&[c(256, g(2)), c(256, g(8)), c(128, g(4))]);
        for q in [
            c(256, 0.02),
            c(256, 0.08),
            c(256, 0.005),
            c(192, 0.03),
            c(64, 0.1),
        ] {
            let (got, want) = (s.sigma(q).unwrap(), law(q));
            assert!((got / want - 1.0).abs() < 1e-9, "{q:?}: {got} vs {want}");
        }
        // Measured points come back exactly.
        assert!((s.sigma(c(256, g(8))).unwrap() - law(c(256, g(8)))).abs() < 1e-3);
        // A point with no σ is left out; an empty surface predicts nothing.
        assert!(Surface::new([Point {
            candidate: c(64, 0.01),
            sigma_bytes: f64::NAN,
            tau_secs: 0.1
        }])
        .is_empty());
        assert_eq!(Surface::default().sigma(c(64, 0.01)), None);
        // Two probes of equal σ: flat between them, falling as γ^−½ beyond.
        let flat = Surface::new([g(2), g(4)].map(|gamma| Point {
            candidate: c(64, gamma),
            sigma_bytes: 1000.0,
            tau_secs: 0.1,
        }));
        assert!((flat.sigma(c(64, g(3))).unwrap() - 1000.0).abs() < 1e-6);
        let beyond = flat.sigma(c(64, g(16))).unwrap();
        assert!((beyond - 500.0).abs() < 1e-3, "{beyond}");
        assert!(
            (flat.tau(c(64, g(16))).unwrap() - 0.1).abs() < 1e-9,
            "τ stays flat"
        );
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
        let mut ctl = Controller::new((Some(1_120_000), None), 0.05, grid());
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
        let mut ctl = Controller::new((Some(budget as u64), None), 0.05, grid());
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
        let mut ctl = Controller::new((Some(1_120_000), None), 0.05, grid());
        let mut blind = Controller::new((Some(1_120_000), None), 0.05, grid());
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
        let mut ctl = Controller::new((Some(1_120_000), None), 0.05, grid());
        for k in 0..HORIZON {
            ctl.observe(step(k, 700_000));
        }
        // The horizon's steps were planned at 700 kB; the next, over the budget, is past it.
        ctl.observe(step(HORIZON, 1_200_000));
        assert_eq!(ctl.miss(), 1.0);
        // A miss set by a new candidate's first step: the P_M in force at 70 % of the budget
        // is not at risk, though 70 % × 1.5 would be.
        let mut ctl = Controller::new((Some(1_000_000), None), 0.05, grid());
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
        let mut ctl = Controller::new((Some(1_120_000), None), 0.05, grid());
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
        // Planned to hold 8 steps (of 10): k = 1.1^12 = 3.14 by step 120; r 256 and r 192 would
        // need γ beyond their spans, r 128 at the tuned γ holds (785 kB).
        ctl.horizon = 8;
        let p = ctl.correct(&s, tuned, tuned, 40).unwrap();
        assert_eq!((p.candidate, p.forecast.at), (c(128, g(2)), 120), "{p:?}");
        assert!(
            (p.sigma_bytes - 250_000.0 * 1.1f64.powi(12)).abs() < 1.0,
            "{p:?}"
        );
        // 3 % more than the model still fits the plan: no change.
        let mut ctl = Controller::new((Some(1_120_000), None), 0.05, grid());
        observed(&mut ctl, 0, tuned, 1.03);
        assert_eq!(ctl.correct(&s, tuned, tuned, 10), None);
    }

    #[test]
    fn the_resolution_drops_when_gamma_alone_would_go_too_far() {
        let s = surface_of(&[c(256, g(2)), c(256, g(4)), c(128, g(2))]);
        let mut ctl = Controller::new((Some(1_120_000), None), 0.05, grid());
        let tuned = c(256, g(2));
        // σ at 6× the model: with γ up to the grid's next (0.015), r 256 (needs γ 0.056) and
        // r 192 (0.032) miss the plan; r 128 (0.014) meets it.
        observed(&mut ctl, 0, tuned, 6.0);
        let p = ctl.correct(&s, tuned, tuned, 10).unwrap();
        assert_eq!(p.candidate, c(128, g(3)));
        // Beyond every span: the largest r with any γ that meets the plan (r 128, γ ≥ 0.141).
        let mut ctl = Controller::new((Some(1_120_000), None), 0.05, grid());
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
        let mut ctl = Controller::new((Some(1_120_000), None), 0.05, grid());
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
        let mut ctl = Controller::new((Some(1_120_000), None), 0.05, grid());
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
        let mut ctl = Controller::new((Some(1_120_000), None), 0.05, grid());
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
        let mut ctl = Controller::new((None, Some(0.1)), 0.05, grid());
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
            let mut ctl = Controller::new((None, Some(0.1)), 0.05, grid());
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
                1.05f64.powi(i as i32)
                    * noise[i as usize]
                    * f.tau_growth_per_step.powi(8 - i as i32)
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
            let mut ctl = Controller::new((None, Some(0.1)), 0.05, grid());
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
            let mut ctl = Controller::new((None, Some(0.1)), 0.05, grid());
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
        let mut ctl = Controller::new((None, Some(0.1)), 0.05, grid());
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
        let mut ctl = Controller::new((None, Some(0.1)), 0.05, grid());
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
        let mut ctl = Controller::new((Some(1_120_000), None), 0.05, grid());
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
        let mut ctl = Controller::new((Some(1_120_000), None), 0.05, grid());
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

    /// A candidate is read from the points of its own precision only: σ at 8 bits says
    /// nothing of σ at 6 bits or as floats; a surface holds each precision its points came at.
    #[test]
    fn a_surface_keeps_each_precision_apart() {
        let at = |c: Candidate, precision| Candidate { precision, ..c };
        let eight = [c(64, 0.01), c(128, 0.01), c(128, 0.02)].map(|x| at(x, Precision::Bits(8)));
        let mut points: Vec<Point> = eight
            .iter()
            .map(|&c| Point {
                candidate: c,
                sigma_bytes: law(c),
                tau_secs: 0.01,
            })
            .collect();
        let float = at(c(64, 0.02), Precision::Float32);
        points.push(Point {
            candidate: float,
            sigma_bytes: 1.0,
            tau_secs: 1.0,
        });
        let s = Surface::new(points);
        let probe = at(c(96, 0.015), Precision::Bits(8));
        assert!(s.sigma(probe).is_some() && s.tau(probe).is_some());
        assert_eq!(s.sigma(at(probe, Precision::Bits(6))), None);
        assert_eq!(s.tau(at(probe, Precision::Bits(6))), None);
        // The float point is a layer of its own: σ at r 64 at 8 bits follows the 8-bit law,
        // and the float candidate reads its own point.
        let r64 = at(c(64, 0.02), Precision::Bits(8));
        assert!((s.sigma(r64).unwrap() / law(r64) - 1.0).abs() < 0.2);
        assert!((s.sigma(float).unwrap() - 1.0).abs() < 1e-9);
        assert!((s.tau(float).unwrap() - 1.0).abs() < 1e-9);
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
        let mut ctl = Controller::new((Some(1_000_000), None), 0.05, grid());
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

    /// q is interpolated between the γ the trials scored at a resolution, the worst of a
    /// candidate scored twice, and not extrapolated beyond them or to another resolution.
    #[test]
    fn q_is_read_between_scored_candidates_only() {
        let s = surface_of(&[c(256, g(2)), c(256, g(8))]).with_q([
            (c(256, g(2)), 40.0),
            (c(256, g(8)), 30.0),
            (c(256, g(8)), 31.0),
            (c(128, g(4)), f64::NAN),
        ]);
        // ln-γ halfway between 0.01 and 0.04 is 0.02.
        assert!((s.q(c(256, g(4))).unwrap() - 35.0).abs() < 1e-9);
        assert_eq!(s.q(c(256, g(8))), Some(30.0));
        assert_eq!(s.q(c(256, g(1))), None, "below the scored γ");
        assert_eq!(s.q(c(256, g(16))), None, "above");
        assert_eq!(s.q(c(128, g(4))), None, "another resolution; NaN left out");
    }

    /// At the tuned resolution a γ finer than the tuned one is taken only where production came
    /// in under the tuning's measurements by the hysteresis: else the tuning measured what
    /// fits, and the surface between its probes is a guess at the budget's edge.
    #[test]
    fn the_tuned_gamma_is_refined_only_where_the_data_shrank() {
        let s = surface_of(&[c(256, g(1)), c(256, g(4))]);
        let tuned = c(256, g(4));
        let chosen = |k: f64| {
            let mut ctl = Controller::new((Some(1_120_000), None), 0.05, grid());
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
        let mut ctl = Controller::new((Some(1_120_000), None), 0.05, grid());
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
            let mut ctl = Controller::new((Some(1_120_000), None), 0.05, grid());
            observed(&mut ctl, 0, current, 0.5);
            ctl.correct(&s, tuned, current, 10).map(|p| p.candidate)
        };
        assert_eq!(with_q(40.3), None, "0.3 dB is not worth a change");
        assert_eq!(with_q(40.6), Some(tuned));
        // Unscored: by σ, 1.5× the current's (γ 0.015 → 0.01) is worth it, 1.07× is not.
        let s = surface_of(&base);
        let mut ctl = Controller::new((Some(1_120_000), None), 0.05, grid());
        observed(&mut ctl, 0, current, 0.5);
        assert_eq!(
            ctl.correct(&s, tuned, current, 10).map(|p| p.candidate),
            Some(tuned)
        );
        let near = surface_of(&[c(256, 0.014), c(256, g(3))]);
        let mut ctl = Controller::new((Some(1_120_000), None), 0.05, grid());
        let tuned = c(256, 0.014);
        observed(&mut ctl, 0, current, 0.5);
        assert_eq!(ctl.correct(&near, tuned, current, 10), None);
        // Across resolutions 1 dB is needed: 0.8 dB more at the tuned r 256 is not enough.
        let s = surface_of(&[c(256, g(2)), c(192, g(2))])
            .with_q([(c(256, g(2)), 40.8), (c(192, g(2)), 40.0)]);
        let mut ctl = Controller::new((Some(1_120_000), None), 0.05, grid());
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
            let mut ctl = Controller::new((Some(1_120_000), None), 0.05, grid());
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
        let mut ctl = Controller::new((Some(1_000_000), None), 0.05, grid());
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

    /// A forecast inside the headroom (over the plan, under the budget) changes nothing; one at
    /// the budget is a risk, and the change aims at the plan.
    #[test]
    fn only_a_forecast_at_the_budget_puts_it_at_risk() {
        let s = surface_of(&[c(256, g(2)), c(256, g(4))]);
        let tuned = c(256, g(2));
        // law(tuned) = 1 MB; the plan is 0.95 × 1.1 MB = 1.045 MB, the budget 1.1 MB.
        let at = |k: f64| {
            let mut ctl = Controller::new((Some(1_100_000), None), 0.05, grid());
            observed(&mut ctl, 0, tuned, k);
            ctl.correct(&s, tuned, tuned, 1)
        };
        assert_eq!(at(1.07), None, "1.07 MB: over the plan, within the budget");
        let p = at(1.12).unwrap();
        assert_eq!(p.candidate, c(256, g(3)));
        assert!(p.sigma_bytes <= 1_045_000.0, "{p:?}");
    }
}
