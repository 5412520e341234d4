//! The web viewer: HTTP on the viz-node's tokio runtime, beside the gRPC server.
//!
//! - `GET /` and its assets: the page, embedded in the binary (nothing fetched at run time).
//! - `GET /api/steps`, `GET /api/series`, `GET /api/render`, `GET /api/reference`,
//!   `GET /api/stats`: the JSON API the page and scripts share ([`api`]; docs/viewer.md).
//! - `GET /api/live`: a WebSocket of camera requests in and frames out ([`live`]); the server
//!   renders only each client's latest request.
//! - `GET /api/movie`: the stored steps as an MP4 download, encoded by `ffmpeg` ([`movie`]).
//! - `GET /api/scene`, `POST /api/steer`: the steered scene and steering ([`steer`]; the
//!   steering token only).
//!
//! The gRPC side's rules hold: loopback by default; off loopback a token and TLS (the
//! viz-node's `[tls]` certificate: HTTPS, [`tls`]) unless `insecure`; with a token configured
//! every request needs it (`Authorization: Bearer <token>`, or `?token=<token>` where a
//! browser cannot set headers: the page itself and its socket). Rendering runs on the blocking pool under its
//! own semaphore, so it never holds up storing or scoring.

pub mod api;
pub mod cap;
pub mod conn;
pub mod lanes;
pub mod legend;
pub mod live;
pub mod movie;
pub mod numbers;
pub mod origin;
pub mod pools;
pub mod preview;
pub mod steer;
pub mod tls;

use crate::service::Shared;
use crate::view::ViewError;
use axum::extract::{Request, State};
use axum::http::{header, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::serve::ListenerExt;
use axum::{Json, Router};
use insitu_core::budget::Budgets;
use insitu_core::Vdi;
use insitu_proto::auth::Token;
use insitu_proto::pb;
use insitu_proto::peer::Peer;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// Decoded VDIs kept for quick re-rendering (dragging renders one VDI many times). Each keeps
/// what rendering derived from it: the walk's tables (8 bytes per supersegment) and the levels
/// dragging asked for (the teapot at r = 768: 38 MB of lists, 13 MB of tables, 10 MB for the
/// r = 384 level).
const CACHED_VDIS: usize = 4;
/// How long the tuner's budget is reused before it is asked again.
pub const BUDGET_REFRESH: Duration = Duration::from_secs(5);

/// What the HTTP side shares.
pub struct Http {
    /// The viz-node's state (recording, backend, reports).
    pub shared: Arc<Shared>,
    token: Option<Token>,
    /// The steering token ([`steer`]): it steers, and views as `token` does; `None`:
    /// steering is off.
    steer_token: Option<Token>,
    /// The `Host` and `Origin` answered to ([`origin`]).
    allowed: origin::Allowed,
    /// Renders at once over all HTTP clients.
    renders: lanes::Lane,
    /// The lane of large stills, one at a time ([`lanes`]).
    large: lanes::Lane,
    /// The threads interactive frames and large renders run on ([`pools`]).
    pools: pools::Pools,
    cache: Mutex<Vec<(String, Arc<Vdi>)>>,
    /// Frames rendered (still renders and socket frames).
    pub rendered: AtomicU64,
    /// Socket camera requests replaced by a newer one before they were rendered.
    pub superseded: AtomicU64,
    /// Renders (frames and movies) running now.
    pub rendering: AtomicU64,
    /// Renders and movies stopped because their client went away.
    pub cancelled: AtomicU64,
    /// Socket requests refused (malformed JSON, bad values).
    pub refused: AtomicU64,
    /// Sockets open now.
    pub clients: AtomicU64,
    /// A live socket that has sent nothing (not even a pong to the pings sent every third of
    /// this) for this long is closed.
    socket_idle: Duration,
    /// The tuner whose budget the charts draw.
    tuner: Mutex<Option<Peer>>,
    /// Its budget as last read, and when.
    budget: tokio::sync::Mutex<Option<(Instant, serde_json::Value)>>,
}

impl Http {
    /// Over `shared`, requiring `token` when one is configured; `render_concurrency` renders
    /// at once; answering to IP addresses, `localhost` and the names `hosts` ([`origin`]);
    /// live sockets closed after `socket_idle` without a word from their page.
    pub fn new(
        shared: Arc<Shared>,
        token: Option<Token>,
        render_concurrency: usize,
        hosts: &[String],
        socket_idle: Duration,
    ) -> Self {
        Self {
            shared,
            token,
            steer_token: None,
            allowed: origin::Allowed::new(hosts),
            renders: lanes::Lane::new(render_concurrency, lanes::WAITING),
            large: lanes::Lane::new(1, lanes::LARGE_WAITING),
            pools: pools::Pools::new(0),
            cache: Mutex::new(Vec::new()),
            rendered: AtomicU64::new(0),
            superseded: AtomicU64::new(0),
            rendering: AtomicU64::new(0),
            cancelled: AtomicU64::new(0),
            refused: AtomicU64::new(0),
            clients: AtomicU64::new(0),
            socket_idle,
            tuner: Mutex::new(None),
            budget: tokio::sync::Mutex::new(None),
        }
    }

    /// Lets the holder of `token` steer the run ([`steer`]).
    #[must_use]
    pub fn steering(mut self, token: Option<Token>) -> Self {
        self.steer_token = token;
        self
    }

    /// The tuner, when one is configured.
    pub fn tuner_peer(&self) -> Option<Peer> {
        self.tuner.lock().unwrap_or_else(|e| e.into_inner()).clone()
    }

    /// Draws the budget of the tuner at `peer` in the charts.
    pub fn watch_tuner(&self, peer: Peer) {
        *self.tuner.lock().unwrap_or_else(|e| e.into_inner()) = Some(peer);
    }

    /// The tuner's budget `{"sigma_bytes", "tau_s", "q_db", "utility"}` (null where the
    /// utility has none), read at most every [`BUDGET_REFRESH`] with a 1 s limit (the viewer
    /// never waits long on it); while the tuner cannot be reached, the last one read; null
    /// without a tuner.
    pub async fn budget(&self) -> serde_json::Value {
        let Some(peer) = self.tuner_peer() else {
            return serde_json::Value::Null;
        };
        let mut cached = self.budget.lock().await;
        if let Some((at, v)) = cached.as_ref() {
            if at.elapsed() < BUDGET_REFRESH {
                return v.clone();
            }
        }
        let ask = async {
            let mut c = steer::tuner_client(&peer).await.ok()?;
            c.get_status(pb::StatusRequest {}).await.ok()
        };
        let v = match tokio::time::timeout(Duration::from_secs(1), ask).await {
            Ok(Some(s)) => {
                let s = s.into_inner();
                let budgets = Budgets::from_wire(s.sigma_target_bytes, s.tau_target_secs);
                serde_json::json!({
                    "sigma_bytes": budgets.size_bytes,
                    "tau_s": budgets.time_secs,
                    "q_db": (s.q_target_db > 0.0).then_some(s.q_target_db),
                    "utility": s.utility_description,
                })
            }
            // Unreachable: the last budget read, if any (a budget changes only with the
            // tuner's configuration).
            _ => cached.take().map_or(serde_json::Value::Null, |(_, v)| v),
        };
        *cached = Some((Instant::now(), v.clone()));
        v
    }

    /// The decoded VDI `file` of the recording, from the cache or the disk.
    ///
    /// # Errors
    /// [`ViewError::Failed`] when it cannot be read or decoded, or is not what its row says.
    pub fn vdi(&self, file: &crate::view::VdiFile) -> Result<Arc<Vdi>, ViewError> {
        let name = file.name.as_str();
        let lock = || self.cache.lock().unwrap_or_else(|e| e.into_inner());
        if let Some((_, v)) = lock().iter().find(|(n, _)| n == name) {
            return Ok(v.clone());
        }
        let v = Arc::new(crate::view::load_vdi(self.shared.recording.dir(), file)?);
        let mut c = lock();
        c.retain(|(n, _)| n != name);
        c.push((name.to_owned(), v.clone()));
        if c.len() > CACHED_VDIS {
            c.remove(0);
        }
        Ok(v)
    }
}

/// Largest request body (a steering request or preview with its transfer function), bytes.
pub const MAX_BODY_BYTES: usize = 2 << 20;

/// The router: page, API and socket, behind the token check.
pub fn router(http: Arc<Http>) -> Router {
    Router::new()
        .route("/", get(page))
        .route("/app.js", get(script))
        .route("/style.css", get(style))
        .route("/api/steps", get(api::steps))
        .route("/api/series", get(api::series))
        // HEAD would render the whole frame to send its headers: refused instead.
        .route("/api/render", get(api::render).head(no_head))
        .route("/api/reference", get(api::reference))
        .route("/api/stats", get(api::stats))
        .route("/api/movie", get(movie::movie).head(no_head))
        .route("/api/live", get(live::upgrade))
        .route("/api/scene", get(steer::scene))
        .route("/api/colormaps", get(steer::colormaps))
        .route("/api/tf", get(legend::tf))
        .route("/api/steer", axum::routing::post(steer::steer))
        .route("/api/preview", axum::routing::post(preview::preview))
        .fallback(|| async { error(StatusCode::NOT_FOUND, "no such page or API".into()) })
        // Steering and preview bodies (a transfer function): larger ones get 413.
        .layer(axum::extract::DefaultBodyLimit::max(MAX_BODY_BYTES))
        .layer(axum::middleware::from_fn_with_state(
            http.clone(),
            require_token,
        ))
        // Outermost: a request from a foreign host or origin gets no further, token or not.
        .layer(axum::middleware::from_fn_with_state(
            http.clone(),
            require_own_origin,
        ))
        .with_state(http)
}

/// Serves the viewer on `listener` until `stop` resolves: HTTPS with `tls`, else HTTP; at most
/// `max_connections` open at once ([`cap`]), each under `timeouts` ([`conn`]).
///
/// # Errors
/// An I/O error setting up TLS.
pub async fn serve(
    listener: tokio::net::TcpListener,
    tls: Option<rustls::ServerConfig>,
    http: Arc<Http>,
    max_connections: usize,
    timeouts: conn::Timeouts,
    stop: impl std::future::Future<Output = ()> + Send + 'static,
) -> std::io::Result<()> {
    let router = router(http);
    match tls {
        Some(cfg) => {
            let listener = cap::Capped::new(tls::TlsListener::new(listener, cfg)?, max_connections);
            conn::serve(listener, router, timeouts, stop).await;
        }
        None => {
            // Frames are a small header then the image: without TCP_NODELAY the image's last
            // segment waits for the header's delayed ACK (40 ms on Linux).
            let listener = listener.tap_io(|tcp| {
                let _ = tcp.set_nodelay(true);
            });
            let listener = cap::Capped::new(listener, max_connections);
            conn::serve(listener, router, timeouts, stop).await;
        }
    }
    Ok(())
}

/// A JSON error `{"error": message}` with `status`.
pub fn error(status: StatusCode, message: String) -> Response {
    (status, Json(serde_json::json!({ "error": message }))).into_response()
}

impl IntoResponse for ViewError {
    fn into_response(self) -> Response {
        let status = match &self {
            ViewError::NotFound(_) => StatusCode::NOT_FOUND,
            ViewError::BadRequest(_) => StatusCode::BAD_REQUEST,
            ViewError::TooLarge(_) => StatusCode::PAYLOAD_TOO_LARGE,
            // Cancelled: nobody waits for the answer.
            ViewError::Busy(_) | ViewError::Cancelled => StatusCode::SERVICE_UNAVAILABLE,
            ViewError::Failed(_) => StatusCode::INTERNAL_SERVER_ERROR,
        };
        let message = self.to_string();
        if status == StatusCode::SERVICE_UNAVAILABLE {
            let mut r = error(status, message);
            r.headers_mut()
                .insert(header::RETRY_AFTER, header::HeaderValue::from_static("1"));
            return r;
        }
        if status == StatusCode::INTERNAL_SERVER_ERROR {
            // The whole story for the operator (a corrupt or swapped file, say); the caller
            // learns what failed, not where the server keeps its files.
            tracing::warn!(error = %message, "a viewer request failed");
            return error(status, without_dirs(&message));
        }
        error(status, message)
    }
}

/// `message` with every absolute path cut to its file name.
fn without_dirs(message: &str) -> String {
    message
        .split(' ')
        .map(|word| match word.strip_prefix('/') {
            Some(rest) => rest.rsplit('/').next().unwrap_or(rest),
            None => word,
        })
        .collect::<Vec<_>>()
        .join(" ")
}

async fn no_head() -> Response {
    let mut r = error(
        StatusCode::METHOD_NOT_ALLOWED,
        "HEAD would render the frame to send its headers: use GET".into(),
    );
    r.headers_mut()
        .insert(header::ALLOW, header::HeaderValue::from_static("GET"));
    r
}

async fn require_own_origin(State(http): State<Arc<Http>>, req: Request, next: Next) -> Response {
    if let Err((status, message)) = own_origin(&http.allowed, &req) {
        return error(status, message);
    }
    next.run(req).await
}

/// [`require_own_origin`]'s check: the refusal for a foreign `Host` or `Origin`.
fn own_origin(allowed: &origin::Allowed, req: &Request) -> Result<(), (StatusCode, String)> {
    // Two `Host` or `Origin` headers: which one a proxy, a cache and this check would each
    // believe differs, so none is.
    for name in [header::HOST, header::ORIGIN] {
        if req.headers().get_all(&name).iter().count() > 1 {
            return Err((
                StatusCode::BAD_REQUEST,
                format!("the request has more than one {name} header: send one"),
            ));
        }
    }
    let text = |name| req.headers().get(name).and_then(|v| v.to_str().ok());
    // HTTP/1.1 sends `Host`; HTTP/2 the URI's authority.
    let host = text(header::HOST)
        .or_else(|| req.uri().authority().map(|a| a.as_str()))
        .unwrap_or_default();
    if !allowed.host(host) {
        return Err((
            StatusCode::MISDIRECTED_REQUEST,
            format!("Host {host:?} is not one this viewer answers to: use its address, localhost, or a name listed in http_hosts"),
        ));
    }
    if let Some(origin) = text(header::ORIGIN) {
        if !allowed.origin(origin, host) {
            return Err((
                StatusCode::FORBIDDEN,
                format!("requests from the origin {origin:?} are not answered: the viewer serves its own page only (or names listed in http_hosts)"),
            ));
        }
    }
    Ok(())
}

async fn require_token(State(http): State<Arc<Http>>, req: Request, next: Next) -> Response {
    let Some(token) = &http.token else {
        return next.run(req).await;
    };
    // The steering token views too.
    let matches =
        |t: &str| token.matches(t) || http.steer_token.as_ref().is_some_and(|s| s.matches(t));
    let bearer = req
        .headers()
        .get(header::AUTHORIZATION)
        .and_then(|v| v.to_str().ok())
        .and_then(insitu_proto::auth::bearer);
    let query = req.uri().query().and_then(|q| {
        form_urlencoded::parse(q.as_bytes()).find_map(|(k, v)| (k == "token").then_some(v))
    });
    let ok = bearer.is_some_and(matches) || query.is_some_and(|t| matches(&t));
    if ok {
        next.run(req).await
    } else {
        error(
            StatusCode::UNAUTHORIZED,
            "missing or wrong token: send `Authorization: Bearer <token>` or add `?token=<token>` to the URL".into(),
        )
    }
}

async fn page() -> impl IntoResponse {
    (
        [(header::CONTENT_TYPE, "text/html; charset=utf-8")],
        include_str!("assets/index.html"),
    )
}

async fn script() -> impl IntoResponse {
    (
        [(header::CONTENT_TYPE, "text/javascript; charset=utf-8")],
        include_str!("assets/app.js"),
    )
}

async fn style() -> impl IntoResponse {
    (
        [(header::CONTENT_TYPE, "text/css; charset=utf-8")],
        include_str!("assets/style.css"),
    )
}

/// Counts a render in [`Http::rendering`] while it lives, and in [`Http::cancelled`] when
/// it ends cancelled ([`Running::end`]).
pub(crate) struct Running<'a>(&'a Http);

impl<'a> Running<'a> {
    pub(crate) fn start(http: &'a Http) -> Self {
        http.rendering.fetch_add(1, Ordering::Relaxed);
        Self(http)
    }

    /// Passes `out` through, counting it when it says the render was cancelled.
    pub(crate) fn end<T, E>(
        self,
        out: Result<T, E>,
        cancelled: impl Fn(&E) -> bool,
    ) -> Result<T, E> {
        if out.as_ref().err().is_some_and(cancelled) {
            self.0.cancelled.fetch_add(1, Ordering::Relaxed);
        }
        out
    }
}

impl Drop for Running<'_> {
    fn drop(&mut self) {
        self.0.rendering.fetch_sub(1, Ordering::Relaxed);
    }
}

/// The counters of `GET /api/stats`.
pub fn stats(http: &Http) -> serde_json::Value {
    let n = |a: &AtomicU64| a.load(Ordering::Relaxed);
    serde_json::json!({
        "rendered": n(&http.rendered),
        "superseded": n(&http.superseded),
        "rendering": n(&http.rendering),
        "cancelled": n(&http.cancelled),
        "refused": n(&http.refused),
        "clients": n(&http.clients),
        "vdis_stored": n(&http.shared.vdis_stored),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_request_with_two_hosts_or_origins_is_refused() {
        let allowed = origin::Allowed::default();
        let req = |headers: &[(&str, &str)]| {
            let mut b = axum::http::Request::builder().uri("/api/stats");
            for (k, v) in headers {
                b = b.header(*k, *v);
            }
            b.body(axum::body::Body::empty()).unwrap()
        };
        assert!(own_origin(&allowed, &req(&[("host", "127.0.0.1:8080")])).is_ok());
        let (status, m) = own_origin(
            &allowed,
            &req(&[("host", "127.0.0.1:8080"), ("host", "evil.example")]),
        )
        .unwrap_err();
        assert_eq!(status, StatusCode::BAD_REQUEST);
        assert!(m.contains("more than one host header"), "{m}");
        let two_origins = req(&[
            ("host", "127.0.0.1:8080"),
            ("origin", "http://127.0.0.1:8080"),
            ("origin", "http://evil.example"),
        ]);
        assert_eq!(
            own_origin(&allowed, &two_origins).unwrap_err().0,
            StatusCode::BAD_REQUEST
        );
    }

    #[test]
    fn failures_name_files_not_the_server_s_folders() {
        assert_eq!(
            without_dirs("cannot read /srv/rec/step_00000001_rank_0000.vdi: No such file"),
            "cannot read step_00000001_rank_0000.vdi: No such file"
        );
        assert_eq!(without_dirs("nothing to cut"), "nothing to cut");
    }
}
