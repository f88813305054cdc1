//! Criterion benchmark of the CPU reference splatting renderer (three passes).
//!
//! Size: 100,000 surfels on a sphere filling a 640x480 image: big enough that the parallel
//! bands are busy, small enough for repeated sampling on a 2-core machine. The GPU path and the
//! 1920x1080 case are in `fluid-surfels bench splat`.

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use fluid_surfels::scenes::{surfel_sphere, surfel_sphere_camera};
use fluid_surfels::splat::{Light, SplatParams, View, render_view_cpu};

fn splat_cpu(c: &mut Criterion) {
    let surfels = surfel_sphere(100_000);
    let camera = surfel_sphere_camera();
    // prepared outside the timed region
    let view = View::new(
        &camera,
        &Light::default(),
        &SplatParams::default(),
        640,
        480,
    )
    .expect("valid view");
    let mut group = c.benchmark_group("splat_cpu_100k_640x480");
    group.sample_size(10);
    group.bench_function("three_passes", |b| {
        b.iter(|| render_view_cpu(black_box(&surfels), &view).expect("a frame within the limit"))
    });
    group.finish();
}

criterion_group!(benches, splat_cpu);
criterion_main!(benches);
