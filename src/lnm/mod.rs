//! The narrow band of the Layered Neighborhood Method (LNM, Oliveira et al., "Narrow-band
//! screen-space fluid rendering", §4.1, Algorithm 1; the paper in
//! `../shared/papers/oliveira-narrow-band-screen-space-fluid-rendering.txt`).
//!
//! Voxels of edge 2h (the paper's h is the smoothing length of a kernel whose support is 2h,
//! so a voxel is one support radius wide: the neighbour-search cell the paper says it reuses)
//! over the domain; a voxel is full when a particle lies in it. Layer 1: the full voxels with
//! an empty voxel in their 1-ring (the 26 voxels sharing a vertex, an edge or a face) or on the
//! domain's border; layer 2: the other full voxels with a layer-1 neighbour holding at most
//! `n_min = 2^dim = 8` particles (a thin layer-1 voxel may leave holes; its inner neighbours
//! fill them). The band is the particles of layers 1 and 2.
//!
//! A compact body is counted in a dense array of the domain's voxels; a spread-out one stores
//! only its full voxels (sorted by key, looked up by hash), so a far-flung splash costs what its
//! particles cost and not the volume of its bounding box (the paper's dense grid is its own
//! future-work note); [`Layout`] says which, and both give the same band bit for bit. The CPU
//! path ([`cpu`]) is parallel over voxels; every voxel's label depends on nothing but its
//! neighbours' counts, so the result does not depend on the thread count. The GPU twin
//! ([`gpu`]) is dense.

use glam::Vec3;
use serde::{Deserialize, Serialize};

pub mod cpu;
pub mod gpu;

pub use cpu::{Layout, narrow_band, narrow_band_in};
pub(crate) use cpu::{dense_index, voxel_at};

/// Errors of the narrow band.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum LnmError {
    /// A parameter is out of range.
    #[error("invalid narrow-band parameter `{name}`: {reason}")]
    InvalidParameter { name: &'static str, reason: String },
    /// A particle position is NaN or infinite.
    #[error("particle {index} has a non-finite position")]
    NonFinite { index: usize },
    /// The particles (or the domain) span more voxels than keys can address.
    #[error(
        "the domain spans {voxels:?} voxels of edge {edge}, more than {max} along an axis; use larger voxels or a smaller domain"
    )]
    TooManyVoxels {
        voxels: [u64; 3],
        edge: f32,
        max: u64,
    },
    /// The GPU path's dense voxel grid would be too large.
    #[error(
        "the GPU narrow band's dense grid would hold {voxels} voxels, more than {max}; use the CPU path (sparse) or larger voxels"
    )]
    DenseTooLarge { voxels: u64, max: u64 },
}

/// Parameters of the narrow band.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LnmParams {
    /// Voxel edge in support radii. Default 1 (the paper's 2h).
    pub voxel_in_radii: f32,
    /// A layer-1 voxel with at most this many particles pulls its full neighbours into layer 2.
    /// Default 8 (the paper's `n_min = 2^dim`).
    pub n_min: u32,
    /// The domain whose border counts as surface (min, max corners); default: the particles'
    /// bounds.
    pub domain: Option<[[f32; 3]; 2]>,
}

impl Default for LnmParams {
    fn default() -> Self {
        Self {
            voxel_in_radii: 1.0,
            n_min: 8,
            domain: None,
        }
    }
}

impl LnmParams {
    /// Checks every parameter.
    pub fn validate(&self) -> Result<(), LnmError> {
        if !(self.voxel_in_radii.is_finite() && self.voxel_in_radii > 0.0) {
            return Err(LnmError::InvalidParameter {
                name: "voxel_in_radii",
                reason: "must be finite and > 0".into(),
            });
        }
        if let Some([lo, hi]) = self.domain {
            let (lo, hi) = (Vec3::from(lo), Vec3::from(hi));
            if !(lo.is_finite() && hi.is_finite() && lo.cmple(hi).all()) {
                return Err(LnmError::InvalidParameter {
                    name: "domain",
                    reason: "needs finite corners, min <= max".into(),
                });
            }
        }
        Ok(())
    }
}

/// A full voxel.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct BandVoxel {
    /// Integer coordinates (voxel units from the domain's minimum corner).
    pub coord: [u32; 3],
    /// Particles inside.
    pub count: u32,
    /// Their centroid (eq. 3's `c_j`).
    pub centroid: Vec3,
    /// 0 interior, 1 first layer, 2 second layer.
    pub label: u8,
}

/// The narrow band of a particle set.
#[derive(Clone, Debug, PartialEq)]
pub struct NarrowBand {
    /// The domain's minimum corner and the voxel edge.
    pub origin: Vec3,
    pub edge: f32,
    /// Voxels along each axis of the domain.
    pub dims: [u32; 3],
    /// The full voxels, in key order (z, then y, then x).
    pub voxels: Vec<BandVoxel>,
    /// Per particle: its voxel's label.
    pub labels: Vec<u8>,
    /// Per particle: the index of its voxel in `voxels`.
    pub voxel_of: Vec<u32>,
}

impl NarrowBand {
    /// Whether particle `i` is in the band (layer 1 or 2).
    #[must_use]
    pub fn contains(&self, i: usize) -> bool {
        self.labels[i] != 0
    }

    /// The band's particles, in index order.
    #[must_use]
    pub fn particles(&self) -> Vec<u32> {
        (0..self.labels.len() as u32)
            .filter(|&i| self.labels[i as usize] != 0)
            .collect()
    }

    /// Particles in the band.
    #[must_use]
    pub fn len(&self) -> usize {
        self.labels.iter().filter(|&&l| l != 0).count()
    }

    /// Whether the band holds no particle.
    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

impl NarrowBand {
    /// The index in `voxels` of the full voxel at `coord`, if any (a binary search: the voxels
    /// are sorted by z, then y, then x).
    #[must_use]
    pub fn voxel_at(&self, coord: [u32; 3]) -> Option<usize> {
        let key = |c: [u32; 3]| (c[2], c[1], c[0]);
        self.voxels
            .binary_search_by_key(&key(coord), |v| key(v.coord))
            .ok()
    }

    /// A normal per band particle from the voxels alone (no neighbour search): away from the
    /// centre of mass about the particle at voxel scale (Solenthaler et al.'s eq. 2 with the
    /// voxels' centroids as masses of their counts), each centroid of the 2-ring (125 voxels)
    /// weighted by `n_j (1 - d^2 / R^2)` for its distance `d < R`, `R` two voxel edges (every
    /// centroid that near lies in the 2-ring, so the neighbourhood is a ball about the particle).
    /// Measured on a particle sphere: with the 1-ring and `R` one edge the particle's own voxel
    /// dominates and half the shell's normals are off by more than 30 degrees; with the 2-ring
    /// every one is within 30 degrees (`tests/lnm.rs`). Where that centre coincides with the
    /// particle, away from its own voxel's centroid; zero for particles off the band.
    #[must_use]
    pub fn ring_normals(&self, positions: &[Vec3]) -> Vec<Vec3> {
        use rayon::prelude::*;
        let r2 = 4.0 * self.edge * self.edge;
        // each band voxel's 2-ring, looked up once for all its particles
        let rings: Vec<Vec<(Vec3, f32)>> = self
            .voxels
            .par_iter()
            .map(|v| {
                if v.label == 0 {
                    return Vec::new();
                }
                (0..125i64)
                    .filter_map(|k| {
                        let d = [k % 5 - 2, (k / 5) % 5 - 2, k / 25 - 2];
                        let c: [i64; 3] = std::array::from_fn(|a| i64::from(v.coord[a]) + d[a]);
                        if c.iter().any(|&x| x < 0 || x > i64::from(u32::MAX)) {
                            return None;
                        }
                        let n = &self.voxels[self.voxel_at(c.map(|x| x as u32))?];
                        Some((n.centroid, n.count as f32))
                    })
                    .collect()
            })
            .collect();
        positions
            .par_iter()
            .enumerate()
            .map(|(i, &x)| {
                if self.labels[i] == 0 {
                    return Vec3::ZERO;
                }
                let v = self.voxel_of[i] as usize;
                let (mut sum, mut n) = (Vec3::ZERO, 0.0f32);
                for &(c, count) in &rings[v] {
                    let w = count * (1.0 - c.distance_squared(x) / r2);
                    if w > 0.0 {
                        sum += w * c;
                        n += w;
                    }
                }
                let own = self.voxels[v].centroid;
                let centre = if n > 0.0 { sum / n } else { own };
                (x - centre)
                    .try_normalize()
                    .or_else(|| (x - own).try_normalize())
                    .unwrap_or(Vec3::Y)
            })
            .collect()
    }
}

/// How the narrow band agrees with a surface detection's classes (the centre-of-mass method of
/// [`crate::surface`]): its surface and isolated particles against the band.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct Agreement {
    pub particles: usize,
    /// Particles in the band.
    pub band: usize,
    /// Surface or isolated particles of the detection.
    pub detected: usize,
    /// Both.
    pub both: usize,
    /// In the band, interior to the detection (the band's second layer and its thick first
    /// layer: the paper's "few false positives").
    pub band_only: usize,
    /// Detected, not in the band (should be none: the band's recall).
    pub detected_only: usize,
    /// `both / detected`: the share of the detected surface the band holds.
    pub recall: f64,
    /// The share of all particles both put on the same side.
    pub agreement: f64,
}

/// The narrow band as a [`crate::surface::Surface`] (the detection method
/// [`crate::surface::SurfaceMethod::Lnm`]): band particles are surface, isolated where `com` (the
/// centre-of-mass detection of the same particles) found them isolated, the rest interior;
/// normals from the voxels ([`NarrowBand::ring_normals`]); the offsets are `com`'s; `flips` 0
/// (the band has no hysteresis).
#[must_use]
pub fn band_surface(
    band: &NarrowBand,
    positions: &[Vec3],
    com: &crate::surface::Surface,
) -> crate::surface::Surface {
    use crate::surface::ParticleClass;
    let classes = band
        .labels
        .iter()
        .zip(&com.classes)
        .map(|(&l, &c)| match (l, c) {
            (0, _) => ParticleClass::Interior,
            (_, ParticleClass::Isolated) => ParticleClass::Isolated,
            _ => ParticleClass::Surface,
        })
        .collect();
    crate::surface::Surface {
        classes,
        offsets: com.offsets.clone(),
        normals: band.ring_normals(positions),
        flips: 0,
        timings: Default::default(),
    }
}

/// The agreement of `band` with `classes` (one per particle).
#[must_use]
pub fn agreement(band: &NarrowBand, classes: &[crate::surface::ParticleClass]) -> Agreement {
    use crate::surface::ParticleClass;
    let mut a = Agreement {
        particles: classes.len().min(band.labels.len()),
        ..Default::default()
    };
    for (&label, &class) in band.labels.iter().zip(classes) {
        let (b, d) = (label != 0, class != ParticleClass::Interior);
        a.band += usize::from(b);
        a.detected += usize::from(d);
        a.both += usize::from(b && d);
        a.band_only += usize::from(b && !d);
        a.detected_only += usize::from(d && !b);
    }
    a.recall = a.both as f64 / a.detected.max(1) as f64;
    a.agreement = (a.particles - a.band_only - a.detected_only) as f64 / a.particles.max(1) as f64;
    a
}
