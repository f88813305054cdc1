//! A collapsing water column in a tank, simulated with position based fluids (Macklin and
//! Müller 2013, "Position Based Fluids"): the test-data generator behind the `column` scene.
//!
//! It is deliberately small and plain: a Jacobi solve of the density constraint
//! `C_i = max(rho_i / rho_0 - 1, 0)` (unilateral, so the free surface does not clump), spiky
//! kernel gradients, XSPH viscosity, and walls that clamp positions. Every update is a pure
//! function of the previous state, so frames are identical whatever the thread count.
//! It is not a validated solver; it makes irregular, dynamic particle frames with splashes,
//! lone drops and a settling pool, like the paper's Figure 8.

use glam::Vec3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::{Scene, SceneError};
use crate::kernels::{poly6, spiky_gradient};
use crate::neighbours::{CellGrid, Neighbourhoods};
use crate::particles::ParticleSet;

/// Parameters of the column simulation. Lengths in metres, times in seconds, y is up.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ColumnParams {
    /// Particle spacing of the initial lattice (the data in `../shared/data` uses 0.05; the
    /// column is smaller to keep 3,000 particles in a meaningful tank).
    pub spacing: f32,
    /// Column size in particles along x, y (up) and z.
    pub column: [u32; 3],
    /// Tank size; the column stands in the corner at the origin.
    pub tank: Vec3,
    /// Output frames per second.
    pub frame_rate: f32,
    /// Solver substeps per frame.
    pub substeps: u32,
    /// Constraint iterations per substep.
    pub iterations: u32,
    /// XSPH viscosity, as a fraction of the way to the kernel-weighted mean velocity.
    pub viscosity: f32,
    /// Seed of the initial 1 % jitter that breaks the lattice's symmetry.
    pub seed: u64,
}

impl ColumnParams {
    /// A frame in the middle of the first splash against the far walls.
    pub const SPLASH_FRAME: usize = 14;
    /// A frame of the initial block, before it has moved much.
    pub const INITIAL_FRAME: usize = 1;
    /// A frame of the nearly settled pool.
    pub const EQUILIBRIUM_FRAME: usize = 150;
    /// The last frame the simulation is run to (five and a half minutes at 30 frames a
    /// second): later frames are refused rather than simulated for hours.
    pub const LAST_FRAME: usize = 10_000;

    /// Refuses a frame past [`Self::LAST_FRAME`].
    pub fn check_frame(frame: usize) -> Result<(), SceneError> {
        if frame > Self::LAST_FRAME {
            return Err(SceneError::FrameTooLate {
                frame,
                last: Self::LAST_FRAME,
            });
        }
        Ok(())
    }
}

impl Default for ColumnParams {
    /// A 12 x 20 x 12 column (2,880 particles) of spacing 2.5 cm in a 0.45 x 0.8 x 0.45 m tank.
    fn default() -> Self {
        Self {
            spacing: 0.025,
            column: [12, 20, 12],
            tank: Vec3::new(0.45, 0.8, 0.45),
            frame_rate: 30.0,
            substeps: 6,
            iterations: 4,
            viscosity: 0.2,
            seed: 3,
        }
    }
}

/// The running simulation.
#[derive(Clone, Debug)]
pub struct ColumnSim {
    params: ColumnParams,
    particles: ParticleSet,
    frame: usize,
    support: f32,
    rest_density: f32,
    relaxation: f32,
}

const GRAVITY: Vec3 = Vec3::new(0.0, -9.81, 0.0);

impl ColumnSim {
    /// Sets up frame 0: the column at rest.
    pub fn new(params: ColumnParams) -> Result<Self, SceneError> {
        let s = params.spacing;
        let [nx, ny, nz] = params.column;
        let count = nx as u64 * ny as u64 * nz as u64;
        let bad = |name, reason: String| Err(SceneError::InvalidParameter { name, reason });
        if !(s.is_finite() && s > 0.0) {
            return bad("spacing", format!("must be finite and > 0, got {s}"));
        }
        if count == 0 || count > 2_000_000 {
            return bad("column", format!("{count} particles: need 1 to 2 million"));
        }
        let size = Vec3::new(nx as f32, ny as f32, nz as f32) * s;
        if !params.tank.is_finite() || params.tank.cmplt(size).any() {
            return bad(
                "tank",
                format!("{} does not hold the column {size}", params.tank),
            );
        }
        if !(params.frame_rate.is_finite() && params.frame_rate > 0.0) || params.substeps == 0 {
            return bad("frame_rate", "frame rate and substeps must be > 0".into());
        }
        let mut rng = ChaCha8Rng::seed_from_u64(params.seed);
        let mut positions = Vec::with_capacity(count as usize);
        for k in 0..nz {
            for j in 0..ny {
                for i in 0..nx {
                    let jitter = Vec3::new(rng.random(), rng.random(), rng.random()) - 0.5;
                    positions
                        .push((Vec3::new(i as f32, j as f32, k as f32) + 0.5 + jitter * 0.02) * s);
                }
            }
        }
        let n = positions.len();
        let mut particles = ParticleSet::from_positions(positions);
        particles.ids = Some((0..n as u32).collect());
        particles.masses = Some(vec![1.0; n]);
        particles.velocities = Some(vec![Vec3::ZERO; n]);
        let support = 2.0 * s;
        // Rest density and the constraint-gradient norm of a particle inside a perfect lattice,
        // so that the initial column is exactly at rest and the relaxation is scale-free.
        let mut rest_density = 0.0;
        let mut grad_sum = Vec3::ZERO;
        let mut grad_sq = 0.0;
        for k in -3..=3 {
            for j in -3..=3 {
                for i in -3..=3 {
                    let r = Vec3::new(i as f32, j as f32, k as f32) * s;
                    rest_density += poly6(r.length_squared(), support);
                    let g = spiky_gradient(r, support);
                    grad_sum += g;
                    grad_sq += g.length_squared();
                }
            }
        }
        let relaxation =
            0.01 * (grad_sum.length_squared() + grad_sq) / (rest_density * rest_density);
        Ok(Self {
            params,
            particles,
            frame: 0,
            support,
            rest_density,
            relaxation,
        })
    }

    /// The current frame number.
    #[must_use]
    pub fn frame(&self) -> usize {
        self.frame
    }

    /// The current particles (positions, ids, masses, velocities).
    #[must_use]
    pub fn particles(&self) -> &ParticleSet {
        &self.particles
    }

    /// The SPH support radius (twice the spacing).
    #[must_use]
    pub fn support_radius(&self) -> f32 {
        self.support
    }

    /// The parameters.
    #[must_use]
    pub fn params(&self) -> &ColumnParams {
        &self.params
    }

    /// The current frame as a [`Scene`].
    #[must_use]
    pub fn scene(&self) -> Scene {
        Scene {
            name: "column",
            particles: self.particles.clone(),
            spacing: self.params.spacing,
            support_radius: self.support,
            shape: None,
        }
    }

    /// Runs until frame `frame` (no-op when already there or past it).
    pub fn advance_to(&mut self, frame: usize) {
        while self.frame < frame {
            self.step_frame();
        }
    }

    /// Advances one output frame.
    pub fn step_frame(&mut self) {
        let dt = 1.0 / (self.params.frame_rate * self.params.substeps as f32);
        for _ in 0..self.params.substeps {
            self.substep(dt);
        }
        self.frame += 1;
    }

    fn clamp(&self, p: Vec3) -> Vec3 {
        let margin = 0.5 * self.params.spacing;
        p.clamp(Vec3::splat(margin), self.params.tank - margin)
    }

    fn substep(&mut self, dt: f32) {
        let h = self.support;
        let rho0 = self.rest_density;
        let x = &self.particles.positions;
        let v = self
            .particles
            .velocities
            .as_ref()
            .expect("the simulation keeps velocities");
        let mut p: Vec<Vec3> = x
            .par_iter()
            .zip(v.par_iter())
            .map(|(&x, &v)| self.clamp(x + (v + GRAVITY * dt) * dt))
            .collect();
        // The cell grid's build cannot fail here: positions are clamped into the tank.
        let nb = CellGrid::new(&p, h)
            .map(|g| g.all_neighbours())
            .unwrap_or_else(|_| Neighbourhoods::from_lists(h, &vec![Vec::new(); p.len()]));
        for _ in 0..self.params.iterations {
            let lambda: Vec<f32> = (0..p.len())
                .into_par_iter()
                .map(|i| {
                    let mut rho = poly6(0.0, h);
                    let mut grad_i = Vec3::ZERO;
                    let mut sum_sq = 0.0;
                    for &j in nb.of(i) {
                        let r = p[i] - p[j as usize];
                        rho += poly6(r.length_squared(), h);
                        let g = spiky_gradient(r, h) / rho0;
                        grad_i += g;
                        sum_sq += g.length_squared();
                    }
                    let c = (rho / rho0 - 1.0).max(0.0);
                    -c / (grad_i.length_squared() + sum_sq + self.relaxation)
                })
                .collect();
            p = (0..p.len())
                .into_par_iter()
                .map(|i| {
                    let mut dp = Vec3::ZERO;
                    for &j in nb.of(i) {
                        let j = j as usize;
                        dp += spiky_gradient(p[i] - p[j], h) * (lambda[i] + lambda[j]);
                    }
                    self.clamp(p[i] + dp / rho0)
                })
                .collect();
        }
        let velocity: Vec<Vec3> = x
            .par_iter()
            .zip(p.par_iter())
            .map(|(&x, &p)| (p - x) / dt)
            .collect();
        let c = self.params.viscosity;
        let smoothed: Vec<Vec3> = (0..p.len())
            .into_par_iter()
            .map(|i| {
                let mut sum_w = poly6(0.0, h);
                let mut mean = velocity[i] * sum_w;
                for &j in nb.of(i) {
                    let w = poly6(p[i].distance_squared(p[j as usize]), h);
                    mean += velocity[j as usize] * w;
                    sum_w += w;
                }
                velocity[i] + (mean / sum_w - velocity[i]) * c
            })
            .collect();
        self.particles.positions = p;
        self.particles.velocities = Some(smoothed);
    }
}

/// The pool scene of the column's tank (the main job's): an open box with a tiled floor,
/// sunlight from above and the side, water whose extinction is strong enough to tint a 0.45 m
/// tank, and a fixed camera looking into the tank.
#[must_use]
pub fn column_pool(tank: Vec3) -> crate::optics::OpticsScene {
    use crate::optics::{OpticsScene, ReceiverKind};
    let mut s = OpticsScene::default();
    s.receiver.kind = ReceiverKind::OpenBox;
    s.receiver.min = Vec3::new(-0.005, -0.005, -0.005);
    s.receiver.max = Vec3::new(tank.x + 0.005, tank.y * 0.45, tank.z + 0.005);
    s.receiver.checker = 0.05;
    s.light.direction = Vec3::new(0.35, 1.0, 0.25);
    s.water.extinction = Vec3::new(3.0, 0.9, 0.5);
    s.camera = Some(crate::splat::Camera {
        eye: Vec3::new(tank.x * 1.9, tank.y * 1.25, tank.z * 2.3),
        target: Vec3::new(tank.x * 0.45, tank.y * 0.12, tank.z * 0.45),
        fov_y_degrees: 40.0,
        near: 0.05,
        far: 5.0,
        ..Default::default()
    });
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn column_falls_spreads_and_stays_in_the_tank() {
        let params = ColumnParams::default();
        let mut sim = ColumnSim::new(params).unwrap();
        let n = sim.particles().len();
        assert_eq!(n, 2880);
        let mean = |s: &ColumnSim| s.particles().positions.iter().sum::<Vec3>() / n as f32;
        let start = mean(&sim);
        sim.advance_to(20);
        let (lo, hi) = sim.particles().bounds().unwrap();
        assert!(lo.cmpge(Vec3::ZERO).all() && hi.cmple(params.tank).all());
        // collapsed: the centre of mass is lower and has moved away from the corner
        let now = mean(&sim);
        assert!(now.y < start.y - 0.05, "{now} vs {start}");
        assert!(
            now.x > start.x + 0.05 && now.z > start.z + 0.05,
            "{now} vs {start}"
        );
        assert!(sim.particles().validate().is_ok());
    }

    #[test]
    fn frames_are_deterministic() {
        let mut a = ColumnSim::new(ColumnParams::default()).unwrap();
        let mut b = ColumnSim::new(ColumnParams::default()).unwrap();
        a.advance_to(3);
        b.advance_to(3);
        assert_eq!(a.particles(), b.particles());
    }
}
