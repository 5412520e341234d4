//! Utility functions ν (Sec. 5.4): map (σ, q, τ) to one number, smaller is better, `+∞` for
//! infeasible. Implement [`Utility`] to add one.

use crate::measure::Measurement;

/// A utility function ν (shareable across threads, as the tuner service needs).
pub trait Utility: Send + Sync {
    /// A short description, e.g. `size < 2.0 MB`.
    fn describe(&self) -> String;
    /// ν(σ, q, τ): smaller is better; `+∞` when the constraint is not met.
    fn value(&self, m: &Measurement) -> f64;
}

/// ν_size (Eq. 1): `−q` if `σ < σ_target`, else `∞`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SizeBudget {
    /// σ_target, bytes.
    pub sigma_target: u64,
}

/// ν_time (Eq. 2): `−q` if `τ < τ_target`, else `∞`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TimeBudget {
    /// τ_target, seconds.
    pub tau_target: f64,
}

/// Both budgets at once: `−q` if `σ < σ_target` and `τ < τ_target`, else `∞`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SizeAndTime {
    /// σ_target, bytes.
    pub sigma_target: u64,
    /// τ_target, seconds.
    pub tau_target: f64,
}

/// The dual: the smallest σ with `q ≥ q_target` (value σ in bytes, `∞` below the target).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct QualityTarget {
    /// q_target, dB.
    pub q_target: f64,
}

impl Utility for SizeBudget {
    fn describe(&self) -> String {
        format!("max q with σ < {}", bytes_text(self.sigma_target))
    }
    fn value(&self, m: &Measurement) -> f64 {
        if m.sizing.sigma_bytes < self.sigma_target {
            -m.q()
        } else {
            f64::INFINITY
        }
    }
}

impl Utility for TimeBudget {
    fn describe(&self) -> String {
        format!("max q with τ < {} s", self.tau_target)
    }
    fn value(&self, m: &Measurement) -> f64 {
        if m.sizing.tau_secs < self.tau_target {
            -m.q()
        } else {
            f64::INFINITY
        }
    }
}

impl Utility for SizeAndTime {
    fn describe(&self) -> String {
        format!(
            "max q with σ < {} and τ < {} s",
            bytes_text(self.sigma_target),
            self.tau_target
        )
    }
    fn value(&self, m: &Measurement) -> f64 {
        if m.sizing.sigma_bytes < self.sigma_target && m.sizing.tau_secs < self.tau_target {
            -m.q()
        } else {
            f64::INFINITY
        }
    }
}

impl Utility for QualityTarget {
    fn describe(&self) -> String {
        format!("min σ with q ≥ {} dB", self.q_target)
    }
    fn value(&self, m: &Measurement) -> f64 {
        if m.q() >= self.q_target {
            m.sizing.sigma_bytes as f64
        } else {
            f64::INFINITY
        }
    }
}

/// Errors parsing a utility or a size.
#[derive(Debug, thiserror::Error, PartialEq)]
#[error("utility {spec:?}: {problem}")]
pub struct UtilityError {
    /// As given.
    pub spec: String,
    /// What is wrong.
    pub problem: String,
}

pub use insitu_core::budget::Budgets;
pub use insitu_core::units::parse_bytes;

/// Bytes as text with a decimal unit.
pub fn bytes_text(b: u64) -> String {
    match b {
        b if b >= 1_000_000_000 => format!("{:.2} GB", b as f64 / 1e9),
        b if b >= 1_000_000 => format!("{:.2} MB", b as f64 / 1e6),
        b if b >= 1_000 => format!("{:.1} kB", b as f64 / 1e3),
        b => format!("{b} B"),
    }
}

/// A built-in utility from text: `size:2MB` (Eq. 1), `time:0.5` or `time:0.5s` or
/// `time:500ms` (Eq. 2, seconds), `size:2MB,time:0.5s` (both), `quality:40` or `quality:40dB`
/// (smallest σ with q ≥ 40 dB).
///
/// # Errors
/// [`UtilityError`] naming the spec: unknown kind, unparsable or non-positive budget.
pub fn parse_utility(spec: &str) -> Result<Box<dyn Utility>, UtilityError> {
    UtilitySpec::parse(spec).map(|u| u.utility())
}

/// A built-in utility, parsed: its budgets or target as numbers.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum UtilitySpec {
    /// ν_size (Eq. 1) with σ_target, bytes.
    Size(u64),
    /// ν_time (Eq. 2) with τ_target, seconds.
    Time(f64),
    /// Both budgets.
    SizeAndTime(u64, f64),
    /// The dual with q_target, dB.
    Quality(f64),
}

impl UtilitySpec {
    /// The utility function.
    pub fn utility(self) -> Box<dyn Utility> {
        match self {
            Self::Size(s) => Box::new(SizeBudget { sigma_target: s }),
            Self::Time(t) => Box::new(TimeBudget { tau_target: t }),
            Self::SizeAndTime(s, t) => Box::new(SizeAndTime {
                sigma_target: s,
                tau_target: t,
            }),
            Self::Quality(q) => Box::new(QualityTarget { q_target: q }),
        }
    }

    /// σ_target (bytes) and τ_target (seconds), where the utility has them.
    pub fn budgets(self) -> Budgets {
        let (size_bytes, time_secs) = match self {
            Self::Size(s) => (Some(s), None),
            Self::Time(t) => (None, Some(t)),
            Self::SizeAndTime(s, t) => (Some(s), Some(t)),
            Self::Quality(_) => (None, None),
        };
        Budgets {
            size_bytes,
            time_secs,
        }
    }

    /// The same with the budgets scaled by `keep` (e.g. 0.95 keeps 5 % headroom; a size stays
    /// ≥ 1 byte); a quality target is unchanged.
    pub fn scaled(self, keep: f64) -> Self {
        let size = |s: u64| ((s as f64 * keep).round() as u64).max(1);
        match self {
            Self::Size(s) => Self::Size(size(s)),
            Self::Time(t) => Self::Time(t * keep),
            Self::SizeAndTime(s, t) => Self::SizeAndTime(size(s), t * keep),
            Self::Quality(q) => Self::Quality(q),
        }
    }

    /// Parses a spec (see [`parse_utility`]).
    ///
    /// # Errors
    /// [`UtilityError`] naming the spec.
    pub fn parse(spec: &str) -> Result<Self, UtilityError> {
        let err = |problem: &str| UtilityError {
            spec: spec.to_owned(),
            problem: problem.to_owned(),
        };
        let (mut size, mut time, mut quality) = (None, None, None);
        for part in spec.split(',') {
            let (kind, value) = part
                .split_once(':')
                .ok_or_else(|| err("expected KIND:VALUE with KIND size, time or quality"))?;
            match kind.trim() {
                "size" => {
                    let b = parse_bytes(value)
                        .ok_or_else(|| err("size must be bytes such as 2MB, 800kB or 123456"))?;
                    if b == 0 {
                        return Err(err("a size budget must be > 0"));
                    }
                    size = Some(b);
                }
                "time" => {
                    let t = parse_seconds(value)
                        .ok_or_else(|| err("time must be seconds such as 0.5, 0.5s or 500ms"))?;
                    if !(t.is_finite() && t > 0.0) {
                        return Err(err("a time budget must be finite and > 0"));
                    }
                    time = Some(t);
                }
                "quality" => {
                    let q = parse_db(value)
                        .ok_or_else(|| err("quality must be dB such as 40 or 40dB"))?;
                    if !q.is_finite() {
                        return Err(err("a quality target must be finite"));
                    }
                    quality = Some(q);
                }
                other => {
                    return Err(err(&format!(
                        "unknown kind {other:?}; use size, time or quality"
                    )))
                }
            }
        }
        Ok(match (size, time, quality) {
            (Some(s), None, None) => Self::Size(s),
            (None, Some(t), None) => Self::Time(t),
            (Some(s), Some(t), None) => Self::SizeAndTime(s, t),
            (None, None, Some(q)) => Self::Quality(q),
            _ => return Err(err("quality cannot be combined with budgets")),
        })
    }
}

/// Seconds as text: a number, with an optional unit `s` or `ms` (`0.5`, `0.5s`, `500 ms`).
pub fn parse_seconds(text: &str) -> Option<f64> {
    let t = text.trim();
    let (number, scale) = if let Some(n) = t.strip_suffix("ms") {
        (n, 1e-3)
    } else if let Some(n) = t.strip_suffix('s') {
        (n, 1.0)
    } else {
        (t, 1.0)
    };
    number.trim().parse::<f64>().ok().map(|v| v * scale)
}

/// Decibels as text: a number, with an optional unit `dB` (any case: `40`, `40dB`, `40 db`).
pub fn parse_db(text: &str) -> Option<f64> {
    let t = text.trim();
    let cut = t.len().saturating_sub(2);
    let number = match (t.get(..cut), t.get(cut..)) {
        (Some(n), Some(unit)) if unit.eq_ignore_ascii_case("db") => n,
        _ => t,
    };
    number.trim().parse().ok()
}

/// The row minimising ν, or `None` when every row is infeasible (Alg. 1, lines 19–25).
pub fn best<'m>(rows: &'m [Measurement], u: &dyn Utility) -> Option<(&'m Measurement, f64)> {
    rows.iter()
        .map(|m| (m, u.value(m)))
        .filter(|(_, v)| *v < f64::INFINITY)
        .min_by(|a, b| {
            a.1.total_cmp(&b.1)
                .then(a.0.sizing.sigma_bytes.cmp(&b.0.sizing.sigma_bytes))
        })
}

#[cfg(test)]
mod tests {
    use super::*;
    use insitu_core::evaluate::Sizing;
    use insitu_core::metrics::Db;

    fn m(sigma: u64, q: f64, tau: f64) -> Measurement {
        Measurement {
            r: 1,
            gamma: 0.1,
            precision: Default::default(),
            sigma_paper_bytes: None,
            sizing: Sizing {
                sigma_bytes: sigma,
                tau_secs: tau,
                ..Sizing::default()
            },
            tau_render_secs: 0.0,
            q_db: Db(q),
            view_q_db: vec![],
            ssim: None,
        }
    }

    #[test]
    fn the_papers_equations_and_the_dual() {
        let rows = [m(100, 30.0, 1.0), m(200, 35.0, 2.0), m(300, 40.0, 3.0)];
        let pick = |spec: &str| {
            best(&rows, parse_utility(spec).unwrap().as_ref()).map(|(m, _)| m.sizing.sigma_bytes)
        };
        assert_eq!(pick("size:250"), Some(200));
        assert_eq!(pick("size:200"), Some(100), "σ < σ_target is strict");
        assert_eq!(pick("size:100"), None, "infeasible is None, not a default");
        assert_eq!(pick("time:2.5"), Some(200));
        assert_eq!(pick("size:1kB,time:1.5"), Some(100));
        assert_eq!(pick("quality:34"), Some(200));
        assert_eq!(pick("quality:41"), None);
        // Units as the docs write them.
        assert_eq!(pick("time:2.5s"), Some(200));
        assert_eq!(pick("time:2500ms"), Some(200));
        assert_eq!(pick("quality:34dB"), Some(200));
        assert_eq!(pick("quality:34 db"), Some(200));
    }

    #[test]
    fn bad_specs_are_refused() {
        for s in [
            "size:0",
            "size:-1MB",
            "time:0",
            "time:inf",
            "speed:3",
            "size",
            "quality:40,size:1MB",
            "size:3XB",
            "time:0.5h",
            "time:ms",
            "quality:40€",
            "quality:dB",
        ] {
            assert!(parse_utility(s).is_err(), "{s}");
        }
        assert_eq!(parse_bytes("1.5MB"), Some(1_500_000));
        assert_eq!(parse_bytes("2MiB"), Some(2 << 20));
    }
}
