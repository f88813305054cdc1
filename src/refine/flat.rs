//! The parallel refinement ([`super::refine`]): the reference's steps in flat storage (one
//! array per attribute, neighbourhoods and registrations in CSR form, kept in the chunks they
//! are built in), every pass but three spread over rayon in fixed chunks of points or
//! candidates, so the result does not depend on the thread count. The three sequential ones:
//! the inversion of the would-be registrations (a counting sort), the acceptance decision and
//! the moves of eq. 17-19. The candidates are made once, in place, at their counted size.
//!
//! By region (detail from the view), when at most a quarter of the points are open to the next
//! step, the neighbourhood update lists only the points near them ([`near_open`]): the finished
//! frame of the dam break at 640x480 takes its third step for 942 of 89,488 points, and its
//! update after the second step listed all of them (45 ms): refinement 93-99 -> 51-58 ms, the
//! same points (the reference, which lists every point, is the oracle in tests/refine.rs).
//!
//! The type 3 pass of the reference (§3.3) is sequential by nature: a child is checked against
//! the children accepted before it. It is reformulated so that only a cheap decision stays
//! sequential. A child `j` would register at the older point `q` if it were accepted exactly
//! when `q` lies in `U(j) = N1 ∪ N2` within `r_{i+1} + beta` of it, which depends on the older
//! points only; so the children that could hit candidate `k` (its *rivals*: earlier candidates
//! without a type 2 hit, within `beta` of `k`, whose `U` holds both of `k`'s parents) are found
//! in parallel, and the sequential pass only asks which rivals were accepted, taking the
//! nearest, ties to the earliest, as the reference does. Most candidates have no rival.
//!
//! The three sequential passes stay, measured (issue 36, this project's 2 cores, the dam break's
//! surface at three steps, 363,266 points; `bench refine`): the inversion is 21 of the step's
//! 60-70 ms of type 2 work, the decisions 3-10 ms, the moves 52 ms. Each was made parallel and
//! deterministic, and none paid: the inversion as a two-pass counting sort over fixed segments
//! of the sources (type 2 phase 59-71 -> 55-61 ms, but 22 MiB more peak memory, 68 -> 90 MiB);
//! the decisions in parallel rounds, each deciding the candidates whose rivals are all decided
//! (the reference's result exactly, but slower: the splashing frame's acceptance 4.6-4.9 -> 6.8-7.0
//! ms, the sequential pass being one cheap sweep); the moves in slabs along the longest axis,
//! even slabs at once then odd ones, each keeping its own moved points apart (deterministic, not
//! the reference's order), where every read of a point a move sees must ask whether its slab
//! moved it: an unpredictable branch that doubled the work per move (115 ms on one thread for
//! the sweep's 52; 58 ms on two cores). On more cores the slabs would pay; on two the sweep
//! stays, and the step keeps the reference's result point for point.

use std::time::Instant;

use glam::Vec3;
use rayon::prelude::*;

use super::{
    BYTES_PER_POINT, Candidate, Levels, Lists, NeighbourLists, RADIUS_FACTOR, RefineError,
    RefineParams, Refined, StepStats, Target, apply_moves, candidates_of, caps_of, finish,
    for_each_new_neighbour, initial_neighbours, may_pair, open_to, pairs_of, radii_after,
    run_steps,
};

/// Items per parallel task: fixed, so that the output does not depend on the thread count.
const CHUNK: usize = 512;
/// No point, no candidate.
const NONE: u32 = u32::MAX;

/// Lists in compressed sparse rows, kept in the chunks of [`CHUNK`] lists they are built in
/// (in parallel): list `i` is `items[ends[j]..ends[j + 1]]` of chunk `i / CHUNK`, `j = i % CHUNK`.
/// No concatenation after a parallel build (which held every list twice at its peak), and the
/// ends are `u32`, relative to the chunk.
#[derive(Clone, Debug, Default)]
pub(super) struct Csr {
    n: usize,
    chunks: Vec<Chunk>,
}

/// [`CHUNK`] lists (the last chunk fewer): `ends` starts at 0 and has one more entry than lists.
#[derive(Clone, Debug, Default)]
struct Chunk {
    ends: Vec<u32>,
    items: Vec<u32>,
}

impl Lists for Csr {
    #[inline]
    fn of(&self, i: usize) -> &[u32] {
        let c = &self.chunks[i / CHUNK];
        let j = i % CHUNK;
        &c.items[c.ends[j] as usize..c.ends[j + 1] as usize]
    }
}

/// A chunk-relative item offset as a `u32`. A chunk holds the lists of [`CHUNK`] points or
/// candidates; 2^32 items there would be 16 GiB of one chunk's lists, beyond the memory budget
/// checked before every step.
fn chunk_offset(n: usize) -> u32 {
    u32::try_from(n).expect("a chunk of lists holds fewer than 2^32 items")
}

impl Csr {
    /// `n` empty lists.
    fn empty(n: usize) -> Self {
        Self::build(n, |_, _| {})
    }

    /// Number of lists.
    pub(super) fn len(&self) -> usize {
        self.n
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
        let parts: Vec<(Chunk, Vec<T>)> = (0..n.div_ceil(CHUNK))
            .into_par_iter()
            .map(|c| {
                let range = c * CHUNK..((c + 1) * CHUNK).min(n);
                let mut ends = Vec::with_capacity(range.len() + 1);
                let mut values = Vec::with_capacity(range.len());
                ends.push(0);
                let mut items = Vec::new();
                for i in range {
                    values.push(fill(i, &mut items));
                    ends.push(chunk_offset(items.len()));
                }
                items.shrink_to_fit();
                (Chunk { ends, items }, values)
            })
            .collect();
        let mut values = Vec::with_capacity(n);
        let mut chunks = Vec::with_capacity(parts.len());
        for (chunk, v) in parts {
            chunks.push(chunk);
            values.extend(v);
        }
        (Self { n, chunks }, values)
    }

    /// Lists of `n` keys from `(key, value)` pairs, each list in the order the pairs come
    /// (a counting sort; `pairs` is called twice and must emit the same pairs both times).
    fn group(n: usize, pairs: impl Fn(&mut dyn FnMut(u32, u32))) -> Self {
        let mut next = vec![0u32; n];
        pairs(&mut |k, _| next[k as usize] += 1);
        let chunks = (0..n.div_ceil(CHUNK))
            .map(|c| {
                let range = c * CHUNK..((c + 1) * CHUNK).min(n);
                let mut ends = Vec::with_capacity(range.len() + 1);
                let mut end = 0usize;
                ends.push(0);
                for k in range {
                    let count = next[k] as usize;
                    // where key k's items start, then (second pass) where its next one goes
                    next[k] = chunk_offset(end);
                    end += count;
                    ends.push(chunk_offset(end));
                }
                Chunk {
                    ends,
                    items: vec![0; end],
                }
            })
            .collect::<Vec<_>>();
        let mut csr = Self { n, chunks };
        pairs(&mut |k, v| {
            let k = k as usize;
            csr.chunks[k / CHUNK].items[next[k] as usize] = v;
            next[k] += 1;
        });
        csr
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
    /// the most steps of each point's region
    cap: Vec<u8>,
    /// neighbours within the current radius, sorted ascending
    nb: Csr,
}

/// The step's candidates in (first point, neighbour) order, stored once (no second copy of the
/// largest array of the step), with the number of pairs that gave no child. A first parallel
/// pass counts each point's pairs (a distance test each), a second makes the candidates in
/// place, a pair without a child leaving a hole that a last pass closes. The count is checked
/// against the memory budget before the candidates are kept.
fn make_candidates(
    pts: &Points,
    params: &RefineParams,
    r: f32,
    step: u32,
) -> Result<(Vec<Candidate>, usize), RefineError> {
    let n_old = pts.pos.len();
    let r_next = r * RADIUS_FACTOR;
    let chunks = n_old.div_ceil(CHUNK);
    let range = |c: usize| c * CHUNK..((c + 1) * CHUNK).min(n_old);
    let pairs: Vec<usize> = (0..chunks)
        .into_par_iter()
        .map(|c| {
            range(c)
                .map(|p1| pairs_of(&pts.pos, &pts.cap, pts.nb.of(p1), p1, r_next, step).count())
                .sum()
        })
        .collect();
    let mut candidates = vec![Candidate::default(); pairs.iter().sum()];
    let mut shares = Vec::with_capacity(chunks);
    let mut rest = candidates.as_mut_slice();
    for &n in &pairs {
        let (share, tail) = rest.split_at_mut(n);
        shares.push(share);
        rest = tail;
    }
    let hole = Candidate {
        p2: NONE,
        ..Candidate::default()
    };
    let no_normal: usize = shares
        .into_par_iter()
        .enumerate()
        .map(|(c, share)| {
            let mut out = Vec::with_capacity(share.len());
            let mut none = 0;
            for p1 in range(c) {
                let n = candidates_of(
                    &pts.pos,
                    &pts.nrm,
                    &pts.cap,
                    pts.nb.of(p1),
                    p1,
                    params,
                    r,
                    step,
                    &mut out,
                );
                out.extend(std::iter::repeat_n(hole, n));
                none += n;
            }
            share.copy_from_slice(&out);
            none
        })
        .sum();
    if no_normal > 0 {
        candidates.retain(|c| c.p2 != NONE);
    }
    // every new point is the child of one candidate pair: the bound is known before the work
    let predicted = n_old + candidates.len();
    if predicted as u128 * BYTES_PER_POINT as u128 > params.memory_budget as u128 {
        return Err(RefineError::OverBudget {
            step,
            steps: params.steps,
            predicted,
            points: n_old,
            budget: params.memory_budget,
        });
    }
    Ok((candidates, no_normal))
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

/// Each candidate's type 2 hit ([`NONE`] if none) and, for each older point `q`, the candidates
/// without a hit that would be registered at `q` if accepted, ascending: the per-candidate lists
/// of [`type2_and_registrations`], made in parallel, inverted by a counting sort.
fn hits_and_registrations(
    pts: &Points,
    candidates: &[Candidate],
    beta: f32,
    reach: f32,
) -> (Vec<u32>, Csr) {
    let (pos, nb) = (&pts.pos, &pts.nb);
    let (would, hits) = Csr::build_with(candidates.len(), |k, out| {
        let c = &candidates[k];
        let (n1, n2) = (nb.of(c.p1 as usize), nb.of(c.p2 as usize));
        type2_and_registrations(pos, n1, n2, c, beta, reach, out)
    });
    let at = Csr::group(pos.len(), |emit| {
        for k in 0..candidates.len() {
            for &q in would.of(k) {
                emit(q, k as u32);
            }
        }
    });
    (hits, at)
}

/// What the acceptance pass decided, as candidate indices.
struct Decision {
    accepted: Vec<u32>,
    moves: Vec<(Target, u32)>,
    /// accepted children (their rank in `accepted`) registered at each older point, in
    /// acceptance order
    registered: Csr,
    type2: usize,
    type3: usize,
}

/// Type 3 checks, acceptance and registration: the reference's pass in candidate order,
/// reformulated (module docs) so that all but the decision runs in parallel. `at`: the
/// candidates that would register at each older point, ascending
/// ([`hits_and_registrations`]); `None` when collisions are off.
fn decide(candidates: &[Candidate], hits: &[u32], at: Option<Csr>, beta: f32) -> Decision {
    let Some(at) = at else {
        return Decision {
            accepted: (0..candidates.len() as u32).collect(),
            moves: Vec::new(),
            registered: Csr::empty(0),
            type2: 0,
            type3: 0,
        };
    };
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
            d.moves.push((Target::Old(hits[k]), k as u32));
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
            d.moves.push((Target::New(a), k as u32));
            continue;
        }
        index[k] = d.accepted.len() as u32;
        d.accepted.push(k as u32);
    }
    drop(rivals);
    d.registered = Csr::build(at.len(), |q, out| {
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
///
/// `near`: by region, the points whose lists the steps to come can read ([`near_open`]); the
/// others get empty lists (`None`: every point's list).
fn update(
    pts: &Points,
    candidates: &[Candidate],
    accepted: &[u32],
    n_old: usize,
    r_next: f32,
    near: Option<&Near>,
) -> Csr {
    let r2 = r_next * r_next;
    let (pos, nb) = (&pts.pos, &pts.nb);
    let listed = |p: usize| near.is_none_or(|n| n.points[p]);
    let child_listed = |p: usize| near.is_none_or(|n| n.children[p]);
    let children_of = Csr::group(n_old, |emit| {
        for (a, &k) in accepted.iter().enumerate() {
            let c = &candidates[k as usize];
            emit(c.p1, a as u32);
            emit(c.p2, a as u32);
        }
    });
    // each child's list: old points (type 2) then children (type 3), sorted
    let lists = Csr::build(accepted.len(), |k, out| {
        if !child_listed(n_old + k) {
            return;
        }
        let c = &candidates[accepted[k] as usize];
        let start = out.len();
        let g = (n_old + k) as u32;
        for_each_new_neighbour(pos, nb, &children_of, c, g, n_old, r_next, |q| out.push(q));
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
        if !listed(p) {
            return;
        }
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

/// How far from the points open to the next step (their region takes it) a point's list may
/// still be read, in radii `r` of the lists made for that step: the step reads the lists of
/// its pairs' points (within `r` of an open point) and of the older points they may move
/// (`2 r`); the update after it lists the points within `NEAR_RADII * F r` of the points open
/// to the step after (each within `r` of one open now), reading their own lists (`5.3 r`) and
/// the lists of the parents of the children within one more radius of them (`6.9 r`); the
/// points move less than a radius meanwhile. Eight leaves room.
const NEAR_RADII: f32 = 8.0;

/// The points whose lists the steps to come can read, when few points are open to them: the
/// points within [`NEAR_RADII`] radii of an open point, and the children within one more
/// radius (an older point within reach gains the children near it, and needs their lists).
struct Near {
    points: Vec<bool>,
    children: Vec<bool>,
}

/// [`Near`] for the next step (lists of radius `r`) and the points `open` to it: `None` (every
/// list) unless at most a quarter of the points are open. Only the lists this leaves empty
/// differ from a whole update's, and the steps to come never read them: the same points, bit for
/// bit (tested against the reference, which updates every list).
fn near_open(pos: &[Vec3], open: &[usize], r: f32) -> Option<Near> {
    if open.len() * 4 > pos.len() || open.is_empty() {
        return None;
    }
    let open: Vec<Vec3> = open.iter().map(|&i| pos[i]).collect();
    let (reach, wider) = (NEAR_RADII * r, (NEAR_RADII + 1.0) * r);
    let grid = crate::neighbours::CellGrid::new(&open, wider).ok()?;
    let (points, children): (Vec<bool>, Vec<bool>) = pos
        .par_iter()
        .map(|&x| {
            let mut nearest = f32::INFINITY;
            grid.for_each_slot_within(x, wider, |_, q| {
                nearest = nearest.min(q.distance_squared(x));
            });
            (nearest <= reach * reach, nearest <= wider * wider)
        })
        .unzip();
    Some(Near { points, children })
}

/// One step (§3.2-3.4), the reference's result, and whether another step follows: one does
/// up to `last`, except, by region, where no point is left to pair ([`may_pair`]).
fn step_once(
    pts: &mut Points,
    params: &RefineParams,
    r: f32,
    (step, last): (u32, u32),
    by_region: bool,
) -> Result<(StepStats, bool), RefineError> {
    let t = Instant::now();
    let n_old = pts.pos.len();
    let (r_next, beta) = (r * RADIUS_FACTOR, params.collision_factor * r);
    let mut s = StepStats {
        step,
        radius: r,
        points_before: n_old,
        ..StepStats::default()
    };
    let (candidates, no_normal) = make_candidates(pts, params, r, step)?;
    s.different_surfaces = no_normal;
    s.candidates = candidates.len();
    s.phases.candidates_ms = t.elapsed().as_secs_f64() * 1e3;
    let phase = Instant::now();
    // type 2 hits depend on the older points only; with them, the older points each candidate
    // would register at, were it accepted
    let (hits, at) = if params.collisions {
        let (hits, at) = hits_and_registrations(pts, &candidates, beta, r_next + beta);
        (hits, Some(at))
    } else {
        (vec![NONE; candidates.len()], None)
    };
    s.phases.type2_ms = phase.elapsed().as_secs_f64() * 1e3;
    let phase = Instant::now();
    let d = decide(&candidates, &hits, at, beta);
    drop(hits);
    (s.collisions_type2, s.collisions_type3) = (d.type2, d.type3);
    s.resolved = d.moves.len();
    s.phases.accept_ms = phase.elapsed().as_secs_f64() * 1e3;
    let phase = Instant::now();
    let n_new = n_old + d.accepted.len();
    pts.pos.reserve_exact(n_new - pts.pos.len());
    pts.nrm.reserve_exact(n_new - pts.nrm.len());
    pts.step.reserve_exact(n_new - pts.step.len());
    pts.weight.reserve_exact(n_new - pts.weight.len());
    // a child's level: the higher of its parents'
    let caps: Vec<u8> = d
        .accepted
        .iter()
        .map(|&k| {
            let c = &candidates[k as usize];
            pts.cap[c.p1 as usize].max(pts.cap[c.p2 as usize])
        })
        .collect();
    pts.cap.extend(caps);
    for &k in &d.accepted {
        let c = &candidates[k as usize];
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
        d.moves.iter().map(|&(t, k)| (t, &candidates[k as usize])),
        |a| {
            let c = &candidates[d.accepted[a as usize] as usize];
            (c.p1, c.p2)
        },
        n_old,
        beta,
    );
    s.phases.moves_ms = phase.elapsed().as_secs_f64() * 1e3;
    drop((d.registered, d.moves));
    // by region, the next step only where a point open to it can pair, and then only the lists
    // near the points it refines
    let open = (step < last && by_region).then(|| open_to(&pts.cap, step + 1));
    let more = step < last && open.as_ref().is_none_or(|o| may_pair(&pts.pos, o, r_next));
    if more {
        let near = open.as_ref().and_then(|o| near_open(&pts.pos, o, r_next));
        pts.nb = update(pts, &candidates, &d.accepted, n_old, r_next, near.as_ref());
    }
    // no update after the last step (§3.4)
    s.points_after = pts.pos.len();
    s.phases.update_ms = phase.elapsed().as_secs_f64() * 1e3;
    s.ms = t.elapsed().as_secs_f64() * 1e3;
    Ok((s, more))
}

/// Runs the steps on validated input, each region to its level (`levels`, every point
/// `params.steps` without); `observe` sees the positions, neighbourhoods and radius after each
/// step's update (not after the last step, which has none).
pub(super) fn run(
    positions: &[Vec3],
    normals: &[Vec3],
    params: &RefineParams,
    levels: Option<Levels<'_>>,
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
    let (cap, last) = caps_of(params, positions.len(), levels);
    let mut pts = Points {
        pos: positions.to_vec(),
        nrm: normals.par_iter().map(|n| n.normalize_or_zero()).collect(),
        step: vec![0; n],
        weight: vec![params.original_weight; n],
        cap,
        nb: lists,
    };
    let radius_after = radii_after(params.initial_radius, last);
    let stats = run_steps(
        &mut pts,
        &radius_after,
        last,
        |pts, r, step| step_once(pts, params, r, (step, last), levels.is_some()),
        |pts, r| observe(&pts.pos, NeighbourLists::flat(&pts.nb), r),
    )?;
    drop(pts.nb);
    Ok(finish(
        pts.pos,
        pts.nrm,
        pts.step,
        pts.weight,
        &pts.cap,
        &isolated,
        params,
        stats,
        &radius_after,
        levels.is_some(),
    ))
}
