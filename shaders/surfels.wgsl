// Surfels on the GPU (issue 37), the twin of src/surfels/cpu.rs: the crossings of the iso-value on
// the density grid's x, y and z edges, compacted in the CPU's order by a prefix sum, then
// projected onto the exact iso-surface of the points' density by Newton steps along its
// analytic gradient.
//
// Order: grid point p = i + nx (j + ny k) owns its x edge (to i + 1), its y edge (to j + 1) and
// its z edge (down to k - 1), in that order: the order in which `SurfelExtractor` finds them, so
// surfel n is the CPU's surfel n. `count` finds how many crossings each point owns and sums them
// per block of 256 points; `scan_blocks` turns the block sums into each block's first surfel
// (one workgroup: a serial sum over each thread's run of blocks, then a scan of the 256 runs);
// `emit` writes each crossing at its block's first surfel plus its rank within the block;
// `project` runs the Newton steps.

struct SurfelParams {
    // grid origin and spacing
    origin: vec3<f32>,
    spacing: f32,
    // grid points along x, y, z; the iso-value
    dims: vec3<u32>,
    iso: f32,
    // bins of the points (sorted by bin, src/density/bins.rs): origin and side
    bin_origin: vec3<f32>,
    bin_size: f32,
    // bins along x, y, z; bins searched on each side (bin_size * reach >= the largest radius)
    bins: vec3<u32>,
    reach: u32,
    // the reference radius and its kernel constant; 0: Wyvill, 1: cubic spline; Newton steps
    h: f32,
    constant: f32,
    kernel: u32,
    newton_steps: u32,
    // blocks of 256 grid points; a Newton step shorter than `converged` cells ends it
    blocks: u32,
    converged: f32,
    // a sparse grid (src/density/sparse.rs): the side of its blocks of grid points (0: a dense
    // grid), and the value its inside blocks read as
    sparse_block: u32,
    inside: f32,
    // surfels the buffer holds: the crossings past it are left out
    capacity: u32,
    // the points of the largest radius lead (index < leading, first in every bin: the bins keep
    // the points' order); the others' largest radius (negative: every point of every bin read)
    leading: u32,
    rest_radius: f32,
    _pad0: u32,
    // the surfels' colour (`splat::WATER`)
    colour: vec4<f32>,
}

// A surfel as the splatting draws it (`splat::Surfel`, 64 bytes): a circular disk.
struct Surfel {
    position: vec3<f32>,
    radius: f32,
    normal: vec3<f32>,
    stretch: f32,
    tangent: vec3<f32>,
    _pad: f32,
    colour: vec4<f32>,
}

@group(0) @binding(0) var<uniform> params: SurfelParams;
// the grid's values, x fastest; a sparse grid's: its evaluated blocks' values, a block after
// the other (x fastest within a block)
@group(0) @binding(1) var<storage, read> grid: array<f32>;
// per block of 256 points: its crossings (count), then its first surfel (scan_blocks)
@group(0) @binding(2) var<storage, read_write> block_sums: array<u32>;
// [0]: the number of surfels; [1..4]: the workgroups of `project` for the surfels the buffer
// holds, for an indirect dispatch; [4..8]: the splatting's indirect draw of them (6 vertices an
// instance) (scan_blocks)
@group(0) @binding(3) var<storage, read_write> total: array<u32>;
// the surfels: the crossings' positions (emit), then projected, with normals out of the fluid,
// radius, colour (project)
@group(0) @binding(4) var<storage, read_write> surfels: array<Surfel>;
// the points sorted by bin (position, radius, weight), and where each bin starts
@group(0) @binding(5) var<storage, read> points: array<IndexedPoint>;
@group(0) @binding(6) var<storage, read> bin_start: array<u32>;
// a sparse grid's block states (x fastest): empty (0xffffffff, every value 0), inside
// (0xfffffffe, every value `inside`) or the slot of the block's values in `grid`
@group(0) @binding(7) var<storage, read> states: array<u32>;

fn point_count() -> u32 {
    return params.dims.x * params.dims.y * params.dims.z;
}

fn grid_point(i: u32, j: u32, k: u32) -> vec3<f32> {
    return params.origin + vec3<f32>(f32(i), f32(j), f32(k)) * params.spacing;
}

// The value at grid point (i, j, k), from the dense grid or through a sparse grid's blocks
// (`SparseGrid::at`).
fn value_at(i: u32, j: u32, k: u32) -> f32 {
    let s = params.sparse_block;
    if s == 0u {
        return grid[i + params.dims.x * (j + params.dims.y * k)];
    }
    let state = block_state(i, j, k);
    if state == 0xffffffffu {
        return 0.0;
    }
    if state == 0xfffffffeu {
        return params.inside;
    }
    return grid[state * s * s * s + (i % s) + s * ((j % s) + s * (k % s))];
}

// A sparse grid's state of the block holding grid point (i, j, k) (`params.sparse_block` > 0).
fn block_state(i: u32, j: u32, k: u32) -> u32 {
    let s = params.sparse_block;
    let bx = (params.dims.x + s - 1u) / s;
    let by = (params.dims.y + s - 1u) / s;
    return states[i / s + bx * (j / s + by * (k / s))];
}

// The value at grid point (i, j, k) where a crossing edge ends: a sparse grid's inside block
// reads as `inside`, which says no more than "above the iso-value" (the blocks the GPU fills,
// `GridFiller::record_sparse`, are not made exact at their crossings as the CPU's
// `exact_ends` makes them); there the points' density at the grid point, the dense grid's
// value, places the surfel where the dense grid does.
fn end_value(i: u32, j: u32, k: u32) -> f32 {
    if params.sparse_block != 0u && block_state(i, j, k) == 0xfffffffeu {
        return density_and_gradient(grid_point(i, j, k)).w;
    }
    return value_at(i, j, k);
}

fn below(v: f32) -> bool {
    return v < params.iso;
}

// Which of point p's edges the iso-value crosses: bit 0 its x edge, bit 1 its y edge, bit 2
// its z edge (to the plane below), as `plane_crossings` tests them.
fn crossing_mask(p: u32) -> u32 {
    let nx = params.dims.x;
    let plane = nx * params.dims.y;
    let i = p % nx;
    let j = (p / nx) % params.dims.y;
    let k = p / plane;
    let v = below(value_at(i, j, k));
    var m = 0u;
    if i + 1u < nx && v != below(value_at(i + 1u, j, k)) {
        m |= 1u;
    }
    if j + 1u < params.dims.y && v != below(value_at(i, j + 1u, k)) {
        m |= 2u;
    }
    if k > 0u && v != below(value_at(i, j, k - 1u)) {
        m |= 4u;
    }
    return m;
}


@compute @workgroup_size(256)
fn count(
    @builtin(local_invocation_index) local: u32,
    @builtin(workgroup_id) wg: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
) {
    let block = block_of(wg, groups);
    let p = block * 256u + local;
    var n = 0u;
    if p < point_count() {
        n = countOneBits(crossing_mask(p));
    }
    let inclusive = workgroup_scan(local, n);
    if local == 255u && block < params.blocks {
        block_sums[block] = inclusive;
    }
}

@compute @workgroup_size(256)
fn scan_blocks(@builtin(local_invocation_index) local: u32) {
    let per = (params.blocks + 255u) / 256u;
    let first = min(local * per, params.blocks);
    let end = min(first + per, params.blocks);
    var sum = 0u;
    for (var b = first; b < end; b++) {
        sum += block_sums[b];
    }
    let inclusive = workgroup_scan(local, sum);
    var running = inclusive - sum;
    for (var b = first; b < end; b++) {
        let s = block_sums[b];
        block_sums[b] = running;
        running += s;
    }
    if local == 255u {
        total[0] = inclusive;
        // `project`'s dispatch: 64 surfels a workgroup, at most 65,535 workgroups a dimension
        let groups = (min(inclusive, params.capacity) + 63u) / 64u;
        let x = min(groups, 65535u);
        total[1] = x;
        total[2] = select(0u, (groups + x - 1u) / max(x, 1u), groups > 0u);
        total[3] = 1u;
        total[4] = 6u;
        total[5] = min(inclusive, params.capacity);
        total[6] = 0u;
        total[7] = 0u;
    }
}

@compute @workgroup_size(256)
fn emit(
    @builtin(local_invocation_index) local: u32,
    @builtin(workgroup_id) wg: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
) {
    let block = block_of(wg, groups);
    let p = block * 256u + local;
    var m = 0u;
    if p < point_count() {
        m = crossing_mask(p);
    }
    let n = countOneBits(m);
    let inclusive = workgroup_scan(local, n);
    if n == 0u {
        return;
    }
    var at = block_sums[block] + inclusive - n;
    let nx = params.dims.x;
    let plane = nx * params.dims.y;
    let i = p % nx;
    let j = (p / nx) % params.dims.y;
    let k = p / plane;
    let here = grid_point(i, j, k);
    let v = end_value(i, j, k);
    let dims = params.dims;
    // each crossed edge's point by the cubic through the values along its line, as the CPU's
    // `crossing_t` (linear at the grid's border); none past the capacity
    if (m & 1u) != 0u {
        let w = end_value(i + 1u, j, k);
        let there = grid_point(i + 1u, j, k);
        if at < params.capacity {
            var t = linear_t(v, w);
            if i >= 1u && i + 2u < dims.x {
                t = crossing_t(end_value(i - 1u, j, k), v, w, end_value(i + 2u, j, k));
            }
            surfels[at].position = here + (there - here) * t;
        }
        at += 1u;
    }
    if (m & 2u) != 0u {
        let w = end_value(i, j + 1u, k);
        let there = grid_point(i, j + 1u, k);
        if at < params.capacity {
            var t = linear_t(v, w);
            if j >= 1u && j + 2u < dims.y {
                t = crossing_t(end_value(i, j - 1u, k), v, w, end_value(i, j + 2u, k));
            }
            surfels[at].position = here + (there - here) * t;
        }
        at += 1u;
    }
    if (m & 4u) != 0u && at < params.capacity {
        let u = end_value(i, j, k - 1u);
        let under = grid_point(i, j, k - 1u);
        var t = linear_t(u, v);
        if k >= 2u && k + 1u < dims.z {
            t = crossing_t(end_value(i, j, k - 2u), u, v, end_value(i, j, k + 1u));
        }
        surfels[at].position = under + (here - under) * t;
    }
}

// The linear interpolation's fraction of an edge from `v` to `w` at the iso-value.
fn linear_t(v: f32, w: f32) -> f32 {
    return (params.iso - v) / (w - v);
}

// `surfels::crossing_t` with the values `u` and `z` one point before and after the edge: the
// root in [0, 1] of the cubic through (-1, u), (0, v), (1, w), (2, z), by Newton's steps from
// the linear interpolation kept inside the bracket the signs give (halving it where a step
// would leave it) until a step is under 1e-6 of the edge (`CUBIC_TOLERANCE`), at most 40
// (`CUBIC_STEPS`).
fn crossing_t(u: f32, v: f32, w: f32, z: f32) -> f32 {
    let iso = params.iso;
    let c1 = (-2.0 * u - 3.0 * v + 6.0 * w - z) / 6.0;
    let c2 = (u - 2.0 * v + w) / 2.0;
    let c3 = (-u + 3.0 * v - 3.0 * w + z) / 6.0;
    let below = v < iso;
    var lo = 0.0;
    var hi = 1.0;
    var t = clamp(linear_t(v, w), 0.0, 1.0);
    for (var s = 0u; s < 40u; s++) {
        let f = v + t * (c1 + t * (c2 + t * c3)) - iso;
        if f == 0.0 {
            return t;
        }
        if (f < 0.0) == below {
            lo = t;
        } else {
            hi = t;
        }
        let df = c1 + t * (2.0 * c2 + t * (3.0 * c3));
        let newton = t - f / df;
        var next = 0.5 * (lo + hi);
        if newton > lo && newton < hi {
            next = newton;
        }
        if abs(next - t) <= 1e-6 {
            return next;
        }
        t = next;
    }
    return t;
}

// The points' density at x (w) and its analytic gradient (xyz): `ExactDensity::value_and_gradient`,
// each point's kernel of its own radius against the reference radius's constant
// (`Kernel::weighted_and_gradient`), times its weight. Each row of bins is read only where the
// ball of the largest radius reaches it (`row_span`), and the points after the leading ones
// (the refined points, of radii a fraction of the particles') only in the bins the ball of
// their largest radius reaches, each other bin up to its first such point: every point left
// out lies beyond its radius and adds nothing, so the sums are those over every bin of the
// range, in the same order.
fn density_and_gradient(x: vec3<f32>) -> vec4<f32> {
    let range = bin_range(x, params.bin_origin, params.bin_size, params.bins, params.reach);
    let largest = f32(params.reach) * params.bin_size;
    var sum = 0.0;
    var grad = vec3<f32>(0.0);
    let c = params.constant;
    for (var bz = range.lo.z; bz <= range.hi.z; bz++) {
        for (var by = range.lo.y; by <= range.hi.y; by++) {
            let row = (u32(bz) * params.bins.y + u32(by)) * params.bins.x;
            let spans = row_spans(x, params.bin_origin, params.bin_size, range, by, bz, largest, params.rest_radius);
            for (var bx = spans.x; bx <= spans.y; bx++) {
                let rest_too = bx >= spans.z && bx <= spans.w;
                let end = bin_start[row + u32(bx) + 1u];
                for (var n = bin_start[row + u32(bx)]; n < end; n++) {
                    if !rest_too && points[n].index >= params.leading {
                        break;
                    }
                    let d = x - points[n].at.xyz;
                    let hj = points[n].at.w;
                    let wj = points[n].weight;
                    let r2 = dot(d, d);
                    if params.kernel == 0u {
                        let inv = 1.0 / (hj * hj);
                        let a2 = r2 * inv;
                        if a2 < 1.0 {
                            let poly = ((-4.0 / 9.0 * a2 + 17.0 / 9.0) * a2 - 22.0 / 9.0) * a2 + 1.0;
                            let slope = (-4.0 / 3.0 * a2 + 34.0 / 9.0) * a2 - 22.0 / 9.0;
                            sum += wj * (c * poly);
                            grad += wj * (d * (c * slope * 2.0 * inv));
                        }
                    } else {
                        let r = sqrt(r2);
                        if r < hj {
                            let q = 2.0 * (r / hj);
                            var v = 0.0;
                            var df = 0.0;
                            if q < 1.0 {
                                v = c * (1.0 - 1.5 * q * q + 0.75 * q * q * q);
                                df = -3.0 * q + 2.25 * q * q;
                            } else {
                                let t = 2.0 - q;
                                v = c * 0.25 * t * t * t;
                                df = -0.75 * t * t;
                            }
                            sum += wj * v;
                            if r > 0.0 {
                                grad += wj * (d * (c * df * 2.0 / (hj * r)));
                            }
                        }
                    }
                }
            }
        }
    }
    return vec4<f32>(grad, sum);
}

@compute @workgroup_size(64)
fn project(
    @builtin(local_invocation_index) local: u32,
    @builtin(workgroup_id) wg: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
) {
    let s = block_of(wg, groups) * 64u + local;
    if s >= min(total[0], params.capacity) {
        return;
    }
    var x = surfels[s].position;
    var g = vec3<f32>(0.0);
    let cap = 0.5 * params.spacing;
    let done = params.converged * params.spacing;
    for (var step = 0u; step < params.newton_steps; step++) {
        let vg = density_and_gradient(x);
        g = vg.xyz;
        let g2 = dot(g, g);
        if g2 <= 1.17549435e-38 {
            break;
        }
        // a Newton step along the gradient, never more than half a cell
        var st = g * ((params.iso - vg.w) / g2);
        let len = length(st);
        if len > cap {
            st *= cap / len;
        }
        x += st;
        if dot(st, st) < done * done {
            break;
        }
    }
    if params.newton_steps == 0u {
        g = density_and_gradient(x).xyz;
    }
    var nrm = vec3<f32>(0.0);
    let g2 = dot(g, g);
    if g2 > 0.0 {
        nrm = -g / sqrt(g2);
    }
    // a disk of the grid's spacing (`Surfel::disk`)
    surfels[s] = Surfel(x, params.spacing, nrm, 1.0, vec3<f32>(0.0), 0.0, params.colour);
}
