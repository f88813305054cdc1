//! Criterion benchmarks of neighbour search (cell grid vs kiddo) and surface detection.
//!
//! Size: 100,000 particles (a 46^3 jittered block, r = 2 spacings, about 28 neighbours each),
//! large enough that both threads are busy and caches are exceeded, small enough for criterion's
//! repeated sampling on a 2-core machine. `fluid-surfels bench detect` runs the 1,000,000 case.

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use fluid_surfels::neighbours::{Backend, Neighbourhoods, reference_neighbours};
use fluid_surfels::scenes::{BlockParams, block};
use fluid_surfels::surface::{SurfaceDetector, SurfaceParams};

fn neighbours(c: &mut Criterion) {
    let scene = block(&BlockParams::with_particles(100_000)).expect("valid block");
    let p = &scene.particles.positions;
    let r = scene.support_radius;
    let mut group = c.benchmark_group("neighbours_100k");
    group.sample_size(10);
    group.bench_function("cell_grid", |b| {
        b.iter(|| Neighbourhoods::build(black_box(p), r, Backend::CellGrid))
    });
    group.bench_function("kiddo", |b| {
        b.iter(|| Neighbourhoods::build(black_box(p), r, Backend::KdTree))
    });
    group.bench_function("reference_single_thread", |b| {
        b.iter(|| reference_neighbours(black_box(p), r))
    });
    group.finish();
}

fn detection(c: &mut Criterion) {
    let scene = block(&BlockParams::with_particles(100_000)).expect("valid block");
    // built outside the timed region: this measures detection alone
    let nb = Neighbourhoods::build(
        &scene.particles.positions,
        scene.support_radius,
        Backend::CellGrid,
    )
    .expect("finite input");
    let mut group = c.benchmark_group("detect_100k");
    group.sample_size(10);
    group.bench_function("classify_and_normals", |b| {
        b.iter(|| {
            let mut detector =
                SurfaceDetector::new(SurfaceParams::default()).expect("default params are valid");
            detector.detect(black_box(&scene.particles), &nb)
        })
    });
    group.finish();
}

criterion_group!(benches, neighbours, detection);
criterion_main!(benches);
