//! # fluid-surfels
//!
//! Turns the particles of a low-resolution fluid simulation (SPH, PBF, MPS, FLIP) into a
//! rendered water surface. The chain is one type, [`pipeline::Pipeline`] on the CPU or
//! [`pipeline::GpuPipeline`] on the caller's wgpu device (drawing into the caller's texture);
//! [`pipeline`] reads as the design. Its stages, one module each:
//!
//! 1. [`surface`]: surface particle detection with hysteresis and normals (Solenthaler et al.
//!    2007, §3.1), on [`neighbours`] (fixed-radius neighbour search).
//! 2. [`refine`]: upsampling of the surface points by spherical interpolation with collision
//!    avoidance and incremental neighbourhoods (Solenthaler et al. 2007, §3.2-3.4).
//! 3. [`density`]: the density grid of the refined surface points and the interior particles,
//!    each with its own kernel radius (Iwasaki et al. §4), dense or sparse, on the CPU and on
//!    the GPU; [`surfels`] on its iso-surface, or a triangle [`mesh`] of it (marching cubes,
//!    PLY and OBJ).
//! 4. [`splat`]: EWA surface splatting (Botsch et al. 2005), with particle splatting (Adams et
//!    al. 2006) as a mode; the peer renderers [`raycast`] (ray casting to the iso-surface, Xiao
//!    et al.) and [`ssfr`] (narrow-band screen-space rendering, Oliveira and Paiva, on the
//!    narrow band of [`lnm`]).
//! 5. [`optics`]: caustics through illumination volumes, refraction and reflection (Iwasaki et
//!    al. §5).
//!
//! Supporting modules: [`particles`] (the [`ParticleSet`] every stage reads), [`io`] (readers and
//! writers for PLY, legacy VTK, VTU, BGEO, XYZ, CSV and JSON), [`sequence`] (numbered frame
//! sequences), [`scenes`] (deterministic test scenes and a small simulator), [`view`] (cameras,
//! lights, the view parameters `SplatParams`, projections and the `Render` buffers), [`gpu`] (the shared wgpu context and read-back), [`kernels`] (SPH
//! kernels), [`linalg`] (3x3 symmetric eigen-decomposition), [`memory`] (the memory
//! left, the default budget and the peak resident set), [`preview`] (PNG pictures of
//! particle sets) and [`quality`] (holes, specks and differences of rendered frames, distances
//! to meshes). The command line is the crate `fluid-surfels-cli` (`cli/`, binary
//! `fluid-surfels`); the Python bindings are `python/`.
//!
//! ```
//! use fluid_surfels::{scenes, neighbours::{Backend, Neighbourhoods}, surface::{SurfaceDetector, SurfaceParams}};
//!
//! let scene = scenes::block(&scenes::BlockParams { counts: [10, 10, 10], ..Default::default() })?;
//! let nb = Neighbourhoods::build(&scene.particles.positions, scene.support_radius, Backend::CellGrid)?;
//! let mut detector = SurfaceDetector::new(SurfaceParams::default())?;
//! let surface = detector.detect(&scene.particles, &nb)?;
//! // 10^3 block: the 8^3 core is interior, the 488 outer particles are surface
//! assert_eq!(surface.counts().surface, 1000 - 512);
//! # Ok::<(), fluid_surfels::Error>(())
//! ```

pub mod density;
pub mod gpu;
pub mod io;
pub mod kernels;
pub mod linalg;
pub mod lnm;
pub mod memory;
pub mod mesh;
pub mod neighbours;
pub mod optics;
pub mod particles;
pub mod pipeline;
pub mod preview;
pub mod quality;
pub mod raycast;
pub mod refine;
pub mod scenes;
pub mod sequence;
pub mod splat;
pub mod ssfr;
pub mod surface;
pub mod surfels;
pub mod view;

pub use particles::{Attribute, ParticleSet, ParticleView, ScalarKind};

pub use memory::{peak_resident_mib, reset_peak_resident};

/// Every error the crate returns.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum Error {
    /// Reading or writing a file.
    #[error(transparent)]
    Io(#[from] io::IoError),
    /// Neighbour search.
    #[error(transparent)]
    Neighbour(#[from] neighbours::NeighbourError),
    /// Surface detection.
    #[error(transparent)]
    Surface(#[from] surface::SurfaceError),
    /// Upsampling.
    #[error(transparent)]
    Refine(#[from] refine::RefineError),
    /// The density grid.
    #[error(transparent)]
    Density(#[from] density::DensityError),
    /// The GPU stages.
    #[error(transparent)]
    Gpu(#[from] gpu::GpuError),
    /// Surfel extraction.
    #[error(transparent)]
    Surfels(#[from] surfels::SurfelError),
    /// Scene construction.
    #[error(transparent)]
    Scene(#[from] scenes::SceneError),
    /// An invalid particle set.
    #[error(transparent)]
    Particles(#[from] particles::ParticleSetError),
    /// Drawing a picture.
    #[error(transparent)]
    Preview(#[from] preview::PreviewError),
    /// A command-line or API argument that cannot be used as given.
    #[error("invalid argument `{argument}`: {reason}")]
    InvalidArgument {
        argument: &'static str,
        reason: String,
    },
    /// Surfel rendering.
    #[error(transparent)]
    Splat(#[from] splat::SplatError),
    /// Ray casting to the iso-surface (the reference renderer).
    #[error(transparent)]
    RayCast(#[from] raycast::RayCastError),
    /// The narrow band of the Layered Neighborhood Method.
    #[error(transparent)]
    Lnm(#[from] lnm::LnmError),
    /// The screen-space renderer.
    #[error(transparent)]
    Ssfr(#[from] ssfr::SsfrError),
    /// Optics: caustics, refraction and reflection.
    #[error(transparent)]
    Optics(#[from] optics::OpticsError),
    /// Frame patterns and ranges.
    #[error(transparent)]
    Sequence(#[from] sequence::SequenceError),
    /// The pipeline's own settings.
    #[error(transparent)]
    Pipeline(#[from] pipeline::PipelineError),
}
