//! A volume and transfer function uploaded to the GPU: reference DVR and VDI generation.

use super::context::{copy_from_le, extend_from_le, le_bytes, Scratch, Uniform};
use super::{Gpu, GpuError};
use crate::camera::Camera;
use crate::image::Image;
use crate::raycast::Raycaster;
use crate::vdi::{generate::meta_for, Supersegment, Vdi, VdiParams};

/// Bytes of one supersegment on the GPU (six `f32`, the layout of [`Supersegment`]).
pub(super) const SEGMENT_BYTES: u64 = 24;
// Read back and uploaded as they lie in memory (`le_bytes`, `copy_from_le`).
const _: () = assert!(std::mem::size_of::<Supersegment>() == SEGMENT_BYTES as usize);
/// Per-ray supersegment budget of the first generation pass; a band whose rays need more is
/// run again with the next power of two above the largest count.
pub const INITIAL_BUDGET: u32 = 16;
/// Most bytes of per-ray slots in one generation band. A larger per-ray budget makes more,
/// shorter bands rather than a larger buffer: the slots stay within what the device keeps
/// between calls, and the memory a generation holds does not grow with its longest list.
const SLOTS_PER_BAND: u64 = 512 << 20;
/// Largest κ stored in the classification texture: `a = 1` has κ = ∞, which WGSL may not
/// represent; `e^(−1e30·ℓ)` is 0 for any step, so the opacity is still exactly 1.
const KAPPA_MAX: f32 = 1e30;

/// A [`Raycaster`]'s scene on the GPU: the volume as an `R32Float` 3D texture (trilinear
/// interpolation in the shader, as on the CPU: exact, and NaN-aware, which hardware filtering
/// with its 8-bit weights is not), the transfer function as two 1D textures, the macro-cell
/// visibility as a storage buffer.
pub struct GpuScene<'g, 'v> {
    gpu: &'g Gpu,
    raycaster: &'v Raycaster<'v>,
    volume_view: wgpu::TextureView,
    color_view: wgpu::TextureView,
    extinction_view: wgpu::TextureView,
    macro_cells: wgpu::Buffer,
    /// Per-ray budget that sufficed last time: later generations of the scene (a study's many
    /// candidates, the frames of a time series) start there instead of overflowing again.
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

/// Adds kernel times; `None` as soon as one pass had no timestamp.
fn add_time(total: &mut Option<f64>, t: Option<f64>) {
    *total = match (*total, t) {
        (Some(a), Some(b)) => Some(a + b),
        _ => None,
    };
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

impl<'g, 'v> GpuScene<'g, 'v> {
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
    fn params(
        &self,
        camera: &Camera,
        width: u32,
        height: u32,
        row0: u32,
        extra: (f32, u32),
    ) -> Uniform {
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
        let (gamma, budget) = extra;
        // Generation (a VDI budget) stops rays at its own threshold, the DVR at the render one.
        let termination = if budget > 0 {
            rc.generation_stop()
        } else {
            rc.termination
        };
        Uniform::default()
            .frame(&f, rc.step)
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
            .uvec4([width, height, row0, budget])
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
    /// in bands of rows whose output fits one storage binding.
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
        image_in_bands(self.gpu, width, height, "DVR", |row0, rows, out| {
            let scene = self.scene_group(&self.params(camera, width, height, row0, (0.0, 0)));
            let out_group = self.gpu.bind_group(
                "dvr out",
                &self.gpu.kernels.dvr_out_layout,
                &[out.binding()],
            );
            self.gpu.dispatch(
                "dvr",
                &self.gpu.kernels.dvr[self.shaded()],
                &[&scene, &out_group],
                [width.div_ceil(8), rows.div_ceil(8), 1],
            )
        })
    }

    /// VDI generation `R` for `params` (mirrors [`crate::vdi::generate::generate`]): one
    /// invocation per ray writes up to a per-ray budget of supersegments, the host prefix-sums
    /// the counts, and a compaction kernel packs the band into the compact list layout. Bands
    /// of rows keep every buffer under the storage-binding limit; a band with a ray over the
    /// budget is run again with a larger budget (its time counts), and the scene keeps that
    /// budget for its next generations.
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
        let r = params.resolution;
        let mut budget = self.budget.load(std::sync::atomic::Ordering::Relaxed);
        let mut offsets = Vec::with_capacity(r as usize * r as usize + 1);
        offsets.push(0u32);
        let mut supersegments: Vec<Supersegment> = Vec::new();
        let mut kernel_s = Some(0.0);
        let mut row0 = 0;
        while row0 < r {
            let per_ray = u64::from(budget) * SEGMENT_BYTES;
            let rows = band_rows(self.gpu, r, per_ray, "VDI row of per-ray budgets")?
                .min((SLOTS_PER_BAND / (u64::from(r) * per_ray)).max(1) as u32);
            let n = rows.min(r - row0);
            let rays = u64::from(r) * u64::from(n);
            let slots = self.gpu.scratch("vdi slots", rays * per_ray);
            let counts_buf = self.gpu.scratch("vdi counts", rays * 4);
            let scene = self.scene_group(&self.params(camera, r, r, row0, (params.gamma, budget)));
            let out_group = self.gpu.bind_group(
                "generate out",
                &self.gpu.kernels.generate_out_layout,
                &[slots.binding(), counts_buf.binding()],
            );
            let t = self.gpu.dispatch(
                "generate",
                &self.gpu.kernels.generate[self.shaded()],
                &[&scene, &out_group],
                [r.div_ceil(8), n.div_ceil(8), 1],
            )?;
            add_time(&mut kernel_s, t);
            let mut counts = Vec::with_capacity(rays as usize);
            self.gpu.read_with(counts_buf.buffer(), rays * 4, |b| {
                extend_from_le(b, &mut counts)
            })?;
            let most = counts.iter().copied().max().unwrap_or(0);
            if most > budget {
                budget = most.checked_next_power_of_two().unwrap_or(most);
                self.budget
                    .fetch_max(budget, std::sync::atomic::Ordering::Relaxed);
                continue;
            }
            // Band-local prefix offsets, then the global ones.
            let mut local = Vec::with_capacity(counts.len() + 1);
            local.push(0u32);
            let mut acc = 0u64;
            for &c in &counts {
                acc += u64::from(c);
                local.push(acc as u32);
            }
            let base = u64::from(offsets.last().copied().unwrap_or(0));
            if base + acc > u64::from(u32::MAX) {
                return Err(GpuError::Limit {
                    what: "supersegments in one VDI".into(),
                    needed: base + acc,
                    limit: u64::from(u32::MAX),
                    name: "u32 offsets",
                });
            }
            offsets.extend(local[1..].iter().map(|&o| base as u32 + o));
            if acc > 0 {
                let t = self.compact(&slots, &local, rays, budget, &mut supersegments)?;
                add_time(&mut kernel_s, t);
            }
            row0 += n;
        }
        let meta = meta_for(self.raycaster, camera, params, tf_hash, tf_name);
        let vdi = Vdi::from_parts(meta, offsets, supersegments).ok_or(GpuError::Limit {
            what: "VDI list layout".into(),
            needed: 0,
            limit: 0,
            name: "offsets",
        })?;
        Ok(KernelRun {
            value: vdi,
            kernel_s,
        })
    }

    /// Packs a band's slots into contiguous supersegments (as many as the last of
    /// `local_offsets`) appended to `out`; returns the kernel time.
    fn compact(
        &self,
        slots: &Scratch,
        local_offsets: &[u32],
        rays: u64,
        budget: u32,
        out: &mut Vec<Supersegment>,
    ) -> Result<Option<f64>, GpuError> {
        let total = u64::from(local_offsets.last().copied().unwrap_or(0));
        let gpu = self.gpu;
        let groups = rays.div_ceil(64);
        let max_x = u64::from(gpu.limits.max_compute_workgroups_per_dimension);
        let gx = groups.min(max_x);
        let gy = groups.div_ceil(gx);
        let uniform = Uniform::default().uvec4([rays as u32, budget, gx as u32, 0]);
        let params = gpu.uniform("compact params", &uniform);
        let offsets = gpu.buffer_init(
            "compact offsets",
            &le_bytes(local_offsets),
            wgpu::BufferUsages::STORAGE,
        );
        let bytes = total * SEGMENT_BYTES;
        let packed = gpu.scratch("vdi packed", bytes);
        let group = gpu.bind_group(
            "compact",
            &gpu.kernels.compact_layout,
            &[
                params.as_entire_binding(),
                slots.binding(),
                offsets.as_entire_binding(),
                packed.binding(),
            ],
        );
        let t = gpu.dispatch(
            "compact",
            &gpu.kernels.compact,
            &[&group],
            [gx as u32, gy as u32, 1],
        )?;
        gpu.read_with(packed.buffer(), bytes, |b| extend_from_le(b, out))?;
        Ok(t)
    }
}

/// An RGB image rendered in bands of rows whose output (12 bytes a pixel) fits one storage
/// binding: `run(row0, rows, out)` dispatches a kernel writing the band into `out` and
/// returns its kernel time.
pub(super) fn image_in_bands(
    gpu: &Gpu,
    width: u32,
    height: u32,
    what: &str,
    mut run: impl FnMut(u32, u32, &Scratch) -> Result<Option<f64>, GpuError>,
) -> Result<KernelRun<Image>, GpuError> {
    let rows = band_rows(gpu, width, 12, &format!("{what} image row"))?;
    let mut image = Image::new(width, height);
    let mut kernel_s = Some(0.0);
    let mut row0 = 0;
    while row0 < height {
        let n = rows.min(height - row0);
        let bytes = u64::from(width) * u64::from(n) * 12;
        let out = gpu.scratch(what, bytes);
        add_time(&mut kernel_s, run(row0, n, &out)?);
        let start = (row0 * width) as usize;
        let band = &mut image.pixels_mut()[start..start + (width * n) as usize];
        gpu.read_with(out.buffer(), bytes, |b| copy_from_le(b, band))?;
        row0 += n;
    }
    Ok(KernelRun {
        value: image,
        kernel_s,
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
