//! A running viz-node: the gRPC server and the scoring task.

use crate::config::Config;
use crate::http::tls::HttpsError;
use crate::http::Http;
use crate::scene::SceneAgreement;
use crate::service::{scorer, Shared, VizService};
use insitu_proto::auth::{check_bind, AuthError};
use insitu_proto::daemon::{bind, select_backend, DaemonConfig, ServeError, Served};
use insitu_proto::pb::viz_server::VizServer;
use insitu_proto::security::Security;
use insitu_proto::transport;
use insitu_recording::decoded::Kept;
use insitu_recording::store::Recording;
use insitu_recording::store::StoreError;
use std::collections::HashSet;
use std::net::SocketAddr;
use std::sync::atomic::AtomicU64;
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::sync::{broadcast, mpsc, oneshot};
use tokio::task::JoinHandle;
use tracing::info;

/// The environment variable that holds the steering token when `steer_token_file` is unset.
pub const STEER_TOKEN_ENV: &str = "INSITU_STEER_TOKEN";

/// Why a viz-node did not start; each names the input at fault.
#[derive(Debug, thiserror::Error)]
pub enum StartError {
    /// The configuration, the token, TLS files or a peer's address, the compute backend, a
    /// listening address (`listen`, or `http_listen` for the web viewer).
    #[error(transparent)]
    Serve(#[from] ServeError),
    /// The recording directory, its index or its scene (the errors name the file).
    #[error("recording: {0}")]
    Recording(#[from] StoreError),
    /// The web viewer's HTTPS configuration.
    #[error("http_listen: {0}")]
    Https(#[from] HttpsError),
    /// The steering token (`steer_token_file` or [`STEER_TOKEN_ENV`]).
    #[error("steer_token_file: {0}")]
    SteerToken(AuthError),
    /// The web viewer's address without the token or TLS it needs off loopback.
    #[error("http_listen {addr}: {source}")]
    HttpBind {
        /// The address configured.
        addr: SocketAddr,
        /// Why.
        source: AuthError,
    },
}

/// A started viz-node.
pub struct RunningViz {
    shared: Arc<Shared>,
    served: Served,
    http: Option<HttpParts>,
}

/// The web viewer: its address and URL, state, stop signal and server task.
struct HttpParts {
    addr: SocketAddr,
    url: String,
    http: Arc<Http>,
    stop: oneshot::Sender<()>,
    server: JoinHandle<std::io::Result<()>>,
}

/// Opens the recording, binds, and serves.
///
/// # Errors
/// [`StartError`]: a bad config, token or TLS file, a non-loopback address without a token,
/// a corrupt index, no backend, or a bind failure.
pub async fn start(cfg: Config) -> Result<RunningViz, StartError> {
    cfg.validate().map_err(ServeError::from)?;
    let security = cfg.serve().security().map_err(ServeError::from)?;
    let recording = if cfg.read_only {
        Recording::open_read_only(&cfg.recording_dir)?
    } else {
        Recording::open(&cfg.recording_dir)?
    };
    let scene = SceneAgreement::open(
        &cfg.recording_dir,
        Duration::from_secs_f64(cfg.compose_timeout_secs),
    )?;
    let backend = select_backend(cfg.backend).await?;
    tracing::info!("rendering on {}", backend.describe());
    let bound = bind("listen", cfg.listen).await?;
    // An archive is served as it is: nothing tidied, scored or composed.
    let recovery = if cfg.read_only {
        insitu_recording::store::Recovery::default()
    } else {
        recording.recover()?
    };
    let (to_score, score_rx) = mpsc::channel(cfg.score_queue);
    let shared = Arc::new(Shared {
        recording,
        reports: broadcast::channel(cfg.report_buffer).0,
        to_score,
        renders: Arc::new(tokio::sync::Semaphore::new(cfg.render_concurrency)),
        max_render_pixels: cfg.max_render_pixels,
        scene,
        compose_timeout: Duration::from_secs_f64(cfg.compose_timeout_secs),
        timers: Mutex::new(HashSet::new()),
        steps_composed: AtomicU64::new(0),
        steps_partial: AtomicU64::new(0),
        compose_errors: AtomicU64::new(0),
        max_vdi_bytes: cfg.max_vdi_bytes,
        max_reference_bytes: cfg.max_reference_bytes,
        termination: cfg.termination,
        backend,
        kept: Kept::new(cfg.keep_decoded_bytes),
        vdis_stored: AtomicU64::new(0),
        references_stored: AtomicU64::new(0),
        reports_sent: AtomicU64::new(0),
        rejected: AtomicU64::new(0),
        read_only: cfg.read_only,
        faces: Default::default(),
    });
    tokio::spawn(scorer(shared.clone(), score_rx));
    resume(&shared, recovery);
    let svc = VizServer::new(VizService(shared.clone()))
        .max_decoding_message_size(transport::MAX_MESSAGE_BYTES)
        .max_encoding_message_size(transport::MAX_MESSAGE_BYTES);
    let served = Served::start(bound, &security, svc).await?;
    info!(addr = %served.local_addr(), tls = security.serves_tls(), recording = %cfg.recording_dir.display(), "viz-node listening");
    let http = match cfg.http_listen {
        Some(at) => Some(start_http(at, &cfg, &security, shared.clone()).await?),
        None => None,
    };
    Ok(RunningViz {
        shared,
        served,
        http,
    })
}

/// Binds and serves the web viewer ([`crate::http`]).
async fn start_http(
    at: SocketAddr,
    cfg: &Config,
    security: &Security,
    shared: Arc<Shared>,
) -> Result<HttpParts, StartError> {
    // HTTPS with the gRPC side's certificate when it has one; off loopback as for gRPC.
    let tls = cfg
        .tls
        .serves()
        .then(|| crate::http::tls::server_config(&cfg.tls))
        .transpose()?;
    check_bind(at, security.token(), tls.is_some(), cfg.insecure)
        .map_err(|source| StartError::HttpBind { addr: at, source })?;
    let (listener, addr) = bind("http_listen", at).await?;
    let steer_token =
        insitu_proto::auth::Token::load_or_env(cfg.steer_token_file.as_deref(), STEER_TOKEN_ENV)
            .map_err(StartError::SteerToken)?;
    let http = Arc::new(
        Http::new(
            shared,
            security.token().cloned(),
            cfg.render_concurrency,
            &cfg.http_hosts,
            cfg.http_timeouts().idle,
        )
        .steering(steer_token),
    );
    if let Some(peer) = security
        .peer_for("tuner", cfg.tuner.as_deref())
        .map_err(ServeError::from)?
    {
        http.watch_tuner(peer);
    }
    let (stop, stopped) = oneshot::channel::<()>();
    let scheme = if tls.is_some() { "https" } else { "http" };
    let max = cfg.http_max_connections;
    let server = tokio::spawn(crate::http::serve(
        listener,
        tls,
        http.clone(),
        max,
        cfg.http_timeouts(),
        async {
            let _ = stopped.await;
        },
    ));
    let url = format!("{scheme}://{addr}/");
    info!(%addr, "web viewer on {url}");
    Ok(HttpParts {
        addr,
        url,
        http,
        stop,
        server,
    })
}

/// Logs what the recording's recovery found and queues the work a crash interrupted: scoring
/// of steps stored without q, composition of multi-rank steps not composed (now when complete,
/// else after the timeout).
fn resume(shared: &Arc<Shared>, r: insitu_recording::store::Recovery) {
    if !r.temp_removed.is_empty() {
        info!(files = ?r.temp_removed, "removed temporary files left by an interrupted write");
    }
    if !r.files_without_rows.is_empty() {
        tracing::warn!(files = ?r.files_without_rows, "payload files that no index row names (kept; stored before a crash, not acknowledged)");
    }
    if !r.rows_without_files.is_empty() {
        tracing::warn!(files = ?r.rows_without_files, "index rows whose files are missing (kept; restore the files or they will not render)");
    }
    if r.unscored.is_empty() && r.uncomposed.is_empty() {
        return;
    }
    info!(
        unscored = r.unscored.len(),
        uncomposed = r.uncomposed.len(),
        "resuming scoring and composing interrupted by a stop"
    );
    let tx = shared.to_score.clone();
    tokio::spawn(async move {
        for (step, rank) in r.unscored {
            let _ = tx.send(crate::service::Job::Score(step, rank)).await;
        }
        for step in r.uncomposed {
            let _ = tx
                .send(crate::service::Job::Compose {
                    step,
                    partial_ok: true,
                })
                .await;
        }
    });
}

impl RunningViz {
    /// The address served (the actual port when 0 was asked for).
    pub fn local_addr(&self) -> SocketAddr {
        self.served.local_addr()
    }

    /// The web viewer's address, when `http_listen` is set.
    pub fn http_addr(&self) -> Option<SocketAddr> {
        self.http.as_ref().map(|h| h.addr)
    }

    /// The web viewer's URL (`https://` when it serves TLS).
    pub fn viewer_url(&self) -> Option<&str> {
        self.http.as_ref().map(|h| h.url.as_str())
    }

    /// The web viewer's state (none without `http_listen`).
    pub fn http(&self) -> Option<&Arc<Http>> {
        self.http.as_ref().map(|h| &h.http)
    }

    /// Shared state (recording, counters).
    pub fn shared(&self) -> &Arc<Shared> {
        &self.shared
    }

    /// Stops serving after in-flight calls finish.
    pub async fn shutdown(self) {
        self.served.draining().await;
        let http = self.http.map(|h| {
            let _ = h.stop.send(());
            h.server
        });
        self.served.stop().await;
        if let Some(server) = http {
            // Open sockets keep a graceful shutdown waiting; the page reconnects to a new node.
            server.abort();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A recording directory that is a file, and a taken web-viewer port, come back as their
    /// own variants, naming the path or the address and key.
    #[tokio::test]
    async fn start_errors_name_the_input_at_fault() {
        let dir = tempfile::tempdir().unwrap();
        let cpu = |recording_dir| Config {
            backend: insitu_core::BackendChoice::Cpu,
            listen: SocketAddr::from(([127, 0, 0, 1], 0)),
            recording_dir,
            ..Config::default()
        };
        let file = dir.path().join("not-a-dir");
        std::fs::write(&file, b"x").unwrap();
        let Err(err) = start(cpu(file.clone())).await else {
            panic!("a file as recording started");
        };
        assert!(matches!(err, StartError::Recording(_)), "{err:?}");
        assert!(err.to_string().contains("not-a-dir"), "{err}");

        let taken = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let addr = taken.local_addr().unwrap();
        let cfg = Config {
            http_listen: Some(addr),
            ..cpu(dir.path().join("rec"))
        };
        let Err(err) = start(cfg).await else {
            panic!("a taken port started");
        };
        assert!(
            matches!(&err, StartError::Serve(ServeError::Listen { key: "http_listen", addr: a, .. }) if *a == addr),
            "{err:?}"
        );
    }
}
