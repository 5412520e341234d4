//! A VDI uploaded to the GPU and rendered from new cameras.

use super::context::{le_bytes, Pass, Uniform};
use super::scene::{image_in_bands, KernelRun, SEGMENT_BYTES};
use super::{Gpu, GpuError};
use crate::camera::Camera;
use crate::image::Image;
use crate::vdi::render::tile_depth_ranges;
use crate::vdi::Vdi;

/// A VDI's compact lists in two storage buffers (prefix offsets, supersegments), read by
/// `render.wgsl`'s DDA walk.
pub struct GpuVdi<'g> {
    gpu: &'g Gpu,
    offsets: wgpu::Buffer,
    segments: wgpu::Buffer,
    /// Per `SKIP_TILE²` tile of the generation image: its supersegments' depth range.
    tile_depth: wgpu::Buffer,
    generation: Camera,
    resolution: u32,
    volume_box: crate::volume::Aabb,
}

impl<'g> GpuVdi<'g> {
    /// Uploads `vdi`.
    ///
    /// # Errors
    /// [`GpuError::Limit`] when the supersegments or the offsets exceed
    /// `max_storage_buffer_binding_size` (a walk may cross any pixel, so the lists are not
    /// split); errors of the device.
    pub fn new(gpu: &'g Gpu, vdi: &Vdi) -> Result<Self, GpuError> {
        let seg_bytes = vdi.supersegments().len() as u64 * SEGMENT_BYTES;
        gpu.check_binding("VDI supersegments", seg_bytes)?;
        gpu.check_binding("VDI offsets", vdi.offsets().len() as u64 * 4)?;
        gpu.scoped("uploading the VDI", || {
            let offsets = gpu.buffer_init(
                "vdi offsets",
                &le_bytes(vdi.offsets()),
                wgpu::BufferUsages::STORAGE,
            );
            let segments = gpu.buffer_init(
                "vdi supersegments",
                &le_bytes(vdi.supersegments()),
                wgpu::BufferUsages::STORAGE,
            );
            let tile_depth = gpu.buffer_init(
                "vdi tile depths",
                &le_bytes(&tile_depth_ranges(vdi)),
                wgpu::BufferUsages::STORAGE,
            );
            let meta = vdi.meta();
            Ok(Self {
                gpu,
                offsets,
                segments,
                tile_depth,
                generation: meta.camera,
                resolution: vdi.resolution(),
                volume_box: meta.volume_box,
            })
        })
    }

    /// Renders the VDI seen by `camera` at `width × height`, stopping rays at accumulated
    /// opacity `termination` (mirrors [`crate::vdi::render::render`]).
    ///
    /// # Errors
    /// [`GpuError::Limit`] when one image row exceeds the binding or dispatch limits; errors
    /// of the device.
    pub fn render(
        &self,
        camera: &Camera,
        width: u32,
        height: u32,
        termination: f32,
    ) -> Result<KernelRun<Image>, GpuError> {
        let gpu = self.gpu;
        let f = camera.frame(width, height);
        let r = self.resolution;
        let g = self.generation.frame(r, r);
        let b = self.volume_box;
        image_in_bands(gpu, width, height, "render", |row0, rows, out| {
            let uniform = Uniform::default()
                .frame(&f, termination)
                .frame(&g, 0.0)
                .vec4([b.min.x, b.min.y, b.min.z, 0.0])
                .vec4([b.max.x, b.max.y, b.max.z, 0.0])
                .uvec4([width, height, row0, r])
                .uvec4([rows, 0, 0, 0]);
            let params = gpu.uniform("render params", &uniform);
            let group = gpu.bind_group(
                "render",
                &gpu.kernels.render_layout,
                &[
                    params.as_entire_binding(),
                    self.offsets.as_entire_binding(),
                    self.segments.as_entire_binding(),
                    out.binding(),
                    self.tile_depth.as_entire_binding(),
                ],
            );
            let pass = Pass {
                label: "render",
                pipeline: &gpu.kernels.render,
                groups: &[&group],
                workgroups: [width.div_ceil(8), rows.div_ceil(8), 1],
            };
            gpu.submit("render", &[pass], Some((out.buffer(), out.size())))
        })
    }
}
