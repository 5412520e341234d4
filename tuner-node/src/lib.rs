//! The tuner service (docs/conventions.md, "The system"; Frey & Ertl, Sec. 4, 6, 7): a thin layer over
//! the `insitu-tuner` library that closes the loop while a simulation runs.
//!
//! Generator-nodes dial out to it and keep one stream open ([`service`], [`hub`]). From their
//! per-step summaries the [`engine`] picks characteristic steps (the offline rule, live), asks
//! the nodes that hold those steps' fields to measure candidate `P_M` (trials, at lower
//! priority than production), searches for the conservative choice over all characteristic
//! steps, and pushes it with an increasing version. It watches the viz-node's quality reports
//! and re-tunes when a production step breaks the budget. Everything it learns is persisted
//! atomically ([`state`]), so a restarted tuner repeats no finished trial. One tuning is the
//! `tune` module. [`config`] is the
//! TOML file; [`node`] wires it together.

#![cfg_attr(test, allow(clippy::unwrap_used, clippy::expect_used))]

pub mod check;
pub mod config;
pub mod engine;
pub mod hub;
pub mod node;
pub mod preview;
pub mod service;
pub mod state;
pub mod steer;
pub mod trigger;
mod tune;

pub use config::Config;
pub use node::{start, RunningTuner, StartError};
