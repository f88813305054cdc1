//! The particle set every stage reads: positions plus optional per-particle attributes.

use glam::Vec3;
use serde::{Deserialize, Serialize};

/// Storage type of an extra attribute as it was found in a file (PLY's scalar types).
///
/// Values are held as `f64`, which represents every one of these types exactly, and are written
/// back with the type they were read with, so a round trip keeps them bit for bit.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum ScalarKind {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl ScalarKind {
    /// Size of one value in bytes.
    #[must_use]
    pub const fn size(self) -> usize {
        match self {
            Self::I8 | Self::U8 => 1,
            Self::I16 | Self::U16 => 2,
            Self::I32 | Self::U32 | Self::F32 => 4,
            Self::F64 => 8,
        }
    }

    /// True for the integer kinds.
    #[must_use]
    pub const fn is_integer(self) -> bool {
        !matches!(self, Self::F32 | Self::F64)
    }
}

/// A named per-particle attribute that the crate does not interpret (density, pressure, texture
/// coordinates, a vorticity vector...), kept so that files round-trip without losing anything.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Attribute {
    /// Name as found in the file.
    pub name: String,
    /// Type as found in the file.
    pub kind: ScalarKind,
    /// Values per particle: 1 for a scalar, 3 for a vector.
    pub components: usize,
    /// `components` values per particle, particle after particle.
    pub values: Vec<f64>,
}

impl Attribute {
    /// A scalar attribute.
    #[must_use]
    pub fn scalar(name: impl Into<String>, kind: ScalarKind, values: Vec<f64>) -> Self {
        Self {
            name: name.into(),
            kind,
            components: 1,
            values,
        }
    }

    /// The values of particle `i`.
    #[must_use]
    pub fn of(&self, i: usize) -> &[f64] {
        &self.values[i * self.components..(i + 1) * self.components]
    }

    /// Smallest and largest value over all particles and components (NaN ignored), `None` when
    /// empty.
    #[must_use]
    pub fn range(&self) -> Option<(f64, f64)> {
        self.values
            .iter()
            .filter(|v| !v.is_nan())
            .fold(None, |acc, &v| match acc {
                None => Some((v, v)),
                Some((lo, hi)) => Some((lo.min(v), hi.max(v))),
            })
    }
}

/// Particles of one simulation frame.
///
/// Only `positions` is required. Every optional attribute, when present, has exactly one entry
/// per particle ([`ParticleSet::validate`] checks this).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ParticleSet {
    /// Particle centres, in the simulation's length unit.
    pub positions: Vec<Vec3>,
    /// Stable particle ids: the same physical particle keeps its id from frame to frame, which
    /// lets per-particle state (the surface detector's hysteresis) follow it when the order changes.
    pub ids: Option<Vec<u32>>,
    /// Particle masses; stages treat all masses as equal when absent.
    pub masses: Option<Vec<f32>>,
    /// Particle velocities.
    pub velocities: Option<Vec<Vec3>>,
    /// Unit normals (for surface particles or surfels).
    pub normals: Option<Vec<Vec3>>,
    /// 8-bit RGB colours.
    pub colours: Option<Vec<[u8; 3]>>,
    /// Attributes kept from the file that the crate does not interpret.
    pub extra: Vec<Attribute>,
}

/// A borrowed view of what the pipeline reads of a frame: positions and, when known, ids and
/// masses. [`crate::pipeline::Pipeline::frame`] and surface detection take anything that turns
/// into one: a `&ParticleSet`, or slices a caller holds elsewhere (a binding's arrays, a
/// simulation's own buffers), which are then read where they lie, without a copy.
#[derive(Clone, Copy, Debug, Default)]
pub struct ParticleView<'a> {
    /// Particle centres.
    pub positions: &'a [Vec3],
    /// Stable ids (see [`ParticleSet::ids`]).
    pub ids: Option<&'a [u32]>,
    /// Masses; all equal when absent.
    pub masses: Option<&'a [f32]>,
}

impl<'a> From<&'a ParticleSet> for ParticleView<'a> {
    fn from(set: &'a ParticleSet) -> Self {
        set.view()
    }
}

impl<'a> ParticleView<'a> {
    /// Positions only.
    #[must_use]
    pub fn of_positions(positions: &'a [Vec3]) -> Self {
        Self {
            positions,
            ..Self::default()
        }
    }

    /// Number of particles.
    #[must_use]
    pub fn len(&self) -> usize {
        self.positions.len()
    }

    /// True when there is no particle.
    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.positions.is_empty()
    }

    /// Mass of particle `i`, 1 when there are no masses.
    #[must_use]
    #[inline]
    pub fn mass(&self, i: usize) -> f32 {
        self.masses.map_or(1.0, |m| m[i])
    }

    /// Stable id of particle `i`: its id when there are ids, else its index.
    #[must_use]
    #[inline]
    pub fn id(&self, i: usize) -> u32 {
        self.ids.map_or(i as u32, |ids| ids[i])
    }

    /// Checks that ids and masses have one entry per particle, that positions are finite and
    /// that ids are unique.
    pub fn validate(&self) -> Result<(), ParticleSetError> {
        let n = self.len();
        check_length("id", n, self.ids.map(<[u32]>::len))?;
        check_length("mass", n, self.masses.map(<[f32]>::len))?;
        if let Some(index) = self.positions.iter().position(|p| !p.is_finite()) {
            return Err(ParticleSetError::NonFinitePosition {
                index,
                position: self.positions[index].to_array(),
            });
        }
        if let Some(ids) = self.ids {
            let mut order: Vec<usize> = (0..n).collect();
            order.sort_unstable_by_key(|&i| ids[i]);
            for w in order.windows(2) {
                if ids[w[0]] == ids[w[1]] {
                    return Err(ParticleSetError::DuplicateId {
                        id: ids[w[0]],
                        first: w[0].min(w[1]),
                        second: w[0].max(w[1]),
                    });
                }
            }
        }
        Ok(())
    }
}

/// An attribute's entry count against the particle count.
fn check_length(name: &str, expected: usize, found: Option<usize>) -> Result<(), ParticleSetError> {
    match found {
        Some(found) if found != expected => Err(ParticleSetError::LengthMismatch {
            attribute: name.to_owned(),
            expected,
            found,
        }),
        _ => Ok(()),
    }
}

/// What [`ParticleSet::validate`] found wrong.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ParticleSetError {
    /// An attribute has a different number of entries than there are particles.
    #[error("attribute `{attribute}` has {found} entries but there are {expected} particles")]
    LengthMismatch {
        attribute: String,
        expected: usize,
        found: usize,
    },
    /// A position is NaN or infinite.
    #[error("particle {index} has a non-finite position {position:?}")]
    NonFinitePosition { index: usize, position: [f32; 3] },
    /// Two particles share an id.
    #[error("particle id {id} appears more than once (particles {first} and {second})")]
    DuplicateId {
        id: u32,
        first: usize,
        second: usize,
    },
}

impl ParticleSet {
    /// Turns the set by `rotation` about the origin: positions, velocities and normals (the
    /// other attributes are left as they are). With [`crate::view::UpAxis::to_y_up`], data of a
    /// z-up tool becomes the y-up data the pipeline's pools, light and sky assume.
    pub fn rotate(&mut self, rotation: glam::Quat) {
        for p in &mut self.positions {
            *p = rotation * *p;
        }
        for v in self.velocities.iter_mut().chain(self.normals.iter_mut()) {
            for x in v.iter_mut() {
                *x = rotation * *x;
            }
        }
    }

    /// A set holding only positions.
    #[must_use]
    pub fn from_positions(positions: Vec<Vec3>) -> Self {
        Self {
            positions,
            ..Self::default()
        }
    }

    /// The view the pipeline reads: positions, ids and masses, borrowed.
    #[must_use]
    pub fn view(&self) -> ParticleView<'_> {
        ParticleView {
            positions: &self.positions,
            ids: self.ids.as_deref(),
            masses: self.masses.as_deref(),
        }
    }

    /// Number of particles.
    #[must_use]
    pub fn len(&self) -> usize {
        self.positions.len()
    }

    /// True when the set holds no particle.
    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.positions.is_empty()
    }

    /// Mass of particle `i`, 1 when the set has no masses.
    #[must_use]
    #[inline]
    pub fn mass(&self, i: usize) -> f32 {
        self.view().mass(i)
    }

    /// Stable id of particle `i`: its id when the set has ids, else its index.
    #[must_use]
    #[inline]
    pub fn id(&self, i: usize) -> u32 {
        self.view().id(i)
    }

    /// Looks up an extra attribute by name.
    #[must_use]
    pub fn attribute(&self, name: &str) -> Option<&Attribute> {
        self.extra.iter().find(|a| a.name == name)
    }

    /// Axis-aligned bounds `(min, max)` of the positions, `None` for an empty set.
    #[must_use]
    pub fn bounds(&self) -> Option<(Vec3, Vec3)> {
        let first = *self.positions.first()?;
        Some(
            self.positions
                .iter()
                .fold((first, first), |(lo, hi), &p| (lo.min(p), hi.max(p))),
        )
    }

    /// The subset of particles whose indices are given, with all attributes.
    #[must_use]
    pub fn select(&self, indices: &[usize]) -> Self {
        fn pick<T: Copy>(v: &Option<Vec<T>>, idx: &[usize]) -> Option<Vec<T>> {
            v.as_ref().map(|v| idx.iter().map(|&i| v[i]).collect())
        }
        Self {
            positions: indices.iter().map(|&i| self.positions[i]).collect(),
            ids: pick(&self.ids, indices),
            masses: pick(&self.masses, indices),
            velocities: pick(&self.velocities, indices),
            normals: pick(&self.normals, indices),
            colours: pick(&self.colours, indices),
            extra: self
                .extra
                .iter()
                .map(|a| Attribute {
                    name: a.name.clone(),
                    kind: a.kind,
                    components: a.components,
                    values: indices
                        .iter()
                        .flat_map(|&i| a.of(i).iter().copied())
                        .collect(),
                })
                .collect(),
        }
    }

    /// The particles inside the box `[lo, hi]` (bounds included), with all attributes, and how
    /// many were outside: what a leaked particle far from the fluid needs before the set can be
    /// gridded (splashsurf's particle AABB filter; `--bounds` on the command line).
    #[must_use]
    pub fn crop(&self, lo: Vec3, hi: Vec3) -> (Self, usize) {
        let inside: Vec<usize> = (0..self.len())
            .filter(|&i| {
                let p = self.positions[i];
                p.cmpge(lo).all() && p.cmple(hi).all()
            })
            .collect();
        let outside = self.len() - inside.len();
        (self.select(&inside), outside)
    }

    /// Checks that every attribute has one entry per particle, that positions are finite and
    /// that ids are unique.
    pub fn validate(&self) -> Result<(), ParticleSetError> {
        let n = self.len();
        check_length("id", n, self.ids.as_ref().map(Vec::len))?;
        check_length("mass", n, self.masses.as_ref().map(Vec::len))?;
        check_length("velocity", n, self.velocities.as_ref().map(Vec::len))?;
        check_length("normal", n, self.normals.as_ref().map(Vec::len))?;
        check_length("colour", n, self.colours.as_ref().map(Vec::len))?;
        for a in &self.extra {
            if a.components == 0 || !a.values.len().is_multiple_of(a.components) {
                return Err(ParticleSetError::LengthMismatch {
                    attribute: a.name.clone(),
                    expected: n * a.components.max(1),
                    found: a.values.len(),
                });
            }
            check_length(&a.name, n, Some(a.values.len() / a.components))?;
        }
        // finite positions and unique ids
        self.view().validate()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn validate_catches_each_defect() {
        let mut set = ParticleSet::from_positions(vec![Vec3::ZERO, Vec3::ONE]);
        assert!(set.validate().is_ok());
        set.masses = Some(vec![1.0]);
        assert!(matches!(
            set.validate(),
            Err(ParticleSetError::LengthMismatch { .. })
        ));
        set.masses = None;
        set.ids = Some(vec![7, 7]);
        assert_eq!(
            set.validate(),
            Err(ParticleSetError::DuplicateId {
                id: 7,
                first: 0,
                second: 1
            })
        );
        set.ids = None;
        set.positions[1].y = f32::NAN;
        assert!(matches!(
            set.validate(),
            Err(ParticleSetError::NonFinitePosition { index: 1, .. })
        ));
    }

    #[test]
    fn select_keeps_attributes_aligned() {
        let mut set = ParticleSet::from_positions(vec![Vec3::X, Vec3::Y, Vec3::Z]);
        set.ids = Some(vec![10, 11, 12]);
        set.extra.push(Attribute::scalar(
            "density",
            ScalarKind::F32,
            vec![1.0, 2.0, 3.0],
        ));
        set.extra.push(Attribute {
            name: "vorticity".into(),
            kind: ScalarKind::F32,
            components: 3,
            values: (0..9).map(f64::from).collect(),
        });
        let sub = set.select(&[2, 0]);
        assert_eq!(sub.positions, vec![Vec3::Z, Vec3::X]);
        assert_eq!(sub.ids, Some(vec![12, 10]));
        assert_eq!(sub.extra[0].values, vec![3.0, 1.0]);
        assert_eq!(sub.extra[1].values, vec![6.0, 7.0, 8.0, 0.0, 1.0, 2.0]);
        assert!(sub.validate().is_ok());
    }
}
