//! Fixed-radius neighbour search: every particle's neighbours within a radius, in parallel.
//!
//! The result is a compact CSR structure ([`Neighbourhoods`]): one flat index array and one
//! offset array, not a `Vec` per particle. Two backends build it:
//!
//! - [`Backend::CellGrid`] (default): a uniform grid of cells of edge `radius`; particles sorted by
//!   cell so that the 27-cell stencil reads nine contiguous runs of positions (one per row of three
//!   cells along x). Grids whose cell count would exceed a few per particle switch to a sparse
//!   index (binary search in the sorted cell keys), so a far-flung splash particle cannot blow up
//!   memory.
//! - [`Backend::KdTree`]: kiddo's immutable k-d tree with unsorted radius queries.
//!
//! `fluid-surfels bench detect` times both; docs/design.md records why the grid is the default.
//! kiddo also serves k-nearest queries ([`estimate_spacing`]).

use std::num::NonZeroUsize;
use std::ops::ControlFlow;

use glam::Vec3;
use kiddo::{ImmutableKdTree, SquaredEuclidean};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use wide::{CmpLe, f32x4};

/// Particles processed per parallel task: large enough to amortise task overhead, small enough
/// to balance two to sixteen threads on a million particles.
const CHUNK: usize = 4096;

/// Particles of a run of cells whose distances [`CellGrid::for_each_slot_within`] tests at once.
const SCAN_BLOCK: usize = 32;

/// The particles of a block (at most [`SCAN_BLOCK`], its coordinates one array per axis)
/// within `sqrt(r2)` of `p`, as the bits of their places in it: the distances of the whole
/// block at once (vectorised, as `(q - p).length_squared()` computes them, so the same
/// particles pass), then one bit per test, with no branch: a test that fails for most of them
/// costs more in mispredictions than the distances (the dam break's neighbour search at two
/// steps 20 -> 14 ms on one thread, its boundary calibration 216 -> 200 ms, when they were
/// listed one at a time).
#[inline]
fn near_mask(axes: &[Vec<f32>; 3], block: std::ops::Range<usize>, p: Vec3, r2: f32) -> u32 {
    let n = block.len();
    debug_assert!((1..=SCAN_BLOCK).contains(&n));
    let [xs, ys, zs] = axes;
    let (px, py, pz, r2) = (
        f32x4::splat(p.x),
        f32x4::splat(p.y),
        f32x4::splat(p.z),
        f32x4::splat(r2),
    );
    // four at a time: the arrays run on past the last slot by `LANES - 1` (infinite) values, so
    // that every load is whole; the bits beyond the block are cleared at the end
    let lanes = |a: &[f32], i: usize| {
        f32x4::from(<[f32; LANES]>::try_from(&a[i..i + LANES]).expect("padded"))
    };
    let mut mask = 0u32;
    for (g, i) in (block.start..block.end).step_by(LANES).enumerate() {
        let (dx, dy, dz) = (lanes(xs, i) - px, lanes(ys, i) - py, lanes(zs, i) - pz);
        let d2 = dx * dx + dy * dy + dz * dz;
        mask |= (d2.cmp_le(r2).move_mask() as u32) << (LANES * g);
    }
    mask & (u32::MAX >> (SCAN_BLOCK - n))
}

/// Distances [`near_mask`] computes at once: one SSE vector.
const LANES: usize = 4;

/// The blocks of at most `size` slots a run of slots is cut into, in order.
#[inline]
fn blocks_of(
    run: std::ops::Range<usize>,
    size: usize,
) -> impl Iterator<Item = std::ops::Range<usize>> {
    run.clone()
        .step_by(size)
        .map(move |a| a..(a + size).min(run.end))
}

/// Longest grid axis, in cells, that the search accepts (keys must fit in 64 bits).
const MAX_CELLS_PER_AXIS: u64 = 1 << 21;

/// Errors of the neighbour search.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum NeighbourError {
    /// The radius is zero, negative or not finite.
    #[error("neighbour radius must be finite and > 0, got {radius}")]
    InvalidRadius { radius: f32 },
    /// A position is NaN or infinite.
    #[error("particle {index} has a non-finite position {position:?}")]
    NonFinitePosition { index: usize, position: [f32; 3] },
    /// The particles span too many cells of the given radius along one axis.
    #[error(
        "the particles span {cells:?} cells of size {radius} (extent {extent:?}); at most {max} per axis are supported: use a larger radius, or drop far-away particles (`--bounds MIN_X,MIN_Y,MIN_Z,MAX_X,MAX_Y,MAX_Z` on the command line, `ParticleSet::crop` in the library)"
    )]
    GridTooLarge {
        cells: [u64; 3],
        extent: [f32; 3],
        radius: f32,
        max: u64,
    },
    /// More particles than 32-bit indices can address.
    #[error("{count} particles exceed the supported maximum of {max}")]
    TooManyParticles { count: usize, max: usize },
    /// A spacing estimate needs at least two distinct positions.
    #[error("cannot estimate a particle spacing: {reason}")]
    NoSpacing { reason: &'static str },
    /// kiddo refused to build its tree.
    #[error("k-d tree construction failed: {0}")]
    KdTree(String),
}

/// Which search structure builds the neighbourhoods.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Backend {
    /// Uniform cell grid (default; measured faster, see docs/design.md).
    #[default]
    CellGrid,
    /// kiddo's immutable k-d tree.
    KdTree,
}

/// All neighbours within `radius` of every particle, stored compactly (CSR).
///
/// A particle is never its own neighbour; the relation is symmetric (up to the rounding of the
/// inclusive bound `|p_i - p_j| <= radius`, which is computed identically both ways).
/// Rows are stored in the order the search visited particles (cell order for the grid), which
/// keeps the build cache-friendly, and in the chunks of 4,096 rows the parallel search made
/// them in (joining the chunks into one array was a sixth of the search's time and held every
/// list twice); [`Neighbourhoods::of`] hides both.
#[derive(Clone, Debug, Default)]
pub struct Neighbourhoods {
    radius: f32,
    /// particle index -> row
    row_of: Vec<u32>,
    /// rows `c * CHUNK..` of chunk `c`
    chunks: Vec<Rows>,
    total: usize,
}

/// Up to [`CHUNK`] rows: row `j` is `indices[ends[j]..ends[j + 1]]` (`ends` starts at 0).
#[derive(Clone, Debug, Default)]
struct Rows {
    ends: Vec<usize>,
    indices: Vec<u32>,
}

impl Rows {
    fn new(rows: usize, indices: usize) -> Self {
        let mut ends = Vec::with_capacity(rows + 1);
        ends.push(0);
        Self {
            ends,
            indices: Vec::with_capacity(indices),
        }
    }

    /// Closes the row made of the indices pushed since the last call.
    fn end_row(&mut self) {
        self.ends.push(self.indices.len());
    }
}

impl Neighbourhoods {
    /// Builds the neighbourhoods of `positions` within `radius`.
    pub fn build(
        positions: &[Vec3],
        radius: f32,
        backend: Backend,
    ) -> Result<Self, NeighbourError> {
        check_input(positions, radius)?;
        match backend {
            Backend::CellGrid => Ok(CellGrid::new(positions, radius)?.all_neighbours()),
            Backend::KdTree => kd_tree_neighbours(positions, radius),
        }
    }

    /// Builds from one list per particle (used by the reference implementation and tests).
    #[must_use]
    pub fn from_lists(radius: f32, lists: &[Vec<u32>]) -> Self {
        let chunks = lists
            .chunks(CHUNK)
            .map(|part| {
                let mut rows = Rows::new(part.len(), part.iter().map(Vec::len).sum());
                for l in part {
                    rows.indices.extend_from_slice(l);
                    rows.end_row();
                }
                rows
            })
            .collect();
        Self::from_chunks(radius, (0..lists.len() as u32).collect(), chunks)
    }

    fn from_chunks(radius: f32, row_of: Vec<u32>, chunks: Vec<Rows>) -> Self {
        let total = chunks.iter().map(|c| c.indices.len()).sum();
        Self {
            radius,
            row_of,
            chunks,
            total,
        }
    }

    /// The search radius.
    #[must_use]
    pub fn radius(&self) -> f32 {
        self.radius
    }

    /// Number of particles.
    #[must_use]
    pub fn len(&self) -> usize {
        self.row_of.len()
    }

    /// True when built over no particle.
    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.row_of.is_empty()
    }

    /// Neighbours of particle `i` (indices into the particle set), in no particular order.
    #[must_use]
    #[inline]
    pub fn of(&self, i: usize) -> &[u32] {
        let row = self.row_of[i] as usize;
        let c = &self.chunks[row / CHUNK];
        let j = row % CHUNK;
        &c.indices[c.ends[j]..c.ends[j + 1]]
    }

    /// Total number of (ordered) neighbour pairs.
    #[must_use]
    pub fn total(&self) -> usize {
        self.total
    }

    /// Mean number of neighbours per particle.
    #[must_use]
    pub fn mean_count(&self) -> f32 {
        if self.is_empty() {
            0.0
        } else {
            self.total() as f32 / self.len() as f32
        }
    }

    /// Memory held, in bytes.
    #[must_use]
    pub fn heap_bytes(&self) -> usize {
        self.row_of.capacity() * 4
            + self
                .chunks
                .iter()
                .map(|c| c.ends.capacity() * 8 + c.indices.capacity() * 4)
                .sum::<usize>()
    }
}

fn check_input(positions: &[Vec3], radius: f32) -> Result<(), NeighbourError> {
    if !(radius.is_finite() && radius > 0.0) {
        return Err(NeighbourError::InvalidRadius { radius });
    }
    if positions.len() > u32::MAX as usize {
        return Err(NeighbourError::TooManyParticles {
            count: positions.len(),
            max: u32::MAX as usize,
        });
    }
    if let Some(index) = positions.par_iter().position_first(|p| !p.is_finite()) {
        return Err(NeighbourError::NonFinitePosition {
            index,
            position: positions[index].to_array(),
        });
    }
    Ok(())
}

/// Where the particles of a run of cells start in the cell-sorted order.
#[derive(Debug)]
enum CellIndex {
    /// `start[key]` for every cell key, plus one final entry.
    Dense(Vec<u32>),
    /// Sorted cell key of every particle; ranges found by binary search.
    Sparse(Vec<u64>),
}

/// A uniform grid of cubic cells with particles sorted by cell.
#[derive(Debug)]
pub struct CellGrid {
    origin: Vec3,
    cell: f32,
    dims: [u64; 3],
    /// positions in cell order, one array per axis (the scans' distances four at a time,
    /// [`near_mask`]), each run on by `LANES - 1` infinite values
    axes: [Vec<f32>; 3],
    /// cell-order slot -> particle index
    order: Vec<u32>,
    index: CellIndex,
}

/// The box of `positions` (lowest and highest corner), found in parallel: the minimum and
/// maximum are exact, so the same box whatever the split (for finite positions; an empty set
/// gives the infinite, inverted box).
#[must_use]
pub fn bounds(positions: &[Vec3]) -> (Vec3, Vec3) {
    let empty = || (Vec3::INFINITY, Vec3::NEG_INFINITY);
    positions
        .par_iter()
        .fold(empty, |(lo, hi), &p| (lo.min(p), hi.max(p)))
        .reduce(empty, |(a, b), (c, d)| (a.min(c), b.max(d)))
}

impl CellGrid {
    /// Sorts `positions` into cells of edge `cell`. Positions must be finite and `cell > 0`.
    pub fn new(positions: &[Vec3], cell: f32) -> Result<Self, NeighbourError> {
        check_input(positions, cell)?;
        let (lo, hi) = bounds(positions);
        let (lo, hi) = if positions.is_empty() {
            (Vec3::ZERO, Vec3::ZERO)
        } else {
            (lo, hi)
        };
        let extent = hi - lo;
        let cells_f = (extent / cell).floor() + Vec3::ONE;
        let dims_f = [cells_f.x as f64, cells_f.y as f64, cells_f.z as f64];
        if dims_f.iter().any(|&d| d > MAX_CELLS_PER_AXIS as f64) {
            return Err(NeighbourError::GridTooLarge {
                cells: dims_f.map(|d| d.min(u64::MAX as f64) as u64),
                extent: extent.to_array(),
                radius: cell,
                max: MAX_CELLS_PER_AXIS,
            });
        }
        let dims = dims_f.map(|d| d as u64);
        let inv = 1.0 / cell;
        // `(p - lo) * inv` is at least 0, so the cast's truncation is the floor (no call into
        // libm per axis: `floorf` is not inlined on the baseline x86-64 target)
        let key_of = |p: Vec3| {
            let c = (p - lo) * inv;
            let cx = (c.x as u64).min(dims[0] - 1);
            let cy = (c.y as u64).min(dims[1] - 1);
            let cz = (c.z as u64).min(dims[2] - 1);
            cx + dims[0] * (cy + dims[1] * cz)
        };
        let keys: Vec<u64> = positions.par_iter().map(|&p| key_of(p)).collect();
        let total_cells = dims[0] * dims[1] * dims[2];
        // A dense start table costs 4 bytes a cell: allow a few cells per particle, and at
        // least 4 MiB, so that sparse surfaces in large boxes stay on the fast path.
        let dense_limit = (8 * positions.len() as u64).max(1 << 20);
        // The particles ordered by (cell key, index), deterministic whatever the thread count:
        // by counting where the start table is dense (one pass, no sort), else by sorting the
        // pairs.
        let (order, index): (Vec<u32>, CellIndex) = if total_cells <= dense_limit {
            let mut start = vec![0u32; total_cells as usize + 1];
            for &k in &keys {
                start[k as usize + 1] += 1;
            }
            for c in 0..total_cells as usize {
                start[c + 1] += start[c];
            }
            let mut next = start[..total_cells as usize].to_vec();
            let mut order = vec![0u32; positions.len()];
            for (i, &k) in keys.iter().enumerate() {
                let slot = &mut next[k as usize];
                order[*slot as usize] = i as u32;
                *slot += 1;
            }
            (order, CellIndex::Dense(start))
        } else {
            let mut keyed: Vec<(u64, u32)> = keys
                .par_iter()
                .enumerate()
                .map(|(i, &k)| (k, i as u32))
                .collect();
            keyed.par_sort_unstable();
            (
                keyed.par_iter().map(|&(_, i)| i).collect(),
                CellIndex::Sparse(keyed.iter().map(|&(k, _)| k).collect()),
            )
        };
        // one array per axis, run on by `LANES - 1` infinite values ([`near_mask`])
        let axis = |c: fn(&Vec3) -> f32| -> Vec<f32> {
            let mut values = Vec::with_capacity(order.len() + LANES - 1);
            values.par_extend(order.par_iter().map(|&i| c(&positions[i as usize])));
            values.extend(std::iter::repeat_n(f32::INFINITY, LANES - 1));
            values
        };
        let axes = [axis(|p| p.x), axis(|p| p.y), axis(|p| p.z)];
        Ok(Self {
            origin: lo,
            cell,
            dims,
            axes,
            order,
            index,
        })
    }

    fn cell_of(&self, p: Vec3) -> [u64; 3] {
        // the cast truncates a float of at least 0 to its floor and takes a negative one (or
        // NaN) to 0, as the floor and the clamp to 0 would
        let c = (p - self.origin) / self.cell;
        [
            (c.x as u64).min(self.dims[0] - 1),
            (c.y as u64).min(self.dims[1] - 1),
            (c.z as u64).min(self.dims[2] - 1),
        ]
    }

    /// Range of cell-order slots covering cells with keys `first..=last`.
    #[inline]
    fn slots(&self, first: u64, last: u64) -> std::ops::Range<usize> {
        match &self.index {
            CellIndex::Dense(start) => {
                start[first as usize] as usize..start[last as usize + 1] as usize
            }
            CellIndex::Sparse(keys) => {
                keys.partition_point(|&k| k < first)..keys.partition_point(|&k| k <= last)
            }
        }
    }

    /// Calls `visit(j)` for every particle `j` within `radius` (<= the cell size) of `p`,
    /// including any particle at `p` itself.
    #[inline]
    pub fn for_each_within(&self, p: Vec3, radius: f32, mut visit: impl FnMut(u32)) {
        self.for_each_slot_within(p, radius, |s, _| visit(self.order[s]));
    }

    /// [`Self::for_each_within`] handing out the particle's cell-order slot and position
    /// (`visit(slot, x_j)`, the particle being [`Self::order`]`[slot]`): the positions are read
    /// where the grid keeps them, in cell order, with no lookup through the particle index.
    #[inline]
    pub fn for_each_slot_within(&self, p: Vec3, radius: f32, mut visit: impl FnMut(usize, Vec3)) {
        let r2 = radius * radius;
        self.for_each_run(p, radius, |range| {
            for block in blocks_of(range, SCAN_BLOCK) {
                let mut near = near_mask(&self.axes, block.clone(), p, r2);
                while near != 0 {
                    let s = block.start + near.trailing_zeros() as usize;
                    near &= near - 1;
                    visit(s, self.position(s));
                }
            }
        });
    }

    /// Calls `run(slots)` for each of the (up to nine) runs of cell-order slots that hold the
    /// particles of the 27 cells around `p`'s cell (one run per row of three cells along x),
    /// which hold every particle within `radius` (<= the cell size) of `p`.
    #[inline]
    fn for_each_run(&self, p: Vec3, radius: f32, mut run: impl FnMut(std::ops::Range<usize>)) {
        let _ = self.try_for_each_run(p, radius, |range| {
            run(range);
            ControlFlow::Continue(())
        });
    }

    /// [`Self::for_each_run`] until `run` breaks.
    #[inline]
    fn try_for_each_run(
        &self,
        p: Vec3,
        radius: f32,
        mut run: impl FnMut(std::ops::Range<usize>) -> ControlFlow<()>,
    ) -> ControlFlow<()> {
        debug_assert!(radius <= self.cell * 1.0001);
        if self.order.is_empty() {
            return ControlFlow::Continue(());
        }
        let [cx, cy, cz] = self.cell_of(p);
        let [nx, ny, nz] = self.dims;
        let x0 = cx.saturating_sub(1);
        let x1 = (cx + 1).min(nx - 1);
        for z in cz.saturating_sub(1)..=(cz + 1).min(nz - 1) {
            for y in cy.saturating_sub(1)..=(cy + 1).min(ny - 1) {
                let row = nx * (y + ny * z);
                run(self.slots(row + x0, row + x1))?;
            }
        }
        ControlFlow::Continue(())
    }

    /// [`Self::for_each_slot_within`] until `visit` breaks, in the same order; returns whether
    /// it broke.
    #[inline]
    pub fn try_for_each_slot_within(
        &self,
        p: Vec3,
        radius: f32,
        mut visit: impl FnMut(usize, Vec3) -> ControlFlow<()>,
    ) -> ControlFlow<()> {
        let r2 = radius * radius;
        self.try_for_each_run(p, radius, |range| {
            for block in blocks_of(range, SCAN_BLOCK) {
                let mut near = near_mask(&self.axes, block.clone(), p, r2);
                while near != 0 {
                    let s = block.start + near.trailing_zeros() as usize;
                    near &= near - 1;
                    visit(s, self.position(s))?;
                }
            }
            ControlFlow::Continue(())
        })
    }

    /// Cell-order slot -> particle index.
    #[must_use]
    pub fn order(&self) -> &[u32] {
        &self.order
    }

    /// The position in cell-order slot `s`, particle [`Self::order`]`[s]`.
    #[must_use]
    #[inline]
    pub fn position(&self, s: usize) -> Vec3 {
        let [xs, ys, zs] = &self.axes;
        Vec3::new(xs[s], ys[s], zs[s])
    }

    /// The neighbourhoods of every particle within the cell size, in parallel.
    #[must_use]
    pub fn all_neighbours(&self) -> Neighbourhoods {
        let n = self.order.len();
        let chunks: Vec<Rows> = (0..n.div_ceil(CHUNK))
            .into_par_iter()
            .map(|c| {
                let slots = c * CHUNK..((c + 1) * CHUNK).min(n);
                let mut rows = Rows::new(slots.len(), slots.len() * 40);
                for s in slots {
                    let me = self.order[s];
                    self.for_each_within(self.position(s), self.cell, |j| {
                        if j != me {
                            rows.indices.push(j);
                        }
                    });
                    rows.end_row();
                }
                rows
            })
            .collect();
        let mut row_of = vec![0u32; n];
        for (s, &i) in self.order.iter().enumerate() {
            row_of[i as usize] = s as u32;
        }
        Neighbourhoods::from_chunks(self.cell, row_of, chunks)
    }
}

fn kd_tree_neighbours(positions: &[Vec3], radius: f32) -> Result<Neighbourhoods, NeighbourError> {
    let n = positions.len();
    if n == 0 {
        return Ok(Neighbourhoods::from_chunks(radius, Vec::new(), Vec::new()));
    }
    let points: Vec<[f32; 3]> = positions.iter().map(|p| p.to_array()).collect();
    let tree: ImmutableKdTree<f32, 3> = ImmutableKdTree::new_from_slice(&points)
        .map_err(|e| NeighbourError::KdTree(format!("{e:?}")))?;
    let r2 = radius * radius;
    let chunks: Vec<Rows> = (0..n.div_ceil(CHUNK))
        .into_par_iter()
        .map(|c| {
            let range = c * CHUNK..((c + 1) * CHUNK).min(n);
            let mut rows = Rows::new(range.len(), range.len() * 40);
            for i in range {
                tree.query(&points[i])
                    .within::<SquaredEuclidean<f32>>(r2)
                    .unsorted()
                    .visit(|nb| {
                        if nb.item as usize != i {
                            rows.indices.push(nb.item);
                        }
                    });
                rows.end_row();
            }
            rows
        })
        .collect();
    Ok(Neighbourhoods::from_chunks(
        radius,
        (0..n as u32).collect(),
        chunks,
    ))
}

/// The straightforward single-threaded neighbour search that benchmarks compare against: a hash
/// map from cell to particle list and one `Vec` of neighbours per particle.
#[must_use]
pub fn reference_neighbours(positions: &[Vec3], radius: f32) -> Vec<Vec<u32>> {
    use std::collections::HashMap;
    let cell_of = |p: Vec3| {
        let c = (p / radius).floor();
        (c.x as i64, c.y as i64, c.z as i64)
    };
    let mut cells: HashMap<(i64, i64, i64), Vec<u32>> = HashMap::new();
    for (i, &p) in positions.iter().enumerate() {
        cells.entry(cell_of(p)).or_default().push(i as u32);
    }
    let r2 = radius * radius;
    positions
        .iter()
        .enumerate()
        .map(|(i, &p)| {
            let (cx, cy, cz) = cell_of(p);
            let mut list = Vec::new();
            for dz in -1..=1 {
                for dy in -1..=1 {
                    for dx in -1..=1 {
                        if let Some(cell) = cells.get(&(cx + dx, cy + dy, cz + dz)) {
                            for &j in cell {
                                if j as usize != i
                                    && positions[j as usize].distance_squared(p) <= r2
                                {
                                    list.push(j);
                                }
                            }
                        }
                    }
                }
            }
            list
        })
        .collect()
}

/// Neighbours counted by [`spacing_estimate`]: enough that the lattice shells of a regular
/// arrangement average out (a simple cubic lattice's 32nd neighbour closes its fourth shell).
pub const SPACING_NEIGHBOURS: usize = 32;

/// What [`spacing_estimate`] found.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct SpacingEstimate {
    /// The particle spacing: the edge of the cube each particle fills, from the local number
    /// density (median over the sample).
    pub spacing: f32,
    /// Median distance to the nearest other particle (shorter than the spacing in a disordered
    /// fluid: about 0.78 of it in SPlisHSPlasH's dam breaks).
    pub nearest: f32,
    /// Particles sampled.
    pub sampled: usize,
    /// Sampled particles left out as isolated (nearest neighbour farther than 2.5x the median).
    pub isolated: usize,
}

/// A hash of a position's bits (splitmix64's finaliser over the three coordinates).
fn position_hash(p: Vec3) -> u64 {
    let mut h = (u64::from(p.x.to_bits()) << 32) ^ u64::from(p.y.to_bits());
    h ^= u64::from(p.z.to_bits()).rotate_left(17);
    h = (h ^ (h >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    h = (h ^ (h >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    h ^ (h >> 31)
}

/// Estimates the particle spacing from the local number density, robustly, over a deterministic
/// sample of about 20,000 particles at most, chosen by their positions (the same for any order of
/// the particles; kiddo k-nearest queries).
///
/// For each sampled particle, `d` is the distance to its [`SPACING_NEIGHBOURS`]-th neighbour
/// (`k`); the ball of radius `d` holds `k + 1` particles, so each fills `(4/3) pi d^3 / (k + 1)`
/// and the spacing is the cube root of that. The median is taken over the particles that are not
/// isolated. Unlike the nearest-neighbour distance (which the disorder of a flowing fluid makes
/// about a fifth shorter than the spacing), this gives the simulation's spacing on real SPH frames
/// (0.048 for SPlisHSPlasH's dam break of spacing 0.05) and exactly the spacing of a lattice; on a
/// sheet one or two particles thick it is larger (0.070 on the double dam break), which is what a
/// kernel needs to close the sheet. Coincident particles count as particles. A set of at most
/// [`SPACING_NEIGHBOURS`] particles has no bulk to count in: its spacing is the median
/// nearest-neighbour distance.
pub fn spacing_estimate(positions: &[Vec3]) -> Result<SpacingEstimate, NeighbourError> {
    check_input(positions, 1.0)?;
    if positions.len() < 2 {
        return Err(NeighbourError::NoSpacing {
            reason: "fewer than two particles",
        });
    }
    let points: Vec<[f32; 3]> = positions.iter().map(|p| p.to_array()).collect();
    let tree: ImmutableKdTree<f32, 3> = ImmutableKdTree::new_from_slice(&points)
        .map_err(|e| NeighbourError::KdTree(format!("{e:?}")))?;
    let step = positions.len().div_ceil(20_000);
    let k = SPACING_NEIGHBOURS.min(positions.len() - 1);
    let query = NonZeroUsize::new(k + 1).expect("k + 1 is not zero");
    // per sampled particle: nearest non-zero distance, and the k-th neighbour's distance. One in
    // `step` particles, chosen by a hash of its position rather than its index, so that the
    // same particles in another order give the same estimate (the dam break's 24,389 particles
    // gave 0.04759 or 0.04758 by the order: another surface, another picture)
    let step = step as u64;
    let sample: Vec<(f32, f32)> = (0..positions.len())
        .into_par_iter()
        .filter(|&i| step == 1 || position_hash(positions[i]).is_multiple_of(step))
        .filter_map(|i| {
            let found = tree
                .query(&points[i])
                .nearest_n::<SquaredEuclidean<f32>>(query)
                .execute();
            let nearest = found.iter().map(|nb| nb.distance).find(|&d2| d2 > 0.0)?;
            let kth = found.last().map_or(nearest, |nb| nb.distance);
            Some((nearest.sqrt(), kth.sqrt()))
        })
        .collect();
    if sample.is_empty() {
        return Err(NeighbourError::NoSpacing {
            reason: "all particles coincide",
        });
    }
    let median = |mut v: Vec<f32>| {
        let mid = v.len() / 2;
        let (_, m, _) = v.select_nth_unstable_by(mid, f32::total_cmp);
        *m
    };
    let nearest = median(sample.iter().map(|s| s.0).collect());
    let kept: Vec<f32> = sample
        .iter()
        .filter(|s| s.0 <= 2.5 * nearest)
        .map(|s| s.1)
        .collect();
    let isolated = sample.len() - kept.len();
    // a set smaller than the count has no bulk to measure a density in: the nearest distance
    let spacing = if k < SPACING_NEIGHBOURS {
        nearest
    } else {
        let d = median(kept);
        (4.0 / 3.0 * std::f32::consts::PI * d.powi(3) / (k as f32 + 1.0)).cbrt()
    };
    Ok(SpacingEstimate {
        spacing,
        nearest,
        sampled: sample.len(),
        isolated,
    })
}

/// The particle spacing of [`spacing_estimate`].
pub fn estimate_spacing(positions: &[Vec3]) -> Result<f32, NeighbourError> {
    spacing_estimate(positions).map(|e| e.spacing)
}

/// The support radius in multiples of the particle spacing that the chain uses when none is given
/// (Solenthaler et al. 2007 §3.1 take the SPH smoothing length; SPH codes set it to about twice
/// the spacing).
pub const SUPPORT_SPACINGS: f32 = 2.0;

/// The support radius the chain uses when none is given: [`SUPPORT_SPACINGS`] times the
/// [`estimate_spacing`] of `positions`. The pipeline, the command line and the Python bindings
/// all take their default radius from here.
pub fn support_radius(positions: &[Vec3]) -> Result<f32, NeighbourError> {
    estimate_spacing(positions).map(|s| SUPPORT_SPACINGS * s)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn seed() -> u64 {
        std::env::var("FLUID_SURFELS_SEED")
            .ok()
            .and_then(|s| s.parse().ok())
            .unwrap_or(0x5eed)
    }

    fn brute_force(positions: &[Vec3], r: f32) -> Vec<Vec<u32>> {
        (0..positions.len())
            .map(|i| {
                (0..positions.len() as u32)
                    .filter(|&j| {
                        j as usize != i
                            && positions[j as usize].distance_squared(positions[i]) <= r * r
                    })
                    .collect()
            })
            .collect()
    }

    fn sorted(mut v: Vec<u32>) -> Vec<u32> {
        v.sort_unstable();
        v
    }

    #[test]
    fn backends_match_brute_force_on_random_clouds() {
        let seed = seed();
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        for case in 0..20 {
            let n = rng.random_range(0..600);
            let scale = [0.01f32, 1.0, 1000.0][case % 3];
            let mut positions: Vec<Vec3> = (0..n)
                .map(|_| Vec3::new(rng.random(), rng.random(), rng.random()) * scale)
                .collect();
            if n > 10 {
                // coincident points and a far outlier (forces the sparse index)
                positions[3] = positions[2];
                positions[5] = Vec3::splat(scale * 1e3);
            }
            let r = scale * rng.random_range(0.02..0.3);
            let truth = brute_force(&positions, r);
            for backend in [Backend::CellGrid, Backend::KdTree] {
                let nb = Neighbourhoods::build(&positions, r, backend).unwrap();
                assert_eq!(nb.len(), n);
                for (i, expected) in truth.iter().enumerate() {
                    assert_eq!(
                        sorted(nb.of(i).to_vec()),
                        *expected,
                        "seed {seed} (FLUID_SURFELS_SEED), case {case}, backend {backend:?}, particle {i}"
                    );
                }
            }
            let reference = reference_neighbours(&positions, r);
            for i in 0..n {
                assert_eq!(
                    sorted(reference[i].clone()),
                    truth[i],
                    "seed {seed}, case {case}"
                );
            }
        }
    }

    #[test]
    fn near_masks_pass_the_particles_a_scalar_test_passes() {
        let seed = seed();
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let n = 200;
        let mut positions: Vec<Vec3> = (0..n)
            .map(|_| Vec3::new(rng.random(), rng.random(), rng.random()))
            .collect();
        // one exactly at the radius, one at the query itself
        let p = Vec3::new(0.5, 0.5, 0.5);
        positions[7] = p + Vec3::new(0.25, 0.0, 0.0);
        positions[40] = p;
        let grid = CellGrid::new(&positions, 1.0).unwrap();
        let r2 = 0.25f32 * 0.25;
        for start in [0, 5, 31, 100, 168] {
            for len in 1..=SCAN_BLOCK {
                let block = start..start + len;
                let mask = near_mask(&grid.axes, block.clone(), p, r2);
                for (bit, s) in block.clone().enumerate() {
                    let near = grid.position(s).distance_squared(p) <= r2;
                    assert_eq!(
                        mask >> bit & 1 == 1,
                        near,
                        "seed {seed}, slot {s} of {block:?}"
                    );
                }
                if len < SCAN_BLOCK {
                    assert_eq!(mask >> len, 0, "seed {seed}: bits beyond {block:?}");
                }
            }
        }
    }

    #[test]
    fn degenerate_inputs() {
        assert_eq!(
            Neighbourhoods::build(&[Vec3::ZERO], 0.0, Backend::CellGrid).unwrap_err(),
            NeighbourError::InvalidRadius { radius: 0.0 }
        );
        assert!(matches!(
            Neighbourhoods::build(&[Vec3::ZERO], f32::NAN, Backend::KdTree),
            Err(NeighbourError::InvalidRadius { .. })
        ));
        assert!(matches!(
            Neighbourhoods::build(
                &[Vec3::ZERO, Vec3::new(f32::NAN, 0.0, 0.0)],
                1.0,
                Backend::CellGrid
            ),
            Err(NeighbourError::NonFinitePosition { index: 1, .. })
        ));
        for backend in [Backend::CellGrid, Backend::KdTree] {
            let empty = Neighbourhoods::build(&[], 1.0, backend).unwrap();
            assert!(empty.is_empty());
            let one = Neighbourhoods::build(&[Vec3::ONE], 1.0, backend).unwrap();
            assert!(one.of(0).is_empty());
            let same = Neighbourhoods::build(&[Vec3::ONE; 4], 1.0, backend).unwrap();
            assert_eq!(same.of(0).len(), 3);
        }
        let far = [Vec3::ZERO, Vec3::splat(1e30)];
        assert!(matches!(
            Neighbourhoods::build(&far, 1e-6, Backend::CellGrid),
            Err(NeighbourError::GridTooLarge { .. })
        ));
    }

    #[test]
    fn spacing_of_a_lattice_and_of_a_jittered_one() {
        let lattice = |n: usize| -> Vec<Vec3> {
            (0..n * n * n)
                .map(|i| Vec3::new((i % n) as f32, ((i / n) % n) as f32, (i / n / n) as f32) * 0.05)
                .collect()
        };
        let e = spacing_estimate(&lattice(30)).unwrap();
        assert!((e.spacing - 0.05).abs() < 0.0005, "{e:?}");
        assert!((e.nearest - 0.05).abs() < 1e-6, "{e:?}");
        // 27,000 > 20,000: one particle in two sampled, chosen by position
        assert!(e.sampled.abs_diff(13_500) < 300 && e.isolated == 0, "{e:?}");
        // the same particles in reverse order: the same sample, the same estimate
        let mut reversed = lattice(30);
        reversed.reverse();
        assert_eq!(spacing_estimate(&reversed).unwrap(), e);
        // jittered by a fifth of the spacing: nearest distances shrink, the spacing holds (4 %;
        // the surface particles, a third of a 30^3 block, see half-empty balls)
        let mut rng = ChaCha8Rng::seed_from_u64(seed());
        let jittered: Vec<Vec3> = lattice(30)
            .into_iter()
            .map(|p| p + Vec3::from_array([(); 3].map(|()| rng.random_range(-0.01..0.01))))
            .collect();
        let j = spacing_estimate(&jittered).unwrap();
        assert!(j.nearest < 0.045, "{j:?}");
        assert!((j.spacing - 0.05).abs() < 0.002, "{j:?}");
        // far-away lone particles are left out and do not move the estimate
        let mut spray = lattice(30);
        spray.extend((0..500).map(|i| Vec3::new(10.0 + i as f32, 5.0, 5.0)));
        let s = spacing_estimate(&spray).unwrap();
        // (one particle in two sampled: 27,500 > 20,000)
        assert!(
            s.sampled.abs_diff(13_750) < 300 && s.isolated.abs_diff(250) < 40,
            "{s:?}"
        );
        assert!((s.spacing - e.spacing).abs() < 1e-4, "{s:?} {e:?}");
        // a small set: the nearest distance
        let few = spacing_estimate(&lattice(3)).unwrap();
        assert_eq!(few.spacing, few.nearest);
        assert!((few.spacing - 0.05).abs() < 1e-6, "{few:?}");
        assert!(estimate_spacing(&[Vec3::ONE; 3]).is_err());
        assert!(estimate_spacing(&[Vec3::ONE]).is_err());
    }
}
