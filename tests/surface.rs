//! Surface detection against analytic truth, hysteresis on the simulated column, normals, and
//! degenerate inputs.

use fluid_surfels::neighbours::{self, Backend, Neighbourhoods};
use fluid_surfels::scenes::{self, ColumnParams, ColumnSim, Scene};
use fluid_surfels::surface::{
    self, NormalMethod, ParticleClass, SurfaceDetector, SurfaceError, SurfaceParams, detect_surface,
};
use fluid_surfels::{Error, ParticleSet};
use glam::Vec3;

fn neighbourhoods(scene: &Scene) -> Neighbourhoods {
    Neighbourhoods::build(
        &scene.particles.positions,
        scene.support_radius,
        Backend::CellGrid,
    )
    .unwrap()
}

/// Recall and precision of the default detector against "within one spacing of the boundary".
fn recall_precision(scene: &Scene) -> (f64, f64) {
    let shape = scene.shape.unwrap();
    let surface = detect_surface(
        &scene.particles,
        &neighbourhoods(scene),
        &SurfaceParams::default(),
    )
    .unwrap();
    let (mut tp, mut fp, mut fneg) = (0usize, 0usize, 0usize);
    for (p, class) in scene.particles.positions.iter().zip(&surface.classes) {
        match (
            shape.depth(*p) < scene.spacing,
            *class == ParticleClass::Surface,
        ) {
            (true, true) => tp += 1,
            (false, true) => fp += 1,
            (true, false) => fneg += 1,
            (false, false) => {}
        }
    }
    assert!(tp > 0, "no true positive at all");
    (tp as f64 / (tp + fneg) as f64, tp as f64 / (tp + fp) as f64)
}

#[test]
fn block_and_sphere_recall_and_precision() {
    let block = scenes::block(&scenes::BlockParams::default()).unwrap();
    let sphere = scenes::sphere(&scenes::SphereParams::default()).unwrap();
    for scene in [&block, &sphere] {
        assert!(scene.particles.len() >= 20_000);
        let (recall, precision) = recall_precision(scene);
        println!(
            "{}: {} particles, recall {:.2} %, precision {:.2} %",
            scene.name,
            scene.particles.len(),
            recall * 100.0,
            precision * 100.0
        );
        assert!(recall >= 0.98, "{} recall {recall}", scene.name);
        assert!(precision >= 0.95, "{} precision {precision}", scene.name);
    }
}

#[test]
fn hysteresis_flips_far_fewer_particles_than_one_threshold() {
    // 100 frames of the settling pool once the splash has died down (frames 101..=200,
    // 3.4 s to 6.7 s after the column was released)
    let mut sim = ColumnSim::new(ColumnParams::default()).unwrap();
    sim.advance_to(100);
    let frames: Vec<ParticleSet> = (0..100)
        .map(|_| {
            sim.step_frame();
            sim.particles().clone()
        })
        .collect();
    let nbs: Vec<Neighbourhoods> = frames
        .iter()
        .map(|f| {
            Neighbourhoods::build(&f.positions, sim.support_radius(), Backend::CellGrid).unwrap()
        })
        .collect();
    let defaults = SurfaceParams::default();
    let single = SurfaceParams {
        low_threshold: defaults.high_threshold,
        ..defaults
    };
    let flips = |params: SurfaceParams| {
        let mut detector = SurfaceDetector::new(params).unwrap();
        frames
            .iter()
            .zip(&nbs)
            .map(|(f, nb)| detector.detect(f, nb).unwrap().flips)
            .sum::<usize>()
    };
    let with = flips(defaults);
    let without = flips(single);
    println!(
        "column frames 101-200: flips per frame {:.2} with hysteresis, {:.2} with a single threshold",
        with as f64 / 99.0,
        without as f64 / 99.0
    );
    assert!(without >= 50, "too few flips to compare: {without}");
    assert!(4 * with <= without, "hysteresis {with} vs single {without}");
}

#[test]
fn normals_on_a_sphere_point_outwards() {
    let scene = scenes::sphere(&scenes::SphereParams::default()).unwrap();
    let shape = scene.shape.unwrap();
    let nb = neighbourhoods(&scene);
    for method in [NormalMethod::Covariance, NormalMethod::ColourField] {
        let params = SurfaceParams {
            normals: method,
            ..SurfaceParams::default()
        };
        let surface = detect_surface(&scene.particles, &nb, &params).unwrap();
        let idx = surface.indices_of(ParticleClass::Surface);
        let mut angles: Vec<f32> = idx
            .iter()
            .map(|&i| {
                let n = surface.normals[i];
                assert!(
                    (n.length() - 1.0).abs() < 1e-4,
                    "normal {n} of particle {i} is not unit"
                );
                n.dot(shape.normal(scene.particles.positions[i]))
                    .clamp(-1.0, 1.0)
                    .acos()
                    .to_degrees()
            })
            .collect();
        angles.sort_by(f32::total_cmp);
        let within = angles.iter().filter(|&&a| a <= 10.0).count() as f64 / angles.len() as f64;
        println!(
            "{method:?}: {} surface particles, {:.2} % within 10 degrees, median {:.2}, 95th percentile {:.2} degrees",
            angles.len(),
            within * 100.0,
            angles[angles.len() / 2],
            angles[angles.len() * 95 / 100]
        );
        assert!(within >= 0.95, "{method:?}: {within}");
        // interior particles carry no normal
        assert!(
            surface
                .indices_of(ParticleClass::Interior)
                .iter()
                .all(|&i| surface.normals[i] == Vec3::ZERO)
        );
    }
}

#[test]
fn state_follows_particle_ids_not_indices() {
    // Two consecutive frames; in the second, particles are stored in reverse order. A detector
    // that matched by index would mix up the hysteresis state.
    let mut sim = ColumnSim::new(ColumnParams::default()).unwrap();
    sim.advance_to(30);
    let a = sim.particles().clone();
    sim.step_frame();
    let b = sim.particles().clone();
    let reversed: Vec<usize> = (0..b.len()).rev().collect();
    let b_rev = b.select(&reversed);
    let r = sim.support_radius();
    let nb = |p: &ParticleSet| Neighbourhoods::build(&p.positions, r, Backend::CellGrid).unwrap();
    let mut straight = SurfaceDetector::new(SurfaceParams::default()).unwrap();
    let mut shuffled = straight.clone();
    straight.detect(&a, &nb(&a)).unwrap();
    shuffled.detect(&a, &nb(&a)).unwrap();
    let s1 = straight.detect(&b, &nb(&b)).unwrap();
    let s2 = shuffled.detect(&b_rev, &nb(&b_rev)).unwrap();
    for (k, &i) in reversed.iter().enumerate() {
        assert_eq!(s1.classes[i], s2.classes[k], "particle {i}");
    }
    assert_eq!(s1.flips, s2.flips);
    // and hysteresis does act on this pair of frames
    let fresh = detect_surface(&b, &nb(&b), &SurfaceParams::default()).unwrap();
    assert!(
        fresh.counts().surface < s1.counts().surface,
        "{:?} vs {:?}",
        fresh.counts(),
        s1.counts()
    );
}

#[test]
fn parallel_detection_matches_the_single_threaded_reference() {
    for scene in [
        scenes::build(scenes::SceneName::Column, Some(ColumnParams::SPLASH_FRAME)).unwrap(),
        scenes::block(&scenes::BlockParams {
            counts: [20, 15, 10],
            ..Default::default()
        })
        .unwrap(),
    ] {
        let r = scene.support_radius;
        let params = SurfaceParams::default();
        let fast = detect_surface(&scene.particles, &neighbourhoods(&scene), &params).unwrap();
        let lists = neighbours::reference_neighbours(&scene.particles.positions, r);
        let (classes, normals) = surface::detect_reference(&scene.particles, &lists, r, &params);
        assert_eq!(fast.classes, classes, "{}", scene.name);
        for (i, (a, b)) in fast.normals.iter().zip(&normals).enumerate() {
            assert!(
                a.angle_between(*b) < 1e-2 || (*a == Vec3::ZERO && *b == Vec3::ZERO),
                "{}: particle {i}: {a} vs {b}",
                scene.name
            );
        }
    }
}

#[test]
fn degenerate_inputs_give_errors_or_documented_results() {
    let params = SurfaceParams::default();
    // empty set: empty result
    let empty = ParticleSet::default();
    let nb = Neighbourhoods::build(&empty.positions, 1.0, Backend::CellGrid).unwrap();
    let s = detect_surface(&empty, &nb, &params).unwrap();
    assert!(s.classes.is_empty());
    // one particle: isolated, no normal
    let one = ParticleSet::from_positions(vec![Vec3::ONE]);
    let nb = Neighbourhoods::build(&one.positions, 1.0, Backend::CellGrid).unwrap();
    let s = detect_surface(&one, &nb, &params).unwrap();
    assert_eq!(s.classes, vec![ParticleClass::Isolated]);
    assert_eq!(s.normals, vec![Vec3::ZERO]);
    // coincident particles: every offset is zero, so all are interior; normals finite
    let same = ParticleSet::from_positions(vec![Vec3::ONE; 5]);
    let nb = Neighbourhoods::build(&same.positions, 1.0, Backend::CellGrid).unwrap();
    for method in [NormalMethod::Covariance, NormalMethod::ColourField] {
        let s = detect_surface(
            &same,
            &nb,
            &SurfaceParams {
                normals: method,
                ..params
            },
        )
        .unwrap();
        assert!(s.classes.iter().all(|&c| c == ParticleClass::Interior));
        assert!(s.normals.iter().all(|n| n.is_finite()));
    }
    // two particles: both surface, normals finite unit vectors along the pair
    let pair = ParticleSet::from_positions(vec![Vec3::ZERO, Vec3::X * 0.5]);
    let nb = Neighbourhoods::build(&pair.positions, 1.0, Backend::CellGrid).unwrap();
    for method in [NormalMethod::Covariance, NormalMethod::ColourField] {
        let s = detect_surface(
            &pair,
            &nb,
            &SurfaceParams {
                normals: method,
                ..params
            },
        )
        .unwrap();
        assert_eq!(s.classes, vec![ParticleClass::Surface; 2]);
        assert!(
            s.normals.iter().all(|n| (n.length() - 1.0).abs() < 1e-4),
            "{method:?}: {:?}",
            s.normals
        );
    }
    // NaN positions: the neighbour search refuses them
    let nan = ParticleSet::from_positions(vec![Vec3::ZERO, Vec3::new(0.0, f32::NAN, 0.0)]);
    let err = Neighbourhoods::build(&nan.positions, 1.0, Backend::CellGrid).unwrap_err();
    assert!(
        matches!(
            err,
            neighbours::NeighbourError::NonFinitePosition { index: 1, .. }
        ),
        "{err}"
    );
    // neighbourhoods of another set
    let nb = Neighbourhoods::build(&pair.positions, 1.0, Backend::CellGrid).unwrap();
    assert!(matches!(
        detect_surface(&one, &nb, &params),
        Err(SurfaceError::SizeMismatch { .. })
    ));
    // attribute lengths that do not match
    let mut bad = pair.clone();
    bad.masses = Some(vec![1.0]);
    assert!(matches!(
        detect_surface(&bad, &nb, &params),
        Err(SurfaceError::Particles(_))
    ));
    // thresholds
    for (low, high) in [
        (0.2, 0.1),
        (0.0, 0.1),
        (f32::NAN, 0.1),
        (0.1, f32::INFINITY),
    ] {
        let p = SurfaceParams {
            low_threshold: low,
            high_threshold: high,
            ..params
        };
        assert!(
            matches!(
                SurfaceDetector::new(p),
                Err(SurfaceError::InvalidThresholds { .. })
            ),
            "{low} {high}"
        );
    }
    // the crate error wraps stage errors
    let e: Error = SurfaceError::InvalidThresholds {
        low: 1.0,
        high: 0.0,
    }
    .into();
    assert!(e.to_string().contains("low"));
}

#[test]
fn masses_weight_the_centre_of_mass() {
    // a particle between a heavy and a light neighbour: the offset points away from the heavy one
    let mut set = ParticleSet::from_positions(vec![Vec3::ZERO, Vec3::X * 0.5, -Vec3::X * 0.5]);
    set.masses = Some(vec![1.0, 10.0, 1.0]);
    let nb = Neighbourhoods::build(&set.positions, 0.6, Backend::CellGrid).unwrap();
    let offsets = surface::com_offsets(&set, &nb);
    // sum_j (x_0 - x_j) m_j / sum m = (-0.5*10 + 0.5*1) / 12
    assert!(
        (offsets[0].x - (-4.5 / 12.0)).abs() < 1e-6,
        "{}",
        offsets[0]
    );
}
