//! `insitu export --movie FILE.mp4`: a recording's steps (composed over their ranks) rendered
//! along an orbit and encoded by Debian's `ffmpeg` (H.264, yuv420p), the frames piped to it as
//! raw RGB (no temporary images). The file is written beside its final name and renamed into
//! place once `ffmpeg` has finished: a failed encode leaves nothing under it.

use super::stored::Stored;
use anyhow::{bail, Context, Result};
use insitu_core::Backend;
use insitu_viz_node::view::{self, View};
use std::io::Write;
use std::path::Path;
use std::process::{Command, Stdio};

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
    /// Frame width, pixels (even: yuv420p halves the chroma).
    pub width: u32,
    /// Frame height, pixels (even).
    pub height: u32,
}

/// Encodes the movie of `stored` into `out`; returns the frames written.
///
/// # Errors
/// When `ffmpeg` is not installed (saying how to get it), a side is odd, a step cannot be
/// rendered, or `ffmpeg` fails (its own message included).
pub fn write(stored: &Stored, out: &Path, path: &Orbit, backend: &Backend) -> Result<u32> {
    if path.width % 2 == 1 || path.height % 2 == 1 {
        bail!(
            "--size {}x{}: a movie's sides must be even (H.264 in yuv420p)",
            path.width,
            path.height
        );
    }
    if !(1..=240).contains(&path.fps) || path.frames_per_step == 0 {
        bail!("--fps must be 1..=240 and --frames-per-step at least 1");
    }
    let name = out
        .file_name()
        .with_context(|| format!("{} names no file", out.display()))?;
    let tmp = out.with_file_name(format!(
        ".{}.partial-{}.mp4",
        name.to_string_lossy(),
        std::process::id()
    ));
    let spawned = Command::new("ffmpeg")
        .args([
            "-y",
            "-loglevel",
            "error",
            "-f",
            "rawvideo",
            "-pix_fmt",
            "rgb24",
        ])
        .args(["-s", &format!("{}x{}", path.width, path.height)])
        .args(["-r", &path.fps.to_string(), "-i", "-"])
        .args([
            "-c:v",
            "libx264",
            "-pix_fmt",
            "yuv420p",
            "-movflags",
            "+faststart",
        ])
        .arg(&tmp)
        .stdin(Stdio::piped())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn();
    let mut child = match spawned {
        Ok(c) => c,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => bail!(
            "ffmpeg is not installed: --movie pipes the frames to it (Debian: apt-get install ffmpeg)"
        ),
        Err(e) => return Err(e).context("starting ffmpeg"),
    };
    let encoded = (|| -> Result<u32> {
        let mut stdin = child.stdin.take().context("ffmpeg's input")?;
        let mut frame = 0u32;
        for s in &stored.steps {
            let vdi = stored.vdi(s)?;
            let termination = vdi.meta().termination;
            for _ in 0..path.frames_per_step {
                let v = View {
                    angle_deg: path.orbit_deg * frame as f32,
                    elevation_deg: path.elevation,
                    zoom: 1.0,
                    width: path.width,
                    height: path.height,
                };
                let (image, _) = view::render(backend, &vdi, &v, termination)
                    .with_context(|| format!("step {} frame {frame}", s.step))?;
                stdin
                    .write_all(&image.to_rgb8())
                    .context("ffmpeg stopped taking frames")?;
                frame += 1;
            }
        }
        Ok(frame)
    })();
    let output = child.wait_with_output().context("waiting for ffmpeg")?;
    let frames = match encoded {
        Ok(n) if output.status.success() => n,
        Ok(_) => {
            let _ = std::fs::remove_file(&tmp);
            bail!(
                "ffmpeg failed ({}): {}",
                output.status,
                String::from_utf8_lossy(&output.stderr).trim()
            );
        }
        Err(e) => {
            let _ = std::fs::remove_file(&tmp);
            return Err(e);
        }
    };
    std::fs::rename(&tmp, out)
        .with_context(|| format!("renaming {} to {}", tmp.display(), out.display()))?;
    Ok(frames)
}
