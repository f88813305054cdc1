// The boundary calibration's weights on the GPU (issue 37): the twin of
// `pipeline::boundary::boundary_weights` (src/pipeline/boundary/mod.rs derives the rule). Each
// refined point ("sheet" point) j gets the weight w_j that puts the density at its target,
// half a spacing out along its normal, at the iso-value, solved by Jacobi steps from w = 1; a
// lone point gets the weight of a ball of one particle's volume, blended by how alone it is.
// The points are binned as the gather pass bins them (`BinnedPoints`), each carrying its index
// in the chain's order (interior particles first, then the sheet), so that a sum tells the two
// apart and reads a sheet point's current weight. Sums are written, not blended: no atomics,
// the order of the terms fixed by the bins, so runs are reproducible.

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
    // interior points (indices below), sheet points (indices from `interior` on)
    interior: u32,
    sheet: u32,
    // half a spacing, the iso-value, a lone ball's radius squared, the largest weight
    half_spacing: f32,
    tau: f32,
    lone_r2: f32,
    max_weight: f32,
}

// `RawPoint` with the index it keeps in its padding
struct IndexedPoint {
    at: vec4<f32>,
    weight: f32,
    index: u32,
    pad0: u32,
    pad1: u32,
}

// a sheet point: position and kernel radius (w); outward normal (zero: none) and its own
// weight (w)
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

// The densities at x of the interior points (x) and of the sheet points (y), these with their
// own weights times the current `w_in` when `weighted`.
fn sums(x: vec3<f32>, weighted: bool) -> vec2<f32> {
    let range = bin_range(x, params.bin_origin, params.bin_size, params.bins, params.reach);
    let lo = range.lo;
    let hi = range.hi;
    var inner = 0.0;
    var outer = 0.0;
    for (var bz = lo.z; bz <= hi.z; bz++) {
        for (var by = lo.y; by <= hi.y; by++) {
            let row = (u32(bz) * params.bins.y + u32(by)) * params.bins.x;
            let first = bin_start[row + u32(lo.x)];
            let end = bin_start[row + u32(hi.x) + 1u];
            for (var n = first; n < end; n++) {
                let p = points[n];
                let d = x - p.at.xyz;
                let r2 = d.x * d.x + (d.y * d.y + d.z * d.z);
                let k = density_kernel_r2(r2, p.at.w, params.constant, params.kernel);
                if p.index < params.interior {
                    inner += p.weight * k;
                } else {
                    var w = p.weight;
                    if weighted {
                        w *= w_in[p.index - params.interior];
                    }
                    outer += w * k;
                }
            }
        }
    }
    return vec2<f32>(inner, outer);
}

// the sheet point of an invocation (rows of 65,535 workgroups of 64)
fn sheet_index(id: vec3<u32>) -> u32 {
    return id.x + id.y * 65535u * 64u;
}

// Per sheet point: its target, how alone it is (1 - the other points' density at it over its
// own peak, in [0, 1]), its lone ball's weight and the interior's density at the target.
@compute @workgroup_size(64)
fn targets_pass(@builtin(global_invocation_id) id: vec3<u32>) {
    let j = sheet_index(id);
    if j >= params.sheet {
        return;
    }
    let s = sheet[j];
    let x = s.at.xyz;
    let base = s.normal.w;
    let own = base * density_kernel_r2(0.0, s.at.w, params.constant, params.kernel);
    let at_x = sums(x, false);
    // the CPU adds the interior only while the others are under the point's own term: alone is
    // 0 either way past it
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
    targets[j] = Target(vec4<f32>(at, alone), lone, sums(at, false).x, 0.0, 0.0);
    // the Jacobi steps start from w = 1 (the first step's `w_in`, bound here as `w_out`)
    w_out[j] = 1.0;
}

// One Jacobi step: the sheet's density at each target with the weights `w_in`, each weight
// scaled so that the target holds the iso-value less the interior's share there.
@compute @workgroup_size(64)
fn step(@builtin(global_invocation_id) id: vec3<u32>) {
    let j = sheet_index(id);
    if j >= params.sheet {
        return;
    }
    let t = targets[j];
    let alone = t.at.w;
    if alone >= 1.0 {
        w_out[j] = t.lone;
        return;
    }
    let w = w_in[j];
    let sheet_sum = sums(t.at.xyz, true).y;
    let want = max(params.tau - t.inside, 0.0);
    var boundary = w;
    if sheet_sum > 0.0 {
        boundary = clamp(w * want / sheet_sum, 0.0, params.max_weight);
    }
    w_out[j] = alone * t.lone + (1.0 - alone) * boundary;
}

// the binned points again, written (`apply` alone binds them so)
@group(0) @binding(7) var<storage, read_write> binned_rw: array<IndexedPoint>;

// Per binned point: a sheet point's weight in the density becomes its own times its solved one
// (`w_in`), in place, before the grid is filled from the same points.
@compute @workgroup_size(64)
fn apply(@builtin(global_invocation_id) id: vec3<u32>) {
    let n = sheet_index(id);
    if n >= params.interior + params.sheet {
        return;
    }
    let index = binned_rw[n].index;
    if index >= params.interior {
        binned_rw[n].weight *= w_in[index - params.interior];
    }
}
