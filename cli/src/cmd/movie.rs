//! `insitu export --movie FILE.mp4`: a recording's steps (composed over their ranks) rendered
//! along an orbit and encoded by Debian's `ffmpeg` ([`insitu_viz_node::movie`]).

use super::stored::Stored;
use anyhow::Result;
use insitu_core::Backend;
use insitu_viz_node::movie::{encode_orbit, Orbit};
use std::path::Path;

/// Encodes the movie of `stored` into `out` along `orbit`; returns the frames written.
///
/// # Errors
/// As [`encode_orbit`], and when a step's VDI cannot be read.
pub fn write(stored: &Stored, out: &Path, orbit: &Orbit, backend: &Backend) -> Result<u32> {
    let load = |i: usize| {
        let s = &stored.steps[i];
        stored.vdi(s).map_err(|e| format!("step {}: {e:#}", s.step))
    };
    Ok(encode_orbit(
        out,
        orbit,
        stored.steps.len(),
        backend,
        |i| load(i).map(Box::new),
        |v| v.meta().termination,
        None,
    )?)
}
