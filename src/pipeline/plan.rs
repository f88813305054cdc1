//! A sequence in chunks (issue 39): the state a sequence fixes on its first frame, as a plan
//! every chunk loads, and the warm-up that gives a chunk the hysteresis of the frames before it.
//!
//! A sequence carries state from frame to frame: the support radius (estimated on the first
//! frame), the views it fits once and keeps (camera, pool, scene box, the light's screen and map
//! resolutions), surface detection's hysteresis (each particle's class on the previous frame)
//! and, with `detail = "auto"`, each particle's level of detail. The first two are fixed after
//! the first rendered frame: [`Pipeline::plan`] gives them as a [`SequencePlan`] (a small JSON
//! file, [`SequencePlan::write`]) and [`Pipeline::set_plan`] hands them to the pipeline of
//! another chunk, process or machine, so that it renders with the serial run's camera, pool and
//! radius. The hysteresis is the frames': [`Pipeline::warm_up`] runs the detection (and the
//! levels of detail) alone on the frames before a chunk's first, so that its first frame starts
//! from the classes the serial run would have.

use std::path::Path;

use glam::Vec3;
use serde::{Deserialize, Serialize};

use super::{KeptOptics, Pipeline, Through, Views};
use crate::io::{IoError, Location};
use crate::splat::Camera;
use crate::{Error, ParticleView};

/// The frames a chunk warms up on by default ([`Pipeline::warm_up`] on the frames before its
/// first). Measured on the column scene (48 frames, finished frames at 64x48, chunks starting
/// at frames 4 to 40 with the serial run's plan): the classes that differ from the serial run's
/// on the chunk's first frame after a warm-up of 0, 1, 2... frames fall as 81, 25, 12, 3, 2, 0
/// (the chunk at frame 16) and 30, 13, 7, 4, 3, 1, 1, 0 (at frame 32, the slowest: 7 frames),
/// and once they agree the finished image is the serial run's byte for byte (the levels of
/// detail agree too). Eight frames: the slowest case and one more.
pub const DEFAULT_WARMUP: usize = 8;

/// The version [`SequencePlan::version`] has.
pub const PLAN_VERSION: u32 = 1;

/// What a sequence fixes on its first rendered frame. See the module documentation.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SequencePlan {
    /// The plan's format ([`PLAN_VERSION`]).
    pub version: u32,
    /// The support radius (given, or estimated on the first frame).
    pub support_radius: f32,
    /// The camera of the pictures.
    pub camera: Camera,
    /// What the optics keep: the pool, the scene box, the light's screen and map resolutions
    /// (`None` when the first frame drew no finished frame).
    pub optics: Option<KeptOptics>,
    /// The box the views were fitted to besides the first frame's water
    /// ([`Pipeline::fit_to`]: `--fit union`).
    pub fit: Option<[Vec3; 2]>,
}

impl SequencePlan {
    /// Checks the values a file could hold wrong: the version, a finite positive radius, a
    /// usable camera, resolutions of at least one texel, finite boxes.
    pub fn validate(&self) -> Result<(), String> {
        if self.version != PLAN_VERSION {
            return Err(format!(
                "version {} (this build reads version {PLAN_VERSION})",
                self.version
            ));
        }
        let r = self.support_radius;
        if !(r.is_finite() && r > 0.0) {
            return Err(format!("support_radius must be finite and > 0, got {r}"));
        }
        let c = &self.camera;
        if ![c.eye, c.target, c.up].iter().all(|v| v.is_finite()) || c.eye == c.target {
            return Err(
                "the camera needs finite eye, target and up, the eye off the target".into(),
            );
        }
        let finite_box = |[a, b]: [Vec3; 2]| a.is_finite() && b.is_finite() && a.cmple(b).all();
        if let Some(fit) = self.fit
            && !finite_box(fit)
        {
            return Err("the fitted box must be finite with min <= max".into());
        }
        if let Some(o) = &self.optics {
            if !finite_box(o.bounds) {
                return Err("the scene box must be finite with min <= max".into());
            }
            if o.screen.contains(&0) || o.map.contains(&0) {
                return Err("the light's screen and map need at least one texel a side".into());
            }
        }
        Ok(())
    }

    /// Reads a plan written by [`SequencePlan::write`], checked.
    pub fn read(path: &Path) -> Result<Self, Error> {
        let text = std::fs::read_to_string(path).map_err(|e| IoError::os(path, e))?;
        let plan: Self = serde_json::from_str(&text).map_err(|e| {
            IoError::parse(
                path,
                Location::Line(e.line()),
                "a sequence plan (JSON)",
                e.to_string(),
            )
        })?;
        plan.validate().map_err(|reason| {
            IoError::parse(path, Location::Line(1), "a usable sequence plan", reason)
        })?;
        Ok(plan)
    }

    /// Writes the plan as JSON, atomically (a temporary file renamed): chunks that write the
    /// same plan at once leave one whole file.
    pub fn write(&self, path: &Path) -> Result<(), Error> {
        let text = serde_json::to_string_pretty(self).map_err(|e| Error::InvalidArgument {
            argument: "plan",
            reason: e.to_string(),
        })?;
        Ok(crate::io::write_atomically(path, text.as_bytes())?)
    }
}

impl Pipeline {
    /// The sequence's plan: its support radius, camera, kept optics views and fitted box, once
    /// a frame was rendered (the views are fitted on the first one); `None` before.
    #[must_use]
    pub fn plan(&self) -> Option<SequencePlan> {
        let views = self.views.as_ref()?;
        Some(SequencePlan {
            version: PLAN_VERSION,
            support_radius: self.radius?,
            camera: views.camera,
            optics: views.optics.clone(),
            fit: self.fit.map(|(a, b)| [a, b]),
        })
    }

    /// Takes a sequence's plan: the next frames render with its radius, camera, pool, scene box
    /// and resolutions, as the frames of the run that made it do (the hysteresis is the
    /// frames': [`Pipeline::warm_up`]).
    pub fn set_plan(&mut self, plan: &SequencePlan) -> Result<(), Error> {
        plan.validate().map_err(|reason| Error::InvalidArgument {
            argument: "plan",
            reason,
        })?;
        self.radius = Some(plan.support_radius);
        self.fit = plan.fit.map(|[a, b]| (a, b));
        self.views = Some(Views {
            camera: plan.camera,
            optics: plan.optics.clone(),
        });
        Ok(())
    }

    /// Runs what carries over from frame to frame, and only that, on a frame before the ones
    /// to draw: surface detection with its hysteresis and, with `detail = "auto"` on frames
    /// drawn `through` a picture, each particle's level of detail. No refinement, grid, surfels
    /// or picture. Warm up on the frames just before a chunk's first, in order, after
    /// [`Pipeline::set_plan`].
    pub fn warm_up<'a>(
        &mut self,
        particles: impl Into<ParticleView<'a>>,
        through: Through,
    ) -> Result<(), Error> {
        let particles: ParticleView<'a> = particles.into();
        self.in_pool(|p| p.warm_up_here(particles, through))
    }

    /// [`Pipeline::warm_up`] in the current thread pool.
    fn warm_up_here(&mut self, particles: ParticleView<'_>, through: Through) -> Result<(), Error> {
        particles.validate()?;
        let mut timings = super::FrameTimings::default();
        let mut warnings = Vec::new();
        let detected = self.detect_stage(particles, &mut timings, &mut warnings)?;
        // as `frame_through` decides to refine
        let refines = through >= Through::Refine
            && (through == Through::Refine || self.params.source != super::SurfelSource::Particles);
        if refines
            && let Some(view) = self.view_levels(particles.positions, detected.radius, through)?
        {
            self.surface_levels(&view, particles, &detected.surface_indices);
        }
        Ok(())
    }
}

/// What [`render_chunk`] did.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct ChunkReport {
    /// Frames drawn and written.
    pub written: Vec<usize>,
    /// Frames whose PNG existed (kept).
    pub skipped: Vec<usize>,
    /// Frames that could not be read or drawn, with the error; the others were written.
    pub failed: Vec<(usize, String)>,
    /// Warm-up frames that could not be read (the warm-up went on without them).
    pub warmup_failed: Vec<(usize, String)>,
    /// Wall-clock seconds.
    pub seconds: f64,
}

/// The PNG [`render_chunk`] writes frame `frame` to in `out`: `frame_NNNN.png`, as `render
/// --frames` names them.
#[must_use]
pub fn frame_png(out: &Path, frame: usize) -> std::path::PathBuf {
    out.join(format!("frame_{frame:04}.png"))
}

/// The plan of a sequence of files: frame `first` of `input` drawn through the finished frame
/// by a pipeline of `params` (the camera, pool and scene box fitted to it, or also to `fit`).
pub fn plan_of(
    input: &crate::sequence::FramePattern,
    first: usize,
    params: &super::PipelineParams,
    fit: Option<(Vec3, Vec3)>,
) -> Result<SequencePlan, Error> {
    let set = crate::io::read_particles(&input.path(first), None)?;
    let mut p = Pipeline::new(params.clone())?;
    if let Some((lo, hi)) = fit {
        p.fit_to(lo, hi)?;
    }
    p.frame_through(&set, Through::Frame)?;
    p.plan().ok_or_else(|| Error::InvalidArgument {
        argument: "plan",
        reason: format!("frame {first} fitted no views"),
    })
}

/// One chunk of a sequence of files drawn as the serial run draws it (for a task of a cluster,
/// `fluid_surfels.cluster` in Python): a pipeline of `params` takes `plan` (the range's first
/// frame's, [`plan_of`]), warms up on `warmup` (the frames just before the chunk), then draws
/// the finished frame of each of `frames` into the folder `out` (made when missing;
/// [`frame_png`], written atomically: an
/// interrupted task leaves no half-written PNG under a frame's name). A frame whose file cannot
/// be read or drawn is reported and the others are written; with `skip_existing` the frames
/// whose PNG exists are kept (warmed up on), so a rerun after a crash draws only the missing
/// ones, as the uninterrupted run would have.
pub fn render_chunk(
    input: &crate::sequence::FramePattern,
    (warmup, frames): (&[usize], &[usize]),
    out: &Path,
    params: &super::PipelineParams,
    plan: Option<&SequencePlan>,
    skip_existing: bool,
) -> Result<ChunkReport, Error> {
    let start = std::time::Instant::now();
    let mut report = ChunkReport::default();
    std::fs::create_dir_all(out).map_err(|e| IoError::os(out, e))?;
    let mut p = Pipeline::new(params.clone())?;
    if let Some(plan) = plan {
        p.set_plan(plan)?;
    }
    let read = |f: usize| crate::io::read_particles(&input.path(f), None);
    let warm = |p: &mut Pipeline, report: &mut ChunkReport, f: usize| {
        let warmed = read(f)
            .map_err(Error::from)
            .and_then(|set| p.warm_up(&set, Through::Frame));
        if let Err(e) = warmed {
            report.warmup_failed.push((f, e.to_string()));
        }
    };
    for &f in warmup {
        warm(&mut p, &mut report, f);
    }
    for &f in frames {
        let png = frame_png(out, f);
        if skip_existing && png.exists() {
            // kept, but its hysteresis carries over to the frames after it
            report.skipped.push(f);
            warm(&mut p, &mut report, f);
            continue;
        }
        let drawn = read(f).map_err(Error::from).and_then(|set| {
            let frame = p.frame_through(&set, Through::Frame)?;
            let image = &frame.finished.as_ref().expect("through the frame").image;
            crate::preview::save_rgba_png(image, &png)?;
            p.recycle(frame);
            Ok(())
        });
        match drawn {
            Ok(()) => report.written.push(f),
            Err(e) => report.failed.push((f, e.to_string())),
        }
    }
    report.seconds = start.elapsed().as_secs_f64();
    Ok(report)
}
