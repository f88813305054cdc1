//! The optics stage (Iwasaki et al. §5): caustics and the final image, CPU reference and GPU.

use fluid_surfels::optics::{
    Caustics, LightKind, OpticsScene, ReceiverKind, Stage, caustics_cpu, frame_cpu,
    fresnel_reflectance, refract,
};
use fluid_surfels::scenes::{height_field, water_lens};
use fluid_surfels::splat::Surfel;
use glam::Vec3;

/// Flat water at `depth` over a floor at y = 0, light from straight above; the screen covers
/// `|x|, |z| <= window` inside the water.
fn flat_scene(depth: f32, window: f32, screen: u32, map: u32) -> (OpticsScene, Vec<Surfel>) {
    let surfels = height_field(1.0, 0.02, |_, _| depth);
    let mut scene = OpticsScene::default();
    scene.light.direction = Vec3::Y;
    scene.light.colour = Vec3::new(1.0, 0.8, 0.6);
    scene.water.extinction = Vec3::new(0.4, 0.2, 0.1);
    scene.receiver.kind = ReceiverKind::Plane;
    scene.receiver.min = Vec3::new(-1.2, 0.0, -1.2);
    scene.receiver.max = Vec3::new(1.2, 1.0, 1.2);
    scene.optics.screen_bounds = Some([
        Vec3::new(-window, 0.0, -window),
        Vec3::new(window, 1.0, window),
    ]);
    scene.optics.caustics_resolution = Some([screen, screen]);
    scene.optics.map_resolution = Some([map, map]);
    (scene, surfels)
}

fn normal_transmittance(ior: f32) -> f32 {
    1.0 - ((ior - 1.0) / (ior + 1.0)).powi(2)
}

/// Side of the square the water triangles cover: they join pixel centres, so the window's outer
/// half-pixel ring is not sampled.
fn sampled_side(window: f32, pixels: u32) -> f32 {
    2.0 * window * (pixels - 1) as f32 / pixels as f32
}

#[test]
fn flat_water_gives_a_uniform_map_carrying_the_transmitted_flux() {
    let depth = 0.5;
    let (scene, surfels) = flat_scene(depth, 0.8, 128, 256);
    let stage = Stage::new(&scene, &surfels).unwrap();
    let c = caustics_cpu(&stage, &surfels).unwrap();
    let t0 = normal_transmittance(1.33);
    let expected_e = scene.light.colour * t0 * (-scene.water.extinction * depth).exp();
    // away from the edges: texels whose centre lies 3 texels inside the sampled square
    let side = sampled_side(0.8, 128);
    let texel = 2.0 * c.map.half_extent().x / c.map.width as f32;
    let mut worst = 0f32;
    let mut inner = 0;
    for (i, e) in c.irradiance.iter().enumerate() {
        let g = c.geometry[i];
        if g[3] > 0.0
            && g[0].abs() < side / 2.0 - 3.0 * texel
            && g[2].abs() < side / 2.0 - 3.0 * texel
        {
            inner += 1;
            let rel = (Vec3::new(e[0], e[1], e[2]) / expected_e - 1.0)
                .abs()
                .max_element();
            if rel > worst {
                println!("texel {i} at {g:?}: {e:?}");
            }
            worst = worst.max(rel);
        }
    }
    println!(
        "flat water: {inner} inner texels, largest deviation from the analytic irradiance {:.4} %",
        worst * 100.0
    );
    assert!(inner > 10_000, "{inner}");
    assert!(worst < 0.005, "{worst}");
    let incident = scene.light.colour * side * side;
    let expected = incident * t0 * (-scene.water.extinction * depth).exp();
    let total = c.total_flux();
    let rel = (total / expected - 1.0).abs().max_element();
    println!(
        "flat water: total {total:?}, expected {expected:?}, relative {:.5} %",
        rel * 100.0
    );
    assert!(rel < 0.02, "{rel}");
    assert!((c.incident / incident - 1.0).abs().max_element() < 1e-3);
    assert!(total.cmple(incident).all());
}

/// Peak irradiance of the map.
fn peak(c: &Caustics) -> f32 {
    c.irradiance.iter().map(|e| e[0]).fold(0.0, f32::max)
}

fn lens_scene(floor_depth: f32) -> (OpticsScene, Vec<Surfel>) {
    // curvature radius 1, vertex at y = 0, floor `floor_depth` below it
    let surfels = water_lens(1.0, 0.2, 0.0, 0.004);
    let mut scene = OpticsScene::default();
    scene.light.direction = Vec3::Y;
    scene.water.extinction = Vec3::ZERO;
    scene.receiver.kind = ReceiverKind::Plane;
    scene.receiver.min = Vec3::new(-0.2, -floor_depth, -0.2);
    scene.receiver.max = Vec3::new(0.2, 0.0, 0.2);
    scene.optics.screen_bounds = Some([Vec3::new(-0.15, -1.0, -0.15), Vec3::new(0.15, 0.0, 0.15)]);
    scene.optics.caustics_resolution = Some([128, 128]);
    scene.optics.map_resolution = Some([512, 512]);
    (scene, surfels)
}

#[test]
fn a_lens_focuses_at_the_paraxial_focal_distance_and_conserves_flux() {
    let ior = 1.33f32;
    let focal = ior / (ior - 1.0);
    let mut best = (0.0f32, 0.0f32);
    let mut curve = Vec::new();
    for k in -10..=10 {
        let d = focal * (1.0 + 0.01 * k as f32);
        let (scene, surfels) = lens_scene(d);
        let stage = Stage::new(&scene, &surfels).unwrap();
        let c = caustics_cpu(&stage, &surfels).unwrap();
        let p = peak(&c);
        curve.push((d, p));
        if p > best.1 {
            best = (d, p);
        }
        if k == 0 {
            // flux: the sampled square's light times the Fresnel transmittance of the sphere's
            // normal there, integrated numerically (no extinction)
            let side = sampled_side(0.15, 128);
            let n = 400;
            let mut expected = 0.0f64;
            for j in 0..n {
                for i in 0..n {
                    let x = -side / 2.0 + side * (i as f32 + 0.5) / n as f32;
                    let z = -side / 2.0 + side * (j as f32 + 0.5) / n as f32;
                    let cos_i = (1.0 - x * x - z * z).sqrt();
                    expected += f64::from(1.0 - fresnel_reflectance(cos_i, 1.0, ior));
                }
            }
            let expected = expected as f32 * side * side / (n * n) as f32;
            let total = c.total_flux().x;
            println!(
                "lens at the paraxial focus: map total {total}, expected {expected}, peak {p}"
            );
            assert!(
                (total / expected - 1.0).abs() < 0.02,
                "{total} vs {expected}"
            );
            assert!(total <= c.incident.x);
        }
    }
    println!("peak irradiance by floor depth: {curve:?}");
    let err = (best.0 - focal).abs() / focal;
    println!(
        "brightest caustic at depth {:.4}, paraxial focus {focal:.4}: {:.2} % off",
        best.0,
        err * 100.0
    );
    assert!(err <= 0.02, "{err}");
    // and it is a real focus: far brighter than the light itself
    assert!(best.1 > 50.0, "{}", best.1);
}

#[test]
fn the_map_never_holds_more_flux_than_fell_on_the_water() {
    let wavy = height_field(1.0, 0.02, |x, z| {
        0.5 + 0.04 * (7.0 * x).sin() * (5.0 * z + 1.0).cos()
    });
    for (name, surfels, ior) in [
        ("wavy", wavy.clone(), 1.33f32),
        ("lens", water_lens(1.0, 0.2, 0.0, 0.004), 1.33),
        ("dense", wavy, 2.4),
    ] {
        let mut scene = OpticsScene::default();
        scene.light.direction = Vec3::new(0.2, 1.0, 0.1);
        scene.water.ior = ior;
        scene.water.extinction = Vec3::ZERO;
        scene.optics.caustics_resolution = Some([96, 96]);
        scene.optics.map_resolution = Some([192, 192]);
        let stage = Stage::new(&scene, &surfels).unwrap();
        let c = caustics_cpu(&stage, &surfels).unwrap();
        let total = c.total_flux();
        // everything the screen can see: the light across its whole window
        let half = c.screen.half_extent();
        let window = scene.light.colour * 4.0 * half.x * half.y;
        println!(
            "{name}: map {total:?}, through the water {:?}, window {window:?}",
            c.incident
        );
        assert!(total.x > 0.0);
        assert!(total.cmple(c.incident * 1.000_01).all(), "{name}");
        assert!(c.incident.cmple(window * 1.000_01).all(), "{name}");
    }
}

#[test]
fn refraction_and_fresnel_follow_snell_and_total_internal_reflection() {
    let n = Vec3::Y;
    let i = Vec3::new(0.6, -0.8, 0.0);
    let t = refract(i, n, 1.0, 1.33).unwrap();
    let sin_t = t.x;
    assert!((sin_t * 1.33 - 0.6).abs() < 1e-5);
    // from water into air beyond the critical angle (sin > 1 / 1.33): none, reflectance 1
    let steep = Vec3::new(0.8, -0.6, 0.0);
    assert!(refract(steep, n, 1.33, 1.0).is_none());
    assert_eq!(fresnel_reflectance(0.6, 1.33, 1.0), 1.0);
    // normal incidence: ((n - 1) / (n + 1))^2
    assert!((fresnel_reflectance(1.0, 1.0, 1.33) - 0.02006).abs() < 1e-4);
    // grazing: everything reflected
    assert!(fresnel_reflectance(0.0, 1.0, 1.33) > 0.999);
}

fn assert_finite(name: &str, stage: &Stage, c: &Caustics, surfels: &[Surfel]) {
    for e in &c.irradiance {
        assert!(
            e.iter().all(|v| v.is_finite() && *v >= 0.0),
            "{name}: irradiance {e:?}"
        );
    }
    let f = frame_cpu(stage, surfels, c, (48, 48)).unwrap();
    for p in &f.linear {
        assert!(p.iter().all(|v| v.is_finite()), "{name}: pixel {p:?}");
    }
}

#[test]
fn degenerate_scenes_give_finite_images() {
    let flat = height_field(1.0, 0.05, |_, _| 0.5);
    let mut cases: Vec<(&str, OpticsScene, Vec<Surfel>)> = Vec::new();
    let mut base = OpticsScene::default();
    base.optics.caustics_resolution = Some([32, 32]);
    base.optics.map_resolution = Some([48, 48]);
    cases.push(("empty", base.clone(), Vec::new()));
    let mut tir = base.clone();
    tir.water.ior = 0.7;
    tir.light.direction = Vec3::new(1.0, 0.5, 0.0);
    cases.push(("total internal reflection", tir, flat.clone()));
    let mut parallel = base.clone();
    parallel.light.direction = Vec3::X;
    cases.push(("light parallel to the water", parallel, flat.clone()));
    let mut miss = base.clone();
    miss.receiver.kind = ReceiverKind::Plane;
    miss.receiver.min = Vec3::new(5.0, 0.0, 5.0);
    miss.receiver.max = Vec3::new(6.0, 1.0, 6.0);
    cases.push(("rays that miss the receiver", miss, flat.clone()));
    let mut point = base.clone();
    point.light.kind = LightKind::Point;
    point.light.position = Vec3::new(0.0, 0.6, 0.0);
    cases.push(("point light just above the water", point, flat.clone()));
    let mut nan = flat.clone();
    nan[3].position[0] = f32::NAN;
    nan[5].normal = [0.0; 3];
    nan[7].radius = 0.0;
    cases.push(("NaN and degenerate surfels", base.clone(), nan));
    for (name, scene, surfels) in cases {
        let stage = Stage::new(&scene, &surfels).unwrap_or_else(|e| panic!("{name}: {e}"));
        let c = caustics_cpu(&stage, &surfels).unwrap();
        assert_finite(name, &stage, &c, &surfels);
        if name == "total internal reflection" || name == "light parallel to the water" {
            // the case really happened: no light crosses the water
            assert_eq!(c.total_flux(), Vec3::ZERO, "{name}");
        }
        if name == "total internal reflection" {
            // ... though the light does fall on it
            assert!(c.incident.x > 0.0);
        }
        if name == "rays that miss the receiver" {
            assert_eq!(c.triangles, 0);
            assert!(c.missed > 0);
        }
    }
}

#[test]
fn bad_scenes_are_refused_with_typed_errors() {
    let surfels = height_field(1.0, 0.1, |_, _| 0.5);
    let mut bad = Vec::new();
    let mut s = OpticsScene::default();
    s.water.ior = f32::NAN;
    bad.push(s);
    let mut s = OpticsScene::default();
    s.light.direction = Vec3::ZERO;
    bad.push(s);
    let mut s = OpticsScene::default();
    s.optics.caustics_resolution = Some([1, 100_000]);
    bad.push(s);
    let mut s = OpticsScene::default();
    s.receiver.kind = ReceiverKind::OpenBox;
    s.receiver.max = Vec3::new(1.0, f32::INFINITY, 1.0);
    bad.push(s);
    let mut s = OpticsScene::default();
    s.receiver.kind = ReceiverKind::Mesh;
    s.receiver.path = Some("/nonexistent/pool.obj".into());
    bad.push(s);
    let mut s = OpticsScene::default();
    s.water.extinction = Vec3::new(-1.0, 0.0, 0.0);
    bad.push(s);
    for s in bad {
        let e = Stage::new(&s, &surfels).unwrap_err();
        assert!(!e.to_string().is_empty());
    }
}

#[test]
fn obj_meshes_and_toml_scenes_load() {
    let dir = tempfile::tempdir().unwrap();
    let obj = dir.path().join("pool.obj");
    std::fs::write(
        &obj,
        "# a floor\nv -1 0 -1\nv 1 0 -1\nv 1 0 1\nv -1 0 1\nf 1 2 3 4\n",
    )
    .unwrap();
    let toml_path = dir.path().join("scene.toml");
    std::fs::write(
        &toml_path,
        "[light]\nkind = \"directional\"\ndirection = [0.0, 1.0, 0.0]\n\n[receiver]\nkind = \"mesh\"\npath = \"pool.obj\"\nchecker = 0.25\n\n[water]\nior = 1.5\n\n[optics]\ncaustics_resolution = [64, 32]\n",
    )
    .unwrap();
    let scene = OpticsScene::from_toml_file(&toml_path).unwrap();
    assert_eq!(scene.water.ior, 1.5);
    assert_eq!(scene.optics.caustics_resolution, Some([64, 32]));
    let surfels = height_field(0.5, 0.05, |_, _| 0.3);
    let stage = Stage::new(&scene, &surfels).unwrap();
    assert_eq!(stage.receiver.triangles.len(), 2);
    assert_eq!(
        (stage.views.screen.width, stage.views.screen.height),
        (64, 32)
    );
    // malformed files: typed errors naming the line
    for (text, what) in [
        ("v 0 0\nf 1 2 3\n", "line 1"),
        ("v 0 0 0\nf 1 2 9\n", "line 2"),
        ("v 0 0 0\n", "no faces"),
    ] {
        std::fs::write(&obj, text).unwrap();
        let e = Stage::new(&scene, &surfels).unwrap_err().to_string();
        assert!(e.contains(what), "{e}");
    }
    std::fs::write(&toml_path, "[water]\nior = \"wet\"\n").unwrap();
    assert!(OpticsScene::from_toml_file(&toml_path).is_err());
    std::fs::write(&toml_path, "[watre]\nior = 1.2\n").unwrap();
    assert!(
        OpticsScene::from_toml_file(&toml_path)
            .unwrap_err()
            .to_string()
            .contains("watre")
    );
}

// ---- GPU path (lavapipe in CI) ----

use fluid_surfels::gpu::context_or_skip;
use fluid_surfels::optics::gpu::render_gpu;

fn relative_l1(a: &[[f32; 4]], b: &[[f32; 4]]) -> f64 {
    let mut num = 0.0f64;
    let mut den = 0.0f64;
    for (x, y) in a.iter().zip(b) {
        for k in 0..3 {
            num += f64::from((x[k] - y[k]).abs());
            den += f64::from(x[k].abs());
        }
    }
    num / den.max(1e-30)
}

fn wavy_scene() -> (OpticsScene, Vec<Surfel>) {
    let surfels = height_field(1.0, 0.02, |x, z| {
        0.5 + 0.03 * (6.0 * x).sin() * (4.0 * z + 1.0).cos()
    });
    let mut scene = OpticsScene::default();
    scene.light.direction = Vec3::new(0.25, 1.0, 0.15);
    scene.water.extinction = Vec3::new(0.6, 0.2, 0.1);
    scene.receiver.kind = ReceiverKind::OpenBox;
    scene.receiver.min = Vec3::new(-1.1, 0.0, -1.1);
    scene.receiver.max = Vec3::new(1.1, 0.8, 1.1);
    scene.receiver.checker = 0.25;
    scene.optics.caustics_resolution = Some([128, 128]);
    scene.optics.map_resolution = Some([256, 256]);
    (scene, surfels)
}

#[test]
fn gpu_caustics_agree_with_the_cpu_reference() {
    let Some(ctx) = context_or_skip("gpu_caustics_agree_with_the_cpu_reference").unwrap() else {
        return;
    };
    let (flat, flat_surfels) = flat_scene(0.5, 0.8, 128, 256);
    let (lens, lens_surfels) = lens_scene(1.33 / 0.33);
    let (wavy, wavy_surfels) = wavy_scene();
    for (name, scene, surfels) in [
        ("flat", flat, flat_surfels),
        ("lens", lens, lens_surfels),
        ("wavy", wavy, wavy_surfels),
    ] {
        let stage = Stage::new(&scene, &surfels).unwrap();
        let cpu = caustics_cpu(&stage, &surfels).unwrap();
        let (gpu, times) = render_gpu(&ctx, &stage, &surfels, None).unwrap();
        let l1 = relative_l1(&cpu.irradiance, &gpu.irradiance);
        let flux_l1 = relative_l1(&cpu.flux, &gpu.flux);
        let gpu_total: f32 = gpu.flux.iter().map(|f| f[0]).sum();
        println!(
            "{name}: relative L1 of the irradiance maps {:.4} %, of the flux maps {:.4} %; totals CPU {} GPU {gpu_total}; GPU {:.1} ms",
            l1 * 100.0,
            flux_l1 * 100.0,
            cpu.total_flux().x,
            times.caustics_ms
        );
        assert!(l1 < 0.03, "{name}: {l1}");
        assert!(gpu_total <= cpu.incident.x * 1.0001, "{name}");
        assert!(gpu.irradiance.iter().flatten().all(|v| v.is_finite()));
    }
}

fn golden_scene() -> (OpticsScene, Vec<Surfel>) {
    let (mut scene, surfels) = wavy_scene();
    // the GPU path finds refracted hits in the camera's geometry map (§5.2, then the light's),
    // which hold only what they see, where the CPU reference traces the BVH (see
    // `search_receiver` in optics.wgsl). Measured: this view 41.6 dB; a more grazing one,
    // eye (0.7, 3.2, 2.0), 32.4 dB, its differences all in one row of pixels along the far edge
    // of the water and a dozen isolated pixels
    scene.camera = Some(fluid_surfels::splat::Camera {
        eye: Vec3::new(0.5, 3.6, 1.4),
        target: Vec3::new(0.0, 0.2, 0.0),
        fov_y_degrees: 40.0,
        near: 0.5,
        far: 8.0,
        ..Default::default()
    });
    scene.water.extinction = Vec3::new(1.2, 0.35, 0.2);
    // a floor without walls: refracted rays that end behind a wall, hidden from both the camera
    // and the light, are where the GPU's geometry-map search (the paper's method) and the CPU's
    // BVH must differ (28.8 dB with the open box, all of it in one row of pixels along the front)
    scene.receiver.kind = ReceiverKind::Plane;
    scene.receiver.min = Vec3::new(-1.3, 0.0, -1.3);
    scene.receiver.max = Vec3::new(1.3, 0.8, 1.3);
    (scene, surfels)
}

#[test]
fn golden_frame_cpu_and_gpu_agree() {
    let (scene, surfels) = golden_scene();
    let stage = Stage::new(&scene, &surfels).unwrap();
    let c = caustics_cpu(&stage, &surfels).unwrap();
    let cpu = frame_cpu(&stage, &surfels, &c, (128, 128)).unwrap();
    let golden_path =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/golden/optics_frame.png");
    if std::env::var("FLUID_SURFELS_BLESS").is_ok_and(|v| v == "1") {
        std::fs::create_dir_all(golden_path.parent().unwrap()).unwrap();
        cpu.image.save(&golden_path).unwrap();
    }
    let golden = image::open(&golden_path)
        .unwrap_or_else(|e| {
            panic!(
                "{}: {e} (FLUID_SURFELS_BLESS=1 writes it)",
                golden_path.display()
            )
        })
        .to_rgba8();
    let out = std::path::Path::new(env!("CARGO_TARGET_TMPDIR")).join("optics");
    std::fs::create_dir_all(&out).unwrap();
    let cpu_vs_golden = fluid_surfels::splat::psnr(&cpu.image, &golden);
    println!("CPU reference vs golden: {cpu_vs_golden:.1} dB");
    if cpu_vs_golden < 45.0 {
        cpu.image.save(out.join("cpu.png")).unwrap();
    }
    assert!(cpu_vs_golden >= 45.0, "{cpu_vs_golden}");
    let water = cpu.linear.iter().filter(|p| p[3] > 0.0).count();
    assert!(water > 3000, "{water} water pixels");
    let Some(ctx) = context_or_skip("golden_frame_cpu_and_gpu_agree").unwrap() else {
        return;
    };
    let (gpu, times) = render_gpu(&ctx, &stage, &surfels, Some((128, 128))).unwrap();
    let (image, linear) = gpu.frame.unwrap();
    let db = fluid_surfels::splat::psnr(&image, &golden);
    println!(
        "GPU vs golden (CPU reference): {db:.1} dB; GPU caustics {:.1} ms, frame {:.1} ms",
        times.caustics_ms, times.frame_ms
    );
    if db < 35.0 {
        image.save(out.join("gpu.png")).unwrap();
        golden.save(out.join("golden.png")).unwrap();
        fluid_surfels::splat::difference_image(&image, &golden, 8)
            .save(out.join("difference.png"))
            .unwrap();
    }
    assert!(db >= 35.0, "{db} dB; images in {}", out.display());
    assert!(linear.iter().flatten().all(|v| v.is_finite()));
}

#[test]
fn degenerate_scenes_give_finite_gpu_images() {
    let Some(ctx) = context_or_skip("degenerate_scenes_give_finite_gpu_images").unwrap() else {
        return;
    };
    let flat = height_field(1.0, 0.05, |_, _| 0.5);
    let mut base = OpticsScene::default();
    base.optics.caustics_resolution = Some([32, 32]);
    base.optics.map_resolution = Some([48, 48]);
    let mut tir = base.clone();
    tir.water.ior = 0.7;
    tir.light.direction = Vec3::new(1.0, 0.5, 0.0);
    let mut parallel = base.clone();
    parallel.light.direction = Vec3::X;
    let mut miss = base.clone();
    miss.receiver.kind = ReceiverKind::Plane;
    miss.receiver.min = Vec3::new(5.0, 0.0, 5.0);
    miss.receiver.max = Vec3::new(6.0, 1.0, 6.0);
    let mut point = base.clone();
    point.light.kind = LightKind::Point;
    point.light.position = Vec3::new(0.0, 0.6, 0.0);
    for (name, scene, surfels) in [
        ("empty", base.clone(), Vec::new()),
        ("total internal reflection", tir, flat.clone()),
        ("light parallel to the water", parallel, flat.clone()),
        ("rays that miss the receiver", miss, flat.clone()),
        ("point light", point, flat.clone()),
    ] {
        let stage = Stage::new(&scene, &surfels).unwrap();
        let (gpu, _) = render_gpu(&ctx, &stage, &surfels, Some((32, 32))).unwrap();
        assert!(
            gpu.irradiance.iter().flatten().all(|v| v.is_finite()),
            "{name}"
        );
        assert!(
            gpu.frame.unwrap().1.iter().flatten().all(|v| v.is_finite()),
            "{name}"
        );
    }
}

/// Flat water 0.5 deep in an open box of walls `height` high, under a slanted light.
fn pool_scene(height: f32, light: Vec3) -> (OpticsScene, Vec<Surfel>) {
    let surfels = height_field(1.0, 0.02, |_, _| 0.5);
    let mut scene = OpticsScene::default();
    scene.light.direction = light;
    scene.receiver.kind = ReceiverKind::OpenBox;
    scene.receiver.min = Vec3::new(-1.2, 0.0, -1.2);
    scene.receiver.max = Vec3::new(1.2, height, 1.2);
    scene.optics.caustics_resolution = Some([96, 96]);
    scene.optics.map_resolution = Some([192, 192]);
    (scene, surfels)
}

/// Water that the pool's walls shade from the light receives no light, so it sends none into the
/// water: under a low light behind walls 3 high, all of the 0.5-deep water is in the walls'
/// shadow and the caustics map stays dark, on the CPU and on the GPU. (Before, the CPU refracted
/// the light of water the light could not reach: a third of the column pool's water pixels.)
#[test]
fn water_in_the_walls_shadow_sends_no_light() {
    // travel towards -x, 0.3 down per unit: the +x wall's shadow reaches 8.3 units in
    let (scene, surfels) = pool_scene(3.0, Vec3::new(1.0, 0.3, 0.0));
    let stage = Stage::new(&scene, &surfels).unwrap();
    let c = caustics_cpu(&stage, &surfels).unwrap();
    let lit_water = c
        .vertices
        .iter()
        .filter(|v| v.surface.w > 0.0 && v.transmit.max_element() > 0.0)
        .count();
    assert_eq!(
        lit_water, 0,
        "water pixels the light reaches behind the wall"
    );
    assert_eq!(c.total_flux(), Vec3::ZERO);
    // the same light over low walls (0.6: shadow 0.33 units in) lights most of the water
    let (low, _) = pool_scene(0.6, Vec3::new(1.0, 0.3, 0.0));
    let open = caustics_cpu(&Stage::new(&low, &surfels).unwrap(), &surfels).unwrap();
    assert!(open.total_flux().x > 0.1, "{}", open.total_flux());
    if let Some(ctx) = context_or_skip("water_in_the_walls_shadow_sends_no_light").unwrap() {
        let (gpu, _) = render_gpu(&ctx, &stage, &surfels, None).unwrap();
        let total: f32 = gpu.flux.iter().map(|f| f[0] + f[1] + f[2]).sum();
        assert_eq!(total, 0.0, "GPU flux behind the wall");
    }
}

/// Light reaching a wall from outside the water is the analytic direct light: Lambert, nothing
/// else. On the outer faces of the two walls that face the light, the irradiance equals
/// `E cos(theta)` exactly; no caustics of the floor behind them (the light's caustics map is a
/// view from the light, and the refracted light that lands on the walls' inner sides, which the
/// light does not see, used to be kept in the texels of the outer faces in front of them).
#[test]
fn outer_walls_get_exactly_the_direct_light() {
    let light = Vec3::new(0.5, 1.0, 0.3);
    let (scene, surfels) = pool_scene(1.0, light);
    let stage = Stage::new(&scene, &surfels).unwrap();
    let c = caustics_cpu(&stage, &surfels).unwrap();
    assert!(c.total_flux().x > 0.1, "the floor gets caustics");
    let l = light.normalize();
    let e = scene.light.colour;
    let mut checked = 0;
    // away from the rim by more than the map's 3-texel depth bias (texels of 0.016 here): within
    // it the light still cannot tell the two sides of the zero-thickness wall apart, and the rim
    // keeps 0.1 % of the inner side's caustics (measured at 0.05 below the top)
    for normal in [Vec3::X, Vec3::Z] {
        for i in 1..18 {
            for j in 1..20 {
                let (a, b) = (i as f32 * 0.05, -1.1 + j as f32 * 0.11);
                let p = if normal == Vec3::X {
                    Vec3::new(1.2, a, b)
                } else {
                    Vec3::new(b, a, 1.2)
                };
                let got = fluid_surfels::optics::receiver_irradiance(&stage, &c, p, normal);
                let expected = e * normal.dot(l);
                assert!(
                    (got - expected).abs().max_element() <= 1e-6 * expected.max_element(),
                    "outer wall {normal} at {p}: {got} instead of {expected}"
                );
                checked += 1;
            }
        }
    }
    assert_eq!(checked, 2 * 17 * 19);
}

/// The same on the column's splash frame, where the splash sends refracted light onto the inner
/// sides of the walls that face away from the light: on the outer faces of the two walls facing
/// the light (the ones the main job's camera looks at), the irradiance is exactly the direct
/// light `E cos(theta)`. The light reaching an outer face of the container crosses no water
/// (`Container::outer_face`), so the light's maps are not read there. History: before the
/// caustics map kept only the sides the light sees, 963 of the points were off; then 34 of
/// 1,022 by more than 1e-4 and 4 by more than 1 %, the worst 9.4 % (a caustics triangle on the
/// floor behind the wall straddling the wall's texels), and the points the light's screen showed
/// water in front of (a splat reaching through the wall) were left out. Now: every point, none off.
#[test]
fn column_pool_outer_walls_get_the_direct_light() {
    use fluid_surfels::pipeline::{Pipeline, PipelineParams, Through, column_frame};
    use fluid_surfels::scenes::{ColumnParams, ColumnSim, column_pool};
    let mut sim = ColumnSim::new(ColumnParams::default()).unwrap();
    let tank = ColumnParams::default().tank;
    let mut params = PipelineParams {
        support_radius: Some(sim.support_radius()),
        scene: column_pool(tank),
        ..Default::default()
    };
    params.scene.optics.image_size = [32, 32];
    let mut p = Pipeline::new(params).unwrap();
    let f = column_frame(
        &mut p,
        &mut sim,
        ColumnParams::SPLASH_FRAME,
        Through::Frame,
        |_| {},
    )
    .unwrap();
    let fin = f.finished.as_ref().unwrap();
    let (stage, c) = (&fin.stage, &fin.caustics);
    let (lo, hi) = stage.receiver.bounds();
    let l = stage.scene.light.direction.normalize();
    let e = stage.scene.light.colour;
    let (mut checked, mut wrong, mut lit) = (0, Vec::new(), 0);
    for normal in [Vec3::X, Vec3::Z] {
        for i in 1..24 {
            for j in 1..24 {
                // below the rim by more than the map's depth bias (see the pool test above)
                let a = lo.y + (hi.y - lo.y) * 0.9 * i as f32 / 24.0;
                let p = if normal == Vec3::X {
                    Vec3::new(hi.x, a, lo.z + (hi.z - lo.z) * j as f32 / 24.0)
                } else {
                    Vec3::new(lo.x + (hi.x - lo.x) * j as f32 / 24.0, a, hi.z)
                };
                checked += 1;
                let got = fluid_surfels::optics::receiver_irradiance(stage, c, p, normal);
                let expected = e * normal.dot(l);
                let off = (got - expected).abs().max_element() / expected.max_element();
                if off > 1e-6 {
                    lit += 1;
                }
                if off > 1e-4 {
                    wrong.push((p, got, expected));
                }
            }
        }
    }
    let worst = wrong
        .iter()
        .map(|(_, got, expected): &(Vec3, Vec3, Vec3)| {
            (*got - *expected).abs().max_element() / expected.max_element()
        })
        .fold(0f32, f32::max);
    println!(
        "{checked} points on the outer walls: {lit} with light besides the direct, {} by more than 1e-4 (at most {:.3} %)",
        wrong.len(),
        100.0 * worst
    );
    assert_eq!(checked, 2 * 23 * 23);
    assert_eq!(lit, 0, "points with light besides the direct");
    assert!(wrong.is_empty(), "{:?}", &wrong[..wrong.len().min(3)]);
}

/// Wall and floor pixels that no water covers (and whose light reaches them past no water)
/// show the analytic direct light: `albedo (E cos(theta) visible) + L_a`, with the pool's own
/// shadow found by an exact ray towards the light. A water slab (its top 0.4 high, |x|, |z| <=
/// 0.6) stands in an open box 2.4 wide with walls 0.8 high, under light from straight above and
/// from the side. Pixels whose light passes the water's surface or where its refracted light can
/// land (the floor swept from under the slab to its shadow, with a margin of the splats' size)
/// are left out: they carry caustics, which have no closed form here.
#[test]
fn dry_pool_pixels_show_the_analytic_direct_light() {
    use fluid_surfels::splat::{Light, SplatParams, View};
    let surfels = height_field(0.6, 0.02, |_, _| 0.4);
    let (half, top, margin) = (0.6f32, 0.4f32, 0.06f32);
    for light in [Vec3::Y, Vec3::new(0.6, 1.0, 0.3)] {
        let mut scene = OpticsScene::default();
        scene.light.direction = light;
        scene.receiver.kind = ReceiverKind::OpenBox;
        scene.receiver.min = Vec3::new(-1.2, 0.0, -1.2);
        scene.receiver.max = Vec3::new(1.2, 0.8, 1.2);
        scene.receiver.checker = 0.2;
        scene.camera = Some(fluid_surfels::splat::Camera {
            eye: Vec3::new(0.9, 2.8, 2.9),
            target: Vec3::new(0.0, 0.2, 0.0),
            near: 0.1,
            far: 20.0,
            ..Default::default()
        });
        let (w, h) = (200u32, 150u32);
        let stage = Stage::new(&scene, &surfels).unwrap();
        let c = caustics_cpu(&stage, &surfels).unwrap();
        let frame = frame_cpu(&stage, &surfels, &c, (w, h)).unwrap();
        let view = View::new(
            &stage.camera,
            &Light::default(),
            &SplatParams::default(),
            w,
            h,
        )
        .unwrap();
        let l = light.normalize();
        let e = scene.light.colour;
        let horizontal = Vec3::new(l.x, 0.0, l.z);
        // how far the slab's light (direct and refracted) moves sideways on its way to the floor
        let sweep = if l.y > 0.0 {
            top * horizontal.length() / l.y
        } else {
            0.0
        };
        let over_slab = |q: Vec3| q.x.abs() <= half + margin && q.z.abs() <= half + margin;
        let (mut checked, mut off, mut worst) = (0usize, 0usize, 0.0f32);
        let mut marked = frame.image.clone();
        for i in 0..(w * h) as usize {
            if frame.linear[i][3] > 0.0 {
                continue; // water covers the pixel
            }
            let (o, d) = view.world_ray(glam::Vec2::new(
                (i as u32 % w) as f32 + 0.5,
                (i as u32 / w) as f32 + 0.5,
            ));
            let Some(hit) = stage.receiver.intersect(o, d.normalize(), 0.0) else {
                continue; // the environment
            };
            let (p, n) = (hit.position, hit.normal);
            // the light's path from the water's surface, and where refracted light can land
            let toward = horizontal.normalize_or_zero();
            let wet = (0..=20).any(|k| over_slab(p + toward * (sweep * k as f32 / 20.0)))
                && p.y < top + margin;
            if wet {
                continue;
            }
            let cos = n.dot(l);
            let lit = cos > 0.0 && stage.receiver.intersect(p + n * 1e-4, l, 1e-4).is_none();
            let expected =
                stage.albedo(p, n) * if lit { e * cos } else { Vec3::ZERO } + scene.light.ambient;
            let got = Vec3::new(frame.linear[i][0], frame.linear[i][1], frame.linear[i][2]);
            let err = ((got - expected).abs() / expected.max(Vec3::splat(1e-3))).max_element();
            worst = worst.max(err);
            if err > 0.01 {
                off += 1;
                marked.put_pixel(i as u32 % w, i as u32 / w, image::Rgba([255, 0, 0, 255]));
            }
            checked += 1;
        }
        let share = off as f64 / checked.max(1) as f64;
        let out = std::path::Path::new(env!("CARGO_TARGET_TMPDIR")).join("optics");
        std::fs::create_dir_all(&out).unwrap();
        marked
            .save(out.join(format!(
                "dry_pool_off_{}.png",
                if light == Vec3::Y { "above" } else { "side" }
            )))
            .unwrap();
        println!(
            "light {light}: {checked} dry receiver pixels checked, {off} off by more than 1 % ({:.3} %), worst {:.1} %",
            100.0 * share,
            100.0 * worst
        );
        assert!(checked > 5000, "{checked}");
        assert!(
            share <= 0.001,
            "light {light}: {off} of {checked} pixels off"
        );
    }
}

/// The water's shadow on the floor ends in a ramp one texel of the light's screen wide, not in
/// texel steps: along a line from under a water slab out into the sun, the share of the direct
/// light the water takes (`water_cover`) goes from 1 to 0 and changes by no more than the
/// distance walked in texels (the bound of bilinear filtering). Tested per texel, it jumped
/// from 1 to 0 in one step: the saw-tooth edges and blocky drop shadows of issue 14.
#[test]
fn the_waters_shadow_edge_is_a_ramp_not_texel_steps() {
    let surfels = height_field(0.6, 0.02, |_, _| 0.4);
    let mut scene = OpticsScene::default();
    scene.light.direction = Vec3::Y;
    scene.receiver.kind = ReceiverKind::OpenBox;
    scene.receiver.min = Vec3::new(-1.2, 0.0, -1.2);
    scene.receiver.max = Vec3::new(1.2, 0.8, 1.2);
    let stage = Stage::new(&scene, &surfels).unwrap();
    let c = caustics_cpu(&stage, &surfels).unwrap();
    let screen = &stage.views.screen;
    let steps = 4000;
    let samples: Vec<(f32, Vec3)> = (0..=steps)
        .map(|k| {
            // along the floor, diagonally (texel edges cross it in x and z), out from the centre
            let t = 1.0 * k as f32 / steps as f32;
            let p = Vec3::new(0.2 + t, 1e-4, 0.1 + 0.37 * t);
            (c.water_cover(p), screen.project(p))
        })
        .collect();
    assert_eq!(samples[0].0, 1.0, "under the slab");
    assert_eq!(samples[steps].0, 0.0, "in the sun");
    let ramp = samples
        .iter()
        .filter(|(c, _)| *c > 0.02 && *c < 0.98)
        .count();
    assert!(ramp > 10, "{ramp} samples on the edge's ramp");
    let mut worst = 0f32;
    for w in samples.windows(2) {
        let ((a, qa), (b, qb)) = (w[0], w[1]);
        let walked = (qb.x - qa.x).abs() + (qb.y - qa.y).abs();
        worst = worst.max((b - a).abs() / walked.max(1e-9));
        assert!(
            (b - a).abs() <= walked + 1e-5,
            "the cover jumps by {} over {walked} texels",
            (b - a).abs()
        );
    }
    println!("{ramp} samples on the ramp; steepest {worst:.3} per texel");
}

/// The CPU caustics are the same on 1, 2 and 3 threads: the triangles' fates in parallel, the
/// map's bands deposited at once, each texel's shares in triangle order.
#[test]
fn cpu_caustics_do_not_depend_on_the_thread_count() {
    let (scene, surfels) = lens_scene(3.5);
    let stage = Stage::new(&scene, &surfels).unwrap();
    let run = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| caustics_cpu(&stage, &surfels).unwrap())
    };
    let one = run(1);
    assert!(one.triangles > 1000, "{}", one.triangles);
    for threads in [2, 3] {
        let other = run(threads);
        assert_eq!(one.flux, other.flux, "{threads} threads");
        assert_eq!(one.irradiance, other.irradiance, "{threads} threads");
        assert_eq!(
            (one.transmitted, one.dropped, one.incident),
            (other.transmitted, other.dropped, other.incident)
        );
        assert_eq!(
            (one.triangles, one.hidden, one.missed, one.discontinuous),
            (
                other.triangles,
                other.hidden,
                other.missed,
                other.discontinuous
            )
        );
    }
}

/// The receiver's views kept from frame to frame (`ReceiverViews`: the light's geometry map, the
/// camera's receiver hits) give the caustics and the frame of a fresh computation, bit for bit:
/// frames over the same views and pool, then the pool's floor alone seen through the same views
/// (the kept ones must not be read), then a moved camera, then the first pool again.
#[test]
fn kept_receiver_views_give_the_fresh_frames() {
    use fluid_surfels::optics::{
        ReceiverViews, caustics_of, caustics_reusing, frame_of, frame_reusing,
    };
    let (low, surfels) = pool_scene(0.8, Vec3::new(0.3, 1.0, 0.2));
    let mut floor = low.clone();
    floor.receiver.kind = ReceiverKind::Plane;
    let mut moved = low.clone();
    moved.camera = Some(fluid_surfels::splat::Camera {
        eye: Vec3::new(1.5, 3.0, 2.5),
        target: Vec3::new(0.0, 0.3, 0.0),
        ..Default::default()
    });
    let stage = |scene: &OpticsScene| Stage::new(scene, &surfels).unwrap();
    // the floor's stage with the pool's views and camera: only the receiver changes
    let pool = stage(&low);
    let mut floor = stage(&floor);
    floor.views = pool.views;
    floor.camera = pool.camera;
    let water: &[Surfel] = &surfels;
    let mut kept = ReceiverViews::default();
    for (k, stage) in [pool, stage(&low), floor, stage(&moved), stage(&low)]
        .iter()
        .enumerate()
    {
        let fresh = caustics_of(stage, &water).unwrap();
        let reused = caustics_reusing(stage, &water, &mut kept).unwrap();
        assert!(
            fresh == reused,
            "frame {k}: the caustics differ from a fresh computation"
        );
        let size = (64, 48);
        let a = frame_of(stage, &water, &fresh, size).unwrap();
        let b = frame_reusing(stage, &water, &fresh, size, &mut kept).unwrap();
        assert_eq!(
            a.linear, b.linear,
            "frame {k}: the picture differs from a fresh one"
        );
        assert!(
            a.linear.iter().any(|p| p[3] > 0.0),
            "frame {k}: no water drawn"
        );
    }
}
