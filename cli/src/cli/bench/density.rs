//! `bench density`: the density grid (dense, sparse, GPU) and the surfel extraction.

use std::time::Instant;

use fluid_surfels::Error;
use fluid_surfels::io::{self};
use serde::Serialize;

use crate::cli::ms;

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

/// Each GPU method's time in ms and its largest relative difference from the CPU, with the
/// adapter's name.
type GpuTimes = (
    Vec<(fluid_surfels::density::gpu::GpuDensityMethod, f64, f32)>,
    String,
);

/// `particles` points of a block filling the lower half of the unit box (side n, height n/2),
/// and the support radius (two spacings).
fn block_positions(particles: usize) -> (Vec<glam::Vec3>, f32) {
    // a block filling the lower half of the unit box: side n, height n/2
    let side = ((2 * particles.max(1)) as f64).cbrt().round().max(2.0) as u32;
    let s = 1.0 / side as f32;
    let mut positions = Vec::with_capacity(particles);
    'fill: for k in 0..side {
        for j in 0..side {
            for i in 0..side {
                if positions.len() == particles {
                    break 'fill;
                }
                positions.push((glam::Vec3::new(i as f32, k as f32, j as f32) + 0.5) * s);
            }
        }
    }
    let h = 2.0 * s;
    (positions, h)
}

/// Whether every evaluated value of the sparse grid is the dense grid's, bit for bit.
fn sparse_equals_dense(
    sparse: &fluid_surfels::density::SparseGrid,
    grid: &fluid_surfels::density::DensityGrid,
    spec: &fluid_surfels::density::GridSpec,
) -> bool {
    let [nx, ny, _] = spec.dims;
    sparse.evaluated_blocks().all(|b| {
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
    })
}

/// Each GPU method's time on `positions` (after an untimed run on a few) and its largest
/// difference from the CPU's `grid`, relative to the grid's peak.
fn time_gpu(
    ctx: &fluid_surfels::gpu::GpuContext,
    positions: &[glam::Vec3],
    h: f32,
    spec: &fluid_surfels::density::GridSpec,
    grid: &fluid_surfels::density::DensityGrid,
) -> Result<Vec<(fluid_surfels::density::gpu::GpuDensityMethod, f64, f32)>, Error> {
    use fluid_surfels::density::Kernel;
    use fluid_surfels::density::Points;
    use fluid_surfels::density::gpu::{GpuDensityMethod, density_grid_gpu_with};
    let max = grid.max().max(f32::MIN_POSITIVE);
    let mut timed = Vec::new();
    for method in [GpuDensityMethod::Splat, GpuDensityMethod::Gather] {
        let few = &positions[..positions.len().min(1000)];
        let _ = density_grid_gpu_with(ctx, Points::uniform(few, h), spec, Kernel::Wyvill, method)?;
        let t = Instant::now();
        let g = density_grid_gpu_with(
            ctx,
            Points::uniform(positions, h),
            spec,
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
    Ok(timed)
}

/// The paper's case by default: 150,000 particles of a water body into a 256^3 grid.
pub fn bench_density(args: &BenchDensityArgs) -> Result<(), Error> {
    use fluid_surfels::density::{self, GridSpec, Kernel, Resolution};
    let (positions, h) = block_positions(args.particles);
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
    let sparse_equals_dense = sparse_equals_dense(&sparse, &grid, &spec);
    let (empty_blocks, inside_blocks, evaluated_blocks) = sparse.counts();
    let sparse_points = sparse.evaluated_points();
    let sparse_bytes = sparse.bytes();
    drop(sparse);
    // the GPU paths, when an adapter exists: one untimed run each (pipeline creation, shader
    // compilation), then the timed one
    let gpu = match fluid_surfels::gpu::GpuContext::headless() {
        Ok(ctx) => {
            let timed = time_gpu(&ctx, &positions, h, &spec, &grid)?;
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
        crate::cli::print_json(&report);
    } else {
        print_text(&report, &spec, gpu.as_ref());
    }
    Ok(())
}

/// The bench's text report: each path's time, the ratios, the sizes, and each GPU method's.
fn print_text(
    report: &DensityBenchReport,
    spec: &fluid_surfels::density::GridSpec,
    gpu: Option<&GpuTimes>,
) {
    let cpu = report.cpu_density_ms;
    println!(
        "bench density: {} particles (block filling the lower half of a cubic box), h = {:.5}, grid {:?}, {} threads",
        report.particles, report.h, report.grid, report.threads
    );
    println!(
        "  CPU (z-clustered slabs, parallel)  {:>9.1} ms",
        report.cpu_density_ms
    );
    println!(
        "  CPU sparse blocks (8^3, LNM band)  {:>9.1} ms   ratio {:.2}x ({:.1} ms of it the band); blocks {} empty, {} inside, {} evaluated ({:.1} % of the grid's points, {:.1} MiB against {:.1}), {}",
        report.cpu_sparse_ms,
        cpu / report.cpu_sparse_ms,
        report.band_ms,
        report.sparse_blocks[0],
        report.sparse_blocks[1],
        report.sparse_blocks[2],
        100.0 * report.sparse_evaluated_points as f64 / spec.cells() as f64,
        report.sparse_bytes as f64 / (1u64 << 20) as f64,
        spec.bytes() as f64 / (1u64 << 20) as f64,
        if report.sparse_equals_dense {
            "every evaluated value the dense one's"
        } else {
            "DIFFERENT from the dense grid"
        }
    );
    if let (Some(n), Some(d)) = (report.naive_density_ms, report.max_difference_from_naive) {
        println!(
            "  naive reference (one thread)       {n:>9.1} ms   ratio {:.1}x, max difference {d:e} of the peak",
            n / cpu
        );
    }
    println!(
        "  surfel extraction (CPU)            {:>9.1} ms   {} surfels",
        report.cpu_extract_ms.unwrap_or(0.0),
        report.surfels.unwrap_or(0)
    );
    println!(
        "  surfel extraction, sparse          {:>9.1} ms   ratio {:.2}x, {}",
        report.sparse_extract_ms,
        report.cpu_extract_ms.unwrap_or(0.0) / report.sparse_extract_ms,
        if report.sparse_same_surfels {
            "the same surfels"
        } else {
            "DIFFERENT surfels"
        }
    );
    if let Some((timed, name)) = gpu {
        for (method, g, d) in timed {
            println!(
                "  GPU {method:?} ({name})  {g:>9.1} ms   ratio to CPU {:.2}x, max difference {d:e} of the peak",
                cpu / g
            );
        }
    }
}
