//! Why a tuning starts: the step that changed the characteristic set and the cause, which the
//! log and the decision it leads to say in words.

use std::fmt;

/// Why the characteristic set changed, so that a tuning is due.
#[derive(Clone, Debug)]
pub struct Trigger {
    /// The step that changed the set (or the newest one when none did).
    pub step: u64,
    /// Why.
    pub cause: Cause,
}

/// The causes of a tuning.
#[derive(Clone, Debug, PartialEq)]
pub enum Cause {
    /// The run's first characteristic step.
    First,
    /// A step whose histogram lies farther than the threshold (total variation) from every
    /// characteristic step.
    NewCharacter {
        /// Its distance to the nearest characteristic step.
        distance: f64,
        /// The threshold it exceeded.
        threshold: f64,
    },
    /// A production step whose σ came out far over what its decision planned for it: the
    /// data changed character in a way its histogram does not show (structure, not values).
    SizeMiss {
        /// The step's σ, bytes (summed over its ranks).
        sigma_bytes: u64,
        /// What its decision planned for it, bytes.
        planned_bytes: f64,
        /// The factor over the plan that makes a step characteristic.
        threshold: f64,
    },
    /// While a tuning for a step that missed its plan was due or running, a later step made
    /// with the same `P_M` came out far over that step's σ: the data changed character again,
    /// and the tuning for the earlier step would not represent it.
    SizeJump {
        /// The step's σ, bytes (summed over its ranks).
        sigma_bytes: u64,
        /// The step the tuning was due for.
        than_step: u64,
        /// Its σ, bytes.
        than_bytes: u64,
        /// The factor over it that makes a step characteristic.
        threshold: f64,
    },
    /// A production step broke the budget; `why` names the indicator and by how much.
    BrokeBudget {
        /// E.g. `σ 1000 B ≥ σ_target 1000 B`.
        why: String,
    },
    /// Characteristic steps were lost with the node that held them.
    Lost {
        /// The steps lost.
        steps: Vec<u64>,
    },
    /// A restarted tuner resumes the tuning it had under way.
    Resume,
    /// An operator steered the run (docs/steering.md); `what` says what changed.
    Steered {
        /// E.g. `utility size:1MB`.
        what: String,
    },
}

impl fmt::Display for Trigger {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let step = self.step;
        match &self.cause {
            Cause::First => write!(f, "step {step} is the first characteristic step"),
            Cause::NewCharacter {
                distance,
                threshold,
            } => write!(
                f,
                "step {step} became characteristic (histogram distance {distance:.3} > threshold {threshold})"
            ),
            Cause::SizeMiss {
                sigma_bytes,
                planned_bytes,
                threshold,
            } => write!(
                f,
                "step {step} became characteristic (σ {sigma_bytes} B is {:.2}× the {:.0} B its P_M was planned at, over {threshold}×: the data changed character)",
                *sigma_bytes as f64 / planned_bytes,
                planned_bytes
            ),
            Cause::SizeJump {
                sigma_bytes,
                than_step,
                than_bytes,
                threshold,
            } => write!(
                f,
                "step {step} became characteristic (σ {sigma_bytes} B is {:.2}× the {than_bytes} B of step {than_step} at the same P_M, over {threshold}×, while a tuning for that step was due: the data changed character again)",
                *sigma_bytes as f64 / (*than_bytes).max(1) as f64,
            ),
            Cause::BrokeBudget { why } => {
                write!(f, "production step {step} broke the budget ({why})")
            }
            Cause::Lost { steps } => {
                write!(f, "characteristic step(s) {steps:?} lost with their node")
            }
            Cause::Resume => write!(f, "resuming the tuning of a restarted tuner"),
            Cause::Steered { what } => write!(f, "steered ({what}) at step {step}"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_cause_reads_as_its_reason() {
        let t = |cause| Trigger { step: 7, cause }.to_string();
        assert_eq!(t(Cause::First), "step 7 is the first characteristic step");
        assert_eq!(
            t(Cause::NewCharacter {
                distance: 0.2,
                threshold: 0.15
            }),
            "step 7 became characteristic (histogram distance 0.200 > threshold 0.15)"
        );
        assert_eq!(
            t(Cause::SizeMiss {
                sigma_bytes: 300,
                planned_bytes: 100.0,
                threshold: 1.5
            }),
            "step 7 became characteristic (σ 300 B is 3.00× the 100 B its P_M was planned at, over 1.5×: the data changed character)"
        );
        assert_eq!(
            t(Cause::SizeJump {
                sigma_bytes: 300,
                than_step: 5,
                than_bytes: 150,
                threshold: 1.5
            }),
            "step 7 became characteristic (σ 300 B is 2.00× the 150 B of step 5 at the same P_M, over 1.5×, while a tuning for that step was due: the data changed character again)"
        );
        assert_eq!(
            t(Cause::BrokeBudget {
                why: "σ 2 kB ≥ σ_target 1 kB".into()
            }),
            "production step 7 broke the budget (σ 2 kB ≥ σ_target 1 kB)"
        );
        assert_eq!(
            t(Cause::Lost { steps: vec![3, 5] }),
            "characteristic step(s) [3, 5] lost with their node"
        );
    }
}
