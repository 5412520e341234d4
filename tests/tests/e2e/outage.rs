//! Kill the viz-node mid-run and restart it: the generator-node keeps running, reconnects, and
//! every step acknowledged before the outage is in the recording (and nothing is lost after).

use crate::common::{flush, generator, index, load_vdi, push_steps, small_config, status, viz};
use insitu_e2e::wait_until;

#[test]
fn a_viz_node_outage_loses_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    let rec = tmp.path().join("rec");
    let v = viz(&rec, "127.0.0.1:0", tmp.path());
    let viz_addr = v.addr.clone();
    let g = generator(&small_config(&viz_addr, "block", 16), tmp.path(), &[]);
    push_steps(&g.addr, 0..5);
    let s = flush(&g.addr);
    assert_eq!(s.steps_shipped, 5);
    let acknowledged: Vec<u64> = index(&rec).iter().map(|e| e.step).collect();
    assert_eq!(acknowledged, vec![0, 1, 2, 3, 4]);
    v.kill();
    push_steps(&g.addr, 5..10);
    // The generator keeps serving and notices the outage.
    assert!(wait_until(20.0, || !status(&g.addr).viz_connected));
    assert_eq!(status(&g.addr).steps_received, 10);
    let v = viz(&rec, &viz_addr, tmp.path());
    let s = flush(&g.addr);
    assert_eq!(
        (s.steps_shipped, s.dropped_outbox, s.failed),
        (10, 0, 0),
        "{s:?}"
    );
    let entries = index(&rec);
    assert_eq!(
        entries.iter().map(|e| e.step).collect::<Vec<_>>(),
        (0..10).collect::<Vec<_>>()
    );
    for e in &entries {
        assert_eq!(load_vdi(&rec, e).resolution(), 32);
    }
    let summary = g.terminate();
    assert!(summary.contains("shipped 10"), "{summary}");
    v.terminate();
}
