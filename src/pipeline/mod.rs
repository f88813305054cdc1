//! The spine of the crate: one chain from particles to pixels, on the CPU.
//!
//! ```text
//! particles ─> surface detection ─> upsampling ─> density grid ─> surfels ─> EWA splats ─> optics
//!              (hysteresis, §3.1)   (§3.2-3.4)    (refined surface  (iso-surface)            (caustics,
//!                                                  + interior, each                          refraction,
//!                                                  its own radius)                           reflection)
//! ```
//!
//! [`Pipeline`] is built from one [`PipelineParams`] (every stage's parameters and the optics
//! scene, loadable from one TOML file) and runs one frame at a time: [`Pipeline::frame`] returns
//! a [`Frame`] holding every intermediate (classes and normals, refined points, density grid,
//! surfels, shaded splats, caustics, finished image) and the time of each stage. What must live
//! across the frames of a sequence lives in the pipeline: the hysteresis state of surface
//! detection (keyed by particle id), the support radius (given, or estimated on the first
//! frame), and the camera, pool and scene box, fitted on the first frame that is rendered and
//! then kept, so that what does not move renders the same in every frame.
//!
//! Where the rendered surfels come from is [`SurfelSource`]: the design chain (default), the
//! density grid of the raw particles, or the refined points themselves. How they are drawn is
//! [`Renderer`]: EWA surface splatting of surfels (default), particle splatting (Adams et al.
//! 2006), which draws the source's points as spheres with neither a grid nor surfels, ray
//! casting to the points' iso-surface or the screen-space surface; each gives the optics stage
//! the same per-pixel depth and normal buffers to refract and reflect. The pipeline holds the
//! renderer as a [`WaterRenderer`] ([`water_renderer`], the registry; or one of the caller's
//! own, [`Pipeline::set_water_renderer`]) and never matches on its kind
//! ([`crate::splat::water`]).
//!
//! ```
//! use fluid_surfels::pipeline::{Pipeline, PipelineParams, Through};
//! use fluid_surfels::scenes;
//!
//! let scene = scenes::block(&scenes::BlockParams { counts: [8, 8, 8], ..Default::default() })?;
//! let params = PipelineParams { support_radius: Some(scene.support_radius), ..Default::default() };
//! let mut pipeline = Pipeline::new(params)?;
//! let frame = pipeline.frame_through(&scene.particles, Through::Surfels)?;
//! assert!(frame.surfels.as_ref().is_some_and(|s| !s.is_empty()));
//! # Ok::<(), fluid_surfels::Error>(())
//! ```

use std::borrow::Cow;
use std::path::Path;
use std::time::Instant;

use glam::Vec3;
use image::RgbaImage;
use serde::{Deserialize, Serialize};

use crate::density::{self, Grid, GridSpec, Kernel, Points, Resolution};
use crate::neighbours::{self, Backend, Neighbourhoods};
use crate::optics::{self, Caustics, OpticsScene, ReceiverKind, Stage};
use crate::refine::{self, RefineParams, Refined};
use crate::scenes::ColumnSim;
use crate::splat::{
    self, Camera, Drawn, Light, Render, SplatParams, Surfel, View, WaterInput, WaterRenderer,
    WaterSurface,
};
use crate::surface::{ParticleClass, Surface, SurfaceDetector, SurfaceParams};
use crate::surfels::{self, SurfelParams, Surfels};
use crate::{Error, ParticleView};

pub mod boundary;
mod detail;
pub mod gpu;
mod plan;

pub use boundary::{
    BAND, BURIED, ChainPoints, Fluid, LISTED_TARGETS, LONE_RADIUS, MAX_WEIGHT, Sheet, WEIGHT_STEPS,
    boundary_weights, chain_points_at_boundary, particle_points_at_boundary,
};
pub use detail::{DEFAULT_DETAIL_PX, Detail, LEVEL_HYSTERESIS, ViewLevels, spacing_after};
pub use gpu::{GpuPipeline, iso_surfels_gpu};
pub use plan::{
    ChunkReport, DEFAULT_WARMUP, PLAN_VERSION, SequencePlan, frame_png, plan_of, render_chunk,
};

/// Where the surfels that are rendered come from.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SurfelSource {
    /// The design chain: the density grid of the refined surface points (each with the kernel
    /// radius its refinement gives it) plus the interior particles, surfels on its iso-surface.
    #[default]
    Chain,
    /// The density grid of all particles with one radius (the support radius), surfels on its
    /// iso-surface (Iwasaki et al. as published, without the upsampling).
    Particles,
    /// The refined points used directly as surfels, with their splat radius.
    Refined,
}

impl SurfelSource {
    /// Every source, in the order of the documentation.
    pub const ALL: [Self; 3] = [Self::Chain, Self::Particles, Self::Refined];

    /// The name used in files and on the command line.
    #[must_use]
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Chain => "chain",
            Self::Particles => "particles",
            Self::Refined => "refined",
        }
    }
}

/// How the water surface is drawn, in the shaded splats and in the optics' views.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Renderer {
    /// EWA surface splatting (Botsch et al. 2005) of the source's surfels: the design.
    #[default]
    Ewa,
    /// Particle splatting (Adams et al. 2006, [`splat::SplatMode::Spheres`]): the source's
    /// points drawn as spheres of their kernel radius (the zero level set of eq. 1), blended
    /// within `sphere_depth_offset` radii of the nearest; no density grid and no surfels. The
    /// points: `chain`, the interior particles with the support radius and the refined surface
    /// points with their kernel radii; `particles`, every particle with the support radius;
    /// `refined`, the refined points with their kernel radii.
    ParticleSplat,
    /// Ray casting to the iso-surface of the source's points (Xiao et al., [`crate::raycast`]):
    /// the same points and radii as `ParticleSplat`, the density of the grid's kernel, the
    /// iso-value and normals of `[raycast]`. The reference surface; on the GPU in
    /// [`GpuPipeline`] too (`raycast::gpu`).
    RayCast,
    /// Narrow-band screen-space fluid rendering (Oliveira and Paiva, [`crate::ssfr`]): the same
    /// points and radii as `ParticleSplat` drawn as spheres into a depth buffer (only the
    /// narrow band's, by default), the depth filtered (`[ssfr] filter`), the thickness from the
    /// band's voxels; on the GPU in [`GpuPipeline`] too (`ssfr::gpu`).
    Ssfr,
}

/// The renderer registry: the [`WaterRenderer`] of each [`Renderer`], made from the pipeline's
/// parameters. A new renderer is its module (a `WaterRenderer`, its `WaterSurface` and
/// `GpuWaterPass`) and one line here, with its name in [`Renderer`].
#[must_use]
pub fn water_renderer(params: &PipelineParams) -> Box<dyn WaterRenderer> {
    match params.renderer {
        Renderer::Ewa => Box::new(splat::Ewa),
        Renderer::ParticleSplat => Box::new(splat::ParticleSplat),
        Renderer::RayCast => Box::new(crate::raycast::Method {
            kernel: params.grid.kernel,
            params: params.raycast,
        }),
        Renderer::Ssfr => Box::new(crate::ssfr::Method {
            params: params.ssfr,
        }),
    }
}

impl Renderer {
    /// Every renderer, in the order of the documentation.
    pub const ALL: [Self; 4] = [Self::Ewa, Self::ParticleSplat, Self::RayCast, Self::Ssfr];

    /// What it draws the water from ([`WaterRenderer::drawn`] of its registered renderer).
    #[must_use]
    pub fn drawn(self) -> Drawn {
        water_renderer(&PipelineParams {
            renderer: self,
            ..PipelineParams::default()
        })
        .drawn()
    }

    /// The name used in files and on the command line.
    #[must_use]
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Ewa => "ewa",
            Self::ParticleSplat => "particle-splat",
            Self::RayCast => "ray-cast",
            Self::Ssfr => "ssfr",
        }
    }
}

/// How far [`Pipeline::frame_through`] runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Through {
    /// Surface detection only.
    Surface,
    /// Detection and upsampling.
    Refine,
    /// Up to the surfels of the chosen source.
    Surfels,
    /// Up to the surfels and the triangle mesh of the iso-surface they lie on
    /// ([`Frame::mesh`], made by [`Frame::triangulate`]), for renderers of one's own; no
    /// picture.
    Mesh,
    /// Up to the shaded EWA splats (Blinn-Phong, no optics).
    Splats,
    /// The finished frame: caustics, refraction and reflection.
    Frame,
}

/// The density grid of the surfel sources.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct GridParams {
    /// The density function (eq. 1 by default).
    pub kernel: Kernel,
    /// Grid spacing as a fraction of the smallest effective radius in use: spacing =
    /// `r_min / cells_per_radius`. Default 3: with fewer cells per radius the iso-surface keeps
    /// the grid's bumps (`tests/surfels.rs` measures normals within 2.2 degrees at 3 cells, up
    /// to 6.4 at 2).
    pub cells_per_radius: f32,
    /// A fixed resolution instead (overrides `cells_per_radius`).
    pub resolution: Option<Resolution>,
    /// Largest grid in bytes (4 per grid point). A finer grid is coarsened to fit, and the frame
    /// says so in [`Frame::warnings`]. Default 1 GiB.
    pub memory_budget: u64,
    /// Evaluate the grid only near the surface, in sparse blocks of 8^3 points
    /// ([`density::sparse`]): the blocks that lie in the LNM narrow band's interior voxels
    /// ([`crate::lnm`], voxels of the largest radius) or that no point reaches are not
    /// evaluated; the same surfels, in the same order, as the dense grid (tested), in less
    /// memory (measured: 19 against 87 MiB on the dam break's chain; 1.3-1.7x faster on `bench
    /// density`'s 150k block, but 1.2-1.4x slower than the dense grid on the dam break's chain,
    /// whose dense grid has since become faster; not profiled, the likely cause each point's
    /// disk set up again for every run of blocks it reaches). In [`GpuPipeline`] the blocks
    /// are chosen on the CPU and filled on the GPU, whose grid buffer then holds the evaluated
    /// blocks only ([`GpuPipeline::gpu_grid_bytes`]). Default off.
    pub narrow_band: bool,
    /// Where the chain's iso-surface lies: `paper` (every point's term as Iwasaki et al. eq. 1
    /// sums it; the surface 0.3-2.6 spacings outside the fluid below three refinement steps) or
    /// `boundary` (the refined points weighted so that it lies half a spacing outside the
    /// outermost particle centres at every level, [`boundary_weights`]) or `volume` (the raw
    /// particles only: splashsurf's field, each particle weighted by its SPH volume).
    /// Default `boundary`.
    pub calibration: Calibration,
    /// The fluid fraction the surface lies at with `calibration = "volume"` (splashsurf's
    /// `iso_surface_threshold`, in multiples of the rest density; its default 0.6). In (0, 1).
    pub volume_threshold: f32,
    /// How [`GpuPipeline`] fills the grid on the GPU ([`PipelineParams::gpu_surfels`]): `splat`
    /// (default; the paper's §4.1: four planes per RGBA pass with additive blending, the
    /// points' z-clusters drawn per group, each group unpacked into the grid's buffer) or
    /// `gather` (a compute pass summing the binned points around each grid point, in a fixed
    /// order).
    pub gpu_method: density::GpuDensityMethod,
}

/// Where the chain's iso-surface lies ([`GridParams::calibration`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Calibration {
    /// Every point's term as the paper sums it.
    Paper,
    /// The refined points weighted to put the surface at the fluid's boundary at every level.
    #[default]
    Boundary,
    /// splashsurf's field, for the raw particles (`source = "particles"`) alone: each particle
    /// weighted by its SPH volume ([`density::volume_weights`]), the surface where the fluid
    /// fraction is [`GridParams::volume_threshold`]. For users moving from splashsurf and for
    /// comparing with it: on the same particles, kernel and cells the two tools' meshes lie
    /// 0.013-0.031 cells apart (`tests/surfels.rs`), where the equal weights of `paper` and
    /// `boundary` put the double dam break's sheets 0.3-0.4 cells inside splashsurf's.
    Volume,
}

impl Calibration {
    /// Every calibration, in the order of the documentation.
    pub const ALL: [Self; 3] = [Self::Paper, Self::Boundary, Self::Volume];

    /// The name used in files and on the command line.
    #[must_use]
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Paper => "paper",
            Self::Boundary => "boundary",
            Self::Volume => "volume",
        }
    }
}

impl Default for GridParams {
    fn default() -> Self {
        Self {
            kernel: Kernel::Wyvill,
            cells_per_radius: 3.0,
            resolution: None,
            memory_budget: crate::memory::DEFAULT_MEMORY_BUDGET,
            narrow_band: false,
            calibration: Calibration::Boundary,
            volume_threshold: 0.6,
            gpu_method: density::GpuDensityMethod::Splat,
        }
    }
}

/// Every parameter of the chain, with the optics scene. `Default` holds the papers' values.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PipelineParams {
    /// Support radius of the simulation (world units); `None`: twice the particle spacing
    /// estimated from the first frame, then kept for the sequence.
    pub support_radius: Option<f32>,
    /// Stage 1.
    pub surface: SurfaceParams,
    /// Stage 2. `initial_radius` 0 (the default) follows the support radius.
    pub refine: RefineParams,
    /// Where the rendered surfels come from.
    pub source: SurfelSource,
    /// How they are drawn (EWA surfels, particle spheres or rays cast to the iso-surface).
    pub renderer: Renderer,
    /// The ray caster of [`Renderer::RayCast`].
    pub raycast: crate::raycast::RayCastParams,
    /// The screen-space renderer of [`Renderer::Ssfr`] (filter, narrow band, scales).
    pub ssfr: crate::ssfr::SsfrParams,
    /// Stage 3: the density grid.
    pub grid: GridParams,
    /// Stage 3: surfels on the iso-surface.
    pub surfels: SurfelParams,
    /// Stage 4: EWA splatting of the shaded-splats image (the optics stage has its own, in
    /// `scene.optics.splat`).
    pub splat: SplatParams,
    /// Stage 5 and the camera: light, receiver (pool), water, environment, image size.
    pub scene: OpticsScene,
    /// Fit the camera, the pool and the scene box on the first rendered frame and keep them
    /// (default); off, every frame is fitted anew.
    pub keep_views: bool,
    /// How much of `refine.steps` the upsampling takes: `auto` (default; detail from the view,
    /// [`Detail::Auto`]: a region stops once its points' spacing seen from the camera is under
    /// `detail_px` pixels; only for frames drawn from a camera, through [`Through::Splats`] or
    /// [`Through::Frame`] or drawn by the caller, [`Pipeline::set_drawn`]: the others refine
    /// every region fully) or `fixed` (every region all of them).
    pub detail: Detail,
    /// The footprint of `detail = "auto"`, in pixels (default [`DEFAULT_DETAIL_PX`]).
    pub detail_px: f32,
    /// The threads a frame may use (`None`, the default: rayon's global pool, one per core);
    /// a worker of a cluster is told how many cores are its own.
    pub threads: Option<usize>,
    /// [`GpuPipeline`] makes the density grid and the surfels on the GPU (default): the grid
    /// filled by the gather pass and the surfels extracted there, drawn from the GPU's buffer,
    /// nothing read back. Off, on the CPU as [`Pipeline`] makes them (to compare the two in one
    /// program). Only for the EWA renderer and the chain or particle source (the others have no
    /// density grid); [`Pipeline`] itself always makes them on the CPU. For the ray-cast
    /// renderer with the boundary calibration it says where the calibration's factors and the
    /// spheres' weights are found ([`GpuPipeline::weights_on_gpu`]).
    pub gpu_surfels: bool,
}

impl Default for PipelineParams {
    fn default() -> Self {
        Self {
            support_radius: None,
            surface: SurfaceParams::default(),
            refine: RefineParams::default(),
            source: SurfelSource::default(),
            renderer: Renderer::default(),
            raycast: crate::raycast::RayCastParams::default(),
            ssfr: crate::ssfr::SsfrParams::default(),
            grid: GridParams::default(),
            surfels: SurfelParams::default(),
            splat: SplatParams::default(),
            scene: OpticsScene::default(),
            keep_views: true,
            detail: Detail::Auto,
            detail_px: DEFAULT_DETAIL_PX,
            threads: None,
            gpu_surfels: true,
        }
    }
}

/// The keys of a TOML file that belong to the pipeline; every other key is the optics scene's.
const PIPELINE_KEYS: [&str; 15] = [
    "threads",
    "gpu_surfels",
    "detail",
    "detail_px",
    "raycast",
    "ssfr",
    "support_radius",
    "surface",
    "refine",
    "source",
    "renderer",
    "grid",
    "surfels",
    "splat",
    "keep_views",
];

impl PipelineParams {
    /// Reads a TOML file: the pipeline's tables (`support_radius`, `source`, `renderer`,
    /// `[raycast]`, `[surface]`,
    /// `[refine]`, `[grid]`, `[surfels]`, `[splat]`, `keep_views`) beside the scene's
    /// (`[camera]`, `[light]`, `[receiver]`, `[water]`, `[environment]`, `[optics]`), so a scene
    /// file of `render --config` is a pipeline file too. Unknown keys are refused; relative paths
    /// are relative to the file.
    pub fn from_toml_file(path: &Path) -> Result<Self, PipelineError> {
        let text = std::fs::read_to_string(path).map_err(|e| PipelineError::File {
            path: path.to_path_buf(),
            reason: e.to_string(),
        })?;
        Self::from_toml_str(&text, path.parent().unwrap_or(Path::new("."))).map_err(|reason| {
            PipelineError::File {
                path: path.to_path_buf(),
                reason,
            }
        })
    }

    /// [`PipelineParams::from_toml_file`] from text, relative paths taken from `base`.
    pub fn from_toml_str(text: &str, base: &Path) -> Result<Self, String> {
        let table: toml::Table = toml::from_str(text).map_err(|e| e.to_string())?;
        Self::from_table(table, base)
    }

    /// [`PipelineParams::from_toml_str`] from a table already parsed (or built by a binding from
    /// keyword arguments): the pipeline's keys and the scene's side by side, every key optional,
    /// unknown keys refused.
    pub fn from_table(table: toml::Table, base: &Path) -> Result<Self, String> {
        let (ours, theirs): (toml::Table, toml::Table) = table
            .into_iter()
            .partition(|(k, _)| PIPELINE_KEYS.contains(&k.as_str()));
        let mut params: Self = ours.try_into().map_err(|e| one_line(&e))?;
        params.scene = theirs.try_into().map_err(|e| one_line(&e))?;
        params.scene.resolve_paths(base);
        Ok(params)
    }

    /// Every parameter as one table in the layout of a pipeline file (the pipeline's keys and
    /// the scene's side by side; unset optional keys left out): what
    /// [`PipelineParams::from_table`] reads back to the same parameters.
    pub fn to_table(&self) -> Result<toml::Table, String> {
        let mut table = toml::Table::try_from(&self.scene).map_err(|e| e.to_string())?;
        let mut ours = toml::Table::try_from(self).map_err(|e| e.to_string())?;
        ours.remove("scene");
        table.extend(ours);
        Ok(table)
    }

    /// Checks what can be checked before any particle is seen.
    pub fn validate(&self) -> Result<(), PipelineError> {
        let bad = |name: &'static str, reason: String| {
            Err(PipelineError::InvalidParameter { name, reason })
        };
        if let Some(r) = self.support_radius
            && !(r.is_finite() && r > 0.0)
        {
            return bad("support_radius", format!("must be finite and > 0, got {r}"));
        }
        if let Some(t) = self.threads
            && !(1..=crate::sequence::MAX_JOBS).contains(&t)
        {
            return bad(
                "threads",
                format!("must lie in 1..={}, got {t}", crate::sequence::MAX_JOBS),
            );
        }
        if !(self.detail_px.is_finite() && self.detail_px > 0.0) {
            return bad(
                "detail_px",
                format!(
                    "must be finite and > 0 (the footprint in pixels under which a region stops refining), got {}",
                    self.detail_px
                ),
            );
        }
        let g = &self.grid;
        if !(g.cells_per_radius.is_finite() && (0.5..=64.0).contains(&g.cells_per_radius)) {
            return bad(
                "grid.cells_per_radius",
                format!("must lie in [0.5, 64], got {}", g.cells_per_radius),
            );
        }
        if !(g.volume_threshold > 0.0 && g.volume_threshold < 1.0) {
            return bad(
                "grid.volume_threshold",
                format!(
                    "must lie in (0, 1) (the fluid fraction the surface lies at; 1 is the bulk), got {}",
                    g.volume_threshold
                ),
            );
        }
        if g.calibration == Calibration::Volume && self.source != SurfelSource::Particles {
            return bad(
                "grid.calibration",
                format!(
                    "\"volume\" weighs the raw particles by their SPH volume (splashsurf's field): use it with source = \"particles\", not {:?}",
                    self.source.as_str()
                ),
            );
        }
        if g.memory_budget < 1 << 16 {
            return bad(
                "grid.memory_budget",
                format!("{} bytes is too small for any grid", g.memory_budget),
            );
        }
        self.surface.validate()?;
        Ok(())
    }
}

/// A table's deserialisation error on one line: toml writes where the key lies after an
/// escaped line break (`unknown field ..., expected ...\nin `grid`\n`), which the command line
/// printed as the two characters `\n`.
fn one_line(e: &toml::de::Error) -> String {
    e.to_string()
        .replace("\\n", " ")
        .split_whitespace()
        .collect::<Vec<_>>()
        .join(" ")
}

/// Errors of the pipeline's own settings (each stage has its own error type besides).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PipelineError {
    /// A parameter is out of range.
    #[error("invalid pipeline parameter `{name}`: {reason}")]
    InvalidParameter { name: &'static str, reason: String },
    /// A pipeline file could not be read or parsed.
    #[error("{}: {reason}", path.display())]
    File {
        path: std::path::PathBuf,
        reason: String,
    },
    /// The surface parameters.
    #[error(transparent)]
    Surface(#[from] crate::surface::SurfaceError),
}

/// Milliseconds spent in each stage of one frame (0 for stages that did not run).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct FrameTimings {
    pub neighbours_ms: f64,
    pub detect_ms: f64,
    pub refine_ms: f64,
    /// The chain's points weighted so that the surface lies at the fluid's boundary
    /// ([`Calibration::Boundary`]); in [`GpuPipeline`], whose GPU finds the weights, the CPU's
    /// part alone (the points gathered in one list, the particles' classes).
    pub calibration_ms: f64,
    pub density_ms: f64,
    pub surfels_ms: f64,
    /// The mesh of [`Through::Mesh`] (marching cubes over the density grid, its vertices moved
    /// onto the surfels).
    #[serde(default)]
    pub mesh_ms: f64,
    pub splats_ms: f64,
    pub caustics_ms: f64,
    pub image_ms: f64,
    pub total_ms: f64,
}

impl std::fmt::Display for FrameTimings {
    /// Each stage's milliseconds, `neighbours 8.0, detection 3.0, ..., image 0.0` (the total
    /// apart), as the command line prints them.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "neighbours {:.1}, detection {:.1}, refinement {:.1}, calibration {:.1}, density {:.1}, surfels {:.1}, mesh {:.1}, splats {:.1}, caustics {:.1}, image {:.1}",
            self.neighbours_ms,
            self.detect_ms,
            self.refine_ms,
            self.calibration_ms,
            self.density_ms,
            self.surfels_ms,
            self.mesh_ms,
            self.splats_ms,
            self.caustics_ms,
            self.image_ms
        )
    }
}

/// What a frame's level of detail chose and made (issue 36): `Frame::detail`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DetailReport {
    /// `auto` or `fixed` as applied: `fixed` for a frame without a camera (through
    /// [`Through::Surfels`] or earlier) whatever [`PipelineParams::detail`] says.
    pub detail: Detail,
    /// The steps run: the finest region's level (0 without refined points).
    pub steps: u32,
    /// Refined points.
    pub refined_points: usize,
    /// Refined points by the level of their region ([`Refined::levels`]), from level 0 up to
    /// the steps run.
    pub points_per_level: Vec<usize>,
    /// Refined particles whose level differs from their level in the last `auto` frame (by id;
    /// the level's hysteresis keeps this low in a sequence with a fixed camera).
    pub level_changes: usize,
    /// The density grid's cell, world units (0 without a grid).
    pub cell: f32,
    /// Surfels on the iso-surface (0 without a density grid): with `auto`, those the frame's
    /// picture can show ([`Pipeline::keep_hidden_surfels`]).
    pub surfels: usize,
    /// Crossings of the iso-surface left out as facing away from every view of the picture
    /// (`auto`; 0 otherwise): `surfels` plus these are the surfels of the whole surface.
    pub hidden_surfels: usize,
}

impl Default for DetailReport {
    /// Nothing made yet, every region at its full steps (`fixed`) until the view says otherwise.
    fn default() -> Self {
        Self {
            detail: Detail::Fixed,
            steps: 0,
            refined_points: 0,
            points_per_level: Vec::new(),
            level_changes: 0,
            cell: 0.0,
            surfels: 0,
            hidden_surfels: 0,
        }
    }
}

/// The finished frame of the optics stage.
#[derive(Debug)]
pub struct Finished {
    /// The scene resolved for this frame (receiver, light views, camera).
    pub stage: Stage,
    /// The caustics map.
    pub caustics: Caustics,
    /// The finished image (gamma-encoded RGBA).
    pub image: RgbaImage,
    /// Linear radiance per pixel, row-major from the top; `w = 1` where water covers the pixel
    /// (in front of the receiver), 0 elsewhere.
    pub linear: Vec<[f32; 4]>,
}

/// One frame through the pipeline: every intermediate that was computed.
#[derive(Debug)]
pub struct Frame {
    /// The support radius used.
    pub radius: f32,
    /// Mean neighbour count at the support radius.
    pub mean_neighbours: f32,
    /// Classes, offsets and normals of every particle; flips since the previous frame.
    pub surface: Surface,
    /// Indices of the particles that were refined (surface and isolated ones, in the spatial
    /// order of [`refined_indices`]; the refined points' first ones follow it).
    pub surface_indices: Vec<u32>,
    /// The refined surface (through [`Through::Refine`] and after).
    pub refined: Option<Refined>,
    /// The density grid (Chain and Particles sources): dense, or sparse with
    /// [`GridParams::narrow_band`].
    pub grid: Option<Grid>,
    /// Surfels on the iso-surface (Chain and Particles sources, EWA renderer).
    pub surfels: Option<Surfels>,
    /// The triangle mesh of the surfels' iso-surface (through [`Through::Mesh`];
    /// [`Frame::triangulate`] makes it for a frame run through the surfels or later).
    pub mesh: Option<crate::mesh::Mesh>,
    /// The surfels that are rendered, whatever their source (the spheres of
    /// [`Renderer::ParticleSplat`]).
    pub render_surfels: Vec<Surfel>,
    /// The weights of [`Frame::render_surfels`]' spheres in the ray caster's density (the
    /// boundary calibration, [`boundary_weights`]; empty: every one 1).
    pub render_weights: Vec<f32>,
    /// The camera the frame is seen from.
    pub camera: Option<Camera>,
    /// The shaded EWA splats (only when run [`Through::Splats`]: the finished frame splats the
    /// water itself).
    pub splats: Option<Render>,
    /// The finished frame (through [`Through::Frame`]).
    pub finished: Option<Finished>,
    /// Milliseconds per stage.
    pub timings: FrameTimings,
    /// The level of detail: steps run, refined points, grid cell, surfels.
    pub detail: DetailReport,
    /// What a user should know: a grid coarsened to fit the memory budget, for instance.
    pub warnings: Vec<String>,
    /// The density grid and the surfels were made on the GPU ([`GpuPipeline::prepare`] with
    /// [`PipelineParams::gpu_surfels`]) and stay there: `grid`, `surfels` and `render_surfels`
    /// are empty, [`DetailReport::surfels`] is a recent frame's count (read back without a
    /// wait), [`GpuPipeline::read_surfels`] reads them back.
    pub surfels_on_gpu: bool,
    /// The weights of the ray caster's spheres (the boundary calibration's) were found on the
    /// GPU ([`GpuPipeline::prepare`] with [`PipelineParams::gpu_surfels`]) and stay there:
    /// `render_surfels` holds a sphere for every particle and every sheet point (those the
    /// calibration's factors leave out are weighted [`boundary::gpu::DROPPED`] there and not
    /// drawn), `render_weights` is empty, [`GpuPipeline::read_sphere_weights`] reads them
    /// back; the frame is drawn by the `GpuPipeline` that prepared it.
    pub weights_on_gpu: bool,
    /// Where the water is, as the views (camera, pool, the light's screen) are fitted to it,
    /// for surfels on a density grid with the boundary calibration: from the particles
    /// ([`Pipeline::grid_water_shape`]), so that the CPU's pictures and [`GpuPipeline`]'s,
    /// whose surfels stay on the GPU, are seen alike; for the spheres of the peer renderers,
    /// their box with the water's level from the particles (`Pipeline::sphere_water_shape`).
    /// `None`: fitted to the surfels.
    pub shape: Option<optics::WaterShape>,
}

impl Frame {
    /// The box the pictures of this frame are fitted to: that of its shape ([`Frame::shape`],
    /// what is drawn where the particles put the water), else that of its drawable surfels.
    #[must_use]
    pub fn water_box(&self) -> Option<(Vec3, Vec3)> {
        self.shape
            .and_then(|s| s.drawn)
            .or_else(|| splat::bounds(&self.render_surfels))
    }

    /// The triangle mesh of the iso-surface the surfels lie on: marching cubes over the frame's
    /// density grid (dense, or sparse: the blocks near the surface) at the surfels' iso-value
    /// ([`crate::mesh`]), its vertices the surfels themselves (vertex `n` is the crossing surfel
    /// `n` was projected from: on the exact iso-surface, the kernel's gradient as normal; the
    /// few whose move would fold a triangle stay on their edges, [`crate::mesh::Mesh::move_onto`]);
    /// `None` without a grid (the peer renderers' spheres, or a frame not run through the
    /// surfels). [`Through::Mesh`] stores it in [`Frame::mesh`]. A frame that left out the
    /// surfels its picture cannot show ([`Pipeline::keep_hidden_surfels`]) has vertices on the
    /// grid's edges instead.
    #[must_use]
    pub fn triangulate(&self) -> Option<crate::mesh::Mesh> {
        let grid = self.grid.as_ref()?;
        let surfels = self.surfels.as_ref()?;
        let mut mesh = match grid {
            Grid::Dense(g) => {
                crate::mesh::marching_cubes_of_values(&g.spec, &g.values, surfels.iso)
            }
            Grid::Sparse(g) => crate::mesh::marching_cubes_of_sparse(g, surfels.iso),
        };
        // the same crossings in the same order (tests/pipeline.rs); were they ever not, the
        // vertices would stay on the grid's edges. A vertex whose move would fold or collapse a
        // triangle stays on its edge.
        if mesh.positions.len() == surfels.len() {
            mesh.move_onto(&surfels.positions, &surfels.normals);
        }
        Some(mesh)
    }
}

/// What [`Pipeline::detect_stage`] gives a frame.
struct Detected {
    radius: f32,
    mean_neighbours: f32,
    surface: Surface,
    surface_indices: Vec<u32>,
}

/// What a sequence keeps from its first rendered frame.
#[derive(Clone, Debug)]
struct Views {
    camera: Camera,
    /// The receiver as fitted (an `Auto` pool resolved into its box), the scene box, and the
    /// light's screen and map resolutions, when the optics ran.
    optics: Option<KeptOptics>,
}

/// What the optics stage keeps of the first rendered frame (part of a [`SequencePlan`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct KeptOptics {
    /// The receiver as fitted (an `auto` pool resolved into its box).
    pub receiver: optics::Receiver,
    /// The scene box.
    pub bounds: [Vec3; 2],
    /// The light's caustics screen resolution.
    pub screen: [u32; 2],
    /// The caustics map's resolution.
    pub map: [u32; 2],
}

/// The chain on the CPU. See the module documentation.
pub struct Pipeline {
    params: PipelineParams,
    detector: SurfaceDetector,
    radius: Option<f32>,
    views: Option<Views>,
    /// The box the views are fitted to besides the first frame's water ([`Pipeline::fit_to`]).
    fit: Option<(Vec3, Vec3)>,
    /// The density grid's buffer, handed back by [`Pipeline::recycle`] for the next frame.
    grid_buffer: Vec<f32>,
    /// Told each warning as soon as it is known ([`Pipeline::on_warning`]).
    warning_sink: Option<WarningSink>,
    /// Frames through the surfels are drawn by the caller as this picture
    /// ([`Pipeline::set_drawn`]).
    drawn: Option<Through>,
    /// Frames keep the surfels their pictures cannot show ([`Pipeline::keep_hidden_surfels`]).
    keep_hidden: bool,
    /// The level of detail of each surface particle (by id) in the last `detail = "auto"`
    /// frame: the hysteresis of [`ViewLevels::level_after`].
    levels_before: std::collections::HashMap<u32, u8>,
    /// What draws the water ([`water_renderer`] of the parameters, or the caller's own).
    water: Box<dyn WaterRenderer>,
    /// The threads of `params.threads`, when given.
    pool: Option<std::sync::Arc<rayon::ThreadPool>>,
    /// The receiver as the light's map and the camera saw it last frame ([`optics::ReceiverViews`]).
    receiver_views: optics::ReceiverViews,
    /// The boundary calibration's term lists, their memory kept for the next frame
    /// ([`boundary::TermLists`]).
    term_lists: std::sync::Mutex<boundary::TermLists>,
}

/// A function told each warning of a frame as soon as it is known.
type WarningSink = Box<dyn FnMut(&str) + Send>;

impl Pipeline {
    /// A pipeline for a new sequence. Reads the environment image, if any, once.
    pub fn new(mut params: PipelineParams) -> Result<Self, Error> {
        params.validate()?;
        params.scene.environment.load()?;
        Ok(Self {
            detector: SurfaceDetector::new(params.surface)?,
            radius: params.support_radius,
            views: None,
            fit: None,
            grid_buffer: Vec::new(),
            warning_sink: None,
            drawn: None,
            keep_hidden: false,
            levels_before: std::collections::HashMap::new(),
            water: water_renderer(&params),
            receiver_views: optics::ReceiverViews::default(),
            term_lists: std::sync::Mutex::default(),
            pool: match params.threads {
                Some(n) => Some(std::sync::Arc::new(
                    rayon::ThreadPoolBuilder::new()
                        .num_threads(n)
                        .build()
                        .map_err(|e| Error::InvalidArgument {
                            argument: "threads",
                            reason: e.to_string(),
                        })?,
                )),
                None => None,
            },
            params,
        })
    }

    /// Says that the frames made through [`Through::Surfels`] are drawn by the caller (on a
    /// GPU, in a viewer) as the shaded splats (`Some(Through::Splats)`) or the finished frame
    /// (`Some(Through::Frame)`), from the pipeline's camera ([`Pipeline::set_camera`], the
    /// scene's, or the one such a picture fits) at the image size, so that `detail = "auto"`
    /// chooses their detail from that view as it does for the pictures the pipeline draws
    /// itself. `None` (the default): such frames refine every region to `refine.steps`, so that
    /// surfels written to disk never depend on an image size.
    pub fn set_drawn(&mut self, drawn_as: Option<Through>) {
        self.drawn = drawn_as.filter(|&t| t >= Through::Splats);
    }

    /// Whether frames keep the surfels their pictures cannot show. By default (`false`) a frame
    /// with `detail = "auto"` whose picture the pipeline draws from known views leaves out the
    /// surfels that face away from all of them (see [`Pipeline::frame_through`]); `true` keeps
    /// every one, for a caller that wants the whole surface as well as the picture (surfels
    /// written to disk, or compared with [`GpuPipeline`]'s, which keeps them all).
    pub fn keep_hidden_surfels(&mut self, keep: bool) {
        self.keep_hidden = keep;
    }

    /// Tells `sink` each warning as soon as it is known, before the rest of the frame's work (a
    /// support radius far off is known after the neighbour search, before the upsampling and the
    /// grid): a command line prints it at once instead of after minutes of work. The warnings
    /// are in [`Frame::warnings`] as well.
    pub fn on_warning(&mut self, sink: impl FnMut(&str) + Send + 'static) {
        self.warning_sink = Some(Box::new(sink));
    }

    /// Keeps `warning` for the frame and tells the sink.
    fn warn(&mut self, warnings: &mut Vec<String>, warning: Option<String>) {
        if let Some(w) = warning {
            if let Some(sink) = self.warning_sink.as_mut() {
                sink(&w);
            }
            warnings.push(w);
        }
    }

    /// Fits the camera, the pool and the scene box of the sequence to the box `[lo, hi]` as well
    /// as to the first rendered frame's water: give the union of every frame's particle bounds
    /// (widened by the support radius) so that the water of every frame lies inside the views
    /// kept from the first one (`keep_views`). Call before the first frame; a later call refits
    /// on the next frame.
    pub fn fit_to(&mut self, lo: Vec3, hi: Vec3) -> Result<(), Error> {
        if !(lo.is_finite() && hi.is_finite() && lo.cmple(hi).all()) {
            return Err(Error::InvalidArgument {
                argument: "fit_to",
                reason: format!("[{lo}, {hi}] is not a finite box"),
            });
        }
        self.fit = Some((lo, hi));
        self.views = None;
        Ok(())
    }

    /// The parameters.
    #[must_use]
    pub fn params(&self) -> &PipelineParams {
        &self.params
    }

    /// The support radius in use (`None` before the first frame when it is estimated).
    #[must_use]
    pub fn support_radius(&self) -> Option<f32> {
        self.radius
    }

    /// The camera kept for the sequence, once a frame has been rendered.
    #[must_use]
    pub fn camera(&self) -> Option<Camera> {
        self.views.as_ref().map(|v| v.camera)
    }

    /// Looks from `camera` from the next frame on (an orbiting viewer's camera), keeping the
    /// pool and the scene box the sequence fitted.
    pub fn set_camera(&mut self, camera: Camera) {
        self.params.scene.camera = Some(camera);
        if let Some(v) = self.views.as_mut() {
            v.camera = camera;
        }
    }

    /// Renders images of `width` x `height` from the next frame on (a resized window).
    pub fn set_image_size(&mut self, width: u32, height: u32) {
        self.params.scene.optics.image_size = [width, height];
    }

    /// Takes the rendered surfels from `source` from the next frame on.
    pub fn set_source(&mut self, source: SurfelSource) {
        self.params.source = source;
    }

    /// Draws with `renderer` from the next frame on.
    pub fn set_renderer(&mut self, renderer: Renderer) {
        self.params.renderer = renderer;
        self.water = water_renderer(&self.params);
    }

    /// Draws with a renderer of the caller's own from the next frame on (the shaded splats, the
    /// finished frame's views and [`GpuPipeline`]'s passes; `params().renderer` then names only
    /// the one it replaced). See [`crate::splat::water`].
    pub fn set_water_renderer(&mut self, water: Box<dyn WaterRenderer>) {
        self.water = water;
    }

    /// What draws the water.
    #[must_use]
    pub fn water_renderer(&self) -> &dyn WaterRenderer {
        self.water.as_ref()
    }

    /// Forgets what the sequence kept (hysteresis, estimated radius, camera and pool): the next
    /// frame starts a new sequence.
    pub fn reset(&mut self) {
        self.detector.reset();
        self.levels_before.clear();
        self.radius = self.params.support_radius;
        self.views = None;
    }

    /// Hands a frame's largest buffer (the density grid's values) back, so that the next frame
    /// fills it instead of allocating: a sequence that recycles each frame after use allocates
    /// the grid only while it grows.
    pub fn recycle(&mut self, frame: Frame) {
        if let Some(Grid::Dense(grid)) = frame.grid
            && grid.values.capacity() > self.grid_buffer.capacity()
        {
            self.grid_buffer = grid.values;
        }
    }

    /// The whole chain on one frame: a `&ParticleSet`, or a [`ParticleView`] of positions (and
    /// ids, masses) held elsewhere, read where they lie.
    pub fn frame<'a>(&mut self, particles: impl Into<ParticleView<'a>>) -> Result<Frame, Error> {
        self.frame_through(particles, Through::Frame)
    }

    /// The chain on one frame, up to `through` (on `params.threads` threads, when given).
    ///
    /// With `detail = "auto"` and EWA splats, a frame drawn here (through the shaded splats or
    /// the finished frame, or marked drawn as the shaded splats by [`Pipeline::set_drawn`])
    /// leaves out of [`Frame::surfels`] the surfels that face away from its camera, and for the
    /// finished frame from its light too, which the picture cannot show (the same pixels; see
    /// [`surfels::Viewpoints`]); [`Pipeline::keep_hidden_surfels`] keeps them.
    pub fn frame_through<'a>(
        &mut self,
        particles: impl Into<ParticleView<'a>>,
        through: Through,
    ) -> Result<Frame, Error> {
        let particles: ParticleView<'a> = particles.into();
        self.in_pool(|p| p.frame_here(particles, through))
    }

    /// Runs `f` on the pipeline in its own thread pool (`params.threads`), or where it is.
    fn in_pool<R: Send>(&mut self, f: impl FnOnce(&mut Self) -> R + Send) -> R {
        match self.pool.clone() {
            Some(pool) => pool.install(|| f(self)),
            None => f(self),
        }
    }

    /// [`Pipeline::frame_through`] in the current thread pool.
    fn frame_here(
        &mut self,
        particles: ParticleView<'_>,
        through: Through,
    ) -> Result<Frame, Error> {
        let total = Instant::now();
        let (mut frame, mut warnings) = self.detect_and_refine(particles, through)?;
        if through < Through::Surfels {
            frame.timings.total_ms = ms(total);
            frame.warnings = warnings;
            return Ok(frame);
        }
        // stage 3: density grid and iso-surface surfels
        let SourceStage {
            render,
            iso,
            calibration_ms,
            weights,
        } = self.source_stage(
            self.params.source,
            particles,
            &frame.surface,
            frame.refined.as_ref(),
            (
                frame.radius,
                self.hidden_from(particles.positions, frame.radius, through)?,
            ),
        )?;
        frame.render_surfels = render;
        frame.render_weights = weights;
        frame.timings.calibration_ms = calibration_ms;
        match iso {
            Some(Some(iso)) => {
                frame.timings.density_ms = iso.density_ms;
                frame.timings.surfels_ms = iso.surfels_ms;
                self.warn(&mut warnings, iso.warning);
                frame.detail.cell = iso.grid.spec().spacing;
                frame.detail.surfels = iso.surfels.len();
                frame.detail.hidden_surfels = iso.hidden;
                frame.grid = Some(iso.grid);
                frame.surfels = Some(iso.surfels);
            }
            Some(None) => frame.surfels = Some(Surfels::default()),
            None => {}
        }
        frame.shape = frame.grid.as_ref().and_then(|g| {
            self.grid_water_shape(particles.positions, &frame.surface, frame.radius, g.spec())
        });
        if self.water.drawn() != Drawn::Surfels {
            frame.shape = Some(self.sphere_water_shape(
                particles.positions,
                &frame.surface,
                frame.radius,
                &frame.render_surfels,
            ));
        }
        if through == Through::Mesh {
            let t = Instant::now();
            frame.mesh = frame.triangulate();
            frame.timings.mesh_ms = ms(t);
        }
        if through >= Through::Splats {
            self.render(&mut frame, through)?;
        }
        frame.warnings = warnings;
        frame.timings.total_ms = ms(total);
        Ok(frame)
    }

    /// The chain up to the density grid's input, for a caller that makes the grid and the
    /// surfels itself ([`GpuPipeline`] on the GPU): detection and upsampling of `particles`
    /// as [`Pipeline::frame_through`] runs them for a frame made [`Through::Surfels`], then the
    /// points of the pipeline's source with their kernel radii and weights (the boundary
    /// calibration) and the grid around them ([`grid_for`] with `budget` as the memory budget
    /// when it is smaller; a coarsened grid is said in the frame's warnings). `None` instead of
    /// the points for a source or a renderer that has no density grid (the refined points, the
    /// peer renderers' spheres) and for a frame without points.
    pub fn frame_to_grid<'a>(
        &mut self,
        particles: impl Into<ParticleView<'a>>,
        budget: u64,
    ) -> Result<(Frame, Option<GridInput<'a>>), Error> {
        self.frame_to_grid_with(particles.into(), budget, false)
    }

    /// [`Pipeline::frame_to_grid`]; with `defer_weights` and the boundary calibration, the
    /// calibration's factors and the sheet's weights are left to find ([`GridInput::solve`]:
    /// every particle, then every sheet point, with no weights; [`GpuPipeline`] finds them on
    /// the GPU).
    pub(crate) fn frame_to_grid_with<'a>(
        &mut self,
        particles: ParticleView<'a>,
        budget: u64,
        defer_weights: bool,
    ) -> Result<(Frame, Option<GridInput<'a>>), Error> {
        self.in_pool(|p| {
            let total = Instant::now();
            let (mut frame, mut warnings) = p.detect_and_refine(particles, Through::Surfels)?;
            let source = p.params.source;
            let input = if source == SurfelSource::Refined || p.water.drawn() != Drawn::Surfels {
                None
            } else {
                let t = Instant::now();
                let mut solve = None;
                let (positions, radii, weights) =
                    if defer_weights && p.params.grid.calibration == Calibration::Boundary {
                        // every particle, then every sheet point: the factors and the
                        // weights are found on the GPU
                        let b = p.with_boundary_sheet(
                            source,
                            particles,
                            &frame.surface,
                            frame.refined.as_ref(),
                            frame.radius,
                            |sheet| {
                                Ok(boundary::boundary_layout(
                                    particles.positions,
                                    &frame.surface,
                                    sheet,
                                    frame.radius,
                                ))
                            },
                        )?;
                        solve = Some(WeightSolve {
                            particles: b.particles,
                            classes: b.classes,
                            normals: b.normals,
                            spacing: b.spacing,
                            tau: p.iso_value(frame.radius),
                        });
                        (Cow::Owned(b.positions), b.radii, Vec::new())
                    } else {
                        p.density_points(
                            source,
                            particles,
                            &frame.surface,
                            frame.refined.as_ref(),
                            frame.radius,
                        )?
                    };
                if !weights.is_empty() || solve.is_some() {
                    frame.timings.calibration_ms = ms(t);
                }
                let points = points_of(&positions, &radii, &weights, frame.radius);
                if points.is_empty() {
                    None
                } else {
                    points.check()?;
                    let grid = GridParams {
                        memory_budget: p.params.grid.memory_budget.min(budget),
                        ..p.params.grid
                    };
                    let (spec, warning) = grid_for(&points, &grid)?;
                    p.warn(&mut warnings, warning);
                    frame.detail.cell = spec.spacing;
                    Some(GridInput {
                        positions,
                        radii,
                        weights,
                        radius: frame.radius,
                        spec,
                        solve,
                    })
                }
            };
            frame.warnings = warnings;
            frame.timings.total_ms = ms(total);
            Ok((frame, input))
        })
    }

    /// The chain up to the ray caster's spheres with the boundary calibration's factors left
    /// to find, for a caller that finds them and solves the weights
    /// ([`boundary::gpu::PointWeights::record_layout`], on the GPU): detection, upsampling,
    /// and every particle then every sheet point ([`boundary::boundary_layout`], uncompacted:
    /// a point the factors leave out is drawn by no one, its weight on the GPU negative). The
    /// frame's `render_surfels` are the spheres of the layout's points, its `render_weights`
    /// empty, its shape the particles' ([`Pipeline::sphere_water_shape`]). `None`: no point.
    pub(crate) fn frame_to_boundary_layout(
        &mut self,
        particles: ParticleView<'_>,
    ) -> Result<(Frame, Option<boundary::BoundaryLayout>), Error> {
        self.in_pool(|p| {
            let total = Instant::now();
            let (mut frame, warnings) = p.detect_and_refine(particles, Through::Surfels)?;
            let t = Instant::now();
            let layout = p.with_boundary_sheet(
                p.params.source,
                particles,
                &frame.surface,
                frame.refined.as_ref(),
                frame.radius,
                |sheet| {
                    Ok(boundary::boundary_layout(
                        particles.positions,
                        &frame.surface,
                        sheet,
                        frame.radius,
                    ))
                },
            )?;
            frame.timings.calibration_ms = ms(t);
            frame.render_surfels =
                splat::spheres_from(&layout.positions, &layout.radii, frame.radius, splat::WATER);
            frame.shape = Some(p.sphere_water_shape(
                particles.positions,
                &frame.surface,
                frame.radius,
                &frame.render_surfels,
            ));
            frame.warnings = warnings;
            frame.timings.total_ms = ms(total);
            let layout = (!layout.positions.is_empty()).then_some(layout);
            Ok((frame, layout))
        })
    }

    /// Stages 1 and 2 of a frame made `through`: detection and, where `through` and the
    /// source need it, upsampling.
    fn detect_and_refine(
        &mut self,
        particles: ParticleView<'_>,
        through: Through,
    ) -> Result<(Frame, Vec<String>), Error> {
        particles.validate()?;
        let mut timings = FrameTimings::default();
        let mut warnings = Vec::new();
        let Detected {
            radius,
            mean_neighbours,
            surface,
            surface_indices,
        } = self.detect_stage(particles, &mut timings, &mut warnings)?;
        let mut frame = Frame {
            radius,
            mean_neighbours,
            surface,
            surface_indices,
            refined: None,
            grid: None,
            surfels: None,
            mesh: None,
            render_surfels: Vec::new(),
            render_weights: Vec::new(),
            camera: None,
            splats: None,
            finished: None,
            timings,
            detail: DetailReport::default(),
            warnings: Vec::new(),
            surfels_on_gpu: false,
            weights_on_gpu: false,
            shape: None,
        };
        // stage 2: upsampling of the surface
        let needs_refined = through >= Through::Refine
            && (through == Through::Refine || self.params.source != SurfelSource::Particles);
        if needs_refined {
            let t = Instant::now();
            let (p, n) = gather(particles, &frame.surface, &frame.surface_indices);
            let params = self.refine_params(radius);
            let refined = match self.view_levels(particles.positions, radius, through)? {
                Some(view) => {
                    frame.detail.detail = Detail::Auto;
                    let (levels, changes) =
                        self.surface_levels(&view, particles, &frame.surface_indices);
                    frame.detail.level_changes = changes;
                    refine::refine_to_levels(&p, &n, &params, true, &levels)?
                }
                None => refine::refine(&p, &n, &params)?,
            };
            frame.detail.steps = refined.levels.iter().copied().max().map_or(0, u32::from);
            frame.detail.refined_points = refined.len();
            frame.detail.points_per_level = vec![0; refined.stats.len() + 1];
            for &l in &refined.levels {
                frame.detail.points_per_level[l as usize] += 1;
            }
            frame.refined = Some(refined);
            frame.timings.refine_ms = ms(t);
        }
        Ok((frame, warnings))
    }

    /// Stage 3 for `source` and the pipeline's renderer, from a frame's surface and refined
    /// points: the surfels to draw (spheres of the source's points for the peer renderers), and
    /// for the density sources with the EWA renderer the grid stage's result (`Some(None)`: no
    /// point to make a grid of), and the milliseconds spent weighting the points for the
    /// boundary calibration. The ray caster draws the iso-surface of the source's points: with
    /// the boundary calibration those of the density grid, weighted alike.
    fn source_stage(
        &mut self,
        source: SurfelSource,
        particles: ParticleView<'_>,
        surface: &Surface,
        refined: Option<&Refined>,
        (radius, seen): (f32, Option<surfels::Viewpoints>),
    ) -> Result<SourceStage, Error> {
        let colour = splat::WATER;
        let given = refined;
        let refined = || refined.expect("refined above");
        let boundary = self.params.grid.calibration == Calibration::Boundary;
        let drawn = self.water.drawn();
        if drawn == (Drawn::Spheres { calibrated: true })
            && boundary
            && source != SurfelSource::Refined
        {
            let t = Instant::now();
            let c = self.points_at_boundary(source, particles, surface, given, radius)?;
            return Ok(SourceStage {
                render: splat::spheres_from(&c.positions, &c.radii, radius, colour),
                iso: None,
                calibration_ms: ms(t),
                weights: c.weights,
            });
        }
        if drawn != Drawn::Surfels {
            let (positions, radii) = match source {
                SurfelSource::Chain => chain_points(particles, surface, refined(), radius),
                SurfelSource::Particles => (particles.positions.to_vec(), Vec::new()),
                SurfelSource::Refined => {
                    let r = refined();
                    (r.positions.clone(), r.kernel_radii.clone())
                }
            };
            return Ok(SourceStage {
                render: splat::spheres_from(&positions, &radii, radius, colour),
                iso: None,
                calibration_ms: 0.0,
                weights: Vec::new(),
            });
        }
        // stage 3 of the EWA renderer: the refined points themselves, or the iso-surface of
        // the source's density grid
        if source == SurfelSource::Refined {
            let r = refined();
            let render = splat::surfels_from(&r.positions, &r.normals, &r.gap_free_radii(), colour);
            return Ok(SourceStage {
                render,
                iso: None,
                calibration_ms: 0.0,
                weights: Vec::new(),
            });
        }
        let t = Instant::now();
        let (positions, radii, weights) =
            self.density_points(source, particles, surface, given, radius)?;
        let calibration_ms = if weights.is_empty() { 0.0 } else { ms(t) };
        let points = points_of(&positions, &radii, &weights, radius);
        let buffer = std::mem::take(&mut self.grid_buffer);
        let iso = iso_surfels_in(
            points,
            (&self.params.grid, &self.params.surfels),
            buffer,
            seen,
        )?;
        let render = iso.as_ref().map_or_else(Vec::new, |iso| {
            splat::surfels_from(
                &iso.surfels.positions,
                &iso.surfels.normals,
                &iso.surfels.radii,
                colour,
            )
        });
        Ok(SourceStage {
            render,
            iso: Some(iso),
            calibration_ms,
            weights: Vec::new(),
        })
    }

    /// The points of the density grid of `source` (the chain or the raw particles): positions,
    /// kernel radii (empty: every one the support radius `radius`) and weights (empty: every
    /// one 1; the boundary calibration's otherwise).
    fn density_points<'a>(
        &self,
        source: SurfelSource,
        particles: ParticleView<'a>,
        surface: &Surface,
        refined: Option<&Refined>,
        radius: f32,
    ) -> Result<SourcePoints<'a>, Error> {
        if self.params.grid.calibration == Calibration::Boundary {
            let c = self.points_at_boundary(source, particles, surface, refined, radius)?;
            return Ok((Cow::Owned(c.positions), c.radii, c.weights));
        }
        Ok(match source {
            SurfelSource::Particles if self.params.grid.calibration == Calibration::Volume => {
                let g = &self.params.grid;
                let scale = self.iso_value(radius) / g.volume_threshold;
                let weights =
                    density::volume_weights(particles.positions, g.kernel, radius, scale)?;
                (Cow::Borrowed(particles.positions), Vec::new(), weights)
            }
            SurfelSource::Particles => (Cow::Borrowed(particles.positions), Vec::new(), Vec::new()),
            _ if self.params.grid.calibration == Calibration::Volume => {
                return Err(Error::InvalidArgument {
                    argument: "grid.calibration",
                    reason: format!(
                        "\"volume\" weighs the raw particles (source \"particles\"), not the {} source's points",
                        source.as_str()
                    ),
                });
            }
            _ => {
                let r = refined.expect("refined above");
                let (p, r) = chain_points(particles, surface, r, radius);
                (Cow::Owned(p), r, Vec::new())
            }
        })
    }

    /// The points of `source` (the chain or the raw particles) with the surface at the fluid's
    /// boundary ([`chain_points_at_boundary`], [`particle_points_at_boundary`]): positions,
    /// kernel radii and weights. The chain past 3 steps is refused: the surface can lie no
    /// farther from a refined point than its kernel reaches, and past 3 steps (with the default
    /// kernel factor 2) that is short of the half spacing the boundary lies out.
    fn points_at_boundary(
        &self,
        source: SurfelSource,
        particles: ParticleView<'_>,
        surface: &Surface,
        refined: Option<&Refined>,
        radius: f32,
    ) -> Result<boundary::ChainPoints, Error> {
        let (kernel, tau) = (self.params.grid.kernel, self.iso_value(radius));
        self.with_boundary_sheet(source, particles, surface, refined, radius, |sheet| {
            let mut lists = self
                .term_lists
                .lock()
                .unwrap_or_else(std::sync::PoisonError::into_inner);
            Ok(
                boundary::chain_input_at_boundary(particles.positions, surface, sheet, radius)?
                    .solve_reusing(radius, kernel, tau, &mut lists)?,
            )
        })
    }

    /// `f` of the boundary calibration's sheet for `source`: the surface and isolated
    /// particles (the raw-particle source), or the refined points (the chain, refused past 3
    /// steps).
    fn with_boundary_sheet<T>(
        &self,
        source: SurfelSource,
        particles: ParticleView<'_>,
        surface: &Surface,
        refined: Option<&Refined>,
        radius: f32,
        f: impl FnOnce(boundary::Sheet<'_>) -> Result<T, Error>,
    ) -> Result<T, Error> {
        if source == SurfelSource::Particles {
            let outer = boundary::OwnedSheet::of_particles(particles.positions, surface, radius);
            return f(outer.sheet());
        }
        let r = refined.expect("refined above");
        self.check_boundary_steps(r, radius)?;
        f(boundary::Sheet::refined(r))
    }

    /// The boundary calibration's refusal of the chain past 3 steps
    /// ([`Pipeline::points_at_boundary`]).
    fn check_boundary_steps(&self, r: &Refined, radius: f32) -> Result<(), Error> {
        let reach = self.params.refine.kernel_factor * r.final_radius;
        if reach < 0.5 * (0.5 * radius) * (1.0 - 1e-4) {
            return Err(Error::InvalidArgument {
                argument: "refine.steps",
                reason: format!(
                    "{} steps with grid.calibration = \"boundary\": the refined points' kernel reaches {reach} (kernel_factor x final radius), short of the half spacing {} the surface lies outside them; use at most 3 steps, a larger refine.kernel_factor, or calibration = \"paper\"",
                    self.params.refine.steps,
                    0.25 * radius
                ),
            });
        }
        Ok(())
    }

    /// The absolute iso-value of the density grid for the support radius `radius`:
    /// `iso_fraction` of one point's peak, as the surfel extraction takes it.
    fn iso_value(&self, radius: f32) -> f32 {
        self.params.surfels.iso_fraction * self.params.grid.kernel.peak(radius)
    }

    /// The surfels `source` draws for a frame this pipeline made from `particles` (its surface
    /// and refined points), as [`Pipeline::frame_through`] with that source would make them:
    /// the chain's, the raw particles' or the refined points', for pictures that set the
    /// sources side by side (the main job's `splats.png`). The hysteresis state is not touched.
    pub fn source_surfels<'a>(
        &mut self,
        particles: impl Into<ParticleView<'a>>,
        frame: &Frame,
        source: SurfelSource,
    ) -> Result<Vec<Surfel>, Error> {
        if frame.refined.is_none() && source != SurfelSource::Particles {
            return Err(Error::InvalidArgument {
                argument: "frame",
                reason: "the chain and refined sources need a frame made through refinement".into(),
            });
        }
        let SourceStage { render, iso, .. } = self.source_stage(
            source,
            particles.into(),
            &frame.surface,
            frame.refined.as_ref(),
            (frame.radius, None),
        )?;
        // a coarsened grid is said as frame_through says it
        if let Some(Some(iso)) = iso {
            self.warn(&mut Vec::new(), iso.warning);
        }
        Ok(render)
    }

    /// Stages 4 and 5 on surfels made elsewhere (a file of surfels, another tool's): the shaded
    /// splats ([`Through::Splats`]) or the finished frame ([`Through::Frame`]), with the views
    /// kept for the sequence like [`Pipeline::frame`]'s. Earlier `through` values return the
    /// surfels as they are.
    pub fn frame_of_surfels(
        &mut self,
        surfels: Vec<Surfel>,
        through: Through,
    ) -> Result<Frame, Error> {
        let total = Instant::now();
        let mut frame = Frame {
            radius: self.radius.unwrap_or(0.0),
            mean_neighbours: 0.0,
            surface: Surface::default(),
            surface_indices: Vec::new(),
            refined: None,
            grid: None,
            surfels: None,
            mesh: None,
            render_surfels: surfels,
            render_weights: Vec::new(),
            camera: None,
            splats: None,
            finished: None,
            timings: FrameTimings::default(),
            detail: DetailReport::default(),
            warnings: Vec::new(),
            surfels_on_gpu: false,
            weights_on_gpu: false,
            shape: None,
        };
        let skipped = frame
            .render_surfels
            .iter()
            .filter(|s| !s.is_drawable())
            .count();
        let warning = (skipped > 0).then(|| {
            format!(
                "{skipped} of {} surfels cannot be drawn (a radius that is zero, negative or not \
                 finite, or a zero normal) and are skipped",
                frame.render_surfels.len()
            )
        });
        self.warn(&mut frame.warnings, warning);
        if through >= Through::Splats {
            self.render(&mut frame, through)?;
        }
        frame.timings.total_ms = ms(total);
        Ok(frame)
    }

    /// Stage 1 of a frame, what carries over to the next: the support radius (estimated on the
    /// first frame), the neighbourhoods, surface detection with its hysteresis, the refined
    /// particles' order.
    fn detect_stage(
        &mut self,
        particles: ParticleView<'_>,
        timings: &mut FrameTimings,
        warnings: &mut Vec<String>,
    ) -> Result<Detected, Error> {
        let radius = match self.radius {
            Some(r) => r,
            None => {
                let r = neighbours::support_radius(particles.positions)?;
                self.radius = Some(r);
                r
            }
        };
        // stage 1: surface detection with hysteresis
        let t = Instant::now();
        let nb = Neighbourhoods::build(particles.positions, radius, Backend::CellGrid)?;
        timings.neighbours_ms = ms(t);
        if !particles.is_empty() {
            self.warn(warnings, neighbour_count_warning(radius, nb.mean_count()));
        }
        let t = Instant::now();
        let mut surface = self.detector.detect(particles, &nb)?;
        if self.params.surface.method == crate::surface::SurfaceMethod::Lnm {
            // the band in place of the centre-of-mass classes (its isolated particles and
            // offsets kept); the detector keeps its own hysteresis state
            let band = crate::lnm::narrow_band(
                particles.positions,
                radius,
                &crate::lnm::LnmParams::default(),
            )?;
            surface = crate::lnm::band_surface(&band, particles.positions, &surface);
        }
        timings.detect_ms = ms(t);
        let surface_indices = refined_indices(&surface, particles.positions);
        Ok(Detected {
            radius,
            mean_neighbours: nb.mean_count(),
            surface,
            surface_indices,
        })
    }

    /// The level of detail each region needs (`detail = "auto"` on a frame drawn through
    /// `through`, [`Through::Splats`] or later, or [`Through::Surfels`] drawn by the caller,
    /// [`Pipeline::set_drawn`]): from the camera the frame will be seen from
    /// ([`Pipeline::detail_camera`]) at the image size. `None` refines every region to
    /// `refine.steps`.
    fn view_levels(
        &self,
        positions: &[Vec3],
        radius: f32,
        through: Through,
    ) -> Result<Option<ViewLevels>, Error> {
        let seen = match (through, self.drawn) {
            (Through::Splats | Through::Frame, _) => through,
            (Through::Surfels, Some(drawn)) => drawn,
            _ => return Ok(None),
        };
        if self.params.detail != Detail::Auto {
            return Ok(None);
        }
        let water = self.water_box(positions, radius);
        let camera = self.detail_camera(water, seen);
        let [w, h] = self.params.scene.optics.image_size;
        let mut views = vec![splat::View::new(
            &camera,
            &Light::default(),
            &self.splat_params(),
            w,
            h,
        )?];
        if seen == Through::Frame {
            // the caustics sample the water from the light's screen: its texels set their own
            // footprint (the map's texels hold the receiver's light, not the water's detail)
            let mut scene = self.params.scene.clone();
            let mut all = water;
            if let Some(kept) = self.views.as_ref().and_then(|v| v.optics.as_ref()) {
                let o = &mut scene.optics;
                o.caustics_resolution = Some(o.caustics_resolution.unwrap_or(kept.screen));
                all = (kept.bounds[0], kept.bounds[1]);
            }
            if let Some([a, b]) = scene.optics.scene_bounds {
                all = (a, b);
            }
            views.push(optics::light_screen(&scene, water, all)?);
        }
        Ok(Some(ViewLevels::new(
            views,
            radius,
            self.params.refine.steps,
            self.params.detail_px,
        )))
    }

    /// Where the picture of a frame made `through` sees the water from, when the surfels facing
    /// away from it may be left out ([`surfels::SurfelExtractor::finish_seen`]; `None` keeps them
    /// all). That takes `detail = "auto"`; a renderer that culls a disk facing away from the eye
    /// ([`WaterRenderer::culls_back_faces`]: EWA's disks and sprites); views fitted to the
    /// particles (every calibration but `paper`, whose views are fitted to the surfels); and a
    /// picture drawn right after from the views the level of detail sees
    /// ([`Pipeline::view_levels`]: the camera, and for the finished frame the light), through
    /// the splats or the finished frame, or the surfels drawn by the caller as the shaded splats
    /// ([`Pipeline::set_drawn`]). Not for surfels drawn as the finished frame by the caller:
    /// [`GpuPipeline`] may draw them again from another camera.
    fn hidden_from(
        &self,
        positions: &[Vec3],
        radius: f32,
        through: Through,
    ) -> Result<Option<surfels::Viewpoints>, Error> {
        let drawn_here = through >= Through::Splats
            || (through == Through::Surfels && self.drawn == Some(Through::Splats));
        if !drawn_here
            || self.keep_hidden
            || self.water.drawn() != Drawn::Surfels
            || !self.water.culls_back_faces()
            || self.splat_params().mode == splat::SplatMode::Spheres
            || self.params.grid.calibration == Calibration::Paper
        {
            return Ok(None);
        }
        Ok(self
            .view_levels(positions, radius, through)?
            .map(|levels| levels.viewpoints()))
    }

    /// The level of each refined particle (`indices`, in that order) seen in `view`, with the
    /// hysteresis of [`ViewLevels::level_after`] against the particle's level in the last such
    /// frame (by id); remembered for the next. Also how many changed level.
    fn surface_levels(
        &mut self,
        view: &ViewLevels,
        particles: ParticleView<'_>,
        indices: &[u32],
    ) -> (Vec<u8>, usize) {
        use rayon::prelude::*;
        let before = &self.levels_before;
        let (levels, changed): (Vec<u8>, Vec<bool>) = indices
            .par_iter()
            .map(|&i| {
                let i = i as usize;
                let previous = before.get(&particles.id(i)).copied();
                let l = view.level_after(view.needed(particles.positions[i]), previous) as u8;
                (l, previous.is_some_and(|p| p != l))
            })
            .unzip();
        // the map's allocation kept from frame to frame
        self.levels_before.clear();
        self.levels_before.extend(
            indices
                .iter()
                .zip(&levels)
                .map(|(&i, &l)| (particles.id(i as usize), l)),
        );
        (levels, changed.iter().filter(|&&c| c).count())
    }

    /// The water's box before its surfels are known: the particles' box widened by half a
    /// spacing (where the surface lies), and [`Pipeline::fit_to`]'s box.
    fn water_box(&self, positions: &[Vec3], radius: f32) -> (Vec3, Vec3) {
        let own = crate::view::widened_bounds(positions.iter().copied(), 0.25 * radius);
        crate::view::union_boxes(own, self.fit).unwrap_or((Vec3::ZERO, Vec3::ONE))
    }

    /// The camera a picture `through` will be seen from, known before its surfels are
    /// ([`Pipeline::camera_or`]): the one the splats or the finished frame fit, to the water's
    /// box ([`Pipeline::water_box`]). The finished frame's camera fits the pool too, whose walls
    /// may rise over the water: seen from here the water is a little nearer, so that its detail
    /// errs on the fine side.
    fn detail_camera(&self, (lo, hi): (Vec3, Vec3), through: Through) -> Camera {
        self.camera_or(|| {
            if through == Through::Frame {
                let [w, h] = self.params.scene.optics.image_size;
                Camera::fitting(lo, hi, optics::CAMERA_DIRECTION, w as f32 / h.max(1) as f32)
            } else {
                Camera::framing(lo, hi)
            }
        })
    }

    /// The sequence's kept camera (with `keep_views`), else the scene's, else `fit()`.
    fn camera_or(&self, fit: impl FnOnce() -> Camera) -> Camera {
        match &self.views {
            Some(v) if self.params.keep_views => v.camera,
            _ => self.params.scene.camera.unwrap_or_else(fit),
        }
    }

    fn refine_params(&self, radius: f32) -> RefineParams {
        let mut p = self.params.refine;
        if p.initial_radius == 0.0 {
            p.initial_radius = radius;
        }
        p
    }

    /// The points and radii the renderer draws ([`sphere_points`] of the surfels), when it asks
    /// for them ([`WaterRenderer::needs_points`]).
    #[must_use]
    pub fn water_points(&self, surfels: &[Surfel]) -> Option<(Vec<Vec3>, Vec<f32>)> {
        self.water.needs_points().then(|| sphere_points(surfels))
    }

    /// The frame's water, built once for every view of the frame: `points` from
    /// [`Pipeline::water_points`].
    pub fn water_of<'a>(
        &self,
        surfels: &'a [Surfel],
        points: Option<&'a (Vec<Vec3>, Vec<f32>)>,
        weights: &'a [f32],
    ) -> Result<Box<dyn WaterSurface + 'a>, Error> {
        self.water_with(surfels, points, (weights, None))
    }

    /// [`Pipeline::water_of`] with the weights on the CPU or, where `gpu_weights` is given, in
    /// that buffer on the GPU (`f32` a sphere, in their order: [`Frame::weights_on_gpu`]).
    pub(crate) fn water_with<'a>(
        &self,
        surfels: &'a [Surfel],
        points: Option<&'a (Vec<Vec3>, Vec<f32>)>,
        (weights, gpu_weights): (&'a [f32], Option<&'a wgpu::Buffer>),
    ) -> Result<Box<dyn WaterSurface + 'a>, Error> {
        let (positions, radii) = points.map_or((&[][..], &[][..]), |(p, r)| (&p[..], &r[..]));
        self.water.water(WaterInput {
            surfels,
            points: (positions, radii),
            weights,
            gpu_weights,
            reference_radius: self.reference_radius(radii),
        })
    }

    /// Stages 4 and 5 on the frame's surfels, with the views kept for the sequence.
    /// The views are fitted to the frame's shape ([`Frame::shape`]), or to its surfels'.
    fn render(&mut self, frame: &mut Frame, through: Through) -> Result<(), Error> {
        let surfels = &frame.render_surfels;
        let [w, h] = self.params.scene.optics.image_size;
        let points = self.water_points(surfels);
        let water = self.water_of(surfels, points.as_ref(), &frame.render_weights)?;
        let water = water.as_ref();
        let shape = self.shape_of(frame);
        if through == Through::Frame {
            let scene = self.fitted_scene(&shape, frame.radius)?;
            let t = Instant::now();
            let stage = Stage::fitted(&scene, &shape, None)?;
            let caustics = optics::caustics_reusing(&stage, water, &mut self.receiver_views)?;
            frame.timings.caustics_ms = ms(t);
            let t = Instant::now();
            let f =
                optics::frame_reusing(&stage, water, &caustics, (w, h), &mut self.receiver_views)?;
            frame.timings.image_ms = ms(t);
            frame.camera = Some(stage.camera);
            frame.finished = Some(Finished {
                stage,
                caustics,
                image: f.image,
                linear: f.linear,
            });
        }
        let camera = match frame.camera {
            Some(c) => c,
            None => self.splat_camera(shape.drawn),
        };
        frame.camera = Some(camera);
        if through != Through::Splats {
            return Ok(());
        }
        let t = Instant::now();
        frame.splats = Some(self.draw_with(water, &camera, (w, h))?);
        frame.timings.splats_ms = ms(t);
        Ok(())
    }

    /// The shaded picture of `surfels` (a frame's [`Frame::render_surfels`], with its
    /// [`Frame::render_weights`]) seen by `camera`, `size` pixels, drawn on the CPU by the
    /// pipeline's renderer with its parameters (the default light): EWA or particle splats, rays
    /// cast to the points' iso-surface, or the screen-space surface. [`Pipeline::draw_gpu`] is
    /// its twin on a GPU; the shaded splats of [`Through::Splats`] are this picture at the image
    /// size.
    pub fn draw(
        &self,
        (surfels, weights): (&[Surfel], &[f32]),
        camera: &Camera,
        size: (u32, u32),
    ) -> Result<Render, Error> {
        let points = self.water_points(surfels);
        let water = self.water_of(surfels, points.as_ref(), weights)?;
        self.draw_with(water.as_ref(), camera, size)
    }

    /// The view of [`Pipeline::draw`]: `camera`, the default light, the renderer's splat
    /// parameters, `size` pixels.
    pub fn draw_view(&self, camera: &Camera, (w, h): (u32, u32)) -> Result<View, Error> {
        Ok(View::new(
            camera,
            &Light::default(),
            &self.splat_params(),
            w,
            h,
        )?)
    }

    /// [`Pipeline::draw`] of the frame's water already built.
    fn draw_with(
        &self,
        water: &dyn WaterSurface,
        camera: &Camera,
        size: (u32, u32),
    ) -> Result<Render, Error> {
        water.render(&self.draw_view(camera, size)?)
    }

    /// The reference radius of the peer renderers: the support radius, or the largest of
    /// `radii` before one is known (never zero).
    fn reference_radius(&self, radii: &[f32]) -> f32 {
        self.radius
            .unwrap_or_else(|| radii.iter().copied().fold(0.0, f32::max))
            .max(f32::MIN_POSITIVE)
    }

    /// The ray caster of [`Renderer::RayCast`] over points and their radii (from
    /// [`sphere_points`]): the grid's kernel, `[raycast]`, the support radius as the reference
    /// radius (the largest radius before one is known).
    pub fn caster<'a>(
        &self,
        positions: &'a [Vec3],
        radii: &'a [f32],
        weights: &'a [f32],
    ) -> Result<crate::raycast::Caster<'a>, Error> {
        let method = crate::raycast::Method {
            kernel: self.params.grid.kernel,
            params: self.params.raycast,
        };
        Ok(method.caster((positions, radii), weights, self.reference_radius(radii))?)
    }

    /// The screen-space renderer of [`Renderer::Ssfr`] over points and their radii (from
    /// [`sphere_points`]): `[ssfr]`, the support radius as the reference radius (the largest
    /// radius before one is known). Computes the narrow band once for every view.
    pub fn screen_space<'a>(
        &self,
        positions: &'a [Vec3],
        radii: &'a [f32],
    ) -> Result<crate::ssfr::ScreenSpace<'a>, Error> {
        let reference = self.reference_radius(radii);
        Ok(crate::ssfr::ScreenSpace::new(
            positions,
            radii,
            reference,
            &self.params.ssfr,
        )?)
    }

    /// The parameters of the shaded splats: `[splat]`, with the mode of the renderer
    /// ([`splat::SplatMode::Spheres`] for [`Renderer::ParticleSplat`]).
    #[must_use]
    pub fn splat_params(&self) -> SplatParams {
        self.water.splat_params(self.params.splat)
    }

    /// The camera of the shaded splats: the sequence's kept camera, else the scene's, else one
    /// framing the water's box `drawn` (then kept, with `keep_views`).
    pub(crate) fn splat_camera(&mut self, drawn: Option<(Vec3, Vec3)>) -> Camera {
        let camera = self.camera_or(|| {
            let (lo, hi) =
                crate::view::union_boxes(drawn, self.fit).unwrap_or((Vec3::ZERO, Vec3::ONE));
            Camera::framing(lo, hi)
        });
        if self.views.is_none() && self.params.keep_views {
            self.views = Some(Views {
                camera,
                optics: None,
            });
        }
        camera
    }

    /// Where the water of `frame` is, as the views are fitted to it: [`Frame::shape`], else
    /// that of its surfels ([`Pipeline::water_shape`]).
    pub(crate) fn shape_of(&self, frame: &Frame) -> optics::WaterShape {
        frame
            .shape
            .unwrap_or_else(|| self.water_shape(&frame.render_surfels, frame.radius))
    }

    /// Where the water of `surfels` is ([`optics::WaterShape::of_surfels`]); the surface of
    /// the ray caster's calibrated spheres half a spacing (a quarter of the support radius
    /// `radius`) outside their centres.
    pub(crate) fn water_shape(&self, surfels: &[Surfel], radius: f32) -> optics::WaterShape {
        let mut shape = optics::WaterShape::of_surfels(surfels);
        if self.water.drawn() == (Drawn::Spheres { calibrated: true })
            && self.params.grid.calibration == Calibration::Boundary
            && radius.is_finite()
            && radius > 0.0
        {
            shape.surface = crate::view::widened_bounds(
                surfels
                    .iter()
                    .filter(|s| s.is_drawable())
                    .map(|s| Vec3::from(s.position)),
                0.25 * radius,
            );
        }
        shape
    }

    /// Where the water of a frame is before its surfels are known (on a GPU, they never come
    /// back), from its particles at `positions` (their `surface`, support radius `radius`) and
    /// the density grid `grid` the surfels lie on: the particles' box widened by half a spacing
    /// (where the boundary calibration puts the surface) and by the disks' radius (the grid's
    /// cell), and the level of the upward-facing surface particles half a spacing out along
    /// their normals. `None` with the paper's calibration, whose surface lies farther out by an
    /// amount that depends on the level of detail (the views are then fitted to the surfels).
    /// Both pipelines fit their views to it: [`GpuPipeline`] cannot read its surfels, and the
    /// CPU's pictures are then the GPU's.
    pub fn grid_water_shape(
        &self,
        positions: &[Vec3],
        surface: &Surface,
        radius: f32,
        grid: &GridSpec,
    ) -> Option<optics::WaterShape> {
        // `boundary` and `volume` put the surface half a spacing outside the outermost
        // particles (the latter measured 0.033 spacings rms from a particle sphere's, at
        // splashsurf's threshold 0.6: tests/pipeline.rs)
        if self.params.grid.calibration == Calibration::Paper {
            return None;
        }
        let out = 0.25 * radius;
        let own = crate::view::widened_bounds(positions.iter().copied(), out + grid.spacing);
        Some(optics::WaterShape {
            drawn: own,
            surface: own,
            level: surface_level(positions, surface, out),
        })
    }

    /// Where the water of a frame drawn as spheres is (the peer renderers: particle splats,
    /// ray casting, screen space), from its `spheres` ([`Pipeline::water_shape`]) and, since
    /// spheres carry no normals, the level of the water from its particles at `positions` as
    /// [`Pipeline::grid_water_shape`] finds it (the upward-facing surface particles half a
    /// spacing out, `radius` the support radius). Without a level an automatic pool's walls
    /// rose half way up the box of the water and its splash: on the dam break's frame, whose
    /// spray climbs far over its pool, the walls hid the pool's water from the camera in every
    /// peer renderer's finished frame.
    ///
    /// The ray caster's spheres with the boundary calibration are fitted to their particles
    /// alone, as the surfels on a grid are ([`Pipeline::grid_water_shape`]): the calibrated
    /// surface lies half a spacing outside the outermost particles (the surface's box, which
    /// the pool's walls meet), a lone drop's ball 0.62 spacings around its particle
    /// ([`boundary::LONE_RADIUS`]: the drawn box). [`GpuPipeline`] draws every particle and
    /// sheet point as a sphere and leaves out on the GPU those the calibration's factors drop
    /// (their box is not known on the CPU), and both pipelines' views are then alike.
    fn sphere_water_shape(
        &self,
        positions: &[Vec3],
        surface: &Surface,
        radius: f32,
        spheres: &[Surfel],
    ) -> optics::WaterShape {
        if self.water.drawn() == (Drawn::Spheres { calibrated: true })
            && self.params.grid.calibration == Calibration::Boundary
            && radius.is_finite()
            && radius > 0.0
        {
            let out = 0.25 * radius;
            // the particles' box, once, widened for each
            let centres = crate::view::widened_bounds(positions.iter().copied(), 0.0);
            let widened = |by: f32| centres.map(|(lo, hi)| (lo - by, hi + by));
            return optics::WaterShape {
                drawn: widened(boundary::LONE_RADIUS * 2.0 * out),
                surface: widened(out),
                level: surface_level(positions, surface, out),
            };
        }
        let mut shape = self.water_shape(spheres, radius);
        if shape.level.is_none() && radius.is_finite() && radius > 0.0 {
            shape.level = surface_level(positions, surface, 0.25 * radius);
        }
        shape
    }

    /// The optics scene of this frame (support radius `radius`, the water's `shape`): the first
    /// rendered frame fits the camera, the pool and the scene box, later frames of the sequence
    /// keep them.
    pub(crate) fn fitted_scene(
        &mut self,
        shape: &optics::WaterShape,
        radius: f32,
    ) -> Result<OpticsScene, Error> {
        let mut scene = self.params.scene.clone();
        scene.optics.splat = self.water.splat_params(scene.optics.splat);
        if !self.params.keep_views {
            if let Some(pool) = self.pool_at_the_water(&scene, shape, radius) {
                scene.receiver = pool;
            }
            return Ok(scene);
        }
        let kept = match self
            .views
            .as_ref()
            .and_then(|v| v.optics.clone().map(|o| (v.camera, o)))
        {
            Some(k) => k,
            None => {
                // a provisional stage fits the pool and the camera around this frame's water
                let first = Stage::fitted(&scene, shape, self.fit)?;
                let (rmin, rmax) = first.receiver.bounds();
                let receiver = match self.pool_at_the_water(&scene, shape, radius) {
                    Some(pool) => pool,
                    // without a support radius (surfels given as they are): the provisional
                    // stage's automatic pool, kept
                    None if scene.receiver.kind == ReceiverKind::Auto => optics::Receiver {
                        kind: ReceiverKind::OpenBox,
                        min: rmin,
                        max: rmax,
                        ..scene.receiver.clone()
                    },
                    None => scene.receiver.clone(),
                };
                let water = crate::view::union_boxes(shape.drawn, self.fit);
                let (lo, hi) =
                    crate::view::union_boxes(water, Some((rmin, rmax))).unwrap_or((rmin, rmax));
                // room for the water to rise and spread in later frames
                let pad = 0.1 * (hi - lo).max_element();
                let bounds = [lo - Vec3::splat(pad), hi + Vec3::splat(pad)];
                let camera = match &self.views {
                    Some(v) => v.camera,
                    None => first.camera,
                };
                // the resolutions of this first frame's screen and map are kept too, so that
                // later frames' targets have the same sizes (the GPU reuses them); the screen's
                // window still follows the water
                let kept = KeptOptics {
                    receiver,
                    bounds,
                    screen: [first.views.screen.width, first.views.screen.height],
                    map: [first.views.map.width, first.views.map.height],
                };
                self.views = Some(Views {
                    camera,
                    optics: Some(kept.clone()),
                });
                (camera, kept)
            }
        };
        let (camera, kept) = kept;
        scene.camera = Some(camera);
        scene.receiver = kept.receiver;
        let o = &mut scene.optics;
        o.scene_bounds = Some(o.scene_bounds.unwrap_or(kept.bounds));
        o.caustics_resolution = Some(o.caustics_resolution.unwrap_or(kept.screen));
        o.map_resolution = Some(o.map_resolution.unwrap_or(kept.map));
        Ok(scene)
    }

    /// The automatic pool (for a scene whose receiver is `auto`) as an open box whose walls and
    /// floor meet the water: a quarter of a spacing (an eighth of the support radius `radius`)
    /// inside the water's bounds (the surface's box of its `shape`, [`Frame::shape`] or its
    /// surfels', widened to [`Pipeline::fit_to`]'s box), the walls up to the automatic pool's
    /// top ([`optics::WaterShape::wall_top`]: 1.2x the water's level) and at least 7 % of the
    /// water's size over the floor. `None` for another receiver,
    /// without water, or without a support radius.
    /// A simulation's walls lie at the fluid's boundary, half a spacing outside the particles
    /// next to them, where the water's surface lies too; those particles are not all equally near
    /// the wall, and the rims of the ones a little behind the outermost (a one-layer sheet's rim
    /// is a half-cylinder of half a spacing) left a dark groove along walls placed at the water's
    /// bounds or outside them. The container clips the water to the walls (issue 41), so walls a
    /// little inside it meet it flush. Measured on the double dam break's finished frame
    /// (tests/pictures.rs, the speck measure, the surface at the fluid's boundary): walls 2 % of
    /// the water's size outside it (the former margin), 0.99 % of the frame dark specks along
    /// two walls; at the water's bounds, 0.67 %; a quarter spacing inside, 0.38 % and no groove
    /// (with the paper's sums and the former margin: 0.55 %); fitted to the particles' shape
    /// instead of the surfels' (issue 37), 0.285 %.
    fn pool_at_the_water(
        &self,
        scene: &OpticsScene,
        shape: &optics::WaterShape,
        radius: f32,
    ) -> Option<optics::Receiver> {
        if scene.receiver.kind != ReceiverKind::Auto || !(radius.is_finite() && radius > 0.0) {
            return None;
        }
        // the ray caster's spheres reach a support radius past their centres, its calibrated
        // surface half a spacing: the box of that surface ([`Pipeline::water_shape`])
        let (lo, hi) = crate::view::union_boxes(shape.surface, self.fit)?;
        let inset = (0.25 * 0.5 * radius).min(0.25 * (hi - lo).min_element());
        let min = lo + Vec3::splat(inset);
        // walls as high over the floor as the former pool's over its own (5 % of the water's
        // size over its bottom, the floor 2 % below it), on a thin sheet's pool
        let top = shape
            .wall_top(lo.y, hi.y)
            .max(min.y + 0.07 * (hi - lo).max_element());
        Some(optics::Receiver {
            kind: ReceiverKind::OpenBox,
            min,
            max: Vec3::new(hi.x - inset, top, hi.z - inset),
            ..scene.receiver.clone()
        })
    }
}

/// The parameters of the main job on the built-in `column` scene: the simulation's support
/// radius, the tank as the pool ([`crate::scenes::column_pool`]) and its fixed camera, every other
/// value at its default.
#[must_use]
pub fn column_params() -> PipelineParams {
    let column = crate::scenes::ColumnParams::default();
    PipelineParams {
        // the simulation's own support radius (ColumnSim::support_radius)
        support_radius: Some(2.0 * column.spacing),
        scene: crate::scenes::column_pool(column.tank),
        ..PipelineParams::default()
    }
}

/// Steps the built-in `column` simulation to `frame`, running the pipeline through
/// [`Through::Surface`] on every frame before it (so the hysteresis state is that of a real run)
/// and through `through` on the last; `progress` is called once per simulated frame.
pub fn column_frame(
    pipeline: &mut Pipeline,
    sim: &mut ColumnSim,
    frame: usize,
    through: Through,
    mut progress: impl FnMut(usize),
) -> Result<Frame, Error> {
    loop {
        let last = sim.frame() >= frame;
        let f = pipeline.frame_through(
            sim.particles(),
            if last { through } else { Through::Surface },
        )?;
        progress(sim.frame());
        if last {
            return Ok(f);
        }
        sim.step_frame();
    }
}

fn ms(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}

/// Indices of the particles the upsampling refines: surface and isolated ones, in an order of
/// their own positions alone (Morton order of the coordinates' order-preserving bit patterns,
/// their top 21 bits, ties by the exact coordinates, then by index), so that the same particles
/// in another order are refined alike: the upsampling's collision handling (Solenthaler et al.
/// §3.3) accepts candidates first come, first served, and the input order would otherwise decide
/// which of two colliding children stays. No particle's key depends on the others (a key
/// quantised over their bounding box made a drop far outside the view reorder, and so refine
/// anew, the whole surface: the dam break's shaded splats 42.9 dB from themselves). Spatial order
/// also keeps neighbours near in memory: the keys follow each axis monotonically, in steps of
/// 2^-12 of a coordinate's magnitude.
#[must_use]
pub fn refined_indices(surface: &Surface, positions: &[Vec3]) -> Vec<u32> {
    let mut indices: Vec<u32> = (0..surface.classes.len() as u32)
        .filter(|&i| surface.classes[i as usize] != ParticleClass::Interior)
        .collect();
    let key = |i: u32| {
        let p = positions[i as usize];
        morton3_21(
            ordered_bits(p.x) >> 11,
            ordered_bits(p.y) >> 11,
            ordered_bits(p.z) >> 11,
        )
    };
    let mut keyed: Vec<(u64, u32)> = indices.iter().map(|&i| (key(i), i)).collect();
    rayon::slice::ParallelSliceMut::par_sort_unstable_by(
        keyed.as_mut_slice(),
        |&(ka, a), &(kb, b)| {
            let (pa, pb) = (positions[a as usize], positions[b as usize]);
            ka.cmp(&kb)
                .then(pa.x.total_cmp(&pb.x))
                .then(pa.y.total_cmp(&pb.y))
                .then(pa.z.total_cmp(&pb.z))
                .then(a.cmp(&b))
        },
    );
    indices.clear();
    indices.extend(keyed.iter().map(|&(_, i)| i));
    indices
}

/// A float's bits as an unsigned integer in the floats' order (negative ones flipped whole,
/// positive ones with the sign bit set), as `f32::total_cmp` orders them.
fn ordered_bits(v: f32) -> u32 {
    let b = v.to_bits();
    if b >> 31 == 1 { !b } else { b | 0x8000_0000 }
}

/// The Morton code of three 21-bit coordinates (their bits interleaved, x lowest).
fn morton3_21(x: u32, y: u32, z: u32) -> u64 {
    let spread = |v: u32| {
        let mut v = u64::from(v) & 0x1f_ffff;
        v = (v | (v << 32)) & 0x001f_0000_0000_ffff;
        v = (v | (v << 16)) & 0x001f_0000_ff00_00ff;
        v = (v | (v << 8)) & 0x100f_00f0_0f00_f00f;
        v = (v | (v << 4)) & 0x10c3_0c30_c30c_30c3;
        (v | (v << 2)) & 0x1249_2492_4924_9249
    };
    spread(x) | (spread(y) << 1) | (spread(z) << 2)
}

/// Positions and normals of the given particles (isolated ones keep a zero normal, and the
/// refinement keeps them as they are).
#[must_use]
pub fn gather<'a>(
    particles: impl Into<ParticleView<'a>>,
    surface: &Surface,
    indices: &[u32],
) -> (Vec<Vec3>, Vec<Vec3>) {
    let particles = particles.into();
    (
        indices
            .iter()
            .map(|&i| particles.positions[i as usize])
            .collect(),
        indices
            .iter()
            .map(|&i| surface.normals[i as usize])
            .collect(),
    )
}

/// The design chain's points and their kernel radii: the interior particles with the support
/// radius `h`, then the refined surface points with the radii their refinement gives them
/// ([`Refined::kernel_radii`]).
#[must_use]
pub fn chain_points<'a>(
    particles: impl Into<ParticleView<'a>>,
    surface: &Surface,
    refined: &Refined,
    h: f32,
) -> (Vec<Vec3>, Vec<f32>) {
    let particles = particles.into();
    let interior = surface.indices_of(ParticleClass::Interior);
    let mut positions = Vec::with_capacity(interior.len() + refined.len());
    let mut radii = Vec::with_capacity(interior.len() + refined.len());
    for &i in &interior {
        positions.push(particles.positions[i]);
        radii.push(h);
    }
    positions.extend_from_slice(&refined.positions);
    radii.extend_from_slice(&refined.kernel_radii);
    (positions, radii)
}

/// The centres and radii of spheres (or surfels): the points a ray caster casts through.
#[must_use]
pub fn sphere_points(spheres: &[Surfel]) -> (Vec<Vec3>, Vec<f32>) {
    spheres
        .iter()
        .map(|s| (Vec3::from(s.position), s.radius))
        .unzip()
}

/// The level of the water's upward-facing surface: the median height of the surface particles
/// at `positions` (classed in `surface`) whose normal points up, `out` along it (`None`: no
/// such particle).
fn surface_level(positions: &[Vec3], surface: &Surface, out: f32) -> Option<f32> {
    let up = surface
        .classes
        .iter()
        .zip(&surface.normals)
        .zip(positions)
        .filter(|((c, n), _)| **c == ParticleClass::Surface && n.y > 0.5)
        .map(|((_, n), p)| p.y + out * n.y);
    optics::median(up.collect())
}

/// A density grid's points: positions, kernel radii (empty: every one the support radius) and
/// weights (empty: every one 1).
type SourcePoints<'a> = (Cow<'a, [Vec3]>, Vec<f32>, Vec<f32>);

/// What [`Pipeline::source_stage`] makes of a frame.
struct SourceStage {
    /// The surfels to draw (spheres of the source's points for the peer renderers).
    render: Vec<Surfel>,
    /// The grid stage's result for the density sources with the EWA renderer (`Some(None)`: no
    /// point to make a grid of).
    iso: Option<Option<IsoSurfels>>,
    /// Milliseconds spent weighting the points for the boundary calibration.
    calibration_ms: f64,
    /// The weights of the ray caster's spheres (empty: every one 1).
    weights: Vec<f32>,
}

/// A frame's density grid input ([`Pipeline::frame_to_grid`]): the source's points with their
/// kernel radii and weights, and the grid around them.
#[derive(Clone, Debug)]
pub struct GridInput<'a> {
    /// The points' positions (the particles themselves for the raw-particle source).
    pub positions: Cow<'a, [Vec3]>,
    /// Each point's kernel radius (empty: every one [`GridInput::radius`]).
    pub radii: Vec<f32>,
    /// Each point's weight (empty: every one 1).
    pub weights: Vec<f32>,
    /// The support radius.
    pub radius: f32,
    /// The grid ([`grid_for`]).
    pub spec: GridSpec,
    /// The sheet's weights left to solve (`weights` then the points' own): the boundary
    /// calibration's Jacobi steps run where the grid is filled (on the GPU,
    /// [`boundary::gpu::WeightPasses`]).
    pub solve: Option<WeightSolve>,
}

/// The boundary calibration of a [`GridInput`] left to find where the grid is filled, its
/// factors and its weights ([`boundary::BoundaryLayout`]): the sheet follows the `particles`
/// leading points (each with its surface normal and class in `classes`), with `normals`, the
/// particles' `spacing` and the iso-value `tau`.
#[derive(Clone, Debug, PartialEq)]
pub struct WeightSolve {
    pub particles: usize,
    pub classes: Vec<[f32; 4]>,
    pub normals: Vec<Vec3>,
    pub spacing: f32,
    pub tau: f32,
}

impl GridInput<'_> {
    /// The points as the density stages take them.
    #[must_use]
    pub fn points(&self) -> Points<'_> {
        points_of(&self.positions, &self.radii, &self.weights, self.radius)
    }
}

/// Points at `positions` with kernel radii `radii` (empty: every one `radius`) and `weights`
/// (empty: every one 1).
fn points_of<'p>(
    positions: &'p [Vec3],
    radii: &'p [f32],
    weights: &'p [f32],
    radius: f32,
) -> Points<'p> {
    let points = if radii.is_empty() {
        Points::uniform(positions, radius)
    } else {
        Points::with_radii(positions, radii, radius)
    };
    if weights.is_empty() {
        points
    } else {
        points.with_weights(weights)
    }
}

/// What [`iso_surfels`] returns.
#[derive(Debug)]
pub struct IsoSurfels {
    pub grid: Grid,
    pub surfels: Surfels,
    /// Crossings left out as facing away from every viewpoint ([`iso_surfels_in`]'s `seen`).
    pub hidden: usize,
    pub density_ms: f64,
    pub surfels_ms: f64,
    /// Set when the grid was coarsened to fit the memory budget.
    pub warning: Option<String>,
}

/// The grid for a set of points: padded by their largest radius, spacing from their smallest
/// (or the fixed resolution), coarsened to fit the memory budget (with a message saying so).
pub fn grid_for(
    points: &Points<'_>,
    params: &GridParams,
) -> Result<(GridSpec, Option<String>), Error> {
    let resolution = params.resolution.unwrap_or(Resolution::CellSize(
        points.min_radius() / params.cells_per_radius,
    ));
    let pad = points.max_radius();
    let spec = GridSpec::around(points.positions, pad, resolution)?;
    if spec.bytes() <= params.memory_budget as u128 {
        return Ok((spec, None));
    }
    // coarsen in one step (the cell count goes with the spacing's cube), then make sure
    let mut spacing =
        spec.spacing * (spec.bytes() as f64 / params.memory_budget as f64).cbrt() as f32;
    let mut coarse = GridSpec::around(points.positions, pad, Resolution::CellSize(spacing))?;
    while coarse.bytes() > params.memory_budget as u128 {
        spacing *= 1.05;
        coarse = GridSpec::around(points.positions, pad, Resolution::CellSize(spacing))?;
    }
    let mib = |b: u128| b as f64 / (1u64 << 20) as f64;
    let message = format!(
        "the density grid at spacing {:.5} ({} x {} x {}, {:.0} MiB) exceeds the memory budget of {:.0} MiB; \
         coarsened to spacing {:.5} ({} x {} x {}): the surface loses detail finer than that (raise grid.memory_budget, \
         or lower grid.cells_per_radius)",
        spec.spacing,
        spec.dims[0],
        spec.dims[1],
        spec.dims[2],
        mib(spec.bytes()),
        mib(params.memory_budget as u128),
        coarse.spacing,
        coarse.dims[0],
        coarse.dims[1],
        coarse.dims[2],
    );
    Ok((coarse, Some(message)))
}

/// Stage 3 on the CPU: the density grid of the points and the surfels on its iso-surface;
/// `None` when there is no point.
pub fn iso_surfels(
    points: Points<'_>,
    grid: &GridParams,
    params: &SurfelParams,
) -> Result<Option<IsoSurfels>, Error> {
    iso_surfels_in(points, (grid, params), Vec::new(), None)
}

/// [`iso_surfels`] with the grid's values in a buffer earlier frames allocated, without the
/// surfels `seen` does not see ([`surfels::SurfelExtractor::finish_seen`]).
pub fn iso_surfels_in(
    points: Points<'_>,
    (grid, params): (&GridParams, &SurfelParams),
    buffer: Vec<f32>,
    seen: Option<surfels::Viewpoints>,
) -> Result<Option<IsoSurfels>, Error> {
    if points.is_empty() {
        return Ok(None);
    }
    // the radius first: a NaN radius would otherwise surface as a NaN grid box
    points.check()?;
    let (spec, warning) = grid_for(&points, grid)?;
    let t = Instant::now();
    let values = if grid.narrow_band {
        let band = sparse_band(&points)?;
        let iso = params.iso_fraction * grid.kernel.peak(points.h);
        Grid::Sparse(density::points_grid_sparse(
            points,
            &spec,
            grid.kernel,
            grid.memory_budget,
            &band,
            iso,
            sparse_inside(grid.kernel, params, points.h),
        )?)
    } else {
        Grid::Dense(density::points_grid_in(
            points,
            &spec,
            grid.kernel,
            grid.memory_budget,
            buffer,
        )?)
    };
    let density_ms = ms(t);
    let t = Instant::now();
    let (surfels, hidden) = match &values {
        Grid::Dense(g) => {
            surfels::extract_points_seen(g, points, grid.kernel, params, seen.as_ref())?
        }
        Grid::Sparse(g) => {
            surfels::extract_sparse_seen(g, points, grid.kernel, params, seen.as_ref())?
        }
    };
    Ok(Some(IsoSurfels {
        grid: values,
        surfels,
        hidden,
        density_ms,
        surfels_ms: ms(t),
        warning,
    }))
}
/// The LNM narrow band a sparse grid of `points` takes its inside blocks from
/// ([`GridParams::narrow_band`]): voxels of the largest radius.
pub(crate) fn sparse_band(points: &Points<'_>) -> Result<crate::lnm::NarrowBand, Error> {
    Ok(crate::lnm::narrow_band(
        points.positions,
        points.max_radius(),
        &crate::lnm::LnmParams::default(),
    )?)
}

/// The value a sparse grid's inside blocks read as: well above the iso-value (twice the larger
/// of the iso-value and one point's peak, of the reference radius `h`).
pub(crate) fn sparse_inside(kernel: Kernel, params: &SurfelParams, h: f32) -> f32 {
    2.0 * params.iso_fraction.max(1.0) * kernel.peak(h)
}

/// Mean neighbour counts outside which the support radius is probably wrong: SPH kernels are
/// made for about 30-60 neighbours (h = 2 spacings gives 33); under 10 the surface detection
/// sees every particle as a surface one and the grid breaks up into drops, over 200 the radius
/// blurs the surface away and every stage slows down with the square of the count.
pub const NEIGHBOUR_RANGE: (f32, f32) = (10.0, 200.0);

/// A warning for [`Frame::warnings`] when `mean` neighbours at `radius` lie outside
/// [`NEIGHBOUR_RANGE`].
#[must_use]
pub fn neighbour_count_warning(radius: f32, mean: f32) -> Option<String> {
    let (lo, hi) = NEIGHBOUR_RANGE;
    if mean < lo {
        Some(format!(
            "support radius {radius} gives {mean:.1} neighbours per particle (usual: 30-60): \
             too small for this file, the surface breaks up into drops; give a larger support \
             radius (--radius, support_radius: about twice the particle spacing)"
        ))
    } else if mean > hi {
        Some(format!(
            "support radius {radius} gives {mean:.0} neighbours per particle (usual: 30-60): \
             too large for this file, the surface is blurred and every stage is slow; give a \
             smaller support radius (--radius, support_radius: about twice the particle spacing)"
        ))
    } else {
        None
    }
}
