//! A running generator-node: the gRPC server, the generation worker and the shipper, wired
//! together, with a graceful shutdown that drains what it can and says what it dropped.

use crate::config::{Config, Generation, SpoolConfig};
use crate::ingest::RawStep;
use crate::queue::BoundedQueue;
use crate::service::GeneratorService;
use crate::shared::Shared;
use crate::ship::Shipper;
use crate::spool::{Spool, SpoolError};
use crate::stats::{Counters, Stats};
use crate::work;
use insitu_core::NamedTf;
use insitu_proto::daemon::{bind, select_backend, DaemonConfig, ServeError, Served};
use insitu_proto::pb::generator_server::GeneratorServer;
use insitu_proto::peer::Peer;
use insitu_proto::security::{Security, SecurityError};
use insitu_proto::transport;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::atomic::Ordering;
use std::sync::{Arc, RwLock};
use std::time::{Duration, Instant};
use tokio::task::JoinHandle;
use tracing::{error, info, info_span, warn, Instrument};

/// What a shutdown leaves behind.
#[derive(Clone, Debug, PartialEq)]
pub struct Summary {
    /// The final counters (anything unshipped at the drain deadline is in `dropped_outbox`).
    pub counters: Counters,
    /// Of those, VDIs still unshipped when the drain deadline passed.
    pub lost_at_shutdown: u64,
    /// Steps whose ranks' bricks could not be composed, and why ([`crate::layout`]).
    pub layout: Option<String>,
    /// Steps made at an r the node lowered before the tuner's first decision
    /// ([`crate::correct`]).
    pub correction: Option<String>,
    /// How the ADIOS2 input ended, and after which step (`[adios2]`).
    pub input: Option<String>,
}

impl std::fmt::Display for Summary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let c = &self.counters;
        write!(
            f,
            "received {}, generated {}, shipped {}, dropped from queue {}, dropped from outbox {} (of which unshipped at shutdown {}), failed {}",
            c.received, c.generated, c.shipped, c.dropped_queue, c.dropped_outbox, self.lost_at_shutdown, c.failed
        )?;
        if c.limit_retries > 0 {
            write!(
                f,
                "; {} VDI(s) made again under the hard limits or the guard on the tuner's budget ({:.3} s)",
                c.limit_retries, c.limit_retry_secs
            )?;
        }
        for note in [&self.layout, &self.correction, &self.input]
            .into_iter()
            .flatten()
        {
            write!(f, "; {note}")?;
        }
        Ok(())
    }
}

/// Why a node did not start; each names the input at fault.
#[derive(Debug, thiserror::Error)]
pub enum StartError {
    /// The configuration, the token, TLS files or a peer's address, the compute backend, the
    /// listening address.
    #[error(transparent)]
    Serve(#[from] ServeError),
    /// The spool directory.
    #[error("spool {}: {source}", dir.display())]
    Spool {
        /// The directory.
        dir: PathBuf,
        /// Why.
        source: SpoolError,
    },
    /// The run configuration the spool recorded (`run.pb`) does not apply.
    #[error("spool {}: run.pb: {problem}", dir.display())]
    SpoolRun {
        /// The spool directory.
        dir: PathBuf,
        /// Why.
        problem: String,
    },
    /// The worker pool of `threads`.
    #[error("threads = {threads}: cannot start the worker threads: {source}")]
    Threads {
        /// The count configured.
        threads: usize,
        /// Why.
        source: rayon::ThreadPoolBuildError,
    },
}

/// A started node.
pub struct RunningNode {
    shared: Arc<Shared>,
    served: Served,
    worker: JoinHandle<()>,
    host: JoinHandle<()>,
    shippers: Vec<JoinHandle<()>>,
    tuner: Option<JoinHandle<()>>,
    #[cfg(feature = "adios2")]
    input: Option<crate::adios2_input::Input>,
    drain_timeout: Duration,
}

/// Binds, then starts the server, the worker and (with a viz-node configured) the shipper.
///
/// # Errors
/// [`StartError`]: a bad config, token, TLS file or spool, a non-loopback address without a
/// token, no backend, or a bind failure.
pub async fn start(cfg: Config) -> Result<RunningNode, StartError> {
    let mut generation = cfg.generation().map_err(ServeError::from)?;
    let (spool, recovered) = match &cfg.spool {
        Some(sc) => open_spool(sc, &mut generation)?,
        None => (None, Vec::new()),
    };
    let tf_configured = generation.tf.is_some();
    let security = cfg.serve().security().map_err(ServeError::from)?;
    let (viz, viz_shards) = viz_peers(&cfg, &security).map_err(ServeError::from)?;
    let tuner_peer = security
        .peer_for("tuner", cfg.tuner.as_deref())
        .map_err(ServeError::from)?;
    let backend = select_backend(cfg.backend).await?;
    info!("generating on {}", backend.describe());
    let (listener, addr) = bind("listen", cfg.listen).await?;
    let stats = Arc::new(Stats::default());
    // With a tuner: the node's side of the link, and the channel of step summaries to it.
    let tuner = tuner_peer.map(|peer| {
        let (t, rx) =
            crate::tuning::Tuning::new(cfg.hold_bytes, cfg.trial_interleave, stats.clone());
        (peer, Arc::new(t), rx)
    });
    let scene = match (&viz, tf_configured) {
        (Some(viz), false) => Some(Arc::new(crate::scene::SceneLink::new(
            viz.clone(),
            Duration::from_secs_f64(cfg.max_backoff_secs),
            stats.clone(),
        ))),
        _ => None,
    };
    let shared = Arc::new(Shared {
        queue: BoundedQueue::new(cfg.queue.max_items, cfg.queue.max_bytes, cfg.queue.policy),
        generation: RwLock::new(generation),
        stats,
        max_step_bytes: cfg.max_step_bytes,
        shipping: cfg.viz.is_some(),
        outboxes: (0..viz_shards.len().max(1))
            .map(|_| {
                Arc::new(BoundedQueue::new(
                    cfg.outbox.max_items,
                    cfg.outbox.max_bytes,
                    cfg.outbox.policy,
                ))
            })
            .collect(),
        backend,
        lane: tokio::sync::Mutex::new(()),
        tuning: tuner.as_ref().map(|(_, t, _)| t.clone()),
        refusals: Default::default(),
        composing: Default::default(),
        faces_clients: viz_shards.iter().map(|_| Default::default()).collect(),
        viz_shards: viz_shards.clone(),
        begun: Default::default(),
        received: Default::default(),
        spool,
        epoch: new_epoch(),
        spare_fields: crate::spare::SpareFields::new(cfg.queue.max_bytes),
        shared_memory: shared_memory(cfg.shared_memory_dir.as_deref()),
        pool: crate::pool::worker_pool(cfg.threads, cfg.nice).map_err(|source| {
            StartError::Threads {
                threads: cfg.threads,
                source,
            }
        })?,
        scene,
        // Without a viz-node nothing ships, so nothing is gathered either.
        host: Arc::new(crate::host::Gather::new(&crate::config::HostConfig {
            compose: cfg.host.compose && cfg.viz.is_some(),
            ..cfg.host.clone()
        })),
        // With a viz-node, the bricks of a world spread over nodes meet there.
        layout: crate::layout::Layouts::new(cfg.viz.is_some()),
    });
    let svc = GeneratorServer::new(GeneratorService(shared.clone()))
        .max_decoding_message_size(transport::MAX_MESSAGE_BYTES)
        .max_encoding_message_size(transport::MAX_MESSAGE_BYTES);
    let served = Served::start((listener, addr), &security, svc).await?;
    shared.save_run();
    let worker = tokio::spawn(worker(shared.clone()));
    let host =
        tokio::spawn(crate::outbox::host_steps(shared.clone()).instrument(info_span!("host")));
    requeue(&shared, recovered);
    let backoff = Duration::from_secs_f64(cfg.max_backoff_secs);
    let shippers = spawn_shippers(&shared, viz_shards, backoff);
    let tuner = tuner.map(|(peer, tuning, summaries)| {
        let link =
            crate::tuner_link::Link::new(peer, backoff, format!("{addr}/{}", std::process::id()));
        let run = link.run(shared.clone(), tuning, summaries);
        tokio::spawn(run.instrument(info_span!("tuner")))
    });
    #[cfg(feature = "adios2")]
    let input = cfg.adios2.clone().map(|mut a| {
        a.var = a.var.or_else(|| cfg.generation.field.clone());
        crate::adios2_input::Input::spawn(shared.clone(), a, tokio::runtime::Handle::current())
    });
    info!(%addr, tls = security.serves_tls(), viz = ?cfg.viz, tuner = ?cfg.tuner, policy = %cfg.queue.policy, "generator-node listening");
    Ok(RunningNode {
        shared,
        served,
        worker,
        host,
        shippers,
        tuner,
        #[cfg(feature = "adios2")]
        input,
        drain_timeout: Duration::from_secs_f64(cfg.drain_timeout_secs),
    })
}

/// The viz-node to ship to (`viz`) and every shard's, `viz` first.
///
/// # Errors
/// [`StartError`] for an address that does not resolve or lacks its security.
fn viz_peers(
    cfg: &Config,
    security: &Security,
) -> Result<(Option<Peer>, Vec<Peer>), SecurityError> {
    let viz = security.peer_for("viz", cfg.viz.as_deref())?;
    let mut shards: Vec<Peer> = viz.iter().cloned().collect();
    for addr in &cfg.viz_shards {
        if let Some(p) = security.peer_for("viz", Some(addr))? {
            shards.push(p);
        }
    }
    Ok((viz, shards))
}

/// One shipper a viz-node shard, each on its own task.
fn spawn_shippers(
    shared: &Arc<Shared>,
    shards: Vec<Peer>,
    backoff: Duration,
) -> Vec<JoinHandle<()>> {
    shards
        .into_iter()
        .enumerate()
        .map(|(k, viz)| {
            let s = Shipper::new(viz, backoff);
            tokio::spawn(
                s.run(shared.clone(), k)
                    .instrument(info_span!("shipper", shard = k)),
            )
        })
        .collect()
}

/// The spool in `sc.dir` and the steps it holds; where it recorded the run's configuration
/// (`run.pb`), that configuration applied to `generation`, so that the interrupted run's steps
/// and the next ones share a scene.
fn open_spool(
    sc: &SpoolConfig,
    generation: &mut Generation,
) -> Result<(Option<Arc<Spool>>, Vec<RawStep>), StartError> {
    let (spool, steps) =
        Spool::open(&sc.dir, sc.durable, sc.max_bytes).map_err(|source| StartError::Spool {
            dir: sc.dir.clone(),
            source,
        })?;
    if let Some((version, run)) = spool.load_run() {
        *generation =
            crate::settings::apply_config(generation, &run).map_err(|e| StartError::SpoolRun {
                dir: sc.dir.clone(),
                problem: e.message().to_owned(),
            })?;
        generation.pm_version = version;
        info!(r = generation.params.resolution, gamma = generation.params.gamma, pm_version = version, tf = ?generation.tf.as_ref().map(|t| &t.name), "continuing the run configuration recorded in the spool");
    }
    Ok((Some(Arc::new(spool)), steps))
}

/// Shared-memory pushes from `dir`, where it can take them (logged either way); `None` when
/// unset or unusable: a node that cannot take them still takes every streamed step.
fn shared_memory(dir: Option<&std::path::Path>) -> Option<crate::shm::SharedMemory> {
    let dir = dir?;
    match crate::shm::SharedMemory::new(dir) {
        Ok(m) => {
            info!(dir = %m.dir().display(), "taking steps pushed through shared memory from this host");
            Some(m)
        }
        Err(problem) => {
            info!(%problem, "no shared-memory pushes: steps are streamed only");
            None
        }
    }
}

/// Queues the steps an earlier run acknowledged and did not deliver, in the background (the
/// queue is bounded, so this waits for the worker like any push), ahead of new pushes.
fn requeue(shared: &Arc<Shared>, recovered: Vec<RawStep>) {
    if recovered.is_empty() {
        return;
    }
    warn!(
        steps = recovered.len(),
        "steps acknowledged by an earlier run were not delivered: generating them again"
    );
    let n = recovered.len() as u64;
    shared.stats.update(|c| {
        c.received += n;
        c.recovered += n;
    });
    let shared = shared.clone();
    tokio::spawn(async move {
        for raw in recovered {
            // A part of the earlier run may be stored already: these ship rank by rank.
            shared.host.alone(raw.info.step, raw.info.rank);
            shared
                .received
                .fetch_max(raw.info.step + 1, Ordering::SeqCst);
            let _ = shared.layout.record(&raw.info, &raw.field);
            crate::faces::send(&shared);
            let bytes = raw.bytes();
            if let Ok(dropped) = shared.queue.push(raw, bytes).await {
                for d in dropped {
                    shared.layout.made(d.info.step);
                    shared.unspool(d.spooled().as_ref());
                    shared.stats.update(|c| c.dropped_queue += 1);
                }
            }
        }
    });
}

/// A run's identity: the start time in nanoseconds mixed with the process id (distinct across
/// restarts of one node, which is what a client compares).
fn new_epoch() -> u64 {
    let nanos = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as u64);
    nanos ^ (u64::from(std::process::id()) << 48)
}

async fn worker(shared: Arc<Shared>) {
    // The last step's VDI (already compressed into its product): the next one reuses its memory.
    let mut spare = None;
    // Steps whose bricks wait for their neighbours' faces.
    let mut parked = Vec::new();
    while let Some((mut raw, growth)) = next(&shared, &mut parked).await {
        let (step, rank, raw_world_size) = (raw.info.step, raw.info.rank, raw.info.world_size);
        let spooled = raw.spooled();
        // Begun before the snapshot: a decision applied in between takes effect after it.
        shared.begun.fetch_max(step + 1, Ordering::SeqCst);
        let mut gen = shared
            .generation()
            .for_step_holding(step, raw.field_name.as_deref());
        // The guard holds a step made under the tuner's decision to the tuner's budget.
        if gen.pm_version > 0 {
            gen.tuner_size_budget = shared
                .tuning
                .as_ref()
                .and_then(|t| t.correction.size_budget());
        }
        if gen.tf.is_none() {
            if let Some(scene) = &shared.scene {
                // The first step of a run with no TF configured: wait for the world's.
                gen.tf = scene.wait().await;
            }
        }
        let with_refs = gen.reference_every > 0 && step % gen.reference_every == 0;
        let pm_version = gen.pm_version;
        let s = shared.clone();
        let reused = spare.take();
        let lane = shared.lane.lock().await;
        let result = tokio::task::spawn_blocking(move || {
            s.compute(|| {
                let grow_secs = grow(&s, &mut raw, &growth);
                let tf = gen.tf.take().unwrap_or_else(|| {
                    insitu_core::TransferFunction::default_for_volume(&raw.field)
                });
                let (mut product, vdi) = work::run(&s.backend, &raw, &gen, &tf, with_refs, reused)?;
                // Growing the brick is part of making it.
                product.vdi_header.tau_secs += grow_secs;
                if let Some(f) = &mut product.first_try {
                    f.tau_secs += grow_secs;
                }
                // Only while the tuner listens: otherwise nobody would read the summary, and
                // the field's memory receives the next step.
                let for_tuner = if s.tuning.as_ref().is_some_and(|t| t.connected()) {
                    Some(work::for_tuner(raw, &gen, &tf, &product))
                } else {
                    s.spare_fields.put(raw.field);
                    None
                };
                // A rank that will wait for its host's other ranks has its frames packed
                // here, on the worker threads.
                let mut finished = crate::host::Finished::new(product, vdi);
                let reusable = if s.host.gathers(raw_world_size) {
                    finished.pack()
                } else {
                    None
                };
                Ok::<_, work::WorkError>((finished, tf, for_tuner, reusable))
            })
        })
        .instrument(info_span!("step", step, rank))
        .await;
        drop(lane);
        match result {
            Ok(Ok((finished, tf, for_tuner, reusable))) => {
                spare = reusable;
                if let Some(t) = &shared.tuning {
                    let whole = shared.layout.whole_world_here(raw_world_size);
                    let begun = shared.begun.load(Ordering::SeqCst);
                    let h = &finished.product.vdi_header;
                    if t.correction
                        .after_step(&shared.generation, begun, h, pm_version, whole)
                    {
                        shared.save_run();
                    }
                    t.after_step(for_tuner, begun, shared.received.load(Ordering::SeqCst));
                }
                keep_tf(&shared, tf, raw_world_size);
                let (retries, retry_secs) = finished.product.limit_retries;
                shared.stats.update(|c| {
                    c.generated += 1;
                    c.limit_retries += u64::from(retries);
                    c.limit_retry_secs += retry_secs;
                });
                if !shared.shipping {
                    spare = spare.or(finished.into_vdi());
                    shared.unspool(spooled.as_ref());
                    continue;
                }
                // A rank of a world of several waits for its host's other ranks.
                if let Some(f) = shared.host.finish(finished) {
                    let (product, vdi) = f.unpack();
                    spare = spare.or(vdi);
                    crate::outbox::to_outbox(&shared, product).await;
                }
            }
            Ok(Err(e)) => {
                error!(step, rank, error = %e, "generation failed");
                shared.host.settled(step, rank);
                shared.unspool(spooled.as_ref());
                shared.stats.update(|c| c.failed += 1);
            }
            Err(e) => {
                error!(step, rank, error = %e, "generation task panicked");
                shared.host.settled(step, rank);
                shared.unspool(spooled.as_ref());
                shared.stats.update(|c| c.failed += 1);
            }
        }
    }
}

/// The next step to make and how its brick grows ([`crate::layout`]): a parked step whose
/// neighbours have come, else the queue's next. A step whose brick must wait for its
/// neighbours' faces is parked beside the queue, so that the queue keeps taking pushes: the
/// neighbours' pushes may be waiting behind it. After the queue closes, parked steps are made
/// as pushed. `None` when the queue is closed and empty and nothing is parked.
async fn next(
    shared: &Arc<Shared>,
    parked: &mut Vec<(RawStep, Instant)>,
) -> Option<(RawStep, crate::layout::Growth)> {
    let wait = shared.host.wait();
    loop {
        // Taken before the looks, so that a step completed in between still wakes the wait.
        let changed = shared.layout.changed();
        let mut earliest: Option<Instant> = None;
        for i in 0..parked.len() {
            let (raw, since) = &parked[i];
            let decided = shared.layout.decide(&raw.info, wait, *since);
            // A world found spread over nodes posts its bricks' faces now.
            crate::faces::send(shared);
            match decided {
                Ok(growth) => return Some((parked.remove(i).0, growth)),
                Err(d) => earliest = Some(earliest.map_or(d, |e| e.min(d))),
            }
        }
        let deadline = async {
            match earliest {
                Some(d) => tokio::time::sleep_until(d.into()).await,
                None => std::future::pending().await,
            }
        };
        tokio::select! {
            raw = shared.queue.pop() => {
                let Some(raw) = raw else {
                    if parked.is_empty() {
                        return None;
                    }
                    let (raw, _) = parked.remove(0);
                    shared.layout.made(raw.info.step);
                    return Some((raw, crate::layout::Growth::AsPushed));
                };
                let since = Instant::now();
                let decided = shared.layout.decide(&raw.info, wait, since);
                crate::faces::send(shared);
                match decided {
                    Ok(growth) => return Some((raw, growth)),
                    Err(_) => parked.push((raw, since)),
                }
            }
            () = changed => {}
            () = deadline => {}
        }
    }
}

/// Grows `raw`'s brick by its neighbours' faces as `growth` says, in the memory of a settled
/// step's field (the field as pushed kept for the next push); returns the seconds it took. A growth that fails leaves the
/// brick as pushed, logged (the viz-node then names the cells it leaves out).
fn grow(shared: &Shared, raw: &mut RawStep, growth: &crate::layout::Growth) -> f64 {
    if matches!(growth, crate::layout::Growth::AsPushed) {
        return 0.0;
    }
    let t = Instant::now();
    match growth.apply(&mut raw.info, &raw.field, shared.spare_fields.take()) {
        Ok(Some(grown)) => {
            let pushed = std::mem::replace(&mut raw.field, grown);
            shared.spare_fields.put(pushed);
            if matches!(growth, crate::layout::Growth::Grow { across: true, .. }) {
                shared.stats.update(|c| c.bricks_grown_across += 1);
            }
        }
        Ok(None) => {}
        Err(e) => {
            warn!(step = raw.info.step, rank = raw.info.rank, error = %e, "the brick could not be grown by its neighbours' faces: made as pushed");
        }
    }
    t.elapsed().as_secs_f64()
}

/// The first step's transfer function kept for the rest of the run (and recorded in the
/// spool's `run.pb`); later steps' are the same one, so nothing changes.
fn keep_tf(shared: &Shared, tf: NamedTf, world_size: u32) {
    {
        let mut g = shared.generation.write().unwrap_or_else(|e| e.into_inner());
        if g.tf.is_some() {
            return;
        }
        if shared.scene.is_none() && world_size > 1 {
            warn!(tf = %tf.name, "no transfer function configured and no viz-node to agree one with: this rank's default over its own brick's range may differ from other ranks'");
        } else {
            info!(tf = %tf.name, "using the transfer function for the rest of the run");
        }
        g.tf = Some(tf);
    }
    shared.save_run();
}

impl RunningNode {
    /// The address the server listens on (the actual port when 0 was asked for).
    pub fn local_addr(&self) -> SocketAddr {
        self.served.local_addr()
    }

    /// Shared state (status, counters).
    pub fn shared(&self) -> &Arc<Shared> {
        &self.shared
    }

    /// Stops taking steps, generates what is queued and ships it for up to the drain timeout,
    /// and counts whatever is left as dropped (a spool keeps it for the next run).
    pub async fn shutdown(self) -> Summary {
        self.served.draining().await;
        self.shared.queue.close();
        // The queue closed first: a step the input waits to queue is refused, not waited on.
        #[cfg(feature = "adios2")]
        let input = match self.input {
            Some(i) => i.finish().await,
            None => None,
        };
        #[cfg(not(feature = "adios2"))]
        let input = None;
        self.served.stop().await;
        // One deadline for generating what is queued and shipping it: with the viz-node away
        // the worker would wait for room in a full outbox (or for the world's TF) for ever.
        let deadline = tokio::time::Instant::now() + self.drain_timeout;
        let mut worker = self.worker;
        let worker_done = tokio::time::timeout_at(deadline, &mut worker).await.is_ok();
        if !worker_done {
            worker.abort();
            let _ = worker.await;
        }
        if let Some(t) = self.tuner {
            t.abort();
        }
        // The ranks held for their host's other ranks ship now.
        self.shared.host.close();
        let mut host = self.host;
        if tokio::time::timeout_at(deadline, &mut host).await.is_err() {
            host.abort();
            let _ = host.await;
        }
        for outbox in &self.shared.outboxes {
            outbox.close();
        }
        let mut shipper_done = true;
        for mut shipper in self.shippers {
            if tokio::time::timeout_at(deadline, &mut shipper)
                .await
                .is_err()
            {
                shipper.abort();
                let _ = shipper.await;
                shipper_done = false;
            }
        }
        let mut lost = 0;
        if !(worker_done && shipper_done) {
            // Steps still queued, in generation or in the outbox: counted, and (with a spool)
            // kept on disk for the next run.
            let c = self.shared.stats.get();
            lost = c.received.saturating_sub(c.settled(self.shared.shipping));
            self.shared.stats.update(|c| c.dropped_outbox += lost);
            warn!(lost, "drain timeout: steps left undelivered");
        }
        Summary {
            counters: self.shared.stats.get(),
            lost_at_shutdown: lost,
            layout: self.shared.layout.summary(),
            correction: self
                .shared
                .tuning
                .as_ref()
                .and_then(|t| t.correction.summary()),
            input,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cpu() -> Config {
        Config {
            backend: insitu_core::BackendChoice::Cpu,
            listen: SocketAddr::from(([127, 0, 0, 1], 0)),
            ..Config::default()
        }
    }

    /// A taken port and a spool that cannot be a directory each come back as their own
    /// variant, naming the address or the directory once.
    #[tokio::test]
    async fn start_errors_name_the_input_at_fault() {
        let taken = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let addr = taken.local_addr().unwrap();
        let Err(err) = start(Config {
            listen: addr,
            ..cpu()
        })
        .await
        else {
            panic!("a taken port started");
        };
        assert!(
            matches!(&err, StartError::Serve(ServeError::Listen { addr: a, .. }) if *a == addr),
            "{err:?}"
        );
        let said = insitu_proto::peer::error_chain(&err);
        assert_eq!(said.matches(&addr.to_string()).count(), 1, "{said}");
        assert_eq!(said.matches("in use").count(), 1, "{said}");

        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("not-a-dir");
        std::fs::write(&file, b"x").unwrap();
        let spool = SpoolConfig {
            dir: file.clone(),
            durable: false,
            max_bytes: 1 << 20,
        };
        let Err(err) = start(Config {
            spool: Some(spool),
            ..cpu()
        })
        .await
        else {
            panic!("a file as spool started");
        };
        assert!(
            matches!(&err, StartError::Spool { dir, .. } if *dir == file),
            "{err:?}"
        );
    }
}
