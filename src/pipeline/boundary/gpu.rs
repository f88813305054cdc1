//! The boundary calibration's weights on the GPU (issue 37): the twin of
//! [`super::boundary_weights`], the largest CPU stage left in [`crate::pipeline::GpuPipeline`]'s
//! `prepare` (54 of the game loop's 96 ms a frame on lavapipe's machine). The points are binned
//! as the gather pass bins them ([`BinnedPoints`], each keeping its index), one pass finds each
//! sheet point's target, how alone it is, its lone ball's weight and the interior's density at
//! the target, and [`WEIGHT_STEPS`] Jacobi passes solve the weights, ping-ponging between two
//! buffers. The sums run over the bins, not the CPU's cell grids, so the weights agree with the
//! CPU's to rounding (`tests/gpu.rs` measures how closely), not bit for bit.
//!
//! [`WeightPasses::record`] records the passes into the caller's encoder and leaves the weights
//! in a buffer (no read-back); [`boundary_weights_gpu`] reads them back, for tests and one-off
//! use.

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

/// The compute pipelines, built once per device.
pub struct WeightPasses {
    targets: wgpu::ComputePipeline,
    step: wgpu::ComputePipeline,
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
        let [targets, step] =
            gpu::compute_pipelines(device, "boundary weights", SHADER, ["targets_pass", "step"]);
        Self { targets, step }
    }

    /// Records the passes into `encoder`; returns the buffer of the sheet's solved weights
    /// (`f32` per sheet point, in the sheet's order, their own weights not applied: the
    /// density's weight of sheet point `j` is its own times this).
    pub fn record(
        &self,
        device: &wgpu::Device,
        encoder: &mut wgpu::CommandEncoder,
        input: &WeightInput<'_>,
    ) -> Result<wgpu::Buffer, GpuError> {
        use wgpu::util::DeviceExt;
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
        let init = |label, contents: &[u8], usage| {
            device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents,
                usage,
            })
        };
        let storage = wgpu::BufferUsages::STORAGE;
        let uniform = init(
            "boundary weights params",
            bytemuck::bytes_of(&params),
            wgpu::BufferUsages::UNIFORM,
        );
        // a binding holds at least one element
        let zero = [RawSheetPoint::zeroed()];
        let sheet = init(
            "sheet points",
            bytemuck::cast_slice(if n == 0 { &zero } else { input.sheet }),
            storage,
        );
        let targets = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("sheet targets"),
            size: n.max(1) as u64 * TARGET_BYTES,
            usage: storage,
            mapped_at_creation: false,
        });
        let ones = vec![1.0f32; n.max(1)];
        let usage = storage | wgpu::BufferUsages::COPY_SRC;
        let w = [
            init("sheet weights a", bytemuck::cast_slice(&ones), usage),
            init("sheet weights b", bytemuck::cast_slice(&ones), usage),
        ];
        let groups = (n as u32).div_ceil(64).max(1);
        let dispatch = (groups.min(65_535), groups.div_ceil(65_535));
        let bind = |pipeline: &wgpu::ComputePipeline, from: usize, with_sheet: bool| {
            let mut entries = vec![
                (0, uniform.as_entire_binding()),
                (1, input.binned.points.as_entire_binding()),
                (2, input.binned.starts.as_entire_binding()),
                (4, targets.as_entire_binding()),
                (5, w[from].as_entire_binding()),
            ];
            if with_sheet {
                entries.push((3, sheet.as_entire_binding()));
            } else {
                entries.push((6, w[1 - from].as_entire_binding()));
            }
            gpu::bind_group(device, pipeline, &entries)
        };
        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("boundary weights"),
            timestamp_writes: None,
        });
        pass.set_pipeline(&self.targets);
        pass.set_bind_group(0, &bind(&self.targets, 0, true), &[]);
        pass.dispatch_workgroups(dispatch.0, dispatch.1, 1);
        pass.set_pipeline(&self.step);
        let mut from = 0;
        for _ in 0..WEIGHT_STEPS {
            pass.set_bind_group(0, &bind(&self.step, from, false), &[]);
            pass.dispatch_workgroups(dispatch.0, dispatch.1, 1);
            from = 1 - from;
        }
        drop(pass);
        Ok(w[from].clone())
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
    let passes = WeightPasses::new(&ctx.device);
    let mut encoder = ctx.device.create_command_encoder(&Default::default());
    let solved = passes.record(
        &ctx.device,
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
