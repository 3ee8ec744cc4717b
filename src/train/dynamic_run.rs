//! The stage II + III run loop of both methods (node tracking, the cpu preset;
//! the dual field, the paper preset): learn the motion on a dataset's motion
//! video (checkpointing, resuming, interrupt, rerun logging), then find the
//! parts and joints, write the outputs and the twin, and with ground truth
//! match the joints. Batch commands, the benchmark suite and tests call this.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use serde::{Deserialize, Serialize};

use super::config::StaticConfig;
use super::dynamic_stage::{
    load_checkpoint, require_times, save_checkpoint, DualTrainer, DynamicConfig, DynamicStep, PartEstimate,
    StageTwoMethod, StageTwoViews,
};
use super::static_stage::{peak_rss_mib, GaussianTrainer};
use super::track::{EndScan, NodePose, NodeTracker};
use super::views::load_phase_views;
use super::views::TrainView;
use crate::error::{write_atomic, Error, Result};
use crate::eval::tracking::{part_composition, tracking_errors, PartComposition, TrackingError};
use crate::eval::twin::GroundTruth;
use crate::eval::{match_joints, ArticulationReport, PredictedJoint};
use crate::export::{write_twin, TwinPart};
use crate::mesh::tsdf::TsdfConfig;
use crate::splat::GaussianSet;
use crate::viz::Viz;
use aim_capture::Phase;

/// What a stage II run reports as it goes.
pub enum StageTwoProgress<'a> {
    /// A training step (dual field) or a tracked segment (node tracking).
    Step(&'a DynamicStep),
    /// The parts and their joints are known; the meshes, the twin's export and
    /// the held-out metrics follow. A live session shows the articulation here.
    Articulated(&'a [PartEstimate]),
}

/// Where a stage II run continues from and when it stops early.
pub struct RunControl<'a> {
    /// Continue from OUT/checkpoint.bin when it exists.
    pub resume: bool,
    /// Raised (Ctrl-C) to checkpoint and stop.
    pub interrupt: &'a AtomicBool,
    /// Rerun log: scalars (every 10 iterations, or every tracked segment); the
    /// sets at t = 0, 0.5, 1 at every checkpoint; the parts at the end.
    pub viz: &'a Viz,
    /// The backend stage II renders with (and the dual field runs its network on).
    pub backend: crate::render::Backend,
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
    /// With ground truth and node tracking: how far the tracked nodes are from
    /// their true positions over the motion, per ground-truth part, as the run
    /// ends (a node left in the base counts as not moving at all).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tracking_error: Option<Vec<TrackingError>>,
    /// The same for the free tracking as it was when the parts were found (up to
    /// `discovery_time`): how well each part was followed before grouping.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tracking_error_at_discovery: Option<Vec<TrackingError>>,
    /// With ground truth: what each part (0 = the static base) is made of, its
    /// start-state Gaussians counted by the ground-truth part they lie on.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub composition: Option<Vec<PartComposition>>,
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

/// What stages II and III learn from, in memory: a dataset's phases, or the
/// frames a session collected from a stream.
pub struct StageTwoInput {
    /// Names the input in messages (a dataset folder, a recording).
    pub source: PathBuf,
    /// Motion frames, each with its time in [0, 1].
    pub motion: Vec<TrainView>,
    /// Held-out motion frames (may be empty).
    pub test: Vec<TrainView>,
    /// The start state's views (the dual field trains on them; node tracking
    /// reads their cameras for revealed content and for the content a part
    /// carries out of sight). May be empty for node tracking.
    pub scan: Vec<TrainView>,
    /// The end state's views (after the hand lets go); may be empty.
    pub end: Vec<TrainView>,
    /// A folder with gt/joints.json (a synthetic dataset), for the joint errors.
    pub ground_truth: Option<PathBuf>,
}

impl StageTwoInput {
    /// The phases of an AiM-layout `dataset` that `cfg`'s method reads, at its resolution.
    pub fn load(dataset: &Path, cfg: &DynamicConfig) -> Result<Self> {
        let (motion, test) = load_phase_views(dataset, Phase::Motion, cfg.resolution, cfg.track.depth_weight > 0.0)?;
        let has = |phase: &str| dataset.join(phase).join("transforms_train.json").exists();
        let scan_needed = match cfg.method {
            StageTwoMethod::DualField => true,
            StageTwoMethod::NodeTrack => (cfg.track.revealed_gaussians > 0 || cfg.track.carry_content) && has("start"),
        };
        let scan =
            if scan_needed { load_phase_views(dataset, Phase::Scan, cfg.resolution, false)?.0 } else { Vec::new() };
        // The end state is optional: a capture may stop right after the motion.
        let end_used = cfg.method == StageTwoMethod::DualField || cfg.track.end_iterations > 0;
        let end = if end_used && has("end") {
            load_phase_views(dataset, Phase::After, cfg.resolution, false)?.0
        } else {
            Vec::new()
        };
        let ground_truth = crate::eval::twin::has_ground_truth(dataset).then(|| dataset.to_path_buf());
        Ok(StageTwoInput { source: dataset.to_path_buf(), motion, test, scan, end, ground_truth })
    }
}

/// Train stages II and III on `input` from the start-state Gaussians in
/// `static_ply` into `out`: checkpoint.bin, metrics.json, the twin in out/twin
/// (meshes by `mesh`), and the method's own outputs (dual field: moving.ply,
/// static_pruned.ply, deform.bin; node tracking: static_pruned.ply, moving.ply
/// at t = 0, track.bin: the node poses at the knots).
pub fn run_dynamic(
    input: StageTwoInput,
    static_ply: &Path,
    out: &Path,
    cfg: DynamicConfig,
    mesh: &TsdfConfig,
    control: &RunControl,
    progress: impl FnMut(StageTwoProgress<'_>),
) -> Result<DynamicOutcome> {
    std::fs::create_dir_all(out).map_err(|e| Error::io(out, e))?;
    let StageTwoInput { source, motion, test, scan, end, ground_truth } = input;
    let run = RunFiles { source: &source, ground_truth: ground_truth.as_deref(), static_ply, out, mesh, test: &test };
    match cfg.method {
        StageTwoMethod::DualField => run_dual_field(&run, motion, scan, end, cfg, control, progress),
        StageTwoMethod::NodeTrack => run_node_track(&run, motion, &scan, end, cfg, control, progress),
    }
}

/// Where a stage II run reads and writes.
struct RunFiles<'a> {
    source: &'a Path,
    ground_truth: Option<&'a Path>,
    static_ply: &'a Path,
    out: &'a Path,
    mesh: &'a TsdfConfig,
    /// Held-out motion frames.
    test: &'a [TrainView],
}

fn run_dual_field(
    run: &RunFiles,
    motion: Vec<TrainView>,
    start: Vec<TrainView>,
    end: Vec<TrainView>,
    cfg: DynamicConfig,
    control: &RunControl,
    mut progress: impl FnMut(StageTwoProgress<'_>),
) -> Result<DynamicOutcome> {
    let out = run.out;
    let views = StageTwoViews::new(motion, start, end)?;
    let checkpoint = out.join("checkpoint.bin");
    let (mut trainer, elapsed_before) = if control.resume && checkpoint.exists() {
        let (t, elapsed) = load_checkpoint(&checkpoint)?;
        if t.config != cfg {
            return Err(other_configuration(&checkpoint));
        }
        tracing::info!(iteration = t.iteration, "resuming from {}", checkpoint.display());
        (t, elapsed)
    } else {
        (DualTrainer::new(cfg, crate::splat::ply::read_ply(run.static_ply)?, &views)?, 0.0)
    };
    trainer.backend = control.backend.clone();
    trainer.field_device = crate::deform::FieldDevice::of(&control.backend);
    tracing::info!(backend = trainer.backend.describe(), "stage II (dual field)");
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
        progress(StageTwoProgress::Step(&s));
    }
    save_checkpoint(&checkpoint, &trainer, elapsed(&started))?;
    let (parts, _) = trainer.analyse();
    articulated(control.viz, &parts, &mut progress);
    let motion_test_psnr = (!run.test.is_empty()).then(|| trainer.evaluate(run.test));
    crate::splat::ply::write_ply(&out.join("moving.ply"), &trainer.moving.gaussians)?;
    crate::splat::ply::write_ply(&out.join("static_pruned.ply"), &trainer.static_set.gaussians)?;
    let net = postcard::to_stdvec(&trainer.net)
        .map_err(|e| Error::Other(format!("encoding the deformation network: {e}")))?;
    write_atomic(&out.join("deform.bin"), &net)?;
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
    log_sets(control.viz, &trainer);
    let summary = RunSummary {
        preset: trainer.config.preset.clone(),
        iterations: trainer.iteration,
        motion_test_psnr,
        moving_gaussians: trainer.moving.gaussians.len(),
        wall_time_s: elapsed(&started),
        tracking_error: None,
        tracking_error_at_discovery: None,
    };
    finish(run, control.viz, &trainer.static_set.gaussians, parts, &part_sets, summary)
}

fn run_node_track(
    run: &RunFiles,
    mut frames: Vec<TrainView>,
    scan: &[TrainView],
    mut end_views: Vec<TrainView>,
    cfg: DynamicConfig,
    control: &RunControl,
    mut progress: impl FnMut(StageTwoProgress<'_>),
) -> Result<DynamicOutcome> {
    let out = run.out;
    let start_cameras: Vec<_> = scan.iter().map(|v| v.camera).collect();
    if frames.is_empty() {
        return Err(Error::bad_file(run.source, "no motion frames to track"));
    }
    require_times(&frames)?;
    let time = |v: &TrainView| v.time.unwrap_or(0.0);
    if frames.windows(2).any(|w| time(&w[1]) < time(&w[0])) {
        tracing::warn!("the motion frames are not in time order; fitting them sorted by time");
        frames.sort_by(|a, b| time(a).total_cmp(&time(b)));
    }
    let checkpoint = out.join("checkpoint.bin");
    let (mut tracker, elapsed_before) = if control.resume && checkpoint.exists() {
        let (t, elapsed) = load_track_checkpoint(&checkpoint)?;
        if t.config != cfg {
            return Err(other_configuration(&checkpoint));
        }
        tracing::info!(segments = t.segments_done, "resuming from {}", checkpoint.display());
        (t, elapsed)
    } else {
        // The scan's cameras show where the start state's hidden volume is (for revealed content).
        let mut tracker = NodeTracker::new(cfg, &crate::splat::ply::read_ply(run.static_ply)?, &start_cameras)?;
        tracker.take_hold(&frames, &end_views);
        (tracker, 0.0)
    };
    tracker.backend = control.backend.clone();
    tracing::info!(backend = tracker.backend.describe(), "stage II");
    // The end state seen from around the object (the frames after the hand lets
    // go), when the capture has it, at time 1: the parts' end poses are fitted on
    // it, and it is part of the evidence the parts are judged on.
    if tracker.config.track.end_iterations == 0 {
        end_views.clear();
    }
    end_views.iter_mut().for_each(|v| v.time = Some(1.0));
    let scan_settings = (!end_views.is_empty() && tracker.wants_end_scan()).then(|| EndScanSettings {
        iterations: tracker.config.track.end_scan_iterations,
        seed: tracker.config.seed,
        backend: tracker.backend.clone(),
    });
    let started = Instant::now();
    let elapsed = |started: &Instant| elapsed_before + started.elapsed().as_secs_f64();
    // The end scan needs only the end views: it trains beside the tracking, on the
    // core the tracking's serial stretches leave idle, and stops when the tracking
    // stops early.
    let tracking_stopped = AtomicBool::new(false);
    let (tracked, scan) = std::thread::scope(|s| {
        let stop = || control.interrupt.load(Ordering::SeqCst) || tracking_stopped.load(Ordering::SeqCst);
        let views = &end_views;
        let resume = control.resume;
        let scan = scan_settings.map(|settings| s.spawn(move || end_state_scan(out, views, settings, resume, stop)));
        let tracked = track_frames(&mut tracker, &frames, &checkpoint, control, &mut progress, &|| elapsed(&started));
        if !matches!(tracked, Ok(true)) {
            tracking_stopped.store(true, Ordering::SeqCst);
        }
        let scan = scan.map(|h| h.join().unwrap_or_else(|panic| std::panic::resume_unwind(panic)));
        (tracked, scan)
    });
    let per_segment = tracker.iterations_per_segment;
    let interrupted = |tracker: &NodeTracker| DynamicOutcome::Interrupted(tracker.fits_done as u32 * per_segment);
    if !tracked? {
        return Ok(interrupted(&tracker));
    }
    let end_scan = match scan {
        Some(scan) => match scan? {
            Some(scan) => Some(scan),
            None => return Ok(interrupted(&tracker)),
        },
        None => None,
    };
    if let Some(scan) = &end_scan {
        let cameras: Vec<_> = end_views.iter().map(|v| v.camera).collect();
        tracker.end_scan = EndScan::new(scan, tracker.object_size, &cameras);
    }
    // The end phase is not checkpointed (a resumed run does it again from the
    // tracking's checkpoint): an interrupt stops it between its steps (and
    // between the parts searched, the candidates tried).
    let stop = || control.interrupt.load(Ordering::SeqCst);
    tracker.refit_end_poses(&end_views);
    tracker.merge_redundant_parts(&frames, &end_views);
    if stop() {
        return Ok(interrupted(&tracker));
    }
    // Merge first, so that pieces that explain nothing are gone before a searched
    // pose lets them explain content the start state lacks (docs/training.md).
    if tracker.search_end_poses(&frames, &end_views, &stop) > 0 {
        tracker.merge_redundant_parts(&frames, &end_views);
    }
    if stop() {
        return Ok(interrupted(&tracker));
    }
    // A tracked part that still looks wrong where it moved is not a part.
    let returned = tracker.drop_parts_that_look_wrong(&end_views);
    // What the tracked parts that stand brought out of hiding is theirs before
    // other parts are looked for where the end state shows the start state moved.
    if let (Some(scan), true) = (&end_scan, tracker.config.track.carry_content) {
        tracker.carry_swept_content(scan, &start_cameras);
    }
    // Parts the tracking never grouped, found where the end state shows the start state moved.
    if tracker.discover_on_end_state(&frames, &end_views, &returned, &stop) > 0 {
        tracker.merge_redundant_parts(&frames, &end_views);
        tracker.refit_grown_parts(&frames, &end_views);
    }
    if stop() {
        return Ok(interrupted(&tracker));
    }
    if tracker.clean_parts(&frames, &end_views) > 0 {
        tracker.refit_end_poses(&end_views);
    }
    // Gaussians at nodes that straddle a part's edge and the body, each given
    // to the side the end scan shows it went with.
    if let Some(scan) = &end_scan {
        tracker.settle_gaussians_on_end_scan(scan);
    }
    let (parts, labels) = tracker.analyse();
    articulated(control.viz, &parts, &mut progress);
    let motion_test_psnr = (!run.test.is_empty()).then(|| tracker.evaluate(run.test));
    let (tracking_error, tracking_error_at_discovery) = match run.ground_truth {
        Some(gt) => {
            let (end, free) = node_tracking_error(gt, &tracker)?;
            (Some(end), (!free.is_empty()).then_some(free))
        }
        None => (None, None),
    };
    let with_label = |l: usize| tracker.gaussians.subset(&labels.iter().map(|&x| x == l).collect::<Vec<_>>());
    let base = with_label(0);
    let part_sets: Vec<_> = (1..=parts.len()).map(with_label).collect();
    let moving = tracker.gaussians.subset(&labels.iter().map(|&x| x > 0).collect::<Vec<_>>());
    crate::splat::ply::write_ply(&out.join("static_pruned.ply"), &base)?;
    crate::splat::ply::write_ply(&out.join("moving.ply"), &moving)?;
    crate::splat::ply::write_ply(&out.join("revealed.ply"), &tracker.revealed.gaussians)?;
    let track = postcard::to_stdvec(&tracker.knots)
        .map_err(|e| Error::Other(format!("encoding the tracked node poses: {e}")))?;
    write_atomic(&out.join("track.bin"), &track)?;
    log_tracked(control.viz, &tracker, &frames);
    if parts.is_empty() {
        tracing::warn!(
            "no moving part found: nothing in the motion video moved by more than {} rad or {} (sdmd_max_rotation, sdmd_max_translation)",
            tracker.config.sdmd_max_rotation,
            tracker.config.sdmd_max_translation
        );
    }
    let summary = RunSummary {
        preset: tracker.config.preset.clone(),
        iterations: tracker.fits_done as u32 * per_segment,
        motion_test_psnr,
        moving_gaussians: moving.len(),
        wall_time_s: elapsed(&started),
        tracking_error,
        tracking_error_at_discovery,
    };
    finish(run, control.viz, &base, parts, &part_sets, summary)
}

/// Track the motion `frames` segment by segment from where `tracker` stands,
/// checkpointing after each; false when the interrupt stopped it (after a checkpoint).
fn track_frames(
    tracker: &mut NodeTracker,
    frames: &[TrainView],
    checkpoint: &Path,
    control: &RunControl,
    progress: &mut impl FnMut(StageTwoProgress<'_>),
    elapsed: &dyn Fn() -> f64,
) -> Result<bool> {
    let per_segment = tracker.iterations_per_segment;
    while tracker.segments_done < tracker.segments() {
        if control.interrupt.load(Ordering::SeqCst) {
            save_track_checkpoint(checkpoint, tracker, elapsed())?;
            return Ok(false);
        }
        let fit = tracker.fit_next(frames);
        let step = DynamicStep {
            iteration: fit.fits_done as u32 * per_segment,
            loss: fit.loss,
            psnr: fit.psnr,
            static_count: tracker.gaussians.len(),
            moving_count: 0,
            sdmd_moved: 0,
        };
        log_step(control.viz, &step);
        if tracker
            .knots
            .last()
            .is_some_and(|p| p.iter().any(|p| !(p.translation.is_finite() && p.rotation.is_finite())))
        {
            return Err(Error::Other(format!("stage II tracking diverged in segment {}", fit.segments_done)));
        }
        // One segment is a few seconds of work: checkpoint after each.
        if fit.segments_done < tracker.segments() {
            save_track_checkpoint(checkpoint, tracker, elapsed())?;
            log_tracked(control.viz, tracker, frames);
        }
        progress(StageTwoProgress::Step(&step));
    }
    save_track_checkpoint(checkpoint, tracker, elapsed())?;
    Ok(true)
}

/// How the end state is scanned: stage I's trainer and its cpu settings for
/// `track.end_scan_iterations`, the run's seed.
struct EndScanSettings {
    iterations: u32,
    seed: u64,
    backend: crate::render::Backend,
}

/// The end state scanned as the start state was (`settings`, on `end_views`):
/// when `resume`, out/end_scan.ply if the run being resumed wrote it, else
/// trained and written there; None when `stop` said so first. A new run trains
/// its own: the folder's scan may be of another dataset.
fn end_state_scan(
    out: &Path,
    end_views: &[TrainView],
    settings: EndScanSettings,
    resume: bool,
    stop: impl Fn() -> bool,
) -> Result<Option<GaussianSet>> {
    let path = out.join("end_scan.ply");
    if resume && path.exists() {
        return crate::splat::ply::read_ply(&path).map(Some);
    }
    let cpu = StaticConfig::cpu();
    let mut config = cpu.compressed(f64::from(settings.iterations) / f64::from(cpu.iterations));
    config.seed = settings.seed;
    let mut trainer = GaussianTrainer::new(config, end_views, None)?;
    trainer.backend = settings.backend;
    let started = Instant::now();
    while trainer.iteration < trainer.config.iterations {
        if stop() {
            return Ok(None);
        }
        trainer.step(end_views);
    }
    tracing::info!(
        gaussians = trainer.gaussians.len(),
        wall_s = started.elapsed().as_secs_f64(),
        "stage II: the end state scanned"
    );
    crate::splat::ply::write_ply(&path, &trainer.gaussians)?;
    Ok(Some(trainer.gaussians))
}

/// The articulation is known: its joints to the log (as arrows, before the
/// meshes and the export take their time) and to `progress`.
fn articulated(viz: &Viz, parts: &[PartEstimate], progress: &mut impl FnMut(StageTwoProgress<'_>)) {
    let joints: Vec<_> = parts.iter().map(|p| p.joint).collect();
    viz.joints("stage3/joints", &joints);
    progress(StageTwoProgress::Articulated(parts));
}

/// The tracked nodes' distance from their true positions (the ground truth of
/// the dataset `dataset`) at tenths of the motion, per ground-truth part (also logged).
fn node_tracking_error(dataset: &Path, tracker: &NodeTracker) -> Result<(Vec<TrackingError>, Vec<TrackingError>)> {
    let gt = GroundTruth::load(dataset)?;
    let positions =
        |poses: Vec<NodePose>| poses.iter().zip(&tracker.node_centres).map(|(p, &c)| c + p.translation).collect();
    let times: Vec<f32> = (1..=10).map(|k| k as f32 / 10.0).collect();
    let seed = tracker.config.seed;
    let errors = tracking_errors(&gt, &tracker.node_centres, |t| positions(tracker.poses_at(t)), &times, seed);
    let free_end = tracker.free_tracking_end();
    let free_times: Vec<f32> = times.iter().copied().filter(|&t| free_end.is_some_and(|end| t <= end)).collect();
    let free = tracking_errors(
        &gt,
        &tracker.node_centres,
        |t| positions(tracker.free_poses_at(t).expect("a time free tracking fitted")),
        &free_times,
        seed,
    );
    for (what, list) in [("tracking error", &errors), ("free tracking error at discovery", &free)] {
        for e in list {
            let parts: Vec<String> = e
                .parts
                .iter()
                .map(|p| format!("part {} ({} nodes) median {:.3} p90 {:.3}", p.gt_part, p.points, p.median, p.p90))
                .collect();
            tracing::info!("{what} at t = {:.1}: {}", e.time, parts.join("; "));
        }
    }
    Ok((errors, free))
}

const TRACK_CHECKPOINT_STAGE: &str = "stage II tracking";

/// A checkpoint written with another configuration than the run's: refused as a
/// configuration error (running again does not help; another configuration or a
/// new run folder does).
fn other_configuration(checkpoint: &Path) -> Error {
    Error::Config(format!(
        "{} was written with another configuration; resume with the same one, or rerun without --resume",
        checkpoint.display()
    ))
}

fn save_track_checkpoint(path: &Path, tracker: &NodeTracker, elapsed_s: f64) -> Result<()> {
    crate::train::checkpoint::save(path, TRACK_CHECKPOINT_STAGE, tracker, elapsed_s)
}

fn load_track_checkpoint(path: &Path) -> Result<(NodeTracker, f64)> {
    crate::train::checkpoint::load(path, TRACK_CHECKPOINT_STAGE, |t: &NodeTracker| {
        t.gaussians.check_shapes()?;
        let nodes = t.node_centres.len();
        if t.binding.len() != t.gaussians.len() || t.binding.iter().any(|&k| k as usize >= nodes) {
            return Err("the node binding does not match the Gaussians".into());
        }
        if t.knots.iter().any(|p| p.len() != nodes)
            || t.knots.len() != t.segments_done + 1
            || t.gains.len() != t.knots.len()
            || t.gains.iter().any(|g| g.len() != nodes)
        {
            return Err("the node poses do not match the nodes".into());
        }
        if t.segments_done > t.segments() {
            return Err(format!("{} segments fitted of {}", t.segments_done, t.segments()));
        }
        Ok(())
    })
}

/// Log the tracked Gaussians at t = 0, 0.5, 1 to rerun.
fn log_tracked(viz: &Viz, tracker: &NodeTracker, frames: &[TrainView]) {
    if !viz.is_enabled() {
        return;
    }
    for (name, t) in [("t0", 0.0), ("t05", 0.5), ("t1", 1.0)] {
        viz.gaussians(&format!("stage2/tracked/{name}"), &tracker.deformed_at(t));
    }
    // A preview: the model as tracked so far, rendered from the motion frame
    // nearest the last time fitted, beside that frame.
    let t = tracker.segments_done as f32 / tracker.segments().max(1) as f32;
    let nearest = frames.iter().min_by(|a, b| {
        let d = |v: &TrainView| (v.time.unwrap_or(0.0) - t).abs();
        d(a).total_cmp(&d(b))
    });
    if let Some(frame) = nearest {
        let bg = glam::Vec3::from(tracker.config.eval_background);
        let r = tracker.backend.render(&tracker.deformed_at(t), &frame.camera, &frame.render_options(bg));
        let (w, h) = (r.width(), r.height());
        viz.camera("stage2/preview", &frame.camera);
        viz.image_rgb("stage2/preview/render", w, h, &r.image().color);
        viz.image_rgb("stage2/preview/frame", w, h, &frame.target(bg));
    }
}

/// What a method reports for metrics.json besides the parts.
struct RunSummary {
    preset: String,
    iterations: u32,
    motion_test_psnr: Option<f32>,
    moving_gaussians: usize,
    wall_time_s: f64,
    tracking_error: Option<Vec<TrackingError>>,
    tracking_error_at_discovery: Option<Vec<TrackingError>>,
}

/// Write the twin (the static base and each part's Gaussians at t = 0), log the
/// parts, match the joints with ground truth when the dataset has it, and write
/// metrics.json.
fn finish(
    run: &RunFiles,
    viz: &Viz,
    base: &GaussianSet,
    parts: Vec<PartEstimate>,
    part_sets: &[GaussianSet],
    summary: RunSummary,
) -> Result<DynamicOutcome> {
    let twin: Vec<TwinPart> = std::iter::once(TwinPart { gaussians: base, joint: None })
        .chain(parts.iter().zip(part_sets).map(|(p, g)| TwinPart { gaussians: g, joint: Some(p.joint) }))
        .collect();
    write_twin(&run.out.join("twin"), &twin, run.mesh, &crate::export::ExportConfig::default())?;
    for (k, g) in part_sets.iter().enumerate() {
        viz.gaussians(&format!("stage3/part_{}", k + 1), g);
    }
    viz.flush();
    // A diagnostic: ground truth without its meshes leaves it out rather than losing the run.
    let composition = match run.ground_truth.map(GroundTruth::load) {
        Some(Ok(gt)) => {
            let sets: Vec<Vec<glam::Vec3>> =
                std::iter::once(base).chain(part_sets).map(|g| (0..g.len()).map(|i| g.mean(i)).collect()).collect();
            let composition = part_composition(&gt, &sets, 0);
            for c in &composition {
                tracing::info!(part = c.part, gt_parts = ?c.gt_parts, "stage III: a part's make-up (Gaussians per ground-truth part)");
            }
            Some(composition)
        }
        Some(Err(e)) => {
            tracing::warn!("the parts' make-up against ground truth is left out: {e}");
            None
        }
        None => None,
    };
    let gt_path = run.ground_truth.map(|d| d.join("gt").join("joints.json"));
    let gt_report = if let Some(gt_path) = gt_path {
        let gt: Vec<_> =
            crate::synth::JointsFile::load(&gt_path)?.joints.iter().map(crate::eval::twin::gt_joint).collect();
        let pred: Vec<PredictedJoint> = parts.iter().map(|p| PredictedJoint::of_part(p.joint, &p.motion)).collect();
        Some(match_joints(&pred, &gt))
    } else {
        None
    };
    let metrics = DynamicMetrics {
        preset: summary.preset,
        iterations: summary.iterations,
        motion_test_psnr: summary.motion_test_psnr,
        static_gaussians: base.len(),
        moving_gaussians: summary.moving_gaussians,
        wall_time_s: summary.wall_time_s,
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
        tracking_error: summary.tracking_error,
        tracking_error_at_discovery: summary.tracking_error_at_discovery,
        composition,
    };
    let json = serde_json::to_vec_pretty(&metrics).map_err(|e| Error::Other(e.to_string()))?;
    write_atomic(&run.out.join("metrics.json"), &json)?;
    Ok(DynamicOutcome::Finished { parts, metrics: Box::new(metrics) })
}
