//! The `fluid-surfels` command line: the main job on the built-in scene, stage subcommands for
//! users' own data and frame sequences, file inspection, and benchmarks.

mod cli;

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};
use fluid_surfels::scenes::ColumnParams;

use cli::bench::{BenchDetectArgs, BenchIoArgs};
use cli::detect::DetectArgs;
use cli::info::InfoArgs;
use cli::refine::RefineArgs;
use cli::run::RunArgs;

#[derive(Parser)]
#[command(version, about = "Turns fluid simulation particles into a rendered water surface.", long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
    #[command(flatten)]
    global: cli::GlobalArgs,
}

#[derive(Subcommand)]
enum Command {
    /// The main job (also what runs with no arguments): the built-in `column` scene through the
    /// pipeline, pictures and files written to a folder.
    Run(RunArgs),
    /// Surface detection (Solenthaler et al. 2007, §3.1) on a file, a frame sequence or a
    /// built-in scene.
    Detect(DetectArgs),
    /// Surface detection then upsampling (Solenthaler et al. 2007, §3.2-3.4) on a file, a frame
    /// sequence or a built-in scene.
    Refine(RefineArgs),
    /// Density grid and iso-surface surfels (Iwasaki et al., §4) of a file, a frame sequence or
    /// a built-in scene.
    Surfels(cli::surfels::SurfelsArgs),
    /// A triangle mesh of the iso-surface the surfels lie on (marching cubes over the chain's
    /// density grid, the surfels as its vertices, the particles' velocities interpolated at
    /// them), per frame, as binary PLY, OBJ, legacy VTK or USD (with a stage that plays a
    /// sequence), for Blender, Houdini or a game engine.
    Mesh(cli::mesh::MeshArgs),
    /// The surface to a PNG: particles through the pipeline, drawn by EWA surfel splatting
    /// (Botsch et al. 2005; default), particle splatting (Adams et al. 2006), ray casting
    /// (Xiao et al.) or narrow-band screen-space rendering (Oliveira and Paiva), or a file of
    /// surfels as they are; with --optics the finished frame.
    Render(Box<cli::render::RenderArgs>),
    /// One frame drawn by every renderer from every surfel source, side by side on a labelled
    /// contact sheet, each with its time and its depth, normal and coverage errors against the
    /// ray-cast reference (the particles' exact iso-surface).
    Compare(cli::compare::CompareArgs),
    /// What a particle file holds: format, count, attributes and their ranges, bounds, spacing.
    Info(InfoArgs),
    /// Benchmarks.
    #[command(subcommand)]
    Bench(BenchCommand),
}

#[derive(Subcommand)]
enum BenchCommand {
    /// Neighbour search and surface detection on a jittered block, against a single-threaded
    /// reference timed in the same run.
    Detect(BenchDetectArgs),
    /// Writing and reading every file format.
    Io(BenchIoArgs),
    /// Upsampling on frames of the column scene like the paper's Table 1, against the
    /// single-threaded reference.
    Refine(cli::bench::BenchRefineArgs),
    /// The density grid (the paper's case: 150,000 particles into 256^3), against a naive
    /// single-threaded reference.
    Density(cli::bench::BenchDensityArgs),
    /// EWA surfel splatting: splats per second and ms per pass, GPU (when an adapter exists) and
    /// the CPU reference in the same run.
    Splat(cli::bench::BenchSplatArgs),
    /// Optics: caustics and the final image at the paper's sizes (512x512, 256x64 and 256x256
    /// light screens, 55k-120k surfels), GPU (when an adapter exists) and the CPU reference.
    Optics(cli::bench::BenchOpticsArgs),
    /// The whole chain on the CPU (`Pipeline`: detection to the finished frame with optics) on a
    /// frame of the column scene, per stage.
    Pipeline(cli::bench::BenchPipelineArgs),
    /// Each renderer (EWA splatting, particle splatting, ray casting) on one frame at one size,
    /// the draw alone on the CPU and on the GPU (any adapter), from the same surfels and camera;
    /// `--particles N` resamples the body to about N particles first.
    Renderers(cli::bench::BenchRenderersArgs),
    /// The narrow band of the Layered Neighborhood Method (Oliveira et al., Algorithm 1) on a
    /// block of particles, on all threads and on one.
    Lnm(cli::bench::BenchLnmArgs),
    /// The screen-space renderer (Oliveira and Paiva) on one frame's particles at full HD on the
    /// CPU: each depth filter with and without the narrow band, per pass, the band's share and
    /// the memory it saves.
    Ssfr(cli::bench::BenchSsfrArgs),
}

/// A standard output closed early (`fluid-surfels info F | head`) ends the process quietly, as
/// other command-line tools do: Rust ignores SIGPIPE, and `println!` then panicked ("failed
/// printing to stdout: Broken pipe").
fn default_sigpipe() {
    #[cfg(unix)]
    // SAFETY: restores the default action of one signal, first thing in main, before any other
    // thread exists
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
}

/// Mesa's software Vulkan driver (lavapipe) prints "XDG_RUNTIME_DIR is invalid" on stderr when
/// the variable is unset, which reads like a failure of ours: point it at a private folder.
fn quiet_lavapipe() {
    #[cfg(unix)]
    if std::env::var_os("XDG_RUNTIME_DIR").is_none() {
        use std::os::unix::fs::{DirBuilderExt, PermissionsExt};
        let dir = std::env::temp_dir().join("fluid-surfels-runtime");
        let _ = std::fs::DirBuilder::new().mode(0o700).create(&dir);
        // only a folder nobody else can enter
        let ours = std::fs::metadata(&dir)
            .is_ok_and(|m| m.is_dir() && m.permissions().mode() & 0o077 == 0);
        if ours {
            // SAFETY: called first thing in main, before any other thread exists
            unsafe { std::env::set_var("XDG_RUNTIME_DIR", &dir) };
        }
    }
}

/// glibc's allocator returns freed memory to the system as soon as a few hundred KiB lie free
/// (its trim threshold, and an mmap threshold that starts at 128 KiB), so every frame of a
/// pipeline faults its buffers in afresh: on the dam break at 640x480 (`bench pipeline --detail
/// auto`, 2 cores) 16,600 page faults a frame, a tenth of the frame's CPU time in the kernel.
/// The command line keeps up to 64 MiB free per allocator arena and serves allocations under
/// 32 MiB from its heaps: measured there, the frame 255-271 -> 245-246 ms (medians of 9, these
/// values set through `GLIBC_TUNABLES`, two runs each, a quiet hour), system time 0.41-0.62 -> 0.10-0.20 s over ten frames, peak RSS 87-91
/// -> 119-135 MB. Only on glibc, and not when `GLIBC_TUNABLES` is set (the user's own
/// settings win). The library leaves its host's allocator alone.
fn keep_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    if std::env::var_os("GLIBC_TUNABLES").is_none() {
        // SAFETY: mallopt only sets the allocator's parameters; called first thing in main,
        // before any other thread exists
        unsafe {
            libc::mallopt(libc::M_MMAP_THRESHOLD, 32 << 20);
            libc::mallopt(libc::M_TRIM_THRESHOLD, 64 << 20);
        }
    }
}

/// Every option of every subcommand takes negative numbers as values (`--radius -1` reaches
/// the range check, which says what is allowed, instead of clap's "unexpected argument").
fn negative_numbers(command: clap::Command) -> clap::Command {
    command
        .mut_args(|a| {
            // only options that take a value (clap asserts it)
            if matches!(
                a.get_action(),
                clap::ArgAction::Set | clap::ArgAction::Append
            ) {
                a.allow_negative_numbers(true)
            } else {
                a
            }
        })
        .mut_subcommands(negative_numbers)
}

fn parse() -> Cli {
    use clap::{CommandFactory, FromArgMatches};
    let matches = negative_numbers(Cli::command()).get_matches();
    Cli::from_arg_matches(&matches).unwrap_or_else(|e| e.exit())
}

fn main() -> ExitCode {
    default_sigpipe();
    quiet_lavapipe();
    keep_freed_memory();
    let cli = parse();
    cli::set_globals(cli.global.clone());
    let result = match cli.command {
        None => cli::run::run(&RunArgs {
            out_dir: PathBuf::from("out"),
            frame: ColumnParams::SPLASH_FRAME,
        }),
        Some(Command::Run(args)) => cli::run::run(&args),
        Some(Command::Detect(args)) => cli::detect::detect(&args),
        Some(Command::Info(args)) => cli::info::info(&args),
        Some(Command::Refine(args)) => cli::refine::refine_command(&args),
        Some(Command::Surfels(args)) => cli::surfels::surfels_command(&args),
        Some(Command::Mesh(args)) => cli::mesh::mesh_command(&args),
        Some(Command::Render(args)) => cli::render::render_command(&args),
        Some(Command::Compare(args)) => cli::compare::compare_command(&args),
        Some(Command::Bench(BenchCommand::Detect(args))) => cli::bench::bench_detect(&args),
        Some(Command::Bench(BenchCommand::Io(args))) => cli::bench::bench_io(&args),
        Some(Command::Bench(BenchCommand::Refine(args))) => cli::bench::bench_refine(&args),
        Some(Command::Bench(BenchCommand::Density(args))) => cli::bench::bench_density(&args),
        Some(Command::Bench(BenchCommand::Optics(args))) => cli::bench::bench_optics(&args),
        Some(Command::Bench(BenchCommand::Splat(args))) => cli::bench::bench_splat(&args),
        Some(Command::Bench(BenchCommand::Pipeline(args))) => cli::bench::bench_pipeline(&args),
        Some(Command::Bench(BenchCommand::Renderers(args))) => cli::bench::bench_renderers(&args),
        Some(Command::Bench(BenchCommand::Lnm(args))) => cli::bench::bench_lnm(&args),
        Some(Command::Bench(BenchCommand::Ssfr(args))) => cli::bench::bench_ssfr(&args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            // what reaches the terminal is escaped: a file's bytes never drive it
            let message = e.to_string();
            eprintln!("error: {}", fluid_surfels::io::clean(&message, 1000));
            let mut source = std::error::Error::source(&e);
            let mut shown = 0;
            while let Some(s) = source {
                // most errors already quote their cause; a short chain at most
                let text = s.to_string();
                if !message.contains(&text) && shown < 3 {
                    eprintln!("  caused by: {}", fluid_surfels::io::clean(&text, 300));
                    shown += 1;
                }
                source = s.source();
            }
            ExitCode::FAILURE
        }
    }
}

#[cfg(test)]
mod tests {
    use clap::CommandFactory;

    /// clap's own consistency checks over every subcommand, as the binary builds it.
    #[test]
    fn command_line_is_consistent() {
        super::negative_numbers(super::Cli::command()).debug_assert();
    }
}
