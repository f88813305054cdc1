//! `bench renderers`: each renderer's draw on the CPU and the GPU from the same surfels.

use std::time::Instant;

use fluid_surfels::Error;
use fluid_surfels::pipeline::{Renderer, SurfelSource};
use serde::Serialize;

use super::{BenchFrame, bench_context, median_of};
use crate::cli::ms;

/// Arguments of `bench renderers`.
#[derive(clap::Args)]
pub struct BenchRenderersArgs {
    #[command(flatten)]
    pub frame: BenchFrame,
    /// Image size, WIDTHxHEIGHT.
    #[arg(long, default_value = "1024x1024", value_parser = crate::cli::render::parse_size)]
    pub size: (u32, u32),
    /// Where the drawn surfels or points come from (as `render --source`).
    #[arg(long, value_parser = crate::cli::names_parser(&SurfelSource::ALL, SurfelSource::as_str), default_value = "chain")]
    pub source: SurfelSource,
    /// The renderers to time, comma-separated.
    #[arg(
        long,
        value_parser = crate::cli::names_parser(&Renderer::ALL, Renderer::as_str),
        value_delimiter = ',',
        default_value = "ewa,particle-splat,ray-cast"
    )]
    pub renderers: Vec<Renderer>,
    /// Timed runs of each renderer on each backend (the median is reported), after one untimed
    /// run when more than one.
    #[arg(long, default_value_t = 3)]
    pub repeat: usize,
    /// CPU only. Otherwise any adapter runs, a software one too (a bench measures what it is
    /// asked; `render` takes a software adapter only with --gpu).
    #[arg(long)]
    pub no_gpu: bool,
    /// Print one JSON object instead of the table.
    #[arg(long)]
    pub json: bool,
}

/// One renderer's figures in `bench renderers`.
#[derive(Serialize)]
struct RendererBench {
    renderer: &'static str,
    /// Surfels (EWA) or spheres (particle splatting, ray casting) drawn.
    drawn: usize,
    /// The frame up to what is drawn (detection, upsampling, grid, surfels), once, on the CPU.
    prepare_ms: f64,
    cpu_ms: f64,
    gpu_ms: Option<f64>,
    /// GPU time over CPU time, measured in the same run.
    gpu_over_cpu: Option<f64>,
    covered_pixels: usize,
    gpu_covered_pixels: Option<usize>,
    /// PSNR of the GPU image against the CPU's; null when identical.
    psnr_gpu_against_cpu_db: Option<f64>,
}

#[derive(Serialize)]
struct RenderersBenchReport {
    source: String,
    particles: usize,
    support_radius: f32,
    surfel_source: &'static str,
    width: u32,
    height: u32,
    threads: usize,
    repeat: usize,
    adapter: Option<String>,
    renderers: Vec<RendererBench>,
}

/// Each renderer on one frame at one size, on the CPU and on the GPU: the draw alone, from the
/// same surfels or points and the same camera on both.
pub fn bench_renderers(args: &BenchRenderersArgs) -> Result<(), Error> {
    use fluid_surfels::pipeline::{self, Pipeline, PipelineParams, Renderer, Through};
    use fluid_surfels::splat::{self, Light};
    let (source, set, radius) = args.frame.read()?;
    let ctx = bench_context(args.no_gpu, args.json);
    let (w, h) = args.size;
    let light = Light::default();
    let mut rows = Vec::new();
    let bar = crate::cli::progress(args.renderers.len() as u64, "renderers");
    for &renderer in &args.renderers {
        let mut pipeline = Pipeline::new(PipelineParams {
            support_radius: Some(radius),
            renderer,
            source: args.source,
            ..Default::default()
        })?;
        let t = Instant::now();
        let frame = pipeline.frame_through(&set, Through::Surfels)?;
        let prepare_ms = ms(t);
        let surfels = &frame.render_surfels;
        let camera = crate::cli::render::framing(surfels);
        let params = pipeline.splat_params();
        let (points, radii) = pipeline::sphere_points(surfels);
        let caster = (renderer == Renderer::RayCast)
            .then(|| pipeline.caster(&points, &radii, &frame.render_weights))
            .transpose()?;
        let screen = (renderer == Renderer::Ssfr)
            .then(|| pipeline.screen_space(&points, &radii))
            .transpose()?;
        let (cpu_ms, cpu) = median_of(args.repeat, || {
            Ok(if let Some(screen) = &screen {
                let v = splat::View::new(&camera, &light, &params, w, h)?;
                screen.render_view(&v)?.render
            } else if let Some(caster) = &caster {
                fluid_surfels::raycast::render_cpu(caster, &camera, &light, &params, w, h)?.render
            } else {
                splat::render_cpu(surfels, &camera, &light, &params, w, h)?
            })
        })?;
        let mut gpu_ssfr = match (&ctx, &screen) {
            (Some(ctx), Some(_)) => Some(fluid_surfels::ssfr::gpu::GpuSsfr::new(&ctx.device)?),
            _ => None,
        };
        let gpu = match (&ctx, &screen, &mut gpu_ssfr) {
            (Some(ctx), Some(screen), Some(g)) => Some(median_of(args.repeat, || {
                let v = splat::View::new(&camera, &light, &params, w, h)?;
                Ok(g.render(ctx, screen, &v)?.render)
            })?),
            (Some(ctx), _, _) => Some(median_of(args.repeat, || {
                Ok(if let Some(caster) = &caster {
                    fluid_surfels::raycast::gpu::render_gpu(
                        ctx, caster, &camera, &light, &params, w, h,
                    )?
                    .render
                } else {
                    splat::gpu::render_gpu(ctx, surfels, &camera, &light, &params, w, h)?
                })
            })?),
            _ => None,
        };
        rows.push(RendererBench {
            renderer: renderer.as_str(),
            drawn: surfels.len(),
            prepare_ms,
            cpu_ms,
            gpu_ms: gpu.as_ref().map(|g| g.0),
            gpu_over_cpu: gpu.as_ref().map(|g| g.0 / cpu_ms),
            covered_pixels: cpu.covered_pixels(),
            gpu_covered_pixels: gpu.as_ref().map(|g| g.1.covered_pixels()),
            psnr_gpu_against_cpu_db: gpu
                .as_ref()
                .map(|g| splat::psnr(&cpu.image, &g.1.image))
                .filter(|p| p.is_finite()),
        });
        bar.inc(1);
    }
    bar.finish_and_clear();
    let report = RenderersBenchReport {
        source,
        particles: set.len(),
        support_radius: radius,
        surfel_source: args.source.as_str(),
        width: w,
        height: h,
        threads: rayon::current_num_threads(),
        repeat: args.repeat.max(1),
        adapter: ctx.as_ref().map(|c| {
            c.adapter
                .as_ref()
                .map(|a| a.name.clone())
                .unwrap_or_default()
        }),
        renderers: rows,
    };
    if args.json {
        crate::cli::print_json(&report);
        return Ok(());
    }
    println!(
        "bench renderers: {} ({} particles, support radius {:.4}), source {}, {w}x{h}, {} threads, median of {}",
        report.source,
        report.particles,
        report.support_radius,
        report.surfel_source,
        report.threads,
        report.repeat
    );
    if let Some(a) = &report.adapter {
        println!("  GPU: {a}");
    }
    println!("  renderer         drawn   prepare ms    CPU ms     GPU ms  GPU/CPU  covered  PSNR");
    for r in &report.renderers {
        println!(
            "  {:<14} {:>7} {:>12.1} {:>9.1} {:>10} {:>8} {:>8} {}",
            r.renderer,
            r.drawn,
            r.prepare_ms,
            r.cpu_ms,
            r.gpu_ms.map_or("-".into(), |g| format!("{g:.1}")),
            r.gpu_over_cpu.map_or("-".into(), |g| format!("{g:.2}x")),
            r.covered_pixels,
            match (r.gpu_ms, r.psnr_gpu_against_cpu_db) {
                (None, _) => "-".into(),
                (Some(_), None) => "identical".into(),
                (Some(_), Some(p)) => format!("{p:.1} dB"),
            }
        );
    }
    Ok(())
}
