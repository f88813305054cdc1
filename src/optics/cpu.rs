//! The CPU reference of the optics stage: caustics (§5.1) and the final image (§5.2), with exact
//! ray-triangle intersection in the receiver's BVH.

// `!(x > 0.0)` on purpose throughout: NaN compares false and is rejected with the rest
#![allow(clippy::neg_cmp_op_on_partial_ord)]

use glam::{Vec2, Vec3, Vec4};
use image::RgbaImage;
use rayon::prelude::*;

use super::{OpticsError, Stage, encode, fresnel_reflectance, refract, texel_area};
use crate::splat::{Light, Render, Surfel, View, WaterSurface, render_view_cpu};

/// One pixel of the virtual screen: the water point, its depth from the light, where its
/// refracted ray meets the receiver, and `T exp(-sigma_t l)` per channel.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct CausticVertex {
    /// Water point `s` and its view depth from the light (`w <= 0`: no water at this pixel).
    pub surface: Vec4,
    /// Receiver point `c` (`w = 1`: the refracted ray met the receiver on a side the light sees,
    /// `2`: on the side facing away from it, `0`: it missed).
    pub hit: Vec4,
    /// `T(theta_i, theta_t) exp(-sigma_t l_c)` per colour channel.
    pub transmit: Vec3,
}

/// The caustics of one frame (§5.1): the light's view of the water and the caustics map.
#[derive(Clone, Debug, PartialEq)]
pub struct Caustics {
    /// The virtual screen (light's view of the water).
    pub screen: View,
    /// The caustics map's view (light's view of receiver and water).
    pub map: View,
    /// Per screen pixel, row-major from the top.
    pub vertices: Vec<CausticVertex>,
    /// Per map texel: flux (linear RGB, per unit of the light's colour units times area).
    pub flux: Vec<[f32; 4]>,
    /// Per map texel: caustics irradiance (RGB), `w = 1` where the texel sees the receiver.
    pub irradiance: Vec<[f32; 4]>,
    /// Per map texel: receiver point (xyz) and depth (`w`, 0: no receiver), the geometry map.
    pub geometry: Vec<[f32; 4]>,
    /// Per map texel: receiver normal facing the light (xyz); `w` 1 where it is a container's
    /// outer face ([`super::ReceiverGeometry::outer_face`], which the deposit keeps flux off), else 0.
    pub normals: Vec<[f32; 4]>,
    /// Flux through the water triangles, before transmission.
    pub incident: Vec3,
    /// Flux the caustics triangles carried into the map.
    pub transmitted: Vec3,
    /// Caustics triangles drawn.
    pub triangles: usize,
    /// Water triangles skipped as spanning a depth discontinuity.
    pub discontinuous: usize,
    /// Water triangles whose refracted rays missed the receiver.
    pub missed: usize,
    /// Water triangles whose refracted rays reached receiver points hidden from the light (their
    /// flux is not kept: see `caustics_cpu`), or whose caustics triangle covers no texel of its
    /// own surface.
    pub hidden: usize,
    /// Flux that reached the receiver where the light's map cannot hold it: at points hidden
    /// from the light, on the far sides of surfaces, and over texels that show another surface
    /// (`deposit_owned`). `transmitted + dropped` is all the flux the caustics triangles carried.
    pub dropped: Vec3,
}

/// World point and view depth of a screen pixel seen with `depth`.
fn point_at(v: &View, x: u32, y: u32, depth: f32) -> Vec3 {
    let (o, d) = v.world_ray(Vec2::new(x as f32 + 0.5, y as f32 + 0.5));
    o + d * depth
}

/// Size of a pixel of `v` at view depth `depth` (world units).
pub(crate) fn pixel_size(v: &View, depth: f32) -> f32 {
    let s = 2.0 * v.half_extent().x / v.width as f32;
    if v.is_orthographic() { s } else { s * depth }
}

/// Water normal and depth of a splatted pixel (eq. 2), `None` where no surfel covers it.
fn water_at(r: &Render, i: usize) -> Option<(Vec3, f32)> {
    let w = r.colour[i][3];
    if !(w > 0.0) {
        return None;
    }
    let nd = Vec4::from(r.normal_depth[i]) / w;
    let depth = nd.w;
    if !(depth.is_finite() && depth > 0.0) {
        return None;
    }
    Some((nd.truncate(), depth))
}

/// Unit normal of an accumulated normal, or `fallback` where it vanishes.
fn unit_or(n: Vec3, fallback: Vec3) -> Vec3 {
    n.try_normalize().unwrap_or(fallback)
}

/// Clips a convex polygon (`n` points in `p`) to the half-plane `sign * (q[axis] - bound) >= 0`,
/// in place (Sutherland-Hodgman); returns the new count. `clip_polygon` in the WGSL.
fn clip_polygon(p: &mut [Vec2; 8], n: usize, axis: usize, bound: f32, sign: f32) -> usize {
    let mut out = [Vec2::ZERO; 8];
    let mut m = 0;
    for i in 0..n {
        let a = p[i];
        let b = p[(i + 1) % n];
        let da = sign * (a[axis] - bound);
        let db = sign * (b[axis] - bound);
        if da >= 0.0 && m < 8 {
            out[m] = a;
            m += 1;
        }
        if (da >= 0.0) != (db >= 0.0) && m < 8 {
            out[m] = a + (b - a) * (da / (da - db));
            m += 1;
        }
    }
    *p = out;
    m
}

/// Twice the signed area of a polygon.
fn polygon_area2(p: &[Vec2; 8], n: usize) -> f32 {
    (0..n).map(|i| p[i].perp_dot(p[(i + 1) % n])).sum()
}

fn add_texel(map: &mut [[f32; 4]], width: u32, x: u32, y: u32, v: Vec3) {
    let t = &mut map[(y * width + x) as usize];
    t[0] += v.x;
    t[1] += v.y;
    t[2] += v.z;
}

/// Adds `value` (a flux) to the caustics map by box-filtered rasterisation ([`rasterise`]),
/// into the texels that show the caustics triangle's own surface (issue 41): the
/// triangle `q` is in the map's pixel coordinates with its view depth in `z`; a texel takes its
/// share only where the receiver the light sees there (`geometry`, `normals`) lies within the
/// triangle's depths, widened by the texel's slope-scaled bias ([`depth_bias`]). A caustics
/// triangle on the floor behind a wall's edge, seen from the light, overlaps texels of the
/// wall's top or outer face, far nearer the light; their shares are dropped like the light that
/// reaches points hidden from the light (`Caustics::dropped`) instead of lighting the wall.
/// The depth range, not the triangle's plane: a triangle across a corner (a vertex on the floor,
/// two on a wall) has a chord for a plane, and the plane test dropped a quarter of such
/// triangles' flux on the column's splash frame (the range: 4-6 %, the texels at the seams).
/// Nor does a texel of a container's outer face take any (`normals`' `w` 1, from
/// [`super::ReceiverGeometry::outer_face`] once per texel): the light that reaches it crosses no water, so a triangle
/// whose depth range spans such a texel (a vertex on the floor, one on the wall's rim) brings it
/// light that belongs elsewhere (measured on the column's splash frame with the surface at the
/// fluid's boundary: 4 texels, up to 0.04 % of a texel's direct light).
/// Returns the share of `value` deposited. `deposit_triangle` in the WGSL.
/// The map is handed in bands of rows (`band`: the map's rows `rows`, `width` texels each), so
/// that bands take their triangles at once ([`caustics_of`]); the share returned is the band's.
/// `texels` are the map's [`DepositTexel`]s.
fn deposit_owned(
    (band, rows): (&mut [[f32; 4]], std::ops::Range<u32>),
    view: &View,
    texels: &[DepositTexel],
    q: [Vec3; 3],
    value: Vec3,
) -> f32 {
    let (w, h) = (view.width, view.height);
    let zmin = q[0].z.min(q[1].z).min(q[2].z);
    let zmax = q[0].z.max(q[1].z).max(q[2].z);
    let mut deposited = 0.0;
    let first = rows.start;
    rasterise(w, h, q.map(|v| v.truncate()), rows, |x, y, share| {
        let t = texels[(y * w + x) as usize];
        // NaN-safe: a texel that takes no light has a NaN depth, which fails both tests
        if t.depth >= zmin - t.bias && t.depth <= zmax + t.bias {
            add_texel(band, w, x, y - first, value * share);
            deposited += share;
        }
    });
    deposited
}

/// A caustics map texel as [`deposit_owned`] tests it: the depth of the receiver it shows and
/// the depth a triangle may lie off it ([`depth_bias`]). Both depend on the texel alone, so
/// they are found with the geometry map ([`MapTexel`]), not once for each triangle that covers
/// the texel (the column's splash frame: 731,416 visits of 189,440 texels by 24,889 triangles).
#[derive(Clone, Copy, Debug)]
struct DepositTexel {
    depth: f32,
    bias: f32,
}

/// A texel of the light's geometry map: the receiver point it shows and its depth (`w`, 0:
/// none), the receiver's normal facing the light (`w` 1 on a container's outer face), and its
/// [`DepositTexel`] (the depth NaN where no light is deposited: no receiver, or an outer face).
#[derive(Clone, Copy, Debug)]
struct MapTexel {
    geometry: [f32; 4],
    normal: [f32; 4],
    deposit: DepositTexel,
}

impl MapTexel {
    /// Texel `(x, y)` of the map `map` over the stage's receiver.
    fn of(stage: &Stage, map: &View, (x, y): (u32, u32)) -> Self {
        let centre = Vec2::new(x as f32 + 0.5, y as f32 + 0.5);
        let (o, d) = map.world_ray(centre);
        let none = DepositTexel {
            depth: f32::NAN,
            bias: 0.0,
        };
        let Some(h) = stage.receiver.intersect(o, d, 0.0) else {
            return Self {
                geometry: [0.0; 4],
                normal: [0.0; 4],
                deposit: none,
            };
        };
        let outer = stage.receiver.outer_face(h.position, h.normal);
        let deposit = if h.t > 0.0 && !outer {
            DepositTexel {
                depth: h.t,
                bias: depth_bias(map, centre, h.t, h.normal),
            }
        } else {
            none
        };
        Self {
            geometry: h.position.extend(h.t).to_array(),
            normal: h.normal.extend(f32::from(u8::from(outer))).to_array(),
            deposit,
        }
    }
}

/// The depth a lookup in a light's map allows between a point and the surface a texel shows:
/// 1.5 texels plus twice the surface's depth change across a texel (slope-scaled, capped at 20),
/// for a surface of normal `n` seen at pixel `q` and depth `z`. `depth_bias` in the WGSL.
pub(crate) fn depth_bias(v: &View, q: Vec2, z: f32, n: Vec3) -> f32 {
    let (_, d) = v.world_ray(q);
    let c = (n.dot(d) / d.length().max(1e-20)).abs();
    let slope = ((1.0 - c * c).max(0.0).sqrt() / c.max(0.05)).min(20.0);
    (1.5 + 2.0 * slope) * pixel_size(v, z)
}

/// Calls `texel(x, y, share)` for each texel of a `width x height` map that the triangle `p`
/// (pixel coordinates) overlaps, with the exact area of the overlap as a share of the
/// triangle's: box-filtered rasterisation. Unlike drawing the irradiance `value / S_c` at texel
/// centres (the paper's hardware rasterisation), a deposit this way loses no flux to triangles
/// smaller than a texel, so the map conserves flux exactly, and a uniform tiling of triangles
/// still gives a uniform map. A degenerate triangle gives all of it to the texel of its
/// centroid.
/// Only the texels of the rows `rows` are visited (the same shares as in a whole pass: each row
/// is clipped on its own, relative to the triangle's first texel).
fn rasterise(
    width: u32,
    height: u32,
    p: [Vec2; 3],
    rows: std::ops::Range<u32>,
    mut texel: impl FnMut(u32, u32, f32),
) {
    if !(p[0].is_finite() && p[1].is_finite() && p[2].is_finite()) {
        return;
    }
    let total = (p[1] - p[0]).perp_dot(p[2] - p[0]).abs();
    let lo = p[0].min(p[1]).min(p[2]);
    let hi = p[0].max(p[1]).max(p[2]);
    if !(total > 1e-12) {
        let m = (p[0] + p[1] + p[2]) / 3.0;
        if m.x >= 0.0
            && m.y >= 0.0
            && m.x < width as f32
            && m.y < height as f32
            && rows.contains(&(m.y as u32))
        {
            texel(m.x as u32, m.y as u32, 1.0);
        }
        return;
    }
    let y0 = lo.y.floor().max(0.0) as u32;
    let y1 = (hi.y.ceil().min(height as f32) as u32).max(y0);
    let x0 = lo.x.floor().max(0.0) as u32;
    let x1 = (hi.x.ceil().min(width as f32) as u32).max(x0);
    // clipped and measured relative to the first texel: with coordinates of hundreds of pixels,
    // the shoelace formula loses ~0.2 % of a texel's area to f32 rounding
    let origin = Vec2::new(x0 as f32, y0 as f32);
    let local = p.map(|q| q - origin);
    for y in y0.max(rows.start)..y1.min(rows.end) {
        let ly = (y - y0) as f32;
        let mut row = [Vec2::ZERO; 8];
        row[..3].copy_from_slice(&local);
        let mut n = clip_polygon(&mut row, 3, 1, ly, 1.0);
        n = clip_polygon(&mut row, n, 1, ly + 1.0, -1.0);
        if n < 3 {
            continue;
        }
        // only the texels the row's piece reaches: a texel past its x extent keeps no area (the
        // same texels and shares as the whole box's row)
        let (mut min_x, mut max_x) = (f32::MAX, f32::MIN);
        for v in &row[..n] {
            min_x = min_x.min(v.x);
            max_x = max_x.max(v.x);
        }
        let from = x0 + (min_x.floor().max(0.0) as u32).min(x1 - x0);
        let to = x0 + (max_x.ceil().max(0.0) as u32).min(x1 - x0);
        for x in from..to {
            let lx = (x - x0) as f32;
            let mut cell = row;
            let mut m = clip_polygon(&mut cell, n, 0, lx, 1.0);
            m = clip_polygon(&mut cell, m, 0, lx + 1.0, -1.0);
            if m < 3 {
                continue;
            }
            let a = polygon_area2(&cell, m).abs();
            if a > 0.0 {
                texel(x, y, a / total);
            }
        }
    }
}

/// The caustics of the surfels under the stage's light (§5.1), CPU reference.
pub fn caustics_cpu(stage: &Stage, surfels: &[Surfel]) -> Result<Caustics, OpticsError> {
    caustics_of_render(
        stage,
        &render_view_cpu(surfels, &stage.views.screen)?,
        &mut ReceiverViews::default(),
    )
}

/// [`caustics_cpu`] of any water surface (the renderers of [`crate::splat::water`]: splatted
/// surfels, rays cast to the iso-surface, the screen-space surface).
pub fn caustics_of(stage: &Stage, water: &dyn WaterSurface) -> Result<Caustics, crate::Error> {
    caustics_reusing(stage, water, &mut ReceiverViews::default())
}

/// [`caustics_of`] with the light's geometry map taken from `seen` when its view and the
/// receiver are the last frame's (and kept there for the next frame otherwise).
pub fn caustics_reusing(
    stage: &Stage,
    water: &dyn WaterSurface,
    seen: &mut ReceiverViews,
) -> Result<Caustics, crate::Error> {
    Ok(caustics_of_render(
        stage,
        &water.render(&stage.views.screen)?,
        seen,
    )?)
}

/// The receiver as two views of a frame see it, kept from frame to frame while the views and
/// the receiver stay the same (a sequence's kept views and pool): the light's geometry map
/// ([`Caustics::geometry`] and [`Caustics::normals`]) and the first receiver hit of each of the
/// camera's pixel rays (as [`super::receiver::Nearest`], 8 bytes a pixel). Each depends on its
/// view and the receiver alone; found again when either changes (compared exactly), so the
/// frames are those of a fresh computation bit for bit. On the column's splash frame at 512x512
/// they are 189,440 and 262,144 rays a frame.
#[derive(Debug, Default)]
pub struct ReceiverViews {
    map: Option<Seen<MapTexels>>,
    camera: Option<Seen<Vec<Option<super::receiver::Nearest>>>>,
}

/// What one view saw of one receiver.
#[derive(Debug)]
struct Seen<T> {
    view: View,
    triangles: Vec<[Vec3; 3]>,
    container: Option<super::Container>,
    value: T,
}

impl<T> Seen<T> {
    /// What `view` sees of the receiver of `stage`: the kept value when it is of the same view
    /// and receiver, else `make()`, kept for the next call.
    fn of<'a>(
        kept: &'a mut Option<Self>,
        stage: &Stage,
        view: &View,
        make: impl FnOnce() -> T,
    ) -> &'a T {
        let receiver = &stage.receiver;
        let same = kept.as_ref().is_some_and(|k| {
            k.view == *view
                && k.container == receiver.container
                && k.triangles == receiver.triangles
        });
        if !same {
            *kept = Some(Self {
                view: *view,
                triangles: receiver.triangles.clone(),
                container: receiver.container,
                value: make(),
            });
        }
        &kept.as_ref().expect("kept above").value
    }
}

/// `pixel(x, y)` of every pixel of `view`, row-major, in parallel.
fn per_pixel<T: Send>(view: &View, pixel: impl Fn(u32, u32) -> T + Sync) -> Vec<T> {
    let w = view.width;
    (0..(view.width * view.height) as usize)
        .into_par_iter()
        .map(|i| pixel(i as u32 % w, i as u32 / w))
        .collect()
}

/// The light's geometry map ([`MapTexel`] a texel), one array per field: the deposit's tests
/// packed together for its hot loop.
#[derive(Debug)]
struct MapTexels {
    geometry: Vec<[f32; 4]>,
    normals: Vec<[f32; 4]>,
    deposit: Vec<DepositTexel>,
}

impl MapTexels {
    /// The map `map` over the receiver of `stage`.
    fn of(stage: &Stage, map: &View) -> Self {
        let texels = per_pixel(map, |x, y| MapTexel::of(stage, map, (x, y)));
        Self {
            geometry: texels.iter().map(|t| t.geometry).collect(),
            normals: texels.iter().map(|t| t.normal).collect(),
            deposit: texels.iter().map(|t| t.deposit).collect(),
        }
    }
}

/// [`caustics_cpu`] of the water as drawn from the light's screen: the per-pixel buffers of a
/// [`Render`], `(sum w normal, sum w depth)` with their weight, read as the water's normal and
/// depth.
fn caustics_of_render(
    stage: &Stage,
    water: &Render,
    seen: &mut ReceiverViews,
) -> Result<Caustics, OpticsError> {
    let screen = stage.views.screen;
    let map = stage.views.map;
    let ior = stage.scene.water.ior;
    let sigma = stage.scene.water.extinction;
    let eps = 1e-5 * stage.size;
    let (sw, sh) = (screen.width, screen.height);
    // 1.-3. water point, refracted ray and its hit on the receiver, per screen pixel
    let vertices: Vec<CausticVertex> = (0..(sw * sh) as usize)
        .into_par_iter()
        .map(|i| {
            let Some((n_acc, depth)) = water_at(water, i) else {
                return CausticVertex::default();
            };
            let (x, y) = (i as u32 % sw, i as u32 / sw);
            let s = point_at(&screen, x, y, depth);
            // the water outside its container (through a wall) sends no light (issue 41)
            if !stage.holds_water(s) {
                return CausticVertex::default();
            }
            let (inc, _) = stage.incoming(s);
            let n = unit_or(n_acc, -inc);
            let cos_i = -n.dot(inc);
            let (dir, mut transmittance) = match refract(inc, n, 1.0, ior) {
                Some(t) if cos_i > 0.0 => (t, 1.0 - fresnel_reflectance(cos_i, 1.0, ior)),
                _ => (inc, 0.0),
            };
            // water the receiver shades from the light (behind a pool wall, seen from the
            // light) receives no light, so it sends none into the water. Found on the column's
            // splash frame: a third of the water pixels of the light's screen lie in the walls'
            // shadow, and without this test they lit the floor and the walls' far sides.
            if stage.light_blocked(s, eps) {
                transmittance = 0.0;
            }
            let mut v = CausticVertex {
                surface: s.extend(depth),
                ..Default::default()
            };
            if let Some(h) = stage.receiver.intersect(s, dir, eps) {
                // w = 2: the ray met the side of a surface that faces away from the light (the
                // inside of a thin wall); the light's map holds only the side it sees
                let side = if h.normal.dot(-inc) > 0.0 { 1.0 } else { 2.0 };
                v.hit = h.position.extend(side);
                v.transmit = transmittance * (-sigma * h.t).exp();
            }
            v
        })
        .collect();
    // the geometry map: the receiver seen from the light, per map texel, with each texel's
    // deposit test (kept while the map's view and the receiver stay)
    let texels = Seen::of(&mut seen.map, stage, &map, || MapTexels::of(stage, &map));
    let (geometry, normals) = (texels.geometry.clone(), texels.normals.clone());
    // 4. caustics triangles: their fates in parallel, deposited band by band (deterministic)
    let fates = fates_of(stage, &screen, &map, &vertices, &geometry);
    let deposits: Vec<([Vec3; 3], Vec3)> = fates
        .iter()
        .filter_map(|f| match *f {
            Fate::Deposit { q, flux, .. } => Some((q, flux)),
            _ => None,
        })
        .collect();
    let (flux, share) = deposit_in_bands(&deposits, &map, &texels.deposit);
    let mut out = Caustics {
        screen,
        map,
        vertices: Vec::new(),
        flux: Vec::new(),
        irradiance: Vec::new(),
        geometry,
        normals,
        incident: Vec3::ZERO,
        transmitted: Vec3::ZERO,
        triangles: 0,
        discontinuous: 0,
        missed: 0,
        hidden: 0,
        dropped: Vec3::ZERO,
    };
    // the sums over the triangles, in order
    let mut next_deposit = 0;
    for fate in &fates {
        match *fate {
            Fate::Other(TriangleFlux::NoWater) | Fate::Other(TriangleFlux::Lit { .. }) => {}
            Fate::Other(TriangleFlux::Discontinuous(incident)) => {
                out.incident += incident;
                out.discontinuous += 1;
            }
            Fate::Other(TriangleFlux::Missed(incident)) => {
                out.incident += incident;
                out.missed += 1;
            }
            Fate::Hidden { incident, flux: f } => {
                out.incident += incident;
                out.hidden += 1;
                out.dropped += f;
            }
            Fate::Deposit {
                incident, flux: f, ..
            } => {
                out.incident += incident;
                let share = share[next_deposit];
                next_deposit += 1;
                out.transmitted += f * share;
                out.dropped += f * (1.0 - share);
                if share > 0.0 {
                    out.triangles += 1;
                } else {
                    out.hidden += 1;
                }
            }
        }
    }
    out.irradiance = flux
        .par_iter()
        .enumerate()
        .map(|(i, f)| irradiance_of(&map, i, *f, out.geometry[i], out.normals[i]))
        .collect();
    out.flux = flux;
    out.vertices = vertices;
    Ok(out)
}

/// Irradiance of a map texel from its flux, `texel_irradiance` in the WGSL.
pub(crate) fn irradiance_of(
    map: &View,
    i: usize,
    flux: [f32; 4],
    geometry: [f32; 4],
    normal: [f32; 4],
) -> [f32; 4] {
    if !(geometry[3] > 0.0) {
        return [0.0; 4];
    }
    let (x, y) = (i as u32 % map.width, i as u32 / map.width);
    let (_, d) = map.world_ray(Vec2::new(x as f32 + 0.5, y as f32 + 0.5));
    let area = texel_area(map, d, geometry[3], Vec4::from(normal).truncate());
    let e = Vec3::new(flux[0], flux[1], flux[2]) / area;
    e.extend(1.0).to_array()
}

/// What one water triangle contributes.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum TriangleFlux {
    /// A vertex without water: not part of the surface.
    NoWater,
    /// Spans a depth discontinuity: its incident flux, dropped.
    Discontinuous(Vec3),
    /// A refracted ray missed the receiver: its incident flux, lost.
    Missed(Vec3),
    /// Incident flux and the flux it carries to the receiver.
    Lit { incident: Vec3, flux: Vec3 },
}

/// Each caustics triangle's fate (two a screen pixel, in pixel order), in parallel: eq. 3 over
/// the screen's `vertices`, the hidden test against the map's `geometry`, the projection into
/// the `map`.
fn fates_of(
    stage: &Stage,
    screen: &View,
    map: &View,
    vertices: &[CausticVertex],
    geometry: &[[f32; 4]],
) -> Vec<Fate> {
    let (sw, sh) = (screen.width, screen.height);
    let limit = stage.scene.optics.discontinuity;
    // each triangle's fate, in parallel (two a pixel, in pixel order)
    let quads = (sw.saturating_sub(1) * sh.saturating_sub(1)) as usize;
    (0..2 * quads)
        .into_par_iter()
        .map(|t| {
            let (x, y) = ((t / 2) as u32 % (sw - 1), (t / 2) as u32 / (sw - 1));
            let k = |dx: u32, dy: u32| ((y + dy) * sw + x + dx) as usize;
            let tri = if t % 2 == 0 {
                [k(0, 0), k(1, 0), k(0, 1)]
            } else {
                [k(1, 1), k(0, 1), k(1, 0)]
            };
            let v = tri.map(|j| vertices[j]);
            match triangle_flux(stage, screen, &v, limit) {
                TriangleFlux::Lit { incident, flux } => {
                    // the map's texels belong to the surfaces the light sees: light that a
                    // refracted ray brings to a receiver point hidden from the light, or to
                    // the side of a surface facing away from it (the inside of a thin wall),
                    // cannot be kept in the map without lighting the surface the light sees
                    // there (the wall's outer face), so it is dropped (GPU: the same)
                    if v.iter()
                        .any(|c| c.hit.w > 1.5 || hidden_in_map(map, geometry, c.hit.truncate()))
                    {
                        Fate::Hidden { incident, flux }
                    } else {
                        Fate::Deposit {
                            incident,
                            flux,
                            q: v.map(|c| map.project(c.hit.truncate())),
                        }
                    }
                }
                other => Fate::Other(other),
            }
        })
        .collect()
}

/// The caustics map of the `deposits` (each triangle's projected vertices and flux, in order)
/// and each one's share deposited ([`deposit_owned`]), band by band of the map's rows at once:
/// each band's texels take their shares in triangle order (the same sums as one pass over the
/// triangles); each band lists the shares of the triangles it reaches, and a triangle's share
/// is the sum of its bands', in band order.
fn deposit_in_bands(
    deposits: &[([Vec3; 3], Vec3)],
    map: &View,
    texels: &[DepositTexel],
) -> (Vec<[f32; 4]>, Vec<f32>) {
    let (mw, mh) = (map.width, map.height);
    let band_rows = mh.div_ceil(MAP_BANDS).max(1);
    let mut flux = vec![[0.0f32; 4]; (mw * mh) as usize];
    let band_shares: Vec<Vec<(u32, f32)>> = flux
        .par_chunks_mut((band_rows * mw).max(1) as usize)
        .enumerate()
        .map(|(b, band)| {
            let rows = b as u32 * band_rows..((b as u32 + 1) * band_rows).min(mh);
            let mut shares = Vec::new();
            for (t, &(q, f)) in deposits.iter().enumerate() {
                let (lo, hi) = q.iter().fold((f32::MAX, f32::MIN), |(lo, hi), p| {
                    (lo.min(p.y), hi.max(p.y))
                });
                // a band no row of the triangle's box reaches takes nothing
                if hi >= rows.start as f32 - 1.0 && lo <= rows.end as f32 + 1.0 {
                    let share = deposit_owned((&mut *band, rows.clone()), map, texels, q, f);
                    shares.push((t as u32, share));
                }
            }
            shares
        })
        .collect();
    let mut share = vec![0.0f32; deposits.len()];
    for (t, s) in band_shares.into_iter().flatten() {
        share[t as usize] += s;
    }
    (flux, share)
}

/// Bands of the caustics map's rows that take their triangles' deposits at once.
const MAP_BANDS: u32 = 16;

/// What becomes of a caustics triangle ([`caustics_of`]).
#[derive(Clone, Copy)]
enum Fate {
    /// No water, a discontinuity or a miss ([`TriangleFlux`]).
    Other(TriangleFlux),
    /// Lit, but a vertex's receiver point is hidden from the light: its flux is dropped.
    Hidden { incident: Vec3, flux: Vec3 },
    /// Lit: deposited into the map at the projected vertices `q`.
    Deposit {
        incident: Vec3,
        flux: Vec3,
        q: [Vec3; 3],
    },
}

/// Eq. 3 for one triangle (see the module docs): `triangle_flux` in the WGSL.
pub fn triangle_flux(
    stage: &Stage,
    screen: &View,
    v: &[CausticVertex; 3],
    discontinuity: f32,
) -> TriangleFlux {
    if v.iter().any(|c| !(c.surface.w > 0.0)) {
        return TriangleFlux::NoWater;
    }
    let s = v.map(|c| c.surface.truncate());
    let centroid = (s[0] + s[1] + s[2]) / 3.0;
    let (inc, e_perp) = stage.incoming(centroid);
    let area = 0.5 * (s[1] - s[0]).cross(s[2] - s[0]).dot(inc).abs();
    let incident = e_perp * area;
    let (d0, d1) = v.iter().fold((f32::MAX, f32::MIN), |(a, b), c| {
        (a.min(c.surface.w), b.max(c.surface.w))
    });
    if d1 - d0 > discontinuity * pixel_size(screen, d1) {
        return TriangleFlux::Discontinuous(incident);
    }
    if v.iter().any(|c| !(c.hit.w > 0.0)) {
        return TriangleFlux::Missed(incident);
    }
    let transmit = (v[0].transmit + v[1].transmit + v[2].transmit) / 3.0;
    TriangleFlux::Lit {
        incident,
        flux: incident * transmit,
    }
}

impl Caustics {
    /// Total flux in the map.
    #[must_use]
    pub fn total_flux(&self) -> Vec3 {
        self.flux
            .iter()
            .fold(Vec3::ZERO, |a, f| a + Vec3::new(f[0], f[1], f[2]))
    }

    /// Caustics irradiance at a receiver point `p` of normal `n` (`caustics_at` in the WGSL):
    /// bilinear over the four map texels around it, each counted only where it shows the same
    /// surface (a normal within 60 degrees of `n`, a depth within a slope-scaled bias: 1.5
    /// texels plus twice the surface's depth change across a texel), the weights renormalised. A plain bilinear sample mixed the
    /// floor's caustics into the narrow strip of texels of a wall's outer face next to it.
    #[must_use]
    pub fn irradiance_at(&self, p: Vec3, n: Vec3) -> Vec3 {
        let v = &self.map;
        let q = v.project(p);
        if !q.is_finite() {
            return Vec3::ZERO;
        }
        let (w, h) = (v.width as i64, v.height as i64);
        let (x, y) = (q.x - 0.5, q.y - 0.5);
        if x < -1.0 || y < -1.0 || x > w as f32 || y > h as f32 {
            return Vec3::ZERO;
        }
        let bias = depth_bias(v, Vec2::new(q.x, q.y), q.z, n);
        let (fx, fy) = (x.floor(), y.floor());
        let (tx, ty) = (x - fx, y - fy);
        let (mut sum, mut weight) = (Vec3::ZERO, 0.0);
        for (di, dj, wt) in [
            (0, 0, (1.0 - tx) * (1.0 - ty)),
            (1, 0, tx * (1.0 - ty)),
            (0, 1, (1.0 - tx) * ty),
            (1, 1, tx * ty),
        ] {
            let k =
                ((fy as i64 + dj).clamp(0, h - 1) * w + (fx as i64 + di).clamp(0, w - 1)) as usize;
            let g = self.geometry[k];
            let gn = Vec3::new(self.normals[k][0], self.normals[k][1], self.normals[k][2]);
            if g[3] > 0.0 && gn.dot(n) > 0.5 && (g[3] - q.z).abs() <= bias {
                let e = self.irradiance[k];
                sum += Vec3::new(e[0], e[1], e[2]) * wt;
                weight += wt;
            }
        }
        if weight > 0.0 {
            sum / weight
        } else {
            Vec3::ZERO
        }
    }

    /// How much of the light's screen about `p` sees water nearer the light than `p`
    /// (`water_cover` in the WGSL), in [0, 1]: the four texels about `p`, bilinearly weighted
    /// (percentage-closer filtering). The direct light reaching `p` is `1 - cover` of the
    /// light's. Tested per texel (the texel under `p` sees water or not) the direct light
    /// switched on and off along texel edges: saw-tooth edges where the water's shadow ends, and
    /// each small drop a whole-texel square of shadow (the dark blocky patches above the dam
    /// break's far wall, issue 14). Filtered, the light fades over one texel instead.
    #[must_use]
    pub fn water_cover(&self, p: Vec3) -> f32 {
        let v = &self.screen;
        let q = v.project(p);
        if !q.is_finite() {
            return 0.0;
        }
        let (w, h) = (v.width as i64, v.height as i64);
        let (x, y) = (q.x - 0.5, q.y - 0.5);
        if x < -1.0 || y < -1.0 || x > w as f32 || y > h as f32 {
            return 0.0;
        }
        let (fx, fy) = (x.floor(), y.floor());
        let (tx, ty) = (x - fx, y - fy);
        let mut cover = 0.0;
        for (di, dj, wt) in [
            (0, 0, (1.0 - tx) * (1.0 - ty)),
            (1, 0, tx * (1.0 - ty)),
            (0, 1, (1.0 - tx) * ty),
            (1, 1, tx * ty),
        ] {
            // texels off the screen see no water, as before the filter
            let (i, j) = (fx as i64 + di, fy as i64 + dj);
            if i < 0 || j < 0 || i >= w || j >= h {
                continue;
            }
            let d = self.vertices[(j * w + i) as usize].surface.w;
            if d > 0.0 && d < q.z {
                cover += wt;
            }
        }
        cover
    }

    /// A picture of the map: the irradiance arriving on the receiver as the light sees it
    /// (direct light where no water covers it, plus the caustics), the light's own irradiance
    /// shown as mid grey, gamma-encoded.
    #[must_use]
    pub fn image(&self, stage: &Stage) -> RgbaImage {
        let centre = (stage.receiver.bounds().0 + stage.receiver.bounds().1) * 0.5;
        let reference = stage.incoming(centre).1.max_element().max(1e-30);
        RgbaImage::from_fn(self.map.width, self.map.height, |x, y| {
            let i = (y * self.map.width + x) as usize;
            let g = self.geometry[i];
            if !(g[3] > 0.0) {
                return image::Rgba([0, 0, 0, 255]);
            }
            let p = Vec3::new(g[0], g[1], g[2]);
            let n = Vec4::from(self.normals[i]).truncate();
            let e = receiver_irradiance(stage, self, p, n);
            let [r, g, b] = encode(e * (0.5 / reference));
            image::Rgba([r, g, b, 255])
        })
    }
}

/// The texel of `v` under the world point `p` (row-major index) and `p`'s pixel coordinates and
/// depth; `None` off the view. `texel_of` in the WGSL.
fn texel_of(v: &View, p: Vec3) -> Option<(usize, Vec3)> {
    let q = v.project(p);
    // NaN-safe: NaN fails the comparisons
    if !(q.x >= 0.0 && q.y >= 0.0 && q.x < v.width as f32 && q.y < v.height as f32) {
        return None;
    }
    Some(((q.y as u32 * v.width + q.x as u32) as usize, q))
}

/// Whether a receiver point lies behind the surface the light's geometry map sees at its texel
/// (by more than three texels), i.e. is hidden from the light.
fn hidden_in_map(map: &View, geometry: &[[f32; 4]], p: Vec3) -> bool {
    texel_of(map, p).is_some_and(|(i, q)| {
        let g = geometry[i][3];
        g > 0.0 && g < q.z - 3.0 * pixel_size(map, q.z)
    })
}

/// Irradiance arriving at the receiver point `p` (normal `n`, either side): direct light where
/// neither the water nor the receiver covers it, plus the caustics. `receiver_irradiance` in
/// the WGSL.
#[must_use]
pub fn receiver_irradiance(stage: &Stage, c: &Caustics, p: Vec3, n: Vec3) -> Vec3 {
    let (inc, e) = stage.incoming(p);
    let facing = n.dot(-inc);
    // the caustics map is the light's view: its texels belong to the surfaces the light sees,
    // so a point turned away from the light or shadowed by the receiver reads none of it (it
    // lit the outer faces of the pool's walls with the caustics of the floor behind them). The
    // receiver's own shadow is found by an exact ray towards the light: the light's geometry map
    // (the GPU's test for large receivers) leaks light near contacts, where the occluder is
    // nearer than its depth bias (the top of one wall over the corner of the next: 78 of 13,312
    // dry pixels off in tests/optics.rs, 0 with the ray)
    let eps = 1e-5 * stage.size;
    if !(facing > 0.0) || stage.light_blocked(p + n * eps, eps) {
        return Vec3::ZERO;
    }
    // an outer face of the container: the light reaching it crosses no water (see
    // `ReceiverGeometry::outer_face`), and the light's maps, whose texels there may show the water or
    // the floor behind the wall's edge, are not read (issue 41: dark streaks of the water's
    // cover and the caustics of the floor on the tank's sunlit outer faces)
    if stage.receiver.outer_face(p, n) {
        return e * facing;
    }
    let direct = e * facing * (1.0 - c.water_cover(p));
    direct + c.irradiance_at(p, n)
}

/// Radiance of the receiver at `p` seen along `view_dir` (eq. 3's `f_r E + L_a`).
fn receiver_radiance(stage: &Stage, c: &Caustics, p: Vec3, n: Vec3) -> Vec3 {
    stage.albedo(p, n) * receiver_irradiance(stage, c, p, n) + stage.scene.light.ambient
}

/// A finished frame.
#[derive(Clone, Debug, PartialEq)]
pub struct FrameImage {
    /// Display image (gamma-encoded).
    pub image: RgbaImage,
    /// Linear radiance per pixel, row-major from the top (`w = 1` where water covers it).
    pub linear: Vec<[f32; 4]>,
    /// The camera's splatting of the water (eq. 2 buffers).
    pub water: Render,
}

/// The final image (§5.2), CPU reference: splatted water from the camera, per pixel Fresnel blend
/// of the reflected ray's environment and the refracted ray's receiver (with caustics),
/// attenuated by `exp(-sigma_t l)`; the receiver and environment where there is no water.
pub fn frame_cpu(
    stage: &Stage,
    surfels: &[Surfel],
    caustics: &Caustics,
    size: (u32, u32),
) -> Result<FrameImage, OpticsError> {
    let view = camera_view(stage, size)?;
    let water = render_view_cpu(surfels, &view)?;
    frame_of_render(stage, &view, water, caustics, &mut ReceiverViews::default())
}

/// [`frame_cpu`] of any water surface.
pub fn frame_of(
    stage: &Stage,
    water: &dyn WaterSurface,
    caustics: &Caustics,
    size: (u32, u32),
) -> Result<FrameImage, crate::Error> {
    frame_reusing(stage, water, caustics, size, &mut ReceiverViews::default())
}

/// [`frame_of`] with the camera's receiver hits taken from `seen` when its view and the receiver
/// are the last frame's (and kept there for the next frame otherwise).
pub fn frame_reusing(
    stage: &Stage,
    water: &dyn WaterSurface,
    caustics: &Caustics,
    size: (u32, u32),
    seen: &mut ReceiverViews,
) -> Result<FrameImage, crate::Error> {
    let view = camera_view(stage, size)?;
    let water = water.render(&view)?;
    Ok(frame_of_render(stage, &view, water, caustics, seen)?)
}

/// The camera's view of the finished frame, `size` pixels.
fn camera_view(stage: &Stage, size: (u32, u32)) -> Result<View, OpticsError> {
    Ok(View::new(
        &stage.camera,
        &Light::default(),
        &stage.scene.optics.splat,
        size.0,
        size.1,
    )?)
}

/// [`frame_cpu`] of the water as drawn from the camera's `view`.
fn frame_of_render(
    stage: &Stage,
    view: &View,
    water: Render,
    caustics: &Caustics,
    seen: &mut ReceiverViews,
) -> Result<FrameImage, OpticsError> {
    let size = (view.width, view.height);
    let ray = |x: u32, y: u32| view.world_ray(Vec2::new(x as f32 + 0.5, y as f32 + 0.5));
    // the receiver each pixel's ray meets first (kept while the view and the receiver stay)
    let hits = Seen::of(&mut seen.camera, stage, view, || {
        per_pixel(view, |x, y| {
            let (o, d) = ray(x, y);
            stage.receiver.nearest(o, d.normalize(), 0.0)
        })
    });
    let linear: Vec<[f32; 4]> = (0..(size.0 * size.1) as usize)
        .into_par_iter()
        .map(|i| {
            let (x, y) = (i as u32 % size.0, i as u32 / size.0);
            let (o, d) = ray(x, y);
            let dn = d.normalize();
            // the water where it lies in front of the receiver (an opaque wall may hide it)
            let len = d.length();
            let receiver = hits[i].map(|near| stage.receiver.hit_at(o, dn, near));
            // and inside its container (what reaches through a wall is not water: issue 41)
            match water_at(&water, i) {
                Some((n_acc, depth))
                    if receiver.is_none_or(|h| h.t / len >= depth)
                        && stage.holds_water(o + d * depth) =>
                {
                    let p = o + d * depth;
                    water_pixel(stage, caustics, p, dn, unit_or(n_acc, -dn)).extend(1.0)
                }
                _ => dry_pixel(stage, caustics, receiver, dn).extend(0.0),
            }
            .to_array()
        })
        .collect();
    // the sRGB encoding row by row in parallel (one pass of the column's splash frame at
    // 512x512: 6.8 ms on one thread)
    let mut image = RgbaImage::new(size.0, size.1);
    image
        .as_mut()
        .par_chunks_mut(4 * size.0 as usize)
        .zip(linear.par_chunks(size.0 as usize))
        .for_each(|(row, values)| {
            for (px, v) in row.chunks_exact_mut(4).zip(values) {
                let [r, g, b] = encode(Vec4::from(*v).truncate());
                px.copy_from_slice(&[r, g, b, 255]);
            }
        });
    Ok(FrameImage {
        image,
        linear,
        water,
    })
}

fn dry_pixel(
    stage: &Stage,
    caustics: &Caustics,
    hit: Option<super::receiver::Hit>,
    dn: Vec3,
) -> Vec3 {
    match hit {
        Some(h) => receiver_radiance(stage, caustics, h.position, h.normal),
        None => stage.scene.environment.colour(dn),
    }
}

/// One water pixel: `water_pixel` in the WGSL (there the refracted ray's hit comes from the
/// geometry-map search instead of the BVH).
fn water_pixel(stage: &Stage, caustics: &Caustics, p: Vec3, dn: Vec3, n: Vec3) -> Vec3 {
    let ior = stage.scene.water.ior;
    let sigma = stage.scene.water.extinction;
    let mut n = n;
    let mut cos_i = -n.dot(dn);
    if cos_i < 0.0 {
        n = -n;
        cos_i = -cos_i;
    }
    let reflected = stage.scene.environment.colour(dn + 2.0 * cos_i * n);
    let r = fresnel_reflectance(cos_i, 1.0, ior);
    let refracted = match refract(dn, n, 1.0, ior) {
        Some(t) => match stage.receiver.intersect(p, t, 1e-5 * stage.size) {
            Some(h) => {
                receiver_radiance(stage, caustics, h.position, h.normal) * (-sigma * h.t).exp()
            }
            None => stage.scene.environment.colour(t) * (-sigma * stage.size).exp(),
        },
        None => Vec3::ZERO,
    };
    reflected * r + refracted * (1.0 - r)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Triangles rasterised band by band of rows give every texel the shares of one pass over
    /// all rows, bit for bit, and the same total share up to rounding (what [`caustics_of`]
    /// relies on to deposit bands at once).
    #[test]
    fn rows_in_bands_give_the_shares_of_one_pass() {
        let (w, h) = (37u32, 29u32);
        let triangles: Vec<[Vec2; 3]> = (0..200)
            .map(|i| {
                let t = i as f32 * 0.71;
                let c = Vec2::new(18.0 + 17.0 * t.sin(), 14.0 + 15.0 * (1.3 * t).cos());
                let r = 0.3 + (i % 9) as f32;
                [
                    c,
                    c + Vec2::new(r, 0.4 * r),
                    c + Vec2::new(-0.3 * r, r * (i % 3) as f32 * 0.5),
                ]
            })
            .collect();
        let pass = |bands: &[std::ops::Range<u32>]| {
            let mut map = vec![0.0f32; (w * h) as usize];
            let mut totals = Vec::new();
            for p in &triangles {
                let mut total = 0.0f32;
                for rows in bands {
                    let mut part = 0.0f32;
                    rasterise(w, h, *p, rows.clone(), |x, y, share| {
                        map[(y * w + x) as usize] += share;
                        part += share;
                    });
                    total += part;
                }
                totals.push(total);
            }
            (map, totals)
        };
        let all = 0..h;
        let (whole, whole_totals) = pass(std::slice::from_ref(&all));
        let (banded, banded_totals) = pass(&[0..5, 5..6, 6..17, 17..h]);
        assert_eq!(whole, banded);
        assert!(whole.iter().any(|&v| v > 0.0));
        for (a, b) in whole_totals.iter().zip(&banded_totals) {
            assert!((a - b).abs() <= 1e-6 * a.max(1.0), "{a} {b}");
        }
    }

    /// A triangle inside the map gives away all of its area: its shares sum to 1 (the texels a
    /// row visits are only those its piece of the triangle reaches, and none is missed), for
    /// large, tiny and sliver triangles of either orientation.
    #[test]
    fn a_triangle_inside_the_map_deposits_its_whole_area() {
        let (w, h) = (64u32, 48u32);
        for i in 0..400 {
            let t = i as f32 * 0.37;
            let c = Vec2::new(32.0 + 15.0 * t.sin(), 24.0 + 8.0 * (1.7 * t).cos());
            let size = [0.05, 0.6, 3.0, 11.0][i % 4];
            let a = Vec2::new((2.3 * t).cos(), (2.3 * t).sin()) * size;
            // every third a sliver: its third vertex close to the line of the other two
            let b = if i % 3 == 0 {
                a.perp() * 0.01 - a * 0.7
            } else {
                Vec2::new((3.1 * t + 1.0).cos(), (3.1 * t + 1.0).sin()) * size
            };
            let p = if i % 2 == 0 {
                [c, c + a, c + b]
            } else {
                [c, c + b, c + a]
            };
            let mut total = 0.0f64;
            rasterise(w, h, p, 0..h, |x, y, share| {
                assert!(x < w && y < h && share > 0.0, "texel {x},{y} share {share}");
                total += f64::from(share);
            });
            // (a sliver of a twentieth of a texel keeps its area to about 1e-3: the clipping's
            // rounding against an area of 1e-5 texels)
            assert!(
                (total - 1.0).abs() < 5e-3,
                "triangle {i} {p:?}: shares sum to {total}"
            );
        }
    }
}
