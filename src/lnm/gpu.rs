//! The narrow band on the GPU: `shaders/lnm.wgsl` over a dense voxel grid of the domain (the
//! paper's layout; the CPU path's sparse keys have no cheap GPU twin), three compute passes
//! (count, first layer, second layer) and a read-back that keeps the full voxels in the CPU's
//! order. Labels, counts and each particle's voxel equal the CPU's exactly (both find a voxel as
//! `floor((p - lo) * (1 / edge))`, correctly rounded in both); centroids are summed in fixed
//! point (integer atomics, so the order of the sum does not matter), within 2^-16 voxel edges
//! of the CPU's.

use glam::Vec3;
use wgpu::util::DeviceExt;

use super::cpu::domain;
use super::{BandVoxel, LnmError, LnmParams, NarrowBand};
use crate::gpu::{GpuContext, GpuError};

/// The WGSL source of the passes.
pub const SHADER: &str = include_str!("../../shaders/lnm.wgsl");

/// The uniforms (`Params` in the WGSL, 48 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct RawLnmParams {
    /// the domain's minimum corner, 1 / voxel edge
    pub lo: [f32; 4],
    /// voxels along x, y, z; particles
    pub dims: [u32; 4],
    /// n_min, fixed-point scale of the offsets, a point's stride in `vec4`s (1: positions
    /// alone), 1 to count only (no offsets' sums, no voxel per particle)
    pub misc: [u32; 4],
}

const _: () = assert!(std::mem::size_of::<RawLnmParams>() == 48);

/// Most voxels of the dense grid (128 MiB of counts and labels, 384 MiB of sums).
pub const MAX_DENSE_VOXELS: u64 = 1 << 25;

/// Fixed-point scale of a particle's offset in its voxel (`[0, 1)` voxel edges).
pub(crate) const SCALE: u32 = 1 << 16;

/// A voxel with more particles than this could overflow its `i32` sums; its centroid is
/// summed on the host instead.
const MAX_FIXED_COUNT: u32 = (i32::MAX as u32) / SCALE;

/// Workgroups of 64 for `n` invocations: `(x, y)` with `x <= 65535` (the WGSL's index is
/// `x + y * 65535 * 64`; `density::sparse_gpu`'s passes index so too).
pub(crate) fn groups(n: u64) -> (u32, u32) {
    let g = n.div_ceil(64);
    if g <= 65_535 {
        (g as u32, 1)
    } else {
        (65_535, g.div_ceil(65_535) as u32)
    }
}

/// [`super::narrow_band`] on the GPU of `ctx`.
pub fn narrow_band_gpu(
    ctx: &GpuContext,
    positions: &[Vec3],
    support_radius: f32,
    params: &LnmParams,
) -> Result<NarrowBand, crate::Error> {
    let (lo, edge, dims) = ResidentBand::domain(positions, support_radius, params)?;
    let total = dims.iter().map(|&d| u64::from(d)).product::<u64>();
    let n = positions.len();
    let device = &ctx.device;
    let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
    let uniforms = RawLnmParams {
        lo: lo.extend(1.0 / edge).to_array(),
        dims: [dims[0], dims[1], dims[2], n as u32],
        misc: [params.n_min, SCALE, 1, 0],
    };
    let uniform = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
        label: Some("lnm params"),
        contents: bytemuck::bytes_of(&uniforms),
        usage: wgpu::BufferUsages::UNIFORM,
    });
    let padded: Vec<[f32; 4]> = positions.iter().map(|p| p.extend(0.0).to_array()).collect();
    let points = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
        label: Some("lnm positions"),
        contents: if padded.is_empty() {
            &[0u8; 16]
        } else {
            bytemuck::cast_slice(&padded)
        },
        usage: wgpu::BufferUsages::STORAGE,
    });
    let zeroed = |label, bytes: u64| {
        // created zeroed (wgpu clears new buffers)
        device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size: bytes.max(16),
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
            mapped_at_creation: false,
        })
    };
    let counts = zeroed("lnm counts", 4 * total);
    let sums = zeroed("lnm sums", 12 * total);
    let voxel_of = zeroed("lnm voxel of", 4 * n as u64);
    let labels = zeroed("lnm labels", 4 * total);
    let [count, first, second] =
        crate::gpu::compute_pipelines(device, "lnm", SHADER, ["cs_count", "cs_first", "cs_second"]);
    let group = |p: &wgpu::ComputePipeline, entries: &[(u32, &wgpu::Buffer)]| {
        crate::gpu::buffer_bind_group(device, p, entries)
    };
    let count_group = group(
        &count,
        &[
            (0, &uniform),
            (1, &points),
            (2, &counts),
            (3, &sums),
            (4, &voxel_of),
        ],
    );
    let first_group = group(&first, &[(0, &uniform), (2, &counts), (5, &labels)]);
    let second_group = group(&second, &[(0, &uniform), (2, &counts), (5, &labels)]);
    let mut encoder = device.create_command_encoder(&Default::default());
    {
        let mut pass = encoder.begin_compute_pass(&Default::default());
        if n > 0 {
            let (gx, gy) = groups(n as u64);
            pass.set_pipeline(&count);
            pass.set_bind_group(0, &count_group, &[]);
            pass.dispatch_workgroups(gx, gy, 1);
        }
        let (gx, gy) = groups(total);
        pass.set_pipeline(&first);
        pass.set_bind_group(0, &first_group, &[]);
        pass.dispatch_workgroups(gx, gy, 1);
        pass.set_pipeline(&second);
        pass.set_bind_group(0, &second_group, &[]);
        pass.dispatch_workgroups(gx, gy, 1);
    }
    ctx.queue.submit([encoder.finish()]);
    if let Some(e) = pollster::block_on(scope.pop()) {
        return Err(GpuError::Validation(e.to_string()).into());
    }
    let counts: Vec<u32> = crate::gpu::read_buffer(ctx, &counts)?;
    let sums: Vec<i32> = crate::gpu::read_buffer(ctx, &sums)?;
    let labels: Vec<u32> = crate::gpu::read_buffer(ctx, &labels)?;
    let dense_of: Vec<u32> = crate::gpu::read_buffer(ctx, &voxel_of)?;
    // the full voxels in dense order: x fastest, so in the CPU's key order (z, then y, then x)
    let mut compact = vec![u32::MAX; total as usize];
    let mut voxels = Vec::new();
    let plane = u64::from(dims[0]) * u64::from(dims[1]);
    for v in 0..total as usize {
        let c = counts[v];
        if c == 0 {
            continue;
        }
        let coord = [
            (v as u64 % u64::from(dims[0])) as u32,
            ((v as u64 / u64::from(dims[0])) % u64::from(dims[1])) as u32,
            (v as u64 / plane) as u32,
        ];
        let corner = Vec3::from(coord.map(|x| x as f32));
        let offset = Vec3::new(
            sums[3 * v] as f32,
            sums[3 * v + 1] as f32,
            sums[3 * v + 2] as f32,
        ) / (c as f32 * SCALE as f32);
        compact[v] = voxels.len() as u32;
        voxels.push(BandVoxel {
            coord,
            count: c,
            centroid: lo + (corner + offset) * edge,
            label: labels[v] as u8,
        });
    }
    let voxel_of: Vec<u32> = dense_of[..n].iter().map(|&d| compact[d as usize]).collect();
    // a voxel whose fixed-point sums could have overflowed: its centroid from the positions
    if voxels.iter().any(|v| v.count > MAX_FIXED_COUNT) {
        let mut sum = vec![Vec3::ZERO; voxels.len()];
        for (i, &v) in voxel_of.iter().enumerate() {
            if voxels[v as usize].count > MAX_FIXED_COUNT {
                sum[v as usize] += positions[i];
            }
        }
        for (v, s) in voxels.iter_mut().zip(sum) {
            if v.count > MAX_FIXED_COUNT {
                v.centroid = s / v.count as f32;
            }
        }
    }
    let particle_labels = voxel_of.iter().map(|&v| voxels[v as usize].label).collect();
    Ok(NarrowBand {
        origin: lo,
        edge,
        dims,
        voxels,
        labels: particle_labels,
        voxel_of,
    })
}

/// The band's interior on the GPU, kept there for the passes that read it (issue 37: the sparse
/// density grid's block states, [`crate::density::sparse_gpu`]): the counting and labelling
/// passes of [`narrow_band_gpu`] recorded into a frame's encoder over points already on the
/// GPU, their buffers kept from frame to frame. A voxel `v` is interior when
/// `counts[v] > 0 && labels[v] == 0`, as in the CPU's band ([`super::NarrowBand`]); the
/// centroids and each particle's voxel are not made.
pub struct ResidentBand {
    pipelines: [wgpu::ComputePipeline; 3],
    uniform: wgpu::Buffer,
    counts: crate::gpu::Grow,
    labels: crate::gpu::Grow,
    /// The bindings the counting-only passes do not write (the offsets' sums, the voxel of
    /// each particle): the smallest buffer.
    unused: crate::gpu::Grow,
    /// The points bound and the bind groups of the three passes.
    binds: Option<(wgpu::Buffer, [wgpu::BindGroup; 3])>,
    created: usize,
}

/// Where a band's voxels lie: the domain's minimum corner, the voxel's edge and the voxels
/// along each axis ([`ResidentBand::domain`]).
pub type BandDomain = (Vec3, f32, [u32; 3]);

impl ResidentBand {
    /// Compiles the passes for `device`.
    #[must_use]
    pub fn new(device: &wgpu::Device) -> Self {
        let usage = wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC;
        Self {
            pipelines: crate::gpu::compute_pipelines(
                device,
                "resident band",
                SHADER,
                ["cs_count", "cs_first", "cs_second"],
            ),
            uniform: crate::gpu::uniform_buffer(
                device,
                "resident band params",
                std::mem::size_of::<RawLnmParams>() as u64,
            ),
            counts: crate::gpu::Grow::new("band counts", usage),
            labels: crate::gpu::Grow::new("band labels", usage),
            unused: crate::gpu::Grow::new("band (unused)", usage),
            binds: None,
            created: 0,
        }
    }

    /// The domain of the band of points whose largest radius is `support_radius` and whose
    /// positions are `positions` (the CPU's [`super::narrow_band`] over them has these voxels),
    /// refused as [`narrow_band_gpu`] refuses (too many voxels for the dense layout).
    pub fn domain(
        positions: &[Vec3],
        support_radius: f32,
        params: &LnmParams,
    ) -> Result<BandDomain, LnmError> {
        let (lo, edge, dims) = domain(positions, support_radius, params)?;
        let total = dims.iter().map(|&d| u64::from(d)).product::<u64>();
        if total > MAX_DENSE_VOXELS {
            return Err(LnmError::DenseTooLarge {
                voxels: total,
                max: MAX_DENSE_VOXELS,
            });
        }
        Ok((lo, edge, dims))
    }

    /// Records the band of the `count` points of `points` (each `stride` `vec4`s apart, its
    /// position first) over `domain` into `encoder`: each voxel's count and label, in
    /// [`Self::counts`] and [`Self::labels`] once the encoder's work has run. `n_min`: the
    /// paper's, [`LnmParams::n_min`].
    pub fn record(
        &mut self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        (points, stride, count): (&wgpu::Buffer, u32, u32),
        (lo, edge, dims): BandDomain,
        n_min: u32,
    ) -> Result<(), GpuError> {
        let (device, queue) = (&ctx.device, &ctx.queue);
        let total = dims.iter().map(|&d| u64::from(d)).product::<u64>();
        if total > MAX_DENSE_VOXELS || total * 4 > crate::gpu::max_binding(device) {
            return Err(GpuError::Validation(format!(
                "a band of {total} voxels exceeds the dense layout's {MAX_DENSE_VOXELS} or the GPU's storage binding limit"
            )));
        }
        let made = [
            self.counts.reserve(device, total * 4),
            self.labels.reserve(device, total * 4),
            self.unused.reserve(device, 0),
        ];
        self.created = made.iter().filter(|&&m| m).count();
        if self.created > 0 || self.binds.as_ref().is_none_or(|(p, _)| p != points) {
            let group = |p, entries: &[(u32, &wgpu::Buffer)]| {
                crate::gpu::buffer_bind_group(device, p, entries)
            };
            let (counts, labels, unused) = (
                self.counts.buffer(),
                self.labels.buffer(),
                self.unused.buffer(),
            );
            let [count_pass, first, second] = &self.pipelines;
            let binds = [
                group(
                    count_pass,
                    &[
                        (0, &self.uniform),
                        (1, points),
                        (2, counts),
                        (3, unused),
                        (4, unused),
                    ],
                ),
                group(first, &[(0, &self.uniform), (2, counts), (5, labels)]),
                group(second, &[(0, &self.uniform), (2, counts), (5, labels)]),
            ];
            self.binds = Some((points.clone(), binds));
            self.created += 3;
        }
        let uniforms = RawLnmParams {
            lo: lo.extend(1.0 / edge).to_array(),
            dims: [dims[0], dims[1], dims[2], count],
            misc: [n_min, SCALE, stride, 1],
        };
        queue.write_buffer(&self.uniform, 0, bytemuck::bytes_of(&uniforms));
        encoder.clear_buffer(self.counts.buffer(), 0, Some(total * 4));
        let (_, binds) = self.binds.as_ref().expect("made above");
        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("resident band"),
            timestamp_writes: None,
        });
        for (i, (pipeline, bind)) in self.pipelines.iter().zip(binds).enumerate() {
            let (gx, gy) = groups(if i == 0 { u64::from(count) } else { total });
            if gx * gy == 0 {
                continue;
            }
            pass.set_pipeline(pipeline);
            pass.set_bind_group(0, bind, &[]);
            pass.dispatch_workgroups(gx, gy, 1);
        }
        Ok(())
    }

    /// Each voxel's particle count (x fastest over the domain's voxels).
    #[must_use]
    pub fn counts(&self) -> &wgpu::Buffer {
        self.counts.buffer()
    }

    /// Each voxel's label: 1 and 2 the paper's layers, 0 interior (or empty: count 0).
    #[must_use]
    pub fn labels(&self) -> &wgpu::Buffer {
        self.labels.buffer()
    }

    /// Buffers and bind groups the last [`Self::record`] made (0 once they are large enough).
    #[must_use]
    pub fn created(&self) -> usize {
        self.created
    }
}
