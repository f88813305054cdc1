//! `fluid-surfels render`: particles through the pipeline to surfels, or a user's own surfels,
//! rendered by EWA splatting (Botsch et al. 2005), or as the finished frame with optics, to a
//! PNG; a sequence of frames through one pipeline (hysteresis, camera and pool kept).

use std::path::PathBuf;
use std::time::Instant;

use fluid_surfels::Error;
use fluid_surfels::density::Resolution;
use fluid_surfels::gpu::GpuContext;
use fluid_surfels::io::{self, Format};
use fluid_surfels::pipeline::{
    self, Calibration, Detail, DetailReport, GpuPipeline, Pipeline, PipelineParams, Renderer,
    SurfelSource, Through,
};
use fluid_surfels::scenes::{self, ColumnParams, ColumnSim, SceneName};
use fluid_surfels::sequence::{FramePattern, FrameRange};
use fluid_surfels::splat::{self, Camera, SplatMode, Surfel};
use fluid_surfels::ssfr::DepthFilter;
use fluid_surfels::view::UpAxis;
use glam::Vec3;
use serde::Serialize;

use super::{OutputKind, check_output, ms};

/// Arguments of `render`.
#[derive(clap::Args)]
#[command(group = clap::ArgGroup::new("what").required(true).args(["input", "scene", "surfels"]))]
pub struct RenderArgs {
    /// Particle file: density grid and surfels are made from it, then rendered.
    #[arg(long)]
    pub input: Option<PathBuf>,
    /// Built-in scene (particles).
    #[arg(long, value_parser = super::scene_parser())]
    pub scene: Option<SceneName>,
    /// A file of surfels to render as they are: positions, normals (nx ny nz), a `radius`
    /// attribute, optional colours (red green blue).
    #[arg(long)]
    pub surfels: Option<PathBuf>,
    /// Format of --input or --surfels (default: from the extension).
    #[arg(long, value_parser = super::format_parser())]
    pub format: Option<Format>,
    /// Frame of the `column` scene (default: the splash).
    #[arg(long)]
    pub frame: Option<usize>,
    /// Support radius of the particles, the density kernel's h (default: the scene's, or twice
    /// the spacing estimated from the file).
    #[arg(long)]
    pub radius: Option<f32>,
    /// Where the rendered surfels come from: chain (the refined surface and the interior
    /// particles in one density grid), particles (the density grid of the raw particles) or
    /// refined (the refined points as surfels).
    #[arg(long, value_parser = super::names_parser(&SurfelSource::ALL, SurfelSource::as_str), default_value = "chain")]
    pub source: SurfelSource,
    /// How the surface is drawn: ewa (EWA surface splatting of the source's surfels),
    /// particle-splat (Adams et al. 2006: the source's points as spheres of their kernel
    /// radius, blended within 1.5 radii of the nearest; no density grid), ray-cast (Xiao et
    /// al.: rays cast to the iso-surface of the source's points, PCA-blended normals; the
    /// reference surface), or ssfr (Oliveira and Paiva: narrow-band screen-space fluid
    /// rendering, the source's points as spheres in a depth buffer, filtered), in the shaded
    /// splats and in the finished frame alike.
    #[arg(long, value_parser = super::names_parser(&Renderer::ALL, Renderer::as_str), default_value = "ewa")]
    pub renderer: Renderer,
    /// The depth filter of --renderer ssfr: narrow-range (Truong and Yuksel 2018), bilateral
    /// (Green 2010), plane (plane fitting, Imai et al. 2016), curvature-flow (van der Laan et
    /// al. 2009) or none; 7x7, 4 iterations (30 for curvature flow).
    #[arg(long, value_parser = super::names_parser(&DepthFilter::ALL, DepthFilter::as_str), default_value = "narrow-range")]
    pub filter: DepthFilter,
    /// With --renderer ssfr: draw every point's depth and take the thickness from every point
    /// (eq. 1), instead of the narrow band's particles and voxels (eq. 3).
    #[arg(long)]
    pub no_narrow_band: bool,
    /// Density grid points along the longest axis (default: spacing a third of the smallest
    /// kernel radius in use, within the grid's memory budget).
    #[arg(long)]
    pub resolution: Option<u32>,
    /// Image size, WIDTHxHEIGHT.
    #[arg(long, default_value = "800x600", value_parser = parse_size)]
    pub size: (u32, u32),
    /// Camera: EYE_X,EYE_Y,EYE_Z,TARGET_X,TARGET_Y,TARGET_Z[,FOV_Y_DEGREES] (default: framing
    /// the surfels from the front, right and above).
    #[arg(long, value_parser = parse_camera, allow_hyphen_values = true)]
    pub camera: Option<Camera>,
    /// A flat background colour R,G,B (0-255, as written in the PNG), for compositing and for
    /// checks: the shaded splats' empty pixels, or the constant environment of the finished
    /// frame (reflections show it too).
    #[arg(long, value_parser = parse_rgb)]
    pub background: Option<[u8; 3]>,
    /// Paint the holes (background inside the silhouette closed by 3 pixels, as counted in the
    /// report) magenta in the shaded splats, to see where they are.
    #[arg(long)]
    pub mark_holes: bool,
    /// The up axis of --input or --surfels: x, y, z, -x, -y or -z (Houdini and Blender write
    /// z-up). The file's points and --camera (given in the file's coordinates, its up the axis)
    /// are turned so that the axis points up (+y) before anything runs, so the pool's floor, the
    /// sunlight and the sky follow it. A --config scene file is read in the turned, y-up
    /// coordinates.
    #[arg(long, default_value = "y", value_parser = super::up_parser(), allow_hyphen_values = true)]
    pub up: UpAxis,
    /// Paint the specks (pixels darker than 0.6x the median of their 7x7 neighbourhood, as
    /// counted in the report) red in the finished frame, to see where they are.
    #[arg(long)]
    pub mark_specks: bool,
    /// Draw plain point sprites instead of EWA splats (for comparison).
    #[arg(long, conflicts_with = "renderer")]
    pub sprites: bool,
    /// Depth offset epsilon in surfel radii (default 1; with --renderer particle-splat in
    /// sphere radii, default 1.5).
    #[arg(long)]
    pub depth_offset: Option<f32>,
    /// Screen-space low-pass radius in pixels (default 1; 0 switches it off).
    #[arg(long)]
    pub low_pass: Option<f32>,
    /// The most pixel fragments a render may cost (the sum of the splats' screen rectangles,
    /// counted before drawing); more is refused with the count (default 10^9, about a minute
    /// of the CPU reference on two cores).
    #[arg(long)]
    pub max_fragments: Option<u64>,
    /// Render on the GPU (an error without an adapter; a software one such as lavapipe is taken
    /// too). Default: a hardware GPU when one is found, otherwise the CPU reference.
    #[arg(long, conflicts_with = "cpu")]
    pub gpu: bool,
    /// Render with the CPU reference.
    #[arg(long)]
    pub cpu: bool,
    /// Render the finished frame (refraction, reflection, caustics; Iwasaki et al. §5) instead
    /// of the shaded splats. Implied by --config, --frames and --caustics-resolution.
    #[arg(long)]
    pub optics: bool,
    /// Scene and pipeline file (TOML: camera, light, receiver, water, environment, optics, and
    /// the stages' tables); see docs/parameters.md. Default: a pool around the water (the tank for the
    /// column scene), sunlight, clear water.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Frames to render as a sequence: A..B or A..=B with an optional :STEP; frames of the
    /// `column` scene, or of an --input pattern holding `{}`. --out is then a folder that
    /// receives frame_NNNN.png.
    #[arg(long)]
    pub frames: Option<FrameRange>,
    /// With --frames: what the camera and the pool (kept for the whole sequence) are fitted to:
    /// `first`, the first frame's water, or `union`, the bounds of every frame's particles
    /// (read once before rendering; --input patterns only), so that water that moves or rises
    /// later stays in view. A camera or pool given by --camera or --config is kept as given.
    #[arg(long, value_enum, default_value = "first")]
    pub fit: FitChoice,
    /// Virtual screen of the caustics, WIDTHxHEIGHT (default: 256 on the water's longer side).
    #[arg(long, value_parser = parse_size)]
    pub caustics_resolution: Option<(u32, u32)>,
    /// Refinement steps of the chain and refined sources (the `refine.steps` key, over a
    /// --config file's; default 3, the paper's).
    #[arg(long)]
    pub steps: Option<u32>,
    /// Where the chain's iso-surface lies: paper (eq. 1's sums) or boundary (half a spacing
    /// outside the outermost particles at every level); the `grid.calibration` key, over a
    /// --config file's.
    #[arg(long, value_parser = super::names_parser(&Calibration::ALL, Calibration::as_str))]
    pub calibration: Option<Calibration>,
    /// How much of --steps the chain's upsampling takes: auto (detail from the view: each
    /// region stops once its points' spacing seen from the camera is under --detail-px pixels;
    /// regions outside the view are not refined) or fixed (every region all the steps); the
    /// `detail` key, over a --config file's (default auto).
    #[arg(long, value_parser = super::names_parser(&Detail::ALL, Detail::as_str))]
    pub detail: Option<Detail>,
    /// The footprint of --detail auto, in pixels (the `detail_px` key; default 1.5).
    #[arg(long)]
    pub detail_px: Option<f32>,
    /// Also write the level map of the detail: the chain's refined points from the picture's
    /// camera, coloured by the steps their region took (black 0, blue 1, red 2, yellow 3), a
    /// PNG of --size. The shaded splats only (not with --optics, --config or --frames).
    #[arg(long, conflicts_with_all = ["optics", "config", "frames", "caustics_resolution", "surfels"])]
    pub level_map: Option<PathBuf>,
    /// Also write the surfels the frame renders (positions, normals and a `radius` attribute:
    /// what --surfels reads back) to this particle file, in the coordinates of the rendering
    /// (turned by --up). One frame only, not with --frames. The frame is then refined with
    /// --detail fixed unless --detail is given, so that the file does not depend on the image
    /// size.
    #[arg(long, conflicts_with = "frames")]
    pub save_surfels: Option<PathBuf>,
    /// The PNG to write (a folder with --frames).
    #[arg(long, default_value = "render.png")]
    pub out: PathBuf,
    /// Replace an existing output file (with --frames: the frames that exist).
    #[arg(long)]
    pub force: bool,
    /// With --frames: keep the frames whose PNG exists and render only the others (resume an
    /// interrupted sequence; the camera and the pool are still fitted on the range's first
    /// frame).
    #[arg(long, conflicts_with = "force")]
    pub skip_existing: bool,
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

/// Comma-separated values of one type, each described as `what` in errors.
pub fn parse_list<T: std::str::FromStr>(s: &str, what: &str) -> Result<Vec<T>, String>
where
    T::Err: std::fmt::Display,
{
    s.split(',')
        .map(|x| {
            x.trim()
                .parse::<T>()
                .map_err(|e| format!("`{x}` is not {what} ({e})"))
        })
        .collect()
}

pub fn parse_rgb(s: &str) -> Result<[u8; 3], String> {
    match parse_list::<u8>(s, "a value from 0 to 255")?[..] {
        [r, g, b] => Ok([r, g, b]),
        _ => Err(format!("`{s}`: expected R,G,B such as 255,255,255")),
    }
}

fn parse_camera(s: &str) -> Result<Camera, String> {
    let v: Vec<f32> = parse_list(s, "a number")?;
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

/// `--fit`: what a sequence's camera and pool are fitted to.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum FitChoice {
    /// The first frame's water.
    First,
    /// The bounds of every frame's particles.
    Union,
}

/// The GPU context to render with: `--gpu` needs one (any adapter, a software one included),
/// `--cpu` takes none, otherwise a hardware adapter when one is found: a software rasteriser
/// (lavapipe) would run the GPU path slower than the CPU reference (measured: 1.3-3.2x for the
/// splatting renderers, 38-94x for ray casting; docs/cli.md).
pub fn choose_gpu(cpu: bool, gpu: bool) -> Result<Option<GpuContext>, Error> {
    if cpu {
        return Ok(None);
    }
    match GpuContext::headless() {
        Ok(c) if gpu => Ok(Some(c)),
        Ok(c) if c.adapter.as_ref().is_some_and(|a| a.is_software()) => Ok(None),
        Ok(c) => Ok(Some(c)),
        Err(e) if gpu => Err(e.into()),
        Err(_) => Ok(None),
    }
}

/// A camera framing the surfels (or the unit box when none is drawable).
pub fn framing(surfels: &[Surfel]) -> Camera {
    let (lo, hi) = splat::bounds(surfels).unwrap_or((Vec3::ZERO, Vec3::ONE));
    Camera::framing(lo, hi)
}

/// The pipeline's parameters from the command line: the scene file (or the defaults, the
/// column's tank for the column scene), then the flags over it.
fn pipeline_params(args: &RenderArgs) -> Result<PipelineParams, Error> {
    let mut p = match &args.config {
        Some(path) => PipelineParams::from_toml_file(path)?,
        None if args.scene == Some(SceneName::Column) => {
            super::run::column_params(Default::default())
        }
        None => PipelineParams::default(),
    };
    if args.radius.is_some() {
        p.support_radius = args.radius;
    }
    p.source = args.source;
    p.renderer = args.renderer;
    if let Some(k) = args.steps {
        p.refine.steps = k;
    }
    if let Some(c) = args.calibration {
        p.grid.calibration = c;
    }
    match (args.detail, &args.save_surfels) {
        (Some(d), _) => p.detail = d,
        // the surfels written to disk never depend on the image size unless asked for
        (None, Some(_)) => p.detail = Detail::Fixed,
        (None, None) => {}
    }
    if let Some(px) = args.detail_px {
        p.detail_px = px;
    }
    p.ssfr.filter = args.filter;
    if args.no_narrow_band {
        p.ssfr.narrow_band = false;
    }
    if let Some(r) = args.resolution {
        p.grid.resolution = Some(Resolution::LongestAxis(r));
    }
    if args.sprites {
        p.splat.mode = SplatMode::Sprites;
    }
    if let Some(d) = args.depth_offset {
        fluid_surfels::pipeline::water_renderer(&p).set_depth_offset(&mut p.splat, d);
    }
    if let Some(l) = args.low_pass {
        p.splat.low_pass_px = l;
    }
    if let Some(m) = args.max_fragments {
        p.splat.max_fragments = m;
        p.scene.optics.splat.max_fragments = m;
    }
    if let Some((w, h)) = args.caustics_resolution {
        p.scene.optics.caustics_resolution = Some([w, h]);
    }
    // --size keeps its default unless given; the scene file's image size wins over the default
    if args.size != (800, 600) || args.config.is_none() {
        p.scene.optics.image_size = [args.size.0, args.size.1];
    }
    if let Some(c) = args.camera {
        p.scene.camera = Some(turned_camera(c, args.up));
    }
    if let Some(rgb) = args.background {
        // the splats store their colour as it is; the finished frame encodes linear radiance
        // with gamma 2.2 (optics::encode)
        let unit = rgb.map(|c| f32::from(c) / 255.0);
        p.splat.background = [unit[0], unit[1], unit[2], 1.0];
        p.scene.environment.kind = fluid_surfels::optics::EnvironmentKind::Constant;
        p.scene.environment.colour = Vec3::from_array(unit.map(|c| c.powf(2.2)));
    }
    Ok(p)
}

/// A camera given in the file's coordinates, turned with the particles (`--up`).
fn turned_camera(c: Camera, up: UpAxis) -> Camera {
    // --camera's up is the file's up axis, which the turn makes +y
    let q = up.to_y_up();
    Camera {
        eye: q * c.eye,
        target: q * c.target,
        up: Vec3::Y,
        ..c
    }
}

/// Where the frames come from.
enum Frames {
    /// A user's surfels, rendered as they are.
    Surfels(PathBuf),
    /// One particle file, or a pattern with the frame number.
    File(PathBuf),
    Pattern(FramePattern),
    /// The column simulation, stepped frame by frame.
    Column(Box<ColumnSim>),
    /// Another built-in scene (static: built once, at `--frame`).
    Scene(SceneName, Box<scenes::Scene>),
}

impl Frames {
    /// The source of `args`, for `--frames` when `sequence`.
    fn of(args: &RenderArgs, sequence: bool) -> Result<Self, Error> {
        if let Some(p) = &args.surfels {
            if sequence {
                return Err(Error::InvalidArgument {
                    argument: "--frames",
                    reason: "needs --scene column or an --input pattern with {}".into(),
                });
            }
            return Ok(Self::Surfels(p.clone()));
        }
        if let Some(p) = &args.input {
            return match FramePattern::parse(&p.display().to_string())? {
                Some(pattern) => {
                    if !sequence {
                        return Err(Error::InvalidArgument {
                            argument: "--input",
                            reason: "a pattern holding {} needs --frames A..B".into(),
                        });
                    }
                    Ok(Self::Pattern(pattern))
                }
                None if sequence => Err(Error::InvalidArgument {
                    argument: "--input",
                    reason:
                        "with --frames the input must be a pattern holding {}, such as frame_{}.vtk"
                            .into(),
                }),
                None => Ok(Self::File(p.clone())),
            };
        }
        match args.scene {
            Some(SceneName::Column) => Ok(Self::Column(Box::new(ColumnSim::new(
                ColumnParams::default(),
            )?))),
            Some(_) if sequence => Err(Error::InvalidArgument {
                argument: "--frames",
                reason: "only the `column` scene has frames".into(),
            }),
            Some(name) => Ok(Self::Scene(
                name,
                Box::new(scenes::build(name, args.frame)?),
            )),
            None => Err(Error::InvalidArgument {
                argument: "--input/--scene/--surfels",
                reason: "one of them is needed".into(),
            }),
        }
    }

    /// The support radius the source implies when none is given (a built-in scene's own).
    fn support_radius(&self) -> Option<f32> {
        match self {
            Self::Column(sim) => Some(sim.support_radius()),
            Self::Scene(_, scene) => Some(scene.support_radius),
            _ => None,
        }
    }

    /// Frame `frame` through `pipeline` up to `through`, with a description of the source. The
    /// column scene runs surface detection on the frames it steps over (hysteresis).
    fn frame(
        &mut self,
        pipeline: &mut Pipeline,
        args: &RenderArgs,
        frame: Option<usize>,
        through: Through,
    ) -> Result<(String, Option<usize>, pipeline::Frame), Error> {
        let read = |path: &std::path::Path| {
            let mut set = super::read_particles(path, args.format)?;
            if args.up != UpAxis::Y {
                set.rotate(args.up.to_y_up());
            }
            Ok::<_, Error>(set)
        };
        Ok(match self {
            Self::Surfels(path) => {
                let set = read(path)?;
                let surfels = splat::surfels_from_particles(&set)?;
                let f = pipeline.frame_of_surfels(surfels, through)?;
                (path.display().to_string(), None, f)
            }
            Self::File(path) => {
                let set = read(path)?;
                let f = pipeline.frame_through(&set, through)?;
                (path.display().to_string(), Some(set.len()), f)
            }
            Self::Pattern(pattern) => {
                let path = pattern.path(frame.unwrap_or(0));
                let set = read(&path)?;
                let f = pipeline.frame_through(&set, through)?;
                (path.display().to_string(), Some(set.len()), f)
            }
            Self::Column(sim) => {
                let target = frame.unwrap_or(ColumnParams::SPLASH_FRAME);
                ColumnParams::check_frame(target)?;
                if sim.frame() > target {
                    return Err(Error::InvalidArgument {
                        argument: "--frames",
                        reason: "frames must increase".into(),
                    });
                }
                let f = pipeline::column_frame(pipeline, sim, target, through, |_| {})?;
                ("scene column".into(), Some(sim.particles().len()), f)
            }
            Self::Scene(name, scene) => {
                let f = pipeline.frame_through(&scene.particles, through)?;
                (
                    format!("scene {}", name.as_str()),
                    Some(scene.particles.len()),
                    f,
                )
            }
        })
    }
}

#[derive(Serialize)]
struct RenderReport {
    /// Particles dropped by `--bounds` (only with it).
    #[serde(skip_serializing_if = "Option::is_none")]
    outside_bounds: Option<usize>,
    source: String,
    particles: Option<usize>,
    surfel_source: Option<&'static str>,
    renderer: &'static str,
    surfels: usize,
    skipped_surfels: usize,
    width: u32,
    height: u32,
    mode: SplatMode,
    backend: String,
    camera: Camera,
    covered_pixels: usize,
    /// Background showing through inside the silhouette closed by 3 pixels (`quality::holes`).
    holes: fluid_surfels::quality::Holes,
    holes_fraction: f64,
    enclosed_holes_fraction: f64,
    surfels_ms: f64,
    render_ms: f64,
    /// The level of detail: steps run, refined points, grid cell, surfels.
    detail: DetailReport,
    warnings: Vec<String>,
    output: String,
}

fn backend_name(ctx: Option<&GpuContext>) -> String {
    match ctx {
        Some(c) => match &c.adapter {
            Some(a) => format!("gpu: {} ({})", a.name, a.backend),
            None => "gpu: given device".into(),
        },
        None => "cpu reference".into(),
    }
}

/// Whether `args` ask for the finished frame (the optics), not the shaded splats.
fn finished_frame_asked(args: &RenderArgs) -> bool {
    args.optics
        || args.config.is_some()
        || args.frames.is_some()
        || args.caustics_resolution.is_some()
}

pub fn render_command(args: &RenderArgs) -> Result<(), Error> {
    if args.skip_existing && args.frames.is_none() {
        return Err(Error::InvalidArgument {
            argument: "--skip-existing",
            reason: "is for sequences (--frames); for one file, --force replaces it".into(),
        });
    }
    if finished_frame_asked(args) {
        return render_optics(args);
    }
    let input = args.input.as_deref().or(args.surfels.as_deref());
    check_output(&args.out, input, args.force, OutputKind::Single)?;
    if let Some(path) = &args.save_surfels {
        check_output(path, input, args.force, OutputKind::Single)?;
    }
    if let Some(path) = &args.level_map {
        check_output(path, input, args.force, OutputKind::Single)?;
    }
    let mut frames = Frames::of(args, false)?;
    let mut params = pipeline_params(args)?;
    if params.support_radius.is_none() {
        params.support_radius = frames.support_radius();
    }
    let mut pipeline = Pipeline::new(params)?;
    // the surfels are drawn here as the shaded splats (from --camera or the one framing them):
    // --detail auto sees them so
    pipeline.set_drawn(Some(Through::Splats));
    let splat_params = pipeline.splat_params();
    super::warn_at_once(&mut pipeline);
    let t = Instant::now();
    let (source, particles, frame) =
        frames.frame(&mut pipeline, args, args.frame, Through::Surfels)?;
    let surfels_ms = ms(t);
    let surfels = &frame.render_surfels;
    save_surfels(args, surfels)?;
    let camera = args
        .camera
        .map_or_else(|| framing(surfels), |c| turned_camera(c, args.up));
    if let Some(path) = &args.level_map {
        let refined = frame
            .refined
            .as_ref()
            .ok_or_else(|| Error::InvalidArgument {
                argument: "--level-map",
                reason: "the level map shows the refined points: use --source chain or refined"
                    .into(),
            })?;
        let map =
            fluid_surfels::preview::levels_picture(refined, &camera, args.size.0, args.size.1)?;
        fluid_surfels::preview::save_png(&map, path)?;
    }
    let ctx = choose_gpu(args.cpu, args.gpu)?;
    let t = Instant::now();
    let render = match ctx.as_ref() {
        Some(ctx) => {
            pipeline.draw_gpu(ctx, (surfels, &frame.render_weights), &camera, args.size)?
        }
        None => pipeline.draw((surfels, &frame.render_weights), &camera, args.size)?,
    };
    let render_ms = ms(t);
    let covered: Vec<bool> = render.colour.iter().map(|c| c[3] > 0.0).collect();
    let holes =
        fluid_surfels::quality::holes(&covered, render.width as usize, render.height as usize, 3);
    if args.mark_holes {
        let marked = fluid_surfels::quality::mark_holes(&render.image, &covered, 3);
        fluid_surfels::preview::save_rgba_png(&marked, &args.out)?;
    } else {
        fluid_surfels::preview::save_rgba_png(&render.image, &args.out)?;
    }
    let report = RenderReport {
        outside_bounds: super::outside_bounds(),
        source,
        particles,
        surfel_source: particles.map(|_| args.source).map(SurfelSource::as_str),
        renderer: args.renderer.as_str(),
        surfels: surfels.len(),
        skipped_surfels: surfels.iter().filter(|s| !s.is_drawable()).count(),
        width: args.size.0,
        height: args.size.1,
        mode: splat_params.mode,
        backend: backend_name(ctx.as_ref()),
        camera,
        covered_pixels: render.covered_pixels(),
        holes,
        holes_fraction: holes.fraction(),
        enclosed_holes_fraction: holes.enclosed_fraction(),
        surfels_ms,
        render_ms,
        detail: frame.detail.clone(),
        warnings: frame.warnings,
        output: args.out.display().to_string(),
    };
    if args.json {
        super::print_json(&report);
    } else {
        println!(
            "{}: {} {}{} ({} skipped as undrawable){}",
            report.source,
            report.surfels,
            drawn_as(args),
            report
                .surfel_source
                .map(|s| format!(" from the {s} source"))
                .unwrap_or_default(),
            report.skipped_surfels,
            report
                .particles
                .map(|p| format!(" from {p} particles in {surfels_ms:.0} ms"))
                .unwrap_or_default()
        );
        for w in &report.warnings {
            println!("  warning: {w}");
        }
        println!(
            "  {}x{} {} on the {}: {:.1} ms, {} pixels covered, holes {:.3} % of the silhouette ({:.3} % enclosed)",
            report.width,
            report.height,
            match report.renderer {
                "ewa" => format!("{:?}", report.mode),
                other => other.to_string(),
            },
            report.backend,
            render_ms,
            report.covered_pixels,
            100.0 * report.holes_fraction,
            100.0 * report.enclosed_holes_fraction
        );
        println!("  wrote {}", report.output);
    }
    Ok(())
}

/// What the renderer draws, for the reports: surfels, or the spheres of particle splatting.
fn drawn_as(args: &RenderArgs) -> &'static str {
    args.renderer.drawn().noun()
}

/// Writes the rendered surfels to `--save-surfels`, when given.
fn save_surfels(args: &RenderArgs, surfels: &[Surfel]) -> Result<(), Error> {
    if let Some(path) = &args.save_surfels {
        io::write_particles(path, &splat::surfels_to_particles(surfels), None)?;
    }
    Ok(())
}

/// Statistics of one finished frame.
#[derive(Clone, Debug, Serialize)]
struct FrameReport {
    surfels: usize,
    backend: String,
    /// The virtual screen and the caustics map (from the CPU path's stage).
    screen: Option<[u32; 2]>,
    map: Option<[u32; 2]>,
    image: [u32; 2],
    /// Caustics triangles, the flux through the water and the map's total flux (CPU path).
    caustics_triangles: Option<usize>,
    incident_flux: Option<[f32; 3]>,
    map_flux: Option<[f32; 3]>,
    /// Milliseconds: the CPU stages up to the surfels, the caustics and the image (CPU path),
    /// or the GPU's caustics and image together.
    surfels_ms: f64,
    caustics_ms: Option<f64>,
    frame_ms: f64,
    /// Pixels darker than 0.6x the median of their 7x7 neighbourhood (`quality::specks`), and
    /// their fraction of the image.
    specks: usize,
    specks_fraction: f64,
    /// Specks none of whose 8 neighbours is one (`quality::isolated`): 1-pixel dots, not lines.
    isolated_specks: usize,
    /// The level of detail: steps run, refined points, grid cell, surfels.
    detail: DetailReport,
    warnings: Vec<String>,
}

#[derive(Serialize)]
struct OpticsFrameReport {
    /// Particles dropped by `--bounds` (only with it).
    #[serde(skip_serializing_if = "Option::is_none")]
    outside_bounds: Option<usize>,
    source: String,
    frame: Option<usize>,
    output: String,
    #[serde(flatten)]
    stats: FrameReport,
}

/// The finished frame on the CPU (the pipeline through the optics) or on the GPU (the
/// pipeline's CPU stages, then `GpuPipeline`).
fn finished_frame(
    pipeline: &mut Pipeline,
    gpu: Option<&mut (GpuContext, GpuPipeline)>,
    frames: &mut Frames,
    args: &RenderArgs,
    frame: Option<usize>,
) -> Result<(String, image::RgbaImage, FrameReport), Error> {
    let image_size = pipeline.params().scene.optics.image_size;
    match gpu {
        None => {
            let (source, _, f) = frames.frame(pipeline, args, frame, Through::Frame)?;
            save_surfels(args, &f.render_surfels)?;
            let fin = f.finished.as_ref().expect("through the frame");
            let t = &f.timings;
            let report = FrameReport {
                surfels: f.render_surfels.len(),
                backend: backend_name(None),
                screen: Some([fin.stage.views.screen.width, fin.stage.views.screen.height]),
                map: Some([fin.stage.views.map.width, fin.stage.views.map.height]),
                image: image_size,
                caustics_triangles: Some(fin.caustics.triangles),
                incident_flux: Some(fin.caustics.incident.to_array()),
                map_flux: Some(fin.caustics.total_flux().to_array()),
                surfels_ms: t.total_ms - t.caustics_ms - t.image_ms,
                caustics_ms: Some(t.caustics_ms),
                frame_ms: t.image_ms,
                specks: 0,
                specks_fraction: 0.0,
                isolated_specks: 0,
                detail: f.detail.clone(),
                warnings: f.warnings.clone(),
            };
            let image = fin.image.clone();
            pipeline.recycle(f);
            Ok((source, image, report))
        }
        Some((ctx, gpu)) => {
            let (source, _, f) = frames.frame(pipeline, args, frame, Through::Surfels)?;
            save_surfels(args, &f.render_surfels)?;
            let t = Instant::now();
            let image = gpu.render_frame_image(ctx, &f)?;
            let report = FrameReport {
                surfels: f.render_surfels.len(),
                backend: backend_name(Some(ctx)),
                screen: None,
                map: None,
                image: image_size,
                caustics_triangles: None,
                incident_flux: None,
                map_flux: None,
                surfels_ms: f.timings.total_ms,
                caustics_ms: None,
                frame_ms: ms(t),
                specks: 0,
                specks_fraction: 0.0,
                isolated_specks: 0,
                detail: f.detail.clone(),
                warnings: f.warnings.clone(),
            };
            Ok((source, image, report))
        }
    }
}

/// `render` with optics: one finished frame, or a numbered sequence of them through one
/// pipeline (hysteresis, camera, pool and scene box kept across the frames).
fn render_optics(args: &RenderArgs) -> Result<(), Error> {
    let sequence = args.frames.is_some();
    let input = args.input.as_deref().or(args.surfels.as_deref());
    if sequence {
        // the folder is made below; what must exist is the folder it goes into
        super::check_folder(&args.out)?;
    } else {
        check_output(&args.out, input, args.force, OutputKind::Single)?;
        if let Some(path) = &args.save_surfels {
            check_output(path, input, args.force, OutputKind::Single)?;
        }
    }
    let mut frames = Frames::of(args, sequence)?;
    let mut params = pipeline_params(args)?;
    if params.support_radius.is_none() {
        params.support_radius = frames.support_radius();
    }
    let [w, h] = params.scene.optics.image_size;
    let mut pipeline = Pipeline::new(params.clone())?;
    super::warn_at_once(&mut pipeline);
    let mut gpu = match choose_gpu(args.cpu, args.gpu)? {
        Some(ctx) => {
            let g = GpuPipeline::new(
                &ctx.device,
                &ctx.queue,
                wgpu::TextureFormat::Rgba8Unorm,
                (w, h),
                &params,
            )?;
            // the CPU stages' surfels are drawn as the finished frame on the GPU
            pipeline.set_drawn(Some(Through::Frame));
            Some((ctx, g))
        }
        None => None,
    };
    let Some(range) = args.frames else {
        let (source, image, report) =
            finished_frame(&mut pipeline, gpu.as_mut(), &mut frames, args, args.frame)?;
        fluid_surfels::preview::save_rgba_png(&marked(args, &image), &args.out)?;
        return report_frame(args, source, args.frame, &args.out, &image, report);
    };
    let list: Vec<usize> = match &frames {
        Frames::Pattern(pattern) => pattern.frames(Some(range))?,
        _ => {
            fluid_surfels::scenes::ColumnParams::check_frame(range.end - 1)?;
            range.frames().collect()
        }
    };
    if args.out.exists() && !args.out.is_dir() {
        return Err(Error::InvalidArgument {
            argument: "--out",
            reason: format!(
                "{} is a file; with --frames --out names the folder of frame_NNNN.png",
                args.out.display()
            ),
        });
    }
    // refuse before any work: every output that exists without --force or --skip-existing
    let outputs: Vec<PathBuf> = list
        .iter()
        .map(|f| args.out.join(format!("frame_{f:04}.png")))
        .collect();
    let todo: Vec<bool> = outputs
        .iter()
        .map(|o| !(args.skip_existing && o.exists()))
        .collect();
    std::fs::create_dir_all(&args.out).map_err(|e| Error::InvalidArgument {
        argument: "--out",
        reason: format!("{}: {e}", args.out.display()),
    })?;
    super::check_folder(&args.out.join("frame_0000.png"))?;
    for (out, _) in outputs.iter().zip(&todo).filter(|(_, t)| **t) {
        super::check_replaceable(out, None, args.force, OutputKind::Frame)?;
    }
    let skipped = todo.iter().filter(|t| !**t).count();
    if skipped == list.len() {
        println!(
            "all {} frames exist in {} (--skip-existing): nothing to do",
            list.len(),
            args.out.display()
        );
        return Ok(());
    }
    if skipped > 0 && !args.json {
        println!(
            "skipping {skipped} of {} frames whose PNG exists",
            list.len()
        );
    }
    if args.fit == FitChoice::Union {
        let Frames::Pattern(pattern) = &frames else {
            return Err(Error::InvalidArgument {
                argument: "--fit",
                reason: "`union` reads the frames' files first: it needs an --input pattern (the \
                         column scene's frames are simulated in order)"
                    .into(),
            });
        };
        let (lo, hi) = union_bounds(pattern, &list, args)?;
        match gpu.as_mut() {
            Some((_, g)) => g.cpu_mut().fit_to(lo, hi)?,
            None => pipeline.fit_to(lo, hi)?,
        }
    }
    if !todo[0] {
        // a resumed sequence keeps the camera and the pool of a whole run: fitted on its first
        // frame, rendered again but not written
        finished_frame(
            &mut pipeline,
            gpu.as_mut(),
            &mut frames,
            args,
            Some(list[0]),
        )?;
    }
    let bar = super::progress((list.len() - skipped) as u64, "rendering");
    for ((&frame, out), _) in list.iter().zip(&outputs).zip(&todo).filter(|(_, t)| **t) {
        let (source, image, report) =
            finished_frame(&mut pipeline, gpu.as_mut(), &mut frames, args, Some(frame))?;
        fluid_surfels::preview::save_rgba_png(&marked(args, &image), out)?;
        bar.suspend(|| report_frame(args, source, Some(frame), out, &image, report))?;
        bar.inc(1);
    }
    bar.finish_and_clear();
    Ok(())
}

/// The union of the particle bounds of `frames`, in the turned (`--up`) coordinates, widened by
/// the support radius (given, or twice the spacing estimated on the first frame) so that the
/// surfels around the particles lie inside too.
fn union_bounds(
    pattern: &FramePattern,
    frames: &[usize],
    args: &RenderArgs,
) -> Result<(Vec3, Vec3), Error> {
    use rayon::prelude::*;
    // each frame's bounds (none for an empty frame) and, on the first, the radius to pad by
    let bounds: Vec<(Option<(Vec3, Vec3)>, f32)> = frames
        .par_iter()
        .enumerate()
        .map(|(k, &f)| {
            let mut set = super::read_particles(&pattern.path(f), args.format)?;
            if args.up != UpAxis::Y {
                set.rotate(args.up.to_y_up());
            }
            let pad = match (args.radius, k) {
                (Some(r), _) => r,
                (None, 0) => fluid_surfels::neighbours::support_radius(&set.positions)?,
                _ => 0.0,
            };
            Ok((set.bounds(), pad))
        })
        .collect::<Result<_, Error>>()?;
    let pad = Vec3::splat(bounds.iter().map(|b| b.1).fold(0.0, f32::max));
    let union = bounds
        .iter()
        .fold(None, |u, b| fluid_surfels::view::union_boxes(u, b.0));
    let (lo, hi) = union.ok_or_else(|| Error::InvalidArgument {
        argument: "--fit",
        reason: "`union`: every frame of the range is empty".into(),
    })?;
    Ok((lo - pad, hi + pad))
}

/// The finished frame as written: with its specks painted red under `--mark-specks`.
fn marked(args: &RenderArgs, image: &image::RgbaImage) -> image::RgbaImage {
    let mut out = image.clone();
    if args.mark_specks {
        let mask = fluid_surfels::quality::speck_mask(image, 7, 0.6);
        for (p, &s) in out.pixels_mut().zip(&mask) {
            if s {
                *p = image::Rgba([255, 0, 0, 255]);
            }
        }
    }
    out
}

fn report_frame(
    args: &RenderArgs,
    source: String,
    frame: Option<usize>,
    out: &std::path::Path,
    image: &image::RgbaImage,
    mut stats: FrameReport,
) -> Result<(), Error> {
    let mask = fluid_surfels::quality::speck_mask(image, 7, 0.6);
    stats.specks = mask.iter().filter(|&&s| s).count();
    stats.isolated_specks =
        fluid_surfels::quality::isolated(&mask, image.width() as usize, image.height() as usize);
    stats.specks_fraction =
        stats.specks as f64 / (f64::from(image.width()) * f64::from(image.height())).max(1.0);
    let r = OpticsFrameReport {
        outside_bounds: super::outside_bounds(),
        source,
        frame,
        output: out.display().to_string(),
        stats,
    };
    if args.json {
        super::print_json(&r);
    } else {
        let s = &r.stats;
        println!(
            "{}{}: {} {} ({:.0} ms){}{}; frame {}x{} on the {}, {:.1} ms; wrote {}",
            r.source,
            frame.map(|f| format!(" frame {f}")).unwrap_or_default(),
            s.surfels,
            drawn_as(args),
            s.surfels_ms,
            match (s.screen, s.map) {
                (Some(a), Some(b)) =>
                    format!("; caustics {}x{} screen, {}x{} map", a[0], a[1], b[0], b[1]),
                _ => String::new(),
            },
            match (s.caustics_triangles, s.caustics_ms) {
                (Some(t), Some(c)) => format!(", {t} triangles, {c:.1} ms"),
                _ => String::new(),
            },
            s.image[0],
            s.image[1],
            s.backend,
            s.frame_ms,
            r.output
        );
        for w in &s.warnings {
            println!("  warning: {w}");
        }
    }
    Ok(())
}
