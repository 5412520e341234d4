//! Steering in the engine's loop: a steered scene or utility versioned, pushed and tuned for
//! afresh (docs/steering.md), and whether a production step was made under the scene in
//! force.

use super::*;

impl Loop {
    /// Whether production step `step` was made under the steered scene in force (its
    /// histogram and σ then say something of it); the first such step of a pending change
    /// marks the change applied (docs/steering.md).
    pub(super) fn under_scene_in_force(&mut self, step: u64, p: &Pending) -> bool {
        let e = self.engine.clone();
        let mut s = e.state();
        if p.scene_version < s.scene_version() {
            return false;
        }
        let mut changed = false;
        for r in &mut s.steering {
            if r.standing == Standing::Pending && r.scene_version <= p.scene_version {
                r.standing = Standing::Applied;
                changed = true;
                info!(
                    scene_version = r.scene_version,
                    step, "steered scene applied"
                );
            }
        }
        if changed {
            e.save(&s);
        }
        true
    }

    /// A steering request (docs/steering.md): checked; a utility change re-tunes over the
    /// characteristic steps; a scene change becomes the next scene version, pushed at once in
    /// a decision of the `P_M` in force, supersedes a change not applied yet, and starts the
    /// tuner afresh for the new scene (the old scene's characteristic steps released, a
    /// running tuning cut short, the controller reset): the first step made under it is
    /// characteristic.
    pub(super) fn steer(&mut self, req: pb::SteerRequest) -> Result<pb::SteerReply, tonic::Status> {
        let e = self.engine.clone();
        let scene = e.state().scene();
        let change = crate::steer::check(&req, &scene, &e.domain())
            .map_err(tonic::Status::invalid_argument)?;
        let resolved = change
            .utility
            .as_deref()
            .map(|u| resolve_with(&e.cfg, u))
            .transpose()
            .map_err(|err| tonic::Status::invalid_argument(format!("utility: {err}")))?;
        let carrier = {
            let s = e.state();
            s.current()
                .map(|d| d.candidate)
                .or(*e.reported.lock().unwrap_or_else(|p| p.into_inner()))
        };
        if change.scene.is_some() && carrier.is_none() {
            return Err(tonic::Status::failed_precondition(
                "no generator-node has attached yet: a scene change travels in a decision, and there is no P_M to carry it",
            ));
        }
        let at = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0.0, |d| d.as_secs_f64());
        let newest = self.recent.back().map_or(0, |(s, _)| *s);
        if let (Some(u), Some(r)) = (change.utility.clone(), resolved) {
            let retune_from = change.scene.is_none().then_some(newest);
            self.steer_utility(u, r, (&req.who, at), retune_from);
        }
        let Some((mut next, candidate)) = change.scene.zip(carrier) else {
            return Ok(pb::SteerReply {
                scene_version: scene.version,
                utility_description: e.utility_description(),
                ..Default::default()
            });
        };
        let from_step = e.decision_start();
        let (version, pm_version, superseded, released) = {
            let mut s = e.state();
            next.version = s.scene_version() + 1;
            let version = next.version;
            let pm_version = s.next_version();
            let mut superseded = Vec::new();
            for r in &mut s.steering {
                if r.standing == Standing::Pending && r.scene_version > 0 {
                    r.standing = Standing::Superseded;
                    superseded.push(r.scene_version);
                }
            }
            s.scenes.push(next);
            s.steering.push(SteerRecord {
                scene_version: version,
                pm_version,
                from_step,
                standing: Standing::Pending,
                change: change.words.clone(),
                who: req.who.clone(),
                at_unix_secs: at,
            });
            // The old scene's characteristic steps and validation say nothing of the new one.
            let released = s.tracker.step_indices();
            for step in &released {
                s.forget(*step);
            }
            s.validated.clear();
            // Saved with the decision (`publish`).
            (version, pm_version, superseded, released)
        };
        for step in released {
            self.release_evicted(step);
        }
        self.dirty = None;
        self.recent.clear();
        if e.counters().tuning {
            e.superseded.store(true, Ordering::SeqCst);
        }
        e.restart_control();
        let who = if req.who.is_empty() {
            String::new()
        } else {
            format!(" by {}", req.who)
        };
        e.publish(Decision {
            pm_version,
            candidate,
            old: Some(candidate),
            characteristic_steps: Vec::new(),
            predicted: unmeasured(candidate),
            reason: format!("scene {version} steered{who}: {}", change.words),
            trigger_step: newest,
            trials: 0,
            trial_secs: 0.0,
            utility_description: e.utility_description(),
            from_step,
            corrects: None,
            tuned: None,
            forecast_ratio: None,
            scene_version: version,
            steered: true,
            provisional: false,
        });
        info!(scene_version = version, pm_version, from_step, superseded = ?superseded, change = %change.words, "scene steered");
        Ok(pb::SteerReply {
            scene_version: version,
            pm_version,
            from_step,
            utility_description: e.utility_description(),
            superseded,
        })
    }

    /// A steered utility `u` (resolved as `r`) put in force: recorded, the nodes told their
    /// budget, and the characteristic steps re-tuned from `retune_from` where there are some
    /// (`None` when a scene change in the same request starts the tuner afresh anyway).
    fn steer_utility(
        &mut self,
        u: String,
        r: Resolved,
        (who, at): (&str, f64),
        retune_from: Option<u64>,
    ) {
        let e = self.engine.clone();
        *e.resolved.write().unwrap_or_else(|p| p.into_inner()) = Arc::new(r);
        e.restart_control();
        let mut s = e.state();
        s.utility = Some(u.clone());
        s.steering.push(SteerRecord {
            scene_version: 0,
            pm_version: 0,
            from_step: 0,
            standing: Standing::Applied,
            change: format!("utility {u}"),
            who: who.to_string(),
            at_unix_secs: at,
        });
        // The decision in force was found best for the old utility.
        s.validated.clear();
        e.save(&s);
        let retune = retune_from.filter(|_| !s.tracker.steps.is_empty());
        drop(s);
        info!(utility = %e.utility_description(), who = %who, "utility steered");
        e.hub.broadcast(&Down::Budget(e.node_budget()));
        if let Some(step) = retune {
            self.mark_dirty(Trigger {
                step,
                cause: Cause::Steered {
                    what: format!("utility {u}"),
                },
            });
        }
    }
}
