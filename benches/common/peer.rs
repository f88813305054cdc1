//! The peer comparison's two reconstructions, shared by `benches/splashsurf.rs` (criterion
//! timings) and `examples/peer_splashsurf.rs` (time ratio, peak memory, surface distance):
//! splashsurf 0.14 (`splashsurf_lib`, a dev-dependency only) and our density grid plus
//! iso-surface surfels, on the same particles with the same kernel (cubic spline), support radius
//! (twice the spacing) and cell size (a third of it), at splashsurf's iso-value (0.6 of the rest
//! density, as `tests/surfels.rs::surfels_lie_on_splashsurfs_mesh` derives).

#![allow(dead_code)] // each target uses its part

use fluid_surfels::density::{self, GridSpec, Kernel, Resolution};
use fluid_surfels::surfels::{self, SurfelParams, Surfels};
use fluid_surfels::{io, lnm, neighbours, scenes};
use glam::Vec3;
use splashsurf_lib::nalgebra::Vector3;

/// Particles to reconstruct and their spacing.
pub struct Case {
    pub name: &'static str,
    pub positions: Vec<Vec3>,
    pub spacing: f32,
}

/// A jittered block of `n^3` particles.
pub fn block(name: &'static str, n: u32) -> Case {
    let scene = scenes::block(&scenes::BlockParams {
        counts: [n; 3],
        ..Default::default()
    })
    .expect("a valid block");
    Case {
        name,
        positions: scene.particles.positions,
        spacing: scene.spacing,
    }
}

/// A particle file of `tests/data/`, at its estimated spacing (the pipeline's default radius).
pub fn file(name: &'static str, file: &str) -> Case {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data")
        .join(file);
    let positions = io::read_particles(&path, None)
        .expect("the shipped file")
        .positions;
    let spacing = neighbours::estimate_spacing(&positions).expect("a spacing");
    Case {
        name,
        positions,
        spacing,
    }
}

/// The benchmark's cases: the density benchmark's 150k block and the two real files.
pub fn cases() -> Vec<Case> {
    vec![
        block("150k block", 53),
        file(
            "double dam break",
            "double_dam_break_frame_26_4732_particles.vtk",
        ),
        file("dam break", "dam_break_frame_23_24389_particles.bgeo"),
    ]
}

/// Support radius and cell size of a case.
pub fn sizes(spacing: f32) -> (f32, f32) {
    (2.0 * spacing, 2.0 * spacing / 3.0)
}

/// splashsurf's particles and parameters for `p`.
pub fn peer_input(
    p: &[Vec3],
    spacing: f32,
) -> (Vec<Vector3<f32>>, splashsurf_lib::Parameters<f32>) {
    let (h, cell) = sizes(spacing);
    let peer = p.iter().map(|q| Vector3::new(q.x, q.y, q.z)).collect();
    (
        peer,
        splashsurf_lib::Parameters::new(0.5 * spacing, h, cell),
    )
}

/// splashsurf's reconstruction (its spatial decomposition and threads on): the mesh's triangles.
pub fn splashsurf(
    peer: &[Vector3<f32>],
    params: &splashsurf_lib::Parameters<f32>,
) -> Vec<[Vec3; 3]> {
    let r =
        splashsurf_lib::reconstruct_surface::<i64, f32>(peer, params).expect("a reconstruction");
    let mesh = &r.mesh;
    let v = |i: usize| {
        let q = mesh.vertices[i];
        Vec3::new(q.x, q.y, q.z)
    };
    mesh.triangles
        .iter()
        .map(|t| [v(t[0]), v(t[1]), v(t[2])])
        .collect()
}

/// Our surfels at splashsurf's iso-value.
pub fn iso(spacing: f32) -> SurfelParams {
    let (h, _) = sizes(spacing);
    SurfelParams {
        iso_fraction: 0.6 / (spacing * spacing * spacing) / Kernel::CubicSpline.peak(h),
        ..SurfelParams::default()
    }
}

/// Our dense density grid and its surfels.
pub fn ours_dense(p: &[Vec3], spacing: f32) -> Surfels {
    let (h, cell) = sizes(spacing);
    let spec = GridSpec::around(p, h, Resolution::CellSize(cell)).expect("a grid");
    let grid =
        density::density_grid(p, &spec, Kernel::CubicSpline, h, 1 << 32).expect("within memory");
    surfels::extract(&grid, p, Kernel::CubicSpline, h, &iso(spacing)).expect("surfels")
}

/// Our sparse density grid (the LNM band included) and its surfels.
pub fn ours_sparse(p: &[Vec3], spacing: f32) -> Surfels {
    let (h, cell) = sizes(spacing);
    let iso = iso(spacing);
    let spec = GridSpec::around(p, h, Resolution::CellSize(cell)).expect("a grid");
    let band = lnm::narrow_band(p, h, &Default::default()).expect("a band");
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
}
