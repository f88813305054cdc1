// The prefix sums of workgroups of 256 invocations that the passes compacting or sorting their
// output share (surfels.wgsl, bin_sort.wgsl, boundary_weights.wgsl), prepended at load after
// common.wgsl.

var<workgroup> scan: array<u32, 256>;

// The inclusive prefix sum of `value` over the workgroup (Hillis and Steele); every invocation
// of the workgroup calls it.
fn workgroup_scan(local: u32, value: u32) -> u32 {
    scan[local] = value;
    workgroupBarrier();
    for (var offset = 1u; offset < 256u; offset <<= 1u) {
        var add = 0u;
        if local >= offset {
            add = scan[local - offset];
        }
        workgroupBarrier();
        scan[local] += add;
        workgroupBarrier();
    }
    return scan[local];
}

// The block a workgroup of the two-dimensional dispatch handles.
fn block_of(wg: vec3<u32>, groups: vec3<u32>) -> u32 {
    return wg.x + wg.y * groups.x;
}
