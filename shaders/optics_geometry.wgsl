// The geometry map of Iwasaki et al. §5.1.2: the receiver drawn from a view (the light's or the
// camera's), world position and view depth (w; 0 where no receiver) in one Rgba32Float target,
// the unit normal facing the view in the other. Read by optics.wgsl; the CPU reference traces
// the same texel-centre rays through the BVH instead.

// The geometry map: the receiver drawn from a view, position and depth in one target, the
// normal facing the view in the other.
struct GeometryU {
    view_proj: mat4x4<f32>,
    view: mat4x4<f32>,
    // xyz: eye (perspective) or view direction (orthographic); w = 1: orthographic
    eye: vec4<f32>,
}

@group(0) @binding(0) var<uniform> g: GeometryU;

struct GeometryOut {
    @builtin(position) position: vec4<f32>,
    @location(0) world: vec3<f32>,
    @location(1) depth: f32,
    @location(2) @interpolate(flat) normal: vec3<f32>,
}

@vertex
fn vs_geometry(@location(0) position: vec3<f32>, @location(1) normal: vec3<f32>) -> GeometryOut {
    var out: GeometryOut;
    out.position = g.view_proj * vec4<f32>(position, 1.0);
    out.world = position;
    out.depth = -(g.view * vec4<f32>(position, 1.0)).z;
    out.normal = normal;
    return out;
}

struct GeometryTargets {
    @location(0) position: vec4<f32>,
    @location(1) normal: vec4<f32>,
}

@fragment
fn fs_geometry(v: GeometryOut) -> GeometryTargets {
    var to_eye = -g.eye.xyz;
    if (g.eye.w == 0.0) {
        to_eye = g.eye.xyz - v.world;
    }
    var n = normalize(v.normal);
    if (dot(n, to_eye) < 0.0) {
        n = -n;
    }
    var out: GeometryTargets;
    out.position = vec4<f32>(v.world, v.depth);
    out.normal = vec4<f32>(n, 0.0);
    return out;
}
