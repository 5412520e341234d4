//! σ_target and τ_target in one type: a utility's budgets (paper Eq. 1 and 2), which the
//! tuner plans for and a run is judged against, and a generator-node's hard limits, which no
//! stored step may exceed. Either may be absent; absence is `None`, never a zero.

use serde::{Deserialize, Serialize};

mod lowering;
pub use lowering::{lowered_resolution, GROWTH, HEADROOM, MIN_EXCESS, MIN_R, R_STEP};

/// A size budget (bytes) and a time budget (seconds), each where one is set.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Budgets {
    /// σ_target: a step's VDI bytes (summed over its ranks), > 0 where set.
    pub size_bytes: Option<u64>,
    /// τ_target: a step's generation seconds (its slowest rank's), finite and > 0 where set.
    pub time_secs: Option<f64>,
}

impl Budgets {
    /// No budget of either kind.
    pub const NONE: Self = Self {
        size_bytes: None,
        time_secs: None,
    };

    /// A size budget alone, `bytes`.
    pub fn size(bytes: u64) -> Self {
        Self {
            size_bytes: Some(bytes),
            time_secs: None,
        }
    }

    /// A time budget alone, `secs` seconds.
    pub fn time(secs: f64) -> Self {
        Self {
            size_bytes: None,
            time_secs: Some(secs),
        }
    }

    /// Whether neither budget is set.
    pub fn is_none(&self) -> bool {
        self.size_bytes.is_none() && self.time_secs.is_none()
    }

    /// The budgets as a proto3 message carries them, 0 for "none" (`u64` bytes, `f64`
    /// seconds): a size of 0 and a time that is not finite and positive are none.
    pub fn from_wire(size_bytes: u64, time_secs: f64) -> Self {
        Self {
            size_bytes: (size_bytes > 0).then_some(size_bytes),
            time_secs: (time_secs.is_finite() && time_secs > 0.0).then_some(time_secs),
        }
    }

    /// The budgets as a proto3 message carries them: 0 where none ([`Budgets::from_wire`]).
    pub fn to_wire(&self) -> (u64, f64) {
        (self.size_bytes.unwrap_or(0), self.time_secs.unwrap_or(0.0))
    }

    /// One rank's share of a world's budgets, `ranks` ranks side by side: `1/ranks` of the
    /// size (σ of a step is summed over its ranks; at least 1 byte), the whole time (τ of a
    /// step is its slowest rank's).
    pub fn share(&self, ranks: u32) -> Self {
        Self {
            size_bytes: self
                .size_bytes
                .map(|b| (b / u64::from(ranks.max(1))).max(1)),
            time_secs: self.time_secs,
        }
    }

    /// σ over σ_target and τ over τ_target (`sigma_bytes` bytes, `tau_secs` seconds), each
    /// where its budget is set.
    pub fn ratios(&self, sigma_bytes: f64, tau_secs: f64) -> (Option<f64>, Option<f64>) {
        (
            self.size_bytes.map(|b| sigma_bytes / b as f64),
            self.time_secs.map(|b| tau_secs / b),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_wire_s_zeros_are_none_and_come_back_as_zeros() {
        assert!(Budgets::from_wire(0, 0.0).is_none());
        assert!(Budgets::from_wire(0, f64::NAN).is_none());
        assert!(Budgets::from_wire(0, -1.0).is_none());
        let b = Budgets::from_wire(1_000_000, 0.5);
        assert_eq!(b.size_bytes, Some(1_000_000));
        assert_eq!(b.time_secs, Some(0.5));
        assert_eq!(b.to_wire(), (1_000_000, 0.5));
        assert_eq!(Budgets::NONE.to_wire(), (0, 0.0));
    }

    #[test]
    fn ratios_only_where_a_budget_is_set() {
        let size = Budgets::size(400);
        assert_eq!(size.ratios(500.0, 2.0), (Some(1.25), None));
        assert_eq!(Budgets::NONE.ratios(500.0, 2.0), (None, None));
    }

    #[test]
    fn a_rank_keeps_its_share_of_the_size_and_the_whole_time() {
        let world = Budgets {
            size_bytes: Some(1000),
            time_secs: Some(0.5),
        };
        let rank = world.share(4);
        assert_eq!((rank.size_bytes, rank.time_secs), (Some(250), Some(0.5)));
        assert_eq!(world.share(0), world);
        assert_eq!(Budgets::size(3).share(8).size_bytes, Some(1));
        assert!(Budgets::NONE.share(2).is_none());
    }
}
