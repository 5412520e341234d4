//! Bearer tokens.
//!
//! A daemon started with a token rejects every call whose `authorization` metadata is not
//! `Bearer <token>` with `UNAUTHENTICATED`. Listening on anything but loopback without a token
//! and TLS is refused by [`check_bind`] unless the config says `insecure = true`; dialling a
//! peer off loopback with a token but without TLS is refused by [`crate::peer::Peer::new`] on the
//! same terms.

use std::net::SocketAddr;
use std::path::Path;
use std::sync::Arc;
use tonic::metadata::MetadataValue;
use tonic::service::Interceptor;
use tonic::{Request, Status};

/// Environment variable a token is read from when no file is given.
pub const TOKEN_ENV: &str = "INSITU_TOKEN";

/// Errors reading a token or checking a bind address.
#[derive(Debug, thiserror::Error)]
pub enum AuthError {
    /// The token file could not be read.
    #[error("cannot read token file {path}: {source}")]
    Read {
        /// The file.
        path: std::path::PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// The token is empty or not printable ASCII.
    #[error("token from {0} is empty or contains characters other than printable ASCII")]
    Malformed(String),
    /// A non-loopback address without a token or without TLS.
    #[error("refusing to listen on {addr} without {missing}: off loopback every call needs a token ({TOKEN_ENV} or a token file) and TLS (tls.cert_file and tls.key_file); set insecure = true only on a network you trust")]
    Unprotected {
        /// The address.
        addr: SocketAddr,
        /// `a token`, `TLS` or `a token and TLS`.
        missing: &'static str,
    },
    /// A token would cross a non-loopback link in clear text.
    #[error("refusing to send the token in clear text to {0}: configure TLS (tls.ca_file, or an https:// address with a CA) or set insecure = true")]
    TokenInClear(String),
    /// An `https://` address without a CA to verify it against.
    #[error("{0} asks for TLS but no CA is configured (tls.ca_file)")]
    HttpsWithoutCa(String),
}

/// A shared secret, printable ASCII, never logged.
#[derive(Clone)]
pub struct Token(Arc<str>);

impl std::fmt::Debug for Token {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Token(***)")
    }
}

impl Token {
    /// Wraps `s` (surrounding whitespace trimmed).
    ///
    /// # Errors
    /// [`AuthError::Malformed`] when it is empty or not printable ASCII.
    pub fn new(s: &str, source: &str) -> Result<Self, AuthError> {
        let t = s.trim();
        if t.is_empty() || !t.bytes().all(|b| b.is_ascii_graphic()) {
            return Err(AuthError::Malformed(source.to_owned()));
        }
        Ok(Self(t.into()))
    }

    /// The token from `file` if given, else from [`TOKEN_ENV`] if set, else none.
    ///
    /// # Errors
    /// [`AuthError`] when the file cannot be read or the token is malformed.
    pub fn load(file: Option<&Path>) -> Result<Option<Self>, AuthError> {
        Self::load_or_env(file, TOKEN_ENV)
    }

    /// The token from `file` if given, else from the environment variable `env` if set, else
    /// none (e.g. a viz-node's steering token, docs/steering.md).
    ///
    /// # Errors
    /// [`AuthError`] when the file cannot be read or the token is malformed.
    pub fn load_or_env(file: Option<&Path>, env: &str) -> Result<Option<Self>, AuthError> {
        if let Some(path) = file {
            let s = std::fs::read_to_string(path).map_err(|source| AuthError::Read {
                path: path.to_owned(),
                source,
            })?;
            return Self::new(&s, &path.display().to_string()).map(Some);
        }
        match std::env::var(env) {
            Ok(s) => Self::new(&s, env).map(Some),
            Err(_) => Ok(None),
        }
    }

    /// Whether `given` is this token (compared in constant time).
    pub fn matches(&self, given: &str) -> bool {
        constant_time_eq(given.as_bytes(), self.0.as_bytes())
    }

    fn header(&self) -> String {
        format!("Bearer {}", self.0)
    }
}

/// Refuses a non-loopback `addr` without a token and TLS, unless `insecure` (then logs a
/// warning saying what is missing).
///
/// # Errors
/// [`AuthError::Unprotected`] naming what is missing.
pub fn check_bind(
    addr: SocketAddr,
    token: Option<&Token>,
    tls: bool,
    insecure: bool,
) -> Result<(), AuthError> {
    let missing = match (token.is_some(), tls) {
        _ if addr.ip().is_loopback() => return Ok(()),
        (true, true) => return Ok(()),
        (false, false) => "a token and TLS",
        (false, true) => "a token",
        (true, false) => "TLS",
    };
    if insecure {
        tracing::warn!(
            %addr,
            missing,
            "INSECURE: listening off loopback without {missing} because insecure = true; anyone who can reach {addr} can read or inject time steps"
        );
        Ok(())
    } else {
        Err(AuthError::Unprotected { addr, missing })
    }
}

/// Server side: checks the bearer token of every call (no token configured: lets all through).
#[derive(Clone, Debug, Default)]
pub struct RequireToken(Option<Token>);

impl RequireToken {
    /// Checks against `token`.
    pub fn new(token: Option<Token>) -> Self {
        Self(token)
    }
}

impl Interceptor for RequireToken {
    fn call(&mut self, req: Request<()>) -> Result<Request<()>, Status> {
        let Some(token) = &self.0 else {
            return Ok(req);
        };
        let given = req
            .metadata()
            .get("authorization")
            .and_then(|v| v.to_str().ok())
            .and_then(bearer);
        if given.is_some_and(|t| token.matches(t)) {
            Ok(req)
        } else {
            Err(Status::unauthenticated(
                "missing or wrong bearer token in the `authorization` metadata",
            ))
        }
    }
}

/// Client side: attaches the bearer token to every call.
#[derive(Clone, Debug, Default)]
pub struct AttachToken(Option<MetadataValue<tonic::metadata::Ascii>>);

impl AttachToken {
    /// Attaches `token` (none: attaches nothing).
    pub fn new(token: Option<&Token>) -> Self {
        // A Token is printable ASCII by construction, so the parse cannot fail.
        Self(token.and_then(|t| t.header().parse().ok()))
    }
}

impl Interceptor for AttachToken {
    fn call(&mut self, mut req: Request<()>) -> Result<Request<()>, Status> {
        if let Some(v) = &self.0 {
            req.metadata_mut().insert("authorization", v.clone());
        }
        Ok(req)
    }
}

/// The token of an `Authorization` value `Bearer <token>`; the scheme's name in any case
/// (RFC 7235: schemes are case-insensitive), then one or more spaces. `None` for any other
/// scheme or no token.
pub fn bearer(value: &str) -> Option<&str> {
    let (scheme, token) = value.split_once(' ')?;
    let token = token.trim_start_matches(' ');
    (scheme.eq_ignore_ascii_case("bearer") && !token.is_empty()).then_some(token)
}

fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

#[cfg(test)]
mod tests {
    use super::*;

    fn with_auth(v: Option<&str>) -> Request<()> {
        let mut r = Request::new(());
        if let Some(v) = v {
            r.metadata_mut().insert("authorization", v.parse().unwrap());
        }
        r
    }

    #[test]
    fn tokens_are_checked() {
        let t = Token::new(" s3cret\n", "test").unwrap();
        let mut need = RequireToken::new(Some(t.clone()));
        assert!(need.call(with_auth(Some("Bearer s3cret"))).is_ok());
        // The scheme's name in any case (RFC 7235), and more than one space after it.
        assert!(need.call(with_auth(Some("bearer s3cret"))).is_ok());
        assert!(need.call(with_auth(Some("BEARER  s3cret"))).is_ok());
        assert!(need.call(with_auth(Some("Basic s3cret"))).is_err());
        assert!(need.call(with_auth(Some("Bearer"))).is_err());
        assert!(need.call(with_auth(Some("s3cret"))).is_err());
        for bad in [
            None,
            Some("Bearer s3cre"),
            Some("Bearer s3cret2"),
            Some("s3cret"),
        ] {
            let e = need.call(with_auth(bad)).unwrap_err();
            assert_eq!(e.code(), tonic::Code::Unauthenticated, "{bad:?}");
        }
        let attached = AttachToken::new(Some(&t)).call(Request::new(())).unwrap();
        assert!(need.call(attached).is_ok());
        assert!(RequireToken::new(None).call(with_auth(None)).is_ok());
        assert!(Token::new("  ", "x").is_err());
        assert!(Token::new("a b", "x").is_err());
    }

    #[test]
    fn non_loopback_needs_a_token_and_tls() {
        let t = Token::new("x", "t").unwrap();
        let any: SocketAddr = "0.0.0.0:1".parse().unwrap();
        assert!(check_bind("127.0.0.1:1".parse().unwrap(), None, false, false).is_ok());
        assert!(check_bind("[::1]:1".parse().unwrap(), None, false, false).is_ok());
        for (token, tls, missing) in [
            (None, false, "a token and TLS"),
            (None, true, "a token"),
            (Some(&t), false, "TLS"),
        ] {
            match check_bind(any, token, tls, false) {
                Err(AuthError::Unprotected { missing: m, .. }) => assert_eq!(m, missing),
                other => panic!("{other:?}"),
            }
            assert!(check_bind(any, token, tls, true).is_ok(), "insecure = true");
        }
        assert!(check_bind(any, Some(&t), true, false).is_ok());
    }
}
