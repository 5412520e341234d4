//! Integration tests of insitu-core, built as one binary.

mod analytic;
mod codec_props;
mod common;
mod hard_cases;
mod real_data;
