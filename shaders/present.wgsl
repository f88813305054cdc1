// Presents the optics stage's finished frame (a storage buffer of linear RGBA, one vec4 per
// pixel, row-major from the top) in the caller's render pass: a full-screen triangle whose
// fragments read their pixel, clamp, and gamma-encode (2.2) as the CPU's `optics::encode` does.
// On an sRGB target the hardware encodes what the shader writes, so the shader writes the
// display value decoded by the sRGB curve: the stored byte is then the display value.

struct Present {
    width: u32,
    height: u32,
    // 1 when the target format is sRGB
    srgb_target: u32,
    _pad: u32,
}

@group(0) @binding(0) var<uniform> present: Present;
@group(0) @binding(1) var<storage, read> image: array<vec4<f32>>;

@vertex
fn vs_main(@builtin(vertex_index) i: u32) -> @builtin(position) vec4<f32> {
    return fullscreen_vertex(i);
}

fn srgb_to_linear(c: vec3<f32>) -> vec3<f32> {
    let low = c / 12.92;
    let high = pow((c + 0.055) / 1.055, vec3<f32>(2.4));
    return select(high, low, c <= vec3<f32>(0.04045));
}

@fragment
fn fs_main(@builtin(position) position: vec4<f32>) -> @location(0) vec4<f32> {
    let x = u32(position.x);
    let y = u32(position.y);
    if x >= present.width || y >= present.height {
        return vec4<f32>(0.0, 0.0, 0.0, 1.0);
    }
    let raw = image[y * present.width + x].rgb;
    // NaN to 0 (a NaN compares false), then clamp, as `optics::encode`
    let c = clamp(select(vec3<f32>(0.0), raw, raw == raw), vec3<f32>(0.0), vec3<f32>(1.0));
    let display = pow(c, vec3<f32>(1.0 / 2.2));
    if present.srgb_target == 1u {
        return vec4<f32>(srgb_to_linear(display), 1.0);
    }
    return vec4<f32>(display, 1.0);
}
