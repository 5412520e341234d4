//! Slurm for real: a one-host cluster (`deploy/slurm/local-cluster.sh`: munge, slurmctld and
//! slurmd on this machine) runs `deploy/slurm.sbatch` as a cluster would: `srun` starts the
//! host's generator-node and waits for its health check, `srun --mpi=pmix` launches the C
//! MPI example's four ranks, and the job stops the node when they are done. The recording is
//! checked as the MPI test checks it: every (step, rank) arrives, every step composes.

use crate::common::{index, steps, viz};
use insitu_e2e::{bin_dir, build_c, free_port, mpi_tool, wait_until};
use insitu_testenv::{tool, Need};
use std::path::Path;
use std::process::Command;

/// Stops the cluster when the test ends, whatever happens.
struct Cluster<'a>(&'a Path);

impl Drop for Cluster<'_> {
    fn drop(&mut self) {
        let _ = Command::new(script()).arg("stop").arg(self.0).status();
    }
}

fn script() -> std::path::PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../deploy/slurm/local-cluster.sh")
}

#[test]
fn the_sbatch_file_runs_the_mpi_example_through_slurm() {
    let root = Command::new("id")
        .arg("-u")
        .output()
        .is_ok_and(|o| o.stdout.starts_with(b"0"));
    let tools = ["slurmctld", "slurmd", "sbatch", "munged"]
        .iter()
        .all(|t| tool(t, Need::Slurm).is_some());
    let Some(mpicc) = mpi_tool("mpicc") else {
        return;
    };
    if !tools {
        return;
    }
    if !root {
        let _: Option<()> = insitu_testenv::skip(Need::Slurm, "starting slurmd needs root");
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let exe = tmp.path().join("gray_scott_mpi");
    build_c(
        &mpicc,
        "examples/mpi-gray-scott/gray_scott_mpi.c",
        &exe,
        &["-Wall", "-Werror"],
    );
    let cluster_dir = tmp.path().join("cluster");
    let started = Command::new(script())
        .arg("start")
        .arg(&cluster_dir)
        .output()
        .unwrap();
    let _cluster = Cluster(&cluster_dir);
    assert!(
        started.status.success(),
        "{}{}",
        String::from_utf8_lossy(&started.stdout),
        String::from_utf8_lossy(&started.stderr)
    );
    let conf = cluster_dir.join("slurm.conf");

    let rec = tmp.path().join("rec");
    let viz_port = free_port();
    let v = viz(&rec, &format!("127.0.0.1:{viz_port}"), tmp.path());
    let token = tmp.path().join("token");
    std::fs::write(&token, "a-shared-token-for-the-job").unwrap();
    let mut perms = std::fs::metadata(&token).unwrap().permissions();
    std::os::unix::fs::PermissionsExt::set_mode(&mut perms, 0o600);
    std::fs::set_permissions(&token, perms).unwrap();
    let gen_config = tmp.path().join("generator-node.toml");
    std::fs::write(
        &gen_config,
        "[generation]\nresolution = 64\ngamma = 0.01\ncodec = \"zstd\"\nreference_every = 1\n",
    )
    .unwrap();
    let out = tmp.path().join("job.out");
    let sbatch = Command::new("sbatch")
        .args(["--wait", "--nodes=1", "--ntasks-per-node=4", "--time=10"])
        .arg(format!("--output={}", out.display()))
        .arg(format!("--chdir={}", tmp.path().display()))
        .arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("../deploy/slurm.sbatch"))
        .env("SLURM_CONF", &conf)
        .env("INSITU_BIN", bin_dir())
        .env("INSITU_SIM", &exe)
        .env("INSITU_SIM_ARGS", "32 60 20")
        .env("INSITU_TOKEN_FILE", &token)
        .env("INSITU_GEN_CONFIG", &gen_config)
        .env("VIZ_HOST", "127.0.0.1")
        .env("VIZ_PORT", viz_port.to_string())
        .env("GEN_PORT", free_port().to_string())
        .env_remove("INSITU_TOKEN")
        .output()
        .unwrap();
    let log = std::fs::read_to_string(&out).unwrap_or_default();
    assert!(
        sbatch.status.success(),
        "sbatch: {}{}\njob output:\n{log}",
        String::from_utf8_lossy(&sbatch.stdout),
        String::from_utf8_lossy(&sbatch.stderr)
    );
    assert!(log.contains("4 ranks"), "job output:\n{log}");
    eprintln!("job output:\n{log}");
    let all = wait_until(60.0, || {
        let s = steps(&rec);
        s.len() == 3 && s.iter().all(|s| s.missing.is_empty() && s.vdi.is_some())
    });
    assert!(all, "steps: {:?}\njob output:\n{log}", steps(&rec));
    let entries = index(&rec);
    for step in [20, 40, 60] {
        for rank in 0..4 {
            assert!(
                entries
                    .iter()
                    .any(|e| e.step == step && e.holds(rank) && e.world_size == 4),
                "step {step} rank {rank} missing\njob output:\n{log}"
            );
        }
    }
    v.terminate();
}
