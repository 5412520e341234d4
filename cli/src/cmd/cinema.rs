//! `insitu export --cinema DIR.cdb`: a Cinema database (Spec D, the image database Ascent and
//! ParaView Catalyst write) of a recording. Every step (composed over its ranks) rendered from
//! its VDI at a grid of camera angles, with one line per image in `data.csv`:
//! `time,phi,theta` (Ascent's columns: simulation time, the orbit angle about +y and the
//! elevation, degrees), then the step's tuned parameters and metrics
//! (`step,pm_version,r,gamma,sigma_bytes,tau_s,q_db`, `NaN` where a step was not scored), and
//! `FILE` last, as the specification requires (a path relative to the database). The database
//! is written beside its final name and renamed into place: nothing half-written is left under
//! it, and an existing one is never overwritten.

use super::stored::Stored;
use crate::output::write_png;
use anyhow::{bail, Context, Result};
use insitu_core::Backend;
use insitu_viz_node::view::{self, View};
use std::fmt::Write as _;
use std::path::Path;

/// The camera grid and the images' size.
pub struct Grid {
    /// Orbit angles about +y, degrees.
    pub phi: Vec<f32>,
    /// Elevations, degrees in [−89, 89].
    pub theta: Vec<f32>,
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
}

/// The name of the image of `step` at (`phi`, `theta`), relative to the database.
fn image_name(step: u64, phi: f32, theta: f32) -> String {
    format!("image/step_{step:08}/phi_{phi}_theta_{theta}.png")
}

/// Writes the database of `stored` at `out`; returns the images written.
///
/// # Errors
/// When `out` exists, a view is out of range, a step's VDI cannot be read or rendered, or a
/// file cannot be written (then nothing is left under `out`).
pub fn write(stored: &Stored, out: &Path, grid: &Grid, backend: &Backend) -> Result<usize> {
    if out.exists() {
        bail!(
            "{} exists: remove it or name another database",
            out.display()
        );
    }
    let name = out
        .file_name()
        .with_context(|| format!("{} names no directory", out.display()))?;
    let tmp = out.with_file_name(format!(
        ".{}.partial-{}",
        name.to_string_lossy(),
        std::process::id()
    ));
    let result = fill(stored, &tmp, grid, backend);
    match result {
        Ok(n) => {
            std::fs::rename(&tmp, out)
                .with_context(|| format!("renaming {} to {}", tmp.display(), out.display()))?;
            Ok(n)
        }
        Err(e) => {
            let _ = std::fs::remove_dir_all(&tmp);
            Err(e)
        }
    }
}

fn fill(stored: &Stored, dir: &Path, grid: &Grid, backend: &Backend) -> Result<usize> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let mut csv =
        String::from("time,phi,theta,step,pm_version,r,gamma,sigma_bytes,tau_s,q_db,FILE\n");
    let mut images = 0;
    for s in &stored.steps {
        let vdi = stored.vdi(s)?;
        let termination = vdi.meta().termination;
        for &phi in &grid.phi {
            for &theta in &grid.theta {
                let v = View {
                    angle_deg: phi,
                    elevation_deg: theta,
                    zoom: 1.0,
                    width: grid.width,
                    height: grid.height,
                };
                let (image, _) = view::render(backend, &vdi, &v, termination, None)
                    .with_context(|| format!("step {} at phi {phi}, theta {theta}", s.step))?;
                let file = image_name(s.step, phi, theta);
                let path = dir.join(&file);
                if let Some(parent) = path.parent() {
                    std::fs::create_dir_all(parent)
                        .with_context(|| format!("creating {}", parent.display()))?;
                }
                write_png(&path, &image)?;
                let q = s.q_db.map_or_else(|| "NaN".to_owned(), |q| q.to_string());
                writeln!(
                    csv,
                    "{},{phi},{theta},{},{},{},{},{},{},{q},{file}",
                    s.sim_time, s.step, s.pm_version, s.r, s.gamma, s.sigma_bytes, s.tau_s
                )?;
                images += 1;
            }
        }
    }
    crate::output::write_atomic(&dir.join("data.csv"), csv.as_bytes())?;
    Ok(images)
}
