//! A daemon's start and stop as all three do it: bind the configured address, serve its gRPC
//! service behind the token check beside the health service (`grpc.health.v1`), report
//! `NOT_SERVING` while it drains, and stop; and the compute backend, chosen off the runtime's
//! threads.

use crate::auth::RequireToken;
use crate::daemon::ConfigError;
use crate::health::Health;
use crate::security::{Security, SecurityError};
use insitu_core::backend::BackendError;
use insitu_core::{Backend, BackendChoice};
use std::convert::Infallible;
use std::net::SocketAddr;
use tokio::net::TcpListener;
use tokio::sync::oneshot;
use tokio::task::JoinHandle;
use tokio_stream::wrappers::TcpListenerStream;
use tonic::body::Body;
use tonic::codegen::http::{Request, Response};
use tonic::codegen::Service;
use tonic::server::NamedService;
use tonic::service::interceptor::InterceptedService;

/// Why a daemon could not start serving; each names the input at fault. Each daemon's own
/// start error wraps it beside what is its alone (a spool, a recording, a state file).
#[derive(Debug, thiserror::Error)]
pub enum ServeError {
    /// The configuration.
    #[error(transparent)]
    Config(#[from] ConfigError),
    /// The token, TLS files or a peer's address.
    #[error(transparent)]
    Security(#[from] SecurityError),
    /// A listening address (config key `key`).
    #[error("cannot listen on {addr} ({key}): {source}")]
    Listen {
        /// The config key (`listen`, `http_listen`).
        key: &'static str,
        /// The address configured.
        addr: SocketAddr,
        /// Why.
        source: std::io::Error,
    },
    /// The compute backend.
    #[error("backend {choice}: {source}")]
    Backend {
        /// The choice configured.
        choice: BackendChoice,
        /// Why.
        source: BackendError,
    },
    /// The backend's selection did not finish (it panicked).
    #[error("backend {choice}: its selection did not finish: {source}")]
    BackendTask {
        /// The choice configured.
        choice: BackendChoice,
        /// Why.
        source: tokio::task::JoinError,
    },
}

/// A listener on `addr` (config key `key`) and the address it got (the actual port when 0
/// was asked for).
///
/// # Errors
/// [`ServeError::Listen`] naming the key and the address.
pub async fn bind(
    key: &'static str,
    addr: SocketAddr,
) -> Result<(TcpListener, SocketAddr), ServeError> {
    let listen = |source| ServeError::Listen { key, addr, source };
    let listener = TcpListener::bind(addr).await.map_err(listen)?;
    let got = listener.local_addr().map_err(listen)?;
    Ok((listener, got))
}

/// The compute backend `choice` names (probing a GPU blocks, so it runs off the runtime's
/// threads).
///
/// # Errors
/// [`ServeError::Backend`] when none of the kind asked for is found,
/// [`ServeError::BackendTask`] when the probe panicked.
pub async fn select_backend(choice: BackendChoice) -> Result<Backend, ServeError> {
    tokio::task::spawn_blocking(move || Backend::select(choice))
        .await
        .map_err(|source| ServeError::BackendTask { choice, source })?
        .map_err(|source| ServeError::Backend { choice, source })
}

/// A daemon's gRPC server while it runs: its address, its health and the task serving.
pub struct Served {
    addr: SocketAddr,
    health: Health,
    stop: oneshot::Sender<()>,
    task: JoinHandle<Result<(), tonic::transport::Error>>,
}

impl Served {
    /// Serves `svc` (a generated server, configured by its daemon) on `listener` (bound to
    /// `addr`, as [`bind`] gives them) with `security`'s TLS, every call checked for its
    /// token, beside the health service, which reports `svc` as `SERVING`.
    ///
    /// # Errors
    /// [`ServeError::Security`] when the TLS configuration does not apply.
    pub async fn start<S>(
        (listener, addr): (TcpListener, SocketAddr),
        security: &Security,
        svc: S,
    ) -> Result<Self, ServeError>
    where
        S: Service<Request<Body>, Response = Response<Body>, Error = Infallible>
            + NamedService
            + Clone
            + Send
            + Sync
            + 'static,
        S::Future: Send + 'static,
    {
        let (health, health_svc) = Health::serving::<S>().await;
        let svc: InterceptedService<S, RequireToken> =
            InterceptedService::new(svc, security.require_token());
        let (stop, stopped) = oneshot::channel::<()>();
        let server = security
            .server()?
            .add_service(svc)
            .add_service(health_svc)
            .serve_with_incoming_shutdown(TcpListenerStream::new(listener), async {
                let _ = stopped.await;
            });
        Ok(Self {
            addr,
            health,
            stop,
            task: tokio::spawn(server),
        })
    }

    /// The address served.
    pub fn local_addr(&self) -> SocketAddr {
        self.addr
    }

    /// Reports `NOT_SERVING` (load balancers and `insitu health --wait` see the daemon
    /// leave) while calls still run.
    pub async fn draining(&self) {
        self.health.draining().await;
    }

    /// Stops accepting calls and waits for those in flight; a server that ended abnormally
    /// is logged.
    pub async fn stop(self) {
        let _ = self.stop.send(());
        match self.task.await {
            Ok(Ok(())) => {}
            Ok(Err(e)) => tracing::warn!(error = %e, "the gRPC server ended with an error"),
            Err(e) => tracing::warn!(error = %e, "the gRPC server's task ended abnormally"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A taken address comes back naming its key and the address; the CPU backend is always
    /// there.
    #[tokio::test]
    async fn a_taken_address_is_named_with_its_key_and_the_cpu_is_always_a_backend() {
        let (_held, addr) = bind("listen", SocketAddr::from(([127, 0, 0, 1], 0)))
            .await
            .unwrap();
        assert_ne!(addr.port(), 0, "the actual port");
        let Err(e) = bind("http_listen", addr).await else {
            panic!("a taken port was bound twice");
        };
        assert!(
            matches!(&e, ServeError::Listen { key: "http_listen", addr: a, .. } if *a == addr),
            "{e:?}"
        );
        assert!(e
            .to_string()
            .starts_with(&format!("cannot listen on {addr} (http_listen)")));
        assert!(select_backend(BackendChoice::Cpu).await.is_ok());
    }
}
