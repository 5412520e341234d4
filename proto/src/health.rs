//! gRPC health checking (`grpc.health.v1.Health`, the protocol that Kubernetes' gRPC probes,
//! `grpc_health_probe` and load balancers speak) for the daemons, and a probe for scripts.
//!
//! Each daemon adds the health service beside its own once it is ready to take calls, so both
//! the whole server (service `""`) and its named service (e.g. `insitu.v1.Generator`) answer
//! `SERVING` from the first connection on. When the daemon starts to shut down,
//! [`Health::draining`] turns both to `NOT_SERVING` (a watcher sees that, then its stream
//! ends), before the daemon stops taking connections and drains.
//!
//! The health service takes no token: it tells only whether a daemon serves, and probes from
//! orchestrators carry none. Every other service of a daemon still requires one off loopback.

use crate::peer::{error_chain, Peer};
use std::time::Duration;
use tonic::server::NamedService;
use tonic_health::pb::health_check_response::ServingStatus as Wire;
use tonic_health::pb::health_client::HealthClient;
use tonic_health::pb::health_server::{Health as HealthRpc, HealthServer};
use tonic_health::pb::HealthCheckRequest;
use tonic_health::server::HealthReporter;
pub use tonic_health::ServingStatus;

/// A daemon's health as its health service reports it.
#[derive(Clone, Debug)]
pub struct Health {
    reporter: HealthReporter,
    service: &'static str,
}

impl Health {
    /// `SERVING` for the whole server and for service `S`, and the health service to add to
    /// the daemon's server (without the token interceptor).
    pub async fn serving<S: NamedService>() -> (Self, HealthServer<impl HealthRpc>) {
        let (reporter, server) = tonic_health::server::health_reporter();
        reporter.set_serving::<S>().await;
        let health = Self {
            reporter,
            service: S::NAME,
        };
        (health, server)
    }

    /// The daemon's service name (`insitu.v1.Generator`, …).
    pub fn service(&self) -> &'static str {
        self.service
    }

    /// `NOT_SERVING` for the whole server and the service, then their watch streams end, so
    /// that a probe's open `Watch` does not hold up the server's graceful shutdown. Checks
    /// after this (on a connection opened before the shutdown) answer `NOT_FOUND`.
    pub async fn draining(&self) {
        let mut reporter = self.reporter.clone();
        for name in ["", self.service] {
            reporter
                .set_service_status(name, ServingStatus::NotServing)
                .await;
        }
        for name in ["", self.service] {
            reporter.clear_service_status(name).await;
        }
    }
}

/// Why a probe got no `SERVING`; each names the address.
#[derive(Debug, thiserror::Error)]
pub enum ProbeError {
    /// Nothing answered at the address (or the TLS handshake failed).
    #[error("no daemon answers at {addr}: {reason}")]
    Connect {
        /// The address dialled.
        addr: String,
        /// The transport's error chain.
        reason: String,
    },
    /// The daemon does not know the service asked about.
    #[error("{addr} reports no service named {service:?} (its services: \"\" for the whole daemon, insitu.v1.Generator, insitu.v1.Viz or insitu.v1.Tuner)")]
    UnknownService {
        /// The address.
        addr: String,
        /// The service asked about.
        service: String,
    },
    /// The call failed otherwise (e.g. a daemon without a health service).
    #[error("health check at {addr} failed: {status}")]
    Call {
        /// The address.
        addr: String,
        /// The gRPC status.
        status: tonic::Status,
    },
    /// Still not `SERVING` when the wait ended.
    #[error("{addr} was not SERVING within {secs} s (last: {last})")]
    Timeout {
        /// The address.
        addr: String,
        /// How long the probe waited, seconds.
        secs: f64,
        /// The last answer or error.
        last: String,
    },
}

/// One health check of `service` (`""`: the whole daemon) at `peer`.
///
/// # Errors
/// [`ProbeError::Connect`], [`ProbeError::UnknownService`] or [`ProbeError::Call`].
pub async fn check(peer: &Peer, service: &str) -> Result<ServingStatus, ProbeError> {
    let addr = peer.uri().to_owned();
    let channel = peer.connect().await.map_err(|e| ProbeError::Connect {
        addr: addr.clone(),
        reason: error_chain(&e),
    })?;
    let mut client = HealthClient::with_interceptor(channel, peer.auth());
    let request = HealthCheckRequest {
        service: service.to_owned(),
    };
    match client.check(request).await {
        Ok(reply) => Ok(match reply.into_inner().status() {
            Wire::Serving => ServingStatus::Serving,
            Wire::NotServing => ServingStatus::NotServing,
            Wire::Unknown | Wire::ServiceUnknown => ServingStatus::Unknown,
        }),
        Err(status) if status.code() == tonic::Code::NotFound => Err(ProbeError::UnknownService {
            addr,
            service: service.to_owned(),
        }),
        Err(status) => Err(ProbeError::Call { addr, status }),
    }
}

/// Checks `service` at `peer` every `interval` until it is `SERVING` or `timeout` has passed
/// (a daemon still starting refuses connections: that counts as not yet). Each check is bounded
/// by what is left of `timeout`: a server that never answers (e.g. one that refused this
/// client's certificate after a TLS 1.3 handshake the client saw complete) ends the wait on
/// time.
///
/// # Errors
/// [`ProbeError::Timeout`] with the last answer; [`ProbeError::UnknownService`] at once (a
/// daemon's services are all there from its first connection on).
pub async fn wait_serving(
    peer: &Peer,
    service: &str,
    timeout: Duration,
    interval: Duration,
) -> Result<(), ProbeError> {
    let deadline = tokio::time::Instant::now() + timeout;
    loop {
        let last = match tokio::time::timeout_at(deadline, check(peer, service)).await {
            Ok(Ok(ServingStatus::Serving)) => return Ok(()),
            Ok(Ok(other)) => format!("{other}"),
            Ok(Err(e @ ProbeError::UnknownService { .. })) => return Err(e),
            Ok(Err(e)) => e.to_string(),
            Err(_) => "no answer".to_owned(),
        };
        if tokio::time::Instant::now() + interval > deadline {
            return Err(ProbeError::Timeout {
                addr: peer.uri().to_owned(),
                secs: timeout.as_secs_f64(),
                last,
            });
        }
        tokio::time::sleep(interval).await;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tokio_stream::wrappers::TcpListenerStream;
    use tokio_stream::StreamExt;

    /// Serves a health service on `listener` until the sender is dropped.
    async fn serve(
        listener: tokio::net::TcpListener,
    ) -> (Health, Peer, tokio::sync::oneshot::Sender<()>) {
        let addr = listener.local_addr().unwrap();
        let (health, service) = Health::serving::<NamedOnly>().await;
        let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
        tokio::spawn(
            tonic::transport::Server::builder()
                .add_service(service)
                .serve_with_incoming_shutdown(TcpListenerStream::new(listener), async {
                    let _ = stopped.await;
                }),
        );
        let peer = Peer::new(&addr.to_string(), None, None, false).unwrap();
        (health, peer, stop)
    }

    /// A port that was free a moment ago.
    fn free_port() -> u16 {
        let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        l.local_addr().unwrap().port()
    }

    /// A stand-in for a daemon's service: only its name matters here.
    struct NamedOnly;
    impl NamedService for NamedOnly {
        const NAME: &'static str = crate::pb::generator_server::SERVICE_NAME;
    }

    #[tokio::test]
    async fn serving_then_draining_ends_the_watchers() {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let (health, peer, stop) = serve(listener).await;
        assert_eq!(health.service(), "insitu.v1.Generator");
        for service in ["", "insitu.v1.Generator"] {
            assert_eq!(check(&peer, service).await.unwrap(), ServingStatus::Serving);
        }
        let err = check(&peer, "insitu.v1.Nothing").await.unwrap_err();
        assert!(matches!(err, ProbeError::UnknownService { .. }), "{err}");
        assert!(err.to_string().contains("insitu.v1.Nothing"), "{err}");

        let mut client = HealthClient::new(peer.connect().await.unwrap());
        let mut watch = client
            .watch(HealthCheckRequest {
                service: String::new(),
            })
            .await
            .unwrap()
            .into_inner();
        let first = watch.next().await.unwrap().unwrap();
        assert_eq!(first.status(), Wire::Serving);
        health.draining().await;
        let second = watch.next().await.unwrap().unwrap();
        assert_eq!(second.status(), Wire::NotServing);
        // The stream ends, so the graceful shutdown below does not wait for the watcher.
        let end = tokio::time::timeout(Duration::from_secs(5), watch.next()).await;
        assert!(matches!(end, Ok(None)), "{end:?}");
        drop(stop);
    }

    #[tokio::test]
    async fn waiting_for_nothing_times_out_naming_the_address() {
        // Nothing answers there.
        let port = free_port();
        let peer = Peer::new(&format!("127.0.0.1:{port}"), None, None, false).unwrap();
        let err = wait_serving(
            &peer,
            "",
            Duration::from_millis(300),
            Duration::from_millis(50),
        )
        .await
        .unwrap_err();
        let text = err.to_string();
        assert!(matches!(err, ProbeError::Timeout { .. }), "{text}");
        assert!(text.contains(&port.to_string()), "{text}");
        assert!(text.contains("no daemon answers"), "{text}");
    }

    #[tokio::test]
    async fn a_server_that_never_answers_ends_the_wait_on_time() {
        // Takes the connection and says nothing, as a server does that refused a TLS 1.3
        // client's certificate after the client saw its handshake complete.
        let listener = tokio::net::TcpListener::bind(("127.0.0.1", 0))
            .await
            .unwrap();
        let port = listener.local_addr().unwrap().port();
        let silent = tokio::spawn(async move {
            let mut held = Vec::new();
            while let Ok((socket, _)) = listener.accept().await {
                held.push(socket);
            }
        });
        let peer = Peer::new(&format!("127.0.0.1:{port}"), None, None, false).unwrap();
        let wait = wait_serving(
            &peer,
            "",
            Duration::from_millis(300),
            Duration::from_millis(50),
        );
        let err = tokio::time::timeout(Duration::from_secs(10), wait)
            .await
            .expect("the wait ends by its own timeout")
            .unwrap_err();
        let text = err.to_string();
        assert!(matches!(err, ProbeError::Timeout { .. }), "{text}");
        assert!(text.contains("no answer"), "{text}");
        silent.abort();
    }

    #[tokio::test]
    async fn waiting_for_a_daemon_that_comes_up_later_succeeds() {
        let port = free_port();
        let peer = Peer::new(&format!("127.0.0.1:{port}"), None, None, false).unwrap();
        let late = tokio::spawn(async move {
            tokio::time::sleep(Duration::from_millis(300)).await;
            let listener = tokio::net::TcpListener::bind(("127.0.0.1", port))
                .await
                .unwrap();
            serve(listener).await
        });
        wait_serving(
            &peer,
            "insitu.v1.Generator",
            Duration::from_secs(10),
            Duration::from_millis(50),
        )
        .await
        .unwrap();
        drop(late.await.unwrap());
    }
}
