//! `bench detect`: the neighbour search and surface detection on a block scene, against the reference implementations.

use std::time::Instant;

use fluid_surfels::Error;
use fluid_surfels::neighbours::{self, Backend, Neighbourhoods};
use fluid_surfels::scenes;
use fluid_surfels::surface::{self, SurfaceDetector, SurfaceParams};
use serde::Serialize;

use super::median;
use crate::cli::ms;

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
        crate::cli::print_json(&report);
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
