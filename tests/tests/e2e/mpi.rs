//! The MPI example for real: `examples/mpi-gray-scott` compiled with `mpicc` against the C
//! client, run with `mpirun -np 4` against a real generator-node and viz-node. Every (step,
//! rank) arrives, every step composes and is scored, and the composed picture matches the
//! same simulation run in one process (the Rust model, cell for cell the same arithmetic).

use crate::mpi_runs::{assert_same_picture, run, Sizes};
use insitu_core::vdi::{generate::generate, VdiParams};
use insitu_core::volume::{GrayScott, GrayScottParams};
use insitu_core::{Camera, RaycastParams, Raycaster};
use insitu_e2e::{build_c, mpi_tool};
use insitu_viz_node::scene::Agreed;

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

    let (composed, rec) = run(
        &mpirun,
        &[exe.as_os_str()],
        4,
        tmp.path(),
        "C gray-scott",
        Sizes {
            n: N,
            steps: STEPS,
            every: EVERY,
            r: R,
        },
    );
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
        precision: Default::default(),
    };
    let one = generate(&rc, &camera, params, agreed.tf.identity_hash(), "one").unwrap();
    assert_eq!(composed.meta().camera, camera);
    // Not blank: the pattern covers a good part of the frame.
    assert_same_picture(
        &composed,
        &one,
        "composed 4-rank vs one process",
        R,
        (R * R / 20) as usize,
    );
}
