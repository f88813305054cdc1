//! The chain's surface at the fluid's boundary at every level of refinement (issue 35).
//!
//! The chain's density (Iwasaki et al. eq. 1 over the interior particles and the refined
//! surface points, each with its own kernel radius, [`Points`]) crosses the iso-value `tau` at a
//! distance from the refined points that grows with their kernel radius `h_k = kernel_factor
//! r_k`. Why: the refined points of level `k` sample the surface sheet at a spacing about
//! `r_k`, with an area density `sigma_k ~ 1 / r_k^2`; a point adds `(h_k / h)^3 F(r, h_k)`, so
//! at a height `z` over the sheet the sheet's density is
//! `D_k(z) = sigma_k (h_k / h)^3 G(z, h_k) = sigma_k h_k^2 g(z / h_k) / h^3`, with
//! `G(z, h) = g(z / h) / h` the integral of `F` over a plane at distance `z` and `g` the one of
//! the unit kernel. With `h_k = 2 r_k` the factor `sigma_k h_k^2` is the same at every level, so
//! `D_k` is one profile stretched by `h_k`: the iso-surface lies at `z* = alpha h_k`, the same
//! `alpha` at every level (measured, tests/boundary.rs: 2.5, 1.07, 0.37 and 0.0 spacings too far
//! out at 0 to 3 steps, `h_k` = 4, 2, 1 and 0.5 spacings). Only at three steps does `z*` happen to
//! be the half spacing between the outermost particle centres and the fluid's boundary.
//!
//! The kernel radius cannot carry the correction: a kernel shorter than the points' spacing makes
//! beads of the sheet. So each refined point `j` gets a weight `w_j` on its term, chosen so that
//! the density at its target `t_j = x_j + n_j s / 2` (half a spacing `s` out along its normal,
//! where the boundary is) equals the iso-value:
//!
//! `I(t_j) + sum_i w_i (h_i / h)^3 F(|t_j - x_i|, h_i) = tau`,
//!
//! `I` the interior particles' density there. With the weights of neighbouring points alike
//! (they vary smoothly along a surface) it is solved by Jacobi steps from `w = 1`:
//! `w_j <- w_j (tau - I(t_j)) / D_sheet(t_j)`, each a Shepard normalisation of the sheet at the
//! target. The target is local, so the same rule holds on a thin sheet (no interior: both sides'
//! targets half a spacing off the one layer, one spacing thick), on a drop and a tube (the
//! curvature is in the sums), and in the bulk. A lone point (no other point reaches it) is a drop
//! of one particle's volume, a ball of radius `(3 / (4 pi))^(1/3) s = 0.62 s`: its weight puts
//! its own term at the iso-value there. Weights are kept in `[0, MAX_WEIGHT]`: where the interior
//! alone passes the iso-value at the target (a concave fold) a point adds nothing.

pub mod gpu;

use glam::Vec3;
use rayon::prelude::*;

use crate::density::{Kernel, Points};
use crate::neighbours::CellGrid;
use crate::surfels::{ExactDensity, SurfelError};

/// A point is buried (inside the fluid, not on its boundary) when a particle lies within this
/// many spacings of its target half a spacing out, farther than that from the point. On a flat
/// layer the particle a point sits on is half a spacing from its target and excluded (it is
/// near the point); a neighbour on the same layer is `sqrt(1 + 1/4) = 1.12` spacings from a
/// particle's target, and a point between particles is nearer them than this; a particle of the
/// next layer out is half a spacing from the target. 0.6 missed the inner particles of the
/// radius-2 drop (the outer shell's particles lie 0.71 spacings from their targets), whose
/// refined points then left a bubble inside it at three steps.
pub const BURIED: f32 = 0.75;

/// Half width of the burial's smoothsteps around [`BURIED`], in spacings. The real files' particles
/// lie up to 0.2 spacings off their layer, and a step as steep as 0.1 spacings turned a jitter of
/// 1 % of a spacing into burial changes of 0.12: measured on the double dam break's finished
/// frame under that jitter (tests/pictures.rs), 0.96 % mean difference with 0.2, 1.06 % with 0.1.
pub const BAND: f32 = 0.2;

/// Jacobi steps of the weights (measured: 8 steps instead of 3 moved the radius-2 drop's and
/// tube's surfaces by at most 0.01 spacings in tests/boundary.rs, and the real files' frames
/// under jitter by 0.02 points; one step, the Shepard normalisation alone, costs 0.5 s less on
/// the dam break's 363k refined points but its levels agree less: the double dam break's shaded
/// splats at 3 and 1 steps 24.3 dB apart, 27.0 with three).
pub const WEIGHT_STEPS: u32 = 3;

/// The most targets whose sheet terms [`boundary_weights`] lists once for its Jacobi steps
/// (their nonzero terms, 47 a target on the dam break at two steps, of 8 bytes each, a code
/// and a kernel: about 75 MB at this many; beyond, every step searches the cells again, the
/// same sums).
pub const LISTED_TARGETS: usize = 200_000;

/// Targets per list chunk of the Jacobi steps' terms.
const TERMS_CHUNK: usize = 1024;

/// Terms a chunk's lists make room for per target at first: more than most targets have (47
/// on the dam break at two steps; untouched room costs no memory).
const TERMS_PER_TARGET: usize = 80;

/// The largest weight a refined point gets (a point alone at the tip of a spike).
pub const MAX_WEIGHT: f32 = 16.0;

/// Radius of a lone particle's ball, in spacings: a ball of one particle's volume `s^3`.
pub const LONE_RADIUS: f32 = 0.620_350_5;

/// The weights of the chain's points: their own factors ([`Points::weights`]) for the first
/// `interior` points (the interior particles), then per refined point the weight that puts the iso-surface `tau` half a spacing
/// `spacing` out along its normal (`normals`, one per refined point) from it; see the module
/// docs.
pub fn boundary_weights(
    points: Points<'_>,
    interior: usize,
    normals: &[Vec3],
    spacing: f32,
    kernel: Kernel,
    tau: f32,
) -> Result<Vec<f32>, SurfelError> {
    boundary_weights_reusing(
        points,
        interior,
        normals,
        (spacing, kernel, tau),
        &mut TermLists::default(),
    )
}

/// [`boundary_weights`] (`spacing`, `kernel`, `tau` as there) with the sheet's term lists made
/// in `lists`, kept by the caller for the next frame: the same weights bit for bit.
pub fn boundary_weights_reusing(
    points: Points<'_>,
    interior: usize,
    normals: &[Vec3],
    (spacing, kernel, tau): (f32, Kernel, f32),
    lists: &mut TermLists,
) -> Result<Vec<f32>, SurfelError> {
    weights_listing(
        points,
        interior,
        normals,
        (spacing, kernel, tau),
        (LISTED_TARGETS, lists),
    )
}

/// The memory of [`boundary_weights`]' term lists (the sheet's terms at each target, 8 bytes a
/// term: about 33 MB on the dam break at two steps), kept from frame to frame by a caller of
/// [`boundary_weights_reusing`] ([`crate::pipeline::Pipeline`] does). Made afresh every frame,
/// its pages were faulted in again each time: with glibc's default allocator settings 42 % of
/// the page faults of the dam break's frame (`perf record -e page-faults`).
#[derive(Default)]
pub struct TermLists(Vec<Listed>);

impl std::fmt::Debug for TermLists {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TermLists")
            .field("chunks", &self.0.len())
            .finish_non_exhaustive()
    }
}

/// [`boundary_weights`], listing the sheet's terms once for the Jacobi steps in `lists` when
/// there are at most `listed` targets.
fn weights_listing(
    points: Points<'_>,
    interior: usize,
    normals: &[Vec3],
    (spacing, kernel, tau): (f32, Kernel, f32),
    (listed, lists): (usize, &mut TermLists),
) -> Result<Vec<f32>, SurfelError> {
    let n = points.len();
    debug_assert_eq!(n - interior, normals.len());
    // the points' own factors (1 without), fixed for the interior and kept as a factor on the
    // refined points' solved weights
    let base: Vec<f32> = (0..n).map(|i| points.weight(i)).collect();
    if n == interior {
        return Ok(base);
    }
    let h = points.h;
    // every sum below is a density of a part of the points with weights, read in the grids'
    // cell order ([`ExactDensity::value`]): twice as fast as visiting the points by index
    let part = |range: std::ops::Range<usize>, weights: &[f32]| -> Result<_, SurfelError> {
        let mut d = ExactDensity::of(
            Points {
                positions: &points.positions[range.clone()],
                radii: points.radii.map(|r| &r[range.clone()]),
                weights: None,
                h,
            },
            kernel,
        )?;
        d.reweight(&weights[range]);
        Ok(d)
    };
    // per refined point: its target half a spacing out and how alone it is, `1 - (the other
    // points' density at it) / (its own peak)` clamped to [0, 1] (1: no other point reaches
    // it), so that a point's weight goes over from a lone ball's to a sheet's continuously
    // (the interior's large kernels are summed only where the sheet alone does not outweigh
    // the point: a sheet's points have neighbours, and the interior's sum at a point scans 27
    // cells of the support radius, the most expensive sum here)
    let inner = if interior > 0 {
        Some(part(0..interior, &base)?)
    } else {
        None
    };
    let mut sheet_density = part(interior..n, &base)?;
    let targets: Vec<Target> = (interior..n)
        .into_par_iter()
        .map(|j| {
            let x = points.positions[j];
            let own = base[j] * kernel.weighted_r2(0.0, points.radius(j), h);
            // the sum stops once the others pass the point's own term (alone is 0 then, the
            // same as from the whole sum: most points, 44 -> 16 ms on the dam break at two
            // steps)
            let mut others = sheet_density.value_up_to(x, 2.0 * own) - own;
            if others < own {
                others += inner.as_ref().map_or(0.0, |d| d.value(x));
            }
            let alone = if own > 0.0 {
                (1.0 - others / own).clamp(0.0, 1.0)
            } else {
                0.0
            };
            // the weight that makes the point alone a ball of one particle's volume
            let ball =
                base[j] * kernel.weighted_r2((LONE_RADIUS * spacing).powi(2), points.radius(j), h);
            let lone = if ball > 0.0 {
                (tau / ball).min(MAX_WEIGHT)
            } else {
                1.0
            };
            let nj = normals[j - interior].normalize_or_zero();
            if nj == Vec3::ZERO {
                Target {
                    at: x,
                    alone: 1.0,
                    lone,
                }
            } else {
                Target {
                    at: x + nj * (0.5 * spacing),
                    alone,
                    lone,
                }
            }
        })
        .collect();
    // the interior's density at each target, fixed through the steps
    let inside: Vec<f32> = match &inner {
        Some(d) => targets.par_iter().map(|t| d.value(t.at)).collect(),
        None => vec![0.0; targets.len()],
    };
    drop(inner);
    // the refined points' weights `w` (the interior's stay 1), solved step by step; the sheet's
    // density sums `base * w`
    let mut w = vec![1.0f32; n - interior];
    let mut sheet_weights = base[interior..].to_vec();
    // the sheet's terms at each target, found once and summed again at every step (the same
    // sums bit for bit, without the cell searches: the dam break's calibration at two steps,
    // 88,902 refined points, 202 -> 145 ms; the column's splash frame 115-138 -> 92 ms), where
    // they fit [`LISTED_TARGETS`]; the first step's sums come from the same visit as the lists
    // (its weights are the ones the sheet was indexed with: 8 ms less at two steps); with each
    // term's kernel listed beside it and the zero terms left out, the later steps only multiply
    // by the new weights (the dam break's steps 2 and 3 at two steps: about 22 -> 5.4 ms for
    // 4.16 M terms)
    if targets.len() > listed {
        // (unused this frame: their memory given back rather than kept for a frame to come)
        lists.0 = Vec::new();
    }
    let terms = (targets.len() <= listed)
        .then(|| {
            let lists = &mut lists.0;
            lists.resize_with(targets.len().div_ceil(TERMS_CHUNK), Listed::default);
            let fits = lists
                .par_iter_mut()
                .zip(targets.par_chunks(TERMS_CHUNK))
                .all(|(l, chunk)| l.fill(chunk, &sheet_density));
            fits.then_some(&lists[..])
        })
        .flatten();
    let sheet_at = |j: usize, x: Vec3, density: &ExactDensity<'_>, step: u32| match terms {
        Some(lists) => {
            let l = &lists[j / TERMS_CHUNK];
            let k = j % TERMS_CHUNK;
            if step == 0 {
                l.first[k]
            } else {
                let range = l.ends[k] as usize..l.ends[k + 1] as usize;
                density.value_of_kernels(&l.codes[range.clone()], &l.kernels[range])
            }
        }
        None => density.value(x),
    };
    for step in 0..WEIGHT_STEPS {
        if step > 0 {
            for (s, (b, w)) in sheet_weights
                .iter_mut()
                .zip(base[interior..].iter().zip(&w))
            {
                *s = b * w;
            }
            sheet_density.reweight(&sheet_weights);
        }
        let density = &sheet_density;
        let next: Vec<f32> = targets
            .par_iter()
            .enumerate()
            .zip(&inside)
            .zip(&w)
            .map(|(((j, t), &inside), &w)| {
                if t.alone >= 1.0 {
                    return t.lone;
                }
                let sheet = sheet_at(j, t.at, density, step);
                let want = (tau - inside).max(0.0);
                let boundary = if sheet > 0.0 {
                    (w * want / sheet).clamp(0.0, MAX_WEIGHT)
                } else {
                    w
                };
                t.alone * t.lone + (1.0 - t.alone) * boundary
            })
            .collect();
        w = next;
    }
    let mut out = base;
    for (o, w) in out[interior..].iter_mut().zip(&w) {
        *o *= w;
    }
    Ok(out)
}

/// The sheet's terms at a chunk of targets ([`TERMS_CHUNK`]): target `k`'s are
/// `codes[ends[k]..ends[k + 1]]` with their kernels in `kernels` ([`ExactDensity::value_and_kernels`]),
/// `first[k]` their sum with the weights the sheet was indexed with (the first Jacobi step's).
#[derive(Default)]
struct Listed {
    ends: Vec<u32>,
    codes: Vec<u32>,
    kernels: Vec<f32>,
    first: Vec<f32>,
}

impl Listed {
    /// The sheet's terms at the targets of `chunk` in `density`, in the room this list kept
    /// from an earlier frame; `false` where a term's code does not fit
    /// ([`ExactDensity::value_and_kernels`]).
    fn fill(&mut self, chunk: &[Target], density: &ExactDensity<'_>) -> bool {
        self.ends.clear();
        self.codes.clear();
        self.kernels.clear();
        self.first.clear();
        // room for the terms of most chunks at once (about 47 a target at two steps on the dam
        // break): no copies as the lists grow (untouched room costs no memory)
        self.codes.reserve(chunk.len() * TERMS_PER_TARGET);
        self.kernels.reserve(chunk.len() * TERMS_PER_TARGET);
        self.ends.push(0);
        for t in chunk {
            let first = if t.alone < 1.0 {
                match density.value_and_kernels(t.at, &mut self.codes, &mut self.kernels) {
                    Some(sum) => sum,
                    None => return false,
                }
            } else {
                0.0
            };
            self.first.push(first);
            self.ends.push(self.codes.len() as u32);
        }
        true
    }
}

/// A refined point's target half a spacing out along its normal (the point itself without one),
/// how alone it is (1: no other point reaches it) and its weight as a lone ball.
struct Target {
    at: Vec3,
    alone: f32,
    lone: f32,
}

/// A particle set's positions under two cell grids: cells of two spacings (the support
/// radius) for [`Fluid::flat_normal`] and [`Fluid::average`], and cells of the burial's reach
/// for [`Fluid::burial`].
pub struct Fluid<'a> {
    positions: &'a [Vec3],
    grid: CellGrid,
    /// Cells of `(BURIED + BAND)` spacings: the 27 cells a burial query visits hold about 9x
    /// fewer particles than those of the support radius (the cells' volume; the dam break's
    /// refined points' burial at two steps 12.3-13.3 -> 10.1-10.6 ms, the same values).
    near: CellGrid,
    spacing: f32,
}

impl<'a> Fluid<'a> {
    /// Indexes the particles (spacing `spacing`).
    pub fn new(positions: &'a [Vec3], spacing: f32) -> Result<Self, SurfelError> {
        Ok(Self {
            positions,
            grid: CellGrid::new(positions, 2.0 * spacing)?,
            near: CellGrid::new(positions, (BURIED + BAND) * spacing)?,
            spacing,
        })
    }

    /// The normal of particle `i` when its neighbourhood (within two spacings) is flat, one
    /// particle thick, and how flat it is: the smallest-eigenvalue eigenvector of the
    /// neighbourhood's covariance, and 1 when that eigenvalue is under 5 % of the next, 0 over
    /// 15 %, a smoothstep between (a single layer: about zero; the bulk and a layer under the
    /// surface: comparable). The normal points up (+y), else +x, else +z: the eigenvector's sign
    /// is arbitrary, and a sheet lying on more fluid to one side has different targets on its
    /// two sides.
    #[must_use]
    pub fn flat_normal(&self, i: usize) -> Option<(Vec3, f32)> {
        let h = 2.0 * self.spacing;
        let x = self.positions[i];
        // one pass: the count, the sum and the sum of outer products of the offsets
        let (mut n, mut sum, mut outer) = (0.0f32, Vec3::ZERO, glam::Mat3::ZERO);
        self.grid.for_each_within(x, h, |j| {
            let d = self.positions[j as usize] - x;
            if d.length_squared() < h * h {
                n += 1.0;
                sum += d;
                outer += glam::Mat3::from_cols(d * d.x, d * d.y, d * d.z);
            }
        });
        if n < 4.0 {
            return None;
        }
        let mean = sum / n;
        let cov = outer - glam::Mat3::from_cols(mean * mean.x, mean * mean.y, mean * mean.z) * n;
        if surely_thick(cov) {
            // flat would be 0: the eigenvectors are not needed (the bulk and most surface
            // neighbourhoods, 2 % of the dam break's chain on one thread in the solver)
            return None;
        }
        let (values, vectors) = crate::linalg::symmetric_eigen(cov);
        if values[1].is_nan() || values[1] <= 0.0 {
            return None;
        }
        let flat = 1.0 - smoothstep(0.05, 0.15, values[0] / values[1]);
        let v = vectors[0];
        let up = if v.y.abs() > 1e-3 {
            v.y
        } else if v.x.abs() > 1e-3 {
            v.x
        } else {
            v.z
        };
        (flat > 0.0).then_some((v * up.signum(), flat))
    }

    /// How buried the point `x` with outward normal `n` is, in [0, 1]: the largest over the
    /// particles `p` of `near(|p - t|) far(|p - x|)`, `t` the target half a spacing out,
    /// `near` falling from 1 to 0 and `far` rising from 0 to 1 over [`BURIED`] +- [`BAND`]
    /// spacings (smoothsteps): a particle beyond the target and not at the point. Continuous in
    /// the positions, so that particles moved a little change the surface a little (a yes or
    /// no here made the double dam break's finished frame 8 % less stable under jitter).
    #[must_use]
    pub fn burial(&self, x: Vec3, n: Vec3) -> f32 {
        let n = n.normalize_or_zero();
        if n == Vec3::ZERO {
            return 0.0;
        }
        let s = self.spacing;
        let (lo, hi) = ((BURIED - BAND) * s, (BURIED + BAND) * s);
        let t = x + n * (0.5 * s);
        let mut b = 0f32;
        // a particle beyond `hi` of the target adds 0 to the maximum: the finer grid visits the
        // same nonzero terms
        self.near.for_each_within(t, hi, |p| {
            let p = self.positions[p as usize];
            let near = 1.0 - smoothstep(lo, hi, p.distance(t));
            let far = smoothstep(lo, hi, p.distance(x));
            b = b.max(near * far);
        });
        b
    }
}

impl Fluid<'_> {
    /// The particles' `values` averaged around `x`: weights `(1 - d^2 / h^2)^3` over the
    /// particles within `h`, two spacings (0 where none is).
    #[must_use]
    pub fn average(&self, x: Vec3, values: &[f32]) -> f32 {
        let h2 = (2.0 * self.spacing).powi(2);
        let (mut sum, mut total) = (0.0f32, 0.0f32);
        self.grid.for_each_within(x, 2.0 * self.spacing, |i| {
            let q = 1.0 - self.positions[i as usize].distance_squared(x) / h2;
            if q > 0.0 {
                let w = q * q * q;
                sum += w * values[i as usize];
                total += w;
            }
        });
        if total > 0.0 { sum / total } else { 0.0 }
    }
}

/// Whether the covariance `c` (symmetric, positive semi-definite) is surely not flat for
/// [`Fluid::flat_normal`]: its two smallest eigenvalues' ratio `l0 / l1` at least 0.15 (and
/// then 1 % more, so that no ratio the eigen solver would put under 0.15 is skipped), judged
/// from its invariants without the eigen solver: with `l0 <= l1 <= l2`, the trace `T`, the sum
/// of the principal 2x2 minors `M = l0 l1 + l0 l2 + l1 l2 >= l1 l2` and the determinant
/// `D = l0 l1 l2`, `l0 = D / (l1 l2) >= D / M` and `l1 <= (l1 + l2) / 2 <= T / 2`, so
/// `l0 / l1 >= 2 D / (M T)`. An isotropic neighbourhood gives 2/9, a surface's half ball about
/// 0.2, a flat layer about 0.
fn surely_thick(c: glam::Mat3) -> bool {
    let a = |r: usize, k: usize| 0.5 * (f64::from(c.col(k)[r]) + f64::from(c.col(r)[k]));
    let (xx, yy, zz, xy, xz, yz) = (a(0, 0), a(1, 1), a(2, 2), a(0, 1), a(0, 2), a(1, 2));
    let t = xx + yy + zz;
    let m = xx * yy - xy * xy + xx * zz - xz * xz + yy * zz - yz * yz;
    let d = xx * (yy * zz - yz * yz) - xy * (xy * zz - yz * xz) + xz * (xy * yz - yy * xz);
    t > 0.0 && m > 0.0 && 2.0 * d >= 0.15 * 1.01 * m * t
}

fn smoothstep(e0: f32, e1: f32, x: f32) -> f32 {
    let t = ((x - e0) / (e1 - e0)).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

/// The chain's points with the surface at the fluid's boundary: the interior particles, weight
/// one, and the buried surface particles (detected as surface but inside the fluid: the inner
/// particles of a small drop, a slab's second layer; weight their burial) with the support
/// radius `h`; then the refined points not wholly buried, with their kernel radii and the
/// weights of [`boundary_weights`] times how little they are buried. Why the buried points go:
/// a target inside the fluid cannot hold the iso-value without a bubble, and their refined
/// points with weight 1 swelled the small drop (tests/boundary.rs: +0.3 spacings at one step).
///
/// A sheet one particle thick is exposed on both sides of its plane, which the detector's
/// classes do not say (Solenthaler et al. §3.1: a flat layer's centre of mass lies on its
/// particles, so most are "interior", some "surface" where the layer is uneven). Every particle
/// whose neighbourhood is such a sheet ([`Fluid::flat_normal`], not buried on either side) is
/// drawn as a point of the sheet with targets on both sides, whatever its class, and the refined
/// points there are faded by the sheet's share around them ([`Fluid::average`]): with the
/// class deciding (interior particles in the sheet, surface ones by their refined points, whose
/// normals lie along the layer) the double dam break's floor showed creases where the classes
/// met, and its finished frame (tests/pictures.rs, 160x120) changed by 1.34 % under a jitter of
/// 1 % of a spacing and a shuffle; 0.89 % with this rule (the paper's sums: 0.88 %).
pub fn chain_points_at_boundary(
    particles: &[Vec3],
    surface: &crate::surface::Surface,
    refined: Sheet<'_>,
    h: f32,
    kernel: Kernel,
    tau: f32,
) -> Result<ChainPoints, SurfelError> {
    chain_input_at_boundary(particles, surface, refined, h)?.solve(h, kernel, tau)
}

/// [`chain_points_at_boundary`] before the weights are solved: the points, their own weights
/// and the sheet's normals, for [`BoundaryInput::solve`] on the CPU or [`gpu::WeightPasses`]
/// on the GPU.
pub fn chain_input_at_boundary(
    particles: &[Vec3],
    surface: &crate::surface::Surface,
    refined: Sheet<'_>,
    h: f32,
) -> Result<BoundaryInput, SurfelError> {
    let Factors { thin, inner, kept } = boundary_factors(particles, surface, refined, h)?;
    let mut positions = Vec::new();
    let mut base = Vec::new();
    for (i, &b) in inner.iter().enumerate() {
        if b > 0.0 {
            positions.push(particles[i]);
            base.push(b);
        }
    }
    let interior = positions.len();
    let mut radii = vec![h; interior];
    let mut normals = Vec::new();
    for (i, t) in thin.iter().enumerate() {
        if let Some((n, share)) = t {
            positions.push(particles[i]);
            radii.push(h);
            normals.push(*n);
            base.push(*share);
        }
    }
    for j in (0..refined.positions.len()).filter(|&j| kept[j] > 0.0) {
        positions.push(refined.positions[j]);
        radii.push(refined.radii[j]);
        normals.push(refined.normals[j]);
        base.push(kept[j]);
    }
    Ok(BoundaryInput {
        positions,
        radii,
        base,
        interior,
        normals,
        spacing: 0.5 * h,
    })
}

/// The factors of [`chain_input_at_boundary`] before its points are gathered: per particle
/// its sheet one particle thick (normal and share, where it is in one) and its factor as an
/// interior particle, per point of `refined` how much of it is kept (how little it is buried
/// times how little a thin sheet is around it).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Factors {
    pub thin: Vec<Option<(Vec3, f32)>>,
    pub inner: Vec<f32>,
    pub kept: Vec<f32>,
}

/// [`Factors`] of `particles` (classed by `surface`, support radius `h`) and the sheet
/// `refined`.
pub fn boundary_factors(
    particles: &[Vec3],
    surface: &crate::surface::Surface,
    refined: Sheet<'_>,
    h: f32,
) -> Result<Factors, SurfelError> {
    use crate::surface::ParticleClass;
    let spacing = 0.5 * h;
    let fluid = Fluid::new(particles, spacing)?;
    // particles of a sheet one particle thick, exposed on both sides of their plane: (normal,
    // share in the sheet), how flat times how exposed, both continuous
    let thin: Vec<Option<(Vec3, f32)>> = (0..particles.len())
        .into_par_iter()
        .map(|i| {
            (surface.classes[i] != ParticleClass::Isolated)
                .then(|| fluid.flat_normal(i))
                .flatten()
                .and_then(|(n, flat)| {
                    let b = fluid
                        .burial(particles[i], n)
                        .max(fluid.burial(particles[i], -n));
                    let share = flat * (1.0 - b);
                    (share > 0.0).then_some((n, share))
                })
        })
        .collect();
    let share: Vec<f32> = thin.iter().map(|t| t.map_or(0.0, |(_, s)| s)).collect();
    // each particle's factor as an interior one: 1, a surface particle's burial, 0 isolated;
    // less its share in a thin sheet
    let inner: Vec<f32> = (0..particles.len())
        .into_par_iter()
        .map(|i| {
            (match surface.classes[i] {
                ParticleClass::Interior => 1.0,
                ParticleClass::Surface => fluid.burial(particles[i], surface.normals[i]),
                ParticleClass::Isolated => 0.0,
            }) * (1.0 - share[i])
        })
        .collect();
    // (the sheet's share around a refined point only where a thin sheet's particle lies within
    // the average's reach: elsewhere it is 0 exactly, and most points skip that neighbour loop
    // over every particle)
    let thin_positions: Vec<Vec3> = (0..particles.len())
        .filter(|&i| share[i] > 0.0)
        .map(|i| particles[i])
        .collect();
    let thin_grid = if thin_positions.is_empty() {
        None
    } else {
        Some(CellGrid::new(&thin_positions, 2.0 * spacing)?)
    };
    let kept: Vec<f32> = (0..refined.positions.len())
        .into_par_iter()
        .map(|j| {
            let x = refined.positions[j];
            let mut near_thin = false;
            if let Some(g) = &thin_grid {
                g.for_each_within(x, 2.0 * spacing, |_| near_thin = true);
            }
            let around = if near_thin {
                fluid.average(x, &share)
            } else {
                0.0
            };
            (1.0 - fluid.burial(x, refined.normals[j])) * (1.0 - around)
        })
        .collect();
    Ok(Factors { thin, inner, kept })
}

/// Every particle and every sheet point, uncompacted, for [`chain_input_at_boundary`]'s
/// factors found where the weights are solved (on the GPU:
/// `boundary::gpu::Split::Found`): the particles lead (support radius `h`), then the sheet.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct BoundaryLayout {
    pub positions: Vec<Vec3>,
    pub radii: Vec<f32>,
    /// How many particles lead.
    pub particles: usize,
    /// Per particle its surface normal and class, `[nx, ny, nz, class]`: 0 interior, 1
    /// surface, 2 isolated (a non-finite normal is zero).
    pub classes: Vec<[f32; 4]>,
    /// The sheet's outward normals (zero: none), one per sheet point.
    pub normals: Vec<Vec3>,
    /// The particles' spacing.
    pub spacing: f32,
}

/// The [`BoundaryLayout`] of `particles` (classed by `surface`, support radius `h`) and the
/// sheet `refined`.
#[must_use]
pub fn boundary_layout(
    particles: &[Vec3],
    surface: &crate::surface::Surface,
    refined: Sheet<'_>,
    h: f32,
) -> BoundaryLayout {
    let mut positions = Vec::with_capacity(particles.len() + refined.positions.len());
    positions.extend_from_slice(particles);
    positions.extend_from_slice(refined.positions);
    let mut radii = vec![h; particles.len()];
    radii.extend_from_slice(refined.radii);
    let classes = surface
        .classes
        .iter()
        .zip(&surface.normals)
        .map(|(&c, &n)| {
            let n = if n.is_finite() { n } else { Vec3::ZERO };
            n.extend(f32::from(c as u8)).to_array()
        })
        .collect();
    BoundaryLayout {
        positions,
        radii,
        particles: particles.len(),
        classes,
        normals: refined.normals.to_vec(),
        spacing: 0.5 * h,
    }
}

/// The chain's points for the density grid before the sheet's weights are solved
/// ([`chain_input_at_boundary`], [`particle_input_at_boundary`]).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct BoundaryInput {
    /// The interior points first, then the sheet.
    pub positions: Vec<Vec3>,
    pub radii: Vec<f32>,
    /// Each point's own weight: the interior's final, the sheet's a factor of its solved one.
    pub base: Vec<f32>,
    /// How many interior points lead.
    pub interior: usize,
    /// The sheet's outward normals (zero: none), one per sheet point.
    pub normals: Vec<Vec3>,
    /// The particles' spacing.
    pub spacing: f32,
}

impl BoundaryInput {
    /// The weights solved on the CPU ([`boundary_weights`], reference radius `h`).
    pub fn solve(self, h: f32, kernel: Kernel, tau: f32) -> Result<ChainPoints, SurfelError> {
        self.solve_reusing(h, kernel, tau, &mut TermLists::default())
    }

    /// [`Self::solve`] with the term lists made in `lists` ([`boundary_weights_reusing`]).
    pub fn solve_reusing(
        self,
        h: f32,
        kernel: Kernel,
        tau: f32,
        lists: &mut TermLists,
    ) -> Result<ChainPoints, SurfelError> {
        let weights = boundary_weights_reusing(
            Points::with_radii(&self.positions, &self.radii, h).with_weights(&self.base),
            self.interior,
            &self.normals,
            (self.spacing, kernel, tau),
            lists,
        )?;
        Ok(ChainPoints {
            positions: self.positions,
            radii: self.radii,
            weights,
        })
    }
}

/// The points of the surface sheet the weights are solved for: the refined points (the chain),
/// or the surface and isolated particles themselves (the raw-particle source).
#[derive(Clone, Copy, Debug)]
pub struct Sheet<'a> {
    pub positions: &'a [Vec3],
    /// Outward normals (zero: none, a lone point).
    pub normals: &'a [Vec3],
    /// Kernel radii.
    pub radii: &'a [f32],
}

impl<'a> Sheet<'a> {
    /// The refined points with their kernel radii.
    #[must_use]
    pub fn refined(r: &'a crate::refine::Refined) -> Self {
        Self {
            positions: &r.positions,
            normals: &r.normals,
            radii: &r.kernel_radii,
        }
    }
}

/// The raw-particle source's points with the surface at the fluid's boundary: the same rule as
/// the chain's ([`chain_points_at_boundary`]) with the surface and isolated particles, each with
/// the support radius `h`, as the sheet (the chain at level 0 with the particles' own kernel).
pub fn particle_points_at_boundary(
    particles: &[Vec3],
    surface: &crate::surface::Surface,
    h: f32,
    kernel: Kernel,
    tau: f32,
) -> Result<ChainPoints, SurfelError> {
    particle_input_at_boundary(particles, surface, h)?.solve(h, kernel, tau)
}

/// [`particle_points_at_boundary`] before the weights are solved.
pub fn particle_input_at_boundary(
    particles: &[Vec3],
    surface: &crate::surface::Surface,
    h: f32,
) -> Result<BoundaryInput, SurfelError> {
    let outer = OwnedSheet::of_particles(particles, surface, h);
    chain_input_at_boundary(particles, surface, outer.sheet(), h)
}

/// The raw-particle source's sheet, owned: the surface and isolated particles in the
/// refinement's order (`refined_indices`) with their surface normals and the support radius.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct OwnedSheet {
    pub positions: Vec<Vec3>,
    pub normals: Vec<Vec3>,
    pub radii: Vec<f32>,
}

impl OwnedSheet {
    /// The surface and isolated particles of `particles` (classed by `surface`), radius `h`.
    #[must_use]
    pub fn of_particles(particles: &[Vec3], surface: &crate::surface::Surface, h: f32) -> Self {
        let outer = super::refined_indices(surface, particles);
        let (positions, normals) = super::gather(
            crate::ParticleView::of_positions(particles),
            surface,
            &outer,
        );
        Self {
            positions,
            normals,
            radii: vec![h; outer.len()],
        }
    }

    /// The sheet's view.
    #[must_use]
    pub fn sheet(&self) -> Sheet<'_> {
        Sheet {
            positions: &self.positions,
            normals: &self.normals,
            radii: &self.radii,
        }
    }
}

/// The chain's points for the density grid: positions, kernel radii and weights.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ChainPoints {
    pub positions: Vec<Vec3>,
    pub radii: Vec<f32>,
    pub weights: Vec<f32>,
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `surely_thick` is a bound: wherever it says so, the eigen solver's two smallest
    /// eigenvalues are at least 0.15 apart in ratio (`flat_normal`'s flatness 0), over
    /// covariances from flat (a layer's) to isotropic, rotated; and it does skip the bulk.
    #[test]
    fn surely_thick_only_where_the_solver_finds_no_flatness() {
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let mut unit = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 40) as f32 / (1u64 << 24) as f32
        };
        let (mut skipped, mut flat_kept) = (0, 0);
        for k in 0..20_000 {
            // eigenvalues: the smallest from 0 to the others' size, the two others alike
            let l = [unit() * unit(), 0.5 + unit(), 0.5 + unit()];
            let q = glam::Quat::from_euler(
                glam::EulerRot::XYZ,
                6.3 * unit(),
                6.3 * unit(),
                6.3 * unit(),
            );
            let r = glam::Mat3::from_quat(q);
            let c =
                r * glam::Mat3::from_diagonal(Vec3::from(l) * (1.0 + 9.0 * unit())) * r.transpose();
            let (values, _) = crate::linalg::symmetric_eigen(c);
            let ratio = values[0] / values[1];
            if surely_thick(c) {
                skipped += 1;
                assert!(ratio >= 0.15, "case {k}: skipped at ratio {ratio} ({l:?})");
            } else if ratio < 0.15 {
                flat_kept += 1;
            }
        }
        assert!(
            skipped > 5_000 && flat_kept > 1_000,
            "{skipped} skipped, {flat_kept} kept"
        );
        assert!(surely_thick(glam::Mat3::IDENTITY));
    }

    /// The Jacobi steps give the same weights, bit for bit, with the sheet's terms listed once
    /// and with the cells searched at every step: a wavy sheet of points of two radii over a
    /// block of interior particles, with lone points beside it.
    #[test]
    fn listed_terms_give_the_same_weights() {
        let s = 0.1f32;
        let mut positions = Vec::new();
        let mut radii = Vec::new();
        for i in 0..12 {
            for j in 0..12 {
                for k in 0..4 {
                    positions.push(Vec3::new(i as f32, -(k as f32) - 1.0, j as f32) * s);
                    radii.push(2.0 * s);
                }
            }
        }
        let interior = positions.len();
        let mut normals = Vec::new();
        for i in 0..40 {
            for j in 0..40 {
                let (x, z) = (i as f32 * 0.3 * s, j as f32 * 0.3 * s);
                positions.push(Vec3::new(x, -0.5 * s + 0.05 * s * (7.0 * x).sin(), z));
                radii.push(if i < 20 { 0.6 * s } else { 0.35 * s });
                normals.push(Vec3::new(-0.05 * (7.0 * x).cos(), 1.0, 0.0).normalize());
            }
        }
        for i in 0..3 {
            positions.push(Vec3::new(5.0 + i as f32, 3.0, 0.0));
            radii.push(0.6 * s);
            normals.push(Vec3::Y);
        }
        let points = Points::with_radii(&positions, &radii, 2.0 * s);
        let kernel = Kernel::Wyvill;
        let tau = 0.75 * kernel.peak(2.0 * s);
        let args = (s, kernel, tau);
        let lists = &mut TermLists::default();
        let listed =
            weights_listing(points, interior, &normals, args, (usize::MAX, lists)).unwrap();
        let searched = weights_listing(points, interior, &normals, args, (0, lists)).unwrap();
        assert_eq!(listed, searched);
        // the lists kept from the first run (their terms cleared and made again): the same
        let again = weights_listing(points, interior, &normals, args, (usize::MAX, lists)).unwrap();
        assert_eq!(listed, again);
        assert!(listed[interior..].iter().any(|&w| w != 1.0));
    }
}
