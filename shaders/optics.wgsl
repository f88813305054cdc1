// Optics on the GPU (Iwasaki et al. §5): caustics through illumination volumes and the final image.
// The CPU reference in src/optics/ is the specification: each function here names its mirror
// there. The differences are the paper's: the refracted rays meet the receiver by the iterative
// search in a geometry map (§5.1.2, `search_receiver`) instead of the BVH, and flux is added to
// the caustics map with atomic compare-and-swap loops (the sums' order differs).
//
// Entry points, in the order they run:
//   cs_vertices    per virtual-screen pixel: water point and normal (eq. 2, from the light's
//                  splatting), refracted ray, its hit on the receiver, T exp(-sigma_t l)
//   cs_triangles   per screen cell, two water triangles: eq. 3's flux, deposited into the map
//                  by box-filtered rasterisation of the caustics triangle
//   cs_irradiance  per map texel: flux / receiver area of the texel
//   cs_frame       per image pixel: Fresnel blend of the reflected environment and the refracted
//                  receiver with its caustics, or the receiver / environment where no water is
// The geometry maps they read (the receiver seen from the light or the camera) are drawn by
// optics_geometry.wgsl.

struct ViewU {
    view: mat4x4<f32>,
    inv_view: mat4x4<f32>,
    proj: mat4x4<f32>,
    viewport: vec2<f32>,
    tan_half: vec2<f32>,
    // x = 1: orthographic
    flags: vec4<f32>,
}

struct Uniforms {
    screen: ViewU,
    map: ViewU,
    camera: ViewU,
    // xyz: travel direction of a directional light; w: 0 directional, 1 point
    light_dir: vec4<f32>,
    light_pos: vec4<f32>,
    light_colour: vec4<f32>,
    ambient: vec4<f32>,
    // ior, discontinuity (pixels), search tolerance (world), iterations
    water: vec4<f32>,
    // sigma_t rgb, scene size
    extinction: vec4<f32>,
    // albedo rgb, checker size
    albedo: vec4<f32>,
    // kind (0 constant, 1 gradient, 2 image), ray epsilon, image width, height
    env: vec4<f32>,
    env_colour: vec4<f32>,
    env_horizon: vec4<f32>,
    env_zenith: vec4<f32>,
    env_ground: vec4<f32>,
    // x: receiver triangles met by exact rays (0: the geometry-map search instead)
    exact: vec4<f32>,
    // the receiver's container: floor corner (w = 1: there is one) and opposite corner
    container_min: vec4<f32>,
    container_max: vec4<f32>,
}

struct Vertex {
    // water point, depth from the light (w <= 0: none)
    surface: vec4<f32>,
    // receiver point, w = 1 when found
    hit: vec4<f32>,
    // T exp(-sigma_t l) per channel
    transmit: vec4<f32>,
}

@group(0) @binding(0) var<uniform> u: Uniforms;
@group(0) @binding(1) var screen_colour: texture_2d<f32>;
@group(0) @binding(2) var screen_normal: texture_2d<f32>;
@group(0) @binding(3) var map_position: texture_2d<f32>;
@group(0) @binding(4) var map_normal: texture_2d<f32>;
@group(0) @binding(5) var<storage, read_write> vertices: array<Vertex>;
@group(0) @binding(6) var<storage, read_write> flux: array<atomic<u32>>;
@group(0) @binding(7) var<storage, read_write> irradiance: array<vec4<f32>>;
@group(0) @binding(8) var camera_colour: texture_2d<f32>;
@group(0) @binding(9) var camera_normal: texture_2d<f32>;
@group(0) @binding(10) var camera_position: texture_2d<f32>;
@group(0) @binding(11) var camera_geometry_normal: texture_2d<f32>;
@group(0) @binding(12) var<storage, read_write> image: array<vec4<f32>>;
@group(0) @binding(13) var environment: texture_2d<f32>;
// the receiver's triangles, 3 vertices of (position, normal) each, for exact rays
@group(0) @binding(14) var<storage, read_write> receiver_tris: array<f32>;

const PI: f32 = 3.14159265358979;

// World ray through a pixel position (`Ray` is in common.wgsl) (mirror: View::world_ray).
fn world_ray(v: ViewU, pixel: vec2<f32>) -> Ray {
    let ndc = vec2<f32>(pixel.x / v.viewport.x * 2.0 - 1.0, 1.0 - pixel.y / v.viewport.y * 2.0);
    var o = vec3<f32>(0.0);
    var d = vec3<f32>(ndc * v.tan_half, -1.0);
    if (v.flags.x == 1.0) {
        o = vec3<f32>(ndc * v.tan_half, 0.0);
        d = vec3<f32>(0.0, 0.0, -1.0);
    }
    var r: Ray;
    r.origin = (v.inv_view * vec4<f32>(o, 1.0)).xyz;
    r.dir = (v.inv_view * vec4<f32>(d, 0.0)).xyz;
    return r;
}

// Pixel coordinates and view depth of a world point (mirror: View::project).
fn project(v: ViewU, p: vec3<f32>) -> vec3<f32> {
    let q = (v.view * vec4<f32>(p, 1.0)).xyz;
    let clip = v.proj * vec4<f32>(q, 1.0);
    let ndc = clip.xy / clip.w;
    return vec3<f32>((ndc.x + 1.0) * 0.5 * v.viewport.x, (1.0 - ndc.y) * 0.5 * v.viewport.y, -q.z);
}

// Mirror: pixel_size in src/optics/cpu.rs.
fn pixel_size(v: ViewU, depth: f32) -> f32 {
    let s = 2.0 * v.tan_half.x / v.viewport.x;
    return select(s * depth, s, v.flags.x == 1.0);
}

// Mirror: refract in src/optics/mod.rs; w = 0 on total internal reflection.
fn refract_dir(i: vec3<f32>, n: vec3<f32>, n1: f32, n2: f32) -> vec4<f32> {
    let eta = n1 / n2;
    let cos_i = -dot(n, i);
    let k = 1.0 - eta * eta * (1.0 - cos_i * cos_i);
    if (k < 0.0) {
        return vec4<f32>(0.0);
    }
    return vec4<f32>(normalize(eta * i + (eta * cos_i - sqrt(k)) * n), 1.0);
}

// Mirror: fresnel_reflectance.
fn fresnel_reflectance(cos_in: f32, n1: f32, n2: f32) -> f32 {
    let cos_i = clamp(cos_in, 0.0, 1.0);
    let sin_t2 = (n1 / n2) * (n1 / n2) * (1.0 - cos_i * cos_i);
    if (sin_t2 >= 1.0) {
        return 1.0;
    }
    let cos_t = sqrt(1.0 - sin_t2);
    let rs = (n1 * cos_i - n2 * cos_t) / (n1 * cos_i + n2 * cos_t);
    let rp = (n2 * cos_i - n1 * cos_t) / (n2 * cos_i + n1 * cos_t);
    let r = 0.5 * (rs * rs + rp * rp);
    if (!(r >= 0.0 && r <= 1.0)) {
        return select(1.0, 0.0, r < 0.0);
    }
    return r;
}

// Mirror: Environment::colour.
fn env_colour(dir: vec3<f32>) -> vec3<f32> {
    let kind = u.env.x;
    if (kind == 0.0) {
        return u.env_colour.rgb;
    }
    if (kind == 1.0) {
        if (dir.y < 0.0) {
            return u.env_ground.rgb;
        }
        return mix(u.env_horizon.rgb, u.env_zenith.rgb, min(dir.y, 1.0));
    }
    // equirect_texel
    let w = u.env.z;
    let h = u.env.w;
    let uu = atan2(dir.x, -dir.z) / (2.0 * PI) + 0.5;
    let vv = acos(clamp(dir.y, -1.0, 1.0)) / PI;
    let x = clamp(i32(uu * w), 0, i32(w) - 1);
    let y = clamp(i32(vv * h), 0, i32(h) - 1);
    return textureLoad(environment, vec2<i32>(x, y), 0).rgb;
}

// Mirror: Stage::incoming; xyz travel direction, w unused; irradiance across it returned apart.
struct Incoming {
    dir: vec3<f32>,
    e: vec3<f32>,
}

fn incoming(p: vec3<f32>) -> Incoming {
    var r: Incoming;
    if (u.light_dir.w == 0.0) {
        r.dir = u.light_dir.xyz;
        r.e = u.light_colour.rgb;
    } else {
        let d = p - u.light_pos.xyz;
        let r2 = max(dot(d, d), 1e-12);
        r.dir = d / sqrt(r2);
        r.e = u.light_colour.rgb / r2;
    }
    return r;
}

// Mirror: Stage::albedo.
fn receiver_albedo(p: vec3<f32>, n: vec3<f32>) -> vec3<f32> {
    let size = u.albedo.w;
    if (size <= 0.0) {
        return u.albedo.rgb;
    }
    let a = abs(n);
    var q = vec2<f32>(p.x, p.y);
    if (a.y >= a.x && a.y >= a.z) {
        q = vec2<f32>(p.x, p.z);
    } else if (a.x >= a.z) {
        q = vec2<f32>(p.y, p.z);
    }
    let cell = floor(q / size);
    let s = cell.x + cell.y;
    let odd = (s - 2.0 * floor(s / 2.0)) >= 0.5;
    return select(u.albedo.rgb, u.albedo.rgb * 0.55, odd);
}

// Mirror: texel_area in src/optics/mod.rs.
fn texel_area(v: ViewU, d: vec3<f32>, depth: f32, n: vec3<f32>) -> f32 {
    let window = 4.0 * v.tan_half.x * v.tan_half.y / (v.viewport.x * v.viewport.y);
    let len = max(length(d), 1e-20);
    let cos_surface = max(abs(dot(n, d) / len), 1e-3);
    if (v.flags.x == 1.0) {
        return window / cos_surface;
    }
    return window * depth * depth / len / cos_surface;
}

fn texel(t: texture_2d<f32>, x: i32, y: i32) -> vec4<f32> {
    let size = vec2<i32>(textureDimensions(t));
    return textureLoad(t, clamp(vec2<i32>(x, y), vec2<i32>(0), size - 1), 0);
}

// The receiver point of a geometry map at pixel coordinates q: bilinear where the four texels
// around q all see the receiver (exact on planes), else the nearest texel. w <= 0: none.
fn geometry_at(t: texture_2d<f32>, q: vec2<f32>) -> vec4<f32> {
    let x = q.x - 0.5;
    let y = q.y - 0.5;
    let fx = floor(x);
    let fy = floor(y);
    let i = i32(fx);
    let j = i32(fy);
    let a = texel(t, i, j);
    let b = texel(t, i + 1, j);
    let c = texel(t, i, j + 1);
    let d = texel(t, i + 1, j + 1);
    if (a.w > 0.0 && b.w > 0.0 && c.w > 0.0 && d.w > 0.0) {
        let tx = x - fx;
        let ty = y - fy;
        return mix(mix(a, b, tx), mix(c, d, tx), ty);
    }
    return texel(t, i32(floor(q.x)), i32(floor(q.y)));
}

fn receiver_vertex(i: u32) -> vec3<f32> {
    return vec3<f32>(receiver_tris[6u * i], receiver_tris[6u * i + 1u], receiver_tris[6u * i + 2u]);
}

// The closest receiver hit of the ray o + t d with t > t_min, against every triangle (mirror:
// ReceiverGeometry::intersect and intersect_triangle: Möller-Trumbore with a barycentric slack
// of 1e-6). xyz: the point, w: t (w < 0: none); the normal faces against the ray, in `n_out`.
struct ExactHit {
    hit: vec4<f32>,
    normal: vec3<f32>,
}

fn intersect_receiver(o: vec3<f32>, d: vec3<f32>, t_min: f32) -> ExactHit {
    let slack = 1e-6;
    var best = 3.4e38;
    var normal = vec3<f32>(0.0);
    let count = u32(u.exact.x);
    for (var k = 0u; k < count; k++) {
        let v0 = receiver_vertex(3u * k);
        let e1 = receiver_vertex(3u * k + 1u) - v0;
        let e2 = receiver_vertex(3u * k + 2u) - v0;
        let p = cross(d, e2);
        let det = dot(e1, p);
        if (abs(det) < 1e-20) {
            continue;
        }
        let inv = 1.0 / det;
        let s = o - v0;
        let a = dot(s, p) * inv;
        if (a < -slack || a > 1.0 + slack) {
            continue;
        }
        let q = cross(s, e1);
        let b = dot(d, q) * inv;
        if (b < -slack || a + b > 1.0 + slack) {
            continue;
        }
        let t = dot(e2, q) * inv;
        if (t > t_min && t < best) {
            best = t;
            normal = normalize(cross(e1, e2));
        }
    }
    var r: ExactHit;
    if (best < 3.4e38) {
        r.hit = vec4<f32>(o + d * best, best);
        r.normal = select(normal, -normal, dot(normal, d) > 0.0);
    } else {
        r.hit = vec4<f32>(0.0, 0.0, 0.0, -1.0);
        r.normal = vec3<f32>(0.0, 1.0, 0.0);
    }
    return r;
}

// §5.1.2: the refracted ray from s along t meets the receiver: P1 is the receiver point the map
// shows at s; P1 is projected onto the ray (P2); the receiver point the map shows at P2 is P3;
// repeated until the point on the ray and the point found are closer than the tolerance
// (`u.water.z` pixels of the map at that depth).
// The paper's iteration converges when the ray runs close to the map's own rays; from a camera
// looking at the water obliquely it diverges (each step moves the grazing view ray's floor point
// farther than the refracted ray's). Where it has not converged, the ray is marched in 48 steps
// up to the scene's size until it passes behind the map's surface, and the crossing is refined
// by 16 bisections: the standard bracketed search of screen-space ray marching.
// Returns the receiver point and w = its distance from s, or w < 0 when none is found.
fn search_receiver(v: ViewU, t_map: texture_2d<f32>, s: vec3<f32>, t: vec3<f32>) -> vec4<f32> {
    var q = s;
    let iterations = u32(u.water.w);
    for (var k = 0u; k < iterations; k++) {
        let pr = project(v, q);
        if (!(pr.x >= 0.0 && pr.y >= 0.0 && pr.x <= v.viewport.x && pr.y <= v.viewport.y && pr.z > 0.0)) {
            break;
        }
        let g = geometry_at(t_map, pr.xy);
        if (!(g.w > 0.0)) {
            break;
        }
        let along = max(dot(g.xyz - s, t), 0.0);
        let p2 = s + t * along;
        if (distance(p2, g.xyz) < u.water.z * pixel_size(v, pr.z)) {
            return vec4<f32>(g.xyz, distance(g.xyz, s));
        }
        q = p2;
    }
    // bracketed fallback: f(t) = depth of the map's surface - depth of the ray point
    let steps = 48u;
    let reach = u.extinction.w;
    var lo = 0.0;
    var found = false;
    var hi = 0.0;
    for (var k = 1u; k <= steps; k++) {
        let tk = reach * f32(k) / f32(steps);
        let pr = project(v, s + t * tk);
        if (!(pr.x >= 0.0 && pr.y >= 0.0 && pr.x <= v.viewport.x && pr.y <= v.viewport.y && pr.z > 0.0)) {
            break;
        }
        let g = geometry_at(t_map, pr.xy);
        if (g.w > 0.0 && g.w <= pr.z) {
            hi = tk;
            found = true;
            break;
        }
        lo = tk;
    }
    if (!found) {
        return vec4<f32>(0.0, 0.0, 0.0, -1.0);
    }
    for (var k = 0u; k < 16u; k++) {
        let mid = 0.5 * (lo + hi);
        let pr = project(v, s + t * mid);
        let g = geometry_at(t_map, pr.xy);
        if (g.w > 0.0 && g.w <= pr.z) {
            hi = mid;
        } else {
            lo = mid;
        }
    }
    let end = s + t * hi;
    let pr = project(v, end);
    let g = geometry_at(t_map, pr.xy);
    // a crossing onto the silhouette of a nearer surface (the ray went behind it) is no hit
    if (!(g.w > 0.0) || distance(g.xyz, end) > 4.0 * pixel_size(v, pr.z)) {
        return vec4<f32>(0.0, 0.0, 0.0, -1.0);
    }
    return vec4<f32>(g.xyz, distance(g.xyz, s));
}

// Water normal and depth of an accumulated pixel (mirror: water_at); w <= 0: none.
fn water_at(colour: vec4<f32>, normal_depth: vec4<f32>) -> vec4<f32> {
    let w = colour.a;
    if (!(w > 0.0)) {
        return vec4<f32>(0.0);
    }
    let nd = normal_depth / w;
    if (!(nd.w > 0.0 && nd.w < 3.0e38)) {
        return vec4<f32>(0.0);
    }
    return nd;
}

// Mirror: ReceiverGeometry::inside (the parity of the crossings along PARITY_DIR, every
// triangle tested as intersect_receiver does, at most 64 counted).
fn inside_mesh(p: vec3<f32>) -> bool {
    let lo = u.container_min.xyz;
    let hi = u.container_max.xyz;
    if (any(p < lo) || any(p > hi) || !(abs(p.x) < 3.0e38 && abs(p.y) < 3.0e38 && abs(p.z) < 3.0e38)) {
        return false;
    }
    let d = vec3<f32>(0.3112658, 0.8660254, 0.3911472);
    let eps = 1e-6 * max(hi.x - lo.x, max(hi.y - lo.y, hi.z - lo.z));
    var t = 0.0;
    var crossings = 0u;
    for (; crossings < 64u; crossings++) {
        let h = intersect_receiver(p, d, t).hit;
        if (h.w < 0.0) {
            break;
        }
        t = h.w + eps;
    }
    return crossings % 2u == 1u;
}

// Mirror: Stage::holds_water and ReceiverGeometry::holds (NaN is outside): w = 1 an open box's
// prism, w = 2 a closed mesh.
fn holds_water(p: vec3<f32>) -> bool {
    if (!(u.container_min.w > 0.0)) {
        return true;
    }
    if (u.container_min.w > 1.5) {
        return inside_mesh(p);
    }
    let lo = u.container_min.xyz;
    let hi = u.container_max.xyz;
    return p.x >= lo.x && p.x <= hi.x && p.z >= lo.z && p.z <= hi.z && p.y >= lo.y;
}

// Mirror: ReceiverGeometry::outer_face.
fn outer_face(p: vec3<f32>, n: vec3<f32>) -> bool {
    if (!(u.container_min.w > 0.0)) {
        return false;
    }
    let e = u.container_max.xyz - u.container_min.xyz;
    return !holds_water(p + n * (1e-4 * max(e.x, max(e.y, e.z))));
}

fn unit_or(n: vec3<f32>, fallback: vec3<f32>) -> vec3<f32> {
    let l2 = dot(n, n);
    if (!(l2 > 0.0 && l2 < 3.0e38)) {
        return fallback;
    }
    return n / sqrt(l2);
}

@compute @workgroup_size(8, 8)
fn cs_vertices(@builtin(global_invocation_id) id: vec3<u32>) {
    let w = u32(u.screen.viewport.x);
    let h = u32(u.screen.viewport.y);
    if (id.x >= w || id.y >= h) {
        return;
    }
    let i = id.y * w + id.x;
    var v: Vertex;
    v.surface = vec4<f32>(0.0);
    v.hit = vec4<f32>(0.0);
    v.transmit = vec4<f32>(0.0);
    let p = vec2<i32>(id.xy);
    let nd = water_at(textureLoad(screen_colour, p, 0), textureLoad(screen_normal, p, 0));
    let ray = world_ray(u.screen, vec2<f32>(id.xy) + 0.5);
    let s = ray.origin + ray.dir * nd.w;
    // the water outside its container sends no light
    if (nd.w > 0.0 && holds_water(s)) {
        let inc = incoming(s);
        let n = unit_or(nd.xyz, -inc.dir);
        let cos_i = -dot(n, inc.dir);
        let ior = u.water.x;
        var dir = inc.dir;
        var transmittance = 0.0;
        let t = refract_dir(inc.dir, n, 1.0, ior);
        if (t.w > 0.0 && cos_i > 0.0) {
            dir = t.xyz;
            transmittance = 1.0 - fresnel_reflectance(cos_i, 1.0, ior);
        }
        // water the receiver shades from the light (a pool wall between them) receives no light
        // (mirror: `Stage::light_blocked`, there by an exact ray; here the light's geometry map,
        // with a bias of two texels)
        let pm = project(u.map, s);
        let shade = texel(map_position, i32(floor(pm.x)), i32(floor(pm.y)));
        if (shade.w > 0.0 && shade.w < pm.z - 2.0 * pixel_size(u.map, pm.z)) {
            transmittance = 0.0;
        }
        v.surface = vec4<f32>(s, nd.w);
        var hit: vec4<f32>;
        // w = 2: the ray met the side of a surface facing away from the light (the inside of
        // a thin wall), which the light's map does not hold (mirror: CausticVertex::hit); the
        // search finds only what the map shows, the side the light sees
        var side = 1.0;
        if (u.exact.x > 0.0) {
            let e = intersect_receiver(s, dir, u.env.y);
            hit = e.hit;
            side = select(2.0, 1.0, dot(e.normal, -inc.dir) > 0.0);
        } else {
            hit = search_receiver(u.map, map_position, s, dir);
        }
        if (hit.w >= 0.0) {
            v.hit = vec4<f32>(hit.xyz, side);
            v.transmit = vec4<f32>(transmittance * exp(-u.extinction.rgb * hit.w), 0.0);
        }
    }
    vertices[i] = v;
}

// Adds v to a float held in an atomic u32 (compare-and-swap loop).
fn add_flux(i: u32, v: f32) {
    if (v == 0.0) {
        return;
    }
    var old = atomicLoad(&flux[i]);
    loop {
        let r = atomicCompareExchangeWeak(&flux[i], old, bitcast<u32>(bitcast<f32>(old) + v));
        if (r.exchanged) {
            break;
        }
        old = r.old_value;
    }
}

fn add_texel(x: u32, y: u32, v: vec3<f32>) {
    let i = (y * u32(u.map.viewport.x) + x) * 4u;
    add_flux(i, v.x);
    add_flux(i + 1u, v.y);
    add_flux(i + 2u, v.z);
}

struct Polygon {
    p: array<vec2<f32>, 8>,
    n: u32,
}

// Mirror: clip_polygon (Sutherland-Hodgman against one axis-aligned half-plane).
fn clip_polygon(poly: Polygon, axis: u32, bound: f32, sign: f32) -> Polygon {
    var out: Polygon;
    out.n = 0u;
    var p = poly.p;
    for (var i = 0u; i < poly.n; i++) {
        let a = p[i];
        let b = p[(i + 1u) % poly.n];
        let da = sign * (a[axis] - bound);
        let db = sign * (b[axis] - bound);
        if (da >= 0.0 && out.n < 8u) {
            out.p[out.n] = a;
            out.n += 1u;
        }
        if ((da >= 0.0) != (db >= 0.0) && out.n < 8u) {
            out.p[out.n] = a + (b - a) * (da / (da - db));
            out.n += 1u;
        }
    }
    return out;
}

fn polygon_area2(poly: Polygon) -> f32 {
    var p = poly.p;
    var s = 0.0;
    for (var i = 0u; i < poly.n; i++) {
        let a = p[i];
        let b = p[(i + 1u) % poly.n];
        s += a.x * b.y - a.y * b.x;
    }
    return s;
}

fn finite2(p: vec2<f32>) -> bool {
    return abs(p.x) < 3.0e38 && abs(p.y) < 3.0e38;
}

// Mirror: depth_bias (1.5 texels plus twice the surface's depth change across a texel).
fn depth_bias(q: vec2<f32>, z: f32, n: vec3<f32>) -> f32 {
    let d = world_ray(u.map, q).dir;
    let c = abs(dot(n, d) / max(length(d), 1e-20));
    let slope = min(sqrt(max(1.0 - c * c, 0.0)) / max(c, 0.05), 20.0);
    return (1.5 + 2.0 * slope) * pixel_size(u.map, z);
}

// Whether the map texel (x, y) shows the caustics triangle's own surface: its receiver depth
// within the triangle's depths [z0, z1], widened by the texel's bias (mirror: deposit_owned).
fn owns_texel(x: u32, y: u32, z0: f32, z1: f32) -> bool {
    let t = vec2<i32>(i32(x), i32(y));
    let g = textureLoad(map_position, t, 0).w;
    let n = textureLoad(map_normal, t, 0).xyz;
    let bias = depth_bias(vec2<f32>(f32(x) + 0.5, f32(y) + 0.5), g, n);
    return g > 0.0 && g >= z0 - bias && g <= z1 + bias
        // (only for texels that pass the depth test: && short-circuits; the CPU keeps the flag
        // per texel of its geometry map, which the GPU's geometry pass cannot compute)
        && !outer_face(textureLoad(map_position, t, 0).xyz, n);
}

// Mirror: deposit_owned in src/optics/cpu.rs (box-filtered, flux-conserving rasterisation into
// the texels that show the triangle's own surface). q0..q2: map pixel coordinates and depth.
fn deposit_triangle(q0: vec3<f32>, q1: vec3<f32>, q2: vec3<f32>, value: vec3<f32>) {
    let width = u.map.viewport.x;
    let height = u.map.viewport.y;
    let p0 = q0.xy;
    let p1 = q1.xy;
    let p2 = q2.xy;
    if (!(finite2(p0) && finite2(p1) && finite2(p2))) {
        return;
    }
    let e1 = p1 - p0;
    let e2 = p2 - p0;
    let total = abs(e1.x * e2.y - e1.y * e2.x);
    let z0 = min(min(q0.z, q1.z), q2.z);
    let z1 = max(max(q0.z, q1.z), q2.z);
    let lo = min(min(p0, p1), p2);
    let hi = max(max(p0, p1), p2);
    if (!(total > 1e-12)) {
        let m = (p0 + p1 + p2) / 3.0;
        if (m.x >= 0.0 && m.y >= 0.0 && m.x < width && m.y < height
            && owns_texel(u32(m.x), u32(m.y), z0, z1)) {
            add_texel(u32(m.x), u32(m.y), value);
        }
        return;
    }
    let y0 = u32(max(floor(lo.y), 0.0));
    let y1 = max(u32(min(ceil(hi.y), height)), y0);
    let x0 = u32(max(floor(lo.x), 0.0));
    let x1 = max(u32(min(ceil(hi.x), width)), x0);
    let origin = vec2<f32>(f32(x0), f32(y0));
    var tri: Polygon;
    tri.p[0] = p0 - origin;
    tri.p[1] = p1 - origin;
    tri.p[2] = p2 - origin;
    tri.n = 3u;
    for (var y = y0; y < y1; y++) {
        let ly = f32(y - y0);
        var row = clip_polygon(tri, 1u, ly, 1.0);
        row = clip_polygon(row, 1u, ly + 1.0, -1.0);
        if (row.n < 3u) {
            continue;
        }
        for (var x = x0; x < x1; x++) {
            let lx = f32(x - x0);
            var cell = clip_polygon(row, 0u, lx, 1.0);
            cell = clip_polygon(cell, 0u, lx + 1.0, -1.0);
            if (cell.n < 3u) {
                continue;
            }
            let a = abs(polygon_area2(cell));
            if (a > 0.0 && owns_texel(x, y, z0, z1)) {
                add_texel(x, y, value * (a / total));
            }
        }
    }
}

// Mirror: triangle_flux (eq. 3 for one water triangle) and the deposit of its caustics triangle.
fn draw_triangle(a: Vertex, b: Vertex, c: Vertex) {
    if (!(a.surface.w > 0.0 && b.surface.w > 0.0 && c.surface.w > 0.0)) {
        return;
    }
    let s0 = a.surface.xyz;
    let s1 = b.surface.xyz;
    let s2 = c.surface.xyz;
    let inc = incoming((s0 + s1 + s2) / 3.0);
    let area = 0.5 * abs(dot(cross(s1 - s0, s2 - s0), inc.dir));
    let incident = inc.e * area;
    let d0 = min(min(a.surface.w, b.surface.w), c.surface.w);
    let d1 = max(max(a.surface.w, b.surface.w), c.surface.w);
    if (d1 - d0 > u.water.y * pixel_size(u.screen, d1)) {
        return;
    }
    if (!(a.hit.w > 0.0 && b.hit.w > 0.0 && c.hit.w > 0.0)) {
        return;
    }
    // light brought to a receiver point hidden from the light, or to the side of a surface
    // facing away from it, is not kept (mirror: the CPU's hidden_in_map and hit.w = 2)
    if (a.hit.w > 1.5 || b.hit.w > 1.5 || c.hit.w > 1.5) {
        return;
    }
    if (hidden_in_map(a.hit.xyz) || hidden_in_map(b.hit.xyz) || hidden_in_map(c.hit.xyz)) {
        return;
    }
    let transmit = (a.transmit.rgb + b.transmit.rgb + c.transmit.rgb) / 3.0;
    let q0 = project(u.map, a.hit.xyz);
    let q1 = project(u.map, b.hit.xyz);
    let q2 = project(u.map, c.hit.xyz);
    deposit_triangle(q0, q1, q2, incident * transmit);
}

@compute @workgroup_size(8, 8)
fn cs_triangles(@builtin(global_invocation_id) id: vec3<u32>) {
    let w = u32(u.screen.viewport.x);
    let h = u32(u.screen.viewport.y);
    if (id.x + 1u >= w || id.y + 1u >= h) {
        return;
    }
    let k00 = id.y * w + id.x;
    let k10 = k00 + 1u;
    let k01 = k00 + w;
    let k11 = k01 + 1u;
    draw_triangle(vertices[k00], vertices[k10], vertices[k01]);
    draw_triangle(vertices[k11], vertices[k01], vertices[k10]);
}

// Mirror: irradiance_of.
@compute @workgroup_size(8, 8)
fn cs_irradiance(@builtin(global_invocation_id) id: vec3<u32>) {
    let w = u32(u.map.viewport.x);
    let h = u32(u.map.viewport.y);
    if (id.x >= w || id.y >= h) {
        return;
    }
    let i = id.y * w + id.x;
    let g = textureLoad(map_position, vec2<i32>(id.xy), 0);
    if (!(g.w > 0.0)) {
        irradiance[i] = vec4<f32>(0.0);
        return;
    }
    let n = textureLoad(map_normal, vec2<i32>(id.xy), 0).xyz;
    let ray = world_ray(u.map, vec2<f32>(id.xy) + 0.5);
    let area = texel_area(u.map, ray.dir, g.w, n);
    let f = vec3<f32>(
        bitcast<f32>(atomicLoad(&flux[i * 4u])),
        bitcast<f32>(atomicLoad(&flux[i * 4u + 1u])),
        bitcast<f32>(atomicLoad(&flux[i * 4u + 2u])),
    );
    irradiance[i] = vec4<f32>(f / area, 1.0);
}

// Mirror: Caustics::irradiance_at (bilinear over the texels that show the same surface).
fn caustics_at(p: vec3<f32>, n: vec3<f32>) -> vec3<f32> {
    let q3 = project(u.map, p);
    let q = q3.xy;
    if (!finite2(q)) {
        return vec3<f32>(0.0);
    }
    let w = i32(u.map.viewport.x);
    let h = i32(u.map.viewport.y);
    let x = q.x - 0.5;
    let y = q.y - 0.5;
    if (x < -1.0 || y < -1.0 || x > f32(w) || y > f32(h)) {
        return vec3<f32>(0.0);
    }
    let bias = depth_bias(q, q3.z, n);
    let fx = floor(x);
    let fy = floor(y);
    let tx = x - fx;
    let ty = y - fy;
    var sum = vec3<f32>(0.0);
    var weight = 0.0;
    for (var k = 0; k < 4; k++) {
        let di = k % 2;
        let dj = k / 2;
        let wt = select(1.0 - tx, tx, di == 1) * select(1.0 - ty, ty, dj == 1);
        let ix = clamp(i32(fx) + di, 0, w - 1);
        let jy = clamp(i32(fy) + dj, 0, h - 1);
        let g = textureLoad(map_position, vec2<i32>(ix, jy), 0);
        let gn = textureLoad(map_normal, vec2<i32>(ix, jy), 0).xyz;
        if (g.w > 0.0 && dot(gn, n) > 0.5 && abs(g.w - q3.z) <= bias) {
            sum += irradiance[jy * w + ix].rgb * wt;
            weight += wt;
        }
    }
    if (weight > 0.0) {
        return sum / weight;
    }
    return vec3<f32>(0.0);
}

// Row-major index of the texel under pixel coordinates q of view v, -1 off the view (mirror:
// texel_of).
fn texel_of(v: ViewU, q: vec3<f32>) -> i32 {
    if (!(q.x >= 0.0 && q.y >= 0.0 && q.x < v.viewport.x && q.y < v.viewport.y)) {
        return -1;
    }
    return i32(q.y) * i32(v.viewport.x) + i32(q.x);
}

// Mirror: hidden_in_map (a receiver point behind the map's surface by more than three texels).
fn hidden_in_map(p: vec3<f32>) -> bool {
    let q = project(u.map, p);
    if (texel_of(u.map, q) < 0) {
        return false;
    }
    let g = textureLoad(map_position, vec2<i32>(q.xy), 0).w;
    return g > 0.0 && g < q.z - 3.0 * pixel_size(u.map, q.z);
}

// Mirror: Caustics::water_cover (the four screen texels about p that see water nearer the light
// than p, bilinearly weighted; texels off the screen see none).
fn water_cover(p: vec3<f32>) -> f32 {
    let q = project(u.screen, p);
    let w = i32(u.screen.viewport.x);
    let h = i32(u.screen.viewport.y);
    let x = q.x - 0.5;
    let y = q.y - 0.5;
    if (!(x >= -1.0 && y >= -1.0 && x <= f32(w) && y <= f32(h) && abs(q.z) < 3.0e38)) {
        return 0.0;
    }
    let fx = floor(x);
    let fy = floor(y);
    let tx = x - fx;
    let ty = y - fy;
    var cover = 0.0;
    for (var k = 0; k < 4; k++) {
        let di = k % 2;
        let dj = k / 2;
        let wt = select(1.0 - tx, tx, di == 1) * select(1.0 - ty, ty, dj == 1);
        let i = i32(fx) + di;
        let j = i32(fy) + dj;
        if (i < 0 || j < 0 || i >= w || j >= h) {
            continue;
        }
        let d = vertices[j * w + i].surface.w;
        if (d > 0.0 && d < q.z) {
            cover += wt;
        }
    }
    return cover;
}

// Whether the receiver shadows p (normal n) from the light. Mirror: `Stage::light_blocked` (an
// exact ray, as in `receiver_irradiance`) where the receiver is small enough for exact rays;
// otherwise the light's geometry map with a slope-scaled bias (1.5 texels plus twice the
// surface's depth change across a texel), which leaks light near contacts and has no CPU twin.
fn shadowed(p: vec3<f32>, n: vec3<f32>) -> bool {
    if (u.exact.x > 0.0) {
        let eps = u.env.y;
        let o = p + n * eps;
        let h = intersect_receiver(o, -incoming(o).dir, eps).hit;
        if (h.w < 0.0) {
            return false;
        }
        return u.light_dir.w == 0.0 || h.w < length(u.light_pos.xyz - o);
    }
    let q = project(u.map, p);
    if (texel_of(u.map, q) < 0) {
        return false;
    }
    let g = textureLoad(map_position, vec2<i32>(q.xy), 0).w;
    let d = world_ray(u.map, q.xy).dir;
    let c = abs(dot(n, d) / max(length(d), 1e-20));
    let slope = min(sqrt(max(1.0 - c * c, 0.0)) / max(c, 0.05), 20.0);
    return g > 0.0 && g < q.z - (1.5 + 2.0 * slope) * pixel_size(u.map, q.z);
}

// Mirror: receiver_irradiance.
fn receiver_irradiance(p: vec3<f32>, n: vec3<f32>) -> vec3<f32> {
    let inc = incoming(p);
    let facing = dot(n, -inc.dir);
    // the caustics map's texels belong to the surfaces the light sees: none for a point turned
    // away from the light or shadowed by the receiver
    if (!(facing > 0.0) || shadowed(p, n)) {
        return vec3<f32>(0.0);
    }
    // an outer face of the container: no water between it and the light, the maps not read
    if (outer_face(p, n)) {
        return inc.e * facing;
    }
    let direct = inc.e * facing * (1.0 - water_cover(p));
    return direct + caustics_at(p, n);
}

fn receiver_radiance(p: vec3<f32>, n: vec3<f32>) -> vec3<f32> {
    return receiver_albedo(p, n) * receiver_irradiance(p, n) + u.ambient.rgb;
}

// Mirror: water_pixel (the refracted ray meets the receiver by the geometry-map search in the
// camera's geometry map, §5.2).
fn water_pixel(p: vec3<f32>, dn: vec3<f32>, n_in: vec3<f32>) -> vec3<f32> {
    let ior = u.water.x;
    var n = n_in;
    var cos_i = -dot(n, dn);
    if (cos_i < 0.0) {
        n = -n;
        cos_i = -cos_i;
    }
    let reflected = env_colour(dn + 2.0 * cos_i * n);
    let r = fresnel_reflectance(cos_i, 1.0, ior);
    var refracted = vec3<f32>(0.0);
    let t = refract_dir(dn, n, 1.0, ior);
    if (t.w > 0.0) {
        // exact rays for a small receiver; otherwise the camera's geometry map first and, where
        // the receiver the ray meets is hidden from the camera (behind a wall), the light's
        var hit = vec4<f32>(0.0, 0.0, 0.0, -1.0);
        var gn = vec3<f32>(0.0, 1.0, 0.0);
        if (u.exact.x > 0.0) {
            let e = intersect_receiver(p, t.xyz, u.env.y);
            hit = e.hit;
            gn = e.normal;
        } else {
            hit = search_receiver(u.camera, camera_position, p, t.xyz);
            if (hit.w >= 0.0) {
                let g = project(u.camera, hit.xyz);
                gn = texel(camera_geometry_normal, i32(floor(g.x)), i32(floor(g.y))).xyz;
            } else {
                hit = search_receiver(u.map, map_position, p, t.xyz);
                let g = project(u.map, hit.xyz);
                gn = texel(map_normal, i32(floor(g.x)), i32(floor(g.y))).xyz;
            }
        }
        if (hit.w >= 0.0) {
            refracted = receiver_radiance(hit.xyz, gn) * exp(-u.extinction.rgb * hit.w);
        } else {
            refracted = env_colour(t.xyz) * exp(-u.extinction.rgb * u.extinction.w);
        }
    }
    return reflected * r + refracted * (1.0 - r);
}

@compute @workgroup_size(8, 8)
fn cs_frame(@builtin(global_invocation_id) id: vec3<u32>) {
    let w = u32(u.camera.viewport.x);
    let h = u32(u.camera.viewport.y);
    if (id.x >= w || id.y >= h) {
        return;
    }
    let p = vec2<i32>(id.xy);
    let ray = world_ray(u.camera, vec2<f32>(id.xy) + 0.5);
    let dn = normalize(ray.dir);
    let nd = water_at(textureLoad(camera_colour, p, 0), textureLoad(camera_normal, p, 0));
    let receiver = textureLoad(camera_position, p, 0);
    var c: vec4<f32>;
    // the water where it lies in front of the receiver (an opaque wall may hide it)
    let point = ray.origin + ray.dir * nd.w;
    if (nd.w > 0.0 && !(receiver.w > 0.0 && receiver.w < nd.w) && holds_water(point)) {
        c = vec4<f32>(water_pixel(point, dn, unit_or(nd.xyz, -dn)), 1.0);
    } else {
        let g = textureLoad(camera_position, p, 0);
        if (g.w > 0.0) {
            let gn = textureLoad(camera_geometry_normal, p, 0).xyz;
            c = vec4<f32>(receiver_radiance(g.xyz, gn), 0.0);
        } else {
            c = vec4<f32>(env_colour(dn), 0.0);
        }
    }
    image[id.y * w + id.x] = c;
}
