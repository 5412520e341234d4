//! What the daemons do the same way (feature `daemon`): logging to stderr, waiting for
//! SIGINT/SIGTERM, reading a TOML config file with errors that name the file, and the flags
//! they all take ([`CommonArgs`]).

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

/// A daemon's configuration, as far as [`CommonArgs`] sets it.
pub trait DaemonConfig: Default + DeserializeOwned {
    /// The address to serve on.
    fn listen_mut(&mut self) -> &mut SocketAddr;
    /// The token file.
    fn token_file_mut(&mut self) -> &mut Option<PathBuf>;
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

/// Logs to stderr at `RUST_LOG` or `info` (coloured only on a terminal).
pub fn init_tracing() {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .with_writer(std::io::stderr)
        // Colours only on a terminal: logs redirected to files stay plain text.
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .init();
}

/// Resolves on SIGINT (Ctrl-C) or SIGTERM.
pub async fn shutdown_signal() {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{signal, SignalKind};
        if let Ok(mut term) = signal(SignalKind::terminate()) {
            tokio::select! {
                _ = tokio::signal::ctrl_c() => {}
                _ = term.recv() => {}
            }
            return;
        }
    }
    let _ = tokio::signal::ctrl_c().await;
}

/// Runs a daemon's `main` on a multi-threaded tokio runtime: prints its error chain and exits
/// non-zero on failure (also when the runtime cannot be started).
pub fn run_main(
    main: impl std::future::Future<Output = anyhow::Result<()>>,
) -> std::process::ExitCode {
    init_tracing();
    let result = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .map_err(anyhow::Error::from)
        .and_then(|rt| rt.block_on(main));
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {}", crate::peer::error_chain(e.as_ref()));
            std::process::ExitCode::FAILURE
        }
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
        other: u32,
    }

    impl DaemonConfig for Cfg {
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
