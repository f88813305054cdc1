// Ray casting to the iso-surface with PCA normals (Xiao et al.), the GPU twin of src/raycast
// (whose CPU functions are the specification: `Caster::first_crossing`, `surface_normal`,
// `Caster::pca_normal`, `blend`, `bilateral`, `linalg::symmetric_eigen`).
//
// 1. cs_init, cs_step, one thread per pixel of a band of rows: the view ray meets the spheres of
//    its screen tile exactly (entry, exit, thickness from the summed chords); it is marched on one
//    step grid from the first entry to the last exit through the density of the points (a uniform
//    grid per group of similar radii, cells one group radius wide, as `ExactDensity`'s), the
//    first crossing refined by bisection; the normal there is the density gradient blended with
//    the PCA normal of the neighbours (one more grid, one PCA reach wide).
// 2. cs_filter: the bilateral filter of the normal map, into the output textures with the
//    water's tint.
// The shading is the splats' (`splat::shade`, on the CPU after the read-back).
//
// Why cs_step is a resumable state machine: llvmpipe (lavapipe) ends every loop of an invocation
// once the loops of that invocation have run 65,535 iterations in all (LP_MAX_TGSI_LOOP_ITERATIONS
// in gallivm, one counter shared by all loops of the shader, counted per SIMD group), silently,
// with whatever the variables hold. A ray through dense points takes far more (855 points per
// density sample on the column's chain points, tens of samples per ray), so a plain loop nest
// stopped marching after about ten samples there. cs_step instead runs ONE loop of `band.budget`
// iterations, the same count for every lane, each iteration one unit of work (one sphere of the
// tile, one point of a sum, or the step to the next row of cells or the next sample), and keeps
// the pixel's state in `state` between dispatches; the host dispatches it until `unfinished`
// stays 0. The only other loop that runs inside it, the Jacobi sweeps of the PCA normal, runs
// once per pixel. The same bound keeps every dispatch short on real GPUs (no watchdog resets).

struct Params {
    inv_view: mat4x4<f32>,
    // viewport width and height, tan of the half angles (or half extents, orthographic)
    screen: vec4<f32>,
    // orthographic (1) or perspective (0), tiles along x, width, height
    a: vec4<u32>,
    // absolute iso-value, march step (world), reference radius h, PCA radius in point radii
    b: vec4<f32>,
    // bisection steps, normals (0 blended, 1 gradient, 2 PCA), kernel (0 Wyvill, 1 cubic spline),
    // bilateral half width
    c: vec4<u32>,
    // blend d, blend k, blend max, bilateral sigma in pixels
    d: vec4<f32>,
    // bilateral sigma in depth (world), density reach, PCA reach
    e: vec4<f32>,
    // grids of the density's radius groups (0..n), the PCA grid's index (n)
    g: vec4<u32>,
    // the water's colour before the tint (rgb); its absorption per world length (rgb)
    base: vec4<f32>,
    absorb: vec4<f32>,
}

// A uniform grid of points: origin, cell; cells along x, y, z and where their starts are in
// `cells`; where their items are (compressed rows: the points of cell c are
// cells[at + cells[starts + c] .. at + cells[starts + c + 1]]).
struct Grid {
    g: vec4<f32>,
    dims: vec4<u32>,
    at: vec4<u32>,
}

// mirror: MAX_GRIDS in src/raycast/gpu.rs
const MAX_GRIDS: u32 = 33u;

struct Grids {
    grid: array<Grid, MAX_GRIDS>,
}

@group(0) @binding(0) var<uniform> p: Params;
// centre and radius of each point
@group(0) @binding(1) var<storage, read> points: array<vec4<f32>>;
// the points of each 16x16 screen tile (CSR)
@group(0) @binding(2) var<storage, read> tile_start: array<u32>;
@group(0) @binding(3) var<storage, read> tile_items: array<u32>;
// every grid's starts and items
@group(0) @binding(4) var<storage, read> cells: array<u32>;
// Each point's factor on its density term (the boundary calibration's weights; 1 without).
// Mirror: Points::weight. A negative one (DROPPED, src/pipeline/boundary/gpu.rs: a point the
// calibration's factors left out, weighed on the GPU) is a point that is not there: no sphere,
// no term, no PCA neighbour, as the CPU's caster of the points it keeps.
@group(0) @binding(16) var<storage, read> weights: array<f32>;
@group(0) @binding(12) var<uniform> grids: Grids;
// per pixel: unfiltered normal and hit depth (w < 0: no hit)
@group(0) @binding(6) var<storage, read_write> hits: array<vec4<f32>>;
// per pixel: entry depth (or -1), thickness, density samples
@group(0) @binding(7) var<storage, read_write> extra: array<vec4<f32>>;

// One pixel's progress between dispatches of cs_step.
struct State {
    // phase | row << 4 | bisection steps done << 16, cursor, end of the cursor's range, march step
    u: vec4<u32>,
    // entry, exit, below, above (from the gradient on, `below` holds the hit)
    f: vec4<f32>,
    // sums: density in x; gradient in xyz; PCA: total weight, weighted offsets
    a: vec4<f32>,
    // PCA: covariance sums xx, xy, xz, count; while entering: chords in x
    b: vec4<f32>,
    // PCA: covariance sums yy, yz, zz; density samples taken in w
    c: vec4<f32>,
}

// The rows of the band this dispatch works on: first row, rows, loop iterations per dispatch.
struct Band {
    y0: u32,
    rows: u32,
    budget: u32,
    groups_x: u32,
    groups_y: u32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
}

@group(0) @binding(9) var<storage, read_write> state: array<State>;
@group(0) @binding(10) var<uniform> band: Band;
// pixels of the band not done after this dispatch
@group(0) @binding(11) var<storage, read_write> unfinished: atomic<u32>;
// the workgroups of the next run of cs_step (an indirect dispatch)
@group(0) @binding(13) var<storage, read_write> next_run: array<u32, 3>;
// what the filter leaves for the shading and the optics: (tint, 1) and (normal, view depth) per
// covered pixel, zero elsewhere (the splats' accumulation targets hold the same)
@group(0) @binding(14) var colour_out: texture_storage_2d<rgba32float, write>;
@group(0) @binding(15) var normal_depth_out: texture_storage_2d<rgba32float, write>;

// mirror: TILE in src/raycast/cpu.rs
const TILE: u32 = 16u;
const PI: f32 = 3.14159265358979;
// mirror: VOLUME_SHARE in src/raycast/cpu.rs
const VOLUME_SHARE: f32 = 3.0 / (32.0 * PI);

// `Kernel::weighted_r2`: the contribution of a point of radius hj at squared distance r2.
fn kernel_r2(r2: f32, hj: f32) -> f32 {
    let h = p.b.z;
    if (p.c.z == 0u) {
        let a2 = r2 * (1.0 / (hj * hj));
        let poly = ((-4.0 / 9.0 * a2 + 17.0 / 9.0) * a2 - 22.0 / 9.0) * a2 + 1.0;
        let v = 2835.0 / (736.0 * PI * h * h * h) * poly;
        return select(0.0, v, a2 < 1.0);
    }
    let r = sqrt(r2);
    if (r >= hj) {
        return 0.0;
    }
    let q = 2.0 * (r / hj);
    let sigma = 8.0 / (PI * h * h * h);
    if (q < 1.0) {
        return sigma * (1.0 - 1.5 * q * q + 0.75 * q * q * q);
    }
    let t = 2.0 - q;
    return sigma * 0.25 * t * t * t;
}

// `Kernel::weighted_and_gradient`'s gradient, for the offset d = x - x_j.
fn kernel_gradient(d: vec3<f32>, hj: f32) -> vec3<f32> {
    let h = p.b.z;
    let r2 = dot(d, d);
    if (p.c.z == 0u) {
        let inv = 1.0 / (hj * hj);
        let a2 = r2 * inv;
        if (a2 >= 1.0) {
            return vec3<f32>(0.0);
        }
        let c = 2835.0 / (736.0 * PI * h * h * h);
        let slope = (-4.0 / 3.0 * a2 + 34.0 / 9.0) * a2 - 22.0 / 9.0;
        return d * (c * slope * 2.0 * inv);
    }
    let r = sqrt(r2);
    if (r >= hj || r <= 0.0) {
        return vec3<f32>(0.0);
    }
    let q = 2.0 * (r / hj);
    let sigma = 8.0 / (PI * h * h * h);
    var df = 0.0;
    if (q < 1.0) {
        df = -3.0 * q + 2.25 * q * q;
    } else {
        let t = 2.0 - q;
        df = -0.75 * t * t;
    }
    return d * (sigma * df * 2.0 / (hj * r));
}

// The cell range (clamped to the grid) around x: min corner and max corner, inclusive.
fn cell_of(x: vec3<f32>, origin: vec3<f32>, cell: f32, dims: vec3<u32>) -> vec3<i32> {
    let c = floor((x - origin) / cell);
    let hi = vec3<f32>(dims) - vec3<f32>(1.0);
    return vec3<i32>(clamp(c, vec3<f32>(0.0), hi));
}

// The range of `cells` (absolute) of row `slot` (0..9: dy, dz in -1..1) of the 27 cells about x
// in grid `gi`: a run of consecutive cells along x, whose points are consecutive; empty off the
// grid.
fn row_span(x: vec3<f32>, gi: u32, slot: u32) -> vec2<u32> {
    let gr = grids.grid[gi];
    let dims = gr.dims.xyz;
    let c = cell_of(x, gr.g.xyz, gr.g.w, dims);
    let y = c.y + i32(slot % 3u) - 1;
    let z = c.z + i32(slot / 3u) - 1;
    if (y < 0 || z < 0 || y >= i32(dims.y) || z >= i32(dims.z)) {
        return vec2<u32>(0u);
    }
    let x0 = u32(max(c.x - 1, 0));
    let x1 = u32(min(c.x + 1, i32(dims.x) - 1));
    let base = dims.x * (u32(y) + dims.y * u32(z));
    let s0 = cells[gr.dims.w + base + x0];
    let s1 = cells[gr.dims.w + base + x1 + 1u];
    return vec2<u32>(gr.at.x + s0, gr.at.x + s1);
}

// Row `row` of a sum of phase `phase`: the PCA sum's 9 rows in the PCA grid, the others' 9 rows
// in each radius group's grid.
fn sum_row(x: vec3<f32>, phase: u32, row: u32) -> vec2<u32> {
    let gi = select(row / 9u, p.g.y, phase == PCA);
    return row_span(x, gi, row % 9u);
}

fn sum_rows(phase: u32) -> u32 {
    return select(9u * p.g.x, 9u, phase == PCA);
}

// The least eigenvector of a symmetric 3x3 matrix (rows m0, m1, m2; `symmetric_eigen`,
// shaders/eigen.wgsl); w = 1 when the least eigenvalue is below half the middle one.
fn least_eigenvector(m0: vec3<f32>, m1: vec3<f32>, m2: vec3<f32>) -> vec4<f32> {
    let e = symmetric_eigen(m0, m1, m2);
    let ok = e.values.x < 0.5 * e.values.y && any(e.least != vec3<f32>(0.0));
    return vec4<f32>(e.least, select(0.0, 1.0, ok));
}

// The PCA normal from its sums (`Caster::pca_normal`); w = 0 where there is none.
fn pca_finish(total: f32, count: f32, weighted: vec3<f32>, s0: vec3<f32>, s1: vec3<f32>) -> vec4<f32> {
    if (count < 4.0 || !(total > 0.0)) {
        return vec4<f32>(0.0);
    }
    let mean = weighted / total;
    // the covariance (symmetric): E[e e^T] - mean mean^T
    let xx = s0.x / total - mean.x * mean.x;
    let xy = s0.y / total - mean.x * mean.y;
    let xz = s0.z / total - mean.x * mean.z;
    let yy = s1.x / total - mean.y * mean.y;
    let yz = s1.y / total - mean.y * mean.z;
    let zz = s1.z / total - mean.z * mean.z;
    return least_eigenvector(vec3<f32>(xx, xy, xz), vec3<f32>(xy, yy, yz), vec3<f32>(xz, yz, zz));
}

// `surface_normal`'s blend of the outward gradient direction `basic` with the PCA normal.
fn blend_normal(basic: vec3<f32>, pca4: vec4<f32>) -> vec3<f32> {
    if (pca4.w == 0.0) {
        return basic;
    }
    var pca = pca4.xyz;
    if (dot(pca, basic) < 0.0) {
        pca = -pca;
    }
    if (p.c.y == 2u) {
        return pca;
    }
    let w = min(exp(p.d.x * (dot(basic, pca) - p.d.y)), p.d.z);
    let n = (1.0 - w) * basic + w * pca;
    let nl = length(n);
    return select(basic, n / nl, nl > 0.0);
}

// The world ray through a pixel position (`View::world_ray`): origin and direction (view depth t
// at origin + t dir).
fn world_ray(pixel: vec2<f32>) -> array<vec3<f32>, 2> {
    let ndc = vec2<f32>(pixel.x / p.screen.x * 2.0 - 1.0, 1.0 - pixel.y / p.screen.y * 2.0);
    var o = vec3<f32>(0.0);
    var d = vec3<f32>(ndc * p.screen.zw, -1.0);
    if (p.a.x == 1u) {
        o = vec3<f32>(ndc * p.screen.zw, 0.0);
        d = vec3<f32>(0.0, 0.0, -1.0);
    }
    return array<vec3<f32>, 2>((p.inv_view * vec4<f32>(o, 1.0)).xyz, (p.inv_view * vec4<f32>(d, 0.0)).xyz);
}

// the phases of a pixel in cs_step
const ENTER: u32 = 0u;
const MARCH: u32 = 1u;
const BISECT: u32 = 2u;
const GRADIENT: u32 = 3u;
const PCA: u32 = 4u;
const DONE: u32 = 5u;

// The pixel of thread `id` of the band, or none (x = width).
fn band_pixel(id: vec3<u32>) -> vec2<u32> {
    if (id.x >= p.a.z || id.y >= band.rows || band.y0 + id.y >= p.a.w) {
        return vec2<u32>(p.a.z, 0u);
    }
    return vec2<u32>(id.x, band.y0 + id.y);
}

@compute @workgroup_size(8, 8)
fn cs_init(@builtin(global_invocation_id) id: vec3<u32>) {
    let px = band_pixel(id);
    if (px.x >= p.a.z) {
        return;
    }
    let i = px.y * p.a.z + px.x;
    let tile = (px.y / TILE) * p.a.y + px.x / TILE;
    var st: State;
    st.u = vec4<u32>(ENTER, tile_start[tile], tile_start[tile + 1u], 0u);
    st.f = vec4<f32>(3.0e38, -1.0, 0.0, 0.0);
    st.a = vec4<f32>(0.0);
    st.b = vec4<f32>(0.0);
    st.c = vec4<f32>(0.0);
    state[id.y * p.a.z + id.x] = st;
    hits[i] = vec4<f32>(0.0, 0.0, 0.0, -1.0);
    extra[i] = vec4<f32>(-1.0, 0.0, 0.0, 0.0);
    // the first run of cs_step runs
    atomicStore(&unfinished, 1u);
}

// Before each run of cs_step: the whole band while a pixel of it is left after the last run
// (`unfinished`, which cs_step counts again), else nothing; the runs after the last pixel is
// done cost one empty dispatch each.
@compute @workgroup_size(1)
fn cs_args() {
    let left = atomicLoad(&unfinished);
    atomicStore(&unfinished, 0u);
    next_run[0] = select(0u, band.groups_x, left > 0u);
    next_run[1] = band.groups_y;
    next_run[2] = 1u;
}

// Where the sample of a phase lies along the ray: march step k, the bisection's middle, the hit.
fn sample_t(phase: u32, k: u32, f: vec4<f32>, dt: f32) -> f32 {
    if (phase == MARCH) {
        return f.x + f32(k) * dt;
    }
    if (phase == BISECT) {
        return 0.5 * (f.z + f.w);
    }
    return f.z;
}

@compute @workgroup_size(8, 8)
fn cs_step(@builtin(global_invocation_id) id: vec3<u32>) {
    let px = band_pixel(id);
    if (px.x >= p.a.z) {
        return;
    }
    let i = px.y * p.a.z + px.x;
    let si = id.y * p.a.z + id.x;
    var st = state[si];
    var phase = st.u.x & 15u;
    if (phase == DONE) {
        return;
    }
    var row = (st.u.x >> 4u) & 4095u;
    var n = st.u.x >> 16u;
    var s = st.u.y;
    var s_end = st.u.z;
    var k = st.u.w;
    var f = st.f;
    var acc = st.a;
    var acc1 = st.b;
    var acc2 = st.c;
    let ray = world_ray(vec2<f32>(f32(px.x) + 0.5, f32(px.y) + 0.5));
    let o = ray[0];
    let d = ray[1];
    let a = dot(d, d);
    let iso = p.b.x;
    let dt = p.b.y / sqrt(a);
    let reach2 = p.e.z * p.e.z;
    // the sample point of the sum in progress
    var x = o + sample_t(phase, k, f, dt) * d;
    // ONE loop, the same iterations for every lane (see the top of the file)
    for (var it = 0u; it < band.budget; it++) {
        if (phase == DONE) {
            break;
        }
        if (phase == ENTER) {
            if (s < s_end) {
                let item = tile_items[s];
                s += 1u;
                if (weights[item] < 0.0) {
                    continue;
                }
                let q = points[item];
                let oc = o - q.xyz;
                let b = dot(oc, d);
                let disc = b * b - a * (dot(oc, oc) - q.w * q.w);
                if (disc > 0.0) {
                    let root = sqrt(disc);
                    let t0 = max((-b - root) / a, 0.0);
                    let t1 = (-b + root) / a;
                    if (t1 > t0) {
                        acc1.x += t1 - t0;
                        f.x = min(f.x, t0);
                        f.y = max(f.y, t1);
                    }
                }
                continue;
            }
            if (f.y < 0.0) {
                phase = DONE;
                continue;
            }
            extra[i] = vec4<f32>(f.x, acc1.x * sqrt(a) * VOLUME_SHARE, 0.0, -1.0);
            acc1 = vec4<f32>(0.0);
            phase = MARCH;
            k = 0u;
            x = o + f.x * d;
            row = 0u;
            let span = sum_row(x, MARCH, 0u);
            s = span.x;
            s_end = span.y;
            acc = vec4<f32>(0.0);
            continue;
        }
        if (s < s_end) {
            // one point of the sum
            let c = cells[s];
            let q = points[c];
            s += 1u;
            if (weights[c] < 0.0) {
                continue;
            }
            if (phase == PCA) {
                let e = q.xyz - x;
                // CellGrid::for_each_within's test, then the weight's own reach
                if (dot(e, e) <= reach2) {
                    let r = length(e) / (p.b.w * q.w);
                    if (r < 1.0) {
                        let w = 1.0 - r * r * r;
                        acc += vec4<f32>(w, e * w);
                        acc1 += vec4<f32>(e * (e.x * w), 1.0);
                        acc2 += vec4<f32>(e.y * e.y * w, e.y * e.z * w, e.z * e.z * w, 0.0);
                    }
                }
            } else {
                let e = x - q.xyz;
                let r2 = dot(e, e);
                if (r2 < q.w * q.w) {
                    if (phase == GRADIENT) {
                        acc += vec4<f32>(weights[c] * kernel_gradient(e, q.w), 0.0);
                    } else {
                        acc.x += weights[c] * kernel_r2(r2, q.w);
                    }
                }
            }
            continue;
        }
        if (row + 1u < sum_rows(phase)) {
            row += 1u;
            let span = sum_row(x, phase, row);
            s = span.x;
            s_end = span.y;
            continue;
        }
        // the sum is complete: what it decides, and the next sum
        var next = phase;
        if (phase == MARCH || phase == BISECT) {
            acc2.w += 1.0;
            let inside = acc.x >= iso;
            if (phase == MARCH) {
                if (inside) {
                    if (k == 0u) {
                        f.z = f.x;
                        next = GRADIENT;
                    } else {
                        f.z = f.x + f32(k - 1u) * dt;
                        f.w = f.x + f32(k) * dt;
                        n = 0u;
                        next = BISECT;
                    }
                } else {
                    k += 1u;
                    let steps = u32(min(floor((f.y - f.x) / dt) + 1.0, 4.0e9));
                    if (k > steps || f.x + f32(k) * dt > f.y) {
                        next = DONE;
                    }
                }
            } else {
                let mid = 0.5 * (f.z + f.w);
                if (inside) {
                    f.w = mid;
                } else {
                    f.z = mid;
                }
                n += 1u;
            }
            if (next == BISECT && n >= p.c.x) {
                f.z = 0.5 * (f.z + f.w);
                next = GRADIENT;
            }
        } else if (phase == GRADIENT) {
            let g = -acc.xyz;
            let gl = length(g);
            if (!(gl > 0.0)) {
                next = DONE;
            } else if (p.c.y == 1u) {
                hits[i] = vec4<f32>(g / gl, f.z);
                next = DONE;
            } else {
                // the outward gradient direction waits in hits (w < 0 until done)
                hits[i] = vec4<f32>(g / gl, -1.0);
                next = PCA;
            }
        } else {
            let pca4 = pca_finish(acc.x, acc1.w, acc.yzw, acc1.xyz, acc2.xyz);
            let basic = hits[i].xyz;
            hits[i] = vec4<f32>(blend_normal(basic, pca4), f.z);
            next = DONE;
        }
        phase = next;
        if (phase != DONE) {
            x = o + sample_t(phase, k, f, dt) * d;
            row = 0u;
            let span = sum_row(x, phase, 0u);
            s = span.x;
            s_end = span.y;
            let samples = acc2.w;
            acc = vec4<f32>(0.0);
            acc1 = vec4<f32>(0.0);
            acc2 = vec4<f32>(0.0, 0.0, 0.0, samples);
        }
    }
    st.u = vec4<u32>(phase | (row << 4u) | (n << 16u), s, s_end, k);
    st.f = f;
    st.a = acc;
    st.b = acc1;
    st.c = acc2;
    state[si] = st;
    if (phase != ENTER) {
        extra[i].z = acc2.w;
    }
    if (phase != DONE) {
        atomicAdd(&unfinished, 1u);
    }
}

// `bilateral`: each hit pixel's normal, the normalised weighted sum of the hit normals around it.
@compute @workgroup_size(8, 8)
fn cs_filter(@builtin(global_invocation_id) id: vec3<u32>) {
    let width = p.a.z;
    let height = p.a.w;
    if (id.x >= width || id.y >= height) {
        return;
    }
    let i = id.y * width + id.x;
    let h0 = hits[i];
    let at = vec2<i32>(id.xy);
    if (h0.w < 0.0) {
        textureStore(colour_out, at, vec4<f32>(0.0));
        textureStore(normal_depth_out, at, vec4<f32>(0.0));
        return;
    }
    // `finish`: the tint of the water's thickness along the ray
    let tint = p.base.xyz * exp(-p.absorb.xyz * extra[i].y);
    textureStore(colour_out, at, vec4<f32>(tint, 1.0));
    let r = i32(p.c.w);
    if (r == 0) {
        textureStore(normal_depth_out, at, h0);
        return;
    }
    let ks = -0.5 / (p.d.w * p.d.w);
    let kz = -0.5 / (p.e.x * p.e.x);
    var sum = vec3<f32>(0.0);
    for (var dy = -r; dy <= r; dy++) {
        for (var dx = -r; dx <= r; dx++) {
            let u = i32(id.x) + dx;
            let v = i32(id.y) + dy;
            if (u < 0 || v < 0 || u >= i32(width) || v >= i32(height)) {
                continue;
            }
            let hj = hits[u32(v) * width + u32(u)];
            if (hj.w >= 0.0) {
                let dz = hj.w - h0.w;
                sum += hj.xyz * exp(ks * f32(dx * dx + dy * dy) + kz * dz * dz);
            }
        }
    }
    let l = length(sum);
    textureStore(normal_depth_out, at, vec4<f32>(select(h0.xyz, sum / l, l > 0.0), h0.w));
}
