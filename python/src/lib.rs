//! The extension module `insitu._insitu`: a Python simulation's link to a generator-node,
//! wrapping the Rust client ([`insitu_client::SimClient`]: its retries of nothing, its checks
//! and its messages). A C-contiguous NumPy field is sent without a copy (the array is kept
//! alive, not copied, while its bytes are sent) with the GIL released; see `insitu/__init__.pyi`
//! for the Python-side documentation. The core's maths on NumPy arrays (render, generate,
//! evaluate, VDI files) are in [`offline`], a recording read from Python in [`recording`].

use insitu_client::{
    BearerToken, Bytes, ClientError, Code, GeneratorStatus, PushReply, ScalarType, SimClient, Step,
};
use numpy::{PyArrayDescrMethods, PyUntypedArray, PyUntypedArrayMethods};
use pyo3::create_exception;
use pyo3::exceptions::{PyException, PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;
use std::time::Duration;

mod offline;
mod recording;

create_exception!(
    insitu,
    Error,
    PyException,
    "A call to the generator-node failed (the message says why)."
);
create_exception!(
    insitu,
    UnreachableError,
    Error,
    "Nothing answers at the address, or the connection broke."
);
create_exception!(
    insitu,
    RefusedError,
    Error,
    "The generator-node refused the call (a bad step, a wrong token, shutting down)."
);
create_exception!(
    insitu,
    TimeoutError,
    Error,
    "A flush or close did not finish within its timeout."
);

/// The Rust client's error as the Python exception that says the same.
fn to_py(e: ClientError) -> PyErr {
    let text = e.to_string();
    match e {
        ClientError::InvalidStep(_) | ClientError::Address { .. } => PyValueError::new_err(text),
        ClientError::Unreachable { .. } => UnreachableError::new_err(text),
        ClientError::Refused {
            code: Code::Unavailable,
            ..
        } => UnreachableError::new_err(text),
        ClientError::Refused {
            code: Code::DeadlineExceeded,
            ..
        } => TimeoutError::new_err(text),
        ClientError::Refused { .. } => RefusedError::new_err(text),
        ClientError::Security(_) | ClientError::Tls(_) => PyValueError::new_err(text),
    }
}

/// A NumPy array's bytes, kept alive by a reference to the array rather than copied.
struct ArrayBytes {
    _array: Py<PyUntypedArray>,
    ptr: *const u8,
    len: usize,
}

// SAFETY: the pointer is into the buffer of the array held by `_array`, which NumPy keeps
// alive (and in place: a referenced array cannot be resized) for as long as the reference
// lives; the bytes are only read.
unsafe impl Send for ArrayBytes {}

impl AsRef<[u8]> for ArrayBytes {
    fn as_ref(&self) -> &[u8] {
        // SAFETY: see `Send`: `len` bytes from `ptr` belong to the live array.
        unsafe { std::slice::from_raw_parts(self.ptr, self.len) }
    }
}

/// The scalar type of `array` if the service takes it (native byte order), else a `TypeError`
/// naming the dtype.
fn scalar_type(array: &Bound<'_, PyUntypedArray>) -> PyResult<ScalarType> {
    let py = array.py();
    let dtype = array.dtype();
    let candidates = [
        (numpy::dtype::<f32>(py), ScalarType::F32),
        (numpy::dtype::<f64>(py), ScalarType::F64),
        (numpy::dtype::<u8>(py), ScalarType::U8),
        (numpy::dtype::<u16>(py), ScalarType::U16),
        (numpy::dtype::<i16>(py), ScalarType::I16),
    ];
    candidates
        .into_iter()
        .find(|(d, _)| dtype.is_equiv_to(d))
        .map(|(_, t)| t)
        .ok_or_else(|| {
            PyTypeError::new_err(format!(
                "field dtype {} is not one the service takes: float32, float64, uint8, uint16 or \
                 int16 in native byte order (convert with field.astype(numpy.float32))",
                dtype.str().map_or_else(|_| "?".into(), |s| s.to_string())
            ))
        })
}

/// A triple of non-negative integers from Python, or a `ValueError` naming it.
fn dims3(name: &str, v: (i64, i64, i64)) -> PyResult<[u32; 3]> {
    let t = [v.0, v.1, v.2];
    if t.iter().any(|&x| !(0..=i64::from(u32::MAX)).contains(&x)) {
        return Err(PyValueError::new_err(format!(
            "{name} {t:?} must be three integers ≥ 0"
        )));
    }
    Ok(t.map(|x| x as u32))
}

fn floats3(name: &str, v: (f64, f64, f64)) -> PyResult<[f32; 3]> {
    let t = [v.0, v.1, v.2];
    if !t.iter().all(|x| x.is_finite()) {
        return Err(PyValueError::new_err(format!(
            "{name} {t:?} must be finite"
        )));
    }
    Ok(t.map(|x| x as f32))
}

fn status_dict<'py>(py: Python<'py>, s: &GeneratorStatus) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("queue_depth", s.queue_depth)?;
    d.set_item("steps_received", s.steps_received)?;
    d.set_item("steps_generated", s.steps_generated)?;
    d.set_item("steps_shipped", s.steps_shipped)?;
    d.set_item("dropped_queue", s.dropped_queue)?;
    d.set_item("dropped_outbox", s.dropped_outbox)?;
    d.set_item("failed", s.failed)?;
    Ok(d)
}

fn reply_dict<'py>(py: Python<'py>, r: &PushReply) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("queue_depth", r.queue_depth)?;
    d.set_item("dropped_by_push", r.dropped_by_push)?;
    d.set_item("steps_received", r.steps_received)?;
    d.set_item("epoch", r.epoch)?;
    Ok(d)
}

fn timeout(secs: Option<f64>) -> PyResult<Duration> {
    match secs {
        None => Ok(Duration::from_secs(600)),
        Some(s) if s.is_finite() && s > 0.0 => Ok(Duration::from_secs_f64(s.min(86_400.0))),
        Some(s) => Err(PyValueError::new_err(format!(
            "timeout {s} must be a positive number of seconds"
        ))),
    }
}

/// A connection to one generator-node.
#[pyclass(module = "insitu._insitu")]
struct Client {
    rt: tokio::runtime::Runtime,
    client: Option<SimClient>,
    address: String,
}

impl Client {
    /// The runtime and the open client, or a `ValueError` once closed.
    fn live(&mut self) -> PyResult<(&tokio::runtime::Runtime, &mut SimClient)> {
        let address = &self.address;
        let client = self
            .client
            .as_mut()
            .ok_or_else(|| PyValueError::new_err(format!("the client of {address} is closed")))?;
        Ok((&self.rt, client))
    }
}

#[pymethods]
impl Client {
    #[new]
    #[pyo3(signature = (address, token=None))]
    fn new(py: Python<'_>, address: String, token: Option<String>) -> PyResult<Self> {
        let token = token
            .or_else(|| std::env::var("INSITU_TOKEN").ok())
            .map(|t| BearerToken::new(&t, "python client"))
            .transpose()
            .map_err(|e| PyValueError::new_err(e.to_string()))?;
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .map_err(|e| Error::new_err(format!("the client's runtime could not start: {e}")))?;
        let client = py
            .detach(|| rt.block_on(SimClient::connect(&address, token.as_ref())))
            .map_err(to_py)?;
        Ok(Self {
            rt,
            client: Some(client),
            address,
        })
    }

    /// Pushes one rank's brick; returns once the node has queued it.
    #[pyo3(signature = (step, field, *, offset=(0, 0, 0), global_dims=None, rank=0,
                        world_size=1, spacing=(1.0, 1.0, 1.0), origin=(0.0, 0.0, 0.0),
                        sim_time=0.0))]
    #[allow(clippy::too_many_arguments)]
    fn push<'py>(
        &mut self,
        py: Python<'py>,
        step: u64,
        field: &Bound<'py, PyAny>,
        offset: (i64, i64, i64),
        global_dims: Option<(i64, i64, i64)>,
        rank: u32,
        world_size: u32,
        spacing: (f64, f64, f64),
        origin: (f64, f64, f64),
        sim_time: f64,
    ) -> PyResult<Bound<'py, PyDict>> {
        let array = field.cast::<PyUntypedArray>().map_err(|_| {
            PyTypeError::new_err(format!(
                "field must be a numpy.ndarray, not {}",
                field
                    .get_type()
                    .name()
                    .map_or_else(|_| "?".into(), |n| n.to_string())
            ))
        })?;
        let dtype = scalar_type(array)?;
        if array.ndim() != 3 {
            return Err(PyValueError::new_err(format!(
                "field has {} dimensions: a brick is indexed [z, y, x], shape (nz, ny, nx)",
                array.ndim()
            )));
        }
        if !array.is_c_contiguous() {
            return Err(PyValueError::new_err(
                "field is not C-contiguous (x fastest): pass numpy.ascontiguousarray(field)",
            ));
        }
        let shape = array.shape();
        let brick_dims = dims3(
            "field.shape",
            (shape[2] as i64, shape[1] as i64, shape[0] as i64),
        )?;
        let brick_offset = dims3("offset", offset)?;
        let global_dims = match global_dims {
            Some(g) => dims3("global_dims", g)?,
            None => std::array::from_fn(|a| brick_offset[a] + brick_dims[a]),
        };
        let len = array.len() * array.dtype().itemsize();
        let data = if len == 0 {
            Bytes::new()
        } else {
            // SAFETY: a C-contiguous array's buffer holds `len` bytes from its data pointer.
            let ptr = unsafe { (*array.as_array_ptr()).fields.data }
                .cast::<u8>()
                .cast_const();
            Bytes::from_owner(ArrayBytes {
                _array: array.clone().unbind(),
                ptr,
                len,
            })
        };
        let step = Step {
            step,
            sim_time,
            dtype,
            global_dims,
            brick_offset,
            brick_dims,
            rank,
            world_size,
            spacing: floats3("spacing", spacing)?,
            origin: floats3("origin", origin)?,
            data,
            fields: Vec::new(),
        };
        let (rt, client) = self.live()?;
        let reply = py
            .detach(|| rt.block_on(client.push_step(step)))
            .map_err(to_py)?;
        reply_dict(py, &reply)
    }

    /// Waits until every step the node has received is generated and shipped; the node's
    /// counters.
    #[pyo3(signature = (timeout=None))]
    fn flush<'py>(
        &mut self,
        py: Python<'py>,
        timeout: Option<f64>,
    ) -> PyResult<Bound<'py, PyDict>> {
        let t = self::timeout(timeout)?;
        let (rt, client) = self.live()?;
        let s = py.detach(|| rt.block_on(client.flush(t))).map_err(to_py)?;
        status_dict(py, &s)
    }

    /// The node's counters.
    fn status<'py>(&mut self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let (rt, client) = self.live()?;
        let s = py.detach(|| rt.block_on(client.status())).map_err(to_py)?;
        status_dict(py, &s)
    }

    /// Flushes, then closes; later calls raise ValueError. Closing twice does nothing.
    #[pyo3(signature = (timeout=None))]
    fn close<'py>(
        &mut self,
        py: Python<'py>,
        timeout: Option<f64>,
    ) -> PyResult<Option<Bound<'py, PyDict>>> {
        let t = self::timeout(timeout)?;
        let Some(client) = self.client.take() else {
            return Ok(None);
        };
        let rt = &self.rt;
        let s = py.detach(|| rt.block_on(client.close(t))).map_err(to_py)?;
        status_dict(py, &s).map(Some)
    }

    /// Whether `close` was called.
    #[getter]
    fn closed(&self) -> bool {
        self.client.is_none()
    }

    /// The node's address as given.
    #[getter]
    fn address(&self) -> &str {
        &self.address
    }

    fn __enter__(slf: Py<Self>) -> Py<Self> {
        slf
    }

    /// Closes (flushing). When the block is left by an exception, that exception is the one
    /// raised: a failed close then (e.g. a flush reporting the same fault again) does not
    /// stack a second traceback on it.
    #[pyo3(signature = (*exc))]
    fn __exit__(
        &mut self,
        py: Python<'_>,
        exc: &Bound<'_, pyo3::types::PyTuple>,
    ) -> PyResult<bool> {
        let raising = exc.get_item(0).is_ok_and(|t| !t.is_none());
        match self.close(py, None) {
            Err(e) if !raising => Err(e),
            _ => Ok(false),
        }
    }

    fn __repr__(&self) -> String {
        format!(
            "insitu.Client({:?}{})",
            self.address,
            if self.client.is_none() {
                ", closed"
            } else {
                ""
            }
        )
    }
}

/// The extension module.
#[pymodule]
fn _insitu(m: &Bound<'_, PyModule>) -> PyResult<()> {
    let py = m.py();
    m.add_class::<Client>()?;
    m.add_class::<offline::Vdi>()?;
    m.add_class::<recording::Recording>()?;
    m.add_function(wrap_pyfunction!(offline::render_volume, m)?)?;
    m.add_function(wrap_pyfunction!(offline::generate_vdi, m)?)?;
    m.add_function(wrap_pyfunction!(offline::evaluate, m)?)?;
    m.add("Error", py.get_type::<Error>())?;
    m.add("UnreachableError", py.get_type::<UnreachableError>())?;
    m.add("RefusedError", py.get_type::<RefusedError>())?;
    m.add("TimeoutError", py.get_type::<TimeoutError>())?;
    Ok(())
}
