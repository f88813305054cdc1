//! `fluid-surfels mesh`: a triangle mesh of the chain's iso-surface (issue 40) per frame, for
//! Blender, Houdini or a game engine: marching cubes over the density grid the surfels lie on,
//! its vertices the surfels (on the exact iso-surface), written as binary PLY or OBJ.

use std::path::{Path, PathBuf};
use std::time::Instant;

use fluid_surfels::Error;
use fluid_surfels::mesh::Mesh;
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
    /// grid); the surface at the fluid's boundary unless --calibration paper.
    #[arg(long = "source", value_parser = super::names_parser(&[SurfelSource::Chain, SurfelSource::Particles], SurfelSource::as_str), default_value = "chain")]
    pub surfel_source: SurfelSource,
    /// Refinement steps of the chain (the `refine.steps` key; default 3, the paper's).
    #[arg(long)]
    pub steps: Option<u32>,
    /// Where the surface lies: boundary (default) or paper (eq. 1's sums).
    #[arg(long, value_parser = super::names_parser(&Calibration::ALL, Calibration::as_str))]
    pub calibration: Option<Calibration>,
}

#[derive(Serialize)]
struct MeshReport {
    frame: Option<usize>,
    particles: usize,
    vertices: usize,
    triangles: usize,
    closed: bool,
    euler_characteristic: i64,
    surfels_ms: f64,
    mesh_ms: f64,
    output: Option<String>,
}

impl MeshArgs {
    /// The pipeline's parameters: `fixed` detail (a file on disk never depends on an image
    /// size), the grid within the memory budget.
    fn params(&self, radius: f32) -> PipelineParams {
        let mut p = PipelineParams {
            support_radius: Some(radius),
            source: self.surfel_source,
            detail: Detail::Fixed,
            ..PipelineParams::default()
        };
        if let Some(k) = self.steps {
            p.refine.steps = k;
        }
        if let Some(c) = self.calibration {
            p.grid.calibration = c;
        }
        p.grid.memory_budget = super::memory_budget();
        p
    }
}

/// The mesh of one frame through `pipeline`, written to `out` when given.
fn mesh_frame(
    pipeline: &mut Pipeline,
    particles: fluid_surfels::ParticleView<'_>,
    frame: Option<usize>,
    out: Option<&Path>,
) -> Result<MeshReport, Error> {
    let t = Instant::now();
    let f = pipeline.frame_through(particles, Through::Surfels)?;
    for w in &f.warnings {
        eprintln!("warning: {w}");
    }
    let surfels_ms = ms(t);
    let t = Instant::now();
    let mesh = f.mesh().unwrap_or_default();
    let mesh_ms = ms(t);
    if let Some(out) = out {
        mesh.write(out)?;
    }
    let topology = mesh.topology();
    Ok(MeshReport {
        frame,
        particles: particles.len(),
        vertices: mesh.positions.len(),
        triangles: mesh.triangles.len(),
        closed: topology.closed,
        euler_characteristic: topology.euler_characteristic,
        surfels_ms,
        mesh_ms,
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
            reason: "a mesh is written by the extension of --out (.ply or .obj)".into(),
        });
    }
    if let Some(out) = &args.outputs.out {
        Mesh::is_ply(Path::new(out)).map_err(|_| Error::InvalidArgument {
            argument: "--out",
            reason: format!("{out}: a mesh is written as .ply (binary) or .obj"),
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
    let (_, positions, radius) = super::positions_of(
        input.as_deref(),
        src.scene,
        src.format,
        src.frame,
        src.radius,
    )?;
    let mut pipeline = Pipeline::new(args.params(radius))?;
    let view = fluid_surfels::ParticleView::of_positions(&positions);
    let report = mesh_frame(&mut pipeline, view, None, out.as_deref())?;
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
    let run = sequence.run_warm(
        || Pipeline::new(args.params(radius)),
        |pipeline, f| {
            let particles = super::read_particles(&pattern.path(f), args.source.format)?;
            pipeline.warm_up(&particles, Through::Surfels)
        },
        |pipeline, f| {
            let particles = super::read_particles(&pattern.path(f), args.source.format)?;
            let path = out.as_ref().map(|p| p.path(f));
            mesh_frame(pipeline, particles.view(), Some(f), path.as_deref())
        },
    )?;
    if args.outputs.json {
        super::print_json(&serde_json::json!({
            "input": args.source.input, "radius": radius, "jobs": run.jobs,
            "processed": run.results.len(), "skipped": run.skipped, "seconds": run.seconds,
            "frames": run.results,
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
    }
    Ok(())
}
