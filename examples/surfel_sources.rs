//! Measures the three surfel sources of the pipeline (chain, particles, refined) on the real
//! particle files in `../shared/data/` (falling back to the copies in `tests/data/`), the
//! `column` splash frame and an analytic sphere: surfels, holes inside the silhouette of the
//! shaded splats (256x256, one camera per input), how far the surfels lie from the particles
//! (mean distance to the nearest particle centre, in spacings; for the sphere the rms distance
//! to the analytic surface) and the CPU time of the chain up to the surfels.
//!
//! `cargo run --release --example surfel_sources [-- --size 256] [--png DIR] [--support R]
//! [--kernel-factor K]`; prints a Markdown table, and with `--png` writes one picture per input:
//! the three sources' splats side by side. `--support` gives the files a support radius instead
//! of twice the estimated spacing, `--kernel-factor` the refined points' kernel radius in `r_n`.

use std::path::{Path, PathBuf};

use fluid_surfels::neighbours::{self, CellGrid};
use fluid_surfels::pipeline::{Pipeline, PipelineParams, SurfelSource, Through};
use fluid_surfels::scenes::{self, ColumnParams, ColumnSim};
use fluid_surfels::splat::Camera;
use fluid_surfels::{ParticleSet, io};
use glam::Vec3;

fn data(name: &str) -> Option<PathBuf> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    [
        root.join("../shared/data").join(name),
        root.join("tests/data").join(name),
    ]
    .into_iter()
    .find(|p| p.exists())
}

/// Mean distance from each surfel to the nearest particle centre, in spacings.
fn distance_to_particles(surfels: &[Vec3], particles: &[Vec3], spacing: f32) -> f32 {
    let reach = 4.0 * spacing;
    let grid = CellGrid::new(particles, reach).expect("finite particles");
    let sum: f32 = surfels
        .iter()
        .map(|&s| {
            let mut best = reach;
            grid.for_each_within(s, reach, |j| {
                best = best.min(particles[j as usize].distance(s));
            });
            best
        })
        .sum();
    sum / surfels.len().max(1) as f32 / spacing
}

fn main() -> Result<(), fluid_surfels::Error> {
    let size: u32 = std::env::args()
        .skip_while(|a| a != "--size")
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or(256);
    let png_dir: Option<PathBuf> = std::env::args()
        .skip_while(|a| a != "--png")
        .nth(1)
        .map(PathBuf::from);
    let flag = |name: &str| -> Option<f32> {
        std::env::args()
            .skip_while(|a| a != name)
            .nth(1)
            .and_then(|s| s.parse().ok())
    };
    // the files' own support radius (their README: 0.1) instead of the estimate
    let file_radius = flag("--support");
    let kernel_factor = flag("--kernel-factor");
    let mut inputs: Vec<(String, ParticleSet, Option<f32>)> = Vec::new();
    for name in [
        "dam_break_frame_23_24389_particles.bgeo",
        "double_dam_break_frame_26_4732_particles.vtk",
        "free_particles_125_particles.vtk",
    ] {
        if let Some(path) = data(name) {
            inputs.push((name.into(), io::read_particles(&path, None)?, file_radius));
        }
    }
    let mut sim = ColumnSim::new(ColumnParams::default())?;
    sim.advance_to(ColumnParams::SPLASH_FRAME);
    inputs.push((
        "column, splash frame".into(),
        sim.particles().clone(),
        Some(sim.support_radius()),
    ));
    let sphere = scenes::sphere(&scenes::SphereParams {
        radius_in_spacings: 10.0,
        ..Default::default()
    })?;
    let sphere_radius = 10.0 * sphere.spacing;
    inputs.push((
        "sphere, R = 10 spacings".into(),
        sphere.particles.clone(),
        Some(sphere.support_radius),
    ));
    println!(
        "| input | particles | source | surfels | grid | holes (px of {size}x{size}) | covered px | distance (spacings) | ms to surfels |"
    );
    println!("| --- | --- | --- | --- | --- | --- | --- | --- | --- |");
    for (name, particles, radius) in &inputs {
        let spacing = neighbours::estimate_spacing(&particles.positions)?;
        let (lo, hi) = particles
            .positions
            .iter()
            .fold((Vec3::INFINITY, Vec3::NEG_INFINITY), |(a, b), &p| {
                (a.min(p), b.max(p))
            });
        let pad = Vec3::splat(2.0 * radius.unwrap_or(2.0 * spacing));
        let camera = Camera::framing(lo - pad, hi + pad);
        let mut panels = Vec::new();
        for source in SurfelSource::ALL {
            let mut params = PipelineParams {
                support_radius: *radius,
                source,
                ..Default::default()
            };
            if let Some(k) = kernel_factor {
                params.refine.kernel_factor = k;
            }
            params.scene.camera = Some(camera);
            params.scene.optics.image_size = [size, size];
            let mut pipeline = Pipeline::new(params)?;
            // one warm-up frame, then the timed one (the hysteresis state then is a second
            // frame's, as in a sequence)
            pipeline.frame_through(particles, Through::Surfels)?;
            let frame = pipeline.frame_through(particles, Through::Splats)?;
            let t = &frame.timings;
            let ms = t.neighbours_ms + t.detect_ms + t.refine_ms + t.density_ms + t.surfels_ms;
            let splats = frame.splats.as_ref().expect("through the splats");
            let positions: Vec<Vec3> = frame
                .render_surfels
                .iter()
                .map(|s| Vec3::from(s.position))
                .collect();
            let distance = if name.starts_with("sphere") {
                let rms = (positions
                    .iter()
                    .map(|p| (p.length() - sphere_radius).powi(2))
                    .sum::<f32>()
                    / positions.len().max(1) as f32)
                    .sqrt();
                format!("{:.3} rms to the sphere", rms / sphere.spacing)
            } else {
                format!(
                    "{:.2}",
                    distance_to_particles(&positions, &particles.positions, spacing)
                )
            };
            let grid = frame
                .grid
                .as_ref()
                .map(|g| {
                    let d = g.spec().dims;
                    format!("{}x{}x{}", d[0], d[1], d[2])
                })
                .unwrap_or_else(|| "-".into());
            println!(
                "| {name} | {} | {} | {} | {grid} | {} | {} | {distance} | {ms:.0} |",
                particles.len(),
                source.as_str(),
                positions.len(),
                fluid_surfels::quality::enclosed_holes(splats),
                splats.covered_pixels(),
            );
            for w in &frame.warnings {
                eprintln!("{name} {}: {w}", source.as_str());
            }
            panels.push(image::buffer::ConvertBuffer::convert(&splats.image));
        }
        if let Some(dir) = &png_dir {
            std::fs::create_dir_all(dir).map_err(|e| io::IoError::Os {
                path: dir.clone(),
                source: e,
            })?;
            let file: String = name
                .chars()
                .map(|c| if c.is_ascii_alphanumeric() { c } else { '_' })
                .collect();
            fluid_surfels::preview::save_png(
                &fluid_surfels::preview::side_by_side(&panels),
                &dir.join(format!("{file}.png")),
            )?;
        }
    }
    Ok(())
}
