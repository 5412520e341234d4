//! The tuner against brute force and against itself.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use insitu_core::evaluate::Sizing;
use insitu_core::vdi::codec::Codec;
use insitu_core::volume::RawFormat;
use insitu_core::{Camera, RaycastParams, Raycaster, TransferFunction, Volume};
use insitu_tuner::search::{adaptive_search, grid_search, size_ladder};
use insitu_tuner::study::StudyError;
use insitu_tuner::utility::{best, QualityTarget, SizeBudget, UtilitySpec};
use insitu_tuner::{Candidate, Measurement, Oracle, ParamGrid, Study, StudySetup, TableOracle};
use std::collections::BTreeSet;

fn blob() -> Volume {
    Volume::from_fn([24, 24, 24], |x, y, z| {
        let d = ((x as f32 - 12.0).powi(2) + (y as f32 - 10.0).powi(2) + (z as f32 - 13.0).powi(2))
            .sqrt();
        (9.0 - d).max(0.0) + 0.3 * ((x * 7 + y * 3 + z) % 5) as f32
    })
    .unwrap()
}

fn scene<'a>(v: &'a Volume, tf: &TransferFunction, size: u32, codec: Codec) -> StudySetup<'a> {
    // The scene borrows its ray-caster; a test's few small ones may live to the end.
    let rc: &'a Raycaster<'a> = Box::leak(Box::new(
        Raycaster::new(v, tf, RaycastParams::default()).unwrap(),
    ));
    let cam = Camera::default_for_box(&v.world_box());
    StudySetup::new(
        insitu_core::backend::PreparedVolume::Cpu(rc),
        v.content_hash(),
        tf,
        "tf",
        cam,
        &[0.0, 30.0],
        (size, size),
        codec,
    )
    .unwrap()
}

#[test]
fn a_second_identical_run_generates_nothing_and_changed_inputs_are_not_trusted() {
    let dir = tempfile::tempdir().unwrap();
    let v = blob();
    let tf = TransferFunction::default_for_range(0.0, 10.0);
    let grid = ParamGrid::parse("16,24,32", "0.01,0.05,0.2").unwrap();
    let mut s = Study::new(scene(&v, &tf, 24, Codec::Zstd), Some(dir.path()));
    let first = s.run(&grid.candidates(), |_, _| {}).unwrap();
    assert_eq!(s.generations(), 9);
    let mut again = Study::new(scene(&v, &tf, 24, Codec::Zstd), Some(dir.path()));
    let second = again.run(&grid.candidates(), |_, _| {}).unwrap();
    assert_eq!(again.generations(), 0, "the cache should answer everything");
    assert_eq!(first, second);
    // Any input the rows depend on changes the identity: TF, codec, image size.
    for sc in [
        scene(
            &v,
            &TransferFunction::default_for_range(0.0, 11.0),
            24,
            Codec::Zstd,
        ),
        scene(&v, &tf, 24, Codec::Bzip2),
        scene(&v, &tf, 20, Codec::Zstd),
    ] {
        let mut other = Study::new(sc, Some(dir.path()));
        other.run(&grid.candidates()[..1], |_, _| {}).unwrap();
        assert_eq!(other.generations(), 1);
    }
    // A corrupt cache file is rebuilt, not trusted.
    let files: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    for f in &files {
        std::fs::write(f, b"{\"version\": 1, \"entries\": [tru").unwrap();
    }
    let mut rebuilt = Study::new(scene(&v, &tf, 24, Codec::Zstd), Some(dir.path()));
    rebuilt.run(&grid.candidates(), |_, _| {}).unwrap();
    assert_eq!(rebuilt.generations(), 9);
    let mut trusted = Study::new(scene(&v, &tf, 24, Codec::Zstd), Some(dir.path()));
    trusted.run(&grid.candidates(), |_, _| {}).unwrap();
    assert_eq!(trusted.generations(), 0);
}

/// Brute force: the largest q among rows with σ < target.
fn brute_best_q(rows: &[Measurement], target: u64) -> Option<f64> {
    rows.iter()
        .filter(|m| m.sizing.sigma_bytes < target)
        .map(Measurement::q)
        .max_by(f64::total_cmp)
}

fn real(name: &str, tf: &str, grid: &ParamGrid) -> Option<Vec<Measurement>> {
    let path = insitu_testenv::data_file(name)?;
    let tf_path = insitu_testenv::tf_file(tf)?;
    let v = RawFormat::from_file_name(&path)
        .unwrap()
        .load(&path, 0, glam::Vec3::ONE)
        .unwrap();
    let tf = TransferFunction::load(&tf_path).unwrap();
    let mut s = Study::new(scene(&v, &tf, 64, Codec::Bzip2), None);
    Some(s.run(&grid.candidates(), |_, _| {}).unwrap())
}

fn check_ladder(rows: &[Measurement]) {
    let ladder = size_ladder(rows);
    assert!(ladder.len() >= 3, "{ladder:?}");
    for &target in &ladder {
        let (m, _) = best(
            rows,
            &SizeBudget {
                sigma_target: target,
            },
        )
        .unwrap();
        assert!(m.sizing.sigma_bytes < target);
        assert_eq!(Some(m.q()), brute_best_q(rows, target), "σ_target {target}");
    }
    let smallest = rows.iter().map(|m| m.sizing.sigma_bytes).min().unwrap();
    assert!(
        best(
            rows,
            &SizeBudget {
                sigma_target: smallest
            }
        )
        .is_none(),
        "infeasible must be None"
    );
}

/// A table oracle that records which candidates were measured fully and which only sized.
struct Counting<'t> {
    table: TableOracle<'t>,
    full: BTreeSet<(u32, u32)>,
    sized: BTreeSet<(u32, u32)>,
}

impl<'t> Counting<'t> {
    fn new(rows: &'t [Measurement]) -> Self {
        Self {
            table: TableOracle::new(rows),
            full: BTreeSet::new(),
            sized: BTreeSet::new(),
        }
    }
}

impl Oracle for Counting<'_> {
    fn measure(&mut self, c: Candidate) -> Result<Measurement, StudyError> {
        self.full.insert((c.r, c.gamma.to_bits()));
        self.table.measure(c)
    }

    fn measure_sizing(&mut self, c: Candidate) -> Result<Sizing, StudyError> {
        self.sized.insert((c.r, c.gamma.to_bits()));
        self.table.measure(c).map(|m| m.sizing)
    }

    fn generations(&self) -> u64 {
        self.table.generations()
    }

    fn generation_secs(&self) -> f64 {
        self.table.generation_secs()
    }
}

fn check_adaptive(rows: &[Measurement], grid: &ParamGrid) {
    let (mut adaptive_total, mut budgets) = (0, 0);
    for target in size_ladder(rows) {
        let mut full = TableOracle::new(rows);
        let g = grid_search(
            &mut full,
            grid,
            &SizeBudget {
                sigma_target: target,
            },
        )
        .unwrap();
        let mut table = Counting::new(rows);
        let a = adaptive_search(&mut table, grid, UtilitySpec::Size(target)).unwrap();
        // Under a size budget the probes need σ alone: a full measurement (rendering and
        // scoring) is paid at most once per resolution, and only for a probed candidate.
        let probed_rs: BTreeSet<u32> = table.sized.iter().map(|k| k.0).collect();
        assert!(
            table.full.len() <= probed_rs.len() && table.full.is_subset(&table.sized),
            "σ_target {target}: {} full measurements for {} resolutions probed",
            table.full.len(),
            probed_rs.len()
        );
        let (gq, aq) = (g.best.as_ref().unwrap().q(), a.best.as_ref().unwrap().q());
        assert!(a.best.as_ref().unwrap().sizing.sigma_bytes < target);
        assert!(
            aq >= gq - 0.25,
            "σ_target {target}: adaptive {aq} dB vs grid {gq} dB"
        );
        assert!(
            a.generations < g.generations,
            "adaptive used {} of {}",
            a.generations,
            g.generations
        );
        adaptive_total += a.generations;
        budgets += 1;
    }
    eprintln!(
        "size ladder of {budgets} budgets: {adaptive_total} generations adaptive, {} per budget on the grid",
        grid.len()
    );
    check_time_ladder(rows, grid);
    // The dual, at a quality the grid can reach.
    let q_target = rows
        .iter()
        .map(Measurement::q)
        .fold(f64::INFINITY, f64::min)
        + 3.0;
    let (g, _) = best(rows, &QualityTarget { q_target }).unwrap();
    let a = adaptive_search(
        &mut TableOracle::new(rows),
        grid,
        UtilitySpec::Quality(q_target),
    )
    .unwrap();
    let a = a.best.unwrap();
    assert!(a.q() >= q_target);
    assert!(
        a.sizing.sigma_bytes as f64 <= g.sizing.sigma_bytes as f64 * 1.25,
        "adaptive σ {} vs grid σ {}",
        a.sizing.sigma_bytes,
        g.sizing.sigma_bytes
    );
    // Below the smallest σ nothing is feasible: a clear None.
    let smallest = rows.iter().map(|m| m.sizing.sigma_bytes).min().unwrap();
    assert!(adaptive_search(
        &mut TableOracle::new(rows),
        grid,
        UtilitySpec::Size(smallest)
    )
    .unwrap()
    .best
    .is_none());
}

/// Time budgets on a measured table, whose τ are timings of a few milliseconds: not
/// monotone in γ (±15 % between neighbours), so the grid's optimum may be a candidate that
/// met the budget by chance once. The adaptive answer meets each budget of a ladder (from the
/// smallest τ up, each 1.2× the previous) in fewer generations than the grid, and is as good
/// (within 0.25 dB, as q is not quite monotone either) as the best candidate at a resolution
/// that meets the budget at every γ, as every smaller resolution does: those answers no noise
/// in the table can hide. (On a grid of 7 γ the gallop saves little: up to 4 probes per
/// resolution; what it saves on the paper's grid is pinned by the noisy-timing test.)
fn check_time_ladder(rows: &[Measurement], grid: &ParamGrid) {
    let tau = |m: &Measurement| m.sizing.tau_secs;
    let (lo, hi) = rows
        .iter()
        .map(tau)
        .fold((f64::INFINITY, 0.0_f64), |(lo, hi), t| {
            (lo.min(t), hi.max(t))
        });
    let mut tau_target = lo * 1.2;
    while tau_target < hi * 1.2 {
        let spec = UtilitySpec::Time(tau_target);
        let slowest_up_to = |r: u32| {
            rows.iter()
                .filter(|m| m.r <= r)
                .map(tau)
                .fold(0.0, f64::max)
        };
        let certain = rows
            .iter()
            .filter(|m| slowest_up_to(m.r) < tau_target)
            .map(Measurement::q)
            .fold(f64::NEG_INFINITY, f64::max);
        let mut table = Counting::new(rows);
        let a = adaptive_search(&mut table, grid, spec).unwrap();
        if let Some(m) = &a.best {
            assert!(tau(m) < tau_target, "{spec:?}: {m:?}");
        }
        let q = a.best.as_ref().map_or(f64::NEG_INFINITY, Measurement::q);
        assert!(
            q >= certain - 0.25,
            "{spec:?}: adaptive {:?} at {q} dB, {certain} dB was certain",
            a.best.as_ref().map(Measurement::candidate)
        );
        assert!(
            a.generations < rows.len() as u64,
            "{spec:?}: {} generations",
            a.generations
        );
        tau_target *= 1.2;
    }
}

#[test]
fn teapot_grid_and_adaptive_optima_match_brute_force() {
    let grid = ParamGrid::parse("48:128:16", "0.002,0.006,0.013,0.03,0.06,0.12,0.26").unwrap();
    let Some(rows) = real("teapot_256x256x178_uint8.raw", "teapot.json", &grid) else {
        return;
    };
    check_ladder(&rows);
    check_adaptive(&rows, &grid);
}

#[test]
fn hydrogen_grid_and_adaptive_optima_match_brute_force() {
    let grid = ParamGrid::parse("32:128:16", "0.001,0.004,0.013,0.03,0.06,0.12,0.26").unwrap();
    let Some(rows) = real("hydrogen_64x64x64_float32.raw", "hydrogen.json", &grid) else {
        return;
    };
    check_ladder(&rows);
    check_adaptive(&rows, &grid);
}

#[test]
fn the_accuracy_sweep_shows_the_expected_trade_offs() {
    use insitu_tuner::accuracy::{sweep, Sweep};
    let v = Volume::from_fn([20, 20, 20], |x, y, z| {
        ((x as f32 * 0.4).sin() + (y as f32 * 0.3).cos() + z as f32 * 0.05).abs()
    })
    .unwrap();
    let tf = TransferFunction::default_for_range(0.0, 3.0);
    let rows = sweep(&Sweep {
        volume: &v,
        tf: &tf,
        tf_name: "ramp",
        base: RaycastParams::default(),
        camera: Camera::default_for_box(&v.world_box()),
        views: &[0.0, 40.0],
        size: 32,
        base_pm: insitu_tuner::Candidate {
            r: 32,
            gamma: 0.013,
            precision: Default::default(),
        },
        codec: Codec::Zstd,
        backend: &insitu_core::Backend::Cpu,
    })
    .unwrap();
    let of = |knob: &str| rows.iter().filter(|r| r.knob == knob).collect::<Vec<_>>();
    // Coarser steps are less accurate.
    let q: Vec<f64> = of("ray-casting step")
        .iter()
        .map(|r| r.q_db.unwrap())
        .collect();
    assert!(q.windows(2).all(|w| w[0] > w[1]), "{q:?}");
    // Empty-space skipping does not change the image.
    assert!(of("empty-space skipping")
        .iter()
        .all(|r| r.q_db == Some(f64::INFINITY)));
    // σ falls as γ grows; a lossless codec does not enlarge the file.
    let s: Vec<u64> = of("VDI threshold γ")
        .iter()
        .map(|r| r.sigma_bytes.unwrap())
        .collect();
    assert!(s.windows(2).all(|w| w[0] >= w[1]), "{s:?}");
    let c = of("codec (lossless)");
    let none = c
        .iter()
        .find(|r| r.value == "none")
        .unwrap()
        .sigma_bytes
        .unwrap();
    assert!(c.iter().all(|r| r.sigma_bytes.unwrap() <= none));
    assert!(rows
        .iter()
        .all(|r| r.tau_secs.is_finite() && r.tau_secs >= 0.0));
}

#[test]
fn charts_are_drawn_and_empty_input_is_an_error() {
    use insitu_tuner::charts;
    let dir = tempfile::tempdir().unwrap();
    let v = blob();
    let tf = TransferFunction::default_for_range(0.0, 10.0);
    let grid = ParamGrid::parse("16,24,32", "0.01,0.05,0.2").unwrap();
    let rows = Study::new(scene(&v, &tf, 24, Codec::Zstd), None)
        .run(&grid.candidates(), |_, _| {})
        .unwrap();
    let map = dir.path().join("map.png");
    charts::study_map(&rows, "blob", &map).unwrap();
    charts::pareto(&rows, "blob", &dir.path().join("p.png")).unwrap();
    let img = image::open(&map).unwrap().to_rgb8();
    assert_eq!(img.dimensions(), (1200, 800));
    let colours: std::collections::HashSet<[u8; 3]> = img.pixels().map(|p| p.0).collect();
    assert!(
        colours.len() > 50,
        "the map looks blank: {} colours",
        colours.len()
    );
    assert!(matches!(
        charts::study_map(&[], "x", &map),
        Err(charts::ChartError::Empty(_))
    ));
}

/// A synthetic scene whose τ is a timing: each call draws fresh noise of relative amplitude
/// `noise` (as a trial after a probe times a second generation). The truth: τ = 2·10⁻⁷ r²
/// seconds, 15 % less at the largest γ; q = 20 + 8 ln(r/64) − 40γ dB; σ = 4r²/(1 + 40γ).
struct NoisyTimings {
    noise: f64,
    state: u64,
    generations: u64,
    secs: f64,
    /// The `P_M` in force, whose σ and τ production measured: its probe costs no generation.
    produced: Option<Candidate>,
}

impl NoisyTimings {
    fn new(noise: f64, seed: u64) -> Self {
        Self {
            noise,
            state: seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1,
            generations: 0,
            secs: 0.0,
            produced: None,
        }
    }

    /// The same, with `c` measured by production.
    fn produced(self, c: Candidate) -> Self {
        Self {
            produced: Some(c),
            ..self
        }
    }

    fn true_tau(c: Candidate) -> f64 {
        2e-7 * f64::from(c.r).powi(2) * (1.0 - 0.6 * f64::from(c.gamma))
    }

    fn sigma(c: Candidate) -> u64 {
        (4.0 * f64::from(c.r).powi(2) / (1.0 + 40.0 * f64::from(c.gamma))) as u64
    }

    fn q(c: Candidate) -> f64 {
        20.0 + 8.0 * (f64::from(c.r) / 64.0).ln() - 40.0 * f64::from(c.gamma)
    }

    /// Uniform in [−1, 1] (xorshift64).
    fn draw(&mut self) -> f64 {
        self.state ^= self.state << 13;
        self.state ^= self.state >> 7;
        self.state ^= self.state << 17;
        (self.state >> 11) as f64 / (1u64 << 52) as f64 - 1.0
    }
}

impl Oracle for NoisyTimings {
    fn measure(&mut self, c: Candidate) -> Result<Measurement, StudyError> {
        Ok(Measurement {
            r: c.r,
            gamma: c.gamma,
            sizing: self.measure_sizing(c)?,
            tau_render_secs: 0.0,
            q_db: insitu_core::metrics::Db(Self::q(c)),
            view_q_db: vec![],
            ssim: None,
            precision: Default::default(),
            sigma_paper_bytes: None,
        })
    }

    fn measure_sizing(&mut self, c: Candidate) -> Result<Sizing, StudyError> {
        let tau = Self::true_tau(c) * (1.0 + self.noise * self.draw());
        if self.produced != Some(c) {
            self.generations += 1;
            self.secs += tau;
        }
        Ok(Sizing {
            sigma_bytes: Self::sigma(c),
            tau_secs: tau,
            ..Sizing::default()
        })
    }

    fn generations(&self) -> u64 {
        self.generations
    }

    fn generation_secs(&self) -> f64 {
        self.secs
    }
}

/// Under time budgets (alone and with a size budget) with timings ±20 % noisy, the adaptive
/// search's answer meets the budgets as measured and is at least as good as the best candidate
/// that meets them under any noise, in at most a fifth of the grid's generations.
#[test]
fn time_budgets_are_searched_adaptively_despite_noisy_timings() {
    let grid = ParamGrid::parse("128:768:32", "0.001:0.26:0.008").unwrap();
    let noise = 0.2;
    let mut most = 0;
    for seed in 0..500 {
        for tau_target in [0.005, 0.01, 0.02, 0.04, 0.08] {
            for spec in [
                UtilitySpec::Time(tau_target),
                UtilitySpec::SizeAndTime(600_000, tau_target),
            ] {
                let sigma_target = spec.budgets().size_bytes;
                let robust = grid
                    .candidates()
                    .into_iter()
                    .filter(|&c| {
                        NoisyTimings::true_tau(c) * (1.0 + noise) < tau_target
                            && sigma_target.is_none_or(|t| NoisyTimings::sigma(c) < t)
                    })
                    .map(NoisyTimings::q)
                    .fold(f64::NEG_INFINITY, f64::max);
                let mut oracle = NoisyTimings::new(noise, seed);
                let a = adaptive_search(&mut oracle, &grid, spec).unwrap();
                let m = a
                    .best
                    .unwrap_or_else(|| panic!("seed {seed}, {spec:?}: nothing found"));
                assert!(spec.utility().value(&m) < f64::INFINITY, "{spec:?}: {m:?}");
                assert!(
                    m.q() >= robust,
                    "seed {seed}, {spec:?}: q {} dB at r {} γ {}, {robust} dB was certain",
                    m.q(),
                    m.r,
                    m.gamma
                );
                most = most.max(a.generations);
            }
        }
    }
    assert!(
        most <= grid.len() as u64 / 5,
        "{most} generations of a grid of {}",
        grid.len()
    );
}

/// A re-tune under a size budget starts at the P_M in force (whose σ production measured on the
/// step): it finds the answer the plain search finds, wherever the P_M in force lies, and when
/// that P_M is the answer (still data) or a neighbour of it (drift), in fewer generations.
#[test]
fn a_size_search_from_the_p_m_in_force_finds_the_same_answer_sooner() {
    use insitu_tuner::search::adaptive_search_near;
    let grid = ParamGrid::parse("128:768:32", "0.001:0.26:0.008").unwrap();
    let (mut plain_total, mut near_total) = (0, 0);
    for sigma_target in [150_000u64, 400_000, 900_000, 2_000_000] {
        let spec = UtilitySpec::Size(sigma_target);
        let a = adaptive_search(&mut NoisyTimings::new(0.0, 1), &grid, spec).unwrap();
        let best = a.best.as_ref().unwrap().candidate();
        let step = |i: usize, d: isize| i.saturating_add_signed(d);
        let (ri, gi) = (
            grid.rs.iter().position(|&r| r == best.r).unwrap(),
            grid.gammas
                .iter()
                .position(|g| g.to_bits() == best.gamma.to_bits())
                .unwrap(),
        );
        let mut hints = vec![best];
        for (dr, dg) in [(0, 2), (0, -2), (-1, 1), (1, -1)] {
            let (r, g) = (step(ri, dr), step(gi, dg));
            if r < grid.rs.len() && g < grid.gammas.len() {
                hints.push(Candidate {
                    r: grid.rs[r],
                    gamma: grid.gammas[g],
                    precision: Default::default(),
                });
            }
        }
        // Far away too: the answer is the same, whatever the probes cost.
        hints.push(Candidate {
            r: grid.rs[0],
            gamma: grid.gammas[grid.gammas.len() - 1],
            precision: Default::default(),
        });
        for (k, hint) in hints.iter().enumerate() {
            let mut oracle = NoisyTimings::new(0.0, 1).produced(*hint);
            let n = adaptive_search_near(&mut oracle, &grid, spec, Some(*hint)).unwrap();
            assert_eq!(
                n.best.as_ref().map(Measurement::candidate),
                Some(best),
                "σ_target {sigma_target}, from {hint:?}"
            );
            if k + 1 < hints.len() {
                plain_total += a.generations;
                near_total += n.generations;
            }
        }
    }
    assert!(
        near_total < plain_total,
        "from the P_M in force or a neighbour: {near_total} generations, plain: {plain_total}"
    );
    eprintln!("size searches from the P_M in force or a neighbour: {near_total} generations against {plain_total}");
}
