//! The density grid on the CPU: slab by slab along z, each slab from the points within reach of
//! it (z-clustering, §4.2), in parallel, handed to a sink in order; and the naive reference.

use glam::Vec3;
use rayon::prelude::*;

use super::{DensityError, DensityGrid, GridSpec, Kernel, Points};

/// Adds every point of `cluster` to the planes `k0..k0 + planes.len() / plane_len` of `slab`.
fn splat_slab(
    spec: &GridSpec,
    kernel: Kernel,
    points: &Points<'_>,
    cluster: &[u32],
    k0: u32,
    slab: &mut [f32],
) {
    let [nx, ny, _] = spec.dims;
    let plane = nx as usize * ny as usize;
    let planes = (slab.len() / plane) as u32;
    let whole = Window {
        lo: [0, 0],
        hi: [nx - 1, ny - 1],
        stride: nx as usize,
    };
    let columns: Vec<f32> = (0..nx).map(|i| column(spec, i)).collect();
    for &p in cluster {
        let x = points.positions[p as usize];
        let hj = points.radius(p as usize);
        let w = points.weight(p as usize);
        for dk in 0..planes {
            let base = dk as usize * plane;
            splat_disk(
                spec,
                kernel,
                x,
                (hj, w),
                points.h,
                k0 + dk,
                &whole,
                &columns,
                &mut slab[base..base + plane],
            );
        }
    }
}

/// The grid points of one z plane a splat may write: `[lo, hi]` in x and y (inclusive), stored
/// from `lo` with `stride` values per row.
pub(super) struct Window {
    pub lo: [u32; 2],
    pub hi: [u32; 2],
    pub stride: usize,
}

/// Where the ball of the point `x` (radius `hj`) meets grid plane `k` (§4.1): `dz` and the
/// square of grid points around the disk, `(dz, [i0, j0], [i1, j1])` (inclusive, the upper ends
/// negative when the disk misses the grid), or `None` when the ball misses the plane. The dense
/// slabs and the sparse blocks ([`super::sparse`]) both go through it and through [`term`], so
/// a grid point gets the same sum, bit for bit, whichever stores it.
#[inline(always)]
pub(super) fn disk(spec: &GridSpec, x: Vec3, hj: f32, k: u32) -> Option<(f32, [i64; 2], [i64; 2])> {
    let [nx, ny, _] = spec.dims;
    let inv = 1.0 / spec.spacing;
    let z = spec.origin.z + k as f32 * spec.spacing;
    let dz = x.z - z;
    if dz.abs() >= hj {
        return None;
    }
    let disk = (hj * hj - dz * dz).sqrt();
    let i0 = ceil((x.x - disk - spec.origin.x) * inv).max(0.0) as i64;
    let i1 = floor((x.x + disk - spec.origin.x) * inv).min((nx - 1) as f32) as i64;
    let j0 = ceil((x.y - disk - spec.origin.y) * inv).max(0.0) as i64;
    let j1 = floor((x.y + disk - spec.origin.y) * inv).min((ny - 1) as f32) as i64;
    Some((dz, [i0, j0], [i1, j1]))
}

/// `v.floor()` as an integer would read it, without the library call (`floorf` is not inlined
/// on the baseline x86-64 target, and the splats call it four times per plane): exact for
/// `|v| < 2^23` by truncation, and every float at least that large is an integer already. Only
/// the sign of a zero may differ, which no integer conversion sees.
#[inline(always)]
pub(super) fn floor(v: f32) -> f32 {
    // NaN, infinities and floats of 2^23 and more: already integral (or not numbers)
    if v.abs() >= 8_388_608.0 || v.is_nan() {
        return v;
    }
    let t = v as i32 as f32;
    if t > v { t - 1.0 } else { t }
}

/// `v.ceil()` as [`floor`] computes `floor`.
#[inline(always)]
pub(super) fn ceil(v: f32) -> f32 {
    // NaN, infinities and floats of 2^23 and more: already integral (or not numbers)
    if v.abs() >= 8_388_608.0 || v.is_nan() {
        return v;
    }
    let t = v as i32 as f32;
    if t < v { t + 1.0 } else { t }
}

/// `dy^2 + dz^2` of row `j` of a plane, for [`term`].
#[inline(always)]
pub(super) fn row_offset(spec: &GridSpec, x: Vec3, dz: f32, j: i64) -> f32 {
    let y = spec.origin.y + j as f32 * spec.spacing;
    let dy = y - x.y;
    dy * dy + dz * dz
}

/// The x coordinate of grid column `i`, for [`term`] (computed once per column: the same value
/// the expression gives in the loop, without a conversion per kernel).
#[inline(always)]
pub(super) fn column(spec: &GridSpec, i: u32) -> f32 {
    spec.origin.x + i as f32 * spec.spacing
}

/// The kernel of the point `x` at the grid point of [`column`] `gx` in a row whose
/// [`row_offset`] is `dyz2`.
#[inline(always)]
pub(super) fn term(kernel: Kernel, gx: f32, x: Vec3, hj: f32, h: f32, dyz2: f32) -> f32 {
    let dx = gx - x.x;
    kernel.weighted_r2(dx * dx + dyz2, hj, h)
}

/// Adds the kernel of the point `x` (radius `hj` and weight `w`, reference radius `h`) to the
/// grid points of plane `k` inside `window`; `columns[i]` is [`column`] `i`. A weight of 1 adds
/// exactly the unweighted term.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
pub(super) fn splat_disk(
    spec: &GridSpec,
    kernel: Kernel,
    x: Vec3,
    (hj, w): (f32, f32),
    h: f32,
    k: u32,
    window: &Window,
    columns: &[f32],
    plane: &mut [f32],
) {
    let Some((dz, lo, hi)) = disk(spec, x, hj, k) else {
        return;
    };
    let (a, b) = (
        lo[0].max(i64::from(window.lo[0])),
        hi[0].min(i64::from(window.hi[0])),
    );
    if b < a {
        return;
    }
    for j in lo[1].max(i64::from(window.lo[1]))..=hi[1].min(i64::from(window.hi[1])) {
        let dyz2 = row_offset(spec, x, dz, j);
        let row = (j as usize - window.lo[1] as usize) * window.stride;
        // the whole row of the disk's square: the kernel is zero outside the ball, and a short
        // branch-free loop beats computing each row's chord
        let start = row + (a as usize - window.lo[0] as usize);
        let cells = &mut plane[start..=start + (b - a) as usize];
        let xs = &columns[a as usize..=b as usize];
        for (v, &gx) in cells.iter_mut().zip(xs) {
            *v += w * term(kernel, gx, x, hj, h, dyz2);
        }
    }
}

/// Fills the grid slab by slab (`slab_planes` z planes each) and hands each slab to `sink(k0,
/// values)` in increasing z. Slabs are computed in parallel, a few at a time, so that only
/// `2 x threads` slabs are held at once. Every particle has the effective radius `h`.
pub fn splat_slabs(
    positions: &[Vec3],
    spec: &GridSpec,
    kernel: Kernel,
    h: f32,
    slab_planes: u32,
    sink: impl FnMut(u32, Vec<f32>),
) -> Result<(), DensityError> {
    splat_points_slabs(
        Points::uniform(positions, h),
        spec,
        kernel,
        slab_planes,
        sink,
    )
}

/// [`splat_slabs`] for points with a radius each.
pub fn splat_points_slabs(
    points: Points<'_>,
    spec: &GridSpec,
    kernel: Kernel,
    slab_planes: u32,
    mut sink: impl FnMut(u32, Vec<f32>),
) -> Result<(), DensityError> {
    points.check()?;
    if slab_planes == 0 {
        return Err(DensityError::InvalidGrid {
            name: "slab_planes",
            reason: "must be at least 1".into(),
        });
    }
    let [_, _, nz] = spec.dims;
    let plane = spec.dims[0] as usize * spec.dims[1] as usize;
    let clusters = Clusters::new(&points, spec);
    let slabs: Vec<u32> = (0..nz).step_by(slab_planes as usize).collect();
    let batch = 2 * rayon::current_num_threads().max(1);
    for group in slabs.chunks(batch) {
        let filled: Vec<(u32, Vec<f32>)> = group
            .par_iter()
            .map(|&k0| {
                let planes = slab_planes.min(nz - k0);
                let mut slab = vec![0.0f32; plane * planes as usize];
                let cluster = clusters.of(k0, planes);
                splat_slab(spec, kernel, &points, &cluster, k0, &mut slab);
                (k0, slab)
            })
            .collect();
        for (k0, slab) in filled {
            sink(k0, slab);
        }
    }
    Ok(())
}

/// The points sorted by z for the slabs' clusters (z-clustering, §4.2): a slab takes the
/// points within the largest radius of its planes.
struct Clusters {
    /// point indices by z (ties by index)
    order: Vec<u32>,
    /// their z, in that order
    zs: Vec<f32>,
    /// the largest radius
    reach: f32,
    origin_z: f32,
    spacing: f32,
}

impl Clusters {
    fn new(points: &Points<'_>, spec: &GridSpec) -> Self {
        let positions = points.positions;
        let mut order: Vec<u32> = (0..positions.len() as u32).collect();
        order.par_sort_unstable_by(|&a, &b| {
            positions[a as usize]
                .z
                .total_cmp(&positions[b as usize].z)
                .then(a.cmp(&b))
        });
        let zs = order.iter().map(|&i| positions[i as usize].z).collect();
        Self {
            order,
            zs,
            reach: points.max_radius(),
            origin_z: spec.origin.z,
            spacing: spec.spacing,
        }
    }

    /// The points within the largest radius of the `planes` planes from `k0` (each point still
    /// tests its own radius), in the points' order, so that sums do not depend on the slab size.
    fn of(&self, k0: u32, planes: u32) -> Vec<u32> {
        let z_lo = self.origin_z + k0 as f32 * self.spacing - self.reach;
        let z_hi = self.origin_z + (k0 + planes - 1) as f32 * self.spacing + self.reach;
        let a = self.zs.partition_point(|&z| z <= z_lo);
        let b = self.zs.partition_point(|&z| z < z_hi);
        let mut cluster = self.order[a..b.max(a)].to_vec();
        cluster.sort_unstable();
        cluster
    }
}

/// Planes of a slab that [`points_grid_in`] fills in one task.
const SLAB_PLANES: u32 = 4;

/// The whole density grid (the values [`splat_slabs`] hands out, filled in place); refused
/// when it would need more than `memory_limit` bytes.
pub fn density_grid(
    positions: &[Vec3],
    spec: &GridSpec,
    kernel: Kernel,
    h: f32,
    memory_limit: u64,
) -> Result<DensityGrid, DensityError> {
    points_grid(Points::uniform(positions, h), spec, kernel, memory_limit)
}

/// [`density_grid`] for points with a radius each.
pub fn points_grid(
    points: Points<'_>,
    spec: &GridSpec,
    kernel: Kernel,
    memory_limit: u64,
) -> Result<DensityGrid, DensityError> {
    points_grid_in(points, spec, kernel, memory_limit, Vec::new())
}

/// [`points_grid`] into a buffer that earlier frames allocated (a sequence's workspace): its
/// capacity is reused, its contents replaced.
pub fn points_grid_in(
    points: Points<'_>,
    spec: &GridSpec,
    kernel: Kernel,
    memory_limit: u64,
    mut values: Vec<f32>,
) -> Result<DensityGrid, DensityError> {
    points.check()?;
    spec.check_memory(memory_limit)?;
    // the slabs filled in place, each zeroed by its task (a buffer of earlier frames keeps its
    // pages: no fresh allocation to fault in and copy a slab at a time, 14.6 MB a frame for the
    // dam break at two steps)
    let cells = spec.cells() as usize;
    values.resize(cells, 0.0);
    if cells > 0 {
        let plane = spec.dims[0] as usize * spec.dims[1] as usize;
        let clusters = Clusters::new(&points, spec);
        values
            .par_chunks_mut(plane * SLAB_PLANES as usize)
            .enumerate()
            .for_each(|(s, slab)| {
                slab.fill(0.0);
                let k0 = s as u32 * SLAB_PLANES;
                let cluster = clusters.of(k0, (slab.len() / plane) as u32);
                splat_slab(spec, kernel, &points, &cluster, k0, slab);
            });
    }
    Ok(DensityGrid {
        spec: *spec,
        values,
    })
}

/// The naive reference: every particle against every grid point of its bounding box, one thread.
pub fn density_naive(
    positions: &[Vec3],
    spec: &GridSpec,
    kernel: Kernel,
    h: f32,
) -> Result<DensityGrid, DensityError> {
    points_naive(Points::uniform(positions, h), spec, kernel)
}

/// [`density_naive`] for points with a radius each.
pub fn points_naive(
    points: Points<'_>,
    spec: &GridSpec,
    kernel: Kernel,
) -> Result<DensityGrid, DensityError> {
    points.check()?;
    spec.check_memory(crate::memory::available_memory())?;
    let [nx, ny, nz] = spec.dims;
    let mut values = vec![0.0f32; spec.cells() as usize];
    for (p, &x) in points.positions.iter().enumerate() {
        let hj = points.radius(p);
        let w = points.weight(p);
        let lo_index = |v: f32, o: f32| ((v - hj - o) / spec.spacing).ceil().max(0.0) as u32;
        let hi_index = |v: f32, o: f32, n: u32| {
            (((v + hj - o) / spec.spacing).floor().max(-1.0) as i64).min(n as i64 - 1)
        };
        for k in lo_index(x.z, spec.origin.z) as i64..=hi_index(x.z, spec.origin.z, nz) {
            for j in lo_index(x.y, spec.origin.y) as i64..=hi_index(x.y, spec.origin.y, ny) {
                for i in lo_index(x.x, spec.origin.x) as i64..=hi_index(x.x, spec.origin.x, nx) {
                    let d = spec.point(i as u32, j as u32, k as u32) - x;
                    // the same operations as the slab splatting: bit-identical sums
                    let dyz2 = d.y * d.y + d.z * d.z;
                    let v = w * kernel.weighted_r2(d.x * d.x + dyz2, hj, points.h);
                    values[i as usize + nx as usize * (j as usize + ny as usize * k as usize)] += v;
                }
            }
        }
    }
    Ok(DensityGrid {
        spec: *spec,
        values,
    })
}
