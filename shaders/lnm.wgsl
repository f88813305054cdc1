// The narrow band of the Layered Neighborhood Method (Oliveira and Paiva, Algorithm 1), the GPU
// twin of `src/lnm/cpu.rs` on a dense voxel grid over the domain (the paper's own layout):
//
//   cs_count   per particle: its voxel (the CPU's formula: floor((p - lo) * inv_edge), clamped),
//              the voxel's count and its particles' offsets from the voxel's corner summed in
//              fixed point (integer atomics: the sum does not depend on the order)
//   cs_first   per voxel: full and on the border or next to an empty voxel: label 1
//   cs_second  per voxel: full, not 1, next to a label-1 voxel of at most n_min particles: 2
//
// Labels are 0 for empty voxels too; the host keeps the full ones (an interior voxel: count > 0
// and label 0). `ResidentBand` (src/lnm/gpu.rs) runs the passes over the binned points of the
// density's passes (32 bytes a point: a stride of two `vec4`s), counting only.

struct Params {
    // the domain's minimum corner, 1 / voxel edge
    lo: vec4<f32>,
    // voxels along x, y, z; particles
    dims: vec4<u32>,
    // n_min, fixed-point scale of the offsets, a point's stride in `vec4`s, 1: counts only (no
    // offsets' sums, no voxel per particle)
    misc: vec4<u32>,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> positions: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read_write> counts: array<atomic<u32>>;
@group(0) @binding(3) var<storage, read_write> sums: array<atomic<i32>>;
@group(0) @binding(4) var<storage, read_write> voxel_of: array<u32>;
@group(0) @binding(5) var<storage, read_write> labels: array<u32>;

// The invocation's index in a dispatch of 64-wide groups laid out as `lnm::gpu::groups` lays
// them out (at most 65,535 groups a row, then more rows); ssfr_band.wgsl's passes use it too.
fn invocation(id: vec3<u32>) -> u32 {
    return id.x + id.y * 65535u * 64u;
}

fn index_of(c: vec3<u32>) -> u32 {
    return c.x + params.dims.x * (c.y + params.dims.y * c.z);
}

@compute @workgroup_size(64)
fn cs_count(@builtin(global_invocation_id) id: vec3<u32>) {
    let i = invocation(id);
    if i >= params.dims.w {
        return;
    }
    let p = positions[i * params.misc.z].xyz;
    let f = floor((p - params.lo.xyz) * params.lo.w);
    let n = params.dims.xyz;
    // the CPU's `(v.max(0.0) as u32).min(n - 1)`
    let c = min(vec3<u32>(max(f, vec3<f32>(0.0))), n - vec3<u32>(1u));
    let v = index_of(c);
    atomicAdd(&counts[v], 1u);
    if params.misc.w == 1u {
        return;
    }
    voxel_of[i] = v;
    // the offset from the voxel's corner in voxel units, in [0, 1) (clamped particles aside)
    let offset = clamp((p - params.lo.xyz) * params.lo.w - vec3<f32>(c), vec3<f32>(0.0), vec3<f32>(1.0));
    let scale = f32(params.misc.y);
    atomicAdd(&sums[3u * v], i32(round(offset.x * scale)));
    atomicAdd(&sums[3u * v + 1u], i32(round(offset.y * scale)));
    atomicAdd(&sums[3u * v + 2u], i32(round(offset.z * scale)));
}

// The voxel at c + d: its count, or -1 outside the domain.
fn count_at(c: vec3<i32>, d: vec3<i32>) -> i32 {
    let n = c + d;
    let dims = vec3<i32>(params.dims.xyz);
    if any(n < vec3<i32>(0)) || any(n >= dims) {
        return -1;
    }
    return i32(atomicLoad(&counts[index_of(vec3<u32>(n))]));
}

fn voxel_coord(v: u32) -> vec3<i32> {
    let x = v % params.dims.x;
    let y = (v / params.dims.x) % params.dims.y;
    let z = v / (params.dims.x * params.dims.y);
    return vec3<i32>(i32(x), i32(y), i32(z));
}

@compute @workgroup_size(64)
fn cs_first(@builtin(global_invocation_id) id: vec3<u32>) {
    let v = invocation(id);
    let total = params.dims.x * params.dims.y * params.dims.z;
    if v >= total {
        return;
    }
    var label = 0u;
    if atomicLoad(&counts[v]) > 0u {
        let c = voxel_coord(v);
        let dims = vec3<i32>(params.dims.xyz);
        if any(c == vec3<i32>(0)) || any(c + vec3<i32>(1) == dims) {
            label = 1u;
        } else {
            for (var k = 0; k < 27; k++) {
                if k == 13 {
                    continue;
                }
                let d = vec3<i32>(k % 3 - 1, (k / 3) % 3 - 1, k / 9 - 1);
                if count_at(c, d) == 0 {
                    label = 1u;
                    break;
                }
            }
        }
    }
    labels[v] = label;
}

@compute @workgroup_size(64)
fn cs_second(@builtin(global_invocation_id) id: vec3<u32>) {
    let v = invocation(id);
    let total = params.dims.x * params.dims.y * params.dims.z;
    if v >= total {
        return;
    }
    if atomicLoad(&counts[v]) == 0u || labels[v] == 1u {
        return;
    }
    let c = voxel_coord(v);
    let dims = vec3<i32>(params.dims.xyz);
    for (var k = 0; k < 27; k++) {
        if k == 13 {
            continue;
        }
        let n = c + vec3<i32>(k % 3 - 1, (k / 3) % 3 - 1, k / 9 - 1);
        if any(n < vec3<i32>(0)) || any(n >= dims) {
            continue;
        }
        let w = index_of(vec3<u32>(n));
        // a neighbour's first-layer label (1) was written by cs_first; this pass writes only 2
        if labels[w] == 1u && atomicLoad(&counts[w]) <= params.misc.x {
            labels[v] = 2u;
            return;
        }
    }
}
