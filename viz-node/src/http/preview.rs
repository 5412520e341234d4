//! `POST /api/preview` (docs/steering.md): a transfer function seen before it is applied. The
//! viewer holds VDIs and reference frames, whose colours are baked in, not the field; the
//! preview is therefore a reference DVR of the newest step the generator-nodes still hold,
//! rendered there with the new transfer function (each rank by the node that holds it) and
//! composed by the tuner (`Tuner.Preview`). Answered as a PNG; nothing is steered.
//!
//! Body: `{"tf": {…}, "camera": {…}, "step": s, "size": n}`: the transfer function (required),
//! the view as `POST /api/steer` takes it (optional: the held step's generation camera), the
//! held step (optional: the newest held whole) and the side in pixels (16..=512, default 256).
//! Headers of the answer: `x-insitu-step` (the step rendered), `x-insitu-ranks`,
//! `x-insitu-render-secs` (the slowest node), `x-insitu-secs` (at the tuner). Behind the
//! steering token, as steering is: it spends the nodes' time.

use super::steer::{steering_peer, tuner_client, tuner_refused, wire_tf, CameraBody};
use super::{error, Http};
use axum::extract::State;
use axum::http::{header, HeaderMap, StatusCode};
use axum::response::{IntoResponse, Response};
use insitu_core::TransferFunction;
use insitu_proto::pb;
use serde::Deserialize;
use std::sync::Arc;
use std::time::Duration;

/// How long a preview waits for the tuner (which gives the nodes 30 s).
const PREVIEW_WAIT: Duration = Duration::from_secs(35);

/// A preview request's body.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PreviewBody {
    /// Transfer function (docs/conventions.md format), as a JSON object, checked where it is
    /// read.
    tf: TransferFunction,
    /// The view.
    camera: Option<CameraBody>,
    /// The held step to render.
    step: Option<u64>,
    /// Side, pixels.
    size: Option<u32>,
}

/// `POST /api/preview`.
pub async fn preview(State(http): State<Arc<Http>>, headers: HeaderMap, body: String) -> Response {
    let peer = match steering_peer(&http, &headers) {
        Ok(p) => p,
        Err((status, why)) => return error(status, why),
    };
    let b: PreviewBody = match serde_json::from_str(&body) {
        Ok(b) => b,
        Err(e) => {
            return error(
                StatusCode::BAD_REQUEST,
                format!("malformed preview request: {e}"),
            )
        }
    };
    let camera = match b.camera {
        None => None,
        Some(c) => match c.camera(&http).await {
            Ok(c) => Some(pb::Camera::from(&c)),
            Err(e) => return error(StatusCode::BAD_REQUEST, e),
        },
    };
    let tf = match wire_tf(&b.tf) {
        Ok(tf) => tf,
        Err(e) => return error(StatusCode::BAD_REQUEST, e),
    };
    let request = pb::PreviewRequest {
        step: b.step,
        tf: Some(tf),
        camera,
        size: b.size.unwrap_or(0),
        ..Default::default()
    };
    let call = async {
        tuner_client(&peer)
            .await
            .map_err(tonic::Status::unavailable)?
            .preview(request)
            .await
            .map(tonic::Response::into_inner)
    };
    let r = match tokio::time::timeout(PREVIEW_WAIT, call).await {
        Ok(Ok(r)) => r,
        Ok(Err(s)) => return tuner_refused(&s),
        Err(_) => {
            return error(
                StatusCode::GATEWAY_TIMEOUT,
                "the tuner-node did not answer the preview".into(),
            )
        }
    };
    let png = image::RgbImage::from_raw(r.size, r.size, r.rgb.to_vec()).and_then(|rgb| {
        let mut out = std::io::Cursor::new(Vec::new());
        rgb.write_to(&mut out, image::ImageFormat::Png).ok()?;
        Some(out.into_inner())
    });
    let Some(png) = png else {
        return error(
            StatusCode::BAD_GATEWAY,
            format!(
                "the tuner's preview is not {0}×{0} RGB, or did not encode",
                r.size
            ),
        );
    };
    (
        [
            (header::CONTENT_TYPE, "image/png".to_owned()),
            (header::CACHE_CONTROL, "no-store".to_owned()),
            (
                header::HeaderName::from_static("x-insitu-step"),
                r.step.to_string(),
            ),
            (
                header::HeaderName::from_static("x-insitu-ranks"),
                r.ranks.to_string(),
            ),
            (
                header::HeaderName::from_static("x-insitu-render-secs"),
                format!("{:.4}", r.render_secs),
            ),
            (
                header::HeaderName::from_static("x-insitu-secs"),
                format!("{:.4}", r.secs),
            ),
        ],
        png,
    )
        .into_response()
}
