//! Pictures people can trust, on the real files in `tests/data/` (SPlisHSPlasH's double dam
//! break, a Houdini BGEO dam break) and on a lattice block: holes inside the silhouette, dark
//! specks, stability under reordering and jitter, and golden finished frames (a difference image
//! is written on failure). Figures are printed (`-- --nocapture`).

use std::path::{Path, PathBuf};

use fluid_surfels::pipeline::{Pipeline, PipelineParams, SurfelSource, Through};
use fluid_surfels::{ParticleSet, io, quality, scenes};
use glam::Vec3;
use image::RgbaImage;
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

const DAM_BREAK: &str = "dam_break_frame_23_24389_particles.bgeo";
const DOUBLE_DAM_BREAK: &str = "double_dam_break_frame_26_4732_particles.vtk";

fn read(name: &str) -> ParticleSet {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data")
        .join(name);
    io::read_particles(&path, None).unwrap()
}

/// Where failing tests leave their images.
fn out_dir(what: &str) -> PathBuf {
    let d = Path::new(env!("CARGO_TARGET_TMPDIR"))
        .join("pictures")
        .join(what);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn params(source: SurfelSource, size: [u32; 2]) -> PipelineParams {
    let mut p = PipelineParams {
        source,
        ..Default::default()
    };
    p.scene.optics.image_size = size;
    p.splat.background = [1.0, 1.0, 1.0, 1.0];
    p
}

/// The shaded splats of `set` (white background) and their coverage.
fn splats(set: &ParticleSet, source: SurfelSource, size: [u32; 2]) -> (RgbaImage, Vec<bool>) {
    let mut pipeline = Pipeline::new(params(source, size)).unwrap();
    let f = pipeline.frame_through(set, Through::Splats).unwrap();
    let r = f.splats.expect("through the splats");
    let covered = r.colour.iter().map(|c| c[3] > 0.0).collect();
    (r.image, covered)
}

fn holes_of(name: &str, set: &ParticleSet, source: SurfelSource, size: [u32; 2]) -> quality::Holes {
    let (image, covered) = splats(set, source, size);
    let h = quality::holes(&covered, size[0] as usize, size[1] as usize, 3);
    println!(
        "{name} {}: {} of {} px holes ({:.3} %), {} enclosed ({:.3} %)",
        source.as_str(),
        h.holes,
        h.silhouette,
        100.0 * h.fraction(),
        h.enclosed,
        100.0 * h.enclosed_fraction()
    );
    let file = format!("{name}_{}.png", source.as_str());
    quality::mark_holes(&image, &covered, 3)
        .save(out_dir("holes").join(file))
        .unwrap();
    h
}

#[test]
fn density_surfaces_have_no_holes_on_a_lattice_block_and_the_real_files() {
    let block = scenes::block(&scenes::BlockParams {
        counts: [20, 20, 20],
        ..Default::default()
    })
    .unwrap()
    .particles;
    // no spray on the block: the closing's count is the measure itself. The chain's outline is
    // smooth (0.018 %); the raw particles' grid follows the jittered lattice, and its bumpy
    // outline has 1-2 px notches that the closing fills, none enclosed: how many depends on
    // where the block lies on the grid's lattice (the world's, `GridSpec::for_box`) and the
    // pixels; measured over 8 shifts of the block by an eighth of a spacing, 0.06-0.40 %
    // (the chain 0.02-0.09 %), 0.345 % here
    let h = holes_of("block", &block, SurfelSource::Chain, [200, 200]);
    assert!(h.fraction() <= 0.001, "block chain: {h:?}");
    let h = holes_of("block", &block, SurfelSource::Particles, [200, 200]);
    assert!(
        h.fraction() <= 0.005 && h.enclosed == 0,
        "block particles: {h:?}"
    );
    // the real files have spray: the closing also fills the gaps between drops (painted cyan in
    // the images left in target/tmp/pictures/holes), so the enclosed holes are the measure
    for source in [SurfelSource::Chain, SurfelSource::Particles] {
        // the double dam break's thin sheet is closed
        let h = holes_of(
            "double_dam_break",
            &read(DOUBLE_DAM_BREAK),
            source,
            [400, 400],
        );
        assert!(h.enclosed_fraction() <= 0.001, "{h:?}");
        // the dam break: what is enclosed is background between drop clusters at the top of
        // the splash (looked at: no hole in the surface), so it follows the camera: 0.157 % for
        // the chain with the camera framing the surfels' box, 0.200 % framing the particles'
        // (widened to the surface, issue 37: the views of both pipelines); the particles 0.168
        // and 0.207 %
        let h = holes_of("dam_break", &read(DAM_BREAK), source, [400, 400]);
        assert!(h.enclosed_fraction() <= 0.0025, "{h:?}");
    }
}

/// `set` reordered at random and each particle moved by up to `amount` in each axis.
fn shuffled_and_jittered(set: &ParticleSet, amount: f32, seed: u64) -> ParticleSet {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut order: Vec<usize> = (0..set.len()).collect();
    order.shuffle(&mut rng);
    let mut s = set.select(&order);
    if amount > 0.0 {
        for p in &mut s.positions {
            *p += Vec3::from_array([(); 3].map(|()| rng.random_range(-amount..amount)));
        }
    }
    s
}

#[test]
fn frames_are_stable_when_particles_are_reordered_and_jittered() {
    for name in [DOUBLE_DAM_BREAK, DAM_BREAK] {
        let set = read(name);
        for through in [Through::Splats, Through::Frame] {
            // one pipeline: the camera, pool and radius fitted on the first frame are kept
            let mut pipeline = Pipeline::new(params(SurfelSource::Chain, [160, 120])).unwrap();
            let image = |f: fluid_surfels::pipeline::Frame| match through {
                Through::Splats => f.splats.unwrap().image,
                _ => f.finished.unwrap().image,
            };
            let a = pipeline.frame_through(&set, through).unwrap();
            let spacing = 0.5 * a.radius;
            let a = image(a);
            let moved = shuffled_and_jittered(&set, 0.01 * spacing, 11);
            let b = image(pipeline.frame_through(&moved, through).unwrap());
            let diff = quality::mean_abs_diff(&a, &b);
            println!(
                "{name} {through:?}: mean abs difference {:.3} %",
                100.0 * diff
            );
            if diff > 0.01 {
                let d = out_dir("stability");
                a.save(d.join("a.png")).unwrap();
                b.save(d.join("b.png")).unwrap();
            }
            assert!(diff <= 0.01, "{name} {through:?}: {diff}");
        }
    }
}

/// The same particles in another order make the same frame: the refinement takes the surface
/// particles in an order of their positions (`pipeline::refined_indices`), so its collision
/// handling, first come first served, no longer depends on the file's order (before: the dam
/// break's finished frame changed by 0.51 %, the double dam break's by 0.38 %). Fresh pipelines:
/// the hysteresis of a sequence follows the particles' indices (or ids), which a reordering
/// without ids breaks.
#[test]
fn frames_do_not_depend_on_the_particles_order() {
    for name in [DOUBLE_DAM_BREAK, DAM_BREAK] {
        let set = read(name);
        let shuffled = shuffled_and_jittered(&set, 0.0, 5);
        let frame = |set: &ParticleSet| {
            let mut pipeline = Pipeline::new(params(SurfelSource::Chain, [160, 120])).unwrap();
            let f = pipeline.frame_through(set, Through::Frame).unwrap();
            (f.refined.unwrap().len(), f.finished.unwrap().image)
        };
        let (a, b) = (frame(&set), frame(&shuffled));
        let diff = quality::mean_abs_diff(&a.1, &b.1);
        println!(
            "{name}: {} and {} refined points, mean abs difference {:.4} %",
            a.0,
            b.0,
            100.0 * diff
        );
        assert_eq!(a.0, b.0, "{name}: refined points");
        assert!(diff <= 1e-4, "{name}: {diff}");
    }
}

/// The finished frame of a real file through the default pipeline (CPU), 320x240.
fn finished(name: &str) -> RgbaImage {
    let mut p = PipelineParams::default();
    p.scene.optics.image_size = [320, 240];
    let mut pipeline = Pipeline::new(p).unwrap();
    pipeline.frame(&read(name)).unwrap().finished.unwrap().image
}

#[test]
fn finished_frames_of_the_real_files_match_their_golden_images_without_specks() {
    for (name, golden) in [
        (DAM_BREAK, "dam_break_frame.png"),
        (DOUBLE_DAM_BREAK, "double_dam_break_frame.png"),
    ] {
        let image = finished(name);
        let mask = quality::speck_mask(&image, 7, 0.6);
        let specks = mask.iter().filter(|&&s| s).count();
        let isolated = quality::isolated(&mask, image.width() as usize, image.height() as usize);
        let pixels = f64::from(image.width() * image.height());
        let (fraction, isolated_fraction) = (specks as f64 / pixels, isolated as f64 / pixels);
        let path = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("tests/golden")
            .join(golden);
        if std::env::var("FLUID_SURFELS_BLESS").is_ok_and(|v| v == "1") {
            image.save(&path).unwrap();
        }
        let reference = image::open(&path)
            .unwrap_or_else(|e| panic!("{}: {e} (FLUID_SURFELS_BLESS=1 writes it)", path.display()))
            .to_rgba8();
        let db = fluid_surfels::splat::psnr(&image, &reference);
        println!(
            "{name}: {db:.1} dB against {golden}; {specks} specks ({:.3} %), {isolated} isolated \
             ({:.3} %)",
            100.0 * fraction,
            100.0 * isolated_fraction
        );
        let mut marked = image.clone();
        for (p, &s) in marked.pixels_mut().zip(&mask) {
            if s {
                *p = image::Rgba([255, 0, 0, 255]);
            }
        }
        marked.save(out_dir("specks").join(golden)).unwrap();
        if db < 45.0 {
            let d = out_dir("golden");
            image.save(d.join(golden)).unwrap();
            fluid_surfels::splat::difference_image(&image, &reference, 8)
                .save(d.join(format!("difference_{golden}")))
                .unwrap();
        }
        assert!(
            db >= 45.0,
            "{name}: {db} dB; images in {}",
            out_dir("golden").display()
        );
        // the goal is 0.05 % of the image; not reached: what the test flags are the dark edges
        // of shadows (the pool walls' lines along the water) and of the pool's seams seen
        // through the water (0.38-0.56 % in all since the water's shadow is filtered, 0.44-0.60 %
        // before) and 1-pixel dark cells between caustic highlights (0.08-0.11 %); these bounds
        // keep them from growing (the dark dashes on the walls, before the splats' depth reach:
        // 0.63 % on the dam break)
        assert!(fraction <= 0.007, "{name}: {specks} specks");
        assert!(
            isolated_fraction <= 0.0015,
            "{name}: {isolated} isolated specks"
        );
    }
}

/// A drop far outside the view widens the particles' box; the density grid lies on the world's
/// lattice (`GridSpec::for_box`), so the water in view keeps its grid points and is drawn as
/// before. Shaded splats of both real files with the camera and support radius of the frame
/// without the drop, the drop behind the camera (measured: the same image, infinite PSNR. Before,
/// 43.4 and 38.5 dB: the grid was anchored at the box's corner and the refinement's order
/// quantised over the surface particles' box, so the spray's drops and the surface's fine
/// shading moved with the box; the grid on the lattice alone gave the dam break 42.9 dB).
#[test]
fn a_drop_outside_the_view_leaves_the_picture_as_it_was() {
    for name in [DAM_BREAK, DOUBLE_DAM_BREAK] {
        let mut set = read(name);
        // attributes the pipeline does not read, each as long as the positions
        (set.normals, set.colours) = (None, None);
        set.extra.clear();
        let mut first = Pipeline::new(params(SurfelSource::Chain, [320, 240])).unwrap();
        first.frame_through(&set, Through::Splats).unwrap();
        let (camera, radius) = (first.camera().unwrap(), first.support_radius().unwrap());
        let draw = |set: &ParticleSet| {
            let mut p = params(SurfelSource::Chain, [320, 240]);
            p.scene.camera = Some(camera);
            p.support_radius = Some(radius);
            let mut pipeline = Pipeline::new(p).unwrap();
            let f = pipeline.frame_through(set, Through::Splats).unwrap();
            f.splats.expect("through the splats").image
        };
        let mut with_drop = set.clone();
        // behind the camera, 37.3 support radii out along the view axis and off it
        let back = (camera.eye - camera.target).normalize();
        let drop = camera.eye + back * (37.3 * radius) + Vec3::new(0.31, -0.17, 0.23) * radius;
        with_drop.positions.push(drop);
        if let Some(ids) = &mut with_drop.ids {
            ids.push(ids.iter().max().map_or(0, |m| m + 1));
        }
        if let Some(v) = &mut with_drop.velocities {
            v.push(Vec3::ZERO);
        }
        if let Some(m) = &mut with_drop.masses {
            m.push(m[0]);
        }
        let (a, b) = (draw(&set), draw(&with_drop));
        let db = fluid_surfels::splat::psnr(&a, &b);
        println!("{name}: a drop behind the camera changes the splats by {db:.1} dB");
        assert!(db >= 60.0, "{name}: {db} dB");
    }
}

/// Every renderer's finished frame of the dam break sees the water in its pool: the automatic
/// pool's walls rise to about the water's level for the peer renderers too (their spheres carry
/// no normals, so the level comes from the surface particles, as the density grid's does), and
/// the water covers about as many pixels as the EWA frame's from the same camera. Seen to fail without the particles'
/// level: the peers' walls rose half way up the splash and hid most of the pool's water.
#[test]
fn every_renderer_sees_the_water_in_its_pool() {
    use fluid_surfels::pipeline::Renderer;
    let set = read(DAM_BREAK);
    let size = [64, 48];
    let mut ewa: Option<(f32, f32, usize)> = None;
    // one camera for all, the EWA frame's (each renderer frames the box of what it draws: the
    // ray caster's spheres reach a support radius out)
    let mut camera = None;
    for renderer in [
        Renderer::Ewa,
        Renderer::ParticleSplat,
        Renderer::RayCast,
        Renderer::Ssfr,
    ] {
        let mut p = params(SurfelSource::Particles, size);
        p.renderer = renderer;
        p.scene.optics.caustics_resolution = Some([32, 32]);
        p.scene.optics.map_resolution = Some([64, 64]);
        p.scene.camera = camera;
        let frame = Pipeline::new(p)
            .unwrap()
            .frame_through(&set, Through::Frame)
            .unwrap();
        let finished = frame.finished.unwrap();
        camera.get_or_insert(finished.stage.camera);
        let heights = || {
            finished
                .stage
                .receiver
                .triangles
                .iter()
                .flatten()
                .map(|v| v.y)
        };
        let top = heights().fold(f32::MIN, f32::max);
        let floor = heights().fold(f32::MAX, f32::min);
        let water = finished.linear.iter().filter(|c| c[3] > 0.0).count();
        println!("{renderer:?}: the pool's walls {floor:.3} to {top:.3}, water on {water} pixels");
        let (ewa_floor, ewa_top, ewa_water) = *ewa.get_or_insert((floor, top, water));
        let depth = ewa_top - ewa_floor;
        assert!(
            (top - ewa_top).abs() <= 0.15 * depth,
            "{renderer:?}: walls up to {top}, the EWA frame's {ewa_top}"
        );
        // measured (64x48): 348 pixels (EWA), 422 (particle splats), 249 (ray cast: its pool
        // a cell narrower, its sphere centres' box), 323 (screen space); without the
        // particles' level the particle splats' walls reached 2.0 (EWA's 0.60) and their
        // water 213 pixels
        assert!(
            water as f64 >= 0.65 * ewa_water as f64,
            "{renderer:?}: water on {water} pixels, the EWA frame's on {ewa_water}"
        );
    }
}
