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
use fluid_surfels::sequence::{FramePattern, FrameRange, Shard};
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
    /// Where the iso-surface lies: paper (eq. 1's sums), boundary (half a spacing outside the
    /// outermost particles at every level) or volume (with --source particles: splashsurf's
    /// field, each particle weighted by its SPH volume); the `grid.calibration` key, over a
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
    /// size; with --detail auto the file holds the whole surface too, also the surfels facing
    /// away from the camera that the picture leaves out.
    #[arg(long, conflicts_with = "frames")]
    pub save_surfels: Option<PathBuf>,
    /// The PNG to write (a folder with --frames).
    #[arg(long, default_value = "render.png")]
    pub out: PathBuf,
    /// Replace an existing output file (with --frames: the frames that exist).
    #[arg(long)]
    pub force: bool,
    /// With --frames: keep the frames whose PNG exists and render only the others (resume an
    /// interrupted sequence; the camera, the pool and the radius are still the range's first
    /// frame's, through the sequence's plan, and the hysteresis comes from a warm-up).
    #[arg(long, conflicts_with = "force")]
    pub skip_existing: bool,
    /// With --frames: render only the K-th of N contiguous chunks of the range (1-based), as
    /// the serial run would (the plan of the range's first frame, and a --warmup on the frames
    /// before the chunk); `slurm`: the chunk of this Slurm array task
    /// (SLURM_ARRAY_TASK_ID, _MIN, _COUNT; sbatch --array=1-N).
    #[arg(long, requires = "frames")]
    pub shard: Option<Shard>,
    /// With --frames: how many frames before a chunk that does not start the range (--shard,
    /// --skip-existing) run surface detection alone, so that its hysteresis is the serial
    /// run's (default 8: on the column scene every chunk's classes and images agree with the
    /// serial run's after 7; docs/cli.md).
    #[arg(long, requires = "frames")]
    pub warmup: Option<usize>,
    /// With --frames: the sequence's plan (support radius, camera, pool, scene box, the
    /// light's resolutions; JSON): read when the file exists, else made from the range's first
    /// frame and written, so that the chunks of a farm make it once. Without it every chunk
    /// that does not start the range makes it in memory.
    #[arg(long, requires = "frames")]
    pub plan: Option<PathBuf>,
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

    /// Frame `frame` of a sequence, warmed up on (`Pipeline::warm_up`: the detection and the
    /// levels of detail alone) before the frames to draw. The column scene steps to it as
    /// [`Frames::frame`] does, detecting on the frames it steps over.
    fn warm_up(
        &mut self,
        pipeline: &mut Pipeline,
        args: &RenderArgs,
        frame: usize,
    ) -> Result<(), Error> {
        match self {
            Self::Pattern(pattern) => {
                let mut set = super::read_particles(&pattern.path(frame), args.format)?;
                if args.up != UpAxis::Y {
                    set.rotate(args.up.to_y_up());
                }
                pipeline.warm_up(&set, Through::Frame)
            }
            Self::Column(sim) => {
                ColumnParams::check_frame(frame)?;
                while sim.frame() < frame {
                    pipeline.frame_through(sim.particles(), Through::Surface)?;
                    sim.step_frame();
                }
                pipeline.warm_up(sim.particles(), Through::Frame)
            }
            _ => Ok(()),
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
    // the surfels written to a file are the whole surface, not only what the picture shows
    pipeline.keep_hidden_surfels(args.save_surfels.is_some());
    let splat_params = pipeline.splat_params();
    super::warn_at_once(&mut pipeline);
    let t = Instant::now();
    let (source, particles, frame) =
        frames.frame(&mut pipeline, args, args.frame, Through::Surfels)?;
    let surfels_ms = ms(t);
    let surfels = &frame.render_surfels;
    save_surfels(args, surfels)?;
    let camera = args.camera.map_or_else(
        // the box the pipeline's own pictures frame (the water's shape)
        || {
            let (lo, hi) = frame.water_box().unwrap_or((Vec3::ZERO, Vec3::ONE));
            Camera::framing(lo, hi)
        },
        |c| turned_camera(c, args.up),
    );
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
    let Some(range) = args.frames else {
        let (mut pipeline, mut gpu) = pipelines(args, &params)?;
        let (source, image, report) =
            finished_frame(&mut pipeline, gpu.as_mut(), &mut frames, args, args.frame)?;
        fluid_surfels::preview::save_rgba_png(&marked(args, &image), &args.out)?;
        return report_frame(args, source, args.frame, &args.out, &image, report);
    };
    render_sequence(args, params, frames, range)
}

/// The CPU pipeline of a finished frame and, on a GPU, the `GpuPipeline` that draws it.
fn pipelines(
    args: &RenderArgs,
    params: &PipelineParams,
) -> Result<(Pipeline, Option<(GpuContext, GpuPipeline)>), Error> {
    let [w, h] = params.scene.optics.image_size;
    let mut pipeline = Pipeline::new(params.clone())?;
    super::warn_at_once(&mut pipeline);
    // the surfels written to a file are the whole surface, not only what the picture shows
    pipeline.keep_hidden_surfels(args.save_surfels.is_some());
    let gpu = match choose_gpu(args.cpu, args.gpu)? {
        Some(ctx) => {
            let g = GpuPipeline::new(
                &ctx.device,
                &ctx.queue,
                wgpu::TextureFormat::Rgba8Unorm,
                (w, h),
                params,
            )?;
            // the CPU stages' surfels are drawn as the finished frame on the GPU
            pipeline.set_drawn(Some(Through::Frame));
            Some((ctx, g))
        }
        None => None,
    };
    Ok((pipeline, gpu))
}

/// The frames of `--frames` in the order they are drawn, checked.
fn range_frames(frames: &Frames, range: FrameRange) -> Result<Vec<usize>, Error> {
    Ok(match frames {
        Frames::Pattern(pattern) => pattern.frames(Some(range))?,
        _ => {
            fluid_surfels::scenes::ColumnParams::check_frame(range.end - 1)?;
            range.frames().collect()
        }
    })
}

/// `render --frames`: the range, or its `--shard`, into a folder of numbered PNGs through one
/// pipeline. A run that does not start at the range's first frame (a shard, a resumed run)
/// takes the sequence's plan (the radius, camera, pool and scene box of the range's first
/// frame: `--plan`, or made here) and warms up on the `--warmup` frames before its first, so
/// that it draws what the serial run draws.
fn render_sequence(
    args: &RenderArgs,
    mut params: PipelineParams,
    mut frames: Frames,
    range: FrameRange,
) -> Result<(), Error> {
    let list = range_frames(&frames, range)?;
    let chunk = args.shard.map_or(&list[..], |s| s.of(&list));
    let Some(todo) = sequence_outputs(args, &list, chunk)? else {
        return Ok(());
    };
    let plan_exists = args.plan.as_ref().is_some_and(|p| p.exists());
    let fit = match (args.fit, &frames) {
        // the plan holds the fitted box
        _ if plan_exists => None,
        (FitChoice::First, _) => None,
        (FitChoice::Union, Frames::Pattern(pattern)) => Some(union_bounds(pattern, &list, args)?),
        (FitChoice::Union, _) => {
            return Err(Error::InvalidArgument {
                argument: "--fit",
                reason: "`union` reads the frames' files first: it needs an --input pattern (the \
                         column scene's frames are simulated in order)"
                    .into(),
            });
        }
    };
    let first = todo[0];
    let start = list
        .iter()
        .position(|&f| f == first)
        .expect("a frame of the list");
    let plan = match &args.plan {
        Some(path) if path.exists() => Some(pipeline::SequencePlan::read(path)?),
        _ if start > 0 => {
            let plan = sequence_plan(args, &params, fit, list[0])?;
            if let Some(path) = &args.plan {
                plan.write(path)?;
            }
            Some(plan)
        }
        _ => None,
    };
    if let Some(plan) = &plan {
        // the frames' pipeline takes the plan's radius (on a GPU the views are the GPU
        // pipeline's, as in a serial run)
        params.support_radius = Some(plan.support_radius);
    }
    let (mut pipeline, mut gpu) = pipelines(args, &params)?;
    let fitted = match gpu.as_mut() {
        Some((_, g)) => g.cpu_mut(),
        None => &mut pipeline,
    };
    match (&plan, fit) {
        (Some(plan), _) => fitted.set_plan(plan)?,
        (None, Some((lo, hi))) => fitted.fit_to(lo, hi)?,
        (None, None) => {}
    }
    let warmup = args.warmup.unwrap_or(pipeline::DEFAULT_WARMUP);
    let warm = &list[start.saturating_sub(warmup)..start];
    if !args.json && (args.shard.is_some() || start > 0) {
        println!(
            "frames {} of {} ({}), warm-up on {} frame(s) before",
            todo.len(),
            list.len(),
            args.shard.map_or_else(
                || "resumed".into(),
                |s| format!("shard {}/{}", s.index, s.count)
            ),
            warm.len()
        );
    }
    for &f in warm {
        frames.warm_up(&mut pipeline, args, f)?;
    }
    let bar = super::progress(todo.len() as u64, "rendering");
    for &frame in &todo {
        let out = args.out.join(format!("frame_{frame:04}.png"));
        let (source, image, report) =
            finished_frame(&mut pipeline, gpu.as_mut(), &mut frames, args, Some(frame))?;
        fluid_surfels::preview::save_rgba_png(&marked(args, &image), &out)?;
        if plan.is_none()
            && let Some(path) = args.plan.as_ref().filter(|p| !p.exists())
        {
            let fitted = match gpu.as_ref() {
                Some((_, g)) => g.cpu(),
                None => &pipeline,
            };
            if let Some(p) = fitted.plan() {
                p.write(path)?;
            }
        }
        bar.suspend(|| report_frame(args, source, Some(frame), &out, &image, report))?;
        bar.inc(1);
    }
    bar.finish_and_clear();
    Ok(())
}

/// The sequence's plan, made from the range's first frame through a pipeline of its own.
fn sequence_plan(
    args: &RenderArgs,
    params: &PipelineParams,
    fit: Option<(Vec3, Vec3)>,
    first: usize,
) -> Result<pipeline::SequencePlan, Error> {
    let mut frames = Frames::of(args, true)?;
    let mut p = Pipeline::new(params.clone())?;
    if let Some((lo, hi)) = fit {
        p.fit_to(lo, hi)?;
    }
    frames.frame(&mut p, args, Some(first), Through::Frame)?;
    p.plan().ok_or_else(|| Error::InvalidArgument {
        argument: "--plan",
        reason: "the range's first frame fitted no views".into(),
    })
}

/// The frames of `chunk` to draw, after the checks of `--out` (a folder), `--force` and
/// `--skip-existing` (made before any work); `None` when there is nothing to do (said).
fn sequence_outputs(
    args: &RenderArgs,
    list: &[usize],
    chunk: &[usize],
) -> Result<Option<Vec<usize>>, Error> {
    if args.out.exists() && !args.out.is_dir() {
        return Err(Error::InvalidArgument {
            argument: "--out",
            reason: format!(
                "{} is a file; with --frames --out names the folder of frame_NNNN.png",
                args.out.display()
            ),
        });
    }
    if chunk.is_empty() {
        if !args.json {
            println!(
                "no frame to do: the range holds {} frames, fewer than the shards",
                list.len()
            );
        }
        return Ok(None);
    }
    let out = |f: usize| args.out.join(format!("frame_{f:04}.png"));
    let todo: Vec<usize> = chunk
        .iter()
        .copied()
        .filter(|&f| !(args.skip_existing && out(f).exists()))
        .collect();
    std::fs::create_dir_all(&args.out).map_err(|e| Error::InvalidArgument {
        argument: "--out",
        reason: format!("{}: {e}", args.out.display()),
    })?;
    super::check_folder(&args.out.join("frame_0000.png"))?;
    for &f in &todo {
        super::check_replaceable(&out(f), None, args.force, OutputKind::Frame)?;
    }
    let skipped = chunk.len() - todo.len();
    if todo.is_empty() {
        println!(
            "all {} frames exist in {} (--skip-existing): nothing to do",
            chunk.len(),
            args.out.display()
        );
        return Ok(None);
    }
    if skipped > 0 && !args.json {
        println!(
            "skipping {skipped} of {} frames whose PNG exists",
            chunk.len()
        );
    }
    Ok(Some(todo))
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
