//! The surface at the fluid's boundary (issue 35): on shapes built of shells of particles whose
//! outermost centres lie half a spacing inside the analytic surface (`scenes::block` for slabs,
//! `scenes::tube`, `scenes::sphere` for drops), how far the surfels lie from that surface, in
//! spacings (+: outside, the water too big), per surfel source and refinement level.

use fluid_surfels::pipeline::{Calibration, Pipeline, PipelineParams, SurfelSource, Through};
use fluid_surfels::scenes::{self, BlockParams, Scene, SphereParams, TubeParams};

/// A shape and the part of it measured: away from a slab's rims and a tube's ends by four
/// spacings (where the analytic shape's edges round off).
struct Shape {
    name: String,
    scene: Scene,
    measured: Box<dyn Fn(glam::Vec3) -> bool>,
}

fn slab(layers: u32) -> Shape {
    let p = BlockParams {
        counts: [24, layers, 24],
        jitter: 0.0,
        ..Default::default()
    };
    let s = p.spacing;
    Shape {
        name: format!("slab, {layers} layers"),
        scene: scenes::block(&p).unwrap(),
        measured: Box::new(move |q| {
            q.x > 4.0 * s && q.x < 20.0 * s && q.z > 4.0 * s && q.z < 20.0 * s
        }),
    }
}

fn tube(radius: f32) -> Shape {
    let p = TubeParams {
        radius_in_spacings: radius,
        ..Default::default()
    };
    let (s, l) = (p.spacing, p.length_in_spacings);
    Shape {
        name: format!("tube, radius {radius}s"),
        scene: scenes::tube(&p).unwrap(),
        measured: Box::new(move |q| q.x > 4.0 * s && q.x < (l - 4.0) * s),
    }
}

fn drop(radius: f32) -> Shape {
    let p = SphereParams {
        radius_in_spacings: radius,
        jitter: 0.0,
        ..Default::default()
    };
    Shape {
        name: format!("drop, radius {radius}s"),
        scene: scenes::sphere(&p).unwrap(),
        measured: Box::new(|_| true),
    }
}

/// The median of signed distances `d` and the 95th percentile of their sizes (`d` not empty).
fn median_and_p95(mut d: Vec<f32>) -> (f32, f32) {
    d.sort_by(f32::total_cmp);
    let median = d[d.len() / 2];
    let mut a: Vec<f32> = d.iter().map(|x| x.abs()).collect();
    a.sort_by(f32::total_cmp);
    (median, a[(a.len() * 95 / 100).min(a.len() - 1)])
}

/// Median signed distance and 95th percentile of the distance of the measured surfels from the
/// analytic surface, in spacings; `None` without surfels.
fn offsets(shape: &Shape, source: SurfelSource, steps: u32) -> Option<(f32, f32, usize)> {
    offsets_with(shape, source, steps, Calibration::Boundary)
}

/// [`offsets`] with the given calibration.
fn offsets_with(
    shape: &Shape,
    source: SurfelSource,
    steps: u32,
    calibration: Calibration,
) -> Option<(f32, f32, usize)> {
    let scene = &shape.scene;
    let mut params = PipelineParams {
        support_radius: Some(scene.support_radius),
        source,
        ..Default::default()
    };
    params.refine.steps = steps;
    params.grid.calibration = calibration;
    let mut p = Pipeline::new(params).unwrap();
    let f = p.frame_through(&scene.particles, Through::Surfels).unwrap();
    let analytic = scene.shape.unwrap();
    let d: Vec<f32> = f
        .surfels?
        .positions
        .iter()
        .filter(|q| (shape.measured)(**q))
        .map(|&q| -analytic.depth(q) / scene.spacing)
        .collect();
    if d.is_empty() {
        return None;
    }
    let n = d.len();
    let (median, p95) = median_and_p95(d);
    Some((median, p95, n))
}

/// The table of issue 35, measured: every shape through the particle source and the chain
/// (`calibration = "boundary"`) at 0 to 3 refinement steps. Asserted: the chain at every level
/// within 0.1 spacings (median) and 0.25 (95th percentile) of the boundary, 0.2 and 0.35 on the
/// radius-2 drop and tube; the same for the raw-particle source. Measured: within 0.03 (median)
/// and 0.08 (95th percentile) at every level and from the particles, the one-layer slab 0.95
/// spacings thick; with the paper's sums +2.2..+2.6, +0.9..+1.1, +0.30..+0.37 and -0.06..0.00
/// spacings at 0 to 3 steps, +0.54..+0.74 from the particles, and the one-layer slab 2.5 thick.
#[test]
fn the_surface_lies_at_the_fluids_boundary() {
    let shapes = vec![
        slab(1),
        slab(2),
        slab(4),
        tube(2.0),
        tube(3.0),
        tube(5.0),
        drop(2.0),
        drop(3.0),
        drop(5.0),
        drop(8.0),
    ];
    let cell = |r: Option<(f32, f32, usize)>| match r {
        Some((m, p, _)) => format!("{m:+.2} ({p:.2})"),
        None => "(no surfels)".to_owned(),
    };
    println!(
        "median offset from the analytic surface in spacings (95th percentile of the distance)"
    );
    println!(
        "{:22} {:>14} {:>14} {:>14} {:>14} {:>14} {:>14}",
        "shape", "particles, paper", "particles", "chain 0", "chain 1", "chain 2", "chain 3"
    );
    let mut failures = Vec::new();
    for shape in &shapes {
        let particles = offsets(shape, SurfelSource::Particles, 3);
        let particles_paper = offsets_with(shape, SurfelSource::Particles, 3, Calibration::Paper);
        let chain: Vec<_> = (0..=3)
            .map(|k| offsets(shape, SurfelSource::Chain, k))
            .collect();
        println!(
            "{:22} {:>14} {:>14} {:>14} {:>14} {:>14} {:>14}",
            shape.name,
            cell(particles_paper),
            cell(particles),
            cell(chain[0]),
            cell(chain[1]),
            cell(chain[2]),
            cell(chain[3])
        );
        let small = shape.name.ends_with("radius 2s");
        let (median_bound, p95_bound) = if small { (0.2, 0.35) } else { (0.1, 0.25) };
        for (what, r) in chain
            .iter()
            .enumerate()
            .map(|(k, r)| (format!("chain at {k} steps"), r))
            .chain([("particles".to_owned(), &particles)])
        {
            match r {
                Some((m, p, n)) if m.abs() <= median_bound && *p <= p95_bound && *n > 20 => {}
                other => failures.push(format!("{}, {what}: {other:?}", shape.name)),
            }
        }
    }
    assert!(failures.is_empty(), "{failures:?}");
}

/// The tube scene is what it says: its outermost particles lie half a spacing inside the
/// analytic surface and every particle inside it.
#[test]
fn tube_shells_sit_half_a_spacing_inside() {
    let p = TubeParams::default();
    let scene = scenes::tube(&p).unwrap();
    let shape = scene.shape.unwrap();
    let s = p.spacing;
    let depths: Vec<f32> = scene
        .particles
        .positions
        .iter()
        .map(|&q| shape.depth(q) / s)
        .collect();
    let least = depths.iter().copied().fold(f32::MAX, f32::min);
    assert!((least - 0.5).abs() < 1e-4, "{least}");
    // shells at 2.5, 1.5 and 0.5 spacings: 16, 9 and 3 particles a ring, 24 rings
    assert_eq!(scene.particles.len(), (16 + 9 + 3) * 24);
}

/// The same bounds plus 0.1 spacings on arrangements the constants were not fitted to: shells
/// and tube rings jittered by 10 % of a spacing (median 0.2, 95th percentile 0.35), and
/// jittered cubic-lattice spheres (their surface a staircase), judged against the outermost
/// particle along each surfel's direction, half a spacing out. Those meet the median's 0.2 at
/// 1-3 steps (measured +0.07..+0.20) but not at level 0 (+0.28 and +0.33: the raw particles'
/// kernels round the staircase's corners outwards), bounded at 0.4 there; their 95th
/// percentile is the staircase's corners (1.3-2.2 spacings), printed only.
#[test]
fn the_boundary_holds_on_arrangements_not_fitted() {
    use fluid_surfels::scenes::AnalyticShape;
    let jittered = |mut shape: Shape, scene: Scene| {
        shape.scene = scene;
        shape.name += ", jittered";
        shape
    };
    let shapes = vec![
        jittered(
            drop(3.0),
            scenes::sphere(&SphereParams {
                radius_in_spacings: 3.0,
                jitter: 0.1,
                seed: 11,
                ..Default::default()
            })
            .unwrap(),
        ),
        jittered(
            drop(5.0),
            scenes::sphere(&SphereParams {
                radius_in_spacings: 5.0,
                jitter: 0.1,
                seed: 12,
                ..Default::default()
            })
            .unwrap(),
        ),
        jittered(
            tube(3.0),
            scenes::tube(&TubeParams {
                radius_in_spacings: 3.0,
                jitter: 0.1,
                seed: 13,
                ..Default::default()
            })
            .unwrap(),
        ),
    ];
    let mut lattice = Vec::new();
    for radius in [4.0, 6.0] {
        let mut scene = scenes::lattice_sphere(&SphereParams {
            radius_in_spacings: radius,
            jitter: 0.1,
            seed: 14,
            ..Default::default()
        })
        .unwrap();
        let outermost = scene
            .particles
            .positions
            .iter()
            .map(|p| p.length())
            .fold(0.0, f32::max);
        scene.shape = Some(AnalyticShape::Sphere {
            centre: glam::Vec3::ZERO,
            radius: outermost + 0.5 * scene.spacing,
        });
        lattice.push((format!("lattice sphere {radius}s"), scene));
    }
    let mut failures = Vec::new();
    for shape in &shapes {
        let row: Vec<_> = (0..=3)
            .map(|k| offsets(shape, SurfelSource::Chain, k))
            .collect();
        println!("{:28} {row:.2?}", shape.name);
        for (k, r) in row.iter().enumerate() {
            match r {
                Some((m, p, n)) if m.abs() <= 0.2 && *p <= 0.35 && *n > 20 => {}
                other => failures.push(format!("{} at {k} steps: {other:?}", shape.name)),
            }
        }
    }
    // the lattice spheres' staircase: each surfel against the outermost particle along its
    // direction (within half a spacing of the ray from the centre), half a spacing out
    for (name, scene) in &lattice {
        let s = scene.spacing;
        let ps = &scene.particles.positions;
        for k in 0..=3 {
            let mut params = PipelineParams {
                support_radius: Some(scene.support_radius),
                ..Default::default()
            };
            params.refine.steps = k;
            params.grid.calibration = Calibration::Boundary;
            let f = Pipeline::new(params)
                .unwrap()
                .frame_through(&scene.particles, Through::Surfels)
                .unwrap();
            let d: Vec<f32> = f
                .surfels
                .unwrap()
                .positions
                .iter()
                .filter_map(|q| {
                    let u = q.normalize_or_zero();
                    let local = ps
                        .iter()
                        .filter(|p| p.dot(u) > 0.0 && (**p - u * p.dot(u)).length() < 0.5 * s)
                        .map(|p| p.dot(u))
                        .fold(f32::MIN, f32::max);
                    (local > f32::MIN).then(|| (q.length() - local - 0.5 * s) / s)
                })
                .collect();
            let n = d.len();
            let (median, p95) = median_and_p95(d);
            println!("{name:28} {k} steps: {median:+.2} ({p95:.2}), {n} surfels");
            let bound = if k == 0 { 0.4 } else { 0.2 };
            if !(median.abs() <= bound && n > 100) {
                failures.push(format!("{name} at {k} steps: median {median}, {n} surfels"));
            }
        }
    }
    assert!(failures.is_empty(), "{failures:?}");
}

/// A lone particle is a drop of its own volume: a ball of radius 0.62 spacings at every level
/// and from the raw-particle source.
#[test]
fn a_lone_particle_is_a_ball_of_its_own_volume() {
    let s = 0.05;
    let set = fluid_surfels::ParticleSet::from_positions(vec![glam::Vec3::new(0.1, 0.2, 0.3)]);
    for steps in 0..=3 {
        let mut params = PipelineParams {
            support_radius: Some(2.0 * s),
            ..Default::default()
        };
        params.refine.steps = steps;
        params.grid.calibration = Calibration::Boundary;
        let mut p = Pipeline::new(params).unwrap();
        let f = p.frame_through(&set, Through::Surfels).unwrap();
        let surfels = f.surfels.expect("a lone particle is drawn");
        let r: Vec<f32> = surfels
            .positions
            .iter()
            .map(|q| q.distance(glam::Vec3::new(0.1, 0.2, 0.3)) / s)
            .collect();
        let mean = r.iter().sum::<f32>() / r.len() as f32;
        println!("{steps} steps: {} surfels at {mean:.3} spacings", r.len());
        assert!((mean - 0.62).abs() <= 0.1, "{steps} steps: radius {mean}");
    }
    // the raw-particle source draws it too, at the same size
    let mut params = PipelineParams {
        support_radius: Some(2.0 * s),
        source: SurfelSource::Particles,
        ..Default::default()
    };
    params.grid.calibration = Calibration::Boundary;
    let f = Pipeline::new(params)
        .unwrap()
        .frame_through(&set, Through::Surfels)
        .unwrap();
    let surfels = f
        .surfels
        .expect("a lone particle is drawn by the particle source");
    let mean = surfels
        .positions
        .iter()
        .map(|q| q.distance(glam::Vec3::new(0.1, 0.2, 0.3)) / s)
        .sum::<f32>()
        / surfels.len() as f32;
    println!(
        "particle source: {} surfels at {mean:.3} spacings",
        surfels.len()
    );
    assert!((mean - 0.62).abs() <= 0.1, "particle source: radius {mean}");
}

/// The weights the boundary calibration gives the refined points are summed alike on every CPU
/// path: the streamed dense grid equals the naive reference, the exact density (the surfels'
/// projection) equals the grid, weights of 1 change nothing bit for bit, and the sparse grid of
/// the calibrated chain gives the dense grid's surfels. The GPU's splatting density (the
/// default method) sums them alike too (issue 37; both methods in `tests/gpu.rs`).
#[test]
fn weighted_points_sum_alike_on_every_cpu_path() {
    use fluid_surfels::density::{self, GridSpec, Kernel, Points, Resolution};
    use fluid_surfels::surfels::ExactDensity;
    let scene = drop(3.0).scene;
    let pos = &scene.particles.positions;
    let h = scene.support_radius;
    let radii: Vec<f32> = (0..pos.len())
        .map(|i| h * (0.5 + 0.5 * ((i * 7) % 11) as f32 / 10.0))
        .collect();
    let weights: Vec<f32> = (0..pos.len())
        .map(|i| ((i * 5) % 13) as f32 / 4.0)
        .collect();
    let ones = vec![1.0; pos.len()];
    let plain = Points::with_radii(pos, &radii, h);
    let points = plain.with_weights(&weights);
    let spec = GridSpec::around(pos, h, Resolution::LongestAxis(40)).unwrap();
    let kernel = Kernel::Wyvill;
    let dense = density::points_grid(points, &spec, kernel, 1 << 30).unwrap();
    let naive = density::points_naive(points, &spec, kernel).unwrap();
    let max = naive.max();
    let worst = largest_difference(&dense.values, &naive.values);
    assert!(worst <= 1e-5 * max, "{worst} of {max}");
    let exact = ExactDensity::of(points, kernel).unwrap();
    let [nx, ny, nz] = spec.dims;
    for (i, j, k) in [
        (nx / 2, ny / 2, nz / 2),
        (nx / 3, ny / 2, nz / 4),
        (5, 7, 9),
    ] {
        let v = dense.values[(i + nx * (j + ny * k)) as usize];
        let e = exact.value(spec.point(i, j, k));
        assert!((v - e).abs() <= 1e-5 * max, "{v} vs {e}");
    }
    let unweighted = density::points_grid(plain, &spec, kernel, 1 << 30).unwrap();
    let unit = density::points_grid(plain.with_weights(&ones), &spec, kernel, 1 << 30).unwrap();
    assert_eq!(unweighted.values, unit.values);
    // the calibrated chain on the sparse grid
    let surfels = |narrow_band: bool| {
        let mut params = PipelineParams {
            support_radius: Some(h),
            ..Default::default()
        };
        params.refine.steps = 2;
        params.grid.calibration = Calibration::Boundary;
        params.grid.narrow_band = narrow_band;
        let mut p = Pipeline::new(params).unwrap();
        p.frame_through(&scene.particles, Through::Surfels)
            .unwrap()
            .surfels
            .unwrap()
    };
    let (a, b) = (surfels(false), surfels(true));
    assert!(a.len() > 100);
    assert_eq!(a.positions, b.positions);
    if let Some(ctx) = fluid_surfels::gpu::context_or_skip("weighted_points").unwrap() {
        // the GPU's default method (the splatting) sums the weights too (issue 37)
        let gpu = density::gpu::density_grid_gpu(&ctx, points, &spec, kernel).unwrap();
        let worst = largest_difference(&gpu.values, &naive.values);
        assert!(worst <= 1e-5 * max, "GPU: {worst} of {max}");
    }
}

/// The calibrated chain and particle source give the same surfels on 1, 2 and 3 threads (the
/// weights' Jacobi steps read the previous step's weights only).
#[test]
fn the_calibration_does_not_depend_on_the_thread_count() {
    let scene = scenes::sphere(&SphereParams {
        radius_in_spacings: 4.0,
        jitter: 0.1,
        seed: 21,
        ..Default::default()
    })
    .unwrap();
    for source in [SurfelSource::Chain, SurfelSource::Particles] {
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| {
                let mut params = PipelineParams {
                    support_radius: Some(scene.support_radius),
                    source,
                    ..Default::default()
                };
                params.refine.steps = 2;
                params.grid.calibration = Calibration::Boundary;
                Pipeline::new(params)
                    .unwrap()
                    .frame_through(&scene.particles, Through::Surfels)
                    .unwrap()
                    .surfels
                    .unwrap()
            })
        };
        let one = run(1);
        assert!(one.len() > 100);
        for threads in [2, 3] {
            let other = run(threads);
            assert_eq!(
                one.positions, other.positions,
                "{source:?}, {threads} threads"
            );
            assert_eq!(one.normals, other.normals, "{source:?}, {threads} threads");
        }
    }
}

/// Past three steps the refined points' kernel (twice the final radius) is shorter than the half
/// spacing the surface must lie outside them: the calibrated chain refuses with a clear error
/// instead of drawing the water too small; three steps pass.
#[test]
fn deeper_levels_are_refused_with_a_clear_error() {
    let scene = drop(3.0).scene;
    let run = |steps: u32| {
        let mut params = PipelineParams {
            support_radius: Some(scene.support_radius),
            ..Default::default()
        };
        params.refine.steps = steps;
        params.grid.calibration = Calibration::Boundary;
        Pipeline::new(params)
            .unwrap()
            .frame_through(&scene.particles, Through::Surfels)
    };
    assert!(run(3).is_ok());
    let e = run(4).unwrap_err().to_string();
    assert!(
        e.contains("refine.steps") && e.contains("at most 3 steps"),
        "{e}"
    );
}

/// The two real files (the dam break BGEO, the double dam break VTK) at 1, 2 and 3 refinement
/// steps everywhere (fixed detail), shaded splats from one camera (400x400, white background):
/// with the boundary calibration the levels agree far better than with the paper's sums, and
/// the silhouette stays closed. The goals (32 dB between any two levels, enclosed holes
/// at most 0.1 %) are not met; measured 2026-12-06: 24.7-26.8 dB (dam break) and 26.4-28.3 dB
/// (double dam break) with the calibration, 19.3-22.8 and 18.0-22.5 with the paper's sums;
/// enclosed holes 0.14-0.27 % on the dam break (background between the splash's drops and
/// sheets; the paper's 0.12-0.17 %), at most 0.02 % on the double dam break. The bounds keep
/// these from falling. Printed beside them, the metric's floor: 3 steps against 3 steps on a
/// grid 0.5 % finer, one surface sampled twice, 32.4 and 33.0 dB (the splats' silhouettes are
/// not anti-aliased: most of that error is pixels that flip between water and background).
/// Before 2026-12-06 the test ran the view's detail, which stops the dam break at two steps at
/// this size, so its "3 steps" were its 2 (3-2: infinite PSNR).
#[test]
fn the_real_files_levels_agree_at_the_boundary() {
    use fluid_surfels::{io, quality, splat};
    let data = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data");
    for (name, psnr_bound, holes_bound) in [
        ("dam_break_frame_23_24389_particles.bgeo", 24.5, 0.005),
        ("double_dam_break_frame_26_4732_particles.vtk", 26.0, 0.001),
    ] {
        let set = io::read_particles(&data.join(name), None).unwrap();
        let mut db = Vec::new();
        // the chain's calibrations (`volume` weighs the raw particles alone)
        for calibration in [Calibration::Paper, Calibration::Boundary] {
            let mut camera = None;
            let mut images = Vec::new();
            let mut cell = 0.0;
            let params = |steps| {
                let mut p = PipelineParams {
                    source: SurfelSource::Chain,
                    // each level everywhere (the view's detail would stop the dam break at
                    // two steps at this size: its "3 steps" were its 2)
                    detail: fluid_surfels::pipeline::Detail::Fixed,
                    ..Default::default()
                };
                p.scene.optics.image_size = [400, 400];
                p.splat.background = [1.0; 4];
                p.grid.calibration = calibration;
                p.refine.steps = steps;
                p
            };
            for steps in [3, 2, 1] {
                let mut pipeline = Pipeline::new(params(steps)).unwrap();
                if let Some(c) = camera {
                    pipeline.set_camera(c);
                }
                let frame = pipeline.frame_through(&set, Through::Splats).unwrap();
                if steps == 3 {
                    cell = frame.detail.cell;
                }
                let r = frame.splats.unwrap();
                camera = pipeline.camera();
                let covered: Vec<bool> = r.colour.iter().map(|c| c[3] > 0.0).collect();
                let h = quality::holes(&covered, 400, 400, 3);
                println!(
                    "{name} {} {steps} steps: enclosed holes {:.3} %",
                    calibration.as_str(),
                    100.0 * h.enclosed_fraction()
                );
                if calibration == Calibration::Boundary {
                    assert!(
                        h.enclosed_fraction() <= holes_bound,
                        "{name} {steps}: {h:?}"
                    );
                }
                images.push(r.image);
            }
            let pairs = [(0, 1), (0, 2), (1, 2)].map(|(a, b)| splat::psnr(&images[a], &images[b]));
            println!(
                "{name} {}: 3-2 {:.1} dB, 3-1 {:.1} dB, 2-1 {:.1} dB",
                calibration.as_str(),
                pairs[0],
                pairs[1],
                pairs[2]
            );
            db.push(pairs.iter().copied().fold(f64::INFINITY, f64::min));
            if calibration == Calibration::Boundary {
                // the metric's floor: the same surface (3 steps) on a grid 0.5 % finer, its
                // surfels sampled elsewhere (measured by hand on the dam break: 61 % of the
                // squared error in silhouette pixels that flip)
                let mut p = params(3);
                p.grid.resolution =
                    Some(fluid_surfels::density::Resolution::CellSize(0.995 * cell));
                let mut pipeline = Pipeline::new(p).unwrap();
                pipeline.set_camera(camera.unwrap());
                let finer = pipeline
                    .frame_through(&set, Through::Splats)
                    .unwrap()
                    .splats
                    .unwrap()
                    .image;
                println!(
                    "{name}: 3 steps on a grid 0.5 % finer {:.1} dB from 3 steps (one surface sampled twice)",
                    splat::psnr(&images[0], &finer)
                );
            }
        }
        let (paper, boundary) = (db[0], db[1]);
        assert!(boundary >= psnr_bound, "{name}: {boundary} dB");
        assert!(
            boundary >= paper + 3.0,
            "{name}: {boundary} against {paper} dB"
        );
    }
}

/// The largest absolute difference between two grids' values.
fn largest_difference(a: &[f32], b: &[f32]) -> f32 {
    a.iter()
        .zip(b)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max)
}

/// A solid torus about the y axis (major radius `big`, minor `small`, in spacings of `s`), built
/// like `scenes::tube`: shells of minor radius `(k + 1/2) s` (the outermost half a spacing inside
/// the analytic surface), each a set of circles about the y axis a spacing apart round the
/// shell, a circle of radius `rho` holding `round(2 pi rho / s)` particles; the innermost shell
/// of an integer radius the core circle. Returns the particles and the analytic depth.
fn torus(big: f32, small: f32, s: f32) -> (Vec<glam::Vec3>, impl Fn(glam::Vec3) -> f32) {
    use std::f32::consts::TAU;
    let mut p = Vec::new();
    let shells = (small - 0.5).floor() as i32;
    for k in 0..=shells {
        let r = small - 0.5 - k as f32;
        if r < 0.0 {
            continue;
        }
        let around = ((TAU * r).round() as usize).max(1);
        for j in 0..around {
            let theta = TAU * j as f32 / around as f32 + 0.37 * k as f32;
            let (rho, y) = (big + r * theta.cos(), r * theta.sin());
            let count = (TAU * rho).round() as usize;
            for i in 0..count {
                let phi = TAU * (i as f32 + 0.5 * (j % 2) as f32) / count as f32;
                p.push(glam::Vec3::new(rho * phi.cos(), y, rho * phi.sin()) * s);
            }
        }
    }
    let depth = move |q: glam::Vec3| {
        small * s - glam::Vec2::new(glam::Vec2::new(q.x, q.z).length() - big * s, q.y).length()
    };
    (p, depth)
}

/// The chain's mesh of analytic shapes (issue 40), `Through::Mesh` at the default calibration,
/// at three steps and one and from the raw particles: a slab, a tube, a drop, two drops and a torus, each closed and manifold with
/// the shape's Euler characteristic (2, 2, 2, 4, 0) and no degenerate triangle; every vertex
/// within 0.05 cells of its surfel (the projection of the same crossing onto the exact
/// iso-surface: a vertex kept on its grid edge so as not to fold a triangle is the one that can
/// differ), and the vertices where the surfels are, at the fluid's boundary: median distance
/// from the analytic surface within 0.1 spacings, 95th percentile within 0.25 (the surfels'
/// bounds, `the_surface_lies_at_the_fluids_boundary`).
#[test]
fn meshes_of_analytic_shapes_are_closed_at_the_boundary() {
    let s = 0.05;
    let (slab, tube, drop) = (slab(4), tube(3.0), drop(5.0));
    let two_drops: Vec<glam::Vec3> = drop
        .scene
        .particles
        .positions
        .iter()
        .flat_map(|&q| [q, q + glam::Vec3::new(14.0 * s, 0.0, 0.0)])
        .collect();
    let one = drop.scene.shape.unwrap();
    let (ring, ring_depth) = torus(8.0, 3.0, s);
    // name, particles, Euler characteristic, analytic depth, where measured
    type Depth<'a> = Box<dyn Fn(glam::Vec3) -> f32 + 'a>;
    type Case<'a> = (
        &'a str,
        Vec<glam::Vec3>,
        i64,
        Depth<'a>,
        &'a dyn Fn(glam::Vec3) -> bool,
    );
    let cases: Vec<Case> = vec![
        (
            "slab",
            slab.scene.particles.positions.clone(),
            2,
            Box::new(|q| slab.scene.shape.unwrap().depth(q)),
            &*slab.measured,
        ),
        (
            "tube",
            tube.scene.particles.positions.clone(),
            2,
            Box::new(|q| tube.scene.shape.unwrap().depth(q)),
            &*tube.measured,
        ),
        (
            "drop",
            drop.scene.particles.positions.clone(),
            2,
            Box::new(move |q| one.depth(q)),
            &|_| true,
        ),
        (
            "two drops",
            two_drops,
            4,
            Box::new(move |q| {
                one.depth(q)
                    .max(one.depth(q - glam::Vec3::new(14.0 * s, 0.0, 0.0)))
            }),
            &|_| true,
        ),
        ("torus", ring, 0, Box::new(ring_depth), &|_| true),
    ];
    let levels = [
        (SurfelSource::Chain, 3),
        (SurfelSource::Chain, 1),
        (SurfelSource::Particles, 3),
    ];
    for ((name, positions, euler, depth, measured), (source, steps)) in
        cases.iter().flat_map(|c| levels.map(|level| (c, level)))
    {
        let mut params = PipelineParams {
            support_radius: Some(2.0 * s),
            source,
            ..Default::default()
        };
        params.refine.steps = steps;
        let name = format!("{name}, {} at {steps} steps", source.as_str());
        let set = fluid_surfels::ParticleSet::from_positions(positions.clone());
        let frame = Pipeline::new(params)
            .unwrap()
            .frame_through(&set, Through::Mesh)
            .unwrap();
        let mesh = frame.mesh.as_ref().unwrap();
        let surfels = frame.surfels.as_ref().unwrap();
        let cell = frame.grid.as_ref().unwrap().spec().spacing;
        let topology = mesh.topology();
        assert!(topology.closed, "{name}: not closed");
        assert_eq!(topology.euler_characteristic, *euler, "{name}");
        assert!(
            !mesh.triangles.iter().any(|t| mesh.is_collapsed(t)),
            "{name}: a degenerate triangle"
        );
        assert_eq!(mesh.positions.len(), surfels.len(), "{name}");
        let off_surfels = mesh
            .positions
            .iter()
            .zip(&surfels.positions)
            .map(|(v, q)| v.distance(*q) / cell)
            .fold(0.0f32, f32::max);
        let (median, p95) = median_and_p95(
            mesh.positions
                .iter()
                .filter(|q| measured(**q))
                .map(|&q| -depth(q) / s)
                .collect(),
        );
        println!(
            "{name}: {} particles, {} vertices, {} triangles, Euler {euler}; farthest vertex from its surfel {off_surfels:.3} cells; from the analytic surface median {median:+.3}, 95th percentile {p95:.3} spacings",
            set.len(),
            mesh.positions.len(),
            mesh.triangles.len()
        );
        assert!(off_surfels <= 0.05, "{name}: {off_surfels} cells");
        assert!(
            median.abs() <= 0.1 && p95 <= 0.25,
            "{name}: {median}, {p95}"
        );
    }
}
