//! A running tuner-node: the gRPC server, the engine task and the watcher of the viz-node's
//! quality reports.

use crate::config::Config;
use crate::config::ConfigError;
use crate::engine::{Engine, Event};
use crate::service::TunerService;
use crate::state::{State, StateError};
use insitu_proto::health::Health;
use insitu_proto::pb;
use insitu_proto::pb::tuner_server::TunerServer;
use insitu_proto::pb::viz_client::VizClient;
use insitu_proto::peer::{error_chain, Backoff, Peer};
use insitu_proto::security::{Security, SecurityError};
use insitu_tuner::live::Tracker;
use std::net::SocketAddr;
use std::sync::Arc;
use tokio::sync::oneshot;
use tokio::task::JoinHandle;
use tokio_stream::wrappers::TcpListenerStream;
use tracing::{info, warn};

/// Why a tuner-node did not start; each names the input at fault.
#[derive(Debug, thiserror::Error)]
pub enum StartError {
    /// The configuration.
    #[error(transparent)]
    Config(#[from] ConfigError),
    /// The token, TLS files or the viz-node's address.
    #[error(transparent)]
    Security(#[from] SecurityError),
    /// The state directory (the errors name the file).
    #[error(transparent)]
    State(#[from] StateError),
    /// The listening address.
    #[error("cannot listen on {addr}: {source}")]
    Listen {
        /// The address configured.
        addr: SocketAddr,
        /// Why.
        source: std::io::Error,
    },
}

/// A started tuner.
pub struct RunningTuner {
    addr: SocketAddr,
    engine: Arc<Engine>,
    health: Health,
    stop: oneshot::Sender<()>,
    server: JoinHandle<Result<(), tonic::transport::Error>>,
    tasks: Vec<JoinHandle<()>>,
}

/// Loads (or starts) the state, binds, and serves.
///
/// # Errors
/// [`StartError`]: a bad config, token or TLS file, a non-loopback address without a token,
/// an unreadable or unwritable state file, or a bind failure.
pub async fn start(cfg: Config) -> Result<RunningTuner, StartError> {
    let resolved = cfg.resolve()?;
    let security = Security::load(
        cfg.listen,
        cfg.token_file.as_deref(),
        &cfg.tls,
        cfg.insecure,
    )?;
    let mut watched = Vec::new();
    for addr in cfg.viz.iter().chain(&cfg.viz_shards) {
        watched.extend(security.peer_for("viz", Some(addr))?);
    }
    let state = match State::load(&cfg.state_dir)? {
        Some(s) => {
            info!(
                dir = %cfg.state_dir.display(),
                characteristic = ?s.tracker.step_indices(),
                trials = s.trials.len(),
                pm_version = s.current().map_or(0, |d| d.pm_version),
                "resuming from the persisted state"
            );
            s
        }
        None => {
            let s = State::new(Tracker::new(
                cfg.characteristic.threshold,
                cfg.characteristic.max,
            ));
            s.save(&cfg.state_dir)?;
            s
        }
    };
    let listen = |source| StartError::Listen {
        addr: cfg.listen,
        source,
    };
    let listener = tokio::net::TcpListener::bind(cfg.listen)
        .await
        .map_err(listen)?;
    let addr = listener.local_addr().map_err(listen)?;
    let (engine, events) = Engine::new(cfg, resolved, state, crate::tune::tune);
    let mut tasks = vec![tokio::spawn(engine.clone().run(events))];
    // Every shard's reports: each step's q comes from the shard that stored it.
    for viz in watched {
        tasks.push(tokio::spawn(watch(viz, engine.clone())));
    }
    let svc = tonic::service::interceptor::InterceptedService::new(
        TunerServer::new(TunerService(engine.clone())),
        security.require_token(),
    );
    let (health, health_svc) = Health::serving::<TunerServer<TunerService>>().await;
    let (stop, stopped) = oneshot::channel::<()>();
    let server = tokio::spawn(
        security
            .server()?
            .add_service(svc)
            .add_service(health_svc)
            .serve_with_incoming_shutdown(TcpListenerStream::new(listener), async {
                let _ = stopped.await;
            }),
    );
    info!(%addr, utility = %engine.utility(), "tuner-node listening");
    Ok(RunningTuner {
        addr,
        engine,
        health,
        stop,
        server,
        tasks,
    })
}

/// Subscribes to the viz-node's quality reports (reconnecting with back-off) and hands them
/// to the engine.
async fn watch(viz: Peer, engine: Arc<Engine>) {
    let uri = viz.uri().to_owned();
    let mut backoff = Backoff::new(Backoff::DEFAULT_MAX);
    loop {
        let r: Result<(), String> = async {
            let channel = viz.connect().await.map_err(|e| error_chain(&e))?;
            let mut client = VizClient::with_interceptor(channel, viz.auth());
            let mut stream = client
                .subscribe(pb::SubscribeRequest {})
                .await
                .map_err(|e| e.message().to_owned())?
                .into_inner();
            info!(%uri, "watching the viz-node's quality reports");
            backoff.reset();
            while let Some(r) = stream.message().await.map_err(|e| e.message().to_owned())? {
                engine.event(Event::Report(r)).await;
            }
            Err("the viz-node ended the report stream".into())
        }
        .await;
        if let Err(e) = r {
            warn!(%uri, error = %e, "viz-node reports unavailable; retrying");
        }
        backoff.wait().await;
    }
}

impl RunningTuner {
    /// The address served.
    pub fn local_addr(&self) -> SocketAddr {
        self.addr
    }

    /// The engine (status, decisions).
    pub fn engine(&self) -> &Arc<Engine> {
        &self.engine
    }

    /// Stops serving; the state is already on disk.
    pub async fn shutdown(self) {
        self.health.draining().await;
        self.engine
            .stopping
            .store(true, std::sync::atomic::Ordering::Relaxed);
        let _ = self.stop.send(());
        for t in &self.tasks {
            t.abort();
        }
        let _ = self.server.await;
    }
}
