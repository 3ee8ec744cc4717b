//! Stage II: the dual-Gaussian representation (paper Sec. 3.1). The static set
//! (stage I's result) and a moving set with the deformation field are rendered
//! together on the motion video; the static set first trains its opacities only
//! and is pruned as moving content fades from it, the moving set learns the
//! motion, and static-during-motion detection (SDMD) hands rigid groups that do
//! not move back to the static set. [`DualTrainer::analyse`] then runs stage III
//! on the moving set.

use glam::{DVec3, Vec3};
use rand::Rng;
use serde::{Deserialize, Serialize};

use crate::deform::{DeformConfig, DeformNet};
use crate::error::{Error, Result};
use crate::motion::{
    extract_joint, kmeans_rigid_parts, segment_rigid_parts, JointEstimate, RansacConfig, Rigid, Trajectories,
};
use crate::render::{render, Gradients, RenderOptions};
use crate::splat::{sigmoid, GaussianSet};
use crate::train::config::{DensityConfig, LrConfig, Preset, StageConfig};
use crate::train::density::{densify_and_prune, remove, reset_opacity, DensityStats, OPACITY_RESET_VALUE};
use crate::train::init::{gaussians_from_points, random_points};
use crate::train::loss::{loss_and_grad, psnr};
use crate::train::optim::{Adam, AdamBuffer, ExponLr, LearningRates};
use crate::train::rigidity::{rigidity_loss, RigidityConfig};
use crate::train::static_stage::{background_for, epoch_order_index, rng_for};
use crate::train::track::TrackConfig;
use crate::train::views::{camera_extent, TrainView};

/// Stage II settings. Defaults from the paper; the official code's values where
/// they differ are noted.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DynamicConfig {
    pub preset: String,
    /// How the motion is learnt: the paper's deformation field over the dual
    /// Gaussian sets, or time-ordered node tracking of the start state.
    pub method: StageTwoMethod,
    /// Settings of `node_track`.
    pub track: TrackConfig,
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
    /// How the moving set starts, and how many Gaussians it starts with (official: 50k random).
    pub moving_init: MovingInit,
    pub moving_init_points: usize,
    /// With `StartState`: this many random points in the init box as well, to
    /// take on content the start state never saw (a fridge's inside).
    pub moving_init_random_points: usize,
    pub init_box_min: [f32; 3],
    pub init_box_max: [f32; 3],
    pub deform: DeformConfig,
    pub deform_lr_init: f32,
    pub deform_lr_final: f32,
    /// SDMD every this many iterations after the opacity-only phase (paper 2000, official 500; 0 = off).
    pub sdmd_interval: u32,
    /// While the static set trains opacities only, train on the motion frames at
    /// or after this time (official code: time > 0.5). Moved parts are then well
    /// away from their start pose, so their start-state Gaussians fade instead of
    /// being kept alive by early frames in which nothing has moved yet.
    pub prune_phase_min_time: f32,
    /// Grow the training frames' time window [0, T] from T = `time_window_start`
    /// to 1 over this many iterations (0 = off; it then takes the place of
    /// `prune_phase_min_time`). Large motions are learnt from small ones: the
    /// photometric gradient only sees displacements of about a Gaussian's size.
    pub time_curriculum_iterations: u32,
    pub time_window_start: f32,
    /// After that phase, each pass over the motion video also trains this many
    /// random start-state views (at time 0) ...
    pub start_views_per_epoch: usize,
    /// ... and this many end-state views (at time 1), when the capture has them
    /// (official code: 5 and 10).
    pub end_views_per_epoch: usize,
    /// Weight of mean |d_xyz| + mean |d_rot| from the warm-up until one SDMD
    /// interval after the opacity-only phase (official code: 1e-3). Keeps the
    /// canonical moving set near where it is observed while the motion is learnt.
    pub deform_magnitude_weight: f32,
    /// Local rigidity of the deformation between random times (docs/training.md).
    pub rigidity: RigidityConfig,
    /// Groups rotating at most this (radians) ...
    pub sdmd_max_rotation: f64,
    /// ... and translating at most this (world units) between t = 0 and 1 are static.
    pub sdmd_max_translation: f64,
    pub ransac: RansacConfig,
    /// Stage III by K-means with this many parts instead of sequential RANSAC
    /// (0 = sequential RANSAC; the paper's Table 4 ablation uses the true count).
    pub kmeans_parts: usize,
    /// One deformable set for everything (the paper's "Ours-b" ablation): every
    /// start-state Gaussian is moving, the static set starts empty.
    pub single_deformable_set: bool,
    pub lambda_dssim: f32,
    pub random_background: bool,
    pub eval_background: [f32; 3],
    pub lr: LrConfig,
    /// Write a checkpoint every this many iterations (0 = only at the end and on interrupt).
    pub checkpoint_interval: u32,
    /// Density control of the moving set (and of both sets after the opacity-only phase).
    pub density: DensityConfig,
}

impl DynamicConfig {
    /// Whether a part moving by `m` (t = 0 -> 1) with its centroid at `centroid`
    /// stays within the static thresholds: its turn (`sdmd_max_rotation`) and its
    /// centroid's displacement (`sdmd_max_translation`).
    pub(crate) fn is_static_motion(&self, m: &Rigid, centroid: DVec3) -> bool {
        m.angle() <= self.sdmd_max_rotation && m.displacement(centroid).length() <= self.sdmd_max_translation
    }

    pub fn paper() -> Self {
        let s = crate::train::config::StaticConfig::paper();
        Self {
            preset: "paper".into(),
            method: StageTwoMethod::DualField,
            track: TrackConfig::default(),
            iterations: 40_000,
            resolution: 0,
            seed: 0,
            warmup_iterations: 3000,
            static_opacity_only_iterations: 10_000,
            static_prune_opacity: 0.005,
            moving_init: MovingInit::Random,
            moving_init_points: 50_000,
            moving_init_random_points: 0,
            init_box_min: [-0.5; 3],
            init_box_max: [0.5; 3],
            deform: DeformConfig::default(),
            deform_lr_init: 8e-4,
            deform_lr_final: 1.6e-6,
            sdmd_interval: 2000,
            prune_phase_min_time: 0.5,
            time_curriculum_iterations: 0,
            time_window_start: 0.1,
            start_views_per_epoch: 5,
            end_views_per_epoch: 10,
            deform_magnitude_weight: 1e-3,
            rigidity: RigidityConfig::default(),
            sdmd_max_rotation: 0.1,
            sdmd_max_translation: 0.05,
            ransac: RansacConfig::default(),
            kmeans_parts: 0,
            single_deformable_set: false,
            lambda_dssim: 0.2,
            random_background: true,
            eval_background: [1.0; 3],
            lr: s.lr,
            checkpoint_interval: 500,
            density: DensityConfig { from_iter: 500, until_iter: 30_000, ..s.density },
        }
    }

    /// Practical on two cores: lower resolution, fewer iterations, a smaller
    /// network, and, because 4000 iterations are too few for the paper's random
    /// start to learn a large motion, a moving set that starts as a copy of part
    /// of the start state with the field anchored at t = 0, trained on a growing
    /// time window (docs/training.md has the measurements behind this).
    pub fn cpu() -> Self {
        let mut c = Self::paper();
        c.preset = "cpu".into();
        c.iterations = 4000;
        c.resolution = 128;
        c.warmup_iterations = 0;
        c.static_opacity_only_iterations = 1500;
        c.time_curriculum_iterations = 1500;
        c.moving_init = MovingInit::StartState;
        c.moving_init_points = 10_000;
        c.deform_magnitude_weight = 0.0;
        c.deform = DeformConfig { depth: 4, width: 128, xyz_frequencies: 10, time_frequencies: 6, zero_at_start: true };
        c.sdmd_interval = 500;
        c.density.from_iter = 300;
        c.density.until_iter = 3200;
        c.density.opacity_reset_interval = 1500;
        c.density.grad_threshold = 2e-4;
        c.density.max_gaussians = 30_000;
        c.lr.means_init = 4e-4;
        // The method measured best on the benchmark (docs/training.md): node tracking
        // at the recorded resolution (stage I's Gaussians rendered at half their
        // training resolution alias badly: 28 instead of 37 dB on the same views).
        c.method = StageTwoMethod::NodeTrack;
        c.resolution = 256;
        c.iterations = 3600;
        c.random_background = false;
        c
    }
}

impl StageConfig for DynamicConfig {
    fn presets() -> [Preset<Self>; 2] {
        [("paper", Self::paper), ("cpu", Self::cpu)]
    }

    fn run_settings(&mut self) -> (&mut u64, &mut u32) {
        (&mut self.seed, &mut self.iterations)
    }

    fn validate(&self) -> std::result::Result<(), String> {
        if self.iterations == 0 {
            return Err("iterations must be at least 1".into());
        }
        if self.warmup_iterations >= self.iterations {
            return Err("warmup_iterations must be below iterations".into());
        }
        if self.moving_init_points == 0 {
            return Err("moving_init_points must be at least 1".into());
        }
        if !(0.0..=1.0).contains(&self.time_window_start) {
            return Err(format!("time_window_start must be in [0, 1], got {}", self.time_window_start));
        }
        if !(0.0..=1.0).contains(&self.prune_phase_min_time) {
            return Err(format!("prune_phase_min_time must be in [0, 1], got {}", self.prune_phase_min_time));
        }
        if !(0.0..1.0).contains(&self.static_prune_opacity) {
            return Err(format!("static_prune_opacity must be in [0, 1), got {}", self.static_prune_opacity));
        }
        for (k, v) in [
            ("deform_lr_init", self.deform_lr_init),
            ("deform_lr_final", self.deform_lr_final),
            ("lr.means_init", self.lr.means_init),
            ("lr.opacity", self.lr.opacity),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return Err(format!("{k} must be a positive number, got {v}"));
            }
        }
        for (k, v) in [("deform_magnitude_weight", self.deform_magnitude_weight), ("lambda_dssim", self.lambda_dssim)] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(format!("{k} must be >= 0, got {v}"));
            }
        }
        if self.deform.depth == 0 || self.deform.width == 0 {
            return Err("deform.depth and deform.width must be at least 1".into());
        }
        if self.density.interval == 0 {
            return Err("density.interval must be at least 1".into());
        }
        // The view schedule runs the time curriculum, then (without one) the
        // opacity-only phase: a curriculum that ends inside that phase has no schedule.
        if self.time_curriculum_iterations > 0 && self.time_curriculum_iterations < self.static_opacity_only_iterations
        {
            return Err(format!(
                "time_curriculum_iterations ({}) must be 0 or at least static_opacity_only_iterations ({})",
                self.time_curriculum_iterations, self.static_opacity_only_iterations
            ));
        }
        self.track.validate()?;
        for i in 0..3 {
            if self.init_box_min[i].partial_cmp(&self.init_box_max[i]) != Some(std::cmp::Ordering::Less) {
                return Err(format!("init_box_min[{i}] must be below init_box_max[{i}]"));
            }
        }
        Ok(())
    }
}

/// How stage II learns the motion.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum StageTwoMethod {
    /// The paper: the dual Gaussian sets, a deformation network on the moving set, SDMD.
    DualField,
    /// Time-ordered tracking of the start state by control nodes ([`crate::train::track`]).
    NodeTrack,
}

/// How stage II's moving set starts.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum MovingInit {
    /// Random points in the init box (the paper, following Deformable-3DGS).
    Random,
    /// A random subset of the start-state Gaussians: with `deform.zero_at_start`
    /// each begins exactly where the start state has it, so the moving parts
    /// only have to learn where they go.
    StartState,
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

/// The views stage II trains on: the motion video, and multi-view frames of the
/// start and end states when the capture has them (trained at times 0 and 1).
pub struct StageTwoViews {
    pub motion: Vec<TrainView>,
    pub start: Vec<TrainView>,
    pub end: Vec<TrainView>,
}

impl StageTwoViews {
    /// Checks that there is a motion video with times; gives the start and end
    /// views times 0 and 1.
    pub fn new(motion: Vec<TrainView>, mut start: Vec<TrainView>, mut end: Vec<TrainView>) -> Result<Self> {
        if motion.is_empty() {
            return Err(Error::Config("no motion views".into()));
        }
        require_times(&motion)?;
        start.iter_mut().for_each(|v| v.time = Some(0.0));
        end.iter_mut().for_each(|v| v.time = Some(1.0));
        Ok(Self { motion, start, end })
    }
}

/// Every motion view must carry its time in the motion.
pub(crate) fn require_times(motion: &[TrainView]) -> Result<()> {
    if motion.iter().any(|v| v.time.is_none()) {
        return Err(Error::Config("every motion view needs a time".into()));
    }
    Ok(())
}

/// Both sets, the deformation network and their optimizers: the whole state of
/// a stage II run (what a checkpoint holds).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct DualTrainer {
    /// The rasterizer of the training step (not saved: a run may resume on another).
    #[serde(skip)]
    pub backend: crate::render::Backend,
    /// Where the deformation network runs (the backend's device).
    #[serde(skip)]
    pub field_device: crate::deform::FieldDevice,
    pub config: DynamicConfig,
    pub static_set: OptimizedSet,
    pub moving: OptimizedSet,
    pub net: DeformNet,
    pub net_adam: AdamBuffer,
    pub iteration: u32,
    pub extent: f32,
}

/// Random streams of stage II: view order, backgrounds, densification, and the
/// start and end views drawn into each epoch.
const STREAM_VIEWS: u64 = 11;
const STREAM_BACKGROUND: u64 = 12;
const STREAM_DENSIFY: u64 = 13;
const STREAM_START_VIEWS: u64 = 14;
const STREAM_END_VIEWS: u64 = 15;
const STREAM_RIGIDITY: u64 = 16;
const STREAM_MOVING_INIT: u64 = 17;

/// Moving Gaussians below this opacity are left out of SDMD and stage III.
const ANALYSIS_MIN_OPACITY: f32 = 0.1;
/// Smallest part, as a fraction of the analysed moving Gaussians.
const MIN_PART_FRACTION: f64 = 0.02;

const CHECKPOINT_STAGE: &str = "stage II";

/// Write the trainer's full state atomically.
pub fn save_checkpoint(path: &std::path::Path, trainer: &DualTrainer, elapsed_s: f64) -> Result<()> {
    crate::train::checkpoint::save(path, CHECKPOINT_STAGE, trainer, elapsed_s)
}

/// Read a checkpoint written by [`save_checkpoint`].
pub fn load_checkpoint(path: &std::path::Path) -> Result<(DualTrainer, f64)> {
    crate::train::checkpoint::load(path, CHECKPOINT_STAGE, |t: &DualTrainer| {
        for (name, set) in [("static", &t.static_set), ("moving", &t.moving)] {
            set.gaussians.check_shapes().map_err(|m| format!("{name} set: {m}"))?;
            if set.adam.len() != set.gaussians.len() || set.stats.len() != set.gaussians.len() {
                return Err(format!("{name} set: optimizer or density state does not match the Gaussians"));
            }
        }
        if t.net.params.len() != DeformNet::new(t.net.config.clone(), 0).parameter_count()
            || t.net_adam.m.len() != t.net.params.len()
            || t.net_adam.v.len() != t.net.params.len()
        {
            return Err("the deformation network does not match its configuration".into());
        }
        Ok(())
    })
}

/// Add `weight` times the gradient of sum_i |x_i| (rows of `dim` floats of `x`) to `grad`.
fn add_norm_gradient(grad: &mut [f32], x: &[f32], dim: usize, weight: f32) {
    for (g, v) in grad.chunks_exact_mut(dim).zip(x.chunks_exact(dim)) {
        let norm = v.iter().map(|a| a * a).sum::<f32>().sqrt();
        if norm > 1e-12 {
            g.iter_mut().zip(v).for_each(|(g, a)| *g += weight * a / norm);
        }
    }
}

/// Motion time in [0, 1] as the network's time input (the one place the mapping lives).
pub fn network_time(t: f32) -> f32 {
    t
}

/// RANSAC settings for this many candidate points: a part must hold at least
/// `MIN_PART_FRACTION` of them (floaters form many small rigid-looking groups).
fn ransac_for(config: &DynamicConfig, points: usize) -> RansacConfig {
    let mut c = config.ransac.clone();
    c.min_inliers = c.min_inliers.max((MIN_PART_FRACTION * points as f64).ceil() as usize);
    c
}

/// Stage III on trajectories of points (`traj[k][i]`: point i at time sample k, t = 0
/// first; `index[i]` is point i's index in the caller's set): sequential RANSAC (or
/// K-means with `kmeans_parts`), groups that do not move dropped, a joint per group.
/// Returns the parts (members as the caller's indices) and the unexplained points.
pub(crate) fn parts_from_trajectories(
    config: &DynamicConfig,
    traj: &[Vec<DVec3>],
    index: &[usize],
) -> (Vec<PartEstimate>, Vec<usize>) {
    if index.len() < 3 {
        return (Vec::new(), index.to_vec());
    }
    let cfg = ransac_for(config, index.len());
    let trajectories = Trajectories { positions: traj };
    let (groups, rest) = if config.kmeans_parts > 0 {
        (kmeans_rigid_parts(&trajectories, config.kmeans_parts, cfg.seed), Vec::new())
    } else {
        segment_rigid_parts(&trajectories, &cfg)
    };
    let rest = rest.into_iter().map(|i| index[i]).collect();
    let parts = groups
        .into_iter()
        .filter_map(|g| {
            let m = *g.motions.last()?;
            let centroid = g.members.iter().map(|&i| traj[0][i]).sum::<DVec3>() / g.members.len() as f64;
            let members: Vec<usize> = g.members.iter().map(|&i| index[i]).collect();
            let joint = extract_joint(&m, centroid);
            // A group that does not move is static content, not a part.
            (!config.is_static_motion(&m, centroid)).then_some(PartEstimate { members, joint, motion: m })
        })
        .collect();
    (parts, rest)
}

impl DualTrainer {
    /// Start from a trained static set.
    pub fn new(config: DynamicConfig, static_gaussians: GaussianSet, views: &StageTwoViews) -> Result<Self> {
        config.validate().map_err(Error::Config)?;
        if config.single_deformable_set {
            let sh_degree = static_gaussians.sh_degree;
            return Ok(Self::from_sets(config, GaussianSet::new(sh_degree), static_gaussians, views));
        }
        let moving = match config.moving_init {
            MovingInit::Random => {
                let pts = random_points(
                    config.moving_init_points,
                    Vec3::from(config.init_box_min),
                    Vec3::from(config.init_box_max),
                    config.seed ^ 0x5eed,
                );
                gaussians_from_points(&pts, None, 0.1, static_gaussians.sh_degree)
            }
            MovingInit::StartState => {
                let n = static_gaussians.len();
                let mut keep = vec![false; n];
                let mut rng = rng_for(config.seed, STREAM_MOVING_INIT, 0);
                for i in rand::seq::index::sample(&mut rng, n, config.moving_init_points.min(n)) {
                    keep[i] = true;
                }
                let mut moving = static_gaussians.subset(&keep);
                if config.moving_init_random_points > 0 {
                    let pts = random_points(
                        config.moving_init_random_points,
                        Vec3::from(config.init_box_min),
                        Vec3::from(config.init_box_max),
                        config.seed ^ 0x5eed,
                    );
                    moving.extend_from(&gaussians_from_points(&pts, None, 0.1, static_gaussians.sh_degree));
                }
                moving
            }
        };
        Ok(Self::from_sets(config, static_gaussians, moving, views))
    }

    fn from_sets(config: DynamicConfig, static_set: GaussianSet, moving: GaussianSet, views: &StageTwoViews) -> Self {
        let net = DeformNet::new(config.deform.clone(), config.seed);
        let net_adam = AdamBuffer::zeros(net.parameter_count());
        Self {
            backend: crate::render::Backend::Cpu,
            field_device: crate::deform::FieldDevice::Cpu,
            // The scene's extent from the scan, as stage I takes it (the motion video
            // circles closer or farther); the motion cameras when there is no scan.
            extent: camera_extent(if views.start.is_empty() { &views.motion } else { &views.start }),
            static_set: OptimizedSet::new(static_set),
            moving: OptimizedSet::new(moving),
            net,
            net_adam,
            iteration: 0,
            config,
        }
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

    /// The view of 1-based iteration `it`. During the opacity-only phase: the
    /// motion frames from `prune_phase_min_time` on. After it: epochs of the whole
    /// motion video plus a few start and end views drawn per epoch.
    fn view_for<'v>(&self, it: u32, views: &'v StageTwoViews) -> &'v TrainView {
        let c = &self.config;
        if it <= c.time_curriculum_iterations {
            let f = it as f32 / c.time_curriculum_iterations as f32;
            let limit = c.time_window_start + (1.0 - c.time_window_start) * f;
            let early: Vec<&TrainView> = views.motion.iter().filter(|v| v.time.is_some_and(|t| t <= limit)).collect();
            if !early.is_empty() {
                return early[epoch_order_index(early.len(), c.seed, it - 1, STREAM_VIEWS)];
            }
        }
        if it <= c.static_opacity_only_iterations && c.time_curriculum_iterations == 0 {
            let late: Vec<&TrainView> =
                views.motion.iter().filter(|v| v.time.is_some_and(|t| t >= c.prune_phase_min_time)).collect();
            return if late.is_empty() {
                &views.motion[epoch_order_index(views.motion.len(), c.seed, it - 1, STREAM_VIEWS)]
            } else {
                late[epoch_order_index(late.len(), c.seed, it - 1, STREAM_VIEWS)]
            };
        }
        let local = it - 1 - c.static_opacity_only_iterations;
        let n_start = c.start_views_per_epoch.min(views.start.len());
        let n_end = c.end_views_per_epoch.min(views.end.len());
        let pool = views.motion.len() + n_start + n_end;
        let k = epoch_order_index(pool, c.seed, local, STREAM_VIEWS);
        let epoch = u64::from(local) / pool as u64;
        let drawn = |set: &'v [TrainView], n: usize, stream: u64, i: usize| {
            let picks = rand::seq::index::sample(&mut rng_for(c.seed, stream, epoch), set.len(), n);
            &set[picks.index(i)]
        };
        match k.checked_sub(views.motion.len()) {
            None => &views.motion[k],
            Some(i) if i < n_start => drawn(&views.start, n_start, STREAM_START_VIEWS, i),
            Some(i) => drawn(&views.end, n_end, STREAM_END_VIEWS, i - n_start),
        }
    }

    /// One optimisation step.
    pub fn step(&mut self, views: &StageTwoViews) -> DynamicStep {
        let it = self.iteration + 1;
        let c = &self.config;
        let view = self.view_for(it, views);
        let bg =
            background_for(view, c.seed, self.iteration, c.random_background, c.eval_background, STREAM_BACKGROUND);
        let t = view.time.unwrap_or(0.0);

        let deforming = it > self.config.warmup_iterations;
        let nm = self.moving.gaussians.len();
        let mut moving = self.moving.gaussians.clone();
        let deform = deforming.then(|| self.net.forward_on(&self.field_device, &moving.means, network_time(t)));
        if let Some(d) = &deform {
            d.apply(&mut moving);
        }
        // Both sets rendered as one scene, each getting its own gradients.
        let sets = [&self.static_set.gaussians, &moving];
        let whole = [0, 0, view.camera.width(), view.camera.height()];
        let r = self.backend.render_sets(&sets, &view.camera, whole, &RenderOptions::uniform(bg));
        let target = view.target(bg);
        let (w, h) = (r.width() as usize, r.height() as usize);
        let loss = loss_and_grad(&r.image().color, &target, w, h, self.config.lambda_dssim);
        let [grads_static, grads_moving]: [Gradients; 2] =
            self.backend.backward_sets(&sets, &r, &loss.grad, None, None).try_into().expect("one per set");
        let (g_static, g_moving) = (&grads_static.params, &grads_moving.params);

        // The deformed mean is mean + d(sg(mean)): the canonical mean and the offset
        // receive the same gradient (likewise the rotation).
        if let Some(d) = &deform {
            let regularise = it <= self.config.static_opacity_only_iterations + self.config.sdmd_interval.max(1);
            let mut g_net = if regularise && self.config.deform_magnitude_weight > 0.0 {
                let (mut g_dxyz, mut g_drot) = (g_moving.means.clone(), g_moving.rotations.clone());
                let w = self.config.deform_magnitude_weight / nm.max(1) as f32;
                add_norm_gradient(&mut g_dxyz, &d.d_xyz, 3, w);
                add_norm_gradient(&mut g_drot, &d.d_rot, 4, w);
                self.net.backward(&d.cache, &g_dxyz, &g_drot)
            } else {
                self.net.backward(&d.cache, &g_moving.means, &g_moving.rotations)
            };
            self.add_rigidity_gradient(it, &mut g_net);
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
            self.moving.stats.record(&grads_moving);
            if !opacity_only {
                self.static_set.stats.record(&grads_static);
            }
        }
        let lr_static = self.learning_rates(it, !opacity_only);
        let lr_moving = self.learning_rates(it, true);
        self.static_set.adam.step(&mut self.static_set.gaussians, g_static, &lr_static);
        self.moving.adam.step(&mut self.moving.gaussians, g_moving, &lr_moving);

        if it < d.until_iter && it > d.from_iter && it.is_multiple_of(d.interval) {
            let params = d.densify_params(it, self.extent);
            let mut rng = rng_for(self.config.seed, STREAM_DENSIFY, u64::from(it));
            let m = &mut self.moving;
            densify_and_prune(&mut m.gaussians, &mut m.adam, &mut m.stats, &params, &mut rng);
            if !opacity_only {
                let s = &mut self.static_set;
                densify_and_prune(&mut s.gaussians, &mut s.adam, &mut s.stats, &params, &mut rng);
            }
        }
        // As stage I: on its own schedule, not only on densification iterations.
        if it < d.until_iter && d.opacity_reset_interval > 0 && it.is_multiple_of(d.opacity_reset_interval) {
            reset_opacity(&mut self.moving.gaussians, &mut self.moving.adam, OPACITY_RESET_VALUE);
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
            psnr: psnr(&r.image().color, &target),
            static_count: self.static_set.gaussians.len(),
            moving_count: self.moving.gaussians.len(),
            sdmd_moved,
        }
    }

    /// Add the rigidity term's network gradient at iteration `it` (every
    /// `rigidity.interval` iterations, scaled by it): a random sample of the
    /// moving set between two random times.
    fn add_rigidity_gradient(&self, it: u32, g_net: &mut [f32]) {
        let r = &self.config.rigidity;
        let nm = self.moving.gaussians.len();
        if r.weight <= 0.0 || r.interval == 0 || it < r.from_iteration || !it.is_multiple_of(r.interval) || nm < 2 {
            return;
        }
        let mut rng = rng_for(self.config.seed, STREAM_RIGIDITY, u64::from(it));
        let picks = rand::seq::index::sample(&mut rng, nm, r.samples.min(nm));
        let means: Vec<f32> =
            picks.iter().flat_map(|i| self.moving.gaussians.means[3 * i..3 * i + 3].iter().copied()).collect();
        // With the field anchored at t = 0, distances are kept from the start state,
        // where neighbours are known to be neighbours; otherwise between two random times.
        let t_a = if self.config.deform.zero_at_start { 0.0 } else { rng.random::<f32>() };
        let t_b = rng.random::<f32>();
        let (_, g) = rigidity_loss(&self.net, &means, network_time(t_a), network_time(t_b), r.neighbours, r.scale);
        let w = r.weight * r.interval as f32;
        g_net.iter_mut().zip(g).for_each(|(acc, v)| *acc += w * v);
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

    /// SDMD: rigid groups of the moving set that do not move are handed to the
    /// static set (at their t = 1 pose, where newly revealed content is seen).
    /// Returns how many Gaussians moved.
    pub fn static_during_motion(&mut self) -> usize {
        let (traj, index) = self.trajectories();
        if index.len() < self.config.ransac.min_inliers {
            return 0;
        }
        let cfg = ransac_for(&self.config, index.len());
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
        parts_from_trajectories(&self.config, &traj, &index)
    }

    /// Mean PSNR of `views` rendered at their times over the evaluation background.
    pub fn evaluate(&self, views: &[TrainView]) -> f32 {
        let bg = Vec3::from(self.config.eval_background);
        let sum: f32 = views
            .iter()
            .map(|v| {
                let g = self.union_at(v.time.unwrap_or(0.0));
                let r = render(&g, &v.camera, &RenderOptions::uniform(bg));
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

    fn motion_views(name: &str) -> StageTwoViews {
        let dir = std::env::temp_dir().join(format!("aim-dyn-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let cfg = SynthConfig {
            resolution: 32,
            scan_views: 2,
            motion_frames: 12,
            end_views: 3,
            test_views: 1,
            motion_test_every: 0,
            samples_per_pixel: 1,
            ..Default::default()
        };
        write_dataset(&crate::synth::object("storage").expect("object"), &dir, &cfg, &|_, _| {}).expect("written");
        let load = |folder: &str, phase: Phase| {
            let path = dir.join(folder).join("transforms_train.json");
            let frames = load_aim_transforms(&path, phase, &LoadOptions { depth: false }).expect("loads");
            views_from_frames(&frames, 0).expect("views")
        };
        let views =
            StageTwoViews::new(load("motion", Phase::Motion), load("start", Phase::Scan), load("end", Phase::After))
                .expect("motion views");
        let _ = std::fs::remove_dir_all(&dir);
        views
    }

    fn small_config() -> DynamicConfig {
        let mut c = DynamicConfig::cpu();
        c.resolution = 0;
        c.iterations = 30;
        c.moving_init_points = 400;
        c.warmup_iterations = 5;
        c.static_opacity_only_iterations = 20;
        c.deform = DeformConfig { depth: 2, width: 16, xyz_frequencies: 2, time_frequencies: 2, zero_at_start: false };
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

    #[test]
    fn a_curriculum_ending_inside_the_opacity_only_phase_is_refused() {
        let views = motion_views("curriculum");
        let mut c = small_config();
        c.time_curriculum_iterations = 10;
        c.static_opacity_only_iterations = 30;
        let Err(e) = DualTrainer::new(c, static_set(), &views) else {
            panic!("a curriculum inside the opacity-only phase must be refused")
        };
        let e = e.to_string();
        assert!(e.contains("time_curriculum_iterations"), "{e}");
    }

    #[test]
    fn view_schedule_follows_the_phases() {
        let views = motion_views("schedule");
        let times = |c: DynamicConfig, its: std::ops::RangeInclusive<u32>| {
            let t = DualTrainer::new(c, static_set(), &views).expect("trainer");
            its.map(|it| t.view_for(it, &views).time.expect("timed")).collect::<Vec<f32>>()
        };
        // Growing window: early iterations see only early frames, and it reaches 1.
        let mut c = small_config();
        c.time_curriculum_iterations = 40;
        c.time_window_start = 0.1;
        c.static_opacity_only_iterations = 40;
        let ts = times(c, 1..=40);
        for (i, t) in ts.iter().enumerate() {
            let limit = 0.1 + 0.9 * (i + 1) as f32 / 40.0;
            assert!(*t <= limit + 1e-6, "iteration {}: time {t} beyond the window {limit}", i + 1);
        }
        assert!(ts[30..].iter().any(|t| *t > 0.7), "the window grows");
        // The paper's schedule: late frames only while the static set trains opacities.
        let mut c = small_config();
        c.time_curriculum_iterations = 0;
        c.static_opacity_only_iterations = 30;
        assert!(times(c.clone(), 1..=30).iter().all(|t| *t >= c.prune_phase_min_time));
        // Afterwards start (time 0) and end (time 1) views join the motion frames.
        c.start_views_per_epoch = 2;
        c.end_views_per_epoch = 3;
        let after = times(c, 31..=31 + 4 * 17);
        let starts = after.iter().filter(|t| **t == 0.0).count();
        let ends = after.iter().filter(|t| **t == 1.0).count();
        assert!(starts >= 2 * 4 && ends >= 3 * 4, "start views {starts}, end views {ends} over 4 epochs");
    }

    #[test]
    fn start_state_init_begins_on_the_start_state() {
        let views = motion_views("startinit");
        let mut c = small_config();
        c.moving_init = MovingInit::StartState;
        c.moving_init_points = 100;
        c.deform.zero_at_start = true;
        let start = static_set();
        let t = DualTrainer::new(c, start.clone(), &views).expect("trainer");
        assert_eq!(t.moving.gaussians.len(), 100);
        let at0 = t.moving_at(0.0);
        for i in 0..at0.len() {
            assert!(
                (0..start.len()).any(|j| start.mean(j) == at0.mean(i)),
                "moving Gaussian {i} is a start-state copy"
            );
        }
        assert_ne!(t.moving_at(0.5).means, at0.means, "the field moves them later");
    }

    #[test]
    fn resuming_from_a_checkpoint_is_bit_identical() {
        let views = motion_views("resume");
        let mut c = small_config();
        c.sdmd_interval = 10;
        let mut straight = DualTrainer::new(c.clone(), static_set(), &views).expect("trainer");
        for _ in 0..30 {
            straight.step(&views);
        }
        let mut first = DualTrainer::new(c, static_set(), &views).expect("trainer");
        for _ in 0..15 {
            first.step(&views);
        }
        let path = std::env::temp_dir().join(format!("aim-dyn-ckpt-{}.bin", std::process::id()));
        save_checkpoint(&path, &first, 1.5).expect("saved");
        let (mut resumed, elapsed) = load_checkpoint(&path).expect("loads");
        assert_eq!(elapsed, 1.5);
        for _ in 0..15 {
            resumed.step(&views);
        }
        assert_eq!(resumed.moving.gaussians, straight.moving.gaussians);
        assert_eq!(resumed.static_set.gaussians, straight.static_set.gaussians);
        assert_eq!(resumed.net.params, straight.net.params);
        // A stage I checkpoint is refused by name.
        crate::train::checkpoint::save(&path, "stage I", &0u32, 0.0).expect("saved");
        let e = load_checkpoint(&path).unwrap_err().to_string();
        assert!(e.contains("stage I") && e.contains(&path.display().to_string()), "{e}");
        let _ = std::fs::remove_file(&path);
    }

    #[test]
    fn toml_overrides_the_preset_and_names_unknown_keys() {
        let c = DynamicConfig::from_toml(
            "preset = \"cpu\"\niterations = 77\n[deform]\nwidth = 64\n",
            std::path::Path::new("d.toml"),
        )
        .expect("parses");
        assert_eq!((c.iterations, c.deform.width, c.resolution), (77, 64, DynamicConfig::cpu().resolution));
        let e =
            DynamicConfig::from_toml("sdmd_intervall = 3\n", std::path::Path::new("d.toml")).unwrap_err().to_string();
        assert!(e.contains("d.toml") && e.contains("sdmd_intervall"), "{e}");
        let e = DynamicConfig::from_toml("time_window_start = 2.0\n", std::path::Path::new("d.toml"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("time_window_start"), "{e}");
    }
}
