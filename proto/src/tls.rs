//! TLS for every gRPC link: rustls through tonic, certificates and keys as
//! PEM files, optional mutual TLS.
//!
//! One [`TlsFiles`] per daemon (the `[tls]` table of its TOML) serves two roles: with
//! `cert_file` and `key_file` the daemon serves TLS on its `listen` address; with `ca_file` it
//! dials its peers (viz-node, tuner) over TLS and verifies their certificates against that CA,
//! presenting its own certificate when a peer asks for one (mutual TLS). `client_auth`
//! makes the server require such a client certificate, signed by `ca_file`.
//!
//! Peers are verified by the host name or IP address they are dialled at, which must be in
//! the certificate's subject alternative names.

use std::path::{Path, PathBuf};
use tonic::transport::{Certificate, ClientTlsConfig, Identity, ServerTlsConfig};

/// Errors loading TLS material; each names the file or the key.
#[derive(Debug, thiserror::Error)]
pub enum TlsError {
    /// A file could not be read.
    #[error("cannot read TLS {what} {path}: {source}")]
    Read {
        /// Which file (`certificate`, `key`, `CA`).
        what: &'static str,
        /// The file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// A file holds no PEM block of the expected kind.
    #[error("TLS {what} {path} is not PEM (no `-----BEGIN {label}` block)")]
    NotPem {
        /// Which file.
        what: &'static str,
        /// The file.
        path: PathBuf,
        /// The PEM label looked for.
        label: &'static str,
    },
    /// Keys that make sense only together, or a setting that needs another.
    #[error("TLS settings: {0}")]
    Incomplete(&'static str),
}

/// The `[tls]` table of a daemon's config (all paths PEM).
#[derive(Clone, Debug, Default, PartialEq)]
#[cfg_attr(
    feature = "daemon",
    derive(serde::Serialize, serde::Deserialize),
    serde(deny_unknown_fields, default)
)]
pub struct TlsFiles {
    /// This daemon's certificate chain, leaf first. With `key_file`: TLS on `listen`, and the
    /// client certificate shown to peers that require mutual TLS.
    pub cert_file: Option<PathBuf>,
    /// The private key of `cert_file` (PKCS#8, PKCS#1 or SEC1).
    pub key_file: Option<PathBuf>,
    /// The CA that signed the peers' certificates. Set: peers this daemon dials are reached
    /// over TLS and verified against it (and, with `client_auth`, so are its clients).
    pub ca_file: Option<PathBuf>,
    /// Mutual TLS: refuse clients without a certificate signed by `ca_file`.
    pub client_auth: bool,
}

impl TlsFiles {
    /// Whether the daemon serves TLS (`cert_file` and `key_file` set).
    pub fn serves(&self) -> bool {
        self.cert_file.is_some() && self.key_file.is_some()
    }

    /// The server side: `None` without `cert_file`/`key_file`.
    ///
    /// # Errors
    /// [`TlsError`]: one of `cert_file`/`key_file` without the other, `client_auth` without
    /// `ca_file`, or a file that cannot be read or is not PEM.
    pub fn server(&self) -> Result<Option<ServerTlsConfig>, TlsError> {
        let identity = self.identity()?;
        let Some(identity) = identity else {
            if self.client_auth {
                return Err(TlsError::Incomplete(
                    "client_auth needs cert_file and key_file (the server's own certificate)",
                ));
            }
            return Ok(None);
        };
        let mut cfg = ServerTlsConfig::new().identity(identity);
        if self.client_auth {
            let ca = self.ca_file.as_deref().ok_or(TlsError::Incomplete(
                "client_auth needs ca_file (the CA clients' certificates are checked against)",
            ))?;
            cfg = cfg.client_ca_root(ca_certificate(ca)?);
        }
        Ok(Some(cfg))
    }

    /// The dialling side: `None` without `ca_file`; with `cert_file`/`key_file`, they are the
    /// client certificate for mutual TLS.
    ///
    /// # Errors
    /// As [`TlsFiles::server`].
    pub fn client(&self) -> Result<Option<ClientTlsConfig>, TlsError> {
        let identity = self.identity()?;
        let Some(ca) = self.ca_file.as_deref() else {
            return Ok(None);
        };
        let mut cfg = ClientTlsConfig::new().ca_certificate(ca_certificate(ca)?);
        if let Some(id) = identity {
            cfg = cfg.identity(id);
        }
        Ok(Some(cfg))
    }

    fn identity(&self) -> Result<Option<Identity>, TlsError> {
        match (&self.cert_file, &self.key_file) {
            (None, None) => Ok(None),
            (Some(c), Some(k)) => {
                let cert = read_pem(c, "certificate", &["CERTIFICATE"])?;
                let key = read_pem(
                    k,
                    "key",
                    &["PRIVATE KEY", "RSA PRIVATE KEY", "EC PRIVATE KEY"],
                )?;
                Ok(Some(Identity::from_pem(cert, key)))
            }
            _ => Err(TlsError::Incomplete(
                "cert_file and key_file must be set together",
            )),
        }
    }
}

fn ca_certificate(path: &Path) -> Result<Certificate, TlsError> {
    Ok(Certificate::from_pem(read_pem(
        path,
        "CA",
        &["CERTIFICATE"],
    )?))
}

/// Reads `path` and checks that it holds a PEM block with one of `labels` (the contents are
/// parsed by rustls when the link is made; its errors name the problem).
fn read_pem(path: &Path, what: &'static str, labels: &[&'static str]) -> Result<Vec<u8>, TlsError> {
    let bytes = std::fs::read(path).map_err(|source| TlsError::Read {
        what,
        path: path.to_owned(),
        source,
    })?;
    let text = String::from_utf8_lossy(&bytes);
    if !labels
        .iter()
        .any(|l| text.contains(&format!("-----BEGIN {l}-----")))
    {
        return Err(TlsError::NotPem {
            what,
            path: path.to_owned(),
            label: labels[0],
        });
    }
    Ok(bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn file(dir: &Path, name: &str, text: &str) -> PathBuf {
        let p = dir.join(name);
        std::fs::write(&p, text).unwrap();
        p
    }

    #[test]
    fn settings_are_checked_and_files_named() {
        let dir = tempfile::tempdir().unwrap();
        let cert = file(
            dir.path(),
            "c.pem",
            "-----BEGIN CERTIFICATE-----\nAA==\n-----END CERTIFICATE-----\n",
        );
        let key = file(
            dir.path(),
            "k.pem",
            "-----BEGIN PRIVATE KEY-----\nAA==\n-----END PRIVATE KEY-----\n",
        );
        let junk = file(dir.path(), "junk.pem", "hello");
        let none = TlsFiles::default();
        assert!(none.server().unwrap().is_none() && none.client().unwrap().is_none());
        assert!(!none.serves());

        let half = TlsFiles {
            cert_file: Some(cert.clone()),
            ..TlsFiles::default()
        };
        assert!(matches!(half.server(), Err(TlsError::Incomplete(_))));

        let serving = TlsFiles {
            cert_file: Some(cert.clone()),
            key_file: Some(key.clone()),
            ..TlsFiles::default()
        };
        assert!(serving.serves() && serving.server().unwrap().is_some());
        assert!(
            serving.client().unwrap().is_none(),
            "no CA: peers are dialled in clear"
        );

        let mtls_no_ca = TlsFiles {
            client_auth: true,
            ..serving.clone()
        };
        assert!(
            matches!(mtls_no_ca.server(), Err(TlsError::Incomplete(m)) if m.contains("ca_file"))
        );

        let bad_ca = TlsFiles {
            ca_file: Some(junk.clone()),
            ..TlsFiles::default()
        };
        let e = bad_ca.client().unwrap_err().to_string();
        assert!(e.contains("junk.pem") && e.contains("not PEM"), "{e}");

        let missing = TlsFiles {
            ca_file: Some(dir.path().join("nope.pem")),
            ..TlsFiles::default()
        };
        assert!(missing
            .client()
            .unwrap_err()
            .to_string()
            .contains("nope.pem"));

        let key_as_cert = TlsFiles {
            cert_file: Some(key.clone()),
            key_file: Some(key),
            ..TlsFiles::default()
        };
        assert!(matches!(
            key_as_cert.server(),
            Err(TlsError::NotPem {
                what: "certificate",
                ..
            })
        ));
    }
}
