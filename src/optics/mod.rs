//! Stage 5, optics (Iwasaki et al. §5, after Nishita & Nakamae 1994 and Iwasaki et al. 2003):
//! caustics through illumination volumes, then refraction and reflection in the final image, all
//! from the point-sampled water surface without a mesh.
//!
//! * [`OpticsScene`]: what a frame needs besides the surfels (camera, light, receiver, water,
//!   environment, parameters), a serde type read from TOML scene files.
//! * [`Stage`]: the scene resolved for one set of surfels: the receiver's triangles and BVH, the
//!   environment, the light's virtual screen and caustics-map views.
//! * [`caustics_cpu`] and [`frame_cpu`]: the CPU reference (exact ray-triangle intersection in an
//!   obvhs BVH of the receiver), the specification the GPU path ([`crate::optics::gpu`]) is
//!   tested against. Both share the functions of this module ([`refract`], [`fresnel_reflectance`],
//!   [`Environment::colour`], [`Stage::albedo`]), mirrored name for name in `shaders/optics.wgsl`.
//!
//! ## The caustics map
//!
//! §5.1: the virtual screen faces the light; per pixel, eq. 2 gives the water point `s` and normal
//! `n` (the splatting of [`crate::splat`] from the light's view); the light refracts at `s`
//! (Snell) and meets the receiver at `c`. Neighbouring pixels make two triangles per screen cell;
//! the caustics triangle `c0 c1 c2` receives the flux that crosses the water triangle
//! `s0 s1 s2`. Eq. 3 writes its irradiance as
//! `L_i cos(theta_i) T exp(-sigma_t l) (S / S_c)`: the flux through the water triangle,
//! `L_i cos(theta_i) S`, spread over the caustics triangle's area `S_c`. With `theta_i` measured
//! against the water triangle's own normal, `cos(theta_i) S` is the triangle's area projected
//! across the light, which for a directional light is exactly its screen triangle. This module
//! uses that exact form (derived from eq. 3, not a change of it): the incident flux of a triangle
//! is `E_perp |((s1 - s0) x (s2 - s0)) . i| / 2`, the transmitted flux is that times the mean of
//! `T exp(-sigma_t l)` over its three vertices (per colour channel).
//!
//! Drawing the caustics triangles with the irradiance `flux / S_c` at texel centres (the paper's
//! additive rasterisation) loses the flux of every triangle smaller than a texel, and near a focus
//! all of them are. The map therefore stores flux per texel: a triangle covering `k` texel centres
//! adds `flux / k` to each, and one covering none adds its flux to the texel of its centroid. The
//! map's total is the transmitted flux exactly (flux is conserved by construction, tested), and
//! the irradiance at a texel is its flux over the receiver area the texel covers.
//!
//! The map is parameterised like the paper's geometry map: texels of a view from the light (an
//! orthographic one for a directional light, a perspective one for a point light) over the
//! receiver and the water. Caustics land on what the light sees; receiver surfaces hidden from the
//! light (a wall parallel to a vertical light) receive none, as in any light-space caustics map.
//!
//! ## Shading the receiver
//!
//! The receiver's irradiance at a point is the direct light where the water does not cover it
//! (the light's view of the water, compared in depth) and the receiver does not shadow itself
//! (a shadow-map test in the caustics map's geometry), plus the caustics map's irradiance: light
//! through the water is redistributed, never added. Its radiance is eq. 3's `f_r E + L_a`.

// `!(x > 0.0)` on purpose throughout: NaN compares false and is rejected with the rest
#![allow(clippy::neg_cmp_op_on_partial_ord)]

mod cpu;
pub mod gpu;
pub mod receiver;

use std::path::PathBuf;

use glam::{Vec2, Vec3};
use serde::{Deserialize, Serialize};

use crate::splat::{Camera, SplatError, SplatParams, Surfel, View};

pub use cpu::{
    Caustics, FrameImage, ReceiverViews, caustics_cpu, caustics_of, caustics_reusing, frame_cpu,
    frame_of, frame_reusing, receiver_irradiance,
};
pub use receiver::{Container, Nearest, Receiver, ReceiverGeometry, ReceiverKind};

/// Errors of the optics stage.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum OpticsError {
    /// A parameter outside its range.
    #[error("invalid optics parameter `{name}`: {reason}")]
    InvalidParameter { name: &'static str, reason: String },
    /// A file of the scene (mesh, environment image, scene file) could not be used.
    #[error("{path}: {reason}")]
    File { path: PathBuf, reason: String },
    /// The splatting of the water surface.
    #[error(transparent)]
    Splat(#[from] SplatError),
}

fn invalid(name: &'static str, reason: impl Into<String>) -> OpticsError {
    OpticsError::InvalidParameter {
        name,
        reason: reason.into(),
    }
}

/// Which light.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LightKind {
    /// Parallel light (the sun): `direction` points towards it.
    #[default]
    Directional,
    /// A point light at `position`; its irradiance falls off as `1 / r^2`.
    Point,
}

/// The light of the optics stage.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct OpticsLight {
    pub kind: LightKind,
    /// Direction towards a directional light (need not be unit length).
    pub direction: Vec3,
    /// Position of a point light.
    pub position: Vec3,
    /// `L_i` of eq. 3, linear RGB: irradiance across the beam of a directional light, intensity
    /// (irradiance at unit distance) of a point light.
    pub colour: Vec3,
    /// `L_a` of eq. 3: ambient radiance added to the receiver.
    pub ambient: Vec3,
}

impl Default for OpticsLight {
    fn default() -> Self {
        Self {
            kind: LightKind::Directional,
            direction: Vec3::new(0.2, 1.0, 0.3),
            position: Vec3::new(0.0, 2.0, 0.0),
            colour: Vec3::ONE,
            ambient: Vec3::splat(0.04),
        }
    }
}

/// The water.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Water {
    /// Index of refraction (air outside: 1), in [0.25, 4]. Below 1 the medium is thinner than
    /// air outside it (an air pocket seen from the water), and total internal reflection occurs.
    pub ior: f32,
    /// `sigma_t` of eq. 3 per colour channel, per unit length of the scene (metres for the
    /// built-in scenes). Default: pure water's absorption (Pope and Fry 1997, at 650, 550 and
    /// 450 nm: 0.35, 0.0565, 0.0145 per metre) rounded.
    pub extinction: Vec3,
}

impl Default for Water {
    fn default() -> Self {
        Self {
            ior: 1.33,
            extinction: Vec3::new(0.35, 0.057, 0.015),
        }
    }
}

/// What reflected rays (and rays that leave the scene) see.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum EnvironmentKind {
    /// One colour everywhere.
    Constant,
    /// `ground` below the horizon, `horizon` to `zenith` above it.
    #[default]
    Gradient,
    /// An equirectangular (longitude-latitude) image, `image`.
    Image,
}

/// A loaded environment image: width, height, linear RGBA rows from the top, shared.
pub type EnvironmentPixels = (u32, u32, std::sync::Arc<Vec<[f32; 4]>>);

/// The environment seen in reflections.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Environment {
    pub kind: EnvironmentKind,
    /// The colour of a constant environment (linear RGB).
    pub colour: Vec3,
    pub horizon: Vec3,
    pub zenith: Vec3,
    pub ground: Vec3,
    /// An equirectangular PNG or JPEG (sRGB), for `kind = "image"`.
    pub image: Option<PathBuf>,
    /// The loaded image: width, height, linear RGB rows from the top (not serialised).
    #[serde(skip)]
    /// Shared, so that the scene clones a sequence makes per frame do not copy the image.
    pub pixels: Option<EnvironmentPixels>,
}

impl Default for Environment {
    fn default() -> Self {
        Self {
            kind: EnvironmentKind::Gradient,
            colour: Vec3::new(0.6, 0.7, 0.85),
            horizon: Vec3::new(0.75, 0.82, 0.9),
            zenith: Vec3::new(0.25, 0.45, 0.8),
            ground: Vec3::new(0.3, 0.28, 0.25),
            image: None,
            pixels: None,
        }
    }
}

impl Environment {
    /// Loads `image` for `kind = "image"` (a no-op otherwise).
    pub fn load(&mut self) -> Result<(), OpticsError> {
        if self.kind != EnvironmentKind::Image || self.pixels.is_some() {
            return Ok(());
        }
        let path = self
            .image
            .clone()
            .ok_or_else(|| invalid("environment.image", "kind = \"image\" needs an image path"))?;
        let img = image::open(&path)
            .map_err(|e| OpticsError::File {
                path: path.clone(),
                reason: e.to_string(),
            })?
            .to_rgba32f();
        let (w, h) = img.dimensions();
        if w == 0 || h == 0 || w > 16384 || h > 16384 {
            return Err(OpticsError::File {
                path,
                reason: format!("image size {w}x{h} must be between 1 and 16384"),
            });
        }
        let to_linear = |c: f32| c.max(0.0).powf(2.2);
        let pixels = img
            .pixels()
            .map(|p| [to_linear(p[0]), to_linear(p[1]), to_linear(p[2]), 1.0])
            .collect();
        self.pixels = Some((w, h, std::sync::Arc::new(pixels)));
        Ok(())
    }

    /// The colour seen along `dir` (unit), `env_colour` in the WGSL. An image not yet loaded reads
    /// as the constant colour.
    #[must_use]
    pub fn colour(&self, dir: Vec3) -> Vec3 {
        match self.kind {
            EnvironmentKind::Constant => self.colour,
            EnvironmentKind::Gradient => {
                if dir.y < 0.0 {
                    self.ground
                } else {
                    self.horizon.lerp(self.zenith, dir.y.min(1.0))
                }
            }
            EnvironmentKind::Image => match &self.pixels {
                Some((w, h, pixels)) => {
                    let (x, y) = equirect_texel(dir, *w, *h);
                    Vec3::from_slice(&pixels[(y * w + x) as usize][..3])
                }
                None => self.colour,
            },
        }
    }

    fn validate(&self) -> Result<(), OpticsError> {
        if !(self.colour.is_finite()
            && self.horizon.is_finite()
            && self.zenith.is_finite()
            && self.ground.is_finite())
        {
            return Err(invalid("environment", "colours must be finite"));
        }
        Ok(())
    }
}

/// The texel of an equirectangular image seen along `dir` (nearest), `equirect_texel` in the WGSL.
#[must_use]
pub fn equirect_texel(dir: Vec3, w: u32, h: u32) -> (u32, u32) {
    let u = dir.x.atan2(-dir.z) / std::f32::consts::TAU + 0.5;
    let v = dir.y.clamp(-1.0, 1.0).acos() / std::f32::consts::PI;
    let x = ((u * w as f32) as i64).clamp(0, i64::from(w) - 1) as u32;
    let y = ((v * h as f32) as i64).clamp(0, i64::from(h) - 1) as u32;
    (x, y)
}

/// Parameters of the optics stage.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct OpticsParams {
    /// The virtual screen (§5.1) in pixels. Default: 256 along the longer side of the water as the
    /// light sees it, the other side in proportion (the paper's 256x64 is this rule for its 4:1
    /// wave tank).
    pub caustics_resolution: Option<[u32; 2]>,
    /// The caustics map in texels. Default: 512 along the longer side of the receiver as the light
    /// sees it, the other side in proportion.
    pub map_resolution: Option<[u32; 2]>,
    /// Final image size.
    pub image_size: [u32; 2],
    /// Iterations of the geometry-map search (§5.1.2, GPU path).
    pub max_iterations: u32,
    /// The search's threshold on the distance between the point on the ray and the receiver
    /// point found for it, in pixels of the map searched at that depth (§5.1.2: "specified by
    /// the user").
    pub tolerance: f32,
    /// Water triangles whose depths from the light differ by more than this many screen pixels
    /// (pixel size at their depth) join different surfaces (a drop over the pool) and carry no
    /// light: their caustics triangle would smear it across the receiver.
    pub discontinuity: f32,
    /// Overrides the part of the light's view the virtual screen covers (a world box whose
    /// projection it spans); default: the water's bounds.
    pub screen_bounds: Option<[Vec3; 2]>,
    /// Overrides the whole scene's box (water and receiver) that the caustics map and the
    /// light's depth range cover; default: the bounds of this frame's water and receiver. A
    /// sequence fixes it (with the camera and the pool) so that what does not move renders the
    /// same in every frame ([`crate::pipeline::Pipeline`] does).
    pub scene_bounds: Option<[Vec3; 2]>,
    /// Splatting of the water surface, from the light and from the camera.
    pub splat: SplatParams,
}

impl Default for OpticsParams {
    fn default() -> Self {
        Self {
            caustics_resolution: None,
            map_resolution: None,
            image_size: [512, 512],
            max_iterations: 16,
            tolerance: 0.02,
            discontinuity: 8.0,
            screen_bounds: None,
            scene_bounds: None,
            splat: SplatParams::default(),
        }
    }
}

/// Largest virtual screen or caustics map side.
pub const MAX_MAP: u32 = 4096;

impl OpticsParams {
    fn validate(&self) -> Result<(), OpticsError> {
        for (name, r) in [
            ("caustics_resolution", self.caustics_resolution),
            ("map_resolution", self.map_resolution),
        ] {
            if let Some([w, h]) = r
                && (!(2..=MAX_MAP).contains(&w) || !(2..=MAX_MAP).contains(&h))
            {
                return Err(invalid(
                    name,
                    format!("{w}x{h}: each side must lie in 2..={MAX_MAP}"),
                ));
            }
        }
        let [w, h] = self.image_size;
        if !(1..=crate::splat::MAX_SIZE).contains(&w) || !(1..=crate::splat::MAX_SIZE).contains(&h)
        {
            return Err(invalid("image_size", format!("{w}x{h} is out of range")));
        }
        if !(1..=256).contains(&self.max_iterations) {
            return Err(invalid("max_iterations", "must lie in 1..=256"));
        }
        if !(self.tolerance > 0.0 && self.tolerance <= 10.0) {
            return Err(invalid("tolerance", "must lie in (0, 10] pixels"));
        }
        if !(self.discontinuity > 0.0) {
            return Err(invalid(
                "discontinuity",
                "must be > 0 (use a large value to keep all)",
            ));
        }
        for (name, bounds) in [
            ("screen_bounds", self.screen_bounds),
            ("scene_bounds", self.scene_bounds),
        ] {
            if let Some([a, b]) = bounds
                && !(a.is_finite() && b.is_finite() && b.cmpgt(a).all())
            {
                return Err(invalid(name, "need finite min < max"));
            }
        }
        Ok(())
    }
}

/// Everything a frame needs besides the surfels; the TOML scene file of `render --config`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct OpticsScene {
    /// The camera; default: framing the water and the receiver.
    pub camera: Option<Camera>,
    pub light: OpticsLight,
    pub receiver: Receiver,
    pub water: Water,
    pub environment: Environment,
    pub optics: OpticsParams,
}

impl OpticsScene {
    /// Reads a TOML scene file (relative paths in it are relative to the file).
    pub fn from_toml_file(path: &std::path::Path) -> Result<Self, OpticsError> {
        let file_error = |reason: String| OpticsError::File {
            path: path.to_path_buf(),
            reason,
        };
        let text = std::fs::read_to_string(path).map_err(|e| file_error(e.to_string()))?;
        let mut scene: Self = toml::from_str(&text).map_err(|e| file_error(e.to_string()))?;
        scene.resolve_paths(path.parent().unwrap_or(std::path::Path::new(".")));
        Ok(scene)
    }

    /// Makes the relative paths of the scene (receiver mesh, environment image) relative to
    /// `base`, the folder of the file that named them.
    pub fn resolve_paths(&mut self, base: &std::path::Path) {
        for p in [self.receiver.path.as_mut(), self.environment.image.as_mut()]
            .into_iter()
            .flatten()
        {
            if p.is_relative() {
                *p = base.join(&*p);
            }
        }
    }

    fn validate(&self) -> Result<(), OpticsError> {
        let l = &self.light;
        if !(l.colour.is_finite()
            && l.colour.min_element() >= 0.0
            && l.ambient.is_finite()
            && l.ambient.min_element() >= 0.0)
        {
            return Err(invalid(
                "light",
                "colour and ambient must be finite and >= 0",
            ));
        }
        match l.kind {
            LightKind::Directional => {
                if !(l.direction.is_finite() && l.direction.length_squared() > 1e-20) {
                    return Err(invalid("light.direction", "must be finite and non-zero"));
                }
            }
            LightKind::Point => {
                if !l.position.is_finite() {
                    return Err(invalid("light.position", "must be finite"));
                }
            }
        }
        let w = &self.water;
        if !(w.ior.is_finite() && (0.25..=4.0).contains(&w.ior)) {
            return Err(invalid("water.ior", "must lie in [0.25, 4]"));
        }
        if !(w.extinction.is_finite() && w.extinction.min_element() >= 0.0) {
            return Err(invalid("water.extinction", "must be finite and >= 0"));
        }
        self.environment.validate()?;
        self.optics.validate()
    }
}

/// Refraction of the unit direction `i` at a surface of unit normal `n` facing against `i`, from
/// index `n1` into `n2` (Snell); `None` on total internal reflection. `refract` in the WGSL.
#[must_use]
pub fn refract(i: Vec3, n: Vec3, n1: f32, n2: f32) -> Option<Vec3> {
    let eta = n1 / n2;
    let cos_i = -n.dot(i);
    let k = 1.0 - eta * eta * (1.0 - cos_i * cos_i);
    if k < 0.0 {
        return None;
    }
    Some((eta * i + (eta * cos_i - k.sqrt()) * n).normalize())
}

/// Fresnel reflectance of unpolarised light (the mean of the s and p reflectances, exact, not
/// Schlick's approximation) at incidence cosine `cos_i` from index `n1` into `n2`; 1 on total
/// internal reflection. `T(theta_i, theta_t)` of eq. 3 is `1 - R`. `fresnel_reflectance` in the WGSL.
#[must_use]
pub fn fresnel_reflectance(cos_i: f32, n1: f32, n2: f32) -> f32 {
    let cos_i = cos_i.clamp(0.0, 1.0);
    let sin_t2 = (n1 / n2) * (n1 / n2) * (1.0 - cos_i * cos_i);
    if sin_t2 >= 1.0 {
        return 1.0;
    }
    let cos_t = (1.0 - sin_t2).sqrt();
    let rs = (n1 * cos_i - n2 * cos_t) / (n1 * cos_i + n2 * cos_t);
    let rp = (n2 * cos_i - n1 * cos_t) / (n2 * cos_i + n1 * cos_t);
    let r = 0.5 * (rs * rs + rp * rp);
    if r.is_finite() {
        r.clamp(0.0, 1.0)
    } else {
        1.0
    }
}

/// Linear colour to an 8-bit display value (clamp, gamma 2.2), as the GPU path's read-back.
#[must_use]
pub fn encode(c: Vec3) -> [u8; 3] {
    let f = |x: f32| {
        let x = if x.is_nan() { 0.0 } else { x.clamp(0.0, 1.0) };
        (x.powf(1.0 / 2.2) * 255.0 + 0.5) as u8
    };
    [f(c.x), f(c.y), f(c.z)]
}

/// The light's two views of a stage: the virtual screen over the water, and the caustics map over
/// the receiver and the water. Both share the eye (plane) and axis, so that their depths compare.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LightViews {
    pub screen: View,
    pub map: View,
}

/// The direction (towards the eye) the finished frame's automatic camera looks from: higher than
/// the particle previews' (40 degrees instead of 24), so that it sees into the pool over its
/// walls.
pub const CAMERA_DIRECTION: Vec3 = Vec3::new(0.55, 0.95, 1.0);

/// An [`OpticsScene`] resolved for one set of surfels.
#[derive(Debug)]
pub struct Stage {
    pub scene: OpticsScene,
    pub receiver: ReceiverGeometry,
    pub views: LightViews,
    /// The camera (the scene's, or one framing water and receiver).
    pub camera: Camera,
    /// Diagonal of the scene's bounds.
    pub size: f32,
}

impl Stage {
    /// Checks the scene, builds the receiver (and its BVH), loads the environment image and sets
    /// up the light's views around the surfels ([`Stage::fitted`] for water known by its
    /// shape).
    pub fn new(scene: &OpticsScene, surfels: &[Surfel]) -> Result<Self, OpticsError> {
        Self::fitted(scene, &WaterShape::of_surfels(surfels), None)
    }

    /// [`Stage::new`] for water known by its [`WaterShape`] (its surfels may live on a GPU),
    /// with the pool and the camera fitted to the water's bounds widened to `fit` (the union of
    /// a sequence's frames, say), so that every frame's water lies inside what is fitted; the
    /// light's screen still follows this frame's water.
    pub fn fitted(
        scene: &OpticsScene,
        shape: &WaterShape,
        fit: Option<(Vec3, Vec3)>,
    ) -> Result<Self, OpticsError> {
        scene.validate()?;
        let mut scene = scene.clone();
        scene.environment.load()?;
        let own = shape.drawn;
        let water = crate::view::union_boxes(own, fit);
        let receiver = scene
            .receiver
            .build(water.map(|(a, b)| (a, Vec3::new(b.x, shape.wall_top(a.y, b.y), b.z))))?;
        let (rmin, rmax) = receiver.bounds();
        let (all_min, all_max) = match (scene.optics.scene_bounds, water) {
            (Some([a, b]), _) => (a, b),
            (None, Some((a, b))) => (rmin.min(a), rmax.max(b)),
            (None, None) => (rmin, rmax),
        };
        let size = (all_max - all_min).length().max(1e-6);
        let screen_box = match scene.optics.screen_bounds {
            Some([a, b]) => (a, b),
            None => own.or(water).unwrap_or((all_min, all_max)),
        };
        let views = light_views(&scene, screen_box, (all_min, all_max))?;
        let camera = match scene.camera {
            Some(c) => c,
            // from higher than the particle previews (40 degrees instead of 24), so that the
            // camera sees into the pool over its walls, and close: the box fills the picture
            None => {
                let [w, h] = scene.optics.image_size;
                Camera::fitting(
                    all_min,
                    all_max,
                    CAMERA_DIRECTION,
                    w as f32 / h.max(1) as f32,
                )
            }
        };
        Ok(Self {
            scene,
            receiver,
            views,
            camera,
            size,
        })
    }

    /// Direction of the light's travel at `p` (unit) and the irradiance across it there.
    #[must_use]
    pub fn incoming(&self, p: Vec3) -> (Vec3, Vec3) {
        let l = &self.scene.light;
        match l.kind {
            LightKind::Directional => (-l.direction.normalize(), l.colour),
            LightKind::Point => {
                let d = p - l.position;
                let r2 = d.length_squared().max(1e-12);
                (d / r2.sqrt(), l.colour / r2)
            }
        }
    }

    /// Whether the receiver lies between `p` and the light: an opaque wall shading a water point,
    /// which then receives no light to refract (exact, by a ray towards the light).
    #[must_use]
    pub fn light_blocked(&self, p: Vec3, eps: f32) -> bool {
        let (dir, _) = self.incoming(p);
        match self.receiver.intersect(p, -dir, eps) {
            None => false,
            Some(h) => match self.scene.light.kind {
                LightKind::Directional => true,
                LightKind::Point => h.t < (self.scene.light.position - p).length(),
            },
        }
    }

    /// Whether the water point `p` is inside the receiver's container (always, for a receiver
    /// that is no container). `holds_water` in the WGSL.
    #[must_use]
    pub fn holds_water(&self, p: Vec3) -> bool {
        self.receiver.holds(p)
    }

    /// The receiver's diffuse reflectance `f_r` at `p` with normal `n` (a checkerboard when
    /// `checker > 0`, in the plane across the normal's dominant axis). `receiver_albedo` in the WGSL.
    #[must_use]
    pub fn albedo(&self, p: Vec3, n: Vec3) -> Vec3 {
        let r = &self.scene.receiver;
        if r.checker <= 0.0 {
            return r.albedo;
        }
        let cell = (checker_coordinates(p, n) / r.checker).floor();
        let odd = (cell.x + cell.y).rem_euclid(2.0) >= 0.5;
        if odd { r.albedo * 0.55 } else { r.albedo }
    }
}

/// The receiver's checkerboard coordinates of `p` on a surface of normal `n`: the two axes across
/// the normal's dominant one (`receiver_albedo` in the WGSL picks them the same way).
#[must_use]
pub fn checker_coordinates(p: Vec3, n: Vec3) -> Vec2 {
    let a = n.abs();
    if a.y >= a.x && a.y >= a.z {
        Vec2::new(p.x, p.z)
    } else if a.x >= a.z {
        Vec2::new(p.y, p.z)
    } else {
        Vec2::new(p.x, p.y)
    }
}

/// Where a frame's water is, as the views and the automatic pool are fitted to it: known from
/// its surfels on the CPU ([`WaterShape::of_surfels`]), or before them from its particles (the
/// chain on a GPU, whose surfels never come back to the CPU: `pipeline::GpuPipeline`).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct WaterShape {
    /// The box of what is drawn (the surfels' disks, the spheres of the peer renderers).
    pub drawn: Option<(Vec3, Vec3)>,
    /// The box of the water's surface, which an automatic pool's walls meet (the drawn box,
    /// but for spheres whose iso-surface lies inside them).
    pub surface: Option<(Vec3, Vec3)>,
    /// The height of the water's free surface: the median height of its upward-facing part
    /// (normal within 60 degrees of +y), which the few tops of drops and splashes do not move.
    pub level: Option<f32>,
}

impl WaterShape {
    /// The shape of drawn `surfels`: their box, and the level of the upward-facing ones.
    #[must_use]
    pub fn of_surfels(surfels: &[Surfel]) -> Self {
        let drawn = crate::splat::bounds(surfels);
        let up = surfels
            .iter()
            .filter(|s| s.is_drawable() && Vec3::from(s.normal).normalize_or_zero().y > 0.5)
            .map(|s| s.position[1]);
        Self {
            drawn,
            surface: drawn,
            level: median(up.collect()),
        }
    }

    /// The top of an automatic pool's walls: 1.2x the water's level above its bottom `floor`
    /// (half way to `top` without a level), at most `top`. The water's bounding box would put
    /// the walls halfway up a splash (the dam break's climbs to 4 over a body 0.6 deep, and
    /// walls 2 high hid the water from every camera).
    #[must_use]
    pub fn wall_top(&self, floor: f32, top: f32) -> f32 {
        match self.level {
            None => floor + 0.5 * (top - floor),
            Some(level) => (floor + 1.2 * (level - floor)).min(top),
        }
    }
}

/// The median of `values` (the upper one of an even count); `None` when there is none.
#[must_use]
pub fn median(mut values: Vec<f32>) -> Option<f32> {
    if values.is_empty() {
        return None;
    }
    let mid = values.len() / 2;
    let (_, m, _) = values.select_nth_unstable_by(mid, f32::total_cmp);
    Some(*m)
}

/// The light's virtual screen (Iwasaki et al. §5.1) around the water's box `water` in a scene
/// whose box is `all`: the view the caustics sample the water's surface from (a texel of the
/// screen is a ray refracted through the surface), as [`Stage::fitted`] sets it up, known
/// before the water's surfels are (to choose the detail the caustics need).
pub fn light_screen(
    scene: &OpticsScene,
    water: (Vec3, Vec3),
    all: (Vec3, Vec3),
) -> Result<View, OpticsError> {
    Ok(light_views(scene, water, all)?.screen)
}

/// Sets up the screen and map views of the light around the water box and the whole scene box.
fn light_views(
    scene: &OpticsScene,
    screen_box: (Vec3, Vec3),
    all: (Vec3, Vec3),
) -> Result<LightViews, OpticsError> {
    let p = &scene.optics;
    let light = &scene.light;
    let corners = |(a, b): (Vec3, Vec3)| crate::view::box_corners(a, b).into_iter();
    let size = (all.1 - all.0).length().max(1e-6);
    let resolution = |given: Option<[u32; 2]>, half: Vec2, long: u32| -> [u32; 2] {
        given.unwrap_or_else(|| {
            let aspect = half.x / half.y;
            if aspect >= 1.0 {
                [long, ((long as f32 / aspect).round() as u32).clamp(2, long)]
            } else {
                [((long as f32 * aspect).round() as u32).clamp(2, long), long]
            }
        })
    };
    let orthographic = light.kind == LightKind::Directional;
    let (eye_base, forward) = if orthographic {
        (Vec3::ZERO, -light.direction.normalize())
    } else {
        let centre = (screen_box.0 + screen_box.1) * 0.5;
        let f = (centre - light.position)
            .try_normalize()
            .ok_or_else(|| invalid("light.position", "is at the centre of the water"))?;
        (light.position, f)
    };
    let up = if forward.y.abs() > 0.99 {
        Vec3::NEG_Z
    } else {
        Vec3::Y
    };
    let right = forward.cross(up).normalize();
    let upv = right.cross(forward);
    if orthographic {
        // depth range over the whole scene; eye plane a margin before it
        let (zmin, zmax) = corners(all)
            .map(|c| c.dot(forward))
            .fold((f32::MAX, f32::MIN), |(a, b), z| (a.min(z), b.max(z)));
        let margin = 0.05 * size;
        let window = |b: (Vec3, Vec3), pad: f32| {
            let (mn, mx) = corners(b)
                .map(|c| Vec2::new(c.dot(right), c.dot(upv)))
                .fold((Vec2::MAX, Vec2::MIN), |(a, m), q| (a.min(q), m.max(q)));
            let centre = (mn + mx) * 0.5;
            let half = ((mx - mn) * 0.5 * (1.0 + pad)).max(Vec2::splat(1e-4 * size));
            (centre, half)
        };
        let make = |(centre, half): (Vec2, Vec2), res: [u32; 2]| {
            let eye = right * centre.x + upv * centre.y + forward * (zmin - margin);
            View::window(
                eye,
                forward,
                up,
                half,
                true,
                margin * 0.5,
                zmax - zmin + 2.0 * margin,
                &p.splat,
                res[0],
                res[1],
            )
        };
        let sw = window(screen_box, 0.0);
        let mw = window(all, 0.02);
        Ok(LightViews {
            screen: make(sw, resolution(p.caustics_resolution, sw.1, 256))?,
            map: make(mw, resolution(p.map_resolution, mw.1, 512))?,
        })
    } else {
        let max_tan = 75f32.to_radians().tan();
        let frustum = |b: (Vec3, Vec3)| {
            let mut half = Vec2::splat(1e-3);
            let (mut zn, mut zf) = (f32::MAX, 0f32);
            for c in corners(b) {
                let v = c - eye_base;
                let z = v.dot(forward).max(1e-4 * size);
                half = half.max(Vec2::new(v.dot(right).abs(), v.dot(upv).abs()) / z);
                zn = zn.min(z);
                zf = zf.max(v.length());
            }
            (half.min(Vec2::splat(max_tan)), zn, zf)
        };
        let (sh, _, _) = frustum(screen_box);
        let (mh, zn, zf) = frustum(all);
        let near = (zn * 0.5).max(1e-4 * size);
        let far = zf * 1.5 + 1e-3 * size;
        let make = |half: Vec2, res: [u32; 2]| {
            View::window(
                eye_base, forward, up, half, false, near, far, &p.splat, res[0], res[1],
            )
        };
        Ok(LightViews {
            screen: make(sh, resolution(p.caustics_resolution, sh, 256))?,
            map: make(mh * 1.02, resolution(p.map_resolution, mh, 512))?,
        })
    }
}

/// Receiver area covered by the texel whose ray (`View::world_ray` direction `d`) meets a surface
/// of unit normal `n` at view depth `depth`: the texel's window area at that depth, projected
/// along the ray onto the surface. `texel_area` in the WGSL.
#[must_use]
pub fn texel_area(v: &View, d: Vec3, depth: f32, n: Vec3) -> f32 {
    let half = v.half_extent();
    let window = 4.0 * half.x * half.y / (v.width as f32 * v.height as f32);
    let len = d.length().max(1e-20);
    let cos_surface = (n.dot(d) / len).abs().max(1e-3);
    if v.is_orthographic() {
        window / cos_surface
    } else {
        window * depth * depth / len / cos_surface
    }
}
