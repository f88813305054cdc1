//! The narrow band of the Layered Neighborhood Method on analytic shapes: every particle near
//! the true surface is in it, it holds at most two voxel layers, and bad input is refused.

use std::collections::HashSet;

use fluid_surfels::lnm::{LnmError, LnmParams, NarrowBand, narrow_band};
use fluid_surfels::scenes::{self, BlockParams, SphereParams};
use glam::Vec3;

/// The shapes both layouts and both devices are compared on: a block (jittered by `jitter`
/// spacings), a jittered sphere, the two real files and no particles; with support radii.
fn shapes(jitter: f32) -> Vec<(&'static str, Vec<Vec3>, f32)> {
    let block = scenes::block(&BlockParams {
        jitter,
        ..Default::default()
    })
    .unwrap();
    let sphere = scenes::sphere(&SphereParams::default()).unwrap();
    vec![
        ("block", block.particles.positions, block.support_radius),
        ("sphere", sphere.particles.positions, sphere.support_radius),
        (
            "double dam break",
            data("double_dam_break_frame_26_4732_particles.vtk"),
            0.14,
        ),
        (
            "dam break",
            data("dam_break_frame_23_24389_particles.bgeo"),
            0.095,
        ),
        ("nothing", Vec::new(), 0.1),
    ]
}

/// The positions of a real file in `tests/data/`.
fn data(name: &str) -> Vec<Vec3> {
    fluid_surfels::io::read_particles(
        &std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("tests/data")
            .join(name),
        None,
    )
    .unwrap()
    .positions
}

/// Every band voxel has an empty voxel or the outside of the domain within two voxels
/// (Chebyshev distance): the band is at most two voxel layers thick.
fn at_most_two_layers(band: &NarrowBand) {
    let full: HashSet<[u32; 3]> = band.voxels.iter().map(|v| v.coord).collect();
    for v in band.voxels.iter().filter(|v| v.label != 0) {
        let near_surface = (-2i64..=2).any(|dz| {
            (-2i64..=2).any(|dy| {
                (-2i64..=2).any(|dx| {
                    let n = [dx, dy, dz];
                    let c: [i64; 3] = std::array::from_fn(|a| i64::from(v.coord[a]) + n[a]);
                    (0..3).any(|a| c[a] < 0 || c[a] >= i64::from(band.dims[a]))
                        || !full.contains(&c.map(|x| x as u32))
                })
            })
        });
        assert!(
            near_surface,
            "band voxel {:?} is deeper than two layers",
            v.coord
        );
    }
}

/// Recall against the analytic surface: the particles within one spacing of it, and how many
/// of them the band holds; also the band's share of all particles.
fn check_recall(name: &str, positions: &[Vec3], depth: impl Fn(Vec3) -> f32, spacing: f32) {
    let h = 2.0 * spacing;
    let band = narrow_band(positions, h, &LnmParams::default()).unwrap();
    let near: Vec<usize> = (0..positions.len())
        .filter(|&i| depth(positions[i]) < spacing)
        .collect();
    let missed = near.iter().filter(|&&i| !band.contains(i)).count();
    println!(
        "{name}: {} particles, {} within one spacing of the surface, band {} ({:.1} %), missed {missed}; {} voxels",
        positions.len(),
        near.len(),
        band.len(),
        100.0 * band.len() as f64 / positions.len() as f64,
        band.voxels.len()
    );
    assert!(!near.is_empty());
    assert_eq!(missed, 0, "{name}: recall below 100 %");
    assert!(band.len() < positions.len(), "{name}: no interior left out");
    at_most_two_layers(&band);
    // the counts and centroids add up to the particles
    let total: u32 = band.voxels.iter().map(|v| v.count).sum();
    assert_eq!(total as usize, positions.len());
    let sum: Vec3 = band
        .voxels
        .iter()
        .map(|v| v.centroid * v.count as f32)
        .sum();
    let direct: Vec3 = positions.iter().copied().sum();
    // f32 sums in another order: relative to the sum of the magnitudes
    let scale: f32 = positions.iter().map(|p| p.abs().max_element()).sum();
    assert!(
        (sum - direct).abs().max_element() < 1e-5 * scale,
        "{name}: centroids {sum} against {direct}"
    );
}

#[test]
fn the_band_holds_every_particle_near_a_block_a_sphere_and_a_holed_slab() {
    let block = scenes::block(&BlockParams::default()).unwrap();
    let shape = block.shape.unwrap();
    check_recall(
        "block",
        &block.particles.positions,
        |p| shape.depth(p),
        BlockParams::default().spacing,
    );
    let sphere = scenes::sphere(&SphereParams::default()).unwrap();
    let shape = sphere.shape.unwrap();
    let spacing = fluid_surfels::neighbours::estimate_spacing(&sphere.particles.positions).unwrap();
    check_recall(
        "sphere",
        &sphere.particles.positions,
        |p| shape.depth(p),
        spacing,
    );
    // a slab 40 x 16 x 40 spacings with a round hole of radius 6 spacings through it
    let s = 0.05;
    let (side, thick, hole) = (40, 16, 6.0 * s);
    let centre = Vec3::new(side as f32 * s / 2.0, 0.0, side as f32 * s / 2.0);
    let radial = |p: Vec3| Vec3::new(p.x - centre.x, 0.0, p.z - centre.z).length();
    let mut slab = Vec::new();
    for z in 0..side {
        for y in 0..thick {
            for x in 0..side {
                let p = (Vec3::new(x as f32, y as f32, z as f32) + 0.5) * s;
                if radial(p) >= hole {
                    slab.push(p);
                }
            }
        }
    }
    let (lo, hi) = (
        Vec3::ZERO,
        Vec3::new(side as f32, thick as f32, side as f32) * s,
    );
    check_recall(
        "holed slab",
        &slab,
        |p| (p - lo).min(hi - p).min_element().min(radial(p) - hole),
        s,
    );
}

/// Layer 2 is the paper's deficiency rule: with `n_min = 0` there is none, and a thin layer-1
/// voxel pulls its inner neighbours in; the result does not depend on the thread count.
#[test]
fn layer_two_follows_the_deficiency_rule_and_threads_do_not_matter() {
    let block = scenes::block(&BlockParams {
        counts: [24, 24, 24],
        jitter: 0.3,
        ..BlockParams::default()
    })
    .unwrap();
    let p = &block.particles.positions;
    let h = 0.1;
    let band = narrow_band(p, h, &LnmParams::default()).unwrap();
    let none = narrow_band(
        p,
        h,
        &LnmParams {
            n_min: 0,
            ..LnmParams::default()
        },
    )
    .unwrap();
    assert!(none.voxels.iter().all(|v| v.label != 2));
    let second = band.voxels.iter().filter(|v| v.label == 2).count();
    println!(
        "jittered block: {} voxels, layer 1 {}, layer 2 {second} (n_min 8), band {} of {} particles",
        band.voxels.len(),
        band.voxels.iter().filter(|v| v.label == 1).count(),
        band.len(),
        p.len()
    );
    assert!(second > 0, "a jittered block has thin voxels on its faces");
    for v in band.voxels.iter().filter(|v| v.label == 2) {
        let thin = band.voxels.iter().any(|u| {
            u.label == 1 && u.count <= 8 && (0..3).all(|a| u.coord[a].abs_diff(v.coord[a]) <= 1)
        });
        assert!(
            thin,
            "layer-2 voxel {:?} has no thin layer-1 neighbour",
            v.coord
        );
    }
    let one = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap()
        .install(|| narrow_band(p, h, &LnmParams::default()).unwrap());
    assert_eq!(one, band);
    // reordering the particles changes no voxel and moves the labels with the particles
    let reversed: Vec<Vec3> = p.iter().rev().copied().collect();
    let r = narrow_band(&reversed, h, &LnmParams::default()).unwrap();
    assert_eq!(
        r.voxels
            .iter()
            .map(|v| (v.coord, v.count, v.label))
            .collect::<Vec<_>>(),
        band.voxels
            .iter()
            .map(|v| (v.coord, v.count, v.label))
            .collect::<Vec<_>>()
    );
    assert!((0..p.len()).all(|i| r.labels[p.len() - 1 - i] == band.labels[i]));
}

#[test]
fn bad_input_is_refused_and_nothing_is_empty() {
    let p = [Vec3::ZERO, Vec3::ONE];
    let d = LnmParams::default();
    assert!(matches!(
        narrow_band(&[Vec3::ZERO, Vec3::NAN], 0.1, &d),
        Err(LnmError::NonFinite { index: 1 })
    ));
    assert!(narrow_band(&p, 0.0, &d).is_err());
    assert!(narrow_band(&p, f32::NAN, &d).is_err());
    let bad = LnmParams {
        voxel_in_radii: -1.0,
        ..d
    };
    assert!(narrow_band(&p, 0.1, &bad).is_err());
    // a splash far away: too many voxels along an axis for the keys, refused (not allocated)
    assert!(matches!(
        narrow_band(&[Vec3::ZERO, Vec3::new(1e6, 0.0, 0.0)], 0.1, &d),
        Err(LnmError::TooManyVoxels { .. })
    ));
    // but a wide spread that fits costs its particles, not its box
    let far = narrow_band(&[Vec3::ZERO, Vec3::new(1e4, 1e4, 1e4)], 0.1, &d).unwrap();
    assert_eq!(far.voxels.len(), 2);
    assert_eq!(far.len(), 2);
    let empty = narrow_band(&[], 0.1, &d).unwrap();
    assert!(empty.is_empty() && empty.voxels.is_empty());
    // a single particle is its own surface
    let one = narrow_band(&[Vec3::ONE], 0.1, &d).unwrap();
    assert_eq!(one.labels, [1]);
}

/// As a detection (`detect --method lnm`): on a particle sphere the band holds every surface
/// particle of the centre-of-mass detection near the surface (the agreement printed), and the
/// voxel-ring normals point outwards (within 30 degrees of the radial direction on >= 95 % of
/// the band's outer shell).
#[test]
fn the_band_holds_the_centre_of_mass_surface_and_its_normals_point_out() {
    use fluid_surfels::lnm::agreement;
    use fluid_surfels::neighbours::{Backend, Neighbourhoods};
    use fluid_surfels::surface::{SurfaceDetector, SurfaceParams};
    let scene = scenes::sphere(&SphereParams {
        radius_in_spacings: 10.0,
        ..Default::default()
    })
    .unwrap();
    let p = &scene.particles.positions;
    let h = scene.support_radius;
    let nb = Neighbourhoods::build(p, h, Backend::CellGrid).unwrap();
    let com = SurfaceDetector::new(SurfaceParams::default())
        .unwrap()
        .detect(&scene.particles, &nb)
        .unwrap();
    let band = narrow_band(p, h, &LnmParams::default()).unwrap();
    let a = agreement(&band, &com.classes);
    println!("sphere of 10 spacings: {a:?}");
    assert_eq!(a.particles, p.len());
    assert!(a.detected > 500, "{a:?}");
    // the centre-of-mass detection also flags two particles at the sphere's centre (its
    // innermost lattice shell is lopsided): every detected particle within two spacings of the
    // true surface is in the band, and the band misses only those deep ones
    let centre = p.iter().copied().sum::<Vec3>() / p.len() as f32;
    let depth = |x: Vec3| 10.0 * 0.05 - (x - centre).length();
    let detected = |i: usize| com.classes[i] != fluid_surfels::surface::ParticleClass::Interior;
    let near = (0..p.len()).filter(|&i| detected(i) && depth(p[i]) < 0.1);
    assert!(near.clone().all(|i| band.contains(i)));
    let deep = (0..p.len())
        .filter(|&i| detected(i) && depth(p[i]) >= 0.1)
        .count();
    assert!(a.detected_only <= deep, "{a:?}, {deep} deep");
    assert!(a.recall > 0.99, "{a:?}");
    assert_eq!(a.both + a.band_only, a.band);
    let normals = band.ring_normals(p);
    let outer = p
        .iter()
        .map(|&x| (x - centre).length())
        .fold(0.0f32, f32::max);
    let shell: Vec<usize> = (0..p.len())
        .filter(|&i| (p[i] - centre).length() > outer - 0.06)
        .collect();
    assert!(shell.iter().all(|&i| band.contains(i)));
    let good = shell
        .iter()
        .filter(|&&i| normals[i].dot((p[i] - centre).normalize()) > 30f32.to_radians().cos())
        .count();
    println!(
        "ring normals within 30 degrees of radial: {good} of {}",
        shell.len()
    );
    assert!(
        good as f64 >= 0.95 * shell.len() as f64,
        "{good} of {}",
        shell.len()
    );
    // off the band: zero; on it: unit
    for (i, n) in normals.iter().enumerate() {
        if band.contains(i) {
            assert!((n.length() - 1.0).abs() < 1e-4);
        } else {
            assert_eq!(*n, Vec3::ZERO);
        }
    }
}

/// The GPU twin (`lnm::gpu`, a dense voxel grid) equals the CPU's sparse band exactly in every
/// voxel's coordinates, count and label and in every particle's label and voxel, with centroids
/// within 1e-4 voxel edges (fixed-point sums), on a block, a jittered sphere, the two real files
/// and no particles; a domain too large for the dense grid is refused with a typed error.
#[test]
fn the_gpu_band_equals_the_cpu_band() {
    use fluid_surfels::lnm::gpu::narrow_band_gpu;
    let Some(ctx) =
        fluid_surfels::gpu::context_or_skip("the_gpu_band_equals_the_cpu_band").unwrap()
    else {
        return;
    };
    let cases = shapes(BlockParams::default().jitter);
    for (name, p, h) in cases {
        let params = LnmParams::default();
        let cpu = narrow_band(&p, h, &params).unwrap();
        let t = std::time::Instant::now();
        let gpu = narrow_band_gpu(&ctx, &p, h, &params).unwrap();
        println!(
            "{name}: {} particles, {} voxels, band {}; GPU {:.1} ms",
            p.len(),
            cpu.voxels.len(),
            cpu.len(),
            t.elapsed().as_secs_f64() * 1e3
        );
        assert_eq!(
            (gpu.origin, gpu.edge, gpu.dims),
            (cpu.origin, cpu.edge, cpu.dims)
        );
        assert_eq!(gpu.labels, cpu.labels, "{name}");
        assert_eq!(gpu.voxel_of, cpu.voxel_of, "{name}");
        assert_eq!(gpu.voxels.len(), cpu.voxels.len(), "{name}");
        for (g, c) in gpu.voxels.iter().zip(&cpu.voxels) {
            assert_eq!(
                (g.coord, g.count, g.label),
                (c.coord, c.count, c.label),
                "{name}"
            );
            assert!(
                g.centroid.distance(c.centroid) < 1e-4 * cpu.edge,
                "{name}: {} against {}",
                g.centroid,
                c.centroid
            );
        }
    }
    // 2^12 voxels along each axis: far more than the dense grid's limit
    let far = vec![Vec3::ZERO, Vec3::splat(4096.0 * 0.1)];
    assert!(matches!(
        narrow_band_gpu(&ctx, &far, 0.1, &LnmParams::default()),
        Err(fluid_surfels::Error::Lnm(LnmError::DenseTooLarge { .. }))
    ));
}

/// The dense layout (a counting sort over an array of the domain) and the sparse one (sorted
/// keys, hashed neighbours) give the same band bit for bit, on every shape and real file here,
/// on one thread and on two; the automatic choice keeps a far-flung splash sparse.
#[test]
fn dense_and_sparse_layouts_give_the_same_band() {
    use fluid_surfels::lnm::{Layout, cpu::auto_layout, narrow_band_in};
    let mut cases = shapes(0.3);
    let (block, h) = (cases[0].1.clone(), cases[0].2);
    let mut splash = block;
    splash.push(Vec3::splat(1000.0));
    cases.push(("block and a far drop", splash, h));
    let pool = |n| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(n)
            .build()
            .unwrap()
    };
    for (name, p, h) in cases {
        let params = LnmParams {
            n_min: 8,
            ..Default::default()
        };
        let sparse = narrow_band_in(&p, h, &params, Layout::Sparse).unwrap();
        let total = sparse.dims.iter().map(|&d| u64::from(d)).product::<u64>();
        // a domain too large for a dense array is counted sparse whatever is asked: comparing
        // the two there would compare the sparse layout with itself
        if total <= fluid_surfels::lnm::cpu::MAX_DENSE {
            for threads in [1, 2] {
                let dense = pool(threads)
                    .install(|| narrow_band_in(&p, h, &params, Layout::Dense))
                    .unwrap();
                assert_eq!(dense, sparse, "{name}, {threads} threads");
            }
        }
        let auto = auto_layout(total, p.len());
        println!(
            "{name}: {} voxels in a domain of {total}: {auto:?}",
            sparse.voxels.len()
        );
        if name == "block and a far drop" {
            assert_eq!(auto, Layout::Sparse);
            assert!(total > fluid_surfels::lnm::cpu::MAX_DENSE);
        } else if !p.is_empty() {
            assert!(total <= fluid_surfels::lnm::cpu::MAX_DENSE, "{name}");
            assert_eq!(auto, Layout::Dense, "{name}");
        }
        assert_eq!(narrow_band(&p, h, &params).unwrap(), sparse, "{name}");
    }
}

/// `[surface] method = "lnm"` in the pipeline: the frame's surface is the narrow band made into
/// classes by `lnm::band_surface` from the centre-of-mass detection of the same frame (every
/// band particle surface or isolated, every other interior), and the chain runs on it to surfels.
/// (The dam break's band, refined 3 steps, is over the default memory budget: its ~21,500
/// band particles against 8,458 surface ones make 8x the points.)
#[test]
fn the_pipeline_takes_the_band_as_its_surface() {
    use fluid_surfels::ParticleSet;
    use fluid_surfels::pipeline::{Pipeline, PipelineParams, Through};
    use fluid_surfels::surface::{ParticleClass, SurfaceMethod, SurfaceParams};
    let positions = data("dam_break_frame_23_24389_particles.bgeo");
    let set = ParticleSet::from_positions(positions.clone());
    let params = |method| PipelineParams {
        support_radius: Some(0.095),
        surface: SurfaceParams {
            method,
            ..Default::default()
        },
        ..Default::default()
    };
    let com = Pipeline::new(params(SurfaceMethod::CentreOfMass))
        .unwrap()
        .frame_through(&set, Through::Surface)
        .unwrap()
        .surface;
    let band = narrow_band(&positions, 0.095, &LnmParams::default()).unwrap();
    let expected = fluid_surfels::lnm::band_surface(&band, &positions, &com);
    let frame = Pipeline::new(params(SurfaceMethod::Lnm))
        .unwrap()
        .frame_through(&set, Through::Surface)
        .unwrap();
    assert_eq!(frame.surface.classes, expected.classes);
    assert_eq!(frame.surface.normals, expected.normals);
    for (i, (&label, &class)) in band.labels.iter().zip(&frame.surface.classes).enumerate() {
        assert_eq!(label != 0, class != ParticleClass::Interior, "particle {i}");
    }
    let band_count = frame
        .surface
        .classes
        .iter()
        .filter(|&&c| c != ParticleClass::Interior)
        .count();
    // a bulk body: the band is the outer voxel layers, not the whole (21,514 of 24,389 when
    // measured, 8,458 of them surface to the centre-of-mass detection)
    assert!(
        band_count > 0 && band_count < positions.len(),
        "{band_count}"
    );
    // the chain runs on to surfels from the band (a thin sheet: every particle in the band)
    let sheet = ParticleSet::from_positions(data("double_dam_break_frame_26_4732_particles.vtk"));
    let frame = Pipeline::new(PipelineParams {
        support_radius: Some(0.14),
        ..params(SurfaceMethod::Lnm)
    })
    .unwrap()
    .frame_through(&sheet, Through::Surfels)
    .unwrap();
    assert!(!frame.surfels.as_ref().expect("surfels").is_empty());
}
