//! Adam over the parameter groups of a [`GaussianSet`], as 3DGS runs it: one
//! learning rate per group, β1 = 0.9, β2 = 0.999, ε = 1e-15, PyTorch's update
//! rule, and moments stored per row so density control can remove, append and
//! reset rows (3DGS keeps the step count when it edits the optimizer state, and
//! so do we).

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::splat::{retain_rows, GaussianSet, ParamGroup};

pub const BETA1: f32 = 0.9;
pub const BETA2: f32 = 0.999;
pub const EPS: f32 = 1e-15;

/// Adam state of one flat parameter buffer; also usable on its own (e.g. network weights).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct AdamBuffer {
    /// First moment, one per parameter.
    pub m: Vec<f32>,
    /// Second moment, one per parameter.
    pub v: Vec<f32>,
    /// Steps taken (for bias correction).
    pub steps: u32,
}

impl AdamBuffer {
    pub fn zeros(len: usize) -> Self {
        Self { m: vec![0.0; len], v: vec![0.0; len], steps: 0 }
    }

    /// One Adam step on `params` with gradient `grads` (PyTorch `torch.optim.Adam` rule).
    pub fn step(&mut self, params: &mut [f32], grads: &[f32], lr: f32) {
        assert!(
            params.len() == grads.len() && params.len() == self.m.len(),
            "Adam: {} params, {} grads, {} moments",
            params.len(),
            grads.len(),
            self.m.len()
        );
        self.steps += 1;
        let t = self.steps as i32;
        let step_size = lr / (1.0 - BETA1.powi(t));
        let inv_sqrt_bc2 = 1.0 / (1.0 - BETA2.powi(t)).sqrt();
        (params, grads, &mut self.m, &mut self.v).into_par_iter().with_min_len(8192).for_each(|(p, &g, m, v)| {
            *m = BETA1 * *m + (1.0 - BETA1) * g;
            *v = BETA2 * *v + (1.0 - BETA2) * g * g;
            *p -= step_size * *m / (v.sqrt() * inv_sqrt_bc2 + EPS);
        });
    }
}

/// A learning rate for each parameter group. A rate of 0 freezes the group: its
/// moments and step count stay untouched (like a tensor without gradient in PyTorch).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct LearningRates {
    pub means: f32,
    pub log_scales: f32,
    pub rotations: f32,
    pub opacity_logits: f32,
    pub sh_dc: f32,
    pub sh_rest: f32,
}

impl LearningRates {
    pub fn get(&self, group: ParamGroup) -> f32 {
        match group {
            ParamGroup::Means => self.means,
            ParamGroup::LogScales => self.log_scales,
            ParamGroup::Rotations => self.rotations,
            ParamGroup::OpacityLogits => self.opacity_logits,
            ParamGroup::ShDc => self.sh_dc,
            ParamGroup::ShRest => self.sh_rest,
        }
    }

    pub fn set(&mut self, group: ParamGroup, lr: f32) {
        match group {
            ParamGroup::Means => self.means = lr,
            ParamGroup::LogScales => self.log_scales = lr,
            ParamGroup::Rotations => self.rotations = lr,
            ParamGroup::OpacityLogits => self.opacity_logits = lr,
            ParamGroup::ShDc => self.sh_dc = lr,
            ParamGroup::ShRest => self.sh_rest = lr,
        }
    }
}

/// 3DGS `get_expon_lr_func`: log-linear interpolation from `lr_init` at step 0 to
/// `lr_final` at `max_steps` (constant after), times a delay factor rising from
/// `delay_mult` to 1 along a quarter sine over the first `delay_steps`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ExponLr {
    pub lr_init: f32,
    pub lr_final: f32,
    pub delay_steps: u64,
    pub delay_mult: f32,
    pub max_steps: u64,
}

impl ExponLr {
    pub fn at(&self, step: u64) -> f32 {
        if self.lr_init == 0.0 && self.lr_final == 0.0 {
            return 0.0;
        }
        let delay = if self.delay_steps > 0 {
            let s = (step as f64 / self.delay_steps as f64).min(1.0);
            self.delay_mult as f64 + (1.0 - self.delay_mult as f64) * (0.5 * std::f64::consts::PI * s).sin()
        } else {
            1.0
        };
        let t = if self.max_steps == 0 { 1.0 } else { (step as f64 / self.max_steps as f64).min(1.0) };
        let (a, b) = (self.lr_init as f64, self.lr_final as f64);
        // Log-linear needs positive endpoints; otherwise fall back to linear.
        let lr = if a > 0.0 && b > 0.0 { (a.ln() * (1.0 - t) + b.ln() * t).exp() } else { a * (1.0 - t) + b * t };
        (delay * lr) as f32
    }
}

/// Adam state for every group of a Gaussian set, row-aligned with the set.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Adam {
    groups: [AdamBuffer; 6],
    widths: [usize; 6],
}

impl Adam {
    /// Zero moments for every row of `set`.
    pub fn new(set: &GaussianSet) -> Self {
        let widths = ParamGroup::ALL.map(|g| set.width(g));
        Self { groups: widths.map(|w| AdamBuffer::zeros(w * set.len())), widths }
    }

    /// Position of `group` in `ParamGroup::ALL`, the order of `groups` and `widths`.
    fn index(group: ParamGroup) -> usize {
        ParamGroup::ALL.iter().position(|&g| g == group).expect("ParamGroup::ALL lists every group")
    }

    /// Number of rows (Gaussians) the state covers.
    pub fn len(&self) -> usize {
        self.groups[Self::index(ParamGroup::OpacityLogits)].m.len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The state of one group (moments as rows of `set.width(group)` floats).
    pub fn state(&self, group: ParamGroup) -> &AdamBuffer {
        &self.groups[Self::index(group)]
    }

    /// Update every group with a non-zero learning rate. `grads` has the layout of
    /// `params` and holds dL/d(parameter). Values are updated raw (quaternions are
    /// normalised at use, not here).
    pub fn step(&mut self, params: &mut GaussianSet, grads: &GaussianSet, lrs: &LearningRates) {
        assert_eq!(params.len(), self.len(), "Adam state has {} rows, the set {}", self.len(), params.len());
        for g in ParamGroup::ALL {
            let lr = lrs.get(g);
            if lr != 0.0 {
                self.groups[Self::index(g)].step(params.group_mut(g), grads.group(g), lr);
            }
        }
    }

    /// Keep the state of the rows where `keep` is true (mirror of `GaussianSet::retain`).
    pub fn retain(&mut self, keep: &[bool]) {
        assert_eq!(keep.len(), self.len(), "retain mask length");
        for (buf, &w) in self.groups.iter_mut().zip(&self.widths) {
            retain_rows(&mut buf.m, w, keep);
            retain_rows(&mut buf.v, w, keep);
        }
    }

    /// Add zero moments for `rows` new rows at the end (after appending to the set).
    pub fn append_rows(&mut self, rows: usize) {
        for (buf, &w) in self.groups.iter_mut().zip(&self.widths) {
            let len = buf.m.len() + rows * w;
            buf.m.resize(len, 0.0);
            buf.v.resize(len, 0.0);
        }
    }

    /// Zero both moments of the rows of `group` where `rows` is true (opacity reset).
    pub fn zero_moments(&mut self, group: ParamGroup, rows: &[bool]) {
        assert_eq!(rows.len(), self.len(), "row mask length");
        let w = self.widths[Self::index(group)];
        let buf = &mut self.groups[Self::index(group)];
        for (i, _) in rows.iter().enumerate().filter(|(_, &z)| z) {
            buf.m[i * w..(i + 1) * w].fill(0.0);
            buf.v[i * w..(i + 1) * w].fill(0.0);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    fn lrs(lr: f32) -> LearningRates {
        LearningRates { means: lr, log_scales: lr, rotations: lr, opacity_logits: lr, sh_dc: lr, sh_rest: lr }
    }

    /// A set of `n` Gaussians whose every value in row i is `base + i`.
    fn rows(n: usize, degree: u32, base: f32) -> GaussianSet {
        let mut set = GaussianSet::new(degree);
        let rest_w = set.width(ParamGroup::ShRest);
        for i in 0..n {
            let v = base + i as f32;
            set.push(Vec3::splat(v), Vec3::splat(v), [v; 4], v, [v; 3], &vec![v; rest_w]);
        }
        set
    }

    #[test]
    fn two_steps_match_hand_computation() {
        let mut params = rows(1, 0, 1.0);
        let mut adam = Adam::new(&params);
        let only_opacity = LearningRates { opacity_logits: 0.1, ..lrs(0.0) };
        // Step 1: m = 0.05, v = 2.5e-4, m̂ = 0.5, v̂ = 0.25 -> p = 1 - 0.1 * 0.5 / 0.5 = 0.9.
        let mut grads = rows(1, 0, 0.5);
        adam.step(&mut params, &grads, &only_opacity);
        assert!((params.opacity_logits[0] - 0.9).abs() < 1e-6);
        // Step 2: m = 0.02, v = 3.1225e-4, m̂ = 0.02/0.19, v̂ = 3.1225e-4/0.001999
        // -> p = 0.9 - 0.1 * m̂ / sqrt(v̂) = 0.873366296 (float64 reference).
        grads.opacity_logits[0] = -0.25;
        adam.step(&mut params, &grads, &only_opacity);
        assert!((params.opacity_logits[0] - 0.873_366_3).abs() < 1e-6, "{}", params.opacity_logits[0]);
        // Frozen groups (lr 0) are untouched, moments included.
        assert_eq!(params.means, vec![1.0; 3]);
        assert_eq!(adam.state(ParamGroup::Means), &AdamBuffer::zeros(3));
        assert_eq!(adam.state(ParamGroup::OpacityLogits).steps, 2);
    }

    #[test]
    fn moments_follow_rows_through_retain_append_and_reset() {
        let mut params = rows(5, 1, 0.0);
        let mut adam = Adam::new(&params);
        // Gradient of row i is i + 1 everywhere, so after one step m = 0.1 (i + 1).
        adam.step(&mut params, &rows(5, 1, 1.0), &lrs(0.01));
        let keep = [true, false, true, false, true];
        params.retain(&keep);
        adam.retain(&keep);
        assert_eq!(adam.len(), 3);
        for g in ParamGroup::ALL {
            let w = params.width(g);
            let m = &adam.state(g).m;
            for (row, orig) in [0usize, 2, 4].into_iter().enumerate() {
                assert!(
                    m[row * w..(row + 1) * w].iter().all(|&x| (x - 0.1 * (orig as f32 + 1.0)).abs() < 1e-6),
                    "{g:?}"
                );
            }
        }
        // Appended rows start with zero moments.
        let extra = rows(2, 1, 10.0);
        for i in 0..2 {
            let rest = extra.sh_rest[9 * i..9 * (i + 1)].to_vec();
            params.push(extra.mean(i), extra.log_scale(i), [0.0; 4], 0.0, [0.0; 3], &rest);
        }
        adam.append_rows(2);
        assert_eq!(adam.len(), 5);
        for g in ParamGroup::ALL {
            let w = params.width(g);
            assert!(adam.state(g).m[3 * w..].iter().all(|&x| x == 0.0));
            assert!(adam.state(g).v[3 * w..].iter().all(|&x| x == 0.0));
        }
        // Resetting the opacity moments of row 1 leaves other rows and groups alone.
        adam.zero_moments(ParamGroup::OpacityLogits, &[false, true, false, false, false]);
        let op = &adam.state(ParamGroup::OpacityLogits).m;
        assert!((op[0] - 0.1).abs() < 1e-6 && op[1] == 0.0 && (op[2] - 0.5).abs() < 1e-6);
        assert!((adam.state(ParamGroup::Means).m[3] - 0.3).abs() < 1e-6);
        // A further step works on the edited state.
        adam.step(&mut params, &rows(5, 1, 1.0), &lrs(0.01));
        assert_eq!(adam.state(ParamGroup::Means).steps, 2);
    }

    #[test]
    fn exponential_schedule_endpoints_midpoint_and_delay() {
        let s = ExponLr { lr_init: 1.6e-4, lr_final: 1.6e-6, delay_steps: 0, delay_mult: 0.01, max_steps: 30_000 };
        let close = |a: f32, b: f32| (a - b).abs() <= 1e-6 * b.abs();
        assert!(close(s.at(0), 1.6e-4));
        assert!(close(s.at(15_000), 1.6e-5), "log-linear midpoint is the geometric mean");
        assert!(close(s.at(30_000), 1.6e-6));
        assert!(close(s.at(90_000), 1.6e-6));
        let d = ExponLr { delay_steps: 100, ..s };
        assert!(close(d.at(0), 0.01 * 1.6e-4));
        assert!(close(d.at(100), s.at(100)));
        let zero = ExponLr { lr_init: 0.0, lr_final: 0.0, ..s };
        assert_eq!(zero.at(10), 0.0);
    }
}
