//! Stage 2: upsampling of surface points (Solenthaler et al. 2007, §3.2-3.4).
//!
//! Each step inserts a child between every pair of neighbouring points (eq. 3-14), on a sphere
//! through the two parents, rejects children that would land within the collision distance
//! `beta = 0.2 r_i` of an existing point and moves that point instead (eq. 17-19), and updates the
//! neighbourhoods for the next, smaller radius `r_{i+1} = r_i sqrt(4 - 2 sqrt 2) / 2` (eq. 16)
//! from the relations already known, without a search structure (§3.4).
//!
//! Two implementations run the same step: [`refine_reference`] (module `reference`) as the
//! paper describes it, on one thread with one `Vec` of neighbours per point, and [`refine`]
//! (module `flat`), in flat storage (CSR neighbourhoods) with every pass but three cheap
//! sequential ones (the inversion of the would-be registrations, the acceptance decision and
//! the moves) spread over rayon: the type 3 pass,
//! which depends on every earlier decision of the step, is reformulated so that what a child
//! could collide with is found in parallel beforehand. Both give the same points in the same
//! order whatever the thread count (tested).
//!
//! Both also refine each region to its own level ([`refine_to_levels`], for detail chosen from
//! the view, issue 36): a pair makes a child in step `i` only when one of its points' level is
//! at least `i`, a child takes the higher of its parents' levels, and each point's kernel and
//! splat radii are those of its level ([`Refined::levels`]).
//!
//! Where this differs from, or makes precise, the paper:
//! - Eq. 8 and 10 take `|n . a|`, which loses the side of the child: between two points on the
//!   inside of a bowl the child is pushed away from the surface. With `a = (x1 - x2)/|x1 - x2|`
//!   the signed slopes are `s1 = n1 . a` and `s2 = -n2 . a`: for a circle of radius `rho` whose
//!   centre lies `k` from the midpoint on the normal's side (concave), `n1 . a = -|d|/(2 rho)` and
//!   `n1 . b = k/rho`, so eq. 6 gives `h1 = k - rho < 0`, the point of the arc; on a convex circle
//!   it gives `rho - k > 0` as before. [`child`] uses the signed form.
//! - With eq. 5 (`min(|h1|, |h2|)`, the default) the sign is the parents' common sign; when they
//!   disagree (an inflection between them) `h = 0` and the child sits at the midpoint. Eq. 4
//!   (the average) is kept signed.
//! - Collision checks of a step use the positions at the start of the step, and the moves of
//!   eq. 17-19 are applied after all children of the step are decided, in candidate order. The
//!   paper leaves this order open; fixing it makes the result independent of processing order.
//! - A rejected child moves the nearest colliding point: an older point (type 2) if any, else the
//!   nearest child of this step (type 3). Children weigh their distance to a parent in units of
//!   `r0`; original points weigh `original_weight` (1e6), so they effectively stay put.

use glam::Vec3;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::neighbours::{Backend, NeighbourError, Neighbourhoods};
use crate::particles::{Attribute, ParticleSet, ScalarKind};

/// `r_{i+1} / r_i` (eq. 16): `sqrt(4 - 2 sqrt 2) / 2`, about 0.5412.
pub const RADIUS_FACTOR: f32 = 0.541_196_1;
/// `h_max / r_i` (eq. 15): `(sqrt 2 - 1) / 2`.
pub const HMAX_FACTOR: f32 = 0.207_106_78;
/// Below this `|b'|` (eq. 13) the parents are taken to lie on different surfaces.
pub const MIN_B_PRIME: f32 = 0.05;

/// How the two parents' displacements combine (eq. 4 and 5).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum HeightRule {
    /// `min(|h1|, |h2|)` with the parents' common sign (eq. 5): keeps edges and corners.
    #[default]
    Min,
    /// `(h1 + h2) / 2` (eq. 4): smoother.
    Average,
}

impl HeightRule {
    /// Every rule, in the order of the documentation.
    pub const ALL: [Self; 2] = [Self::Min, Self::Average];

    /// The name used in files and on the command line.
    #[must_use]
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Min => "min",
            Self::Average => "average",
        }
    }
}

/// Parameters of the refinement.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RefineParams {
    /// Initial visibility radius `r0`: the SPH support radius of the simulation (§3.2.1).
    pub initial_radius: f32,
    /// Refinement steps (the paper shows 3).
    pub steps: u32,
    /// Eq. 4 or eq. 5.
    pub height: HeightRule,
    /// Collision distance as a fraction of the step's radius (`beta = 0.2 r_i`, §3.3.1).
    pub collision_factor: f32,
    /// Detect and handle collisions (§3.3); off only to measure what they bring.
    pub collisions: bool,
    /// Weight of the original points in eq. 17-19 ("a high weight").
    pub original_weight: f32,
    /// Splat radius of refined points as a fraction of the final radius `r_n`.
    pub splat_factor: f32,
    /// Density kernel radius of refined points as a multiple of the final radius `r_n`, for the
    /// design chain's density grid (Iwasaki et al. §4 fed with the refined surface). The
    /// refinement leaves neighbouring points at most about `r_n` apart, so 2 is the analogue of
    /// an SPH support radius of two particle spacings. Points that had no neighbour keep the
    /// initial radius `r0` (a lone drop stays the size of a particle).
    pub kernel_factor: f32,
    /// The most memory the refined points may take, in bytes, at [`BYTES_PER_POINT`] each: a
    /// step whose candidates (an upper bound on its new points) would go over it is refused
    /// before it runs, with [`RefineError::OverBudget`]. Default
    /// [`crate::memory::DEFAULT_MEMORY_BUDGET`], the density grid's.
    pub memory_budget: u64,
}

/// Memory per refined point while refining: position, normal, radius, neighbour list and the
/// step's bookkeeping (measured: peak RSS 698 MB for the 2.61 M points of 5 steps on the
/// double dam break file with the parallel implementation, 268 bytes a point; 821 MB, 315 bytes
/// a point, with the reference).
pub const BYTES_PER_POINT: u64 = 400;

impl Default for RefineParams {
    /// The paper's values; `initial_radius` must be set (0 is refused).
    fn default() -> Self {
        Self {
            initial_radius: 0.0,
            steps: 3,
            height: HeightRule::Min,
            collision_factor: 0.2,
            collisions: true,
            original_weight: 1e6,
            splat_factor: 0.6,
            kernel_factor: 2.0,
            memory_budget: crate::memory::DEFAULT_MEMORY_BUDGET,
        }
    }
}

impl RefineParams {
    /// The paper's values for a simulation of support radius `r0`.
    #[must_use]
    pub fn with_radius(r0: f32) -> Self {
        Self {
            initial_radius: r0,
            ..Self::default()
        }
    }
}

/// Errors of the refinement.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RefineError {
    /// A parameter is out of range.
    #[error("invalid refinement parameter `{name}`: {reason}")]
    InvalidParameter { name: &'static str, reason: String },
    /// Positions and normals differ in number.
    #[error("{normals} normals for {points} points")]
    LengthMismatch { points: usize, normals: usize },
    /// A position or normal is NaN or infinite.
    #[error("point {index} has a non-finite position or normal")]
    NonFinite { index: usize },
    /// The initial neighbourhoods could not be built.
    #[error(transparent)]
    Neighbours(#[from] NeighbourError),
    /// A step would make more points than the memory budget holds.
    #[error(
        "refinement step {step} of {steps} would make up to {predicted} points ({} MiB at {BYTES_PER_POINT} bytes a point), over the memory budget of {} MiB; the steps before made {points} points: use fewer steps, or raise the budget (--memory-budget, `RefineParams::memory_budget`)",
        (predicted * BYTES_PER_POINT as usize) >> 20, budget >> 20
    )]
    OverBudget {
        step: u32,
        steps: u32,
        predicted: usize,
        points: usize,
        budget: u64,
    },
}

/// What one step did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct StepStats {
    /// Step number, from 1.
    pub step: u32,
    /// Visibility radius `r_i` of the step.
    pub radius: f32,
    /// Points before and after the step.
    pub points_before: usize,
    pub points_after: usize,
    /// Neighbouring pairs farther apart than `r_{i+1}` (each a child candidate).
    pub candidates: usize,
    /// Pairs whose normals gave no child (`|b'|` near zero: different surfaces).
    pub different_surfaces: usize,
    /// Children rejected for an older point within `beta` (type 2) or a child of this step (type 3).
    pub collisions_type2: usize,
    pub collisions_type3: usize,
    /// Collisions resolved: every detected collision rejects its child.
    pub resolved: usize,
    /// Points moved towards a rejected child (eq. 17-19); a move that would bring the point
    /// within `beta` of another is not made.
    pub moved: usize,
    /// Wall-clock time of the step.
    pub ms: f64,
    /// Where the step's time went, in milliseconds: making the candidates, their type 2 checks
    /// (with, in the parallel implementation, each candidate's would-be registrations), the type 3
    /// checks with acceptance and registration, and the append, moves and neighbourhood update
    /// (`bench refine` sums them).
    pub phases: StepPhases,
}

/// Milliseconds of each phase of one step ([`StepStats::phases`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct StepPhases {
    /// The candidate pairs and their midpoints on the sphere (eq. 14-16), in parallel.
    pub candidates_ms: f64,
    /// Type 2 checks, in parallel; the parallel implementation also lists here, per candidate,
    /// the points it would be registered with if accepted, and inverts those lists (per point,
    /// the candidates that would register there).
    pub type2_ms: f64,
    /// Type 3 checks and acceptance: the reference tests and registers candidate by candidate;
    /// the parallel implementation finds each candidate's rivals in parallel, then decides in
    /// one sequential pass over them.
    pub accept_ms: f64,
    /// Of `update_ms`: the moves of eq. 17-19 (sequential).
    pub moves_ms: f64,
    /// Appending the accepted children, the moves, and the new neighbourhoods (in parallel).
    pub update_ms: f64,
}

impl StepPhases {
    /// The sum of two steps' phases.
    #[must_use]
    pub fn plus(self, o: Self) -> Self {
        Self {
            candidates_ms: self.candidates_ms + o.candidates_ms,
            type2_ms: self.type2_ms + o.type2_ms,
            accept_ms: self.accept_ms + o.accept_ms,
            moves_ms: self.moves_ms + o.moves_ms,
            update_ms: self.update_ms + o.update_ms,
        }
    }
}

/// The refined point set `P_n`.
#[derive(Clone, Debug, Default)]
pub struct Refined {
    /// Positions: the input points first (in input order), then each step's children.
    pub positions: Vec<Vec3>,
    /// Unit normals.
    pub normals: Vec<Vec3>,
    /// The step that created each point (0 for input points).
    pub steps: Vec<u8>,
    /// Weights of eq. 17-19.
    pub weights: Vec<f32>,
    /// Splat radius of each point for rendering.
    pub radii: Vec<f32>,
    /// Density kernel radius of each point (`kernel_factor r_k`, `k` its level; `r0` for points
    /// that had no neighbour), for the design chain's density grid.
    pub kernel_radii: Vec<f32>,
    /// The steps each point's region took ([`refine_to_levels`]; every point `steps` in a fixed
    /// refinement): its splat and kernel radii are that level's.
    pub levels: Vec<u8>,
    /// Per step.
    pub stats: Vec<StepStats>,
    /// `r_n`, the radius after the last step run (the finest level's).
    pub final_radius: f32,
}

impl Refined {
    /// Number of points.
    #[must_use]
    pub fn len(&self) -> usize {
        self.positions.len()
    }

    /// True when empty.
    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.positions.is_empty()
    }

    /// As a particle set with normals and `step`, `weight`, `radius` and `kernel_radius`
    /// attributes.
    #[must_use]
    pub fn to_particle_set(&self) -> ParticleSet {
        let mut set = ParticleSet::from_positions(self.positions.clone());
        set.normals = Some(self.normals.clone());
        set.extra.push(Attribute::scalar(
            "step",
            ScalarKind::U8,
            self.steps.iter().map(|&s| s as f64).collect(),
        ));
        set.extra.push(Attribute::scalar(
            "weight",
            ScalarKind::F32,
            self.weights.iter().map(|&w| w as f64).collect(),
        ));
        set.extra.push(Attribute::scalar(
            "radius",
            ScalarKind::F32,
            self.radii.iter().map(|&r| r as f64).collect(),
        ));
        set.extra.push(Attribute::scalar(
            "kernel_radius",
            ScalarKind::F32,
            self.kernel_radii.iter().map(|&r| r as f64).collect(),
        ));
        set
    }
}

/// The child of a pair (eq. 3-14 with signed slopes, see the module docs): its position and
/// unit normal, or `None` when `|b'|` is near zero.
#[must_use]
pub fn child(
    x1: Vec3,
    n1: Vec3,
    x2: Vec3,
    n2: Vec3,
    rule: HeightRule,
    h_max: f32,
) -> Option<(Vec3, Vec3)> {
    let d = x1 - x2;
    let len = d.length();
    if len <= 0.0 {
        return None;
    }
    let a = d / len; // eq. 12
    let sum = n1 + n2;
    let b_prime = sum - a * sum.dot(a); // eq. 13
    let bl = b_prime.length();
    if bl < MIN_B_PRIME || !bl.is_finite() {
        return None;
    }
    let b = b_prime / bl; // eq. 14: the child's normal
    let half = 0.5 * len;
    // eq. 6-11 with signed s: h = s / t * |d| / 2, t = n . b + |n_c|, clamped to h_max (eq. 15)
    let height = |s: f32, t: f32| {
        if t <= 1e-6 {
            h_max.copysign(s)
        } else {
            (s / t * half).clamp(-h_max, h_max)
        }
    };
    let h1 = height(n1.dot(a), n1.dot(b) + 1.0);
    let h2 = height(-n2.dot(a), n2.dot(b) + 1.0);
    let h = match rule {
        HeightRule::Min if h1 * h2 <= 0.0 => 0.0,
        HeightRule::Min => h1.abs().min(h2.abs()).copysign(h1),
        HeightRule::Average => 0.5 * (h1 + h2),
    };
    Some(((x1 + x2) * 0.5 + b * h, b))
}

mod flat;
mod reference;

/// A child candidate of the current step.
#[derive(Clone, Copy, Debug, Default)]
struct Candidate {
    p1: u32,
    p2: u32,
    pos: Vec3,
    nrm: Vec3,
    weight: f32,
}

/// The point a rejected child moves.
#[derive(Clone, Copy, Debug)]
enum Target {
    Old(u32),
    New(u32),
}

/// One sorted list of point indices per point (neighbourhoods, registrations), whatever the
/// storage.
trait Lists {
    fn of(&self, i: usize) -> &[u32];
}

impl Lists for [Vec<u32>] {
    #[inline]
    fn of(&self, i: usize) -> &[u32] {
        &self[i]
    }
}

/// The neighbour lists after a step, as [`refine_observed`] shows them: for each point, the
/// indices of the points within the new radius, ascending.
#[derive(Clone, Copy)]
pub struct NeighbourLists<'a>(ListsRef<'a>);

#[derive(Clone, Copy)]
enum ListsRef<'a> {
    Nested(&'a [Vec<u32>]),
    Flat(&'a flat::Csr),
}

impl<'a> NeighbourLists<'a> {
    fn nested(lists: &'a [Vec<u32>]) -> Self {
        Self(ListsRef::Nested(lists))
    }

    fn flat(lists: &'a flat::Csr) -> Self {
        Self(ListsRef::Flat(lists))
    }

    /// Number of points.
    #[must_use]
    pub fn len(&self) -> usize {
        match self.0 {
            ListsRef::Nested(l) => l.len(),
            ListsRef::Flat(l) => l.len(),
        }
    }

    /// True when there are no points.
    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The neighbours of point `i`, ascending.
    #[must_use]
    pub fn of(&self, i: usize) -> &'a [u32] {
        match self.0 {
            ListsRef::Nested(l) => &l[i],
            ListsRef::Flat(l) => l.of(i),
        }
    }
}

fn validate(
    positions: &[Vec3],
    normals: &[Vec3],
    params: &RefineParams,
) -> Result<(), RefineError> {
    let bad = |name, reason: String| Err(RefineError::InvalidParameter { name, reason });
    let r0 = params.initial_radius;
    if !(r0.is_finite() && r0 > 0.0) {
        return bad(
            "initial_radius",
            format!("must be finite and > 0 (the SPH support radius), got {r0}"),
        );
    }
    if params.steps > 8 {
        return bad(
            "steps",
            format!(
                "at most 8 (each step multiplies the points several times), got {}",
                params.steps
            ),
        );
    }
    if !(params.collision_factor.is_finite()
        && (0.0..0.5 * RADIUS_FACTOR).contains(&params.collision_factor))
    {
        return bad(
            "collision_factor",
            format!(
                "must lie in [0, 0.27) so that parents never collide (§3.3.1), got {}",
                params.collision_factor
            ),
        );
    }
    if !(params.original_weight.is_finite() && params.original_weight > 0.0) {
        return bad(
            "original_weight",
            format!("must be finite and > 0, got {}", params.original_weight),
        );
    }
    if !(params.splat_factor.is_finite() && params.splat_factor > 0.0) {
        return bad(
            "splat_factor",
            format!("must be finite and > 0, got {}", params.splat_factor),
        );
    }
    if !(params.kernel_factor.is_finite() && params.kernel_factor > 0.0) {
        return bad(
            "kernel_factor",
            format!("must be finite and > 0, got {}", params.kernel_factor),
        );
    }
    if positions.len() != normals.len() {
        return Err(RefineError::LengthMismatch {
            points: positions.len(),
            normals: normals.len(),
        });
    }
    if positions.len() > (u32::MAX / 64) as usize {
        return bad(
            "points",
            format!("{} points: too many to refine", positions.len()),
        );
    }
    if let Some(index) = positions
        .iter()
        .zip(normals)
        .position(|(p, n)| !p.is_finite() || !n.is_finite())
    {
        return Err(RefineError::NonFinite { index });
    }
    Ok(())
}

/// Sorted intersection of two sorted lists, visited.
#[inline]
fn for_each_common(a: &[u32], b: &[u32], mut f: impl FnMut(u32)) {
    // branch-free steps: the comparisons of a merge are unpredictable
    let (mut i, mut j) = (0, 0);
    while i < a.len() && j < b.len() {
        let (x, y) = (a[i], b[j]);
        if x == y {
            f(x);
        }
        i += usize::from(x <= y);
        j += usize::from(y <= x);
    }
}

/// The neighbours of `p1` that make a pair with it this step: the higher-numbered ones at least
/// `r_next` away (nearer ones are left to the next step: type 1 collisions, §3.3.1), where one
/// of the two may still refine this step (`caps`, the most steps of each point's region,
/// [`refine_to_levels`]).
fn pairs_of<'a>(
    pos: &'a [Vec3],
    caps: &'a [u8],
    nb: &'a [u32],
    p1: usize,
    r_next: f32,
    step: u32,
) -> impl Iterator<Item = u32> + 'a {
    let x1 = pos[p1];
    let open1 = u32::from(caps[p1]) >= step;
    nb.iter().copied().filter(move |&p2| {
        p2 as usize > p1
            && (open1 || u32::from(caps[p2 as usize]) >= step)
            && x1.distance_squared(pos[p2 as usize]) >= r_next * r_next
    })
}

/// The most points a step may be open to for [`may_pair`] to look for their pairs by brute force.
const FEW_OPEN: usize = 64;

/// The points open to step `step`: those whose region takes it (`caps`, [`refine_to_levels`]).
fn open_to(caps: &[u8], step: u32) -> Vec<usize> {
    (0..caps.len())
        .into_par_iter()
        .filter(|&i| u32::from(caps[i]) >= step)
        .collect()
}

/// Whether a step at radius `r` could pair two points ([`pairs_of`]): some point `open` to it
/// ([`open_to`]) has another point at a distance in `[r_next, r]`. The neighbourhoods before
/// the step hold only points within `r`, so where no point is there the step makes nothing,
/// and the neighbourhood update before it (the largest phase of a step) can be skipped. Detail
/// from the view leaves a handful of points (isolated drops, a crest near the camera) at a
/// level no other point reaches: on the dam break at 640x480, 5 of 8,457 surface particles
/// asked for a third step that made no point, after a 45 ms update. Brute force over all
/// points when at most [`FEW_OPEN`] points are open (a few milliseconds at most), else `true`
/// (the step runs and finds its pairs). Conservative: the range is widened by a few ulps, and
/// the answer is `true` wherever the lists could hold a pair.
fn may_pair(pos: &[Vec3], open: &[usize], r: f32) -> bool {
    if open.len() > FEW_OPEN {
        return true;
    }
    let r_next = r * RADIUS_FACTOR;
    let (near, far) = (r_next * r_next * (1.0 - 1e-5), r * r * (1.0 + 1e-5));
    open.par_iter().any(|&p| {
        pos.iter()
            .enumerate()
            .any(|(q, x)| q != p && (near..=far).contains(&x.distance_squared(pos[p])))
    })
}

/// The steps of a refinement, for both implementations: step `s` at radius
/// `radius_after[s - 1]` (`step(points, r, s)`, which says whether another follows), from 1 up
/// to `last` or until one says none follows; `after(points, r_next)` sees the points after
/// each step that another follows.
fn run_steps<P>(
    pts: &mut P,
    radius_after: &[f32],
    last: u32,
    mut step: impl FnMut(&mut P, f32, u32) -> Result<(StepStats, bool), RefineError>,
    mut after: impl FnMut(&P, f32),
) -> Result<Vec<StepStats>, RefineError> {
    let mut stats = Vec::new();
    for s in 1..=last {
        let (done, more) = step(pts, radius_after[s as usize - 1], s)?;
        stats.push(done);
        if !more {
            break;
        }
        after(pts, radius_after[s as usize]);
    }
    Ok(stats)
}

/// The child candidates of point `p1` with its higher-numbered neighbours, in neighbour order.
/// Returns the number of pairs that gave no child (`|b'|` near zero).
#[allow(clippy::too_many_arguments)] // one point's pairs, passed once
fn candidates_of(
    pos: &[Vec3],
    nrm: &[Vec3],
    caps: &[u8],
    nb: &[u32],
    p1: usize,
    params: &RefineParams,
    r: f32,
    step: u32,
    out: &mut Vec<Candidate>,
) -> usize {
    let (r_next, h_max, rule, r0) = (
        r * RADIUS_FACTOR,
        r * HMAX_FACTOR,
        params.height,
        params.initial_radius,
    );
    let mut no_normal = 0;
    let (x1, n1) = (pos[p1], nrm[p1]);
    for p2 in pairs_of(pos, caps, nb, p1, r_next, step) {
        let (x2, n2) = (pos[p2 as usize], nrm[p2 as usize]);
        match child(x1, n1, x2, n2, rule, h_max) {
            Some((at, normal)) => out.push(Candidate {
                p1: p1 as u32,
                p2,
                pos: at,
                nrm: normal,
                weight: at.distance(x1) / r0,
            }),
            None => no_normal += 1,
        }
    }
    no_normal
}

/// Nearest older point of `N1 ∩ N2` within `beta` of the candidate (type 2).
fn type2_hit(pos: &[Vec3], n1: &[u32], n2: &[u32], c: &Candidate, beta: f32) -> Option<u32> {
    let mut best: Option<(f32, u32)> = None;
    for_each_common(n1, n2, |q| {
        let d2 = pos[q as usize].distance_squared(c.pos);
        if d2 < beta * beta && best.is_none_or(|(bd, _)| d2 < bd) {
            best = Some((d2, q));
        }
    });
    best.map(|(_, q)| q)
}

/// Calls `f(q)` once for every older point of `U = N1 ∪ N2` (which holds both parents) within
/// `reach` of the candidate, in ascending order: a merge of the two sorted neighbour lists.
fn for_each_registration_unique(
    pos: &[Vec3],
    a: &[u32],
    b: &[u32],
    c: &Candidate,
    reach: f32,
    mut f: impl FnMut(u32),
) {
    let reach2 = reach * reach;
    let mut visit = |q: u32| {
        if pos[q as usize].distance_squared(c.pos) < reach2 {
            f(q);
        }
    };
    // branch-free merge steps, as in `for_each_common`
    let (mut i, mut j) = (0, 0);
    while i < a.len() && j < b.len() {
        let (x, y) = (a[i], b[j]);
        visit(x.min(y));
        i += usize::from(x <= y);
        j += usize::from(y <= x);
    }
    a[i..].iter().chain(&b[j..]).for_each(|&q| visit(q));
}

/// The neighbours within `r_next` of the new child `g` (a point index, `x` its position) of the
/// pair `c`, as §3.4 finds them without a search: `visit(q)` for each point `q` of `U = N1 ∪ N2`
/// (the parents included) within `r_next` (type 2), and for each child `g2 != g` of this step,
/// of a point of `U`, within `r_next` (type 3; children are numbered from `n_old`, in the order
/// of `children_of`). A point can be visited more than once: callers sort and deduplicate.
#[allow(clippy::too_many_arguments)] // one child's relations, passed once
fn for_each_new_neighbour<N: Lists + ?Sized, C: Lists + ?Sized>(
    pos: &[Vec3],
    nb: &N,
    children_of: &C,
    c: &Candidate,
    g: u32,
    n_old: usize,
    r_next: f32,
    mut visit: impl FnMut(u32),
) {
    let (r2, x) = (r_next * r_next, pos[g as usize]);
    for &q in [c.p1, c.p2]
        .iter()
        .chain(nb.of(c.p1 as usize))
        .chain(nb.of(c.p2 as usize))
    {
        if pos[q as usize].distance_squared(x) <= r2 {
            visit(q);
        }
        for &k2 in children_of.of(q as usize) {
            let g2 = (n_old + k2 as usize) as u32;
            if g2 != g && pos[g2 as usize].distance_squared(x) <= r2 {
                visit(g2);
            }
        }
    }
}

/// Applies eq. 17-19 in candidate order: the point hit moves towards the rejected child and
/// takes its weight, unless the move would bring it within `beta` of a point it can see (its
/// neighbours and the children registered near it). The paper does not guard the move; without
/// the guard, measured on the splash frame, 3.7 % of the refined points end up closer than the
/// final collision distance to another point (0.1 % with it).
#[allow(clippy::too_many_arguments)] // one step's state, passed once
/// `moves` gives each rejected child with the point it hit, in candidate order; `parents(k)`
/// the parents of the `k`-th accepted child.
fn apply_moves<'a, N: Lists + ?Sized, R: Lists + ?Sized>(
    pos: &mut [Vec3],
    nrm: &mut [Vec3],
    weight: &mut [f32],
    nb: &N,
    registered: &R,
    moves: impl IntoIterator<Item = (Target, &'a Candidate)>,
    parents: impl Fn(u32) -> (u32, u32),
    n_old: usize,
    beta: f32,
) -> usize {
    let beta2 = beta * beta;
    let mut moved_count = 0;
    for (target, c) in moves {
        let i = match target {
            Target::Old(q) => q as usize,
            Target::New(k) => n_old + k as usize,
        };
        let (wp, wc) = (weight[i], c.weight);
        let moved = (pos[i] * wp + c.pos * wc) / (wp + wc);
        let clear = |j: usize| j == i || pos[j].distance_squared(moved) >= beta2;
        let visible_clear = match target {
            Target::Old(q) => {
                let q = q as usize;
                nb.of(q).iter().all(|&j| clear(j as usize))
                    && registered.of(q).iter().all(|&k| clear(n_old + k as usize))
            }
            Target::New(k) => {
                let (p1, p2) = parents(k);
                let (p1, p2) = (p1 as usize, p2 as usize);
                [p1, p2].iter().all(|&j| clear(j))
                    && nb
                        .of(p1)
                        .iter()
                        .chain(nb.of(p2))
                        .all(|&j| clear(j as usize))
                    && registered
                        .of(p1)
                        .iter()
                        .chain(registered.of(p2))
                        .all(|&k2| clear(n_old + k2 as usize))
            }
        };
        if !visible_clear {
            continue;
        }
        pos[i] = moved;
        let n = nrm[i] * wp + c.nrm * wc;
        nrm[i] = n.normalize_or(nrm[i]);
        weight[i] = wp + wc;
        moved_count += 1;
    }
    moved_count
}

/// Initial neighbourhoods within `r0`.
fn initial_neighbours(
    positions: &[Vec3],
    params: &RefineParams,
) -> Result<Neighbourhoods, RefineError> {
    Ok(Neighbourhoods::build(
        positions,
        params.initial_radius,
        Backend::CellGrid,
    )?)
}

/// The refined set from the final points. Splat and kernel radii: `splat_factor * r_k` and
/// `kernel_factor * r_k` for points that took part in the refinement, `r_k` the radius after the
/// `k` steps their region took (`caps`, at most the steps run, or `by_region` the last step
/// that made a point: every point of a fixed refinement has `r_n`); points that had no neighbour at the start (isolated drops) keep half
/// the initial radius as splat and the initial radius as kernel. `radius_after[k]` is `r_k`.
#[allow(clippy::too_many_arguments)] // the final state, passed once
fn finish(
    positions: Vec<Vec3>,
    normals: Vec<Vec3>,
    steps: Vec<u8>,
    weights: Vec<f32>,
    caps: &[u8],
    isolated: &[bool],
    params: &RefineParams,
    stats: Vec<StepStats>,
    radius_after: &[f32],
    by_region: bool,
) -> Refined {
    // by region: the finest level used is the last step that made a point (a region may ask for
    // a step that finds no pair far enough apart), so that no point takes a finer kernel (and
    // the density grid a finer cell) than the points around it were refined to
    let run = if by_region {
        stats
            .iter()
            .rposition(|s| s.points_after > s.points_before)
            .map_or(0, |i| i + 1)
    } else {
        stats.len()
    };
    let levels: Vec<u8> = caps.iter().map(|&c| c.min(run as u8)).collect();
    let (radii, kernel_radii) = (0..positions.len())
        .map(|i| {
            if i < isolated.len() && isolated[i] {
                (0.5 * params.initial_radius, params.initial_radius)
            } else {
                let r = radius_after[levels[i] as usize];
                (params.splat_factor * r, params.kernel_factor * r)
            }
        })
        .unzip();
    Refined {
        positions,
        normals,
        steps,
        weights,
        radii,
        kernel_radii,
        levels,
        stats,
        final_radius: radius_after[run],
    }
}

/// The most steps the refinement takes around each input point ([`refine_to_levels`]): detail
/// chosen from the view (issue 36), where a region seen small stops early.
pub type Levels<'a> = &'a [u8];

/// The steps each input point's region takes (`levels`, at most `params.steps`), and how many
/// steps run: the most of them with `levels` (none without points), else `params.steps`.
fn caps_of(params: &RefineParams, n: usize, levels: Option<Levels<'_>>) -> (Vec<u8>, u32) {
    let steps = params.steps as u8;
    let caps: Vec<u8> = match levels {
        Some(l) => l.iter().map(|&k| k.min(steps)).collect(),
        None => vec![steps; n],
    };
    let run = match levels {
        Some(_) => caps.iter().copied().max().unwrap_or(0),
        None => steps,
    };
    (caps, u32::from(run))
}

/// `r_k` after `k` steps from `r_0`, for `k` in `0..=steps`, multiplied step by step as the
/// refinement does.
fn radii_after(r0: f32, steps: u32) -> Vec<f32> {
    let mut r = r0;
    let mut out = vec![r];
    for _ in 0..steps {
        r *= RADIUS_FACTOR;
        out.push(r);
    }
    out
}

/// The faithful single-threaded refinement (the specification the parallel one is tested
/// against): the paper's steps on one `Vec` of neighbours per point.
pub fn refine_reference(
    positions: &[Vec3],
    normals: &[Vec3],
    params: &RefineParams,
) -> Result<Refined, RefineError> {
    refine_observed(positions, normals, params, false, |_, _, _| {})
}

/// The parallel refinement in flat storage: the same points in the same order as
/// [`refine_reference`], whatever the thread count.
pub fn refine(
    positions: &[Vec3],
    normals: &[Vec3],
    params: &RefineParams,
) -> Result<Refined, RefineError> {
    refine_observed(positions, normals, params, true, |_, _, _| {})
}

/// [`refine`] (`parallel`) or [`refine_reference`] with a look at the incremental
/// neighbourhoods after each step but the last: `observe(positions, neighbour lists, radius)`.
/// For tests and diagnostics.
pub fn refine_observed(
    positions: &[Vec3],
    normals: &[Vec3],
    params: &RefineParams,
    parallel: bool,
    observe: impl FnMut(&[Vec3], NeighbourLists<'_>, f32),
) -> Result<Refined, RefineError> {
    validate(positions, normals, params)?;
    if parallel {
        flat::run(positions, normals, params, None, observe)
    } else {
        reference::run(positions, normals, params, None, observe)
    }
}

/// [`refine`] (`parallel`) or [`refine_reference`] where each region stops after its own number
/// of steps, `levels[i]` around input point `i`: a pair of points makes a child in step `s` only
/// when the level of one of them is at least `s`, and a child takes the higher of its parents'
/// levels (so the finer side of a border refines the pairs that straddle it). The steps run are
/// the most that `levels` gives (at most `params.steps`); each point's kernel and splat radii are
/// those of its level ([`Refined::levels`]), so a region that stops early is drawn as the whole
/// surface would be after that many steps. With every level `params.steps`, the same points as
/// [`refine`].
pub fn refine_to_levels(
    positions: &[Vec3],
    normals: &[Vec3],
    params: &RefineParams,
    parallel: bool,
    levels: Levels<'_>,
) -> Result<Refined, RefineError> {
    validate(positions, normals, params)?;
    if levels.len() != positions.len() {
        return Err(RefineError::InvalidParameter {
            name: "levels",
            reason: format!("{} levels for {} points", levels.len(), positions.len()),
        });
    }
    if parallel {
        flat::run(positions, normals, params, Some(levels), |_, _, _| {})
    } else {
        reference::run(positions, normals, params, Some(levels), |_, _, _| {})
    }
}

/// Neighbours looked at by [`Refined::gap_free_radii`].
pub const GAP_NEIGHBOURS: usize = 6;

impl Refined {
    /// Splat radii that close the gaps between the refined points when they are drawn as
    /// surfels (`SurfelSource::Refined`): each point's own radius, grown to `0.75 d6`, where `d6`
    /// is the distance, in the point's tangent plane, to the 6th nearest of the neighbours on the
    /// same side of the surface (normals within 60 degrees, from the 16 nearest points).
    ///
    /// Why `0.75 d6`: in a hexagonal sampling of spacing `a` (the densest arrangement of points
    /// on a surface) every point of the plane lies within `a / sqrt 3 = 0.577 a` of a sample and
    /// the 6th neighbour is at `a`; 0.75 leaves room for irregular samplings, where the gap to
    /// be closed is wider exactly where the neighbours are farther. Neighbours are taken on the
    /// same side and in the tangent plane so that the other side of a thin sheet, closer than the
    /// neighbours along it, does not shrink the radius. The growth is capped at 3x the point's
    /// radius so that a point with few neighbours (a torn edge) does not become a large disk.
    #[must_use]
    pub fn gap_free_radii(&self) -> Vec<f32> {
        use kiddo::{ImmutableKdTree, SquaredEuclidean};
        let n = self.positions.len();
        if n < 2 {
            return self.radii.clone();
        }
        let points: Vec<[f32; 3]> = self.positions.iter().map(|p| p.to_array()).collect();
        let Ok(tree) = ImmutableKdTree::<f32, 3>::new_from_slice(&points) else {
            return self.radii.clone();
        };
        let query = std::num::NonZeroUsize::new(17.min(n)).expect("n >= 2");
        (0..n)
            .into_par_iter()
            .map(|i| {
                let (p, normal, r) = (self.positions[i], self.normals[i], self.radii[i]);
                // tangent-plane distances of the same-side neighbours, on the stack
                let mut tangent = [0f32; 16];
                let mut count = 0;
                for nb in tree
                    .query(&points[i])
                    .nearest_n::<SquaredEuclidean<f32>>(query)
                    .execute()
                {
                    let j = nb.item as usize;
                    if j == i || self.normals[j].dot(normal) <= 0.5 || count == tangent.len() {
                        continue;
                    }
                    let d = self.positions[j] - p;
                    tangent[count] = (d - d.dot(normal) * normal).length();
                    count += 1;
                }
                if count < GAP_NEIGHBOURS {
                    return r;
                }
                let (_, d6, _) =
                    tangent[..count].select_nth_unstable_by(GAP_NEIGHBOURS - 1, f32::total_cmp);
                (0.75 * *d6).clamp(r, 3.0 * r)
            })
            .collect()
    }
}
