//! A viz-node's recording read from Python: its steps as dicts and any step's picture from any
//! orbit view, read-only (a running viz-node may go on writing it).

use crate::offline::{image_array, Vdi};
use insitu_core::raycast::DEFAULT_TERMINATION;
use insitu_core::vdi::codec::{decode, DecodeLimits};
use insitu_core::vdi::render;
use insitu_recording::rows::{Entry, StepEntry};
use numpy::PyArray3;
use pyo3::exceptions::{PyKeyError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;
use std::path::PathBuf;

/// One step as the recording holds it: the composed step of several ranks, or the one rank's
/// entry.
enum Stored {
    Composed(StepEntry),
    Single(Entry),
}

impl Stored {
    fn step(&self) -> u64 {
        match self {
            Self::Composed(s) => s.step,
            Self::Single(e) => e.step,
        }
    }

    fn vdi(&self) -> Option<&str> {
        match self {
            Self::Composed(s) => s.vdi.as_deref(),
            Self::Single(e) => e.vdi.as_deref(),
        }
    }

    fn dict<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let d = PyDict::new(py);
        d.set_item("step", self.step())?;
        d.set_item("vdi", self.vdi())?;
        let (sizing, r, gamma, version, quality) = match self {
            Self::Composed(s) => {
                d.set_item("world_size", s.world_size)?;
                d.set_item("ranks", s.ranks.clone())?;
                d.set_item("missing", s.missing.clone())?;
                d.set_item("error", s.error.clone())?;
                (&s.sizing, s.resolution, s.gamma, s.pm_version, &s.quality)
            }
            Self::Single(e) => {
                d.set_item("world_size", e.world_size)?;
                d.set_item("ranks", vec![e.rank])?;
                d.set_item("missing", Vec::<u32>::new())?;
                d.set_item("error", None::<String>)?;
                d.set_item("sim_time", e.sim_time)?;
                (&e.sizing, e.resolution, e.gamma, e.pm_version, &e.quality)
            }
        };
        d.set_item("r", r)?;
        d.set_item("gamma", gamma)?;
        d.set_item("pm_version", version)?;
        d.set_item("sigma_bytes", sizing.sigma_bytes)?;
        d.set_item("supersegments", sizing.supersegments)?;
        d.set_item("tau_s", sizing.tau_secs)?;
        d.set_item("q_db", quality.as_ref().map(|q| q.q_db.0))?;
        Ok(d)
    }
}

/// A viz-node's recording, read-only.
#[pyclass(module = "insitu._insitu")]
pub struct Recording {
    dir: PathBuf,
    steps: Vec<Stored>,
}

#[pymethods]
impl Recording {
    #[new]
    fn new(path: PathBuf) -> PyResult<Self> {
        let (entries, composed) = insitu_recording::index::read(&path)
            .map_err(|e| PyValueError::new_err(format!("{}: {e}", path.display())))?;
        let mut steps: Vec<Stored> = composed.into_iter().map(Stored::Composed).collect();
        steps.extend(
            entries
                .into_iter()
                .filter(|e| e.world_size <= 1)
                .map(Stored::Single),
        );
        steps.sort_by_key(Stored::step);
        Ok(Self { dir: path, steps })
    }

    /// Every stored step, in order, as dicts: step, world_size, ranks, missing, error, vdi
    /// (the file), r, gamma, pm_version, sigma_bytes, supersegments, tau_s, q_db (None until
    /// scored).
    #[getter]
    fn steps<'py>(&self, py: Python<'py>) -> PyResult<Vec<Bound<'py, PyDict>>> {
        self.steps.iter().map(|s| s.dict(py)).collect()
    }

    /// The VDI of `step` (composed over its ranks).
    fn vdi(&self, step: u64) -> PyResult<Vdi> {
        let stored = self
            .steps
            .iter()
            .find(|s| s.step() == step)
            .ok_or_else(|| {
                PyKeyError::new_err(format!("no step {step} in {}", self.dir.display()))
            })?;
        let file = stored.vdi().ok_or_else(|| {
            PyValueError::new_err(format!("step {step} has no VDI (partial or refused)"))
        })?;
        let path = self.dir.join(file);
        let bytes = std::fs::read(&path)
            .map_err(|e| PyValueError::new_err(format!("{}: {e}", path.display())))?;
        let vdi = decode(&bytes, &DecodeLimits::default())
            .map_err(|e| PyValueError::new_err(format!("{}: {e}", path.display())))?;
        Ok(Vdi::from(vdi))
    }

    /// `step`'s picture from its generation camera orbited by `angle` and raised by
    /// `elevation` degrees: an array (size, size, 3), RGB in [0, 1].
    #[pyo3(signature = (step, *, size=512, angle=0.0, elevation=0.0))]
    fn image<'py>(
        &self,
        py: Python<'py>,
        step: u64,
        size: u32,
        angle: f32,
        elevation: f32,
    ) -> PyResult<Bound<'py, PyArray3<f32>>> {
        let vdi = self.vdi(step)?;
        let cam = crate::offline::orbit(&vdi.inner().meta().camera, angle, elevation)?;
        let s = crate::offline::size(size)?;
        let image = py.detach(|| render::render(vdi.inner(), &cam, s, s, DEFAULT_TERMINATION));
        image_array(py, &image)
    }

    fn __len__(&self) -> usize {
        self.steps.len()
    }

    fn __repr__(&self) -> String {
        format!(
            "insitu.Recording({:?}, {} steps)",
            self.dir.display().to_string(),
            self.steps.len()
        )
    }
}
