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
//! blocks. An inside point that ends a crossing edge or lies one beyond its end (one or two
//! points from a point below the iso-value along an axis) gets its exact value, the dense
//! grid's, so that edge's surfel is placed as on the dense grid (by the values along the edge's
//! line, [`crate::surfels::crossing_t`]). The
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

/// The factor on a point's radius within which its ball counts as reaching a block (or a
/// window of one): a margin of 1e-4 of the radius, so that the dense grid's kernels outside are
/// exactly 0 despite rounding. The GPU's layout ([`super::sparse_gpu`]) applies the same f32.
pub const REACH_MARGIN: f32 = 1.0 + 1e-4;

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

    /// The block states (x fastest: `u32::MAX` empty, `u32::MAX - 1` inside, else the slot of
    /// the block's values) and the evaluated blocks' values (`BLOCK_VALUES` a slot, x fastest
    /// within a block), as the GPU surfels read them ([`crate::surfels::gpu`]).
    pub(crate) fn raw(&self) -> (&[u32], &[f32]) {
        (&self.states, &self.values)
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
            .for_each(|(k, plane)| self.plane_into(k as u32, plane));
        DensityGrid {
            spec: self.spec,
            values,
        }
    }

    /// The values of z plane `k` (`nx * ny`, x fastest), as [`Self::at`] reads them, written
    /// into `out` block row by block row: an empty block's rows 0, an inside one's
    /// [`Self::inside`], an evaluated one's copied (marching cubes over a sparse grid read
    /// its planes so: the dam break's chain mesh took 162 ms through `at` point by point,
    /// against 82 ms on the dense grid).
    ///
    /// # Panics
    /// If `k` lies past the grid or `out` does not hold one value per point of a plane.
    pub fn plane_into(&self, k: u32, out: &mut [f32]) {
        let [nx, ny, nz] = self.spec.dims;
        assert!(k < nz, "plane {k} of {nz}");
        assert_eq!(out.len(), nx as usize * ny as usize, "one value per point");
        let (bz, lz) = (k / BLOCK, (k % BLOCK) as usize);
        for by in 0..self.blocks[1] {
            for bx in 0..self.blocks[0] {
                let state = self.states[self.block_index([bx, by, bz])];
                let (i0, j0) = (bx * BLOCK, by * BLOCK);
                let width = (nx - i0).min(BLOCK) as usize;
                for dj in 0..(ny - j0).min(BLOCK) {
                    let start = (i0 + nx * (j0 + dj)) as usize;
                    let row = &mut out[start..start + width];
                    match state {
                        EMPTY => row.fill(0.0),
                        INSIDE => row.fill(self.inside),
                        slot => {
                            let from = slot as usize * BLOCK_VALUES + B * (dj as usize + B * lz);
                            row.copy_from_slice(&self.values[from..from + width]);
                        }
                    }
                }
            }
        }
    }
}

/// The closed range of grid points of block `b` along one axis of `n` points.
/// Blocks along each axis of a grid of `spec` (`ceil(dims / BLOCK)`).
pub(crate) fn blocks_of(spec: &GridSpec) -> [u32; 3] {
    spec.dims.map(|n| n.div_ceil(BLOCK))
}

fn closed(b: u32, n: u32) -> (u32, u32) {
    let lo = b * BLOCK;
    (lo, (lo + BLOCK).min(n - 1))
}

/// The sparse density grid of `points` (see the module's documentation), the interior taken
/// from `band` (the LNM band of the same points, voxels at least as wide as the largest radius);
/// refused when its blocks' states, or the values of the blocks it evaluates, would need more
/// than `memory_limit` bytes. In phases: the points sorted into blocks (`Blocks::new`), the
/// blocks' states (`Blocks::states`), the evaluated blocks' values (`Blocks::evaluate`), the
/// inside points that end a crossing edge made exact (`exact_ends`).
pub fn points_grid_sparse(
    points: Points<'_>,
    spec: &GridSpec,
    kernel: Kernel,
    memory_limit: u64,
    band: &NarrowBand,
    iso: f32,
    inside: f32,
) -> Result<SparseGrid, DensityError> {
    check_sparse(&points, band, iso, inside)?;
    let blocks = blocks_of(spec);
    let count = blocks.iter().map(|&b| b as u128).product::<u128>();
    let too_large = |bytes: u128| too_large(spec, bytes, memory_limit);
    // per block: its state (4 bytes), its first point (4) and its interior voxel count (2)
    if count * 10 > u128::from(memory_limit) {
        return too_large(count * 10);
    }
    let b = Blocks::new(points, spec, band, blocks.map(|b| b as usize));
    let (states, evaluated) = b.layout();
    let bytes = evaluated.len() as u128 * BLOCK_VALUES as u128 * 4;
    if bytes > u128::from(memory_limit) {
        return too_large(bytes);
    }
    let columns: Vec<f32> = (0..spec.dims[0]).map(|i| column(spec, i)).collect();
    let (values, interior) = b.evaluate(kernel, inside, &columns, &evaluated);
    let mut grid = SparseGrid {
        spec: *spec,
        blocks,
        inside,
        states,
        evaluated,
        values,
        interior,
    };
    exact_ends(&mut grid, &b, kernel, &columns, iso);
    Ok(grid)
}

/// Which blocks of a sparse grid are evaluated, without their values: what the GPU fills
/// ([`crate::density::gpu::GridFiller::record_sparse`], issue 37). The states and the
/// evaluated blocks of [`points_grid_sparse`] before it makes the crossings' inside ends
/// exact (the GPU computes those where it meets them).
#[derive(Clone, Debug, PartialEq)]
pub struct SparseLayout {
    /// The grid.
    pub spec: GridSpec,
    /// Blocks along x, y and z (`ceil(dims / BLOCK)`).
    pub blocks: [u32; 3],
    /// Per block (x fastest): `u32::MAX` empty, `u32::MAX - 1` inside, else its slot (its
    /// index in `evaluated`).
    pub states: Vec<u32>,
    /// The evaluated blocks' indices (x fastest), in block order.
    pub evaluated: Vec<u32>,
}

impl SparseLayout {
    /// Bytes of the evaluated blocks' values (4 per grid point).
    #[must_use]
    pub fn value_bytes(&self) -> u64 {
        self.evaluated.len() as u64 * BLOCK_VALUES as u64 * 4
    }
}

/// The blocks [`points_grid_sparse`] would evaluate for the same arguments, and the states of
/// the others; refused as it refuses (a layout or values over `memory_limit` bytes).
pub fn sparse_layout(
    points: Points<'_>,
    spec: &GridSpec,
    memory_limit: u64,
    band: &NarrowBand,
) -> Result<SparseLayout, DensityError> {
    check_sparse(&points, band, 0.0, 0.0)?;
    let blocks = blocks_of(spec);
    let count = blocks.iter().map(|&b| b as u128).product::<u128>();
    // per block: its state (4 bytes), its first point (4) and its interior voxel count (2)
    if count * 10 > u128::from(memory_limit) {
        return too_large(spec, count * 10, memory_limit);
    }
    let b = Blocks::new(points, spec, band, blocks.map(|b| b as usize));
    let (states, evaluated) = b.layout();
    let layout = SparseLayout {
        spec: *spec,
        blocks,
        states,
        evaluated,
    };
    if u128::from(layout.value_bytes()) > u128::from(memory_limit) {
        return too_large(spec, u128::from(layout.value_bytes()), memory_limit);
    }
    Ok(layout)
}

/// The checks of [`points_grid_sparse`]: the points, an inside value above the iso-value, a
/// band of these points.
fn check_sparse(
    points: &Points<'_>,
    band: &NarrowBand,
    iso: f32,
    inside: f32,
) -> Result<(), DensityError> {
    points.check()?;
    if !(iso.is_finite() && inside.is_finite() && inside >= iso) {
        return Err(DensityError::InvalidGrid {
            name: "iso",
            reason: format!(
                "the inside value {inside} must be finite and at least the iso-value {iso}"
            ),
        });
    }
    if band.voxel_of.len() != points.len() {
        return Err(DensityError::InvalidGrid {
            name: "narrow band",
            reason: format!(
                "a band of {} particles with voxels of {} for {} points of radius up to {}",
                band.voxel_of.len(),
                band.edge,
                points.len(),
                points.max_radius()
            ),
        });
    }
    Ok(())
}

/// The error of a sparse grid of `spec` that needs `bytes`, over `limit`.
fn too_large<T>(spec: &GridSpec, bytes: u128, limit: u64) -> Result<T, DensityError> {
    let [nx, ny, nz] = spec.dims.map(u64::from);
    Err(DensityError::TooLarge {
        nx,
        ny,
        nz,
        cells: spec.cells(),
        bytes,
        limit,
    })
}

/// The blocks of a grid, the points sorted into them and the band's interior: what the phases of
/// [`points_grid_sparse`] read.
struct Blocks<'a> {
    points: Points<'a>,
    spec: &'a GridSpec,
    band: &'a NarrowBand,
    /// blocks along each axis
    dims: [usize; 3],
    count: usize,
    /// the largest radius with the margin ([`REACH_MARGIN`]): no point farther from a box
    /// reaches it
    reach: f32,
    /// a block's edge in world units
    side: f32,
    /// 1 / the band's voxel edge
    inv: f32,
    /// block `b`'s points are `sorted[start[b]..start[b + 1]]`, in index order
    start: Vec<u32>,
    sorted: Vec<u32>,
}

impl<'a> Blocks<'a> {
    /// The points sorted into blocks (a counting sort: each block's points in index order).
    fn new(points: Points<'a>, spec: &'a GridSpec, band: &'a NarrowBand, dims: [usize; 3]) -> Self {
        let count = dims.iter().product();
        let mut b = Self {
            points,
            spec,
            band,
            dims,
            count,
            reach: points.max_radius() * REACH_MARGIN,
            side: BLOCK as f32 * spec.spacing,
            inv: 1.0 / band.edge,
            start: vec![0u32; count + 1],
            sorted: vec![0u32; points.len()],
        };
        let home: Vec<u32> = points
            .positions
            .par_iter()
            .map(|&p| b.index(b.block_of(p)) as u32)
            .collect();
        for &k in &home {
            b.start[k as usize + 1] += 1;
        }
        for k in 0..count {
            b.start[k + 1] += b.start[k];
        }
        let mut fill = b.start.clone();
        for (p, &k) in home.iter().enumerate() {
            b.sorted[fill[k as usize] as usize] = p as u32;
            fill[k as usize] += 1;
        }
        b
    }

    fn index(&self, b: [usize; 3]) -> usize {
        b[0] + self.dims[0] * (b[1] + self.dims[1] * b[2])
    }

    fn coords(&self, b: usize) -> [usize; 3] {
        let [bx, by, _] = self.dims;
        [b % bx, (b / bx) % by, b / (bx * by)]
    }

    fn block_of(&self, p: Vec3) -> [usize; 3] {
        let c = ((p - self.spec.origin) / self.side).floor();
        let at = |v: f32, n: usize| (v.max(0.0) as usize).min(n - 1);
        [
            at(c.x, self.dims[0]),
            at(c.y, self.dims[1]),
            at(c.z, self.dims[2]),
        ]
    }

    /// The world box of a block's closed range.
    fn world_box(&self, b: [usize; 3]) -> (Vec3, Vec3) {
        let r = [0, 1, 2].map(|a| closed(b[a] as u32, self.spec.dims[a]));
        (
            self.spec.point(r[0].0, r[1].0, r[2].0),
            self.spec.point(r[0].1, r[1].1, r[2].1),
        )
    }

    /// The blocks whose points may reach the world box `[lo, hi]`.
    fn around(&self, lo: Vec3, hi: Vec3) -> ([usize; 3], [usize; 3]) {
        (
            self.block_of(lo - Vec3::splat(self.reach)),
            self.block_of(hi + Vec3::splat(self.reach)),
        )
    }

    /// The points of the blocks within reach of the world box `[lo, hi]`, until `visit` says
    /// stop.
    fn for_each_near(&self, lo: Vec3, hi: Vec3, visit: &mut dyn FnMut(u32) -> bool) {
        let (a, c) = self.around(lo, hi);
        for z in a[2]..=c[2] {
            for y in a[1]..=c[1] {
                let row = self.index([0, y, z]);
                let (s, e) = (self.start[row + a[0]], self.start[row + c[0] + 1]);
                for &p in &self.sorted[s as usize..e as usize] {
                    if !visit(p) {
                        return;
                    }
                }
            }
        }
    }

    /// The band's voxels the world box `[lo, hi]` covers, as ranges per axis.
    fn voxel_range(&self, lo: Vec3, hi: Vec3) -> ([i64; 3], [i64; 3]) {
        let a = ((lo - self.band.origin) * self.inv).floor();
        let c = ((hi - self.band.origin) * self.inv).floor();
        (
            [a.x as i64, a.y as i64, a.z as i64],
            [c.x as i64, c.y as i64, c.z as i64],
        )
    }

    /// Whether the band's voxel `c` is an interior one.
    fn interior_voxel(&self, c: [i64; 3]) -> bool {
        let band = self.band;
        (0..3).all(|a| c[a] >= 0 && c[a] < i64::from(band.dims[a]))
            && band
                .voxel_at(c.map(|v| v as u32))
                .is_some_and(|v| band.voxels[v].label == 0)
    }

    /// The interior voxels each block's closed range covers, counted.
    fn interior_seen(&self) -> Vec<u16> {
        let band = self.band;
        let mut seen = vec![0u16; self.count];
        for v in band.voxels.iter().filter(|v| v.label == 0) {
            let vlo = band.origin
                + Vec3::new(v.coord[0] as f32, v.coord[1] as f32, v.coord[2] as f32) * band.edge;
            let (a, c) = self.around(vlo, vlo + Vec3::splat(band.edge));
            for z in a[2]..=c[2] {
                for y in a[1]..=c[1] {
                    for x in a[0]..=c[0] {
                        let (lo, hi) = self.world_box([x, y, z]);
                        let (r0, r1) = self.voxel_range(lo, hi);
                        if (0..3).all(|k| (r0[k]..=r1[k]).contains(&i64::from(v.coord[k]))) {
                            let s = &mut seen[self.index([x, y, z])];
                            *s = s.saturating_add(1);
                        }
                    }
                }
            }
        }
        seen
    }

    /// Each block's state: inside when every voxel its closed range covers is interior
    /// (`interior_seen`), empty when no point's ball reaches its closed range (with a margin of
    /// 1e-4 of the radius, so that the dense grid's kernels there are exactly 0 despite
    /// rounding), 0 (to evaluate) otherwise.
    fn states(&self, interior_seen: &[u16]) -> Vec<u32> {
        let band = self.band;
        (0..self.count)
            .into_par_iter()
            .map(|b| {
                let (lo, hi) = self.world_box(self.coords(b));
                let (r0, r1) = self.voxel_range(lo, hi);
                let in_domain = (0..3).all(|k| r0[k] >= 0 && r1[k] < i64::from(band.dims[k]));
                let covered: i64 = (0..3).map(|k| r1[k] - r0[k] + 1).product();
                if in_domain && covered == i64::from(interior_seen[b]) {
                    return INSIDE;
                }
                let mut reached = false;
                self.for_each_near(lo, hi, &mut |p| {
                    let x = self.points.positions[p as usize];
                    let r = self.points.radius(p as usize) * REACH_MARGIN;
                    let d = (lo - x).max(x - hi).max(Vec3::ZERO);
                    reached = d.length_squared() < r * r;
                    !reached
                });
                if reached { 0 } else { EMPTY }
            })
            .collect()
    }

    /// The blocks' states with the evaluated ones' slots, and the evaluated blocks in block
    /// order.
    fn layout(&self) -> (Vec<u32>, Vec<u32>) {
        let mut states = self.states(&self.interior_seen());
        let evaluated: Vec<u32> = (0..self.count as u32)
            .filter(|&k| states[k as usize] == 0)
            .collect();
        for (slot, &k) in evaluated.iter().enumerate() {
            states[k as usize] = slot as u32;
        }
        (states, evaluated)
    }

    /// The values and interior masks of the `evaluated` blocks, from their candidates in index
    /// order (the dense grid's order), over the window of their points that lie outside the
    /// interior voxels; the interior points read as `inside`. Consecutive evaluated blocks
    /// along x are filled as one run ([`Self::fill_run`]), so that a point's disk is set up once
    /// per plane and its rows are long, as in the dense slabs.
    fn evaluate(
        &self,
        kernel: Kernel,
        inside: f32,
        columns: &[f32],
        evaluated: &[u32],
    ) -> (Vec<f32>, Vec<[u64; 8]>) {
        let mut values = vec![0.0f32; evaluated.len() * BLOCK_VALUES];
        let mut interior = vec![[0u64; 8]; evaluated.len()];
        // runs of slots: consecutive blocks of one row of blocks
        let mut runs: Vec<(usize, usize)> = Vec::new();
        for (slot, &b) in evaluated.iter().enumerate() {
            match runs.last_mut() {
                Some((first, len))
                    if evaluated[*first + *len - 1] + 1 == b
                        && !(b as usize).is_multiple_of(self.dims[0]) =>
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
            |scratch, (b, len, out, masks)| {
                self.fill_run((kernel, inside, columns), (b, len), (out, masks), scratch);
            },
        );
        (values, interior)
    }

    /// One run of `len` evaluated blocks from block `b` along x: the interior points marked in
    /// `masks` (and read as `inside`), the other points' values splatted into `out` over the
    /// window they span. `scratch`: the candidates' and the window's buffers, reused.
    fn fill_run(
        &self,
        (kernel, inside, columns): (Kernel, f32, &[f32]),
        (b, len): (usize, usize),
        (out, masks): (&mut [f32], &mut [[u64; 8]]),
        (candidates, scratch): &mut (Vec<u32>, Vec<f32>),
    ) {
        let spec = self.spec;
        let o = self.coords(b).map(|v| v as u32 * BLOCK);
        // local extents: x over the whole run, y and z of one block
        let n = [
            (spec.dims[0] - o[0]).min(BLOCK * len as u32) as usize,
            (spec.dims[1] - o[1]).min(BLOCK) as usize,
            (spec.dims[2] - o[2]).min(BLOCK) as usize,
        ];
        let Some((lo, hi)) = self.mark_interior(o, n, masks) else {
            fill_inside(out, masks, inside);
            return;
        };
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
        let points = self.points;
        candidates.clear();
        self.for_each_near(box_lo, box_hi, &mut |p| {
            let x = points.positions[p as usize];
            let r = points.radius(p as usize);
            let d = (box_lo - x).max(x - box_hi).max(Vec3::ZERO);
            // a point whose ball misses the window adds nothing there (the margin as for the
            // empty blocks)
            if d.length_squared() < (r * REACH_MARGIN).powi(2) {
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
                    columns,
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
        fill_inside(out, masks, inside);
    }

    /// Marks in `masks` the points of the run at grid point `o` (extents `n`) that lie in
    /// interior voxels, and returns the local box of the others (`None`: every point interior).
    /// The voxel of each point is found axis by axis (the voxel lattice is separable), and the
    /// interior test of the few voxels the run meets once.
    fn mark_interior(
        &self,
        o: [u32; 3],
        n: [usize; 3],
        masks: &mut [[u64; 8]],
    ) -> Option<([usize; 3], [usize; 3])> {
        let spec = self.spec;
        let voxel = |a: usize, l: usize| {
            let p = spec.origin[a] + (o[a] + l as u32) as f32 * spec.spacing;
            ((p - self.band.origin[a]) * self.inv).floor() as i64
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
                self.interior_voxel([0, 1, 2].map(|a| first[a] + d[a] as i64))
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
        (lo[0] != usize::MAX).then_some((lo, hi))
    }
}

/// The interior points of a run's blocks (`masks`) read as `inside` in `out`.
fn fill_inside(out: &mut [f32], masks: &[[u64; 8]], inside: f32) {
    for (t, mask) in masks.iter().enumerate() {
        for l in 0..BLOCK_VALUES {
            if mask[l / 64] >> (l % 64) & 1 == 1 {
                out[t * BLOCK_VALUES + l] = inside;
            }
        }
    }
}

/// The grid points one and two steps from `p` along the axes, within the grid: the ends of
/// the edges at `p` and the points one beyond them, whose values place a crossing
/// ([`crate::surfels::crossing_t`]).
fn axis_neighbours(p: [u32; 3], n: [u32; 3]) -> [Option<[u32; 3]>; 12] {
    let mut out = [None; 12];
    for (t, slot) in out.iter_mut().enumerate() {
        let (axis, d) = (t / 4, [-2, -1, 1, 2][t % 4]);
        *slot = p[axis]
            .checked_add_signed(d)
            .filter(|&c| c < n[axis])
            .map(|c| {
                let mut q = p;
                q[axis] = c;
                q
            });
    }
    out
}

/// An inside point one or two steps along an axis from a point below the iso-value ends a
/// crossing edge or lies one point beyond its end, and the surfel is placed by the values along
/// the edge's line ([`crate::surfels::crossing_t`]): such points (rare: a dip of the density next to the band's interior,
/// as where the chain's fine surface points meet the interior particles) get their exact value,
/// the dense grid's, an inside block holding one becoming an evaluated one. In rounds: an end
/// whose exact value is below the iso-value was no inside point, and its inside neighbours end
/// crossings in turn (found on the dam break's chain once its grid lay on the world's lattice:
/// four surfels placed by an inside value 2.7 times the iso-value, up to 3e-3 cells from the
/// dense grid's).
fn exact_ends(grid: &mut SparseGrid, b: &Blocks<'_>, kernel: Kernel, columns: &[f32], iso: f32) {
    let mut ends = crossing_ends(grid, b, iso);
    while !ends.is_empty() {
        let exact = exact_round(grid, b, kernel, columns, &ends);
        let mut next: Vec<[u32; 3]> = ends
            .iter()
            .zip(&exact)
            .filter(|&(_, &v)| v < iso)
            .flat_map(|(&p, _)| axis_neighbours(p, grid.spec.dims).into_iter().flatten())
            .filter(|&q| inside_point(grid, q))
            .collect();
        next.sort_unstable();
        next.dedup();
        ends = next;
    }
}

/// Whether grid point `p` of `g` holds the inside value (in an inside block, or an interior
/// point of an evaluated one).
fn inside_point(g: &SparseGrid, p: [u32; 3]) -> bool {
    match g.state(p.map(|c| c / BLOCK)) {
        BlockState::Inside => true,
        BlockState::Empty => false,
        BlockState::Evaluated(slot) => {
            let l = local(p);
            g.interior[slot as usize][l / 64] >> (l % 64) & 1 == 1
        }
    }
}

/// One round of [`exact_ends`]: the exact values of `ends` written into `grid` (and returned).
fn exact_round(
    grid: &mut SparseGrid,
    b: &Blocks<'_>,
    kernel: Kernel,
    columns: &[f32],
    ends: &[[u32; 3]],
) -> Vec<f32> {
    let spec = b.spec;
    // the inside blocks that hold one become evaluated (appended, in block order)
    let mut promote: Vec<usize> = ends
        .iter()
        .map(|p| b.index(p.map(|c| (c / BLOCK) as usize)))
        .filter(|&k| grid.states[k] == INSIDE)
        .collect();
    promote.sort_unstable();
    promote.dedup();
    for k in promote {
        let slot = grid.evaluated.len() as u32;
        grid.states[k] = slot;
        grid.evaluated.push(k as u32);
        grid.values
            .extend(std::iter::repeat_n(grid.inside, BLOCK_VALUES));
        let c = b.coords(k).map(|v| v as u32 * BLOCK);
        let n = [0, 1, 2].map(|a| (spec.dims[a] - c[a]).min(BLOCK));
        let mut mask = [0u64; 8];
        for z in 0..n[2] {
            for y in 0..n[1] {
                for x in 0..n[0] {
                    let l = local([x, y, z]);
                    mask[l / 64] |= 1 << (l % 64);
                }
            }
        }
        grid.interior.push(mask);
    }
    let points = b.points;
    let exact: Vec<f32> = ends
        .par_iter()
        .map(|&p| {
            let x0 = spec.point(p[0], p[1], p[2]);
            let mut candidates = Vec::new();
            b.for_each_near(x0, x0, &mut |q| {
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
                    columns,
                    &mut v,
                );
            }
            v[0]
        })
        .collect();
    for (&p, &v) in ends.iter().zip(&exact) {
        let k = b.index(p.map(|c| (c / BLOCK) as usize));
        let slot = grid.states[k] as usize;
        let l = local(p);
        grid.values[slot * BLOCK_VALUES + l] = v;
        grid.interior[slot][l / 64] &= !(1 << (l % 64));
    }
    exact
}

/// The inside points one or two steps along an axis from a point off the inside below the
/// iso-value ([`exact_ends`]): among
/// the interior points of the evaluated blocks and the points of the inside blocks next to a
/// block that is not inside.
fn crossing_ends(g: &SparseGrid, b: &Blocks<'_>, iso: f32) -> Vec<[u32; 3]> {
    let spec = b.spec;
    (0..b.count)
        .into_par_iter()
        .filter(|&k| match g.states[k] {
            EMPTY => false,
            INSIDE => {
                let c = b.coords(k);
                (0..27).any(|t| {
                    let d = [t % 3, (t / 3) % 3, t / 9];
                    let n: Option<Vec<usize>> = (0..3)
                        .map(|a| (c[a] + d[a]).checked_sub(1).filter(|&v| v < b.dims[a]))
                        .collect();
                    n.is_some_and(|n| g.states[b.index([n[0], n[1], n[2]])] != INSIDE)
                })
            }
            slot => g.interior[slot as usize].iter().any(|&w| w != 0),
        })
        .flat_map_iter(|k| {
            let c = b.coords(k).map(|v| v as u32 * BLOCK);
            let n = [0, 1, 2].map(|a| (spec.dims[a] - c[a]).min(BLOCK));
            let mut out = Vec::new();
            for z in 0..n[2] {
                for y in 0..n[1] {
                    for x in 0..n[0] {
                        let p = [c[0] + x, c[1] + y, c[2] + z];
                        if inside_point(g, p)
                            && axis_neighbours(p, spec.dims)
                                .into_iter()
                                .flatten()
                                .any(|q| !inside_point(g, q) && g.at(q[0], q[1], q[2]) < iso)
                        {
                            out.push(p);
                        }
                    }
                }
            }
            out
        })
        .collect()
}

/// Index of grid point `p` inside its block.
fn local(p: [u32; 3]) -> usize {
    let [i, j, k] = p.map(|c| (c % BLOCK) as usize);
    i + B * (j + B * k)
}
