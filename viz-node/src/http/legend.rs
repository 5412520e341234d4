//! `GET /api/tf?hash=`: the transfer function a frame was made with, for the page's colour
//! legend. A frame's header names it by identity ([`insitu_core::TransferFunction::identity_hash`], 16 hex
//! digits); the recording keeps every transfer function its VDIs were made with
//! ([`crate::tfs`]), and the run's agreed one (`scene.json`) answers for VDIs from nodes that
//! did not send theirs. The answer is `{"hash", "tf": {"domain", "points"}}`, or 404 naming
//! the hash when neither holds it.

use super::{error, Http};
use axum::extract::rejection::QueryRejection;
use axum::extract::{Query, State};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use axum::Json;
use serde::Deserialize;
use serde_json::json;
use std::sync::Arc;

/// The query: the transfer function's identity hash as the frame header gives it.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TfQuery {
    hash: String,
    #[allow(dead_code)] // read by the token check
    token: Option<String>,
}

/// `GET /api/tf?hash=`.
pub async fn tf(
    State(http): State<Arc<Http>>,
    q: Result<Query<TfQuery>, QueryRejection>,
) -> Response {
    let q = match q {
        Ok(Query(q)) => q,
        Err(e) => return error(StatusCode::BAD_REQUEST, e.body_text()),
    };
    let Ok(hash) = u64::from_str_radix(&q.hash, 16) else {
        return error(
            StatusCode::BAD_REQUEST,
            format!("hash {:?} is not 16 hex digits", q.hash),
        );
    };
    let found = crate::tfs::read(http.shared.recording.dir(), hash).or_else(|| {
        let agreed = http.shared.scene.agreed().map(|a| a.tf);
        agreed.filter(|tf| tf.identity_hash() == hash)
    });
    match found {
        Some(tf) => Json(json!({"hash": q.hash, "tf": tf})).into_response(),
        None => error(
            StatusCode::NOT_FOUND,
            format!("transfer function {} is not kept in this recording", q.hash),
        ),
    }
}
