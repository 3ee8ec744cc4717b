//! Turning view-dependent colour with a rotated Gaussian: each SH band of degree
//! l is closed under rotation, so the rotated function f'(d) = f(R^T d) has
//! band-l coefficients M_l c_l. M_l is found by least squares on 2(2l+1)+1
//! directions (exact: both sides lie in the band's span), from the renderer's
//! own basis, so its constants and sign conventions are the ones rendered.

use glam::{Mat3, Vec3};

use crate::render::sh::basis;

/// Rotate the SH coefficients above degree 0 (`rest`: per Gaussian, coefficient-major
/// `[k][rgb]`, k = 1..(degree+1)^2) of every Gaussian by `r`.
pub(crate) fn rotate_sh_rest(rest: &mut [f32], degree: u32, r: Mat3) {
    if degree == 0 || rest.is_empty() {
        return;
    }
    let width = 3 * (((degree + 1) * (degree + 1)) as usize - 1);
    let bands: Vec<(usize, Vec<f64>)> = (1..=degree as usize).map(|l| (l * l, band_matrix(l, degree, r))).collect();
    for row in rest.chunks_exact_mut(width) {
        for (first, m) in &bands {
            let n = 2 * (first.isqrt()) + 1;
            for c in 0..3 {
                let old: Vec<f64> = (0..n).map(|k| f64::from(row[3 * (first + k - 1) + c])).collect();
                for i in 0..n {
                    row[3 * (first + i - 1) + c] = (0..n).map(|k| m[i * n + k] * old[k]).sum::<f64>() as f32;
                }
            }
        }
    }
}

/// The (2l+1)^2 matrix (row-major) taking band l's coefficients of f to those of f(R^T d).
fn band_matrix(l: usize, degree: u32, r: Mat3) -> Vec<f64> {
    let (first, n) = (l * l, 2 * l + 1);
    let samples = 2 * n + 1;
    let band = |d: Vec3| -> Vec<f64> { basis(degree, d)[first..first + n].iter().map(|&y| f64::from(y)).collect() };
    // Directions spread on the sphere (Fibonacci), so A^T A is well conditioned.
    let golden = std::f32::consts::PI * (3.0 - 5f32.sqrt());
    let dirs: Vec<Vec3> = (0..samples)
        .map(|i| {
            let z = 1.0 - 2.0 * (i as f32 + 0.5) / samples as f32;
            let rho = (1.0 - z * z).sqrt();
            let phi = golden * i as f32;
            Vec3::new(rho * phi.cos(), rho * phi.sin(), z)
        })
        .collect();
    let a: Vec<Vec<f64>> = dirs.iter().map(|&d| band(d)).collect();
    let b: Vec<Vec<f64>> = dirs.iter().map(|&d| band(r.transpose() * d)).collect();
    // Solve (A^T A) M = A^T B.
    let mut ata = vec![0.0; n * n];
    let mut atb = vec![0.0; n * n];
    for (ra, rb) in a.iter().zip(&b) {
        for i in 0..n {
            for j in 0..n {
                ata[i * n + j] += ra[i] * ra[j];
                atb[i * n + j] += ra[i] * rb[j];
            }
        }
    }
    solve(&mut ata, &mut atb, n);
    atb
}

/// Gauss-Jordan elimination with partial pivoting: `rhs` <- `lhs`^-1 `rhs` (both n x n, row-major).
fn solve(lhs: &mut [f64], rhs: &mut [f64], n: usize) {
    for col in 0..n {
        let pivot = (col..n).max_by(|&i, &j| lhs[i * n + col].abs().total_cmp(&lhs[j * n + col].abs())).unwrap_or(col);
        for k in 0..n {
            lhs.swap(col * n + k, pivot * n + k);
            rhs.swap(col * n + k, pivot * n + k);
        }
        let p = lhs[col * n + col];
        for k in 0..n {
            lhs[col * n + k] /= p;
            rhs[col * n + k] /= p;
        }
        for i in (0..n).filter(|&i| i != col) {
            let f = lhs[i * n + col];
            for k in 0..n {
                lhs[i * n + k] -= f * lhs[col * n + k];
                rhs[i * n + k] -= f * rhs[col * n + k];
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use glam::{Affine3A, Quat, Vec3};

    use crate::render::sh::basis;
    use crate::splat::GaussianSet;

    /// Colour channel c of Gaussian 0 seen along direction d (without the DC term).
    fn view_colour(g: &GaussianSet, d: Vec3, c: usize) -> f32 {
        let y = basis(g.sh_degree, d);
        (1..16.min(((g.sh_degree + 1) * (g.sh_degree + 1)) as usize)).map(|k| y[k] * g.sh_rest[3 * (k - 1) + c]).sum()
    }

    #[test]
    fn turned_gaussians_show_the_same_colour_from_the_turned_direction() {
        let rest: Vec<f32> = (0..45).map(|i| ((i * 37 % 11) as f32 - 5.0) / 7.0).collect();
        let mut g = GaussianSet::new(3);
        g.push(Vec3::new(0.1, 0.2, 0.3), Vec3::splat(-3.0), [1.0, 0.0, 0.0, 0.0], 0.0, [0.1, 0.2, 0.3], &rest);
        let q = Quat::from_axis_angle(Vec3::new(1.0, -2.0, 0.5).normalize(), 1.2);
        let m = Affine3A::from_rotation_translation(q, Vec3::new(0.5, -0.3, 0.2));
        let t = g.transformed(&m);
        assert!((t.mean(0) - m.transform_point3(g.mean(0))).length() < 1e-6);
        assert!(t.rotation(0).angle_between(q) < 1e-5);
        for d in [Vec3::X, Vec3::new(0.3, -0.8, 0.52).normalize(), Vec3::new(-0.6, 0.1, -0.79).normalize()] {
            for c in 0..3 {
                let (before, after) = (view_colour(&g, d, c), view_colour(&t, q * d, c));
                assert!((before - after).abs() < 1e-4, "channel {c} along {d}: {before} vs {after}");
            }
        }
    }
}
