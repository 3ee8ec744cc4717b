//! `aim train-static DATASET --out RUN [--preset cpu|paper] [--config FILE] [--resume]`

use std::path::{Path, PathBuf};

use anyhow::bail;

use aim::splat::ply::PointCloud;
use aim::train::config::{StageConfig, StaticConfig};
use aim::train::static_stage::{run_static, RunOutcome, RunSetup};
use aim::train::views::load_phase_views;
use aim_capture::Phase;

#[derive(clap::Args)]
pub struct Args {
    /// Dataset in the AiM layout (trains on start/transforms_train.json, evaluates on start/transforms_test.json).
    pub dataset: PathBuf,
    /// Run folder (static.ply, config.toml, metrics.json, test/, checkpoint.bin).
    #[arg(long)]
    pub out: PathBuf,
    /// Configuration preset.
    #[arg(long, default_value = "cpu")]
    pub preset: String,
    /// TOML file overriding preset values (its own `preset` key picks the base).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Continue from RUN/checkpoint.bin.
    #[arg(long)]
    pub resume: bool,
    /// Initial points instead of random ones: a point-cloud PLY (x y z [red green blue])
    /// or a COLMAP sparse model folder (cameras, images, points3D; .bin or .txt).
    #[arg(long, value_name = "PLY|COLMAP_DIR")]
    pub init_points: Option<PathBuf>,
    /// Override the seed.
    #[arg(long)]
    pub seed: Option<u64>,
    /// Override the iteration count.
    #[arg(long)]
    pub iterations: Option<u32>,
    /// Rasterizer: cpu, gpu or auto (see `aim render --help`).
    #[arg(long, default_value = "cpu")]
    pub backend: aim::render::BackendChoice,
    #[command(flatten)]
    pub rerun: RerunArgs,
}

/// Where to send the rerun log (none by default).
#[derive(clap::Args, Clone, Debug, Default)]
pub struct RerunArgs {
    /// Save a rerun recording of the run (.rrd; open with `rerun FILE`).
    #[arg(long, value_name = "FILE.rrd", visible_alias = "rerun")]
    pub rrd: Option<PathBuf>,
    /// Stream to a running rerun viewer, e.g. rerun+http://127.0.0.1:9876/proxy.
    #[arg(long, value_name = "URL", conflicts_with = "rrd")]
    pub rerun_connect: Option<String>,
}

impl RerunArgs {
    pub fn open(&self) -> anyhow::Result<aim::viz::Viz> {
        let target = match (&self.rrd, &self.rerun_connect) {
            (Some(p), _) => aim::viz::VizTarget::File(p.clone()),
            (None, Some(url)) => aim::viz::VizTarget::Connect(url.clone()),
            (None, None) => aim::viz::VizTarget::Off,
        };
        Ok(aim::viz::Viz::new("aim", &target)?)
    }
}

/// Initial points from a PLY point cloud or a COLMAP sparse model folder.
pub fn load_init_points(path: &Path) -> anyhow::Result<PointCloud> {
    let cloud = if path.is_dir() {
        let model = aim_capture::dataset::read_colmap_model(path)?;
        PointCloud {
            points: model.point_positions(),
            colors: Some(model.points.iter().map(|p| glam::Vec3::from(p.rgb.map(|c| f32::from(c) / 255.0))).collect()),
        }
    } else {
        aim::splat::ply::read_point_cloud(path)?
    };
    if cloud.points.is_empty() {
        bail!("{}: the point cloud has no points", path.display());
    }
    tracing::info!(points = cloud.points.len(), "initial points from {}", path.display());
    Ok(cloud)
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let cfg = StaticConfig::resolve(args.config.as_deref(), &args.preset, args.seed, args.iterations)?;
    let (train, test) = load_phase_views(&args.dataset, Phase::Scan, cfg.resolution, cfg.depth_weight > 0.0)?;
    tracing::info!(
        train = train.len(),
        test = test.len(),
        width = train[0].width(),
        height = train[0].height(),
        preset = %cfg.preset,
        "stage I"
    );
    let interrupt = super::progress::interrupt_on_ctrl_c();
    let bar = super::progress::Progress::new("stage I", cfg.iterations);
    let mut ema_psnr = 0.0f32;
    let viz = args.rerun.open()?;
    let init = args.init_points.as_deref().map(load_init_points).transpose()?;
    let setup = RunSetup {
        run_dir: &args.out,
        resume: args.resume,
        init: init.as_ref(),
        arriving: None,
        backend: aim::render::Backend::open(args.backend)?,
    };
    let outcome = run_static(cfg, &train, &test, &setup, &interrupt, &viz, |r| {
        ema_psnr = if ema_psnr == 0.0 { r.psnr } else { 0.9 * ema_psnr + 0.1 * r.psnr };
        bar.update(r.iteration, || format!("loss {:.4} psnr {:.2} gaussians {}", r.loss, ema_psnr, r.gaussians));
    })?;
    bar.finish();
    match outcome {
        RunOutcome::Finished(m) => {
            println!(
                "stage I done: {} iterations, {} Gaussians, test PSNR {:.2} dB, SSIM {:.4}, {:.1} s, peak RSS {:.0} MiB",
                m.iterations,
                m.gaussians,
                m.mean_psnr,
                m.mean_ssim,
                m.wall_time_s,
                m.peak_rss_mib.unwrap_or(f64::NAN)
            );
            println!("wrote {}", args.out.join("static.ply").display());
            Ok(())
        }
        RunOutcome::Interrupted(it) => {
            bail!("interrupted at iteration {it}; checkpoint written, continue with --resume")
        }
    }
}
