//! Surfels on the GPU (issue 37), the twin of [`super::cpu`]: the crossings of the iso-value
//! on the grid's edges, compacted by a prefix sum in the CPU's order (surfel `n` is the CPU's
//! surfel `n`), projected onto the exact iso-surface by Newton steps along the analytic
//! gradient of the points' density (the points binned as the density's gather pass bins them,
//! [`BinnedPoints`], each with its radius and weight), disks of the grid's spacing. Four
//! compute passes (`shaders/surfels.wgsl`): `count` (the crossings each grid point owns, summed
//! per block of 256 points), `scan_blocks` (each block's first surfel), `emit` (the crossings),
//! `project`.
//!
//! The grid ([`SurfelGrid`]) comes from the CPU, dense or sparse (only its evaluated blocks),
//! or stays on the GPU where the gather pass filled it
//! ([`crate::density::gpu::density_grid_on_gpu`]), with its points binned there.
//! [`SurfelPasses::extract`] hands the surfels back (a read-back of the count between the
//! passes sizes their buffer). For a frame path, [`ResidentSurfels`] keeps them on the GPU:
//! recorded into the caller's encoder with the grid of a [`crate::density::gpu::GridFiller`],
//! `project` dispatched indirectly, the count read back asynchronously to grow the buffers,
//! nothing created after the first frames and nothing waited on;
//! [`ResidentSurfels::surfel_buffer`] hands them to the splatting as they are (an indirect
//! draw). `pipeline::GpuPipeline::prepare` records both into a game's frame, drawn by its
//! splatting and optics.

use bytemuck::{Pod, Zeroable};
use glam::Vec3;

use super::{CONVERGED, SurfelParams, Surfels, iso_of};
use crate::density::gpu::{BinnedPoints, GpuGrid};
use crate::density::{DensityGrid, GridSpec, Kernel, Points, SparseGrid};
use crate::gpu::{self, GpuContext, GpuError};
use crate::splat::Surfel;
use crate::splat::gpu::SurfelBuffer;

/// The shader's `SurfelParams`, std140-compatible: 128 bytes (checked against the WGSL in a
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
    pub capacity: u32,
    /// The points of the largest radius lead: the first `leading`
    /// ([`BinnedPoints::leading`]) ...
    pub leading: u32,
    /// ... and the others' largest radius: their sums read them only in the bins it reaches
    /// (negative: every point of every bin within `reach` read, `BinSearch::Whole`).
    pub rest_radius: f32,
    pub _pad: u32,
    pub colour: [f32; 4],
}

const _: () = assert!(std::mem::size_of::<RawSurfelParams>() == 128);

impl RawSurfelParams {
    /// The parameters of a dense grid of `spec` at `iso`, the points binned as `binned` (over
    /// the grid's box), no capacity (set it).
    fn new(
        spec: &GridSpec,
        iso: f32,
        binned: &BinnedPoints,
        points: &Points<'_>,
        kernel: Kernel,
        params: &SurfelParams,
    ) -> Self {
        Self {
            origin: spec.origin.to_array(),
            spacing: spec.spacing,
            dims: spec.dims,
            iso,
            bin_origin: spec.origin.to_array(),
            bin_size: binned.bin_size,
            bins: binned.bins,
            reach: crate::density::gpu::GATHER_REACH,
            h: points.h,
            constant: crate::density::gpu::kernel_constant(kernel, points.h),
            kernel: crate::density::gpu::kernel_code(kernel),
            newton_steps: params.newton_steps,
            blocks: (spec.cells().min(u128::from(u32::MAX)) as u32).div_ceil(BLOCK),
            converged: CONVERGED,
            sparse_block: 0,
            inside: 0.0,
            capacity: 0,
            leading: binned.leading as u32,
            rest_radius: binned.rest_radius,
            _pad: 0,
            colour: crate::splat::WATER,
        }
    }
}

/// The WGSL source of the passes (`common.wgsl` and `scan.wgsl` prepended).
pub const SHADER: &str = concat!(
    include_str!("../../shaders/common.wgsl"),
    include_str!("../../shaders/scan.wgsl"),
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
/// parameters or points, a grid or points beyond the
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

    /// The bind group of the passes' eight buffers, in binding order.
    fn bind(&self, device: &wgpu::Device, buffers: &[&wgpu::Buffer; 8]) -> wgpu::BindGroup {
        gpu::buffers_bind_group(device, "surfels", &self.layout, buffers)
    }

    /// The surfels of `grid` (a [`DensityGrid`], a [`SparseGrid`] or a [`GpuGrid`]) of
    /// `points`, with these passes: [`extract_gpu`]'s surfels. A sparse grid uploads only its
    /// evaluated blocks and block states (the same surfels as [`super::extract_sparse`], in the
    /// dense grid's order); a grid on the GPU is read where it is, with the points it was
    /// filled with as binned there.
    pub fn extract<'g>(
        &self,
        ctx: &GpuContext,
        grid: impl Into<SurfelGrid<'g>>,
        points: Points<'_>,
        kernel: Kernel,
        params: &SurfelParams,
    ) -> Result<Surfels, crate::Error> {
        let grid = grid.into();
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
        let bind = |surfels: &wgpu::Buffer| {
            let [
                uniform,
                values,
                block_sums,
                total,
                binned,
                bin_start,
                states,
            ] = &inputs.buffers;
            self.bind(
                device,
                &[
                    uniform, values, block_sums, total, surfels, binned, bin_start, states,
                ],
            )
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
            64,
            wgpu::BufferUsages::empty(),
        );
        let points_dispatch = dispatch_size(inputs.raw.blocks);
        run(
            &[(&self.count, points_dispatch), (&self.scan_blocks, (1, 1))],
            &bind(&placeholder),
        );
        let surfels = gpu::read_buffer::<u32>(ctx, &inputs.buffers[3])?[0];
        if surfels == 0 {
            return finish(scope, empty);
        }
        let bytes = u64::from(surfels) * 64;
        if bytes > inputs.max_binding {
            return Err(GpuError::Validation(format!(
                "{surfels} surfels exceed the GPU's storage binding limit of {} bytes; extract them on the CPU",
                inputs.max_binding
            ))
            .into());
        }
        let written = storage(device, "surfels", bytes, wgpu::BufferUsages::COPY_SRC);
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
            &bind(&written),
        );
        let (positions, normals) = split(&gpu::read_buffer::<Surfel>(ctx, &written)?);
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

/// A grid the surfel passes read ([`SurfelPasses::extract`]).
#[derive(Clone, Copy, Debug)]
pub enum SurfelGrid<'a> {
    /// A dense grid on the CPU, uploaded.
    Dense(&'a DensityGrid),
    /// A sparse grid's evaluated blocks and block states, uploaded.
    Sparse(&'a SparseGrid),
    /// A grid already on the GPU, with its binned points.
    Gpu(&'a GpuGrid),
}

impl<'a> From<&'a DensityGrid> for SurfelGrid<'a> {
    fn from(g: &'a DensityGrid) -> Self {
        Self::Dense(g)
    }
}

impl<'a> From<&'a SparseGrid> for SurfelGrid<'a> {
    fn from(g: &'a SparseGrid) -> Self {
        Self::Sparse(g)
    }
}

impl<'a> From<&'a GpuGrid> for SurfelGrid<'a> {
    fn from(g: &'a GpuGrid) -> Self {
        Self::Gpu(g)
    }
}

impl SurfelGrid<'_> {
    fn spec(self) -> GridSpec {
        match self {
            Self::Dense(g) => g.spec,
            Self::Sparse(g) => g.spec,
            Self::Gpu(g) => g.spec,
        }
    }
}

/// The binned points of a grid on the GPU, checked to be as many as `points` (the points it
/// was filled with).
fn binned_of(grid: &GpuGrid, points: &Points<'_>) -> Result<BinnedPoints, GpuError> {
    if grid.points.count != points.len() {
        return Err(GpuError::Validation(format!(
            "the GPU grid was filled with {} points, the surfels are asked of {}",
            grid.points.count,
            points.len()
        )));
    }
    Ok(grid.points.clone())
}

/// The block side and inside value of a grid on the GPU for [`RawSurfelParams`]: `(0, 0)`
/// for a dense grid.
fn sparse_of(grid: &GpuGrid) -> (u32, f32) {
    grid.sparse
        .as_ref()
        .map_or((0, 0.0), |s| (crate::density::sparse::BLOCK, s.inside))
}

/// Checks the inputs and uploads them; `None` when there is nothing to extract (no grid point
/// or no point).
fn upload(
    ctx: &GpuContext,
    grid: SurfelGrid<'_>,
    points: Points<'_>,
    kernel: Kernel,
    params: &SurfelParams,
    iso: f32,
) -> Result<Option<Inputs>, crate::Error> {
    points.check()?;
    let spec = grid.spec();
    let n = spec.cells();
    if n == 0 || points.is_empty() {
        return Ok(None);
    }
    let device = &ctx.device;
    let max_binding = gpu::max_binding(device);
    let value_bytes = match grid {
        SurfelGrid::Sparse(g) => 4 * g.raw().1.len().max(g.raw().0.len()) as u128,
        _ => n * 4,
    };
    if value_bytes > u128::from(max_binding) || n > u128::from(u32::MAX) {
        return Err(GpuError::Validation(format!(
            "a grid of {n} points exceeds the GPU's storage binding limit of {max_binding} bytes; extract its surfels on the CPU"
        ))
        .into());
    }
    if let SurfelGrid::Gpu(g) = grid
        && g.sparse.is_none()
        && u128::from(g.values.size()) < n * 4
    {
        return Err(GpuError::Validation(format!(
            "the GPU grid's buffer holds {} bytes, not the {} of its {n} points",
            g.values.size(),
            n * 4
        ))
        .into());
    }
    let binned = match grid {
        SurfelGrid::Gpu(g) => binned_of(g, &points)?,
        _ => BinnedPoints::new(device, &points, &spec)?,
    };
    let blocks = (n as u32).div_ceil(BLOCK);
    let (sparse_block, inside) = match grid {
        SurfelGrid::Sparse(g) => (crate::density::sparse::BLOCK, g.inside),
        SurfelGrid::Gpu(g) => sparse_of(g),
        SurfelGrid::Dense(_) => (0, 0.0),
    };
    let raw = RawSurfelParams {
        sparse_block,
        inside,
        // the buffers are sized from the count read back: every surfel fits
        capacity: u32::MAX,
        ..RawSurfelParams::new(&spec, iso, &binned, &points, kernel, params)
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
            SurfelGrid::Dense(g) => init(
                "surfel grid",
                bytemuck::cast_slice(&g.values),
                wgpu::BufferUsages::STORAGE,
            ),
            SurfelGrid::Gpu(g) => g.values.clone(),
            SurfelGrid::Sparse(g) => init(
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
        storage(device, "surfel count", 32, wgpu::BufferUsages::COPY_SRC),
        binned.points,
        binned.starts,
        match grid {
            SurfelGrid::Sparse(g) => init(
                "surfel block states",
                bytemuck::cast_slice(g.raw().0),
                wgpu::BufferUsages::STORAGE,
            ),
            SurfelGrid::Gpu(GpuGrid {
                sparse: Some(sparse),
                ..
            }) => sparse.states.clone(),
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

/// The positions and normals of surfels as the splatting draws them.
fn split(surfels: &[Surfel]) -> (Vec<Vec3>, Vec<Vec3>) {
    surfels
        .iter()
        .map(|s| (Vec3::from(s.position), Vec3::from(s.normal)))
        .unzip()
}

/// The surfels, or the validation error the device reported meanwhile.
fn finish(scope: wgpu::ErrorScopeGuard, surfels: Surfels) -> Result<Surfels, crate::Error> {
    match pollster::block_on(scope.pop()) {
        Some(e) => Err(GpuError::Validation(e.to_string()).into()),
        None => Ok(surfels),
    }
}

/// The passes' bindings: the parameters, the grid, the block sums, the count, the surfels, the
/// binned points, the bins' starts and a sparse grid's block states.
fn bind_group_layout(device: &wgpu::Device) -> wgpu::BindGroupLayout {
    let read_only = [false, true, false, false, false, true, true, true];
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

/// Surfels extracted into buffers that stay on the GPU (issue 37), for the passes that draw
/// them: the grid read where it is ([`crate::density::gpu::GridFiller`]), the passes recorded
/// into the caller's encoder, `project` dispatched indirectly from the count the scan wrote, no
/// read-back and no wait. The surfel buffers hold [`ResidentSurfels::capacity`] surfels, a first
/// guess from the grid (its box's faces in cells, times three) that grows from the count read
/// back asynchronously a few frames later (mapped after a submit, looked at by a later
/// `record`), scaled by how many more points the frame has than the counted one (a body that
/// grows at once); until it has grown, the surfels past the capacity are left out
/// ([`ResidentSurfels::overflowed`]). After the first frames of a sequence `record` creates
/// nothing ([`ResidentSurfels::created`]).
pub struct ResidentSurfels {
    passes: SurfelPasses,
    uniform: wgpu::Buffer,
    block_sums: gpu::Grow,
    instances: gpu::Grow,
    total: wgpu::Buffer,
    args: wgpu::Buffer,
    draw: wgpu::Buffer,
    states: wgpu::Buffer,
    readback: gpu::AsyncRead,
    bind: Option<(wgpu::BindGroup, [wgpu::Buffer; 4])>,
    capacity: u32,
    last_count: Option<u32>,
    /// The points of the frame whose count is being read back, and of the one counted last.
    pending_points: Option<usize>,
    counted_points: Option<usize>,
    created: usize,
    iso: f32,
    spacing: f32,
    search: crate::density::bins::BinSearch,
}

impl ResidentSurfels {
    /// How the next [`Self::record`]s' projections search the bins (the default:
    /// [`BinSearch::Trimmed`](crate::density::bins::BinSearch::Trimmed)).
    pub fn set_search(&mut self, search: crate::density::bins::BinSearch) {
        self.search = search;
    }

    /// Compiles the passes and makes the fixed buffers for `device`.
    #[must_use]
    pub fn new(device: &wgpu::Device) -> Self {
        let fixed = |label, size, usage| {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size,
                usage,
                mapped_at_creation: false,
            })
        };
        let storage = wgpu::BufferUsages::STORAGE;
        Self {
            passes: SurfelPasses::new(device),
            uniform: fixed(
                "surfel params",
                std::mem::size_of::<RawSurfelParams>() as u64,
                wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            ),
            block_sums: gpu::Grow::new("surfel block sums", storage),
            instances: gpu::Grow::new(
                "surfels",
                storage | wgpu::BufferUsages::VERTEX | wgpu::BufferUsages::COPY_SRC,
            ),
            total: fixed("surfel count", 32, storage | wgpu::BufferUsages::COPY_SRC),
            args: fixed(
                "surfel projection dispatch",
                16,
                wgpu::BufferUsages::INDIRECT | wgpu::BufferUsages::COPY_DST,
            ),
            draw: fixed(
                "surfel draw",
                16,
                wgpu::BufferUsages::INDIRECT | wgpu::BufferUsages::COPY_DST,
            ),
            states: fixed("surfel no block states", 16, storage),
            readback: gpu::AsyncRead::new(device, "surfel count readback", 16),
            bind: None,
            capacity: 0,
            last_count: None,
            pending_points: None,
            counted_points: None,
            created: 0,
            iso: 0.0,
            spacing: 0.0,
            search: crate::density::bins::BinSearch::Trimmed,
        }
    }

    /// Surfels the buffers hold.
    #[must_use]
    pub fn capacity(&self) -> u32 {
        self.capacity
    }

    /// The count of a recent frame, read back asynchronously (`None` until one arrived).
    #[must_use]
    pub fn last_count(&self) -> Option<u32> {
        self.last_count
    }

    /// Whether that frame had more surfels than the buffers held (some were left out).
    #[must_use]
    pub fn overflowed(&self) -> bool {
        self.last_count.is_some_and(|c| c > self.capacity)
    }

    /// Buffers and bind groups the last [`Self::record`] made.
    #[must_use]
    pub fn created(&self) -> usize {
        self.created
    }

    /// The surfels for the splatting: the buffer the passes write ([`Surfel`]s, disks of the
    /// grid's spacing in [`crate::splat::WATER`]) drawn with the count the scan wrote, by an
    /// indirect draw; no read-back.
    #[must_use]
    pub fn surfel_buffer(&self) -> SurfelBuffer {
        SurfelBuffer::indirect(
            self.instances.buffer().clone(),
            self.draw.clone(),
            self.capacity as usize,
        )
    }

    /// Records the passes extracting the surfels of `grid` into `encoder`; call
    /// [`Self::after_submit`] once the encoder is submitted. `points` are those the grid was
    /// filled with: their binned copy on the GPU ([`GpuGrid::points`]) is read, not binned
    /// again.
    pub fn record(
        &mut self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        grid: &GpuGrid,
        points: Points<'_>,
        kernel: Kernel,
        params: &SurfelParams,
    ) -> Result<(), crate::Error> {
        let iso = iso_of(points.h, kernel, params)?;
        points.check()?;
        self.take_count();
        let (device, queue) = (&ctx.device, &ctx.queue);
        let spec = grid.spec;
        let n = spec.cells();
        if (grid.sparse.is_none() && u128::from(grid.values.size()) < n * 4)
            || n > u128::from(u32::MAX)
        {
            return Err(GpuError::Validation(format!(
                "the GPU grid's buffer holds {} bytes, not the {} of its {n} points",
                grid.values.size(),
                n * 4
            ))
            .into());
        }
        let [nx, ny, nz] = spec.dims.map(u64::from);
        let guess = (3 * 2 * (nx * ny + ny * nz + nz * nx)).min(u64::from(u32::MAX)) as u32;
        // a recent count, half again, times the growth of the points since its frame (at least
        // the guess where they grew by more than a quarter)
        let wanted = match (self.last_count, self.counted_points) {
            (Some(c), Some(counted)) => {
                let grown = points.len() as f64 / counted.max(1) as f64;
                let scaled = (1.5 * f64::from(c) * grown.max(1.0)).min(f64::from(u32::MAX)) as u32;
                if grown > 1.25 {
                    scaled.max(guess)
                } else {
                    scaled
                }
            }
            _ => guess,
        }
        .max(self.capacity)
        .max(1024);
        self.capacity = wanted;
        // the points as the grid's filler binned and uploaded them: not binned again
        let binned = binned_of(grid, &points)?;
        let blocks = (n as u32).div_ceil(BLOCK);
        let made = [
            self.block_sums.reserve(device, u64::from(blocks) * 4),
            self.instances.reserve(device, u64::from(wanted) * 64),
        ];
        self.created = made.iter().filter(|&&m| m).count();
        let (sparse_block, inside) = sparse_of(grid);
        let mut raw = RawSurfelParams {
            capacity: wanted,
            sparse_block,
            inside,
            ..RawSurfelParams::new(&spec, iso, &binned, &points, kernel, params)
        };
        if self.search == crate::density::bins::BinSearch::Whole {
            // every point of every bin read (shaders/surfels.wgsl's `whole_search`)
            raw.leading = points.len() as u32;
            raw.rest_radius = -1.0;
        }
        queue.write_buffer(&self.uniform, 0, bytemuck::bytes_of(&raw));
        let states = grid.sparse.as_ref().map_or(&self.states, |s| &s.states);
        // the bind group holds the grid's buffers: made anew when one of them is another
        let key = [
            grid.values.clone(),
            binned.points.clone(),
            binned.starts.clone(),
            states.clone(),
        ];
        let stale = self
            .bind
            .as_ref()
            .is_none_or(|(_, k)| *k != key || self.created > 0);
        if stale {
            let buffers = [
                &self.uniform,
                &grid.values,
                self.block_sums.buffer(),
                &self.total,
                self.instances.buffer(),
                &binned.points,
                &binned.starts,
                states,
            ];
            self.bind = Some((self.passes.bind(device, &buffers), key));
            self.created += 1;
        }
        let bind = &self.bind.as_ref().expect("made above").0;
        let points_dispatch = dispatch_size(blocks);
        for (pipeline, (x, y)) in [
            (&self.passes.count, points_dispatch),
            (&self.passes.scan_blocks, (1, 1)),
            (&self.passes.emit, points_dispatch),
        ] {
            let mut pass = encoder.begin_compute_pass(&Default::default());
            pass.set_pipeline(pipeline);
            pass.set_bind_group(0, bind, &[]);
            pass.dispatch_workgroups(x, y, 1);
        }
        // the workgroups `scan_blocks` wrote after the count, into a buffer of their own: the
        // count's buffer is bound for `project` too, and one dispatch cannot use a buffer both
        // ways
        encoder.copy_buffer_to_buffer(&self.total, 4, &self.args, 0, 12);
        encoder.copy_buffer_to_buffer(&self.total, 16, &self.draw, 0, 16);
        {
            let mut pass = encoder.begin_compute_pass(&Default::default());
            pass.set_pipeline(&self.passes.project);
            pass.set_bind_group(0, bind, &[]);
            pass.dispatch_workgroups_indirect(&self.args, 0);
        }
        if self.readback.copy(encoder, &self.total, 0) {
            self.pending_points = Some(points.len());
        }
        self.iso = iso;
        self.spacing = spec.spacing;
        Ok(())
    }

    /// Starts the count's read-back once the encoder that [`Self::record`] filled is submitted
    /// (no wait: the result is looked at by a later `record`).
    pub fn after_submit(&mut self) {
        self.readback.after_submit();
    }

    /// Takes the count of a finished read-back, if one has finished.
    fn take_count(&mut self) {
        if let Some(bytes) = self.readback.take() {
            self.last_count = bytes
                .get(..4)
                .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]));
            self.counted_points = self.pending_points.take();
        }
    }

    /// The surfels of the last recorded frame, read back (waits on the device: for tests and
    /// tools, never on a frame's path). At most [`Self::capacity`] of them.
    pub fn read(&self, ctx: &GpuContext) -> Result<Surfels, crate::Error> {
        let count = gpu::read_buffer::<u32>(ctx, &self.total)?[0].min(self.capacity) as usize;
        let all = gpu::read_buffer::<Surfel>(ctx, self.instances.buffer())?;
        let (positions, normals) = split(&all[..count.min(all.len())]);
        Ok(Surfels {
            normals,
            radii: vec![self.spacing; positions.len()],
            positions,
            iso: self.iso,
        })
    }
}
