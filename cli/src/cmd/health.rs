//! `insitu health`: whether a daemon (generator-node, viz-node or tuner-node) serves, by the
//! standard gRPC health check (`grpc.health.v1`), for scripts that start daemons and must wait
//! for them (`deploy/slurm.sbatch`) and for people asking "is it up?".

use anyhow::{bail, Result};
use insitu_proto::health::{check, wait_serving, ServingStatus};
use insitu_proto::peer::Peer;
use std::time::Duration;

#[derive(clap::Args, Debug)]
pub struct Args {
    /// The daemon's gRPC address (host:port).
    addr: String,
    /// The service to ask about: "" (the default) for the whole daemon, or insitu.v1.Generator,
    /// insitu.v1.Viz, insitu.v1.Tuner.
    #[arg(long, default_value = "")]
    service: String,
    /// Wait up to SECS seconds for SERVING (a daemon still starting counts as not yet), checking
    /// every 0.1 s. Without it, one check, which gets 10 s to answer.
    #[arg(long, value_name = "SECS")]
    wait: Option<f64>,
    #[command(flatten)]
    tls: super::ClientTlsArgs,
}

/// How long one check without `--wait` waits for its answer.
const ONE_CHECK: Duration = Duration::from_secs(10);

/// Prints `SERVING` and succeeds, or fails saying what the daemon answered or why none did.
pub fn run(a: Args) -> Result<()> {
    let wait = match a.wait {
        Some(s) if s.is_finite() && (0.0..=86_400.0).contains(&s) => {
            Some(Duration::from_secs_f64(s))
        }
        Some(s) => bail!("--wait {s}: must be seconds in [0, 86400]"),
        None => None,
    };
    // The health service takes no token.
    let peer = Peer::new(&a.addr, None, a.tls.files().client()?, false)?;
    tokio::runtime::Runtime::new()?.block_on(async {
        match wait {
            Some(timeout) => {
                wait_serving(&peer, &a.service, timeout, Duration::from_millis(100)).await?
            }
            None => match tokio::time::timeout(ONE_CHECK, check(&peer, &a.service)).await {
                Ok(Ok(ServingStatus::Serving)) => {}
                Ok(Ok(other)) => bail!("{} answers {other}", peer.uri()),
                Ok(Err(e)) => return Err(e.into()),
                Err(_) => bail!(
                    "{} gave no answer within {} s",
                    peer.uri(),
                    ONE_CHECK.as_secs()
                ),
            },
        }
        println!("SERVING");
        Ok(())
    })
}
