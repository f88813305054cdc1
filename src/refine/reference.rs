//! The reference refinement: the steps of §3.2-3.4 as the paper describes them, on one thread,
//! one `Vec` of neighbours per point. It is the specification the parallel refinement
//! ([`super::flat`]) is tested against: same points, same order.
//!
//! Type 3 collisions and registrations run in one pass in candidate order, as §3.3 describes:
//! pairs in order of their first point, each child checked against the older points of
//! `N1 ∩ N2` (type 2) and against the children registered so far at both parents (type 3).

use std::time::Instant;

use glam::Vec3;

use super::{
    BYTES_PER_POINT, Candidate, Levels, NeighbourLists, RADIUS_FACTOR, RefineError, RefineParams,
    Refined, StepStats, Target, apply_moves, candidates_of, caps_of, finish, for_each_common,
    for_each_new_neighbour, for_each_registration_unique, initial_neighbours, may_pair, open_to,
    radii_after, run_steps, type2_hit,
};

/// Point data carried between steps.
struct Points {
    pos: Vec<Vec3>,
    nrm: Vec<Vec3>,
    step: Vec<u8>,
    weight: Vec<f32>,
    /// the most steps of each point's region
    cap: Vec<u8>,
    /// neighbours within the current radius, sorted ascending
    nb: Vec<Vec<u32>>,
}

/// Nearest child of this step within `beta` among those registered at both parents
/// (type 3: `S = R1 ∩ R2`), ties to the earliest.
fn type3_hit(
    registered: &[Vec<u32>],
    accepted: &[Candidate],
    c: &Candidate,
    beta: f32,
) -> Option<u32> {
    let mut best: Option<(f32, u32)> = None;
    for_each_common(
        &registered[c.p1 as usize],
        &registered[c.p2 as usize],
        |k| {
            let d2 = accepted[k as usize].pos.distance_squared(c.pos);
            if d2 < beta * beta && best.is_none_or(|(bd, _)| d2 < bd) {
                best = Some((d2, k));
            }
        },
    );
    best.map(|(_, k)| k)
}

/// Appends the accepted children, applies the moves and, unless this was the last step,
/// updates every neighbourhood to `r_next` (§3.4) from the step's relations: type 1 by filtering
/// the old lists, types 2 and 3 from `U` of each child's parents and the children of the points
/// in `U`, unless this is the last step (`last`, or by region where no point is left to pair,
/// [`may_pair`]). Returns the points moved, the milliseconds of the moves and whether another
/// step follows.
#[allow(clippy::too_many_arguments)] // one step's state, passed once
fn append_and_update(
    pts: &mut Points,
    accepted: &[Candidate],
    moves: &[(Target, Candidate)],
    registered: &[Vec<u32>],
    children_of: &[Vec<u32>],
    step: u8,
    r_next: f32,
    beta: f32,
    (step_number, last, by_region): (u32, u32, bool),
) -> (usize, f64, bool) {
    let n_old = pts.pos.len();
    for c in accepted {
        // a child's level: the higher of its parents'
        pts.cap
            .push(pts.cap[c.p1 as usize].max(pts.cap[c.p2 as usize]));
        pts.pos.push(c.pos);
        pts.nrm.push(c.nrm);
        pts.step.push(step);
        pts.weight.push(c.weight);
    }
    let t = Instant::now();
    let moved = apply_moves(
        &mut pts.pos,
        &mut pts.nrm,
        &mut pts.weight,
        pts.nb.as_slice(),
        registered,
        moves.iter().map(|(t, c)| (*t, c)),
        |k| (accepted[k as usize].p1, accepted[k as usize].p2),
        n_old,
        beta,
    );
    let moves_ms = t.elapsed().as_secs_f64() * 1e3;
    let more = step_number < last
        && (!by_region || may_pair(&pts.pos, &open_to(&pts.cap, step_number + 1), r_next));
    if !more {
        // no update after the last step (§3.4)
        pts.nb.resize(pts.pos.len(), Vec::new());
        return (moved, moves_ms, false);
    }
    let r2 = r_next * r_next;
    let pos = &pts.pos;
    let nb = &pts.nb;
    let lists: Vec<(Vec<u32>, Vec<u32>)> = (0..accepted.len())
        .map(|k| {
            let g = (n_old + k) as u32;
            let mut old = Vec::new();
            let mut new = Vec::new();
            for_each_new_neighbour(
                pos,
                nb.as_slice(),
                children_of,
                &accepted[k],
                g,
                n_old,
                r_next,
                |q| {
                    // type 2, type 3
                    if (q as usize) < n_old {
                        old.push(q)
                    } else {
                        new.push(q)
                    }
                },
            );
            old.sort_unstable();
            old.dedup();
            new.sort_unstable();
            new.dedup();
            (old, new)
        })
        .collect();
    // type 2, the other way round: old points gain the children near them
    let mut pairs: Vec<(u32, u32)> = lists
        .iter()
        .enumerate()
        .flat_map(|(k, (old, _))| old.iter().map(move |&q| (q, (n_old + k) as u32)))
        .collect();
    pairs.sort_unstable();
    // type 1: old relations that survive the smaller radius
    let pos = &pts.pos;
    for (p, list) in pts.nb.iter_mut().enumerate() {
        list.retain(|&q| pos[q as usize].distance_squared(pos[p]) <= r2);
    }
    for &(q, g) in &pairs {
        pts.nb[q as usize].push(g); // children have higher indices: the lists stay sorted
    }
    for (mut old, new) in lists {
        old.extend(new); // old indices < n_old <= new indices: sorted
        pts.nb.push(old);
    }
    (moved, moves_ms, true)
}

/// One step (§3.2-3.4).
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
    // candidates, in (first point, neighbour) order
    let mut candidates = Vec::new();
    for p1 in 0..n_old {
        s.different_surfaces += candidates_of(
            &pts.pos,
            &pts.nrm,
            &pts.cap,
            &pts.nb[p1],
            p1,
            params,
            r,
            step,
            &mut candidates,
        );
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
    s.candidates = candidates.len();
    s.phases.candidates_ms = t.elapsed().as_secs_f64() * 1e3;
    let phase = Instant::now();
    // type 2 hits depend on the older points only
    let hits: Vec<Option<u32>> = if params.collisions {
        candidates
            .iter()
            .map(|c| {
                type2_hit(
                    &pts.pos,
                    &pts.nb[c.p1 as usize],
                    &pts.nb[c.p2 as usize],
                    c,
                    beta,
                )
            })
            .collect()
    } else {
        vec![None; candidates.len()]
    };
    s.phases.type2_ms = phase.elapsed().as_secs_f64() * 1e3;
    let phase = Instant::now();
    // type 3, acceptance and registration, in candidate order
    let mut registered: Vec<Vec<u32>> = vec![Vec::new(); n_old];
    let mut children_of: Vec<Vec<u32>> = vec![Vec::new(); n_old];
    let mut accepted: Vec<Candidate> = Vec::new();
    let mut moves: Vec<(Target, Candidate)> = Vec::new();
    for (k, c) in candidates.iter().enumerate() {
        if let Some(q) = hits[k] {
            s.collisions_type2 += 1;
            moves.push((Target::Old(q), *c));
            continue;
        }
        if params.collisions
            && let Some(j) = type3_hit(&registered, &accepted, c, beta)
        {
            s.collisions_type3 += 1;
            moves.push((Target::New(j), *c));
            continue;
        }
        let a = accepted.len() as u32;
        let (n1, n2) = (&pts.nb[c.p1 as usize], &pts.nb[c.p2 as usize]);
        for_each_registration_unique(&pts.pos, n1, n2, c, r_next + beta, |q| {
            registered[q as usize].push(a)
        });
        children_of[c.p1 as usize].push(a);
        children_of[c.p2 as usize].push(a);
        accepted.push(*c);
    }
    s.resolved = moves.len();
    s.phases.accept_ms = phase.elapsed().as_secs_f64() * 1e3;
    let phase = Instant::now();
    let more;
    (s.moved, s.phases.moves_ms, more) = append_and_update(
        pts,
        &accepted,
        &moves,
        &registered,
        &children_of,
        step as u8,
        r_next,
        beta,
        (step, last, by_region),
    );
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
    let (cap, last) = caps_of(params, positions.len(), levels);
    let mut pts = Points {
        pos: positions.to_vec(),
        nrm: normals.iter().map(|n| n.normalize_or_zero()).collect(),
        step: vec![0; positions.len()],
        weight: vec![params.original_weight; positions.len()],
        cap,
        nb: (0..positions.len())
            .map(|i| {
                let mut v = nb.of(i).to_vec();
                v.sort_unstable();
                v
            })
            .collect(),
    };
    drop(nb);
    let isolated: Vec<bool> = pts.nb.iter().map(Vec::is_empty).collect();
    let radius_after = radii_after(params.initial_radius, last);
    let stats = run_steps(
        &mut pts,
        &radius_after,
        last,
        |pts, r, step| step_once(pts, params, r, (step, last), levels.is_some()),
        |pts, r| observe(&pts.pos, NeighbourLists::nested(&pts.nb), r),
    )?;
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
