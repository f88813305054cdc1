//! `bench splat`: the splatting renderer on the CPU and the GPU.

use std::time::Instant;

use fluid_surfels::Error;
use serde::Serialize;

use super::GpuBenchRun;
use crate::cli::ms;
use fluid_surfels::splat::SplatMode;

/// Arguments of `bench splat`.
#[derive(clap::Args)]
pub struct BenchSplatArgs {
    /// Number of surfels (a sphere of surfels filling most of the image; half face the camera).
    #[arg(long, default_value_t = 1_000_000)]
    pub surfels: usize,
    /// Image size, WIDTHxHEIGHT (default: 1920x1080, the goal's case).
    #[arg(long, default_value = "1920x1080", value_parser = crate::cli::render::parse_size)]
    pub size: (u32, u32),
    /// What the surfels are drawn as: ewa (EWA splats), sprites, or spheres (particle
    /// splatting, Adams et al. 2006: each surfel's centre and radius as a sphere).
    #[arg(long, value_parser = crate::cli::names_parser(&SplatMode::ALL, SplatMode::as_str), default_value = "ewa")]
    pub mode: SplatMode,
    #[command(flatten)]
    pub run: GpuBenchRun,
}

#[derive(Serialize)]
struct SplatGpuReport {
    adapter: String,
    visibility_ms: f64,
    attributes_ms: f64,
    shading_ms: f64,
    total_ms: f64,
    splats_per_second: f64,
    /// PSNR of the GPU image against the CPU reference; null when they are identical (or the
    /// reference was skipped).
    psnr_against_cpu_db: Option<f64>,
    /// Largest difference of one 8-bit channel between the GPU and the CPU images.
    max_difference_from_cpu: Option<u8>,
}

#[derive(Serialize)]
struct SplatBenchReport {
    mode: fluid_surfels::splat::SplatMode,
    surfels: usize,
    width: u32,
    height: u32,
    threads: usize,
    covered_pixels: usize,
    gpu: Option<SplatGpuReport>,
    cpu_ms: Option<f64>,
    cpu_splats_per_second: Option<f64>,
    gpu_speedup_over_cpu: Option<f64>,
}

pub fn bench_splat(args: &BenchSplatArgs) -> Result<(), Error> {
    use fluid_surfels::splat::gpu::{SplatRenderer, render_timed};
    use fluid_surfels::splat::{self, Light, SplatParams, View};
    let (width, height) = args.size;
    let surfels = fluid_surfels::scenes::surfel_sphere(args.surfels);
    let camera = fluid_surfels::scenes::surfel_sphere_camera();
    let mode = args.mode;
    let params = SplatParams {
        mode,
        ..SplatParams::default()
    };
    let view = View::new(&camera, &Light::default(), &params, width, height)?;
    let cpu = if args.run.no_cpu {
        None
    } else {
        let t = Instant::now();
        let r = splat::render_view_cpu(&surfels, &view)?;
        Some((ms(t), r))
    };
    let gpu = match fluid_surfels::gpu::GpuContext::headless() {
        Ok(ctx) => {
            let renderer =
                SplatRenderer::new(&ctx.device, wgpu::TextureFormat::Rgba8Unorm, width, height)?;
            let buffer = SplatRenderer::upload(&ctx.device, &surfels);
            // one untimed frame: shader compilation, first-use allocations
            let (first, _) = render_timed(&ctx, &renderer, &buffer, &view)?;
            let mut runs = Vec::new();
            for _ in 0..args.run.repeat.max(1) {
                runs.push(render_timed(&ctx, &renderer, &buffer, &view)?.1);
            }
            runs.sort_by(|a, b| a.total_ms().total_cmp(&b.total_ms()));
            let t = runs[runs.len() / 2];
            Some(SplatGpuReport {
                adapter: ctx.adapter.map(|a| a.name).unwrap_or_default(),
                visibility_ms: t.visibility_ms,
                attributes_ms: t.attributes_ms,
                shading_ms: t.shading_ms,
                total_ms: t.total_ms(),
                splats_per_second: surfels.len() as f64 / (t.total_ms() * 1e-3),
                psnr_against_cpu_db: cpu
                    .as_ref()
                    .map(|(_, c)| splat::psnr(&c.image, &first.image))
                    .filter(|p| p.is_finite()),
                max_difference_from_cpu: cpu.as_ref().map(|(_, c)| {
                    c.image
                        .as_raw()
                        .iter()
                        .zip(first.image.as_raw())
                        .map(|(a, b)| a.abs_diff(*b))
                        .max()
                        .unwrap_or(0)
                }),
            })
        }
        Err(e) => {
            if !args.run.json {
                println!("  (no GPU: {e})");
            }
            None
        }
    };
    let covered = cpu.as_ref().map(|(_, r)| r.covered_pixels()).unwrap_or(0);
    let cpu_ms = cpu.as_ref().map(|c| c.0);
    let report = SplatBenchReport {
        mode,
        surfels: surfels.len(),
        width,
        height,
        threads: rayon::current_num_threads(),
        covered_pixels: covered,
        cpu_ms,
        cpu_splats_per_second: cpu_ms.map(|c| surfels.len() as f64 / (c * 1e-3)),
        gpu_speedup_over_cpu: match (&gpu, cpu_ms) {
            (Some(g), Some(c)) => Some(c / g.total_ms),
            _ => None,
        },
        gpu,
    };
    if args.run.json {
        crate::cli::print_json(&report);
    } else {
        println!(
            "bench splat: {} surfels on a sphere drawn as {:?}, {width}x{height}, {} pixels covered, {} threads",
            report.surfels, report.mode, report.covered_pixels, report.threads
        );
        if let (Some(c), Some(r)) = (report.cpu_ms, report.cpu_splats_per_second) {
            println!(
                "  CPU reference (3 passes)  {c:>9.1} ms   {:.2} M splats/s",
                r / 1e6
            );
        }
        if let Some(g) = &report.gpu {
            println!(
                "  GPU ({})  {:>9.1} ms   {:.2} M splats/s (visibility {:.1}, attributes {:.1}, shading {:.1} ms){}",
                g.adapter,
                g.total_ms,
                g.splats_per_second / 1e6,
                g.visibility_ms,
                g.attributes_ms,
                g.shading_ms,
                report
                    .gpu_speedup_over_cpu
                    .map(|s| format!(", {s:.2}x the CPU reference"))
                    .unwrap_or_default()
            );
            if let Some(d) = g.max_difference_from_cpu {
                println!(
                    "  GPU image against the CPU reference: PSNR {}, largest channel difference {d}",
                    g.psnr_against_cpu_db
                        .map_or("infinite (identical)".into(), |p| format!("{p:.1} dB"))
                );
            }
        }
    }
    Ok(())
}
