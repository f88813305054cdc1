//! Triangle meshes of the density grid's iso-surface (issue 40), for renderers that take
//! meshes (Blender, Houdini, game engines): [`marching_cubes`] over the grid the surfels lie on
//! (an indexed, watertight, consistently wound mesh; see [`cubes`] for how), [`Mesh`] with its
//! checks (closed, Euler characteristic) and the move of its vertices onto the surfels, and the
//! writers ([`self::write`]).

pub mod cubes;
pub mod read;
pub mod write;

pub use cubes::{marching_cubes, marching_cubes_of_sparse, marching_cubes_of_values};

use glam::Vec3;
use rayon::prelude::*;

/// An indexed triangle mesh.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Mesh {
    /// Vertex positions.
    pub positions: Vec<Vec3>,
    /// Unit vertex normals, pointing out of the fluid.
    pub normals: Vec<Vec3>,
    /// Triangles: three vertex indices each, counter-clockwise seen from outside.
    pub triangles: Vec<[u32; 3]>,
    /// Vertex velocities (for motion blur), when the particles had them
    /// ([`Mesh::interpolate_velocities`]).
    pub velocities: Option<Vec<Vec3>>,
}

/// What [`Mesh::topology`] finds.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Topology {
    /// Every edge shared by exactly two triangles, once each way.
    pub closed: bool,
    /// `V - E + F` over the vertices the triangles use.
    pub euler_characteristic: i64,
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
            velocities: None,
        })
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
        // the first pass checks every triangle, each later one only those around the vertices
        // the pass before put back (a flag read instead of the check: the double dam break's
        // 244,444 triangles were checked up to eight times over)
        let mut changed: Option<Vec<bool>> = None;
        for _ in 0..8 {
            let bad: Vec<u32> = self
                .triangles
                .par_iter()
                .filter(|t| {
                    changed
                        .as_ref()
                        .is_none_or(|c| t.iter().any(|&v| c[v as usize]))
                })
                .filter(|t| {
                    let n = normal_of(&self.positions, t);
                    let given: Vec3 = t.iter().map(|&v| self.normals[v as usize]).sum();
                    self.is_collapsed(t)
                        || n.dot(normal_of(&on_edges, t)) <= 0.0
                        || n.dot(given) <= 0.0
                })
                .flat_map_iter(|t| t.iter().copied())
                .filter(|&v| !kept[v as usize])
                .collect();
            if bad.is_empty() {
                break;
            }
            let mut now = vec![false; on_edges.len()];
            for v in bad {
                self.positions[v as usize] = on_edges[v as usize];
                kept[v as usize] = true;
                now[v as usize] = true;
            }
            changed = Some(now);
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

    /// Sets [`Mesh::velocities`] to the particles' velocities interpolated at every vertex
    /// with the SPH cubic spline of support `radius` (the frame's support radius), normalised
    /// by the kernel's sum (Shepard):
    ///
    /// `v(x) = sum_j v_j W(|x - x_j|, h) / sum_j W(|x - x_j|, h)`.
    ///
    /// Unnormalised (`sum_j m_j / rho_j v_j W`, the textbook SPH estimate) the velocity would
    /// fall towards zero at the surface, where the vertices are and half the kernel is empty;
    /// the normalised sum is exact for a uniform flow and first-order for a sheared one. A
    /// vertex with no particle within `radius` (none on a surface made from these particles at
    /// this radius) takes its nearest particle's velocity. Errors: lengths that differ, a radius
    /// that is not positive and finite, velocities or positions that are not finite, no
    /// particle for a mesh with vertices.
    pub fn interpolate_velocities(
        &mut self,
        positions: &[Vec3],
        velocities: &[Vec3],
        radius: f32,
    ) -> Result<(), crate::Error> {
        let invalid = |argument: &'static str, reason: String| crate::Error::InvalidArgument {
            argument,
            reason,
        };
        if positions.len() != velocities.len() {
            return Err(invalid(
                "velocities",
                format!(
                    "{} velocities for {} particles",
                    velocities.len(),
                    positions.len()
                ),
            ));
        }
        if let Some(i) = velocities.iter().position(|v| !v.is_finite()) {
            return Err(invalid(
                "velocities",
                format!("the velocity of particle {i} is not finite"),
            ));
        }
        if self.positions.is_empty() {
            self.velocities = Some(Vec::new());
            return Ok(());
        }
        if positions.is_empty() {
            return Err(invalid(
                "positions",
                "no particle to take the mesh's velocities from".into(),
            ));
        }
        let grid = crate::neighbours::CellGrid::new(positions, radius)
            .map_err(|e| invalid("positions", e.to_string()))?;
        let kernel = crate::density::Kernel::CubicSpline;
        let mut out: Vec<Option<Vec3>> = self
            .positions
            .par_iter()
            .map(|&x| {
                let (mut sum, mut weight) = (Vec3::ZERO, 0.0f32);
                grid.for_each_within(x, radius, |j| {
                    let w = kernel.value_r2(positions[j as usize].distance_squared(x), radius);
                    sum += velocities[j as usize] * w;
                    weight += w;
                });
                (weight > 0.0).then(|| sum / weight)
            })
            .collect();
        if out.iter().any(Option::is_none) {
            use kiddo::{ImmutableKdTree, SquaredEuclidean};
            let points: Vec<[f32; 3]> = positions.iter().map(|p| p.to_array()).collect();
            let tree = ImmutableKdTree::<f32, 3>::new_from_slice(&points)
                .map_err(|e| invalid("positions", format!("{e:?}")))?;
            let one = std::num::NonZeroUsize::MIN;
            out.par_iter_mut()
                .zip(&self.positions)
                .filter(|(v, _)| v.is_none())
                .for_each(|(v, x)| {
                    let nearest = tree
                        .query(&x.to_array())
                        .nearest_n::<SquaredEuclidean<f32>>(one)
                        .execute();
                    *v = nearest.first().map(|nb| velocities[nb.item as usize]);
                });
        }
        self.velocities = Some(out.into_iter().map(Option::unwrap_or_default).collect());
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Particles on a cubic lattice of spacing `s` filling a ball of radius `r`.
    fn ball(r: f32, s: f32) -> Vec<Vec3> {
        let n = (r / s).ceil() as i32;
        let mut out = Vec::new();
        for i in -n..=n {
            for j in -n..=n {
                for k in -n..=n {
                    let p = Vec3::new(i as f32, j as f32, k as f32) * s;
                    if p.length() <= r {
                        out.push(p);
                    }
                }
            }
        }
        out
    }

    /// The interpolated velocity: exact for a uniform flow (the kernel sum normalised), close
    /// for a rotation at the surface, the nearest particle's far from every particle; bad
    /// input refused.
    #[test]
    fn velocities_interpolated_from_the_particles() {
        let (s, h) = (0.1, 0.2);
        let particles = ball(1.0, s);
        let mut mesh = Mesh::new(
            vec![
                Vec3::new(1.05, 0.0, 0.0),
                Vec3::new(0.0, -1.05, 0.0),
                Vec3::new(0.3, 0.7, 0.7),
                Vec3::new(5.0, 0.0, 0.0),
            ],
            vec![[0, 1, 2]],
        )
        .unwrap();
        let uniform = vec![Vec3::new(0.3, -0.2, 1.0); particles.len()];
        mesh.interpolate_velocities(&particles, &uniform, h)
            .unwrap();
        for v in mesh.velocities.as_ref().unwrap() {
            assert!((*v - uniform[0]).length() < 1e-5, "{v}");
        }
        // a rotation about z: v = (-y, x, 0); at the surface the neighbours lie inside, so the
        // estimate is within the kernel's reach of the truth (first order: a few percent)
        let rotation: Vec<Vec3> = particles
            .iter()
            .map(|p| Vec3::new(-p.y, p.x, 0.0))
            .collect();
        mesh.interpolate_velocities(&particles, &rotation, h)
            .unwrap();
        let v = mesh.velocities.as_ref().unwrap();
        for (x, v) in mesh.positions.iter().zip(v).take(3) {
            let truth = Vec3::new(-x.y, x.x, 0.0);
            assert!(
                (*v - truth).length() < 0.1 * truth.length(),
                "{x}: {v} vs {truth}"
            );
        }
        // far from every particle: the nearest one's, (0, 1, 0) at (1, 0, 0)
        assert!(
            (v[3] - Vec3::new(0.0, 1.0, 0.0)).length() < 1e-5,
            "{}",
            v[3]
        );
        // bad input
        assert!(
            mesh.interpolate_velocities(&particles, &rotation[1..], h)
                .is_err()
        );
        let mut nan = rotation.clone();
        nan[7].x = f32::NAN;
        assert!(mesh.interpolate_velocities(&particles, &nan, h).is_err());
        assert!(
            mesh.interpolate_velocities(&particles, &rotation, 0.0)
                .is_err()
        );
        assert!(mesh.interpolate_velocities(&[], &[], h).is_err());
    }
}
