//! Benchmarks users can run, one file per `bench` subcommand; what they share (the median,
//! the GPU options, the frame a renderer bench draws, the context) is here.

use std::path::PathBuf;
use std::time::Instant;

use fluid_surfels::io::Format;
use fluid_surfels::{Error, scenes};

use super::ms;

mod density;
mod detect;
mod io;
mod lnm;
mod optics;
mod pipeline;
mod refine;
mod renderers;
mod splat;
mod ssfr;

pub use density::*;
pub use detect::*;
pub use io::*;
pub use lnm::*;
pub use optics::*;
pub use pipeline::*;
pub use refine::*;
pub use renderers::*;
pub use splat::*;
pub use ssfr::*;

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
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
