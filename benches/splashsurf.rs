//! Criterion benchmark against the peer: splashsurf 0.14 (`splashsurf_lib`, a dev-dependency
//! only) reconstructing its marching-cubes mesh, and our density grid plus iso-surface surfels, on
//! the same particles with the same kernel (cubic spline), support radius and cell size, in one
//! run, our grid both dense and sparse (`density::sparse`, the LNM band included); the two
//! reconstructions are `common/peer.rs`, shared with `examples/peer_splashsurf.rs`, which prints
//! the time ratio, each one's peak memory and how far our surfels lie from splashsurf's mesh. The
//! surface each gives is also compared in `tests/surfels.rs::surfels_lie_on_splashsurfs_mesh`.
//!
//! Sizes: the density benchmark's case, a jittered block of 150,000 particles (53 x 53 x 53 =
//! 148,877), and the two real files of `tests/data/`; support radius twice the spacing, cells of
//! a third of it.

#[path = "common/peer.rs"]
mod peer;

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};

/// Both reconstructions of a case in one group named `name`.
fn compare(c: &mut Criterion, name: &str, case: &peer::Case) {
    let (p, s) = (&case.positions, case.spacing);
    let (input, params) = peer::peer_input(p, s);
    let mut group = c.benchmark_group(name);
    group.sample_size(10);
    group.bench_function("splashsurf_0_14_marching_cubes", |b| {
        b.iter(|| peer::splashsurf(black_box(&input), &params))
    });
    group.bench_function("fluid_surfels_density_and_surfels", |b| {
        b.iter(|| peer::ours_dense(black_box(p), s))
    });
    group.bench_function("fluid_surfels_sparse_density_and_surfels", |b| {
        b.iter(|| peer::ours_sparse(black_box(p), s))
    });
    group.finish();
}

fn block(c: &mut Criterion) {
    compare(c, "reconstruct_150k_block", &peer::block("150k block", 53));
}

/// The real files, each at twice its estimated spacing (the pipeline's default radius).
fn real_files(c: &mut Criterion) {
    for (group, case) in [
        (
            "reconstruct_double_dam_break",
            peer::file(
                "double dam break",
                "double_dam_break_frame_26_4732_particles.vtk",
            ),
        ),
        (
            "reconstruct_dam_break_frame",
            peer::file("dam break", "dam_break_frame_23_24389_particles.bgeo"),
        ),
    ] {
        compare(c, group, &case);
    }
}

criterion_group!(benches, block, real_files);
criterion_main!(benches);
