//! The main job: the built-in `column` scene through the pipeline.

use std::path::PathBuf;
use std::time::Instant;

use fluid_surfels::Error;
use fluid_surfels::io;
use fluid_surfels::neighbours::{Backend, Neighbourhoods};
use fluid_surfels::preview::{self, PreviewCamera};
use fluid_surfels::scenes::{ColumnParams, ColumnSim};
use fluid_surfels::surface::{Surface, SurfaceDetector, SurfaceParams};

use super::{class_colours, ms, progress, surface_particles};

/// Arguments of `fluid-surfels run` (and of the bare command).
#[derive(clap::Args)]
pub struct RunArgs {
    /// Output folder (created if missing; the job's own files in it are replaced).
    #[arg(long, default_value = "out")]
    pub out_dir: PathBuf,
    /// Frame of the column simulation to process.
    #[arg(long, default_value_t = ColumnParams::SPLASH_FRAME)]
    pub frame: usize,
}

/// What [`column_to_frame`] returns: the simulation at the frame, its surface, the time of its
/// neighbour search and its mean neighbour count.
pub struct ColumnFrame {
    pub sim: ColumnSim,
    pub surface: Surface,
    pub neighbours_ms: f64,
    pub mean_neighbours: f32,
    pub radius: f32,
}

/// Runs the column simulation to `frame`, detecting the surface on every frame so that the
/// hysteresis state is that of a real run.
pub fn column_to_frame(
    frame: usize,
    params: SurfaceParams,
    radius: Option<f32>,
) -> Result<ColumnFrame, Error> {
    let mut sim = ColumnSim::new(ColumnParams::default())?;
    let radius = radius.unwrap_or(sim.support_radius());
    let mut detector = SurfaceDetector::new(params)?;
    let bar = progress(frame as u64 + 1, "simulating column");
    loop {
        let t = Instant::now();
        let nb = Neighbourhoods::build(&sim.particles().positions, radius, Backend::CellGrid)?;
        let neighbours_ms = ms(t);
        let surface = detector.detect(sim.particles(), &nb)?;
        bar.inc(1);
        if sim.frame() >= frame {
            bar.finish_and_clear();
            return Ok(ColumnFrame {
                sim,
                surface,
                neighbours_ms,
                mean_neighbours: nb.mean_count(),
                radius,
            });
        }
        sim.step_frame();
    }
}

pub fn run(args: &RunArgs) -> Result<(), Error> {
    let total = Instant::now();
    std::fs::create_dir_all(&args.out_dir).map_err(|e| io::IoError::Os {
        path: args.out_dir.clone(),
        source: e,
    })?;
    let t = Instant::now();
    let ColumnFrame {
        sim,
        surface,
        neighbours_ms,
        ..
    } = column_to_frame(args.frame, SurfaceParams::default(), None)?;
    let sim_ms = ms(t);
    let particles = sim.particles();
    let counts = surface.counts();

    let t = Instant::now();
    let ply = args.out_dir.join("surface.ply");
    io::write_particles(&ply, &surface_particles(particles, &surface), None)?;
    let camera = PreviewCamera::framing(glam::Vec3::ZERO, sim.params().tank);
    let picture = preview::render_points(
        &particles.positions,
        &class_colours(&surface),
        sim.params().spacing * 0.5,
        &camera,
        800,
        800,
    )?;
    let png = args.out_dir.join("classes.png");
    preview::save_png(&picture, &png)?;
    let write_ms = ms(t);

    // stage 2: upsampling of the surface, 3 steps
    let (points, normals) =
        super::refine::surface_of(particles, &surface.classes, &surface.normals);
    let t = Instant::now();
    let refined = fluid_surfels::refine::refine(
        &points,
        &normals,
        &fluid_surfels::refine::RefineParams::with_radius(sim.support_radius()),
    )?;
    let refine_ms = ms(t);
    let refined_ply = args.out_dir.join("refined.ply");
    io::write_particles(&refined_ply, &refined.to_particle_set(), None)?;
    let refine_png = args.out_dir.join("refine.png");
    preview::save_png(
        &super::refine::refinement_picture(&points, &refined, 700)?,
        &refine_png,
    )?;

    println!(
        "fluid-surfels: scene `column` (collapsing water column, position based fluids), frame {}",
        sim.frame()
    );
    println!("  particles          {}", particles.len());
    println!(
        "  support radius     {} (2 x spacing)",
        sim.support_radius()
    );
    println!(
        "  surface            {} ({:.1} %), interior {}, isolated {}; {} flips since the previous frame",
        counts.surface,
        100.0 * counts.surface as f64 / particles.len() as f64,
        counts.interior,
        counts.isolated,
        surface.flips
    );
    println!(
        "  time               simulation+detection of {} frames {:.0} ms; last frame: neighbours {:.2} ms, classify {:.2} ms, normals {:.2} ms; writing {:.0} ms",
        sim.frame() + 1,
        sim_ms,
        neighbours_ms,
        surface.timings.classify_ms,
        surface.timings.normals_ms,
        write_ms
    );
    println!(
        "  wrote              {} (surface particles with normals)",
        ply.display()
    );
    println!(
        "  wrote              {} (orange surface, blue interior, green isolated)",
        png.display()
    );
    let counts: Vec<String> = refined
        .stats
        .iter()
        .map(|s| s.points_after.to_string())
        .collect();
    println!(
        "  refinement         {} surface points -> {} in 3 steps ({}), {:.1}x, {:.1} ms",
        points.len(),
        refined.len(),
        counts.join(" -> "),
        refined.len() as f64 / points.len().max(1) as f64,
        refine_ms
    );
    println!(
        "  wrote              {} (refined points: normal, step, weight, splat radius)",
        refined_ply.display()
    );
    println!(
        "  wrote              {} (input | refined: black P0, blue P1, red P2, yellow P3)",
        refine_png.display()
    );
    // stage 3: density grid and iso-surface surfels of all particles (CPU)
    let (surfels, spec, density_ms, extract_ms) = super::surfels::surfels_of(
        &particles.positions,
        sim.support_radius(),
        128,
        fluid_surfels::surfels::SurfelParams::default().iso_fraction,
    )?;
    let surfels_ply = args.out_dir.join("surfels.ply");
    io::write_particles(&surfels_ply, &surfels.to_particle_set(), None)?;
    let surfels_png = args.out_dir.join("surfels.png");
    preview::save_png(
        &super::surfels::surfels_picture(&surfels, &camera, 800)?,
        &surfels_png,
    )?;
    println!(
        "  density grid       {:?} points (spacing {:.4}), {:.1} ms; {} surfels extracted in {:.1} ms (CPU)",
        spec.dims,
        spec.spacing,
        density_ms,
        surfels.len(),
        extract_ms
    );
    println!(
        "  wrote              {} (surfels: normal, radius)",
        surfels_ply.display()
    );
    println!(
        "  wrote              {} (surfels coloured by normal)",
        surfels_png.display()
    );
    // stage 4: EWA splatting of the refined points and of the density surfels, beside plain
    // point sprites of the same surfels
    let ctx = super::render::choose_gpu(false, false)?;
    let water = fluid_surfels::splat::WATER;
    let refined_surfels = fluid_surfels::splat::surfels_from(
        &refined.positions,
        &refined.normals,
        &refined.radii,
        water,
    );
    let density_surfels = fluid_surfels::splat::surfels_from(
        &surfels.positions,
        &surfels.normals,
        &surfels.radii,
        water,
    );
    let splat_camera = super::render::framing(&density_surfels);
    let ewa = fluid_surfels::splat::SplatParams::default();
    let sprites = fluid_surfels::splat::SplatParams {
        mode: fluid_surfels::splat::SplatMode::Sprites,
        ..ewa
    };
    let t = Instant::now();
    let mut panels = Vec::new();
    for (s, p) in [
        (&refined_surfels, &ewa),
        (&density_surfels, &ewa),
        (&refined_surfels, &sprites),
        (&density_surfels, &sprites),
    ] {
        let r = super::render::render_with(ctx.as_ref(), s, &splat_camera, p, (480, 480))?;
        panels.push(image::buffer::ConvertBuffer::convert(&r.image));
    }
    let splat_ms = ms(t);
    let splats_png = args.out_dir.join("splats.png");
    preview::save_png(&preview::side_by_side(&panels), &splats_png)?;
    println!(
        "  splatting          4 images of 480x480 in {:.0} ms on the {}",
        splat_ms,
        match ctx.as_ref().and_then(|c| c.adapter.as_ref()) {
            Some(a) => format!("GPU ({})", a.name),
            None => "CPU reference (no GPU adapter found)".into(),
        }
    );
    println!(
        "  wrote              {} (EWA splats: refined points | density surfels; point sprites: refined | density)",
        splats_png.display()
    );
    // stage 5: the finished frame, refraction, reflection and caustics on the tank's floor
    let pool = super::optics::column_pool(sim.params().tank);
    let finished = super::optics::FrameRenderer::new(ctx)?.finish(&pool, &refined_surfels, true)?;
    let frame_png = args.out_dir.join("frame.png");
    super::optics::save(&finished.image, &frame_png)?;
    let caustics_png = args.out_dir.join("caustics.png");
    if let Some(c) = &finished.caustics {
        super::optics::save(&c.image(&finished.stage), &caustics_png)?;
    }
    let stages_png = args.out_dir.join("stages.png");
    preview::save_png(&super::optics::stages_panel(&finished, 512), &stages_png)?;
    let r = &finished.report;
    println!(
        "  optics             caustics {}x{} screen -> {}x{} map, {} triangles; frame {}x{} on the {}: caustics {:.0} ms + image {:.0} ms{}",
        r.screen[0],
        r.screen[1],
        r.map[0],
        r.map[1],
        r.caustics_triangles.unwrap_or(0),
        r.image[0],
        r.image[1],
        r.backend,
        r.caustics_ms,
        r.frame_ms,
        r.reference_caustics_ms
            .map(|t| format!(" (CPU reference caustics for the map picture: {t:.0} ms)"))
            .unwrap_or_default()
    );
    println!(
        "  wrote              {} (refined water with refraction, reflection and caustics)",
        frame_png.display()
    );
    println!(
        "  wrote              {} (light arriving on the pool, seen from the light)",
        caustics_png.display()
    );
    println!(
        "  wrote              {} (light's view of the water | caustics map | frame)",
        stages_png.display()
    );
    println!("  total              {:.0} ms", ms(total));
    Ok(())
}
