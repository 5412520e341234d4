//! The MPI example for real: `examples/mpi-gray-scott` compiled with `mpicc` against the C
//! client, run with `mpirun -np 4` against a real generator-node and viz-node. Every (step,
//! rank) arrives, every step composes and is scored, and the composed picture matches the
//! same simulation run in one process (the Rust model, cell for cell the same arithmetic).

use crate::common::{generator, index, steps, viz};
use crate::mpi_runs::assert_same_picture;
use insitu_core::vdi::codec::{decode, DecodeLimits};
use insitu_core::vdi::{generate::generate, VdiParams};
use insitu_core::volume::{GrayScott, GrayScottParams};
use insitu_core::{Camera, RaycastParams, Raycaster};
use insitu_e2e::{build_c, mpi_tool, wait_until};
use insitu_viz_node::scene::Agreed;
use std::process::Command;

const N: usize = 48;
const STEPS: u64 = 300;
const EVERY: u64 = 100;
const R: u32 = 96;

#[test]
fn four_mpi_ranks_make_one_picture_per_step_like_one_process() {
    let (Some(mpicc), Some(mpirun)) = (mpi_tool("mpicc"), mpi_tool("mpirun")) else {
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    let exe = tmp.path().join("gray_scott_mpi");
    build_c(
        &mpicc,
        "examples/mpi-gray-scott/gray_scott_mpi.c",
        &exe,
        &["-ffp-contract=off", "-Wall", "-Werror"],
    );

    let rec = tmp.path().join("rec");
    let v = viz(&rec, "127.0.0.1:0", tmp.path());
    let cfg = format!(
        r#"listen = "127.0.0.1:0"
viz = "{}"
[generation]
resolution = {R}
gamma = 0.01
codec = "zstd"
reference_every = 1
"#,
        v.addr
    );
    let g = generator(&cfg, tmp.path(), &[]);
    let run = Command::new(mpirun)
        .args(["--allow-run-as-root", "--oversubscribe", "-np", "4"])
        .arg(&exe)
        .arg(&g.addr)
        .args([N.to_string(), STEPS.to_string(), EVERY.to_string()])
        .env_remove("INSITU_TOKEN")
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&run.stdout);
    assert!(
        run.status.success(),
        "mpirun: {stdout}\n{}",
        String::from_utf8_lossy(&run.stderr)
    );
    assert!(stdout.contains("4 ranks"), "{stdout}");

    let all = wait_until(60.0, || {
        let s = steps(&rec);
        s.len() == 3 && s.iter().all(|s| s.quality.is_some())
    });
    assert!(
        all,
        "not every step was composed and scored: {:?}",
        steps(&rec)
    );
    // Every (step, rank) arrived.
    let entries = index(&rec);
    for step in (EVERY..=STEPS).step_by(EVERY as usize) {
        for rank in 0..4 {
            assert!(
                entries
                    .iter()
                    .any(|e| e.step == step && e.rank == rank && e.world_size == 4),
                "step {step} rank {rank} missing"
            );
        }
    }
    let agreed: Agreed =
        serde_json::from_slice(&std::fs::read(rec.join("scene.json")).unwrap()).unwrap();
    // The same simulation in one process.
    let mut sim = GrayScott::new(N, GrayScottParams::default()).unwrap();
    sim.advance(STEPS);
    let whole = sim.v_volume();
    let rc = Raycaster::new(&whole, &agreed.tf, RaycastParams::default()).unwrap();
    let camera = Camera::default_for_box(&whole.world_box());
    let params = VdiParams {
        resolution: R,
        gamma: 0.01,
    };
    let one = generate(&rc, &camera, params, agreed.tf.identity_hash(), "one").unwrap();
    let last = steps(&rec).into_iter().find(|s| s.step == STEPS).unwrap();
    assert!(last.missing.is_empty() && last.error.is_none(), "{last:?}");
    let bytes = std::fs::read(rec.join(last.vdi.as_ref().unwrap())).unwrap();
    let composed = decode(&bytes, &DecodeLimits::default()).unwrap();
    assert_eq!(composed.meta().camera, camera);
    // Not blank: the pattern covers a good part of the frame.
    assert_same_picture(
        &composed,
        &one,
        "composed 4-rank vs one process",
        R,
        (R * R / 20) as usize,
    );
    g.terminate();
    v.terminate();
}
