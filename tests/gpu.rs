//! GPU stages against their CPU specification (on lavapipe in CI). Without an adapter these
//! tests skip with a message, unless FLUID_SURFELS_REQUIRE_GPU=1 makes that a failure.

use fluid_surfels::density::gpu::{self as gpu_density, GpuDensityMethod};
use fluid_surfels::density::{self, GridSpec, Kernel, Points, Resolution};
use fluid_surfels::gpu::{self, splat as gpu_splat};
use fluid_surfels::scenes;
use fluid_surfels::splat;

#[test]
fn shaders_validate_and_their_structs_match_the_rust_mirrors() {
    let shaders = [
        (
            "density_splat.wgsl",
            gpu_density::SHADER,
            "Params",
            std::mem::size_of::<gpu_density::RawParams>(),
        ),
        (
            "density_gather.wgsl",
            gpu_density::GATHER_SHADER,
            "GatherParams",
            std::mem::size_of::<gpu_density::RawGatherParams>(),
        ),
        (
            "surfel_splat.wgsl",
            gpu_splat::SHADER,
            "Uniforms",
            std::mem::size_of::<splat::RawUniforms>(),
        ),
        (
            "optics.wgsl",
            gpu::optics::SHADER,
            "Uniforms",
            std::mem::size_of::<gpu::optics::RawOptics>(),
        ),
        (
            "optics.wgsl",
            gpu::optics::SHADER,
            "ViewU",
            std::mem::size_of::<gpu::optics::RawView>(),
        ),
        (
            "optics_geometry.wgsl",
            gpu::optics::GEOMETRY_SHADER,
            "GeometryU",
            std::mem::size_of::<gpu::optics::RawGeometry>(),
        ),
    ];
    for (file, source, name, rust_size) in shaders {
        let module = naga::front::wgsl::parse_str(source)
            .unwrap_or_else(|e| panic!("{file}: {}", e.emit_to_string(source)));
        naga::valid::Validator::new(
            naga::valid::ValidationFlags::all(),
            naga::valid::Capabilities::all(),
        )
        .validate(&module)
        .unwrap_or_else(|e| panic!("{file} does not validate: {e:?}"));
        let size = module
            .types
            .iter()
            .find(|(_, t)| t.name.as_deref() == Some(name))
            .map(|(_, t)| t.inner.size(module.to_ctx()))
            .unwrap_or_else(|| panic!("{file}: no struct {name}"));
        assert_eq!(
            size as usize, rust_size,
            "{file}: {name} and its Rust mirror differ in size"
        );
    }
    // the surfel vertex layout: four vec4 attributes
    assert_eq!(std::mem::size_of::<splat::Surfel>(), 64);
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
            let max = cpu.max();
            let (worst, at) = cpu
                .values
                .iter()
                .zip(&gpu.values)
                .enumerate()
                .map(|(i, (a, b))| ((a - b).abs(), i))
                .fold((0.0f32, 0), |m, x| if x.0 > m.0 { x } else { m });
            println!(
                "per-point radii, {kernel:?}, {method:?}: grid {:?}, largest GPU-CPU difference {:e} of the max at {at}",
                spec.dims,
                worst / max
            );
            assert!(
                worst <= 1e-4 * max,
                "{kernel:?}, {method:?}: {worst} at {at} (cpu {}, gpu {})",
                cpu.values[at],
                gpu.values[at]
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
        assert_eq!(gpu.values.len(), cpu.values.len());
        let max = cpu.max();
        let (worst, at) = cpu
            .values
            .iter()
            .zip(&gpu.values)
            .enumerate()
            .map(|(i, (a, b))| ((a - b).abs(), i))
            .fold((0.0f32, 0), |m, x| if x.0 > m.0 { x } else { m });
        println!(
            "{kernel:?}, {method:?}: grid {:?}, max density {max}, largest GPU-CPU difference {worst:e} ({:e} of the max) at {at}",
            spec.dims,
            worst / max
        );
        assert!(
            worst <= 1e-4 * max,
            "{kernel:?}, {method:?}: {worst} at {at} (cpu {}, gpu {})",
            cpu.values[at],
            gpu.values[at]
        );
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
