//! A bounded async queue with a named policy for when it is full (docs/conventions.md: the node "never
//! blocks the simulation for longer than a copy of the step; what happens when the queue is
//! full is a named, configurable policy").
//!
//! Bounded by item count and by bytes. An item larger than the byte limit is still admitted
//! into an empty queue (otherwise `block` would wait forever). Used for the input queue of
//! time steps and for the outbox of finished VDIs.

use serde::{Deserialize, Serialize};
use std::collections::VecDeque;
use std::sync::Mutex;
use tokio::sync::Notify;

/// What a full queue does with one more item.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum Policy {
    /// The producer waits for room; nothing is dropped (back-pressure).
    #[default]
    Block,
    /// The oldest waiting items are dropped to make room.
    DropOldest,
    /// Every push drops all waiting items: only the newest is kept.
    LatestOnly,
}

/// A queue policy for the wire (`GeneratorStatus.queue_policy`).
impl From<Policy> for insitu_proto::pb::QueuePolicy {
    fn from(p: Policy) -> Self {
        match p {
            Policy::Block => Self::Block,
            Policy::DropOldest => Self::DropOldest,
            Policy::LatestOnly => Self::LatestOnly,
        }
    }
}

impl Policy {
    /// The name used in config files and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            Self::Block => "block",
            Self::DropOldest => "drop-oldest",
            Self::LatestOnly => "latest-only",
        }
    }
}

impl std::str::FromStr for Policy {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        [Self::Block, Self::DropOldest, Self::LatestOnly]
            .into_iter()
            .find(|p| p.name() == s)
            .ok_or_else(|| {
                format!("unknown queue policy {s:?}: expected block, drop-oldest or latest-only")
            })
    }
}

impl std::fmt::Display for Policy {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// The queue was closed; the item comes back.
#[derive(Debug)]
pub struct Closed<T>(pub T);

struct State<T> {
    items: VecDeque<(T, u64)>,
    bytes: u64,
    closed: bool,
}

/// A bounded multi-producer queue (see the module docs).
pub struct BoundedQueue<T> {
    state: Mutex<State<T>>,
    changed: Notify,
    max_items: usize,
    max_bytes: u64,
    policy: Policy,
}

impl<T> BoundedQueue<T> {
    /// A queue of at most `max_items` (≥ 1) items and `max_bytes` bytes.
    pub fn new(max_items: usize, max_bytes: u64, policy: Policy) -> Self {
        Self {
            state: Mutex::new(State {
                items: VecDeque::new(),
                bytes: 0,
                closed: false,
            }),
            changed: Notify::new(),
            max_items: max_items.max(1),
            max_bytes,
            policy,
        }
    }

    /// The policy.
    pub fn policy(&self) -> Policy {
        self.policy
    }

    /// The item limit.
    pub fn max_items(&self) -> usize {
        self.max_items
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, State<T>> {
        // A panic while holding the lock cannot leave the state inconsistent (every update is
        // a single push/pop plus a byte count), so a poisoned lock is still usable.
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn fits(&self, s: &State<T>, bytes: u64) -> bool {
        s.items.is_empty()
            || (s.items.len() < self.max_items && s.bytes.saturating_add(bytes) <= self.max_bytes)
    }

    /// Adds `item` of `bytes` bytes. With [`Policy::Block`] waits for room; otherwise returns at
    /// once with the items the policy dropped, oldest first.
    ///
    /// # Errors
    /// [`Closed`] with the item when the queue is closed (also while waiting).
    pub async fn push(&self, item: T, bytes: u64) -> Result<Vec<T>, Closed<T>> {
        loop {
            let notified = self.changed.notified();
            tokio::pin!(notified);
            notified.as_mut().enable();
            {
                let mut s = self.lock();
                if s.closed {
                    return Err(Closed(item));
                }
                let mut dropped = Vec::new();
                let admit = match self.policy {
                    Policy::Block => self.fits(&s, bytes),
                    Policy::DropOldest => {
                        while !self.fits(&s, bytes) {
                            if let Some((old, b)) = s.items.pop_front() {
                                s.bytes -= b;
                                dropped.push(old);
                            }
                        }
                        true
                    }
                    Policy::LatestOnly => {
                        dropped.extend(s.items.drain(..).map(|(old, _)| old));
                        s.bytes = 0;
                        true
                    }
                };
                if admit {
                    s.items.push_back((item, bytes));
                    s.bytes += bytes;
                    drop(s);
                    self.changed.notify_waiters();
                    return Ok(dropped);
                }
            }
            notified.await;
        }
    }

    /// Takes the oldest item, waiting for one; `None` once the queue is closed and empty.
    pub async fn pop(&self) -> Option<T> {
        loop {
            let notified = self.changed.notified();
            tokio::pin!(notified);
            notified.as_mut().enable();
            {
                let mut s = self.lock();
                if let Some((it, b)) = s.items.pop_front() {
                    s.bytes -= b;
                    drop(s);
                    self.changed.notify_waiters();
                    return Some(it);
                }
                if s.closed {
                    return None;
                }
            }
            notified.await;
        }
    }

    /// Refuses further pushes (waiting ones get [`Closed`]); items already in stay poppable.
    pub fn close(&self) {
        self.lock().closed = true;
        self.changed.notify_waiters();
    }

    /// Items waiting.
    pub fn len(&self) -> usize {
        self.lock().items.len()
    }

    /// Whether nothing is waiting.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Bytes waiting.
    pub fn bytes(&self) -> u64 {
        self.lock().bytes
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use std::sync::Arc;
    use std::time::Duration;

    fn rt() -> tokio::runtime::Runtime {
        tokio::runtime::Builder::new_current_thread()
            .enable_time()
            .build()
            .unwrap()
    }

    proptest! {
        /// Drop policies: never over the limits (beyond a lone oversized item), every item is
        /// either popped or dropped exactly once, order is preserved.
        #[test]
        fn drop_policies_account_for_every_item(
            ops in proptest::collection::vec((any::<bool>(), 1u64..50), 1..200),
            max_items in 1usize..5,
            max_bytes in 1u64..120,
            latest in any::<bool>(),
        ) {
            let policy = if latest { Policy::LatestOnly } else { Policy::DropOldest };
            let q = BoundedQueue::new(max_items, max_bytes, policy);
            let rt = rt();
            let (mut pushed, mut popped, mut dropped) = (Vec::new(), Vec::new(), Vec::new());
            for (i, (is_push, bytes)) in ops.into_iter().enumerate() {
                if is_push {
                    pushed.push(i);
                    dropped.extend(rt.block_on(q.push(i, bytes)).unwrap());
                    let n = q.len();
                    prop_assert!(n <= max_items);
                    prop_assert!(n == 1 || q.bytes() <= max_bytes);
                    if latest { prop_assert_eq!(n, 1); }
                } else if !q.is_empty() {
                    popped.push(rt.block_on(q.pop()).unwrap());
                }
            }
            q.close();
            while let Some(i) = rt.block_on(q.pop()) { popped.push(i); }
            prop_assert!(popped.windows(2).all(|w| w[0] < w[1]));
            let mut all: Vec<usize> = popped.iter().chain(&dropped).copied().collect();
            all.sort_unstable();
            prop_assert_eq!(all, pushed);
        }
    }

    #[test]
    fn block_waits_for_room_and_drops_nothing() {
        let rt = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .enable_time()
            .build()
            .unwrap();
        rt.block_on(async {
            let q = Arc::new(BoundedQueue::new(2, u64::MAX, Policy::Block));
            let producer = {
                let q = q.clone();
                tokio::spawn(async move {
                    for i in 0..50u32 {
                        assert!(q.push(i, 1).await.unwrap().is_empty());
                        assert!(q.len() <= 2);
                    }
                    q.close();
                })
            };
            let mut got = Vec::new();
            while let Some(i) = q.pop().await {
                tokio::time::sleep(Duration::from_millis(1)).await;
                got.push(i);
            }
            producer.await.unwrap();
            assert_eq!(got, (0..50).collect::<Vec<_>>());
        });
    }

    #[test]
    fn close_wakes_a_blocked_producer_with_its_item() {
        rt().block_on(async {
            let q = Arc::new(BoundedQueue::new(1, u64::MAX, Policy::Block));
            q.push(1, 1).await.unwrap();
            let q2 = q.clone();
            let waiting = tokio::spawn(async move { q2.push(2, 1).await });
            tokio::task::yield_now().await;
            q.close();
            assert!(matches!(waiting.await.unwrap(), Err(Closed(2))));
            assert_eq!(q.pop().await, Some(1));
            assert_eq!(q.pop().await, None);
        });
    }

    #[test]
    fn an_oversized_item_enters_an_empty_queue() {
        rt().block_on(async {
            let q = BoundedQueue::new(4, 10, Policy::Block);
            q.push("big", 100).await.unwrap();
            assert_eq!(q.bytes(), 100);
            assert_eq!(q.pop().await, Some("big"));
            assert!("drop-newest".parse::<Policy>().is_err());
            assert_eq!("drop-oldest".parse::<Policy>(), Ok(Policy::DropOldest));
        });
    }
}
