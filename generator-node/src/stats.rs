//! Counters of a generator-node, observable (for `GetStatus`) and awaitable (for `Flush`).

use tokio::sync::watch;

/// What happened to the steps received so far (one per rank). Every received step ends in
/// exactly one of `shipped` (or `generated` when no viz-node is configured), `dropped_queue`,
/// `dropped_outbox` or `failed`; until then it is in flight. A part holding several ranks
/// counts once per rank in `shipped`, `dropped_outbox` and `failed`.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Counters {
    /// Steps fully received and queued.
    pub received: u64,
    /// VDIs generated.
    pub generated: u64,
    /// Ranks' VDIs acknowledged (stored) by the viz-node, alone or in a host's part.
    pub shipped: u64,
    /// Steps dropped from the input queue by its policy.
    pub dropped_queue: u64,
    /// VDIs dropped from the outbox by its policy or left unshipped at shutdown.
    pub dropped_outbox: u64,
    /// Steps whose generation or shipping failed for good (logged).
    pub failed: u64,
    /// Of those, VDIs the viz-node refused (authentication, validation, a full disk).
    pub ship_failed: u64,
    /// Steps found in the spool at start (acknowledged by an earlier run), queued again.
    pub recovered: u64,
    /// VDIs made again at a coarser `P_M` because σ came out over the hard limit or τ would
    /// have.
    pub limit_retries: u64,
    /// Seconds of the generations and compressions those threw away.
    pub limit_retry_secs: f64,
    /// Parts shipped that hold several of this node's ranks (`crate::host`).
    pub host_parts: u64,
    /// Ranks in those parts.
    pub host_ranks: u64,
    /// Seconds spent composing and encoding them.
    pub host_compose_secs: f64,
    /// CPU seconds of the trials run (`crate::cpu`).
    pub trial_cpu_secs: f64,
    /// Steps received through shared memory (`crate::shm`).
    pub shared_pushes: u64,
    /// Bytes of faces posted to the viz-node and received from it (`crate::faces`).
    pub faces_sent_bytes: u64,
    pub faces_received_bytes: u64,
    /// Bricks grown by faces that came from another node.
    pub bricks_grown_across: u64,
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

/// Shared counters, and the last reason VDIs did not reach the viz-node.
#[derive(Debug)]
pub struct Stats(watch::Sender<Counters>, std::sync::Mutex<String>);

impl Default for Stats {
    fn default() -> Self {
        Self(watch::Sender::new(Counters::default()), Default::default())
    }
}

impl Stats {
    /// Records why shipping is failing (empty: it works again).
    pub fn set_ship_error(&self, e: impl Into<String>) {
        *self.1.lock().unwrap_or_else(|p| p.into_inner()) = e.into();
    }

    /// The last reason shipping failed, empty once a VDI was stored after it.
    pub fn ship_error(&self) -> String {
        self.1.lock().unwrap_or_else(|p| p.into_inner()).clone()
    }

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
