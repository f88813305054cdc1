//! Reading and writing particle files.
//!
//! - [`ply`]: PLY, ASCII and binary (little- and big-endian), every vertex property kept.
//! - [`vtk`]: legacy VTK 2.0-5.1, ASCII and binary, unstructured grids and poly data with point
//!   data (`SCALARS`, `VECTORS`, `NORMALS`, `FIELD`), as SPlisHSPlasH and ParaView write it.
//! - [`vtu`]: VTK XML (`.vtu`, `.vtp`): ascii, base64 and raw appended data, zlib or uncompressed.
//! - [`bgeo`]: Houdini classic BGEO version 5 as partio writes it, gzipped or not.
//! - [`xyz`]: plain text, whitespace-separated `x y z [nx ny nz]` (`.xyz`, `.txt`) or CSV with an
//!   optional header row naming the columns (`.csv`); raw little-endian f32 triplets
//!   (`--format xyz-raw`).
//! - [`json`]: `[[x, y, z], ...]`.
//!
//! Every malformed file gives an [`IoError`] naming the file, the line or byte offset, what was
//! expected and what was found. Readers check counts against the file size before allocating, so
//! a lying header cannot exhaust memory.

pub mod bgeo;
pub mod json;
pub mod ply;
pub mod vtk;
pub mod vtu;
pub mod xyz;

use std::fmt;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::particles::{ParticleSet, ScalarKind};

/// Where in a file a problem was found.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Location {
    /// 1-based line number (text files and PLY headers).
    Line(usize),
    /// 0-based byte offset (binary data).
    Byte(u64),
}

impl fmt::Display for Location {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Line(l) => write!(f, "line {l}"),
            Self::Byte(b) => write!(f, "byte {b}"),
        }
    }
}

/// Errors of reading and writing particle files.
#[derive(Debug, thiserror::Error)]
pub enum IoError {
    /// The operating system refused a read or write.
    #[error("{}: {source}", path.display())]
    Os {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// The file's content is not what its format requires.
    #[error("{}: {location}: expected {expected}, found {found}", path.display())]
    Parse {
        path: PathBuf,
        location: Location,
        expected: String,
        found: String,
    },
    /// A coordinate is NaN or infinite.
    #[error("{}: {location}: particle {index} has a non-finite coordinate `{value}`", path.display())]
    NonFinite {
        path: PathBuf,
        location: Location,
        index: usize,
        value: String,
    },
    /// The file is not in the format its name or `--format` says.
    #[error("{}: expected a {expected} file, found {found}", path.display())]
    WrongFormat {
        path: PathBuf,
        expected: &'static str,
        found: String,
    },
    /// A valid file uses a feature this reader does not support.
    #[error("{}: {location}: {what} is not supported", path.display())]
    Unsupported {
        path: PathBuf,
        location: Location,
        what: String,
    },
    /// The file declares more data than this machine's memory can hold.
    #[error("{}: {location}: the file declares data needing {needed} bytes, more than the {available} bytes of memory available", path.display())]
    TooLarge {
        path: PathBuf,
        location: Location,
        needed: u128,
        available: u64,
    },
    /// Decompressing the file would take more memory than the reader's budget allows.
    #[error("{}: {location}: {what} inflates to {needed} bytes, more than the memory budget of {budget} bytes (raise it with --memory-budget, or `ReadOptions::memory_budget`)", path.display())]
    OverBudget {
        path: PathBuf,
        location: Location,
        what: String,
        needed: u128,
        budget: u64,
    },
    /// The format cannot be told from the file name.
    #[error("{}: cannot tell the format from the extension `{extension}`; known: .ply .vtk .vtu .bgeo .bgeo.gz .xyz .txt .csv .json (or pass --format)", path.display())]
    UnknownFormat { path: PathBuf, extension: String },
    /// A set to be written is inconsistent.
    #[error("{}: cannot write an invalid particle set: {source}", path.display())]
    InvalidSet {
        path: PathBuf,
        #[source]
        source: crate::particles::ParticleSetError,
    },
}

impl IoError {
    pub(crate) fn os(path: &Path, source: std::io::Error) -> Self {
        Self::Os {
            path: path.to_owned(),
            source,
        }
    }

    pub(crate) fn parse(
        path: &Path,
        location: Location,
        expected: impl Into<String>,
        found: impl Into<String>,
    ) -> Self {
        Self::Parse {
            path: path.to_owned(),
            location,
            expected: clean(&expected.into(), 120),
            found: clean(&found.into(), 100),
        }
    }

    pub(crate) fn unsupported(path: &Path, location: Location, what: impl Into<String>) -> Self {
        Self::Unsupported {
            path: path.to_owned(),
            location,
            what: clean(&what.into(), 120),
        }
    }

    /// Where in the file the error is, when it is about one place.
    #[must_use]
    pub fn location(&self) -> Option<Location> {
        match self {
            Self::Parse { location, .. }
            | Self::NonFinite { location, .. }
            | Self::Unsupported { location, .. }
            | Self::TooLarge { location, .. }
            | Self::OverBudget { location, .. } => Some(*location),
            _ => None,
        }
    }
}

/// Particle file formats.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Format {
    /// PLY, ASCII or binary (the header says which).
    Ply,
    /// Legacy VTK (`.vtk`), versions 2.0 to 5.1, ASCII or binary.
    Vtk,
    /// VTK XML unstructured grid or poly data (`.vtu`, `.vtp`): ascii, base64 or raw appended,
    /// zlib-compressed or not.
    Vtu,
    /// Houdini classic BGEO (`BgeoV`, version 5, as partio writes it), gzipped or not.
    Bgeo,
    /// Whitespace-separated text `x y z [nx ny nz]`.
    Xyz,
    /// Raw little-endian f32 triplets without any header (what splashsurf calls `.xyz`).
    XyzRaw,
    /// Comma-separated text with an optional header row.
    Csv,
    /// JSON array of `[x, y, z]` triplets.
    Json,
}

impl Format {
    /// Every format.
    pub const ALL: [Format; 8] = [
        Self::Ply,
        Self::Vtk,
        Self::Vtu,
        Self::Bgeo,
        Self::Xyz,
        Self::XyzRaw,
        Self::Csv,
        Self::Json,
    ];

    /// The format named by a path's extension. `.xyz` means text; raw binary triplets need
    /// `--format xyz-raw` (the two are never told apart by guessing).
    pub fn from_path(path: &Path) -> Result<Self, IoError> {
        let name = path
            .file_name()
            .and_then(|n| n.to_str())
            .unwrap_or("")
            .to_ascii_lowercase();
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .unwrap_or("")
            .to_ascii_lowercase();
        match ext.as_str() {
            "ply" => Ok(Self::Ply),
            "vtk" => Ok(Self::Vtk),
            "vtu" | "vtp" => Ok(Self::Vtu),
            "bgeo" | "bhclassic" => Ok(Self::Bgeo),
            "gz" if name.ends_with(".bgeo.gz") => Ok(Self::Bgeo),
            "xyz" | "txt" => Ok(Self::Xyz),
            "csv" => Ok(Self::Csv),
            "json" => Ok(Self::Json),
            _ => Err(IoError::UnknownFormat {
                path: path.to_owned(),
                extension: ext,
            }),
        }
    }

    /// The name used by `--format`.
    #[must_use]
    pub fn name(self) -> &'static str {
        match self {
            Self::Ply => "ply",
            Self::Vtk => "vtk",
            Self::Vtu => "vtu",
            Self::Bgeo => "bgeo",
            Self::Xyz => "xyz",
            Self::XyzRaw => "xyz-raw",
            Self::Csv => "csv",
            Self::Json => "json",
        }
    }
}

// the memory helpers live in `crate::memory`; still reachable here
pub use crate::memory::{DEFAULT_MEMORY_BUDGET, available_memory};

/// How files are read.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ReadOptions {
    /// The most bytes that decompressing a file (gzipped BGEO, zlib blocks of VTK XML) may
    /// produce; a file that declares or inflates to more is refused with
    /// [`IoError::OverBudget`] before the memory is taken. Default [`DEFAULT_MEMORY_BUDGET`].
    pub memory_budget: u64,
}

impl Default for ReadOptions {
    fn default() -> Self {
        Self {
            memory_budget: DEFAULT_MEMORY_BUDGET,
        }
    }
}

/// Reads a particle file, in `format` or else the format its extension names.
pub fn read_particles(path: &Path, format: Option<Format>) -> Result<ParticleSet, IoError> {
    read_particles_with(path, format, &ReadOptions::default())
}

/// [`read_particles`] with explicit [`ReadOptions`].
pub fn read_particles_with(
    path: &Path,
    format: Option<Format>,
    options: &ReadOptions,
) -> Result<ParticleSet, IoError> {
    let format = match format {
        Some(f) => f,
        None => Format::from_path(path)?,
    };
    let bytes = std::fs::read(path).map_err(|e| IoError::os(path, e))?;
    parse_bytes_with(format, &bytes, path, options)
}

/// Parses a particle file held in memory; `path` names it in errors.
pub fn parse_bytes(format: Format, bytes: &[u8], path: &Path) -> Result<ParticleSet, IoError> {
    parse_bytes_with(format, bytes, path, &ReadOptions::default())
}

/// [`parse_bytes`] with explicit [`ReadOptions`].
pub fn parse_bytes_with(
    format: Format,
    bytes: &[u8],
    path: &Path,
    options: &ReadOptions,
) -> Result<ParticleSet, IoError> {
    match format {
        Format::Ply => ply::parse(bytes, path),
        Format::Vtk => vtk::parse(bytes, path),
        Format::Vtu => vtu::parse_with(bytes, path, options),
        Format::Bgeo => bgeo::parse_with(bytes, path, options),
        Format::Xyz | Format::Csv => xyz::parse(bytes, path),
        Format::XyzRaw => xyz::parse_raw(bytes, path),
        Format::Json => json::parse(bytes, path),
    }
}

/// Writes a particle file in `format` or else the format its extension names (atomically: a
/// temporary file renamed into place). PLY and VTK are written binary.
pub fn write_particles(
    path: &Path,
    set: &ParticleSet,
    format: Option<Format>,
) -> Result<(), IoError> {
    let format = match format {
        Some(f) => f,
        None => Format::from_path(path)?,
    };
    write_atomically(path, &to_bytes(format, set, path)?)
}

/// Serialises a particle set in `format` (validated first; `path` names it in errors).
pub fn to_bytes(format: Format, set: &ParticleSet, path: &Path) -> Result<Vec<u8>, IoError> {
    set.validate().map_err(|source| IoError::InvalidSet {
        path: path.to_owned(),
        source,
    })?;
    Ok(match format {
        Format::Ply => ply::to_bytes(set, ply::Encoding::BinaryLittleEndian),
        Format::Vtk => vtk::to_bytes(set),
        Format::Vtu => vtu::to_bytes(set),
        Format::Bgeo
            if path
                .extension()
                .is_some_and(|e| e.eq_ignore_ascii_case("gz")) =>
        {
            use std::io::Write;
            let mut gz = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
            gz.write_all(&bgeo::to_bytes(set))
                .map_err(|e| IoError::os(path, e))?;
            gz.finish().map_err(|e| IoError::os(path, e))?
        }
        Format::Bgeo => bgeo::to_bytes(set),
        Format::Xyz => xyz::to_string(set, xyz::Delimiter::Space).into_bytes(),
        Format::XyzRaw => xyz::to_raw(set),
        Format::Csv => xyz::to_string(set, xyz::Delimiter::Comma).into_bytes(),
        Format::Json => json::to_bytes(set),
    })
}

/// A short description of what some bytes look like, for "expected X, found Y" errors.
#[must_use]
pub fn describe(bytes: &[u8]) -> String {
    let head = &bytes[..bytes.len().min(64)];
    let starts = |p: &[u8]| head.starts_with(p);
    if bytes.is_empty() {
        "an empty file".into()
    } else if starts(b"ply") {
        "a PLY file (magic `ply`)".into()
    } else if starts(b"# vtk DataFile") {
        "a legacy VTK file".into()
    } else if starts(b"<?xml") || starts(b"<VTKFile") {
        "an XML file".into()
    } else if starts(b"Bgeo") {
        "a BGEO file".into()
    } else if starts(&[0x7f, b'N', b'S', b'J']) {
        "a new-style (JSON) BGEO file; only classic BGEO (.bhclassic) is supported".into()
    } else if starts(&[0x1f, 0x8b]) {
        "gzip-compressed data".into()
    } else if head.first().is_some_and(|&c| c == b'[' || c == b'{') {
        "JSON-like text".into()
    } else if std::str::from_utf8(head).is_ok() {
        let line = String::from_utf8_lossy(head);
        format!(
            "text starting {}",
            quoted(line.lines().next().unwrap_or(""))
        )
    } else {
        "binary data".into()
    }
}

/// Refuses to decompress `needed` bytes beyond the budget.
pub(crate) fn check_budget(
    path: &Path,
    location: Location,
    what: &str,
    needed: u128,
    options: &ReadOptions,
) -> Result<(), IoError> {
    if needed > options.memory_budget as u128 {
        return Err(IoError::OverBudget {
            path: path.to_owned(),
            location,
            what: what.to_owned(),
            needed,
            budget: options.memory_budget,
        });
    }
    check_allocation(path, location, needed)
}

/// How many characters of a value found in a file an error shows.
pub(crate) const FOUND_CHARS: usize = 60;

/// The most bytes one byte of deflate (zlib, gzip) data can inflate to: a stored length code
/// of 258 bytes takes at least two bits, so about 1032 (RFC 1951, §3.2.5).
pub(crate) const DEFLATE_MAX_RATIO: u128 = 1032;

/// Text from a file made safe for a message: control and invisible formatting characters
/// escaped (`\u{1b}`, `\n`), cut to at most `max` characters of output with `...` after.
#[must_use]
pub fn clean(text: &str, max: usize) -> String {
    let mut out = String::new();
    let mut len = 0;
    for c in text.chars() {
        let invisible = matches!(c, '\u{200b}'..='\u{200f}' | '\u{202a}'..='\u{202e}' | '\u{2066}'..='\u{2069}' | '\u{feff}');
        let piece: String = if c.is_control() || invisible {
            c.escape_debug().collect()
        } else {
            c.to_string()
        };
        let n = piece.chars().count();
        if len + n > max {
            out.push_str("...");
            break;
        }
        out.push_str(&piece);
        len += n;
    }
    out
}

/// A value found in a file, quoted and escaped as Rust's `{:?}` writes strings, cut to about
/// 60 characters of output: `"1 x 1"`, `"\u{1b}[31m"`.
#[must_use]
pub fn quoted(text: &str) -> String {
    let mut out = String::from("\"");
    let mut len = 0;
    for c in text.chars() {
        // as `str`'s Debug: a single quote stays as it is
        let piece: String = if c == '\'' {
            c.to_string()
        } else {
            c.escape_debug().collect()
        };
        let n = piece.chars().count();
        if len + n > FOUND_CHARS {
            out.push_str("\"...");
            return out;
        }
        out.push_str(&piece);
        len += n;
    }
    out.push('"');
    out
}

/// Refuses an allocation of `needed` bytes that the machine cannot hold.
pub(crate) fn check_allocation(
    path: &Path,
    location: Location,
    needed: u128,
) -> Result<(), IoError> {
    let available = available_memory();
    if needed > available as u128 {
        return Err(IoError::TooLarge {
            path: path.to_owned(),
            location,
            needed,
            available,
        });
    }
    Ok(())
}

/// An attribute as a reader found it, before the crate's own attributes are picked out.
pub(crate) struct RawAttribute {
    pub name: String,
    pub kind: ScalarKind,
    pub components: usize,
    pub values: Vec<f64>,
}

/// Builds a particle set from positions and named attributes, recognising ids, velocities,
/// masses and normals by their usual names (case-insensitive); everything else is kept as an
/// extra attribute.
pub(crate) fn assemble(positions: Vec<glam::Vec3>, attributes: Vec<RawAttribute>) -> ParticleSet {
    let n = positions.len();
    let mut set = ParticleSet::from_positions(positions);
    for a in attributes {
        let lower = a.name.to_ascii_lowercase();
        let vec3 = |v: &[f64]| {
            v.chunks_exact(3)
                .map(|c| glam::Vec3::new(c[0] as f32, c[1] as f32, c[2] as f32))
                .collect::<Vec<_>>()
        };
        let complete = a.values.len() == n * a.components;
        match (lower.as_str(), a.components) {
            ("id" | "ids" | "particle_id" | "particleid" | "pid", 1)
                if complete
                    && set.ids.is_none()
                    && a.kind.is_integer()
                    && a.values
                        .iter()
                        .all(|&v| (0.0..=u32::MAX as f64).contains(&v)) =>
            {
                set.ids = Some(a.values.iter().map(|&v| v as u32).collect());
            }
            ("velocity" | "velocities" | "vel" | "v", 3)
                if complete && set.velocities.is_none() =>
            {
                set.velocities = Some(vec3(&a.values));
            }
            ("normal" | "normals" | "n", 3) if complete && set.normals.is_none() => {
                set.normals = Some(vec3(&a.values));
            }
            ("mass" | "masses", 1) if complete && set.masses.is_none() => {
                set.masses = Some(a.values.iter().map(|&m| m as f32).collect());
            }
            _ => set.extra.push(crate::particles::Attribute {
                name: a.name,
                kind: a.kind,
                components: a.components,
                values: a.values,
            }),
        }
    }
    set
}

/// The attributes of a set in the generic form of formats with named arrays (VTK, VTU, BGEO):
/// ids, velocities, masses, normals and colours under their usual names, then the extras.
pub(crate) fn named_arrays(set: &ParticleSet) -> Vec<RawAttribute> {
    let mut out = Vec::new();
    let flat = |v: &[glam::Vec3]| {
        v.iter()
            .flat_map(|p| [p.x as f64, p.y as f64, p.z as f64])
            .collect::<Vec<_>>()
    };
    if let Some(ids) = &set.ids {
        out.push(RawAttribute {
            name: "id".into(),
            kind: ScalarKind::U32,
            components: 1,
            values: ids.iter().map(|&i| i as f64).collect(),
        });
    }
    if let Some(v) = &set.velocities {
        out.push(RawAttribute {
            name: "velocity".into(),
            kind: ScalarKind::F32,
            components: 3,
            values: flat(v),
        });
    }
    if let Some(m) = &set.masses {
        out.push(RawAttribute {
            name: "mass".into(),
            kind: ScalarKind::F32,
            components: 1,
            values: m.iter().map(|&m| m as f64).collect(),
        });
    }
    if let Some(nrm) = &set.normals {
        out.push(RawAttribute {
            name: "normal".into(),
            kind: ScalarKind::F32,
            components: 3,
            values: flat(nrm),
        });
    }
    if let Some(c) = &set.colours {
        out.push(RawAttribute {
            name: "colour".into(),
            kind: ScalarKind::U8,
            components: 3,
            values: c.iter().flat_map(|c| c.map(f64::from)).collect(),
        });
    }
    for a in &set.extra {
        out.push(RawAttribute {
            name: a.name.clone(),
            kind: a.kind,
            components: a.components,
            values: a.values.clone(),
        });
    }
    out
}

/// Big- or little-endian bytes of one value of `kind`.
pub(crate) fn push_value(out: &mut Vec<u8>, kind: ScalarKind, v: f64, big_endian: bool) {
    let mut b = [0u8; 8];
    let size = kind.size();
    match kind {
        ScalarKind::I8 => b[..1].copy_from_slice(&(v as i8).to_le_bytes()),
        ScalarKind::U8 => b[..1].copy_from_slice(&(v as u8).to_le_bytes()),
        ScalarKind::I16 => b[..2].copy_from_slice(&(v as i16).to_le_bytes()),
        ScalarKind::U16 => b[..2].copy_from_slice(&(v as u16).to_le_bytes()),
        ScalarKind::I32 => b[..4].copy_from_slice(&(v as i32).to_le_bytes()),
        ScalarKind::U32 => b[..4].copy_from_slice(&(v as u32).to_le_bytes()),
        ScalarKind::F32 => b[..4].copy_from_slice(&(v as f32).to_le_bytes()),
        ScalarKind::F64 => b.copy_from_slice(&v.to_le_bytes()),
    }
    if big_endian {
        b[..size].reverse();
    }
    out.extend_from_slice(&b[..size]);
}

/// One value of `kind` from `size` bytes in the given byte order.
#[inline]
pub(crate) fn read_value(raw: &[u8], kind: ScalarKind, big_endian: bool) -> f64 {
    let size = kind.size();
    let mut b = [0u8; 8];
    b[..size].copy_from_slice(&raw[..size]);
    if big_endian {
        b[..size].reverse();
    }
    match kind {
        ScalarKind::I8 => b[0] as i8 as f64,
        ScalarKind::U8 => b[0] as f64,
        ScalarKind::I16 => i16::from_le_bytes([b[0], b[1]]) as f64,
        ScalarKind::U16 => u16::from_le_bytes([b[0], b[1]]) as f64,
        ScalarKind::I32 => i32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
        ScalarKind::U32 => u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
        ScalarKind::F32 => f32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
        ScalarKind::F64 => f64::from_le_bytes(b),
    }
}

/// Positions from flat coordinates, refusing NaN and infinity; `location_of(i)` places particle
/// `i` in the file for the error.
pub(crate) fn positions_from(
    path: &Path,
    coords: &[f64],
    location_of: impl Fn(usize) -> Location,
) -> Result<Vec<glam::Vec3>, IoError> {
    let mut out = Vec::with_capacity(coords.len() / 3);
    for (i, c) in coords.chunks_exact(3).enumerate() {
        let p = glam::Vec3::new(c[0] as f32, c[1] as f32, c[2] as f32);
        if !p.is_finite() {
            let bad = c
                .iter()
                .find(|v| !(**v as f32).is_finite())
                .copied()
                .unwrap_or(f64::NAN);
            return Err(IoError::NonFinite {
                path: path.to_owned(),
                location: location_of(i),
                index: i,
                value: format!("{bad:e}"),
            });
        }
        out.push(p);
    }
    Ok(out)
}

/// Decompresses gzip data, reading at most `limit` bytes out of it: a "gzip bomb" stops at the
/// limit instead of filling memory. Returns the data and whether more was left.
pub(crate) fn gunzip_limited(
    path: &Path,
    bytes: &[u8],
    limit: u64,
) -> Result<(Vec<u8>, bool), IoError> {
    use std::io::Read;
    let mut decoder = flate2::read::MultiGzDecoder::new(bytes).take(limit);
    let mut out = Vec::new();
    decoder.read_to_end(&mut out).map_err(|e| {
        IoError::parse(
            path,
            Location::Byte(0),
            "valid gzip data",
            format!("a broken stream ({e})"),
        )
    })?;
    let mut rest = decoder.into_inner();
    let more = rest.read(&mut [0u8; 1]).map(|k| k > 0).unwrap_or(false);
    Ok((out, more))
}

/// Column names of an attribute in formats that hold only scalars (PLY, CSV): the name itself
/// for a scalar, `name_x name_y name_z` for a 3-vector, `name_0 name_1 ...` otherwise.
pub(crate) fn component_names(a: &crate::particles::Attribute) -> Vec<String> {
    match a.components {
        1 => vec![a.name.clone()],
        3 => ["x", "y", "z"]
            .iter()
            .map(|c| format!("{}_{c}", a.name))
            .collect(),
        k => (0..k).map(|c| format!("{}_{c}", a.name)).collect(),
    }
}

/// The faces of a mesh file, flat: each face's vertex count, then all their vertex indices in
/// order (read by [`ply::parse_with_faces`] and [`vtk::parse_with_polygons`]).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Polygons {
    /// Vertices of each face.
    pub counts: Vec<u32>,
    /// The faces' vertex indices, one face after the other.
    pub indices: Vec<u32>,
}

/// Writes `bytes` to `path` through a temporary file in the same folder and a rename, so that a
/// failed write never leaves a half-written file under the final name.
pub(crate) fn write_atomically(path: &Path, bytes: &[u8]) -> Result<(), IoError> {
    let dir = path
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let tmp = dir.join(format!(".{name}.{}.tmp", std::process::id()));
    std::fs::write(&tmp, bytes).map_err(|e| IoError::os(path, e))?;
    std::fs::rename(&tmp, path).map_err(|e| {
        let _ = std::fs::remove_file(&tmp);
        IoError::os(path, e)
    })
}
