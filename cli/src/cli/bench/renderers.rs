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
    use fluid_surfels::pipeline::{Pipeline, PipelineParams, Through};
    use fluid_surfels::splat;
    let (source, set, radius) = args.frame.read()?;
    let ctx = bench_context(args.no_gpu, args.json);
    let (w, h) = args.size;
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
        // the renderer's water, built once (the ray caster's index, the narrow band), drawn
        // from one view; the GPU's time includes making its passes, for every renderer
        let points = pipeline.water_points(surfels);
        let water = pipeline.water_of(surfels, points.as_ref(), &frame.render_weights)?;
        let view = pipeline.draw_view(&camera, (w, h))?;
        let (cpu_ms, cpu) = median_of(args.repeat, || water.render(&view))?;
        let gpu = match &ctx {
            Some(ctx) => Some(median_of(args.repeat, || water.render_gpu(ctx, &view))?),
            None => None,
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
