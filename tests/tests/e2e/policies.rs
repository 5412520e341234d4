//! Queue policies with a viz-node that is not there yet (the slowest possible consumer): with
//! `drop-oldest` the simulation's pushes return at once, the queue never exceeds its limit and
//! drops are reported; with `block` nothing is dropped.

use crate::common::{flush, free_port, generator, index, push_steps, small_config, status, viz};
use insitu_e2e::wait_until;

#[test]
fn drop_oldest_never_waits_and_counts_every_drop() {
    let tmp = tempfile::tempdir().unwrap();
    let port = free_port();
    let viz_addr = format!("127.0.0.1:{port}");
    let g = generator(&small_config(&viz_addr, "drop-oldest", 1), tmp.path(), &[]);
    // Nothing consumes: the outbox (1) fills, generation stalls, the queue (2) fills.
    let replies = push_steps(&g.addr, 0..20);
    assert!(replies.iter().all(|r| r.queue_depth <= 2), "{replies:?}");
    let dropped: u64 = replies.iter().map(|r| r.dropped_by_push).sum();
    assert!(dropped > 0, "no drops with a stalled consumer: {replies:?}");
    let s = status(&g.addr);
    assert_eq!(s.steps_received, 20);
    assert_eq!(s.dropped_queue, dropped);
    assert!(s.queue_depth <= 2);
    // The consumer appears: everything not dropped is delivered.
    let rec = tmp.path().join("rec");
    let v = viz(&rec, &viz_addr, tmp.path());
    let s = flush(&g.addr);
    assert_eq!(
        s.steps_shipped + s.dropped_queue + s.dropped_outbox + s.failed,
        20,
        "{s:?}"
    );
    assert_eq!(s.failed, 0);
    assert_eq!(index(&rec).len() as u64, s.steps_shipped);
    g.terminate();
    v.terminate();
}

#[test]
fn block_drops_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    let port = free_port();
    let viz_addr = format!("127.0.0.1:{port}");
    let g = generator(&small_config(&viz_addr, "block", 1), tmp.path(), &[]);
    let addr = g.addr.clone();
    let pusher = std::thread::spawn(move || push_steps(&addr, 0..12));
    // While nothing consumes, the pushes back up behind the queue limit.
    assert!(wait_until(20.0, || status(&g.addr).queue_depth == 2));
    let s = status(&g.addr);
    assert!(s.steps_received < 12 && s.queue_depth <= 2, "{s:?}");
    let rec = tmp.path().join("rec");
    let v = viz(&rec, &viz_addr, tmp.path());
    let replies = pusher.join().unwrap();
    assert!(replies
        .iter()
        .all(|r| r.dropped_by_push == 0 && r.queue_depth <= 2));
    let s = flush(&g.addr);
    assert_eq!(
        (s.steps_shipped, s.dropped_queue, s.dropped_outbox, s.failed),
        (12, 0, 0, 0)
    );
    let steps: Vec<u64> = index(&rec).iter().map(|e| e.step).collect();
    assert_eq!(steps, (0..12).collect::<Vec<_>>());
    g.terminate();
    v.terminate();
}
