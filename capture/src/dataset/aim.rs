//! The AiM data layout: `{start,motion,end}/transforms_{train,test}.json`.
//!
//! Each transforms file holds `camera_angle_x` (horizontal field of view, radians) and
//! `frames[]` with `file_path` (relative to the file's folder, usually without the
//! extension), `transform_matrix` (Blender camera-to-world, list of rows), `time` for
//! motion frames (id / (N - 1)) and an optional `depth_file_path` (uint16 PNG in
//! millimetres). Images are RGBA PNGs.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::{matrix_from_rows, read_depth_mm, read_rgba, resolve_image_path, LoadOptions, NOMINAL_FPS};
use crate::error::{Error, Result};
use crate::frame::{opencv_world_to_camera_from_blender, Frame, Intrinsics, Phase};

/// A transforms_{train,test}.json file (unknown fields are ignored).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct TransformsFile {
    pub camera_angle_x: f32,
    pub frames: Vec<TransformsFrame>,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct TransformsFrame {
    pub file_path: String,
    /// Blender camera-to-world, rows.
    pub transform_matrix: [[f32; 4]; 4],
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub time: Option<f32>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub depth_file_path: Option<String>,
    /// Part-id image (synthetic data only): 8-bit, value = part id, 255 = background.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub part_file_path: Option<String>,
}

/// Train and test frames of one phase.
#[derive(Clone, Debug, Default)]
pub struct AimPhase {
    pub train: Vec<Frame>,
    pub test: Vec<Frame>,
}

/// A dataset in the AiM layout.
#[derive(Clone, Debug)]
pub struct AimDataset {
    pub root: PathBuf,
    /// Start state (static scan).
    pub start: AimPhase,
    /// The motion video (frames carry `motion_time`; `timestamp_s` is the frame's place
    /// in the whole video, train and test together, at the nominal 30 fps).
    pub motion: AimPhase,
    /// End state, when the dataset has an `end/` folder.
    pub end: Option<AimPhase>,
}

fn phase_dir_name(phase: Phase) -> &'static str {
    match phase {
        Phase::Scan => "start",
        Phase::Motion => "motion",
        Phase::After => "end",
    }
}

fn load_phase(root: &Path, phase: Phase, opts: &LoadOptions, required: bool) -> Result<Option<AimPhase>> {
    let dir = root.join(phase_dir_name(phase));
    let train_path = dir.join("transforms_train.json");
    if !train_path.exists() {
        if required {
            return Err(Error::bad_file(
                &train_path,
                "missing: an AiM dataset needs start/ and motion/ folders with transforms_train.json",
            ));
        }
        return Ok(None);
    }
    let train = load_aim_transforms(&train_path, phase, opts)?;
    let test_path = dir.join("transforms_test.json");
    let mut test = if test_path.exists() { load_aim_transforms(&test_path, phase, opts)? } else { Vec::new() };
    // Motion frames of both files share one time line: put them on one clock, frame
    // i of N (time i / (N - 1)) at i / NOMINAL_FPS seconds.
    let n = train.len() + test.len();
    let mut train = train;
    if n > 1 && train.iter().chain(&test).all(|f| f.motion_time.is_some()) {
        for f in train.iter_mut().chain(test.iter_mut()) {
            let i = (f.motion_time.unwrap_or(0.0) as f64 * (n - 1) as f64).round();
            f.timestamp_s = i / NOMINAL_FPS;
        }
    }
    Ok(Some(AimPhase { train, test }))
}

/// Load a dataset in the AiM layout rooted at `root` (start/ and motion/ required, end/ optional).
pub fn load_aim(root: &Path, opts: &LoadOptions) -> Result<AimDataset> {
    if !root.is_dir() {
        return Err(Error::bad_file(root, "not a directory"));
    }
    let start = load_phase(root, Phase::Scan, opts, true)?.unwrap_or_default();
    let motion = load_phase(root, Phase::Motion, opts, true)?.unwrap_or_default();
    let end = load_phase(root, Phase::After, opts, false)?;
    Ok(AimDataset { root: root.to_path_buf(), start, motion, end })
}

/// Parse a transforms file without reading images.
pub fn read_transforms_file(path: &Path) -> Result<TransformsFile> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    let file: TransformsFile =
        serde_json::from_str(&text).map_err(|e| Error::bad_file(path, format!("not a transforms file: {e}")))?;
    if !(file.camera_angle_x.is_finite() && file.camera_angle_x > 0.0 && file.camera_angle_x < std::f32::consts::PI) {
        return Err(Error::bad_file(
            path,
            format!("camera_angle_x must be in (0, pi) radians, got {}", file.camera_angle_x),
        ));
    }
    for (i, f) in file.frames.iter().enumerate() {
        if let Some(t) = f.time {
            if !t.is_finite() {
                return Err(Error::bad_file(path, format!("frame {i} ({}): time is not finite", f.file_path)));
            }
        }
    }
    Ok(file)
}

/// Load one transforms_{train,test}.json with its images (in parallel), in file order.
pub fn load_aim_transforms(path: &Path, phase: Phase, opts: &LoadOptions) -> Result<Vec<Frame>> {
    let file = read_transforms_file(path)?;
    let dir = path.parent().unwrap_or(Path::new("."));
    file.frames
        .par_iter()
        .enumerate()
        .map(|(index, f)| {
            let what = format!("frame {index} ({})", f.file_path);
            let c2w = matrix_from_rows(&f.transform_matrix, path, &what)?;
            let img_path = resolve_image_path(dir, &f.file_path);
            let image = read_rgba(&img_path)?;
            let intrinsics = Intrinsics::from_fov_x(image.width(), image.height(), file.camera_angle_x);
            let depth = match (&f.depth_file_path, opts.depth) {
                (Some(d), true) => {
                    Some(Arc::new(read_depth_mm(&resolve_image_path(dir, d), image.width(), image.height())?))
                }
                _ => None,
            };
            Ok(Frame {
                index,
                timestamp_s: index as f64 / NOMINAL_FPS,
                motion_time: f.time,
                phase,
                intrinsics,
                world_to_camera: opencv_world_to_camera_from_blender(c2w),
                image: Arc::new(image),
                depth,
                source: img_path.display().to_string(),
            })
        })
        .collect()
}
