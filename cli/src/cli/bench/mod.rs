//! Benchmarks users can run: `bench detect` and `bench io`.

use std::path::PathBuf;
use std::time::Instant;

use fluid_surfels::io::{self, Format};
use fluid_surfels::neighbours::{self, Backend, Neighbourhoods};
use fluid_surfels::scenes;
use fluid_surfels::surface::{self, SurfaceDetector, SurfaceParams};
use fluid_surfels::{Attribute, Error, ScalarKind};
use serde::Serialize;

use super::ms;

/// Arguments of `bench detect`.
#[derive(clap::Args)]
pub struct BenchDetectArgs {
    /// Number of particles.
    #[arg(long, default_value_t = 1_000_000)]
    pub particles: usize,
    /// Timed repetitions of the parallel path (the median is reported).
    #[arg(long, default_value_t = 3)]
    pub repeat: usize,
    /// Print one JSON object instead of text.
    #[arg(long)]
    pub json: bool,
}

#[derive(Serialize)]
pub struct BenchDetectReport {
    particles: usize,
    threads: usize,
    radius: f32,
    mean_neighbours: f32,
    surface_particles: usize,
    neighbours_grid_ms: f64,
    neighbours_kdtree_ms: f64,
    detect_ms: f64,
    total_ms: f64,
    particles_per_second: f64,
    reference_neighbours_ms: f64,
    reference_detect_ms: f64,
    reference_total_ms: f64,
    reference_particles_per_second: f64,
    speedup: f64,
    classes_agree_with_reference: bool,
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

pub fn bench_detect(args: &BenchDetectArgs) -> Result<(), Error> {
    let scene = scenes::block(&scenes::BlockParams::with_particles(args.particles))?;
    let particles = &scene.particles;
    let r = scene.support_radius;
    let n = particles.len();
    let repeat = args.repeat.max(1);
    let params = SurfaceParams::default();
    if !args.json {
        println!(
            "bench detect: jittered block of {n} particles, radius {r} (2 x spacing), {} threads",
            rayon::current_num_threads()
        );
    }
    let mut grid_ms = Vec::new();
    let mut kd_ms = Vec::new();
    let mut det_ms = Vec::new();
    let mut last = None;
    for _ in 0..repeat {
        let t = Instant::now();
        let nb = Neighbourhoods::build(&particles.positions, r, Backend::CellGrid)?;
        grid_ms.push(ms(t));
        let t = Instant::now();
        let kd = Neighbourhoods::build(&particles.positions, r, Backend::KdTree)?;
        kd_ms.push(ms(t));
        drop(kd);
        let t = Instant::now();
        let surface = SurfaceDetector::new(params)?.detect(particles, &nb)?;
        det_ms.push(ms(t));
        last = Some((nb, surface));
    }
    let (nb, surface) = last.expect("at least one repetition");
    let (grid, kd, det) = (median(grid_ms), median(kd_ms), median(det_ms));
    let total = grid + det;

    let t = Instant::now();
    let lists = neighbours::reference_neighbours(&particles.positions, r);
    let ref_nb = ms(t);
    let t = Instant::now();
    let (ref_classes, _) = surface::detect_reference(particles, &lists, r, &params);
    let ref_det = ms(t);
    let ref_total = ref_nb + ref_det;
    let agree = ref_classes == surface.classes;

    let report = BenchDetectReport {
        particles: n,
        threads: rayon::current_num_threads(),
        radius: r,
        mean_neighbours: nb.mean_count(),
        surface_particles: surface.counts().surface,
        neighbours_grid_ms: grid,
        neighbours_kdtree_ms: kd,
        detect_ms: det,
        total_ms: total,
        particles_per_second: n as f64 / (total / 1e3),
        reference_neighbours_ms: ref_nb,
        reference_detect_ms: ref_det,
        reference_total_ms: ref_total,
        reference_particles_per_second: n as f64 / (ref_total / 1e3),
        speedup: ref_total / total,
        classes_agree_with_reference: agree,
    };
    if args.json {
        super::print_json(&report);
    } else {
        println!(
            "  mean neighbours {:.1}, surface particles {}",
            report.mean_neighbours, report.surface_particles
        );
        println!("  phase                          ms      particles/s");
        let row =
            |name: &str, v: f64| println!("  {name:<28} {v:>8.1}  {:>12.0}", n as f64 / (v / 1e3));
        row("neighbours (cell grid)", grid);
        row("neighbours (kiddo k-d tree)", kd);
        row("detection + normals", det);
        row("total (grid + detection)", total);
        row("reference neighbours", ref_nb);
        row("reference detection", ref_det);
        row("reference total", ref_total);
        println!(
            "  speedup over the single-threaded reference: {:.2}x (classes identical: {agree})",
            report.speedup
        );
        println!("  (parallel figures are the median of {repeat} runs; the reference runs once)");
    }
    Ok(())
}

/// Arguments of `bench io`.
#[derive(clap::Args)]
pub struct BenchIoArgs {
    /// Number of particles in the files written and read.
    #[arg(long, default_value_t = 1_000_000)]
    pub particles: usize,
    /// Timed reads per format (the fastest is reported).
    #[arg(long, default_value_t = 3)]
    pub repeat: usize,
    /// Formats to measure (default: all).
    #[arg(long, value_parser = super::format_parser(), value_delimiter = ',')]
    pub formats: Vec<Format>,
    /// Print one JSON object instead of text.
    #[arg(long)]
    pub json: bool,
}

#[derive(Serialize)]
struct IoRow {
    format: &'static str,
    file: String,
    bytes: u64,
    write_ms: f64,
    read_ms: f64,
    particles_per_second: f64,
}

#[derive(Serialize)]
struct IoReport {
    particles: usize,
    attributes: Vec<&'static str>,
    formats: Vec<IoRow>,
}

/// Writes a jittered block with ids, velocities and a density in every format, then times
/// reading each back.
pub fn bench_io(args: &BenchIoArgs) -> Result<(), Error> {
    let mut set = scenes::block(&scenes::BlockParams::with_particles(args.particles))?.particles;
    let n = set.len();
    set.velocities = Some(
        set.positions
            .iter()
            .map(|p| glam::Vec3::new(p.y, -p.x, 0.1))
            .collect(),
    );
    set.extra.push(Attribute::scalar(
        "density",
        ScalarKind::F32,
        (0..n).map(|i| 1000.0 + (i % 17) as f64).collect(),
    ));
    let dir = std::env::temp_dir().join(format!("fluid-surfels-bench-io-{}", std::process::id()));
    std::fs::create_dir_all(&dir).map_err(|e| io::IoError::Os {
        path: dir.clone(),
        source: e,
    })?;
    let formats = if args.formats.is_empty() {
        Format::ALL.to_vec()
    } else {
        args.formats.clone()
    };
    let mut rows = Vec::new();
    let mut failure = None;
    for format in formats {
        let name: PathBuf = dir.join(match format {
            Format::Bgeo => "particles.bgeo".to_owned(),
            Format::XyzRaw => "particles.bin".to_owned(),
            f => format!("particles.{}", f.name()),
        });
        let t = Instant::now();
        if let Err(e) = io::write_particles(&name, &set, Some(format)) {
            failure = Some(e);
            break;
        }
        let write_ms = ms(t);
        let bytes = std::fs::metadata(&name).map(|m| m.len()).unwrap_or(0);
        let mut best = f64::INFINITY;
        for _ in 0..args.repeat.max(1) {
            let t = Instant::now();
            match io::read_particles(&name, Some(format)) {
                Ok(back) => {
                    assert_eq!(back.len(), n, "{format:?} read back a different count");
                    best = best.min(ms(t));
                }
                Err(e) => failure = Some(e),
            }
        }
        let _ = std::fs::remove_file(&name);
        if failure.is_some() {
            break;
        }
        rows.push(IoRow {
            format: format.name(),
            file: name
                .file_name()
                .map(|f| f.to_string_lossy().into_owned())
                .unwrap_or_default(),
            bytes,
            write_ms,
            read_ms: best,
            particles_per_second: n as f64 / (best / 1e3),
        });
    }
    let _ = std::fs::remove_dir_all(&dir);
    if let Some(e) = failure {
        return Err(e.into());
    }
    let report = IoReport {
        particles: n,
        attributes: vec!["id", "velocity", "density"],
        formats: rows,
    };
    if args.json {
        super::print_json(&report);
    } else {
        println!(
            "bench io: {n} particles with id, velocity and density; fastest of {} reads",
            args.repeat.max(1)
        );
        println!("  format      file MB   write ms    read ms   particles/s");
        for r in &report.formats {
            println!(
                "  {:<10} {:>8.1} {:>10.1} {:>10.1} {:>13.0}",
                r.format,
                r.bytes as f64 / 1e6,
                r.write_ms,
                r.read_ms,
                r.particles_per_second
            );
        }
    }
    Ok(())
}

/// Arguments of `bench refine`.
#[derive(clap::Args)]
pub struct BenchRefineArgs {
    /// Timed repetitions per frame and implementation (the fastest is reported).
    #[arg(long, default_value_t = 3)]
    pub repeat: usize,
    /// Print one JSON object instead of text.
    #[arg(long)]
    pub json: bool,
    /// A particle file to refine instead of the column frames: its surface is detected, then
    /// each implementation runs as a `refine` child process of its own, so that the peak memory
    /// of each is measured apart (peak resident set of the child, input and detection included).
    #[arg(long)]
    pub input: Option<std::path::PathBuf>,
    /// Refinement steps with `--input` (the children get the same `--memory-budget`).
    #[arg(long, default_value_t = 4, requires = "input")]
    pub steps: u32,
}

/// One implementation's run on a file (`bench refine --input`).
#[derive(Serialize)]
struct FileRun {
    implementation: &'static str,
    points: u64,
    /// Fastest refinement of the runs, ms (detection and input not included).
    refine_ms: f64,
    /// Peak resident set of the first child, MiB (absent where the system does not report it).
    peak_rss_mib: Option<f64>,
}

/// `bench refine --input`: both implementations on one file, each in its own process.
fn bench_refine_file(args: &BenchRefineArgs, input: &std::path::Path) -> Result<(), Error> {
    let exe = std::env::current_exe().map_err(|e| Error::InvalidArgument {
        argument: "--input",
        reason: format!("cannot find this program to run its refine children: {e}"),
    })?;
    let mut runs = Vec::new();
    for (implementation, flag) in [("parallel", None), ("reference", Some("--reference"))] {
        let mut best: Option<FileRun> = None;
        for _ in 0..args.repeat.max(1) {
            let mut cmd = std::process::Command::new(&exe);
            cmd.arg("refine")
                .arg("--input")
                .arg(input)
                .args(["--steps", &args.steps.to_string()])
                .args([
                    "--memory-budget",
                    &super::memory_budget().to_string(),
                    "--json",
                ])
                .args(flag);
            let out = cmd.output().map_err(|e| Error::InvalidArgument {
                argument: "--input",
                reason: format!("cannot run the refine child: {e}"),
            })?;
            if !out.status.success() {
                return Err(Error::InvalidArgument {
                    argument: "--input",
                    reason: format!(
                        "the {implementation} refinement failed: {}",
                        String::from_utf8_lossy(&out.stderr)
                            .trim()
                            .trim_start_matches("error: ")
                    ),
                });
            }
            let v: serde_json::Value =
                serde_json::from_slice(&out.stdout).map_err(|e| Error::InvalidArgument {
                    argument: "--input",
                    reason: format!("the refine child's report does not parse: {e}"),
                })?;
            let run = FileRun {
                implementation,
                points: v["points"].as_u64().unwrap_or(0),
                refine_ms: v["refine_ms"].as_f64().unwrap_or(f64::NAN),
                peak_rss_mib: v["peak_rss_mib"].as_f64(),
            };
            best = Some(match best {
                Some(b) if b.refine_ms <= run.refine_ms => b,
                Some(b) => FileRun {
                    peak_rss_mib: b.peak_rss_mib,
                    ..run
                },
                None => run,
            });
        }
        runs.extend(best);
    }
    if runs[0].points != runs[1].points {
        return Err(Error::InvalidArgument {
            argument: "--input",
            reason: format!(
                "the implementations disagree: {} against {} points",
                runs[0].points, runs[1].points
            ),
        });
    }
    let report = serde_json::json!({
        "input": input.display().to_string(),
        "steps": args.steps,
        "threads": rayon::current_num_threads(),
        "runs": runs,
        "speedup": runs[1].refine_ms / runs[0].refine_ms,
    });
    if args.json {
        super::print_json(&report);
        return Ok(());
    }
    println!(
        "bench refine: {} in {} steps -> {} points, {} threads, fastest of {}, each in its own process",
        input.display(),
        args.steps,
        runs[0].points,
        rayon::current_num_threads(),
        args.repeat.max(1)
    );
    println!("  implementation   refinement ms   peak RSS MiB (whole process)");
    for r in &runs {
        let rss = r
            .peak_rss_mib
            .map_or_else(|| "not reported".to_string(), |m| format!("{m:.1}"));
        println!("  {:<15} {:>14.1}   {rss}", r.implementation, r.refine_ms);
    }
    println!(
        "  parallel against reference: {:.2}x the speed{}",
        runs[1].refine_ms / runs[0].refine_ms,
        match (runs[0].peak_rss_mib, runs[1].peak_rss_mib) {
            (Some(a), Some(b)) => format!(", {:.2}x the memory", a / b),
            _ => String::new(),
        }
    );
    Ok(())
}

#[derive(Serialize)]
struct RefineRow {
    name: &'static str,
    frame: usize,
    p0: usize,
    p3: usize,
    seconds: f64,
    points_per_second: f64,
    reference_seconds: f64,
    reference_points_per_second: f64,
    speedup: f64,
    /// Milliseconds per phase of the fastest parallel run, summed over its steps.
    phases: fluid_surfels::refine::StepPhases,
}

#[derive(Serialize)]
struct RefineBenchReport {
    threads: usize,
    steps: u32,
    points_per_second_means: &'static str,
    frames: Vec<RefineRow>,
}

/// Refines the surface of three `column` frames like the paper's Table 1 (initial block,
/// splashing, equilibrium) with the parallel and the reference implementation.
pub fn bench_refine(args: &BenchRefineArgs) -> Result<(), Error> {
    use fluid_surfels::refine::{RefineParams, refine, refine_reference};
    if let Some(input) = &args.input {
        return bench_refine_file(args, input);
    }
    use fluid_surfels::scenes::{ColumnParams, ColumnSim};
    let frames = [
        ("initial block", ColumnParams::INITIAL_FRAME),
        ("splashing", ColumnParams::SPLASH_FRAME),
        ("equilibrium", ColumnParams::EQUILIBRIUM_FRAME),
    ];
    let mut sim = ColumnSim::new(ColumnParams::default())?;
    let mut detector = SurfaceDetector::new(SurfaceParams::default())?;
    let mut inputs = Vec::new();
    for f in 0..=ColumnParams::EQUILIBRIUM_FRAME {
        sim.advance_to(f);
        let nb = Neighbourhoods::build(
            &sim.particles().positions,
            sim.support_radius(),
            Backend::CellGrid,
        )?;
        let surface = detector.detect(sim.particles(), &nb)?;
        if let Some((name, _)) = frames.iter().find(|x| x.1 == f) {
            let (p, n) = super::refine::surface_of(sim.particles(), &surface);
            inputs.push((*name, f, p, n));
        }
    }
    let params = RefineParams::with_radius(sim.support_radius());
    let mut rows = Vec::new();
    for (name, frame, p, n) in inputs {
        let mut best = f64::INFINITY;
        let mut best_ref = f64::INFINITY;
        let mut p3 = 0;
        let mut phases = fluid_surfels::refine::StepPhases::default();
        for _ in 0..args.repeat.max(1) {
            let t = Instant::now();
            let r = refine(&p, &n, &params)?;
            let seconds = t.elapsed().as_secs_f64();
            if seconds < best {
                // the phases of the fastest run
                phases = r
                    .stats
                    .iter()
                    .fold(Default::default(), |a, s| s.phases.plus(a));
            }
            best = best.min(seconds);
            p3 = r.len();
            let t = Instant::now();
            let r = refine_reference(&p, &n, &params)?;
            best_ref = best_ref.min(t.elapsed().as_secs_f64());
            assert_eq!(r.len(), p3, "the implementations disagree");
        }
        rows.push(RefineRow {
            name,
            frame,
            p0: p.len(),
            p3,
            seconds: best,
            points_per_second: p3 as f64 / best,
            reference_seconds: best_ref,
            reference_points_per_second: p3 as f64 / best_ref,
            speedup: best_ref / best,
            phases,
        });
    }
    let report = RefineBenchReport {
        threads: rayon::current_num_threads(),
        steps: params.steps,
        points_per_second_means: "P3 / seconds, as the paper's Table 1",
        frames: rows,
    };
    if args.json {
        super::print_json(&report);
    } else {
        println!(
            "bench refine: column frames like Table 1, 3 steps, {} threads, fastest of {}",
            report.threads,
            args.repeat.max(1)
        );
        println!(
            "  frame              P0      P3    parallel s   points/s    reference s   points/s   speedup"
        );
        for r in &report.frames {
            println!(
                "  {:<14} {:>6} {:>7}   {:>9.4} {:>10.0}   {:>11.4} {:>10.0}   {:>6.2}x",
                r.name,
                r.p0,
                r.p3,
                r.seconds,
                r.points_per_second,
                r.reference_seconds,
                r.reference_points_per_second,
                r.speedup
            );
        }
        println!("  (points/s = P3 / seconds, as in the paper's Table 1)");
        println!(
            "  the parallel run's phases, ms over its steps: candidates | type 2 checks + registration lists | type 3 rivals (parallel) + decisions (sequential) | update: moves (sequential) + neighbourhoods"
        );
        for r in &report.frames {
            let p = r.phases;
            println!(
                "  {:<14} {:>8.1} {:>8.1} {:>8.1} {:>8.1} = {:.1} + {:.1}",
                r.name,
                p.candidates_ms,
                p.type2_ms,
                p.accept_ms,
                p.update_ms,
                p.moves_ms,
                p.update_ms - p.moves_ms
            );
        }
    }
    Ok(())
}

/// Arguments of `bench density`.
#[derive(clap::Args)]
pub struct BenchDensityArgs {
    /// Number of particles (a block filling the lower half of a cubic box, h = 2 spacings).
    #[arg(long, default_value_t = 150_000)]
    pub particles: usize,
    /// Grid points along each axis of the box.
    #[arg(long, default_value_t = 256)]
    pub resolution: u32,
    /// Skip the naive single-threaded reference (seconds at the default size).
    #[arg(long)]
    pub no_naive: bool,
    /// Print one JSON object instead of text.
    #[arg(long)]
    pub json: bool,
}

#[derive(Serialize)]
struct DensityBenchReport {
    particles: usize,
    resolution: u32,
    grid: [u32; 3],
    h: f32,
    threads: usize,
    cpu_density_ms: f64,
    cpu_extract_ms: Option<f64>,
    /// The sparse grid (`density::points_grid_sparse`), its LNM band included (`band_ms` of
    /// it), and the extraction from it, in the same run.
    cpu_sparse_ms: f64,
    band_ms: f64,
    sparse_extract_ms: f64,
    /// Its blocks of 8^3 points: empty, inside (not evaluated) and evaluated.
    sparse_blocks: [usize; 3],
    sparse_evaluated_points: usize,
    sparse_bytes: usize,
    /// Every evaluated value equals the dense grid's bit for bit.
    sparse_equals_dense: bool,
    /// The surfels from the sparse grid equal the dense grid's (same order).
    sparse_same_surfels: bool,
    /// GPU time of the default method (`gpu_method`).
    gpu_density_ms: Option<f64>,
    gpu_method: Option<fluid_surfels::density::gpu::GpuDensityMethod>,
    /// The paper's slice splatting.
    gpu_splat_ms: Option<f64>,
    /// The compute-shader gather.
    gpu_gather_ms: Option<f64>,
    /// Largest difference of either GPU method from the CPU grid, relative to the peak.
    gpu_difference_from_cpu: Option<f32>,
    gpu_adapter: Option<String>,
    naive_density_ms: Option<f64>,
    speedup_over_naive: Option<f64>,
    max_difference_from_naive: Option<f32>,
    surfels: Option<usize>,
}

/// The paper's case by default: 150,000 particles of a water body into a 256^3 grid.
pub fn bench_density(args: &BenchDensityArgs) -> Result<(), Error> {
    use fluid_surfels::density::{self, GridSpec, Kernel, Resolution};
    // a block filling the lower half of the unit box: side n, height n/2
    let side = ((2 * args.particles.max(1)) as f64).cbrt().round().max(2.0) as u32;
    let s = 1.0 / side as f32;
    let mut positions = Vec::with_capacity(args.particles);
    'fill: for k in 0..side {
        for j in 0..side {
            for i in 0..side {
                if positions.len() == args.particles {
                    break 'fill;
                }
                positions.push((glam::Vec3::new(i as f32, k as f32, j as f32) + 0.5) * s);
            }
        }
    }
    let h = 2.0 * s;
    let spec = GridSpec::for_box(
        glam::Vec3::ZERO,
        glam::Vec3::ONE,
        Resolution::LongestAxis(args.resolution),
    )?;
    let limit = io::available_memory();
    // one untimed run warms caches and the thread pool
    let _ = density::density_grid(
        &positions[..positions.len().min(1000)],
        &spec,
        Kernel::Wyvill,
        h,
        limit,
    )?;
    let t = Instant::now();
    let grid = density::density_grid(&positions, &spec, Kernel::Wyvill, h, limit)?;
    let cpu = ms(t);
    // the sparse grid: the band, the blocks, the evaluated ones; then its surfels
    let iso_params = fluid_surfels::surfels::SurfelParams::default();
    let iso = iso_params.iso_fraction * Kernel::Wyvill.peak(h);
    let t = Instant::now();
    let band = fluid_surfels::lnm::narrow_band(&positions, h, &Default::default())?;
    let band_ms = ms(t);
    let sparse = density::points_grid_sparse(
        density::Points::uniform(&positions, h),
        &spec,
        Kernel::Wyvill,
        limit,
        &band,
        iso,
        2.0 * iso,
    )?;
    let cpu_sparse_ms = ms(t);
    let t = Instant::now();
    let sparse_surfels = fluid_surfels::surfels::extract_sparse(
        &sparse,
        density::Points::uniform(&positions, h),
        Kernel::Wyvill,
        &iso_params,
    )?;
    let sparse_extract_ms = ms(t);
    let [nx, ny, _] = spec.dims;
    let sparse_equals_dense = sparse.evaluated_blocks().all(|b| {
        let values = sparse.block_values(b).expect("evaluated");
        (0..values.len()).all(|l| {
            use fluid_surfels::density::sparse::BLOCK;
            let n = BLOCK as usize;
            let p = [l % n, (l / n) % n, l / (n * n)].map(|v| v as u32);
            let (i, j, k) = (
                b[0] * BLOCK + p[0],
                b[1] * BLOCK + p[1],
                b[2] * BLOCK + p[2],
            );
            i >= nx
                || j >= ny
                || k >= spec.dims[2]
                || !sparse.is_evaluated(i, j, k)
                || values[l].to_bits() == grid.at(i, j, k).to_bits()
        })
    });
    let (empty_blocks, inside_blocks, evaluated_blocks) = sparse.counts();
    let sparse_points = sparse.evaluated_points();
    let sparse_bytes = sparse.bytes();
    drop(sparse);
    // the GPU path, when an adapter exists: one untimed run (pipeline creation, shader
    // compilation), then the timed one
    // the GPU paths, when an adapter exists: one untimed run each (pipeline creation, shader
    // compilation), then the timed one
    let gpu = match fluid_surfels::gpu::GpuContext::headless() {
        Ok(ctx) => {
            use fluid_surfels::density::Points;
            use fluid_surfels::density::gpu::{GpuDensityMethod, density_grid_gpu_with};
            let max = grid.max().max(f32::MIN_POSITIVE);
            let mut timed = Vec::new();
            for method in [GpuDensityMethod::Splat, GpuDensityMethod::Gather] {
                let few = &positions[..positions.len().min(1000)];
                let _ = density_grid_gpu_with(
                    &ctx,
                    Points::uniform(few, h),
                    &spec,
                    Kernel::Wyvill,
                    method,
                )?;
                let t = Instant::now();
                let g = density_grid_gpu_with(
                    &ctx,
                    Points::uniform(&positions, h),
                    &spec,
                    Kernel::Wyvill,
                    method,
                )?;
                let gpu_ms = ms(t);
                let diff = g
                    .values
                    .iter()
                    .zip(&grid.values)
                    .map(|(a, b)| (a - b).abs())
                    .fold(0.0f32, f32::max)
                    / max;
                timed.push((method, gpu_ms, diff));
            }
            Some((timed, ctx.adapter.map(|a| a.name).unwrap_or_default()))
        }
        Err(e) => {
            if !args.json {
                println!("  (no GPU: {e})");
            }
            None
        }
    };
    let default_gpu = gpu.as_ref().and_then(|(t, _)| {
        t.iter()
            .find(|x| x.0 == fluid_surfels::density::gpu::GpuDensityMethod::default())
            .copied()
    });
    let gpu_ms_of = |m: fluid_surfels::density::gpu::GpuDensityMethod| {
        gpu.as_ref()
            .and_then(|(t, _)| t.iter().find(|x| x.0 == m).map(|x| x.1))
    };
    let t = Instant::now();
    let surfels = fluid_surfels::surfels::extract(
        &grid,
        &positions,
        Kernel::Wyvill,
        h,
        &fluid_surfels::surfels::SurfelParams::default(),
    )?;
    let extract_ms = ms(t);
    let sparse_same_surfels = sparse_surfels == surfels;
    let (naive_ms, diff) = if args.no_naive {
        (None, None)
    } else {
        let t = Instant::now();
        let naive = density::density_naive(&positions, &spec, Kernel::Wyvill, h)?;
        let naive_ms = ms(t);
        let diff = naive
            .values
            .iter()
            .zip(&grid.values)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        (
            Some(naive_ms),
            Some(diff / naive.max().max(f32::MIN_POSITIVE)),
        )
    };
    let report = DensityBenchReport {
        particles: positions.len(),
        resolution: args.resolution,
        grid: spec.dims,
        h,
        threads: rayon::current_num_threads(),
        cpu_density_ms: cpu,
        cpu_extract_ms: Some(extract_ms),
        cpu_sparse_ms,
        band_ms,
        sparse_extract_ms,
        sparse_blocks: [empty_blocks, inside_blocks, evaluated_blocks],
        sparse_evaluated_points: sparse_points,
        sparse_bytes,
        sparse_equals_dense,
        sparse_same_surfels,
        gpu_density_ms: default_gpu.map(|g| g.1),
        gpu_method: default_gpu.map(|g| g.0),
        gpu_splat_ms: gpu_ms_of(fluid_surfels::density::gpu::GpuDensityMethod::Splat),
        gpu_gather_ms: gpu_ms_of(fluid_surfels::density::gpu::GpuDensityMethod::Gather),
        gpu_difference_from_cpu: gpu
            .as_ref()
            .map(|(t, _)| t.iter().map(|x| x.2).fold(0.0f32, f32::max)),
        gpu_adapter: gpu.as_ref().map(|g| g.1.clone()),
        naive_density_ms: naive_ms,
        speedup_over_naive: naive_ms.map(|n| n / cpu),
        max_difference_from_naive: diff,
        surfels: Some(surfels.len()),
    };
    if args.json {
        super::print_json(&report);
    } else {
        println!(
            "bench density: {} particles (block filling the lower half of a cubic box), h = {h:.5}, grid {:?}, {} threads",
            report.particles, report.grid, report.threads
        );
        println!("  CPU (z-clustered slabs, parallel)  {cpu:>9.1} ms");
        println!(
            "  CPU sparse blocks (8^3, LNM band)  {cpu_sparse_ms:>9.1} ms   ratio {:.2}x ({band_ms:.1} ms of it the band); blocks {empty_blocks} empty, {inside_blocks} inside, {evaluated_blocks} evaluated ({:.1} % of the grid's points, {:.1} MiB against {:.1}), {}",
            cpu / cpu_sparse_ms,
            100.0 * sparse_points as f64 / spec.cells() as f64,
            sparse_bytes as f64 / (1u64 << 20) as f64,
            spec.bytes() as f64 / (1u64 << 20) as f64,
            if sparse_equals_dense {
                "every evaluated value the dense one's"
            } else {
                "DIFFERENT from the dense grid"
            }
        );
        if let (Some(n), Some(d)) = (naive_ms, diff) {
            println!(
                "  naive reference (one thread)       {n:>9.1} ms   ratio {:.1}x, max difference {d:e} of the peak",
                n / cpu
            );
        }
        println!(
            "  surfel extraction (CPU)            {extract_ms:>9.1} ms   {} surfels",
            surfels.len()
        );
        println!(
            "  surfel extraction, sparse          {sparse_extract_ms:>9.1} ms   ratio {:.2}x, {}",
            extract_ms / sparse_extract_ms,
            if sparse_same_surfels {
                "the same surfels"
            } else {
                "DIFFERENT surfels"
            }
        );
        if let Some((timed, name)) = &gpu {
            for (method, g, d) in timed {
                println!(
                    "  GPU {method:?} ({name})  {g:>9.1} ms   ratio to CPU {:.2}x, max difference {d:e} of the peak",
                    cpu / g
                );
            }
        }
    }
    Ok(())
}

/// Options the GPU-against-CPU benchmarks (`splat`, `optics`) share.
#[derive(clap::Args)]
pub struct GpuBenchRun {
    /// Timed GPU frames (the median is reported), after one untimed frame.
    #[arg(long, default_value_t = 5)]
    pub repeat: usize,
    /// Skip the CPU reference.
    #[arg(long)]
    pub no_cpu: bool,
    /// Print one JSON object instead of text.
    #[arg(long)]
    pub json: bool,
}

/// Arguments of `bench splat`.
#[derive(clap::Args)]
pub struct BenchSplatArgs {
    /// Number of surfels (a sphere of surfels filling most of the image; half face the camera).
    #[arg(long, default_value_t = 1_000_000)]
    pub surfels: usize,
    /// Image size, WIDTHxHEIGHT (default: 1920x1080, the goal's case).
    #[arg(long, default_value = "1920x1080", value_parser = super::render::parse_size)]
    pub size: (u32, u32),
    /// What the surfels are drawn as: ewa (EWA splats), sprites, or spheres (particle
    /// splatting, Adams et al. 2006: each surfel's centre and radius as a sphere).
    #[arg(long, value_enum, default_value = "ewa")]
    pub mode: ModeChoice,
    #[command(flatten)]
    pub run: GpuBenchRun,
}

/// `bench splat --mode`.
#[derive(Clone, Copy, clap::ValueEnum)]
pub enum ModeChoice {
    Ewa,
    Sprites,
    Spheres,
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
    use fluid_surfels::splat::SplatMode;
    use fluid_surfels::splat::gpu::{SplatRenderer, render_timed};
    use fluid_surfels::splat::{self, Light, SplatParams, View};
    let (width, height) = args.size;
    let surfels = fluid_surfels::scenes::surfel_sphere(args.surfels);
    let camera = fluid_surfels::scenes::surfel_sphere_camera();
    let mode = match args.mode {
        ModeChoice::Ewa => SplatMode::Ewa,
        ModeChoice::Sprites => SplatMode::Sprites,
        ModeChoice::Spheres => SplatMode::Spheres,
    };
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
        super::print_json(&report);
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

/// Arguments of `bench optics`.
#[derive(clap::Args)]
pub struct BenchOpticsArgs {
    /// Surfel counts of the wave tank (the paper's animation had 55,000 to 120,000).
    #[arg(long, value_delimiter = ',', default_values_t = [55_000usize, 120_000])]
    pub surfels: Vec<usize>,
    /// Final image size (the paper's 512x512).
    #[arg(long, default_value = "512x512", value_parser = super::render::parse_size)]
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
        super::print_json(&report);
    } else {
        println!(
            "adapter: {}; CPU reference on {} threads",
            report.adapter.as_deref().unwrap_or("none"),
            report.threads
        );
    }
    Ok(())
}

/// Arguments of `bench pipeline`.
#[derive(clap::Args)]
pub struct BenchPipelineArgs {
    /// Frame of the column scene (default: the splash).
    #[arg(long, default_value_t = fluid_surfels::scenes::ColumnParams::SPLASH_FRAME)]
    pub frame: usize,
    /// Image size of the finished frame.
    #[arg(long, default_value = "512x512", value_parser = super::render::parse_size)]
    pub size: (u32, u32),
    /// Timed frames (the median is reported), after the frames of the simulation up to it.
    #[arg(long, default_value_t = 5)]
    pub repeat: usize,
    /// Print one JSON object instead of text.
    #[arg(long)]
    pub json: bool,
}

#[derive(Serialize)]
struct PipelineBenchReport {
    frame: usize,
    particles: usize,
    surfels: usize,
    size: [u32; 2],
    threads: usize,
    repeat: usize,
    /// Median and fastest of the whole chain (detection to the finished frame), ms.
    median_ms: f64,
    fastest_ms: f64,
    /// The stages of the median frame.
    stages_ms: fluid_surfels::pipeline::FrameTimings,
    goal_ms: f64,
}

/// The CPU `Pipeline` on one frame of the column scene: the whole chain with optics, repeated on
/// the same particles (the hysteresis is that of a sequence that stays on the frame).
pub fn bench_pipeline(args: &BenchPipelineArgs) -> Result<(), Error> {
    use fluid_surfels::pipeline::Through;
    let mut params = super::run::column_params(SurfaceParams::default());
    params.scene.optics.image_size = [args.size.0, args.size.1];
    let mut sim = fluid_surfels::scenes::ColumnSim::new(Default::default())?;
    let mut pipeline =
        fluid_surfels::pipeline::Pipeline::new(fluid_surfels::pipeline::PipelineParams {
            support_radius: Some(sim.support_radius()),
            ..params
        })?;
    // detection on every frame up to this one (the hysteresis of a real run), then one untimed
    // whole frame: the views are fitted, the thread pool is warm
    let first = fluid_surfels::pipeline::column_frame(
        &mut pipeline,
        &mut sim,
        args.frame,
        Through::Frame,
        |_| {},
    )?;
    pipeline.recycle(first);
    let particles = sim.particles().clone();
    let mut runs = Vec::new();
    for _ in 0..args.repeat.max(1) {
        let f = pipeline.frame(&particles)?;
        runs.push((f.timings.total_ms, f.timings, f.render_surfels.len()));
        pipeline.recycle(f);
    }
    runs.sort_by(|a, b| a.0.total_cmp(&b.0));
    let (median_ms, stages_ms, surfels) = runs[runs.len() / 2];
    let report = PipelineBenchReport {
        frame: args.frame,
        particles: particles.len(),
        surfels,
        size: [args.size.0, args.size.1],
        threads: rayon::current_num_threads(),
        repeat: runs.len(),
        median_ms,
        fastest_ms: runs[0].0,
        stages_ms,
        goal_ms: 100.0,
    };
    if args.json {
        super::print_json(&report);
    } else {
        let t = &report.stages_ms;
        println!(
            "pipeline (CPU), column frame {}: {} particles -> {} surfels -> {}x{} frame, {} threads",
            report.frame,
            report.particles,
            report.surfels,
            args.size.0,
            args.size.1,
            report.threads
        );
        println!(
            "  median {:.1} ms (fastest {:.1} of {}; goal {:.0} ms)",
            report.median_ms, report.fastest_ms, report.repeat, report.goal_ms
        );
        println!(
            "  neighbours {:.1}, detection {:.1}, refinement {:.1}, density {:.1}, surfels {:.1}, caustics {:.1}, image {:.1}",
            t.neighbours_ms,
            t.detect_ms,
            t.refine_ms,
            t.density_ms,
            t.surfels_ms,
            t.caustics_ms,
            t.image_ms
        );
    }
    Ok(())
}

/// The frame a bench draws: a file or the column scene's splash frame, resampled on request.
#[derive(clap::Args)]
pub struct BenchFrame {
    /// Particle file (default: the column scene's splash frame).
    #[arg(long)]
    pub input: Option<PathBuf>,
    /// Format of --input (default: from its extension).
    #[arg(long, value_parser = super::format_parser())]
    pub format: Option<Format>,
    /// Resample the particles to about this many first: the same body on a finer lattice
    /// (`scenes::resample`; e.g. 100000 on ../shared/data's double dam break frame).
    #[arg(long)]
    pub particles: Option<usize>,
    /// Support radius (default: the scene's, or twice the spacing estimated from the file),
    /// before any resampling.
    #[arg(long)]
    pub radius: Option<f32>,
}

impl BenchFrame {
    /// The frame's description, particles and support radius (after any resampling).
    fn read(&self) -> Result<(String, fluid_surfels::ParticleSet, f32), Error> {
        let (mut source, mut positions, mut radius) = super::positions_of(
            self.input.as_deref(),
            self.input.is_none().then_some(super::SceneName::Column),
            self.format,
            None,
            self.radius,
        )?;
        if let Some(n) = self.particles {
            let (fine, h) = scenes::resample(&positions, radius, n)?;
            source = format!("{source}, resampled from {} particles", positions.len());
            positions = fine;
            radius = h;
        }
        let set = fluid_surfels::ParticleSet::from_positions(positions);
        set.validate()?;
        Ok((source, set, radius))
    }
}

/// The adapter a bench runs its GPU twins on: any, a software one too (a bench measures what it
/// is asked), none with `no_gpu` or when none is found (said unless `json`).
fn bench_context(no_gpu: bool, json: bool) -> Option<fluid_surfels::gpu::GpuContext> {
    if no_gpu {
        return None;
    }
    match fluid_surfels::gpu::GpuContext::headless() {
        Ok(ctx) => Some(ctx),
        Err(e) => {
            if !json {
                println!("  (no GPU: {e})");
            }
            None
        }
    }
}

/// Arguments of `bench renderers`.
#[derive(clap::Args)]
pub struct BenchRenderersArgs {
    #[command(flatten)]
    pub frame: BenchFrame,
    /// Image size, WIDTHxHEIGHT.
    #[arg(long, default_value = "1024x1024", value_parser = super::render::parse_size)]
    pub size: (u32, u32),
    /// Where the drawn surfels or points come from (as `render --source`).
    #[arg(long, value_enum, default_value = "chain")]
    pub source: super::render::SourceChoice,
    /// The renderers to time, comma-separated.
    #[arg(
        long,
        value_enum,
        value_delimiter = ',',
        default_value = "ewa,particle-splat,ray-cast"
    )]
    pub renderers: Vec<super::render::RendererChoice>,
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

/// The median of `repeat` timed runs of `run` (after one untimed one when `repeat` > 1, so a
/// single long run is not paid twice), and the first result.
fn median_of<T>(
    repeat: usize,
    mut run: impl FnMut() -> Result<T, Error>,
) -> Result<(f64, T), Error> {
    let mut times = Vec::new();
    let first = if repeat > 1 {
        run()?
    } else {
        let t = Instant::now();
        let r = run()?;
        times.push(ms(t));
        r
    };
    while times.len() < repeat.max(1) {
        let t = Instant::now();
        run()?;
        times.push(ms(t));
    }
    times.sort_by(f64::total_cmp);
    Ok((times[times.len() / 2], first))
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
    let bar = super::progress(args.renderers.len() as u64, "renderers");
    for &choice in &args.renderers {
        let renderer = Renderer::from(choice);
        let mut pipeline = Pipeline::new(PipelineParams {
            support_radius: Some(radius),
            renderer,
            source: args.source.into(),
            ..Default::default()
        })?;
        let t = Instant::now();
        let frame = pipeline.frame_through(&set, Through::Surfels)?;
        let prepare_ms = ms(t);
        let surfels = &frame.render_surfels;
        let camera = super::render::framing(surfels);
        let params = pipeline.splat_params();
        let (points, radii) = pipeline::sphere_points(surfels);
        let caster = (renderer == Renderer::RayCast)
            .then(|| pipeline.caster(&points, &radii))
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
        surfel_source: fluid_surfels::pipeline::SurfelSource::from(args.source).as_str(),
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
        super::print_json(&report);
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

/// Arguments of `bench lnm`.
#[derive(clap::Args)]
pub struct BenchLnmArgs {
    /// Particles (a jittered block, support radius two spacings).
    #[arg(long, default_value_t = 1_000_000)]
    pub particles: usize,
    /// Timed runs (the median is reported), after one untimed.
    #[arg(long, default_value_t = 5)]
    pub repeat: usize,
    /// CPU only. Otherwise any adapter runs the GPU twin too (`lnm::gpu`, a dense grid), a
    /// software one included.
    #[arg(long)]
    pub no_gpu: bool,
    /// Print one JSON object instead of text.
    #[arg(long)]
    pub json: bool,
}

#[derive(Serialize)]
struct LnmBenchReport {
    particles: usize,
    band: usize,
    band_share: f64,
    voxels: usize,
    layer_1_voxels: usize,
    layer_2_voxels: usize,
    threads: usize,
    median_ms: f64,
    /// The layout the automatic choice took (dense or sparse).
    layout: &'static str,
    /// The same on one thread, in the same run.
    one_thread_ms: f64,
    speedup_over_one_thread: f64,
    /// The sparse layout (sorted keys, hashed neighbours) on all threads, in the same run: the
    /// reference the dense one is measured against (the same band, bit for bit).
    sparse_ms: f64,
    /// The GPU twin with its upload and read-back, and its adapter.
    gpu_ms: Option<f64>,
    adapter: Option<String>,
    /// Whether its labels and voxels equal the CPU's.
    gpu_equals_cpu: Option<bool>,
}

/// The narrow band of the Layered Neighborhood Method (`lnm::narrow_band`) on a block, on all
/// threads and on one.
pub fn bench_lnm(args: &BenchLnmArgs) -> Result<(), Error> {
    use fluid_surfels::lnm::{LnmParams, narrow_band};
    let block = scenes::BlockParams::with_particles(args.particles);
    let h = 2.0 * block.spacing;
    let scene = scenes::block(&block)?;
    let p = &scene.particles.positions;
    let params = LnmParams::default();
    let (median_ms, band) = median_of(args.repeat, || Ok(narrow_band(p, h, &params)?))?;
    let one = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .map_err(|e| Error::InvalidArgument {
            argument: "threads",
            reason: e.to_string(),
        })?;
    let (one_thread_ms, _) =
        one.install(|| median_of(args.repeat, || Ok(narrow_band(p, h, &params)?)))?;
    let (sparse_ms, sparse) = median_of(args.repeat, || {
        Ok(fluid_surfels::lnm::narrow_band_in(
            p,
            h,
            &params,
            fluid_surfels::lnm::Layout::Sparse,
        )?)
    })?;
    if sparse != band {
        return Err(Error::InvalidArgument {
            argument: "bench lnm",
            reason:
                "the dense and sparse layouts gave different bands (a defect: please report it)"
                    .into(),
        });
    }
    let total = band.dims.iter().map(|&d| u64::from(d)).product::<u64>();
    let layout = match fluid_surfels::lnm::cpu::auto_layout(total, p.len()) {
        fluid_surfels::lnm::Layout::Dense => "dense",
        _ => "sparse",
    };
    let ctx = if args.no_gpu {
        None
    } else {
        fluid_surfels::gpu::GpuContext::headless().ok()
    };
    let gpu = match &ctx {
        Some(ctx) => Some(median_of(args.repeat, || {
            fluid_surfels::lnm::gpu::narrow_band_gpu(ctx, p, h, &params)
        })?),
        None => None,
    };
    let layer = |l: u8| band.voxels.iter().filter(|v| v.label == l).count();
    let report = LnmBenchReport {
        particles: p.len(),
        band: band.len(),
        band_share: band.len() as f64 / p.len().max(1) as f64,
        voxels: band.voxels.len(),
        layer_1_voxels: layer(1),
        layer_2_voxels: layer(2),
        threads: rayon::current_num_threads(),
        median_ms,
        layout,
        one_thread_ms,
        speedup_over_one_thread: one_thread_ms / median_ms,
        sparse_ms,
        gpu_ms: gpu.as_ref().map(|g| g.0),
        adapter: ctx
            .as_ref()
            .and_then(|c| c.adapter.as_ref().map(|a| a.name.clone())),
        gpu_equals_cpu: gpu
            .as_ref()
            .map(|g| g.1.labels == band.labels && g.1.voxel_of == band.voxel_of),
    };
    if args.json {
        super::print_json(&report);
    } else {
        println!(
            "bench lnm: {} particles in a block, {} voxels (layer 1 {}, layer 2 {}), band {} ({:.1} %)",
            report.particles,
            report.voxels,
            report.layer_1_voxels,
            report.layer_2_voxels,
            report.band,
            100.0 * report.band_share
        );
        println!(
            "  {:.1} ms on {} threads ({} voxels), {:.1} ms on one ({:.2}x); sparse layout {:.1} ms ({:.2}x the dense), median of {}",
            report.median_ms,
            report.threads,
            report.layout,
            report.one_thread_ms,
            report.speedup_over_one_thread,
            report.sparse_ms,
            report.sparse_ms / report.median_ms,
            args.repeat.max(1)
        );
        if let (Some(g), Some(a)) = (report.gpu_ms, &report.adapter) {
            println!(
                "  GPU ({a}): {g:.1} ms with upload and read-back, {:.2}x the CPU; labels {}",
                g / report.median_ms,
                if report.gpu_equals_cpu == Some(true) {
                    "equal to the CPU's"
                } else {
                    "DIFFER from the CPU's"
                }
            );
        }
    }
    Ok(())
}

/// Arguments of `bench ssfr`.
#[derive(clap::Args)]
pub struct BenchSsfrArgs {
    #[command(flatten)]
    pub frame: BenchFrame,
    /// Image size, WIDTHxHEIGHT (default full HD, the paper's).
    #[arg(long, default_value = "1920x1080", value_parser = super::render::parse_size)]
    pub size: (u32, u32),
    /// The depth filters to time, comma-separated.
    #[arg(
        long,
        value_enum,
        value_delimiter = ',',
        default_value = "narrow-range,bilateral,plane,curvature-flow"
    )]
    pub filters: Vec<super::render::FilterChoice>,
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
    let camera = super::render::framing(&spheres);
    let (w, h) = args.size;
    let view = View::new(&camera, &Light::default(), &SplatParams::default(), w, h)?;
    let ctx = bench_context(args.no_gpu, args.json);
    let mut gpu = match &ctx {
        Some(c) => Some(fluid_surfels::ssfr::gpu::GpuSsfr::new(&c.device)?),
        None => None,
    };
    let mut rows = Vec::new();
    let (mut band, mut voxels) = (p.len(), 0);
    let bar = super::progress(2 * args.filters.len() as u64, "filters");
    for &choice in &args.filters {
        let mut all_image = None;
        for narrow_band in [false, true] {
            let params = SsfrParams {
                filter: choice.into(),
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
        super::print_json(&report);
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
