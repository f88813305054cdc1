//! Ray casting to the iso-surface (Xiao et al.): the CPU reference against the analytic
//! iso-surface of one particle, against the kernel sum's first crossing found by brute force on a
//! particle sphere and a particle slab, and the paper's PCA blending against the density gradient
//! on a noisy slab (its Figure 1 claim).

use fluid_surfels::density::{Kernel, Points};
use fluid_surfels::raycast::{self, Caster, RayCastError, RayCastParams, RayNormals};
use fluid_surfels::scenes;
use fluid_surfels::splat::{Camera, Light, SplatParams, View};
use glam::{Vec2, Vec3};

const SIZE: u32 = 96;

fn exact_params() -> RayCastParams {
    RayCastParams {
        normals: RayNormals::Gradient,
        bilateral_radius_px: 0,
        ..RayCastParams::default()
    }
}

/// The first crossing of the kernel sum of *every* particle (no grid, no sphere intervals) along
/// the world ray `o + t d`, marched from `t0` to `t1` in steps of `dt`, refined by 30 bisections,
/// and the outward gradient normal there.
fn brute_force_hit(
    positions: &[Vec3],
    h: f32,
    iso: f32,
    o: Vec3,
    d: Vec3,
    (t0, t1, dt): (f32, f32, f32),
) -> Option<(f32, Vec3)> {
    let field = |x: Vec3| -> (f32, Vec3) {
        positions.iter().fold((0.0, Vec3::ZERO), |(s, g), &p| {
            let (v, dv) = Kernel::Wyvill.weighted_and_gradient(x - p, h, h);
            (s + v, g + dv)
        })
    };
    let mut t = t0;
    while t < t1 {
        let next = t + dt;
        if field(o + next * d).0 >= iso {
            let (mut lo, mut hi) = (t, next);
            for _ in 0..30 {
                let mid = 0.5 * (lo + hi);
                if field(o + mid * d).0 >= iso {
                    hi = mid;
                } else {
                    lo = mid;
                }
            }
            let t = 0.5 * (lo + hi);
            return Some((t, (-field(o + t * d).1).normalize()));
        }
        t = next;
    }
    None
}

/// One particle: its iso-surface is the sphere where Wyvill's polynomial equals the iso
/// fraction; depth and normal of every covered pixel against the ray's hit on that sphere.
#[test]
fn one_particle_casts_its_analytic_sphere() {
    let h = 1.0;
    let positions = [Vec3::ZERO];
    // poly(a^2) = 1 - 22/9 a^2 + 17/9 a^4 - 4/9 a^6 = 0.75, solved by bisection in a^2
    let poly = |s: f32| ((-4.0 / 9.0 * s + 17.0 / 9.0) * s - 22.0 / 9.0) * s + 1.0;
    let (mut lo, mut hi) = (0.0f32, 1.0f32);
    for _ in 0..60 {
        let mid = 0.5 * (lo + hi);
        if poly(mid) > 0.75 { lo = mid } else { hi = mid }
    }
    let r_iso = (0.5 * (lo + hi)).sqrt() * h;
    let camera = Camera {
        eye: Vec3::new(0.2, 0.4, 2.4),
        target: Vec3::ZERO,
        fov_y_degrees: 25.0,
        ..Default::default()
    };
    let caster = Caster::new(
        Points::uniform(&positions, h),
        Kernel::Wyvill,
        &exact_params(),
    )
    .unwrap();
    let cast = raycast::render_cpu(
        &caster,
        &camera,
        &Light::default(),
        &SplatParams::default(),
        SIZE,
        SIZE,
    )
    .unwrap();
    cast.render.validate().unwrap();
    let v = View::new(
        &camera,
        &Light::default(),
        &SplatParams::default(),
        SIZE,
        SIZE,
    )
    .unwrap();
    let (mut hits, mut misses, mut rim, mut worst_depth, mut worst_angle) =
        (0, 0, 0, 0.0f32, 0.0f32);
    for y in 0..SIZE {
        for x in 0..SIZE {
            let i = (y * SIZE + x) as usize;
            let (o, d) = v.world_ray(Vec2::new(x as f32 + 0.5, y as f32 + 0.5));
            let a = d.length_squared();
            let b = o.dot(d);
            let disc = b * b - a * (o.length_squared() - r_iso * r_iso);
            match (disc > 0.0, cast.render.depth(i)) {
                (true, Some(t)) => {
                    let t_ref = (-b - disc.sqrt()) / a;
                    let n_ref = (o + t_ref * d).normalize();
                    worst_depth = worst_depth.max((t - t_ref).abs() / t_ref);
                    let n = cast.render.normal(i).unwrap();
                    worst_angle =
                        worst_angle.max(n.dot(n_ref).clamp(-1.0, 1.0).acos().to_degrees());
                    hits += 1;
                }
                (false, None) => {}
                // a ray grazing the sphere: the march steps over a chord shorter than a step
                // (0.1 h), and only such a chord may be missed
                (true, None) if 2.0 * disc.sqrt() / a.sqrt() < 0.1 * h => rim += 1,
                _ => misses += 1,
            }
        }
    }
    println!(
        "one particle: {hits} pixels hit, {rim} grazing rays missed (chords under a step), {misses} others differ; worst depth error {:.5} %, worst normal error {worst_angle:.3} degrees",
        100.0 * worst_depth
    );
    assert!(hits > 1500, "{hits} hits");
    assert_eq!(misses, 0, "{misses} pixels differ from the analytic sphere");
    assert!(rim <= hits / 20, "{rim} grazing misses");
    assert!(worst_depth < 1e-3, "depth error {worst_depth}");
    assert!(worst_angle < 0.1, "normal error {worst_angle} degrees");
}

/// On a particle sphere and a particle slab, the caster (gradient normals, no filter) finds the
/// kernel sum's first crossing as a brute-force march over every particle does: depth within
/// 1 % on every sampled pixel, normal within 1 degree on >= 99 % of them.
#[test]
fn sphere_and_slab_hit_the_kernel_sums_first_crossing() {
    let sphere = jittered_sphere(5.0);
    let slab = scenes::block(&scenes::BlockParams {
        counts: [14, 4, 14],
        spacing: 0.05,
        jitter: 0.1,
        seed: 4,
    })
    .unwrap();
    for (name, scene) in [("sphere", sphere), ("slab", slab)] {
        let p = &scene.particles.positions;
        let h = scene.support_radius;
        let (lo, hi) = p
            .iter()
            .fold((Vec3::INFINITY, Vec3::NEG_INFINITY), |(a, b), &q| {
                (a.min(q), b.max(q))
            });
        let centre = 0.5 * (lo + hi);
        let reach = 0.5 * (hi - lo).length() + h;
        let camera = Camera {
            eye: centre + Vec3::new(0.4, 1.0, 0.7).normalize() * 3.0 * reach,
            target: centre,
            fov_y_degrees: 40.0,
            ..Default::default()
        };
        let caster = Caster::new(Points::uniform(p, h), Kernel::Wyvill, &exact_params()).unwrap();
        let cast = raycast::render_cpu(
            &caster,
            &camera,
            &Light::default(),
            &SplatParams::default(),
            SIZE,
            SIZE,
        )
        .unwrap();
        let v = View::new(
            &camera,
            &Light::default(),
            &SplatParams::default(),
            SIZE,
            SIZE,
        )
        .unwrap();
        let (mut sampled, mut within_1_degree, mut worst_depth, mut worst_spacings) =
            (0, 0, 0.0f32, 0.0f32);
        for y in (0..SIZE).step_by(3) {
            for x in (0..SIZE).step_by(3) {
                let i = (y * SIZE + x) as usize;
                let (o, d) = v.world_ray(Vec2::new(x as f32 + 0.5, y as f32 + 0.5));
                // the ray's span through the bounding ball
                let a = d.length_squared();
                let b = (o - centre).dot(d);
                let disc = b * b - a * ((o - centre).length_squared() - reach * reach);
                let reference = (disc > 0.0)
                    .then(|| {
                        let (t0, t1) = ((-b - disc.sqrt()) / a, (-b + disc.sqrt()) / a);
                        brute_force_hit(p, h, caster.iso(), o, d, (t0, t1, 0.02 * h / a.sqrt()))
                    })
                    .flatten();
                match (reference, cast.render.depth(i)) {
                    (Some((t_ref, n_ref)), Some(t)) => {
                        sampled += 1;
                        worst_depth = worst_depth.max((t - t_ref).abs() / t_ref);
                        worst_spacings =
                            worst_spacings.max((t - t_ref).abs() * a.sqrt() / scene.spacing);
                        let n = cast.render.normal(i).unwrap();
                        if n.dot(n_ref).clamp(-1.0, 1.0).acos().to_degrees() <= 1.0 {
                            within_1_degree += 1;
                        }
                    }
                    (None, None) => {}
                    (r, c) => panic!("{name}: pixel ({x}, {y}): reference {r:?}, caster {c:?}"),
                }
            }
        }
        let share = within_1_degree as f64 / sampled as f64;
        println!(
            "{name}: {sampled} pixels sampled; worst depth error {:.4} % ({worst_spacings:.4} spacings); normals within 1 degree on {:.2} %",
            100.0 * worst_depth,
            100.0 * share
        );
        assert!(sampled > 150, "{name}: {sampled} pixels");
        assert!(worst_depth <= 0.01, "{name}: depth error {worst_depth}");
        assert!(share >= 0.99, "{name}: normals within 1 degree on {share}");
    }
}

/// The paper's Figure 1 claim, measured: on a noisy flat slab seen from above, the blended normal
/// map (eqs. 5, 6, then the bilateral filter) errs at most half as much as the density gradient's.
#[test]
fn pca_blending_halves_the_normal_error_on_a_noisy_slab() {
    let scene = scenes::block(&scenes::BlockParams {
        counts: [24, 4, 24],
        spacing: 0.05,
        jitter: 0.3,
        seed: 7,
    })
    .unwrap();
    let p = &scene.particles.positions;
    let h = scene.support_radius;
    let (lo, hi) = p
        .iter()
        .fold((Vec3::INFINITY, Vec3::NEG_INFINITY), |(a, b), &q| {
            (a.min(q), b.max(q))
        });
    let centre = 0.5 * (lo + hi);
    let camera = Camera {
        eye: centre + Vec3::new(0.05, 1.0, 0.1) * 2.0,
        target: centre,
        fov_y_degrees: 20.0,
        ..Default::default()
    };
    let mean_error = |params: RayCastParams| {
        let caster = Caster::new(Points::uniform(p, h), Kernel::Wyvill, &params).unwrap();
        let cast = raycast::render_cpu(
            &caster,
            &camera,
            &Light::default(),
            &SplatParams::default(),
            SIZE,
            SIZE,
        )
        .unwrap();
        let v = View::new(
            &camera,
            &Light::default(),
            &SplatParams::default(),
            SIZE,
            SIZE,
        )
        .unwrap();
        let (mut sum, mut n) = (0.0f64, 0usize);
        for i in 0..(SIZE * SIZE) as usize {
            let (Some(normal), Some(t)) = (cast.render.normal(i), cast.render.depth(i)) else {
                continue;
            };
            let pixel = Vec2::new(
                (i as u32 % SIZE) as f32 + 0.5,
                (i as u32 / SIZE) as f32 + 0.5,
            );
            let (o, d) = v.world_ray(pixel);
            let x = o + t * d;
            // the top face, away from the slab's sides by two support radii
            if x.y < hi.y - 0.5 * h
                || (x.x - centre.x).abs() > 0.5 * (hi.x - lo.x) - 2.0 * h
                || (x.z - centre.z).abs() > 0.5 * (hi.z - lo.z) - 2.0 * h
            {
                continue;
            }
            sum += f64::from(normal.dot(Vec3::Y).clamp(-1.0, 1.0).acos().to_degrees());
            n += 1;
        }
        assert!(n > 1000, "only {n} top pixels");
        sum / n as f64
    };
    let gradient = mean_error(exact_params());
    let pca = mean_error(RayCastParams {
        normals: RayNormals::Pca,
        bilateral_radius_px: 0,
        ..RayCastParams::default()
    });
    let blended_unfiltered = mean_error(RayCastParams {
        bilateral_radius_px: 0,
        ..RayCastParams::default()
    });
    let blended = mean_error(RayCastParams::default());
    for r in [1.0, 1.5, 3.0] {
        let e = mean_error(RayCastParams {
            pca_radius: r,
            ..RayCastParams::default()
        });
        let e_pca = mean_error(RayCastParams {
            pca_radius: r,
            normals: RayNormals::Pca,
            bilateral_radius_px: 0,
            ..RayCastParams::default()
        });
        println!(
            "  PCA radius {r} radii: PCA alone {e_pca:.2} degrees, blended + bilateral {e:.2}"
        );
    }
    println!(
        "noisy slab, mean normal error on the top face: density gradient {gradient:.2} degrees, PCA {pca:.2}, blended {blended_unfiltered:.2}, blended + bilateral {blended:.2} ({:.2}x the gradient's)",
        blended / gradient
    );
    assert!(
        blended <= 0.5 * gradient,
        "blended {blended} against gradient {gradient}"
    );
}

#[test]
fn bad_points_and_parameters_are_refused_and_nothing_renders_empty() {
    let nan = [Vec3::new(f32::NAN, 0.0, 0.0)];
    assert!(
        Caster::new(
            Points::uniform(&nan, 0.1),
            Kernel::Wyvill,
            &RayCastParams::default()
        )
        .is_err()
    );
    let one = [Vec3::ZERO];
    assert!(matches!(
        Caster::new(
            Points::uniform(&one, -1.0),
            Kernel::Wyvill,
            &RayCastParams::default()
        ),
        Err(RayCastError::Density(_) | RayCastError::Surfels(_))
    ));
    for params in [
        RayCastParams {
            step: 0.0,
            ..Default::default()
        },
        RayCastParams {
            iso_fraction: f32::NAN,
            ..Default::default()
        },
        RayCastParams {
            blend_max: 2.0,
            ..Default::default()
        },
        RayCastParams {
            bilateral_sigma_px: 0.0,
            ..Default::default()
        },
    ] {
        let e = Caster::new(Points::uniform(&one, 0.1), Kernel::Wyvill, &params)
            .err()
            .expect("refused");
        assert!(
            e.to_string().contains("invalid ray-casting parameter"),
            "{e}"
        );
    }
    let caster = Caster::new(
        Points::uniform(&[], 0.1),
        Kernel::Wyvill,
        &RayCastParams::default(),
    )
    .unwrap();
    let cast = raycast::render_cpu(
        &caster,
        &Camera::default(),
        &Light::default(),
        &SplatParams::default(),
        16,
        12,
    )
    .unwrap();
    assert_eq!(cast.render.covered_pixels(), 0);
    assert_eq!(cast.samples, 0);
}

/// `Renderer::RayCast` in the pipeline: the shaded splats are the caster's image of the frame's
/// points, and the finished frame refracts through the cast water (its caustics and its camera
/// view both cast).
#[test]
fn the_pipeline_casts_rays_for_the_splats_and_the_optics() {
    use fluid_surfels::pipeline::{
        self, Pipeline, PipelineParams, Renderer, SurfelSource, Through,
    };
    let set = fluid_surfels::io::read_particles(
        std::path::Path::new(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/tests/data/double_dam_break_frame_26_4732_particles.vtk"
        )),
        None,
    )
    .unwrap();
    let mut params = PipelineParams {
        renderer: Renderer::RayCast,
        source: SurfelSource::Particles,
        ..Default::default()
    };
    params.scene.optics.image_size = [80, 60];
    let mut pipeline = Pipeline::new(params).unwrap();
    let frame = pipeline.frame_through(&set, Through::Splats).unwrap();
    assert!(
        frame.grid.is_none() && frame.surfels.is_none(),
        "ray casting needs no grid"
    );
    // the particles weighted so that the surface lies at the fluid's boundary (the default
    // calibration): a weight per sphere
    assert!(!frame.render_surfels.is_empty());
    assert_eq!(frame.render_weights.len(), frame.render_surfels.len());
    let splats = frame.splats.as_ref().unwrap();
    let (positions, radii) = pipeline::sphere_points(&frame.render_surfels);
    let caster = pipeline
        .caster(&positions, &radii, &frame.render_weights)
        .unwrap();
    let expected = raycast::render_cpu(
        &caster,
        &frame.camera.unwrap(),
        &Light::default(),
        &pipeline.splat_params(),
        80,
        60,
    )
    .unwrap();
    assert_eq!(splats.image, expected.render.image);
    assert!(
        splats.covered_pixels() > 500,
        "{} pixels",
        splats.covered_pixels()
    );
    let finished = pipeline.frame(&set).unwrap();
    let f = finished.finished.as_ref().unwrap();
    let wet = f.linear.iter().filter(|p| p[3] > 0.0).count();
    println!(
        "double dam break through the ray caster: {} splat pixels, {wet} wet pixels in the finished frame",
        splats.covered_pixels()
    );
    assert!(wet > 200, "{wet} wet pixels");
    assert!(f.caustics.total_flux().length() > 0.0);
    // the automatic pool meets the calibrated surface (half a spacing outside the spheres'
    // centres, a quarter spacing in), not the spheres' bounds a support radius out
    let (lo, hi) = f.stage.receiver.bounds();
    let (clo, chi) = positions.iter().fold(
        (Vec3::splat(f32::MAX), Vec3::splat(f32::MIN)),
        |(a, b), p| (a.min(*p), b.max(*p)),
    );
    let s = 0.5 * finished.radius;
    for (got, want) in [
        (lo.x, clo.x - 0.25 * s),
        (lo.z, clo.z - 0.25 * s),
        (hi.x, chi.x + 0.25 * s),
        (hi.z, chi.z + 0.25 * s),
        (lo.y, clo.y - 0.25 * s),
    ] {
        assert!(
            (got - want).abs() < 1e-3 * s,
            "pool {lo} {hi}, centres {clo} {chi}"
        );
    }
}

/// The caster's image from `camera` at SIZE x SIZE on the CPU and on the GPU.
fn cast_both(
    ctx: &fluid_surfels::gpu::GpuContext,
    caster: &Caster<'_>,
    camera: &Camera,
) -> (raycast::RayCast, raycast::RayCast) {
    let (light, splat) = (Light::default(), SplatParams::default());
    let gpu = raycast::gpu::render_gpu(ctx, caster, camera, &light, &splat, SIZE, SIZE).unwrap();
    (cast_cpu(caster, camera), gpu)
}

/// The CPU reference's cast of `caster` from `camera` at `SIZE` x `SIZE`, default light.
fn cast_cpu(caster: &Caster<'_>, camera: &Camera) -> raycast::RayCast {
    let (light, splat) = (Light::default(), SplatParams::default());
    raycast::render_cpu(caster, camera, &light, &splat, SIZE, SIZE).unwrap()
}

/// The GPU twin casts the same rays as the CPU reference: PSNR >= 40 dB on a particle sphere
/// and on the column scene's splash frame, every normal mode, with the same covered pixels
/// (but for a few grazing rays).
#[test]
fn gpu_and_cpu_ray_casts_agree() {
    let Some(ctx) = fluid_surfels::gpu::context_or_skip("gpu_and_cpu_ray_casts_agree").unwrap()
    else {
        return;
    };
    let sphere = jittered_sphere(6.0);
    let mut sim = scenes::ColumnSim::new(scenes::ColumnParams::default()).unwrap();
    sim.advance_to(scenes::ColumnParams::SPLASH_FRAME);
    let column = (sim.particles().positions.clone(), sim.support_radius());
    let cases = [
        (
            "particle-sphere",
            (sphere.particles.positions.clone(), sphere.support_radius),
        ),
        ("column-splash", column),
    ];
    // one caster for every case: its buffers kept and rewritten (grown where a case needs more)
    let mut kept = raycast::gpu::GpuCaster::new(&ctx.device, SIZE, SIZE).unwrap();
    let mut cast_kept = |caster: &Caster<'_>, camera: &Camera| {
        let v = View::new(
            camera,
            &Light::default(),
            &SplatParams::default(),
            SIZE,
            SIZE,
        )
        .unwrap();
        kept.prepare(&ctx.device, &ctx.queue, caster, &v).unwrap();
        let mut encoder = ctx.device.create_command_encoder(&Default::default());
        kept.encode(&mut encoder).unwrap();
        ctx.queue.submit([encoder.finish()]);
        (kept.read(&ctx).unwrap(), kept.created())
    };
    let mut last = None;
    for (name, (positions, h)) in &cases {
        let (lo, hi) = positions
            .iter()
            .fold((Vec3::INFINITY, Vec3::NEG_INFINITY), |(a, b), &q| {
                (a.min(q), b.max(q))
            });
        let camera = Camera::framing(lo - *h, hi + *h);
        for normals in [RayNormals::Blended, RayNormals::Gradient, RayNormals::Pca] {
            let params = RayCastParams {
                normals,
                ..RayCastParams::default()
            };
            let caster =
                Caster::new(Points::uniform(positions, *h), Kernel::Wyvill, &params).unwrap();
            let cpu = cast_cpu(&caster, &camera);
            let (gpu, created) = cast_kept(&caster, &camera);
            if last.is_none() {
                assert!(created > 0, "the first cast made no buffers");
            }
            last = Some((positions, *h, params, camera, gpu.render.image.clone()));
            gpu.render.validate().unwrap();
            let psnr = fluid_surfels::splat::psnr(&cpu.render.image, &gpu.render.image);
            let (c, g) = (cpu.render.covered_pixels(), gpu.render.covered_pixels());
            println!(
                "{name} ({normals:?}): PSNR {psnr:.1} dB, covered CPU {c} GPU {g}, samples CPU {} GPU {}",
                cpu.samples, gpu.samples
            );
            assert!(c > 1000, "{name}: {c} pixels");
            assert!(c.abs_diff(g) <= c / 200, "{name}: covered {c} against {g}");
            assert!(psnr >= 40.0, "{name} ({normals:?}): {psnr:.1} dB");
        }
    }
    // the last case again: nothing created, the same picture (the first case made the buffers)
    let (positions, h, params, camera, image) = last.unwrap();
    let caster = Caster::new(Points::uniform(positions, h), Kernel::Wyvill, &params).unwrap();
    let (again, created) = cast_kept(&caster, &camera);
    assert_eq!(
        created, 0,
        "the kept caster made buffers for the same inputs"
    );
    assert_eq!(again.render.image, image);
    // and the kept buffers (written over by six cases of other sizes) draw what fresh ones do
    let (_, fresh) = cast_both(&ctx, &caster, &camera);
    assert_eq!(again.render.image, fresh.render.image);
    assert_eq!(again.samples, fresh.samples);
}

/// The same on the column splash frame's chain points (50,849 points of radii 0.016-0.05,
/// hundreds per density cell, tens of samples per ray): the case that llvmpipe's loop limit
/// (65,535 loop iterations per invocation, see `shaders/raycast.wgsl`) cut short when the cast
/// was one loop nest (305 of the CPU's 1,467 pixels covered at 96x96); the resumable passes
/// cover the same pixels.
#[test]
fn gpu_and_cpu_ray_casts_agree_on_the_chains_points() {
    use fluid_surfels::pipeline::{self, Pipeline, Renderer, Through};
    let Some(ctx) = fluid_surfels::gpu::context_or_skip("gpu_ray_casts_on_chain_points").unwrap()
    else {
        return;
    };
    let mut sim = scenes::ColumnSim::new(scenes::ColumnParams::default()).unwrap();
    sim.advance_to(scenes::ColumnParams::SPLASH_FRAME);
    let mut params = pipeline::column_params();
    params.renderer = Renderer::RayCast;
    let mut p = Pipeline::new(params).unwrap();
    let frame = p.frame_through(sim.particles(), Through::Surfels).unwrap();
    let (positions, radii) = pipeline::sphere_points(&frame.render_surfels);
    let caster = p.caster(&positions, &radii, &frame.render_weights).unwrap();
    let (lo, hi) = fluid_surfels::splat::bounds(&frame.render_surfels).unwrap();
    let (cpu, gpu) = cast_both(&ctx, &caster, &Camera::framing(lo, hi));
    let (c, g) = (cpu.render.covered_pixels(), gpu.render.covered_pixels());
    let psnr = fluid_surfels::splat::psnr(&cpu.render.image, &gpu.render.image);
    println!("chain points: covered CPU {c} GPU {g}, PSNR {psnr:.1} dB");
    assert!(
        c.abs_diff(g) <= c / 200 && psnr >= 40.0,
        "covered {c} against {g}, {psnr:.1} dB"
    );
}

/// A caster whose weights are on the GPU (`Caster::with_weights_on_gpu`, as `GpuPipeline`'s
/// calibrated spheres) builds no CPU index and casts, from each of two views of one frame (the
/// inputs made once and shared), what the caster with the same weights on the CPU casts on the
/// GPU, bit for bit; the CPU refuses to cast it.
#[test]
fn a_caster_with_its_weights_on_the_gpu_casts_what_the_cpus_does() {
    let Some(ctx) = fluid_surfels::gpu::context_or_skip(
        "a_caster_with_its_weights_on_the_gpu_casts_what_the_cpus_does",
    )
    .unwrap() else {
        return;
    };
    let sphere = jittered_sphere(5.0);
    let (positions, h) = (&sphere.particles.positions, sphere.support_radius);
    // two radius groups and weights that differ from point to point
    let radii: Vec<f32> = (0..positions.len())
        .map(|j| if j % 3 == 0 { 0.6 * h } else { h })
        .collect();
    let weights = varied_weights(positions.len());
    let params = RayCastParams::default();
    let points = Points::with_radii(positions, &radii, h);
    let on_cpu = Caster::new(points.with_weights(&weights), Kernel::Wyvill, &params).unwrap();
    let buffer = weights_buffer(&ctx, &weights);
    let on_gpu = Caster::with_weights_on_gpu(points, Kernel::Wyvill, &params, buffer).unwrap();
    // the groups the GPU's grids index: the two radii, each with its own points (both casters
    // find them through `radius_groups`, so checked against the radii themselves too)
    assert_eq!(on_gpu.groups(), on_cpu.groups());
    let groups = on_gpu.groups();
    assert_eq!(groups.len(), 2);
    for (reach, members) in groups {
        assert!(!members.is_empty());
        assert!(
            members.iter().all(|&j| radii[j as usize] == reach),
            "{reach}"
        );
    }
    assert!(on_gpu.density().is_none() && on_cpu.density().is_some());
    let (lo, hi) = positions
        .iter()
        .fold((Vec3::INFINITY, Vec3::NEG_INFINITY), |(a, b), &q| {
            (a.min(q), b.max(q))
        });
    let near = Camera::framing(lo - h, hi + h);
    let far = Camera {
        eye: near.eye + (near.eye - near.target) * 0.5 + Vec3::X * h,
        ..near
    };
    let (light, splat) = (Light::default(), SplatParams::default());
    // one pass per size, as a frame's camera and light have
    let mut passes = [
        raycast::gpu::GpuCaster::new(&ctx.device, SIZE, SIZE).unwrap(),
        raycast::gpu::GpuCaster::new(&ctx.device, SIZE / 2, SIZE).unwrap(),
    ];
    let mut cast = |k: usize, caster: &Caster<'_>, camera: &Camera| {
        let (w, ht) = passes[k].size();
        let v = View::new(camera, &light, &splat, w, ht).unwrap();
        passes[k]
            .prepare(&ctx.device, &ctx.queue, caster, &v)
            .unwrap();
        let mut encoder = ctx.device.create_command_encoder(&Default::default());
        passes[k].encode(&mut encoder).unwrap();
        ctx.queue.submit([encoder.finish()]);
        passes[k].read(&ctx).unwrap()
    };
    for (k, camera) in [(0, &near), (1, &far)] {
        // the GPU's first, so that its passes hold no weights uploaded before
        let got = cast(k, &on_gpu, camera);
        let expected = cast(k, &on_cpu, camera);
        assert!(expected.render.covered_pixels() > 300, "view {k}");
        assert!(
            got.render.image == expected.render.image,
            "view {k}: {:.1} dB apart",
            fluid_surfels::splat::psnr(&expected.render.image, &got.render.image)
        );
        assert_eq!(got.samples, expected.samples, "view {k}");
    }
    // the CPU has no index to cast it with: refused, not a picture without water
    let v = View::new(&near, &light, &splat, SIZE, SIZE).unwrap();
    let refused = raycast::cpu::render_view_cpu(&on_gpu, &v);
    assert!(
        matches!(
            refused,
            Err(RayCastError::InvalidParameter { name: "caster", .. })
        ),
        "{:?}",
        refused.err()
    );
    let x = positions[0];
    assert!(on_gpu.pca_normal(x).is_none() && raycast::surface_normal(&on_gpu, x).is_none());
}

/// A point whose weight on the GPU is negative (`boundary::gpu::DROPPED`: one the calibration's
/// factors leave out, as `GpuPipeline` draws every particle and sheet point) is not there: the
/// cast with such points added (a copy of every third point half a support radius farther out,
/// which would move the surface, the entries, the thickness and the PCA normals) is the cast
/// without them (measured: the same image; the bound allows for the sums' order, the cells
/// holding the added points too). Seen to fail with either of the shader's skips left out
/// (the tiles' spheres: 55.9 dB; the sums' points: 30.8 dB).
#[test]
fn a_casters_dropped_points_are_not_there() {
    use fluid_surfels::pipeline::boundary::gpu::DROPPED;
    let Some(ctx) =
        fluid_surfels::gpu::context_or_skip("a_casters_dropped_points_are_not_there").unwrap()
    else {
        return;
    };
    let sphere = jittered_sphere(5.0);
    let (positions, h) = (&sphere.particles.positions, sphere.support_radius);
    let centre = positions.iter().copied().sum::<Vec3>() / positions.len() as f32;
    let weights = varied_weights(positions.len());
    let mut more = positions.clone();
    let mut more_weights = weights.clone();
    for (j, &p) in positions.iter().enumerate().step_by(3) {
        more.push(p + (p - centre).normalize_or_zero() * 0.5 * h);
        more_weights.push(if j % 2 == 0 { DROPPED } else { 1.0 });
    }
    let (lo, hi) = widened_box(&more, h);
    let camera = Camera::framing(lo, hi);
    let (light, splat) = (Light::default(), SplatParams::default());
    let cast = |c: &Caster<'_>| {
        raycast::gpu::render_gpu(&ctx, c, &camera, &light, &splat, SIZE, SIZE).unwrap()
    };
    let plain = cast(&gpu_weighed(&ctx, positions, &weights, h));
    // the added points half dropped, half drawn with weight 1: the drawn half's cast differs
    let kept: Vec<Vec3> = more
        .iter()
        .zip(&more_weights)
        .filter(|(_, w)| **w >= 0.0)
        .map(|(p, _)| *p)
        .collect();
    let kept_weights: Vec<f32> = more_weights.iter().copied().filter(|w| *w >= 0.0).collect();
    let expected = cast(&gpu_weighed(&ctx, &kept, &kept_weights, h));
    let got = cast(&gpu_weighed(&ctx, &more, &more_weights, h));
    let db = fluid_surfels::splat::psnr(&expected.render.image, &got.render.image);
    let moved = fluid_surfels::splat::psnr(&plain.render.image, &expected.render.image);
    println!(
        "dropped points: {db:.1} dB from the cast without them ({} and {} pixels); the drawn ones move it {moved:.1} dB",
        got.render.covered_pixels(),
        expected.render.covered_pixels()
    );
    assert!(
        moved < 40.0,
        "the added points should change the cast: {moved:.1} dB"
    );
    assert!(db >= 60.0, "{db:.1} dB");
    assert_eq!(
        got.render.covered_pixels(),
        expected.render.covered_pixels()
    );
}

/// The box of `points` widened by `by`.
fn widened_box(points: &[Vec3], by: f32) -> (Vec3, Vec3) {
    fluid_surfels::view::widened_bounds(points.iter().copied(), by).unwrap()
}

/// The caster of `points` (radius `h`) with `weights` on the GPU of `ctx`.
fn gpu_weighed<'a>(
    ctx: &fluid_surfels::gpu::GpuContext,
    points: &'a [Vec3],
    weights: &[f32],
    h: f32,
) -> Caster<'a> {
    let buffer = weights_buffer(ctx, weights);
    let points = Points::uniform(points, h);
    Caster::with_weights_on_gpu(points, Kernel::Wyvill, &RayCastParams::default(), buffer).unwrap()
}

/// A sphere of particles `radius_in_spacings` spacings in radius, jittered by a tenth of a
/// spacing.
fn jittered_sphere(radius_in_spacings: f32) -> scenes::Scene {
    scenes::sphere(&scenes::SphereParams {
        radius_in_spacings,
        jitter: 0.1,
        ..Default::default()
    })
    .unwrap()
}

/// Weights between 0.7 and 1.3 that differ from point to point, for `n` points.
fn varied_weights(n: usize) -> Vec<f32> {
    (0..n)
        .map(|j| 0.7 + 0.6 * ((j * 37 % 101) as f32 / 100.0))
        .collect()
}

/// A storage buffer of `weights` on the GPU of `ctx`.
fn weights_buffer(ctx: &fluid_surfels::gpu::GpuContext, weights: &[f32]) -> wgpu::Buffer {
    use wgpu::util::DeviceExt;
    ctx.device
        .create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("weights"),
            contents: bytemuck::cast_slice(weights),
            usage: wgpu::BufferUsages::STORAGE,
        })
}
