//! Steering from the page and from scripts (docs/steering.md): one JSON API in front of the
//! tuner's `Steer`.
//!
//! - `GET /api/scene`: the steered scene in force, every steering change with its standing
//!   (pending, applied, superseded), the fields the newest step carries, the utility, and
//!   whether this viz-node steers at all.
//! - `GET /api/colormaps`: the colour maps the page's transfer-function editor offers
//!   (`colorous`), each sampled at [`COLORMAP_SAMPLES`] even steps as `[r, g, b]` in [0, 1].
//! - `POST /api/steer`: a change, `{"tf": {…}, "tf_name": "…", "field": "…", "camera": {…},
//!   "sample_distance": 0.5, "shading": true, "utility": "…"}` (any of them; the ray-casting
//!   sample distance in world units; a top-level `step` is refused with a message naming
//!   `sample_distance`, as `step` elsewhere is a time step). A camera is either explicit, `{"eye": [x, y, z],
//!   "target": [x, y, z], "up": [x, y, z], "fov_y_deg": 30}` (world units; `up` and the field
//!   of view optional), or a view of a stored step as the page orbits it, `{"step": s,
//!   "angle": a, "elevation": e, "zoom": z}` ("generate from here": that step's generation
//!   camera orbited so). The answer is the tuner's: the scene version, the decision that
//!   carries it, the first step made with it, the versions it superseded.
//!
//! Only the steering token steers (`Authorization: Bearer <steering token>`); the viewing
//! token gets 403. Without a steering token configured, or without a tuner, steering is off
//! and says so.

use super::{error, Http};
use crate::view::View;
use axum::extract::State;
use axum::http::{header, HeaderMap, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::Json;
use insitu_core::{Camera, TransferFunction};
use insitu_proto::auth::AttachToken;
use insitu_proto::pb;
use insitu_proto::pb::tuner_client::TunerClient;
use insitu_proto::peer::Peer;
use serde::{Deserialize, Serialize};
use serde_json::json;
use std::sync::Arc;
use std::time::Duration;
use tonic::codegen::InterceptedService;
use tonic::transport::Channel;

/// Colours per colour map sent to the page (it interpolates between them).
pub const COLORMAP_SAMPLES: usize = 33;

/// The colour maps offered, by name: perceptually uniform ones first, then diverging and grey.
const COLORMAPS: [(&str, colorous::Gradient); 8] = [
    ("viridis", colorous::VIRIDIS),
    ("inferno", colorous::INFERNO),
    ("magma", colorous::MAGMA),
    ("plasma", colorous::PLASMA),
    ("cividis", colorous::CIVIDIS),
    ("turbo", colorous::TURBO),
    ("red-blue", colorous::RED_BLUE),
    ("greys", colorous::GREYS),
];

/// `GET /api/colormaps`, in the order offered.
pub async fn colormaps() -> Response {
    let mut maps = serde_json::Map::new();
    for (name, g) in COLORMAPS {
        let colours: Vec<[f64; 3]> = (0..COLORMAP_SAMPLES)
            .map(|i| {
                let c = g.eval_continuous(i as f64 / (COLORMAP_SAMPLES - 1) as f64);
                [c.r, c.g, c.b].map(|v| (f64::from(v) / 255.0 * 1e4).round() / 1e4)
            })
            .collect();
        maps.insert(name.into(), json!(colours));
    }
    Json(serde_json::Value::Object(maps)).into_response()
}

/// How long a steering request waits for the tuner.
pub(super) const TUNER_WAIT: Duration = Duration::from_secs(10);

/// A steering request's body, as the page and `insitu steer` send it and this API reads it:
/// every part optional, unset parts left out.
#[derive(Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SteerBody {
    /// Transfer function (docs/conventions.md format), as a JSON object, checked where it is
    /// read.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub tf: Option<TransferFunction>,
    /// Its name.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub tf_name: Option<String>,
    /// The field to render.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub field: Option<String>,
    /// The generation camera.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub camera: Option<CameraBody>,
    /// The tuner's utility, e.g. `size:1MB`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub utility: Option<String>,
    /// The ray-casting sample distance, world units.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sample_distance: Option<f32>,
    /// Gradient shading on or off.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub shading: Option<bool>,
    /// Refused: the sample distance is `sample_distance` (a `step` is a time step).
    #[serde(default, rename = "step", skip_serializing)]
    old_step: Option<serde_json::Value>,
}

impl SteerBody {
    /// Whether it asks for no change at all.
    pub fn is_empty(&self) -> bool {
        *self == Self::default()
    }
}

/// A camera as a steering request gives it.
#[derive(Debug, PartialEq, Serialize, Deserialize)]
#[serde(untagged, deny_unknown_fields)]
pub enum CameraBody {
    /// World coordinates: eye and target, `up` (default +y) and the vertical field of view in
    /// degrees (default 30).
    Explicit {
        /// Eye position.
        eye: [f32; 3],
        /// Point looked at.
        target: [f32; 3],
        /// Up hint.
        #[serde(default = "y_up")]
        up: [f32; 3],
        /// Vertical field of view, degrees.
        #[serde(default = "thirty")]
        fov_y_deg: f32,
    },
    /// A stored step's generation camera (unset: the newest step's) orbited as the page shows
    /// it: azimuth and elevation in degrees, zoom 1 the generation camera's distance.
    View {
        /// The stored step.
        #[serde(skip_serializing_if = "Option::is_none")]
        step: Option<u64>,
        /// Azimuth about +y, degrees.
        #[serde(default)]
        angle: f32,
        /// Elevation, degrees.
        #[serde(default)]
        elevation: f32,
        /// Zoom (> 1 nearer).
        #[serde(default = "one")]
        zoom: f32,
    },
}

fn y_up() -> [f32; 3] {
    [0.0, 1.0, 0.0]
}

fn thirty() -> f32 {
    30.0
}

fn one() -> f32 {
    1.0
}

/// `GET /api/scene`.
pub async fn scene(State(http): State<Arc<Http>>) -> Response {
    let Some(peer) = http.tuner_peer() else {
        return Json(json!({"steering": false, "why": "no tuner-node is configured (`tuner`)"}))
            .into_response();
    };
    let status = async {
        tuner_client(&peer)
            .await?
            .get_status(pb::StatusRequest {})
            .await
            .map(tonic::Response::into_inner)
            .map_err(|e| e.message().to_owned())
    };
    let s = match tokio::time::timeout(TUNER_WAIT, status).await {
        Ok(Ok(s)) => s,
        Ok(Err(e)) => return error(StatusCode::BAD_GATEWAY, format!("the tuner-node: {e}")),
        Err(_) => {
            return error(
                StatusCode::GATEWAY_TIMEOUT,
                "the tuner-node did not answer".into(),
            )
        }
    };
    let scene = s.scene.unwrap_or_default();
    let tf = scene
        .tf
        .as_ref()
        .and_then(|t| TransferFunction::try_from(t).ok());
    let steering: Vec<serde_json::Value> = s
        .steering
        .iter()
        .map(|r| {
            json!({"scene_version": r.scene_version, "pm_version": r.pm_version,
                   "from_step": r.from_step, "state": r.state, "change": r.change,
                   "who": r.who, "at_unix_secs": r.at_unix_secs})
        })
        .collect();
    Json(json!({
        "steering": http.steer_token.is_some(),
        "why": if http.steer_token.is_some() { "" } else { "no steering token is configured (`steer_token_file`)" },
        "scene": {
            "version": scene.version,
            "tf": tf,
            "tf_name": scene.tf_name,
            "field": scene.field,
            "camera": scene.camera.as_ref().map(camera_json),
            "sample_distance": scene.sample_distance,
            "shading": scene.shading,
        },
        "history": steering,
        "fields": s.fields,
        "utility": s.utility_description,
        "configured_tf": http.shared.scene.agreed().map(|a| a.tf),
        "histogram": (!s.histogram.is_empty()).then(|| json!({
            "step": s.histogram_step,
            "lo": s.histogram_lo,
            "hi": s.histogram_hi,
            "counts": s.histogram,
        })),
        "pm_version": s.pm_version,
    }))
    .into_response()
}

/// A client of the tuner-node at `peer` (its token attached).
///
/// # Errors
/// Why it cannot be reached, naming it.
pub async fn tuner_client(
    peer: &Peer,
) -> Result<TunerClient<InterceptedService<Channel, AttachToken>>, String> {
    let channel = peer.connect().await.map_err(|e| {
        format!(
            "tuner-node {}: {}",
            peer.uri(),
            insitu_proto::peer::error_chain(&e)
        )
    })?;
    Ok(TunerClient::with_interceptor(channel, peer.auth()))
}

fn camera_json(c: &pb::Camera) -> serde_json::Value {
    let v = |v: &Option<pb::Vec3>| v.as_ref().map(|v| [v.x, v.y, v.z]);
    json!({"eye": v(&c.eye), "target": v(&c.target), "up": v(&c.up), "fov_y_deg": c.fov_y_deg})
}

/// `POST /api/steer`.
pub async fn steer(State(http): State<Arc<Http>>, headers: HeaderMap, body: String) -> Response {
    let peer = match steering_peer(&http, &headers) {
        Ok(p) => p,
        Err((status, why)) => return error(status, why),
    };
    let b: SteerBody = match serde_json::from_str(&body) {
        Ok(b) => b,
        Err(e) => {
            return error(
                StatusCode::BAD_REQUEST,
                format!("malformed steering request: {e}"),
            )
        }
    };
    let request = match request(&http, b).await {
        Ok(r) => r,
        Err(e) => return error(StatusCode::BAD_REQUEST, e),
    };
    let call = async {
        tuner_client(&peer)
            .await
            .map_err(tonic::Status::unavailable)?
            .steer(request)
            .await
            .map(tonic::Response::into_inner)
    };
    match tokio::time::timeout(TUNER_WAIT, call).await {
        Ok(Ok(r)) => Json(json!({
            "scene_version": r.scene_version,
            "pm_version": r.pm_version,
            "from_step": r.from_step,
            "utility": r.utility_description,
            "superseded": r.superseded,
        }))
        .into_response(),
        Ok(Err(s)) => tuner_refused(&s),
        Err(_) => error(
            StatusCode::GATEWAY_TIMEOUT,
            "the tuner-node did not answer the steering request".into(),
        ),
    }
}

/// The tuner to steer through, when the request presents the steering token.
///
/// # Errors
/// The status and message to answer instead: 403 when steering is off or the request lacks
/// the steering token, 503 without a tuner.
pub(super) fn steering_peer(
    http: &Http,
    headers: &HeaderMap,
) -> Result<Peer, (StatusCode, String)> {
    let Some(token) = &http.steer_token else {
        return Err((
            StatusCode::FORBIDDEN,
            "steering is off on this viz-node: start it with a steering token (`steer_token_file` or INSITU_STEER_TOKEN)".into(),
        ));
    };
    let bearer = headers
        .get(header::AUTHORIZATION)
        .and_then(|v| v.to_str().ok())
        .and_then(insitu_proto::auth::bearer);
    if !bearer.is_some_and(|t| token.matches(t)) {
        return Err((
            StatusCode::FORBIDDEN,
            "this request may view but not steer: send `Authorization: Bearer <steering token>`"
                .into(),
        ));
    }
    http.tuner_peer().ok_or_else(|| {
        (
            StatusCode::SERVICE_UNAVAILABLE,
            "steering needs a tuner-node: set `tuner` in the viz-node's config".into(),
        )
    })
}

/// The tuner's refusal as an HTTP answer: a bad request 400, a state that does not allow it
/// 409, the deadline 504, the rest 502.
pub(super) fn tuner_refused(s: &tonic::Status) -> Response {
    let status = match s.code() {
        tonic::Code::InvalidArgument => StatusCode::BAD_REQUEST,
        tonic::Code::FailedPrecondition => StatusCode::CONFLICT,
        tonic::Code::DeadlineExceeded => StatusCode::GATEWAY_TIMEOUT,
        _ => StatusCode::BAD_GATEWAY,
    };
    error(status, s.message().to_owned())
}

/// The tuner's request for `b`: the transfer function checked and typed for the wire, a
/// view's camera made from its step's generation camera.
///
/// # Errors
/// A message naming the bad part (a view of a step not stored, a bad view).
async fn request(http: &Arc<Http>, b: SteerBody) -> Result<pb::SteerRequest, String> {
    if b.old_step.is_some() {
        return Err(
            "\"step\" is not a steering key: the ray-casting sample distance is \"sample_distance\" (world units)"
                .into(),
        );
    }
    let camera = match b.camera {
        None => None,
        Some(c) => Some(c.camera(http).await?),
    };
    Ok(pb::SteerRequest {
        tf: b.tf.as_ref().map(wire_tf).transpose()?,
        tf_name: b.tf_name,
        field: b.field,
        camera: camera.as_ref().map(pb::Camera::from),
        utility: b.utility,
        sample_distance: b.sample_distance,
        shading: b.shading,
        who: "the viewer's steering API".into(),
        legacy_tf_json: None,
    })
}

/// A request body's transfer function checked (as a file's is) and typed for the tuner: a
/// broken one is refused here, before the tuner is called.
///
/// # Errors
/// `tf: transfer function in the request: …` naming the broken rule.
pub(super) fn wire_tf(tf: &TransferFunction) -> Result<pb::TransferFunction, String> {
    tf.validate("in the request")
        .map_err(|e| format!("tf: {e}"))?;
    Ok(pb::TransferFunction::from(tf))
}

impl CameraBody {
    /// The camera it stands for: as given, or made from its step's generation camera.
    ///
    /// # Errors
    /// A message naming the bad part (a view of a step not stored, a bad view).
    pub(super) async fn camera(self, http: &Arc<Http>) -> Result<Camera, String> {
        match self {
            Self::Explicit {
                eye,
                target,
                up,
                fov_y_deg,
            } => Ok(Camera {
                eye: eye.into(),
                target: target.into(),
                up: up.into(),
                fov_y_deg,
            }),
            Self::View {
                step,
                angle,
                elevation,
                zoom,
            } => view_camera(http, step, angle, elevation, zoom).await,
        }
    }
}

/// The generation camera of `step` (none: the newest stored) orbited by the page's view.
async fn view_camera(
    http: &Arc<Http>,
    step: Option<u64>,
    angle: f32,
    elevation: f32,
    zoom: f32,
) -> Result<Camera, String> {
    let view = View {
        angle_deg: angle,
        elevation_deg: elevation,
        zoom,
        ..View::default()
    };
    view.check(u64::MAX).map_err(|e| format!("camera: {e}"))?;
    let rec = &http.shared.recording;
    let step = step
        .or_else(|| rec.latest_step())
        .ok_or("camera: the recording holds no step yet to take a view from")?;
    let file = crate::view::vdi_file(step, None, &rec.ranks_of(step), rec.step(step).as_ref())
        .map_err(|e| format!("camera: {e}"))?;
    let h = http.clone();
    let generation = tokio::task::spawn_blocking(move || h.vdi(&file).map(|v| v.meta().camera))
        .await
        .map_err(|e| format!("camera: {e}"))?
        .map_err(|e| format!("camera: {e}"))?;
    Ok(view.camera(&generation))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn every_colour_map_runs_from_its_first_colour_to_its_last_in_range() {
        let r = colormaps().await;
        let bytes = axum::body::to_bytes(r.into_body(), 1 << 20).await.unwrap();
        let maps: serde_json::Map<String, serde_json::Value> =
            serde_json::from_slice(&bytes).unwrap();
        assert_eq!(maps.len(), COLORMAPS.len());
        let viridis = maps["viridis"].as_array().unwrap();
        assert_eq!(viridis.len(), COLORMAP_SAMPLES);
        // viridis runs from dark purple (#440154) to yellow (#fde725).
        let first: Vec<f64> = serde_json::from_value(viridis[0].clone()).unwrap();
        let last: Vec<f64> = serde_json::from_value(viridis[COLORMAP_SAMPLES - 1].clone()).unwrap();
        assert!(
            (first[0] - 68.0 / 255.0).abs() < 0.01 && (first[2] - 84.0 / 255.0).abs() < 0.01,
            "{first:?}"
        );
        assert!(
            (last[0] - 253.0 / 255.0).abs() < 0.02 && (last[1] - 231.0 / 255.0).abs() < 0.02,
            "{last:?}"
        );
        for colours in maps.values() {
            for c in colours.as_array().unwrap() {
                for v in c.as_array().unwrap() {
                    assert!((0.0..=1.0).contains(&v.as_f64().unwrap()));
                }
            }
        }
    }

    #[test]
    fn a_camera_is_explicit_or_a_view_and_nothing_else() {
        let b: SteerBody =
            serde_json::from_str(r#"{"camera": {"eye": [0, 0, 9], "target": [0, 0, 0]}}"#).unwrap();
        assert!(matches!(
            b.camera,
            Some(CameraBody::Explicit {
                up: [0.0, 1.0, 0.0],
                fov_y_deg: 30.0,
                ..
            })
        ));
        let b: SteerBody = serde_json::from_str(r#"{"camera": {"step": 3, "angle": 40}}"#).unwrap();
        assert!(matches!(
            b.camera,
            Some(CameraBody::View {
                step: Some(3),
                zoom: 1.0,
                ..
            })
        ));
        for bad in [
            r#"{"camera": {"eye": [0, 0]}}"#,
            r#"{"camera": {"angle": 1, "eye": [0, 0, 9]}}"#,
            r#"{"colour": "red"}"#,
            r#"{"tf": "#,
        ] {
            assert!(serde_json::from_str::<SteerBody>(bad).is_err(), "{bad}");
        }
    }

    /// What `insitu steer` sends (the type serialized) reads back as the same request; unset
    /// parts are left out, so the empty body is `{}`, which asks for nothing.
    #[test]
    fn a_body_written_by_the_type_reads_back_the_same() {
        let b = SteerBody {
            tf: Some(TransferFunction::default_for_range(-2.0, 5.0)),
            tf_name: Some("warm".into()),
            camera: Some(CameraBody::View {
                step: None,
                angle: 30.0,
                elevation: -10.0,
                zoom: 1.5,
            }),
            sample_distance: Some(0.25),
            ..Default::default()
        };
        let text = serde_json::to_string(&b).unwrap();
        assert_eq!(serde_json::from_str::<SteerBody>(&text).unwrap(), b);
        assert!(
            !text.contains("field") && !text.contains("\"step\""),
            "{text}"
        );
        assert_eq!(serde_json::to_string(&SteerBody::default()).unwrap(), "{}");
        assert!(SteerBody::default().is_empty() && !b.is_empty());
    }
}
