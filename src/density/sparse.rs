//! The density grid stored sparse: blocks of [`BLOCK`]^3 grid points (as splashsurf and OpenVDB
//! store theirs), evaluated only where the iso-surface can be, so that the cost follows the
//! surface's area and not the fluid's volume.
//!
//! Every block is one of three kinds ([`BlockState`]):
//! - **empty**: no point's ball reaches any grid point of the block or of the faces it shares
//!   with its upper neighbours (its closed range `[b B, b B + B]^3`); every such value is exactly
//!   0, as the dense grid's;
//! - **inside**: every grid point of that closed range lies in an interior voxel (label 0) of the
//!   LNM narrow band ([`crate::lnm`]), whose voxels are at least as wide as the largest radius:
//!   deep in the fluid, its values are not computed and read as `inside` (a value above the
//!   iso-value);
//! - **evaluated**: every other block; its values are the dense grid's, bit for bit (the same
//!   [`super::cpu`] splat, the points added in the same index order), except at its points that
//!   lie in interior voxels, which read as `inside` too.
//!
//! Why that keeps the surfels: an edge of the grid crosses the iso-value only between two points
//! on either side of it; every edge lies in the closed range of the block that holds its lower
//! end, so a block whose closed range is all zero or all inside owns no crossing, and the
//! extraction ([`crate::surfels::SurfelExtractor::from_sparse`]) scans only the evaluated
//! blocks. An inside point that ends a crossing edge (next to a point below the iso-value) gets
//! its exact value, the dense grid's, so that edge's surfel is placed as on the dense grid. The
//! one assumption is the band's: an interior voxel's density is above the iso-value, which fails
//! only for a cavity smaller than a voxel; tested on analytic shapes and both real files.
//!
//! Finding the blocks costs little: the points are sorted into the blocks by one counting sort,
//! a block's candidates are the points of the blocks within reach, the interior blocks come from
//! the band's interior voxels. The evaluated blocks are filled in parallel, each on its own, so
//! the result does not depend on the thread count.

use glam::Vec3;
use rayon::prelude::*;

use super::cpu::{Window, column, splat_disk};
use super::{DensityError, DensityGrid, GridSpec, Kernel, Points};
use crate::lnm::NarrowBand;

/// Grid points along each edge of a block.
pub const BLOCK: u32 = 8;
const B: usize = BLOCK as usize;
/// Values per block.
pub const BLOCK_VALUES: usize = B * B * B;

const EMPTY: u32 = u32::MAX;
const INSIDE: u32 = u32::MAX - 1;

/// What a block holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BlockState {
    /// Every value 0.
    Empty,
    /// Deep inside: every value reads as [`SparseGrid::inside`].
    Inside,
    /// Evaluated: the slot of its values.
    Evaluated(u32),
}

/// A density grid in blocks, only the blocks near the surface evaluated.
#[derive(Clone, Debug, PartialEq)]
pub struct SparseGrid {
    /// The grid, as the dense one's.
    pub spec: GridSpec,
    /// Blocks along x, y and z (`ceil(dims / BLOCK)`).
    pub blocks: [u32; 3],
    /// The value the inside blocks read as.
    pub inside: f32,
    /// Per block (x fastest): [`EMPTY`], [`INSIDE`] or the slot of its values.
    states: Vec<u32>,
    /// The evaluated blocks, in block order.
    evaluated: Vec<u32>,
    /// `BLOCK_VALUES` per evaluated block, x fastest inside a block; the points past the grid's
    /// last plane stay 0.
    values: Vec<f32>,
    /// Per evaluated block, one bit per value: the point lies in an interior voxel and reads as
    /// `inside` (not evaluated).
    interior: Vec<[u64; 8]>,
}

impl SparseGrid {
    fn block_index(&self, b: [u32; 3]) -> usize {
        b[0] as usize
            + self.blocks[0] as usize * (b[1] as usize + self.blocks[1] as usize * b[2] as usize)
    }

    /// What block `b` holds.
    #[must_use]
    pub fn state(&self, b: [u32; 3]) -> BlockState {
        match self.states[self.block_index(b)] {
            EMPTY => BlockState::Empty,
            INSIDE => BlockState::Inside,
            slot => BlockState::Evaluated(slot),
        }
    }

    /// The evaluated blocks' coordinates, in slot order: block order (x fastest), then the inside
    /// blocks that became evaluated for an exact value at a crossing, in block order.
    pub fn evaluated_blocks(&self) -> impl ExactSizeIterator<Item = [u32; 3]> + '_ {
        self.evaluated.iter().map(|&b| self.coord(b as usize))
    }

    fn coord(&self, b: usize) -> [u32; 3] {
        let [bx, by, _] = self.blocks.map(|n| n as usize);
        [
            (b % bx) as u32,
            ((b / bx) % by) as u32,
            (b / (bx * by)) as u32,
        ]
    }

    /// Blocks in each state: (empty, inside, evaluated).
    #[must_use]
    pub fn counts(&self) -> (usize, usize, usize) {
        let inside = self.states.iter().filter(|&&s| s == INSIDE).count();
        let evaluated = self.evaluated.len();
        (self.states.len() - inside - evaluated, inside, evaluated)
    }

    /// Grid points evaluated (every point of the evaluated blocks that lies in the grid).
    #[must_use]
    pub fn evaluated_points(&self) -> usize {
        let [nx, ny, nz] = self.spec.dims;
        self.evaluated_blocks()
            .zip(&self.interior)
            .map(|(b, mask)| {
                let span = |c: u32, n: u32| (n - c * BLOCK).min(BLOCK) as usize;
                span(b[0], nx) * span(b[1], ny) * span(b[2], nz)
                    - mask.iter().map(|w| w.count_ones() as usize).sum::<usize>()
            })
            .sum()
    }

    /// Bytes held: the values of the evaluated blocks and one state per block.
    #[must_use]
    pub fn bytes(&self) -> usize {
        4 * (self.values.len() + self.states.len() + self.evaluated.len())
            + 64 * self.interior.len()
    }

    /// Whether grid point `(i, j, k)` was evaluated: its block is, and the point lies outside
    /// the band's interior voxels.
    #[must_use]
    pub fn is_evaluated(&self, i: u32, j: u32, k: u32) -> bool {
        match self.state([i / BLOCK, j / BLOCK, k / BLOCK]) {
            BlockState::Evaluated(slot) => {
                let l =
                    (i % BLOCK) as usize + B * ((j % BLOCK) as usize + B * (k % BLOCK) as usize);
                self.interior[slot as usize][l / 64] >> (l % 64) & 1 == 0
            }
            _ => false,
        }
    }

    /// Value at grid point `(i, j, k)`: the evaluated value, 0 in an empty block, `inside` in
    /// an inside one.
    #[must_use]
    #[inline]
    pub fn at(&self, i: u32, j: u32, k: u32) -> f32 {
        let b = self.block_index([i / BLOCK, j / BLOCK, k / BLOCK]);
        match self.states[b] {
            EMPTY => 0.0,
            INSIDE => self.inside,
            slot => {
                let local =
                    (i % BLOCK) as usize + B * ((j % BLOCK) as usize + B * (k % BLOCK) as usize);
                self.values[slot as usize * BLOCK_VALUES + local]
            }
        }
    }

    /// The values of evaluated block `b`, `BLOCK_VALUES` of them, x fastest.
    #[must_use]
    pub fn block_values(&self, b: [u32; 3]) -> Option<&[f32]> {
        match self.state(b) {
            BlockState::Evaluated(slot) => {
                let s = slot as usize * BLOCK_VALUES;
                Some(&self.values[s..s + BLOCK_VALUES])
            }
            _ => None,
        }
    }

    /// The whole grid, dense (for comparisons and for callers that want one).
    #[must_use]
    pub fn to_dense(&self) -> DensityGrid {
        let [nx, ny, _] = self.spec.dims;
        let mut values = vec![0.0f32; self.spec.cells() as usize];
        values
            .par_chunks_mut(nx as usize * ny as usize)
            .enumerate()
            .for_each(|(k, plane)| {
                for j in 0..ny {
                    for i in 0..nx {
                        plane[i as usize + nx as usize * j as usize] = self.at(i, j, k as u32);
                    }
                }
            });
        DensityGrid {
            spec: self.spec,
            values,
        }
    }
}

/// The closed range of grid points of block `b` along one axis of `n` points.
fn closed(b: u32, n: u32) -> (u32, u32) {
    let lo = b * BLOCK;
    (lo, (lo + BLOCK).min(n - 1))
}

/// The sparse density grid of `points` (see the module's documentation), the interior taken
/// from `band` (the LNM band of the same points, voxels at least as wide as the largest radius);
/// refused when its blocks' states, or the values of the blocks it evaluates, would need more
/// than `memory_limit` bytes.
#[allow(
    clippy::too_many_lines,
    reason = "issue 38: still to split into named phases"
)]
pub fn points_grid_sparse(
    points: Points<'_>,
    spec: &GridSpec,
    kernel: Kernel,
    memory_limit: u64,
    band: &NarrowBand,
    iso: f32,
    inside: f32,
) -> Result<SparseGrid, DensityError> {
    points.check()?;
    if !(iso.is_finite() && inside.is_finite() && inside >= iso) {
        return Err(DensityError::InvalidGrid {
            name: "iso",
            reason: format!(
                "the inside value {inside} must be finite and at least the iso-value {iso}"
            ),
        });
    }
    let reach = points.max_radius();
    if band.voxel_of.len() != points.len() {
        return Err(DensityError::InvalidGrid {
            name: "narrow band",
            reason: format!(
                "a band of {} particles with voxels of {} for {} points of radius up to {}",
                band.voxel_of.len(),
                band.edge,
                points.len(),
                reach
            ),
        });
    }
    let blocks = spec.dims.map(|n| n.div_ceil(BLOCK));
    let count = blocks.iter().map(|&b| b as u128).product::<u128>();
    let too_large = |bytes: u128| {
        let [nx, ny, nz] = spec.dims.map(u64::from);
        Err(DensityError::TooLarge {
            nx,
            ny,
            nz,
            cells: spec.cells(),
            bytes,
            limit: memory_limit,
        })
    };
    // per block: its state (4 bytes), its first point (4) and its interior voxel count (2)
    if count * 10 > u128::from(memory_limit) {
        return too_large(count * 10);
    }
    let count = count as usize;
    let [bx, by, bz] = blocks.map(|b| b as usize);
    let index = |b: [usize; 3]| b[0] + bx * (b[1] + by * b[2]);
    let side = BLOCK as f32 * spec.spacing;
    let block_of = |p: Vec3| -> [usize; 3] {
        let c = ((p - spec.origin) / side).floor();
        let at = |v: f32, n: usize| (v.max(0.0) as usize).min(n - 1);
        [at(c.x, bx), at(c.y, by), at(c.z, bz)]
    };

    // the points sorted into blocks (counting sort: each block's points in index order)
    let home: Vec<u32> = points
        .positions
        .par_iter()
        .map(|&p| index(block_of(p)) as u32)
        .collect();
    let mut start = vec![0u32; count + 1];
    for &b in &home {
        start[b as usize + 1] += 1;
    }
    for b in 0..count {
        start[b + 1] += start[b];
    }
    let mut sorted = vec![0u32; points.len()];
    let mut fill = start.clone();
    for (p, &b) in home.iter().enumerate() {
        sorted[fill[b as usize] as usize] = p as u32;
        fill[b as usize] += 1;
    }
    drop(fill);
    drop(home);

    // the world box of a block's closed range, and the blocks whose points may reach it
    let world_box = |b: [usize; 3]| -> (Vec3, Vec3) {
        let r = [0, 1, 2].map(|a| closed(b[a] as u32, spec.dims[a]));
        (
            spec.point(r[0].0, r[1].0, r[2].0),
            spec.point(r[0].1, r[1].1, r[2].1),
        )
    };
    let around = |lo: Vec3, hi: Vec3| -> ([usize; 3], [usize; 3]) {
        (
            block_of(lo - Vec3::splat(reach)),
            block_of(hi + Vec3::splat(reach)),
        )
    };
    // the points of the blocks within reach of the world box [lo, hi], until `visit` says stop
    let for_each_near = |lo: Vec3, hi: Vec3, visit: &mut dyn FnMut(u32) -> bool| {
        let (a, c) = around(lo, hi);
        for z in a[2]..=c[2] {
            for y in a[1]..=c[1] {
                let row = index([0, y, z]);
                let (s, e) = (start[row + a[0]], start[row + c[0] + 1]);
                for &p in &sorted[s as usize..e as usize] {
                    if !visit(p) {
                        return;
                    }
                }
            }
        }
    };

    // inside: count the interior voxels each block's closed range covers
    let inv = 1.0 / band.edge;
    let voxel_range = |lo: Vec3, hi: Vec3| -> ([i64; 3], [i64; 3]) {
        let a = ((lo - band.origin) * inv).floor();
        let c = ((hi - band.origin) * inv).floor();
        (
            [a.x as i64, a.y as i64, a.z as i64],
            [c.x as i64, c.y as i64, c.z as i64],
        )
    };
    let mut interior_seen = vec![0u16; count];
    for v in band.voxels.iter().filter(|v| v.label == 0) {
        let vlo = band.origin
            + Vec3::new(v.coord[0] as f32, v.coord[1] as f32, v.coord[2] as f32) * band.edge;
        let (a, c) = around(vlo, vlo + Vec3::splat(band.edge));
        for z in a[2]..=c[2] {
            for y in a[1]..=c[1] {
                for x in a[0]..=c[0] {
                    let (lo, hi) = world_box([x, y, z]);
                    let (r0, r1) = voxel_range(lo, hi);
                    if (0..3).all(|k| (r0[k]..=r1[k]).contains(&i64::from(v.coord[k]))) {
                        let s = &mut interior_seen[index([x, y, z])];
                        *s = s.saturating_add(1);
                    }
                }
            }
        }
    }

    // each block's state: inside when every voxel its closed range covers is interior, empty
    // when no point's ball reaches its closed range (with a margin of 1e-4 of the radius, so
    // that the dense grid's kernels there are exactly 0 despite rounding), evaluated otherwise
    let mut states: Vec<u32> = (0..count)
        .into_par_iter()
        .map(|b| {
            let c = [b % bx, (b / bx) % by, b / (bx * by)];
            let (lo, hi) = world_box(c);
            let (r0, r1) = voxel_range(lo, hi);
            let in_domain = (0..3).all(|k| r0[k] >= 0 && r1[k] < i64::from(band.dims[k]));
            let covered: i64 = (0..3).map(|k| r1[k] - r0[k] + 1).product();
            if in_domain && covered == i64::from(interior_seen[b]) {
                return INSIDE;
            }
            let mut reached = false;
            for_each_near(lo, hi, &mut |p| {
                let x = points.positions[p as usize];
                let r = points.radius(p as usize) * (1.0 + 1e-4);
                let d = (lo - x).max(x - hi).max(Vec3::ZERO);
                reached = d.length_squared() < r * r;
                !reached
            });
            if reached { 0 } else { EMPTY }
        })
        .collect();
    drop(interior_seen);
    let evaluated: Vec<u32> = (0..count as u32)
        .filter(|&b| states[b as usize] == 0)
        .collect();
    let bytes = evaluated.len() as u128 * BLOCK_VALUES as u128 * 4;
    if bytes > u128::from(memory_limit) {
        return too_large(bytes);
    }
    for (slot, &b) in evaluated.iter().enumerate() {
        states[b as usize] = slot as u32;
    }

    // the evaluated blocks, from their candidates in index order (the dense grid's order),
    // over the window of their points that lie outside the interior voxels; the interior points
    // read as `inside`. Consecutive evaluated blocks along x are filled as one run, so that a
    // point's disk is set up once per plane and its rows are long, as in the dense slabs.
    let interior_voxel = |c: [i64; 3]| -> bool {
        (0..3).all(|a| c[a] >= 0 && c[a] < i64::from(band.dims[a]))
            && band
                .voxel_at(c.map(|v| v as u32))
                .is_some_and(|v| band.voxels[v].label == 0)
    };
    let columns: Vec<f32> = (0..spec.dims[0]).map(|i| column(spec, i)).collect();
    let mut values = vec![0.0f32; evaluated.len() * BLOCK_VALUES];
    let mut interior = vec![[0u64; 8]; evaluated.len()];
    // runs of slots: consecutive blocks of one row of blocks
    let mut runs: Vec<(usize, usize)> = Vec::new();
    for (slot, &b) in evaluated.iter().enumerate() {
        match runs.last_mut() {
            Some((first, len))
                if evaluated[*first + *len - 1] + 1 == b && !(b as usize).is_multiple_of(bx) =>
            {
                *len += 1;
            }
            _ => runs.push((slot, 1)),
        }
    }
    let mut jobs = Vec::with_capacity(runs.len());
    let (mut rest_v, mut rest_m) = (values.as_mut_slice(), interior.as_mut_slice());
    for &(first, len) in &runs {
        let (v, tail_v) = rest_v.split_at_mut(len * BLOCK_VALUES);
        let (m, tail_m) = rest_m.split_at_mut(len);
        jobs.push((evaluated[first] as usize, len, v, m));
        (rest_v, rest_m) = (tail_v, tail_m);
    }
    jobs.into_par_iter().for_each_init(
        || (Vec::new(), Vec::new()),
        |(candidates, scratch), (b, len, out, masks)| {
            let c = [b % bx, (b / bx) % by, b / (bx * by)];
            let o = c.map(|v| v as u32 * BLOCK);
            // local extents: x over the whole run, y and z of one block
            let n = [
                (spec.dims[0] - o[0]).min(BLOCK * len as u32) as usize,
                (spec.dims[1] - o[1]).min(BLOCK) as usize,
                (spec.dims[2] - o[2]).min(BLOCK) as usize,
            ];
            // the voxel of each point, axis by axis (the voxel lattice is separable), and the
            // interior test of the few voxels the run meets
            let voxel = |a: usize, l: usize| {
                let p = spec.origin[a] + (o[a] + l as u32) as f32 * spec.spacing;
                ((p - band.origin[a]) * inv).floor() as i64
            };
            let axes: [Vec<i64>; 3] = [0, 1, 2].map(|a| (0..n[a]).map(|l| voxel(a, l)).collect());
            let first = [0, 1, 2].map(|a| axes[a][0]);
            let span = [0, 1, 2].map(|a| (axes[a][n[a] - 1] - first[a] + 1) as usize);
            let table: Vec<bool> = (0..span[0] * span[1] * span[2])
                .map(|t| {
                    let d = [
                        t % span[0],
                        (t / span[0]) % span[1],
                        t / (span[0] * span[1]),
                    ];
                    interior_voxel([0, 1, 2].map(|a| first[a] + d[a] as i64))
                })
                .collect();
            let mut lo = [usize::MAX; 3];
            let mut hi = [0usize; 3];
            for k in 0..n[2] {
                for j in 0..n[1] {
                    for i in 0..n[0] {
                        let d = [
                            (axes[0][i] - first[0]) as usize,
                            (axes[1][j] - first[1]) as usize,
                            (axes[2][k] - first[2]) as usize,
                        ];
                        if table[d[0] + span[0] * (d[1] + span[1] * d[2])] {
                            let l = i % B + B * (j + B * k);
                            masks[i / B][l / 64] |= 1 << (l % 64);
                        } else {
                            for (a, v) in [i, j, k].into_iter().enumerate() {
                                lo[a] = lo[a].min(v);
                                hi[a] = hi[a].max(v);
                            }
                        }
                    }
                }
            }
            if lo[0] != usize::MAX {
                let (wlo, whi) = (
                    [0, 1, 2].map(|a| o[a] + lo[a] as u32),
                    [0, 1, 2].map(|a| o[a] + hi[a] as u32),
                );
                let window = Window {
                    lo: [wlo[0], wlo[1]],
                    hi: [whi[0], whi[1]],
                    stride: hi[0] - lo[0] + 1,
                };
                let (box_lo, box_hi) = (
                    spec.point(wlo[0], wlo[1], wlo[2]),
                    spec.point(whi[0], whi[1], whi[2]),
                );
                candidates.clear();
                for_each_near(box_lo, box_hi, &mut |p| {
                    let x = points.positions[p as usize];
                    let r = points.radius(p as usize);
                    let d = (box_lo - x).max(x - box_hi).max(Vec3::ZERO);
                    // a point whose ball misses the window adds nothing there (the margin as
                    // for the empty blocks)
                    if d.length_squared() < (r * (1.0 + 1e-4)).powi(2) {
                        candidates.push(p);
                    }
                    true
                });
                candidates.sort_unstable();
                let plane = window.stride * (hi[1] - lo[1] + 1);
                scratch.clear();
                scratch.resize(plane * (hi[2] - lo[2] + 1), 0.0f32);
                for &p in candidates.iter() {
                    let x = points.positions[p as usize];
                    let hj = points.radius(p as usize);
                    let w = points.weight(p as usize);
                    for k in lo[2]..=hi[2] {
                        let s = (k - lo[2]) * plane;
                        splat_disk(
                            spec,
                            kernel,
                            x,
                            (hj, w),
                            points.h,
                            o[2] + k as u32,
                            &window,
                            &columns,
                            &mut scratch[s..s + plane],
                        );
                    }
                }
                // into the blocks
                for k in lo[2]..=hi[2] {
                    for j in lo[1]..=hi[1] {
                        let row = (k - lo[2]) * plane + (j - lo[1]) * window.stride;
                        for i in lo[0]..=hi[0] {
                            out[(i / B) * BLOCK_VALUES + i % B + B * (j + B * k)] =
                                scratch[row + i - lo[0]];
                        }
                    }
                }
            }
            for (t, mask) in masks.iter().enumerate() {
                for l in 0..BLOCK_VALUES {
                    if mask[l / 64] >> (l % 64) & 1 == 1 {
                        out[t * BLOCK_VALUES + l] = inside;
                    }
                }
            }
        },
    );
    let mut grid = SparseGrid {
        spec: *spec,
        blocks,
        inside,
        states,
        evaluated,
        values,
        interior,
    };

    // An inside point next to a point below the iso-value ends a crossing edge, whose surfel is
    // placed by both values: such points (rare: a dip of the density next to the band's
    // interior, as where the chain's fine surface points meet the interior particles) get their
    // exact value, the dense grid's, an inside block holding one becomes an evaluated one.
    let neighbours = |[i, j, k]: [u32; 3]| {
        let n = spec.dims;
        [
            (i > 0).then(|| [i - 1, j, k]),
            (i + 1 < n[0]).then(|| [i + 1, j, k]),
            (j > 0).then(|| [i, j - 1, k]),
            (j + 1 < n[1]).then(|| [i, j + 1, k]),
            (k > 0).then(|| [i, j, k - 1]),
            (k + 1 < n[2]).then(|| [i, j, k + 1]),
        ]
    };
    let ends: Vec<[u32; 3]> = {
        let g = &grid;
        let inside_point = |p: [u32; 3]| match g.state(p.map(|c| c / BLOCK)) {
            BlockState::Inside => true,
            BlockState::Empty => false,
            BlockState::Evaluated(slot) => {
                let l = local(p);
                g.interior[slot as usize][l / 64] >> (l % 64) & 1 == 1
            }
        };
        // the inside points that can touch a point off the inside: the interior points of the
        // evaluated blocks and the points of the inside blocks next to a block that is not
        (0..count)
            .into_par_iter()
            .filter(|&b| match g.states[b] {
                EMPTY => false,
                INSIDE => {
                    let c = [b % bx, (b / bx) % by, b / (bx * by)];
                    (0..27).any(|t| {
                        let d = [t % 3, (t / 3) % 3, t / 9];
                        let n: Option<Vec<usize>> = (0..3)
                            .map(|a| {
                                (c[a] + d[a])
                                    .checked_sub(1)
                                    .filter(|&v| v < blocks[a] as usize)
                            })
                            .collect();
                        n.is_some_and(|n| g.states[index([n[0], n[1], n[2]])] != INSIDE)
                    })
                }
                slot => g.interior[slot as usize].iter().any(|&w| w != 0),
            })
            .flat_map_iter(|b| {
                let c = [b % bx, (b / bx) % by, b / (bx * by)].map(|v| v as u32 * BLOCK);
                let n = [0, 1, 2].map(|a| (spec.dims[a] - c[a]).min(BLOCK));
                let mut out = Vec::new();
                for k in 0..n[2] {
                    for j in 0..n[1] {
                        for i in 0..n[0] {
                            let p = [c[0] + i, c[1] + j, c[2] + k];
                            if inside_point(p)
                                && neighbours(p)
                                    .into_iter()
                                    .flatten()
                                    .any(|q| !inside_point(q) && g.at(q[0], q[1], q[2]) < iso)
                            {
                                out.push(p);
                            }
                        }
                    }
                }
                out
            })
            .collect()
    };
    if !ends.is_empty() {
        // the inside blocks that hold one become evaluated (appended, in block order)
        let mut promote: Vec<usize> = ends
            .iter()
            .map(|p| index(p.map(|c| (c / BLOCK) as usize)))
            .filter(|&b| grid.states[b] == INSIDE)
            .collect();
        promote.sort_unstable();
        promote.dedup();
        for b in promote {
            let slot = grid.evaluated.len() as u32;
            grid.states[b] = slot;
            grid.evaluated.push(b as u32);
            grid.values
                .extend(std::iter::repeat_n(inside, BLOCK_VALUES));
            let c = [b % bx, (b / bx) % by, b / (bx * by)].map(|v| v as u32 * BLOCK);
            let n = [0, 1, 2].map(|a| (spec.dims[a] - c[a]).min(BLOCK));
            let mut mask = [0u64; 8];
            for k in 0..n[2] {
                for j in 0..n[1] {
                    for i in 0..n[0] {
                        let l = local([i, j, k]);
                        mask[l / 64] |= 1 << (l % 64);
                    }
                }
            }
            grid.interior.push(mask);
        }
        let exact: Vec<f32> = ends
            .par_iter()
            .map(|&p| {
                let x0 = spec.point(p[0], p[1], p[2]);
                let mut candidates = Vec::new();
                for_each_near(x0, x0, &mut |q| {
                    candidates.push(q);
                    true
                });
                candidates.sort_unstable();
                let window = Window {
                    lo: [p[0], p[1]],
                    hi: [p[0], p[1]],
                    stride: 1,
                };
                let mut v = [0.0f32];
                for &q in &candidates {
                    splat_disk(
                        spec,
                        kernel,
                        points.positions[q as usize],
                        (points.radius(q as usize), points.weight(q as usize)),
                        points.h,
                        p[2],
                        &window,
                        &columns,
                        &mut v,
                    );
                }
                v[0]
            })
            .collect();
        for (&p, v) in ends.iter().zip(exact) {
            let b = index(p.map(|c| (c / BLOCK) as usize));
            let slot = grid.states[b] as usize;
            let l = local(p);
            grid.values[slot * BLOCK_VALUES + l] = v;
            grid.interior[slot][l / 64] &= !(1 << (l % 64));
        }
    }
    Ok(grid)
}

/// Index of grid point `p` inside its block.
fn local(p: [u32; 3]) -> usize {
    let [i, j, k] = p.map(|c| (c % BLOCK) as usize);
    i + B * (j + B * k)
}
