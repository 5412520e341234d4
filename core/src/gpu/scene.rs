//! A volume and transfer function uploaded to the GPU: reference DVR and VDI generation.

use super::context::{extend_from_le, le_bytes, KernelTime, Pass, Scratch, Submitted, Uniform};
use super::{Gpu, GpuError};
use crate::camera::Camera;
use crate::image::Image;
use crate::raycast::Raycaster;
use crate::vdi::{generate::meta_for, Supersegment, Vdi, VdiParams};

/// Bytes of one supersegment on the GPU (six `f32`, the layout of [`Supersegment`]).
pub(super) const SEGMENT_BYTES: u64 = 24;
// Read back and uploaded as they lie in memory (`le_bytes`, `extend_from_le`).
const _: () = assert!(std::mem::size_of::<Supersegment>() == SEGMENT_BYTES as usize);
/// Counts per workgroup of the prefix sum (`scan.wgsl`'s `BLOCK`).
const SCAN_BLOCK: u64 = 1024;
/// Per-ray slot budget of a scene's first generation; later ones use the next power of two
/// above the longest list seen, within [`SLOTS_BYTES`].
pub const INITIAL_BUDGET: u32 = 16;
/// Most bytes of per-ray slots in one counted band. A ray whose list is longer than its slots
/// is marched again when written; on the H200 one march of every ray and a copy cost about
/// half of two marches (teapot and a 432³ field, r 256–768).
const SLOTS_BYTES: u64 = 1 << 30;
/// Largest κ stored in the classification texture: `a = 1` has κ = ∞, which WGSL may not
/// represent; `e^(−1e30·ℓ)` is 0 for any step, so the opacity is still exactly 1.
const KAPPA_MAX: f32 = 1e30;

/// A [`Raycaster`]'s scene on the GPU: the volume as an `R32Float` 3D texture (trilinear
/// interpolation in the shader, as on the CPU: exact, and NaN-aware, which hardware filtering
/// with its 8-bit weights is not), the transfer function as two 1D textures, the macro-cell
/// visibility as a storage buffer.
pub struct GpuVolume<'g, 'v> {
    gpu: &'g Gpu,
    raycaster: &'v Raycaster<'v>,
    volume_view: wgpu::TextureView,
    color_view: wgpu::TextureView,
    extinction_view: wgpu::TextureView,
    macro_cells: wgpu::Buffer,
    /// Per-ray slot budget for the next generation: the scene's generations (a study's
    /// candidates, a series' views) have lists of similar lengths.
    budget: std::sync::atomic::AtomicU32,
}

/// An image or VDI with the kernel time spent making it.
pub struct KernelRun<T> {
    /// The result.
    pub value: T,
    /// Kernel time in seconds from GPU timestamps (sum over every pass), `None` when the
    /// adapter has no timestamps.
    pub kernel_s: Option<f64>,
}

/// What a dispatch of the scene's kernels does (`Params.image.w` and `Params.band` of
/// `common.wgsl`), and its band of rows.
#[derive(Clone, Copy)]
enum Work {
    /// Reference DVR of `rows` rows.
    Dvr { rows: u32 },
    /// Counting the supersegments of `rows` rows with interrupt threshold `gamma`, keeping
    /// up to `budget` of them per ray.
    Count { gamma: f32, rows: u32, budget: u32 },
    /// Writing them: `rows` rows starting `first_row` rows into the counted band, whose
    /// first supersegment has offset `first` in the band; lists of at most `budget` are
    /// copied from their slots.
    Write {
        gamma: f32,
        rows: u32,
        first_row: u32,
        first: u32,
        budget: u32,
    },
}

fn texture_view(
    gpu: &Gpu,
    label: &str,
    size: wgpu::Extent3d,
    dimension: wgpu::TextureDimension,
    format: wgpu::TextureFormat,
    texel_bytes: u32,
    data: &[u8],
) -> wgpu::TextureView {
    let texture = gpu.device.create_texture(&wgpu::TextureDescriptor {
        label: Some(label),
        size,
        mip_level_count: 1,
        sample_count: 1,
        dimension,
        format,
        usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
        view_formats: &[],
    });
    gpu.queue.write_texture(
        wgpu::TexelCopyTextureInfo {
            texture: &texture,
            mip_level: 0,
            origin: wgpu::Origin3d::ZERO,
            aspect: wgpu::TextureAspect::All,
        },
        data,
        wgpu::TexelCopyBufferLayout {
            offset: 0,
            bytes_per_row: Some(size.width * texel_bytes),
            rows_per_image: Some(size.height),
        },
        size,
    );
    texture.create_view(&wgpu::TextureViewDescriptor::default())
}

impl<'g, 'v> GpuVolume<'g, 'v> {
    /// Uploads `raycaster`'s volume, classification table and macro-cell grid.
    ///
    /// # Errors
    /// [`GpuError::Limit`] when a volume side exceeds `max_texture_dimension_3d` (bricks of
    /// at most that side must be made by the caller, as ranks do), or errors of the device.
    pub fn new(gpu: &'g Gpu, raycaster: &'v Raycaster<'v>) -> Result<Self, GpuError> {
        let volume = raycaster.volume();
        let dims = volume.dims();
        let max3 = gpu.limits.max_texture_dimension_3d;
        for (axis, &n) in ["x", "y", "z"].iter().zip(&dims) {
            if n as u64 > u64::from(max3) {
                return Err(GpuError::Limit {
                    what: format!("volume side {axis} of {dims:?}"),
                    needed: n as u64,
                    limit: u64::from(max3),
                    name: "max_texture_dimension_3d",
                });
            }
        }
        let lut = raycaster.lut();
        let entries = lut.entries();
        let max1 = gpu.limits.max_texture_dimension_1d;
        if entries.len() as u64 > u64::from(max1) {
            return Err(GpuError::Limit {
                what: "transfer-function table".into(),
                needed: entries.len() as u64,
                limit: u64::from(max1),
                name: "max_texture_dimension_1d",
            });
        }
        let grid = raycaster.macro_grid();
        gpu.scoped("uploading the scene", || {
            let volume_view = texture_view(
                gpu,
                "volume",
                wgpu::Extent3d {
                    width: dims[0] as u32,
                    height: dims[1] as u32,
                    depth_or_array_layers: dims[2] as u32,
                },
                wgpu::TextureDimension::D3,
                wgpu::TextureFormat::R32Float,
                4,
                &le_bytes(&volume.data()),
            );
            let lut_size = wgpu::Extent3d {
                width: entries.len() as u32,
                height: 1,
                depth_or_array_layers: 1,
            };
            let lut_texture = |label: &str, texel: fn(&crate::tf::LutEntry) -> [f32; 4]| {
                texture_view(
                    gpu,
                    label,
                    lut_size,
                    wgpu::TextureDimension::D1,
                    wgpu::TextureFormat::Rgba32Float,
                    16,
                    &le_bytes(&entries.iter().map(texel).collect::<Vec<_>>()),
                )
            };
            let color_view = lut_texture("tf colour", |e| {
                [e.rgb[0], e.rgb[1], e.rgb[2], e.alpha_unit]
            });
            let extinction_view = lut_texture("tf extinction", |e| {
                [e.kappa.min(KAPPA_MAX), e.alpha_step, 0.0, 0.0]
            });
            let macro_cells = gpu.buffer_init(
                "macro cells",
                &le_bytes(
                    &grid
                        .visibility()
                        .iter()
                        .map(|&v| u32::from(v))
                        .collect::<Vec<_>>(),
                ),
                wgpu::BufferUsages::STORAGE,
            );
            Ok(Self {
                gpu,
                raycaster,
                volume_view,
                color_view,
                extinction_view,
                macro_cells,
                budget: std::sync::atomic::AtomicU32::new(INITIAL_BUDGET),
            })
        })
    }

    /// The device this scene lives on.
    pub fn gpu(&self) -> &'g Gpu {
        self.gpu
    }

    /// The ray-caster this scene was uploaded from.
    pub fn raycaster(&self) -> &'v Raycaster<'v> {
        self.raycaster
    }

    /// The uniform block of `common.wgsl` for `camera` at `width × height`, band from `row0`.
    fn params(&self, camera: &Camera, width: u32, height: u32, row0: u32, work: Work) -> Uniform {
        let f = camera.frame(width, height);
        let rc = self.raycaster.params();
        let volume = self.raycaster.volume();
        let b = self.raycaster.bounds();
        let inv = volume.spacing().recip();
        let d = volume.dims();
        let (lo, scale) = self.raycaster.lut().mapping();
        let s = rc.shading.unwrap_or_default();
        let grid = self.raycaster.macro_grid();
        let cells = grid.cells();
        let (gamma, code, band) = match work {
            Work::Dvr { rows } => (0.0, 0, [rows, 0, 0, 0]),
            Work::Count {
                gamma,
                rows,
                budget,
            } => (gamma, 1, [rows, 0, 0, budget]),
            Work::Write {
                gamma,
                rows,
                first_row,
                first,
                budget,
            } => (gamma, 2, [rows, first_row, first, budget]),
        };
        // Generation stops rays at its own threshold, the DVR at the render one.
        let termination = match work {
            Work::Dvr { .. } => rc.termination,
            _ => rc.generation_stop(),
        };
        Uniform::default()
            .frame(&f, rc.sample_distance)
            .vec4([b.min.x, b.min.y, b.min.z, termination])
            .vec4([b.max.x, b.max.y, b.max.z, gamma])
            .vec4([inv.x, inv.y, inv.z, lo])
            .vec4([
                (d[0] - 1) as f32,
                (d[1] - 1) as f32,
                (d[2] - 1) as f32,
                scale,
            ])
            .vec4([s.ambient, s.diffuse, s.specular, s.shininess])
            .uvec4([
                d[0] as u32,
                d[1] as u32,
                d[2] as u32,
                u32::from(rc.empty_space_skipping),
            ])
            .uvec4([
                cells[0] as u32,
                cells[1] as u32,
                cells[2] as u32,
                grid.cell_size() as u32,
            ])
            .uvec4([width, height, row0, code])
            .uvec4(band)
    }

    fn scene_group(&self, uniform: &Uniform) -> wgpu::BindGroup {
        let buffer = self.gpu.uniform("scene params", uniform);
        self.gpu.bind_group(
            "scene",
            &self.gpu.kernels.scene_layout,
            &[
                buffer.as_entire_binding(),
                wgpu::BindingResource::TextureView(&self.volume_view),
                wgpu::BindingResource::TextureView(&self.color_view),
                wgpu::BindingResource::TextureView(&self.extinction_view),
                self.macro_cells.as_entire_binding(),
            ],
        )
    }

    fn shaded(&self) -> usize {
        usize::from(self.raycaster.params().shading.is_some())
    }

    /// Reference DVR of `camera`'s view at `width × height` (mirrors [`crate::dvr::render`]),
    /// in bands of rows whose output fits one storage binding, read back while the next runs.
    ///
    /// # Errors
    /// [`GpuError::Limit`] when one row of the image exceeds the storage-binding or dispatch
    /// limits; errors of the device.
    pub fn dvr(
        &self,
        camera: &Camera,
        width: u32,
        height: u32,
    ) -> Result<KernelRun<Image>, GpuError> {
        let gpu = self.gpu;
        image_in_bands(gpu, width, height, "DVR", |row0, rows, out| {
            let work = Work::Dvr { rows };
            let scene = self.scene_group(&self.params(camera, width, height, row0, work));
            let out_group =
                gpu.bind_group("dvr out", &gpu.kernels.dvr_out_layout, &[out.binding()]);
            let pass = Pass {
                label: "dvr",
                pipeline: &gpu.kernels.dvr[self.shaded()],
                groups: &[&scene, &out_group],
                workgroups: [width.div_ceil(8), rows.div_ceil(8), 1],
            };
            gpu.submit("dvr", &[pass], Some((out.buffer(), out.size())))
        })
    }

    /// VDI generation `R` for `params` (mirrors [`crate::vdi::generate::generate`]), its
    /// compact lists made on the device in two passes: the first marches every ray, counts
    /// its supersegments and keeps up to a per-ray budget of them in slots, and a prefix sum
    /// turns the counts into the list offsets; the second writes each ray's list at its
    /// offset, copied from its slots or, for a ray longer than the budget, marched again.
    /// The budget grows to the longest list seen (within [`SLOTS_BYTES`]) for the scene's
    /// next generations. Rows are counted in bands whose offsets fit one storage binding, and
    /// written in parts whose supersegments do, each read back while the next runs.
    ///
    /// # Errors
    /// [`GpuError::Params`] for bad `params` or a degenerate camera; [`GpuError::Limit`] when
    /// a single row exceeds the binding limit or the VDI exceeds `u32::MAX` supersegments;
    /// errors of the device.
    pub fn generate(
        &self,
        camera: &Camera,
        params: VdiParams,
        tf_hash: u64,
        tf_name: &str,
    ) -> Result<KernelRun<Vdi>, GpuError> {
        params.validate()?;
        if !camera.is_valid() {
            return Err(crate::vdi::VdiParamError::Camera(*camera).into());
        }
        let gpu = self.gpu;
        let r = params.resolution;
        // Rows per counted band: its counts and one more (the band's total) fit one binding.
        let mut rows = band_rows(gpu, r, 4, "VDI row of counts")?;
        if u64::from(rows) * u64::from(r) * 4 + 4 > gpu.max_storage_binding() {
            rows -= 1;
        }
        if rows == 0 {
            return Err(GpuError::Limit {
                what: "VDI row of counts and its total".into(),
                needed: u64::from(r) * 4 + 4,
                limit: gpu.max_storage_binding(),
                name: "max_storage_buffer_binding_size",
            });
        }
        let mut offsets = Vec::with_capacity(r as usize * r as usize + 1);
        offsets.push(0u32);
        let mut supersegments: Vec<Supersegment> = Vec::new();
        let mut time = KernelTime::default();
        let mut row0 = 0;
        while row0 < r {
            let n = rows.min(r - row0);
            let (counting, band) = self.count(camera, r, params.gamma, row0, n)?;
            let (most, t) = counting.finish(|b| append_offsets(b, &mut offsets))?;
            let most = most?;
            time.add(t);
            let local = &offsets[offsets.len() - (r * n) as usize - 1..];
            let next = most.checked_next_power_of_two().unwrap_or(most);
            self.budget
                .fetch_max(next, std::sync::atomic::Ordering::Relaxed);
            let band_first = local[0];
            let total = (local[local.len() - 1] - band_first) as usize;
            if total > 0 {
                supersegments.reserve(total);
                let parts = write_parts(gpu, local, r)?;
                // Parts are consumed in order, each appending its rows' lists.
                let t = gpu.pipelined(
                    parts,
                    |&(a, b)| {
                        let first = local[(a * r) as usize] - band_first;
                        let last = local[(b * r) as usize] - band_first;
                        let work = Work::Write {
                            gamma: params.gamma,
                            rows: b - a,
                            first_row: a,
                            first,
                            budget: band.budget,
                        };
                        let bytes = u64::from(last - first) * SEGMENT_BYTES;
                        self.write(camera, r, row0 + a, work, &band, bytes)
                    },
                    |_, bytes| extend_from_le(bytes, &mut supersegments),
                )?;
                time.add(t);
            }
            row0 += n;
        }
        let meta = meta_for(self.raycaster, camera, params, tf_hash, tf_name);
        // The offsets were checked as they were read back.
        let vdi = Vdi::from_sorted_parts(meta, offsets, supersegments).ok_or(GpuError::Limit {
            what: "VDI list layout".into(),
            needed: 0,
            limit: 0,
            name: "offsets",
        })?;
        Ok(KernelRun {
            value: vdi,
            kernel_s: time.seconds(gpu),
        })
    }

    /// Submits the counting pass over `rows` rows from `row0` and the prefix sum of its
    /// counts; the submission's output is the band's `rays + 1` offsets.
    fn count(
        &self,
        camera: &Camera,
        r: u32,
        gamma: f32,
        row0: u32,
        rows: u32,
    ) -> Result<(Submitted<'g>, CountedBand<'g>), GpuError> {
        let gpu = self.gpu;
        let k = &gpu.kernels;
        let rays = u64::from(r) * u64::from(rows);
        let offsets = gpu.scratch("vdi offsets", (rays + 1) * 4);
        let blocks = rays.div_ceil(SCAN_BLOCK);
        let sums = gpu.scratch("vdi block sums", blocks * 4);
        let per_ray = rays * SEGMENT_BYTES;
        let room = SLOTS_BYTES.min(gpu.max_storage_binding()) / per_ray;
        let learned = self.budget.load(std::sync::atomic::Ordering::Relaxed);
        let budget = u64::from(learned).min(room) as u32;
        let slots = gpu.scratch("vdi slots", u64::from(budget) * per_ray);
        // Counting writes no list; its binding is a placeholder.
        let none = gpu.scratch("no supersegments", 0);
        let work = Work::Count {
            gamma,
            rows,
            budget,
        };
        let scene = self.scene_group(&self.params(camera, r, r, row0, work));
        let out = gpu.bind_group(
            "count out",
            &k.generate_out_layout,
            &[none.binding(), offsets.binding(), slots.binding()],
        );
        let max_x = u64::from(gpu.limits.max_compute_workgroups_per_dimension);
        let gx = blocks.min(max_x);
        let gy = blocks.div_ceil(gx.max(1));
        let uniform = Uniform::default().uvec4([rays as u32, blocks as u32, gx as u32, 0]);
        let scan_params = gpu.uniform("scan params", &uniform);
        let scan = gpu.bind_group(
            "scan",
            &k.scan_layout,
            &[
                scan_params.as_entire_binding(),
                offsets.binding(),
                sums.binding(),
            ],
        );
        let grid = [gx as u32, gy as u32, 1];
        let passes = [
            Pass {
                label: "count supersegments",
                pipeline: &k.generate[self.shaded()],
                groups: &[&scene, &out],
                workgroups: [r.div_ceil(8), rows.div_ceil(8), 1],
            },
            Pass {
                label: "scan blocks",
                pipeline: &k.scan[0],
                groups: &[&scan],
                workgroups: grid,
            },
            Pass {
                label: "scan block totals",
                pipeline: &k.scan[1],
                groups: &[&scan],
                workgroups: [1, 1, 1],
            },
            Pass {
                label: "add block offsets",
                pipeline: &k.scan[2],
                groups: &[&scan],
                workgroups: grid,
            },
        ];
        let submitted = gpu.submit(
            "counting",
            &passes,
            Some((offsets.buffer(), (rays + 1) * 4)),
        )?;
        Ok((
            submitted,
            CountedBand {
                offsets,
                slots,
                budget,
            },
        ))
    }

    /// Submits the writing pass of `work`'s rows (from image row `row0`) into a buffer of
    /// `bytes`, the part's supersegments, with the counted `band`'s offsets and slots.
    fn write(
        &self,
        camera: &Camera,
        r: u32,
        row0: u32,
        work: Work,
        band: &CountedBand<'_>,
        bytes: u64,
    ) -> Result<Submitted<'g>, GpuError> {
        let gpu = self.gpu;
        let rows = match work {
            Work::Dvr { rows } | Work::Count { rows, .. } | Work::Write { rows, .. } => rows,
        };
        let segments = gpu.scratch("vdi supersegments", bytes);
        let scene = self.scene_group(&self.params(camera, r, r, row0, work));
        let out = gpu.bind_group(
            "write out",
            &gpu.kernels.generate_out_layout,
            &[
                segments.binding(),
                band.offsets.binding(),
                band.slots.binding(),
            ],
        );
        let pass = Pass {
            label: "write supersegments",
            pipeline: &gpu.kernels.generate[self.shaded()],
            groups: &[&scene, &out],
            workgroups: [r.div_ceil(8), rows.div_ceil(8), 1],
        };
        gpu.submit("writing", &[pass], Some((segments.buffer(), bytes)))
    }
}

/// A counted band's buffers on the device: its `rays + 1` list offsets and its per-ray slots
/// of `budget` supersegments each.
struct CountedBand<'g> {
    offsets: Scratch<'g>,
    slots: Scratch<'g>,
    budget: u32,
}

/// Appends a counted band's offsets (`bytes`: its `rays + 1` little-endian `u32`s, from 0)
/// to `offsets`, shifted by the last offset there, and checks them; returns the longest
/// list's length. Read out of the mapping once, on the worker threads.
///
/// # Errors
/// [`GpuError::Limit`] when the VDI's supersegments exceed `u32::MAX` (the device's sums wrap,
/// which shows as a decrease).
fn append_offsets(bytes: &[u8], offsets: &mut Vec<u32>) -> Result<u32, GpuError> {
    use rayon::prelude::*;
    let start = offsets.len();
    let base = offsets.last().copied().unwrap_or(0);
    let first_is_zero = bytes.get(..4).is_some_and(|b| b == [0; 4]);
    extend_from_le(bytes.get(4..).unwrap_or(&[]), offsets);
    if base != 0 {
        offsets[start..]
            .par_iter_mut()
            .for_each(|o| *o = o.wrapping_add(base));
    }
    let (wrapped, most) = offsets[start.saturating_sub(1)..]
        .par_windows(2)
        .map(|w| (w[1] < w[0], w[1].wrapping_sub(w[0])))
        .reduce(|| (false, 0), |a, b| (a.0 | b.0, a.1.max(b.1)));
    let end = u64::from(base) + u64::from(offsets[offsets.len() - 1].wrapping_sub(base));
    if wrapped || !first_is_zero || end > u64::from(u32::MAX) {
        return Err(GpuError::Limit {
            what: "supersegments in one VDI".into(),
            needed: end.max(u64::from(u32::MAX) + 1),
            limit: u64::from(u32::MAX),
            name: "u32 offsets",
        });
    }
    Ok(most)
}

/// The parts a counted band's rows are written in, `(first row, end row)` within the band,
/// each as large as one storage binding allows (one on most devices: splitting a kernel into
/// parts cost more on the H200 than overlapping their read-backs saved). `local` holds the
/// band's `r · rows + 1` offsets; rows without supersegments are left out.
///
/// # Errors
/// [`GpuError::Limit`] when one row's supersegments exceed a binding.
fn write_parts(gpu: &Gpu, local: &[u32], r: u32) -> Result<Vec<(u32, u32)>, GpuError> {
    let rows = ((local.len() - 1) / r as usize) as u32;
    let at = |row: u32| u64::from(local[(row * r) as usize]) * SEGMENT_BYTES;
    let limit = gpu.max_storage_binding();
    let mut parts = Vec::new();
    let mut a = 0;
    while a < rows {
        let mut b = a + 1;
        if at(b) - at(a) > limit {
            return Err(GpuError::Limit {
                what: format!("supersegments of VDI row {a}"),
                needed: at(b) - at(a),
                limit,
                name: "max_storage_buffer_binding_size",
            });
        }
        while b < rows && at(b + 1) - at(a) <= limit {
            b += 1;
        }
        if at(b) > at(a) {
            parts.push((a, b));
        }
        a = b;
    }
    Ok(parts)
}
/// An RGB image rendered in bands of rows whose output (12 bytes a pixel) fits one storage
/// binding (one band on most devices), each read back while the next runs:
/// `submit(row0, rows, out)` submits a kernel writing the band into `out` with `out` as its
/// output.
pub(super) fn image_in_bands<'g>(
    gpu: &'g Gpu,
    width: u32,
    height: u32,
    what: &str,
    mut submit: impl FnMut(u32, u32, &Scratch<'g>) -> Result<Submitted<'g>, GpuError>,
) -> Result<KernelRun<Image>, GpuError> {
    let rows = band_rows(gpu, width, 12, &format!("{what} image row"))?;
    let bands = (0..height)
        .step_by(rows as usize)
        .map(|row0| (row0, rows.min(height - row0)));
    let expected = width as usize * height as usize;
    let mut pixels: Vec<[f32; 3]> = Vec::with_capacity(expected);
    // Bands are consumed in order, each appending its rows.
    let time = gpu.pipelined(
        bands,
        |&(row0, n)| {
            let out = gpu.scratch(what, u64::from(width) * u64::from(n) * 12);
            submit(row0, n, &out)
        },
        |_, bytes| extend_from_le(bytes, &mut pixels),
    )?;
    let read = pixels.len();
    let image = Image::from_pixels(width, height, pixels).ok_or_else(|| {
        GpuError::Validation(format!("{what}: {read} of {expected} pixels read back"))
    })?;
    Ok(KernelRun {
        value: image,
        kernel_s: time.seconds(gpu),
    })
}

/// Rows per band so that `width × bytes_per_item` per row fits one storage binding and the
/// dispatch (8 rows per workgroup) stays within the workgroup limit.
pub(super) fn band_rows(
    gpu: &Gpu,
    width: u32,
    bytes_per_item: u64,
    what: &str,
) -> Result<u32, GpuError> {
    let row_bytes = u64::from(width) * bytes_per_item;
    gpu.check_binding(what, row_bytes)?;
    let limit = gpu.max_storage_binding();
    let max_groups = u64::from(gpu.limits.max_compute_workgroups_per_dimension);
    if u64::from(width).div_ceil(8) > max_groups {
        return Err(GpuError::Limit {
            what: format!("{what}: workgroups across a row of {width}"),
            needed: u64::from(width).div_ceil(8),
            limit: max_groups,
            name: "max_compute_workgroups_per_dimension",
        });
    }
    let rows = (limit / row_bytes.max(1))
        .min(max_groups * 8)
        .min(u64::from(u32::MAX));
    Ok(rows.max(1) as u32)
}
