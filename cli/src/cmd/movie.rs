//! `insitu export --movie FILE.mp4`: a recording's steps (composed over their ranks) rendered
//! along an orbit and encoded by Debian's `ffmpeg` ([`insitu_viz_node::movie`]).

use super::stored::Stored;
use anyhow::{Context, Result};
use insitu_core::vdi::Vdi;
use insitu_core::Backend;
use insitu_viz_node::view::{self, View};
use std::path::Path;

/// The camera path and the frames.
pub struct Orbit {
    /// Degrees the camera orbits about +y from one frame to the next.
    pub orbit_deg: f32,
    /// Elevation, degrees in [−89, 89].
    pub elevation: f32,
    /// Frames per step (the camera keeps moving while a step is shown).
    pub frames_per_step: u32,
    /// Frames per second.
    pub fps: u32,
    /// Frame width, pixels (even).
    pub width: u32,
    /// Frame height, pixels (even).
    pub height: u32,
}

/// Encodes the movie of `stored` into `out`; returns the frames written.
///
/// # Errors
/// As [`insitu_viz_node::movie::encode`], and when a step's VDI cannot be read.
pub fn write(stored: &Stored, out: &Path, orbit: &Orbit, backend: &Backend) -> Result<u32> {
    let per = orbit.frames_per_step.max(1);
    let frames = u32::try_from(stored.steps.len())
        .ok()
        .and_then(|n| n.checked_mul(per))
        .context("too many frames")?;
    // The step being shown, loaded once for its frames.
    let mut shown: Option<(usize, Vdi)> = None;
    insitu_viz_node::movie::encode(out, (orbit.width, orbit.height), orbit.fps, frames, |k| {
        let i = (k / per) as usize;
        if shown.as_ref().is_none_or(|(j, _)| *j != i) {
            let vdi = stored.vdi(&stored.steps[i]).map_err(|e| format!("{e:#}"))?;
            shown = Some((i, vdi));
        }
        let Some((_, vdi)) = &shown else {
            return Err("no step".into());
        };
        let v = View {
            angle_deg: orbit.orbit_deg * k as f32,
            elevation_deg: orbit.elevation,
            zoom: 1.0,
            width: orbit.width,
            height: orbit.height,
        };
        view::render(backend, vdi, &v, vdi.meta().termination)
            .map(|(image, _)| image)
            .map_err(|e| format!("step {}: {e}", stored.steps[i].step))
    })?;
    Ok(frames)
}
