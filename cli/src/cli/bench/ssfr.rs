//! `bench ssfr`: the screen-space renderer per filter, CPU and GPU.

use std::time::Instant;

use fluid_surfels::Error;
use fluid_surfels::ssfr::DepthFilter;
use serde::Serialize;

use super::{BenchFrame, bench_context, median_of};
use crate::cli::ms;

/// Arguments of `bench ssfr`.
#[derive(clap::Args)]
pub struct BenchSsfrArgs {
    #[command(flatten)]
    pub frame: BenchFrame,
    /// Image size, WIDTHxHEIGHT (default full HD, the paper's).
    #[arg(long, default_value = "1920x1080", value_parser = crate::cli::render::parse_size)]
    pub size: (u32, u32),
    /// The depth filters to time, comma-separated.
    #[arg(
        long,
        value_parser = crate::cli::names_parser(&DepthFilter::ALL, DepthFilter::as_str),
        value_delimiter = ',',
        default_value = "narrow-range,bilateral,plane,curvature-flow"
    )]
    pub filters: Vec<DepthFilter>,
    /// Timed runs of each (the median is reported), after one untimed run when more than one.
    #[arg(long, default_value_t = 3)]
    pub repeat: usize,
    /// CPU only. Otherwise any adapter runs the GPU twin too, a software one included.
    #[arg(long)]
    pub no_gpu: bool,
    /// Print one JSON object instead of the table.
    #[arg(long)]
    pub json: bool,
}

/// One filter with or without the narrow band in `bench ssfr`.
#[derive(Serialize)]
struct SsfrBench {
    filter: &'static str,
    narrow_band: bool,
    /// Particles drawn in the depth pass.
    drawn: usize,
    /// Gaussians of the thickness (voxels with the band, particles without).
    thickness_sources: usize,
    /// The narrow band and the thickness sources, once per frame (not in `median_ms`).
    prepare_ms: f64,
    median_ms: f64,
    /// The passes of the median run's first result: depth, filter, thickness, shading.
    passes: fluid_surfels::ssfr::cpu::SsfrTimings,
    /// Bytes of what the passes read: 16 a drawn sphere, 20 a thickness source.
    input_bytes: usize,
    covered_pixels: usize,
    /// PSNR against the same filter without the narrow band (on the band's rows).
    psnr_against_all_db: Option<f64>,
    /// The GPU twin (`ssfr::gpu`), the whole run with its read-back, when an adapter exists.
    gpu_ms: Option<f64>,
    /// GPU time over CPU time, measured in the same run.
    gpu_over_cpu: Option<f64>,
    /// The GPU's image against the CPU's.
    psnr_gpu_against_cpu_db: Option<f64>,
}

#[derive(Serialize)]
struct SsfrBenchReport {
    source: String,
    particles: usize,
    support_radius: f32,
    width: u32,
    height: u32,
    threads: usize,
    repeat: usize,
    adapter: Option<String>,
    band: usize,
    band_share: f64,
    voxels: usize,
    /// `1 - band input bytes / all input bytes` (the paper's Table 2 "mem", as we define it:
    /// the spheres drawn and the thickness sources the passes read).
    memory_saved: f64,
    rows: Vec<SsfrBench>,
}

/// The screen-space renderer on one frame (the raw particles, as the paper draws them) at one
/// size on the CPU: each filter with and without the narrow band, per pass.
pub fn bench_ssfr(args: &BenchSsfrArgs) -> Result<(), Error> {
    use fluid_surfels::splat::{self, Light, SplatParams, View};
    use fluid_surfels::ssfr::{ScreenSpace, SsfrParams};
    let (source, set, radius) = args.frame.read()?;
    let p = &set.positions;
    let radii = vec![radius; p.len()];
    let spheres = splat::spheres_from(p, &[], radius, splat::WATER);
    let camera = crate::cli::render::framing(&spheres);
    let (w, h) = args.size;
    let view = View::new(&camera, &Light::default(), &SplatParams::default(), w, h)?;
    let ctx = bench_context(args.no_gpu, args.json);
    let mut gpu = match &ctx {
        Some(c) => Some(fluid_surfels::ssfr::gpu::GpuSsfr::new(&c.device)?),
        None => None,
    };
    let mut rows = Vec::new();
    let (mut band, mut voxels) = (p.len(), 0);
    let bar = crate::cli::progress(2 * args.filters.len() as u64, "filters");
    for &choice in &args.filters {
        let mut all_image = None;
        for narrow_band in [false, true] {
            let params = SsfrParams {
                filter: choice,
                narrow_band,
                ..Default::default()
            };
            let t = Instant::now();
            let screen = ScreenSpace::new(p, &radii, radius, &params)?;
            let prepare_ms = ms(t);
            if let Some(b) = screen.band() {
                band = b.len();
                voxels = b.voxels.len();
            }
            let (median_ms, r) = median_of(args.repeat, || Ok(screen.render_view(&view)?))?;
            let on_gpu = match (&ctx, &mut gpu) {
                (Some(ctx), Some(g)) => {
                    Some(median_of(args.repeat, || g.render(ctx, &screen, &view))?)
                }
                _ => None,
            };
            let psnr = match (&all_image, narrow_band) {
                (Some(a), true) => Some(splat::psnr(a, &r.render.image)),
                _ => None,
            };
            rows.push(SsfrBench {
                filter: params.filter.as_str(),
                narrow_band,
                drawn: screen.drawn(),
                thickness_sources: screen.sources().len(),
                prepare_ms,
                median_ms,
                passes: r.timings,
                input_bytes: 16 * screen.drawn() + 20 * screen.sources().len(),
                covered_pixels: r.render.covered_pixels(),
                psnr_against_all_db: psnr,
                gpu_ms: on_gpu.as_ref().map(|g| g.0),
                gpu_over_cpu: on_gpu.as_ref().map(|g| g.0 / median_ms),
                psnr_gpu_against_cpu_db: on_gpu
                    .as_ref()
                    .map(|g| splat::psnr(&r.render.image, &g.1.render.image)),
            });
            if !narrow_band {
                all_image = Some(r.render.image);
            }
            bar.inc(1);
        }
    }
    bar.finish_and_clear();
    let bytes = |nb: bool| {
        rows.iter()
            .find(|r| r.narrow_band == nb)
            .map_or(0, |r| r.input_bytes)
    };
    let report = SsfrBenchReport {
        source,
        particles: p.len(),
        support_radius: radius,
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
        band,
        band_share: band as f64 / p.len().max(1) as f64,
        voxels,
        memory_saved: 1.0 - bytes(true) as f64 / bytes(false).max(1) as f64,
        rows,
    };
    if args.json {
        crate::cli::print_json(&report);
        return Ok(());
    }
    println!(
        "bench ssfr: {} ({} particles, support radius {:.4}), {w}x{h}, {} threads, median of {}",
        report.source, report.particles, report.support_radius, report.threads, report.repeat
    );
    println!(
        "  narrow band: {} particles ({:.1} %), {} voxels; the passes read {:.0} % less",
        report.band,
        100.0 * report.band_share,
        report.voxels,
        100.0 * report.memory_saved
    );
    if let Some(a) = &report.adapter {
        println!("  GPU: {a}");
    }
    let db = |p: Option<f64>| match p {
        None => "-".to_owned(),
        Some(p) if p.is_finite() => format!("{p:.1} dB"),
        Some(_) => "identical".to_owned(),
    };
    println!(
        "  filter          band   drawn  prepare ms   frame ms   depth  filter  thickness  shading  covered  PSNR vs all   GPU ms  GPU/CPU  GPU PSNR"
    );
    for r in &report.rows {
        println!(
            "  {:<15} {:>4} {:>7} {:>11.1} {:>10.1} {:>7.1} {:>7.1} {:>10.1} {:>8.1} {:>8} {:>11} {:>8} {:>8} {}",
            r.filter,
            if r.narrow_band { "yes" } else { "no" },
            r.drawn,
            r.prepare_ms,
            r.median_ms,
            r.passes.depth_ms,
            r.passes.filter_ms,
            r.passes.thickness_ms,
            r.passes.shading_ms,
            r.covered_pixels,
            db(r.psnr_against_all_db),
            r.gpu_ms.map_or("-".into(), |g| format!("{g:.1}")),
            r.gpu_over_cpu.map_or("-".into(), |g| format!("{g:.2}x")),
            db(r.psnr_gpu_against_cpu_db),
        );
    }
    Ok(())
}
