//! VTK XML particle files: `UnstructuredGrid` (`.vtu`) and `PolyData` (`.vtp`).
//!
//! Every `DataArray` encoding is read: `ascii`, inline `binary` (base64) and `appended` data,
//! both `raw` (which splashsurf cannot read) and `base64`; little- or big-endian, `UInt32` or
//! `UInt64` headers, uncompressed or `vtkZLibDataCompressor`. Points come from `<Points>`, named
//! arrays from `<PointData>`; several pieces are concatenated. Cells are read past.
//!
//! Written files are unstructured grids of vertex cells with raw appended data (the compact and
//! fast choice), or base64 or ascii inline data on request ([`Encoding`]).

use std::collections::HashMap;
use std::path::Path;

use base64::Engine as _;
use base64::engine::general_purpose::STANDARD as BASE64;
use glam::Vec3;
use quick_xml::events::{BytesStart, Event};

use super::{
    IoError, Location, RawAttribute, ReadOptions, assemble, check_allocation, check_budget,
    named_arrays, positions_from, push_value, read_value,
};
use crate::particles::{ParticleSet, ScalarKind};

/// How a written file stores its arrays.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Encoding {
    /// Numbers as text.
    Ascii,
    /// Inline base64 binary.
    Base64,
    /// Raw binary after the XML (`<AppendedData encoding="raw">`).
    RawAppended,
}

#[derive(Clone, Copy, Debug)]
struct ArrayType {
    kind: ScalarKind,
    size: usize,
    /// 64-bit integers, read into f64
    int64: Option<bool>,
}

fn array_type(name: &str) -> Option<ArrayType> {
    let t = |kind: ScalarKind| ArrayType {
        kind,
        size: kind.size(),
        int64: None,
    };
    Some(match name {
        "Int8" | "Char" => t(ScalarKind::I8),
        "UInt8" | "UChar" => t(ScalarKind::U8),
        "Int16" => t(ScalarKind::I16),
        "UInt16" => t(ScalarKind::U16),
        "Int32" => t(ScalarKind::I32),
        "UInt32" => t(ScalarKind::U32),
        "Float32" => t(ScalarKind::F32),
        "Float64" => t(ScalarKind::F64),
        "Int64" => ArrayType {
            kind: ScalarKind::F64,
            size: 8,
            int64: Some(true),
        },
        "UInt64" => ArrayType {
            kind: ScalarKind::F64,
            size: 8,
            int64: Some(false),
        },
        _ => return None,
    })
}

fn type_name(kind: ScalarKind) -> &'static str {
    match kind {
        ScalarKind::I8 => "Int8",
        ScalarKind::U8 => "UInt8",
        ScalarKind::I16 => "Int16",
        ScalarKind::U16 => "UInt16",
        ScalarKind::I32 => "Int32",
        ScalarKind::U32 => "UInt32",
        ScalarKind::F32 => "Float32",
        ScalarKind::F64 => "Float64",
    }
}

/// Where an array is: its section, attributes and inline text.
#[derive(Debug)]
struct ArrayRef {
    section: Section,
    name: String,
    ty: ArrayType,
    components: usize,
    format: String,
    offset: Option<usize>,
    text: String,
    /// byte offset of the `<DataArray` tag, for errors
    at: u64,
    piece: usize,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Section {
    Points,
    PointData,
    Other,
}

struct FileInfo {
    big_endian: bool,
    header_size: usize,
    compressed: bool,
    pieces: Vec<u64>,
}

fn attr(e: &BytesStart<'_>, key: &str) -> Option<String> {
    e.attributes()
        .flatten()
        .find(|a| a.key.as_ref() == key)
        .map(|a| a.value.into_owned())
}

/// Parses a whole VTK XML file held in memory; `path` names it in errors.
pub fn parse(bytes: &[u8], path: &Path) -> Result<ParticleSet, IoError> {
    parse_with(bytes, path, &ReadOptions::default())
}

/// [`parse`] within a memory budget for decompression.
pub fn parse_with(
    bytes: &[u8],
    path: &Path,
    options: &ReadOptions,
) -> Result<ParticleSet, IoError> {
    let start = bytes
        .iter()
        .position(|b| !b.is_ascii_whitespace())
        .unwrap_or(0);
    if !(bytes[start..].starts_with(b"<?xml") || bytes[start..].starts_with(b"<VTKFile")) {
        return Err(IoError::WrongFormat {
            path: path.to_owned(),
            expected: "VTK XML",
            found: super::describe(bytes),
        });
    }
    // Raw appended data is not XML: parse only the text before it, and slice the data by hand.
    let appended_tag = find(bytes, b"<AppendedData");
    let (xml, appended) = match appended_tag {
        Some(tag) => {
            let open_end = find(&bytes[tag..], b">")
                .map(|k| tag + k + 1)
                .ok_or_else(|| {
                    IoError::parse(
                        path,
                        Location::Byte(tag as u64),
                        "`>` closing <AppendedData",
                        "end of file",
                    )
                })?;
            let tag_text = String::from_utf8_lossy(&bytes[tag..open_end]);
            let raw = tag_text.contains("\"raw\"");
            let underscore = bytes[open_end..]
                .iter()
                .position(|&b| b == b'_')
                .map(|k| open_end + k + 1)
                .ok_or_else(|| {
                    IoError::parse(
                        path,
                        Location::Byte(open_end as u64),
                        "`_` starting the appended data",
                        "end of file",
                    )
                })?;
            let end = rfind(bytes, b"</AppendedData>")
                .filter(|&e| e >= underscore)
                .ok_or_else(|| {
                    IoError::parse(
                        path,
                        Location::Byte(bytes.len() as u64),
                        "`</AppendedData>` after the appended data",
                        "end of file (truncated file)",
                    )
                })?;
            if find(&bytes[end..], b"</VTKFile>").is_none() {
                return Err(IoError::parse(
                    path,
                    Location::Byte(bytes.len() as u64),
                    "`</VTKFile>` closing the file",
                    "end of file (truncated file)",
                ));
            }
            let data = &bytes[underscore..end];
            (&bytes[..tag], Some((raw, data, underscore)))
        }
        None => (bytes, None),
    };
    let xml = std::str::from_utf8(xml).map_err(|e| {
        IoError::parse(
            path,
            Location::Byte(e.valid_up_to() as u64),
            "UTF-8 XML text",
            "invalid bytes",
        )
    })?;
    let (info, arrays) = scan(xml, path, appended.is_some())?;

    let points_total: u128 = info.pieces.iter().map(|&p| p as u128).sum();
    // a point takes at least 12 bytes of data, which zlib can shrink by at most its ratio
    if points_total * 12 > bytes.len() as u128 * super::DEFLATE_MAX_RATIO {
        return Err(IoError::parse(
            path,
            Location::Byte(0),
            format!(
                "a NumberOfPoints that a file of {} bytes can hold",
                bytes.len()
            ),
            points_total.to_string(),
        ));
    }
    check_allocation(path, Location::Byte(0), points_total * 48)?;
    let mut coords: Vec<f64> = Vec::new();
    let mut named: Vec<RawAttribute> = Vec::new();
    let mut by_name: HashMap<String, usize> = HashMap::new();
    let mut piece_of_coords = Vec::new();
    for a in &arrays {
        let n = info.pieces.get(a.piece).copied().unwrap_or(0) as usize;
        match a.section {
            Section::Points => {
                if a.components != 3 {
                    return Err(IoError::parse(
                        path,
                        Location::Byte(a.at),
                        "3 components for Points",
                        a.components.to_string(),
                    ));
                }
                let values = decode(a, n * 3, &info, appended, path, options)?;
                piece_of_coords.push(a.piece);
                coords.extend(values);
            }
            Section::PointData => {
                let values = decode(a, n * a.components, &info, appended, path, options)?;
                match by_name.get(&a.name) {
                    Some(&k) if named[k].components == a.components => {
                        named[k].values.extend(values)
                    }
                    Some(_) => {
                        return Err(IoError::parse(
                            path,
                            Location::Byte(a.at),
                            format!("array `{}` with the same components in every piece", a.name),
                            a.components.to_string(),
                        ));
                    }
                    None => {
                        by_name.insert(a.name.clone(), named.len());
                        named.push(RawAttribute {
                            name: a.name.clone(),
                            kind: a.ty.kind,
                            components: a.components,
                            values,
                        });
                    }
                }
            }
            Section::Other => {}
        }
    }
    if piece_of_coords.len() != info.pieces.len() {
        return Err(IoError::parse(
            path,
            Location::Byte(0),
            format!(
                "a <Points> array in each of the {} pieces",
                info.pieces.len()
            ),
            format!("{}", piece_of_coords.len()),
        ));
    }
    let total = (coords.len() / 3) as u128;
    named.retain(|a| a.values.len() as u128 == total * a.components as u128);
    let positions = positions_from(path, &coords, |_| Location::Byte(0))?;
    Ok(assemble(positions, named))
}

fn find(hay: &[u8], needle: &[u8]) -> Option<usize> {
    hay.windows(needle.len()).position(|w| w == needle)
}

fn rfind(hay: &[u8], needle: &[u8]) -> Option<usize> {
    hay.windows(needle.len()).rposition(|w| w == needle)
}

/// The `<VTKFile>` element's settings: its type (unstructured grid or poly data), byte order,
/// header size and compressor.
fn root_settings(
    e: &BytesStart<'_>,
    path: &Path,
    at: u64,
    info: &mut FileInfo,
) -> Result<(), IoError> {
    let kind = attr(e, "type").unwrap_or_default();
    if kind != "UnstructuredGrid" && kind != "PolyData" {
        return Err(IoError::unsupported(
            path,
            Location::Byte(at),
            format!(
                "VTK XML type {} (particles come as UnstructuredGrid or PolyData)",
                super::quoted(&kind)
            ),
        ));
    }
    info.big_endian = attr(e, "byte_order").as_deref() == Some("BigEndian");
    info.header_size = match attr(e, "header_type").as_deref() {
        None | Some("UInt32") => 4,
        Some("UInt64") => 8,
        Some(other) => {
            return Err(IoError::unsupported(
                path,
                Location::Byte(at),
                format!("header type {}", super::quoted(other)),
            ));
        }
    };
    match attr(e, "compressor").as_deref() {
        None | Some("") => {}
        Some("vtkZLibDataCompressor") => info.compressed = true,
        Some(other) => {
            return Err(IoError::unsupported(
                path,
                Location::Byte(at),
                format!("the compressor {} (only zlib)", super::quoted(other)),
            ));
        }
    }
    Ok(())
}

/// A `<DataArray>` element of `section` in piece `piece`: its type, components, name, format
/// and offset (its text follows).
fn data_array(
    e: &BytesStart<'_>,
    path: &Path,
    at: u64,
    section: Section,
    piece: usize,
) -> Result<ArrayRef, IoError> {
    let ty_name = attr(e, "type").unwrap_or_default();
    let ty = array_type(&ty_name).ok_or_else(|| {
        IoError::unsupported(
            path,
            Location::Byte(at),
            format!("DataArray type {}", super::quoted(&ty_name)),
        )
    })?;
    let components = attr(e, "NumberOfComponents")
        .map_or(Ok(1), |c| c.parse::<usize>())
        .map_err(|_| IoError::parse(path, Location::Byte(at), "a component count", "text"))?;
    if components == 0 || components > 64 {
        return Err(IoError::parse(
            path,
            Location::Byte(at),
            "1 to 64 components",
            components.to_string(),
        ));
    }
    Ok(ArrayRef {
        section,
        name: attr(e, "Name").unwrap_or_default(),
        ty,
        components,
        format: attr(e, "format").unwrap_or_else(|| "ascii".into()),
        offset: attr(e, "offset").and_then(|o| o.trim().parse().ok()),
        text: String::new(),
        at,
        piece,
    })
}

/// Walks the XML, collecting the file's settings, the pieces' point counts and every array.
fn scan(
    xml: &str,
    path: &Path,
    appended_follows: bool,
) -> Result<(FileInfo, Vec<ArrayRef>), IoError> {
    let mut reader = quick_xml::Reader::from_str(xml);
    let mut info = FileInfo {
        big_endian: false,
        header_size: 4,
        compressed: false,
        pieces: Vec::new(),
    };
    let mut arrays: Vec<ArrayRef> = Vec::new();
    let mut section = Section::Other;
    let mut open_array: Option<ArrayRef> = None;
    let mut saw_root = false;
    let mut closed_root = false;
    loop {
        let at = reader.buffer_position();
        let event = reader.read_event().map_err(|e| {
            IoError::parse(
                path,
                Location::Byte(reader.error_position()),
                "well-formed XML",
                e.to_string(),
            )
        })?;
        let empty = matches!(event, Event::Empty(_));
        match event {
            Event::Start(e) | Event::Empty(e) => match e.name().as_ref() {
                "VTKFile" => {
                    saw_root = true;
                    root_settings(&e, path, at, &mut info)?;
                }
                "Piece" => {
                    let n = attr(&e, "NumberOfPoints").unwrap_or_default();
                    let n: u64 = n.parse().map_err(|_| {
                        IoError::parse(
                            path,
                            Location::Byte(at),
                            "NumberOfPoints=\"<count>\"",
                            super::quoted(&n),
                        )
                    })?;
                    info.pieces.push(n);
                }
                "Points" => section = Section::Points,
                "PointData" => section = Section::PointData,
                "CellData" | "Cells" | "Verts" | "Lines" | "Polys" | "Strips" | "FieldData" => {
                    section = Section::Other
                }
                "DataArray" => {
                    let array =
                        data_array(&e, path, at, section, info.pieces.len().saturating_sub(1))?;
                    if empty {
                        arrays.push(array);
                    } else {
                        open_array = Some(array);
                    }
                }
                _ => {}
            },
            Event::Text(t) => {
                if let Some(a) = open_array.as_mut() {
                    a.text.push_str(&t);
                }
            }
            Event::End(e) => match e.name().as_ref() {
                "DataArray" => {
                    if let Some(a) = open_array.take() {
                        arrays.push(a);
                    }
                }
                "Points" | "PointData" => section = Section::Other,
                "VTKFile" => closed_root = true,
                _ => {}
            },
            Event::Eof => break,
            _ => {}
        }
    }
    if !saw_root {
        return Err(IoError::parse(
            path,
            Location::Byte(0),
            "a <VTKFile> element",
            "none",
        ));
    }
    // with appended data the XML parsed here stops at <AppendedData>, whose end was checked
    if !closed_root
        && !xml.contains("<AppendedData")
        && !xml.trim_end().is_empty()
        && !appended_follows
    {
        return Err(IoError::parse(
            path,
            Location::Byte(xml.len() as u64),
            "`</VTKFile>` closing the file",
            "end of file (truncated file)",
        ));
    }
    if info.pieces.is_empty() {
        return Err(IoError::parse(
            path,
            Location::Byte(0),
            "a <Piece> element",
            "none",
        ));
    }
    Ok((info, arrays))
}

/// Decodes `count` values of an array.
fn decode(
    a: &ArrayRef,
    count: usize,
    info: &FileInfo,
    appended: Option<(bool, &[u8], usize)>,
    path: &Path,
    options: &ReadOptions,
) -> Result<Vec<f64>, IoError> {
    let at = Location::Byte(a.at);
    let need = count * a.ty.size;
    let bytes: Vec<u8> = match a.format.as_str() {
        "ascii" => {
            let mut out = Vec::with_capacity(count.min(a.text.len() / 2 + 1));
            for token in a.text.split_ascii_whitespace() {
                let v: f64 = token.parse().map_err(|_| {
                    IoError::parse(
                        path,
                        at,
                        format!("numbers in array `{}`", a.name),
                        super::quoted(token),
                    )
                })?;
                out.push(if a.ty.kind == ScalarKind::F32 {
                    v as f32 as f64
                } else {
                    v
                });
            }
            if out.len() != count {
                return Err(IoError::parse(
                    path,
                    at,
                    format!("{count} values in array `{}`", a.name),
                    out.len().to_string(),
                ));
            }
            return Ok(out);
        }
        "binary" => {
            let text: Vec<u8> = a
                .text
                .bytes()
                .filter(|b| !b.is_ascii_whitespace())
                .collect();
            let mut stream = Stream::Base64 {
                text: &text,
                pos: 0,
                pending: Vec::new(),
            };
            read_block(&mut stream, info, need, path, at, options)?
        }
        "appended" => {
            let Some((raw, data, data_start)) = appended else {
                return Err(IoError::parse(
                    path,
                    at,
                    "an <AppendedData> section",
                    "none",
                ));
            };
            let offset = a
                .offset
                .ok_or_else(|| IoError::parse(path, at, "an offset attribute", "none"))?;
            let location = Location::Byte(data_start.saturating_add(offset) as u64);
            let tail = data.get(offset..).ok_or_else(|| {
                IoError::parse(
                    path,
                    location,
                    format!("appended data at offset {offset}"),
                    format!("{} bytes of appended data (truncated file)", data.len()),
                )
            })?;
            // base64 appended data is one stream per array (VTK's writers encode each array,
            // and a compressed array's header and blocks, on their own, `=` padding included)
            let mut stream = if raw {
                Stream::Raw {
                    bytes: tail,
                    pos: 0,
                }
            } else {
                Stream::Base64 {
                    text: tail,
                    pos: 0,
                    pending: Vec::new(),
                }
            };
            read_block(&mut stream, info, need, path, location, options)?
        }
        other => {
            return Err(IoError::unsupported(
                path,
                at,
                format!("DataArray format {}", super::quoted(other)),
            ));
        }
    };
    if bytes.len() < need {
        return Err(IoError::parse(
            path,
            at,
            format!("{need} bytes for {count} values of `{}`", a.name),
            format!("{} bytes (wrong count or truncated file)", bytes.len()),
        ));
    }
    let data = &bytes[..need];
    Ok(match a.ty.int64 {
        None => data
            .chunks_exact(a.ty.size)
            .map(|c| read_value(c, a.ty.kind, info.big_endian))
            .collect(),
        Some(signed) => data
            .chunks_exact(8)
            .map(|c| {
                let mut b: [u8; 8] = c.try_into().expect("8 bytes");
                if info.big_endian {
                    b.reverse();
                }
                if signed {
                    i64::from_le_bytes(b) as f64
                } else {
                    u64::from_le_bytes(b) as f64
                }
            })
            .collect(),
    })
}

/// The bytes of one array's data as the file holds them: raw appended bytes, or base64 text
/// read as a sequence of four-character groups, each decoded on its own where needed, so that
/// several streams one after another (each with its `=` padding) read as their concatenation.
enum Stream<'a> {
    Raw {
        bytes: &'a [u8],
        pos: usize,
    },
    Base64 {
        text: &'a [u8],
        pos: usize,
        /// decoded bytes of the last group not yet taken
        pending: Vec<u8>,
    },
}

impl Stream<'_> {
    /// The most bytes still readable.
    fn capacity(&self) -> usize {
        match self {
            Self::Raw { bytes, pos } => bytes.len() - pos,
            Self::Base64 { text, pos, pending } => pending.len() + (text.len() - pos) / 4 * 3,
        }
    }

    /// The next `n` bytes; refused before allocating when the data cannot hold them.
    fn take(&mut self, n: usize, what: &str) -> Result<Vec<u8>, String> {
        if n > self.capacity() {
            return Err(format!(
                "{what} of {n} bytes, but at most {} bytes are left (wrong size or truncated file)",
                self.capacity()
            ));
        }
        match self {
            Self::Raw { bytes, pos } => {
                let out = bytes[*pos..*pos + n].to_vec();
                *pos += n;
                Ok(out)
            }
            Self::Base64 { text, pos, pending } => {
                let mut out = std::mem::take(pending);
                out.reserve(n.saturating_sub(out.len()));
                while out.len() < n {
                    let chars = ((n - out.len()).div_ceil(3) * 4).min(text.len() - *pos);
                    if chars < 4 {
                        return Err(format!("{what} of {n} bytes, but the base64 text ends"));
                    }
                    let before = out.len();
                    // one call for the whole run; group by group where padding ends a stream
                    // inside it
                    if BASE64
                        .decode_vec(&text[*pos..*pos + chars], &mut out)
                        .is_ok()
                    {
                        *pos += chars;
                    } else {
                        out.truncate(before);
                        BASE64
                            .decode_vec(&text[*pos..*pos + 4], &mut out)
                            .map_err(|e| format!("base64 data ({e})"))?;
                        *pos += 4;
                    }
                }
                *pending = out.split_off(n);
                Ok(out)
            }
        }
    }
}

fn header_value(b: &[u8], info: &FileInfo) -> u64 {
    let mut v = [0u8; 8];
    v[..info.header_size].copy_from_slice(&b[..info.header_size]);
    if info.big_endian {
        v[..info.header_size].reverse();
    }
    u64::from_le_bytes(v)
}

/// The uncompressed bytes of one array's block: `[size][data]`, or for zlib data
/// `[blocks][block size][last size][compressed sizes...][compressed blocks]`. Every size the
/// header gives is checked against what is left of the data before anything is allocated, and
/// the inflated total against `need` (what the array's point count needs), zlib's largest
/// ratio and the memory budget.
fn read_block(
    stream: &mut Stream<'_>,
    info: &FileInfo,
    need: usize,
    path: &Path,
    at: Location,
    options: &ReadOptions,
) -> Result<Vec<u8>, IoError> {
    let h = info.header_size;
    let fail = |e: String| IoError::parse(path, at, "an array's binary data", e);
    let value = |stream: &mut Stream<'_>, what: &str| -> Result<u64, IoError> {
        Ok(header_value(&stream.take(h, what).map_err(fail)?, info))
    };
    if !info.compressed {
        let size = value(stream, "a block size")?;
        let size = usize::try_from(size).unwrap_or(usize::MAX);
        return stream.take(size, "a block").map_err(fail);
    }
    let nblocks = value(stream, "a block count")?;
    let block = value(stream, "a block size")?;
    let last = value(stream, "a last block size")?;
    if nblocks as u128 * h as u128 > stream.capacity() as u128 {
        return Err(fail(format!(
            "a compression header of {nblocks} blocks, more than the {} bytes left hold",
            stream.capacity()
        )));
    }
    let mut sizes = Vec::with_capacity(nblocks as usize);
    for _ in 0..nblocks {
        sizes.push(value(stream, "a compressed block size")?);
    }
    let compressed: u128 = sizes.iter().map(|&s| s as u128).sum();
    let total = if nblocks == 0 {
        0
    } else {
        block as u128 * (nblocks as u128 - 1) + if last == 0 { block } else { last } as u128
    };
    if total > compressed * super::DEFLATE_MAX_RATIO {
        return Err(fail(format!(
            "a header claiming {total} bytes from {compressed} compressed (zlib inflates 1032x at most)"
        )));
    }
    if total < need as u128 {
        return Err(fail(format!(
            "{total} bytes in the compression header for an array of {need} bytes (wrong \
             count or truncated file)"
        )));
    }
    check_budget(path, at, "a zlib-compressed array", total, options)?;
    let mut out = Vec::with_capacity(total as usize);
    for (k, &size) in sizes.iter().enumerate() {
        let chunk = stream
            .take(
                usize::try_from(size).unwrap_or(usize::MAX),
                "a compressed block",
            )
            .map_err(fail)?;
        let expect = if k + 1 == sizes.len() && last != 0 {
            last
        } else {
            block
        };
        let before = out.len();
        use std::io::Read;
        flate2::read::ZlibDecoder::new(&chunk[..])
            .take(expect)
            .read_to_end(&mut out)
            .map_err(|e| IoError::parse(path, at, "zlib data", e.to_string()))?;
        if (out.len() - before) as u64 != expect {
            return Err(IoError::parse(
                path,
                at,
                format!("block {k} inflating to {expect} bytes"),
                format!("{} bytes", out.len() - before),
            ));
        }
    }
    Ok(out)
}

/// Serialises a particle set as a VTK XML unstructured grid of vertex cells.
#[must_use]
pub fn to_bytes_with(set: &ParticleSet, encoding: Encoding) -> Vec<u8> {
    let n = set.len();
    let point_data: Vec<Array> = named_arrays(set)
        .into_iter()
        .map(|a| (a.name, a.kind, a.components, a.values))
        .collect();
    let cells = [
        (
            "connectivity",
            ScalarKind::I32,
            (0..n).map(|i| i as f64).collect(),
        ),
        (
            "offsets",
            ScalarKind::I32,
            (1..=n).map(|i| i as f64).collect(),
        ),
        ("types", ScalarKind::U8, vec![1.0; n]),
    ];
    unstructured_grid(&set.positions, &point_data, (n, &cells), encoding)
}

/// A named array of a written file: name, type, components, values.
type Array = (String, ScalarKind, usize, Vec<f64>);

/// A grid's cells as written: the connectivity, offsets and types arrays (name, type, values).
type Cells<'a> = [(&'a str, ScalarKind, Vec<f64>); 3];

/// Serialises a triangle mesh as a VTK XML unstructured grid of triangle cells (VTK type 5),
/// with `point_data` (name and one vector a point each, such as normals and velocities), as
/// ParaView and meshio read it.
#[must_use]
pub fn triangles_to_bytes(
    positions: &[Vec3],
    triangles: &[[u32; 3]],
    point_data: &[(&str, &[Vec3])],
    encoding: Encoding,
) -> Vec<u8> {
    let arrays: Vec<Array> = point_data
        .iter()
        .map(|(name, values)| {
            (
                (*name).to_string(),
                ScalarKind::F32,
                3,
                values
                    .iter()
                    .flat_map(|v| v.to_array().map(f64::from))
                    .collect(),
            )
        })
        .collect();
    let t = triangles.len();
    let cells = [
        (
            "connectivity",
            ScalarKind::I32,
            triangles.iter().flatten().map(|&v| f64::from(v)).collect(),
        ),
        (
            "offsets",
            ScalarKind::I32,
            (1..=t).map(|i| (3 * i) as f64).collect(),
        ),
        ("types", ScalarKind::U8, vec![5.0; t]),
    ];
    unstructured_grid(positions, &arrays, (t, &cells), encoding)
}

/// An `UnstructuredGrid` file of `positions` with `point_data` and `cells` (its count, and its
/// connectivity, offsets and types arrays).
fn unstructured_grid(
    positions: &[Vec3],
    point_data: &[Array],
    (cell_count, cells): (usize, &Cells<'_>),
    encoding: Encoding,
) -> Vec<u8> {
    let n = positions.len();
    let points: Vec<f64> = positions
        .iter()
        .flat_map(|p| p.to_array().map(f64::from))
        .collect();
    let mut xml = String::new();
    let mut appended: Vec<u8> = Vec::new();
    let mut data_array =
        |xml: &mut String, name: &str, kind: ScalarKind, components: usize, values: &[f64]| {
            let head = format!(
                "<DataArray type=\"{}\" Name=\"{}\" NumberOfComponents=\"{components}\"",
                type_name(kind),
                escape(name)
            );
            match encoding {
                Encoding::Ascii => {
                    xml.push_str(&head);
                    xml.push_str(" format=\"ascii\">\n");
                    for v in values {
                        if kind == ScalarKind::F32 {
                            xml.push_str(&format!("{} ", *v as f32));
                        } else {
                            xml.push_str(&format!("{v} "));
                        }
                    }
                    xml.push_str("\n</DataArray>\n");
                }
                Encoding::Base64 | Encoding::RawAppended => {
                    let mut block = Vec::with_capacity(4 + values.len() * kind.size());
                    block.extend_from_slice(&((values.len() * kind.size()) as u32).to_le_bytes());
                    for &v in values {
                        push_value(&mut block, kind, v, false);
                    }
                    if encoding == Encoding::Base64 {
                        xml.push_str(&head);
                        xml.push_str(" format=\"binary\">\n");
                        xml.push_str(&BASE64.encode(&block));
                        xml.push_str("\n</DataArray>\n");
                    } else {
                        xml.push_str(&format!(
                            "{head} format=\"appended\" offset=\"{}\"/>\n",
                            appended.len()
                        ));
                        appended.extend_from_slice(&block);
                    }
                }
            }
        };
    xml.push_str("<?xml version=\"1.0\"?>\n<VTKFile type=\"UnstructuredGrid\" version=\"1.0\" byte_order=\"LittleEndian\" header_type=\"UInt32\">\n<UnstructuredGrid>\n");
    xml.push_str(&format!(
        "<Piece NumberOfPoints=\"{n}\" NumberOfCells=\"{cell_count}\">\n<PointData>\n"
    ));
    for (name, kind, components, values) in point_data {
        data_array(&mut xml, name, *kind, *components, values);
    }
    xml.push_str("</PointData>\n<Points>\n");
    data_array(&mut xml, "Points", ScalarKind::F32, 3, &points);
    xml.push_str("</Points>\n<Cells>\n");
    for (name, kind, values) in cells {
        data_array(&mut xml, name, *kind, 1, values);
    }
    xml.push_str("</Cells>\n</Piece>\n</UnstructuredGrid>\n");
    let mut out = xml.into_bytes();
    if encoding == Encoding::RawAppended {
        out.extend_from_slice(b"<AppendedData encoding=\"raw\">\n_");
        out.extend_from_slice(&appended);
        out.extend_from_slice(b"\n</AppendedData>\n");
    }
    out.extend_from_slice(b"</VTKFile>\n");
    out
}

/// Serialises with raw appended data (see [`to_bytes_with`]).
#[must_use]
pub fn to_bytes(set: &ParticleSet) -> Vec<u8> {
    to_bytes_with(set, Encoding::RawAppended)
}

fn escape(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('"', "&quot;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
}
