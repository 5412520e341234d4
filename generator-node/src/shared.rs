//! The state a generator-node's parts share: the queue, the settings in force, the counters,
//! the outbox, the compute lane and pool, the spool, and the links to the tuner and to the
//! viz-node's scene agreement. The gRPC service, the worker, the shipper and the tuner link
//! each hold an `Arc` of it.

use crate::config::Generation;
use crate::ingest::RawStep;
use crate::queue::BoundedQueue;
use crate::settings::to_pb;
use crate::stats::Stats;
use insitu_proto::pb;
use std::sync::{Arc, RwLock};

/// State shared by the service, the worker and the shipper.
pub struct Shared {
    /// Steps waiting for generation.
    pub(crate) queue: BoundedQueue<RawStep>,
    /// Current settings (a worker takes a snapshot per step).
    pub(crate) generation: RwLock<Generation>,
    /// Counters.
    pub stats: Arc<Stats>,
    /// Largest accepted step, bytes.
    pub(crate) max_step_bytes: u64,
    /// Whether a viz-node is configured.
    pub(crate) shipping: bool,
    /// Finished VDIs waiting to be shipped, one outbox per viz-node shard (one without
    /// shards): step `s` waits in the `s mod n`-th.
    pub(crate) outboxes: Vec<Arc<BoundedQueue<crate::work::Product>>>,
    /// Where VDIs and reference frames are made.
    pub backend: insitu_core::Backend,
    /// Production steps and the tuner's trials take turns on this lane.
    pub(crate) lane: tokio::sync::Mutex<()>,
    /// The link to the tuner, when one is configured.
    pub(crate) tuning: Option<Arc<crate::tuning::Tuning>>,
    /// The viz-node's refusals per rank, until a flush of that rank's client reports them.
    pub(crate) refusals: crate::refusals::Refusals,
    /// Every viz-node shard, the configured viz-node first (asked how composing their steps came out).
    pub(crate) viz_shards: Vec<insitu_proto::peer::Peer>,
    /// A client of each shard for the exchange of faces, connected on its first post and kept
    /// (the channel reconnects by itself), so a step's post pays no connection of its own.
    pub(crate) faces_clients: Vec<tokio::sync::OnceCell<crate::viz_link::Client>>,
    /// Steps of several ranks whose VDIs this node shipped, with those ranks, until a flush
    /// of each rank's client has heard how composing the step came out.
    pub(crate) composing:
        std::sync::Mutex<std::collections::BTreeMap<u64, std::collections::BTreeSet<u32>>>,
    /// The first step index no rank of which this node has begun to generate: a tuner's
    /// decision applies from it at the earliest.
    pub(crate) begun: std::sync::atomic::AtomicU64,
    /// The first step index past every step this node has received (queued or parked): a
    /// step not received cannot have begun (`StepSummary.received`).
    pub(crate) received: std::sync::atomic::AtomicU64,
    /// The durable spool, when configured.
    pub(crate) spool: Option<Arc<crate::spool::Spool>>,
    /// This run's identity (`PushReply.epoch`).
    pub(crate) epoch: u64,
    /// Where the world's default transfer function is agreed (the viz-node), when one is
    /// configured and the config names no transfer function.
    pub(crate) scene: Option<Arc<crate::scene::SceneLink>>,
    /// The node's worker threads (`threads` and `nice` in the config, [`crate::pool`]).
    pub(crate) pool: Arc<rayon::ThreadPool>,
    /// Fields of settled steps (generated or dropped): the next pushes are received into
    /// their memory (beyond what the queue counts: one, and a second within the queue's
    /// `max_bytes`; see [`crate::spare`]).
    pub(crate) spare_fields: crate::spare::SpareFields,
    /// Where steps pushed through shared memory are read from; `None`: streamed only.
    pub(crate) shared_memory: Option<crate::shm::SharedMemory>,
    /// The ranks of steps in flight, composed into the host's parts before they ship.
    pub(crate) host: Arc<crate::host::Gather>,
    /// The ranks' bricks, checked once a step's ranks are all in ([`crate::layout`]).
    pub(crate) layout: crate::layout::Layouts,
}

impl Shared {
    /// Runs CPU work (generation, reference frames, trials) on the node's worker threads:
    /// `f` itself and every rayon loop inside it.
    pub(crate) fn compute<R: Send>(&self, f: impl FnOnce() -> R + Send) -> R {
        self.pool.install(f)
    }

    /// A snapshot of the current settings.
    pub(crate) fn generation(&self) -> Generation {
        self.generation
            .read()
            .unwrap_or_else(|e| e.into_inner())
            .clone()
    }

    /// The status message.
    pub fn status(&self) -> pb::GeneratorStatus {
        let c = self.stats.get();
        let g = self.generation();
        let (shared_memory_dir, host_id) = self
            .shared_memory
            .as_ref()
            .map_or_else(Default::default, |m| {
                (m.dir().display().to_string(), m.host_id().to_owned())
            });
        pb::GeneratorStatus {
            queue_depth: self.queue.len() as u32,
            queue_limit: self.queue.max_items() as u32,
            queue_bytes: self.queue.bytes(),
            queue_policy: pb::QueuePolicy::from(self.queue.policy()) as i32,
            outbox_depth: self.outboxes.iter().map(|o| o.len()).sum::<usize>() as u32,
            steps_received: c.received,
            steps_generated: c.generated,
            steps_shipped: c.shipped,
            dropped_queue: c.dropped_queue,
            dropped_outbox: c.dropped_outbox,
            failed: c.failed,
            resolution: g.params.resolution,
            gamma: g.params.gamma,
            viz_connected: c.viz_connected,
            pm_version: g.pm_version,
            tuner_connected: c.tuner_connected,
            ship_failed: c.ship_failed,
            ship_error: self.stats.ship_error(),
            epoch: self.epoch,
            recovered: c.recovered,
            spooled_bytes: self.spool.as_ref().map_or(0, |s| s.used()),
            limit_retries: c.limit_retries,
            limit_retry_secs: c.limit_retry_secs,
            host_parts: c.host_parts,
            host_ranks: c.host_ranks,
            host_compose_secs: c.host_compose_secs,
            cpu_secs: crate::cpu::process_cpu_secs(),
            trial_cpu_secs: c.trial_cpu_secs,
            shared_memory_dir,
            host_id,
            shared_pushes: c.shared_pushes,
            faces_sent_bytes: c.faces_sent_bytes,
            faces_received_bytes: c.faces_received_bytes,
            bricks_grown_across: c.bricks_grown_across,
        }
    }

    /// The shard (index into [`Self::outboxes`] and [`Self::viz_shards`]) that step `step`
    /// goes to: `step mod n`.
    pub(crate) fn shard_of(&self, step: u64) -> usize {
        (step % self.outboxes.len().max(1) as u64) as usize
    }

    /// Removes settled steps' files (name, bytes) from the spool (no-op without one).
    pub(crate) fn unspool<'a>(&self, spool: impl IntoIterator<Item = &'a (String, u64)>) {
        if let Some(sp) = &self.spool {
            for (name, bytes) in spool {
                sp.remove(name, *bytes);
            }
        }
    }

    /// Records the current generation settings in the spool (no-op without one), so that a
    /// restarted node continues the same scene.
    pub(crate) fn save_run(&self) {
        if let Some(sp) = &self.spool {
            let g = self.generation();
            if let Err(e) = sp.save_run(g.pm_version, &to_pb(&g)) {
                tracing::warn!(error = %e, "could not record the run configuration");
            }
        }
    }
}
