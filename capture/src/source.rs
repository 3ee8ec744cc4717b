//! Frame sources: Aria VRS, image folders with timestamps, dataset folders (already
//! posed and undistorted frames from [`crate::dataset`]), video files (feature `video`).
//! A source yields [`RawFrame`]s in capture order; decoding and undistortion happen in
//! the [`crate::pipeline`] so that they can run in parallel off the consumer's thread.

use std::path::{Path, PathBuf};

use crate::aria::AriaRecording;
use crate::calib::CameraCalibration;
use crate::error::{Error, Result};
use crate::frame::Frame;

/// An image as the source delivers it.
#[derive(Clone, Debug)]
pub enum RawImage {
    /// JPEG bytes (Aria RGB frames).
    Jpeg(Vec<u8>),
    /// Any encoded image file's bytes (PNG, JPEG, ...), decoded with the `image` crate.
    Encoded(Vec<u8>),
    Rgb(image::RgbImage),
    /// A frame that is already undistorted and posed (datasets); passed through. With
    /// `phase_given` its phase is kept, otherwise it is detected like any other frame.
    Ready {
        frame: Box<Frame>,
        phase_given: bool,
    },
}

/// A frame before decoding and undistortion.
#[derive(Clone, Debug)]
pub struct RawFrame {
    pub index: usize,
    /// Capture time on the source's clock, in ns (for Aria: the device clock, which is
    /// the MPS time base).
    pub timestamp_ns: i64,
    pub image: RawImage,
    /// Where the frame came from, for error messages ("recording.vrs frame 3").
    pub label: String,
}

/// A recording or folder that yields frames in capture order.
pub trait FrameSource: Send {
    /// Human-readable description (path and kind).
    fn describe(&self) -> String;
    /// Number of frames, when known.
    fn len_hint(&self) -> Option<usize>;
    /// The camera the raw images come from (a fisheye model for Aria), at the raw
    /// images' resolution. None when frames are already linear (datasets, folders
    /// without calibration).
    fn camera(&self) -> Option<CameraCalibration>;
    /// The next frame; None at the end. An `Err` for one frame is not fatal: the
    /// consumer may skip it and continue (a corrupt record).
    fn next_frame(&mut self) -> Option<Result<RawFrame>>;
}

/// The RGB stream of an Aria VRS file.
pub struct VrsSource {
    rec: AriaRecording,
    camera: Option<CameraCalibration>,
    next: usize,
}

impl VrsSource {
    pub fn open(path: impl AsRef<Path>) -> Result<Self> {
        let rec = AriaRecording::open(path)?;
        let camera = match rec.rgb_calibration() {
            Ok(c) => Some(c),
            Err(e) => {
                tracing::warn!("{e}: frames will not be undistorted");
                None
            }
        };
        Ok(VrsSource { rec, camera, next: 0 })
    }

    /// Replace the factory calibration (e.g. with an MPS online calibration).
    pub fn set_camera(&mut self, camera: CameraCalibration) {
        self.camera = Some(camera);
    }

    pub fn recording(&self) -> &AriaRecording {
        &self.rec
    }
}

impl FrameSource for VrsSource {
    fn describe(&self) -> String {
        format!("Aria VRS {}", self.rec.path().display())
    }
    fn len_hint(&self) -> Option<usize> {
        Some(self.rec.frame_count())
    }
    fn camera(&self) -> Option<CameraCalibration> {
        self.camera.clone()
    }
    fn next_frame(&mut self) -> Option<Result<RawFrame>> {
        if self.next >= self.rec.frame_count() {
            return None;
        }
        let i = self.next;
        self.next += 1;
        Some(self.rec.read_frame(i).map(|f| RawFrame {
            index: i,
            timestamp_ns: f.capture_timestamp_ns,
            image: RawImage::Jpeg(f.jpeg),
            label: format!("{} frame {i}", self.rec.path().display()),
        }))
    }
}

/// A folder of images in name order. Timestamps come from a `timestamps.csv`
/// (`file,timestamp_ns` rows) if present, else from the digits in each file name when
/// every name has some (taken as ns), else from `fps`.
pub struct FolderSource {
    dir: PathBuf,
    files: Vec<(PathBuf, i64)>,
    camera: Option<CameraCalibration>,
    next: usize,
}

fn is_image(p: &Path) -> bool {
    matches!(
        p.extension().and_then(|e| e.to_str()).map(|e| e.to_ascii_lowercase()).as_deref(),
        Some("png" | "jpg" | "jpeg")
    )
}

impl FolderSource {
    pub fn open(dir: impl AsRef<Path>, fps: f64, camera: Option<CameraCalibration>) -> Result<Self> {
        let dir = dir.as_ref().to_path_buf();
        let rd = std::fs::read_dir(&dir).map_err(|e| Error::io(&dir, e))?;
        let mut names: Vec<PathBuf> = rd.filter_map(|e| e.ok().map(|e| e.path())).filter(|p| is_image(p)).collect();
        // Capture order: by the number in the name where every name has one (img_2
        // before img_10), else by name.
        let number = |p: &Path| -> Option<u128> {
            let s: String = p.file_stem()?.to_str()?.chars().filter(|c| c.is_ascii_digit()).collect();
            s.parse().ok()
        };
        if names.iter().all(|p| number(p).is_some()) {
            names.sort_by_key(|p| (number(p), p.clone()));
        } else {
            names.sort();
        }
        if names.is_empty() {
            return Err(Error::bad_file(&dir, "no PNG or JPEG images in the folder"));
        }
        let ts_path = dir.join("timestamps.csv");
        let mut table = std::collections::HashMap::new();
        if ts_path.exists() {
            let text = std::fs::read_to_string(&ts_path).map_err(|e| Error::io(&ts_path, e))?;
            for (i, line) in text.lines().enumerate() {
                let mut it = line.split(',');
                let (Some(f), Some(t)) = (it.next(), it.next()) else { continue };
                match t.trim().parse::<i64>() {
                    Ok(t) => {
                        table.insert(f.trim().to_string(), t);
                    }
                    Err(_) if i == 0 => {} // header
                    Err(_) => return Err(Error::bad_file(&ts_path, format!("line {}: bad timestamp {t:?}", i + 1))),
                }
            }
        }
        let from_names: Option<Vec<i64>> =
            names.iter().map(|p| number(p).and_then(|n| i64::try_from(n).ok())).collect();
        let from_names = from_names.filter(|v| v.windows(2).all(|w| w[0] < w[1]) && v.iter().any(|&t| t > 1_000_000));
        let fps = if fps > 0.0 { fps } else { 30.0 };
        let mut files = Vec::with_capacity(names.len());
        for (i, p) in names.into_iter().enumerate() {
            let name = p.file_name().and_then(|n| n.to_str()).unwrap_or("").to_string();
            let t = if let Some(&t) = table.get(&name) {
                t
            } else if !table.is_empty() {
                return Err(Error::bad_file(&ts_path, format!("no timestamp for {name}")));
            } else if let Some(v) = &from_names {
                v[i]
            } else {
                (i as f64 / fps * 1e9).round() as i64
            };
            files.push((p, t));
        }
        Ok(FolderSource { dir, files, camera, next: 0 })
    }
}

impl FrameSource for FolderSource {
    fn describe(&self) -> String {
        format!("image folder {}", self.dir.display())
    }
    fn len_hint(&self) -> Option<usize> {
        Some(self.files.len())
    }
    fn camera(&self) -> Option<CameraCalibration> {
        self.camera.clone()
    }
    fn next_frame(&mut self) -> Option<Result<RawFrame>> {
        let (p, t) = self.files.get(self.next)?.clone();
        let i = self.next;
        self.next += 1;
        Some(std::fs::read(&p).map_err(|e| Error::io(&p, e)).map(|bytes| RawFrame {
            index: i,
            timestamp_ns: t,
            image: RawImage::Encoded(bytes),
            label: p.display().to_string(),
        }))
    }
}

/// Frames that are already posed and undistorted (datasets): passed through, keeping
/// their phase.
pub struct DatasetSource {
    name: String,
    frames: std::vec::IntoIter<Frame>,
    len: usize,
    phase_given: bool,
}

impl DatasetSource {
    /// Frames whose phases are known (AiM layout: start/motion/end folders).
    pub fn from_frames(name: impl Into<String>, frames: Vec<Frame>) -> Self {
        let len = frames.len();
        DatasetSource { name: name.into(), frames: frames.into_iter(), len, phase_given: true }
    }

    /// Posed frames without phases (nerfstudio, COLMAP): the detector decides them,
    /// in time order (a transforms.json need not list its frames in it).
    pub fn from_frames_undetected(name: impl Into<String>, mut frames: Vec<Frame>) -> Self {
        frames.sort_by(|a, b| a.timestamp_s.total_cmp(&b.timestamp_s));
        DatasetSource { phase_given: false, ..Self::from_frames(name, frames) }
    }

    /// A nerfstudio folder (transforms.json). Per-frame lens distortion, if any, is not
    /// removed here: the loader reports it and frames are used as they are.
    pub fn nerfstudio(path: &Path) -> Result<Self> {
        let ds = crate::dataset::load_nerfstudio(path, &crate::dataset::LoadOptions { depth: false })?;
        if ds.distortion.iter().any(|d| !matches!(d, crate::dataset::Distortion::None)) {
            tracing::warn!("{}: frames have lens distortion; used without undistortion", path.display());
        }
        Ok(Self::from_frames_undetected(path.display().to_string(), ds.frames))
    }

    /// A COLMAP model (`sparse/0` or `sparse`) with its `images/` folder.
    pub fn colmap(root: &Path) -> Result<Self> {
        let model = [root.join("sparse/0"), root.join("sparse")]
            .into_iter()
            .find(|p| p.join("cameras.bin").exists() || p.join("cameras.txt").exists())
            .ok_or_else(|| Error::bad_file(root, "no COLMAP model in sparse/0 or sparse"))?;
        let (_, frames) = crate::dataset::load_colmap_frames(
            &model,
            &root.join("images"),
            &crate::dataset::LoadOptions { depth: false },
        )?;
        Ok(Self::from_frames_undetected(root.display().to_string(), frames))
    }

    /// An AiM-layout dataset: start, motion and end training frames in that order, on
    /// one clock (the loaders' timestamps).
    pub fn aim(root: &Path) -> Result<Self> {
        let ds = crate::dataset::load_aim(root, &crate::dataset::LoadOptions { depth: false })?;
        let mut frames = ds.start.train;
        frames.extend(ds.motion.train);
        if let Some(end) = ds.end {
            frames.extend(end.train);
        }
        Ok(Self::from_frames(root.display().to_string(), frames))
    }
}

impl FrameSource for DatasetSource {
    fn describe(&self) -> String {
        format!("dataset {}", self.name)
    }
    fn len_hint(&self) -> Option<usize> {
        Some(self.len)
    }
    fn camera(&self) -> Option<CameraCalibration> {
        None
    }
    fn next_frame(&mut self) -> Option<Result<RawFrame>> {
        let f = self.frames.next()?;
        Some(Ok(RawFrame {
            index: f.index,
            timestamp_ns: (f.timestamp_s * 1e9).round() as i64,
            label: f.source.clone(),
            image: RawImage::Ready { frame: Box::new(f), phase_given: self.phase_given },
        }))
    }
}

/// Repeats another source's frames `times` times with shifted timestamps (benchmarks).
pub struct RepeatSource {
    frames: Vec<RawFrame>,
    camera: Option<CameraCalibration>,
    times: usize,
    next: usize,
    period_ns: i64,
}

impl RepeatSource {
    pub fn new(mut inner: Box<dyn FrameSource>, times: usize) -> Result<Self> {
        let camera = inner.camera();
        let mut frames = Vec::new();
        while let Some(f) = inner.next_frame() {
            frames.push(f?);
        }
        let span = match (frames.first(), frames.last()) {
            (Some(a), Some(b)) => b.timestamp_ns - a.timestamp_ns,
            _ => 0,
        };
        let period_ns = span + span / frames.len().max(2) as i64 + 1;
        Ok(RepeatSource { frames, camera, times, next: 0, period_ns })
    }
}

impl FrameSource for RepeatSource {
    fn describe(&self) -> String {
        format!("{} frames repeated {} times", self.frames.len(), self.times)
    }
    fn len_hint(&self) -> Option<usize> {
        Some(self.frames.len() * self.times)
    }
    fn camera(&self) -> Option<CameraCalibration> {
        self.camera.clone()
    }
    fn next_frame(&mut self) -> Option<Result<RawFrame>> {
        let n = self.frames.len();
        if n == 0 || self.next >= n * self.times {
            return None;
        }
        let (rep, k) = (self.next / n, self.next % n);
        let mut f = self.frames[k].clone();
        f.index = self.next;
        f.timestamp_ns += rep as i64 * self.period_ns;
        self.next += 1;
        Some(Ok(f))
    }
}

/// The layouts of posed datasets (frames already undistorted and posed).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DatasetLayout {
    /// `start/transforms_train.json` (and motion/, end/).
    Aim,
    /// `transforms.json`.
    Nerfstudio,
    /// `sparse/` + `images/`.
    Colmap,
}

/// The dataset layout of the folder `path`, if it is a dataset.
pub fn dataset_layout(path: &Path) -> Option<DatasetLayout> {
    if !path.is_dir() {
        None
    } else if path.join("start").join("transforms_train.json").exists() {
        Some(DatasetLayout::Aim)
    } else if path.join("transforms.json").exists() {
        Some(DatasetLayout::Nerfstudio)
    } else if path.join("sparse").is_dir() && path.join("images").is_dir() {
        Some(DatasetLayout::Colmap)
    } else {
        None
    }
}

/// Open a recording by what it is: a dataset ([`dataset_layout`]), a `.vrs` file,
/// a synthetic Aria-like recording (`frames/`), a folder of images, or (feature
/// `video`) a video file.
pub fn open_source(path: &Path, fps: f64) -> Result<Box<dyn FrameSource>> {
    match dataset_layout(path) {
        Some(DatasetLayout::Aim) => return Ok(Box::new(DatasetSource::aim(path)?)),
        Some(DatasetLayout::Nerfstudio) => return Ok(Box::new(DatasetSource::nerfstudio(path)?)),
        Some(DatasetLayout::Colmap) => return Ok(Box::new(DatasetSource::colmap(path)?)),
        None => {}
    }
    if path.is_dir() {
        // A synthetic Aria-like recording: frames/ + calibration.json.
        let frames = path.join("frames");
        if frames.is_dir() {
            let cal = path.join("calibration.json");
            let camera = if cal.exists() { Some(load_rgb_calibration_json(&cal)?) } else { None };
            return Ok(Box::new(FolderSource::open(&frames, fps, camera)?));
        }
        return Ok(Box::new(FolderSource::open(path, fps, None)?));
    }
    match path.extension().and_then(|e| e.to_str()) {
        Some("vrs") => Ok(Box::new(VrsSource::open(path)?)),
        #[cfg(feature = "video")]
        Some(_) => Ok(Box::new(crate::video::VideoSource::open(path, None)?)),
        #[cfg(not(feature = "video"))]
        Some(ext) if matches!(ext, "mp4" | "mov" | "mkv" | "avi" | "webm") => Err(Error::bad_file(
            path,
            "video files need aim built with the `video` feature (ffmpeg): cargo build --features video",
        )),
        _ => Err(Error::bad_file(path, "not a recording: expected a .vrs file, a video, or a folder")),
    }
}

/// Load the RGB camera from an Aria-style calibration JSON file (calib_json layout or
/// one online_calibration line), at the resolution stored next to it as
/// `"ImageWidth"`/`"ImageHeight"` (written by the synthetic recorder) or 1408.
pub fn load_rgb_calibration_json(path: &Path) -> Result<CameraCalibration> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    let v: serde_json::Value =
        serde_json::from_str(&text).map_err(|e| Error::bad_file(path, format!("calibration JSON: {e}")))?;
    let dev = crate::calib::DeviceCalibration::from_json(path, &v)?;
    let cam = dev.rgb(path)?;
    let w = v.get("ImageWidth").and_then(|x| x.as_u64()).unwrap_or(1408) as u32;
    let h = v.get("ImageHeight").and_then(|x| x.as_u64()).unwrap_or(w as u64) as u32;
    cam.rescaled_to(w, h).map_err(|e| Error::bad_file(path, e))
}
