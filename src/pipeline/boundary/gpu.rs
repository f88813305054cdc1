//! The boundary calibration on the GPU (issue 37): the twin of [`super::boundary_weights`] and of
//! the factors of [`super::chain_input_at_boundary`] (which particles form a sheet one
//! particle thick, how buried each point is), the CPU stages that were left in
//! [`crate::pipeline::GpuPipeline`]'s `prepare` (54, then 8.7 ms of the game loop's frame on
//! lavapipe's machine). Every point carries two weights (its `split`): its share in the
//! interior and its own weight as a sheet point, which the solved weight multiplies. Given the
//! particles as the leading points ([`Split::Found`]), two passes find the split; the points
//! are binned as the gather pass bins them ([`BinnedPoints`], each keeping its index), one pass
//! finds each sheet point's target, how alone it is, its lone ball's weight and the interior's
//! density at the target, and [`WEIGHT_STEPS`] Jacobi passes solve the weights, ping-ponging
//! between two buffers. The sums run over the bins, not the CPU's cell grids, so the weights
//! agree with the CPU's to rounding (`tests/gpu.rs` measures how closely), not bit for bit.
//!
//! [`WeightPasses::record`] records the passes into the caller's encoder, writes each binned
//! point's weight in the density (the gather pass and the surfels then read them) and leaves
//! the solved weights in a buffer (no read-back); [`boundary_weights_gpu`] and
//! [`boundary_factors_gpu`] read them back, for tests and one-off use.

use bytemuck::{Pod, Zeroable};
use glam::Vec3;

use super::{BAND, BURIED, LONE_RADIUS, MAX_WEIGHT, WEIGHT_STEPS};
use crate::density::bins::{BinLayout, GpuBinSort};
use crate::density::gpu::{BinnedPoints, GATHER_REACH, kernel_code, kernel_constant, raw_points};
use crate::density::{GridSpec, Kernel, Points, Resolution};
use crate::gpu::{self, GpuContext, GpuError};
use crate::surface::Surface;

/// The WGSL of the passes.
pub const SHADER: &str = concat!(
    include_str!("../../../shaders/common.wgsl"),
    include_str!("../../../shaders/scan.wgsl"),
    include_str!("../../../shaders/eigen.wgsl"),
    include_str!("../../../shaders/boundary_weights.wgsl")
);

/// The passes' `WeightParams` uniform (80 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
pub struct RawWeightParams {
    pub bin_origin: [f32; 3],
    pub bin_size: f32,
    pub bins: [u32; 3],
    pub reach: u32,
    pub constant: f32,
    pub kernel: u32,
    pub particles: u32,
    pub count: u32,
    pub half_spacing: f32,
    pub tau: f32,
    pub lone_r2: f32,
    pub max_weight: f32,
    pub buried: f32,
    pub band: f32,
    /// The points that may have an interior share: the first `leading` (the particles with
    /// [`Split::Found`]); the others are the sheet.
    pub leading: u32,
    /// The others' (the sheet's) largest radius; negative: every point of every bin within
    /// `reach` read ([`BinSearch::Whole`]).
    pub sheet_radius: f32,
}

const _: () = assert!(std::mem::size_of::<RawWeightParams>() == 80);

/// A point as the passes read it (`SheetPoint`): position and kernel radius, outward normal
/// (zero: none; a particle's found on the GPU with [`Split::Found`]), `w` unused.
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
pub struct RawSheetPoint {
    pub at: [f32; 4],
    pub normal: [f32; 4],
}

/// The weight [`PointWeights::record_layout`] gives a point the calibration's factors leave out
/// (mirror: `DROPPED` in shaders/boundary_weights.wgsl): negative, which no weight is, so the
/// ray caster draws no sphere for it and takes it for no neighbour (shaders/raycast.wgsl).
pub const DROPPED: f32 = -1.0;

/// Bytes of a `Target` (target and how alone, lone weight, interior density, padding).
const TARGET_BYTES: u64 = 32;

/// Bytes of an `IndexedPoint` (a binned point).
const POINT_BYTES: u64 = std::mem::size_of::<crate::density::gpu::RawPoint>() as u64;

pub use crate::density::bins::BinSearch;

/// Where the points' split (interior share, sheet weight) comes from.
#[derive(Clone, Copy, Debug)]
pub enum Split<'a> {
    /// Given per point.
    Given(&'a [[f32; 2]]),
    /// Found on the GPU: the leading `classes.len()` points are the particles themselves, with
    /// their surface normals and classes ([`super::BoundaryLayout::classes`]); the rest are the sheet
    /// ([`super::chain_input_at_boundary`]'s factors, uncompacted: a point it leaves out gets
    /// the split `[0, 0]`).
    Found { classes: &'a [[f32; 4]] },
}

/// The compute pipelines, built once per device, and their buffers, kept from frame to frame
/// (grown when a frame needs more) with their bind groups (made anew only when a buffer they
/// hold changes).
pub struct WeightPasses {
    thin: wgpu::ComputePipeline,
    factors: wgpu::ComputePipeline,
    targets: wgpu::ComputePipeline,
    step: wgpu::ComputePipeline,
    step_whole: wgpu::ComputePipeline,
    apply: wgpu::ComputePipeline,
    /// The compaction of the points with a sheet weight, which the steps read
    /// ([`BinSearch::Trimmed`]): per block of 256 binned points their count, the blocks' first
    /// slots, the points and the prefix.
    sheet_count: wgpu::ComputePipeline,
    sheet_scan: wgpu::ComputePipeline,
    sheet_scatter: wgpu::ComputePipeline,
    /// The compacted points' solved weights written back to their points.
    sheet_back: wgpu::ComputePipeline,
    /// The weights in the density in the points' own order ([`Self::write_ordered`]).
    ordered: wgpu::ComputePipeline,
    uniform: wgpu::Buffer,
    sheet: gpu::Grow,
    split: gpu::Grow,
    classes: gpu::Grow,
    share: gpu::Grow,
    target_buf: gpu::Grow,
    w: [gpu::Grow; 2],
    sheet_prefix: gpu::Grow,
    sheet_blocks: gpu::Grow,
    sheet_binned: gpu::Grow,
    /// The compacted points' weights through the steps (in their order), ping-ponged.
    sheet_w: [gpu::Grow; 2],
    /// The bind groups ([`Binds`]) and the binned buffers they hold.
    binds: Option<([wgpu::Buffer; 2], Binds)>,
    /// The application to another copy of the points ([`Self::apply_to`]): that copy, the
    /// solved weights' buffer it reads, the bind group.
    copy_bind: Option<(wgpu::Buffer, wgpu::Buffer, wgpu::BindGroup)>,
    /// The weights in order ([`Self::write_ordered`]): the buffer written, the solved
    /// weights' buffer read, the bind group.
    ordered_bind: Option<(wgpu::Buffer, wgpu::Buffer, wgpu::BindGroup)>,
    created: usize,
    search: BinSearch,
}

/// What [`WeightPasses::record`] solves for: the binned points (each keeping its index in the
/// chain's order) over the box from `origin`, every point as a sheet point, and the split.
pub struct WeightInput<'a> {
    pub binned: &'a BinnedPoints,
    pub origin: Vec3,
    /// Every point, in the chain's order: position and kernel radius, normal.
    pub sheet: &'a [RawSheetPoint],
    pub split: Split<'a>,
    /// Half a particle spacing, the iso-value, the kernel and the reference radius.
    pub half_spacing: f32,
    pub tau: f32,
    pub kernel: Kernel,
    pub h: f32,
}

impl WeightPasses {
    /// Compiles the passes.
    #[must_use]
    pub fn new(device: &wgpu::Device) -> Self {
        let [
            thin,
            factors,
            targets,
            step,
            step_whole,
            apply,
            sheet_count,
            sheet_scan,
            sheet_scatter,
            sheet_back,
            ordered,
        ] = gpu::compute_pipelines(
            device,
            "boundary weights",
            SHADER,
            [
                "thin_pass",
                "factors_pass",
                "targets_pass",
                "step",
                "step_whole",
                "apply",
                "sheet_count",
                "sheet_scan",
                "sheet_scatter",
                "sheet_weights_back",
                "ordered",
            ],
        );
        let storage = wgpu::BufferUsages::STORAGE;
        Self {
            thin,
            factors,
            targets,
            step,
            step_whole,
            apply,
            sheet_count,
            sheet_scan,
            sheet_scatter,
            sheet_back,
            ordered,
            uniform: crate::gpu::uniform_buffer(
                device,
                "boundary weights params",
                std::mem::size_of::<RawWeightParams>() as u64,
            ),
            sheet: gpu::Grow::new("sheet points", storage | wgpu::BufferUsages::COPY_SRC),
            split: gpu::Grow::new("points' split", storage | wgpu::BufferUsages::COPY_SRC),
            classes: gpu::Grow::new("particle classes", storage),
            share: gpu::Grow::new("thin sheet shares", storage),
            target_buf: gpu::Grow::new("sheet targets", storage),
            w: [
                gpu::Grow::new("sheet weights a", storage | wgpu::BufferUsages::COPY_SRC),
                gpu::Grow::new("sheet weights b", storage | wgpu::BufferUsages::COPY_SRC),
            ],
            sheet_prefix: gpu::Grow::new("sheet points' prefix", storage),
            sheet_blocks: gpu::Grow::new("sheet points' blocks", storage),
            sheet_binned: gpu::Grow::new("sheet points compacted", storage),
            sheet_w: [
                gpu::Grow::new("compacted sheet weights a", storage),
                gpu::Grow::new("compacted sheet weights b", storage),
            ],
            binds: None,
            copy_bind: None,
            ordered_bind: None,
            created: 0,
            search: BinSearch::Trimmed,
        }
    }

    /// How the next [`Self::record`]s search the bins (the default: [`BinSearch::Trimmed`]).
    pub fn set_search(&mut self, search: BinSearch) {
        self.search = search;
    }

    /// Buffers and bind groups the last [`Self::record`] made (0 once they are large enough).
    #[must_use]
    pub fn created(&self) -> usize {
        self.created
    }

    /// The points' split of the last [`Self::record`]: `[f32; 2]` a point (interior share,
    /// sheet weight), in the chain's order.
    #[must_use]
    pub fn split(&self) -> &wgpu::Buffer {
        self.split.buffer()
    }

    /// Records the passes into `encoder` (with [`Split::Found`], the two that find the split
    /// first), then the weights' application: each binned point's weight in `input.binned`
    /// becomes its interior share plus its sheet weight times its solved one, in place (the
    /// binned points must be those the grid is then filled from). The solved weights
    /// themselves (`f32` a point, in the chain's order; 1 where the sheet weight is 0) are
    /// left in the returned buffer.
    pub fn record(
        &mut self,
        (device, queue): (&wgpu::Device, &wgpu::Queue),
        encoder: &mut wgpu::CommandEncoder,
        input: &WeightInput<'_>,
    ) -> Result<wgpu::Buffer, GpuError> {
        self.record_marked((device, queue), encoder, input, &mut |_, _| {})
    }

    /// [`Self::record`], calling `mark` between its passes with the name of the one just
    /// recorded (`"calibration: factors"`, `"calibration: targets"`, `"calibration:
    /// compaction"`, `"calibration: steps"`, `"calibration: apply"`), so that a caller can write
    /// a timestamp there (`GpuPipeline::gpu_pass_ms`).
    pub fn record_marked(
        &mut self,
        (device, queue): (&wgpu::Device, &wgpu::Queue),
        encoder: &mut wgpu::CommandEncoder,
        input: &WeightInput<'_>,
        mark: &mut dyn FnMut(&mut wgpu::CommandEncoder, &'static str),
    ) -> Result<wgpu::Buffer, GpuError> {
        let n = input.sheet.len();
        let limit = gpu::max_binding(device);
        if (n as u64).max(1) * TARGET_BYTES > limit {
            return Err(GpuError::Validation(format!(
                "{n} points exceed the GPU's storage binding limit of {limit} bytes; use the CPU calibration"
            )));
        }
        let particles = match input.split {
            Split::Given(split) => {
                if split.len() != n {
                    return Err(GpuError::Validation(format!(
                        "{} splits for {n} points: one a point",
                        split.len()
                    )));
                }
                0
            }
            Split::Found { classes } => {
                if classes.len() > n {
                    return Err(GpuError::Validation(format!(
                        "{} particles' classes for {n} points: the particles lead the points",
                        classes.len()
                    )));
                }
                classes.len()
            }
        };
        // the points with an interior share lead (the particles, or the given shares' last
        // nonzero one and those before it)
        let leading = match (self.search, input.split) {
            (BinSearch::Whole, _) => n,
            (_, Split::Given(split)) => {
                split.iter().rposition(|s| s[0] != 0.0).map_or(0, |i| i + 1)
            }
            (_, Split::Found { .. }) => particles,
        };
        let params = RawWeightParams {
            bin_origin: input.origin.to_array(),
            bin_size: input.binned.bin_size,
            bins: input.binned.bins,
            reach: GATHER_REACH,
            constant: kernel_constant(input.kernel, input.h),
            kernel: kernel_code(input.kernel),
            particles: particles as u32,
            count: n as u32,
            half_spacing: input.half_spacing,
            tau: input.tau,
            lone_r2: (LONE_RADIUS * 2.0 * input.half_spacing).powi(2),
            max_weight: MAX_WEIGHT,
            buried: BURIED,
            band: BAND,
            leading: leading as u32,
            sheet_radius: match self.search {
                BinSearch::Whole => -1.0,
                BinSearch::Trimmed => input.sheet[leading..]
                    .iter()
                    .map(|p| p.at[3])
                    .fold(0.0f32, f32::max),
            },
        };
        queue.write_buffer(&self.uniform, 0, bytemuck::bytes_of(&params));
        let (split_made, classes_made) = match input.split {
            Split::Given(split) => (
                self.split.write(device, queue, bytemuck::cast_slice(split)),
                self.classes.reserve(device, 16),
            ),
            Split::Found { classes } => (
                self.split.reserve(device, n as u64 * 8),
                self.classes
                    .write(device, queue, bytemuck::cast_slice(classes)),
            ),
        };
        let made = [
            self.sheet
                .write(device, queue, bytemuck::cast_slice(input.sheet)),
            split_made,
            classes_made,
            self.share.reserve(device, particles as u64 * 4),
            self.target_buf.reserve(device, n as u64 * TARGET_BYTES),
            // the targets pass sets the first step's weights to 1
            self.w[0].reserve(device, n as u64 * 4),
            self.w[1].reserve(device, n as u64 * 4),
            // the compaction: a prefix entry a point and one more, a block of 256 of them
            self.sheet_prefix.reserve(device, (n as u64 + 1) * 4),
            self.sheet_blocks.reserve(device, (n as u64 / 256 + 1) * 4),
            self.sheet_binned
                .reserve(device, (n as u64).max(1) * POINT_BYTES),
            self.sheet_w[0].reserve(device, n as u64 * 4),
            self.sheet_w[1].reserve(device, n as u64 * 4),
        ];
        self.created = made.iter().filter(|&&m| m).count();
        let key = [input.binned.points.clone(), input.binned.starts.clone()];
        if self.created > 0 || self.binds.as_ref().is_none_or(|(k, _)| *k != key) {
            self.binds = Some((key, self.bind_groups(device, input.binned)));
            self.created += Binds::COUNT;
        }
        self.encode(encoder, (n, particles), mark);
        Ok(self.w[self.solved()].buffer().clone())
    }

    /// Records the passes over the bind groups made for this frame: the factors' (with
    /// `particles` leading points), the targets', the compaction and the steps, the
    /// application; `mark` after each.
    fn encode(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        (n, particles): (usize, usize),
        mark: &mut dyn FnMut(&mut wgpu::CommandEncoder, &'static str),
    ) {
        let binds = &self.binds.as_ref().expect("made by record").1;
        let groups = |count: usize| {
            let g = (count as u32).div_ceil(64).max(1);
            (g.min(65_535), g.div_ceil(65_535))
        };
        let (gx, gy) = groups(n);
        fn begin<'e>(
            encoder: &'e mut wgpu::CommandEncoder,
            label: &'static str,
        ) -> wgpu::ComputePass<'e> {
            encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some(label),
                timestamp_writes: None,
            })
        }
        if particles > 0 {
            let (px, py) = groups(particles);
            let mut pass = begin(encoder, "boundary factors");
            pass.set_pipeline(&self.thin);
            pass.set_bind_group(0, &binds.thin, &[]);
            pass.dispatch_workgroups(px, py, 1);
            pass.set_pipeline(&self.factors);
            pass.set_bind_group(0, &binds.factors, &[]);
            pass.dispatch_workgroups(gx, gy, 1);
            drop(pass);
            mark(encoder, "calibration: factors");
        }
        let mut pass = begin(encoder, "boundary targets");
        pass.set_pipeline(&self.targets);
        pass.set_bind_group(0, &binds.targets, &[]);
        pass.dispatch_workgroups(gx, gy, 1);
        drop(pass);
        mark(encoder, "calibration: targets");
        let steps = match self.search {
            BinSearch::Trimmed => {
                // the points with a sheet weight compacted, in blocks of 256 over n + 1 entries
                let blocks = n as u32 / 256 + 1;
                let (bx, by) = (blocks.min(65_535), blocks.div_ceil(65_535));
                let mut pass = begin(encoder, "boundary sheet compaction");
                pass.set_bind_group(0, &binds.sheet_count, &[]);
                pass.set_pipeline(&self.sheet_count);
                pass.dispatch_workgroups(bx, by, 1);
                pass.set_bind_group(0, &binds.sheet_scan, &[]);
                pass.set_pipeline(&self.sheet_scan);
                pass.dispatch_workgroups(1, 1, 1);
                pass.set_bind_group(0, &binds.sheet_scatter, &[]);
                pass.set_pipeline(&self.sheet_scatter);
                pass.dispatch_workgroups(bx, by, 1);
                drop(pass);
                mark(encoder, "calibration: compaction");
                (&self.step, &binds.steps)
            }
            BinSearch::Whole => (&self.step_whole, &binds.steps_whole),
        };
        let mut from = 0;
        let mut pass = begin(encoder, "boundary steps");
        pass.set_pipeline(steps.0);
        for _ in 0..WEIGHT_STEPS {
            pass.set_bind_group(0, &steps.1[from], &[]);
            pass.dispatch_workgroups(gx, gy, 1);
            from = 1 - from;
        }
        if self.search == BinSearch::Trimmed {
            // the compacted weights back to their points, into buffer a
            pass.set_pipeline(&self.sheet_back);
            pass.set_bind_group(0, &binds.back, &[]);
            pass.dispatch_workgroups(gx, gy, 1);
        }
        drop(pass);
        mark(encoder, "calibration: steps");
        let mut pass = begin(encoder, "boundary weights apply");
        pass.set_pipeline(&self.apply);
        pass.set_bind_group(0, &binds.apply[self.solved()], &[]);
        pass.dispatch_workgroups(gx, gy, 1);
        drop(pass);
        mark(encoder, "calibration: apply");
    }

    /// Which weights buffer holds the solved weights in the chain's order: a (0) after the
    /// compacted steps' write-back, the last step's output with [`BinSearch::Whole`] (b after an
    /// odd count of steps).
    fn solved(&self) -> usize {
        match self.search {
            BinSearch::Trimmed => 0,
            BinSearch::Whole => WEIGHT_STEPS as usize % 2,
        }
    }

    /// After [`Self::record`] in the same encoder: the weights in the density written into
    /// another copy of the same points (`points`: [`RawPoint`](crate::density::gpu::RawPoint)s
    /// that keep their index, as the splatting's copy sorted by slab does), in place.
    pub fn apply_to(
        &mut self,
        device: &wgpu::Device,
        encoder: &mut wgpu::CommandEncoder,
        points: &wgpu::Buffer,
        count: usize,
    ) {
        self.per_point(device, encoder, PerPoint::Copy, points, count);
    }

    /// After [`Self::record`] in the same encoder: each point's weight in the density (its
    /// interior share plus its sheet weight times its solved weight, what the binned points
    /// get) written into `out` (`f32` a point, at least `count`, the points of that record)
    /// in the points' own order, for a reader that keeps it (the ray caster's spheres,
    /// [`PointWeights`]).
    pub fn write_ordered(
        &mut self,
        device: &wgpu::Device,
        encoder: &mut wgpu::CommandEncoder,
        out: &wgpu::Buffer,
        count: usize,
    ) {
        self.per_point(device, encoder, PerPoint::Ordered, out, count);
    }

    /// The pass of [`Self::apply_to`] or [`Self::write_ordered`] over `count` points into
    /// `target`; its bind group made anew only when `target` or the solved weights' buffer
    /// changes (counted in [`Self::created`]).
    fn per_point(
        &mut self,
        device: &wgpu::Device,
        encoder: &mut wgpu::CommandEncoder,
        kind: PerPoint,
        target: &wgpu::Buffer,
        count: usize,
    ) {
        let solved = self.w[self.solved()].buffer().clone();
        let kept = match kind {
            PerPoint::Copy => &self.copy_bind,
            PerPoint::Ordered => &self.ordered_bind,
        };
        if self.created > 0
            || kept
                .as_ref()
                .is_none_or(|(t, w, _)| t != target || *w != solved)
        {
            let bind = self.target_bind(device, kind, &solved, target);
            let made = Some((target.clone(), solved, bind));
            match kind {
                PerPoint::Copy => self.copy_bind = made,
                PerPoint::Ordered => self.ordered_bind = made,
            }
            self.created += 1;
        }
        let (pipeline, bind, label) = match kind {
            PerPoint::Copy => (
                &self.apply,
                &self.copy_bind,
                "boundary weights apply to a copy",
            ),
            PerPoint::Ordered => (
                &self.ordered,
                &self.ordered_bind,
                "boundary weights in order",
            ),
        };
        let all = (count as u32).div_ceil(64).max(1);
        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some(label),
            timestamp_writes: None,
        });
        pass.set_pipeline(pipeline);
        pass.set_bind_group(0, &bind.as_ref().expect("made above").2, &[]);
        pass.dispatch_workgroups(all.min(65_535), all.div_ceil(65_535), 1);
    }

    /// The bind group of a pass writing the weights in `solved` into `target`: the copy of
    /// the points `apply` writes in place, or the weights in order.
    fn target_bind(
        &self,
        device: &wgpu::Device,
        kind: PerPoint,
        solved: &wgpu::Buffer,
        target: &wgpu::Buffer,
    ) -> wgpu::BindGroup {
        let (pipeline, binding) = match kind {
            PerPoint::Copy => (&self.apply, 7),
            PerPoint::Ordered => (&self.ordered, 6),
        };
        gpu::buffer_bind_group(
            device,
            pipeline,
            &[
                (0, &self.uniform),
                (5, solved),
                (binding, target),
                (8, self.split.buffer()),
            ],
        )
    }

    /// The passes' bind groups over this frame's buffers.
    fn bind_groups(&self, device: &wgpu::Device, binned: &BinnedPoints) -> Binds {
        let uniform = self.uniform.as_entire_binding();
        let (points, starts) = (
            binned.points.as_entire_binding(),
            binned.starts.as_entire_binding(),
        );
        let targets = self.target_buf.buffer().as_entire_binding();
        let split = self.split.buffer().as_entire_binding();
        let w = [self.w[0].buffer(), self.w[1].buffer()];
        let (prefix, blocks, sheet_binned) = (
            self.sheet_prefix.buffer().as_entire_binding(),
            self.sheet_blocks.buffer().as_entire_binding(),
            self.sheet_binned.buffer().as_entire_binding(),
        );
        let factors = |pipeline: &wgpu::ComputePipeline, with_split: bool| {
            let mut entries = vec![
                (0, uniform.clone()),
                (1, points.clone()),
                (2, starts.clone()),
                (9, self.sheet.buffer().as_entire_binding()),
                (11, self.classes.buffer().as_entire_binding()),
                (12, self.share.buffer().as_entire_binding()),
            ];
            if with_split {
                entries.push((10, split.clone()));
            }
            gpu::bind_group(device, pipeline, &entries)
        };
        let sheet_w = [self.sheet_w[0].buffer(), self.sheet_w[1].buffer()];
        let step = |from: usize| {
            gpu::bind_group(
                device,
                &self.step,
                &[
                    (0, uniform.clone()),
                    (2, starts.clone()),
                    (4, targets.clone()),
                    (5, sheet_w[from].as_entire_binding()),
                    (6, sheet_w[1 - from].as_entire_binding()),
                    (16, sheet_binned.clone()),
                    (17, prefix.clone()),
                ],
            )
        };
        let step_whole = |from: usize| {
            gpu::bind_group(
                device,
                &self.step_whole,
                &[
                    (0, uniform.clone()),
                    (1, points.clone()),
                    (2, starts.clone()),
                    (4, targets.clone()),
                    (5, w[from].as_entire_binding()),
                    (6, w[1 - from].as_entire_binding()),
                    (8, split.clone()),
                ],
            )
        };
        Binds {
            thin: factors(&self.thin, false),
            factors: factors(&self.factors, true),
            targets: gpu::bind_group(
                device,
                &self.targets,
                &[
                    (0, uniform.clone()),
                    (1, points.clone()),
                    (2, starts.clone()),
                    (3, self.sheet.buffer().as_entire_binding()),
                    (4, targets.clone()),
                    // unread here (`sums` unweighted), bound apart from the buffer it fills
                    (5, w[1].as_entire_binding()),
                    (6, w[0].as_entire_binding()),
                    (8, split.clone()),
                ],
            ),
            sheet_count: gpu::bind_group(
                device,
                &self.sheet_count,
                &[
                    (0, uniform.clone()),
                    (1, points.clone()),
                    (8, split.clone()),
                    (14, blocks.clone()),
                ],
            ),
            sheet_scan: gpu::bind_group(
                device,
                &self.sheet_scan,
                &[(0, uniform.clone()), (14, blocks.clone())],
            ),
            sheet_scatter: gpu::bind_group(
                device,
                &self.sheet_scatter,
                &[
                    (0, uniform.clone()),
                    (1, points.clone()),
                    (8, split.clone()),
                    (6, sheet_w[0].as_entire_binding()),
                    (13, prefix.clone()),
                    (14, blocks),
                    (15, sheet_binned.clone()),
                ],
            ),
            back: gpu::bind_group(
                device,
                &self.sheet_back,
                &[
                    (0, uniform.clone()),
                    (5, sheet_w[WEIGHT_STEPS as usize % 2].as_entire_binding()),
                    (6, w[0].as_entire_binding()),
                    (16, sheet_binned.clone()),
                    (17, prefix.clone()),
                ],
            ),
            steps: [step(0), step(1)],
            steps_whole: [step_whole(0), step_whole(1)],
            apply: w.map(|solved| self.target_bind(device, PerPoint::Copy, solved, &binned.points)),
        }
    }
}

/// Which of the passes writing the solved weights per point ([`WeightPasses::per_point`]).
#[derive(Clone, Copy)]
enum PerPoint {
    /// Into another copy of the binned points, in place (`apply`).
    Copy,
    /// Into a buffer in the points' own order (`ordered`).
    Ordered,
}

/// The boundary calibration's weights of points given with their split
/// ([`super::BoundaryInput`]: the interior's own weights, the sheet's factors), solved on the
/// GPU in the caller's encoder and left there in the points' own order: the ray caster's
/// spheres in [`crate::pipeline::GpuPipeline`], whose points are the CPU's, so that only the
/// Jacobi steps (30 of the 35 ms of the CPU's calibration on the column scene) move to the
/// GPU. The points are sorted into bins on the GPU ([`GpuBinSort`]) over their box padded by
/// the largest radius, as [`boundary_weights_gpu`] bins them; every buffer is kept from frame
/// to frame and grows when a frame needs more.
pub struct PointWeights {
    sort: GpuBinSort,
    passes: WeightPasses,
    out: gpu::Grow,
    created: usize,
    count: usize,
}

impl PointWeights {
    /// Compiles the passes.
    #[must_use]
    pub fn new(device: &wgpu::Device) -> Self {
        Self {
            sort: GpuBinSort::new(device),
            passes: WeightPasses::new(device),
            out: gpu::Grow::new(
                "boundary weights in order",
                wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
            ),
            created: 0,
            count: 0,
        }
    }

    /// The buffer [`Self::record`] writes the weights into (kept from frame to frame until a
    /// frame needs more).
    #[must_use]
    pub fn buffer(&self) -> &wgpu::Buffer {
        self.out.buffer()
    }

    /// How many points the last [`Self::record`] weighed.
    #[must_use]
    pub fn count(&self) -> usize {
        self.count
    }

    /// How the next [`Self::record`]s search the bins ([`WeightPasses::set_search`]).
    pub fn set_search(&mut self, search: BinSearch) {
        self.passes.set_search(search);
    }

    /// Buffers and bind groups the last [`Self::record`] made (0 once they are large enough).
    #[must_use]
    pub fn created(&self) -> usize {
        self.created
    }

    /// Records the sort, the solve and the weights' write in order into `encoder`: once it
    /// has run, the returned buffer holds each point's weight in the density (`f32` a point,
    /// the first `input.positions.len()`), the CPU's ([`super::BoundaryInput::solve`]) to
    /// rounding. `h` is the support radius, `tau` the iso-value. No point: nothing recorded.
    pub fn record(
        &mut self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        input: &super::BoundaryInput,
        (h, kernel, tau): (f32, Kernel, f32),
    ) -> Result<wgpu::Buffer, crate::Error> {
        let points =
            Points::with_radii(&input.positions, &input.radii, h).with_weights(&input.base);
        points.check()?;
        let n = points.len();
        if input.normals.len() != n - input.interior.min(n) || input.interior > n {
            return Err(GpuError::Validation(format!(
                "{n} points, {} interior, {} normals: one normal per sheet point",
                input.interior,
                input.normals.len()
            ))
            .into());
        }
        let split: Vec<[f32; 2]> = (0..n)
            .map(|j| {
                let b = points.weight(j);
                if j < input.interior {
                    [b, 0.0]
                } else {
                    [0.0, b]
                }
            })
            .collect();
        self.record_split(
            ctx,
            encoder,
            &points,
            (input.interior, &input.normals, Split::Given(&split)),
            (input.spacing, kernel, tau),
        )
    }

    /// [`Self::record`] of every particle and every sheet point ([`super::BoundaryLayout`]),
    /// the calibration's factors found on the GPU too ([`Split::Found`]): once it has run, the
    /// returned buffer holds each point's weight in the density (`f32` a point, in the
    /// layout's order), the CPU's ([`super::chain_input_at_boundary`] then
    /// [`super::BoundaryInput::solve`], whose points are these without those the factors
    /// leave out, a particle in the interior and in a thin sheet summed) to rounding, and
    /// [`DROPPED`] for a point the factors leave out (its split zero): no reader draws it.
    pub fn record_layout(
        &mut self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        layout: &super::BoundaryLayout,
        (h, kernel, tau): (f32, Kernel, f32),
    ) -> Result<wgpu::Buffer, crate::Error> {
        let points = Points::with_radii(&layout.positions, &layout.radii, h);
        points.check()?;
        let n = points.len();
        let sheet = n - layout.particles.min(n);
        if layout.classes.len() != layout.particles || layout.normals.len() != sheet {
            return Err(GpuError::Validation(format!(
                "{n} points, {} particles with {} classes, {} normals: one class per particle, \
                 one normal per sheet point",
                layout.particles,
                layout.classes.len(),
                layout.normals.len()
            ))
            .into());
        }
        self.record_split(
            ctx,
            encoder,
            &points,
            (
                layout.particles,
                &layout.normals,
                Split::Found {
                    classes: &layout.classes,
                },
            ),
            (layout.spacing, kernel, tau),
        )
    }

    /// The sort of `points` into bins on the GPU, the solve with sheet normals from point
    /// `first` on and the split `split`, and the weights' write in order.
    fn record_split(
        &mut self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        points: &Points<'_>,
        (first, normals, split): (usize, &[Vec3], Split<'_>),
        (spacing, kernel, tau): (f32, Kernel, f32),
    ) -> Result<wgpu::Buffer, crate::Error> {
        let (device, queue) = (&ctx.device, &ctx.queue);
        let n = points.len();
        let made = self.out.reserve(device, n.max(1) as u64 * 4);
        self.count = n;
        if n == 0 {
            self.created = usize::from(made);
            return Ok(self.out.buffer().clone());
        }
        let reach = points.max_radius();
        let spec = GridSpec::around(points.positions, reach, Resolution::CellSize(reach))?;
        let layout = BinLayout::of(points, &spec);
        self.sort
            .record(ctx, encoder, &raw_points(points), &layout)?;
        let binned = BinnedPoints::sorted_by(&self.sort, &layout, points);
        let sheet = sheet_points(points, first, normals);
        self.passes.record(
            (device, queue),
            encoder,
            &WeightInput {
                binned: &binned,
                origin: spec.origin,
                sheet: &sheet,
                split,
                half_spacing: 0.5 * spacing,
                tau,
                kernel,
                h: points.h,
            },
        )?;
        let created = self.sort.created() + self.passes.created() + usize::from(made);
        self.passes
            .write_ordered(device, encoder, self.out.buffer(), n);
        self.created = created + self.passes.created();
        Ok(self.out.buffer().clone())
    }
}

/// The bind groups of [`WeightPasses`]' passes over one frame's buffers: the two factor passes,
/// the targets pass, the sheet points' compaction, the steps over the compacted points (from
/// their weights buffer a and from b) and their weights' write-back, the steps over every point
/// (from weights buffer a and from b), the application of the solved weights in a or in b.
struct Binds {
    thin: wgpu::BindGroup,
    factors: wgpu::BindGroup,
    targets: wgpu::BindGroup,
    sheet_count: wgpu::BindGroup,
    sheet_scan: wgpu::BindGroup,
    sheet_scatter: wgpu::BindGroup,
    steps: [wgpu::BindGroup; 2],
    /// The compacted points' weights back to their points.
    back: wgpu::BindGroup,
    steps_whole: [wgpu::BindGroup; 2],
    /// The application of the weights in buffer a, in buffer b.
    apply: [wgpu::BindGroup; 2],
}

impl Binds {
    /// How many bind groups one set holds.
    const COUNT: usize = 13;
}

/// The sheet points as the passes read them: every point's position and kernel radius, and
/// `normals[j]` for the points from `first` on (zero before; a non-finite normal is none).
#[must_use]
pub fn sheet_points(points: &Points<'_>, first: usize, normals: &[Vec3]) -> Vec<RawSheetPoint> {
    (0..points.len())
        .map(|j| {
            let nj = j.checked_sub(first).map_or(Vec3::ZERO, |k| normals[k]);
            let nj = if nj.is_finite() { nj } else { Vec3::ZERO };
            RawSheetPoint {
                at: points.positions[j].extend(points.radius(j)).to_array(),
                normal: nj.extend(0.0).to_array(),
            }
        })
        .collect()
}

/// The passes of [`boundary_weights_gpu`] and [`boundary_factors_gpu`] recorded once and
/// submitted: `points` binned over their box padded by the largest radius (the targets, half
/// a spacing out, lie inside it), each a sheet point with `normals` from point `first` on,
/// with `split`; the passes (their buffers hold the split and the sheet) and the solved
/// weights' buffer.
fn solve_once(
    ctx: &GpuContext,
    points: &Points<'_>,
    (first, normals): (usize, &[Vec3]),
    split: Split<'_>,
    (spacing, kernel, tau): (f32, Kernel, f32),
    search: BinSearch,
) -> Result<(WeightPasses, wgpu::Buffer), crate::Error> {
    let reach = points.max_radius();
    let spec = GridSpec::around(points.positions, reach, Resolution::CellSize(reach))?;
    let binned = BinnedPoints::new(&ctx.device, points, &spec)?;
    let sheet = sheet_points(points, first, normals);
    let mut passes = WeightPasses::new(&ctx.device);
    passes.set_search(search);
    let mut encoder = ctx.device.create_command_encoder(&Default::default());
    let solved = passes.record(
        (&ctx.device, &ctx.queue),
        &mut encoder,
        &WeightInput {
            binned: &binned,
            origin: spec.origin,
            sheet: &sheet,
            split,
            half_spacing: 0.5 * spacing,
            tau,
            kernel,
            h: points.h,
        },
    )?;
    ctx.queue.submit([encoder.finish()]);
    Ok((passes, solved))
}

/// [`super::boundary_weights`] on the GPU of `ctx`, read back: the weights of every point (the
/// interior's their own, the sheet's their own times the solved ones), the CPU's to rounding.
pub fn boundary_weights_gpu(
    ctx: &GpuContext,
    points: Points<'_>,
    interior: usize,
    normals: &[Vec3],
    spacing: f32,
    kernel: Kernel,
    tau: f32,
) -> Result<Vec<f32>, crate::Error> {
    boundary_weights_gpu_searching(
        ctx,
        points,
        (interior, normals),
        (spacing, kernel, tau),
        BinSearch::Trimmed,
    )
}

/// [`boundary_weights_gpu`] with the bins searched as `search` says.
pub fn boundary_weights_gpu_searching(
    ctx: &GpuContext,
    points: Points<'_>,
    (interior, normals): (usize, &[Vec3]),
    (spacing, kernel, tau): (f32, Kernel, f32),
    search: BinSearch,
) -> Result<Vec<f32>, crate::Error> {
    points.check()?;
    let n = points.len();
    if n == interior {
        return Ok((0..n).map(|j| points.weight(j)).collect());
    }
    let input = super::BoundaryInput {
        positions: points.positions.to_vec(),
        radii: (0..n).map(|j| points.radius(j)).collect(),
        base: (0..n).map(|j| points.weight(j)).collect(),
        interior,
        normals: normals.to_vec(),
        spacing,
    };
    let mut weights = PointWeights::new(&ctx.device);
    weights.set_search(search);
    let mut encoder = ctx.device.create_command_encoder(&Default::default());
    let out = weights.record(ctx, &mut encoder, &input, (points.h, kernel, tau))?;
    ctx.queue.submit([encoder.finish()]);
    let mut w: Vec<f32> = gpu::read_buffer(ctx, &out)?;
    w.truncate(n);
    Ok(w)
}

/// The factors of [`super::chain_input_at_boundary`] found on the GPU of `ctx`, with the
/// weights solved after them, read back: per particle (`particles`, classed by `surface`) and
/// per sheet point (`sheet`, support radius `h`) the split `[interior share, sheet weight]`
/// and the weight in the density (the interior share plus the sheet weight times the solved
/// one), in the order particles then sheet; and each particle's thin-sheet normal (zero where
/// it is in no sheet one particle thick).
pub fn boundary_factors_gpu(
    ctx: &GpuContext,
    particles: &[Vec3],
    surface: &Surface,
    sheet: super::Sheet<'_>,
    h: f32,
    kernel: Kernel,
    tau: f32,
) -> Result<GpuFactors, crate::Error> {
    boundary_factors_gpu_searching(
        ctx,
        (particles, surface, sheet),
        (h, kernel, tau),
        BinSearch::Trimmed,
    )
}

/// [`boundary_factors_gpu`] with the bins searched as `search` says.
pub fn boundary_factors_gpu_searching(
    ctx: &GpuContext,
    (particles, surface, sheet): (&[Vec3], &Surface, super::Sheet<'_>),
    (h, kernel, tau): (f32, Kernel, f32),
    search: BinSearch,
) -> Result<GpuFactors, crate::Error> {
    let layout = super::boundary_layout(particles, surface, sheet, h);
    let points = Points::with_radii(&layout.positions, &layout.radii, h);
    points.check()?;
    let (passes, solved) = solve_once(
        ctx,
        &points,
        (layout.particles, &layout.normals),
        Split::Found {
            classes: &layout.classes,
        },
        (layout.spacing, kernel, tau),
        search,
    )?;
    let n = points.len();
    let split: Vec<[f32; 2]> = gpu::read_buffer(ctx, passes.split())?;
    let w: Vec<f32> = gpu::read_buffer(ctx, &solved)?;
    let sheet_read: Vec<RawSheetPoint> = gpu::read_buffer(ctx, passes.sheet.buffer())?;
    let split = split[..n].to_vec();
    let weights = (0..n).map(|j| split[j][0] + split[j][1] * w[j]).collect();
    let thin_normals = sheet_read[..layout.particles]
        .iter()
        .map(|p| Vec3::new(p.normal[0], p.normal[1], p.normal[2]))
        .collect();
    Ok(GpuFactors {
        split,
        weights,
        thin_normals,
    })
}

/// What [`boundary_factors_gpu`] reads back.
#[derive(Clone, Debug, Default)]
pub struct GpuFactors {
    /// `[interior share, sheet weight]` a point: the particles, then the sheet.
    pub split: Vec<[f32; 2]>,
    /// Each point's weight in the density.
    pub weights: Vec<f32>,
    /// Each particle's thin-sheet normal (zero: in no sheet one particle thick).
    pub thin_normals: Vec<Vec3>,
}
