//! The boundary calibration's weights on the GPU (issue 37): the twin of
//! [`super::boundary_weights`], the largest CPU stage left in [`crate::pipeline::GpuPipeline`]'s
//! `prepare` (54 of the game loop's 96 ms a frame on lavapipe's machine). The points are binned
//! as the gather pass bins them ([`BinnedPoints`], each keeping its index), one pass finds each
//! sheet point's target, how alone it is, its lone ball's weight and the interior's density at
//! the target, and [`WEIGHT_STEPS`] Jacobi passes solve the weights, ping-ponging between two
//! buffers. The sums run over the bins, not the CPU's cell grids, so the weights agree with the
//! CPU's to rounding (`tests/gpu.rs` measures how closely), not bit for bit.
//!
//! [`WeightPasses::record`] records the passes into the caller's encoder, applies the weights
//! to the binned points in place (the gather pass then fills the grid from them) and leaves
//! the solved weights in a buffer (no read-back); [`boundary_weights_gpu`] reads them back, for
//! tests and one-off use. `GpuPipeline` solves them so whenever its grid is gathered from the
//! binned points (the sparse grid, or `gpu_method = "gather"`).

use bytemuck::{Pod, Zeroable};
use glam::Vec3;

use super::{LONE_RADIUS, MAX_WEIGHT, WEIGHT_STEPS};
use crate::density::gpu::{BinnedPoints, GATHER_REACH, kernel_code, kernel_constant};
use crate::density::{GridSpec, Kernel, Points, Resolution};
use crate::gpu::{self, GpuContext, GpuError};

/// The WGSL of the passes.
pub const SHADER: &str = concat!(
    include_str!("../../../shaders/common.wgsl"),
    include_str!("../../../shaders/boundary_weights.wgsl")
);

/// The passes' `WeightParams` uniform (64 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
pub struct RawWeightParams {
    pub bin_origin: [f32; 3],
    pub bin_size: f32,
    pub bins: [u32; 3],
    pub reach: u32,
    pub constant: f32,
    pub kernel: u32,
    pub interior: u32,
    pub sheet: u32,
    pub half_spacing: f32,
    pub tau: f32,
    pub lone_r2: f32,
    pub max_weight: f32,
}

const _: () = assert!(std::mem::size_of::<RawWeightParams>() == 64);

/// A sheet point as the passes read it (`SheetPoint`): position and kernel radius, outward
/// normal (zero: none) and its own weight.
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
pub struct RawSheetPoint {
    pub at: [f32; 4],
    pub normal: [f32; 4],
}

/// Bytes of a `Target` (target and how alone, lone weight, interior density, padding).
const TARGET_BYTES: u64 = 32;

/// The compute pipelines, built once per device, and their buffers, kept from frame to frame
/// (grown when a frame needs more) with their bind groups (made anew only when a buffer they
/// hold changes).
pub struct WeightPasses {
    targets: wgpu::ComputePipeline,
    step: wgpu::ComputePipeline,
    apply: wgpu::ComputePipeline,
    uniform: wgpu::Buffer,
    sheet: gpu::Grow,
    target_buf: gpu::Grow,
    w: [gpu::Grow; 2],
    /// The bind groups (targets, the steps from buffer a and from b, the application of the
    /// result) and the binned buffers they hold.
    binds: Option<([wgpu::Buffer; 2], [wgpu::BindGroup; 4])>,
    /// The application to another copy of the points ([`Self::apply_to`]) and that copy.
    copy_bind: Option<(wgpu::Buffer, wgpu::BindGroup)>,
    created: usize,
}

/// What [`WeightPasses::record`] solves for: the binned points (interior first in the chain's
/// order, then the sheet, each keeping its index) over the box from `origin`, and the sheet.
pub struct WeightInput<'a> {
    pub binned: &'a BinnedPoints,
    pub origin: Vec3,
    pub interior: usize,
    pub sheet: &'a [RawSheetPoint],
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
        let [targets, step, apply] = gpu::compute_pipelines(
            device,
            "boundary weights",
            SHADER,
            ["targets_pass", "step", "apply"],
        );
        let storage = wgpu::BufferUsages::STORAGE;
        Self {
            targets,
            step,
            apply,
            uniform: device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("boundary weights params"),
                size: std::mem::size_of::<RawWeightParams>() as u64,
                usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            }),
            sheet: gpu::Grow::new("sheet points", storage),
            target_buf: gpu::Grow::new("sheet targets", storage),
            w: [
                gpu::Grow::new("sheet weights a", storage | wgpu::BufferUsages::COPY_SRC),
                gpu::Grow::new("sheet weights b", storage | wgpu::BufferUsages::COPY_SRC),
            ],
            binds: None,
            copy_bind: None,
            created: 0,
        }
    }

    /// Buffers and bind groups the last [`Self::record`] made (0 once they are large enough).
    #[must_use]
    pub fn created(&self) -> usize {
        self.created
    }

    /// Records the passes into `encoder`, then the weights' application: each sheet point's
    /// weight in `input.binned`'s points becomes its own times its solved one, in place (the
    /// binned points must be those the grid is then filled from). The solved weights
    /// themselves (`f32` per sheet point, in the sheet's order, their own weights not applied)
    /// are left in the returned buffer.
    pub fn record(
        &mut self,
        (device, queue): (&wgpu::Device, &wgpu::Queue),
        encoder: &mut wgpu::CommandEncoder,
        input: &WeightInput<'_>,
    ) -> Result<wgpu::Buffer, GpuError> {
        let n = input.sheet.len();
        let limit = gpu::max_binding(device);
        if (n as u64).max(1) * TARGET_BYTES > limit {
            return Err(GpuError::Validation(format!(
                "{n} sheet points exceed the GPU's storage binding limit of {limit} bytes; use the CPU calibration"
            )));
        }
        let params = RawWeightParams {
            bin_origin: input.origin.to_array(),
            bin_size: input.binned.bin_size,
            bins: input.binned.bins,
            reach: GATHER_REACH,
            constant: kernel_constant(input.kernel, input.h),
            kernel: kernel_code(input.kernel),
            interior: input.interior as u32,
            sheet: n as u32,
            half_spacing: input.half_spacing,
            tau: input.tau,
            lone_r2: (LONE_RADIUS * 2.0 * input.half_spacing).powi(2),
            max_weight: MAX_WEIGHT,
        };
        queue.write_buffer(&self.uniform, 0, bytemuck::bytes_of(&params));
        let made = [
            self.sheet
                .write(device, queue, bytemuck::cast_slice(input.sheet)),
            self.target_buf.reserve(device, n as u64 * TARGET_BYTES),
            // the targets pass sets the first step's weights to 1
            self.w[0].reserve(device, n as u64 * 4),
            self.w[1].reserve(device, n as u64 * 4),
        ];
        self.created = made.iter().filter(|&&m| m).count();
        let key = [input.binned.points.clone(), input.binned.starts.clone()];
        if self.created > 0 || self.binds.as_ref().is_none_or(|(k, _)| *k != key) {
            self.binds = Some((key, self.bind_groups(device, input.binned)));
            self.created += 4;
        }
        let binds = &self.binds.as_ref().expect("made above").1;
        let groups = (n as u32).div_ceil(64).max(1);
        let (gx, gy) = (groups.min(65_535), groups.div_ceil(65_535));
        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("boundary weights"),
            timestamp_writes: None,
        });
        pass.set_pipeline(&self.targets);
        pass.set_bind_group(0, &binds[0], &[]);
        pass.dispatch_workgroups(gx, gy, 1);
        pass.set_pipeline(&self.step);
        let mut from = 0;
        for _ in 0..WEIGHT_STEPS {
            pass.set_bind_group(0, &binds[1 + from], &[]);
            pass.dispatch_workgroups(gx, gy, 1);
            from = 1 - from;
        }
        // the application reads the last step's output: buffer `from` (b after an odd count)
        debug_assert_eq!(from, WEIGHT_STEPS as usize % 2);
        let all = ((input.interior + n) as u32).div_ceil(64).max(1);
        pass.set_pipeline(&self.apply);
        pass.set_bind_group(0, &binds[3], &[]);
        pass.dispatch_workgroups(all.min(65_535), all.div_ceil(65_535), 1);
        drop(pass);
        Ok(self.w[from].buffer().clone())
    }

    /// After [`Self::record`] in the same encoder: the solved weights applied to another copy of
    /// the same points (`points`: [`RawPoint`](crate::density::gpu::RawPoint)s that keep their
    /// index, as the splatting's copy sorted by z does), in place.
    pub fn apply_to(
        &mut self,
        device: &wgpu::Device,
        encoder: &mut wgpu::CommandEncoder,
        points: &wgpu::Buffer,
        count: usize,
    ) {
        if self.created > 0 || self.copy_bind.as_ref().is_none_or(|(b, _)| b != points) {
            let bind = gpu::bind_group(
                device,
                &self.apply,
                &[
                    (0, self.uniform.as_entire_binding()),
                    (
                        5,
                        self.w[WEIGHT_STEPS as usize % 2]
                            .buffer()
                            .as_entire_binding(),
                    ),
                    (7, points.as_entire_binding()),
                ],
            );
            self.copy_bind = Some((points.clone(), bind));
            self.created += 1;
        }
        let all = (count as u32).div_ceil(64).max(1);
        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("boundary weights apply to a copy"),
            timestamp_writes: None,
        });
        pass.set_pipeline(&self.apply);
        pass.set_bind_group(0, &self.copy_bind.as_ref().expect("made above").1, &[]);
        pass.dispatch_workgroups(all.min(65_535), all.div_ceil(65_535), 1);
    }

    /// The passes' bind groups over this frame's buffers: the targets pass, a step from each
    /// weights buffer into the other, the application of the last step's output.
    fn bind_groups(&self, device: &wgpu::Device, binned: &BinnedPoints) -> [wgpu::BindGroup; 4] {
        let uniform = self.uniform.as_entire_binding();
        let (points, starts) = (
            binned.points.as_entire_binding(),
            binned.starts.as_entire_binding(),
        );
        let targets = self.target_buf.buffer().as_entire_binding();
        let w = [self.w[0].buffer(), self.w[1].buffer()];
        let step = |from: usize| {
            gpu::bind_group(
                device,
                &self.step,
                &[
                    (0, uniform.clone()),
                    (1, points.clone()),
                    (2, starts.clone()),
                    (4, targets.clone()),
                    (5, w[from].as_entire_binding()),
                    (6, w[1 - from].as_entire_binding()),
                ],
            )
        };
        [
            gpu::bind_group(
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
                ],
            ),
            step(0),
            step(1),
            gpu::bind_group(
                device,
                &self.apply,
                &[
                    (0, uniform),
                    (5, w[WEIGHT_STEPS as usize % 2].as_entire_binding()),
                    (7, points),
                ],
            ),
        ]
    }
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
    points.check()?;
    let n = points.len();
    if normals.len() != n - interior.min(n) || interior > n {
        return Err(GpuError::Validation(format!(
            "{n} points, {interior} interior, {} normals: one normal per sheet point",
            normals.len()
        ))
        .into());
    }
    let base: Vec<f32> = (0..n).map(|i| points.weight(i)).collect();
    if n == interior {
        return Ok(base);
    }
    // the bins over the points' box padded by the largest radius (the targets, half a spacing
    // out, lie inside it)
    let reach = points.max_radius();
    let spec = GridSpec::around(points.positions, reach, Resolution::CellSize(reach))?;
    let binned = BinnedPoints::new(&ctx.device, &points, &spec)?;
    let sheet: Vec<RawSheetPoint> = (interior..n)
        .map(|j| {
            let x = points.positions[j];
            let nj = normals[j - interior];
            let nj = if nj.is_finite() { nj } else { Vec3::ZERO };
            RawSheetPoint {
                at: x.extend(points.radius(j)).to_array(),
                normal: nj.extend(base[j]).to_array(),
            }
        })
        .collect();
    let mut passes = WeightPasses::new(&ctx.device);
    let mut encoder = ctx.device.create_command_encoder(&Default::default());
    let solved = passes.record(
        (&ctx.device, &ctx.queue),
        &mut encoder,
        &WeightInput {
            binned: &binned,
            origin: spec.origin,
            interior,
            sheet: &sheet,
            half_spacing: 0.5 * spacing,
            tau,
            kernel,
            h: points.h,
        },
    )?;
    ctx.queue.submit([encoder.finish()]);
    let w: Vec<f32> = gpu::read_buffer(ctx, &solved)?;
    let mut out = base;
    for (o, w) in out[interior..].iter_mut().zip(&w) {
        *o *= w;
    }
    Ok(out)
}
