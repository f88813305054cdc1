// The points sorted by bin on the GPU (issue 37), the twin of `bin_particles` in
// src/density/bins.rs: a stable counting sort, so that within a bin the points keep their order
// (the particles lead every bin, which the boundary calibration's loops rely on) and the sorted
// points are the CPU's, bit for bit.
//
// `bin_keys`: each point's bin (the CPU's arithmetic: (x - origin) * inverse side, floored and
// clamped), its index, and the bins' counts (atomics: the counts do not depend on the order).
// `count_blocks`, `scan_blocks`, `count_starts`: the exclusive prefix sum of the counts, in place,
// into each bin's first slot (one more entry than bins: the last holds the count).
// `radix_histogram`, `scan_table`, `radix_scatter`: a least-significant-digit radix sort of the
// (bin, index) pairs by the bin, 8 bits a pass, each pass stable (a point's place among the points
// of its digit is the number of them before it: in earlier workgroups by the scanned table, in its
// own by a count over the workgroup's digits). `gather_points`: the points in sorted order.

struct SortParams {
    // the grid's origin and the inverse of a bin's side
    origin: vec3<f32>,
    inv_size: f32,
    // bins along x, y and z; the points
    bins: vec3<u32>,
    count: u32,
    // the radix pass's first bit; workgroups of 256 points; entries of the scan (`count_*`:
    // bins + 1; `scan_table`: 256 digits times the workgroups)
    shift: u32,
    groups: u32,
    entries: u32,
    _pad: u32,
}

// one layout for every pass (seven storage buffers: within the default limit of eight), the
// parameters at a dynamic offset per pass
@group(0) @binding(0) var<uniform> params: SortParams;
// the points in their order (`bin_keys`, `gather_points`)
@group(0) @binding(1) var<storage, read> points: array<IndexedPoint>;
// (bin, index) pairs: read by a radix pass, written by it to the other buffer
@group(0) @binding(2) var<storage, read_write> pairs_in: array<vec2<u32>>;
@group(0) @binding(3) var<storage, read_write> pairs_out: array<vec2<u32>>;
// the bins' counts, then their starts (`count_*`): one more entry than bins
@group(0) @binding(4) var<storage, read_write> starts: array<atomic<u32>>;
// per block of 256 entries of the counts: their sum, then their first slot
@group(0) @binding(5) var<storage, read_write> block_sums: array<u32>;
// the points sorted by bin (`gather_points`)
@group(0) @binding(6) var<storage, read_write> sorted: array<IndexedPoint>;
// a radix pass's table: per digit and workgroup its points, then the first slot of each
@group(0) @binding(7) var<storage, read_write> table: array<atomic<u32>>;

var<workgroup> digits: array<u32, 256>;
var<workgroup> seen: array<u32, 256>;
var<workgroup> ranks: array<u32, 256>;
var<workgroup> histogram: array<atomic<u32>, 256>;

// The bin of a position, as `bin_particles` finds it.
fn bin_of(x: vec3<f32>) -> u32 {
    let last = vec3<f32>(params.bins - vec3<u32>(1u));
    let b = vec3<u32>(clamp(floor((x - params.origin) * params.inv_size), vec3<f32>(0.0), last));
    return (b.z * params.bins.y + b.y) * params.bins.x + b.x;
}

@compute @workgroup_size(256)
fn bin_keys(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>,
            @builtin(local_invocation_index) local: u32) {
    let i = block_of(wg, groups) * 256u + local;
    if i >= params.count {
        return;
    }
    let key = bin_of(points[i].at.xyz);
    pairs_in[i] = vec2<u32>(key, i);
    atomicAdd(&starts[key], 1u);
}

// Entries of the counts each invocation of `count_blocks` and `count_starts` sums in turn, so
// that a block is 4,096 entries: with one count each, the three passes over 426,496 counts
// took lavapipe 94 ms (two passes of 1,667 workgroups, 17 barriers each), with 16 about 10 ms.
const RUN: u32 = 16u;

// Per block of 256 runs of the counts: their sum.
@compute @workgroup_size(256)
fn count_blocks(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>,
                @builtin(local_invocation_index) local: u32) {
    let block = block_of(wg, groups);
    let first = (block * 256u + local) * RUN;
    var n = 0u;
    for (var e = first; e < min(first + RUN, params.entries); e++) {
        n += atomicLoad(&starts[e]);
    }
    let inclusive = workgroup_scan(local, n);
    if local == 255u && block * 256u * RUN < params.entries {
        block_sums[block] = inclusive;
    }
}

// The blocks' sums turned into their first slots (one workgroup: a serial sum over each
// invocation's run of blocks, then a scan of the 256 runs).
@compute @workgroup_size(256)
fn scan_blocks(@builtin(local_invocation_index) local: u32) {
    let blocks = (params.entries + 256u * RUN - 1u) / (256u * RUN);
    let per = (blocks + 255u) / 256u;
    let first = min(local * per, blocks);
    let end = min(first + per, blocks);
    var sum = 0u;
    for (var b = first; b < end; b++) {
        sum += block_sums[b];
    }
    var running = workgroup_scan(local, sum) - sum;
    for (var b = first; b < end; b++) {
        let s = block_sums[b];
        block_sums[b] = running;
        running += s;
    }
}

// Each count replaced by its entry's first slot: its block's first, the runs before its own in
// the block, the counts before it in its run.
@compute @workgroup_size(256)
fn count_starts(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>,
                @builtin(local_invocation_index) local: u32) {
    let block = block_of(wg, groups);
    let first = (block * 256u + local) * RUN;
    let end = min(first + RUN, params.entries);
    var n = 0u;
    for (var e = first; e < end; e++) {
        n += atomicLoad(&starts[e]);
    }
    let inclusive = workgroup_scan(local, n);
    if block * 256u * RUN >= params.entries {
        return;
    }
    var running = block_sums[block] + inclusive - n;
    for (var e = first; e < end; e++) {
        let c = atomicLoad(&starts[e]);
        atomicStore(&starts[e], running);
        running += c;
    }
}

// Per workgroup of 256 points: how many of them have each digit, at `table[digit * groups +
// workgroup]` (the scan then runs digit by digit, each over the workgroups in order).
@compute @workgroup_size(256)
fn radix_histogram(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>,
                   @builtin(local_invocation_index) local: u32) {
    let block = block_of(wg, groups);
    atomicStore(&histogram[local], 0u);
    workgroupBarrier();
    let i = block * 256u + local;
    if i < params.count {
        atomicAdd(&histogram[(pairs_in[i].x >> params.shift) & 255u], 1u);
    }
    workgroupBarrier();
    if block < params.groups {
        atomicStore(&table[local * params.groups + block], atomicLoad(&histogram[local]));
    }
}

// The radix pass's table scanned in place (one workgroup, as `scan_blocks`): each entry the
// number of points before it, digit by digit, workgroup by workgroup.
@compute @workgroup_size(256)
fn scan_table(@builtin(local_invocation_index) local: u32) {
    let per = (params.entries + 255u) / 256u;
    let first = min(local * per, params.entries);
    let end = min(first + per, params.entries);
    var sum = 0u;
    for (var e = first; e < end; e++) {
        sum += atomicLoad(&table[e]);
    }
    var running = workgroup_scan(local, sum) - sum;
    for (var e = first; e < end; e++) {
        let s = atomicLoad(&table[e]);
        atomicStore(&table[e], running);
        running += s;
    }
}

// Each (bin, index) pair to its place: the points of its digit in earlier workgroups (the
// table), then those of its own workgroup before it, counted by one invocation walking the
// workgroup's digits in order (256 steps; an invocation counting the equal digits before its
// own made it up to 256 steps for each: on lavapipe, 110,000 points, 55 ms a pass for the scatter
// then, under 11 ms for the histogram, the table's scan and the scatter now).
@compute @workgroup_size(256)
fn radix_scatter(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>,
                 @builtin(local_invocation_index) local: u32) {
    let block = block_of(wg, groups);
    let i = block * 256u + local;
    var digit = 0xffffffffu;
    if i < params.count {
        digit = (pairs_in[i].x >> params.shift) & 255u;
    }
    digits[local] = digit;
    seen[local] = 0u;
    workgroupBarrier();
    if local == 0u {
        for (var j = 0u; j < 256u; j++) {
            let d = digits[j];
            if d != 0xffffffffu {
                ranks[j] = seen[d];
                seen[d] += 1u;
            }
        }
    }
    workgroupBarrier();
    if i >= params.count {
        return;
    }
    let at = atomicLoad(&table[digit * params.groups + block]) + ranks[local];
    pairs_out[at] = pairs_in[i];
}

// The points in sorted order (the last radix pass's output, bound as `pairs_in`).
@compute @workgroup_size(256)
fn gather_points(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>,
                 @builtin(local_invocation_index) local: u32) {
    let q = block_of(wg, groups) * 256u + local;
    if q >= params.count {
        return;
    }
    sorted[q] = points[pairs_in[q].y];
}
