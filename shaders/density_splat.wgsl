// Density splatting, four z planes per pass (Iwasaki et al., §4.1): every particle of the
// pass's z-cluster is drawn as a screen-aligned square covering its influence disk on the grid
// plane; each fragment (one grid point in x, y) adds the particle's kernel value for the four
// planes to the R, G, B and A channels of a float target with additive blending. The points are
// sorted by slab of four planes on the GPU (src/density/bins.rs), and a pass draws the slabs
// that reach its planes (`cs_draws` counts their points for its indirect draw; a point of them
// farther than its radius from the planes adds exact zeros). Each instance is (x, y, z, radius)
// and a weight: its square is its own radius wide, its kernel is measured
// against the reference radius h (`constant` is h's), as the CPU path's `Kernel::weighted_r2`
// does, times its weight (the boundary calibration's, issue 35; 1 otherwise).
//
// The arithmetic is the CPU path's (src/density/cpu.rs): grid point x = origin.x + i * spacing,
// r^2 = dx^2 + (dy^2 + dz^2); the kernels are in common.wgsl, prepended.

struct Params {
    origin: vec3<f32>,
    spacing: f32,
    // grid points along x and y
    dims: vec2<f32>,
    // the reference radius
    h: f32,
    // 2835 / (736 pi h^3) for Wyvill, 8 / (pi h^3) for the cubic spline, of the reference h
    constant: f32,
    // z of the pass's four planes
    planes: vec4<f32>,
    // 0: Wyvill, 1: cubic spline
    kernel: u32,
    // the pass's first plane and how many of its four lie in the grid (`cs_unpack`)
    first_plane: u32,
    plane_count: u32,
    // the first slab of points the pass draws
    first_slab: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
// the points sorted by slab, and where each slab's points start
@group(0) @binding(3) var<storage, read> instances: array<Point>;
@group(0) @binding(4) var<storage, read> slab_start: array<u32>;

struct VertexOut {
    @builtin(position) position: vec4<f32>,
    @location(0) @interpolate(flat) centre: vec4<f32>,
    @location(1) @interpolate(flat) weight: f32,
}

@vertex
fn vs_main(
    @builtin(vertex_index) vertex: u32,
    @builtin(instance_index) instance: u32,
) -> VertexOut {
    let point = instances[slab_start[params.first_slab] + instance];
    let particle = point.at;
    let weight = point.weight;
    // two triangles over the square [x - r, x + r] x [y - r, y + r] of the instance's radius r,
    // in framebuffer pixels where grid point i sits at the centre of pixel i
    let corners = array<vec2<f32>, 6>(vec2(-1.0, -1.0), vec2(1.0, -1.0), vec2(1.0, 1.0), vec2(-1.0, -1.0), vec2(1.0, 1.0), vec2(-1.0, 1.0));
    var out: VertexOut;
    if weight == 0.0 {
        // a point that adds nothing (the boundary calibration weighs the particles it draws
        // by their refined points, and a buried point, 0): its square outside the target, no
        // fragment drawn (the same sums: it adds 0 to each)
        out.position = vec4<f32>(-2.0, -2.0, 0.0, 1.0);
        out.centre = particle;
        out.weight = 0.0;
        return out;
    }
    let c = corners[vertex];
    let world = particle.xy + c * particle.w;
    let pixel = (world - params.origin.xy) / params.spacing + vec2<f32>(0.5, 0.5);
    let ndc = vec2<f32>(pixel.x / params.dims.x * 2.0 - 1.0, 1.0 - pixel.y / params.dims.y * 2.0);
    out.position = vec4<f32>(ndc, 0.0, 1.0);
    out.centre = particle;
    out.weight = weight;
    return out;
}

fn kernel_r2(r2: f32, radius: f32) -> f32 {
    return density_kernel_r2(r2, radius, params.constant, params.kernel);
}

@fragment
fn fs_main(in: VertexOut) -> @location(0) vec4<f32> {
    let i = floor(in.position.x);
    let j = floor(in.position.y);
    let dx = params.origin.x + i * params.spacing - in.centre.x;
    let dy = params.origin.y + j * params.spacing - in.centre.y;
    let dz = params.planes - vec4<f32>(in.centre.z);
    let dyz2 = vec4<f32>(dy * dy) + dz * dz;
    let r2 = vec4<f32>(dx * dx) + dyz2;
    let r = in.centre.w;
    return in.weight * vec4<f32>(kernel_r2(r2.x, r), kernel_r2(r2.y, r), kernel_r2(r2.z, r), kernel_r2(r2.w, r));
}

// For a grid that stays on the GPU (issue 37): the pass's four planes copied from the target
// into the grid's buffer (x fastest, as `DensityGrid`), channel c into plane first_plane + c.
@group(0) @binding(1) var planes_in: texture_2d<f32>;
@group(0) @binding(2) var<storage, read_write> grid_out: array<f32>;

@compute @workgroup_size(8, 8, 1)
fn cs_unpack(@builtin(global_invocation_id) id: vec3<u32>) {
    let nx = u32(params.dims.x);
    let ny = u32(params.dims.y);
    if id.x >= nx || id.y >= ny {
        return;
    }
    let v = textureLoad(planes_in, vec2<i32>(id.xy), 0);
    for (var c = 0u; c < params.plane_count; c++) {
        grid_out[id.x + nx * (id.y + ny * (params.first_plane + c))] = v[c];
    }
}

// Each pass's indirect draw: 6 vertices for each point of its slabs, `slabs[g]` (first, last +
// 1; one invocation a pass).
@group(0) @binding(5) var<storage, read> slabs: array<vec2<u32>>;
@group(0) @binding(6) var<storage, read_write> draws: array<vec4<u32>>;

@compute @workgroup_size(1)
fn cs_draws(@builtin(global_invocation_id) id: vec3<u32>) {
    let s = slabs[id.x];
    draws[id.x] = vec4<u32>(6u, slab_start[s.y] - slab_start[s.x], 0u, 0u);
}
