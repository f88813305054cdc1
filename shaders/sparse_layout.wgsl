// The sparse density grid's layout on the GPU (issue 37), the twin of `Blocks::layout` in
// src/density/sparse.rs: which blocks of 8^3 grid points are empty, inside or evaluated, and the
// evaluated ones' slots in block order. Prepended at load: common.wgsl, scan.wgsl.
//
// `block_states`  per block: inside when every voxel of the LNM band its closed range covers is
//                 an interior voxel (src/lnm/gpu.rs' `ResidentBand`), else evaluated (flag 1) when
//                 a point's ball reaches its closed range, else empty; the CPU's arithmetic
// `layout_count`, `layout_scan`, `layout_scatter`  the evaluated blocks compacted in block order:
//                 each one's slot written over its flag in `states`, its index in `evaluated`,
//                 their count and the fill's indirect dispatch in `count`; a block whose slot
//                 lies past the values' capacity reads as empty (the host sees the count a few
//                 frames later, says so and grows the values)

struct LayoutParams {
    // the grid's first point and spacing
    origin: vec3<f32>,
    spacing: f32,
    // grid points along x, y, z; the binned points
    dims: vec3<u32>,
    count: u32,
    // blocks along x, y, z; all blocks
    blocks: vec3<u32>,
    total: u32,
    // the band's domain: its minimum corner and 1 / its voxel's edge
    band_lo: vec3<f32>,
    band_inv: f32,
    // the band's voxels along x, y, z; the evaluated blocks the values hold (the fill's buffer)
    band_dims: vec3<u32>,
    capacity: u32,
    // the bins' origin (the grid's) and 1 / a bin's side
    bin_origin: vec3<f32>,
    bin_inv: f32,
    // bins along x, y, z; -
    bins: vec3<u32>,
    _pad1: u32,
    // the largest radius times `margin`; the margin on a radius (`REACH_MARGIN`: 1 + 1e-4)
    reach: f32,
    margin: f32,
    _pad2: u32,
    _pad3: u32,
}

const EMPTY: u32 = 0xffffffffu;
const INSIDE: u32 = 0xfffffffeu;

@group(0) @binding(0) var<uniform> params: LayoutParams;
// the binned points (`BinnedPoints`) and where each bin's start
@group(0) @binding(1) var<storage, read> points: array<IndexedPoint>;
@group(0) @binding(2) var<storage, read> bin_start: array<u32>;
// the band's voxels: particle counts and labels (interior: count > 0, label 0)
@group(0) @binding(3) var<storage, read> band_counts: array<u32>;
@group(0) @binding(4) var<storage, read> band_labels: array<u32>;
// per block: EMPTY, INSIDE, 0 (to evaluate), then the evaluated ones' slots
@group(0) @binding(5) var<storage, read_write> states: array<u32>;
// the evaluated blocks' indices in slot order
@group(0) @binding(6) var<storage, read_write> evaluated: array<u32>;
// per workgroup of 256 blocks: its evaluated blocks, then its first slot
@group(0) @binding(7) var<storage, read_write> layout_blocks: array<u32>;
// the evaluated blocks' count, then the fill's workgroups (x, y, z) of `gather_blocks`
@group(0) @binding(8) var<storage, read_write> layout_count: array<u32>;

fn block_coords(b: u32) -> vec3<u32> {
    let n = params.blocks;
    return vec3<u32>(b % n.x, (b / n.x) % n.y, b / (n.x * n.y));
}

// The band's voxel of x along each axis (the CPU's `voxel_range`: floor((x - lo) * inv)).
fn voxel_of(x: vec3<f32>) -> vec3<i32> {
    return vec3<i32>(floor((x - params.band_lo) * params.band_inv));
}

// Whether every voxel the box [lo, hi] covers lies in the band's domain and is interior.
fn all_interior(lo: vec3<f32>, hi: vec3<f32>) -> bool {
    let r0 = voxel_of(lo);
    let r1 = voxel_of(hi);
    let n = vec3<i32>(params.band_dims);
    if any(r0 < vec3<i32>(0)) || any(r1 >= n) {
        return false;
    }
    for (var z = r0.z; z <= r1.z; z++) {
        for (var y = r0.y; y <= r1.y; y++) {
            for (var x = r0.x; x <= r1.x; x++) {
                let v = u32(x) + params.band_dims.x * (u32(y) + params.band_dims.y * u32(z));
                if band_counts[v] == 0u || band_labels[v] != 0u {
                    return false;
                }
            }
        }
    }
    return true;
}

// The bin of x along each axis, a bin wider on the side of `side` (-1 or +1: the bins' product
// may round a point into its neighbour), clamped to the bins there are.
fn bin_at(x: vec3<f32>, side: i32) -> vec3<u32> {
    let b = vec3<i32>(floor((x - params.bin_origin) * params.bin_inv)) + vec3<i32>(side);
    return vec3<u32>(clamp(b, vec3<i32>(0), vec3<i32>(params.bins) - vec3<i32>(1)));
}

// Whether a point's ball (its radius times the margin) reaches the box [lo, hi]: the CPU's
// `(lo - x).max(x - hi).max(0).length_squared() < r * r`, in its order.
fn reached(lo: vec3<f32>, hi: vec3<f32>) -> bool {
    let a = bin_at(lo - vec3<f32>(params.reach), -1);
    let c = bin_at(hi + vec3<f32>(params.reach), 1);
    for (var z = a.z; z <= c.z; z++) {
        for (var y = a.y; y <= c.y; y++) {
            // a row's bins are consecutive, so are their points
            let row = (z * params.bins.y + y) * params.bins.x;
            let end = bin_start[row + c.x + 1u];
            for (var n = bin_start[row + a.x]; n < end; n++) {
                let x = points[n].at.xyz;
                let r = points[n].at.w * params.margin;
                let d = max(max(lo - x, x - hi), vec3<f32>(0.0));
                if d.x * d.x + d.y * d.y + d.z * d.z < r * r {
                    return true;
                }
            }
        }
    }
    return false;
}

@compute @workgroup_size(64)
fn block_states(@builtin(global_invocation_id) id: vec3<u32>) {
    let b = id.x + id.y * 65535u * 64u;
    if b >= params.total {
        return;
    }
    // the block's closed range of grid points (the CPU's `closed`) and its world box
    let first = block_coords(b) * 8u;
    let last = min(first + vec3<u32>(8u), params.dims - vec3<u32>(1u));
    let lo = params.origin + vec3<f32>(first) * params.spacing;
    let hi = params.origin + vec3<f32>(last) * params.spacing;
    var state = EMPTY;
    if all_interior(lo, hi) {
        state = INSIDE;
    } else if reached(lo, hi) {
        state = 0u;
    }
    states[b] = state;
}

// 1 when block b is to be evaluated (0 past the blocks)
fn layout_flag(b: u32) -> u32 {
    if b >= params.total {
        return 0u;
    }
    return select(0u, 1u, states[b] == 0u);
}

fn layout_block_count() -> u32 {
    return (params.total + 255u) / 256u;
}

@compute @workgroup_size(256)
fn layout_count_blocks(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>,
                       @builtin(local_invocation_index) local: u32) {
    let block = block_of(wg, groups);
    let inclusive = workgroup_scan(local, layout_flag(block * 256u + local));
    if local == 255u && block < layout_block_count() {
        layout_blocks[block] = inclusive;
    }
}

// one workgroup: a serial sum over each invocation's run of workgroups' counts, then a scan of
// the runs
@compute @workgroup_size(256)
fn layout_scan(@builtin(local_invocation_index) local: u32) {
    let blocks = layout_block_count();
    let per = (blocks + 255u) / 256u;
    let first = min(local * per, blocks);
    let end = min(first + per, blocks);
    var sum = 0u;
    for (var b = first; b < end; b++) {
        sum += layout_blocks[b];
    }
    var running = workgroup_scan(local, sum) - sum;
    for (var b = first; b < end; b++) {
        let s = layout_blocks[b];
        layout_blocks[b] = running;
        running += s;
    }
}

@compute @workgroup_size(256)
fn layout_scatter(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>,
                  @builtin(local_invocation_index) local: u32) {
    let block = block_of(wg, groups);
    let b = block * 256u + local;
    let flag = layout_flag(b);
    let inclusive = workgroup_scan(local, flag);
    if b >= params.total {
        return;
    }
    let slot = layout_blocks[block] + inclusive - flag;
    if flag == 1u {
        states[b] = select(EMPTY, slot, slot < params.capacity);
        evaluated[slot] = b;
    }
    if b + 1u == params.total {
        // the count and `gather_blocks`' workgroups: a plane of a block each, y + z * 65,535
        // the slot
        let count = slot + flag;
        let filled = min(count, params.capacity);
        layout_count[0] = count;
        layout_count[1] = select(0u, 8u, filled > 0u);
        layout_count[2] = min(filled, 65535u);
        layout_count[3] = (filled + 65534u) / 65535u;
    }
}
