//! One scene per world, the generator-node's side (docs/conventions.md, "A world of ranks"): with no transfer
//! function configured, each rank's first step reports its brick's value range to the
//! viz-node (`AgreeScene`) as soon as it is received, before it is queued, and the worker
//! waits for the world's answer before it generates. Reporting at receipt, not in the worker,
//! matters when several ranks share a node: the worker holds one rank's step while the
//! others are still in the queue, and they must have reported for the answer to come.

use crate::ingest::RawStep;
use insitu_core::NamedTf;
use insitu_proto::convert::tf_field;
use insitu_proto::pb;
use insitu_proto::peer::{is_transient, Backoff, Peer};
use std::collections::HashSet;
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::sync::watch;
use tracing::{info, warn};

/// The link to the viz-node's scene agreement.
pub struct SceneLink {
    peer: Peer,
    max_backoff: Duration,
    proposed: Mutex<HashSet<u32>>,
    /// `Some(Ok)`: agreed; `Some(Err)`: the viz-node refused for a reason retrying cannot fix
    /// (a wrong token, a second world size), and this node uses its own brick's range.
    agreed: watch::Sender<Option<Result<NamedTf, String>>>,
    stats: Arc<crate::stats::Stats>,
}

impl SceneLink {
    /// A link to the viz-node at `addr`; why it fails goes to `stats` (`GetStatus`, `Flush`).
    pub fn new(peer: Peer, max_backoff: Duration, stats: Arc<crate::stats::Stats>) -> Self {
        Self {
            peer,
            max_backoff,
            proposed: Mutex::new(HashSet::new()),
            agreed: watch::channel(None).0,
            stats,
        }
    }

    /// Whether the scene is agreed.
    pub fn is_agreed(&self) -> bool {
        self.agreed.borrow().is_some()
    }

    /// Reports `raw`'s range in the background, once per rank, until the viz-node answers
    /// (retrying with back-off while it is away or other ranks are missing).
    pub fn propose(self: &Arc<Self>, raw: &RawStep) {
        if self.is_agreed()
            || !self
                .proposed
                .lock()
                .unwrap_or_else(|p| p.into_inner())
                .insert(raw.info.rank)
        {
            return;
        }
        let field = raw.field.clone();
        let mut p = pb::SceneProposal {
            step: raw.info.step,
            rank: raw.info.rank,
            world_size: raw.info.world_size,
            min: f64::NAN,
            max: f64::NAN,
            wait_secs: 60.0,
        };
        let link = self.clone();
        tokio::spawn(async move {
            let range = tokio::task::spawn_blocking(move || {
                field.data().iter().filter(|v| v.is_finite()).fold(
                    None,
                    |r: Option<(f32, f32)>, &v| {
                        Some(r.map_or((v, v), |(lo, hi)| (lo.min(v), hi.max(v))))
                    },
                )
            })
            .await
            .ok()
            .flatten();
            if let Some((lo, hi)) = range {
                (p.min, p.max) = (f64::from(lo), f64::from(hi));
            }
            link.agree(p).await;
        });
    }

    async fn agree(&self, p: pb::SceneProposal) {
        let mut backoff = Backoff::new(self.max_backoff);
        loop {
            if self.is_agreed() {
                return;
            }
            match self.call(p).await {
                Ok(a) => {
                    let result = match tf_field(a.tf.as_ref(), None) {
                        Ok(Some(tf)) => Ok(NamedTf::new(tf, a.tf_name.clone())),
                        Ok(None) => Err("the viz-node's agreement carries no transfer function (a viz-node older than this node?)".into()),
                        Err(e) => Err(format!("the viz-node's transfer function is invalid: {e}")),
                    };
                    match &result {
                        Ok(_) => {
                            info!(tf = %a.tf_name, ranks = a.world_size, "the world agreed on a transfer function");
                        }
                        Err(e) => warn!(error = %e, "using this node's own default"),
                    }
                    self.agreed.send_replace(Some(result));
                    return;
                }
                Err(e) if !is_transient(e.code()) => {
                    let why = format!(
                        "agreeing the scene with the viz-node {}: {:?}: {}",
                        self.peer.uri(),
                        e.code(),
                        e.message()
                    );
                    tracing::error!(error = %why, "refused: this node uses a default over its own brick's range");
                    self.stats.set_ship_error(why.clone());
                    self.agreed.send_replace(Some(Err(why)));
                    return;
                }
                Err(e) => {
                    warn!(
                        rank = p.rank,
                        code = ?e.code(),
                        error = %e.message(),
                        "no scene agreed yet; retrying"
                    );
                    self.stats.set_ship_error(format!(
                        "waiting for the world's transfer function: {:?}: {}",
                        e.code(),
                        e.message()
                    ));
                }
            }
            backoff.wait().await;
        }
    }

    async fn call(&self, p: pb::SceneProposal) -> Result<pb::SceneAgreement, tonic::Status> {
        let mut client = crate::viz_link::connect(&self.peer).await?;
        Ok(client.agree_scene(p).await?.into_inner())
    }

    /// Waits for the agreed transfer function; `None` when the viz-node refused to agree (the
    /// node then uses its own default, as without a viz-node).
    pub async fn wait(&self) -> Option<NamedTf> {
        let mut rx = self.agreed.subscribe();
        rx.wait_for(Option::is_some)
            .await
            .ok()
            .and_then(|a| a.clone())
            .and_then(Result::ok)
    }
}

/// How composing `steps` came out at the viz-node (those composed or refused so far).
///
/// # Errors
/// The viz-node unreachable, or its refusal.
pub async fn step_outcomes(
    peer: &Peer,
    steps: Vec<u64>,
) -> Result<Vec<pb::StepOutcome>, tonic::Status> {
    let mut client = crate::viz_link::connect(peer).await?;
    let reply = client
        .step_outcomes(pb::StepOutcomesRequest { steps })
        .await?;
    Ok(reply.into_inner().outcomes)
}
