//! Shipping finished VDIs (and reference frames) to the viz-node: reconnect with exponential
//! back-off while it is away; an item leaves the outbox for good only when the viz-node has
//! acknowledged it (stored it), or when it fails with an error that retrying cannot fix.

use crate::stats::Stats;
use crate::viz_link::{connect, Client};
use crate::work::Product;
use insitu_proto::peer::{is_transient, Backoff, Peer};
use insitu_proto::{chunk, pb};
use std::sync::Arc;
use std::time::Duration;
use tonic::{Code, Status};
use tracing::{info, info_span, warn, Instrument};

/// Ships the outbox to one viz-node.
pub struct Shipper {
    peer: Peer,
    max_backoff: Duration,
    client: Option<Client>,
}

/// Steps of several ranks whose composition is remembered for the flushes to come.
const MAX_COMPOSING_STEPS: usize = 100_000;

impl Shipper {
    /// A shipper for the viz-node `peer`.
    pub fn new(peer: Peer, max_backoff: Duration) -> Self {
        Self {
            peer,
            max_backoff,
            client: None,
        }
    }

    async fn client(&mut self) -> Result<&mut Client, Status> {
        if self.client.is_none() {
            self.client = Some(connect(&self.peer).await?);
        }
        // Just set when it was `None`.
        self.client
            .as_mut()
            .ok_or_else(|| Status::internal("viz client missing"))
    }

    async fn ship_references(
        &mut self,
        header: &pb::ReferenceHeader,
        data: &bytes::Bytes,
    ) -> Result<(), Status> {
        let msgs = chunk::split::<pb::ReferenceChunk>(header.clone(), data.clone());
        self.client()
            .await?
            .ship_references(tokio_stream::iter(msgs))
            .await?;
        Ok(())
    }

    async fn ship_vdi(&mut self, p: &Product) -> Result<(), Status> {
        let msgs = chunk::split::<pb::VdiChunk>(p.vdi_header.clone(), p.vdi.clone());
        self.client()
            .await?
            .ship_vdi(tokio_stream::iter(msgs))
            .await?;
        Ok(())
    }

    /// The VDI, then its reference frames: frames never reach the viz-node for a VDI it
    /// refused (they would leave a row of their own there, without the VDI's world size or
    /// brick, which later ranks of the step would be checked against).
    async fn try_once(&mut self, p: &Product, vdi_done: &mut bool) -> Result<(), Status> {
        if !*vdi_done {
            self.ship_vdi(p).await?;
            *vdi_done = true;
        }
        if let Some((h, d)) = &p.references {
            self.ship_references(h, d).await?;
        }
        Ok(())
    }

    /// Ships `p`, retrying transient failures with back-off (100 ms doubling up to the
    /// maximum) for as long as it takes; returns a non-transient error.
    ///
    /// # Errors
    /// The viz-node's status when it refuses the item for a reason retrying cannot fix.
    pub async fn ship(&mut self, p: &Product, stats: &Stats) -> Result<(), Status> {
        let mut backoff = Backoff::new(self.max_backoff);
        let mut vdi_done = false;
        loop {
            match self.try_once(p, &mut vdi_done).await {
                Ok(()) => {
                    if !stats.get().viz_connected {
                        info!(uri = %self.peer.uri(), "connected to the viz-node");
                    }
                    stats.update(|c| c.viz_connected = true);
                    stats.set_ship_error("");
                    return Ok(());
                }
                Err(e) if !is_transient(e.code()) => return Err(e),
                Err(e) => {
                    let why = if e.code() == Code::ResourceExhausted {
                        "cannot store (out of space, read-only or refused; see the message)"
                    } else {
                        "unreachable"
                    };
                    if stats.get().viz_connected {
                        warn!(error = %e.message(), "viz-node {why}; retrying with back-off");
                    }
                    stats.update(|c| c.viz_connected = false);
                    stats.set_ship_error(format!(
                        "viz-node {} {why}: {:?}: {}",
                        self.peer.uri(),
                        e.code(),
                        e.message()
                    ));
                    self.client = None;
                    backoff.wait().await;
                }
            }
        }
    }

    /// Ships the items of outbox `shard` until it is closed and empty; a settled item leaves
    /// the spool, and a step of several ranks is kept for the flushes that will ask how
    /// composing it went.
    pub async fn run(mut self, shared: Arc<crate::shared::Shared>, shard: usize) {
        let stats = shared.stats.clone();
        let outbox = shared.outboxes[shard].clone();
        while let Some(p) = outbox.pop().await {
            let span = info_span!("ship", step = p.vdi_header.step, rank = p.vdi_header.rank);
            let result = self.ship(&p, &stats).instrument(span).await;
            shared.unspool(&p.spool);
            let held = p.ranks();
            let ranks = held.len() as u64;
            match result {
                Ok(()) => {
                    stats.update(|c| c.shipped += ranks);
                    let h = &p.vdi_header;
                    if h.world_size > 1 {
                        let mut c = shared.composing.lock().unwrap_or_else(|e| e.into_inner());
                        c.entry(h.step).or_default().extend(&held);
                        // Clients that never flush: the oldest steps are forgotten first.
                        while c.len() > MAX_COMPOSING_STEPS {
                            c.pop_first();
                        }
                    }
                }
                Err(e) => {
                    warn!(step = p.vdi_header.step, rank = p.vdi_header.rank, code = ?e.code(), error = %e.message(), "the viz-node refused a VDI; it is counted as failed");
                    let why = format!(
                        "the viz-node refused step {} rank {}: {:?}: {}",
                        p.vdi_header.step,
                        p.vdi_header.rank,
                        e.code(),
                        e.message()
                    );
                    stats.set_ship_error(why.clone());
                    for r in held {
                        shared.refusals.record(r, why.clone());
                    }
                    stats.update(|c| {
                        c.failed += ranks;
                        c.ship_failed += ranks;
                    });
                }
            }
        }
    }
}
