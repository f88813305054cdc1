//! The CPU reference of ray casting: exact sphere intervals per ray, a march with bisection
//! through them, normals at the hits, the bilateral filter, shading. Parallel over pixels; every
//! pixel's result depends on nothing but its own ray, so the image does not depend on the thread
//! count.

use glam::{Vec2, Vec3};
use rayon::prelude::*;

use super::{Caster, RayCast, RayCastError, bilateral, surface_normal};
use crate::splat::{Camera, Light, Render, SplatParams, View};
use crate::view::{TILE, bin};

/// One pixel's ray: where it enters the first sphere, the water's thickness along it, the hit
/// (view depth, unfiltered normal) and the density samples it took.
struct PixelRay {
    entry: f32,
    thickness: f32,
    hit: Option<(f32, Vec3)>,
    samples: u64,
}

/// Ray casting of the caster's points from `camera` at `width` x `height`; `splat` gives the
/// background (and the cost limits), `light` the shading.
pub fn render_cpu(
    caster: &Caster<'_>,
    camera: &Camera,
    light: &Light,
    splat: &SplatParams,
    width: u32,
    height: u32,
) -> Result<RayCast, RayCastError> {
    let v = View::new(camera, light, splat, width, height)?;
    render_view_cpu(caster, &v)
}

/// One pixel's ray: the depth intervals of the spheres it crosses (merged, in order) and the
/// water thickness their chords stand for ([`VOLUME_SHARE`]).
fn intervals_of(
    caster: &Caster<'_>,
    members: &[u32],
    o: Vec3,
    d: Vec3,
    out: &mut Vec<(f32, f32)>,
) -> f32 {
    let points = caster.points();
    let a = d.length_squared();
    let mut chords = 0.0;
    out.clear();
    for &j in members {
        let j = j as usize;
        let r = points.radius(j);
        let oc = o - points.positions[j];
        let b = oc.dot(d);
        let disc = b * b - a * (oc.length_squared() - r * r);
        if disc.is_nan() || disc <= 0.0 {
            continue;
        }
        let root = disc.sqrt();
        let t0 = ((-b - root) / a).max(0.0);
        let t1 = (-b + root) / a;
        if t1 > t0 {
            chords += t1 - t0;
            out.push((t0, t1));
        }
    }
    out.sort_by(|p, q| p.0.total_cmp(&q.0));
    let mut merged = 0;
    for k in 0..out.len() {
        if merged > 0 && out[k].0 <= out[merged - 1].1 {
            out[merged - 1].1 = out[merged - 1].1.max(out[k].1);
        } else {
            out[merged] = out[k];
            merged += 1;
        }
    }
    out.truncate(merged);
    chords * a.sqrt() * VOLUME_SHARE
}

/// The thickness of water one sphere's chord stands for: the spheres of neighbouring points
/// overlap, each point's own volume being about `(r / 2)^3` (its radius is twice the spacing)
/// of its sphere's `4/3 pi r^3`, so the summed chords are scaled by `3 / (32 pi)` to estimate the
/// water's depth along the ray (a slab of n layers gives about n spacings).
const VOLUME_SHARE: f32 = 3.0 / (32.0 * std::f32::consts::PI);

/// [`render_cpu`] for a prepared view (perspective or orthographic, such as a light's screen).
/// Refused before casting, like the splats, when the spheres' screen rectangles add up to more
/// pixels than the view's limit or the buffers would not fit in memory, and for a caster whose
/// weights are on the GPU ([`Caster::with_weights_on_gpu`]).
pub fn render_view_cpu(caster: &Caster<'_>, v: &View) -> Result<RayCast, RayCastError> {
    if caster.density().is_none() {
        return Err(RayCastError::InvalidParameter {
            name: "caster",
            reason: "its weights were solved on the GPU and stay there: the CPU cannot cast it"
                .into(),
        });
    }
    let (w, h) = (v.width as usize, v.height as usize);
    let points = caster.points();
    let params = &caster.params;
    // 1. the spheres binned into screen tiles
    let (tw, tiles) = bin_spheres(caster, v)?;
    // 2. per pixel: the sphere intervals, the first crossing, the normal there
    let dt_world = params.step * points.min_radius();
    let per_pixel: Vec<PixelRay> = (0..w * h)
        .into_par_iter()
        .map_init(Vec::new, |intervals, i| {
            let (x, y) = (i % w, i / w);
            let (o, d) = v.world_ray(Vec2::new(x as f32 + 0.5, y as f32 + 0.5));
            let thickness =
                intervals_of(caster, &tiles[(y / TILE) * tw + x / TILE], o, d, intervals);
            let entry = intervals.first().map_or(f32::INFINITY, |s| s.0);
            let mut samples = 0;
            let dt = dt_world / d.length();
            let hit = caster
                .first_crossing(o, d, intervals, dt, &mut samples)
                .and_then(|t| surface_normal(caster, o + t * d).map(|n| (t, n)));
            PixelRay {
                entry,
                thickness,
                hit,
                samples,
            }
        })
        .collect();
    // 3. the bilateral filter of the normal map
    let normals: Vec<Option<Vec3>> = per_pixel.iter().map(|p| p.hit.map(|h| h.1)).collect();
    let depths: Vec<f32> = per_pixel
        .iter()
        .map(|p| p.hit.map_or(0.0, |h| h.0))
        .collect();
    let filtered = bilateral(
        &normals,
        &depths,
        w,
        h,
        params.bilateral_radius_px,
        params.bilateral_sigma_px,
        params.bilateral_sigma_depth * points.h,
    );
    let hits: Vec<Option<(f32, Vec3)>> = per_pixel
        .iter()
        .zip(&filtered)
        .map(|(p, n)| p.hit.and_then(|(t, _)| n.map(|n| (t, n))))
        .collect();
    Ok(finish(
        caster,
        v,
        &hits,
        per_pixel.iter().map(|p| p.thickness).collect(),
        per_pixel.iter().map(|p| p.entry).collect(),
        per_pixel.iter().map(|p| p.samples).sum(),
    ))
}

/// The spheres binned into the screen's 16x16 tiles: tiles along x and each tile's spheres, in
/// order. Refused, like the splats, when the spheres' rectangles add up to more pixels than the
/// view's limit or the buffers would not fit in memory.
pub(crate) fn bin_spheres(
    caster: &Caster<'_>,
    v: &View,
) -> Result<(usize, Vec<Vec<u32>>), RayCastError> {
    let points = caster.points();
    Ok(bin(v, points.len(), |j| {
        (points.positions[j], points.radius(j))
    })?)
}

/// The result from each pixel's hit (view depth and filtered normal), thickness and entry: the
/// buffers (`(tinted colour, 1)`, `(normal, depth)`) and the shaded image (`splat::shade`).
pub(crate) fn finish(
    caster: &Caster<'_>,
    v: &View,
    hits: &[Option<(f32, Vec3)>],
    thickness: Vec<f32>,
    entry: Vec<f32>,
    samples: u64,
) -> RayCast {
    let n = hits.len();
    let points = caster.points();
    let base = Vec3::from_slice(&crate::splat::WATER[..3]);
    let absorption = Vec3::from(caster.params.absorption) / points.h;
    let mut colour = vec![[0.0f32; 4]; n];
    let mut normal_depth = vec![[0.0f32; 4]; n];
    for (i, hit) in hits.iter().enumerate() {
        if let Some((t, normal)) = *hit {
            let tint = base * (-absorption * thickness[i]).exp();
            colour[i] = tint.extend(1.0).to_array();
            normal_depth[i] = normal.extend(t).to_array();
        }
    }
    let image = crate::splat::cpu::shade_image(&colour, &normal_depth, v);
    RayCast {
        render: Render {
            width: v.width,
            height: v.height,
            image,
            colour,
            normal_depth,
        },
        thickness,
        entry,
        samples,
    }
}
