//! `fluid-surfels mesh`: a triangle mesh of the chain's iso-surface (issue 40) per frame, for
//! Blender, Houdini or a game engine: marching cubes over the density grid the surfels lie on,
//! its vertices the surfels (on the exact iso-surface), with the particles' velocities
//! interpolated at the vertices when the input has them, written as binary PLY, OBJ, legacy VTK
//! or USD (a `.usda` sequence also gets a stage that plays it, with value clips).

use std::path::{Path, PathBuf};
use std::time::Instant;

use fluid_surfels::Error;
use fluid_surfels::mesh::write::{MeshFormat, usd_stage_text, write_usd_stage};
use fluid_surfels::pipeline::{
    Calibration, Detail, Pipeline, PipelineParams, SurfelSource, Through,
};
use fluid_surfels::sequence::FramePattern;
use serde::Serialize;

use super::{OutputKind, check_output, ms};

/// Arguments of `mesh`.
#[derive(clap::Args)]
pub struct MeshArgs {
    #[command(flatten)]
    pub source: super::SourceArgs,
    #[command(flatten)]
    pub outputs: super::OutputArgs,
    /// Where the surface comes from: `chain` (detection, upsampling, the density grid of the
    /// refined surface and the interior; default) or `particles` (the particles' own density
    /// grid); the surface at the fluid's boundary unless --calibration paper. Over a --config
    /// file's `source`.
    #[arg(long = "source", value_parser = super::names_parser(&[SurfelSource::Chain, SurfelSource::Particles], SurfelSource::as_str))]
    pub surfel_source: Option<SurfelSource>,
    /// Pipeline file (TOML; see docs/parameters.md): the stages' tables and keys, such as
    /// `source`, `[grid] kernel = "cubic-spline"` or `[surfels] iso_fraction`, under the flags
    /// given here (its camera, light and optics draw nothing: a mesh has no picture).
    #[arg(long, value_name = "FILE")]
    pub config: Option<PathBuf>,
    /// Refinement steps of the chain (the `refine.steps` key; default 3, the paper's).
    #[arg(long)]
    pub steps: Option<u32>,
    /// Where the surface lies: boundary (default), paper (eq. 1's sums) or volume (with
    /// --source particles: splashsurf's field, each particle weighted by its SPH volume, the
    /// surface at the fluid fraction `grid.volume_threshold`, default 0.6).
    #[arg(long, value_parser = super::names_parser(&Calibration::ALL, Calibration::as_str))]
    pub calibration: Option<Calibration>,
    /// The USD stage that plays a `.usda` sequence (value clips of the frames' files, listing
    /// every frame of --frames, so that the shards of a job array write the same stage); by
    /// default the --out pattern without its number (`out/mesh_{:04}.usda` -> `out/mesh.usda`).
    #[arg(long, value_name = "FILE")]
    pub stage: Option<PathBuf>,
    /// Frames per second of the USD stage (`timeCodesPerSecond`; velocities are per second).
    #[arg(long, default_value_t = 24.0)]
    pub fps: f64,
}

#[derive(Serialize)]
struct MeshReport {
    frame: Option<usize>,
    particles: usize,
    vertices: usize,
    triangles: usize,
    closed: bool,
    euler_characteristic: i64,
    /// Whether the vertices carry the particles' interpolated velocities.
    velocities: bool,
    surfels_ms: f64,
    mesh_ms: f64,
    velocities_ms: f64,
    output: Option<String>,
}

impl MeshArgs {
    /// The pipeline's parameters: the --config file's (or the defaults), the flags over them,
    /// the support radius `radius` (--radius, else the file's `support_radius`, else the one
    /// estimated), `fixed` detail (a file on disk never depends on an image size), the grid
    /// within the memory budget. Checked here, so that a bad file fails before any frame.
    fn params(&self, radius: f32) -> Result<PipelineParams, Error> {
        let mut p = match &self.config {
            Some(path) => PipelineParams::from_toml_file(path)?,
            None => PipelineParams::default(),
        };
        if self.source.radius.is_some() || p.support_radius.is_none() {
            p.support_radius = Some(radius);
        }
        if let Some(s) = self.surfel_source {
            p.source = s;
        }
        p.detail = Detail::Fixed;
        if let Some(k) = self.steps {
            p.refine.steps = k;
        }
        if let Some(c) = self.calibration {
            p.grid.calibration = c;
        }
        p.grid.memory_budget = super::memory_budget();
        p.validate()?;
        Ok(p)
    }
}

/// The mesh of one frame through `pipeline`, with velocities interpolated from `velocities`
/// when given and the output holds them, written to `out` when given (a `.usda` frame of a
/// sequence as time samples at its frame number).
fn mesh_frame(
    pipeline: &mut Pipeline,
    particles: fluid_surfels::ParticleView<'_>,
    velocities: Option<&[glam::Vec3]>,
    frame: Option<usize>,
    out: Option<&Path>,
) -> Result<MeshReport, Error> {
    let t = Instant::now();
    let mut f = pipeline.frame_through(particles, Through::Mesh)?;
    for w in &f.warnings {
        eprintln!("warning: {w}");
    }
    let mesh_ms = f.timings.mesh_ms;
    let surfels_ms = ms(t) - mesh_ms;
    let mut mesh = f.mesh.take().unwrap_or_default();
    let format = out.map(MeshFormat::of_path).transpose()?;
    let t = Instant::now();
    if let Some(v) = velocities.filter(|_| format.is_none_or(MeshFormat::has_velocities)) {
        mesh.interpolate_velocities(particles.positions, v, f.radius)?;
    }
    let velocities_ms = ms(t);
    if let Some(out) = out {
        match (format, frame) {
            (Some(MeshFormat::Usda), Some(f)) => mesh.write_usda(out, Some(f as f64))?,
            _ => mesh.write(out)?,
        }
    }
    let topology = mesh.topology();
    Ok(MeshReport {
        frame,
        particles: particles.len(),
        vertices: mesh.positions.len(),
        triangles: mesh.triangles.len(),
        closed: topology.closed,
        euler_characteristic: topology.euler_characteristic,
        velocities: mesh.velocities.is_some(),
        surfels_ms,
        mesh_ms,
        velocities_ms,
        output: out.map(|p| p.display().to_string()),
    })
}

fn print(r: &MeshReport) {
    println!(
        "{}{} particles: {} vertices, {} triangles ({}, Euler characteristic {}); surfels {:.0} ms, mesh {:.0} ms{}",
        r.frame.map(|f| format!("frame {f}: ")).unwrap_or_default(),
        r.particles,
        r.vertices,
        r.triangles,
        if r.closed { "closed" } else { "open" },
        r.euler_characteristic,
        r.surfels_ms,
        r.mesh_ms,
        r.output
            .as_ref()
            .map(|o| format!("; wrote {o}"))
            .unwrap_or_default()
    );
}

pub fn mesh_command(args: &MeshArgs) -> Result<(), Error> {
    if args.outputs.png.is_some() || args.outputs.out_format.is_some() {
        return Err(Error::InvalidArgument {
            argument: "--png/--out-format",
            reason: "a mesh is written by the extension of --out (.ply, .obj, .vtk, .vtu or .usda)"
                .into(),
        });
    }
    if let Some(out) = &args.outputs.out {
        MeshFormat::of_path(Path::new(out)).map_err(|e| match e {
            Error::InvalidArgument { reason, .. } => Error::InvalidArgument {
                argument: "--out",
                reason,
            },
            e => e,
        })?;
    }
    if let Some(pattern) = args.source.sequence()? {
        return mesh_sequence(args, &pattern);
    }
    let src = &args.source;
    let input = src.input.as_deref().map(PathBuf::from);
    let out = args.outputs.out.as_deref().map(PathBuf::from);
    if let Some(o) = &out {
        check_output(o, input.as_deref(), args.outputs.force, OutputKind::Single)?;
    }
    if args.stage.is_some() {
        return Err(Error::InvalidArgument {
            argument: "--stage",
            reason:
                "a stage plays a sequence: give --input a frame pattern and --out a .usda pattern"
                    .into(),
        });
    }
    let (_, particles, radius) = super::particles_of(
        input.as_deref(),
        src.scene,
        src.format,
        src.frame,
        src.radius,
    )?;
    let mut pipeline = Pipeline::new(args.params(radius)?)?;
    let view = fluid_surfels::ParticleView::of_positions(&particles.positions);
    let report = mesh_frame(
        &mut pipeline,
        view,
        particles.velocities.as_deref(),
        None,
        out.as_deref(),
    )?;
    if args.outputs.json {
        super::print_json(&report);
    } else {
        print(&report);
    }
    Ok(())
}

fn mesh_sequence(args: &MeshArgs, pattern: &FramePattern) -> Result<(), Error> {
    let super::PreparedSequence {
        sequence,
        out,
        radius,
        ..
    } = super::prepare_sequence(&args.source, &args.outputs, pattern, "mesh")?;
    let params = args.params(radius)?;
    let stage = stage_of(args, out.as_ref(), &sequence.frames)?;
    let run = sequence.run_warm(
        || Pipeline::new(params.clone()),
        |pipeline, f| {
            let particles = super::read_particles(&pattern.path(f), args.source.format)?;
            pipeline.warm_up(&particles, Through::Surfels)
        },
        |pipeline, f| {
            let particles = super::read_particles(&pattern.path(f), args.source.format)?;
            let path = out.as_ref().map(|p| p.path(f));
            mesh_frame(
                pipeline,
                particles.view(),
                particles.velocities.as_deref(),
                Some(f),
                path.as_deref(),
            )
        },
    )?;
    if let Some((stage, frames)) = &stage {
        write_usd_stage(stage, frames, args.fps)?;
    }
    if args.outputs.json {
        super::print_json(&serde_json::json!({
            "input": args.source.input, "radius": radius, "jobs": run.jobs,
            "processed": run.results.len(), "skipped": run.skipped, "seconds": run.seconds,
            "frames": run.results,
            "stage": stage.as_ref().map(|(s, _)| s.display().to_string()),
        }));
    } else {
        for r in &run.results {
            print(r);
        }
        println!(
            "{} frames meshed, {} skipped (outputs existed), {:.1} s",
            run.results.len(),
            run.skipped.len(),
            run.seconds
        );
        if let Some((stage, frames)) = &stage {
            println!(
                "wrote the USD stage {} ({} frames, {} fps)",
                stage.display(),
                frames.len(),
                args.fps
            );
        }
    }
    Ok(())
}

/// A USD stage's path and its frames (time code, file).
type Stage = (PathBuf, Vec<(f64, PathBuf)>);

/// The USD stage of a `.usda` sequence and its frames (every frame of the range, so that
/// every shard writes the same stage), checked before any work: an existing stage is
/// replaced only when it is the same text, or with --force or --skip-existing.
fn stage_of(
    args: &MeshArgs,
    out: Option<&FramePattern>,
    frames: &[usize],
) -> Result<Option<Stage>, Error> {
    let usda =
        out.is_some_and(|p| MeshFormat::of_path(&p.path(0)).is_ok_and(|f| f == MeshFormat::Usda));
    if !usda {
        return match args.stage {
            Some(_) => Err(Error::InvalidArgument {
                argument: "--stage",
                reason: "a stage plays a .usda sequence: give --out a .usda pattern".into(),
            }),
            None => Ok(None),
        };
    }
    let out = out.expect("a .usda pattern");
    let stage = args.stage.clone().unwrap_or_else(|| out.without_number());
    let frames: Vec<(f64, PathBuf)> = frames.iter().map(|&f| (f as f64, out.path(f))).collect();
    let text = usd_stage_text(&stage, &frames, args.fps)?;
    let same = std::fs::read(&stage).is_ok_and(|old| old == text.as_bytes());
    if !same {
        check_output(
            &stage,
            None,
            args.outputs.force || args.outputs.skip_existing,
            OutputKind::Single,
        )?;
    }
    Ok(Some((stage, frames)))
}
