//! The points sorted into cubic bins over a grid's box, which the compute passes search (the
//! gather density, the boundary calibration's passes, the GPU surfels' projection): the CPU
//! reference ([`bin_particles`]) and its GPU twin ([`GpuBinSort`], `shaders/bin_sort.wgsl`),
//! which sorts them in the frame's encoder so that `GpuPipeline::prepare` only uploads them
//! (issue 37). Both are stable counting sorts by bin: within a bin the points keep their order
//! (the particles lead every bin, which the calibration's loops rely on), so the two give the
//! same points in the same order, bit for bit (tested in `tests/gpu.rs`).

use bytemuck::{Pod, Zeroable};
use glam::{UVec3, Vec3};

use super::gpu::{GATHER_REACH, RawPoint};
use super::{GridSpec, Points};
use crate::gpu::{self, GpuContext, GpuError};

/// Most bins (4 bytes each); beyond, bins grow larger than `h / reach`.
pub const MAX_BINS: u64 = 1 << 24;

/// How the compute passes' density sums search the bins (the boundary calibration's,
/// `pipeline::boundary::gpu::WeightPasses::set_search`, and the surfels' projection,
/// `surfels::gpu::ResidentSurfels::set_search`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum BinSearch {
    /// The passes' own search: each row of bins trimmed to the ball of the sum's radius, and
    /// the points of smaller radii (the sheet, the refined points) read only in the bins their
    /// largest radius reaches (every point left out adds an exact zero, or leaves a maximum as
    /// it is).
    #[default]
    Trimmed,
    /// Every point of every bin within the largest radius of all (the bins' reach): the search
    /// the trimmed one must equal bit for bit (tests and measurements).
    Whole,
}

/// The points the compute passes' density sums read in every bin within the largest radius
/// (the gather's `density_at`, the surfels' `density_and_gradient`): the first `leading`, up to
/// the last of the largest radius (the chain's particles, which come before its refined points);
/// and the largest radius of the others, which the sums read only in the bins that radius
/// reaches (the sums are the same: every point left out lies beyond its radius). All points lead
/// when they share one radius.
#[must_use]
pub fn leading_and_rest(points: &Points<'_>) -> (usize, f32) {
    let Some(radii) = points.radii else {
        return (points.len(), 0.0);
    };
    let largest = points.max_radius();
    let leading = radii
        .iter()
        .rposition(|&r| r >= largest)
        .map_or(0, |i| i + 1);
    let rest = radii[leading..].iter().copied().fold(0.0f32, f32::max);
    (leading, rest)
}

/// The bins over a grid's box: cubic, of side `size` (>= the largest radius / [`GATHER_REACH`]),
/// from the grid's origin, `bins` along each axis (x fastest).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BinLayout {
    pub origin: Vec3,
    pub size: f32,
    /// `1 / size`: a point's bin is `floor((x - origin) * inverse)`, the same product on the CPU
    /// and the GPU (a WGSL division may differ from the CPU's by 2.5 ulp, a product may not).
    pub inverse: f32,
    pub bins: [u32; 3],
}

impl BinLayout {
    /// Bins of side `h / reach` over the box of `spec`, larger by steps of 25 % while there
    /// would be more than [`MAX_BINS`].
    #[must_use]
    pub fn new(spec: &GridSpec, h: f32, reach: u32) -> Self {
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
        Self {
            origin: spec.origin,
            size,
            inverse: 1.0 / size,
            bins: counts(size).to_array(),
        }
    }

    /// The bins of the compute passes for `points` (sized for the largest radius; each point's
    /// kernel uses its own).
    #[must_use]
    pub fn of(points: &Points<'_>, spec: &GridSpec) -> Self {
        Self::new(spec, points.max_radius(), GATHER_REACH)
    }

    /// Slabs of `planes` planes of the grid of `spec` along z (one bin across x and y): the
    /// splatting's z-clusters (Iwasaki et al. §4.2), slab `s` holding the points from plane
    /// `s * planes` up to the next slab's.
    #[must_use]
    pub fn slabs(spec: &GridSpec, planes: u32) -> Self {
        let size = planes as f32 * spec.spacing;
        Self {
            origin: spec.origin,
            size,
            inverse: 1.0 / size,
            bins: [1, 1, spec.dims[2].div_ceil(planes).max(1)],
        }
    }

    /// The slabs of [`Self::slabs`] holding every point with z in `[lo, hi]`: the first and
    /// the last + 1, with a slab more on each side (a point's slab is found by a product that
    /// the GPU rounds as it may; the points of the slabs added lie farther from the planes than
    /// their radius and add zeros).
    #[must_use]
    pub fn slabs_within(&self, lo: f32, hi: f32) -> [u32; 2] {
        let last = self.bins[2] - 1;
        let slab = |z: f32| ((z - self.origin.z) * self.inverse).floor().max(0.0) as u32;
        [
            slab(lo).saturating_sub(1).min(last),
            (slab(hi) + 1).min(last) + 1,
        ]
    }

    /// How many bins.
    #[must_use]
    pub fn total(&self) -> usize {
        self.bins.iter().map(|&b| b as usize).product()
    }

    /// The bin holding `p` (clamped to the bins there are), as the WGSL's `bin_of`.
    #[must_use]
    pub fn bin_of(&self, p: Vec3) -> usize {
        let n = UVec3::from(self.bins);
        let b = ((p - self.origin) * self.inverse)
            .floor()
            .clamp(Vec3::ZERO, (n - 1).as_vec3())
            .as_uvec3();
        ((b.z * n.y + b.y) * n.x + b.x) as usize
    }
}

/// Points sorted into the bins of `layout` on the CPU (a stable counting sort): the sorted
/// points and the start of each bin (one more entry than bins: the last is the count). The
/// reference of [`GpuBinSort`].
#[must_use]
pub fn bin_particles(raw: &[RawPoint], layout: &BinLayout) -> (Vec<RawPoint>, Vec<u32>) {
    let total = layout.total();
    let mut start = vec![0u32; total + 1];
    let bin = |p: &RawPoint| layout.bin_of(Vec3::new(p.at[0], p.at[1], p.at[2]));
    for p in raw {
        start[bin(p) + 1] += 1;
    }
    for i in 0..total {
        start[i + 1] += start[i];
    }
    let mut next = start.clone();
    let mut sorted = vec![RawPoint::zeroed(); raw.len()];
    for p in raw {
        let b = bin(p);
        sorted[next[b] as usize] = *p;
        next[b] += 1;
    }
    (sorted, start)
}

/// The WGSL source of the sort (`common.wgsl` and `scan.wgsl` prepended; it reads and copies
/// the points as `IndexedPoint`s, so that the copies keep the index in the padding).
pub const SHADER: &str = concat!(
    include_str!("../../shaders/common.wgsl"),
    include_str!("../../shaders/scan.wgsl"),
    include_str!("../../shaders/bin_sort.wgsl")
);

/// The sort's `SortParams` (48 bytes, checked against the WGSL in a test).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct RawSortParams {
    pub origin: [f32; 3],
    pub inv_size: f32,
    pub bins: [u32; 3],
    pub count: u32,
    pub shift: u32,
    pub groups: u32,
    pub entries: u32,
    pub _pad: u32,
}

const _: () = assert!(std::mem::size_of::<RawSortParams>() == 48);

/// Counts each invocation of the counts' prefix sum adds in turn (`RUN` in the WGSL).
const COUNT_RUN: usize = 16;

/// Radix passes at most (8 bits each: bins' keys are below 2^24, three suffice).
const MAX_PASSES: usize = 4;

/// The sort's entry points, in the order [`GpuBinSort`] keeps their pipelines.
const ENTRIES: [&str; 8] = [
    "bin_keys",
    "count_blocks",
    "scan_blocks",
    "count_starts",
    "radix_histogram",
    "scan_table",
    "radix_scatter",
    "gather_points",
];

/// Workgroups of a two-dimensional dispatch covering `blocks` blocks of 256 (at most 65,535
/// along x).
pub(crate) fn dispatch_of(blocks: u32) -> (u32, u32) {
    let x = blocks.clamp(1, 65_535);
    (x, blocks.div_ceil(x))
}

/// The points sorted by bin on the GPU, recorded into a frame's encoder (see the module): the
/// points are uploaded in their order, every buffer is kept from frame to frame and grows
/// when a frame needs more.
pub struct GpuBinSort {
    pipelines: [wgpu::ComputePipeline; ENTRIES.len()],
    /// One slice per pass of the parameters (the counts' at 0, the radix passes' after), at
    /// the adapter's uniform offset alignment.
    uniform: wgpu::Buffer,
    stride: u64,
    points: gpu::Grow,
    pairs: [gpu::Grow; 2],
    starts: gpu::Grow,
    block_sums: gpu::Grow,
    sorted: gpu::Grow,
    table: gpu::Grow,
    /// The bind groups reading pairs `[0]` then `[1]`, and the other way.
    binds: Option<[wgpu::BindGroup; 2]>,
    created: usize,
}

impl GpuBinSort {
    /// Compiles the passes for `device`.
    #[must_use]
    pub fn new(device: &wgpu::Device) -> Self {
        let mut entries = vec![wgpu::BindGroupLayoutEntry {
            binding: 0,
            visibility: wgpu::ShaderStages::COMPUTE,
            ty: wgpu::BindingType::Buffer {
                ty: wgpu::BufferBindingType::Uniform,
                has_dynamic_offset: true,
                min_binding_size: wgpu::BufferSize::new(std::mem::size_of::<RawSortParams>() as u64),
            },
            count: None,
        }];
        let compute = wgpu::ShaderStages::COMPUTE;
        entries.push(gpu::entry::read_only(1, compute));
        entries.extend((2..8).map(|b| gpu::entry::storage(b, compute)));
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("bin sort"),
            entries: &entries,
        });
        let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("bin sort"),
            bind_group_layouts: &[Some(&layout)],
            ..Default::default()
        });
        let pipelines = gpu::compute_pipelines_with(
            device,
            ("bin_sort", SHADER),
            Some(&pipeline_layout),
            ENTRIES,
        );
        let stride = (std::mem::size_of::<RawSortParams>() as u64).next_multiple_of(u64::from(
            device.limits().min_uniform_buffer_offset_alignment,
        ));
        // (read back by the tests)
        let usage = wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC;
        Self {
            pipelines,
            uniform: crate::gpu::uniform_buffer(
                device,
                "bin sort params",
                stride * (1 + MAX_PASSES as u64),
            ),
            stride,
            points: gpu::Grow::new("unsorted points", usage),
            pairs: [
                gpu::Grow::new("bin sort pairs", usage),
                gpu::Grow::new("bin sort pairs", usage),
            ],
            starts: gpu::Grow::new("bin starts", usage),
            block_sums: gpu::Grow::new("bin sort block sums", usage),
            sorted: gpu::Grow::new("binned points", usage),
            table: gpu::Grow::new("radix table", usage),
            binds: None,
            created: 0,
        }
    }

    /// Buffers and bind groups the last [`Self::record`] made (0 once they are large enough).
    #[must_use]
    pub fn created(&self) -> usize {
        self.created
    }

    /// The sorted points (after [`Self::record`]'s work has run).
    #[must_use]
    pub fn sorted(&self) -> &wgpu::Buffer {
        self.sorted.buffer()
    }

    /// Where each bin's points start in [`Self::sorted`], one more entry than bins.
    #[must_use]
    pub fn starts(&self) -> &wgpu::Buffer {
        self.starts.buffer()
    }

    /// Uploads `raw` (in the points' order) and records their sort into the bins of `layout`
    /// into `encoder`; the sorted points and the bins' starts are in [`Self::sorted`] and
    /// [`Self::starts`] once the encoder's work has run. Refused when they exceed the
    /// adapter's storage binding limit. Whether buffers were made anew is in
    /// [`Self::created`].
    pub fn record(
        &mut self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        raw: &[RawPoint],
        layout: &BinLayout,
    ) -> Result<(), GpuError> {
        let (device, queue) = (&ctx.device, &ctx.queue);
        let max_binding = gpu::max_binding(device);
        let entries = layout.total() + 1;
        let n = raw.len();
        let groups = n.div_ceil(256);
        let table = 256 * groups;
        if (n.max(1) * 32) as u64 > max_binding
            || (entries * 4) as u64 > max_binding
            || (table * 4) as u64 > max_binding
            || n >= 1 << 31
        {
            return Err(GpuError::Validation(format!(
                "{n} points in {} bins exceed the GPU's storage binding limit of {max_binding} bytes; use the splatting method or the CPU path",
                entries - 1
            )));
        }
        let point_bytes: &[u8] = bytemuck::cast_slice(raw);
        let made = [
            self.points.write(device, queue, point_bytes),
            self.pairs[0].reserve(device, n as u64 * 8),
            self.pairs[1].reserve(device, n as u64 * 8),
            self.starts.reserve(device, entries as u64 * 4),
            self.block_sums
                .reserve(device, entries.div_ceil(256 * COUNT_RUN) as u64 * 4),
            self.sorted.reserve(device, n as u64 * 32),
            self.table.reserve(device, table as u64 * 4),
        ];
        self.created = made.iter().filter(|&&m| m).count();
        if self.binds.is_none() || self.created > 0 {
            // (the pipelines share the layout: any of them gives it)
            let bind = |a: usize| {
                gpu::bind_group(
                    device,
                    &self.pipelines[0],
                    &[
                        (
                            0,
                            wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                                buffer: &self.uniform,
                                offset: 0,
                                size: wgpu::BufferSize::new(
                                    std::mem::size_of::<RawSortParams>() as u64
                                ),
                            }),
                        ),
                        (1, self.points.buffer().as_entire_binding()),
                        (2, self.pairs[a].buffer().as_entire_binding()),
                        (3, self.pairs[1 - a].buffer().as_entire_binding()),
                        (4, self.starts.buffer().as_entire_binding()),
                        (5, self.block_sums.buffer().as_entire_binding()),
                        (6, self.sorted.buffer().as_entire_binding()),
                        (7, self.table.buffer().as_entire_binding()),
                    ],
                )
            };
            self.binds = Some([bind(0), bind(1)]);
            self.created += 2;
        }
        let binds = self.binds.as_ref().expect("made above");
        encoder.clear_buffer(self.starts.buffer(), 0, Some(entries as u64 * 4));
        if n == 0 {
            return Ok(());
        }
        // the parameters of each pass, at its slice of the uniform
        let bits = 32 - (entries as u32 - 2).leading_zeros();
        let passes = (bits.div_ceil(8) as usize).min(MAX_PASSES);
        let base = RawSortParams {
            origin: layout.origin.to_array(),
            inv_size: layout.inverse,
            bins: layout.bins,
            count: n as u32,
            shift: 0,
            groups: groups as u32,
            entries: entries as u32,
            _pad: 0,
        };
        let mut slices = vec![0u8; self.uniform.size() as usize];
        for p in 0..=passes {
            let params = if p == 0 {
                base
            } else {
                RawSortParams {
                    shift: 8 * (p as u32 - 1),
                    entries: table as u32,
                    ..base
                }
            };
            let at = p * self.stride as usize;
            slices[at..at + std::mem::size_of::<RawSortParams>()]
                .copy_from_slice(bytemuck::bytes_of(&params));
        }
        queue.write_buffer(&self.uniform, 0, &slices);
        let point_blocks = dispatch_of(groups as u32);
        let entry_blocks = dispatch_of(entries.div_ceil(256 * COUNT_RUN) as u32);
        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("bin sort"),
            timestamp_writes: None,
        });
        let mut run = |entry: usize, bind: usize, slice: usize, (x, y): (u32, u32)| {
            pass.set_pipeline(&self.pipelines[entry]);
            pass.set_bind_group(0, &binds[bind], &[(slice as u64 * self.stride) as u32]);
            pass.dispatch_workgroups(x, y, 1);
        };
        run(0, 0, 0, point_blocks);
        run(1, 0, 0, entry_blocks);
        run(2, 0, 0, (1, 1));
        run(3, 0, 0, entry_blocks);
        for p in 0..passes {
            // pass p reads pairs[p % 2] and writes the other
            let bind = p % 2;
            run(4, bind, p + 1, point_blocks);
            run(5, bind, p + 1, (1, 1));
            run(6, bind, p + 1, point_blocks);
        }
        run(7, passes % 2, 0, point_blocks);
        Ok(())
    }
}
