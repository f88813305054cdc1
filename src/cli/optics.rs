//! The finished frame (optics stage) for `render` and the main job.

use std::path::Path;
use std::time::Instant;

use fluid_surfels::Error;
use fluid_surfels::gpu::GpuContext;
use fluid_surfels::gpu::optics::{OpticsGpu, run_timed};
use fluid_surfels::optics::{self, Caustics, OpticsScene, Stage};
use fluid_surfels::splat::Surfel;
use glam::Vec3;
use image::RgbaImage;
use serde::Serialize;

use super::ms;

/// One finished frame.
pub struct Finished {
    pub image: RgbaImage,
    pub report: FrameReport,
}

/// Statistics of one finished frame.
#[derive(Clone, Debug, Serialize)]
pub struct FrameReport {
    pub surfels: usize,
    pub backend: String,
    pub screen: [u32; 2],
    pub map: [u32; 2],
    pub image: [u32; 2],
    /// Caustics triangles and the flux through the water (from the CPU reference's caustics,
    /// when they were made).
    pub caustics_triangles: Option<usize>,
    pub incident_flux: Option<[f32; 3]>,
    /// Total flux in the caustics map the frame was shaded with.
    pub map_flux: [f32; 3],
    /// The caustics the frame was shaded with (the GPU's on the GPU path).
    pub caustics_ms: f64,
    /// The final image after the caustics.
    pub frame_ms: f64,
    /// The CPU reference's caustics made beside the GPU's for the map picture.
    pub reference_caustics_ms: Option<f64>,
}

/// Renders finished frames on the GPU (its pipelines compiled once) or with the CPU reference.
pub struct FrameRenderer {
    gpu: Option<(GpuContext, OpticsGpu)>,
}

impl FrameRenderer {
    /// On the given context's device, or the CPU reference without one.
    pub fn new(ctx: Option<GpuContext>) -> Result<Self, Error> {
        let gpu = match ctx {
            Some(ctx) => {
                let optics = OpticsGpu::new(&ctx.device)?;
                Some((ctx, optics))
            }
            None => None,
        };
        Ok(Self { gpu })
    }

    /// Caustics and the final image.
    pub fn finish(&self, scene: &OpticsScene, surfels: &[Surfel]) -> Result<Finished, Error> {
        let stage = Stage::new(scene, surfels)?;
        let size = (scene.optics.image_size[0], scene.optics.image_size[1]);
        let cpu_caustics = |stage: &Stage| -> Result<(Caustics, f64), Error> {
            let t = Instant::now();
            let c = optics::caustics_cpu(stage, surfels)?;
            Ok((c, ms(t)))
        };
        let (image, caustics, backend, map_flux, caustics_ms, frame_ms, reference_ms) = match &self
            .gpu
        {
            Some((ctx, gpu)) => {
                let prepared = gpu.prepare(&ctx.device, &ctx.queue, &stage, surfels, Some(size))?;
                let times = run_timed(ctx, gpu, &prepared)?;
                let r = prepared.read(ctx)?;
                let (image, _) = r.frame.ok_or_else(|| Error::InvalidArgument {
                    argument: "image",
                    reason: "the GPU returned no frame".into(),
                })?;
                let flux = r
                    .flux
                    .iter()
                    .fold(Vec3::ZERO, |a, f| a + Vec3::new(f[0], f[1], f[2]));
                let name = ctx
                    .adapter
                    .as_ref()
                    .map_or("given device".to_string(), |a| {
                        format!("{} ({})", a.name, a.backend)
                    });
                let (caustics, reference_ms) = (None::<Caustics>, None);
                (
                    image,
                    caustics,
                    format!("gpu: {name}"),
                    flux,
                    times.caustics_ms,
                    times.frame_ms,
                    reference_ms,
                )
            }
            None => {
                let (c, caustics_ms) = cpu_caustics(&stage)?;
                let t = Instant::now();
                let f = optics::frame_cpu(&stage, surfels, &c, size)?;
                let flux = c.total_flux();
                (
                    f.image,
                    Some(c),
                    "cpu reference".to_string(),
                    flux,
                    caustics_ms,
                    ms(t),
                    None,
                )
            }
        };
        let report = FrameReport {
            surfels: surfels.len(),
            backend,
            screen: [stage.views.screen.width, stage.views.screen.height],
            map: [stage.views.map.width, stage.views.map.height],
            image: [size.0, size.1],
            caustics_triangles: caustics.as_ref().map(|c| c.triangles),
            incident_flux: caustics.as_ref().map(|c| c.incident.to_array()),
            map_flux: map_flux.to_array(),
            caustics_ms,
            frame_ms,
            reference_caustics_ms: reference_ms,
        };
        Ok(Finished { image, report })
    }
}

/// Writes an RGBA image as an RGB PNG.
pub fn save(img: &RgbaImage, path: &Path) -> Result<(), Error> {
    fluid_surfels::preview::save_rgba_png(img, path)?;
    Ok(())
}
