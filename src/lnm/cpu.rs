//! The narrow band on the CPU (rayon): sort the particles by voxel, label the full voxels.

use std::collections::HashMap;
use std::hash::{BuildHasherDefault, Hasher};

use glam::Vec3;
use rayon::prelude::*;

use super::{BandVoxel, LnmError, LnmParams, NarrowBand};

/// Bits of a voxel coordinate in a key (three of them in a `u64`).
const BITS: u32 = 21;
/// Most voxels along an axis.
const MAX_AXIS: u64 = 1 << BITS;

fn key([x, y, z]: [u32; 3]) -> u64 {
    u64::from(x) | (u64::from(y) << BITS) | (u64::from(z) << (2 * BITS))
}

fn coord(k: u64) -> [u32; 3] {
    let m = MAX_AXIS - 1;
    [
        (k & m) as u32,
        ((k >> BITS) & m) as u32,
        ((k >> (2 * BITS)) & m) as u32,
    ]
}

/// A hasher for voxel keys: a multiplicative mix (Fibonacci hashing) of the one `u64`.
#[derive(Default)]
struct KeyHasher(u64);

impl Hasher for KeyHasher {
    fn finish(&self) -> u64 {
        self.0
    }

    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.write_u64(u64::from(b) ^ self.0.rotate_left(8));
        }
    }

    fn write_u64(&mut self, k: u64) {
        let h = (k ^ self.0).wrapping_mul(0x9E37_79B9_7F4A_7C15);
        self.0 = h ^ (h >> 29);
    }
}

type VoxelTable = HashMap<u64, u32, BuildHasherDefault<KeyHasher>>;

/// The 26 offsets of the 1-ring.
fn ring() -> impl Iterator<Item = [i64; 3]> {
    (0..27)
        .filter(|&k| k != 13)
        .map(|k| [k % 3 - 1, (k / 3) % 3 - 1, k / 9 - 1])
}

/// The voxel of `p` in a domain from `lo` of voxels `1 / inv` wide, `dims` along each axis,
/// clamped into it: `floor((p - lo) * inv)`, times the inverse edge and not divided by the edge,
/// as a product is correctly rounded in WGSL too (a quotient only within 2.5 ulp), so that the
/// GPU's passes (`lnm.wgsl`'s `cs_count`) find the same voxels.
pub(crate) fn voxel_at(p: Vec3, lo: Vec3, inv: f32, dims: [u32; 3]) -> [u32; 3] {
    let c = ((p - lo) * inv).floor();
    let at = |v: f32, n: u32| (v.max(0.0) as u32).min(n - 1);
    [at(c.x, dims[0]), at(c.y, dims[1]), at(c.z, dims[2])]
}

/// The index of voxel `c` in the dense layout of `dims` voxels (x fastest, then y, then z: the
/// CPU's key order).
pub(crate) fn dense_index(c: [u32; 3], dims: [u32; 3]) -> usize {
    c[0] as usize + dims[0] as usize * (c[1] as usize + dims[1] as usize * c[2] as usize)
}

/// The domain of the band: its minimum corner, the voxel edge and the voxels along each axis,
/// with every input checked (shared by the CPU and GPU paths).
pub(crate) fn domain(
    positions: &[Vec3],
    support_radius: f32,
    params: &LnmParams,
) -> Result<(Vec3, f32, [u32; 3]), LnmError> {
    params.validate()?;
    if !(support_radius.is_finite() && support_radius > 0.0) {
        return Err(LnmError::InvalidParameter {
            name: "support_radius",
            reason: "must be finite and > 0".into(),
        });
    }
    if let Some(index) = positions.par_iter().position_any(|p| !p.is_finite()) {
        return Err(LnmError::NonFinite { index });
    }
    let edge = params.voxel_in_radii * support_radius;
    let (lo, hi) = match params.domain {
        Some([lo, hi]) => (Vec3::from(lo), Vec3::from(hi)),
        None if positions.is_empty() => (Vec3::ZERO, Vec3::ZERO),
        None => crate::neighbours::bounds(positions),
    };
    let span = ((hi - lo) / edge).floor();
    let voxels = [span.x, span.y, span.z].map(|v| v as u64 + 1);
    if voxels.iter().any(|&v| v >= MAX_AXIS) || !span.is_finite() {
        return Err(LnmError::TooManyVoxels {
            voxels,
            edge,
            max: MAX_AXIS - 1,
        });
    }
    Ok((lo, edge, voxels.map(|v| v as u32)))
}

/// The narrow band of `positions` with kernel support `support_radius` (Algorithm 1).
pub fn narrow_band(
    positions: &[Vec3],
    support_radius: f32,
    params: &LnmParams,
) -> Result<NarrowBand, LnmError> {
    narrow_band_in(positions, support_radius, params, Layout::Auto)
}

/// The band over sparse voxel keys: the particles sorted by voxel, the full voxels looked up by
/// hash.
fn sparse_band(
    positions: &[Vec3],
    lo: Vec3,
    edge: f32,
    dims: [u32; 3],
    params: &LnmParams,
) -> NarrowBand {
    let inv = 1.0 / edge;
    let voxel_of = |p: Vec3| -> u64 { key(voxel_at(p, lo, inv, dims)) };
    // (key, index) pairs sorted together: no lookup of a key through its index while sorting
    let mut pairs: Vec<(u64, u32)> = positions
        .par_iter()
        .enumerate()
        .map(|(i, &p)| (voxel_of(p), i as u32))
        .collect();
    pairs.par_sort_unstable();
    let order: Vec<u32> = pairs.par_iter().map(|&(_, i)| i).collect();
    // runs of one voxel: (key, start in `order`, count)
    let mut runs: Vec<(u64, u32, u32)> = Vec::new();
    for (s, &(k, _)) in pairs.iter().enumerate() {
        match runs.last_mut() {
            Some(r) if r.0 == k => r.2 += 1,
            _ => runs.push((k, s as u32, 1)),
        }
    }
    let mut table = VoxelTable::with_capacity_and_hasher(runs.len(), Default::default());
    for (v, r) in runs.iter().enumerate() {
        table.insert(r.0, v as u32);
    }
    let neighbour = |c: [u32; 3], d: [i64; 3]| -> Option<Option<u32>> {
        // None: outside the domain; Some(None): empty; Some(Some(v)): full voxel v
        let n: [i64; 3] = std::array::from_fn(|a| i64::from(c[a]) + d[a]);
        if (0..3).any(|a| n[a] < 0 || n[a] >= i64::from(dims[a])) {
            return None;
        }
        Some(table.get(&key(n.map(|v| v as u32))).copied())
    };
    let labels = layers(&runs, dims, params.n_min, neighbour);
    finish(positions, lo, edge, dims, &runs, &order, &labels)
}

/// Algorithm 1's two labelling passes over the full voxels (`(key, start, count)`), in
/// parallel: `neighbour(c, d)` is the voxel at `c + d`: `None` outside the domain, `Some(None)`
/// empty, `Some(Some(v))` the full voxel `v`. Layer 1: on the domain's border or next to an
/// empty voxel; layer 2: the other full voxels next to a layer-1 voxel of at most `n_min`
/// particles.
fn layers(
    runs: &[(u64, u32, u32)],
    dims: [u32; 3],
    n_min: u32,
    neighbour: impl Fn([u32; 3], [i64; 3]) -> Option<Option<u32>> + Sync,
) -> Vec<u8> {
    let first: Vec<bool> = runs
        .par_iter()
        .map(|r| {
            let c = coord(r.0);
            (0..3).any(|a| c[a] == 0 || c[a] + 1 == dims[a])
                || ring().any(|d| neighbour(c, d) == Some(None))
        })
        .collect();
    runs.par_iter()
        .zip(&first)
        .map(|(r, &one)| {
            if one {
                return 1;
            }
            let c = coord(r.0);
            let thin = ring().any(|d| {
                neighbour(c, d)
                    .flatten()
                    .is_some_and(|v| first[v as usize] && runs[v as usize].2 <= n_min)
            });
            if thin { 2 } else { 0 }
        })
        .collect()
}

/// The band from the full voxels (`(key, start, count)` in key order, their particles at
/// `order[start..start + count]` in index order) and their labels: centroids, and every
/// particle's label and voxel.
fn finish(
    positions: &[Vec3],
    lo: Vec3,
    edge: f32,
    dims: [u32; 3],
    runs: &[(u64, u32, u32)],
    order: &[u32],
    labels: &[u8],
) -> NarrowBand {
    let voxels_out: Vec<BandVoxel> = runs
        .par_iter()
        .zip(labels)
        .map(|(&(k, start, count), &label)| {
            let members = &order[start as usize..(start + count) as usize];
            let sum: Vec3 = members.iter().map(|&i| positions[i as usize]).sum();
            BandVoxel {
                coord: coord(k),
                count,
                centroid: sum / count as f32,
                label,
            }
        })
        .collect();
    let mut particle_labels = vec![0u8; positions.len()];
    let mut particle_voxels = vec![0u32; positions.len()];
    for (v, (&(_, start, count), &label)) in runs.iter().zip(labels).enumerate() {
        for &i in &order[start as usize..(start + count) as usize] {
            particle_labels[i as usize] = label;
            particle_voxels[i as usize] = v as u32;
        }
    }
    NarrowBand {
        origin: lo,
        edge,
        dims,
        voxels: voxels_out,
        labels: particle_labels,
        voxel_of: particle_voxels,
    }
}

/// How the full voxels are found: a dense array over the domain, or sorted sparse keys. Both
/// give the same band, bit for bit (the same voxels in the same order, each centroid summed over
/// its particles in index order).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Layout {
    /// Dense when the domain holds at most [`DENSE_PER_PARTICLE`] voxels a particle (and at most
    /// [`MAX_DENSE`]), sparse otherwise: a compact body is counted in place, a far-flung splash
    /// costs only its voxels.
    #[default]
    Auto,
    Dense,
    Sparse,
}

/// The most voxels a particle the automatic layout allows for the dense array.
pub const DENSE_PER_PARTICLE: u64 = 4;
/// The most voxels of a dense array (64 MiB of counts).
pub const MAX_DENSE: u64 = 1 << 24;

/// The layout [`Layout::Auto`] takes for a domain of `voxels` voxels and `particles` particles.
#[must_use]
pub fn auto_layout(voxels: u64, particles: usize) -> Layout {
    if voxels <= MAX_DENSE && voxels <= DENSE_PER_PARTICLE * (particles as u64).max(1024) {
        Layout::Dense
    } else {
        Layout::Sparse
    }
}

/// [`narrow_band`] with the voxels found the `layout` way (a dense array asked for a domain of
/// more than [`MAX_DENSE`] voxels is sparse).
pub fn narrow_band_in(
    positions: &[Vec3],
    support_radius: f32,
    params: &LnmParams,
    layout: Layout,
) -> Result<NarrowBand, LnmError> {
    let (lo, edge, dims) = domain(positions, support_radius, params)?;
    let total = dims.iter().map(|&d| u64::from(d)).product::<u64>();
    let dense = match layout {
        Layout::Dense => total <= MAX_DENSE,
        Layout::Sparse => false,
        Layout::Auto => auto_layout(total, positions.len()) == Layout::Dense,
    };
    if dense {
        Ok(dense_band(positions, lo, edge, dims, params))
    } else {
        Ok(sparse_band(positions, lo, edge, dims, params))
    }
}

/// The band over a dense array of the domain's voxels: counts by a counting sort (sequential,
/// so each voxel's particles stay in index order), labels in parallel over the full voxels.
fn dense_band(
    positions: &[Vec3],
    lo: Vec3,
    edge: f32,
    dims: [u32; 3],
    params: &LnmParams,
) -> NarrowBand {
    let inv = 1.0 / edge;
    let (nx, ny, nz) = (dims[0] as usize, dims[1] as usize, dims[2] as usize);
    let total = nx * ny * nz;
    let dense_of: Vec<u32> = positions
        .par_iter()
        .map(|&p| dense_index(voxel_at(p, lo, inv, dims), dims) as u32)
        .collect();
    let mut counts = vec![0u32; total];
    for &v in &dense_of {
        counts[v as usize] += 1;
    }
    // the full voxels in dense order (the sparse keys' order) and each one's start
    let mut compact = vec![u32::MAX; total];
    let mut runs: Vec<(u32, u32, u32)> = Vec::new(); // (dense index, start, count)
    let mut start = 0u32;
    for (v, &c) in counts.iter().enumerate() {
        if c > 0 {
            compact[v] = runs.len() as u32;
            runs.push((v as u32, start, c));
            start += c;
        }
    }
    let mut fill: Vec<u32> = runs.iter().map(|r| r.1).collect();
    let mut order = vec![0u32; positions.len()];
    for (i, &v) in dense_of.iter().enumerate() {
        let k = compact[v as usize] as usize;
        order[fill[k] as usize] = i as u32;
        fill[k] += 1;
    }
    let coord_of = |v: u32| {
        let v = v as usize;
        [
            (v % nx) as u32,
            ((v / nx) % ny) as u32,
            (v / (nx * ny)) as u32,
        ]
    };
    let neighbour = |c: [u32; 3], d: [i64; 3]| -> Option<Option<u32>> {
        let n: [i64; 3] = std::array::from_fn(|a| i64::from(c[a]) + d[a]);
        if (0..3).any(|a| n[a] < 0 || n[a] >= i64::from(dims[a])) {
            return None;
        }
        let k = compact[n[0] as usize + nx * (n[1] as usize + ny * n[2] as usize)];
        Some((k != u32::MAX).then_some(k))
    };
    let runs: Vec<(u64, u32, u32)> = runs
        .into_iter()
        .map(|(v, s, c)| (key(coord_of(v)), s, c))
        .collect();
    let labels = layers(&runs, dims, params.n_min, neighbour);
    finish(positions, lo, edge, dims, &runs, &order, &labels)
}
