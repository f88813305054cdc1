//! Pictures of particle sets: a small CPU rasteriser drawing each particle as a shaded sphere
//! impostor with a depth buffer. Used by the CLI for pictures where a person would rather look
//! than read; not part of the rendering pipeline.

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
    if width == 0 || height == 0 || width > 16384 || height > 16384 {
        return Err(PreviewError::InvalidSize { width, height });
    }
    if colours.len() != positions.len() {
        return Err(PreviewError::LengthMismatch {
            positions: positions.len(),
            colours: colours.len(),
        });
    }
    let mut image = RgbImage::from_pixel(width, height, Rgb(background));
    let mut depth = vec![f32::INFINITY; (width * height) as usize];
    let view = glam::camera::rh::view::look_at_mat4(camera.eye, camera.target, Vec3::Y);
    let aspect = width as f32 / height as f32;
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
        let _ = aspect;
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
    Ok(image)
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

#[cfg(test)]
mod tests {
    use super::*;

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
