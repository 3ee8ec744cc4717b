//! Initial Gaussians: random points in the object's box or a given point cloud,
//! scales from the mean distance to the 3 nearest neighbours (as 3DGS does).

use std::num::NonZero;

use glam::Vec3;
use kiddo::ImmutableKdTree;
use kiddo::SquaredEuclidean;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;

use crate::splat::{logit, rgb_to_sh_dc, GaussianSet, ParamGroup};

/// Uniform random points in the box [min, max].
pub fn random_points(n: usize, min: Vec3, max: Vec3, seed: u64) -> Vec<Vec3> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    (0..n)
        .map(|_| {
            Vec3::new(rng.random_range(min.x..max.x), rng.random_range(min.y..max.y), rng.random_range(min.z..max.z))
        })
        .collect()
}

/// Mean distance from each point to its 3 nearest other points (floored so
/// duplicates do not make degenerate Gaussians).
pub fn knn_mean_distance(points: &[Vec3]) -> Vec<f32> {
    if points.len() < 2 {
        return vec![0.01; points.len()];
    }
    let coords: Vec<[f32; 3]> = points.iter().map(|p| p.to_array()).collect();
    let tree: ImmutableKdTree<f32, 3> = ImmutableKdTree::new_from_slice(&coords);
    let k = 4.min(points.len());
    coords
        .par_iter()
        .map(|q| {
            let nn = tree.nearest_n::<SquaredEuclidean>(q, NonZero::new(k).expect("k >= 2"));
            // The first neighbour is the point itself (distance 0).
            let d: f32 = nn.iter().skip(1).map(|n| n.distance.sqrt()).sum::<f32>() / (k - 1) as f32;
            d.max(1e-7)
        })
        .collect()
}

/// Gaussians at `points` with isotropic scales from 3-NN distances, identity
/// rotations, the given opacity and colours (grey when none are given).
pub fn gaussians_from_points(points: &[Vec3], colors: Option<&[Vec3]>, opacity: f32, sh_degree: u32) -> GaussianSet {
    let dist = knn_mean_distance(points);
    let mut gs = GaussianSet::new(sh_degree);
    let rest = vec![0.0; gs.width(ParamGroup::ShRest)];
    for (i, (p, d)) in points.iter().zip(&dist).enumerate() {
        let c = colors.map_or(Vec3::splat(0.5), |c| c[i]);
        gs.push(
            *p,
            Vec3::splat(d.ln()),
            [1.0, 0.0, 0.0, 0.0],
            logit(opacity),
            [rgb_to_sh_dc(c.x), rgb_to_sh_dc(c.y), rgb_to_sh_dc(c.z)],
            &rest,
        );
    }
    gs
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn knn_distance_of_a_grid_is_its_spacing() {
        let mut pts = Vec::new();
        for x in 0..10 {
            for y in 0..10 {
                for z in 0..10 {
                    pts.push(Vec3::new(x as f32, y as f32, z as f32) * 0.1);
                }
            }
        }
        let d = knn_mean_distance(&pts);
        // Interior points have 6 neighbours at exactly the spacing.
        let interior = 5 * 100 + 5 * 10 + 5;
        assert!((d[interior] - 0.1).abs() < 1e-5, "{}", d[interior]);
    }

    #[test]
    fn random_points_stay_in_the_box_and_are_seeded() {
        let a = random_points(1000, Vec3::splat(-0.5), Vec3::splat(0.5), 3);
        assert!(a.iter().all(|p| p.abs().max_element() <= 0.5));
        assert_eq!(a, random_points(1000, Vec3::splat(-0.5), Vec3::splat(0.5), 3));
        assert_ne!(a, random_points(1000, Vec3::splat(-0.5), Vec3::splat(0.5), 4));
    }
}
