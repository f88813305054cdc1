//! Surfels on the CPU: the crossings plane by plane ([`SurfelExtractor`]), projected onto the
//! exact iso-surface ([`ExactDensity`]); see the [module](super) for the method.

use glam::Vec3;
use rayon::prelude::*;

use super::{CONVERGED, SurfelError, SurfelParams, Surfels, Viewpoints, crossing_t, iso_of};
use crate::density::bits::{self, Bits};
use crate::density::{DensityGrid, GridSpec, Kernel, Points};
use crate::neighbours::CellGrid;

/// The exact density of the particles and its gradient at a point.
///
/// Points are grouped by effective radius (each group in a cell grid of its own radius), so that
/// a query near a fine sheet of refined points does not visit them through the coarse cells of
/// the interior particles' radius. Radii that differ by less than a factor of 2^(1/4) share a
/// group (its cells sized for the largest); the sum still uses each point's own radius.
pub struct ExactDensity<'a> {
    points: Points<'a>,
    groups: Vec<Group>,
    kernel: Kernel,
}

/// Bits of a term code ([`ExactDensity::value_and_kernels`]) that name the group.
const TERM_GROUP_BITS: u32 = 4;

/// Points of similar radius in a cell grid of the largest of them.
struct Group {
    reach: f32,
    grid: CellGrid,
    /// group slot -> point index
    members: Vec<u32>,
    /// the radius of each point in the grid's cell order (`None`: every point has `h`)
    cell_radii: Option<Vec<f32>>,
    /// the weight of each point in the grid's cell order (`None`: every point has 1)
    cell_weights: Option<Vec<f32>>,
}

impl Group {
    /// The radius and the weight of the point in cell-order slot `slot` (`h` and 1 where the
    /// group has none of its own).
    #[inline(always)]
    fn radius_and_weight(&self, slot: usize, h: f32) -> (f32, f32) {
        let r = self.cell_radii.as_ref().map_or(h, |r| r[slot]);
        let w = self.cell_weights.as_ref().map_or(1.0, |w| w[slot]);
        (r, w)
    }
}

impl<'a> ExactDensity<'a> {
    /// Indexes the particles for density queries with effective radius `h`.
    pub fn new(positions: &'a [Vec3], kernel: Kernel, h: f32) -> Result<Self, SurfelError> {
        Self::of(Points::uniform(positions, h), kernel)
    }

    /// Indexes points with a radius each (see [`Points`] for how they combine).
    pub fn of(points: Points<'a>, kernel: Kernel) -> Result<Self, SurfelError> {
        points.check()?;
        let mut groups = Vec::new();
        for (reach, run) in radius_groups(&points) {
            if points.radii.is_none() && points.weights.is_none() {
                // every point of radius `h` and weight 1: one group over the positions as given
                let grid = CellGrid::new(points.positions, reach)?;
                groups.push(Group {
                    reach,
                    grid,
                    members: run,
                    cell_radii: None,
                    cell_weights: None,
                });
                continue;
            }
            let pos: Vec<Vec3> = run
                .par_iter()
                .map(|&i| points.positions[i as usize])
                .collect();
            let grid = CellGrid::new(&pos, reach)?;
            let in_cells = |values: &(dyn Fn(usize) -> f32 + Sync)| -> Vec<f32> {
                grid.order()
                    .par_iter()
                    .map(|&slot| values(run[slot as usize] as usize))
                    .collect()
            };
            let cell_radii = Some(in_cells(&|i| points.radius(i)));
            let cell_weights = points.weights.map(|w| in_cells(&|i| w[i]));
            groups.push(Group {
                reach,
                grid,
                members: run,
                cell_radii,
                cell_weights,
            });
        }
        Ok(Self {
            points,
            groups,
            kernel,
        })
    }

    /// Density and its gradient at `x`, both analytic ([`Kernel::weighted_and_gradient`]), in
    /// one pass over the points.
    #[must_use]
    pub fn value_and_gradient(&self, x: Vec3) -> (f32, Vec3) {
        let mut sum = 0.0;
        let mut grad = Vec3::ZERO;
        let h = self.points.h;
        for g in &self.groups {
            // the positions and radii in the grid's cell order: the same terms in the same order
            // as through the point indices, without the indirection; only the points within
            // reach, which the scan lists without a branch (a gradient for every point scanned
            // cost more than it saved), as in the value sums
            g.grid.for_each_slot_within(x, g.reach, |slot, q| {
                let (r, w) = g.radius_and_weight(slot, h);
                let (v, dv) = self.kernel.weighted_and_gradient(x - q, r, h);
                sum += w * v;
                grad += w * dv;
            });
        }
        (sum, grad)
    }

    /// Sums the points with `weights` (one per point, in the points' order) from now on, in
    /// [`Self::value`] and [`Self::value_and_gradient`] (not in [`Self::points`]): the index
    /// kept, only the weights' copies in the grids' cell order made anew, for sums that change
    /// their weights step by step (the boundary calibration's Jacobi steps).
    ///
    /// # Panics
    /// When `weights` has another length than the points.
    pub fn reweight(&mut self, weights: &[f32]) {
        assert_eq!(weights.len(), self.points.len(), "one weight per point");
        for g in &mut self.groups {
            let w: Vec<f32> = g
                .grid
                .order()
                .par_iter()
                .map(|&slot| weights[g.members[slot as usize] as usize])
                .collect();
            g.cell_weights = Some(w);
        }
    }

    /// Calls `visit(j, x - x_j, r_j)` for every point `j` whose own radius `r_j` reaches `x`
    /// (the points the density at `x` sums).
    pub fn for_each_reaching(&self, x: Vec3, mut visit: impl FnMut(usize, Vec3, f32)) {
        let p = &self.points;
        for g in &self.groups {
            g.grid.for_each_within(x, g.reach, |slot| {
                let j = g.members[slot as usize] as usize;
                let d = x - p.positions[j];
                let r = p.radius(j);
                if d.length_squared() < r * r {
                    visit(j, d, r);
                }
            });
        }
    }

    /// The groups of similar radii the points are indexed in: each group's reach (its largest
    /// radius) and its points (indices into [`Self::points`]).
    pub fn groups(&self) -> impl Iterator<Item = (f32, &[u32])> {
        self.groups.iter().map(|g| (g.reach, g.members.as_slice()))
    }

    /// The points the densities are summed over.
    #[must_use]
    pub fn points(&self) -> &Points<'a> {
        &self.points
    }

    /// The density function.
    #[must_use]
    pub fn kernel(&self) -> Kernel {
        self.kernel
    }

    /// [`Self::value`] at `x`, bit for bit, appending the terms it sums whose kernel is not
    /// zero, in the order it visits them: each as a code (its group and slot) to `codes` and
    /// its kernel (the term without its weight) to `kernels`, which
    /// [`ExactDensity::value_of_kernels`] sums again with the weights as they are then: for sums
    /// at the same place with weights that change ([`Self::reweight`]), each then without the
    /// cell search and the kernels. `None`, appending nothing, when the points lie in more
    /// groups or slots than a code holds (16 groups of radius, 2^28 points a group).
    pub fn value_and_kernels(
        &self,
        x: Vec3,
        codes: &mut Vec<u32>,
        kernels: &mut Vec<f32>,
    ) -> Option<f32> {
        if !self.codes_fit() {
            return None;
        }
        let mut sum = 0.0;
        let h = self.points.h;
        for (gi, g) in self.groups.iter().enumerate() {
            // only the points within the group's reach, which the scan lists without a branch:
            // every other point's kernel is zero (the reach is at least its radius) and would
            // add +0 to a sum of terms >= 0
            g.grid.for_each_slot_within(x, g.reach, |slot, q| {
                let (w, k) = self.weight_and_kernel(g, slot, q, x, h);
                // the term is the weight times the kernel, listed apart (a zero one left out)
                sum += w * k;
                if k != 0.0 {
                    codes.push(((slot as u32) << TERM_GROUP_BITS) | gi as u32);
                    kernels.push(k);
                }
            });
        }
        Some(sum)
    }

    /// Whether every point's term fits a code of [`Self::value_and_kernels`].
    fn codes_fit(&self) -> bool {
        self.groups.len() <= 1 << TERM_GROUP_BITS
            && self
                .groups
                .iter()
                .all(|g| g.members.len() < 1 << (32 - TERM_GROUP_BITS))
    }

    /// [`Self::value`] at the place where [`Self::value_and_kernels`] listed `codes` and
    /// `kernels`, with the weights as they are now: the same nonzero terms in the same order,
    /// so the same sum bit for bit.
    #[must_use]
    pub fn value_of_kernels(&self, codes: &[u32], kernels: &[f32]) -> f32 {
        let mut sum = 0.0;
        for (&code, &k) in codes.iter().zip(kernels) {
            let g = &self.groups[(code & ((1 << TERM_GROUP_BITS) - 1)) as usize];
            let slot = (code >> TERM_GROUP_BITS) as usize;
            let w = g.cell_weights.as_ref().map_or(1.0, |w| w[slot]);
            sum += w * k;
        }
        sum
    }

    /// [`Self::value`] at `x` where it is below `limit`, bit for bit; elsewhere a partial sum
    /// of the same terms in the same order that is at least `limit` (the sum stops there: every
    /// term is at least zero with weights at least zero, and a float sum of such terms only
    /// grows, so the value is at least `limit` too). For densities tested against a bound that
    /// most points pass early (how alone a refined point is, in the boundary calibration).
    #[must_use]
    pub fn value_up_to(&self, x: Vec3, limit: f32) -> f32 {
        let mut sum = 0.0;
        let h = self.points.h;
        for g in &self.groups {
            // the points within the group's reach (every other adds +0), as in `value`
            let reached = g.grid.try_for_each_slot_within(x, g.reach, |slot, q| {
                sum += self.term(g, slot, q, x, h);
                if sum >= limit {
                    std::ops::ControlFlow::Break(())
                } else {
                    std::ops::ControlFlow::Continue(())
                }
            });
            if reached.is_break() {
                break;
            }
        }
        sum
    }

    /// Density at `x`: the sum of the kernels of the points whose radius reaches it.
    #[must_use]
    pub fn value(&self, x: Vec3) -> f32 {
        let mut sum = 0.0;
        let h = self.points.h;
        for g in &self.groups {
            // only the points within the group's reach, which the scan lists without a branch:
            // every other point's kernel is zero (the reach is at least its radius) and would
            // add +0 to a sum of terms >= 0, so the sum is every point's, bit for bit
            g.grid.for_each_slot_within(x, g.reach, |slot, q| {
                sum += self.term(g, slot, q, x, h);
            });
        }
        sum
    }

    /// The term of group `g`'s point in cell-order slot `slot` (at `q`) at `x`: its weight
    /// times its kernel ([`Self::weight_and_kernel`]), the same operations in every sum, so
    /// that they agree bit for bit.
    #[inline(always)]
    fn term(&self, g: &Group, slot: usize, q: Vec3, x: Vec3, h: f32) -> f32 {
        let (w, k) = self.weight_and_kernel(g, slot, q, x, h);
        w * k
    }

    /// The weight and the kernel ([`Kernel::weighted_r2`] of its own radius, zero beyond it)
    /// at `x` of group `g`'s point in cell-order slot `slot` (at `q`).
    #[inline(always)]
    fn weight_and_kernel(&self, g: &Group, slot: usize, q: Vec3, x: Vec3, h: f32) -> (f32, f32) {
        let (r, w) = g.radius_and_weight(slot, h);
        (w, self.kernel.weighted_r2((q - x).length_squared(), r, h))
    }
}

/// The groups of similar radius [`ExactDensity`] indexes `points` in, each as its reach (its
/// largest radius) and its points' indices: quarter octaves of the radius (so a group's cells
/// are at most 19 % too large), in the order of the radii, each group's points in their own
/// order; one group of reach `h` when the points have no radii of their own. For indexes of the
/// same groups built elsewhere (the ray caster's grids on the GPU).
#[must_use]
pub fn radius_groups(points: &Points<'_>) -> Vec<(f32, Vec<u32>)> {
    let Some(radii) = points.radii else {
        return vec![(points.h, (0..points.len() as u32).collect())];
    };
    let key = |r: f32| (r.log2() * 4.0).floor() as i32;
    // each point's key once (a key per comparison cost a logarithm each)
    let keys: Vec<i32> = radii.par_iter().map(|&r| key(r)).collect();
    // each group's points picked out in order by one pass, rather than every point sorted by
    // key (a frame's points have a few radii, the interior's and one per level, mostly in runs)
    let mut runs: Vec<(i32, Vec<u32>)> = Vec::new();
    let mut last = 0;
    for (i, &k) in keys.iter().enumerate() {
        if runs.get(last).is_none_or(|r| r.0 != k) {
            last = runs.iter().position(|r| r.0 == k).unwrap_or_else(|| {
                runs.push((k, Vec::new()));
                runs.len() - 1
            });
        }
        runs[last].1.push(i as u32);
    }
    runs.sort_unstable_by_key(|r| r.0);
    runs.into_iter()
        .map(|(_, run)| {
            let reach = run.iter().map(|&i| radii[i as usize]).fold(0.0, f32::max);
            (reach, run)
        })
        .collect()
}

/// The z planes around plane `k` that its crossings read: `k - 2`, `k - 1` (none at the first
/// planes), `k` and `k + 1` (none past the last, or not yet known: see [`plane_crossings`]).
struct Around<'p> {
    below2: Option<&'p [f32]>,
    below: Option<&'p [f32]>,
    plane: &'p [f32],
    above: Option<&'p [f32]>,
}

/// The crossings of the iso-value `iso` on the edges of z plane `k` (`around.plane`, `nx * ny`
/// values): its x and y edges, and its z edges down to the plane below (none at the first), in
/// (row, point, then x, y and z edge) order, each placed by [`crossing_t`] on the values along
/// its line. With `around.above` unknown (`pending`), the z edges are placed linearly and
/// their places in the list and points `(i, j)` are returned, to be placed again once the
/// plane above is known ([`z_crossing`]). The crossing edges are found from the planes' inside
/// bits (`bits`: the plane's, and the plane below's where there is one;
/// [`crate::density::bits`]), a few word operations per 64 points: the dam break's grid at two
/// steps, 174 x 223 x 94 points, 20-22 -> 8.3-8.8 ms on one thread (the crossings' places most of
/// the rest) against comparing each edge's two values (`scan_by_edges`, the oracle of the
/// tests), the same crossings in the same order.
fn plane_crossings(
    spec: &GridSpec,
    iso: f32,
    k: u32,
    (around, bits): (&Around<'_>, PlaneBits<'_>),
    pending: bool,
) -> (Vec<Vec3>, Vec<Pending>) {
    let [nx, ny, _] = spec.dims;
    let plane = around.plane;
    let at = |i: u32, j: u32| spec.point(i, j, k);
    let mut found = Vec::new();
    let mut later = Vec::new();
    let (here, under) = bits;
    debug_assert_eq!(
        around.below.is_some(),
        under.is_some(),
        "bits for the plane below"
    );
    for j in 0..ny {
        let row = here.row(j);
        let up = (j + 1 < ny).then(|| here.row(j + 1));
        let down = around
            .below
            .zip(under)
            .map(|(values, b)| (values, b.row(j)));
        for w in 0..here.words {
            let x = (row[w] ^ bits::next_point(row, w)) & bits::below(w, nx - 1);
            let y = up.map_or(0, |u| row[w] ^ u[w]);
            let z = down.map_or(0, |(_, d)| row[w] ^ d[w]);
            for i in bits::points_of(x | y | z, w) {
                let bit = 1u64 << (i % 64);
                let (iu, ju) = (i as usize, j as usize);
                let p = iu + nx as usize * ju;
                let v = plane[p];
                if x & bit != 0 {
                    let outer = beside(iu, nx as usize, |c| plane[c + nx as usize * ju]);
                    let t = crossing_t(v, plane[p + 1], outer, iso);
                    found.push(at(i, j).lerp(at(i + 1, j), t));
                }
                if y & bit != 0 {
                    let outer = beside(ju, ny as usize, |c| plane[iu + nx as usize * c]);
                    let t = crossing_t(v, plane[p + nx as usize], outer, iso);
                    found.push(at(i, j).lerp(at(i, j + 1), t));
                }
                if let Some((below, _)) = down
                    && z & bit != 0
                {
                    if pending {
                        later.push((found.len(), i, j));
                    }
                    found.push(z_crossing(spec, iso, k, below, around, (i, j)));
                }
            }
        }
    }
    (found, later)
}

/// A plane's inside bits and those of the plane below it, where there is one
/// ([`plane_crossings`]).
type PlaneBits<'b> = (&'b Bits, Option<&'b Bits>);

/// [`plane_crossings`] by comparing the two values of each edge: the first scan, the oracle of
/// the bit scan's tests.
#[cfg(test)]
fn scan_by_edges(
    spec: &GridSpec,
    iso: f32,
    k: u32,
    around: &Around<'_>,
    pending: bool,
) -> (Vec<Vec3>, Vec<Pending>) {
    let [nx, ny, _] = spec.dims;
    let (nx, ny) = (nx as usize, ny as usize);
    let plane = around.plane;
    let at = |i: usize, j: usize| spec.point(i as u32, j as u32, k);
    let cross = |a: f32, b: f32| (a < iso) != (b < iso);
    let mut found = Vec::new();
    let mut later = Vec::new();
    for j in 0..ny {
        for i in 0..nx {
            let p = i + nx * j;
            let v = plane[p];
            if i + 1 < nx {
                let w = plane[p + 1];
                if cross(v, w) {
                    let outer = beside(i, nx, |c| plane[c + nx * j]);
                    found.push(at(i, j).lerp(at(i + 1, j), crossing_t(v, w, outer, iso)));
                }
            }
            if j + 1 < ny {
                let w = plane[p + nx];
                if cross(v, w) {
                    let outer = beside(j, ny, |c| plane[i + nx * c]);
                    found.push(at(i, j).lerp(at(i, j + 1), crossing_t(v, w, outer, iso)));
                }
            }
            if let Some(below) = around.below
                && cross(below[p], v)
            {
                if pending {
                    later.push((found.len(), i as u32, j as u32));
                }
                found.push(z_crossing(
                    spec,
                    iso,
                    k,
                    below,
                    around,
                    (i as u32, j as u32),
                ));
            }
        }
    }
    (found, later)
}

/// The values one point before and one after the edge from point `c` to `c + 1` of a line of
/// `n` grid points (`at(c')`: the value at point `c'`), which place its crossing with the
/// edge's own ([`crossing_t`]); `None` where the edge touches the grid's border.
#[inline]
fn beside(c: usize, n: usize, at: impl Fn(usize) -> f32) -> Option<(f32, f32)> {
    (c >= 1 && c + 2 < n).then(|| (at(c - 1), at(c + 2)))
}

/// The crossing on the z edge from point `(i, j)` of plane `k - 1` (`below`, `around.below`)
/// to plane `k` ([`plane_crossings`]).
fn z_crossing(
    spec: &GridSpec,
    iso: f32,
    k: u32,
    below: &[f32],
    around: &Around<'_>,
    (i, j): (u32, u32),
) -> Vec3 {
    let p = i as usize + spec.dims[0] as usize * j as usize;
    let (u, v) = (below[p], around.plane[p]);
    let outer = around.below2.zip(around.above).map(|(b2, a)| (b2[p], a[p]));
    spec.point(i, j, k - 1)
        .lerp(spec.point(i, j, k), crossing_t(u, v, outer, iso))
}

/// A z crossing placed before the plane above it was known: its place in the list and its
/// point `(i, j)` ([`plane_crossings`]).
type Pending = (usize, u32, u32);

/// Collects edge crossings plane by plane.
pub struct SurfelExtractor {
    spec: GridSpec,
    iso: f32,
    /// The last planes pushed (at most three, the latest last) with the index of the first.
    kept: (u32, Vec<Vec<f32>>),
    /// The z crossings of the latest plane placed before the plane above it was known: their
    /// places in `crossings` and points, placed again by the next push.
    pending: Vec<Pending>,
    crossings: Vec<Vec3>,
}

impl SurfelExtractor {
    /// An extractor for a grid and an absolute iso-value.
    #[must_use]
    pub fn new(spec: GridSpec, iso: f32) -> Self {
        Self {
            spec,
            iso,
            kept: (0, Vec::new()),
            pending: Vec::new(),
            crossings: Vec::new(),
        }
    }

    /// Takes the next z plane (`k` in increasing order, `nx * ny` values); copies of the
    /// latest three planes are kept.
    pub fn push_plane(&mut self, k: u32, plane: &[f32]) {
        self.push_planes(k, plane);
    }

    /// The crossings of a sparse grid ([`crate::density::sparse`]): the edges the evaluated
    /// blocks own (every edge lies in the closed range of the block holding its lower end, and
    /// an empty or inside block's closed range is all 0 or all inside), found in parallel and
    /// put in the order
    /// [`Self::push_plane`] finds them in (plane, row, point, then x, y and z edge), so the
    /// surfels are the dense grid's, in the same order.
    #[must_use]
    pub fn from_sparse(grid: &crate::density::SparseGrid, iso: f32) -> Self {
        use crate::density::sparse::BLOCK;
        let spec = grid.spec;
        let [nx, ny, nz] = spec.dims;
        let scanned: Vec<[u32; 3]> = grid.evaluated_blocks().collect();
        let b_ = BLOCK as usize;
        let cross = |a: f32, b: f32| (a < iso) != (b < iso);
        let mut found: Vec<(u64, Vec3)> = scanned
            .par_iter()
            .flat_map_iter(|&b| {
                let mut out = Vec::new();
                // the block's own values read directly, its neighbours' through `at`
                let own = grid.block_values(b).expect("an evaluated block");
                let [i0, j0, k0] = b.map(|c| c * BLOCK);
                for k in k0..(k0 + BLOCK).min(nz) {
                    for j in j0..(j0 + BLOCK).min(ny) {
                        for i in i0..(i0 + BLOCK).min(nx) {
                            let v = own[(i - i0) as usize
                                + b_ * ((j - j0) as usize + b_ * (k - k0) as usize)];
                            let key = |kk: u32, t: u64| {
                                ((u64::from(kk) * u64::from(ny) + u64::from(j)) * u64::from(nx)
                                    + u64::from(i))
                                    * 3
                                    + t
                            };
                            let here = spec.point(i, j, k);
                            // the values one point before and one after the edge, where
                            // the grid has them (every one that is not inside is the dense
                            // grid's; the sparse grid makes those inside exact,
                            // `exact_ends`)
                            if i + 1 < nx {
                                let w = grid.at(i + 1, j, k);
                                if cross(v, w) {
                                    let outer = beside(i as usize, nx as usize, |c| {
                                        grid.at(c as u32, j, k)
                                    });
                                    let t = crossing_t(v, w, outer, iso);
                                    out.push((key(k, 0), here.lerp(spec.point(i + 1, j, k), t)));
                                }
                            }
                            if j + 1 < ny {
                                let w = grid.at(i, j + 1, k);
                                if cross(v, w) {
                                    let outer = beside(j as usize, ny as usize, |c| {
                                        grid.at(i, c as u32, k)
                                    });
                                    let t = crossing_t(v, w, outer, iso);
                                    out.push((key(k, 1), here.lerp(spec.point(i, j + 1, k), t)));
                                }
                            }
                            if k + 1 < nz {
                                let w = grid.at(i, j, k + 1);
                                if cross(v, w) {
                                    let outer = beside(k as usize, nz as usize, |c| {
                                        grid.at(i, j, c as u32)
                                    });
                                    let t = crossing_t(v, w, outer, iso);
                                    out.push((
                                        key(k + 1, 2),
                                        here.lerp(spec.point(i, j, k + 1), t),
                                    ));
                                }
                            }
                        }
                    }
                }
                out
            })
            .collect();
        found.par_sort_unstable_by_key(|c| c.0);
        Self {
            spec,
            iso,
            kept: (0, Vec::new()),
            pending: Vec::new(),
            crossings: found.into_iter().map(|c| c.1).collect(),
        }
    }

    /// Takes a slab of consecutive planes starting at `k0`, as [`crate::density::splat_slabs`]
    /// hands them out.
    pub fn push_slab(&mut self, k0: u32, slab: Vec<f32>) {
        self.push_planes(k0, &slab);
    }

    /// Takes consecutive planes starting at `k0` (`nx * ny` values each), their crossings
    /// found in parallel, plane by plane, in the order [`Self::push_plane`] finds them.
    pub fn push_planes(&mut self, k0: u32, planes: &[f32]) {
        let plane = self.spec.dims[0] as usize * self.spec.dims[1] as usize;
        if plane == 0 || planes.is_empty() {
            return;
        }
        let (spec, iso, nz) = (&self.spec, self.iso, self.spec.dims[2]);
        let count = (planes.len() / plane) as u32;
        let (first_kept, kept) = (self.kept.0, &self.kept.1);
        // plane `k`: of this push, or one of the kept ones
        let plane_at = |k: u32| -> Option<&[f32]> {
            if k >= k0 {
                let d = (k - k0) as usize;
                (d < count as usize).then(|| &planes[d * plane..(d + 1) * plane])
            } else {
                k.checked_sub(first_kept)
                    .and_then(|d| kept.get(d as usize))
                    .map(Vec::as_slice)
            }
        };
        let around = |k: u32| Around {
            below2: k.checked_sub(2).and_then(plane_at),
            below: k.checked_sub(1).and_then(plane_at),
            plane: plane_at(k).expect("a plane of this push"),
            above: (k + 1 < nz).then(|| plane_at(k + 1)).flatten(),
        };
        // the z crossings of the last push's last plane, now that the plane above is known
        // (pushed out of order, the planes do not follow: they keep their linear places)
        if let Some(k) = k0.checked_sub(1)
            && !self.pending.is_empty()
            && let Some(plane) = plane_at(k)
            && let Some(below) = k.checked_sub(1).and_then(plane_at)
        {
            let a = Around {
                below2: k.checked_sub(2).and_then(plane_at),
                below: Some(below),
                plane,
                above: plane_at(k0),
            };
            for &(at, i, j) in &self.pending {
                self.crossings[at] = z_crossing(spec, iso, k, below, &a, (i, j));
            }
        }
        // the inside bits of this push's planes and of the plane below the first, where known
        let first_bits = if k0 > 0 && plane_at(k0 - 1).is_some() {
            k0 - 1
        } else {
            k0
        };
        let plane_bits: Vec<Bits> = (first_bits..k0 + count)
            .into_par_iter()
            .map(|k| Bits::of(plane_at(k).expect("a known plane"), spec.dims[0], iso))
            .collect();
        let bits_at = |k: u32| {
            k.checked_sub(first_bits)
                .and_then(|d| plane_bits.get(d as usize))
        };
        let found: Vec<(Vec<Vec3>, Vec<Pending>)> = (k0..k0 + count)
            .into_par_iter()
            .map(|k| {
                let a = around(k);
                let b = (
                    bits_at(k).expect("this push's plane"),
                    k.checked_sub(1).and_then(bits_at),
                );
                // the last plane's z edges wait for the plane above, unless it is the grid's last
                let pending = a.above.is_none() && k + 1 < nz;
                plane_crossings(spec, iso, k, (&a, b), pending)
            })
            .collect();
        self.pending.clear();
        for (f, later) in found {
            let offset = self.crossings.len();
            self.pending
                .extend(later.into_iter().map(|(at, i, j)| (offset + at, i, j)));
            self.crossings.extend(f);
        }
        // keep the last three planes for the z edges of the next ones: those of the kept ones
        // still wanted where they run on into this push, then this push's, copied into the
        // buffers of the kept planes they replace
        let last = k0 + count - 1;
        let (first_old, old) = (self.kept.0, std::mem::take(&mut self.kept.1));
        let follows = first_old + old.len() as u32 == k0;
        let first = last
            .saturating_sub(2)
            .max(if follows { first_old } else { k0 });
        let mut next = Vec::with_capacity(3);
        let mut spare = Vec::new();
        for (k, values) in (first_old..).zip(old) {
            if k >= first && follows {
                next.push(values);
            } else {
                spare.push(values);
            }
        }
        for k in first.max(k0)..=last {
            let d = (k - k0) as usize;
            let mut buffer: Vec<f32> = spare.pop().unwrap_or_default();
            buffer.clear();
            buffer.extend_from_slice(&planes[d * plane..(d + 1) * plane]);
            next.push(buffer);
        }
        self.kept = (first, next);
    }

    /// Projects the crossings onto the exact iso-surface and returns the surfels.
    pub fn finish(self, density: &ExactDensity<'_>, params: &SurfelParams) -> Surfels {
        self.finish_seen(density, params, None)
    }

    /// The crossings found so far: the surfels [`Self::finish`] makes from them.
    #[must_use]
    pub fn crossings(&self) -> usize {
        self.crossings.len()
    }

    /// [`Self::finish`] without the surfels whose outward normal faces away from every one of
    /// `seen` by more than [`super::HIDDEN_PAST`] ([`Viewpoints::sees`]), judged on the density's
    /// exact gradient at the crossing, the projection's first evaluation (the crossings start
    /// 0.006 cells from the surface on average, [`crossing_t`]; on the double dam break's
    /// crest, a few cells thick, the grid's differences turned a normal more than 37 degrees
    /// off the exact one, measured by the pixels that changed): for a picture drawn from
    /// those viewpoints alone, which never shows them (the EWA splats cull a disk facing away
    /// from the eye), they are not projected further nor handed on. The others are the same
    /// surfels in the same order.
    pub fn finish_seen(
        self,
        density: &ExactDensity<'_>,
        params: &SurfelParams,
        seen: Option<&Viewpoints>,
    ) -> Surfels {
        let iso = self.iso;
        let spacing = self.spec.spacing;
        let (positions, normals): (Vec<Vec3>, Vec<Vec3>) = self
            .crossings
            .par_iter()
            .filter_map(|&start| {
                let mut x = start;
                let mut g = Vec3::ZERO;
                for step in 0..params.newton_steps {
                    let (v, grad) = density.value_and_gradient(x);
                    if step == 0 && seen.is_some_and(|s| !s.sees(x, -grad)) {
                        return None;
                    }
                    g = grad;
                    let g2 = grad.length_squared();
                    if g2 <= f32::MIN_POSITIVE {
                        break;
                    }
                    // a Newton step along the gradient, never more than half a cell
                    let step = (grad * ((iso - v) / g2)).clamp_length_max(0.5 * spacing);
                    x += step;
                    // converged: Newton's steps shrink quadratically, so the next would move
                    // the point by about 1e-4 cells ([`CONVERGED`])
                    if step.length_squared() < (CONVERGED * spacing).powi(2) {
                        break;
                    }
                }
                if params.newton_steps == 0 {
                    g = density.value_and_gradient(x).1;
                    if seen.is_some_and(|s| !s.sees(x, -g)) {
                        return None;
                    }
                }
                Some((x, (-g).normalize_or_zero()))
            })
            .unzip();
        let radii = vec![spacing; positions.len()];
        Surfels {
            positions,
            normals,
            radii,
            iso,
        }
    }
}

/// [`extract_points`] on a sparse grid ([`crate::density::sparse`]): the same surfels as on the
/// dense grid, in the same order.
pub fn extract_sparse(
    grid: &crate::density::SparseGrid,
    points: Points<'_>,
    kernel: Kernel,
    params: &SurfelParams,
) -> Result<Surfels, SurfelError> {
    Ok(extract_sparse_seen(grid, points, kernel, params, None)?.0)
}

/// [`extract_sparse`] without the surfels `seen` does not see ([`SurfelExtractor::finish_seen`]),
/// and how many it left out.
pub fn extract_sparse_seen(
    grid: &crate::density::SparseGrid,
    points: Points<'_>,
    kernel: Kernel,
    params: &SurfelParams,
    seen: Option<&Viewpoints>,
) -> Result<(Surfels, usize), SurfelError> {
    let iso = iso_of(points.h, kernel, params)?;
    let density = ExactDensity::of(points, kernel)?;
    let extractor = SurfelExtractor::from_sparse(grid, iso);
    let crossings = extractor.crossings();
    let surfels = extractor.finish_seen(&density, params, seen);
    let hidden = crossings - surfels.len();
    Ok((surfels, hidden))
}

/// The absolute iso-value of `params`: `iso_fraction` of the peak `F(0, h)`.
/// Extracts the surfels of a whole density grid.
pub fn extract(
    grid: &DensityGrid,
    particles: &[Vec3],
    kernel: Kernel,
    h: f32,
    params: &SurfelParams,
) -> Result<Surfels, SurfelError> {
    extract_points(grid, Points::uniform(particles, h), kernel, params)
}

/// [`extract`] for points with a radius each; the iso-value is `iso_fraction` of the peak
/// `F(0, h)` of the reference radius, which every point shares (see [`Points`]).
pub fn extract_points(
    grid: &DensityGrid,
    points: Points<'_>,
    kernel: Kernel,
    params: &SurfelParams,
) -> Result<Surfels, SurfelError> {
    Ok(extract_points_seen(grid, points, kernel, params, None)?.0)
}

/// [`extract_points`] without the surfels `seen` does not see ([`SurfelExtractor::finish_seen`]),
/// and how many it left out.
pub fn extract_points_seen(
    grid: &DensityGrid,
    points: Points<'_>,
    kernel: Kernel,
    params: &SurfelParams,
    seen: Option<&Viewpoints>,
) -> Result<(Surfels, usize), SurfelError> {
    let iso = iso_of(points.h, kernel, params)?;
    let density = ExactDensity::of(points, kernel)?;
    let mut extractor = SurfelExtractor::new(grid.spec, iso);
    extractor.push_planes(0, &grid.values);
    let crossings = extractor.crossings();
    let surfels = extractor.finish_seen(&density, params, seen);
    let hidden = crossings - surfels.len();
    Ok((surfels, hidden))
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// The bit scan finds the edge scan's crossings, in its order, bit for bit: rows of 1 to 130
    /// points (words' ends), values on the iso-value itself, NaN, the first and last planes,
    /// with the plane above known or not.
    #[test]
    fn bit_scan_equals_the_edge_scan() {
        let mut rng = ChaCha8Rng::seed_from_u64(0xb175);
        let iso = 0.5;
        for dims in [
            [1, 1, 1],
            [1, 5, 3],
            [63, 4, 3],
            [64, 3, 4],
            [65, 5, 3],
            [130, 6, 5],
        ] {
            let spec = GridSpec {
                origin: Vec3::new(-1.0, 0.25, 2.0),
                spacing: 0.1,
                dims,
            };
            let [nx, ny, nz] = dims.map(|d| d as usize);
            let values: Vec<f32> = (0..nx * ny * nz)
                .map(|_| match rng.random_range(0..20) {
                    0 => iso,
                    1 => f32::NAN,
                    _ => rng.random_range(0.0..1.0),
                })
                .collect();
            let plane = |k: usize| &values[k * nx * ny..(k + 1) * nx * ny];
            let bits: Vec<Bits> = (0..nz)
                .map(|k| Bits::of(plane(k), nx as u32, iso))
                .collect();
            let mut found = 0;
            for k in 0..nz {
                let around = Around {
                    below2: k.checked_sub(2).map(plane),
                    below: k.checked_sub(1).map(plane),
                    plane: plane(k),
                    above: (k + 1 < nz).then(|| plane(k + 1)),
                };
                let b = (&bits[k], k.checked_sub(1).map(|d| &bits[d]));
                for pending in [false, true] {
                    let (a, later_a) = plane_crossings(&spec, iso, k as u32, (&around, b), pending);
                    let (e, later_e) = scan_by_edges(&spec, iso, k as u32, &around, pending);
                    let bits_of = |v: &[Vec3]| -> Vec<[u32; 3]> {
                        v.iter().map(|p| p.to_array().map(f32::to_bits)).collect()
                    };
                    assert_eq!(bits_of(&a), bits_of(&e), "dims {dims:?}, plane {k}");
                    assert_eq!(later_a, later_e, "dims {dims:?}, plane {k}");
                    found += a.len();
                }
            }
            if nx * ny > 1 {
                assert!(found > 0, "dims {dims:?}: some crossings to compare");
            }
        }
    }
}
