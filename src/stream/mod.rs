//! The session: one input's frames to the twin, the stages wired one way.
//!
//! source -> ingestion thread (aim-capture: decode, undistort, pose, phases and
//! the hand-in / hand-out events) -> phase router (the calling thread: frames to
//! training views, bounded per phase) -> stage I worker (starts when the scan
//! ends, trains while the motion is still arriving) -> stages II and III (when
//! the stream ends: the node tracker fits the motion on its whole window) -> the
//! twin. Batch commands call the same stage code (`run_static`,
//! `run_dynamic`), so a dataset fed through a session gives the stage
//! commands' result (test `a_session_on_a_dataset_gives_the_stage_commands_result`).

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};

use aim_capture::crop::ObjectCrop;
use aim_capture::detect::{MotionEvent, ObjectRegion};
use aim_capture::ingest::{motion_time, Ingest, IngestConfig, IngestStats, Message};
use aim_capture::mps::{HandTracking, SemidensePoints, Trajectory};
use aim_capture::recording::Opened;
use aim_capture::{Frame, Phase};
use serde::Serialize;

use crate::error::{write_atomic, Error, Result};
use crate::mesh::tsdf::TsdfConfig;
use crate::train::config::StaticConfig;
use crate::train::dynamic_run::{run_dynamic, DynamicMetrics, DynamicOutcome, RunControl, StageTwoInput};
use crate::train::dynamic_stage::{DynamicConfig, DynamicStep, PartEstimate, StageTwoMethod};
use crate::train::static_stage::{run_static, RunOutcome, RunSetup, StaticMetrics, StepReport};
use crate::train::views::TrainView;
use crate::viz::Viz;

/// How a session trains.
#[derive(Clone, Debug)]
pub struct SessionConfig {
    pub stage_one: StaticConfig,
    pub stage_two: DynamicConfig,
    pub ingest: IngestConfig,
    pub mesh: TsdfConfig,
    /// Frames kept per phase: past it the store keeps every other frame (and
    /// then every fourth, ...), so memory stays bounded on long captures.
    pub max_frames_per_phase: usize,
    /// A raw recording's frames cut to the object and the room around it
    /// learnt too (None: a dataset's frames show the object alone).
    pub room: Option<RoomSetup>,
}

/// How a session separates the object from the room of a raw recording:
/// stage I learns both from crops around the object region, starting from the
/// recording's SLAM points (the room's Gaussians start where the room is, so
/// they, not the region's, explain it); the object is what lies in the region;
/// stages II and III see the room as a fixed backdrop behind it.
#[derive(Clone, Debug)]
pub struct RoomSetup {
    pub crop: ObjectCrop,
    /// Stage I's initial points (the recording's MPS semidense points).
    pub points: crate::splat::ply::PointCloud,
    /// The recording's hand tracking and device poses, when it has them: each
    /// motion frame carries the palms seen at its time (the contact term of
    /// stage II's node tracking).
    pub hands: Option<(HandTracking, Trajectory)>,
}

/// Hand samples this far from a frame's time are not its palms (MPS hand
/// tracking runs at 30-60 Hz).
const PALM_MAX_GAP_NS: i64 = 50_000_000;
/// Hands tracked with less confidence are not placed.
const PALM_MIN_CONFIDENCE: f64 = 0.5;

impl RoomSetup {
    /// Crops of `region` at the trainers' resolution, every pixel kept.
    pub fn new(region: ObjectRegion, points: Vec<glam::Vec3>, cfg: &SessionConfig) -> Self {
        let size = [cfg.stage_one.resolution, cfg.stage_two.resolution].into_iter().max().unwrap_or(0);
        let size = if size == 0 { CROP_SIZE_AS_RECORDED } else { size };
        let crop = ObjectCrop { region, size, margin: aim_capture::crop::DEFAULT_MARGIN, mask_outside: false };
        RoomSetup { crop, points: crate::splat::ply::PointCloud { points, colors: None }, hands: None }
    }

    /// World positions of the palms seen at `timestamp_s` (device clock).
    fn palms_at(&self, timestamp_s: f64) -> Vec<glam::Vec3> {
        self.hands.as_ref().map_or_else(Vec::new, |(hands, trajectory)| {
            let t_ns = (timestamp_s * 1e9).round() as i64;
            hands
                .palms_in_world(trajectory, t_ns, PALM_MAX_GAP_NS, PALM_MIN_CONFIDENCE)
                .into_iter()
                .map(|p| p.as_vec3())
                .collect()
        })
    }

    /// The setup of the recording `input` as opened: its poses, object region and
    /// SLAM points are all needed, and each missing one is named.
    pub fn for_recording(input: &Path, opened: &Opened, cfg: &SessionConfig) -> Result<Self> {
        if opened.trajectory_path.is_none() {
            return Err(Error::bad_file(
                input,
                "a recording needs its camera poses (an MPS closed_loop_trajectory.csv beside it, or --trajectory)",
            ));
        }
        let Some(region) = opened.region else {
            return Err(Error::bad_file(
                input,
                "a recording needs the object's region (object_region.json beside it, or --region \
                 x0,y0,z0,x1,y1,z1 in its trajectory's world frame): its frames show the whole room",
            ));
        };
        let Some(points_path) = &opened.points_path else {
            return Err(Error::bad_file(
                input,
                "a recording needs its SLAM points (MPS semidense_points.csv.gz beside it, or --points): without them \
                 the room behind the object is learnt inside the object's region (docs/session.md)",
            ));
        };
        let points: Vec<glam::Vec3> =
            SemidensePoints::load(points_path)?.confident(MAX_POINT_DIST_STD).map(|p| p.as_vec3()).collect();
        if points.is_empty() {
            return Err(Error::bad_file(
                points_path,
                format!("no semidense point is placed to within {MAX_POINT_DIST_STD} m"),
            ));
        }
        // The trajectory as the frames' poses were read from it (loaded once).
        let hands = match (&opened.hands_path, &opened.processor.trajectory) {
            (Some(path), Some(trajectory)) => Some((HandTracking::load(path)?, trajectory.clone())),
            _ => None,
        };
        Ok(Self { hands, ..Self::new(region, points, cfg) })
    }

    /// Whether a Gaussian centred at `p` is the object's: inside the region
    /// grown by `OBJECT_MARGIN` of its size, since a region drawn tight to the
    /// object has the object's surface Gaussians on both sides of its faces.
    fn contains(&self, p: glam::Vec3) -> bool {
        let r = &self.crop.region;
        let (lo, hi) = (glam::Vec3::from(r.min.map(|v| v as f32)), glam::Vec3::from(r.max.map(|v| v as f32)));
        let margin = OBJECT_MARGIN * (hi - lo).max_element();
        p.cmpge(lo - margin).all() && p.cmple(hi + margin).all()
    }

    /// Stage I's result split: the object (Gaussians in the region) written to
    /// `object_ply`, and the room.
    fn split(&self, static_ply: &Path, object_ply: &Path) -> Result<crate::splat::GaussianSet> {
        let set = crate::splat::ply::read_ply(static_ply)?;
        let inside: Vec<bool> = (0..set.len()).map(|i| self.contains(set.mean(i))).collect();
        crate::splat::ply::write_ply(object_ply, &set.subset(&inside))?;
        let outside: Vec<bool> = inside.iter().map(|b| !b).collect();
        Ok(set.subset(&outside))
    }
}

/// Each view's backdrop: the room rendered from its camera where the room's
/// Gaussians cover the pixel, and the frame itself where they do not (parts of
/// the room no scan frame showed): a pixel of unknown room then costs nothing
/// whatever the object does there, rather than pulling the object towards a
/// colour the room never had.
fn set_backdrops(views: &mut [TrainView], room: &crate::splat::GaussianSet) {
    for v in views {
        let r = crate::render::render(room, &v.camera, &crate::render::RenderOptions::uniform(glam::Vec3::ZERO));
        let frame = v.target(glam::Vec3::ZERO);
        let backdrop: Vec<f32> = r
            .image
            .color
            .iter()
            .zip(&frame)
            .enumerate()
            .map(|(k, (room, seen))| room + (1.0 - r.image.alpha[k / 3]) * seen)
            .collect();
        v.backdrop = Some(backdrop.into());
    }
}

impl SessionConfig {
    /// The cpu presets of both stages with `seed`.
    pub fn cpu(seed: u64) -> Self {
        let mut stage_one = StaticConfig::cpu();
        stage_one.seed = seed;
        let mut stage_two = DynamicConfig::cpu();
        stage_two.seed = seed;
        SessionConfig {
            stage_one,
            stage_two,
            ingest: IngestConfig::default(),
            mesh: TsdfConfig::default(),
            max_frames_per_phase: 512,
            room: None,
        }
    }
}

/// Semidense points placed less surely than this (metres) are left out.
const MAX_POINT_DIST_STD: f64 = 0.05;

/// How far past the region's faces a Gaussian still counts as the object's,
/// as a fraction of the region's largest side.
const OBJECT_MARGIN: f32 = 0.05;

/// Crop size when the presets train at the recorded resolution (0).
const CROP_SIZE_AS_RECORDED: u32 = 512;

/// What a session knows that its frames do not carry: held-out views for the
/// metrics and ground truth (a synthetic dataset's), when there are any.
#[derive(Default)]
pub struct Reference {
    pub scan_test: Vec<TrainView>,
    pub motion_test: Vec<TrainView>,
    /// A folder with gt/joints.json.
    pub ground_truth: Option<PathBuf>,
}

/// Where a session stops early and what it logs to.
pub struct SessionControl<'a> {
    /// Raised (Ctrl-C): the running stage checkpoints and the session stops.
    pub interrupt: &'a AtomicBool,
    pub viz: &'a Viz,
}

/// What a session reports as it goes (from the router and the stage I worker).
pub enum SessionEvent<'a> {
    Window(MotionEvent),
    StageOneStarted { views: usize },
    StageOne(&'a StepReport),
    StageTwoStarted { motion: usize, end: usize },
    StageTwo(&'a DynamicStep),
}

/// Frames per phase as the router kept them.
#[derive(Clone, Copy, Debug, Default, Serialize)]
pub struct PhaseCounts {
    pub scan: usize,
    pub motion: usize,
    pub after: usize,
}

/// OUT/session.json.
#[derive(Clone, Debug, Serialize)]
pub struct SessionReport {
    pub source: String,
    pub frames: PhaseCounts,
    /// Frames dropped because the object region was out of their view (cropped inputs).
    pub frames_without_object: usize,
    /// Hand-in and hand-out as the ingestion thread saw them (frame index and
    /// seconds on the source's clock; a dataset's clock is nominal, per phase).
    pub events: Vec<MotionEvent>,
    pub ingest: IngestStats,
    pub stage_one: StaticMetrics,
    pub stage_two: DynamicMetrics,
    pub timing: SessionTiming,
}

/// How long the session took, on the wall clock.
#[derive(Clone, Debug, Serialize)]
pub struct SessionTiming {
    /// From the start of the session to the twin written.
    pub wall_s: f64,
    /// From the moment the hand-out event arrived to the twin written: how far
    /// the reconstruction lags behind the capture (`aim run --live`).
    pub hand_out_to_twin_s: Option<f64>,
}

/// How a session ended.
pub enum SessionOutcome {
    Finished {
        parts: Vec<PartEstimate>,
        report: Box<SessionReport>,
    },
    /// Stopped by the interrupt flag; the running stage wrote its checkpoint.
    Interrupted,
}

/// Training views of one phase, bounded: past `cap` frames every other one is
/// dropped and from then on only every `stride`-th frame is kept, so the frames
/// kept stay spread over the whole phase.
struct FrameStore {
    cap: usize,
    stride: usize,
    seen: usize,
    views: Vec<(f64, TrainView)>,
}

impl FrameStore {
    fn new(cap: usize) -> Self {
        FrameStore { cap: cap.max(2), stride: 1, seen: 0, views: Vec::new() }
    }

    fn push(&mut self, timestamp_s: f64, view: TrainView) {
        let keep = self.seen.is_multiple_of(self.stride);
        self.seen += 1;
        if !keep {
            return;
        }
        if self.views.len() == self.cap {
            let mut k = 0;
            self.views.retain(|_| {
                k += 1;
                k % 2 == 1
            });
            self.stride *= 2;
            if !(self.seen - 1).is_multiple_of(self.stride) {
                return;
            }
        }
        self.views.push((timestamp_s, view));
    }
}

/// Run `opened` through the ingestion thread to the twin in `out` (static/:
/// stage I, dynamic/: stages II and III and the twin, session.json).
pub fn run_session(
    opened: Opened,
    reference: Reference,
    out: &Path,
    cfg: &SessionConfig,
    control: &SessionControl,
    on_event: &(dyn Fn(SessionEvent) + Sync),
) -> Result<SessionOutcome> {
    if cfg.room.is_some() && cfg.stage_two.method != StageTwoMethod::NodeTrack {
        // Only node tracking renders over a backdrop.
        return Err(Error::Config(format!(
            "the {} preset's stage II does not train on recordings yet (the cpu preset does)",
            cfg.stage_two.preset
        )));
    }
    let source = opened.source.describe();
    let started = std::time::Instant::now();
    let ingest = Ingest::spawn(opened.source, opened.processor, opened.tagger, cfg.ingest.clone())
        .map_err(|e| Error::Other(format!("starting the ingestion thread: {e}")))?;
    let static_dir = out.join("static");
    std::thread::scope(|scope| {
        let mut scan: Vec<TrainView> = Vec::new();
        let mut motion = FrameStore::new(cfg.max_frames_per_phase);
        let mut after = FrameStore::new(cfg.max_frames_per_phase);
        let mut events = Vec::new();
        let mut stage_one = None;
        let mut frames_without_object = 0;
        let mut hand_out_at = None;
        for message in &ingest {
            if control.interrupt.load(Ordering::SeqCst) {
                break;
            }
            let frame = match message {
                Message::Frame(f) => f,
                Message::Event(e) => {
                    if matches!(e, MotionEvent::HandOut { .. }) {
                        hand_out_at = Some(std::time::Instant::now());
                    }
                    control.viz.text("session/events", &format!("{e:?}"));
                    on_event(SessionEvent::Window(e));
                    events.push(e);
                    continue;
                }
                Message::Error(e) => return Err(Error::from(e)),
            };
            let frame = match &cfg.room {
                None => frame,
                Some(room) => match room.crop.apply(&frame) {
                    Some(f) => f,
                    None => {
                        frames_without_object += 1;
                        continue;
                    }
                },
            };
            log_frame(control.viz, &frame);
            if frame.phase == Phase::Scan {
                if stage_one.is_some() {
                    tracing::warn!("{}: a scan frame after the motion began; not used", frame.source);
                    continue;
                }
                scan.push(TrainView::from_frame(&frame, cfg.stage_one.resolution)?);
                continue;
            }
            if stage_one.is_none() {
                // The scan is over: stage I trains while the motion arrives.
                if scan.is_empty() {
                    return Err(Error::bad_file(
                        &frame.source,
                        "the motion begins at the first frame: no scan of the start state to train on",
                    ));
                }
                control.viz.text("session/events", &format!("stage I starts on {} scan frames", scan.len()));
                on_event(SessionEvent::StageOneStarted { views: scan.len() });
                let (views, test, dir) = (std::mem::take(&mut scan), &reference.scan_test, &static_dir);
                stage_one = Some(scope.spawn(move || {
                    let setup = RunSetup { run_dir: dir, resume: false, init: cfg.room.as_ref().map(|r| &r.points) };
                    let outcome =
                        run_static(cfg.stage_one.clone(), &views, test, &setup, control.interrupt, control.viz, |r| {
                            on_event(SessionEvent::StageOne(r))
                        });
                    (views, outcome)
                }));
            }
            let mut view = TrainView::from_frame(&frame, cfg.stage_two.resolution)?;
            match frame.phase {
                Phase::Motion => {
                    if let Some(room) = &cfg.room {
                        view.palms = room.palms_at(frame.timestamp_s);
                    }
                    motion.push(frame.timestamp_s, view)
                }
                _ => after.push(frame.timestamp_s, view),
            }
        }
        let (stats, _) = ingest.stop();
        let interrupted = control.interrupt.load(Ordering::SeqCst);
        let Some(stage_one) = stage_one else {
            if interrupted {
                return Ok(SessionOutcome::Interrupted);
            }
            return Err(Error::Other(format!(
                "{source}: no interaction found ({} scan frame(s), no hand-in): nothing moved, so there is no articulation to learn",
                scan.len()
            )));
        };
        let (scan_views, outcome) = stage_one.join().map_err(|_| Error::Other("the stage I worker panicked".into()))?;
        let stage_one_metrics = match outcome? {
            RunOutcome::Finished(m) if !interrupted => *m,
            _ => return Ok(SessionOutcome::Interrupted),
        };
        let motion_views = timed_motion(motion.views, &events, &source)?;
        let end: Vec<TrainView> = after.views.into_iter().map(|(_, v)| v).collect();
        let frames = PhaseCounts { scan: scan_views.len(), motion: motion_views.len(), after: end.len() };
        control.viz.text(
            "session/events",
            &format!("stages II and III start on {} motion and {} end-state frames", frames.motion, frames.after),
        );
        on_event(SessionEvent::StageTwoStarted { motion: frames.motion, end: frames.after });
        let mut input = StageTwoInput {
            source: PathBuf::from(&source),
            motion: motion_views,
            test: reference.motion_test,
            scan: scan_views,
            end,
            ground_truth: reference.ground_truth,
        };
        let mut start_state = static_dir.join("static.ply");
        if let Some(room) = &cfg.room {
            let object = static_dir.join("object.ply");
            let room_set = room.split(&start_state, &object)?;
            set_backdrops(&mut input.motion, &room_set);
            set_backdrops(&mut input.end, &room_set);
            start_state = object;
        }
        let run_control = RunControl { resume: false, interrupt: control.interrupt, viz: control.viz };
        let outcome = run_dynamic(
            input,
            &start_state,
            &out.join("dynamic"),
            cfg.stage_two.clone(),
            &cfg.mesh,
            &run_control,
            |s| on_event(SessionEvent::StageTwo(s)),
        )?;
        let DynamicOutcome::Finished { parts, metrics } = outcome else {
            return Ok(SessionOutcome::Interrupted);
        };
        let report = SessionReport {
            source,
            frames,
            frames_without_object,
            events,
            ingest: stats,
            stage_one: stage_one_metrics,
            stage_two: *metrics,
            timing: SessionTiming {
                wall_s: started.elapsed().as_secs_f64(),
                hand_out_to_twin_s: hand_out_at.map(|t: std::time::Instant| t.elapsed().as_secs_f64()),
            },
        };
        let json = serde_json::to_vec_pretty(&report).map_err(|e| Error::Other(e.to_string()))?;
        write_atomic(&out.join("session.json"), &json)?;
        Ok(SessionOutcome::Finished { parts, report: Box::new(report) })
    })
}

/// The motion frames with their time in [0, 1]: the one the source gave, or
/// from the detected window (`aim_capture::ingest::motion_time`).
fn timed_motion(frames: Vec<(f64, TrainView)>, events: &[MotionEvent], source: &str) -> Result<Vec<TrainView>> {
    if frames.is_empty() {
        return Err(Error::Other(format!("{source}: no motion frames between hand-in and hand-out")));
    }
    frames
        .into_iter()
        .map(|(t, mut v)| {
            if v.time.is_none() {
                v.time = Some(motion_time(t, events).ok_or_else(|| {
                    Error::Other(format!(
                        "{source}: the hand never left the object (no hand-out after the hand-in), so the motion has no end to learn to"
                    ))
                })?);
            }
            Ok(v)
        })
        .collect()
}

/// The input frame's camera to rerun, under its phase (session/input/scan,
/// motion, after), so the viewer shows where the wearer looked in each.
fn log_frame(viz: &Viz, frame: &Frame) {
    if !viz.is_enabled() {
        return;
    }
    let phase = match frame.phase {
        Phase::Scan => "scan",
        Phase::Motion => "motion",
        Phase::After => "after",
    };
    let camera = crate::camera::Camera::new(frame.intrinsics, frame.world_to_camera);
    viz.camera(&format!("session/input/{phase}"), &camera);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::{Camera, Intrinsics};

    fn view(k: usize) -> TrainView {
        let intrinsics = Intrinsics { fx: 10.0, fy: 10.0, cx: 2.0, cy: 2.0, width: 4, height: 4 };
        TrainView {
            name: format!("{k}"),
            camera: Camera::new(intrinsics, glam::Mat4::IDENTITY),
            premultiplied: vec![0.0; 48],
            alpha: None,
            time: None,
            depth: None,
            backdrop: None,
            palms: Vec::new(),
        }
    }

    #[test]
    fn the_frame_store_stays_bounded_and_spread_over_the_phase() {
        let mut store = FrameStore::new(64);
        for k in 0..1000 {
            store.push(k as f64, view(k));
        }
        let kept: Vec<usize> = store.views.iter().map(|(t, _)| *t as usize).collect();
        assert!(kept.len() <= 64 && kept.len() >= 32, "{} kept", kept.len());
        // Evenly strided from the first frame to near the last.
        let stride = kept[1] - kept[0];
        assert_eq!(stride, 16);
        assert!(kept.windows(2).all(|w| w[1] - w[0] == stride), "{kept:?}");
        assert_eq!(kept[0], 0);
        assert!(*kept.last().unwrap() >= 1000 - stride, "{kept:?}");
        // Under the cap nothing is dropped.
        let mut small = FrameStore::new(64);
        (0..64).for_each(|k| small.push(k as f64, view(k)));
        assert_eq!(small.views.len(), 64);
    }

    #[test]
    fn motion_times_come_from_the_window_when_the_frames_lack_them() {
        let frames: Vec<(f64, TrainView)> = [10.0, 11.0, 12.5].iter().map(|&t| (t, view(0))).collect();
        let hand_in = MotionEvent::HandIn { frame: 0, timestamp_s: 10.0 };
        let window = [hand_in, MotionEvent::HandOut { frame: 2, timestamp_s: 12.0 }];
        let timed = timed_motion(frames.clone(), &window, "rec").expect("a window");
        let times: Vec<f32> = timed.iter().map(|v| v.time.expect("timed")).collect();
        assert_eq!(times, vec![0.0, 0.5, 1.0]);
        let err = timed_motion(frames, &[hand_in], "rec").expect_err("no hand-out");
        assert!(err.to_string().contains("rec") && err.to_string().contains("hand-out"), "{err}");
    }
}
