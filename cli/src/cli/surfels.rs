//! `fluid-surfels surfels`: density grid and iso-surface surfels (Iwasaki et al., §4).

use std::path::{Path, PathBuf};

use fluid_surfels::Error;
use fluid_surfels::density::{GridSpec, Points, Resolution};
use fluid_surfels::io;
use fluid_surfels::pipeline::{
    self, Calibration, GridParams, Pipeline, PipelineParams, SurfelSource, Through,
};
use fluid_surfels::preview;
use fluid_surfels::sequence::FramePattern;
use fluid_surfels::surfels::{SurfelParams, Surfels};
use glam::Vec3;
use serde::Serialize;

use super::{OutputKind, check_output};

/// Arguments of `surfels`.
#[derive(clap::Args)]
pub struct SurfelsArgs {
    #[command(flatten)]
    pub source: super::SourceArgs,
    #[command(flatten)]
    pub outputs: super::OutputArgs,
    /// Grid points along the longest axis of the particles' padded box (default 128; with
    /// --source, the pipeline's cell: a third of the smallest kernel radius).
    #[arg(long)]
    pub resolution: Option<u32>,
    /// The surfels of the library's pipeline (CPU) from this source instead of the raw
    /// particles' density grid with eq. 1's sums: `chain` (detection, upsampling, the density
    /// grid of the refined surface and the interior) or `particles` (the particles' own density
    /// grid), each with the surface at the fluid's boundary unless --calibration paper.
    #[arg(long = "source", value_parser = super::names_parser(&[SurfelSource::Chain, SurfelSource::Particles], SurfelSource::as_str), conflicts_with_all = ["gpu", "h"])]
    pub surfel_source: Option<SurfelSource>,
    /// Refinement steps of the chain (the `refine.steps` key; default 3, the paper's); implies
    /// --source chain.
    #[arg(long, conflicts_with_all = ["gpu", "h"])]
    pub steps: Option<u32>,
    /// Where the pipeline's surface lies: boundary (half a spacing outside the outermost
    /// particles at every level; the default), paper (eq. 1's sums) or volume (the raw
    /// particles weighted by their SPH volumes: splashsurf's field); the `grid.calibration`
    /// key; implies --source chain (volume: --source particles).
    #[arg(long, value_parser = super::names_parser(&Calibration::ALL, Calibration::as_str), conflicts_with_all = ["gpu", "h"])]
    pub calibration: Option<Calibration>,
    /// Iso-value as a fraction of one particle's peak density (default 0.75).
    #[arg(long)]
    pub iso: Option<f32>,
    /// Effective radius h of the density kernel (default: the support radius).
    #[arg(long)]
    pub h: Option<f32>,
    /// Fill the density grid on the GPU (headless adapter; surfels are extracted on the CPU).
    #[arg(long, conflicts_with = "cpu")]
    pub gpu: bool,
    /// Use the CPU path (the default).
    #[arg(long)]
    pub cpu: bool,
}

#[derive(Serialize)]
struct SurfelsReport {
    /// Particles dropped by `--bounds` (only with it).
    #[serde(skip_serializing_if = "Option::is_none")]
    outside_bounds: Option<usize>,
    source: String,
    particles: usize,
    h: f32,
    grid: [u32; 3],
    spacing: f32,
    iso: f32,
    surfels: usize,
    path: &'static str,
    density_ms: f64,
    extract_ms: f64,
    /// With --source: the source, the refinement steps and the calibration.
    #[serde(skip_serializing_if = "Option::is_none")]
    pipeline: Option<PipelineReport>,
    outputs: Vec<String>,
}

#[derive(Serialize)]
struct PipelineReport {
    source: &'static str,
    steps: u32,
    calibration: &'static str,
    refined_points: usize,
}

impl SurfelsArgs {
    /// The source to run the pipeline from (`--steps` or `--calibration` alone: the chain;
    /// `--calibration volume`: the raw particles), if any.
    fn pipeline_source(&self) -> Option<SurfelSource> {
        self.surfel_source.or_else(|| {
            if self.calibration == Some(Calibration::Volume) {
                return Some(SurfelSource::Particles);
            }
            (self.steps.is_some() || self.calibration.is_some()).then_some(SurfelSource::Chain)
        })
    }

    /// The pipeline's parameters for these arguments and the support radius `radius`.
    fn pipeline_params(&self, source: SurfelSource, radius: f32, iso: f32) -> PipelineParams {
        let mut p = PipelineParams {
            support_radius: Some(radius),
            source,
            ..PipelineParams::default()
        };
        if let Some(k) = self.steps {
            p.refine.steps = k;
        }
        if let Some(c) = self.calibration {
            p.grid.calibration = c;
        }
        if let Some(r) = self.resolution {
            p.grid.resolution = Some(Resolution::LongestAxis(r));
        }
        p.grid.memory_budget = super::memory_budget();
        p.surfels.iso_fraction = iso;
        p
    }
}

/// The surfels of `pipeline` for one frame's particles (their ids carry the detection's
/// hysteresis over a sequence), with the grid, the ms of the density grid and of the
/// extraction, and what the report says of the pipeline.
fn pipeline_surfels(
    pipeline: &mut Pipeline,
    particles: fluid_surfels::ParticleView<'_>,
) -> Result<(Surfels, GridSpec, f64, f64, PipelineReport), Error> {
    let frame = pipeline.frame_through(particles, Through::Surfels)?;
    for w in &frame.warnings {
        eprintln!("warning: {w}");
    }
    let spec = *frame
        .grid
        .as_ref()
        .ok_or(fluid_surfels::density::DensityError::Empty)?
        .spec();
    let p = pipeline.params();
    let report = PipelineReport {
        source: p.source.as_str(),
        steps: if p.source == SurfelSource::Chain {
            p.refine.steps
        } else {
            0
        },
        calibration: p.grid.calibration.as_str(),
        refined_points: frame.refined.as_ref().map_or(0, |r| r.len()),
    };
    let t = frame.timings;
    Ok((
        frame.surfels.unwrap_or_default(),
        spec,
        t.calibration_ms + t.density_ms,
        t.surfels_ms,
        report,
    ))
}

/// Grid points along the longest axis of the raw density grid without `--resolution`.
const DEFAULT_RESOLUTION: u32 = 128;

/// Surfels of a particle set, with the grid used and the time of each phase.
pub fn surfels_of(
    positions: &[Vec3],
    h: f32,
    resolution: u32,
    iso_fraction: f32,
) -> Result<(Surfels, GridSpec, f64, f64), Error> {
    surfels_with(None, positions, h, resolution, iso_fraction)
}

/// [`surfels_of`] with the density grid filled on the GPU when a context is given.
pub fn surfels_with(
    gpu: Option<&fluid_surfels::gpu::GpuContext>,
    positions: &[Vec3],
    h: f32,
    resolution: u32,
    iso_fraction: f32,
) -> Result<(Surfels, GridSpec, f64, f64), Error> {
    let grid = GridParams {
        resolution: Some(Resolution::LongestAxis(resolution)),
        memory_budget: super::memory_budget(),
        ..GridParams::default()
    };
    let params = SurfelParams {
        iso_fraction,
        ..SurfelParams::default()
    };
    let points = Points::uniform(positions, h);
    let iso = match gpu {
        None => pipeline::iso_surfels(points, &grid, &params)?,
        Some(ctx) => pipeline::iso_surfels_gpu(ctx, points, &grid, &params)?,
    }
    .ok_or(fluid_surfels::density::DensityError::Empty)?;
    if let Some(w) = &iso.warning {
        eprintln!("warning: {w}");
    }
    Ok((
        iso.surfels,
        *iso.grid.spec(),
        iso.density_ms,
        iso.surfels_ms,
    ))
}

fn write(
    s: &Surfels,
    (out, out_format): (Option<&Path>, Option<io::Format>),
    png: Option<(&Path, fluid_surfels::view::UpAxis)>,
) -> Result<Vec<String>, Error> {
    let mut outputs = Vec::new();
    if let Some(out) = out {
        io::write_particles(out, &s.to_particle_set(), out_format)?;
        outputs.push(out.display().to_string());
    }
    if let Some((png, up)) = png {
        let mut turned = s.clone();
        turned.positions = super::turned(&s.positions, up);
        turned.normals = super::turned(&s.normals, up);
        preview::save_png(&preview::surfels_picture(&turned, None, 800)?, png)?;
        outputs.push(png.display().to_string());
    }
    Ok(outputs)
}

pub fn surfels_command(args: &SurfelsArgs) -> Result<(), Error> {
    let iso = args.iso.unwrap_or(SurfelParams::default().iso_fraction);
    let src = &args.source;
    let out_args = &args.outputs;
    if let Some(pattern) = src.sequence()? {
        return surfels_sequence(args, &pattern, iso);
    }
    let input = src.input.as_deref().map(PathBuf::from);
    let out = out_args.out.as_deref().map(PathBuf::from);
    let png = out_args.png.as_deref().map(PathBuf::from);
    for o in [&out, &png].into_iter().flatten() {
        check_output(o, input.as_deref(), out_args.force, OutputKind::Single)?;
    }
    let (source, positions, radius) = super::positions_of(
        input.as_deref(),
        src.scene,
        src.format,
        src.frame,
        src.radius,
    )?;
    let h = args.h.unwrap_or(radius);
    let gpu = if args.gpu {
        Some(fluid_surfels::gpu::GpuContext::headless()?)
    } else {
        None
    };
    let (s, spec, density_ms, extract_ms, pipeline) = match args.pipeline_source() {
        Some(source) => {
            let mut p = Pipeline::new(args.pipeline_params(source, radius, iso))?;
            let view = fluid_surfels::ParticleView::of_positions(&positions);
            let (s, spec, d, e, r) = pipeline_surfels(&mut p, view)?;
            (s, spec, d, e, Some(r))
        }
        None => {
            let (s, spec, d, e) = surfels_with(
                gpu.as_ref(),
                &positions,
                h,
                args.resolution.unwrap_or(DEFAULT_RESOLUTION),
                iso,
            )?;
            (s, spec, d, e, None)
        }
    };
    let outputs = write(
        &s,
        (out.as_deref(), out_args.out_format),
        png.as_deref().map(|p| (p, out_args.up)),
    )?;
    let report = SurfelsReport {
        outside_bounds: super::outside_bounds(),
        source,
        particles: positions.len(),
        h,
        grid: spec.dims,
        spacing: spec.spacing,
        iso: s.iso,
        surfels: s.len(),
        path: if args.gpu { "gpu" } else { "cpu" },
        density_ms,
        extract_ms,
        pipeline,
        outputs,
    };
    if out_args.json {
        super::print_json(&report);
    } else {
        println!(
            "{}: {} particles, h {}, grid {:?} (spacing {:.5}), iso {:.4}",
            report.source, report.particles, h, report.grid, report.spacing, report.iso
        );
        if let Some(p) = &report.pipeline {
            println!(
                "  the pipeline's {} source, {} refinement steps ({} points), calibration {}",
                p.source, p.steps, p.refined_points, p.calibration
            );
        }
        println!(
            "  {} surfels; ms: density {:.1} ({}), extraction {:.1} (cpu)",
            report.surfels, density_ms, report.path, extract_ms
        );
        for o in &report.outputs {
            println!("  wrote {o}");
        }
    }
    Ok(())
}

fn surfels_sequence(args: &SurfelsArgs, pattern: &FramePattern, iso: f32) -> Result<(), Error> {
    let src = &args.source;
    let o = &args.outputs;
    let super::PreparedSequence {
        sequence,
        out,
        png,
        radius,
    } = super::prepare_sequence(src, o, pattern, "surfels")?;
    let h = args.h.unwrap_or(radius);
    let source = args.pipeline_source();
    let run = sequence.run_warm(
        // one pipeline per job: its hysteresis runs over the job's frames, warmed up before
        || {
            source
                .map(|s| Pipeline::new(args.pipeline_params(s, radius, iso)))
                .transpose()
        },
        |pipeline, f| match pipeline {
            Some(p) => {
                let particles = super::read_particles(&pattern.path(f), src.format)?;
                p.warm_up(&particles, Through::Surfels)
            }
            // the raw density grid carries nothing from frame to frame
            None => Ok(()),
        },
        |pipeline, f| {
            let particles = super::read_particles(&pattern.path(f), src.format)?;
            let (s, d, e) = match pipeline {
                Some(p) => {
                    let (s, _, d, e, _) = pipeline_surfels(p, particles.view())?;
                    (s, d, e)
                }
                None => {
                    let resolution = args.resolution.unwrap_or(DEFAULT_RESOLUTION);
                    let (s, _, d, e) = surfels_of(&particles.positions, h, resolution, iso)?;
                    (s, d, e)
                }
            };
            write(
                &s,
                (out.as_ref().map(|x| x.path(f)).as_deref(), o.out_format),
                png.as_ref().map(|x| x.path(f)).as_deref().map(|x| (x, o.up)),
            )?;
            Ok(serde_json::json!({"frame": f, "particles": particles.len(), "surfels": s.len(), "density_ms": d, "extract_ms": e}))
        },
    )?;
    let v = serde_json::json!({
        "input": src.input, "h": h, "jobs": run.jobs, "processed": run.results.len(), "skipped": run.skipped,
        "seconds": run.seconds, "frames": run.results,
    });
    if o.json {
        println!("{v}");
    } else {
        println!(
            "{}: {} frames, {} skipped, {:.2} s",
            src.input.as_deref().unwrap_or(""),
            run.results.len(),
            run.skipped.len(),
            run.seconds
        );
    }
    Ok(())
}
