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
//! Only full voxels are stored (sorted by key, looked up by hash), so a far-flung splash costs
//! what its particles cost and not the volume of its bounding box (the paper's dense grid is
//! its own future-work note). The CPU path ([`cpu`]) is parallel over voxels; every voxel's
//! label depends on nothing but its neighbours' counts, so the result does not depend on the
//! thread count.

use glam::Vec3;
use serde::{Deserialize, Serialize};

pub mod cpu;

pub use cpu::narrow_band;

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
