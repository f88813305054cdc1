//! Detail chosen from the view (issue 36): the refinement stops region by region
//! (`refine::refine_to_levels`), the levels come from the camera (`pipeline::ViewLevels`), and
//! `detail = "auto"` makes less where the picture needs less.

use fluid_surfels::ParticleSet;
use fluid_surfels::io;
use fluid_surfels::pipeline::{
    Detail, Pipeline, PipelineParams, Through, ViewLevels, spacing_after,
};
use fluid_surfels::refine::{self, RefineParams};
use fluid_surfels::splat::{
    self, Camera, Drawn, Ewa, Light, SplatParams, WaterInput, WaterRenderer, WaterSurface,
};
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

/// A flat square sheet of points on a lattice of spacing `s` in the plane y = 0, normals up.
fn sheet(n: usize, s: f32) -> (Vec<Vec3>, Vec<Vec3>) {
    let p: Vec<Vec3> = (0..n * n)
        .map(|i| Vec3::new((i % n) as f32 * s, 0.0, (i / n) as f32 * s))
        .collect();
    let normals = vec![Vec3::Y; p.len()];
    (p, normals)
}

#[test]
fn levels_at_the_most_steps_refine_as_the_fixed_refinement() {
    let (p, n) = sheet(14, 0.1);
    let params = RefineParams::with_radius(0.2);
    let fixed = refine::refine(&p, &n, &params).unwrap();
    for parallel in [true, false] {
        let levels =
            refine::refine_to_levels(&p, &n, &params, parallel, &vec![99; p.len()]).unwrap();
        assert_eq!(levels.positions, fixed.positions);
        assert_eq!(levels.kernel_radii, fixed.kernel_radii);
        assert_eq!(levels.radii, fixed.radii);
        assert_eq!(levels.final_radius, fixed.final_radius);
        assert!(levels.levels.iter().all(|&l| l == 3));
    }
}

/// Half a sheet at one step, half at three: the parallel refinement equals the reference (its
/// oracle), each half is as dense as a fixed refinement of that many steps, and each point's
/// kernel radius is its level's (a child takes the higher of its parents' levels, so points a
/// little way into the coarse half near the border have the fine level).
#[test]
fn a_sheet_refines_each_half_to_its_own_level() {
    let s = 0.1;
    let (p, n) = sheet(24, s);
    let params = RefineParams::with_radius(2.0 * s);
    let split = 12.0 * s;
    let level = |x: Vec3| if x.x < split { 1 } else { 3 };
    let levels: Vec<u8> = p.iter().map(|&x| level(x) as u8).collect();
    let parallel = refine::refine_to_levels(&p, &n, &params, true, &levels).unwrap();
    let reference = refine::refine_to_levels(&p, &n, &params, false, &levels).unwrap();
    assert_eq!(parallel.positions, reference.positions);
    assert_eq!(parallel.levels, reference.levels);
    let per_level = |k: u32| refine::refine(&p, &n, &RefineParams { steps: k, ..params }).unwrap();
    // points per unit area well inside each half (three spacings from the split and the rims)
    let density = |pts: &[Vec3], lo: f32, hi: f32| {
        let inside = |q: &&Vec3| q.x > lo && q.x < hi && q.z > 3.0 * s && q.z < 20.0 * s;
        pts.iter().filter(inside).count() as f32 / ((hi - lo) * 17.0 * s)
    };
    let (coarse, fine) = (
        density(&parallel.positions, 3.0 * s, split - 3.0 * s),
        density(&parallel.positions, split + 3.0 * s, 20.0 * s),
    );
    let (one, three) = (
        density(&per_level(1).positions, 3.0 * s, split - 3.0 * s),
        density(&per_level(3).positions, split + 3.0 * s, 20.0 * s),
    );
    println!(
        "points per unit area: one-step half {coarse} ({one} fixed), three-step half {fine} ({three} fixed)"
    );
    assert!((coarse / one - 1.0).abs() < 0.05, "{coarse} against {one}");
    assert!((fine / three - 1.0).abs() < 0.05, "{fine} against {three}");
    let r = |k: i32| 2.0 * s * refine::RADIUS_FACTOR.powi(k);
    for (i, x) in parallel.positions.iter().enumerate() {
        let want = if parallel.levels[i] == 1 { r(1) } else { r(3) };
        // (a child takes its parents' higher level: up to two spacings into the coarse half;
        // the moves of eq. 17-19 may carry a point a little way)
        if x.x > split + s || x.x < split - 2.0 * s {
            assert_eq!(u32::from(parallel.levels[i]), level(*x));
        }
        assert!((parallel.kernel_radii[i] - params.kernel_factor * want).abs() < 1e-6);
    }
    assert_eq!(parallel.stats.len(), 3);
}

/// A region that asks for more steps than any point can take (no pair far enough apart) does
/// not make the finest level, so no point gets its kernel: the grid's cell follows the levels
/// used.
#[test]
fn the_finest_level_is_the_last_that_made_points() {
    let (p, n) = sheet(10, 0.1);
    let params = RefineParams::with_radius(0.2);
    // one point far from the others asks for three steps, alone: it makes nothing
    let mut p2 = p.clone();
    p2.push(Vec3::new(50.0, 0.0, 50.0));
    let mut n2 = n.clone();
    n2.push(Vec3::Y);
    let levels: Vec<u8> = p2.iter().map(|x| if x.x > 10.0 { 3 } else { 1 }).collect();
    let r = refine::refine_to_levels(&p2, &n2, &params, true, &levels).unwrap();
    assert_eq!(r.levels.iter().copied().max(), Some(1));
    assert!((r.final_radius - 0.2 * refine::RADIUS_FACTOR).abs() < 1e-7);
    // and no step runs for it: the refinement ends once no point open to the next step has a
    // pair (the update before a step that makes nothing was 45 ms on the dam break); also for
    // two points that see each other but stay closer than any step pairs
    p2.push(Vec3::new(50.01, 0.0, 50.0));
    n2.push(Vec3::Y);
    let levels: Vec<u8> = p2.iter().map(|x| if x.x > 10.0 { 3 } else { 1 }).collect();
    let all_one = refine::refine_to_levels(&p2, &n2, &params, true, &vec![1; p2.len()]).unwrap();
    for parallel in [true, false] {
        let r = refine::refine_to_levels(&p2, &n2, &params, parallel, &levels).unwrap();
        assert_eq!(r.stats.len(), 1, "parallel {parallel}: {:?}", r.stats);
        assert_eq!(r.positions, all_one.positions, "parallel {parallel}");
        assert_eq!(r.kernel_radii, all_one.kernel_radii, "parallel {parallel}");
    }
}

fn view(camera: &Camera, w: u32, h: u32) -> splat::View {
    splat::View::new(camera, &Light::default(), &SplatParams::default(), w, h).unwrap()
}

/// The level is the fewest steps whose spacing bound (`spacing_after`) is at most `detail_px`
/// pixels where the point is seen, fewer farther away, none outside the view.
#[test]
fn view_levels_follow_the_footprint() {
    let camera = Camera {
        eye: Vec3::new(0.0, 0.0, 10.0),
        target: Vec3::ZERO,
        ..Camera::default()
    };
    let (w, h) = (640, 480);
    let radius = 0.1;
    let levels = ViewLevels::new(vec![view(&camera, w, h)], radius, 3, 1.5);
    let per_unit = |depth: f32| h as f32 / (2.0 * (20f32).to_radians().tan() * depth);
    let mut last = u32::MAX;
    for depth in [1.0f32, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0] {
        let x = Vec3::new(0.0, 0.0, 10.0 - depth);
        let k = levels.level(x);
        let px = |k: u32| spacing_after(k) * 0.5 * radius * per_unit(depth);
        assert!(k <= 3);
        assert!(k == 3 || px(k) <= 1.5 + 1e-4, "depth {depth}: level {k}");
        assert!(k == 0 || px(k - 1) > 1.5 - 1e-4, "depth {depth}: level {k}");
        assert!(k <= last, "farther, finer: {k} after {last}");
        last = k;
    }
    assert_eq!(levels.level(Vec3::new(0.0, 0.0, 10.0 - 1.0)), 3);
    // behind the eye and far beside the view: not refined
    assert_eq!(levels.level(Vec3::new(0.0, 0.0, 12.0)), 0);
    assert_eq!(levels.level(Vec3::new(30.0, 0.0, 0.0)), 0);
    // hysteresis: the previous level holds while the need stays within a quarter level of its
    // range (previous - 1, previous]
    assert_eq!(levels.level_after(2.2, Some(2)), 2);
    assert_eq!(levels.level_after(2.3, Some(2)), 3);
    assert_eq!(levels.level_after(0.8, Some(2)), 2);
    assert_eq!(levels.level_after(0.7, Some(2)), 1);
    assert_eq!(levels.level_after(7.0, Some(3)), 3);
    assert_eq!(levels.level_after(f32::NEG_INFINITY, Some(0)), 0);
    assert_eq!(levels.level_after(f32::NEG_INFINITY, Some(2)), 0);
    // a finer picture never asks for less
    let big = ViewLevels::new(vec![view(&camera, 1920, 1080)], radius, 3, 1.5);
    for z in [-20.0f32, -5.0, 0.0, 5.0] {
        let x = Vec3::new(0.5, 0.2, z);
        assert!(big.level(x) >= levels.level(x));
    }
}

#[test]
fn bad_footprints_are_refused() {
    for px in [0.0, -1.0, f32::NAN, f32::INFINITY] {
        let e = Pipeline::new(PipelineParams {
            detail: Detail::Auto,
            detail_px: px,
            ..Default::default()
        })
        .err()
        .unwrap_or_else(|| panic!("detail_px {px} accepted"));
        assert!(e.to_string().contains("detail_px"), "{e}");
    }
}

/// The chain through the surfels of a frame drawn (as the shaded splats) at `size` with
/// `detail`: refined points and surfels.
fn counts(set: &ParticleSet, detail: Detail, size: [u32; 2]) -> (usize, usize) {
    let mut p = PipelineParams {
        detail,
        ..Default::default()
    };
    p.scene.optics.image_size = size;
    let mut pipeline = Pipeline::new(p).unwrap();
    pipeline.set_drawn(Some(Through::Splats));
    let f = pipeline.frame_through(set, Through::Surfels).unwrap();
    assert_eq!(f.detail.detail, detail);
    assert_eq!(f.detail.refined_points, f.refined.as_ref().unwrap().len());
    (f.detail.refined_points, f.detail.surfels)
}

/// The dam break BGEO from the automatic camera: at 640x480 `auto` makes at most a quarter of
/// the refined points and of the surfels `fixed` makes (measured 88,885 refined points against
/// 362,852, 24.5 %; 52,547 surfels against 286,054, 18.4 %: the cell follows the finest level
/// used, level 2 there, which alone left 80,786 surfels, 28.2 %, and the surfels facing away
/// from the camera are not made, `a_picture_leaves_out_only_what_it_cannot_show`); at
/// 1920x1080 never more than `fixed`. Without a camera (`set_drawn(None)`) a frame is `fixed`.
#[test]
fn auto_makes_less_where_the_picture_needs_less() {
    let set = data("dam_break_frame_23_24389_particles.bgeo");
    let fixed = counts(&set, Detail::Fixed, [640, 480]);
    let auto = counts(&set, Detail::Auto, [640, 480]);
    println!("640x480: fixed {fixed:?}, auto {auto:?}");
    assert!(
        auto.0 * 4 <= fixed.0,
        "refined points {auto:?} against {fixed:?}"
    );
    assert!(auto.1 * 4 <= fixed.1, "surfels {auto:?} against {fixed:?}");
    let big = counts(&set, Detail::Auto, [1920, 1080]);
    println!("1920x1080: auto {big:?}");
    assert!(
        big.0 <= fixed.0 && big.1 <= fixed.1,
        "{big:?} against {fixed:?}"
    );
    let mut pipeline = Pipeline::new(PipelineParams {
        detail: Detail::Auto,
        ..Default::default()
    })
    .unwrap();
    let f = pipeline.frame_through(&set, Through::Surfels).unwrap();
    assert_eq!(f.detail.detail, Detail::Fixed);
    assert_eq!(f.detail.refined_points, fixed.0);
}

/// `auto` gives the same refined points and surfels on 1, 2 and 3 threads.
#[test]
fn auto_is_the_same_on_any_thread_count() {
    let set = data("double_dam_break_frame_26_4732_particles.vtk");
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            let mut p = PipelineParams {
                detail: Detail::Auto,
                detail_px: 2.5,
                ..Default::default()
            };
            p.scene.optics.image_size = [320, 240];
            let mut pipeline = Pipeline::new(p).unwrap();
            pipeline.set_drawn(Some(Through::Splats));
            let f = pipeline.frame_through(&set, Through::Surfels).unwrap();
            let r = f.refined.unwrap();
            (r.positions, r.levels, f.render_surfels)
        })
    };
    let one = run(1);
    assert!(
        one.1.iter().any(|&l| l < 3),
        "the view should stop some regions early"
    );
    for threads in [2, 3] {
        let other = run(threads);
        assert_eq!(one.0, other.0, "{threads} threads");
        assert_eq!(one.1, other.1, "{threads} threads");
        assert_eq!(one.2, other.2, "{threads} threads");
    }
}

/// `auto` against `fixed` from the same camera, shaded splats at 640x480 on the two real files:
/// the pictures agree to 32 dB (the goal; measured 32.3 dB on the dam break, where
/// `auto` takes two steps; with the same grid cell for both, 34.5 dB: most of the difference is
/// the cell, one for the frame from the finest level used, 0.0186 against 0.0101, whose surfels
/// draw the box's edges a little differently). The double dam break stays at three steps
/// (`auto` is `fixed` there). Holes: the goal (no more than `fixed`'s and at most 0.1 % of the
/// silhouette) is not met on the dam break, 0.164 % against 0.105 % (background between the
/// splash's drops); the bound keeps it from growing.
#[test]
fn auto_and_fixed_pictures_agree() {
    for (name, psnr_bound, holes_bound) in [
        ("dam_break_frame_23_24389_particles.bgeo", 32.0, 0.0025),
        ("double_dam_break_frame_26_4732_particles.vtk", 40.0, 0.001),
    ] {
        let set = data(name);
        let mut camera = None;
        let mut images = Vec::new();
        for detail in [Detail::Fixed, Detail::Auto] {
            let mut p = PipelineParams {
                detail,
                ..Default::default()
            };
            p.scene.optics.image_size = [640, 480];
            let mut pipeline = Pipeline::new(p).unwrap();
            if let Some(c) = camera {
                pipeline.set_camera(c);
            }
            let f = pipeline.frame_through(&set, Through::Splats).unwrap();
            camera = pipeline.camera();
            let r = f.splats.unwrap();
            let covered: Vec<bool> = r.colour.iter().map(|c| c[3] > 0.0).collect();
            let h = fluid_surfels::quality::holes(&covered, 640, 480, 3);
            println!(
                "{name} {}: {:?}, enclosed holes {:.3} %",
                detail.as_str(),
                f.detail,
                100.0 * h.enclosed_fraction()
            );
            assert!(h.enclosed_fraction() <= holes_bound, "{name}: {h:?}");
            images.push(r.image);
        }
        let db = splat::psnr(&images[0], &images[1]);
        println!("{name}: auto against fixed {db:.1} dB");
        assert!(db >= psnr_bound, "{name}: {db} dB");
    }
}

/// The mean change per pixel and channel between consecutive shaded splats of the column's
/// frames `first..=last` at `size`, the camera fitted on the first and kept, with `detail`; and
/// the refined points per level and the particles that changed level in each frame.
fn popping(
    detail: Detail,
    size: u32,
    first: usize,
    last: usize,
) -> (f64, Vec<(Vec<usize>, usize)>) {
    use fluid_surfels::pipeline::column_params;
    use fluid_surfels::scenes::ColumnSim;
    let mut p = column_params();
    p.detail = detail;
    p.scene.optics.image_size = [size, size];
    let mut pipeline = Pipeline::new(p).unwrap();
    let mut sim = ColumnSim::new(Default::default()).unwrap();
    let mut images = Vec::new();
    let mut levels = Vec::new();
    loop {
        let through = if sim.frame() >= first {
            Through::Splats
        } else {
            Through::Surface
        };
        let f = pipeline.frame_through(sim.particles(), through).unwrap();
        if let Some(r) = f.splats {
            images.push(r.image);
            levels.push((f.detail.points_per_level, f.detail.level_changes));
        }
        if sim.frame() >= last {
            break;
        }
        sim.step_frame();
    }
    let change = images
        .windows(2)
        .map(|w| {
            let (a, b) = (w[0].as_raw(), w[1].as_raw());
            let sum: f64 = a
                .chunks(4)
                .zip(b.chunks(4))
                .map(|(p, q)| (0..3).map(|c| f64::from(p[c].abs_diff(q[c]))).sum::<f64>())
                .sum();
            sum / (3.0 * 255.0 * (a.len() / 4) as f64)
        })
        .sum::<f64>()
        / (images.len() - 1) as f64;
    (change, levels)
}

/// A fixed-camera sequence (the column's frames 20 to 40, shaded splats at 192x192, where `auto`
/// mixes two and three steps): the mean frame-to-frame change of the pictures with `auto` is at
/// most 10 % above `fixed`'s (measured 0.01339 against 0.01345 per channel), and the level's
/// hysteresis (`LEVEL_HYSTERESIS`) keeps particles from flipping between levels as they move
/// across a level's border (measured: none in 20 frames; without the hysteresis 3-15 a frame,
/// 131 in all, though the pictures' change was no larger).
#[test]
fn a_sequence_does_not_pop() {
    let (fixed, _) = popping(Detail::Fixed, 192, 20, 40);
    let (auto, levels) = popping(Detail::Auto, 192, 20, 40);
    let changes: Vec<usize> = levels.iter().map(|l| l.1).collect();
    println!("mean change per frame: fixed {fixed:.5}, auto {auto:.5}; level changes {changes:?}");
    assert!(
        levels
            .iter()
            .all(|(l, _)| l.len() == 4 && l[2] > 0 && l[3] > 0),
        "the sequence should mix two and three steps: {levels:?}"
    );
    assert!(auto <= 1.1 * fixed, "auto {auto} against fixed {fixed}");
    assert!(changes.iter().sum::<usize>() <= 20, "{changes:?}");
}

/// The steps `auto` takes for the dam break drawn as `drawn` at 160x120, with the caustics
/// screen at `caustics` texels when given.
fn steps_drawn_as(set: &ParticleSet, drawn: Through, caustics: Option<[u32; 2]>) -> u32 {
    let mut p = PipelineParams {
        detail: Detail::Auto,
        ..Default::default()
    };
    p.scene.optics.image_size = [160, 120];
    p.scene.optics.caustics_resolution = caustics;
    let mut pipeline = Pipeline::new(p).unwrap();
    pipeline.set_drawn(Some(drawn));
    let f = pipeline.frame_through(set, Through::Surfels).unwrap();
    f.detail.steps
}

/// With the optics on, the light's screen counts too: a small picture's caustics keep the detail
/// their screen resolves (the dam break at 160x120: the shaded splats take fewer steps than the
/// finished frame, whose 256-texel caustics screen asks for two; a 1024-texel screen asks for
/// three).
#[test]
fn the_caustics_keep_their_detail() {
    let set = data("dam_break_frame_23_24389_particles.bgeo");
    let splats = steps_drawn_as(&set, Through::Splats, None);
    let frame = steps_drawn_as(&set, Through::Frame, None);
    let fine = steps_drawn_as(&set, Through::Frame, Some([1024, 1024]));
    println!(
        "steps at 160x120: splats {splats}, finished frame {frame}, 1024-texel caustics {fine}"
    );
    assert!(splats < frame, "{splats} against {frame}");
    assert_eq!(fine, 3);
}

/// EWA drawn as it is, but saying it does not cull the disks facing away from the eye: the
/// pipeline then makes every surfel of the frame.
struct Unculled;

impl WaterRenderer for Unculled {
    fn drawn(&self) -> Drawn {
        Ewa.drawn()
    }
    fn water<'a>(
        &self,
        input: WaterInput<'a>,
    ) -> Result<Box<dyn WaterSurface + 'a>, fluid_surfels::Error> {
        Ewa.water(input)
    }
}

/// With `detail = "auto"` a picture the pipeline draws leaves out the surfels facing away from
/// every view (the camera's, and for the finished frame the light's): the shaded splats and the
/// finished frame (its caustics map too) are the same, bit for bit, as from every surfel, and
/// far fewer surfels are made (measured: the double dam break's shaded splats 120,866 -> 75,931
/// surfels at 640x480; the dam break's finished frame 80,786 -> 61,576 at 400x300).
#[test]
fn a_picture_leaves_out_only_what_it_cannot_show() {
    let set = data("double_dam_break_frame_26_4732_particles.vtk");
    for through in [Through::Splats, Through::Frame] {
        let run = |culled: bool| {
            let mut p = PipelineParams {
                detail: Detail::Auto,
                ..Default::default()
            };
            p.scene.optics.image_size = [160, 120];
            let mut pipeline = Pipeline::new(p).unwrap();
            if !culled {
                pipeline.set_water_renderer(Box::new(Unculled));
            }
            pipeline.frame_through(&set, through).unwrap()
        };
        let (culled, all) = (run(true), run(false));
        let (kept, made) = (culled.detail.surfels, all.detail.surfels);
        println!("{through:?}: {kept} of {made} surfels kept");
        assert_eq!(culled.detail.refined_points, all.detail.refined_points);
        assert_eq!(all.detail.hidden_surfels, 0);
        assert_eq!(culled.detail.surfels + culled.detail.hidden_surfels, made);
        assert!(kept * 4 <= made * 3, "{kept} of {made} surfels kept");
        assert_eq!(culled.render_surfels.len(), kept);
        if through == Through::Splats {
            let (a, b) = (culled.splats.unwrap(), all.splats.unwrap());
            assert!(a.image == b.image, "the shaded splats differ");
        } else {
            let (a, b) = (culled.finished.unwrap(), all.finished.unwrap());
            assert!(a.caustics.flux == b.caustics.flux, "the caustics differ");
            assert!(a.image == b.image, "the finished frame differs");
        }
        // every kept surfel is one of the frame's, in the same order
        let every = all.surfels.unwrap();
        let mut next = every.positions.iter();
        for x in &culled.surfels.unwrap().positions {
            assert!(
                next.any(|y| y == x),
                "a kept surfel not made from every surfel"
            );
        }
    }
}
