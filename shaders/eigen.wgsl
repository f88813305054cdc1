// The eigen-decomposition of a symmetric 3x3 matrix by cyclic Jacobi rotations, in f32 (the
// CPU's `linalg::symmetric_eigen` works in f64): the ray caster's PCA normals
// (shaders/raycast.wgsl) and the boundary calibration's sheets one particle thick
// (shaders/boundary_weights.wgsl) share it.

// The eigenvalues in ascending order (ties in index order, a stable sort as the CPU's) and the
// unit eigenvector of the smallest (zero where it has no length).
struct Eigen {
    values: vec3<f32>,
    least: vec3<f32>,
}

// The eigenvalues and least eigenvector of the symmetric matrix with rows m0, m1, m2.
fn symmetric_eigen(m0: vec3<f32>, m1: vec3<f32>, m2: vec3<f32>) -> Eigen {
    var a = array<array<f32, 3>, 3>(
        array<f32, 3>(m0.x, m0.y, m0.z),
        array<f32, 3>(m1.x, m1.y, m1.z),
        array<f32, 3>(m2.x, m2.y, m2.z),
    );
    var v = array<array<f32, 3>, 3>(
        array<f32, 3>(1.0, 0.0, 0.0),
        array<f32, 3>(0.0, 1.0, 0.0),
        array<f32, 3>(0.0, 0.0, 1.0),
    );
    let pairs = array<vec2<u32>, 3>(vec2<u32>(0u, 1u), vec2<u32>(0u, 2u), vec2<u32>(1u, 2u));
    for (var sweep = 0; sweep < 32; sweep++) {
        let off = abs(a[0][1]) + abs(a[0][2]) + abs(a[1][2]);
        let scale = abs(a[0][0]) + abs(a[1][1]) + abs(a[2][2]);
        if (off <= 1e-7 * scale || off == 0.0) {
            break;
        }
        for (var k = 0u; k < 3u; k++) {
            let pp = pairs[k].x;
            let qq = pairs[k].y;
            if (a[pp][qq] == 0.0) {
                continue;
            }
            let theta = (a[qq][qq] - a[pp][pp]) / (2.0 * a[pp][qq]);
            var t = sign(theta) / (abs(theta) + sqrt(theta * theta + 1.0));
            if (theta == 0.0) {
                t = 1.0;
            }
            let c = 1.0 / sqrt(t * t + 1.0);
            let s = t * c;
            for (var i = 0u; i < 3u; i++) {
                let aip = a[i][pp];
                let aiq = a[i][qq];
                a[i][pp] = c * aip - s * aiq;
                a[i][qq] = s * aip + c * aiq;
            }
            for (var i = 0u; i < 3u; i++) {
                let api = a[pp][i];
                let aqi = a[qq][i];
                a[pp][i] = c * api - s * aqi;
                a[qq][i] = s * api + c * aqi;
            }
            for (var i = 0u; i < 3u; i++) {
                let vp = v[i][pp];
                let vq = v[i][qq];
                v[i][pp] = c * vp - s * vq;
                v[i][qq] = s * vp + c * vq;
            }
        }
    }
    // ascending order of the diagonal, ties in index order (a stable sort, as the CPU's)
    var i0 = 0u;
    var i1 = 1u;
    var i2 = 2u;
    if (a[i1][i1] < a[i0][i0]) { let t = i0; i0 = i1; i1 = t; }
    if (a[i2][i2] < a[i1][i1]) { let t = i1; i1 = i2; i2 = t; }
    if (a[i1][i1] < a[i0][i0]) { let t = i0; i0 = i1; i1 = t; }
    let n = vec3<f32>(v[0][i0], v[1][i0], v[2][i0]);
    let len = length(n);
    return Eigen(
        vec3<f32>(a[i0][i0], a[i1][i1], a[i2][i2]),
        select(vec3<f32>(0.0), n / len, len > 0.0),
    );
}
