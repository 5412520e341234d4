//! The Gray–Scott reaction–diffusion model: the embedded demo simulation (docs/conventions.md, "Data").
//!
//! Settings follow the ADIOS2 tutorial's `gray-scott`: `Du = 0.2`, `Dv = 0.1`, `F = 0.01`,
//! `k = 0.05`, `dt = 2.0`, noise `1e-7` (uniform in ±noise, added to du), a 7-point Laplacian
//! divided by 6, periodic boundaries; initially `u = 1`, `v = 0` except a centred cube of
//! side 12 where `u = 0.25`, `v = 0.33`. The field shown is V.
//!
//! The noise comes from a counter-based hash of (seed, step, cell), so a run is the same
//! whatever the thread count.

use super::{Volume, VolumeError};
use glam::Vec3;
use rayon::prelude::*;

/// Model constants; [`Default`] is the ADIOS2 tutorial's set.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GrayScottParams {
    /// Diffusion rate of U.
    pub du: f64,
    /// Diffusion rate of V.
    pub dv: f64,
    /// Feed rate.
    pub f: f64,
    /// Kill rate.
    pub k: f64,
    /// Time step.
    pub dt: f64,
    /// Amplitude of the uniform noise added to du each step.
    pub noise: f64,
    /// Seed of the noise.
    pub seed: u64,
}

impl Default for GrayScottParams {
    fn default() -> Self {
        Self {
            du: 0.2,
            dv: 0.1,
            f: 0.01,
            k: 0.05,
            dt: 2.0,
            noise: 1e-7,
            seed: 0x5eed_2026,
        }
    }
}

/// A running Gray–Scott simulation on an `n³` periodic grid.
#[derive(Clone, Debug)]
pub struct GrayScott {
    n: usize,
    params: GrayScottParams,
    step: u64,
    u: Vec<f64>,
    v: Vec<f64>,
    u_next: Vec<f64>,
    v_next: Vec<f64>,
}

/// Default number of steps for `gray-scott:N` without a step count.
pub const DEFAULT_GRAY_SCOTT_STEPS: u64 = 1000;

impl GrayScott {
    /// Side of the initial cube of perturbed values (ADIOS2: `d = 6` either side of the centre).
    const SEED_CUBE_HALF: usize = 6;

    /// Sets up the initial state on an `n³` grid.
    ///
    /// # Errors
    /// [`VolumeError::Invalid`] when `n < 2 · 6` (the seed cube would not fit) or `n > 1024`.
    pub fn new(n: usize, params: GrayScottParams) -> Result<Self, VolumeError> {
        if !(2 * Self::SEED_CUBE_HALF..=1024).contains(&n) {
            return Err(VolumeError::Invalid(format!(
                "gray-scott grid size {n} must be in 12..=1024"
            )));
        }
        let len = n * n * n;
        let mut u = vec![1.0; len];
        let mut v = vec![0.0; len];
        let lo = n / 2 - Self::SEED_CUBE_HALF;
        let hi = n / 2 + Self::SEED_CUBE_HALF;
        for z in lo..hi {
            for y in lo..hi {
                for x in lo..hi {
                    let i = x + n * (y + n * z);
                    u[i] = 0.25;
                    v[i] = 0.33;
                }
            }
        }
        Ok(Self {
            n,
            params,
            step: 0,
            u_next: u.clone(),
            v_next: v.clone(),
            u,
            v,
        })
    }

    /// Parses `gray-scott:N[:STEPS]` and runs the model for STEPS (default
    /// `DEFAULT_GRAY_SCOTT_STEPS`, 1000) steps.
    ///
    /// # Errors
    /// [`VolumeError::Invalid`] naming the spec when it does not parse or N is out of range.
    pub fn from_spec(spec: &str) -> Result<Self, VolumeError> {
        let bad = || {
            VolumeError::Invalid(format!(
                "{spec:?} is not a Gray-Scott source; expected gray-scott:N[:STEPS], e.g. gray-scott:64:1000"
            ))
        };
        let mut parts = spec.split(':');
        if parts.next() != Some("gray-scott") {
            return Err(bad());
        }
        let n = parts
            .next()
            .ok_or_else(bad)?
            .parse::<usize>()
            .map_err(|_| bad())?;
        let steps = match parts.next() {
            Some(s) => s.parse::<u64>().map_err(|_| bad())?,
            None => DEFAULT_GRAY_SCOTT_STEPS,
        };
        if parts.next().is_some() {
            return Err(bad());
        }
        let mut sim = Self::new(n, GrayScottParams::default())?;
        sim.advance(steps);
        Ok(sim)
    }

    /// Changes the model constants from the next step on (a simulation switching regime, e.g.
    /// other feed and kill rates); the state is kept.
    pub fn set_params(&mut self, params: GrayScottParams) {
        self.params = params;
    }

    /// The model constants.
    pub fn params(&self) -> GrayScottParams {
        self.params
    }

    /// Steps taken so far.
    pub fn step_index(&self) -> u64 {
        self.step
    }

    /// Grid side `n`.
    pub fn size(&self) -> usize {
        self.n
    }

    /// Runs `steps` explicit Euler steps.
    pub fn advance(&mut self, steps: u64) {
        for _ in 0..steps {
            self.step_once();
        }
    }

    fn step_once(&mut self) {
        let n = self.n;
        let p = self.params;
        let (u, v) = (&self.u, &self.v);
        let step = self.step;
        let plane = n * n;
        self.u_next
            .par_chunks_mut(plane)
            .zip(self.v_next.par_chunks_mut(plane))
            .enumerate()
            .for_each(|(z, (u_out, v_out))| {
                let zm = (z + n - 1) % n;
                let zp = (z + 1) % n;
                for y in 0..n {
                    let ym = (y + n - 1) % n;
                    let yp = (y + 1) % n;
                    for x in 0..n {
                        let xm = (x + n - 1) % n;
                        let xp = (x + 1) % n;
                        let at = |xx: usize, yy: usize, zz: usize| xx + n * (yy + n * zz);
                        let i = at(x, y, z);
                        let lap = |s: &[f64]| {
                            (s[at(xm, y, z)]
                                + s[at(xp, y, z)]
                                + s[at(x, ym, z)]
                                + s[at(x, yp, z)]
                                + s[at(x, y, zm)]
                                + s[at(x, y, zp)]
                                - 6.0 * s[i])
                                / 6.0
                        };
                        let (tu, tv) = (u[i], v[i]);
                        let uvv = tu * tv * tv;
                        let mut du = p.du * lap(u) - uvv + p.f * (1.0 - tu);
                        let dv = p.dv * lap(v) + uvv - (p.f + p.k) * tv;
                        du += p.noise * uniform_pm1(p.seed, step, i as u64);
                        let o = x + n * y;
                        u_out[o] = tu + du * p.dt;
                        v_out[o] = tv + dv * p.dt;
                    }
                }
            });
        std::mem::swap(&mut self.u, &mut self.u_next);
        std::mem::swap(&mut self.v, &mut self.v_next);
        self.step += 1;
    }

    /// The field V as f32, x fastest (n³ values), written into `out` (cleared first): a
    /// simulation's copy out of its own buffer into memory it keeps between pushes, so that
    /// no push faults in fresh pages. Converted in parallel, one z plane per task.
    pub fn copy_v_into(&self, out: &mut Vec<f32>) {
        out.clear();
        out.resize(self.v.len(), 0.0);
        let plane = self.n * self.n;
        out.par_chunks_mut(plane)
            .zip(self.v.par_chunks(plane))
            .for_each(|(o, v)| {
                for (o, &v) in o.iter_mut().zip(v) {
                    *o = v as f32;
                }
            });
    }

    /// The field V as a volume with unit spacing.
    pub fn v_volume(&self) -> Volume {
        let mut data = Vec::new();
        self.copy_v_into(&mut data);
        // n ≥ 12 and the length is n³ by construction, so this cannot fail; fall back to a
        // 1-voxel volume rather than panic if that ever changes.
        Volume::new([self.n; 3], Vec3::ONE, data).unwrap_or_else(|_| Volume {
            dims: [1, 1, 1],
            spacing: Vec3::ONE,
            origin: Vec3::ZERO,
            data: super::Storage::F32(vec![0.0]),
        })
    }
}

/// Uniform in [−1, 1) from a SplitMix64 hash of (seed, step, cell).
fn uniform_pm1(seed: u64, step: u64, cell: u64) -> f64 {
    let mut z =
        seed ^ step.wrapping_mul(0x9e37_79b9_7f4a_7c15) ^ cell.wrapping_mul(0xd1b5_4a32_d192_ed03);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^= z >> 31;
    (z >> 11) as f64 * (2.0 / (1u64 << 53) as f64) - 1.0
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn initial_state_matches_the_tutorial() {
        let sim = GrayScott::new(32, GrayScottParams::default()).unwrap();
        let v = sim.v_volume();
        let at = |x: usize, y: usize, z: usize| v.data()[x + 32 * (y + 32 * z)];
        assert_eq!(at(10, 10, 10), 0.33);
        assert_eq!(at(21, 21, 21), 0.33);
        assert_eq!(at(9, 16, 16), 0.0);
        assert_eq!(at(22, 16, 16), 0.0);
    }

    #[test]
    fn without_noise_a_uniform_state_follows_the_reaction_ode() {
        // With u = 1, v = 0 everywhere the Laplacian vanishes and du = F(1−u) = 0: a fixed point.
        let params = GrayScottParams {
            noise: 0.0,
            ..GrayScottParams::default()
        };
        let mut sim = GrayScott::new(16, params).unwrap();
        sim.u.fill(1.0);
        sim.v.fill(0.0);
        sim.advance(5);
        assert!(sim.u.iter().all(|&x| x == 1.0));
        assert!(sim.v.iter().all(|&x| x == 0.0));
    }

    #[test]
    fn pattern_grows_and_stays_finite_and_deterministic() {
        let a = GrayScott::from_spec("gray-scott:24:200").unwrap();
        let b = GrayScott::from_spec("gray-scott:24:200").unwrap();
        assert_eq!(a.v_volume(), b.v_volume());
        let v = a.v_volume();
        assert!(v.data().iter().all(|x| x.is_finite()));
        let (lo, hi) = v.finite_range().unwrap();
        assert!(lo >= 0.0 && hi > 0.05 && hi < 1.0, "range {lo}..{hi}");
        // Diffusion spreads V beyond the seed cube.
        assert!(
            v.data()[2 + 24 * (12 + 24 * 12)] != 0.0 || v.data()[5 + 24 * (12 + 24 * 12)] > 0.0
        );
        // The copy into a kept buffer is the volume's data, whatever the buffer held before,
        // in the same memory when it has the room.
        let mut kept = vec![7.0f32; 30 * 30 * 30];
        let at = kept.as_ptr();
        a.copy_v_into(&mut kept);
        assert_eq!(kept.as_slice(), &v.data()[..]);
        assert_eq!(kept.as_ptr(), at);
    }

    #[test]
    fn bad_specs_are_rejected() {
        for s in [
            "gray-scott",
            "gray-scott:x",
            "gray-scott:8",
            "grayscott:32",
            "gray-scott:32:1:2",
        ] {
            assert!(GrayScott::from_spec(s).is_err(), "{s}");
        }
    }

    #[test]
    fn noise_is_uniform_in_pm1() {
        let xs: Vec<f64> = (0..10_000).map(|i| uniform_pm1(1, 2, i)).collect();
        assert!(xs.iter().all(|x| (-1.0..1.0).contains(x)));
        let mean = xs.iter().sum::<f64>() / xs.len() as f64;
        assert!(mean.abs() < 0.03, "mean {mean}");
    }
}
