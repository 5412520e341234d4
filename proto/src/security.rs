//! A daemon's `token_file`, `[tls]` and `insecure` keys, resolved once at start and used for
//! both sides of its links: the server it runs and the peers it dials.

use crate::auth::{check_bind, AuthError, RequireToken, Token};
use crate::peer::Peer;
use crate::tls::{TlsError, TlsFiles};
use crate::transport;
use std::net::SocketAddr;
use std::path::Path;
use tonic::transport::{ClientTlsConfig, Server, ServerTlsConfig};

/// Errors resolving a daemon's security settings.
#[derive(Debug, thiserror::Error)]
pub enum SecurityError {
    /// Token or bind rule.
    #[error(transparent)]
    Auth(#[from] AuthError),
    /// TLS files.
    #[error(transparent)]
    Tls(#[from] TlsError),
    /// A peer address in the config that cannot be dialled as configured.
    #[error("{key} = {addr:?}: {source}")]
    Peer {
        /// The config key.
        key: &'static str,
        /// Its value.
        addr: String,
        /// Why.
        source: AuthError,
    },
    /// rustls refused the certificate or key.
    #[error("TLS certificate or key rejected: {0}")]
    Rejected(tonic::transport::Error),
}

/// Token and TLS of one daemon.
#[derive(Clone, Debug)]
pub struct Security {
    token: Option<Token>,
    server_tls: Option<ServerTlsConfig>,
    client_tls: Option<ClientTlsConfig>,
    insecure: bool,
}

impl Security {
    /// Loads the token (`token_file`, else `INSITU_TOKEN`) and the TLS files, and checks that
    /// `listen` is allowed: off loopback, a token and TLS are required unless `insecure`
    /// ([`check_bind`]).
    ///
    /// # Errors
    /// [`SecurityError`] naming the file, the key or what an off-loopback bind lacks.
    pub fn load(
        listen: SocketAddr,
        token_file: Option<&Path>,
        tls: &TlsFiles,
        insecure: bool,
    ) -> Result<Self, SecurityError> {
        let token = Token::load(token_file)?;
        let server_tls = tls.server()?;
        let client_tls = tls.client()?;
        check_bind(listen, token.as_ref(), server_tls.is_some(), insecure)?;
        Ok(Self {
            token,
            server_tls,
            client_tls,
            insecure,
        })
    }

    /// The token, if any.
    pub fn token(&self) -> Option<&Token> {
        self.token.as_ref()
    }

    /// Whether the server side is TLS.
    pub fn serves_tls(&self) -> bool {
        self.server_tls.is_some()
    }

    /// A server builder (the transport's windows) with TLS when configured.
    ///
    /// # Errors
    /// [`SecurityError::Rejected`] when rustls cannot use the certificate or key.
    pub fn server(&self) -> Result<Server, SecurityError> {
        let s = transport::server();
        match &self.server_tls {
            Some(tls) => s.tls_config(tls.clone()).map_err(SecurityError::Rejected),
            None => Ok(s),
        }
    }

    /// The interceptor checking callers' tokens.
    pub fn require_token(&self) -> RequireToken {
        RequireToken::new(self.token.clone())
    }

    /// [`Security::peer`] for the config key `key` when it is set.
    ///
    /// # Errors
    /// [`SecurityError::Peer`] naming the key and its value.
    pub fn peer_for(
        &self,
        key: &'static str,
        addr: Option<&str>,
    ) -> Result<Option<Peer>, SecurityError> {
        addr.map(|a| {
            self.peer(a).map_err(|source| SecurityError::Peer {
                key,
                addr: a.to_owned(),
                source,
            })
        })
        .transpose()
    }

    /// A peer at `addr`, dialled with this daemon's token, over TLS when `tls.ca_file` is set.
    ///
    /// # Errors
    /// As [`Peer::new`].
    pub fn peer(&self, addr: &str) -> Result<Peer, AuthError> {
        Peer::new(
            addr,
            self.token.clone(),
            self.client_tls.clone(),
            self.insecure,
        )
    }
}
