//! SPH smoothing kernels of Müller et al. 2003 ("Particle-based fluid simulation for interactive
//! applications", \[MCG03\] in Solenthaler et al. 2007), shared by surface detection and the
//! built-in simulator. `h` is the support radius: every kernel is zero for `r >= h`.

use std::f32::consts::PI;

use glam::Vec3;

/// Poly6 kernel `W(r, h) = 315 / (64 pi h^9) (h^2 - r^2)^3`, given `r^2`.
#[must_use]
#[inline]
pub fn poly6(r2: f32, h: f32) -> f32 {
    let h2 = h * h;
    if r2 >= h2 {
        return 0.0;
    }
    let d = h2 - r2;
    315.0 / (64.0 * PI * h.powi(9)) * d * d * d
}

/// Gradient of the poly6 kernel with respect to `r = x_i - x_j`:
/// `-945 / (32 pi h^9) (h^2 - r^2)^2 r`.
#[must_use]
#[inline]
pub fn poly6_gradient(r: Vec3, h: f32) -> Vec3 {
    let h2 = h * h;
    let r2 = r.length_squared();
    if r2 >= h2 {
        return Vec3::ZERO;
    }
    let d = h2 - r2;
    r * (-945.0 / (32.0 * PI * h.powi(9)) * d * d)
}

/// Gradient of the spiky kernel `W = 15 / (pi h^6) (h - r)^3` with respect to `r = x_i - x_j`:
/// `-45 / (pi h^6) (h - |r|)^2 r / |r|`; zero at `r = 0` (the direction is undefined there).
#[must_use]
#[inline]
pub fn spiky_gradient(r: Vec3, h: f32) -> Vec3 {
    let len = r.length();
    if len >= h || len <= 1e-12 * h {
        return Vec3::ZERO;
    }
    let d = h - len;
    r * (-45.0 / (PI * h.powi(6)) * d * d / len)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Midpoint-rule integral over a cube of side 2h sampled on n^3 points.
    fn integrate(h: f32, n: usize, f: impl Fn(Vec3) -> f32) -> f64 {
        let step = 2.0 * h / n as f32;
        let mut sum = 0.0f64;
        for i in 0..n {
            for j in 0..n {
                for k in 0..n {
                    let p = Vec3::new(i as f32 + 0.5, j as f32 + 0.5, k as f32 + 0.5) * step
                        - Vec3::splat(h);
                    sum += f(p) as f64;
                }
            }
        }
        sum * (step as f64).powi(3)
    }

    #[test]
    fn poly6_integrates_to_one() {
        for h in [0.1f32, 1.0, 3.0] {
            let total = integrate(h, 80, |p| poly6(p.length_squared(), h));
            assert!((total - 1.0).abs() < 2e-3, "h = {h}: {total}");
        }
    }

    #[test]
    fn gradients_match_finite_differences() {
        let h = 0.7;
        for p in [
            Vec3::new(0.1, 0.2, -0.3),
            Vec3::new(0.5, 0.1, 0.1),
            Vec3::new(-0.2, 0.0, 0.05),
        ] {
            let e = 1e-3;
            let fd = Vec3::new(
                poly6((p + Vec3::X * e).length_squared(), h)
                    - poly6((p - Vec3::X * e).length_squared(), h),
                poly6((p + Vec3::Y * e).length_squared(), h)
                    - poly6((p - Vec3::Y * e).length_squared(), h),
                poly6((p + Vec3::Z * e).length_squared(), h)
                    - poly6((p - Vec3::Z * e).length_squared(), h),
            ) / (2.0 * e);
            let g = poly6_gradient(p, h);
            assert!(
                (fd - g).length() < 1e-2 * g.length().max(1.0),
                "{fd} vs {g}"
            );
            let spiky = |q: Vec3| {
                let l = q.length();
                if l >= h {
                    0.0
                } else {
                    15.0 / (PI * h.powi(6)) * (h - l).powi(3)
                }
            };
            let fd = Vec3::new(
                spiky(p + Vec3::X * e) - spiky(p - Vec3::X * e),
                spiky(p + Vec3::Y * e) - spiky(p - Vec3::Y * e),
                spiky(p + Vec3::Z * e) - spiky(p - Vec3::Z * e),
            ) / (2.0 * e);
            let g = spiky_gradient(p, h);
            assert!(
                (fd - g).length() < 1e-2 * g.length().max(1.0),
                "{fd} vs {g}"
            );
        }
        assert_eq!(spiky_gradient(Vec3::ZERO, h), Vec3::ZERO);
        assert_eq!(poly6_gradient(Vec3::X * h, h), Vec3::ZERO);
    }
}
