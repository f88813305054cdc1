//! Pictures of particle sets: a small CPU rasteriser drawing each particle as a shaded sphere
//! impostor with a depth buffer, and the pictures of each stage built on it (classes, the
//! refinement's steps, surfels by normal, the optics stage's panels). Used by the CLI and the
//! examples for pictures where a person would rather look than read; not part of the rendering
//! pipeline.

use std::path::Path;

use glam::{Vec3, Vec4Swizzles};
use image::{Rgb, RgbImage};
use serde::{Deserialize, Serialize};

/// Errors of drawing or saving a picture.
#[derive(Debug, thiserror::Error)]
pub enum PreviewError {
    /// Width or height zero or over 16384.
    #[error("picture size {width}x{height} must be between 1 and 16384 on each side")]
    InvalidSize { width: u32, height: u32 },
    /// Colours and positions differ in number.
    #[error("{colours} colours for {positions} particles")]
    LengthMismatch { positions: usize, colours: usize },
    /// The PNG could not be written.
    #[error("{}: {source}", path.display())]
    Save {
        path: std::path::PathBuf,
        #[source]
        source: image::ImageError,
    },
}

/// A perspective camera for previews.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PreviewCamera {
    /// Eye position.
    pub eye: Vec3,
    /// Point looked at.
    pub target: Vec3,
    /// Vertical field of view in degrees.
    pub fov_y_degrees: f32,
}

impl PreviewCamera {
    /// A camera that frames the box `[min, max]`, seen from the front, to the right and above
    /// (y is up), the same direction for every scene.
    #[must_use]
    pub fn framing(min: Vec3, max: Vec3) -> Self {
        // the renderer's framing, so previews and renders of a scene show the same view
        let c = crate::splat::Camera::framing(min, max);
        Self {
            eye: c.eye,
            target: c.target,
            fov_y_degrees: c.fov_y_degrees,
        }
    }
}

/// Colours used for particle classes in pictures.
pub mod palette {
    /// Interior particles: muted blue.
    pub const INTERIOR: [u8; 3] = [70, 110, 170];
    /// Surface particles: orange.
    pub const SURFACE: [u8; 3] = [245, 150, 40];
    /// Isolated particles: green.
    pub const ISOLATED: [u8; 3] = [60, 200, 90];
    /// Background.
    pub const BACKGROUND: [u8; 3] = [28, 30, 36];
    /// Light background, for pictures with dark points.
    pub const LIGHT_BACKGROUND: [u8; 3] = [235, 235, 230];
    /// Refinement steps as in Solenthaler et al. 2007, Figure 2: black P0, blue P1, red P2,
    /// yellow P3 (then grey for further steps).
    pub const STEPS: [[u8; 3]; 5] = [
        [20, 20, 20],
        [40, 90, 230],
        [220, 40, 40],
        [240, 200, 30],
        [150, 150, 150],
    ];
}

/// Draws particles as shaded spheres of world radius `radius` on the dark background.
pub fn render_points(
    positions: &[glam::Vec3],
    colours: &[[u8; 3]],
    radius: f32,
    camera: &PreviewCamera,
    width: u32,
    height: u32,
) -> Result<RgbImage, PreviewError> {
    render_points_on(
        positions,
        colours,
        radius,
        camera,
        width,
        height,
        palette::BACKGROUND,
    )
}

/// [`render_points`] on a background of one's choice (dark points need a light one).
pub fn render_points_on(
    positions: &[glam::Vec3],
    colours: &[[u8; 3]],
    radius: f32,
    camera: &PreviewCamera,
    width: u32,
    height: u32,
    background: [u8; 3],
) -> Result<RgbImage, PreviewError> {
    check_size(width, height)?;
    let mut image = RgbImage::from_pixel(width, height, Rgb(background));
    let mut depth = vec![f32::INFINITY; (width * height) as usize];
    draw_points(positions, colours, radius, camera, &mut image, &mut depth)?;
    Ok(image)
}

/// A picture's size: at least 1 and at most 16384 pixels a side.
fn check_size(width: u32, height: u32) -> Result<(), PreviewError> {
    if width == 0 || height == 0 || width > 16384 || height > 16384 {
        return Err(PreviewError::InvalidSize { width, height });
    }
    Ok(())
}

/// Draws shaded spheres of world radius `radius` into `image`, nearer than `depth` (updated).
fn draw_points(
    positions: &[Vec3],
    colours: &[[u8; 3]],
    radius: f32,
    camera: &PreviewCamera,
    image: &mut RgbImage,
    depth: &mut [f32],
) -> Result<(), PreviewError> {
    if colours.len() != positions.len() {
        return Err(PreviewError::LengthMismatch {
            positions: positions.len(),
            colours: colours.len(),
        });
    }
    let (width, height) = image.dimensions();
    let view = glam::camera::rh::view::look_at_mat4(camera.eye, camera.target, Vec3::Y);
    let focal = 0.5 * height as f32 / (camera.fov_y_degrees.to_radians() * 0.5).tan();
    let light = Vec3::new(-0.4, 0.7, 0.6).normalize();
    for (p, colour) in positions.iter().zip(colours) {
        if !p.is_finite() {
            continue;
        }
        let v = (view * p.extend(1.0)).xyz();
        let z = -v.z;
        if z <= radius * 0.5 {
            continue;
        }
        let sx = 0.5 * width as f32 + v.x / z * focal;
        let sy = 0.5 * height as f32 - v.y / z * focal;
        let pr = (radius / z * focal).max(0.7);
        let x0 = (sx - pr).floor().max(0.0) as i64;
        let x1 = ((sx + pr).ceil() as i64).min(width as i64 - 1);
        let y0 = (sy - pr).floor().max(0.0) as i64;
        let y1 = ((sy + pr).ceil() as i64).min(height as i64 - 1);
        for py in y0..=y1 {
            for px in x0..=x1 {
                let dx = (px as f32 + 0.5 - sx) / pr;
                let dy = (py as f32 + 0.5 - sy) / pr;
                let d2 = dx * dx + dy * dy;
                if d2 > 1.0 {
                    continue;
                }
                let dz = (1.0 - d2).sqrt();
                let zd = z - dz * radius;
                let slot = (py as u32 * width + px as u32) as usize;
                if zd >= depth[slot] {
                    continue;
                }
                depth[slot] = zd;
                let normal = Vec3::new(dx, -dy, dz);
                let shade = 0.35 + 0.65 * normal.dot(light).max(0.0);
                let c = colour.map(|c| (c as f32 * shade).min(255.0) as u8);
                image.put_pixel(px as u32, py as u32, Rgb(c));
            }
        }
    }
    Ok(())
}

/// Places pictures side by side on one canvas (heights may differ; shorter ones are centred).
#[must_use]
pub fn side_by_side(images: &[RgbImage]) -> RgbImage {
    let width = images.iter().map(RgbImage::width).sum::<u32>().max(1);
    let height = images.iter().map(RgbImage::height).max().unwrap_or(1);
    let mut canvas = RgbImage::from_pixel(width, height, Rgb(palette::BACKGROUND));
    let mut x = 0;
    for img in images {
        let y = (height - img.height()) / 2;
        image::imageops::replace(&mut canvas, img, x as i64, y as i64);
        x += img.width();
    }
    canvas
}

/// Saves a picture as PNG, through a temporary name in the same folder and a rename, so that an
/// interrupted run never leaves a half-written picture under the final name.
pub fn save_png(image: &RgbImage, path: &Path) -> Result<(), PreviewError> {
    let tmp = path.with_extension(format!("{}.tmp.png", std::process::id()));
    let saved = image
        .save(&tmp)
        .and_then(|()| std::fs::rename(&tmp, path).map_err(image::ImageError::IoError));
    saved.map_err(|source| {
        let _ = std::fs::remove_file(&tmp);
        PreviewError::Save {
            path: path.to_owned(),
            source,
        }
    })
}

/// Bounds of points, or the unit box when there is no finite one.
pub fn bounds_or_unit<'a>(points: impl IntoIterator<Item = &'a Vec3>) -> (Vec3, Vec3) {
    let (lo, hi) = points
        .into_iter()
        .fold((Vec3::INFINITY, Vec3::NEG_INFINITY), |(lo, hi), &p| {
            (lo.min(p), hi.max(p))
        });
    if lo.is_finite() && hi.is_finite() {
        (lo, hi)
    } else {
        (Vec3::ZERO, Vec3::ONE)
    }
}

/// Particles coloured by class: orange surface, blue interior, green isolated.
#[must_use]
pub fn class_colours(classes: &[crate::surface::ParticleClass]) -> Vec<[u8; 3]> {
    use crate::surface::ParticleClass;
    classes
        .iter()
        .map(|c| match c {
            ParticleClass::Interior => palette::INTERIOR,
            ParticleClass::Surface => palette::SURFACE,
            ParticleClass::Isolated => palette::ISOLATED,
        })
        .collect()
}

/// The level map of detail from the view (issue 36): the refined points seen from `camera`,
/// coloured by the level of their region ([`crate::refine::Refined::levels`]: the colours of the
/// steps, black for level 0, blue 1, red 2, yellow 3), each drawn with its level's splat radius
/// (the coarsest level's where levels overlap on screen).
pub fn levels_picture(
    refined: &crate::refine::Refined,
    camera: &crate::splat::Camera,
    width: u32,
    height: u32,
) -> Result<RgbImage, PreviewError> {
    check_size(width, height)?;
    let camera = PreviewCamera {
        eye: camera.eye,
        target: camera.target,
        fov_y_degrees: camera.fov_y_degrees,
    };
    let colours: Vec<[u8; 3]> = refined
        .levels
        .iter()
        .map(|&l| palette::STEPS[(l as usize).min(4)])
        .collect();
    // coarse levels first, each with its own radius, finer ones over them
    let mut image = RgbImage::from_pixel(width, height, Rgb(palette::LIGHT_BACKGROUND));
    let mut depth = vec![f32::INFINITY; (width as usize) * (height as usize)];
    for level in 0..=refined.levels.iter().copied().max().unwrap_or(0) {
        let (points, point_colours): (Vec<Vec3>, Vec<[u8; 3]>) = (0..refined.len())
            .filter(|&i| refined.levels[i] == level)
            .map(|i| (refined.positions[i], colours[i]))
            .unzip();
        let Some(radius) = (0..refined.len())
            .filter(|&i| refined.levels[i] == level)
            .map(|i| refined.radii[i])
            .reduce(f32::min)
        else {
            continue;
        };
        draw_points(
            &points,
            &point_colours,
            radius,
            &camera,
            &mut image,
            &mut depth,
        )?;
    }
    Ok(image)
}

/// The input points beside the refined points coloured by step (Solenthaler et al.'s Figure 2:
/// black P0, blue P1, red P2, yellow P3).
pub fn refinement_picture(
    input: &[Vec3],
    refined: &crate::refine::Refined,
    size: u32,
) -> Result<RgbImage, PreviewError> {
    let (lo, hi) = bounds_or_unit(input.iter().chain(&refined.positions));
    let camera = PreviewCamera::framing(lo, hi);
    let splat = refined.final_radius * 0.5;
    let input_colours = vec![palette::STEPS[0]; input.len()];
    // the finest level's radius over that level's factor (every point's level in a fixed
    // refinement is its steps)
    let finest = refined.levels.iter().copied().max().unwrap_or(0);
    let r0 = refined.final_radius / crate::refine::RADIUS_FACTOR.powi(i32::from(finest));
    let left = render_points_on(
        input,
        &input_colours,
        0.2 * r0,
        &camera,
        size,
        size,
        palette::LIGHT_BACKGROUND,
    )?;
    let colours: Vec<[u8; 3]> = refined
        .steps
        .iter()
        .map(|&s| palette::STEPS[(s as usize).min(4)])
        .collect();
    let right = render_points_on(
        &refined.positions,
        &colours,
        splat,
        &camera,
        size,
        size,
        palette::LIGHT_BACKGROUND,
    )?;
    Ok(side_by_side(&[left, right]))
}

/// Surfels drawn as small shaded disks coloured by their normal; `camera` defaults to framing
/// them.
pub fn surfels_picture(
    s: &crate::surfels::Surfels,
    camera: Option<&PreviewCamera>,
    size: u32,
) -> Result<RgbImage, PreviewError> {
    let colours: Vec<[u8; 3]> = s
        .normals
        .iter()
        .map(|n| {
            ((*n * 0.5 + 0.5) * 255.0)
                .to_array()
                .map(|c| c.clamp(0.0, 255.0) as u8)
        })
        .collect();
    let radius = s.radii.first().copied().unwrap_or(0.01) * 0.6;
    let framing = {
        let (lo, hi) = bounds_or_unit(&s.positions);
        PreviewCamera::framing(lo, hi)
    };
    render_points(
        &s.positions,
        &colours,
        radius,
        camera.unwrap_or(&framing),
        size,
        size,
    )
}

/// The light's view of the water: depth from the light as grey levels (near bright), black where
/// there is none.
#[must_use]
pub fn screen_picture(c: &crate::optics::Caustics) -> RgbImage {
    let depths: Vec<f32> = c.vertices.iter().map(|v| v.surface.w).collect();
    let (lo, hi) = depths
        .iter()
        .filter(|d| **d > 0.0)
        .fold((f32::MAX, f32::MIN), |(a, b), d| (a.min(*d), b.max(*d)));
    let span = (hi - lo).max(1e-6);
    RgbImage::from_fn(c.screen.width, c.screen.height, |x, y| {
        let d = depths[(y * c.screen.width + x) as usize];
        if d > 0.0 {
            let g = (255.0 * (1.0 - 0.8 * (d - lo) / span)) as u8;
            Rgb([g / 3, (u16::from(g) * 2 / 3) as u8, g])
        } else {
            Rgb([0, 0, 0])
        }
    })
}

/// Scales an image to `height` rows (nearest neighbour, aspect kept).
#[must_use]
pub fn to_height(img: &RgbImage, height: u32) -> RgbImage {
    let w = (img.width() as f32 * height as f32 / img.height().max(1) as f32).round() as u32;
    image::imageops::resize(img, w.max(1), height, image::imageops::FilterType::Nearest)
}

/// The optics stage's panel: light's view of the water | caustics map (when the caustics are
/// given) | finished frame, each scaled to `height` rows.
#[must_use]
pub fn stages_panel(
    caustics: Option<(&crate::optics::Caustics, &crate::optics::Stage)>,
    frame: &image::RgbaImage,
    height: u32,
) -> RgbImage {
    let rgb = |i: &image::RgbaImage| -> RgbImage { image::buffer::ConvertBuffer::convert(i) };
    let mut panels = Vec::new();
    if let Some((c, stage)) = caustics {
        panels.push(to_height(&screen_picture(c), height));
        panels.push(to_height(&rgb(&c.image(stage)), height));
    }
    panels.push(to_height(&rgb(frame), height));
    side_by_side(&panels)
}

/// Writes an RGBA image as an RGB PNG (through a temporary file and a rename, like
/// [`save_png`]).
pub fn save_rgba_png(img: &image::RgbaImage, path: &Path) -> Result<(), PreviewError> {
    save_png(&image::buffer::ConvertBuffer::convert(img), path)
}

/// Writes `text` into `image` at pixel `(x, y)` (its top left) in the 8x8 bitmap font of
/// `font8x8`, each font pixel `scale` pixels wide, on a dark band so it reads on any picture.
/// Characters the font lacks are drawn as `?`; what falls outside the image is clipped.
pub fn label(image: &mut RgbImage, x: u32, y: u32, text: &str, scale: u32) {
    use font8x8::UnicodeFonts;
    let scale = scale.max(1);
    let cell = 8 * scale;
    let width = cell * text.chars().count() as u32 + 2 * scale;
    for py in y..(y + cell + 2 * scale).min(image.height()) {
        for px in x..(x + width).min(image.width()) {
            let p = image.get_pixel_mut(px, py);
            for c in &mut p.0 {
                *c /= 4;
            }
        }
    }
    for (k, ch) in text.chars().enumerate() {
        let glyph = font8x8::BASIC_FONTS
            .get(ch)
            .or_else(|| font8x8::BASIC_FONTS.get('?'))
            .unwrap_or([0; 8]);
        for (row, bits) in glyph.iter().enumerate() {
            for col in 0..8 {
                if bits & (1 << col) == 0 {
                    continue;
                }
                for dy in 0..scale {
                    for dx in 0..scale {
                        let px = x + scale + k as u32 * cell + col * scale + dx;
                        let py = y + scale + row as u32 * scale + dy;
                        if px < image.width() && py < image.height() {
                            image.put_pixel(px, py, image::Rgb([255, 255, 255]));
                        }
                    }
                }
            }
        }
    }
}

/// Pictures of one size laid out in rows of `columns` (the last row padded with black).
///
/// # Panics
/// When the pictures differ in size.
#[must_use]
pub fn grid(images: &[RgbImage], columns: usize) -> RgbImage {
    let Some(first) = images.first() else {
        return RgbImage::new(1, 1);
    };
    let (w, h) = first.dimensions();
    let columns = columns.clamp(1, images.len());
    let rows = images.len().div_ceil(columns);
    let mut out = RgbImage::new(w * columns as u32, h * rows as u32);
    for (k, img) in images.iter().enumerate() {
        assert_eq!(img.dimensions(), (w, h), "pictures of different sizes");
        let (cx, cy) = ((k % columns) as u32 * w, (k / columns) as u32 * h);
        image::imageops::replace(&mut out, img, i64::from(cx), i64::from(cy));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn labels_draw_white_glyphs_on_a_darkened_band_and_clip() {
        let mut img = RgbImage::from_pixel(40, 12, image::Rgb([200, 200, 200]));
        label(&mut img, 0, 0, "I-", 1);
        // inside the band every pixel is either a glyph's white or the background darkened
        let white = img.pixels().filter(|p| p.0 == [255; 3]).count();
        let dark = img.pixels().filter(|p| p.0 == [50; 3]).count();
        assert!(white > 6, "{white} glyph pixels");
        assert_eq!(
            white + dark,
            18 * 10,
            "the band is 2 glyphs + 2 px wide, 10 px high"
        );
        // text running off the image is clipped, not a panic
        label(&mut img, 30, 8, "far too long for the picture", 2);
        let sheet = grid(&[img.clone(), img.clone(), img], 2);
        assert_eq!(sheet.dimensions(), (80, 24));
    }

    #[test]
    fn a_point_in_front_of_the_camera_is_drawn_at_the_centre() {
        let camera = PreviewCamera {
            eye: Vec3::new(0.0, 0.0, 5.0),
            target: Vec3::ZERO,
            fov_y_degrees: 40.0,
        };
        let img = render_points(
            &[Vec3::ZERO, Vec3::new(0.0, 0.0, 10.0)],
            &[[255, 0, 0], [0, 255, 0]],
            0.2,
            &camera,
            64,
            48,
        )
        .unwrap();
        let centre = img.get_pixel(32, 24);
        assert!(centre[0] > 80 && centre[1] == 0, "{centre:?}");
        assert_eq!(*img.get_pixel(0, 0), Rgb(palette::BACKGROUND));
        assert!(render_points(&[], &[], 1.0, &camera, 0, 10).is_err());
        assert!(render_points(&[Vec3::ZERO], &[], 1.0, &camera, 10, 10).is_err());
    }
}
