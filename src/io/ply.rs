//! PLY particle files (Turk's polygon file format): ASCII, binary little-endian and binary
//! big-endian.
//!
//! The `vertex` element becomes the particle set: `x y z` positions (required), `nx ny nz`
//! normals, `vx vy vz` velocities, `mass`, an integer `id`, `red green blue` 8-bit colours; every
//! other vertex property is kept as an [`Attribute`] with its PLY type and written back with it.
//! Other elements (faces of a mesh) are read past and dropped. Recognised properties are written
//! with fixed types (`float`, `uint` for `id`, `uchar` for colours).

use std::path::Path;

use glam::Vec3;

use super::{IoError, Location, write_atomically};
use crate::particles::{Attribute, ParticleSet, ScalarKind};

/// Data encoding of a PLY file.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Encoding {
    /// Text.
    Ascii,
    /// Binary, little-endian (the common one).
    BinaryLittleEndian,
    /// Binary, big-endian.
    BinaryBigEndian,
}

#[derive(Clone, Copy, Debug)]
enum PropType {
    Scalar(ScalarKind),
    List { count: ScalarKind, item: ScalarKind },
}

#[derive(Debug)]
struct Element {
    name: String,
    count: u64,
    props: Vec<(String, PropType)>,
}

fn kind_from_name(s: &str) -> Option<ScalarKind> {
    Some(match s {
        "char" | "int8" => ScalarKind::I8,
        "uchar" | "uint8" => ScalarKind::U8,
        "short" | "int16" => ScalarKind::I16,
        "ushort" | "uint16" => ScalarKind::U16,
        "int" | "int32" => ScalarKind::I32,
        "uint" | "uint32" => ScalarKind::U32,
        "float" | "float32" => ScalarKind::F32,
        "double" | "float64" => ScalarKind::F64,
        _ => return None,
    })
}

fn kind_name(k: ScalarKind) -> &'static str {
    match k {
        ScalarKind::I8 => "char",
        ScalarKind::U8 => "uchar",
        ScalarKind::I16 => "short",
        ScalarKind::U16 => "ushort",
        ScalarKind::I32 => "int",
        ScalarKind::U32 => "uint",
        ScalarKind::F32 => "float",
        ScalarKind::F64 => "double",
    }
}

/// Largest count a list may declare before it is refused (a real particle file has none this long).
const MAX_LIST_LEN: f64 = 1e6;

struct Header {
    encoding: Encoding,
    elements: Vec<Element>,
    data_start: usize,
    /// line number of the first data line (ASCII)
    data_line: usize,
}

fn parse_header(bytes: &[u8], path: &Path) -> Result<Header, IoError> {
    let err = |line: usize, expected: &str, found: &str| {
        IoError::parse(path, Location::Line(line), expected, found)
    };
    let mut pos = 0;
    let mut line_no = 0;
    let mut encoding = None;
    let mut elements: Vec<Element> = Vec::new();
    loop {
        line_no += 1;
        let Some(len) = bytes[pos..].iter().position(|&b| b == b'\n') else {
            return Err(err(
                line_no,
                "a header ending in `end_header`",
                "end of file",
            ));
        };
        let raw = &bytes[pos..pos + len];
        pos += len + 1;
        let text = std::str::from_utf8(raw)
            .map_err(|_| err(line_no, "a text header line", "non-text bytes"))?
            .trim_end_matches('\r')
            .trim();
        let words: Vec<&str> = text.split_whitespace().collect();
        if line_no == 1 {
            if text != "ply" {
                return Err(err(1, "the magic line `ply`", &truncate(text)));
            }
            continue;
        }
        match words.first().copied() {
            Some("format") => {
                let enc = match words.get(1).copied() {
                    Some("ascii") => Encoding::Ascii,
                    Some("binary_little_endian") => Encoding::BinaryLittleEndian,
                    Some("binary_big_endian") => Encoding::BinaryBigEndian,
                    _ => {
                        return Err(err(
                            line_no,
                            "format ascii|binary_little_endian|binary_big_endian",
                            text,
                        ));
                    }
                };
                if words.get(2).copied() != Some("1.0") {
                    return Err(err(line_no, "PLY version 1.0", text));
                }
                encoding = Some(enc);
            }
            Some("comment" | "obj_info") | None => {}
            Some("element") => {
                let (Some(name), Some(count), None) = (words.get(1), words.get(2), words.get(3))
                else {
                    return Err(err(line_no, "`element <name> <count>`", text));
                };
                let count = count
                    .parse::<u64>()
                    .map_err(|_| err(line_no, "a non-negative element count", count))?;
                elements.push(Element {
                    name: (*name).to_owned(),
                    count,
                    props: Vec::new(),
                });
            }
            Some("property") => {
                let Some(element) = elements.last_mut() else {
                    return Err(err(
                        line_no,
                        "an `element` line before the first property",
                        text,
                    ));
                };
                let prop = match words[1..] {
                    ["list", c, i, name] => match (kind_from_name(c), kind_from_name(i)) {
                        (Some(count), Some(item)) if count.is_integer() => {
                            (name, PropType::List { count, item })
                        }
                        _ => {
                            return Err(err(
                                line_no,
                                "`property list <integer type> <type> <name>`",
                                text,
                            ));
                        }
                    },
                    [t, name] => match kind_from_name(t) {
                        Some(k) => (name, PropType::Scalar(k)),
                        None => {
                            return Err(err(
                                line_no,
                                "a PLY scalar type (char, uchar, short, ushort, int, uint, float, double)",
                                t,
                            ));
                        }
                    },
                    _ => return Err(err(line_no, "`property <type> <name>`", text)),
                };
                if element.props.iter().any(|(n, _)| n == prop.0) {
                    return Err(err(
                        line_no,
                        "a property name not used before in the element",
                        prop.0,
                    ));
                }
                element.props.push((prop.0.to_owned(), prop.1));
            }
            Some("end_header") => break,
            Some(other) => {
                return Err(err(
                    line_no,
                    "a header keyword (format, comment, element, property, end_header)",
                    other,
                ));
            }
        }
    }
    let encoding = encoding.ok_or_else(|| err(2, "a `format` line", "none before end_header"))?;
    Ok(Header {
        encoding,
        elements,
        data_start: pos,
        data_line: line_no + 1,
    })
}

fn truncate(s: &str) -> String {
    super::quoted(s)
}

/// Reads values one by one from the data section, in either encoding.
enum Reader<'a> {
    Binary {
        bytes: &'a [u8],
        pos: usize,
        little: bool,
    },
    Ascii {
        bytes: &'a [u8],
        pos: usize,
        line: usize,
    },
}

impl Reader<'_> {
    fn location(&self) -> Location {
        match self {
            Self::Binary { pos, .. } => Location::Byte(*pos as u64),
            Self::Ascii { line, .. } => Location::Line(*line),
        }
    }

    fn remaining(&self) -> usize {
        match self {
            Self::Binary { bytes, pos, .. } | Self::Ascii { bytes, pos, .. } => bytes.len() - pos,
        }
    }

    /// Reads one value of type `kind`; returns it and the location where it started.
    fn next(&mut self, kind: ScalarKind, path: &Path) -> Result<(f64, Location), IoError> {
        match self {
            Self::Binary { bytes, pos, little } => {
                let at = Location::Byte(*pos as u64);
                let size = kind.size();
                let Some(raw) = bytes.get(*pos..*pos + size) else {
                    return Err(IoError::parse(
                        path,
                        at,
                        format!("a {} value ({size} bytes)", kind_name(kind)),
                        "end of file",
                    ));
                };
                *pos += size;
                let v = super::read_value(raw, kind, !*little);
                Ok((v, at))
            }
            Self::Ascii { .. } => {
                self.skip_whitespace();
                let Self::Ascii { bytes, pos, line } = self else {
                    unreachable!()
                };
                let at = Location::Line(*line);
                let start = *pos;
                while bytes.get(*pos).is_some_and(|c| !c.is_ascii_whitespace()) {
                    *pos += 1;
                }
                if start == *pos {
                    return Err(IoError::parse(
                        path,
                        at,
                        format!("a {} value", kind_name(kind)),
                        "end of file",
                    ));
                }
                let token = String::from_utf8_lossy(&bytes[start..*pos]);
                let v: f64 = token.parse().map_err(|_| {
                    IoError::parse(
                        path,
                        at,
                        format!("a {} value", kind_name(kind)),
                        truncate(&token),
                    )
                })?;
                // a `float` property holds f32 values: round the decimal as an f32 reader would
                let v = if kind == ScalarKind::F32 {
                    v as f32 as f64
                } else {
                    v
                };
                let fits = !kind.is_integer()
                    || (v.fract() == 0.0 && v >= int_min(kind) && v <= int_max(kind));
                if !fits {
                    return Err(IoError::parse(
                        path,
                        at,
                        format!("a {} value", kind_name(kind)),
                        truncate(&token),
                    ));
                }
                Ok((v, at))
            }
        }
    }

    /// Moves past whitespace (counting lines), so that `location` names the next value.
    fn skip_whitespace(&mut self) {
        if let Self::Ascii { bytes, pos, line } = self {
            while let Some(&c) = bytes.get(*pos) {
                if !c.is_ascii_whitespace() {
                    break;
                }
                if c == b'\n' {
                    *line += 1;
                }
                *pos += 1;
            }
        }
    }

    /// True when nothing but whitespace remains.
    fn at_end(&self) -> bool {
        match self {
            Self::Binary { bytes, pos, .. } => *pos == bytes.len(),
            Self::Ascii { bytes, pos, .. } => bytes[*pos..].iter().all(u8::is_ascii_whitespace),
        }
    }
}

fn int_min(k: ScalarKind) -> f64 {
    match k {
        ScalarKind::I8 => i8::MIN as f64,
        ScalarKind::I16 => i16::MIN as f64,
        ScalarKind::I32 => i32::MIN as f64,
        _ => 0.0,
    }
}

fn int_max(k: ScalarKind) -> f64 {
    match k {
        ScalarKind::I8 => i8::MAX as f64,
        ScalarKind::U8 => u8::MAX as f64,
        ScalarKind::I16 => i16::MAX as f64,
        ScalarKind::U16 => u16::MAX as f64,
        ScalarKind::I32 => i32::MAX as f64,
        ScalarKind::U32 => u32::MAX as f64,
        _ => f64::INFINITY,
    }
}

/// Parses a whole PLY file held in memory; `path` names it in errors.
pub fn parse(bytes: &[u8], path: &Path) -> Result<ParticleSet, IoError> {
    parse_with_faces(bytes, path, None)
}

/// [`parse`], with the `face` element's `vertex_indices` (or `vertex_index`) lists appended
/// to `faces` when given (a mesh read back, [`crate::mesh::Mesh::read`]); each index is checked
/// against the vertex count.
pub fn parse_with_faces(
    bytes: &[u8],
    path: &Path,
    mut faces: Option<&mut super::Polygons>,
) -> Result<ParticleSet, IoError> {
    if !looks_like(bytes) {
        return Err(IoError::WrongFormat {
            path: path.to_owned(),
            expected: "PLY",
            found: super::describe(bytes),
        });
    }
    let header = parse_header(bytes, path)?;
    let hdr_err =
        |expected: &str, found: &str| IoError::parse(path, Location::Line(2), expected, found);
    let Some(vertex_index) = header.elements.iter().position(|e| e.name == "vertex") else {
        return Err(hdr_err("an `element vertex` in the header", "none"));
    };
    let data = &bytes[header.data_start..];
    let mut reader = match header.encoding {
        Encoding::Ascii => Reader::Ascii {
            bytes,
            pos: header.data_start,
            line: header.data_line,
        },
        Encoding::BinaryLittleEndian | Encoding::BinaryBigEndian => Reader::Binary {
            bytes,
            pos: header.data_start,
            little: header.encoding == Encoding::BinaryLittleEndian,
        },
    };
    // Refuse counts the file cannot hold before allocating anything for them: a binary record
    // needs at least the sizes of its scalars and list counts, an ASCII one two bytes a value.
    let mut min_bytes: u128 = 0;
    for e in &header.elements {
        let per: u128 = e
            .props
            .iter()
            .map(|(_, t)| match (header.encoding, t) {
                (Encoding::Ascii, _) => 2,
                (_, PropType::Scalar(k)) => k.size() as u128,
                (_, PropType::List { count, .. }) => count.size() as u128,
            })
            .sum();
        min_bytes += per * e.count as u128;
    }
    if min_bytes > data.len() as u128 + 1 {
        return Err(IoError::parse(
            path,
            Location::Byte(header.data_start as u64),
            format!("data for the header's element counts (at least {min_bytes} bytes)"),
            format!(
                "{} bytes after the header (wrong counts or truncated file)",
                data.len()
            ),
        ));
    }

    let vertex = &header.elements[vertex_index];
    for (name, t) in &vertex.props {
        if matches!(t, PropType::List { .. }) {
            return Err(hdr_err(
                "scalar vertex properties",
                &format!("list property `{name}`"),
            ));
        }
    }
    let find = |n: &str| vertex.props.iter().position(|(p, _)| p == n);
    let (Some(ix), Some(iy), Some(iz)) = (find("x"), find("y"), find("z")) else {
        return Err(hdr_err("vertex properties x, y and z", "some missing"));
    };
    let n = vertex.count as usize;
    let mut columns: Vec<Vec<f64>> = vertex.props.iter().map(|_| Vec::with_capacity(n)).collect();
    // the face element's list of vertex indices, when faces are wanted
    let face_list = faces.as_ref().and(
        header
            .elements
            .iter()
            .position(|e| e.name == "face")
            .and_then(|e| {
                header.elements[e]
                    .props
                    .iter()
                    .position(|(p, _)| p == "vertex_indices" || p == "vertex_index")
                    .map(|p| (e, p))
            }),
    );

    for (e_index, element) in header.elements.iter().enumerate() {
        for record in 0..element.count as usize {
            for (p_index, (_, t)) in element.props.iter().enumerate() {
                match *t {
                    PropType::Scalar(kind) => {
                        let (v, at) = reader.next(kind, path)?;
                        if e_index == vertex_index {
                            if (p_index == ix || p_index == iy || p_index == iz)
                                && !(v as f32).is_finite()
                            {
                                return Err(IoError::NonFinite {
                                    path: path.to_owned(),
                                    location: at,
                                    index: record,
                                    value: format!("{v:e}"),
                                });
                            }
                            columns[p_index].push(v);
                        }
                    }
                    PropType::List { count, item } => {
                        let (len, at) = reader.next(count, path)?;
                        let min_item = if header.encoding == Encoding::Ascii {
                            1.0
                        } else {
                            item.size() as f64
                        };
                        if !(0.0..=MAX_LIST_LEN).contains(&len)
                            || len * min_item > reader.remaining() as f64 + 1.0
                        {
                            return Err(IoError::parse(
                                path,
                                at,
                                "a list length the file can hold",
                                len.to_string(),
                            ));
                        }
                        let wanted = face_list == Some((e_index, p_index));
                        if wanted && let Some(f) = faces.as_deref_mut() {
                            f.counts.push(len as u32);
                        }
                        for _ in 0..len as usize {
                            let (v, at) = reader.next(item, path)?;
                            if wanted && let Some(f) = faces.as_deref_mut() {
                                if !(v >= 0.0 && v < n as f64) {
                                    return Err(IoError::parse(
                                        path,
                                        at,
                                        format!("a vertex index below {n}"),
                                        v.to_string(),
                                    ));
                                }
                                f.indices.push(v as u32);
                            }
                        }
                    }
                }
            }
        }
    }
    reader.skip_whitespace();
    if !reader.at_end() {
        return Err(IoError::parse(
            path,
            reader.location(),
            "end of file after the elements the header declares",
            "more data (wrong counts)",
        ));
    }
    Ok(assemble(vertex, columns, n))
}

/// Turns vertex columns into a particle set, recognising the crate's own attributes.
fn assemble(vertex: &Element, mut columns: Vec<Vec<f64>>, n: usize) -> ParticleSet {
    let names: Vec<&str> = vertex.props.iter().map(|(name, _)| name.as_str()).collect();
    let kinds: Vec<ScalarKind> = vertex
        .props
        .iter()
        .map(|(_, t)| match t {
            PropType::Scalar(k) => *k,
            PropType::List { item, .. } => *item,
        })
        .collect();
    let mut taken = vec![false; names.len()];
    let mut take3 =
        |a: &str, b: &str, c: &str, cols: &[Vec<f64>], accept: &dyn Fn(ScalarKind) -> bool| {
            let idx = [a, b, c].map(|name| names.iter().position(|&n| n == name));
            match idx {
                [Some(i), Some(j), Some(k)]
                    if accept(kinds[i]) && accept(kinds[j]) && accept(kinds[k]) =>
                {
                    taken[i] = true;
                    taken[j] = true;
                    taken[k] = true;
                    Some(
                        (0..n)
                            .map(|r| [cols[i][r], cols[j][r], cols[k][r]])
                            .collect::<Vec<_>>(),
                    )
                }
                _ => None,
            }
        };
    let any = |_: ScalarKind| true;
    let to_vec3 = |v: Vec<[f64; 3]>| {
        v.into_iter()
            .map(|a| Vec3::new(a[0] as f32, a[1] as f32, a[2] as f32))
            .collect::<Vec<_>>()
    };
    let positions = to_vec3(take3("x", "y", "z", &columns, &any).unwrap_or_default());
    let normals = take3("nx", "ny", "nz", &columns, &any).map(to_vec3);
    let velocities = take3("vx", "vy", "vz", &columns, &any).map(to_vec3);
    let colours = take3("red", "green", "blue", &columns, &|k| k == ScalarKind::U8)
        .map(|v| v.into_iter().map(|a| a.map(|c| c as u8)).collect());
    let mut single = |name: &str, accept: &dyn Fn(ScalarKind, &[f64]) -> bool| {
        let i = names.iter().position(|&n| n == name)?;
        if !accept(kinds[i], &columns[i]) {
            return None;
        }
        taken[i] = true;
        Some(i)
    };
    let masses =
        single("mass", &|_, _| true).map(|i| columns[i].iter().map(|&m| m as f32).collect());
    let ids = single("id", &|k, v| {
        k.is_integer() && v.iter().all(|&x| (0.0..=u32::MAX as f64).contains(&x))
    })
    .map(|i| columns[i].iter().map(|&x| x as u32).collect());
    let extra = (0..names.len())
        .filter(|&i| !taken[i])
        .map(|i| Attribute::scalar(names[i], kinds[i], std::mem::take(&mut columns[i])))
        .collect();
    ParticleSet {
        positions,
        ids,
        masses,
        velocities,
        normals,
        colours,
        extra,
    }
}

/// Serialises a particle set as PLY.
#[must_use]
pub fn to_bytes(set: &ParticleSet, encoding: Encoding) -> Vec<u8> {
    type Getter<'a> = Box<dyn Fn(usize) -> f64 + 'a>;
    let mut cols: Vec<(String, ScalarKind, Getter<'_>)> = Vec::new();
    let vectors = [
        (["x", "y", "z"], Some(&set.positions)),
        (["nx", "ny", "nz"], set.normals.as_ref()),
        (["vx", "vy", "vz"], set.velocities.as_ref()),
    ];
    for (names, data) in vectors {
        if let Some(d) = data {
            for (axis, name) in names.into_iter().enumerate() {
                cols.push((
                    name.to_owned(),
                    ScalarKind::F32,
                    Box::new(move |i| d[i][axis] as f64),
                ));
            }
        }
    }
    if let Some(m) = &set.masses {
        cols.push((
            "mass".into(),
            ScalarKind::F32,
            Box::new(move |i| m[i] as f64),
        ));
    }
    if let Some(ids) = &set.ids {
        cols.push((
            "id".into(),
            ScalarKind::U32,
            Box::new(move |i| ids[i] as f64),
        ));
    }
    if let Some(c) = &set.colours {
        for (channel, name) in ["red", "green", "blue"].into_iter().enumerate() {
            cols.push((
                name.into(),
                ScalarKind::U8,
                Box::new(move |i| c[i][channel] as f64),
            ));
        }
    }
    for a in &set.extra {
        for (c, name) in super::component_names(a).into_iter().enumerate() {
            let k = a.components;
            cols.push((name, a.kind, Box::new(move |i| a.values[i * k + c])));
        }
    }

    let format = match encoding {
        Encoding::Ascii => "ascii",
        Encoding::BinaryLittleEndian => "binary_little_endian",
        Encoding::BinaryBigEndian => "binary_big_endian",
    };
    let mut out = format!(
        "ply\nformat {format} 1.0\ncomment written by fluid-surfels {}\nelement vertex {}\n",
        env!("CARGO_PKG_VERSION"),
        set.len()
    );
    for (name, kind, _) in &cols {
        out.push_str(&format!("property {} {name}\n", kind_name(*kind)));
    }
    out.push_str("end_header\n");
    let mut bytes = out.into_bytes();
    let record: usize = cols.iter().map(|c| c.1.size()).sum();
    bytes.reserve(
        set.len()
            * if encoding == Encoding::Ascii {
                12 * cols.len()
            } else {
                record
            },
    );
    for i in 0..set.len() {
        for (c, (_, kind, get)) in cols.iter().enumerate() {
            let v = get(i);
            match encoding {
                Encoding::Ascii => {
                    if c > 0 {
                        bytes.push(b' ');
                    }
                    let text = match kind {
                        ScalarKind::F32 => format!("{}", v as f32),
                        ScalarKind::F64 => format!("{v}"),
                        _ => format!("{}", v as i64),
                    };
                    bytes.extend_from_slice(text.as_bytes());
                }
                Encoding::BinaryLittleEndian | Encoding::BinaryBigEndian => {
                    super::push_value(&mut bytes, *kind, v, encoding == Encoding::BinaryBigEndian);
                }
            }
        }
        if encoding == Encoding::Ascii {
            bytes.push(b'\n');
        }
    }
    bytes
}

/// Writes a particle set as PLY (atomically: a temporary file renamed into place).
pub fn write(path: &Path, set: &ParticleSet, encoding: Encoding) -> Result<(), IoError> {
    set.validate().map_err(|source| IoError::InvalidSet {
        path: path.to_owned(),
        source,
    })?;
    write_atomically(path, &to_bytes(set, encoding))
}

/// True when `bytes` start like a PLY file.
pub(crate) fn looks_like(bytes: &[u8]) -> bool {
    bytes.starts_with(b"ply")
}
