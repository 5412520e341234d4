//! The σ/τ surface the controller plans on: what the last tuning's trials and size probes
//! measured, each candidate's worst case over the characteristic steps, one layer per
//! precision, interpolated in log γ at a resolution and scaled by r² across resolutions.

use crate::grid::Candidate;
use std::collections::BTreeMap;

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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::control::tests::{c, g, law, surface_of};
    use insitu_core::vdi::Precision;

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
}
