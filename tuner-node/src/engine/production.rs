//! A production step in the engine's loop: its summary (σ, τ, histogram) and quality report,
//! what makes it characteristic or a tuning due, and the closed-loop correction after it
//! (docs/tuning.md, "A new character" and "The control loop").

use super::*;

impl Loop {
    /// Lets the nodes drop an evicted step's field, after the running tuning if there is one
    /// (it searches over the steps it started with; dropping one under it would fail it, and
    /// a field that drifts faster than a tuning takes would never be tuned for).
    pub(super) fn release_evicted(&mut self, step: u64) {
        if self.engine.counters().tuning {
            self.deferred.push(step);
        } else {
            self.engine.hub.hold(step, false);
        }
    }

    /// After a tuning: releases the fields [`Self::release_evicted`] kept for it.
    pub(super) fn tuning_ended(&mut self) {
        let keep = self.engine.state().tracker.step_indices();
        for step in std::mem::take(&mut self.deferred) {
            if !keep.contains(&step) {
                self.engine.hub.hold(step, false);
            }
        }
    }

    pub(super) fn summary(&mut self, conn: u64, s: pb::StepSummary) {
        let e = self.engine.clone();
        e.counters().summaries += 1;
        e.domain().saw(&s);
        if s.held {
            e.hub.held(conn, s.step, s.rank);
        }
        // Progress first: a decision made for this step applies past it.
        let newest = e
            .progress
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .saw(s.step, s.begun, s.received, conn);
        let p = self.pending.entry(s.step).or_insert(Pending {
            world_size: s.world_size,
            counts: [0; BINS],
            ranks: 0,
            sigma_bytes: 0,
            tau_secs: 0.0,
            pm_version: s.pm_version,
            scene_version: s.scene_version,
            range: (s.range_lo, s.range_hi),
            candidate: Candidate {
                r: s.resolution,
                gamma: s.gamma,
                precision: precision_of(s.precision_bits),
            },
            sampled: s.sampled,
            nodes: Vec::new(),
        });
        if !p.nodes.contains(&conn) {
            p.nodes.push(conn);
        }
        for (c, &n) in p.counts.iter_mut().zip(&s.histogram) {
            *c += n;
        }
        p.ranks += 1;
        p.sigma_bytes += s.sigma_bytes;
        p.tau_secs = p.tau_secs.max(s.tau_secs);
        if p.ranks >= p.world_size {
            if let Some(p) = self.pending.remove(&s.step) {
                self.complete(s.step, p);
            }
        }
        let stale: Vec<u64> = self
            .pending
            .keys()
            .chain(self.awaiting.keys())
            .copied()
            .filter(|&k| k + STALE_STEPS < newest)
            .collect();
        for k in stale {
            if self.pending.remove(&k).is_some() {
                warn!(
                    step = k,
                    "not every rank of the step was summarised; it is left out"
                );
            }
            self.awaiting.remove(&k);
            e.hub.hold(k, false);
        }
    }

    /// σ and τ of a production step against the budget (σ summed over ranks, τ the slowest).
    fn over_budget(&self, p: &Pending) -> Option<Break> {
        let budgets = self.engine.resolved().budgets();
        let (size, time) = (budgets.size_bytes, budgets.time_secs);
        if let Some(t) = size.filter(|&t| p.sigma_bytes >= t) {
            return Some(Break::Size(format!(
                "σ {} B ≥ σ_target {t} B",
                p.sigma_bytes
            )));
        }
        if let Some(t) = time.filter(|&t| p.tau_secs >= t) {
            return Some(Break::Time(format!(
                "τ {:.4} s ≥ τ_target {t} s",
                p.tau_secs
            )));
        }
        None
    }

    /// Why the production step `p` (made under the tuning whose decision is version
    /// `tuned`, or a correction of it) starts a re-tuning, if it does: a σ over the budget at
    /// once, a τ over it when it is the `time_breaks`-th such step in a row under that tuning.
    fn retunes(&mut self, tuned: u64, p: &Pending) -> Option<String> {
        let version = tuned;
        let streak = if self.slow.0 == version {
            self.slow.1
        } else {
            0
        };
        // The reason, if any, and the run of slow steps left behind (none after a re-tuning).
        let (why, run) = match self.over_budget(p) {
            Some(Break::Size(why)) => (Some(why), 0),
            Some(Break::Time(why)) => {
                let (n, needed) = (streak + 1, self.engine.cfg.time_breaks);
                if n < needed {
                    (None, n)
                } else if needed > 1 {
                    (Some(format!("{why}, {n} steps in a row")), 0)
                } else {
                    (Some(why), 0)
                }
            }
            None => (None, 0),
        };
        self.slow = (version, run);
        why
    }

    /// The version of the last tuning's decision, when no tuning is pending or running: a
    /// production step made with it or a later version (a correction of it) is held against
    /// what that tuning measured. `validated` also asks that the decision was found best on
    /// the characteristic steps as they are (after a forced step, the re-tuning that takes it
    /// into account must finish first; after a failed one, only a new characteristic step
    /// starts another).
    fn unforced_tuning(&self, validated: bool) -> Option<u64> {
        if self.dirty.is_some() || self.engine.counters().tuning {
            return None;
        }
        let s = self.engine.state();
        s.tuned()
            .filter(|_| !validated || s.validated == s.tracker.step_indices())
            .map(|d| d.pm_version)
    }

    /// Whether the production step made with version `v` has a size miss (see
    /// [`Cause::SizeMiss`]): σ at least `characteristic.sigma_miss` times `planned`, made under
    /// the last tuning (no tuning pending or running) with the `P_M` of the step before
    /// (`steady`). The plan for a `P_M` production has not made yet is the surface's
    /// interpolation, whose error at one candidate can be as large (on Gray–Scott 128³ a
    /// correction to r 192, γ 0.009 planned at 239 kB made 805 kB); the next step's plan
    /// rests on that step's own σ.
    fn size_miss(&self, v: u64, p: &Pending, planned: Option<f64>, steady: bool) -> Option<Cause> {
        let threshold = self.engine.cfg.characteristic.sigma_miss;
        let planned_bytes = planned.filter(|_| steady)?;
        let Some(tuned) = self.unforced_tuning(false) else {
            return self.size_jump(v, p, threshold);
        };
        (v >= tuned && p.sigma_bytes as f64 >= threshold * planned_bytes).then_some(
            Cause::SizeMiss {
                sigma_bytes: p.sigma_bytes,
                planned_bytes,
                threshold,
            },
        )
    }

    /// While the tuning for the last step that missed its plan is due or running: whether the
    /// production step made with version `v` (with the `P_M` of the step before) is that
    /// step's `P_M` at `threshold` times its σ or more ([`Cause::SizeJump`]). A field that
    /// drifts within a factor of `threshold` of it is left to that tuning.
    fn size_jump(&self, v: u64, p: &Pending, threshold: f64) -> Option<Cause> {
        let m = self
            .missed
            .filter(|m| m.pm_version == v && m.candidate == p.candidate && m.sigma_bytes > 0)?;
        (p.sigma_bytes as f64 >= threshold * m.sigma_bytes as f64).then_some(Cause::SizeJump {
            sigma_bytes: p.sigma_bytes,
            than_step: m.step,
            than_bytes: m.sigma_bytes,
            threshold,
        })
    }

    fn force(
        &mut self,
        step: u64,
        h: &[f64; BINS],
        world_size: u32,
        production: Option<(Candidate, insitu_core::evaluate::Sizing)>,
        cause: Cause,
    ) {
        let e = self.engine.clone();
        let evicted = {
            let mut s = e.state();
            let ev = s.force(step, h, world_size);
            if let Some((c, sizing)) = production {
                s.add_production(step, c, sizing, e.process);
            }
            e.save(&s);
            ev
        };
        e.hub.hold(step, true);
        if let Some((gone, d)) = evicted {
            info!(
                evicted = gone,
                nearest = d,
                "evicted the most redundant characteristic step"
            );
            self.release_evicted(gone);
        }
        let trigger = Trigger { step, cause };
        info!(step, reason = %trigger, "step becomes characteristic");
        self.mark_dirty(trigger);
    }

    /// A tuning is due for `trigger`; a running one is cut short for it, unless the last one
    /// was or no decision but a provisional one is in force yet (the first decision, even on
    /// fewer steps, is worth more than a better one later: the nodes run on the configured or
    /// a provisional P_M until it comes).
    pub(super) fn mark_dirty(&mut self, trigger: Trigger) {
        let decided = self.engine.state().decisions.iter().any(|d| !d.provisional);
        if decided && self.engine.counters().tuning && !self.cut_last {
            self.engine.superseded.store(true, Ordering::SeqCst);
        }
        self.dirty = Some(trigger);
    }

    /// Closed-loop control after production step `step` (all ranks in): the controller
    /// records it and, when the `P_M` in force misses the plan for the step a decision made
    /// now would apply from (or a finer one clears it), pushes a correction of the tuned
    /// decision. Nothing before the first tuning, without a budget, or while no candidate of
    /// the tuning was measured.
    fn control(&mut self, step: u64, p: &Pending, planned_sigma_bytes: Option<f64>) {
        let e = self.engine.clone();
        // A step made before any decision at an r the node lowered itself to keep the budget
        // (generator-node/src/correct.rs) is no plan of the tuner's, and its candidate lies off
        // the tuning's grid: its σ against the surface's interpolation would be read as
        // growth. Only steps at the configured P_M or a decision's inform the forecast.
        let configured = *e.reported.lock().unwrap_or_else(|p| p.into_inner());
        if p.pm_version == 0 && configured.is_some_and(|c| c != p.candidate) {
            return;
        }
        let mut ctl = e.control();
        if !ctl.active() {
            return;
        }
        ctl.observe(Observation {
            step,
            candidate: p.candidate,
            sigma_bytes: p.sigma_bytes,
            tau_secs: p.tau_secs,
            planned_sigma_bytes,
        });
        let at = e.decision_start();
        let (tuned, current, surface, next) = {
            let s = e.state();
            let (Some(t), Some(c)) = (s.tuned(), s.current()) else {
                return;
            };
            if t.scene_version != s.scene_version() {
                // Tuned under an earlier scene: its measurements say nothing of this one.
                return;
            }
            (
                t.clone(),
                c.candidate,
                s.surface(&t.characteristic_steps),
                s.next_version(),
            )
        };
        let Some(plan) = ctl.correct(&surface, tuned.ceiling(), current, at) else {
            return;
        };
        debug!(
            step,
            r = plan.candidate.r,
            gamma = plan.candidate.gamma,
            surface_sigma = surface.sigma(plan.candidate),
            planned_sigma = plan.sigma_bytes,
            k = plan.forecast.sigma,
            steps = ?tuned.characteristic_steps,
            "correction planned"
        );
        let miss = ctl.miss();
        let broke = ctl
            .sigma_target
            .filter(|&t| p.sigma_bytes as f64 >= t && p.pm_version > tuned.pm_version)
            .map(|t| {
                format!(
                    "; step {step} was over the budget (σ {} B ≥ {t:.0} B) under a correction: this correction takes it up, no tuning",
                    p.sigma_bytes
                )
            });
        drop(ctl);
        let k = plan.forecast;
        let mut notes = if miss >= 1.005 {
            format!(", planned {miss:.2}× below the budget for the model's last miss")
        } else {
            String::new()
        };
        if !plan.feasible {
            notes.push_str(INFEASIBLE);
        }
        notes.push_str(broke.as_deref().unwrap_or(""));
        let reason = format!(
            "correction after step {step}: production σ {:.2}× the tuning's measurements at its P_M, forecast {:.2}× by step {}; {} kB planned under {}{notes}",
            k.sigma_now,
            k.sigma,
            k.at,
            (plan.sigma_bytes / 1e3).round(),
            e.utility_description()
        );
        let q = q_on(&e.state(), &tuned.characteristic_steps, plan.candidate);
        e.publish(Decision {
            pm_version: next,
            candidate: plan.candidate,
            old: Some(current),
            characteristic_steps: tuned.characteristic_steps.clone(),
            predicted: planned(&plan, q),
            reason,
            trigger_step: step,
            trials: 0,
            trial_secs: 0.0,
            utility_description: e.utility_description(),
            from_step: at,
            corrects: Some(tuned.pm_version),
            tuned: None,
            forecast_ratio: Some(k.sigma),
            scene_version: 0,
            steered: false,
            provisional: false,
        });
    }

    fn complete(&mut self, step: u64, p: Pending) {
        let e = self.engine.clone();
        e.domain().histogram = Some(StepHistogram {
            step,
            counts: p.counts.to_vec(),
            lo: p.range.0,
            hi: p.range.1,
        });
        if !self.under_scene_in_force(step, &p) {
            e.hub.hold(step, false);
            return;
        }
        let Ok(h) = normalise(&p.counts) else { return };
        self.recent.push_back((step, h));
        if self.recent.len() > STALE_STEPS as usize {
            self.recent.pop_front();
        }
        // What the decision the step was made under planned for it, and whether it was
        // provisional: such a step's r lies off the tuning's grid, like one the node lowered.
        let (planned, provisional) = {
            let s = e.state();
            let d = s
                .decisions
                .iter()
                .rev()
                .find(|d| d.pm_version == p.pm_version && d.candidate == p.candidate);
            (
                d.map(|d| d.predicted.sizing.sigma_bytes as f64)
                    .filter(|&b| b > 0.0),
                d.is_some_and(|d| d.provisional),
            )
        };
        if !provisional {
            self.control(step, &p, planned);
        }
        self.provisional(step, &p);
        let production = Some((p.candidate, p.sizing()));
        let steady = self.last_candidate.replace(p.candidate) == Some(p.candidate);
        let cause = self
            .size_miss(p.pm_version, &p, planned, steady)
            .or_else(|| {
                // A broken budget re-tunes for a step made with the tuned decision itself; one
                // made under a correction is the forecast's miss, which the next correction
                // takes up (its reason says so).
                let tuned = self.unforced_tuning(true).filter(|&t| p.pm_version == t)?;
                let why = self.retunes(tuned, &p)?;
                Some(Cause::BrokeBudget { why })
            });
        if let Some(cause) = cause {
            if matches!(cause, Cause::SizeMiss { .. } | Cause::SizeJump { .. }) {
                self.missed = Some(Missed {
                    step,
                    pm_version: p.pm_version,
                    candidate: p.candidate,
                    sigma_bytes: p.sigma_bytes,
                });
            }
            self.force(step, &h, p.world_size, production, cause);
            return;
        }
        let verdict = {
            let mut s = e.state();
            let v = s.observe(step, &h, p.world_size);
            if matches!(v, Verdict::New { .. }) {
                s.add_production(step, p.candidate, p.sizing(), e.process);
                e.save(&s);
            }
            v
        };
        match verdict {
            Verdict::New { distance, evicted } => {
                e.hub.hold(step, true);
                if let Some((gone, d)) = evicted {
                    info!(evicted = gone, nearest = d, max = e.cfg.characteristic.max, "evicted the most redundant characteristic step (its nearest other one is closest)");
                    self.release_evicted(gone);
                }
                let cause = match distance {
                    None => Cause::First,
                    Some(d) => Cause::NewCharacter {
                        distance: d,
                        threshold: e.cfg.characteristic.threshold,
                    },
                };
                let trigger = Trigger { step, cause };
                info!(step, reason = %trigger, "characteristic step");
                self.mark_dirty(trigger);
            }
            Verdict::Alike { .. } if p.sampled && e.cfg.viz.is_some() => {
                // Keep the field until its q is known: a q far below the prediction makes
                // the step characteristic, and then its field is needed.
                self.awaiting.insert(
                    step,
                    AwaitingQ {
                        world_size: p.world_size,
                        mses: Vec::new(),
                        pm_version: p.pm_version,
                    },
                );
            }
            Verdict::Alike { .. } => e.hub.hold(step, false),
        }
    }

    pub(super) fn report(&mut self, r: &pb::QualityReport) {
        let Some(q) = r.q_db else { return };
        let Some(a) = self.awaiting.get_mut(&r.step) else {
            return;
        };
        a.mses.push(mse_from_psnr(q));
        // A composed report is the whole step's q (the viz-node composes steps of several
        // ranks); otherwise (older viz-nodes) the ranks' MSEs are summed once all are in, as
        // `combine_ranks` estimates a composed step's error from its bricks'.
        if !r.composed && a.mses.len() < r.world_size.max(a.world_size) as usize {
            return;
        }
        let Some(a) = self.awaiting.remove(&r.step) else {
            return;
        };
        let q = psnr_from_mse(a.mses.iter().sum::<f64>());
        let e = self.engine.clone();
        let predicted = e
            .state()
            .current()
            .filter(|d| !d.steered)
            .map(|d| d.predicted.q());
        if let (Some(v), Some(pq)) = (self.unforced_tuning(true), predicted) {
            if a.pm_version >= v && q < pq - e.cfg.q_margin_db {
                let h = self.recent.iter().find(|(s, _)| *s == r.step).map(|x| x.1);
                if let Some(h) = h {
                    let why = format!(
                        "q {q:.2} dB is more than {} dB below the predicted {pq:.2} dB",
                        e.cfg.q_margin_db
                    );
                    self.force(r.step, &h, a.world_size, None, Cause::BrokeBudget { why });
                    return;
                }
            }
        }
        e.hub.hold(r.step, false);
    }
}
