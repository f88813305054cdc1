//! JSON particle files: an array of `[x, y, z]` triplets, as splashsurf reads them.

use std::path::Path;

use super::{IoError, Location, positions_from};
use crate::particles::ParticleSet;

/// Parses `[[x, y, z], ...]`; `path` names the file in errors (with serde_json's line).
pub fn parse(bytes: &[u8], path: &Path) -> Result<ParticleSet, IoError> {
    let trimmed = bytes
        .iter()
        .position(|b| !b.is_ascii_whitespace())
        .map_or(&bytes[..0], |i| &bytes[i..]);
    if !trimmed.starts_with(b"[") {
        return Err(IoError::WrongFormat {
            path: path.to_owned(),
            expected: "JSON array of [x, y, z]",
            found: super::describe(bytes),
        });
    }
    let triplets: Vec<[f64; 3]> = serde_json::from_slice(bytes).map_err(|e| {
        IoError::parse(
            path,
            Location::Line(e.line()),
            "a JSON array of [x, y, z] number triplets",
            e.to_string(),
        )
    })?;
    let coords: Vec<f64> = triplets.iter().flatten().copied().collect();
    Ok(ParticleSet::from_positions(positions_from(
        path,
        &coords,
        |_| Location::Line(1),
    )?))
}

/// Serialises the positions as `[[x, y, z], ...]` (shortest decimals that read back exactly).
#[must_use]
pub fn to_bytes(set: &ParticleSet) -> Vec<u8> {
    let mut out = String::with_capacity(set.len() * 32 + 2);
    out.push('[');
    for (i, p) in set.positions.iter().enumerate() {
        if i > 0 {
            out.push(',');
        }
        out.push_str(&format!("[{},{},{}]", p.x, p.y, p.z));
    }
    out.push_str("]\n");
    out.into_bytes()
}
