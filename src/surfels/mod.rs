//! Stage 3, second half: sampling the iso-surface of the density grid into surfels
//! (Iwasaki et al., §4.3), on the CPU ([`cpu`]) and on the GPU ([`gpu`], issue 37), tested
//! against each other.
//!
//! Surfels are placed where the density crosses the iso-value along the grid's x, y and z edges
//! (linear interpolation), then projected onto the exact iso-surface of the particles' density by
//! Newton steps along the gradient (the grid alone is only accurate to its interpolation). The
//! normal is the negative density gradient (pointing out of the fluid). The radius is the grid
//! spacing: every point of the iso-surface inside a grid cube lies within about 0.71 spacing of a
//! crossing on the cube's edges (a plane through the cube's centre, measured from the centre to the
//! edge midpoints) and the projection moves points by a fraction of that, so one spacing leaves no
//! gap (tested on a dense sample of the surface). This replaces the paper's after-the-fact gap
//! filling, which the edge sampling makes unnecessary.
//!
//! Extraction reads the grid plane by plane ([`SurfelExtractor::push_plane`]), so it can run on
//! the slabs that [`crate::density::splat_slabs`] streams, never holding the whole grid.

pub mod cpu;
pub mod gpu;

pub use cpu::{
    ExactDensity, SurfelExtractor, extract, extract_points, extract_sparse, radius_groups,
};

use glam::Vec3;
use serde::{Deserialize, Serialize};

use crate::density::{DensityError, Kernel};

/// A Newton step shorter than this fraction of a cell ends the projection
/// ([`SurfelExtractor::finish`]): Newton's steps shrink quadratically near the surface (the
/// next about this squared over the kernel's length scale), so the point then lies within about
/// 1e-4 cells of the iso-surface. Measured on the real files' chain (tests/surfels.rs): 1.5e-5
/// cells off on average; the density evaluations per surfel (the chain of the real files,
/// tests/surfels.rs) 3.56 -> 2.60 on the dam break and 2.50 -> 1.76 on the double dam break
/// against 1e-4 (the evaluation that only confirmed the convergence is saved), the dam break's
/// surfels 14-16 % faster.
pub const CONVERGED: f32 = 1e-2;

/// Parameters of surfel extraction.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SurfelParams {
    /// Iso-value as a fraction of one particle's peak density `F(0, h)`. Default 0.75, so that a
    /// lone drop still shows (as a sphere of radius about 0.3 h). Measured on a jittered sphere
    /// of particles with h = 2 spacings, the surface then lies 0.7 spacing outside the boundary
    /// the particles sample (1.2 outside the outermost centres); 3.0 puts it on that boundary but
    /// makes every lone particle vanish (a single particle never exceeds 1.0).
    pub iso_fraction: f32,
    /// The most Newton steps projecting a surfel onto the exact iso-surface (it stops earlier
    /// once a step is under [`CONVERGED`] cells: 1.8-2.6 density evaluations a surfel on the
    /// real files' chain). Default 16:
    /// with 4, 11 of the dam break's 283,114 chain surfels and 9 of the double dam break's
    /// 122,208 stopped 0.4-0.6 cells off the surface (steps capped at half a cell, where the
    /// density's gradient is weak); with 16 every one lies within 6.5e-4 cells
    /// (tests/surfels.rs), at no measurable cost (the others stop as before).
    pub newton_steps: u32,
}

impl Default for SurfelParams {
    fn default() -> Self {
        Self {
            iso_fraction: 0.75,
            newton_steps: 16,
        }
    }
}

/// Errors of surfel extraction.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SurfelError {
    /// A parameter is out of range.
    #[error("invalid surfel parameter `{name}`: {reason}")]
    InvalidParameter { name: &'static str, reason: String },
    /// The neighbour grid of the particles could not be built.
    #[error(transparent)]
    Neighbours(#[from] crate::neighbours::NeighbourError),
    /// The points' radii or positions are unusable.
    #[error(transparent)]
    Density(#[from] DensityError),
}

/// Surfels: oriented disks on the iso-surface.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Surfels {
    /// Centres, on the iso-surface.
    pub positions: Vec<Vec3>,
    /// Unit normals, out of the fluid.
    pub normals: Vec<Vec3>,
    /// Disk radii.
    pub radii: Vec<f32>,
    /// The iso-value used.
    pub iso: f32,
}

impl Surfels {
    /// Number of surfels.
    #[must_use]
    pub fn len(&self) -> usize {
        self.positions.len()
    }

    /// True when there is none.
    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.positions.is_empty()
    }

    /// As a particle set with normals and a `radius` attribute.
    #[must_use]
    pub fn to_particle_set(&self) -> crate::ParticleSet {
        let mut set = crate::ParticleSet::from_positions(self.positions.clone());
        set.normals = Some(self.normals.clone());
        set.extra.push(crate::Attribute::scalar(
            "radius",
            crate::ScalarKind::F32,
            self.radii.iter().map(|&r| r as f64).collect(),
        ));
        set
    }
}

pub(crate) fn iso_of(h: f32, kernel: Kernel, params: &SurfelParams) -> Result<f32, SurfelError> {
    if !(params.iso_fraction.is_finite() && params.iso_fraction > 0.0) {
        return Err(SurfelError::InvalidParameter {
            name: "iso_fraction",
            reason: format!("must be finite and > 0, got {}", params.iso_fraction),
        });
    }
    Ok(params.iso_fraction * kernel.peak(h))
}
