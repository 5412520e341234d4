//! A VDI uploaded to the GPU and rendered from new cameras.

use super::context::{f32_bytes, to_f32s, u32_bytes, Uniform};
use super::scene::{band_rows, KernelRun};
use super::{Gpu, GpuError};
use crate::camera::Camera;
use crate::image::Image;
use crate::vdi::Vdi;

/// A VDI's compact lists in two storage buffers (prefix offsets, supersegments), read by
/// `render.wgsl`'s DDA walk.
pub struct GpuVdi<'g> {
    gpu: &'g Gpu,
    offsets: wgpu::Buffer,
    segments: wgpu::Buffer,
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
        let limit = gpu.max_storage_binding();
        let seg_bytes = vdi.supersegments().len() as u64 * 24;
        let off_bytes = vdi.offsets().len() as u64 * 4;
        for (what, bytes) in [("VDI supersegments", seg_bytes), ("VDI offsets", off_bytes)] {
            if bytes > limit {
                return Err(GpuError::Limit {
                    what: what.into(),
                    needed: bytes,
                    limit,
                    name: "max_storage_buffer_binding_size",
                });
            }
        }
        gpu.scoped("uploading the VDI", || {
            let offsets = gpu.buffer_init(
                "vdi offsets",
                &u32_bytes(vdi.offsets().iter().copied()),
                wgpu::BufferUsages::STORAGE,
            );
            let segments = gpu.buffer_init(
                "vdi supersegments",
                &f32_bytes(vdi.supersegments().iter().flat_map(|s| {
                    [
                        s.z_start, s.z_end, s.color[0], s.color[1], s.color[2], s.alpha,
                    ]
                })),
                wgpu::BufferUsages::STORAGE,
            );
            let meta = vdi.meta();
            Ok(Self {
                gpu,
                offsets,
                segments,
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
        let rows = band_rows(gpu, width, 12, "rendered image row")?;
        let mut image = Image::new(width, height);
        let mut kernel_s = Some(0.0);
        let mut row0 = 0;
        while row0 < height {
            let n = rows.min(height - row0);
            let uniform = Uniform::default()
                .vec4([f.eye.x, f.eye.y, f.eye.z, 0.0])
                .vec4([f.right.x, f.right.y, f.right.z, f.tan_half_x])
                .vec4([f.up.x, f.up.y, f.up.z, f.tan_half_y])
                .vec4([f.forward.x, f.forward.y, f.forward.z, termination])
                .vec4([g.eye.x, g.eye.y, g.eye.z, 0.0])
                .vec4([g.right.x, g.right.y, g.right.z, g.tan_half_x])
                .vec4([g.up.x, g.up.y, g.up.z, g.tan_half_y])
                .vec4([g.forward.x, g.forward.y, g.forward.z, 0.0])
                .vec4([b.min.x, b.min.y, b.min.z, 0.0])
                .vec4([b.max.x, b.max.y, b.max.z, 0.0])
                .uvec4([width, height, row0, r]);
            let params = gpu.buffer_init(
                "render params",
                uniform.bytes(),
                wgpu::BufferUsages::UNIFORM,
            );
            let bytes = u64::from(width) * u64::from(n) * 12;
            let out = gpu.storage("render image", bytes);
            let group = gpu.device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("render"),
                layout: &gpu.kernels.render_layout,
                entries: &[
                    wgpu::BindGroupEntry {
                        binding: 0,
                        resource: params.as_entire_binding(),
                    },
                    wgpu::BindGroupEntry {
                        binding: 1,
                        resource: self.offsets.as_entire_binding(),
                    },
                    wgpu::BindGroupEntry {
                        binding: 2,
                        resource: self.segments.as_entire_binding(),
                    },
                    wgpu::BindGroupEntry {
                        binding: 3,
                        resource: out.as_entire_binding(),
                    },
                ],
            });
            let t = gpu.dispatch(
                "render",
                &gpu.kernels.render,
                &[&group],
                [width.div_ceil(8), n.div_ceil(8), 1],
            )?;
            kernel_s = kernel_s.zip(t).map(|(a, b)| a + b);
            let values = to_f32s(&gpu.read(&out, bytes)?);
            let start = (row0 * width) as usize;
            for (p, rgb) in image.pixels_mut()[start..]
                .iter_mut()
                .zip(values.chunks_exact(3))
            {
                *p = [rgb[0], rgb[1], rgb[2]];
            }
            row0 += n;
        }
        Ok(KernelRun {
            value: image,
            kernel_s,
        })
    }
}
