//! Stage 4: surfel rendering by EWA surface splatting (Botsch, Hornung, Zwicker, Kobbelt 2005,
//! "High-quality surface splatting on today's GPUs"; the EWA filter of Zwicker et al. 2001), the
//! renderer that Iwasaki et al. §5.2 extend with optics.
//!
//! Three passes:
//! 1. **visibility**: every surfel is drawn as a screen-aligned quad that bounds the projection of
//!    its disk (the projected corners of the disk's bounding rectangle: perspective maps convex sets
//!    to convex sets, so the bound is conservative, unlike the classic point-size estimate that
//!    clips splats seen at an angle); per pixel the view ray meets the disk's plane, pixels outside
//!    the disk are discarded, and the depth written is pushed back along the ray by
//!    `epsilon = depth_offset * radius`;
//! 2. **attributes**: depth-tested against pass 1 without writing, each fragment adds
//!    `(colour * w, w)` and `(normal * w, depth * w)` into float targets, with
//!    `w = exp(-sharpness * r^2)`, `r^2 = min(r3^2, r2^2)`: `r3` the object-space distance in the
//!    disk (1 at the rim), `r2` the screen-space distance to the projected centre in units of the
//!    low-pass radius (about one pixel). Botsch et al. approximate the EWA resampling kernel (the
//!    object-space Gaussian convolved with the screen-space low-pass) by the smaller of the two
//!    distances: a magnified splat keeps its exact elliptical footprint, a minified one still
//!    covers about a pixel instead of falling between pixel centres;
//! 3. **shading**: divide by the accumulated weight, Blinn-Phong with one directional light.
//!
//! [`render_cpu`] is the specification: a CPU implementation of the three passes whose functions
//! ([`frame`], [`fragment`], [`shade`]) mirror, name for name and operation for operation, those
//! of `shaders/surfel_splat.wgsl`, which [`gpu`] runs. Tests compare the two images.

use glam::{Vec2, Vec3, Vec3Swizzles, Vec4, Vec4Swizzles};

pub mod cpu;
pub mod gpu;
pub mod water;

// the view's types and the picture metrics, where the splats have always been found
pub use crate::quality::{difference_image, psnr};
pub use crate::view::{
    BYTES_PER_PIXEL, Camera, Light, MAX_SIZE, Render, SplatError, SplatMode, SplatParams, View,
};
pub(crate) use crate::view::{check_cost, pixel_span};
pub use cpu::{render_cpu, render_view_cpu};
pub use water::{Drawn, Ewa, GpuWaterPass, ParticleSplat, WaterInput, WaterRenderer, WaterSurface};

/// One surfel as the GPU stores it (64 bytes, `SurfelIn` in the WGSL): position and radius,
/// normal and stretch (minor / major axis; 1 for a circle), the major axis direction (ignored
/// for circles), colour (linear RGBA).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct Surfel {
    pub position: [f32; 3],
    pub radius: f32,
    pub normal: [f32; 3],
    pub stretch: f32,
    pub tangent: [f32; 3],
    pub _pad: f32,
    pub colour: [f32; 4],
}

const _: () = assert!(std::mem::size_of::<Surfel>() == 64);

/// The colour surfels get when none is given: a light water blue.
pub const WATER: [f32; 4] = [0.35, 0.58, 0.86, 1.0];

impl Surfel {
    /// A circular disk.
    #[must_use]
    pub fn disk(position: Vec3, normal: Vec3, radius: f32, colour: [f32; 4]) -> Self {
        Self {
            position: position.to_array(),
            radius,
            normal: normal.to_array(),
            stretch: 1.0,
            tangent: [0.0; 3],
            _pad: 0.0,
            colour,
        }
    }

    /// A sphere of particle splatting ([`SplatMode::Spheres`]): centre and radius; the normal
    /// (+z) only keeps it drawable, the renderer takes each fragment's normal from the sphere.
    #[must_use]
    pub fn sphere(position: Vec3, radius: f32, colour: [f32; 4]) -> Self {
        Self::disk(position, Vec3::Z, radius, colour)
    }

    /// An elliptical disk with semi-axes `major` along `tangent` and `minor` across it.
    #[must_use]
    pub fn ellipse(
        position: Vec3,
        normal: Vec3,
        tangent: Vec3,
        major: f32,
        minor: f32,
        colour: [f32; 4],
    ) -> Self {
        Self {
            position: position.to_array(),
            radius: major,
            normal: normal.to_array(),
            stretch: if major > 0.0 { minor / major } else { 0.0 },
            tangent: tangent.to_array(),
            _pad: 0.0,
            colour,
        }
    }

    /// True when the surfel can be drawn: finite, radius and stretch > 0, normal not zero.
    /// Others are skipped by both renderers.
    #[must_use]
    pub fn is_drawable(&self) -> bool {
        let n = Vec3::from(self.normal);
        Vec3::from(self.position).is_finite()
            && n.is_finite()
            && n.length_squared() > 1e-20
            && self.radius.is_finite()
            && self.radius > 0.0
            && self.stretch.is_finite()
            && self.stretch > 0.0
            && Vec3::from(self.tangent).is_finite()
            && self.colour.iter().all(|c| c.is_finite())
    }
}

/// Surfels from positions, normals and radii, all of one colour.
#[must_use]
pub fn surfels_from(
    positions: &[Vec3],
    normals: &[Vec3],
    radii: &[f32],
    colour: [f32; 4],
) -> Vec<Surfel> {
    positions
        .iter()
        .zip(normals)
        .zip(radii)
        .map(|((&p, &n), &r)| Surfel::disk(p, n, r, colour))
        .collect()
}

/// Spheres of particle splatting ([`SplatMode::Spheres`]) at `positions`, radius `radii[i]`
/// (or `radius` for all when `radii` is empty), all of one colour.
#[must_use]
pub fn spheres_from(
    positions: &[Vec3],
    radii: &[f32],
    radius: f32,
    colour: [f32; 4],
) -> Vec<Surfel> {
    positions
        .iter()
        .enumerate()
        .map(|(i, &p)| Surfel::sphere(p, radii.get(i).copied().unwrap_or(radius), colour))
        .collect()
}

/// Surfels as a point set: positions, normals and a `radius` attribute, what
/// [`surfels_from_particles`] reads back (the colours are left out).
#[must_use]
pub fn surfels_to_particles(surfels: &[Surfel]) -> crate::ParticleSet {
    let mut set =
        crate::ParticleSet::from_positions(surfels.iter().map(|s| s.position.into()).collect());
    set.normals = Some(surfels.iter().map(|s| s.normal.into()).collect());
    set.extra.push(crate::Attribute::scalar(
        "radius",
        crate::ScalarKind::F32,
        surfels.iter().map(|s| f64::from(s.radius)).collect(),
    ));
    set
}

/// Surfels from a point set read from a file: positions, normals (required), a `radius`
/// attribute (required; `radii` and `r` are accepted too) and the colours when present.
pub fn surfels_from_particles(set: &crate::ParticleSet) -> Result<Vec<Surfel>, SplatError> {
    let normals = set
        .normals
        .as_ref()
        .ok_or_else(|| SplatError::InvalidParameter {
            name: "surfels",
            reason: "the file has no normals (nx, ny, nz)".into(),
        })?;
    let radius = ["radius", "radii", "r"]
        .iter()
        .find_map(|n| set.attribute(n).filter(|a| a.components == 1))
        .ok_or_else(|| SplatError::InvalidParameter {
            name: "surfels",
            reason: "the file has no scalar `radius` attribute".into(),
        })?;
    // a radius beyond any view of the set: the camera fitted around it would not be finite
    let extent = set
        .bounds()
        .map_or(0.0, |(lo, hi)| (hi - lo).length())
        .max(f32::MIN_POSITIVE);
    let limit = MAX_RADIUS_PER_EXTENT * extent;
    if let Some(i) = radius
        .values
        .iter()
        .position(|&r| (r as f32).is_infinite() || (set.len() > 1 && r as f32 > limit))
    {
        return Err(SplatError::InvalidParameter {
            name: "radius",
            reason: format!(
                "surfel {i} has radius {}, more than {MAX_RADIUS_PER_EXTENT} times the {extent} \
                 extent of the surfels (zero, negative and NaN radii are skipped with a count)",
                radius.values[i]
            ),
        });
    }
    Ok((0..set.len())
        .map(|i| {
            let colour = set.colours.as_ref().map_or(WATER, |c| {
                let [r, g, b] = c[i];
                [
                    f32::from(r) / 255.0,
                    f32::from(g) / 255.0,
                    f32::from(b) / 255.0,
                    1.0,
                ]
            });
            Surfel::disk(
                set.positions[i],
                normals[i],
                radius.values[i] as f32,
                colour,
            )
        })
        .collect())
}

/// Bounds of the drawable surfels' centres, widened by their radii; `None` when there is none.
#[must_use]
pub fn bounds(surfels: &[Surfel]) -> Option<(Vec3, Vec3)> {
    surfels
        .iter()
        .filter(|s| s.is_drawable())
        .map(|s| {
            let p = Vec3::from(s.position);
            (p - s.radius, p + s.radius)
        })
        .reduce(|(a, b), (c, d)| (a.min(c), b.max(d)))
}

/// The drawable surfels (see [`Surfel::is_drawable`]) in their order, and how many were skipped.
#[must_use]
pub fn drawable(surfels: &[Surfel]) -> (Vec<Surfel>, usize) {
    let kept: Vec<Surfel> = surfels
        .iter()
        .copied()
        .filter(Surfel::is_drawable)
        .collect();
    let skipped = surfels.len() - kept.len();
    (kept, skipped)
}

/// The pixel fragments a render of `surfels` in `v` costs, known before rasterising: the sum
/// over drawn splats of the pixels of their screen rectangles.
#[must_use]
pub fn fragments(surfels: &[Surfel], v: &View) -> u128 {
    use rayon::prelude::*;
    let (w, h) = (v.width as usize, v.height as usize);
    surfels
        .par_iter()
        .filter(|s| s.is_drawable())
        .filter_map(|s| frame(s, v))
        .map(|f| {
            let xs = pixel_span(f.rect.x, f.rect.z, w);
            let ys = pixel_span(f.rect.y, f.rect.w, h);
            (xs.1 - xs.0) as u128 * (ys.1 - ys.0) as u128
        })
        .sum()
}

/// The largest surfel radius read from a file, as a multiple of the extent (bounding box
/// diagonal) of the surfels' centres.
pub const MAX_RADIUS_PER_EXTENT: f32 = 1000.0;

/// Orthonormal tangent of a unit normal (Duff et al. 2017), as `basis_tangent` in the WGSL.
fn basis_tangent(n: Vec3) -> Vec3 {
    let s = if n.z >= 0.0 { 1.0 } else { -1.0 };
    let a = -1.0 / (s + n.z);
    let b = n.x * n.y * a;
    Vec3::new(1.0 + s * n.x * n.x * a, s * b, -s * n.x)
}

/// The per-surfel set-up of passes 1 and 2 (`splat_frame` in the WGSL). `None`: culled (back
/// facing, behind the camera, or off screen).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Frame {
    /// Pixel rectangle: min x, min y, max x, max y.
    pub rect: Vec4,
    centre: Vec3,
    axis_u: Vec3,
    axis_v: Vec3,
    normal_view: Vec3,
    /// Projected centre (pixels), sprite radius (pixels), epsilon.
    screen: Vec4,
    /// [`depth_extent`] of the axes (disks).
    depth_extent: f32,
}

/// Sets up one drawable surfel for the view, as `splat_frame` in the WGSL.
#[must_use]
pub fn frame(s: &Surfel, v: &View) -> Option<Frame> {
    let n = Vec3::from(s.normal).normalize();
    let tangent = Vec3::from(s.tangent);
    let mut t = tangent - n * n.dot(tangent);
    if s.stretch == 1.0 || t.dot(t) < 1e-12 {
        t = basis_tangent(n);
    } else {
        t = t.normalize();
    }
    let big_u = t * s.radius;
    let big_v = n.cross(t) * (s.radius * s.stretch);
    let c = (v.view * Vec3::from(s.position).extend(1.0)).xyz();
    let uv = (v.view * big_u.extend(0.0)).xyz();
    let vv = (v.view * big_v.extend(0.0)).xyz();
    let nv = (v.view * n.extend(0.0)).xyz();
    let towards = if v.orthographic { Vec3::NEG_Z } else { c };
    let round = v.mode != SplatMode::Ewa;
    if v.mode != SplatMode::Spheres && nv.dot(towards) >= 0.0 {
        return None;
    }
    let eps = v.depth_offset * s.radius;
    let vp = v.viewport();
    let mut lo = Vec2::ZERO;
    let mut hi = vp;
    let centre_px = v.pixels_of(c);
    let screen;
    let mut axis_u = uv / uv.dot(uv);
    if round {
        if centre_px.z <= 0.0 {
            return None;
        }
        // the projected radius h' by perspective scaling (Adams et al. §3.1); a sphere covers
        // at least the low-pass radius, so that a minified one does not fall between pixel
        // centres (Botsch et al.'s reason for the filter, which Adams et al. leave to future
        // work, §6)
        let mut r_px = s.radius * v.proj.y_axis.y * 0.5 * vp.y / centre_px.z;
        // sprites have no depth offset: the nearest wins
        let mut offset = 0.0;
        if v.mode == SplatMode::Spheres {
            r_px = r_px.max(v.low_pass);
            // a sphere's frame keeps its world radius in axis_u.x
            axis_u = Vec3::new(s.radius, 0.0, 0.0);
            offset = eps;
        }
        screen = Vec4::new(centre_px.x, centre_px.y, r_px, offset);
        lo = lo.max(centre_px.xy() - Vec2::splat(r_px + RECT_MARGIN_PX));
        hi = hi.min(centre_px.xy() + Vec2::splat(r_px + RECT_MARGIN_PX));
    } else {
        let mut all_front = true;
        let mut mn = Vec2::splat(3.0e38);
        let mut mx = Vec2::splat(-3.0e38);
        for k in 0..4u32 {
            let su = if k & 1 == 0 { 1.0 } else { -1.0 };
            let sv = if k & 2 == 0 { 1.0 } else { -1.0 };
            let q = v.pixels_of(c + su * uv + sv * vv);
            if q.z <= 1e-6 {
                all_front = false;
            }
            mn = mn.min(q.xy());
            mx = mx.max(q.xy());
        }
        let centre = if centre_px.z > 0.0 {
            centre_px.xy()
        } else {
            Vec2::splat(-1.0e15)
        };
        if all_front {
            // the disk's pixels (inside the projected square) and the low-pass filter's (within
            // its radius of the projected centre, in front when every corner is)
            let reach = Vec2::splat(v.low_pass);
            lo = lo.max(mn.min(centre - reach) - Vec2::splat(RECT_MARGIN_PX));
            hi = hi.min(mx.max(centre + reach) + Vec2::splat(RECT_MARGIN_PX));
        }
        screen = Vec4::new(centre.x, centre.y, 0.0, eps);
    }
    // NaN-safe: a NaN bound culls
    if !(hi.x > lo.x && hi.y > lo.y) {
        return None;
    }
    let axis_v = vv / vv.dot(vv);
    Some(Frame {
        rect: Vec4::new(lo.x, lo.y, hi.x, hi.y),
        centre: c,
        axis_u,
        axis_v,
        normal_view: nv,
        screen,
        depth_extent: depth_extent(axis_u, axis_v),
    })
}

/// How far from the centre's depth a disk's fragment depth may lie (`frame.axis_u`,
/// `frame.axis_v` its axes over their squared lengths): the depth the disk spans plus
/// [`DEPTH_REACH_RADII`] of its radius (see the WGSL's `fragment`). Once a surfel, not once a
/// pixel: the same value, three square roots and divisions a fragment fewer.
fn depth_extent(axis_u: Vec3, axis_v: Vec3) -> f32 {
    let uz = axis_u.z / axis_u.length_squared();
    let vz = axis_v.z / axis_v.length_squared();
    let radius = 1.0 / axis_u.length().min(axis_v.length());
    (uz * uz + vz * vz).sqrt() + DEPTH_REACH_RADII * radius
}

/// One fragment of passes 1 and 2 (`Fragment` in the WGSL).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Fragment {
    /// `r^2` of the weight.
    pub r2: f32,
    /// View depth (distance along the view axis).
    pub depth: f32,
    /// Depth-buffer value without offset (pass 2).
    pub ndc: f32,
    /// Depth-buffer value pushed back by epsilon (pass 1).
    pub ndc_offset: f32,
    /// The sphere's normal at the fragment, in view space ([`SplatMode::Spheres`]; zero for
    /// disks, whose normal is the surfel's).
    pub sphere_normal: Vec3,
    /// The depth offset epsilon of the surfel (world units).
    pub epsilon: f32,
}

/// How far (pixels) a splat's rectangle reaches beyond the pixels its weight can cover: the
/// projected square around a disk (its corners projected exactly, a convex hull of the disk's
/// projection) joined with the low-pass filter's circle, or a sprite's or sphere's screen disk;
/// the margin only absorbs the rounding of the projections (`RECT_MARGIN_PX` in the WGSL). It
/// was one pixel plus the low-pass radius around the square: the dam break's 640x480 splats
/// evaluated 1.95 M fragments of which 0.18 M (9 %) lie on a disk or in the filter; 0.39 M now.
pub const RECT_MARGIN_PX: f32 = 1.0 / 16.0;

/// How far (in surfel radii) beyond the depths its disk spans a pixel's depth may lie on the
/// disk's plane where the screen-space filter, not the disk, covers the pixel (`DEPTH_REACH` in
/// the WGSL). The plane's depth keeps coplanar splats of a grazing plane blending (a pixel's
/// footprint there spans several radii of depth); unbounded, the plane of a disk seen edge-on
/// runs off arbitrarily far. Measured (`tests/splat.rs` grazing plane, pixel-to-pixel variance;
/// the dam break's finished frame at 320x240, specks): 0 radii 471 / 347, 2: 374 / 307, 4: 230 /
/// 315, 8: 78 / 335, unbounded: 70 / 484 and dark dashes on the pool walls. 8 keeps both.
pub const DEPTH_REACH_RADII: f32 = 8.0;

/// Evaluates a surfel at a pixel centre, as `splat_fragment` in the WGSL. `None`: discarded.
#[must_use]
pub fn fragment(pixel: Vec2, f: &Frame, v: &View) -> Option<Fragment> {
    let (o, d) = v.ray(pixel);
    let mut depth = -f.centre.z;
    let r2;
    let mut sphere_normal = Vec3::ZERO;
    if v.mode == SplatMode::Spheres {
        // eq. 5: z_i(x') = z_i - sqrt(h^2 - |x - x_i|^2), |x - x_i| = r h on the square through
        // the centre; the normal of the same point, (e, sqrt(1 - r^2)) with the screen's y down
        let e = (pixel - f.screen.xy()) / f.screen.z;
        r2 = e.dot(e);
        let height = (1.0 - r2).max(0.0).sqrt();
        depth = -f.centre.z - f.axis_u.x * height;
        sphere_normal = Vec3::new(e.x, -e.y, height);
    } else if v.mode == SplatMode::Sprites {
        let e = (pixel - f.screen.xy()) / f.screen.z;
        r2 = e.dot(e);
    } else {
        let mut r3 = 3.0e38f32;
        let denom = f.normal_view.dot(d);
        let t = if denom != 0.0 {
            f.normal_view.dot(f.centre - o) / denom
        } else {
            0.0
        };
        if t > 0.0 {
            let q = o + t * d - f.centre;
            let a = q.dot(f.axis_u);
            let b = q.dot(f.axis_v);
            r3 = a * a + b * b;
        }
        let mut r2d = 3.0e38f32;
        if v.low_pass > 0.0 {
            let e = (pixel - f.screen.xy()) / v.low_pass;
            r2d = e.dot(e);
        }
        r2 = r3.min(r2d);
        // the hit on the disk's plane, also where the filter decides the weight, within
        // DEPTH_REACH_RADII of the depths the disk spans (see the WGSL)
        if t > 0.0 {
            let extent = f.depth_extent;
            depth = t.clamp(-f.centre.z - extent, -f.centre.z + extent);
        }
    }
    // NaN-safe: NaN fails both comparisons and is discarded
    if !(r2 <= 1.0 && depth > 0.0) {
        return None;
    }
    let p = o + d * depth;
    let ndc = v.ndc_depth(p);
    if !(0.0..=1.0).contains(&ndc) {
        return None;
    }
    // the disks' offset runs along the ray; the spheres' along the view axis, so that the
    // shifted buffer holds z_eps = min z_i + epsilon in view depth as eq. 7 reads it
    let pushed = if v.mode == SplatMode::Spheres {
        o + d * (depth + f.screen.w)
    } else {
        p + d.normalize() * f.screen.w
    };
    let ndc_offset = v.ndc_depth(pushed).min(1.0);
    Some(Fragment {
        r2,
        depth,
        ndc,
        ndc_offset,
        sphere_normal,
        epsilon: f.screen.w,
    })
}

/// The weight of a fragment in pass 2 (`splat_weight` in the WGSL), `buffer` the pass-1
/// depth-buffer value at its pixel: EWA's Gaussian; 1 for sprites (the nearest alone passes);
/// for spheres Adams et al.'s `W1 W2` (eqs. 6, 7), `W1 = 1 - r` to the projected rim and
/// `W2 = (z_eps - z) / epsilon` to the shifted depth, in view depth. With epsilon 0 only the
/// nearest sphere passes the depth test, and `W2` (0 / 0 there) is taken as 1.
#[must_use]
pub fn weight(f: &Fragment, buffer: f32, v: &View) -> f32 {
    match v.mode {
        SplatMode::Ewa => (-v.sharpness * f.r2).exp(),
        SplatMode::Sprites => 1.0,
        SplatMode::Spheres => {
            let w1 = 1.0 - f.r2.sqrt();
            let eps = f.epsilon;
            let w2 = if eps > 0.0 {
                ((v.linear_depth(buffer) - f.depth) / eps).clamp(0.0, 1.0)
            } else {
                1.0
            };
            w1 * w2
        }
    }
}

/// Normalisation and Blinn-Phong shading of one pixel (`shade` in the WGSL): `colour` holds
/// `(sum w c, sum w)`, `normal_depth` `(sum w n, sum w depth)`.
#[must_use]
pub fn shade(pixel: Vec2, colour: Vec4, normal_depth: Vec4, v: &View) -> Vec4 {
    let w = colour.w;
    if w.is_nan() || w <= 0.0 {
        return v.background;
    }
    let base = colour.xyz() / w;
    let mut n = normal_depth.xyz() / w;
    let d = (v.inv_view * v.ray(pixel).1.extend(0.0)).xyz();
    let view = -d.normalize();
    n = if n.dot(n) > 1e-12 {
        n.normalize()
    } else {
        view
    };
    let l = v.light_dir.xyz();
    let half_vector = (l + view).normalize();
    let diffuse = n.dot(l).max(0.0);
    let specular = n.dot(half_vector).max(0.0).powf(v.shininess);
    let lit = base * (v.light_dir.w + (1.0 - v.light_dir.w) * diffuse) * v.light_colour.xyz()
        + v.light_colour.w * specular * v.light_colour.xyz();
    lit.clamp(Vec3::ZERO, Vec3::ONE).extend(1.0)
}
