//! Surfels on the iso-surface of the CPU density grid: accuracy, normals, no gaps, topology.

use fluid_surfels::density::{self, GridSpec, Kernel, Resolution};
use fluid_surfels::neighbours::{Backend, Neighbourhoods};
use fluid_surfels::pipeline::Calibration;
use fluid_surfels::scenes;
use fluid_surfels::surfels::{self, ExactDensity, SurfelExtractor, SurfelParams};
use glam::Vec3;

#[path = "../benches/common/peer.rs"]
mod peer;

fn surfels_of(p: &[Vec3], h: f32, cell: f32) -> (surfels::Surfels, GridSpec) {
    let spec = GridSpec::around(p, h, Resolution::CellSize(cell)).unwrap();
    let grid = density::density_grid(p, &spec, Kernel::Wyvill, h, 1 << 32).unwrap();
    (
        surfels::extract(&grid, p, Kernel::Wyvill, h, &SurfelParams::default()).unwrap(),
        spec,
    )
}

/// Number of connected groups of surfels, two being connected when closer than `reach`.
fn components(points: &[Vec3], reach: f32) -> usize {
    let nb = Neighbourhoods::build(points, reach, Backend::CellGrid).unwrap();
    let mut label = vec![usize::MAX; points.len()];
    let mut count = 0;
    for start in 0..points.len() {
        if label[start] != usize::MAX {
            continue;
        }
        let mut stack = vec![start];
        label[start] = count;
        while let Some(i) = stack.pop() {
            for &j in nb.of(i) {
                if label[j as usize] == usize::MAX {
                    label[j as usize] = count;
                    stack.push(j as usize);
                }
            }
        }
        count += 1;
    }
    count
}

#[test]
fn sphere_surfels_are_on_the_iso_surface_with_radial_normals_and_no_gaps() {
    let scene = scenes::sphere(&scenes::SphereParams {
        radius_in_spacings: 10.0,
        jitter: 0.0,
        ..Default::default()
    })
    .unwrap();
    let p = &scene.particles.positions;
    // smoothing radius 3 spacings: with 2 the iso-surface of the particle shells keeps bumps of
    // the particles' size and its normals stray up to 6.4 degrees from the radial direction
    let h = 3.0 * scene.spacing;
    let (s, spec) = surfels_of(p, h, 0.5 * scene.spacing);
    let exact = ExactDensity::new(p, Kernel::Wyvill, h).unwrap();
    let iso = s.iso;
    let worst = s
        .positions
        .iter()
        .map(|&x| ((exact.value(x) - iso) / iso).abs())
        .fold(0.0f32, f32::max);
    let angles: Vec<f32> = s
        .positions
        .iter()
        .zip(&s.normals)
        .map(|(x, n)| n.angle_between(x.normalize()).to_degrees())
        .collect();
    let worst_angle = angles.iter().copied().fold(0.0f32, f32::max);
    let radius = s.positions.iter().map(|x| x.length()).sum::<f32>() / s.len() as f32;
    println!(
        "sphere: {} particles, grid {:?}, {} surfels at mean radius {radius:.4} (particles to {:.4}); density within {:.4} % of the iso-value; normals within {worst_angle:.2} degrees",
        p.len(),
        spec.dims,
        s.len(),
        p.iter().map(|x| x.length()).fold(0.0f32, f32::max),
        worst * 100.0
    );
    assert!(worst <= 0.01, "{worst}");
    assert!(worst_angle <= 5.0, "{worst_angle}");
    // a dense sample of the iso-surface, found along rays from the centre by bisection
    let n = 20_000;
    let golden = std::f32::consts::PI * (3.0 - 5f32.sqrt());
    let reach = Neighbourhoods::build(&s.positions, s.radii[0], Backend::CellGrid).unwrap();
    let _ = reach;
    let all: Vec<Vec3> = s.positions.clone();
    let index = fluid_surfels::neighbours::CellGrid::new(&all, s.radii[0]).unwrap();
    let mut uncovered = 0;
    for i in 0..n {
        let y = 1.0 - 2.0 * (i as f32 + 0.5) / n as f32;
        let ring = (1.0 - y * y).sqrt();
        let dir = Vec3::new(
            ring * (golden * i as f32).cos(),
            y,
            ring * (golden * i as f32).sin(),
        );
        let (mut lo, mut hi) = (0.0f32, 2.0 * radius);
        for _ in 0..40 {
            let mid = 0.5 * (lo + hi);
            if exact.value(dir * mid) > iso {
                lo = mid
            } else {
                hi = mid
            }
        }
        let q = dir * lo;
        let mut covered = false;
        index.for_each_within(q, s.radii[0], |_| covered = true);
        if !covered {
            uncovered += 1;
        }
    }
    println!(
        "sphere: {uncovered} of {n} sample points of the iso-surface farther than R = {} from every surfel",
        s.radii[0]
    );
    assert_eq!(uncovered, 0);
}

#[test]
fn two_drops_give_two_shells_and_a_thin_sheet_stays_closed() {
    let drop = scenes::sphere(&scenes::SphereParams {
        radius_in_spacings: 4.0,
        jitter: 0.0,
        ..Default::default()
    })
    .unwrap();
    let s = drop.spacing;
    let h = 2.0 * s;
    let offset = Vec3::new(20.0 * s, 0.0, 0.0);
    let mut p = drop.particles.positions.clone();
    p.extend(drop.particles.positions.iter().map(|&x| x + offset));
    let (surfels, _) = surfels_of(&p, h, 0.5 * s);
    let groups = components(&surfels.positions, 2.0 * surfels.radii[0]);
    println!("two drops: {} surfels in {groups} groups", surfels.len());
    assert_eq!(groups, 2);

    // a one-particle-thick sheet: surfels on both sides everywhere in its interior
    let mut sheet = Vec::new();
    for i in 0..20 {
        for j in 0..20 {
            sheet.push(Vec3::new(i as f32, j as f32, 0.0) * s);
        }
    }
    let (surfels, _) = surfels_of(&sheet, h, 0.5 * s);
    let r = surfels.radii[0];
    let (mut above, mut below) = (0, 0);
    let mut holes = 0;
    for i in 3..17 {
        for j in 3..17 {
            let c = Vec3::new(i as f32 + 0.5, j as f32 + 0.5, 0.0) * s;
            let near = |sign: f32| {
                surfels.positions.iter().any(|x| {
                    (x.z * sign) > 0.0 && Vec3::new(x.x - c.x, x.y - c.y, 0.0).length() <= r
                })
            };
            if near(1.0) {
                above += 1
            } else {
                holes += 1
            }
            if near(-1.0) { below += 1 } else { holes += 1 }
        }
    }
    println!(
        "sheet: {} surfels, {above} of 196 spots covered above, {below} below",
        surfels.len()
    );
    assert_eq!(holes, 0);
    assert_eq!(
        components(&surfels.positions, 2.0 * r),
        1,
        "the sheet's surface is one closed shell"
    );
}

#[test]
fn streamed_extraction_equals_whole_grid_extraction() {
    let scene = scenes::sphere(&scenes::SphereParams {
        radius_in_spacings: 6.0,
        ..Default::default()
    })
    .unwrap();
    let p = &scene.particles.positions;
    let h = 2.0 * scene.spacing;
    let (whole, spec) = surfels_of(p, h, 0.5 * scene.spacing);
    let params = SurfelParams::default();
    let mut extractor = SurfelExtractor::new(spec, params.iso_fraction * Kernel::Wyvill.peak(h));
    density::splat_slabs(p, &spec, Kernel::Wyvill, h, 3, |k0, slab| {
        extractor.push_slab(k0, slab)
    })
    .unwrap();
    let streamed = extractor.finish(&ExactDensity::new(p, Kernel::Wyvill, h).unwrap(), &params);
    assert_eq!(streamed, whole);
    // a plane left out or planes pushed out of order (a caller's mistake) give surfels, not a
    // panic: the z edges whose plane above never followed keep their linear places
    let iso = params.iso_fraction * Kernel::Wyvill.peak(h);
    let grid = density::density_grid(p, &spec, Kernel::Wyvill, h, 1 << 30).unwrap();
    let plane = (spec.dims[0] * spec.dims[1]) as usize;
    let half = spec.dims[2] / 2;
    let mut gappy = SurfelExtractor::new(spec, iso);
    gappy.push_planes(0, &grid.values[..half as usize * plane]);
    for k in (half + 1..spec.dims[2]).chain([3, 7, 4]) {
        let at = k as usize * plane;
        gappy.push_plane(k, &grid.values[at..at + plane]);
    }
    let out = gappy.finish(&ExactDensity::new(p, Kernel::Wyvill, h).unwrap(), &params);
    assert!(!out.is_empty());
    assert!(
        surfels::extract(
            &density::density_grid(p, &spec, Kernel::Wyvill, h, 1 << 30).unwrap(),
            p,
            Kernel::Wyvill,
            h,
            &SurfelParams {
                iso_fraction: -1.0,
                ..params
            }
        )
        .is_err()
    );
}

/// Our surfels against splashsurf's marching-cubes mesh (the peer of issue 17) on the same
/// particles, with the same kernel (cubic spline), support radius and cell size: how far each
/// surfel lies from the mesh, in cell sizes. The two iso-values are defined differently
/// (splashsurf: 0.6 of the rest density; ours: a fraction of one lone particle's peak), so the
/// surfaces are offset by a fraction of a cell; the test also matches the iso-values.
#[test]
fn surfels_lie_on_splashsurfs_mesh() {
    use splashsurf_lib::nalgebra::Vector3;
    let scene = scenes::block(&scenes::BlockParams {
        counts: [16, 16, 16],
        ..Default::default()
    })
    .unwrap();
    let p = &scene.particles.positions;
    let (s, h) = (scene.spacing, scene.support_radius);
    let cell = h / 3.0;
    let t = std::time::Instant::now();
    let params = splashsurf_lib::Parameters::new(0.5 * s, h, cell);
    let peer: Vec<Vector3<f32>> = p.iter().map(|q| Vector3::new(q.x, q.y, q.z)).collect();
    let reconstruction = splashsurf_lib::reconstruct_surface::<i64, f32>(&peer, &params).unwrap();
    let peer_ms = t.elapsed().as_secs_f64() * 1e3;
    let mesh = &reconstruction.mesh;
    let v: Vec<Vec3> = mesh
        .vertices
        .iter()
        .map(|q| Vec3::new(q.x, q.y, q.z))
        .collect();
    assert!(
        mesh.triangles.len() > 1000,
        "{} triangles",
        mesh.triangles.len()
    );
    let t = std::time::Instant::now();
    let spec = GridSpec::around(p, h, Resolution::CellSize(cell)).unwrap();
    let grid = density::density_grid(p, &spec, Kernel::CubicSpline, h, 1 << 32).unwrap();
    let ours =
        surfels::extract(&grid, p, Kernel::CubicSpline, h, &SurfelParams::default()).unwrap();
    let ours_ms = t.elapsed().as_secs_f64() * 1e3;
    // the same iso-value as splashsurf's: its density is sum_j m W with m = rho_0 (2 r)^3 =
    // rho_0 s^3 (a cube per particle), so its threshold 0.6 rho_0 is sum_j W = 0.6 / s^3, here
    // as a fraction of one particle's peak
    let matched = SurfelParams {
        iso_fraction: 0.6 / (s * s * s) / Kernel::CubicSpline.peak(h),
        ..SurfelParams::default()
    };
    let same_iso = surfels::extract(&grid, p, Kernel::CubicSpline, h, &matched).unwrap();
    let near = fluid_surfels::quality::MeshDistance::new(
        mesh.triangles
            .iter()
            .map(|t| [v[t[0]], v[t[1]], v[t[2]]])
            .collect(),
        cell,
    );
    let distances = |surfels: &surfels::Surfels| -> (f32, f32) {
        let d: Vec<f32> = near
            .distances(&surfels.positions)
            .iter()
            .map(|d| d / cell)
            .collect();
        let mean = d.iter().sum::<f32>() / d.len() as f32;
        (mean, d.iter().copied().fold(0.0, f32::max))
    };
    let (mean, max) = distances(&ours);
    let (mean_same, max_same) = distances(&same_iso);
    println!(
        "{} particles, splashsurf {} triangles in {peer_ms:.0} ms, ours {} surfels in {ours_ms:.0} ms (test build, not a benchmark); distance to its mesh in cells: our default iso mean {mean:.3} max {max:.3}, at its iso-value mean {mean_same:.3} max {max_same:.3}",
        p.len(),
        mesh.triangles.len(),
        ours.len()
    );
    // measured 2026-12-02: default iso mean 0.54, max 0.69 cells, our surface outside theirs
    // alike everywhere (the bounding boxes: 0.843 against 0.815 across); at splashsurf's
    // iso-value mean 0.17, max 0.45, ours now slightly inside (0.798 across). What remains is
    // not explained yet (a candidate: marching cubes places its vertices by linear
    // interpolation along cell edges, ours are projected onto the iso-surface by Newton steps).
    // The bounds pin this agreement so that a faster path cannot drift (issue 17 measures it on
    // the real files).
    assert!(
        mean < 0.6 && max < 0.8,
        "default iso: mean {mean}, max {max} cells"
    );
    assert!(
        mean_same < 0.25 && max_same < 0.6,
        "same iso: mean {mean_same}, max {max_same} cells"
    );
}

/// A particle file of `tests/data/`.
fn read_data(name: &str) -> fluid_surfels::ParticleSet {
    fluid_surfels::io::read_particles(
        &std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("tests/data")
            .join(name),
        None,
    )
    .unwrap()
}

/// The pipeline's stage 3 with `GridParams::narrow_band` (the sparse grid in the LNM band)
/// gives the same surfels as with the dense grid, bit for bit and in the same order, on the
/// chain's points of both real files (refined surface points with their own radii beside the
/// interior particles) and on a jittered sphere; the time of each is printed.
#[test]
fn the_grid_in_the_narrow_band_gives_the_same_surfels() {
    use fluid_surfels::density::Grid;
    use fluid_surfels::pipeline::{GridParams, Pipeline, PipelineParams, Through, iso_surfels};
    let read = read_data;
    let sphere = scenes::sphere(&scenes::SphereParams::default()).unwrap();
    let points = density::Points::uniform(&sphere.particles.positions, sphere.support_radius);
    let dense = iso_surfels(points, &GridParams::default(), &SurfelParams::default())
        .unwrap()
        .unwrap();
    let banded = GridParams {
        narrow_band: true,
        ..GridParams::default()
    };
    let sparse = iso_surfels(points, &banded, &SurfelParams::default())
        .unwrap()
        .unwrap();
    assert!(matches!(sparse.grid, Grid::Sparse(_)));
    assert!(
        dense.surfels == sparse.surfels,
        "sphere: the surfels differ"
    );
    for name in [
        "double_dam_break_frame_26_4732_particles.vtk",
        "dam_break_frame_23_24389_particles.bgeo",
    ] {
        let particles = read(name);
        let run = |narrow_band| {
            let mut params = PipelineParams::default();
            params.grid.narrow_band = narrow_band;
            let mut pipeline = Pipeline::new(params).unwrap();
            pipeline
                .frame_through(&particles, Through::Surfels)
                .unwrap()
        };
        let (a, b) = (run(false), run(true));
        let (sa, sb) = (a.surfels.as_ref().unwrap(), b.surfels.as_ref().unwrap());
        assert!(!sa.is_empty(), "{name}");
        let (ga, gb) = (a.grid.as_ref().unwrap(), b.grid.as_ref().unwrap());
        assert_eq!(ga.spec(), gb.spec(), "{name}");
        let spec = *ga.spec();
        let Grid::Sparse(sparse) = gb else {
            panic!("{name}: not sparse")
        };
        let mut wrong = Vec::new();
        for k in 0..spec.dims[2] {
            for j in 0..spec.dims[1] {
                for i in 0..spec.dims[0] {
                    let (d, v) = (ga.at(i, j, k), sparse.at(i, j, k));
                    let fine = if sparse.is_evaluated(i, j, k) {
                        d.to_bits() == v.to_bits()
                    } else if v == 0.0 {
                        d == 0.0
                    } else {
                        d >= sb.iso
                    };
                    if !fine {
                        wrong.push((i, j, k, d, v));
                    }
                }
            }
        }
        assert!(
            wrong.is_empty(),
            "{name}: {} grid points differ, the first {:?} (iso {})",
            wrong.len(),
            &wrong[..wrong.len().min(5)],
            sb.iso
        );
        let differ = (0..sa.len().min(sb.len()))
            .filter(|&i| sa.positions[i] != sb.positions[i] || sa.normals[i] != sb.normals[i])
            .count();
        assert!(
            sa.len() == sb.len() && differ == 0 && sa.radii == sb.radii,
            "{name}: {} surfels dense, {} sparse, {differ} differ",
            sa.len(),
            sb.len()
        );
        println!(
            "{name}: {} surfels; density + surfels {:.0} + {:.0} ms dense ({} KiB), {:.0} + {:.0} ms sparse ({} KiB)",
            sa.len(),
            a.timings.density_ms,
            a.timings.surfels_ms,
            ga.bytes() / 1024,
            b.timings.density_ms,
            b.timings.surfels_ms,
            gb.bytes() / 1024
        );
    }
}

/// The sparse grid (`density::points_grid_sparse`, blocks of 8^3 evaluated near the surface
/// only) against the dense one on a 20^3 lattice block, a jittered sphere, the sphere with
/// mixed radii (the chain's case: fine points beside coarse ones), two far drops, a grid box
/// that cuts the particles, and both real files: every evaluated value bit for bit, every empty
/// block's values 0 in the dense grid too, every inside point above the iso-value there, the
/// same surfels in the same order, the same mesh as its dense twin's (its planes read block
/// row by block row), and the same grid on one thread as on three.
#[test]
#[allow(
    clippy::too_many_lines,
    reason = "a test is one scenario; issue 38 exempts tests"
)]
fn the_sparse_grid_equals_the_dense_one() {
    use fluid_surfels::density::Points;
    let read = |name: &str| read_data(name).positions;
    let block = scenes::block(&scenes::BlockParams {
        counts: [20, 20, 20],
        ..Default::default()
    })
    .unwrap();
    let sphere = scenes::sphere(&scenes::SphereParams::default()).unwrap();
    let drops: Vec<Vec3> = (0..2)
        .flat_map(|d| {
            (0..27).map(move |t| {
                Vec3::new((t % 3) as f32, ((t / 3) % 3) as f32, (t / 9) as f32) * 0.5
                    + Vec3::X * (40.0 * d as f32)
            })
        })
        .collect();
    let mixed: Vec<f32> = (0..sphere.particles.len())
        .map(|i| {
            if i % 3 == 0 {
                0.5 * sphere.support_radius
            } else {
                sphere.support_radius
            }
        })
        .collect();
    struct Case {
        name: &'static str,
        positions: Vec<Vec3>,
        h: f32,
        radii: Option<Vec<f32>>,
        cut: bool,
    }
    let case = |name, positions, h| Case {
        name,
        positions,
        h,
        radii: None,
        cut: false,
    };
    let cases = vec![
        case(
            "20^3 block",
            block.particles.positions.clone(),
            block.support_radius,
        ),
        case(
            "sphere",
            sphere.particles.positions.clone(),
            sphere.support_radius,
        ),
        Case {
            radii: Some(mixed),
            ..case(
                "sphere, mixed radii",
                sphere.particles.positions.clone(),
                sphere.support_radius,
            )
        },
        case("two far drops", drops, 1.0),
        Case {
            cut: true,
            ..case(
                "block cut by the grid",
                block.particles.positions.clone(),
                block.support_radius,
            )
        },
        case(
            "double dam break",
            read("double_dam_break_frame_26_4732_particles.vtk"),
            0.14,
        ),
        case(
            "dam break",
            read("dam_break_frame_23_24389_particles.bgeo"),
            0.095,
        ),
    ];
    let kernel = Kernel::Wyvill;
    let params = SurfelParams::default();
    for c in cases {
        let points = match &c.radii {
            Some(r) => Points::with_radii(&c.positions, r, c.h),
            None => Points::uniform(&c.positions, c.h),
        };
        let reach = points.max_radius();
        let spec = if c.cut {
            // the grid holds the lower half of the block only
            let (lo, hi) = c
                .positions
                .iter()
                .fold((Vec3::MAX, Vec3::MIN), |(a, b), &p| (a.min(p), b.max(p)));
            GridSpec::for_box(
                lo - Vec3::splat(reach),
                Vec3::new(hi.x + reach, 0.5 * (lo.y + hi.y), hi.z + reach),
                Resolution::CellSize(points.min_radius() / 3.0),
            )
            .unwrap()
        } else {
            GridSpec::around(
                &c.positions,
                reach,
                Resolution::CellSize(points.min_radius() / 3.0),
            )
            .unwrap()
        };
        let limit = 1 << 30;
        let dense = density::points_grid(points, &spec, kernel, limit).unwrap();
        let band =
            fluid_surfels::lnm::narrow_band(&c.positions, reach, &Default::default()).unwrap();
        let iso = params.iso_fraction * kernel.peak(c.h);
        let inside = 1e9;
        let sparse =
            density::points_grid_sparse(points, &spec, kernel, limit, &band, iso, inside).unwrap();
        let full = sparse.to_dense();
        // marching cubes read the sparse grid's planes block row by block row: the mesh of its
        // dense twin, vertex for vertex
        let (a, b) = (
            fluid_surfels::mesh::marching_cubes_of_sparse(&sparse, iso),
            fluid_surfels::mesh::marching_cubes_of_values(&full.spec, &full.values, iso),
        );
        assert!(!a.triangles.is_empty(), "{}", c.name);
        assert!(
            a.positions == b.positions && a.triangles == b.triangles,
            "{}: the sparse grid's mesh",
            c.name
        );
        let (mut evaluated, mut empty, mut interior, mut reached) =
            (0usize, 0usize, 0usize, 0usize);
        for k in 0..spec.dims[2] {
            for j in 0..spec.dims[1] {
                for i in 0..spec.dims[0] {
                    let (d, s) = (dense.at(i, j, k), sparse.at(i, j, k));
                    assert_eq!(
                        full.at(i, j, k).to_bits(),
                        s.to_bits(),
                        "{}: to_dense",
                        c.name
                    );
                    reached += usize::from(d > 0.0);
                    if sparse.is_evaluated(i, j, k) {
                        assert_eq!(d.to_bits(), s.to_bits(), "{} at {i} {j} {k}", c.name);
                        evaluated += 1;
                    } else if s == inside {
                        assert!(
                            d >= iso,
                            "{} at {i} {j} {k}: inside, but {d} < {iso}",
                            c.name
                        );
                        interior += 1;
                    } else {
                        assert_eq!(s, 0.0, "{}", c.name);
                        assert_eq!(d, 0.0, "{} at {i} {j} {k}: empty, but {d}", c.name);
                        empty += 1;
                    }
                }
            }
        }
        assert_eq!(evaluated, sparse.evaluated_points(), "{}", c.name);
        let a = surfels::extract_points(&dense, points, kernel, &params).unwrap();
        let b = surfels::extract_sparse(&sparse, points, kernel, &params).unwrap();
        assert!(!a.is_empty(), "{}", c.name);
        assert_eq!(a, b, "{}: the surfels", c.name);
        let on = |threads| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| {
                    density::points_grid_sparse(points, &spec, kernel, limit, &band, iso, inside)
                        .unwrap()
                })
        };
        assert!(
            on(1) == sparse && on(3) == sparse,
            "{}: thread count",
            c.name
        );
        let (e, i, v) = sparse.counts();
        println!(
            "{}: {} surfels; grid {:?}: {evaluated} points evaluated ({:.1} % of the grid; the particles reach {reached}), {interior} inside, {empty} empty; blocks {e} empty, {i} inside, {v} evaluated; {} KiB against {} KiB dense",
            c.name,
            a.len(),
            spec.dims,
            100.0 * evaluated as f64 / spec.cells() as f64,
            sparse.bytes() / 1024,
            spec.bytes() / 1024
        );
    }
}

/// The sparse grid refuses what it cannot hold or was given wrong, with typed errors.
#[test]
fn the_sparse_grid_refuses_bad_input() {
    use fluid_surfels::density::{DensityError, Points};
    let p = vec![Vec3::ZERO, Vec3::X * 0.5];
    let band = fluid_surfels::lnm::narrow_band(&p, 1.0, &Default::default()).unwrap();
    let spec = GridSpec::around(&p, 1.0, Resolution::CellSize(0.1)).unwrap();
    let run = |points: Points<'_>, limit| {
        density::points_grid_sparse(points, &spec, Kernel::Wyvill, limit, &band, 1.0, 1e9)
    };
    assert!(run(Points::uniform(&p, 1.0), 1 << 30).is_ok());
    // a band of other particles
    let three = vec![Vec3::ZERO, Vec3::X, Vec3::Y];
    assert!(matches!(
        run(Points::uniform(&three, 1.0), 1 << 30),
        Err(DensityError::InvalidGrid { .. })
    ));
    // a memory limit below the block states
    assert!(matches!(
        run(Points::uniform(&p, 1.0), 8),
        Err(DensityError::TooLarge { .. })
    ));
    let nan = vec![Vec3::ZERO, Vec3::NAN];
    assert!(matches!(
        run(Points::uniform(&nan, 1.0), 1 << 30),
        Err(DensityError::NonFinite { index: 1 })
    ));
    assert!(matches!(
        run(Points::uniform(&p, -1.0), 1 << 30),
        Err(DensityError::InvalidRadius { .. })
    ));
}

/// `ExactDensity::value_up_to` is the density bit for bit below its limit and at least the
/// limit elsewhere (the boundary calibration's test of how alone a point is relies on both):
/// points of three radii and varied weights, queried at and between them against limits from
/// a tenth to twice the density there.
#[test]
fn a_density_up_to_a_limit_is_the_density_below_it() {
    let (mut positions, mut radii, mut weights) = (Vec::new(), Vec::new(), Vec::new());
    for i in 0..600 {
        let t = i as f32 * 0.37;
        positions.push(Vec3::new(t.sin(), (1.7 * t).cos(), (0.3 * t).sin()) * 0.5);
        radii.push([0.05, 0.12, 0.3][i % 3]);
        weights.push(0.25 + (i % 7) as f32 * 0.3);
    }
    let points = density::Points::with_radii(&positions, &radii, 0.3).with_weights(&weights);
    let exact = ExactDensity::of(points, Kernel::Wyvill).unwrap();
    let (mut below, mut stopped) = (0, 0);
    for (i, &p) in positions.iter().enumerate().step_by(7) {
        for x in [p, p + Vec3::new(0.013, -0.021, 0.008) * (i % 5) as f32] {
            let value = exact.value(x);
            for factor in [0.1, 0.5, 0.99, 1.0, 1.01, 2.0] {
                let limit = value * factor;
                let up_to = exact.value_up_to(x, limit);
                if value < limit {
                    assert_eq!(up_to.to_bits(), value.to_bits(), "at {x}, limit {limit}");
                    below += 1;
                } else {
                    assert!(
                        up_to >= limit && up_to <= value,
                        "at {x}: {up_to} {limit} {value}"
                    );
                    stopped += usize::from(up_to < value);
                }
            }
        }
    }
    assert!(
        below > 0 && stopped > 0,
        "{below} below, {stopped} stopped early"
    );
}

/// Our mesh against splashsurf's (issue 40), at the peer comparison's settings (the same
/// particles, cubic spline, support radius of two spacings, cells of a third of it,
/// splashsurf's iso-value). With splashsurf's per-particle volumes as weights (the same density
/// field, [`peer::peer_weights`]) the meshes agree within 0.25 cells on average both ways on the
/// 150k block and the double dam break, for our mesh as `Frame::mesh` makes it (vertices on
/// the exact iso-surface) and on the grid's edges (linear interpolation, as splashsurf's); with
/// our `particles` source's uniform weights they agree as closely on the block, where every
/// particle has its bulk density, and the double dam break's figures, where thin sheets make
/// the two fields differ, are printed. Closed, both.
#[test]
fn the_mesh_agrees_with_splashsurfs() {
    for c in [
        peer::block("150k block", 53),
        peer::file(
            "double dam break",
            "double_dam_break_frame_26_4732_particles.vtk",
        ),
    ] {
        let (input, params) = peer::peer_input(&c.positions, c.spacing);
        let (_, cell) = peer::sizes(c.spacing);
        let theirs = peer::splashsurf_mesh(&input, &params);
        let weights = peer::peer_weights(&c.positions, c.spacing);
        for (project, weighted) in [(true, true), (false, true), (true, false)] {
            let ours = peer::ours_mesh(
                &c.positions,
                c.spacing,
                project,
                weighted.then_some(weights.as_slice()),
            );
            assert!(ours.is_closed(), "{}", c.name);
            let to_theirs = peer::mean_distance(&ours, &theirs, cell);
            let to_ours = peer::mean_distance(&theirs, &ours, cell);
            println!(
                "{} (projected {project}, splashsurf's weights {weighted}): ours {} triangles, splashsurf {} ({:+.1} %); mean distance ours -> theirs {to_theirs:.3} cells, theirs -> ours {to_ours:.3}",
                c.name,
                ours.triangles.len(),
                theirs.triangles.len(),
                100.0 * (ours.triangles.len() as f64 / theirs.triangles.len() as f64 - 1.0)
            );
            if weighted || c.name == "150k block" {
                assert!(to_theirs <= 0.25 && to_ours <= 0.25, "{}", c.name);
            }
            // the same field on the same lattice (both grids on the world's lattice of the
            // cell size): marching cubes make the same triangles (measured: equal counts on
            // both cases)
            if weighted {
                let diff = ours.triangles.len().abs_diff(theirs.triangles.len());
                assert!(
                    diff * 1000 <= theirs.triangles.len(),
                    "{}: {} against {} triangles",
                    c.name,
                    ours.triangles.len(),
                    theirs.triangles.len()
                );
            }
        }
        // the pipeline's `particles` source with `calibration = "volume"` (splashsurf's field,
        // as a user asks for it), dense and sparse: as close as with the weights above
        for narrow_band in [false, true] {
            let ours =
                peer::pipeline_mesh(&c.positions, c.spacing, Calibration::Volume, narrow_band);
            assert!(ours.is_closed(), "{}", c.name);
            let to_theirs = peer::mean_distance(&ours, &theirs, cell);
            let to_ours = peer::mean_distance(&theirs, &ours, cell);
            let diff = ours.triangles.len().abs_diff(theirs.triangles.len());
            println!(
                "{} (the pipeline, calibration volume, narrow band {narrow_band}): {} triangles against {}; mean distance {to_theirs:.3} / {to_ours:.3} cells",
                c.name,
                ours.triangles.len(),
                theirs.triangles.len()
            );
            assert!(to_theirs <= 0.25 && to_ours <= 0.25, "{}", c.name);
            assert!(diff * 1000 <= theirs.triangles.len(), "{}", c.name);
        }
    }
}

/// A grid at a cell size lies on the world's lattice (`GridSpec::for_box`), so a drop far away
/// that widens the box leaves a body's grid points, and so its surfels, where they were: the
/// same count, each within 1e-3 cells (the surfels' own accuracy: the grid points' coordinates
/// round differently from another origin, and Newton's projection stops within
/// `surfels::CONVERGED`; measured 8.4e-5). A grid anchored at the box's
/// corner instead (the layout before) moves under the body by a fraction of a cell and changes
/// its surfels, which this test also checks so that it cannot pass by accident.
#[test]
fn a_far_drop_leaves_a_bodys_surfels_where_they_were() {
    let scene = scenes::sphere(&scenes::SphereParams {
        radius_in_spacings: 5.0,
        jitter: 0.0,
        ..Default::default()
    })
    .unwrap();
    let body = scene.particles.positions.clone();
    let s = scene.spacing;
    let (h, cell) = (2.0 * s, 0.5 * s);
    // a lone drop 20 spacings out, off the lattice in every axis
    let mut with_drop = body.clone();
    with_drop.push(Vec3::new(-20.37, -19.71, -20.13) * s);
    let near_body = |x: &Vec3| x.length() < 8.0 * s;
    let surfels_in = |p: &[Vec3], spec: &GridSpec| -> Vec<Vec3> {
        let grid = density::density_grid(p, spec, Kernel::Wyvill, h, 1 << 32).unwrap();
        let s = surfels::extract(&grid, p, Kernel::Wyvill, h, &SurfelParams::default()).unwrap();
        s.positions.into_iter().filter(near_body).collect()
    };
    let alone_spec = GridSpec::around(&body, h, Resolution::CellSize(cell)).unwrap();
    let with_spec = GridSpec::around(&with_drop, h, Resolution::CellSize(cell)).unwrap();
    for (a, b) in [(alone_spec, with_spec), (with_spec, alone_spec)] {
        let offset = (a.origin - b.origin) / cell;
        assert!(
            (offset - offset.round()).abs().max_element() < 1e-3,
            "the grids share a lattice: {offset}"
        );
    }
    let alone = surfels_in(&body, &alone_spec);
    let with = surfels_in(&with_drop, &with_spec);
    assert!(alone.len() > 1000);
    assert_eq!(alone.len(), with.len(), "the body's surfels");
    let worst = alone
        .iter()
        .zip(&with)
        .map(|(a, b)| a.distance(*b) / cell)
        .fold(0.0f32, f32::max);
    println!(
        "a far drop: the body's {} surfels at most {worst:.2e} cells from where they were",
        alone.len()
    );
    assert!(worst < 1e-3, "{worst} cells");
    // anchored at the widened box's corner, the grid moves under the body
    let anchored = GridSpec {
        origin: with_drop
            .iter()
            .fold(Vec3::splat(f32::MAX), |lo, p| lo.min(*p))
            - Vec3::splat(h),
        ..with_spec
    };
    let moved = surfels_in(&with_drop, &anchored);
    let same = moved.len() == alone.len()
        && moved
            .iter()
            .zip(&alone)
            .all(|(a, b)| a.distance(*b) / cell < 1e-3);
    assert!(!same, "a grid off the lattice moves the surfels");
}

/// The surfels lie on the exact iso-surface of the chain's points (Newton's projection with the
/// analytic gradient, stopped once a step is under `surfels::CONVERGED` cells, after which the
/// next would be about that squared): on both real files' chain points (radii and boundary
/// weights per point), every surfel within 1e-3 cells of the iso-surface and 1e-4 cells on
/// average (measured: at most 4.0e-4 and 6.5e-4, 1.3e-5 and 3.8e-6 on average), as
/// `|density - iso| / |gradient|`.
#[test]
fn surfels_lie_on_the_exact_iso_surface_of_the_chain() {
    use fluid_surfels::pipeline::{Pipeline, PipelineParams};
    for name in [
        "dam_break_frame_23_24389_particles.bgeo",
        "double_dam_break_frame_26_4732_particles.vtk",
    ] {
        let particles = read_data(name);
        let mut pipeline = Pipeline::new(PipelineParams::default()).unwrap();
        let (_, input) = pipeline.frame_to_grid(&particles, u64::MAX).unwrap();
        let input = input.unwrap();
        let points = input.points();
        let kernel = Kernel::Wyvill;
        let grid = density::points_grid(points, &input.spec, kernel, 1 << 30).unwrap();
        let s = surfels::extract_points(&grid, points, kernel, &SurfelParams::default()).unwrap();
        let exact = ExactDensity::of(points, kernel).unwrap();
        let cell = input.spec.spacing;
        let off: Vec<f32> = s
            .positions
            .iter()
            .map(|&x| {
                let (v, g) = exact.value_and_gradient(x);
                (v - s.iso).abs() / g.length() / cell
            })
            .collect();
        let worst = off.iter().copied().fold(0.0f32, f32::max);
        let mean = off.iter().sum::<f32>() / off.len() as f32;
        let beyond = |t: f32| off.iter().filter(|&&d| d > t).count();
        println!(
            "{name}: {} surfels off the iso-surface by {mean:.1e} cells on average, {worst:.1e} at most; beyond 1e-4: {}, 1e-3: {}, 1e-2: {}, 0.1: {}",
            s.len(),
            beyond(1e-4),
            beyond(1e-3),
            beyond(1e-2),
            beyond(0.1)
        );
        assert!(s.len() > 1000);
        // every one (with at most 4 steps, 11 and 9 here stopped 0.4-0.6 cells off)
        assert!(
            worst <= 1e-3,
            "{name}: a surfel {worst} cells off the iso-surface"
        );
        assert!(mean <= 1e-4, "{name}: {mean} cells off on average");
    }
}
