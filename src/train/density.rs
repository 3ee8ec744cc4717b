//! Adaptive density control as in 3DGS: accumulate each Gaussian's screen-space
//! mean-gradient norm over the views it was seen in, then clone small and split
//! large Gaussians whose mean exceeds the threshold, prune transparent and
//! oversized ones, and reset opacities periodically. The optimizer's rows are
//! kept aligned with the Gaussians through every edit.

use glam::{Quat, Vec3};
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use serde::{Deserialize, Serialize};

use crate::render::Gradients;
use crate::splat::{logit, retain_rows, sigmoid, GaussianSet, ParamGroup};
use crate::train::optim::Adam;

/// Per-Gaussian statistics gathered between densification steps.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct DensityStats {
    /// Sum of NDC mean-gradient norms over the views the Gaussian was visible in.
    pub grad_accum: Vec<f32>,
    /// Number of those views.
    pub denom: Vec<f32>,
    /// Largest screen radius (pixels) seen.
    pub max_radius: Vec<f32>,
}

impl DensityStats {
    pub fn new(n: usize) -> Self {
        Self { grad_accum: vec![0.0; n], denom: vec![0.0; n], max_radius: vec![0.0; n] }
    }

    pub fn len(&self) -> usize {
        self.denom.len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Add one view's statistics: `grads` are this set's (a render of several
    /// sets gives each its own, `render::backward_sets`).
    pub fn record(&mut self, grads: &Gradients) {
        for i in 0..self.len() {
            if !grads.visible[i] {
                continue;
            }
            self.grad_accum[i] += grads.mean2d_grad_norm[i];
            self.denom[i] += 1.0;
            self.max_radius[i] = self.max_radius[i].max(grads.radius[i]);
        }
    }

    /// Append zeroed statistics for `n` new Gaussians.
    pub fn append(&mut self, n: usize) {
        let len = self.len() + n;
        self.grad_accum.resize(len, 0.0);
        self.denom.resize(len, 0.0);
        self.max_radius.resize(len, 0.0);
    }

    fn retain(&mut self, keep: &[bool]) {
        retain_rows(&mut self.grad_accum, 1, keep);
        retain_rows(&mut self.denom, 1, keep);
        retain_rows(&mut self.max_radius, 1, keep);
    }

    fn reset(&mut self, n: usize) {
        *self = Self::new(n);
    }
}

/// What one densification step did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct DensifyReport {
    pub cloned: usize,
    pub split: usize,
    pub pruned: usize,
    pub total: usize,
}

/// Limits for one densify-and-prune step.
#[derive(Clone, Copy, Debug)]
pub struct DensifyParams {
    pub grad_threshold: f32,
    /// Absolute size (max scale, world units) separating clone from split.
    pub dense_size: f32,
    pub min_opacity: f32,
    /// Prune when the screen radius exceeds this (pixels), if set.
    pub max_screen_size: Option<f32>,
    /// Prune when the max scale exceeds this (world units), if set.
    pub max_world_size: Option<f32>,
    /// Do not add Gaussians beyond this count (0 = no cap).
    pub max_gaussians: usize,
}

/// Clone, split and prune (3DGS `densify_and_prune`), keeping `adam` and `stats` aligned.
pub fn densify_and_prune(
    gs: &mut GaussianSet,
    adam: &mut Adam,
    stats: &mut DensityStats,
    params: &DensifyParams,
    rng: &mut ChaCha8Rng,
) -> DensifyReport {
    let n = gs.len();
    assert_eq!(stats.len(), n, "density statistics are out of step with the Gaussians");
    let max_scale: Vec<f32> = (0..n).map(|i| gs.log_scale(i).exp().max_element()).collect();
    let mean_grad: Vec<f32> =
        (0..n).map(|i| if stats.denom[i] > 0.0 { stats.grad_accum[i] / stats.denom[i] } else { 0.0 }).collect();
    let mut candidates: Vec<usize> = (0..n).filter(|&i| mean_grad[i] >= params.grad_threshold).collect();
    if params.max_gaussians > 0 {
        // Under a cap, densify the largest gradients first (each split adds one net row).
        let room = params.max_gaussians.saturating_sub(n);
        candidates.sort_by(|&a, &b| mean_grad[b].total_cmp(&mean_grad[a]).then(a.cmp(&b)));
        candidates.truncate(room);
        candidates.sort_unstable();
    }
    let (clone, split): (Vec<usize>, Vec<usize>) =
        candidates.into_iter().partition(|&i| max_scale[i] <= params.dense_size);

    let mut added = GaussianSet::new(gs.sh_degree);
    for &i in &clone {
        copy_row(gs, i, &mut added);
    }
    for &i in &split {
        let scale = gs.log_scale(i).exp();
        let rot = gs.rotation(i);
        let new_log_scale = (scale / (0.8 * 2.0)).map(f32::ln);
        for _ in 0..2 {
            let offset = Vec3::new(
                rng.sample::<f32, _>(StandardNormal),
                rng.sample::<f32, _>(StandardNormal),
                rng.sample::<f32, _>(StandardNormal),
            ) * scale;
            let row = added.len();
            copy_row(gs, i, &mut added);
            let mean = gs.mean(i) + Quat::mul_vec3(rot, offset);
            added.means[3 * row..3 * row + 3].copy_from_slice(&mean.to_array());
            added.log_scales[3 * row..3 * row + 3].copy_from_slice(&new_log_scale.to_array());
        }
    }
    let appended = added.len();
    for g in ParamGroup::ALL {
        let extra = std::mem::take(added.group_mut(g));
        gs.group_mut(g).extend(extra);
    }
    adam.append_rows(appended);
    stats.append(appended);

    // Remove split originals, then prune the whole set (new rows included, as 3DGS does).
    let mut keep = vec![true; gs.len()];
    for &i in &split {
        keep[i] = false;
    }
    let mut pruned = 0;
    for (i, k) in keep.iter_mut().enumerate() {
        if !*k {
            continue;
        }
        let too_transparent = sigmoid(gs.opacity_logits[i]) < params.min_opacity;
        let too_big_screen = params.max_screen_size.is_some_and(|m| stats.max_radius[i] > m);
        let too_big_world = params.max_world_size.is_some_and(|m| gs.log_scale(i).exp().max_element() > m);
        if too_transparent || too_big_screen || too_big_world {
            *k = false;
            pruned += 1;
        }
    }
    gs.retain(&keep);
    adam.retain(&keep);
    stats.retain(&keep);
    stats.reset(gs.len());
    DensifyReport { cloned: clone.len(), split: split.len(), pruned, total: gs.len() }
}

/// Append row `i` of `src` to `dst`.
fn copy_row(src: &GaussianSet, i: usize, dst: &mut GaussianSet) {
    for g in ParamGroup::ALL {
        let w = src.width(g);
        let row = src.group(g)[i * w..(i + 1) * w].to_vec();
        dst.group_mut(g).extend(row);
    }
}

/// Opacity cap applied by the periodic reset, in both stages (3DGS value).
pub const OPACITY_RESET_VALUE: f32 = 0.01;

/// 3DGS opacity reset: clamp every opacity to at most `value` and restart the
/// opacity moments, so Gaussians that are not needed fade and get pruned.
pub fn reset_opacity(gs: &mut GaussianSet, adam: &mut Adam, value: f32) {
    let cap = logit(value);
    for o in &mut gs.opacity_logits {
        *o = o.min(cap);
    }
    adam.zero_moments(ParamGroup::OpacityLogits, &vec![true; gs.len()]);
}

/// Remove Gaussians where `drop` is true, keeping optimizer and statistics aligned.
pub fn remove(gs: &mut GaussianSet, adam: &mut Adam, stats: &mut DensityStats, drop: &[bool]) {
    let keep: Vec<bool> = drop.iter().map(|d| !d).collect();
    gs.retain(&keep);
    adam.retain(&keep);
    stats.retain(&keep);
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    /// A set whose rows are identifiable: row i has mean x = i and opacity logit i/10.
    fn labelled(n: usize) -> GaussianSet {
        let mut gs = GaussianSet::new(1);
        let rest = vec![0.0; gs.width(ParamGroup::ShRest)];
        for i in 0..n {
            let ls = if i % 2 == 0 { -6.0 } else { -1.0 }; // even rows small (clone), odd large (split)
            gs.push(
                Vec3::new(i as f32, 0.0, 0.0),
                Vec3::splat(ls),
                [1.0, 0.0, 0.0, 0.0],
                i as f32 / 10.0,
                [0.0; 3],
                &rest,
            );
        }
        gs
    }

    /// Adam moments tagged with the row they belong to (m = row id in every group).
    fn tagged_adam(gs: &GaussianSet) -> Adam {
        let mut adam = Adam::new(gs);
        let mut fake = gs.clone();
        for g in ParamGroup::ALL {
            let w = gs.width(g);
            let grads: Vec<f32> = (0..gs.len()).flat_map(|i| std::iter::repeat_n(i as f32 + 1.0, w)).collect();
            *fake.group_mut(g) = grads;
        }
        let mut p = gs.clone();
        let lrs = crate::train::optim::LearningRates {
            means: 1e-9,
            log_scales: 1e-9,
            rotations: 1e-9,
            opacity_logits: 1e-9,
            sh_dc: 1e-9,
            sh_rest: 1e-9,
        };
        adam.step(&mut p, &fake, &lrs);
        adam
    }

    #[test]
    fn optimizer_moments_follow_their_gaussians_through_clone_split_and_prune() {
        let mut gs = labelled(6);
        // Row 4 is transparent and gets pruned; rows 0,1,2,3 are densified.
        gs.opacity_logits[4] = logit(0.001);
        let mut adam = tagged_adam(&gs);
        let first_moment = |adam: &Adam, row: usize| adam.state(ParamGroup::Means).m[3 * row];
        let ids_before: Vec<f32> = (0..gs.len()).map(|i| first_moment(&adam, i)).collect();
        let mut stats = DensityStats::new(gs.len());
        for i in 0..4 {
            stats.grad_accum[i] = 1.0;
            stats.denom[i] = 1.0;
        }
        let params = DensifyParams {
            grad_threshold: 0.5,
            dense_size: 0.01,
            min_opacity: 0.005,
            max_screen_size: None,
            max_world_size: None,
            max_gaussians: 0,
        };
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let report = densify_and_prune(&mut gs, &mut adam, &mut stats, &params, &mut rng);
        // Clones of rows 0 and 2, splits of 1 and 3 (2 children each, originals removed), row 4 pruned.
        assert_eq!(report, DensifyReport { cloned: 2, split: 2, pruned: 1, total: 6 - 2 - 1 + 2 + 4 });
        assert_eq!(adam.len(), gs.len());
        assert_eq!(stats.len(), gs.len());
        // Survivors in order: 0, 2, 5 (originals kept), then clones 0, 2 with zero moments,
        // then the children of 1 and 3 (zero moments, mean near their parent).
        let xs: Vec<f32> = (0..gs.len()).map(|i| gs.mean(i).x).collect();
        assert_eq!(&xs[..5], &[0.0, 2.0, 5.0, 0.0, 2.0]);
        assert!((xs[5] - 1.0).abs() < 2.0 && (xs[7] - 3.0).abs() < 2.0, "{xs:?}");
        let m: Vec<f32> = (0..gs.len()).map(|i| first_moment(&adam, i)).collect();
        assert_eq!(m[0], ids_before[0]);
        assert_eq!(m[1], ids_before[2]);
        assert_eq!(m[2], ids_before[5]);
        assert!(m[3..].iter().all(|v| *v == 0.0), "new rows start with zero moments: {m:?}");
        // Opacity logits identify rows too.
        assert_eq!(gs.opacity_logits[2], 0.5);
        assert_eq!(gs.opacity_logits[5], 0.1);
        // Split children are smaller by 1.6.
        assert!((gs.log_scale(5).x - (-1.0 - 1.6f32.ln())).abs() < 1e-6);
    }

    #[test]
    fn opacity_reset_caps_opacity_and_clears_its_moments() {
        let mut gs = labelled(4);
        let mut adam = tagged_adam(&gs);
        reset_opacity(&mut gs, &mut adam, 0.01);
        assert!(gs.opacity_logits.iter().all(|o| sigmoid(*o) <= 0.01 + 1e-6));
        assert!(adam.state(ParamGroup::OpacityLogits).m.iter().all(|v| *v == 0.0));
        assert!(adam.state(ParamGroup::Means).m.iter().any(|v| *v != 0.0));
    }

    #[test]
    fn cap_limits_growth_to_the_largest_gradients() {
        let mut gs = labelled(6);
        let mut adam = Adam::new(&gs);
        let mut stats = DensityStats::new(6);
        for i in 0..6 {
            stats.grad_accum[i] = i as f32;
            stats.denom[i] = 1.0;
        }
        let params = DensifyParams {
            grad_threshold: 0.5,
            dense_size: 0.01,
            min_opacity: 0.0,
            max_screen_size: None,
            max_world_size: None,
            max_gaussians: 7,
        };
        let report = densify_and_prune(&mut gs, &mut adam, &mut stats, &params, &mut ChaCha8Rng::seed_from_u64(0));
        // Room for one: the largest gradient (row 5, large: split) is densified.
        assert_eq!((report.cloned, report.split), (0, 1));
    }
}
