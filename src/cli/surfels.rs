//! `fluid-surfels surfels`: density grid and iso-surface surfels (Iwasaki et al., §4).

use std::path::{Path, PathBuf};
use std::time::Instant;

use fluid_surfels::Error;
use fluid_surfels::density::{self, GridSpec, Kernel, Resolution};
use fluid_surfels::io;
use fluid_surfels::preview::{self, PreviewCamera};
use fluid_surfels::sequence::FramePattern;
use fluid_surfels::surfels::{self, SurfelParams, Surfels};
use glam::Vec3;
use serde::Serialize;

use super::{check_output, ms};

/// Arguments of `surfels`.
#[derive(clap::Args)]
pub struct SurfelsArgs {
    #[command(flatten)]
    pub source: super::SourceArgs,
    #[command(flatten)]
    pub outputs: super::OutputArgs,
    /// Grid points along the longest axis of the particles' padded box.
    #[arg(long, default_value_t = 128)]
    pub resolution: u32,
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
    outputs: Vec<String>,
}

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
    let spec = GridSpec::around(positions, h, Resolution::LongestAxis(resolution))?;
    let limit = io::available_memory() / 2;
    let t = Instant::now();
    let grid = match gpu {
        Some(ctx) => {
            spec.check_memory(limit)?;
            fluid_surfels::gpu::density::density_grid_gpu(ctx, positions, &spec, Kernel::Wyvill, h)?
        }
        None => density::density_grid(positions, &spec, Kernel::Wyvill, h, limit)?,
    };
    let density_ms = ms(t);
    let t = Instant::now();
    let params = SurfelParams {
        iso_fraction,
        ..SurfelParams::default()
    };
    let s = surfels::extract(&grid, positions, Kernel::Wyvill, h, &params)?;
    Ok((s, spec, density_ms, ms(t)))
}

/// Surfels drawn as small shaded disks coloured by their normal.
pub fn surfels_picture(
    s: &Surfels,
    camera: &PreviewCamera,
    size: u32,
) -> Result<image::RgbImage, Error> {
    let colours: Vec<[u8; 3]> = s
        .normals
        .iter()
        .map(|n| {
            ((*n * 0.5 + 0.5) * 255.0)
                .to_array()
                .map(|c| c.clamp(0.0, 255.0) as u8)
        })
        .collect();
    let radius = s.radii.first().copied().unwrap_or(0.01) * 0.6;
    Ok(preview::render_points(
        &s.positions,
        &colours,
        radius,
        camera,
        size,
        size,
    )?)
}

fn write(s: &Surfels, out: Option<&Path>, png: Option<&Path>) -> Result<Vec<String>, Error> {
    let mut outputs = Vec::new();
    if let Some(out) = out {
        io::write_particles(out, &s.to_particle_set(), None)?;
        outputs.push(out.display().to_string());
    }
    if let Some(png) = png {
        let (lo, hi) = s
            .positions
            .iter()
            .fold((Vec3::INFINITY, Vec3::NEG_INFINITY), |(lo, hi), &p| {
                (lo.min(p), hi.max(p))
            });
        let (lo, hi) = if lo.is_finite() {
            (lo, hi)
        } else {
            (Vec3::ZERO, Vec3::ONE)
        };
        let picture = surfels_picture(s, &PreviewCamera::framing(lo, hi), 800)?;
        preview::save_png(&picture, png)?;
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
        check_output(o, input.as_deref(), out_args.force)?;
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
    let (s, spec, density_ms, extract_ms) =
        surfels_with(gpu.as_ref(), &positions, h, args.resolution, iso)?;
    let outputs = write(&s, out.as_deref(), png.as_deref())?;
    let report = SurfelsReport {
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
        outputs,
    };
    if out_args.json {
        super::print_json(&report);
    } else {
        println!(
            "{}: {} particles, h {}, grid {:?} (spacing {:.5}), iso {:.4}",
            report.source, report.particles, h, report.grid, report.spacing, report.iso
        );
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
    let run = sequence.run(
        || Ok(()),
        |_, f| {
            let particles = io::read_particles(&pattern.path(f), src.format)?;
            let (s, _, d, e) = surfels_of(&particles.positions, h, args.resolution, iso)?;
            write(&s, out.as_ref().map(|x| x.path(f)).as_deref(), png.as_ref().map(|x| x.path(f)).as_deref())?;
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
