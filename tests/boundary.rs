//! The surface at the fluid's boundary (issue 35): on shapes built of shells of particles whose
//! outermost centres lie half a spacing inside the analytic surface (`scenes::block` for slabs,
//! `scenes::tube`, `scenes::sphere` for drops), how far the surfels lie from that surface, in
//! spacings (+: outside, the water too big), per surfel source and refinement level.

use fluid_surfels::pipeline::{Pipeline, PipelineParams, SurfelSource, Through};
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

/// Median signed distance and 95th percentile of the distance of the measured surfels from the
/// analytic surface, in spacings; `None` without surfels.
fn offsets(shape: &Shape, source: SurfelSource, steps: u32) -> Option<(f32, f32, usize)> {
    let scene = &shape.scene;
    let mut params = PipelineParams {
        support_radius: Some(scene.support_radius),
        source,
        ..Default::default()
    };
    params.refine.steps = steps;
    let mut p = Pipeline::new(params).unwrap();
    let f = p.frame_through(&scene.particles, Through::Surfels).unwrap();
    let analytic = scene.shape.unwrap();
    let mut d: Vec<f32> = f
        .surfels?
        .positions
        .iter()
        .filter(|q| (shape.measured)(**q))
        .map(|&q| -analytic.depth(q) / scene.spacing)
        .collect();
    if d.is_empty() {
        return None;
    }
    d.sort_by(f32::total_cmp);
    let median = d[d.len() / 2];
    let mut a: Vec<f32> = d.iter().map(|x| x.abs()).collect();
    a.sort_by(f32::total_cmp);
    let p95 = a[(a.len() * 95 / 100).min(a.len() - 1)];
    Some((median, p95, d.len()))
}

/// The table of issue 35, measured: every shape through the particle source and the chain at 0
/// to 3 refinement steps. Asserted now: the paper's three steps put the surface within 0.1
/// spacings (median) and 0.25 (95th percentile) of the boundary on the larger shapes, 0.2 and
/// 0.35 on the radius-2 drop and tube. The other levels and the particle source are printed
/// (issue 35 calibrates them to the same bounds).
#[test]
fn the_surface_lies_at_the_fluids_boundary() {
    let shapes = vec![
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
        "{:22} {:>14} {:>14} {:>14} {:>14} {:>14}",
        "shape", "particles", "chain 0", "chain 1", "chain 2", "chain 3"
    );
    let mut failures = Vec::new();
    for shape in &shapes {
        let particles = offsets(shape, SurfelSource::Particles, 3);
        let chain: Vec<_> = (0..=3)
            .map(|k| offsets(shape, SurfelSource::Chain, k))
            .collect();
        println!(
            "{:22} {:>14} {:>14} {:>14} {:>14} {:>14}",
            shape.name,
            cell(particles),
            cell(chain[0]),
            cell(chain[1]),
            cell(chain[2]),
            cell(chain[3])
        );
        let small = shape.name.ends_with("radius 2s");
        let (median_bound, p95_bound) = if small { (0.2, 0.35) } else { (0.1, 0.25) };
        match chain[3] {
            Some((m, p, n)) if m.abs() <= median_bound && p <= p95_bound && n > 20 => {}
            other => failures.push(format!("{} at 3 steps: {other:?}", shape.name)),
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
