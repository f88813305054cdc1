//! Detail chosen from the view (issue 36): the upsampling stops, region by region, once the
//! refined points' spacing seen from the camera falls below a footprint of `detail_px` pixels.
//!
//! The spacing after `k` steps. The step with radius `r_i` makes a child between every pair of
//! neighbours at least `r_{i+1} = F r_i` apart (Solenthaler et al. eq. 16, `F = 0.5412`), then
//! keeps the neighbours within `r_{i+1}`: a pair `d` apart, `r_{i+1} <= d <= r_i`, becomes two
//! pairs `d / 2 <= r_i / 2 < r_{i+1}` apart. So after `k` steps no two neighbouring points of the
//! surface lie farther apart than `r_{k+1} = r_0 F^(k+1)`, with `r_0` the support radius, two
//! particle spacings `s`: the spacing bound is `2 s F^(k+1)`, 1.08 s, 0.59 s, 0.32 s and 0.17 s
//! at 0 to 3 steps. A region's level is the fewest steps whose bound, seen from the view, is at
//! most `detail_px` pixels: `2 s F^(k+1) p(x) <= detail_px`, `p(x)` the pixels per world unit at
//! the point (`H / (2 tan(fov_y / 2) z)` at view depth `z`; `H / (2 half_height)` for an
//! orthographic view).
//!
//! Points outside every view by more than a margin (the level-0 kernel's reach, twice the
//! support radius: a point farther out cannot move the surface inside the view) are not refined.

use glam::{Vec3, Vec4Swizzles};
use serde::{Deserialize, Serialize};

use crate::refine::RADIUS_FACTOR;
use crate::splat::View;
use crate::surfels::Viewpoints;

/// How much of `refine.steps` the chain's upsampling takes ([`super::PipelineParams::detail`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Detail {
    /// Each region stops once its points' spacing seen from the camera is under `detail_px`
    /// pixels, never past `refine.steps` (the default); outputs without a camera (surfels,
    /// refined points) take `fixed`, so that what is written to disk never depends on an image
    /// size.
    #[default]
    Auto,
    /// Every region takes `refine.steps` (the paper's three by default).
    Fixed,
}

impl Detail {
    /// Every choice, in the order of the documentation.
    pub const ALL: [Self; 2] = [Self::Auto, Self::Fixed];

    /// The name used in files and on the command line.
    #[must_use]
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Auto => "auto",
            Self::Fixed => "fixed",
        }
    }
}

/// The default footprint of `detail = "auto"`, in pixels.
pub const DEFAULT_DETAIL_PX: f32 = 1.5;

/// The upper bound of the refined points' spacing after `steps` steps, in particle spacings
/// `s` (module docs): `2 F^(steps + 1)`.
#[must_use]
pub fn spacing_after(steps: u32) -> f32 {
    2.0 * RADIUS_FACTOR.powi(steps as i32 + 1)
}

/// The level of detail each point needs in one or more views (the camera's; the light's where
/// the caustics are drawn): the largest over the views.
#[derive(Clone, Debug)]
pub struct ViewLevels {
    views: Vec<View>,
    /// The particles' spacing (half the support radius).
    spacing: f32,
    /// The most steps.
    steps: u32,
    detail_px: f32,
    /// How far outside a view a point still counts (world units).
    margin: f32,
}

impl ViewLevels {
    /// Levels for particles of support radius `radius` seen in `views`, at most `steps`.
    #[must_use]
    pub fn new(views: Vec<View>, radius: f32, steps: u32, detail_px: f32) -> Self {
        Self {
            views,
            spacing: 0.5 * radius,
            steps,
            detail_px,
            margin: 2.0 * radius,
        }
    }

    /// The views' eyes (perspective) and directions (orthographic), for leaving out the surface
    /// that faces away from all of them.
    #[must_use]
    pub fn viewpoints(&self) -> Viewpoints {
        self.views.iter().fold(Viewpoints::new(), |seen, v| {
            if v.is_orthographic() {
                seen.with_direction(v.forward())
            } else {
                seen.with_eye(v.matrices().1.w_axis.xyz())
            }
        })
    }

    /// The fewest steps whose spacing, seen at `x` from the view that sees it largest, is at most
    /// `detail_px` pixels (0 outside every view, at most the most steps).
    #[must_use]
    pub fn level(&self, x: Vec3) -> u32 {
        self.level_after(self.needed(x), None)
    }

    /// The level `x` needs as a real number `k*`, where the spacing bound `2 s F^(k*+1)` seen
    /// there is exactly `detail_px` pixels: `ceil(k*)` steps are enough (minus infinity outside
    /// every view).
    #[must_use]
    pub fn needed(&self, x: Vec3) -> f32 {
        let px = self
            .views
            .iter()
            .map(|v| pixels_per_unit(v, x, self.margin))
            .fold(0.0f32, f32::max);
        if px <= 0.0 {
            return f32::NEG_INFINITY;
        }
        // 2 s F^(k+1) px = detail_px
        (self.detail_px / (2.0 * self.spacing * px)).ln() / RADIUS_FACTOR.ln() - 1.0
    }

    /// The level of a point that needs `needed` ([`ViewLevels::needed`]) and had `previous` in
    /// the frame before: the previous level while the need stays within [`LEVEL_HYSTERESIS`] of
    /// that level's range `(previous - 1, previous]`, else `ceil(needed)`; within `0..=steps`.
    #[must_use]
    pub fn level_after(&self, needed: f32, previous: Option<u8>) -> u32 {
        let fresh = if needed.is_nan() {
            self.steps
        } else {
            needed.ceil().clamp(0.0, self.steps as f32) as u32
        };
        match previous {
            Some(p) => {
                let p = u32::from(p).min(self.steps);
                let (lo, hi) = (
                    p as f32 - 1.0 - LEVEL_HYSTERESIS,
                    p as f32 + LEVEL_HYSTERESIS,
                );
                // at the ends of the range any need beyond keeps the level
                let above = p == self.steps || needed <= hi;
                let below = p == 0 || needed > lo;
                if above && below { p } else { fresh }
            }
            None => fresh,
        }
    }
}

/// How far, in levels, a point's need may pass the range of its previous frame's level before
/// the level changes: the hysteresis that keeps a region's level from popping back and forth
/// in a sequence as its particles move across a level's border (`detail = "auto"`).
pub const LEVEL_HYSTERESIS: f32 = 0.25;

/// Pixels per world unit at `x` in view `v`: 0 when `x` lies outside the view by more than
/// `margin` (behind the eye, beside the window).
fn pixels_per_unit(v: &View, x: Vec3, margin: f32) -> f32 {
    let (view, _, _) = v.matrices();
    let p = (view * x.extend(1.0)).xyz();
    let depth = -p.z;
    let half = v.half_extent();
    let per_unit_at = |scale: f32| v.height as f32 / (2.0 * half.y * scale);
    if v.is_orthographic() {
        let inside = p.x.abs() <= half.x + margin && p.y.abs() <= half.y + margin;
        return if inside { per_unit_at(1.0) } else { 0.0 };
    }
    if depth <= -margin {
        return 0.0;
    }
    // within the margin of the view's pyramid (the margin measured across the axis)
    let z = depth.max(0.0);
    let inside = p.x.abs() <= half.x * z + margin && p.y.abs() <= half.y * z + margin;
    if !inside {
        return 0.0;
    }
    // nearer than a margin: as seen from the margin's depth (no infinite detail at the eye)
    per_unit_at(depth.max(margin))
}
