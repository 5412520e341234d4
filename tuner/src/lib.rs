//! Auto-tuning of `P_M = (r, γ)` (Frey & Ertl, Sec. 4–6).
//!
//! - [`grid`]: the candidate set (the paper's grid by default).
//! - [`study`]: Alg. 1's measurement loop — references rendered once per view, every
//!   measurement ([`measure::Measurement`]: σ, q per view and pooled, SSIM, τ, compression
//!   time) cached on disk ([`cache`]) under the identity of everything that determines it.
//! - [`utility`]: ν_size (Eq. 1), ν_time (Eq. 2), both, and the dual; a trait for more.
//! - [`search`]: exhaustive grid and an adaptive search that needs a fraction of the
//!   measurements.
//! - [`series`]: characteristic time steps, the conservative `P_M`, cross-evaluation.
//! - [`live`]: the same while a simulation runs (the tuner service's maths): characteristic
//!   steps as they arrive, the worst case over steps as an oracle, budgets over ranks.
//! - [`control`]: closed-loop control between tunings: every production step corrects the
//!   measured σ/τ surface, forecasts the growth and steps `P_M` to keep the budget.
//! - [`accuracy`]: what accuracy costs in time, knob by knob.
//! - [`charts`]: the study map (Fig. 7), Pareto fronts, the budget ladder (Fig. 8), accuracy.
//! - [`report`]: CSV and JSON of a study.

#![cfg_attr(test, allow(clippy::unwrap_used, clippy::expect_used))]

pub mod accuracy;
pub mod cache;
pub mod charts;
pub mod control;
pub mod grid;
pub mod live;
pub mod measure;
pub mod report;
pub mod search;
pub mod series;
pub mod study;
pub mod utility;

pub use grid::{Candidate, ParamGrid};
pub use measure::Measurement;
pub use study::{Oracle, Study, StudySetup, TableOracle};
pub use utility::{parse_utility, Utility};
