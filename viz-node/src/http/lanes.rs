//! The viewer's render lanes: how many frames render at once, which wait, and which are
//! turned away.
//!
//! Every frame takes one of `render_concurrency` permits. A large still (over
//! [`LARGE_PIXELS`]) also takes the one permit of the stills' lane first, so at most one large
//! still renders at a time and the other permits stay free for interactive frames: a small
//! frame never waits behind a queue of large ones. Each lane bounds how many may wait for it;
//! one more is answered at once with 503 and `Retry-After` ([`Busy`]) instead of waiting
//! without end.

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use tokio::sync::{OwnedSemaphorePermit, Semaphore};

/// Frames over this many pixels are large stills (1024², the viewer's largest interactive
/// frame is 768²).
pub const LARGE_PIXELS: u64 = 1024 * 1024;
/// Large stills that may wait for their lane.
pub const LARGE_WAITING: usize = 4;
/// Frames that may wait for a render permit.
pub const WAITING: usize = 64;

/// A lane full: how many wait for it.
#[derive(Debug, PartialEq, Eq)]
pub struct Busy {
    /// What waits.
    pub waiting: usize,
}

/// A semaphore with a bound on its waiters.
pub struct Lane {
    permits: Arc<Semaphore>,
    waiting: AtomicUsize,
    max_waiting: usize,
}

impl Lane {
    /// `permits` at once, at most `max_waiting` waiting.
    pub fn new(permits: usize, max_waiting: usize) -> Self {
        Self {
            permits: Arc::new(Semaphore::new(permits.max(1))),
            waiting: AtomicUsize::new(0),
            max_waiting,
        }
    }

    /// A permit: at once when one is free, else after waiting, unless `max_waiting` already
    /// wait.
    ///
    /// # Errors
    /// [`Busy`] when the lane is full (and also when the semaphore is closed, at shutdown).
    pub async fn enter(&self) -> Result<OwnedSemaphorePermit, Busy> {
        if let Ok(p) = self.permits.clone().try_acquire_owned() {
            return Ok(p);
        }
        let waiting = self.waiting.fetch_add(1, Ordering::AcqRel);
        let _leave = Leave(&self.waiting);
        if waiting >= self.max_waiting {
            return Err(Busy { waiting });
        }
        self.permits
            .clone()
            .acquire_owned()
            .await
            .map_err(|_| Busy { waiting })
    }
}

/// Counts a waiter out when its wait ends, however it ends (a dropped request included).
struct Leave<'a>(&'a AtomicUsize);

impl Drop for Leave<'_> {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::AcqRel);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn a_full_lane_turns_away_at_once_and_frees_its_places() {
        let lane = Arc::new(Lane::new(1, 2));
        let held = lane.enter().await.unwrap();
        let waiters: Vec<_> = (0..2)
            .map(|_| {
                let l = lane.clone();
                tokio::spawn(async move { l.enter().await.map(drop) })
            })
            .collect();
        while lane.waiting.load(Ordering::Acquire) < 2 {
            tokio::task::yield_now().await;
        }
        assert_eq!(lane.enter().await.map(drop), Err(Busy { waiting: 2 }));
        drop(held);
        for w in waiters {
            assert_eq!(w.await.unwrap(), Ok(()));
        }
        assert_eq!(lane.waiting.load(Ordering::Acquire), 0);
        assert!(lane.enter().await.is_ok());
    }
}
