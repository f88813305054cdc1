//! EWA surfel splatting: the CPU reference against analytic shapes, and the GPU path against the
//! CPU reference (on lavapipe in CI; without an adapter the GPU tests skip with a message unless
//! FLUID_SURFELS_REQUIRE_GPU=1).

use std::path::PathBuf;

use fluid_surfels::density::{self, GridSpec, Kernel, Resolution};
use fluid_surfels::gpu;
use fluid_surfels::scenes;
use fluid_surfels::splat::gpu as gpu_splat;
use fluid_surfels::splat::{
    self, Camera, Light, Render, SplatError, SplatMode, SplatParams, Surfel,
};
use fluid_surfels::surfels::{self, SurfelParams};
use glam::{Vec2, Vec3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

const SIZE: u32 = 128;

/// Surfels of a sphere of particles from the density stage, and the sphere's centre.
fn density_sphere() -> (Vec<Surfel>, Vec3) {
    let scene = scenes::sphere(&scenes::SphereParams {
        radius_in_spacings: 8.0,
        jitter: 0.0,
        ..Default::default()
    })
    .unwrap();
    let p = &scene.particles.positions;
    let h = 3.0 * scene.spacing;
    let spec = GridSpec::around(p, h, Resolution::CellSize(0.5 * scene.spacing)).unwrap();
    let grid = density::density_grid(p, &spec, Kernel::Wyvill, h, 1 << 32).unwrap();
    let s = surfels::extract(&grid, p, Kernel::Wyvill, h, &SurfelParams::default()).unwrap();
    let centre = p.iter().copied().sum::<Vec3>() / p.len() as f32;
    (
        splat::surfels_from(&s.positions, &s.normals, &s.radii, splat::WATER),
        centre,
    )
}

/// A square of surfels in the plane z = `z`, jittered grid positions, normal +z, random colours
/// when `random_colours`.
fn plane(
    half: f32,
    n: usize,
    z: f32,
    colour: [f32; 4],
    random_colours: bool,
    seed: u64,
) -> Vec<Surfel> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let spacing = 2.0 * half / n as f32;
    let mut out = Vec::with_capacity(n * n);
    for j in 0..n {
        for i in 0..n {
            let x = -half + (i as f32 + rng.random_range(0.0..1.0)) * spacing;
            let y = -half + (j as f32 + rng.random_range(0.0..1.0)) * spacing;
            let c = if random_colours {
                let g = rng.random_range(0.0..1.0f32);
                [g, g, g, 1.0]
            } else {
                colour
            };
            out.push(Surfel::disk(Vec3::new(x, y, z), Vec3::Z, 1.5 * spacing, c));
        }
    }
    out
}

/// The world ray through the centre of pixel (x, y).
fn pixel_ray(camera: &Camera, size: u32, x: u32, y: u32) -> Vec3 {
    let forward = (camera.target - camera.eye).normalize();
    let right = forward.cross(camera.up).normalize();
    let up = right.cross(forward);
    let tan = (camera.fov_y_degrees.to_radians() * 0.5).tan();
    let ndc = Vec2::new(
        (x as f32 + 0.5) / size as f32 * 2.0 - 1.0,
        1.0 - (y as f32 + 0.5) / size as f32 * 2.0,
    );
    (forward + right * ndc.x * tan + up * ndc.y * tan).normalize()
}

fn sphere_camera(centre: Vec3, distance: f32) -> Camera {
    Camera {
        eye: centre + Vec3::new(0.3, 0.4, 1.0).normalize() * distance,
        target: centre,
        ..Default::default()
    }
}

/// Weight coverage inside the analytic silhouette and mean normal error of a sphere render.
fn sphere_checks(render: &Render, camera: &Camera, centre: Vec3, radius: f32) -> (f64, f64) {
    let (mut inside, mut covered, mut angle_sum, mut angles) = (0usize, 0usize, 0.0f64, 0usize);
    let distance = (camera.eye - centre).length();
    // one pixel at the sphere's distance, in world units
    let pixel = 2.0 * distance * (camera.fov_y_degrees.to_radians() * 0.5).tan() / SIZE as f32;
    for y in 0..SIZE {
        for x in 0..SIZE {
            let d = pixel_ray(camera, SIZE, x, y);
            let oc = camera.eye - centre;
            let b = oc.dot(d);
            // rays at least two pixels inside the silhouette
            let miss = oc.length_squared() - b * b;
            let inner = radius - 2.0 * pixel;
            if miss > inner * inner {
                continue;
            }
            inside += 1;
            let i = (y * SIZE + x) as usize;
            if render.weight(i) > 0.0 {
                covered += 1;
            }
            let t = -b - (radius * radius - miss).sqrt();
            let analytic = (camera.eye + t * d - centre).normalize();
            if let Some(n) = render.normal(i) {
                angle_sum += f64::from(n.dot(analytic).clamp(-1.0, 1.0).acos().to_degrees());
                angles += 1;
            }
        }
    }
    assert!(inside > 5000, "only {inside} pixels inside the silhouette");
    (
        covered as f64 / inside as f64,
        angle_sum / angles.max(1) as f64,
    )
}

fn check_sphere(render: &Render, camera: &Camera, surfels: &[Surfel], centre: Vec3, what: &str) {
    render.validate().unwrap();
    let radius = surfels
        .iter()
        .map(|s| (Vec3::from(s.position) - centre).length())
        .sum::<f32>()
        / surfels.len() as f32;
    let (coverage, mean_angle) = sphere_checks(render, camera, centre, radius);
    println!(
        "{what}: {} surfels, coverage inside the silhouette {:.4} %, mean normal error {mean_angle:.2} degrees",
        surfels.len(),
        100.0 * coverage
    );
    assert!(coverage >= 0.999, "{what}: holes, coverage {coverage}");
    assert!(
        mean_angle <= 3.0,
        "{what}: mean normal error {mean_angle} degrees"
    );
}

/// A renderer under test at SIZE x SIZE.
type RenderFn = Box<dyn Fn(&[Surfel], &Camera, &Light, &SplatParams) -> Render>;

/// The CPU reference, and the GPU path when an adapter exists (otherwise a skip message, or a
/// failure with FLUID_SURFELS_REQUIRE_GPU=1).
fn renderers(test: &str) -> Vec<(&'static str, RenderFn)> {
    let mut out: Vec<(&'static str, RenderFn)> = vec![(
        "CPU reference",
        Box::new(|s, c, l, p| splat::render_cpu(s, c, l, p, SIZE, SIZE).unwrap()),
    )];
    if let Some(ctx) = gpu::context_or_skip(test).unwrap() {
        out.push((
            "GPU",
            Box::new(move |s, c, l, p| {
                gpu_splat::render_gpu(&ctx, s, c, l, p, SIZE, SIZE).unwrap()
            }),
        ));
    }
    out
}

#[test]
fn sphere_of_density_surfels_has_no_holes_and_analytic_normals() {
    let (surfels, centre) = density_sphere();
    let camera = sphere_camera(centre, 1.6);
    for (what, render) in renderers("sphere_of_density_surfels (GPU part)") {
        let r = render(
            &surfels,
            &camera,
            &Light::default(),
            &SplatParams::default(),
        );
        check_sphere(&r, &camera, &surfels, centre, what);
    }
}

/// Relative spread (max - min) / mean of the red channel over the central pixels.
fn spread(render: &Render, margin: u32) -> f64 {
    let values: Vec<f64> = (margin..SIZE - margin)
        .flat_map(|y| (margin..SIZE - margin).map(move |x| (x, y)))
        .map(|(x, y)| f64::from(render.image.get_pixel(x, y)[0]))
        .collect();
    let mean = values.iter().sum::<f64>() / values.len() as f64;
    let (lo, hi) = values
        .iter()
        .fold((f64::MAX, f64::MIN), |(a, b), &v| (a.min(v), b.max(v)));
    (hi - lo) / mean
}

#[test]
fn flat_plane_of_random_surfels_shades_uniformly() {
    let surfels = plane(1.0, 60, 0.0, [0.8, 0.8, 0.8, 1.0], false, 7);
    let camera = Camera {
        eye: Vec3::new(0.0, -0.6, 1.6),
        target: Vec3::ZERO,
        ..Default::default()
    };
    // no specular: with one normal everywhere the lit colour is then the same at every pixel
    let light = Light {
        specular: 0.0,
        ..Default::default()
    };
    let render = splat::render_cpu(
        &surfels,
        &camera,
        &light,
        &SplatParams::default(),
        SIZE,
        SIZE,
    )
    .unwrap();
    render.validate().unwrap();
    let s = spread(&render, 32);
    // without normalisation the same plane shows the summed Gaussians as blotches
    let weights: Vec<f32> = (0..(SIZE * SIZE) as usize)
        .filter(|&i| {
            let (x, y) = ((i as u32) % SIZE, (i as u32) / SIZE);
            (32..SIZE - 32).contains(&x) && (32..SIZE - 32).contains(&y)
        })
        .map(|i| render.weight(i))
        .collect();
    let (wlo, whi) = weights
        .iter()
        .fold((f32::MAX, f32::MIN), |(a, b), &v| (a.min(v), b.max(v)));
    println!(
        "flat plane: shading spread {:.3} % over the centre; accumulated weight from {wlo:.2} to {whi:.2} (what unnormalised splatting would show)",
        100.0 * s
    );
    assert!(wlo > 0.0, "a hole in the plane");
    assert!(s <= 0.02, "shading varies by {s}");
    assert!(
        whi / wlo > 1.5,
        "the test needs uneven raw weights to mean anything"
    );
}

/// Mean squared difference of horizontally and vertically adjacent pixels (red channel).
fn pixel_variance(render: &Render) -> f64 {
    let img = &render.image;
    let (mut sum, mut n) = (0.0f64, 0usize);
    for y in 0..SIZE - 1 {
        for x in 0..SIZE - 1 {
            let v = f64::from(img.get_pixel(x, y)[0]);
            for (dx, dy) in [(1, 0), (0, 1)] {
                let d = v - f64::from(img.get_pixel(x + dx, y + dy)[0]);
                sum += d * d;
                n += 1;
            }
        }
    }
    sum / n as f64
}

fn grazing_camera() -> Camera {
    Camera {
        eye: Vec3::new(0.0, -12.0, 0.6),
        target: Vec3::new(0.0, 0.0, 0.0),
        up: Vec3::Z,
        fov_y_degrees: 8.0,
        near: 1.0,
        far: 40.0,
    }
}

#[test]
fn grazing_distant_plane_is_smoother_with_the_low_pass_filter() {
    let surfels = plane(3.0, 240, 0.0, [0.0; 4], true, 11);
    let camera = grazing_camera();
    let light = Light {
        specular: 0.0,
        ..Default::default()
    };
    let with = SplatParams::default();
    let without = SplatParams {
        low_pass_px: 0.0,
        ..with
    };
    let a = splat::render_cpu(&surfels, &camera, &light, &with, SIZE, SIZE).unwrap();
    let b = splat::render_cpu(&surfels, &camera, &light, &without, SIZE, SIZE).unwrap();
    let (va, vb) = (pixel_variance(&a), pixel_variance(&b));
    println!(
        "grazing plane: pixel-to-pixel variance {va:.1} with the low-pass filter, {vb:.1} without"
    );
    assert!(
        va < vb,
        "the low-pass filter does not reduce aliasing: {va} vs {vb}"
    );
}

fn output_dir() -> PathBuf {
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("splat");
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// A height field z = 0.15 sin(3x) cos(2y) of elliptical surfels stretched along x, random colours.
fn wavy_ellipses() -> Vec<Surfel> {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let n = 70;
    let spacing = 2.0 / n as f32;
    let mut out = Vec::new();
    for j in 0..n {
        for i in 0..n {
            let x = -1.0 + (i as f32 + rng.random_range(0.0..1.0)) * spacing;
            let y = -1.0 + (j as f32 + rng.random_range(0.0..1.0)) * spacing;
            let z = 0.15 * (3.0 * x).sin() * (2.0 * y).cos();
            let dzdx = 0.45 * (3.0 * x).cos() * (2.0 * y).cos();
            let dzdy = -0.3 * (3.0 * x).sin() * (2.0 * y).sin();
            let normal = Vec3::new(-dzdx, -dzdy, 1.0).normalize();
            let tangent = Vec3::new(1.0, 0.0, dzdx);
            let c = [
                rng.random_range(0.2..1.0),
                rng.random_range(0.2..1.0),
                0.6,
                1.0,
            ];
            out.push(Surfel::ellipse(
                Vec3::new(x, y, z),
                normal,
                tangent,
                2.2 * spacing,
                1.3 * spacing,
                c,
            ));
        }
    }
    out
}

#[test]
fn gpu_and_cpu_reference_images_agree() {
    let Some(ctx) = gpu::context_or_skip("gpu_and_cpu_reference_images_agree").unwrap() else {
        return;
    };
    let (sphere, centre) = density_sphere();
    let scenes: Vec<(&str, Vec<Surfel>, Camera, SplatParams)> = vec![
        (
            "density-sphere",
            sphere,
            sphere_camera(centre, 1.6),
            SplatParams::default(),
        ),
        (
            "grazing-plane",
            plane(3.0, 160, 0.0, [0.0; 4], true, 3),
            grazing_camera(),
            SplatParams::default(),
        ),
        (
            "wavy-ellipses",
            wavy_ellipses(),
            Camera {
                eye: Vec3::new(0.4, -2.0, 1.8),
                target: Vec3::ZERO,
                up: Vec3::Z,
                ..Default::default()
            },
            SplatParams::default(),
        ),
    ];
    let mut failures = Vec::new();
    for (name, surfels, camera, params) in &scenes {
        for mode in [SplatMode::Ewa, SplatMode::Sprites] {
            let params = SplatParams { mode, ..*params };
            let light = Light::default();
            let cpu = splat::render_cpu(surfels, camera, &light, &params, SIZE, SIZE).unwrap();
            let gpu =
                gpu_splat::render_gpu(&ctx, surfels, camera, &light, &params, SIZE, SIZE).unwrap();
            let psnr = splat::psnr(&cpu.image, &gpu.image);
            println!(
                "{name} ({mode:?}): PSNR {psnr:.1} dB, covered pixels CPU {} GPU {}",
                cpu.covered_pixels(),
                gpu.covered_pixels()
            );
            if psnr < 40.0 {
                let dir = output_dir();
                let stem = format!("{name}-{mode:?}");
                cpu.image
                    .save(dir.join(format!("{stem}-expected.png")))
                    .unwrap();
                gpu.image
                    .save(dir.join(format!("{stem}-actual.png")))
                    .unwrap();
                splat::difference_image(&cpu.image, &gpu.image, 8)
                    .save(dir.join(format!("{stem}-difference.png")))
                    .unwrap();
                failures.push(format!(
                    "{stem}: {psnr:.1} dB (images in {})",
                    dir.display()
                ));
            }
        }
    }
    assert!(failures.is_empty(), "GPU and CPU differ: {failures:?}");
}

/// Two parallel planes `gap` apart facing the camera: front red, back green; the green share of
/// the centre pixel.
fn green_share(gap_in_epsilons: f32, render: &RenderFn) -> f32 {
    let params = SplatParams::default();
    let n = 40;
    let radius = 1.5 * 2.0 / n as f32;
    let epsilon = params.depth_offset * radius;
    let mut surfels = plane(1.0, n, 0.0, [1.0, 0.0, 0.0, 1.0], false, 1);
    surfels.extend(plane(
        1.0,
        n,
        -gap_in_epsilons * epsilon,
        [0.0, 1.0, 0.0, 1.0],
        false,
        2,
    ));
    let camera = Camera {
        eye: Vec3::new(0.0, 0.0, 2.5),
        target: Vec3::ZERO,
        ..Default::default()
    };
    let r = render(&surfels, &camera, &Light::default(), &params);
    r.validate().unwrap();
    let i = (SIZE / 2 * SIZE + SIZE / 2) as usize;
    let c = r.colour[i];
    c[1] / (c[0] + c[1])
}

#[test]
fn surfaces_closer_than_epsilon_blend_and_farther_ones_hide() {
    for (what, render) in renderers("surfaces_closer_than_epsilon_blend (GPU part)") {
        let near = green_share(0.3, &render);
        let far = green_share(3.0, &render);
        println!(
            "{what}: green share of the centre pixel {near:.3} with planes 0.3 epsilon apart, {far:.3} at 3 epsilon"
        );
        assert!(
            near > 0.2 && near < 0.8,
            "{what}: close surfaces do not blend: {near}"
        );
        assert_eq!(far, 0.0, "{what}: the hidden surface shows through");
    }
}

fn degenerate_cases() -> Vec<(&'static str, Vec<Surfel>, Camera)> {
    let camera = Camera::default();
    let good = Surfel::disk(Vec3::ZERO, Vec3::Z, 0.3, splat::WATER);
    let (sphere, centre) = density_sphere();
    vec![
        ("no surfels", vec![], camera),
        (
            "zero normals, zero and negative radii, NaN and infinite values",
            vec![
                Surfel::disk(Vec3::ZERO, Vec3::ZERO, 0.3, splat::WATER),
                Surfel::disk(Vec3::ZERO, Vec3::Z, 0.0, splat::WATER),
                Surfel::disk(Vec3::ZERO, Vec3::Z, -1.0, splat::WATER),
                Surfel::disk(Vec3::NAN, Vec3::Z, 0.3, splat::WATER),
                Surfel::disk(Vec3::ZERO, Vec3::new(f32::NAN, 0.0, 1.0), 0.3, splat::WATER),
                Surfel::disk(Vec3::ZERO, Vec3::Z, f32::INFINITY, splat::WATER),
                Surfel::disk(Vec3::ZERO, Vec3::Z, 0.3, [f32::NAN, 0.0, 0.0, 1.0]),
                Surfel::ellipse(Vec3::ZERO, Vec3::Z, Vec3::Z, 0.3, 0.0, splat::WATER),
                good,
            ],
            camera,
        ),
        (
            "a surfel through the camera's eye",
            vec![Surfel::disk(
                Vec3::new(0.0, 0.0, 3.0),
                Vec3::new(0.0, 0.3, 1.0),
                2.0,
                splat::WATER,
            )],
            camera,
        ),
        (
            "camera inside the sphere",
            sphere,
            Camera {
                eye: centre,
                target: centre + Vec3::X,
                ..Default::default()
            },
        ),
    ]
}

#[test]
fn degenerate_surfels_and_cameras_give_finite_images() {
    let gpu = gpu::context_or_skip("degenerate_surfels_and_cameras (GPU part)").unwrap();
    for (what, surfels, camera) in degenerate_cases() {
        let params = SplatParams::default();
        let light = Light::default();
        let cpu = splat::render_cpu(&surfels, &camera, &light, &params, 64, 48).unwrap();
        cpu.validate().unwrap_or_else(|e| panic!("{what}: {e}"));
        println!("{what}: {} pixels covered", cpu.covered_pixels());
        if let Some(ctx) = &gpu {
            let g = gpu_splat::render_gpu(ctx, &surfels, &camera, &light, &params, 64, 48).unwrap();
            g.validate().unwrap_or_else(|e| panic!("{what} (GPU): {e}"));
            let psnr = splat::psnr(&cpu.image, &g.image);
            assert!(psnr >= 40.0, "{what}: GPU and CPU differ, {psnr} dB");
        }
    }
    // the one drawable surfel among the broken ones is drawn
    let (kept, skipped) = splat::drawable(&degenerate_cases()[1].1);
    assert_eq!((kept.len(), skipped), (1, 8));
}

#[test]
fn invalid_views_are_refused() {
    let s = [Surfel::disk(Vec3::ZERO, Vec3::Z, 0.3, splat::WATER)];
    let light = Light::default();
    let p = SplatParams::default();
    let c = Camera::default();
    let cases: Vec<(&str, Result<Render, SplatError>)> = vec![
        ("zero width", splat::render_cpu(&s, &c, &light, &p, 0, 10)),
        ("huge", splat::render_cpu(&s, &c, &light, &p, 100_000, 10)),
        (
            "eye on target",
            splat::render_cpu(&s, &Camera { target: c.eye, ..c }, &light, &p, 8, 8),
        ),
        (
            "NaN eye",
            splat::render_cpu(
                &s,
                &Camera {
                    eye: Vec3::NAN,
                    ..c
                },
                &light,
                &p,
                8,
                8,
            ),
        ),
        (
            "near beyond far",
            splat::render_cpu(
                &s,
                &Camera {
                    near: 5.0,
                    far: 1.0,
                    ..c
                },
                &light,
                &p,
                8,
                8,
            ),
        ),
        (
            "zero light direction",
            splat::render_cpu(
                &s,
                &c,
                &Light {
                    direction: Vec3::ZERO,
                    ..light
                },
                &p,
                8,
                8,
            ),
        ),
        (
            "negative low-pass",
            splat::render_cpu(
                &s,
                &c,
                &light,
                &SplatParams {
                    low_pass_px: -1.0,
                    ..p
                },
                8,
                8,
            ),
        ),
    ];
    for (what, r) in cases {
        let e = r.expect_err(what);
        println!("{what}: {e}");
    }
}

/// The GPU twin refuses the same inputs with the same stage error (issue 38: `GpuError` no
/// longer wraps it, so a caller matching `Error::Splat` catches the GPU path's refusal too).
#[test]
fn the_gpu_twin_refuses_bad_views_with_the_splat_error() {
    let Some(ctx) =
        gpu::context_or_skip("the_gpu_twin_refuses_bad_views_with_the_splat_error").unwrap()
    else {
        return;
    };
    let s = [Surfel::disk(Vec3::ZERO, Vec3::Z, 0.3, splat::WATER)];
    let (light, p, c) = (Light::default(), SplatParams::default(), Camera::default());
    let eye_on_target = Camera { target: c.eye, ..c };
    let cases = [
        ("zero width", c, 0, 10),
        ("huge", c, 100_000, 10),
        ("eye on target", eye_on_target, 8, 8),
    ];
    for (what, camera, w, h) in cases {
        let cpu = splat::render_cpu(&s, &camera, &light, &p, w, h).expect_err(what);
        match gpu_splat::render_gpu(&ctx, &s, &camera, &light, &p, w, h) {
            Err(fluid_surfels::Error::Splat(e)) => {
                assert_eq!(
                    std::mem::discriminant(&e),
                    std::mem::discriminant(&cpu),
                    "{what}: GPU {e} against CPU {cpu}"
                );
            }
            other => panic!("{what}: expected Error::Splat, got {other:?}"),
        }
    }
}

/// Every pixel whose centre a splat's weight covers (`splat::fragment` keeps it) lies in the
/// splat's screen rectangle (`splat::frame`), which both renderers draw (the GPU's quad, the
/// CPU's loops): the rectangle is only the projected disk's box joined with the low-pass circle,
/// plus `RECT_MARGIN_PX`. Random disks and ellipses from sub-pixel to wide, every orientation
/// (edge-on included), near and far, three low-pass radii, the three modes; pixels scanned over
/// the whole screen.
#[test]
fn splat_rectangles_hold_every_pixel_the_weight_covers() {
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let (w, h) = (48u32, 32u32);
    let camera = Camera {
        eye: Vec3::new(0.2, 0.5, 3.0),
        target: Vec3::ZERO,
        ..Default::default()
    };
    let mut covered = 0usize;
    let mut in_rects = 0usize;
    for mode in [SplatMode::Ewa, SplatMode::Spheres, SplatMode::Sprites] {
        for low_pass_px in [0.0, 1.0, 2.5] {
            let params = SplatParams {
                mode,
                low_pass_px,
                ..Default::default()
            };
            let v = splat::View::new(&camera, &Light::default(), &params, w, h).unwrap();
            for _ in 0..400 {
                let normal = random_direction(&mut rng);
                let position = Vec3::new(
                    rng.random_range(-1.2..1.2),
                    rng.random_range(-0.8..0.8),
                    rng.random_range(-2.0..2.5),
                );
                let radius = 10f32.powf(rng.random_range(-3.0..-0.5));
                let s = if rng.random_bool(0.5) {
                    Surfel::disk(position, normal, radius, splat::WATER)
                } else {
                    let tangent = random_direction(&mut rng);
                    let stretch = rng.random_range(0.2..3.0);
                    Surfel::ellipse(
                        position,
                        normal,
                        tangent,
                        radius,
                        radius * stretch,
                        splat::WATER,
                    )
                };
                let Some(f) = splat::frame(&s, &v) else {
                    continue;
                };
                in_rects +=
                    ((f.rect.z - f.rect.x).max(0.0) * (f.rect.w - f.rect.y).max(0.0)) as usize;
                for y in 0..h {
                    for x in 0..w {
                        let pixel = Vec2::new(x as f32 + 0.5, y as f32 + 0.5);
                        if splat::fragment(pixel, &f, &v).is_some() {
                            covered += 1;
                            assert!(
                                pixel.x >= f.rect.x
                                    && pixel.x < f.rect.z
                                    && pixel.y >= f.rect.y
                                    && pixel.y < f.rect.w,
                                "{mode:?}, low-pass {low_pass_px}: pixel {pixel} is covered by \
                                 {s:?} but lies outside its rectangle {:?}",
                                f.rect
                            );
                        }
                    }
                }
            }
        }
    }
    println!("{covered} covered pixels in rectangles of {in_rects} pixels in all");
    assert!(
        covered > 10_000,
        "too few covered pixels to test: {covered}"
    );
}

/// A direction uniform enough for the tests: a normalised point of the cube `[-1, 1]^3`.
fn random_direction(rng: &mut ChaCha8Rng) -> Vec3 {
    Vec3::new(
        rng.random_range(-1.0..1.0f32),
        rng.random_range(-1.0..1.0f32),
        rng.random_range(-1.0..1.0f32),
    )
    .normalize_or(Vec3::Z)
}
