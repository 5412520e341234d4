//! Counters of a generator-node, observable (for `GetStatus`) and awaitable (for `Flush`).

use tokio::sync::watch;

/// What happened to the steps received so far. Every received step ends in exactly one of
/// `shipped` (or `generated` when no viz-node is configured), `dropped_queue`,
/// `dropped_outbox` or `failed`; until then it is in flight.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Counters {
    /// Steps fully received and queued.
    pub received: u64,
    /// VDIs generated.
    pub generated: u64,
    /// VDIs acknowledged (stored) by the viz-node.
    pub shipped: u64,
    /// Steps dropped from the input queue by its policy.
    pub dropped_queue: u64,
    /// VDIs dropped from the outbox by its policy or left unshipped at shutdown.
    pub dropped_outbox: u64,
    /// Steps whose generation or shipping failed for good (logged).
    pub failed: u64,
    /// Whether the last attempt to reach the viz-node succeeded.
    pub viz_connected: bool,
    /// Whether the stream to the tuner is up.
    pub tuner_connected: bool,
}

impl Counters {
    /// Steps whose fate is decided, given whether VDIs are shipped at all.
    pub fn settled(&self, shipping: bool) -> u64 {
        let delivered = if shipping {
            self.shipped
        } else {
            self.generated
        };
        delivered + self.dropped_queue + self.dropped_outbox + self.failed
    }
}

/// Shared counters.
#[derive(Debug)]
pub struct Stats(watch::Sender<Counters>);

impl Default for Stats {
    fn default() -> Self {
        Self(watch::Sender::new(Counters::default()))
    }
}

impl Stats {
    /// Applies `f` and wakes waiters.
    pub fn update(&self, f: impl FnOnce(&mut Counters)) {
        self.0.send_modify(f);
    }

    /// A snapshot.
    pub fn get(&self) -> Counters {
        *self.0.borrow()
    }

    /// Waits until `pred` holds.
    pub async fn wait_for(&self, pred: impl FnMut(&Counters) -> bool) {
        let mut rx = self.0.subscribe();
        // The sender lives as long as `self`, so this cannot fail while we are borrowed.
        let _ = rx.wait_for(pred).await;
    }
}
