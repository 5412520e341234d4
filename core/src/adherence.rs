//! How well a run kept its budget: the share of steps within it, the worst overshoot, how
//! much of the budget the steps used on average, and how often the `P_M` changed.
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
    /// The mean value over the budget, as a ratio (the share of the budget used; 0 with no
    /// steps or a non-finite value).
    pub mean_ratio: f64,
    /// Changes of `P_M` (r or γ) between consecutive counted steps: a scientist scrubbing
    /// through the recording sees the picture change this often (a new version of the same
    /// r and γ is no visible change).
    pub changes: usize,
}

impl Adherence {
    /// Adherence of `steps` — `(P_M version, (r, γ), value)` per step in step order, a value
    /// in the budget's unit (bytes or seconds) — to `budget` (> 0). Non-finite values count
    /// as over it.
    pub fn of(steps: impl IntoIterator<Item = (u64, (u32, f32), f64)>, budget: f64) -> Self {
        let mut a = Self::default();
        let mut last: Option<(u32, f32)> = None;
        let mut sum = 0.0;
        for (version, pm, value) in steps {
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
            sum += ratio;
            a.changes += usize::from(last.is_some_and(|l| l != pm));
            last = Some(pm);
        }
        if a.steps > 0 && sum.is_finite() {
            a.mean_ratio = sum / a.steps as f64;
        }
        a
    }

    /// `P_M` changes per 100 counted steps (0 with no steps).
    pub fn changes_per_100(&self) -> f64 {
        if self.steps == 0 {
            0.0
        } else {
            100.0 * self.changes as f64 / self.steps as f64
        }
    }

    /// Share of the steps within the budget, in [0, 1] (1 with no steps: nothing broke it).
    pub fn share(&self) -> f64 {
        if self.steps == 0 {
            1.0
        } else {
            self.within as f64 / self.steps as f64
        }
    }

    /// As JSON: `{"steps", "within", "share", "worst_ratio", "mean_ratio", "pm_changes",
    /// "pm_changes_per_100"}` (what the CLI, the viewer's API and the export print).
    pub fn json(&self) -> serde_json::Value {
        serde_json::json!({
            "steps": self.steps,
            "within": self.within,
            "share": self.share(),
            "worst_ratio": self.worst_ratio,
            "mean_ratio": self.mean_ratio,
            "pm_changes": self.changes,
            "pm_changes_per_100": self.changes_per_100(),
        })
    }

    /// In words, e.g. "49 of 50 steps within (98 %), worst 1.10×, mean use 81 %, 2 changes of
    /// P_M (4 per 100 steps)".
    pub fn describe(&self) -> String {
        format!(
            "{} of {} steps within ({:.0} %), worst {:.2}×, mean use {:.0} %, {} change{} of P_M ({:.0} per 100 steps)",
            self.within,
            self.steps,
            100.0 * self.share(),
            self.worst_ratio,
            100.0 * self.mean_ratio,
            self.changes,
            if self.changes == 1 { "" } else { "s" },
            self.changes_per_100()
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn steps_before_the_first_decision_do_not_count_and_the_budget_is_strict() {
        let pm = (64, 0.01);
        let a = Adherence::of(
            [
                (0, pm, 5e6),
                (1, pm, 0.9e6),
                (1, pm, 1e6),
                (2, pm, 1.2e6),
                (2, pm, f64::NAN),
            ],
            1e6,
        );
        assert_eq!((a.steps, a.within), (4, 1));
        assert_eq!(a.worst_ratio, f64::INFINITY);
        assert_eq!(a.share(), 0.25);
        let a = Adherence::of([(1, pm, 0.5e6), (3, (64, 0.02), 1.1e6)], 1e6);
        assert!((a.worst_ratio - 1.1).abs() < 1e-12);
        assert!((a.mean_ratio - 0.8).abs() < 1e-12);
        assert_eq!(
            a.describe(),
            "1 of 2 steps within (50 %), worst 1.10×, mean use 80 %, 1 change of P_M (50 per 100 steps)"
        );
        assert_eq!(Adherence::of([(0, pm, 9.0)], 1.0).share(), 1.0);
    }

    /// A change counts where consecutive counted steps differ in r or γ; the step made before
    /// the first decision does not count, nor does a new version of the same r and γ.
    #[test]
    fn changes_count_between_consecutive_tuned_steps() {
        let (a, b) = ((64, 0.01), (64, 0.02));
        let steps = [
            (0, b, 1.0),
            (1, a, 1.0),
            (2, a, 1.0),
            (3, b, 1.0),
            (3, b, 1.0),
            (4, a, 1.0),
        ];
        let x = Adherence::of(steps, 2.0);
        assert_eq!((x.steps, x.changes), (5, 2));
        assert!((x.changes_per_100() - 40.0).abs() < 1e-12);
        assert!((x.mean_ratio - 0.5).abs() < 1e-12);
        assert_eq!(Adherence::of([(0, a, 1.0)], 2.0).changes_per_100(), 0.0);
    }
}
