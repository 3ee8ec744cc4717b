//! Real spherical harmonics up to degree 3, with the constants and sign
//! conventions of the original 3DGS (so trained PLYs interoperate).

use glam::Vec3;

pub const SH_C0: f32 = 0.282_094_8;
const SH_C1: f32 = 0.488_602_5;
const SH_C2: [f32; 5] = [1.092_548_4, -1.092_548_4, 0.315_391_57, -1.092_548_4, 0.546_274_2];
const SH_C3: [f32; 7] =
    [-0.590_043_6, 2.890_611_4, -0.457_045_8, 0.373_176_33, -0.457_045_8, 1.445_305_7, -0.590_043_6];

/// Basis values Y_k(d) for k < (degree+1)^2 at unit direction `d`; unused entries are 0.
pub fn basis(degree: u32, d: Vec3) -> [f32; 16] {
    let mut y = [0.0f32; 16];
    y[0] = SH_C0;
    if degree == 0 {
        return y;
    }
    let (x, yy, z) = (d.x, d.y, d.z);
    y[1] = -SH_C1 * yy;
    y[2] = SH_C1 * z;
    y[3] = -SH_C1 * x;
    if degree == 1 {
        return y;
    }
    let (xx, y2, zz) = (x * x, yy * yy, z * z);
    y[4] = SH_C2[0] * x * yy;
    y[5] = SH_C2[1] * yy * z;
    y[6] = SH_C2[2] * (2.0 * zz - xx - y2);
    y[7] = SH_C2[3] * x * z;
    y[8] = SH_C2[4] * (xx - y2);
    if degree == 2 {
        return y;
    }
    y[9] = SH_C3[0] * yy * (3.0 * xx - y2);
    y[10] = SH_C3[1] * x * yy * z;
    y[11] = SH_C3[2] * yy * (4.0 * zz - xx - y2);
    y[12] = SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * y2);
    y[13] = SH_C3[4] * x * (4.0 * zz - xx - y2);
    y[14] = SH_C3[5] * z * (xx - y2);
    y[15] = SH_C3[6] * x * (xx - 3.0 * y2);
    y
}

/// Gradients dY_k/dd (treating the direction's components as independent).
pub fn basis_grad(degree: u32, d: Vec3) -> [Vec3; 16] {
    let mut g = [Vec3::ZERO; 16];
    if degree == 0 {
        return g;
    }
    let (x, y, z) = (d.x, d.y, d.z);
    g[1] = Vec3::new(0.0, -SH_C1, 0.0);
    g[2] = Vec3::new(0.0, 0.0, SH_C1);
    g[3] = Vec3::new(-SH_C1, 0.0, 0.0);
    if degree == 1 {
        return g;
    }
    let (xx, yy, zz) = (x * x, y * y, z * z);
    g[4] = SH_C2[0] * Vec3::new(y, x, 0.0);
    g[5] = SH_C2[1] * Vec3::new(0.0, z, y);
    g[6] = SH_C2[2] * Vec3::new(-2.0 * x, -2.0 * y, 4.0 * z);
    g[7] = SH_C2[3] * Vec3::new(z, 0.0, x);
    g[8] = SH_C2[4] * Vec3::new(2.0 * x, -2.0 * y, 0.0);
    if degree == 2 {
        return g;
    }
    g[9] = SH_C3[0] * Vec3::new(6.0 * x * y, 3.0 * xx - 3.0 * yy, 0.0);
    g[10] = SH_C3[1] * Vec3::new(y * z, x * z, x * y);
    g[11] = SH_C3[2] * Vec3::new(-2.0 * x * y, 4.0 * zz - xx - 3.0 * yy, 8.0 * y * z);
    g[12] = SH_C3[3] * Vec3::new(-6.0 * x * z, -6.0 * y * z, 6.0 * zz - 3.0 * xx - 3.0 * yy);
    g[13] = SH_C3[4] * Vec3::new(4.0 * zz - 3.0 * xx - yy, -2.0 * x * y, 8.0 * x * z);
    g[14] = SH_C3[5] * Vec3::new(2.0 * x * z, -2.0 * y * z, xx - yy);
    g[15] = SH_C3[6] * Vec3::new(3.0 * xx - 3.0 * yy, -6.0 * x * y, 0.0);
    g
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn basis_gradient_matches_finite_differences() {
        let d = Vec3::new(0.3, -0.5, 0.8);
        let eps = 1e-3;
        let g = basis_grad(3, d);
        for axis in 0..3 {
            let mut e = Vec3::ZERO;
            e[axis] = eps;
            let (p, m) = (basis(3, d + e), basis(3, d - e));
            for k in 0..16 {
                let fd = (p[k] - m[k]) / (2.0 * eps);
                assert!((fd - g[k][axis]).abs() < 1e-3, "k={k} axis={axis}: fd {fd} analytic {}", g[k][axis]);
            }
        }
    }

    #[test]
    fn degree_one_is_linear_in_direction() {
        let y = basis(1, Vec3::X);
        assert_eq!(y[3], -SH_C1);
        assert_eq!(y[1], 0.0);
        assert_eq!(basis(0, Vec3::X)[1], 0.0);
    }
}
