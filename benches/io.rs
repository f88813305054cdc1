//! Reading a 1,000,000-particle binary PLY: this crate's reader against `ply-rs-bw` (the
//! maintained fork of `ply-rs`), the comparison behind the choice recorded in ARCHITECTURE.md;
//! and binary legacy VTK and BGEO, the formats with a 0.2 s goal.
//!
//! One million particles is the size the goal names; criterion samples ten reads of each.

use std::hint::black_box;
use std::path::Path;

use criterion::{Criterion, criterion_group, criterion_main};
use fluid_surfels::io::{self, Format};
use fluid_surfels::scenes::{BlockParams, block};

fn readers(c: &mut Criterion) {
    let mut set = block(&BlockParams::with_particles(1_000_000))
        .expect("valid block")
        .particles;
    set.velocities = Some(
        set.positions
            .iter()
            .map(|p| glam::Vec3::new(p.y, -p.x, 0.0))
            .collect(),
    );
    let path = Path::new("bench.ply");
    let ply = io::to_bytes(Format::Ply, &set, path).expect("valid set");
    let vtk = io::to_bytes(Format::Vtk, &set, path).expect("valid set");
    let bgeo = io::to_bytes(Format::Bgeo, &set, path).expect("valid set");
    let mut group = c.benchmark_group("read_1m");
    group.sample_size(10);
    group.bench_function("ply_fluid_surfels", |b| {
        b.iter(|| io::parse_bytes(Format::Ply, black_box(&ply), path))
    });
    group.bench_function("ply_rs_bw", |b| {
        b.iter(|| {
            let parser = ply_rs_bw::parser::Parser::<ply_rs_bw::ply::DefaultElement>::new();
            let mut reader = std::io::Cursor::new(black_box(&ply));
            parser.read_ply(&mut reader).expect("valid PLY")
        })
    });
    group.bench_function("vtk_binary", |b| {
        b.iter(|| io::parse_bytes(Format::Vtk, black_box(&vtk), path))
    });
    group.bench_function("bgeo", |b| {
        b.iter(|| io::parse_bytes(Format::Bgeo, black_box(&bgeo), path))
    });
    group.finish();
}

criterion_group!(benches, readers);
criterion_main!(benches);
