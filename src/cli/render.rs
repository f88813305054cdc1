//! `fluid-surfels render`: particles through the pipeline to surfels, or a user's own surfels,
//! rendered by EWA splatting (Botsch et al. 2005) to a PNG.

use std::path::PathBuf;
use std::time::Instant;

use fluid_surfels::Error;
use fluid_surfels::gpu::{self, GpuContext};
use fluid_surfels::io::{self, Format};
use fluid_surfels::scenes::SceneName;
use fluid_surfels::sequence::{FramePattern, FrameRange};
use fluid_surfels::splat::{self, Camera, Light, Render, SplatMode, SplatParams, Surfel};
use fluid_surfels::surfels::SurfelParams;
use glam::Vec3;
use serde::Serialize;

use super::{check_output, ms};

/// Arguments of `render`.
#[derive(clap::Args)]
#[command(group = clap::ArgGroup::new("what").required(true).args(["input", "scene", "surfels"]))]
pub struct RenderArgs {
    /// Particle file: density grid and surfels are made from it, then rendered.
    #[arg(long)]
    pub input: Option<PathBuf>,
    /// Built-in scene (particles).
    #[arg(long, value_enum)]
    pub scene: Option<SceneName>,
    /// A file of surfels to render as they are: positions, normals (nx ny nz), a `radius`
    /// attribute, optional colours (red green blue).
    #[arg(long)]
    pub surfels: Option<PathBuf>,
    /// Format of --input or --surfels (default: from the extension).
    #[arg(long, value_enum)]
    pub format: Option<Format>,
    /// Frame of the `column` scene (default: the splash).
    #[arg(long)]
    pub frame: Option<usize>,
    /// Support radius of the particles, the density kernel's h (default: the scene's, or twice
    /// the spacing estimated from the file).
    #[arg(long)]
    pub radius: Option<f32>,
    /// Density grid points along the longest axis.
    #[arg(long, default_value_t = 128)]
    pub resolution: u32,
    /// Image size, WIDTHxHEIGHT.
    #[arg(long, default_value = "800x600", value_parser = parse_size)]
    pub size: (u32, u32),
    /// Camera: EYE_X,EYE_Y,EZE_Z,TARGET_X,TARGET_Y,TARGET_Z[,FOV_Y_DEGREES] (default: framing
    /// the surfels from the front, right and above).
    #[arg(long, value_parser = parse_camera, allow_hyphen_values = true)]
    pub camera: Option<Camera>,
    /// Draw plain point sprites instead of EWA splats (for comparison).
    #[arg(long)]
    pub sprites: bool,
    /// Depth offset epsilon in surfel radii (default 1).
    #[arg(long)]
    pub depth_offset: Option<f32>,
    /// Screen-space low-pass radius in pixels (default 1; 0 switches it off).
    #[arg(long)]
    pub low_pass: Option<f32>,
    /// Render on the GPU (an error without an adapter). Default: the GPU when one is found,
    /// otherwise the CPU reference.
    #[arg(long, conflicts_with = "cpu")]
    pub gpu: bool,
    /// Render with the CPU reference.
    #[arg(long)]
    pub cpu: bool,
    /// Render the finished frame (refraction, reflection, caustics; Iwasaki et al. §5) instead
    /// of the shaded splats. Implied by --config, --frames and --caustics-resolution.
    #[arg(long)]
    pub optics: bool,
    /// Scene file (TOML: camera, light, receiver, water, environment, optics); see the README.
    /// Default: a pool around the water, sunlight, clear water.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Frames to render as a sequence: A..B or A..=B with an optional :STEP; frames of the
    /// `column` scene, or of an --input pattern holding `{}`. --out is then a folder that
    /// receives frame_NNNN.png.
    #[arg(long)]
    pub frames: Option<FrameRange>,
    /// Virtual screen of the caustics, WIDTHxHEIGHT (default: 256 on the water's longer side).
    #[arg(long, value_parser = parse_size)]
    pub caustics_resolution: Option<(u32, u32)>,
    /// The PNG to write (a folder with --frames).
    #[arg(long, default_value = "render.png")]
    pub out: PathBuf,
    /// Replace an existing output file.
    #[arg(long)]
    pub force: bool,
    /// Print one JSON object of statistics on stdout instead of text.
    #[arg(long)]
    pub json: bool,
}

pub fn parse_size(s: &str) -> Result<(u32, u32), String> {
    let (w, h) = s
        .split_once(['x', 'X'])
        .ok_or_else(|| format!("`{s}`: expected WIDTHxHEIGHT, such as 800x600"))?;
    let parse = |v: &str| {
        v.trim()
            .parse::<u32>()
            .map_err(|e| format!("`{s}`: `{v}` is not a size in pixels ({e})"))
    };
    let (w, h) = (parse(w)?, parse(h)?);
    if w == 0 || h == 0 || w > splat::MAX_SIZE || h > splat::MAX_SIZE {
        return Err(format!(
            "`{s}`: each side must be between 1 and {}",
            splat::MAX_SIZE
        ));
    }
    Ok((w, h))
}

fn parse_camera(s: &str) -> Result<Camera, String> {
    let v: Vec<f32> = s
        .split(',')
        .map(|x| {
            x.trim()
                .parse::<f32>()
                .map_err(|e| format!("`{x}` is not a number ({e})"))
        })
        .collect::<Result<_, _>>()?;
    if v.len() != 6 && v.len() != 7 {
        return Err(format!(
            "expected 6 or 7 numbers (eye, target, optional field of view), got {}",
            v.len()
        ));
    }
    let eye = Vec3::new(v[0], v[1], v[2]);
    let target = Vec3::new(v[3], v[4], v[5]);
    let distance = (target - eye).length();
    Ok(Camera {
        eye,
        target,
        fov_y_degrees: v.get(6).copied().unwrap_or(40.0),
        near: (distance * 1e-3).max(1e-4),
        far: distance * 100.0 + 1.0,
        ..Camera::default()
    })
}

/// The GPU context to render with: `--gpu` needs one, `--cpu` takes none, otherwise one when
/// an adapter is found.
pub fn choose_gpu(cpu: bool, gpu: bool) -> Result<Option<GpuContext>, Error> {
    if cpu {
        return Ok(None);
    }
    match GpuContext::headless() {
        Ok(c) => Ok(Some(c)),
        Err(e) if gpu => Err(e.into()),
        Err(_) => Ok(None),
    }
}

/// Renders on the GPU when a context is given, else with the CPU reference.
pub fn render_with(
    ctx: Option<&GpuContext>,
    surfels: &[Surfel],
    camera: &Camera,
    params: &SplatParams,
    (width, height): (u32, u32),
) -> Result<Render, Error> {
    let light = Light::default();
    Ok(match ctx {
        Some(ctx) => gpu::splat::render_gpu(ctx, surfels, camera, &light, params, width, height)?,
        None => splat::render_cpu(surfels, camera, &light, params, width, height)?,
    })
}

/// A camera framing the surfels (or the unit box when none is drawable).
pub fn framing(surfels: &[Surfel]) -> Camera {
    let (lo, hi) = splat::bounds(surfels).unwrap_or((Vec3::ZERO, Vec3::ONE));
    Camera::framing(lo, hi)
}

#[derive(Serialize)]
struct RenderReport {
    source: String,
    particles: Option<usize>,
    surfels: usize,
    skipped_surfels: usize,
    width: u32,
    height: u32,
    mode: SplatMode,
    backend: String,
    camera: Camera,
    covered_pixels: usize,
    surfels_ms: f64,
    render_ms: f64,
    output: String,
}

pub fn render_command(args: &RenderArgs) -> Result<(), Error> {
    if args.optics
        || args.config.is_some()
        || args.frames.is_some()
        || args.caustics_resolution.is_some()
    {
        return render_optics(args);
    }
    let input = args.input.as_deref().or(args.surfels.as_deref());
    check_output(&args.out, input, args.force)?;
    let t = Instant::now();
    let (source, particles, surfels) = if let Some(path) = &args.surfels {
        let set = io::read_particles(path, args.format)?;
        (
            path.display().to_string(),
            None,
            splat::surfels_from_particles(&set)?,
        )
    } else {
        let (source, positions, radius) = super::positions_of(
            args.input.as_deref(),
            args.scene,
            args.format,
            args.frame,
            args.radius,
        )?;
        let (s, ..) = super::surfels::surfels_of(
            &positions,
            radius,
            args.resolution,
            SurfelParams::default().iso_fraction,
        )?;
        (
            source,
            Some(positions.len()),
            splat::surfels_from(&s.positions, &s.normals, &s.radii, splat::WATER),
        )
    };
    let surfels_ms = ms(t);
    let defaults = SplatParams::default();
    let params = SplatParams {
        mode: if args.sprites {
            SplatMode::Sprites
        } else {
            SplatMode::Ewa
        },
        depth_offset: args.depth_offset.unwrap_or(defaults.depth_offset),
        low_pass_px: args.low_pass.unwrap_or(defaults.low_pass_px),
        ..defaults
    };
    let camera = args.camera.unwrap_or_else(|| framing(&surfels));
    let ctx = choose_gpu(args.cpu, args.gpu)?;
    let t = Instant::now();
    let render = render_with(ctx.as_ref(), &surfels, &camera, &params, args.size)?;
    let render_ms = ms(t);
    fluid_surfels::preview::save_png(
        &image::buffer::ConvertBuffer::convert(&render.image),
        &args.out,
    )?;
    let skipped = surfels.iter().filter(|s| !s.is_drawable()).count();
    let report = RenderReport {
        source,
        particles,
        surfels: surfels.len(),
        skipped_surfels: skipped,
        width: args.size.0,
        height: args.size.1,
        mode: params.mode,
        backend: match ctx.as_ref().and_then(|c| c.adapter.as_ref()) {
            Some(a) => format!("gpu: {} ({})", a.name, a.backend),
            None => "cpu reference".into(),
        },
        camera,
        covered_pixels: render.covered_pixels(),
        surfels_ms,
        render_ms,
        output: args.out.display().to_string(),
    };
    if args.json {
        super::print_json(&report);
    } else {
        println!(
            "{}: {} surfels ({} skipped as undrawable){}",
            report.source,
            report.surfels,
            report.skipped_surfels,
            report
                .particles
                .map(|p| format!(" from {p} particles in {surfels_ms:.0} ms"))
                .unwrap_or_default()
        );
        println!(
            "  {}x{} {:?} on the {}: {:.1} ms, {} pixels covered",
            report.width,
            report.height,
            report.mode,
            report.backend,
            render_ms,
            report.covered_pixels
        );
        println!("  wrote {}", report.output);
    }
    Ok(())
}

/// Surfels of one frame: from a surfel file, or particles through the density stage.
fn frame_surfels(
    args: &RenderArgs,
    input: Option<&std::path::Path>,
    frame: Option<usize>,
) -> Result<(String, Vec<Surfel>), Error> {
    if let Some(path) = &args.surfels {
        let set = io::read_particles(path, args.format)?;
        return Ok((
            path.display().to_string(),
            splat::surfels_from_particles(&set)?,
        ));
    }
    let (source, positions, radius) =
        super::positions_of(input, args.scene, args.format, frame, args.radius)?;
    let (s, ..) = super::surfels::surfels_of(
        &positions,
        radius,
        args.resolution,
        SurfelParams::default().iso_fraction,
    )?;
    Ok((
        source,
        splat::surfels_from(&s.positions, &s.normals, &s.radii, splat::WATER),
    ))
}

#[derive(Serialize)]
struct OpticsFrameReport {
    source: String,
    frame: Option<usize>,
    output: String,
    #[serde(flatten)]
    stats: super::optics::FrameReport,
}

/// `render` with optics: one finished frame, or a numbered sequence of them.
fn render_optics(args: &RenderArgs) -> Result<(), Error> {
    let mut scene = match &args.config {
        Some(path) => fluid_surfels::optics::OpticsScene::from_toml_file(path)?,
        None if args.scene == Some(SceneName::Column) => {
            fluid_surfels::scenes::column_pool(fluid_surfels::scenes::ColumnParams::default().tank)
        }
        None => Default::default(),
    };
    if let Some((w, h)) = args.caustics_resolution {
        scene.optics.caustics_resolution = Some([w, h]);
    }
    // --size keeps its default unless given; the scene file's image size wins over the default
    if args.size != (800, 600) || args.config.is_none() {
        scene.optics.image_size = [args.size.0, args.size.1];
    }
    if let Some(c) = args.camera {
        scene.camera = Some(c);
    }
    // an environment image is read once for the whole sequence, not by every frame's stage
    scene.environment.load()?;
    let renderer = super::optics::FrameRenderer::new(choose_gpu(args.cpu, args.gpu)?)?;
    let Some(range) = args.frames else {
        check_output(
            &args.out,
            args.input.as_deref().or(args.surfels.as_deref()),
            args.force,
        )?;
        let (source, surfels) = frame_surfels(args, args.input.as_deref(), args.frame)?;
        let f = renderer.finish(&scene, &surfels)?;
        super::optics::save(&f.image, &args.out)?;
        return report_frame(args, source, None, &args.out, f.report);
    };
    if args.surfels.is_some() {
        return Err(Error::InvalidArgument {
            argument: "--frames",
            reason: "needs --scene column or an --input pattern with {}".into(),
        });
    }
    let pattern = match &args.input {
        Some(p) => Some(
            FramePattern::parse(&p.display().to_string())?.ok_or_else(|| {
                Error::InvalidArgument {
                    argument: "--input",
                    reason:
                        "with --frames the input must be a pattern holding {}, such as frame_{}.vtk"
                            .into(),
                }
            })?,
        ),
        None => None,
    };
    if pattern.is_none() && args.scene != Some(SceneName::Column) {
        return Err(Error::InvalidArgument {
            argument: "--frames",
            reason: "only the `column` scene has frames".into(),
        });
    }
    std::fs::create_dir_all(&args.out).map_err(|e| Error::InvalidArgument {
        argument: "--out",
        reason: format!("{}: {e}", args.out.display()),
    })?;
    let frames: Vec<usize> = range.frames().collect();
    let bar = super::progress(frames.len() as u64, "rendering");
    for &frame in &frames {
        let out = args.out.join(format!("frame_{frame:04}.png"));
        check_output(&out, None, args.force)?;
        let path = pattern.as_ref().map(|p| p.path(frame));
        let (source, surfels) = frame_surfels(args, path.as_deref(), Some(frame))?;
        let f = renderer.finish(&scene, &surfels)?;
        super::optics::save(&f.image, &out)?;
        bar.suspend(|| report_frame(args, source, Some(frame), &out, f.report))?;
        bar.inc(1);
    }
    bar.finish_and_clear();
    Ok(())
}

fn report_frame(
    args: &RenderArgs,
    source: String,
    frame: Option<usize>,
    out: &std::path::Path,
    stats: super::optics::FrameReport,
) -> Result<(), Error> {
    let r = OpticsFrameReport {
        source,
        frame,
        output: out.display().to_string(),
        stats,
    };
    if args.json {
        super::print_json(&r);
    } else {
        println!(
            "{}{}: {} surfels; caustics {}x{} screen, {}x{} map{}, {:.1} ms; frame {}x{} on the {}, {:.1} ms; wrote {}",
            r.source,
            frame.map(|f| format!(" frame {f}")).unwrap_or_default(),
            r.stats.surfels,
            r.stats.screen[0],
            r.stats.screen[1],
            r.stats.map[0],
            r.stats.map[1],
            r.stats
                .caustics_triangles
                .map(|t| format!(", {t} triangles"))
                .unwrap_or_default(),
            r.stats.caustics_ms,
            r.stats.image[0],
            r.stats.image[1],
            r.stats.backend,
            r.stats.frame_ms,
            r.output
        );
    }
    Ok(())
}
