//! `GET /api/tf?hash=`: the transfer function a frame was made with, for the page's colour
//! legend. A frame's header names it by identity
//! ([`insitu_core::TransferFunction::identity_hash`], 16 hex digits); the recording keeps
//! every transfer function its VDIs were made with ([`crate::tfs`]), and the run's agreed one
//! (`scene.json`) answers for VDIs from nodes that did not send theirs. The answer is
//! `{"hash", "tf": {"domain", "points"}}`, or 404 naming the hash when neither holds it.

use super::api::query;
use super::Http;
use crate::view::ViewError;
use axum::extract::rejection::QueryRejection;
use axum::extract::{Query, State};
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
    match found(&http, q).await {
        Ok((hash, tf)) => Json(json!({"hash": hash, "tf": tf})).into_response(),
        Err(e) => e.into_response(),
    }
}

/// The transfer function the query names, with its hash as given.
async fn found(
    http: &Arc<Http>,
    q: Result<Query<TfQuery>, QueryRejection>,
) -> Result<(String, insitu_core::TransferFunction), ViewError> {
    let q = query(q)?;
    let hash = u64::from_str_radix(&q.hash, 16)
        .map_err(|_| ViewError::BadRequest(format!("hash {:?} is not 16 hex digits", q.hash)))?;
    let dir = http.shared.recording.dir().to_owned();
    let kept = tokio::task::spawn_blocking(move || crate::tfs::read(&dir, hash))
        .await
        .map_err(|e| ViewError::Failed(format!("reading the transfer function: {e}")))?;
    let agreed = || {
        let agreed = http.shared.scene.agreed().map(|a| a.tf);
        agreed.filter(|tf| tf.identity_hash() == hash)
    };
    let tf = kept.or_else(agreed).ok_or_else(|| {
        ViewError::NotFound(format!(
            "transfer function {} is not kept in this recording",
            q.hash
        ))
    })?;
    Ok((q.hash, tf))
}
