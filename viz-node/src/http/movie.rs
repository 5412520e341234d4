//! `GET /api/movie?from=&to=&orbit=&elevation=&frames_per_step=&fps=&size=`: the stored steps
//! from `from` to `to` (default: all), each composed over its ranks, rendered along an orbit
//! and encoded by `ffmpeg` ([`crate::movie`]) as an MP4 download — what the page offers for
//! the steps it shows, and `insitu export --movie` makes from a recording. One movie at a time
//! (it takes the large stills' lane), at most [`MAX_PIXELS`] a frame and [`MAX_FRAMES`] frames.

use super::Http;
use crate::movie::MovieError;
use crate::view::{self, View, ViewError};
use axum::extract::rejection::QueryRejection;
use axum::extract::{Query, State};
use axum::http::header;
use axum::response::{IntoResponse, Response};
use insitu_core::cancel::Cancel;
use serde::Deserialize;
use std::sync::Arc;

/// Largest frame of a movie, pixels.
pub const MAX_PIXELS: u64 = 1024 * 1024;
/// Most frames of a movie asked over HTTP.
pub const MAX_FRAMES: u32 = 2000;

/// The query.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MovieQuery {
    from: Option<u64>,
    to: Option<u64>,
    /// Degrees about +y per frame (default 3).
    #[serde(default, deserialize_with = "super::numbers::narrow_opt")]
    orbit: Option<f32>,
    /// Degrees up (default 15).
    #[serde(default, deserialize_with = "super::numbers::narrow_opt")]
    elevation: Option<f32>,
    /// Frames per step (default 4).
    frames_per_step: Option<u32>,
    /// Frames per second (default 24).
    fps: Option<u32>,
    /// `N` or `WxH` (default 512), even sides.
    size: Option<String>,
    #[allow(dead_code)] // read by the token check
    token: Option<String>,
}

/// The movie, or an error: 400 for a bad query, 404 for no step in the range, 503 while
/// another movie or large still renders, 501 without `ffmpeg`.
pub async fn movie(
    State(http): State<Arc<Http>>,
    q: Result<Query<MovieQuery>, QueryRejection>,
) -> Response {
    match make(&http, q).await {
        Ok((bytes, name)) => (
            [
                (header::CONTENT_TYPE, "video/mp4".to_owned()),
                (
                    header::CONTENT_DISPOSITION,
                    format!("attachment; filename=\"{name}\""),
                ),
            ],
            bytes,
        )
            .into_response(),
        Err(MovieError::NoFfmpeg) => super::error(
            axum::http::StatusCode::NOT_IMPLEMENTED,
            MovieError::NoFfmpeg.to_string(),
        ),
        Err(MovieError::BadRequest(m)) => ViewError::BadRequest(m).into_response(),
        Err(MovieError::Busy(m)) => ViewError::Busy(m).into_response(),
        Err(e) => ViewError::Failed(e.to_string()).into_response(),
    }
}

async fn make(
    http: &Arc<Http>,
    q: Result<Query<MovieQuery>, QueryRejection>,
) -> Result<(Vec<u8>, String), MovieError> {
    let bad = |m: String| MovieError::BadRequest(m);
    let Query(q) = q.map_err(|e| bad(e.body_text()))?;
    let (width, height) = super::api::parse_size(q.size.as_deref().unwrap_or("512"))
        .map_err(|e| bad(e.to_string()))?;
    if u64::from(width) * u64::from(height) > MAX_PIXELS {
        return Err(bad(format!(
            "a movie of {width}x{height}: at most {MAX_PIXELS} pixels a frame"
        )));
    }
    let rec = &http.shared.recording;
    let (from, to) = (q.from.unwrap_or(0), q.to.unwrap_or(u64::MAX));
    let mut steps: Vec<u64> = rec.entries().iter().map(|e| e.step).collect();
    steps.retain(|s| (from..=to).contains(s));
    steps.dedup();
    let (mut files, mut shown_steps) = (Vec::new(), Vec::new());
    for s in steps {
        // Steps not composed yet are left out, as the page's time slider leaves them.
        if let Ok(f) = view::vdi_file(s, None, &rec.ranks_of(s), rec.step(s).as_ref()) {
            files.push(f);
            shown_steps.push(s);
        }
    }
    let name = match (shown_steps.first(), shown_steps.last()) {
        (Some(a), Some(b)) => format!("steps-{a}-{b}.mp4"),
        _ => "steps.mp4".to_owned(),
    };
    let per = q.frames_per_step.unwrap_or(4).max(1);
    // Refused before it takes the lane: the HTTP bound on frames.
    u32::try_from(files.len())
        .ok()
        .and_then(|n| n.checked_mul(per))
        .filter(|&n| (1..=MAX_FRAMES).contains(&n))
        .ok_or_else(|| {
            bad(format!(
                "{} steps × {per} frames: a movie has 1 to {MAX_FRAMES} frames (no step in {from}..={to}?)",
                files.len()
            ))
        })?;
    let orbit = q.orbit.unwrap_or(3.0);
    let elevation = q.elevation.unwrap_or(15.0);
    let fps = q.fps.unwrap_or(24);
    let first = View {
        elevation_deg: elevation,
        width,
        height,
        ..View::default()
    };
    first.check(MAX_PIXELS).map_err(|e| bad(e.to_string()))?;
    let lane = http.large.enter().await.map_err(|b| {
        MovieError::Busy(format!(
            "{} large renders already wait; try again shortly",
            b.waiting
        ))
    })?;
    // Dropped with this request (its client hung up): the frame being rendered stops at its
    // next tile, ffmpeg is stopped, and the lane is free for the next.
    let cancel = Cancel::new();
    let _stop = cancel.on_drop();
    let h = http.clone();
    tokio::task::spawn_blocking(move || {
        let _lane = lane;
        let dir = tempfile_dir()?;
        let out = dir.join("movie.mp4");
        let orbit = crate::movie::Orbit {
            start: first,
            orbit_deg: orbit,
            frames_per_step: per,
            fps,
        };
        let running = super::Running::start(&h);
        let made = h.pools.install(true, || {
            crate::movie::encode_orbit(
                &out,
                &orbit,
                files.len(),
                &h.shared.backend,
                |i| h.vdi(&files[i]).map_err(|e| e.to_string()),
                |_| h.shared.termination,
                Some(&cancel),
            )
        });
        let made = running.end(made, |e| matches!(e, MovieError::Cancelled));
        let bytes = made.and_then(|_| {
            std::fs::read(&out).map_err(|e| MovieError::Ffmpeg(format!("reading the movie: {e}")))
        });
        let _ = std::fs::remove_dir_all(&dir);
        bytes.map(|b| (b, name))
    })
    .await
    .map_err(|e| MovieError::Ffmpeg(format!("movie task: {e}")))?
}

/// A fresh directory for one movie under the system's temporary directory.
fn tempfile_dir() -> Result<std::path::PathBuf, MovieError> {
    static NEXT: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
    let k = NEXT.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let dir = std::env::temp_dir().join(format!("insitu-movie-{}-{k}", std::process::id()));
    std::fs::create_dir_all(&dir)
        .map_err(|e| MovieError::Ffmpeg(format!("creating {}: {e}", dir.display())))?;
    Ok(dir)
}
