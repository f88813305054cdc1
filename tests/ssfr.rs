//! The screen-space renderer (Oliveira and Paiva, narrow-band screen-space fluid rendering):
//! the narrow band against every particle, each filter against the analytic surface of a
//! particle sphere, thickness from voxel centroids against thickness from voxel centres, the
//! renderer in the pipeline and bad input.

use fluid_surfels::pipeline::{self, Pipeline, PipelineParams, Renderer, SurfelSource, Through};
use fluid_surfels::splat::{self, Camera, Light, SplatParams, View};
use fluid_surfels::ssfr::{
    DepthFilter, ScreenSpace, SsfrError, SsfrParams, cpu::ThicknessSource, cpu::thickness_image,
};
use fluid_surfels::{ParticleSet, io, scenes};
use glam::Vec3;

fn data(name: &str) -> ParticleSet {
    io::read_particles(
        &std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("tests/data")
            .join(name),
        None,
    )
    .unwrap()
}

fn bounds(p: &[Vec3]) -> (Vec3, Vec3) {
    p.iter()
        .fold((Vec3::INFINITY, Vec3::NEG_INFINITY), |(a, b), &q| {
            (a.min(q), b.max(q))
        })
}

/// A camera from the front, right and above, at `distance` times the points' reach.
fn camera_for(p: &[Vec3], distance: f32) -> Camera {
    let (lo, hi) = bounds(p);
    let centre = 0.5 * (lo + hi);
    let reach = 0.5 * (hi - lo).length();
    Camera {
        eye: centre + Vec3::new(0.4, 0.8, 1.0).normalize() * distance * reach,
        target: centre,
        fov_y_degrees: 40.0,
        ..Default::default()
    }
}

fn view(camera: &Camera, w: u32, h: u32) -> View {
    View::new(camera, &Light::default(), &SplatParams::default(), w, h).unwrap()
}

/// The column scene's splash frame, a particle sphere and the two real files, with their support
/// radii.
fn frames() -> Vec<(&'static str, Vec<Vec3>, f32)> {
    let mut sim = scenes::ColumnSim::new(scenes::ColumnParams::default()).unwrap();
    sim.advance_to(scenes::ColumnParams::SPLASH_FRAME);
    let column = sim.particles().positions.clone();
    let mut out = vec![("column splash", column, sim.support_radius())];
    // a particle sphere of 18 spacings (about 24,000 particles): a body with an interior
    let ball = scenes::sphere(&scenes::SphereParams::default()).unwrap();
    out.push((
        "particle sphere",
        ball.particles.positions,
        ball.support_radius,
    ));
    for name in [
        "double_dam_break_frame_26_4732_particles.vtk",
        "dam_break_frame_23_24389_particles.bgeo",
    ] {
        let set = data(name);
        let h = fluid_surfels::neighbours::support_radius(&set.positions).unwrap();
        out.push((name, set.positions.clone(), h));
    }
    out
}

/// The paper's "nearly indistinguishable": with the same filter, the narrow band's image (its
/// particles' depth, its voxels' thickness, eq. 3) lies >= 35 dB from every particle's (eq. 1),
/// on the column splash frame, a particle sphere and both real files; the band's share of the particles is
/// printed (the paper's Table 2).
#[test]
fn the_narrow_band_renders_what_every_particle_renders() {
    for (name, positions, h) in frames() {
        let radii = vec![h; positions.len()];
        let camera = camera_for(&positions, 2.2);
        let v = view(&camera, 320, 240);
        for filter in [DepthFilter::NarrowRange, DepthFilter::CurvatureFlow] {
            let band = SsfrParams {
                filter,
                ..Default::default()
            };
            let all = SsfrParams {
                narrow_band: false,
                ..band
            };
            let nb = ScreenSpace::new(&positions, &radii, h, &band).unwrap();
            let full = ScreenSpace::new(&positions, &radii, h, &all).unwrap();
            let a = nb.render_view(&v).unwrap();
            let b = full.render_view(&v).unwrap();
            let psnr = splat::psnr(&a.render.image, &b.render.image);
            let covered = a.render.covered_pixels();
            println!(
                "{name}, {filter}: band {} of {} particles ({:.1} %), {} voxels; {psnr:.1} dB, {covered} px",
                nb.drawn(),
                positions.len(),
                100.0 * nb.drawn() as f64 / positions.len() as f64,
                nb.sources().len()
            );
            assert!(covered > 2000, "{name}: {covered} pixels");
            assert!(psnr >= 35.0, "{name}, {filter}: {psnr:.1} dB");
        }
    }
}

/// The depth of an analytic sphere (centre `c`, radius `r`) along pixel `(x, y)`'s ray.
fn sphere_depth(v: &View, x: usize, y: usize, c: Vec3, r: f32) -> Option<f32> {
    let (o, d) = v.world_ray(glam::Vec2::new(x as f32 + 0.5, y as f32 + 0.5));
    let a = d.length_squared();
    let oc = o - c;
    let b = oc.dot(d);
    let disc = b * b - a * (oc.length_squared() - r * r);
    (disc >= 0.0).then(|| (-b - disc.sqrt()) / a)
}

/// Each filter brings the depth of a jittered particle sphere closer to a true sphere: the mean
/// absolute depth error against the best-fitting sphere about the particles' centre (its radius
/// searched, so that the spheres' offset does not count), over the pixels within 80 % of the
/// silhouette's radius, is smaller after every filter than before (printed).
#[test]
fn every_filter_brings_a_particle_sphere_closer_to_a_sphere() {
    let scene = scenes::sphere(&scenes::SphereParams {
        radius_in_spacings: 8.0,
        jitter: 0.1,
        ..Default::default()
    })
    .unwrap();
    let p = &scene.particles.positions;
    let h = scene.support_radius;
    let spacing = 0.05;
    let centre = p.iter().copied().sum::<Vec3>() / p.len() as f32;
    let radii = vec![h; p.len()];
    let camera = camera_for(p, 3.0);
    let (w, hgt) = (200usize, 200usize);
    let v = view(&camera, w as u32, hgt as u32);
    let outer = 8.0 * spacing;
    // pixels whose ray passes within 80 % of the outer radius of the centre
    let inner: Vec<(usize, usize)> = (0..w * hgt)
        .map(|i| (i % w, i / w))
        .filter(|&(x, y)| sphere_depth(&v, x, y, centre, 0.8 * outer).is_some())
        .collect();
    assert!(inner.len() > 2000, "{} pixels", inner.len());
    let error = |depth: &[f32]| -> f64 {
        (0..=60)
            .map(|k| {
                let r = outer * (0.8 + 0.01 * k as f32);
                let sum: f64 = inner
                    .iter()
                    .map(|&(x, y)| {
                        let z = depth[y * w + x];
                        match sphere_depth(&v, x, y, centre, r) {
                            Some(t) if z.is_finite() => f64::from((z - t).abs()),
                            _ => f64::from(outer),
                        }
                    })
                    .sum();
                sum / inner.len() as f64
            })
            .fold(f64::INFINITY, f64::min)
    };
    let mut unfiltered = None;
    for filter in DepthFilter::ALL {
        let params = SsfrParams {
            filter,
            ..Default::default()
        };
        let r = ScreenSpace::new(p, &radii, h, &params)
            .unwrap()
            .render_view(&v)
            .unwrap();
        let before = *unfiltered.get_or_insert(error(&r.raw_depth));
        let after = error(&r.depth);
        println!(
            "{filter}: mean depth error {:.3} spacings (unfiltered {:.3})",
            after / f64::from(spacing),
            before / f64::from(spacing)
        );
        if filter != DepthFilter::None {
            assert!(
                after < 0.9 * before,
                "{filter}: {after} against {before} unfiltered"
            );
        }
    }
}

/// The paper's Figure 13 claim: the thickness from the voxels' particle centroids (eq. 3) is
/// closer to the particles' own thickness (eq. 1) than the thickness from the voxel centres,
/// as mean absolute difference over the pixels either covers (measured on both real files and
/// the column splash, printed).
#[test]
fn thickness_from_centroids_is_closer_to_the_particles_than_from_voxel_centres() {
    for (name, positions, h) in frames() {
        let radii = vec![h; positions.len()];
        let params = SsfrParams::default();
        let screen = ScreenSpace::new(&positions, &radii, h, &params).unwrap();
        let band = screen.band().unwrap();
        let v = view(&camera_for(&positions, 2.2), 240, 180);
        let particles: Vec<ThicknessSource> = positions
            .iter()
            .map(|&c| ThicknessSource {
                centre: c,
                volume: (0.5 * h).powi(3),
                sigma: params.thickness_sigma * h,
            })
            .collect();
        let centres: Vec<ThicknessSource> = screen
            .sources()
            .iter()
            .zip(&band.voxels)
            .map(|(s, voxel)| ThicknessSource {
                centre: band.origin + (Vec3::from(voxel.coord.map(|c| c as f32)) + 0.5) * band.edge,
                ..*s
            })
            .collect();
        let reference = thickness_image(&v, &particles).unwrap();
        let from_centroids = thickness_image(&v, screen.sources()).unwrap();
        let from_centres = thickness_image(&v, &centres).unwrap();
        let mad = |t: &[f32]| -> f64 {
            let (sum, n) = reference
                .iter()
                .zip(t)
                .filter(|(a, b)| **a > 0.0 || **b > 0.0)
                .fold((0.0f64, 0usize), |(s, n), (a, b)| {
                    (s + f64::from((a - b).abs()), n + 1)
                });
            sum / n as f64
        };
        let volume: f64 = particles.iter().map(|s| f64::from(s.volume)).sum();
        let (c, v_) = (mad(&from_centroids), mad(&from_centres));
        println!(
            "{name}: mean |T_G - T_P| from centroids {:.4} h, from voxel centres {:.4} h ({:.2}x); {} voxels, fluid volume {volume:.4}",
            c / f64::from(h),
            v_ / f64::from(h),
            v_ / c,
            band.voxels.len()
        );
        assert!(c < v_, "{name}: centroids {c} against centres {v_}");
    }
}

/// The renderer in the pipeline: the shaded splats are the screen-space image of the frame's
/// points, the finished frame refracts through the screen-space water, and the GPU pipeline is
/// not pretended: it says the renderer has no GPU path.
#[test]
fn the_pipeline_draws_the_screen_space_water_in_the_splats_and_the_optics() {
    let set = data("double_dam_break_frame_26_4732_particles.vtk");
    let mut params = PipelineParams {
        renderer: Renderer::Ssfr,
        source: SurfelSource::Particles,
        ..Default::default()
    };
    params.scene.optics.image_size = [96, 72];
    let mut pipeline = Pipeline::new(params).unwrap();
    let frame = pipeline.frame_through(&set, Through::Splats).unwrap();
    assert!(frame.grid.is_none(), "no density grid for screen space");
    let splats = frame.splats.as_ref().unwrap();
    let (positions, radii) = pipeline::sphere_points(&frame.render_surfels);
    let screen = pipeline.screen_space(&positions, &radii).unwrap();
    let expected = screen
        .render_view(
            &View::new(
                &frame.camera.unwrap(),
                &Light::default(),
                &pipeline.splat_params(),
                96,
                72,
            )
            .unwrap(),
        )
        .unwrap();
    assert_eq!(splats.image, expected.render.image);
    assert!(splats.covered_pixels() > 800, "{}", splats.covered_pixels());
    let finished = pipeline.frame(&set).unwrap();
    let f = finished.finished.as_ref().unwrap();
    let wet = f.linear.iter().filter(|p| p[3] > 0.0).count();
    assert!(wet > 400, "{wet} wet pixels");
    assert!(f.caustics.total_flux().length() > 0.0);
}

/// The image does not depend on the thread count.
#[test]
fn one_thread_renders_what_two_render() {
    let set = data("double_dam_break_frame_26_4732_particles.vtk");
    let h = fluid_surfels::neighbours::support_radius(&set.positions).unwrap();
    let radii = vec![h; set.len()];
    let v = view(&camera_for(&set.positions, 2.2), 160, 120);
    let run = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| {
                ScreenSpace::new(&set.positions, &radii, h, &SsfrParams::default())
                    .unwrap()
                    .render_view(&v)
                    .unwrap()
            })
    };
    let (a, b) = (run(1), run(2));
    assert_eq!(a.render.image, b.render.image);
    assert_eq!(a.thickness, b.thickness);
}

/// Bad points and parameters get typed errors; no points renders the background.
#[test]
fn bad_input_is_refused_and_no_points_render_the_background() {
    let p = vec![Vec3::ZERO, Vec3::X];
    let r = vec![0.1, 0.1];
    let params = SsfrParams::default();
    let nan = vec![Vec3::ZERO, Vec3::NAN];
    assert!(matches!(
        ScreenSpace::new(&nan, &r, 0.1, &params),
        Err(SsfrError::InvalidPoint { index: 1, .. })
    ));
    assert!(matches!(
        ScreenSpace::new(&p, &[0.1, 0.0], 0.1, &params),
        Err(SsfrError::InvalidPoint { index: 1, .. })
    ));
    assert!(matches!(
        ScreenSpace::new(&p, &r[..1], 0.1, &params),
        Err(SsfrError::InvalidParameter { name: "radii", .. })
    ));
    assert!(matches!(
        ScreenSpace::new(&p, &r, f32::INFINITY, &params),
        Err(SsfrError::InvalidParameter { .. })
    ));
    let bad = SsfrParams {
        curvature_step: 1.0,
        ..params
    };
    assert!(matches!(
        ScreenSpace::new(&p, &r, 0.1, &bad),
        Err(SsfrError::InvalidParameter {
            name: "curvature_step",
            ..
        })
    ));
    // coincident points are fine
    let same = vec![Vec3::ONE; 3];
    ScreenSpace::new(&same, &[0.1; 3], 0.1, &params).unwrap();
    let camera = Camera {
        eye: Vec3::new(0.0, 0.0, 3.0),
        target: Vec3::ZERO,
        ..Default::default()
    };
    let empty = ScreenSpace::new(&[], &[], 0.1, &params)
        .unwrap()
        .render_view(&view(&camera, 32, 32))
        .unwrap();
    assert_eq!(empty.render.covered_pixels(), 0);
}

/// Two depth buffers against each other over the pixels either covers: the largest difference
/// (world units), the share of the pixels both cover that differ by more than 1e-5 relative,
/// and the count of pixels only one covers.
fn depth_difference(a: &[f32], b: &[f32]) -> (f32, f64, usize) {
    let (mut worst, mut off, mut both, mut coverage) = (0.0f32, 0usize, 0usize, 0usize);
    for (&x, &y) in a.iter().zip(b) {
        match (x.is_finite(), y.is_finite()) {
            (true, true) => {
                both += 1;
                worst = worst.max((x - y).abs());
                off += usize::from((x - y).abs() > 1e-5 * x.abs());
            }
            (false, false) => {}
            _ => coverage += 1,
        }
    }
    (worst, off as f64 / both.max(1) as f64, coverage)
}

/// The largest difference of two thickness images over the first's largest thickness.
fn thickness_difference(a: &[f32], b: &[f32]) -> f32 {
    let largest = a.iter().fold(0.0f32, |m, &t| m.max(t));
    let worst = a
        .iter()
        .zip(b)
        .fold(0.0f32, |m, (x, y)| m.max((x - y).abs()));
    worst / largest.max(f32::MIN_POSITIVE)
}

/// The GPU twin against the CPU reference, each filter, with and without the band, in a
/// perspective view and in an orthographic one (a light's screen): the same coverage, raw and
/// filtered depth within 1e-3 sphere radii (measured: 1e-4; all but 1 % of the pixels within
/// 1e-5 relative), the thickness within 1e-4 of its largest value (measured: 3.3e-6 with the
/// band, whose inputs the GPU makes from the points, 3.8e-7 without), the shaded image >= 40 dB
/// (measured: 74-88 dB; printed). The cases alternate the band's inputs made on the GPU and
/// the CPU's uploaded into the same kept buffers (a stale bind group of the band's passes after
/// the CPU's inputs grew them put the thickness 0.28 of its largest off, 47 dB: found so). A
/// voxel of 3,000 coincident points (its volume from the mean radius, past the fixed-point cube
/// sums' range) meets the CPU's thickness too; a drop far from the body (a dense domain of a
/// million mostly empty voxels) keeps the CPU's sparse band.
#[test]
fn gpu_passes_match_the_cpu_reference_for_every_filter() {
    let Some(ctx) =
        fluid_surfels::gpu::context_or_skip("gpu_passes_match_the_cpu_reference_for_every_filter")
            .unwrap()
    else {
        return;
    };
    let set = data("double_dam_break_frame_26_4732_particles.vtk");
    let p = &set.positions;
    let h = fluid_surfels::neighbours::support_radius(p).unwrap();
    let radii = vec![h; p.len()];
    let camera = camera_for(p, 2.2);
    let perspective = view(&camera, 160, 120);
    let (lo, hi) = bounds(p);
    let centre = 0.5 * (lo + hi);
    let ortho = View::window(
        centre + Vec3::new(0.2, 1.0, 0.3) * 3.0,
        -Vec3::new(0.2, 1.0, 0.3),
        Vec3::Z,
        glam::Vec2::splat(0.6 * (hi - lo).max_element()),
        true,
        0.01,
        10.0,
        &SplatParams::default(),
        128,
        128,
    )
    .unwrap();
    let mut gpu = fluid_surfels::ssfr::gpu::GpuSsfr::new(&ctx.device).unwrap();
    for (name, v) in [("perspective", &perspective), ("orthographic", &ortho)] {
        for filter in DepthFilter::ALL {
            for narrow_band in [true, false] {
                let params = SsfrParams {
                    filter,
                    narrow_band,
                    ..Default::default()
                };
                let screen = ScreenSpace::new(p, &radii, h, &params).unwrap();
                let cpu = screen.render_view(v).unwrap();
                let g = gpu.render(&ctx, &screen, v).unwrap();
                let sphere = screen.sphere();
                let (raw, raw_off, raw_cov) = depth_difference(&cpu.raw_depth, &g.raw_depth);
                let (filtered, off, cov) = depth_difference(&cpu.depth, &g.depth);
                let psnr = splat::psnr(&cpu.render.image, &g.render.image);
                let thickness = thickness_difference(&cpu.thickness, &g.thickness);
                println!(
                    "{name}, {filter}, band {narrow_band}: raw depth within {:.1e} sphere radii ({:.3} % beyond 1e-5), filtered {:.1e} ({:.3} %), thickness {thickness:.1e} of its largest, {psnr:.1} dB, {} px",
                    raw / sphere,
                    100.0 * raw_off,
                    filtered / sphere,
                    100.0 * off,
                    cpu.render.covered_pixels()
                );
                // the band's inputs made on the GPU (and only with the band)
                assert_eq!(gpu.band_on_gpu(), narrow_band, "{name}, {filter}");
                assert!(
                    thickness < 1e-4,
                    "{name}, {filter}: thickness {thickness:.1e}"
                );
                assert!(cpu.render.covered_pixels() > 1000, "{name}");
                assert_eq!((raw_cov, cov), (0, 0), "{name}, {filter}: coverage differs");
                assert!(
                    raw < 1e-3 * sphere && raw_off < 1e-3,
                    "{name}, {filter}: raw depth"
                );
                assert!(
                    filtered < 1e-3 * sphere && off < 1e-2,
                    "{name}, {filter}: filtered"
                );
                assert!(psnr >= 40.0, "{name}, {filter}: {psnr:.1} dB");
            }
        }
    }
    // the CPU's and the GPU's thickness of `points` (radius h each) from the perspective view,
    // and whether the GPU made its band
    let mut thickness_of = |points: &[Vec3]| {
        let radii = vec![h; points.len()];
        let screen = ScreenSpace::new(points, &radii, h, &SsfrParams::default()).unwrap();
        let cpu = screen.render_view(&perspective).unwrap();
        let g = gpu.render(&ctx, &screen, &perspective).unwrap();
        (
            thickness_difference(&cpu.thickness, &g.thickness),
            gpu.band_on_gpu(),
        )
    };
    // coincident points: one voxel of 3,000
    let mut heap = p.clone();
    heap.extend(std::iter::repeat_n(p[0], 3000));
    let (thickness, on_gpu) = thickness_of(&heap);
    println!("3,000 coincident points: thickness within {thickness:.1e} of its largest");
    assert!(on_gpu && thickness < 1e-4, "{thickness:.1e}");
    // a drop far from the body: a dense domain of mostly empty voxels, the CPU's sparse band
    let mut spray = p.clone();
    spray.push(p[0] + Vec3::splat(100.0 * h));
    let (thickness, on_gpu) = thickness_of(&spray);
    println!("a far drop: the CPU's band, thickness within {thickness:.1e} of its largest");
    assert!(!on_gpu && thickness < 1e-4, "{thickness:.1e}");
    // the passes were kept through every case (their buffers rewritten, grown where a case
    // needed more); the last case again creates nothing and draws the same picture
    let params = SsfrParams {
        filter: *DepthFilter::ALL.last().unwrap(),
        narrow_band: false,
        ..Default::default()
    };
    let screen = ScreenSpace::new(p, &radii, h, &params).unwrap();
    let first = gpu.render(&ctx, &screen, &ortho).unwrap();
    let again = gpu.render(&ctx, &screen, &ortho).unwrap();
    // fresh passes make their buffers and draw what the kept ones draw
    let mut fresh = fluid_surfels::ssfr::gpu::GpuSsfr::new(&ctx.device).unwrap();
    let new = fresh.render(&ctx, &screen, &ortho).unwrap();
    assert!(fresh.created() > 0);
    assert_eq!(new.render.image, first.render.image);
    assert_eq!(
        gpu.created(),
        0,
        "the kept passes made buffers for the same inputs"
    );
    assert_eq!(first.render.image, again.render.image);
}
