//! A peer renderer: narrow-band screen-space fluid rendering (Oliveira and Paiva, "Narrow-band
//! screen-space fluid rendering", the paper in
//! `../shared/papers/oliveira-narrow-band-screen-space-fluid-rendering.txt`, §3 and §4).
//!
//! The passes of the paper's Figure 2, each a function of this module or of [`cpu`]:
//!
//! 1. **Depth**: the points drawn as spheres (exact ray-sphere depth per pixel, nearest kept).
//!    With the narrow band (default) only the particles of [`crate::lnm`]'s layers 1 and 2.
//! 2. **Filtered depth**: one of four filters ([`DepthFilter`]), 7x7, 4 iterations (30 for
//!    curvature flow), the paper's settings (§5).
//! 3. **Thickness**: eq. 1 (a Gaussian per point) without the narrow band, eq. 3 (a Gaussian per
//!    full voxel at the centroid of its particles, weighted by their count) with it; then a
//!    bilateral filter.
//! 4. **Normals** from the filtered depth (the view-space positions of neighbouring pixels, the
//!    smaller one-sided difference across a silhouette).
//! 5. **Attenuation** (Beer-Lambert with the thickness as the path length) into the same
//!    per-pixel buffers as the other renderers, `(tint, 1)` and `(normal, depth)`: shaded by
//!    [`crate::splat::shade`], and read by the optics ([`crate::optics`], which refracts the
//!    pool, reflects the sky with Fresnel and adds caustics) like the splats' buffers.
//!
//! Units. Depths are view depths (`t` along [`crate::splat::View::ray`]), lengths are world
//! units: a point of radius `r` (a kernel support, twice the particle spacing) stands for the
//! volume `(r / 2)^3` of fluid and is drawn as a sphere of `sphere_radius * r`. A thickness is a
//! length: eq. 1's sum of unit Gaussians is scaled by each point's volume over the Gaussian's
//! area `2 pi sigma^2` (so that the thickness integrated over the screen is the fluid's volume),
//! which the paper leaves unscaled (its `kappa` absorbs it).

use serde::{Deserialize, Serialize};

use crate::lnm::{LnmError, LnmParams};
use crate::splat::SplatError;

pub mod cpu;
pub mod gpu;

pub use cpu::{ScreenSpace, render_cpu};

use crate::Error;
use crate::splat::{Drawn, GpuWaterPass, Render, View, WaterInput, WaterRenderer, WaterSurface};

/// Errors of the screen-space renderer.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SsfrError {
    /// A parameter is out of range.
    #[error("invalid screen-space parameter `{name}`: {reason}")]
    InvalidParameter { name: &'static str, reason: String },
    /// A point's position or radius is unusable.
    #[error("point {index}: {reason}")]
    InvalidPoint { index: usize, reason: &'static str },
    /// The narrow band.
    #[error(transparent)]
    Lnm(#[from] LnmError),
    /// The view (camera, light, size) or the cost limits.
    #[error(transparent)]
    Splat(#[from] SplatError),
    /// A screen tile holds more spheres or thickness Gaussians than a GPU pass loops over.
    #[error(
        "a 16x16 screen tile holds {items} spheres or thickness Gaussians, more than the GPU passes loop over ({limit}); draw a larger image or use the CPU path"
    )]
    TooDense { items: usize, limit: usize },
}

/// The depth filter (§5: "narrow-range filter \[TY18\], bilateral filter \[Gre10\], plane fitting
/// filter \[IKM16\], and curvature flow filter \[LGS09\]").
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum DepthFilter {
    /// Truong and Yuksel 2018: a Gaussian over the depths within a narrow range of the pixel's;
    /// farther samples are dropped, nearer ones clamped ([`narrow_range`]).
    #[default]
    NarrowRange,
    /// Green 2010: a bilateral Gaussian ([`bilateral`]).
    Bilateral,
    /// Imai et al. 2016: a weighted least-squares plane per pixel ([`plane_fit`]).
    Plane,
    /// van der Laan et al. 2009: mean-curvature flow of the depth ([`curvature_flow_step`]).
    CurvatureFlow,
    /// No filter: the spheres' depth as drawn (for comparison).
    None,
}

impl DepthFilter {
    /// Every filter, in the order of the documentation.
    pub const ALL: [Self; 5] = [
        Self::NarrowRange,
        Self::Bilateral,
        Self::Plane,
        Self::CurvatureFlow,
        Self::None,
    ];

    /// The name used in files and on the command line.
    #[must_use]
    pub fn as_str(self) -> &'static str {
        match self {
            Self::NarrowRange => "narrow-range",
            Self::Bilateral => "bilateral",
            Self::Plane => "plane",
            Self::CurvatureFlow => "curvature-flow",
            Self::None => "none",
        }
    }
}

/// Parameters of the screen-space renderer. `Default` holds the paper's settings where it gives
/// them (7x7 filters, 4 iterations, 30 for curvature flow, voxels of 2h, `n_min = 8`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SsfrParams {
    /// The depth filter.
    pub filter: DepthFilter,
    /// Draw the depth of the narrow band's particles only and take the thickness from its
    /// voxels (eq. 3); `false`: every point, thickness from every point (eq. 1). Default true.
    pub narrow_band: bool,
    /// The narrow band's voxels (edge in support radii, `n_min`, domain).
    pub lnm: LnmParams,
    /// Radius of each point's sphere in the depth pass, in radii of the point (a kernel
    /// support, twice the spacing). Default 0.5: spheres of one spacing's radius. The paper
    /// draws spheres of diameter h (one spacing, 0.25 here); measured at 640x480 from a framing
    /// camera, the holes inside the silhouette (closed by 3 px) at 0.25 / 0.35 / 0.5: double dam
    /// break 1.08 / 0.68 / 0.40 % (enclosed 0.35 / 0.05 / 0.002 %), dam break 4.35 / 3.63 /
    /// 2.26 % (enclosed 0.62 / 0.25 / 0.12 %).
    pub sphere_radius: f32,
    /// Half width of every filter window, in pixels. Default 3 (7x7, the paper's).
    pub filter_radius_px: u32,
    /// Iterations of the narrow-range, bilateral and plane filters. Default 4 (the paper's).
    pub iterations: u32,
    /// Iterations of curvature flow. Default 30 (the paper's).
    pub curvature_flow_iterations: u32,
    /// Spatial standard deviation of the filters' Gaussian, in pixels. Default 2.
    pub sigma_px: f32,
    /// Depth standard deviation of the bilateral and plane filters, in sphere radii. Default 1.
    pub sigma_depth: f32,
    /// The narrow range: samples farther than this many sphere radii behind the pixel are
    /// dropped (they belong to a surface behind), in the narrow-range, plane and curvature-flow
    /// filters. Default 2.
    pub range: f32,
    /// The narrow-range filter's clamp: nearer samples (beyond the range in front) count as
    /// lying this many sphere radii in front of the pixel. Default 1.
    pub clamp: f32,
    /// Curvature flow's step: the diffusion per iteration in pixels^2 (stable below 0.25).
    /// Default 0.15.
    pub curvature_step: f32,
    /// Standard deviation of each thickness Gaussian (eqs. 1, 3), in radii of the point.
    /// Default 0.5.
    pub thickness_sigma: f32,
    /// Thickness standard deviation of the thickness's bilateral filter, in support radii.
    /// Default 1.
    pub thickness_sigma_range: f32,
    /// Beer-Lambert absorption per support radius of thickness, per RGB channel (the ray
    /// caster's: `tint = base * exp(-absorption * thickness / h)`).
    pub absorption: [f32; 3],
}

impl Default for SsfrParams {
    fn default() -> Self {
        Self {
            filter: DepthFilter::NarrowRange,
            narrow_band: true,
            lnm: LnmParams::default(),
            sphere_radius: 0.5,
            filter_radius_px: 3,
            iterations: 4,
            curvature_flow_iterations: 30,
            sigma_px: 2.0,
            sigma_depth: 1.0,
            range: 2.0,
            clamp: 1.0,
            curvature_step: 0.15,
            thickness_sigma: 0.5,
            thickness_sigma_range: 1.0,
            absorption: crate::raycast::RayCastParams::default().absorption,
        }
    }
}

/// Largest filter half width (a 33x33 window).
const MAX_FILTER_RADIUS: u32 = 16;
/// Most iterations of any filter.
const MAX_ITERATIONS: u32 = 1000;

impl SsfrParams {
    /// Checks every parameter.
    pub fn validate(&self) -> Result<(), SsfrError> {
        self.lnm.validate()?;
        let positive = [
            ("sphere_radius", self.sphere_radius),
            ("sigma_px", self.sigma_px),
            ("sigma_depth", self.sigma_depth),
            ("range", self.range),
            ("thickness_sigma", self.thickness_sigma),
            ("thickness_sigma_range", self.thickness_sigma_range),
        ];
        for (name, v) in positive {
            if !(v.is_finite() && v > 0.0) {
                return Err(SsfrError::InvalidParameter {
                    name,
                    reason: format!("must be finite and > 0, not {v}"),
                });
            }
        }
        if !(self.clamp.is_finite() && self.clamp >= 0.0) {
            return Err(SsfrError::InvalidParameter {
                name: "clamp",
                reason: format!("must be finite and >= 0, not {}", self.clamp),
            });
        }
        if !(self.curvature_step.is_finite()
            && self.curvature_step > 0.0
            && self.curvature_step <= 0.25)
        {
            return Err(SsfrError::InvalidParameter {
                name: "curvature_step",
                reason: format!(
                    "must lie in (0, 0.25] (an explicit step beyond 0.25 px^2 is unstable), not {}",
                    self.curvature_step
                ),
            });
        }
        if self.filter_radius_px > MAX_FILTER_RADIUS {
            return Err(SsfrError::InvalidParameter {
                name: "filter_radius_px",
                reason: format!("at most {MAX_FILTER_RADIUS}, not {}", self.filter_radius_px),
            });
        }
        for (name, v) in [
            ("iterations", self.iterations),
            ("curvature_flow_iterations", self.curvature_flow_iterations),
        ] {
            if v > MAX_ITERATIONS {
                return Err(SsfrError::InvalidParameter {
                    name,
                    reason: format!("at most {MAX_ITERATIONS}, not {v}"),
                });
            }
        }
        if !self.absorption.iter().all(|a| a.is_finite() && *a >= 0.0) {
            return Err(SsfrError::InvalidParameter {
                name: "absorption",
                reason: "every channel finite and >= 0".into(),
            });
        }
        Ok(())
    }

    /// Iterations of the chosen filter.
    #[must_use]
    pub fn filter_iterations(&self) -> u32 {
        match self.filter {
            DepthFilter::CurvatureFlow => self.curvature_flow_iterations,
            DepthFilter::None => 0,
            _ => self.iterations,
        }
    }
}

/// A depth image: view depth per pixel, row-major from the top, `f32::INFINITY` where no fluid
/// is drawn. What every filter reads and writes.
#[derive(Clone, Debug, PartialEq)]
pub struct DepthImage {
    pub width: usize,
    pub height: usize,
    pub depth: Vec<f32>,
    /// Orthographic view: a plane's depth is affine in the pixel coordinates; perspective: its
    /// inverse depth is (the plane filter fits what is affine).
    pub orthographic: bool,
    /// World size of a pixel at depth 1 (perspective) or everywhere (orthographic).
    pub pixel_size: f32,
}

impl DepthImage {
    /// Whether pixel `i` holds fluid.
    #[must_use]
    pub fn covered(&self, i: usize) -> bool {
        self.depth[i].is_finite()
    }

    /// World size of a pixel at depth `z`.
    #[must_use]
    pub fn pixel_at(&self, z: f32) -> f32 {
        if self.orthographic {
            self.pixel_size
        } else {
            self.pixel_size * z
        }
    }
}

/// What the filters need besides the image: the window, the Gaussian and the depth scales
/// (world units: the ranges are multiples of the sphere radius).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FilterScales {
    pub radius_px: u32,
    pub sigma_px: f32,
    /// Bilateral depth standard deviation.
    pub sigma_depth: f32,
    /// Samples farther behind than this are dropped.
    pub range: f32,
    /// Nearer samples beyond the range count as this far in front.
    pub clamp: f32,
    /// Curvature flow's diffusion per step, px^2.
    pub step: f32,
}

impl FilterScales {
    /// The scales of `params` for spheres of world radius `sphere`.
    #[must_use]
    pub fn of(params: &SsfrParams, sphere: f32) -> Self {
        Self {
            radius_px: params.filter_radius_px,
            sigma_px: params.sigma_px,
            sigma_depth: params.sigma_depth * sphere,
            range: params.range * sphere,
            clamp: params.clamp * sphere,
            step: params.curvature_step,
        }
    }
}

/// Runs `iterations` of `filter` on `image` (in place, each iteration reading the last).
pub fn filter_depth(
    image: &mut DepthImage,
    filter: DepthFilter,
    iterations: u32,
    s: &FilterScales,
) {
    for _ in 0..iterations {
        image.depth = match filter {
            DepthFilter::NarrowRange => narrow_range(image, s),
            DepthFilter::Bilateral => bilateral(image, s),
            DepthFilter::Plane => plane_fit(image, s),
            DepthFilter::CurvatureFlow => curvature_flow_step(image, s),
            DepthFilter::None => return,
        };
    }
}

/// The window's offsets with their spatial Gaussian weight.
fn window(s: &FilterScales) -> Vec<(i64, i64, f32)> {
    let r = i64::from(s.radius_px);
    let k = -0.5 / (s.sigma_px * s.sigma_px);
    let mut w = Vec::with_capacity(((2 * r + 1) * (2 * r + 1)) as usize);
    for dy in -r..=r {
        for dx in -r..=r {
            w.push((dx, dy, (k * (dx * dx + dy * dy) as f32).exp()));
        }
    }
    w
}

/// The depth at `(x + dx, y + dy)`, infinite outside the image.
#[inline]
fn at(image: &DepthImage, x: usize, y: usize, dx: i64, dy: i64) -> f32 {
    let (u, v) = (x as i64 + dx, y as i64 + dy);
    if u < 0 || v < 0 || u >= image.width as i64 || v >= image.height as i64 {
        return f32::INFINITY;
    }
    image.depth[v as usize * image.width + u as usize]
}

/// Applies `f(x, y, z)` to every covered pixel in parallel; uncovered pixels stay infinite.
fn per_pixel(image: &DepthImage, f: impl Fn(usize, usize, f32) -> f32 + Sync) -> Vec<f32> {
    use rayon::prelude::*;
    let w = image.width;
    (0..image.depth.len())
        .into_par_iter()
        .map(|i| {
            let z = image.depth[i];
            if z.is_finite() { f(i % w, i / w, z) } else { z }
        })
        .collect()
}

/// The bilateral Gaussian filter (Green 2010): the mean of the covered depths in the window,
/// weighted `exp(-|dp|^2 / 2 sigma_px^2 - dz^2 / 2 sigma_depth^2)`.
#[must_use]
pub fn bilateral(image: &DepthImage, s: &FilterScales) -> Vec<f32> {
    let win = window(s);
    let kz = -0.5 / (s.sigma_depth * s.sigma_depth);
    per_pixel(image, |x, y, z0| {
        let (mut sum, mut weight) = (0.0f32, 0.0f32);
        for &(dx, dy, g) in &win {
            let z = at(image, x, y, dx, dy);
            if z.is_finite() {
                let dz = z - z0;
                let w = g * (kz * dz * dz).exp();
                sum += w * z;
                weight += w;
            }
        }
        sum / weight
    })
}

/// The narrow-range filter (Truong and Yuksel 2018), as we read it: a Gaussian over the window
/// in which a sample farther than `range` behind the pixel is dropped (another surface, or the
/// background) and a sample nearer than `range` in front counts as lying `clamp` in front (so
/// that a foreground edge pulls the surface only a little). Their bias correction, as we
/// derive it: a dropped sample drops its mirror sample too (offset `-d`), so the kept samples
/// are symmetric about the pixel and a plane's depth is kept exactly at a silhouette, where a
/// one-sided window would bend it. Their adaptive window size is not used: the narrow-band
/// paper filters with a fixed 7x7 window (§5).
#[must_use]
pub fn narrow_range(image: &DepthImage, s: &FilterScales) -> Vec<f32> {
    let win = window(s);
    per_pixel(image, |x, y, z0| {
        let value = |z: f32| -> Option<f32> {
            if !z.is_finite() || z > z0 + s.range {
                None
            } else if z < z0 - s.range {
                Some(z0 - s.clamp)
            } else {
                Some(z)
            }
        };
        let (mut sum, mut weight) = (0.0f32, 0.0f32);
        for &(dx, dy, g) in &win {
            // each pair once: the half window with (dx, dy) > (0, 0) in row order, and the centre
            if (dy, dx) < (0, 0) {
                continue;
            }
            let a = value(at(image, x, y, dx, dy));
            if dx == 0 && dy == 0 {
                sum += g * z0;
                weight += g;
                continue;
            }
            let b = value(at(image, x, y, -dx, -dy));
            if let (Some(a), Some(b)) = (a, b) {
                sum += g * (a + b);
                weight += 2.0 * g;
            }
        }
        sum / weight
    })
}

/// Plane fitting (Imai et al. 2016): per pixel, the weighted least-squares plane through the
/// window's samples within the narrow range (weights of the bilateral filter), evaluated at the
/// pixel. What is fitted is what is affine in the pixel coordinates on a plane: the inverse
/// depth under a perspective projection, the depth under an orthographic one; so a plane, tilted
/// or not, is kept exactly, where a bilateral mean flattens the slopes. Too few samples (a
/// singular system) fall back to the weighted mean.
#[must_use]
pub fn plane_fit(image: &DepthImage, s: &FilterScales) -> Vec<f32> {
    let win = window(s);
    let kz = -0.5 / (s.sigma_depth * s.sigma_depth);
    let ortho = image.orthographic;
    let (to, from) = (
        move |z: f32| if ortho { z } else { 1.0 / z },
        move |q: f64| if ortho { q as f32 } else { (1.0 / q) as f32 },
    );
    per_pixel(image, |x, y, z0| {
        // normal equations of q = a + b dx + c dy, in f64 (sums of 49 squares of offsets)
        let mut m = [[0.0f64; 3]; 3];
        let mut rhs = [0.0f64; 3];
        for &(dx, dy, g) in &win {
            let z = at(image, x, y, dx, dy);
            if !z.is_finite() || (z - z0).abs() > s.range {
                continue;
            }
            let dz = z - z0;
            let w = f64::from(g * (kz * dz * dz).exp());
            let basis = [1.0, dx as f64, dy as f64];
            let q = f64::from(to(z)) - f64::from(to(z0));
            for r in 0..3 {
                rhs[r] += w * basis[r] * q;
                for c in 0..3 {
                    m[r][c] += w * basis[r] * basis[c];
                }
            }
        }
        let q0 = f64::from(to(z0));
        match solve3(m, rhs) {
            Some(abc) => from(q0 + abc[0]),
            None => from(q0 + rhs[0] / m[0][0]),
        }
    })
}

/// Solves the 3x3 system by Cramer's rule; `None` when it is (nearly) singular.
fn solve3(m: [[f64; 3]; 3], b: [f64; 3]) -> Option<[f64; 3]> {
    let det = |a: [[f64; 3]; 3]| {
        a[0][0] * (a[1][1] * a[2][2] - a[1][2] * a[2][1])
            - a[0][1] * (a[1][0] * a[2][2] - a[1][2] * a[2][0])
            + a[0][2] * (a[1][0] * a[2][1] - a[1][1] * a[2][0])
    };
    let d = det(m);
    let scale = m[0][0] * m[1][1] * m[2][2];
    if d.is_nan() || d.abs() <= 1e-9 * scale.abs() || scale == 0.0 {
        return None;
    }
    let mut x = [0.0; 3];
    for (c, xc) in x.iter_mut().enumerate() {
        let mut a = m;
        for r in 0..3 {
            a[r][c] = b[r];
        }
        *xc = det(a) / d;
    }
    Some(x)
}

/// One step of curvature flow (van der Laan et al. 2009): the depth moves by its mean curvature,
/// `z += step * [(1 + zv^2) zxx - 2 zu zv zxy + (1 + zu^2) zyy] / (1 + zu^2 + zv^2)^(3/2)`, the
/// mean curvature of the depth as a graph over the image plane (`zu = zx / s`, `s` the world size
/// of a pixel at the pixel's depth; derivatives by central differences in pixels) times `2 s^2`,
/// so that `step` is the diffusion per iteration in pixels^2 whatever the scale (stable up to
/// 0.25). Their eq. keeps the terms of the rays' divergence across the stencil; this locally
/// orthographic form drops them (their size: the stencil's 2 pixels over the image's width).
/// Their boundary rule: a derivative across a silhouette or a depth jump beyond the narrow range
/// is zero (one-sided first derivatives where one side is covered), so the flow does not pull
/// surfaces into each other or into the background.
#[must_use]
pub fn curvature_flow_step(image: &DepthImage, s: &FilterScales) -> Vec<f32> {
    per_pixel(image, |x, y, z0| {
        let near = |dx, dy| {
            let z = at(image, x, y, dx, dy);
            (z.is_finite() && (z - z0).abs() <= s.range).then_some(z)
        };
        let axis = |a: Option<f32>, b: Option<f32>| -> (f32, f32) {
            // first and second derivative along one axis from the samples at -1 and +1
            match (a, b) {
                (Some(a), Some(b)) => (0.5 * (b - a), b - 2.0 * z0 + a),
                (Some(a), None) => (z0 - a, 0.0),
                (None, Some(b)) => (b - z0, 0.0),
                (None, None) => (0.0, 0.0),
            }
        };
        let (zx, zxx) = axis(near(-1, 0), near(1, 0));
        let (zy, zyy) = axis(near(0, -1), near(0, 1));
        let zxy = match (near(1, 1), near(-1, -1), near(1, -1), near(-1, 1)) {
            (Some(a), Some(b), Some(c), Some(d)) => 0.25 * (a + b - c - d),
            _ => 0.0,
        };
        let px = image.pixel_at(z0);
        let (zu, zv) = (zx / px, zy / px);
        let g = 1.0 + zu * zu + zv * zv;
        let flow =
            ((1.0 + zv * zv) * zxx - 2.0 * zu * zv * zxy + (1.0 + zu * zu) * zyy) / (g * g.sqrt());
        z0 + s.step * flow
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn image(w: usize, h: usize, f: impl Fn(usize, usize) -> f32) -> DepthImage {
        DepthImage {
            width: w,
            height: h,
            depth: (0..w * h).map(|i| f(i % w, i / w)).collect(),
            orthographic: false,
            pixel_size: 0.01,
        }
    }

    fn scales() -> FilterScales {
        FilterScales::of(&SsfrParams::default(), 0.05)
    }

    #[test]
    fn every_filter_keeps_a_flat_surface_and_the_background() {
        // a fronto-parallel disc of depth 2 on the background
        let img = image(32, 32, |x, y| {
            let (dx, dy) = (x as f32 - 15.5, y as f32 - 15.5);
            if dx * dx + dy * dy < 100.0 {
                2.0
            } else {
                f32::INFINITY
            }
        });
        for f in DepthFilter::ALL {
            let mut out = img.clone();
            filter_depth(&mut out, f, 4, &scales());
            for (a, b) in img.depth.iter().zip(&out.depth) {
                assert!(a == b || (a - b).abs() < 1e-5, "{f:?}: {a} became {b}");
            }
        }
    }

    #[test]
    fn plane_fitting_keeps_a_tilted_plane_where_the_bilateral_mean_bends_it() {
        // a perspective plane: inverse depth affine in the pixels; cut by a silhouette at x = 20
        let img = image(40, 24, |x, y| {
            if x < 20 {
                1.0 / (0.5 + 0.004 * x as f32 + 0.002 * y as f32)
            } else {
                f32::INFINITY
            }
        });
        let s = FilterScales {
            range: 10.0,
            ..scales()
        };
        let plane = plane_fit(&img, &s);
        let mean = bilateral(&img, &s);
        let err = |v: &[f32]| {
            img.depth
                .iter()
                .zip(v)
                .filter(|(a, _)| a.is_finite())
                .map(|(a, b)| (a - b).abs() / a)
                .fold(0.0f32, f32::max)
        };
        assert!(err(&plane) < 1e-5, "plane fit: {}", err(&plane));
        assert!(
            err(&mean) > 1e-3,
            "the bilateral mean bends the edge: {}",
            err(&mean)
        );
    }

    #[test]
    fn the_narrow_range_filter_keeps_a_tilted_plane_up_to_its_silhouette() {
        let img = image(40, 24, |x, y| {
            if x < 20 {
                2.0 + 0.01 * x as f32 + 0.005 * y as f32
            } else {
                f32::INFINITY
            }
        });
        let out = narrow_range(&img, &scales());
        for (a, b) in img.depth.iter().zip(&out) {
            assert!(a == b || (a - b).abs() < 1e-5, "{a} became {b}");
        }
    }

    #[test]
    fn curvature_flow_flattens_a_bump_and_ignores_a_surface_behind() {
        // a bump in front of a plane, and a far wall on the right that must not pull it
        let img = image(48, 32, |x, y| {
            if x >= 40 {
                return 9.0;
            }
            let (dx, dy) = (x as f32 - 20.0, y as f32 - 16.0);
            2.0 - 0.05 * (-(dx * dx + dy * dy) / 8.0).exp()
        });
        let mut out = img.clone();
        filter_depth(&mut out, DepthFilter::CurvatureFlow, 30, &scales());
        let peak = |d: &[f32]| 2.0 - d[16 * 48 + 20];
        assert!(
            peak(&out.depth) < 0.5 * peak(&img.depth),
            "{}",
            peak(&out.depth)
        );
        assert_eq!(out.depth[16 * 48 + 45], 9.0);
        // the near surface next to the wall stays where it was
        assert!((out.depth[16 * 48 + 39] - img.depth[16 * 48 + 39]).abs() < 1e-4);
    }

    #[test]
    fn bad_parameters_are_refused() {
        let cases: [fn(&mut SsfrParams); 6] = [
            |p| p.sphere_radius = 0.0,
            |p| p.sigma_px = f32::NAN,
            |p| p.curvature_step = 0.3,
            |p| p.filter_radius_px = 100,
            |p| p.iterations = 1_000_000,
            |p| p.absorption = [-1.0, 0.0, 0.0],
        ];
        for f in cases {
            let mut p = SsfrParams::default();
            f(&mut p);
            assert!(matches!(
                p.validate(),
                Err(SsfrError::InvalidParameter { .. })
            ));
        }
        assert_eq!(SsfrParams::default().validate(), Ok(()));
    }
}

/// Screen-space rendering as a [`WaterRenderer`]: the source's points with `[ssfr]`.
#[derive(Clone, Debug)]
pub struct Method {
    pub params: SsfrParams,
}

impl WaterRenderer for Method {
    fn drawn(&self) -> Drawn {
        Drawn::Spheres { calibrated: false }
    }
    fn needs_points(&self) -> bool {
        true
    }
    fn water<'a>(&self, input: WaterInput<'a>) -> Result<Box<dyn WaterSurface + 'a>, Error> {
        let (positions, radii) = input.points;
        // the band made on the first CPU render: a GPU render makes its own
        Ok(Box::new(ScreenSpace::deferred(
            positions,
            radii,
            input.reference_radius,
            &self.params,
        )?))
    }
}

impl WaterSurface for ScreenSpace<'_> {
    fn render(&self, view: &View) -> Result<Render, Error> {
        Ok(self.render_view(view)?.render)
    }

    fn render_gpu(&self, ctx: &crate::gpu::GpuContext, view: &View) -> Result<Render, Error> {
        Ok(gpu::render_view_gpu(ctx, self, view)?.render)
    }

    fn gpu_pass(
        &self,
        device: &wgpu::Device,
        _format: wgpu::TextureFormat,
        _size: (u32, u32),
    ) -> Result<Box<dyn GpuWaterPass>, Error> {
        Ok(Box::new(gpu::GpuSsfr::new(device)?))
    }

    fn prepare_gpu(
        &self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        pass: &mut dyn GpuWaterPass,
        view: &View,
    ) -> Result<bool, Error> {
        let Some(passes) = pass.as_any_mut().downcast_mut::<gpu::GpuSsfr>() else {
            return Ok(false);
        };
        passes.prepare(device, queue, self, view)?;
        Ok(true)
    }
}
