// Surfel splatting in three passes (Botsch, Hornung, Zwicker, Kobbelt 2005, "High-quality surface
// splatting on today's GPUs"; the EWA filter of Zwicker et al. 2001), as extended by Iwasaki et al.
// §5.2. The CPU reference in src/splat/mod.rs is the specification: every function here has a mirror
// there with the same name and the same arithmetic, and tests compare the two images.
//
// 1. vs_splat + fs_visibility: each surfel becomes a screen-aligned quad bounding the projection of
//    its disk (the projected corners of the disk's bounding rectangle, which contain the disk's
//    projection because perspective maps convex sets to convex sets), joined with the low-pass
//    filter's circle around the projected centre. Per fragment the view ray meets the disk's plane
//    (perspective-correct depth); outside the disk and the filter the fragment is discarded; the
//    depth written is pushed back along the ray by epsilon = depth_offset * radius.
// 2. vs_splat + fs_attributes: depth-tested against pass 1 without writes; adds (colour * w, w) and
//    (normal * w, depth * w) into two Rgba32Float targets, w = exp(-sharpness * r^2) with
//    r^2 = min(r3^2, r2^2): r3 the object-space distance in the disk (1 at its rim), r2 the
//    screen-space distance to the projected centre in units of the low-pass radius. Taking the
//    smaller of the two is Botsch et al.'s approximation of the EWA resampling filter (the
//    convolution of the object-space kernel with a screen-space low-pass): a minified splat still
//    covers about one pixel instead of falling between pixel centres.
// 3. vs_fullscreen + fs_shade: divides by the weight and shades (Blinn-Phong, directional light).
//
// Mode 2 is particle splatting (Adams, Lenaerts, Dutré 2006, §3): each surfel's position and radius
// is a sphere drawn as a screen square of the projected radius; pass 1 writes the nearest sphere
// depth (eq. 5) pushed back by epsilon along the view axis; pass 2 reads that depth (bound at
// binding 3 beside the read-only depth attachment) for the weight W1 W2 (eqs. 6, 7) and blends the
// per-fragment sphere normals.

struct Uniforms {
    // world -> view (rigid; the camera looks along -z)
    view: mat4x4<f32>,
    // view -> clip (depth 0..1)
    proj: mat4x4<f32>,
    // view -> world
    inv_view: mat4x4<f32>,
    // width, height in pixels
    viewport: vec2<f32>,
    // tan(fov_y / 2) * aspect, tan(fov_y / 2)
    tan_half: vec2<f32>,
    // world direction towards the light (unit), w = ambient
    light_dir: vec4<f32>,
    // light colour, w = specular strength
    light_colour: vec4<f32>,
    // colour where no surfel covers the pixel
    background: vec4<f32>,
    // x = shininess, y = 1 for an orthographic view (a directional light's virtual screen)
    material: vec4<f32>,
    // epsilon / radius
    depth_offset: f32,
    // screen-space low-pass radius in pixels (0: off)
    low_pass: f32,
    // Gaussian weight exp(-sharpness * r^2)
    sharpness: f32,
    // 0: EWA splats, 1: plain point sprites (round, nearest wins, no blending), 2: particle
    // spheres (Adams et al. 2006)
    mode: u32,
}

@group(0) @binding(0) var<uniform> u: Uniforms;
// pass 1's depth buffer, read by pass 2 (the spheres' W2)
@group(0) @binding(3) var visible_depth: texture_depth_2d;

// A surfel as it is stored (64 bytes, `Surfel` in src/splat/mod.rs).
struct SurfelIn {
    @location(0) position_radius: vec4<f32>,
    @location(1) normal_stretch: vec4<f32>,
    @location(2) tangent: vec4<f32>,
    @location(3) colour: vec4<f32>,
}

struct SplatOut {
    @builtin(position) position: vec4<f32>,
    // centre in view space
    @location(0) @interpolate(flat) centre: vec3<f32>,
    // disk axes in view space, divided by their squared length
    @location(1) @interpolate(flat) axis_u: vec3<f32>,
    @location(2) @interpolate(flat) axis_v: vec3<f32>,
    // plane normal in view space
    @location(3) @interpolate(flat) normal_view: vec3<f32>,
    // world normal (shading)
    @location(4) @interpolate(flat) normal_world: vec3<f32>,
    @location(5) @interpolate(flat) colour: vec4<f32>,
    // projected centre in pixels, radius in pixels of a sprite, epsilon
    @location(6) @interpolate(flat) screen: vec4<f32>,
}

// Orthonormal tangent of a unit normal (Duff et al. 2017, "Building an orthonormal basis,
// revisited"), branch-free except for the sign.
fn basis_tangent(n: vec3<f32>) -> vec3<f32> {
    let s = select(-1.0, 1.0, n.z >= 0.0);
    let a = -1.0 / (s + n.z);
    let b = n.x * n.y * a;
    return vec3<f32>(1.0 + s * n.x * n.x * a, s * b, -s * n.x);
}

// pixel coordinates (origin top left) of a view-space point, and its clip w
fn pixels_of(p: vec3<f32>) -> vec3<f32> {
    let clip = u.proj * vec4<f32>(p, 1.0);
    let ndc = clip.xy / clip.w;
    return vec3<f32>((ndc.x + 1.0) * 0.5 * u.viewport.x, (1.0 - ndc.y) * 0.5 * u.viewport.y, clip.w);
}

// The view ray through a pixel position, in view space: perspective rays start at the eye and
// have z = -1; orthographic rays start on the plane z = 0 and run along -z (mirror: `View::ray`).
// (`Ray` is in common.wgsl.)

fn view_ray(pixel: vec2<f32>) -> Ray {
    let ndc = vec2<f32>(pixel.x / u.viewport.x * 2.0 - 1.0, 1.0 - pixel.y / u.viewport.y * 2.0);
    var r: Ray;
    if (u.material.y == 1.0) {
        r.origin = vec3<f32>(ndc * u.tan_half, 0.0);
        r.dir = vec3<f32>(0.0, 0.0, -1.0);
    } else {
        r.origin = vec3<f32>(0.0);
        r.dir = vec3<f32>(ndc * u.tan_half, -1.0);
    }
    return r;
}

struct Frame {
    // visible: 1, culled: 0
    keep: bool,
    // pixel rectangle min.xy, max.xy
    rect: vec4<f32>,
    centre: vec3<f32>,
    axis_u: vec3<f32>,
    axis_v: vec3<f32>,
    normal_view: vec3<f32>,
    screen: vec4<f32>,
}

// Mirror: splat::RECT_MARGIN_PX (a quad's reach beyond the pixels its weight can cover).
const RECT_MARGIN_PX: f32 = 0.0625;

// The per-surfel set-up of passes 1 and 2 (mirror: `frame` in src/splat/mod.rs).
fn splat_frame(position: vec3<f32>, radius: f32, normal: vec3<f32>, stretch: f32, tangent_in: vec3<f32>) -> Frame {
    var f: Frame;
    f.keep = false;
    let n = normalize(normal);
    var t = tangent_in - n * dot(n, tangent_in);
    if (stretch == 1.0 || dot(t, t) < 1e-12) {
        t = basis_tangent(n);
    } else {
        t = normalize(t);
    }
    let big_u = t * radius;
    let big_v = cross(n, t) * (radius * stretch);
    let c = (u.view * vec4<f32>(position, 1.0)).xyz;
    let uv = (u.view * vec4<f32>(big_u, 0.0)).xyz;
    let vv = (u.view * vec4<f32>(big_v, 0.0)).xyz;
    let nv = (u.view * vec4<f32>(n, 0.0)).xyz;
    f.centre = c;
    f.axis_u = uv / dot(uv, uv);
    f.axis_v = vv / dot(vv, vv);
    f.normal_view = nv;
    // back faces culled (the camera is at the view-space origin; orthographic views look along -z);
    // spheres have none
    if (u.mode != 2u && dot(nv, select(c, vec3<f32>(0.0, 0.0, -1.0), u.material.y == 1.0)) >= 0.0) {
        return f;
    }
    let eps = u.depth_offset * radius;
    var lo = vec2<f32>(0.0, 0.0);
    var hi = u.viewport;
    let centre_px = pixels_of(c);
    if (u.mode != 0u) {
        // a sprite or a sphere: a screen disk of the projected radius around the projected centre
        if (centre_px.z <= 0.0) {
            return f;
        }
        var r_px = radius * u.proj[1][1] * 0.5 * u.viewport.y / centre_px.z;
        var offset = 0.0;
        if (u.mode == 2u) {
            // at least the low-pass radius (mirror: `frame`); the world radius in axis_u.x
            r_px = max(r_px, u.low_pass);
            f.axis_u = vec3<f32>(radius, 0.0, 0.0);
            offset = eps;
        }
        f.screen = vec4<f32>(centre_px.xy, r_px, offset);
        lo = max(lo, centre_px.xy - vec2<f32>(r_px + RECT_MARGIN_PX));
        hi = min(hi, centre_px.xy + vec2<f32>(r_px + RECT_MARGIN_PX));
    } else {
        var s = vec2<f32>(1.0, 1.0);
        var all_front = true;
        var mn = vec2<f32>(3.0e38, 3.0e38);
        var mx = vec2<f32>(-3.0e38, -3.0e38);
        for (var k = 0u; k < 4u; k++) {
            let su = select(-1.0, 1.0, (k & 1u) == 0u);
            let sv = select(-1.0, 1.0, (k & 2u) == 0u);
            let q = pixels_of(c + su * uv + sv * vv);
            if (q.z <= 1e-6) {
                all_front = false;
            }
            mn = min(mn, q.xy);
            mx = max(mx, q.xy);
        }
        let centre = select(vec2<f32>(-1.0e15), centre_px.xy, centre_px.z > 0.0);
        // the projected square's pixels joined with the low-pass filter's circle (mirror:
        // `frame`); a disk that reaches behind the camera: the whole screen (rare, exact)
        if (all_front) {
            let reach = vec2<f32>(u.low_pass);
            lo = max(lo, min(mn, centre - reach) - vec2<f32>(RECT_MARGIN_PX));
            hi = min(hi, max(mx, centre + reach) + vec2<f32>(RECT_MARGIN_PX));
        }
        f.screen = vec4<f32>(centre, 0.0, eps);
    }
    if (hi.x <= lo.x || hi.y <= lo.y) {
        return f;
    }
    f.rect = vec4<f32>(lo, hi);
    f.keep = true;
    return f;
}

@vertex
fn vs_splat(@builtin(vertex_index) vertex: u32, s: SurfelIn) -> SplatOut {
    var out: SplatOut;
    let f = splat_frame(s.position_radius.xyz, s.position_radius.w, s.normal_stretch.xyz, s.normal_stretch.w, s.tangent.xyz);
    out.centre = f.centre;
    out.axis_u = f.axis_u;
    out.axis_v = f.axis_v;
    out.normal_view = f.normal_view;
    out.normal_world = normalize(s.normal_stretch.xyz);
    out.colour = s.colour;
    out.screen = f.screen;
    if (!f.keep) {
        // degenerate triangle: nothing rasterised
        out.position = vec4<f32>(2.0, 2.0, 2.0, 1.0);
        return out;
    }
    let corners = array<vec2<f32>, 6>(vec2(0.0, 0.0), vec2(1.0, 0.0), vec2(1.0, 1.0), vec2(0.0, 0.0), vec2(1.0, 1.0), vec2(0.0, 1.0));
    let px = mix(f.rect.xy, f.rect.zw, corners[vertex]);
    out.position = vec4<f32>(px.x / u.viewport.x * 2.0 - 1.0, 1.0 - px.y / u.viewport.y * 2.0, 0.5, 1.0);
    return out;
}

struct Fragment {
    keep: bool,
    // r^2 of the weight
    r2: f32,
    // view depth (distance along -z) of the point
    depth: f32,
    // depth-buffer value without and with the offset
    ndc: f32,
    ndc_offset: f32,
    // the sphere's normal at the fragment in view space (mode 2)
    sphere_normal: vec3<f32>,
}

fn ndc_depth(p: vec3<f32>) -> f32 {
    let clip = u.proj * vec4<f32>(p, 1.0);
    return clip.z / clip.w;
}

// Mirror: splat::DEPTH_REACH_RADII.
const DEPTH_REACH: f32 = 8.0;

// Per-pixel evaluation of passes 1 and 2 at a pixel centre (mirror: `fragment` in src/splat/mod.rs).
fn splat_fragment(pixel: vec2<f32>, centre: vec3<f32>, axis_u: vec3<f32>, axis_v: vec3<f32>, nv: vec3<f32>, screen: vec4<f32>) -> Fragment {
    var f: Fragment;
    f.keep = false;
    let ray = view_ray(pixel);
    let o = ray.origin;
    let d = ray.dir;
    var r2 = 3.0e38;
    var depth = -centre.z;
    if (u.mode == 2u) {
        // eq. 5 (mirror: `fragment`)
        let e = (pixel - screen.xy) / screen.z;
        r2 = dot(e, e);
        let height = sqrt(max(1.0 - r2, 0.0));
        depth = -centre.z - axis_u.x * height;
        f.sphere_normal = vec3<f32>(e.x, -e.y, height);
    } else if (u.mode == 1u) {
        let e = (pixel - screen.xy) / screen.z;
        r2 = dot(e, e);
    } else {
        var r3 = 3.0e38;
        let denom = dot(nv, d);
        var t = 0.0;
        if (denom != 0.0) {
            t = dot(nv, centre - o) / denom;
        }
        if (t > 0.0) {
            let q = o + t * d - centre;
            let a = dot(q, axis_u);
            let b = dot(q, axis_v);
            r3 = a * a + b * b;
        }
        var r2d = 3.0e38;
        if (u.low_pass > 0.0) {
            let e = (pixel - screen.xy) / u.low_pass;
            r2d = dot(e, e);
        }
        r2 = min(r3, r2d);
        // the depth is the ray's hit on the disk's plane even where the low-pass filter decides
        // the weight: the centre's depth would make coplanar splats seen at a grazing angle
        // (many rows of them within one pixel) hide each other, and the filter would then
        // average fewer of them, not more. It stays within DEPTH_REACH radii of the depths the
        // disk itself spans (its centre's, plus or minus the view-z extent of its two axes):
        // outside the disk the plane of a disk seen edge-on runs off far in depth, and the
        // light's view of a drop then put water units in front of the pool walls, whose direct
        // light it took away (the dark dashes on the walls, issue 14). Mirror of
        // splat::DEPTH_REACH_RADII, with the measurements.
        if (t > 0.0) {
            let uz = axis_u.z / dot(axis_u, axis_u);
            let vz = axis_v.z / dot(axis_v, axis_v);
            let radius = 1.0 / min(length(axis_u), length(axis_v));
            let extent = sqrt(uz * uz + vz * vz) + DEPTH_REACH * radius;
            depth = clamp(t, -centre.z - extent, -centre.z + extent);
        }
    }
    if (!(r2 <= 1.0) || !(depth > 0.0)) {
        return f;
    }
    let p = o + d * depth;
    f.ndc = ndc_depth(p);
    if (u.mode == 2u) {
        f.ndc_offset = ndc_depth(o + d * (depth + screen.w));
    } else {
        f.ndc_offset = ndc_depth(p + normalize(d) * screen.w);
    }
    if (!(f.ndc >= 0.0 && f.ndc <= 1.0)) {
        return f;
    }
    f.ndc_offset = min(f.ndc_offset, 1.0);
    f.r2 = r2;
    f.depth = depth;
    f.keep = true;
    return f;
}

@fragment
fn fs_visibility(s: SplatOut) -> @builtin(frag_depth) f32 {
    let f = splat_fragment(s.position.xy, s.centre, s.axis_u, s.axis_v, s.normal_view, s.screen);
    if (!f.keep) {
        discard;
    }
    return f.ndc_offset;
}

struct Accumulated {
    @location(0) colour: vec4<f32>,
    @location(1) normal_depth: vec4<f32>,
    @builtin(frag_depth) depth: f32,
}

// The view depth of the point on a view ray whose depth-buffer value is `ndc` (mirror:
// `View::linear_depth`).
fn linear_depth(ndc: f32) -> f32 {
    return (u.proj[3][2] - ndc * u.proj[3][3]) / (u.proj[2][2] - ndc * u.proj[2][3]);
}

// The weight of a fragment in pass 2, `buffer` pass 1's depth at its pixel (mirror: `weight`).
fn splat_weight(f: Fragment, buffer: f32, epsilon: f32) -> f32 {
    if (u.mode == 1u) {
        return 1.0;
    }
    if (u.mode == 2u) {
        let w1 = 1.0 - sqrt(f.r2);
        var w2 = 1.0;
        if (epsilon > 0.0) {
            w2 = clamp((linear_depth(buffer) - f.depth) / epsilon, 0.0, 1.0);
        }
        return w1 * w2;
    }
    return exp(-u.sharpness * f.r2);
}

@fragment
fn fs_attributes(s: SplatOut) -> Accumulated {
    let f = splat_fragment(s.position.xy, s.centre, s.axis_u, s.axis_v, s.normal_view, s.screen);
    if (!f.keep) {
        discard;
    }
    var buffer = 1.0;
    var normal = s.normal_world;
    if (u.mode == 2u) {
        buffer = textureLoad(visible_depth, vec2<i32>(s.position.xy), 0);
        normal = (u.inv_view * vec4<f32>(f.sphere_normal, 0.0)).xyz;
    }
    let w = splat_weight(f, buffer, s.screen.w);
    var out: Accumulated;
    out.colour = vec4<f32>(s.colour.rgb * w, w);
    out.normal_depth = vec4<f32>(normal * w, f.depth * w);
    out.depth = f.ndc;
    return out;
}

@group(0) @binding(1) var colour_acc: texture_2d<f32>;
@group(0) @binding(2) var normal_acc: texture_2d<f32>;

@vertex
fn vs_fullscreen(@builtin(vertex_index) vertex: u32) -> @builtin(position) vec4<f32> {
    return fullscreen_vertex(vertex);
}

// Normalisation and Blinn-Phong shading of one pixel (mirror: `shade` in src/splat/mod.rs).
fn shade(pixel: vec2<f32>, colour: vec4<f32>, normal_depth: vec4<f32>) -> vec4<f32> {
    let w = colour.a;
    if (!(w > 0.0)) {
        return u.background;
    }
    let base = colour.rgb / w;
    var n = normal_depth.xyz / w;
    let d = (u.inv_view * vec4<f32>(view_ray(pixel).dir, 0.0)).xyz;
    let view = -normalize(d);
    if (dot(n, n) > 1e-12) {
        n = normalize(n);
    } else {
        n = view;
    }
    let l = u.light_dir.xyz;
    let half_vector = normalize(l + view);
    let diffuse = max(dot(n, l), 0.0);
    let specular = pow(max(dot(n, half_vector), 0.0), u.material.x);
    let lit = base * (u.light_dir.w + (1.0 - u.light_dir.w) * diffuse) * u.light_colour.rgb + u.light_colour.w * specular * u.light_colour.rgb;
    return vec4<f32>(clamp(lit, vec3<f32>(0.0), vec3<f32>(1.0)), 1.0);
}

@fragment
fn fs_shade(@builtin(position) position: vec4<f32>) -> @location(0) vec4<f32> {
    let p = vec2<i32>(position.xy);
    return shade(position.xy, textureLoad(colour_acc, p, 0), textureLoad(normal_acc, p, 0));
}
