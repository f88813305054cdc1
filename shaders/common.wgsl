// WGSL the passes share, prepended at load to every pass's file (the `concat!` beside each
// pass's Rust twin): the density kernels, the ray type, the full-screen triangle.

// The density kernels of the density passes (density_splat.wgsl, density_gather.wgsl). The arithmetic is the CPU path's (`Kernel::weighted_r2` in
// src/density/mod.rs): Wyvill's kernel as a polynomial in a^2 = r^2 / h^2, the cubic spline in
// q = 2 r / h, for the point's own radius h, times the reference radius's constant.
// kernel 0: Wyvill, 1: cubic spline; constant: 2835 / (736 pi h_ref^3) or 8 / (pi h_ref^3).
fn density_kernel_r2(r2: f32, h: f32, constant: f32, kernel: u32) -> f32 {
    if kernel == 0u {
        let a2 = r2 * (1.0 / (h * h));
        let poly = ((-4.0 / 9.0 * a2 + 17.0 / 9.0) * a2 - 22.0 / 9.0) * a2 + 1.0;
        return select(0.0, constant * poly, a2 < 1.0);
    }
    let q = 2.0 * sqrt(r2) / h;
    if q >= 2.0 {
        return 0.0;
    }
    if q < 1.0 {
        return constant * (1.0 - 1.5 * q * q + 0.75 * q * q * q);
    }
    let t = 2.0 - q;
    return constant * 0.25 * t * t * t;
}

// A point of the compute passes (density_gather.wgsl, surfels.wgsl), the `RawPoint` of
// src/density/gpu.rs: position and radius (w), and its weight in the density.
struct Point {
    at: vec4<f32>,
    weight: f32,
}

// `Point` with the index `RawPoint` keeps in the first word of its padding (the passes that
// tell the points apart: boundary_weights.wgsl; bin_sort.wgsl, whose copies keep it).
struct IndexedPoint {
    at: vec4<f32>,
    weight: f32,
    index: u32,
    pad0: u32,
    pad1: u32,
}

// The bins of the binned points (`BinnedPoints`) within `reach` bins of the bin holding x on
// each side, clamped to the bins there are: the lowest and the highest (the gather pass and the
// surfels' projection search them).
struct BinRange {
    lo: vec3<i32>,
    hi: vec3<i32>,
}

fn bin_range(x: vec3<f32>, origin: vec3<f32>, size: f32, bins: vec3<u32>, reach: u32) -> BinRange {
    let b = vec3<i32>(floor((x - origin) / size));
    let last = vec3<i32>(bins) - vec3<i32>(1);
    let r = vec3<i32>(i32(reach));
    return BinRange(clamp(b - r, vec3<i32>(0), last), clamp(b + r, vec3<i32>(0), last));
}

// The bins of row (by, bz) within `range` that a ball of `radius` around x reaches along x:
// (first, last), empty when first > last. A point binned in the row lies within the row's
// extent in y and z, so at least its gaps `gy`, `gz` from x there, and within
// sqrt(radius^2 - gy^2 - gz^2) of x along x; rounded out to bins. The margin covers the
// rounding of a point's bin (a few ulps of its coordinates) and of these sums, so that a point
// the ball reaches is never left out: a search over the spans visits every point within
// `radius` that the whole range does, in the same order, and fewer others.
fn row_span(x: vec3<f32>, origin: vec3<f32>, size: f32, range: BinRange, by: i32, bz: i32, radius: f32) -> vec2<i32> {
    let far = max(abs(x), abs(origin));
    let margin = 1.0e-4 * (radius + size) + 1.0e-6 * max(far.x, max(far.y, far.z));
    let y0 = origin.y + f32(by) * size;
    let z0 = origin.z + f32(bz) * size;
    let gy = max(max(y0 - x.y, x.y - (y0 + size)) - margin, 0.0);
    let gz = max(max(z0 - x.z, x.z - (z0 + size)) - margin, 0.0);
    let r = radius + margin;
    let rest = r * r - gy * gy - gz * gz;
    if rest < 0.0 {
        return vec2<i32>(1, 0);
    }
    let ext = sqrt(rest) + margin;
    let first = max(i32(floor((x.x - ext - origin.x) / size)), range.lo.x);
    let last = min(i32(floor((x.x + ext - origin.x) / size)), range.hi.x);
    return vec2<i32>(first, last);
}

// The bins of row (by, bz) that density sums at x read: xy where the ball of `largest` (every
// point's radius at most) reaches, zw where the ball of `rest` reaches, the only bins where the
// points after the leading ones (of radius at most `rest`) are read; a negative `rest`: the
// range's whole row for both (`BinSearch::Whole`, the reference the trimmed search must equal).
fn row_spans(x: vec3<f32>, origin: vec3<f32>, size: f32, range: BinRange, by: i32, bz: i32, largest: f32, rest: f32) -> vec4<i32> {
    if rest < 0.0 {
        return vec4<i32>(range.lo.x, range.hi.x, range.lo.x, range.hi.x);
    }
    return vec4<i32>(
        row_span(x, origin, size, range, by, bz, largest),
        row_span(x, origin, size, range, by, bz, rest),
    );
}

// A ray: origin and direction (view space in the splat passes, world space in the optics).
struct Ray {
    origin: vec3<f32>,
    dir: vec3<f32>,
}

// The clip-space position of vertex 0, 1 or 2 of a triangle that covers the whole screen.
fn fullscreen_vertex(vertex: u32) -> vec4<f32> {
    let xy = vec2<f32>(f32((vertex << 1u) & 2u), f32(vertex & 2u));
    return vec4<f32>(xy * 2.0 - 1.0, 0.0, 1.0);
}
