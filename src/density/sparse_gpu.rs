//! The sparse density grid's layout on the GPU (issue 37), the twin of
//! [`super::sparse_layout`]: which blocks of [`BLOCK`]^3 grid points are empty, inside or
//! evaluated, and the evaluated blocks' slots in block order, found in a frame's encoder from
//! the points the density's passes read (the binned points, [`BinnedPoints`]) and the LNM band
//! of the same points kept on the GPU ([`ResidentBand`]), so that no layout is made on the CPU
//! and nothing is read back: the fill reads the evaluated blocks and their count from the
//! buffers here (the count also as an indirect dispatch).
//!
//! `shaders/sparse_layout.wgsl`: one invocation per block decides its state with the CPU's
//! arithmetic (inside: every band voxel its closed range covers is interior, which the CPU
//! counts voxel by voxel and the GPU checks block by block; evaluated: a point's ball, its
//! radius times [`super::sparse::REACH_MARGIN`], reaches the closed range; the CPU searches the
//! points of the blocks within reach, the GPU those of the bins within reach, and both find
//! every point that reaches), then a compaction in block order. The states and the evaluated
//! blocks equal the CPU's exactly (tested in `tests/gpu.rs`).

use rayon::prelude::*;

use super::gpu::BinnedPoints;
use super::sparse::{BLOCK, REACH_MARGIN, SparseLayout, blocks_of};
use super::{GridSpec, Points};
use crate::gpu::{self, GpuContext, GpuError};
use crate::lnm::LnmParams;
use crate::lnm::gpu::{BandDomain, ResidentBand};

/// The WGSL of the passes.
pub const SHADER: &str = concat!(
    include_str!("../../shaders/common.wgsl"),
    include_str!("../../shaders/scan.wgsl"),
    include_str!("../../shaders/sparse_layout.wgsl")
);

/// The passes' uniforms (`LayoutParams` in the WGSL, 128 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct RawLayoutParams {
    /// the grid's first point and spacing
    pub origin: [f32; 3],
    pub spacing: f32,
    /// grid points along x, y, z; the binned points
    pub dims: [u32; 3],
    pub count: u32,
    /// blocks along x, y, z; all blocks
    pub blocks: [u32; 3],
    pub total: u32,
    /// the band's minimum corner, 1 / its voxel's edge
    pub band_lo: [f32; 3],
    pub band_inv: f32,
    /// the band's voxels along x, y, z; the evaluated blocks the values hold (a slot past them:
    /// the block read as empty)
    pub band_dims: [u32; 3],
    pub capacity: u32,
    /// the bins' origin, 1 / a bin's side
    pub bin_origin: [f32; 3],
    pub bin_inv: f32,
    /// bins along x, y, z
    pub bins: [u32; 3],
    pub _pad1: u32,
    /// the largest radius times the margin; the margin
    pub reach: f32,
    pub margin: f32,
    pub _pad2: [u32; 2],
}

const _: () = assert!(std::mem::size_of::<RawLayoutParams>() == 128);

/// The passes' entry points, in the order they run.
const ENTRIES: [&str; 4] = [
    "block_states",
    "layout_count_blocks",
    "layout_scan",
    "layout_scatter",
];

/// Bytes of the count buffer: the evaluated blocks' count, then the fill's indirect dispatch.
const COUNT_BYTES: u64 = 16;

/// The sparse grid's layout found on the GPU (see the module): its buffers kept from frame to
/// frame, grown when a frame needs more.
pub struct GpuSparseLayout {
    band: ResidentBand,
    pipelines: [wgpu::ComputePipeline; ENTRIES.len()],
    uniform: wgpu::Buffer,
    states: gpu::Grow,
    evaluated: gpu::Grow,
    scan: gpu::Grow,
    count: gpu::Grow,
    /// The binned points and starts bound, and each pass's bind group.
    binds: Option<(wgpu::Buffer, wgpu::Buffer, [wgpu::BindGroup; ENTRIES.len()])>,
    /// The last layout's grid and blocks.
    last: Option<(GridSpec, [u32; 3])>,
    /// The evaluated blocks' count, read back a few frames late (no wait).
    readback: gpu::AsyncRead,
    /// The frame whose count is being read back.
    pending: Option<Counted>,
    /// The frame whose count came back last.
    counted: Option<Counted>,
    /// The evaluated blocks the last frame's values held.
    capacity: u32,
    created: usize,
}

/// A frame whose evaluated blocks were counted: the count (once read back), its points, its
/// grid's spacing and the blocks its values held.
#[derive(Clone, Copy, Debug)]
struct Counted {
    blocks: u32,
    points: usize,
    spacing: f32,
    capacity: u32,
}

impl GpuSparseLayout {
    /// Compiles the passes for `device`.
    #[must_use]
    pub fn new(device: &wgpu::Device) -> Self {
        let usage = wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC;
        Self {
            band: ResidentBand::new(device),
            pipelines: gpu::compute_pipelines(device, "sparse layout", SHADER, ENTRIES),
            uniform: crate::gpu::uniform_buffer(
                device,
                "sparse layout params",
                std::mem::size_of::<RawLayoutParams>() as u64,
            ),
            states: gpu::Grow::new("sparse block states", usage),
            evaluated: gpu::Grow::new("sparse evaluated blocks", usage),
            scan: gpu::Grow::new("sparse layout scan", usage),
            count: gpu::Grow::new(
                "sparse evaluated count",
                usage | wgpu::BufferUsages::INDIRECT,
            ),
            binds: None,
            last: None,
            readback: gpu::AsyncRead::new(device, "sparse evaluated count readback", 4),
            pending: None,
            counted: None,
            capacity: 0,
            created: 0,
        }
    }

    /// The evaluated blocks the next frame's values are to hold, at most `limit`, never less
    /// than the last frame's (the buffer only grows). From a recent frame's count, read back a
    /// few frames late, where that frame is like this one (it fitted its values, this frame
    /// has at most a quarter more points and a grid spacing within a tenth of its): half
    /// again that count once it comes within a quarter of the capacity, no work on the CPU.
    /// Otherwise (no count yet, a count that did not fit, a frame unlike the counted one: a
    /// new body, another level of detail) [`evaluated_bound`] of `points` on `spec`, an upper
    /// bound known before the pass (one pass over the points on the CPU). Takes the count of a
    /// finished read-back first.
    pub fn plan(&mut self, points: &Points<'_>, spec: &GridSpec, limit: u32) -> u32 {
        self.take_count();
        let like = self.counted.filter(|c| {
            c.blocks <= c.capacity
                && points.len() as f64 <= 1.25 * c.points as f64
                && (spec.spacing / c.spacing - 1.0).abs() <= 0.1
        });
        let wanted = match like {
            Some(c) if c.blocks.saturating_add(c.blocks / 4) > self.capacity => {
                c.blocks.saturating_add(c.blocks / 2)
            }
            Some(_) => self.capacity,
            None => evaluated_bound(points, spec).min(u64::from(u32::MAX)) as u32,
        };
        wanted.max(self.capacity).max(64).min(limit)
    }

    /// Lets the evaluated count of the frame just submitted come back: call it once the
    /// encoder [`Self::record`] recorded into is submitted.
    pub fn after_submit(&mut self) {
        self.readback.after_submit();
    }

    fn take_count(&mut self) {
        if let Some(bytes) = self.readback.take() {
            let blocks = bytes
                .get(..4)
                .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]));
            self.counted = self
                .pending
                .take()
                .zip(blocks)
                .map(|(c, blocks)| Counted { blocks, ..c });
        }
    }

    /// The evaluated blocks of the frame whose count came back last (`None` before one has).
    #[must_use]
    pub fn last_count(&self) -> Option<u32> {
        self.counted.map(|c| c.blocks)
    }

    /// The evaluated blocks the last recorded frame's values held.
    #[must_use]
    pub fn capacity(&self) -> u32 {
        self.capacity
    }

    /// Whether the frame whose count came back last had more evaluated blocks than its values
    /// held (those past them read as empty).
    #[must_use]
    pub fn overflowed(&self) -> bool {
        self.counted.is_some_and(|c| c.blocks > c.capacity)
    }

    /// The evaluated blocks the values held in the frame whose count came back last.
    #[must_use]
    pub fn counted_capacity(&self) -> Option<u32> {
        self.counted.map(|c| c.capacity)
    }

    /// Records the layout of the grid `spec` over the points `binned` (binned over the box of
    /// `spec`), whose band has the voxels of `domain` ([`ResidentBand::domain`] of the same
    /// points and their largest radius) and whose largest radius is `largest`, into `encoder`,
    /// for values that hold `capacity` evaluated blocks (a block past them reads as empty).
    /// Refused when the blocks' states exceed the GPU's storage binding limit.
    pub fn record(
        &mut self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        (binned, spec): (&BinnedPoints, &GridSpec),
        (domain, largest): (BandDomain, f32),
        capacity: u32,
    ) -> Result<(), GpuError> {
        let (device, queue) = (&ctx.device, &ctx.queue);
        let blocks = blocks_of(spec);
        let total = blocks.iter().map(|&b| u64::from(b)).product::<u64>();
        let max_binding = gpu::max_binding(device);
        if total * 4 > max_binding || total >= u64::from(u32::MAX - 1) {
            return Err(GpuError::Validation(format!(
                "a sparse grid of {total} blocks exceeds the GPU's storage binding limit of {max_binding} bytes for its states; make it on the CPU"
            )));
        }
        let count = u32::try_from(binned.count)
            .map_err(|_| GpuError::Validation(format!("{} points are too many", binned.count)))?;
        self.band.record(
            ctx,
            encoder,
            (&binned.points, 2, count),
            domain,
            LnmParams::default().n_min,
        )?;
        let scan_groups = total.div_ceil(256);
        let made = [
            self.states.reserve(device, total * 4),
            self.evaluated.reserve(device, total * 4),
            self.scan.reserve(device, scan_groups * 4),
            self.count.reserve(device, COUNT_BYTES),
        ];
        self.created = self.band.created() + made.iter().filter(|&&m| m).count();
        let stale = self
            .binds
            .as_ref()
            .is_none_or(|(p, s, _)| *p != binned.points || *s != binned.starts);
        if self.created > 0 || stale {
            let entries: [(u32, &wgpu::Buffer); 9] = [
                (0, &self.uniform),
                (1, &binned.points),
                (2, &binned.starts),
                (3, self.band.counts()),
                (4, self.band.labels()),
                (5, self.states.buffer()),
                (6, self.evaluated.buffer()),
                (7, self.scan.buffer()),
                (8, self.count.buffer()),
            ];
            // each pass's derived layout holds the bindings it uses
            let used: [&[u32]; ENTRIES.len()] =
                [&[0, 1, 2, 3, 4, 5], &[0, 5, 7], &[0, 7], &[0, 5, 6, 7, 8]];
            let binds = std::array::from_fn(|i| {
                let buffers: Vec<(u32, &wgpu::Buffer)> = entries
                    .iter()
                    .filter(|(b, _)| used[i].contains(b))
                    .copied()
                    .collect();
                gpu::buffer_bind_group(device, &self.pipelines[i], &buffers)
            });
            self.binds = Some((binned.points.clone(), binned.starts.clone(), binds));
            self.created += ENTRIES.len();
        }
        let (lo, edge, band_dims) = domain;
        let raw = RawLayoutParams {
            origin: spec.origin.to_array(),
            spacing: spec.spacing,
            dims: spec.dims,
            count,
            blocks,
            total: total as u32,
            band_lo: lo.to_array(),
            band_inv: 1.0 / edge,
            band_dims,
            capacity,
            bin_origin: spec.origin.to_array(),
            bin_inv: 1.0 / binned.bin_size,
            bins: binned.bins,
            reach: largest * REACH_MARGIN,
            margin: REACH_MARGIN,
            ..Default::default()
        };
        queue.write_buffer(&self.uniform, 0, bytemuck::bytes_of(&raw));
        self.last = Some((*spec, blocks));
        self.capacity = capacity;
        let (_, _, binds) = self.binds.as_ref().expect("made above");
        let (sx, sy) = crate::lnm::gpu::groups(total);
        let scan = super::bins::dispatch_of(scan_groups as u32);
        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("sparse layout"),
            timestamp_writes: None,
        });
        for (i, (x, y)) in [(sx, sy), scan, (1, 1), scan].into_iter().enumerate() {
            pass.set_pipeline(&self.pipelines[i]);
            pass.set_bind_group(0, &binds[i], &[]);
            pass.dispatch_workgroups(x, y, 1);
        }
        drop(pass);
        if self.readback.copy(encoder, self.count.buffer(), 0) {
            self.pending = Some(Counted {
                blocks: 0,
                points: binned.count,
                spacing: spec.spacing,
                capacity,
            });
        }
        Ok(())
    }

    /// Per block (x fastest): `u32::MAX` empty, `u32::MAX - 1` inside, else its slot (after
    /// [`Self::record`]'s work has run).
    #[must_use]
    pub fn states(&self) -> &wgpu::Buffer {
        self.states.buffer()
    }

    /// The evaluated blocks' indices in slot order (block order).
    #[must_use]
    pub fn evaluated(&self) -> &wgpu::Buffer {
        self.evaluated.buffer()
    }

    /// The evaluated blocks' count (a `u32` at 0), then the workgroups of the fill's
    /// `gather_blocks` (three `u32` at 4: an indirect dispatch's arguments).
    #[must_use]
    pub fn count(&self) -> &wgpu::Buffer {
        self.count.buffer()
    }

    /// Buffers and bind groups the last [`Self::record`] made (0 once they are large enough).
    #[must_use]
    pub fn created(&self) -> usize {
        self.created
    }

    /// The last recorded layout, read back (waits on the device: tests and offline use, never
    /// the frame path).
    pub fn read(&self, ctx: &GpuContext) -> Result<SparseLayout, GpuError> {
        let Some((spec, blocks)) = self.last else {
            return Err(GpuError::Validation("no layout was recorded".into()));
        };
        let total = blocks.iter().map(|&b| b as usize).product::<usize>();
        let mut states: Vec<u32> = gpu::read_buffer(ctx, self.states.buffer())?;
        states.truncate(total);
        let count: Vec<u32> = gpu::read_buffer(ctx, self.count.buffer())?;
        let mut evaluated: Vec<u32> = gpu::read_buffer(ctx, self.evaluated.buffer())?;
        evaluated.truncate(count[0] as usize);
        Ok(SparseLayout {
            spec,
            blocks,
            states,
            evaluated,
        })
    }
}

/// The sparse layout of `points` on the grid `spec` made on the GPU of `ctx` and read back:
/// [`super::sparse_layout`]'s states and evaluated blocks (tests, offline use). The band's
/// voxels are those of [`crate::lnm::narrow_band`] over the points and their largest radius.
pub fn sparse_layout_gpu(
    ctx: &GpuContext,
    points: Points<'_>,
    spec: &GridSpec,
) -> Result<SparseLayout, crate::Error> {
    points.check()?;
    let largest = points.max_radius();
    let domain = ResidentBand::domain(points.positions, largest, &LnmParams::default())?;
    let binned = BinnedPoints::new(&ctx.device, &points, spec)?;
    let mut layout = GpuSparseLayout::new(&ctx.device);
    let mut encoder = ctx.device.create_command_encoder(&Default::default());
    let capacity = blocks_of(spec).iter().product::<u32>();
    layout.record(
        ctx,
        &mut encoder,
        (&binned, spec),
        (domain, largest),
        capacity,
    )?;
    ctx.queue.submit([encoder.finish()]);
    Ok(layout.read(ctx)?)
}

/// An upper bound of the blocks [`super::sparse_layout`] evaluates for `points` on `spec`,
/// found without the layout: the blocks whose closed range a point's ball (its radius times the
/// margin, and a slack for rounding) could reach along each axis. Why it bounds: block `b` is
/// evaluated only where a point's ball reaches its closed range, from `b` to `b + 1` blocks
/// (`side` wide), so `x - r < (b + 1) side` and `x + r > b side`: `b` lies from
/// `floor((x - r) / side)` to `floor((x + r) / side)` (a point outside the grid is clamped
/// into it, which only adds blocks). One parallel pass over the points, at most eight blocks
/// each where a radius is under a block's side (about 1-2 ms for 40,000 points on this
/// project's 2-core machine, with lavapipe's GPU work beside it).
#[must_use]
pub fn evaluated_bound(points: &Points<'_>, spec: &GridSpec) -> u64 {
    let n = blocks_of(spec).map(|b| b as usize);
    let total = n.iter().product::<usize>();
    if points.is_empty() || total == 0 {
        return 0;
    }
    // 1 / a block's side: a product rounds differently from the division, well within the slack
    let inv = 1.0 / (BLOCK as f32 * spec.spacing);
    let at = |v: f32, n: usize| (v.max(0.0) as usize).min(n - 1);
    let origin_slack = 1e-5 * spec.origin.abs().max_element() + 1e-4 * spec.spacing;
    // one bit per block, per chunk of points, joined
    let words = total.div_ceil(64);
    let reached = (0..points.len())
        .into_par_iter()
        .with_min_len(4096)
        .fold(
            || vec![0u64; words],
            |mut bits, i| {
                let x = points.positions[i];
                let d = x - spec.origin;
                // the rounding of the grid's points and of these sums: relative to the
                // coordinates
                let r =
                    points.radius(i) * REACH_MARGIN + 1e-5 * x.abs().max_element() + origin_slack;
                let lo = ((d - r) * inv).floor();
                let hi = ((d + r) * inv).floor();
                let (x0, x1) = (at(lo.x, n[0]), at(hi.x, n[0]));
                for z in at(lo.z, n[2])..=at(hi.z, n[2]) {
                    for y in at(lo.y, n[1])..=at(hi.y, n[1]) {
                        let row = n[0] * (y + n[1] * z);
                        for b in row + x0..=row + x1 {
                            bits[b / 64] |= 1 << (b % 64);
                        }
                    }
                }
                bits
            },
        )
        .reduce(
            || vec![0u64; words],
            |mut a, b| {
                a.iter_mut().zip(&b).for_each(|(a, b)| *a |= b);
                a
            },
        );
    reached.iter().map(|w| u64::from(w.count_ones())).sum()
}
