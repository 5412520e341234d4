//! Movies of stored steps: frames piped as raw RGB to Debian's `ffmpeg` (H.264, yuv420p, no
//! temporary images), written beside their final name and renamed into place when `ffmpeg`
//! has finished, so a failed encode leaves nothing under it. Used by `insitu export --movie`
//! and the viewer's `/api/movie`.

use crate::view::{self, View};
use insitu_core::cancel::Cancel;
use insitu_core::{Backend, Image, Vdi};
use std::io::Write;
use std::ops::Deref;
use std::path::Path;
use std::process::{Command, Stdio};

/// Most frames one movie may have.
pub const MAX_FRAMES: u32 = 10_000;

/// Why a movie was not made.
#[derive(Debug, thiserror::Error)]
pub enum MovieError {
    /// `ffmpeg` is not on `PATH`.
    #[error("ffmpeg is not installed: movies are encoded by it (Debian: apt-get install ffmpeg)")]
    NoFfmpeg,
    /// The size, rate or frame count cannot be encoded.
    #[error("{0}")]
    BadRequest(String),
    /// A frame could not be rendered.
    #[error("frame {frame}: {problem}")]
    Frame {
        /// Its index.
        frame: u32,
        /// Why.
        problem: String,
    },
    /// `ffmpeg` failed, or its output could not be kept.
    #[error("ffmpeg: {0}")]
    Ffmpeg(String),
    /// Another movie or large still holds the lane: try again shortly.
    #[error("{0}")]
    Busy(String),
    /// Its client went away ([`Cancel`]); `ffmpeg` was stopped and nothing kept.
    #[error("the movie was cancelled (its client went away)")]
    Cancelled,
}

/// A movie's camera path: `start` (its elevation, zoom and frame size) orbited by
/// `orbit_deg` about +y each frame, each step shown for `frames_per_step` frames.
#[derive(Clone, Copy, Debug)]
pub struct Orbit {
    /// The first frame's view.
    pub start: View,
    /// Degrees about +y from one frame to the next.
    pub orbit_deg: f32,
    /// Frames per step (the camera keeps moving while a step is shown).
    pub frames_per_step: u32,
    /// Frames per second.
    pub fps: u32,
}

/// Encodes `steps` steps along `orbit` into `out`: step `i`'s VDI from `load(i)` (loaded once
/// for its frames), rendered on `backend` with the early termination `termination` gives for
/// it; `cancel`, once set, stops the frame being rendered and the movie. Returns the frames
/// written.
///
/// # Errors
/// As [`encode`]; a step that cannot be loaded or rendered is a [`MovieError::Frame`];
/// [`MovieError::Cancelled`] when `cancel` was set.
pub fn encode_orbit<V: Deref<Target = Vdi>>(
    out: &Path,
    orbit: &Orbit,
    steps: usize,
    backend: &Backend,
    mut load: impl FnMut(usize) -> Result<V, String>,
    termination: impl Fn(&Vdi) -> f32,
    cancel: Option<&Cancel>,
) -> Result<u32, MovieError> {
    let per = orbit.frames_per_step.max(1);
    let frames = u32::try_from(steps)
        .ok()
        .and_then(|n| n.checked_mul(per))
        .ok_or_else(|| MovieError::BadRequest(format!("{steps} steps × {per} frames")))?;
    let size = (orbit.start.width, orbit.start.height);
    let mut shown: Option<(usize, V)> = None;
    let made = encode(out, size, orbit.fps, frames, |k| {
        let i = (k / per) as usize;
        if shown.as_ref().is_none_or(|(j, _)| *j != i) {
            shown = Some((i, load(i)?));
        }
        let Some((_, vdi)) = &shown else {
            return Err("no step".into());
        };
        let v = View {
            angle_deg: orbit.start.angle_deg + orbit.orbit_deg * k as f32,
            ..orbit.start
        };
        view::render(backend, vdi, &v, termination(vdi), cancel)
            .map(|(image, _)| image)
            .map_err(|e| e.to_string())
    });
    match made {
        Err(_) if cancel.is_some_and(Cancel::is_cancelled) => Err(MovieError::Cancelled),
        other => other.map(|()| frames),
    }
}

/// Encodes `frames` frames of `width × height` at `fps` into `out`, frame `k` rendered by
/// `frame(k)`.
///
/// # Errors
/// [`MovieError::BadRequest`] for an odd side (yuv420p halves the chroma), a rate outside
/// 1..=240 or no frames; [`MovieError::NoFfmpeg`]; [`MovieError::Frame`] when `frame` fails
/// or gives another size; [`MovieError::Ffmpeg`] with `ffmpeg`'s own message.
pub fn encode(
    out: &Path,
    (width, height): (u32, u32),
    fps: u32,
    frames: u32,
    mut frame: impl FnMut(u32) -> Result<Image, String>,
) -> Result<(), MovieError> {
    if width % 2 == 1 || height % 2 == 1 || width == 0 || height == 0 {
        return Err(MovieError::BadRequest(format!(
            "a movie of {width}x{height}: its sides must be even and non-zero (H.264 in yuv420p)"
        )));
    }
    if !(1..=240).contains(&fps) || !(1..=MAX_FRAMES).contains(&frames) {
        return Err(MovieError::BadRequest(format!(
            "{frames} frames at {fps} fps: the rate must be 1..=240 and the frames 1..={MAX_FRAMES}"
        )));
    }
    let name = out
        .file_name()
        .ok_or_else(|| MovieError::BadRequest(format!("{} names no file", out.display())))?;
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
        .args(["-s", &format!("{width}x{height}")])
        .args(["-r", &fps.to_string(), "-i", "-"])
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
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Err(MovieError::NoFfmpeg),
        Err(e) => return Err(MovieError::Ffmpeg(format!("starting it: {e}"))),
    };
    let fed = (|| -> Result<(), MovieError> {
        let mut stdin = child
            .stdin
            .take()
            .ok_or_else(|| MovieError::Ffmpeg("no input pipe".into()))?;
        for k in 0..frames {
            let image = frame(k).map_err(|problem| MovieError::Frame { frame: k, problem })?;
            if (image.width(), image.height()) != (width, height) {
                return Err(MovieError::Frame {
                    frame: k,
                    problem: format!("{}x{}, not {width}x{height}", image.width(), image.height()),
                });
            }
            stdin
                .write_all(&image.to_rgb8())
                .map_err(|e| MovieError::Ffmpeg(format!("it stopped taking frames: {e}")))?;
        }
        Ok(())
    })();
    if fed.is_err() {
        // Not waited for to finish encoding what it has: that is thrown away.
        let _ = child.kill();
    }
    let output = child
        .wait_with_output()
        .map_err(|e| MovieError::Ffmpeg(format!("waiting for it: {e}")));
    let done = match (fed, output) {
        (Ok(()), Ok(o)) if o.status.success() => std::fs::rename(&tmp, out)
            .map_err(|e| MovieError::Ffmpeg(format!("keeping {}: {e}", out.display()))),
        (Ok(()), Ok(o)) => Err(MovieError::Ffmpeg(format!(
            "{}: {}",
            o.status,
            String::from_utf8_lossy(&o.stderr).trim()
        ))),
        (Err(e), _) | (Ok(()), Err(e)) => Err(e),
    };
    if done.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    done
}
