//! Stage II: the dual-Gaussian representation (paper Sec. 3.1). The static set
//! (stage I's result) and a moving set with the deformation field are rendered
//! together on the motion video; the static set first trains its opacities only
//! and is pruned as moving content fades from it, the moving set learns the
//! motion, and static-during-motion detection (SDMD) hands rigid groups that do
//! not move back to the static set. [`DualTrainer::analyse`] then runs stage III
//! on the moving set.

use glam::{DVec3, Vec3};
use serde::{Deserialize, Serialize};

use crate::deform::{DeformConfig, DeformNet};
use crate::error::{Error, Result};
use crate::motion::{extract_joint, segment_rigid_parts, JointEstimate, RansacConfig, Rigid, Trajectories};
use crate::render::{backward, render, RenderOptions};
use crate::splat::{sigmoid, GaussianSet};
use crate::train::config::{DensityConfig, LrConfig};
use crate::train::density::{densify_and_prune, remove, reset_opacity, DensityStats};
use crate::train::init::{gaussians_from_points, random_points};
use crate::train::loss::{loss_and_grad, psnr};
use crate::train::optim::{Adam, AdamBuffer, ExponLr, LearningRates};
use crate::train::static_stage::{pick_view, rng_for};
use crate::train::views::{camera_extent, TrainView};

/// Stage II settings. Defaults from the paper; the official code's values where
/// they differ are noted.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DynamicConfig {
    pub preset: String,
    pub iterations: u32,
    /// Train at this image width (0 = as recorded).
    pub resolution: u32,
    pub seed: u64,
    /// No deformation before this iteration (Deformable-3DGS warm-up).
    pub warmup_iterations: u32,
    /// The static set trains only its opacities until here (paper 10k, official 8k).
    pub static_opacity_only_iterations: u32,
    /// Static Gaussians whose opacity falls below this are pruned (online pruning).
    pub static_prune_opacity: f32,
    /// Random initial moving Gaussians in the box (official 50k).
    pub moving_init_points: usize,
    pub init_box_min: [f32; 3],
    pub init_box_max: [f32; 3],
    pub deform: DeformConfig,
    pub deform_lr_init: f32,
    pub deform_lr_final: f32,
    /// SDMD every this many iterations after the opacity-only phase (paper 2000, official 500; 0 = off).
    pub sdmd_interval: u32,
    /// Groups rotating at most this (radians) ...
    pub sdmd_max_rotation: f64,
    /// ... and translating at most this (world units) between t = 0 and 1 are static.
    pub sdmd_max_translation: f64,
    pub ransac: RansacConfig,
    pub lambda_dssim: f32,
    pub random_background: bool,
    pub eval_background: [f32; 3],
    pub lr: LrConfig,
    /// Density control of the moving set (and of both sets after the opacity-only phase).
    pub density: DensityConfig,
}

impl DynamicConfig {
    pub fn paper() -> Self {
        let s = crate::train::config::StaticConfig::paper();
        Self {
            preset: "paper".into(),
            iterations: 40_000,
            resolution: 0,
            seed: 0,
            warmup_iterations: 3000,
            static_opacity_only_iterations: 10_000,
            static_prune_opacity: 0.005,
            moving_init_points: 50_000,
            init_box_min: [-0.5; 3],
            init_box_max: [0.5; 3],
            deform: DeformConfig::default(),
            deform_lr_init: 8e-4,
            deform_lr_final: 1.6e-6,
            sdmd_interval: 2000,
            sdmd_max_rotation: 0.1,
            sdmd_max_translation: 0.05,
            ransac: RansacConfig::default(),
            lambda_dssim: 0.2,
            random_background: true,
            eval_background: [1.0; 3],
            lr: s.lr,
            density: DensityConfig { from_iter: 500, until_iter: 30_000, ..s.density },
        }
    }

    /// Practical on two cores: lower resolution, fewer iterations and points, a
    /// smaller network (docs/training.md).
    pub fn cpu() -> Self {
        let mut c = Self::paper();
        c.preset = "cpu".into();
        c.iterations = 4000;
        c.resolution = 128;
        c.warmup_iterations = 300;
        c.static_opacity_only_iterations = 1500;
        c.moving_init_points = 5000;
        c.deform = DeformConfig { depth: 4, width: 128, xyz_frequencies: 10, time_frequencies: 6 };
        c.sdmd_interval = 500;
        c.density.from_iter = 300;
        c.density.until_iter = 3200;
        c.density.opacity_reset_interval = 1500;
        c.density.grad_threshold = 2e-4;
        c.density.max_gaussians = 30_000;
        c.lr.means_init = 4e-4;
        c
    }

    pub fn preset(name: &str) -> Result<Self> {
        match name {
            "paper" => Ok(Self::paper()),
            "cpu" => Ok(Self::cpu()),
            other => Err(Error::Config(format!("unknown preset '{other}' (valid: paper, cpu)"))),
        }
    }
}

/// A Gaussian set with its optimizer state and density statistics.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct OptimizedSet {
    pub gaussians: GaussianSet,
    pub adam: Adam,
    pub stats: DensityStats,
}

impl OptimizedSet {
    pub fn new(gaussians: GaussianSet) -> Self {
        let adam = Adam::new(&gaussians);
        let stats = DensityStats::new(gaussians.len());
        Self { gaussians, adam, stats }
    }

    fn drop_rows(&mut self, drop: &[bool]) {
        remove(&mut self.gaussians, &mut self.adam, &mut self.stats, drop);
    }

    fn append(&mut self, extra: &GaussianSet) {
        self.gaussians.extend_from(extra);
        self.adam.append_rows(extra.len());
        self.stats.append(extra.len());
    }
}

/// What one iteration did.
#[derive(Clone, Debug, Default)]
pub struct DynamicStep {
    pub iteration: u32,
    pub loss: f32,
    pub psnr: f32,
    pub static_count: usize,
    pub moving_count: usize,
    /// Gaussians SDMD moved to the static set at this iteration.
    pub sdmd_moved: usize,
}

/// A moving part found by stage III.
#[derive(Clone, Debug)]
pub struct PartEstimate {
    /// Indices into the moving set.
    pub members: Vec<usize>,
    pub joint: JointEstimate,
    /// Rigid motion from t = 0 to t = 1.
    pub motion: Rigid,
}

/// Both sets, the deformation network and their optimizers.
pub struct DualTrainer {
    pub config: DynamicConfig,
    pub static_set: OptimizedSet,
    pub moving: OptimizedSet,
    pub net: DeformNet,
    pub net_adam: AdamBuffer,
    pub iteration: u32,
    pub extent: f32,
}

/// Random streams of stage II's view order and backgrounds.
const STAGE_II_STREAMS: (u64, u64) = (11, 12);

/// Moving Gaussians below this opacity are left out of SDMD and stage III.
const ANALYSIS_MIN_OPACITY: f32 = 0.1;
/// Smallest part, as a fraction of the analysed moving Gaussians.
const MIN_PART_FRACTION: f64 = 0.02;

/// Motion time in [0, 1] as the network's time input (the one place the mapping lives).
pub fn network_time(t: f32) -> f32 {
    t
}

impl DualTrainer {
    /// Start from a trained static set.
    pub fn new(config: DynamicConfig, static_gaussians: GaussianSet, views: &[TrainView]) -> Result<Self> {
        if views.is_empty() {
            return Err(Error::Config("no motion views".into()));
        }
        if views.iter().any(|v| v.time.is_none()) {
            return Err(Error::Config("every motion view needs a time".into()));
        }
        let pts = random_points(
            config.moving_init_points,
            Vec3::from(config.init_box_min),
            Vec3::from(config.init_box_max),
            config.seed ^ 0x5eed,
        );
        let moving = gaussians_from_points(&pts, None, 0.1, static_gaussians.sh_degree);
        let net = DeformNet::new(config.deform.clone(), config.seed);
        let net_adam = AdamBuffer::zeros(net.parameter_count());
        Ok(Self {
            extent: camera_extent(views),
            static_set: OptimizedSet::new(static_gaussians),
            moving: OptimizedSet::new(moving),
            net,
            net_adam,
            iteration: 0,
            config,
        })
    }

    /// Learning rates at `it`; without `positions` only the opacity trains.
    fn learning_rates(&self, it: u32, positions: bool) -> LearningRates {
        let lr = self.config.lr.rates(it, self.config.iterations, self.extent);
        if positions {
            lr
        } else {
            LearningRates { means: 0.0, log_scales: 0.0, rotations: 0.0, sh_dc: 0.0, sh_rest: 0.0, ..lr }
        }
    }

    /// The moving set deformed to time `t` by the network.
    pub fn moving_at(&self, t: f32) -> GaussianSet {
        let mut g = self.moving.gaussians.clone();
        self.net.forward(&g.means, network_time(t)).apply(&mut g);
        g
    }

    /// Static and moving sets together at time `t`.
    pub fn union_at(&self, t: f32) -> GaussianSet {
        let mut u = self.static_set.gaussians.clone();
        u.extend_from(&self.moving_at(t));
        u
    }

    /// One optimisation step on one of the motion `views`.
    pub fn step(&mut self, views: &[TrainView]) -> DynamicStep {
        let it = self.iteration + 1;
        let c = &self.config;
        let (view, bg) =
            pick_view(views, c.seed, self.iteration, c.random_background, c.eval_background, STAGE_II_STREAMS);
        let t = view.time.unwrap_or(0.0);

        let deforming = it > self.config.warmup_iterations;
        let ns = self.static_set.gaussians.len();
        let nm = self.moving.gaussians.len();
        let mut moving = self.moving.gaussians.clone();
        let deform = deforming.then(|| self.net.forward(&moving.means, network_time(t)));
        if let Some(d) = &deform {
            d.apply(&mut moving);
        }
        let mut union = self.static_set.gaussians.clone();
        union.extend_from(&moving);
        let r = render(&union, &view.camera, &RenderOptions { background: bg, sh_degree: None });
        let target = view.target(bg);
        let loss =
            loss_and_grad(&r.image.color, &target, r.width as usize, r.height as usize, self.config.lambda_dssim);
        let grads = backward(&union, &r, &loss.grad, None, None);
        let g_static = grads.params.rows(0..ns);
        let g_moving = grads.params.rows(ns..ns + nm);

        // The deformed mean is mean + d(sg(mean)): the canonical mean and the offset
        // receive the same gradient (likewise the rotation).
        if let Some(d) = &deform {
            let g_net = self.net.backward(&d.cache, &g_moving.means, &g_moving.rotations);
            let lr = ExponLr {
                lr_init: self.config.deform_lr_init,
                lr_final: self.config.deform_lr_final,
                delay_steps: 0,
                delay_mult: 1.0,
                max_steps: u64::from(self.config.iterations),
            }
            .at(u64::from(it));
            self.net_adam.step(&mut self.net.params, &g_net, lr);
        }

        let d = self.config.density.clone();
        let opacity_only = it <= self.config.static_opacity_only_iterations;
        if it < d.until_iter {
            self.moving.stats.record(&r, &grads, ns..ns + nm);
            if !opacity_only {
                self.static_set.stats.record(&r, &grads, 0..ns);
            }
        }
        let lr_static = self.learning_rates(it, !opacity_only);
        let lr_moving = self.learning_rates(it, true);
        self.static_set.adam.step(&mut self.static_set.gaussians, &g_static, &lr_static);
        self.moving.adam.step(&mut self.moving.gaussians, &g_moving, &lr_moving);

        if it < d.until_iter && it > d.from_iter && it.is_multiple_of(d.interval) {
            let params = d.densify_params(it, self.extent);
            let mut rng = rng_for(self.config.seed, 13, u64::from(it));
            let m = &mut self.moving;
            densify_and_prune(&mut m.gaussians, &mut m.adam, &mut m.stats, &params, &mut rng);
            if !opacity_only {
                let s = &mut self.static_set;
                densify_and_prune(&mut s.gaussians, &mut s.adam, &mut s.stats, &params, &mut rng);
            }
            if d.opacity_reset_interval > 0 && it.is_multiple_of(d.opacity_reset_interval) {
                reset_opacity(&mut self.moving.gaussians, &mut self.moving.adam, 0.01);
            }
        }
        // Online pruning of the static set while only its opacities train.
        if opacity_only && it.is_multiple_of(d.interval) {
            let drop: Vec<bool> = self
                .static_set
                .gaussians
                .opacity_logits
                .iter()
                .map(|o| sigmoid(*o) < self.config.static_prune_opacity)
                .collect();
            self.static_set.drop_rows(&drop);
        }
        let mut sdmd_moved = 0;
        let sdmd = self.config.sdmd_interval;
        if deforming && !opacity_only && sdmd > 0 && it.is_multiple_of(sdmd) {
            sdmd_moved = self.static_during_motion();
        }
        self.iteration = it;
        DynamicStep {
            iteration: it,
            loss: loss.loss,
            psnr: psnr(&r.image.color, &target),
            static_count: self.static_set.gaussians.len(),
            moving_count: self.moving.gaussians.len(),
            sdmd_moved,
        }
    }

    /// Centres at t = 0, 0.5, 1 of the moving Gaussians that are visible enough to
    /// carry motion evidence (opacity >= `ANALYSIS_MIN_OPACITY`), with their indices.
    fn trajectories(&self) -> (Vec<Vec<DVec3>>, Vec<usize>) {
        let keep: Vec<usize> = (0..self.moving.gaussians.len())
            .filter(|&i| self.moving.gaussians.opacity(i) >= ANALYSIS_MIN_OPACITY)
            .collect();
        let traj = [0.0f32, 0.5, 1.0]
            .iter()
            .map(|&t| {
                let g = self.moving_at(t);
                keep.iter().map(|&i| g.mean(i).as_dvec3()).collect()
            })
            .collect();
        (traj, keep)
    }

    /// RANSAC settings for this many candidate points: a part must hold at least
    /// `MIN_PART_FRACTION` of them (floaters form many small rigid-looking groups).
    fn ransac_for(&self, points: usize) -> RansacConfig {
        let mut c = self.config.ransac.clone();
        c.min_inliers = c.min_inliers.max((MIN_PART_FRACTION * points as f64).ceil() as usize);
        c
    }

    /// SDMD: rigid groups of the moving set that do not move are handed to the
    /// static set (at their t = 1 pose, where newly revealed content is seen).
    /// Returns how many Gaussians moved.
    pub fn static_during_motion(&mut self) -> usize {
        let (traj, index) = self.trajectories();
        if index.len() < self.config.ransac.min_inliers {
            return 0;
        }
        let cfg = self.ransac_for(index.len());
        let (groups, _) = segment_rigid_parts(&Trajectories { positions: &traj }, &cfg);
        let mut drop = vec![false; self.moving.gaussians.len()];
        for g in &groups {
            let m = g.motions.last().expect("a motion to t = 1");
            if m.angle() <= self.config.sdmd_max_rotation && m.t.length() <= self.config.sdmd_max_translation {
                for &i in &g.members {
                    drop[index[i]] = true;
                }
            }
        }
        let moved = drop.iter().filter(|d| **d).count();
        if moved > 0 {
            let at_end = self.moving_at(1.0).subset(&drop);
            self.static_set.append(&at_end);
            self.moving.drop_rows(&drop);
        }
        moved
    }

    /// Stage III on the moving set: rigid parts and their joints.
    pub fn analyse(&self) -> (Vec<PartEstimate>, Vec<usize>) {
        let (traj, index) = self.trajectories();
        if index.len() < 3 {
            return (Vec::new(), index);
        }
        let cfg = self.ransac_for(index.len());
        let (groups, rest) = segment_rigid_parts(&Trajectories { positions: &traj }, &cfg);
        let rest = rest.into_iter().map(|i| index[i]).collect();
        let parts = groups
            .into_iter()
            .filter_map(|g| {
                let m = *g.motions.last()?;
                let centroid = g.members.iter().map(|&i| traj[0][i]).sum::<DVec3>() / g.members.len() as f64;
                let members: Vec<usize> = g.members.iter().map(|&i| index[i]).collect();
                let joint = extract_joint(&m, centroid);
                // A group that does not move is static content, not a part.
                let static_like =
                    m.angle() <= self.config.sdmd_max_rotation && m.t.length() <= self.config.sdmd_max_translation;
                (!static_like).then_some(PartEstimate { members, joint, motion: m })
            })
            .collect();
        (parts, rest)
    }

    /// Mean PSNR of `views` rendered at their times over the evaluation background.
    pub fn evaluate(&self, views: &[TrainView]) -> f32 {
        let bg = Vec3::from(self.config.eval_background);
        let sum: f32 = views
            .iter()
            .map(|v| {
                let g = self.union_at(v.time.unwrap_or(0.0));
                let r = render(&g, &v.camera, &RenderOptions { background: bg, sh_degree: None });
                psnr(&r.image.color, &v.target(bg))
            })
            .sum();
        sum / views.len().max(1) as f32
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synth::dataset::{write_dataset, SynthConfig};
    use crate::train::views::views_from_frames;
    use aim_capture::dataset::{load_aim_transforms, LoadOptions};
    use aim_capture::Phase;

    fn motion_views(name: &str) -> Vec<TrainView> {
        let dir = std::env::temp_dir().join(format!("aim-dyn-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let cfg = SynthConfig {
            resolution: 32,
            scan_views: 2,
            motion_frames: 12,
            end_views: 1,
            test_views: 1,
            motion_test_every: 0,
            samples_per_pixel: 1,
            ..Default::default()
        };
        write_dataset(&crate::synth::object("storage").expect("object"), &dir, &cfg, &|_, _| {}).expect("written");
        let frames = load_aim_transforms(
            &dir.join("motion").join("transforms_train.json"),
            Phase::Motion,
            &LoadOptions { depth: false },
        )
        .expect("loads");
        views_from_frames(&frames, 0).expect("views")
    }

    fn small_config() -> DynamicConfig {
        let mut c = DynamicConfig::cpu();
        c.resolution = 0;
        c.iterations = 30;
        c.moving_init_points = 400;
        c.warmup_iterations = 5;
        c.static_opacity_only_iterations = 20;
        c.deform = DeformConfig { depth: 2, width: 16, xyz_frequencies: 2, time_frequencies: 2 };
        c
    }

    fn static_set() -> GaussianSet {
        let pts = random_points(300, Vec3::splat(-0.5), Vec3::splat(0.5), 9);
        gaussians_from_points(&pts, None, 0.5, 0)
    }

    #[test]
    fn opacity_only_phase_freezes_everything_but_static_opacities() {
        let views = motion_views("freeze");
        let start = static_set();
        let mut t = DualTrainer::new(small_config(), start.clone(), &views).expect("trainer");
        let moving_before = t.moving.gaussians.clone();
        for _ in 0..10 {
            let s = t.step(&views);
            assert!(s.loss.is_finite());
        }
        // Pruning may drop static rows; the survivors keep their geometry and colour.
        let s = &t.static_set.gaussians;
        for i in 0..s.len() {
            let j = (0..start.len()).find(|&j| start.mean(j) == s.mean(i)).expect("static means unchanged");
            assert_eq!(s.log_scale(i), start.log_scale(j));
            assert_eq!(s.sh_dc[3 * i..3 * i + 3], start.sh_dc[3 * j..3 * j + 3]);
        }
        assert_ne!(s.opacity_logits, start.opacity_logits[..s.len()].to_vec(), "static opacities train");
        assert_ne!(t.moving.gaussians.means, moving_before.means, "the moving set trains");
    }

    #[test]
    fn sdmd_hands_motionless_groups_to_the_static_set() {
        let views = motion_views("sdmd");
        let mut t = DualTrainer::new(small_config(), static_set(), &views).expect("trainer");
        // A network whose output is zero: nothing in the moving set moves.
        t.net.params.iter_mut().for_each(|p| *p = 0.0);
        // Half the moving set visible (opacity 0.5), half transparent (left alone).
        let n = t.moving.gaussians.len();
        for (i, o) in t.moving.gaussians.opacity_logits.iter_mut().enumerate() {
            *o = if i < n / 2 { 0.0 } else { -6.0 };
        }
        let (ns, nm) = (t.static_set.gaussians.len(), t.moving.gaussians.len());
        let opaque = (0..nm).filter(|&i| t.moving.gaussians.opacity(i) >= ANALYSIS_MIN_OPACITY).count();
        let moved = t.static_during_motion();
        assert_eq!(opaque, n / 2);
        assert_eq!(moved, opaque, "every visible moving Gaussian is static");
        assert_eq!(t.static_set.gaussians.len(), ns + moved);
        assert_eq!(t.moving.gaussians.len(), nm - moved);
        assert_eq!(t.static_set.adam.len(), t.static_set.gaussians.len());
        assert_eq!(t.moving.stats.len(), t.moving.gaussians.len());
        assert!(t.analyse().0.is_empty(), "no moving parts remain");
    }
}
