//! Stage 3, first half: the density grid (Iwasaki et al., §4): parameters, kernels and grid
//! geometry here, the CPU path in [`cpu`] (re-exported), the GPU twin in [`gpu`].
//!
//! Every particle adds a kernel `F(r, h)` to the grid points within its effective radius `h`.
//! The grid is filled slab by slab along z (the paper's planes), each slab from the particles
//! whose z lies within `h` of it (z-clustering, §4.2), so a slab's planes only ever see the
//! particles that can reach them and slabs can be streamed: [`splat_slabs`] hands each slab to a
//! sink in order and keeps only a few in memory.
//!
//! Kernels. Eq. 1 gives Wyvill's kernel as
//! `F = 405 / (748 pi h) (-4/9 a^6 + 17/9 a^4 - 22/9 a^2 + 1)`, `a = r / h`. That constant does not
//! normalise it in 3D (nor in 1D or 2D): the integral of the polynomial over the unit ball is
//! `4 pi (-4/81 + 17/63 - 22/45 + 1/3) = 4 pi * 184/2835`, so the normalised kernel is
//! `F = 2835 / (736 pi h^3) (...)`, which is what [`Kernel::Wyvill`] uses (tested: it integrates to
//! 1). Only the scale differs; iso-values given relative to one particle's peak density are the
//! same either way. [`Kernel::CubicSpline`] is the usual SPH cubic spline with support `h`.
//!
//! Points may carry a radius each ([`Points`]): the design chain's refined surface points beside
//! the interior particles. The GPU twin ([`gpu`]: point-sprites with a per-instance radius, four
//! planes per RGBA pass, or a compute gather) is tested against the CPU path and its naive
//! reference, which are the specification. Surfel extraction is [`crate::surfels`].

pub mod bins;
pub(crate) mod bits;
pub mod cpu;
pub mod gpu;
pub mod sparse;
pub mod sparse_gpu;

use std::f32::consts::PI;

use glam::Vec3;
use serde::{Deserialize, Serialize};

pub use cpu::{
    density_grid, density_naive, points_grid, points_grid_in, points_naive, splat_points_slabs,
    splat_slabs,
};
pub use sparse::{SparseGrid, SparseLayout, points_grid_sparse, sparse_layout};

/// The density function of a particle.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Kernel {
    /// Wyvill and Trotman's soft-object kernel (eq. 1, the paper's), normalised in 3D.
    #[default]
    Wyvill,
    /// The SPH cubic spline (Monaghan) with support radius `h`.
    CubicSpline,
}

impl Kernel {
    /// `F(r, h)`, zero for `r >= h`; integrates to 1 over space.
    #[must_use]
    #[inline]
    pub fn value(self, r: f32, h: f32) -> f32 {
        if r >= h {
            return 0.0;
        }
        let a = r / h;
        match self {
            Self::Wyvill => {
                let a2 = a * a;
                let poly = ((-4.0 / 9.0 * a2 + 17.0 / 9.0) * a2 - 22.0 / 9.0) * a2 + 1.0;
                2835.0 / (736.0 * PI * h * h * h) * poly
            }
            Self::CubicSpline => {
                // support h: q = 2a in the usual form with support 2 h'
                let q = 2.0 * a;
                let sigma = 8.0 / (PI * h * h * h);
                if q < 1.0 {
                    sigma * (1.0 - 1.5 * q * q + 0.75 * q * q * q)
                } else {
                    let t = 2.0 - q;
                    sigma * 0.25 * t * t * t
                }
            }
        }
    }

    /// `F` from the squared distance: Wyvill's kernel is a polynomial in `r^2`, so the hot loop
    /// needs no square root.
    #[must_use]
    #[inline]
    pub fn value_r2(self, r2: f32, h: f32) -> f32 {
        match self {
            Self::Wyvill => {
                // written so that, inlined in a loop, the constants are hoisted and the branch
                // becomes a select (the loop vectorises)
                let a2 = r2 * (1.0 / (h * h));
                let poly = ((-4.0 / 9.0 * a2 + 17.0 / 9.0) * a2 - 22.0 / 9.0) * a2 + 1.0;
                let v = 2835.0 / (736.0 * PI * h * h * h) * poly;
                if a2 < 1.0 { v } else { 0.0 }
            }
            Self::CubicSpline => self.value(r2.sqrt(), h),
        }
    }

    /// The contribution of a point of effective radius `hj` measured against the reference
    /// radius `h`: `(hj / h)^3 F(r, hj)`, given `r^2` (see [`Points`] for why the volume weight).
    /// Equals [`Kernel::value_r2`] bit for bit when `hj == h`. For Wyvill's kernel this is
    /// `F(0, h) poly(r^2 / hj^2)`: the same peak for every point, whatever its radius.
    #[must_use]
    #[inline]
    pub fn weighted_r2(self, r2: f32, hj: f32, h: f32) -> f32 {
        match self {
            Self::Wyvill => {
                let a2 = r2 * (1.0 / (hj * hj));
                let poly = ((-4.0 / 9.0 * a2 + 17.0 / 9.0) * a2 - 22.0 / 9.0) * a2 + 1.0;
                let v = 2835.0 / (736.0 * PI * h * h * h) * poly;
                if a2 < 1.0 { v } else { 0.0 }
            }
            Self::CubicSpline => {
                // `value` with the reference radius's constant: the same operations, so equal to
                // it bit for bit when hj == h
                let r = r2.sqrt();
                if r >= hj {
                    return 0.0;
                }
                let q = 2.0 * (r / hj);
                let sigma = 8.0 / (PI * h * h * h);
                if q < 1.0 {
                    sigma * (1.0 - 1.5 * q * q + 0.75 * q * q * q)
                } else {
                    let t = 2.0 - q;
                    sigma * 0.25 * t * t * t
                }
            }
        }
    }

    /// [`Kernel::weighted_r2`] and its gradient with respect to the evaluation point, given the
    /// offset `d = x - x_j` from the point: `(value, gradient)`. Analytic: for Wyvill's kernel
    /// `dF/dx = F(0, h) poly'(a^2) 2 d / hj^2` with `poly'(s) = -4/3 s^2 + 34/9 s - 22/9`; for the
    /// cubic spline `F(0, h) f'(q) (2 / hj) d / |d|` with `q = 2 |d| / hj`.
    #[must_use]
    #[inline]
    pub fn weighted_and_gradient(self, d: Vec3, hj: f32, h: f32) -> (f32, Vec3) {
        let r2 = d.length_squared();
        match self {
            Self::Wyvill => {
                let inv = 1.0 / (hj * hj);
                let a2 = r2 * inv;
                if a2 >= 1.0 {
                    return (0.0, Vec3::ZERO);
                }
                let c = 2835.0 / (736.0 * PI * h * h * h);
                let poly = ((-4.0 / 9.0 * a2 + 17.0 / 9.0) * a2 - 22.0 / 9.0) * a2 + 1.0;
                let slope = (-4.0 / 3.0 * a2 + 34.0 / 9.0) * a2 - 22.0 / 9.0;
                (c * poly, d * (c * slope * 2.0 * inv))
            }
            Self::CubicSpline => {
                let r = r2.sqrt();
                if r >= hj {
                    return (0.0, Vec3::ZERO);
                }
                let q = 2.0 * (r / hj);
                let sigma = 8.0 / (PI * h * h * h);
                let (v, df) = if q < 1.0 {
                    (
                        sigma * (1.0 - 1.5 * q * q + 0.75 * q * q * q),
                        -3.0 * q + 2.25 * q * q,
                    )
                } else {
                    let t = 2.0 - q;
                    (sigma * 0.25 * t * t * t, -0.75 * t * t)
                };
                let g = if r > 0.0 {
                    d * (sigma * df * 2.0 / (hj * r))
                } else {
                    Vec3::ZERO
                };
                (v, g)
            }
        }
    }

    /// The peak density of one particle, `F(0, h)`.
    #[must_use]
    pub fn peak(self, h: f32) -> f32 {
        self.value(0.0, h)
    }
}

/// Errors of the density grid.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum DensityError {
    /// The effective radius is zero, negative or not finite.
    #[error("the effective radius h must be finite and > 0, got {h}")]
    InvalidRadius { h: f32 },
    /// A grid setting is out of range.
    #[error("invalid grid setting `{name}`: {reason}")]
    InvalidGrid { name: &'static str, reason: String },
    /// No particle to take the grid's bounds from.
    #[error("cannot size a density grid around an empty particle set")]
    Empty,
    /// A position is NaN or infinite.
    #[error("particle {index} has a non-finite position")]
    NonFinite { index: usize },
    /// The grid would need more memory than the limit.
    #[error(
        "a {nx} x {ny} x {nz} grid ({cells} cells) needs {bytes} bytes, over the limit of {limit} bytes; use a coarser resolution or stream it by slabs"
    )]
    TooLarge {
        nx: u64,
        ny: u64,
        nz: u64,
        cells: u128,
        bytes: u128,
        limit: u64,
    },
}

/// The points a density grid is made of: positions, and each point's effective radius.
///
/// With one radius for all (`radii: None`) every point adds `F(r, h)`, as in the paper (eq. 1).
/// With a radius per point (the refined surface points beside the interior particles, §3 of
/// Solenthaler et al. feeding §4 of Iwasaki et al.) the paper is silent on how kernels of
/// different radii combine. A point of radius `hj` adds `(hj / h)^3 F(r, hj)`: the SPH estimate
/// `sum_j V_j W(x - x_j, h_j)` with each point's volume `V_j` proportional to its kernel's
/// volume, `h_j^3`. Why: where points sample a region at spacing `s` with radius `hj = c s`, the
/// sum is a Riemann sum, `sum_j (hj / h)^3 F(r, hj) ~ (hj / h)^3 / s^3 int F dV = c^3 / h^3`
/// (`int F = 1`), the same whatever the spacing; so a fine sheet of refined points and coarse
/// interior particles join without a step in density, and every point has the same peak
/// `F(0, h)`, so an iso-value given as a fraction of that peak means the same for both (tested:
/// a block sampled at two spacings with `hj = 2 s` gives the same interior density). With
/// `hj == h` it is exactly the uniform case, bit for bit.
#[derive(Clone, Copy, Debug)]
pub struct Points<'a> {
    /// Positions.
    pub positions: &'a [Vec3],
    /// Effective radius of each point; `None`: every point has `h`.
    pub radii: Option<&'a [f32]>,
    /// A factor on each point's term (`None`: 1), for the chain's surface points, whose weight
    /// puts the iso-surface at the fluid's boundary (see `crate::pipeline::boundary_weights`).
    pub weights: Option<&'a [f32]>,
    /// The reference radius: every point's without `radii`, and the radius whose peak `F(0, h)`
    /// iso-values are measured against.
    pub h: f32,
}

impl<'a> Points<'a> {
    /// Points of one effective radius `h`.
    #[must_use]
    pub fn uniform(positions: &'a [Vec3], h: f32) -> Self {
        Self {
            positions,
            radii: None,
            weights: None,
            h,
        }
    }

    /// Points with a radius each, measured against the reference radius `h`.
    #[must_use]
    pub fn with_radii(positions: &'a [Vec3], radii: &'a [f32], h: f32) -> Self {
        Self {
            positions,
            radii: Some(radii),
            weights: None,
            h,
        }
    }

    /// These points with a factor on each one's term.
    #[must_use]
    pub fn with_weights(self, weights: &'a [f32]) -> Self {
        Self {
            weights: Some(weights),
            ..self
        }
    }

    /// The factor on point `i`'s term (1 without weights).
    #[must_use]
    #[inline]
    pub fn weight(&self, i: usize) -> f32 {
        match self.weights {
            Some(w) => w[i],
            None => 1.0,
        }
    }

    /// Number of points.
    #[must_use]
    pub fn len(&self) -> usize {
        self.positions.len()
    }

    /// True when there is none.
    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.positions.is_empty()
    }

    /// Effective radius of point `i`.
    #[must_use]
    #[inline]
    pub fn radius(&self, i: usize) -> f32 {
        match self.radii {
            Some(r) => r[i],
            None => self.h,
        }
    }

    /// The largest effective radius (`h` when there are no per-point radii or no points).
    #[must_use]
    pub fn max_radius(&self) -> f32 {
        match self.radii {
            Some(r) if !r.is_empty() => r.iter().copied().fold(0.0, f32::max),
            _ => self.h,
        }
    }

    /// The smallest effective radius (`h` when there are no per-point radii or no points).
    #[must_use]
    pub fn min_radius(&self) -> f32 {
        match self.radii {
            Some(r) if !r.is_empty() => r.iter().copied().fold(f32::INFINITY, f32::min),
            _ => self.h,
        }
    }

    /// Checks the radii (finite, > 0, one per point) and the positions (finite).
    pub fn check(&self) -> Result<(), DensityError> {
        if !(self.h.is_finite() && self.h > 0.0) {
            return Err(DensityError::InvalidRadius { h: self.h });
        }
        if let Some(r) = self.radii {
            if r.len() != self.positions.len() {
                return Err(DensityError::InvalidGrid {
                    name: "radii",
                    reason: format!("{} radii for {} points", r.len(), self.positions.len()),
                });
            }
            if let Some(&h) = r.iter().find(|h| !(h.is_finite() && **h > 0.0)) {
                return Err(DensityError::InvalidRadius { h });
            }
        }
        if let Some(w) = self.weights {
            if w.len() != self.positions.len() {
                return Err(DensityError::InvalidGrid {
                    name: "weights",
                    reason: format!("{} weights for {} points", w.len(), self.positions.len()),
                });
            }
            if let Some(&x) = w.iter().find(|x| !(x.is_finite() && **x >= 0.0)) {
                return Err(DensityError::InvalidGrid {
                    name: "weights",
                    reason: format!("{x} is not a finite weight >= 0"),
                });
            }
        }
        if let Some(index) = self.positions.iter().position(|p| !p.is_finite()) {
            return Err(DensityError::NonFinite { index });
        }
        Ok(())
    }
}

/// How fine the grid is.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Resolution {
    /// Distance between grid points.
    CellSize(f32),
    /// Grid points along the longest axis of the box.
    LongestAxis(u32),
}

/// A regular grid of points `origin + (i, j, k) * spacing`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct GridSpec {
    /// Position of grid point (0, 0, 0).
    pub origin: Vec3,
    /// Distance between neighbouring grid points.
    pub spacing: f32,
    /// Points along x, y and z.
    pub dims: [u32; 3],
}

impl GridSpec {
    /// A grid over the particles' bounding box padded by `padding` on every side (the effective
    /// radius, so that every particle's kernel lies inside), at the given resolution.
    pub fn around(
        positions: &[Vec3],
        padding: f32,
        resolution: Resolution,
    ) -> Result<Self, DensityError> {
        if let Some(index) = positions.iter().position(|p| !p.is_finite()) {
            return Err(DensityError::NonFinite { index });
        }
        let first = *positions.first().ok_or(DensityError::Empty)?;
        let (lo, hi) = positions
            .iter()
            .fold((first, first), |(lo, hi), &p| (lo.min(p), hi.max(p)));
        Self::for_box(
            lo - Vec3::splat(padding),
            hi + Vec3::splat(padding),
            resolution,
        )
    }

    /// A grid over the box `[lo, hi]` at the given resolution.
    pub fn for_box(lo: Vec3, hi: Vec3, resolution: Resolution) -> Result<Self, DensityError> {
        let extent = hi - lo;
        if !lo.is_finite() || !hi.is_finite() || extent.min_element() < 0.0 {
            return Err(DensityError::InvalidGrid {
                name: "box",
                reason: format!("[{lo}, {hi}] is not a finite box"),
            });
        }
        let spacing = match resolution {
            Resolution::CellSize(s) if s.is_finite() && s > 0.0 => s,
            Resolution::LongestAxis(n) if n >= 2 => {
                (extent.max_element() / (n - 1) as f32).max(f32::MIN_POSITIVE)
            }
            other => {
                return Err(DensityError::InvalidGrid {
                    name: "resolution",
                    reason: format!(
                        "{other:?}: a cell size must be finite and > 0, an axis resolution at least 2"
                    ),
                });
            }
        };
        // A cell size puts the grid on the world's lattice `spacing * Z^3` (as splashsurf does,
        // "to get consistent results between frames"): the grid points near a body stay where
        // they were when a drop far away widens the box, so that body's surfels and mesh do not
        // shift with it. An axis resolution fits its spacing to this box and keeps `lo`.
        let lo = match resolution {
            Resolution::CellSize(_) => {
                let mut o = (lo / spacing).floor() * spacing;
                // rounding may leave a lattice point a hair above `lo`
                for a in 0..3 {
                    if o[a] > lo[a] {
                        o[a] -= spacing;
                    }
                }
                o
            }
            Resolution::LongestAxis(_) => lo,
        };
        let extent = hi - lo;
        // a hair of tolerance so that `LongestAxis(n)` gives n points despite rounding
        let dims_f = (extent / spacing * (1.0 + 1e-6)).floor() + Vec3::ONE;
        let dims_u = [dims_f.x as f64, dims_f.y as f64, dims_f.z as f64];
        if dims_u.iter().any(|&d| d > u32::MAX as f64) {
            return Err(DensityError::TooLarge {
                nx: dims_u[0] as u64,
                ny: dims_u[1] as u64,
                nz: dims_u[2] as u64,
                // saturating: absurd sizes must not overflow while being reported
                cells: dims_u.iter().product::<f64>().min(u128::MAX as f64 / 8.0) as u128,
                bytes: (dims_u.iter().product::<f64>() * 4.0).min(u128::MAX as f64 / 2.0) as u128,
                limit: crate::memory::available_memory(),
            });
        }
        Ok(Self {
            origin: lo,
            spacing,
            dims: dims_u.map(|d| d as u32),
        })
    }

    /// Number of grid points.
    #[must_use]
    pub fn cells(&self) -> u128 {
        self.dims.iter().map(|&d| d as u128).product()
    }

    /// Bytes of an `f32` value per grid point.
    #[must_use]
    pub fn bytes(&self) -> u128 {
        self.cells() * 4
    }

    /// Position of grid point `(i, j, k)`.
    #[must_use]
    #[inline]
    pub fn point(&self, i: u32, j: u32, k: u32) -> Vec3 {
        self.origin + Vec3::new(i as f32, j as f32, k as f32) * self.spacing
    }

    /// Refuses grids whose values would exceed `limit` bytes.
    pub fn check_memory(&self, limit: u64) -> Result<(), DensityError> {
        if self.bytes() > limit as u128 {
            let [nx, ny, nz] = self.dims.map(u64::from);
            return Err(DensityError::TooLarge {
                nx,
                ny,
                nz,
                cells: self.cells(),
                bytes: self.bytes(),
                limit,
            });
        }
        Ok(())
    }
}

/// A filled density grid as the pipeline keeps it: dense, or in sparse blocks evaluated near
/// the surface only ([`sparse`]).
#[derive(Clone, Debug, PartialEq)]
pub enum Grid {
    /// Every grid point.
    Dense(DensityGrid),
    /// The blocks near the surface.
    Sparse(SparseGrid),
}

impl Grid {
    /// The grid's geometry.
    #[must_use]
    pub fn spec(&self) -> &GridSpec {
        match self {
            Self::Dense(g) => &g.spec,
            Self::Sparse(g) => &g.spec,
        }
    }

    /// Value at grid point `(i, j, k)` (for a sparse grid, see [`SparseGrid::at`]).
    #[must_use]
    pub fn at(&self, i: u32, j: u32, k: u32) -> f32 {
        match self {
            Self::Dense(g) => g.at(i, j, k),
            Self::Sparse(g) => g.at(i, j, k),
        }
    }

    /// The dense grid, when it is one.
    #[must_use]
    pub fn dense(&self) -> Option<&DensityGrid> {
        match self {
            Self::Dense(g) => Some(g),
            Self::Sparse(_) => None,
        }
    }

    /// Bytes its values take.
    #[must_use]
    pub fn bytes(&self) -> usize {
        match self {
            Self::Dense(g) => 4 * g.values.len(),
            Self::Sparse(g) => g.bytes(),
        }
    }
}

/// A filled density grid, x fastest, then y, then z.
#[derive(Clone, Debug, PartialEq)]
pub struct DensityGrid {
    /// The grid.
    pub spec: GridSpec,
    /// One value per grid point: index `i + nx (j + ny k)`.
    pub values: Vec<f32>,
}

impl DensityGrid {
    /// Value at grid point `(i, j, k)`.
    #[must_use]
    pub fn at(&self, i: u32, j: u32, k: u32) -> f32 {
        let [nx, ny, _] = self.spec.dims;
        self.values[i as usize + nx as usize * (j as usize + ny as usize * k as usize)]
    }

    /// Largest value.
    #[must_use]
    pub fn max(&self) -> f32 {
        self.values.iter().copied().fold(0.0, f32::max)
    }
}

/// Each particle's SPH volume `V_j = 1 / sum_i F(|x_j - x_i|, h)` (its own term included),
/// times `scale`: with these weights the density `sum_j V_j F(|x - x_j|, h)` is a fluid fraction,
/// about 1 inside a body of any spacing and falling to 0 outside it. splashsurf's density map
/// is this field (`m_j / rho_j` with `rho_j = sum_i m_i W_ij`: the masses cancel when they are
/// equal), its iso-value a fraction of the rest density (0.6 by default); with `scale =
/// F(0, h) * iso_fraction / threshold` the pipeline's iso-value (`iso_fraction` of one point's
/// peak) lies where the fraction is `threshold` ([`crate::pipeline::Calibration::Volume`]).
/// Where a particle has fewer neighbours than in the bulk (sheets, drops, a jittered face) its
/// volume is larger, so the field there is stronger than with equal weights. In parallel.
pub fn volume_weights(
    positions: &[Vec3],
    kernel: Kernel,
    h: f32,
    scale: f32,
) -> Result<Vec<f32>, crate::neighbours::NeighbourError> {
    use rayon::prelude::*;
    let grid = crate::neighbours::CellGrid::new(positions, h)?;
    Ok(positions
        .par_iter()
        .map(|&x| {
            let mut sum = 0.0f32;
            grid.for_each_slot_within(x, h, |_, q| {
                sum += kernel.value_r2(q.distance_squared(x), h)
            });
            // the particle's own term makes the sum at least F(0, h) > 0
            scale / sum
        })
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The SPH volumes make a fluid fraction: about 1 inside a lattice of any spacing, both
    /// kernels (the sum of `V_j F` at a particle is 1 exactly, at a point between particles
    /// within a few per cent); a lone particle's volume is `1 / F(0, h)`, so its peak is
    /// `scale`; `scale` multiplies every weight.
    #[test]
    fn volume_weights_make_a_fluid_fraction() {
        for kernel in [Kernel::Wyvill, Kernel::CubicSpline] {
            for s in [0.01f32, 0.5] {
                let h = 2.0 * s;
                let n = 12;
                let mut p: Vec<Vec3> = (0..n * n * n)
                    .map(|i| {
                        Vec3::new((i % n) as f32, ((i / n) % n) as f32, (i / (n * n)) as f32) * s
                    })
                    .collect();
                let lone = Vec3::splat(-10.0 * s);
                p.push(lone);
                let w = volume_weights(&p, kernel, h, 1.0).unwrap();
                let field = |x: Vec3| -> f32 {
                    p.iter()
                        .zip(&w)
                        .map(|(q, wq)| wq * kernel.value_r2(q.distance_squared(x), h))
                        .sum()
                };
                let centre = Vec3::splat(5.0 * s);
                assert!(
                    (field(centre) - 1.0).abs() < 1e-4,
                    "{kernel:?} {s}: {}",
                    field(centre)
                );
                let between = centre + Vec3::new(0.5, 0.3, 0.2) * s;
                assert!(
                    (field(between) - 1.0).abs() < 0.05,
                    "{kernel:?} {s}: {}",
                    field(between)
                );
                // outside the lattice the fraction falls to 0
                assert!(field(Vec3::new(5.0, 5.0, 13.5) * s) == 0.0);
                let alone = *w.last().unwrap();
                assert!(
                    (alone * kernel.peak(h) - 1.0).abs() < 1e-5,
                    "{kernel:?} {s}"
                );
                let scaled = volume_weights(&p, kernel, h, 3.0).unwrap();
                assert!(
                    scaled
                        .iter()
                        .zip(&w)
                        .all(|(a, b)| (a - 3.0 * b).abs() <= 1e-5 * a)
                );
            }
        }
        assert!(volume_weights(&[Vec3::NAN], Kernel::Wyvill, 1.0, 1.0).is_err());
    }

    #[test]
    fn analytic_gradients_match_central_differences() {
        for kernel in [Kernel::Wyvill, Kernel::CubicSpline] {
            let (hj, h) = (0.3f32, 0.8f32);
            for d in [
                Vec3::new(0.05, -0.1, 0.02),
                Vec3::new(0.2, 0.1, -0.05),
                Vec3::new(-0.01, 0.0, 0.27),
            ] {
                let (v, g) = kernel.weighted_and_gradient(d, hj, h);
                assert_eq!(
                    v,
                    kernel.weighted_r2(d.length_squared(), hj, h),
                    "{kernel:?}"
                );
                let e = 1e-3 * hj;
                let f = |x: Vec3| kernel.weighted_r2(x.length_squared(), hj, h) as f64;
                let fd = Vec3::new(
                    ((f(d + Vec3::X * e) - f(d - Vec3::X * e)) / (2.0 * e as f64)) as f32,
                    ((f(d + Vec3::Y * e) - f(d - Vec3::Y * e)) / (2.0 * e as f64)) as f32,
                    ((f(d + Vec3::Z * e) - f(d - Vec3::Z * e)) / (2.0 * e as f64)) as f32,
                );
                let scale = fd.length().max(1e-3 * kernel.peak(h) / hj);
                assert!(
                    (g - fd).length() <= 1e-2 * scale,
                    "{kernel:?} at {d}: analytic {g}, differences {fd}"
                );
            }
            // zero outside the support and at the centre of the cubic spline
            assert_eq!(
                kernel.weighted_and_gradient(Vec3::splat(hj), hj, h),
                (0.0, Vec3::ZERO)
            );
        }
    }

    #[test]
    fn kernels_integrate_to_one() {
        for kernel in [Kernel::Wyvill, Kernel::CubicSpline] {
            for h in [0.1f32, 1.0, 2.5] {
                let n = 100;
                let step = 2.0 * h / n as f32;
                let mut sum = 0.0f64;
                for i in 0..n {
                    for j in 0..n {
                        for k in 0..n {
                            let p = (Vec3::new(i as f32, j as f32, k as f32) + 0.5) * step
                                - Vec3::splat(h);
                            sum += kernel.value(p.length(), h) as f64;
                        }
                    }
                }
                let total = sum * (step as f64).powi(3);
                assert!((total - 1.0).abs() < 2e-3, "{kernel:?} h = {h}: {total}");
            }
        }
        // eq. 1's shape: 1 at the centre (times the constant), 0 and flat at r = h
        let h = 1.0;
        assert!(Kernel::Wyvill.value(0.999_9, h) < 1e-6);
        assert_eq!(Kernel::Wyvill.value(1.0, h), 0.0);
    }
}

/// How the GPU fills the density grid.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum GpuDensityMethod {
    /// The paper's method: particles drawn as point sprites into four planes per RGBA pass with
    /// additive blending (`gpu::splat_slabs_gpu`; on the frame path, `gpu::GridFiller`). The default: the faster of the two on lavapipe,
    /// the only adapter measured so far (150,000 particles into 256^3: 2.0-2.4 s against
    /// 5.1-6.2 s for the gather; see docs/design.md).
    #[default]
    Splat,
    /// A compute shader: particles binned into cubes, one invocation per grid point gathers the
    /// bins around it (`gpu::gather_slabs_gpu`); no blending and no atomics, a fixed summation order.
    Gather,
}
