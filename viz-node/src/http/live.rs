//! `GET /api/live`: the page's WebSocket.
//!
//! In: camera requests as JSON text, `{"id", "step" (null: the latest), "rank" (null:
//! composed), "angle", "elevation", "zoom", "width", "height", "format": "jpeg"|"png",
//! "quality", "lod"}`. Out: for each frame a JSON text `{"frame": id, "step", "rank", "format",
//! "width", "height", "bytes", "render_ms", "encode_ms", "vdi_resolution", "superseded",
//! "camera": {"eye", "target", "up", "fov_y_deg"} (the camera rendered), "fit_zoom" (the zoom
//! that frames the volume from this direction), "box": {"min", "max"} (the volume's world
//! box), "tf": {"name", "hash"}}` followed by the image
//! as one binary message; `{"event": "stored", "step", "rank"}` whenever the viz-node stores
//! a VDI (so a page following the latest step needs no reload); `{"error": message, "id"}`
//! for a request that cannot be served (the socket stays open).
//!
//! Only the latest request is rendered: a request that arrives while a frame renders
//! replaces any request still waiting, which is counted as superseded and never rendered.
//! So a burst of camera changes costs one render in flight and one after it, not a queue.

use super::api::render_frame;
use super::Http;
use crate::view::{Format, View, ViewError};
use axum::extract::ws::{CloseFrame, Message, WebSocket, WebSocketUpgrade};
use axum::extract::State;
use axum::response::Response;
use futures_util::{SinkExt, StreamExt};
use serde::Deserialize;
use serde_json::json;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::sync::Mutex;
use tokio::sync::{mpsc, Notify};

/// Largest camera request, bytes.
const MAX_REQUEST_BYTES: usize = 4096;

/// Largest message read from a socket, bytes: a larger request is answered in-band up to
/// `4 × MAX_REQUEST_BYTES`, and beyond it the socket is closed with 1009 ("message too big",
/// RFC 6455) up to this size; only what exceeds this is cut off by the WebSocket layer.
const MAX_MESSAGE_BYTES: usize = 1 << 20;

/// One camera request.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct FrameRequest {
    /// Echoed in the frame's header.
    #[serde(default)]
    pub id: u64,
    /// Step; none: the latest stored.
    pub step: Option<u64>,
    /// Rank; none: the step composed over its ranks.
    pub rank: Option<u32>,
    /// Degrees about +y.
    #[serde(default, deserialize_with = "super::numbers::angle")]
    pub angle: f32,
    /// Degrees up.
    #[serde(default, deserialize_with = "super::numbers::narrow")]
    pub elevation: f32,
    /// Distance factor.
    #[serde(default = "one", deserialize_with = "super::numbers::narrow")]
    pub zoom: f32,
    /// Pixels.
    pub width: u32,
    /// Pixels.
    pub height: u32,
    /// Encoding.
    pub format: Format,
    /// JPEG quality, 1..=100 (default 55).
    #[serde(default = "jpeg_quality")]
    pub quality: u8,
    /// Render from the coarsest level of the VDI that still has the frame's resolution
    /// ([`insitu_core::vdi::Vdi::level_for`]): what the page asks for while the camera moves
    /// (default false: the full VDI).
    #[serde(default)]
    pub lod: bool,
}

fn one() -> f32 {
    1.0
}

fn jpeg_quality() -> u8 {
    55
}

/// Parses a request, saying what is wrong.
///
/// # Errors
/// A message naming the problem (too long, not JSON, a missing or unknown field).
pub fn parse(text: &str) -> Result<FrameRequest, String> {
    if text.len() > MAX_REQUEST_BYTES {
        return Err(format!(
            "camera request of {} bytes exceeds {MAX_REQUEST_BYTES}",
            text.len()
        ));
    }
    serde_json::from_str(text).map_err(|e| format!("malformed camera request: {e}"))
}

/// Upgrades to the socket.
pub async fn upgrade(State(http): State<Arc<Http>>, ws: WebSocketUpgrade) -> Response {
    ws.max_message_size(MAX_MESSAGE_BYTES)
        .on_upgrade(move |socket| session(http, socket))
}

async fn session(http: Arc<Http>, socket: WebSocket) {
    http.clients.fetch_add(1, Ordering::Relaxed);
    let (mut sink, mut stream) = socket.split();
    let (out_tx, mut out_rx) = mpsc::channel::<Message>(8);
    let latest = Arc::new(Latest::default());
    let writer = tokio::spawn(async move {
        while let Some(m) = out_rx.recv().await {
            if sink.send(m).await.is_err() {
                break;
            }
        }
    });
    let renderer = tokio::spawn(render_loop(http.clone(), latest.clone(), out_tx.clone()));
    // Stored VDIs, told to the page.
    let mut reports = http.shared.reports.subscribe();
    let events = {
        let out = out_tx.clone();
        tokio::spawn(async move {
            loop {
                match reports.recv().await {
                    Ok(r) => {
                        let m = json!({"event": "stored", "step": r.step, "rank": r.rank});
                        if out.send(Message::Text(m.to_string().into())).await.is_err() {
                            break;
                        }
                    }
                    Err(tokio::sync::broadcast::error::RecvError::Lagged(_)) => {}
                    Err(_) => break,
                }
            }
        })
    };
    // Pings keep a quiet page's socket open through proxies and show a vanished peer: a socket
    // with no message at all (pongs included) for `socket_idle` is closed.
    let pinger = {
        let out = out_tx.clone();
        let every = http.socket_idle / 3;
        tokio::spawn(async move {
            loop {
                tokio::time::sleep(every).await;
                if out.send(Message::Ping(Vec::new().into())).await.is_err() {
                    break;
                }
            }
        })
    };
    while let Ok(Some(Ok(msg))) = tokio::time::timeout(http.socket_idle, stream.next()).await {
        let text = match msg {
            Message::Text(t) if t.len() > 4 * MAX_REQUEST_BYTES => {
                let reason = format!(
                    "a message of {} bytes: camera requests are at most {MAX_REQUEST_BYTES}",
                    t.len()
                );
                let close = CloseFrame {
                    code: 1009,
                    reason: reason.into(),
                };
                let _ = out_tx.send(Message::Close(Some(close))).await;
                break;
            }
            Message::Text(t) => t,
            Message::Close(_) => break,
            Message::Binary(_) => {
                refuse(
                    &http,
                    &out_tx,
                    None,
                    "send camera requests as JSON text".into(),
                )
                .await;
                continue;
            }
            _ => continue,
        };
        match parse(text.as_str()) {
            Ok(req) => {
                if latest.put(req) {
                    http.superseded.fetch_add(1, Ordering::Relaxed);
                }
            }
            Err(problem) => refuse(&http, &out_tx, None, problem).await,
        }
    }
    renderer.abort();
    events.abort();
    pinger.abort();
    drop(out_tx);
    let _ = writer.await;
    http.clients.fetch_sub(1, Ordering::Relaxed);
}

/// The one request waiting to be rendered.
#[derive(Default)]
struct Latest {
    slot: Mutex<Option<FrameRequest>>,
    ready: Notify,
}

impl Latest {
    /// Makes `req` the waiting request; returns whether it replaced one never rendered.
    fn put(&self, req: FrameRequest) -> bool {
        let replaced = self
            .slot
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .replace(req)
            .is_some();
        self.ready.notify_one();
        replaced
    }

    /// Waits for a request and takes it.
    async fn take(&self) -> FrameRequest {
        loop {
            if let Some(r) = self.slot.lock().unwrap_or_else(|e| e.into_inner()).take() {
                return r;
            }
            self.ready.notified().await;
        }
    }
}

async fn refuse(http: &Http, out: &mpsc::Sender<Message>, id: Option<u64>, problem: String) {
    http.refused.fetch_add(1, Ordering::Relaxed);
    let m = json!({"error": problem, "id": id});
    let _ = out.send(Message::Text(m.to_string().into())).await;
}

/// Renders the latest request whenever one is waiting (aborted when the socket closes).
async fn render_loop(http: Arc<Http>, latest: Arc<Latest>, out: mpsc::Sender<Message>) {
    loop {
        let req = latest.take().await;
        match frame(&http, &req).await {
            Ok((header, bytes)) => {
                if out
                    .send(Message::Text(header.to_string().into()))
                    .await
                    .is_err()
                    || out.send(Message::Binary(bytes.into())).await.is_err()
                {
                    break;
                }
            }
            Err(e) => refuse(&http, &out, Some(req.id), e.to_string()).await,
        }
    }
}

async fn frame(
    http: &Arc<Http>,
    req: &FrameRequest,
) -> Result<(serde_json::Value, Vec<u8>), ViewError> {
    let v = View {
        angle_deg: req.angle,
        elevation_deg: req.elevation,
        zoom: req.zoom,
        width: req.width,
        height: req.height,
    };
    let f = render_frame(
        http,
        req.step,
        req.rank,
        v,
        req.format,
        req.quality,
        req.lod,
    )
    .await?;
    let header = json!({
        "frame": req.id,
        "step": f.step,
        "rank": req.rank,
        "format": req.format,
        "width": req.width,
        "height": req.height,
        "bytes": f.bytes.len(),
        "render_ms": f.render_secs * 1e3,
        "encode_ms": f.encode_secs * 1e3,
        "vdi_resolution": f.vdi_resolution,
        "superseded": http.superseded.load(Ordering::Relaxed),
        "camera": {
            "eye": f.camera.eye.to_array(),
            "target": f.camera.target.to_array(),
            "up": f.camera.up.to_array(),
            "fov_y_deg": f.camera.fov_y_deg,
        },
        "fit_zoom": f.fit_zoom,
        "box": {"min": f.volume_box.min.to_array(), "max": f.volume_box.max.to_array()},
        "tf": {"name": f.tf.0, "hash": format!("{:016x}", f.tf.1)},
    });
    Ok((header, f.bytes))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn only_the_latest_request_waits() {
        let l = Latest::default();
        let req = |id| {
            parse(&format!(
                r#"{{"id":{id},"width":1,"height":1,"format":"png"}}"#
            ))
            .unwrap()
        };
        assert!(!l.put(req(1)));
        assert!(
            l.put(req(2)) && l.put(req(3)),
            "waiting requests are replaced"
        );
        assert_eq!(l.take().await.id, 3);
        assert!(!l.put(req(4)), "a taken request is not superseded");
        assert_eq!(l.take().await.id, 4);
    }

    #[test]
    fn requests_parse_or_say_what_is_wrong() {
        let r = parse(r#"{"id":3,"step":null,"rank":null,"angle":10,"elevation":-5,"width":64,"height":48,"format":"jpeg"}"#).unwrap();
        assert_eq!(
            (r.id, r.zoom, r.quality, r.format, r.lod),
            (3, 1.0, 55, Format::Jpeg, false)
        );
        assert!(parse("{").unwrap_err().contains("malformed"));
        assert!(parse(r#"{"width":1,"height":1,"format":"gif"}"#)
            .unwrap_err()
            .contains("malformed"));
        assert!(parse(r#"{"width":1,"height":1,"format":"png","fov":3}"#)
            .unwrap_err()
            .contains("fov"));
        assert!(parse(&"x".repeat(5000)).unwrap_err().contains("exceeds"));
    }
}
