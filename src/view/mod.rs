//! Cameras, lights and views: what a renderer needs to know about where the picture is taken
//! from. [`Camera`] (perspective look-at) and [`Light`] (directional, Blinn-Phong) are the
//! serde types users write; [`View`] is a camera, a light and the splatting parameters checked
//! and turned into the matrices, rays and projections that the CPU reference and the WGSL
//! share (`view_ray`, `world_ray`, `project`), for perspective cameras and for the orthographic
//! views of a directional light (the optics stage's virtual screen).

pub mod gpu;

use glam::{Mat4, Vec2, Vec3, Vec4, Vec4Swizzles};
use serde::{Deserialize, Serialize};

use image::RgbaImage;

/// Which axis of a particle file points up. The pipeline is y-up (a pool's floor lies at its
/// lowest y, the sky and the default sunlight come from +y); Houdini and Blender write z-up.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum UpAxis {
    X,
    #[default]
    Y,
    Z,
    NegX,
    NegY,
    NegZ,
}

impl UpAxis {
    /// Every axis, in the order of [`UpAxis::name`]'s names.
    pub const ALL: [Self; 6] = [
        Self::X,
        Self::Y,
        Self::Z,
        Self::NegX,
        Self::NegY,
        Self::NegZ,
    ];

    /// `x`, `y`, `z`, `-x`, `-y`, `-z`.
    #[must_use]
    pub const fn name(self) -> &'static str {
        match self {
            Self::X => "x",
            Self::Y => "y",
            Self::Z => "z",
            Self::NegX => "-x",
            Self::NegY => "-y",
            Self::NegZ => "-z",
        }
    }

    /// The axis as a unit vector.
    #[must_use]
    pub const fn vector(self) -> Vec3 {
        match self {
            Self::X => Vec3::X,
            Self::Y => Vec3::Y,
            Self::Z => Vec3::Z,
            Self::NegX => Vec3::NEG_X,
            Self::NegY => Vec3::NEG_Y,
            Self::NegZ => Vec3::NEG_Z,
        }
    }

    /// The proper rotation (no mirror, so handedness is kept) that turns this axis into +y: a
    /// quarter turn about the axis perpendicular to both, or a half turn about x for `-y`.
    #[must_use]
    pub fn to_y_up(self) -> glam::Quat {
        match self {
            Self::Y => glam::Quat::IDENTITY,
            Self::NegY => glam::Quat::from_rotation_x(std::f32::consts::PI),
            a => glam::Quat::from_rotation_arc(a.vector(), Vec3::Y),
        }
    }
}

/// The field of view of the cameras [`Camera::framing`] and [`Camera::fitting`] make.
const FRAMING_FOV_DEGREES: f32 = 40.0;

/// The smallest box holding both boxes; either may be missing.
#[must_use]
pub fn union_boxes(a: Option<(Vec3, Vec3)>, b: Option<(Vec3, Vec3)>) -> Option<(Vec3, Vec3)> {
    match (a, b) {
        (Some((a0, a1)), Some((b0, b1))) => Some((a0.min(b0), a1.max(b1))),
        (a, b) => a.or(b),
    }
}

/// The smallest box holding `points` widened by `margin` on every side; `None` without points.
#[must_use]
pub fn widened_bounds(points: impl IntoIterator<Item = Vec3>, margin: f32) -> Option<(Vec3, Vec3)> {
    points
        .into_iter()
        .map(|p| (p, p))
        .reduce(|(a, b), (c, d)| (a.min(c), b.max(d)))
        .map(|(a, b)| (a - Vec3::splat(margin), b + Vec3::splat(margin)))
}

/// The eight corners of the box `[min, max]`.
#[must_use]
pub fn box_corners(min: Vec3, max: Vec3) -> [Vec3; 8] {
    std::array::from_fn(|k| {
        Vec3::new(
            if k & 1 == 0 { min.x } else { max.x },
            if k & 2 == 0 { min.y } else { max.y },
            if k & 4 == 0 { min.z } else { max.z },
        )
    })
}

/// A perspective look-at camera (right-handed, y up by default).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Camera {
    /// Eye position (world units).
    pub eye: Vec3,
    /// The point looked at.
    pub target: Vec3,
    /// The up direction.
    pub up: Vec3,
    /// Vertical field of view in degrees, in (0, 180).
    pub fov_y_degrees: f32,
    /// Near clipping distance (world units, > 0).
    pub near: f32,
    /// Far clipping distance (world units, > near).
    pub far: f32,
}

impl Default for Camera {
    fn default() -> Self {
        Self {
            eye: Vec3::new(0.0, 0.0, 3.0),
            target: Vec3::ZERO,
            up: Vec3::Y,
            fov_y_degrees: 40.0,
            near: 0.01,
            far: 100.0,
        }
    }
}

impl Camera {
    /// A camera that frames the box `[min, max]` from the front, right and above, the same
    /// direction as the particle previews; near and far planes bracket the box.
    #[must_use]
    pub fn framing(min: Vec3, max: Vec3) -> Self {
        let radius = ((max - min).length() * 0.5).max(1e-6);
        let distance = radius / (FRAMING_FOV_DEGREES.to_radians() * 0.5).sin() * 1.05;
        let back = Vec3::new(0.55, 0.5, 1.0).normalize();
        Self::looking_at((min + max) * 0.5, back, distance, radius)
    }

    /// A camera looking from `direction` (towards the eye; y up) as close as it can be with
    /// every corner of the box `[min, max]` inside the view of a picture of `aspect` (width /
    /// height), with 5 % to spare: the box fills the picture instead of its bounding sphere.
    #[must_use]
    pub fn fitting(min: Vec3, max: Vec3, direction: Vec3, aspect: f32) -> Self {
        let centre = (min + max) * 0.5;
        let back = direction.try_normalize().unwrap_or(Vec3::Z);
        let up_hint = if back.y.abs() > 0.99 {
            Vec3::Z
        } else {
            Vec3::Y
        };
        let right = up_hint.cross(back).normalize();
        let up = back.cross(right);
        let tan_y = (FRAMING_FOV_DEGREES.to_radians() * 0.5).tan();
        let aspect = if aspect.is_finite() && aspect > 0.0 {
            aspect
        } else {
            1.0
        };
        let (tan_x, mut distance, mut reach) = (tan_y * aspect, 1e-6f32, 1e-6f32);
        for corner in box_corners(min, max) {
            // the corner's depth in front of the eye is distance - o.back
            let o = corner - centre;
            let along = o.dot(back);
            distance = distance
                .max(along + o.dot(right).abs() / tan_x)
                .max(along + o.dot(up).abs() / tan_y);
            reach = reach.max(o.length());
        }
        Self::looking_at(centre, back, distance * 1.05, reach)
    }

    /// A camera `distance` from `centre` along `back` (unit), looking at it, y up, its near and
    /// far planes bracketing a ball of radius `reach` around the centre.
    fn looking_at(centre: Vec3, back: Vec3, distance: f32, reach: f32) -> Self {
        Self {
            eye: centre + back * distance,
            target: centre,
            up: Vec3::Y,
            fov_y_degrees: FRAMING_FOV_DEGREES,
            near: (distance - 2.0 * reach).max(distance * 1e-3),
            far: distance + 2.0 * reach,
        }
    }

    pub(crate) fn validate(&self) -> Result<(), SplatError> {
        let bad = |name, reason: &str| {
            Err(SplatError::InvalidParameter {
                name,
                reason: reason.to_string(),
            })
        };
        if !(self.eye.is_finite() && self.target.is_finite() && self.up.is_finite()) {
            return bad("camera", "eye, target and up must be finite");
        }
        let forward = self.target - self.eye;
        if forward.length_squared() < 1e-20 || forward.cross(self.up).length_squared() < 1e-20 {
            return bad(
                "camera",
                "eye and target must differ and up must not be parallel to the view direction",
            );
        }
        if !(self.fov_y_degrees > 0.0 && self.fov_y_degrees < 180.0) {
            return bad("fov_y_degrees", "must lie in (0, 180)");
        }
        if !(self.near > 0.0 && self.far > self.near && self.far.is_finite()) {
            return bad("near/far", "need 0 < near < far < infinity");
        }
        Ok(())
    }

    /// World to view transform.
    #[must_use]
    pub fn view(&self) -> Mat4 {
        glam::camera::rh::view::look_at_mat4(self.eye, self.target, self.up)
    }

    /// View to clip transform (WebGPU depth range 0..1).
    #[must_use]
    pub fn projection(&self, aspect: f32) -> Mat4 {
        glam::camera::rh::proj::directx::perspective(
            self.fov_y_degrees.to_radians(),
            aspect,
            self.near,
            self.far,
        )
    }
}

/// A directional light with Blinn-Phong shading.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Light {
    /// Direction towards the light (need not be unit length).
    pub direction: Vec3,
    /// Light colour (linear RGB).
    pub colour: Vec3,
    /// Ambient fraction of the diffuse term, in [0, 1].
    pub ambient: f32,
    /// Specular strength.
    pub specular: f32,
    /// Blinn-Phong exponent.
    pub shininess: f32,
}

impl Default for Light {
    fn default() -> Self {
        Self {
            direction: Vec3::new(0.3, 1.0, 0.5),
            colour: Vec3::ONE,
            ambient: 0.25,
            specular: 0.35,
            shininess: 48.0,
        }
    }
}

/// Everything a render needs besides the surfels: camera, light, parameters and image size,
/// checked, in the form both renderers read.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct View {
    pub width: u32,
    pub height: u32,
    pub(crate) view: Mat4,
    pub(crate) proj: Mat4,
    pub(crate) inv_view: Mat4,
    pub(crate) tan_half: Vec2,
    pub(crate) light_dir: Vec4,
    pub(crate) light_colour: Vec4,
    pub(crate) background: Vec4,
    pub(crate) shininess: f32,
    pub(crate) orthographic: bool,
    pub(crate) depth_offset: f32,
    pub(crate) low_pass: f32,
    pub(crate) max_fragments: u64,
    pub(crate) sharpness: f32,
    pub(crate) mode: SplatMode,
}

impl View {
    /// Checks the inputs and prepares the uniforms.
    pub fn new(
        camera: &Camera,
        light: &Light,
        params: &SplatParams,
        width: u32,
        height: u32,
    ) -> Result<Self, SplatError> {
        if width == 0 || height == 0 || width > MAX_SIZE || height > MAX_SIZE {
            return Err(SplatError::InvalidSize {
                width,
                height,
                max: MAX_SIZE,
            });
        }
        camera.validate()?;
        params.validate()?;
        let direction =
            light
                .direction
                .try_normalize()
                .ok_or_else(|| SplatError::InvalidParameter {
                    name: "light.direction",
                    reason: "must be finite and non-zero".into(),
                })?;
        if !(light.colour.is_finite()
            && light.ambient.is_finite()
            && (0.0..=1.0).contains(&light.ambient)
            && light.specular.is_finite()
            && light.specular >= 0.0
            && light.shininess.is_finite()
            && light.shininess >= 0.0)
        {
            return Err(SplatError::InvalidParameter {
                name: "light",
                reason: "colour finite, ambient in [0, 1], specular and shininess finite and >= 0"
                    .into(),
            });
        }
        let aspect = width as f32 / height as f32;
        let view = camera.view();
        let tan = (camera.fov_y_degrees.to_radians() * 0.5).tan();
        Ok(Self {
            width,
            height,
            view,
            proj: camera.projection(aspect),
            inv_view: view.inverse(),
            tan_half: Vec2::new(tan * aspect, tan),
            light_dir: direction.extend(light.ambient),
            light_colour: light.colour.extend(light.specular),
            background: Vec4::from(params.background),
            shininess: light.shininess,
            orthographic: false,
            // Adams et al.'s spheres have their own epsilon (1.5 h, §4), the disks theirs
            depth_offset: if params.mode == SplatMode::Spheres {
                params.sphere_depth_offset
            } else {
                params.depth_offset
            },
            low_pass: params.low_pass_px,
            max_fragments: params.max_fragments,
            sharpness: params.sharpness,
            mode: params.mode,
        })
    }

    pub(crate) fn viewport(&self) -> Vec2 {
        Vec2::new(self.width as f32, self.height as f32)
    }

    /// Pixel coordinates (origin top left) of a view-space point, and its clip w.
    pub(crate) fn pixels_of(&self, p: Vec3) -> Vec3 {
        let clip = self.proj * p.extend(1.0);
        let ndc = clip.xy() / clip.w;
        let vp = self.viewport();
        Vec3::new(
            (ndc.x + 1.0) * 0.5 * vp.x,
            (1.0 - ndc.y) * 0.5 * vp.y,
            clip.w,
        )
    }

    pub(crate) fn ndc_depth(&self, p: Vec3) -> f32 {
        let clip = self.proj * p.extend(1.0);
        clip.z / clip.w
    }

    /// The view depth `t` of the point on a view ray (`origin + t dir`, see [`View::ray`]) whose
    /// depth-buffer value is `ndc`: the inverse of [`View::ndc_depth`] along the ray
    /// (`linear_depth` in the WGSL). The projections here map view `z` alone to clip `z` and `w`:
    /// `ndc = (Zz z + Wz) / (Zw z + Ww)` with `z = -t`, so `t = (Wz - ndc Ww) / (Zz - ndc Zw)`.
    pub(crate) fn linear_depth(&self, ndc: f32) -> f32 {
        let (z, w) = (self.proj.z_axis, self.proj.w_axis);
        (w.z - ndc * w.w) / (z.z - ndc * z.w)
    }

    /// The view ray through a pixel position, in view space (`view_ray` in the WGSL): origin and
    /// direction. Perspective rays start at the eye with z = -1, so that `origin + t dir` has view
    /// depth `t`; orthographic rays start on the plane z = 0 and run along -z.
    #[must_use]
    pub fn ray(&self, pixel: Vec2) -> (Vec3, Vec3) {
        let vp = self.viewport();
        let ndc = Vec2::new(pixel.x / vp.x * 2.0 - 1.0, 1.0 - pixel.y / vp.y * 2.0);
        if self.orthographic {
            ((ndc * self.tan_half).extend(0.0), Vec3::NEG_Z)
        } else {
            (Vec3::ZERO, (ndc * self.tan_half).extend(-1.0))
        }
    }

    /// The world-space ray through a pixel position: origin and direction (not normalised;
    /// `origin + t dir` lies at view depth `t`).
    #[must_use]
    pub fn world_ray(&self, pixel: Vec2) -> (Vec3, Vec3) {
        let (o, d) = self.ray(pixel);
        (
            (self.inv_view * o.extend(1.0)).xyz(),
            (self.inv_view * d.extend(0.0)).xyz(),
        )
    }

    /// Pixel coordinates (origin top left) and view depth of a world point (depth <= 0: behind).
    #[must_use]
    pub fn project(&self, world: Vec3) -> Vec3 {
        let p = (self.view * world.extend(1.0)).xyz();
        let q = self.pixels_of(p);
        Vec3::new(q.x, q.y, -p.z)
    }

    /// The screen's 16x16 tiles ([`TILE`]) along x and y, the last of each partial.
    #[must_use]
    pub fn tiles(&self) -> (usize, usize) {
        (
            (self.width as usize).div_ceil(TILE),
            (self.height as usize).div_ceil(TILE),
        )
    }

    /// Whether the view is orthographic.
    #[must_use]
    pub fn is_orthographic(&self) -> bool {
        self.orthographic
    }

    /// A view looking from `eye` along `forward`, `up` roughly up, whose window spans
    /// `half_extent` either side of the axis: world units for an orthographic view (a directional
    /// light's virtual screen, Iwasaki et al. §5.1, Fig. 3), tangents of the half angles for a
    /// perspective one (a point light's). Depths `near..far` from the eye('s plane).
    #[allow(clippy::too_many_arguments)]
    pub fn window(
        eye: Vec3,
        forward: Vec3,
        up: Vec3,
        half_extent: Vec2,
        orthographic: bool,
        near: f32,
        far: f32,
        params: &SplatParams,
        width: u32,
        height: u32,
    ) -> Result<Self, SplatError> {
        let camera = Camera {
            eye,
            target: eye + forward,
            up,
            fov_y_degrees: 60.0,
            near,
            far,
        };
        let mut v = Self::new(&camera, &Light::default(), params, width, height)?;
        if !(half_extent.x > 0.0 && half_extent.y > 0.0 && half_extent.is_finite()) {
            return Err(SplatError::InvalidParameter {
                name: "half_extent",
                reason: "must be finite and > 0".into(),
            });
        }
        v.orthographic = orthographic;
        v.tan_half = half_extent;
        let (x, y) = (half_extent.x, half_extent.y);
        v.proj = if orthographic {
            glam::camera::rh::proj::directx::orthographic(-x, x, -y, y, near, far)
        } else {
            // glam's right-handed 0..1 perspective with separate horizontal and vertical scales
            let r = far / (near - far);
            Mat4::from_cols(
                Vec4::new(1.0 / x, 0.0, 0.0, 0.0),
                Vec4::new(0.0, 1.0 / y, 0.0, 0.0),
                Vec4::new(0.0, 0.0, r, -1.0),
                Vec4::new(0.0, 0.0, r * near, 0.0),
            )
        };
        Ok(v)
    }

    /// Half extents of the window: tangents of the half angles (perspective) or world units
    /// (orthographic).
    #[must_use]
    pub fn half_extent(&self) -> Vec2 {
        self.tan_half
    }

    /// World-space direction of the view axis (unit).
    #[must_use]
    pub fn forward(&self) -> Vec3 {
        (self.inv_view * Vec4::new(0.0, 0.0, -1.0, 0.0)).xyz()
    }

    /// The view's matrices: world to view, view to world, view to clip.
    #[must_use]
    pub fn matrices(&self) -> (Mat4, Mat4, Mat4) {
        (self.view, self.inv_view, self.proj)
    }
}

/// Side of the square screen tiles that renderers bin spheres into (the ray caster, the screen-space passes).
pub const TILE: usize = 16;

/// The half-open pixel rectangle (columns, rows) that holds the projection of the sphere at `c`
/// of radius `r`: the bounding box of its bounding cube's projected corners (perspective maps
/// convex sets to convex sets). The whole screen when the cube reaches behind the eye; `None`
/// when it lies wholly behind it or off screen.
pub fn sphere_rect(v: &View, c: Vec3, r: f32) -> Option<[usize; 4]> {
    // a sphere of radius 0 covers no pixel centre: its corners are its centre, the pixel span
    // from it to itself is empty (the same answer as below, without the projections)
    if r == 0.0 {
        return None;
    }
    let (w, h) = (v.width as f32, v.height as f32);
    let mut lo = Vec2::splat(f32::INFINITY);
    let mut hi = Vec2::splat(f32::NEG_INFINITY);
    let mut behind = 0;
    for k in 0..8 {
        let s = Vec3::new(
            if k & 1 == 0 { -r } else { r },
            if k & 2 == 0 { -r } else { r },
            if k & 4 == 0 { -r } else { r },
        );
        let q = v.project(c + s);
        // NaN counts as behind
        if q.z.is_nan() || q.z <= 0.0 {
            behind += 1;
            continue;
        }
        lo = lo.min(q.truncate());
        hi = hi.max(q.truncate());
    }
    if behind == 8 {
        return None;
    }
    if behind > 0 {
        lo = Vec2::ZERO;
        hi = Vec2::new(w, h);
    }
    let (x0, x1) = pixel_span(lo.x, hi.x, v.width as usize);
    let (y0, y1) = pixel_span(lo.y, hi.y, v.height as usize);
    (x0 < x1 && y0 < y1).then_some([x0, x1, y0, y1])
}

/// The pixel rectangles of the `n` spheres (centre and radius of sphere `j`), refused when
/// they add up to more pixels than the view's limit or the buffers would not fit in memory.
fn checked_rects(
    v: &View,
    n: usize,
    sphere: impl Fn(usize) -> (Vec3, f32) + Sync,
) -> Result<Vec<Option<[usize; 4]>>, SplatError> {
    use rayon::prelude::*;
    let rects: Vec<Option<[usize; 4]>> = (0..n)
        .into_par_iter()
        .map(|j| {
            let (c, r) = sphere(j);
            sphere_rect(v, c, r)
        })
        .collect();
    let fragments: u128 = rects
        .iter()
        .flatten()
        .map(|r| ((r[1] - r[0]) * (r[3] - r[2])) as u128)
        .sum();
    check_cost(n, fragments, v)?;
    Ok(rects)
}

/// The tiles a pixel rectangle covers, `(first, last)` along x then y (inclusive).
fn tile_range([x0, x1, y0, y1]: [usize; 4]) -> [usize; 4] {
    [x0 / TILE, (x1 - 1) / TILE, y0 / TILE, (y1 - 1) / TILE]
}

/// The `n` spheres (centre and radius of sphere `j`) binned into the screen's 16x16 tiles: tiles
/// along x and each tile's spheres, in index order (so that any per-tile loop is deterministic).
/// Refused when their rectangles add up to more pixels than the view's limit or the buffers
/// would not fit in memory. The CPU reference of [`gpu::GpuTiles`].
pub fn bin(
    v: &View,
    n: usize,
    sphere: impl Fn(usize) -> (Vec3, f32) + Sync,
) -> Result<(usize, Vec<Vec<u32>>), SplatError> {
    let rects = checked_rects(v, n, sphere)?;
    let (tw, th) = v.tiles();
    let mut tiles: Vec<Vec<u32>> = vec![Vec::new(); tw * th];
    for (j, r) in rects.iter().enumerate() {
        if let Some(r) = *r {
            let [tx0, tx1, ty0, ty1] = tile_range(r);
            for ty in ty0..=ty1 {
                for tx in tx0..=tx1 {
                    tiles[ty * tw + tx].push(j as u32);
                }
            }
        }
    }
    Ok((tw, tiles))
}

/// What [`bin`] would make of the `n` spheres without making it: its (tile, sphere) pairs in
/// all and the most spheres of one tile (the room [`gpu::GpuTiles`] needs). Refused as `bin`
/// refuses.
pub fn tile_counts(
    v: &View,
    n: usize,
    sphere: impl Fn(usize) -> (Vec3, f32) + Sync,
) -> Result<(u64, usize), SplatError> {
    let rects = checked_rects(v, n, sphere)?;
    let (tw, th) = v.tiles();
    let mut counts = vec![0u32; tw * th];
    let mut pairs = 0u64;
    for r in rects.into_iter().flatten() {
        let [tx0, tx1, ty0, ty1] = tile_range(r);
        pairs += ((tx1 - tx0 + 1) * (ty1 - ty0 + 1)) as u64;
        for ty in ty0..=ty1 {
            for c in &mut counts[ty * tw + tx0..=ty * tw + tx1] {
                *c += 1;
            }
        }
    }
    Ok((pairs, counts.into_iter().max().unwrap_or(0) as usize))
}

/// Errors of surfel rendering.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SplatError {
    /// A parameter is out of range.
    #[error("invalid splatting parameter `{name}`: {reason}")]
    InvalidParameter { name: &'static str, reason: String },
    /// The image size is zero or too large.
    #[error("image size {width}x{height} must be between 1 and {max} on each side")]
    InvalidSize { width: u32, height: u32, max: u32 },
    /// The splats would cover more pixels than the limit: the work grows with the image size
    /// times the splats' screen areas, which a low-pass radius wider than the disks widens
    /// quadratically.
    #[error(
        "the {surfels} splats would cover {fragments} pixel fragments ({} per splat, with a low-pass radius of {low_pass_px} px) at {width}x{height}, over the limit of {limit}: lower the low-pass radius (--low-pass) or the image size, or raise the limit (`SplatParams::max_fragments`, --max-fragments)",
        fragments / (*surfels as u128).max(1)
    )]
    TooCostly {
        surfels: usize,
        fragments: u128,
        limit: u64,
        low_pass_px: f32,
        width: u32,
        height: u32,
    },
}

/// What the splats are drawn as.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SplatMode {
    /// EWA surface splatting (the method).
    #[default]
    Ewa,
    /// Plain point sprites: round screen disks of the projected radius, the nearest wins, no
    /// blending (the baseline the method improves on).
    Sprites,
    /// Particle splatting (Adams, Lenaerts, Dutré 2006, §3): each surfel's position and radius
    /// is a sphere (its normal and stretch are not used, see [`crate::splat::Surfel::sphere`]); the visibility
    /// pass writes the nearest sphere depth (eq. 5) pushed back by `sphere_depth_offset` radii;
    /// the attribute pass blends the per-fragment sphere normals of the spheres within that
    /// distance with the weight `W1 W2` (eqs. 6, 7): the linear fall-off to the projected rim
    /// times the depth fall-off to the shifted depth.
    Spheres,
}

impl SplatMode {
    /// Every mode, in the order of the documentation.
    pub const ALL: [Self; 3] = [Self::Ewa, Self::Sprites, Self::Spheres];

    /// The name used in files and on the command line.
    #[must_use]
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Ewa => "ewa",
            Self::Sprites => "sprites",
            Self::Spheres => "spheres",
        }
    }
}

/// Parameters of the splatting passes.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SplatParams {
    /// Pass 1 depth offset epsilon as a multiple of each surfel's radius. Surfaces closer than
    /// epsilon along the view ray blend; farther behind they are hidden. Default 1.0: neighbouring
    /// disks of one smooth surface differ in depth by a fraction of a radius, while the two sides
    /// of a sheet are at least a particle apart (about two surfel radii for density surfels).
    pub depth_offset: f32,
    /// Radius of the screen-space low-pass filter in pixels (0 switches it off). Default 1.0, the
    /// "about one pixel" of Botsch et al.
    pub low_pass_px: f32,
    /// Gaussian weight `exp(-sharpness * r^2)`, `r = 1` at the disk's rim. Default 2.0 (the rim
    /// at two standard deviations, weight 0.135).
    pub sharpness: f32,
    /// Colour of pixels no surfel covers (linear RGBA).
    pub background: [f32; 4],
    /// EWA splats, plain point sprites, or particle spheres.
    pub mode: SplatMode,
    /// The depth offset epsilon of [`SplatMode::Spheres`] as a multiple of each sphere's
    /// radius. Default 1.5, Adams et al.'s `epsilon = 1.5 h_i` (§4); 0 degenerates to the
    /// nearest sphere alone (no blending, seams between spheres).
    pub sphere_depth_offset: f32,
    /// The most pixel fragments (the sum over splats of the pixels of each one's screen
    /// rectangle, counted before rasterising) a render may cost; more is refused with
    /// [`SplatError::TooCostly`]. Default 10^9, about a minute of the CPU reference on two
    /// cores (measured: 2.3 x 10^9 fragments in 150 s); ordinary frames cost 10^6 to 10^8.
    pub max_fragments: u64,
}

impl Default for SplatParams {
    fn default() -> Self {
        Self {
            depth_offset: 1.0,
            low_pass_px: 1.0,
            sharpness: 2.0,
            background: [0.08, 0.09, 0.11, 1.0],
            mode: SplatMode::Ewa,
            sphere_depth_offset: 1.5,
            max_fragments: 1_000_000_000,
        }
    }
}

impl SplatParams {
    pub(crate) fn validate(&self) -> Result<(), SplatError> {
        let check = |name, ok: bool, reason: &str| {
            if ok {
                Ok(())
            } else {
                Err(SplatError::InvalidParameter {
                    name,
                    reason: reason.to_string(),
                })
            }
        };
        check(
            "depth_offset",
            self.depth_offset >= 0.0 && self.depth_offset.is_finite(),
            "must be finite and >= 0",
        )?;
        check(
            "sphere_depth_offset",
            self.sphere_depth_offset >= 0.0 && self.sphere_depth_offset.is_finite(),
            "must be finite and >= 0",
        )?;
        check(
            "low_pass_px",
            self.low_pass_px >= 0.0 && self.low_pass_px.is_finite(),
            "must be finite and >= 0",
        )?;
        check(
            "sharpness",
            self.sharpness >= 0.0 && self.sharpness.is_finite(),
            "must be finite and >= 0",
        )?;
        check(
            "background",
            self.background.iter().all(|c| c.is_finite()),
            "must be finite",
        )
    }
}

/// Largest image side.
pub const MAX_SIZE: u32 = 16384;

/// The pixel columns (or rows) whose centres lie in `[lo, hi)` of a line of `n` pixels.
pub(crate) fn pixel_span(lo: f32, hi: f32, n: usize) -> (usize, usize) {
    let a = (lo - 0.5).ceil().clamp(0.0, n as f32) as usize;
    let b = (hi - 0.5).ceil().clamp(0.0, n as f32) as usize;
    (a, b)
}

/// Bytes a render holds per pixel: the depth, the accumulated colour and normal-depth, and the
/// image (4 + 16 + 16 + 4), with the read-back copies of the GPU path as much again.
pub const BYTES_PER_PIXEL: u64 = 80;

/// Refuses a render of `fragments` pixel fragments over the view's limit, or whose buffers
/// would not fit in the memory left.
pub(crate) fn check_cost(surfels: usize, fragments: u128, v: &View) -> Result<(), SplatError> {
    let bytes = v.width as u128 * v.height as u128 * BYTES_PER_PIXEL as u128;
    let available = crate::memory::available_memory();
    if bytes > available as u128 {
        return Err(SplatError::InvalidParameter {
            name: "size",
            reason: format!(
                "a {}x{} render needs {} MiB of buffers ({BYTES_PER_PIXEL} bytes a pixel), more than the {} MiB of memory available",
                v.width,
                v.height,
                bytes >> 20,
                available >> 20
            ),
        });
    }
    if fragments > v.max_fragments as u128 {
        return Err(SplatError::TooCostly {
            surfels,
            fragments,
            limit: v.max_fragments,
            low_pass_px: v.low_pass,
            width: v.width,
            height: v.height,
        });
    }
    Ok(())
}

/// A rendered image with the buffers it was made from.
#[derive(Clone, Debug, PartialEq)]
pub struct Render {
    pub width: u32,
    pub height: u32,
    /// The shaded image (8-bit, linear RGB as stored by an `Rgba8Unorm` target).
    pub image: RgbaImage,
    /// Per pixel, row-major from the top: `(sum w colour, sum w)`.
    pub colour: Vec<[f32; 4]>,
    /// Per pixel: `(sum w normal, sum w depth)`.
    pub normal_depth: Vec<[f32; 4]>,
}

impl Render {
    /// Accumulated weight of pixel `i` (0: no surfel covers it).
    #[must_use]
    pub fn weight(&self, i: usize) -> f32 {
        self.colour[i][3]
    }

    /// Number of pixels some surfel covers (weight > 0).
    #[must_use]
    pub fn covered_pixels(&self) -> usize {
        self.colour.iter().filter(|c| c[3] > 0.0).count()
    }

    /// Normalised world normal of pixel `i`, if covered.
    #[must_use]
    pub fn normal(&self, i: usize) -> Option<Vec3> {
        let w = self.weight(i);
        (w > 0.0).then(|| (Vec3::from_slice(&self.normal_depth[i][..3]) / w).normalize_or_zero())
    }

    /// Normalised view depth of pixel `i`, if covered.
    #[must_use]
    pub fn depth(&self, i: usize) -> Option<f32> {
        let w = self.weight(i);
        (w > 0.0).then(|| self.normal_depth[i][3] / w)
    }

    /// Checks the buffers: right sizes, every value finite, weights >= 0.
    pub fn validate(&self) -> Result<(), String> {
        let n = self.width as usize * self.height as usize;
        if self.colour.len() != n || self.normal_depth.len() != n {
            return Err(format!(
                "buffers of {} and {} pixels for {n}",
                self.colour.len(),
                self.normal_depth.len()
            ));
        }
        for (i, (c, nd)) in self.colour.iter().zip(&self.normal_depth).enumerate() {
            if c.iter().chain(nd).any(|x| !x.is_finite()) || c[3] < 0.0 {
                return Err(format!(
                    "pixel {i} (x {}, y {}): colour {c:?}, normal/depth {nd:?}",
                    i % self.width as usize,
                    i / self.width as usize
                ));
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn up_axes_turn_onto_y_without_mirroring() {
        for a in UpAxis::ALL {
            let q = a.to_y_up();
            assert!((q * a.vector() - Vec3::Y).length() < 1e-6, "{a:?}");
            // a rotation keeps handedness: x cross y = z after the turn too
            let (x, y, z) = (q * Vec3::X, q * Vec3::Y, q * Vec3::Z);
            assert!((x.cross(y) - z).length() < 1e-6, "{a:?}");
        }
        // z-up (Houdini, Blender): (x, y, z) becomes (x, z, -y)
        let p = UpAxis::Z.to_y_up() * Vec3::new(1.0, 2.0, 3.0);
        assert!((p - Vec3::new(1.0, 3.0, -2.0)).length() < 1e-5, "{p}");
    }
}
