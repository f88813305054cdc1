//! `bench optics`: caustics and the finished frame, CPU and GPU.

use std::time::Instant;

use fluid_surfels::Error;
use serde::Serialize;

use super::{GpuBenchRun, median};
use crate::cli::ms;

/// Arguments of `bench optics`.
#[derive(clap::Args)]
pub struct BenchOpticsArgs {
    /// Surfel counts of the wave tank (the paper's animation had 55,000 to 120,000).
    #[arg(long, value_delimiter = ',', default_values_t = [55_000usize, 120_000])]
    pub surfels: Vec<usize>,
    /// Final image size (the paper's 512x512).
    #[arg(long, default_value = "512x512", value_parser = crate::cli::render::parse_size)]
    pub size: (u32, u32),
    #[command(flatten)]
    pub run: GpuBenchRun,
}

#[derive(Serialize)]
struct OpticsCase {
    surfels: usize,
    screen: [u32; 2],
    map: [u32; 2],
    image: [u32; 2],
    cpu_caustics_ms: Option<f64>,
    cpu_frame_ms: Option<f64>,
    gpu_caustics_ms: Option<f64>,
    gpu_frame_ms: Option<f64>,
    gpu_fps: Option<f64>,
    cpu_fps: Option<f64>,
}

#[derive(Serialize)]
struct OpticsBenchReport {
    adapter: Option<String>,
    threads: usize,
    cases: Vec<OpticsCase>,
}

/// `bench optics`: caustics and final image at the paper's sizes, GPU and CPU reference.
pub fn bench_optics(args: &BenchOpticsArgs) -> Result<(), Error> {
    use fluid_surfels::optics::gpu::{OpticsGpu, run_timed};
    use fluid_surfels::optics::{self, OpticsScene, ReceiverKind, Stage};
    let ctx = fluid_surfels::gpu::GpuContext::headless().ok();
    let gpu = match &ctx {
        Some(c) => Some(OpticsGpu::new(&c.device)?),
        None => None,
    };
    let mut cases = Vec::new();
    for &n in &args.surfels {
        let side = (n as f32).sqrt().max(2.0);
        let surfels = fluid_surfels::scenes::height_field(1.0, 2.0 / (side - 1.0), |x, z| {
            0.5 + 0.03 * (6.0 * x).sin() * (4.0 * z + 1.0).cos() + 0.01 * (17.0 * z - 3.0 * x).sin()
        });
        for screen in [[256u32, 64], [256, 256]] {
            let mut scene = OpticsScene::default();
            scene.receiver.kind = ReceiverKind::OpenBox;
            scene.receiver.min = glam::Vec3::new(-1.05, 0.0, -1.05);
            scene.receiver.max = glam::Vec3::new(1.05, 0.7, 1.05);
            scene.receiver.checker = 0.25;
            scene.water.extinction = glam::Vec3::new(1.2, 0.35, 0.2);
            scene.optics.caustics_resolution = Some(screen);
            scene.optics.image_size = [args.size.0, args.size.1];
            scene.camera = Some(fluid_surfels::splat::Camera {
                eye: glam::Vec3::new(0.5, 3.6, 1.4),
                target: glam::Vec3::new(0.0, 0.2, 0.0),
                near: 0.5,
                far: 8.0,
                ..Default::default()
            });
            let stage = Stage::new(&scene, &surfels)?;
            let (mut cpu_c, mut cpu_f) = (None, None);
            if !args.run.no_cpu {
                let t = Instant::now();
                let c = optics::caustics_cpu(&stage, &surfels)?;
                cpu_c = Some(ms(t));
                let t = Instant::now();
                optics::frame_cpu(&stage, &surfels, &c, args.size)?;
                cpu_f = Some(ms(t));
            }
            let (mut gpu_c, mut gpu_f) = (None, None);
            if let (Some(ctx), Some(g)) = (&ctx, &gpu) {
                let prepared =
                    g.prepare(&ctx.device, &ctx.queue, &stage, &surfels, Some(args.size))?;
                run_timed(ctx, g, &prepared)?;
                let mut cs = Vec::new();
                let mut fs = Vec::new();
                for _ in 0..args.run.repeat.max(1) {
                    let t = run_timed(ctx, g, &prepared)?;
                    cs.push(t.caustics_ms);
                    fs.push(t.frame_ms);
                }
                gpu_c = Some(median(cs));
                gpu_f = Some(median(fs));
            }
            let fps = |a: Option<f64>, b: Option<f64>| a.zip(b).map(|(a, b)| 1e3 / (a + b));
            let case = OpticsCase {
                surfels: surfels.len(),
                screen,
                map: [stage.views.map.width, stage.views.map.height],
                image: [args.size.0, args.size.1],
                cpu_caustics_ms: cpu_c,
                cpu_frame_ms: cpu_f,
                gpu_caustics_ms: gpu_c,
                gpu_frame_ms: gpu_f,
                gpu_fps: fps(gpu_c, gpu_f),
                cpu_fps: fps(cpu_c, cpu_f),
            };
            if !args.run.json {
                let f = |v: Option<f64>| v.map_or("-".to_string(), |v| format!("{v:.1}"));
                println!(
                    "{} surfels, screen {}x{}, map {}x{}, image {}x{}: CPU caustics {} ms + frame {} ms ({} fps); GPU caustics {} ms + frame {} ms ({} fps)",
                    case.surfels,
                    screen[0],
                    screen[1],
                    case.map[0],
                    case.map[1],
                    args.size.0,
                    args.size.1,
                    f(cpu_c),
                    f(cpu_f),
                    f(case.cpu_fps),
                    f(gpu_c),
                    f(gpu_f),
                    f(case.gpu_fps)
                );
            }
            cases.push(case);
        }
    }
    let report = OpticsBenchReport {
        adapter: ctx
            .as_ref()
            .and_then(|c| c.adapter.as_ref())
            .map(|a| format!("{} ({}, {})", a.name, a.backend, a.device_type)),
        threads: rayon::current_num_threads(),
        cases,
    };
    if args.run.json {
        crate::cli::print_json(&report);
    } else {
        println!(
            "adapter: {}; CPU reference on {} threads",
            report.adapter.as_deref().unwrap_or("none"),
            report.threads
        );
    }
    Ok(())
}
