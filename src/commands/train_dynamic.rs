//! `aim train-dynamic DATASET --static STATIC.ply --out RUN [--preset cpu|paper]`:
//! stage II on the motion video, then stage III on the moving set; prints the
//! joints and, when the dataset has ground truth (gt/joints.json), their errors.

use std::path::{Path, PathBuf};

use aim::eval::ArticulationReport;
use aim::mesh::tsdf::TsdfConfig;
use aim::motion::JointKind;
use aim::train::config::StageConfig;
use aim::train::dynamic_run::{
    run_dynamic, DynamicMetrics, DynamicOutcome, RunControl, StageTwoInput, StageTwoProgress,
};
use aim::train::dynamic_stage::{DynamicConfig, PartEstimate};

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
    /// Where stage II renders (and the paper preset's deformation network runs):
    /// cpu, gpu or auto (see `aim render --help`).
    #[arg(long, default_value = "cpu")]
    pub backend: aim::render::BackendChoice,
    #[command(flatten)]
    pub rerun: super::train_static::RerunArgs,
}

/// Train stages II and III with a progress bar; None when interrupted (after
/// writing the checkpoint, which the message names).
pub fn train_with_progress(
    dataset: &Path,
    static_ply: &Path,
    out: &Path,
    cfg: DynamicConfig,
    control: &RunControl,
) -> anyhow::Result<Option<(Vec<PartEstimate>, Box<DynamicMetrics>)>> {
    let bar = super::progress::Progress::new("stage II", cfg.iterations);
    let input = StageTwoInput::load(dataset, &cfg)?;
    let outcome = run_dynamic(input, static_ply, out, cfg, &TsdfConfig::default(), control, |p| {
        if let StageTwoProgress::Step(s) = p {
            bar.update(s.iteration, || {
                format!("psnr {:.2} static {} moving {}", s.psnr, s.static_count, s.moving_count)
            });
        }
    })?;
    bar.finish();
    match outcome {
        DynamicOutcome::Finished { parts, metrics } => {
            if let Some(psnr) = metrics.motion_test_psnr {
                println!("    motion test PSNR {psnr:.2} dB");
            }
            println!(
                "    wrote the twin to {} (articulation.json, object.urdf, parts/, meshes/)",
                out.join("twin").display()
            );
            Ok(Some((parts, metrics)))
        }
        DynamicOutcome::Interrupted(it) => {
            println!(
                "interrupted at iteration {it}; checkpoint written to {} (continue with --resume)",
                out.join("checkpoint.bin").display()
            );
            Ok(None)
        }
    }
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
    let control = RunControl {
        resume: args.resume,
        interrupt: &interrupt,
        viz: &viz,
        backend: aim::render::Backend::open(args.backend)?,
    };
    if let Some((parts, metrics)) = train_with_progress(&args.dataset, &args.static_ply, &args.out, cfg, &control)? {
        print_joints(&parts, metrics.gt_report.as_ref());
    }
    Ok(())
}
