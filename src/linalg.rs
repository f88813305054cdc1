//! Small dense linear algebra that glam does not provide.

use glam::{Mat3, Vec3};

/// Eigen-decomposition of a symmetric 3x3 matrix by cyclic Jacobi rotations.
///
/// Returns the eigenvalues in ascending order and the matching unit eigenvectors.
/// Only the symmetric part of `m` is used. Jacobi is slower than a closed form but accurate for
/// nearly repeated eigenvalues, which flat neighbourhoods produce.
#[must_use]
#[allow(clippy::needless_range_loop)] // index loops read like the rotation formulas
pub fn symmetric_eigen(m: Mat3) -> ([f32; 3], [Vec3; 3]) {
    let mut a = [[0.0f64; 3]; 3];
    for (r, row) in a.iter_mut().enumerate() {
        for (c, v) in row.iter_mut().enumerate() {
            *v = 0.5 * (m.col(c)[r] as f64 + m.col(r)[c] as f64);
        }
    }
    let mut v = [[1.0f64, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    for _sweep in 0..32 {
        let off = a[0][1].abs() + a[0][2].abs() + a[1][2].abs();
        let scale = a[0][0].abs() + a[1][1].abs() + a[2][2].abs();
        if off <= 1e-15 * scale || off == 0.0 {
            break;
        }
        for (p, q) in [(0usize, 1usize), (0, 2), (1, 2)] {
            if a[p][q] == 0.0 {
                continue;
            }
            let theta = (a[q][q] - a[p][p]) / (2.0 * a[p][q]);
            let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
            let t = if theta == 0.0 { 1.0 } else { t };
            let c = 1.0 / (t * t + 1.0).sqrt();
            let s = t * c;
            for k in 0..3 {
                let akp = a[k][p];
                let akq = a[k][q];
                a[k][p] = c * akp - s * akq;
                a[k][q] = s * akp + c * akq;
            }
            for k in 0..3 {
                let apk = a[p][k];
                let aqk = a[q][k];
                a[p][k] = c * apk - s * aqk;
                a[q][k] = s * apk + c * aqk;
            }
            for row in &mut v {
                let vp = row[p];
                let vq = row[q];
                row[p] = c * vp - s * vq;
                row[q] = s * vp + c * vq;
            }
        }
    }
    let mut idx = [0usize, 1, 2];
    idx.sort_by(|&i, &j| a[i][i].total_cmp(&a[j][j]));
    let values = idx.map(|i| a[i][i] as f32);
    let vectors =
        idx.map(|i| Vec3::new(v[0][i] as f32, v[1][i] as f32, v[2][i] as f32).normalize_or_zero());
    (values, vectors)
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Quat;

    #[test]
    fn recovers_a_rotated_diagonal() {
        for (k, diag) in [
            [1.0, 2.0, 3.0],
            [0.0, 0.0, 5.0],
            [2.0, 2.0, 2.0],
            [1e-6, 1.0, 1.0],
        ]
        .into_iter()
        .enumerate()
        {
            let r = Mat3::from_quat(Quat::from_euler(
                glam::EulerRot::XYZ,
                0.3 * k as f32,
                1.1,
                -0.7,
            ));
            let m = r * Mat3::from_diagonal(Vec3::from(diag)) * r.transpose();
            let (vals, vecs) = symmetric_eigen(m);
            let mut sorted = diag;
            sorted.sort_by(f32::total_cmp);
            for i in 0..3 {
                assert!((vals[i] - sorted[i]).abs() < 1e-5, "{vals:?} vs {sorted:?}");
                let mv = m * vecs[i];
                assert!(
                    (mv - vecs[i] * vals[i]).length() < 1e-4,
                    "case {k} vector {i}"
                );
                assert!((vecs[i].length() - 1.0).abs() < 1e-5);
            }
        }
    }
}
