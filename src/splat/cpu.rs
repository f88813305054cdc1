//! The CPU reference of the three splatting passes: the specification the GPU twin
//! ([`super::gpu`]) is tested against. Parallel over bands of rows; within a band, surfels blend
//! in their order, so the image does not depend on the thread count.

use glam::{Vec2, Vec3, Vec4, Vec4Swizzles};
use image::RgbaImage;
use rayon::prelude::*;

use super::{
    Camera, Fragment, Frame, Light, Render, SplatError, SplatMode, SplatParams, Surfel, View,
    fragment, frame, shade, weight,
};

/// Converts a shaded pixel to 8 bits as an `Rgba8Unorm` store does (round to nearest).
pub(crate) fn to_unorm8(c: Vec4) -> [u8; 4] {
    c.to_array()
        .map(|x| (x.clamp(0.0, 1.0) * 255.0).round() as u8)
}

/// Rows per parallel band of the CPU renderer.
const BAND: usize = 8;

/// A fragment of a band's first pass kept for its second: its pixel in the band, its surfel
/// and what the weight and the sums read (20 bytes: the whole [`Fragment`] with its pixel and
/// surfel was 40, and the bands' passes are bound by what the two cores share; a sphere's
/// normal and depth offset are kept beside, for [`SplatMode::Spheres`] alone).
struct Kept {
    pixel: u32,
    surfel: u32,
    r2: f32,
    depth: f32,
    ndc: f32,
}

/// A surfel as the CPU renderer places it: its frame, colour, unit normal, and the pixel
/// columns and rows (half-open) whose centres lie in its rectangle.
struct Placed {
    frame: Frame,
    colour: [f32; 4],
    normal: Vec3,
    xs: (usize, usize),
    ys: (usize, usize),
}

impl Placed {
    /// A surfel set up for the view; `None`: not drawn (undrawable or culled).
    fn of(s: &Surfel, v: &View) -> Option<Self> {
        if !s.is_drawable() {
            return None;
        }
        let f = frame(s, v)?;
        let span = super::pixel_span;
        Some(Self {
            xs: span(f.rect.x, f.rect.z, v.width as usize),
            ys: span(f.rect.y, f.rect.w, v.height as usize),
            colour: s.colour,
            normal: Vec3::from(s.normal).normalize(),
            frame: f,
        })
    }
}

/// The CPU reference of the three passes (the specification of the GPU path). Undrawable
/// surfels (see [`Surfel::is_drawable`]) are skipped.
pub fn render_cpu(
    surfels: &[Surfel],
    camera: &Camera,
    light: &Light,
    params: &SplatParams,
    width: u32,
    height: u32,
) -> Result<Render, SplatError> {
    let v = View::new(camera, light, params, width, height)?;
    render_view_cpu(surfels, &v)
}

/// [`render_cpu`] for a prepared view; refused before rasterising when the splats would cost
/// more pixel fragments than the view's limit ([`SplatError::TooCostly`]).
pub fn render_view_cpu(surfels: &[Surfel], v: &View) -> Result<Render, SplatError> {
    let (w, h) = (v.width as usize, v.height as usize);
    // frame, colour, unit normal and pixel spans of every surfel that is drawn, in input order
    let placed: Vec<Placed> = surfels
        .par_iter()
        .filter_map(|s| Placed::of(s, v))
        .collect();
    let fragments: u128 = placed
        .iter()
        .map(|p| (p.xs.1 - p.xs.0) as u128 * (p.ys.1 - p.ys.0) as u128)
        .sum();
    super::check_cost(placed.len(), fragments, v)?;
    // the surfels of each band of rows, in input order (so each band reads only its own)
    let mut in_band: Vec<Vec<u32>> = vec![Vec::new(); h.div_ceil(BAND)];
    for (k, p) in placed.iter().enumerate() {
        if p.xs.0 < p.xs.1 && p.ys.0 < p.ys.1 {
            for list in &mut in_band[p.ys.0 / BAND..=(p.ys.1 - 1) / BAND] {
                list.push(k as u32);
            }
        }
    }
    // passes 1 (visibility) and 2 (attributes, blended in surfel order like the GPU's ordered
    // blending) band by band: a band's depths are final once its own surfels have been drawn
    // into them, so its second pass follows at once and reads the fragments the first one kept
    // (a band's fit in the caches) instead of computing each twice; the same sums in the same
    // order as two passes over the whole image
    let spheres = v.mode == SplatMode::Spheres;
    let mut colour = vec![[0.0f32; 4]; w * h];
    let mut normal_depth = vec![[0.0f32; 4]; w * h];
    colour
        .par_chunks_mut(w * BAND)
        .zip(normal_depth.par_chunks_mut(w * BAND))
        .zip(&in_band)
        .enumerate()
        .for_each_init(
            || {
                (
                    Vec::<f32>::new(),
                    Vec::<Kept>::new(),
                    Vec::<(Vec3, f32)>::new(),
                )
            },
            |(depth, kept, extra), (band, ((crow, nrow), members))| {
                let y0 = band * BAND;
                let y1 = y0 + crow.len() / w;
                depth.clear();
                depth.resize(crow.len(), 1.0);
                kept.clear();
                extra.clear();
                for &k in members {
                    let p = &placed[k as usize];
                    for y in p.ys.0.max(y0)..p.ys.1.min(y1) {
                        for x in p.xs.0..p.xs.1 {
                            let pixel = Vec2::new(x as f32 + 0.5, y as f32 + 0.5);
                            if let Some(frag) = fragment(pixel, &p.frame, v) {
                                let i = (y - y0) * w + x;
                                depth[i] = depth[i].min(frag.ndc_offset);
                                kept.push(Kept {
                                    pixel: i as u32,
                                    surfel: k,
                                    r2: frag.r2,
                                    depth: frag.depth,
                                    ndc: frag.ndc,
                                });
                                if spheres {
                                    extra.push((frag.sphere_normal, frag.epsilon));
                                }
                            }
                        }
                    }
                }
                for (f, kept) in kept.iter().enumerate() {
                    let i = kept.pixel as usize;
                    let buffer = depth[i];
                    if kept.ndc > buffer {
                        continue;
                    }
                    // the fragment as pass 2 reads it (the offset depth was pass 1's alone)
                    let (sphere_normal, epsilon) = extra.get(f).copied().unwrap_or_default();
                    let frag = &Fragment {
                        r2: kept.r2,
                        depth: kept.depth,
                        ndc: kept.ndc,
                        ndc_offset: kept.ndc,
                        sphere_normal,
                        epsilon,
                    };
                    let k = kept.surfel;
                    let p = &placed[k as usize];
                    let wt = weight(frag, buffer, v);
                    let n = if spheres {
                        (v.inv_view * frag.sphere_normal.extend(0.0)).xyz()
                    } else {
                        p.normal
                    };
                    let c = p.colour;
                    let acc = &mut crow[i];
                    for ch in 0..3 {
                        acc[ch] += c[ch] * wt;
                    }
                    acc[3] += wt;
                    let acc = &mut nrow[i];
                    for ch in 0..3 {
                        acc[ch] += n[ch] * wt;
                    }
                    acc[3] += frag.depth * wt;
                }
            },
        );
    // pass 3: normalisation and shading
    let image = shade_image(&colour, &normal_depth, v);
    Ok(Render {
        width: v.width,
        height: v.height,
        image,
        colour,
        normal_depth,
    })
}

/// Pass 3 of the splats (and the shading of every renderer that fills the same buffers): each
/// pixel's accumulated colour and normal-depth normalised and shaded ([`shade`]), in parallel
/// over rows.
pub fn shade_image(colour: &[[f32; 4]], normal_depth: &[[f32; 4]], v: &View) -> RgbaImage {
    let w = v.width as usize;
    let mut image = RgbaImage::new(v.width, v.height);
    image
        .as_mut()
        .par_chunks_mut(4 * w)
        .enumerate()
        .for_each(|(y, row)| {
            for x in 0..w {
                let i = y * w + x;
                let pixel = Vec2::new(x as f32 + 0.5, y as f32 + 0.5);
                let c = shade(pixel, Vec4::from(colour[i]), Vec4::from(normal_depth[i]), v);
                row[4 * x..4 * x + 4].copy_from_slice(&to_unorm8(c));
            }
        });
    image
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Passes 1 and 2 over the whole image in turn, as the first version drew them: the oracle
    /// of the fused bands.
    fn two_passes(surfels: &[Surfel], v: &View) -> (Vec<[f32; 4]>, Vec<[f32; 4]>) {
        let (w, h) = (v.width as usize, v.height as usize);
        let placed: Vec<Placed> = surfels.iter().filter_map(|s| Placed::of(s, v)).collect();
        let mut depth = vec![1.0f32; w * h];
        for p in &placed {
            for y in p.ys.0..p.ys.1 {
                for x in p.xs.0..p.xs.1 {
                    let pixel = Vec2::new(x as f32 + 0.5, y as f32 + 0.5);
                    if let Some(frag) = fragment(pixel, &p.frame, v) {
                        let d = &mut depth[y * w + x];
                        *d = d.min(frag.ndc_offset);
                    }
                }
            }
        }
        let mut colour = vec![[0.0f32; 4]; w * h];
        let mut normal_depth = vec![[0.0f32; 4]; w * h];
        for p in &placed {
            for y in p.ys.0..p.ys.1 {
                for x in p.xs.0..p.xs.1 {
                    let pixel = Vec2::new(x as f32 + 0.5, y as f32 + 0.5);
                    let Some(frag) = fragment(pixel, &p.frame, v) else {
                        continue;
                    };
                    let buffer = depth[y * w + x];
                    if frag.ndc > buffer {
                        continue;
                    }
                    let wt = weight(&frag, buffer, v);
                    let n = if v.mode == SplatMode::Spheres {
                        (v.inv_view * frag.sphere_normal.extend(0.0)).xyz()
                    } else {
                        p.normal
                    };
                    let i = y * w + x;
                    for ch in 0..3 {
                        colour[i][ch] += p.colour[ch] * wt;
                        normal_depth[i][ch] += n[ch] * wt;
                    }
                    colour[i][3] += wt;
                    normal_depth[i][3] += frag.depth * wt;
                }
            }
        }
        (colour, normal_depth)
    }

    /// The bands' fused passes sum what two whole passes sum, bit for bit, in every mode, with
    /// surfels that overlap across the bands' edges and hide one another.
    #[test]
    fn fused_bands_equal_two_whole_passes() {
        // disks on a unit sphere (Fibonacci points, overlapping), and a smaller sphere in
        // front partly hiding it (built here as `scenes::surfel_sphere` builds its sphere:
        // `scenes` imports `splat`, and `splat` importing it back, even in a test, is the
        // cycle tests/pipeline.rs refuses)
        let sphere = |n: usize, scale: f32, centre: Vec3| -> Vec<Surfel> {
            let golden = std::f32::consts::PI * (3.0 - 5.0f32.sqrt());
            let radius = 0.9 * (4.0 * std::f32::consts::PI / n as f32).sqrt() * scale;
            (0..n)
                .map(|i| {
                    let y = 1.0 - 2.0 * (i as f32 + 0.5) / n as f32;
                    let r = (1.0 - y * y).max(0.0).sqrt();
                    let a = golden * i as f32;
                    let q = Vec3::new(r * a.cos(), y, r * a.sin());
                    let c = q * 0.3 + 0.6;
                    Surfel::disk(centre + q * scale, q, radius, [c.x, c.y, c.z, 1.0])
                })
                .collect()
        };
        let mut surfels = sphere(900, 1.0, Vec3::ZERO);
        surfels.extend(sphere(300, 0.4, Vec3::new(0.3, 0.2, 1.2)));
        let camera = Camera {
            eye: Vec3::new(0.0, 0.0, 3.2),
            target: Vec3::ZERO,
            near: 1.0,
            far: 5.0,
            ..Camera::default()
        };
        for mode in [SplatMode::Ewa, SplatMode::Sprites, SplatMode::Spheres] {
            let params = SplatParams {
                mode,
                ..SplatParams::default()
            };
            let v = View::new(&camera, &Light::default(), &params, 96, 80).unwrap();
            let got = render_view_cpu(&surfels, &v).unwrap();
            let (colour, normal_depth) = two_passes(&surfels, &v);
            assert!(
                colour.iter().filter(|c| c[3] > 0.0).count() > 1000,
                "{mode:?}"
            );
            assert!(got.colour == colour, "{mode:?}: colour");
            assert!(
                got.normal_depth == normal_depth,
                "{mode:?}: normals and depths"
            );
        }
    }
}
