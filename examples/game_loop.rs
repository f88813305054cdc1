//! A game loop around `GpuPipeline`: the game creates its own device, builds the pipeline once,
//! steps the built-in `column` simulation, and every frame records the pipeline's GPU passes into
//! its own encoder and draws the finished water into its own texture (an sRGB target, as a
//! swap-chain image would be). Only the frames it saves are copied back, and each saved frame is
//! compared with the CPU `Pipeline`'s image of the same frame.
//!
//! Run: `cargo run --release --example game_loop -- [--frames 60] [--size 320x320]
//! [--save 0,30,59] [--out DIR] [--json] [--cpu-surfels] [--narrow-band] [--stage-ms]
//! [--renderer ewa|particle-splat|ray-cast|ssfr] [--orbit DEGREES] [--input FILE
//! [--particles N]]`. The
//! density grid and the surfels are made on the GPU (`PipelineParams::gpu_surfels`);
//! `--cpu-surfels` makes them on the CPU, as the CPU `Pipeline` does, to compare the two;
//! `--narrow-band` makes the grid sparse (`grid.narrow_band`: the blocks near the surface
//! chosen on the GPU and filled there by the gather pass); `--renderer` draws the water with
//! another renderer (default `ewa`; the others take the CPU's points, the ray caster's weights
//! solved on the GPU, see `GpuPipeline`); `--orbit` turns the camera by that many degrees a
//! frame around the point it looks at, as a game's camera moves (the CPU reference follows it);
//! `--input` draws a particle file's frame every frame instead of the column simulation (the
//! automatic pool; `--particles N` resamples it to about N particles first, the same body on a
//! finer lattice: the 100,000-particle double dam break).
//! Needs a GPU or Mesa's lavapipe (on lavapipe, a
//! software rasteriser, it proves the loop works, not how fast a GPU runs it).
//!
//! `--json` prints one object: frames, the CPU milliseconds per frame (the CPU stages plus
//! recording and submitting; mean and 95th percentile), those of `prepare` alone
//! (`cpu_prepare_ms`, its mean; `cpu_prepare_ms_median`, the steady state without the first
//! frame's compiles; `cpu_prepare_stages_ms`: its mean per stage, where the density and surfels
//! made on the GPU count only their recording), the stages that ran on the GPU (`gpu_stages`),
//! the GPU milliseconds per frame from timestamp queries where the adapter has them (then each
//! frame waits for its timestamps) and
//! with `--stage-ms` those of each stage and each timed pass of a recent frame (`gpu_stage_ms`,
//! `gpu_pass_ms`,
//! `GpuPipeline::time_stages`; they slow lavapipe down, see there), and
//! the PSNR of every saved frame against the CPU pipeline, the largest grid the GPU held
//! (`gpu_grid_mib_max`, `GpuPipeline::gpu_grid_bytes`), and how many frames reused the
//! pipeline's GPU resources (all but those whose water needed larger buffers than any frame
//! before).

use std::path::PathBuf;
use std::time::Instant;

use fluid_surfels::ParticleSet;
use fluid_surfels::gpu::{GpuContext, REQUIRED_FEATURES};
use fluid_surfels::pipeline::{
    FrameTimings, GpuPipeline, Pipeline, PipelineParams, Renderer, Through,
};
use fluid_surfels::scenes::{ColumnParams, ColumnSim, column_pool};
use fluid_surfels::splat::psnr;

struct Args {
    frames: usize,
    size: (u32, u32),
    save: Vec<usize>,
    out: PathBuf,
    json: bool,
    cpu_surfels: bool,
    narrow_band: bool,
    stage_ms: bool,
    renderer: Renderer,
    orbit_degrees: f32,
    input: Option<PathBuf>,
    particles: Option<usize>,
}

fn args() -> Result<Args, String> {
    let mut a = Args {
        frames: 60,
        size: (320, 320),
        save: Vec::new(),
        out: PathBuf::from("out/game_loop"),
        json: false,
        cpu_surfels: false,
        narrow_band: false,
        stage_ms: false,
        renderer: Renderer::Ewa,
        orbit_degrees: 0.0,
        input: None,
        particles: None,
    };
    let mut it = std::env::args().skip(1);
    while let Some(flag) = it.next() {
        let mut value = || it.next().ok_or(format!("{flag} needs a value"));
        match flag.as_str() {
            "--frames" => a.frames = value()?.parse().map_err(|e| format!("--frames: {e}"))?,
            "--size" => {
                let v = value()?;
                let (w, h) = v
                    .split_once('x')
                    .ok_or(format!("--size {v}: expected WxH"))?;
                a.size = (
                    w.parse().map_err(|e| format!("--size: {e}"))?,
                    h.parse().map_err(|e| format!("--size: {e}"))?,
                );
            }
            "--save" => {
                a.save = value()?
                    .split(',')
                    .map(|f| f.trim().parse().map_err(|e| format!("--save: {e}")))
                    .collect::<Result<_, _>>()?
            }
            "--out" => a.out = PathBuf::from(value()?),
            "--json" => a.json = true,
            "--cpu-surfels" => a.cpu_surfels = true,
            "--narrow-band" => a.narrow_band = true,
            "--stage-ms" => a.stage_ms = true,
            "--input" => a.input = Some(PathBuf::from(value()?)),
            "--particles" => {
                a.particles = Some(value()?.parse().map_err(|e| format!("--particles: {e}"))?);
            }
            "--orbit" => {
                a.orbit_degrees = value()?.parse().map_err(|e| format!("--orbit: {e}"))?;
                if !a.orbit_degrees.is_finite() {
                    return Err("--orbit must be a finite number of degrees".into());
                }
            }
            "--renderer" => {
                let v = value()?;
                a.renderer = Renderer::ALL
                    .into_iter()
                    .find(|r| r.as_str() == v)
                    .ok_or(format!(
                        "--renderer {v}: expected ewa, particle-splat, ray-cast or ssfr"
                    ))?;
            }
            other => return Err(format!("unknown argument {other}")),
        }
    }
    if a.frames == 0 {
        return Err("--frames must be at least 1".into());
    }
    if a.particles.is_some() && a.input.is_none() {
        return Err("--particles resamples an --input file".into());
    }
    if a.save.is_empty() {
        a.save = vec![0, a.frames / 2, a.frames - 1];
    }
    a.save.retain(|&f| f < a.frames);
    a.save.dedup();
    Ok(a)
}

/// The particles the loop draws: the column simulation, stepped every frame, or a file's frame
/// (resampled on request), drawn again every frame as a paused game's would be.
enum Particles {
    Column(Box<ColumnSim>),
    File(ParticleSet, String),
}

impl Particles {
    /// The particles `args` ask for and the pipeline's parameters for them (the column's pool
    /// and support radius; a file's automatic pool, and its support radius twice the spacing
    /// estimated from it, scaled with the spacing when resampled).
    fn of(args: &Args) -> Result<(Self, PipelineParams), Box<dyn std::error::Error>> {
        let Some(path) = &args.input else {
            let sim = ColumnSim::new(ColumnParams::default())?;
            let params = PipelineParams {
                support_radius: Some(sim.support_radius()),
                scene: column_pool(ColumnParams::default().tank),
                ..Default::default()
            };
            return Ok((Self::Column(Box::new(sim)), params));
        };
        let set = fluid_surfels::io::read_particles(path, None)?;
        let mut radius = 2.0 * fluid_surfels::neighbours::estimate_spacing(&set.positions)?;
        let mut source = path.display().to_string();
        let set = match args.particles {
            Some(n) => {
                let (fine, h) = fluid_surfels::scenes::resample(&set.positions, radius, n)?;
                source = format!("{source}, resampled from {} particles", set.len());
                radius = h;
                ParticleSet::from_positions(fine)
            }
            None => set,
        };
        let params = PipelineParams {
            support_radius: Some(radius),
            ..Default::default()
        };
        Ok((Self::File(set, source), params))
    }

    fn particles(&self) -> &ParticleSet {
        match self {
            Self::Column(sim) => sim.particles(),
            Self::File(set, _) => set,
        }
    }

    fn source(&self) -> &str {
        match self {
            Self::Column(_) => "the column scene",
            Self::File(_, source) => source,
        }
    }

    /// The next frame: the column's next step; a file's frame again.
    fn step(&mut self) {
        if let Self::Column(sim) = self {
            sim.step_frame();
        }
    }
}

/// Adds `timings`' share of a mean over `frames` to `mean` (the stages `prepare` runs).
fn add_share(mean: &mut FrameTimings, timings: &FrameTimings, frames: usize) {
    let n = frames as f64;
    for (sum, ms) in [
        (&mut mean.neighbours_ms, timings.neighbours_ms),
        (&mut mean.detect_ms, timings.detect_ms),
        (&mut mean.refine_ms, timings.refine_ms),
        (&mut mean.calibration_ms, timings.calibration_ms),
        (&mut mean.density_ms, timings.density_ms),
        (&mut mean.surfels_ms, timings.surfels_ms),
    ] {
        *sum += ms / n;
    }
}

/// Turns the pipelines' camera by `degrees` around the point it looks at, about its up axis,
/// from the second frame on (the first fits it).
fn orbit(gpu: &mut GpuPipeline, reference: &mut Pipeline, frame: usize, degrees: f32) {
    if frame > 0
        && degrees != 0.0
        && let Some(mut camera) = gpu.cpu().camera()
    {
        let turn = glam::Quat::from_axis_angle(camera.up.normalize(), degrees.to_radians());
        camera.eye = camera.target + turn * (camera.eye - camera.target);
        gpu.cpu_mut().set_camera(camera);
        reference.set_camera(camera);
    }
}

fn percentile(v: &[f64], p: f64) -> f64 {
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    s[((s.len() as f64 - 1.0) * p).round() as usize]
}

/// Two timestamps around a frame's work: the query set, the buffer it resolves into and the
/// buffer read back.
fn timestamp_query(device: &wgpu::Device) -> (wgpu::QuerySet, wgpu::Buffer, wgpu::Buffer) {
    let set = device.create_query_set(&wgpu::QuerySetDescriptor {
        label: Some("frame"),
        ty: wgpu::QueryType::Timestamp,
        count: 2,
    });
    let resolve = device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("timestamps"),
        size: 16,
        usage: wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
        mapped_at_creation: false,
    });
    let read = device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("timestamps read"),
        size: 16,
        usage: wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::MAP_READ,
        mapped_at_creation: false,
    });
    (set, resolve, read)
}

/// The ticks between the two timestamps copied into `read` (waits for the GPU).
fn read_ticks(
    device: &wgpu::Device,
    read: &wgpu::Buffer,
) -> Result<u64, Box<dyn std::error::Error>> {
    let slice = read.slice(..);
    let (tx, rx) = std::sync::mpsc::channel();
    slice.map_async(wgpu::MapMode::Read, move |r| {
        let _ = tx.send(r);
    });
    device.poll(wgpu::PollType::wait_indefinitely())?;
    rx.recv()??;
    let ticks: Vec<u64> = bytemuck::cast_slice(&slice.get_mapped_range()?).to_vec();
    read.unmap();
    Ok(ticks[1].saturating_sub(ticks[0]))
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args = args()?;
    // --- the game's own device ---
    let instance =
        wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle().with_env());
    let adapter = match pollster::block_on(instance.request_adapter(&Default::default())) {
        Ok(a) => a,
        Err(e) => {
            eprintln!("no GPU adapter ({e}); install a Vulkan driver such as mesa-vulkan-drivers");
            return Ok(());
        }
    };
    let timestamps = adapter.features().contains(
        wgpu::Features::TIMESTAMP_QUERY | wgpu::Features::TIMESTAMP_QUERY_INSIDE_ENCODERS,
    );
    let mut features = REQUIRED_FEATURES;
    if timestamps {
        features |=
            wgpu::Features::TIMESTAMP_QUERY | wgpu::Features::TIMESTAMP_QUERY_INSIDE_ENCODERS;
    }
    let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
        label: Some("game"),
        required_features: features,
        ..Default::default()
    }))?;
    let info = adapter.get_info();
    // the context the crate's read-back helper takes (the same device and queue)
    let ctx = GpuContext::from_device(device.clone(), queue.clone());

    // --- once: the pipeline for the game's target ---
    let format = wgpu::TextureFormat::Rgba8UnormSrgb;
    let (mut sim, mut params) = Particles::of(&args)?;
    params.gpu_surfels = !args.cpu_surfels;
    params.scene.optics.image_size = [args.size.0, args.size.1];
    params.grid.narrow_band = args.narrow_band;
    params.renderer = args.renderer;
    let mut gpu = GpuPipeline::new(&device, &queue, format, args.size, &params)?;
    // (off by default)
    gpu.time_stages(&device, &queue, args.stage_ms);
    // the CPU reference, stepped in lockstep (detection every frame for the same hysteresis)
    let mut reference = Pipeline::new(params)?;
    let query = timestamps.then(|| timestamp_query(&device));
    let period_ns = f64::from(queue.get_timestamp_period());
    if !args.save.is_empty() {
        std::fs::create_dir_all(&args.out)?;
    }
    let (mut cpu_ms, mut gpu_ms, mut saved) = (Vec::new(), Vec::new(), Vec::new());
    let mut prepare_ms = Vec::new();
    let mut stages_ms = FrameTimings::default();
    let (mut reused, mut grid_bytes) = (0, 0u64);
    for f in 0..args.frames {
        let save = args.save.contains(&f);
        // the camera fitted on the first frame, turned around its target from then on
        orbit(&mut gpu, &mut reference, f, args.orbit_degrees);
        let t = Instant::now();
        let mut encoder = device.create_command_encoder(&Default::default());
        if let Some((set, _, _)) = &query {
            encoder.write_timestamp(set, 0);
        }
        let t_prepare = Instant::now();
        let frame = gpu.prepare(&device, &queue, &mut encoder, sim.particles())?;
        prepare_ms.push(t_prepare.elapsed().as_secs_f64() * 1e3);
        add_share(&mut stages_ms, &frame.timings, args.frames);
        reused += usize::from(gpu.reused_resources());
        grid_bytes = grid_bytes.max(gpu.gpu_grid_bytes().unwrap_or(0));
        let target = gpu.draw_to_texture(&device, &mut encoder);
        if let Some((set, resolve, read)) = &query {
            encoder.write_timestamp(set, 1);
            encoder.resolve_query_set(set, 0..2, resolve, 0);
            encoder.copy_buffer_to_buffer(resolve, 0, read, 0, 16);
        }
        queue.submit([encoder.finish()]);
        // the surfel count comes back without a wait, to size the GPU's surfel buffer
        gpu.after_submit();
        cpu_ms.push(t.elapsed().as_secs_f64() * 1e3);
        if let Some((_, _, read)) = &query {
            gpu_ms.push(read_ticks(&device, read)? as f64 * period_ns * 1e-6);
        }
        // the CPU reference: detection on every frame, the whole frame where one is saved
        let through = if save {
            Through::Frame
        } else {
            Through::Surface
        };
        let cpu_frame = reference.frame_through(sim.particles(), through)?;
        if save {
            let image = fluid_surfels::gpu::read_rgba8(&ctx, &target)?;
            let cpu_image = &cpu_frame
                .finished
                .as_ref()
                .expect("through the frame")
                .image;
            let path = args.out.join(format!("frame_{f:04}.png"));
            image.save(&path)?;
            saved.push(serde_json::json!({
                "frame": f,
                "path": path.display().to_string(),
                // made on the GPU: a recent frame's count, read back without a wait
                "surfels": frame.detail.surfels,
                "psnr_against_cpu_db": psnr(cpu_image, &image),
            }));
        }
        gpu.cpu_mut().recycle(frame);
        sim.step();
    }
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
    let report = serde_json::json!({
        "adapter": format!("{} ({:?}, {:?})", info.name, info.backend, info.device_type),
        "frames": args.frames,
        "particles": sim.particles().len(),
        "source": sim.source(),
        "frames_reusing_gpu_resources": reused,
        "size": [args.size.0, args.size.1],
        "cpu_ms_mean": mean(&cpu_ms),
        "cpu_ms_p95": percentile(&cpu_ms, 0.95),
        "cpu_prepare_ms": mean(&prepare_ms),
        "cpu_prepare_ms_p95": percentile(&prepare_ms, 0.95),
        // the steady state: the first frame compiles the passes and makes the buffers
        "cpu_prepare_ms_median": percentile(&prepare_ms, 0.5),
        "cpu_prepare_stages_ms": stages_ms,
        "gpu_stages": gpu.gpu_stages(),
        "gpu_grid_mib_max": grid_bytes as f64 / f64::from(1 << 20),
        // a recent frame's GPU ms per stage, by the pipeline's own timestamps (null without them)
        "gpu_stage_ms": gpu.gpu_stage_ms(),
        // and per pass, in order (the stages and the calibration's passes)
        "gpu_pass_ms": gpu.gpu_pass_ms(),
        "gpu_ms_mean": (!gpu_ms.is_empty()).then(|| mean(&gpu_ms)),
        "gpu_ms_p95": (!gpu_ms.is_empty()).then(|| percentile(&gpu_ms, 0.95)),
        "saved": saved,
    });
    if args.json {
        println!("{report}");
    } else {
        println!(
            "game loop on {}: {} frames of {}x{}; CPU {:.1} ms a frame (p95 {:.1}){}",
            report["adapter"].as_str().unwrap_or(""),
            args.frames,
            args.size.0,
            args.size.1,
            mean(&cpu_ms),
            percentile(&cpu_ms, 0.95),
            if gpu_ms.is_empty() {
                String::from(", no GPU timestamps on this adapter")
            } else {
                format!(
                    "; GPU {:.1} ms a frame (p95 {:.1})",
                    mean(&gpu_ms),
                    percentile(&gpu_ms, 0.95)
                )
            }
        );
        for s in &saved {
            println!(
                "  saved {} ({:.1} dB against the CPU pipeline)",
                s["path"].as_str().unwrap_or(""),
                s["psnr_against_cpu_db"].as_f64().unwrap_or(f64::NAN)
            );
        }
    }
    Ok(())
}
