//! The command line's subcommands and what they share.

pub mod bench;
pub mod detect;
pub mod info;
pub mod run;

use std::io::IsTerminal;
use std::path::Path;
use std::time::Instant;

use fluid_surfels::io;
use fluid_surfels::preview::palette;
use fluid_surfels::surface::{ParticleClass, Surface};
use fluid_surfels::{Error, ParticleSet};

pub fn ms(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}

pub fn class_colours(surface: &Surface) -> Vec<[u8; 3]> {
    surface
        .classes
        .iter()
        .map(|c| match c {
            ParticleClass::Interior => palette::INTERIOR,
            ParticleClass::Surface => palette::SURFACE,
            ParticleClass::Isolated => palette::ISOLATED,
        })
        .collect()
}

/// The surface particles with their normals (and every attribute they had).
pub fn surface_particles(particles: &ParticleSet, surface: &Surface) -> ParticleSet {
    let idx = surface.indices_of(ParticleClass::Surface);
    let mut out = particles.select(&idx);
    out.normals = Some(idx.iter().map(|&i| surface.normals[i]).collect());
    out
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

/// Refuses to replace an existing file without `--force`, and never replaces the input.
pub fn check_output(out: &Path, input: Option<&Path>, force: bool) -> Result<(), Error> {
    let same = input.is_some_and(|i| {
        i == out || matches!((std::fs::canonicalize(i), std::fs::canonicalize(out)), (Ok(a), Ok(b)) if a == b)
    });
    if same || (out.exists() && !force) {
        let why = if same {
            "it is the input file"
        } else {
            "it exists; pass --force to replace it (or --skip-existing for sequences)"
        };
        return Err(io::IoError::Os {
            path: out.to_owned(),
            source: std::io::Error::new(
                std::io::ErrorKind::AlreadyExists,
                format!("refusing to overwrite: {why}"),
            ),
        }
        .into());
    }
    Ok(())
}
