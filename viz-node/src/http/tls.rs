//! HTTPS for the web viewer: the viz-node's own `[tls]` certificate and key (the ones its gRPC
//! port serves), with rustls on ring as everywhere else; with `client_auth`, browsers must show
//! a certificate signed by `ca_file`. Handshakes run in their own tasks (10 s at most), so a
//! slow or silent client never holds up the accept loop.

use axum::serve::Listener;
use insitu_proto::tls::TlsFiles;
use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, PrivateKeyDer};
use std::net::SocketAddr;
use std::path::Path;
use std::sync::Arc;
use std::time::Duration;
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::mpsc;
use tokio_rustls::server::TlsStream;
use tokio_rustls::TlsAcceptor;

/// Longest TLS handshake allowed.
const HANDSHAKE: Duration = Duration::from_secs(10);

/// Why the viewer cannot serve HTTPS; each names the file.
#[derive(Debug, thiserror::Error)]
pub enum HttpsError {
    /// A PEM file cannot be read or holds nothing usable.
    #[error("TLS {what} {path}: {problem}")]
    Pem {
        /// `certificate`, `key` or `CA`.
        what: &'static str,
        /// The file.
        path: String,
        /// Why.
        problem: String,
    },
    /// rustls refused the configuration (e.g. a key that does not match the certificate).
    #[error("TLS configuration: {0}")]
    Config(String),
}

fn pem_error(what: &'static str, path: &Path, problem: impl ToString) -> HttpsError {
    HttpsError::Pem {
        what,
        path: path.display().to_string(),
        problem: problem.to_string(),
    }
}

/// The rustls server configuration for `files` (`cert_file` and `key_file` set), HTTP/1.1.
///
/// # Errors
/// [`HttpsError`] naming the file or the problem.
pub fn server_config(files: &TlsFiles) -> Result<rustls::ServerConfig, HttpsError> {
    let (Some(cert), Some(key)) = (&files.cert_file, &files.key_file) else {
        return Err(HttpsError::Config(
            "HTTPS needs tls.cert_file and tls.key_file".into(),
        ));
    };
    let certs = CertificateDer::pem_file_iter(cert)
        .map_err(|e| pem_error("certificate", cert, e))?
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| pem_error("certificate", cert, e))?;
    if certs.is_empty() {
        return Err(pem_error("certificate", cert, "no CERTIFICATE block"));
    }
    let key = PrivateKeyDer::from_pem_file(key).map_err(|e| pem_error("key", key, e))?;
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let builder = rustls::ServerConfig::builder_with_provider(provider.clone())
        .with_safe_default_protocol_versions()
        .map_err(|e| HttpsError::Config(e.to_string()))?;
    let builder = if files.client_auth {
        let ca = files
            .ca_file
            .as_deref()
            .ok_or_else(|| HttpsError::Config("client_auth needs tls.ca_file".into()))?;
        let mut roots = rustls::RootCertStore::empty();
        for c in CertificateDer::pem_file_iter(ca).map_err(|e| pem_error("CA", ca, e))? {
            roots
                .add(c.map_err(|e| pem_error("CA", ca, e))?)
                .map_err(|e| pem_error("CA", ca, e))?;
        }
        let verifier =
            rustls::server::WebPkiClientVerifier::builder_with_provider(Arc::new(roots), provider)
                .build()
                .map_err(|e| HttpsError::Config(e.to_string()))?;
        builder.with_client_cert_verifier(verifier)
    } else {
        builder.with_no_client_auth()
    };
    let mut cfg = builder
        .with_single_cert(certs, key)
        .map_err(|e| HttpsError::Config(e.to_string()))?;
    cfg.alpn_protocols = vec![b"http/1.1".to_vec()];
    Ok(cfg)
}

/// A listener that yields connections after their TLS handshake.
pub struct TlsListener {
    accepted: mpsc::Receiver<(TlsStream<TcpStream>, SocketAddr)>,
    addr: SocketAddr,
}

impl TlsListener {
    /// Accepts on `listener` with `cfg`; the accept loop (and the bound socket) ends when this
    /// listener is dropped.
    ///
    /// # Errors
    /// When the listener has no local address.
    pub fn new(listener: TcpListener, cfg: rustls::ServerConfig) -> std::io::Result<Self> {
        let addr = listener.local_addr()?;
        let acceptor = TlsAcceptor::from(Arc::new(cfg));
        let (tx, accepted) = mpsc::channel(64);
        tokio::spawn(async move {
            loop {
                let accepted = tokio::select! {
                    a = listener.accept() => a,
                    () = tx.closed() => break,
                };
                let (tcp, peer) = match accepted {
                    Ok(x) => x,
                    Err(e) => {
                        tracing::debug!(error = %e, "accept");
                        tokio::time::sleep(Duration::from_millis(50)).await;
                        continue;
                    }
                };
                let _ = tcp.set_nodelay(true); // see `super::serve`
                let (acceptor, tx) = (acceptor.clone(), tx.clone());
                tokio::spawn(async move {
                    match tokio::time::timeout(HANDSHAKE, acceptor.accept(tcp)).await {
                        Ok(Ok(tls)) => {
                            let _ = tx.send((tls, peer)).await;
                        }
                        Ok(Err(e)) => tracing::debug!(%peer, error = %e, "TLS handshake failed"),
                        Err(_) => tracing::debug!(%peer, "TLS handshake timed out"),
                    }
                });
            }
        });
        Ok(Self { accepted, addr })
    }
}

impl Listener for TlsListener {
    type Io = TlsStream<TcpStream>;
    type Addr = SocketAddr;

    async fn accept(&mut self) -> (Self::Io, Self::Addr) {
        match self.accepted.recv().await {
            Some(x) => x,
            // The accept loop is gone (it never ends while this listener lives).
            None => std::future::pending().await,
        }
    }

    fn local_addr(&self) -> std::io::Result<Self::Addr> {
        Ok(self.addr)
    }
}
