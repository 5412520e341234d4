//! The JSON API (docs/viewer.md): what is stored, the series over time, and still
//! frames of any stored step from any camera. Errors are `{"error": message}` with 400
//! (bad parameter), 401 (token), 404 (no such step, rank or view), 413 (image too large) or
//! 500 (a stored file cannot be read).

use super::Http;
use crate::view::{self, Format, View, ViewError};
use axum::extract::rejection::QueryRejection;
use axum::extract::{Query, State};
use axum::http::{header, HeaderName};
use axum::response::{IntoResponse, Response};
use axum::Json;
use insitu_core::adherence::Adherence;
use insitu_core::cancel::Cancel;
use insitu_core::evaluate::Sizing;
use insitu_core::json::f32_number;
use insitu_recording::store::{Entry, Quality, StepEntry};
use serde::Deserialize;
use serde_json::{json, Value};
use std::collections::BTreeMap;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Instant;

/// One stored step as the API shows it: its ranks (`ranks_held` counts those a host's part
/// covers; `complete` when they are the whole world and composed without `error`) and, for a
/// world of ranks, the composed step (σ summed, τ of the slowest rank, q of the composition).
pub fn step_json(step: u64, ranks: &[Entry], composed: Option<&StepEntry>) -> Value {
    let world = view::world_size(ranks);
    let quality = |q: &Option<Quality>| {
        q.as_ref()
            .map(|q| json!({"q_db": q.q_db, "view_q_db": q.view_q_db, "ssim": q.ssim}))
    };
    let rank_json: Vec<Value> = ranks
        .iter()
        .map(|e| {
            json!({
                "rank": e.rank,
                "r": e.resolution,
                "gamma": f32_number(e.gamma),
                "precision": e.precision.name(),
                "pm_version": e.pm_version,
                "sigma_bytes": e.sizing.sigma_bytes,
                "tau_s": e.sizing.tau_secs,
                "supersegments": e.sizing.supersegments,
                "sampled": e.with_references || e.references.is_some(),
                "quality": quality(&e.quality),
            })
        })
        .collect();
    let first = ranks.first();
    let (sizing, q) = match (composed, world) {
        (Some(c), w) if w > 1 => (c.sizing, quality(&c.quality)),
        _ => (
            Sizing::of_ranks(ranks.iter().map(|e| &e.sizing)),
            first.and_then(|e| quality(&e.quality)),
        ),
    };
    // The ranks stored: a host's part holds every rank it covers.
    let held: std::collections::BTreeSet<u32> = ranks.iter().flat_map(Entry::ranks).collect();
    // A step whose ranks could not be composed (bricks that overlap or leave a gap) failed,
    // however many ranks it holds.
    let error = composed.and_then(|c| c.error.clone());
    let complete = held.len() as u32 >= world && error.is_none();
    json!({
        "step": step,
        "sim_time": first.map(|e| e.sim_time),
        "world_size": world,
        "ranks": rank_json,
        "ranks_held": held.len(),
        "complete": complete,
        "partial": composed.is_some_and(|c| !c.missing.is_empty()),
        "error": error,
        "composed": composed.is_some_and(|c| c.vdi.is_some()),
        "r": first.map(|e| e.resolution),
        "gamma": first.map(|e| f32_number(e.gamma)),
        "precision": first.map(|e| e.precision.name()),
        "pm_version": first.map(|e| e.pm_version),
        "sigma_bytes": sizing.sigma_bytes,
        "tau_s": sizing.tau_secs,
        "quality": q,
        "sampled": ranks.iter().any(|e| e.with_references || e.references.is_some()),
    })
}

/// Every stored step, oldest first, grouped with its composition.
fn all_steps(http: &Http) -> Vec<Value> {
    let mut by_step: BTreeMap<u64, Vec<Entry>> = BTreeMap::new();
    for e in http.shared.recording.entries() {
        by_step.entry(e.step).or_default().push(e);
    }
    let composed: BTreeMap<u64, StepEntry> = http
        .shared
        .recording
        .steps()
        .into_iter()
        .map(|s| (s.step, s))
        .collect();
    by_step
        .iter()
        .map(|(&step, ranks)| step_json(step, ranks, composed.get(&step)))
        .collect()
}

/// `GET /api/steps`: `{"steps": [...], "latest": step or null}`.
pub async fn steps(State(http): State<Arc<Http>>) -> Json<Value> {
    let steps = all_steps(&http);
    let latest = steps.last().map(|s| s["step"].clone());
    Json(json!({ "steps": steps, "latest": latest }))
}

/// `GET /api/series`: per stored step σ, τ, q (null when not sampled) and the P_M version,
/// the steps where the P_M version changed, the tuner's budget, and the adherence of the steps
/// made with a tuned P_M to it (`insitu_core::adherence`: steps, within, share, worst_ratio,
/// mean_ratio, pm_changes, pm_changes_per_100; null without that budget).
pub async fn series(State(http): State<Arc<Http>>) -> Json<Value> {
    let steps = all_steps(&http);
    let col = |k: &str| -> Vec<Value> { steps.iter().map(|s| s[k].clone()).collect() };
    let q: Vec<Value> = steps.iter().map(|s| s["quality"]["q_db"].clone()).collect();
    let mut changes = Vec::new();
    let mut last: Option<&Value> = None;
    for s in &steps {
        let v = &s["pm_version"];
        if last.is_some_and(|l| l != v) {
            changes.push(
                json!({"step": s["step"], "pm_version": v, "r": s["r"], "gamma": s["gamma"]}),
            );
        }
        last = Some(v);
    }
    let budget = http.budget().await;
    // Adherence of the steps made with a tuned P_M to each budget the tuner has.
    let adherence = |key: &str| {
        let b = budget[key].as_f64().filter(|&b| b > 0.0)?;
        let values = steps.iter().map(|s| {
            let v = s[key].as_f64().unwrap_or(f64::NAN);
            let pm = (
                s["r"].as_u64().unwrap_or(0) as u32,
                s["gamma"].as_f64().unwrap_or(0.0) as f32,
            );
            (s["pm_version"].as_u64().unwrap_or(0), pm, v)
        });
        Some(Adherence::of(values, b).json())
    };
    Json(json!({
        "step": col("step"),
        "sigma_bytes": col("sigma_bytes"),
        "tau_s": col("tau_s"),
        "q_db": q,
        "pm_version": col("pm_version"),
        "pm_changes": changes,
        "adherence": {"sigma": adherence("sigma_bytes"), "tau": adherence("tau_s")},
        "budget": budget,
    }))
}

/// The query of a still frame.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RenderQuery {
    step: Option<u64>,
    rank: Option<u32>,
    #[serde(default, deserialize_with = "super::numbers::angle")]
    angle: f32,
    #[serde(default, deserialize_with = "super::numbers::narrow")]
    elevation: f32,
    #[serde(default, deserialize_with = "super::numbers::narrow_opt")]
    zoom: Option<f32>,
    /// `N` or `WxH`.
    size: Option<String>,
    format: Option<Format>,
    quality: Option<u8>,
    /// From the VDI's level matching the size (default false: the full VDI).
    #[serde(default)]
    lod: bool,
    #[allow(dead_code)] // read by the token check
    token: Option<String>,
}

/// Parses `N` or `WxH`.
pub(super) fn parse_size(s: &str) -> Result<(u32, u32), ViewError> {
    let bad = || ViewError::BadRequest(format!("size {s:?} must be N or WxH pixels"));
    let (w, h) = s.split_once('x').unwrap_or((s, s));
    Ok((w.parse().map_err(|_| bad())?, h.parse().map_err(|_| bad())?))
}

/// A rendered and encoded frame.
pub struct Frame {
    /// The step shown (the latest when none was asked for).
    pub step: u64,
    /// The encoded image.
    pub bytes: Vec<u8>,
    /// Seconds to render it.
    pub render_secs: f64,
    /// Seconds to encode it.
    pub encode_secs: f64,
    /// Resolution of the VDI level it was rendered from.
    pub vdi_resolution: u32,
    /// The camera it was rendered from.
    pub camera: insitu_core::Camera,
    /// The zoom that frames the volume from this direction ([`View::fit_zoom`]).
    pub fit_zoom: f32,
    /// The volume's world box (the page draws it).
    pub volume_box: insitu_core::volume::Aabb,
    /// The transfer function's name and identity hash.
    pub tf: (String, u64),
}

/// Renders `step` (none: the latest stored; `rank`, or composed) at `view` and encodes it as
/// `format`, counted; both on the blocking pool under the HTTP render semaphore, the render
/// on its lane's threads ([`super::pools`]), cancelled if this future is dropped.
///
/// # Errors
/// [`ViewError`] for a bad view, a missing step, or a failed render or encoding.
pub async fn render_frame(
    http: &Arc<Http>,
    step: Option<u64>,
    rank: Option<u32>,
    v: View,
    format: Format,
    quality: u8,
    lod: bool,
) -> Result<Frame, ViewError> {
    v.check(http.shared.max_render_pixels)?;
    let rec = &http.shared.recording;
    let step = step
        .or_else(|| rec.latest_step())
        .ok_or_else(|| ViewError::NotFound("the recording holds no step yet".into()))?;
    let file = view::vdi_file(step, rank, &rec.ranks_of(step), rec.step(step).as_ref())?;
    let busy = |b: super::lanes::Busy, what: &str| {
        ViewError::Busy(format!(
            "{} {what} already wait to render; try again shortly",
            b.waiting
        ))
    };
    let large = u64::from(v.width) * u64::from(v.height) > super::lanes::LARGE_PIXELS;
    let lane = if large {
        Some(
            http.large
                .enter()
                .await
                .map_err(|b| busy(b, "large stills"))?,
        )
    } else {
        None
    };
    let permit = (
        http.renders.enter().await.map_err(|b| busy(b, "frames"))?,
        lane,
    );
    // Dropped with this request (its client hung up, its socket closed): the render stops
    // at its next tile and gives its permits back.
    let cancel = Cancel::new();
    let _stop = cancel.on_drop();
    let h = http.clone();
    let frame = tokio::task::spawn_blocking(move || {
        let _permit = permit;
        let running = super::Running::start(&h);
        let vdi = h.vdi(&file)?;
        let level = view::level(&vdi, &v, lod);
        let rendered = h.pools.install(large, || {
            view::render(
                &h.shared.backend,
                level,
                &v,
                h.shared.termination,
                Some(&cancel),
            )
        });
        let (image, render_secs) = running.end(rendered, |e| matches!(e, ViewError::Cancelled))?;
        let t = Instant::now();
        let bytes = view::encode(&image, format, quality)?;
        let meta = vdi.meta();
        Ok::<_, ViewError>(Frame {
            step,
            bytes,
            render_secs,
            encode_secs: t.elapsed().as_secs_f64(),
            vdi_resolution: level.resolution(),
            camera: v.camera(&meta.camera),
            fit_zoom: v.fit_zoom(&meta.camera, &meta.volume_box),
            volume_box: meta.volume_box,
            tf: (meta.tf_name.clone(), meta.tf_hash),
        })
    })
    .await
    .map_err(|e| ViewError::Failed(format!("render task: {e}")))??;
    http.rendered.fetch_add(1, Ordering::Relaxed);
    Ok(frame)
}

/// The query string as `T`, or a bad request naming what is wrong.
pub(super) fn query<T>(q: Result<Query<T>, QueryRejection>) -> Result<T, ViewError> {
    q.map(|Query(q)| q)
        .map_err(|e| ViewError::BadRequest(e.body_text()))
}

/// `GET /api/render?step=&rank=&angle=&elevation=&zoom=&size=&format=png|jpeg&quality=`: a
/// still frame (default: the latest step, composed over its ranks, 512², PNG). The header
/// `x-render-ms` gives the render time.
pub async fn render(
    State(http): State<Arc<Http>>,
    q: Result<Query<RenderQuery>, QueryRejection>,
) -> Response {
    let q = match query(q) {
        Ok(q) => q,
        Err(bad) => return bad.into_response(),
    };
    let run = async {
        let (width, height) = parse_size(q.size.as_deref().unwrap_or("512"))?;
        let v = View {
            angle_deg: q.angle,
            elevation_deg: q.elevation,
            zoom: q.zoom.unwrap_or(1.0),
            width,
            height,
        };
        let format = q.format.unwrap_or(Format::Png);
        let frame = render_frame(
            &http,
            q.step,
            q.rank,
            v,
            format,
            q.quality.unwrap_or(90),
            q.lod,
        )
        .await?;
        Ok::<_, ViewError>((format, frame))
    };
    match run.await {
        Ok((format, f)) => (
            [
                (header::CONTENT_TYPE, format.mime().to_owned()),
                (
                    HeaderName::from_static("x-render-ms"),
                    format!("{:.1}", f.render_secs * 1e3),
                ),
                (HeaderName::from_static("x-step"), f.step.to_string()),
                (
                    HeaderName::from_static("x-vdi-resolution"),
                    f.vdi_resolution.to_string(),
                ),
            ],
            f.bytes,
        )
            .into_response(),
        Err(e) => e.into_response(),
    }
}

/// The query of a stored reference frame.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ReferenceQuery {
    step: u64,
    rank: Option<u32>,
    view: usize,
    #[allow(dead_code)] // read by the token check
    token: Option<String>,
}

/// `GET /api/reference?step=&rank=&view=K`: the stored reference frame (direct ray-casting) of
/// test view `K` as PNG (a world of ranks: the composed frames unless `rank`); the header
/// `x-angle` gives the view's orbit angle, so the VDI can be rendered beside it.
pub async fn reference(
    State(http): State<Arc<Http>>,
    q: Result<Query<ReferenceQuery>, QueryRejection>,
) -> Response {
    let q = match query(q) {
        Ok(q) => q,
        Err(bad) => return bad.into_response(),
    };
    let rec = &http.shared.recording;
    let ranks = rec.ranks_of(q.step);
    let name = match q.rank {
        None if view::world_size(&ranks) > 1 => rec.step(q.step).and_then(|s| s.references),
        r => ranks
            .iter()
            .find(|e| e.rank == r.unwrap_or(0))
            .and_then(|e| e.references.clone()),
    };
    if ranks.is_empty() && rec.step(q.step).is_none() {
        return ViewError::NotFound(format!("step {} is not in the recording", q.step))
            .into_response();
    }
    if let Some(r) = q.rank.filter(|r| !ranks.iter().any(|e| e.rank == *r)) {
        let stored: Vec<u32> = ranks.iter().map(|e| e.rank).collect();
        return ViewError::NotFound(format!(
            "step {} has no rank {r} (stored ranks: {stored:?})",
            q.step
        ))
        .into_response();
    }
    let Some(name) = name else {
        return ViewError::NotFound(format!(
            "step {} has no stored reference frames (not a sampled step)",
            q.step
        ))
        .into_response();
    };
    let path = rec.dir().join(&name);
    let out = tokio::task::spawn_blocking(move || {
        let refs = insitu_recording::store::References::read(&path)
            .map_err(|e| ViewError::Failed(e.to_string()))?;
        let frame = refs.frames.get(q.view).ok_or_else(|| {
            ViewError::NotFound(format!(
                "view {} is not among the {} test views",
                q.view,
                refs.frames.len()
            ))
        })?;
        let png = view::encode(frame, Format::Png, 0)?;
        let angle = refs
            .view_angles_deg
            .get(q.view)
            .copied()
            .unwrap_or(f32::NAN);
        Ok::<_, ViewError>((angle, png))
    })
    .await;
    match out {
        Ok(Ok((angle, png))) => (
            [
                (header::CONTENT_TYPE, "image/png".to_owned()),
                (HeaderName::from_static("x-angle"), angle.to_string()),
            ],
            png,
        )
            .into_response(),
        Ok(Err(e)) => e.into_response(),
        Err(e) => ViewError::Failed(format!("reference task: {e}")).into_response(),
    }
}

/// `GET /api/stats`: frames rendered, camera requests superseded before rendering, renders
/// running now and those cancelled by their client going away, requests refused, sockets
/// open, VDIs stored.
pub async fn stats(State(http): State<Arc<Http>>) -> Json<Value> {
    Json(super::stats(&http))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_parse_as_n_or_w_by_h() {
        assert_eq!(parse_size("256").unwrap(), (256, 256));
        assert_eq!(parse_size("320x200").unwrap(), (320, 200));
        assert!(parse_size("0x").is_err() && parse_size("-1").is_err() && parse_size("").is_err());
    }

    /// A step a host composed whole (one part covering its four ranks) is complete; two of
    /// four ranks stored apart are not.
    #[test]
    fn a_host_s_part_counts_every_rank_it_covers() {
        let part = |rank: u32, covers: &[u32]| Entry {
            world_size: 4,
            covers: covers.to_vec(),
            ..Entry::empty(3, rank)
        };
        let whole = step_json(3, &[part(0, &[0, 1, 2, 3])], None);
        assert_eq!(
            (whole["ranks_held"].as_u64(), whole["complete"].as_bool()),
            (Some(4), Some(true))
        );
        let half = step_json(3, &[part(0, &[]), part(1, &[])], None);
        assert_eq!(
            (half["ranks_held"].as_u64(), half["complete"].as_bool()),
            (Some(2), Some(false))
        );
        // Every rank held, but the bricks could not be composed: failed, and why.
        let two = |rank| Entry {
            world_size: 2,
            ..Entry::empty(3, rank)
        };
        let failed = StepEntry {
            error: Some("the bricks leave a gap at z = 32".into()),
            ..StepEntry::of_ranks(3, 2, &[&two(0), &two(1)], Vec::new())
        };
        let s = step_json(3, &[two(0), two(1)], Some(&failed));
        assert_eq!(s["complete"], false, "{s}");
        assert_eq!(s["error"], "the bricks leave a gap at z = 32", "{s}");
        assert_eq!(step_json(3, &[two(0), two(1)], None)["error"], Value::Null);
    }
}
