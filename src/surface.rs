//! Stage 1: surface particle detection and normals (Solenthaler et al. 2007, §3.1).
//!
//! A particle's *centre-of-mass offset* is the distance from the particle to the mass-weighted
//! centre of mass of its neighbourhood within the support radius `r` (eq. 2):
//!
//! ```text
//! d_i = | sum_j (x_i - x_j) m_j / sum_j m_j |      j over the neighbourhood, i included
//! ```
//!
//! Inside the fluid the neighbourhood surrounds the particle and `d_i` is close to zero; at the
//! surface half the neighbourhood is missing and `d_i` approaches `3r/8` (the centroid of a
//! half-ball). The paper includes the particle itself in its SPH sums; it adds nothing to the
//! numerator but keeps the denominator non-zero.
//!
//! Thresholds are fractions of `r`. A particle that was not surface in the previous frame becomes
//! surface when `d_i > high_threshold * r`; a surface particle stays surface while
//! `d_i > low_threshold * r` (hysteresis). The state follows particles by their ids across frames
//! inside a [`SurfaceDetector`]. Particles with an empty neighbourhood are
//! [`ParticleClass::Isolated`].

use std::collections::HashSet;
use std::time::Instant;

use glam::{Mat3, Vec3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::kernels::{poly6, poly6_gradient};
use crate::linalg::symmetric_eigen;
use crate::neighbours::Neighbourhoods;
use crate::particles::ParticleView;

/// How surface normals are computed.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum NormalMethod {
    /// Weighted covariance analysis of the neighbourhood (the paper's \[Paj03\]); the normal is the
    /// eigenvector of the smallest eigenvalue. Higher quality, slightly more expensive.
    #[default]
    Covariance,
    /// Negative gradient of the SPH colour field `c(x) = sum_j m_j / rho_j W(x - x_j)`
    /// (Müller et al. 2003), with the poly6 kernel.
    ColourField,
}

impl NormalMethod {
    /// Every method, in the order of the documentation.
    pub const ALL: [Self; 2] = [Self::Covariance, Self::ColourField];

    /// The name used in files and on the command line.
    #[must_use]
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Covariance => "covariance",
            Self::ColourField => "colour-field",
        }
    }
}

/// Which particles a frame's surface is made of.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SurfaceMethod {
    /// Solenthaler et al. 2007 §3.1: the centre-of-mass offset with two thresholds and
    /// hysteresis across frames, normals of [`NormalMethod`]. The chain's design.
    #[default]
    CentreOfMass,
    /// The narrow band of the Layered Neighborhood Method (Oliveira and Paiva, Algorithm 1;
    /// [`crate::lnm`]): band particles are surface (isolated where the centre-of-mass detection
    /// found no neighbour), the rest interior; normals from the voxels
    /// ([`crate::lnm::NarrowBand::ring_normals`]); no hysteresis (`flips` is 0). The pipeline
    /// runs the centre-of-mass detection too, for the isolated particles and the offsets.
    Lnm,
}

impl SurfaceMethod {
    /// Every method, in the order of the documentation.
    pub const ALL: [Self; 2] = [Self::CentreOfMass, Self::Lnm];

    /// The name used in files and on the command line.
    #[must_use]
    pub fn as_str(self) -> &'static str {
        match self {
            Self::CentreOfMass => "centre-of-mass",
            Self::Lnm => "lnm",
        }
    }
}

/// Parameters of surface detection.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SurfaceParams {
    /// A particle not yet at the surface becomes surface when its centre-of-mass offset exceeds
    /// this fraction of the support radius. Default 0.14, the middle of the range 0.11-0.19
    /// where both jittered test solids (block, sphere; 10 % jitter, r = 2 spacings) keep recall
    /// >= 99.7 % and precision >= 95 % (`examples/threshold_sweep.rs`, docs/design.md).
    pub high_threshold: f32,
    /// A surface particle stops being surface only when its offset falls below this fraction of
    /// the support radius. Default 0.09: on the settling `column` pool (frames 101-200) it cuts
    /// flips per frame from 1.21 with a single threshold to 0.15 (`tests/surface.rs`,
    /// `examples/threshold_sweep.rs`); lower values gain little more and keep particles that
    /// sank marked as surface longer.
    /// Set equal to `high_threshold` to disable hysteresis.
    pub low_threshold: f32,
    /// How normals of surface particles are computed.
    pub normals: NormalMethod,
    /// Which particles are the surface: the centre-of-mass detection (default) or the LNM
    /// narrow band. [`SurfaceDetector`] itself always runs the centre-of-mass detection; the
    /// [`crate::pipeline::Pipeline`] turns it into the band with [`crate::lnm::band_surface`].
    pub method: SurfaceMethod,
}

impl Default for SurfaceParams {
    fn default() -> Self {
        Self {
            high_threshold: 0.14,
            low_threshold: 0.09,
            normals: NormalMethod::default(),
            method: SurfaceMethod::default(),
        }
    }
}

impl SurfaceParams {
    /// Checks `0 < low <= high`, all finite.
    pub fn validate(&self) -> Result<(), SurfaceError> {
        let (low, high) = (self.low_threshold, self.high_threshold);
        if !(low.is_finite() && high.is_finite() && low > 0.0 && low <= high) {
            return Err(SurfaceError::InvalidThresholds { low, high });
        }
        Ok(())
    }
}

/// Errors of surface detection.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SurfaceError {
    /// Thresholds must satisfy `0 < low <= high`.
    #[error("surface thresholds must satisfy 0 < low <= high, got low = {low}, high = {high}")]
    InvalidThresholds { low: f32, high: f32 },
    /// The neighbourhoods were built for another particle set.
    #[error("neighbourhoods cover {neighbourhoods} particles but the set has {particles}")]
    SizeMismatch {
        particles: usize,
        neighbourhoods: usize,
    },
    /// An attribute's length does not match the particle count.
    #[error("invalid particle set: {0}")]
    Particles(#[from] crate::particles::ParticleSetError),
}

/// Class of a particle after detection.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[repr(u8)]
pub enum ParticleClass {
    /// Inside the fluid.
    Interior = 0,
    /// On the free surface.
    Surface = 1,
    /// No neighbour within the support radius (a lone drop).
    Isolated = 2,
}

/// Counts of particles per class.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct ClassCounts {
    pub interior: usize,
    pub surface: usize,
    pub isolated: usize,
}

/// Wall-clock time spent in each phase of [`SurfaceDetector::detect`], in milliseconds.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct SurfaceTimings {
    pub classify_ms: f64,
    pub normals_ms: f64,
}

/// Result of surface detection on one frame.
#[derive(Clone, Debug, Default)]
pub struct Surface {
    /// Class of every particle.
    pub classes: Vec<ParticleClass>,
    /// Centre-of-mass offset `d_i / r` of every particle (eq. 2), 0 for isolated ones.
    pub offsets: Vec<f32>,
    /// Outward unit normal of every surface particle; zero for interior and isolated particles.
    pub normals: Vec<Vec3>,
    /// Particles (present in the previous frame, matched by id) whose surface state changed
    /// since the previous frame; 0 on a detector's first frame.
    pub flips: usize,
    /// Time per phase.
    pub timings: SurfaceTimings,
}

impl Surface {
    /// Particles per class.
    #[must_use]
    pub fn counts(&self) -> ClassCounts {
        let mut c = ClassCounts::default();
        for class in &self.classes {
            match class {
                ParticleClass::Interior => c.interior += 1,
                ParticleClass::Surface => c.surface += 1,
                ParticleClass::Isolated => c.isolated += 1,
            }
        }
        c
    }

    /// Indices of the particles of one class.
    #[must_use]
    pub fn indices_of(&self, class: ParticleClass) -> Vec<usize> {
        (0..self.classes.len())
            .filter(|&i| self.classes[i] == class)
            .collect()
    }
}

/// A set of particle ids: a bitset for ids not much larger than the particle count, a hash set
/// for sparse id ranges.
#[derive(Clone, Debug)]
enum IdSet {
    Dense(Vec<u64>),
    Sparse(HashSet<u32>),
}

impl IdSet {
    fn contains(&self, id: u32) -> bool {
        match self {
            Self::Dense(bits) => bits
                .get(id as usize / 64)
                .is_some_and(|w| w >> (id % 64) & 1 == 1),
            Self::Sparse(set) => set.contains(&id),
        }
    }

    /// The ids of the particles for which `keep(i)` holds.
    fn collect(particles: ParticleView<'_>, keep: impl Fn(usize) -> bool) -> Self {
        let n = particles.len();
        let max_id = (0..n).map(|i| particles.id(i)).max().unwrap_or(0) as usize;
        let kept = (0..n).filter(|&i| keep(i)).map(|i| particles.id(i));
        if max_id <= 64 * n + (1 << 20) {
            let mut bits = vec![0u64; max_id / 64 + 1];
            for id in kept {
                bits[id as usize / 64] |= 1 << (id % 64);
            }
            Self::Dense(bits)
        } else {
            Self::Sparse(kept.collect())
        }
    }
}

/// What a detector remembers of the previous frame.
#[derive(Clone, Debug)]
struct History {
    /// ids that were surface or isolated
    surface: IdSet,
    /// ids that were present
    present: IdSet,
}

/// Surface detection with hysteresis across the frames of one simulation.
///
/// Keep one detector per simulation and call [`SurfaceDetector::detect`] on its frames in order.
/// Particles are matched between frames by their ids ([`crate::ParticleSet::ids`]) when there are, otherwise
/// by index (correct only when the simulation keeps its particle order).
#[derive(Clone, Debug)]
pub struct SurfaceDetector {
    params: SurfaceParams,
    previous: Option<History>,
}

impl SurfaceDetector {
    /// A detector with no history.
    pub fn new(params: SurfaceParams) -> Result<Self, SurfaceError> {
        params.validate()?;
        Ok(Self {
            params,
            previous: None,
        })
    }

    /// The parameters in use.
    #[must_use]
    pub fn params(&self) -> &SurfaceParams {
        &self.params
    }

    /// Forgets the history (the next frame is treated as a first frame).
    pub fn reset(&mut self) {
        self.previous = None;
    }

    /// Classifies the particles of the next frame and computes normals of the surface ones.
    /// `particles`: a `&ParticleSet` or a [`ParticleView`] of slices held elsewhere.
    pub fn detect<'a>(
        &mut self,
        particles: impl Into<ParticleView<'a>>,
        neighbourhoods: &Neighbourhoods,
    ) -> Result<Surface, SurfaceError> {
        let particles = particles.into();
        check_sizes(particles, neighbourhoods)?;
        let start = Instant::now();
        let r = neighbourhoods.radius();
        let offset_vectors = com_offsets(particles, neighbourhoods);
        let (high, low) = (self.params.high_threshold, self.params.low_threshold);
        let previous = self.previous.as_ref();
        let classes: Vec<ParticleClass> = (0..particles.len())
            .into_par_iter()
            .map(|i| {
                if neighbourhoods.of(i).is_empty() {
                    return ParticleClass::Isolated;
                }
                let was_surface = previous.is_some_and(|h| h.surface.contains(particles.id(i)));
                let threshold = if was_surface { low } else { high };
                if offset_vectors[i].length() > threshold * r {
                    ParticleClass::Surface
                } else {
                    ParticleClass::Interior
                }
            })
            .collect();
        let flips = match previous {
            None => 0,
            Some(h) => (0..particles.len())
                .into_par_iter()
                .filter(|&i| {
                    let id = particles.id(i);
                    h.present.contains(id)
                        && h.surface.contains(id) != (classes[i] != ParticleClass::Interior)
                })
                .count(),
        };
        self.previous = Some(History {
            surface: IdSet::collect(particles, |i| classes[i] != ParticleClass::Interior),
            present: IdSet::collect(particles, |_| true),
        });
        let classify_ms = start.elapsed().as_secs_f64() * 1e3;

        let start = Instant::now();
        let normals = surface_normals(
            particles,
            neighbourhoods,
            &classes,
            &offset_vectors,
            self.params.normals,
        );
        let normals_ms = start.elapsed().as_secs_f64() * 1e3;
        Ok(Surface {
            offsets: offset_vectors.iter().map(|d| d.length() / r).collect(),
            classes,
            normals,
            flips,
            timings: SurfaceTimings {
                classify_ms,
                normals_ms,
            },
        })
    }
}

/// Detects the surface of a single frame (no history: every particle uses the high threshold).
pub fn detect_surface<'a>(
    particles: impl Into<ParticleView<'a>>,
    neighbourhoods: &Neighbourhoods,
    params: &SurfaceParams,
) -> Result<Surface, SurfaceError> {
    SurfaceDetector::new(*params)?.detect(particles, neighbourhoods)
}

fn check_sizes(
    particles: ParticleView<'_>,
    neighbourhoods: &Neighbourhoods,
) -> Result<(), SurfaceError> {
    if particles.len() != neighbourhoods.len() {
        return Err(SurfaceError::SizeMismatch {
            particles: particles.len(),
            neighbourhoods: neighbourhoods.len(),
        });
    }
    let n = particles.len();
    let bad = |name: &str, len: Option<usize>| {
        len.filter(|&l| l != n)
            .map(|found| crate::particles::ParticleSetError::LengthMismatch {
                attribute: name.to_owned(),
                expected: n,
                found,
            })
    };
    if let Some(e) = bad("id", particles.ids.map(<[u32]>::len))
        .or_else(|| bad("mass", particles.masses.map(<[f32]>::len)))
    {
        return Err(e.into());
    }
    Ok(())
}

/// The vector `x_i - cm_i` of eq. 2 for every particle (zero for isolated particles).
#[must_use]
pub fn com_offsets<'a>(
    particles: impl Into<ParticleView<'a>>,
    neighbourhoods: &Neighbourhoods,
) -> Vec<Vec3> {
    let particles = particles.into();
    let x = particles.positions;
    (0..particles.len())
        .into_par_iter()
        .map(|i| {
            let mut sum_m = particles.mass(i);
            let mut acc = Vec3::ZERO;
            for &j in neighbourhoods.of(i) {
                let m = particles.mass(j as usize);
                acc += (x[i] - x[j as usize]) * m;
                sum_m += m;
            }
            acc / sum_m
        })
        .collect()
}

/// Outward unit normals of the particles classed as surface; zero elsewhere.
///
/// `offsets` are the vectors of [`com_offsets`]; they point out of the fluid and orient the
/// covariance normal, whose sign the eigen-decomposition leaves open.
#[must_use]
pub fn surface_normals<'a>(
    particles: impl Into<ParticleView<'a>>,
    neighbourhoods: &Neighbourhoods,
    classes: &[ParticleClass],
    offsets: &[Vec3],
    method: NormalMethod,
) -> Vec<Vec3> {
    let particles = particles.into();
    let r = neighbourhoods.radius();
    let x = particles.positions;
    let densities = match method {
        NormalMethod::ColourField => Some(densities(particles, neighbourhoods)),
        NormalMethod::Covariance => None,
    };
    (0..particles.len())
        .into_par_iter()
        .map(|i| {
            if classes[i] != ParticleClass::Surface {
                return Vec3::ZERO;
            }
            let nb = neighbourhoods.of(i);
            let n = match &densities {
                Some(rho) => {
                    // n = -grad c (Müller et al. 2003): the colour field grows into the fluid.
                    let mut grad = Vec3::ZERO;
                    for &j in nb {
                        let j = j as usize;
                        grad += poly6_gradient(x[i] - x[j], r) * (particles.mass(j) / rho[j]);
                    }
                    -grad
                }
                None => covariance_normal(particles, i, nb, r),
            };
            let n = n.normalize_or_zero();
            if n.dot(offsets[i]) < 0.0 { -n } else { n }
        })
        .collect()
}

/// SPH density `rho_i = sum_j m_j W_poly6(x_i - x_j)` over the neighbourhood and the particle.
#[must_use]
pub fn densities<'a>(
    particles: impl Into<ParticleView<'a>>,
    neighbourhoods: &Neighbourhoods,
) -> Vec<f32> {
    let particles = particles.into();
    let r = neighbourhoods.radius();
    let x = particles.positions;
    (0..particles.len())
        .into_par_iter()
        .map(|i| {
            let mut rho = particles.mass(i) * poly6(0.0, r);
            for &j in neighbourhoods.of(i) {
                let j = j as usize;
                rho += particles.mass(j) * poly6(x[i].distance_squared(x[j]), r);
            }
            rho
        })
        .collect()
}

/// Smallest-eigenvalue eigenvector of the kernel-weighted covariance of the neighbourhood
/// (particle included) about its weighted mean. The weight `m_j (1 - d^2/r^2)^3` favours close
/// neighbours, which follow the local tangent plane best. Sign unresolved.
fn covariance_normal(particles: ParticleView<'_>, i: usize, nb: &[u32], r: f32) -> Vec3 {
    let x = particles.positions;
    let weight = |j: usize| {
        let q = 1.0 - x[i].distance_squared(x[j]) / (r * r);
        particles.mass(j) * (q * q * q).max(0.0)
    };
    let all = || std::iter::once(i).chain(nb.iter().map(|&j| j as usize));
    let mut sum_w = 0.0;
    let mut mean = Vec3::ZERO;
    for j in all() {
        let w = weight(j);
        sum_w += w;
        // relative to x_i to keep precision for large coordinates
        mean += (x[j] - x[i]) * w;
    }
    mean /= sum_w;
    let mut cov = Mat3::ZERO;
    for j in all() {
        let d = x[j] - x[i] - mean;
        let w = weight(j);
        cov += Mat3::from_cols(d * d.x, d * d.y, d * d.z) * w;
    }
    let (_, vectors) = symmetric_eigen(cov);
    vectors[0]
}

/// The straightforward single-threaded detection that benchmarks and tests compare against:
/// one frame, no history, neighbourhoods as one `Vec` per particle, covariance normals.
/// Returns the classes and normals (zero for non-surface particles).
#[must_use]
pub fn detect_reference<'a>(
    particles: impl Into<ParticleView<'a>>,
    neighbours: &[Vec<u32>],
    radius: f32,
    params: &SurfaceParams,
) -> (Vec<ParticleClass>, Vec<Vec3>) {
    let particles = particles.into();
    let x = particles.positions;
    let mut classes = Vec::with_capacity(x.len());
    let mut normals = Vec::with_capacity(x.len());
    for i in 0..x.len() {
        let list = &neighbours[i];
        if list.is_empty() {
            classes.push(ParticleClass::Isolated);
            normals.push(Vec3::ZERO);
            continue;
        }
        let mut sum_m = particles.mass(i);
        let mut acc = Vec3::ZERO;
        for &j in list {
            let m = particles.mass(j as usize);
            acc += (x[i] - x[j as usize]) * m;
            sum_m += m;
        }
        let offset = acc / sum_m;
        if offset.length() > params.high_threshold * radius {
            classes.push(ParticleClass::Surface);
            let n = covariance_normal(particles, i, list, radius).normalize_or_zero();
            normals.push(if n.dot(offset) < 0.0 { -n } else { n });
        } else {
            classes.push(ParticleClass::Interior);
            normals.push(Vec3::ZERO);
        }
    }
    (classes, normals)
}
