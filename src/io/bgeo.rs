//! Houdini classic BGEO files (`Bgeo` magic, `V` and version 5), the format partio writes,
//! gzipped or not.
//!
//! Layout (all big-endian): magic, version, eight counts (points, primitives, point groups,
//! primitive groups, point, vertex, primitive and detail attributes), the point attribute
//! definitions (name, component count, type: 0 float, 1 int, 4 indexed string, 5 vector; then
//! defaults), then per point `x y z w` followed by its attribute values, 4 bytes each.
//! Primitives and detail attributes after the points are not read (particle files have none that
//! matter). Houdini's `v` and `N` become velocities and normals, an integer `id` the ids.
//! Offsets in errors count bytes of the decompressed data.

use std::path::Path;

use super::{
    IoError, Location, RawAttribute, ReadOptions, assemble, check_allocation, check_budget,
    named_arrays, positions_from,
};
use crate::particles::{ParticleSet, ScalarKind};

const MAGIC: &[u8; 4] = b"Bgeo";

struct Reader<'a> {
    data: &'a [u8],
    pos: usize,
    path: &'a Path,
}

impl Reader<'_> {
    fn take(&mut self, n: usize, what: &str) -> Result<&[u8], IoError> {
        let Some(s) = self.data.get(self.pos..self.pos + n) else {
            return Err(IoError::parse(
                self.path,
                Location::Byte(self.pos as u64),
                format!("{what} ({n} bytes)"),
                format!(
                    "end of data after {} bytes (truncated file)",
                    self.data.len()
                ),
            ));
        };
        self.pos += n;
        Ok(s)
    }

    fn i32(&mut self, what: &str) -> Result<i32, IoError> {
        let b = self.take(4, what)?;
        Ok(i32::from_be_bytes([b[0], b[1], b[2], b[3]]))
    }

    fn u16(&mut self, what: &str) -> Result<u16, IoError> {
        let b = self.take(2, what)?;
        Ok(u16::from_be_bytes([b[0], b[1]]))
    }

    fn count(&mut self, what: &str) -> Result<usize, IoError> {
        let at = self.pos;
        let v = self.i32(what)?;
        usize::try_from(v).map_err(|_| {
            IoError::parse(
                self.path,
                Location::Byte(at as u64),
                format!("a non-negative {what}"),
                v.to_string(),
            )
        })
    }

    fn string(&mut self, what: &str) -> Result<String, IoError> {
        let len = self.u16(what)? as usize;
        Ok(String::from_utf8_lossy(self.take(len, what)?).into_owned())
    }
}

struct AttributeDef {
    name: String,
    components: usize,
    kind: ScalarKind,
}

/// Parses the header and attribute definitions; returns the point count, the definitions, and
/// the offset of the point data.
fn header(data: &[u8], path: &Path) -> Result<(usize, Vec<AttributeDef>, usize), IoError> {
    let mut r = Reader { data, pos: 0, path };
    if !data.starts_with(MAGIC) {
        return Err(IoError::WrongFormat {
            path: path.to_owned(),
            expected: "classic BGEO",
            found: super::describe(data),
        });
    }
    r.take(4, "the magic")?;
    let v = r.take(1, "the version mark")?[0];
    let version = r.i32("the version")?;
    if v != b'V' || version != 5 {
        return Err(IoError::unsupported(
            path,
            Location::Byte(4),
            format!(
                "BGEO version {}{version} (only V5, as partio writes it)",
                v as char
            ),
        ));
    }
    let points = r.count("point count")?;
    let _prims = r.count("primitive count")?;
    let _point_groups = r.count("point group count")?;
    let _prim_groups = r.count("primitive group count")?;
    let point_attributes = r.count("point attribute count")?;
    let _vertex_attributes = r.count("vertex attribute count")?;
    let _prim_attributes = r.count("primitive attribute count")?;
    let _detail_attributes = r.count("detail attribute count")?;
    if point_attributes > 10_000 {
        return Err(IoError::parse(
            path,
            Location::Byte(29),
            "at most 10,000 point attributes",
            point_attributes.to_string(),
        ));
    }
    let mut defs = Vec::with_capacity(point_attributes);
    for _ in 0..point_attributes {
        let name = r.string("an attribute name")?;
        let components = r.u16("a component count")? as usize;
        let at = r.pos;
        let kind = r.i32("an attribute type")?;
        let kind = match kind {
            0 | 5 => {
                r.take(4 * components, "default values")?;
                ScalarKind::F32
            }
            1 => {
                r.take(4 * components, "default values")?;
                ScalarKind::I32
            }
            4 => {
                let strings = r.count("an index string count")?;
                for _ in 0..strings {
                    r.string("an index string")?;
                }
                ScalarKind::I32
            }
            other => {
                return Err(IoError::unsupported(
                    path,
                    Location::Byte(at as u64),
                    format!(
                        "BGEO attribute type {other} (attribute {})",
                        super::quoted(&name)
                    ),
                ));
            }
        };
        if components == 0 {
            return Err(IoError::parse(
                path,
                Location::Byte(at as u64 - 2),
                "a component count > 0",
                "0",
            ));
        }
        defs.push(AttributeDef {
            name,
            components,
            kind,
        });
    }
    Ok((points, defs, r.pos))
}

/// Parses a BGEO file held in memory (gzipped or not); `path` names it in errors.
pub fn parse(bytes: &[u8], path: &Path) -> Result<ParticleSet, IoError> {
    parse_with(bytes, path, &ReadOptions::default())
}

/// [`parse`] within a memory budget for decompression.
pub fn parse_with(
    bytes: &[u8],
    path: &Path,
    options: &ReadOptions,
) -> Result<ParticleSet, IoError> {
    if bytes.starts_with(&[0x1f, 0x8b]) {
        // Decompress a prefix for the header, then exactly as much as the header declares: a
        // stream that inflates far beyond it (a gzip bomb) is cut off, not buffered.
        let (prefix, _) =
            super::gunzip_limited(path, bytes, 1 << 20).map_err(|_| truncated_gzip(path, bytes))?;
        let (points, defs, start) = header(&prefix, path)?;
        let needed = start as u128 + points as u128 * record_size(&defs) as u128;
        if needed > bytes.len() as u128 * super::DEFLATE_MAX_RATIO {
            return Err(IoError::parse(
                path,
                Location::Byte(9),
                format!("a point count that {} gzipped bytes can hold", bytes.len()),
                format!("{points} points of {} bytes", record_size(&defs)),
            ));
        }
        // room for a particle-system primitive listing every point, and detail attributes
        let slack = 4 * points as u128 + (1 << 20);
        check_budget(
            path,
            Location::Byte(9),
            "the gzip stream",
            needed + slack,
            options,
        )?;
        check_allocation(path, Location::Byte(9), needed * 3)?;
        let limit = u64::try_from(needed + slack).unwrap_or(u64::MAX);
        let (data, more) =
            super::gunzip_limited(path, bytes, limit).map_err(|_| truncated_gzip(path, bytes))?;
        if more {
            return Err(IoError::parse(
                path,
                Location::Byte(limit),
                format!("at most {limit} bytes of decompressed data for {points} points"),
                "more (a gzip bomb, or a wrong point count)",
            ));
        }
        return parse_plain(&data, path);
    }
    parse_plain(bytes, path)
}

fn truncated_gzip(path: &Path, bytes: &[u8]) -> IoError {
    IoError::parse(
        path,
        Location::Byte(bytes.len() as u64),
        "a complete gzip stream",
        "a stream that ends early or is corrupt",
    )
}

fn record_size(defs: &[AttributeDef]) -> usize {
    4 * (4 + defs.iter().map(|d| d.components).sum::<usize>())
}

fn parse_plain(data: &[u8], path: &Path) -> Result<ParticleSet, IoError> {
    let (points, defs, start) = header(data, path)?;
    let record = record_size(&defs);
    let needed = points as u128 * record as u128;
    if needed > (data.len() - start) as u128 {
        return Err(IoError::parse(
            path,
            Location::Byte(start as u64),
            format!("{points} points of {record} bytes"),
            format!(
                "{} bytes (wrong count or truncated file)",
                data.len() - start
            ),
        ));
    }
    check_allocation(path, Location::Byte(9), needed * 3)?;
    let body = &data[start..start + points * record];
    let float = |b: &[u8]| f32::from_be_bytes([b[0], b[1], b[2], b[3]]) as f64;
    let mut coords = Vec::with_capacity(points * 3);
    for rec in body.chunks_exact(record) {
        coords.extend([float(&rec[0..4]), float(&rec[4..8]), float(&rec[8..12])]);
    }
    let positions = positions_from(path, &coords, |i| {
        Location::Byte((start + i * record) as u64)
    })?;
    let mut offset = 16;
    let mut attributes = Vec::with_capacity(defs.len());
    for d in defs {
        let mut values = Vec::with_capacity(points * d.components);
        for rec in body.chunks_exact(record) {
            for k in 0..d.components {
                let b = &rec[offset + 4 * k..offset + 4 * k + 4];
                values.push(if d.kind == ScalarKind::F32 {
                    float(b)
                } else {
                    i32::from_be_bytes([b[0], b[1], b[2], b[3]]) as f64
                });
            }
        }
        offset += 4 * d.components;
        attributes.push(RawAttribute {
            name: d.name,
            kind: d.kind,
            components: d.components,
            values,
        });
    }
    Ok(assemble(positions, attributes))
}

/// Serialises a particle set as uncompressed BGEO V5. Integer attributes become BGEO ints, all
/// others floats (f64 attributes lose precision: BGEO has no doubles). Velocities are written
/// as Houdini's `v` and normals as `N`.
#[must_use]
pub fn to_bytes(set: &ParticleSet) -> Vec<u8> {
    let arrays: Vec<RawAttribute> = named_arrays(set)
        .into_iter()
        .map(|mut a| {
            a.name = match a.name.as_str() {
                "velocity" => "v".into(),
                "normal" => "N".into(),
                _ => a.name,
            };
            a
        })
        .collect();
    let n = set.len();
    let mut out = Vec::with_capacity(64 + n * 16);
    out.extend_from_slice(MAGIC);
    out.push(b'V');
    let counts = [5, n as i32, 0, 0, 0, arrays.len() as i32, 0, 0, 0];
    for c in counts {
        out.extend_from_slice(&c.to_be_bytes());
    }
    for a in &arrays {
        out.extend_from_slice(&(a.name.len() as u16).to_be_bytes());
        out.extend_from_slice(a.name.as_bytes());
        out.extend_from_slice(&(a.components as u16).to_be_bytes());
        let kind: i32 = if a.kind.is_integer() {
            1
        } else if a.components == 3 {
            5
        } else {
            0
        };
        out.extend_from_slice(&kind.to_be_bytes());
        out.extend(std::iter::repeat_n(0u8, 4 * a.components));
    }
    for i in 0..n {
        for v in set.positions[i].to_array() {
            out.extend_from_slice(&v.to_be_bytes());
        }
        out.extend_from_slice(&1f32.to_be_bytes());
        for a in &arrays {
            for &v in &a.values[i * a.components..(i + 1) * a.components] {
                if a.kind.is_integer() {
                    out.extend_from_slice(&(v as i64 as i32).to_be_bytes());
                } else {
                    out.extend_from_slice(&(v as f32).to_be_bytes());
                }
            }
        }
    }
    // partio ends the file with two bytes
    out.extend_from_slice(&[0x00, 0xff]);
    out
}
