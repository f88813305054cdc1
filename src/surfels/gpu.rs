//! Surfels on the GPU (issue 37, first part), the twin of [`super::cpu`]: the crossings of the
//! iso-value on the grid's edges, compacted by a prefix sum in the CPU's order (surfel `n` is
//! the CPU's surfel `n`), projected onto the exact iso-surface by Newton steps along the
//! analytic gradient of the points' density (the points binned as the density's gather pass bins
//! them), radii the grid spacing. Four compute passes (`shaders/surfels.wgsl`): `count` (the
//! crossings each grid point owns, summed per block of 256 points), `scan_blocks` (each block's
//! first surfel), `emit` (the crossings), `project`.
//!
//! The grid comes from the CPU, dense ([`SurfelPasses::extract`]) or sparse (only its evaluated
//! blocks, [`SurfelPasses::extract_sparse`]), or stays on the GPU where the gather
//! pass filled it ([`SurfelPasses::extract_on`] with
//! [`crate::density::gpu::density_grid_on_gpu`]). The surfels are handed back (a read-back of
//! the count between the passes sizes their buffers); leaving them on the GPU for the splatting,
//! with no read-back on the frame path, is the next part of issue 37.

use bytemuck::{Pod, Zeroable};
use glam::Vec3;

use super::{CONVERGED, SurfelParams, Surfels, iso_of};
use crate::density::gpu::GpuGrid;
use crate::density::{DensityGrid, GridSpec, Kernel, Points, SparseGrid};
use crate::gpu::{self, GpuContext, GpuError};

/// The shader's `SurfelParams`, std140-compatible: 96 bytes (checked against the WGSL in a
/// test).
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
pub struct RawSurfelParams {
    pub origin: [f32; 3],
    pub spacing: f32,
    pub dims: [u32; 3],
    pub iso: f32,
    pub bin_origin: [f32; 3],
    pub bin_size: f32,
    pub bins: [u32; 3],
    pub reach: u32,
    pub h: f32,
    pub constant: f32,
    pub kernel: u32,
    pub newton_steps: u32,
    pub blocks: u32,
    pub converged: f32,
    pub sparse_block: u32,
    pub inside: f32,
}

const _: () = assert!(std::mem::size_of::<RawSurfelParams>() == 96);

/// The WGSL source of the passes (`common.wgsl` prepended).
pub const SHADER: &str = concat!(
    include_str!("../../shaders/common.wgsl"),
    include_str!("../../shaders/surfels.wgsl")
);

/// Grid points per block of the prefix sum (the workgroup size of `count` and `emit`).
const BLOCK: u32 = 256;
/// Surfels per workgroup of `project`.
const PROJECT_GROUP: u32 = 64;
/// Most workgroups along one dimension of a dispatch (WebGPU's default limit).
const MAX_GROUPS: u32 = 65_535;

/// A two-dimensional dispatch of at least `groups` workgroups.
fn dispatch_size(groups: u32) -> (u32, u32) {
    let x = groups.clamp(1, MAX_GROUPS);
    (x, groups.div_ceil(x))
}

/// Storage buffer of `bytes` (at least 16) with `usage` besides `STORAGE`.
fn storage(
    device: &wgpu::Device,
    label: &str,
    bytes: u64,
    usage: wgpu::BufferUsages,
) -> wgpu::Buffer {
    device.create_buffer(&wgpu::BufferDescriptor {
        label: Some(label),
        size: bytes.max(16),
        usage: wgpu::BufferUsages::STORAGE | usage,
        mapped_at_creation: false,
    })
}

/// The surfels of `grid` on the GPU: the same as [`super::extract_points`] (counts equal,
/// positions and normals within float rounding of the sums' order). Errors: the CPU's for bad
/// parameters or points, points with weights (not on the GPU yet), a grid or points beyond the
/// adapter's storage binding limit, and the device's own. Compiles the passes each call; a
/// sequence keeps a [`SurfelPasses`].
pub fn extract_gpu(
    ctx: &GpuContext,
    grid: &DensityGrid,
    points: Points<'_>,
    kernel: Kernel,
    params: &SurfelParams,
) -> Result<Surfels, crate::Error> {
    SurfelPasses::new(&ctx.device).extract(ctx, grid, points, kernel, params)
}

/// The four compute pipelines and their bind group layout, made once per device.
pub struct SurfelPasses {
    layout: wgpu::BindGroupLayout,
    count: wgpu::ComputePipeline,
    scan_blocks: wgpu::ComputePipeline,
    emit: wgpu::ComputePipeline,
    project: wgpu::ComputePipeline,
}

/// What the passes read: the parameters, the grid, the binned points, the bins' starts and a
/// sparse grid's block states, uploaded; the block sums and the count, allocated.
struct Inputs {
    raw: RawSurfelParams,
    buffers: [wgpu::Buffer; 7],
    max_binding: u64,
}

impl SurfelPasses {
    /// Compiles the passes for `device`.
    #[must_use]
    pub fn new(device: &wgpu::Device) -> Self {
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("surfels"),
            source: wgpu::ShaderSource::Wgsl(SHADER.into()),
        });
        let layout = bind_group_layout(device);
        let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("surfels"),
            bind_group_layouts: &[Some(&layout)],
            ..Default::default()
        });
        let pipeline = |entry: &str| {
            device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(entry),
                layout: Some(&pipeline_layout),
                module: &module,
                entry_point: Some(entry),
                compilation_options: Default::default(),
                cache: None,
            })
        };
        Self {
            count: pipeline("count"),
            scan_blocks: pipeline("scan_blocks"),
            emit: pipeline("emit"),
            project: pipeline("project"),
            layout,
        }
    }

    /// [`extract_gpu`] with these passes.
    pub fn extract(
        &self,
        ctx: &GpuContext,
        grid: &DensityGrid,
        points: Points<'_>,
        kernel: Kernel,
        params: &SurfelParams,
    ) -> Result<Surfels, crate::Error> {
        self.extract_from(ctx, GridIn::Cpu(grid), points, kernel, params)
    }

    /// The surfels of a sparse grid (only its evaluated blocks uploaded, read through its block
    /// states): the same as [`super::extract_sparse`], in the dense grid's order.
    pub fn extract_sparse(
        &self,
        ctx: &GpuContext,
        grid: &SparseGrid,
        points: Points<'_>,
        kernel: Kernel,
        params: &SurfelParams,
    ) -> Result<Surfels, crate::Error> {
        self.extract_from(ctx, GridIn::Sparse(grid), points, kernel, params)
    }

    /// The surfels of a grid that lives on the GPU ([`crate::density::gpu::density_grid_on_gpu`]):
    /// the grid is read where it is, never copied back.
    pub fn extract_on(
        &self,
        ctx: &GpuContext,
        grid: &GpuGrid,
        points: Points<'_>,
        kernel: Kernel,
        params: &SurfelParams,
    ) -> Result<Surfels, crate::Error> {
        self.extract_from(ctx, GridIn::Gpu(grid), points, kernel, params)
    }

    fn extract_from(
        &self,
        ctx: &GpuContext,
        grid: GridIn<'_>,
        points: Points<'_>,
        kernel: Kernel,
        params: &SurfelParams,
    ) -> Result<Surfels, crate::Error> {
        let iso = iso_of(points.h, kernel, params)?;
        let empty = Surfels {
            iso,
            ..Surfels::default()
        };
        let scope = ctx.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let Some(inputs) = upload(ctx, grid, points, kernel, params, iso)? else {
            return finish(scope, empty);
        };
        let device = &ctx.device;
        let bind = |positions: &wgpu::Buffer, normals: &wgpu::Buffer| {
            let [
                uniform,
                values,
                block_sums,
                total,
                binned,
                bin_start,
                states,
            ] = &inputs.buffers;
            let buffers = [
                uniform, values, block_sums, total, positions, normals, binned, bin_start, states,
            ];
            let entries: Vec<wgpu::BindGroupEntry<'_>> = buffers
                .iter()
                .enumerate()
                .map(|(i, b)| wgpu::BindGroupEntry {
                    binding: i as u32,
                    resource: b.as_entire_binding(),
                })
                .collect();
            device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("surfels"),
                layout: &self.layout,
                entries: &entries,
            })
        };
        let run = |passes: &[(&wgpu::ComputePipeline, (u32, u32))], bind: &wgpu::BindGroup| {
            let mut encoder = device.create_command_encoder(&Default::default());
            for (pipeline, (x, y)) in passes {
                let mut pass = encoder.begin_compute_pass(&Default::default());
                pass.set_pipeline(pipeline);
                pass.set_bind_group(0, bind, &[]);
                pass.dispatch_workgroups(*x, *y, 1);
            }
            ctx.queue.submit([encoder.finish()]);
        };
        // the count, read back to size the surfels' buffers (the next part of issue 37 bounds
        // it beforehand instead)
        let placeholder = storage(
            device,
            "surfel placeholder",
            16,
            wgpu::BufferUsages::empty(),
        );
        let points_dispatch = dispatch_size(inputs.raw.blocks);
        run(
            &[(&self.count, points_dispatch), (&self.scan_blocks, (1, 1))],
            &bind(&placeholder, &placeholder),
        );
        let surfels = gpu::read_buffer::<u32>(ctx, &inputs.buffers[3])?[0];
        if surfels == 0 {
            return finish(scope, empty);
        }
        let bytes = u64::from(surfels) * 16;
        if bytes > inputs.max_binding {
            return Err(GpuError::Validation(format!(
                "{surfels} surfels exceed the GPU's storage binding limit of {} bytes; extract them on the CPU",
                inputs.max_binding
            ))
            .into());
        }
        let positions = storage(
            device,
            "surfel positions",
            bytes,
            wgpu::BufferUsages::COPY_SRC,
        );
        let normals = storage(
            device,
            "surfel normals",
            bytes,
            wgpu::BufferUsages::COPY_SRC,
        );
        run(
            &[
                (&self.count, points_dispatch),
                (&self.scan_blocks, (1, 1)),
                (&self.emit, points_dispatch),
                (
                    &self.project,
                    dispatch_size(surfels.div_ceil(PROJECT_GROUP)),
                ),
            ],
            &bind(&positions, &normals),
        );
        let xyz = |v: Vec<[f32; 4]>| -> Vec<Vec3> {
            v.iter().map(|p| Vec3::new(p[0], p[1], p[2])).collect()
        };
        let positions = xyz(gpu::read_buffer::<[f32; 4]>(ctx, &positions)?);
        let normals = xyz(gpu::read_buffer::<[f32; 4]>(ctx, &normals)?);
        if let Some(bad) = positions.iter().position(|p| !p.is_finite()) {
            return Err(GpuError::Readback(format!("surfel {bad} is not finite")).into());
        }
        finish(
            scope,
            Surfels {
                radii: vec![grid.spec().spacing; positions.len()],
                positions,
                normals,
                iso,
            },
        )
    }
}

/// Where the passes read the grid.
#[derive(Clone, Copy)]
enum GridIn<'a> {
    /// Values on the CPU, uploaded.
    Cpu(&'a DensityGrid),
    /// Values already on the GPU.
    Gpu(&'a GpuGrid),
    /// A sparse grid's evaluated blocks and block states, uploaded.
    Sparse(&'a SparseGrid),
}

impl GridIn<'_> {
    fn spec(self) -> GridSpec {
        match self {
            Self::Cpu(g) => g.spec,
            Self::Gpu(g) => g.spec,
            Self::Sparse(g) => g.spec,
        }
    }
}

/// Checks the inputs and uploads them; `None` when there is nothing to extract (no grid point
/// or no point).
fn upload(
    ctx: &GpuContext,
    grid: GridIn<'_>,
    points: Points<'_>,
    kernel: Kernel,
    params: &SurfelParams,
    iso: f32,
) -> Result<Option<Inputs>, crate::Error> {
    points.check()?;
    if points.weights.is_some_and(|w| w.iter().any(|&x| x != 1.0)) {
        return Err(GpuError::Validation(
            "the GPU surfels do not take per-point weights yet; extract these on the CPU".into(),
        )
        .into());
    }
    let spec = grid.spec();
    let n = spec.cells();
    if n == 0 || points.is_empty() {
        return Ok(None);
    }
    let device = &ctx.device;
    let limits = device.limits();
    let max_binding = limits
        .max_storage_buffer_binding_size
        .min(limits.max_buffer_size);
    let value_bytes = match grid {
        GridIn::Sparse(g) => 4 * g.raw().1.len().max(g.raw().0.len()) as u128,
        _ => n * 4,
    };
    if value_bytes > u128::from(max_binding) || n > u128::from(u32::MAX) {
        return Err(GpuError::Validation(format!(
            "a grid of {n} points exceeds the GPU's storage binding limit of {max_binding} bytes; extract its surfels on the CPU"
        ))
        .into());
    }
    if let GridIn::Gpu(g) = grid
        && u128::from(g.values.size()) < n * 4
    {
        return Err(GpuError::Validation(format!(
            "the GPU grid's buffer holds {} bytes, not the {} of its {n} points",
            g.values.size(),
            n * 4
        ))
        .into());
    }
    let (sorted, start, bins, bin_size) = crate::density::gpu::bin_particles(
        &points,
        &spec,
        points.max_radius(),
        crate::density::gpu::GATHER_REACH,
    );
    if (sorted.len() * 16) as u64 > max_binding || (start.len() * 4) as u64 > max_binding {
        return Err(GpuError::Validation(format!(
            "{} points exceed the GPU's storage binding limit of {max_binding} bytes; extract these surfels on the CPU",
            points.len()
        ))
        .into());
    }
    let blocks = (n as u32).div_ceil(BLOCK);
    let raw = RawSurfelParams {
        origin: spec.origin.to_array(),
        spacing: spec.spacing,
        dims: spec.dims,
        iso,
        bin_origin: spec.origin.to_array(),
        bin_size,
        bins,
        reach: crate::density::gpu::GATHER_REACH,
        h: points.h,
        constant: crate::density::gpu::kernel_constant(kernel, points.h),
        kernel: crate::density::gpu::kernel_code(kernel),
        newton_steps: params.newton_steps,
        blocks,
        converged: CONVERGED,
        sparse_block: match grid {
            GridIn::Sparse(_) => crate::density::sparse::BLOCK,
            _ => 0,
        },
        inside: match grid {
            GridIn::Sparse(g) => g.inside,
            _ => 0.0,
        },
    };
    use wgpu::util::DeviceExt;
    let init = |label: &str, contents: &[u8], usage: wgpu::BufferUsages| {
        device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some(label),
            contents,
            usage,
        })
    };
    let buffers = [
        init(
            "surfel params",
            bytemuck::bytes_of(&raw),
            wgpu::BufferUsages::UNIFORM,
        ),
        match grid {
            GridIn::Cpu(g) => init(
                "surfel grid",
                bytemuck::cast_slice(&g.values),
                wgpu::BufferUsages::STORAGE,
            ),
            GridIn::Gpu(g) => g.values.clone(),
            GridIn::Sparse(g) => init(
                "surfel sparse grid",
                bytemuck::cast_slice(if g.raw().1.is_empty() {
                    &[0.0f32]
                } else {
                    g.raw().1
                }),
                wgpu::BufferUsages::STORAGE,
            ),
        },
        storage(
            device,
            "surfel block sums",
            u64::from(blocks) * 4,
            wgpu::BufferUsages::empty(),
        ),
        storage(device, "surfel count", 16, wgpu::BufferUsages::COPY_SRC),
        init(
            "surfel points",
            bytemuck::cast_slice(&sorted),
            wgpu::BufferUsages::STORAGE,
        ),
        init(
            "surfel bins",
            bytemuck::cast_slice(&start),
            wgpu::BufferUsages::STORAGE,
        ),
        match grid {
            GridIn::Sparse(g) => init(
                "surfel block states",
                bytemuck::cast_slice(g.raw().0),
                wgpu::BufferUsages::STORAGE,
            ),
            _ => storage(
                device,
                "surfel no block states",
                16,
                wgpu::BufferUsages::empty(),
            ),
        },
    ];
    Ok(Some(Inputs {
        raw,
        buffers,
        max_binding,
    }))
}

/// The surfels, or the validation error the device reported meanwhile.
fn finish(scope: wgpu::ErrorScopeGuard, surfels: Surfels) -> Result<Surfels, crate::Error> {
    match pollster::block_on(scope.pop()) {
        Some(e) => Err(GpuError::Validation(e.to_string()).into()),
        None => Ok(surfels),
    }
}

/// The passes' bindings: the parameters, the grid, the block sums, the count, the positions,
/// the normals, the binned points, the bins' starts and a sparse grid's block states.
fn bind_group_layout(device: &wgpu::Device) -> wgpu::BindGroupLayout {
    let read_only = [false, true, false, false, false, false, true, true, true];
    let entries: Vec<wgpu::BindGroupLayoutEntry> = read_only
        .iter()
        .enumerate()
        .map(|(i, &read_only)| wgpu::BindGroupLayoutEntry {
            binding: i as u32,
            visibility: wgpu::ShaderStages::COMPUTE,
            ty: wgpu::BindingType::Buffer {
                ty: if i == 0 {
                    wgpu::BufferBindingType::Uniform
                } else {
                    wgpu::BufferBindingType::Storage { read_only }
                },
                has_dynamic_offset: false,
                min_binding_size: None,
            },
            count: None,
        })
        .collect();
    device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
        label: Some("surfels"),
        entries: &entries,
    })
}
