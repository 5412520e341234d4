//! A peer this process dials (a generator-node, viz-node or tuner): its address, the bearer
//! token sent with every call, and TLS.

use crate::auth::{AttachToken, AuthError, Token};
use crate::transport;
use std::net::IpAddr;
use tonic::transport::{Channel, ClientTlsConfig, Endpoint};

/// Where and how to call a peer. Cheap to clone.
#[derive(Clone, Debug)]
pub struct Peer {
    uri: String,
    token: Option<Token>,
    tls: Option<ClientTlsConfig>,
}

impl Peer {
    /// A peer at `addr` (`host:port`, `http://host:port` or `https://host:port`).
    ///
    /// With `tls`, the link is TLS (`https://`) whatever scheme `addr` names, and the peer's
    /// certificate must name the host dialled. Without it, the link is clear text.
    ///
    /// # Errors
    /// [`AuthError::HttpsWithoutCa`] for an `https://` address without `tls`;
    /// [`AuthError::TokenInClear`] when `token` would travel in clear text to a host that is
    /// not loopback, unless `insecure`.
    pub fn new(
        addr: &str,
        token: Option<Token>,
        tls: Option<ClientTlsConfig>,
        insecure: bool,
    ) -> Result<Self, AuthError> {
        let rest = addr.split_once("://").map_or(addr, |(_, r)| r);
        let uri = match &tls {
            Some(_) => format!("https://{rest}"),
            None if addr.starts_with("https://") => {
                return Err(AuthError::HttpsWithoutCa(addr.to_owned()))
            }
            None => transport::uri(addr),
        };
        if tls.is_none() && token.is_some() && !insecure && !is_loopback_host(rest) {
            return Err(AuthError::TokenInClear(addr.to_owned()));
        }
        Ok(Self { uri, token, tls })
    }

    /// The URI dialled (`http://…` or `https://…`).
    pub fn uri(&self) -> &str {
        &self.uri
    }

    /// Whether the link is TLS.
    pub fn is_tls(&self) -> bool {
        self.tls.is_some()
    }

    /// The endpoint, with the transport's windows and TLS applied; not yet connected.
    ///
    /// # Errors
    /// When the URI is invalid or the TLS settings cannot be applied.
    pub fn endpoint(&self) -> Result<Endpoint, tonic::transport::Error> {
        let e = transport::endpoint(&self.uri)?;
        match &self.tls {
            Some(tls) => e.tls_config(tls.clone()),
            None => Ok(e),
        }
    }

    /// Connects now (the TLS handshake included).
    ///
    /// # Errors
    /// As [`Peer::endpoint`], or when nothing answers, or the handshake fails (e.g. the
    /// certificate is not signed by the CA or does not name the host).
    pub async fn connect(&self) -> Result<Channel, tonic::transport::Error> {
        self.endpoint()?.connect().await
    }

    /// The interceptor that attaches the token to every call.
    pub fn auth(&self) -> AttachToken {
        AttachToken::new(self.token.as_ref())
    }
}

/// Exponential back-off between attempts at something that may come back (a peer that is
/// away or restarting, a disk that is full): the first wait is [`Backoff::FIRST`], each next
/// one twice the last, never more than the cap. Every retry loop of the daemons uses it.
#[derive(Clone, Debug)]
pub struct Backoff {
    next: std::time::Duration,
    max: std::time::Duration,
}

impl Backoff {
    /// The first wait after a failure.
    pub const FIRST: std::time::Duration = std::time::Duration::from_millis(100);
    /// The cap where a daemon has no `max_backoff_secs` setting.
    pub const DEFAULT_MAX: std::time::Duration = std::time::Duration::from_secs(5);

    /// Back-off from [`Backoff::FIRST`] up to `max` (at least `FIRST`).
    pub fn new(max: std::time::Duration) -> Self {
        Self {
            next: Self::FIRST,
            max: max.max(Self::FIRST),
        }
    }

    /// The wait before the next attempt; the one after it doubles, up to the cap.
    pub fn next_delay(&mut self) -> std::time::Duration {
        let d = self.next;
        self.next = (self.next * 2).min(self.max);
        d
    }

    /// Sleeps [`Backoff::next_delay`] on the tokio timer.
    pub async fn wait(&mut self) {
        tokio::time::sleep(self.next_delay()).await;
    }

    /// After a success: the next failure waits [`Backoff::FIRST`] again.
    pub fn reset(&mut self) {
        self.next = Self::FIRST;
    }
}

/// Whether a call's failure may go away by trying again: the peer is away or restarting, or
/// its disk is full (`RESOURCE_EXHAUSTED`, which the viz-node returns only for that on the
/// calls that store: the item waits until there is room, like a step while the viz-node is
/// away). Anything else is a refusal that retrying cannot fix.
pub fn is_transient(code: tonic::Code) -> bool {
    use tonic::Code;
    matches!(
        code,
        Code::Unavailable
            | Code::Unknown
            | Code::Cancelled
            | Code::DeadlineExceeded
            | Code::Aborted
            | Code::ResourceExhausted
    )
}

/// `e` and its sources, joined by `: ` (tonic's transport errors say only "transport error"
/// at the top; the cause, e.g. a refused certificate, is further down), each said once
/// ([`error_messages`]).
pub fn error_chain(e: &dyn std::error::Error) -> String {
    error_messages(e).join(": ")
}

/// The messages of `e` and its sources, top first, without the sources that the message
/// before them already ends with: most of the workspace's errors say their cause inline
/// (`"spool /x: permission denied"`) and also hand it on as their source, which a printer of
/// the whole chain would otherwise say twice.
pub fn error_messages(e: &dyn std::error::Error) -> Vec<String> {
    let mut messages = vec![e.to_string()];
    let mut last = e.to_string();
    let mut next = e.source();
    while let Some(cause) = next {
        let message = cause.to_string();
        if !last.ends_with(&message) {
            messages.push(message.clone());
        }
        last = message;
        next = cause.source();
    }
    messages
}

/// Whether `authority` (`host:port`, possibly with a path) names a loopback host.
fn is_loopback_host(authority: &str) -> bool {
    let hostport = authority.split('/').next().unwrap_or("");
    let host = if let Some(v6) = hostport.strip_prefix('[') {
        v6.split(']').next().unwrap_or("")
    } else {
        hostport.rsplit_once(':').map_or(hostport, |(h, _)| h)
    };
    host.eq_ignore_ascii_case("localhost")
        || host.parse::<IpAddr>().is_ok_and(|ip| ip.is_loopback())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn backoff_doubles_to_its_cap_and_resets() {
        use std::time::Duration;
        let mut b = Backoff::new(Duration::from_millis(500));
        let waits: Vec<u128> = (0..5).map(|_| b.next_delay().as_millis()).collect();
        assert_eq!(waits, [100, 200, 400, 500, 500]);
        b.reset();
        assert_eq!(b.next_delay(), Backoff::FIRST);
        // A cap below the first wait is raised to it.
        let mut tiny = Backoff::new(Duration::from_millis(1));
        assert_eq!(tiny.next_delay(), Backoff::FIRST);
        assert_eq!(tiny.next_delay(), Backoff::FIRST);
    }

    #[test]
    fn only_what_may_come_back_is_transient() {
        use tonic::Code;
        assert!(is_transient(Code::Unavailable));
        assert!(is_transient(Code::ResourceExhausted));
        assert!(!is_transient(Code::InvalidArgument));
        assert!(!is_transient(Code::PermissionDenied));
        assert!(!is_transient(Code::Unauthenticated));
    }

    #[derive(Debug, thiserror::Error)]
    enum Outer {
        #[error("spool /x: {source}")]
        Inline { source: std::io::Error },
        #[error("transport error")]
        Apart { source: std::io::Error },
        #[error("config: {source}")]
        Nested { source: Box<Outer> },
    }

    /// A cause said inline is not said again; one said only as a source is.
    #[test]
    fn each_cause_is_said_once() {
        let io = || std::io::Error::new(std::io::ErrorKind::PermissionDenied, "permission denied");
        let inline = Outer::Inline { source: io() };
        assert_eq!(error_messages(&inline), ["spool /x: permission denied"]);
        assert_eq!(error_chain(&inline), "spool /x: permission denied");
        let apart = Outer::Apart { source: io() };
        assert_eq!(error_chain(&apart), "transport error: permission denied");
        let nested = Outer::Nested {
            source: Box::new(Outer::Apart { source: io() }),
        };
        assert_eq!(
            error_messages(&nested),
            ["config: transport error", "permission denied"]
        );
    }

    #[test]
    fn tokens_never_travel_in_clear_off_loopback() {
        let t = Token::new("s", "t").unwrap();
        for local in [
            "127.0.0.1:1",
            "http://127.0.0.1:1",
            "[::1]:1",
            "localhost:9",
        ] {
            let p = Peer::new(local, Some(t.clone()), None, false).unwrap();
            assert!(p.uri().starts_with("http://") && !p.is_tls(), "{local}");
        }
        for remote in ["10.0.0.7:1", "http://node12:50052", "[2001:db8::1]:5"] {
            assert!(
                matches!(
                    Peer::new(remote, Some(t.clone()), None, false),
                    Err(AuthError::TokenInClear(_))
                ),
                "{remote}"
            );
            assert!(
                Peer::new(remote, Some(t.clone()), None, true).is_ok(),
                "insecure"
            );
            assert!(
                Peer::new(remote, None, None, false).is_ok(),
                "no secret to leak"
            );
        }
        let tls = ClientTlsConfig::new();
        let p = Peer::new("http://node12:50052", Some(t), Some(tls), false).unwrap();
        assert_eq!(p.uri(), "https://node12:50052");
        assert!(matches!(
            Peer::new("https://node12:1", None, None, false),
            Err(AuthError::HttpsWithoutCa(_))
        ));
    }
}
