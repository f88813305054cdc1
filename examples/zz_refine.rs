use fluid_surfels::neighbours::{Backend, Neighbourhoods};
use fluid_surfels::refine::{self, RADIUS_FACTOR, RefineParams};
use fluid_surfels::scenes::{ColumnParams, ColumnSim};
use fluid_surfels::surface::{ParticleClass, SurfaceDetector, SurfaceParams};
use glam::Vec3;
use std::collections::HashMap;
fn main() {
    let mut sim = ColumnSim::new(ColumnParams::default()).unwrap();
    let mut det = SurfaceDetector::new(SurfaceParams::default()).unwrap();
    for f in 0..=14 {
        sim.advance_to(f);
        let p = sim.particles();
        let nb =
            Neighbourhoods::build(&p.positions, sim.support_radius(), Backend::CellGrid).unwrap();
        let surf = det.detect(p, &nb).unwrap();
        if f == 14 {
            let idx: Vec<usize> = (0..p.len())
                .filter(|&i| surf.classes[i] != ParticleClass::Interior)
                .collect();
            let pos: Vec<Vec3> = idx.iter().map(|&i| p.positions[i]).collect();
            let nrm: Vec<Vec3> = idx.iter().map(|&i| surf.normals[i]).collect();
            for steps in 1..=3 {
                let params = RefineParams {
                    steps,
                    ..RefineParams::with_radius(sim.support_radius())
                };
                let r = refine::refine(&pos, &nrm, &params).unwrap();
                let last = r.final_radius / RADIUS_FACTOR;
                let beta = 0.2 * last;
                let nb = Neighbourhoods::build(&r.positions, beta, Backend::CellGrid).unwrap();
                let mut kinds: HashMap<(u8, u8, bool, bool), usize> = HashMap::new();
                let mut count = 0;
                for i in 0..r.len() {
                    for &j in nb.of(i) {
                        let j = j as usize;
                        if j > i {
                            count += 1;
                            let (a, b) = (r.steps[i].min(r.steps[j]), r.steps[i].max(r.steps[j]));
                            let moved = |k: usize| {
                                r.steps[k] > 0 && r.weights[k] > 1.0 * 10.0
                                    || (r.steps[k] == 0 && r.weights[k] > 1e6)
                            };
                            *kinds.entry((a, b, moved(i), moved(j))).or_default() += 1;
                        }
                    }
                }
                let mut k: Vec<_> = kinds.into_iter().collect();
                k.sort_by_key(|x| std::cmp::Reverse(x.1));
                let rn =
                    Neighbourhoods::build(&r.positions, r.final_radius, Backend::CellGrid).unwrap();
                let pairs_rn = rn.total() / 2;
                println!(
                    "   neighbour pairs within r_n: {pairs_rn}, fraction closer than beta {:.3} %",
                    100.0 * count as f64 / pairs_rn as f64
                );
                println!(
                    "steps {steps}: {} points, {count} pairs closer than beta {beta:.4}: {:?}",
                    r.len(),
                    &k[..k.len().min(8)]
                );
            }
        }
    }
}
