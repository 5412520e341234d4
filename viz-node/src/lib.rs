//! The viz-node: receives VDIs and reference frames over gRPC ([`service`]), keeps them in a
//! recording directory written atomically ([`store`]), renders any stored step from any
//! camera, and when a step has reference frames, scores its VDI ([`score`]: PSNR and SSIM at
//! the test views) and reports (step, `P_M`, σ, τ, q) to subscribers. A step of many ranks is
//! composed into one VDI once all its ranks are in ([`compose`]), and the run's default
//! transfer function is agreed over all ranks' ranges ([`scene`]).

#![cfg_attr(test, allow(clippy::unwrap_used, clippy::expect_used))]

pub mod compose;
pub mod config;
pub mod faces;
pub mod http;
pub mod movie;
pub mod node;
pub mod scene;
pub mod score;
pub mod service;
pub mod tfs;
pub mod view;

pub use config::Config;
pub use node::{start, RunningViz, StartError};
