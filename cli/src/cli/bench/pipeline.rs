//! `bench pipeline`: the whole chain per stage.

use fluid_surfels::Error;
use fluid_surfels::surface::SurfaceParams;
use serde::Serialize;

/// Arguments of `bench pipeline`.
#[derive(clap::Args)]
pub struct BenchPipelineArgs {
    /// Frame of the column scene (default: the splash).
    #[arg(long, default_value_t = fluid_surfels::scenes::ColumnParams::SPLASH_FRAME)]
    pub frame: usize,
    /// Image size of the finished frame.
    #[arg(long, default_value = "512x512", value_parser = crate::cli::render::parse_size)]
    pub size: (u32, u32),
    /// Timed frames (the median is reported), after the frames of the simulation up to it.
    #[arg(long, default_value_t = 5)]
    pub repeat: usize,
    /// Print one JSON object instead of text.
    #[arg(long)]
    pub json: bool,
}

#[derive(Serialize)]
struct PipelineBenchReport {
    frame: usize,
    particles: usize,
    surfels: usize,
    size: [u32; 2],
    threads: usize,
    repeat: usize,
    /// Median and fastest of the whole chain (detection to the finished frame), ms.
    median_ms: f64,
    fastest_ms: f64,
    /// The stages of the median frame.
    stages_ms: fluid_surfels::pipeline::FrameTimings,
    goal_ms: f64,
}

/// The CPU `Pipeline` on one frame of the column scene: the whole chain with optics, repeated on
/// the same particles (the hysteresis is that of a sequence that stays on the frame).
pub fn bench_pipeline(args: &BenchPipelineArgs) -> Result<(), Error> {
    use fluid_surfels::pipeline::Through;
    let mut params = crate::cli::run::column_params(SurfaceParams::default());
    params.scene.optics.image_size = [args.size.0, args.size.1];
    let mut sim = fluid_surfels::scenes::ColumnSim::new(Default::default())?;
    let mut pipeline =
        fluid_surfels::pipeline::Pipeline::new(fluid_surfels::pipeline::PipelineParams {
            support_radius: Some(sim.support_radius()),
            ..params
        })?;
    // detection on every frame up to this one (the hysteresis of a real run), then one untimed
    // whole frame: the views are fitted, the thread pool is warm
    let first = fluid_surfels::pipeline::column_frame(
        &mut pipeline,
        &mut sim,
        args.frame,
        Through::Frame,
        |_| {},
    )?;
    pipeline.recycle(first);
    let particles = sim.particles().clone();
    let mut runs = Vec::new();
    for _ in 0..args.repeat.max(1) {
        let f = pipeline.frame(&particles)?;
        runs.push((f.timings.total_ms, f.timings, f.render_surfels.len()));
        pipeline.recycle(f);
    }
    runs.sort_by(|a, b| a.0.total_cmp(&b.0));
    let (median_ms, stages_ms, surfels) = runs[runs.len() / 2];
    let report = PipelineBenchReport {
        frame: args.frame,
        particles: particles.len(),
        surfels,
        size: [args.size.0, args.size.1],
        threads: rayon::current_num_threads(),
        repeat: runs.len(),
        median_ms,
        fastest_ms: runs[0].0,
        stages_ms,
        goal_ms: 100.0,
    };
    if args.json {
        crate::cli::print_json(&report);
    } else {
        let t = &report.stages_ms;
        println!(
            "pipeline (CPU), column frame {}: {} particles -> {} surfels -> {}x{} frame, {} threads",
            report.frame,
            report.particles,
            report.surfels,
            args.size.0,
            args.size.1,
            report.threads
        );
        println!(
            "  median {:.1} ms (fastest {:.1} of {}; goal {:.0} ms)",
            report.median_ms, report.fastest_ms, report.repeat, report.goal_ms
        );
        println!(
            "  neighbours {:.1}, detection {:.1}, refinement {:.1}, calibration {:.1}, density {:.1}, surfels {:.1}, caustics {:.1}, image {:.1}",
            t.neighbours_ms,
            t.detect_ms,
            t.refine_ms,
            t.calibration_ms,
            t.density_ms,
            t.surfels_ms,
            t.caustics_ms,
            t.image_ms
        );
    }
    Ok(())
}
