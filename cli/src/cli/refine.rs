//! `fluid-surfels refine`: surface detection then upsampling (Solenthaler et al. 2007).

use std::path::{Path, PathBuf};
use std::time::Instant;

use fluid_surfels::io;
use fluid_surfels::neighbours;
use fluid_surfels::pipeline::{self, Pipeline, PipelineParams, Through};
use fluid_surfels::preview;
use fluid_surfels::refine::{self, HeightRule, RefineParams, Refined, StepStats};
use fluid_surfels::scenes::{self, ColumnParams, SceneName};
use fluid_surfels::sequence::FramePattern;
use fluid_surfels::surface::Surface;
use fluid_surfels::{Error, ParticleSet};
use glam::Vec3;
use serde::Serialize;

use super::{OutputKind, check_output, ms};

/// Arguments of `refine`.
#[derive(clap::Args)]
pub struct RefineArgs {
    #[command(flatten)]
    pub source: super::SourceArgs,
    #[command(flatten)]
    pub outputs: super::OutputArgs,
    /// The input already holds surface points with normals (the output of `detect`): refine it
    /// as it is instead of detecting its surface first.
    #[arg(long)]
    pub surface_input: bool,
    /// Refinement steps.
    #[arg(long, default_value_t = 3)]
    pub steps: u32,
    /// Child height rule: min (eq. 5, keeps edges) or average (eq. 4, smoother).
    #[arg(long, value_parser = super::names_parser(&HeightRule::ALL, HeightRule::as_str), default_value = "min")]
    pub height: HeightRule,
    /// Run the single-threaded reference implementation instead of the parallel one.
    #[arg(long)]
    pub reference: bool,
}

#[derive(Serialize)]
struct RefineReport {
    /// Particles dropped by `--bounds` (only with it).
    #[serde(skip_serializing_if = "Option::is_none")]
    outside_bounds: Option<usize>,
    source: String,
    frame: Option<usize>,
    radius: f32,
    implementation: &'static str,
    p0: usize,
    points: usize,
    steps: Vec<StepStats>,
    detect_ms: f64,
    refine_ms: f64,
    /// Peak resident set of the whole command (input, detection, refinement, output), MiB;
    /// absent where the system does not report it.
    #[serde(skip_serializing_if = "Option::is_none")]
    peak_rss_mib: Option<f64>,
    outputs: Vec<String>,
}

/// Surface points (with normals) of a particle set: detected, or taken as they are.
pub fn surface_points(
    particles: &ParticleSet,
    radius: f32,
    surface_input: bool,
) -> Result<(Vec<Vec3>, Vec<Vec3>), Error> {
    if surface_input {
        let normals = particles
            .normals
            .clone()
            .ok_or_else(|| Error::InvalidArgument {
                argument: "--surface-input",
                reason: "the input has no normals (nx ny nz or a normal array)".into(),
            })?;
        return Ok((particles.positions.clone(), normals));
    }
    let surface = detection_pipeline(radius)?
        .frame_through(particles, Through::Surface)?
        .surface;
    Ok(surface_of(particles, &surface))
}

/// A pipeline that detects the surface at the given support radius (the refinement runs as the
/// command line asks: steps, height rule, reference or parallel).
fn detection_pipeline(radius: f32) -> Result<Pipeline, Error> {
    Pipeline::new(PipelineParams {
        support_radius: Some(radius),
        ..PipelineParams::default()
    })
}

/// The surface and isolated particles with their normals (the pipeline's refinement input).
pub fn surface_of(particles: &ParticleSet, surface: &Surface) -> (Vec<Vec3>, Vec<Vec3>) {
    pipeline::gather(
        particles,
        surface,
        &pipeline::refined_indices(surface, &particles.positions),
    )
}

fn params(args: &RefineArgs, radius: f32) -> RefineParams {
    RefineParams {
        steps: args.steps,
        height: args.height,
        memory_budget: super::memory_budget(),
        ..RefineParams::with_radius(radius)
    }
}

fn run_refine(
    args: &RefineArgs,
    p: &[Vec3],
    n: &[Vec3],
    params: &RefineParams,
) -> Result<Refined, Error> {
    Ok(if args.reference {
        refine::refine_reference(p, n, params)?
    } else {
        refine::refine(p, n, params)?
    })
}

fn write(
    (out, out_format): (Option<&Path>, Option<io::Format>),
    png: Option<(&Path, fluid_surfels::view::UpAxis)>,
    input: &[Vec3],
    refined: &Refined,
) -> Result<Vec<String>, Error> {
    let mut outputs = Vec::new();
    if let Some(out) = out {
        io::write_particles(out, &refined.to_particle_set(), out_format)?;
        outputs.push(out.display().to_string());
    }
    if let Some((png, up)) = png {
        let mut turned = refined.clone();
        turned.positions = super::turned(&refined.positions, up);
        let picture = preview::refinement_picture(&super::turned(input, up), &turned, 700)?;
        preview::save_png(&picture, png)?;
        outputs.push(png.display().to_string());
    }
    Ok(outputs)
}

pub fn refine_command(args: &RefineArgs) -> Result<(), Error> {
    if let Some(pattern) = args.source.sequence()? {
        return refine_sequence(args, &pattern);
    }
    if args.source.frames.is_some() || args.outputs.jobs != 1 || args.outputs.skip_existing {
        return Err(Error::InvalidArgument {
            argument: "--frames",
            reason:
                "--frames, --jobs and --skip-existing need an --input pattern with {} (a sequence)"
                    .into(),
        });
    }
    let input = args.source.input.as_deref().map(PathBuf::from);
    let out = args.outputs.out.as_deref().map(PathBuf::from);
    let png = args.outputs.png.as_deref().map(PathBuf::from);
    for o in [&out, &png].into_iter().flatten() {
        check_output(o, input.as_deref(), args.outputs.force, OutputKind::Single)?;
    }
    let t = Instant::now();
    let (source, radius, points, normals) = match (&input, args.source.scene) {
        (Some(path), _) => {
            let particles = super::read_particles(path, args.source.format)?;
            let radius = match args.source.radius {
                Some(r) => r,
                None => neighbours::support_radius(&particles.positions)?,
            };
            let (p, n) = surface_points(&particles, radius, args.surface_input)?;
            (path.display().to_string(), radius, p, n)
        }
        (None, Some(SceneName::Column)) => {
            let frame = args.source.frame.unwrap_or(ColumnParams::SPLASH_FRAME);
            let params = fluid_surfels::pipeline::PipelineParams {
                support_radius: args.source.radius,
                ..Default::default()
            };
            let result = super::run::column_to_frame(
                frame,
                params,
                fluid_surfels::pipeline::Through::Surface,
            )?;
            let (p, n) = surface_of(result.sim.particles(), &result.frame.surface);
            ("scene column".into(), result.frame.radius, p, n)
        }
        (None, Some(name)) => {
            let scene = scenes::build(name, args.source.frame)?;
            let radius = args.source.radius.unwrap_or(scene.support_radius);
            let (p, n) = surface_points(&scene.particles, radius, false)?;
            (format!("scene {}", name.as_str()), radius, p, n)
        }
        (None, None) => unreachable!("clap requires --input or --scene"),
    };
    let detect_ms = ms(t);
    let t = Instant::now();
    let refined = run_refine(args, &points, &normals, &params(args, radius))?;
    let refine_ms = ms(t);
    let outputs = write(
        (out.as_deref(), args.outputs.out_format),
        png.as_deref().map(|p| (p, args.outputs.up)),
        &points,
        &refined,
    )?;
    let report = RefineReport {
        outside_bounds: super::outside_bounds(),
        source,
        frame: args.source.frame,
        radius,
        implementation: if args.reference {
            "reference"
        } else {
            "parallel"
        },
        p0: points.len(),
        points: refined.len(),
        steps: refined.stats.clone(),
        detect_ms,
        refine_ms,
        peak_rss_mib: fluid_surfels::peak_resident_mib(),
        outputs,
    };
    if args.outputs.json {
        super::print_json(&report);
        return Ok(());
    }
    println!(
        "{}: {} surface points -> {} refined points in {} steps ({:.1}x), r0 {}",
        report.source,
        report.p0,
        report.points,
        args.steps,
        report.points as f64 / report.p0.max(1) as f64,
        radius
    );
    println!("  step  radius     points  candidates  collisions (type 2 / 3)  moved      ms");
    for s in &report.steps {
        println!(
            "  {:>4}  {:<9.5} {:>7}  {:>10}  {:>10} / {:<10}  {:>6}  {:>6.1}",
            s.step,
            s.radius,
            s.points_after,
            s.candidates,
            s.collisions_type2,
            s.collisions_type3,
            s.moved,
            s.ms
        );
    }
    println!(
        "  ms: input and detection {:.1}, refinement {:.1} ({})",
        report.detect_ms, report.refine_ms, report.implementation
    );
    if let Some(mib) = report.peak_rss_mib {
        println!("  peak resident set {mib:.1} MiB (the whole command)");
    }
    for o in &report.outputs {
        println!("  wrote {o}");
    }
    Ok(())
}

#[derive(Serialize)]
struct FrameReport {
    frame: usize,
    p0: usize,
    points: usize,
    ms: f64,
}

fn refine_sequence(args: &RefineArgs, pattern: &FramePattern) -> Result<(), Error> {
    let super::PreparedSequence {
        sequence,
        out,
        png,
        radius,
    } = super::prepare_sequence(&args.source, &args.outputs, pattern, "refine")?;
    let run = sequence.run_warm(
        || detection_pipeline(radius),
        |pipeline, f| {
            if args.surface_input {
                // the file's own classes: no hysteresis to carry
                return Ok(());
            }
            let particles = super::read_particles(&pattern.path(f), args.source.format)?;
            pipeline.warm_up(&particles, Through::Surface)
        },
        |pipeline, f| {
            let t = Instant::now();
            let particles = super::read_particles(&pattern.path(f), args.source.format)?;
            let (p, n) = if args.surface_input {
                surface_points(&particles, radius, true)?
            } else {
                let surface = pipeline
                    .frame_through(&particles, Through::Surface)?
                    .surface;
                surface_of(&particles, &surface)
            };
            let refined = run_refine(args, &p, &n, &params(args, radius))?;
            write(
                (
                    out.as_ref().map(|x| x.path(f)).as_deref(),
                    args.outputs.out_format,
                ),
                png.as_ref()
                    .map(|x| x.path(f))
                    .as_deref()
                    .map(|x| (x, args.outputs.up)),
                &p,
                &refined,
            )?;
            Ok(FrameReport {
                frame: f,
                p0: p.len(),
                points: refined.len(),
                ms: ms(t),
            })
        },
    )?;
    if args.outputs.json {
        let v = serde_json::json!({
            "input": args.source.input,
            "radius": radius,
            "jobs": run.jobs,
            "processed": run.results.len(),
            "skipped": run.skipped,
            "seconds": run.seconds,
            "frames_per_second": run.results.len() as f64 / run.seconds.max(1e-9),
            "frames": run.results,
        });
        println!("{v}");
    } else {
        println!(
            "{}: {} frames refined, {} skipped, {:.2} s ({:.1} frames/s, {} jobs)",
            args.source.input.as_deref().unwrap_or(""),
            run.results.len(),
            run.skipped.len(),
            run.seconds,
            run.results.len() as f64 / run.seconds.max(1e-9),
            run.jobs
        );
    }
    Ok(())
}
