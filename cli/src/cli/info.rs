//! `fluid-surfels info FILE`: what a particle file holds.

use std::path::PathBuf;

use fluid_surfels::io::Format;
use fluid_surfels::sequence::{FramePattern, FrameRange};
use fluid_surfels::{Error, neighbours};
use rayon::prelude::*;
use serde::Serialize;

/// Arguments of `info`.
#[derive(clap::Args)]
pub struct InfoArgs {
    /// The particle file, or a numbered sequence with `{}` or `{:04}` for the frame number
    /// (one line per frame).
    pub file: PathBuf,
    /// Frames of a sequence: A..B, A..=B, with an optional :STEP (default: every file found).
    #[arg(long)]
    pub frames: Option<FrameRange>,
    /// Frames read at once (sequences).
    #[arg(long, default_value_t = 1)]
    pub jobs: usize,
    /// Its format (default: from the extension).
    #[arg(long, value_parser = super::format_parser())]
    pub format: Option<Format>,
    /// Print one JSON object instead of text.
    #[arg(long)]
    pub json: bool,
}

#[derive(Serialize)]
struct AttributeInfo {
    name: String,
    kind: String,
    components: usize,
    min: Option<f64>,
    max: Option<f64>,
}

#[derive(Serialize)]
struct Info {
    file: String,
    format: &'static str,
    bytes: u64,
    particles: usize,
    attributes: Vec<AttributeInfo>,
    bounds_min: Option<[f32; 3]>,
    bounds_max: Option<[f32; 3]>,
    spacing_estimate: Option<f32>,
    /// Median distance to the nearest other particle.
    nearest_distance: Option<f32>,
}

fn range(values: impl Iterator<Item = f64>) -> (Option<f64>, Option<f64>) {
    values.fold((None, None), |(lo, hi): (Option<f64>, Option<f64>), v| {
        (
            Some(lo.map_or(v, |l| l.min(v))),
            Some(hi.map_or(v, |h| h.max(v))),
        )
    })
}

/// Integers as integers, other values with six significant decimals.
fn number(v: f64) -> String {
    if v.fract() == 0.0 && v.abs() < 1e15 {
        format!("{v:.0}")
    } else {
        format!("{v:.6}")
    }
}

#[derive(Serialize)]
struct FrameInfo {
    frame: usize,
    particles: usize,
    bounds_min: Option<[f32; 3]>,
    bounds_max: Option<[f32; 3]>,
}

/// One line per frame of a sequence.
fn info_sequence(args: &InfoArgs, pattern: &FramePattern) -> Result<(), Error> {
    let frames = super::sequence_frames(pattern, args.frames)?;
    let jobs = super::jobs(args.jobs, frames.len())?;
    let bar = super::progress(frames.len() as u64, "info");
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(jobs)
        .build()
        .map_err(|e| Error::InvalidArgument {
            argument: "--jobs",
            reason: e.to_string(),
        })?;
    let rows: Result<Vec<FrameInfo>, Error> = pool.install(|| {
        frames
            .par_iter()
            .map(|&f| {
                let set = super::read_particles(&pattern.path(f), args.format)?;
                bar.inc(1);
                let b = set.bounds();
                Ok(FrameInfo {
                    frame: f,
                    particles: set.len(),
                    bounds_min: b.map(|b| b.0.to_array()),
                    bounds_max: b.map(|b| b.1.to_array()),
                })
            })
            .collect()
    });
    bar.finish_and_clear();
    let rows = rows?;
    if args.json {
        super::print_json(&rows);
    } else {
        for r in &rows {
            let (lo, hi) = (
                r.bounds_min.unwrap_or_default(),
                r.bounds_max.unwrap_or_default(),
            );
            println!(
                "frame {:>6}: {:>9} particles, bounds [{:.4}, {:.4}, {:.4}] .. [{:.4}, {:.4}, {:.4}]",
                r.frame, r.particles, lo[0], lo[1], lo[2], hi[0], hi[1], hi[2]
            );
        }
    }
    Ok(())
}

pub fn info(args: &InfoArgs) -> Result<(), Error> {
    if let Some(pattern) = FramePattern::parse(&args.file.to_string_lossy())? {
        return info_sequence(args, &pattern);
    }
    if args.frames.is_some() {
        return Err(Error::InvalidArgument {
            argument: "--frames",
            reason: "needs a file pattern with {} (a sequence)".into(),
        });
    }
    let format = match args.format {
        Some(f) => f,
        None => Format::from_path(&args.file)?,
    };
    let set = super::read_particles(&args.file, Some(format))?;
    let mut attributes = Vec::new();
    let mut push =
        |name: &str, kind: &str, components: usize, values: &mut dyn Iterator<Item = f64>| {
            let (min, max) = range(values);
            attributes.push(AttributeInfo {
                name: name.to_owned(),
                kind: kind.to_owned(),
                components,
                min,
                max,
            });
        };
    if let Some(ids) = &set.ids {
        push("id", "u32", 1, &mut ids.iter().map(|&i| i as f64));
    }
    if let Some(v) = &set.velocities {
        push(
            "velocity",
            "f32",
            3,
            &mut v.iter().flat_map(|v| v.to_array()).map(f64::from),
        );
    }
    if let Some(m) = &set.masses {
        push("mass", "f32", 1, &mut m.iter().map(|&m| m as f64));
    }
    if let Some(nrm) = &set.normals {
        push(
            "normal",
            "f32",
            3,
            &mut nrm.iter().flat_map(|v| v.to_array()).map(f64::from),
        );
    }
    if let Some(c) = &set.colours {
        push(
            "colour",
            "u8",
            3,
            &mut c.iter().flatten().map(|&c| c as f64),
        );
    }
    for a in &set.extra {
        push(
            &a.name,
            &format!("{:?}", a.kind).to_lowercase(),
            a.components,
            &mut a.values.iter().copied(),
        );
    }
    let bounds = set.bounds();
    let spacing = neighbours::spacing_estimate(&set.positions).ok();
    let info = Info {
        file: args.file.display().to_string(),
        format: format.name(),
        bytes: std::fs::metadata(&args.file).map(|m| m.len()).unwrap_or(0),
        particles: set.len(),
        attributes,
        bounds_min: bounds.map(|b| b.0.to_array()),
        bounds_max: bounds.map(|b| b.1.to_array()),
        spacing_estimate: spacing.map(|e| e.spacing),
        nearest_distance: spacing.map(|e| e.nearest),
    };
    if args.json {
        super::print_json(&info);
        return Ok(());
    }
    println!("{}: {} ({} bytes)", info.file, info.format, info.bytes);
    println!("  particles  {}", info.particles);
    if let (Some(lo), Some(hi)) = (info.bounds_min, info.bounds_max) {
        println!(
            "  bounds     [{:.6}, {:.6}, {:.6}] .. [{:.6}, {:.6}, {:.6}]",
            lo[0], lo[1], lo[2], hi[0], hi[1], hi[2]
        );
    }
    match info.spacing_estimate {
        Some(s) => println!(
            "  spacing    {s:.6} (from the density of the {} nearest neighbours; support radius 2x: {:.6}; median nearest-neighbour distance {:.6})",
            neighbours::SPACING_NEIGHBOURS,
            2.0 * s,
            info.nearest_distance.unwrap_or(s)
        ),
        None => println!("  spacing    unknown (fewer than two distinct particles)"),
    }
    if info.attributes.is_empty() {
        println!("  attributes none");
    }
    for a in &info.attributes {
        let shape = if a.components == 1 {
            a.kind.clone()
        } else {
            format!("{} x {}", a.kind, a.components)
        };
        match (a.min, a.max) {
            (Some(lo), Some(hi)) => println!(
                "  attribute  {:<16} {:<10} range {} .. {}",
                a.name,
                shape,
                number(lo),
                number(hi)
            ),
            _ => println!("  attribute  {:<16} {:<10}", a.name, shape),
        }
    }
    Ok(())
}
