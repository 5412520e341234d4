//! Running an MPI example against real daemons and comparing pictures, for the examples in
//! every language (`mpi.rs` compares the C one with the Rust model, `fortran.rs` and
//! `python.rs` four ranks with one).

use crate::common::{generator, index, steps, viz};
use insitu_core::metrics::psnr;
use insitu_core::vdi::codec::{decode, DecodeLimits};
use insitu_core::vdi::{render, Vdi};
use insitu_e2e::wait_until;
use std::ffi::OsStr;
use std::path::{Path, PathBuf};
use std::process::Command;

/// What a run computes and pushes: an `n`³ grid for `steps` steps, a brick per rank every
/// `every` steps, VDIs at resolution `r`.
#[derive(Clone, Copy, Debug)]
pub struct Sizes {
    pub n: usize,
    pub steps: u64,
    pub every: u64,
    pub r: u32,
}

/// The Fortran and mpi4py examples' sizes.
pub const SMALL: Sizes = Sizes {
    n: 32,
    steps: 60,
    every: 20,
    r: 64,
};

/// Runs `program` (with its arguments before the generator's address) on `np` ranks under
/// `mpirun`, against daemons of its own, as `program ADDR N STEPS EVERY`; checks that every
/// (step, rank) arrived and every step was stored and scored. Returns the last step's VDI
/// (composed for several ranks) and the recording.
pub fn run(
    mpirun: &Path,
    program: &[&OsStr],
    np: u32,
    dir: &Path,
    what: &str,
    sizes: Sizes,
) -> (Vdi, PathBuf) {
    let Sizes {
        n,
        steps: last,
        every,
        r,
    } = sizes;
    let rec = dir.join(format!("rec{np}"));
    let v = viz(&rec, "127.0.0.1:0", dir);
    let cfg = format!(
        r#"listen = "127.0.0.1:0"
viz = "{}"
[generation]
resolution = {r}
gamma = 0.01
codec = "zstd"
reference_every = 1
"#,
        v.addr
    );
    let g = generator(&cfg, dir, &[]);
    let out = Command::new(mpirun)
        .args([
            "--allow-run-as-root",
            "--oversubscribe",
            "-np",
            &np.to_string(),
        ])
        .args(program)
        .arg(&g.addr)
        .args([n.to_string(), last.to_string(), every.to_string()])
        .env_remove("INSITU_TOKEN")
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "mpirun -np {np}: {stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(stdout.contains(&format!("{np} ranks")), "{stdout}");
    // Several ranks: composed steps; one rank: its steps as they are.
    let scored = |rec: &Path| -> Vec<(u64, Option<String>, Option<f64>)> {
        if np > 1 {
            steps(rec)
                .into_iter()
                .filter(|s| s.missing.is_empty() && s.error.is_none())
                .map(|s| (s.step, s.vdi, s.quality.map(|q| q.q_db.0)))
                .collect()
        } else {
            index(rec)
                .into_iter()
                .map(|e| (e.step, e.vdi, e.quality.map(|q| q.q_db.0)))
                .collect()
        }
    };
    let all = wait_until(60.0, || {
        let s = scored(&rec);
        s.len() == 3 && s.iter().all(|s| s.2.is_some())
    });
    assert!(
        all,
        "{np} ranks: not every step was stored and scored: {:?}",
        scored(&rec)
    );
    // Every rank is held by a stored part (the node composes the ranks it serves).
    let entries = index(&rec);
    for step in (every..=last).step_by(every as usize) {
        for rank in 0..np {
            assert!(
                entries
                    .iter()
                    .any(|e| e.step == step && e.holds(rank) && e.world_size == np),
                "{np} ranks: step {step} rank {rank} missing"
            );
        }
    }
    let (_, vdi, q) = scored(&rec).into_iter().find(|s| s.0 == last).unwrap();
    eprintln!(
        "{what}, {np} ranks: step {last} q {:.2} dB",
        q.unwrap_or_default()
    );
    let bytes = std::fs::read(rec.join(vdi.unwrap())).unwrap();
    g.terminate();
    v.terminate();
    (decode(&bytes, &DecodeLimits::default()).unwrap(), rec)
}

/// Asserts that `many` (a run on several ranks) looks as `one` (one rank, or one process) from
/// the generation view and two orbits of it, at `size`²: ≥ 40 dB, and more than `min_lit`
/// pixels lit (not blank).
pub fn assert_same_picture(many: &Vdi, one: &Vdi, what: &str, size: u32, min_lit: usize) {
    assert_eq!(many.meta().camera, one.meta().camera);
    for angle in [0.0, 30.0, 60.0] {
        let view = one.meta().camera.orbit_y(angle);
        let a = render::render(many, &view, size, size, 0.99);
        let b = render::render(one, &view, size, size, 0.99);
        let lit = a
            .pixels()
            .iter()
            .filter(|p| p.iter().sum::<f32>() > 0.05)
            .count();
        assert!(lit > min_lit, "{what}: only {lit} lit pixels at {angle}°");
        let q = psnr(&a, &b).unwrap();
        eprintln!("{what}, several ranks vs one at {angle}°: {q:.1} dB, {lit} lit pixels");
        assert!(
            q >= 40.0,
            "{what}: several ranks vs one at {angle}°: {q:.1} dB"
        );
    }
}
