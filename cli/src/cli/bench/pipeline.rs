//! `bench pipeline`: the whole chain per stage.

use fluid_surfels::Error;
use fluid_surfels::pipeline::{
    Detail, DetailReport, FrameTimings, Pipeline, PipelineParams, Through,
};
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
    /// A particle file instead of the column scene: its shaded splats (the finished frame with
    /// --optics) from the automatic camera, with `--detail auto` against `fixed` in the same
    /// run (each stage's ms, refined points, surfels, grid cell; the pictures' PSNR and holes).
    #[arg(long)]
    pub input: Option<std::path::PathBuf>,
    /// With --input: the finished frame instead of the shaded splats.
    #[arg(long, requires = "input")]
    pub optics: bool,
    /// With --input: only this level of detail (default: both, fixed first).
    #[arg(long, requires = "input", value_parser = crate::cli::names_parser(&Detail::ALL, Detail::as_str))]
    pub detail: Option<Detail>,
    /// With --input: the footprint of `auto`, pixels (the `detail_px` key).
    #[arg(long, requires = "input")]
    pub detail_px: Option<f32>,
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
    if let Some(path) = &args.input {
        return bench_file(args, path);
    }
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
        println!("  {t}");
    }
    Ok(())
}

/// One level of detail on a file ([`bench_file`]).
#[derive(Serialize)]
struct DetailRun {
    detail: Detail,
    /// Median and fastest of the whole chain (detection to the picture), ms.
    median_ms: f64,
    fastest_ms: f64,
    /// The stages of the median frame.
    stages_ms: FrameTimings,
    /// What the level of detail made: steps run, refined points (per level), cell, surfels.
    made: DetailReport,
    /// Enclosed holes of the picture, as a fraction of the silhouette (`quality::holes`).
    enclosed_holes_fraction: f64,
}

#[derive(Serialize)]
struct FileBenchReport {
    input: String,
    particles: usize,
    size: [u32; 2],
    picture: &'static str,
    threads: usize,
    repeat: usize,
    runs: Vec<DetailRun>,
    /// With both: `fixed`'s median over `auto`'s, and the pictures' PSNR (dB).
    speedup: Option<f64>,
    psnr_db: Option<f64>,
}

/// `bench pipeline --input`: the chain on a file through the shaded splats (or the finished
/// frame) from the automatic camera (the first level's, kept for the others), per level of
/// detail, each from a fresh pipeline (one untimed frame fits the views and warms the thread
/// pool).
fn bench_file(args: &BenchPipelineArgs, path: &std::path::Path) -> Result<(), Error> {
    let set = crate::cli::read_particles(path, None)?;
    let through = if args.optics {
        Through::Frame
    } else {
        Through::Splats
    };
    let details = match args.detail {
        Some(d) => vec![d],
        None => vec![Detail::Fixed, Detail::Auto],
    };
    let mut runs = Vec::new();
    let mut images = Vec::new();
    // every level of detail from the first one's camera (fitted to its water)
    let mut camera = None;
    for detail in details {
        let mut params = PipelineParams {
            detail,
            ..PipelineParams::default()
        };
        if let Some(px) = args.detail_px {
            params.detail_px = px;
        }
        params.scene.optics.image_size = [args.size.0, args.size.1];
        let mut pipeline = Pipeline::new(params)?;
        if let Some(c) = camera {
            pipeline.set_camera(c);
        }
        let first = pipeline.frame_through(&set, through)?;
        camera = pipeline.camera();
        pipeline.recycle(first);
        let mut timed = Vec::new();
        for _ in 0..args.repeat.max(1) {
            let f = pipeline.frame_through(&set, through)?;
            let (image, covered): (image::RgbaImage, Vec<bool>) = match (&f.splats, &f.finished) {
                (Some(r), _) => (
                    r.image.clone(),
                    r.colour.iter().map(|c| c[3] > 0.0).collect(),
                ),
                (_, Some(fin)) => (
                    fin.image.clone(),
                    fin.linear.iter().map(|c| c[3] > 0.0).collect(),
                ),
                _ => unreachable!("through the picture"),
            };
            let holes = fluid_surfels::quality::holes(
                &covered,
                args.size.0 as usize,
                args.size.1 as usize,
                3,
            );
            timed.push((
                f.timings.total_ms,
                f.timings,
                f.detail.clone(),
                holes,
                image,
            ));
            pipeline.recycle(f);
        }
        timed.sort_by(|a, b| a.0.total_cmp(&b.0));
        let fastest_ms = timed[0].0;
        let (median_ms, stages_ms, made, holes, image) = timed.swap_remove(timed.len() / 2);
        runs.push(DetailRun {
            detail,
            median_ms,
            fastest_ms,
            stages_ms,
            made,
            enclosed_holes_fraction: holes.enclosed_fraction(),
        });
        images.push(image);
    }
    let both = runs.len() == 2;
    let report = FileBenchReport {
        input: path.display().to_string(),
        particles: set.len(),
        size: [args.size.0, args.size.1],
        picture: if args.optics { "frame" } else { "splats" },
        threads: rayon::current_num_threads(),
        repeat: args.repeat.max(1),
        speedup: both.then(|| runs[0].median_ms / runs[1].median_ms),
        psnr_db: both.then(|| fluid_surfels::splat::psnr(&images[0], &images[1])),
        runs,
    };
    if args.json {
        crate::cli::print_json(&report);
        return Ok(());
    }
    println!(
        "pipeline (CPU), {}: {} particles -> {}x{} {}, {} threads, median of {}",
        report.input,
        report.particles,
        args.size.0,
        args.size.1,
        report.picture,
        report.threads,
        report.repeat
    );
    for r in &report.runs {
        let (t, m) = (&r.stages_ms, &r.made);
        println!(
            "  {:<5} {:>8.1} ms (fastest {:.1}): {} steps, {} refined points {:?}, cell {:.5}, {} surfels ({} facing away left out), enclosed holes {:.3} %",
            r.detail.as_str(),
            r.median_ms,
            r.fastest_ms,
            m.steps,
            m.refined_points,
            m.points_per_level,
            m.cell,
            m.surfels,
            m.hidden_surfels,
            100.0 * r.enclosed_holes_fraction
        );
        println!("        {t}");
    }
    if let (Some(x), Some(db)) = (report.speedup, report.psnr_db) {
        println!("  auto {x:.2}x faster than fixed; pictures {db:.1} dB apart");
    }
    Ok(())
}
