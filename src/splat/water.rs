//! The renderers behind one trait each side (issue 38): what draws the water, for the shaded
//! splats and for the optics' views (the light's screen and the camera).
//!
//! - [`WaterRenderer`]: a way of drawing the water, made once from the pipeline's parameters
//!   (`pipeline::water_renderer` holds the registration: one line a renderer). It says what the
//!   surfel source gives it ([`Drawn`]) and builds the frame's water.
//! - [`WaterSurface`]: one frame's water, built once for every view of the frame (the ray
//!   caster's index, the screen-space renderer's narrow band): drawn on the CPU
//!   ([`WaterSurface::render`]), headless on a GPU ([`WaterSurface::render_gpu`]), or uploaded
//!   into a [`GpuWaterPass`] that records into the caller's encoder.
//! - [`GpuWaterPass`]: the GPU targets and passes of one view size, kept from frame to frame;
//!   its accumulation targets are what the splats' shading pass and the GPU optics read.
//!
//! The implementations: [`Ewa`] and [`ParticleSplat`] here (a slice of surfels splatted), `raycast::Method`
//! and `ssfr::Method` in their modules. `Pipeline` and `GpuPipeline` hold a `WaterRenderer` and
//! never match on the kind; a renderer of one's own is given by `Pipeline::set_water_renderer`.

use std::any::Any;

use glam::Vec3;

use super::gpu::{SplatRenderer, SurfelBuffer};
use super::{Render, SplatMode, SplatParams, Surfel, View};
use crate::Error;
use crate::gpu::{GpuContext, GpuError};

/// What a renderer draws the water from: what the pipeline's surfel source makes for it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Drawn {
    /// The surfels on the density grid's iso-surface (EWA splatting).
    Surfels,
    /// The source's points as spheres of their kernel radius (no density grid). `calibrated`:
    /// the renderer draws the iso-surface of the points' density, so with the boundary
    /// calibration it takes the density grid's points with their weights (the ray caster).
    Spheres { calibrated: bool },
}

impl Drawn {
    /// What is drawn, for reports: "surfels" or "spheres".
    #[must_use]
    pub fn noun(self) -> &'static str {
        match self {
            Self::Surfels => "surfels",
            Self::Spheres { .. } => "spheres",
        }
    }
}

/// One frame's inputs of [`WaterRenderer::water`].
#[derive(Clone, Copy)]
pub struct WaterInput<'a> {
    /// The frame's surfels (`Frame::render_surfels`: the spheres of [`Drawn::Spheres`]).
    pub surfels: &'a [Surfel],
    /// The centres and radii of those spheres (`pipeline::sphere_points`), when the renderer
    /// asks for them ([`WaterRenderer::needs_points`]); empty otherwise.
    pub points: (&'a [Vec3], &'a [f32]),
    /// The spheres' weights in the density (the boundary calibration's; empty: every one 1).
    pub weights: &'a [f32],
    /// The same weights on the GPU instead (`f32` a sphere, in their order; solved there by
    /// `GpuPipeline`): the GPU passes read them, a CPU render of such water is refused.
    pub gpu_weights: Option<&'a wgpu::Buffer>,
    /// The reference radius (the support radius, or the largest radius before one is known).
    pub reference_radius: f32,
}

/// A way of drawing the water. See the module documentation.
pub trait WaterRenderer: Send + Sync {
    /// What the surfel source makes for it.
    fn drawn(&self) -> Drawn;
    /// Whether [`WaterRenderer::water`] reads [`WaterInput::points`].
    fn needs_points(&self) -> bool {
        false
    }
    /// The splat parameters of its pictures, from the pipeline's `[splat]` (particle splatting
    /// draws spheres).
    fn splat_params(&self, params: SplatParams) -> SplatParams {
        params
    }
    /// Sets the depth offset `--depth-offset` means for this renderer (EWA: `depth_offset`,
    /// particle splatting: `sphere_depth_offset`; none for the others).
    fn set_depth_offset(&self, params: &mut SplatParams, offset: f32) {
        let _ = (params, offset);
    }
    /// Whether it never draws a surfel whose normal faces away from the eye (EWA's disks and
    /// sprites, not its spheres: [`SplatMode::Spheres`]), so that the pipeline may leave those
    /// out of a picture drawn from known views (`detail = "auto"`). Default `false`.
    fn culls_back_faces(&self) -> bool {
        false
    }
    /// The frame's water, built once for every view of the frame.
    fn water<'a>(&self, input: WaterInput<'a>) -> Result<Box<dyn WaterSurface + 'a>, Error>;
}

/// One frame's water. See the module documentation.
pub trait WaterSurface: Sync {
    /// The water as seen in `view`, on the CPU: the per-pixel accumulations
    /// (`(sum w colour, sum w)`, `(sum w normal, sum w depth)`) the optics read, and the shaded
    /// image.
    fn render(&self, view: &View) -> Result<Render, Error>;

    /// [`WaterSurface::render`] on a GPU, read back (offline use).
    fn render_gpu(&self, ctx: &GpuContext, view: &View) -> Result<Render, Error> {
        let _ = (ctx, view);
        Err(no_gpu_twin())
    }

    /// New GPU targets and passes for views of `size`, shading into targets of `format`.
    fn gpu_pass(
        &self,
        device: &wgpu::Device,
        format: wgpu::TextureFormat,
        size: (u32, u32),
    ) -> Result<Box<dyn GpuWaterPass>, Error> {
        let _ = (device, format, size);
        Err(no_gpu_twin())
    }

    /// Uploads this frame's water into `pass` for `view`; `false`, changing nothing, when `pass`
    /// was made by another renderer or for another size (make a new one with
    /// [`WaterSurface::gpu_pass`]).
    fn prepare_gpu(
        &self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        pass: &mut dyn GpuWaterPass,
        view: &View,
    ) -> Result<bool, Error> {
        let _ = (device, queue, pass, view);
        Ok(false)
    }
}

fn no_gpu_twin() -> Error {
    Error::InvalidArgument {
        argument: "renderer",
        reason: "this renderer has no GPU twin".into(),
    }
}

/// The GPU targets and passes of one renderer at one view size. See the module documentation.
pub trait GpuWaterPass: Any + Send + Sync {
    /// The size of its targets.
    fn size(&self) -> (u32, u32);
    /// Records the passes that fill the accumulation targets for the view last prepared. Its
    /// uniforms may be written through the queue: one view per submission.
    fn encode(&self, queue: &wgpu::Queue, encoder: &mut wgpu::CommandEncoder) -> Result<(), Error>;
    /// The accumulation targets after [`GpuWaterPass::encode`]: `(sum w colour, sum w)` and
    /// `(sum w normal, sum w depth)`, `Rgba32Float`.
    fn accumulation(&self) -> Result<(&wgpu::TextureView, &wgpu::TextureView), Error>;
    /// Whether [`GpuWaterPass::encode_shaded`] shades with a renderer of its own.
    fn shades_itself(&self) -> bool {
        false
    }
    /// Records the passes and the shading into `target` (a view of the format and size the
    /// pass was made for): by default [`GpuWaterPass::encode`] then `shading`'s shading pass
    /// over the accumulation targets.
    fn encode_shaded(
        &self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        encoder: &mut wgpu::CommandEncoder,
        target: &wgpu::TextureView,
        shading: Option<&SplatRenderer>,
    ) -> Result<(), Error> {
        let shading = shading.ok_or_else(|| {
            GpuError::Validation("a water pass without a shading renderer".into())
        })?;
        self.encode(queue, encoder)?;
        let view = self.view()?;
        shading.encode_shading_of(device, queue, encoder, target, self.accumulation()?, view)
    }
    /// The view last prepared.
    fn view(&self) -> Result<&View, Error>;
    /// Buffers and bind groups the last [`WaterSurface::prepare_gpu`] made for it (0 in the
    /// steady state of a sequence, when the frame's inputs were written into kept buffers).
    fn created(&self) -> usize {
        0
    }
    /// Starts what it reads back without a wait (the screen-space renderer's tiles'
    /// statistics) once the encoder it recorded into is submitted; nothing by default.
    fn after_submit(&mut self) {}
    /// For [`WaterSurface::prepare_gpu`]'s downcast to the concrete pass.
    fn as_any_mut(&mut self) -> &mut dyn Any;
}

/// EWA surface splatting of the source's surfels (Botsch et al. 2005): the design.
#[derive(Clone, Copy, Debug, Default)]
pub struct Ewa;

impl WaterRenderer for Ewa {
    fn drawn(&self) -> Drawn {
        Drawn::Surfels
    }
    fn culls_back_faces(&self) -> bool {
        true
    }
    fn set_depth_offset(&self, params: &mut SplatParams, offset: f32) {
        params.depth_offset = offset;
    }
    fn water<'a>(&self, input: WaterInput<'a>) -> Result<Box<dyn WaterSurface + 'a>, Error> {
        Ok(Box::new(input.surfels))
    }
}

/// Particle splatting (Adams et al. 2006): the source's points drawn as spheres of their kernel
/// radius ([`SplatMode::Spheres`]), blended within `sphere_depth_offset` radii of the nearest.
#[derive(Clone, Copy, Debug, Default)]
pub struct ParticleSplat;

impl WaterRenderer for ParticleSplat {
    fn drawn(&self) -> Drawn {
        Drawn::Spheres { calibrated: false }
    }
    fn splat_params(&self, mut params: SplatParams) -> SplatParams {
        params.mode = SplatMode::Spheres;
        params
    }
    fn set_depth_offset(&self, params: &mut SplatParams, offset: f32) {
        params.sphere_depth_offset = offset;
    }
    fn water<'a>(&self, input: WaterInput<'a>) -> Result<Box<dyn WaterSurface + 'a>, Error> {
        Ok(Box::new(input.surfels))
    }
}

/// Surfels drawn by splatting, as the view's mode says (EWA disks, sprites or spheres).
impl WaterSurface for &[Surfel] {
    fn render(&self, view: &View) -> Result<Render, Error> {
        Ok(super::render_view_cpu(self, view)?)
    }

    fn render_gpu(&self, ctx: &GpuContext, view: &View) -> Result<Render, Error> {
        super::gpu::render_view_gpu(ctx, self, view)
    }

    fn gpu_pass(
        &self,
        device: &wgpu::Device,
        format: wgpu::TextureFormat,
        size: (u32, u32),
    ) -> Result<Box<dyn GpuWaterPass>, Error> {
        SplatPass::boxed(device, format, size)
    }

    fn prepare_gpu(
        &self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        pass: &mut dyn GpuWaterPass,
        view: &View,
    ) -> Result<bool, Error> {
        let Some(pass) = SplatPass::of_size(pass, view) else {
            return Ok(false);
        };
        pass.created = usize::from(pass.surfels.write(device, queue, self));
        pass.view = Some(*view);
        Ok(true)
    }
}

/// Surfels that live on the GPU (made there by `surfels::gpu::ResidentSurfels`), drawn by the
/// EWA splatting's passes from their buffer with an indirect draw: nothing uploaded, nothing
/// read back. They have no CPU picture ([`WaterSurface::render`] refuses; read them back
/// first).
pub struct GpuSurfels(pub SurfelBuffer);

impl WaterSurface for GpuSurfels {
    fn render(&self, _view: &View) -> Result<Render, Error> {
        Err(Error::InvalidArgument {
            argument: "water",
            reason: "surfels that live on the GPU have no CPU picture: read them back first \
                     (ResidentSurfels::read)"
                .into(),
        })
    }

    fn render_gpu(&self, ctx: &GpuContext, view: &View) -> Result<Render, Error> {
        super::gpu::render_buffer_gpu(ctx, &self.0, view)
    }

    fn gpu_pass(
        &self,
        device: &wgpu::Device,
        format: wgpu::TextureFormat,
        size: (u32, u32),
    ) -> Result<Box<dyn GpuWaterPass>, Error> {
        SplatPass::boxed(device, format, size)
    }

    fn prepare_gpu(
        &self,
        _device: &wgpu::Device,
        _queue: &wgpu::Queue,
        pass: &mut dyn GpuWaterPass,
        view: &View,
    ) -> Result<bool, Error> {
        let Some(pass) = SplatPass::of_size(pass, view) else {
            return Ok(false);
        };
        // the same buffers frame after frame: a clone of the handles, nothing created
        pass.surfels = self.0.clone();
        pass.created = 0;
        pass.view = Some(*view);
        Ok(true)
    }
}

/// The splats' GPU pass: a [`SplatRenderer`] and its surfel buffer (written in place from frame
/// to frame).
pub struct SplatPass {
    renderer: SplatRenderer,
    surfels: SurfelBuffer,
    view: Option<View>,
    /// Buffers the last prepare made (the surfel buffer grown).
    created: usize,
}

impl SplatPass {
    /// A pass for views of `size` shading into `format`, with no surfels yet.
    fn boxed(
        device: &wgpu::Device,
        format: wgpu::TextureFormat,
        (w, h): (u32, u32),
    ) -> Result<Box<dyn GpuWaterPass>, Error> {
        Ok(Box::new(Self {
            renderer: SplatRenderer::new(device, format, w, h)?,
            surfels: SplatRenderer::upload(device, &[]),
            view: None,
            created: 0,
        }))
    }

    /// `pass` as the splats' pass, when it is one made for the size of `view`.
    fn of_size<'p>(pass: &'p mut dyn GpuWaterPass, view: &View) -> Option<&'p mut Self> {
        pass.as_any_mut()
            .downcast_mut::<Self>()
            .filter(|p| p.renderer.size() == (view.width, view.height))
    }
}

impl GpuWaterPass for SplatPass {
    fn size(&self) -> (u32, u32) {
        self.renderer.size()
    }
    fn encode(&self, queue: &wgpu::Queue, encoder: &mut wgpu::CommandEncoder) -> Result<(), Error> {
        self.renderer
            .encode_accumulation_queued(queue, encoder, &self.surfels, self.view()?)
    }
    fn accumulation(&self) -> Result<(&wgpu::TextureView, &wgpu::TextureView), Error> {
        Ok(self.renderer.accumulation())
    }
    fn shades_itself(&self) -> bool {
        true
    }
    fn encode_shaded(
        &self,
        _device: &wgpu::Device,
        queue: &wgpu::Queue,
        encoder: &mut wgpu::CommandEncoder,
        target: &wgpu::TextureView,
        _shading: Option<&SplatRenderer>,
    ) -> Result<(), Error> {
        self.renderer
            .encode_queued(queue, encoder, target, &self.surfels, self.view()?)
    }
    fn view(&self) -> Result<&View, Error> {
        self.view.as_ref().ok_or_else(unprepared)
    }
    fn created(&self) -> usize {
        self.created
    }
    fn as_any_mut(&mut self) -> &mut dyn Any {
        self
    }
}

/// The error of a pass recorded before it was prepared.
pub fn unprepared() -> Error {
    GpuError::Validation("a water pass recorded before it was prepared".into()).into()
}
