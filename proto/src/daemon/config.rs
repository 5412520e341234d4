//! A daemon's configuration: its TOML file read with errors that name the file or key, the
//! keys every daemon has for serving ([`ServeKeys`]), and the flags every daemon takes
//! ([`CommonArgs`]) laid over the file.

use crate::security::{Security, SecurityError};
use crate::tls::TlsFiles;
use serde::de::DeserializeOwned;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};

/// Errors loading a configuration; each names the file or key.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// The file could not be read.
    #[error("cannot read config {path}: {source}")]
    Read {
        /// The file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// Not valid TOML for the schema (unknown keys included).
    #[error("config {path}: {source}")]
    Parse {
        /// The file.
        path: PathBuf,
        /// Why.
        source: toml::de::Error,
    },
    /// A value out of range.
    #[error("config key {key}: {problem}")]
    Invalid {
        /// Dotted key.
        key: &'static str,
        /// What is wrong.
        problem: String,
    },
}

/// Reads a TOML file into `T`.
///
/// # Errors
/// [`ConfigError::Read`] or [`ConfigError::Parse`], naming the file.
pub fn load_toml<T: DeserializeOwned>(path: &Path) -> Result<T, ConfigError> {
    let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read {
        path: path.to_owned(),
        source,
    })?;
    toml::from_str(&text).map_err(|source| ConfigError::Parse {
        path: path.to_owned(),
        source,
    })
}

/// The flags every daemon takes, flattened into its own (`#[command(flatten)]`).
#[derive(clap::Args, Debug)]
pub struct CommonArgs {
    /// TOML config file (where its keys are documented: see the end of this help).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Address to serve on (port 0: ephemeral; the chosen one is printed).
    #[arg(long)]
    pub listen: Option<SocketAddr>,
    /// File holding the bearer token (else INSITU_TOKEN).
    #[arg(long)]
    pub token_file: Option<PathBuf>,
}

/// The keys every daemon's file has for serving, as one daemon's config holds them (each
/// config declares them at the top level of its file, where they are documented with the
/// daemon's defaults).
#[derive(Clone, Copy, Debug)]
pub struct ServeKeys<'a> {
    /// `listen`: the address to serve on (port 0: ephemeral).
    pub listen: SocketAddr,
    /// `insecure`: allow a non-loopback `listen` without a token or TLS (and the token sent in
    /// clear text to the peers the daemon dials).
    pub insecure: bool,
    /// `[tls]`: certificate, key, CA, mutual TLS.
    pub tls: &'a TlsFiles,
    /// `token_file`: the bearer token's file (else `INSITU_TOKEN`).
    pub token_file: Option<&'a Path>,
}

impl ServeKeys<'_> {
    /// The token, TLS and `insecure` setting the daemon serves and dials with.
    ///
    /// # Errors
    /// [`SecurityError`]: an unreadable token or TLS file, or a non-loopback `listen` without
    /// a token and TLS unless `insecure`.
    pub fn security(&self) -> Result<Security, SecurityError> {
        Security::load(self.listen, self.token_file, self.tls, self.insecure)
    }
}

/// A daemon's configuration: read from its TOML file ([`DaemonConfig::load`]), laid under
/// [`CommonArgs`], checked as a whole.
pub trait DaemonConfig: Default + DeserializeOwned {
    /// Its serving keys.
    fn serve(&self) -> ServeKeys<'_>;
    /// The address to serve on, for `--listen`.
    fn listen_mut(&mut self) -> &mut SocketAddr;
    /// The token file, for `--token-file`.
    fn token_file_mut(&mut self) -> &mut Option<PathBuf>;
    /// Checks the values.
    ///
    /// # Errors
    /// [`ConfigError::Invalid`] naming the first bad key.
    fn validate(&self) -> Result<(), ConfigError>;

    /// Reads and checks a TOML file.
    ///
    /// # Errors
    /// [`ConfigError`] naming the file or key.
    fn load(path: &Path) -> Result<Self, ConfigError> {
        let cfg: Self = load_toml(path)?;
        cfg.validate()?;
        Ok(cfg)
    }
}

impl CommonArgs {
    /// The `--config` file's configuration (else the defaults) with `--listen` and
    /// `--token-file` applied. Not yet checked: the daemon applies its own flags, then
    /// checks the whole.
    ///
    /// # Errors
    /// [`ConfigError::Read`] or [`ConfigError::Parse`], naming the file.
    pub fn config<C: DaemonConfig>(&self) -> Result<C, ConfigError> {
        let mut c = match &self.config {
            Some(path) => load_toml(path)?,
            None => C::default(),
        };
        if let Some(listen) = self.listen {
            *c.listen_mut() = listen;
        }
        if self.token_file.is_some() {
            c.token_file_mut().clone_from(&self.token_file);
        }
        Ok(c)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Default, serde::Deserialize, Debug, PartialEq)]
    #[serde(default, deny_unknown_fields)]
    struct Cfg {
        listen: Option<SocketAddr>,
        token_file: Option<PathBuf>,
        tls: TlsFiles,
        other: u32,
    }

    impl DaemonConfig for Cfg {
        fn serve(&self) -> ServeKeys<'_> {
            ServeKeys {
                listen: self.listen.unwrap_or(SocketAddr::from(([127, 0, 0, 1], 1))),
                insecure: false,
                tls: &self.tls,
                token_file: self.token_file.as_deref(),
            }
        }
        fn validate(&self) -> Result<(), ConfigError> {
            Ok(())
        }
        fn listen_mut(&mut self) -> &mut SocketAddr {
            self.listen
                .get_or_insert(SocketAddr::from(([127, 0, 0, 1], 1)))
        }
        fn token_file_mut(&mut self) -> &mut Option<PathBuf> {
            &mut self.token_file
        }
    }

    #[derive(Parser)]
    struct Flags {
        #[command(flatten)]
        common: CommonArgs,
    }

    fn parse(args: &[&str]) -> CommonArgs {
        Flags::parse_from(std::iter::once("daemon").chain(args.iter().copied())).common
    }

    /// The file's values, replaced by the flags that are given and kept where none is; no
    /// file: the defaults; a bad file: an error naming it.
    #[test]
    fn flags_override_the_file_and_only_where_given() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("d.toml");
        std::fs::write(
            &file,
            "listen = \"127.0.0.1:7000\"\ntoken_file = \"/from/file\"\nother = 5\n",
        )
        .unwrap();
        let f = file.to_str().unwrap();
        let c: Cfg = parse(&["--config", f]).config().unwrap();
        assert_eq!(c.listen, Some(SocketAddr::from(([127, 0, 0, 1], 7000))));
        assert_eq!(c.token_file.as_deref(), Some(Path::new("/from/file")));
        assert_eq!(c.other, 5);
        let c: Cfg = parse(&[
            "--config",
            f,
            "--listen",
            "0.0.0.0:9",
            "--token-file",
            "/flag",
        ])
        .config()
        .unwrap();
        assert_eq!(c.listen, Some(SocketAddr::from(([0, 0, 0, 0], 9))));
        assert_eq!(c.token_file.as_deref(), Some(Path::new("/flag")));
        assert_eq!(c.other, 5);
        assert_eq!(parse(&[]).config::<Cfg>().unwrap(), Cfg::default());
        std::fs::write(&file, "unknown = 1\n").unwrap();
        let err = parse(&["--config", f]).config::<Cfg>().unwrap_err();
        assert!(
            matches!(&err, ConfigError::Parse { path, .. } if *path == file),
            "{err}"
        );
    }
}
