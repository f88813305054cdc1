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
    let inv = 1.0 / spec.spacing;
    let h = points.h;
    for &p in cluster {
        let x = points.positions[p as usize];
        let hj = points.radius(p as usize);
        for dk in 0..planes {
            let z = spec.origin.z + (k0 + dk) as f32 * spec.spacing;
            let dz = x.z - z;
            if dz.abs() >= hj {
                continue;
            }
            // the disk where the particle's ball meets this plane (§4.1)
            let disk = (hj * hj - dz * dz).sqrt();
            let i0 = (((x.x - disk - spec.origin.x) * inv).ceil().max(0.0)) as u32;
            let i1 = (((x.x + disk - spec.origin.x) * inv)
                .floor()
                .min((nx - 1) as f32)) as i64;
            let j0 = (((x.y - disk - spec.origin.y) * inv).ceil().max(0.0)) as u32;
            let j1 = (((x.y + disk - spec.origin.y) * inv)
                .floor()
                .min((ny - 1) as f32)) as i64;
            let base = dk as usize * plane;
            for j in j0 as i64..=j1 {
                let y = spec.origin.y + j as f32 * spec.spacing;
                let row = base + j as usize * nx as usize;
                let dy = y - x.y;
                let dyz2 = dy * dy + dz * dz;
                // the whole row of the disk's square: the kernel is zero outside the ball, and
                // a short branch-free loop beats computing each row's chord
                let (a, b) = (i0 as i64, i1);
                if b < a {
                    continue;
                }
                let cells = &mut slab[row + a as usize..=row + b as usize];
                for (t, v) in cells.iter_mut().enumerate() {
                    let dx = spec.origin.x + (a as usize + t) as f32 * spec.spacing - x.x;
                    *v += kernel.weighted_r2(dx * dx + dyz2, hj, h);
                }
            }
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
    let positions = points.positions;
    let reach = points.max_radius();
    let [nx, ny, nz] = spec.dims;
    let plane = nx as usize * ny as usize;
    // z-clustering (§4.2): particles sorted by z; a slab takes those within the largest radius
    // of its planes (each point still tests its own radius)
    let mut order: Vec<u32> = (0..positions.len() as u32).collect();
    order.par_sort_unstable_by(|&a, &b| {
        positions[a as usize]
            .z
            .total_cmp(&positions[b as usize].z)
            .then(a.cmp(&b))
    });
    let zs: Vec<f32> = order.iter().map(|&i| positions[i as usize].z).collect();
    let slabs: Vec<u32> = (0..nz).step_by(slab_planes as usize).collect();
    let batch = 2 * rayon::current_num_threads().max(1);
    for group in slabs.chunks(batch) {
        let filled: Vec<(u32, Vec<f32>)> = group
            .par_iter()
            .map(|&k0| {
                let planes = slab_planes.min(nz - k0);
                let z_lo = spec.origin.z + k0 as f32 * spec.spacing - reach;
                let z_hi = spec.origin.z + (k0 + planes - 1) as f32 * spec.spacing + reach;
                let a = zs.partition_point(|&z| z <= z_lo);
                let b = zs.partition_point(|&z| z < z_hi);
                // the cluster in particle order, so that sums do not depend on the slab size
                let mut cluster = order[a..b.max(a)].to_vec();
                cluster.sort_unstable();
                let mut slab = vec![0.0f32; plane * planes as usize];
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

/// The whole density grid, filled by [`splat_slabs`]; refused when it would need more than
/// `memory_limit` bytes.
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
    values.clear();
    values.reserve(spec.cells() as usize);
    splat_points_slabs(points, spec, kernel, 4, |_, slab| {
        values.extend_from_slice(&slab)
    })?;
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
    spec.check_memory(crate::io::available_memory())?;
    let [nx, ny, nz] = spec.dims;
    let mut values = vec![0.0f32; spec.cells() as usize];
    for (p, &x) in points.positions.iter().enumerate() {
        let hj = points.radius(p);
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
                    let v = kernel.weighted_r2(d.x * d.x + dyz2, hj, points.h);
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

/// [`points_grid_in`] restricted to the narrow band `band` of the same points (its voxels at
/// least as wide as the largest radius): the points deep inside (their voxel and its 26
/// neighbours all interior, label 0) are not splatted, and every grid point in an interior voxel
/// is set to `inside` (a value above the iso-value). Why that keeps the surface: a point reaches
/// only the voxels next to its own, so no deep point reaches a band voxel or an empty one; their
/// grid points get the same sums in the same order as the whole grid's, bit for bit, and the
/// iso-surface lies there. Only an interior voxel whose true density is below the iso-value (a
/// cavity smaller than a voxel) would read otherwise. Returns the grid and the points skipped.
pub fn points_grid_in_band(
    points: Points<'_>,
    spec: &GridSpec,
    kernel: Kernel,
    memory_limit: u64,
    values: Vec<f32>,
    band: &crate::lnm::NarrowBand,
    inside: f32,
) -> Result<(DensityGrid, usize), DensityError> {
    points.check()?;
    if band.voxel_of.len() != points.len() || band.edge < points.max_radius() {
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
    // deep: interior and every neighbour full and interior
    let deep: Vec<bool> = band
        .voxels
        .par_iter()
        .map(|v| {
            v.label == 0
                && (0..27i64).filter(|&k| k != 13).all(|k| {
                    let d = [k % 3 - 1, (k / 3) % 3 - 1, k / 9 - 1];
                    let c: [i64; 3] = std::array::from_fn(|a| i64::from(v.coord[a]) + d[a]);
                    c.iter().all(|&x| x >= 0)
                        && band
                            .voxel_at(c.map(|x| x as u32))
                            .is_some_and(|j| band.voxels[j].label == 0)
                })
        })
        .collect();
    let kept: Vec<usize> = (0..points.len())
        .filter(|&i| !deep[band.voxel_of[i] as usize])
        .collect();
    let positions: Vec<Vec3> = kept.iter().map(|&i| points.positions[i]).collect();
    let radii: Vec<f32> = kept.iter().map(|&i| points.radius(i)).collect();
    let mut grid = points_grid_in(
        Points::with_radii(&positions, &radii, points.h),
        spec,
        kernel,
        memory_limit,
        values,
    )?;
    // the grid points in interior voxels, found as the band finds a particle's voxel
    let inv = 1.0 / band.edge;
    let [nx, ny, _] = spec.dims;
    let voxel_of = |p: Vec3| -> [u32; 3] {
        let c = ((p - band.origin) * inv).floor();
        let at = |v: f32, n: u32| (v.max(0.0) as u32).min(n - 1);
        [
            at(c.x, band.dims[0]),
            at(c.y, band.dims[1]),
            at(c.z, band.dims[2]),
        ]
    };
    let plane = nx as usize * ny as usize;
    grid.values
        .par_chunks_mut(plane)
        .enumerate()
        .for_each(|(k, slice)| {
            for j in 0..ny {
                // a row crosses a voxel every few grid points: look each up once
                let mut last: Option<([u32; 3], bool)> = None;
                for i in 0..nx {
                    let c = voxel_of(spec.point(i, j, k as u32));
                    let interior = match last {
                        Some((l, b)) if l == c => b,
                        _ => {
                            let b = band.voxel_at(c).is_some_and(|v| band.voxels[v].label == 0);
                            last = Some((c, b));
                            b
                        }
                    };
                    if interior {
                        slice[j as usize * nx as usize + i as usize] = inside;
                    }
                }
            }
        });
    Ok((grid, points.len() - kept.len()))
}
