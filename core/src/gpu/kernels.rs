//! The WGSL kernels, their bind-group layouts and pipelines, compiled once per device.
//! Shading is a pipeline-overridable constant: scenes without it run code with no shading
//! in it at all.

use super::GpuError;

const PRELUDE: &str = include_str!("shaders/prelude.wgsl");
const COMMON: &str = include_str!("shaders/common.wgsl");
const DVR: &str = include_str!("shaders/dvr.wgsl");
const GENERATE: &str = include_str!("shaders/generate.wgsl");
const SCAN: &str = include_str!("shaders/scan.wgsl");
const RENDER: &str = include_str!("shaders/render.wgsl");

/// Layouts and pipelines of every kernel.
pub(super) struct Kernels {
    pub scene_layout: wgpu::BindGroupLayout,
    pub dvr_out_layout: wgpu::BindGroupLayout,
    pub generate_out_layout: wgpu::BindGroupLayout,
    pub scan_layout: wgpu::BindGroupLayout,
    pub render_layout: wgpu::BindGroupLayout,
    /// Indexed by `shaded as usize`.
    pub dvr: [wgpu::ComputePipeline; 2],
    pub generate: [wgpu::ComputePipeline; 2],
    /// The prefix sum's three passes: blocks, block totals, block offsets added back.
    pub scan: [wgpu::ComputePipeline; 3],
    pub render: wgpu::ComputePipeline,
}

fn entry(binding: u32, ty: wgpu::BindingType) -> wgpu::BindGroupLayoutEntry {
    wgpu::BindGroupLayoutEntry {
        binding,
        visibility: wgpu::ShaderStages::COMPUTE,
        ty,
        count: None,
    }
}

fn uniform(binding: u32) -> wgpu::BindGroupLayoutEntry {
    entry(
        binding,
        wgpu::BindingType::Buffer {
            ty: wgpu::BufferBindingType::Uniform,
            has_dynamic_offset: false,
            min_binding_size: None,
        },
    )
}

fn storage(binding: u32, read_only: bool) -> wgpu::BindGroupLayoutEntry {
    entry(
        binding,
        wgpu::BindingType::Buffer {
            ty: wgpu::BufferBindingType::Storage { read_only },
            has_dynamic_offset: false,
            min_binding_size: None,
        },
    )
}

fn texture(binding: u32, view_dimension: wgpu::TextureViewDimension) -> wgpu::BindGroupLayoutEntry {
    entry(
        binding,
        wgpu::BindingType::Texture {
            sample_type: wgpu::TextureSampleType::Float { filterable: false },
            view_dimension,
            multisampled: false,
        },
    )
}

/// The WGSL module of `parts` concatenated.
fn shader_module(device: &wgpu::Device, label: &str, parts: &[&str]) -> wgpu::ShaderModule {
    device.create_shader_module(wgpu::ShaderModuleDescriptor {
        label: Some(label),
        source: wgpu::ShaderSource::Wgsl(parts.concat().into()),
    })
}

/// The compute pipeline of `entry_point` in `module`, with bind groups `layouts` (in order)
/// and the pipeline-overridable `constants`.
fn compute_pipeline(
    device: &wgpu::Device,
    label: &str,
    module: &wgpu::ShaderModule,
    entry_point: &str,
    layouts: &[&wgpu::BindGroupLayout],
    constants: &[(&str, f64)],
) -> wgpu::ComputePipeline {
    let layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
        label: Some(label),
        bind_group_layouts: &layouts.iter().map(|l| Some(*l)).collect::<Vec<_>>(),
        immediate_size: 0,
    });
    device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
        label: Some(label),
        layout: Some(&layout),
        module,
        entry_point: Some(entry_point),
        compilation_options: wgpu::PipelineCompilationOptions {
            constants,
            ..Default::default()
        },
        cache: None,
    })
}

impl Kernels {
    pub(super) fn new(device: &wgpu::Device) -> Result<Self, GpuError> {
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
        let layout = |label: &str, entries: &[wgpu::BindGroupLayoutEntry]| {
            device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
                label: Some(label),
                entries,
            })
        };
        let scene_layout = layout(
            "scene",
            &[
                uniform(0),
                texture(1, wgpu::TextureViewDimension::D3),
                texture(2, wgpu::TextureViewDimension::D1),
                texture(3, wgpu::TextureViewDimension::D1),
                storage(4, true),
            ],
        );
        let dvr_out_layout = layout("dvr out", &[storage(0, false)]);
        let generate_out_layout = layout(
            "generate out",
            &[storage(0, false), storage(1, false), storage(2, false)],
        );
        let scan_layout = layout("scan", &[uniform(0), storage(1, false), storage(2, false)]);
        let render_layout = layout(
            "render",
            &[
                uniform(0),
                storage(1, true),
                storage(2, true),
                storage(3, false),
                storage(4, true),
            ],
        );
        let dvr_module = shader_module(device, "dvr", &[PRELUDE, COMMON, DVR]);
        let generate_module = shader_module(device, "generate", &[PRELUDE, COMMON, GENERATE]);
        let scan_module = shader_module(device, "scan", &[SCAN]);
        let render_module = shader_module(device, "render", &[PRELUDE, RENDER]);
        let shade = |on: bool| [("SHADE", if on { 1.0 } else { 0.0 })];
        let dvr = [false, true].map(|on| {
            compute_pipeline(
                device,
                "dvr",
                &dvr_module,
                "dvr_main",
                &[&scene_layout, &dvr_out_layout],
                &shade(on),
            )
        });
        let generate = [false, true].map(|on| {
            compute_pipeline(
                device,
                "generate",
                &generate_module,
                "generate_main",
                &[&scene_layout, &generate_out_layout],
                &shade(on),
            )
        });
        let scan = ["scan_blocks", "scan_sums", "scan_add"].map(|entry_point| {
            compute_pipeline(
                device,
                entry_point,
                &scan_module,
                entry_point,
                &[&scan_layout],
                &[],
            )
        });
        let render = compute_pipeline(
            device,
            "render",
            &render_module,
            "render_main",
            &[&render_layout],
            &[],
        );
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(GpuError::Validation(format!("compiling the kernels: {e}")));
        }
        Ok(Self {
            scene_layout,
            dvr_out_layout,
            generate_out_layout,
            scan_layout,
            render_layout,
            dvr,
            generate,
            scan,
            render,
        })
    }
}
