//! The CPU reference of every screen-space pass: sphere depth, the depth filter, thickness
//! (eq. 1 or eq. 3) and its bilateral filter, normals, attenuation and shading. Parallel over
//! pixels; each pixel of a pass depends only on the pass before, so the image does not depend on
//! the thread count.

use std::time::Instant;

use glam::{Vec2, Vec3};
use rayon::prelude::*;
use serde::Serialize;

use super::{DepthFilter, DepthImage, FilterScales, SsfrError, SsfrParams, filter_depth};
use crate::lnm::NarrowBand;
use crate::splat::{Camera, Light, Render, SplatParams, View};
use crate::view::{TILE, bin};

/// One Gaussian of the thickness (eq. 1: a point; eq. 3: a full voxel).
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct ThicknessSource {
    /// Where it is projected from: the point, or the voxel's centroid `c_j`.
    pub centre: Vec3,
    /// The fluid volume it stands for: `(r / 2)^3` a point, the sum over a voxel's points (eq.
    /// 3's `n_j` times a particle's volume when all are alike).
    pub volume: f32,
    /// Standard deviation of its Gaussian, world units.
    pub sigma: f32,
}

/// Milliseconds of each pass.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct SsfrTimings {
    pub depth_ms: f64,
    pub filter_ms: f64,
    pub thickness_ms: f64,
    pub shading_ms: f64,
}

/// One screen-space render with its intermediate buffers.
#[derive(Clone, Debug, PartialEq)]
pub struct SsfrRender {
    /// The buffers (`(tint, 1)`, `(normal, depth)`) and the shaded image.
    pub render: Render,
    /// The spheres' depth before the filter (infinite: no fluid).
    pub raw_depth: Vec<f32>,
    /// The filtered depth.
    pub depth: Vec<f32>,
    /// The filtered thickness (world units).
    pub thickness: Vec<f32>,
    pub timings: SsfrTimings,
}

/// Points prepared for screen-space rendering: the narrow band (when asked) and the thickness
/// sources, made once and drawn from any number of views (the light's and the camera's). Made
/// by [`ScreenSpace::new`]; [`ScreenSpace::deferred`] makes them on the first CPU use instead,
/// so that the GPU passes ([`super::gpu::GpuSsfr`]), which make their own band on the GPU, leave
/// the CPU without that work.
pub struct ScreenSpace<'a> {
    positions: &'a [Vec3],
    radii: &'a [f32],
    h: f32,
    params: SsfrParams,
    prepared: std::sync::OnceLock<Result<Prepared, SsfrError>>,
}

/// The band, the points drawn in the depth pass and the thickness sources of a
/// [`ScreenSpace`].
struct Prepared {
    band: Option<NarrowBand>,
    drawn: Vec<u32>,
    sources: Vec<ThicknessSource>,
}

/// The fluid volume a point of kernel radius `r` stands for: `(r / 2)^3` (a support radius is
/// twice the spacing).
fn volume_of(r: f32) -> f32 {
    (0.5 * r).powi(3)
}

impl<'a> ScreenSpace<'a> {
    /// Prepares `positions` with their radii (kernel supports); `h` is the reference support
    /// radius (the narrow band's voxel edge, the filters' depth scales).
    pub fn new(
        positions: &'a [Vec3],
        radii: &'a [f32],
        h: f32,
        params: &SsfrParams,
    ) -> Result<Self, SsfrError> {
        let screen = Self::deferred(positions, radii, h, params)?;
        screen.prepared()?;
        Ok(screen)
    }

    /// [`ScreenSpace::new`] with the inputs checked but the narrow band and the thickness
    /// sources made on their first use on the CPU (an error of the band's then comes from the
    /// render that needed it): the GPU passes make their own.
    pub fn deferred(
        positions: &'a [Vec3],
        radii: &'a [f32],
        h: f32,
        params: &SsfrParams,
    ) -> Result<Self, SsfrError> {
        params.validate()?;
        if !(h.is_finite() && h > 0.0) {
            return Err(SsfrError::InvalidParameter {
                name: "support_radius",
                reason: format!("must be finite and > 0, not {h}"),
            });
        }
        if positions.len() != radii.len() {
            return Err(SsfrError::InvalidParameter {
                name: "radii",
                reason: format!("{} radii for {} positions", radii.len(), positions.len()),
            });
        }
        if let Some(index) = positions.iter().position(|p| !p.is_finite()) {
            return Err(SsfrError::InvalidPoint {
                index,
                reason: "non-finite position",
            });
        }
        if let Some(index) = radii.iter().position(|r| !(r.is_finite() && *r > 0.0)) {
            return Err(SsfrError::InvalidPoint {
                index,
                reason: "radius not finite and > 0",
            });
        }
        Ok(Self {
            positions,
            radii,
            h,
            params: *params,
            prepared: std::sync::OnceLock::new(),
        })
    }

    /// The band, the drawn points and the sources, made on the first call.
    fn prepared(&self) -> Result<&Prepared, SsfrError> {
        self.prepared
            .get_or_init(|| self.prepare())
            .as_ref()
            .map_err(Clone::clone)
    }

    fn prepare(&self) -> Result<Prepared, SsfrError> {
        let (positions, radii, params) = (self.positions, self.radii, &self.params);
        let (band, drawn, sources) = if params.narrow_band {
            let band = crate::lnm::narrow_band(positions, self.h, &params.lnm)?;
            let drawn = band.particles();
            // eq. 3: one Gaussian per full voxel at its particles' centroid, their volume
            let mut volume = vec![0.0f32; band.voxels.len()];
            let mut radius = vec![0.0f32; band.voxels.len()];
            for (i, &v) in band.voxel_of.iter().enumerate() {
                volume[v as usize] += volume_of(radii[i]);
                radius[v as usize] += radii[i];
            }
            let sources = band
                .voxels
                .iter()
                .enumerate()
                .map(|(v, voxel)| ThicknessSource {
                    centre: voxel.centroid,
                    volume: volume[v],
                    sigma: params.thickness_sigma * radius[v] / voxel.count as f32,
                })
                .collect();
            (Some(band), drawn, sources)
        } else {
            let sources = positions
                .iter()
                .zip(radii)
                .map(|(&p, &r)| ThicknessSource {
                    centre: p,
                    volume: volume_of(r),
                    sigma: params.thickness_sigma * r,
                })
                .collect();
            (None, (0..positions.len() as u32).collect(), sources)
        };
        Ok(Prepared {
            band,
            drawn,
            sources,
        })
    }

    /// The points with their kernel radii, as given.
    #[must_use]
    pub fn points(&self) -> (&'a [Vec3], &'a [f32]) {
        (self.positions, self.radii)
    }

    /// The narrow band, when the parameters ask for one (none when it could not be made: the
    /// render says why).
    #[must_use]
    pub fn band(&self) -> Option<&NarrowBand> {
        self.prepared().ok().and_then(|p| p.band.as_ref())
    }

    /// Points drawn in the depth pass (the band's, or all; none when the band could not be
    /// made).
    #[must_use]
    pub fn drawn(&self) -> usize {
        self.prepared().map_or(0, |p| p.drawn.len())
    }

    /// The Gaussians of the thickness (voxels with the band, points without; none when the
    /// band could not be made).
    #[must_use]
    pub fn sources(&self) -> &[ThicknessSource] {
        self.prepared().map_or(&[], |p| p.sources.as_slice())
    }

    /// The parameters.
    #[must_use]
    pub fn params(&self) -> &SsfrParams {
        &self.params
    }

    /// Sphere `k` (below [`Self::drawn`]) of the depth pass: centre and world radius.
    #[must_use]
    pub fn sphere_of(&self, k: usize) -> (Vec3, f32) {
        self.sphere_at(self.prepared().map_or(k, |p| p.drawn[k] as usize))
    }

    /// The depth pass's sphere of point `j`: centre and world radius.
    fn sphere_at(&self, j: usize) -> (Vec3, f32) {
        (self.positions[j], self.params.sphere_radius * self.radii[j])
    }

    /// The reference support radius.
    #[must_use]
    pub fn reference_radius(&self) -> f32 {
        self.h
    }

    /// World radius of the spheres of the reference radius: the filters' depth scale.
    #[must_use]
    pub fn sphere(&self) -> f32 {
        self.params.sphere_radius * self.h
    }

    /// Every pass from one view (perspective, or orthographic such as a light's screen).
    pub fn render_view(&self, v: &View) -> Result<SsfrRender, SsfrError> {
        let mut timings = SsfrTimings::default();
        // the band and sources, when deferred: their time is the depth pass's
        let t = Instant::now();
        let prepared = self.prepared()?;
        let raw = self.depth(v, &prepared.drawn)?;
        timings.depth_ms = ms(t);
        let t = Instant::now();
        let mut image = depth_image(v, raw.clone());
        let scales = FilterScales::of(&self.params, self.sphere());
        filter_depth(
            &mut image,
            self.params.filter,
            self.params.filter_iterations(),
            &scales,
        );
        timings.filter_ms = ms(t);
        let t = Instant::now();
        let thickness = thickness_image(v, &prepared.sources)?;
        let thickness = filter_thickness(
            &thickness,
            &image,
            &scales,
            self.params.thickness_sigma_range * self.h,
        );
        timings.thickness_ms = ms(t);
        let t = Instant::now();
        let normals = normals(v, &image, scales.range);
        let base = Vec3::from_slice(&crate::splat::WATER[..3]);
        let absorption = Vec3::from(self.params.absorption) / self.h;
        let n = image.depth.len();
        let mut colour = vec![[0.0f32; 4]; n];
        let mut normal_depth = vec![[0.0f32; 4]; n];
        for i in 0..n {
            if let Some(normal) = normals[i] {
                let tint = base * (-absorption * thickness[i]).exp();
                colour[i] = tint.extend(1.0).to_array();
                normal_depth[i] = normal.extend(image.depth[i]).to_array();
            }
        }
        let shaded = crate::splat::cpu::shade_image(&colour, &normal_depth, v);
        timings.shading_ms = ms(t);
        Ok(SsfrRender {
            render: Render {
                width: v.width,
                height: v.height,
                image: shaded,
                colour,
                normal_depth,
            },
            raw_depth: raw,
            depth: image.depth,
            thickness,
            timings,
        })
    }

    /// Pass 1: the nearest sphere's depth per pixel (exact ray-sphere intersections).
    fn depth(&self, v: &View, drawn: &[u32]) -> Result<Vec<f32>, SsfrError> {
        let (w, hgt) = (v.width as usize, v.height as usize);
        // the drawn points read directly, not through `sphere_of`'s check that the band is
        // made: this runs for every sphere of every pixel's tile
        let sphere = |k: usize| self.sphere_at(drawn[k] as usize);
        let (tw, tiles) = bin(v, drawn.len(), sphere)?;
        Ok((0..w * hgt)
            .into_par_iter()
            .map(|i| {
                let (x, y) = (i % w, i / w);
                let (o, d) = v.world_ray(Vec2::new(x as f32 + 0.5, y as f32 + 0.5));
                // the ray's unit direction: `t` along it is `t / |d|` in view depth
                let len = d.length();
                let dn = d / len;
                let mut best = f32::INFINITY;
                for &k in &tiles[(y / TILE) * tw + x / TILE] {
                    let (c, r) = sphere(k as usize);
                    // the stable form (Haines et al., "Precision improvements for ray/sphere
                    // intersection", Ray Tracing Gems ch. 7): the squared distance of the
                    // centre from the ray from its offset vector, not as the difference of two
                    // squares about (40 radii)^2 = 1600 times larger than it (some 10 bits
                    // lost, by that ratio), which left the GPU twin's depths 1.5e-4 relative
                    // apart (measured; now 1e-4 sphere radii)
                    let oc = o - c;
                    let l = oc.dot(dn);
                    let q = oc - l * dn;
                    let h2 = r * r - q.length_squared();
                    if h2 < 0.0 {
                        continue;
                    }
                    let t = (-l - h2.sqrt()) / len;
                    if t > 0.0 && t < best {
                        best = t;
                    }
                }
                best
            })
            .collect())
    }
}

fn ms(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}

/// The depth buffer of view `v` as a [`DepthImage`].
#[must_use]
pub fn depth_image(v: &View, depth: Vec<f32>) -> DepthImage {
    DepthImage {
        width: v.width as usize,
        height: v.height as usize,
        depth,
        orthographic: v.is_orthographic(),
        pixel_size: 2.0 * v.tan_half.y / v.height as f32,
    }
}

/// The sources as the thickness pass reads them: projected centre (pixels), `-1 / (2 sigma_px^2)`
/// and amplitude `volume / (2 pi sigma^2)`; `None` behind the view.
#[must_use]
pub fn project_sources(v: &View, sources: &[ThicknessSource]) -> Vec<Option<(Vec2, f32, f32)>> {
    let pixel = depth_image(v, Vec::new());
    sources
        .par_iter()
        .map(|s| {
            let q = v.project(s.centre);
            if (q.z.is_nan() || q.z <= 0.0) && !v.is_orthographic() {
                return None;
            }
            let sigma_px = s.sigma / pixel.pixel_at(q.z);
            let amplitude = s.volume / (std::f32::consts::TAU * s.sigma * s.sigma);
            Some((q.truncate(), -0.5 / (sigma_px * sigma_px), amplitude))
        })
        .collect()
}

/// Thickness (eqs. 1 and 3): per pixel, the sum of the sources' Gaussians, each scaled by its
/// volume over its area `2 pi sigma^2` (world units at the source's depth), cut at 3 sigma.
pub fn thickness_image(v: &View, sources: &[ThicknessSource]) -> Result<Vec<f32>, SsfrError> {
    let (w, h) = (v.width as usize, v.height as usize);
    let projected = project_sources(v, sources);
    let (tw, tiles) = bin(v, sources.len(), |k| {
        (sources[k].centre, 3.0 * sources[k].sigma)
    })?;
    Ok((0..w * h)
        .into_par_iter()
        .map(|i| {
            let (x, y) = (i % w, i / w);
            let p = Vec2::new(x as f32 + 0.5, y as f32 + 0.5);
            let mut sum = 0.0f32;
            for &k in &tiles[(y / TILE) * tw + x / TILE] {
                if let Some((c, k2, a)) = projected[k as usize] {
                    let d2 = (p - c).length_squared();
                    // cut at 3 sigma: exp(-4.5)
                    let g = (k2 * d2).exp();
                    if g > 0.011 {
                        sum += a * g;
                    }
                }
            }
            sum
        })
        .collect())
}

/// The thickness's bilateral filter (Green 2010, as the paper's §3): a Gaussian over the window
/// weighted by the thickness difference (`sigma_thickness`), on the fluid's pixels and the
/// pixels next to them.
#[must_use]
pub fn filter_thickness(
    thickness: &[f32],
    depth: &DepthImage,
    s: &FilterScales,
    sigma_thickness: f32,
) -> Vec<f32> {
    let (w, h) = (depth.width, depth.height);
    let r = i64::from(s.radius_px);
    let (ks, kt) = (
        -0.5 / (s.sigma_px * s.sigma_px),
        -0.5 / (sigma_thickness * sigma_thickness),
    );
    (0..w * h)
        .into_par_iter()
        .map(|i| {
            let t0 = thickness[i];
            if !depth.covered(i) {
                return t0;
            }
            let (x, y) = ((i % w) as i64, (i / w) as i64);
            let (mut sum, mut weight) = (0.0f32, 0.0f32);
            for dy in -r..=r {
                for dx in -r..=r {
                    let (u, v) = (x + dx, y + dy);
                    if u < 0 || v < 0 || u >= w as i64 || v >= h as i64 {
                        continue;
                    }
                    let t = thickness[v as usize * w + u as usize];
                    let dt = t - t0;
                    let g = (ks * (dx * dx + dy * dy) as f32 + kt * dt * dt).exp();
                    sum += g * t;
                    weight += g;
                }
            }
            sum / weight
        })
        .collect()
}

/// Pass 4: world-space normals from the filtered depth: the view-space positions of the pixel
/// and its neighbours, along each axis the one-sided difference with the smaller depth step
/// (neighbours farther than `range` in depth or uncovered are not used), the cross product
/// turned to face the eye. A pixel with no usable neighbour along an axis faces the eye.
#[must_use]
pub fn normals(v: &View, image: &DepthImage, range: f32) -> Vec<Option<Vec3>> {
    let (w, h) = (image.width, image.height);
    let point = |x: usize, y: usize, z: f32| {
        let (o, d) = v.world_ray(Vec2::new(x as f32 + 0.5, y as f32 + 0.5));
        o + z * d
    };
    (0..w * h)
        .into_par_iter()
        .map(|i| {
            let z0 = image.depth[i];
            if !z0.is_finite() {
                return None;
            }
            let (x, y) = (i % w, i / w);
            let p0 = point(x, y, z0);
            let (_, dir) = v.world_ray(Vec2::new(x as f32 + 0.5, y as f32 + 0.5));
            let facing = -dir.normalize();
            let neighbour = |dx: i64, dy: i64| -> Option<(f32, Vec3)> {
                let (u, vv) = (x as i64 + dx, y as i64 + dy);
                if u < 0 || vv < 0 || u >= w as i64 || vv >= h as i64 {
                    return None;
                }
                let z = image.depth[vv as usize * w + u as usize];
                (z.is_finite() && (z - z0).abs() <= range)
                    .then(|| ((z - z0).abs(), point(u as usize, vv as usize, z)))
            };
            // the step along +axis: forward difference, or backward, whichever is smaller
            let step = |a: Option<(f32, Vec3)>, b: Option<(f32, Vec3)>| match (a, b) {
                (Some(f), Some(b)) if b.0 < f.0 => Some(p0 - b.1),
                (Some(f), _) => Some(f.1 - p0),
                (None, Some(b)) => Some(p0 - b.1),
                (None, None) => None,
            };
            let ddx = step(neighbour(1, 0), neighbour(-1, 0));
            let ddy = step(neighbour(0, 1), neighbour(0, -1));
            let n = match (ddx, ddy) {
                (Some(a), Some(b)) => a.cross(b).try_normalize().unwrap_or(facing),
                _ => facing,
            };
            Some(if n.dot(facing) < 0.0 { -n } else { n })
        })
        .collect()
}

/// Screen-space rendering of `positions` (radii: kernel supports; `h` the reference support
/// radius) from `camera` at `width` x `height`; `splat` gives the background and the cost
/// limits, `light` the shading.
#[allow(clippy::too_many_arguments)]
pub fn render_cpu(
    positions: &[Vec3],
    radii: &[f32],
    h: f32,
    params: &SsfrParams,
    camera: &Camera,
    light: &Light,
    splat: &SplatParams,
    width: u32,
    height: u32,
) -> Result<SsfrRender, SsfrError> {
    let v = View::new(camera, light, splat, width, height)?;
    ScreenSpace::new(positions, radii, h, params)?.render_view(&v)
}

impl std::fmt::Display for DepthFilter {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}
