//! Drifting series for the tuner's budget tests and benches, and the reading of a run's
//! `--json` lines.
//!
//! [`growing_structure`] is a deterministic field whose structure grows step by step, as a
//! reaction front spreads: a fixed pattern of plane waves inside a ball whose radius grows
//! linearly over the series, empty (0) outside, so each step's VDI covers more pixels with
//! more supersegments than the last at the same `P_M`. [`changing_character`] is one whose
//! character changes abruptly half-way while its histogram stays: a smooth orbital drifting
//! slowly, then the same orbital tiled at a third of the size. Values stay in [0, 1] (two
//! corner voxels pin the range, so the first step's default transfer function covers every
//! step).

use std::f32::consts::TAU;
use std::io::Write;
use std::path::{Path, PathBuf};

/// Waves of the pattern.
const MODES: u32 = 6;

/// Step `t` of `steps` of the growing-structure series on an `n³` grid (x fastest), values in
/// [0, 1]: `0.5 + 0.5 · Σ_m a_m sin(k_m·p + φ_m) / Σ_m a_m` inside the ball about the centre of
/// radius `(0.35 + 0.6 · t / (steps − 1)) · n / 2` (a one-voxel smooth edge), 0 outside; the
/// waves' directions and phases come from a fixed hash.
pub fn growing_structure(n: usize, t: usize, steps: usize) -> Vec<f32> {
    let modes: Vec<([f32; 3], f32, f32)> = (0..MODES)
        .map(|m| {
            let h = |i: u32| {
                let x = m
                    .wrapping_mul(2_654_435_761)
                    .wrapping_add(i.wrapping_mul(40_503));
                let x = (x ^ (x >> 15)).wrapping_mul(2_246_822_519);
                f32::from((x >> 16) as u16) / f32::from(u16::MAX)
            };
            let (theta, z, phase) = (TAU * h(1), 2.0 * h(2) - 1.0, TAU * h(3));
            let s = (1.0 - z * z).sqrt();
            let k = TAU * (2.0 + m as f32) / n as f32;
            (
                [k * s * theta.cos(), k * s * theta.sin(), k * z],
                phase,
                1.0 / (1.0 + 0.3 * m as f32),
            )
        })
        .collect();
    let total: f32 = modes.iter().map(|m| m.2).sum();
    let half = n as f32 / 2.0;
    let radius = (0.35 + 0.6 * t as f32 / (steps.max(2) - 1) as f32) * half;
    let mut v = Vec::with_capacity(n * n * n);
    for z in 0..n {
        for y in 0..n {
            for x in 0..n {
                let p = [x as f32, y as f32, z as f32];
                let d = p
                    .iter()
                    .map(|c| (c - half) * (c - half))
                    .sum::<f32>()
                    .sqrt();
                let inside = (radius - d + 0.5).clamp(0.0, 1.0);
                let s: f32 = modes
                    .iter()
                    .map(|(k, phase, a)| {
                        a * (k[0] * p[0] + k[1] * p[1] + k[2] * p[2] + phase).sin()
                    })
                    .sum();
                v.push(inside * (0.5 + 0.5 * s / total).clamp(0.0, 1.0));
            }
        }
    }
    v[0] = 0.0;
    v[n * n * n - 1] = 1.0;
    v
}

/// Step `t` of `steps` of a series that changes character at `steps / 2` while its histogram
/// does not, on an `n³` grid (x fastest), values in [0, 1]. Before: a hydrogen-like 2p
/// orbital, `|ψ|² ∝ z² e^(−ρ)` with `ρ = |p − c| / (n / 10)` normalised to a peak of 1, whose
/// centre `c` drifts by 0.1 n over the first half (smooth: few supersegments per ray). From
/// `steps / 2`: the same orbital at a third of the size tiled 3 × 3 × 3 (each tile the whole
/// field shrunk, so the values' distribution is the first half's), drifting alike: 27 lobes
/// along the rays where there was one, several times the σ at one `P_M`. What tells the two
/// apart is the structure, not the histogram.
pub fn changing_character(n: usize, t: usize, steps: usize) -> Vec<f32> {
    let half = steps / 2;
    let (tiles, t) = if t >= half { (3, t - half) } else { (1, t) };
    let side = n as f32;
    let s = side / 10.0;
    let drift = 0.1 * side * t as f32 / half.max(1) as f32;
    let centre = [side / 2.0 - 0.05 * side + drift, side / 2.0, side / 2.0];
    let peak = 4.0 * (-2.0f32).exp();
    let tile = side / tiles as f32;
    let mut v = Vec::with_capacity(n * n * n);
    for z in 0..n {
        for y in 0..n {
            for x in 0..n {
                // The point in the whole field that this point's tile shows.
                let p = [x, y, z].map(|p| (p as f32 % tile) * tiles as f32);
                let d = [0, 1, 2].map(|i| (p[i] - centre[i]) / s);
                let rho = d.iter().map(|a| a * a).sum::<f32>().sqrt();
                v.push((d[2] * d[2] * (-rho).exp() / peak).clamp(0.0, 1.0));
            }
        }
    }
    v[0] = 0.0;
    v[n * n * n - 1] = 1.0;
    v
}

/// Writes `steps` steps of `field(t)` on an `n³` grid as the 4-D raw series
/// `dir/name_NxNxNxT_float32.raw` (`insitu replay --series`), and returns its path.
///
/// # Panics
/// When the file cannot be written or a step has not `n³` values.
pub fn write_series(
    dir: &Path,
    name: &str,
    n: usize,
    steps: usize,
    field: impl Fn(usize) -> Vec<f32>,
) -> PathBuf {
    let path = dir.join(format!("{name}_{n}x{n}x{n}x{steps}_float32.raw"));
    let mut f = std::io::BufWriter::new(std::fs::File::create(&path).unwrap());
    for t in 0..steps {
        let v = field(t);
        assert_eq!(v.len(), n * n * n);
        let bytes: Vec<u8> = v.iter().flat_map(|x| x.to_le_bytes()).collect();
        f.write_all(&bytes).unwrap();
    }
    f.flush().unwrap();
    path
}

/// One stored step of a run, from its `--json` line.
#[derive(Clone, Debug, PartialEq)]
pub struct StepLine {
    /// Step index.
    pub step: u64,
    /// `P_M` version it was made with.
    pub pm_version: u64,
    /// Its `P_M`.
    pub r: u32,
    /// Its `P_M`.
    pub gamma: f64,
    /// σ, bytes.
    pub sigma_bytes: u64,
    /// τ, seconds.
    pub tau_secs: f64,
    /// q, dB, on sampled steps.
    pub q_db: Option<f64>,
}

impl StepLine {
    /// Its `P_M` as `(r, γ)` (what [`insitu_core::adherence::Adherence`] counts changes of).
    pub fn pm(&self) -> (u32, f32) {
        (self.r, self.gamma as f32)
    }
}

/// What a `demo` or `replay --json` run printed: its steps (one rank each), its `P_M` changes
/// and its summary.
#[derive(Clone, Debug, Default)]
pub struct RunLines {
    /// Stored steps, by step index.
    pub steps: Vec<StepLine>,
    /// The `pm_change` events.
    pub decisions: Vec<serde_json::Value>,
    /// The summary object.
    pub summary: serde_json::Value,
}

impl RunLines {
    /// Prints every step and decision to stderr (what a failing test shows).
    pub fn log(&self) {
        for s in &self.steps {
            eprintln!("{s:?}");
        }
        for d in &self.decisions {
            eprintln!("{d}");
        }
    }

    /// Adherence of the steps from step `from` on to the size budget `budget` (bytes).
    pub fn sigma_adherence(&self, budget: f64, from: u64) -> insitu_core::adherence::Adherence {
        insitu_core::adherence::Adherence::of(
            self.steps
                .iter()
                .filter(|s| s.step >= from)
                .map(|s| (s.pm_version, s.pm(), s.sigma_bytes as f64)),
            budget,
        )
    }

    /// Reads the JSON lines of `stdout` (lines that are not JSON are skipped).
    pub fn parse(stdout: &str) -> Self {
        let mut out = Self::default();
        for line in stdout.lines() {
            let Ok(v) = serde_json::from_str::<serde_json::Value>(line) else {
                continue;
            };
            if v.get("event").and_then(|e| e.as_str()) == Some("pm_change") {
                out.decisions.push(v);
            } else if let Some(s) = v.get("summary") {
                out.summary = s.clone();
            } else if v.get("sigma_bytes").is_some() && v["composed"] != true {
                out.steps.push(StepLine {
                    step: v["step"].as_u64().unwrap_or(0),
                    pm_version: v["pm_version"].as_u64().unwrap_or(0),
                    r: v["r"].as_u64().unwrap_or(0) as u32,
                    gamma: v["gamma"].as_f64().unwrap_or(f64::NAN),
                    sigma_bytes: v["sigma_bytes"].as_u64().unwrap_or(0),
                    tau_secs: v["tau_s"].as_f64().unwrap_or(f64::NAN),
                    q_db: v["q_db"].as_f64(),
                });
            }
        }
        out.steps.sort_by_key(|s| s.step);
        out
    }
}

/// A dense, semi-transparent 64³ field that shifts with `step` (every ray crosses many
/// samples under the default transfer function): slow to render large, for the tests and
/// benches of the viewer's render lanes.
pub fn dense(step: u64) -> Vec<f32> {
    let n = 64usize;
    let s = step as f32 * 0.3;
    (0..n * n * n)
        .map(|i| {
            let (x, y, z) = (i % n, (i / n) % n, i / (n * n));
            ((x as f32 * 0.31 + s).sin() * (y as f32 * 0.23).cos() + (z as f32 * 0.17).sin()).abs()
        })
        .collect()
}

/// Pushes `steps` steps of [`dense`] to the generator-node at `addr` at r = 256 (big enough
/// that a 4096² still takes most of a second here) and flushes.
///
/// # Panics
/// When the node cannot be reached or refuses them (a test's setup).
pub fn push_dense(addr: &str, steps: u64) {
    crate::rt().block_on(async {
        let mut c = insitu_client::SimClient::connect(addr, None).await.unwrap();
        c.set_config(insitu_proto::pb::GenerationConfig {
            resolution: 256,
            gamma: 0.01,
            ..Default::default()
        })
        .await
        .unwrap();
        for s in 0..steps {
            let step = insitu_client::Step::whole_f32(s, s as f64, [64; 3], &dense(s));
            c.push_step(step).await.unwrap();
        }
        c.flush(std::time::Duration::from_secs(300)).await.unwrap();
    });
}
