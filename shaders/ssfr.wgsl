// Narrow-band screen-space fluid rendering (Oliveira and Paiva), the GPU twin of
// `src/ssfr/cpu.rs` and the filters of `src/ssfr/mod.rs`: one invocation per pixel in every
// pass, each pass the CPU reference's per-pixel function in the same order of operations.
//
//   cs_depth            the nearest sphere per pixel (the spheres binned into 16x16 tiles on
//                       the host, as the CPU bins them)
//   cs_narrow_range, cs_bilateral, cs_plane, cs_curvature_flow
//                       one iteration of a depth filter, src -> dst (the host ping-pongs)
//   cs_thickness        the sum of the thickness Gaussians per pixel (eqs. 1, 3; projected on
//                       the host, as the CPU projects them)
//   cs_thickness_filter the thickness's bilateral filter
//   cs_shade            normals from the filtered depth, the Beer-Lambert tint: the
//                       (tint, 1) and (normal, depth) textures the shading and the optics read
//
// No fluid is depth >= NONE (the CPU's infinity). Every loop is bounded by the window or by a
// tile's list; llvmpipe ends an invocation's loops after 65,535 iterations in total, so a tile
// list longer than that would be cut there (`GpuScreenSpace` refuses such a frame).

const NONE: f32 = 1e30;

struct Params {
    inv_view: mat4x4<f32>,
    // width, height, tan_half.x, tan_half.y
    screen: vec4<f32>,
    // orthographic (0/1), tiles along x, filter half width, -
    a: vec4<u32>,
    // sigma_px, sigma_depth, range, clamp
    b: vec4<f32>,
    // curvature step, pixel size at depth 1 (or everywhere, orthographic), thickness sigma, -
    c: vec4<f32>,
    // the water's colour before the tint (rgb)
    base: vec4<f32>,
    // absorption per world length (rgb)
    absorb: vec4<f32>,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> spheres: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> tile_starts: array<u32>;
@group(0) @binding(3) var<storage, read> tile_items: array<u32>;
@group(0) @binding(4) var<storage, read> sources: array<vec4<f32>>;
@group(0) @binding(5) var<storage, read> src: array<f32>;
@group(0) @binding(6) var<storage, read_write> dst: array<f32>;
@group(0) @binding(7) var<storage, read> thickness: array<f32>;
@group(0) @binding(8) var colour: texture_storage_2d<rgba32float, write>;
@group(0) @binding(9) var normal_depth: texture_storage_2d<rgba32float, write>;

fn width() -> u32 {
    return u32(params.screen.x);
}

fn height() -> u32 {
    return u32(params.screen.y);
}

fn covered(z: f32) -> bool {
    return z < NONE;
}

// The world ray through a pixel position (`View::world_ray`): origin and direction, the
// origin plus t times the direction at view depth t.
fn world_ray(pixel: vec2<f32>) -> array<vec3<f32>, 2> {
    let ndc = vec2<f32>(pixel.x / params.screen.x * 2.0 - 1.0, 1.0 - pixel.y / params.screen.y * 2.0);
    var o = vec3<f32>(0.0);
    var d = vec3<f32>(ndc * params.screen.zw, -1.0);
    if params.a.x != 0u {
        o = vec3<f32>(ndc * params.screen.zw, 0.0);
        d = vec3<f32>(0.0, 0.0, -1.0);
    }
    return array<vec3<f32>, 2>((params.inv_view * vec4<f32>(o, 1.0)).xyz, (params.inv_view * vec4<f32>(d, 0.0)).xyz);
}

fn tile_of(x: u32, y: u32) -> u32 {
    return (y / 16u) * params.a.y + x / 16u;
}

@compute @workgroup_size(8, 8)
fn cs_depth(@builtin(global_invocation_id) id: vec3<u32>) {
    if id.x >= width() || id.y >= height() {
        return;
    }
    let ray = world_ray(vec2<f32>(f32(id.x) + 0.5, f32(id.y) + 0.5));
    let o = ray[0];
    let len = length(ray[1]);
    let dn = ray[1] / len;
    var best = NONE;
    let t = tile_of(id.x, id.y);
    for (var k = tile_starts[t]; k < tile_starts[t + 1u]; k++) {
        let s = spheres[tile_items[k]];
        // the stable form, as the CPU: the centre's squared distance from the ray
        let oc = o - s.xyz;
        let l = dot(oc, dn);
        let q = oc - l * dn;
        let h2 = s.w * s.w - dot(q, q);
        if h2 < 0.0 {
            continue;
        }
        let hit = (-l - sqrt(h2)) / len;
        if hit > 0.0 && hit < best {
            best = hit;
        }
    }
    dst[id.y * width() + id.x] = best;
}

// The depth at (x + dx, y + dy) of `src`, NONE outside the image.
fn at(x: u32, y: u32, dx: i32, dy: i32) -> f32 {
    let u = i32(x) + dx;
    let v = i32(y) + dy;
    if u < 0 || v < 0 || u >= i32(width()) || v >= i32(height()) {
        return NONE;
    }
    return src[u32(v) * width() + u32(u)];
}

fn gauss(dx: i32, dy: i32) -> f32 {
    let k = -0.5 / (params.b.x * params.b.x);
    return exp(k * f32(dx * dx + dy * dy));
}

@compute @workgroup_size(8, 8)
fn cs_bilateral(@builtin(global_invocation_id) id: vec3<u32>) {
    if id.x >= width() || id.y >= height() {
        return;
    }
    let i = id.y * width() + id.x;
    let z0 = src[i];
    if !covered(z0) {
        dst[i] = z0;
        return;
    }
    let r = i32(params.a.z);
    let kz = -0.5 / (params.b.y * params.b.y);
    var sum = 0.0;
    var weight = 0.0;
    for (var dy = -r; dy <= r; dy++) {
        for (var dx = -r; dx <= r; dx++) {
            let z = at(id.x, id.y, dx, dy);
            if covered(z) {
                let dz = z - z0;
                let w = gauss(dx, dy) * exp(kz * dz * dz);
                sum += w * z;
                weight += w;
            }
        }
    }
    dst[i] = sum / weight;
}

// The narrow-range filter's value of a sample: dropped (a negative weight flag) beyond the
// range behind, clamped beyond it in front.
fn ranged(z: f32, z0: f32) -> vec2<f32> {
    if !covered(z) || z > z0 + params.b.z {
        return vec2<f32>(0.0, 0.0);
    }
    if z < z0 - params.b.z {
        return vec2<f32>(z0 - params.b.w, 1.0);
    }
    return vec2<f32>(z, 1.0);
}

@compute @workgroup_size(8, 8)
fn cs_narrow_range(@builtin(global_invocation_id) id: vec3<u32>) {
    if id.x >= width() || id.y >= height() {
        return;
    }
    let i = id.y * width() + id.x;
    let z0 = src[i];
    if !covered(z0) {
        dst[i] = z0;
        return;
    }
    let r = i32(params.a.z);
    var sum = 0.0;
    var weight = 0.0;
    for (var dy = -r; dy <= r; dy++) {
        for (var dx = -r; dx <= r; dx++) {
            // each pair once, as the CPU: the half window after the centre, and the centre
            if dy < 0 || (dy == 0 && dx < 0) {
                continue;
            }
            let g = gauss(dx, dy);
            if dx == 0 && dy == 0 {
                sum += g * z0;
                weight += g;
                continue;
            }
            let a = ranged(at(id.x, id.y, dx, dy), z0);
            let b = ranged(at(id.x, id.y, -dx, -dy), z0);
            if a.y > 0.0 && b.y > 0.0 {
                sum += g * (a.x + b.x);
                weight += 2.0 * g;
            }
        }
    }
    dst[i] = sum / weight;
}

fn to_q(z: f32) -> f32 {
    if params.a.x != 0u {
        return z;
    }
    return 1.0 / z;
}

fn from_q(q: f32) -> f32 {
    if params.a.x != 0u {
        return q;
    }
    return 1.0 / q;
}

fn det3(m: mat3x3<f32>) -> f32 {
    return determinant(m);
}

@compute @workgroup_size(8, 8)
fn cs_plane(@builtin(global_invocation_id) id: vec3<u32>) {
    if id.x >= width() || id.y >= height() {
        return;
    }
    let i = id.y * width() + id.x;
    let z0 = src[i];
    if !covered(z0) {
        dst[i] = z0;
        return;
    }
    let r = i32(params.a.z);
    let kz = -0.5 / (params.b.y * params.b.y);
    // normal equations of q = a + b dx + c dy (rows of the symmetric matrix as columns)
    var m0 = vec3<f32>(0.0);
    var m1 = vec3<f32>(0.0);
    var m2 = vec3<f32>(0.0);
    var rhs = vec3<f32>(0.0);
    let q0 = to_q(z0);
    for (var dy = -r; dy <= r; dy++) {
        for (var dx = -r; dx <= r; dx++) {
            let z = at(id.x, id.y, dx, dy);
            if !covered(z) || abs(z - z0) > params.b.z {
                continue;
            }
            let dz = z - z0;
            let w = gauss(dx, dy) * exp(kz * dz * dz);
            let basis = vec3<f32>(1.0, f32(dx), f32(dy));
            let q = to_q(z) - q0;
            rhs += w * basis * q;
            m0 += w * basis.x * basis;
            m1 += w * basis.y * basis;
            m2 += w * basis.z * basis;
        }
    }
    let m = mat3x3<f32>(m0, m1, m2);
    let det = det3(m);
    let scale = m0.x * m1.y * m2.z;
    if det != det || abs(det) <= 1e-9 * abs(scale) || scale == 0.0 {
        dst[i] = from_q(q0 + rhs.x / m0.x);
        return;
    }
    // Cramer's rule for the first unknown: the first column replaced by the right-hand side
    let a = det3(mat3x3<f32>(vec3<f32>(rhs.x, m0.y, m0.z), vec3<f32>(rhs.y, m1.y, m1.z), vec3<f32>(rhs.z, m2.y, m2.z)));
    dst[i] = from_q(q0 + a / det);
}

// A neighbour within the range: (depth, 1), or (0, 0).
fn near(x: u32, y: u32, dx: i32, dy: i32, z0: f32) -> vec2<f32> {
    let z = at(x, y, dx, dy);
    if covered(z) && abs(z - z0) <= params.b.z {
        return vec2<f32>(z, 1.0);
    }
    return vec2<f32>(0.0, 0.0);
}

// First and second derivative along one axis from the samples at -1 and +1.
fn axis(a: vec2<f32>, b: vec2<f32>, z0: f32) -> vec2<f32> {
    if a.y > 0.0 && b.y > 0.0 {
        return vec2<f32>(0.5 * (b.x - a.x), b.x - 2.0 * z0 + a.x);
    }
    if a.y > 0.0 {
        return vec2<f32>(z0 - a.x, 0.0);
    }
    if b.y > 0.0 {
        return vec2<f32>(b.x - z0, 0.0);
    }
    return vec2<f32>(0.0, 0.0);
}

@compute @workgroup_size(8, 8)
fn cs_curvature_flow(@builtin(global_invocation_id) id: vec3<u32>) {
    if id.x >= width() || id.y >= height() {
        return;
    }
    let i = id.y * width() + id.x;
    let z0 = src[i];
    if !covered(z0) {
        dst[i] = z0;
        return;
    }
    let x = id.x;
    let y = id.y;
    let gx = axis(near(x, y, -1, 0, z0), near(x, y, 1, 0, z0), z0);
    let gy = axis(near(x, y, 0, -1, z0), near(x, y, 0, 1, z0), z0);
    let p = near(x, y, 1, 1, z0);
    let q = near(x, y, -1, -1, z0);
    let s = near(x, y, 1, -1, z0);
    let t = near(x, y, -1, 1, z0);
    var zxy = 0.0;
    if p.y > 0.0 && q.y > 0.0 && s.y > 0.0 && t.y > 0.0 {
        zxy = 0.25 * (p.x + q.x - s.x - t.x);
    }
    var px = params.c.y * z0;
    if params.a.x != 0u {
        px = params.c.y;
    }
    let zu = gx.x / px;
    let zv = gy.x / px;
    let g = 1.0 + zu * zu + zv * zv;
    let flow = ((1.0 + zv * zv) * gx.y - 2.0 * zu * zv * zxy + (1.0 + zu * zu) * gy.y) / (g * sqrt(g));
    dst[i] = z0 + params.c.x * flow;
}

// Thickness: the sources (projected centre x, y in pixels, -1 / (2 sigma_px^2), amplitude; an
// amplitude of zero: behind the view) of the pixel's tile, cut at 3 sigma.
@compute @workgroup_size(8, 8)
fn cs_thickness(@builtin(global_invocation_id) id: vec3<u32>) {
    if id.x >= width() || id.y >= height() {
        return;
    }
    let p = vec2<f32>(f32(id.x) + 0.5, f32(id.y) + 0.5);
    var sum = 0.0;
    let t = tile_of(id.x, id.y);
    for (var k = tile_starts[t]; k < tile_starts[t + 1u]; k++) {
        let s = sources[tile_items[k]];
        if s.w == 0.0 {
            continue;
        }
        let d = p - s.xy;
        let g = exp(s.z * dot(d, d));
        if g > 0.011 {
            sum += s.w * g;
        }
    }
    dst[id.y * width() + id.x] = sum;
}

// The thickness's bilateral filter: `src` is the filtered depth (which pixels hold fluid),
// `thickness` the raw thickness.
@compute @workgroup_size(8, 8)
fn cs_thickness_filter(@builtin(global_invocation_id) id: vec3<u32>) {
    if id.x >= width() || id.y >= height() {
        return;
    }
    let i = id.y * width() + id.x;
    let t0 = thickness[i];
    if !covered(src[i]) {
        dst[i] = t0;
        return;
    }
    let r = i32(params.a.z);
    let ks = -0.5 / (params.b.x * params.b.x);
    let kt = -0.5 / (params.c.z * params.c.z);
    var sum = 0.0;
    var weight = 0.0;
    for (var dy = -r; dy <= r; dy++) {
        for (var dx = -r; dx <= r; dx++) {
            let u = i32(id.x) + dx;
            let v = i32(id.y) + dy;
            if u < 0 || v < 0 || u >= i32(width()) || v >= i32(height()) {
                continue;
            }
            let t = thickness[u32(v) * width() + u32(u)];
            let dt = t - t0;
            let g = exp(ks * f32(dx * dx + dy * dy) + kt * dt * dt);
            sum += g * t;
            weight += g;
        }
    }
    dst[i] = sum / weight;
}

// A neighbour's depth step and its world point: (|dz|, x, y, z) with |dz| < 0 when unusable.
fn neighbour(x: u32, y: u32, dx: i32, dy: i32, z0: f32) -> vec4<f32> {
    let u = i32(x) + dx;
    let v = i32(y) + dy;
    if u < 0 || v < 0 || u >= i32(width()) || v >= i32(height()) {
        return vec4<f32>(-1.0);
    }
    let z = src[u32(v) * width() + u32(u)];
    if !covered(z) || abs(z - z0) > params.b.z {
        return vec4<f32>(-1.0);
    }
    let ray = world_ray(vec2<f32>(f32(u) + 0.5, f32(v) + 0.5));
    return vec4<f32>(abs(z - z0), ray[0] + z * ray[1]);
}

// The step along +axis: forward difference, or backward, whichever is smaller; (0, 0, 0, 0)
// when neither is usable, w = 1 otherwise.
fn step_of(f: vec4<f32>, b: vec4<f32>, p0: vec3<f32>) -> vec4<f32> {
    if f.x >= 0.0 && b.x >= 0.0 && b.x < f.x {
        return vec4<f32>(p0 - b.yzw, 1.0);
    }
    if f.x >= 0.0 {
        return vec4<f32>(f.yzw - p0, 1.0);
    }
    if b.x >= 0.0 {
        return vec4<f32>(p0 - b.yzw, 1.0);
    }
    return vec4<f32>(0.0);
}

// Normals from the filtered depth (`src`), the tint from the filtered thickness (`thickness`).
@compute @workgroup_size(8, 8)
fn cs_shade(@builtin(global_invocation_id) id: vec3<u32>) {
    if id.x >= width() || id.y >= height() {
        return;
    }
    let i = id.y * width() + id.x;
    let z0 = src[i];
    let texel = vec2<i32>(i32(id.x), i32(id.y));
    if !covered(z0) {
        textureStore(colour, texel, vec4<f32>(0.0));
        textureStore(normal_depth, texel, vec4<f32>(0.0));
        return;
    }
    let ray = world_ray(vec2<f32>(f32(id.x) + 0.5, f32(id.y) + 0.5));
    let p0 = ray[0] + z0 * ray[1];
    let facing = -normalize(ray[1]);
    let ddx = step_of(neighbour(id.x, id.y, 1, 0, z0), neighbour(id.x, id.y, -1, 0, z0), p0);
    let ddy = step_of(neighbour(id.x, id.y, 0, 1, z0), neighbour(id.x, id.y, 0, -1, z0), p0);
    var n = facing;
    if ddx.w > 0.0 && ddy.w > 0.0 {
        let c = cross(ddx.xyz, ddy.xyz);
        let l = length(c);
        if l > 0.0 && l < 1e30 {
            n = c / l;
        }
    }
    if dot(n, facing) < 0.0 {
        n = -n;
    }
    let tint = params.base.xyz * exp(-params.absorb.xyz * thickness[i]);
    textureStore(colour, texel, vec4<f32>(tint, 1.0));
    textureStore(normal_depth, texel, vec4<f32>(n, z0));
}
