//! What the daemons do the same way (feature `daemon`): their configuration ([`config`]:
//! the TOML file, the serving keys, the common flags), their start and stop ([`serve`]: bind,
//! serve with the token check and the health service, drain, stop; the compute backend), and
//! their process: logging to stderr, waiting for SIGINT/SIGTERM, `main`'s error exit.

pub mod config;
pub mod serve;

pub use config::{load_toml, CommonArgs, ConfigError, DaemonConfig, ServeKeys};
pub use serve::{bind, select_backend, ServeError, Served};

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
