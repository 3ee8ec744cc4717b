//! Opening a recording with everything that goes with it: the frame source, MPS
//! trajectory and hand tracking found beside it, the object region, the undistortion
//! and the motion-window detector. Used by `aim capture ...`, the live session and tests.
//!
//! MPS files are looked for in the MPS output folder when one is given
//! (`RecordingOptions::mps`), else beside the recording (a `.vrs` file's folder, or
//! the recording folder) in `mps/` and then in the folder itself: in each,
//! `slam/closed_loop_trajectory.csv` (or under `trajectory/`, or flat);
//! `hand_tracking/wrist_and_palm_poses.csv` (or flat, or
//! `hand_tracking/hand_tracking_results.csv`); `slam/semidense_points.csv.gz` (or
//! `.csv`, or flat). `object_region.json` (`{"min": [x, y, z], "max": [x, y, z]}`,
//! world frame, or a list of them: one per object the recording's interactions
//! move) is looked for beside the recording.

use std::path::{Path, PathBuf};

use serde::Serialize;

use crate::calib::CameraCalibration;
use crate::detect::{
    window_of, Evidence, ExplicitEvidence, HandTrackingEvidence, MotionEvent, NoEvidence, ObjectRegion, SkinEvidence,
};
use crate::error::{Error, Result};
use crate::frame::{Frame, Phase};
use crate::ingest::{collect_all, IngestStats};
use crate::mps::{HandTracking, Trajectory};
use crate::pipeline::{PhaseTagger, Processor};
use crate::source::{open_source, FrameSource};
use crate::undistort::UndistortConfig;

/// Which motion-window detector to use.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum DetectorKind {
    /// MPS hand tracking when a hand-tracking CSV is available, else skin colour.
    Auto,
    Mps,
    Skin,
    /// Explicit hand-in / hand-out seconds.
    Explicit(f64, f64),
    None,
}

impl std::str::FromStr for DetectorKind {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "auto" => Ok(DetectorKind::Auto),
            "mps" => Ok(DetectorKind::Mps),
            "skin" => Ok(DetectorKind::Skin),
            "none" => Ok(DetectorKind::None),
            other => {
                let parts: Vec<&str> = other.split(',').collect();
                if let [a, b] = parts[..] {
                    if let (Ok(a), Ok(b)) = (a.trim().parse(), b.trim().parse()) {
                        return Ok(DetectorKind::Explicit(a, b));
                    }
                }
                Err(format!("detector must be auto, mps, skin, none or HAND_IN_S,HAND_OUT_S; got {other:?}"))
            }
        }
    }
}

#[derive(Clone, Debug)]
pub struct RecordingOptions {
    pub undistort: UndistortConfig,
    pub trajectory: Option<PathBuf>,
    pub hands: Option<PathBuf>,
    /// MPS semidense_points.csv(.gz).
    pub points: Option<PathBuf>,
    /// An MPS output folder (slam/, hand_tracking/) to find the files above in,
    /// instead of beside the recording.
    pub mps: Option<PathBuf>,
    pub region: Option<ObjectRegion>,
    pub vignetting: Option<PathBuf>,
    /// MPS online_calibration.jsonl: use the camera-rgb of its first line (the start of
    /// the recording) instead of the factory calibration.
    pub online_calibration: Option<PathBuf>,
    pub detector: DetectorKind,
    /// Frame rate assumed for folders without timestamps.
    pub fps: f64,
    /// Look for MPS files and object_region.json beside the recording.
    pub discover: bool,
}

impl Default for RecordingOptions {
    fn default() -> Self {
        RecordingOptions {
            undistort: UndistortConfig::aria_default(),
            trajectory: None,
            hands: None,
            points: None,
            mps: None,
            region: None,
            vignetting: None,
            online_calibration: None,
            detector: DetectorKind::Auto,
            fps: 30.0,
            discover: true,
        }
    }
}

/// (frame index, timestamp in seconds, detector evidence).
pub type EvidenceSample = (usize, f64, f32);

/// An opened recording, ready to run on a thread ([`crate::ingest::Ingest::spawn`]) or
/// in batch ([`Opened::collect`]).
pub struct Opened {
    pub source: Box<dyn FrameSource>,
    pub processor: Processor,
    pub tagger: PhaseTagger,
    pub camera: Option<CameraCalibration>,
    pub trajectory_path: Option<PathBuf>,
    pub hands_path: Option<PathBuf>,
    /// MPS semidense points found beside the recording.
    pub points_path: Option<PathBuf>,
    /// The object regions (object_region.json or --region); empty when none is known.
    pub regions: Vec<ObjectRegion>,
}

impl Opened {
    /// Process every frame on the calling thread (rayon) and return them with events.
    pub fn collect(self) -> (Vec<Frame>, Vec<MotionEvent>, IngestStats) {
        let (f, e, s, _) = self.collect_with_evidence();
        (f, e, s)
    }

    /// As [`Opened::collect`], plus each frame's detector evidence (index, seconds, score).
    pub fn collect_with_evidence(mut self) -> (Vec<Frame>, Vec<MotionEvent>, IngestStats, Vec<EvidenceSample>) {
        let (f, e, s) = collect_all(self.source.as_mut(), &self.processor, &mut self.tagger);
        (f, e, s, std::mem::take(&mut self.tagger.trace))
    }
}

fn first_existing(base: &Path, names: &[&str]) -> Option<PathBuf> {
    names.iter().map(|n| base.join(n)).find(|p| p.is_file())
}

/// The first of `names` (relative to an MPS output folder) in any of `roots`, in order.
fn find_mps(roots: &[PathBuf], names: &[&str]) -> Option<PathBuf> {
    roots.iter().find_map(|r| first_existing(r, names))
}

/// Open a recording (VRS file, synthetic Aria-like folder, image folder, AiM dataset).
pub fn open_recording(path: &Path, opts: &RecordingOptions) -> Result<Opened> {
    let source = open_source(path, opts.fps)?;
    let base = if path.is_dir() { path.to_path_buf() } else { path.parent().unwrap_or(Path::new(".")).to_path_buf() };
    let mps_roots = match &opts.mps {
        Some(dir) if dir.is_dir() => vec![dir.clone()],
        Some(dir) => return Err(Error::bad_file(dir, "no such MPS folder")),
        None if opts.discover => vec![base.join("mps"), base.clone()],
        None => Vec::new(),
    };
    let find = |given: &Option<PathBuf>, names: &[&str]| given.clone().or_else(|| find_mps(&mps_roots, names));
    let trajectory_path = find(
        &opts.trajectory,
        &["slam/closed_loop_trajectory.csv", "trajectory/closed_loop_trajectory.csv", "closed_loop_trajectory.csv"],
    );
    let hands_path = find(
        &opts.hands,
        &[
            "hand_tracking/wrist_and_palm_poses.csv",
            "wrist_and_palm_poses.csv",
            "hand_tracking/hand_tracking_results.csv",
        ],
    );
    let points_path = find(
        &opts.points,
        &[
            "slam/semidense_points.csv.gz",
            "semidense_points.csv.gz",
            "slam/semidense_points.csv",
            "semidense_points.csv",
        ],
    );
    let regions = match opts.region {
        Some(r) => vec![r],
        None if opts.discover => match first_existing(&base, &["object_region.json"]) {
            Some(p) => read_regions(&p)?,
            None => Vec::new(),
        },
        None => Vec::new(),
    };
    let vignetting = match &opts.vignetting {
        Some(p) => Some(image::open(p).map_err(|e| Error::bad_file(p, e.to_string()))?.to_luma8()),
        None => None,
    };
    let mut camera = source.camera();
    if let Some(p) = &opts.online_calibration {
        camera = Some(online_rgb_camera(p, camera.as_ref())?);
    }
    let trajectory = trajectory_path.as_deref().map(Trajectory::load).transpose()?;
    let processor = Processor::new(camera.as_ref(), &opts.undistort, vignetting.as_ref()).with_trajectory(trajectory);
    let hands = match (&hands_path, opts.detector) {
        (Some(p), DetectorKind::Auto | DetectorKind::Mps) => Some(HandTracking::load(p)?),
        _ => None,
    };
    let evidence: Box<dyn Evidence> = match (opts.detector, hands) {
        (DetectorKind::Auto | DetectorKind::Mps, Some(h)) => Box::new(HandTrackingEvidence::new(h, regions.clone())),
        (DetectorKind::Mps, None) => {
            return Err(Error::bad_file(
                path,
                "detector mps needs a hand-tracking CSV (--hands or beside the recording)",
            ))
        }
        (DetectorKind::Auto | DetectorKind::Skin, _) => {
            Box::new(SkinEvidence { regions: regions.clone(), ..SkinEvidence::default() })
        }
        (DetectorKind::Explicit(a, b), _) => Box::new(ExplicitEvidence { hand_in_s: a, hand_out_s: b }),
        (DetectorKind::None, _) => Box::new(NoEvidence),
    };
    Ok(Opened {
        source,
        processor,
        tagger: PhaseTagger::new(evidence),
        camera,
        trajectory_path,
        hands_path,
        points_path,
        regions,
    })
}

/// object_region.json: one region, or a list of them (one per object).
fn read_regions(path: &Path) -> Result<Vec<ObjectRegion>> {
    #[derive(serde::Deserialize)]
    #[serde(untagged)]
    enum RegionFile {
        One(ObjectRegion),
        Several(Vec<ObjectRegion>),
    }
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    let regions = match serde_json::from_str(&text) {
        Ok(RegionFile::One(r)) => vec![r],
        Ok(RegionFile::Several(list)) => list,
        Err(_) => {
            return Err(Error::bad_file(
                path,
                "object region: expected {\"min\": [x, y, z], \"max\": [x, y, z]} or a list of such regions",
            ))
        }
    };
    let ordered = |r: &ObjectRegion| (0..3).all(|a| r.min[a] < r.max[a]);
    match regions.iter().position(|r| !ordered(r)) {
        _ if regions.is_empty() => Err(Error::bad_file(path, "object region: the list is empty")),
        Some(k) => Err(Error::bad_file(path, format!("object region {k}: min must be below max on every axis"))),
        None => Ok(regions),
    }
}

/// The RGB camera of the first line of an online_calibration.jsonl, at the resolution of
/// `like` (the source's own calibration) or 1408.
fn online_rgb_camera(path: &Path, like: Option<&CameraCalibration>) -> Result<CameraCalibration> {
    let lines = crate::calib::load_online_calibration(path)?;
    let first = lines.first().ok_or_else(|| Error::bad_file(path, "no calibration lines"))?;
    let cam = first.calibration.rgb(path)?;
    let (w, h) = like.map(|c| (c.width, c.height)).unwrap_or((1408, 1408));
    cam.rescaled_to(w, h).map_err(|e| Error::bad_file(path, e))
}

/// `aim capture inspect` report.
#[derive(Clone, Debug, Serialize)]
pub struct InspectReport {
    pub recording: String,
    pub source: String,
    pub streams: Vec<StreamReport>,
    pub frame_count: usize,
    pub width: Option<u32>,
    pub height: Option<u32>,
    pub calibration: Option<CalibrationReport>,
    pub timestamps_ns: Vec<i64>,
    pub time_span_s: Option<f64>,
    pub trajectory: Option<String>,
    pub hand_tracking: Option<String>,
    pub detector: String,
    pub frames_posed: usize,
    pub hand_in_s: Option<f64>,
    pub hand_out_s: Option<f64>,
    pub events: Vec<MotionEvent>,
    pub phase_counts: [usize; 3],
    pub stats: IngestStats,
    /// Detector evidence per processed frame, in frame order.
    pub evidence: Vec<f32>,
}

#[derive(Clone, Debug, Serialize)]
pub struct StreamReport {
    pub id: String,
    pub name: Option<String>,
    pub records: usize,
}

#[derive(Clone, Debug, Serialize)]
pub struct CalibrationReport {
    pub label: String,
    pub model: String,
    pub width: u32,
    pub height: u32,
    pub params: Vec<f64>,
    /// T_Device_Camera: translation (m) and quaternion (x, y, z, w).
    pub t_device_camera_translation: [f64; 3],
    pub t_device_camera_quaternion_xyzw: [f64; 4],
}

/// Inspect a recording: streams, frames, calibration, timestamps, detected window.
pub fn inspect(path: &Path, opts: &RecordingOptions) -> Result<InspectReport> {
    let mut streams = Vec::new();
    let mut width = None;
    let mut height = None;
    if path.extension().and_then(|e| e.to_str()) == Some("vrs") {
        let rec = crate::aria::AriaRecording::open(path)?;
        let counts = rec.vrs.record_counts();
        for (id, tags) in &rec.vrs.streams {
            streams.push(StreamReport {
                id: id.to_string(),
                name: tags.name().map(str::to_string),
                records: counts.get(id).copied().unwrap_or(0),
            });
        }
        width = rec.config.width;
        height = rec.config.height;
    }
    let opened = open_recording(path, opts)?;
    let describe = opened.source.describe();
    let detector = opened.tagger.evidence.name().to_string();
    let calibration = opened.camera.as_ref().map(|c| {
        let q = c.t_device_camera.rotation;
        let t = c.t_device_camera.translation;
        CalibrationReport {
            label: c.label.clone(),
            model: c.model.name().to_string(),
            width: c.width,
            height: c.height,
            params: c.model.params().to_vec(),
            t_device_camera_translation: [t.x, t.y, t.z],
            t_device_camera_quaternion_xyzw: [q.x, q.y, q.z, q.w],
        }
    });
    if width.is_none() {
        if let Some(c) = &opened.camera {
            width = Some(c.width);
            height = Some(c.height);
        }
    }
    let trajectory = opened.trajectory_path.as_ref().map(|p| p.display().to_string());
    let hand_tracking = opened.hands_path.as_ref().map(|p| p.display().to_string());
    let has_traj = trajectory.is_some();
    let (frames, events, stats, trace) = opened.collect_with_evidence();
    let timestamps_ns: Vec<i64> = frames.iter().map(|f| (f.timestamp_s * 1e9).round() as i64).collect();
    let time_span_s = match (timestamps_ns.first(), timestamps_ns.last()) {
        (Some(a), Some(b)) => Some((b - a) as f64 * 1e-9),
        _ => None,
    };
    let mut phase_counts = [0usize; 3];
    for f in &frames {
        phase_counts[match f.phase {
            Phase::Scan => 0,
            Phase::Motion => 1,
            Phase::After => 2,
        }] += 1;
    }
    if width.is_none() {
        if let Some(f) = frames.first() {
            width = Some(f.image.width());
            height = Some(f.image.height());
        }
    }
    let (hand_in_s, hand_out_s) = window_of(&events);
    Ok(InspectReport {
        recording: path.display().to_string(),
        source: describe,
        streams,
        frame_count: frames.len() + (stats.corrupt + stats.unposed + stats.out_of_order) as usize,
        width,
        height,
        calibration,
        timestamps_ns,
        time_span_s,
        trajectory,
        hand_tracking,
        detector,
        frames_posed: if has_traj { frames.len() } else { 0 },
        hand_in_s,
        hand_out_s,
        events,
        phase_counts,
        stats,
        evidence: trace.iter().map(|t| t.2).collect(),
    })
}

/// Frame `index` of a recording, undistorted, posed and cut to the region of
/// object `object` ([`crate::crop::ObjectCrop`], `size` pixels square): what the
/// trainers see of it.
pub fn cropped_frame(
    path: &Path,
    index: usize,
    object: usize,
    opts: &RecordingOptions,
    size: u32,
    margin: f32,
) -> Result<Frame> {
    let opened = open_recording(path, opts)?;
    let region = match opened.regions.get(object) {
        Some(r) => *r,
        None if opened.regions.is_empty() => {
            return Err(Error::bad_file(
                path,
                "no object region (object_region.json beside the recording, or --region)",
            ))
        }
        None => {
            return Err(Error::bad_file(
                path,
                format!("object {object} out of range: the recording has {} object region(s)", opened.regions.len()),
            ))
        }
    };
    let mut source = opened.source;
    let mut k = 0;
    while let Some(r) = source.next_frame() {
        if k == index {
            let p = opened.processor.process(r?).map_err(|e| Error::bad_file(path, format!("frame {index}: {e:?}")))?;
            if !p.posed {
                return Err(Error::bad_file(
                    path,
                    format!("frame {index}: no camera pose (MPS trajectory) at its time"),
                ));
            }
            let crop = crate::crop::ObjectCrop { region, size, margin, mask_outside: true };
            return crop
                .apply(&p.frame)
                .ok_or_else(|| Error::bad_file(path, format!("frame {index}: the object region is out of view")));
        }
        k += 1;
    }
    Err(Error::bad_file(path, format!("frame {index} out of range: the recording has {k} frames")))
}

/// Undistort one frame of a recording to a linear camera (`aim capture undistort`).
/// Returns the RGBA image (alpha 0 where the fisheye does not see) and the linear camera.
pub fn undistort_frame(
    path: &Path,
    index: usize,
    cfg: &UndistortConfig,
    vignetting: Option<&Path>,
) -> Result<(image::RgbaImage, CameraCalibration)> {
    let mut source = open_source(path, 30.0)?;
    let camera = source
        .camera()
        .ok_or_else(|| Error::bad_file(path, "recording has no fisheye calibration to undistort with"))?;
    let mask = match vignetting {
        Some(p) => Some(image::open(p).map_err(|e| Error::bad_file(p, e.to_string()))?.to_luma8()),
        None => None,
    };
    let processor = Processor::new(Some(&camera), cfg, mask.as_ref());
    let mut k = 0;
    while let Some(r) = source.next_frame() {
        if k == index {
            let raw = r?;
            let p = processor.process(raw).map_err(|e| Error::bad_file(path, format!("frame {index}: {e:?}")))?;
            let target = processor.map.as_ref().map(|m| m.target.clone()).unwrap_or(camera);
            return Ok(((*p.frame.image).clone(), target));
        }
        k += 1;
    }
    Err(Error::bad_file(path, format!("frame {index} out of range: the recording has {k} frames")))
}
