//! Criterion benchmark against the peer: splashsurf 0.14 (`splashsurf_lib`, a dev-dependency
//! only) reconstructing its marching-cubes mesh, and our density grid plus iso-surface surfels, on
//! the same particles with the same kernel (cubic spline), support radius and cell size, in one
//! run. The surface each gives is compared in `tests/surfels.rs::surfels_lie_on_splashsurfs_mesh`.
//!
//! Size: the density benchmark's case, a jittered block of 150,000 particles (53 x 53 x 53 =
//! 148,877), cells of a third of the support radius.

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use fluid_surfels::density::{self, GridSpec, Kernel, Resolution};
use fluid_surfels::scenes;
use fluid_surfels::surfels::{self, SurfelParams};
use splashsurf_lib::nalgebra::Vector3;

fn reconstruct(c: &mut Criterion) {
    let scene = scenes::block(&scenes::BlockParams {
        counts: [53, 53, 53],
        ..Default::default()
    })
    .expect("a valid block");
    let p = scene.particles.positions;
    let (s, h) = (scene.spacing, scene.support_radius);
    let cell = h / 3.0;
    let peer: Vec<Vector3<f32>> = p.iter().map(|q| Vector3::new(q.x, q.y, q.z)).collect();
    let params = splashsurf_lib::Parameters::new(0.5 * s, h, cell);
    // splashsurf's threshold, 0.6 of the rest density, as ours (see the test)
    let iso = SurfelParams {
        iso_fraction: 0.6 / (s * s * s) / Kernel::CubicSpline.peak(h),
        ..SurfelParams::default()
    };
    let mut group = c.benchmark_group("reconstruct_150k_block");
    group.sample_size(10);
    group.bench_function("splashsurf_0_14_marching_cubes", |b| {
        b.iter(|| {
            splashsurf_lib::reconstruct_surface::<i64, f32>(black_box(&peer), &params)
                .expect("a reconstruction")
        })
    });
    group.bench_function("fluid_surfels_density_and_surfels", |b| {
        b.iter(|| {
            let spec =
                GridSpec::around(black_box(&p), h, Resolution::CellSize(cell)).expect("a grid");
            let grid = density::density_grid(&p, &spec, Kernel::CubicSpline, h, 1 << 32)
                .expect("within memory");
            surfels::extract(&grid, &p, Kernel::CubicSpline, h, &iso).expect("surfels")
        })
    });
    group.finish();
}

criterion_group!(benches, reconstruct);
criterion_main!(benches);
