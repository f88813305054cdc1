// The boundary calibration on the GPU (issue 37): the twin of `pipeline::boundary`
// (src/pipeline/boundary/mod.rs derives the rule). Every point carries two weights, `split`:
// its share in the interior (x) and its own weight as a sheet point (y), the sheet's weight
// multiplied by the w_j solved here. Each sheet point j gets the w_j that puts the density at
// its target, half a spacing out along its normal, at the iso-value, solved by Jacobi steps
// from w = 1; a lone point gets the weight of a ball of one particle's volume, blended by how
// alone it is. Given the leading `particles` points as the particles themselves (with their
// classes), `thin_pass` and `factors_pass` first find the split: how flat and exposed each
// particle's neighbourhood is (a sheet one particle thick), how buried each point is
// (`chain_input_at_boundary`'s factors); the CPU then uploads no weight at all. The points are
// binned as the gather pass bins them (`BinnedPoints`), each carrying its index in the
// chain's order. Sums are written, not blended: no atomics, the order of the terms fixed by the
// bins, so runs are reproducible.

struct WeightParams {
    // the bins' origin and side, their counts and the bins searched on each side
    bin_origin: vec3<f32>,
    bin_size: f32,
    bins: vec3<u32>,
    reach: u32,
    // the reference radius's kernel constant (`kernel_constant`) and the kernel (0: Wyvill,
    // 1: cubic spline)
    constant: f32,
    kernel: u32,
    // the leading points that are the particles, whose factors `thin_pass` and `factors_pass`
    // find (0: the split is given); all points
    particles: u32,
    count: u32,
    // half a spacing, the iso-value, a lone ball's radius squared, the largest weight
    half_spacing: f32,
    tau: f32,
    lone_r2: f32,
    max_weight: f32,
    // the burial's distance and the half width of its smoothsteps, in spacings (`BURIED`,
    // `BAND`)
    buried: f32,
    band: f32,
    // the points that may have an interior share (the leading ones: index < leading, first in
    // every bin), and the others' (the sheet's) largest radius (negative: every bin within the
    // bins' reach read whole, the search the trimmed one must equal, `BinSearch::Whole`)
    leading: u32,
    sheet_radius: f32,
}


// a point as a sheet point: position and kernel radius (w); outward normal (zero: none; the
// particles' found by `thin_pass`), w unused
struct SheetPoint {
    at: vec4<f32>,
    normal: vec4<f32>,
}

// a sheet point's target and how alone it is (w); its lone ball's weight; the interior's
// density at the target
struct Target {
    at: vec4<f32>,
    lone: f32,
    inside: f32,
    pad0: f32,
    pad1: f32,
}

@group(0) @binding(0) var<uniform> params: WeightParams;
@group(0) @binding(1) var<storage, read> points: array<IndexedPoint>;
@group(0) @binding(2) var<storage, read> bin_start: array<u32>;
@group(0) @binding(3) var<storage, read> sheet: array<SheetPoint>;
@group(0) @binding(4) var<storage, read_write> targets: array<Target>;
@group(0) @binding(5) var<storage, read> w_in: array<f32>;
@group(0) @binding(6) var<storage, read_write> w_out: array<f32>;
@group(0) @binding(8) var<storage, read> split: array<vec2<f32>>;

// Whether every bin within the bins' reach is read whole (`BinSearch::Whole`).
fn whole_search() -> bool {
    return params.sheet_radius < 0.0;
}

// The bins of row (by, bz) to read around x for terms within `radius`: `row_span`'s, or the
// range's whole row.
fn span_of(x: vec3<f32>, range: BinRange, by: i32, bz: i32, radius: f32) -> vec2<i32> {
    if whole_search() {
        return vec2<i32>(range.lo.x, range.hi.x);
    }
    return row_span(x, params.bin_origin, params.bin_size, range, by, bz, radius);
}

// The densities at x of the interior (x) and of the sheet (y), the sheet's weights times the
// current `w_in` when `weighted` (then the interior's is left partial: its caller reads the
// sheet's alone); without `with_sheet` only the leading points are summed (the interior's
// density is theirs alone: the others have no interior share).
//
// Each row of bins is read only where the ball of the largest radius around x reaches it
// (`span_of`), and the sheet's points (index >= leading) only in the bins the ball of the
// sheet's largest radius reaches: a sheet point elsewhere lies farther from x than its radius,
// so its kernel is 0 and its term +0. Those bins are read up to their first sheet point (the
// leading points come first in every bin: the bins keep the chain's order). Every sum is the
// same bit for bit as over every point of every bin of the range (`BinSearch::Whole`, tested),
// and far fewer points are visited: the refined points outnumber the particles many times and
// their radii are a fraction of the particles'.
//
// The sum stops once the two parts together reach `stop` (`NO_STOP`: never): the terms are all
// >= 0 (the weights, `Points::check`, and the kernels), so the whole sums would be no smaller.
fn sums(x: vec3<f32>, weighted: bool, with_sheet: bool, stop: f32) -> vec2<f32> {
    let range = bin_range(x, params.bin_origin, params.bin_size, params.bins, params.reach);
    // the largest radius the bins were made for
    let largest = f32(params.reach) * params.bin_size;
    var inner = 0.0;
    var outer = 0.0;
    for (var bz = range.lo.z; bz <= range.hi.z; bz++) {
        for (var by = range.lo.y; by <= range.hi.y; by++) {
            let row = (u32(bz) * params.bins.y + u32(by)) * params.bins.x;
            let spans = row_spans(x, params.bin_origin, params.bin_size, range, by, bz, largest, params.sheet_radius);
            for (var bx = spans.x; bx <= spans.y; bx++) {
                let sheet_too = with_sheet && bx >= spans.z && bx <= spans.w;
                let end = bin_start[row + u32(bx) + 1u];
                for (var n = bin_start[row + u32(bx)]; n < end; n++) {
                    let p = points[n];
                    if !sheet_too && p.index >= params.leading {
                        break;
                    }
                    let s = split[p.index];
                    // weighted (the Jacobi steps) only the sheet's density is read: a point
                    // without a sheet weight adds +0 there
                    if (s.x == 0.0 || weighted) && s.y == 0.0 {
                        continue;
                    }
                    let d = x - p.at.xyz;
                    let r2 = d.x * d.x + (d.y * d.y + d.z * d.z);
                    let k = density_kernel_r2(r2, p.at.w, params.constant, params.kernel);
                    inner += s.x * k;
                    var w = s.y;
                    if weighted && w != 0.0 {
                        w *= w_in[p.index];
                    }
                    outer += w * k;
                    if inner + outer >= stop {
                        return vec2<f32>(inner, outer);
                    }
                }
            }
        }
    }
    return vec2<f32>(inner, outer);
}

// `sums` without a stop
const NO_STOP: f32 = 3.0e38;

// the point of an invocation (rows of 65,535 workgroups of 64)
fn point_index(id: vec3<u32>) -> u32 {
    return id.x + id.y * 65535u * 64u;
}

// Per sheet point (a point whose sheet weight is not 0): its target, how alone it is (1 - the
// other points' density at it over its own peak, in [0, 1]), its lone ball's weight and the
// interior's density at the target.
@compute @workgroup_size(64)
fn targets_pass(@builtin(global_invocation_id) id: vec3<u32>) {
    let j = point_index(id);
    if j >= params.count {
        return;
    }
    // the Jacobi steps start from w = 1 (the first step's `w_in`, bound here as `w_out`)
    w_out[j] = 1.0;
    let base = split[j].y;
    let s = sheet[j];
    let x = s.at.xyz;
    if base <= 0.0 {
        // no sheet point: its weight multiplies 0 (the steps leave it as it is)
        targets[j] = Target(vec4<f32>(x, 0.0), 1.0, 0.0, 0.0, 0.0);
        return;
    }
    let own = base * density_kernel_r2(0.0, s.at.w, params.constant, params.kernel);
    // alone is 0 once the others reach the point's own term: the sum stops there (the CPU's
    // `value_up_to`; most sheet points have neighbours enough), with a margin of 1e-5 that keeps
    // `others` computed from the partial sums at least `own` despite their rounding (three
    // roundings of 6e-8 each), so alone is 0 as from the whole sums, bit for bit (tested against
    // `BinSearch::Whole`, which sums every term)
    var stop = NO_STOP;
    if own > 0.0 && !whole_search() {
        stop = 2.0 * own * (1.0 + 1.0e-5);
    }
    let at_x = sums(x, false, true, stop);
    let others = at_x.y - own + at_x.x;
    var alone = 0.0;
    if own > 0.0 {
        alone = clamp(1.0 - others / own, 0.0, 1.0);
    }
    let ball = base * density_kernel_r2(params.lone_r2, s.at.w, params.constant, params.kernel);
    var lone = 1.0;
    if ball > 0.0 {
        lone = min(params.tau / ball, params.max_weight);
    }
    let len = length(s.normal.xyz);
    var at = x;
    if len > 0.0 {
        at = x + s.normal.xyz * (1.0 / len) * params.half_spacing;
    } else {
        alone = 1.0;
    }
    targets[j] = Target(vec4<f32>(at, alone), lone, sums(at, false, false, NO_STOP).x, 0.0, 0.0);
}

// A Jacobi step's new weight for sheet point j without the sheet's density at its target: its
// weight as it is when it has no sheet weight, its lone ball's when it is alone; -1 when the
// density is needed (`stepped`).
fn unsummed(j: u32) -> f32 {
    if split[j].y <= 0.0 {
        return w_in[j];
    }
    let t = targets[j];
    if t.at.w >= 1.0 {
        return t.lone;
    }
    return -1.0;
}

// A Jacobi step's new weight w' for a sheet point of weight w and target t, given the sheet's
// density at its target with the weights `w_in`: the weight scaled so that the target holds the
// iso-value less the interior's share there, blended with its lone ball's by how alone it is.
fn stepped(w: f32, t: Target, sheet_sum: f32) -> f32 {
    let alone = t.at.w;
    let want = max(params.tau - t.inside, 0.0);
    var boundary = w;
    if sheet_sum > 0.0 {
        boundary = clamp(w * want / sheet_sum, 0.0, params.max_weight);
    }
    return alone * t.lone + (1.0 - alone) * boundary;
}

// One Jacobi step (`BinSearch::Trimmed`) over the compacted points with a sheet weight, in
// their order (the bins'): invocation m steps `sheet_binned[m]`, whose weight is `w_in[m]`
// (`w_out[m]` after the step), the sheet's density at its target summed from the compacted
// points alone (`sheet_density`); the same arithmetic as `step_whole`'s for the same point.
// Neighbouring invocations read the same bins, and a sum reads the weights in the order it
// reads the points.
@compute @workgroup_size(64)
fn step(@builtin(global_invocation_id) id: vec3<u32>) {
    let m = point_index(id);
    if m >= sheet_prefix[params.count] {
        return;
    }
    let p = sheet_binned[m];
    let t = targets[p.index];
    let w = w_in[m];
    if p.weight <= 0.0 {
        w_out[m] = w;
    } else if t.at.w >= 1.0 {
        w_out[m] = t.lone;
    } else {
        w_out[m] = stepped(w, t, sheet_density(t.at.xyz));
    }
}

// The compacted points' solved weights (`w_in`, in their order) written to their points
// (`w_out`, in the chain's order; the points without a sheet weight keep the 1 the targets pass
// wrote there).
@compute @workgroup_size(64)
fn sheet_weights_back(@builtin(global_invocation_id) id: vec3<u32>) {
    let m = point_index(id);
    if m >= sheet_prefix[params.count] {
        return;
    }
    w_out[sheet_binned[m].index] = w_in[m];
}

// One Jacobi step over every point of every bin within the bins' reach (`BinSearch::Whole`):
// the sums `step` must equal bit for bit.
@compute @workgroup_size(64)
fn step_whole(@builtin(global_invocation_id) id: vec3<u32>) {
    let j = point_index(id);
    if j >= params.count {
        return;
    }
    let fixed = unsummed(j);
    if fixed >= 0.0 {
        w_out[j] = fixed;
        return;
    }
    let t = targets[j];
    w_out[j] = stepped(w_in[j], t, sums(t.at.xyz, true, true, NO_STOP).y);
}

// The points with a sheet weight, compacted once the split is known (the Jacobi steps' sums
// read nothing else: every other point adds +0 to the sheet's density). A step's sum over every
// point of the bins read each particle of about 60 bins to find the few of a thin sheet
// (lavapipe: 575-696 ms a step for 21,874 points). The compaction is stable, so the points keep
// the bins' order (the particles lead every bin) and a sum adds the same terms in the same order:
// the same bits. `sheet_prefix[n]`: the binned points before n that carry a sheet weight (n from
// 0 to count: the last is their number), so bin b's sheet points are `sheet_binned[
// sheet_prefix[bin_start[b]] .. sheet_prefix[bin_start[b + 1]]]`, each with its sheet weight as
// its `weight`. Blocks of 256 binned points: `sheet_count` counts each block's, `sheet_scan`
// turns the counts into the blocks' first slots, `sheet_scatter` writes the prefix and the
// points.
@group(0) @binding(13) var<storage, read_write> sheet_prefix_rw: array<u32>;
@group(0) @binding(14) var<storage, read_write> sheet_blocks: array<u32>;
@group(0) @binding(15) var<storage, read_write> sheet_binned_rw: array<IndexedPoint>;
@group(0) @binding(16) var<storage, read> sheet_binned: array<IndexedPoint>;
@group(0) @binding(17) var<storage, read> sheet_prefix: array<u32>;

// 1 when binned point n carries a sheet weight (0 past the points)
fn sheet_flag(n: u32) -> u32 {
    if n >= params.count {
        return 0u;
    }
    return select(0u, 1u, split[points[n].index].y != 0.0);
}

// the blocks of 256 over the prefix's count + 1 entries
fn sheet_block_count() -> u32 {
    return params.count / 256u + 1u;
}

@compute @workgroup_size(256)
fn sheet_count(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>,
               @builtin(local_invocation_index) local: u32) {
    let block = block_of(wg, groups);
    let inclusive = workgroup_scan(local, sheet_flag(block * 256u + local));
    if local == 255u && block < sheet_block_count() {
        sheet_blocks[block] = inclusive;
    }
}

// one workgroup: a serial sum over each invocation's run of blocks, then a scan of the runs
@compute @workgroup_size(256)
fn sheet_scan(@builtin(local_invocation_index) local: u32) {
    let blocks = sheet_block_count();
    let per = (blocks + 255u) / 256u;
    let first = min(local * per, blocks);
    let end = min(first + per, blocks);
    var sum = 0u;
    for (var b = first; b < end; b++) {
        sum += sheet_blocks[b];
    }
    var running = workgroup_scan(local, sum) - sum;
    for (var b = first; b < end; b++) {
        let s = sheet_blocks[b];
        sheet_blocks[b] = running;
        running += s;
    }
}

@compute @workgroup_size(256)
fn sheet_scatter(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>,
                 @builtin(local_invocation_index) local: u32) {
    let block = block_of(wg, groups);
    let n = block * 256u + local;
    let flag = sheet_flag(n);
    let inclusive = workgroup_scan(local, flag);
    if n > params.count {
        return;
    }
    let slot = sheet_blocks[block] + inclusive - flag;
    sheet_prefix_rw[n] = slot;
    if flag == 1u {
        var p = points[n];
        p.weight = split[p.index].y;
        sheet_binned_rw[slot] = p;
        // the first step's weight
        w_out[slot] = 1.0;
    }
}

// The sheet's density at x with the weights `w_in` (in the compacted order), from the
// compacted points with a sheet weight: the terms `sums(x, true, true, NO_STOP).y` adds other
// than +0, in its order (the same bits).
fn sheet_density(x: vec3<f32>) -> f32 {
    let range = bin_range(x, params.bin_origin, params.bin_size, params.bins, params.reach);
    let largest = f32(params.reach) * params.bin_size;
    var outer = 0.0;
    for (var bz = range.lo.z; bz <= range.hi.z; bz++) {
        for (var by = range.lo.y; by <= range.hi.y; by++) {
            let row = (u32(bz) * params.bins.y + u32(by)) * params.bins.x;
            let spans = row_spans(x, params.bin_origin, params.bin_size, range, by, bz, largest, params.sheet_radius);
            for (var bx = spans.x; bx <= spans.y; bx++) {
                let sheet_too = bx >= spans.z && bx <= spans.w;
                let bin = row + u32(bx);
                let end = sheet_prefix[bin_start[bin + 1u]];
                for (var n = sheet_prefix[bin_start[bin]]; n < end; n++) {
                    let p = sheet_binned[n];
                    if !sheet_too && p.index >= params.leading {
                        break;
                    }
                    let d = x - p.at.xyz;
                    let r2 = d.x * d.x + (d.y * d.y + d.z * d.z);
                    let k = density_kernel_r2(r2, p.at.w, params.constant, params.kernel);
                    outer += p.weight * w_in[n] * k;
                }
            }
        }
    }
    return outer;
}

// the binned points again, written (`apply` alone binds them so)
@group(0) @binding(7) var<storage, read_write> binned_rw: array<IndexedPoint>;

// Per binned point (or another copy of the points that keeps their indices): its weight in
// the density becomes its interior share plus its sheet weight times its solved w (`w_in`),
// in place, before the grid is filled from the same points.
@compute @workgroup_size(64)
fn apply(@builtin(global_invocation_id) id: vec3<u32>) {
    let n = point_index(id);
    if n >= params.count {
        return;
    }
    let index = binned_rw[n].index;
    let s = split[index];
    binned_rw[n].weight = s.x + s.y * w_in[index];
}

// A point the factors leave out, in `ordered`'s output. Mirror: DROPPED in
// src/pipeline/boundary/gpu.rs.
const DROPPED: f32 = -1.0;

// Per point in the points' own order: its weight in the density (as `apply` writes it into
// the binned points) into `w_out`, for a reader that keeps that order (the ray caster's spheres
// in `GpuPipeline`, `PointWeights`). With the split found here (`particles` > 0), a point whose
// split is zero is one `chain_input_at_boundary` leaves out: DROPPED, so that the reader draws
// it as that function's caller draws the points it keeps (no sphere, no PCA neighbour).
@compute @workgroup_size(64)
fn ordered(@builtin(global_invocation_id) id: vec3<u32>) {
    let j = point_index(id);
    if j >= params.count {
        return;
    }
    let s = split[j];
    if params.particles > 0u && s.x <= 0.0 && s.y <= 0.0 {
        w_out[j] = DROPPED;
        return;
    }
    w_out[j] = s.x + s.y * w_in[j];
}

// The particles' factors (`chain_input_at_boundary`): the sheet points' normals and the split,
// written (`thin_pass` and `factors_pass` alone bind them so), each particle's surface normal
// and class (w: 0 interior, 1 surface, 2 isolated), and each particle's share in a sheet one
// particle thick.
@group(0) @binding(9) var<storage, read_write> sheet_rw: array<SheetPoint>;
@group(0) @binding(10) var<storage, read_write> split_rw: array<vec2<f32>>;
@group(0) @binding(11) var<storage, read> classes: array<vec4<f32>>;
@group(0) @binding(12) var<storage, read_write> share: array<f32>;

// The particles lead the binned points of each bin (the bins keep the points' order), so the
// loops over particles below read each bin only up to its first other point: at three steps
// the refined points outnumber the particles 15 to 1. Every query lies within 1.45 spacings
// of the point the bins are searched around (the burial's reach, 0.95 spacings, from a target
// half a spacing out), inside the bins' reach of the particles' support radius (two spacings).

// One particle's term of the burial (`Fluid::burial`): near(|p - t|) far(|p - x|), `near`
// falling from 1 to 0 and `far` rising from 0 to 1 over `buried` +- `band` spacings.
fn burial_term(p: vec3<f32>, x: vec3<f32>, t: vec3<f32>) -> f32 {
    let s = 2.0 * params.half_spacing;
    let lo = (params.buried - params.band) * s;
    let hi = (params.buried + params.band) * s;
    return (1.0 - smoothstep(lo, hi, distance(p, t))) * smoothstep(lo, hi, distance(p, x));
}

// The unit normal of n, zero when n has no direction (`normalize_or_zero`).
fn unit_or_zero(n: vec3<f32>) -> vec3<f32> {
    let len = length(n);
    if !(len > 0.0) || len > 3.0e38 {
        return vec3<f32>(0.0);
    }
    return n / len;
}

// At x with outward normal n: how buried x is (x: the largest burial term over the particles,
// 0 without a normal), how buried it is towards -n (y), and the particles' `share` averaged
// around x (z: weights (1 - d^2 / h^2)^3 over the particles within h, two spacings;
// `Fluid::average`, 0 where none is) when `average`.
fn burial_and_average(x: vec3<f32>, n_in: vec3<f32>, average: bool) -> vec3<f32> {
    let n = unit_or_zero(n_in);
    let has_normal = any(n != vec3<f32>(0.0));
    let t_up = x + n * params.half_spacing;
    let t_down = x - n * params.half_spacing;
    let h2 = 16.0 * params.half_spacing * params.half_spacing;
    // the targets lie half a spacing from x, and a burial term is 0 (1 - smoothstep = 0) from
    // (buried + band) spacings of its target on: with a margin of 1e-3 spacings for the
    // rounding of the distances
    let burial_reach = (params.buried + params.band + 0.501) * 2.0 * params.half_spacing;
    let burial_reach2 = burial_reach * burial_reach;
    let range = bin_range(x, params.bin_origin, params.bin_size, params.bins, params.reach);
    // the particles any term reaches: within h for the average, the burial's reach without it
    var radius = burial_reach;
    if average {
        radius = max(radius, sqrt(h2));
    }
    var up = 0.0;
    var down = 0.0;
    var sum = 0.0;
    var total = 0.0;
    for (var bz = range.lo.z; bz <= range.hi.z; bz++) {
        for (var by = range.lo.y; by <= range.hi.y; by++) {
            let row = (u32(bz) * params.bins.y + u32(by)) * params.bins.x;
            let span = span_of(x, range, by, bz, radius);
            for (var bx = span.x; bx <= span.y; bx++) {
                let end = bin_start[row + u32(bx) + 1u];
                for (var m = bin_start[row + u32(bx)]; m < end; m++) {
                    let p = points[m];
                    if p.index >= params.particles {
                        break;
                    }
                    let d = p.at.xyz - x;
                    let d2 = dot(d, d);
                    // a particle farther than `burial_reach` from x lies farther than the
                    // burial's outer edge from both targets: its terms are exactly 0
                    if has_normal && (d2 < burial_reach2 || whole_search()) {
                        up = max(up, burial_term(p.at.xyz, x, t_up));
                        down = max(down, burial_term(p.at.xyz, x, t_down));
                    }
                    if average {
                        let q = 1.0 - d2 / h2;
                        if q > 0.0 {
                            let w = q * q * q;
                            sum += w * share[p.index];
                            total += w;
                        }
                    }
                }
            }
        }
    }
    var mean = 0.0;
    if total > 0.0 {
        mean = sum / total;
    }
    return vec3<f32>(up, down, mean);
}

// Particle i's sheet normal and how flat its neighbourhood is (`Fluid::flat_normal`): the
// smallest-eigenvalue eigenvector of the covariance of the particles within two spacings, and
// 1 when that eigenvalue is under 5 % of the next, 0 over 15 %; zero when fewer than 4 or the
// neighbourhood is a line. The normal points up (+y), else +x, else +z.
fn flat_normal(x: vec3<f32>) -> vec4<f32> {
    let h = 4.0 * params.half_spacing;
    let range = bin_range(x, params.bin_origin, params.bin_size, params.bins, params.reach);
    var n = 0.0;
    var sum = vec3<f32>(0.0);
    var outer = mat3x3<f32>(vec3<f32>(0.0), vec3<f32>(0.0), vec3<f32>(0.0));
    for (var bz = range.lo.z; bz <= range.hi.z; bz++) {
        for (var by = range.lo.y; by <= range.hi.y; by++) {
            let row = (u32(bz) * params.bins.y + u32(by)) * params.bins.x;
            let span = span_of(x, range, by, bz, h);
            for (var bx = span.x; bx <= span.y; bx++) {
                let end = bin_start[row + u32(bx) + 1u];
                for (var m = bin_start[row + u32(bx)]; m < end; m++) {
                    let p = points[m];
                    if p.index >= params.particles {
                        break;
                    }
                    let d = p.at.xyz - x;
                    if dot(d, d) < h * h {
                        n += 1.0;
                        sum += d;
                        outer += mat3x3<f32>(d * d.x, d * d.y, d * d.z);
                    }
                }
            }
        }
    }
    if n < 4.0 {
        return vec4<f32>(0.0);
    }
    let mean = sum / n;
    let cov = outer - mat3x3<f32>(mean * mean.x, mean * mean.y, mean * mean.z) * n;
    // symmetric: its columns are its rows
    let e = symmetric_eigen(cov[0], cov[1], cov[2]);
    if !(e.values.y > 0.0) {
        return vec4<f32>(0.0);
    }
    let flat = 1.0 - smoothstep(0.05, 0.15, e.values.x / e.values.y);
    let v = e.least;
    var up = v.z;
    if abs(v.y) > 1.0e-3 {
        up = v.y;
    } else if abs(v.x) > 1.0e-3 {
        up = v.x;
    }
    if !(flat > 0.0) {
        return vec4<f32>(0.0);
    }
    return vec4<f32>(v * select(-1.0, 1.0, up >= 0.0), flat);
}

// Per particle: its share in a sheet one particle thick, exposed on both sides of its plane
// (how flat times how little buried on either side), and that sheet's normal on its sheet
// point (zero when it is none).
@compute @workgroup_size(64)
fn thin_pass(@builtin(global_invocation_id) id: vec3<u32>) {
    let i = point_index(id);
    if i >= params.particles {
        return;
    }
    let x = sheet_rw[i].at.xyz;
    var s = 0.0;
    var normal = vec3<f32>(0.0);
    if classes[i].w != 2.0 {
        let f = flat_normal(x);
        if f.w > 0.0 {
            let sides = burial_and_average(x, f.xyz, false);
            s = f.w * (1.0 - max(sides.x, sides.y));
            if s > 0.0 {
                normal = f.xyz;
            } else {
                s = 0.0;
            }
        }
    }
    share[i] = s;
    sheet_rw[i].normal = vec4<f32>(normal, 0.0);
}

// Per point, after `thin_pass`: a particle's interior share (1 inside, a surface particle's
// burial, 0 isolated; less its share in a thin sheet) and its sheet weight (that share); a
// sheet point's weight, how little it is buried times how little a thin sheet is around it.
@compute @workgroup_size(64)
fn factors_pass(@builtin(global_invocation_id) id: vec3<u32>) {
    let n = point_index(id);
    if n >= params.count {
        return;
    }
    let x = sheet_rw[n].at.xyz;
    if n < params.particles {
        let c = classes[n];
        var inner = 1.0;
        if c.w == 1.0 {
            inner = burial_and_average(x, c.xyz, false).x;
        } else if c.w == 2.0 {
            inner = 0.0;
        }
        split_rw[n] = vec2<f32>(inner * (1.0 - share[n]), share[n]);
    } else {
        let b = burial_and_average(x, sheet_rw[n].normal.xyz, true);
        let kept = (1.0 - b.x) * (1.0 - b.z);
        split_rw[n] = vec2<f32>(0.0, max(kept, 0.0));
    }
}
