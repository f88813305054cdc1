//! The density grid on the GPU, the twin of [`super::cpu`], two ways ([`GpuDensityMethod`]).
//! Every point carries its effective radius in the `w` of its `vec4` (the design chain's
//! per-point radii; one radius for all in the paper's case), combined as [`super::Points`] says:
//!
//! - splatting, the paper's method (Iwasaki et al., §4.1-4.2): for each group of four z planes,
//!   the particles of the group's z-cluster (the points sorted by slab of four planes, so a
//!   group's are the contiguous range of its slabs) are drawn as instanced squares; the fragment shader
//!   adds each particle's kernel for the four planes into the R, G, B and A channels of an
//!   `Rgba32Float` target with additive blending; each instance's square is its own radius wide
//!   (a per-instance sprite size); the target is copied back. Only one group's target (and a
//!   batch of read-back copies) lives on the GPU, not the grid;
//! - gathering, a compute shader: particles binned (bins of side >= the largest radius /
//!   [`GATHER_REACH`]), one invocation per grid point of a group of up to 32 planes sums the
//!   bins around it; the group is copied back. Again only a group of planes lives on the GPU.
//!
//! These one-shot functions sort the points on the CPU; the frame path ([`GridFiller`], a grid
//! that stays on the GPU) sorts them on the GPU in the caller's encoder
//! ([`super::bins::GpuBinSort`], the same order bit for bit), by bin and by slab.

use bytemuck::{Pod, Zeroable};

use super::bins::{BinLayout, BinSearch, GpuBinSort, bin_particles};
use super::sparse::{BLOCK, BLOCK_VALUES, SparseLayout};
use super::sparse_gpu::GpuSparseLayout;
use super::{DensityGrid, GridSpec, Kernel, Points};
use crate::gpu::{self, GpuContext, GpuError};
use crate::lnm::gpu::BandDomain;

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
    /// The pass's first plane and how many of its four lie in the grid (the unpacking of a grid
    /// that stays on the GPU).
    pub first_plane: u32,
    pub plane_count: u32,
    /// The first slab of points the pass draws ([`BinLayout::slabs`]).
    pub first_slab: u32,
}

const _: () = assert!(std::mem::size_of::<RawParams>() == 64);

impl RawParams {
    /// The uniform of the group of four planes from plane `k0` of the grid `spec`, the kernel
    /// measured against the reference radius `h`, drawing from slab `first_slab`.
    fn group(spec: &GridSpec, h: f32, kernel: Kernel, (k0, first_slab): (u32, u32)) -> Self {
        let [nx, ny, nz] = spec.dims;
        Self {
            origin: spec.origin.to_array(),
            spacing: spec.spacing,
            dims: [nx as f32, ny as f32],
            h,
            constant: kernel_constant(kernel, h),
            planes: std::array::from_fn(|c| spec.origin.z + (k0 + c as u32) as f32 * spec.spacing),
            kernel: kernel_code(kernel),
            first_plane: k0,
            plane_count: PLANES.min(nz - k0),
            first_slab,
        }
    }
}

/// The WGSL source of the splatting pass (`common.wgsl` prepended).
pub const SHADER: &str = concat!(
    include_str!("../../shaders/common.wgsl"),
    include_str!("../../shaders/density_splat.wgsl")
);

/// The WGSL source of the compute (gather) pass (`common.wgsl` prepended).
pub const GATHER_SHADER: &str = concat!(
    include_str!("../../shaders/common.wgsl"),
    include_str!("../../shaders/density_gather.wgsl")
);

/// Planes per pass: one per channel of an RGBA target.
const PLANES: u32 = 4;
/// Groups read back per submission.
const BATCH: u32 = 8;

/// Both GPU methods refuse what the CPU path refuses (radii <= 0 or not finite, non-finite
/// positions or weights), as a validation error.
fn check_inputs(points: &Points<'_>) -> Result<(), GpuError> {
    points
        .check()
        .map_err(|e| GpuError::Validation(e.to_string()))
}

/// A point as the compute passes read it (the WGSL `Point` of `common.wgsl`, 32 bytes) and the
/// splatting pass draws it (an instance: `at` at location 0, `weight` at 1): its position and
/// radius, and its weight in the density.
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
pub struct RawPoint {
    pub at: [f32; 4],
    pub weight: f32,
    pub _pad: [f32; 3],
}

const _: () = assert!(std::mem::size_of::<RawPoint>() == 32);

/// The points in their order as the passes read them: `(x, y, z, radius)`, the weight, and the
/// point's index in the padding's first word ([`FillPoints`]).
pub fn raw_points(points: &Points<'_>) -> Vec<RawPoint> {
    points
        .positions
        .iter()
        .enumerate()
        .map(|(i, p)| RawPoint {
            at: [p.x, p.y, p.z, points.radius(i)],
            weight: points.weights.map_or(1.0, |w| w[i]),
            _pad: [f32::from_bits(i as u32), 0.0, 0.0],
        })
        .collect()
}

/// The shaders' kernel selector.
pub(crate) fn kernel_code(kernel: Kernel) -> u32 {
    match kernel {
        Kernel::Wyvill => 0,
        Kernel::CubicSpline => 1,
    }
}

pub(crate) fn kernel_constant(kernel: Kernel, h: f32) -> f32 {
    match kernel {
        // the same expressions as `Kernel::value_r2` / `Kernel::value`
        Kernel::Wyvill => 2835.0 / (736.0 * std::f32::consts::PI * h * h * h),
        Kernel::CubicSpline => 8.0 / (std::f32::consts::PI * h * h * h),
    }
}

/// Instances as bytes (one zero point when there is none: a buffer is never empty).
fn instance_bytes(sorted: &[RawPoint]) -> &[u8] {
    static NONE: [RawPoint; 1] = [RawPoint {
        at: [0.0; 4],
        weight: 0.0,
        _pad: [0.0; 3],
    }];
    bytemuck::cast_slice(if sorted.is_empty() { &NONE[..] } else { sorted })
}

/// The slabs of points the group of four planes from plane `k0` of the grid `spec` draws
/// (those within `reach`, the largest radius, of its planes), in `slabs`
/// ([`BinLayout::slabs_within`]).
fn group_slabs(spec: &GridSpec, slabs: &BinLayout, k0: u32, reach: f32) -> [u32; 2] {
    let last = (k0 + PLANES - 1).min(spec.dims[2] - 1);
    slabs.slabs_within(
        spec.origin.z + k0 as f32 * spec.spacing - reach,
        spec.origin.z + last as f32 * spec.spacing + reach,
    )
}

/// How a group's pass draws its points: this many (counted on the CPU), or as the indirect
/// draw at this offset of the buffer says (`cs_draws`).
enum GroupDraw<'a> {
    Points(u32),
    Indirect(&'a wgpu::Buffer, u64),
}

/// Records the splatting pass of a group of four planes of the grid `spec` into `target`
/// (cleared, drawn through a viewport of the grid's planes: a target kept at the largest
/// planes of a sequence may be larger): the points of the group's z-cluster (§4.2), which
/// its bind group finds.
fn encode_group(
    encoder: &mut wgpu::CommandEncoder,
    target: &wgpu::TextureView,
    (pipeline, bind): (&wgpu::RenderPipeline, &wgpu::BindGroup),
    spec: &GridSpec,
    draw: GroupDraw<'_>,
) {
    let [nx, ny, _] = spec.dims;
    let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
        label: Some("density planes"),
        color_attachments: &[gpu::cleared(target)],
        ..Default::default()
    });
    pass.set_viewport(0.0, 0.0, nx as f32, ny as f32, 0.0, 1.0);
    pass.set_pipeline(pipeline);
    pass.set_bind_group(0, bind, &[]);
    match draw {
        GroupDraw::Points(0) => {}
        GroupDraw::Points(n) => pass.draw(0..6, 0..n),
        GroupDraw::Indirect(buffer, offset) => pass.draw_indirect(buffer, offset),
    }
}

/// The splatting's bind group: a group's uniform slot, the points sorted by slab and the
/// slabs' starts.
fn splat_bind_group(
    device: &wgpu::Device,
    layout: &wgpu::BindGroupLayout,
    uniform: wgpu::BufferBinding<'_>,
    (points, starts): (&wgpu::Buffer, &wgpu::Buffer),
) -> wgpu::BindGroup {
    device.create_bind_group(&wgpu::BindGroupDescriptor {
        label: Some("density group"),
        layout,
        entries: &[
            wgpu::BindGroupEntry {
                binding: 0,
                resource: wgpu::BindingResource::Buffer(uniform),
            },
            wgpu::BindGroupEntry {
                binding: 3,
                resource: points.as_entire_binding(),
            },
            wgpu::BindGroupEntry {
                binding: 4,
                resource: starts.as_entire_binding(),
            },
        ],
    })
}

/// The splatting pass (§4.1): one instanced quad per particle and plane group, additive
/// blending into the four planes of an `Rgba32Float` target; with its bind group layout.
fn splat_pipeline(device: &wgpu::Device) -> (wgpu::RenderPipeline, wgpu::BindGroupLayout) {
    let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
        label: Some("density_splat"),
        source: wgpu::ShaderSource::Wgsl(SHADER.into()),
    });
    let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
        label: Some("density params"),
        entries: &[
            gpu::entry::uniform(0, wgpu::ShaderStages::VERTEX_FRAGMENT),
            gpu::entry::read_only(3, wgpu::ShaderStages::VERTEX),
            gpu::entry::read_only(4, wgpu::ShaderStages::VERTEX),
        ],
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
            buffers: &[],
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
    (pipeline, layout)
}

/// Fills the density grid on the GPU and hands slabs of four planes to `sink(k0, values)` in
/// increasing z, like [`super::splat_points_slabs`].
pub fn splat_slabs_gpu(
    ctx: &GpuContext,
    points: Points<'_>,
    spec: &GridSpec,
    kernel: Kernel,
    mut sink: impl FnMut(u32, Vec<f32>),
) -> Result<(), GpuError> {
    check_inputs(&points)?;
    let (h, reach) = (points.h, points.max_radius());
    let device = &ctx.device;
    let [nx, ny, nz] = spec.dims;
    let max_dim = device.limits().max_texture_dimension_2d;
    if nx > max_dim || ny > max_dim {
        return Err(GpuError::Validation(format!(
            "a {nx} x {ny} plane exceeds the GPU's {max_dim} texture size"
        )));
    }
    let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
    // particles sorted by slab of four planes (here on the CPU): each group's cluster is a
    // contiguous range of slabs (§4.2)
    let slabs = BinLayout::slabs(spec, PLANES);
    let (sorted, starts) = bin_particles(&raw_points(&points), &slabs);
    use wgpu::util::DeviceExt;
    let storage = |label, contents| {
        device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some(label),
            contents,
            usage: wgpu::BufferUsages::STORAGE,
        })
    };
    let instances = storage("particles", instance_bytes(&sorted));
    let slab_starts = storage("slab starts", bytemuck::cast_slice(&starts));
    let (pipeline, layout) = splat_pipeline(device);
    let target = gpu::texture_2d(
        device,
        "density planes",
        (nx, ny),
        wgpu::TextureFormat::Rgba32Float,
        wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC,
    );
    let view = target.create_view(&wgpu::TextureViewDescriptor::default());
    let row_bytes = (nx as u64 * 16).div_ceil(256) * 256;
    let group_bytes = row_bytes * ny as u64;
    let groups: Vec<u32> = (0..nz).step_by(PLANES as usize).collect();
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
            let [first, end] = group_slabs(spec, &slabs, k0, reach);
            let raw = RawParams::group(spec, h, kernel, (k0, first));
            let uniform = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("density params"),
                contents: bytemuck::bytes_of(&raw),
                usage: wgpu::BufferUsages::UNIFORM,
            });
            let bind = splat_bind_group(
                device,
                &layout,
                uniform.as_entire_buffer_binding(),
                (&instances, &slab_starts),
            );
            encode_group(
                &mut encoder,
                &view,
                (&pipeline, &bind),
                spec,
                GroupDraw::Points(starts[end as usize] - starts[first as usize]),
            );
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
        gpu::map_read_and_wait(device, &slice)?;
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

/// The whole density grid on the GPU, by the default method ([`GpuDensityMethod::default`]).
pub fn density_grid_gpu(
    ctx: &GpuContext,
    points: Points<'_>,
    spec: &GridSpec,
    kernel: Kernel,
) -> Result<DensityGrid, GpuError> {
    density_grid_gpu_with(ctx, points, spec, kernel, GpuDensityMethod::default())
}

pub use super::GpuDensityMethod;

/// The compute shader's `GatherParams` (80 bytes, checked against the WGSL in a test).
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
pub struct RawGatherParams {
    pub origin: [f32; 3],
    pub spacing: f32,
    pub dims: [u32; 3],
    pub k0: u32,
    pub bin_origin: [f32; 3],
    pub bin_size: f32,
    pub bins: [u32; 3],
    pub planes: u32,
    pub h: f32,
    pub constant: f32,
    pub kernel: u32,
    pub reach: u32,
    /// The points of the largest radius lead: the first `leading`
    /// ([`leading_and_rest`](super::bins::leading_and_rest)) ...
    pub leading: u32,
    /// ... and the others' largest radius: the sums read them only in the bins it reaches
    /// (negative: every point of every bin within `reach`, [`BinSearch::Whole`]).
    pub rest_radius: f32,
    pub _pad: [u32; 2],
}

const _: () = assert!(std::mem::size_of::<RawGatherParams>() == 96);

impl RawGatherParams {
    /// These parameters read with `search`: for [`BinSearch::Whole`] every point of every bin.
    fn searching(mut self, search: BinSearch, points: usize) -> Self {
        if search == BinSearch::Whole {
            self.leading = points as u32;
            self.rest_radius = -1.0;
        }
        self
    }

    /// The parameters filling planes `k0 .. k0 + planes` of the grid of `spec` with the points
    /// `binned` (over the grid's box), of reference radius `h`.
    fn new(
        spec: &GridSpec,
        binned: &BinnedPoints,
        h: f32,
        kernel: Kernel,
        (k0, planes): (u32, u32),
    ) -> Self {
        Self {
            origin: spec.origin.to_array(),
            spacing: spec.spacing,
            dims: spec.dims,
            k0,
            bin_origin: spec.origin.to_array(),
            bin_size: binned.bin_size,
            bins: binned.bins,
            planes,
            h,
            constant: kernel_constant(kernel, h),
            kernel: kernel_code(kernel),
            reach: GATHER_REACH,
            leading: binned.leading as u32,
            rest_radius: binned.rest_radius,
            _pad: [0; 2],
        }
    }
}

/// The gather pass's bind group: its parameters, the binned points and their bins' starts, and
/// the grid values it writes.
fn gather_bind_group(
    device: &wgpu::Device,
    pipeline: &wgpu::ComputePipeline,
    buffers: [&wgpu::Buffer; 4],
) -> wgpu::BindGroup {
    gpu::buffers_bind_group(
        device,
        "gather",
        &pipeline.get_bind_group_layout(0),
        &buffers,
    )
}

/// Bins per `h` of the gather path: bins of side `h / GATHER_REACH`, searched `GATHER_REACH`
/// bins to each side; smaller bins waste fewer kernel evaluations on particles beyond h (a
/// searched volume of `(2.5 h)^3` instead of `(3 h)^3`, 0.58 as much). On lavapipe (150k particles into 256^3) 1 and 2 measured alike,
/// 5.1-6.2 s, within the run-to-run spread.
pub const GATHER_REACH: u32 = 2;

/// Points binned on the CPU ([`bin_particles`]) and checked against the binding limit
/// `max_binding`: sorted points, the bins' starts, the bins.
struct Bins {
    sorted: Vec<RawPoint>,
    start: Vec<u32>,
    layout: BinLayout,
}

impl Bins {
    fn new(points: &Points<'_>, spec: &GridSpec, max_binding: u64) -> Result<Self, GpuError> {
        let layout = BinLayout::of(points, spec);
        let (sorted, start) = bin_particles(&raw_points(points), &layout);
        if (sorted.len().max(1) * 32) as u64 > max_binding || (start.len() * 4) as u64 > max_binding
        {
            return Err(GpuError::Validation(format!(
                "{} points exceed the GPU's storage binding limit of {max_binding} bytes; use the splatting method or the CPU path",
                points.len()
            )));
        }
        Ok(Self {
            sorted,
            start,
            layout,
        })
    }

    /// The sorted points as bytes (one zero point when there is none: a binding holds at
    /// least one).
    fn point_bytes(&self) -> &[u8] {
        instance_bytes(&self.sorted)
    }
}

/// Points binned for the compute passes (the gather density, the GPU surfels' projection),
/// on the GPU: sorted by cubic bins of side `bin_size` (>= the largest radius /
/// [`GATHER_REACH`]) over a grid's box from its origin, as `Point`s ([`RawPoint`]), with the
/// start of every bin (x fastest). A [`GpuGrid`] carries the points it was filled with, so that
/// the surfels of the grid read them without binning them again.
#[derive(Clone, Debug)]
pub struct BinnedPoints {
    /// The points, sorted by bin.
    pub points: wgpu::Buffer,
    /// `starts[b] .. starts[b + 1]`: the points of bin `b`.
    pub starts: wgpu::Buffer,
    /// Bins along x, y and z.
    pub bins: [u32; 3],
    /// The side of a bin.
    pub bin_size: f32,
    /// How many points.
    pub count: usize,
    /// The points the sums read in every bin within the largest radius, the first `leading`,
    /// and the others' largest radius ([`leading_and_rest`](super::bins::leading_and_rest)).
    pub leading: usize,
    pub rest_radius: f32,
}

impl BinnedPoints {
    /// The points `sort` sorts into the bins of `layout` (its buffers, once the encoder it
    /// recorded into has run).
    pub(crate) fn sorted_by(
        sort: &super::bins::GpuBinSort,
        layout: &super::bins::BinLayout,
        points: &Points<'_>,
    ) -> Self {
        let (leading, rest_radius) = super::bins::leading_and_rest(points);
        Self {
            points: sort.sorted().clone(),
            starts: sort.starts().clone(),
            bins: layout.bins,
            bin_size: layout.size,
            count: points.len(),
            leading,
            rest_radius,
        }
    }

    /// Bins `points` over the box of `spec` and uploads them.
    pub fn new(
        device: &wgpu::Device,
        points: &Points<'_>,
        spec: &GridSpec,
    ) -> Result<Self, GpuError> {
        let bins = Bins::new(points, spec, gpu::max_binding(device))?;
        let (leading, rest_radius) = super::bins::leading_and_rest(points);
        use wgpu::util::DeviceExt;
        let init = |label, contents| {
            device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents,
                usage: wgpu::BufferUsages::STORAGE,
            })
        };
        Ok(Self {
            points: init("binned points", bins.point_bytes()),
            starts: init("bin starts", bytemuck::cast_slice(&bins.start)),
            bins: bins.layout.bins,
            bin_size: bins.layout.size,
            count: points.len(),
            leading,
            rest_radius,
        })
    }
}

/// The gather pass's compute pipeline (entry point `gather`, or `gather_blocks` for a sparse
/// grid's evaluated blocks).
fn gather_pipeline_of(device: &wgpu::Device, entry: &str) -> wgpu::ComputePipeline {
    let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
        label: Some("density_gather"),
        source: wgpu::ShaderSource::Wgsl(GATHER_SHADER.into()),
    });
    device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
        label: Some("density gather"),
        layout: None,
        module: &module,
        entry_point: Some(entry),
        compilation_options: Default::default(),
        cache: None,
    })
}

/// The gather pass's compute pipeline over whole planes.
fn gather_pipeline(device: &wgpu::Device) -> wgpu::ComputePipeline {
    gather_pipeline_of(device, "gather")
}

/// The gather pass's pipeline and the binned points, set up once for a grid.
struct Gather {
    pipeline: wgpu::ComputePipeline,
    binned: BinnedPoints,
    max_binding: u64,
}

impl Gather {
    /// Checks the points and the grid's planes against the adapter's limits, bins and uploads
    /// the points, compiles the pass.
    fn new(ctx: &GpuContext, points: &Points<'_>, spec: &GridSpec) -> Result<Self, GpuError> {
        check_inputs(points)?;
        let device = &ctx.device;
        let [nx, ny, _] = spec.dims;
        let plane_bytes = u64::from(nx) * u64::from(ny) * 4;
        let max_binding = gpu::max_binding(device);
        if plane_bytes > max_binding {
            return Err(GpuError::Validation(format!(
                "a {nx} x {ny} plane ({plane_bytes} bytes) exceeds the GPU's storage binding limit of {max_binding} bytes"
            )));
        }
        Ok(Self {
            pipeline: gather_pipeline(device),
            binned: BinnedPoints::new(device, points, spec)?,
            max_binding,
        })
    }

    /// Records the pass filling planes `k0 .. k0 + planes` of the grid into `out` (x fastest,
    /// from plane `k0`).
    #[allow(clippy::too_many_arguments)]
    fn record(
        &self,
        device: &wgpu::Device,
        encoder: &mut wgpu::CommandEncoder,
        spec: &GridSpec,
        points: &Points<'_>,
        kernel: Kernel,
        (k0, planes): (u32, u32),
        out: &wgpu::Buffer,
    ) {
        use wgpu::util::DeviceExt;
        let binned = &self.binned;
        let raw = RawGatherParams::new(spec, binned, points.h, kernel, (k0, planes));
        let uniform = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("gather params"),
            contents: bytemuck::bytes_of(&raw),
            usage: wgpu::BufferUsages::UNIFORM,
        });
        let bind = gather_bind_group(
            device,
            &self.pipeline,
            [&uniform, &binned.points, &binned.starts, out],
        );
        let mut pass = encoder.begin_compute_pass(&Default::default());
        pass.set_pipeline(&self.pipeline);
        pass.set_bind_group(0, &bind, &[]);
        pass.dispatch_workgroups(spec.dims[0].div_ceil(8), spec.dims[1].div_ceil(8), planes);
    }
}

/// Fills the density grid on the GPU with the compute (gather) variant and hands slabs of
/// planes to `sink(k0, values)` in increasing z, like [`splat_slabs_gpu`].
pub fn gather_slabs_gpu(
    ctx: &GpuContext,
    points: Points<'_>,
    spec: &GridSpec,
    kernel: Kernel,
    mut sink: impl FnMut(u32, Vec<f32>),
) -> Result<(), GpuError> {
    let gather = Gather::new(ctx, &points, spec)?;
    let device = &ctx.device;
    let [nx, ny, nz] = spec.dims;
    let plane_bytes = u64::from(nx) * u64::from(ny) * 4;
    // planes per dispatch: up to 32 (8 MiB at 256^2), within the binding limit
    let planes_per = ((gather.max_binding / plane_bytes) as u32)
        .clamp(1, 32)
        .min(nz.max(1));
    let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
    let out_bytes = plane_bytes * u64::from(planes_per);
    let densities = device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("density planes"),
        size: out_bytes,
        usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
        mapped_at_creation: false,
    });
    let readback = device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("density readback"),
        size: out_bytes,
        usage: wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::MAP_READ,
        mapped_at_creation: false,
    });
    for k0 in (0..nz).step_by(planes_per as usize) {
        let planes = planes_per.min(nz - k0);
        let mut encoder = device.create_command_encoder(&Default::default());
        gather.record(
            device,
            &mut encoder,
            spec,
            &points,
            kernel,
            (k0, planes),
            &densities,
        );
        let bytes = plane_bytes * u64::from(planes);
        encoder.copy_buffer_to_buffer(&densities, 0, &readback, 0, bytes);
        ctx.queue.submit([encoder.finish()]);
        let slice = readback.slice(..bytes);
        gpu::map_read_and_wait(device, &slice)?;
        let slab: Vec<f32> = {
            let data = slice
                .get_mapped_range()
                .map_err(|e| GpuError::Readback(format!("{e:?}")))?;
            bytemuck::cast_slice(&data).to_vec()
        };
        readback.unmap();
        if let Some(bad) = slab.iter().position(|v| !v.is_finite()) {
            return Err(GpuError::Readback(format!(
                "non-finite density in the slab from plane {k0}, value {bad}"
            )));
        }
        sink(k0, slab);
    }
    if let Some(e) = pollster::block_on(scope.pop()) {
        return Err(GpuError::Validation(e.to_string()));
    }
    Ok(())
}

/// A density grid that lives on the GPU (issue 37): its values in a storage buffer, x fastest
/// ([`DensityGrid`]'s layout), or a sparse grid's evaluated blocks ([`GpuGrid::sparse`]), for
/// the passes that read it there ([`crate::surfels::gpu`]).
#[derive(Clone, Debug)]
pub struct GpuGrid {
    /// The grid.
    pub spec: GridSpec,
    /// Dense: one `f32` per grid point, index `i + nx (j + ny k)`. Sparse: [`BLOCK_VALUES`] per
    /// evaluated block in slot order, x fastest within a block.
    pub values: wgpu::Buffer,
    /// The points the grid was filled with, binned (the surfels' projection reads them).
    pub points: BinnedPoints,
    /// The block states of a sparse grid ([`GridFiller::record_sparse`]); `None`: dense.
    pub sparse: Option<GpuSparse>,
}

/// The blocks of a sparse grid on the GPU ([`GpuGrid::sparse`]).
#[derive(Clone, Debug)]
pub struct GpuSparse {
    /// Per block of [`super::sparse::BLOCK`]^3 grid points (x fastest): `u32::MAX` empty (its
    /// values 0), `u32::MAX - 1` inside (its values read as `inside`), else the slot of its
    /// values.
    pub states: wgpu::Buffer,
    /// The value the inside blocks read as (above the iso-value; the surfels compute the exact
    /// value where a crossing ends in one).
    pub inside: f32,
    /// Evaluated blocks the values hold (a layout found on the GPU: the values' capacity, its
    /// count in [`super::sparse_gpu::GpuSparseLayout::count`]).
    pub evaluated: u32,
}

impl GpuGrid {
    /// The values read back (a wait on the device: for tests and tools, never on a frame's
    /// path); a sparse grid's as a dense grid (the inside blocks' values `inside`).
    pub fn read(&self, ctx: &GpuContext) -> Result<DensityGrid, GpuError> {
        let mut values: Vec<f32> = gpu::read_buffer(ctx, &self.values)?;
        let Some(sparse) = &self.sparse else {
            values.truncate(self.spec.cells() as usize);
            return Ok(DensityGrid {
                spec: self.spec,
                values,
            });
        };
        let states: Vec<u32> = gpu::read_buffer(ctx, &sparse.states)?;
        let [nx, ny, nz] = self.spec.dims;
        let bx = nx.div_ceil(BLOCK);
        let by = ny.div_ceil(BLOCK);
        let mut dense = vec![0.0f32; self.spec.cells() as usize];
        for k in 0..nz {
            for j in 0..ny {
                for i in 0..nx {
                    let b = (i / BLOCK + bx * (j / BLOCK + by * (k / BLOCK))) as usize;
                    let l = (i % BLOCK + BLOCK * (j % BLOCK + BLOCK * (k % BLOCK))) as usize;
                    dense[(i + nx * (j + ny * k)) as usize] = match states[b] {
                        u32::MAX => 0.0,
                        s if s == u32::MAX - 1 => sparse.inside,
                        slot => values[slot as usize * BLOCK_VALUES + l],
                    };
                }
            }
        }
        Ok(DensityGrid {
            spec: self.spec,
            values: dense,
        })
    }
}

/// The density grid filled on the GPU by the gather pass and left there: one dispatch over
/// every plane, recorded and submitted, no read-back (a [`GridFiller`] of its own; a sequence
/// keeps one). Errors as [`gather_slabs_gpu`], and a grid beyond the adapter's storage binding
/// limit or a dispatch's 65,535 planes (the slabs of the read-back paths are not bound by
/// them).
pub fn density_grid_on_gpu(
    ctx: &GpuContext,
    points: Points<'_>,
    spec: &GridSpec,
    kernel: Kernel,
) -> Result<GpuGrid, GpuError> {
    let device = &ctx.device;
    let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
    let mut encoder = device.create_command_encoder(&Default::default());
    let grid = GridFiller::new(device).record(ctx, &mut encoder, points, spec, kernel)?;
    ctx.queue.submit([encoder.finish()]);
    if let Some(e) = pollster::block_on(scope.pop()) {
        return Err(GpuError::Validation(e.to_string()));
    }
    Ok(grid)
}

/// The gather pass kept from frame to frame (issue 37): its pipeline and uniform, and buffers
/// for the binned points, the bins' starts and the grid that grow when a frame needs more and
/// are otherwise rewritten in place. [`GridFiller::record`] records the pass into the caller's
/// encoder and waits on nothing; after the first frames of a sequence (while the buffers grow)
/// it creates nothing ([`GridFiller::created`]).
pub struct GridFiller {
    pipeline: wgpu::ComputePipeline,
    uniform: wgpu::Buffer,
    /// The points sorted by bin, on the GPU.
    bins: GpuBinSort,
    grid: gpu::Grow,
    bind: Option<wgpu::BindGroup>,
    created: usize,
    /// The splatting method's passes ([`GridFiller::with_method`]); `None`: the gather pass.
    splat: Option<SplatPasses>,
    /// A sparse grid's pass ([`GridFiller::record_sparse`]), made on first use.
    sparse: Option<SparseFill>,
    /// How the gather passes search the bins ([`GridFiller::set_search`]).
    search: BinSearch,
}

/// The gather over a sparse grid's evaluated blocks (`gather_blocks`), its block states and
/// evaluated blocks uploaded into buffers kept from frame to frame.
struct SparseFill {
    pipeline: wgpu::ComputePipeline,
    states: gpu::Grow,
    evaluated: gpu::Grow,
    bind: Option<wgpu::BindGroup>,
    /// The bind group over a layout found on the GPU ([`GridFiller::record_sparse_resident`])
    /// and the evaluated blocks' buffer it reads.
    resident_bind: Option<(wgpu::Buffer, wgpu::BindGroup)>,
}

impl SparseFill {
    /// The gather's pipeline and empty lists (the states read back by tests).
    fn new(device: &wgpu::Device) -> Self {
        Self {
            pipeline: gather_pipeline_of(device, "gather_blocks"),
            states: gpu::Grow::new(
                "sparse block states",
                wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
            ),
            evaluated: gpu::Grow::new("sparse evaluated blocks", wgpu::BufferUsages::STORAGE),
            bind: None,
            resident_bind: None,
        }
    }
}

/// The paper's splatting (§4.1) into a grid that stays on the GPU: the points sorted by slab
/// of four planes on the GPU ([`GpuBinSort`]), `cs_draws` counting each group's points (its
/// z-cluster, §4.2) for its indirect draw; per group of four planes a render pass draws them
/// into an `Rgba32Float` target with additive blending, and a compute pass (`cs_unpack`)
/// copies the four planes into the grid's buffer; the sort's buffers, the groups' uniforms
/// (one aligned slot a group) and slabs, the draws, the target and the bind groups are kept
/// from frame to frame.
struct SplatPasses {
    pipeline: wgpu::RenderPipeline,
    layout: wgpu::BindGroupLayout,
    unpack: wgpu::ComputePipeline,
    draws_pipeline: wgpu::ComputePipeline,
    sort: GpuBinSort,
    uniforms: gpu::Grow,
    /// Per group its first and last + 1 slab, and its indirect draw.
    slabs: gpu::Grow,
    draws: gpu::Grow,
    draws_bind: Option<wgpu::BindGroup>,
    target: Option<(wgpu::Texture, wgpu::TextureView)>,
    /// Per group: the splat's and the unpacking's bind groups.
    binds: Vec<(wgpu::BindGroup, wgpu::BindGroup)>,
}

impl SplatPasses {
    fn new(device: &wgpu::Device) -> Self {
        let (pipeline, layout) = splat_pipeline(device);
        let [unpack, draws_pipeline] =
            gpu::compute_pipelines(device, "density_splat", SHADER, ["cs_unpack", "cs_draws"]);
        Self {
            pipeline,
            layout,
            unpack,
            draws_pipeline,
            sort: GpuBinSort::new(device),
            uniforms: gpu::Grow::new("density groups", wgpu::BufferUsages::UNIFORM),
            slabs: gpu::Grow::new("density group slabs", wgpu::BufferUsages::STORAGE),
            draws: gpu::Grow::new(
                "density group draws",
                wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::INDIRECT,
            ),
            draws_bind: None,
            target: None,
            binds: Vec::new(),
        }
    }

    /// Records the groups' passes filling `grid` (the buffer of `spec`'s values) with the points
    /// `raw` (of `points`); how many buffers, textures and bind groups it made.
    fn record(
        &mut self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        (points, raw, spec, kernel): (&Points<'_>, &[RawPoint], &GridSpec, Kernel),
        (grid, grid_new): (&wgpu::Buffer, bool),
        before: Option<BeforeFill<'_>>,
    ) -> Result<usize, GpuError> {
        let (device, queue) = (&ctx.device, &ctx.queue);
        let [nx, ny, nz] = spec.dims;
        let max_dim = device.limits().max_texture_dimension_2d;
        if nx > max_dim || ny > max_dim {
            return Err(GpuError::Validation(format!(
                "a {nx} x {ny} plane exceeds the GPU's {max_dim} texture size; use the gather method"
            )));
        }
        let slabs = BinLayout::slabs(spec, PLANES);
        self.sort.record(ctx, encoder, raw, &slabs)?;
        let mut created = self.sort.created();
        if let Some(before) = before {
            before(encoder, FillPoints::Sorted(self.sort.sorted(), raw.len()))?;
        }
        let groups: Vec<u32> = (0..nz).step_by(PLANES as usize).collect();
        let stride = u64::from(device.limits().min_uniform_buffer_offset_alignment)
            .max(std::mem::size_of::<RawParams>() as u64);
        created += usize::from(
            self.uniforms
                .reserve(device, stride * groups.len().max(1) as u64),
        );
        let (h, reach) = (points.h, points.max_radius());
        // every group's uniform in its aligned slot, in one write, and its slabs
        let mut slots = vec![0u8; stride as usize * groups.len()];
        let mut group_slabs_of = Vec::with_capacity(groups.len());
        for (slot, &k0) in slots.chunks_exact_mut(stride as usize).zip(&groups) {
            let range = group_slabs(spec, &slabs, k0, reach);
            let raw = RawParams::group(spec, h, kernel, (k0, range[0]));
            slot[..std::mem::size_of::<RawParams>()].copy_from_slice(bytemuck::bytes_of(&raw));
            group_slabs_of.push(range);
        }
        queue.write_buffer(self.uniforms.buffer(), 0, &slots);
        let made_lists = usize::from(self.slabs.write(
            device,
            queue,
            bytemuck::cast_slice(&group_slabs_of),
        )) + usize::from(self.draws.reserve(device, 16 * groups.len() as u64));
        created += made_lists;
        if self.draws_bind.is_none() || made_lists > 0 || self.sort.created() > 0 {
            self.draws_bind = Some(gpu::bind_group(
                device,
                &self.draws_pipeline,
                &[
                    (4, self.sort.starts().as_entire_binding()),
                    (5, self.slabs.buffer().as_entire_binding()),
                    (6, self.draws.buffer().as_entire_binding()),
                ],
            ));
            created += 1;
        }
        // the target grows to the largest planes of the sequence; each pass draws into its
        // corner of the grid's size (the viewport)
        let (w, h) = self
            .target
            .as_ref()
            .map_or((0, 0), |(t, _)| (t.width(), t.height()));
        if w < nx || h < ny {
            let texture = gpu::texture_2d(
                device,
                "density planes",
                (w.max(nx), h.max(ny)),
                wgpu::TextureFormat::Rgba32Float,
                wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::TEXTURE_BINDING,
            );
            let view = texture.create_view(&Default::default());
            self.target = Some((texture, view));
            created += 1;
        }
        let (_, view) = self.target.as_ref().expect("made above");
        if created > 0 || grid_new || self.binds.len() < groups.len() {
            let slot = |g: usize| wgpu::BufferBinding {
                buffer: self.uniforms.buffer(),
                offset: stride * g as u64,
                size: std::num::NonZeroU64::new(std::mem::size_of::<RawParams>() as u64),
            };
            let unpack_layout = self.unpack.get_bind_group_layout(0);
            self.binds = (0..groups.len().max(self.binds.len()))
                .map(|g| {
                    let splat = splat_bind_group(
                        device,
                        &self.layout,
                        slot(g),
                        (self.sort.sorted(), self.sort.starts()),
                    );
                    let unpack = device.create_bind_group(&wgpu::BindGroupDescriptor {
                        label: Some("density unpack"),
                        layout: &unpack_layout,
                        entries: &[
                            wgpu::BindGroupEntry {
                                binding: 0,
                                resource: wgpu::BindingResource::Buffer(slot(g)),
                            },
                            wgpu::BindGroupEntry {
                                binding: 1,
                                resource: wgpu::BindingResource::TextureView(view),
                            },
                            wgpu::BindGroupEntry {
                                binding: 2,
                                resource: grid.as_entire_binding(),
                            },
                        ],
                    });
                    (splat, unpack)
                })
                .collect();
            created += 1;
        }
        if !groups.is_empty() {
            let mut pass = encoder.begin_compute_pass(&Default::default());
            pass.set_pipeline(&self.draws_pipeline);
            pass.set_bind_group(0, self.draws_bind.as_ref(), &[]);
            pass.dispatch_workgroups(groups.len() as u32, 1, 1);
        }
        for (g, (splat, unpack)) in self.binds.iter().take(groups.len()).enumerate() {
            encode_group(
                encoder,
                view,
                (&self.pipeline, splat),
                spec,
                GroupDraw::Indirect(self.draws.buffer(), 16 * g as u64),
            );
            let mut pass = encoder.begin_compute_pass(&Default::default());
            pass.set_pipeline(&self.unpack);
            pass.set_bind_group(0, unpack, &[]);
            pass.dispatch_workgroups(nx.div_ceil(8), ny.div_ceil(8), 1);
        }
        Ok(created)
    }
}

/// A pass [`GridFiller::record_with`] records between the points' upload and the fill, for
/// each copy of the points the fill reads.
pub type BeforeFill<'a> =
    &'a mut dyn FnMut(&mut wgpu::CommandEncoder, FillPoints<'_>) -> Result<(), GpuError>;

/// A copy of the points a grid is filled from, as [`BeforeFill`] sees it: each point
/// ([`RawPoint`]) keeps its index in the points (`_pad[0]`'s bits).
pub enum FillPoints<'a> {
    /// The binned points, which the gather pass and the GPU surfels read (always, first).
    Binned(&'a BinnedPoints),
    /// The splatting's copy sorted by slab of four planes, of this many points (with the
    /// splatting, second).
    Sorted(&'a wgpu::Buffer, usize),
    /// No copy: a sparse grid's layout found on the GPU is recorded, the fill comes next
    /// ([`GridFiller::record_sparse_resident`], second; a hook that times passes marks it).
    Laid,
}

impl GridFiller {
    /// Compiles the pass for `device`.
    #[must_use]
    pub fn new(device: &wgpu::Device) -> Self {
        let storage = wgpu::BufferUsages::STORAGE;
        Self {
            pipeline: gather_pipeline(device),
            uniform: crate::gpu::uniform_buffer(
                device,
                "gather params",
                std::mem::size_of::<RawGatherParams>() as u64,
            ),
            bins: GpuBinSort::new(device),
            grid: gpu::Grow::new("density grid", storage | wgpu::BufferUsages::COPY_SRC),
            bind: None,
            created: 0,
            splat: None,
            sparse: None,
            search: BinSearch::Trimmed,
        }
    }

    /// How the next records' gather passes (the gather method's and a sparse grid's) search
    /// the bins (the default: [`BinSearch::Trimmed`]).
    pub fn set_search(&mut self, search: BinSearch) {
        self.search = search;
    }

    /// [`GridFiller::new`] filling the grid by `method`: the compute gather pass, or the
    /// paper's splatting of four planes per RGBA pass (§4.1), each group of planes unpacked into
    /// the grid's buffer where the surfels read it.
    #[must_use]
    pub fn with_method(device: &wgpu::Device, method: GpuDensityMethod) -> Self {
        let mut filler = Self::new(device);
        if method == GpuDensityMethod::Splat {
            filler.splat = Some(SplatPasses::new(device));
        }
        filler
    }

    /// The method it fills the grid by.
    #[must_use]
    pub fn method(&self) -> GpuDensityMethod {
        if self.splat.is_some() {
            GpuDensityMethod::Splat
        } else {
            GpuDensityMethod::Gather
        }
    }

    /// Buffers and bind groups the last [`Self::record`] made (0 once they are large enough).
    #[must_use]
    pub fn created(&self) -> usize {
        self.created
    }

    /// Records the pass filling the grid of `spec` with `points` into `encoder`; the grid is
    /// in the returned [`GpuGrid`] once the encoder's work is submitted and done (its buffer is
    /// this filler's, rewritten by the next `record`). Errors as [`density_grid_on_gpu`].
    pub fn record(
        &mut self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        points: Points<'_>,
        spec: &GridSpec,
        kernel: Kernel,
    ) -> Result<GpuGrid, GpuError> {
        self.record_with(ctx, encoder, (points, spec, kernel), None)
    }

    /// [`Self::record`], recording `before` into `encoder` once the points are binned and
    /// uploaded and before the grid is filled from them (a pass that changes their weights in
    /// place: the boundary calibration's on the GPU, `pipeline::boundary::gpu`).
    pub fn record_with(
        &mut self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        (points, spec, kernel): (Points<'_>, &GridSpec, Kernel),
        before: Option<BeforeFill<'_>>,
    ) -> Result<GpuGrid, GpuError> {
        check_inputs(&points)?;
        let (device, queue) = (&ctx.device, &ctx.queue);
        let max_binding = gpu::max_binding(device);
        let bytes = spec.cells() * 4;
        if bytes > u128::from(max_binding) || spec.dims[2] > 65_535 {
            return Err(GpuError::Validation(format!(
                "a grid of {} points ({bytes} bytes) exceeds the GPU's storage binding limit of {max_binding} bytes or a dispatch's 65,535 planes; fill it in slabs (density_slabs_gpu) or on the CPU",
                spec.cells()
            )));
        }
        let (binned, made, uploaded) = self.upload(ctx, encoder, &points, (spec, bytes as u64))?;
        let mut before = before;
        if let Some(before) = before.as_mut() {
            before(encoder, FillPoints::Binned(&binned))?;
        }
        let raw = RawGatherParams::new(spec, &binned, points.h, kernel, (0, spec.dims[2]))
            .searching(self.search, points.len());
        queue.write_buffer(&self.uniform, 0, bytemuck::bytes_of(&raw));
        if self.bind.is_none() || self.created > 0 {
            self.bind = Some(gather_bind_group(
                device,
                &self.pipeline,
                [
                    &self.uniform,
                    self.bins.sorted(),
                    self.bins.starts(),
                    self.grid.buffer(),
                ],
            ));
            self.created += 1;
        }
        if let Some(splat) = self.splat.as_mut()
            && bytes > 0
        {
            let grid_new = made[1];
            self.created += splat.record(
                ctx,
                encoder,
                (&points, &uploaded, spec, kernel),
                (self.grid.buffer(), grid_new),
                before,
            )?;
        } else if bytes > 0 {
            let mut pass = encoder.begin_compute_pass(&Default::default());
            pass.set_pipeline(&self.pipeline);
            pass.set_bind_group(0, self.bind.as_ref(), &[]);
            pass.dispatch_workgroups(
                spec.dims[0].div_ceil(8),
                spec.dims[1].div_ceil(8),
                spec.dims[2],
            );
        }
        Ok(self.grid_of(spec, binned, None))
    }

    /// Uploads `points` and records their sort into the bins over the grid of `spec`
    /// ([`GpuBinSort`]) into `encoder`, and makes sure the grid's buffer holds `bytes`; the
    /// binned points (in the sort's buffers), whether the sort's buffers and the grid's were
    /// made anew (counted in [`Self::created`]), and the points as uploaded.
    fn upload(
        &mut self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        points: &Points<'_>,
        (spec, bytes): (&GridSpec, u64),
    ) -> Result<(BinnedPoints, [bool; 2], Vec<RawPoint>), GpuError> {
        let layout = BinLayout::of(points, spec);
        let raw = raw_points(points);
        self.bins.record(ctx, encoder, &raw, &layout)?;
        let made = [
            self.bins.created() > 0,
            self.grid.reserve(&ctx.device, bytes),
        ];
        self.created = self.bins.created() + usize::from(made[1]);
        let binned = BinnedPoints::sorted_by(&self.bins, &layout, points);
        Ok((binned, made, raw))
    }

    /// The grid in this filler's buffer, filled from `points`.
    fn grid_of(&self, spec: &GridSpec, points: BinnedPoints, sparse: Option<GpuSparse>) -> GpuGrid {
        GpuGrid {
            spec: *spec,
            values: self.grid.buffer().clone(),
            points,
            sparse,
        }
    }

    /// Records the pass filling the evaluated blocks of the sparse grid `layout` (from
    /// [`super::sparse_layout`]) with `points` into `encoder`, by the gather (whatever
    /// [`Self::method`]: the splatting draws whole planes), every grid point of an evaluated
    /// block given its value (the dense grid's: the CPU's sparse grid reads the points in the
    /// band's interior voxels as `inside` instead); the inside blocks read as `inside`. The
    /// grid's buffer holds the evaluated blocks only: its memory follows the surface. Errors as
    /// [`Self::record`], for the evaluated blocks' values against the binding limit.
    pub fn record_sparse(
        &mut self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        points: Points<'_>,
        (layout, inside): (&SparseLayout, f32),
        kernel: Kernel,
    ) -> Result<GpuGrid, GpuError> {
        self.record_sparse_with(ctx, encoder, (points, layout, inside, kernel), None)
    }

    /// [`Self::record_sparse`] with a pass recorded before the fill ([`Self::record_with`]).
    pub fn record_sparse_with(
        &mut self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        (points, layout, inside, kernel): (Points<'_>, &SparseLayout, f32, Kernel),
        before: Option<BeforeFill<'_>>,
    ) -> Result<GpuGrid, GpuError> {
        check_inputs(&points)?;
        let (device, queue) = (&ctx.device, &ctx.queue);
        let max_binding = gpu::max_binding(device);
        let spec = &layout.spec;
        let bytes = check_sparse_fill(
            spec,
            (layout.evaluated.len() as u64, layout.states.len() as u64),
            inside,
            max_binding,
        )?;
        let (binned, made, _) = self.upload(ctx, encoder, &points, (spec, bytes))?;
        if let Some(before) = before {
            before(encoder, FillPoints::Binned(&binned))?;
        }
        let fill = self.sparse.get_or_insert_with(|| SparseFill::new(device));
        let lists = gpu::write_grown(
            device,
            queue,
            [
                (&mut fill.states, bytemuck::cast_slice(&layout.states)),
                (&mut fill.evaluated, bytemuck::cast_slice(&layout.evaluated)),
            ],
        );
        self.created += lists;
        let slots = layout.evaluated.len() as u32;
        let raw = RawGatherParams::new(spec, &binned, points.h, kernel, (0, slots))
            .searching(self.search, points.len());
        queue.write_buffer(&self.uniform, 0, bytemuck::bytes_of(&raw));
        if fill.bind.is_none() || made.contains(&true) || lists > 0 {
            fill.bind = Some(gpu::buffers_bind_group(
                device,
                "gather blocks",
                &fill.pipeline.get_bind_group_layout(0),
                &[
                    &self.uniform,
                    self.bins.sorted(),
                    self.bins.starts(),
                    self.grid.buffer(),
                    fill.evaluated.buffer(),
                ],
            ));
            self.created += 1;
        }
        if slots > 0 {
            let mut pass = encoder.begin_compute_pass(&Default::default());
            pass.set_pipeline(&fill.pipeline);
            pass.set_bind_group(0, fill.bind.as_ref(), &[]);
            pass.dispatch_workgroups(BLOCK, slots.min(65_535), slots.div_ceil(65_535));
        }
        let sparse = GpuSparse {
            states: fill.states.buffer().clone(),
            inside,
            evaluated: slots,
        };
        Ok(self.grid_of(spec, binned, Some(sparse)))
    }

    /// [`Self::record_sparse_with`] with the layout found on the GPU (issue 37): `layout`
    /// records the blocks' states and the evaluated blocks from the binned points and their
    /// band over `domain` (after `before`), and the fill reads them there, dispatched
    /// indirectly by their count; nothing of the layout is made on the CPU or read back. The
    /// values hold `capacity` evaluated blocks (a block past them reads as empty; the count
    /// comes back a few frames late, [`GpuSparseLayout::plan`]). Errors as
    /// [`Self::record_sparse`].
    pub fn record_sparse_resident(
        &mut self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        (points, spec, inside, kernel): (Points<'_>, &GridSpec, f32, Kernel),
        (layout, domain, capacity): (&mut GpuSparseLayout, BandDomain, u32),
        before: Option<BeforeFill<'_>>,
    ) -> Result<GpuGrid, GpuError> {
        check_inputs(&points)?;
        let (device, queue) = (&ctx.device, &ctx.queue);
        let max_binding = gpu::max_binding(device);
        let blocks = super::sparse::blocks_of(spec)
            .map(u64::from)
            .iter()
            .product();
        let bytes = check_sparse_fill(spec, (u64::from(capacity), blocks), inside, max_binding)?;
        let (binned, made, _) = self.upload(ctx, encoder, &points, (spec, bytes))?;
        let mut before = before;
        if let Some(before) = before.as_mut() {
            before(encoder, FillPoints::Binned(&binned))?;
        }
        layout.record(
            ctx,
            encoder,
            (&binned, spec),
            (domain, points.max_radius()),
            capacity,
        )?;
        if let Some(before) = before.as_mut() {
            before(encoder, FillPoints::Laid)?;
        }
        self.created += layout.created();
        let fill = self.sparse.get_or_insert_with(|| SparseFill::new(device));
        let raw = RawGatherParams::new(spec, &binned, points.h, kernel, (0, capacity))
            .searching(self.search, points.len());
        queue.write_buffer(&self.uniform, 0, bytemuck::bytes_of(&raw));
        let evaluated = layout.evaluated();
        let stale = fill
            .resident_bind
            .as_ref()
            .is_none_or(|(e, _)| e != evaluated);
        if stale || made.contains(&true) {
            let bind = gpu::buffers_bind_group(
                device,
                "gather blocks (layout on the GPU)",
                &fill.pipeline.get_bind_group_layout(0),
                &[
                    &self.uniform,
                    self.bins.sorted(),
                    self.bins.starts(),
                    self.grid.buffer(),
                    evaluated,
                ],
            );
            fill.resident_bind = Some((evaluated.clone(), bind));
            self.created += 1;
        }
        {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("gather blocks"),
                timestamp_writes: None,
            });
            pass.set_pipeline(&fill.pipeline);
            pass.set_bind_group(0, fill.resident_bind.as_ref().map(|(_, b)| b), &[]);
            pass.dispatch_workgroups_indirect(layout.count(), 4);
        }
        let sparse = GpuSparse {
            states: layout.states().clone(),
            inside,
            evaluated: capacity,
        };
        Ok(self.grid_of(spec, binned, Some(sparse)))
    }
}

/// The bytes of a sparse grid's values for `slots` evaluated blocks of `spec` with `blocks`
/// blocks in all, refused when they or the blocks' states exceed `max_binding` or the inside
/// value is not finite.
fn check_sparse_fill(
    spec: &GridSpec,
    (slots, blocks): (u64, u64),
    inside: f32,
    max_binding: u64,
) -> Result<u64, GpuError> {
    let bytes = slots * BLOCK_VALUES as u64 * 4;
    if bytes > max_binding || blocks * 4 > max_binding || spec.cells() > u128::from(u32::MAX) {
        return Err(GpuError::Validation(format!(
            "a sparse grid of {slots} evaluated blocks ({bytes} bytes) and {blocks} block states exceeds the GPU's storage binding limit of {max_binding} bytes; make it on the CPU"
        )));
    }
    if !inside.is_finite() {
        return Err(GpuError::Validation(format!(
            "the inside value {inside} of a sparse grid must be finite"
        )));
    }
    Ok(bytes)
}

/// Fills the density grid on the GPU by `method`, handing slabs to `sink` in increasing z.
pub fn density_slabs_gpu(
    ctx: &GpuContext,
    points: Points<'_>,
    spec: &GridSpec,
    kernel: Kernel,
    method: GpuDensityMethod,
    sink: impl FnMut(u32, Vec<f32>),
) -> Result<(), GpuError> {
    match method {
        GpuDensityMethod::Splat => splat_slabs_gpu(ctx, points, spec, kernel, sink),
        GpuDensityMethod::Gather => gather_slabs_gpu(ctx, points, spec, kernel, sink),
    }
}

/// The whole density grid on the GPU by `method`.
pub fn density_grid_gpu_with(
    ctx: &GpuContext,
    points: Points<'_>,
    spec: &GridSpec,
    kernel: Kernel,
    method: GpuDensityMethod,
) -> Result<DensityGrid, GpuError> {
    let mut values = Vec::with_capacity(spec.cells() as usize);
    density_slabs_gpu(ctx, points, spec, kernel, method, |_, slab| {
        values.extend_from_slice(&slab)
    })?;
    Ok(DensityGrid {
        spec: *spec,
        values,
    })
}
