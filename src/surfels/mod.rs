//! Stage 3, second half: sampling the iso-surface of the density grid into surfels
//! (Iwasaki et al., §4.3), on the CPU ([`cpu`]) and on the GPU ([`gpu`], issue 37), tested
//! against each other.
//!
//! Surfels are placed where the density crosses the iso-value along the grid's x, y and z edges
//! (the root of the cubic through the grid's values along the edge's line, [`crossing_t`]; the
//! paper's linear interpolation at the grid's border), then projected onto the exact iso-surface
//! of the particles' density by Newton steps along the gradient (the grid alone is only accurate
//! to its interpolation). The normal is the negative density gradient (pointing out of the
//! fluid). The radius is the grid spacing: every point of the iso-surface inside a grid cube lies within about 0.71 spacing of a
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
    ExactDensity, SurfelExtractor, extract, extract_points, extract_points_seen, extract_sparse,
    extract_sparse_seen, radius_groups,
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
/// surfels 14-16 % faster; since the starting points are the cubic's ([`crossing_t`]), most
/// surfels stop at their first evaluation.
pub const CONVERGED: f32 = 1e-2;

/// Where the iso-value `iso` crosses an edge whose ends hold `v` (at 0) and `w` (at 1), as a
/// fraction of the edge: the root of the cubic through the grid's values along the edge's line,
/// `outer = (u, z)` one point before and one after (`None` at the grid's border: the linear
/// interpolation `(iso - v) / (w - v)`).
///
/// Why: the surfels are projected onto the exact iso-surface by Newton steps along the gradient
/// from their starting point ([`SurfelExtractor::finish`]), which stop once a step is under
/// [`CONVERGED`] cells. The linear interpolation is off by about `t (1 - t) f'' / (2 f')` cells
/// along the edge, a few hundredths of a cell where the kernels are a few cells wide, so most
/// surfels needed a second evaluation of the density; the cubic's error goes with the fourth
/// derivative instead. Measured on the dam break's chain at two steps (80,786 surfels, a
/// throwaway program): 1.75 -> 1.22 density evaluations a surfel, the start 0.032 -> 0.006
/// cells from the projected point on average, the projection 87 -> 54 ms on one thread.
///
/// The cubic (Lagrange, through `(-1, u)`, `(0, v)`, `(1, w)`, `(2, z)`) in Horner form:
/// `p(t) = v + t (c1 + t (c2 + t c3))`, `c1 = (-2u - 3v + 6w - z) / 6`,
/// `c2 = (u - 2v + w) / 2`, `c3 = (-u + 3v - 3w + z) / 6`. `p(0) = v` and `p(1) = w` lie on
/// either side of `iso`, so a root lies in `[0, 1]`: Newton's steps from the linear `t`, each
/// kept inside the bracket that the signs give (halving it where a step would leave it), until
/// a step is under [`CUBIC_TOLERANCE`] (at most [`CUBIC_STEPS`]). `shaders/surfels.wgsl`'s
/// `crossing_t` is its twin.
#[must_use]
pub fn crossing_t(v: f32, w: f32, outer: Option<(f32, f32)>, iso: f32) -> f32 {
    let linear = (iso - v) / (w - v);
    let Some((u, z)) = outer else {
        return linear;
    };
    let c1 = (-2.0 * u - 3.0 * v + 6.0 * w - z) / 6.0;
    let c2 = (u - 2.0 * v + w) / 2.0;
    let c3 = (-u + 3.0 * v - 3.0 * w + z) / 6.0;
    // the bracket [lo, hi]: p - iso has the sign of v - iso at lo, of w - iso at hi, narrowed
    // at every point evaluated, so that the root found does not depend on the path taken
    let below = v < iso;
    let (mut lo, mut hi) = (0.0f32, 1.0f32);
    let mut t = linear.clamp(0.0, 1.0);
    for _ in 0..CUBIC_STEPS {
        let f = v + t * (c1 + t * (c2 + t * c3)) - iso;
        if f == 0.0 {
            return t;
        }
        if (f < 0.0) == below {
            lo = t;
        } else {
            hi = t;
        }
        let df = c1 + t * (2.0 * c2 + t * (3.0 * c3));
        let newton = t - f / df;
        let next = if newton > lo && newton < hi {
            newton
        } else {
            0.5 * (lo + hi)
        };
        if (next - t).abs() <= CUBIC_TOLERANCE {
            return next;
        }
        t = next;
    }
    t
}

/// The most steps of [`crossing_t`] on the edge's cubic: Newton's from the linear
/// interpolation (two or three then move it by less than [`CUBIC_TOLERANCE`]), a halving of
/// the bracket where one would leave it.
pub const CUBIC_STEPS: u32 = 40;

/// A step of [`crossing_t`] shorter than this fraction of the edge ends it.
pub const CUBIC_TOLERANCE: f32 = 1e-6;

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
    /// once a step is under [`CONVERGED`] cells: 1.22 density evaluations a surfel on the dam
    /// break's chain at two steps from the cubic's starting points, [`crossing_t`]; 1.75 from
    /// the linear ones). Default 16:
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

/// Where a picture sees the surface from, so that extraction can leave out the surfels that face
/// away from every viewpoint ([`SurfelExtractor::finish_seen`]): a picture drawn from these
/// viewpoints alone never shows them (the EWA splats cull a disk facing away from the eye).
/// Eyes of perspective views and directions towards the viewer of orthographic ones.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Viewpoints {
    eyes: Vec<Vec3>,
    directions: Vec<Vec3>,
}

/// How far past edge-on (the cosine between its outward normal and the direction to the eye) a
/// surfel must face away from every viewpoint before [`Viewpoints::sees`] says it is hidden.
/// The decision is taken on the density's gradient at the crossing, before the surfel is
/// projected onto the exact surface (which turns its normal a little), and the camera a picture
/// is finally drawn from may be fitted a little differently from the one the level of detail
/// saw: a margin of 24 degrees. Measured on the dam break from the automatic camera at
/// 640x480 (`detail = "auto"`): 35 % of its surfels lie past it (48 % face away at all).
pub const HIDDEN_PAST: f32 = 0.4;

impl Viewpoints {
    /// No viewpoint yet (every surfel would be hidden: add some).
    #[must_use]
    pub fn new() -> Self {
        Self::default()
    }

    /// With the eye of a perspective view at `eye`.
    #[must_use]
    pub fn with_eye(mut self, eye: Vec3) -> Self {
        self.eyes.push(eye);
        self
    }

    /// With an orthographic view looking along `forward` (its viewer at infinity against it).
    #[must_use]
    pub fn with_direction(mut self, forward: Vec3) -> Self {
        self.directions.push(-forward.normalize_or_zero());
        self
    }

    /// Whether a surfel at `x` with outward normal `n` (any length; zero: no normal, seen) faces
    /// at least one viewpoint, or lies past edge-on by less than [`HIDDEN_PAST`].
    #[must_use]
    pub fn sees(&self, x: Vec3, n: Vec3) -> bool {
        let n = n.normalize_or_zero();
        if n == Vec3::ZERO {
            return true;
        }
        self.eyes
            .iter()
            .map(|&e| (e - x).normalize_or_zero())
            .chain(self.directions.iter().copied())
            .any(|d| n.dot(d) >= -HIDDEN_PAST)
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

#[cfg(test)]
mod tests {
    use super::*;

    /// A surfel is seen from an eye or a direction when it faces it, or lies past edge-on by
    /// less than [`HIDDEN_PAST`] (normals of any length); one without a normal always; none
    /// without a viewpoint.
    #[test]
    fn viewpoints_see_what_faces_them() {
        let x = Vec3::new(1.0, 2.0, 3.0);
        let eye = Viewpoints::new().with_eye(x + Vec3::new(0.0, 0.0, 10.0));
        // the cosine to the eye: +1, 0, just above and below -HIDDEN_PAST, -1
        let at = |c: f32| Vec3::new((1.0 - c * c).sqrt(), 0.0, c);
        assert!(eye.sees(x, at(1.0) * 3.0));
        assert!(eye.sees(x, at(0.0)));
        assert!(eye.sees(x, at(-HIDDEN_PAST + 1e-3) * 0.01));
        assert!(!eye.sees(x, at(-HIDDEN_PAST - 1e-3)));
        assert!(!eye.sees(x, at(-1.0)));
        assert!(eye.sees(x, Vec3::ZERO));
        // an orthographic view looking down -y sees the normals up, and with it added, either
        let down = Viewpoints::new().with_direction(Vec3::new(0.0, -2.0, 0.0));
        assert!(down.sees(x, Vec3::Y));
        assert!(!down.sees(x, -Vec3::Y));
        assert!(down.with_eye(x - Vec3::Y).sees(x, -Vec3::Y));
        assert!(!Viewpoints::new().sees(x, Vec3::Y));
        assert!(Viewpoints::new().sees(x, Vec3::ZERO));
    }

    /// The cubic's root: exact where the values along the line come from a cubic, the linear
    /// interpolation where they come from a line or the outer values are missing, and always a
    /// root in the edge where the values are anything with a crossing.
    #[test]
    fn crossing_t_finds_the_edges_root() {
        let iso = 1.0;
        // f(t) = 1 + (t - 0.3) + 2 (t - 0.3)^3: its root at 0.3, the linear guess 0.2
        let f = |t: f32| 1.0 + (t - 0.3) + 2.0 * (t - 0.3).powi(3);
        let (u, v, w, z) = (f(-1.0), f(0.0), f(1.0), f(2.0));
        let linear = (iso - v) / (w - v);
        let t = crossing_t(v, w, Some((u, z)), iso);
        assert!((t - 0.3).abs() < 1e-5, "{t}");
        assert!(
            (linear - 0.3).abs() > 0.05,
            "the linear guess {linear} is no test"
        );
        assert_eq!(crossing_t(v, w, None, iso), linear);
        // a line: the linear interpolation's point
        let g = |t: f32| 0.5 + 0.9 * t;
        let t = crossing_t(g(0.0), g(1.0), Some((g(-1.0), g(2.0))), iso);
        assert!((t - 5.0 / 9.0).abs() < 1e-6, "{t}");
        // falling across the iso-value too
        let t = crossing_t(f(1.0), f(0.0), Some((f(2.0), f(-1.0))), iso);
        assert!((t - 0.7).abs() < 1e-5, "{t}");
        // anything with a crossing: a root of the cubic inside the edge
        let mut state = 12_345u32;
        let mut next = || {
            state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            (state >> 8) as f32 / (1u32 << 24) as f32 * 4.0
        };
        for _ in 0..10_000 {
            let (u, v, w, z) = (next(), next(), next(), next());
            if (v < iso) == (w < iso) {
                continue;
            }
            let t = crossing_t(v, w, Some((u, z)), iso);
            assert!((0.0..=1.0).contains(&t), "{t} for {u} {v} {w} {z}");
            let c1 = (-2.0 * u - 3.0 * v + 6.0 * w - z) / 6.0;
            let c2 = (u - 2.0 * v + w) / 2.0;
            let c3 = (-u + 3.0 * v - 3.0 * w + z) / 6.0;
            let p = v + t * (c1 + t * (c2 + t * c3));
            assert!((p - iso).abs() < 1e-4, "p({t}) = {p} for {u} {v} {w} {z}");
        }
    }
}
