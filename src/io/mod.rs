//! Reading and writing particle files.
//!
//! - [`ply`]: PLY, ASCII and binary (little- and big-endian), every vertex property kept.
//! - [`xyz`]: plain text, whitespace-separated `x y z [nx ny nz]` (`.xyz`, `.txt`) or CSV with an
//!   optional header row naming the columns (`.csv`).
//!
//! Every malformed file gives an [`IoError`] naming the file, the line or byte offset, what was
//! expected and what was found. Readers check counts against the file size before allocating, so
//! a lying header cannot exhaust memory.

pub mod ply;
pub mod xyz;

use std::fmt;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::particles::ParticleSet;

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
    /// The format cannot be told from the file name.
    #[error("{}: cannot tell the format from the extension `{extension}`; known: .ply, .xyz, .txt, .csv (or pass --format)", path.display())]
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
            expected: expected.into(),
            found: found.into(),
        }
    }
}

/// Particle file formats.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum Format {
    /// PLY, ASCII or binary (the header says which).
    Ply,
    /// Whitespace-separated text `x y z [nx ny nz]`.
    Xyz,
    /// Comma-separated text with an optional header row.
    Csv,
}

impl Format {
    /// The format named by a path's extension.
    pub fn from_path(path: &Path) -> Result<Self, IoError> {
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .unwrap_or("")
            .to_ascii_lowercase();
        match ext.as_str() {
            "ply" => Ok(Self::Ply),
            "xyz" | "txt" => Ok(Self::Xyz),
            "csv" => Ok(Self::Csv),
            _ => Err(IoError::UnknownFormat {
                path: path.to_owned(),
                extension: ext,
            }),
        }
    }
}

/// Reads a particle file, in `format` or else the format its extension names.
pub fn read_particles(path: &Path, format: Option<Format>) -> Result<ParticleSet, IoError> {
    let format = match format {
        Some(f) => f,
        None => Format::from_path(path)?,
    };
    let bytes = std::fs::read(path).map_err(|e| IoError::os(path, e))?;
    match format {
        Format::Ply => ply::parse(&bytes, path),
        Format::Xyz | Format::Csv => xyz::parse(&bytes, path),
    }
}

/// Writes a particle file in `format` or else the format its extension names; PLY is written
/// binary little-endian.
pub fn write_particles(
    path: &Path,
    set: &ParticleSet,
    format: Option<Format>,
) -> Result<(), IoError> {
    let format = match format {
        Some(f) => f,
        None => Format::from_path(path)?,
    };
    match format {
        Format::Ply => ply::write(path, set, ply::Encoding::BinaryLittleEndian),
        Format::Xyz => xyz::write(path, set, xyz::Delimiter::Space),
        Format::Csv => xyz::write(path, set, xyz::Delimiter::Comma),
    }
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
