//! One scene per world: the default transfer function is agreed here, over the global value
//! range of the run's first step, and then fixed for the run (`AgreeScene` in the proto).
//!
//! Each rank's generator-node reports its brick's finite range of the first step it receives;
//! when every rank `0..world_size` has reported, the TF is the default over
//! `[min of the minima, max of the maxima]`, written atomically to `scene.json` in the
//! recording, and every later call (a restarted node's too) is answered with it, whatever
//! range it reports. A rank that never reports (it died before its first push) does not stall
//! the others for ever: `timeout` after the first report, the scene is fixed over the ranks
//! that did report, and `scene.json` lists them. The viz-node is the meeting point because every generator-node already
//! reaches it and it owns the recording that must stay consistent; without a viz-node a
//! generator-node falls back to its own brick's range (and says so).

use insitu_core::TransferFunction;
use insitu_recording::store::{write_atomic, StoreError};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::time::{Duration, Instant};
use tokio::sync::watch;
use tonic::Status;

/// The file in the recording that fixes the run's scene.
pub const SCENE: &str = "scene.json";

/// The agreed scene, as recorded.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Agreed {
    /// The transfer function.
    pub tf: TransferFunction,
    /// Its name, `default[lo, hi]`.
    pub tf_name: String,
    /// Ranks of the world that agreed.
    pub world_size: u32,
    /// The step whose ranges were pooled.
    pub step: u64,
    /// The ranks whose ranges were pooled (all of the world unless some never reported within
    /// the timeout).
    #[serde(default)]
    pub ranks: Vec<u32>,
}

#[derive(Default)]
struct Proposals {
    world_size: Option<u32>,
    step: u64,
    ranges: BTreeMap<u32, (f64, f64)>,
    first_at: Option<Instant>,
}

impl Proposals {
    /// The scene over the ranks reported so far.
    fn agree(&self, world_size: u32) -> Agreed {
        let finite = |v: f64| v.is_finite().then_some(v);
        let lo = self
            .ranges
            .values()
            .filter_map(|r| finite(r.0))
            .reduce(f64::min);
        let hi = self
            .ranges
            .values()
            .filter_map(|r| finite(r.1))
            .reduce(f64::max);
        // All-NaN data: the default over [0, 1], as one node alone would choose.
        let (lo, hi) = match (lo, hi) {
            (Some(lo), Some(hi)) => (lo as f32, hi as f32),
            _ => (0.0, 1.0),
        };
        let named = TransferFunction::default_named(lo, hi);
        Agreed {
            tf: named.tf,
            tf_name: named.name,
            world_size,
            step: self.step,
            ranks: self.ranges.keys().copied().collect(),
        }
    }
}

/// The agreement, shared by every `AgreeScene` call.
pub struct SceneAgreement {
    path: PathBuf,
    timeout: Duration,
    proposals: Mutex<Proposals>,
    agreed: watch::Sender<Option<Agreed>>,
}

/// Longest wait a caller may ask for, seconds.
pub const MAX_WAIT_SECS: f64 = 3600.0;

impl SceneAgreement {
    /// Opens the agreement of the recording in `dir` (reading `scene.json` when present);
    /// `timeout` after the first rank's report, the scene is fixed over the ranks reported.
    ///
    /// # Errors
    /// [`StoreError::Corrupt`] when `scene.json` exists but cannot be read (never replaced
    /// silently: the run's colours depend on it).
    pub fn open(dir: &Path, timeout: Duration) -> Result<Self, StoreError> {
        let path = dir.join(SCENE);
        let agreed =
            match std::fs::read(&path) {
                Ok(bytes) => Some(serde_json::from_slice::<Agreed>(&bytes).map_err(|e| {
                    StoreError::Corrupt {
                        path: path.clone(),
                        problem: format!("{e}; move it away to agree a new scene"),
                    }
                })?),
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => None,
                Err(source) => return Err(StoreError::Io { path, source }),
            };
        Ok(Self {
            path,
            timeout,
            proposals: Mutex::new(Proposals::default()),
            agreed: watch::channel(agreed).0,
        })
    }

    /// Records `agreed` in `scene.json` and answers every waiter (the first to fix it wins).
    fn fix(&self, agreed: Agreed) -> Result<(), Status> {
        // One writer at a time: a complete agreement and a timed-out one may race.
        let _writer = self.proposals.lock().unwrap_or_else(|e| e.into_inner());
        if self.agreed().is_some() {
            return Ok(());
        }
        let json = serde_json::to_vec_pretty(&agreed)
            .map_err(|e| Status::internal(format!("scene: {e}")))?;
        let dir = self.path.parent().unwrap_or(Path::new("."));
        write_atomic(dir, SCENE, &json).map_err(|e| Status::internal(e.to_string()))?;
        tracing::info!(tf = %agreed.tf_name, ranks = ?agreed.ranks, "scene agreed for the run");
        self.agreed.send_if_modified(|a| {
            if a.is_none() {
                *a = Some(agreed);
                true
            } else {
                false
            }
        });
        Ok(())
    }

    /// The agreed scene, if any.
    pub fn agreed(&self) -> Option<Agreed> {
        self.agreed.borrow().clone()
    }

    /// Records rank `rank`'s range and waits (at most `wait`) until the scene is agreed: by
    /// the last rank's report, or by the agreement's timeout over the ranks reported.
    ///
    /// # Errors
    /// `INVALID_ARGUMENT` for a rank outside the world or a second world size;
    /// `DEADLINE_EXCEEDED` naming the ranks still missing after `wait`; `INTERNAL` when
    /// `scene.json` cannot be written.
    pub async fn propose(
        &self,
        p: &insitu_proto::pb::SceneProposal,
        wait: Duration,
    ) -> Result<Agreed, Status> {
        if let Some(a) = self.agreed() {
            return Ok(a);
        }
        if p.world_size == 0 || p.rank >= p.world_size {
            return Err(Status::invalid_argument(format!(
                "step {} rank {} of world size {}: need 0 ≤ rank < world_size",
                p.step, p.rank, p.world_size
            )));
        }
        let (complete, deadline) = self.record(p)?;
        if let Some(agreed) = complete {
            self.fix(agreed)?;
        }
        let mut rx = self.agreed.subscribe();
        let until_timeout = deadline.saturating_duration_since(Instant::now());
        let waited =
            tokio::time::timeout(wait.min(until_timeout), rx.wait_for(Option::is_some)).await;
        match waited {
            Ok(Ok(a)) => a.clone().ok_or_else(|| Status::internal("scene lost")),
            Ok(Err(_)) => Err(Status::unavailable("the viz-node is shutting down")),
            Err(_) if Instant::now() >= deadline => self.fix_without_the_missing(p.world_size),
            Err(_) => Err(Status::deadline_exceeded(format!(
                "no scene agreed after {:.0} s: ranks {:?} of {} have not reported their range",
                wait.as_secs_f64(),
                self.missing(p.world_size),
                p.world_size
            ))),
        }
    }

    /// Records `p`'s range: the scene when `p` completes the world (`None` before), and the
    /// instant the agreement times out (`timeout` after the first report).
    ///
    /// # Errors
    /// `INVALID_ARGUMENT` when `p` gives a world size other than the ranks before it did.
    fn record(
        &self,
        p: &insitu_proto::pb::SceneProposal,
    ) -> Result<(Option<Agreed>, Instant), Status> {
        let mut s = self.proposals.lock().unwrap_or_else(|e| e.into_inner());
        match s.world_size {
            Some(w) if w != p.world_size => {
                return Err(Status::invalid_argument(format!(
                    "step {} rank {} says world size {}, but ranks {:?} said {w}",
                    p.step,
                    p.rank,
                    p.world_size,
                    s.ranges.keys().collect::<Vec<_>>()
                )))
            }
            _ => s.world_size = Some(p.world_size),
        }
        s.step = s.step.max(p.step);
        s.ranges.insert(p.rank, (p.min, p.max));
        let first = *s.first_at.get_or_insert_with(Instant::now);
        let complete = (s.ranges.len() == p.world_size as usize).then(|| s.agree(p.world_size));
        Ok((complete, first + self.timeout))
    }

    /// The scene over the ranks that reported, once the world has waited long enough for
    /// the others (fixed by the first caller to get here; the others read it).
    ///
    /// # Errors
    /// `INTERNAL` when `scene.json` cannot be written.
    fn fix_without_the_missing(&self, world_size: u32) -> Result<Agreed, Status> {
        let agreed = {
            let s = self.proposals.lock().unwrap_or_else(|e| e.into_inner());
            s.agree(world_size)
        };
        if self.agreed().is_none() {
            tracing::warn!(
                ranks = ?agreed.ranks,
                world_size,
                timeout_secs = self.timeout.as_secs_f64(),
                "not every rank reported its range in time: the scene is fixed over those that did"
            );
            self.fix(agreed)?;
        }
        self.agreed().ok_or_else(|| Status::internal("scene lost"))
    }

    /// The ranks of `0..world_size` that have not reported their range.
    fn missing(&self, world_size: u32) -> Vec<u32> {
        let s = self.proposals.lock().unwrap_or_else(|e| e.into_inner());
        (0..world_size)
            .filter(|r| !s.ranges.contains_key(r))
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use insitu_proto::pb::SceneProposal;

    fn proposal(rank: u32, world_size: u32, min: f64, max: f64) -> SceneProposal {
        SceneProposal {
            step: 0,
            rank,
            world_size,
            min,
            max,
            wait_secs: 0.0,
        }
    }

    #[tokio::test]
    async fn the_global_range_is_agreed_once_and_survives_a_reopen() {
        let dir = tempfile::tempdir().unwrap();
        let s =
            std::sync::Arc::new(SceneAgreement::open(dir.path(), Duration::from_secs(60)).unwrap());
        let short = Duration::from_millis(50);
        let e = s
            .propose(&proposal(0, 2, 0.0, 0.0), short)
            .await
            .unwrap_err();
        assert_eq!(e.code(), tonic::Code::DeadlineExceeded);
        assert!(e.message().contains("[1]"), "{}", e.message());
        let bad = s
            .propose(&proposal(1, 3, 0.0, 1.0), short)
            .await
            .unwrap_err();
        assert_eq!(bad.code(), tonic::Code::InvalidArgument);
        let bad = s
            .propose(&proposal(2, 2, 0.0, 1.0), short)
            .await
            .unwrap_err();
        assert_eq!(bad.code(), tonic::Code::InvalidArgument);
        // A waiter is answered when the last rank reports.
        let waiter = {
            let s = s.clone();
            tokio::spawn(async move {
                s.propose(&proposal(0, 2, 0.0, 0.0), Duration::from_secs(5))
                    .await
            })
        };
        let a = s.propose(&proposal(1, 2, 3.0, 250.0), short).await.unwrap();
        assert_eq!(a.tf_name, "default[0, 250]");
        assert_eq!(waiter.await.unwrap().unwrap(), a);
        // Fixed: another range changes nothing, and a reopened recording keeps it.
        assert_eq!(
            s.propose(&proposal(0, 2, -9.0, 9.0), short).await.unwrap(),
            a
        );
        let reopened = SceneAgreement::open(dir.path(), Duration::from_secs(60)).unwrap();
        assert_eq!(reopened.agreed(), Some(a));
    }

    #[tokio::test]
    async fn a_rank_that_never_reports_does_not_stall_the_world() {
        let dir = tempfile::tempdir().unwrap();
        let s = SceneAgreement::open(dir.path(), Duration::from_millis(100)).unwrap();
        let a = s
            .propose(&proposal(0, 3, 1.0, 7.0), Duration::from_secs(10))
            .await
            .unwrap();
        assert_eq!(
            (a.tf_name.as_str(), a.ranks.as_slice()),
            ("default[1, 7]", &[0][..])
        );
        // The late rank gets the same scene.
        let late = s
            .propose(&proposal(2, 3, 0.0, 99.0), Duration::from_secs(10))
            .await
            .unwrap();
        assert_eq!(late, a);
    }
}
