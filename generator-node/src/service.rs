//! The `Generator` gRPC service: receive steps into the bounded queue, take configuration
//! pushed by a tuner or an operator, report status, flush.

use crate::ingest::{check_step, RawStep};
use crate::settings::apply_config;
use crate::shared::Shared;
use insitu_proto::pb::generator_server::Generator;
use insitu_proto::{chunk, pb};
use std::sync::Arc;
use std::time::Duration;
use tonic::{Request, Response, Status, Streaming};
use tracing::{info, info_span, Instrument};

/// The gRPC service.
pub struct GeneratorService(pub Arc<Shared>);

impl GeneratorService {
    /// One pushed step, the chunks of the field its scene renders converted into the brick's
    /// storage as they arrive (no copy of the bytes; other fields skipped), into the spare
    /// field of an earlier step where there is one.
    ///
    /// # Errors
    /// The stream's rules broken ([`chunk::receive_into`]: a bad header, a step over
    /// `max_step_bytes`, chunks that do not fill it), or a transport error, as a status.
    async fn receive(&self, mut stream: Streaming<pb::StepChunk>) -> Result<RawStep, Status> {
        // The field chosen once, from the header: the one kept is the one the step names.
        let (header, (info, _, field, wanted)) = chunk::receive_into(
            &mut stream,
            self.0.max_step_bytes,
            |h: &pb::StepHeader| {
                let wanted = self.wanted_field(h.step);
                let (info, window) = check_step(h, wanted.as_deref())?;
                self.0.layout.admit(&info)?;
                Ok((
                    info,
                    window,
                    info.assembler(self.0.spare_fields.take()),
                    wanted,
                ))
            },
            |(_, window, field, _), bytes| field.push(window.take(bytes)),
        )
        .await?;
        Ok(info.with_field(field)?.named(&header, wanted.as_deref()))
    }

    /// The field the scene in force for `step` renders, by name (`None`: each step's first);
    /// a step's other fields are passed over as they arrive.
    pub(crate) fn wanted_field(&self, step: u64) -> Option<String> {
        self.0
            .generation
            .read()
            .unwrap_or_else(|e| e.into_inner())
            .field_for(step)
            .map(str::to_owned)
    }

    /// A step whose payload lies in a shared-memory file ([`crate::shm`]): the header checked
    /// as a stream's, the file opened and checked, its payload read into the field on the
    /// blocking pool.
    ///
    /// # Errors
    /// `FAILED_PRECONDITION` when the node takes no shared-memory pushes or the file cannot be
    /// used; as [`Self::receive`] otherwise.
    async fn receive_shared(&self, step: pb::SharedStep) -> Result<RawStep, Status> {
        let Some(shm) = self.0.shared_memory.clone() else {
            return Err(Status::failed_precondition(
                "this generator-node takes no shared-memory pushes (shared_memory_dir); stream the step",
            ));
        };
        let header = step
            .header
            .ok_or_else(|| Status::invalid_argument("shared step without a header"))?;
        let total = header.total_bytes;
        if total > self.0.max_step_bytes {
            return Err(chunk::ChunkError::TooLarge {
                what: "field data",
                declared: total,
                limit: self.0.max_step_bytes,
            }
            .into());
        }
        let wanted = self.wanted_field(header.step);
        let (info, mut window) = check_step(&header, wanted.as_deref())?;
        self.0.layout.admit(&info)?;
        let file = shm.open(&step.path, total)?;
        let mut field = info.assembler(self.0.spare_fields.take());
        let field = tokio::task::spawn_blocking(move || {
            crate::shm::read_payload(file, total, &mut window, &mut field).map(|()| field)
        })
        .await
        .map_err(|e| Status::internal(format!("reading the shared-memory file: {e}")))??;
        Ok(info.with_field(field)?.named(&header, wanted.as_deref()))
    }

    /// Spools, announces and queues a received step, and the reply to its push.
    ///
    /// # Errors
    /// As [`Self::spool`] and [`Self::enqueue`].
    pub(crate) async fn accept(&self, mut raw: RawStep) -> Result<Response<pb::PushReply>, Status> {
        self.spool(&mut raw).await?;
        self.0
            .received
            .fetch_max(raw.info.step + 1, std::sync::atomic::Ordering::SeqCst);
        // Checked once the step's ranks are all in; logged the first time it fails.
        let _ = self.0.layout.record(&raw.info, &raw.field);
        crate::faces::send(&self.0);
        self.propose_scene(&raw);
        let (dropped, received) = self.enqueue(raw).await?;
        let s = &self.0;
        Ok(Response::new(pb::PushReply {
            queue_depth: s.queue.len() as u32,
            dropped_by_push: dropped,
            steps_received: received,
            epoch: s.epoch,
        }))
    }

    /// With a spool: `raw` on disk (fsync'd when durable) before it is acknowledged, and its
    /// spool name recorded in it.
    ///
    /// # Errors
    /// `RESOURCE_EXHAUSTED` when the spool has no room for it, `UNAVAILABLE` when it cannot
    /// be written.
    async fn spool(&self, raw: &mut RawStep) -> Result<(), Status> {
        let Some(spool) = &self.0.spool else {
            return Ok(());
        };
        let name = spool.put(raw).await.map_err(|e| match e {
            crate::spool::SpoolError::TooLarge { .. } => Status::resource_exhausted(e.to_string()),
            crate::spool::SpoolError::Io { .. } => Status::unavailable(e.to_string()),
        })?;
        raw.spool = Some(name);
        Ok(())
    }

    /// Why steps of `ranks` (every rank's when empty) could not be composed at the viz-node,
    /// once per rank: the steps of several ranks shipped since, whose composition the viz-node
    /// has decided (a step not composed yet is asked again at the next flush). `None` when
    /// all composed, or the viz-node cannot say now.
    async fn composition_errors(&self, ranks: &[u32]) -> Option<String> {
        let shards = &self.0.viz_shards;
        if shards.is_empty() {
            return None;
        }
        let asked: Vec<u64> = {
            let composing = self.0.composing.lock().unwrap_or_else(|e| e.into_inner());
            composing
                .iter()
                .filter(|(_, r)| ranks.is_empty() || r.iter().any(|k| ranks.contains(k)))
                .map(|(step, _)| *step)
                .collect()
        };
        if asked.is_empty() {
            return None;
        }
        // Each step from the shard it went to.
        let mut outcomes = Vec::new();
        for (k, viz) in shards.iter().enumerate() {
            let steps: Vec<u64> = asked
                .iter()
                .copied()
                .filter(|&s| self.0.shard_of(s) == k)
                .collect();
            if !steps.is_empty() {
                outcomes.extend(crate::scene::step_outcomes(viz, steps).await.ok()?);
            }
        }
        let mut errors = Vec::new();
        let mut composing = self.0.composing.lock().unwrap_or_else(|e| e.into_inner());
        for o in outcomes {
            let Some(r) = composing.get_mut(&o.step) else {
                continue;
            };
            let before = r.len();
            r.retain(|k| !(ranks.is_empty() || ranks.contains(k)));
            if !o.error.is_empty() && r.len() < before {
                // The viz-node's reason names the step.
                errors.push((o.step, o.error));
            }
            if r.is_empty() {
                composing.remove(&o.step);
            }
        }
        errors.sort_unstable();
        let (_, first) = errors.first()?;
        // One reason, the first step's: a decomposition at fault repeats it at every step.
        let mut steps: Vec<String> = errors.iter().take(10).map(|(s, _)| s.to_string()).collect();
        if errors.len() > steps.len() {
            steps.push("…".into());
        }
        Some(format!(
            "flush: {} step(s) of your ranks could not be composed at the viz-node (steps {}); the first: {first}",
            errors.len(),
            steps.join(", ")
        ))
    }

    /// Reports `raw`'s value range to the scene agreement while no TF is fixed.
    fn propose_scene(&self, raw: &RawStep) {
        let Some(scene) = &self.0.scene else {
            return;
        };
        // A read of one field, not a copy of the settings, on every push.
        let no_tf = self
            .0
            .generation
            .read()
            .unwrap_or_else(|e| e.into_inner())
            .tf
            .is_none();
        if no_tf {
            scene.propose(raw);
        }
    }

    /// Queues `raw` (waiting for room, or dropping by the queue's policy) and counts it:
    /// the steps it dropped and the steps received so far.
    ///
    /// # Errors
    /// `UNAVAILABLE` when the node is shutting down.
    async fn enqueue(&self, raw: RawStep) -> Result<(u64, u64), Status> {
        let (step, rank, n) = (raw.info.step, raw.info.rank, raw.bytes());
        let span = info_span!("receive", step, rank, bytes = n);
        // Announced before the worker can finish it: its host's other ranks wait for it.
        self.0.host.received(step, rank, raw.info.world_size);
        let dropped = self
            .0
            .queue
            .push(raw, n)
            .instrument(span)
            .await
            .map_err(|_| {
                self.0.host.settled(step, rank);
                Status::unavailable("the generator-node is shutting down")
            })?;
        let n_dropped = dropped.len() as u64;
        for d in dropped {
            info!(step = d.info.step, rank = d.info.rank, policy = %self.0.queue.policy(), "dropped a queued step");
            self.0.host.settled(d.info.step, d.info.rank);
            self.0.layout.made(d.info.step);
            self.0.unspool(d.spooled().as_ref());
            self.0.spare_fields.put(d.field);
        }
        let mut received = 0;
        self.0.stats.update(|c| {
            c.received += 1;
            c.dropped_queue += n_dropped;
            received = c.received;
        });
        Ok((n_dropped, received))
    }
}

#[tonic::async_trait]
impl Generator for GeneratorService {
    async fn push_step(
        &self,
        request: Request<Streaming<pb::StepChunk>>,
    ) -> Result<Response<pb::PushReply>, Status> {
        let raw = self.receive(request.into_inner()).await?;
        self.accept(raw).await
    }

    async fn push_shared(
        &self,
        request: Request<pb::SharedStep>,
    ) -> Result<Response<pb::PushReply>, Status> {
        let raw = self.receive_shared(request.into_inner()).await?;
        self.0.stats.update(|c| c.shared_pushes += 1);
        self.accept(raw).await
    }

    async fn set_config(
        &self,
        request: Request<pb::GenerationConfig>,
    ) -> Result<Response<pb::ConfigReply>, Status> {
        let c = request.into_inner();
        let reply = {
            let mut g = self.0.generation.write().unwrap_or_else(|e| e.into_inner());
            *g = apply_config(&g, &c)?;
            info!(r = g.params.resolution, gamma = g.params.gamma, codec = %g.codec, "new generation config");
            pb::ConfigReply {
                resolution: g.params.resolution,
                gamma: g.params.gamma,
            }
        };
        self.0.save_run();
        Ok(Response::new(reply))
    }

    async fn get_status(
        &self,
        _: Request<pb::StatusRequest>,
    ) -> Result<Response<pb::GeneratorStatus>, Status> {
        Ok(Response::new(self.0.status()))
    }

    async fn flush(
        &self,
        request: Request<pb::FlushRequest>,
    ) -> Result<Response<pb::GeneratorStatus>, Status> {
        let request = request.into_inner();
        let t = request.timeout_secs;
        let timeout = if t.is_finite() && t > 0.0 {
            t.min(86_400.0)
        } else {
            600.0
        };
        let s = &self.0;
        let target = s.stats.get().received;
        let shipping = s.shipping;
        tokio::time::timeout(
            Duration::from_secs_f64(timeout),
            s.stats.wait_for(|c| c.settled(shipping) >= target),
        )
        .await
        .map_err(|_| {
            let why = s.stats.ship_error();
            let why = if !why.is_empty() {
                why
            } else if let Some(gathering) = s.host.waiting() {
                gathering
            } else if s.stats.get().viz_connected {
                "the viz-node is connected: the steps are still being made or shipped".to_owned()
            } else {
                "is the viz-node reachable?".to_owned()
            };
            Status::deadline_exceeded(format!(
                "flush: not all of {target} steps were shipped within {timeout} s ({why})"
            ))
        })?;
        // Refusals of the flushing client's ranks since their last flush make this one fail,
        // naming the last cause: the steps were received, but the viz-node did not store
        // their VDIs. Another rank's refusals are left for that rank's client.
        if let Some(why) = self.composition_errors(&request.ranks).await {
            return Err(Status::failed_precondition(why));
        }
        if let Some((n, why)) = s.refusals.take(&request.ranks) {
            return Err(Status::failed_precondition(format!(
                "flush: the viz-node refused {n} VDI(s) of {} since the last flush; last: {why}",
                if request.ranks.is_empty() {
                    "this node".to_owned()
                } else {
                    format!("rank(s) {:?}", request.ranks)
                }
            )));
        }
        Ok(Response::new(s.status()))
    }
}
