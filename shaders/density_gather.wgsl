// Density grid by gathering (the compute-shader variant of Iwasaki et al. §4.1), each particle
// weighted (the chain's boundary weights; 1 otherwise): the particles are
// binned (on the CPU, or on the GPU by bin_sort.wgsl) into cubic bins of side >= (largest radius) / reach (sorted by bin, with the
// start of every bin), and one invocation per grid point of a group of planes sums the kernel of
// each particle's own radius (measured against the reference radius h) over the particles
// of the (2 reach + 1)^3 bins around it that a particle's ball can reach it from (`density_at`).
// The result is written, not blended: no float atomics, and the sum's order is fixed (the
// particles' sorted order), so runs are reproducible.

struct GatherParams {
    // grid origin and spacing
    origin: vec3<f32>,
    spacing: f32,
    // grid points along x, y, z; first plane of this dispatch
    dims: vec3<u32>,
    k0: u32,
    // bin grid origin and side
    bin_origin: vec3<f32>,
    bin_size: f32,
    // bins along x, y, z; planes in this dispatch (`gather_blocks`: the evaluated blocks)
    bins: vec3<u32>,
    planes: u32,
    // the reference radius
    h: f32,
    // 2835 / (736 pi h^3) for Wyvill, 8 / (pi h^3) for the cubic spline, of the reference h
    constant: f32,
    // 0: Wyvill, 1: cubic spline
    kernel: u32,
    // bins searched on each side: bin_size * reach >= the largest radius
    reach: u32,
    // the points of the largest radius lead (index < leading, first in every bin: the bins keep
    // the points' order); the others' largest radius (negative: every point of every bin read)
    leading: u32,
    rest_radius: f32,
    _pad0: u32,
    _pad1: u32,
}

@group(0) @binding(0) var<uniform> params: GatherParams;
// particles sorted by bin (position, radius and weight)
@group(0) @binding(1) var<storage, read> particles: array<IndexedPoint>;
// bin_start[b] .. bin_start[b + 1]: the particles of bin b (x fastest, then y, then z)
@group(0) @binding(2) var<storage, read> bin_start: array<u32>;
// densities of the dispatch's planes, x fastest
@group(0) @binding(3) var<storage, read_write> densities: array<f32>;

// a sparse grid's evaluated blocks (`gather_blocks`): each block's index, x fastest over the
// grid's blocks of 8^3 points (src/density/sparse.rs), in slot order
@group(0) @binding(4) var<storage, read> evaluated: array<u32>;

// The density at grid point (i, j, k): the particles of the bins around it, in sorted order.
// Each row of bins is read only where the ball of the largest radius reaches it (`row_span`),
// and the points after the leading ones (the refined points, of radii a fraction of the
// particles') only in the bins the ball of their largest radius reaches, each other bin up to
// its first such point: every point left out lies beyond its radius and adds an exact zero, so
// the sum is the one over every bin of the range, bit for bit (`BinSearch::Whole`, tested).
fn density_at(i: u32, j: u32, k: u32) -> f32 {
    let x = params.origin + vec3<f32>(f32(i), f32(j), f32(k)) * params.spacing;
    let range = bin_range(x, params.bin_origin, params.bin_size, params.bins, params.reach);
    let largest = f32(params.reach) * params.bin_size;
    var sum = 0.0;
    for (var bz = range.lo.z; bz <= range.hi.z; bz++) {
        for (var by = range.lo.y; by <= range.hi.y; by++) {
            let row = (u32(bz) * params.bins.y + u32(by)) * params.bins.x;
            let spans = row_spans(x, params.bin_origin, params.bin_size, range, by, bz, largest, params.rest_radius);
            for (var bx = spans.x; bx <= spans.y; bx++) {
                let rest_too = bx >= spans.z && bx <= spans.w;
                let end = bin_start[row + u32(bx) + 1u];
                for (var n = bin_start[row + u32(bx)]; n < end; n++) {
                    if !rest_too && particles[n].index >= params.leading {
                        break;
                    }
                    let d = x - particles[n].at.xyz;
                    let r2 = d.x * d.x + (d.y * d.y + d.z * d.z);
                    sum += particles[n].weight
                        * density_kernel_r2(r2, particles[n].at.w, params.constant, params.kernel);
                }
            }
        }
    }
    return sum;
}

@compute @workgroup_size(8, 8, 1)
fn gather(@builtin(global_invocation_id) id: vec3<u32>) {
    if id.x >= params.dims.x || id.y >= params.dims.y || id.z >= params.planes {
        return;
    }
    densities[(id.z * params.dims.y + id.y) * params.dims.x + id.x] =
        density_at(id.x, id.y, params.k0 + id.z);
}

// A sparse grid (issue 37): one workgroup per plane of an evaluated block (workgroup x: the
// plane within the block, y + z * 65,535: the block's slot), its values written at the slot's
// 512 values, x fastest within the block; the points past the grid's last planes stay 0, as
// the CPU's `SparseGrid` keeps them.
@compute @workgroup_size(8, 8, 1)
fn gather_blocks(
    @builtin(local_invocation_id) local: vec3<u32>,
    @builtin(workgroup_id) wg: vec3<u32>,
) {
    let slot = wg.y + wg.z * 65535u;
    if slot >= params.planes {
        return;
    }
    let b = evaluated[slot];
    let bx = (params.dims.x + 7u) / 8u;
    let by = (params.dims.y + 7u) / 8u;
    let block = vec3<u32>(b % bx, (b / bx) % by, b / (bx * by));
    let i = block.x * 8u + local.x;
    let j = block.y * 8u + local.y;
    let k = block.z * 8u + wg.x;
    var value = 0.0;
    if i < params.dims.x && j < params.dims.y && k < params.dims.z {
        value = density_at(i, j, k);
    }
    densities[slot * 512u + local.x + 8u * (local.y + 8u * wg.x)] = value;
}
