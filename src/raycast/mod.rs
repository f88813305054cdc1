//! A peer renderer: ray casting to the iso-surface of the SPH density with PCA normals (Xiao,
//! Zhang, Yang, "Fast and high-quality rendering of liquids from large-scale SPH", the paper in
//! `../shared/papers/xiao-fast-high-quality-rendering-of-liquids-large-sph.txt`).
//!
//! Per pixel the view ray is cast through the density of the points (eq. 1, the same kernel sum
//! as the density grid's, [`crate::surfels::ExactDensity`]) until it first reaches the iso-value,
//! the crossing refined by bisection; the normal there blends the density gradient with the PCA
//! normal of the neighbours (eqs. 2-6), and a bilateral filter smooths the normal map. A
//! thickness per pixel (the summed chords of the points' spheres, what additive sphere splats
//! accumulate, §3.4) tints the water.
//!
//! The entry of each ray: the paper splats the particles as spheres and starts from their depth
//! (§3.1), so that the march skips the empty space in front. The CPU reference ([`cpu`]) does the
//! same exactly: the density is zero outside every point's sphere of its radius, so the rays are
//! marched only through the spheres they cross (the exact intervals, in depth order), and the
//! first crossing found is the true first hit of the iso-surface up to the step (a step of 0.1
//! radii, then 12 bisections). That makes it the project's **reference surface**: its depth and
//! normal per pixel are what other renderers are measured against.
//!
//! The result is a [`Render`] whose buffers hold one sample per covered pixel (`(colour, 1)` and
//! `(normal, depth)`), so it is shaded by [`crate::splat::shade`] and read by the optics like
//! the splats' buffers.

use glam::{Mat3, Vec3};
use serde::{Deserialize, Serialize};

use crate::Error;
use crate::density::{DensityError, Points};
use crate::neighbours::CellGrid;
use crate::splat::{
    Drawn, GpuWaterPass, Render, SplatError, View, WaterInput, WaterRenderer, WaterSurface,
};
use crate::surfels::{ExactDensity, SurfelError};

pub mod cpu;
pub mod gpu;

pub use cpu::{render_cpu, render_view_cpu};

/// Errors of ray casting.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RayCastError {
    /// A parameter is out of range.
    #[error("invalid ray-casting parameter `{name}`: {reason}")]
    InvalidParameter { name: &'static str, reason: String },
    /// The points or their radii are unusable.
    #[error(transparent)]
    Density(#[from] DensityError),
    /// The density index could not be built.
    #[error(transparent)]
    Surfels(#[from] SurfelError),
    /// The view (camera, light, size).
    #[error(transparent)]
    Splat(#[from] SplatError),
}

/// Which normal each pixel gets.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum RayNormals {
    /// The paper's: the density gradient blended with the PCA normal (eqs. 5, 6).
    #[default]
    Blended,
    /// The density gradient alone (the exact iso-surface's normal, eq. 2).
    Gradient,
    /// The PCA normal alone (eq. 3), oriented like the gradient.
    Pca,
}

/// Parameters of ray casting. `Default` holds the paper's values where it gives them.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RayCastParams {
    /// Iso-value as a fraction of one point's peak density `F(0, h)`; default 0.75, the
    /// surfels' ([`crate::surfels::SurfelParams::iso_fraction`]), so both find one surface.
    pub iso_fraction: f32,
    /// March step in radii of the smallest point radius. Default 0.1.
    pub step: f32,
    /// Bisection steps refining each crossing. Default 12 (the crossing within 0.1 / 4096 radii).
    pub bisection_steps: u32,
    /// Which normal each pixel gets.
    pub normals: RayNormals,
    /// Radius `R` of the PCA neighbourhood (eqs. 3, 4) in radii of each point. Default 2: the
    /// paper's `R = 3` beside a rendering radius equal to its smoothing length gives no ratio
    /// in our units; measured on the noisy slab (`tests/raycast.rs`), PCA smooths only when its
    /// neighbourhood is wider than the density's own (figures in docs/design.md).
    pub pca_radius: f32,
    /// Shape `d` of the blending function (eq. 6). Default 10, the paper's.
    pub blend_d: f32,
    /// Shape `k` of the blending function (eq. 6). Default 0.998, the paper's.
    pub blend_k: f32,
    /// The largest PCA weight `w`. Default 0.5: the paper sets "the blending parameter w equal
    /// to 0.5" beside eq. 6, which alone gives 1 wherever PCA and gradient agree within 3.6
    /// degrees; read together, `w = min(0.5, exp(d (N' . N'' - k)))`: half PCA where the two
    /// agree, falling to the gradient where PCA fails (too few neighbours, §3.3).
    pub blend_max: f32,
    /// Half width of the bilateral filter on the normal map, in pixels (0: off). Default 3
    /// (a 7x7 window).
    pub bilateral_radius_px: u32,
    /// Spatial standard deviation of the bilateral filter, in pixels. Default 2.
    pub bilateral_sigma_px: f32,
    /// Depth standard deviation of the bilateral filter, in radii: pixels farther apart in
    /// depth do not mix (edges keep). Default 0.5.
    pub bilateral_sigma_depth: f32,
    /// The water's tint: `colour = base * exp(-absorption * thickness / h)` per RGB channel,
    /// thickness from the sphere chords (§3.4). Default `[0.06, 0.025, 0.012]` per radius, a
    /// look (the optics stage attenuates physically).
    pub absorption: [f32; 3],
}

impl Default for RayCastParams {
    fn default() -> Self {
        Self {
            iso_fraction: 0.75,
            step: 0.1,
            bisection_steps: 12,
            normals: RayNormals::Blended,
            pca_radius: 2.0,
            blend_d: 10.0,
            blend_k: 0.998,
            blend_max: 0.5,
            bilateral_radius_px: 3,
            bilateral_sigma_px: 2.0,
            bilateral_sigma_depth: 0.5,
            absorption: [0.06, 0.025, 0.012],
        }
    }
}

impl RayCastParams {
    /// Checks every parameter.
    pub fn validate(&self) -> Result<(), RayCastError> {
        let check = |name, ok: bool, reason: &str| {
            if ok {
                Ok(())
            } else {
                Err(RayCastError::InvalidParameter {
                    name,
                    reason: reason.to_string(),
                })
            }
        };
        let positive = |x: f32| x.is_finite() && x > 0.0;
        check(
            "iso_fraction",
            positive(self.iso_fraction),
            "must be finite and > 0",
        )?;
        check(
            "step",
            self.step.is_finite() && (1e-3..=1.0).contains(&self.step),
            "must lie in [0.001, 1] radii",
        )?;
        check(
            "bisection_steps",
            self.bisection_steps <= 40,
            "must be at most 40",
        )?;
        check(
            "pca_radius",
            self.pca_radius.is_finite() && (0.25..=4.0).contains(&self.pca_radius),
            "must lie in [0.25, 4] radii",
        )?;
        check(
            "blend_d, blend_k",
            self.blend_d.is_finite() && self.blend_k.is_finite(),
            "must be finite",
        )?;
        check(
            "blend_max",
            (0.0..=1.0).contains(&self.blend_max),
            "must lie in [0, 1]",
        )?;
        check(
            "bilateral_radius_px",
            self.bilateral_radius_px <= 32,
            "must be at most 32",
        )?;
        check(
            "bilateral_sigma_px, bilateral_sigma_depth",
            positive(self.bilateral_sigma_px) && positive(self.bilateral_sigma_depth),
            "must be finite and > 0",
        )?;
        check(
            "absorption",
            self.absorption.iter().all(|a| a.is_finite() && *a >= 0.0),
            "must be finite and >= 0",
        )
    }
}

/// What ray casting returns.
#[derive(Clone, Debug, PartialEq)]
pub struct RayCast {
    /// The shaded image and its buffers: per covered pixel `(tinted colour, 1)` and
    /// `(normal, view depth of the hit)`; weight 0 where the ray meets no iso-surface.
    pub render: Render,
    /// Per pixel, the water's thickness along the ray (world units): the summed chords of the
    /// points' spheres times the share of a sphere one point's volume is.
    pub thickness: Vec<f32>,
    /// Per pixel, the view depth where the ray enters the first sphere (infinite: none).
    pub entry: Vec<f32>,
    /// Density evaluations of the march and the bisections, over all pixels.
    pub samples: u64,
}

/// The normal at a point `x` of the iso-surface: the outward density gradient `N'` (eq. 2, with
/// the density's own kernel rather than the paper's spiky one, so that it is the iso-surface's
/// exact normal), the PCA normal `N''` (eqs. 3, 4: the least-eigenvalue eigenvector of the
/// covariance of the neighbours weighted `1 - (r / R)^3`, oriented like `N'`), and their blend
/// (eqs. 5, 6). `None` where the gradient vanishes, and for a caster without the CPU's index
/// ([`Caster::with_weights_on_gpu`]).
#[must_use]
pub fn surface_normal(caster: &Caster<'_>, x: Vec3) -> Option<Vec3> {
    let params = &caster.params;
    let (_, gradient) = caster.density()?.value_and_gradient(x);
    let basic = (-gradient).try_normalize()?;
    if params.normals == RayNormals::Gradient {
        return Some(basic);
    }
    let pca = caster
        .pca_normal(x)
        .map(|n| if n.dot(basic) < 0.0 { -n } else { n });
    let Some(pca) = pca else {
        // too few neighbours for a covariance: the paper's fallback to N'
        return Some(basic);
    };
    match params.normals {
        RayNormals::Pca => Some(pca),
        _ => Some(blend(basic, pca, params)),
    }
}

/// Eqs. 5 and 6: `(1 - w) N' + w N''`, `w = min(blend_max, exp(d (N' . N'' - k)))`, normalised.
#[must_use]
pub fn blend(basic: Vec3, pca: Vec3, params: &RayCastParams) -> Vec3 {
    let w = (params.blend_d * (basic.dot(pca) - params.blend_k))
        .exp()
        .min(params.blend_max);
    ((1.0 - w) * basic + w * pca)
        .try_normalize()
        .unwrap_or(basic)
}

/// The bilateral Gaussian filter of the normal map (Aurich and Weule 1995, as the paper's §3.3
/// closing step): each covered pixel's normal becomes the normalised sum of the covered normals
/// in a `(2 radius + 1)^2` window, weighted `exp(-|dp|^2 / 2 sigma_px^2 - dz^2 / 2 sigma_z^2)`.
#[must_use]
pub fn bilateral(
    normals: &[Option<Vec3>],
    depths: &[f32],
    width: usize,
    height: usize,
    radius: u32,
    sigma_px: f32,
    sigma_z: f32,
) -> Vec<Option<Vec3>> {
    use rayon::prelude::*;
    let r = radius as i64;
    let (ks, kz) = (-0.5 / (sigma_px * sigma_px), -0.5 / (sigma_z * sigma_z));
    (0..width * height)
        .into_par_iter()
        .map(|i| {
            let n0 = normals[i]?;
            if r == 0 {
                return Some(n0);
            }
            let (x, y) = ((i % width) as i64, (i / width) as i64);
            let z0 = depths[i];
            let mut sum = Vec3::ZERO;
            for dy in -r..=r {
                for dx in -r..=r {
                    let (u, v) = (x + dx, y + dy);
                    if u < 0 || v < 0 || u >= width as i64 || v >= height as i64 {
                        continue;
                    }
                    let j = (v as usize) * width + u as usize;
                    if let Some(n) = normals[j] {
                        let dz = depths[j] - z0;
                        sum += n * (ks * (dx * dx + dy * dy) as f32 + kz * dz * dz).exp();
                    }
                }
            }
            Some(sum.try_normalize().unwrap_or(n0))
        })
        .collect()
}

/// Points ready for ray casting: the density index and the radii the march needs.
pub struct Caster<'a> {
    points: Points<'a>,
    kernel: crate::density::Kernel,
    index: Index<'a>,
    pca_reach: f32,
    iso: f32,
    params: RayCastParams,
    /// The points' weights on the GPU instead of in `points` ([`Caster::with_weights_on_gpu`]).
    gpu_weights: Option<wgpu::Buffer>,
    /// What the GPU cast of every view reads, made by the first view's upload: the views of a
    /// frame (the light's and the camera's) share it.
    gpu_inputs: std::sync::OnceLock<gpu::CastInputs>,
}

/// How a [`Caster`]'s points are indexed.
enum Index<'a> {
    /// For the CPU's cast: the density's cells and the PCA neighbourhood's.
    Cpu {
        density: ExactDensity<'a>,
        /// boxed: the GPU's variant is a small list
        pca_grid: Box<CellGrid>,
    },
    /// For the GPU's cast alone (the weights there): the density's radius groups, which the
    /// GPU's grids index ([`crate::surfels::radius_groups`]).
    Gpu { groups: Vec<(f32, Vec<u32>)> },
}

impl<'a> Caster<'a> {
    /// Indexes `points` for casting with `kernel`.
    pub fn new(
        points: Points<'a>,
        kernel: crate::density::Kernel,
        params: &RayCastParams,
    ) -> Result<Self, RayCastError> {
        params.validate()?;
        let density = ExactDensity::of(points, kernel)?;
        let pca_reach = params.pca_radius * points.max_radius();
        let pca_grid = CellGrid::new(points.positions, pca_reach).map_err(SurfelError::from)?;
        Ok(Self::of(
            points,
            kernel,
            params,
            Index::Cpu {
                density,
                pca_grid: Box::new(pca_grid),
            },
        ))
    }

    /// The caster of `points` whose weights are in `weights` on the GPU (`f32` a point, in their
    /// order, solved there: `GpuPipeline`'s boundary calibration; `points`' own are not read):
    /// the GPU cast reads them, a CPU cast is refused. A negative weight
    /// ([`crate::pipeline::boundary::gpu::DROPPED`]) is a point that is not there: no sphere,
    /// no density term, no PCA neighbour. The CPU's index is not built (the
    /// density's and the PCA's cells: 5-7 ms of the column's splash frame on this project's
    /// machine), only the radius groups the GPU's grids index.
    pub fn with_weights_on_gpu(
        points: Points<'a>,
        kernel: crate::density::Kernel,
        params: &RayCastParams,
        weights: wgpu::Buffer,
    ) -> Result<Self, RayCastError> {
        params.validate()?;
        points.check()?;
        let groups = crate::surfels::radius_groups(&points);
        let mut caster = Self::of(points, kernel, params, Index::Gpu { groups });
        caster.gpu_weights = Some(weights);
        Ok(caster)
    }

    fn of(
        points: Points<'a>,
        kernel: crate::density::Kernel,
        params: &RayCastParams,
        index: Index<'a>,
    ) -> Self {
        Self {
            points,
            kernel,
            index,
            pca_reach: params.pca_radius * points.max_radius(),
            iso: params.iso_fraction * kernel.peak(points.h),
            params: *params,
            gpu_weights: None,
            gpu_inputs: std::sync::OnceLock::new(),
        }
    }

    /// The points' weights on the GPU, when they are there ([`Caster::with_weights_on_gpu`]).
    #[must_use]
    pub fn gpu_weights(&self) -> Option<&wgpu::Buffer> {
        self.gpu_weights.as_ref()
    }

    /// The density the CPU's rays are cast through; `None` for a caster whose weights are on
    /// the GPU ([`Caster::with_weights_on_gpu`]).
    #[must_use]
    pub fn density(&self) -> Option<&ExactDensity<'a>> {
        match &self.index {
            Index::Cpu { density, .. } => Some(density),
            Index::Gpu { .. } => None,
        }
    }

    /// The points cast.
    #[must_use]
    pub fn points(&self) -> &Points<'a> {
        &self.points
    }

    /// The density function.
    #[must_use]
    pub fn kernel(&self) -> crate::density::Kernel {
        self.kernel
    }

    /// The density's groups of similar radii: each group's reach and its points
    /// ([`ExactDensity::groups`]).
    #[must_use]
    pub fn groups(&self) -> Vec<(f32, &[u32])> {
        match &self.index {
            Index::Cpu { density, .. } => density.groups().collect(),
            Index::Gpu { groups } => groups.iter().map(|(r, m)| (*r, m.as_slice())).collect(),
        }
    }

    /// The absolute iso-value.
    #[must_use]
    pub fn iso(&self) -> f32 {
        self.iso
    }

    /// The PCA normal at `x` (unoriented): eqs. 3 and 4 over the points within `pca_radius` of
    /// their own radius, with the paper's weight `1 - (r / R)^3`. `None` with fewer than four
    /// neighbours or a covariance without a clear least direction (a line or a blob), and for a
    /// caster without the CPU's index ([`Caster::with_weights_on_gpu`]).
    #[must_use]
    pub fn pca_normal(&self, x: Vec3) -> Option<Vec3> {
        let Index::Cpu { pca_grid, .. } = &self.index else {
            return None;
        };
        let points = &self.points;
        let scale = self.params.pca_radius;
        let (mut total, mut count) = (0.0f32, 0usize);
        let mut weighted = Vec3::ZERO;
        let mut second = Mat3::ZERO;
        // one pass: sum w, sum w e and sum w e e^T with e = p - x (about x, for precision),
        // then the covariance about the weighted mean (eqs. 3, 4)
        pca_grid.for_each_within(x, self.pca_reach, |j| {
            let j = j as usize;
            let e = points.positions[j] - x;
            let q = e.length() / (scale * points.radius(j));
            if q < 1.0 {
                let w = 1.0 - q * q * q;
                total += w;
                count += 1;
                weighted += e * w;
                second += Mat3::from_cols(e * e.x, e * e.y, e * e.z) * w;
            }
        });
        if count < 4 || total.is_nan() || total <= 0.0 {
            return None;
        }
        let mean = weighted / total;
        let c =
            second * (1.0 / total) - Mat3::from_cols(mean * mean.x, mean * mean.y, mean * mean.z);
        let (values, vectors) = crate::linalg::symmetric_eigen(c);
        // a plane-like neighbourhood: the least eigenvalue clearly below the middle one
        (values[0] < 0.5 * values[1]).then_some(vectors[0])
    }

    /// The first crossing of the iso-value along `o + t d` inside the sorted, merged intervals
    /// of `t` where the density can be non-zero: samples at `t_k = t_0 + k dt` from the first
    /// interval's start `t_0` (one step grid for the whole ray, so that the GPU twin, which
    /// marches from the first entry to the last exit, takes the same samples; those in the gaps
    /// between intervals are zero and skipped here), the first bracket `[t_(k-1), t_k]` that
    /// crosses refined by the bisection steps. The density evaluations are added to `samples`.
    /// `None` for a caster without the CPU's index ([`Caster::with_weights_on_gpu`]).
    pub fn first_crossing(
        &self,
        o: Vec3,
        d: Vec3,
        intervals: &[(f32, f32)],
        dt: f32,
        samples: &mut u64,
    ) -> Option<f32> {
        let density = self.density()?;
        let inside = |t: f32, samples: &mut u64| {
            *samples += 1;
            density.value(o + t * d) >= self.iso
        };
        let t0 = intervals.first()?.0;
        if inside(t0, samples) {
            return Some(t0);
        }
        let mut k = 1u32;
        for &(a, b) in intervals {
            // skip the gap: the first sample at or after the interval's start
            let first = ((a - t0) / dt).ceil();
            if first.is_finite() && first > k as f32 {
                k = first as u32;
            }
            loop {
                let t = t0 + k as f32 * dt;
                if t > b {
                    break;
                }
                if inside(t, samples) {
                    // bisection between the sample before (below) and this one (above)
                    let (mut below, mut above) = (t0 + (k - 1) as f32 * dt, t);
                    for _ in 0..self.params.bisection_steps {
                        let mid = 0.5 * (below + above);
                        if inside(mid, samples) {
                            above = mid;
                        } else {
                            below = mid;
                        }
                    }
                    return Some(0.5 * (below + above));
                }
                k += 1;
            }
        }
        None
    }
}

/// Ray casting as a [`WaterRenderer`]: the iso-surface of the source's points, with the
/// grid's kernel and `[raycast]`.
#[derive(Clone, Debug)]
pub struct Method {
    pub kernel: crate::density::Kernel,
    pub params: RayCastParams,
}

impl Method {
    /// The caster over points and their radii (the weights: the boundary calibration's, empty
    /// for none), with `reference` as the reference radius.
    pub fn caster<'a>(
        &self,
        (positions, radii): (&'a [Vec3], &'a [f32]),
        weights: &'a [f32],
        reference: f32,
    ) -> Result<Caster<'a>, RayCastError> {
        let mut points = Points::with_radii(positions, radii, reference);
        if !weights.is_empty() {
            points = points.with_weights(weights);
        }
        Caster::new(points, self.kernel, &self.params)
    }
}

impl WaterRenderer for Method {
    fn drawn(&self) -> Drawn {
        Drawn::Spheres { calibrated: true }
    }
    fn needs_points(&self) -> bool {
        true
    }
    fn water<'a>(&self, input: WaterInput<'a>) -> Result<Box<dyn WaterSurface + 'a>, Error> {
        Ok(Box::new(match input.gpu_weights {
            Some(weights) => Caster::with_weights_on_gpu(
                Points::with_radii(input.points.0, input.points.1, input.reference_radius),
                self.kernel,
                &self.params,
                weights.clone(),
            )?,
            None => self.caster(input.points, input.weights, input.reference_radius)?,
        }))
    }
}

impl Caster<'_> {
    /// Refuses a cast that reads the weights on the CPU when they are on the GPU.
    fn cpu_weights(&self) -> Result<(), Error> {
        match self.gpu_weights {
            Some(_) => Err(Error::InvalidArgument {
                argument: "water",
                reason: "its weights were solved on the GPU and stay there: draw it with the \
                         GpuPipeline that prepared it"
                    .into(),
            }),
            None => Ok(()),
        }
    }
}

impl WaterSurface for Caster<'_> {
    fn render(&self, view: &View) -> Result<Render, Error> {
        self.cpu_weights()?;
        Ok(cpu::render_view_cpu(self, view)?.render)
    }

    fn render_gpu(&self, ctx: &crate::gpu::GpuContext, view: &View) -> Result<Render, Error> {
        self.cpu_weights()?;
        Ok(gpu::render_view_gpu(ctx, self, view)?.render)
    }

    fn gpu_pass(
        &self,
        device: &wgpu::Device,
        _format: wgpu::TextureFormat,
        (w, h): (u32, u32),
    ) -> Result<Box<dyn GpuWaterPass>, Error> {
        Ok(Box::new(gpu::GpuCaster::new(device, w, h)?))
    }

    fn prepare_gpu(
        &self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        pass: &mut dyn GpuWaterPass,
        view: &View,
    ) -> Result<bool, Error> {
        let Some(cast) = pass.as_any_mut().downcast_mut::<gpu::GpuCaster>() else {
            return Ok(false);
        };
        if cast.size() != (view.width, view.height) {
            return Ok(false);
        }
        cast.prepare(device, queue, self, view)?;
        Ok(true)
    }
}
