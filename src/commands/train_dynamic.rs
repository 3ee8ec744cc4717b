//! `aim train-dynamic DATASET --static STATIC.ply --out RUN [--preset cpu|paper]`:
//! stage II on the motion video, then stage III on the moving set; prints the
//! joints and, when the dataset has ground truth (gt/joints.json), their errors.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context};
use indicatif::{ProgressBar, ProgressStyle};

use aim::eval::{match_joints, ArticulationReport, GtJoint, PredictedJoint};
use aim::motion::JointKind;
use aim::train::dynamic_stage::{DualTrainer, DynamicConfig, PartEstimate};
use aim_capture::Phase;

#[derive(clap::Args)]
pub struct Args {
    /// Dataset in the AiM layout (trains on motion/transforms_train.json).
    pub dataset: PathBuf,
    /// The start-state Gaussians from stage I (RUN/static.ply).
    #[arg(long = "static")]
    pub static_ply: PathBuf,
    /// Output folder (moving.ply, static_pruned.ply, deform.bin, joints.json).
    #[arg(long)]
    pub out: PathBuf,
    #[arg(long, default_value = "cpu")]
    pub preset: String,
    #[arg(long)]
    pub iterations: Option<u32>,
    #[arg(long)]
    pub seed: Option<u64>,
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

/// Train stages II and III; returns the parts and the report against GT if any.
pub fn train_and_analyse(
    dataset: &Path,
    static_ply: &Path,
    out: &Path,
    cfg: DynamicConfig,
) -> anyhow::Result<(Vec<PartEstimate>, Option<ArticulationReport>)> {
    let (views, test) = super::train_static::load_phase_views(dataset, Phase::Motion, cfg.resolution)?;
    let static_gs = aim::splat::ply::read_ply(static_ply)?;
    let iterations = cfg.iterations;
    let mut trainer = DualTrainer::new(cfg, static_gs, &views)?;
    let bar = ProgressBar::new(u64::from(iterations));
    bar.set_style(
        ProgressStyle::with_template("{bar:30} {pos}/{len} [{elapsed_precise}<{eta_precise}] {msg}").expect("template"),
    );
    while trainer.iteration < iterations {
        let s = trainer.step(&views);
        if let Some(bad) = trainer.moving.gaussians.first_non_finite() {
            bail!("stage II diverged at iteration {}: non-finite {bad:?}", s.iteration);
        }
        bar.set_position(u64::from(s.iteration));
        if s.iteration % 20 == 0 {
            bar.set_message(format!(
                "psnr {:.2} static {} moving {}{}",
                s.psnr,
                s.static_count,
                s.moving_count,
                if s.sdmd_moved > 0 { format!(" (SDMD moved {})", s.sdmd_moved) } else { String::new() }
            ));
        }
    }
    bar.finish_and_clear();
    if !test.is_empty() {
        println!("    motion test PSNR {:.2} dB over {} held-out frames", trainer.evaluate(&test), test.len());
    }
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    aim::splat::ply::write_ply(&out.join("moving.ply"), &trainer.moving.gaussians)?;
    aim::splat::ply::write_ply(&out.join("static_pruned.ply"), &trainer.static_set.gaussians)?;
    let net = postcard::to_stdvec(&trainer.net).context("encoding the deformation network")?;
    aim::error::write_atomic(&out.join("deform.bin"), &net)?;
    let (parts, _) = trainer.analyse();
    let joints: Vec<_> = parts.iter().map(|p| (p.members.len(), p.joint)).collect();
    aim::error::write_atomic(&out.join("joints.json"), &serde_json::to_vec_pretty(&joints)?)?;
    let report = load_gt(dataset)?.map(|gt| {
        let pred: Vec<PredictedJoint> = parts
            .iter()
            .map(|p| PredictedJoint { joint: p.joint, rotation: p.motion.r, translation: p.motion.t })
            .collect();
        match_joints(&pred, &gt)
    });
    Ok((parts, report))
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
    let mut cfg = DynamicConfig::preset(&args.preset)?;
    if let Some(n) = args.iterations {
        cfg.iterations = n;
    }
    if let Some(s) = args.seed {
        cfg.seed = s;
    }
    let (parts, report) = train_and_analyse(&args.dataset, &args.static_ply, &args.out, cfg)?;
    print_joints(&parts, report.as_ref());
    Ok(())
}
