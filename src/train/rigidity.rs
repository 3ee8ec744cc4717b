//! Local rigidity of the deformation field (stage II regulariser, in the spirit
//! of the official code's ARAP term): neighbouring moving Gaussians keep their
//! distances between two times. Distances are rotation-invariant, so rigid
//! parts pay nothing whatever they do, and no per-point rotation fit is needed.
//! The penalty is robust (Geman-McClure): pairs that straddle two parts do
//! separate, and once they have, they stop pulling.

use std::num::NonZero;

use glam::Vec3;
use kiddo::{ImmutableKdTree, SquaredEuclidean};
use serde::{Deserialize, Serialize};

use crate::deform::DeformNet;

/// Settings of the rigidity term.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RigidityConfig {
    /// Loss weight (0 = off).
    pub weight: f32,
    /// Evaluate every this many iterations (its gradient is scaled up to match).
    pub interval: u32,
    /// Moving Gaussians sampled per evaluation.
    pub samples: usize,
    /// Neighbours per sampled Gaussian, found at the first of the two times.
    pub neighbours: usize,
    /// Distance change (world units) at which the robust penalty is half its maximum.
    pub scale: f32,
    /// First iteration it applies at (e.g. once the time window has opened).
    #[serde(default)]
    pub from_iteration: u32,
}

impl Default for RigidityConfig {
    fn default() -> Self {
        Self { weight: 0.0, interval: 1, samples: 2000, neighbours: 8, scale: 0.01, from_iteration: 0 }
    }
}

/// The loss and its gradient with respect to the network's parameters, for the
/// Gaussians at canonical `means` (x, y, z rows) between times `t_a` and `t_b`:
/// mean over neighbour pairs (i, j) at `t_a` of rho(|x_i - x_j|(t_b) - |x_i - x_j|(t_a)),
/// rho(e) = e^2 / (e^2 + scale^2).
pub fn rigidity_loss(
    net: &DeformNet,
    means: &[f32],
    t_a: f32,
    t_b: f32,
    neighbours: usize,
    scale: f32,
) -> (f32, Vec<f32>) {
    let n = means.len() / 3;
    let mut grad_params = vec![0.0; net.parameter_count()];
    if n < 2 || neighbours == 0 {
        return (0.0, grad_params);
    }
    let out_a = net.forward(means, t_a);
    let out_b = net.forward(means, t_b);
    let at = |d: &[f32], i: usize| Vec3::from_slice(&means[3 * i..]) + Vec3::from_slice(&d[3 * i..]);
    let pa: Vec<Vec3> = (0..n).map(|i| at(&out_a.d_xyz, i)).collect();
    let pb: Vec<Vec3> = (0..n).map(|i| at(&out_b.d_xyz, i)).collect();
    let coords: Vec<[f32; 3]> = pa.iter().map(|p| p.to_array()).collect();
    let tree: ImmutableKdTree<f32, 3> = ImmutableKdTree::new_from_slice(&coords);
    let k = (neighbours + 1).min(n);
    let (mut ga, mut gb) = (vec![0.0f32; 3 * n], vec![0.0f32; 3 * n]);
    let (mut loss, mut pairs) = (0.0f64, 0usize);
    let s2 = scale * scale;
    for i in 0..n {
        for nb in tree.nearest_n::<SquaredEuclidean>(&coords[i], NonZero::new(k).expect("k >= 2")) {
            let j = nb.item as usize;
            if j == i {
                continue;
            }
            let (va, vb) = (pa[i] - pa[j], pb[i] - pb[j]);
            let (la, lb) = (va.length(), vb.length());
            if la < 1e-9 || lb < 1e-9 {
                continue;
            }
            let e = lb - la;
            let denom = e * e + s2;
            loss += f64::from(e * e / denom);
            pairs += 1;
            // d rho / d e = 2 e s^2 / (e^2 + s^2)^2.
            let de = 2.0 * e * s2 / (denom * denom);
            let (ua, ub) = (va / la * de, vb / lb * de);
            for c in 0..3 {
                gb[3 * i + c] += ub[c];
                gb[3 * j + c] -= ub[c];
                ga[3 * i + c] -= ua[c];
                ga[3 * j + c] += ua[c];
            }
        }
    }
    if pairs == 0 {
        return (0.0, grad_params);
    }
    let inv = 1.0 / pairs as f32;
    ga.iter_mut().chain(gb.iter_mut()).for_each(|g| *g *= inv);
    let zero_rot = vec![0.0; 4 * n];
    for (out, g) in [(&out_a, &ga), (&out_b, &gb)] {
        for (acc, v) in grad_params.iter_mut().zip(net.backward(&out.cache, g, &zero_rot)) {
            *acc += v;
        }
    }
    ((loss / pairs as f64) as f32, grad_params)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::deform::DeformConfig;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn setup() -> (DeformNet, Vec<f32>) {
        let mut net = DeformNet::new(
            DeformConfig { depth: 2, width: 16, xyz_frequencies: 2, time_frequencies: 2, zero_at_start: false },
            3,
        );
        // Larger heads than the near-identity initialisation, so distances change.
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        net.params.iter_mut().for_each(|p| *p += rng.random_range(-0.2..0.2));
        let means: Vec<f32> = (0..60 * 3).map(|_| rng.random_range(-0.2f32..0.2)).collect();
        (net, means)
    }

    #[test]
    fn gradient_matches_finite_differences() {
        let (net, means) = setup();
        let loss = |n: &DeformNet| rigidity_loss(n, &means, 0.1, 0.8, 6, 0.05).0;
        let (l0, g) = rigidity_loss(&net, &means, 0.1, 0.8, 6, 0.05);
        assert!(l0 > 1e-4, "the perturbed network must change distances, loss {l0}");
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let mut checked = 0;
        for _ in 0..16 {
            let p = rng.random_range(0..net.params.len());
            let eps = 3e-4;
            let (mut plus, mut minus) = (net.clone(), net.clone());
            plus.params[p] += eps;
            minus.params[p] -= eps;
            let (lp, lm) = (loss(&plus), loss(&minus));
            let (right, left) = ((lp - l0) / eps, (l0 - lm) / eps);
            // A ReLU switching inside +-eps makes the loss a kink there; the analytic
            // gradient is then one of the one-sided slopes. Skip those parameters.
            if (right - left).abs() > 0.05 * right.abs().max(left.abs()).max(1e-3) {
                continue;
            }
            let fd = (lp - lm) / (2.0 * eps);
            assert!((fd - g[p]).abs() < 1e-2 * fd.abs().max(0.01), "param {p}: fd {fd} analytic {}", g[p]);
            checked += 1;
        }
        assert!(checked >= 10, "only {checked} smooth parameters checked");
    }

    #[test]
    fn a_rigid_motion_costs_nothing() {
        // A network that outputs zero moves nothing: every distance is kept.
        let (mut net, means) = setup();
        net.params.iter_mut().for_each(|p| *p = 0.0);
        let (l, g) = rigidity_loss(&net, &means, 0.0, 1.0, 6, 0.05);
        assert_eq!(l, 0.0);
        assert!(g.iter().all(|v| *v == 0.0));
    }
}
