//! Density splatting on the GPU (Iwasaki et al., §4.1-4.2): for each group of four z planes,
//! the particles of the group's z-cluster are drawn as instanced squares; the fragment shader
//! adds each particle's kernel for the four planes into the R, G, B and A channels of an
//! `Rgba32Float` target with additive blending; the target is copied back. Only one group's
//! target (and a batch of read-back copies) lives on the GPU, not the grid.

use bytemuck::{Pod, Zeroable};
use glam::Vec3;

use super::{GpuContext, GpuError};
use crate::density::{DensityGrid, GridSpec, Kernel};

/// The shader's `Params`, std140-compatible: 64 bytes (checked against the WGSL in a test).
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
pub struct RawParams {
    pub origin: [f32; 3],
    pub spacing: f32,
    pub dims: [f32; 2],
    pub h: f32,
    pub constant: f32,
    pub planes: [f32; 4],
    pub kernel: u32,
    pub _pad: [u32; 3],
}

const _: () = assert!(std::mem::size_of::<RawParams>() == 64);

/// The WGSL source of the splatting pass.
pub const SHADER: &str = include_str!("../../shaders/density_splat.wgsl");

/// Planes per pass: one per channel of an RGBA target.
const PLANES: u32 = 4;
/// Groups read back per submission.
const BATCH: u32 = 8;

fn kernel_constant(kernel: Kernel, h: f32) -> f32 {
    match kernel {
        // the same expressions as `Kernel::value_r2` / `Kernel::value`
        Kernel::Wyvill => 2835.0 / (736.0 * std::f32::consts::PI * h * h * h),
        Kernel::CubicSpline => 8.0 / (std::f32::consts::PI * h * h * h),
    }
}

/// Fills the density grid on the GPU and hands slabs of four planes to `sink(k0, values)` in
/// increasing z, like [`crate::density::splat_slabs`].
pub fn splat_slabs_gpu(
    ctx: &GpuContext,
    positions: &[Vec3],
    spec: &GridSpec,
    kernel: Kernel,
    h: f32,
    mut sink: impl FnMut(u32, Vec<f32>),
) -> Result<(), GpuError> {
    if !(h.is_finite() && h > 0.0) || positions.iter().any(|p| !p.is_finite()) {
        return Err(GpuError::Validation(
            "h must be finite and > 0 and positions finite".into(),
        ));
    }
    let device = &ctx.device;
    let [nx, ny, nz] = spec.dims;
    let max_dim = device.limits().max_texture_dimension_2d;
    if nx > max_dim || ny > max_dim {
        return Err(GpuError::Validation(format!(
            "a {nx} x {ny} plane exceeds the GPU's {max_dim} texture size"
        )));
    }
    let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
    // particles sorted by z: each group's cluster is a contiguous instance range (§4.2)
    let mut sorted: Vec<[f32; 4]> = positions.iter().map(|p| [p.x, p.y, p.z, 0.0]).collect();
    sorted.sort_by(|a, b| a[2].total_cmp(&b[2]));
    let zs: Vec<f32> = sorted.iter().map(|p| p[2]).collect();
    use wgpu::util::DeviceExt;
    let instances = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
        label: Some("particles"),
        contents: bytemuck::cast_slice(if sorted.is_empty() {
            &[[0.0f32; 4]]
        } else {
            &sorted[..]
        }),
        usage: wgpu::BufferUsages::VERTEX,
    });
    let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
        label: Some("density_splat"),
        source: wgpu::ShaderSource::Wgsl(SHADER.into()),
    });
    let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
        label: Some("density params"),
        entries: &[wgpu::BindGroupLayoutEntry {
            binding: 0,
            visibility: wgpu::ShaderStages::VERTEX_FRAGMENT,
            ty: wgpu::BindingType::Buffer {
                ty: wgpu::BufferBindingType::Uniform,
                has_dynamic_offset: false,
                min_binding_size: None,
            },
            count: None,
        }],
    });
    let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
        label: Some("density"),
        bind_group_layouts: &[Some(&layout)],
        ..Default::default()
    });
    let additive = wgpu::BlendComponent {
        src_factor: wgpu::BlendFactor::One,
        dst_factor: wgpu::BlendFactor::One,
        operation: wgpu::BlendOperation::Add,
    };
    let pipeline = device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
        label: Some("density splat"),
        layout: Some(&pipeline_layout),
        vertex: wgpu::VertexState {
            module: &module,
            entry_point: Some("vs_main"),
            compilation_options: Default::default(),
            buffers: &[Some(wgpu::VertexBufferLayout {
                array_stride: 16,
                step_mode: wgpu::VertexStepMode::Instance,
                attributes: &wgpu::vertex_attr_array![0 => Float32x4],
            })],
        },
        primitive: wgpu::PrimitiveState::default(),
        depth_stencil: None,
        multisample: wgpu::MultisampleState::default(),
        fragment: Some(wgpu::FragmentState {
            module: &module,
            entry_point: Some("fs_main"),
            compilation_options: Default::default(),
            targets: &[Some(wgpu::ColorTargetState {
                format: wgpu::TextureFormat::Rgba32Float,
                blend: Some(wgpu::BlendState {
                    color: additive,
                    alpha: additive,
                }),
                write_mask: wgpu::ColorWrites::ALL,
            })],
        }),
        multiview_mask: None,
        cache: None,
    });
    let target = device.create_texture(&wgpu::TextureDescriptor {
        label: Some("density planes"),
        size: wgpu::Extent3d {
            width: nx,
            height: ny,
            depth_or_array_layers: 1,
        },
        mip_level_count: 1,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D2,
        format: wgpu::TextureFormat::Rgba32Float,
        usage: wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC,
        view_formats: &[],
    });
    let view = target.create_view(&wgpu::TextureViewDescriptor::default());
    let row_bytes = (nx as u64 * 16).div_ceil(256) * 256;
    let group_bytes = row_bytes * ny as u64;
    let groups: Vec<u32> = (0..nz).step_by(PLANES as usize).collect();
    let constant = kernel_constant(kernel, h);
    for batch in groups.chunks(BATCH as usize) {
        let readback = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("density readback"),
            size: group_bytes * batch.len() as u64,
            usage: wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::MAP_READ,
            mapped_at_creation: false,
        });
        let mut encoder = device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some("density"),
        });
        let mut keep = Vec::new();
        for (slot, &k0) in batch.iter().enumerate() {
            let planes: [f32; 4] =
                std::array::from_fn(|c| spec.origin.z + (k0 + c as u32) as f32 * spec.spacing);
            let raw = RawParams {
                origin: spec.origin.to_array(),
                spacing: spec.spacing,
                dims: [nx as f32, ny as f32],
                h,
                constant,
                planes,
                kernel: match kernel {
                    Kernel::Wyvill => 0,
                    Kernel::CubicSpline => 1,
                },
                _pad: [0; 3],
            };
            let uniform = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("density params"),
                contents: bytemuck::bytes_of(&raw),
                usage: wgpu::BufferUsages::UNIFORM,
            });
            let bind = device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("density params"),
                layout: &layout,
                entries: &[wgpu::BindGroupEntry {
                    binding: 0,
                    resource: uniform.as_entire_binding(),
                }],
            });
            // z-cluster of the four planes (§4.2)
            let last = (k0 + PLANES - 1).min(nz - 1);
            let z_lo = spec.origin.z + k0 as f32 * spec.spacing - h;
            let z_hi = spec.origin.z + last as f32 * spec.spacing + h;
            let a = zs.partition_point(|&z| z <= z_lo) as u32;
            let b = zs.partition_point(|&z| z < z_hi) as u32;
            {
                let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
                    label: Some("density planes"),
                    color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                        view: &view,
                        depth_slice: None,
                        resolve_target: None,
                        ops: wgpu::Operations {
                            load: wgpu::LoadOp::Clear(wgpu::Color::TRANSPARENT),
                            store: wgpu::StoreOp::Store,
                        },
                    })],
                    ..Default::default()
                });
                if b > a {
                    pass.set_pipeline(&pipeline);
                    pass.set_bind_group(0, &bind, &[]);
                    pass.set_vertex_buffer(0, instances.slice(..));
                    pass.draw(0..6, a..b);
                }
            }
            encoder.copy_texture_to_buffer(
                wgpu::TexelCopyTextureInfo {
                    texture: &target,
                    mip_level: 0,
                    origin: wgpu::Origin3d::ZERO,
                    aspect: wgpu::TextureAspect::All,
                },
                wgpu::TexelCopyBufferInfo {
                    buffer: &readback,
                    layout: wgpu::TexelCopyBufferLayout {
                        offset: group_bytes * slot as u64,
                        bytes_per_row: Some(row_bytes as u32),
                        rows_per_image: Some(ny),
                    },
                },
                wgpu::Extent3d {
                    width: nx,
                    height: ny,
                    depth_or_array_layers: 1,
                },
            );
            keep.push((uniform, bind));
        }
        ctx.queue.submit([encoder.finish()]);
        let slice = readback.slice(..);
        let (tx, rx) = std::sync::mpsc::channel();
        slice.map_async(wgpu::MapMode::Read, move |r| {
            let _ = tx.send(r);
        });
        device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| GpuError::Readback(e.to_string()))?;
        rx.recv()
            .map_err(|e| GpuError::Readback(e.to_string()))?
            .map_err(|e| GpuError::Readback(e.to_string()))?;
        {
            let data = slice
                .get_mapped_range()
                .map_err(|e| GpuError::Readback(format!("{e:?}")))?;
            let floats: &[f32] = bytemuck::cast_slice(&data);
            let row_floats = (row_bytes / 4) as usize;
            for (slot, &k0) in batch.iter().enumerate() {
                let planes = PLANES.min(nz - k0) as usize;
                let plane = nx as usize * ny as usize;
                let mut slab = vec![0.0f32; plane * planes];
                let base = slot * (group_bytes / 4) as usize;
                for j in 0..ny as usize {
                    let row =
                        &floats[base + j * row_floats..base + j * row_floats + 4 * nx as usize];
                    for i in 0..nx as usize {
                        for c in 0..planes {
                            slab[c * plane + j * nx as usize + i] = row[4 * i + c];
                        }
                    }
                }
                if let Some(bad) = slab.iter().position(|v| !v.is_finite()) {
                    return Err(GpuError::Readback(format!(
                        "non-finite density at slab {k0}, value {bad}"
                    )));
                }
                sink(k0, slab);
            }
        }
        readback.unmap();
    }
    if let Some(e) = pollster::block_on(scope.pop()) {
        return Err(GpuError::Validation(e.to_string()));
    }
    Ok(())
}

/// The whole density grid on the GPU.
pub fn density_grid_gpu(
    ctx: &GpuContext,
    positions: &[Vec3],
    spec: &GridSpec,
    kernel: Kernel,
    h: f32,
) -> Result<DensityGrid, GpuError> {
    let mut values = Vec::with_capacity(spec.cells() as usize);
    splat_slabs_gpu(ctx, positions, spec, kernel, h, |_, slab| {
        values.extend_from_slice(&slab)
    })?;
    Ok(DensityGrid {
        spec: *spec,
        values,
    })
}
