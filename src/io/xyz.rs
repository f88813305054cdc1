//! Plain-text particle files.
//!
//! One particle a line, values separated by whitespace or commas; blank lines and lines starting
//! with `#` are skipped. Without a header the columns are `x y z` or `x y z nx ny nz`. A first
//! line holding any non-numeric token is a header naming the columns (`x,y,z,nx,ny,nz,id,...`);
//! the names the crate knows fill [`ParticleSet`] fields, the others are kept as `f64`
//! attributes. Written files use the shortest decimal form that reads back to the same `f32`.

use std::fmt::Write as _;
use std::path::Path;

use glam::Vec3;

use super::{IoError, Location, write_atomically};
use crate::particles::{Attribute, ParticleSet, ScalarKind};

/// Column separator of written files.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Delimiter {
    /// `x y z` without a header (`.xyz`, `.txt`).
    Space,
    /// `x,y,z` with a header row (`.csv`).
    Comma,
}

fn split(line: &str) -> Vec<&str> {
    line.split(|c: char| c == ',' || c.is_whitespace())
        .filter(|t| !t.is_empty())
        .collect()
}

/// Parses a text particle file held in memory; `path` names it in errors.
pub fn parse(bytes: &[u8], path: &Path) -> Result<ParticleSet, IoError> {
    let text = std::str::from_utf8(bytes).map_err(|e| {
        let line = bytes[..e.valid_up_to()]
            .iter()
            .filter(|&&b| b == b'\n')
            .count()
            + 1;
        IoError::parse(
            path,
            Location::Line(line),
            "text (x y z per line)",
            "binary data; for raw little-endian f32 triplets (splashsurf's binary .xyz) pass --format xyz-raw",
        )
    })?;
    let mut header: Option<Vec<String>> = None;
    let mut columns: Vec<Vec<f64>> = Vec::new();
    let mut width = 0;
    for (index, line) in text.lines().enumerate() {
        let line_no = index + 1;
        let trimmed = line.trim();
        if trimmed.is_empty() || trimmed.starts_with('#') {
            continue;
        }
        let tokens = split(trimmed);
        let parsed: Vec<Option<f64>> = tokens.iter().map(|t| t.parse::<f64>().ok()).collect();
        if width == 0 {
            width = tokens.len();
            columns = vec![Vec::new(); width];
            if parsed.iter().any(Option::is_none) {
                header = Some(tokens.iter().map(|t| t.to_string()).collect());
                continue;
            }
            if header.is_none() && width != 3 && width != 6 {
                return Err(IoError::parse(
                    path,
                    Location::Line(line_no),
                    "3 columns (x y z) or 6 (x y z nx ny nz), or a header row",
                    format!("{width} columns"),
                ));
            }
        }
        if tokens.len() != width {
            return Err(IoError::parse(
                path,
                Location::Line(line_no),
                format!("{width} values like the lines before"),
                format!("{} values", tokens.len()),
            ));
        }
        let particle = columns[0].len();
        for (c, (value, token)) in parsed.iter().zip(&tokens).enumerate() {
            let Some(v) = *value else {
                return Err(IoError::parse(
                    path,
                    Location::Line(line_no),
                    "a number",
                    super::quoted(token),
                ));
            };
            if c < 3 && !(v as f32).is_finite() {
                return Err(IoError::NonFinite {
                    path: path.to_owned(),
                    location: Location::Line(line_no),
                    index: particle,
                    value: super::clean(token, super::FOUND_CHARS),
                });
            }
            columns[c].push(v);
        }
    }
    let names: Vec<String> = header.unwrap_or_else(|| {
        ["x", "y", "z", "nx", "ny", "nz"][..width.min(6)]
            .iter()
            .map(|s| s.to_string())
            .collect()
    });
    let find = |n: &str| names.iter().position(|c| c.eq_ignore_ascii_case(n));
    let (Some(ix), Some(iy), Some(iz)) = (find("x"), find("y"), find("z")) else {
        return Err(IoError::parse(
            path,
            Location::Line(1),
            "columns named x, y and z",
            names.join(","),
        ));
    };
    // positions must be finite wherever the x, y, z columns are
    for (c, col) in [ix, iy, iz].iter().map(|&c| (c, &columns[c])) {
        if let Some(p) = col.iter().position(|v| !(*v as f32).is_finite()) {
            return Err(IoError::NonFinite {
                path: path.to_owned(),
                location: Location::Line(1),
                index: p,
                value: format!("{:e}", columns[c][p]),
            });
        }
    }
    let n = columns.first().map_or(0, Vec::len);
    let mut taken = vec![false; names.len()];
    let mut vec3 = |a: &str, b: &str, c: &str| {
        let (Some(i), Some(j), Some(k)) = (find(a), find(b), find(c)) else {
            return None;
        };
        taken[i] = true;
        taken[j] = true;
        taken[k] = true;
        Some(
            (0..n)
                .map(|r| {
                    Vec3::new(
                        columns[i][r] as f32,
                        columns[j][r] as f32,
                        columns[k][r] as f32,
                    )
                })
                .collect::<Vec<_>>(),
        )
    };
    let positions = vec3("x", "y", "z").unwrap_or_default();
    let normals = vec3("nx", "ny", "nz");
    let velocities = vec3("vx", "vy", "vz");
    let mut set = ParticleSet {
        positions,
        normals,
        velocities,
        ..ParticleSet::default()
    };
    if let Some(i) = find("mass") {
        taken[i] = true;
        set.masses = Some(columns[i].iter().map(|&m| m as f32).collect());
    }
    if let Some(i) = find("id").filter(|&i| {
        columns[i]
            .iter()
            .all(|&v| v.fract() == 0.0 && (0.0..=u32::MAX as f64).contains(&v))
    }) {
        taken[i] = true;
        set.ids = Some(columns[i].iter().map(|&v| v as u32).collect());
    }
    for (i, name) in names.iter().enumerate().filter(|(i, _)| !taken[*i]) {
        set.extra.push(Attribute::scalar(
            name.clone(),
            ScalarKind::F64,
            std::mem::take(&mut columns[i]),
        ));
    }
    Ok(set)
}

/// Serialises a particle set as text. Space-delimited output holds positions and, when present,
/// normals (the plain `.xyz` layout); comma-delimited output has a header row and every
/// attribute except colours.
#[must_use]
pub fn to_string(set: &ParticleSet, delimiter: Delimiter) -> String {
    let mut out = String::with_capacity(set.len() * 40);
    let sep = if delimiter == Delimiter::Comma {
        ","
    } else {
        " "
    };
    let csv = delimiter == Delimiter::Comma;
    if csv {
        let mut names = vec!["x", "y", "z"];
        if set.normals.is_some() {
            names.extend(["nx", "ny", "nz"]);
        }
        if set.velocities.is_some() {
            names.extend(["vx", "vy", "vz"]);
        }
        if set.masses.is_some() {
            names.push("mass");
        }
        if set.ids.is_some() {
            names.push("id");
        }
        let mut names: Vec<String> = names.into_iter().map(String::from).collect();
        for a in &set.extra {
            names.extend(super::component_names(a));
        }
        out.push_str(&names.join(","));
        out.push('\n');
    }
    for i in 0..set.len() {
        let p = set.positions[i];
        let _ = write!(out, "{}{sep}{}{sep}{}", p.x, p.y, p.z);
        if let Some(n) = &set.normals {
            let _ = write!(out, "{sep}{}{sep}{}{sep}{}", n[i].x, n[i].y, n[i].z);
        }
        if csv {
            if let Some(v) = &set.velocities {
                let _ = write!(out, "{sep}{}{sep}{}{sep}{}", v[i].x, v[i].y, v[i].z);
            }
            if let Some(m) = &set.masses {
                let _ = write!(out, "{sep}{}", m[i]);
            }
            if let Some(ids) = &set.ids {
                let _ = write!(out, "{sep}{}", ids[i]);
            }
            for a in &set.extra {
                for v in a.of(i) {
                    let _ = write!(out, "{sep}{v}");
                }
            }
        }
        out.push('\n');
    }
    out
}

/// Writes a particle set as text (atomically).
pub fn write(path: &Path, set: &ParticleSet, delimiter: Delimiter) -> Result<(), IoError> {
    set.validate().map_err(|source| IoError::InvalidSet {
        path: path.to_owned(),
        source,
    })?;
    write_atomically(path, to_string(set, delimiter).as_bytes())
}

/// Parses raw little-endian f32 triplets (splashsurf's binary `.xyz`); the length must be a
/// multiple of 12 bytes.
pub fn parse_raw(bytes: &[u8], path: &Path) -> Result<ParticleSet, IoError> {
    if !bytes.len().is_multiple_of(12) {
        return Err(IoError::parse(
            path,
            Location::Byte((bytes.len() / 12 * 12) as u64),
            "a whole number of 12-byte x y z f32 triplets",
            format!("{} bytes ({} left over)", bytes.len(), bytes.len() % 12),
        ));
    }
    let coords: Vec<f64> = bytes
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]) as f64)
        .collect();
    Ok(ParticleSet::from_positions(super::positions_from(
        path,
        &coords,
        |i| Location::Byte(12 * i as u64),
    )?))
}

/// Serialises the positions as raw little-endian f32 triplets.
#[must_use]
pub fn to_raw(set: &ParticleSet) -> Vec<u8> {
    set.positions
        .iter()
        .flat_map(|p| p.to_array())
        .flat_map(f32::to_le_bytes)
        .collect()
}
