//! The density grid on the GPU, the twin of [`super::cpu`], two ways ([`GpuDensityMethod`]).
//! Every point carries its effective radius in the `w` of its `vec4` (the design chain's
//! per-point radii; one radius for all in the paper's case), combined as [`super::Points`] says:
//!
//! - splatting, the paper's method (Iwasaki et al., §4.1-4.2): for each group of four z planes,
//!   the particles of the group's z-cluster are drawn as instanced squares; the fragment shader
//!   adds each particle's kernel for the four planes into the R, G, B and A channels of an
//!   `Rgba32Float` target with additive blending; each instance's square is its own radius wide
//!   (a per-instance sprite size); the target is copied back. Only one group's target (and a
//!   batch of read-back copies) lives on the GPU, not the grid;
//! - gathering, a compute shader: particles binned on the CPU (bins of side >= the largest
//!   radius / [`GATHER_REACH`]), one invocation per grid point of a group of up to 32 planes sums
//!   the bins around it; the group is copied back. Again only a group of planes lives on the GPU.

use bytemuck::{Pod, Zeroable};
use glam::Vec3;

use super::{DensityGrid, GridSpec, Kernel, Points};
use crate::gpu::{self, GpuContext, GpuError};

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

/// The splatting method draws instances of `(x, y, z, radius)`: it refuses per-point weights
/// (the chain's boundary weights, issue 35), which the gather method sums.
fn refuse_weights(points: &Points<'_>) -> Result<(), GpuError> {
    if points.weights.is_some_and(|w| w.iter().any(|&x| x != 1.0)) {
        return Err(GpuError::Validation(
            "the splatting GPU density does not take per-point weights; use the gather method (GpuDensityMethod::Gather) or the CPU".into(),
        ));
    }
    Ok(())
}

/// A point as the compute passes read it (the WGSL `Point` of `common.wgsl`, 32 bytes): its
/// position and radius, and its weight in the density.
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
pub struct RawPoint {
    pub at: [f32; 4],
    pub weight: f32,
    pub _pad: [f32; 3],
}

const _: () = assert!(std::mem::size_of::<RawPoint>() == 32);

/// The points as the shaders read them: `(x, y, z, radius)`.
fn instances(points: &Points<'_>) -> Vec<[f32; 4]> {
    points
        .positions
        .iter()
        .enumerate()
        .map(|(i, p)| [p.x, p.y, p.z, points.radius(i)])
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

/// The points as instances `(x, y, z, radius)` sorted by z, uploaded, and their z in that order.
fn upload_sorted(device: &wgpu::Device, points: &Points<'_>) -> (wgpu::Buffer, Vec<f32>) {
    let mut sorted = instances(points);
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
    (instances, zs)
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
        entries: &[gpu::entry::uniform(0, wgpu::ShaderStages::VERTEX_FRAGMENT)],
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
    refuse_weights(&points)?;
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
    // particles sorted by z: each group's cluster is a contiguous instance range (§4.2)
    let (instances, zs) = upload_sorted(device, &points);
    use wgpu::util::DeviceExt;
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
                kernel: kernel_code(kernel),
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
            let z_lo = spec.origin.z + k0 as f32 * spec.spacing - reach;
            let z_hi = spec.origin.z + last as f32 * spec.spacing + reach;
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

/// How the GPU fills the density grid.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum GpuDensityMethod {
    /// The paper's method: particles drawn as point sprites into four planes per RGBA pass with
    /// additive blending ([`splat_slabs_gpu`]). The default: the faster of the two on lavapipe,
    /// the only adapter measured so far (150,000 particles into 256^3: 2.0-2.4 s against
    /// 5.1-6.2 s for the gather; see docs/design.md).
    #[default]
    Splat,
    /// A compute shader: particles binned by the CPU, one invocation per grid point gathers the
    /// bins around it ([`gather_slabs_gpu`]); no blending and no atomics, a fixed summation order.
    Gather,
}

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
}

const _: () = assert!(std::mem::size_of::<RawGatherParams>() == 80);

impl RawGatherParams {
    /// The parameters filling planes `k0 .. k0 + planes` of the grid of `spec` with `points`
    /// binned as `binned` (over the grid's box).
    fn new(
        spec: &GridSpec,
        binned: (&[u32; 3], f32),
        points: &Points<'_>,
        kernel: Kernel,
        (k0, planes): (u32, u32),
    ) -> Self {
        let h = points.h;
        Self {
            origin: spec.origin.to_array(),
            spacing: spec.spacing,
            dims: spec.dims,
            k0,
            bin_origin: spec.origin.to_array(),
            bin_size: binned.1,
            bins: *binned.0,
            planes,
            h,
            constant: kernel_constant(kernel, h),
            kernel: kernel_code(kernel),
            reach: GATHER_REACH,
        }
    }
}

/// The gather pass's bind group: its parameters, the binned points and their bins' starts, and
/// the grid values it writes.
fn gather_bind_group(
    device: &wgpu::Device,
    pipeline: &wgpu::ComputePipeline,
    [uniform, points, starts, out]: [&wgpu::Buffer; 4],
) -> wgpu::BindGroup {
    let entries: Vec<wgpu::BindGroupEntry<'_>> = [uniform, points, starts, out]
        .iter()
        .enumerate()
        .map(|(i, b)| wgpu::BindGroupEntry {
            binding: i as u32,
            resource: b.as_entire_binding(),
        })
        .collect();
    device.create_bind_group(&wgpu::BindGroupDescriptor {
        label: Some("gather"),
        layout: &pipeline.get_bind_group_layout(0),
        entries: &entries,
    })
}

/// Bins per `h` of the gather path: bins of side `h / GATHER_REACH`, searched `GATHER_REACH`
/// bins to each side; smaller bins waste fewer kernel evaluations on particles beyond h (a
/// searched volume of `(2.5 h)^3` instead of `(3 h)^3`, 0.58 as much). On lavapipe (150k particles into 256^3) 1 and 2 measured alike,
/// 5.1-6.2 s, within the run-to-run spread.
pub const GATHER_REACH: u32 = 2;

/// Most bins the gather path builds (4 bytes each); beyond, bins grow larger than `h`.
const MAX_BINS: u64 = 1 << 24;

/// Particles sorted into cubic bins of side >= `h / reach` over the grid's box: the sorted points,
/// the start of each bin (one more entry than bins), the bin counts and side.
fn bin_particles(
    points: &Points<'_>,
    spec: &GridSpec,
    h: f32,
    reach: u32,
) -> (Vec<RawPoint>, Vec<u32>, [u32; 3], f32) {
    let positions = points.positions;
    let extent = spec.spacing
        * Vec3::new(
            spec.dims[0].saturating_sub(1) as f32,
            spec.dims[1].saturating_sub(1) as f32,
            spec.dims[2].saturating_sub(1) as f32,
        );
    let mut size = h / reach as f32;
    let counts = |size: f32| (extent / size).floor().as_uvec3() + 1;
    while counts(size).as_u64vec3().element_product() > MAX_BINS {
        size *= 1.25;
    }
    let n = counts(size);
    let bin_of = |p: Vec3| {
        let b = ((p - spec.origin) / size)
            .floor()
            .clamp(Vec3::ZERO, (n - 1).as_vec3())
            .as_uvec3();
        ((b.z * n.y + b.y) * n.x + b.x) as usize
    };
    let total = n.as_u64vec3().element_product() as usize;
    let mut start = vec![0u32; total + 1];
    for &p in positions {
        start[bin_of(p) + 1] += 1;
    }
    for i in 0..total {
        start[i + 1] += start[i];
    }
    let mut next = start.clone();
    let mut sorted = vec![RawPoint::zeroed(); positions.len()];
    for (i, &p) in positions.iter().enumerate() {
        let b = bin_of(p);
        sorted[next[b] as usize] = RawPoint {
            at: [p.x, p.y, p.z, points.radius(i)],
            weight: points.weight(i),
            _pad: [0.0; 3],
        };
        next[b] += 1;
    }
    (sorted, start, n.to_array(), size)
}

/// Points binned on the CPU and checked against the binding limit `max_binding`: sorted
/// points, the bins' starts, the bin counts and side ([`bin_particles`] for the largest radius).
struct Bins {
    sorted: Vec<RawPoint>,
    start: Vec<u32>,
    bins: [u32; 3],
    size: f32,
}

impl Bins {
    fn new(points: &Points<'_>, spec: &GridSpec, max_binding: u64) -> Result<Self, GpuError> {
        // bins sized for the largest radius; each point's kernel uses its own
        let (sorted, start, bins, size) =
            bin_particles(points, spec, points.max_radius(), GATHER_REACH);
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
            bins,
            size,
        })
    }

    /// The sorted points as bytes (one zero point when there is none: a binding holds at
    /// least one).
    fn point_bytes(&self) -> &[u8] {
        static NONE: [RawPoint; 1] = [RawPoint {
            at: [0.0; 4],
            weight: 0.0,
            _pad: [0.0; 3],
        }];
        bytemuck::cast_slice(if self.sorted.is_empty() {
            &NONE[..]
        } else {
            &self.sorted[..]
        })
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
}

impl BinnedPoints {
    /// Bins `points` over the box of `spec` and uploads them.
    pub fn new(
        device: &wgpu::Device,
        points: &Points<'_>,
        spec: &GridSpec,
    ) -> Result<Self, GpuError> {
        let bins = Bins::new(points, spec, gpu::max_binding(device))?;
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
            bins: bins.bins,
            bin_size: bins.size,
            count: points.len(),
        })
    }
}

/// The gather pass's compute pipeline.
fn gather_pipeline(device: &wgpu::Device) -> wgpu::ComputePipeline {
    let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
        label: Some("density_gather"),
        source: wgpu::ShaderSource::Wgsl(GATHER_SHADER.into()),
    });
    device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
        label: Some("density gather"),
        layout: None,
        module: &module,
        entry_point: Some("gather"),
        compilation_options: Default::default(),
        cache: None,
    })
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
        let raw = RawGatherParams::new(
            spec,
            (&binned.bins, binned.bin_size),
            points,
            kernel,
            (k0, planes),
        );
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
/// ([`DensityGrid`]'s layout), for the passes that read it there ([`crate::surfels::gpu`]).
#[derive(Clone, Debug)]
pub struct GpuGrid {
    /// The grid.
    pub spec: GridSpec,
    /// One `f32` per grid point, index `i + nx (j + ny k)`.
    pub values: wgpu::Buffer,
    /// The points the grid was filled with, binned (the surfels' projection reads them).
    pub points: BinnedPoints,
}

impl GpuGrid {
    /// The values read back (a wait on the device: for tests and tools, never on a frame's
    /// path).
    pub fn read(&self, ctx: &GpuContext) -> Result<DensityGrid, GpuError> {
        let mut values: Vec<f32> = gpu::read_buffer(ctx, &self.values)?;
        values.truncate(self.spec.cells() as usize);
        Ok(DensityGrid {
            spec: self.spec,
            values,
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
    particles: gpu::Grow,
    bin_start: gpu::Grow,
    grid: gpu::Grow,
    bind: Option<wgpu::BindGroup>,
    created: usize,
}

impl GridFiller {
    /// Compiles the pass for `device`.
    #[must_use]
    pub fn new(device: &wgpu::Device) -> Self {
        let storage = wgpu::BufferUsages::STORAGE;
        Self {
            pipeline: gather_pipeline(device),
            uniform: device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("gather params"),
                size: std::mem::size_of::<RawGatherParams>() as u64,
                usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            }),
            particles: gpu::Grow::new("binned particles", storage),
            bin_start: gpu::Grow::new("bin starts", storage),
            grid: gpu::Grow::new("density grid", storage | wgpu::BufferUsages::COPY_SRC),
            bind: None,
            created: 0,
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
        let bins = Bins::new(&points, spec, max_binding)?;
        let made = [
            self.particles.write(device, queue, bins.point_bytes()),
            self.bin_start
                .write(device, queue, bytemuck::cast_slice(&bins.start)),
            self.grid.reserve(device, bytes as u64),
        ];
        self.created = made.iter().filter(|&&m| m).count();
        let raw = RawGatherParams::new(
            spec,
            (&bins.bins, bins.size),
            &points,
            kernel,
            (0, spec.dims[2]),
        );
        queue.write_buffer(&self.uniform, 0, bytemuck::bytes_of(&raw));
        if self.bind.is_none() || self.created > 0 {
            self.bind = Some(gather_bind_group(
                device,
                &self.pipeline,
                [
                    &self.uniform,
                    self.particles.buffer(),
                    self.bin_start.buffer(),
                    self.grid.buffer(),
                ],
            ));
            self.created += 1;
        }
        if bytes > 0 {
            let mut pass = encoder.begin_compute_pass(&Default::default());
            pass.set_pipeline(&self.pipeline);
            pass.set_bind_group(0, self.bind.as_ref(), &[]);
            pass.dispatch_workgroups(
                spec.dims[0].div_ceil(8),
                spec.dims[1].div_ceil(8),
                spec.dims[2],
            );
        }
        Ok(GpuGrid {
            spec: *spec,
            values: self.grid.buffer().clone(),
            points: BinnedPoints {
                points: self.particles.buffer().clone(),
                starts: self.bin_start.buffer().clone(),
                bins: bins.bins,
                bin_size: bins.size,
                count: points.len(),
            },
        })
    }
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
