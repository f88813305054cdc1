//! The parallel refinement ([`super::refine`]): the reference's steps in flat storage (one
//! array per attribute, neighbourhoods and registrations in CSR form), every pass but the
//! acceptance and the moves spread over rayon in fixed chunks of points or candidates, so the
//! result does not depend on the thread count.
//!
//! The type 3 pass of the reference (§3.3) is sequential by nature: a child is checked against
//! the children accepted before it. It is reformulated so that only a cheap decision stays
//! sequential. A child `j` would register at the older point `q` if it were accepted exactly
//! when `q` lies in `U(j) = N1 ∪ N2` within `r_{i+1} + beta` of it, which depends on the older
//! points only; so the children that could hit candidate `k` (its *rivals*: earlier candidates
//! without a type 2 hit, within `beta` of `k`, whose `U` holds both of `k`'s parents) are found
//! in parallel, and the sequential pass only asks which rivals were accepted, taking the
//! nearest, ties to the earliest, as the reference does. Most candidates have no rival.

use std::time::Instant;

use glam::Vec3;
use rayon::prelude::*;

use super::{
    BYTES_PER_POINT, Candidate, Lists, NeighbourLists, RADIUS_FACTOR, RefineError, RefineParams,
    Refined, StepStats, Target, apply_moves, candidates_of, finish, initial_neighbours,
};

/// Items per parallel task: fixed, so that the output does not depend on the thread count.
const CHUNK: usize = 512;
/// No point, no candidate.
const NONE: u32 = u32::MAX;

/// Lists in compressed sparse rows: list `i` is `items[offsets[i]..offsets[i + 1]]`.
#[derive(Clone, Debug, Default)]
pub(super) struct Csr {
    offsets: Vec<usize>,
    items: Vec<u32>,
}

impl Lists for Csr {
    #[inline]
    fn of(&self, i: usize) -> &[u32] {
        &self.items[self.offsets[i]..self.offsets[i + 1]]
    }
}

impl Csr {
    /// `n` empty lists.
    fn empty(n: usize) -> Self {
        Self {
            offsets: vec![0; n + 1],
            items: Vec::new(),
        }
    }

    /// Number of lists.
    pub(super) fn len(&self) -> usize {
        self.offsets.len() - 1
    }

    /// Lists `0..n`, list `i` appended to `out` by `fill(i, out)`, in parallel over fixed chunks.
    fn build(n: usize, fill: impl Fn(usize, &mut Vec<u32>) + Sync) -> Self {
        Self::build_with(n, fill).0
    }

    /// [`Csr::build`] where `fill` also returns a value for each list.
    fn build_with<T: Send>(
        n: usize,
        fill: impl Fn(usize, &mut Vec<u32>) -> T + Sync,
    ) -> (Self, Vec<T>) {
        let parts: Vec<(Vec<usize>, Vec<u32>, Vec<T>)> = (0..n.div_ceil(CHUNK))
            .into_par_iter()
            .map(|c| {
                let range = c * CHUNK..((c + 1) * CHUNK).min(n);
                let mut ends = Vec::with_capacity(range.len());
                let mut values = Vec::with_capacity(range.len());
                let mut items = Vec::new();
                for i in range {
                    values.push(fill(i, &mut items));
                    ends.push(items.len());
                }
                (ends, items, values)
            })
            .collect();
        let mut offsets = Vec::with_capacity(n + 1);
        offsets.push(0);
        let mut items = Vec::with_capacity(parts.iter().map(|p| p.1.len()).sum());
        let mut values = Vec::with_capacity(n);
        for (ends, part, v) in parts {
            let base = items.len();
            offsets.extend(ends.iter().map(|e| base + e));
            items.extend_from_slice(&part);
            values.extend(v);
        }
        (Self { offsets, items }, values)
    }

    /// Lists of `n` keys from `(key, value)` pairs, each list in the order the pairs come
    /// (a counting sort; `pairs` is called twice and must emit the same pairs both times).
    fn group(n: usize, pairs: impl Fn(&mut dyn FnMut(u32, u32))) -> Self {
        let mut offsets = vec![0usize; n + 1];
        pairs(&mut |k, _| offsets[k as usize + 1] += 1);
        for i in 0..n {
            offsets[i + 1] += offsets[i];
        }
        let mut items = vec![0u32; offsets[n]];
        let mut next = offsets[..n].to_vec();
        pairs(&mut |k, v| {
            items[next[k as usize]] = v;
            next[k as usize] += 1;
        });
        Self { offsets, items }
    }
}

/// Sorts the tail `out[start..]` and removes its repeats.
fn sort_dedup_tail(out: &mut Vec<u32>, start: usize) {
    out[start..].sort_unstable();
    let mut w = start;
    for i in start..out.len() {
        if w == start || out[i] != out[w - 1] {
            out[w] = out[i];
            w += 1;
        }
    }
    out.truncate(w);
}

/// Point data carried between steps.
struct Points {
    pos: Vec<Vec3>,
    nrm: Vec<Vec3>,
    step: Vec<u8>,
    weight: Vec<f32>,
    /// neighbours within the current radius, sorted ascending
    nb: Csr,
}

/// A candidate's type 2 hit, exactly as `type2_hit` finds it, and, when there is none, the older
/// points it would register at if accepted (`for_each_registration_unique`), appended to `out`:
/// one merge of `N1` and `N2` for both, their intersection being part of the union.
fn type2_and_registrations(
    pos: &[Vec3],
    n1: &[u32],
    n2: &[u32],
    c: &Candidate,
    beta: f32,
    reach: f32,
    out: &mut Vec<u32>,
) -> u32 {
    let (beta2, reach2) = (beta * beta, reach * reach);
    let start = out.len();
    let mut best: Option<(f32, u32)> = None;
    let (mut i, mut j) = (0, 0);
    while i < n1.len() && j < n2.len() {
        let (x, y) = (n1[i], n2[j]);
        let q = x.min(y);
        let d2 = pos[q as usize].distance_squared(c.pos);
        if x == y && d2 < beta2 && best.is_none_or(|(bd, _)| d2 < bd) {
            best = Some((d2, q));
        }
        if d2 < reach2 {
            out.push(q);
        }
        i += usize::from(x <= y);
        j += usize::from(y <= x);
    }
    for &q in n1[i..].iter().chain(&n2[j..]) {
        if pos[q as usize].distance_squared(c.pos) < reach2 {
            out.push(q);
        }
    }
    match best {
        Some((_, q)) => {
            out.truncate(start);
            q
        }
        None => NONE,
    }
}

/// What the acceptance pass decided.
struct Decision {
    accepted: Vec<Candidate>,
    moves: Vec<(Target, Candidate)>,
    /// accepted children registered at each older point, in acceptance order
    registered: Csr,
    type2: usize,
    type3: usize,
}

/// Type 3 checks, acceptance and registration: the reference's pass in candidate order,
/// reformulated (module docs) so that all but the decision runs in parallel.
fn decide(
    n_old: usize,
    candidates: &[Candidate],
    hits: &[u32],
    would: Option<Csr>,
    beta: f32,
) -> Decision {
    let Some(would) = would else {
        return Decision {
            accepted: candidates.to_vec(),
            moves: Vec::new(),
            registered: Csr::empty(n_old),
            type2: 0,
            type3: 0,
        };
    };
    // inverted: the candidates that would register at each older point, in candidate order
    let at = Csr::group(n_old, |emit| {
        for k in 0..candidates.len() {
            for &q in would.of(k) {
                emit(q, k as u32);
            }
        }
    });
    drop(would);
    // each candidate's rivals: earlier candidates within beta registered at both its parents
    let beta2 = beta * beta;
    let rivals = Csr::build(candidates.len(), |k, out| {
        let c = &candidates[k];
        if hits[k] != NONE {
            return;
        }
        // `at` lists ascend: the earlier candidates are a prefix; the rare ones near enough are
        // then looked up at the other parent
        let at2 = at.of(c.p2 as usize);
        for &j in at.of(c.p1 as usize) {
            if j as usize >= k {
                break;
            }
            if candidates[j as usize].pos.distance_squared(c.pos) < beta2
                && at2.binary_search(&j).is_ok()
            {
                out.push(j);
            }
        }
    });
    let mut index = vec![NONE; candidates.len()];
    let mut d = Decision {
        accepted: Vec::new(),
        moves: Vec::new(),
        registered: Csr::empty(0),
        type2: 0,
        type3: 0,
    };
    for (k, c) in candidates.iter().enumerate() {
        if hits[k] != NONE {
            d.type2 += 1;
            d.moves.push((Target::Old(hits[k]), *c));
            continue;
        }
        // nearest accepted rival, ties to the earliest (rivals are in candidate order)
        let mut best: Option<(f32, u32)> = None;
        for &j in rivals.of(k) {
            let a = index[j as usize];
            if a != NONE {
                let d2 = candidates[j as usize].pos.distance_squared(c.pos);
                if best.is_none_or(|(bd, _)| d2 < bd) {
                    best = Some((d2, a));
                }
            }
        }
        if let Some((_, a)) = best {
            d.type3 += 1;
            d.moves.push((Target::New(a), *c));
            continue;
        }
        index[k] = d.accepted.len() as u32;
        d.accepted.push(*c);
    }
    d.registered = Csr::build(n_old, |q, out| {
        out.extend(
            at.of(q)
                .iter()
                .map(|&k| index[k as usize])
                .filter(|&a| a != NONE),
        );
    });
    d
}

/// The neighbourhoods within `r_next` after the step (§3.4), as in the reference: type 1 by
/// filtering the old lists, types 2 and 3 from `U` of each child's parents and the children of
/// the points in `U`.
fn update(pts: &Points, accepted: &[Candidate], n_old: usize, r_next: f32) -> Csr {
    let r2 = r_next * r_next;
    let (pos, nb) = (&pts.pos, &pts.nb);
    let children_of = Csr::group(n_old, |emit| {
        for (a, c) in accepted.iter().enumerate() {
            emit(c.p1, a as u32);
            emit(c.p2, a as u32);
        }
    });
    // each child's list: old points (type 2) then children (type 3), sorted
    let lists = Csr::build(accepted.len(), |k, out| {
        let c = &accepted[k];
        let g = (n_old + k) as u32;
        let x = pos[g as usize];
        let start = out.len();
        for &q in [c.p1, c.p2]
            .iter()
            .chain(nb.of(c.p1 as usize))
            .chain(nb.of(c.p2 as usize))
        {
            if pos[q as usize].distance_squared(x) <= r2 {
                out.push(q);
            }
            for &k2 in children_of.of(q as usize) {
                let g2 = (n_old + k2 as usize) as u32;
                if g2 != g && pos[g2 as usize].distance_squared(x) <= r2 {
                    out.push(g2);
                }
            }
        }
        sort_dedup_tail(out, start);
    });
    // type 2, the other way round: old points gain the children near them, in index order
    let gained = Csr::group(n_old, |emit| {
        for k in 0..accepted.len() {
            let g = (n_old + k) as u32;
            for &q in lists.of(k).iter().take_while(|&&q| (q as usize) < n_old) {
                emit(q, g);
            }
        }
    });
    Csr::build(pos.len(), |p, out| {
        if p < n_old {
            // type 1: old relations that survive the smaller radius
            out.extend(
                nb.of(p)
                    .iter()
                    .filter(|&&q| pos[q as usize].distance_squared(pos[p]) <= r2),
            );
            out.extend_from_slice(gained.of(p));
        } else {
            out.extend_from_slice(lists.of(p - n_old));
        }
    })
}

/// One step (§3.2-3.4), the reference's result.
fn step_once(
    pts: &mut Points,
    params: &RefineParams,
    r: f32,
    step: u32,
) -> Result<StepStats, RefineError> {
    let t = Instant::now();
    let n_old = pts.pos.len();
    let (r_next, beta) = (r * RADIUS_FACTOR, params.collision_factor * r);
    let mut s = StepStats {
        step,
        radius: r,
        points_before: n_old,
        ..StepStats::default()
    };
    // candidates, in (first point, neighbour) order
    let parts: Vec<(Vec<Candidate>, usize)> = (0..n_old.div_ceil(CHUNK))
        .into_par_iter()
        .map(|c| {
            let mut out = Vec::new();
            let mut none = 0;
            for p1 in c * CHUNK..((c + 1) * CHUNK).min(n_old) {
                none += candidates_of(&pts.pos, &pts.nrm, pts.nb.of(p1), p1, params, r, &mut out);
            }
            (out, none)
        })
        .collect();
    s.different_surfaces = parts.iter().map(|p| p.1).sum();
    s.candidates = parts.iter().map(|p| p.0.len()).sum();
    // every new point is the child of one candidate pair: the bound is known before the work
    let predicted = n_old + s.candidates;
    if predicted as u128 * BYTES_PER_POINT as u128 > params.memory_budget as u128 {
        return Err(RefineError::OverBudget {
            step,
            steps: params.steps,
            predicted,
            points: n_old,
            budget: params.memory_budget,
        });
    }
    let mut candidates = Vec::with_capacity(s.candidates);
    for (part, _) in parts {
        candidates.extend_from_slice(&part);
    }
    s.phases.candidates_ms = t.elapsed().as_secs_f64() * 1e3;
    let phase = Instant::now();
    // type 2 hits depend on the older points only; with them, the older points each candidate
    // would register at, were it accepted
    let (would, hits) = if params.collisions {
        let (pos, nb) = (&pts.pos, &pts.nb);
        let (would, hits) = Csr::build_with(candidates.len(), |k, out| {
            let c = &candidates[k];
            let (n1, n2) = (nb.of(c.p1 as usize), nb.of(c.p2 as usize));
            type2_and_registrations(pos, n1, n2, c, beta, r_next + beta, out)
        });
        (Some(would), hits)
    } else {
        (None, vec![NONE; candidates.len()])
    };
    s.phases.type2_ms = phase.elapsed().as_secs_f64() * 1e3;
    let phase = Instant::now();
    let d = decide(n_old, &candidates, &hits, would, beta);
    drop((candidates, hits));
    (s.collisions_type2, s.collisions_type3) = (d.type2, d.type3);
    s.resolved = d.moves.len();
    s.phases.accept_ms = phase.elapsed().as_secs_f64() * 1e3;
    let phase = Instant::now();
    for c in &d.accepted {
        pts.pos.push(c.pos);
        pts.nrm.push(c.nrm);
        pts.step.push(step as u8);
        pts.weight.push(c.weight);
    }
    s.moved = apply_moves(
        &mut pts.pos,
        &mut pts.nrm,
        &mut pts.weight,
        &pts.nb,
        &d.registered,
        &d.moves,
        &d.accepted,
        n_old,
        beta,
    );
    s.phases.moves_ms = phase.elapsed().as_secs_f64() * 1e3;
    drop(d.registered);
    if step < params.steps {
        pts.nb = update(pts, &d.accepted, n_old, r_next);
    }
    // no update after the last step (§3.4)
    s.points_after = pts.pos.len();
    s.phases.update_ms = phase.elapsed().as_secs_f64() * 1e3;
    s.ms = t.elapsed().as_secs_f64() * 1e3;
    Ok(s)
}

/// Runs the steps on validated input; `observe` sees the positions, neighbourhoods and radius
/// after each step's update (not after the last step, which has none).
pub(super) fn run(
    positions: &[Vec3],
    normals: &[Vec3],
    params: &RefineParams,
    mut observe: impl FnMut(&[Vec3], NeighbourLists<'_>, f32),
) -> Result<Refined, RefineError> {
    let nb = initial_neighbours(positions, params)?;
    let lists = Csr::build(positions.len(), |i, out| {
        let start = out.len();
        out.extend_from_slice(nb.of(i));
        out[start..].sort_unstable();
    });
    drop(nb);
    let n = positions.len();
    let isolated: Vec<bool> = (0..n).map(|i| lists.of(i).is_empty()).collect();
    let mut pts = Points {
        pos: positions.to_vec(),
        nrm: normals.par_iter().map(|n| n.normalize_or_zero()).collect(),
        step: vec![0; n],
        weight: vec![params.original_weight; n],
        nb: lists,
    };
    let mut stats = Vec::new();
    let mut r = params.initial_radius;
    for step in 1..=params.steps {
        stats.push(step_once(&mut pts, params, r, step)?);
        r *= RADIUS_FACTOR;
        if step < params.steps {
            observe(&pts.pos, NeighbourLists::flat(&pts.nb), r);
        }
    }
    drop(pts.nb);
    Ok(finish(
        pts.pos, pts.nrm, pts.step, pts.weight, &isolated, params, stats, r,
    ))
}
