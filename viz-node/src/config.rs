//! The viz-node's configuration: one TOML file (every key documented in
//! `deploy/viz-node.toml`), overridden by command-line flags.

use insitu_core::BackendChoice;
pub use insitu_proto::daemon::ConfigError;
use insitu_proto::daemon::{DaemonConfig, ServeKeys};
use insitu_proto::tls::TlsFiles;
use serde::{Deserialize, Serialize};
use std::net::SocketAddr;
use std::path::PathBuf;

/// The whole file.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Config {
    /// Address to serve on (port 0: ephemeral). Anything but loopback needs a token and TLS
    /// unless `insecure`.
    pub listen: SocketAddr,
    /// Allow a non-loopback `listen` without a token or TLS (logged as a warning at start).
    pub insecure: bool,
    /// `[tls]`: certificate, key, CA, mutual TLS.
    pub tls: TlsFiles,
    /// Where VDIs, reference frames and the index are recorded (created if missing).
    pub recording_dir: PathBuf,
    /// Serve the recording as a read-only archive: opened without writing anything (on
    /// read-only media, or owned by another user), viewer and `Render` served, every item
    /// shipped refused with `FAILED_PRECONDITION`, nothing scored or composed.
    pub read_only: bool,
    /// File holding the bearer token (else `INSITU_TOKEN`, if set).
    pub token_file: Option<PathBuf>,
    /// Largest VDI file accepted, bytes.
    pub max_vdi_bytes: u64,
    /// Largest set of reference frames accepted (one step and rank), bytes.
    pub max_reference_bytes: u64,
    /// Early-termination opacity when rendering VDIs.
    pub termination: f32,
    /// Reports kept for slow subscribers before the oldest are skipped.
    pub report_buffer: usize,
    /// Where VDIs are rendered: `cpu`, `gpu` or `auto` (a hardware GPU if found, else CPU).
    pub backend: BackendChoice,
    /// Scoring and composing jobs waiting at most; when full, storing waits (back-pressure to
    /// the generator-nodes' shippers) instead of growing memory.
    pub score_queue: usize,
    /// Memory for ranks' VDIs (and, apart, their reference frames) decoded on receipt and
    /// kept until the scorer or composer reads them, bytes per kind; beyond it the oldest are
    /// dropped and read from disk again when needed (0: always read from disk).
    pub keep_decoded_bytes: u64,
    /// `Render` calls served at once; more are refused with `RESOURCE_EXHAUSTED`.
    pub render_concurrency: usize,
    /// Largest image of one `Render` call, pixels (width × height).
    pub max_render_pixels: u64,
    /// Address of the web viewer and its JSON API (port 0: ephemeral); unset: no HTTP.
    /// Off loopback it needs a token, and since it serves plain HTTP also `insecure` (reach
    /// it through an SSH tunnel or a TLS proxy instead).
    pub http_listen: Option<SocketAddr>,
    /// Names (`viz.example.org`, a port is ignored) the viewer answers to besides IP
    /// addresses and `localhost`: a request whose `Host` or browser `Origin` is anything else is
    /// refused (DNS rebinding, other sites' pages).
    pub http_hosts: Vec<String>,
    /// Viewer connections open at once at most (page, API and sockets together); at the cap a
    /// new connection waits until one closes.
    pub http_max_connections: usize,
    /// Seconds a viewer request's head may take to arrive (a client trickling its headers is
    /// cut off).
    pub http_header_timeout_secs: f64,
    /// Seconds a viewer connection may sit with no request being answered and nothing read or
    /// written before it is closed (the live socket stays open while its page answers pings).
    pub http_idle_secs: f64,
    /// The tuner-node, `host:port`, whose budget the viewer's charts draw (dialled with the
    /// token and `[tls]` as any peer); unset: no budget lines.
    pub tuner: Option<String>,
    /// File holding the steering token (else `INSITU_STEER_TOKEN`, if set): what a page or
    /// script presents to steer the run through the tuner (`POST /api/steer`,
    /// docs/steering.md); it also lets its holder view. The viewing token alone cannot steer.
    /// Unset: steering is off. Needs `tuner`.
    pub steer_token_file: Option<PathBuf>,
    /// Seconds a step of several ranks waits for its last rank after its first arrived; then
    /// it is composed without the missing ranks and marked partial. Also how long the world's
    /// default TF waits for a rank's range before it is fixed without it.
    pub compose_timeout_secs: f64,
}

impl Default for Config {
    fn default() -> Self {
        Self {
            listen: SocketAddr::from(([127, 0, 0, 1], 50052)),
            insecure: false,
            tls: TlsFiles::default(),
            recording_dir: PathBuf::from("recording"),
            read_only: false,
            token_file: None,
            max_vdi_bytes: 2 << 30,
            max_reference_bytes: 2 << 30,
            termination: insitu_core::raycast::DEFAULT_TERMINATION,
            report_buffer: 1024,
            backend: BackendChoice::Auto,
            compose_timeout_secs: 60.0,
            score_queue: 256,
            keep_decoded_bytes: 512 << 20,
            render_concurrency: 2,
            max_render_pixels: 4096 * 4096,
            http_listen: None,
            http_hosts: Vec::new(),
            http_max_connections: crate::http::cap::DEFAULT_MAX_CONNECTIONS,
            http_header_timeout_secs: crate::http::conn::DEFAULT_HEADER_SECS,
            http_idle_secs: crate::http::conn::DEFAULT_IDLE_SECS,
            tuner: None,
            steer_token_file: None,
        }
    }
}

impl DaemonConfig for Config {
    fn serve(&self) -> ServeKeys<'_> {
        ServeKeys {
            listen: self.listen,
            insecure: self.insecure,
            tls: &self.tls,
            token_file: self.token_file.as_deref(),
        }
    }
    fn listen_mut(&mut self) -> &mut SocketAddr {
        &mut self.listen
    }
    fn token_file_mut(&mut self) -> &mut Option<PathBuf> {
        &mut self.token_file
    }
    /// Checks the values.
    ///
    /// # Errors
    /// [`ConfigError::Invalid`].
    fn validate(&self) -> Result<(), ConfigError> {
        if !(self.termination > 0.0 && self.termination <= 1.0) {
            return Err(ConfigError::Invalid {
                key: "termination",
                problem: format!("{} is outside (0, 1]", self.termination),
            });
        }
        if !(self.compose_timeout_secs.is_finite()
            && (0.0..=86_400.0).contains(&self.compose_timeout_secs))
        {
            return Err(ConfigError::Invalid {
                key: "compose_timeout_secs",
                problem: format!("{} is not seconds in [0, 86400]", self.compose_timeout_secs),
            });
        }
        for (key, secs) in [
            ("http_header_timeout_secs", self.http_header_timeout_secs),
            ("http_idle_secs", self.http_idle_secs),
        ] {
            if !(secs.is_finite() && secs > 0.0 && secs <= 86_400.0) {
                return Err(ConfigError::Invalid {
                    key,
                    problem: format!("{secs} is not seconds in (0, 86400]"),
                });
            }
        }
        if self.report_buffer == 0
            || self.max_vdi_bytes == 0
            || self.max_reference_bytes == 0
            || self.score_queue == 0
            || self.render_concurrency == 0
            || self.max_render_pixels == 0
            || self.http_max_connections == 0
        {
            return Err(ConfigError::Invalid {
                key: "report_buffer/max_vdi_bytes/max_reference_bytes/score_queue/render_concurrency/max_render_pixels/http_max_connections",
                problem: "must be ≥ 1".into(),
            });
        }
        Ok(())
    }
}

impl Config {
    /// The viewer's connection timeouts.
    pub fn http_timeouts(&self) -> crate::http::conn::Timeouts {
        crate::http::conn::Timeouts {
            header: std::time::Duration::from_secs_f64(self.http_header_timeout_secs),
            idle: std::time::Duration::from_secs_f64(self.http_idle_secs),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_documented_example_parses_and_matches_the_defaults() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../deploy/viz-node.toml");
        assert_eq!(Config::load(&path).unwrap(), Config::default());
        assert!(toml::from_str::<Config>("termination = 0.0")
            .unwrap()
            .validate()
            .is_err());
        assert!(toml::from_str::<Config>("recording = \"x\"").is_err());
    }
}
