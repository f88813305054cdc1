//! Particle splatting (Adams, Lenaerts, Dutré 2006; `SplatMode::Spheres`): the CPU reference
//! against an analytic sphere and against its own per-sphere fragments, the depth offset's
//! blending against the seams of the nearest sphere alone, and the GPU path against the CPU
//! reference (on lavapipe in CI; without an adapter the GPU test skips with a message unless
//! FLUID_SURFELS_REQUIRE_GPU=1).

use std::path::PathBuf;

use fluid_surfels::gpu;
use fluid_surfels::scenes;
use fluid_surfels::splat::gpu as gpu_splat;
use fluid_surfels::splat::{self, Camera, Light, Render, SplatMode, SplatParams, Surfel, View};
use glam::{Vec2, Vec3, Vec4Swizzles};

const SIZE: u32 = 128;

fn spheres_params() -> SplatParams {
    SplatParams {
        mode: SplatMode::Spheres,
        ..SplatParams::default()
    }
}

fn output_dir() -> PathBuf {
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("particle_splat");
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// The particles of a lattice sphere (radius 6 spacings) as spheres of the support radius
/// (twice the spacing), with a camera looking at it.
fn particle_sphere() -> (Vec<Surfel>, Camera) {
    let scene = scenes::sphere(&scenes::SphereParams {
        radius_in_spacings: 6.0,
        jitter: 0.1,
        ..Default::default()
    })
    .unwrap();
    let p = &scene.particles.positions;
    let centre = p.iter().copied().sum::<Vec3>() / p.len() as f32;
    let reach = 8.0 * scene.spacing;
    let spheres = splat::spheres_from(p, &[], 2.0 * scene.spacing, splat::WATER);
    let camera = Camera {
        eye: centre + Vec3::new(0.3, 0.4, 1.0).normalize() * 4.0 * reach,
        target: centre,
        ..Default::default()
    };
    (spheres, camera)
}

/// The column scene's splash frame as spheres of its support radius, seen from a fitted camera.
fn column_splash() -> (Vec<Surfel>, Camera) {
    let mut sim = scenes::ColumnSim::new(scenes::ColumnParams::default()).unwrap();
    sim.advance_to(scenes::ColumnParams::SPLASH_FRAME);
    let h = sim.support_radius();
    let spheres = splat::spheres_from(&sim.particles().positions, &[], h, splat::WATER);
    let (lo, hi) = splat::bounds(&spheres).unwrap();
    (spheres, Camera::framing(lo, hi))
}

/// One sphere seen from afar: the centre pixel's depth is the distance less the radius, the
/// silhouette is the projected disk, and the normals are the analytic sphere's.
#[test]
fn one_sphere_has_its_analytic_depth_silhouette_and_normals() {
    let radius = 0.5;
    let distance = 20.0;
    let camera = Camera {
        eye: Vec3::new(0.0, 0.0, distance),
        target: Vec3::ZERO,
        fov_y_degrees: 4.0,
        ..Default::default()
    };
    let spheres = [Surfel::sphere(Vec3::ZERO, radius, splat::WATER)];
    let render = splat::render_cpu(
        &spheres,
        &camera,
        &Light::default(),
        &spheres_params(),
        SIZE,
        SIZE,
    )
    .unwrap();
    render.validate().unwrap();
    let v = View::new(&camera, &Light::default(), &spheres_params(), SIZE, SIZE).unwrap();
    let half_px = radius / (distance * (2.0f32.to_radians()).tan()) * 0.5 * SIZE as f32;
    let (mut inside, mut covered, mut outside_covered, mut worst) = (0, 0, 0, 0.0f32);
    let mut centre_depth = None;
    for y in 0..SIZE {
        for x in 0..SIZE {
            let i = (y * SIZE + x) as usize;
            let e = (Vec2::new(x as f32 + 0.5, y as f32 + 0.5) - Vec2::splat(SIZE as f32 / 2.0))
                / half_px;
            let r = e.length();
            if r < 0.97 {
                inside += 1;
                if let Some(n) = render.normal(i) {
                    covered += 1;
                    // the analytic normal of the ray's hit on the sphere, seen from afar
                    let (o, d) = v.world_ray(Vec2::new(x as f32 + 0.5, y as f32 + 0.5));
                    let d = d.normalize();
                    let b = o.dot(d);
                    let t = -b - (b * b - o.length_squared() + radius * radius).sqrt();
                    let analytic = (o + t * d).normalize();
                    if r < 0.9 {
                        worst = worst.max(n.dot(analytic).clamp(-1.0, 1.0).acos().to_degrees());
                    }
                }
            } else if r > 1.03 && render.weight(i) > 0.0 {
                outside_covered += 1;
            }
            if x == SIZE / 2 && y == SIZE / 2 {
                centre_depth = render.depth(i);
            }
        }
    }
    println!(
        "one sphere: {covered} of {inside} pixels inside covered, {outside_covered} outside; worst normal error {worst:.2} degrees inside 0.9 of the radius"
    );
    assert_eq!(covered, inside, "holes inside the silhouette");
    assert_eq!(outside_covered, 0, "covered pixels outside the silhouette");
    assert!(worst < 3.0, "normal error {worst} degrees");
    // the centre pixel lies 1/64 of the radius off the axis: the sphere's front there
    let depth = centre_depth.expect("centre covered");
    assert!(
        (depth - (distance - radius)).abs() < 1e-3 * distance,
        "centre depth {depth}, expected {}",
        distance - radius
    );
}

/// With epsilon 0 every pixel holds the nearest sphere's fragment alone (its normal exactly), and
/// the normals jump at the seams where two spheres meet; with Adams et al.'s epsilon (1.5 h) the
/// blending removes the jumps.
#[test]
fn epsilon_zero_is_the_nearest_sphere_alone_and_epsilon_removes_the_seams() {
    // a row of spheres one radius apart (the paper's Figure 3), seen head-on
    let h = 0.1;
    let spheres: Vec<Surfel> = (0..9)
        .map(|i| Surfel::sphere(Vec3::new((i as f32 - 4.0) * h, 0.0, 0.0), h, splat::WATER))
        .collect();
    let camera = Camera {
        eye: Vec3::new(0.0, 0.0, 3.0),
        target: Vec3::ZERO,
        fov_y_degrees: 20.0,
        ..Default::default()
    };
    let light = Light::default();
    let render = |eps: f32| {
        let p = SplatParams {
            sphere_depth_offset: eps,
            ..spheres_params()
        };
        let r = splat::render_cpu(&spheres, &camera, &light, &p, SIZE, SIZE).unwrap();
        r.validate().unwrap();
        (r, View::new(&camera, &light, &p, SIZE, SIZE).unwrap())
    };
    // the largest angle between the normals of horizontally neighbouring covered pixels, in the
    // band of rows through the centres (a quarter of the projected radius either side) from the
    // first centre to the last: the seams cross it, the silhouette (whose normals turn fast
    // between pixels on one sphere alone) does not
    let view = View::new(&camera, &light, &spheres_params(), SIZE, SIZE).unwrap();
    let first = view.project(Vec3::from(spheres[0].position));
    let last = view.project(Vec3::from(spheres[8].position));
    let h_px = view.project(Vec3::new(h, 0.0, 0.0)).x - view.project(Vec3::ZERO).x;
    let rows = (first.y - 0.25 * h_px).ceil() as u32..(first.y + 0.25 * h_px) as u32;
    let columns = first.x.ceil() as u32..last.x as u32;
    let largest_jump = |r: &Render| {
        let mut worst = 0.0f32;
        for y in rows.clone() {
            for x in columns.clone() {
                let i = (y * SIZE + x) as usize;
                if let (Some(a), Some(b)) = (r.normal(i), r.normal(i + 1)) {
                    worst = worst.max(a.dot(b).clamp(-1.0, 1.0).acos().to_degrees());
                }
            }
        }
        worst
    };
    let (nearest, v) = render(0.0);
    // every covered pixel against the nearest of the spheres' own fragments there
    let mut checked = 0;
    for y in 0..SIZE {
        for x in 0..SIZE {
            let i = (y * SIZE + x) as usize;
            let pixel = Vec2::new(x as f32 + 0.5, y as f32 + 0.5);
            let front = spheres
                .iter()
                .filter_map(|s| splat::frame(s, &v))
                .filter_map(|f| splat::fragment(pixel, &f, &v))
                .min_by(|a, b| a.ndc.total_cmp(&b.ndc));
            match (front, nearest.normal(i)) {
                (Some(f), Some(n)) => {
                    let expected = (v.matrices().1 * f.sphere_normal.extend(0.0))
                        .xyz()
                        .normalize();
                    assert!(
                        n.distance(expected) < 1e-4,
                        "pixel ({x}, {y}): normal {n}, the nearest sphere's {expected}"
                    );
                    checked += 1;
                }
                // a nearest fragment of weight 0 (on the projected rim) covers nothing
                (Some(f), None) => assert!(f.r2 >= 0.999, "pixel ({x}, {y}) uncovered"),
                (None, Some(_)) => panic!("pixel ({x}, {y}) covered by no sphere"),
                (None, None) => {}
            }
        }
    }
    assert!(checked > 2000, "only {checked} pixels covered");
    let seams = largest_jump(&nearest);
    let (blended, _) = render(1.5);
    let smooth = largest_jump(&blended);
    println!(
        "row of spheres: largest normal jump between neighbouring pixels {seams:.1} degrees with epsilon 0, {smooth:.1} with epsilon 1.5 h ({checked} pixels checked against the nearest sphere)"
    );
    assert!(seams > 30.0, "epsilon 0 shows no seam: {seams} degrees");
    assert!(
        smooth < 10.0,
        "epsilon 1.5 h leaves a seam: {smooth} degrees"
    );
    let dir = output_dir();
    nearest.image.save(dir.join("row-epsilon-0.png")).unwrap();
    blended.image.save(dir.join("row-epsilon-1.5.png")).unwrap();
}

/// The GPU twin renders the same images as the CPU reference: PSNR >= 40 dB on a particle sphere
/// and on the column scene's splash frame.
#[test]
fn gpu_and_cpu_particle_splats_agree() {
    let Some(ctx) = gpu::context_or_skip("gpu_and_cpu_particle_splats_agree").unwrap() else {
        return;
    };
    let light = Light::default();
    let mut failures = Vec::new();
    for (name, (spheres, camera)) in [
        ("particle-sphere", particle_sphere()),
        ("column-splash", column_splash()),
    ] {
        let params = spheres_params();
        let cpu = splat::render_cpu(&spheres, &camera, &light, &params, SIZE, SIZE).unwrap();
        let gpu =
            gpu_splat::render_gpu(&ctx, &spheres, &camera, &light, &params, SIZE, SIZE).unwrap();
        let psnr = splat::psnr(&cpu.image, &gpu.image);
        println!(
            "{name}: {} spheres, PSNR {psnr:.1} dB, covered pixels CPU {} GPU {}",
            spheres.len(),
            cpu.covered_pixels(),
            gpu.covered_pixels()
        );
        assert!(cpu.covered_pixels() > 1000, "{name}: nearly empty image");
        if psnr < 40.0 {
            let dir = output_dir();
            cpu.image
                .save(dir.join(format!("{name}-expected.png")))
                .unwrap();
            gpu.image
                .save(dir.join(format!("{name}-actual.png")))
                .unwrap();
            splat::difference_image(&cpu.image, &gpu.image, 8)
                .save(dir.join(format!("{name}-difference.png")))
                .unwrap();
            failures.push(format!(
                "{name}: {psnr:.1} dB (images in {})",
                dir.display()
            ));
        }
    }
    assert!(failures.is_empty(), "GPU and CPU differ: {failures:?}");
}
