//! Stage III: motion-based part segmentation and articulation (paper Sec. 3.2).
//!
//! Input: the moving Gaussians' centres at a few times (t = 0 first, e.g.
//! {0, 0.5, 1}). Sequential RANSAC groups them into rigid parts: each
//! hypothesis is fitted by Kabsch on a random minimal sample of 3 points for
//! every window 0 -> t_k, a point is an inlier when its residual averaged over
//! the windows is below the threshold, the largest consensus set is refitted
//! on all its inliers, removed, and the search repeats. Each group's 0 -> 1
//! transform then gives the joint ([`joint`]).
//!
//! Greedy consensus can merge parts whose motions differ by less than the
//! threshold (two drawers pulled by similar amounts), split one part into two
//! groups when the first minimal sample was slightly off, and hands points
//! near a hinge to whichever hypothesis came first. As the official code
//! refines its parts, the groups are then refined: a group whose residual is
//! well above the noise level is searched again with the tight
//! `merge_tolerance` threshold and split if it holds several motions, groups
//! whose motions explain each other's points are merged, and every point is
//! reassigned to the motion that explains it best (a few EM-like rounds).

use glam::DVec3;
use rand::seq::index::sample;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

pub mod joint;
pub mod rigid;

pub use joint::{extract_joint, JointEstimate, JointKind};
pub use rigid::{kabsch, Rigid};

/// Sequential RANSAC settings (defaults from the paper; the official code uses 0.08).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RansacConfig {
    /// Mean residual (world units) below which a point supports a hypothesis.
    pub inlier_threshold: f64,
    /// Hypotheses sampled per part.
    pub samples: usize,
    /// Stop when the best support set has fewer points than this.
    pub min_inliers: usize,
    /// Stop after this many parts.
    pub max_parts: usize,
    /// Reassign-and-refit rounds after the sequential search (0 = paper only).
    pub refine_rounds: usize,
    /// Mean residual under which two motions count as the same; also the
    /// threshold of the second search inside heterogeneous groups.
    pub merge_tolerance: f64,
    pub seed: u64,
}

impl Default for RansacConfig {
    fn default() -> Self {
        Self {
            inlier_threshold: 0.05,
            samples: 500,
            min_inliers: 30,
            max_parts: 16,
            refine_rounds: 5,
            merge_tolerance: 0.01,
            seed: 0,
        }
    }
}

/// One rigidly moving group.
#[derive(Clone, Debug)]
pub struct RigidGroup {
    /// Indices into the input points.
    pub members: Vec<usize>,
    /// Transform from time 0 to each later time sample.
    pub motions: Vec<Rigid>,
    /// Mean residual of the members.
    pub residual: f64,
}

/// Points at several times: `positions[k][i]` is point i at time sample k; k = 0 is t = 0.
pub struct Trajectories<'a> {
    pub positions: &'a [Vec<DVec3>],
}

impl Trajectories<'_> {
    fn len(&self) -> usize {
        self.positions.first().map_or(0, |p| p.len())
    }

    fn fit(&self, idx: &[usize]) -> Vec<Rigid> {
        let src: Vec<DVec3> = idx.iter().map(|&i| self.positions[0][i]).collect();
        self.positions[1..]
            .iter()
            .map(|pk| {
                let dst: Vec<DVec3> = idx.iter().map(|&i| pk[i]).collect();
                kabsch(&src, &dst)
            })
            .collect()
    }

    /// Residual of point i under the window motions, averaged over windows (Eq. 6).
    fn residual(&self, motions: &[Rigid], i: usize) -> f64 {
        let p0 = self.positions[0][i];
        let sum: f64 = motions.iter().zip(&self.positions[1..]).map(|(m, pk)| (pk[i] - m.apply(p0)).length()).sum();
        sum / motions.len() as f64
    }
}

/// Sequential RANSAC over `traj` followed by the refinement; returns the rigid
/// groups and the indices of points no group explains.
pub fn segment_rigid_parts(traj: &Trajectories, cfg: &RansacConfig) -> (Vec<RigidGroup>, Vec<usize>) {
    let all: Vec<usize> = (0..traj.len()).collect();
    let (groups, _) = sequential_ransac(traj, &all, cfg.inlier_threshold, cfg);
    if cfg.refine_rounds == 0 {
        let taken: std::collections::HashSet<usize> = groups.iter().flat_map(|g| g.members.iter().copied()).collect();
        return (groups, all.into_iter().filter(|i| !taken.contains(i)).collect());
    }
    let groups = split_heterogeneous(traj, groups, cfg);
    let groups = merge_agreeing(traj, groups, cfg);
    let (groups, rest) = reassign(traj, groups, cfg);
    (merge_agreeing(traj, groups, cfg), rest)
}

fn group_from(traj: &Trajectories, members: Vec<usize>) -> RigidGroup {
    let motions = traj.fit(&members);
    let residual = members.iter().map(|&i| traj.residual(&motions, i)).sum::<f64>() / members.len() as f64;
    RigidGroup { members, motions, residual }
}

/// Search groups whose residual is well above the noise level again with the
/// tight threshold; a group holding several motions is replaced by them (its
/// remaining points join the sub-group that explains them best).
fn split_heterogeneous(traj: &Trajectories, groups: Vec<RigidGroup>, cfg: &RansacConfig) -> Vec<RigidGroup> {
    let mut out = Vec::new();
    for g in groups {
        if g.residual < 0.5 * cfg.merge_tolerance {
            out.push(g);
            continue;
        }
        let (mut subs, rest) = sequential_ransac(traj, &g.members, cfg.merge_tolerance, cfg);
        if subs.len() < 2 {
            out.push(g);
            continue;
        }
        for i in rest {
            let best = (0..subs.len())
                .min_by(|&a, &b| traj.residual(&subs[a].motions, i).total_cmp(&traj.residual(&subs[b].motions, i)))
                .expect("at least two sub-groups");
            subs[best].members.push(i);
        }
        out.extend(subs.into_iter().map(|s| group_from(traj, s.members)));
    }
    out
}

/// Merge groups whose motions explain each other's points within `merge_tolerance`.
fn merge_agreeing(traj: &Trajectories, mut groups: Vec<RigidGroup>, cfg: &RansacConfig) -> Vec<RigidGroup> {
    let agree = |x: &RigidGroup, y: &RigidGroup| {
        let mean: f64 = y.members.iter().map(|&i| traj.residual(&x.motions, i)).sum::<f64>() / y.members.len() as f64;
        mean < cfg.merge_tolerance
    };
    let mut a = 0;
    while a < groups.len() {
        let mut b = a + 1;
        while b < groups.len() {
            if agree(&groups[a], &groups[b]) && agree(&groups[b], &groups[a]) {
                let taken = groups.remove(b);
                let mut members = std::mem::take(&mut groups[a].members);
                members.extend(taken.members);
                groups[a] = group_from(traj, members);
                b = a + 1;
            } else {
                b += 1;
            }
        }
        a += 1;
    }
    groups
}

/// Reassign every point to the group whose motion explains it best (below the
/// inlier threshold) and refit, for up to `refine_rounds` rounds; groups that
/// fall under `min_inliers` are dropped.
fn reassign(traj: &Trajectories, mut groups: Vec<RigidGroup>, cfg: &RansacConfig) -> (Vec<RigidGroup>, Vec<usize>) {
    let mut unassigned = Vec::new();
    for _ in 0..cfg.refine_rounds {
        let mut members: Vec<Vec<usize>> = vec![Vec::new(); groups.len()];
        unassigned.clear();
        for i in 0..traj.len() {
            let best = groups
                .iter()
                .enumerate()
                .map(|(g, grp)| (g, traj.residual(&grp.motions, i)))
                .min_by(|a, b| a.1.total_cmp(&b.1));
            match best {
                Some((g, r)) if r < cfg.inlier_threshold => members[g].push(i),
                _ => unassigned.push(i),
            }
        }
        let unchanged = groups.len() == members.len() && groups.iter().zip(&members).all(|(g, m)| g.members == *m);
        groups =
            members.into_iter().filter(|m| m.len() >= cfg.min_inliers.max(3)).map(|m| group_from(traj, m)).collect();
        if unchanged {
            break;
        }
    }
    (groups, unassigned)
}

/// The paper's sequential RANSAC over the points `subset` with inlier
/// threshold `threshold`; returns the groups and the points left over.
pub fn sequential_ransac(
    traj: &Trajectories,
    subset: &[usize],
    threshold: f64,
    cfg: &RansacConfig,
) -> (Vec<RigidGroup>, Vec<usize>) {
    assert!(traj.positions.len() >= 2, "need t = 0 and at least one later time");
    let mut rng = ChaCha8Rng::seed_from_u64(cfg.seed);
    let mut remaining: Vec<usize> = subset.to_vec();
    let mut groups = Vec::new();
    while remaining.len() >= cfg.min_inliers.max(3) && groups.len() < cfg.max_parts {
        let mut best: Option<(Vec<usize>, Vec<Rigid>)> = None;
        for _ in 0..cfg.samples {
            let pick: Vec<usize> = sample(&mut rng, remaining.len(), 3).into_iter().map(|k| remaining[k]).collect();
            let motions = traj.fit(&pick);
            let inliers: Vec<usize> =
                remaining.iter().copied().filter(|&i| traj.residual(&motions, i) < threshold).collect();
            if best.as_ref().is_none_or(|(b, _)| inliers.len() > b.len()) {
                best = Some((inliers, motions));
            }
        }
        let Some((inliers, _)) = best else { break };
        if inliers.len() < cfg.min_inliers {
            break;
        }
        // Refit on the whole support set, then take its inliers once more.
        let motions = traj.fit(&inliers);
        let members: Vec<usize> =
            remaining.iter().copied().filter(|&i| traj.residual(&motions, i) < threshold).collect();
        let members = if members.len() >= inliers.len() { members } else { inliers };
        let taken: std::collections::HashSet<usize> = members.iter().copied().collect();
        remaining.retain(|i| !taken.contains(i));
        groups.push(group_from(traj, members));
    }
    (groups, remaining)
}

/// The ablation baseline of the paper's Table 4: K-means with a given part
/// count on the trajectories (each point's positions at all time samples,
/// concatenated), k-means++ seeding from `seed`, then one rigid fit per cluster.
/// Empty clusters are dropped.
pub fn kmeans_rigid_parts(traj: &Trajectories, parts: usize, seed: u64) -> Vec<RigidGroup> {
    let n = traj.len();
    if n == 0 || parts == 0 {
        return Vec::new();
    }
    let feature = |i: usize| -> Vec<f64> { traj.positions.iter().flat_map(|p| p[i].to_array()).collect() };
    let features: Vec<Vec<f64>> = (0..n).map(feature).collect();
    let dist2 = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum::<f64>();
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut centres = vec![features[rand::Rng::random_range(&mut rng, 0..n)].clone()];
    while centres.len() < parts.min(n) {
        let d: Vec<f64> =
            features.iter().map(|f| centres.iter().map(|c| dist2(f, c)).fold(f64::INFINITY, f64::min)).collect();
        let total: f64 = d.iter().sum();
        if total <= 0.0 {
            break;
        }
        let mut x = rand::Rng::random_range(&mut rng, 0.0..total);
        let pick = d.iter().position(|&di| {
            x -= di;
            x <= 0.0
        });
        centres.push(features[pick.unwrap_or(n - 1)].clone());
    }
    let mut label = vec![0usize; n];
    for _ in 0..100 {
        let mut changed = false;
        for (i, f) in features.iter().enumerate() {
            let best = (0..centres.len())
                .min_by(|&a, &b| dist2(f, &centres[a]).total_cmp(&dist2(f, &centres[b])))
                .unwrap_or(0);
            changed |= best != label[i];
            label[i] = best;
        }
        for (c, centre) in centres.iter_mut().enumerate() {
            let members: Vec<&Vec<f64>> =
                features.iter().zip(&label).filter(|(_, &l)| l == c).map(|(f, _)| f).collect();
            if !members.is_empty() {
                for (k, v) in centre.iter_mut().enumerate() {
                    *v = members.iter().map(|m| m[k]).sum::<f64>() / members.len() as f64;
                }
            }
        }
        if !changed {
            break;
        }
    }
    (0..centres.len())
        .map(|c| (0..n).filter(|&i| label[i] == c).collect::<Vec<_>>())
        .filter(|m| m.len() >= 3)
        .map(|m| group_from(traj, m))
        .collect()
}

#[cfg(test)]
mod tests;
