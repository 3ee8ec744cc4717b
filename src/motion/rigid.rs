//! Rigid transforms and the least-squares rigid fit (Kabsch problem), solved
//! with Horn's quaternion method: the optimal rotation is the eigenvector of a
//! symmetric 4x4 matrix with the largest eigenvalue, so the result is always a
//! proper rotation (no reflection case to repair) and needs no SVD crate.

use glam::{DMat3, DQuat, DVec3, Mat3, Vec3};

/// x -> r x + t.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Rigid {
    pub r: DMat3,
    pub t: DVec3,
}

impl Rigid {
    pub const IDENTITY: Rigid = Rigid { r: DMat3::IDENTITY, t: DVec3::ZERO };

    pub fn apply(&self, p: DVec3) -> DVec3 {
        self.r * p + self.t
    }

    /// How far the motion carries point `p`: a part's displacement when `p` is its
    /// centroid (unlike t, whatever the origin).
    pub fn displacement(&self, p: DVec3) -> DVec3 {
        self.apply(p) - p
    }

    pub fn apply_f32(&self, p: Vec3) -> Vec3 {
        self.apply(p.as_dvec3()).as_vec3()
    }

    /// Rotation angle in radians, in [0, pi].
    pub fn angle(&self) -> f64 {
        ((self.r.x_axis.x + self.r.y_axis.y + self.r.z_axis.z - 1.0) * 0.5).clamp(-1.0, 1.0).acos()
    }

    pub fn rotation_f32(&self) -> Mat3 {
        self.r.as_mat3()
    }
}

/// Eigen-decomposition of a symmetric 4x4 matrix by cyclic Jacobi rotations;
/// returns (eigenvalues, eigenvectors as columns).
fn jacobi_eigen4(mut a: [[f64; 4]; 4]) -> ([f64; 4], [[f64; 4]; 4]) {
    let mut v = [[0.0; 4]; 4];
    for (i, row) in v.iter_mut().enumerate() {
        row[i] = 1.0;
    }
    for _sweep in 0..50 {
        let off: f64 = (0..4).flat_map(|i| (i + 1..4).map(move |j| (i, j))).map(|(i, j)| a[i][j] * a[i][j]).sum();
        if off < 1e-30 {
            break;
        }
        for p in 0..4 {
            for q in p + 1..4 {
                if a[p][q].abs() < 1e-300 {
                    continue;
                }
                let theta = (a[q][q] - a[p][p]) / (2.0 * a[p][q]);
                let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
                let t = if theta == 0.0 { 1.0 } else { t };
                let c = 1.0 / (t * t + 1.0).sqrt();
                let s = t * c;
                for row in a.iter_mut() {
                    let (akp, akq) = (row[p], row[q]);
                    row[p] = c * akp - s * akq;
                    row[q] = s * akp + c * akq;
                }
                let (row_p, row_q) = (a[p], a[q]);
                for k in 0..4 {
                    a[p][k] = c * row_p[k] - s * row_q[k];
                    a[q][k] = s * row_p[k] + c * row_q[k];
                }
                for row in v.iter_mut() {
                    let (vkp, vkq) = (row[p], row[q]);
                    row[p] = c * vkp - s * vkq;
                    row[q] = s * vkp + c * vkq;
                }
            }
        }
    }
    ([a[0][0], a[1][1], a[2][2], a[3][3]], v)
}

/// The rigid transform minimising sum w_i |dst_i - (R src_i + t)|^2 (weights
/// optional). Needs at least 3 non-collinear points for a unique rotation;
/// degenerate input still returns a valid rigid transform.
pub fn kabsch(src: &[DVec3], dst: &[DVec3]) -> Rigid {
    assert_eq!(src.len(), dst.len(), "point sets must correspond");
    if src.is_empty() {
        return Rigid::IDENTITY;
    }
    let n = src.len() as f64;
    let cs = src.iter().copied().sum::<DVec3>() / n;
    let cd = dst.iter().copied().sum::<DVec3>() / n;
    // Cross-covariance S[i][j] = sum a_i b_j over centred points.
    let mut s = [[0.0f64; 3]; 3];
    for (a, b) in src.iter().zip(dst) {
        let (a, b) = (*a - cs, *b - cd);
        for i in 0..3 {
            for j in 0..3 {
                s[i][j] += a[i] * b[j];
            }
        }
    }
    let [[sxx, sxy, sxz], [syx, syy, syz], [szx, szy, szz]] = s;
    let m = [
        [sxx + syy + szz, syz - szy, szx - sxz, sxy - syx],
        [syz - szy, sxx - syy - szz, sxy + syx, szx + sxz],
        [szx - sxz, sxy + syx, -sxx + syy - szz, syz + szy],
        [sxy - syx, szx + sxz, syz + szy, -sxx - syy + szz],
    ];
    let (vals, vecs) = jacobi_eigen4(m);
    let best = (0..4).max_by(|&a, &b| vals[a].total_cmp(&vals[b])).unwrap_or(0);
    let q = DQuat::from_xyzw(vecs[1][best], vecs[2][best], vecs[3][best], vecs[0][best]).normalize();
    let r = DMat3::from_quat(q);
    Rigid { r, t: cd - r * cs }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn kabsch_recovers_an_exact_transform() {
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        for _ in 0..20 {
            let axis =
                DVec3::new(rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0))
                    .normalize();
            let truth = Rigid {
                r: DMat3::from_axis_angle(axis, rng.random_range(-3.0..3.0)),
                t: DVec3::new(rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0)),
            };
            let src: Vec<DVec3> = (0..30)
                .map(|_| {
                    DVec3::new(rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0))
                })
                .collect();
            let dst: Vec<DVec3> = src.iter().map(|p| truth.apply(*p)).collect();
            let fit = kabsch(&src, &dst);
            assert!((fit.r - truth.r).abs().to_cols_array().iter().all(|e| *e < 1e-9), "{fit:?} vs {truth:?}");
            assert!((fit.t - truth.t).length() < 1e-9);
            assert!((fit.r.determinant() - 1.0).abs() < 1e-12);
        }
    }

    #[test]
    fn three_points_fix_the_transform_and_identity_is_identity() {
        let src = [DVec3::ZERO, DVec3::X, DVec3::Y];
        let fit = kabsch(&src, &src);
        assert!(fit.angle() < 1e-12 && fit.t.length() < 1e-12);
        let r = DMat3::from_rotation_z(0.5);
        let dst: Vec<DVec3> = src.iter().map(|p| r * *p + DVec3::Z).collect();
        let fit = kabsch(&src, &dst);
        assert!((fit.angle() - 0.5).abs() < 1e-12);
    }
}
