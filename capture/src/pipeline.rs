//! Per-frame processing shared by batch use, the ingestion thread and the benchmark:
//! decode -> undistort -> pose -> (evidence -> phase). Decoding and undistortion are
//! pure per frame (run in parallel); evidence and phase tracking are sequential.

use std::sync::Arc;

use glam::{DMat4, Mat4};

use crate::calib::{CameraCalibration, Se3};
use crate::detect::{Evidence, FrameView, MotionEvent, NoEvidence, WindowTracker};
use crate::frame::{Frame, Intrinsics, Phase};
use crate::mps::Trajectory;
use crate::source::{RawFrame, RawImage};
use crate::undistort::{UndistortConfig, UndistortMap};

/// Everything needed to turn raw frames into posed, undistorted frames.
pub struct Processor {
    /// Undistortion map from the source camera (None: images are already linear).
    pub map: Option<UndistortMap>,
    /// Linear camera of the output (library convention), when known.
    pub intrinsics: Option<Intrinsics>,
    /// T_device_camera of the output camera (upright applied).
    pub t_device_camera: Se3,
    pub trajectory: Option<Trajectory>,
    /// Largest distance (ns) from the nearest trajectory sample at which a frame is
    /// still posed: beyond the trajectory's ends (clamped), and inside it (a gap
    /// between samples wider than twice this is a hole where tracking was lost).
    pub pose_tolerance_ns: i64,
    /// Skip frames that cannot be posed when a trajectory is given.
    pub require_pose: bool,
}

/// A processed frame before its phase is decided.
pub struct Processed {
    pub frame: Frame,
    pub timestamp_ns: i64,
    pub t_world_device: Option<Se3>,
    /// Phase given by the source (datasets), which overrides detection.
    pub given_phase: Option<Phase>,
    pub posed: bool,
}

/// Why a frame was skipped.
#[derive(Debug)]
pub enum Skip {
    /// The image would not decode or had the wrong size (corrupt record).
    Corrupt(String),
    /// No pose at the frame time (outside the trajectory).
    NoPose(String),
}

impl Processor {
    pub fn new(
        camera: Option<&CameraCalibration>,
        cfg: &UndistortConfig,
        vignetting: Option<&image::GrayImage>,
    ) -> Self {
        let map = camera.map(|c| UndistortMap::with_vignetting(c, cfg, vignetting));
        let intrinsics = map.as_ref().and_then(|m| m.target.to_intrinsics());
        let t_device_camera = map.as_ref().map(|m| m.target.t_device_camera).unwrap_or(Se3::IDENTITY);
        Processor {
            map,
            intrinsics,
            t_device_camera,
            trajectory: None,
            pose_tolerance_ns: 5_000_000,
            require_pose: true,
        }
    }

    pub fn with_trajectory(mut self, t: Option<Trajectory>) -> Self {
        self.trajectory = t;
        self
    }

    /// Decode, undistort and pose one frame (thread-safe, no shared mutable state).
    pub fn process(&self, raw: RawFrame) -> Result<Processed, Skip> {
        let label = raw.label.clone();
        let rgba: image::RgbaImage = match raw.image {
            RawImage::Ready { frame, phase_given } => {
                let f = *frame;
                return Ok(Processed {
                    timestamp_ns: raw.timestamp_ns,
                    t_world_device: None,
                    given_phase: phase_given.then_some(f.phase),
                    posed: true,
                    frame: f,
                });
            }
            RawImage::Jpeg(bytes) => {
                let rgb = crate::aria::decode_jpeg(&bytes).map_err(|e| Skip::Corrupt(format!("{label}: {e}")))?;
                self.undistort(rgb, &label)?
            }
            RawImage::Encoded(bytes) => {
                let img = image::load_from_memory(&bytes).map_err(|e| Skip::Corrupt(format!("{label}: {e}")))?;
                if self.map.is_some() {
                    self.undistort(img.to_rgb8(), &label)?
                } else {
                    img.to_rgba8()
                }
            }
            RawImage::Rgb(rgb) => self.undistort(rgb, &label)?,
        };
        let intrinsics = self.intrinsics.unwrap_or_else(|| {
            // Unknown camera: a 60-degree pinhole guess so downstream code has something.
            Intrinsics::from_fov_x(rgba.width(), rgba.height(), 60f32.to_radians())
        });
        let t_world_device =
            self.trajectory.as_ref().and_then(|t| t.interpolate(raw.timestamp_ns, self.pose_tolerance_ns));
        if self.trajectory.is_some() && t_world_device.is_none() && self.require_pose {
            return Err(Skip::NoPose(format!("{label}: no trajectory pose at t = {} ns", raw.timestamp_ns)));
        }
        let world_to_camera = match t_world_device {
            Some(twd) => {
                let twc: DMat4 = twd.compose(&self.t_device_camera).to_mat4();
                twc.inverse().as_mat4()
            }
            None => Mat4::IDENTITY,
        };
        Ok(Processed {
            frame: Frame {
                index: raw.index,
                timestamp_s: raw.timestamp_ns as f64 * 1e-9,
                motion_time: None,
                phase: Phase::Scan,
                intrinsics,
                world_to_camera,
                image: Arc::new(rgba),
                depth: None,
                source: label,
            },
            timestamp_ns: raw.timestamp_ns,
            posed: t_world_device.is_some(),
            t_world_device,
            given_phase: None,
        })
    }

    fn undistort(&self, rgb: image::RgbImage, label: &str) -> Result<image::RgbaImage, Skip> {
        match &self.map {
            Some(m) => m.apply_rgb(&rgb).map_err(|e| Skip::Corrupt(format!("{label}: {e}"))),
            None => Ok(image::DynamicImage::ImageRgb8(rgb).to_rgba8()),
        }
    }
}

/// Sequential phase decision: evidence per frame, then the window tracker.
pub struct PhaseTagger {
    pub evidence: Box<dyn Evidence>,
    pub tracker: WindowTracker<Processed>,
    /// Evidence values, in frame order (for inspection and tests).
    pub trace: Vec<(usize, f64, f32)>,
    last_given: Option<Phase>,
}

impl PhaseTagger {
    pub fn new(evidence: Box<dyn Evidence>) -> Self {
        let h = evidence.hysteresis();
        PhaseTagger { evidence, tracker: WindowTracker::new(h), trace: Vec::new(), last_given: None }
    }

    pub fn none() -> Self {
        Self::new(Box::new(NoEvidence))
    }

    /// Feed a processed frame; returns frames whose phase is decided and any event.
    pub fn push(&mut self, p: Processed) -> (Vec<Frame>, Option<MotionEvent>) {
        if let Some(given) = p.given_phase {
            // Source-given phases: pass through, events on transitions.
            let ev = match (self.last_given, given) {
                (Some(Phase::Scan | Phase::After) | None, Phase::Motion) => {
                    Some(MotionEvent::HandIn { frame: p.frame.index, timestamp_s: p.frame.timestamp_s })
                }
                (Some(Phase::Motion), Phase::After) => {
                    Some(MotionEvent::HandOut { frame: p.frame.index, timestamp_s: p.frame.timestamp_s })
                }
                _ => None,
            };
            if let Some(e) = ev {
                self.tracker.events.push(e);
            }
            self.last_given = Some(given);
            return (vec![p.frame], ev);
        }
        let view = FrameView {
            index: p.frame.index,
            timestamp_ns: p.timestamp_ns,
            image: &p.frame.image,
            intrinsics: &p.frame.intrinsics,
            world_to_camera: p.posed.then_some(p.frame.world_to_camera),
            t_world_device: p.t_world_device,
        };
        let e = self.evidence.evidence(&view);
        self.trace.push((p.frame.index, p.frame.timestamp_s, e));
        let (idx, t) = (p.frame.index, p.frame.timestamp_s);
        let (out, ev) = self.tracker.push(p, idx, t, e);
        (out.into_iter().map(|(p, phase)| with_phase(p, phase)).collect(), ev)
    }

    pub fn flush(&mut self) -> Vec<Frame> {
        self.tracker.flush().into_iter().map(|(p, phase)| with_phase(p, phase)).collect()
    }
}

fn with_phase(p: Processed, phase: Phase) -> Frame {
    let mut f = p.frame;
    f.phase = phase;
    f
}
