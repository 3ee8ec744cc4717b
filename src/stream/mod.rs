//! The session: one input's frames to a twin per interaction, the stages wired
//! one way.
//!
//! source -> ingestion thread (aim-capture: decode, undistort, pose, phases and
//! the hand-in / hand-out events) -> phase router (the calling thread: frames to
//! training views, cut to each object and bounded per phase) -> one worker per
//! interaction (a hand-in / hand-out window): stage I on the frames that showed
//! its object before the hand-in, while the motion is still arriving, then
//! stages II and III once its after-phase is over (the next hand-in, or the end
//! of the stream: the node tracker fits the motion on its whole window) -> its
//! twin. One stage trains at a time. Batch commands call the same stage code
//! (`run_static`, `run_dynamic`), so a dataset fed through a session gives the
//! stage commands' result (test `a_session_on_a_dataset_gives_the_stage_commands_result`).

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Mutex;
use std::time::Instant;

use aim_capture::crop::ObjectCrop;
use aim_capture::detect::{MotionEvent, ObjectRegion};
use aim_capture::ingest::{motion_time, Ingest, IngestConfig, IngestStats, Message};
use aim_capture::mps::{HandTracking, SemidensePoints, Trajectory};
use aim_capture::recording::{open_recording, Opened, RecordingOptions};
use aim_capture::source::{dataset_layout, DatasetLayout};
use aim_capture::undistort::UndistortConfig;
use aim_capture::{Frame, Phase};
use serde::Serialize;

use crate::error::{write_atomic, Error, Result};
use crate::mesh::tsdf::TsdfConfig;
use crate::train::config::StaticConfig;
use crate::train::dynamic_run::{
    run_dynamic, DynamicMetrics, DynamicOutcome, RunControl, StageTwoInput, StageTwoProgress,
};
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

/// How a session separates the objects from the room of a raw recording: stage
/// I learns an object and the room seen around it from crops around the
/// object's region, starting from the recording's SLAM points (the room's
/// Gaussians start where the room is, so they, not the region's, explain it);
/// the object is what lies in the region; stages II and III see the room as a
/// fixed backdrop behind it. A recording may show several objects, each
/// interaction moving one of them.
#[derive(Clone, Debug)]
pub struct RoomSetup {
    /// One crop per object region, in object_region.json's order.
    pub crops: Vec<ObjectCrop>,
    /// Stage I's initial points (the recording's MPS semidense points).
    pub points: crate::splat::ply::PointCloud,
    /// The recording's hand tracking and device poses, when it has them: each
    /// motion frame carries the palms seen at its time (the contact term of
    /// stage II's node tracking), and they say which object a hand took hold of.
    pub hands: Option<(HandTracking, Trajectory)>,
}

/// Hand samples this far from a frame's time are not its palms (MPS hand
/// tracking runs at 30-60 Hz).
const PALM_MAX_GAP_NS: i64 = 50_000_000;
/// Hands tracked with less confidence are not placed.
const PALM_MIN_CONFIDENCE: f64 = 0.5;

impl RoomSetup {
    /// Crops of each of `regions` at the trainers' resolution, every pixel kept.
    pub fn new(regions: Vec<ObjectRegion>, points: Vec<glam::Vec3>, cfg: &SessionConfig) -> Self {
        let size = [cfg.stage_one.resolution, cfg.stage_two.resolution].into_iter().max().unwrap_or(0);
        let size = if size == 0 { CROP_SIZE_AS_RECORDED } else { size };
        let crops = regions
            .into_iter()
            .map(|region| ObjectCrop { region, size, margin: aim_capture::crop::DEFAULT_MARGIN, mask_outside: false })
            .collect();
        RoomSetup { crops, points: crate::splat::ply::PointCloud { points, colors: None }, hands: None }
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

    /// The object an interaction that starts at `hand_in_s` takes hold of: the
    /// one nearest the palms seen then, or, without palms, the one nearest the
    /// middle of `frame`, the first frame of the motion (a wearer looks at what
    /// they take hold of).
    fn object_touched(&self, hand_in_s: f64, frame: &Frame) -> usize {
        let palms = self.palms_at(hand_in_s);
        let score = |crop: &ObjectCrop| -> f64 {
            let r = &crop.region;
            if palms.is_empty() {
                let centre = glam::DVec3::from_array(r.min).lerp(glam::DVec3::from_array(r.max), 0.5).as_vec3();
                let p = frame.world_to_camera.transform_point3(centre);
                if p.z > 0.0 {
                    f64::from(p.x.hypot(p.y) / p.z)
                } else {
                    f64::INFINITY
                }
            } else {
                palms.iter().map(|p| r.distance(p.as_dvec3())).fold(f64::INFINITY, f64::min)
            }
        };
        let scores: Vec<f64> = self.crops.iter().map(score).collect();
        (0..scores.len()).min_by(|&a, &b| scores[a].total_cmp(&scores[b])).unwrap_or(0)
    }

    /// The setup of the recording `input` as opened: its poses, object regions and
    /// SLAM points are all needed, and each missing one is named.
    pub fn for_recording(input: &Path, opened: &Opened, cfg: &SessionConfig) -> Result<Self> {
        if opened.trajectory_path.is_none() {
            return Err(Error::bad_file(
                input,
                "a recording needs its camera poses (an MPS closed_loop_trajectory.csv beside it, or --trajectory)",
            ));
        }
        if opened.regions.is_empty() {
            return Err(Error::bad_file(
                input,
                "a recording needs the object's region (object_region.json beside it, or --region \
                 x0,y0,z0,x1,y1,z1 in its trajectory's world frame): its frames show the whole room",
            ));
        }
        let Some(points_path) = &opened.points_path else {
            return Err(Error::bad_file(
                input,
                "a recording needs its SLAM points (MPS semidense_points.csv.gz beside it, or --points): without them \
                 the room behind the object is learnt inside the object's region (docs/session.md)",
            ));
        };
        let confident: Vec<glam::Vec3> =
            SemidensePoints::load(points_path)?.confident(MAX_POINT_DIST_STD).map(|p| p.as_vec3()).collect();
        // Evenly spaced in the file's order (the order the SLAM placed them in).
        let points: Vec<glam::Vec3> = (0..confident.len().min(MAX_SEED_POINTS))
            .map(|k| confident[k * confident.len() / confident.len().min(MAX_SEED_POINTS)])
            .collect();
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
        Ok(Self { hands, ..Self::new(opened.regions.clone(), points, cfg) })
    }

    /// Whether a Gaussian centred at `p` is object `object`'s: inside its region
    /// grown by `OBJECT_MARGIN` of its size, since a region drawn tight to the
    /// object has the object's surface Gaussians on both sides of its faces.
    fn contains(&self, object: usize, p: glam::Vec3) -> bool {
        let r = &self.crops[object].region;
        let (lo, hi) = (glam::Vec3::from(r.min.map(|v| v as f32)), glam::Vec3::from(r.max.map(|v| v as f32)));
        let margin = OBJECT_MARGIN * (hi - lo).max_element();
        p.cmpge(lo - margin).all() && p.cmple(hi + margin).all()
    }

    /// Stage I's result split: object `object` (Gaussians in its region) written
    /// to `object_ply`, and the room.
    fn split(&self, object: usize, static_ply: &Path, object_ply: &Path) -> Result<crate::splat::GaussianSet> {
        let set = crate::splat::ply::read_ply(static_ply)?;
        let inside: Vec<bool> = (0..set.len()).map(|i| self.contains(object, set.mean(i))).collect();
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

/// A live session's stage I runs this fraction of its schedule
/// ([`SessionConfig::go_live`]).
pub const LIVE_STAGE_ONE_FRACTION: f64 = 0.8;

impl SessionConfig {
    /// A live capture (`aim run --live`): frames are handed over at their
    /// recorded rate, the oldest buffered frame is dropped when training falls
    /// behind, and stage I runs [`LIVE_STAGE_ONE_FRACTION`] of its schedule. Its
    /// remainder is what delays the articulation most after the hand-out; on
    /// the six single-joint synthetic recordings 80 % of the cpu preset gave
    /// the same joints, 0.01-2 dB less stage I PSNR and 13 s less of stage I
    /// (docs/session.md, "Live").
    pub fn go_live(&mut self) {
        self.ingest.policy = aim_capture::ingest::Policy::Live;
        self.ingest.realtime = true;
        self.stage_one = self.stage_one.compressed(LIVE_STAGE_ONE_FRACTION);
    }

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

/// Stage I starts from at most this many SLAM points: each is a Gaussian, and a
/// stage I's cost grows with them. A longer scan places more points on the same
/// surfaces (a 15 s scan of the fridge: 52,000, and a stage I at 37 instead of 52
/// iterations a second); a little above the cpu preset's 10,000 random points, so
/// the default synthetic recording's 10,601 are all kept.
const MAX_SEED_POINTS: usize = 12_000;

/// How far past the region's faces a Gaussian still counts as the object's,
/// as a fraction of the region's largest side.
const OBJECT_MARGIN: f32 = 0.05;

/// Crop size when the presets train at the recorded resolution (0).
const CROP_SIZE_AS_RECORDED: u32 = 512;

/// What a session knows that its frames do not carry: held-out views for the
/// metrics and ground truth (a synthetic dataset's or recording's), when there
/// are any.
#[derive(Default)]
pub struct Reference {
    pub scan_test: Vec<TrainView>,
    pub motion_test: Vec<TrainView>,
    /// Folders with gt/joints.json, one per object in the order of the object
    /// regions (one for a dataset); empty without ground truth.
    pub ground_truth: Vec<PathBuf>,
}

impl Reference {
    /// The ground truth a synthetic recording carries: `recording`/gt for one
    /// object, `recording`/object_K/gt for each of several
    /// (`aim synth-recording`).
    pub fn recording_ground_truth(recording: &Path) -> Vec<PathBuf> {
        use crate::eval::twin::has_ground_truth;
        if has_ground_truth(recording) {
            return vec![recording.to_path_buf()];
        }
        (0..)
            .map(|k| crate::synth::recording::object_ground_truth(recording, k))
            .take_while(|dir| has_ground_truth(dir))
            .collect()
    }
}

/// A recording's frames undistorted for training, before the object crop: the
/// Aria RGB camera's full field at about its native sampling.
pub const TRAIN_UNDISTORT: UndistortConfig = UndistortConfig { width: 704, height: 704, focal: 300.0, upright: false };

/// Open a session's input: a dataset (AiM layout, nerfstudio, COLMAP; its
/// held-out views and ground truth, when it has them, as the reference) or a
/// recording read with `recording` (the object cut out of the room: `cfg.room`
/// is set from its MPS points and object regions; its synthetic ground truth as
/// the reference).
pub fn open_input(input: &Path, recording: &RecordingOptions, cfg: &mut SessionConfig) -> Result<(Opened, Reference)> {
    if !input.exists() {
        return Err(Error::bad_file(input, "no such file or folder"));
    }
    match dataset_layout(input) {
        Some(layout) => {
            let reference = if layout == DatasetLayout::Aim {
                let test = |phase: Phase, width: u32| -> Result<Vec<TrainView>> {
                    Ok(crate::train::views::load_phase_views(input, phase, width, false)?.1)
                };
                Reference {
                    scan_test: test(Phase::Scan, cfg.stage_one.resolution)?,
                    motion_test: test(Phase::Motion, cfg.stage_two.resolution)?,
                    ground_truth: if crate::eval::twin::has_ground_truth(input) {
                        vec![input.to_path_buf()]
                    } else {
                        Vec::new()
                    },
                }
            } else {
                Reference::default()
            };
            Ok((open_recording(input, &RecordingOptions::default())?, reference))
        }
        None => {
            let opened = open_recording(input, recording)?;
            cfg.room = Some(RoomSetup::for_recording(input, &opened, cfg)?);
            let ground_truth = Reference::recording_ground_truth(input);
            Ok((opened, Reference { ground_truth, ..Reference::default() }))
        }
    }
}

/// Where a session stops early and what it logs to.
pub struct SessionControl<'a> {
    /// Raised (Ctrl-C): the running stage checkpoints and the session stops.
    pub interrupt: &'a AtomicBool,
    pub viz: &'a Viz,
    /// The backend stages I and II render with (see `RunControl::backend`).
    pub backend: crate::render::Backend,
    /// Continue each stage from its checkpoint in the session's folder, where
    /// there is one (an interrupted or killed session run again on the same
    /// input and configuration); a finished stage is then only written again.
    pub resume: bool,
}

/// What a session reports as it goes (from the router and the workers).
/// Interactions count from 0; one stage trains at a time, so the step reports
/// belong to the interaction whose stage started last.
pub enum SessionEvent<'a> {
    Window(MotionEvent),
    StageOneStarted {
        interaction: usize,
        object: usize,
        views: usize,
        /// Its schedule's length (a resumed stage starts past 0).
        iterations: u32,
    },
    StageOne(&'a StepReport),
    StageTwoStarted {
        interaction: usize,
        motion: usize,
        end: usize,
        iterations: u32,
    },
    StageTwo(&'a DynamicStep),
    /// An interaction's parts and joints are known (its meshes and export follow),
    /// `hand_out_to_articulation_s` after its hand-out arrived.
    Articulated {
        interaction: usize,
        parts: &'a [PartEstimate],
        hand_out_to_articulation_s: Option<f64>,
    },
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
    /// Frames no object region was in view of (cropped inputs): not used.
    pub frames_without_object: usize,
    /// Every hand-in and hand-out as the ingestion thread saw them (frame index
    /// and seconds on the source's clock; a dataset's clock is nominal, per phase).
    pub events: Vec<MotionEvent>,
    pub ingest: IngestStats,
    /// One per hand-in that gave a twin, in time order.
    pub interactions: Vec<InteractionReport>,
    /// The interactions that failed (their error; the session then exits with it).
    pub failed: Vec<InteractionFailure>,
    /// Why the stream ended early, if it did (a recording unreadable from some
    /// frame on); the interactions before it are kept.
    pub stream_error: Option<String>,
    /// rerun log items dropped because the logging thread fell behind.
    pub log_items_dropped: u64,
    /// From the start of the session to the last twin written (wall clock).
    pub wall_s: f64,
}

/// What one interaction gave.
#[derive(Clone, Debug, Serialize)]
pub struct InteractionReport {
    /// Its folder under the session's (interaction_K, K from 1).
    pub dir: String,
    /// The object region it moved (0-based, object_region.json's order).
    pub object: usize,
    /// Its hand-in and hand-out.
    pub events: Vec<MotionEvent>,
    pub frames: PhaseCounts,
    pub stage_one: StaticMetrics,
    pub stage_two: DynamicMetrics,
    /// From the moment its hand-out event arrived to its parts and joints known:
    /// how far the articulation lags behind the capture (`aim run --live`).
    pub hand_out_to_articulation_s: Option<f64>,
    /// From the same moment to its twin written (the meshes and the export after
    /// the articulation).
    pub hand_out_to_twin_s: Option<f64>,
}

/// An interaction that gave no twin, and why.
#[derive(Clone, Debug, Serialize)]
pub struct InteractionFailure {
    /// Its folder under the session's (interaction_K).
    pub dir: String,
    pub error: String,
}

/// How a session ended.
pub enum SessionOutcome {
    Finished {
        /// Each interaction's parts, in the report's order.
        parts: Vec<Vec<PartEstimate>>,
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

    /// Whether the view was kept (it may be dropped later, as the store thins out).
    fn push(&mut self, timestamp_s: f64, view: TrainView) -> bool {
        let keep = self.seen.is_multiple_of(self.stride);
        self.seen += 1;
        if !keep {
            return false;
        }
        if self.views.len() == self.cap {
            let mut k = 0;
            self.views.retain(|_| {
                k += 1;
                k % 2 == 1
            });
            self.stride *= 2;
            if !(self.seen - 1).is_multiple_of(self.stride) {
                return false;
            }
        }
        self.views.push((timestamp_s, view));
        true
    }

    /// Its views, oldest first, leaving it empty.
    fn take(&mut self) -> Vec<TrainView> {
        let cap = self.cap;
        std::mem::replace(self, FrameStore::new(cap)).views.into_iter().map(|(_, v)| v).collect()
    }
}

/// The frames an interaction's stages II and III learn from, handed to its
/// worker when its after-phase is over.
struct MotionFrames {
    /// The scan, when stage I trained on it as it arrived (the worker has it
    /// otherwise): stage II reads its cameras, the report counts it.
    arrived_scan: Option<Vec<TrainView>>,
    motion: Vec<(f64, TrainView)>,
    end: Vec<TrainView>,
    events: Vec<MotionEvent>,
    hand_out_at: Option<Instant>,
}

/// An interaction whose scan, motion or after-phase frames are arriving.
struct OpenInteraction<'scope> {
    object: usize,
    /// Its scan, sent on to its stage I as it arrives (the first interaction of a
    /// one-object recording, before its hand-in); None once the hand-in closed it.
    scan_feed: Option<crossbeam_channel::Sender<TrainView>>,
    arrived_scan: Option<Vec<TrainView>>,
    motion: FrameStore,
    after: FrameStore,
    events: Vec<MotionEvent>,
    hand_out_at: Option<Instant>,
    frames: crossbeam_channel::Sender<MotionFrames>,
    worker: WorkerHandle<'scope>,
}

/// An interaction's worker: its parts and report, None when interrupted.
type WorkerHandle<'scope> =
    std::thread::ScopedJoinHandle<'scope, Result<Option<(Vec<PartEstimate>, InteractionReport)>>>;

impl<'scope> OpenInteraction<'scope> {
    /// Its frames are all in: hand them to its worker.
    fn close(self) -> WorkerHandle<'scope> {
        let frames = MotionFrames {
            arrived_scan: self.arrived_scan,
            motion: self.motion.views,
            end: self.after.views.into_iter().map(|(_, v)| v).collect(),
            events: self.events,
            hand_out_at: self.hand_out_at,
        };
        // A worker that stopped (interrupted, or failed in stage I) no longer listens.
        let _ = self.frames.send(frames);
        self.worker
    }
}

/// Run `opened` through the ingestion thread to a twin per interaction in `out`
/// (interaction_K/static: stage I, interaction_K/dynamic: stages II and III and
/// the twin; session.json).
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
    let started = Instant::now();
    control.viz.send_session_blueprint();
    let objects = cfg.room.as_ref().map_or(1, |r| r.crops.len());
    let ingest = Ingest::spawn(opened.source, opened.processor, opened.tagger, cfg.ingest.clone())
        .map_err(|e| Error::Other(format!("starting the ingestion thread: {e}")))?;
    let turns = TrainingTurns::default();
    let worker =
        InteractionWorker { reference: &reference, out, cfg, control, on_event, turns: &turns, source: &source };
    std::thread::scope(|scope| {
        // Per object, the frames that showed it outside any motion: the scan of
        // its next interaction.
        let mut scans: Vec<FrameStore> = (0..objects).map(|_| FrameStore::new(cfg.max_frames_per_phase)).collect();
        let mut events = Vec::new();
        let mut hand_in = None;
        let mut open: Option<OpenInteraction> = None;
        let mut closed = Vec::new();
        let mut frames_without_object = 0;
        // A recording of one object: its first interaction's stage I starts with
        // the first frame that shows it, on the scan as it arrives.
        let start_early = cfg.room.as_ref().is_some_and(|r| r.crops.len() == 1);
        let mut early: Option<OpenInteraction> = None;
        // The stream failing (a recording unreadable from some point on) ends it:
        // the interactions already whole still give their twins.
        let mut stream_error = None;
        for message in &ingest {
            if control.interrupt.load(Ordering::SeqCst) {
                break;
            }
            let frame = match message {
                Message::Frame(f) => f,
                Message::Event(e) => {
                    match (e, open.as_mut()) {
                        (MotionEvent::HandIn { .. }, _) => hand_in = Some(e),
                        (MotionEvent::HandOut { .. }, Some(o)) => {
                            o.hand_out_at = Some(Instant::now());
                            o.events.push(e);
                        }
                        (MotionEvent::HandOut { .. }, None) => {}
                    }
                    control.viz.text("session/events", &format!("{e:?}"));
                    on_event(SessionEvent::Window(e));
                    events.push(e);
                    continue;
                }
                Message::Error(e) => {
                    stream_error = Some(Error::from(e).to_string());
                    break;
                }
            };
            log_frame(control.viz, &frame);
            if let Some(e) = hand_in.take() {
                // The first frame of a motion: the last interaction's after-phase is
                // over, and this one's object is known.
                if let Some(o) = open.take() {
                    closed.push(o.close());
                }
                let MotionEvent::HandIn { timestamp_s, .. } = e else { unreachable!("only hand-ins wait") };
                let object = cfg.room.as_ref().map_or(0, |room| room.object_touched(timestamp_s, &frame));
                let scan = scans[object].take();
                let interaction = match early.take() {
                    // Its stage I has been training on the scan: the scan is complete.
                    Some(started) => {
                        OpenInteraction { scan_feed: None, arrived_scan: Some(scan), events: vec![e], ..started }
                    }
                    None if scan.is_empty() => return Err(Error::bad_file(
                        &frame.source,
                        "the motion begins before any frame showed the object: no scan of its start state to train on",
                    )),
                    None => worker.open(scope, closed.len(), object, scan, None, vec![e], cfg.max_frames_per_phase),
                };
                open = Some(interaction);
            }
            let mut seen = false;
            for (object, scan) in scans.iter_mut().enumerate() {
                let frame = match &cfg.room {
                    None => frame.clone(),
                    Some(room) => match room.crops[object].apply(&frame) {
                        Some(f) => f,
                        None => continue,
                    },
                };
                seen = true;
                let after_a_motion = open.is_some() || !closed.is_empty();
                let current = open.as_mut().filter(|o| o.object == object);
                match (frame.phase, current) {
                    (Phase::Motion, Some(o)) => {
                        let mut view = TrainView::from_frame(&frame, cfg.stage_two.resolution)?;
                        if let Some(room) = &cfg.room {
                            view.palms = room.palms_at(frame.timestamp_s);
                        }
                        o.motion.push(frame.timestamp_s, view);
                    }
                    // Another object's motion: this one stands still, but the
                    // moving one may reach into its crop.
                    (Phase::Motion, None) => {}
                    (Phase::Scan, _) if after_a_motion => {
                        tracing::warn!("{}: a scan frame after the motion began; not used", frame.source);
                    }
                    (Phase::Scan, _) if start_early => {
                        let view = TrainView::from_frame(&frame, cfg.stage_one.resolution)?;
                        match &early {
                            None => {
                                let first = vec![view.clone()];
                                let (feed, arriving) = crossbeam_channel::unbounded();
                                let mut started = worker.open(
                                    scope,
                                    0,
                                    object,
                                    first,
                                    Some(arriving),
                                    Vec::new(),
                                    cfg.max_frames_per_phase,
                                );
                                started.scan_feed = Some(feed);
                                early = Some(started);
                                scan.push(frame.timestamp_s, view);
                            }
                            Some(started) => {
                                // Stage I gets what the store keeps (bounded as it is).
                                if scan.push(frame.timestamp_s, view.clone()) {
                                    if let Some(feed) = &started.scan_feed {
                                        let _ = feed.send(view);
                                    }
                                }
                            }
                        }
                    }
                    (phase, current) => {
                        if let (Phase::After, Some(o)) = (phase, current) {
                            o.after.push(frame.timestamp_s, TrainView::from_frame(&frame, cfg.stage_two.resolution)?);
                        }
                        scan.push(frame.timestamp_s, TrainView::from_frame(&frame, cfg.stage_one.resolution)?);
                    }
                }
            }
            if !seen {
                frames_without_object += 1;
            }
        }
        let (stats, _) = ingest.stop();
        let interrupted = control.interrupt.load(Ordering::SeqCst);
        // A stage I started on a scan that no hand-in followed: its feed closes,
        // and without frames to hand over its worker stops after stage I.
        let unfinished = early.take().map(|o| o.worker);
        match open.take() {
            // Interrupted: its worker sees the channel close and stops.
            Some(o) if interrupted => closed.push(o.worker),
            Some(o) => closed.push(o.close()),
            None => {}
        }
        if closed.is_empty() {
            if let Some(worker) = unfinished {
                let _ = worker.join();
            }
            if interrupted {
                return Ok(SessionOutcome::Interrupted);
            }
            if let Some(e) = stream_error {
                return Err(Error::Other(e));
            }
            let scanned: usize = scans.iter().map(|s| s.views.len()).sum();
            return Err(Error::Unusable(format!(
                "{source}: no interaction found ({scanned} scan frame(s), no hand-in): nothing moved, so there is no articulation to learn"
            )));
        }
        let mut parts = Vec::new();
        let mut interactions = Vec::new();
        let mut failed = Vec::new();
        // Closed in hand-in order: handle k is interaction_{k + 1}.
        for (k, handle) in closed.into_iter().enumerate() {
            match handle.join().map_err(|_| Error::Other("an interaction's worker panicked".into()))? {
                Ok(Some((p, report))) => {
                    parts.push(p);
                    interactions.push(report);
                }
                Ok(None) => return Ok(SessionOutcome::Interrupted),
                // One interaction's failure leaves the others' twins standing.
                Err(e) => {
                    failed.push(InteractionFailure { dir: format!("interaction_{}", k + 1), error: e.to_string() })
                }
            }
        }
        let report = SessionReport {
            source: source.clone(),
            frames_without_object,
            events,
            ingest: stats,
            interactions,
            failed,
            stream_error,
            log_items_dropped: control.viz.dropped_items(),
            wall_s: started.elapsed().as_secs_f64(),
        };
        let json = serde_json::to_vec_pretty(&report).map_err(|e| Error::Other(e.to_string()))?;
        write_atomic(&out.join("session.json"), &json)?;
        if !report.failed.is_empty() || report.stream_error.is_some() {
            let errors: Vec<String> = (report.stream_error.iter().cloned())
                .chain(report.failed.iter().map(|f| format!("{}: {}", f.dir, f.error)))
                .collect();
            return Err(Error::Other(format!(
                "{}; {} interaction(s) gave their twin (listed in {})",
                errors.join("; "),
                report.interactions.len(),
                out.join("session.json").display()
            )));
        }
        Ok(SessionOutcome::Finished { parts, report: Box::new(report) })
    })
}

/// What every interaction's worker shares.
struct InteractionWorker<'a> {
    reference: &'a Reference,
    out: &'a Path,
    cfg: &'a SessionConfig,
    control: &'a SessionControl<'a>,
    on_event: &'a (dyn Fn(SessionEvent) + Sync),
    turns: &'a TrainingTurns,
    source: &'a str,
}

/// One stage trains at a time (the machine's cores go to it), and of the stages
/// waiting, the earliest interaction's goes first: an interaction's twin comes
/// before the next one's stage I.
#[derive(Default)]
struct TrainingTurns {
    /// Whether a stage is training, and the interactions waiting for their turn.
    state: Mutex<(bool, std::collections::BTreeSet<usize>)>,
    changed: std::sync::Condvar,
}

/// A stage's turn to train, given back when dropped.
struct Turn<'a>(&'a TrainingTurns);

impl TrainingTurns {
    /// Wait for `interaction`'s turn.
    fn take(&self, interaction: usize) -> Turn<'_> {
        let mut state = self.state.lock().unwrap_or_else(|e| e.into_inner());
        state.1.insert(interaction);
        while state.0 || state.1.first() != Some(&interaction) {
            state = self.changed.wait(state).unwrap_or_else(|e| e.into_inner());
        }
        state.1.remove(&interaction);
        state.0 = true;
        Turn(self)
    }
}

impl Drop for Turn<'_> {
    fn drop(&mut self) {
        self.0.state.lock().unwrap_or_else(|e| e.into_inner()).0 = false;
        self.0.changed.notify_all();
    }
}

impl<'a> InteractionWorker<'a> {
    /// Interaction `interaction` on object `object`, its worker started on
    /// `scope` with stage I's views `scan` (and `arriving`, the rest of the scan
    /// as it arrives, if it is still arriving).
    #[allow(clippy::too_many_arguments)]
    fn open<'scope>(
        &'scope self,
        scope: &'scope std::thread::Scope<'scope, '_>,
        interaction: usize,
        object: usize,
        scan: Vec<TrainView>,
        arriving: Option<crossbeam_channel::Receiver<TrainView>>,
        events: Vec<MotionEvent>,
        max_frames: usize,
    ) -> OpenInteraction<'scope> {
        let (frames, handed_over) = crossbeam_channel::bounded(1);
        OpenInteraction {
            object,
            scan_feed: None,
            arrived_scan: None,
            motion: FrameStore::new(max_frames),
            after: FrameStore::new(max_frames),
            events,
            hand_out_at: None,
            frames,
            worker: scope.spawn(move || self.run(interaction, object, scan, arriving, handed_over)),
        }
    }

    /// Interaction `interaction` on object `object`: stage I on its scan while
    /// its motion arrives, then stages II and III on the frames `frames` hands
    /// over when its after-phase is over. None: interrupted, or no hand-in came.
    fn run(
        &self,
        interaction: usize,
        object: usize,
        scan: Vec<TrainView>,
        arriving: Option<crossbeam_channel::Receiver<TrainView>>,
        frames: crossbeam_channel::Receiver<MotionFrames>,
    ) -> Result<Option<(Vec<PartEstimate>, InteractionReport)>> {
        let (cfg, control, on_event) = (self.cfg, self.control, self.on_event);
        let dir_name = format!("interaction_{}", interaction + 1);
        let dir = self.out.join(&dir_name);
        let static_dir = dir.join("static");
        let turn = self.turns.take(interaction);
        let stage_one = {
            control.viz.text(
                "session/events",
                &format!(
                    "interaction {}: stage I starts on {} scan frame(s){}",
                    interaction + 1,
                    scan.len(),
                    if arriving.is_some() { ", more arriving" } else { "" }
                ),
            );
            on_event(SessionEvent::StageOneStarted {
                interaction,
                object,
                views: scan.len(),
                iterations: cfg.stage_one.iterations,
            });
            let setup = RunSetup {
                run_dir: &static_dir,
                resume: control.resume,
                init: cfg.room.as_ref().map(|r| &r.points),
                arriving: arriving.as_ref(),
                backend: control.backend.clone(),
            };
            run_static(
                cfg.stage_one.clone(),
                &scan,
                &self.reference.scan_test,
                &setup,
                control.interrupt,
                control.viz,
                |r| on_event(SessionEvent::StageOne(r)),
            )?
        };
        let RunOutcome::Finished(stage_one) = stage_one else { return Ok(None) };
        // Its frames already here (a replay, or a long stage I): its turn goes on
        // into stages II and III. Else the turn is given back while they arrive.
        // The router closes the channel without frames when interrupted.
        let (handed_over, _turn) = match frames.try_recv() {
            Ok(handed_over) => (handed_over, turn),
            Err(_) => {
                drop(turn);
                let Ok(handed_over) = frames.recv() else { return Ok(None) };
                (handed_over, self.turns.take(interaction))
            }
        };
        let MotionFrames { arrived_scan, motion, end, events, hand_out_at } = handed_over;
        let scan = arrived_scan.unwrap_or(scan);
        if control.interrupt.load(Ordering::SeqCst) {
            return Ok(None);
        }
        let motion = timed_motion(motion, &events, self.source)?;
        let counts = PhaseCounts { scan: scan.len(), motion: motion.len(), after: end.len() };
        control.viz.text(
            "session/events",
            &format!(
                "interaction {}: stages II and III start on {} motion and {} end-state frames",
                interaction + 1,
                counts.motion,
                counts.after
            ),
        );
        on_event(SessionEvent::StageTwoStarted {
            interaction,
            motion: counts.motion,
            end: counts.after,
            iterations: cfg.stage_two.iterations,
        });
        let mut input = StageTwoInput {
            source: PathBuf::from(self.source),
            motion,
            test: self.reference.motion_test.clone(),
            scan,
            end,
            ground_truth: self.reference.ground_truth.get(object).cloned(),
        };
        let mut start_state = static_dir.join("static.ply");
        if let Some(room) = &cfg.room {
            let object_ply = static_dir.join("object.ply");
            let room_set = room.split(object, &start_state, &object_ply)?;
            set_backdrops(&mut input.motion, &room_set);
            set_backdrops(&mut input.end, &room_set);
            start_state = object_ply;
        }
        let run_control = RunControl {
            resume: control.resume,
            interrupt: control.interrupt,
            viz: control.viz,
            backend: control.backend.clone(),
        };
        let mut hand_out_to_articulation_s = None;
        let outcome = run_dynamic(
            input,
            &start_state,
            &dir.join("dynamic"),
            cfg.stage_two.clone(),
            &cfg.mesh,
            &run_control,
            |p| match p {
                StageTwoProgress::Step(s) => on_event(SessionEvent::StageTwo(s)),
                StageTwoProgress::Articulated(parts) => {
                    hand_out_to_articulation_s = hand_out_at.map(|t| t.elapsed().as_secs_f64());
                    on_event(SessionEvent::Articulated { interaction, parts, hand_out_to_articulation_s });
                }
            },
        )?;
        let DynamicOutcome::Finished { parts, metrics } = outcome else { return Ok(None) };
        let report = InteractionReport {
            dir: dir_name,
            object,
            events,
            frames: counts,
            stage_one: *stage_one,
            stage_two: *metrics,
            hand_out_to_articulation_s,
            hand_out_to_twin_s: hand_out_at.map(|t| t.elapsed().as_secs_f64()),
        };
        Ok(Some((parts, report)))
    }
}

/// The motion frames with their time in [0, 1]: the one the source gave, or
/// from the detected window (`aim_capture::ingest::motion_time`).
fn timed_motion(frames: Vec<(f64, TrainView)>, events: &[MotionEvent], source: &str) -> Result<Vec<TrainView>> {
    if frames.is_empty() {
        return Err(Error::Unusable(format!("{source}: no motion frames between hand-in and hand-out")));
    }
    frames
        .into_iter()
        .map(|(t, mut v)| {
            if v.time.is_none() {
                v.time = Some(motion_time(t, events).ok_or_else(|| {
                    Error::Unusable(format!(
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
        let kept_on_push: Vec<bool> = (0..1000).map(|k| store.push(k as f64, view(k))).collect();
        let kept: Vec<usize> = store.views.iter().map(|(t, _)| *t as usize).collect();
        // What it keeps now it kept when it came (a live stage I got it then).
        assert!(kept.iter().all(|&k| kept_on_push[k]));
        assert!(kept.len() <= 64 && kept.len() >= 32, "{} kept", kept.len());
        // Evenly strided from the first frame to near the last.
        let stride = kept[1] - kept[0];
        assert_eq!(stride, 16);
        assert!(kept.windows(2).all(|w| w[1] - w[0] == stride), "{kept:?}");
        assert_eq!(kept[0], 0);
        assert!(*kept.last().unwrap() >= 1000 - stride, "{kept:?}");
        // Under the cap nothing is dropped.
        let mut small = FrameStore::new(64);
        assert!((0..64).all(|k| small.push(k as f64, view(k))));
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
