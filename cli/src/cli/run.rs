//! The main job: the built-in `column` scene through the pipeline.

use std::path::{Path, PathBuf};
use std::time::Instant;

use fluid_surfels::Error;
use fluid_surfels::io;
use fluid_surfels::pipeline::{self, Frame, Pipeline, PipelineParams, SurfelSource, Through};
use fluid_surfels::preview::{self, PreviewCamera};
use fluid_surfels::scenes::{ColumnParams, ColumnSim};
use fluid_surfels::splat::{self, Light, SplatMode, SplatParams};
use fluid_surfels::surface::SurfaceParams;

use super::{ms, progress, surface_particles};

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

/// What [`column_to_frame`] returns: the simulation at the frame, the pipeline's frame and the
/// pipeline that made it (for more pictures of the same frame).
pub struct ColumnFrame {
    pub sim: ColumnSim,
    pub frame: Frame,
    pub pipeline: Pipeline,
}

/// Runs the column simulation to `frame` through the pipeline (surface detection on every
/// frame, so that the hysteresis state is that of a real run; `through` on the last).
pub fn column_to_frame(
    frame: usize,
    params: PipelineParams,
    through: Through,
) -> Result<ColumnFrame, Error> {
    ColumnParams::check_frame(frame)?;
    let mut sim = ColumnSim::new(ColumnParams::default())?;
    let params = PipelineParams {
        support_radius: Some(params.support_radius.unwrap_or(sim.support_radius())),
        ..params
    };
    let mut pipeline = Pipeline::new(params)?;
    // the main job writes the surfels to a file: the whole surface, also what its pictures
    // cannot show
    pipeline.keep_hidden_surfels(true);
    let bar = progress(frame as u64 + 1, "simulating column");
    let f = pipeline::column_frame(&mut pipeline, &mut sim, frame, through, |_| bar.inc(1))?;
    bar.finish_and_clear();
    Ok(ColumnFrame {
        sim,
        frame: f,
        pipeline,
    })
}

/// The column scene's pipeline settings ([`pipeline::column_params`]) with `surface`.
pub fn column_params(surface: SurfaceParams) -> PipelineParams {
    PipelineParams {
        surface,
        ..pipeline::column_params()
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
        frame,
        mut pipeline,
    } = column_to_frame(
        args.frame,
        column_params(SurfaceParams::default()),
        Through::Frame,
    )?;
    let chain_ms = ms(t) - frame.timings.total_ms;
    let t = Instant::now();
    let (written, sources_ms) = write_stages(&args.out_dir, &sim, &mut pipeline, &frame)?;
    let write_ms = ms(t) - sources_ms;
    print_summary(&sim, &frame, [chain_ms, sources_ms, write_ms]);
    for (path, what) in &written {
        println!("  wrote              {} ({what})", path.display());
    }
    println!(
        "  surfel source      {} (others: {})",
        SurfelSource::Chain.as_str(),
        [SurfelSource::Particles, SurfelSource::Refined]
            .map(|s| s.as_str())
            .join(", ")
    );
    println!("  total              {:.0} ms", ms(total));
    Ok(())
}

/// The files the main job wrote, each with what it shows.
type Written = Vec<(PathBuf, &'static str)>;

/// Writes each stage's files and pictures into `dir`: what was written with what it shows, in
/// the order of the stages, and the ms the other sources' surfels of `splats.png` took.
fn write_stages(
    dir: &Path,
    sim: &ColumnSim,
    pipeline: &mut Pipeline,
    frame: &Frame,
) -> Result<(Written, f64), Error> {
    let out = |name: &str| dir.join(name);
    let mut written = Vec::new();
    let particles = sim.particles();
    let surface = &frame.surface;
    // stage 1: the surface particles and a picture of the classes
    let surface_ply = out("surface.ply");
    io::write_particles(&surface_ply, &surface_particles(particles, surface), None)?;
    written.push((surface_ply, "surface particles with normals"));
    let camera = PreviewCamera::framing(glam::Vec3::ZERO, sim.params().tank);
    let picture = preview::render_points(
        &particles.positions,
        &preview::class_colours(&surface.classes),
        sim.params().spacing * 0.5,
        &camera,
        800,
        800,
    )?;
    let classes_png = out("classes.png");
    preview::save_png(&picture, &classes_png)?;
    written.push((classes_png, "orange surface, blue interior, green isolated"));
    // stage 2: the refined surface
    let refined = frame.refined.as_ref().expect("the chain refines");
    let (points, _) = pipeline::gather(particles, surface, &frame.surface_indices);
    let refined_ply = out("refined.ply");
    io::write_particles(&refined_ply, &refined.to_particle_set(), None)?;
    written.push((
        refined_ply,
        "refined points: normal, step, weight, splat radius, kernel radius",
    ));
    let refine_png = out("refine.png");
    preview::save_png(
        &preview::refinement_picture(&points, refined, 700)?,
        &refine_png,
    )?;
    written.push((
        refine_png,
        "input | refined: black P0, blue P1, red P2, yellow P3",
    ));
    // stage 3: the chain's surfels
    let surfels = frame.surfels.as_ref().expect("the chain makes surfels");
    let surfels_ply = out("surfels.ply");
    io::write_particles(&surfels_ply, &surfels.to_particle_set(), None)?;
    written.push((surfels_ply, "the chain's surfels: normal, radius"));
    let surfels_png = out("surfels.png");
    preview::save_png(
        &preview::surfels_picture(surfels, Some(&camera), 800)?,
        &surfels_png,
    )?;
    written.push((surfels_png, "surfels coloured by normal"));
    // stage 4: the three surfel sources side by side as EWA splats, and the chain's as sprites
    let t_sources = Instant::now();
    let panels = source_panels(pipeline, particles, frame)?;
    let sources_ms = ms(t_sources);
    let splats_png = out("splats.png");
    preview::save_png(&preview::side_by_side(&panels), &splats_png)?;
    written.push((
        splats_png,
        "EWA splats of the surfel sources: chain | particles | refined points; point sprites of the chain",
    ));
    // stage 5: the finished frame
    let finished = frame.finished.as_ref().expect("through the frame");
    let frame_png = out("frame.png");
    preview::save_rgba_png(&finished.image, &frame_png)?;
    written.push((
        frame_png,
        "the chain's water with refraction, reflection and caustics",
    ));
    let caustics_png = out("caustics.png");
    preview::save_rgba_png(&finished.caustics.image(&finished.stage), &caustics_png)?;
    written.push((
        caustics_png,
        "light arriving on the pool, seen from the light",
    ));
    let stages_png = out("stages.png");
    preview::save_png(
        &preview::stages_panel(
            Some((&finished.caustics, &finished.stage)),
            &finished.image,
            512,
        ),
        &stages_png,
    )?;
    written.push((
        stages_png,
        "light's view of the water | caustics map | frame",
    ));
    Ok((written, sources_ms))
}

/// The panels of `splats.png`: each source's surfels as the pipeline draws them (`render
/// --source ...`) as EWA splats, then the chain's as point sprites.
fn source_panels(
    pipeline: &mut Pipeline,
    particles: &fluid_surfels::ParticleSet,
    frame: &Frame,
) -> Result<Vec<image::RgbImage>, Error> {
    let raw = pipeline.source_surfels(particles, frame, SurfelSource::Particles)?;
    let refined_surfels = pipeline.source_surfels(particles, frame, SurfelSource::Refined)?;
    let splat_camera = frame.camera.expect("rendered frames have a camera");
    let ewa = SplatParams::default();
    let sprites = SplatParams {
        mode: SplatMode::Sprites,
        ..ewa
    };
    let mut panels = Vec::new();
    for (s, params) in [
        (&frame.render_surfels, &ewa),
        (&raw, &ewa),
        (&refined_surfels, &ewa),
        (&frame.render_surfels, &sprites),
    ] {
        let r = splat::render_cpu(s, &splat_camera, &Light::default(), params, 480, 480)?;
        panels.push(image::buffer::ConvertBuffer::convert(&r.image));
    }
    Ok(panels)
}

/// The main job's report on stdout: the frame, each stage's counts and times; `ms` holds the
/// simulation before the frame, the other sources of `splats.png` and the writing.
fn print_summary(sim: &ColumnSim, frame: &Frame, [chain_ms, sources_ms, write_ms]: [f64; 3]) {
    let particles = sim.particles();
    let surface = &frame.surface;
    let counts = surface.counts();
    let tm = &frame.timings;
    let refined = frame.refined.as_ref().expect("the chain refines");
    let surfels = frame.surfels.as_ref().expect("the chain makes surfels");
    let finished = frame.finished.as_ref().expect("through the frame");
    println!(
        "fluid-surfels: scene `column` (collapsing water column, position based fluids), frame {}",
        sim.frame()
    );
    println!("  particles          {}", particles.len());
    println!("  support radius     {} (2 x spacing)", frame.radius);
    println!(
        "  surface            {} ({:.1} %), interior {}, isolated {}; {} flips since the previous frame",
        counts.surface,
        100.0 * counts.surface as f64 / particles.len() as f64,
        counts.interior,
        counts.isolated,
        surface.flips
    );
    let steps: Vec<String> = refined
        .stats
        .iter()
        .map(|s| s.points_after.to_string())
        .collect();
    println!(
        "  refinement         {} surface points -> {} in {} steps ({}), {:.1}x",
        frame.surface_indices.len(),
        refined.len(),
        refined.stats.len(),
        steps.join(" -> "),
        refined.len() as f64 / frame.surface_indices.len().max(1) as f64,
    );
    if let Some(spec) = frame.grid.as_ref().map(|g| *g.spec()) {
        println!(
            "  density grid       refined surface + {} interior particles, each with its own kernel radius: {:?} points (spacing {:.4}); {} surfels",
            counts.interior,
            spec.dims,
            spec.spacing,
            surfels.len()
        );
    }
    let r = &finished.stage.views;
    println!(
        "  optics             caustics {}x{} screen -> {}x{} map; frame {}x{} (CPU)",
        r.screen.width,
        r.screen.height,
        r.map.width,
        r.map.height,
        finished.image.width(),
        finished.image.height()
    );
    for w in &frame.warnings {
        println!("  warning            {w}");
    }
    println!(
        "  time (ms)          chain on the last frame {:.0}: {tm}",
        tm.total_ms
    );
    println!(
        "                     simulation and detection of the {} frames before {:.0}; other sources for splats.png {:.0}; writing {:.0}",
        sim.frame(),
        chain_ms,
        sources_ms,
        write_ms
    );
}
