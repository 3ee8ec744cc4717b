//! Stage I: the start-state 3DGS, trained on the scan views (paper Sec. 3,
//! Appendix A). [`GaussianTrainer`] is the reusable loop (one step = pick a view,
//! render over a random background, L1 + D-SSIM, backward, density control,
//! Adam); [`run_static`] adds the run folder: checkpoints, resume, evaluation
//! and outputs.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use glam::Vec3;
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::error::{write_atomic, Error, Result};
use crate::render::{render, Backend, RenderOptions};
use crate::splat::ply::PointCloud;
use crate::splat::GaussianSet;
use crate::train::config::{StageConfig, StaticConfig};
use crate::train::density::{densify_and_prune, reset_opacity, DensifyReport, DensityStats, OPACITY_RESET_VALUE};
use crate::train::init::{gaussians_from_points, random_points};
use crate::train::loss::{loss_and_grad, psnr, ssim};
use crate::train::optim::Adam;
use crate::train::views::{camera_extent, TrainView};
use crate::viz::Viz;

/// What one iteration did.
#[derive(Clone, Debug, Default)]
pub struct StepReport {
    pub iteration: u32,
    pub loss: f32,
    pub psnr: f32,
    pub gaussians: usize,
    pub densified: Option<DensifyReport>,
}

/// A Gaussian set with its optimizer and density statistics: everything that
/// must be saved to resume training exactly.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct GaussianTrainer {
    /// The rasterizer the steps render with (not saved: a run may resume on another).
    #[serde(skip)]
    pub backend: Backend,
    pub config: StaticConfig,
    pub gaussians: GaussianSet,
    pub adam: Adam,
    pub stats: DensityStats,
    /// Iterations completed.
    pub iteration: u32,
    /// Scene extent (world units) from the training cameras.
    pub extent: f32,
}

/// A seeded generator for one purpose at one iteration, so every random choice
/// depends only on (seed, iteration): a resumed run repeats an uninterrupted one.
pub(crate) fn rng_for(seed: u64, stream: u64, iteration: u64) -> ChaCha8Rng {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(stream);
    rng.set_word_pos(u128::from(iteration) << 20);
    rng
}

/// Position in a fresh per-epoch permutation of `n` items at 0-based `iteration`
/// (epoch = iteration / n), drawn from random stream `stream`.
pub(crate) fn epoch_order_index(n: usize, seed: u64, iteration: u32, stream: u64) -> usize {
    let epoch = iteration as usize / n;
    let mut order: Vec<usize> = (0..n).collect();
    order.shuffle(&mut rng_for(seed, stream, epoch as u64));
    order[iteration as usize % n]
}

/// The background of 0-based iteration `iteration`: RGBA targets over a random
/// colour when asked (the official --random_bg_color), else over the evaluation
/// background.
pub(crate) fn background_for(
    view: &TrainView,
    seed: u64,
    iteration: u32,
    random_background: bool,
    eval_background: [f32; 3],
    stream: u64,
) -> Vec3 {
    if random_background && view.alpha.is_some() {
        let mut rng = rng_for(seed, stream, u64::from(iteration) + 1);
        Vec3::new(rng.random(), rng.random(), rng.random())
    } else {
        Vec3::from(eval_background)
    }
}

/// The view and background of 0-based iteration `iteration`: views in a fresh
/// permutation per epoch, backgrounds as [`background_for`]. `streams` = (view
/// order, background) random streams of the calling stage.
pub(crate) fn pick_view(
    views: &[TrainView],
    seed: u64,
    iteration: u32,
    random_background: bool,
    eval_background: [f32; 3],
    streams: (u64, u64),
) -> (&TrainView, Vec3) {
    let view = &views[epoch_order_index(views.len(), seed, iteration, streams.0)];
    (view, background_for(view, seed, iteration, random_background, eval_background, streams.1))
}

const STREAM_VIEWS: u64 = 1;
const STREAM_BACKGROUND: u64 = 2;
const STREAM_DENSIFY: u64 = 3;

impl GaussianTrainer {
    /// Start from a point cloud (or random points in the configured box).
    pub fn new(config: StaticConfig, views: &[TrainView], points: Option<&PointCloud>) -> Result<Self> {
        if views.is_empty() {
            return Err(Error::Config("no training views".into()));
        }
        config.validate().map_err(Error::Config)?;
        let gaussians = match points {
            Some(cloud) => {
                if cloud.points.is_empty() {
                    return Err(Error::Config("the initial point cloud is empty".into()));
                }
                gaussians_from_points(&cloud.points, cloud.colors.as_deref(), config.init.opacity, config.sh_degree)
            }
            None => {
                let pts = random_points(
                    config.init.points,
                    Vec3::from(config.init.box_min),
                    Vec3::from(config.init.box_max),
                    config.seed,
                );
                gaussians_from_points(&pts, None, config.init.opacity, config.sh_degree)
            }
        };
        let adam = Adam::new(&gaussians);
        let stats = DensityStats::new(gaussians.len());
        Ok(Self { backend: Backend::Cpu, extent: camera_extent(views), config, gaussians, adam, stats, iteration: 0 })
    }

    /// SH degree in use at iteration `it` (raised every `sh_increase_interval`).
    pub fn active_sh_degree(&self, it: u32) -> u32 {
        let interval = self.config.sh_increase_interval.max(1);
        (it / interval).min(self.config.sh_degree)
    }

    /// One optimisation step on one of `views`.
    pub fn step(&mut self, views: &[TrainView]) -> StepReport {
        let it = self.iteration + 1; // 1-based like 3DGS, so schedules match its numbers
        let c = &self.config;
        let streams = (STREAM_VIEWS, STREAM_BACKGROUND);
        let (view, bg) = pick_view(views, c.seed, self.iteration, c.random_background, c.eval_background, streams);
        let opts = RenderOptions { background: bg, sh_degree: Some(self.active_sh_degree(it)), background_image: None };
        let r = self.backend.render(&self.gaussians, &view.camera, &opts);
        let image = r.image();
        let target = view.target(bg);
        let loss =
            loss_and_grad(&image.color, &target, r.width() as usize, r.height() as usize, self.config.lambda_dssim);
        let depth = view.depth_loss(&image.depth, self.config.depth_weight);
        let grads = self.backend.backward(
            &self.gaussians,
            &r,
            &loss.grad,
            None,
            depth.as_ref().map(|(_, g)| g.as_slice()),
            None,
        );
        let d = &self.config.density;
        let total = loss.loss + depth.as_ref().map_or(0.0, |(l, _)| *l);
        let mut report =
            StepReport { iteration: it, loss: total, psnr: psnr(&image.color, &target), ..Default::default() };

        if it < d.until_iter {
            self.stats.record(&grads);
        }
        let lrs = self.config.lr.rates(it, self.config.iterations, self.extent);
        self.adam.step(&mut self.gaussians, &grads.params, &lrs);
        if it < d.until_iter {
            if it > d.from_iter && it.is_multiple_of(d.interval) {
                let params = d.densify_params(it, self.extent);
                let mut rng = rng_for(self.config.seed, STREAM_DENSIFY, u64::from(it));
                report.densified =
                    Some(densify_and_prune(&mut self.gaussians, &mut self.adam, &mut self.stats, &params, &mut rng));
            }
            if d.opacity_reset_interval > 0 && it.is_multiple_of(d.opacity_reset_interval) {
                reset_opacity(&mut self.gaussians, &mut self.adam, OPACITY_RESET_VALUE);
            }
        }
        self.iteration = it;
        report.gaussians = self.gaussians.len();
        report
    }

    /// PSNR and SSIM of each view rendered over the evaluation background.
    pub fn evaluate(&self, views: &[TrainView]) -> Vec<ViewMetrics> {
        evaluate(&self.gaussians, views, Vec3::from(self.config.eval_background))
    }
}

/// Quality of one rendered view.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ViewMetrics {
    pub name: String,
    pub psnr: f32,
    pub ssim: f32,
}

/// Render every view over `background` and compare with its target.
pub fn evaluate(gs: &GaussianSet, views: &[TrainView], background: Vec3) -> Vec<ViewMetrics> {
    views
        .iter()
        .map(|v| {
            let r = render(gs, &v.camera, &RenderOptions::uniform(background));
            let target = v.target(background);
            ViewMetrics {
                name: v.name.clone(),
                psnr: psnr(&r.image.color, &target),
                ssim: ssim(&r.image.color, &target, r.width as usize, r.height as usize),
            }
        })
        .collect()
}

/// Files of a stage I run folder.
pub struct RunPaths {
    pub dir: PathBuf,
}

impl RunPaths {
    pub fn checkpoint(&self) -> PathBuf {
        self.dir.join("checkpoint.bin")
    }
    pub fn static_ply(&self) -> PathBuf {
        self.dir.join("static.ply")
    }
    pub fn config(&self) -> PathBuf {
        self.dir.join("config.toml")
    }
    pub fn metrics(&self) -> PathBuf {
        self.dir.join("metrics.json")
    }
    pub fn test_dir(&self) -> PathBuf {
        self.dir.join("test")
    }
}

const CHECKPOINT_STAGE: &str = "stage I";

/// Write the trainer's full state atomically.
pub fn save_checkpoint(path: &Path, trainer: &GaussianTrainer, elapsed_s: f64) -> Result<()> {
    crate::train::checkpoint::save(path, CHECKPOINT_STAGE, trainer, elapsed_s)
}

/// Read a checkpoint written by [`save_checkpoint`].
pub fn load_checkpoint(path: &Path) -> Result<(GaussianTrainer, f64)> {
    crate::train::checkpoint::load(path, CHECKPOINT_STAGE, |t: &GaussianTrainer| {
        t.gaussians.check_shapes()?;
        if t.adam.len() != t.gaussians.len() || t.stats.len() != t.gaussians.len() {
            return Err("optimizer or density state does not match the Gaussians".into());
        }
        Ok(())
    })
}

/// Summary written to metrics.json.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct StaticMetrics {
    pub preset: String,
    pub iterations: u32,
    pub gaussians: usize,
    pub mean_psnr: f32,
    pub mean_ssim: f32,
    pub test_views: Vec<ViewMetrics>,
    pub wall_time_s: f64,
    pub peak_rss_mib: Option<f64>,
    pub train_resolution: [u32; 2],
}

/// Peak resident memory of this process (Linux VmHWM), in MiB.
pub fn peak_rss_mib() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib / 1024.0)
}

/// How a run ended.
pub enum RunOutcome {
    Finished(Box<StaticMetrics>),
    /// Stopped by the interrupt flag after writing a checkpoint at this iteration.
    Interrupted(u32),
}

/// Log the training state to rerun: the Gaussians and the first evaluation view
/// rendered beside its target.
fn log_state(viz: &Viz, trainer: &GaussianTrainer, eval: &TrainView) {
    if !viz.is_enabled() {
        return;
    }
    viz.set_iteration(trainer.iteration);
    viz.gaussians("world/gaussians", &trainer.gaussians);
    let bg = Vec3::from(trainer.config.eval_background);
    let r = render(&trainer.gaussians, &eval.camera, &RenderOptions::uniform(bg));
    viz.camera("world/eval_camera", &eval.camera);
    viz.image_rgb("world/eval_camera/render", r.width, r.height, &r.image.color);
    viz.image_rgb("eval/target", r.width, r.height, &eval.target(bg));
    viz.image_rgb("eval/render", r.width, r.height, &r.image.color);
}

/// Where a stage I run lives and how it starts.
pub struct RunSetup<'a> {
    pub run_dir: &'a Path,
    /// Continue from the run folder's checkpoint.
    pub resume: bool,
    /// Initial points (a fresh run only); None = random points in the configured box.
    pub init: Option<&'a PointCloud>,
    /// The rasterizer to train with.
    pub backend: Backend,
    /// More training views arriving while it trains (a live session's scan), in
    /// order; the set is complete when their sender is dropped. Iteration i trains
    /// on the first `1 + i / ITERATIONS_PER_ARRIVING_VIEW` views (waiting for them
    /// when they have not arrived), so the result does not depend on when they did.
    pub arriving: Option<&'a crossbeam_channel::Receiver<TrainView>>,
}

/// Iterations trained per view of a scan that arrives while stage I trains: the
/// cpu preset's 3000 iterations take in up to 750 views (a 50 s scan at 15 fps; the
/// session's frame store keeps at most 512 before it thins out), and at ~50
/// iterations a second the trainer asks for 12.5 frames a second, about what a
/// capture delivers (a slower one makes it wait). With 10, a scan's frames past
/// the 300th were never trained on.
pub const ITERATIONS_PER_ARRIVING_VIEW: u32 = 4;

/// The training views of a run whose scan arrives while it trains.
struct ArrivingViews<'a> {
    views: &'a crossbeam_channel::Receiver<TrainView>,
    closed: bool,
}

impl ArrivingViews<'_> {
    /// How many of `train` iteration `iteration` may train on, after taking in
    /// (waiting for) the views it needs; the scene extent follows the cameras.
    fn admit(&mut self, train: &mut Vec<TrainView>, trainer: &mut GaussianTrainer, iteration: u32) -> usize {
        let allowed = 1 + (iteration / ITERATIONS_PER_ARRIVING_VIEW) as usize;
        let before = train.len();
        while train.len() < allowed && !self.closed {
            match self.views.recv() {
                Ok(v) => train.push(v),
                Err(_) => self.closed = true,
            }
        }
        if train.len() > before {
            trainer.extent = camera_extent(train);
        }
        allowed.min(train.len())
    }
}

/// Train stage I into `run_dir`: resume from its checkpoint if asked, checkpoint
/// every `checkpoint_interval` iterations and when `interrupt` is raised, log to
/// `viz`, and on completion write static.ply, config.toml, test renders and
/// metrics.json.
pub fn run_static(
    config: StaticConfig,
    train: &[TrainView],
    test: &[TrainView],
    setup: &RunSetup,
    interrupt: &AtomicBool,
    viz: &Viz,
    mut progress: impl FnMut(&StepReport),
) -> Result<RunOutcome> {
    let run_dir = setup.run_dir;
    std::fs::create_dir_all(run_dir).map_err(|e| Error::io(run_dir, e))?;
    let paths = RunPaths { dir: run_dir.to_path_buf() };
    let (mut trainer, mut elapsed_before) = if setup.resume && paths.checkpoint().exists() {
        let (t, e) = load_checkpoint(&paths.checkpoint())?;
        if t.config != config {
            return Err(Error::Config(format!(
                "{} was written with a different configuration; resume with the same preset/config or start a new run",
                paths.checkpoint().display()
            )));
        }
        tracing::info!(iteration = t.iteration, "resuming from {}", paths.checkpoint().display());
        (t, e)
    } else {
        (GaussianTrainer::new(config.clone(), train, setup.init)?, 0.0)
    };
    trainer.backend = setup.backend.clone();
    tracing::info!(backend = trainer.backend.describe(), "stage I");
    let toml_text = toml::to_string(&config).map_err(|e| Error::Other(e.to_string()))?;
    write_atomic(&paths.config(), toml_text.as_bytes())?;

    let mut arriving = setup.arriving.map(|views| ArrivingViews { views, closed: false });
    let mut train: std::borrow::Cow<[TrainView]> = std::borrow::Cow::Borrowed(train);
    if viz.is_enabled() {
        let eval_views = if test.is_empty() { &train[..] } else { test };
        viz.set_iteration(trainer.iteration);
        for (i, v) in train.iter().enumerate() {
            viz.camera(&format!("world/train_cameras/{i:03}"), &v.camera);
        }
        log_state(viz, &trainer, &eval_views[0]);
    }
    let start = Instant::now();
    while trainer.iteration < config.iterations {
        if interrupt.load(Ordering::SeqCst) {
            save_checkpoint(&paths.checkpoint(), &trainer, elapsed_before + start.elapsed().as_secs_f64())?;
            return Ok(RunOutcome::Interrupted(trainer.iteration));
        }
        let usable = match &mut arriving {
            None => train.len(),
            Some(a) => {
                let iteration = trainer.iteration;
                a.admit(train.to_mut(), &mut trainer, iteration)
            }
        };
        let report = trainer.step(&train[..usable]);
        if let Some(bad) = trainer.gaussians.first_non_finite() {
            return Err(Error::Other(format!(
                "training diverged at iteration {}: non-finite {:?}",
                report.iteration, bad
            )));
        }
        progress(&report);
        if viz.is_enabled() && report.iteration % 10 == 0 {
            viz.set_iteration(report.iteration);
            viz.scalar("train/loss", f64::from(report.loss));
            viz.scalar("train/psnr", f64::from(report.psnr));
            viz.scalar("train/gaussians", report.gaussians as f64);
        }
        if config.viz_interval > 0 && report.iteration % config.viz_interval == 0 {
            log_state(viz, &trainer, if test.is_empty() { &train[0] } else { &test[0] });
        }
        if config.checkpoint_interval > 0 && trainer.iteration % config.checkpoint_interval == 0 {
            save_checkpoint(&paths.checkpoint(), &trainer, elapsed_before + start.elapsed().as_secs_f64())?;
        }
    }
    elapsed_before += start.elapsed().as_secs_f64();
    save_checkpoint(&paths.checkpoint(), &trainer, elapsed_before)?;
    crate::splat::ply::write_ply(&paths.static_ply(), &trainer.gaussians)?;

    let eval_views = if test.is_empty() { &train[..] } else { test };
    let metrics = trainer.evaluate(eval_views);
    std::fs::create_dir_all(paths.test_dir()).map_err(|e| Error::io(paths.test_dir(), e))?;
    let bg = Vec3::from(config.eval_background);
    for (i, v) in eval_views.iter().enumerate() {
        let r = render(&trainer.gaussians, &v.camera, &RenderOptions::uniform(bg));
        let mut bytes = Vec::new();
        image::DynamicImage::ImageRgb8(r.to_rgb8())
            .write_to(&mut std::io::Cursor::new(&mut bytes), image::ImageFormat::Png)
            .map_err(|e| Error::Other(format!("encoding test render: {e}")))?;
        write_atomic(&paths.test_dir().join(format!("{i:03}.png")), &bytes)?;
    }
    let n = metrics.len().max(1) as f32;
    let summary = StaticMetrics {
        preset: config.preset.clone(),
        iterations: trainer.iteration,
        gaussians: trainer.gaussians.len(),
        mean_psnr: metrics.iter().map(|m| m.psnr).sum::<f32>() / n,
        mean_ssim: metrics.iter().map(|m| m.ssim).sum::<f32>() / n,
        test_views: metrics,
        wall_time_s: elapsed_before,
        peak_rss_mib: peak_rss_mib(),
        train_resolution: [train[0].width(), train[0].height()],
    };
    let json = serde_json::to_vec_pretty(&summary).map_err(|e| Error::Other(e.to_string()))?;
    write_atomic(&paths.metrics(), &json)?;
    log_state(viz, &trainer, &eval_views[0]);
    viz.scalar("eval/mean_psnr", f64::from(summary.mean_psnr));
    viz.flush();
    Ok(RunOutcome::Finished(Box::new(summary)))
}
