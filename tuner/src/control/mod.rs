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

mod surface;

pub use surface::{Point, Surface};

use crate::grid::{Candidate, ParamGrid};
use insitu_core::budget::Budgets;
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
    /// The most growth of σ (a factor) a change of `P_M` is planned to hold through, where it
    /// comes before [`Self::horizon`] steps (see [`PLAN_GROWTH`]); infinite: the horizon alone.
    pub plan_growth: f64,
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
    /// The candidate of the newest step and how many steps in a row were made with it (what the
    /// dwell and the miss read).
    run: Option<(Candidate, u64)>,
    /// The last production step made with each candidate (by r, γ's bits and precision) within
    /// [`MEMORY`] steps of the newest: σ measured there is what that candidate gives on data
    /// like today's, whatever the surface says of it.
    seen: BTreeMap<(u32, u32, u32), Observation>,
    /// The growth of σ per step (`ln`, ≥ 0) that the steps forgotten by the last
    /// [`Self::rebase`] showed: consecutive steps and every pair at one `P_M`, where the
    /// surface cancels out, so it outlives the surface it was read against. It stands in until
    /// the steps after the change show their own.
    carried: Option<Growth>,
}

/// σ's growth per step, `ln` of the factor: between consecutive steps (the slope) and over
/// every pair (the trend, three pairs at least), at one `P_M` each.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
struct Growth {
    slope: Option<f64>,
    trend: Option<f64>,
}

impl Growth {
    /// The growth `(step, P_M, ln k)` shows, slopes and pairs taken at one `P_M`.
    fn of(ks: &[(u64, Candidate, f64)]) -> Self {
        let slopes = consecutive(ks, true);
        let pairs: Vec<f64> = ks
            .iter()
            .enumerate()
            .flat_map(|(i, a)| ks[i + 1..].iter().map(move |b| (a, b)))
            .filter(|(a, b)| a.1 == b.1 && b.0 > a.0)
            .map(|(a, b)| (b.2 - a.2) / (b.0 - a.0) as f64)
            .collect();
        Self {
            slope: (!slopes.is_empty()).then(|| median(slopes)),
            trend: (pairs.len() >= 3).then(|| median(pairs)),
        }
    }

    /// Each part of `self`, else of `other`.
    fn or(self, other: Self) -> Self {
        Self {
            slope: self.slope.or(other.slope),
            trend: self.trend.or(other.trend),
        }
    }
}

/// The slopes of `ln k` between consecutive steps of `ks` (`(step, P_M, ln k)`), only between
/// steps of one `P_M` where `same_pm`.
fn consecutive(ks: &[(u64, Candidate, f64)], same_pm: bool) -> Vec<f64> {
    ks.windows(2)
        .filter(|w| w[1].0 > w[0].0 && (!same_pm || w[0].1 == w[1].1))
        .map(|w| (w[1].2 - w[0].2) / (w[1].0 - w[0].0) as f64)
        .collect()
}

/// Production steps (counted in observations) a candidate's own measurement is remembered.
pub const MEMORY: u64 = 32;

/// The default [`Controller::horizon`], steps: on Gray–Scott 128³ (σ growing 4 % a step at one
/// `P_M`, 60 steps under `size:1MB`) a change planned for the next step alone was outgrown two
/// to four steps later (8 changes of r or γ in 56 steps); planned for 8 steps, 5; for 16, 4,
/// but at 68 % of the budget used on average instead of 82 % and a q regret of 1.8 dB instead
/// of 0.2 (docs/tuning.md).
pub const HORIZON: u64 = 8;

/// The default [`Controller::plan_growth`]: a change of `P_M` is planned to hold for
/// [`Controller::horizon`] steps or for the steps the trend takes to grow σ this much,
/// whichever is fewer. On the growing series (8–16 % a step) the 8 steps of [`HORIZON`] came
/// to 1.9–3.3×, so the first steps of each plan used a third to a half of the budget. At 1.4×
/// the bound also cut Gray–Scott 128³'s plans short in its bursts of growth (4 % a step on
/// average, up to 6 %): 13 changes per 100 steps instead of 6–9, up to 1 dB less mean q; at
/// 1.6× its plans keep the 8 steps (docs/tuning.md, "Plans bounded by growth").
pub const PLAN_GROWTH: f64 = 1.6;

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
    /// A controller for `budgets` over `grid`.
    pub fn new(budgets: Budgets, headroom: f64, grid: ParamGrid) -> Self {
        Self {
            sigma_target: budgets.size_bytes.map(|b| b as f64),
            tau_target: budgets.time_secs,
            headroom,
            hysteresis: 0.1,
            horizon: HORIZON,
            dwell: DWELL,
            plan_growth: PLAN_GROWTH,
            grid,
            window: VecDeque::with_capacity(WINDOW),
            miss: 1.0,
            run: None,
            seen: BTreeMap::new(),
            carried: None,
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
    /// say nothing of what comes next. How fast σ grew at one `P_M` is kept, and forecasts
    /// with it until the steps from `step` on show their own: a decision lands steps after its
    /// tuning began, and a field that grew 19 % a step before a re-tune (the growing series)
    /// went on growing after it, where a forecast without growth put the third step of the
    /// new `P_M` at 1.30× the budget.
    pub fn rebase(&mut self, step: u64) {
        let raw: Vec<(u64, Candidate, f64)> = self
            .window
            .iter()
            .map(|o| (o.step, o.candidate, (o.sigma_bytes.max(1) as f64).ln()))
            .collect();
        self.carried = Some(Growth::of(&raw).or(self.carried.unwrap_or_default()));
        self.window.retain(|o| o.step >= step);
        self.seen.retain(|_, o| o.step >= step);
        self.miss = 1.0;
        // The run of the newest candidate among the steps kept.
        self.run = self.window.back().map(|newest| {
            let n = self
                .window
                .iter()
                .rev()
                .take_while(|o| o.candidate == newest.candidate)
                .count();
            (newest.candidate, n as u64)
        });
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
        // P_M, which the surface's error does not touch; before the steps since a change of
        // character have one, the growth the steps before it showed; while every step has a
        // P_M of its own (corrections at each step), between any consecutive steps (an error
        // of the surface at one P_M is then a jump between two steps, which the median passes
        // over). The trend: the Theil–Sen slope over every pair of the window's steps made with
        // one P_M (three pairs at least), no more than the slope.
        let seen = Growth::of(&ks).or(self.carried.unwrap_or_default());
        let slope = seen
            .slope
            .unwrap_or_else(|| median(consecutive(&ks, false)))
            .max(0.0);
        let trend = seen.trend;
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
        let horizon = self.horizon.saturating_mul(self.stride());
        if let Some(trend) = next.trend_per_step.filter(|_| horizon > 0) {
            // The forecast for `at`, carried on by the trend to the horizon (τ by no more
            // than its own growth), or only as far as the trend grows σ by `plan_growth`.
            let to_growth = self.plan_growth.ln() / trend.ln().max(f64::MIN_POSITIVE);
            let lasting = at.saturating_add((to_growth.ceil().min(horizon as f64) as u64).max(1));
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
        let held = match self.run {
            Some((c, n)) if c == current => n,
            _ => 0,
        };
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
mod tests;
