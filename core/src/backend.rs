//! Backend selection: the CPU path (rayon) or the GPU path (wgpu compute shaders) behind the
//! same three functions (docs/conventions.md: both implement the same functions and are tested against
//! each other): reference DVR, VDI generation `R` and VDI rendering `I`.
//!
//! [`BackendChoice`] is what a user asks for (`cpu`, `gpu`, `auto`); [`Backend::select`]
//! opens it and logs what it chose. `auto` takes a hardware GPU when one is found and the CPU
//! otherwise: a software adapter (Mesa's lavapipe) is slower than the CPU path, so `auto`
//! passes it over, while `gpu` accepts it (that is how CI tests the shaders). Results carry
//! their time and its source: GPU timestamps (kernel time, the paper's τ, Sec. 5.3) or wall
//! clock.

use crate::camera::Camera;
use crate::image::Image;
use crate::raycast::Raycaster;
use crate::vdi::{generate, render, Vdi, VdiParamError, VdiParams};
use std::fmt;
use std::str::FromStr;
use std::time::Instant;

/// Keeps Mesa's Vulkan device-selection layer out of a process that has no display session.
///
/// The layer (an implicit layer Mesa installs beside its drivers) orders GPUs by the display
/// the user sits at, and to find it connects to Wayland: where `XDG_RUNTIME_DIR` is unset, the
/// normal case on a compute node, under a batch scheduler or over ssh, that prints
/// `error: XDG_RUNTIME_DIR is invalid or not set in the environment.` at every adapter
/// enumeration. We pick the adapter ourselves ([`Backend::select`]) and never present to a
/// display, so the layer has nothing to do here; this sets its documented off switch,
/// `NODEVICE_SELECT=1`, unless the user set it. With a display session the layer is left alone.
///
/// Call it first thing in `main`, before any thread starts: it changes the process
/// environment, which other threads may be reading.
pub fn quiet_vulkan_layers() {
    let session = std::env::var_os("XDG_RUNTIME_DIR").is_some_and(|v| !v.is_empty());
    if !session && std::env::var_os("NODEVICE_SELECT").is_none() {
        std::env::set_var("NODEVICE_SELECT", "1");
    }
}

/// What the user asked for.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum BackendChoice {
    /// rayon on the CPU.
    Cpu,
    /// wgpu; fails when there is no adapter.
    Gpu,
    /// A hardware GPU when one is found, else the CPU.
    #[default]
    Auto,
}

impl BackendChoice {
    /// The accepted names.
    pub const NAMES: [&'static str; 3] = ["cpu", "gpu", "auto"];
}

impl fmt::Display for BackendChoice {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Self::Cpu => "cpu",
            Self::Gpu => "gpu",
            Self::Auto => "auto",
        })
    }
}

impl FromStr for BackendChoice {
    type Err = BackendError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.to_ascii_lowercase().as_str() {
            "cpu" => Ok(Self::Cpu),
            "gpu" => Ok(Self::Gpu),
            "auto" => Ok(Self::Auto),
            _ => Err(BackendError::UnknownChoice(s.to_string())),
        }
    }
}

/// Errors of backend selection and of the backend's functions.
#[derive(Debug, thiserror::Error)]
pub enum BackendError {
    /// A name that is not `cpu`, `gpu` or `auto`.
    #[error("unknown backend {0:?}: expected one of cpu, gpu, auto")]
    UnknownChoice(String),
    /// `gpu` asked for in a build without the `gpu` feature.
    #[error("backend gpu asked for, but this build has no GPU support (feature \"gpu\")")]
    NotBuilt,
    /// Bad generation parameters or camera.
    #[error(transparent)]
    Params(#[from] VdiParamError),
    /// The GPU failed (no adapter, a limit, device loss, ...).
    #[cfg(feature = "gpu")]
    #[error(transparent)]
    Gpu(#[from] crate::gpu::GpuError),
    /// The caller cancelled the render ([`crate::cancel::Cancel`]).
    #[error(transparent)]
    Cancelled(#[from] crate::cancel::Cancelled),
}

/// Where a reported time comes from.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum TimeSource {
    /// Wall clock around the call (CPU path; GPU without timestamps: includes transfers).
    #[default]
    WallClock,
    /// GPU timestamps around the kernels (no transfers).
    GpuTimestamps,
}

impl TimeSource {
    /// The name in files and on the wire (`wall-clock`, `gpu-timestamps`: the serde names).
    pub fn name(self) -> &'static str {
        match self {
            Self::WallClock => "wall-clock",
            Self::GpuTimestamps => "gpu-timestamps",
        }
    }

    /// The source named `name` ([`TimeSource::name`]), `None` for another name.
    pub fn from_name(name: &str) -> Option<Self> {
        [Self::WallClock, Self::GpuTimestamps]
            .into_iter()
            .find(|s| s.name() == name)
    }
}

impl fmt::Display for TimeSource {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Self::WallClock => "wall clock",
            Self::GpuTimestamps => "GPU timestamps",
        })
    }
}

/// A result with its time.
#[derive(Clone, Debug)]
pub struct Timed<T> {
    /// The result.
    pub value: T,
    /// Seconds, from `source`.
    pub seconds: f64,
    /// Where `seconds` comes from.
    pub source: TimeSource,
    /// Wall-clock seconds of the whole call (uploads and read-backs included).
    pub wall_s: f64,
}

/// An opened backend.
#[derive(Clone, Debug)]
pub enum Backend {
    /// rayon on the CPU.
    Cpu,
    /// A wgpu device.
    #[cfg(feature = "gpu")]
    Gpu(std::sync::Arc<crate::gpu::Gpu>),
}

impl Backend {
    /// Opens `choice` and logs (tracing, info) which backend it chose and why.
    ///
    /// # Errors
    /// As [`Backend::select_explained`].
    pub fn select(choice: BackendChoice) -> Result<Self, BackendError> {
        let (backend, why) = Self::select_explained(choice)?;
        tracing::info!("{why}");
        Ok(backend)
    }

    /// Opens `choice`; also returns one line saying which backend was chosen and why (for a
    /// command line to print).
    ///
    /// # Errors
    /// [`BackendError::NotBuilt`] for `gpu` without the feature; `BackendError::Gpu` (feature
    /// `gpu`) for `gpu` when no adapter is found or the device fails to open. `auto` never
    /// fails: it falls back to the CPU and the line says why.
    pub fn select_explained(choice: BackendChoice) -> Result<(Self, String), BackendError> {
        match choice {
            BackendChoice::Cpu => Ok((Self::Cpu, format!("backend: {}", Self::Cpu.describe()))),
            #[cfg(not(feature = "gpu"))]
            BackendChoice::Gpu => Err(BackendError::NotBuilt),
            #[cfg(not(feature = "gpu"))]
            BackendChoice::Auto => Ok((
                Self::Cpu,
                format!(
                    "backend auto: {} (this build has no GPU support)",
                    Self::Cpu.describe()
                ),
            )),
            #[cfg(feature = "gpu")]
            BackendChoice::Gpu => {
                let gpu = Self::Gpu(std::sync::Arc::new(crate::gpu::Gpu::new(true)?));
                let why = format!("backend: {}", gpu.describe());
                Ok((gpu, why))
            }
            #[cfg(feature = "gpu")]
            BackendChoice::Auto => match crate::gpu::Gpu::new(false) {
                Ok(gpu) => {
                    let gpu = Self::Gpu(std::sync::Arc::new(gpu));
                    let why = format!("backend auto: {}", gpu.describe());
                    Ok((gpu, why))
                }
                Err(e) => Ok((
                    Self::Cpu,
                    format!("backend auto: {} ({e})", Self::Cpu.describe()),
                )),
            },
        }
    }

    /// A one-line description: `cpu (rayon, N threads)` or `gpu: <adapter>`.
    pub fn describe(&self) -> String {
        match self {
            Self::Cpu => format!("cpu (rayon, {} threads)", rayon::current_num_threads()),
            #[cfg(feature = "gpu")]
            Self::Gpu(g) => format!("gpu: {}", g.describe()),
        }
    }

    /// Prepares `raycaster`'s scene (on the GPU: uploads volume, transfer function and
    /// macro-cell grid once for many cameras).
    ///
    /// # Errors
    /// `BackendError::Gpu` (feature `gpu`) when the scene exceeds a device limit or the device
    /// fails.
    pub fn prepare<'a>(
        &'a self,
        raycaster: &'a Raycaster<'a>,
    ) -> Result<PreparedVolume<'a>, BackendError> {
        match self {
            Self::Cpu => Ok(PreparedVolume::Cpu(raycaster)),
            #[cfg(feature = "gpu")]
            Self::Gpu(g) => Ok(PreparedVolume::Gpu(Box::new(crate::gpu::GpuVolume::new(
                g, raycaster,
            )?))),
        }
    }

    /// Prepares `vdi` for rendering from many cameras (on the GPU: uploads its lists).
    ///
    /// # Errors
    /// `BackendError::Gpu` (feature `gpu`) when the VDI exceeds the storage-binding limit or
    /// the device fails.
    pub fn prepare_vdi<'a>(&'a self, vdi: &'a Vdi) -> Result<PreparedVdi<'a>, BackendError> {
        match self {
            Self::Cpu => Ok(PreparedVdi::Cpu(render::Walker::new(vdi))),
            #[cfg(feature = "gpu")]
            Self::Gpu(g) => Ok(PreparedVdi::Gpu(crate::gpu::GpuVdi::new(g, vdi)?)),
        }
    }
}

/// A scene prepared on a backend: reference DVR and VDI generation for any camera.
pub enum PreparedVolume<'a> {
    /// The CPU path reads the ray-caster directly.
    Cpu(&'a Raycaster<'a>),
    /// Uploaded to the GPU.
    #[cfg(feature = "gpu")]
    Gpu(Box<crate::gpu::GpuVolume<'a, 'a>>),
}

#[cfg(feature = "gpu")]
fn from_kernel<T>(run: crate::gpu::KernelRun<T>, start: Instant) -> Timed<T> {
    let wall_s = start.elapsed().as_secs_f64();
    match run.kernel_s {
        Some(s) => Timed {
            value: run.value,
            seconds: s,
            source: TimeSource::GpuTimestamps,
            wall_s,
        },
        None => Timed {
            value: run.value,
            seconds: wall_s,
            source: TimeSource::WallClock,
            wall_s,
        },
    }
}

fn wall<T>(value: T, start: Instant) -> Timed<T> {
    let s = start.elapsed().as_secs_f64();
    Timed {
        value,
        seconds: s,
        source: TimeSource::WallClock,
        wall_s: s,
    }
}

impl PreparedVolume<'_> {
    /// The backend, as [`Backend::describe`] says it.
    pub fn describe(&self) -> String {
        match self {
            Self::Cpu(_) => Backend::Cpu.describe(),
            #[cfg(feature = "gpu")]
            Self::Gpu(s) => format!("gpu: {}", s.gpu().describe()),
        }
    }

    /// The ray-caster this scene was made from.
    pub fn raycaster(&self) -> &Raycaster<'_> {
        match self {
            Self::Cpu(rc) => rc,
            #[cfg(feature = "gpu")]
            Self::Gpu(s) => s.raycaster(),
        }
    }

    /// Prepares `vdi` for rendering on the same backend as this scene.
    ///
    /// # Errors
    /// As [`Backend::prepare_vdi`].
    pub fn prepare_vdi<'v>(&'v self, vdi: &'v Vdi) -> Result<PreparedVdi<'v>, BackendError> {
        match self {
            Self::Cpu(_) => Ok(PreparedVdi::Cpu(render::Walker::new(vdi))),
            #[cfg(feature = "gpu")]
            Self::Gpu(s) => Ok(PreparedVdi::Gpu(crate::gpu::GpuVdi::new(s.gpu(), vdi)?)),
        }
    }

    /// Reference DVR of `camera`'s view at `width × height` ([`crate::dvr::render`]).
    ///
    /// # Errors
    /// `BackendError::Gpu` (feature `gpu`) on the GPU path (limits, device failures); never on
    /// the CPU.
    pub fn dvr(
        &self,
        camera: &Camera,
        width: u32,
        height: u32,
    ) -> Result<Timed<Image>, BackendError> {
        let start = Instant::now();
        match self {
            Self::Cpu(rc) => Ok(wall(crate::dvr::render(rc, camera, width, height), start)),
            #[cfg(feature = "gpu")]
            Self::Gpu(s) => Ok(from_kernel(s.dvr(camera, width, height)?, start)),
        }
    }

    /// VDI generation `R` ([`crate::vdi::generate::generate`]).
    ///
    /// # Errors
    /// [`BackendError::Params`] for bad `params` or camera; `BackendError::Gpu` (feature `gpu`)
    /// on the GPU path.
    pub fn generate(
        &self,
        camera: &Camera,
        params: VdiParams,
        tf_hash: u64,
        tf_name: &str,
    ) -> Result<Timed<Vdi>, BackendError> {
        self.generate_reusing(camera, params, tf_hash, tf_name, None)
    }

    /// [`Self::generate`], reusing the allocations of `spare` (a VDI that is no longer needed)
    /// on the CPU path ([`crate::vdi::generate::generate_into`]): a generator making a VDI
    /// per time step hands back the previous one. The GPU path drops it.
    ///
    /// # Errors
    /// As [`Self::generate`].
    pub fn generate_reusing(
        &self,
        camera: &Camera,
        params: VdiParams,
        tf_hash: u64,
        tf_name: &str,
        spare: Option<Vdi>,
    ) -> Result<Timed<Vdi>, BackendError> {
        match self.generate_until(camera, params, tf_hash, tf_name, spare, &|_| false)? {
            Attempt::Done(vdi) => Ok(vdi),
            // Unreachable with a rule that never stops; answered as the empty VDI it left.
            Attempt::Stopped { spare, progress } => Ok(Timed {
                value: spare,
                seconds: progress.seconds,
                source: TimeSource::WallClock,
                wall_s: progress.seconds,
            }),
        }
    }

    /// [`Self::generate_reusing`] under a stop rule asked between bands of rows
    /// ([`generate::generate_into_until`]): how a generator keeps a deadline. The GPU path
    /// runs its kernel whole and never stops (its τ is checked after).
    ///
    /// # Errors
    /// As [`Self::generate`].
    pub fn generate_until(
        &self,
        camera: &Camera,
        params: VdiParams,
        tf_hash: u64,
        tf_name: &str,
        spare: Option<Vdi>,
        stop: &dyn Fn(generate::Progress) -> bool,
    ) -> Result<Attempt, BackendError> {
        let start = Instant::now();
        match self {
            Self::Cpu(rc) => {
                let mut vdi = match spare {
                    Some(vdi) => vdi,
                    None => generate::blank(rc, camera, params, tf_hash, tf_name),
                };
                match generate::generate_into_until(
                    rc, camera, params, tf_hash, tf_name, &mut vdi, stop,
                )? {
                    generate::Outcome::Complete => Ok(Attempt::Done(wall(vdi, start))),
                    generate::Outcome::Stopped(progress) => Ok(Attempt::Stopped {
                        spare: vdi,
                        progress,
                    }),
                }
            }
            #[cfg(feature = "gpu")]
            Self::Gpu(s) => Ok(Attempt::Done(from_kernel(
                s.generate(camera, params, tf_hash, tf_name)?,
                start,
            ))),
        }
    }
}

/// How a generation under a stop rule ended ([`PreparedVolume::generate_until`]).
#[derive(Debug)]
pub enum Attempt {
    /// The whole VDI, timed.
    Done(Timed<Vdi>),
    /// Stopped by the rule: how far it got, and the VDI's memory for the next try.
    Stopped {
        /// An empty VDI whose allocations the next generation reuses.
        spare: Vdi,
        /// The share of the work done and the seconds it took.
        progress: generate::Progress,
    },
}

/// A VDI prepared on a backend for rendering from any camera.
pub enum PreparedVdi<'a> {
    /// The CPU path: the lists with the walk's per-VDI tables.
    Cpu(render::Walker<'a>),
    /// Uploaded to the GPU.
    #[cfg(feature = "gpu")]
    Gpu(crate::gpu::GpuVdi<'a>),
}

impl PreparedVdi<'_> {
    /// VDI rendering `I` from `camera` at `width × height` ([`crate::vdi::render::render`]).
    ///
    /// # Errors
    /// `BackendError::Gpu` (feature `gpu`) on the GPU path; never on the CPU.
    pub fn render(
        &self,
        camera: &Camera,
        width: u32,
        height: u32,
        termination: f32,
    ) -> Result<Timed<Image>, BackendError> {
        self.render_until(camera, width, height, termination, None)
    }

    /// [`PreparedVdi::render`] that stops when `cancel` is set: on the CPU between tiles of 16²
    /// pixels, on the GPU (one dispatch, tens of milliseconds) before and after it.
    ///
    /// # Errors
    /// As [`PreparedVdi::render`]; [`BackendError::Cancelled`] when cancelled.
    pub fn render_until(
        &self,
        camera: &Camera,
        width: u32,
        height: u32,
        termination: f32,
        cancel: Option<&crate::cancel::Cancel>,
    ) -> Result<Timed<Image>, BackendError> {
        let start = Instant::now();
        match self {
            Self::Cpu(walker) => Ok(wall(
                walker.render_until(camera, width, height, termination, cancel)?,
                start,
            )),
            #[cfg(feature = "gpu")]
            Self::Gpu(v) => {
                let stopped = || cancel.is_some_and(crate::cancel::Cancel::is_cancelled);
                if stopped() {
                    return Err(crate::cancel::Cancelled.into());
                }
                let out = v.render(camera, width, height, termination)?;
                if stopped() {
                    return Err(crate::cancel::Cancelled.into());
                }
                Ok(from_kernel(out, start))
            }
        }
    }
}
