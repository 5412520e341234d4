//! The guard on the tuner's size budget (`generation.size_guard`): a step made under the
//! tuner's decision whose σ comes out far over the budget (the first step of a new character,
//! which no forecast saw) is made again toward the budget and shipped at its last try.
//!
//! Unlike the hard limit ([`super::coarser`]), the guard keeps the decided precision and
//! raises γ: the tuner chose the precision with r and γ, and on the tiled orbital
//! (`insitu_e2e::drift::changing_character`, step 8, r 128) 8 → 6 bits cut σ by 40 % for
//! 5.5 dB of q where raising γ ninefold cut it by 48 % for 1 dB.

use crate::config::Generation;
use insitu_core::VdiParams;

/// Tries the guard makes a step again at most (generations); the step ships at the last.
pub const MAX_GUARD_RETRIES: u32 = 3;

/// The share of the budget a try made again aims at, so that it lands within it.
const AIM: f64 = 0.95;

/// The exponent `k` of `σ ∝ γ^−k` assumed before two tries have measured it (Sec. 6.1 has
/// σ fall about as 1/γ at the γ worth tuning; at the small γ a size budget picks it falls
/// more slowly).
const FIRST_K: f64 = 0.5;

/// Bounds on the measured `k`: on the tiled orbital at r 128 it runs from 0.15 (γ 0.001 to
/// 0.002) to 0.5 (γ 0.003 to 0.009); below 0.3 the secant would leap far past the budget.
const K_RANGE: (f64, f64) = (0.3, 1.0);

/// Bounds on the factor γ is raised by in one try.
const FACTOR_RANGE: (f64, f64) = (1.25, 8.0);

/// A rank's guard: a file over `trigger` bytes is made again toward `aim` bytes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Guard {
    /// σ over which a try is made again, bytes.
    pub trigger: u64,
    /// The rank's share of the tuner's budget, bytes.
    pub aim: u64,
}

impl Guard {
    /// The guard for one rank of a world of `ranks`: the rank's share of the tuner's budget,
    /// while the settings carry one and a ratio, and no time limit (a try made again could
    /// break it).
    pub fn of(gen: &Generation, ranks: u32) -> Option<Self> {
        let ratio = gen.size_guard?;
        let budget = gen.tuner_size_budget?;
        if gen.limits.time_secs.is_some() {
            return None;
        }
        let aim = (budget / u64::from(ranks.max(1))).max(1);
        Some(Self {
            trigger: (aim as f64 * ratio) as u64,
            aim,
        })
    }

    /// The `P_M` the step is made again with after its tries `tries` (`P_M` and σ in bytes,
    /// the last the latest): γ raised by the power law `σ ∝ γ^−k` toward [`AIM`] of the aim,
    /// `k` measured by the last two tries at the same r and precision (else [`FIRST_K`]),
    /// by a factor in [`FACTOR_RANGE`], up to [`super::MAX_LIMIT_GAMMA`]; from there r
    /// shrunk by the square root of the excess (σ ∝ r²), at least by an eighth, where
    /// `may_shrink_r` (a world of one rank). `None` when none can go further or there is
    /// no try.
    pub fn next(&self, tries: &[(VdiParams, u64)], may_shrink_r: bool) -> Option<VdiParams> {
        let &(p, sigma) = tries.last()?;
        let over = sigma as f64 / (AIM * self.aim as f64);
        let k = match tries {
            [.., (a, sa), (b, sb)]
                if (a.resolution, a.precision) == (b.resolution, b.precision)
                    && b.gamma > a.gamma
                    && *sa > 0
                    && *sb > 0 =>
            {
                let k =
                    (*sa as f64 / *sb as f64).ln() / (f64::from(b.gamma) / f64::from(a.gamma)).ln();
                k.clamp(K_RANGE.0, K_RANGE.1)
            }
            _ => FIRST_K,
        };
        if p.gamma < super::MAX_LIMIT_GAMMA {
            let factor = over.powf(1.0 / k).clamp(FACTOR_RANGE.0, FACTOR_RANGE.1);
            let gamma =
                (f64::from(p.gamma.max(1e-3)) * factor).min(f64::from(super::MAX_LIMIT_GAMMA));
            return Some(VdiParams {
                gamma: gamma as f32,
                ..p
            });
        }
        super::shrunk(p, over, may_shrink_r)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use insitu_core::Precision;

    /// σ of a try under the power law `σ = 2·aim·(γ/γ0)^−k` (twice the aim at the decided γ).
    fn law(aim: u64, over: f64, k: f64, p: VdiParams) -> u64 {
        (over * aim as f64 * (f64::from(p.gamma) / 0.001).powf(-k)) as u64
    }

    /// Over the measured range of `σ ∝ γ^−k`, from 2× and 4× the budget, the guard comes
    /// within its trigger in its tries, not far below the budget, at the decided r and
    /// precision.
    #[test]
    fn tries_along_a_power_law_land_within_the_trigger_and_near_the_budget() {
        let g = Guard {
            trigger: 125_000,
            aim: 100_000,
        };
        for k in [0.3, 0.5, 0.75, 1.0] {
            for over in [2.0, 4.0] {
                let p0 = VdiParams {
                    resolution: 128,
                    gamma: 0.001,
                    precision: Precision::Bits(8),
                };
                let mut tries = vec![(p0, law(g.aim, over, k, p0))];
                while tries.last().unwrap().1 > g.trigger {
                    assert!(
                        tries.len() <= MAX_GUARD_RETRIES as usize,
                        "k {k}, {over}×: {tries:?}"
                    );
                    let p = g.next(&tries, true).unwrap();
                    assert_eq!((p.resolution, p.precision), (128, Precision::Bits(8)));
                    tries.push((p, law(g.aim, over, k, p)));
                }
                let last = tries.last().unwrap().1;
                assert!(last >= g.aim * 2 / 5, "k {k}, {over}×: {tries:?}");
            }
        }
    }

    /// At the largest γ the guard shrinks r (one rank), or gives up (several).
    #[test]
    fn at_the_largest_gamma_r_shrinks_for_one_rank_only() {
        let g = Guard {
            trigger: 125,
            aim: 100,
        };
        let p = VdiParams {
            resolution: 128,
            gamma: super::super::MAX_LIMIT_GAMMA,
            precision: Precision::Bits(8),
        };
        let next = g.next(&[(p, 400)], true).unwrap();
        assert!(next.resolution < 128 && next.gamma == p.gamma);
        assert_eq!(g.next(&[(p, 400)], false), None);
        assert_eq!(g.next(&[], true), None);
    }
}
