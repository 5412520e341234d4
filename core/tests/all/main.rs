//! Integration tests of insitu-core, built as one binary.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests fail loudly by design

mod analytic;
mod codec_props;
mod codec_quantized;
mod common;
mod compose;
#[cfg(feature = "gpu")]
mod gpu;
mod hard_cases;
mod real_data;
