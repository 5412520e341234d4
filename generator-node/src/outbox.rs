//! What goes into the outbox the shipper drains: a rank's product as it was made, or a host's
//! ranks of a step composed into parts as the gatherer (`host::Gather`) finds them due.

use crate::host::{compose_part, Finished};
use crate::shared::Shared;
use crate::work::Product;
use insitu_core::volume::bricks::{box_groups, Brick};
use std::sync::Arc;
use std::time::Instant;
use tracing::{info, warn};

/// `product` into the outbox for the shipper; what the outbox's policy drops to make room is
/// logged, counted (per rank) and taken out of the spool.
pub(crate) async fn to_outbox(shared: &Shared, product: Product) {
    let n = product.bytes();
    let ranks = product.ranks().len() as u64;
    let outbox = &shared.outboxes[shared.shard_of(product.vdi_header.step)];
    match outbox.push(product, n).await {
        Ok(dropped) if !dropped.is_empty() => {
            for d in &dropped {
                info!(
                    step = d.vdi_header.step,
                    rank = d.vdi_header.rank,
                    "dropped an unshipped VDI (outbox full)"
                );
                shared.unspool(&d.spool);
            }
            let n: u64 = dropped.iter().map(|d| d.ranks().len() as u64).sum();
            shared.stats.update(|c| c.dropped_outbox += n);
        }
        Ok(_) => {}
        Err(_) => shared.stats.update(|c| c.dropped_outbox += ranks),
    }
}

/// Ships the gatherer's steps as their parts become due, until it is closed and empty.
pub async fn host_steps(shared: Arc<Shared>) {
    let gather = shared.host.clone();
    loop {
        let (due, next, finished) = gather.take_due(Instant::now());
        for ranks in due {
            ship_step(&shared, ranks).await;
        }
        if finished {
            return;
        }
        match next {
            Some(t) => {
                tokio::select! {
                    () = gather.wake.notified() => {}
                    () = tokio::time::sleep_until(t.into()) => {}
                }
            }
            None => gather.wake.notified().await,
        }
    }
}

/// One step's finished ranks into the outbox: a part per box of their bricks.
async fn ship_step(shared: &Arc<Shared>, mut ranks: Vec<Finished>) {
    ranks.sort_by_key(|f| f.product.vdi_header.rank);
    let held: usize = ranks.iter().map(Finished::held_bytes).sum();
    let Some(bricks) = bricks_of(&ranks) else {
        // Ranks that do not say where their bricks lie (or on different grids) ship alone;
        // the viz-node names the problem.
        return ship_alone(shared, ranks).await;
    };
    let groups = box_groups(&bricks);
    let mut slots: Vec<Option<Finished>> = ranks.into_iter().map(Some).collect();
    for (members, brick) in groups {
        let group: Vec<Finished> = members.iter().filter_map(|&i| slots[i].take()).collect();
        if group.len() == 1 {
            ship_alone(shared, group).await;
            continue;
        }
        let s = shared.clone();
        let composed = tokio::task::spawn_blocking(move || {
            let t = Instant::now();
            let part = s.compute(|| compose_part(&group, brick));
            (part, group, t.elapsed().as_secs_f64())
        })
        .await;
        match composed {
            Ok((Ok(part), group, secs)) => {
                info!(
                    step = part.vdi_header.step,
                    ranks = ?part.vdi_header.covers,
                    bytes = part.vdi.len(),
                    held_while_waiting = held,
                    secs,
                    "composed the host's ranks into one part"
                );
                shared.stats.update(|c| {
                    c.host_parts += 1;
                    c.host_ranks += group.len() as u64;
                    c.host_compose_secs += secs;
                });
                to_outbox(shared, part).await;
            }
            Ok((Err(why), group, _)) => {
                let h = &group[0].product.vdi_header;
                warn!(step = h.step, error = %why, "the host's ranks could not be composed: they ship alone");
                ship_alone(shared, group).await;
            }
            Err(e) => warn!(error = %e, "composing the host's ranks panicked; they are lost"),
        }
    }
}

/// Each of `ranks` into the outbox as it was made.
async fn ship_alone(shared: &Arc<Shared>, ranks: Vec<Finished>) {
    for f in ranks {
        to_outbox(shared, f.into_product()).await;
    }
}

/// The bricks of `ranks` (sorted by rank) when all state one on the same grid.
fn bricks_of(ranks: &[Finished]) -> Option<Vec<Brick>> {
    let global = ranks.first()?.product.vdi_header.global_dims;
    ranks
        .iter()
        .map(|f| {
            let h = &f.product.vdi_header;
            (h.global_dims == global).then_some(())?;
            Some(Brick {
                offset: h.brick_offset.as_ref().map(<[usize; 3]>::from)?,
                dims: h.brick_dims.as_ref().map(<[usize; 3]>::from)?,
            })
        })
        .collect()
}
