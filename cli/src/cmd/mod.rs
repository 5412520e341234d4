//! One module per subcommand.

pub mod accuracy;
pub mod cinema;
pub mod demo;
pub mod evaluate;
pub mod export;
pub mod generate;
pub mod health;
pub mod movie;
pub mod recover;
pub mod render;
pub mod replay;
pub mod series;
pub mod steer;
pub mod stored;
pub mod study;
pub mod tune;
pub mod view;

use anyhow::{bail, Context, Result};
use insitu_core::vdi::codec::Codec;

/// `--backend`, shared by every command that renders or generates.
#[derive(clap::Args, Debug, Clone, Copy)]
pub struct BackendArgs {
    /// Where DVR, VDI generation and VDI rendering run: cpu, gpu (any adapter, software ones
    /// such as lavapipe too) or auto (a hardware GPU when one is found, else the CPU).
    #[arg(long, default_value = "auto")]
    pub backend: insitu_core::BackendChoice,
}

impl BackendArgs {
    /// Opens the backend and says on stderr which one was chosen and why.
    pub fn open(&self) -> Result<insitu_core::Backend> {
        let (backend, why) = insitu_core::Backend::select_explained(self.backend)
            .with_context(|| format!("--backend {}", self.backend))?;
        eprintln!("{why}");
        Ok(backend)
    }
}

/// Client TLS flags for dialling a daemon (`replay --generator`, `health`).
#[derive(clap::Args, Debug, Clone, Default)]
pub struct ClientTlsArgs {
    /// CA certificate (PEM): connect over TLS and verify the daemon against it.
    #[arg(long)]
    pub tls_ca: Option<std::path::PathBuf>,
    /// Client certificate (PEM) for a daemon that requires mutual TLS (with --tls-key).
    #[arg(long, requires_all = ["tls_key", "tls_ca"])]
    pub tls_cert: Option<std::path::PathBuf>,
    /// The client certificate's private key (PEM).
    #[arg(long, requires = "tls_cert")]
    pub tls_key: Option<std::path::PathBuf>,
}

impl ClientTlsArgs {
    /// The files as the peers take them (no client authentication asked of others).
    pub fn files(&self) -> insitu_proto::tls::TlsFiles {
        insitu_proto::tls::TlsFiles {
            ca_file: self.tls_ca.clone(),
            cert_file: self.tls_cert.clone(),
            key_file: self.tls_key.clone(),
            client_auth: false,
        }
    }
}

/// `P_M = (r, γ, precision)` flags, shared by every command that makes one VDI.
#[derive(clap::Args, Debug, Clone, Copy)]
pub struct PmArgs {
    /// VDI resolution r (r × r rays).
    #[arg(long, default_value_t = 256)]
    pub r: u32,
    /// Interrupt threshold gamma.
    #[arg(long, default_value_t = 0.013, allow_negative_numbers = true)]
    pub gamma: f32,
    /// Precision of the VDI file: colour and opacity bits (4–16; format 4, depths to 1/16 of
    /// a ray-casting step), or f32 (lossless, format 3: the paper's sigma).
    #[arg(long, default_value = "8")]
    pub precision: insitu_core::Precision,
}

impl PmArgs {
    /// The validated `P_M`.
    pub fn params(&self) -> Result<insitu_core::VdiParams> {
        let p = insitu_core::VdiParams {
            resolution: self.r,
            gamma: self.gamma,
            precision: self.precision,
        };
        p.validate()?;
        Ok(p)
    }
}

/// `--repeat`'s report of the renders after the first: `, then M s (median of N)` with `M`
/// the median of `seconds`, or nothing when there were none.
pub fn warm_median(mut seconds: Vec<f64>) -> String {
    seconds.sort_by(f64::total_cmp);
    seconds
        .get(seconds.len() / 2)
        .map(|m| format!(", then {m:.3} s (median of {})", seconds.len()))
        .unwrap_or_default()
}

/// Parses `--size N` or `--size WxH`.
pub fn parse_size(s: &str) -> Result<(u32, u32)> {
    let parse = |p: &str| -> Result<u32> {
        match p.trim().parse::<u32>() {
            Ok(v) if (1..=16384).contains(&v) => Ok(v),
            _ => bail!("--size {s:?}: each side must be an integer in 1..=16384"),
        }
    };
    match s.split_once('x') {
        Some((w, h)) => Ok((parse(w)?, parse(h)?)),
        None => {
            let n = parse(s)?;
            Ok((n, n))
        }
    }
}

/// `--codec`'s value parser: a [`Codec`] by name (none, bzip2 or zstd), so a bad name is a
/// usage error before anything is loaded.
pub fn codec_arg(s: &str) -> Result<Codec, insitu_core::vdi::codec::CodecError> {
    s.parse()
}

/// q as JSON ([`insitu_core::metrics::Db`]): a number, or the string "inf" when the images
/// are identical.
pub fn q_json(q: f64) -> serde_json::Value {
    serde_json::to_value(insitu_core::metrics::Db(q)).unwrap_or(serde_json::Value::Null)
}

/// q as text: two decimals, or "inf" when the images are identical (NaN as "NaN").
pub fn q_text(q: f64) -> String {
    if q.is_finite() {
        format!("{q:.2}")
    } else {
        q.to_string()
    }
}

/// Parses `--views a,b,c` (degrees).
pub fn parse_views(s: &str) -> Result<Vec<f32>> {
    let views: Vec<f32> = s
        .split(',')
        .map(|v| v.trim().parse::<f32>())
        .collect::<Result<_, _>>()
        .with_context(|| format!("--views {s:?} is not a comma-separated list of degrees"))?;
    if views.is_empty() || views.iter().any(|v| !v.is_finite()) {
        bail!("--views {s:?} must hold finite angles");
    }
    Ok(views)
}
