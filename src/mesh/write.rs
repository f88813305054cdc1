//! Writers of [`Mesh`]: binary PLY, OBJ, legacy VTK POLYDATA, VTK XML unstructured grids and
//! USD (`.usda` text, one mesh a frame, and a stage that sequences the frames with value clips,
//! [`write_usd_stage`]).
//! Every file is written atomically (a temporary file renamed over the name).

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use glam::Vec3;

use super::Mesh;
use crate::io::IoError;

/// A mesh file format, chosen by the file's extension ([`MeshFormat::of_path`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MeshFormat {
    /// `.ply`: binary little-endian PLY, `vertex` with `x y z nx ny nz` (and `vx vy vz` with
    /// velocities), `face` with `vertex_indices`.
    Ply,
    /// `.obj`: Wavefront OBJ, `v`, `vn` and `f v//vn` (no velocities: OBJ has none).
    Obj,
    /// `.vtk`: legacy VTK 4.2 BINARY `POLYDATA`, `POLYGONS`, point data `NORMALS normals` (and
    /// `VECTORS velocity`).
    Vtk,
    /// `.usda`: USD text, a `Mesh` prim `/fluid/surface` with `points`, `normals` (vertex
    /// interpolation), `velocities`, `extent` and the faces.
    Usda,
    /// `.vtu`: VTK XML `UnstructuredGrid` of triangle cells, raw appended binary, point data
    /// `Normals` (and `velocity`): the VTK file meshio reads (it refuses legacy `POLYDATA`).
    Vtu,
}

impl MeshFormat {
    /// Every format, in the order the errors list them.
    pub const ALL: [Self; 5] = [Self::Ply, Self::Obj, Self::Vtk, Self::Vtu, Self::Usda];

    /// The extension naming the format.
    #[must_use]
    pub fn extension(self) -> &'static str {
        match self {
            Self::Ply => "ply",
            Self::Obj => "obj",
            Self::Vtk => "vtk",
            Self::Usda => "usda",
            Self::Vtu => "vtu",
        }
    }

    /// Whether the format holds vertex velocities.
    #[must_use]
    pub fn has_velocities(self) -> bool {
        self != Self::Obj
    }

    /// The format of `path`'s extension (case ignored); an error naming every format otherwise.
    pub fn of_path(path: &Path) -> Result<Self, crate::Error> {
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase);
        Self::ALL
            .into_iter()
            .find(|f| ext.as_deref() == Some(f.extension()))
            .ok_or_else(|| crate::Error::InvalidArgument {
                argument: "path",
                reason: format!(
                    "{}: a mesh is written as .ply (binary), .obj, .vtk (legacy POLYDATA), .vtu (VTK XML) or .usda",
                    path.display()
                ),
            })
    }
}

impl Mesh {
    /// Writes the mesh in the format of `path`'s extension ([`MeshFormat::of_path`]),
    /// atomically; a `.usda` file holds the values as defaults (no time; see
    /// [`Mesh::write_usda`] for a frame of a sequence).
    pub fn write(&self, path: &Path) -> Result<(), crate::Error> {
        match MeshFormat::of_path(path)? {
            MeshFormat::Ply => self.write_ply(path)?,
            MeshFormat::Obj => self.write_obj(path)?,
            MeshFormat::Vtk => self.write_vtk(path)?,
            MeshFormat::Vtu => self.write_vtu(path)?,
            MeshFormat::Usda => self.write_usda(path, None)?,
        }
        Ok(())
    }

    /// Writes the mesh as binary little-endian PLY (`vertex` with `x y z nx ny nz`, then
    /// `vx vy vz` when it has velocities; `face` with `vertex_indices`), atomically.
    pub fn write_ply(&self, path: &Path) -> Result<(), IoError> {
        let velocities = self.velocities.as_deref();
        let mut out = format!(
            "ply\nformat binary_little_endian 1.0\ncomment fluid-surfels mesh\nelement vertex {}\n\
             property float x\nproperty float y\nproperty float z\n\
             property float nx\nproperty float ny\nproperty float nz\n{}\
             element face {}\nproperty list uchar uint vertex_indices\nend_header\n",
            self.positions.len(),
            if velocities.is_some() {
                "property float vx\nproperty float vy\nproperty float vz\n"
            } else {
                ""
            },
            self.triangles.len()
        )
        .into_bytes();
        for (i, (p, n)) in self.positions.iter().zip(&self.normals).enumerate() {
            let v = velocities.map(|v| v[i].to_array());
            for x in p
                .to_array()
                .into_iter()
                .chain(n.to_array())
                .chain(v.into_iter().flatten())
            {
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

    /// Writes the mesh as OBJ (`v`, `vn`, `f v//vn`, 1-based), atomically. OBJ has no
    /// velocities.
    pub fn write_obj(&self, path: &Path) -> Result<(), IoError> {
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

    /// Writes the mesh as legacy VTK 4.2 BINARY (big-endian) `POLYDATA`: `POINTS`,
    /// `POLYGONS` (the older count-prefixed cell list, which ParaView, meshio and VTK 9 read),
    /// and as point data `NORMALS normals` and, with velocities, `VECTORS velocity`;
    /// atomically.
    pub fn write_vtk(&self, path: &Path) -> Result<(), IoError> {
        let n = self.positions.len();
        let mut out = format!(
            "# vtk DataFile Version 4.2\nfluid-surfels mesh\nBINARY\nDATASET POLYDATA\nPOINTS {n} float\n"
        )
        .into_bytes();
        let vec3s = |out: &mut Vec<u8>, values: &[Vec3]| {
            for x in values.iter().flat_map(|v| v.to_array()) {
                out.extend_from_slice(&x.to_be_bytes());
            }
            out.push(b'\n');
        };
        vec3s(&mut out, &self.positions);
        let t = self.triangles.len();
        out.extend_from_slice(format!("POLYGONS {t} {}\n", 4 * t).as_bytes());
        for tri in &self.triangles {
            for v in [3, tri[0], tri[1], tri[2]] {
                // indices below 2^31: a mesh has fewer vertices than that (u32 indices, and
                // VTK's `int`)
                out.extend_from_slice(&(v as i32).to_be_bytes());
            }
        }
        out.extend_from_slice(format!("\nPOINT_DATA {n}\nNORMALS normals float\n").as_bytes());
        vec3s(&mut out, &self.normals);
        if let Some(v) = &self.velocities {
            out.extend_from_slice(b"VECTORS velocity float\n");
            vec3s(&mut out, v);
        }
        crate::io::write_atomically(path, &out)
    }

    /// Writes the mesh as a VTK XML `UnstructuredGrid` of triangle cells (raw appended binary
    /// data), with point data `Normals` and, with velocities, `velocity`; atomically. ParaView,
    /// VTK and meshio read it.
    pub fn write_vtu(&self, path: &Path) -> Result<(), IoError> {
        let mut point_data: Vec<(&str, &[Vec3])> = vec![("Normals", &self.normals)];
        if let Some(v) = &self.velocities {
            point_data.push(("velocity", v));
        }
        let bytes = crate::io::vtu::triangles_to_bytes(
            &self.positions,
            &self.triangles,
            &point_data,
            crate::io::vtu::Encoding::RawAppended,
        );
        crate::io::write_atomically(path, &bytes)
    }

    /// Writes the mesh as USD text: a stage whose default prim `/fluid` (an `Xform`) holds the
    /// `Mesh` `/fluid/surface` with `points`, `faceVertexCounts`, `faceVertexIndices`,
    /// `normals` (vertex interpolation), `velocities` when it has them (units per second, as
    /// the particles'), `extent`, and `subdivisionScheme = "none"` (the triangles are the
    /// surface, not a cage); right-handed winding (counter-clockwise seen from outside, as the
    /// mesh's). With `time`, the values are time samples at that time code, as a value clip of
    /// a sequence needs ([`write_usd_stage`]: clips contribute time samples only); without,
    /// they are the attributes' defaults. Atomically.
    pub fn write_usda(&self, path: &Path, time: Option<f64>) -> Result<(), IoError> {
        let mut out = String::with_capacity(64 * self.positions.len() + 32 * self.triangles.len());
        out.push_str(
            "#usda 1.0\n(\n    defaultPrim = \"fluid\"\n    metersPerUnit = 1\n    upAxis = \"Y\"\n)\n\n\
             def Xform \"fluid\"\n{\n    def Mesh \"surface\"\n    {\n\
             \x20       uniform token subdivisionScheme = \"none\"\n\
             \x20       uniform token orientation = \"rightHanded\"\n",
        );
        let (lo, hi) = self
            .positions
            .iter()
            .fold((Vec3::INFINITY, Vec3::NEG_INFINITY), |(lo, hi), &p| {
                (lo.min(p), hi.max(p))
            });
        let (lo, hi) = if self.positions.is_empty() {
            (Vec3::ZERO, Vec3::ZERO)
        } else {
            (lo, hi)
        };
        // metadata follow a default value, or a declaration of their own before time samples
        let mut attribute = |declaration: &str, meta: &str, write: &dyn Fn(&mut String)| match time
        {
            Some(t) => {
                if !meta.is_empty() {
                    let _ = writeln!(out, "        {declaration}{meta}");
                }
                let _ = write!(
                    out,
                    "        {declaration}.timeSamples = {{\n            {t}: "
                );
                write(&mut out);
                out.push_str(",\n        }\n");
            }
            None => {
                let _ = write!(out, "        {declaration} = ");
                write(&mut out);
                out.push_str(meta);
                out.push('\n');
            }
        };
        let list = |out: &mut String, items: &mut dyn Iterator<Item = String>| {
            out.push('[');
            for (i, item) in items.enumerate() {
                if i > 0 {
                    out.push_str(", ");
                }
                out.push_str(&item);
            }
            out.push(']');
        };
        let vec3 = |v: &Vec3| format!("({}, {}, {})", v.x, v.y, v.z);
        attribute("float3[] extent", "", &|o| {
            list(o, &mut [lo, hi].iter().map(vec3));
        });
        attribute("int[] faceVertexCounts", "", &|o| {
            list(o, &mut self.triangles.iter().map(|_| "3".to_string()));
        });
        attribute("int[] faceVertexIndices", "", &|o| {
            list(o, &mut self.triangles.iter().flatten().map(u32::to_string));
        });
        attribute(
            "normal3f[] normals",
            " (\n            interpolation = \"vertex\"\n        )",
            &|o| list(o, &mut self.normals.iter().map(vec3)),
        );
        attribute("point3f[] points", "", &|o| {
            list(o, &mut self.positions.iter().map(vec3));
        });
        if let Some(v) = &self.velocities {
            attribute("vector3f[] velocities", "", &|o| {
                list(o, &mut v.iter().map(vec3))
            });
        }
        out.push_str("    }\n}\n");
        crate::io::write_atomically(path, out.as_bytes())
    }
}

/// The manifest of a USD stage's value clips ([`usd_stage_text`]): the attributes the frames'
/// files hold, declared once so that USD need not open every frame to find them.
pub const USD_MANIFEST: &str = "#usda 1.0\n\nover \"fluid\"\n{\n    over \"surface\"\n    {\n\
    \x20       float3[] extent\n        int[] faceVertexCounts\n        int[] faceVertexIndices\n\
    \x20       normal3f[] normals (\n            interpolation = \"vertex\"\n        )\n\
    \x20       point3f[] points\n        vector3f[] velocities\n    }\n}\n";

/// Where [`write_usd_stage`] writes the manifest of `stage`: `<stem>.manifest.usda` beside it.
#[must_use]
pub fn usd_manifest_path(stage: &Path) -> PathBuf {
    let stem = stage
        .file_stem()
        .and_then(|s| s.to_str())
        .unwrap_or("stage");
    stage.with_file_name(format!("{stem}.manifest.usda"))
}

/// The text of a USD stage (`.usda`) that plays `frames` (time code, the frame's `.usda` file
/// written by [`Mesh::write_usda`] with that time) as an animation: the prim `/fluid` takes
/// its values from the frames through value clips (`UsdClipsAPI`: `assetPaths`, `active` and
/// `times`, each frame's file active from its time code to the next, mapped to itself), with
/// the manifest [`USD_MANIFEST`] at [`usd_manifest_path`]. The paths are written relative to
/// the stage's folder when they lie under it, absolute otherwise. `fps` sets `timeCodesPerSecond` and
/// `framesPerSecond` (velocities are per second). Frames are sorted by time; an empty list or a
/// non-finite time or `fps` is refused. The same frames give the same text, so that the shards
/// of a sequence write the same stage.
pub fn usd_stage_text(
    stage: &Path,
    frames: &[(f64, PathBuf)],
    fps: f64,
) -> Result<String, crate::Error> {
    let invalid = |reason: String| crate::Error::InvalidArgument {
        argument: "frames",
        reason,
    };
    if frames.is_empty() {
        return Err(invalid("a USD stage needs at least one frame".into()));
    }
    if !(fps.is_finite() && fps > 0.0) || frames.iter().any(|(t, _)| !t.is_finite()) {
        return Err(invalid(format!(
            "the frame rate ({fps}) and every time code must be finite and the rate positive"
        )));
    }
    let mut frames = frames.to_vec();
    frames.sort_by(|a, b| a.0.total_cmp(&b.0));
    let dir = stage.parent().unwrap_or(Path::new(""));
    let asset = |p: &Path| {
        let rel = match p.strip_prefix(dir) {
            Ok(r) if !dir.as_os_str().is_empty() || p.is_relative() => format!("./{}", r.display()),
            // elsewhere: absolute, since a bare relative path is a search path to USD
            _ => std::path::absolute(p)
                .unwrap_or_else(|_| p.to_owned())
                .display()
                .to_string(),
        };
        // `@` closes an asset path
        format!("@{}@", rel.replace('@', "\\@"))
    };
    let pairs = |f: &dyn Fn(usize, f64) -> String| {
        frames
            .iter()
            .enumerate()
            .map(|(i, (t, _))| f(i, *t))
            .collect::<Vec<_>>()
            .join(", ")
    };
    let (first, last) = (frames[0].0, frames[frames.len() - 1].0);
    Ok(format!(
        "#usda 1.0\n(\n    defaultPrim = \"fluid\"\n    doc = \"fluid-surfels mesh sequence\"\n\
         \x20   startTimeCode = {first}\n    endTimeCode = {last}\n\
         \x20   timeCodesPerSecond = {fps}\n    framesPerSecond = {fps}\n    metersPerUnit = 1\n\
         \x20   upAxis = \"Y\"\n)\n\n\
         def Xform \"fluid\" (\n    clips = {{\n        dictionary default = {{\n\
         \x20           double2[] active = [{active}]\n\
         \x20           asset[] assetPaths = [{paths}]\n\
         \x20           asset manifestAssetPath = {manifest}\n\
         \x20           string primPath = \"/fluid\"\n\
         \x20           double2[] times = [{times}]\n        }}\n    }}\n)\n{{\n\
         \x20   def Mesh \"surface\"\n    {{\n        uniform token subdivisionScheme = \"none\"\n\
         \x20       uniform token orientation = \"rightHanded\"\n    }}\n}}\n",
        active = pairs(&|i, t| format!("({t}, {i})")),
        paths = frames
            .iter()
            .map(|(_, p)| asset(p))
            .collect::<Vec<_>>()
            .join(", "),
        manifest = asset(&usd_manifest_path(stage)),
        times = pairs(&|_, t| format!("({t}, {t})")),
    ))
}

/// Writes the stage of [`usd_stage_text`] and its manifest, each atomically.
pub fn write_usd_stage(
    stage: &Path,
    frames: &[(f64, PathBuf)],
    fps: f64,
) -> Result<(), crate::Error> {
    let text = usd_stage_text(stage, frames, fps)?;
    crate::io::write_atomically(&usd_manifest_path(stage), USD_MANIFEST.as_bytes())?;
    Ok(crate::io::write_atomically(stage, text.as_bytes())?)
}

#[cfg(test)]
mod tests {
    use glam::Vec3;

    use super::*;
    use crate::density::GridSpec;
    use crate::mesh::marching_cubes;

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

    /// A `.vtu` mesh read back by the crate's VTK XML reader (which reads points and point
    /// data, not cells): every position, normal and velocity; the file says its triangle cells.
    #[test]
    fn vtu_reads_back() {
        let dir = tempfile::tempdir().unwrap();
        let m = swirling(12);
        let path = dir.path().join("m.vtu");
        m.write(&path).unwrap();
        let back = crate::io::read_particles(&path, None).unwrap();
        assert_eq!(back.positions, m.positions);
        assert_eq!(back.normals.as_ref(), Some(&m.normals));
        assert_eq!(back.velocities, m.velocities);
        let text = String::from_utf8_lossy(&std::fs::read(&path).unwrap()).into_owned();
        assert!(text.contains(&format!("NumberOfCells=\"{}\"", m.triangles.len())));
        assert_eq!(MeshFormat::of_path(&path).unwrap(), MeshFormat::Vtu);
    }

    /// A sphere with a swirling velocity (`v = (-y, x, 0.5)`) at its vertices.
    fn swirling(n: u32) -> Mesh {
        let mut m = sphere(n);
        m.velocities = Some(
            m.positions
                .iter()
                .map(|p| Vec3::new(-p.y, p.x, 0.5))
                .collect(),
        );
        m
    }

    /// PLY and VTK read back by the crate's own readers give the mesh written: every position,
    /// normal, velocity and triangle; without velocities, none come back.
    #[test]
    fn ply_and_vtk_read_back_equal() {
        let dir = tempfile::tempdir().unwrap();
        for m in [swirling(14), sphere(9)] {
            for ext in ["ply", "vtk"] {
                let path = dir.path().join(format!("m.{ext}"));
                m.write(&path).unwrap();
                let back = Mesh::read(&path).unwrap();
                assert_eq!(back, m, "{ext}");
            }
        }
        // quads and pentagons (another writer's polygons) come back as fans of triangles
        let path = dir.path().join("quad.ply");
        let mut bytes = b"ply\nformat ascii 1.0\nelement vertex 5\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n".to_vec();
        bytes.extend_from_slice(b"0 0 0\n1 0 0\n1 1 0\n0.5 1.5 0\n0 1 0\n5 0 1 2 3 4\n");
        std::fs::write(&path, &bytes).unwrap();
        let back = Mesh::read(&path).unwrap();
        assert_eq!(back.triangles, vec![[0, 1, 2], [0, 2, 3], [0, 3, 4]]);
        assert!(back.normals.iter().all(|n| (n.z - 1.0).abs() < 1e-6));
        // bad files: an index past the vertices, a two-vertex face, another extension
        let bad = String::from_utf8(bytes).unwrap();
        for (name, text, says) in [
            (
                "past.ply",
                bad.replace("5 0 1 2 3 4", "3 0 1 7"),
                "vertex index below 5",
            ),
            (
                "two.ply",
                bad.replace("5 0 1 2 3 4", "2 0 1"),
                "three or more",
            ),
        ] {
            let path = dir.path().join(name);
            std::fs::write(&path, text).unwrap();
            let e = Mesh::read(&path).unwrap_err().to_string();
            assert!(e.contains(says), "{name}: {e}");
        }
        let e = Mesh::read(&dir.path().join("m.obj"))
            .unwrap_err()
            .to_string();
        assert!(e.contains(".ply or .vtk"), "{e}");
    }

    /// The `.usda` of a frame holds as many points, normals, velocities and face indices as the
    /// mesh, as time samples at its time when given one; the stage lists the frames in time
    /// order, relative to its folder, with a manifest beside it; bad stages are refused.
    #[test]
    fn usda_frames_and_the_stage_that_plays_them() {
        let dir = tempfile::tempdir().unwrap();
        let m = swirling(10);
        let count = |text: &str, line_start: &str| {
            let line = text
                .lines()
                .find(|l| l.trim_start().starts_with(line_start))
                .unwrap_or_else(|| panic!("no {line_start}"));
            let after = line.split_once("= [").unwrap().1.split(']').next().unwrap();
            if after.contains('(') {
                after.matches('(').count()
            } else {
                after.split(',').filter(|x| !x.trim().is_empty()).count()
            }
        };
        let still = dir.path().join("still.usda");
        m.write(&still).unwrap();
        let text = std::fs::read_to_string(&still).unwrap();
        assert!(text.starts_with("#usda 1.0"));
        assert!(!text.contains("timeSamples"));
        assert_eq!(count(&text, "point3f[] points"), m.positions.len());
        assert_eq!(count(&text, "normal3f[] normals"), m.positions.len());
        assert_eq!(count(&text, "vector3f[] velocities"), m.positions.len());
        assert_eq!(
            count(&text, "int[] faceVertexIndices"),
            3 * m.triangles.len()
        );
        assert_eq!(count(&text, "int[] faceVertexCounts"), m.triangles.len());
        let frames: Vec<(f64, std::path::PathBuf)> = [12.0, 10.0, 11.0]
            .into_iter()
            .map(|t| (t, dir.path().join(format!("m_{t}.usda"))))
            .collect();
        for (t, p) in &frames {
            m.write_usda(p, Some(*t)).unwrap();
            let text = std::fs::read_to_string(p).unwrap();
            assert!(
                text.contains(&format!("points.timeSamples = {{\n            {t}: [")),
                "{text:.400}"
            );
        }
        let stage = dir.path().join("m.usda");
        write_usd_stage(&stage, &frames, 30.0).unwrap();
        let text = std::fs::read_to_string(&stage).unwrap();
        for want in [
            "startTimeCode = 10",
            "endTimeCode = 12",
            "timeCodesPerSecond = 30",
            "asset[] assetPaths = [@./m_10.usda@, @./m_11.usda@, @./m_12.usda@]",
            "double2[] active = [(10, 0), (11, 1), (12, 2)]",
            "double2[] times = [(10, 10), (11, 11), (12, 12)]",
            "asset manifestAssetPath = @./m.manifest.usda@",
            "string primPath = \"/fluid\"",
        ] {
            assert!(text.contains(want), "{want} in\n{text}");
        }
        assert_eq!(
            std::fs::read_to_string(dir.path().join("m.manifest.usda")).unwrap(),
            USD_MANIFEST
        );
        // the same frames in another order: the same stage
        let mut shuffled = frames.clone();
        shuffled.swap(0, 2);
        assert_eq!(usd_stage_text(&stage, &shuffled, 30.0).unwrap(), text);
        for (frames, fps) in [
            (vec![], 24.0),
            (frames.clone(), 0.0),
            (vec![(f64::NAN, stage.clone())], 24.0),
        ] {
            assert!(usd_stage_text(&stage, &frames, fps).is_err());
        }
    }

    /// Every extension is recognised whatever its case; others are refused naming the four.
    #[test]
    fn formats_by_extension() {
        for f in MeshFormat::ALL {
            let upper = format!("x.{}", f.extension().to_uppercase());
            assert_eq!(MeshFormat::of_path(Path::new(&upper)).unwrap(), f);
        }
        let e = MeshFormat::of_path(Path::new("x.stl"))
            .unwrap_err()
            .to_string();
        assert!(e.contains(".vtk") && e.contains(".usda"), "{e}");
    }
}
