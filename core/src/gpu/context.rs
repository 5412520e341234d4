//! The wgpu device: adapter selection, limits, error capture, submission with GPU timestamps,
//! buffer upload and read-back, and the buffers kept between calls.
//!
//! What a call costs besides its kernels is the host's side of the transfers, and on a
//! discrete GPU that dominates unless buffers are reused, bytes are copied once and the
//! copies overlap the kernels:
//! - a submission carries its passes, their timestamps and the copy of its output into a
//!   read-back buffer, so it costs one wait and one mapping ([`Gpu::submit`]);
//! - results read back in parts are pipelined: the host copies one part into place while
//!   the device runs the next ([`Gpu::pipelined`]), with large copies spread over threads;
//! - scratch buffers (counts, offsets, image bands, supersegments) and read-back buffers are
//!   kept for the next call instead of being allocated (and zeroed) again.

use super::GpuError;
use std::borrow::Cow;
use std::num::NonZeroU64;
use std::sync::{Arc, Mutex};
use std::time::Duration;
use wgpu::util::DeviceExt;

/// Smallest buffer made: one element of every array the kernels bind (a 24-byte supersegment).
const MIN_BUFFER: usize = 32;

/// Longest wait for one submission before it is reported as [`GpuError::Timeout`] (a stuck
/// or lost device must not hang the caller).
pub const SUBMISSION_TIMEOUT: Duration = Duration::from_secs(300);

/// Most bytes of read-back buffers kept for the next reads (the largest that fit are kept).
const STAGING_KEPT: u64 = 256 << 20;

/// Most bytes of scratch buffers kept for the next kernels: the largest are kept while they
/// fit under it, the others freed.
const SCRATCH_KEPT: u64 = 2 << 30;

/// An opened GPU: adapter, device, queue, the limits granted and the compiled kernels.
pub struct Gpu {
    pub(super) device: wgpu::Device,
    pub(super) queue: wgpu::Queue,
    pub(super) limits: wgpu::Limits,
    pub(super) kernels: super::kernels::Kernels,
    info: wgpu::AdapterInfo,
    timestamps: bool,
    /// First asynchronous failure (device lost, uncaptured error), reported by the next call.
    failure: Arc<Mutex<Option<String>>>,
    /// Read-back buffers (MAP_READ | COPY_DST) not in use, kept for the next reads.
    staging: Mutex<Vec<wgpu::Buffer>>,
    /// Scratch storage buffers (STORAGE | COPY_SRC) not in use, kept for the next kernels.
    scratch: Mutex<Vec<wgpu::Buffer>>,
}

impl std::fmt::Debug for Gpu {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Gpu")
            .field("adapter", &self.describe())
            .finish()
    }
}

impl Gpu {
    /// Opens the default adapter, obeying `WGPU_BACKEND` / `WGPU_ADAPTER_NAME`, with the
    /// adapter's own limits (the defaults cap buffers far below what adapters allow) and GPU
    /// timestamps when the adapter has them. `allow_software` accepts a CPU-emulated adapter
    /// (lavapipe, llvmpipe).
    ///
    /// # Errors
    /// [`GpuError::NoAdapter`] when no adapter is found (no driver, or `WGPU_BACKEND` naming
    /// one that is absent) or only a software one is and `allow_software` is false;
    /// [`GpuError::Device`] when the device cannot be opened.
    pub fn new(allow_software: bool) -> Result<Self, GpuError> {
        let instance =
            wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
        let adapter = pollster::block_on(wgpu::util::initialize_adapter_from_env_or_default(
            &instance, None,
        ))
        .map_err(|e| GpuError::NoAdapter(e.to_string()))?;
        let info = adapter.get_info();
        if info.device_type == wgpu::DeviceType::Cpu && !allow_software {
            return Err(GpuError::NoAdapter(format!(
                "only a software adapter, {} ({:?}), which is slower than the CPU path",
                info.name, info.backend
            )));
        }
        let limits = adapter.limits();
        let timestamps = adapter.features().contains(wgpu::Features::TIMESTAMP_QUERY);
        let required_features = if timestamps {
            wgpu::Features::TIMESTAMP_QUERY
        } else {
            wgpu::Features::empty()
        };
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("insitu"),
            required_features,
            required_limits: limits.clone(),
            ..Default::default()
        }))
        .map_err(|e| GpuError::Device(e.to_string()))?;
        let failure = Arc::new(Mutex::new(None));
        let lost = Arc::clone(&failure);
        device.set_device_lost_callback(move |reason, message| {
            if let Ok(mut f) = lost.lock() {
                f.get_or_insert(format!("device lost ({reason:?}): {message}"));
            }
        });
        let uncaptured = Arc::clone(&failure);
        device.on_uncaptured_error(Arc::new(move |e: wgpu::Error| {
            tracing::error!("wgpu: {e}");
            if let Ok(mut f) = uncaptured.lock() {
                f.get_or_insert(e.to_string());
            }
        }));
        let kernels = super::kernels::Kernels::new(&device)?;
        Ok(Self {
            device,
            queue,
            limits,
            kernels,
            info,
            timestamps,
            failure,
            staging: Mutex::new(Vec::new()),
            scratch: Mutex::new(Vec::new()),
        })
    }

    /// "name (backend, device type)", e.g. `llvmpipe (LLVM 15.0.6, 256 bits) (Vulkan, Cpu)`.
    pub fn describe(&self) -> String {
        format!(
            "{} ({:?}, {:?})",
            self.info.name, self.info.backend, self.info.device_type
        )
    }

    /// Whether kernel times come from GPU timestamps (else wall clock around the submission).
    pub fn has_timestamps(&self) -> bool {
        self.timestamps
    }

    /// Largest storage-buffer binding used, bytes.
    pub fn max_storage_binding(&self) -> u64 {
        self.limits
            .max_storage_buffer_binding_size
            .min(self.limits.max_buffer_size)
    }

    /// Checks that `bytes` of `what` fit one storage binding.
    ///
    /// # Errors
    /// [`GpuError::Limit`] naming `what` and `max_storage_buffer_binding_size`.
    pub(super) fn check_binding(&self, what: &str, bytes: u64) -> Result<(), GpuError> {
        let limit = self.max_storage_binding();
        if bytes > limit {
            return Err(GpuError::Limit {
                what: what.into(),
                needed: bytes,
                limit,
                name: "max_storage_buffer_binding_size",
            });
        }
        Ok(())
    }

    /// Uses at most `bytes` per storage binding (and buffer), below what the device allows:
    /// leaves room for other users of the device, and lets tests exercise the banding that
    /// large images and VDIs need. Values above the device's limits are ignored.
    pub fn cap_storage_binding(&mut self, bytes: u64) {
        let cap = bytes.max(MIN_BUFFER as u64);
        self.limits.max_storage_buffer_binding_size =
            self.limits.max_storage_buffer_binding_size.min(cap);
        self.limits.max_buffer_size = self.limits.max_buffer_size.min(cap);
    }

    /// Fails if an asynchronous error or device loss was recorded.
    pub(super) fn check_failure(&self) -> Result<(), GpuError> {
        match self.failure.lock() {
            Ok(f) => match f.as_ref() {
                Some(m) => Err(GpuError::Lost(m.clone())),
                None => Ok(()),
            },
            Err(_) => Err(GpuError::Lost("error state poisoned".into())),
        }
    }

    /// Runs `f` (resource creation, encoding, submission) with validation and out-of-memory
    /// errors captured and returned instead of reaching the uncaptured handler.
    pub(super) fn scoped<T>(
        &self,
        what: &str,
        f: impl FnOnce() -> Result<T, GpuError>,
    ) -> Result<T, GpuError> {
        self.check_failure()?;
        let validation = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let oom = self.device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        let result = f();
        let oom = pollster::block_on(oom.pop());
        let validation = pollster::block_on(validation.pop());
        if let Some(e) = oom {
            return Err(GpuError::OutOfMemory(format!("{what}: {e}")));
        }
        if let Some(e) = validation {
            return Err(GpuError::Validation(format!("{what}: {e}")));
        }
        self.check_failure()?;
        result
    }

    /// A buffer initialised with `bytes`, zero-padded to at least [`MIN_BUFFER`] bytes so
    /// that empty data (a VDI without supersegments) still binds as an array of structs.
    pub(super) fn buffer_init(
        &self,
        label: &str,
        bytes: &[u8],
        usage: wgpu::BufferUsages,
    ) -> wgpu::Buffer {
        let padded;
        let contents = if bytes.len() < MIN_BUFFER {
            let mut p = [0u8; MIN_BUFFER];
            p[..bytes.len()].copy_from_slice(bytes);
            padded = p;
            &padded[..]
        } else {
            bytes
        };
        self.device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents,
                usage,
            })
    }

    /// A uniform buffer holding `u`.
    pub(super) fn uniform(&self, label: &str, u: &Uniform) -> wgpu::Buffer {
        self.buffer_init(label, u.bytes(), wgpu::BufferUsages::UNIFORM)
    }

    /// A scratch storage buffer (usage STORAGE | COPY_SRC) of at least `size` bytes (and at
    /// least [`MIN_BUFFER`]), taken from those kept from earlier calls when one is large
    /// enough; its contents are undefined. It goes back to be kept when dropped. Bind it with
    /// [`Scratch::binding`], which is exactly `size` bytes long, so that kernels' bounds are
    /// the requested size whatever buffer lies under it.
    pub(super) fn scratch(&self, label: &str, size: u64) -> Scratch<'_> {
        let size = size.max(MIN_BUFFER as u64).next_multiple_of(4);
        let buffer = take_fitting(&self.scratch, size).unwrap_or_else(|| {
            self.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size,
                usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
                mapped_at_creation: false,
            })
        });
        Scratch {
            gpu: self,
            buffer: Some(buffer),
            size,
        }
    }

    /// A bind group of `layout` whose binding `i` is `resources[i]`.
    pub(super) fn bind_group(
        &self,
        label: &str,
        layout: &wgpu::BindGroupLayout,
        resources: &[wgpu::BindingResource<'_>],
    ) -> wgpu::BindGroup {
        let entries: Vec<wgpu::BindGroupEntry> = resources
            .iter()
            .enumerate()
            .map(|(i, r)| wgpu::BindGroupEntry {
                binding: i as u32,
                resource: r.clone(),
            })
            .collect();
        self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some(label),
            layout,
            entries: &entries,
        })
    }

    /// Encodes `passes` (one compute pass each, in order, each timed when the adapter has
    /// timestamps) and a copy of `output`'s first `size` bytes into a read-back buffer, and
    /// submits them as one command buffer without waiting: [`Submitted::finish`] waits and
    /// hands the bytes over. One submission and one mapping per call keeps the host's share of
    /// a kernel to a single round trip.
    ///
    /// # Errors
    /// Validation or out-of-memory errors, or an earlier device loss.
    pub(super) fn submit(
        &self,
        label: &str,
        passes: &[Pass<'_>],
        output: Option<(&wgpu::Buffer, u64)>,
    ) -> Result<Submitted<'_>, GpuError> {
        let size = output.map_or(0, |(_, s)| s);
        let copied = size.next_multiple_of(wgpu::COPY_BUFFER_ALIGNMENT);
        // Timestamps (u64 pairs) follow the output in the read-back buffer.
        let stamps_at = copied.next_multiple_of(8);
        let stamps = if self.timestamps {
            2 * passes.len() as u32
        } else {
            0
        };
        let total = (stamps_at + 8 * u64::from(stamps)).max(MIN_BUFFER as u64);
        let kept = take_fitting(&self.staging, total);
        let (staging, index) = self.scoped(label, || {
            let staging = kept.unwrap_or_else(|| {
                self.device.create_buffer(&wgpu::BufferDescriptor {
                    label: Some("read-back"),
                    size: total,
                    usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                    mapped_at_creation: false,
                })
            });
            let query = (stamps > 0).then(|| {
                let set = self.device.create_query_set(&wgpu::QuerySetDescriptor {
                    label: Some("timestamps"),
                    ty: wgpu::QueryType::Timestamp,
                    count: stamps,
                });
                let resolve = self.device.create_buffer(&wgpu::BufferDescriptor {
                    label: Some("timestamps resolve"),
                    size: 8 * u64::from(stamps),
                    usage: wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
                    mapped_at_creation: false,
                });
                (set, resolve)
            });
            let mut encoder = self
                .device
                .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some(label) });
            for (k, p) in passes.iter().enumerate() {
                let timestamp_writes =
                    query
                        .as_ref()
                        .map(|(set, _)| wgpu::ComputePassTimestampWrites {
                            query_set: set,
                            beginning_of_pass_write_index: Some(2 * k as u32),
                            end_of_pass_write_index: Some(2 * k as u32 + 1),
                        });
                let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some(p.label),
                    timestamp_writes,
                });
                pass.set_pipeline(p.pipeline);
                for (i, g) in p.groups.iter().enumerate() {
                    pass.set_bind_group(i as u32, *g, &[]);
                }
                let [x, y, z] = p.workgroups;
                pass.dispatch_workgroups(x, y, z);
            }
            if let Some((buffer, _)) = output {
                if copied > 0 {
                    encoder.copy_buffer_to_buffer(buffer, 0, &staging, 0, copied);
                }
            }
            if let Some((set, resolve)) = &query {
                encoder.resolve_query_set(set, 0..stamps, resolve, 0);
                encoder.copy_buffer_to_buffer(
                    resolve,
                    0,
                    &staging,
                    stamps_at,
                    8 * u64::from(stamps),
                );
            }
            let index = self.queue.submit([encoder.finish()]);
            Ok((staging, index))
        })?;
        // One message: the mapping callback never waits on it.
        let (tx, rx) = std::sync::mpsc::sync_channel(1);
        staging.map_async(wgpu::MapMode::Read, ..total, move |r| {
            let _ = tx.send(r);
        });
        Ok(Submitted {
            gpu: self,
            staging: Some(staging),
            index,
            size,
            stamps_at,
            stamps,
            mapped_bytes: total,
            mapped: rx,
        })
    }

    /// Runs `jobs` through `submit` and `consume` with two in flight: the host consumes job
    /// k's bytes (copies them into place) while the device runs job k + 1, so a result read
    /// back in parts costs little more than its kernels. Returns the kernels' total time.
    ///
    /// # Errors
    /// The first error of `submit` or of a submission.
    pub(super) fn pipelined<'g, J>(
        &'g self,
        jobs: impl IntoIterator<Item = J>,
        mut submit: impl FnMut(&J) -> Result<Submitted<'g>, GpuError>,
        mut consume: impl FnMut(J, &[u8]),
    ) -> Result<KernelTime, GpuError> {
        let mut time = KernelTime::default();
        let mut pending: Option<(J, Submitted<'g>)> = None;
        for job in jobs {
            let next = submit(&job)?;
            if let Some((done, s)) = pending.replace((job, next)) {
                let ((), t) = s.finish(|b| consume(done, b))?;
                time.add(t);
            }
        }
        if let Some((done, s)) = pending {
            let ((), t) = s.finish(|b| consume(done, b))?;
            time.add(t);
        }
        Ok(time)
    }

    /// Waits for submission `index`.
    fn wait(&self, index: wgpu::SubmissionIndex, what: &str) -> Result<(), GpuError> {
        match self.device.poll(wgpu::PollType::Wait {
            submission_index: Some(index),
            timeout: Some(SUBMISSION_TIMEOUT),
        }) {
            Ok(_) => self.check_failure(),
            Err(wgpu::PollError::Timeout) => Err(GpuError::Timeout(format!(
                "{what}: no completion within {} s",
                SUBMISSION_TIMEOUT.as_secs()
            ))),
            Err(e) => Err(GpuError::Lost(format!("{what}: {e}"))),
        }
    }

    /// Keeps a read-back buffer for later calls while the kept ones fit [`STAGING_KEPT`].
    fn keep_staging(&self, buffer: wgpu::Buffer) {
        let Ok(mut pool) = self.staging.lock() else {
            return;
        };
        pool.push(buffer);
        keep_largest(&mut pool, STAGING_KEPT);
    }
}

/// The smallest buffer of `pool` of at least `size` bytes, taken out of it.
fn take_fitting(pool: &Mutex<Vec<wgpu::Buffer>>, size: u64) -> Option<wgpu::Buffer> {
    let mut pool = pool.lock().ok()?;
    let best = (0..pool.len())
        .filter(|&i| pool[i].size() >= size)
        .min_by_key(|&i| pool[i].size())?;
    Some(pool.swap_remove(best))
}

/// Keeps the largest buffers of `pool` whose sizes sum to at most `cap` bytes.
fn keep_largest(pool: &mut Vec<wgpu::Buffer>, cap: u64) {
    pool.sort_unstable_by_key(|b| std::cmp::Reverse(b.size()));
    let mut total = 0;
    pool.retain(|b| {
        let keep = total + b.size() <= cap;
        if keep {
            total += b.size();
        }
        keep
    });
}

/// The GPU timestamps of a call's passes, in ticks (`None` once one submission had none).
/// A pass's beginning may be stamped before the work queued ahead of it has ended, so the
/// kernel time is the length of the passes' union, not the sum of their lengths.
#[derive(Debug)]
pub(super) struct KernelTime(Option<Vec<[u64; 2]>>);

impl Default for KernelTime {
    fn default() -> Self {
        Self(Some(Vec::new()))
    }
}

impl KernelTime {
    /// Adds `other`'s passes.
    pub(super) fn add(&mut self, other: KernelTime) {
        match (&mut self.0, other.0) {
            (Some(a), Some(b)) => a.extend(b),
            _ => self.0 = None,
        }
    }

    /// Seconds the device spent in the passes: the length of the union of their intervals.
    pub(super) fn seconds(&self, gpu: &Gpu) -> Option<f64> {
        let mut intervals = self.0.clone()?;
        intervals.sort_unstable();
        let mut ticks = 0u64;
        let mut covered = 0u64;
        for [begin, end] in intervals {
            let begin = begin.max(covered);
            if end > begin {
                ticks += end - begin;
                covered = end;
            }
        }
        Some(ticks as f64 * f64::from(gpu.queue.get_timestamp_period()) * 1e-9)
    }
}

/// One compute pass of a [`Gpu::submit`]: a pipeline, its bind groups in order, a dispatch.
pub(super) struct Pass<'a> {
    pub label: &'static str,
    pub pipeline: &'a wgpu::ComputePipeline,
    pub groups: &'a [&'a wgpu::BindGroup],
    pub workgroups: [u32; 3],
}

/// A submission in flight from [`Gpu::submit`].
pub(super) struct Submitted<'g> {
    gpu: &'g Gpu,
    /// `Some` until finished; mapped once the submission completes.
    staging: Option<wgpu::Buffer>,
    index: wgpu::SubmissionIndex,
    /// Bytes of output at the start of `staging`.
    size: u64,
    /// Where the timestamps start in `staging`, and how many there are.
    stamps_at: u64,
    stamps: u32,
    /// Bytes of `staging` mapped.
    mapped_bytes: u64,
    mapped: std::sync::mpsc::Receiver<Result<(), wgpu::BufferAsyncError>>,
}

impl Submitted<'_> {
    /// Waits for the submission, hands its output bytes to `consume` while they are mapped
    /// (so they are copied once, into their destination), and returns what `consume` returned
    /// with the passes' timestamps. The read-back buffer is kept for later calls.
    ///
    /// # Errors
    /// Device loss, a wait past [`SUBMISSION_TIMEOUT`], or a mapping that fails or never
    /// completes.
    pub(super) fn finish<T>(
        mut self,
        consume: impl FnOnce(&[u8]) -> T,
    ) -> Result<(T, KernelTime), GpuError> {
        let gpu = self.gpu;
        gpu.wait(self.index.clone(), "read-back")?;
        match self.mapped.recv_timeout(Duration::from_secs(1)) {
            Ok(Ok(())) => {}
            Ok(Err(e)) => return Err(GpuError::Lost(format!("read-back mapping: {e}"))),
            Err(_) => return Err(GpuError::Lost("read-back mapping never completed".into())),
        }
        let staging = self
            .staging
            .take()
            .ok_or_else(|| GpuError::Lost("read-back buffer already released".into()))?;
        let (out, kernel_s) = {
            let view = staging
                .get_mapped_range(..self.mapped_bytes)
                .map_err(|e| GpuError::Lost(format!("read-back view: {e}")))?;
            let out = consume(&view[..self.size as usize]);
            let word = |at: usize| {
                let mut le = [0u8; 8];
                le.copy_from_slice(&view[at..at + 8]);
                u64::from_le_bytes(le)
            };
            let at = self.stamps_at as usize;
            let kernel_s = KernelTime((self.stamps > 0).then(|| {
                (0..self.stamps as usize / 2)
                    .map(|k| [word(at + 16 * k), word(at + 16 * k + 8)])
                    .collect()
            }));
            (out, kernel_s)
        };
        staging.unmap();
        gpu.keep_staging(staging);
        Ok((out, kernel_s))
    }
}

/// A scratch storage buffer lent by [`Gpu::scratch`], given back to be kept when dropped.
pub(super) struct Scratch<'g> {
    gpu: &'g Gpu,
    /// `Some` until dropped.
    buffer: Option<wgpu::Buffer>,
    /// The size asked for, bytes: the length of [`Self::binding`].
    size: u64,
}

impl Scratch<'_> {
    /// The buffer under it (at least the size asked for).
    pub(super) fn buffer(&self) -> &wgpu::Buffer {
        // Invariant: `buffer` is only taken in `drop`.
        self.buffer.as_ref().unwrap_or_else(|| unreachable!())
    }

    /// The size asked for, bytes.
    pub(super) fn size(&self) -> u64 {
        self.size
    }

    /// The first `size` bytes of the buffer, as a binding.
    pub(super) fn binding(&self) -> wgpu::BindingResource<'_> {
        wgpu::BindingResource::Buffer(wgpu::BufferBinding {
            buffer: self.buffer(),
            offset: 0,
            size: NonZeroU64::new(self.size),
        })
    }
}

impl Drop for Scratch<'_> {
    fn drop(&mut self) {
        let (Some(buffer), Ok(mut pool)) = (self.buffer.take(), self.gpu.scratch.lock()) else {
            return;
        };
        pool.push(buffer);
        keep_largest(&mut pool, SCRATCH_KEPT);
    }
}

/// Little-endian packing of uniform blocks made of 16-byte vec4 rows.
#[derive(Default)]
pub(super) struct Uniform(Vec<u8>);

impl Uniform {
    /// A camera's view frame as four rows: eye, right + `tan(fov_x/2)`, up + `tan(fov_y/2)`,
    /// forward + `forward_w` (the layout `common.wgsl` and `render.wgsl` read).
    pub(super) fn frame(self, f: &crate::camera::ViewFrame, forward_w: f32) -> Self {
        self.vec4([f.eye.x, f.eye.y, f.eye.z, 0.0])
            .vec4([f.right.x, f.right.y, f.right.z, f.tan_half_x])
            .vec4([f.up.x, f.up.y, f.up.z, f.tan_half_y])
            .vec4([f.forward.x, f.forward.y, f.forward.z, forward_w])
    }

    pub(super) fn vec4(mut self, v: [f32; 4]) -> Self {
        for x in v {
            self.0.extend_from_slice(&x.to_le_bytes());
        }
        self
    }

    pub(super) fn uvec4(mut self, v: [u32; 4]) -> Self {
        for x in v {
            self.0.extend_from_slice(&x.to_le_bytes());
        }
        self
    }

    pub(super) fn bytes(&self) -> &[u8] {
        &self.0
    }
}

/// `values` as the little-endian bytes the kernels read: borrowed on a little-endian host.
/// `T` is made of 4-byte words (`u32`, `f32` and arrays or structs of them).
pub(super) fn le_bytes<T: bytemuck::Pod>(values: &[T]) -> Cow<'_, [u8]> {
    let bytes: &[u8] = bytemuck::cast_slice(values);
    if cfg!(target_endian = "little") {
        Cow::Borrowed(bytes)
    } else {
        let mut owned = bytes.to_vec();
        owned.chunks_exact_mut(4).for_each(<[u8]>::reverse);
        Cow::Owned(owned)
    }
}

/// Fewest bytes read out of a mapping on the worker threads rather than on the caller's.
const PARALLEL_BYTES: usize = 1 << 20;

/// Appends to `out` the values of the little-endian bytes the kernels wrote (a whole number
/// of `T`), written straight into `out`'s new room: no zero-filling first (a freed image
/// reused by the allocator would be cleared on one thread), and on the worker threads when
/// large, so the mapping is read and fresh pages fault in on every core at once. `T` as for
/// [`le_bytes`].
pub(super) fn extend_from_le<T: bytemuck::Pod + Send + Sync>(bytes: &[u8], out: &mut Vec<T>) {
    use rayon::prelude::*;
    let size = std::mem::size_of::<T>();
    let value = |chunk: &[u8]| {
        let mut v: T = bytemuck::pod_read_unaligned(chunk);
        if cfg!(target_endian = "big") {
            bytemuck::bytes_of_mut(&mut v)
                .chunks_exact_mut(4)
                .for_each(<[u8]>::reverse);
        }
        v
    };
    if bytes.len() >= PARALLEL_BYTES {
        out.par_extend(bytes.par_chunks_exact(size).map(value));
    } else {
        out.extend(bytes.chunks_exact(size).map(value));
    }
}
