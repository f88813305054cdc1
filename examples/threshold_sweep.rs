//! The measurement behind the default surface thresholds (`SurfaceParams::default()`): recall and
//! precision of surface detection on the jittered `block` and `sphere` scenes for a range of
//! high thresholds, and flips per frame on the settling `column` pool with and without
//! hysteresis for a range of low thresholds.
//!
//! `cargo run --release --example threshold_sweep [FIRST_FRAME]` (default 100: frames 101-200)

use fluid_surfels::neighbours::{Backend, Neighbourhoods};
use fluid_surfels::scenes::{self, ColumnParams, ColumnSim, Scene};
use fluid_surfels::surface::{ParticleClass, SurfaceDetector, SurfaceParams, detect_surface};

fn recall_precision(scene: &Scene, params: &SurfaceParams) -> (f64, f64) {
    let shape = scene.shape.expect("static scenes have an analytic shape");
    let nb = Neighbourhoods::build(
        &scene.particles.positions,
        scene.support_radius,
        Backend::CellGrid,
    )
    .unwrap();
    let surface = detect_surface(&scene.particles, &nb, params).unwrap();
    let (mut tp, mut fp, mut fneg) = (0usize, 0usize, 0usize);
    for (p, class) in scene.particles.positions.iter().zip(&surface.classes) {
        let truth = shape.depth(*p) < scene.spacing;
        let found = *class == ParticleClass::Surface;
        match (truth, found) {
            (true, true) => tp += 1,
            (false, true) => fp += 1,
            (true, false) => fneg += 1,
            _ => {}
        }
    }
    (
        tp as f64 / (tp + fneg) as f64,
        tp as f64 / (tp + fp).max(1) as f64,
    )
}

fn main() {
    let block = scenes::block(&scenes::BlockParams::default()).unwrap();
    let sphere = scenes::sphere(&scenes::SphereParams::default()).unwrap();
    let lattice = scenes::lattice_sphere(&scenes::SphereParams::default()).unwrap();
    println!(
        "particles: block {}, sphere {}, lattice sphere {}",
        block.particles.len(),
        sphere.particles.len(),
        lattice.particles.len()
    );
    println!(
        "high threshold (x r) | block recall precision | sphere recall precision | lattice-sphere recall precision"
    );
    for k in 0..=20 {
        let high = 0.07 + 0.01 * k as f32;
        let params = SurfaceParams {
            high_threshold: high,
            low_threshold: high,
            ..SurfaceParams::default()
        };
        let (br, bp) = recall_precision(&block, &params);
        let (sr, sp) = recall_precision(&sphere, &params);
        let (lr, lp) = recall_precision(&lattice, &params);
        println!(
            "{high:.3} | {:.2} % {:.2} % | {:.2} % {:.2} % | {:.2} % {:.2} %",
            br * 100.0,
            bp * 100.0,
            sr * 100.0,
            sp * 100.0,
            lr * 100.0,
            lp * 100.0
        );
    }

    let mut sim = ColumnSim::new(ColumnParams::default()).unwrap();
    let first: usize = std::env::args()
        .nth(1)
        .and_then(|a| a.parse().ok())
        .unwrap_or(100);
    sim.advance_to(first);
    let frames: Vec<_> = (0..100)
        .map(|_| {
            sim.step_frame();
            sim.particles().clone()
        })
        .collect();
    let high = SurfaceParams::default().high_threshold;
    println!(
        "\ncolumn frames {}..{}: low threshold (x r) | mean flips per frame",
        first + 1,
        first + 100
    );
    for k in 0..=9 {
        let low = high - 0.01 * k as f32;
        let mut detector = SurfaceDetector::new(SurfaceParams {
            high_threshold: high,
            low_threshold: low,
            ..SurfaceParams::default()
        })
        .unwrap();
        let mut flips = 0;
        for f in &frames {
            let nb = Neighbourhoods::build(&f.positions, sim.support_radius(), Backend::CellGrid)
                .unwrap();
            flips += detector.detect(f, &nb).unwrap().flips;
        }
        println!("{low:.3} | {:.1}", flips as f64 / 99.0);
    }
}
