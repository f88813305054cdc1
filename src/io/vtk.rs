//! Legacy VTK files (`# vtk DataFile Version 2.0` to `5.1`), ASCII and BINARY (big-endian).
//!
//! Reads the points of `UNSTRUCTURED_GRID` and `POLYDATA` datasets (the cells, vertex cells as
//! SPlisHSPlasH writes them or 5.1's `OFFSETS`/`CONNECTIVITY` as ParaView writes them, are read
//! past) and every `POINT_DATA` array: `SCALARS` (with or without a lookup table), `VECTORS`,
//! `NORMALS`, `TEXTURE_COORDINATES`, `TENSORS` and `FIELD` blocks. Arrays named `id`, `velocity`,
//! `mass` or `normal(s)` fill the particle set's own fields; the rest are kept by name.
//! `CELL_DATA` and `METADATA` blocks are skipped.
//!
//! Writes legacy 4.2 BINARY unstructured grids of vertex cells with a `FIELD` block holding every
//! attribute, which ParaView and the `vtkio` crate read.

use std::path::Path;

use super::{
    IoError, Location, RawAttribute, assemble, check_allocation, named_arrays, positions_from,
    push_value, read_value,
};
use crate::particles::{ParticleSet, ScalarKind};

/// A VTK data type: how many bytes a value takes and how it maps to a [`ScalarKind`].
#[derive(Clone, Copy, Debug)]
struct VtkType {
    kind: ScalarKind,
    size: usize,
    /// 64-bit integers, read into f64 (exact up to 2^53)
    int64: Option<bool>,
}

fn vtk_type(name: &str) -> Option<VtkType> {
    let t = |kind: ScalarKind| VtkType {
        kind,
        size: kind.size(),
        int64: None,
    };
    Some(match name.to_ascii_lowercase().as_str() {
        "unsigned_char" => t(ScalarKind::U8),
        "char" | "signed_char" => t(ScalarKind::I8),
        "unsigned_short" => t(ScalarKind::U16),
        "short" => t(ScalarKind::I16),
        "unsigned_int" => t(ScalarKind::U32),
        "int" => t(ScalarKind::I32),
        "float" => t(ScalarKind::F32),
        "double" => t(ScalarKind::F64),
        "long" | "vtktypeint64" | "vtkidtype" => VtkType {
            kind: ScalarKind::F64,
            size: 8,
            int64: Some(true),
        },
        "unsigned_long" | "vtktypeuint64" => VtkType {
            kind: ScalarKind::F64,
            size: 8,
            int64: Some(false),
        },
        _ => return None,
    })
}

/// Walks the file: text lines for keywords, values in ASCII tokens or big-endian binary.
struct Cursor<'a> {
    bytes: &'a [u8],
    pos: usize,
    line: usize,
    binary: bool,
    path: &'a Path,
}

impl<'a> Cursor<'a> {
    fn at(&self) -> Location {
        if self.binary {
            Location::Byte(self.pos as u64)
        } else {
            Location::Line(self.line)
        }
    }

    fn err(&self, expected: impl Into<String>, found: impl Into<String>) -> IoError {
        IoError::parse(self.path, Location::Line(self.line), expected, found)
    }

    /// The next line, without its end; `None` at the end of the file.
    fn raw_line(&mut self) -> Result<Option<&'a str>, IoError> {
        if self.pos >= self.bytes.len() {
            return Ok(None);
        }
        let rest = &self.bytes[self.pos..];
        let len = rest.iter().position(|&b| b == b'\n').unwrap_or(rest.len());
        self.pos += (len + 1).min(rest.len());
        self.line += 1;
        let text = std::str::from_utf8(&rest[..len]).map_err(|_| {
            IoError::parse(
                self.path,
                Location::Line(self.line),
                "a text line",
                "binary bytes",
            )
        })?;
        Ok(Some(text.trim_end_matches('\r')))
    }

    /// The next non-blank line, trimmed.
    fn line(&mut self) -> Result<Option<&'a str>, IoError> {
        while let Some(l) = self.raw_line()? {
            if !l.trim().is_empty() {
                return Ok(Some(l.trim()));
            }
        }
        Ok(None)
    }

    /// Reads `count` values of type `t`; binary values are big-endian and end with a newline.
    fn values(&mut self, count: u64, t: VtkType, what: &str) -> Result<Vec<f64>, IoError> {
        let remaining = (self.bytes.len() - self.pos) as u128;
        // binary values fill `size` bytes each; ASCII values take a digit and a separator
        // each, but the last may end the file without one
        let fits = if self.binary {
            count as u128 * t.size as u128 <= remaining
        } else {
            (count as u128 * 2).saturating_sub(1) <= remaining
        };
        if !fits {
            return Err(IoError::parse(
                self.path,
                self.at(),
                format!("{count} values of {what}"),
                format!("{remaining} bytes left in the file (wrong count or truncated file)"),
            ));
        }
        check_allocation(self.path, self.at(), count as u128 * 8)?;
        let count = count as usize;
        let mut out = Vec::with_capacity(count);
        if self.binary {
            let end = self.pos + count * t.size;
            let data = &self.bytes[self.pos..end];
            match t.int64 {
                None => out.extend(
                    data.chunks_exact(t.size)
                        .map(|c| read_value(c, t.kind, true)),
                ),
                Some(true) => out.extend(
                    data.chunks_exact(8)
                        .map(|c| i64::from_be_bytes(c.try_into().expect("8 bytes")) as f64),
                ),
                Some(false) => out.extend(
                    data.chunks_exact(8)
                        .map(|c| u64::from_be_bytes(c.try_into().expect("8 bytes")) as f64),
                ),
            }
            self.pos = end;
            // the binary block is followed by a line end (some writers omit it at the file's end)
            if self.bytes.get(self.pos) == Some(&b'\n') {
                self.pos += 1;
            }
        } else {
            // `self.line` counts the lines consumed; values start on the next one
            let mut line = self.line + 1;
            while out.len() < count {
                while self
                    .bytes
                    .get(self.pos)
                    .is_some_and(u8::is_ascii_whitespace)
                {
                    if self.bytes[self.pos] == b'\n' {
                        line += 1;
                    }
                    self.pos += 1;
                }
                let start = self.pos;
                while self
                    .bytes
                    .get(self.pos)
                    .is_some_and(|c| !c.is_ascii_whitespace())
                {
                    self.pos += 1;
                }
                if start == self.pos {
                    return Err(IoError::parse(
                        self.path,
                        Location::Line(line),
                        format!("{count} values of {what}"),
                        format!("end of file after {}", out.len()),
                    ));
                }
                let token = String::from_utf8_lossy(&self.bytes[start..self.pos]);
                let v: f64 = token.parse().map_err(|_| {
                    IoError::parse(
                        self.path,
                        Location::Line(line),
                        format!("a number ({what})"),
                        super::quoted(&token),
                    )
                })?;
                out.push(if t.kind == ScalarKind::F32 {
                    v as f32 as f64
                } else {
                    v
                });
            }
            // finish the current line; the next `raw_line` consumes its end
            while self.bytes.get(self.pos).is_some_and(|&c| c != b'\n') {
                self.pos += 1;
            }
            self.line = line - 1;
        }
        Ok(out)
    }
}

fn number<T: std::str::FromStr>(
    c: &Cursor<'_>,
    word: Option<&str>,
    what: &str,
) -> Result<T, IoError> {
    let w = word.ok_or_else(|| c.err(what.to_owned(), "end of line"))?;
    w.parse()
        .map_err(|_| c.err(what.to_owned(), super::quoted(w)))
}

fn data_type(c: &Cursor<'_>, word: Option<&str>) -> Result<VtkType, IoError> {
    let w = word.ok_or_else(|| c.err("a data type", "end of line"))?;
    vtk_type(w).ok_or_else(|| {
        IoError::unsupported(
            c.path,
            Location::Line(c.line),
            format!("the VTK data type {}", super::quoted(w)),
        )
    })
}

/// The header: the version line (1.x to 5.x), the title and `ASCII` or `BINARY` (which sets the
/// cursor's mode); returns the version.
fn header(c: &mut Cursor<'_>, path: &Path) -> Result<f32, IoError> {
    let first = c.raw_line()?.unwrap_or_default();
    let version: f32 = first
        .rsplit(' ')
        .next()
        .and_then(|v| v.parse().ok())
        .ok_or_else(|| c.err("`# vtk DataFile Version X.Y`", super::quoted(first)))?;
    if !(1.0..6.0).contains(&version) {
        return Err(IoError::unsupported(
            path,
            Location::Line(1),
            format!("VTK file version {version}"),
        ));
    }
    c.raw_line()?; // title
    match c.line()? {
        Some("ASCII") => c.binary = false,
        Some("BINARY") => c.binary = true,
        other => {
            return Err(c.err(
                "ASCII or BINARY",
                other.map_or("end of file".into(), super::quoted),
            ));
        }
    }
    Ok(version)
}

/// Skips a `CELLS`-like block (the particles need no cells): 5.x `OFFSETS` and `CONNECTIVITY`
/// arrays of their own type, or the older single list of ints.
/// Reads a block of cells; with `polygons`, appends them to it (each cell's vertex count and
/// its vertex indices, checked against `points`).
fn read_cells(
    c: &mut Cursor<'_>,
    words: &mut std::str::SplitWhitespace<'_>,
    version: f32,
    binary: bool,
    polygons: Option<(&mut super::Polygons, u64)>,
) -> Result<(), IoError> {
    let a: u64 = number(c, words.next(), "a cell count")?;
    let b: u64 = number(c, words.next(), "a cell list size")?;
    let (offsets, connectivity) = if version >= 5.0 {
        // 5.x: OFFSETS <type> (a values) and CONNECTIVITY <type> (b values)
        let mut read = [Vec::new(), Vec::new()];
        for ((label, count), out) in [("OFFSETS", a), ("CONNECTIVITY", b)]
            .into_iter()
            .zip(&mut read)
        {
            c.binary = false;
            let l = c.line()?.unwrap_or("end of file");
            c.binary = binary;
            let mut w = l.split_whitespace();
            if w.next().map(str::to_ascii_uppercase).as_deref() != Some(label) {
                return Err(c.err(format!("`{label} <type>`"), super::quoted(l)));
            }
            let t = data_type(c, w.next())?;
            *out = c.values(count, t, label)?;
        }
        let [offsets, connectivity] = read;
        (offsets, connectivity)
    } else {
        let lists = c.values(b, vtk_type("int").expect("int is a VTK type"), "cell lists")?;
        // count-prefixed lists: the offsets are where each count's cell ends
        let (mut offsets, mut connectivity) = (vec![0.0], Vec::with_capacity(lists.len()));
        let mut at = 0usize;
        for _ in 0..a {
            let n = lists.get(at).copied().unwrap_or(-1.0);
            if !(n >= 0.0 && at + 1 + n as usize <= lists.len()) {
                return Err(c.err(
                    "cell lists as long as their counts say",
                    format!("a count of {n}"),
                ));
            }
            connectivity.extend_from_slice(&lists[at + 1..at + 1 + n as usize]);
            offsets.push(connectivity.len() as f64);
            at += 1 + n as usize;
        }
        (offsets, connectivity)
    };
    if let Some((polygons, points)) = polygons {
        let bad = || {
            c.err(
                "cell offsets that rise within the connectivity, and point indices",
                "others",
            )
        };
        for w in offsets.windows(2) {
            let (s, e) = (w[0], w[1]);
            if !(0.0 <= s && s <= e && e as usize <= connectivity.len()) {
                return Err(bad());
            }
            polygons.counts.push((e - s) as u32);
            for &v in &connectivity[s as usize..e as usize] {
                if !(v >= 0.0 && (v as u64) < points) {
                    return Err(bad());
                }
                polygons.indices.push(v as u32);
            }
        }
    }
    Ok(())
}

/// The component count and value type of a `SCALARS`, `VECTORS`, `NORMALS`, `TENSORS`,
/// `TEXTURE_COORDINATES` or `COLOR_SCALARS` header.
fn array_header(
    c: &Cursor<'_>,
    keyword: &str,
    words: &mut std::str::SplitWhitespace<'_>,
    binary: bool,
) -> Result<(usize, VtkType), IoError> {
    Ok(match keyword {
        "SCALARS" => {
            let t = data_type(c, words.next())?;
            (
                words
                    .next()
                    .map_or(Ok(1), |w| number::<usize>(c, Some(w), "a component count"))?,
                t,
            )
        }
        "VECTORS" | "NORMALS" => (3, data_type(c, words.next())?),
        "TENSORS" => (9, data_type(c, words.next())?),
        "TEXTURE_COORDINATES" => {
            let dim: usize = number(c, words.next(), "a dimension")?;
            (dim, data_type(c, words.next())?)
        }
        _ => {
            let k: usize = number(c, words.next(), "a component count")?;
            let t = if binary {
                vtk_type("unsigned_char")
            } else {
                vtk_type("float")
            };
            (k, t.expect("known VTK types"))
        }
    })
}

/// Skips a `LOOKUP_TABLE` block (four values a colour).
fn skip_lookup_table(
    c: &mut Cursor<'_>,
    words: &mut std::str::SplitWhitespace<'_>,
    binary: bool,
) -> Result<(), IoError> {
    let _name = words.next();
    let size: u64 = number(c, words.next(), "a table size")?;
    let t = if binary {
        vtk_type("unsigned_char")
    } else {
        vtk_type("float")
    };
    c.values(
        size.saturating_mul(4),
        t.expect("known VTK types"),
        "a lookup table",
    )?;
    Ok(())
}

/// A `FIELD` block's arrays; those of point data with one tuple a point (`point_count`, given
/// inside `POINT_DATA` only) join `attributes`.
fn field_arrays(
    c: &mut Cursor<'_>,
    words: &mut std::str::SplitWhitespace<'_>,
    binary: bool,
    point_count: Option<u64>,
    attributes: &mut Vec<RawAttribute>,
) -> Result<(), IoError> {
    let _name = words.next();
    let arrays: u64 = number(c, words.next(), "an array count")?;
    for _ in 0..arrays {
        c.binary = false;
        let l = c
            .line()?
            .ok_or_else(|| c.err("a field array header", "end of file"))?;
        c.binary = binary;
        let mut w = l.split_whitespace();
        let name = w.next().unwrap_or("").to_owned();
        let components: usize = number(c, w.next(), "a component count")?;
        let tuples: u64 = number(c, w.next(), "a tuple count")?;
        let t = data_type(c, w.next())?;
        if components == 0 || components > 64 {
            return Err(c.err("1 to 64 components", components.to_string()));
        }
        let values = c.values(tuples.saturating_mul(components as u64), t, &name)?;
        if point_count == Some(tuples) {
            attributes.push(RawAttribute {
                name,
                kind: t.kind,
                components,
                values,
            });
        }
    }
    Ok(())
}

/// Parses a whole legacy VTK file held in memory; `path` names it in errors.
pub fn parse(bytes: &[u8], path: &Path) -> Result<ParticleSet, IoError> {
    parse_with_polygons(bytes, path, None)
}

/// [`parse`], with the `POLYGONS` of a `POLYDATA` file appended to `polygons` when given (a
/// mesh read back, [`crate::mesh::Mesh::read`]).
pub fn parse_with_polygons(
    bytes: &[u8],
    path: &Path,
    mut polygons: Option<&mut super::Polygons>,
) -> Result<ParticleSet, IoError> {
    if !bytes.starts_with(b"# vtk DataFile") {
        return Err(IoError::WrongFormat {
            path: path.to_owned(),
            expected: "legacy VTK",
            found: super::describe(bytes),
        });
    }
    let mut c = Cursor {
        bytes,
        pos: 0,
        line: 0,
        binary: false,
        path,
    };
    let version = header(&mut c, path)?;
    let binary = c.binary;
    let mut positions: Option<Vec<glam::Vec3>> = None;
    let mut point_count: Option<u64> = None;
    let mut in_point_data = false;
    let mut data_count: Option<u64> = None;
    let mut attributes: Vec<RawAttribute> = Vec::new();

    loop {
        // keywords are read as text even in binary files
        c.binary = false;
        let Some(line) = c.line()? else { break };
        c.binary = binary;
        let mut words = line.split_whitespace();
        let keyword = words.next().unwrap_or("").to_ascii_uppercase();
        match keyword.as_str() {
            "DATASET" => match words.next().map(str::to_ascii_uppercase).as_deref() {
                Some("UNSTRUCTURED_GRID" | "POLYDATA") => {}
                Some(other) => {
                    return Err(IoError::unsupported(
                        path,
                        Location::Line(c.line),
                        format!(
                            "the dataset type {} (particles come as UNSTRUCTURED_GRID or POLYDATA)",
                            super::quoted(other)
                        ),
                    ));
                }
                None => return Err(c.err("a dataset type", "end of line")),
            },
            "POINTS" => {
                let n: u64 = number(&c, words.next(), "a point count")?;
                let t = data_type(&c, words.next())?;
                let start = c.pos;
                let line = c.line + 1;
                let coords = c.values(n.saturating_mul(3), t, "point coordinates")?;
                positions = Some(positions_from(path, &coords, |i| {
                    if binary {
                        Location::Byte((start + 3 * i * t.size) as u64)
                    } else {
                        Location::Line(line)
                    }
                })?);
                point_count = Some(n);
            }
            "CELLS" | "VERTICES" | "LINES" | "POLYGONS" | "TRIANGLE_STRIPS" => {
                let into = match (&mut polygons, point_count) {
                    (Some(p), Some(n)) if keyword == "POLYGONS" => Some((&mut **p, n)),
                    _ => None,
                };
                read_cells(&mut c, &mut words, version, binary, into)?;
            }
            "CELL_TYPES" => {
                let n: u64 = number(&c, words.next(), "a cell type count")?;
                c.values(n, vtk_type("int").expect("int is a VTK type"), "cell types")?;
            }
            "POINT_DATA" | "CELL_DATA" => {
                let n: u64 = number(&c, words.next(), "a data count")?;
                in_point_data = keyword == "POINT_DATA";
                data_count = Some(n);
                if in_point_data && Some(n) != point_count {
                    return Err(c.err(
                        format!("POINT_DATA {} (the POINTS count)", point_count.unwrap_or(0)),
                        super::quoted(line),
                    ));
                }
            }
            "SCALARS"
            | "VECTORS"
            | "NORMALS"
            | "TENSORS"
            | "TEXTURE_COORDINATES"
            | "COLOR_SCALARS" => {
                let name = words
                    .next()
                    .ok_or_else(|| c.err("an array name", "end of line"))?
                    .to_owned();
                let (components, t) = array_header(&c, &keyword, &mut words, binary)?;
                if components == 0 || components > 64 {
                    return Err(c.err("1 to 64 components", components.to_string()));
                }
                if keyword == "SCALARS" {
                    // optional in files written by some tools; required by the specification
                    let save = (c.pos, c.line);
                    c.binary = false;
                    let next = c.line()?;
                    c.binary = binary;
                    if !next.is_some_and(|l| l.to_ascii_uppercase().starts_with("LOOKUP_TABLE")) {
                        (c.pos, c.line) = save;
                    }
                }
                let Some(n) = data_count else {
                    return Err(c.err(
                        "POINT_DATA or CELL_DATA before an array",
                        super::quoted(line),
                    ));
                };
                let values = c.values(n.saturating_mul(components as u64), t, &name)?;
                if in_point_data {
                    attributes.push(RawAttribute {
                        name,
                        kind: t.kind,
                        components,
                        values,
                    });
                }
            }
            "LOOKUP_TABLE" => {
                skip_lookup_table(&mut c, &mut words, binary)?;
            }
            "FIELD" => {
                field_arrays(
                    &mut c,
                    &mut words,
                    binary,
                    in_point_data.then_some(point_count).flatten(),
                    &mut attributes,
                )?;
            }
            "METADATA" => {
                // a block of text ended by a blank line
                c.binary = false;
                while let Some(l) = c.raw_line()? {
                    if l.trim().is_empty() {
                        break;
                    }
                }
            }
            _ => {
                return Err(c.err(
                    "a VTK keyword (DATASET, POINTS, CELLS, POINT_DATA, SCALARS, FIELD...)",
                    super::quoted(line),
                ));
            }
        }
    }
    let positions = positions.ok_or_else(|| c.err("a POINTS block", "end of file"))?;
    Ok(assemble(positions, attributes))
}

fn type_name(kind: ScalarKind) -> &'static str {
    match kind {
        ScalarKind::I8 => "char",
        ScalarKind::U8 => "unsigned_char",
        ScalarKind::I16 => "short",
        ScalarKind::U16 => "unsigned_short",
        ScalarKind::I32 => "int",
        ScalarKind::U32 => "unsigned_int",
        ScalarKind::F32 => "float",
        ScalarKind::F64 => "double",
    }
}

/// Serialises a particle set as a legacy VTK 4.2 BINARY unstructured grid of vertex cells, every
/// attribute in one `FIELD` block (as SPlisHSPlasH writes it).
#[must_use]
pub fn to_bytes(set: &ParticleSet) -> Vec<u8> {
    let n = set.len();
    let mut out = Vec::with_capacity(n * 40 + 256);
    out.extend_from_slice(
        format!(
            "# vtk DataFile Version 4.2\nparticles written by fluid-surfels {}\nBINARY\nDATASET UNSTRUCTURED_GRID\nPOINTS {n} float\n",
            env!("CARGO_PKG_VERSION")
        )
        .as_bytes(),
    );
    for p in &set.positions {
        for v in p.to_array() {
            out.extend_from_slice(&v.to_be_bytes());
        }
    }
    out.extend_from_slice(format!("\nCELLS {n} {}\n", 2 * n).as_bytes());
    for i in 0..n as i32 {
        out.extend_from_slice(&1i32.to_be_bytes());
        out.extend_from_slice(&i.to_be_bytes());
    }
    out.extend_from_slice(format!("\nCELL_TYPES {n}\n").as_bytes());
    for _ in 0..n {
        out.extend_from_slice(&1i32.to_be_bytes()); // VTK_VERTEX
    }
    out.push(b'\n');
    let arrays = named_arrays(set);
    if !arrays.is_empty() {
        out.extend_from_slice(
            format!("POINT_DATA {n}\nFIELD FieldData {}\n", arrays.len()).as_bytes(),
        );
        for a in arrays {
            let name: String = a
                .name
                .chars()
                .map(|ch| if ch.is_whitespace() { '_' } else { ch })
                .collect();
            out.extend_from_slice(
                format!("{name} {} {n} {}\n", a.components, type_name(a.kind)).as_bytes(),
            );
            for &v in &a.values {
                push_value(&mut out, a.kind, v, true);
            }
            out.push(b'\n');
        }
    }
    out
}
