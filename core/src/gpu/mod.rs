//! The GPU backend: reference DVR, VDI generation and VDI rendering as WGSL compute shaders
//! through wgpu (docs/conventions.md: "the GPU path and the CPU path implement the same functions and
//! are tested against each other"). The paper generates with a CUDA ray-caster and renders
//! with OpenGL (Sec. 6); the kernels here mirror the CPU code operation for operation so the
//! two agree up to float rounding, and their output is the same [`crate::Vdi`] and
//! [`crate::Image`] types.
//!
//! - [`Gpu`]: adapter, device, limits, kernels; [`Gpu::new`] fails with
//!   [`GpuError::NoAdapter`] when there is none, the caller's signal to use the CPU.
//! - [`GpuVolume`]: a volume (3D texture), transfer function (1D textures) and macro-cell grid
//!   uploaded once, then [`GpuVolume::dvr`] and [`GpuVolume::generate`] per camera.
//! - [`GpuVdi`]: a VDI's compact lists in storage buffers, [`GpuVdi::render`] per camera.
//!
//! Kernel times come from GPU timestamps when the adapter has them (the paper's τ is kernel
//! time, Sec. 5.3). Limits are handled, not hit: images and VDI generation run in bands of
//! rows that fit one storage binding; a volume side over the 3D-texture limit or a VDI over
//! the binding limit is a [`GpuError::Limit`] naming the limit.

mod context;
mod kernels;
mod scene;
mod vdi;

pub use context::{Gpu, SUBMISSION_TIMEOUT};
pub use scene::{GpuVolume, KernelRun, INITIAL_BUDGET};
pub use vdi::GpuVdi;

/// Errors of the GPU backend.
#[derive(Debug, thiserror::Error)]
pub enum GpuError {
    /// No adapter: no driver, or `WGPU_BACKEND` / `WGPU_ADAPTER_NAME` naming none present.
    #[error("no GPU adapter found: {0}")]
    NoAdapter(String),
    /// The adapter refused to open a device.
    #[error("could not open the GPU device: {0}")]
    Device(String),
    /// An input exceeds a device limit and cannot be split.
    #[error("{what} needs {needed}, over the device limit {name} = {limit}")]
    Limit {
        /// What was too large.
        what: String,
        /// Its size (bytes, texels or count, as the limit counts).
        needed: u64,
        /// The limit.
        limit: u64,
        /// The wgpu limit's name.
        name: &'static str,
    },
    /// Bad generation parameters or camera.
    #[error(transparent)]
    Params(#[from] crate::vdi::VdiParamError),
    /// wgpu reported a validation error (a bug or an unsupported input).
    #[error("GPU validation error: {0}")]
    Validation(String),
    /// The device ran out of memory.
    #[error("GPU out of memory: {0}")]
    OutOfMemory(String),
    /// The device was lost or failed asynchronously.
    #[error("GPU device failed: {0}")]
    Lost(String),
    /// A submission did not complete within [`SUBMISSION_TIMEOUT`].
    #[error("GPU timed out: {0}")]
    Timeout(String),
}
