//! The receiver: the pool's floor and walls (any triangle mesh), with a BVH for the CPU reference.

// `!(x > 0.0)` on purpose throughout: NaN compares false and is rejected with the rest
#![allow(clippy::neg_cmp_op_on_partial_ord)]

use std::path::{Path, PathBuf};
use std::time::Duration;

use glam::{Vec3, Vec3A};
use obvhs::BvhBuildParams;
use obvhs::cwbvh::CwBvh;
use obvhs::cwbvh::builder::build_cwbvh_from_tris;
use obvhs::ray::{Ray, RayHit};
use obvhs::triangle::Triangle;
use serde::{Deserialize, Serialize};

use super::{OpticsError, invalid};

/// The receiver's shape.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ReceiverKind {
    /// An open box (pool) around the water, its walls up to 1.2x the water's level. Built by a
    /// [`crate::optics::Stage`] alone: floor and walls 2 % of the water's size outside it; a
    /// [`crate::pipeline::Pipeline`] fits them a quarter spacing inside the water's surface,
    /// where a simulation's walls are, so that the water meets them.
    #[default]
    Auto,
    /// A horizontal rectangle at `min.y` spanning `min.xz..max.xz`.
    Plane,
    /// An open box: floor at `min.y`, four walls up to `max.y`, no lid.
    OpenBox,
    /// A triangle mesh from a Wavefront OBJ file (`path`; `v` and `f` lines, polygons fanned);
    /// a closed one (every edge shared by two triangles) holds the water (`Container`).
    Mesh,
}

/// The receiver as a scene file describes it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Receiver {
    pub kind: ReceiverKind,
    pub min: Vec3,
    pub max: Vec3,
    pub path: Option<PathBuf>,
    /// Diffuse reflectance `f_r` of eq. 3 (linear RGB).
    pub albedo: Vec3,
    /// Checkerboard tile size (0: plain), to make refraction visible.
    pub checker: f32,
}

impl Default for Receiver {
    fn default() -> Self {
        Self {
            kind: ReceiverKind::Auto,
            min: Vec3::new(-1.0, 0.0, -1.0),
            max: Vec3::new(1.0, 1.0, 1.0),
            path: None,
            albedo: Vec3::new(0.85, 0.82, 0.72),
            checker: 0.0,
        }
    }
}

impl Receiver {
    /// The triangles of the receiver. For `Auto`, `water` is the box to build the pool around:
    /// the floor a margin below its `min.y`, the walls a margin outside it, up to its `max.y`
    /// (see [`crate::optics::Stage::new`], which gives the water's level there, not its top).
    pub fn build(&self, water: Option<(Vec3, Vec3)>) -> Result<ReceiverGeometry, OpticsError> {
        if !(self.albedo.is_finite() && self.albedo.min_element() >= 0.0) {
            return Err(invalid("receiver.albedo", "must be finite and >= 0"));
        }
        if !(self.checker.is_finite() && self.checker >= 0.0) {
            return Err(invalid("receiver.checker", "must be finite and >= 0"));
        }
        let boxed = |name: &'static str| {
            if self.min.is_finite() && self.max.is_finite() && self.max.cmpgt(self.min).all() {
                Ok((self.min, self.max))
            } else {
                Err(invalid(name, "needs finite min < max on every axis"))
            }
        };
        let triangles = match self.kind {
            ReceiverKind::Auto => {
                let (a, b) = water.unwrap_or((Vec3::new(-1.0, 0.0, -1.0), Vec3::ONE));
                let size = (b - a).max_element().max(1e-3);
                let m = 0.02 * size;
                let lo = Vec3::new(a.x - m, a.y - m, a.z - m);
                let hi = Vec3::new(b.x + m, b.y.max(a.y + size * 0.05), b.z + m);
                open_box(lo, hi)
            }
            ReceiverKind::Plane => {
                let (a, b) = boxed("receiver (plane)")?;
                plane(a, b)
            }
            ReceiverKind::OpenBox => {
                let (a, b) = boxed("receiver (open_box)")?;
                open_box(a, b)
            }
            ReceiverKind::Mesh => {
                let path = self
                    .path
                    .as_ref()
                    .ok_or_else(|| invalid("receiver.path", "kind = \"mesh\" needs a path"))?;
                read_obj(path)?
            }
        };
        let mut geometry = ReceiverGeometry::new(triangles)?;
        geometry.container = match self.kind {
            ReceiverKind::Auto | ReceiverKind::OpenBox => {
                let (min, max) = geometry.bounds();
                Some(Container::OpenBox { min, max })
            }
            ReceiverKind::Mesh if is_closed(&geometry.triangles) => Some(Container::ClosedMesh),
            ReceiverKind::Mesh | ReceiverKind::Plane => None,
        };
        Ok(geometry)
    }
}

/// The inside of a receiver that holds the water (issue 41). The water is clipped to it: what of
/// the water's surface lies outside (a splat disk reaching through a wall, the raw particles'
/// surface poking past a face) is neither drawn nor casts shadow nor bends light. Its faces have
/// zero thickness, so without the clip the water inside showed through a wall's outer face and
/// shaded it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Container {
    /// The open box's prism over its floor and between its walls, open upwards (a splash above
    /// the rim is still in it): `min` is the floor's corner; `max.y`, the walls' top, does not
    /// bound it.
    OpenBox { min: Vec3, max: Vec3 },
    /// A closed mesh (every edge shared by two triangles): its inside, by the parity of a ray's
    /// crossings.
    ClosedMesh,
}

impl Container {
    /// Whether the point `p` is inside the open box's prism (inclusive); NaN is outside.
    #[must_use]
    pub fn box_holds(min: Vec3, max: Vec3, p: Vec3) -> bool {
        p.x >= min.x && p.x <= max.x && p.z >= min.z && p.z <= max.z && p.y >= min.y
    }
}

/// Whether a triangle mesh is closed: every edge (between vertices welded by equal positions)
/// shared by exactly two triangles.
fn is_closed(triangles: &[[Vec3; 3]]) -> bool {
    let key = |p: Vec3| [p.x.to_bits(), p.y.to_bits(), p.z.to_bits()];
    let mut edges: std::collections::HashMap<([u32; 3], [u32; 3]), u32> =
        std::collections::HashMap::new();
    for t in triangles {
        for k in 0..3 {
            let (a, b) = (key(t[k]), key(t[(k + 1) % 3]));
            *edges
                .entry(if a < b { (a, b) } else { (b, a) })
                .or_default() += 1;
        }
    }
    !edges.is_empty() && edges.values().all(|&n| n == 2)
}

/// The direction of the parity rays of a closed mesh's inside test: off every axis and diagonal,
/// so that it rarely runs along an edge (where one crossing can count twice). `PARITY_DIR` in
/// the WGSL.
pub const PARITY_DIR: Vec3 = Vec3::new(0.311_265_8, 0.866_025_4, 0.391_147_2);

/// A horizontal rectangle at `a.y` over `a.xz..b.xz`, two triangles whose shared diagonal does not
/// pass through the middle of the usual symmetric pixel grids (see PLATFORM.md on obvhs).
fn plane(a: Vec3, b: Vec3) -> Vec<[Vec3; 3]> {
    quad(
        Vec3::new(a.x, a.y, a.z),
        Vec3::new(b.x, a.y, a.z),
        Vec3::new(b.x, a.y, b.z),
        Vec3::new(a.x, a.y, b.z),
    )
}

fn quad(p0: Vec3, p1: Vec3, p2: Vec3, p3: Vec3) -> Vec<[Vec3; 3]> {
    vec![[p0, p1, p2], [p0, p2, p3]]
}

/// Floor and four walls of the box `a..b`.
fn open_box(a: Vec3, b: Vec3) -> Vec<[Vec3; 3]> {
    let mut t = plane(a, b);
    let v = |x: f32, y: f32, z: f32| Vec3::new(x, y, z);
    t.extend(quad(
        v(a.x, a.y, a.z),
        v(a.x, a.y, b.z),
        v(a.x, b.y, b.z),
        v(a.x, b.y, a.z),
    ));
    t.extend(quad(
        v(b.x, a.y, a.z),
        v(b.x, b.y, a.z),
        v(b.x, b.y, b.z),
        v(b.x, a.y, b.z),
    ));
    t.extend(quad(
        v(a.x, a.y, a.z),
        v(a.x, b.y, a.z),
        v(b.x, b.y, a.z),
        v(b.x, a.y, a.z),
    ));
    t.extend(quad(
        v(a.x, a.y, b.z),
        v(b.x, a.y, b.z),
        v(b.x, b.y, b.z),
        v(a.x, b.y, b.z),
    ));
    t
}

/// Reads the triangles of a Wavefront OBJ file: `v x y z` and `f i j k ...` lines (indices from 1,
/// negative ones relative, `i/t/n` forms accepted, polygons fanned); everything else is ignored.
pub fn read_obj(path: &Path) -> Result<Vec<[Vec3; 3]>, OpticsError> {
    let file_error = |reason: String| OpticsError::File {
        path: path.to_path_buf(),
        reason,
    };
    let text = std::fs::read_to_string(path).map_err(|e| file_error(e.to_string()))?;
    parse_obj(&text).map_err(file_error)
}

/// [`read_obj`] on text.
pub fn parse_obj(text: &str) -> Result<Vec<[Vec3; 3]>, String> {
    let mut vertices: Vec<Vec3> = Vec::new();
    let mut triangles = Vec::new();
    for (line_no, line) in text.lines().enumerate() {
        let at = |reason: &str| format!("line {}: {reason}", line_no + 1);
        let mut words = line.split_whitespace();
        match words.next() {
            Some("v") => {
                let xyz: Vec<f32> = words
                    .take(3)
                    .map(|w| w.parse::<f32>())
                    .collect::<Result<_, _>>()
                    .map_err(|e| at(&format!("bad vertex: {e}")))?;
                if xyz.len() != 3 || xyz.iter().any(|x| !x.is_finite()) {
                    return Err(at("a vertex needs three finite coordinates"));
                }
                vertices.push(Vec3::new(xyz[0], xyz[1], xyz[2]));
            }
            Some("f") => {
                let mut idx = Vec::new();
                for w in words {
                    let first = w.split('/').next().unwrap_or("");
                    let i: i64 = first
                        .parse()
                        .map_err(|_| at(&format!("bad face index `{w}`")))?;
                    let n = vertices.len() as i64;
                    let k = if i > 0 { i - 1 } else { n + i };
                    if i == 0 || !(0..n).contains(&k) {
                        return Err(at(&format!("face index {i} with {n} vertices so far")));
                    }
                    idx.push(vertices[k as usize]);
                }
                if idx.len() < 3 {
                    return Err(at("a face needs at least three vertices"));
                }
                for j in 1..idx.len() - 1 {
                    triangles.push([idx[0], idx[j], idx[j + 1]]);
                }
            }
            _ => {}
        }
    }
    if triangles.is_empty() {
        return Err("no faces".into());
    }
    Ok(triangles)
}

/// Largest receiver.
pub const MAX_TRIANGLES: usize = 4_000_000;

/// The receiver's triangles and their BVH.
pub struct ReceiverGeometry {
    pub triangles: Vec<[Vec3; 3]>,
    bvh: CwBvh,
    tris: Vec<Triangle>,
    bounds: (Vec3, Vec3),
    /// The inside that holds the water, for an open box (`Auto`, `OpenBox`); `None` for a plane or
    /// a mesh, whose water is not clipped.
    pub container: Option<Container>,
}

impl std::fmt::Debug for ReceiverGeometry {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ReceiverGeometry")
            .field("triangles", &self.triangles.len())
            .field("bounds", &self.bounds)
            .finish()
    }
}

/// A ray's hit on the receiver.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    /// Ray parameter (in units of the ray direction's length).
    pub t: f32,
    pub position: Vec3,
    /// Unit geometric normal, facing against the ray.
    pub normal: Vec3,
}

impl ReceiverGeometry {
    /// Builds the BVH of a mesh; degenerate triangles (zero area, non-finite) are dropped.
    pub fn new(triangles: Vec<[Vec3; 3]>) -> Result<Self, OpticsError> {
        if triangles.len() > MAX_TRIANGLES {
            return Err(invalid(
                "receiver",
                format!("{} triangles (at most {MAX_TRIANGLES})", triangles.len()),
            ));
        }
        let triangles: Vec<[Vec3; 3]> = triangles
            .into_iter()
            .filter(|[a, b, c]| {
                a.is_finite()
                    && b.is_finite()
                    && c.is_finite()
                    && (*b - *a).cross(*c - *a).length_squared() > 0.0
            })
            .collect();
        if triangles.is_empty() {
            return Err(invalid("receiver", "has no triangle of non-zero area"));
        }
        let tris: Vec<Triangle> = triangles
            .iter()
            .map(|t| Triangle {
                v0: Vec3A::from(t[0]),
                v1: Vec3A::from(t[1]),
                v2: Vec3A::from(t[2]),
            })
            .collect();
        let bvh = build_cwbvh_from_tris(
            &tris,
            BvhBuildParams::fast_build(),
            &mut Duration::default(),
        );
        let bounds = triangles
            .iter()
            .flat_map(|t| t.iter().copied())
            .fold((Vec3::MAX, Vec3::MIN), |(a, b), p| (a.min(p), b.max(p)));
        Ok(Self {
            triangles,
            bvh,
            tris,
            bounds,
            container: None,
        })
    }

    /// Bounds of the triangles.
    #[must_use]
    pub fn bounds(&self) -> (Vec3, Vec3) {
        self.bounds
    }

    /// Whether the water point `p` is inside the container (always, without one).
    #[must_use]
    pub fn holds(&self, p: Vec3) -> bool {
        match self.container {
            None => true,
            Some(Container::OpenBox { min, max }) => Container::box_holds(min, max, p),
            Some(Container::ClosedMesh) => self.inside(p),
        }
    }

    /// Whether the receiver point `p` with normal `n` is on an outer face of the container: its
    /// side of the face (a step along `n`) lies outside. The light that reaches such a point
    /// crosses no water, which is all inside: for an open box because its outer faces lie on its
    /// hull (the ray from a point of the +x face towards a light with `l.x > 0` only moves away
    /// from the box); for a closed mesh because a ray from outside must cross the mesh to reach
    /// its inside, and a crossing is the receiver's own shadow.
    #[must_use]
    pub fn outer_face(&self, p: Vec3, n: Vec3) -> bool {
        if self.container.is_none() {
            return false;
        }
        let step = 1e-4 * (self.bounds.1 - self.bounds.0).max_element();
        !self.holds(p + n * step)
    }

    /// Whether `p` is inside the mesh: an odd number of crossings along [`PARITY_DIR`] (at most
    /// 64 counted). NaN is outside.
    fn inside(&self, p: Vec3) -> bool {
        if !p.is_finite() {
            return false;
        }
        let (lo, hi) = self.bounds;
        if p.cmplt(lo).any() || p.cmpgt(hi).any() {
            return false;
        }
        let eps = 1e-6 * (hi - lo).max_element();
        let (mut t, mut crossings) = (0.0, 0u32);
        while crossings < 64 {
            match self.intersect(p, PARITY_DIR, t) {
                Some(h) => {
                    crossings += 1;
                    t = h.t + eps;
                }
                None => break,
            }
        }
        crossings % 2 == 1
    }

    /// The closest hit of the ray `origin + t dir`, `t` in `(t_min, inf)`.
    #[must_use]
    pub fn intersect(&self, origin: Vec3, dir: Vec3, t_min: f32) -> Option<Hit> {
        self.nearest(origin, dir, t_min)
            .map(|near| self.hit_at(origin, dir, near))
    }

    /// [`Self::intersect`] as the ray's parameter and the triangle it meets, 8 bytes to keep
    /// (`optics::ReceiverViews`); [`Self::hit_at`] makes the hit of them, bit for bit.
    #[must_use]
    pub fn nearest(&self, origin: Vec3, dir: Vec3, t_min: f32) -> Option<Nearest> {
        if !(origin.is_finite() && dir.is_finite()) || dir.length_squared() == 0.0 {
            return None;
        }
        // obvhs's CWBVH traversal misses every hit of a direction with a -0.0 component (the
        // octant is read from the sign bit; measured: (-0, -1, -0) misses a floor that (0, -1, 0)
        // hits); adding +0.0 turns -0.0 into +0.0 and changes nothing else
        let dir = dir + Vec3::ZERO;
        let ray = Ray::new(Vec3A::from(origin), Vec3A::from(dir), t_min, f32::INFINITY);
        let mut hit = RayHit::none();
        let tris = &self.tris;
        let indices = &self.bvh.primitive_indices;
        if !self.bvh.ray_traverse(ray, &mut hit, |r, id| {
            intersect_triangle(r, &tris[indices[id] as usize])
        }) {
            return None;
        }
        Some(Nearest {
            t: hit.t,
            triangle: indices[hit.primitive_id as usize],
        })
    }

    /// The hit of the ray `origin + t dir` that [`Self::nearest`] found.
    #[must_use]
    pub fn hit_at(&self, origin: Vec3, dir: Vec3, near: Nearest) -> Hit {
        // the direction `nearest` traversed with (-0.0 made +0.0, see there), so that the hit is
        // the one `intersect` made before it was split in two, bit for bit
        let dir = dir + Vec3::ZERO;
        let mut n = Vec3::from(self.tris[near.triangle as usize].compute_normal());
        if n.dot(dir) > 0.0 {
            n = -n;
        }
        Hit {
            t: near.t,
            position: origin + dir * near.t,
            normal: n,
        }
    }
}

/// A ray's closest hit as [`ReceiverGeometry::nearest`] finds it: its parameter and triangle.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Nearest {
    pub t: f32,
    pub triangle: u32,
}

/// Möller-Trumbore with a small tolerance on the barycentric coordinates, so that a ray along an
/// edge shared by two triangles hits one of them (obvhs's own test can miss both, PLATFORM.md).
fn intersect_triangle(ray: &Ray, t: &Triangle) -> f32 {
    const SLACK: f32 = 1e-6;
    let e1 = t.v1 - t.v0;
    let e2 = t.v2 - t.v0;
    let p = ray.direction.cross(e2);
    let det = e1.dot(p);
    if det.abs() < 1e-20 {
        return f32::INFINITY;
    }
    let inv = 1.0 / det;
    let s = ray.origin - t.v0;
    let u = s.dot(p) * inv;
    if !(-SLACK..=1.0 + SLACK).contains(&u) {
        return f32::INFINITY;
    }
    let q = s.cross(e1);
    let v = ray.direction.dot(q) * inv;
    if v < -SLACK || u + v > 1.0 + SLACK {
        return f32::INFINITY;
    }
    let dist = e2.dot(q) * inv;
    if dist > ray.tmin && dist < ray.tmax {
        dist
    } else {
        f32::INFINITY
    }
}
