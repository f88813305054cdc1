//! A triangle mesh of the density grid's iso-surface (issue 40, first part): marching cubes
//! with an indexed, watertight, consistently wound mesh, and writers for binary PLY and OBJ.
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

use std::collections::HashSet;
use std::path::Path;
use std::sync::OnceLock;

use glam::Vec3;
use rayon::prelude::*;

use crate::density::GridSpec;
use crate::io::IoError;

/// An indexed triangle mesh.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Mesh {
    /// Vertex positions.
    pub positions: Vec<Vec3>,
    /// Unit vertex normals, pointing out of the fluid.
    pub normals: Vec<Vec3>,
    /// Triangles: three vertex indices each, counter-clockwise seen from outside.
    pub triangles: Vec<[u32; 3]>,
}

/// What [`Mesh::topology`] finds.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Topology {
    /// Every edge shared by exactly two triangles, once each way.
    pub closed: bool,
    /// `V - E + F` over the vertices the triangles use.
    pub euler_characteristic: i64,
}

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

/// Keeps crossings off the corners, so that no triangle collapses onto a grid point.
const T_MARGIN: f32 = 1e-3;

/// The mesh of the iso-surface `value = iso` of a grid (`value(i, j, k)` at grid point
/// `(i, j, k)` of `spec`; inside where the value is not below `iso`). See the module
/// documentation. The layers of cubes between consecutive z planes are meshed in parallel (each
/// plane read twice), their vertices merged by edge.
#[must_use]
pub fn marching_cubes(
    spec: &GridSpec,
    value: impl Fn(u32, u32, u32) -> f32 + Sync,
    iso: f32,
) -> Mesh {
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
    let layers: Vec<Layer> = (0..nz - 1)
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
    }
}

/// The vertices (keyed by edge, each once) and triangles (as keys) of one layer of cubes.
struct Layer {
    vertices: Vec<(u64, Vec3)>,
    triangles: Vec<[u64; 3]>,
}

/// The cubes between planes `k` and `k + 1` (`planes`: their values, x fastest).
fn mesh_layer(spec: &GridSpec, iso: f32, k: u32, planes: [&[f32]; 2]) -> Layer {
    let [nx, ny, _] = spec.dims;
    let cases = cases();
    let point = |i: u32, j: u32, k: u32| {
        u64::from(i) + u64::from(nx) * (u64::from(j) + u64::from(ny) * u64::from(k))
    };
    let mut layer = Layer {
        vertices: Vec::new(),
        triangles: Vec::new(),
    };
    let mut seen: HashSet<u64> = HashSet::new();
    let mut values = [0.0f32; 8];
    for j in 0..ny - 1 {
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

/// The area-weighted normals of the triangles around each vertex, unit length.
fn vertex_normals(positions: &[Vec3], triangles: &[[u32; 3]]) -> Vec<Vec3> {
    let mut normals = vec![Vec3::ZERO; positions.len()];
    for t in triangles {
        let [a, b, c] = t.map(|v| positions[v as usize]);
        let n = (b - a).cross(c - a);
        for &v in t {
            normals[v as usize] += n;
        }
    }
    normals.iter().map(|n| n.normalize_or_zero()).collect()
}

impl Mesh {
    /// A mesh of given vertices and triangles (indices checked), its normals the area-weighted
    /// normals of the triangles around each vertex.
    pub fn new(positions: Vec<Vec3>, triangles: Vec<[u32; 3]>) -> Result<Self, crate::Error> {
        let n = positions.len();
        if let Some(t) = triangles
            .iter()
            .find(|t| t.iter().any(|&v| v as usize >= n))
        {
            return Err(crate::Error::InvalidArgument {
                argument: "triangles",
                reason: format!("the triangle {t:?} names a vertex past the {n} given"),
            });
        }
        if positions.iter().any(|p| !p.is_finite()) {
            return Err(crate::Error::InvalidArgument {
                argument: "positions",
                reason: "a vertex is not finite".into(),
            });
        }
        Ok(Self {
            normals: vertex_normals(&positions, &triangles),
            positions,
            triangles,
        })
    }

    /// Whether `path` names a mesh format this crate writes: `.ply` (binary, `true`) or `.obj`
    /// (`false`); an error naming both otherwise.
    pub fn is_ply(path: &Path) -> Result<bool, crate::Error> {
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase);
        match ext.as_deref() {
            Some("ply") => Ok(true),
            Some("obj") => Ok(false),
            _ => Err(crate::Error::InvalidArgument {
                argument: "path",
                reason: format!(
                    "{}: a mesh is written as .ply (binary) or .obj",
                    path.display()
                ),
            }),
        }
    }

    /// Writes the mesh in the format of `path`'s extension ([`Mesh::is_ply`]), atomically.
    pub fn write(&self, path: &Path) -> Result<(), crate::Error> {
        if Self::is_ply(path)? {
            Ok(self.write_ply(path)?)
        } else {
            Ok(self.write_obj(path)?)
        }
    }

    /// Moves the vertices to `positions` with `normals` (the surfels projected from the same
    /// crossings onto the exact iso-surface), but keeps on its grid edge every vertex of a
    /// triangle that the move would collapse (no area left), turn over (its normal against the
    /// same triangle's on the edges) or set against its vertices' `normals`, repeated until
    /// none is; returns how many vertices stayed on their edges. Measured (fixed detail,
    /// release, 2 cores): the projection alone turns over 14 of the double dam break's 244,444
    /// triangles and sets 89 against their normals (the dam break: 5 collapsed, 43 turned over,
    /// 197 against their normals of 565,884); with 177 of 122,208 vertices kept on their edges
    /// no triangle stands against the mesh's own normals (the dam break: 368 kept, 4 left where
    /// two sheets nearly touch; 14 on the double dam break when only the collapsed and
    /// turned-over triangles' vertices are kept).
    pub fn move_onto(&mut self, positions: &[Vec3], normals: &[Vec3]) -> usize {
        assert_eq!(
            positions.len(),
            self.positions.len(),
            "one position per vertex"
        );
        let on_edges = std::mem::replace(&mut self.positions, positions.to_vec());
        self.normals = normals.to_vec();
        let normal_of = |p: &[Vec3], t: &[u32; 3]| {
            let [a, b, c] = t.map(|v| p[v as usize]);
            (b - a).cross(c - a)
        };
        let mut kept = vec![false; on_edges.len()];
        for _ in 0..8 {
            let bad: Vec<u32> = self
                .triangles
                .par_iter()
                .filter(|t| {
                    let n = normal_of(&self.positions, t);
                    let given: Vec3 = t.iter().map(|&v| self.normals[v as usize]).sum();
                    self.is_collapsed(t)
                        || n.dot(normal_of(&on_edges, t)) <= 0.0
                        || n.dot(given) <= 0.0
                })
                .flat_map_iter(|t| t.iter().copied())
                .collect();
            if bad.is_empty() {
                break;
            }
            for v in bad {
                self.positions[v as usize] = on_edges[v as usize];
                kept[v as usize] = true;
            }
        }
        kept.iter().filter(|&&k| k).count()
    }

    /// Whether a triangle has no area left (relative to its longest side from its first
    /// vertex).
    #[must_use]
    pub fn is_collapsed(&self, t: &[u32; 3]) -> bool {
        let [a, b, c] = t.map(|v| self.positions[v as usize]);
        let n = (b - a).cross(c - a);
        let scale = (b - a).length_squared().max((c - a).length_squared());
        n.length_squared() <= 1e-12 * scale * scale
    }

    /// Whether the mesh is closed and its Euler characteristic, from one sorted list of its
    /// directed edges: 41 ms on the dam break's 565,884 triangles (release, 2 cores), where
    /// maps of every edge took 270 ms, more than making the mesh (156-199 ms).
    #[must_use]
    pub fn topology(&self) -> Topology {
        let key = |a: u32, b: u32| (u64::from(a) << 32) | u64::from(b);
        let mut directed: Vec<u64> = self
            .triangles
            .par_iter()
            .flat_map_iter(|t| (0..3).map(move |k| key(t[k], t[(k + 1) % 3])))
            .collect();
        directed.par_sort_unstable();
        let unique = directed.windows(2).all(|w| w[0] != w[1]);
        let closed = unique
            && directed
                .par_iter()
                .all(|&e| directed.binary_search(&e.rotate_right(32)).is_ok());
        // undirected edges: each once (a pair used both ways counted at its a < b side)
        let edges = if closed {
            directed.len() / 2
        } else {
            let mut undirected: Vec<u64> = directed
                .iter()
                .map(|&e| {
                    let (a, b) = ((e >> 32) as u32, e as u32);
                    key(a.min(b), a.max(b))
                })
                .collect();
            undirected.par_sort_unstable();
            undirected.dedup();
            undirected.len()
        };
        let mut used = vec![false; self.positions.len()];
        for &v in self.triangles.iter().flatten() {
            used[v as usize] = true;
        }
        let vertices = used.iter().filter(|&&u| u).count();
        Topology {
            closed,
            euler_characteristic: vertices as i64 - edges as i64 + self.triangles.len() as i64,
        }
    }

    /// Whether every edge is shared by exactly two triangles, each way once (closed, manifold
    /// at its edges and consistently wound).
    #[must_use]
    pub fn is_closed(&self) -> bool {
        self.topology().closed
    }

    /// The Euler characteristic `V - E + F` (2 for a sphere, 0 for a torus, 2 per separate
    /// closed body without handles).
    #[must_use]
    pub fn euler_characteristic(&self) -> i64 {
        self.topology().euler_characteristic
    }

    /// Writes the mesh as binary little-endian PLY (`vertex` with `x y z nx ny nz`, `face` with
    /// `vertex_indices`), atomically.
    pub fn write_ply(&self, path: &Path) -> Result<(), IoError> {
        let mut out = format!(
            "ply\nformat binary_little_endian 1.0\ncomment fluid-surfels mesh\nelement vertex {}\n\
             property float x\nproperty float y\nproperty float z\n\
             property float nx\nproperty float ny\nproperty float nz\n\
             element face {}\nproperty list uchar uint vertex_indices\nend_header\n",
            self.positions.len(),
            self.triangles.len()
        )
        .into_bytes();
        for (p, n) in self.positions.iter().zip(&self.normals) {
            for x in p.to_array().into_iter().chain(n.to_array()) {
                out.extend_from_slice(&x.to_le_bytes());
            }
        }
        for t in &self.triangles {
            out.push(3);
            for v in t {
                out.extend_from_slice(&v.to_le_bytes());
            }
        }
        crate::io::write_atomically(path, &out)
    }

    /// Writes the mesh as OBJ (`v`, `vn`, `f v//vn`, 1-based), atomically.
    pub fn write_obj(&self, path: &Path) -> Result<(), IoError> {
        use std::fmt::Write;
        let mut out = String::from("# fluid-surfels mesh\n");
        for p in &self.positions {
            let _ = writeln!(out, "v {} {} {}", p.x, p.y, p.z);
        }
        for n in &self.normals {
            let _ = writeln!(out, "vn {} {} {}", n.x, n.y, n.z);
        }
        for t in &self.triangles {
            let [a, b, c] = t.map(|v| v + 1);
            let _ = writeln!(out, "f {a}//{a} {b}//{b} {c}//{c}");
        }
        crate::io::write_atomically(path, out.as_bytes())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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

    #[test]
    fn ply_and_obj_write_what_the_mesh_holds() {
        let (m, _) = mesh_of(12, |p: Vec3| 1.0 - p.length());
        let dir = tempfile::tempdir().unwrap();
        let ply = dir.path().join("m.ply");
        m.write_ply(&ply).unwrap();
        let bytes = std::fs::read(&ply).unwrap();
        let header_end = bytes
            .windows(11)
            .position(|w| w == b"end_header\n")
            .unwrap()
            + 11;
        let header = String::from_utf8_lossy(&bytes[..header_end]);
        assert!(header.contains(&format!("element vertex {}", m.positions.len())));
        assert!(header.contains(&format!("element face {}", m.triangles.len())));
        assert_eq!(
            bytes.len() - header_end,
            m.positions.len() * 24 + m.triangles.len() * 13
        );
        let obj = dir.path().join("m.obj");
        m.write_obj(&obj).unwrap();
        let text = std::fs::read_to_string(&obj).unwrap();
        assert_eq!(
            text.lines().filter(|l| l.starts_with("v ")).count(),
            m.positions.len()
        );
        assert_eq!(
            text.lines().filter(|l| l.starts_with("f ")).count(),
            m.triangles.len()
        );
    }
}
