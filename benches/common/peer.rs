//! The peer comparison's two reconstructions, shared by `benches/splashsurf.rs` (criterion
//! timings) and `examples/peer_splashsurf.rs` (time ratio, peak memory, surface distance):
//! splashsurf 0.14 (`splashsurf_lib`, a dev-dependency only) and our density grid plus
//! iso-surface surfels, on the same particles with the same kernel (cubic spline), support radius
//! (twice the spacing) and cell size (a third of it), at splashsurf's iso-value (0.6 of the rest
//! density, as `tests/surfels.rs::surfels_lie_on_splashsurfs_mesh` derives).

#![allow(dead_code)] // each target uses its part

use fluid_surfels::density::{self, GridSpec, Kernel, Resolution};
use fluid_surfels::mesh::{Mesh, marching_cubes_of_values};
use fluid_surfels::quality::MeshDistance;
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

/// splashsurf's weights: its density map is `sum_j V_j W(x - x_j)` with each particle's volume
/// `V_j = m / rho_j` from its SPH density `rho_j = sum_k m W_jk` (splashsurf_lib 0.14's
/// `density_map.rs`: `particle_volume = particle_rest_mass / particle_density`), not the rest
/// volume, so where a particle has fewer neighbours than in the bulk (thin sheets, drops) its
/// field is stronger. As weights of our sum `sum_j w_j W` at the same iso-value:
/// `w_j = V_j / s^3 = 1 / (s^3 sum_k W_jk)` (1 in the bulk of a lattice of spacing `s`).
pub fn peer_weights(p: &[Vec3], spacing: f32) -> Vec<f32> {
    let (h, _) = sizes(spacing);
    let grid = neighbours::CellGrid::new(p, h).expect("finite particles");
    p.iter()
        .map(|&x| {
            let mut sum = 0.0f32;
            grid.for_each_within(x, h, |j| {
                sum += Kernel::CubicSpline.value_r2(p[j as usize].distance_squared(x), h);
            });
            1.0 / (spacing * spacing * spacing * sum)
        })
        .collect()
}

/// The pipeline's own mesh of the raw particles (`source = "particles"`, `Through::Mesh`) at the
/// peer comparison's settings and `calibration` (`volume`: splashsurf's field, its threshold
/// 0.6), dense or sparse.
pub fn pipeline_mesh(
    p: &[Vec3],
    spacing: f32,
    calibration: fluid_surfels::pipeline::Calibration,
    narrow_band: bool,
) -> Mesh {
    use fluid_surfels::pipeline::{Pipeline, PipelineParams, SurfelSource, Through};
    let (h, cell) = sizes(spacing);
    let mut params = PipelineParams {
        source: SurfelSource::Particles,
        support_radius: Some(h),
        surfels: iso(spacing),
        ..Default::default()
    };
    params.grid.kernel = Kernel::CubicSpline;
    params.grid.resolution = Some(Resolution::CellSize(cell));
    params.grid.calibration = calibration;
    params.grid.narrow_band = narrow_band;
    let frame = Pipeline::new(params)
        .expect("valid parameters")
        .frame_through(fluid_surfels::ParticleView::of_positions(p), Through::Mesh)
        .expect("a frame");
    frame.mesh.expect("a grid")
}

/// Our mesh of the dense grid at the surfels' iso-value (`pipeline::Frame::mesh`'s steps):
/// marching cubes, then the vertices moved onto the surfels (the exact iso-surface) where that
/// folds no triangle. `project: false` keeps every vertex on its grid edge (linear
/// interpolation, as splashsurf's marching cubes leaves them). `weights`: each particle's
/// weight in the density (splashsurf's, [`peer_weights`]); all 1 without.
pub fn ours_mesh(p: &[Vec3], spacing: f32, project: bool, weights: Option<&[f32]>) -> Mesh {
    let (h, cell) = sizes(spacing);
    let spec = GridSpec::around(p, h, Resolution::CellSize(cell)).expect("a grid");
    let mut points = density::Points::uniform(p, h);
    if let Some(w) = weights {
        points = points.with_weights(w);
    }
    let grid =
        density::points_grid(points, &spec, Kernel::CubicSpline, 1 << 32).expect("within memory");
    let surfels = surfels::extract_points(&grid, points, Kernel::CubicSpline, &iso(spacing))
        .expect("surfels");
    let mut mesh = marching_cubes_of_values(&grid.spec, &grid.values, surfels.iso);
    if project {
        assert_eq!(mesh.positions.len(), surfels.len(), "a vertex per surfel");
        mesh.move_onto(&surfels.positions, &surfels.normals);
    }
    mesh
}

/// Our dense density grid and its marching cubes alone, the vertices on the grid's edges
/// (linear interpolation, as splashsurf's): the library's `mesh::marching_cubes` over
/// `density::density_grid`, without the surfels.
pub fn ours_grid_mesh(p: &[Vec3], spacing: f32) -> Mesh {
    let (h, cell) = sizes(spacing);
    let spec = GridSpec::around(p, h, Resolution::CellSize(cell)).expect("a grid");
    let grid =
        density::density_grid(p, &spec, Kernel::CubicSpline, h, 1 << 32).expect("within memory");
    let level = iso(spacing).iso_fraction * Kernel::CubicSpline.peak(h);
    marching_cubes_of_values(&grid.spec, &grid.values, level)
}

/// splashsurf's mesh as a [`Mesh`] (its vertices and triangles).
pub fn splashsurf_mesh(peer: &[Vector3<f32>], params: &splashsurf_lib::Parameters<f32>) -> Mesh {
    let r =
        splashsurf_lib::reconstruct_surface::<i64, f32>(peer, params).expect("a reconstruction");
    let positions = r
        .mesh
        .vertices
        .iter()
        .map(|q| Vec3::new(q.x, q.y, q.z))
        .collect();
    let triangles = r
        .mesh
        .triangles
        .iter()
        .map(|t| t.map(|v| v as u32))
        .collect();
    Mesh::new(positions, triangles).expect("a valid mesh")
}

/// The mean distance, in cells, from every vertex of `a` to the surface of `b`.
pub fn mean_distance(a: &Mesh, b: &Mesh, cell: f32) -> f64 {
    let near = MeshDistance::new(
        b.triangles
            .iter()
            .map(|t| t.map(|v| b.positions[v as usize]))
            .collect(),
        cell,
    );
    let d = near.distances(&a.positions);
    d.iter().map(|&x| f64::from(x)).sum::<f64>() / d.len().max(1) as f64 / f64::from(cell)
}
