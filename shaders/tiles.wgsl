// Spheres binned into the screen's 16x16 tiles on the GPU (issue 37), the twin of `bin` in
// src/view/mod.rs: each tile's spheres in index order, as compressed rows (`starts`, `items`).
// Prepended at load: common.wgsl, scan.wgsl, bin_sort.wgsl (whose prefix sum and stable radix
// passes run over this binning's buffers: bound by binding number, each pipeline its own layout).
//
// `sphere_tiles`  per sphere: its pixel rectangle (`sphere_rect`: the bounding box of its
//                 bounding cube's projected corners, the whole screen when one lies behind the
//                 eye, nothing when all do or it misses the screen), the tiles it covers (their
//                 number and range), its pixels summed into a 64-bit count (the fragment cost)
// (bin_sort's `count_*` over the per-sphere counts: each sphere's first slot, the total last)
// `emit_pairs`    per slot below the capacity: the (tile, sphere) pair of that slot (the sphere by
//                 a binary search of the first slots, the tile row-major in its rectangle), or
//                 the sentinel key past the total, so the pairs lie in sphere order; each
//                 emitted pair counted in its tile
// (bin_sort's `count_*` over the tiles' counts: each tile's first item, the emitted total last;
// its radix passes: the pairs sorted by tile, stable, so each tile's spheres keep index order)
// `tile_items`    per slot: the sorted pair's sphere; the largest tile and the requested total
//                 into the statistics the host reads a few frames late

struct TileParams {
    // world to view, view to clip
    view: mat4x4<f32>,
    proj: mat4x4<f32>,
    // the image's width and height in pixels
    size: vec2<f32>,
    // tiles along x and y
    tiles: vec2<u32>,
    // the spheres; the pairs' capacity; the sentinel key (the number of tiles); a sphere's
    // stride in vec4s (its centre and radius in the first)
    count: u32,
    capacity: u32,
    sentinel: u32,
    stride: u32,
}

@group(0) @binding(8) var<uniform> tile_params: TileParams;
// centre (xyz) and radius (w) of each sphere, `stride` vec4s apart
@group(0) @binding(9) var<storage, read> spheres: array<vec4<f32>>;
// per sphere: tiles covered, then (after the scan) its first slot; one more entry: the total
@group(0) @binding(10) var<storage, read_write> sphere_slots: array<u32>;
// per sphere: its tile range, first and last along x, then y (inclusive)
@group(0) @binding(11) var<storage, read_write> rects: array<vec4<u32>>;
// the items: each tile's spheres, from `starts[tile]`
@group(0) @binding(12) var<storage, read_write> items: array<u32>;
// [0] pairs requested, [1] the most items of a tile, [2..3] pixel fragments (low, high word)
@group(0) @binding(13) var<storage, read_write> stats: array<atomic<u32>>;

const TILE: u32 = 16u;

// Pixel coordinates (origin top left) and view depth of a world point, as `View::project`.
fn project_point(world: vec3<f32>) -> vec3<f32> {
    let p = (tile_params.view * vec4<f32>(world, 1.0)).xyz;
    let clip = tile_params.proj * vec4<f32>(p, 1.0);
    let ndc = clip.xy / clip.w;
    return vec3<f32>((ndc.x + 1.0) * 0.5 * tile_params.size.x, (1.0 - ndc.y) * 0.5 * tile_params.size.y, -p.z);
}

// The pixels whose centres lie in [lo, hi) of a line of n, as `pixel_span`.
fn pixel_span(lo: f32, hi: f32, n: f32) -> vec2<u32> {
    return vec2<u32>(u32(clamp(ceil(lo - 0.5), 0.0, n)), u32(clamp(ceil(hi - 0.5), 0.0, n)));
}

@compute @workgroup_size(256)
fn sphere_tiles(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>,
                @builtin(local_invocation_index) local: u32) {
    let j = block_of(wg, groups) * 256u + local;
    if j >= tile_params.count {
        return;
    }
    let s = spheres[j * tile_params.stride];
    let r = s.w;
    var lo = vec2<f32>(3.4e38);
    var hi = vec2<f32>(-3.4e38);
    var behind = 0u;
    for (var k = 0u; k < 8u; k++) {
        let corner = vec3<f32>(select(-r, r, (k & 1u) != 0u), select(-r, r, (k & 2u) != 0u),
                               select(-r, r, (k & 4u) != 0u));
        let q = project_point(s.xyz + corner);
        // (NaN counts as behind)
        if !(q.z > 0.0) {
            behind++;
            continue;
        }
        lo = min(lo, q.xy);
        hi = max(hi, q.xy);
    }
    if behind > 0u {
        lo = vec2<f32>(0.0);
        hi = tile_params.size;
    }
    let x = pixel_span(lo.x, hi.x, tile_params.size.x);
    let y = pixel_span(lo.y, hi.y, tile_params.size.y);
    var covered = 0u;
    if behind < 8u && x.x < x.y && y.x < y.y {
        let range = vec4<u32>(x.x / TILE, (x.y - 1u) / TILE, y.x / TILE, (y.y - 1u) / TILE);
        rects[j] = range;
        covered = (range.y - range.x + 1u) * (range.w - range.z + 1u);
        // the fragments' 64-bit sum: a carry into the high word when the low one wraps
        let fragments = (x.y - x.x) * (y.y - y.x);
        let before = atomicAdd(&stats[2], fragments);
        if before + fragments < before {
            atomicAdd(&stats[3], 1u);
        }
    }
    sphere_slots[j] = covered;
}

@compute @workgroup_size(256)
fn emit_pairs(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>,
              @builtin(local_invocation_index) local: u32) {
    let q = block_of(wg, groups) * 256u + local;
    if q >= tile_params.capacity {
        return;
    }
    let n = tile_params.count;
    if q >= sphere_slots[n] {
        pairs_in[q] = vec2<u32>(tile_params.sentinel, 0u);
        return;
    }
    // the last sphere whose first slot is at most q (spheres covering no tile have the same
    // first slot as the next: the search passes over them)
    var a = 0u;
    var b = n;
    while b - a > 1u {
        let m = (a + b) / 2u;
        if sphere_slots[m] <= q {
            a = m;
        } else {
            b = m;
        }
    }
    let range = rects[a];
    let across = range.y - range.x + 1u;
    let k = q - sphere_slots[a];
    let tile = (range.z + k / across) * tile_params.tiles.x + range.x + k % across;
    pairs_in[q] = vec2<u32>(tile, a);
    atomicAdd(&starts[tile], 1u);
}

@compute @workgroup_size(256)
fn tile_items(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>,
              @builtin(local_invocation_index) local: u32) {
    let q = block_of(wg, groups) * 256u + local;
    let tiles = tile_params.tiles.x * tile_params.tiles.y;
    if q < tiles {
        atomicMax(&stats[1], atomicLoad(&starts[q + 1u]) - atomicLoad(&starts[q]));
    }
    if q == 0u {
        atomicStore(&stats[0], sphere_slots[tile_params.count]);
    }
    if q < min(sphere_slots[tile_params.count], tile_params.capacity) {
        items[q] = pairs_in[q].y;
    }
}
