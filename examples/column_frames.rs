//! Runs the built-in `column` simulation and writes a strip of pictures of some frames, with
//! particles coloured by class (interior blue, surface orange, isolated green).
//!
//! `cargo run --release --example column_frames -- [OUT.png]`

use fluid_surfels::neighbours::{Backend, Neighbourhoods};
use fluid_surfels::preview::{self, PreviewCamera, palette};
use fluid_surfels::scenes::{ColumnParams, ColumnSim};
use fluid_surfels::surface::{ParticleClass, SurfaceDetector, SurfaceParams};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let out = std::env::args()
        .nth(1)
        .unwrap_or_else(|| "column_frames.png".into());
    let params = ColumnParams::default();
    let mut sim = ColumnSim::new(params)?;
    let mut detector = SurfaceDetector::new(SurfaceParams::default())?;
    let camera = PreviewCamera::framing(glam::Vec3::ZERO, params.tank);
    let mut pictures = Vec::new();
    for frame in 0..=150 {
        sim.advance_to(frame);
        let particles = sim.particles();
        let nb = Neighbourhoods::build(
            &particles.positions,
            sim.support_radius(),
            Backend::CellGrid,
        )?;
        let surface = detector.detect(particles, &nb)?;
        if [0, 5, 10, 14, 20, 30, 60, 150].contains(&frame) {
            let counts = surface.counts();
            println!("frame {frame:3}: {counts:?}, flips {}", surface.flips);
            let colours: Vec<[u8; 3]> = surface
                .classes
                .iter()
                .map(|c| match c {
                    ParticleClass::Interior => palette::INTERIOR,
                    ParticleClass::Surface => palette::SURFACE,
                    ParticleClass::Isolated => palette::ISOLATED,
                })
                .collect();
            pictures.push(preview::render_points(
                &particles.positions,
                &colours,
                params.spacing * 0.5,
                &camera,
                320,
                320,
            )?);
        }
    }
    preview::save_png(
        &preview::side_by_side(&pictures),
        std::path::Path::new(&out),
    )?;
    println!("wrote {out}");
    Ok(())
}
