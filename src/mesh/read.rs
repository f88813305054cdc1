//! Meshes read back from the files [`Mesh::write`] makes: binary or text PLY and legacy VTK
//! `POLYDATA`, through the crate's particle readers (which read the vertices and their
//! attributes) with the faces kept.

use std::path::Path;

use super::{Mesh, vertex_normals};
use crate::io::{IoError, Polygons, ply, vtk};

impl Mesh {
    /// Reads a mesh from a `.ply` or `.vtk` file (by extension): the vertices, their normals
    /// (`nx ny nz` / `NORMALS`; recomputed from the triangles when absent) and velocities
    /// (`vx vy vz` / `velocity`), and the faces, a polygon of `n > 3` vertices split into a fan
    /// of `n - 2` triangles. Errors: another extension, a malformed file, a face of fewer than
    /// three vertices, an index past the vertices.
    pub fn read(path: &Path) -> Result<Self, crate::Error> {
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase);
        let ply = match ext.as_deref() {
            Some("ply") => true,
            Some("vtk") => false,
            _ => {
                return Err(crate::Error::InvalidArgument {
                    argument: "path",
                    reason: format!("{}: a mesh is read from .ply or .vtk", path.display()),
                });
            }
        };
        let bytes = std::fs::read(path).map_err(|source| IoError::Os {
            path: path.to_owned(),
            source,
        })?;
        let mut faces = Polygons::default();
        let set = if ply {
            ply::parse_with_faces(&bytes, path, Some(&mut faces))?
        } else {
            vtk::parse_with_polygons(&bytes, path, Some(&mut faces))?
        };
        let mut triangles = Vec::with_capacity(faces.indices.len() / 3);
        let mut at = 0usize;
        for (face, &count) in faces.counts.iter().enumerate() {
            let count = count as usize;
            if count < 3 {
                return Err(crate::Error::InvalidArgument {
                    argument: "path",
                    reason: format!(
                        "{}: face {face} has {count} vertices; a mesh's faces have three or more",
                        path.display()
                    ),
                });
            }
            let f = &faces.indices[at..at + count];
            triangles.extend((1..count - 1).map(|i| [f[0], f[i], f[i + 1]]));
            at += count;
        }
        let normals = match &set.normals {
            Some(n) => n.clone(),
            None => vertex_normals(&set.positions, &triangles),
        };
        Ok(Self {
            positions: set.positions,
            normals,
            triangles,
            velocities: set.velocities,
        })
    }
}
