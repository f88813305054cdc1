//! `fluid-surfels compare`: one frame, every renderer and surfel source from one camera on a
//! labelled contact sheet, each measured against the ray-cast reference (the exact first hit of
//! the particles' iso-surface, gradient normals, no filter).

use std::path::PathBuf;
use std::time::Instant;

use fluid_surfels::io::Format;
use fluid_surfels::pipeline::{
    Calibration, Detail, Pipeline, PipelineParams, Renderer, SurfelSource, Through,
};
use fluid_surfels::quality::{self, SurfaceDifference};
use fluid_surfels::raycast::RayNormals;
use fluid_surfels::scenes::SceneName;
use fluid_surfels::splat::{Camera, Light, Render, SplatParams, View};
use fluid_surfels::view::UpAxis;
use fluid_surfels::{Error, preview};
use serde::Serialize;

use super::{OutputKind, check_output, ms};

/// Arguments of `compare`.
#[derive(clap::Args)]
#[command(group = clap::ArgGroup::new("source").required(true).args(["input", "scene"]))]
pub struct CompareArgs {
    /// Particle file.
    #[arg(long)]
    pub input: Option<PathBuf>,
    /// Built-in scene.
    #[arg(long, value_parser = super::scene_parser())]
    pub scene: Option<SceneName>,
    /// Format of --input (default: from its extension).
    #[arg(long, value_parser = super::format_parser())]
    pub format: Option<Format>,
    /// Frame of the `column` scene (default: the splash). The frame runs through a fresh
    /// pipeline: no hysteresis from earlier frames.
    #[arg(long)]
    pub frame: Option<usize>,
    /// Support radius (default: the scene's, or twice the spacing estimated from the file).
    #[arg(long)]
    pub radius: Option<f32>,
    /// The file's up axis: x, y, z, -x, -y or -z (turned to +y before anything runs).
    #[arg(long, default_value = "y", value_parser = super::up_parser(), allow_hyphen_values = true)]
    pub up: UpAxis,
    /// Size of each panel, WIDTHxHEIGHT.
    #[arg(long, default_value = "320x240", value_parser = super::render::parse_size)]
    pub size: (u32, u32),
    /// The contact sheet (PNG).
    #[arg(long, default_value = "compare.png")]
    pub out: PathBuf,
    /// Replace an existing --out.
    #[arg(long)]
    pub force: bool,
    /// Print one JSON object with every method's figures instead of the table.
    #[arg(long)]
    pub json: bool,
    /// Refinement steps of the chain and refined sources (the `refine.steps` key; default 3,
    /// the paper's).
    #[arg(long)]
    pub steps: Option<u32>,
    /// Where the chain's iso-surface lies: paper (eq. 1's sums) or boundary (half a spacing
    /// outside the outermost particles at every level; the `grid.calibration` key).
    #[arg(long, value_parser = super::names_parser(&[Calibration::Paper, Calibration::Boundary], Calibration::as_str), default_value = "boundary")]
    pub calibration: Calibration,
    /// Add the chain (EWA) at 0, 1, 2 and 3 refinement steps to the sheet, to compare the levels
    /// of detail (with the default calibration, boundary, each at the fluid's boundary).
    #[arg(long)]
    pub levels: bool,
    /// How much of --steps the chain's upsampling takes: fixed (default here: every method at
    /// the paper's level, whatever the image size) or auto (detail from the view, as `render`);
    /// the --levels panels are always fixed at their level.
    #[arg(long, value_parser = super::names_parser(&Detail::ALL, Detail::as_str), default_value = "fixed")]
    pub detail: Detail,
}

/// The sources' names of the chain at each level of `--levels`.
const LEVELS: [&str; 4] = [
    "chain, 0 steps",
    "chain, 1 step",
    "chain, 2 steps",
    "chain, 3 steps",
];

/// The methods of the sheet, after the reference: every renderer of the library with every
/// surfel source, but ray casting from the refined points (the sheet's twelfth panel is the
/// reference, rays cast to the particles).
fn methods() -> Vec<(Renderer, SurfelSource)> {
    Renderer::ALL
        .into_iter()
        .flat_map(|r| SurfelSource::ALL.map(|s| (r, s)))
        .filter(|&m| m != (Renderer::RayCast, SurfelSource::Refined))
        .collect()
}

/// One method's figures.
#[derive(Serialize)]
struct MethodReport {
    renderer: &'static str,
    source: &'static str,
    /// The whole frame through the pipeline to the shaded image (detection, upsampling, grid,
    /// surfels where the method needs them, and the drawing).
    ms: f64,
    /// The drawing alone.
    render_ms: f64,
    /// Surfels or spheres drawn.
    drawn: usize,
    covered_pixels: usize,
    /// Against the reference: depths in particle spacings, normals in degrees.
    against_reference: SurfaceDifference,
}

#[derive(Serialize)]
struct CompareReport {
    source: String,
    particles: usize,
    support_radius: f32,
    spacing: f32,
    width: u32,
    height: u32,
    camera: Camera,
    reference: MethodReport,
    methods: Vec<MethodReport>,
    output: String,
}

/// One method through a fresh pipeline, from `camera`.
fn run_method(
    args: &CompareArgs,
    set: &fluid_surfels::ParticleSet,
    (radius, camera): (f32, Camera),
    (renderer, source): (Renderer, SurfelSource),
    exact: bool,
    steps: Option<u32>,
) -> Result<(Render, f64, f64, usize), Error> {
    let size = args.size;
    let mut params = PipelineParams {
        support_radius: Some(radius),
        renderer,
        source,
        ..Default::default()
    };
    if let Some(k) = steps.or(args.steps) {
        params.refine.steps = k;
    }
    // a panel of --levels is its level
    params.detail = if steps.is_some() {
        Detail::Fixed
    } else {
        args.detail
    };
    params.grid.calibration = args.calibration;
    params.scene.optics.image_size = [size.0, size.1];
    if exact {
        params.raycast.normals = RayNormals::Gradient;
        params.raycast.bilateral_radius_px = 0;
    }
    let mut pipeline = Pipeline::new(params)?;
    pipeline.set_camera(camera);
    let t = Instant::now();
    let frame = pipeline.frame_through(set, Through::Splats)?;
    let total = ms(t);
    let drawn = frame.render_surfels.len();
    let render = frame.splats.expect("run through the splats");
    Ok((render, total, frame.timings.splats_ms, drawn))
}

pub fn compare_command(args: &CompareArgs) -> Result<(), Error> {
    check_output(
        &args.out,
        args.input.as_deref(),
        args.force,
        OutputKind::Single,
    )?;
    let (source, positions, radius) = super::positions_of(
        args.input.as_deref(),
        args.scene,
        args.format,
        args.frame,
        args.radius,
    )?;
    let positions = super::turned(&positions, args.up);
    let set = fluid_surfels::ParticleSet::from_positions(positions);
    set.validate()?;
    let spacing = fluid_surfels::neighbours::estimate_spacing(&set.positions)?;
    let (lo, hi) = preview::bounds_or_unit(&set.positions);
    let camera = Camera::framing(lo - radius, hi + radius);
    let view = View::new(
        &camera,
        &Light::default(),
        &SplatParams::default(),
        args.size.0,
        args.size.1,
    )?;
    let extra = if args.levels { LEVELS.len() } else { 0 };
    let methods_run = methods();
    let bar = super::progress((methods_run.len() + extra) as u64 + 1, "renderers");
    let reference = run_method(
        args,
        &set,
        (radius, camera),
        (Renderer::RayCast, SurfelSource::Particles),
        true,
        None,
    )?;
    bar.inc(1);
    let report_of = |(renderer, source): (Renderer, SurfelSource),
                     r: &(Render, f64, f64, usize)| {
        MethodReport {
            renderer: renderer.as_str(),
            source: source.as_str(),
            ms: r.1,
            render_ms: r.2,
            drawn: r.3,
            covered_pixels: r.0.covered_pixels(),
            against_reference: quality::against(&r.0, &reference.0, &view, spacing),
        }
    };
    let mut panels = Vec::new();
    let mut methods = Vec::new();
    let rgb = |r: &Render| image::DynamicImage::ImageRgba8(r.image.clone()).to_rgb8();
    let mut first = rgb(&reference.0);
    preview::label(&mut first, 0, 0, "reference: ray-cast particles", 1);
    preview::label(&mut first, 0, 10, "exact normals, no filter", 1);
    panels.push(first);
    let levels = if args.levels {
        0..LEVELS.len() as u32
    } else {
        0..0
    };
    let runs = methods_run
        .into_iter()
        .map(|m| (m, None))
        .chain(levels.map(|k| ((Renderer::Ewa, SurfelSource::Chain), Some(k))));
    for (method, steps) in runs {
        let r = run_method(args, &set, (radius, camera), method, false, steps)?;
        let mut m = report_of(method, &r);
        if let Some(k) = steps {
            m.source = LEVELS[k as usize];
        }
        let mut panel = rgb(&r.0);
        preview::label(
            &mut panel,
            0,
            0,
            &format!("{} / {} {:.0} ms", m.renderer, m.source, m.ms),
            1,
        );
        let d = &m.against_reference;
        preview::label(
            &mut panel,
            0,
            10,
            &format!(
                "depth {:.2}sp normal {:.1}deg cov {:.1}%",
                d.depth_mean,
                d.normal_mean_degrees,
                100.0 * d.coverage_difference
            ),
            1,
        );
        panels.push(panel);
        methods.push(m);
        bar.inc(1);
    }
    bar.finish_and_clear();
    preview::save_png(&preview::grid(&panels, 4), &args.out)?;
    let report = CompareReport {
        source,
        particles: set.len(),
        support_radius: radius,
        spacing,
        width: args.size.0,
        height: args.size.1,
        camera,
        reference: report_of((Renderer::RayCast, SurfelSource::Particles), &reference),
        methods,
        output: args.out.display().to_string(),
    };
    if args.json {
        super::print_json(&report);
        return Ok(());
    }
    print_table(&report);
    println!("  wrote {}", report.output);
    Ok(())
}

/// The report as the table on stdout.
fn print_table(report: &CompareReport) {
    println!(
        "{}: {} particles, support radius {}, spacing {:.4}; {}x{} per panel; against the ray-cast reference ({:.0} ms, {} pixels):",
        report.source,
        report.particles,
        report.support_radius,
        report.spacing,
        report.width,
        report.height,
        report.reference.ms,
        report.reference.covered_pixels
    );
    println!(
        "  {:<15} {:<15} {:>9} {:>10} {:>9} {:>12} {:>11} {:>12} {:>11} {:>9}",
        "renderer",
        "source",
        "ms",
        "render ms",
        "pixels",
        "depth mean",
        "depth p95",
        "normal mean",
        "normal p95",
        "coverage"
    );
    for m in &report.methods {
        let d = &m.against_reference;
        println!(
            "  {:<15} {:<15} {:>9.1} {:>10.1} {:>9} {:>9.3} sp {:>8.3} sp {:>8.2} deg {:>7.2} deg {:>7.2} %",
            m.renderer,
            m.source,
            m.ms,
            m.render_ms,
            m.covered_pixels,
            d.depth_mean,
            d.depth_p95,
            d.normal_mean_degrees,
            d.normal_p95_degrees,
            100.0 * d.coverage_difference
        );
    }
}
