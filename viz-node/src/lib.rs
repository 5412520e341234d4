//! The viz-node: receives VDIs and reference frames over gRPC ([`service`]), keeps them in a
//! recording directory written atomically ([`store`]), renders any stored step from any
//! camera, and when a step has reference frames, scores its VDI ([`score`]: PSNR and SSIM at
//! the test views) and reports (step, `P_M`, σ, τ, q) to subscribers.

#![cfg_attr(test, allow(clippy::unwrap_used, clippy::expect_used))]

pub mod config;
pub mod node;
pub mod score;
pub mod service;
pub mod store;

pub use config::Config;
pub use node::{start, RunningViz};
