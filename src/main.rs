//! The `fluid-surfels` command line: the main job on the built-in scene, stage subcommands for
//! users' own data, and benchmarks.

use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use clap::{Args, Parser, Subcommand};
use fluid_surfels::io::{self, Format};
use fluid_surfels::neighbours::{self, Backend, Neighbourhoods};
use fluid_surfels::preview::{self, PreviewCamera, palette};
use fluid_surfels::scenes::{self, ColumnParams, ColumnSim, SceneName};
use fluid_surfels::surface::{
    self, NormalMethod, ParticleClass, Surface, SurfaceDetector, SurfaceParams,
};
use fluid_surfels::{Error, ParticleSet};
use serde::Serialize;

#[derive(Parser)]
#[command(version, about = "Turns fluid simulation particles into a rendered water surface.", long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
}

#[derive(Subcommand)]
enum Command {
    /// The main job (also what runs with no arguments): the built-in `column` scene through the
    /// pipeline, pictures and files written to a folder.
    Run(RunArgs),
    /// Surface detection (Solenthaler et al. 2007, §3.1) on a file or a built-in scene.
    Detect(DetectArgs),
    /// Benchmarks.
    #[command(subcommand)]
    Bench(BenchCommand),
}

#[derive(Args)]
struct RunArgs {
    /// Output folder (created if missing; the job's own files in it are replaced).
    #[arg(long, default_value = "out")]
    out_dir: PathBuf,
    /// Frame of the column simulation to process.
    #[arg(long, default_value_t = ColumnParams::SPLASH_FRAME)]
    frame: usize,
}

#[derive(Args)]
#[command(group = clap::ArgGroup::new("source").required(true).args(["input", "scene"]))]
struct DetectArgs {
    /// Particle file (PLY, XYZ, CSV).
    #[arg(long)]
    input: Option<PathBuf>,
    /// Built-in scene.
    #[arg(long, value_enum)]
    scene: Option<SceneName>,
    /// Format of --input (default: from its extension).
    #[arg(long, value_enum)]
    format: Option<Format>,
    /// Support radius (default: the scene's, or twice the particle spacing estimated from the file).
    #[arg(long)]
    radius: Option<f32>,
    /// Frame of the `column` scene (hysteresis runs over all frames up to it).
    #[arg(long)]
    frame: Option<usize>,
    /// Normal estimation.
    #[arg(long, value_enum, default_value = "pca")]
    normals: NormalChoice,
    /// High threshold, as a fraction of the radius (default 0.14).
    #[arg(long)]
    high: Option<f32>,
    /// Low threshold, as a fraction of the radius (default 0.09).
    #[arg(long)]
    low: Option<f32>,
    /// Write the surface particles with their normals here (PLY, XYZ or CSV by extension).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Write a picture of all particles coloured by class here (PNG).
    #[arg(long)]
    png: Option<PathBuf>,
    /// Replace existing output files.
    #[arg(long)]
    force: bool,
    /// Print one JSON object of statistics on stdout instead of text.
    #[arg(long)]
    json: bool,
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum NormalChoice {
    /// Covariance (PCA) analysis of the neighbourhood.
    Pca,
    /// Gradient of the SPH colour field.
    ColourField,
}

#[derive(Subcommand)]
enum BenchCommand {
    /// Neighbour search and surface detection on a jittered block, against a single-threaded
    /// reference timed in the same run.
    Detect(BenchDetectArgs),
}

#[derive(Args)]
struct BenchDetectArgs {
    /// Number of particles.
    #[arg(long, default_value_t = 1_000_000)]
    particles: usize,
    /// Timed repetitions of the parallel path (the median is reported).
    #[arg(long, default_value_t = 3)]
    repeat: usize,
    /// Print one JSON object instead of text.
    #[arg(long)]
    json: bool,
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        None => run(&RunArgs {
            out_dir: PathBuf::from("out"),
            frame: ColumnParams::SPLASH_FRAME,
        }),
        Some(Command::Run(args)) => run(&args),
        Some(Command::Detect(args)) => detect(&args),
        Some(Command::Bench(BenchCommand::Detect(args))) => bench_detect(&args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            let mut source = std::error::Error::source(&e);
            while let Some(s) = source {
                eprintln!("  caused by: {s}");
                source = s.source();
            }
            ExitCode::FAILURE
        }
    }
}

fn ms(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}

fn class_colours(surface: &Surface) -> Vec<[u8; 3]> {
    surface
        .classes
        .iter()
        .map(|c| match c {
            ParticleClass::Interior => palette::INTERIOR,
            ParticleClass::Surface => palette::SURFACE,
            ParticleClass::Isolated => palette::ISOLATED,
        })
        .collect()
}

/// The surface particles with their normals (and every attribute they had).
fn surface_particles(particles: &ParticleSet, surface: &Surface) -> ParticleSet {
    let idx = surface.indices_of(ParticleClass::Surface);
    let mut out = particles.select(&idx);
    out.normals = Some(idx.iter().map(|&i| surface.normals[i]).collect());
    out
}

fn progress(len: u64, what: &str) -> indicatif::ProgressBar {
    if !std::io::stderr().is_terminal() {
        return indicatif::ProgressBar::hidden();
    }
    let bar = indicatif::ProgressBar::new(len);
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{msg} [{bar:30}] {pos}/{len} frames, {per_sec}, {eta} left",
        )
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    bar.set_message(what.to_owned());
    bar
}

/// What [`column_to_frame`] returns: the simulation at the frame, its surface, the time of its
/// neighbour search and its mean neighbour count.
struct ColumnFrame {
    sim: ColumnSim,
    surface: Surface,
    neighbours_ms: f64,
    mean_neighbours: f32,
    radius: f32,
}

/// Runs the column simulation to `frame`, detecting the surface on every frame so that the
/// hysteresis state is that of a real run.
fn column_to_frame(
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

fn run(args: &RunArgs) -> Result<(), Error> {
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
    println!("  total              {:.0} ms", ms(total));
    Ok(())
}

#[derive(Serialize)]
struct DetectReport {
    source: String,
    particles: usize,
    radius: f32,
    spacing_estimate: Option<f32>,
    frame: Option<usize>,
    normals: NormalMethod,
    high_threshold: f32,
    low_threshold: f32,
    counts: surface::ClassCounts,
    flips: usize,
    mean_neighbours: f32,
    timings_ms: DetectTimings,
    outputs: Vec<String>,
}

#[derive(Serialize, Default)]
struct DetectTimings {
    read: f64,
    neighbours: f64,
    classify: f64,
    normals: f64,
    write: f64,
}

/// Refuses to replace an existing file without --force, and never replaces the input.
fn check_output(out: &Path, input: Option<&Path>, force: bool) -> Result<(), Error> {
    let same = input.is_some_and(|i| {
        i == out || matches!((std::fs::canonicalize(i), std::fs::canonicalize(out)), (Ok(a), Ok(b)) if a == b)
    });
    if same || (out.exists() && !force) {
        let why = if same {
            "it is the input file"
        } else {
            "it exists; pass --force to replace it"
        };
        return Err(io::IoError::Os {
            path: out.to_owned(),
            source: std::io::Error::new(
                std::io::ErrorKind::AlreadyExists,
                format!("refusing to overwrite: {why}"),
            ),
        }
        .into());
    }
    Ok(())
}

fn detect(args: &DetectArgs) -> Result<(), Error> {
    let defaults = SurfaceParams::default();
    let high = args.high.unwrap_or(defaults.high_threshold);
    let params = SurfaceParams {
        high_threshold: high,
        low_threshold: args.low.unwrap_or(defaults.low_threshold.min(high)),
        normals: match args.normals {
            NormalChoice::Pca => NormalMethod::Covariance,
            NormalChoice::ColourField => NormalMethod::ColourField,
        },
    };
    params.validate()?;
    for out in [&args.out, &args.png].into_iter().flatten() {
        check_output(out, args.input.as_deref(), args.force)?;
    }
    let mut timings = DetectTimings::default();
    let t = Instant::now();
    let mut spacing_estimate = None;
    let (source, particles, radius, surface) = match (&args.input, args.scene) {
        (Some(path), _) => {
            if args.frame.is_some() {
                return Err(scenes::SceneError::InvalidParameter {
                    name: "frame",
                    reason: "--frame applies to the column scene; frame sequences of files are not supported yet".into(),
                }
                .into());
            }
            let particles = io::read_particles(path, args.format)?;
            timings.read = ms(t);
            let radius = match args.radius {
                Some(r) => r,
                None => {
                    let s = neighbours::estimate_spacing(&particles.positions)?;
                    spacing_estimate = Some(s);
                    2.0 * s
                }
            };
            let t = Instant::now();
            let nb = Neighbourhoods::build(&particles.positions, radius, Backend::CellGrid)?;
            timings.neighbours = ms(t);
            let surface = SurfaceDetector::new(params)?.detect(&particles, &nb)?;
            (
                path.display().to_string(),
                particles,
                radius,
                (surface, nb.mean_count()),
            )
        }
        (None, Some(SceneName::Column)) => {
            let frame = args.frame.unwrap_or(ColumnParams::SPLASH_FRAME);
            let result = column_to_frame(frame, params, args.radius)?;
            // "read" is the simulation of the frames before this one
            timings.read = ms(t)
                - result.neighbours_ms
                - result.surface.timings.classify_ms
                - result.surface.timings.normals_ms;
            timings.neighbours = result.neighbours_ms;
            let particles = result.sim.particles().clone();
            (
                "scene column".to_owned(),
                particles,
                result.radius,
                (result.surface, result.mean_neighbours),
            )
        }
        (None, Some(name)) => {
            let scene = scenes::build(name, args.frame)?;
            timings.read = ms(t);
            let radius = args.radius.unwrap_or(scene.support_radius);
            let t = Instant::now();
            let nb = Neighbourhoods::build(&scene.particles.positions, radius, Backend::CellGrid)?;
            timings.neighbours = ms(t);
            let surface = SurfaceDetector::new(params)?.detect(&scene.particles, &nb)?;
            (
                format!("scene {}", name.as_str()),
                scene.particles,
                radius,
                (surface, nb.mean_count()),
            )
        }
        (None, None) => unreachable!("clap requires --input or --scene"),
    };
    let (surface, mean_neighbours) = surface;
    timings.classify = surface.timings.classify_ms;
    timings.normals = surface.timings.normals_ms;

    let t = Instant::now();
    let mut outputs = Vec::new();
    if let Some(out) = &args.out {
        io::write_particles(out, &surface_particles(&particles, &surface), None)?;
        outputs.push(out.display().to_string());
    }
    if let Some(png) = &args.png {
        let (lo, hi) = particles
            .bounds()
            .unwrap_or((glam::Vec3::ZERO, glam::Vec3::ONE));
        let spacing = spacing_estimate.unwrap_or(radius * 0.5);
        let picture = preview::render_points(
            &particles.positions,
            &class_colours(&surface),
            spacing * 0.5,
            &PreviewCamera::framing(lo, hi),
            800,
            800,
        )?;
        preview::save_png(&picture, png)?;
        outputs.push(png.display().to_string());
    }
    timings.write = ms(t);

    let report = DetectReport {
        source,
        particles: particles.len(),
        radius,
        spacing_estimate,
        frame: args.frame,
        normals: params.normals,
        high_threshold: params.high_threshold,
        low_threshold: params.low_threshold,
        counts: surface.counts(),
        flips: surface.flips,
        mean_neighbours,
        timings_ms: timings,
        outputs,
    };
    if args.json {
        println!(
            "{}",
            serde_json::to_string(&report).expect("the report serialises")
        );
    } else {
        let c = report.counts;
        println!(
            "{}: {} particles, radius {}{}",
            report.source,
            report.particles,
            report.radius,
            report
                .spacing_estimate
                .map(|s| format!(" (2 x estimated spacing {s})"))
                .unwrap_or_default()
        );
        println!(
            "  surface {}, interior {}, isolated {} (mean {:.1} neighbours)",
            c.surface, c.interior, c.isolated, report.mean_neighbours
        );
        let t = &report.timings_ms;
        println!(
            "  ms: read {:.1}, neighbours {:.1}, classify {:.1}, normals {:.1}, write {:.1}",
            t.read, t.neighbours, t.classify, t.normals, t.write
        );
        for o in &report.outputs {
            println!("  wrote {o}");
        }
    }
    Ok(())
}

#[derive(Serialize)]
struct BenchDetectReport {
    particles: usize,
    threads: usize,
    radius: f32,
    mean_neighbours: f32,
    surface_particles: usize,
    neighbours_grid_ms: f64,
    neighbours_kdtree_ms: f64,
    detect_ms: f64,
    total_ms: f64,
    particles_per_second: f64,
    reference_neighbours_ms: f64,
    reference_detect_ms: f64,
    reference_total_ms: f64,
    reference_particles_per_second: f64,
    speedup: f64,
    classes_agree_with_reference: bool,
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn bench_detect(args: &BenchDetectArgs) -> Result<(), Error> {
    let scene = scenes::block(&scenes::BlockParams::with_particles(args.particles))?;
    let particles = &scene.particles;
    let r = scene.support_radius;
    let n = particles.len();
    let repeat = args.repeat.max(1);
    let params = SurfaceParams::default();
    if !args.json {
        println!(
            "bench detect: jittered block of {n} particles, radius {r} (2 x spacing), {} threads",
            rayon::current_num_threads()
        );
    }
    let mut grid_ms = Vec::new();
    let mut kd_ms = Vec::new();
    let mut det_ms = Vec::new();
    let mut last = None;
    for _ in 0..repeat {
        let t = Instant::now();
        let nb = Neighbourhoods::build(&particles.positions, r, Backend::CellGrid)?;
        grid_ms.push(ms(t));
        let t = Instant::now();
        let kd = Neighbourhoods::build(&particles.positions, r, Backend::KdTree)?;
        kd_ms.push(ms(t));
        drop(kd);
        let t = Instant::now();
        let surface = SurfaceDetector::new(params)?.detect(particles, &nb)?;
        det_ms.push(ms(t));
        last = Some((nb, surface));
    }
    let (nb, surface) = last.expect("at least one repetition");
    let (grid, kd, det) = (median(grid_ms), median(kd_ms), median(det_ms));
    let total = grid + det;

    let t = Instant::now();
    let lists = neighbours::reference_neighbours(&particles.positions, r);
    let ref_nb = ms(t);
    let t = Instant::now();
    let (ref_classes, _) = surface::detect_reference(particles, &lists, r, &params);
    let ref_det = ms(t);
    let ref_total = ref_nb + ref_det;
    let agree = ref_classes == surface.classes;

    let report = BenchDetectReport {
        particles: n,
        threads: rayon::current_num_threads(),
        radius: r,
        mean_neighbours: nb.mean_count(),
        surface_particles: surface.counts().surface,
        neighbours_grid_ms: grid,
        neighbours_kdtree_ms: kd,
        detect_ms: det,
        total_ms: total,
        particles_per_second: n as f64 / (total / 1e3),
        reference_neighbours_ms: ref_nb,
        reference_detect_ms: ref_det,
        reference_total_ms: ref_total,
        reference_particles_per_second: n as f64 / (ref_total / 1e3),
        speedup: ref_total / total,
        classes_agree_with_reference: agree,
    };
    if args.json {
        println!(
            "{}",
            serde_json::to_string(&report).expect("the report serialises")
        );
    } else {
        println!(
            "  mean neighbours {:.1}, surface particles {}",
            report.mean_neighbours, report.surface_particles
        );
        println!("  phase                          ms      particles/s");
        let row =
            |name: &str, v: f64| println!("  {name:<28} {v:>8.1}  {:>12.0}", n as f64 / (v / 1e3));
        row("neighbours (cell grid)", grid);
        row("neighbours (kiddo k-d tree)", kd);
        row("detection + normals", det);
        row("total (grid + detection)", total);
        row("reference neighbours", ref_nb);
        row("reference detection", ref_det);
        row("reference total", ref_total);
        println!(
            "  speedup over the single-threaded reference: {:.2}x (classes identical: {agree})",
            report.speedup
        );
        println!("  (parallel figures are the median of {repeat} runs; the reference runs once)");
    }
    Ok(())
}
