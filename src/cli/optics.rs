//! The finished frame (optics stage) for `render` and the main job.

use std::path::Path;
use std::time::Instant;

use fluid_surfels::Error;
use fluid_surfels::gpu::GpuContext;
use fluid_surfels::gpu::optics::{OpticsGpu, run_timed};
use fluid_surfels::optics::{self, Caustics, OpticsScene, ReceiverKind, Stage};
use fluid_surfels::splat::Surfel;
use glam::Vec3;
use image::{RgbImage, RgbaImage};
use serde::Serialize;

use super::ms;

/// One finished frame.
pub struct Finished {
    pub stage: Stage,
    /// The CPU reference's caustics, where they were made (always on the CPU path; on the GPU
    /// path only when asked for, to picture the map).
    pub caustics: Option<Caustics>,
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

    /// Caustics and the final image. `reference_caustics` asks for the CPU reference's caustics
    /// on the GPU path too (the map picture needs them); the CPU path always makes them.
    pub fn finish(
        &self,
        scene: &OpticsScene,
        surfels: &[Surfel],
        reference_caustics: bool,
    ) -> Result<Finished, Error> {
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
                let (caustics, reference_ms) = if reference_caustics {
                    let (c, t) = cpu_caustics(&stage)?;
                    (Some(c), Some(t))
                } else {
                    (None, None)
                };
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
        Ok(Finished {
            stage,
            caustics,
            image,
            report,
        })
    }
}

/// The pool scene of the `column` tank: an open box with a tiled floor, sunlight from above and
/// the side, water whose extinction is strong enough to tint a 0.45 m tank.
pub fn column_pool(tank: Vec3) -> OpticsScene {
    let mut s = OpticsScene::default();
    s.receiver.kind = ReceiverKind::OpenBox;
    s.receiver.min = Vec3::new(-0.005, -0.005, -0.005);
    s.receiver.max = Vec3::new(tank.x + 0.005, tank.y * 0.45, tank.z + 0.005);
    s.receiver.checker = 0.05;
    s.light.direction = Vec3::new(0.35, 1.0, 0.25);
    s.water.extinction = Vec3::new(3.0, 0.9, 0.5);
    s.camera = Some(fluid_surfels::splat::Camera {
        eye: Vec3::new(tank.x * 1.9, tank.y * 1.25, tank.z * 2.3),
        target: Vec3::new(tank.x * 0.45, tank.y * 0.12, tank.z * 0.45),
        fov_y_degrees: 40.0,
        near: 0.05,
        far: 5.0,
        ..Default::default()
    });
    s
}

/// The light's view of the water: depth from the light as grey levels (near bright), black where
/// there is none.
pub fn screen_picture(c: &Caustics) -> RgbImage {
    let depths: Vec<f32> = c.vertices.iter().map(|v| v.surface.w).collect();
    let (lo, hi) = depths
        .iter()
        .filter(|d| **d > 0.0)
        .fold((f32::MAX, f32::MIN), |(a, b), d| (a.min(*d), b.max(*d)));
    let span = (hi - lo).max(1e-6);
    RgbImage::from_fn(c.screen.width, c.screen.height, |x, y| {
        let d = depths[(y * c.screen.width + x) as usize];
        if d > 0.0 {
            let g = (255.0 * (1.0 - 0.8 * (d - lo) / span)) as u8;
            image::Rgb([g / 3, (u16::from(g) * 2 / 3) as u8, g])
        } else {
            image::Rgb([0, 0, 0])
        }
    })
}

/// Scales an image to `height` rows (nearest neighbour, aspect kept).
pub fn to_height(img: &RgbImage, height: u32) -> RgbImage {
    let w = (img.width() as f32 * height as f32 / img.height().max(1) as f32).round() as u32;
    image::imageops::resize(img, w.max(1), height, image::imageops::FilterType::Nearest)
}

/// The panel of all stages: light's view of the water | caustics map | finished frame (the
/// frame alone without the reference caustics).
pub fn stages_panel(f: &Finished, height: u32) -> RgbImage {
    let rgb = |i: &RgbaImage| -> RgbImage { image::buffer::ConvertBuffer::convert(i) };
    let mut panels = Vec::new();
    if let Some(c) = &f.caustics {
        panels.push(to_height(&screen_picture(c), height));
        panels.push(to_height(&rgb(&c.image(&f.stage)), height));
    }
    panels.push(to_height(&rgb(&f.image), height));
    fluid_surfels::preview::side_by_side(&panels)
}

/// Writes an RGBA image as an RGB PNG.
pub fn save(img: &RgbaImage, path: &Path) -> Result<(), Error> {
    fluid_surfels::preview::save_png(&image::buffer::ConvertBuffer::convert(img), path)?;
    Ok(())
}
