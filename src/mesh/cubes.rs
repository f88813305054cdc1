//! Marching cubes that never leaves a hole.
//!
//! **The cases.** The classic table of Lorensen and Cline (1987) leaves holes where two cubes
//! sharing an ambiguous face (two diagonal corners inside) triangulate it differently. Here the
//! 256 cases are built at first use from one rule on faces alone: walking a face's corners
//! counter-clockwise seen from outside the cube, each run of consecutive inside corners gives
//! one segment, from the crossing on the edge entering the run to the crossing on the edge
//! leaving it; an ambiguous face therefore always separates its two inside corners. Both cubes
//! sharing a face see the same corners, so they cut it the same way (traversed in opposite
//! directions), and every crossing of a cube starts a segment on one of its two faces and ends
//! one on the other: the segments close into loops, each triangulated as a fan. The mesh is then
//! closed and manifold wherever the grid's boundary holds no inside point (the density grid is
//! padded by a kernel radius, so it never does).
//!
//! **Vertices** lie on the grid's edges where the values cross the iso-value (linear
//! interpolation; inside at or above it), one per edge whatever the number of cubes around it
//! (keyed by the edge), so the mesh is indexed with no duplicates, and in the order of the
//! edges (plane, row, point, then x, y and z edge): the order in which
//! [`crate::surfels::SurfelExtractor`] finds the same crossings, so vertex `n` is surfel `n`'s
//! crossing and `Frame::mesh` puts the vertices where the surfels are, on the exact
//! iso-surface with the kernel's gradient as normal. **Winding**: counter-clockwise seen from outside (the
//! side of lower density), so the triangles' normals point out of the fluid; vertex normals are
//! the area-weighted normals of the triangles around them.

use std::borrow::Cow;
use std::sync::OnceLock;

use glam::Vec3;
use rayon::prelude::*;

use super::{Mesh, vertex_normals};
use crate::density::GridSpec;
use crate::density::bits::{Bits, below, next_point, points_of};

/// Corner `c` of a cube: its offset along x, y and z (bits 0, 1 and 2 of `c`).
fn corner(c: usize) -> [u32; 3] {
    [(c & 1) as u32, ((c >> 1) & 1) as u32, ((c >> 2) & 1) as u32]
}

/// The twelve edges of a cube as pairs of corners (the lower corner first).
const EDGES: [(usize, usize); 12] = [
    (0, 1),
    (2, 3),
    (4, 5),
    (6, 7),
    (0, 2),
    (1, 3),
    (4, 6),
    (5, 7),
    (0, 4),
    (1, 5),
    (2, 6),
    (3, 7),
];

fn edge_of(a: usize, b: usize) -> usize {
    let key = (a.min(b), a.max(b));
    EDGES
        .iter()
        .position(|&e| e == key)
        .expect("two corners of one edge")
}

/// The six faces of a cube, each as its four corners in order counter-clockwise seen from
/// outside the cube.
fn faces() -> [[usize; 4]; 6] {
    let mut out = [[0; 4]; 6];
    for (f, face) in out.iter_mut().enumerate() {
        let (axis, side) = (f / 2, f % 2);
        // the four corners with bit `axis` = side, in a cycle
        let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
        let at = |a: usize, b: usize| (side << axis) | (a << u) | (b << v);
        let mut cycle = [at(0, 0), at(1, 0), at(1, 1), at(0, 1)];
        // counter-clockwise from outside: (c1 - c0) x (c2 - c0) points outward
        let p = |c: usize| Vec3::from(corner(c).map(|x| x as f32));
        let n = (p(cycle[1]) - p(cycle[0])).cross(p(cycle[2]) - p(cycle[0]));
        let outward = if side == 1 { 1.0 } else { -1.0 };
        if n[axis] * outward < 0.0 {
            cycle.reverse();
        }
        *face = cycle;
    }
    out
}

/// The loops of each of the 256 cases (bit `c` set: corner `c` inside), as edge indices in
/// order, counter-clockwise seen from outside. See the module documentation.
fn cases() -> &'static [Vec<Vec<u8>>] {
    static CASES: OnceLock<Vec<Vec<Vec<u8>>>> = OnceLock::new();
    CASES.get_or_init(|| (0..256).map(case_loops).collect())
}

/// The triangles of a case: each loop as a fan from its first edge.
#[cfg(test)]
fn case(inside: usize) -> Vec<[u8; 3]> {
    case_loops(inside)
        .iter()
        .flat_map(|lp| (1..lp.len() - 1).map(move |i| [lp[0], lp[i], lp[i + 1]]))
        .collect()
}

fn case_loops(inside: usize) -> Vec<Vec<u8>> {
    let is_in = |c: usize| inside >> c & 1 == 1;
    // each crossing edge's segment successor: the segment from `from` to `next[from]`
    let mut next = [usize::MAX; 12];
    for face in faces() {
        for k in 0..4 {
            let (prev, here) = (face[(k + 3) % 4], face[k]);
            // a run of inside corners starts at `here`
            if is_in(here) && !is_in(prev) {
                let mut end = k;
                while is_in(face[(end + 1) % 4]) {
                    end = (end + 1) % 4;
                }
                let from = edge_of(prev, here);
                let to = edge_of(face[end], face[(end + 1) % 4]);
                next[from] = to;
            }
        }
    }
    let mut loops = Vec::new();
    let mut used = [false; 12];
    for start in 0..12 {
        if next[start] == usize::MAX || used[start] {
            continue;
        }
        let mut lp = vec![start];
        used[start] = true;
        let mut e = next[start];
        while e != start {
            used[e] = true;
            lp.push(e);
            e = next[e];
        }
        // the faces' runs are walked counter-clockwise seen from outside the cube, so the loop
        // turns counter-clockwise seen from the fluid's outside (the side of the outside
        // corners): its fans face out (tested on a sphere)
        loops.push(lp.into_iter().map(|e| e as u8).collect());
    }
    loops
}

/// The faces (bits 0-5) each of the twelve edges lies on.
fn edge_faces() -> &'static [u8; 12] {
    static FACES: OnceLock<[u8; 12]> = OnceLock::new();
    FACES.get_or_init(|| {
        let mut out = [0u8; 12];
        for (f, face) in faces().iter().enumerate() {
            for k in 0..4 {
                out[edge_of(face[k], face[(k + 1) % 4])] |= 1 << f;
            }
        }
        out
    })
}

/// The fan of a loop (its edges `lp`, their vertices' positions `p`, counter-clockwise from
/// outside) that folds least: from the vertex whose triangles' smallest agreement with the
/// loop's normal (Newell's) is the largest, among the fans none of whose diagonals lies on a
/// face of the cube (the cube across that face could draw the same diagonal: an edge of four
/// triangles). A fixed fan folds on loops that are far from flat (found on the real files: 93
/// of the double dam break's 244,444 triangles faced inwards).
fn best_fan(lp: &[u8], p: &[Vec3]) -> usize {
    let n = p.len();
    if n <= 3 {
        return 0;
    }
    let on_face = edge_faces();
    let admissible = |r: usize| {
        (2..n - 1).all(|i| on_face[lp[r] as usize] & on_face[lp[(r + i) % n] as usize] == 0)
    };
    let normal: Vec3 = (0..n).map(|i| p[i].cross(p[(i + 1) % n])).sum();
    // the fan whose worst agreement is the largest, the last of equals; a fan's triangles are
    // no longer looked at once one agrees less than the best so far (it cannot win): the same
    // choice as scoring every fan whole; on the 150k block's grid marching cubes went from
    // 8.4 to 5.4 ms with it (the scoring was about half of them, by `perf`)
    let mut best: Option<(usize, f32)> = None;
    'fans: for r in (0..n).filter(|&r| admissible(r)) {
        let mut worst = f32::INFINITY;
        for i in 1..n - 1 {
            let (a, b, c) = (p[r], p[(r + i) % n], p[(r + i + 1) % n]);
            worst = worst.min((b - a).cross(c - a).normalize_or_zero().dot(normal));
            if best.is_some_and(|(_, w)| worst.total_cmp(&w).is_lt()) {
                continue 'fans;
            }
        }
        best = Some((r, worst));
    }
    best.map_or(0, |(r, _)| r)
}

/// Keeps crossings off the corners, so that no triangle collapses onto a grid point.
const T_MARGIN: f32 = 1e-3;

/// The mesh of the iso-surface `value = iso` of a grid (`value(i, j, k)` at grid point
/// `(i, j, k)` of `spec`; inside where the value is not below `iso`). See the module
/// documentation. The layers of cubes between consecutive z planes are meshed in parallel (each
/// plane read twice), their vertices numbered in the order of the edges.
#[must_use]
pub fn marching_cubes(
    spec: &GridSpec,
    value: impl Fn(u32, u32, u32) -> f32 + Sync,
    iso: f32,
) -> Mesh {
    let [nx, ny, _] = spec.dims;
    mesh_planes(spec, iso, |k| {
        Cow::Owned(
            (0..ny)
                .flat_map(|j| (0..nx).map(move |i| (i, j)))
                .map(|(i, j)| value(i, j, k))
                .collect(),
        )
    })
}

/// [`marching_cubes`] of a grid's values held plane after plane (x fastest, then y, then z: a
/// [`crate::density::DensityGrid`]'s), read in place.
///
/// # Panics
/// If `values` does not hold one value per grid point of `spec`.
#[must_use]
pub fn marching_cubes_of_values(spec: &GridSpec, values: &[f32], iso: f32) -> Mesh {
    let plane = spec.dims[0] as usize * spec.dims[1] as usize;
    assert_eq!(
        values.len(),
        plane * spec.dims[2] as usize,
        "one value per grid point"
    );
    mesh_planes(spec, iso, |k| {
        Cow::Borrowed(&values[k as usize * plane..(k as usize + 1) * plane])
    })
}

/// The crossings of one kind of edge of one plane, in the order of the edges (row, point,
/// then x and y edge), each with its edge's code in the plane (x and y edges:
/// `2 * point + axis`; z edges: the point).
#[derive(Default)]
struct Crossings {
    codes: Vec<u32>,
    positions: Vec<Vec3>,
}

/// Where the iso-value crosses the edge from grid point `at` along `axis` (values `va` at
/// its lower end, `vb` at its upper end), kept off the corners.
fn crossing(spec: &GridSpec, at: [u32; 3], axis: usize, va: f32, vb: f32, iso: f32) -> Vec3 {
    let t = ((iso - va) / (vb - va)).clamp(T_MARGIN, 1.0 - T_MARGIN);
    let mut p = Vec3::from(at.map(|c| c as f32));
    p[axis] += t;
    spec.origin + p * spec.spacing
}

/// [`marching_cubes`] of a sparse grid, its planes read block row by block row
/// ([`crate::density::SparseGrid::plane_into`]): the mesh of its dense twin.
#[must_use]
pub fn marching_cubes_of_sparse(grid: &crate::density::SparseGrid, iso: f32) -> Mesh {
    let [nx, ny, _] = grid.spec.dims;
    mesh_planes(&grid.spec, iso, |k| {
        let mut plane = vec![0.0; nx as usize * ny as usize];
        grid.plane_into(k, &mut plane);
        Cow::Owned(plane)
    })
}

/// The crossings on the x and y edges of plane `k` (values `plane`, inside bits `bits`), their
/// places in the list written into `index` (by code).
fn plane_edges(
    spec: &GridSpec,
    iso: f32,
    k: u32,
    plane: &[f32],
    bits: &Bits,
    index: &mut [u32],
) -> Crossings {
    let [nx, ny, _] = spec.dims;
    let mut out = Crossings::default();
    for j in 0..ny {
        let row = bits.row(j);
        let up = (j + 1 < ny).then(|| bits.row(j + 1));
        for w in 0..bits.words {
            let x = (row[w] ^ next_point(row, w)) & below(w, nx - 1);
            let y = up.map_or(0, |u| row[w] ^ u[w]);
            for i in points_of(x | y, w) {
                let n = (i + nx * j) as usize;
                let v = plane[n];
                let bit = 1u64 << (i % 64);
                for (axis, step, crossed) in [(0usize, 1u32, x & bit), (1, nx, y & bit)] {
                    if crossed != 0 {
                        let code = 2 * n as u32 + axis as u32;
                        index[code as usize] = out.codes.len() as u32;
                        out.codes.push(code);
                        let w_ = plane[n + step as usize];
                        out.positions
                            .push(crossing(spec, [i, j, k], axis, v, w_, iso));
                    }
                }
            }
        }
    }
    out
}

/// The crossings on the z edges from plane `k` (values `below_`, bits `bits_below`) to plane
/// `k + 1` (`above`, `bits_above`), their places written into `index` (by code).
fn z_edges(
    spec: &GridSpec,
    iso: f32,
    k: u32,
    [below_, above]: [&[f32]; 2],
    [bits_below, bits_above]: [&Bits; 2],
    index: &mut [u32],
) -> Crossings {
    let [nx, ny, _] = spec.dims;
    let mut out = Crossings::default();
    for j in 0..ny {
        let (a, b) = (bits_below.row(j), bits_above.row(j));
        for w in 0..bits_below.words {
            for i in points_of(a[w] ^ b[w], w) {
                let n = (i + nx * j) as usize;
                index[n] = out.codes.len() as u32;
                out.codes.push(n as u32);
                out.positions
                    .push(crossing(spec, [i, j, k], 2, below_[n], above[n], iso));
            }
        }
    }
    out
}

/// The cubes of row `j` of the layer between the planes of `bits` that hold a crossing (their
/// eight corners not all on one side), with each one's case (bit `c` set: corner `c` inside),
/// in increasing order.
fn row_cubes(bits: [&Bits; 2], j: u32, nx: u32) -> impl Iterator<Item = (u32, usize)> + '_ {
    // the four rows of corners, corner c's row being c >> 1 (bit 1: y, bit 2: z)
    let rows = [
        bits[0].row(j),
        bits[0].row(j + 1),
        bits[1].row(j),
        bits[1].row(j + 1),
    ];
    (0..bits[0].words).flat_map(move |w| {
        let (mut all, mut any) = (below(w, nx - 1), 0u64);
        for row in rows {
            let (here, next) = (row[w], next_point(row, w));
            all &= here & next;
            any |= here | next;
        }
        let mixed = any & !all & below(w, nx - 1);
        points_of(mixed, w).map(move |i| {
            let (b, shift) = (i as usize / 64, i % 64);
            let at = |row: &[u64], dx: u32| {
                let p = shift + dx;
                (row[b + (p / 64) as usize] >> (p % 64)) & 1
            };
            let mut inside = 0usize;
            for c in 0..8 {
                if at(rows[c >> 1], (c & 1) as u32) != 0 {
                    inside |= 1 << c;
                }
            }
            (i, inside)
        })
    })
}

/// A triangle corner's vertex before the vertices are numbered: its list (bits 30-31: the
/// lower plane's x and y edges, the upper plane's, the z edges between them) and its place in
/// it.
const LOWER: u32 = 0;
const UPPER: u32 = 1 << 30;
const BETWEEN: u32 = 2 << 30;
const PLACE: u32 = (1 << 30) - 1;

/// Each of the twelve edges of a cube: its axis and its lower corner's offsets.
fn edge_geometry() -> [(usize, [u32; 3]); 12] {
    EDGES.map(|(a, b)| {
        let axis = (0..3)
            .find(|&d| corner(b)[d] != corner(a)[d])
            .expect("an edge along one axis");
        (axis, corner(a))
    })
}

/// One layer of cubes, between planes `k` and `k + 1`: the crossings it owns (the x and y
/// edges of plane `k + 1`, and of plane 0 for the first layer; the z edges between the two
/// planes) and its triangles, their corners in [`LOWER`] / [`UPPER`] / [`BETWEEN`] form.
struct Layer {
    first: Option<Crossings>,
    upper: Crossings,
    between: Crossings,
    triangles: Vec<[u32; 3]>,
}

/// The index maps a thread reuses from layer to layer: by code, a crossing's place in the
/// lower plane's, the upper plane's and the z edges' lists (only the crossings' entries are
/// written, and only those are read).
struct Maps {
    lower: Vec<u32>,
    upper: Vec<u32>,
    between: Vec<u32>,
}

/// Layer `k` of cubes, between the planes `lower` and `upper`: its crossings and triangles.
fn mesh_layer(
    spec: &GridSpec,
    iso: f32,
    k: u32,
    [lower, upper]: [&[f32]; 2],
    maps: &mut Maps,
) -> Layer {
    let [nx, ny, _] = spec.dims;
    let geometry = edge_geometry();
    let cases = cases();
    let bits = [Bits::of(lower, nx, iso), Bits::of(upper, nx, iso)];
    let lower_edges = plane_edges(spec, iso, k, lower, &bits[0], &mut maps.lower);
    let upper_edges = plane_edges(spec, iso, k + 1, upper, &bits[1], &mut maps.upper);
    let between = z_edges(
        spec,
        iso,
        k,
        [lower, upper],
        [&bits[0], &bits[1]],
        &mut maps.between,
    );
    let mut triangles = Vec::new();
    for j in 0..ny - 1 {
        for (i, inside) in row_cubes([&bits[0], &bits[1]], j, nx) {
            for lp in &cases[inside] {
                let mut refs = [0u32; 12];
                let mut at = [Vec3::ZERO; 12];
                for (slot, &e) in lp.iter().enumerate() {
                    let (axis, [ax, ay, az]) = geometry[e as usize];
                    let n = (i + ax + nx * (j + ay)) as usize;
                    let (tag, list, place) = if axis == 2 {
                        (BETWEEN, &between, maps.between[n])
                    } else if az == 0 {
                        (LOWER, &lower_edges, maps.lower[2 * n + axis])
                    } else {
                        (UPPER, &upper_edges, maps.upper[2 * n + axis])
                    };
                    refs[slot] = tag | place;
                    at[slot] = list.positions[place as usize];
                }
                let n = lp.len();
                let r = best_fan(lp, &at[..n]);
                for i in 1..n - 1 {
                    triangles.push([refs[r], refs[(r + i) % n], refs[(r + i + 1) % n]]);
                }
            }
        }
    }
    Layer {
        first: (k == 0).then_some(lower_edges),
        upper: upper_edges,
        between,
        triangles,
    }
}

/// The mesh of the planes `plane(k)` (`nx * ny` values each, x fastest). Each layer of cubes
/// finds its crossings and triangles in parallel, the triangles naming their vertices by their
/// place in the layer's lists; the vertices are then numbered in the order of the edges'
/// keys (plane, row, point, then x, y and z edge), the order in which
/// `surfels::SurfelExtractor` finds the same crossings, by merging each plane's x and y edges
/// with the z edges below it. No hash set, sort or search: the first version (a set of the
/// edges seen per layer, a sort of every vertex by key and a binary search per triangle
/// corner; eight corners read a cube) took 13.2-13.7 ms on the 150k block's 85^3 grid
/// (`examples/peer_splashsurf`'s, 75,008 triangles) against this one's 4.9 ms, timed side by
/// side in one test binary (release, 2 cores, 30 runs each, twice).
fn mesh_planes<'a>(
    spec: &GridSpec,
    iso: f32,
    plane: impl Fn(u32) -> Cow<'a, [f32]> + Sync,
) -> Mesh {
    let [nx, ny, nz] = spec.dims;
    if nx < 2 || ny < 2 || nz < 2 {
        return Mesh::default();
    }
    let points = nx as usize * ny as usize;
    let layers: Vec<Layer> = (0..nz - 1)
        .into_par_iter()
        .map_init(
            || Maps {
                lower: vec![0; 2 * points],
                upper: vec![0; 2 * points],
                between: vec![0; points],
            },
            |maps, k| mesh_layer(spec, iso, k, [&plane(k), &plane(k + 1)], maps),
        )
        .collect();
    // plane p's vertices: its x and y edges merged with the z edges below it by point (an
    // x or y edge before the z edge of the same point); where each list's entries land
    let planes: Vec<(&Crossings, Option<&Crossings>)> = std::iter::once((
        layers[0]
            .first
            .as_ref()
            .expect("the first layer's lower plane"),
        None,
    ))
    .chain(layers.iter().map(|l| (&l.upper, Some(&l.between))))
    .collect();
    let merged: Vec<(Vec<Vec3>, Vec<u32>, Vec<u32>)> = planes
        .par_iter()
        .map(|&(xy, z)| merge_plane(xy, z))
        .collect();
    let mut offsets = Vec::with_capacity(merged.len() + 1);
    offsets.push(0u32);
    for m in &merged {
        offsets.push(offsets.last().copied().unwrap_or(0) + m.0.len() as u32);
    }
    let triangles: Vec<[u32; 3]> = layers
        .par_iter()
        .enumerate()
        .flat_map_iter(|(k, l)| {
            let (merged, offsets) = (&merged, &offsets);
            l.triangles.iter().map(move |t| {
                t.map(|r| {
                    let place = (r & PLACE) as usize;
                    match r & !PLACE {
                        LOWER => offsets[k] + merged[k].1[place],
                        UPPER => offsets[k + 1] + merged[k + 1].1[place],
                        _ => offsets[k + 1] + merged[k + 1].2[place],
                    }
                })
            })
        })
        .collect();
    let positions: Vec<Vec3> = merged.into_iter().flat_map(|m| m.0).collect();
    Mesh {
        normals: vertex_normals(&positions, &triangles),
        positions,
        triangles,
        velocities: None,
    }
}

/// A plane's vertices in the order of their edges: its x and y edges `xy` merged with the z
/// edges `z` below it (a point's x and y edges before its z edge), with where each of `xy`'s
/// and `z`'s entries lands.
fn merge_plane(xy: &Crossings, z: Option<&Crossings>) -> (Vec<Vec3>, Vec<u32>, Vec<u32>) {
    let empty = Crossings::default();
    let z = z.unwrap_or(&empty);
    let mut positions = Vec::with_capacity(xy.codes.len() + z.codes.len());
    let (mut to_xy, mut to_z) = (Vec::with_capacity(xy.codes.len()), Vec::new());
    to_z.reserve(z.codes.len());
    let (mut a, mut b) = (0, 0);
    while a < xy.codes.len() || b < z.codes.len() {
        // x and y edges of point n have codes 2n and 2n + 1; its z edge comes after them
        let take_xy = b == z.codes.len() || (a < xy.codes.len() && xy.codes[a] / 2 <= z.codes[b]);
        if take_xy {
            to_xy.push(positions.len() as u32);
            positions.push(xy.positions[a]);
            a += 1;
        } else {
            to_z.push(positions.len() as u32);
            positions.push(z.positions[b]);
            b += 1;
        }
    }
    (positions, to_xy, to_z)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::Topology;
    use std::collections::HashSet;

    /// The first version of [`marching_cubes`], kept as its oracle: a set of the edges seen per
    /// layer, a sort of every vertex by key, a binary search per triangle corner. The mesh of the iso-surface `value = iso` of a grid (`value(i, j, k)` at grid point
    /// `(i, j, k)` of `spec`; inside where the value is not below `iso`). See the module
    /// documentation. The layers of cubes between consecutive z planes are meshed in parallel (each
    /// plane read twice), their vertices merged by edge.
    fn reference(spec: &GridSpec, value: impl Fn(u32, u32, u32) -> f32 + Sync, iso: f32) -> Mesh {
        let [nx, ny, nz] = spec.dims;
        if nx < 2 || ny < 2 || nz < 2 {
            return Mesh::default();
        }
        let plane = |k: u32| -> Vec<f32> {
            (0..ny)
                .flat_map(|j| (0..nx).map(move |i| (i, j)))
                .map(|(i, j)| value(i, j, k))
                .collect()
        };
        let layers: Vec<RefLayer> = (0..nz - 1)
            .into_par_iter()
            .map(|k| mesh_layer(spec, iso, k, [&plane(k), &plane(k + 1)]))
            .collect();
        // one vertex per edge, in the order of the edges' keys: (plane, row, point, then x, y and z
        // edge), the order `surfels::SurfelExtractor` finds the same crossings in
        let mut vertices: Vec<(u64, Vec3)> = layers
            .iter()
            .flat_map(|l| l.vertices.iter().copied())
            .collect();
        vertices.par_sort_unstable_by_key(|v| v.0);
        vertices.dedup_by_key(|v| v.0);
        let index = |key: u64| {
            vertices
                .binary_search_by_key(&key, |v| v.0)
                .expect("every corner's vertex") as u32
        };
        let triangles: Vec<[u32; 3]> = layers
            .par_iter()
            .flat_map_iter(|l| l.triangles.iter().map(|t| t.map(index)))
            .collect();
        let positions: Vec<Vec3> = vertices.iter().map(|v| v.1).collect();
        Mesh {
            normals: vertex_normals(&positions, &triangles),
            positions,
            triangles,
            velocities: None,
        }
    }

    /// The vertices (keyed by edge, each once) and triangles (as keys) of one layer of cubes.
    struct RefLayer {
        vertices: Vec<(u64, Vec3)>,
        triangles: Vec<[u64; 3]>,
    }

    /// The cubes between planes `k` and `k + 1` (`planes`: their values, x fastest).
    fn mesh_layer(spec: &GridSpec, iso: f32, k: u32, planes: [&[f32]; 2]) -> RefLayer {
        let [nx, ny, _] = spec.dims;
        let cases = cases();
        let point = |i: u32, j: u32, k: u32| {
            u64::from(i) + u64::from(nx) * (u64::from(j) + u64::from(ny) * u64::from(k))
        };
        let mut layer = RefLayer {
            vertices: Vec::new(),
            triangles: Vec::new(),
        };
        let mut seen: HashSet<u64> = HashSet::new();
        let mut values = [0.0f32; 8];
        // which sides of the iso-value each row of the two planes holds (bit 0: a value below,
        // bit 1: one not below); a row of cubes whose four rows of corners lie all on one side
        // holds no crossing and is skipped: one read a point instead of eight a cube, where most
        // of a grid is far from the surface (the dam break's mesh took 12 ms of marching cubes
        // for 44,276 triangles before)
        let sides = planes.map(|plane| {
            plane
                .chunks_exact(nx as usize)
                .map(|row| {
                    row.iter()
                        .fold(0u8, |s, &v| s | if v < iso { 1 } else { 2 })
                })
                .collect::<Vec<u8>>()
        });
        for j in 0..ny - 1 {
            let j_ = j as usize;
            if sides[0][j_] | sides[0][j_ + 1] | sides[1][j_] | sides[1][j_ + 1] != 3 {
                continue;
            }
            for i in 0..nx - 1 {
                let mut inside = 0usize;
                for (c, v) in values.iter_mut().enumerate() {
                    let [dx, dy, dz] = corner(c);
                    *v = planes[dz as usize][(i + dx + nx * (j + dy)) as usize];
                    // inside unless below the iso-value, as the surfels' crossings count it
                    // (`(a < iso) != (b < iso)`)
                    let below = *v < iso;
                    if !below {
                        inside |= 1 << c;
                    }
                }
                if inside == 0 || inside == 255 {
                    continue;
                }
                for lp in &cases[inside] {
                    let mut keys = [0u64; 12];
                    let mut at = [Vec3::ZERO; 12];
                    for (slot, &e) in lp.iter().enumerate() {
                        let (a, b) = EDGES[e as usize];
                        let [ax, ay, az] = corner(a);
                        let axis = [0, 1, 2]
                            .into_iter()
                            .find(|&d| corner(b)[d] != corner(a)[d])
                            .expect("an edge along one axis");
                        // the surfels' order: a z edge belongs to its upper plane
                        let key =
                            point(i + ax, j + ay, k + az + u32::from(axis == 2)) * 3 + axis as u64;
                        let t = ((iso - values[a]) / (values[b] - values[a]))
                            .clamp(T_MARGIN, 1.0 - T_MARGIN);
                        let mut p = Vec3::new((i + ax) as f32, (j + ay) as f32, (k + az) as f32);
                        p[axis] += t;
                        let p = spec.origin + p * spec.spacing;
                        if seen.insert(key) {
                            layer.vertices.push((key, p));
                        }
                        keys[slot] = key;
                        at[slot] = p;
                    }
                    let n = lp.len();
                    let r = best_fan(lp, &at[..n]);
                    for i in 1..n - 1 {
                        layer
                            .triangles
                            .push([keys[r], keys[(r + i) % n], keys[(r + i + 1) % n]]);
                    }
                }
            }
        }
        layer
    }

    /// A grid of `n` points a side over [-2, 2]^3 sampling `f`.
    fn mesh_of(n: u32, f: impl Fn(Vec3) -> f32 + Sync) -> (Mesh, GridSpec) {
        let spec = GridSpec {
            origin: Vec3::splat(-2.0),
            spacing: 4.0 / (n - 1) as f32,
            dims: [n; 3],
        };
        let at = |i: u32, j: u32, k: u32| {
            f(spec.origin + Vec3::new(i as f32, j as f32, k as f32) * spec.spacing)
        };
        (marching_cubes(&spec, at, 0.0), spec)
    }

    fn check(mesh: &Mesh, euler: i64, what: &str) {
        assert!(!mesh.triangles.is_empty(), "{what}: no triangle");
        assert!(
            mesh.is_closed(),
            "{what}: not closed and consistently wound"
        );
        assert_eq!(mesh.euler_characteristic(), euler, "{what}");
        for t in &mesh.triangles {
            let [a, b, c] = t.map(|v| mesh.positions[v as usize]);
            assert!(
                (b - a).cross(c - a).length() > 1e-9,
                "{what}: a degenerate triangle"
            );
        }
        // no duplicate vertices
        let mut seen = std::collections::HashSet::new();
        for p in &mesh.positions {
            assert!(
                seen.insert(p.to_array().map(f32::to_bits)),
                "{what}: a duplicate vertex"
            );
        }
    }

    /// The 256 cases close: in every cube configuration each crossing edge starts one segment
    /// and ends one (so the loops exist), and every case's triangles use each of its crossing
    /// edges.
    #[test]
    fn every_case_is_made_of_closed_loops() {
        for inside in 0..256usize {
            let crossing: Vec<usize> = (0..12)
                .filter(|&e| {
                    let (a, b) = EDGES[e];
                    (inside >> a & 1) != (inside >> b & 1)
                })
                .collect();
            let used: std::collections::HashSet<usize> =
                case(inside).iter().flatten().map(|&e| e as usize).collect();
            assert_eq!(used.len(), crossing.len(), "case {inside:08b}");
        }
    }

    /// Analytic shapes: a sphere (chi 2), a torus (0), two drops apart (4), a slab (2); closed,
    /// consistently wound, outward, no degenerate triangle, no duplicate vertex; every vertex
    /// on the field's zero crossing along its edge (linear fields are exact).
    #[test]
    fn analytic_shapes_give_closed_manifold_meshes() {
        let sphere = |p: Vec3| 1.2 - p.length();
        let torus = |p: Vec3| {
            let q = glam::Vec2::new(glam::Vec2::new(p.x, p.z).length() - 1.0, p.y);
            0.45 - q.length()
        };
        let drops = |p: Vec3| {
            (0.6 - (p - Vec3::new(-0.9, 0.0, 0.0)).length())
                .max(0.6 - (p - Vec3::new(0.9, 0.1, 0.0)).length())
        };
        let slab = |p: Vec3| (0.3 - p.y.abs()).min(1.5 - p.x.abs()).min(1.5 - p.z.abs());
        for n in [12u32, 25, 41] {
            let (m, _) = mesh_of(n, sphere);
            check(&m, 2, &format!("sphere {n}"));
            // outward: the normals point away from the centre
            for (p, nrm) in m.positions.iter().zip(&m.normals) {
                assert!(p.dot(*nrm) > 0.0, "sphere {n}: an inward normal at {p}");
            }
            check(&mesh_of(n, torus).0, 0, &format!("torus {n}"));
            check(&mesh_of(n, drops).0, 4, &format!("two drops {n}"));
            check(&mesh_of(n, slab).0, 2, &format!("slab {n}"));
        }
        // a linear field (a plane, open at the grid's boundary): every vertex on it
        let (m, _) = mesh_of(17, |p: Vec3| 0.3 - (p.x + 0.5 * p.y));
        assert!(!m.triangles.is_empty());
        // open at the grid's boundary: a disc
        assert_eq!(
            m.topology(),
            Topology {
                closed: false,
                euler_characteristic: 1
            }
        );
        for p in &m.positions {
            assert!((0.3 - (p.x + 0.5 * p.y)).abs() < 1e-5, "{p}");
        }
    }

    /// Random fields (the ambiguous faces included): still closed and consistently wound.
    #[test]
    fn random_fields_give_closed_meshes() {
        let mut state = 12345u64;
        let mut rnd = move || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((state >> 33) as f32 / (1u64 << 31) as f32) - 0.5
        };
        let n = 10u32;
        let values: Vec<f32> = (0..n * n * n).map(|_| rnd()).collect();
        let spec = GridSpec {
            origin: Vec3::ZERO,
            spacing: 1.0,
            dims: [n; 3],
        };
        // the boundary points outside, so the surface closes within the grid
        let at = |i: u32, j: u32, k: u32| {
            if [i, j, k].iter().any(|&x| x == 0 || x == n - 1) {
                -1.0
            } else {
                values[(i + n * (j + n * k)) as usize]
            }
        };
        let m = marching_cubes(&spec, at, 0.0);
        assert!(m.triangles.len() > 100);
        assert!(m.is_closed(), "random field: not closed");
    }

    /// The mesh made without hash set, sort or search is the first version's, vertex for
    /// vertex (bit for bit) and triangle for triangle, from both entry points: analytic shapes,
    /// random fields with ambiguous faces, fields touching the grid's boundary, a grid of one
    /// layer.
    #[test]
    fn the_mesh_is_the_reference_ones() {
        let mut state = 987u64;
        let mut rnd = move || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((state >> 33) as f32 / (1u64 << 31) as f32) - 0.5
        };
        let fields: Vec<(String, [u32; 3], Vec<f32>)> = {
            let mut out = Vec::new();
            for dims in [[13u32, 9, 11], [7, 7, 2], [2, 5, 6], [20, 20, 20]] {
                let n = (dims[0] * dims[1] * dims[2]) as usize;
                out.push((
                    format!("random {dims:?}"),
                    dims,
                    (0..n).map(|_| rnd()).collect(),
                ));
                let [nx, ny, _] = dims;
                let sphere = (0..n)
                    .map(|p| {
                        let p = p as u32;
                        let q = Vec3::new(
                            (p % nx) as f32,
                            ((p / nx) % ny) as f32,
                            (p / (nx * ny)) as f32,
                        );
                        0.4 * dims[0] as f32
                            - (q - Vec3::from(dims.map(|d| d as f32)) * 0.45).length()
                    })
                    .collect();
                out.push((format!("sphere {dims:?}"), dims, sphere));
            }
            out
        };
        for (what, dims, values) in &fields {
            let spec = GridSpec {
                origin: Vec3::new(-1.0, 0.5, 2.0),
                spacing: 0.3,
                dims: *dims,
            };
            let at = |i: u32, j: u32, k: u32| values[(i + dims[0] * (j + dims[1] * k)) as usize];
            let want = reference(&spec, at, 0.0);
            for got in [
                marching_cubes(&spec, at, 0.0),
                marching_cubes_of_values(&spec, values, 0.0),
            ] {
                assert!(
                    !want.triangles.is_empty() || what.starts_with("sphere"),
                    "{what}"
                );
                assert_eq!(
                    got.positions.len(),
                    want.positions.len(),
                    "{what}: vertices"
                );
                let first = |a: &[Vec3], b: &[Vec3]| a.iter().zip(b).position(|(x, y)| x != y);
                assert_eq!(
                    first(&got.positions, &want.positions),
                    None,
                    "{what}: a vertex"
                );
                assert_eq!(first(&got.normals, &want.normals), None, "{what}: a normal");
                assert!(
                    got.triangles == want.triangles,
                    "{what}: the triangles differ"
                );
            }
        }
    }

    /// The fan chosen with the scoring cut short is the one chosen scoring every fan whole
    /// (the first version, kept here), on every case's loops at random crossings.
    #[test]
    fn the_best_fan_is_the_whole_scorings() {
        fn whole(lp: &[u8], p: &[Vec3]) -> usize {
            let n = p.len();
            if n <= 3 {
                return 0;
            }
            let on_face = edge_faces();
            let admissible = |r: usize| {
                (2..n - 1).all(|i| on_face[lp[r] as usize] & on_face[lp[(r + i) % n] as usize] == 0)
            };
            let normal: Vec3 = (0..n).map(|i| p[i].cross(p[(i + 1) % n])).sum();
            let worst = |r: usize| {
                (1..n - 1)
                    .map(|i| {
                        let (a, b, c) = (p[r], p[(r + i) % n], p[(r + i + 1) % n]);
                        (b - a).cross(c - a).normalize_or_zero().dot(normal)
                    })
                    .fold(f32::INFINITY, f32::min)
            };
            (0..n)
                .filter(|&r| admissible(r))
                .max_by(|&a, &b| worst(a).total_cmp(&worst(b)))
                .unwrap_or(0)
        }
        let mut state = 4242u64;
        let mut rnd = move || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 40) as f32 / (1u64 << 24) as f32
        };
        let geometry = edge_geometry();
        let mut long = 0;
        for inside in 0..256 {
            for lp in &cases()[inside] {
                for _ in 0..50 {
                    let p: Vec<Vec3> = lp
                        .iter()
                        .map(|&e| {
                            let (axis, c) = geometry[e as usize];
                            let mut q = Vec3::from(c.map(|x| x as f32));
                            q[axis] += rnd();
                            q
                        })
                        .collect();
                    long += usize::from(lp.len() > 4);
                    assert_eq!(best_fan(lp, &p), whole(lp, &p), "case {inside:08b}");
                }
            }
        }
        assert!(long > 1000, "loops of more than four edges tried: {long}");
    }
}
