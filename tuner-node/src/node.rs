//! A running tuner-node: the gRPC server, the engine task and the watcher of the viz-node's
//! quality reports.

use crate::config::Config;
use crate::engine::{Engine, Event};
use crate::service::TunerService;
use crate::state::{State, StateError};
use insitu_proto::daemon::{bind, DaemonConfig, ServeError, Served};
use insitu_proto::pb;
use insitu_proto::pb::tuner_server::TunerServer;
use insitu_proto::pb::viz_client::VizClient;
use insitu_proto::peer::{error_chain, Backoff, Peer};
use insitu_tuner::live::Tracker;
use std::net::SocketAddr;
use std::sync::Arc;
use tokio::task::JoinHandle;
use tracing::{info, warn};

/// Why a tuner-node did not start; each names the input at fault.
#[derive(Debug, thiserror::Error)]
pub enum StartError {
    /// The configuration, the token, TLS files or the viz-node's address, the listening
    /// address.
    #[error(transparent)]
    Serve(#[from] ServeError),
    /// The state directory (the errors name the file).
    #[error(transparent)]
    State(#[from] StateError),
}

/// A started tuner.
pub struct RunningTuner {
    engine: Arc<Engine>,
    served: Served,
    tasks: Vec<JoinHandle<()>>,
}

/// Loads (or starts) the state, binds, and serves.
///
/// # Errors
/// [`StartError`]: a bad config, token or TLS file, a non-loopback address without a token,
/// an unreadable or unwritable state file, or a bind failure.
pub async fn start(cfg: Config) -> Result<RunningTuner, StartError> {
    let resolved = cfg.resolve().map_err(ServeError::from)?;
    let security = cfg.serve().security().map_err(ServeError::from)?;
    let mut watched = Vec::new();
    for addr in cfg.viz.iter().chain(&cfg.viz_shards) {
        watched.extend(
            security
                .peer_for("viz", Some(addr))
                .map_err(ServeError::from)?,
        );
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
    let bound = bind("listen", cfg.listen).await?;
    let (engine, events) = Engine::new(cfg, resolved, state, crate::tune::tune);
    let mut tasks = vec![tokio::spawn(engine.clone().run(events))];
    // Every shard's reports: each step's q comes from the shard that stored it.
    for viz in watched {
        tasks.push(tokio::spawn(watch(viz, engine.clone())));
    }
    let served = Served::start(
        bound,
        &security,
        TunerServer::new(TunerService(engine.clone())),
    )
    .await?;
    info!(addr = %served.local_addr(), utility = %engine.utility_description(), "tuner-node listening");
    Ok(RunningTuner {
        engine,
        served,
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
        self.served.local_addr()
    }

    /// The engine (status, decisions).
    pub fn engine(&self) -> &Arc<Engine> {
        &self.engine
    }

    /// Stops serving; the state is already on disk.
    pub async fn shutdown(self) {
        self.served.draining().await;
        self.engine
            .stopping
            .store(true, std::sync::atomic::Ordering::Relaxed);
        for t in &self.tasks {
            t.abort();
        }
        self.served.stop().await;
    }
}
