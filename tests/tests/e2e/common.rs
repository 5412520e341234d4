//! Helpers shared by the end-to-end tests.

use insitu_client::{SimClient, Step};
use insitu_core::metrics::{mse, pooled_psnr};
use insitu_core::vdi::codec::{decode, DecodeLimits};
use insitu_core::vdi::render;
use insitu_core::Vdi;
use insitu_e2e::{rt, Daemon};
use insitu_recording::store::{Entry, References, StepEntry};
use std::path::Path;
use std::process::{Child, Output};

pub use insitu_e2e::free_port;

/// The standard output of `insitu replay` (`out`), once it has succeeded.
pub fn replayed(out: Output) -> String {
    succeeded("replay", out)
}

pub use insitu_e2e::succeeded;

/// [`replayed`] of a replay started in the background with its output piped.
pub fn finish(child: Child) -> String {
    replayed(child.wait_with_output().unwrap())
}

/// Starts a viz-node recording into `dir` on `listen`.
pub fn viz(dir: &Path, listen: &str, logs: &Path) -> Daemon {
    insitu_e2e::start_viz(dir, listen, &[], logs)
}

/// q of a stored, scored entry recomputed here with the CPU renderer from the stored VDI and
/// reference frames (pooled PSNR over the views, as the viz-node reports it).
pub fn local_q(rec: &Path, e: &Entry) -> f64 {
    let vdi = load_vdi(rec, e);
    let refs = References::read(&rec.join(e.references.as_ref().unwrap())).unwrap();
    let mses: Vec<f64> = refs
        .view_angles_deg
        .iter()
        .zip(&refs.frames)
        .map(|(&a, f)| {
            let im = render::render(&vdi, &refs.camera.orbit_y(a), f.width(), f.height(), 0.99);
            mse(&im, f).unwrap()
        })
        .collect();
    pooled_psnr(&mses)
}

/// The viz-node's counters.
pub fn viz_status(addr: &str) -> insitu_proto::pb::VizStatus {
    rt().block_on(async {
        let channel = insitu_proto::transport::connect(&insitu_proto::transport::uri(addr))
            .await
            .unwrap();
        insitu_proto::pb::viz_client::VizClient::new(channel)
            .get_status(insitu_proto::pb::StatusRequest {})
            .await
            .unwrap()
            .into_inner()
    })
}

/// Starts a generator-node from a TOML config written to `logs/name.toml`.
pub fn generator(toml: &str, logs: &Path, envs: &[(&str, &str)]) -> Daemon {
    let path = logs.join(format!("generator-{}.toml", free_port()));
    std::fs::write(&path, toml).unwrap();
    Daemon::start(
        "generator-node",
        &["--config", path.to_str().unwrap()],
        envs,
        logs,
    )
}

/// The recording's index entries (none before the viz-node made the index).
pub fn index(dir: &Path) -> Vec<Entry> {
    insitu_recording::index::read(dir).map_or_else(|_| Vec::new(), |(e, _)| e)
}

/// The recording's composed steps.
pub fn steps(dir: &Path) -> Vec<StepEntry> {
    insitu_recording::index::read(dir).map_or_else(|_| Vec::new(), |(_, s)| s)
}

/// Decodes a stored VDI.
pub fn load_vdi(dir: &Path, e: &Entry) -> Vdi {
    let bytes = std::fs::read(dir.join(e.vdi.as_ref().unwrap())).unwrap();
    decode(&bytes, &DecodeLimits::default()).unwrap()
}

/// A small smooth f32 field that changes with `step` (a blob moving along x).
pub fn field(n: u32, step: u64) -> Vec<f32> {
    let c = 4.0 + (step % 8) as f32;
    let n = n as usize;
    (0..n * n * n)
        .map(|i| {
            let (x, y, z) = ((i % n) as f32, ((i / n) % n) as f32, (i / (n * n)) as f32);
            let d2 = (x - c).powi(2) + (y - 8.0).powi(2) + (z - 8.0).powi(2);
            (-d2 / 20.0).exp()
        })
        .collect()
}

/// Step `step` of a 64³ f32 Gaussian blob moving along x (2 points a step) as a world of two
/// ranks, the z-halves sharing the plane z = 32 (points 0–32 and 32–63).
pub fn blob_halves(step: u64) -> [Step; 2] {
    const N: usize = 64;
    let cx = 16.0 + 2.0 * step as f32;
    let field: Vec<f32> = (0..N * N * N)
        .map(|i| ((i % N) as f32, (i / N % N) as f32, (i / (N * N)) as f32))
        .map(|(x, y, z)| {
            (-((x - cx).powi(2) + (y - 32.0).powi(2) + (z - 32.0).powi(2)) / 128.0).exp()
        })
        .collect();
    [(0u32, 0usize, 33usize), (1, 32, 32)].map(|(rank, z0, nz)| Step {
        step,
        sim_time: step as f64,
        dtype: insitu_client::ScalarType::F32,
        global_dims: [N as u32; 3],
        brick_offset: [0, 0, z0 as u32],
        brick_dims: [N as u32, N as u32, nz as u32],
        rank,
        world_size: 2,
        spacing: [1.0; 3],
        origin: [0.0; 3],
        data: insitu_client::f32_bytes(&field[z0 * N * N..(z0 + nz) * N * N]),
        fields: Vec::new(),
    })
}

/// Pushes steps `range` of [`field`] (16³), returning the replies.
pub fn push_steps(addr: &str, range: std::ops::Range<u64>) -> Vec<insitu_client::PushReply> {
    rt().block_on(async {
        let mut c = SimClient::connect(addr, None).await.unwrap();
        let mut replies = Vec::new();
        for s in range {
            replies.push(
                c.push_step(Step::whole_f32(s, s as f64, [16; 3], &field(16, s)))
                    .await
                    .unwrap(),
            );
        }
        replies
    })
}

/// The generator's status.
pub fn status(addr: &str) -> insitu_client::GeneratorStatus {
    rt().block_on(async {
        SimClient::connect(addr, None)
            .await
            .unwrap()
            .status()
            .await
            .unwrap()
    })
}

/// Flushes the generator (up to 120 s).
pub fn flush(addr: &str) -> insitu_client::GeneratorStatus {
    rt().block_on(async {
        SimClient::connect(addr, None)
            .await
            .unwrap()
            .flush(std::time::Duration::from_secs(120))
            .await
            .unwrap()
    })
}

/// A generator config shipping to `viz` with small, fast settings.
pub fn small_config(viz: &str, policy: &str, outbox_items: usize) -> String {
    format!(
        r#"listen = "127.0.0.1:0"
viz = "{viz}"
max_backoff_secs = 0.2
drain_timeout_secs = 5.0
[queue]
max_items = 2
max_bytes = 1073741824
policy = "{policy}"
[outbox]
max_items = {outbox_items}
max_bytes = 1073741824
policy = "block"
[generation]
resolution = 32
gamma = 0.01
codec = "zstd"
reference_every = 0
"#
    )
}
