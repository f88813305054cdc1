//! Criterion benchmark against the peer: splashsurf 0.14 (`splashsurf_lib`, a dev-dependency
//! only) reconstructing its marching-cubes mesh, and our density grid plus iso-surface surfels, on
//! the same particles with the same kernel (cubic spline), support radius and cell size, in one
//! run, our grid both dense and sparse (`density::sparse`, the LNM band included). The surface
//! each gives is compared in `tests/surfels.rs::surfels_lie_on_splashsurfs_mesh`.
//!
//! Sizes: the density benchmark's case, a jittered block of 150,000 particles (53 x 53 x 53 =
//! 148,877), and the two real files of `tests/data/`; support radius twice the spacing, cells of
//! a third of it.

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use fluid_surfels::density::{self, GridSpec, Kernel, Resolution};
use fluid_surfels::scenes;
use fluid_surfels::surfels::{self, SurfelParams};
use glam::Vec3;
use splashsurf_lib::nalgebra::Vector3;

/// Both reconstructions of `p` (spacing `s`) in one group named `name`.
fn compare(c: &mut Criterion, name: &str, p: &[Vec3], s: f32) {
    let (h, cell) = (2.0 * s, 2.0 * s / 3.0);
    let peer: Vec<Vector3<f32>> = p.iter().map(|q| Vector3::new(q.x, q.y, q.z)).collect();
    let params = splashsurf_lib::Parameters::new(0.5 * s, h, cell);
    // splashsurf's threshold, 0.6 of the rest density, as ours (see the test)
    let iso = SurfelParams {
        iso_fraction: 0.6 / (s * s * s) / Kernel::CubicSpline.peak(h),
        ..SurfelParams::default()
    };
    let mut group = c.benchmark_group(name);
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
                GridSpec::around(black_box(p), h, Resolution::CellSize(cell)).expect("a grid");
            let grid = density::density_grid(p, &spec, Kernel::CubicSpline, h, 1 << 32)
                .expect("within memory");
            surfels::extract(&grid, p, Kernel::CubicSpline, h, &iso).expect("surfels")
        })
    });
    group.bench_function("fluid_surfels_sparse_density_and_surfels", |b| {
        b.iter(|| {
            let spec =
                GridSpec::around(black_box(p), h, Resolution::CellSize(cell)).expect("a grid");
            let band = fluid_surfels::lnm::narrow_band(p, h, &Default::default()).expect("a band");
            let level = iso.iso_fraction * Kernel::CubicSpline.peak(h);
            let points = density::Points::uniform(p, h);
            let grid = density::points_grid_sparse(
                points,
                &spec,
                Kernel::CubicSpline,
                1 << 32,
                &band,
                level,
                2.0 * level,
            )
            .expect("within memory");
            surfels::extract_sparse(&grid, points, Kernel::CubicSpline, &iso).expect("surfels")
        })
    });
    group.finish();
}

fn block(c: &mut Criterion) {
    let scene = scenes::block(&scenes::BlockParams {
        counts: [53, 53, 53],
        ..Default::default()
    })
    .expect("a valid block");
    compare(
        c,
        "reconstruct_150k_block",
        &scene.particles.positions,
        scene.spacing,
    );
}

/// The real files, each at twice its estimated spacing (the pipeline's default radius).
fn real_files(c: &mut Criterion) {
    for (group, file) in [
        (
            "reconstruct_double_dam_break",
            "double_dam_break_frame_26_4732_particles.vtk",
        ),
        (
            "reconstruct_dam_break_frame",
            "dam_break_frame_23_24389_particles.bgeo",
        ),
    ] {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("tests/data")
            .join(file);
        let p = fluid_surfels::io::read_particles(&path, None)
            .expect("the shipped file")
            .positions;
        let s = fluid_surfels::neighbours::estimate_spacing(&p).expect("a spacing");
        compare(c, group, &p, s);
    }
}

criterion_group!(benches, block, real_files);
criterion_main!(benches);
