//! Refines the splash frame of the `column` scene repeatedly: a steady workload for profilers.
//!
//! `cargo run --release --example refine_profile -- [REPEATS] [reference]`

use fluid_surfels::neighbours::{Backend, Neighbourhoods};
use fluid_surfels::refine::{self, RefineParams};
use fluid_surfels::scenes::{ColumnParams, ColumnSim};
use fluid_surfels::surface::{ParticleClass, SurfaceDetector, SurfaceParams};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let repeats: usize = std::env::args()
        .nth(1)
        .and_then(|a| a.parse().ok())
        .unwrap_or(20);
    let reference = std::env::args().nth(2).is_some_and(|a| a == "reference");
    let mut sim = ColumnSim::new(ColumnParams::default())?;
    let mut detector = SurfaceDetector::new(SurfaceParams::default())?;
    let mut input = None;
    for f in 0..=ColumnParams::SPLASH_FRAME {
        sim.advance_to(f);
        let p = sim.particles();
        let nb = Neighbourhoods::build(&p.positions, sim.support_radius(), Backend::CellGrid)?;
        let s = detector.detect(p, &nb)?;
        let idx: Vec<usize> = (0..p.len())
            .filter(|&i| s.classes[i] != ParticleClass::Interior)
            .collect();
        input = Some((
            idx.iter().map(|&i| p.positions[i]).collect::<Vec<_>>(),
            idx.iter().map(|&i| s.normals[i]).collect::<Vec<_>>(),
        ));
    }
    let (p, n) = input.expect("at least one frame");
    let params = RefineParams::with_radius(sim.support_radius());
    let t = std::time::Instant::now();
    let mut points = 0;
    for _ in 0..repeats {
        let r = if reference {
            refine::refine_reference(&p, &n, &params)?
        } else {
            refine::refine(&p, &n, &params)?
        };
        points = r.len();
    }
    let s = t.elapsed().as_secs_f64() / repeats as f64;
    println!(
        "{} -> {points} points, {:.1} ms per run, {:.2} M points/s",
        p.len(),
        s * 1e3,
        points as f64 / s / 1e6
    );
    Ok(())
}
