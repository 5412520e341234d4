//! Both daemons on the GPU backend (lavapipe in CI): the ocean series is generated, shipped,
//! stored and scored, and the GPU's q agrees with the CPU path's on the stored files.

use crate::common::{generator, index, local_q, small_config};
use crate::replay::replay;
use insitu_e2e::{gpu_adapter, ocean};

#[test]
fn the_pipeline_runs_on_the_gpu_backend() {
    if ocean().is_none() || gpu_adapter().is_none() {
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let rec = tmp.path().join("rec");
    let v = insitu_e2e::start_viz(&rec, "127.0.0.1:0", &["--backend", "gpu"], tmp.path());
    let g = generator(
        &format!("backend = \"gpu\"\n{}", small_config(&v.addr, "block", 16)),
        tmp.path(),
        &[],
    );
    replay(&g, 1, 4, 2);
    let summary = g.terminate();
    assert!(summary.contains("received 4"), "{summary}");
    let scored = insitu_e2e::wait_until(60.0, || {
        index(&rec).iter().filter(|e| e.quality.is_some()).count() == 2
    });
    assert!(scored, "steps 0 and 2 were never scored: {:?}", index(&rec));
    let entries = index(&rec);
    assert_eq!(entries.len(), 4);
    for e in entries.iter().filter(|e| e.quality.is_some()) {
        // Reference frames made and q scored on the GPU, recomputed here on the CPU.
        let cpu = local_q(&rec, e);
        let gpu = e.quality.as_ref().unwrap().q_db.0;
        assert!(
            gpu > 20.0 && (cpu - gpu).abs() < 0.05,
            "step {}: GPU q {gpu} vs CPU {cpu}",
            e.step
        );
    }
    v.terminate();
}
