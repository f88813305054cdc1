//! `bench io`: reading and writing each particle format.

use std::path::PathBuf;
use std::time::Instant;

use fluid_surfels::io::{self, Format};
use fluid_surfels::scenes;
use fluid_surfels::{Attribute, Error, ScalarKind};
use serde::Serialize;

use crate::cli::ms;

/// Arguments of `bench io`.
#[derive(clap::Args)]
pub struct BenchIoArgs {
    /// Number of particles in the files written and read.
    #[arg(long, default_value_t = 1_000_000)]
    pub particles: usize,
    /// Timed reads per format (the fastest is reported).
    #[arg(long, default_value_t = 3)]
    pub repeat: usize,
    /// Formats to measure (default: all).
    #[arg(long, value_parser = crate::cli::format_parser(), value_delimiter = ',')]
    pub formats: Vec<Format>,
    /// Print one JSON object instead of text.
    #[arg(long)]
    pub json: bool,
}

#[derive(Serialize)]
struct IoRow {
    format: &'static str,
    file: String,
    bytes: u64,
    write_ms: f64,
    read_ms: f64,
    particles_per_second: f64,
}

#[derive(Serialize)]
struct IoReport {
    particles: usize,
    attributes: Vec<&'static str>,
    formats: Vec<IoRow>,
}

/// Writes a jittered block with ids, velocities and a density in every format, then times
/// reading each back.
pub fn bench_io(args: &BenchIoArgs) -> Result<(), Error> {
    let mut set = scenes::block(&scenes::BlockParams::with_particles(args.particles))?.particles;
    let n = set.len();
    set.velocities = Some(
        set.positions
            .iter()
            .map(|p| glam::Vec3::new(p.y, -p.x, 0.1))
            .collect(),
    );
    set.extra.push(Attribute::scalar(
        "density",
        ScalarKind::F32,
        (0..n).map(|i| 1000.0 + (i % 17) as f64).collect(),
    ));
    let dir = std::env::temp_dir().join(format!("fluid-surfels-bench-io-{}", std::process::id()));
    std::fs::create_dir_all(&dir).map_err(|e| io::IoError::Os {
        path: dir.clone(),
        source: e,
    })?;
    let formats = if args.formats.is_empty() {
        Format::ALL.to_vec()
    } else {
        args.formats.clone()
    };
    let mut rows = Vec::new();
    let mut failure = None;
    for format in formats {
        let name: PathBuf = dir.join(match format {
            Format::Bgeo => "particles.bgeo".to_owned(),
            Format::XyzRaw => "particles.bin".to_owned(),
            f => format!("particles.{}", f.name()),
        });
        let t = Instant::now();
        if let Err(e) = io::write_particles(&name, &set, Some(format)) {
            failure = Some(e);
            break;
        }
        let write_ms = ms(t);
        let bytes = std::fs::metadata(&name).map(|m| m.len()).unwrap_or(0);
        let mut best = f64::INFINITY;
        for _ in 0..args.repeat.max(1) {
            let t = Instant::now();
            match io::read_particles(&name, Some(format)) {
                Ok(back) => {
                    assert_eq!(back.len(), n, "{format:?} read back a different count");
                    best = best.min(ms(t));
                }
                Err(e) => failure = Some(e),
            }
        }
        let _ = std::fs::remove_file(&name);
        if failure.is_some() {
            break;
        }
        rows.push(IoRow {
            format: format.name(),
            file: name
                .file_name()
                .map(|f| f.to_string_lossy().into_owned())
                .unwrap_or_default(),
            bytes,
            write_ms,
            read_ms: best,
            particles_per_second: n as f64 / (best / 1e3),
        });
    }
    let _ = std::fs::remove_dir_all(&dir);
    if let Some(e) = failure {
        return Err(e.into());
    }
    let report = IoReport {
        particles: n,
        attributes: vec!["id", "velocity", "density"],
        formats: rows,
    };
    if args.json {
        crate::cli::print_json(&report);
    } else {
        println!(
            "bench io: {n} particles with id, velocity and density; fastest of {} reads",
            args.repeat.max(1)
        );
        println!("  format      file MB   write ms    read ms   particles/s");
        for r in &report.formats {
            println!(
                "  {:<10} {:>8.1} {:>10.1} {:>10.1} {:>13.0}",
                r.format,
                r.bytes as f64 / 1e6,
                r.write_ms,
                r.read_ms,
                r.particles_per_second
            );
        }
    }
    Ok(())
}
