//! The measurement loop of Alg. 1 (lines 6–24): a scene with its test views, whose reference
//! images are rendered once, measured at candidate `P_M`, every result cached.

use crate::cache::{Cache, CacheError};
use crate::grid::Candidate;
use crate::measure::Measurement;
use insitu_core::backend::{BackendError, PreparedVolume};
use insitu_core::evaluate::{evaluate, EvalError, Sizing};
use insitu_core::tf::TfIdentity;
use insitu_core::vdi::codec::{self, Codec};
use insitu_core::vdi::Precision;
use insitu_core::volume::Fnv1a;
use insitu_core::{Camera, Image, TransferFunction};
use std::path::Path;
use std::time::Instant;

/// Errors of a study.
#[derive(Debug, thiserror::Error)]
pub enum StudyError {
    /// A measurement failed (bad `P_M`, codec).
    #[error(transparent)]
    Eval(#[from] EvalError),
    /// The cache could not be written.
    #[error(transparent)]
    Cache(#[from] CacheError),
    /// The backend failed while rendering the references.
    #[error(transparent)]
    Backend(#[from] BackendError),
    /// Nothing to measure.
    #[error("{0}")]
    Invalid(String),
}

/// Answers "what are σ, q, τ at this `P_M`?" — by measuring, or from a table.
pub trait Oracle {
    /// Measures (or looks up) `c`.
    ///
    /// # Errors
    /// [`StudyError`].
    fn measure(&mut self, c: Candidate) -> Result<Measurement, StudyError>;
    /// σ and τ of `c` alone: all a size or time budget needs to tell a feasible candidate
    /// from another (the adaptive search's probes). Oracles that can generate and encode
    /// without rendering and scoring override it
    /// ([`insitu_core::evaluate::generate_encoded`]); the default measures `c` fully.
    ///
    /// # Errors
    /// [`StudyError`].
    fn measure_sizing(&mut self, c: Candidate) -> Result<Sizing, StudyError> {
        self.measure(c).map(|m| m.sizing)
    }
    /// Candidates generated so far (cache hits excluded).
    fn generations(&self) -> u64;
    /// Sum of τ over those generations, seconds.
    fn generation_secs(&self) -> f64;
}

/// What a study measures: the scene, the test views and their reference images.
pub struct StudySetup<'a> {
    scene: PreparedVolume<'a>,
    camera: Camera,
    view_angles: Vec<f32>,
    references: Vec<Image>,
    codec: Codec,
    tf_hash: u64,
    tf_name: String,
    key: u64,
    description: String,
}

impl<'a> StudySetup<'a> {
    /// Renders the reference image of each view (`width × height`) once.
    ///
    /// `volume_hash` is [`insitu_core::Volume::content_hash`] of the scene's volume. The
    /// backend is part of the identity (τ depends on it).
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        scene: PreparedVolume<'a>,
        volume_hash: u64,
        tf: &TransferFunction,
        tf_name: &str,
        camera: Camera,
        view_angles: &[f32],
        size: (u32, u32),
        codec: Codec,
    ) -> Result<Self, StudyError> {
        if view_angles.is_empty() {
            return Err(StudyError::Invalid(
                "a study needs at least one test view".into(),
            ));
        }
        let p = *scene.raycaster().params();
        let backend = scene.describe();
        let mut h = Fnv1a::new();
        h.write(&volume_hash.to_le_bytes());
        h.write(&tf.identity_hash().to_le_bytes());
        for v in [camera.eye, camera.target, camera.up] {
            for c in v.to_array() {
                h.write(&c.to_bits().to_le_bytes());
            }
        }
        h.write(&camera.fov_y_deg.to_bits().to_le_bytes());
        for a in view_angles {
            h.write(&a.to_bits().to_le_bytes());
        }
        h.write(&size.0.to_le_bytes());
        h.write(&size.1.to_le_bytes());
        h.write(&p.sample_distance.to_bits().to_le_bytes());
        h.write(&p.termination.to_bits().to_le_bytes());
        h.write(&[u8::from(p.shading.is_some())]);
        h.write(codec.name().as_bytes());
        h.write(crate::cache::code_version().as_bytes());
        h.write(backend.as_bytes());
        let key = h.finish();
        let description = format!(
            "tf {tf_name}, views {view_angles:?}, {}×{}, step {}, termination {}, shading {}, codec {codec}, {backend}",
            size.0,
            size.1,
            p.sample_distance,
            p.termination,
            p.shading.is_some()
        );
        let references = view_angles
            .iter()
            .map(|&a| Ok(scene.dvr(&camera.orbit_y(a), size.0, size.1)?.value))
            .collect::<Result<Vec<Image>, BackendError>>()?;
        Ok(Self {
            scene,
            camera,
            view_angles: view_angles.to_vec(),
            references,
            codec,
            tf_hash: tf.identity_hash(),
            tf_name: tf_name.to_owned(),
            key,
            description,
        })
    }

    /// The identity of everything but `P_M` (the cache key).
    pub fn key(&self) -> u64 {
        self.key
    }

    /// A human-readable summary of the identity.
    pub fn description(&self) -> &str {
        &self.description
    }
}

/// A study of one scene: measures candidates, caching every result.
pub struct Study<'a> {
    scene: StudySetup<'a>,
    cache: Cache,
    generations: u64,
    generation_secs: f64,
    /// The last candidate's VDI, whose allocations the next one reuses (as production does
    /// from step to step, so that τ is what production pays).
    spare: Option<insitu_core::vdi::Vdi>,
}

impl<'a> Study<'a> {
    /// A study whose results persist in `cache_dir` (or only in memory when `None`).
    pub fn new(scene: StudySetup<'a>, cache_dir: Option<&Path>) -> Self {
        let cache = match cache_dir {
            Some(dir) => Cache::open(dir, scene.key, &scene.description),
            None => Cache::in_memory(scene.key),
        };
        Self {
            scene,
            cache,
            generations: 0,
            generation_secs: 0.0,
            spare: None,
        }
    }

    /// Measures every candidate (cached ones cost nothing), calling `progress` after each.
    ///
    /// # Errors
    /// [`StudyError`]; rows measured before the error stay cached.
    pub fn run(
        &mut self,
        candidates: &[Candidate],
        mut progress: impl FnMut(usize, &Measurement),
    ) -> Result<Vec<Measurement>, StudyError> {
        if candidates.is_empty() {
            return Err(StudyError::Invalid("the grid is empty".into()));
        }
        let mut rows = Vec::with_capacity(candidates.len());
        let result = candidates.iter().enumerate().try_for_each(|(i, &c)| {
            let m = self.measure(c)?;
            progress(i + 1, &m);
            rows.push(m);
            Ok::<_, StudyError>(())
        });
        self.cache.save()?;
        result.map(|()| rows)
    }

    /// Writes pending cache rows.
    ///
    /// # Errors
    /// [`CacheError`].
    pub fn save(&mut self) -> Result<(), CacheError> {
        self.cache.save()
    }

    /// The scene.
    pub fn scene(&self) -> &StudySetup<'a> {
        &self.scene
    }
}

impl Oracle for Study<'_> {
    fn measure(&mut self, c: Candidate) -> Result<Measurement, StudyError> {
        if let Some(m) = self.cache.get(c) {
            return Ok(m.clone());
        }
        let s = &self.scene;
        let t = Instant::now();
        let (e, _) = evaluate(
            &s.scene,
            &s.camera,
            c.params(),
            s.codec,
            &s.view_angles,
            &s.references,
            TfIdentity {
                hash: s.tf_hash,
                name: &s.tf_name,
            },
            &mut self.spare,
        )?;
        tracing::debug!(
            r = c.r,
            gamma = c.gamma,
            secs = t.elapsed().as_secs_f64(),
            "measured"
        );
        let mut m = Measurement::from_evaluation(&e);
        // The paper's σ beside it: the same VDI as floats under bzip2.
        if (c.precision, s.codec) != (Precision::Float32, Codec::Bzip2) {
            // The spare's precision is set again by its next generation.
            if let Some(vdi) = self.spare.as_mut() {
                vdi.set_precision(Precision::Float32);
                let bytes = codec::encode(vdi, Codec::Bzip2).map_err(EvalError::from)?;
                m.sigma_paper_bytes = Some(bytes.len() as u64);
            }
        }
        self.generations += 1;
        self.generation_secs += m.sizing.tau_secs;
        self.cache.insert(m.clone())?;
        Ok(m)
    }

    fn generations(&self) -> u64 {
        self.generations
    }

    fn generation_secs(&self) -> f64 {
        self.generation_secs
    }
}

/// An oracle answering from a complete study table, counting each distinct candidate it is
/// asked for as one generation costing the τ recorded for it. This prices a search strategy
/// exactly as if it had measured, without measuring again.
pub struct TableOracle<'t> {
    rows: &'t [Measurement],
    asked: std::collections::BTreeSet<(u32, u32, u32)>,
    secs: f64,
}

impl<'t> TableOracle<'t> {
    /// Over `rows`.
    pub fn new(rows: &'t [Measurement]) -> Self {
        Self {
            rows,
            asked: Default::default(),
            secs: 0.0,
        }
    }
}

impl Oracle for TableOracle<'_> {
    fn measure(&mut self, c: Candidate) -> Result<Measurement, StudyError> {
        let m = self
            .rows
            .iter()
            .find(|m| m.candidate().key() == c.key())
            .ok_or_else(|| {
                StudyError::Invalid(format!("r = {}, γ = {} is not in the table", c.r, c.gamma))
            })?;
        if self.asked.insert(c.key()) {
            self.secs += m.sizing.tau_secs;
        }
        Ok(m.clone())
    }

    fn generations(&self) -> u64 {
        self.asked.len() as u64
    }

    fn generation_secs(&self) -> f64 {
        self.secs
    }
}
