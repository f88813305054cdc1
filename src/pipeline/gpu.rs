//! [`GpuPipeline`]: the chain on the caller's wgpu device, drawing into the caller's render pass,
//! in the shape of wgpu "middleware" (glyphon, egui-wgpu): `new` builds every pipeline once,
//! `prepare` runs the frame's work and records its GPU passes into the caller's encoder, `render`
//! draws the finished frame into the caller's render pass, `resize` follows the window.
//!
//! What runs where: surface detection and upsampling run on the CPU (the [`Pipeline`] inside);
//! the boundary calibration runs on the GPU, its factors (the sheets one particle thick, how
//! buried each point is) and its weights' Jacobi solve
//! ([`crate::pipeline::boundary::gpu::WeightPasses`], into every copy of the points the grid is
//! filled from: the binned points, and the splatting's copy sorted by slab of four planes); the
//! points are sorted into both on the GPU ([`crate::density::bins::GpuBinSort`]: `prepare`
//! uploads them in their order) and the density grid is
//! filled on the GPU ([`crate::density::gpu::GridFiller`]: the paper's splatting by default,
//! or the gather pass, `grid.gpu_method`) and the surfels extracted
//! there ([`crate::surfels::gpu::ResidentSurfels`]: crossings, a prefix sum, the projection onto
//! the iso-surface), written into the buffer that the splatting draws by an indirect draw; a
//! sparse grid (`grid.narrow_band`) finds its blocks there too
//! ([`crate::density::sparse_gpu::GpuSparseLayout`]: the LNM band of the points and the blocks'
//! states, the evaluated blocks' values sized from a count read back a few frames late);
//! the optics stage (the light's splatting of the water, the caustics, the camera's splatting,
//! the refraction, reflection and the final image) runs on the GPU, and the frame is presented
//! by a full-screen pass. The views are fitted to the particles' box (the surfels never come back
//! to the CPU: half a spacing around the particles, an [`crate::optics::WaterShape`]). With
//! [`PipelineParams::gpu_surfels`] off, and for a renderer or source without a density grid,
//! the grid and the surfels are made on the CPU as [`Pipeline`] makes them and uploaded
//! ([`GpuPipeline::gpu_stages`] says which ran). The ray-cast renderer with the boundary
//! calibration draws a sphere for every particle and every sheet point (the refined points, or
//! the surface particles of the particle source), whose factors (which points are kept, how
//! much) and weights' Jacobi steps run on the GPU, the weights staying there for the caster,
//! which leaves out the spheres the factors drop ([`GpuPipeline::weights_on_gpu`],
//! [`crate::pipeline::boundary::gpu::PointWeights::record_layout`]).
//!
//! Nothing is read back and nothing waits on the GPU on the frame path (the surfel count comes
//! back asynchronously, a few frames late, to size the surfel buffer: call
//! [`GpuPipeline::after_submit`] once the encoder is submitted); the optics stage keeps its
//! targets, buffers and bind groups from frame to frame and updates the water in place while
//! the views' sizes, the receiver and the environment stay the same
//! ([`GpuPipeline::reused_resources`] says so), and builds them anew only when one changes.

use std::time::Instant;

use glam::Vec3;

use super::{Frame, Pipeline, PipelineParams, SurfelSource, Through, ms};
use crate::density::GridSpec;
use crate::density::gpu::{FillPoints, GridFiller};
use crate::density::sparse::BLOCK_VALUES;
use crate::density::sparse_gpu::GpuSparseLayout;
use crate::gpu::timer::{Mark, StageTimer};
use crate::gpu::{GpuContext, GpuError, entry};
use crate::optics::gpu::{OpticsGpu, PreparedOptics};
use crate::optics::{Stage, WaterShape};
use crate::pipeline::boundary::gpu::{
    PointWeights, RawSheetPoint, Split, WeightInput, WeightPasses, sheet_points,
};
use crate::splat::gpu::SplatRenderer;
use crate::splat::water::GpuSurfels;
use crate::splat::{Drawn, GpuWaterPass, WaterSurface};
use crate::surfels::gpu::ResidentSurfels;
use crate::{Error, ParticleView};

/// The stages [`GpuPipeline::prepare`] runs on the GPU with the grid and surfels there.
const GPU_STAGES: &[&str] = &["density", "surfels", "splats", "optics"];
/// ... and with the boundary calibration's weights solved there too.
const GPU_STAGES_WEIGHTS: &[&str] = &["calibration", "density", "surfels", "splats", "optics"];
/// ... and with them on the CPU.
const CPU_STAGES: &[&str] = &["splats", "optics"];
/// The stages with the ray caster's spheres weighted on the GPU
/// ([`GpuPipeline::weights_on_gpu`]).
const SPHERE_STAGES: &[&str] = &["calibration", "splats", "optics"];

/// The WGSL of the presenting pass.
pub const PRESENT_SHADER: &str = concat!(
    include_str!("../../shaders/common.wgsl"),
    include_str!("../../shaders/present.wgsl")
);

/// The presenting pass's `Present` uniform (16 bytes, checked against the WGSL in a test).
#[repr(C)]
#[derive(Clone, Copy, Debug, bytemuck::Pod, bytemuck::Zeroable)]
pub struct RawPresent {
    pub width: u32,
    pub height: u32,
    pub srgb_target: u32,
    pub _pad: u32,
}

const _: () = assert!(std::mem::size_of::<RawPresent>() == 16);

/// The chain on the caller's device. See the module documentation.
pub struct GpuPipeline {
    cpu: Pipeline,
    optics: OpticsGpu,
    format: wgpu::TextureFormat,
    size: (u32, u32),
    present: wgpu::RenderPipeline,
    present_layout: wgpu::BindGroupLayout,
    uniform: wgpu::Buffer,
    prepared: Option<(PreparedOptics, wgpu::BindGroup)>,
    /// Whether the last `prepare` reused the previous frame's GPU resources.
    reused: bool,
    /// The shaded image's water pass (the renderer's, for the caller's format and size), made
    /// on first use and again when the renderer or the size changes.
    pass: Option<Box<dyn GpuWaterPass>>,
    /// The shading pass for a water pass that does not shade itself (the ray caster's, the
    /// screen-space renderer's), made on first use.
    shading: Option<SplatRenderer>,
    /// The density grid and the surfels on the GPU, made on first use.
    chain: Option<GpuChain>,
    /// The ray caster's spheres' weights solved on the GPU, made on first use.
    sphere_weights: Option<PointWeights>,
    /// The stages the last `prepare` ran on the GPU.
    stages: &'static [&'static str],
    /// Timestamps between the stages, when asked for ([`GpuPipeline::time_stages`]) and the
    /// device has them.
    timer: Option<StageTimer>,
}

/// The GPU milliseconds of each stage of a recent frame ([`GpuPipeline::gpu_stage_ms`]), by
/// timestamp queries written between the stages' passes.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct GpuStageMs {
    /// Sorting the uploaded points into the bins the density's sums search (0 when the CPU
    /// made the grid).
    pub sort: f64,
    /// The boundary calibration: its factors and the sheet's weights' Jacobi steps (0 when
    /// the CPU made the grid or the chain has no calibration to solve).
    pub calibration: f64,
    /// Filling the density grid from the sorted, calibrated points, a sparse grid's layout
    /// included (0 when the CPU made it).
    pub density: f64,
    /// Extracting the surfels (0 when the CPU made them).
    pub surfels: f64,
    /// The light's splatting of the water and the caustics.
    pub caustics: f64,
    /// The camera's splatting, the refraction and reflection, the final image.
    pub image: f64,
}

/// The timestamps a timed frame writes ([`GpuPipeline::time_stages`]), in order; a stage that
/// did not run on the GPU writes its mark with the next one's (0 ms).
mod mark {
    /// Before the points' sort.
    pub(super) const START: u32 = 0;
    /// After the sort, before the calibration.
    pub(super) const SORTED: u32 = 1;
    /// After the calibration, before the fill.
    pub(super) const CALIBRATED: u32 = 2;
    /// After the grid's fill.
    pub(super) const FILLED: u32 = 3;
    /// After the surfels.
    pub(super) const SURFELS: u32 = 4;
    /// After the caustics.
    pub(super) const CAUSTICS: u32 = 5;
    /// After the final image.
    pub(super) const IMAGE: u32 = 6;
    /// What ran before each mark ([`super::GpuPipeline::gpu_pass_ms`]).
    pub(super) const STAGE_NAMES: [&str; 7] = [
        "start",
        "sort",
        "calibration",
        "density",
        "surfels",
        "caustics",
        "image",
    ];
}

/// The density grid and the surfels on the GPU, kept from frame to frame.
struct GpuChain {
    filler: GridFiller,
    surfels: ResidentSurfels,
    /// The boundary calibration's factors and weights, found where the grid is filled from the
    /// points (with the gather pass: the splatting draws its own copy of the points).
    weights: WeightPasses,
    /// A sparse grid's layout on the GPU, made on first use.
    layout: Option<GpuSparseLayout>,
    /// The bytes of the last grid's values: every point's, or a sparse grid's evaluated
    /// blocks'.
    grid_bytes: u64,
}

impl GpuPipeline {
    /// Compiles every shader and builds every pipeline once, for frames of `size` drawn into
    /// targets of `format`. The device needs [`crate::gpu::REQUIRED_FEATURES`].
    pub fn new(
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        format: wgpu::TextureFormat,
        size: (u32, u32),
        params: &PipelineParams,
    ) -> Result<Self, Error> {
        let _ = queue;
        check_size(size)?;
        let mut params = params.clone();
        params.scene.optics.image_size = [size.0, size.1];
        let mut cpu = Pipeline::new(params)?;
        // the CPU stages' surfels are drawn as the finished frame: `detail = "auto"` sees them so
        cpu.set_drawn(Some(Through::Frame));
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
        let optics = OpticsGpu::new(device)?;
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("present"),
            source: wgpu::ShaderSource::Wgsl(PRESENT_SHADER.into()),
        });
        let present_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("present"),
            entries: &[
                entry::uniform(0, wgpu::ShaderStages::FRAGMENT),
                wgpu::BindGroupLayoutEntry {
                    binding: 1,
                    visibility: wgpu::ShaderStages::FRAGMENT,
                    ty: wgpu::BindingType::Buffer {
                        ty: wgpu::BufferBindingType::Storage { read_only: true },
                        has_dynamic_offset: false,
                        min_binding_size: None,
                    },
                    count: None,
                },
            ],
        });
        let layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("present"),
            bind_group_layouts: &[Some(&present_layout)],
            ..Default::default()
        });
        let present = device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
            label: Some("present"),
            layout: Some(&layout),
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
                    format,
                    blend: None,
                    write_mask: wgpu::ColorWrites::ALL,
                })],
            }),
            multiview_mask: None,
            cache: None,
        });
        let uniform =
            crate::gpu::uniform_buffer(device, "present", std::mem::size_of::<RawPresent>() as u64);
        crate::splat::gpu::check_device(device, size.0, size.1)?;
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(GpuError::Validation(e.to_string()).into());
        }
        let mut pipeline = Self {
            pass: None,
            shading: None,
            chain: None,
            sphere_weights: None,
            stages: CPU_STAGES,
            timer: None,
            cpu,
            optics,
            format,
            size,
            present,
            present_layout,
            uniform,
            prepared: None,
            reused: false,
        };
        if pipeline.surfels_on_gpu() {
            pipeline.stages =
                if pipeline.cpu.params().grid.calibration == super::Calibration::Boundary {
                    GPU_STAGES_WEIGHTS
                } else {
                    GPU_STAGES
                };
        } else if pipeline.weights_on_gpu() {
            pipeline.stages = SPHERE_STAGES;
        }
        Ok(pipeline)
    }

    /// Whether `prepare` makes the density grid and the surfels on the GPU: with
    /// [`PipelineParams::gpu_surfels`], for the EWA renderer and the chain or particle source.
    #[must_use]
    pub fn surfels_on_gpu(&self) -> bool {
        self.cpu.params().gpu_surfels
            && self.cpu.params().source != SurfelSource::Refined
            && self.cpu.water_renderer().drawn() == Drawn::Surfels
    }

    /// Whether `prepare` solves the weights of the ray caster's spheres on the GPU: with
    /// [`PipelineParams::gpu_surfels`], for the ray-cast renderer with the boundary calibration
    /// and the chain or particle source. The spheres are every particle's and every sheet
    /// point's (made on the CPU); their factors (which particles form a sheet, how buried each
    /// point is, which points are left out) and the Jacobi steps run on the GPU
    /// ([`PointWeights::record_layout`]); the weights stay there ([`Frame::weights_on_gpu`]).
    #[must_use]
    pub fn weights_on_gpu(&self) -> bool {
        let params = self.cpu.params();
        params.gpu_surfels
            && params.source != SurfelSource::Refined
            && params.grid.calibration == super::Calibration::Boundary
            && self.cpu.water_renderer().drawn() == (Drawn::Spheres { calibrated: true })
    }

    /// The weights of the last frame's spheres solved on the GPU
    /// ([`GpuPipeline::weights_on_gpu`]), read back (a wait on the device: for tests and tools,
    /// outside the frame path), in the order of its `render_surfels`, a sphere the factors
    /// leave out [`crate::pipeline::boundary::gpu::DROPPED`]; `None` before one.
    pub fn read_sphere_weights(&self, ctx: &GpuContext) -> Result<Option<Vec<f32>>, Error> {
        let Some(w) = self.sphere_weights.as_ref() else {
            return Ok(None);
        };
        let mut out: Vec<f32> = crate::gpu::read_buffer(ctx, w.buffer())?;
        out.truncate(w.count());
        Ok(Some(out))
    }

    /// The bytes of the density grid's values the last [`GpuPipeline::prepare`] filled on the
    /// GPU: 4 per grid point, or with [`crate::pipeline::GridParams::narrow_band`] 4 per point
    /// of the evaluated blocks only (the memory follows the surface); `None` before the first
    /// such frame or when the CPU makes the grid.
    #[must_use]
    pub fn gpu_grid_bytes(&self) -> Option<u64> {
        self.chain
            .as_ref()
            .filter(|_| self.surfels_on_gpu())
            .map(|c| c.grid_bytes)
    }

    /// The stages the last [`GpuPipeline::prepare`] ran on the GPU (before the first, those it
    /// will run), by name: `"calibration"` (the boundary calibration's factors and weights,
    /// with the boundary calibration), `"density"` (the grid) and `"surfels"` when they run there
    /// ([`GpuPipeline::surfels_on_gpu`]), `"splats"` (the water's splatting for the light's and
    /// the camera's views) and `"optics"` (caustics, refraction, reflection, the final image).
    /// Detection and upsampling always run on the CPU.
    #[must_use]
    pub fn gpu_stages(&self) -> &'static [&'static str] {
        self.stages
    }

    /// Lets the surfel count of the frame just submitted come back (without a wait: it is
    /// looked at a few frames later, to grow the surfel buffer when a frame needs more): call
    /// it once the encoder `prepare` recorded into is submitted. Without it the buffer keeps
    /// its first size, a bound from the grid's faces, and surfels past it are left out (said in
    /// [`Frame::warnings`]).
    pub fn after_submit(&mut self) {
        if let Some(chain) = &mut self.chain {
            chain.surfels.after_submit();
            if let Some(layout) = &mut chain.layout {
                layout.after_submit();
            }
        }
        if let Some(timer) = &mut self.timer {
            timer.after_submit();
        }
        if let Some(pass) = &mut self.pass {
            pass.after_submit();
        }
        if let Some((prepared, _)) = &mut self.prepared {
            prepared.after_submit();
        }
    }

    /// Times each stage of the frames from the next `prepare` on (`on`), by timestamp queries
    /// written between the stages' passes, where the device has
    /// [`crate::gpu::TIMESTAMP_FEATURES`]; whether it can. Off by default: timestamps inside
    /// an encoder cost some drivers dearly (lavapipe: 1.9 s a frame of 96x96 became 3.5 s, the
    /// passes no longer overlapping).
    pub fn time_stages(&mut self, device: &wgpu::Device, queue: &wgpu::Queue, on: bool) -> bool {
        self.timer = if on {
            StageTimer::new(device, queue)
        } else {
            None
        };
        self.timer.is_some()
    }

    /// The GPU milliseconds of each stage of a recent finished frame, by timestamp queries read
    /// back without a wait (a few frames late, once [`GpuPipeline::after_submit`] was called
    /// for it and the device was polled, as a game's submits and presents do); `None` without
    /// [`GpuPipeline::time_stages`] and before the first arrives.
    #[must_use]
    pub fn gpu_stage_ms(&self) -> Option<GpuStageMs> {
        let ms = self.timer.as_ref()?.last_ms(mark::IMAGE as usize + 1)?;
        Some(GpuStageMs {
            sort: ms[0],
            calibration: ms[1],
            density: ms[2],
            surfels: ms[3],
            caustics: ms[4],
            image: ms[5],
        })
    }

    /// The GPU milliseconds of every timed pass of a recent finished frame, in order, each
    /// named by what ran since the timestamp before it: the stages of [`GpuStageMs`] (`"sort"`,
    /// `"calibration"`, `"density"`, `"surfels"`, `"caustics"`, `"image"`) and within the
    /// calibration its passes (`"calibration: factors"`, `"calibration: targets"`,
    /// `"calibration: compaction"`, `"calibration: steps"`, `"calibration: apply"`; the stage's
    /// own entry then holds what ran after its last pass), and with a sparse grid its layout
    /// (`"density: layout"`, the band and the blocks' states; `"density"` then the fill).
    /// Read back as [`Self::gpu_stage_ms`]
    /// is; `None` before the first arrives.
    #[must_use]
    pub fn gpu_pass_ms(&self) -> Option<Vec<(&'static str, f64)>> {
        let marks = self.timer.as_ref()?.last_marks()?;
        Some(
            marks
                .into_iter()
                .map(|(m, ms)| {
                    let name = match m {
                        Mark::Stage(i) => mark::STAGE_NAMES[i as usize],
                        Mark::Pass(name) => name,
                    };
                    (name, ms)
                })
                .collect(),
        )
    }

    /// Starts a frame's timestamps.
    fn begin_timing(&mut self) {
        if let Some(timer) = &mut self.timer {
            timer.begin();
        }
    }

    /// Writes the frame's timestamps up to `index` ([`mark`]'s).
    fn mark(&mut self, encoder: &mut wgpu::CommandEncoder, index: u32) {
        if let Some(timer) = &mut self.timer {
            timer.mark_to(encoder, index);
        }
    }

    /// The surfels of the last frame made on the GPU, read back (a wait on the device: for
    /// tests and tools, outside the frame path); `None` before one.
    pub fn read_surfels(&self, ctx: &GpuContext) -> Result<Option<crate::surfels::Surfels>, Error> {
        self.chain.as_ref().map(|c| c.surfels.read(ctx)).transpose()
    }

    /// Whether the last `prepare` reused the previous frame's GPU resources (the steady state:
    /// nothing created, uniforms, surfels and every renderer's inputs written through the
    /// queue); `false` on the first frame, after a resize, when the light's screen changed
    /// size, and while the GPU's grid, surfel or water buffers grow (the first frames of a
    /// sequence).
    #[must_use]
    pub fn reused_resources(&self) -> bool {
        self.reused
    }

    /// The frame size.
    #[must_use]
    pub fn size(&self) -> (u32, u32) {
        self.size
    }

    /// The target format the pipeline draws into.
    #[must_use]
    pub fn format(&self) -> wgpu::TextureFormat {
        self.format
    }

    /// The CPU half of the chain (hysteresis, kept views, support radius).
    #[must_use]
    pub fn cpu(&self) -> &Pipeline {
        &self.cpu
    }

    /// The CPU half, to run it on frames the GPU does not draw (detection on skipped frames
    /// keeps the hysteresis), to change its camera or its surfel source.
    pub fn cpu_mut(&mut self) -> &mut Pipeline {
        &mut self.cpu
    }

    /// Follows a new target size (from the next `prepare` on).
    pub fn resize(&mut self, device: &wgpu::Device, width: u32, height: u32) -> Result<(), Error> {
        check_size((width, height))?;
        crate::splat::gpu::check_device(device, width, height)?;
        if let Some(shading) = &mut self.shading {
            shading.resize(device, width, height)?;
        }
        self.size = (width, height);
        self.cpu.set_image_size(width, height);
        Ok(())
    }

    /// Runs the frame's CPU stages on `particles` and records its GPU passes (the density grid
    /// and the surfels when [`GpuPipeline::surfels_on_gpu`], caustics and the finished frame)
    /// into `encoder`; returns the CPU stages' frame (classes, refined points, timings; the
    /// surfels when they were made on the CPU, [`Frame::surfels_on_gpu`] otherwise). Submit the
    /// encoder and call [`GpuPipeline::after_submit`], then [`GpuPipeline::render`] draws the
    /// frame. `particles`: a `&ParticleSet`, or a [`ParticleView`] of the game's own buffers.
    pub fn prepare<'a>(
        &mut self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        encoder: &mut wgpu::CommandEncoder,
        particles: impl Into<ParticleView<'a>>,
    ) -> Result<Frame, Error> {
        let particles: ParticleView<'a> = particles.into();
        self.begin_timing();
        if self.weights_on_gpu() {
            return self.prepare_spheres(device, queue, encoder, particles);
        }
        if !self.surfels_on_gpu() {
            self.stages = CPU_STAGES;
            let frame = self.cpu.frame_through(particles, Through::Surfels)?;
            self.prepare_frame(device, queue, encoder, &frame)?;
            return Ok(frame);
        }
        // a dense grid is one storage binding; a sparse one's evaluated blocks are (checked
        // when they are known), its grid bounded by the memory budget as on the CPU
        let sparse = self.cpu.params().grid.narrow_band;
        let budget = if sparse {
            u64::MAX
        } else {
            crate::gpu::max_binding(device)
        };
        // the boundary weights are solved on the GPU, into every copy of the points the fill
        // reads
        let (mut frame, input) = self.cpu.frame_to_grid_with(particles, budget, true)?;
        let Some(input) = input else {
            // no point: the empty frame the CPU path draws
            self.prepare_frame(device, queue, encoder, &frame)?;
            return Ok(frame);
        };
        let ctx = GpuContext::from_device(device.clone(), queue.clone());
        let chain = self.chain.get_or_insert_with(|| GpuChain {
            filler: GridFiller::with_method(device, self.cpu.params().grid.gpu_method),
            surfels: ResidentSurfels::new(device),
            weights: WeightPasses::new(device),
            layout: None,
            grid_bytes: 0,
        });
        let (params, points) = (self.cpu.params(), input.points());
        let kernel = params.grid.kernel;
        let mut timer = self.timer.as_mut();
        // a stage's timestamp (`Mark::Stage`, written with those of the stages before it that
        // wrote none) or a pass's within one
        let mut mark = |encoder: &mut wgpu::CommandEncoder, m: Mark| {
            if let Some(t) = timer.as_deref_mut() {
                match m {
                    Mark::Stage(index) => t.mark_to(encoder, index),
                    Mark::Pass(name) => t.mark_pass(encoder, name),
                }
            }
        };
        let t = Instant::now();
        mark(encoder, Mark::Stage(mark::START));
        // the calibration's factors and the sheet's weights: found in the binned points before
        // the fill
        let sheet: Vec<RawSheetPoint> = input
            .solve
            .as_ref()
            .map_or_else(Vec::new, |s| sheet_points(&points, s.particles, &s.normals));
        // a sparse grid: which blocks to fill and their values, on the GPU (the LNM band of the
        // points and the blocks' states, `density::sparse_gpu`); the values sized from a count
        // read back a few frames late (before one has come back, from an upper bound found on
        // the CPU, `GpuSparseLayout::plan`), the grid coarsened where the whole grid's blocks
        // exceed the memory budget and that bound does too
        let mut spec = input.spec;
        let resident = if sparse {
            let limit = params
                .grid
                .memory_budget
                .min(crate::gpu::max_binding(device));
            let layout = chain
                .layout
                .get_or_insert_with(|| GpuSparseLayout::new(device));
            Some(plan_sparse(layout, points, (&mut spec, limit), &mut frame)?)
        } else {
            None
        };
        let weights = &mut chain.weights;
        let mut weights_made = 0;
        let mut solve = |encoder: &mut wgpu::CommandEncoder, copy: FillPoints<'_>| {
            match copy {
                FillPoints::Binned(_) => mark(encoder, Mark::Stage(mark::SORTED)),
                // the sparse grid's layout, timed apart from the fill
                FillPoints::Laid => {
                    mark(encoder, Mark::Pass("density: layout"));
                    return Ok(());
                }
                FillPoints::Sorted(..) => {}
            }
            let Some(s) = input.solve.as_ref() else {
                mark(encoder, Mark::Stage(mark::CALIBRATED));
                return Ok(());
            };
            match copy {
                FillPoints::Binned(binned) => {
                    weights.record_marked(
                        (device, queue),
                        encoder,
                        &WeightInput {
                            binned,
                            origin: spec.origin,
                            sheet: &sheet,
                            split: Split::Found {
                                classes: &s.classes,
                            },
                            half_spacing: 0.5 * s.spacing,
                            tau: s.tau,
                            kernel,
                            h: points.h,
                        },
                        &mut |encoder, name| mark(encoder, Mark::Pass(name)),
                    )?;
                    mark(encoder, Mark::Stage(mark::CALIBRATED));
                }
                FillPoints::Sorted(copy, count) => weights.apply_to(device, encoder, copy, count),
                FillPoints::Laid => {}
            }
            weights_made = weights.created();
            Ok(())
        };
        let grid = if let Some((domain, capacity)) = resident {
            let inside = super::sparse_inside(kernel, &params.surfels, points.h);
            chain.grid_bytes = u64::from(capacity) * BLOCK_VALUES as u64 * 4;
            let layout = chain.layout.as_mut().expect("made above");
            chain.filler.record_sparse_resident(
                &ctx,
                encoder,
                (points, &spec, inside, kernel),
                (layout, domain, capacity),
                Some(&mut solve),
            )?
        } else {
            chain.grid_bytes = spec.bytes() as u64;
            chain
                .filler
                .record_with(&ctx, encoder, (points, &spec, kernel), Some(&mut solve))?
        };
        mark(encoder, Mark::Stage(mark::FILLED));
        frame.timings.density_ms = ms(t);
        let t = Instant::now();
        chain
            .surfels
            .record(&ctx, encoder, &grid, points, kernel, &params.surfels)?;
        mark(encoder, Mark::Stage(mark::SURFELS));
        frame.timings.surfels_ms = ms(t);
        frame.detail.surfels = chain.surfels.last_count().unwrap_or(0) as usize;
        if chain.surfels.overflowed() {
            frame.warnings.push(format!(
                "a recent frame had {} surfels, more than the {} the GPU's surfel buffer held: \
                 those past it were left out (the buffer has grown since)",
                frame.detail.surfels,
                chain.surfels.capacity()
            ));
        }
        frame.shape = Some(water_shape(&self.cpu, particles.positions, &frame, &spec));
        let created = chain.filler.created() + chain.surfels.created() + weights_made;
        frame.surfels_on_gpu = true;
        self.stages = if input.solve.is_some() {
            GPU_STAGES_WEIGHTS
        } else {
            GPU_STAGES
        };
        self.record(device, queue, encoder, &frame, (true, None))?;
        self.reused &= created == 0;
        Ok(frame)
    }

    /// [`GpuPipeline::prepare`] for the ray caster's spheres with their weights solved on the
    /// GPU ([`GpuPipeline::weights_on_gpu`]): the CPU's chain to the spheres (every particle
    /// and sheet point), then the weights' sort, factors and Jacobi steps in `encoder` (timed
    /// as the calibration, the sort's stage 0 ms), then the views.
    fn prepare_spheres(
        &mut self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        encoder: &mut wgpu::CommandEncoder,
        particles: ParticleView<'_>,
    ) -> Result<Frame, Error> {
        let (mut frame, layout) = self.cpu.frame_to_boundary_layout(particles)?;
        self.stages = SPHERE_STAGES;
        let Some(layout) = layout else {
            // no point: the empty frame the CPU path draws
            self.prepare_frame(device, queue, encoder, &frame)?;
            return Ok(frame);
        };
        let t = Instant::now();
        self.mark(encoder, mark::START);
        let ctx = GpuContext::from_device(device.clone(), queue.clone());
        let kernel = self.cpu.params().grid.kernel;
        let tau = self.cpu.iso_value(frame.radius);
        let weights = self
            .sphere_weights
            .get_or_insert_with(|| PointWeights::new(device));
        weights.record_layout(&ctx, encoder, &layout, (frame.radius, kernel, tau))?;
        let created = weights.created();
        self.mark(encoder, mark::CALIBRATED);
        frame.timings.calibration_ms += ms(t);
        frame.weights_on_gpu = true;
        self.record(device, queue, encoder, &frame, (true, None))?;
        self.reused &= created == 0;
        Ok(frame)
    }

    /// [`GpuPipeline::prepare`] for surfels a CPU [`Pipeline`] already made: records the GPU
    /// passes of `frame.render_surfels` into `encoder`.
    pub fn prepare_frame(
        &mut self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        encoder: &mut wgpu::CommandEncoder,
        frame: &Frame,
    ) -> Result<(), Error> {
        self.begin_timing();
        self.record(device, queue, encoder, frame, (true, None))
    }

    /// Both pictures of `frame` from one build of the renderer's water (the ray caster's index,
    /// the screen-space narrow band): [`GpuPipeline::prepare_frame`], then
    /// [`GpuPipeline::encode_splats`] into `splats_target`.
    pub fn prepare_frame_and_splats(
        &mut self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        encoder: &mut wgpu::CommandEncoder,
        frame: &Frame,
        splats_target: &wgpu::TextureView,
    ) -> Result<(), Error> {
        self.record(device, queue, encoder, frame, (true, Some(splats_target)))
    }

    /// Builds the renderer's water of `frame` once, then records the finished frame's passes
    /// (`finished`) and the shaded splats into a target (`splats`).
    fn record(
        &mut self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        encoder: &mut wgpu::CommandEncoder,
        frame: &Frame,
        (finished, splats): (bool, Option<&wgpu::TextureView>),
    ) -> Result<(), Error> {
        let (points, gpu_weights);
        let water: Box<dyn WaterSurface + '_>;
        if frame.surfels_on_gpu {
            // the surfels the last `prepare` left on the GPU
            let chain = self.chain.as_ref().ok_or_else(|| Error::InvalidArgument {
                argument: "frame",
                reason: "its surfels are on another GpuPipeline's GPU: draw it with the pipeline \
                         that prepared it"
                    .into(),
            })?;
            water = Box::new(GpuSurfels(chain.surfels.surfel_buffer()));
        } else {
            // the spheres' weights the last `prepare` left on the GPU
            gpu_weights = match (frame.weights_on_gpu, self.sphere_weights.as_ref()) {
                (false, _) => None,
                (true, Some(w)) => Some(w.buffer().clone()),
                (true, None) => {
                    return Err(Error::InvalidArgument {
                        argument: "frame",
                        reason: "its weights are on another GpuPipeline's GPU: draw it with the \
                                 pipeline that prepared it"
                            .into(),
                    });
                }
            };
            points = self.cpu.water_points(&frame.render_surfels);
            water = self.cpu.water_with(
                &frame.render_surfels,
                points.as_ref(),
                (&frame.render_weights, gpu_weights.as_ref()),
            )?;
        }
        let shape = self.cpu.shape_of(frame);
        if finished {
            self.prepare_frame_with(
                device,
                queue,
                encoder,
                (&shape, frame.radius),
                water.as_ref(),
            )?;
        }
        match splats {
            Some(target) => {
                self.encode_splats_with(device, queue, encoder, shape.drawn, water.as_ref(), target)
            }
            None => Ok(()),
        }
    }

    /// [`GpuPipeline::prepare_frame`] with the frame's water built (its `shape`, the support
    /// radius `radius`).
    fn prepare_frame_with(
        &mut self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        encoder: &mut wgpu::CommandEncoder,
        (shape, radius): (&WaterShape, f32),
        water: &dyn WaterSurface,
    ) -> Result<(), Error> {
        let scene = self.cpu.fitted_scene(shape, radius)?;
        let stage = Stage::fitted(&scene, shape, None)?;
        // the steady state: last frame's targets fit (the views are kept), only uniforms,
        // receiver and surfels are written
        let updated = match &mut self.prepared {
            Some((prepared, _)) if prepared.image_buffer().map(|(_, s)| s) == Some(self.size) => {
                prepared.update_water(device, queue, &stage, water)?
            }
            _ => false,
        };
        // reused: updated in place, and the water's passes grew no buffer
        self.reused = updated
            && self
                .prepared
                .as_ref()
                .is_some_and(|(p, _)| p.water_created() == 0);
        if !updated {
            let prepared =
                self.optics
                    .prepare_water(device, queue, &stage, water, Some(self.size))?;
            let (image, _) = prepared
                .image_buffer()
                .expect("prepared with an image size");
            let bind = device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("present"),
                layout: &self.present_layout,
                entries: &[
                    wgpu::BindGroupEntry {
                        binding: 0,
                        resource: self.uniform.as_entire_binding(),
                    },
                    wgpu::BindGroupEntry {
                        binding: 1,
                        resource: image.as_entire_binding(),
                    },
                ],
            });
            self.prepared = Some((prepared, bind));
        }
        self.mark(encoder, mark::SURFELS);
        let (prepared, _) = self.prepared.as_ref().expect("prepared above");
        prepared.encode_caustics(queue, &self.optics, encoder)?;
        self.mark(encoder, mark::CAUSTICS);
        let (prepared, _) = self.prepared.as_ref().expect("prepared above");
        prepared.encode_frame(queue, &self.optics, encoder)?;
        self.mark(encoder, mark::IMAGE);
        if let Some(timer) = &mut self.timer {
            timer.end(encoder);
        }
        let (w, h) = self.size;
        queue.write_buffer(
            &self.uniform,
            0,
            bytemuck::bytes_of(&RawPresent {
                width: w,
                height: h,
                srgb_target: u32::from(self.format.is_srgb()),
                _pad: 0,
            }),
        );
        Ok(())
    }

    /// Records the shaded EWA splats of `frame`'s surfels (Blinn-Phong, no optics) into `target`,
    /// a view of a texture of the pipeline's format and size: the other picture `GpuPipeline`
    /// draws, the GPU twin of [`super::Through::Splats`]. Seen from the sequence's kept camera
    /// (or the scene's, or one framing the water's shape, [`Frame::shape`], as the CPU
    /// pipeline does), drawn by the
    /// renderer's [`GpuWaterPass`]: the splats write their surfels into a growing buffer through
    /// the queue and create nothing in the steady state; the ray caster and the screen-space
    /// renderer write their inputs into buffers they keep and are shaded by the splats' shading pass.
    /// A frame whose surfels are on the GPU ([`Frame::surfels_on_gpu`]: the last one
    /// [`GpuPipeline::prepare`] made) is drawn from their buffer.
    pub fn encode_splats(
        &mut self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        encoder: &mut wgpu::CommandEncoder,
        frame: &Frame,
        target: &wgpu::TextureView,
    ) -> Result<(), Error> {
        self.record(device, queue, encoder, frame, (false, Some(target)))
    }

    /// [`GpuPipeline::encode_splats`] with the frame's water built (`drawn`: its box).
    fn encode_splats_with(
        &mut self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        encoder: &mut wgpu::CommandEncoder,
        drawn: Option<(Vec3, Vec3)>,
        water: &dyn WaterSurface,
        target: &wgpu::TextureView,
    ) -> Result<(), Error> {
        let camera = self.cpu.splat_camera(drawn);
        let view = self.cpu.draw_view(&camera, self.size)?;
        let prepared = match &mut self.pass {
            Some(pass) => water.prepare_gpu(device, queue, pass.as_mut(), &view)?,
            None => false,
        };
        if !prepared {
            // the first frame, another renderer or another size: a new pass
            let mut pass = water.gpu_pass(device, self.format, self.size)?;
            if !water.prepare_gpu(device, queue, pass.as_mut(), &view)? {
                return Err(GpuError::Validation(
                    "a water pass its own renderer could not prepare".into(),
                )
                .into());
            }
            self.pass = Some(pass);
        }
        let pass = self.pass.as_deref().expect("made above");
        if !pass.shades_itself() && self.shading.is_none() {
            let (w, h) = self.size;
            self.shading = Some(SplatRenderer::new(device, self.format, w, h)?);
        }
        pass.encode_shaded(device, queue, encoder, target, self.shading.as_ref())
    }

    /// Draws the prepared frame into the caller's render pass (a target of the pipeline's format
    /// and size). Draws nothing before the first `prepare`.
    pub fn render(&self, pass: &mut wgpu::RenderPass<'_>) {
        if let Some((_, bind)) = &self.prepared {
            pass.set_pipeline(&self.present);
            pass.set_bind_group(0, bind, &[]);
            pass.draw(0..3, 0..1);
        }
    }

    /// Headless: prepares `frame`'s surfels, draws them into a texture of the pipeline's size and
    /// reads the image back (for the CLI, tests and saved frames of a game loop). The pipeline's
    /// format must be `Rgba8Unorm` or `Rgba8UnormSrgb`.
    pub fn render_frame_image(
        &mut self,
        ctx: &GpuContext,
        frame: &Frame,
    ) -> Result<image::RgbaImage, Error> {
        let mut encoder = ctx.device.create_command_encoder(&Default::default());
        self.prepare_frame(&ctx.device, &ctx.queue, &mut encoder, frame)?;
        let target = self.draw_to_texture(&ctx.device, &mut encoder);
        ctx.queue.submit([encoder.finish()]);
        self.after_submit();
        Ok(crate::gpu::read_rgba8(ctx, &target)?)
    }

    /// Headless: [`GpuPipeline::prepare`] on `particles`, the finished frame drawn into a
    /// texture of the pipeline's size and read back (a wait on the device: for the command
    /// line, tests and the saved frames of a game loop). The pipeline's format must be
    /// `Rgba8Unorm` or `Rgba8UnormSrgb`.
    pub fn prepare_image<'a>(
        &mut self,
        ctx: &GpuContext,
        particles: impl Into<ParticleView<'a>>,
    ) -> Result<(Frame, image::RgbaImage), Error> {
        let mut encoder = ctx.device.create_command_encoder(&Default::default());
        let frame = self.prepare(&ctx.device, &ctx.queue, &mut encoder, particles)?;
        let target = self.draw_to_texture(&ctx.device, &mut encoder);
        ctx.queue.submit([encoder.finish()]);
        self.after_submit();
        Ok((frame, crate::gpu::read_rgba8(ctx, &target)?))
    }

    /// Records a render pass of its own that clears `target` (a view of the pipeline's format and
    /// size) and draws the prepared frame into it; [`GpuPipeline::render`] draws into a pass the
    /// caller already has.
    pub fn draw_into(&self, encoder: &mut wgpu::CommandEncoder, target: &wgpu::TextureView) {
        let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
            label: Some("present"),
            color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                view: target,
                depth_slice: None,
                resolve_target: None,
                ops: wgpu::Operations {
                    load: wgpu::LoadOp::Clear(wgpu::Color::BLACK),
                    store: wgpu::StoreOp::Store,
                },
            })],
            ..Default::default()
        });
        self.render(&mut pass);
    }

    /// Records a render pass that draws the prepared frame into a new texture (`COPY_SRC`), and
    /// returns it.
    pub fn draw_to_texture(
        &self,
        device: &wgpu::Device,
        encoder: &mut wgpu::CommandEncoder,
    ) -> wgpu::Texture {
        let target = crate::gpu::texture_2d(
            device,
            "frame",
            self.size,
            self.format,
            wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC,
        );
        self.draw_into(encoder, &target.create_view(&Default::default()));
        target
    }
}

/// The water's shape for the views of a frame whose grid is `spec` (`cpu`: the pipeline that
/// detected its surface): with the paper's calibration the surface lies farther out than the
/// particles, so the grid's box bounds it.
fn water_shape(cpu: &Pipeline, positions: &[Vec3], frame: &Frame, spec: &GridSpec) -> WaterShape {
    cpu.grid_water_shape(positions, &frame.surface, frame.radius, spec)
        .unwrap_or_else(|| {
            let far = spec.origin + spec.spacing * Vec3::from(spec.dims.map(|d| d as f32 - 1.0));
            let grid_box = Some((spec.origin, far));
            WaterShape {
                drawn: grid_box,
                surface: grid_box,
                level: None,
            }
        })
}

/// A sparse grid's plan for `layout` (`spec` coarsened where its blocks exceed `limit` bytes,
/// [`sparse_spec_within`]): the band's domain and the evaluated blocks its values are to hold
/// ([`GpuSparseLayout::plan`]), the warnings in `frame`.
fn plan_sparse(
    layout: &mut GpuSparseLayout,
    points: crate::density::Points<'_>,
    (spec, limit): (&mut crate::density::GridSpec, u64),
    frame: &mut Frame,
) -> Result<(crate::lnm::gpu::BandDomain, u32), Error> {
    frame
        .warnings
        .extend(sparse_spec_within(points, spec, limit)?);
    frame.detail.cell = spec.spacing;
    let domain = crate::lnm::gpu::ResidentBand::domain(
        points.positions,
        points.max_radius(),
        &crate::lnm::LnmParams::default(),
    )?;
    let slots = limit / (BLOCK_VALUES as u64 * 4);
    let capacity = layout.plan(&points, spec, slots.min(u64::from(u32::MAX)) as u32);
    if layout.overflowed() {
        frame.warnings.push(format!(
            "a recent frame's sparse density grid had {} evaluated blocks, more than the {} its values held (the memory budget or the GPU's binding limit allows {slots}): those past them were left empty",
            layout.last_count().unwrap_or(0),
            layout.counted_capacity().unwrap_or(0)
        ));
    }
    Ok((domain, capacity))
}

/// The grid `spec` of a sparse grid of `points` coarsened, by steps of 5 %, until an upper
/// bound of its evaluated blocks' values and its blocks' states
/// ([`crate::density::sparse_gpu::evaluated_bound`]) fits `limit` bytes, with a warning when it
/// was (the dense grid fits the budget, [`super::grid_for`], but a sparse one of a small or
/// thin body evaluates blocks that overhang it). The bound is found here only when the whole
/// grid's blocks would not fit.
fn sparse_spec_within(
    points: crate::density::Points<'_>,
    spec: &mut crate::density::GridSpec,
    limit: u64,
) -> Result<Option<String>, Error> {
    use crate::density::{GridSpec, Resolution, sparse_gpu::evaluated_bound};
    let block_bytes = BLOCK_VALUES as u128 * 4 + 8;
    let blocks = |s: &GridSpec| {
        crate::density::sparse::blocks_of(s)
            .map(u128::from)
            .iter()
            .product::<u128>()
    };
    let needed = |s: &GridSpec| {
        let whole = blocks(s) * block_bytes;
        if whole <= u128::from(limit) {
            return whole;
        }
        u128::from(evaluated_bound(&points, s)) * (BLOCK_VALUES as u128 * 4) + blocks(s) * 8
    };
    let first = *spec;
    let wanted = needed(spec);
    let mut now = wanted;
    for _ in 0..200 {
        if now <= u128::from(limit) {
            break;
        }
        *spec = GridSpec::around(
            points.positions,
            points.max_radius(),
            Resolution::CellSize(spec.spacing * 1.05),
        )?;
        now = needed(spec);
    }
    Ok((spec.spacing != first.spacing).then(|| {
        let mib = |b: u128| b as f64 / (1u64 << 20) as f64;
        format!(
            "the sparse density grid's blocks at spacing {:.5} (up to {:.2} MiB) exceed the memory budget of {:.2} MiB; \
             coarsened to spacing {:.5} ({} x {} x {}): the surface loses detail finer than that (raise grid.memory_budget)",
            first.spacing,
            mib(wanted),
            mib(u128::from(limit)),
            spec.spacing,
            spec.dims[0],
            spec.dims[1],
            spec.dims[2],
        )
    }))
}

fn check_size((w, h): (u32, u32)) -> Result<(), Error> {
    if !(1..=crate::splat::MAX_SIZE).contains(&w) || !(1..=crate::splat::MAX_SIZE).contains(&h) {
        return Err(Error::InvalidArgument {
            argument: "size",
            reason: format!(
                "{w}x{h}: each side must lie in 1..={}",
                crate::splat::MAX_SIZE
            ),
        });
    }
    Ok(())
}

/// Stage 3 with the density grid splatted on the GPU (Iwasaki et al. §4: slice by slice, four
/// planes per RGBA pass, each point with its own radius; [`crate::density::gpu`]) and read back
/// for the CPU surfel extraction: [`super::iso_surfels`]'s twin, with the same grid (its box,
/// resolution and memory budget, coarsened with a warning when over it, as on the CPU) and
/// the same surfels to the tolerance of the GPU's sums (`tests/gpu.rs`). Always a dense grid:
/// `grid.narrow_band` (the sparse blocks) is a CPU layout. `None` when there is no point.
///
/// The read-back waits on the GPU, so this is for offline use (`surfels --gpu`); the frame path
/// of a game keeps the CPU grid until extraction moves to the GPU.
pub fn iso_surfels_gpu(
    ctx: &GpuContext,
    points: crate::density::Points<'_>,
    grid: &super::GridParams,
    params: &crate::surfels::SurfelParams,
) -> Result<Option<super::IsoSurfels>, Error> {
    if points.is_empty() {
        return Ok(None);
    }
    points.check()?;
    let (spec, warning) = super::grid_for(&points, grid)?;
    let t = std::time::Instant::now();
    let values = crate::density::gpu::density_grid_gpu(ctx, points, &spec, grid.kernel)?;
    let density_ms = t.elapsed().as_secs_f64() * 1e3;
    let t = std::time::Instant::now();
    let surfels = crate::surfels::extract_points(&values, points, grid.kernel, params)?;
    Ok(Some(super::IsoSurfels {
        grid: crate::density::Grid::Dense(values),
        surfels,
        hidden: 0,
        density_ms,
        surfels_ms: t.elapsed().as_secs_f64() * 1e3,
        warning,
    }))
}

impl Pipeline {
    /// [`Pipeline::draw`] on a GPU: the same picture drawn by the renderer's wgpu twin
    /// (`splat::gpu`, `raycast::gpu`, `ssfr::gpu`) on `ctx`, read back (offline use: `render
    /// --gpu`; a game draws through [`GpuPipeline`] instead).
    pub fn draw_gpu(
        &self,
        ctx: &GpuContext,
        (surfels, weights): (&[crate::splat::Surfel], &[f32]),
        camera: &crate::splat::Camera,
        (w, h): (u32, u32),
    ) -> Result<crate::splat::Render, Error> {
        let points = self.water_points(surfels);
        let water = self.water_of(surfels, points.as_ref(), weights)?;
        water.render_gpu(ctx, &self.draw_view(camera, (w, h))?)
    }
}
