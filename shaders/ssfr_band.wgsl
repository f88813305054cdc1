// The screen-space renderer's inputs made from the narrow band on the GPU (issue 37), the twin of
// `ScreenSpace`'s on the CPU (src/ssfr/cpu.rs: `ScreenSpace::prepare`, `project_sources`).
// Prepended at load: lnm.wgsl, whose passes (`cs_count` in full, then `cs_first`, `cs_second`) make
// each voxel's count, offsets' sum and label and each point's voxel over the points `positions`
// (centre and kernel radius). Indexed as the CPU's lists are found (`GpuSsfr` in src/ssfr/gpu.rs):
// a sphere per point and a source per voxel of the dense domain, those the CPU leaves out given
// radius 0, which no tile holds (`sphere_rect`: an empty pixel span), so that each tile's items
// are the CPU's in the CPU's order (the full voxels in key order: z, then y, then x).
//
//   cs_radii    per point: its kernel radius and the cube of it summed into its voxel in fixed
//               point (integer atomics: the sums do not depend on the order)
//   cs_spheres  per point: its depth pass sphere (its centre, `sphere_radius` times its radius)
//               when its voxel is in the band (label 1 or 2), else radius 0
//   cs_sources  per voxel: eq. 3's Gaussian of a full voxel (at its points' centroid, their volume,
//               sigma from their mean radius) as the tiles' sphere of three sigma, and its sigma
//               and volume; an empty voxel's sphere has radius 0
//   cs_project  per voxel: the Gaussian as the thickness pass reads it from the view (projected
//               centre in pixels, -1 / (2 sigma_px^2), amplitude volume / (2 pi sigma^2); zeros
//               behind a perspective view or for an empty voxel)

struct SsfrBand {
    // sphere radius and thickness sigma in kernel radii, the reference radius h, the voxel edge
    a: vec4<f32>,
    // voxels of the domain, -, -, -
    b: vec4<u32>,
    // the view: world to view, view to clip (as the tiles' `TileParams`)
    view: mat4x4<f32>,
    proj: mat4x4<f32>,
    // width, height, the pixel's world size at depth 1 (orthographic: the pixel's), orthographic
    // (1) or perspective (0)
    screen: vec4<f32>,
}

@group(0) @binding(6) var<uniform> ssfr_band: SsfrBand;
// per voxel: the sum of its points' radii over h, and of their cubes, in fixed point
@group(0) @binding(7) var<storage, read_write> radius_sums: array<atomic<u32>>;
// per point: its depth pass sphere (centre, radius; radius 0: not drawn)
@group(0) @binding(8) var<storage, read_write> band_spheres: array<vec4<f32>>;
// per voxel: its Gaussian's sphere of three sigma (radius 0: no Gaussian)
@group(0) @binding(9) var<storage, read_write> source_spheres: array<vec4<f32>>;
// per voxel: its Gaussian's sigma and volume
@group(0) @binding(10) var<storage, read_write> source_props: array<vec2<f32>>;
// per voxel: the Gaussian projected into the view (the thickness pass's `sources`)
@group(0) @binding(11) var<storage, read_write> projected: array<vec4<f32>>;

// Fixed-point scale of a radius over h (at most 1: a voxel's sum fits 32 bits up to 2^20 points).
const RADIUS_SCALE: f32 = 4096.0;
// Fixed-point scale of a radius' cube over h^3: a point of radius h / 8 (three refinement steps)
// adds 32,768 exactly; a voxel of more than CUBE_COUNT points of radius h could overflow its sum,
// and takes its volume from its mean radius instead (exact when the radii are alike).
const CUBE_SCALE: f32 = 16777216.0;
const CUBE_COUNT: u32 = 255u;
// A voxel of more points than this could overflow its offsets' sums (lnm.wgsl's fixed point,
// `MAX_FIXED_COUNT` in src/lnm/gpu.rs): its Gaussian sits at the voxel's centre.
const OFFSET_COUNT: u32 = 32767u;

@compute @workgroup_size(64)
fn cs_radii(@builtin(global_invocation_id) id: vec3<u32>) {
    let i = invocation(id);
    if i >= params.dims.w {
        return;
    }
    let v = voxel_of[i];
    let r = min(positions[i].w / ssfr_band.a.z, 1.0);
    atomicAdd(&radius_sums[2u * v], u32(round(r * RADIUS_SCALE)));
    atomicAdd(&radius_sums[2u * v + 1u], u32(round(r * r * r * CUBE_SCALE)));
}

@compute @workgroup_size(64)
fn cs_spheres(@builtin(global_invocation_id) id: vec3<u32>) {
    let i = invocation(id);
    if i >= params.dims.w {
        return;
    }
    let p = positions[i];
    let drawn = labels[voxel_of[i]] != 0u;
    band_spheres[i] = vec4<f32>(p.xyz, select(0.0, ssfr_band.a.x * p.w, drawn));
}

@compute @workgroup_size(64)
fn cs_sources(@builtin(global_invocation_id) id: vec3<u32>) {
    let v = invocation(id);
    if v >= ssfr_band.b.x {
        return;
    }
    let c = atomicLoad(&counts[v]);
    if c == 0u {
        source_spheres[v] = vec4<f32>(0.0);
        source_props[v] = vec2<f32>(0.0);
        return;
    }
    let n = f32(c);
    var offset = vec3<f32>(0.5);
    if c <= OFFSET_COUNT {
        let sum = vec3<f32>(
            f32(atomicLoad(&sums[3u * v])),
            f32(atomicLoad(&sums[3u * v + 1u])),
            f32(atomicLoad(&sums[3u * v + 2u])),
        );
        offset = sum / (n * f32(params.misc.y));
    }
    let edge = ssfr_band.a.w;
    let centroid = params.lo.xyz + (vec3<f32>(voxel_coord(v)) + offset) * edge;
    let h = ssfr_band.a.z;
    let mean = f32(atomicLoad(&radius_sums[2u * v])) / RADIUS_SCALE * h / n;
    // the points' volume, (r / 2)^3 each
    var volume = n * pow(0.5 * mean, 3.0);
    if c <= CUBE_COUNT {
        volume = f32(atomicLoad(&radius_sums[2u * v + 1u])) / CUBE_SCALE * (0.125 * h * h * h);
    }
    let sigma = ssfr_band.a.y * mean;
    source_spheres[v] = vec4<f32>(centroid, 3.0 * sigma);
    source_props[v] = vec2<f32>(sigma, volume);
}

@compute @workgroup_size(64)
fn cs_project(@builtin(global_invocation_id) id: vec3<u32>) {
    let v = invocation(id);
    if v >= ssfr_band.b.x {
        return;
    }
    let s = source_spheres[v];
    let orthographic = ssfr_band.screen.w > 0.5;
    // `View::project`: pixel coordinates (origin top left) and view depth
    let p = (ssfr_band.view * vec4<f32>(s.xyz, 1.0)).xyz;
    let clip = ssfr_band.proj * vec4<f32>(p, 1.0);
    let ndc = clip.xy / clip.w;
    let q = vec3<f32>((ndc.x + 1.0) * 0.5 * ssfr_band.screen.x,
                      (1.0 - ndc.y) * 0.5 * ssfr_band.screen.y, -p.z);
    if s.w == 0.0 || (!(q.z > 0.0) && !orthographic) {
        projected[v] = vec4<f32>(0.0);
        return;
    }
    let props = source_props[v];
    let sigma = props.x;
    let pixel = select(ssfr_band.screen.z * q.z, ssfr_band.screen.z, orthographic);
    let sigma_px = sigma / pixel;
    let amplitude = props.y / (6.283185307179586 * sigma * sigma);
    projected[v] = vec4<f32>(q.xy, -0.5 / (sigma_px * sigma_px), amplitude);
}
