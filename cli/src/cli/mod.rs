//! The command line's subcommands and what they share.

pub mod bench;
pub mod compare;
pub mod detect;
pub mod info;
pub mod mesh;

pub mod refine;
pub mod render;
pub mod run;
pub mod surfels;

use std::io::IsTerminal;
use std::path::Path;
use std::sync::atomic::Ordering;
use std::time::Instant;

use fluid_surfels::io::Format;
use fluid_surfels::scenes::SceneName;
use fluid_surfels::sequence::{FramePattern, FrameRange};
pub use fluid_surfels::sequence::{
    OutputKind, Progress, Sequence, check_folder, check_output, check_replaceable, jobs,
};

use fluid_surfels::io;
use fluid_surfels::surface::{ParticleClass, Surface};
use fluid_surfels::{Error, ParticleSet};

/// A value chosen by one of the names `name` gives the values of `all` (the library's names,
/// parsed here: the library knows no clap).
pub fn names_parser<T: Copy + Send + Sync + 'static>(
    all: &'static [T],
    name: fn(T) -> &'static str,
) -> impl clap::builder::TypedValueParser<Value = T> {
    use clap::builder::TypedValueParser;
    clap::builder::PossibleValuesParser::new(all.iter().map(|&v| name(v))).map(move |s| {
        *all.iter()
            .find(|&&v| name(v) == s)
            .expect("one of the possible values")
    })
}

/// `--scene NAME`.
pub fn scene_parser() -> impl clap::builder::TypedValueParser<Value = SceneName> {
    names_parser(&SceneName::ALL, SceneName::as_str)
}

/// `--format NAME`.
pub fn format_parser() -> impl clap::builder::TypedValueParser<Value = Format> {
    names_parser(&Format::ALL, Format::name)
}

/// `--up AXIS`.
pub fn up_parser() -> impl clap::builder::TypedValueParser<Value = fluid_surfels::view::UpAxis> {
    use fluid_surfels::view::UpAxis;
    names_parser(&UpAxis::ALL, UpAxis::name)
}

/// Options of every subcommand that reads particle files.
#[derive(clap::Args, Clone, Debug)]
pub struct GlobalArgs {
    /// Keep only the particles inside this box, MIN_X,MIN_Y,MIN_Z,MAX_X,MAX_Y,MAX_Z (in the
    /// file's coordinates); the others are dropped and counted (`outside_bounds` in reports).
    /// For simulations that leak particles far from the fluid.
    #[arg(long, global = true, value_parser = parse_bounds, allow_hyphen_values = true)]
    pub bounds: Option<[f32; 6]>,
    /// The most memory that decompressing a file (gzipped BGEO, zlib VTK XML) and the points of
    /// `refine` may take, in bytes with an optional K, M or G suffix (powers of 1024); work
    /// predicted to need more is refused before it starts.
    #[arg(long, global = true, value_parser = parse_bytes, default_value = "1G")]
    pub memory_budget: u64,
    /// The threads the work may use (1 to 1024; default: one per core), for a task of a farm
    /// told how many cores are its own; a --config file's `threads` key gives a pipeline's
    /// frames their own pool besides.
    #[arg(long, global = true, value_parser = parse_threads)]
    pub threads: Option<usize>,
}

fn parse_threads(text: &str) -> Result<usize, String> {
    match text.trim().parse::<usize>() {
        Ok(n) if (1..=fluid_surfels::sequence::MAX_JOBS).contains(&n) => Ok(n),
        _ => Err(format!(
            "`{text}`: a whole number of threads from 1 to {}",
            fluid_surfels::sequence::MAX_JOBS
        )),
    }
}

fn parse_bounds(text: &str) -> Result<[f32; 6], String> {
    let v: Vec<f32> = render::parse_list(text, "a number")?;
    let Ok(v) = <[f32; 6]>::try_from(v) else {
        return Err(format!(
            "`{text}`: six numbers MIN_X,MIN_Y,MIN_Z,MAX_X,MAX_Y,MAX_Z"
        ));
    };
    if v.iter().any(|x| !x.is_finite()) || (0..3).any(|k| v[k] > v[k + 3]) {
        return Err(format!(
            "`{text}`: six finite numbers MIN_X,MIN_Y,MIN_Z,MAX_X,MAX_Y,MAX_Z with each min <= its max"
        ));
    }
    Ok(v)
}

fn parse_bytes(text: &str) -> Result<u64, String> {
    let t = text.trim();
    let (digits, unit) = match t.char_indices().find(|(_, c)| c.is_ascii_alphabetic()) {
        Some((k, _)) => t.split_at(k),
        None => (t, ""),
    };
    let shift = match unit.to_ascii_uppercase().trim_end_matches(['B', 'I']) {
        "" => 0,
        "K" => 10,
        "M" => 20,
        "G" => 30,
        "T" => 40,
        _ => return Err(format!("`{text}`: a size in bytes, like 512M or 2G")),
    };
    let n: f64 = digits
        .trim()
        .parse()
        .map_err(|_| format!("`{text}`: a size in bytes, like 512M or 2G"))?;
    let bytes = n * (1u64 << shift) as f64;
    if !(bytes.is_finite() && bytes >= 1.0 && bytes < u64::MAX as f64) {
        return Err(format!("`{text}`: a size of at least one byte"));
    }
    Ok(bytes as u64)
}

static GLOBALS: std::sync::OnceLock<GlobalArgs> = std::sync::OnceLock::new();
static OUTSIDE_BOUNDS: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);

/// Keeps the global options for [`read_particles`] (called once, by `main`).
pub fn set_globals(args: GlobalArgs) {
    if let Some(n) = args.threads {
        // the first pool of the process: nothing ran in parallel before the command line was
        // read, so this cannot fail but for a second call, which keeps the first
        let _ = rayon::ThreadPoolBuilder::new()
            .num_threads(n)
            .build_global();
    }
    // a second call keeps the first: there is only one command line
    let _ = GLOBALS.set(args);
}

fn globals() -> GlobalArgs {
    GLOBALS.get().cloned().unwrap_or(GlobalArgs {
        bounds: None,
        memory_budget: io::DEFAULT_MEMORY_BUDGET,
        threads: None,
    })
}

/// `--memory-budget`.
pub fn memory_budget() -> u64 {
    globals().memory_budget
}

/// Particles dropped by `--bounds` so far (`None` without `--bounds`), for the reports.
pub fn outside_bounds() -> Option<usize> {
    globals()
        .bounds
        .map(|_| OUTSIDE_BOUNDS.load(Ordering::Relaxed))
}

/// Reads a particle file with the command line's `--memory-budget`, and drops the particles
/// outside `--bounds` (saying how many on stderr).
pub fn read_particles(path: &Path, format: Option<Format>) -> Result<ParticleSet, Error> {
    let g = globals();
    let options = io::ReadOptions {
        memory_budget: g.memory_budget,
    };
    let set = io::read_particles_with(path, format, &options)?;
    let Some(b) = g.bounds else {
        return Ok(set);
    };
    let (kept, outside) = set.crop(
        glam::Vec3::new(b[0], b[1], b[2]),
        glam::Vec3::new(b[3], b[4], b[5]),
    );
    if outside > 0 {
        OUTSIDE_BOUNDS.fetch_add(outside, Ordering::Relaxed);
        eprintln!(
            "note: {}: {outside} of {} particles outside --bounds dropped",
            path.display(),
            set.len()
        );
    }
    Ok(kept)
}

/// Where a stage's particles come from (shared by `detect` and `refine`).
#[derive(clap::Args)]
#[command(group = clap::ArgGroup::new("source").required(true).args(["input", "scene"]))]
pub struct SourceArgs {
    /// Particle file, or a numbered sequence with `{}` or `{:04}` for the frame number
    /// (`dir/ParticleData_Fluid_{}.vtk`).
    #[arg(long)]
    pub input: Option<String>,
    /// Built-in scene.
    #[arg(long, value_parser = scene_parser())]
    pub scene: Option<SceneName>,
    /// Format of --input (default: from its extension).
    #[arg(long, value_parser = format_parser())]
    pub format: Option<Format>,
    /// Support radius (default: the scene's, or twice the particle spacing estimated from the
    /// file, or from the first frame of a sequence).
    #[arg(long)]
    pub radius: Option<f32>,
    /// Frame of the `column` scene (hysteresis runs over all frames up to it).
    #[arg(long)]
    pub frame: Option<usize>,
    /// Frames of a sequence: A..B, A..=B, with an optional :STEP (default: every file found).
    #[arg(long)]
    pub frames: Option<FrameRange>,
}

impl SourceArgs {
    /// The frame pattern when `--input` names a sequence (has a `{}`), `None` for one file or a
    /// scene.
    pub fn sequence(&self) -> Result<Option<FramePattern>, Error> {
        Ok(self
            .input
            .as_deref()
            .map(FramePattern::parse)
            .transpose()?
            .flatten())
    }
}

/// Where a stage's results go and how a sequence runs (shared by `detect` and `refine`).
#[derive(clap::Args)]
pub struct OutputArgs {
    /// Write the stage's points here (format by extension); for a sequence, a pattern with `{}`.
    #[arg(long)]
    pub out: Option<String>,
    /// Write a picture here (PNG); a pattern for sequences.
    #[arg(long)]
    pub png: Option<String>,
    /// Frames processed at once (sequences). Each job runs consecutive frames in order with its
    /// own state, warmed up on the --warmup frames before its first (the serial run's
    /// hysteresis).
    #[arg(long, default_value_t = 1)]
    pub jobs: usize,
    /// Sequences: do only the K-th of N contiguous chunks of the frames (1-based), as the
    /// serial run would (the radius of the range's first frame, a --warmup before the chunk);
    /// `slurm`: the chunk of this Slurm array task.
    #[arg(long)]
    pub shard: Option<fluid_surfels::sequence::Shard>,
    /// Sequences: how many frames before a job's first frame (a shard's, a frame after skipped
    /// ones) run surface detection alone, so that its hysteresis is the serial run's (default 8).
    #[arg(long)]
    pub warmup: Option<usize>,
    /// Skip frames whose outputs exist (resume an interrupted sequence).
    #[arg(long, conflicts_with = "force")]
    pub skip_existing: bool,
    /// Replace existing output files.
    #[arg(long)]
    pub force: bool,
    /// Format of --out (default: from its extension; `xyz-raw`, bare little-endian f32 x y z
    /// triplets, has no extension of its own).
    #[arg(long, value_parser = format_parser())]
    pub out_format: Option<Format>,
    /// Print one JSON object of statistics on stdout instead of text.
    #[arg(long)]
    pub json: bool,
    /// The file's axis that points up, for the --png picture (Houdini and Blender write z-up):
    /// x, y, z, -x, -y or -z. The points written with --out keep the file's coordinates.
    #[arg(long, default_value = "y", value_parser = up_parser(), allow_hyphen_values = true)]
    pub up: fluid_surfels::view::UpAxis,
}

/// Positions turned so that `up` points along +y, for pictures.
pub fn turned(positions: &[glam::Vec3], up: fluid_surfels::view::UpAxis) -> Vec<glam::Vec3> {
    let q = up.to_y_up();
    positions.iter().map(|&p| q * p).collect()
}

/// The positions of a particle file or a built-in scene (the `column` scene at `frame`, by
/// default the splash), with a description of the source and the support radius: `radius` when
/// given, else the scene's, else twice the spacing estimated from the file.
pub fn positions_of(
    input: Option<&Path>,
    scene: Option<SceneName>,
    format: Option<Format>,
    frame: Option<usize>,
    radius: Option<f32>,
) -> Result<(String, Vec<glam::Vec3>, f32), Error> {
    particles_of(input, scene, format, frame, radius).map(|(what, set, r)| (what, set.positions, r))
}

/// [`positions_of`] with the whole particle set (velocities and the other attributes).
pub fn particles_of(
    input: Option<&Path>,
    scene: Option<SceneName>,
    format: Option<Format>,
    frame: Option<usize>,
    radius: Option<f32>,
) -> Result<(String, fluid_surfels::ParticleSet, f32), Error> {
    match (input, scene) {
        (Some(path), _) => {
            let particles = read_particles(path, format)?;
            let r = match radius {
                Some(r) => r,
                None => fluid_surfels::neighbours::support_radius(&particles.positions)?,
            };
            Ok((path.display().to_string(), particles, r))
        }
        (None, Some(name)) => {
            let frame = if name == SceneName::Column {
                Some(frame.unwrap_or(fluid_surfels::scenes::ColumnParams::SPLASH_FRAME))
            } else {
                frame
            };
            let scene = fluid_surfels::scenes::build(name, frame)?;
            Ok((
                format!("scene {}", name.as_str()),
                scene.particles,
                radius.unwrap_or(scene.support_radius),
            ))
        }
        (None, None) => Err(Error::InvalidArgument {
            argument: "--input/--scene",
            reason: "one of them is needed".into(),
        }),
    }
}

/// Prints a report as one JSON object on stdout (`--json`).
pub fn print_json(report: &impl serde::Serialize) {
    println!(
        "{}",
        serde_json::to_string(report).expect("reports are plain data and serialise")
    );
}

pub fn ms(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}

/// The surface particles with their normals (and every attribute they had).
pub fn surface_particles(particles: &ParticleSet, surface: &Surface) -> ParticleSet {
    let idx = surface.indices_of(ParticleClass::Surface);
    let mut out = particles.select(&idx);
    out.normals = Some(idx.iter().map(|&i| surface.normals[i]).collect());
    out
}

/// Has `pipeline` print each warning on stderr as soon as it is known (a support radius far off
/// is known before the long work), besides the report's list at the end.
pub fn warn_at_once(pipeline: &mut fluid_surfels::pipeline::Pipeline) {
    pipeline.on_warning(|w| eprintln!("warning: {}", io::clean(w, 1000)));
}

/// A [`Sequence`]'s progress as a bar on stderr (when it is a terminal).
pub fn progress_bar(label: &'static str) -> Box<dyn Fn(Progress) + Sync> {
    let bar = std::sync::OnceLock::new();
    Box::new(move |p| match p {
        Progress::Start(n) => {
            let _ = bar.set(progress(n as u64, label));
        }
        Progress::Frame => {
            if let Some(b) = bar.get() {
                b.inc(1);
            }
        }
        Progress::End => {
            if let Some(b) = bar.get() {
                b.finish_and_clear();
            }
        }
    })
}

/// A progress bar on stderr when it is a terminal, hidden otherwise.
pub fn progress(len: u64, what: &str) -> indicatif::ProgressBar {
    if !std::io::stderr().is_terminal() {
        return indicatif::ProgressBar::hidden();
    }
    let bar = indicatif::ProgressBar::new(len);
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{msg} [{bar:30}] {pos}/{len} frames, {per_sec}, {eta} left",
        )
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    bar.set_message(what.to_owned());
    bar
}

/// The frames of a sequence: the range given (every frame's file checked to exist before any
/// work), or every file of the pattern found on disk.
pub fn sequence_frames(
    pattern: &FramePattern,
    range: Option<fluid_surfels::sequence::FrameRange>,
) -> Result<Vec<usize>, Error> {
    Ok(pattern.frames(range)?)
}

/// An output pattern that must have a placeholder because the input is a sequence.
pub fn output_pattern(
    text: &Option<String>,
    flag: &'static str,
) -> Result<Option<FramePattern>, Error> {
    match text {
        None => Ok(None),
        Some(t) => FramePattern::parse(t)?
            .map(Some)
            .ok_or_else(|| Error::InvalidArgument {
                argument: flag,
                reason: format!(
                    "`{t}` needs a {{}} for the frame number when the input is a sequence"
                ),
            }),
    }
}

/// A sequence set up from the shared arguments: the runner, the output patterns, and the support
/// radius (given, or twice the spacing estimated from the first frame to do).
pub struct PreparedSequence<'a> {
    pub sequence: Sequence<'a>,
    pub out: Option<FramePattern>,
    pub png: Option<FramePattern>,
    pub radius: f32,
}

/// Checks and prepares a sequence run for `detect`, `refine` and `surfels`.
pub fn prepare_sequence<'a>(
    source: &SourceArgs,
    outputs: &OutputArgs,
    pattern: &'a FramePattern,
    label: &'static str,
) -> Result<PreparedSequence<'a>, Error> {
    if source.scene.is_some() || source.frame.is_some() {
        return Err(Error::InvalidArgument {
            argument: "--frame",
            reason: "--scene and --frame do not combine with an --input sequence".into(),
        });
    }
    let out = output_pattern(&outputs.out, "--out")?;
    let png = output_pattern(&outputs.png, "--png")?;
    let sequence = Sequence {
        input: pattern,
        frames: sequence_frames(pattern, source.frames)?,
        outputs: [&out, &png].into_iter().flatten().cloned().collect(),
        jobs: outputs.jobs,
        skip_existing: outputs.skip_existing,
        force: outputs.force,
        label,
        progress: Some(progress_bar(label)),
        shard: outputs.shard,
        warmup: outputs
            .warmup
            .unwrap_or(fluid_surfels::pipeline::DEFAULT_WARMUP),
    };
    sequence.plan()?;
    // the range's first frame sets the radius of every job, shard and resumed run
    let radius = match (source.radius, sequence.frames.first()) {
        (Some(r), _) => r,
        (None, Some(&f)) => {
            let first = read_particles(&pattern.path(f), source.format)?;
            fluid_surfels::neighbours::support_radius(&first.positions)?
        }
        (None, None) => 0.0,
    };
    Ok(PreparedSequence {
        sequence,
        out,
        png,
        radius,
    })
}
