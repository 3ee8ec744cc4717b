//! The stage II + III run loop: train the dual Gaussians on a dataset's motion
//! video (checkpointing, resuming, interrupt, rerun logging), then find the
//! parts and joints, write the outputs and the twin, and with ground truth
//! match the joints. Batch commands, the benchmark suite and tests call this.

use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use serde::{Deserialize, Serialize};

use super::dynamic_stage::{
    load_checkpoint, save_checkpoint, DualTrainer, DynamicConfig, DynamicStep, PartEstimate, StageTwoViews,
};
use super::static_stage::peak_rss_mib;
use super::views::load_phase_views;
use crate::error::{write_atomic, Error, Result};
use crate::eval::{match_joints, ArticulationReport, PredictedJoint};
use crate::export::{write_twin, TwinPart};
use crate::mesh::tsdf::TsdfConfig;
use crate::viz::Viz;
use aim_capture::Phase;

/// Where a stage II run continues from and when it stops early.
pub struct RunControl<'a> {
    /// Continue from OUT/checkpoint.bin when it exists.
    pub resume: bool,
    /// Raised (Ctrl-C) to checkpoint and stop.
    pub interrupt: &'a AtomicBool,
    /// Rerun log: scalars every 10 iterations; the static set and the moving set
    /// at t = 0, 0.5, 1 at every checkpoint; the parts at the end.
    pub viz: &'a Viz,
}

/// One moving part as metrics.json lists it.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct PartSummary {
    pub kind: crate::motion::JointKind,
    pub axis: [f64; 3],
    pub pivot: [f64; 3],
    /// Radians (revolute) or metres (prismatic).
    pub amount: f64,
    pub gaussians: usize,
}

/// metrics.json of a stage II run.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct DynamicMetrics {
    pub preset: String,
    pub iterations: u32,
    /// Mean PSNR over the held-out motion frames (None without any).
    pub motion_test_psnr: Option<f32>,
    pub static_gaussians: usize,
    pub moving_gaussians: usize,
    /// Wall time of the training and analysis, summed over resumes.
    pub wall_time_s: f64,
    pub peak_rss_mib: Option<f64>,
    pub parts: Vec<PartSummary>,
    /// With ground truth (gt/joints.json): the matched joints' errors.
    pub gt_report: Option<ArticulationReport>,
}

/// How a stage II run ended.
pub enum DynamicOutcome {
    Finished {
        parts: Vec<PartEstimate>,
        metrics: Box<DynamicMetrics>,
    },
    /// Stopped by the interrupt flag after writing a checkpoint at this iteration.
    Interrupted(u32),
}

/// Log the two sets to rerun (the moving one at three times of the motion).
fn log_sets(viz: &Viz, trainer: &DualTrainer) {
    if !viz.is_enabled() {
        return;
    }
    viz.gaussians("stage2/static", &trainer.static_set.gaussians);
    for (name, t) in [("t0", 0.0), ("t05", 0.5), ("t1", 1.0)] {
        viz.gaussians(&format!("stage2/moving/{name}"), &trainer.moving_at(t));
    }
}

fn log_step(viz: &Viz, s: &DynamicStep) {
    viz.set_iteration(s.iteration);
    viz.scalar("stage2/loss", f64::from(s.loss));
    viz.scalar("stage2/psnr", f64::from(s.psnr));
    viz.scalar("stage2/static_gaussians", s.static_count as f64);
    viz.scalar("stage2/moving_gaussians", s.moving_count as f64);
    viz.scalar("stage2/sdmd_moved", s.sdmd_moved as f64);
}

/// Train stages II and III on `dataset` from the start-state Gaussians in
/// `static_ply` into `out`: moving.ply, static_pruned.ply, deform.bin,
/// checkpoint.bin, metrics.json and the twin in out/twin (meshes by `mesh`).
pub fn run_dynamic(
    dataset: &Path,
    static_ply: &Path,
    out: &Path,
    cfg: DynamicConfig,
    mesh: &TsdfConfig,
    control: &RunControl,
    mut progress: impl FnMut(&DynamicStep),
) -> Result<DynamicOutcome> {
    let (motion, test) = load_phase_views(dataset, Phase::Motion, cfg.resolution)?;
    let (start, _) = load_phase_views(dataset, Phase::Scan, cfg.resolution)?;
    // The end state is optional: a capture may stop right after the motion.
    let end = if dataset.join("end").join("transforms_train.json").exists() {
        load_phase_views(dataset, Phase::After, cfg.resolution)?.0
    } else {
        Vec::new()
    };
    let views = StageTwoViews::new(motion, start, end)?;
    std::fs::create_dir_all(out).map_err(|e| Error::io(out, e))?;
    let checkpoint = out.join("checkpoint.bin");
    let (mut trainer, elapsed_before) = if control.resume && checkpoint.exists() {
        let (t, elapsed) = load_checkpoint(&checkpoint)?;
        if t.config != cfg {
            tracing::warn!("{}: trained with another configuration; continuing with its own", checkpoint.display());
        }
        tracing::info!(iteration = t.iteration, "resuming from {}", checkpoint.display());
        (t, elapsed)
    } else {
        (DualTrainer::new(cfg, crate::splat::ply::read_ply(static_ply)?, &views)?, 0.0)
    };
    let started = Instant::now();
    let elapsed = |started: &Instant| elapsed_before + started.elapsed().as_secs_f64();
    let (iterations, interval) = (trainer.config.iterations, trainer.config.checkpoint_interval);
    while trainer.iteration < iterations {
        if control.interrupt.load(Ordering::SeqCst) {
            save_checkpoint(&checkpoint, &trainer, elapsed(&started))?;
            return Ok(DynamicOutcome::Interrupted(trainer.iteration));
        }
        let s = trainer.step(&views);
        if s.iteration.is_multiple_of(10) || s.sdmd_moved > 0 {
            log_step(control.viz, &s);
        }
        // The last iteration's checkpoint and sets are written after the loop.
        if interval > 0 && s.iteration.is_multiple_of(interval) && s.iteration < iterations {
            save_checkpoint(&checkpoint, &trainer, elapsed(&started))?;
            log_sets(control.viz, &trainer);
        }
        if let Some(bad) = trainer.moving.gaussians.first_non_finite() {
            return Err(Error::Other(format!("stage II diverged at iteration {}: non-finite {bad:?}", s.iteration)));
        }
        if s.sdmd_moved > 0 {
            tracing::info!(
                iteration = s.iteration,
                moved = s.sdmd_moved,
                "SDMD handed motionless groups to the static set"
            );
        }
        progress(&s);
    }
    save_checkpoint(&checkpoint, &trainer, elapsed(&started))?;
    let motion_test_psnr = (!test.is_empty()).then(|| trainer.evaluate(&test));
    crate::splat::ply::write_ply(&out.join("moving.ply"), &trainer.moving.gaussians)?;
    crate::splat::ply::write_ply(&out.join("static_pruned.ply"), &trainer.static_set.gaussians)?;
    let net = postcard::to_stdvec(&trainer.net)
        .map_err(|e| Error::Other(format!("encoding the deformation network: {e}")))?;
    write_atomic(&out.join("deform.bin"), &net)?;
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
    write_twin(&out.join("twin"), &twin, mesh)?;
    log_sets(control.viz, &trainer);
    for (k, g) in part_sets.iter().enumerate() {
        control.viz.gaussians(&format!("stage3/part_{}", k + 1), g);
    }
    control.viz.flush();
    let gt_path = dataset.join("gt").join("joints.json");
    let gt_report = if gt_path.exists() {
        let gt: Vec<_> =
            crate::synth::JointsFile::load(&gt_path)?.joints.iter().map(crate::eval::twin::gt_joint).collect();
        let pred: Vec<PredictedJoint> = parts
            .iter()
            .map(|p| PredictedJoint { joint: p.joint, rotation: p.motion.r, translation: p.motion.t })
            .collect();
        Some(match_joints(&pred, &gt))
    } else {
        None
    };
    let metrics = DynamicMetrics {
        preset: trainer.config.preset.clone(),
        iterations: trainer.iteration,
        motion_test_psnr,
        static_gaussians: trainer.static_set.gaussians.len(),
        moving_gaussians: trainer.moving.gaussians.len(),
        wall_time_s: elapsed(&started),
        peak_rss_mib: peak_rss_mib(),
        parts: parts
            .iter()
            .map(|p| PartSummary {
                kind: p.joint.kind,
                axis: p.joint.axis.to_array(),
                pivot: p.joint.origin.to_array(),
                amount: p.joint.amount,
                gaussians: p.members.len(),
            })
            .collect(),
        gt_report,
    };
    let json = serde_json::to_vec_pretty(&metrics).map_err(|e| Error::Other(e.to_string()))?;
    write_atomic(&out.join("metrics.json"), &json)?;
    Ok(DynamicOutcome::Finished { parts, metrics: Box::new(metrics) })
}
