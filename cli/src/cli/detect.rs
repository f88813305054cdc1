//! `fluid-surfels detect`: surface detection on a file, a frame sequence or a built-in scene.

use std::path::{Path, PathBuf};
use std::time::Instant;

use fluid_surfels::io;
use fluid_surfels::pipeline::{self, Pipeline, PipelineParams, Through};
use fluid_surfels::preview::{self, PreviewCamera};
use fluid_surfels::scenes::{self, ColumnParams, SceneName};
use fluid_surfels::sequence::FramePattern;
use fluid_surfels::surface::{self, NormalMethod, Surface, SurfaceMethod, SurfaceParams};
use fluid_surfels::{Error, ParticleSet};
use serde::Serialize;

use super::{OutputKind, check_output, ms, surface_particles};

/// Arguments of `detect`.
#[derive(clap::Args)]
pub struct DetectArgs {
    #[command(flatten)]
    pub source: super::SourceArgs,
    #[command(flatten)]
    pub outputs: super::OutputArgs,
    /// Normal estimation: covariance (PCA of the neighbourhood, the paper's [Paj03]; `pca` is
    /// the same) or colour-field (the gradient of the SPH colour field).
    #[arg(long, value_parser = normals_parser(), default_value = "covariance")]
    pub normals: NormalMethod,
    /// High threshold, as a fraction of the radius (default 0.14).
    #[arg(long)]
    pub high: Option<f32>,
    /// Low threshold, as a fraction of the radius (default 0.09).
    #[arg(long)]
    pub low: Option<f32>,
    /// The detection: centre-of-mass (Solenthaler et al. 2007 §3.1, thresholds and hysteresis,
    /// the chain's) or lnm (the narrow band of the Layered Neighborhood Method, Oliveira and
    /// Paiva Algorithm 1: voxel layers, no neighbour search, normals from the voxels; its
    /// agreement with the centre-of-mass classes is reported).
    #[arg(long, value_parser = super::names_parser(&SurfaceMethod::ALL, SurfaceMethod::as_str), default_value = "centre-of-mass")]
    pub method: SurfaceMethod,
}

/// `--normals`: the library's names, and `pca` (the name this option had first) for covariance.
fn normals_parser() -> impl clap::builder::TypedValueParser<Value = NormalMethod> {
    use clap::builder::{PossibleValue, TypedValueParser};
    let values = NormalMethod::ALL.map(|m| match m {
        NormalMethod::Covariance => PossibleValue::new(m.as_str()).alias("pca"),
        _ => PossibleValue::new(m.as_str()),
    });
    clap::builder::PossibleValuesParser::new(values).map(|s| {
        NormalMethod::ALL
            .into_iter()
            .find(|m| m.as_str() == s || (s == "pca" && *m == NormalMethod::Covariance))
            .expect("one of the possible values")
    })
}

/// What `--method lnm` adds to the report.
#[derive(Serialize)]
struct LnmReport {
    /// The narrow band against the centre-of-mass classes of the same frame.
    agreement: fluid_surfels::lnm::Agreement,
    voxels: usize,
    /// The band (Algorithm 1).
    band_ms: f64,
    /// Its normals from the voxels (`NarrowBand::ring_normals`).
    normals_ms: f64,
    /// The centre-of-mass detection with its neighbour search, in the same run.
    centre_of_mass_ms: f64,
}

/// The narrow band of `particles` as a [`Surface`]: band particles are surface (isolated where
/// the centre-of-mass detection found no neighbour), the rest interior; normals from the
/// voxels. With its agreement with `com` (which took `com_ms`) and its time.
fn lnm_surface(
    particles: &ParticleSet,
    radius: f32,
    com: &Surface,
    com_ms: f64,
) -> Result<(Surface, LnmReport), Error> {
    use fluid_surfels::lnm::{LnmParams, agreement, band_surface, narrow_band};
    let t = Instant::now();
    let band = narrow_band(&particles.positions, radius, &LnmParams::default())?;
    let band_ms = ms(t);
    let t = Instant::now();
    let surface = band_surface(&band, &particles.positions, com);
    let normals_ms = ms(t);
    let report = LnmReport {
        agreement: agreement(&band, &com.classes),
        voxels: band.voxels.len(),
        band_ms,
        normals_ms,
        centre_of_mass_ms: com_ms,
    };
    Ok((surface, report))
}

#[derive(Serialize)]
struct DetectReport {
    /// Particles dropped by `--bounds` (only with it).
    #[serde(skip_serializing_if = "Option::is_none")]
    outside_bounds: Option<usize>,
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
    /// Warnings about the support radius (neighbour counts far outside the usual range).
    warnings: Vec<String>,
    /// `--method lnm`: the band's agreement with the centre-of-mass classes and its time.
    #[serde(skip_serializing_if = "Option::is_none")]
    lnm: Option<LnmReport>,
    timings_ms: DetectTimings,
    outputs: Vec<String>,
}

#[derive(Serialize, Default, Clone, Copy)]
struct DetectTimings {
    read: f64,
    neighbours: f64,
    classify: f64,
    normals: f64,
    write: f64,
}

fn params(args: &DetectArgs) -> Result<SurfaceParams, Error> {
    let defaults = SurfaceParams::default();
    let high = args.high.unwrap_or(defaults.high_threshold);
    let params = SurfaceParams {
        high_threshold: high,
        low_threshold: args.low.unwrap_or(defaults.low_threshold.min(high)),
        normals: args.normals,
        // the centre-of-mass classes always: `--method lnm` reports the band's agreement with
        // them and then takes the band (`lnm_surface`)
        method: SurfaceMethod::CentreOfMass,
    };
    params.validate()?;
    Ok(params)
}

/// The pipeline's settings for detection only.
fn surface_params(surface: SurfaceParams, radius: Option<f32>) -> PipelineParams {
    PipelineParams {
        surface,
        support_radius: radius,
        ..PipelineParams::default()
    }
}

/// One frame through the pipeline's detection (the support radius given, or estimated).
fn surface_frame(
    particles: &ParticleSet,
    params: SurfaceParams,
    radius: Option<f32>,
) -> Result<pipeline::Frame, Error> {
    Pipeline::new(surface_params(params, radius))?.frame_through(particles, Through::Surface)
}

fn invalid(argument: &'static str, reason: impl Into<String>) -> Error {
    Error::InvalidArgument {
        argument,
        reason: reason.into(),
    }
}

pub fn detect(args: &DetectArgs) -> Result<(), Error> {
    let params = params(args)?;
    if let Some(pattern) = args.source.sequence()? {
        return detect_sequence(args, &pattern, params);
    }
    if args.source.frames.is_some() || args.outputs.jobs != 1 || args.outputs.skip_existing {
        return Err(invalid(
            "--frames",
            "--frames, --jobs and --skip-existing need an --input pattern with {} (a sequence)",
        ));
    }
    let input = args.source.input.as_deref().map(PathBuf::from);
    let out = args.outputs.out.as_deref().map(PathBuf::from);
    let png = args.outputs.png.as_deref().map(PathBuf::from);
    for o in [&out, &png].into_iter().flatten() {
        check_output(o, input.as_deref(), args.outputs.force, OutputKind::Single)?;
    }
    let mut timings = DetectTimings::default();
    let t = Instant::now();
    let mut spacing_estimate = None;
    let (source, particles, radius, surface, mean_neighbours) = match (&input, args.source.scene) {
        (Some(path), _) => {
            if args.source.frame.is_some() {
                return Err(invalid(
                    "--frame",
                    "--frame applies to the column scene; use --frames with an --input pattern for sequences",
                ));
            }
            let particles = super::read_particles(path, args.source.format)?;
            timings.read = ms(t);
            let f = surface_frame(&particles, params, args.source.radius)?;
            if args.source.radius.is_none() {
                spacing_estimate = Some(0.5 * f.radius);
            }
            timings.neighbours = f.timings.neighbours_ms;
            (
                path.display().to_string(),
                particles,
                f.radius,
                f.surface,
                f.mean_neighbours,
            )
        }
        (None, Some(SceneName::Column)) => {
            let frame = args.source.frame.unwrap_or(ColumnParams::SPLASH_FRAME);
            let pipeline = fluid_surfels::pipeline::PipelineParams {
                surface: params,
                support_radius: args.source.radius,
                ..Default::default()
            };
            let result = super::run::column_to_frame(
                frame,
                pipeline,
                fluid_surfels::pipeline::Through::Surface,
            )?;
            let f = result.frame;
            // "read" is the simulation of the frames up to this one
            timings.read = ms(t)
                - f.timings.neighbours_ms
                - f.surface.timings.classify_ms
                - f.surface.timings.normals_ms;
            timings.neighbours = f.timings.neighbours_ms;
            let particles = result.sim.particles().clone();
            (
                "scene column".to_owned(),
                particles,
                f.radius,
                f.surface,
                f.mean_neighbours,
            )
        }
        (None, Some(name)) => {
            let scene = scenes::build(name, args.source.frame)?;
            timings.read = ms(t);
            let radius = args.source.radius.unwrap_or(scene.support_radius);
            let f = surface_frame(&scene.particles, params, Some(radius))?;
            timings.neighbours = f.timings.neighbours_ms;
            let (surface, mean) = (f.surface, f.mean_neighbours);
            (
                format!("scene {}", name.as_str()),
                scene.particles,
                radius,
                surface,
                mean,
            )
        }
        (None, None) => unreachable!("clap requires --input or --scene"),
    };
    timings.classify = surface.timings.classify_ms;
    timings.normals = surface.timings.normals_ms;
    let (surface, lnm) = if args.method == SurfaceMethod::Lnm {
        let com_ms = timings.neighbours + timings.classify + timings.normals;
        let (s, r) = lnm_surface(&particles, radius, &surface, com_ms)?;
        (s, Some(r))
    } else {
        (surface, None)
    };
    let t = Instant::now();
    let outputs = write_outputs(
        &particles,
        &surface,
        radius,
        spacing_estimate,
        out.as_deref(),
        args.outputs.out_format,
        png.as_deref().map(|p| (p, args.outputs.up)),
    )?;
    timings.write = ms(t);

    let report = DetectReport {
        outside_bounds: super::outside_bounds(),
        source,
        particles: particles.len(),
        radius,
        spacing_estimate,
        frame: args.source.frame,
        normals: params.normals,
        high_threshold: params.high_threshold,
        low_threshold: params.low_threshold,
        counts: surface.counts(),
        flips: surface.flips,
        mean_neighbours,
        warnings: fluid_surfels::pipeline::neighbour_count_warning(radius, mean_neighbours)
            .into_iter()
            .collect(),
        lnm,
        timings_ms: timings,
        outputs,
    };
    if args.outputs.json {
        super::print_json(&report);
    } else {
        print_report(&report);
    }
    Ok(())
}

/// The report of one frame as text.
fn print_report(report: &DetectReport) {
    let c = report.counts;
    let estimate = report
        .spacing_estimate
        .map(|s| format!(" (2 x estimated spacing {s})"))
        .unwrap_or_default();
    println!(
        "{}: {} particles, radius {}{estimate}",
        report.source, report.particles, report.radius
    );
    println!(
        "  surface {}, interior {}, isolated {} (mean {:.1} neighbours)",
        c.surface, c.interior, c.isolated, report.mean_neighbours
    );
    if let Some(l) = &report.lnm {
        let a = &l.agreement;
        println!(
            "  lnm narrow band: {} particles in {} voxels, {:.1} ms, normals {:.1} ms (centre of mass with its neighbour search {:.1} ms); \
             holds {:.2} % of the {} centre-of-mass surface particles, {} more, same side for {:.1} % of all",
            a.band,
            l.voxels,
            l.band_ms,
            l.normals_ms,
            l.centre_of_mass_ms,
            100.0 * a.recall,
            a.detected,
            a.band_only,
            100.0 * a.agreement
        );
    }
    for w in &report.warnings {
        println!("  warning: {w}");
    }
    let t = &report.timings_ms;
    println!(
        "  ms: read {:.1}, neighbours {:.1}, classify {:.1}, normals {:.1}, write {:.1}",
        t.read, t.neighbours, t.classify, t.normals, t.write
    );
    for o in &report.outputs {
        println!("  wrote {o}");
    }
}

/// Writes the surface particles and the picture, each when asked for.
pub fn write_outputs(
    particles: &ParticleSet,
    surface: &Surface,
    radius: f32,
    spacing: Option<f32>,
    out: Option<&Path>,
    out_format: Option<io::Format>,
    png: Option<(&Path, fluid_surfels::view::UpAxis)>,
) -> Result<Vec<String>, Error> {
    let mut outputs = Vec::new();
    if let Some(out) = out {
        io::write_particles(out, &surface_particles(particles, surface), out_format)?;
        outputs.push(out.display().to_string());
    }
    if let Some((png, up)) = png {
        let positions = super::turned(&particles.positions, up);
        let (lo, hi) = preview::bounds_or_unit(&positions);
        let spacing = spacing.unwrap_or(radius * 0.5);
        let picture = preview::render_points(
            &positions,
            &fluid_surfels::preview::class_colours(&surface.classes),
            spacing * 0.5,
            &PreviewCamera::framing(lo, hi),
            800,
            800,
        )?;
        preview::save_png(&picture, png)?;
        outputs.push(png.display().to_string());
    }
    Ok(outputs)
}

#[derive(Serialize)]
struct FrameReport {
    frame: usize,
    particles: usize,
    counts: surface::ClassCounts,
    flips: usize,
    /// `--method lnm`: the band's agreement with the centre-of-mass classes.
    #[serde(skip_serializing_if = "Option::is_none")]
    lnm: Option<fluid_surfels::lnm::Agreement>,
    ms: f64,
}

#[derive(Serialize)]
struct SequenceReport {
    input: String,
    radius: f32,
    jobs: usize,
    processed: usize,
    skipped: Vec<usize>,
    seconds: f64,
    frames_per_second: f64,
    frames: Vec<FrameReport>,
}

fn detect_sequence(
    args: &DetectArgs,
    pattern: &FramePattern,
    params: SurfaceParams,
) -> Result<(), Error> {
    let super::PreparedSequence {
        sequence,
        out,
        png,
        radius,
    } = super::prepare_sequence(&args.source, &args.outputs, pattern, "detect")?;
    let run = sequence.run_warm(
        || Pipeline::new(surface_params(params, Some(radius))),
        |pipeline, f| {
            let particles = super::read_particles(&pattern.path(f), args.source.format)?;
            pipeline.warm_up(&particles, Through::Surface)
        },
        |pipeline, f| {
            let t = Instant::now();
            let particles = super::read_particles(&pattern.path(f), args.source.format)?;
            let surface = pipeline
                .frame_through(&particles, Through::Surface)?
                .surface;
            let (surface, lnm) = if args.method == SurfaceMethod::Lnm {
                let (s, r) = lnm_surface(&particles, radius, &surface, 0.0)?;
                (s, Some(r.agreement))
            } else {
                (surface, None)
            };
            write_outputs(
                &particles,
                &surface,
                radius,
                None,
                out.as_ref().map(|p| p.path(f)).as_deref(),
                args.outputs.out_format,
                png.as_ref()
                    .map(|p| p.path(f))
                    .as_deref()
                    .map(|p| (p, args.outputs.up)),
            )?;
            Ok(FrameReport {
                frame: f,
                particles: particles.len(),
                counts: surface.counts(),
                flips: surface.flips,
                lnm,
                ms: ms(t),
            })
        },
    )?;
    let report = SequenceReport {
        input: args.source.input.clone().unwrap_or_default(),
        radius,
        jobs: run.jobs,
        processed: run.results.len(),
        skipped: run.skipped,
        seconds: run.seconds,
        frames_per_second: run.results.len() as f64 / run.seconds.max(1e-9),
        frames: run.results,
    };
    if args.outputs.json {
        super::print_json(&report);
    } else {
        println!(
            "{}: {} frames processed, {} skipped (outputs existed), radius {}",
            report.input,
            report.processed,
            report.skipped.len(),
            report.radius
        );
        println!(
            "  {:.2} s, {:.1} frames/s with {} jobs",
            report.seconds, report.frames_per_second, report.jobs
        );
        if let (Some(first), Some(last)) = (report.frames.first(), report.frames.last()) {
            println!(
                "  frame {}: {} surface of {}; frame {}: {} surface of {}",
                first.frame,
                first.counts.surface,
                first.particles,
                last.frame,
                last.counts.surface,
                last.particles
            );
        }
    }
    Ok(())
}
