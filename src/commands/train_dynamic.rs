//! `aim train-dynamic DATASET --static STATIC.ply --out RUN [--preset cpu|paper]`:
//! stage II on the motion video, then stage III on the moving set; prints the
//! joints and, when the dataset has ground truth (gt/joints.json), their errors.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context};

use aim::eval::{match_joints, ArticulationReport, GtJoint, PredictedJoint};
use aim::export::{write_twin, TwinPart};
use aim::motion::JointKind;
use std::sync::atomic::{AtomicBool, Ordering};

use aim::train::config::StageConfig;
use aim::train::dynamic_stage::{
    load_checkpoint, save_checkpoint, DualTrainer, DynamicConfig, PartEstimate, StageTwoViews,
};
use aim_capture::Phase;

#[derive(clap::Args)]
pub struct Args {
    /// Dataset in the AiM layout (trains on motion/transforms_train.json).
    pub dataset: PathBuf,
    /// The start-state Gaussians from stage I (RUN/static.ply).
    #[arg(long = "static")]
    pub static_ply: PathBuf,
    /// Output folder (moving.ply, static_pruned.ply, deform.bin, checkpoint.bin, and
    /// twin/: articulation.json, object.urdf, parts/part_K.ply).
    #[arg(long)]
    pub out: PathBuf,
    #[arg(long, default_value = "cpu")]
    pub preset: String,
    /// TOML over a preset (it names its `preset`; any key of docs/training.md's stage II table).
    #[arg(long)]
    pub config: Option<PathBuf>,
    #[arg(long)]
    pub iterations: Option<u32>,
    #[arg(long)]
    pub seed: Option<u64>,
    /// Continue from OUT/checkpoint.bin (written every `checkpoint_interval` iterations and on Ctrl-C).
    #[arg(long)]
    pub resume: bool,
    #[command(flatten)]
    pub rerun: super::train_static::RerunArgs,
}

/// Ground-truth joints of a synthetic dataset, if it has them.
pub fn load_gt(dataset: &Path) -> anyhow::Result<Option<Vec<GtJoint>>> {
    let path = dataset.join("gt").join("joints.json");
    if !path.exists() {
        return Ok(None);
    }
    let file = aim::synth::JointsFile::load(&path)?;
    Ok(Some(
        file.joints
            .iter()
            .map(|j| GtJoint {
                part: j.part,
                kind: match j.kind {
                    aim::synth::JointType::Revolute => JointKind::Revolute,
                    aim::synth::JointType::Prismatic => JointKind::Prismatic,
                },
                axis: glam::Vec3::from(j.axis).as_dvec3(),
                origin: glam::Vec3::from(j.origin).as_dvec3(),
                range: [f64::from(j.range[0]), f64::from(j.range[1])],
            })
            .collect(),
    ))
}

/// Where a stage II run continues from and when it stops early.
pub struct RunControl<'a> {
    /// Continue from OUT/checkpoint.bin when it exists.
    pub resume: bool,
    /// Raised (Ctrl-C) to checkpoint and stop.
    pub interrupt: &'a AtomicBool,
    /// Rerun log: scalars every 10 iterations; the static set and the moving set
    /// at t = 0, 0.5, 1 at every checkpoint; the parts at the end.
    pub viz: &'a aim::viz::Viz,
}

/// Log the two sets to rerun (the moving one at three times of the motion).
fn log_sets(viz: &aim::viz::Viz, trainer: &DualTrainer) {
    if !viz.is_enabled() {
        return;
    }
    viz.gaussians("stage2/static", &trainer.static_set.gaussians);
    for (name, t) in [("t0", 0.0), ("t05", 0.5), ("t1", 1.0)] {
        viz.gaussians(&format!("stage2/moving/{name}"), &trainer.moving_at(t));
    }
}

/// Train stages II and III into `out`, checkpointing as configured; returns the
/// parts and the report against GT if any, or None when interrupted (after
/// writing the checkpoint).
pub fn train_and_analyse(
    dataset: &Path,
    static_ply: &Path,
    out: &Path,
    cfg: DynamicConfig,
    control: &RunControl,
) -> anyhow::Result<Option<(Vec<PartEstimate>, Option<ArticulationReport>)>> {
    let (motion, test) = super::train_static::load_phase_views(dataset, Phase::Motion, cfg.resolution)?;
    let (start, _) = super::train_static::load_phase_views(dataset, Phase::Scan, cfg.resolution)?;
    // The end state is optional: a capture may stop right after the motion.
    let end = if dataset.join("end").join("transforms_train.json").exists() {
        super::train_static::load_phase_views(dataset, Phase::After, cfg.resolution)?.0
    } else {
        Vec::new()
    };
    let views = StageTwoViews::new(motion, start, end)?;
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let checkpoint = out.join("checkpoint.bin");
    let mut trainer = if control.resume && checkpoint.exists() {
        let (t, _) = load_checkpoint(&checkpoint)?;
        if t.config != cfg {
            tracing::warn!("{}: trained with another configuration; continuing with its own", checkpoint.display());
        }
        tracing::info!(iteration = t.iteration, "resuming from {}", checkpoint.display());
        t
    } else {
        DualTrainer::new(cfg, aim::splat::ply::read_ply(static_ply)?, &views)?
    };
    let (iterations, interval) = (trainer.config.iterations, trainer.config.checkpoint_interval);
    let bar = super::progress::Progress::new("stage II", iterations);
    while trainer.iteration < iterations {
        if control.interrupt.load(Ordering::SeqCst) {
            bar.finish();
            save_checkpoint(&checkpoint, &trainer, 0.0)?;
            println!(
                "interrupted at iteration {}; checkpoint written to {} (continue with --resume)",
                trainer.iteration,
                checkpoint.display()
            );
            return Ok(None);
        }
        let s = trainer.step(&views);
        if s.iteration.is_multiple_of(10) || s.sdmd_moved > 0 {
            control.viz.set_iteration(s.iteration);
            control.viz.scalar("stage2/loss", f64::from(s.loss));
            control.viz.scalar("stage2/psnr", f64::from(s.psnr));
            control.viz.scalar("stage2/static_gaussians", s.static_count as f64);
            control.viz.scalar("stage2/moving_gaussians", s.moving_count as f64);
            control.viz.scalar("stage2/sdmd_moved", s.sdmd_moved as f64);
        }
        // The last iteration's checkpoint and sets are written after the loop.
        if interval > 0 && s.iteration.is_multiple_of(interval) && s.iteration < iterations {
            save_checkpoint(&checkpoint, &trainer, 0.0)?;
            log_sets(control.viz, &trainer);
        }
        if let Some(bad) = trainer.moving.gaussians.first_non_finite() {
            bail!("stage II diverged at iteration {}: non-finite {bad:?}", s.iteration);
        }
        if s.sdmd_moved > 0 {
            tracing::info!(
                iteration = s.iteration,
                moved = s.sdmd_moved,
                "SDMD handed motionless groups to the static set"
            );
        }
        bar.update(s.iteration, || format!("psnr {:.2} static {} moving {}", s.psnr, s.static_count, s.moving_count));
    }
    bar.finish();
    save_checkpoint(&checkpoint, &trainer, 0.0)?;
    if !test.is_empty() {
        println!("    motion test PSNR {:.2} dB over {} held-out frames", trainer.evaluate(&test), test.len());
    }
    aim::splat::ply::write_ply(&out.join("moving.ply"), &trainer.moving.gaussians)?;
    aim::splat::ply::write_ply(&out.join("static_pruned.ply"), &trainer.static_set.gaussians)?;
    let net = postcard::to_stdvec(&trainer.net).context("encoding the deformation network")?;
    aim::error::write_atomic(&out.join("deform.bin"), &net)?;
    let (parts, _) = trainer.analyse();
    // The twin: the pruned static set as the base, each part's moving Gaussians at t = 0.
    let start_pose = trainer.moving_at(0.0);
    let part_sets: Vec<_> = parts
        .iter()
        .map(|p| {
            let mut keep = vec![false; start_pose.len()];
            p.members.iter().for_each(|&i| keep[i] = true);
            start_pose.subset(&keep)
        })
        .collect();
    let twin: Vec<TwinPart> = std::iter::once(TwinPart { gaussians: &trainer.static_set.gaussians, joint: None })
        .chain(parts.iter().zip(&part_sets).map(|(p, g)| TwinPart { gaussians: g, joint: Some(p.joint) }))
        .collect();
    write_twin(&out.join("twin"), &twin)?;
    log_sets(control.viz, &trainer);
    for (k, g) in part_sets.iter().enumerate() {
        control.viz.gaussians(&format!("stage3/part_{}", k + 1), g);
    }
    control.viz.flush();
    println!("    wrote the twin to {} (articulation.json, object.urdf, parts/)", out.join("twin").display());
    let report = load_gt(dataset)?.map(|gt| {
        let pred: Vec<PredictedJoint> = parts
            .iter()
            .map(|p| PredictedJoint { joint: p.joint, rotation: p.motion.r, translation: p.motion.t })
            .collect();
        match_joints(&pred, &gt)
    });
    Ok(Some((parts, report)))
}

/// Print the estimated joints and, with ground truth, their errors.
pub fn print_joints(parts: &[PartEstimate], report: Option<&ArticulationReport>) {
    println!("{} moving part(s) found:", parts.len());
    for (i, p) in parts.iter().enumerate() {
        let amount = match p.joint.kind {
            JointKind::Revolute => format!("{:.1} deg", p.joint.amount.to_degrees()),
            JointKind::Prismatic => format!("{:.3} m", p.joint.amount),
        };
        println!(
            "    part {i}: {:?}, axis {:.3?}, pivot {:.3?}, motion {amount} ({} Gaussians)",
            p.joint.kind,
            p.joint.axis.to_array(),
            p.joint.origin.to_array(),
            p.members.len()
        );
    }
    if let Some(r) = report {
        for e in &r.matched {
            let motion = match e.kind {
                JointKind::Revolute => format!("{:.2} deg", e.part_motion),
                JointKind::Prismatic => format!("{:.4} m", e.part_motion),
            };
            let pos = e.axis_position.map_or(String::new(), |p| format!(", axis position {p:.3} (0.1 m)"));
            println!(
                "    GT part {} <- part {}: axis angle {:.2} deg{pos}, part motion error {motion}",
                e.gt_part, e.predicted, e.axis_angle_deg
            );
        }
        for g in &r.missing {
            println!("    GT part {g}: MISSING (no predicted joint of its type)");
        }
        for p in &r.extra {
            println!("    part {p}: EXTRA (matches no ground-truth joint)");
        }
    }
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let cfg = DynamicConfig::resolve(args.config.as_deref(), &args.preset, args.seed, args.iterations)?;
    let interrupt = super::progress::interrupt_on_ctrl_c();
    let viz = args.rerun.open()?;
    let control = RunControl { resume: args.resume, interrupt: &interrupt, viz: &viz };
    if let Some((parts, report)) = train_and_analyse(&args.dataset, &args.static_ply, &args.out, cfg, &control)? {
        print_joints(&parts, report.as_ref());
    }
    Ok(())
}
