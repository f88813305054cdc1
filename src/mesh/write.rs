//! Writers of [`Mesh`]: binary PLY, OBJ.

use std::path::Path;

use super::Mesh;
use crate::io::IoError;

impl Mesh {
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
    use glam::Vec3;

    use crate::density::GridSpec;
    use crate::mesh::{Mesh, marching_cubes};

    /// The mesh of a unit sphere on a grid of `n` points a side over [-2, 2]^3.
    fn sphere(n: u32) -> Mesh {
        let spec = GridSpec {
            origin: Vec3::splat(-2.0),
            spacing: 4.0 / (n - 1) as f32,
            dims: [n; 3],
        };
        marching_cubes(
            &spec,
            |i, j, k| {
                1.0 - (spec.origin + Vec3::new(i as f32, j as f32, k as f32) * spec.spacing)
                    .length()
            },
            0.0,
        )
    }

    #[test]
    fn ply_and_obj_write_what_the_mesh_holds() {
        let m = sphere(12);
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
