//! GPU stages against their CPU specification (on lavapipe in CI). Without an adapter these
//! tests skip with a message, unless FLUID_SURFELS_REQUIRE_GPU=1 makes that a failure.

use fluid_surfels::density::gpu::{self as gpu_density, GpuDensityMethod};
use fluid_surfels::density::{self, GridSpec, Kernel, Points, Resolution};
use fluid_surfels::gpu;
use fluid_surfels::pipeline::{self, GpuPipeline, Pipeline, PipelineParams, Through};
use fluid_surfels::scenes;
use fluid_surfels::splat;
use fluid_surfels::splat::gpu as gpu_splat;

/// A shader struct and its Rust twin: file, WGSL source, struct name, Rust size, Rust fields.
type Twin = (
    &'static str,
    &'static str,
    &'static str,
    usize,
    Vec<(&'static str, usize)>,
);

/// `(field, offset)` of a `#[repr(C)]` struct, for comparing with its WGSL twin.
macro_rules! fields {
    ($t:ty; $($f:ident),* $(,)?) => {
        vec![$((stringify!($f), std::mem::offset_of!($t, $f))),*]
    };
}

/// Every shader's uniform struct with its Rust twin (a table: one entry per struct).
#[allow(clippy::too_many_lines)]
fn twins() -> Vec<Twin> {
    use fluid_surfels::optics::gpu::{RawGeometry, RawOptics, RawView};
    use gpu_density::{RawGatherParams, RawParams};
    use gpu_splat::RawUniforms;
    use pipeline::boundary::gpu::{RawSheetPoint, RawWeightParams};
    use pipeline::gpu::RawPresent;
    vec![
        (
            "density_splat.wgsl",
            gpu_density::SHADER,
            "Params",
            std::mem::size_of::<RawParams>(),
            fields!(RawParams; origin, spacing, dims, h, constant, planes, kernel, first_plane, plane_count, first_slab),
        ),
        (
            "surfels.wgsl",
            fluid_surfels::surfels::gpu::SHADER,
            "Surfel",
            std::mem::size_of::<splat::Surfel>(),
            fields!(splat::Surfel; position, radius, normal, stretch, tangent, colour),
        ),
        (
            "density_gather.wgsl",
            gpu_density::GATHER_SHADER,
            "Point",
            std::mem::size_of::<gpu_density::RawPoint>(),
            fields!(gpu_density::RawPoint; at, weight),
        ),
        (
            "surfels.wgsl",
            fluid_surfels::surfels::gpu::SHADER,
            "SurfelParams",
            std::mem::size_of::<fluid_surfels::surfels::gpu::RawSurfelParams>(),
            fields!(fluid_surfels::surfels::gpu::RawSurfelParams; origin, spacing, dims, iso, bin_origin, bin_size, bins, reach, h, constant, kernel, newton_steps, blocks, converged, sparse_block, inside, capacity, leading, rest_radius, colour),
        ),
        (
            "density_gather.wgsl",
            gpu_density::GATHER_SHADER,
            "GatherParams",
            std::mem::size_of::<RawGatherParams>(),
            fields!(RawGatherParams; origin, spacing, dims, k0, bin_origin, bin_size, bins, planes, h, constant, kernel, reach, leading, rest_radius),
        ),
        (
            "surfel_splat.wgsl",
            gpu_splat::SHADER,
            "Uniforms",
            std::mem::size_of::<RawUniforms>(),
            fields!(RawUniforms; view, proj, inv_view, viewport, tan_half, light_dir, light_colour, background, material, depth_offset, low_pass, sharpness, mode),
        ),
        (
            "optics.wgsl",
            fluid_surfels::optics::gpu::SHADER,
            "Uniforms",
            std::mem::size_of::<RawOptics>(),
            fields!(RawOptics; screen, map, camera, light_dir, light_pos, light_colour, ambient, water, extinction, albedo, env, env_colour, env_horizon, env_zenith, env_ground, exact, container_min, container_max),
        ),
        (
            "optics.wgsl",
            fluid_surfels::optics::gpu::SHADER,
            "ViewU",
            std::mem::size_of::<RawView>(),
            fields!(RawView; view, inv_view, proj, viewport, tan_half, flags),
        ),
        (
            "optics_geometry.wgsl",
            fluid_surfels::optics::gpu::GEOMETRY_SHADER,
            "GeometryU",
            std::mem::size_of::<RawGeometry>(),
            fields!(RawGeometry; view_proj, view, eye),
        ),
        (
            "raycast.wgsl",
            fluid_surfels::raycast::gpu::SHADER,
            "Params",
            std::mem::size_of::<fluid_surfels::raycast::gpu::RawCastParams>(),
            fields!(fluid_surfels::raycast::gpu::RawCastParams; inv_view, screen, a, b, c, d, e, g, base, absorb),
        ),
        (
            "raycast.wgsl",
            fluid_surfels::raycast::gpu::SHADER,
            "Grid",
            std::mem::size_of::<fluid_surfels::raycast::gpu::RawGrid>(),
            fields!(fluid_surfels::raycast::gpu::RawGrid; g, dims, at),
        ),
        (
            "raycast.wgsl",
            fluid_surfels::raycast::gpu::SHADER,
            "Grids",
            std::mem::size_of::<fluid_surfels::raycast::gpu::RawGrids>(),
            fields!(fluid_surfels::raycast::gpu::RawGrids; grid),
        ),
        (
            "raycast.wgsl",
            fluid_surfels::raycast::gpu::SHADER,
            "Band",
            std::mem::size_of::<fluid_surfels::raycast::gpu::RawBand>(),
            fields!(fluid_surfels::raycast::gpu::RawBand; y0, rows, budget, groups_x, groups_y),
        ),
        (
            "lnm.wgsl",
            fluid_surfels::lnm::gpu::SHADER,
            "Params",
            std::mem::size_of::<fluid_surfels::lnm::gpu::RawLnmParams>(),
            fields!(fluid_surfels::lnm::gpu::RawLnmParams; lo, dims, misc),
        ),
        (
            "sparse_layout.wgsl",
            density::sparse_gpu::SHADER,
            "LayoutParams",
            std::mem::size_of::<density::sparse_gpu::RawLayoutParams>(),
            fields!(density::sparse_gpu::RawLayoutParams; origin, spacing, dims, count, blocks, total, band_lo, band_inv, band_dims, capacity, bin_origin, bin_inv, bins, reach, margin),
        ),
        (
            "ssfr.wgsl",
            fluid_surfels::ssfr::gpu::SHADER,
            "Params",
            std::mem::size_of::<fluid_surfels::ssfr::gpu::RawSsfrParams>(),
            fields!(fluid_surfels::ssfr::gpu::RawSsfrParams; inv_view, screen, a, b, c, base, absorb),
        ),
        (
            "ssfr_band.wgsl",
            fluid_surfels::ssfr::gpu::BAND_SHADER,
            "SsfrBand",
            std::mem::size_of::<fluid_surfels::ssfr::gpu::RawSsfrBand>(),
            fields!(fluid_surfels::ssfr::gpu::RawSsfrBand; a, b, view, proj, screen),
        ),
        (
            "present.wgsl",
            pipeline::gpu::PRESENT_SHADER,
            "Present",
            std::mem::size_of::<RawPresent>(),
            fields!(RawPresent; width, height, srgb_target),
        ),
        (
            "boundary_weights.wgsl",
            pipeline::boundary::gpu::SHADER,
            "WeightParams",
            std::mem::size_of::<RawWeightParams>(),
            fields!(RawWeightParams; bin_origin, bin_size, bins, reach, constant, kernel, particles, count, half_spacing, tau, lone_r2, max_weight, buried, band, leading, sheet_radius),
        ),
        (
            "boundary_weights.wgsl",
            pipeline::boundary::gpu::SHADER,
            "SheetPoint",
            std::mem::size_of::<RawSheetPoint>(),
            fields!(RawSheetPoint; at, normal),
        ),
        (
            "bin_sort.wgsl",
            density::bins::SHADER,
            "SortParams",
            std::mem::size_of::<density::bins::RawSortParams>(),
            fields!(density::bins::RawSortParams; origin, inv_size, bins, count, shift, groups, entries),
        ),
        (
            "tiles.wgsl",
            fluid_surfels::view::gpu::SHADER,
            "TileParams",
            std::mem::size_of::<fluid_surfels::view::gpu::RawTileParams>(),
            fields!(fluid_surfels::view::gpu::RawTileParams; view, proj, size, tiles, count, capacity, sentinel, stride),
        ),
    ]
}

/// Every uniform struct of every shader against its Rust twin, reflected with naga: the struct's
/// size, and each field's offset by name (every WGSL field but padding must exist in Rust at the
/// same offset). Moving a field in a Rust struct fails here (shown once by hand: swapping
/// `spacing` and `h` in `RawParams` gave "density_splat.wgsl: Params.spacing at offset 12 in
/// WGSL, 24 in Rust").
#[test]
fn shaders_validate_and_their_structs_match_the_rust_mirrors() {
    let shaders = twins();
    for (file, source, name, rust_size, rust_fields) in shaders {
        let module = naga::front::wgsl::parse_str(source)
            .unwrap_or_else(|e| panic!("{file}: {}", e.emit_to_string(source)));
        naga::valid::Validator::new(
            naga::valid::ValidationFlags::all(),
            naga::valid::Capabilities::all(),
        )
        .validate(&module)
        .unwrap_or_else(|e| panic!("{file} does not validate: {e:?}"));
        let ty = module
            .types
            .iter()
            .find(|(_, t)| t.name.as_deref() == Some(name))
            .map(|(_, t)| t)
            .unwrap_or_else(|| panic!("{file}: no struct {name}"));
        let size = ty.inner.size(module.to_ctx());
        assert_eq!(
            size as usize, rust_size,
            "{file}: {name} and its Rust mirror differ in size"
        );
        let naga::TypeInner::Struct { members, .. } = &ty.inner else {
            panic!("{file}: {name} is not a struct");
        };
        let mut checked = 0;
        for m in members {
            let Some(field) = m.name.as_deref() else {
                continue;
            };
            if field.starts_with('_') {
                continue;
            }
            let rust = rust_fields
                .iter()
                .find(|(f, _)| *f == field)
                .unwrap_or_else(|| panic!("{file}: {name}.{field} has no Rust twin field"))
                .1;
            assert_eq!(
                m.offset as usize, rust,
                "{file}: {name}.{field} at offset {} in WGSL, {rust} in Rust",
                m.offset
            );
            checked += 1;
        }
        assert_eq!(
            checked,
            rust_fields.len(),
            "{file}: {name}: some Rust fields have no WGSL twin"
        );
    }
    // the surfel vertex layout: four vec4 attributes
    assert_eq!(std::mem::size_of::<splat::Surfel>(), 64);
}

/// Checks a GPU density grid against the CPU's: the largest difference within 1e-4 of the
/// CPU's peak, the first failing grid point named. Prints the figure under `label`.
fn assert_grids_agree(label: &str, cpu: &density::DensityGrid, gpu: &density::DensityGrid) {
    assert_eq!(gpu.values.len(), cpu.values.len(), "{label}: grid sizes");
    let max = cpu.max();
    let (worst, at) = cpu
        .values
        .iter()
        .zip(&gpu.values)
        .enumerate()
        .map(|(i, (a, b))| ((a - b).abs(), i))
        .fold((0.0f32, 0), |m, x| if x.0 > m.0 { x } else { m });
    println!(
        "{label}: grid {:?}, max density {max}, largest GPU-CPU difference {worst:e} ({:e} of the max) at {at}",
        cpu.spec.dims,
        worst / max
    );
    assert!(
        worst <= 1e-4 * max,
        "{label}: {worst} at {at} (cpu {}, gpu {})",
        cpu.values[at],
        gpu.values[at]
    );
}

/// The design chain's points (interior particles with the support radius, a fine sheet of
/// refined points with a quarter of it): both GPU methods equal the CPU path, per-point radii
/// and all.
#[test]
fn gpu_density_with_a_radius_per_point_matches_the_cpu_path() {
    let Some(ctx) =
        gpu::context_or_skip("gpu_density_with_a_radius_per_point_matches_the_cpu_path").unwrap()
    else {
        return;
    };
    let (points, radii, h) = chain_like_points();
    for kernel in [Kernel::Wyvill, Kernel::CubicSpline] {
        let pts = Points::with_radii(&points, &radii, h);
        let spec =
            GridSpec::around(&points, h, Resolution::CellSize(pts.min_radius() / 3.0)).unwrap();
        let cpu = density::points_grid(pts, &spec, kernel, 1 << 30).unwrap();
        let naive = density::points_naive(pts, &spec, kernel).unwrap();
        assert_eq!(
            cpu.values, naive.values,
            "{kernel:?}: CPU slabs and naive differ"
        );
        for method in [GpuDensityMethod::Splat, GpuDensityMethod::Gather] {
            let gpu = gpu_density::density_grid_gpu_with(&ctx, pts, &spec, kernel, method).unwrap();
            assert_grids_agree(
                &format!("per-point radii, {kernel:?}, {method:?}"),
                &cpu,
                &gpu,
            );
        }
        // weights (the chain's boundary weights): summed by both methods, and by the grid
        // that stays on the GPU (GridFiller, either method: the splatting's groups of planes
        // unpacked into the grid's buffer)
        let weights: Vec<f32> = points
            .iter()
            .map(|p| 1.0 + 0.5 * (13.0 * p.x - 7.0 * p.y).sin())
            .collect();
        let weighted = pts.with_weights(&weights);
        let cpu = density::points_grid(weighted, &spec, kernel, 1 << 30).unwrap();
        for method in [GpuDensityMethod::Splat, GpuDensityMethod::Gather] {
            let gpu =
                gpu_density::density_grid_gpu_with(&ctx, weighted, &spec, kernel, method).unwrap();
            assert_grids_agree(&format!("weights, {kernel:?}, {method:?}"), &cpu, &gpu);
            let mut filler = gpu_density::GridFiller::with_method(&ctx.device, method);
            assert_eq!(filler.method(), method);
            let mut encoder = ctx.device.create_command_encoder(&Default::default());
            let grid = filler
                .record(&ctx, &mut encoder, weighted, &spec, kernel)
                .unwrap();
            ctx.queue.submit([encoder.finish()]);
            let resident = grid.read(&ctx).unwrap();
            assert_grids_agree(
                &format!("weights, {kernel:?}, {method:?} on the GPU"),
                &cpu,
                &resident,
            );
        }
    }
}

/// A jittered block of particles (radius h) under a sheet of points at a quarter of the spacing
/// (radius h / 4), like the chain's interior and refined surface.
fn chain_like_points() -> (Vec<glam::Vec3>, Vec<f32>, f32) {
    let scene = scenes::block(&scenes::BlockParams {
        counts: [6, 3, 5],
        ..Default::default()
    })
    .unwrap();
    let s = scene.spacing;
    let h = 2.0 * s;
    let mut points = scene.particles.positions.clone();
    let mut radii = vec![h; points.len()];
    let top = points.iter().fold(f32::MIN, |m, p| m.max(p.y)) + 0.5 * s;
    for i in 0..24 {
        for k in 0..20 {
            points.push(glam::Vec3::new(
                i as f32 * 0.25 * s,
                top,
                k as f32 * 0.25 * s,
            ));
            radii.push(0.25 * h);
        }
    }
    (points, radii, h)
}

#[test]
fn gpu_density_matches_the_cpu_path() {
    let Some(ctx) = gpu::context_or_skip("gpu_density_matches_the_cpu_path").unwrap() else {
        return;
    };
    let scene = scenes::block(&scenes::BlockParams {
        counts: [14, 9, 11],
        ..Default::default()
    })
    .unwrap();
    let p = &scene.particles.positions;
    let h = 2.0 * scene.spacing;
    let methods = [GpuDensityMethod::Splat, GpuDensityMethod::Gather];
    for (kernel, method) in [Kernel::Wyvill, Kernel::CubicSpline]
        .into_iter()
        .flat_map(|k| methods.map(|m| (k, m)))
    {
        // a grid whose plane count is not a multiple of 4 and whose rows are not 256-byte aligned
        let spec = GridSpec::around(p, h, Resolution::LongestAxis(45)).unwrap();
        let cpu = density::density_grid(p, &spec, kernel, h, 1 << 30).unwrap();
        let gpu =
            gpu_density::density_grid_gpu_with(&ctx, Points::uniform(p, h), &spec, kernel, method)
                .unwrap();
        assert_grids_agree(&format!("{kernel:?}, {method:?}"), &cpu, &gpu);
    }
    // an empty set gives an empty grid, no error
    let spec = GridSpec::around(p, h, Resolution::LongestAxis(8)).unwrap();
    for method in methods {
        let empty = gpu_density::density_grid_gpu_with(
            &ctx,
            Points::uniform(&[], h),
            &spec,
            Kernel::Wyvill,
            method,
        )
        .unwrap();
        assert_eq!(empty.values.len() as u128, spec.cells());
        assert!(empty.values.iter().all(|&v| v == 0.0));
    }
    // particles outside the grid's box (within h and far away) are binned at its edges
    let mut outside = p.clone();
    outside.push(glam::Vec3::splat(-50.0));
    outside.push(spec.origin - glam::Vec3::splat(0.5 * h));
    let small = GridSpec::for_box(
        spec.origin,
        spec.origin + glam::Vec3::splat(6.0 * h),
        Resolution::LongestAxis(20),
    )
    .unwrap();
    let cpu = density::density_grid(&outside, &small, Kernel::Wyvill, h, 1 << 30).unwrap();
    let gather = gpu_density::density_grid_gpu_with(
        &ctx,
        Points::uniform(&outside, h),
        &small,
        Kernel::Wyvill,
        GpuDensityMethod::Gather,
    )
    .unwrap();
    let worst = cpu
        .values
        .iter()
        .zip(&gather.values)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    assert!(
        worst <= 1e-4 * cpu.max(),
        "gather with particles outside the box: {worst}"
    );
}

/// The column simulation and the pipeline settings of its pool, for images of `size`.
fn column_setup(size: (u32, u32)) -> (scenes::ColumnSim, PipelineParams) {
    let sim = scenes::ColumnSim::new(scenes::ColumnParams::default()).unwrap();
    let mut params = PipelineParams {
        support_radius: Some(sim.support_radius()),
        scene: scenes::column_pool(scenes::ColumnParams::default().tank),
        ..Default::default()
    };
    params.scene.optics.image_size = [size.0, size.1];
    // a small virtual screen and caustics map: at the defaults (256 and 512 texels) the caustics
    // cost lavapipe 1.7 s of each frame whatever the image size, and what these tests compare
    // (CPU and GPU, frames and resources) does not depend on them; the one test of the optics
    // at their defaults (`gpu_pipeline_equals_the_gpu_optics_and_the_cpu_pipeline`) sets them
    // back
    params.scene.optics.caustics_resolution = Some([64, 64]);
    params.scene.optics.map_resolution = Some([128, 128]);
    (sim, params)
}

/// The chain on the GPU (`GpuPipeline`, drawing into a texture as a game would) against the
/// optics stage's own GPU read-back (the same computation: must agree to the 8-bit rounding) and
/// against the CPU `Pipeline` (the finished frame of the column's splash frame): at least 35 dB,
/// as the pipeline issue asks. Measured on lavapipe: 60.4-63.6 dB over runs (Unorm target;
/// 53.7-54.2 dB on an sRGB target), 63-69 dB on the pixels away from the water. Before the GPU met small receivers with
/// exact rays it measured 27.0 dB: the paper's geometry-map search (§5.1.2) missed a third of the
/// refracted rays of this frame (those of the water the walls shade, which the CPU then wrongly
/// lit) and put 15 % of the hits it found more than 1 cm off.
#[test]
fn gpu_pipeline_equals_the_gpu_optics_and_the_cpu_pipeline() {
    let Some(ctx) = gpu::context_or_skip("gpu_pipeline").unwrap() else {
        return;
    };
    let size = (160, 160);
    let (mut sim, mut params) = column_setup(size);
    // the optics at their defaults
    params.scene.optics.caustics_resolution = None;
    params.scene.optics.map_resolution = None;
    let mut cpu = Pipeline::new(params.clone()).unwrap();
    let frame = pipeline::column_frame(
        &mut cpu,
        &mut sim,
        scenes::ColumnParams::SPLASH_FRAME,
        Through::Frame,
        |_| {},
    )
    .unwrap();
    let finished = frame.finished.as_ref().unwrap();
    let cpu_image = &finished.image;
    let (optics, _) = fluid_surfels::optics::gpu::render_gpu(
        &ctx,
        &finished.stage,
        &frame.render_surfels,
        Some(size),
    )
    .unwrap();
    let (optics_image, _) = optics.frame.unwrap();
    // pixels whose 5x5 neighbourhood has no water in the CPU frame
    let (w, h) = (size.0 as i32, size.1 as i32);
    let wet = |x: i32, y: i32| finished.linear[(y * w + x) as usize][3] > 0.0;
    let dry: Vec<bool> = (0..w * h)
        .map(|i| {
            let (x, y) = (i % w, i / w);
            !(-2..=2).any(|dy| {
                (-2..=2).any(|dx| {
                    let (u, v) = (x + dx, y + dy);
                    u >= 0 && v >= 0 && u < w && v < h && wet(u, v)
                })
            })
        })
        .collect();
    let dry_psnr = |a: &image::RgbaImage, b: &image::RgbaImage| {
        let (mut sum, mut n) = (0.0f64, 0usize);
        for (i, (p, q)) in a.pixels().zip(b.pixels()).enumerate() {
            if dry[i] {
                for c in 0..3 {
                    sum += (p[c] as f64 - q[c] as f64).powi(2);
                }
                n += 3;
            }
        }
        let mse = sum / n.max(1) as f64;
        if mse == 0.0 {
            f64::INFINITY
        } else {
            10.0 * (255.0f64 * 255.0 / mse).log10()
        }
    };
    for format in [
        wgpu::TextureFormat::Rgba8Unorm,
        wgpu::TextureFormat::Rgba8UnormSrgb,
    ] {
        let mut gpu = GpuPipeline::new(&ctx.device, &ctx.queue, format, size, &params).unwrap();
        let image = gpu.render_frame_image(&ctx, &frame).unwrap();
        let same = splat::psnr(&optics_image, &image);
        let db = splat::psnr(cpu_image, &image);
        let dry_db = dry_psnr(cpu_image, &image);
        println!(
            "GpuPipeline ({format:?}), column splash frame {}x{}: {same:.1} dB against the optics stage's read-back; against the CPU Pipeline {db:.1} dB, {dry_db:.1} dB on the {} dry pixels",
            size.0,
            size.1,
            dry.iter().filter(|d| **d).count()
        );
        if same < 50.0 || db < 35.0 || dry_db < 45.0 {
            let dir = std::env::temp_dir();
            cpu_image
                .save(dir.join("gpu_pipeline-expected.png"))
                .unwrap();
            image.save(dir.join("gpu_pipeline-actual.png")).unwrap();
            splat::difference_image(cpu_image, &image, 8)
                .save(dir.join("gpu_pipeline-difference.png"))
                .unwrap();
        }
        assert!(
            same >= 50.0,
            "{format:?}: {same:.1} dB against the optics read-back"
        );
        assert!(dry_db >= 45.0, "{format:?}: dry pixels {dry_db:.1} dB");
        assert!(db >= 35.0, "{format:?}: {db:.1} dB against the CPU");
    }
    // the other picture: the shaded splats, from the same kept camera
    let cpu_splats = cpu
        .frame_of_surfels(frame.render_surfels.clone(), Through::Splats)
        .unwrap();
    let cpu_splats = &cpu_splats.splats.as_ref().unwrap().image;
    let format = wgpu::TextureFormat::Rgba8Unorm;
    let mut gpu = GpuPipeline::new(&ctx.device, &ctx.queue, format, size, &params).unwrap();
    let _ = gpu.render_frame_image(&ctx, &frame).unwrap();
    let splats = splats_image(&ctx, &mut gpu, &frame, size, format);
    let db = splat::psnr(cpu_splats, &splats);
    println!("GpuPipeline shaded splats against the CPU Pipeline's: {db:.1} dB");
    assert!(db >= 35.0, "shaded splats: {db:.1} dB");
}

/// `GpuPipeline` with the peer renderers equals the CPU `Pipeline`: particle splatting and ray
/// casting (the light's and the camera's views cast on the GPU for the optics; the shaded image
/// cast and shaded by the splats' shading pass), on the column splash frame; one `GpuPipeline`
/// switched from one renderer to the other prepares anew and draws what a fresh one draws.
#[test]
fn gpu_pipeline_with_the_peer_renderers_equals_the_cpu_pipeline() {
    let Some(ctx) = gpu::context_or_skip("gpu_pipeline_peer_renderers").unwrap() else {
        return;
    };
    let size = (128, 128);
    let format = wgpu::TextureFormat::Rgba8Unorm;
    let mut switched: Option<GpuPipeline> = None;
    for renderer in [
        pipeline::Renderer::ParticleSplat,
        pipeline::Renderer::RayCast,
        pipeline::Renderer::Ssfr,
    ] {
        let (mut sim, mut params) = column_setup(size);
        params.renderer = renderer;
        // the raw particles for the ray caster, to keep the test short on lavapipe (the chain's
        // points are tests/raycast.rs's)
        if renderer == pipeline::Renderer::RayCast {
            params.source = pipeline::SurfelSource::Particles;
        }
        let mut cpu = Pipeline::new(params.clone()).unwrap();
        let frame = pipeline::column_frame(
            &mut cpu,
            &mut sim,
            scenes::ColumnParams::SPLASH_FRAME,
            Through::Frame,
            |_| {},
        )
        .unwrap();
        assert!(frame.grid.is_none(), "{renderer:?} needs no grid");
        let mut gpu = GpuPipeline::new(&ctx.device, &ctx.queue, format, size, &params).unwrap();
        let image = gpu.render_frame_image(&ctx, &frame).unwrap();
        // the steady state: the second frame rewrites the renderer's inputs (the spheres, the
        // screen-space tiles) into the kept buffers, creating nothing, and draws the same
        // picture (the ray caster's kept buffers are tests/raycast.rs's: a second cast here
        // costs lavapipe 20 s)
        if renderer != pipeline::Renderer::RayCast {
            let again = gpu.render_frame_image(&ctx, &frame).unwrap();
            assert!(gpu.reused_resources(), "{renderer:?}: resources not reused");
            assert_eq!(again, image, "{renderer:?}: the reused frame differs");
        }
        let cpu_image = &frame.finished.as_ref().unwrap().image;
        let db = splat::psnr(cpu_image, &image);
        // the CPU's shaded picture of the frame's spheres and their weights (the ray caster's
        // density: the boundary calibration's weights) from the camera the sequence keeps
        let camera = cpu.camera().unwrap();
        let cpu_splats = cpu
            .draw(
                (&frame.render_surfels, &frame.render_weights),
                &camera,
                size,
            )
            .unwrap();
        let cpu_splats = &cpu_splats.image;
        let splats = splats_image(&ctx, &mut gpu, &frame, size, format);
        let splats_db = splat::psnr(cpu_splats, &splats);
        // both pictures from one build of the renderer's water: the same two images
        let both = gpu::texture_2d(
            &ctx.device,
            "both",
            size,
            format,
            wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC,
        );
        let mut encoder = ctx.device.create_command_encoder(&Default::default());
        gpu.prepare_frame_and_splats(
            &ctx.device,
            &ctx.queue,
            &mut encoder,
            &frame,
            &both.create_view(&Default::default()),
        )
        .unwrap();
        let finished = gpu.draw_to_texture(&ctx.device, &mut encoder);
        ctx.queue.submit([encoder.finish()]);
        assert_eq!(
            gpu::read_rgba8(&ctx, &both).unwrap(),
            splats,
            "{renderer:?}"
        );
        assert_eq!(
            gpu::read_rgba8(&ctx, &finished).unwrap(),
            image,
            "{renderer:?}"
        );
        // the pipeline of the previous renderer, switched to this one
        let switched_db = switched.as_mut().map(|g| {
            g.cpu_mut().set_renderer(renderer);
            g.cpu_mut().set_source(params.source);
            // forget the kept camera and pool, fitted to the other renderer's first frame
            g.cpu_mut().reset();
            splat::psnr(&image, &g.render_frame_image(&ctx, &frame).unwrap())
        });
        println!(
            "{renderer:?}, column splash frame {}x{}: GpuPipeline against the CPU Pipeline {db:.1} dB (finished frame), {splats_db:.1} dB (shaded image); switched to it, against a fresh one: {switched_db:?} dB",
            size.0, size.1
        );
        if db < 35.0 {
            let dir = std::env::temp_dir();
            cpu_image
                .save(dir.join(format!("gpu_pipeline_{renderer:?}-expected.png")))
                .unwrap();
            image
                .save(dir.join(format!("gpu_pipeline_{renderer:?}-actual.png")))
                .unwrap();
        }
        assert!(db >= 35.0, "{renderer:?} finished frame: {db:.1} dB");
        assert!(
            splats_db >= 40.0,
            "{renderer:?} shaded image: {splats_db:.1} dB"
        );
        if let Some(d) = switched_db {
            assert!(
                d >= 60.0,
                "switched to {renderer:?}: {d:.1} dB against a fresh one"
            );
        }
        switched = Some(gpu);
    }
}

/// In a sequence `GpuPipeline` reuses its GPU resources (nothing created after the first frame:
/// uniforms, receiver and surfels are written through the queue) and the reused resources give
/// the image a fresh preparation of the same stage gives.
#[test]
fn gpu_pipeline_reuses_its_resources_across_a_sequence() {
    let Some(ctx) = gpu::context_or_skip("gpu_pipeline_reuses_its_resources").unwrap() else {
        return;
    };
    let size = (96, 96);
    let (mut sim, params) = column_setup(size);
    let mut cpu = Pipeline::new(params.clone()).unwrap();
    let mut gpu = unorm_pipeline(&ctx, size, &params);
    let mut reused = Vec::new();
    let mut last = None;
    for f in 10..=13 {
        let frame = pipeline::column_frame(&mut cpu, &mut sim, f, Through::Frame, |_| {}).unwrap();
        let image = gpu.render_frame_image(&ctx, &frame).unwrap();
        reused.push(gpu.reused_resources());
        last = Some((frame, image));
    }
    println!("resources reused per frame: {reused:?}");
    assert_eq!(reused, [false, true, true, true]);
    let (frame, image) = last.unwrap();
    let finished = frame.finished.as_ref().unwrap();
    let (fresh, _) = fluid_surfels::optics::gpu::render_gpu(
        &ctx,
        &finished.stage,
        &frame.render_surfels,
        Some(size),
    )
    .unwrap();
    let db = splat::psnr(&fresh.frame.unwrap().0, &image);
    println!("frame 13, reused resources against a fresh preparation: {db:.1} dB");
    assert!(db.is_infinite(), "{db:.1} dB");
}

/// Stage 3 with the grid on the GPU (`pipeline::iso_surfels_gpu`, `surfels --gpu`) against the
/// CPU's `pipeline::iso_surfels`: the same grid, the same number of surfels within 1 %, each
/// GPU surfel within 1e-3 spacings of a CPU one; over the memory budget both coarsen the grid
/// alike and say so; no point gives no surfels.
#[test]
fn gpu_iso_surfels_match_the_cpu_stage() {
    use fluid_surfels::pipeline::{GridParams, iso_surfels, iso_surfels_gpu};
    use fluid_surfels::surfels::SurfelParams;
    let Some(ctx) = gpu::context_or_skip("gpu_iso_surfels_match_the_cpu_stage").unwrap() else {
        return;
    };
    let scene = scenes::sphere(&scenes::SphereParams::default()).unwrap();
    let p = &scene.particles.positions;
    let h = scene.support_radius;
    let params = SurfelParams::default();
    for budget in [1 << 30, 1 << 18] {
        let grid = GridParams {
            memory_budget: budget,
            ..GridParams::default()
        };
        let cpu = iso_surfels(Points::uniform(p, h), &grid, &params)
            .unwrap()
            .unwrap();
        let gpu = iso_surfels_gpu(&ctx, Points::uniform(p, h), &grid, &params)
            .unwrap()
            .unwrap();
        assert_eq!(cpu.grid.spec(), gpu.grid.spec(), "budget {budget}");
        assert_eq!(cpu.warning.is_some(), budget < 1 << 20, "{:?}", cpu.warning);
        assert_eq!(cpu.warning, gpu.warning);
        let (c, g) = (&cpu.surfels.positions, &gpu.surfels.positions);
        assert!(
            (c.len() as f32 - g.len() as f32).abs() <= 0.01 * c.len() as f32,
            "{} CPU against {} GPU surfels",
            c.len(),
            g.len()
        );
        let tolerance = 1e-3 * scene.spacing;
        for (i, q) in g.iter().enumerate() {
            let nearest = c
                .iter()
                .map(|x| x.distance(*q))
                .fold(f32::INFINITY, f32::min);
            assert!(
                nearest <= tolerance,
                "GPU surfel {i} is {nearest} from the CPU's"
            );
        }
    }
    let none = iso_surfels_gpu(
        &ctx,
        Points::uniform(&[], h),
        &GridParams::default(),
        &params,
    );
    assert!(none.unwrap().is_none());
}

/// `Pipeline::draw` is the shaded splats of `Through::Splats` (the same picture, bit for bit, for
/// every renderer), and `Pipeline::draw_gpu` its GPU twin (every renderer within 45 dB; the
/// renderers' own tests hold them tighter): the one render entry `render` calls.
#[test]
fn pipeline_draw_is_the_shaded_splats_on_either_backend() {
    use fluid_surfels::pipeline::Renderer;
    let Some(ctx) = gpu::context_or_skip("pipeline_draw").unwrap() else {
        return;
    };
    let scene = scenes::sphere(&scenes::SphereParams::default()).unwrap();
    for renderer in Renderer::ALL {
        let mut params = PipelineParams {
            support_radius: Some(scene.support_radius),
            renderer,
            ..Default::default()
        };
        params.scene.optics.image_size = [96, 72];
        let mut pipeline = Pipeline::new(params).unwrap();
        let frame = pipeline
            .frame_through(&scene.particles, Through::Splats)
            .unwrap();
        let camera = frame.camera.unwrap();
        let cpu = pipeline
            .draw(
                (&frame.render_surfels, &frame.render_weights),
                &camera,
                (96, 72),
            )
            .unwrap();
        assert_eq!(
            cpu.image,
            frame.splats.as_ref().unwrap().image,
            "{renderer:?}"
        );
        let gpu = pipeline
            .draw_gpu(
                &ctx,
                (&frame.render_surfels, &frame.render_weights),
                &camera,
                (96, 72),
            )
            .unwrap();
        let db = splat::psnr(&cpu.image, &gpu.image);
        assert!(db >= 45.0, "{renderer:?}: GPU {db:.1} dB from the CPU");
        assert!(cpu.covered_pixels() > 500, "{renderer:?}");
    }
}

/// The shaded splats `GpuPipeline::encode_splats` draws of `frame` into a texture of `size`
/// and `format`, read back.
fn splats_image(
    ctx: &gpu::GpuContext,
    gpu: &mut GpuPipeline,
    frame: &pipeline::Frame,
    size: (u32, u32),
    format: wgpu::TextureFormat,
) -> image::RgbaImage {
    let target = gpu::texture_2d(
        &ctx.device,
        "splats",
        size,
        format,
        wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC,
    );
    let view = target.create_view(&Default::default());
    let mut encoder = ctx.device.create_command_encoder(&Default::default());
    gpu.encode_splats(&ctx.device, &ctx.queue, &mut encoder, frame, &view)
        .unwrap();
    ctx.queue.submit([encoder.finish()]);
    gpu::read_rgba8(ctx, &target).unwrap()
}

/// The double dam break's particles (a real file).
fn double_dam_break() -> Vec<glam::Vec3> {
    fluid_surfels::io::read_particles(
        &std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("tests/data/double_dam_break_frame_26_4732_particles.vtk"),
        None,
    )
    .unwrap()
    .positions
}

/// The mean of `points` (the middle the tiles tests' cameras look at).
fn mean(points: &[glam::Vec3]) -> glam::Vec3 {
    points.iter().copied().sum::<glam::Vec3>() / points.len() as f32
}

/// A `GpuPipeline` drawing `size` frames into `Rgba8Unorm` targets.
fn unorm_pipeline(ctx: &gpu::GpuContext, size: (u32, u32), params: &PipelineParams) -> GpuPipeline {
    GpuPipeline::new(
        &ctx.device,
        &ctx.queue,
        wgpu::TextureFormat::Rgba8Unorm,
        size,
        params,
    )
    .unwrap()
}

/// The column scene's splash frame.
fn column_splash() -> scenes::Scene {
    scenes::build(
        scenes::SceneName::Column,
        Some(fluid_surfels::scenes::ColumnParams::SPLASH_FRAME),
    )
    .unwrap()
}

/// How far each GPU surfel lies from the nearest CPU surfel, in cells of `spacing`, and the
/// angle between their normals, in degrees: the worst of each (surfels made from grids that
/// differ by rounding need not come in the same order).
fn nearest_cpu_surfels(
    cpu: &fluid_surfels::surfels::Surfels,
    gpu: &fluid_surfels::surfels::Surfels,
    spacing: f32,
) -> (f32, f32) {
    let near = fluid_surfels::neighbours::CellGrid::new(&cpu.positions, spacing).unwrap();
    let (mut worst_d, mut worst_a) = (0.0f32, 0.0f32);
    for (p, n) in gpu.positions.iter().zip(&gpu.normals) {
        let mut best = (f32::INFINITY, None);
        near.for_each_within(*p, spacing, |j| {
            let d = cpu.positions[j as usize].distance(*p);
            if d < best.0 {
                best = (d, Some(j as usize));
            }
        });
        worst_d = worst_d.max(best.0 / spacing);
        if let Some(j) = best.1 {
            let a = cpu.normals[j].angle_between(*n).to_degrees();
            worst_a = worst_a.max(if a.is_nan() { 0.0 } else { a });
        }
    }
    (worst_d, worst_a)
}

/// The GPU surfels (issue 37, first part) against the CPU's, on the same grid: the double dam
/// break (Wyvill, the paper's kernel), the column's splash frame (the cubic spline) and points
/// with a radius each and with weights too (the chain's case), on the dense and the sparse grid: the same count, and
/// surfel by surfel (the same order) positions within 1e-3 of a cell and normals within 1
/// degree.
#[test]
fn gpu_surfels_equal_the_cpus() {
    use fluid_surfels::density::{GridSpec, Kernel, Resolution};
    use fluid_surfels::surfels::{self, SurfelParams};
    let Some(ctx) = gpu::context_or_skip("gpu_surfels_equal_the_cpus").unwrap() else {
        return;
    };
    let (ddb, column) = (double_dam_break(), column_splash());
    let h_ddb = fluid_surfels::neighbours::support_radius(&ddb).unwrap();
    // radii from 0.7 h to 1.3 h, by position, so that they do not follow the order
    let radii: Vec<f32> = ddb
        .iter()
        .map(|p| h_ddb * (1.0 + 0.3 * (37.0 * p.x + 11.0 * p.z).sin()))
        .collect();
    // weights from 0.5 to 1.5, as the boundary calibration's
    let weights: Vec<f32> = ddb
        .iter()
        .map(|p| 1.0 + 0.5 * (23.0 * p.y - 5.0 * p.x).sin())
        .collect();
    let cases = [
        (
            "double dam break",
            Points::uniform(&ddb, h_ddb),
            Kernel::Wyvill,
        ),
        (
            "column splash",
            Points::uniform(&column.particles.positions, column.support_radius),
            Kernel::CubicSpline,
        ),
        (
            "radius per point",
            Points::with_radii(&ddb, &radii, h_ddb),
            Kernel::Wyvill,
        ),
        (
            "weights",
            Points::with_radii(&ddb, &radii, h_ddb).with_weights(&weights),
            Kernel::CubicSpline,
        ),
    ];
    let params = SurfelParams::default();
    let passes = surfels::gpu::SurfelPasses::new(&ctx.device);
    for (name, points, kernel) in cases {
        // the default grid: three cells per (smallest) radius
        let cell = points.min_radius() / 3.0;
        let spec = GridSpec::around(
            points.positions,
            points.max_radius(),
            Resolution::CellSize(cell),
        )
        .unwrap();
        let grid = fluid_surfels::density::points_grid(points, &spec, kernel, 1 << 30).unwrap();
        let cpu = surfels::extract_points(&grid, points, kernel, &params).unwrap();
        let gpu = passes
            .extract(&ctx, &grid, points, kernel, &params)
            .unwrap();
        // the sparse grid: only the blocks near the surface, the same surfels in the same order
        let band = fluid_surfels::lnm::narrow_band(
            points.positions,
            points.max_radius(),
            &Default::default(),
        )
        .unwrap();
        let level = params.iso_fraction * kernel.peak(points.h);
        let sparse = fluid_surfels::density::points_grid_sparse(
            points,
            &spec,
            kernel,
            1 << 30,
            &band,
            level,
            2.0 * level,
        )
        .unwrap();
        let cpu_sparse = surfels::extract_sparse(&sparse, points, kernel, &params).unwrap();
        let gpu_sparse = passes
            .extract(&ctx, &sparse, points, kernel, &params)
            .unwrap();
        assert_eq!(
            cpu_sparse.len(),
            cpu.len(),
            "{name}: the CPU's sparse surfels"
        );
        assert_eq!(
            gpu_sparse.len(),
            cpu.len(),
            "{name}: the GPU's sparse surfels"
        );
        let (_, _, evaluated) = sparse.counts();
        println!("  sparse: {evaluated} blocks evaluated");
        println!(
            "{name}: {} CPU, {} GPU surfels on {:?}",
            cpu.len(),
            gpu.len(),
            spec.dims
        );
        assert!(cpu.len() > 1000, "{name}: {} surfels", cpu.len());
        assert_eq!(cpu.len(), gpu.len(), "{name}");
        assert_eq!(cpu.radii, gpu.radii, "{name}");
        assert_eq!(cpu.iso, gpu.iso, "{name}");
        let (mut worst_d, mut worst_a) = (0.0f32, 0.0f32);
        for g in [&gpu, &gpu_sparse] {
            for i in 0..cpu.len() {
                let d = cpu.positions[i].distance(g.positions[i]) / spec.spacing;
                let a = cpu.normals[i].angle_between(g.normals[i]).to_degrees();
                worst_d = worst_d.max(d);
                worst_a = worst_a.max(if a.is_nan() { 0.0 } else { a });
            }
        }
        println!("  worst position {worst_d:.2e} cells, worst normal {worst_a:.3} degrees");
        assert!(
            worst_d <= 1e-3,
            "{name}: a surfel {worst_d} cells from the CPU's"
        );
        assert!(
            worst_a <= 1.0,
            "{name}: a normal {worst_a} degrees from the CPU's"
        );
    }
}

/// A lone particle on the GPU: no surfels above its peak, the CPU's count at the default
/// iso-value, and a weight of 2 making it larger, as on the CPU.
#[test]
fn gpu_surfels_of_a_lone_particle() {
    use fluid_surfels::density::{GridSpec, Kernel, Resolution};
    use fluid_surfels::surfels::{self, SurfelParams};
    let Some(ctx) = gpu::context_or_skip("gpu_surfels_of_a_lone_particle").unwrap() else {
        return;
    };
    let params = SurfelParams::default();
    // nothing to extract: no surfels, no error
    let one = [glam::Vec3::ZERO];
    let points = Points::uniform(&one, 1.0);
    let spec = GridSpec::around(&one, 1.0, Resolution::CellSize(0.25)).unwrap();
    let grid = fluid_surfels::density::points_grid(points, &spec, Kernel::Wyvill, 1 << 30).unwrap();
    let high = SurfelParams {
        iso_fraction: 2.0,
        ..SurfelParams::default()
    };
    assert!(
        surfels::gpu::extract_gpu(&ctx, &grid, points, Kernel::Wyvill, &high)
            .unwrap()
            .is_empty()
    );
    let lone = surfels::gpu::extract_gpu(&ctx, &grid, points, Kernel::Wyvill, &params).unwrap();
    assert_eq!(
        lone.len(),
        surfels::extract_points(&grid, points, Kernel::Wyvill, &params)
            .unwrap()
            .len()
    );
    // a weighted lone particle: its weight doubles its density, as on the CPU
    let w = [2.0f32];
    let heavy = points.with_weights(&w);
    let grid = fluid_surfels::density::points_grid(heavy, &spec, Kernel::Wyvill, 1 << 30).unwrap();
    let on_cpu = surfels::extract_points(&grid, heavy, Kernel::Wyvill, &params).unwrap();
    assert!(on_cpu.len() > lone.len(), "a heavier drop is larger");
    assert_eq!(
        surfels::gpu::extract_gpu(&ctx, &grid, heavy, Kernel::Wyvill, &params)
            .unwrap()
            .len(),
        on_cpu.len()
    );
}

/// The sparse grid of `layout` (its inside blocks reading `inside`) filled on the GPU with
/// `points` (Wyvill's kernel) and submitted.
fn sparse_on_gpu(
    ctx: &gpu::GpuContext,
    points: Points<'_>,
    layout: &density::SparseLayout,
    inside: f32,
) -> density::gpu::GpuGrid {
    let mut filler = density::gpu::GridFiller::new(&ctx.device);
    let mut encoder = ctx.device.create_command_encoder(&Default::default());
    let sparse = filler
        .record_sparse(ctx, &mut encoder, points, (layout, inside), Kernel::Wyvill)
        .unwrap();
    ctx.queue.submit([encoder.finish()]);
    sparse
}

/// The density grid filled on the GPU and left there, and the surfels extracted from it
/// (issue 37): the grid equal to the CPU's (relative 1e-5 of its largest value), and the
/// surfels against the CPU's from the CPU grid: counts within 0.1 %, every GPU surfel within
/// 1e-3 of a cell of a CPU surfel whose normal is within 1 degree of its own; the double dam
/// break and the column's splash frame.
#[test]
fn gpu_grid_and_surfels_stay_on_the_gpu() {
    use fluid_surfels::density::gpu::density_grid_on_gpu;
    use fluid_surfels::surfels::{self, SurfelParams, gpu::SurfelPasses};
    let Some(ctx) = gpu::context_or_skip("gpu_grid_and_surfels_stay_on_the_gpu").unwrap() else {
        return;
    };
    let (ddb, column) = (double_dam_break(), column_splash());
    let h_ddb = fluid_surfels::neighbours::support_radius(&ddb).unwrap();
    let passes = SurfelPasses::new(&ctx.device);
    let params = SurfelParams::default();
    let mut inside_seen = 0;
    // a bulk body, deep enough for blocks inside the band's interior
    let cube = scenes::block(&scenes::BlockParams {
        counts: [22, 22, 22],
        ..Default::default()
    })
    .unwrap();
    for (name, points) in [
        ("double dam break", Points::uniform(&ddb, h_ddb)),
        (
            "column splash",
            Points::uniform(&column.particles.positions, column.support_radius),
        ),
        (
            "block",
            Points::uniform(&cube.particles.positions, cube.support_radius),
        ),
    ] {
        let spec = GridSpec::around(
            points.positions,
            points.h,
            Resolution::CellSize(points.h / 3.0),
        )
        .unwrap();
        let cpu_grid = density::points_grid(points, &spec, Kernel::Wyvill, 1 << 30).unwrap();
        let gpu_grid = density_grid_on_gpu(&ctx, points, &spec, Kernel::Wyvill).unwrap();
        let back = gpu_grid.read(&ctx).unwrap();
        let top = cpu_grid.values.iter().copied().fold(0.0f32, f32::max);
        let worst = cpu_grid
            .values
            .iter()
            .zip(&back.values)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        assert!(worst <= 1e-5 * top, "{name}: grid off by {worst} of {top}");
        let cpu = surfels::extract_points(&cpu_grid, points, Kernel::Wyvill, &params).unwrap();
        let gpu = passes
            .extract(&ctx, &gpu_grid, points, Kernel::Wyvill, &params)
            .unwrap();
        let diff = (cpu.len() as f64 - gpu.len() as f64).abs() / cpu.len() as f64;
        assert!(
            cpu.len() > 1000 && diff <= 1e-3,
            "{name}: {} CPU, {} GPU surfels",
            cpu.len(),
            gpu.len()
        );
        let (worst_d, worst_a) = nearest_cpu_surfels(&cpu, &gpu, spec.spacing);
        println!(
            "{name}: grid off by {:.1e} of its largest value; {} CPU, {} GPU surfels, worst {worst_d:.1e} cells, {worst_a:.3} degrees",
            worst / top,
            cpu.len(),
            gpu.len()
        );
        assert!(
            worst_d <= 1e-3 && worst_a <= 1.0,
            "{name}: {worst_d} cells, {worst_a} degrees"
        );
        // the sparse grid: which blocks on the CPU, their values on the GPU
        let band = fluid_surfels::lnm::narrow_band(points.positions, points.h, &Default::default())
            .unwrap();
        let layout = density::sparse_layout(points, &spec, 1 << 30, &band).unwrap();
        let inside = 2.0 * Kernel::Wyvill.peak(points.h);
        let sparse = sparse_on_gpu(&ctx, points, &layout, inside);
        let values = sparse.read(&ctx).unwrap();
        // every value of an evaluated block is the dense grid's; an inside block's is `inside`
        let level = Kernel::Wyvill.peak(points.h) * params.iso_fraction;
        let mut off = 0.0f32;
        for (&c, &g) in cpu_grid.values.iter().zip(&values.values) {
            if g == inside {
                assert!(c >= level, "{name}: an inside point below the iso-value");
            } else {
                off = off.max((c - g).abs());
            }
        }
        let inside_blocks = layout.states.iter().filter(|&&s| s == u32::MAX - 1).count();
        inside_seen += inside_blocks;
        assert!(
            off <= 1e-5 * top,
            "{name}: sparse grid off by {off} of {top}"
        );
        let gpu_sparse = passes
            .extract(&ctx, &sparse, points, Kernel::Wyvill, &params)
            .unwrap();
        let (worst_d, worst_a) = nearest_cpu_surfels(&cpu, &gpu_sparse, spec.spacing);
        let full = layout.states.len() * 512 * 4;
        println!(
            "  sparse on the GPU: {} of {} blocks evaluated, {inside_blocks} inside, {:.2} of the dense grid's memory; {} surfels, worst {worst_d:.1e} cells, {worst_a:.3} degrees",
            layout.evaluated.len(),
            layout.states.len(),
            layout.value_bytes() as f64 / full as f64,
            gpu_sparse.len()
        );
        let diff = (cpu.len() as f64 - gpu_sparse.len() as f64).abs() / cpu.len() as f64;
        assert!(
            diff <= 1e-3,
            "{name}: {} CPU, {} sparse GPU surfels",
            cpu.len(),
            gpu_sparse.len()
        );
        assert!(
            worst_d <= 1e-3 && worst_a <= 1.0,
            "{name} sparse: {worst_d} cells, {worst_a} degrees"
        );
    }
    assert!(
        inside_seen > 0,
        "no inside block: the sparse grid's inside blocks untested"
    );
}

/// The sparse grid's layout found on the GPU (issue 37: no layout made on the CPU) equals the
/// CPU's, block for block and slot for slot: on the column splash frame's and the double dam
/// break's chains (refined points of their own radii and weights beside the particles), the
/// double dam break's particles alone and a bulk block (inside blocks), each at cells of a third
/// and a seventh of the radius. Seen to fail with the band's first layer taken as interior and
/// with a closed range one point short; not with the radius margin taken away (no case has a
/// ball within 1e-4 of a block), so the margin rests on the CPU's reasoning, not on this test.
#[test]
fn gpu_sparse_layout_equals_the_cpus() {
    let Some(ctx) = gpu::context_or_skip("gpu_sparse_layout_equals_the_cpus").unwrap() else {
        return;
    };
    let ddb = double_dam_break();
    let h_ddb = fluid_surfels::neighbours::support_radius(&ddb).unwrap();
    let column = column_splash();
    let cube = scenes::block(&scenes::BlockParams {
        counts: [22, 22, 22],
        ..Default::default()
    })
    .unwrap();
    // the chains' points as the density reads them
    fn chain(particles: &fluid_surfels::ParticleSet, h: f32) -> pipeline::GridInput<'_> {
        let mut params = PipelineParams {
            support_radius: Some(h),
            ..Default::default()
        };
        params.refine.steps = 2;
        let mut pipeline = Pipeline::new(params).unwrap();
        let (_, input) = pipeline.frame_to_grid(particles, u64::MAX).unwrap();
        input.expect("a chain with points")
    }
    let column_chain = chain(&column.particles, column.support_radius);
    let ddb_set = fluid_surfels::ParticleSet::from_positions(ddb.clone());
    let ddb_chain = chain(&ddb_set, h_ddb);
    let mut cases = vec![
        ("column chain", column_chain.points(), column_chain.spec),
        ("double dam break chain", ddb_chain.points(), ddb_chain.spec),
    ];
    for (name, points) in [
        ("double dam break", Points::uniform(&ddb, h_ddb)),
        (
            "block",
            Points::uniform(&cube.particles.positions, cube.support_radius),
        ),
    ] {
        for cells in [3.0, 7.0] {
            let spec = GridSpec::around(
                points.positions,
                points.h,
                Resolution::CellSize(points.h / cells),
            )
            .unwrap();
            cases.push((name, points, spec));
        }
    }
    let (mut inside, mut empties) = (0, 0);
    for (name, points, spec) in cases {
        let band = fluid_surfels::lnm::narrow_band(
            points.positions,
            points.max_radius(),
            &Default::default(),
        )
        .unwrap();
        let cpu = density::sparse_layout(points, &spec, 1 << 30, &band).unwrap();
        let gpu = density::sparse_gpu::sparse_layout_gpu(&ctx, points, &spec).unwrap();
        let differ = cpu
            .states
            .iter()
            .zip(&gpu.states)
            .filter(|(a, b)| a != b)
            .count();
        let count = |state: u32| cpu.states.iter().filter(|&&s| s == state).count();
        let (empty, inner) = (count(u32::MAX), count(u32::MAX - 1));
        println!(
            "{name}, cell {:.3}: {} blocks, {empty} empty, {inner} inside, {} evaluated; {differ} states differ",
            spec.spacing,
            cpu.states.len(),
            cpu.evaluated.len()
        );
        assert_eq!(gpu.blocks, cpu.blocks, "{name}");
        assert_eq!(differ, 0, "{name}: block states differ");
        assert_eq!(gpu.states.len(), cpu.states.len(), "{name}");
        assert_eq!(
            gpu.evaluated, cpu.evaluated,
            "{name}: evaluated blocks differ"
        );
        assert!(!cpu.evaluated.is_empty(), "{name}: nothing evaluated");
        // the bound the values are sized from before a count comes back
        let bound = density::sparse_gpu::evaluated_bound(&points, &spec);
        println!(
            "  bound {bound} ({:.2} of the evaluated)",
            bound as f64 / cpu.evaluated.len() as f64
        );
        assert!(bound >= cpu.evaluated.len() as u64, "{name}: bound {bound}");
        inside += inner;
        empties += empty;
    }
    assert!(
        inside > 0 && empties > 0,
        "no inside or no empty block: a state untested"
    );
    // values that hold half the evaluated blocks: those past them read as empty, the count is
    // the whole one and the fill's dispatch covers the half
    let points = column_chain.points();
    let spec = column_chain.spec;
    let band =
        fluid_surfels::lnm::narrow_band(points.positions, points.max_radius(), &Default::default())
            .unwrap();
    let cpu = density::sparse_layout(points, &spec, 1 << 30, &band).unwrap();
    let half = cpu.evaluated.len() as u32 / 2;
    let binned = gpu_density::BinnedPoints::new(&ctx.device, &points, &spec).unwrap();
    let domain = fluid_surfels::lnm::gpu::ResidentBand::domain(
        points.positions,
        points.max_radius(),
        &Default::default(),
    )
    .unwrap();
    let mut layout = density::sparse_gpu::GpuSparseLayout::new(&ctx.device);
    let mut encoder = ctx.device.create_command_encoder(&Default::default());
    layout
        .record(
            &ctx,
            &mut encoder,
            (&binned, &spec),
            (domain, points.max_radius()),
            half,
        )
        .unwrap();
    ctx.queue.submit([encoder.finish()]);
    let gpu = layout.read(&ctx).unwrap();
    let count: Vec<u32> = gpu::read_buffer(&ctx, layout.count()).unwrap();
    assert_eq!(count[..4], [cpu.evaluated.len() as u32, 8, half, 1]);
    for (b, (&c, &g)) in cpu.states.iter().zip(&gpu.states).enumerate() {
        let expected = if c < u32::MAX - 1 && c >= half {
            u32::MAX
        } else {
            c
        };
        assert_eq!(g, expected, "block {b} with values for {half} blocks");
    }
}

/// A sparse grid on the GPU whose inside blocks end crossing edges (issue 37): the GPU does not
/// make such ends exact in the grid as the CPU's `exact_ends` does, its surfel pass computes the
/// points' density there instead. Every block of the cube's dense grid whose own points all lie
/// above the iso-value but that has a point below it next to one of them is declared inside
/// (the case the band's interior meets a dip of the density); the surfels must still be the
/// dense grid's, in count and place.
#[test]
fn gpu_sparse_surfels_are_exact_where_crossings_end_in_inside_blocks() {
    use fluid_surfels::density::sparse::BLOCK;
    use fluid_surfels::surfels::{self, SurfelParams, gpu::SurfelPasses};
    let Some(ctx) = gpu::context_or_skip("gpu_sparse_surfels_exact_ends").unwrap() else {
        return;
    };
    let sphere = scenes::sphere(&Default::default()).unwrap();
    let points = Points::uniform(&sphere.particles.positions, sphere.support_radius);
    let spec = GridSpec::around(
        points.positions,
        points.h,
        Resolution::CellSize(points.h / 3.0),
    )
    .unwrap();
    let params = SurfelParams::default();
    let grid = density::points_grid(points, &spec, Kernel::Wyvill, 1 << 30).unwrap();
    let level = Kernel::Wyvill.peak(points.h) * params.iso_fraction;
    let band =
        fluid_surfels::lnm::narrow_band(points.positions, points.h, &Default::default()).unwrap();
    let mut layout = density::sparse_layout(points, &spec, 1 << 30, &band).unwrap();
    let [nx, ny, nz] = spec.dims;
    let at = |i: u32, j: u32, k: u32| grid.values[(i + nx * (j + ny * k)) as usize];
    let mut tight = Vec::new();
    for &b in &layout.evaluated {
        let c = [
            b % layout.blocks[0],
            (b / layout.blocks[0]) % layout.blocks[1],
            b / (layout.blocks[0] * layout.blocks[1]),
        ]
        .map(|v| v * BLOCK);
        let own = |i: u32, j: u32, k: u32| {
            i >= c[0]
                && i < c[0] + BLOCK
                && j >= c[1]
                && j < c[1] + BLOCK
                && k >= c[2]
                && k < c[2] + BLOCK
        };
        let (mut all_above, mut next_below) = (true, false);
        for k in c[2]..(c[2] + BLOCK).min(nz) {
            for j in c[1]..(c[1] + BLOCK).min(ny) {
                for i in c[0]..(c[0] + BLOCK).min(nx) {
                    all_above &= at(i, j, k) >= level;
                    let near = [
                        (i.wrapping_sub(1), j, k),
                        (i + 1, j, k),
                        (i, j.wrapping_sub(1), k),
                        (i, j + 1, k),
                        (i, j, k.wrapping_sub(1)),
                        (i, j, k + 1),
                    ];
                    next_below |= near.iter().any(|&(a, b2, d)| {
                        a < nx && b2 < ny && d < nz && !own(a, b2, d) && at(a, b2, d) < level
                    });
                }
            }
        }
        if all_above && next_below {
            tight.push(b);
        }
    }
    assert!(!tight.is_empty(), "no block to declare inside");
    layout.evaluated.retain(|b| !tight.contains(b));
    for &b in &tight {
        layout.states[b as usize] = u32::MAX - 1;
    }
    for (slot, &b) in layout.evaluated.iter().enumerate() {
        layout.states[b as usize] = slot as u32;
    }
    let inside = 2.0 * Kernel::Wyvill.peak(points.h);
    let sparse = sparse_on_gpu(&ctx, points, &layout, inside);
    let cpu = surfels::extract_points(&grid, points, Kernel::Wyvill, &params).unwrap();
    let gpu = SurfelPasses::new(&ctx.device)
        .extract(&ctx, &sparse, points, Kernel::Wyvill, &params)
        .unwrap();
    assert_eq!(cpu.len(), gpu.len());
    // in the same order: the crossings ending in the inside blocks placed as on the dense grid
    let worst = (0..cpu.len())
        .map(|i| cpu.positions[i].distance(gpu.positions[i]) / spec.spacing)
        .fold(0.0f32, f32::max);
    println!(
        "{} blocks declared inside at crossings; {} surfels, worst {worst:.1e} cells",
        tight.len(),
        gpu.len()
    );
    assert!(
        worst <= 1e-3,
        "a surfel {worst} cells from the dense grid's"
    );
}

/// The grid and the surfels of a sequence on the GPU, recorded frame after frame into one
/// encoder each (issue 37): after the first frames nothing is created, no frame waits on the
/// device or reads back (`gpu::waits` unchanged over the whole sequence: the count arrives
/// asynchronously), and the last frame's surfels, read back afterwards, are the CPU's.
#[test]
fn gpu_grid_and_surfels_record_frames_without_waits() {
    use fluid_surfels::density::gpu::GridFiller;
    use fluid_surfels::surfels::{self, SurfelParams, gpu::ResidentSurfels};
    let Some(ctx) =
        gpu::context_or_skip("gpu_grid_and_surfels_record_frames_without_waits").unwrap()
    else {
        return;
    };
    let mut sim = scenes::ColumnSim::new(Default::default()).unwrap();
    let frames: Vec<Vec<glam::Vec3>> = (6..18)
        .map(|f| {
            sim.advance_to(f);
            sim.particles().positions.clone()
        })
        .collect();
    let h = sim.support_radius();
    // one grid for the sequence, around every frame (as a sequence fits its views once)
    let all: Vec<glam::Vec3> = frames.iter().flatten().copied().collect();
    let spec = GridSpec::around(&all, h, Resolution::CellSize(h / 3.0)).unwrap();
    let params = SurfelParams::default();
    let mut filler = GridFiller::new(&ctx.device);
    let mut surfels = ResidentSurfels::new(&ctx.device);
    let waits = gpu::waits();
    let mut created = Vec::new();
    for positions in &frames {
        let points = Points::uniform(positions, h);
        let mut encoder = ctx.device.create_command_encoder(&Default::default());
        let grid = filler
            .record(&ctx, &mut encoder, points, &spec, Kernel::Wyvill)
            .unwrap();
        surfels
            .record(&ctx, &mut encoder, &grid, points, Kernel::Wyvill, &params)
            .unwrap();
        ctx.queue.submit([encoder.finish()]);
        surfels.after_submit();
        created.push(filler.created() + surfels.created());
    }
    assert_eq!(gpu::waits(), waits, "a frame waited on the device");
    println!(
        "created per frame {created:?}; capacity {}, a recent count {:?}",
        surfels.capacity(),
        surfels.last_count()
    );
    assert!(created[0] > 0);
    assert!(
        created[4..].iter().all(|&c| c == 0),
        "resources created after the first frames: {created:?}"
    );
    assert!(surfels.last_count().is_some(), "the count never arrived");
    assert!(!surfels.overflowed());
    // the last frame against the CPU, read back outside the frame path
    let last = frames.last().unwrap();
    let points = Points::uniform(last, h);
    let grid = density::points_grid(points, &spec, Kernel::Wyvill, 1 << 30).unwrap();
    let cpu = surfels::extract_points(&grid, points, Kernel::Wyvill, &params).unwrap();
    let gpu = surfels.read(&ctx).unwrap();
    println!(
        "the last frame: {} surfels on the GPU and the CPU",
        gpu.len()
    );
    assert_eq!(gpu.len(), cpu.len());
    let (worst, _) = nearest_cpu_surfels(&cpu, &gpu, spec.spacing);
    assert!(worst <= 1e-3, "a GPU surfel {worst} cells from the CPU's");
}

/// Asserts that the trimmed search's values (`a`) are the whole search's (`b`), bit for bit.
fn same_bits(a: &[f32], b: &[f32], name: &str) {
    assert_eq!(a.len(), b.len(), "{name}: lengths");
    if let Some(i) = (0..a.len()).find(|&i| a[i].to_bits() != b[i].to_bits()) {
        panic!(
            "{name}: value {i} is {} with the trimmed search, {} with the whole",
            a[i], b[i]
        );
    }
}

/// The gather pass (a dense grid's and a sparse grid's) and the surfels' projection read each
/// row of bins only where the ball of the largest radius reaches it and the points of smaller
/// radii (after the leading ones) only in the bins their radius reaches; every point they
/// leave out adds nothing, so the grids and the surfels equal, bit for bit, those of the search
/// over every point of every bin (`BinSearch::Whole`): on the double dam break's particles
/// (radius h) followed by a shifted copy of radius 0.45 h, and on one radius.
#[test]
fn gpu_trimmed_searches_equal_the_whole() {
    use fluid_surfels::density::bins::{BinSearch, leading_and_rest};
    use fluid_surfels::density::gpu::GridFiller;
    use fluid_surfels::surfels::{SurfelParams, gpu::ResidentSurfels};
    let Some(ctx) = gpu::context_or_skip("gpu_trimmed_searches_equal_the_whole").unwrap() else {
        return;
    };
    let ddb = double_dam_break();
    let h = fluid_surfels::neighbours::estimate_spacing(&ddb).unwrap() * 2.0;
    let mut positions = ddb.clone();
    positions.extend(
        ddb.iter()
            .map(|p| *p + glam::Vec3::new(0.1, 0.05, 0.02) * h),
    );
    let radii: Vec<f32> = (0..positions.len())
        .map(|i| if i < ddb.len() { h } else { 0.45 * h })
        .collect();
    let params = SurfelParams::default();
    for (name, points) in [
        ("two radii", Points::with_radii(&positions, &radii, h)),
        ("one radius", Points::uniform(&ddb, h)),
    ] {
        let (leading, rest) = leading_and_rest(&points);
        let spec = GridSpec::around(points.positions, h, Resolution::CellSize(h / 3.0)).unwrap();
        let band = fluid_surfels::lnm::narrow_band(
            points.positions,
            points.max_radius(),
            &Default::default(),
        )
        .unwrap();
        let layout = density::sparse_layout(points, &spec, 1 << 30, &band).unwrap();
        let inside = 4.0 * Kernel::Wyvill.peak(h);
        let mut filler = GridFiller::new(&ctx.device);
        let mut found = Vec::new();
        for search in [BinSearch::Trimmed, BinSearch::Whole] {
            filler.set_search(search);
            let mut surfels = ResidentSurfels::new(&ctx.device);
            surfels.set_search(search);
            let mut encoder = ctx.device.create_command_encoder(&Default::default());
            let grid = filler
                .record(&ctx, &mut encoder, points, &spec, Kernel::Wyvill)
                .unwrap();
            surfels
                .record(&ctx, &mut encoder, &grid, points, Kernel::Wyvill, &params)
                .unwrap();
            ctx.queue.submit([encoder.finish()]);
            let dense = grid.read(&ctx).unwrap().values;
            let got = surfels.read(&ctx).unwrap();
            let mut encoder = ctx.device.create_command_encoder(&Default::default());
            let sparse = filler
                .record_sparse(
                    &ctx,
                    &mut encoder,
                    points,
                    (&layout, inside),
                    Kernel::Wyvill,
                )
                .unwrap();
            ctx.queue.submit([encoder.finish()]);
            found.push((dense, sparse.read(&ctx).unwrap().values, got));
        }
        let (a, b) = (&found[0], &found[1]);
        println!(
            "{name}: {} points, {leading} leading, the rest of radius up to {:.3} h: {} surfels, {} of {} blocks evaluated",
            points.len(),
            rest / h,
            a.2.len(),
            layout.evaluated.len(),
            layout.states.len()
        );
        assert!(a.2.len() > 1000, "{name}: too few surfels to compare");
        assert_eq!(a.2.len(), b.2.len(), "{name}: counts");
        same_bits(&a.0, &b.0, &format!("{name}, the dense grid"));
        same_bits(&a.1, &b.1, &format!("{name}, the sparse grid"));
        for (x, y) in [
            (&a.2.positions, &b.2.positions),
            (&a.2.normals, &b.2.normals),
        ] {
            same_bits(
                bytemuck::cast_slice(x.as_slice()),
                bytemuck::cast_slice(y.as_slice()),
                &format!("{name}, the surfels"),
            );
        }
    }
}

/// Bad input on the GPU frame path (issue 37): a grid beyond the adapter's storage binding
/// limit is a typed error before any work, a frame without particles gives no surfels, a
/// non-finite position is refused; never a panic or a lost device (the next frame works).
#[test]
fn gpu_frame_path_refuses_bad_input_and_goes_on() {
    use fluid_surfels::density::gpu::GridFiller;
    use fluid_surfels::surfels::{SurfelParams, gpu::ResidentSurfels};
    let Some(ctx) = gpu::context_or_skip("gpu_frame_path_refuses_bad_input_and_goes_on").unwrap()
    else {
        return;
    };
    let mut filler = GridFiller::new(&ctx.device);
    let mut surfels = ResidentSurfels::new(&ctx.device);
    let params = SurfelParams::default();
    let block = scenes::block(&scenes::BlockParams {
        counts: [6, 6, 6],
        ..Default::default()
    })
    .unwrap();
    let (p, h) = (&block.particles.positions, block.support_radius);
    let spec = GridSpec::around(p, h, Resolution::CellSize(h / 3.0)).unwrap();
    let mut frame =
        |positions: &[glam::Vec3], spec: &GridSpec| -> Result<usize, fluid_surfels::Error> {
            let points = Points::uniform(positions, h);
            let mut encoder = ctx.device.create_command_encoder(&Default::default());
            let grid = filler.record(&ctx, &mut encoder, points, spec, Kernel::Wyvill)?;
            surfels.record(&ctx, &mut encoder, &grid, points, Kernel::Wyvill, &params)?;
            ctx.queue.submit([encoder.finish()]);
            surfels.after_submit();
            Ok(surfels.read(&ctx)?.len())
        };
    // far too large a grid: refused by size
    let huge = GridSpec {
        dims: [4096, 4096, 4096],
        ..spec
    };
    let e = frame(p, &huge).unwrap_err().to_string();
    assert!(e.contains("storage binding limit"), "{e}");
    // no particles: no surfels
    assert_eq!(frame(&[], &spec).unwrap(), 0);
    // a non-finite position: refused
    let mut bad = p.clone();
    bad[3].y = f32::NAN;
    assert!(frame(&bad, &spec).is_err());
    // and the device goes on
    assert!(frame(p, &spec).unwrap() > 100);
}

/// The surfels made on the GPU drawn from where they are (issue 37): the splatting reads the
/// buffer the surfel passes wrote, with the count they wrote (an indirect draw, no read-back),
/// and the shaded splats of the column's splash frame equal those of the CPU's surfels drawn
/// the usual way within 40 dB.
#[test]
fn gpu_surfels_are_drawn_from_the_gpu() {
    use fluid_surfels::density::gpu::GridFiller;
    use fluid_surfels::surfels::{self, SurfelParams, gpu::ResidentSurfels};
    let Some(ctx) = gpu::context_or_skip("gpu_surfels_are_drawn_from_the_gpu").unwrap() else {
        return;
    };
    let column = column_splash();
    let (p, h) = (&column.particles.positions, column.support_radius);
    let points = Points::uniform(p, h);
    let spec = GridSpec::around(p, h, Resolution::CellSize(h / 3.0)).unwrap();
    let params = SurfelParams::default();
    // on the GPU: grid, surfels, no read-back
    let mut filler = GridFiller::new(&ctx.device);
    let mut resident = ResidentSurfels::new(&ctx.device);
    let mut encoder = ctx.device.create_command_encoder(&Default::default());
    let grid = filler
        .record(&ctx, &mut encoder, points, &spec, Kernel::Wyvill)
        .unwrap();
    resident
        .record(&ctx, &mut encoder, &grid, points, Kernel::Wyvill, &params)
        .unwrap();
    ctx.queue.submit([encoder.finish()]);
    resident.after_submit();
    // on the CPU: the same surfels as disks
    let cpu_grid = density::points_grid(points, &spec, Kernel::Wyvill, 1 << 30).unwrap();
    let cpu = surfels::extract_points(&cpu_grid, points, Kernel::Wyvill, &params).unwrap();
    let disks: Vec<splat::Surfel> = cpu
        .positions
        .iter()
        .zip(&cpu.normals)
        .map(|(&x, &n)| splat::Surfel::disk(x, n, spec.spacing, splat::WATER))
        .collect();
    let (lo, hi) = p.iter().fold(
        (glam::Vec3::INFINITY, glam::Vec3::NEG_INFINITY),
        |(lo, hi), &q| (lo.min(q), hi.max(q)),
    );
    let camera = fluid_surfels::splat::Camera::framing(lo, hi);
    let view =
        splat::View::new(&camera, &Default::default(), &Default::default(), 160, 120).unwrap();
    let renderer =
        gpu_splat::SplatRenderer::new(&ctx.device, wgpu::TextureFormat::Rgba8Unorm, 160, 120)
            .unwrap();
    let from_gpu = gpu_splat::render_timed(&ctx, &renderer, &resident.surfel_buffer(), &view)
        .unwrap()
        .0;
    let uploaded = gpu_splat::SplatRenderer::upload(&ctx.device, &disks);
    let from_cpu = gpu_splat::render_timed(&ctx, &renderer, &uploaded, &view)
        .unwrap()
        .0;
    let db = splat::psnr(&from_cpu.image, &from_gpu.image);
    println!(
        "{} surfels; drawn from the GPU's buffer {db:.1} dB from the CPU's, {} pixels covered",
        cpu.len(),
        from_gpu.covered_pixels()
    );
    assert!(from_gpu.covered_pixels() > 1000);
    assert!(db >= 40.0, "{db:.1} dB");
}

/// The chain on the GPU inside `GpuPipeline::prepare` (issue 37): detection, upsampling and the
/// boundary weights on the CPU, the density grid and the surfels on the GPU, drawn from the
/// GPU's surfel buffer by the optics and the shaded splats. Against the CPU `Pipeline` on the
/// column's splash frame (the same frames before it for the hysteresis, detail from the
/// finished frame's view on both): the surfels read back within 0.1 % in count, 1e-3 of a cell
/// and 1 degree; the finished frame and the shaded splats at least 40 dB; the stages reported.
/// With `gpu_surfels = false` the grid and surfels are the CPU's again.
#[test]
fn gpu_pipeline_makes_the_grid_and_surfels_on_the_gpu() {
    let Some(ctx) = gpu::context_or_skip("gpu_pipeline_makes_the_grid_and_surfels").unwrap() else {
        return;
    };
    let size = (160, 160);
    let format = wgpu::TextureFormat::Rgba8Unorm;
    let (mut sim, params) = column_setup(size);
    let mut cpu = Pipeline::new(params.clone()).unwrap();
    // every surfel, as the GPU makes them (not only those the CPU's picture shows)
    cpu.keep_hidden_surfels(true);
    let mut gpu = GpuPipeline::new(&ctx.device, &ctx.queue, format, size, &params).unwrap();
    assert!(gpu.surfels_on_gpu());
    assert_eq!(
        gpu.gpu_stages(),
        ["calibration", "density", "surfels", "splats", "optics"]
    );
    // the sparse grid on the GPU beside it
    let mut sparse_params = params.clone();
    sparse_params.grid.narrow_band = true;
    let mut sparse =
        GpuPipeline::new(&ctx.device, &ctx.queue, format, size, &sparse_params).unwrap();
    let last = scenes::ColumnParams::SPLASH_FRAME;
    let (cpu_frame, gpu_frame, image, sparse_image) = loop {
        let particles = sim.particles();
        if sim.frame() < last - 1 {
            cpu.frame_through(particles, Through::Surface).unwrap();
            for g in [&mut gpu, &mut sparse] {
                g.cpu_mut()
                    .frame_through(particles, Through::Surface)
                    .unwrap();
            }
            sim.step_frame();
            continue;
        }
        let c = cpu.frame_through(particles, Through::Frame).unwrap();
        let (g, image) = gpu.prepare_image(&ctx, particles).unwrap();
        let (_, sparse_image) = sparse.prepare_image(&ctx, particles).unwrap();
        if sim.frame() >= last {
            break (c, g, image, sparse_image);
        }
        sim.step_frame();
    };
    assert!(gpu_frame.surfels_on_gpu && gpu_frame.render_surfels.is_empty());
    assert_eq!(gpu_frame.detail.steps, cpu_frame.detail.steps);
    assert_eq!(gpu_frame.detail.cell, cpu_frame.detail.cell);
    // the surfels, read back outside the frame path
    let on_gpu = gpu.read_surfels(&ctx).unwrap().unwrap();
    let on_cpu = cpu_frame.surfels.as_ref().unwrap();
    let cell = cpu_frame.detail.cell;
    let (worst, angle) = nearest_cpu_surfels(on_cpu, &on_gpu, cell);
    println!(
        "column splash frame: {} surfels on the GPU, {} on the CPU (a recent count {}); worst {worst:.2e} cells, {angle:.3} degrees",
        on_gpu.len(),
        on_cpu.len(),
        gpu_frame.detail.surfels
    );
    assert!(
        (on_gpu.len() as f64 - on_cpu.len() as f64).abs() <= 1e-3 * on_cpu.len() as f64,
        "{} GPU against {} CPU surfels",
        on_gpu.len(),
        on_cpu.len()
    );
    assert!(worst <= 1e-3, "a GPU surfel {worst} cells from the CPU's");
    assert!(angle <= 1.0, "a GPU normal {angle} degrees from the CPU's");
    // the sparse grid's
    let on_sparse = sparse.read_surfels(&ctx).unwrap().unwrap();
    let (worst, angle) = nearest_cpu_surfels(on_cpu, &on_sparse, cell);
    let (dense_bytes, sparse_bytes) = (
        gpu.gpu_grid_bytes().unwrap(),
        sparse.gpu_grid_bytes().unwrap(),
    );
    println!(
        "  sparse grid on the GPU: {sparse_bytes} bytes against {dense_bytes}; {} surfels, worst {worst:.2e} cells, {angle:.3} degrees",
        on_sparse.len()
    );
    assert!(sparse_bytes < dense_bytes);
    // the boundary weights solved on the GPU, into the binned points (and, with the dense
    // grid's splatting, its copy sorted by z)
    for g in [&gpu, &sparse] {
        assert_eq!(
            g.gpu_stages(),
            ["calibration", "density", "surfels", "splats", "optics"]
        );
    }
    assert!(
        (on_sparse.len() as f64 - on_cpu.len() as f64).abs() <= 1e-3 * on_cpu.len() as f64,
        "{} sparse GPU against {} CPU surfels",
        on_sparse.len(),
        on_cpu.len()
    );
    assert!(
        worst <= 1e-3 && angle <= 1.0,
        "sparse: {worst} cells, {angle} degrees"
    );
    // the finished frame
    let cpu_image = &cpu_frame.finished.as_ref().unwrap().image;
    let db = splat::psnr(cpu_image, &image);
    let sparse_db = splat::psnr(cpu_image, &sparse_image);
    assert!(
        sparse_db >= 40.0,
        "finished frame from the sparse grid {sparse_db:.1} dB"
    );
    // the shaded splats of the same frame, from the GPU's buffer
    let cpu_splats = cpu
        .frame_of_surfels(cpu_frame.render_surfels.clone(), Through::Splats)
        .unwrap();
    let cpu_splats = &cpu_splats.splats.as_ref().unwrap().image;
    let splats = splats_image(&ctx, &mut gpu, &gpu_frame, size, format);
    let splats_db = splat::psnr(cpu_splats, &splats);
    println!(
        "GpuPipeline with the grid and surfels on the GPU against the CPU Pipeline: finished frame {db:.1} dB (sparse grid {sparse_db:.1} dB), shaded splats {splats_db:.1} dB"
    );
    if db < 40.0 || splats_db < 40.0 {
        let dir = std::env::temp_dir();
        cpu_image.save(dir.join("gpu_chain-expected.png")).unwrap();
        image.save(dir.join("gpu_chain-actual.png")).unwrap();
        cpu_splats
            .save(dir.join("gpu_chain-splats-expected.png"))
            .unwrap();
        splats
            .save(dir.join("gpu_chain-splats-actual.png"))
            .unwrap();
    }
    assert!(db >= 40.0, "finished frame {db:.1} dB");
    assert!(splats_db >= 40.0, "shaded splats {splats_db:.1} dB");
    // asked for the CPU's grid and surfels
    let mut on_cpu = GpuPipeline::new(
        &ctx.device,
        &ctx.queue,
        format,
        size,
        &PipelineParams {
            gpu_surfels: false,
            ..params
        },
    )
    .unwrap();
    assert!(!on_cpu.surfels_on_gpu());
    let (frame, _) = on_cpu.prepare_image(&ctx, sim.particles()).unwrap();
    assert!(!frame.surfels_on_gpu && !frame.render_surfels.is_empty());
    assert_eq!(on_cpu.gpu_stages(), ["splats", "optics"]);
}

/// The GPU's sphere weights (`GpuPipeline::read_sphere_weights`: a sphere for every particle
/// and sheet point, `boundary::gpu::DROPPED` for those the factors leave out) against the CPU
/// `Pipeline`'s (the kept spheres only, a particle in the interior and in a thin sheet twice),
/// summed per position: the largest difference (relative, at least 1), the positions the GPU
/// keeps and the CPU does not, those the CPU keeps with a weight and the GPU does not, and the
/// spheres the GPU keeps.
fn weights_by_position(
    gpu: (&[splat::Surfel], &[f32]),
    cpu: (&[splat::Surfel], &[f32]),
) -> (f32, usize, usize, usize) {
    use std::collections::HashMap;
    let key = |s: &splat::Surfel| s.position.map(f32::to_bits);
    let mut at: HashMap<[u32; 3], (f32, bool, f32, bool)> = HashMap::new();
    let mut kept = 0;
    for (s, &w) in gpu.0.iter().zip(gpu.1) {
        let e = at.entry(key(s)).or_default();
        if w != pipeline::boundary::gpu::DROPPED {
            assert!(w >= 0.0, "a GPU weight {w}");
            e.0 += w;
            e.1 = true;
            kept += 1;
        }
    }
    for (s, &w) in cpu.0.iter().zip(cpu.1) {
        let e = at.entry(key(s)).or_default();
        e.2 += w;
        e.3 = true;
    }
    let (mut worst, mut extra, mut missing) = (0.0f32, 0, 0);
    for &(g, g_kept, c, c_kept) in at.values() {
        worst = worst.max((g - c).abs() / c.abs().max(1.0));
        extra += usize::from(g_kept && !c_kept);
        missing += usize::from(c_kept && c > 0.0 && !g_kept);
    }
    (worst, extra, missing, kept)
}

/// The ray caster's spheres weighted on the GPU (issue 37): `GpuPipeline::prepare` with the
/// ray-cast renderer and the boundary calibration draws a sphere for every particle and sheet
/// point and finds their factors and weights on the GPU (`PointWeights::record_layout`), where
/// they stay. On the column's splash frame (the raw particles, small views: lavapipe casts
/// every pixel of the light's screen too): the spheres are the particles then the sheet's
/// points; those the GPU keeps are the CPU `Pipeline`'s and their weights, summed per position,
/// the CPU's to rounding (read back outside the frame path); the finished frame within 40 dB
/// of the CPU's; the frame again makes nothing and waits on nothing; a frame whose weights stay
/// on one pipeline's GPU is refused by another.
#[test]
fn gpu_pipeline_weighs_the_ray_casters_spheres_on_the_gpu() {
    let Some(ctx) = gpu::context_or_skip("gpu_pipeline_weighs_spheres").unwrap() else {
        return;
    };
    let size = (48, 48);
    let format = wgpu::TextureFormat::Rgba8Unorm;
    let (mut sim, mut params) = column_setup(size);
    params.renderer = pipeline::Renderer::RayCast;
    params.source = pipeline::SurfelSource::Particles;
    params.scene.optics.caustics_resolution = Some([32, 32]);
    params.scene.optics.map_resolution = Some([64, 64]);
    let mut cpu = Pipeline::new(params.clone()).unwrap();
    let mut gpu = GpuPipeline::new(&ctx.device, &ctx.queue, format, size, &params).unwrap();
    assert!(gpu.weights_on_gpu() && !gpu.surfels_on_gpu());
    assert_eq!(gpu.gpu_stages(), ["calibration", "splats", "optics"]);
    let last = scenes::ColumnParams::SPLASH_FRAME;
    while sim.frame() < last {
        let particles = sim.particles();
        cpu.frame_through(particles, Through::Surface).unwrap();
        gpu.cpu_mut()
            .frame_through(particles, Through::Surface)
            .unwrap();
        sim.step_frame();
    }
    let particles = sim.particles();
    let c = cpu.frame_through(particles, Through::Frame).unwrap();
    let (g, image) = gpu.prepare_image(&ctx, particles).unwrap();
    assert!(g.weights_on_gpu && g.render_weights.is_empty());
    // every particle, then the sheet (the surface particles again, as the particle source's
    // sheet)
    let positions = &particles.positions;
    assert!(g.render_surfels.len() > positions.len());
    for (s, p) in g.render_surfels.iter().zip(positions) {
        assert_eq!(glam::Vec3::from(s.position), *p);
    }
    let weights = gpu.read_sphere_weights(&ctx).unwrap().unwrap();
    assert_eq!(weights.len(), g.render_surfels.len());
    let (worst, extra, missing, kept) = weights_by_position(
        (&g.render_surfels, &weights),
        (&c.render_surfels, &c.render_weights),
    );
    let solved = c.render_weights.iter().filter(|&&w| w != 1.0).count();
    assert!(solved > 0, "no weight solved");
    let db = splat::psnr(&c.finished.as_ref().unwrap().image, &image);
    println!(
        "column splash frame, ray cast: the GPU's {} spheres, {kept} kept, the CPU's {} ({solved} weights not 1): per position within {worst:.2e}, {extra} kept by the GPU alone, {missing} by the CPU alone; finished frame {db:.1} dB against the CPU Pipeline's",
        weights.len(),
        c.render_surfels.len()
    );
    // measured on lavapipe: 8.3e-7 (the sums' order differs, not their terms), 51.0 dB; a
    // throwaway scaling the solved weights by 1.001 in the write in order: 9.6e-4; one that
    // leaves out DROPPED: no sphere left out
    assert!(worst < 1e-4, "weights {worst}");
    assert!(
        extra == 0 && missing == 0,
        "kept: {extra} extra, {missing} missing"
    );
    assert!(kept < weights.len(), "no sphere left out");
    assert!(db >= 40.0, "finished frame {db:.1} dB");
    // the frame again: nothing made, no wait on the device while it is prepared and
    // submitted, the same picture
    let waits = gpu::waits();
    let mut encoder = ctx.device.create_command_encoder(&Default::default());
    gpu.prepare(&ctx.device, &ctx.queue, &mut encoder, particles)
        .unwrap();
    let target = gpu.draw_to_texture(&ctx.device, &mut encoder);
    ctx.queue.submit([encoder.finish()]);
    gpu.after_submit();
    assert_eq!(gpu::waits() - waits, 0, "waits on the frame path");
    assert!(gpu.reused_resources(), "the frame again made GPU resources");
    assert_eq!(
        gpu::read_rgba8(&ctx, &target).unwrap(),
        image,
        "the frame again"
    );
    // the weights live on this pipeline's GPU: another pipeline refuses the frame
    let mut other = GpuPipeline::new(&ctx.device, &ctx.queue, format, size, &params).unwrap();
    let refused = other.render_frame_image(&ctx, &g).unwrap_err();
    assert!(
        refused.to_string().contains("another GpuPipeline"),
        "{refused}"
    );
}

/// `GpuPipeline::prepare` with the grid and surfels on the GPU, over a sequence (issue 37), with
/// the dense grid and the sparse one: no read-back and no wait on the device in any frame's
/// `prepare` (the surfel count comes back
/// asynchronously, `after_submit`); buffers are made only while the sequence's need grows (the
/// column's splash raises the grid from 66 to 108 planes over these frames), so the same frames
/// run again make nothing (`reused_resources`); the count arrives and no surfel is left out.
#[test]
fn gpu_pipeline_frames_on_the_gpu_wait_on_nothing() {
    let Some(ctx) = gpu::context_or_skip("gpu_pipeline_frames_on_the_gpu_wait_on_nothing").unwrap()
    else {
        return;
    };
    let size = (96, 96);
    let (_, dense) = column_setup(size);
    let mut sparse = dense.clone();
    sparse.grid.narrow_band = true;
    for params in [dense, sparse] {
        let mut gpu = unorm_pipeline(&ctx, size, &params);
        let timed = gpu.time_stages(&ctx.device, &ctx.queue, true);
        let mut sim = scenes::ColumnSim::new(scenes::ColumnParams::default()).unwrap();
        for pass in 0..2 {
            if pass > 0 {
                // the same frames again, from a new sequence
                sim = scenes::ColumnSim::new(scenes::ColumnParams::default()).unwrap();
                gpu.cpu_mut().reset();
            }
            let (mut reused, mut waited, mut counts) = (Vec::new(), Vec::new(), Vec::new());
            for f in 6..11 {
                sim.advance_to(f);
                let waits = gpu::waits();
                let mut encoder = ctx.device.create_command_encoder(&Default::default());
                let frame = gpu
                    .prepare(&ctx.device, &ctx.queue, &mut encoder, sim.particles())
                    .unwrap();
                let _target = gpu.draw_to_texture(&ctx.device, &mut encoder);
                ctx.queue.submit([encoder.finish()]);
                gpu.after_submit();
                waited.push(gpu::waits() - waits);
                reused.push(gpu.reused_resources());
                counts.push(frame.detail.surfels);
                // the game's present: the device polled once the frame is done, so that each
                // frame's count comes back before the next frame (when it arrives otherwise
                // depends on the machine's load, and so would which counts size the buffer:
                // a late count from the first pass grew it in the second)
                ctx.device
                    .poll(wgpu::PollType::wait_indefinitely())
                    .unwrap();
                assert!(frame.surfels_on_gpu);
                assert!(frame.warnings.is_empty(), "{:?}", frame.warnings);
            }
            println!(
                "narrow band {}, pass {pass}: reused per frame {reused:?}; waits {waited:?}; recent counts {counts:?}",
                params.grid.narrow_band
            );
            assert!(waited.iter().all(|&w| w == 0), "waits per frame {waited:?}");
            assert!(
                counts.last().is_some_and(|&c| c > 0),
                "the count never arrived"
            );
            if pass == 0 {
                assert!(!reused[0]);
            } else {
                assert!(reused.iter().all(|&r| r), "the second time: {reused:?}");
            }
        }
        let read = gpu.read_surfels(&ctx).unwrap().unwrap();
        assert!(read.len() > 1000, "{} surfels", read.len());
        // the GPU time of each stage, by timestamps read back as the count is (the test polls the
        // device here, as a game's presents would)
        assert_eq!(
            timed,
            ctx.device.features().contains(gpu::TIMESTAMP_FEATURES)
        );
        if timed && !params.grid.narrow_band {
            ctx.device
                .poll(wgpu::PollType::wait_indefinitely())
                .unwrap();
            let mut encoder = ctx.device.create_command_encoder(&Default::default());
            gpu.prepare(&ctx.device, &ctx.queue, &mut encoder, sim.particles())
                .unwrap();
            ctx.queue.submit([encoder.finish()]);
            gpu.after_submit();
            let ms = gpu
                .gpu_stage_ms()
                .expect("the stages' timestamps never arrived");
            println!("GPU ms per stage (lavapipe, 96x96): {ms:?}");
            // per pass: the stages and the calibration's passes within it, in order (their
            // times sum to the stages' by construction: consecutive timestamps)
            let passes = gpu.gpu_pass_ms().expect("read back with the stages'");
            println!("GPU ms per pass: {passes:?}");
            let names: Vec<&str> = passes.iter().map(|p| p.0).collect();
            assert_eq!(
                names,
                [
                    "sort",
                    "calibration: factors",
                    "calibration: targets",
                    "calibration: compaction",
                    "calibration: steps",
                    "calibration: apply",
                    "calibration",
                    "density",
                    "surfels",
                    "caustics",
                    "image"
                ]
            );
            // the steps' interval holds work (on lavapipe at least the first steps: a pass's
            // last dispatch counts in the next interval, see `gpu::timer`)
            assert!(passes[4].1 > 0.0, "{passes:?}");
            assert!(
                ms.sort > 0.0
                    && ms.calibration > 0.0
                    && ms.density > 0.0
                    && ms.surfels > 0.0
                    && ms.caustics > 0.0
                    && ms.image > 0.0,
                "{ms:?}"
            );
        } else if !timed {
            println!("no timestamp queries on this device");
        }
    }
}

/// The bad frames both pipelines' bad-frame tests draw through `gpu`: `block` (its frame and
/// image), the same with a NaN (refused as not finite, and the next frame draws as before), no
/// particle (its frame and the dry pool's image), one particle of the block (the set, its frame
/// and image).
struct BadFrames {
    first: pipeline::Frame,
    image: image::RgbaImage,
    empty: pipeline::Frame,
    dry: image::RgbaImage,
    lone_set: fluid_surfels::ParticleSet,
    lone: pipeline::Frame,
    drop: image::RgbaImage,
}

fn bad_frames(
    ctx: &gpu::GpuContext,
    gpu: &mut GpuPipeline,
    block: &fluid_surfels::ParticleSet,
) -> BadFrames {
    let (first, image) = gpu.prepare_image(ctx, block).unwrap();
    let mut bad = block.clone();
    bad.positions[3].y = f32::NAN;
    let e = gpu.prepare_image(ctx, &bad).unwrap_err().to_string();
    assert!(e.contains("finite"), "{e}");
    let (_, again) = gpu.prepare_image(ctx, block).unwrap();
    assert_eq!(image, again, "the frame after a refused one");
    let (empty, dry) = gpu
        .prepare_image(ctx, &fluid_surfels::ParticleSet::from_positions(Vec::new()))
        .unwrap();
    assert!(empty.render_surfels.is_empty());
    // the block's particle on its top nearest the middle: in sight of the kept camera (its
    // first, a bottom corner, lies behind the pool's wall)
    let (lo, hi) =
        fluid_surfels::view::widened_bounds(block.positions.iter().copied(), 0.0).unwrap();
    let top = (lo + hi) * 0.5 + glam::Vec3::Y * (hi.y - lo.y) * 0.5;
    let nearest = block
        .positions
        .iter()
        .copied()
        .min_by(|a, b| a.distance(top).total_cmp(&b.distance(top)))
        .unwrap();
    let lone_set = fluid_surfels::ParticleSet::from_positions(vec![nearest]);
    let (lone, drop) = gpu.prepare_image(ctx, &lone_set).unwrap();
    BadFrames {
        first,
        image,
        empty,
        dry,
        lone_set,
        lone,
        drop,
    }
}

/// Pixels of `image` that differ from `background`'s.
fn covered(image: &image::RgbaImage, background: &image::RgbaImage) -> usize {
    image
        .pixels()
        .zip(background.pixels())
        .filter(|(a, b)| a != b)
        .count()
}

/// `GpuPipeline::prepare` with the grid and surfels on the GPU on bad frames (issue 37): a
/// non-finite position is a typed error, an empty frame draws the empty pool, a lone particle
/// is drawn, a grid over the memory budget is coarsened with a warning; after each the
/// pipeline goes on drawing (no panic, no lost device).
#[test]
fn gpu_pipeline_on_the_gpu_meets_bad_frames() {
    let Some(ctx) = gpu::context_or_skip("gpu_pipeline_on_the_gpu_meets_bad_frames").unwrap()
    else {
        return;
    };
    let block = scenes::block(&scenes::BlockParams {
        counts: [6, 6, 6],
        ..Default::default()
    })
    .unwrap();
    let h = block.support_radius;
    let size = (64, 64);
    for narrow_band in [false, true] {
        let params = |budget: u64| {
            let mut p = PipelineParams {
                support_radius: Some(h),
                grid: pipeline::GridParams {
                    memory_budget: budget,
                    narrow_band,
                    ..Default::default()
                },
                ..Default::default()
            };
            p.scene.optics.image_size = [size.0, size.1];
            // a small virtual screen and caustics map (see `column_setup`)
            p.scene.optics.caustics_resolution = Some([32, 32]);
            p.scene.optics.map_resolution = Some([64, 64]);
            p
        };
        let format = wgpu::TextureFormat::Rgba8Unorm;
        let mut gpu =
            GpuPipeline::new(&ctx.device, &ctx.queue, format, size, &params(1 << 30)).unwrap();
        // the block, then the same with a NaN: refused, and the next frame works; no particles:
        // the pool without water; a lone particle: a drop
        let BadFrames {
            first,
            image,
            dry,
            lone_set: lone,
            lone: frame,
            drop,
            ..
        } = bad_frames(&ctx, &mut gpu, &block.particles);
        assert!(first.surfels_on_gpu && frame.surfels_on_gpu);
        let read = gpu.read_surfels(&ctx).unwrap().unwrap();
        println!(
            "a lone particle: {} surfels, {} pixels differ from the empty frame; the block {}",
            read.len(),
            covered(&drop, &dry),
            covered(&image, &dry)
        );
        let mut cpu = Pipeline::new(params(1 << 30)).unwrap();
        let on_cpu = cpu.frame_through(&lone, Through::Surfels).unwrap();
        assert!(!read.is_empty());
        assert_eq!(read.len(), on_cpu.surfels.unwrap().len());
        assert!(covered(&drop, &dry) > 0, "the lone drop is not drawn");
        // a budget the grid does not fit: coarsened, said, drawn
        let budget = 1 << 16;
        let mut tight =
            GpuPipeline::new(&ctx.device, &ctx.queue, format, size, &params(budget)).unwrap();
        let (frame, _) = tight.prepare_image(&ctx, &block.particles).unwrap();
        assert!(
            frame.warnings.iter().any(|w| w.contains("memory budget")),
            "{:?}",
            frame.warnings
        );
        assert!(tight.read_surfels(&ctx).unwrap().unwrap().len() > 10);
    }
}

/// The ray caster's spheres weighted on the GPU on bad frames (issue 37): a non-finite position
/// is a typed error and the next frame draws as before, an empty frame draws the empty pool, a
/// lone particle is drawn with the CPU's weight; no panic, no lost device.
#[test]
fn gpu_pipeline_weighs_the_spheres_of_bad_frames() {
    let Some(ctx) = gpu::context_or_skip("gpu_pipeline_weighs_the_spheres_of_bad_frames").unwrap()
    else {
        return;
    };
    let block = scenes::block(&scenes::BlockParams {
        counts: [6, 6, 6],
        ..Default::default()
    })
    .unwrap();
    let size = (32, 32);
    let mut params = PipelineParams {
        support_radius: Some(block.support_radius),
        renderer: pipeline::Renderer::RayCast,
        ..Default::default()
    };
    params.scene.optics.image_size = [size.0, size.1];
    params.scene.optics.caustics_resolution = Some([32, 32]);
    params.scene.optics.map_resolution = Some([64, 64]);
    let format = wgpu::TextureFormat::Rgba8Unorm;
    let mut gpu = GpuPipeline::new(&ctx.device, &ctx.queue, format, size, &params).unwrap();
    assert!(gpu.weights_on_gpu());
    let BadFrames {
        first,
        empty,
        dry,
        lone_set: lone,
        lone: frame,
        drop,
        ..
    } = bad_frames(&ctx, &mut gpu, &block.particles);
    assert!(first.weights_on_gpu && !first.render_surfels.is_empty());
    assert!(!empty.weights_on_gpu);
    let covered = covered(&drop, &dry);
    let weights = gpu.read_sphere_weights(&ctx).unwrap().unwrap();
    let mut cpu = Pipeline::new(params.clone()).unwrap();
    let on_cpu = cpu.frame_through(&lone, Through::Surfels).unwrap();
    println!(
        "a lone particle: {} sphere(s), weights {weights:?} (the CPU's {:?}), {covered} pixels differ from the empty frame",
        frame.render_surfels.len(),
        on_cpu.render_weights
    );
    assert_eq!(weights.len(), frame.render_surfels.len());
    let (worst, extra, missing, _) = weights_by_position(
        (&frame.render_surfels, &weights),
        (&on_cpu.render_surfels, &on_cpu.render_weights),
    );
    assert!(worst <= 1e-5, "weights {worst}");
    assert!(
        extra == 0 && missing == 0,
        "kept: {extra} extra, {missing} missing"
    );
    assert!(covered > 0, "the lone drop is not drawn");
}

/// A sparse grid on the GPU whose body grows at once (issue 37): the values are sized from a
/// count read back a few frames late only while the frames are like the counted one; a frame
/// with many more points is sized from the bound, so none of its blocks is left out (the
/// surfels are the CPU's) and no frame warns of an overflow; the surfel buffer's size scales
/// with the points too. Seen to fail: with the late count used whatever the frame, the large
/// body's first frame had 8,150 of the CPU's 29,862 surfels (blocks left empty); with the
/// surfel buffer sized from the small body's count, 26,400.
#[test]
fn gpu_sparse_grid_meets_a_body_that_grows_at_once() {
    let Some(ctx) =
        gpu::context_or_skip("gpu_sparse_grid_meets_a_body_that_grows_at_once").unwrap()
    else {
        return;
    };
    let body = |counts: [u32; 3]| {
        scenes::block(&scenes::BlockParams {
            counts,
            ..Default::default()
        })
        .unwrap()
    };
    let (small, large) = (body([5, 4, 5]), body([20, 4, 20]));
    let h = small.support_radius;
    let mut params = PipelineParams {
        support_radius: Some(h),
        ..Default::default()
    };
    params.grid.narrow_band = true;
    params.scene.optics.image_size = [48, 48];
    let mut gpu = unorm_pipeline(&ctx, (48, 48), &params);
    let mut cpu = Pipeline::new(params).unwrap();
    // the small body until its count has come back (each frame here waits on its image)
    for _ in 0..3 {
        let (frame, _) = gpu.prepare_image(&ctx, &small.particles).unwrap();
        assert!(
            frame
                .warnings
                .iter()
                .all(|w| !w.contains("evaluated blocks"))
        );
    }
    for n in 0..2 {
        let (frame, _) = gpu.prepare_image(&ctx, &large.particles).unwrap();
        assert!(
            frame
                .warnings
                .iter()
                .all(|w| !w.contains("evaluated blocks")),
            "frame {n} of the large body: {:?}",
            frame.warnings
        );
        let on_gpu = gpu.read_surfels(&ctx).unwrap().unwrap();
        let on_cpu = cpu
            .frame_through(&large.particles, Through::Surfels)
            .unwrap()
            .surfels
            .unwrap();
        println!(
            "the large body, frame {n}: {} GPU surfels, {} CPU",
            on_gpu.len(),
            on_cpu.len()
        );
        assert!(
            (on_gpu.len() as f64 - on_cpu.len() as f64).abs() <= 1e-3 * on_cpu.len() as f64,
            "{} GPU against {} CPU surfels",
            on_gpu.len(),
            on_cpu.len()
        );
    }
}

/// `GpuPipeline` with the grid and surfels on the GPU draws the real files as the CPU
/// `Pipeline` does (issue 37), with the dense grid and the sparse one (`grid.narrow_band`: the
/// blocks chosen on the CPU, filled on the GPU, in less memory): both fit their views to the particles' box (`Frame::shape`), so
/// the automatic camera, pool and light's screen are the same; the surfels the same within 0.1 %
/// in count, each within 1e-3 cells and 1 degree of a CPU one; the finished frame at least 40 dB
/// from the CPU's (measured 57.3 dB on the dam break and 65.6 dB on the double dam break at
/// 160x120 with the caustics at half the default sides; 53.6 and 58.5 dB at 480x360 with the
/// defaults). Likewise the raw particles with `calibration = "volume"` (weights from the CPU;
/// measured equal counts, 65.0 dB).
#[test]
fn gpu_pipeline_on_the_gpu_draws_the_real_files_as_the_cpu() {
    let Some(ctx) = gpu::context_or_skip("gpu_pipeline_on_the_gpu_draws_the_real_files").unwrap()
    else {
        return;
    };
    let size = (160, 120);
    let mut dense = PipelineParams::default();
    dense.scene.optics.image_size = [size.0, size.1];
    // a virtual screen and caustics map of half the default sides: a quarter of the caustics'
    // work on both sides of the comparison (lavapipe's and the debug build's time; the light's
    // footprint counts in the detail from the view, so the levels may be coarser too): the
    // test 79 -> 15 s alone
    dense.scene.optics.caustics_resolution = Some([128, 128]);
    dense.scene.optics.map_resolution = Some([256, 256]);
    let mut sparse = dense.clone();
    sparse.grid.narrow_band = true;
    // the raw particles weighted by their SPH volumes (splashsurf's field), weights from the CPU
    let mut volume = dense.clone();
    volume.source = pipeline::SurfelSource::Particles;
    volume.grid.calibration = pipeline::Calibration::Volume;
    let mut bytes = Vec::new();
    for (name, params) in [
        ("dam_break_frame_23_24389_particles.bgeo", &dense),
        ("dam_break_frame_23_24389_particles.bgeo", &sparse),
        ("double_dam_break_frame_26_4732_particles.vtk", &dense),
        ("double_dam_break_frame_26_4732_particles.vtk", &sparse),
        ("double_dam_break_frame_26_4732_particles.vtk", &volume),
    ] {
        let grid = if params.grid.narrow_band {
            "sparse"
        } else if params.grid.calibration == pipeline::Calibration::Volume {
            "dense, volume calibration"
        } else {
            "dense"
        };
        let particles = fluid_surfels::io::read_particles(
            &std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
                .join("tests/data")
                .join(name),
            None,
        )
        .unwrap();
        let mut gpu = unorm_pipeline(&ctx, size, params);
        let (frame, image) = gpu.prepare_image(&ctx, &particles).unwrap();
        bytes.push(gpu.gpu_grid_bytes().unwrap());
        let mut cpu = Pipeline::new(params.clone()).unwrap();
        cpu.keep_hidden_surfels(true);
        let cpu_frame = cpu.frame(&particles).unwrap();
        assert_eq!(frame.shape, cpu_frame.shape, "{name}: the views' shape");
        let read = gpu.read_surfels(&ctx).unwrap().unwrap();
        let cpu_surfels = cpu_frame.surfels.as_ref().unwrap();
        let (on_gpu, on_cpu) = (read.len(), cpu_surfels.len());
        let (worst, angle) = nearest_cpu_surfels(cpu_surfels, &read, cpu_frame.detail.cell);
        let db = splat::psnr(&cpu_frame.finished.as_ref().unwrap().image, &image);
        println!(
            "{name}, {grid} grid ({:.1} MiB on the GPU): {on_gpu} surfels on the GPU, {on_cpu} on the CPU, worst {worst:.2e} cells and {angle:.3} degrees; finished frame {db:.1} dB",
            *bytes.last().unwrap() as f64 / f64::from(1 << 20)
        );
        assert!(
            worst <= 1e-3,
            "{name}: a GPU surfel {worst} cells from the CPU's"
        );
        assert!(
            angle <= 1.0,
            "{name}: a GPU normal {angle} degrees from the CPU's"
        );
        assert!(
            (on_gpu as f64 - on_cpu as f64).abs() <= 1e-3 * on_cpu as f64,
            "{name}: {on_gpu} against {on_cpu} surfels"
        );
        assert!(db >= 40.0, "{name}: {db:.1} dB");
    }
    // the sparse grid holds less than the dense one on the GPU
    assert!(
        bytes[1] < bytes[0] && bytes[3] < bytes[2],
        "grid bytes dense, sparse: {bytes:?}"
    );
}

/// The boundary calibration's factors found on the GPU (`boundary_factors_gpu`: which particles
/// form a sheet one particle thick and its normal, each particle's interior share, how much of
/// each sheet point is kept) and the weights solved after them, against the CPU's
/// (`boundary_factors`, `chain_input_at_boundary` then its solve), point by point: the chain at
/// two steps and the raw-particle source on the double dam break (whose floor is a sheet one
/// particle thick), and a slab of two layers beside a layer of one and a lone particle.
#[test]
fn gpu_boundary_factors_equal_the_cpus() {
    use fluid_surfels::pipeline::SurfelSource;
    use fluid_surfels::pipeline::boundary::{self, Sheet};
    use fluid_surfels::surface::ParticleClass;
    use glam::Vec3;
    let Some(ctx) = gpu::context_or_skip("gpu_boundary_factors_equal_the_cpus").unwrap() else {
        return;
    };
    let mut slab = Vec::new();
    for i in 0..14 {
        for j in 0..14 {
            for k in 0..2 {
                slab.push(Vec3::new(i as f32, k as f32, j as f32) * 0.1);
            }
            slab.push(Vec3::new(i as f32 * 0.1 + 2.0, 0.0, j as f32 * 0.1));
        }
    }
    slab.push(Vec3::new(5.0, 1.0, 0.0));
    let mut checked_thin = 0;
    for (name, positions, source) in [
        (
            "double dam break, chain",
            double_dam_break(),
            SurfelSource::Chain,
        ),
        (
            "double dam break, particles",
            double_dam_break(),
            SurfelSource::Particles,
        ),
        ("slabs of two and one layers", slab, SurfelSource::Chain),
    ] {
        let set = fluid_surfels::ParticleSet::from_positions(positions);
        let mut params = PipelineParams {
            detail: pipeline::Detail::Fixed,
            ..Default::default()
        };
        params.refine.steps = 2;
        let frame = Pipeline::new(params.clone())
            .unwrap()
            .frame_through(&set, Through::Refine)
            .unwrap();
        let h = frame.radius;
        let (kernel, tau) = (params.grid.kernel, 0.75 * params.grid.kernel.peak(h));
        let outer = boundary::OwnedSheet::of_particles(&set.positions, &frame.surface, h);
        let sheet = match source {
            SurfelSource::Particles => outer.sheet(),
            _ => Sheet::refined(frame.refined.as_ref().unwrap()),
        };
        let cpu = boundary::boundary_factors(&set.positions, &frame.surface, sheet, h).unwrap();
        let gpu = boundary::gpu::boundary_factors_gpu(
            &ctx,
            &set.positions,
            &frame.surface,
            sheet,
            h,
            kernel,
            tau,
        )
        .unwrap();
        // the trimmed search of the sheet's bins leaves out exact zeros only: the same as
        // reading every bin whole, bit for bit
        let whole = boundary::gpu::boundary_factors_gpu_searching(
            &ctx,
            (&set.positions, &frame.surface, sheet),
            (h, kernel, tau),
            boundary::gpu::BinSearch::Whole,
        )
        .unwrap();
        same_bits(gpu.split.as_flattened(), whole.split.as_flattened(), name);
        same_bits(&gpu.weights, &whole.weights, name);
        let n = set.len();
        assert_eq!(gpu.split.len(), n + sheet.positions.len());
        // the factors, point by point
        let mut worst = [0.0f32; 3];
        let mut worst_angle = 0.0f32;
        let mut thin = 0;
        for i in 0..n {
            let share = cpu.thin[i].map_or(0.0, |(_, s)| s);
            worst[0] = worst[0].max((share - gpu.split[i][1]).abs());
            worst[1] = worst[1].max((cpu.inner[i] - gpu.split[i][0]).abs());
            if let Some((normal, s)) = cpu.thin[i]
                && s > 1e-3
                && gpu.split[i][1] > 1e-3
            {
                thin += 1;
                worst_angle = worst_angle.max(normal.angle_between(gpu.thin_normals[i]));
            }
        }
        for (j, kept) in cpu.kept.iter().enumerate() {
            worst[2] = worst[2].max((kept - gpu.split[n + j][1]).abs());
        }
        // the weights in the density: the CPU's compacted points mapped back to the particles
        // and the sheet
        let solved = boundary::chain_input_at_boundary(&set.positions, &frame.surface, sheet, h)
            .unwrap()
            .solve(h, kernel, tau)
            .unwrap()
            .weights;
        let mut expected = vec![0.0f32; n + sheet.positions.len()];
        let mut k = 0;
        for (i, &inner) in cpu.inner.iter().enumerate() {
            if inner > 0.0 {
                expected[i] += solved[k];
                k += 1;
            }
        }
        for (i, t) in cpu.thin.iter().enumerate() {
            if t.is_some() {
                expected[i] += solved[k];
                k += 1;
            }
        }
        for (j, &kept) in cpu.kept.iter().enumerate() {
            if kept > 0.0 {
                expected[n + j] = solved[k];
                k += 1;
            }
        }
        assert_eq!(k, solved.len());
        let worst_weight = expected
            .iter()
            .zip(&gpu.weights)
            .map(|(a, b)| (a - b).abs() / a.abs().max(1.0))
            .fold(0.0f32, f32::max);
        let classes = [
            ParticleClass::Interior,
            ParticleClass::Surface,
            ParticleClass::Isolated,
        ]
        .map(|c| frame.surface.classes.iter().filter(|&&k| k == c).count());
        println!(
            "{name}: {n} particles {classes:?}, {} sheet points, {thin} in a thin sheet; GPU within {:.1e} (shares), {:.1e} (interior), {:.1e} (kept), {:.1e} rad (normals), {worst_weight:.1e} (weights) of the CPU's",
            sheet.positions.len(),
            worst[0],
            worst[1],
            worst[2],
            worst_angle
        );
        checked_thin += thin;
        for (what, w) in ["shares", "interior shares", "kept"].iter().zip(worst) {
            assert!(w < 1e-3, "{name}: {what} {w}");
        }
        assert!(worst_angle < 1e-3, "{name}: {worst_angle} rad");
        assert!(worst_weight < 1e-3, "{name}: weights {worst_weight}");
    }
    assert!(
        checked_thin > 100,
        "{checked_thin} particles in thin sheets"
    );
}

/// The boundary calibration's weights on the GPU (`pipeline::boundary::gpu`) against the CPU's
/// (`pipeline::boundary_weights`): the double dam break's chain (its interior particles and its
/// refined points at two steps with their kernel radii and normals) and a wavy sheet of two
/// radii over a block with lone points beside it, for both kernels.
#[test]
fn gpu_boundary_weights_equal_the_cpus() {
    use fluid_surfels::surface::ParticleClass;
    use glam::Vec3;
    let Some(ctx) = gpu::context_or_skip("gpu_boundary_weights_equal_the_cpus").unwrap() else {
        return;
    };
    // (name, positions, radii, interior, normals, spacing, h)
    let mut cases = Vec::new();
    let set = fluid_surfels::ParticleSet::from_positions(double_dam_break());
    let mut params = PipelineParams {
        detail: pipeline::Detail::Fixed,
        ..Default::default()
    };
    // two steps: a quarter of three steps' points, as many cases (lavapipe's time)
    params.refine.steps = 2;
    let frame = Pipeline::new(params)
        .unwrap()
        .frame_through(&set, Through::Refine)
        .unwrap();
    let h = frame.radius;
    let r = frame.refined.as_ref().unwrap();
    let mut positions: Vec<Vec3> = (0..set.len())
        .filter(|&i| frame.surface.classes[i] == ParticleClass::Interior)
        .map(|i| set.positions[i])
        .collect();
    let interior = positions.len();
    let mut radii = vec![h; interior];
    positions.extend(&r.positions);
    radii.extend(&r.kernel_radii);
    cases.push((
        "double dam break",
        positions,
        radii,
        interior,
        r.normals.clone(),
        0.5 * h,
        h,
    ));
    let s = 0.1f32;
    let (mut positions, mut radii, mut normals) = (Vec::new(), Vec::new(), Vec::new());
    for i in 0..12 {
        for j in 0..12 {
            for k in 0..4 {
                positions.push(Vec3::new(i as f32, -(k as f32) - 1.0, j as f32) * s);
                radii.push(2.0 * s);
            }
        }
    }
    let interior = positions.len();
    for i in 0..40 {
        for j in 0..40 {
            let (x, z) = (i as f32 * 0.3 * s, j as f32 * 0.3 * s);
            positions.push(Vec3::new(x, -0.5 * s + 0.05 * s * (7.0 * x).sin(), z));
            radii.push(if i < 20 { 0.6 * s } else { 0.35 * s });
            normals.push(Vec3::new(-0.05 * (7.0 * x).cos(), 1.0, 0.0).normalize());
        }
    }
    for i in 0..3 {
        positions.push(Vec3::new(0.5 + 0.1 * i as f32, 0.3, 0.0));
        radii.push(0.6 * s);
        normals.push(if i == 0 { Vec3::ZERO } else { Vec3::Y });
    }
    cases.push((
        "wavy sheet",
        positions,
        radii,
        interior,
        normals,
        s,
        2.0 * s,
    ));
    for (name, positions, radii, interior, normals, spacing, h) in &cases {
        for kernel in [Kernel::Wyvill, Kernel::CubicSpline] {
            let points = Points::with_radii(positions, radii, *h);
            let tau = 0.75 * kernel.peak(*h);
            let cpu = pipeline::boundary_weights(points, *interior, normals, *spacing, kernel, tau)
                .unwrap();
            let gpu = pipeline::boundary::gpu::boundary_weights_gpu(
                &ctx, points, *interior, normals, *spacing, kernel, tau,
            )
            .unwrap();
            let whole = pipeline::boundary::gpu::boundary_weights_gpu_searching(
                &ctx,
                points,
                (*interior, normals),
                (*spacing, kernel, tau),
                pipeline::boundary::gpu::BinSearch::Whole,
            )
            .unwrap();
            same_bits(&gpu, &whole, name);
            assert_eq!(cpu.len(), gpu.len());
            assert_eq!(cpu[..*interior], gpu[..*interior], "{name}: the interior's");
            let worst = cpu
                .iter()
                .zip(&gpu)
                .map(|(a, b)| (a - b).abs() / a.abs().max(1.0))
                .fold(0.0f32, f32::max);
            let solved = cpu[*interior..].iter().filter(|&&w| w != 1.0).count();
            println!(
                "{name} ({kernel:?}): {} sheet weights ({solved} not 1), GPU within {worst:.2e} of the CPU's",
                cpu.len() - interior
            );
            assert!(solved > 0, "{name}: nothing solved");
            // measured: 4.5e-7 and 5.1e-7 on the double dam break, 1.6e-6 and 0 on the
            // sheet (6.6e-6 at three steps): the sums' order differs, not their terms
            assert!(worst < 1e-4, "{name} ({kernel:?}): {worst}");
        }
    }
}

/// The points sorted by bin on the GPU (`density::bins::GpuBinSort`, in the frame's encoder)
/// are the CPU's (`bin_particles`), bit for bit and in the same order within each bin, with the
/// same bins' starts: on the double dam break's chain points at two steps (particles first,
/// then the sheet: the particles must lead each bin), on points in one bin, on bins of more
/// than 2^16 (three radix passes), on no point, and again on the same sort's buffers after a
/// larger frame (nothing made anew).
#[test]
fn gpu_bin_sort_equals_the_cpus() {
    use density::bins::{BinLayout, GpuBinSort, bin_particles};
    use glam::Vec3;
    let Some(ctx) = gpu::context_or_skip("gpu_bin_sort_equals_the_cpus").unwrap() else {
        return;
    };
    let (chain, radii, h) = chain_like_points();
    let particles = double_dam_break();
    let mut ddb: Vec<Vec3> = particles.clone();
    ddb.extend(chain.iter().map(|&p| p * 0.2 + Vec3::splat(0.1)));
    let mut ddb_radii = vec![0.025; particles.len()];
    ddb_radii.extend(radii.iter().map(|r| r * 0.2));
    // a pseudo-random cloud over many small bins (keys above 2^16)
    let mut seed = 12345u32;
    let mut next = || {
        seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
        (seed >> 8) as f32 / (1u32 << 24) as f32
    };
    let cloud: Vec<Vec3> = (0..40_000)
        .map(|_| Vec3::new(next(), next(), next()))
        .collect();
    let cases: Vec<(&str, Vec<Vec3>, Vec<f32>, f32)> = vec![
        (
            "double dam break and a sheet",
            ddb.clone(),
            ddb_radii,
            0.025,
        ),
        ("chain-like points", chain.clone(), radii.clone(), h),
        (
            "coincident points",
            vec![Vec3::splat(0.5); 700],
            vec![1.0; 700],
            1.0,
        ),
        (
            "a cloud of 2^18 bins",
            cloud.clone(),
            vec![0.008; cloud.len()],
            0.008,
        ),
        ("no point", Vec::new(), Vec::new(), 0.1),
    ];
    let mut sort = GpuBinSort::new(&ctx.device);
    let mut passes_seen = std::collections::BTreeSet::new();
    for round in 0..2 {
        for (name, positions, radii, h) in &cases {
            let points = density::Points::with_radii(positions, radii, *h);
            let spec = density::GridSpec::around(
                positions,
                2.0 * h,
                density::Resolution::CellSize(0.5 * h),
            )
            .unwrap_or(density::GridSpec {
                origin: Vec3::ZERO,
                spacing: 0.1,
                dims: [4, 4, 4],
            });
            let layout = BinLayout::of(&points, &spec);
            let raw = fluid_surfels::density::gpu::raw_points(&points);
            let (cpu_sorted, cpu_starts) = bin_particles(&raw, &layout);
            let mut encoder = ctx.device.create_command_encoder(&Default::default());
            sort.record(&ctx, &mut encoder, &raw, &layout).unwrap();
            ctx.queue.submit([encoder.finish()]);
            if round == 1 {
                assert_eq!(sort.created(), 0, "{name}: buffers made again");
            }
            let starts: Vec<u32> = gpu::read_buffer(&ctx, sort.starts()).unwrap();
            assert_eq!(starts[..cpu_starts.len()], cpu_starts[..], "{name}: starts");
            let sorted: Vec<density::gpu::RawPoint> =
                gpu::read_buffer(&ctx, sort.sorted()).unwrap();
            let bits = |p: &[density::gpu::RawPoint]| -> Vec<u32> {
                bytemuck::cast_slice::<_, u32>(p).to_vec()
            };
            assert!(
                bits(&sorted[..cpu_sorted.len()]) == bits(&cpu_sorted),
                "{name}: the sorted points differ"
            );
            // the particles lead every bin (the index order kept within bins)
            for b in cpu_starts.windows(2) {
                let idx: Vec<u32> = cpu_sorted[b[0] as usize..b[1] as usize]
                    .iter()
                    .map(|p| p._pad[0].to_bits())
                    .collect();
                assert!(idx.is_sorted(), "{name}: a bin out of order");
            }
            passes_seen.insert(
                layout
                    .total()
                    .next_power_of_two()
                    .trailing_zeros()
                    .div_ceil(8),
            );
            if round == 0 {
                println!(
                    "{name}: {} points in {} bins, equal",
                    positions.len(),
                    layout.total()
                );
            }
        }
    }
    assert!(
        passes_seen.contains(&3) && passes_seen.len() >= 2,
        "radix passes covered: {passes_seen:?}"
    );
}

/// A storage buffer of `spheres` (centre and radius each; one unread sphere when there is none:
/// a binding is never empty).
fn spheres_buffer(ctx: &gpu::GpuContext, spheres: &[[f32; 4]]) -> wgpu::Buffer {
    let one = [[0.0f32; 4]];
    let contents = if spheres.is_empty() {
        &one[..]
    } else {
        spheres
    };
    wgpu::util::DeviceExt::create_buffer_init(
        &ctx.device,
        &wgpu::util::BufferInitDescriptor {
            label: Some("spheres"),
            contents: bytemuck::cast_slice(contents),
            usage: wgpu::BufferUsages::STORAGE,
        },
    )
}

/// The spheres' (tile, sphere) pairs in sphere order, as `view::bin`'s tiles hold them.
fn pairs_in_sphere_order(tiles: &[Vec<u32>]) -> Vec<(u32, u32)> {
    let mut pairs: Vec<(u32, u32)> = tiles
        .iter()
        .enumerate()
        .flat_map(|(t, items)| items.iter().map(move |&j| (j, t as u32)))
        .collect();
    pairs.sort_unstable();
    pairs.into_iter().map(|(j, t)| (t, j)).collect()
}

#[test]
fn gpu_tiles_equal_the_cpus() {
    use fluid_surfels::view::gpu::GpuTiles;
    use fluid_surfels::view::{self, Camera, Light, View};
    use glam::Vec3;
    let Some(ctx) = gpu::context_or_skip("gpu_tiles_equal_the_cpus").unwrap() else {
        return;
    };
    let (chain, radii, _) = chain_like_points();
    let ddb = double_dam_break();
    let params = splat::SplatParams::default();
    let camera = |eye: Vec3, target: Vec3| Camera {
        eye,
        target,
        ..Default::default()
    };
    let perspective =
        |c: &Camera, (w, h): (u32, u32)| View::new(c, &Light::default(), &params, w, h).unwrap();
    let centre = mean(&chain);
    let ddb_centre = mean(&ddb);
    let ortho = View::window(
        ddb_centre + Vec3::new(0.3, 2.0, 0.1),
        Vec3::NEG_Y,
        Vec3::Z,
        glam::Vec2::new(0.6, 0.45),
        true,
        0.01,
        10.0,
        &params,
        200,
        150,
    )
    .unwrap();
    let chain_spheres: Vec<(Vec3, f32)> =
        chain.iter().copied().zip(radii.iter().copied()).collect();
    let ddb_spheres: Vec<(Vec3, f32)> = ddb.iter().map(|&p| (p, 0.025)).collect();
    // (name, view, spheres)
    type Case<'a> = (&'a str, View, &'a [(Vec3, f32)]);
    let cases: Vec<Case<'_>> = vec![
        (
            "the chain's points, 1920x1080 (2 radix passes)",
            perspective(
                &camera(centre + Vec3::new(0.4, 0.3, 1.2), centre),
                (1920, 1080),
            ),
            &chain_spheres,
        ),
        (
            "the chain's points, 64x48 (1 radix pass)",
            perspective(&camera(centre + Vec3::new(0.4, 0.3, 1.2), centre), (64, 48)),
            &chain_spheres,
        ),
        (
            "the double dam break, 320x240",
            perspective(
                &camera(ddb_centre + Vec3::new(0.8, 0.9, 1.5), ddb_centre),
                (320, 240),
            ),
            &ddb_spheres,
        ),
        (
            "the eye among the spheres (whole-screen spheres), 160x120",
            perspective(&camera(centre, centre + Vec3::X), (160, 120)),
            &chain_spheres,
        ),
        ("an orthographic view, 200x150", ortho, &ddb_spheres),
        (
            "no sphere",
            perspective(&camera(centre + Vec3::Z, centre), (96, 96)),
            &[],
        ),
    ];
    let mut tiles = GpuTiles::new(&ctx.device);
    for round in 0..2 {
        for (name, v, spheres) in &cases {
            let (tw, cpu) = view::bin(v, spheres.len(), |j| spheres[j]).unwrap();
            let pairs = pairs_in_sphere_order(&cpu);
            let raw: Vec<[f32; 4]> = spheres.iter().map(|(c, r)| [c.x, c.y, c.z, *r]).collect();
            // the second round reads them as the chain's binned points do (`RawPoint`: two
            // vec4s a point, its centre and radius first): a stride of 2
            let (buffer, stride) = if round == 0 {
                (spheres_buffer(&ctx, &raw), 1)
            } else {
                let points: Vec<[f32; 4]> = raw
                    .iter()
                    .flat_map(|&s| [s, [1.0, 0.0, 0.0, 0.0]])
                    .collect();
                (spheres_buffer(&ctx, &points), 2)
            };
            // all the pairs, then (the first round) room for a third of them
            for capacity in [pairs.len() as u32 + 7, (pairs.len() / 3) as u32] {
                if round == 1 && capacity < pairs.len() as u32 {
                    continue;
                }
                let mut encoder = ctx.device.create_command_encoder(&Default::default());
                tiles
                    .record(
                        &ctx,
                        &mut encoder,
                        v,
                        (&buffer, spheres.len() as u32, stride),
                        capacity,
                    )
                    .unwrap();
                ctx.queue.submit([encoder.finish()]);
                let (gpu_tw, gpu) = tiles.read(&ctx).unwrap();
                assert_eq!(gpu_tw, tw, "{name}: tiles along x");
                // the first `capacity` pairs in sphere order, by tile
                let mut expected = vec![Vec::new(); cpu.len()];
                for &(t, j) in pairs.iter().take(capacity.max(1) as usize) {
                    expected[t as usize].push(j);
                }
                let differing = (0..cpu.len()).filter(|&t| gpu[t] != expected[t]).count();
                assert_eq!(
                    differing,
                    0,
                    "{name}, room for {capacity} of {} pairs: {differing} tiles differ",
                    pairs.len()
                );
                let stats = tiles.read_stats(&ctx).unwrap();
                let fragments: u64 = spheres
                    .iter()
                    .filter_map(|&(c, r)| view::sphere_rect(v, c, r))
                    .map(|[x0, x1, y0, y1]| ((x1 - x0) * (y1 - y0)) as u64)
                    .sum();
                assert_eq!(
                    stats.requested as usize,
                    pairs.len(),
                    "{name}: pairs requested"
                );
                assert_eq!(stats.fragments, fragments, "{name}: fragments");
                let most = expected.iter().map(Vec::len).max().unwrap_or(0);
                assert_eq!(
                    stats.most_in_tile as usize, most,
                    "{name}: the longest tile"
                );
                if round == 0 {
                    println!(
                        "{name}: {} spheres, {} of {} pairs in {} tiles, equal",
                        spheres.len(),
                        pairs.len().min(capacity as usize),
                        pairs.len(),
                        cpu.len()
                    );
                }
            }
            if round == 1 {
                // a new spheres buffer each case: its bind groups made again, nothing else
                assert!(tiles.created() <= 1, "{name}: buffers made again");
            }
        }
    }
}

#[test]
fn gpu_tiles_are_sized_from_late_counts_of_the_same_view() {
    use fluid_surfels::view::gpu::GpuTiles;
    use fluid_surfels::view::{self, View};
    use glam::Vec3;
    let Some(ctx) =
        gpu::context_or_skip("gpu_tiles_are_sized_from_late_counts_of_the_same_view").unwrap()
    else {
        return;
    };
    let ddb = double_dam_break();
    let centre = mean(&ddb);
    let far = camera_view(centre + Vec3::new(0.8, 0.9, 1.5), centre);
    let near = camera_view(centre + Vec3::new(0.4, 0.45, 0.75), centre);
    let mut tiles = GpuTiles::new(&ctx.device);
    // (frame, view, spheres' radius): the same view and spheres, then the spheres grown to
    // twice the radius under the same view (more pairs than the room), then another view
    let frames: Vec<(&View, f32)> = (0..6)
        .map(|_| (&far, 0.025))
        .chain((0..4).map(|_| (&far, 0.05)))
        .chain((0..2).map(|_| (&near, 0.05)))
        .collect();
    let mut log = Vec::new();
    for (f, (v, r)) in frames.iter().enumerate() {
        let spheres: Vec<[f32; 4]> = ddb.iter().map(|p| [p.x, p.y, p.z, *r]).collect();
        let buffer = spheres_buffer(&ctx, &spheres);
        let sphere = |j: usize| (Vec3::from_slice(&spheres[j][..3]), spheres[j][3]);
        let (room, _) = tiles.plan(v, spheres.len(), sphere).unwrap();
        let mut encoder = ctx.device.create_command_encoder(&Default::default());
        tiles
            .record(
                &ctx,
                &mut encoder,
                v,
                (&buffer, spheres.len() as u32, 1),
                room,
            )
            .unwrap();
        ctx.queue.submit([encoder.finish()]);
        tiles.after_submit();
        let (_, cpu) = view::bin(v, spheres.len(), sphere).unwrap();
        let (_, gpu) = tiles.read(&ctx).unwrap();
        let whole = gpu == cpu;
        log.push((f, tiles.planned_on_cpu(), room, whole));
        println!(
            "frame {f}: radius {r}, counted on the CPU: {}, room {room}, pairs {}, whole: {whole}",
            tiles.planned_on_cpu(),
            cpu.iter().map(Vec::len).sum::<usize>()
        );
    }
    // the first frame counts; the next like ones are sized from the statistics once back
    assert!(log[0].1 && log[0].3, "{log:?}");
    assert!(
        log[1..6].iter().any(|l| !l.1),
        "no frame sized late: {log:?}"
    );
    assert!(
        log[..6].iter().all(|l| l.3),
        "a like frame lost pairs: {log:?}"
    );
    // the grown spheres: the first is sized from the old statistics (the view is the same) and
    // may lose pairs; once the statistics of a short frame are back, the next frame is counted
    // and whole again
    assert!(!log[6].1, "the first grown frame counted: {log:?}");
    let short = log[6..10].iter().position(|l| !l.3);
    if let Some(s) = short {
        let recounted = log[6 + s + 1..10].iter().position(|l| l.1);
        assert!(recounted.is_some(), "never counted again: {log:?}");
        let after = 6 + s + 1 + recounted.unwrap();
        assert!(
            log[after..10].iter().all(|l| l.3),
            "short after the count: {log:?}"
        );
    }
    assert!(
        log[9].3,
        "the last frame of the grown spheres short: {log:?}"
    );
    // another view counts at once
    assert!(log[10].1 && log[10].3, "{log:?}");
}

/// A 320x240 camera's view from `eye` looking at `target` (the splats' default parameters and
/// light): the tiles tests' moving and still cameras.
fn camera_view(eye: glam::Vec3, target: glam::Vec3) -> fluid_surfels::view::View {
    use fluid_surfels::view::{Camera, Light, View};
    let camera = Camera {
        eye,
        target,
        ..Default::default()
    };
    View::new(
        &camera,
        &Light::default(),
        &splat::SplatParams::default(),
        320,
        240,
    )
    .unwrap()
}

/// Bins `spheres` into the tiles of each of `views` in turn, one frame each, with one
/// `GpuTiles` (planned, recorded, submitted and its statistics let come back, as a game's frames
/// do), against the CPU's `view::bin`: per frame its index, whether it was counted on the CPU,
/// whether it held every pair item for item, and whether its longest tile lies within half again
/// of the one planned.
fn bin_views(
    ctx: &gpu::GpuContext,
    spheres: &[[f32; 4]],
    views: impl Iterator<Item = fluid_surfels::view::View>,
) -> Vec<(usize, bool, bool, bool)> {
    use fluid_surfels::view::{self, gpu::GpuTiles};
    let buffer = spheres_buffer(ctx, spheres);
    let sphere = |j: usize| (glam::Vec3::from_slice(&spheres[j][..3]), spheres[j][3]);
    let mut tiles = GpuTiles::new(&ctx.device);
    let mut log = Vec::new();
    for (f, v) in views.enumerate() {
        let (room, most) = tiles.plan(&v, spheres.len(), sphere).unwrap();
        let mut encoder = ctx.device.create_command_encoder(&Default::default());
        tiles
            .record(
                ctx,
                &mut encoder,
                &v,
                (&buffer, spheres.len() as u32, 1),
                room,
            )
            .unwrap();
        ctx.queue.submit([encoder.finish()]);
        tiles.after_submit();
        let (_, cpu) = view::bin(&v, spheres.len(), sphere).unwrap();
        let (_, gpu) = tiles.read(ctx).unwrap();
        let pairs: usize = cpu.iter().map(Vec::len).sum();
        let longest = cpu.iter().map(Vec::len).max().unwrap_or(0);
        println!(
            "frame {f}: counted on the CPU: {}, room {room} for {pairs} pairs, longest tile {longest} (planned {most})",
            tiles.planned_on_cpu()
        );
        log.push((
            f,
            tiles.planned_on_cpu(),
            gpu == cpu,
            longest <= most + most / 2,
        ));
    }
    log
}

/// The tiles of an orthographic view whose window follows the water from frame to frame (a
/// light's screen, fitted to each frame's water: it moves and resizes, so it is never the same
/// view twice) are sized from the statistics of the view before, scaled by how the pixel's
/// size changed (issue 37: the light's tiles were counted on the CPU every frame): after the
/// first frame none is counted on the CPU, and every frame holds all its pairs, item for item
/// the CPU's binning, and its longest tile within half again of the one planned (an estimate:
/// a window moved by part of a tile regroups the spheres, measured up to 10 % over the plan
/// of a nearly equal view, whose late size has no margin; the ray caster, which bounds its
/// iterations by it, adds half again to a late size), through
/// windows that drift, grow and shrink by up to 8 % a frame and then halve at once (the
/// spheres twice as large on the screen).
#[test]
fn gpu_tiles_of_a_moving_light_screen_are_sized_from_late_counts() {
    use fluid_surfels::view::View;
    use glam::{Vec2, Vec3};
    let Some(ctx) =
        gpu::context_or_skip("gpu_tiles_of_a_moving_light_screen_are_sized_from_late_counts")
            .unwrap()
    else {
        return;
    };
    let ddb = double_dam_break();
    let (lo, hi) = ddb
        .iter()
        .fold((Vec3::INFINITY, Vec3::NEG_INFINITY), |(a, b), &p| {
            (a.min(p), b.max(p))
        });
    let centre = 0.5 * (lo + hi);
    let extent = 0.6 * (hi - lo).max_element();
    let params = splat::SplatParams::default();
    let light = Vec3::new(0.2, 1.0, 0.3).normalize();
    let window = |shift: Vec3, scale: f32| {
        View::window(
            centre + shift + light * 3.0,
            -light,
            Vec3::Z,
            Vec2::splat(extent * scale),
            true,
            0.01,
            10.0,
            &params,
            186,
            256,
        )
        .unwrap()
    };
    // (shift, scale) per frame: drifting and breathing, then halved
    let frames: Vec<(Vec3, f32)> = (0..8)
        .map(|f| {
            let t = f as f32;
            (
                Vec3::new(0.02 * t, 0.0, -0.015 * t),
                1.0 + 0.08 * (t * 1.3).sin(),
            )
        })
        .chain((0..3).map(|_| (Vec3::ZERO, 0.5)))
        .collect();
    let spheres: Vec<[f32; 4]> = ddb.iter().map(|p| [p.x, p.y, p.z, 0.02]).collect();
    let log = bin_views(
        &ctx,
        &spheres,
        frames.iter().map(|&(shift, scale)| window(shift, scale)),
    );
    assert!(log[0].1, "{log:?}");
    assert!(
        log.iter().all(|l| l.2 && l.3),
        "a frame lost pairs or its longest tile: {log:?}"
    );
    // the statistics come back a few frames late: from then on, nothing counted on the CPU
    let first = log.iter().position(|l| l.0 > 0 && !l.1);
    assert!(first.is_some(), "never sized late: {log:?}");
    assert!(
        log[first.unwrap()..].iter().all(|l| !l.1),
        "counted again: {log:?}"
    );
}

/// The tiles of a moving perspective camera (a game's or a viewer's: it orbits, comes closer
/// and looks a little elsewhere every frame, so no two frames have the same view) are sized
/// from the statistics of a recent frame, scaled by how much nearer the spheres' box came and
/// how much more of it the screen shows (`Binned::scaled_perspective`; issue 37: such a camera's
/// tiles were counted on the CPU every frame, 3.3-4.4 ms of the column scene's): after the
/// first frame none is counted on the CPU until the camera cuts to another place, every frame
/// holds all its pairs, item for item the CPU's binning, and its longest tile within half again
/// of the one planned (the ray caster adds half again to a late size). A cut to a view far from
/// every recent one is counted on the CPU; after it the camera turns on and moves in among the
/// spheres, some behind the eye (its pairs 28,467 -> 53,766), sized late again.
#[test]
fn gpu_tiles_of_a_moving_camera_are_sized_from_late_counts() {
    use glam::Vec3;
    let Some(ctx) =
        gpu::context_or_skip("gpu_tiles_of_a_moving_camera_are_sized_from_late_counts").unwrap()
    else {
        return;
    };
    let ddb = double_dam_break();
    let centre = mean(&ddb);
    // frame f: the eye turning 1.5 degrees a frame around the water, 2 % nearer a frame, the
    // point looked at drifting sideways; frame 14 cuts to a view from the other side, close,
    // and from there the eye goes on turning and moves in among the spheres (some behind it)
    let view_at = |f: usize| {
        let (angle, distance, drift) = if f < 14 {
            let t = f as f32;
            (
                0.6 + t * 1.5f32.to_radians(),
                1.8 * 0.98f32.powi(f as i32),
                Vec3::new(0.01 * t, 0.0, -0.008 * t),
            )
        } else {
            let t = (f - 14) as f32;
            (
                3.8 + t * 1.5f32.to_radians(),
                0.9 * 0.9f32.powf(t),
                Vec3::ZERO,
            )
        };
        camera_view(
            centre + distance * Vec3::new(angle.cos(), 0.55, angle.sin()),
            centre + drift,
        )
    };
    let spheres: Vec<[f32; 4]> = ddb.iter().map(|p| [p.x, p.y, p.z, 0.02]).collect();
    let log = bin_views(&ctx, &spheres, (0..26).map(view_at));
    assert!(log[0].1, "{log:?}");
    assert!(
        log.iter().all(|l| l.2 && l.3),
        "a frame lost pairs or its longest tile: {log:?}"
    );
    let first = log.iter().position(|l| l.0 > 0 && !l.1);
    assert!(first.is_some(), "never sized late: {log:?}");
    assert!(
        log[first.unwrap()..14].iter().all(|l| !l.1),
        "counted again while the camera moved: {log:?}"
    );
    assert!(log[14].1, "the cut not counted: {log:?}");
    let again = log[15..].iter().position(|l| !l.1);
    assert!(again.is_some(), "never sized late after the cut: {log:?}");
    assert!(
        log[15 + again.unwrap()..].iter().all(|l| !l.1),
        "counted again after the cut: {log:?}"
    );
}
