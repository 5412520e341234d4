//! The core's maths on NumPy arrays, without daemons: direct volume rendering (the reference),
//! VDI generation, rendering a VDI from any orbit view, saving and loading VDI files, and one
//! `P_M`'s σ, τ and q (the paper's Alg. 1, lines 11–18). Always on the CPU.

use insitu_core::evaluate::{evaluate as evaluate_pm, DEFAULT_VIEW_ANGLES};
use insitu_core::file::{write_atomic, Durability};
use insitu_core::raycast::DEFAULT_TERMINATION;
use insitu_core::vdi::codec::{self, Codec, DecodeLimits};
use insitu_core::vdi::{generate, render};
use insitu_core::{
    Backend, Camera, Image, NamedTf, RaycastParams, Raycaster, TransferFunction, VdiParams,
};
use numpy::ndarray::Array3;
use numpy::{
    IntoPyArray, PyArray3, PyArrayDescrMethods, PyReadonlyArray3, PyUntypedArray,
    PyUntypedArrayMethods,
};
use pyo3::exceptions::{PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;
use std::path::PathBuf;

fn bad(e: impl std::fmt::Display) -> PyErr {
    PyValueError::new_err(e.to_string())
}

/// A NumPy field indexed `[z, y, x]` as a volume at `spacing` and `origin` (copied: the core
/// keeps u8, u16 and i16 as they are, the rest as f32).
fn volume(
    field: &Bound<'_, PyAny>,
    spacing: (f32, f32, f32),
    origin: (f32, f32, f32),
) -> PyResult<insitu_core::Volume> {
    let array = field.cast::<PyUntypedArray>().map_err(|_| {
        PyTypeError::new_err("volume must be a 3-D numpy.ndarray indexed [z, y, x]")
    })?;
    if array.ndim() != 3 {
        return Err(PyValueError::new_err(format!(
            "volume has {} dimensions: it is indexed [z, y, x], shape (nz, ny, nx)",
            array.ndim()
        )));
    }
    let s = array.shape();
    let dims = [s[2], s[1], s[0]];
    let spacing = glam::Vec3::new(spacing.0, spacing.1, spacing.2);
    let dtype = array.dtype();
    let py = field.py();
    let v = if dtype.is_equiv_to(&numpy::dtype::<u8>(py)) {
        let a: PyReadonlyArray3<u8> = field.extract()?;
        insitu_core::Volume::from_u8(dims, spacing, a.as_array().iter().copied().collect())
    } else if dtype.is_equiv_to(&numpy::dtype::<u16>(py)) {
        let a: PyReadonlyArray3<u16> = field.extract()?;
        insitu_core::Volume::from_u16(dims, spacing, a.as_array().iter().copied().collect())
    } else if dtype.is_equiv_to(&numpy::dtype::<i16>(py)) {
        let a: PyReadonlyArray3<i16> = field.extract()?;
        insitu_core::Volume::from_i16(dims, spacing, a.as_array().iter().copied().collect())
    } else if dtype.is_equiv_to(&numpy::dtype::<f32>(py)) {
        let a: PyReadonlyArray3<f32> = field.extract()?;
        insitu_core::Volume::new(dims, spacing, a.as_array().iter().copied().collect())
    } else if dtype.is_equiv_to(&numpy::dtype::<f64>(py)) {
        let a: PyReadonlyArray3<f64> = field.extract()?;
        insitu_core::Volume::new(
            dims,
            spacing,
            a.as_array().iter().map(|&x| x as f32).collect(),
        )
    } else {
        return Err(PyTypeError::new_err(format!(
            "volume dtype {} is not float32, float64, uint8, uint16 or int16",
            dtype.str().map_or_else(|_| "?".into(), |s| s.to_string())
        )));
    };
    v.and_then(|v| v.with_origin(glam::Vec3::new(origin.0, origin.1, origin.2)))
        .map_err(bad)
}

/// `tf` as a transfer function: JSON text (docs/conventions.md format) or a file holding it;
/// none: the default ramp over the volume's range.
fn transfer_function(tf: Option<&str>, v: &insitu_core::Volume) -> PyResult<NamedTf> {
    match tf {
        None => Ok(TransferFunction::default_for_volume(v)),
        Some(t) if t.trim_start().starts_with('{') => Ok(NamedTf::new(
            TransferFunction::from_json(t, "python").map_err(bad)?,
            "python",
        )),
        Some(path) => Ok(NamedTf::new(
            TransferFunction::load(std::path::Path::new(path)).map_err(bad)?,
            path,
        )),
    }
}

/// `camera` orbited by `angle` degrees about +y and raised by `elevation`.
pub(crate) fn orbit(camera: &Camera, angle: f32, elevation: f32) -> PyResult<Camera> {
    if !(-89.0..=89.0).contains(&elevation) || !angle.is_finite() {
        return Err(PyValueError::new_err(format!(
            "angle {angle} must be finite and elevation {elevation} within [-89, 89] degrees"
        )));
    }
    Ok(camera.orbit(angle, elevation, 1.0))
}

/// An image side in pixels, 1 to the largest VDI resolution.
pub(crate) fn size(size: u32) -> PyResult<u32> {
    if size == 0 || size > insitu_core::vdi::MAX_RESOLUTION {
        return Err(PyValueError::new_err(format!(
            "size {size} must be 1 to {}",
            insitu_core::vdi::MAX_RESOLUTION
        )));
    }
    Ok(size)
}

/// An image as an array of shape (height, width, 3), RGB in [0, 1].
pub(crate) fn image_array<'py>(
    py: Python<'py>,
    image: &Image,
) -> PyResult<Bound<'py, PyArray3<f32>>> {
    let (w, h) = (image.width() as usize, image.height() as usize);
    let flat: Vec<f32> = image
        .pixels()
        .iter()
        .flat_map(|p| p.iter().copied())
        .collect();
    let a = Array3::from_shape_vec((h, w, 3), flat).map_err(bad)?;
    Ok(a.into_pyarray(py))
}

/// Direct volume rendering of `volume` (the reference): an array (size, size, 3).
#[pyfunction]
#[pyo3(signature = (volume, tf=None, *, size=512, angle=0.0, elevation=0.0,
                    spacing=(1.0, 1.0, 1.0), origin=(0.0, 0.0, 0.0)))]
#[allow(clippy::too_many_arguments)]
pub fn render_volume<'py>(
    py: Python<'py>,
    volume: &Bound<'py, PyAny>,
    tf: Option<&str>,
    size: u32,
    angle: f32,
    elevation: f32,
    spacing: (f32, f32, f32),
    origin: (f32, f32, f32),
) -> PyResult<Bound<'py, PyArray3<f32>>> {
    let v = self::volume(volume, spacing, origin)?;
    let tf = transfer_function(tf, &v)?.tf;
    let cam = orbit(&Camera::default_for_box(&v.world_box()), angle, elevation)?;
    let s = self::size(size)?;
    let image = py
        .detach(|| -> Result<Image, String> {
            let rc =
                Raycaster::new(&v, &tf, RaycastParams::default()).map_err(|e| e.to_string())?;
            let scene = Backend::Cpu.prepare(&rc).map_err(|e| e.to_string())?;
            scene
                .dvr(&cam, s, s)
                .map(|t| t.value)
                .map_err(|e| e.to_string())
        })
        .map_err(PyValueError::new_err)?;
    image_array(py, &image)
}

/// A Volumetric Depth Image.
#[pyclass(module = "insitu._insitu")]
pub struct Vdi {
    vdi: insitu_core::Vdi,
}

impl From<insitu_core::Vdi> for Vdi {
    fn from(vdi: insitu_core::Vdi) -> Self {
        Self { vdi }
    }
}

impl Vdi {
    /// The core's VDI.
    pub(crate) fn inner(&self) -> &insitu_core::Vdi {
        &self.vdi
    }
}

#[pymethods]
impl Vdi {
    /// Renders the VDI from its generation camera orbited by `angle` and raised by
    /// `elevation`: an array (size, size, 3).
    #[pyo3(signature = (*, size=512, angle=0.0, elevation=0.0))]
    fn render<'py>(
        &self,
        py: Python<'py>,
        size: u32,
        angle: f32,
        elevation: f32,
    ) -> PyResult<Bound<'py, PyArray3<f32>>> {
        let cam = orbit(&self.vdi.meta().camera, angle, elevation)?;
        let s = self::size(size)?;
        let image = py.detach(|| render::render(&self.vdi, &cam, s, s, DEFAULT_TERMINATION));
        image_array(py, &image)
    }

    /// Writes the VDI file (at the precision it was generated for, compressed with `codec`:
    /// "zstd", "bzip2" or "none"); its σ.
    #[pyo3(signature = (path, codec="zstd"))]
    fn save(&self, path: PathBuf, codec: &str) -> PyResult<u64> {
        let codec: Codec = codec.parse().map_err(bad)?;
        let bytes = codec::encode(&self.vdi, codec).map_err(bad)?;
        write_atomic(&path, &bytes, Durability::Crash)
            .map_err(|e| PyValueError::new_err(format!("{}: {e}", path.display())))?;
        Ok(bytes.len() as u64)
    }

    /// Reads a VDI file.
    #[staticmethod]
    fn load(path: PathBuf) -> PyResult<Self> {
        let bytes = std::fs::read(&path)
            .map_err(|e| PyValueError::new_err(format!("{}: {e}", path.display())))?;
        let vdi = codec::decode(&bytes, &DecodeLimits::default())
            .map_err(|e| PyValueError::new_err(format!("{}: {e}", path.display())))?;
        Ok(Self { vdi })
    }

    /// r: rays per side.
    #[getter]
    fn resolution(&self) -> u32 {
        self.vdi.resolution()
    }

    /// γ: the interrupt threshold it was made with.
    #[getter]
    fn gamma(&self) -> f32 {
        self.vdi.meta().params.gamma
    }

    /// The number of supersegments.
    #[getter]
    fn supersegments(&self) -> usize {
        self.vdi.supersegments().len()
    }

    fn __repr__(&self) -> String {
        format!(
            "insitu.Vdi(r={}, gamma={}, supersegments={})",
            self.vdi.resolution(),
            self.vdi.meta().params.gamma,
            self.vdi.supersegments().len()
        )
    }
}

/// Generates the VDI of `volume` at `P_M` = (r, γ, precision) from the default camera;
/// `precision` ("8", or 4–16 bits, or "f32") is what its file is written at.
#[pyfunction]
#[pyo3(signature = (volume, tf=None, *, r=256, gamma=0.013, precision="8",
                    spacing=(1.0, 1.0, 1.0), origin=(0.0, 0.0, 0.0)))]
#[allow(clippy::too_many_arguments)]
pub fn generate_vdi(
    py: Python<'_>,
    volume: &Bound<'_, PyAny>,
    tf: Option<&str>,
    r: u32,
    gamma: f32,
    precision: &str,
    spacing: (f32, f32, f32),
    origin: (f32, f32, f32),
) -> PyResult<Vdi> {
    let v = self::volume(volume, spacing, origin)?;
    let NamedTf { tf, name } = transfer_function(tf, &v)?;
    let params = VdiParams {
        resolution: r,
        gamma,
        precision: precision.parse().map_err(bad)?,
    };
    params.validate().map_err(bad)?;
    let cam = Camera::default_for_box(&v.world_box());
    let vdi = py
        .detach(|| -> Result<insitu_core::Vdi, String> {
            let rc =
                Raycaster::new(&v, &tf, RaycastParams::default()).map_err(|e| e.to_string())?;
            generate::generate(&rc, &cam, params, tf.identity_hash(), &name)
                .map_err(|e| e.to_string())
        })
        .map_err(PyValueError::new_err)?;
    Ok(Vdi { vdi })
}

/// σ, τ and q of `P_M` = (r, γ, precision) on `volume`: generated, written at `precision`
/// ("8", 4–16 bits, or "f32") and compressed with `codec`, decoded, rendered at the test
/// views (orbit angles, degrees) and compared with direct rendering at `size`.
#[pyfunction]
#[pyo3(signature = (volume, tf=None, *, r=256, gamma=0.013, codec="zstd", size=256,
                    views=None, spacing=(1.0, 1.0, 1.0), origin=(0.0, 0.0, 0.0), precision="8"))]
#[allow(clippy::too_many_arguments)]
pub fn evaluate<'py>(
    py: Python<'py>,
    volume: &Bound<'py, PyAny>,
    tf: Option<&str>,
    r: u32,
    gamma: f32,
    codec: &str,
    size: u32,
    views: Option<Vec<f32>>,
    spacing: (f32, f32, f32),
    origin: (f32, f32, f32),
    precision: &str,
) -> PyResult<Bound<'py, PyDict>> {
    let v = self::volume(volume, spacing, origin)?;
    let named = transfer_function(tf, &v)?;
    let codec: Codec = codec.parse().map_err(bad)?;
    let params = VdiParams {
        resolution: r,
        gamma,
        precision: precision.parse().map_err(bad)?,
    };
    params.validate().map_err(bad)?;
    let s = self::size(size)?;
    let angles = views.unwrap_or_else(|| DEFAULT_VIEW_ANGLES.to_vec());
    if angles.is_empty() || angles.iter().any(|a| !a.is_finite()) {
        return Err(PyValueError::new_err(
            "views must be finite angles, at least one",
        ));
    }
    let cam = Camera::default_for_box(&v.world_box());
    let eval = py
        .detach(|| -> Result<insitu_core::evaluate::Evaluation, String> {
            let rc = Raycaster::new(&v, &named.tf, RaycastParams::default())
                .map_err(|e| e.to_string())?;
            let scene = Backend::Cpu.prepare(&rc).map_err(|e| e.to_string())?;
            let mut references = Vec::with_capacity(angles.len());
            for &a in &angles {
                references.push(
                    scene
                        .dvr(&cam.orbit_y(a), s, s)
                        .map_err(|e| e.to_string())?
                        .value,
                );
            }
            evaluate_pm(
                &scene,
                &cam,
                params,
                codec,
                &angles,
                &references,
                named.identity(),
                &mut None,
            )
            .map(|(e, _)| e)
            .map_err(|e| e.to_string())
        })
        .map_err(PyValueError::new_err)?;
    let d = PyDict::new(py);
    d.set_item("r", r)?;
    d.set_item("gamma", gamma)?;
    d.set_item("codec", codec.name())?;
    d.set_item("precision", params.precision.name())?;
    d.set_item("sigma_bytes", eval.sizing.sigma_bytes)?;
    d.set_item("supersegments", eval.sizing.supersegments)?;
    d.set_item("tau_s", eval.sizing.tau_secs)?;
    d.set_item("tau_compress_s", eval.sizing.tau_compress_secs)?;
    d.set_item("tau_render_s", eval.tau_render_secs)?;
    d.set_item("q_db", eval.q_db)?;
    let views: Vec<(f32, f64)> = eval.views.iter().map(|v| (v.angle_deg, v.q_db)).collect();
    d.set_item("views", views)?;
    Ok(d)
}
