//! `bench lnm`: the narrow band, sparse, dense and on the GPU.

use fluid_surfels::Error;
use fluid_surfels::scenes;
use serde::Serialize;

use super::median_of;

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
        crate::cli::print_json(&report);
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
