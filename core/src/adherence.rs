//! How well a run kept its budget: the share of steps within it and the worst overshoot.
//!
//! Counted over the steps made with a tuner's `P_M` (version ≥ 1): the steps before the first
//! decision were made with the configured `P_M`, which no tuner chose. A step is within a
//! budget when its value is below it (Eq. 1 and 2 are strict: σ < σ_target, τ < τ_target).

/// Adherence of a run's steps to one budget.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Adherence {
    /// Steps counted (made with a tuner's `P_M`).
    pub steps: usize,
    /// Of those, steps below the budget.
    pub within: usize,
    /// The largest value over the budget, as a ratio (0 with no steps).
    pub worst_ratio: f64,
}

impl Adherence {
    /// Adherence of `steps` — `(P_M version, value)` per step, a value in the budget's unit
    /// (bytes or seconds) — to `budget` (> 0). Non-finite values count as over it.
    pub fn of(steps: impl IntoIterator<Item = (u64, f64)>, budget: f64) -> Self {
        let mut a = Self::default();
        for (version, value) in steps {
            if version == 0 {
                continue;
            }
            a.steps += 1;
            let ratio = if value.is_finite() {
                value / budget
            } else {
                f64::INFINITY
            };
            a.within += usize::from(ratio < 1.0);
            a.worst_ratio = a.worst_ratio.max(ratio);
        }
        a
    }

    /// Share of the steps within the budget, in [0, 1] (1 with no steps: nothing broke it).
    pub fn share(&self) -> f64 {
        if self.steps == 0 {
            1.0
        } else {
            self.within as f64 / self.steps as f64
        }
    }

    /// As JSON: `{"steps", "within", "share", "worst_ratio"}` (what the CLI, the viewer's API
    /// and the export print).
    pub fn json(&self) -> serde_json::Value {
        serde_json::json!({
            "steps": self.steps,
            "within": self.within,
            "share": self.share(),
            "worst_ratio": self.worst_ratio,
        })
    }

    /// In words, e.g. "49 of 50 steps within (98 %), worst 1.10×".
    pub fn describe(&self) -> String {
        format!(
            "{} of {} steps within ({:.0} %), worst {:.2}×",
            self.within,
            self.steps,
            100.0 * self.share(),
            self.worst_ratio
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn steps_before_the_first_decision_do_not_count_and_the_budget_is_strict() {
        let a = Adherence::of(
            [(0, 5e6), (1, 0.9e6), (1, 1e6), (2, 1.2e6), (2, f64::NAN)],
            1e6,
        );
        assert_eq!((a.steps, a.within), (4, 1));
        assert_eq!(a.worst_ratio, f64::INFINITY);
        assert_eq!(a.share(), 0.25);
        let a = Adherence::of([(1, 0.5e6), (3, 1.1e6)], 1e6);
        assert!((a.worst_ratio - 1.1).abs() < 1e-12);
        assert_eq!(a.describe(), "1 of 2 steps within (50 %), worst 1.10×");
        assert_eq!(Adherence::of([(0, 9.0)], 1.0).share(), 1.0);
    }
}
