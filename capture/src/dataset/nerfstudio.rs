//! nerfstudio `transforms.json`.
//!
//! Global intrinsics (`fl_x`, `fl_y`, `cx`, `cy`, `w`, `h`, or `camera_angle_x`) with
//! per-frame overrides; the egocentric_splats / 4DGT spellings (`fx`, `fy`,
//! `image_path`) are accepted too. `transform_matrix` is an OpenGL/Blender
//! camera-to-world (nerfstudio's convention) and is converted to OpenCV
//! world-to-camera. Distortion (`camera_model` OPENCV, OPENCV_FISHEYE, FISHEYE624 with
//! its parameter list) is reported per frame in [`NerfstudioDataset::distortion`], not
//! applied: frames of a distorted model need undistortion before pinhole use.
//! Optional per-frame fields: `depth_file_path` (uint16 PNG, millimetres), `mask_path`
//! (8-bit, 0 = ignore; multiplied into the image's alpha), `time` (normalised motion
//! time) and `timestamp` (seconds; values above 1e12 are taken as nanoseconds).

use std::path::{Path, PathBuf};
use std::sync::Arc;

use rayon::prelude::*;
use serde_json::Value;

use super::{matrix_from_rows, read_depth_mm, read_rgba, resolve_image_path, LoadOptions, NOMINAL_FPS};
use crate::error::{Error, Result};
use crate::frame::{opencv_world_to_camera_from_blender, Frame, Intrinsics, Phase};

/// Lens distortion of a frame's camera, as declared by the file.
#[derive(Clone, Debug, PartialEq)]
pub enum Distortion {
    /// PINHOLE, or OPENCV with all coefficients zero.
    None,
    /// Radial-tangential (OPENCV): k1, k2, k3, k4 (rational extension, usually 0), p1, p2.
    OpenCv { k1: f32, k2: f32, k3: f32, k4: f32, p1: f32, p2: f32 },
    /// Kannala-Brandt (OPENCV_FISHEYE): k1..k4.
    Fisheye { k1: f32, k2: f32, k3: f32, k4: f32 },
    /// Aria Fisheye624 parameters as given (see the capture crate's calibration).
    Fisheye624 { params: Vec<f32> },
    /// A model this loader does not interpret.
    Other { model: String },
}

/// Frames of a transforms.json with each frame's declared distortion.
#[derive(Clone, Debug)]
pub struct NerfstudioDataset {
    pub path: PathBuf,
    pub frames: Vec<Frame>,
    /// Per frame, same order as `frames`.
    pub distortion: Vec<Distortion>,
}

fn num(v: &Value, keys: &[&str]) -> Option<f64> {
    keys.iter().find_map(|k| v.get(*k).and_then(Value::as_f64))
}

fn text<'a>(v: &'a Value, keys: &[&str]) -> Option<&'a str> {
    keys.iter().find_map(|k| v.get(*k).and_then(Value::as_str))
}

/// A frame field, else the file's global one.
fn field(frame: &Value, top: &Value, keys: &[&str]) -> Option<f64> {
    num(frame, keys).or_else(|| num(top, keys))
}

fn distortion_of(frame: &Value, top: &Value, path: &Path, what: &str) -> Result<Distortion> {
    let model = text(frame, &["camera_model"]).or_else(|| text(top, &["camera_model"])).unwrap_or("OPENCV");
    let k = |name: &str| field(frame, top, &[name]).unwrap_or(0.0) as f32;
    Ok(match model.to_ascii_uppercase().as_str() {
        "PINHOLE" | "SIMPLE_PINHOLE" => Distortion::None,
        "OPENCV" | "PERSPECTIVE" => {
            let d = (k("k1"), k("k2"), k("k3"), k("k4"), k("p1"), k("p2"));
            if d == (0.0, 0.0, 0.0, 0.0, 0.0, 0.0) {
                Distortion::None
            } else {
                Distortion::OpenCv { k1: d.0, k2: d.1, k3: d.2, k4: d.3, p1: d.4, p2: d.5 }
            }
        }
        "OPENCV_FISHEYE" => Distortion::Fisheye { k1: k("k1"), k2: k("k2"), k3: k("k3"), k4: k("k4") },
        "FISHEYE624" => {
            let keys = ["fisheye624_params", "fisheye_params", "distortion_params"];
            let arr = keys.iter().find_map(|key| frame.get(*key).or_else(|| top.get(*key))).and_then(Value::as_array);
            let params = match arr {
                Some(a) => {
                    a.iter().map(|x| x.as_f64().map(|x| x as f32)).collect::<Option<Vec<f32>>>().ok_or_else(|| {
                        Error::bad_file(path, format!("{what}: FISHEYE624 parameters must be numbers"))
                    })?
                }
                None => Vec::new(),
            };
            Distortion::Fisheye624 { params }
        }
        other => Distortion::Other { model: other.to_string() },
    })
}

fn matrix(v: &Value, path: &Path, what: &str) -> Result<[[f32; 4]; 4]> {
    let bad = || Error::bad_file(path, format!("{what}: transform_matrix must be 4 rows of 4 numbers (or 3 rows)"));
    let rows = v.get("transform_matrix").and_then(Value::as_array).ok_or_else(bad)?;
    if rows.len() != 4 && rows.len() != 3 {
        return Err(bad());
    }
    let mut m = [[0.0f32, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]];
    for (r, row) in rows.iter().enumerate() {
        let row = row.as_array().filter(|a| a.len() == 4).ok_or_else(bad)?;
        for (c, x) in row.iter().enumerate() {
            m[r][c] = x.as_f64().ok_or_else(bad)? as f32;
        }
    }
    Ok(m)
}

/// Load a nerfstudio transforms.json (a file, or a folder holding `transforms.json`).
pub fn load_nerfstudio(path: &Path, opts: &LoadOptions) -> Result<NerfstudioDataset> {
    let path = if path.is_dir() { path.join("transforms.json") } else { path.to_path_buf() };
    let text_in = std::fs::read_to_string(&path).map_err(|e| Error::io(&path, e))?;
    let top: Value =
        serde_json::from_str(&text_in).map_err(|e| Error::bad_file(&path, format!("not valid JSON: {e}")))?;
    let frames = top
        .get("frames")
        .and_then(Value::as_array)
        .ok_or_else(|| Error::bad_file(&path, "no \"frames\" list: not a nerfstudio transforms.json"))?;
    let dir = path.parent().unwrap_or(Path::new(".")).to_path_buf();
    let loaded: Vec<(Frame, Distortion)> = frames
        .par_iter()
        .enumerate()
        .map(|(index, fv)| {
            let file_path = text(fv, &["file_path", "image_path"])
                .ok_or_else(|| Error::bad_file(&path, format!("frame {index}: no file_path")))?;
            let what = format!("frame {index} ({file_path})");
            let c2w = matrix_from_rows(&matrix(fv, &path, &what)?, &path, &what)?;
            let img_path = resolve_image_path(&dir, file_path);
            let mut image = read_rgba(&img_path)?;
            let (iw, ih) = (image.width(), image.height());
            let w = field(fv, &top, &["w"]).map(|x| x as u32).unwrap_or(iw);
            let h = field(fv, &top, &["h"]).map(|x| x as u32).unwrap_or(ih);
            if (w, h) != (iw, ih) {
                return Err(Error::bad_file(
                    &path,
                    format!("{what}: declares {w}x{h} but {} is {iw}x{ih}", img_path.display()),
                ));
            }
            let fx = field(fv, &top, &["fl_x", "fx"])
                .or_else(|| field(fv, &top, &["camera_angle_x"]).map(|a| 0.5 * w as f64 / (0.5 * a).tan()));
            let fx =
                fx.ok_or_else(|| Error::bad_file(&path, format!("{what}: no focal length (fl_x or camera_angle_x)")))?;
            let fy = field(fv, &top, &["fl_y", "fy"]).unwrap_or(fx);
            let cx = field(fv, &top, &["cx"]).unwrap_or(0.5 * w as f64);
            let cy = field(fv, &top, &["cy"]).unwrap_or(0.5 * h as f64);
            let intrinsics =
                Intrinsics { width: w, height: h, fx: fx as f32, fy: fy as f32, cx: cx as f32, cy: cy as f32 };
            let valid = intrinsics.fx > 0.0
                && intrinsics.fy > 0.0
                && intrinsics.fx.is_finite()
                && intrinsics.fy.is_finite()
                && intrinsics.cx.is_finite()
                && intrinsics.cy.is_finite();
            if !valid {
                return Err(Error::bad_file(&path, format!("{what}: focal lengths must be positive and finite")));
            }
            if let Some(mask) = text(fv, &["mask_path"]) {
                let mpath = resolve_image_path(&dir, mask);
                let bytes = std::fs::read(&mpath).map_err(|e| Error::io(&mpath, e))?;
                let m = image::load_from_memory(&bytes)
                    .map_err(|e| Error::bad_file(&mpath, format!("not a readable image: {e}")))?
                    .into_luma8();
                if (m.width(), m.height()) != (iw, ih) {
                    return Err(Error::bad_file(
                        &mpath,
                        format!("mask is {}x{}, image is {iw}x{ih}", m.width(), m.height()),
                    ));
                }
                for (p, mv) in image.pixels_mut().zip(m.pixels()) {
                    p[3] = ((p[3] as u16 * mv[0] as u16 + 127) / 255) as u8;
                }
            }
            let depth = match (text(fv, &["depth_file_path"]), opts.depth) {
                (Some(d), true) => Some(Arc::new(read_depth_mm(&resolve_image_path(&dir, d), iw, ih)?)),
                _ => None,
            };
            let timestamp_s = match num(fv, &["timestamp"]) {
                Some(ts) if ts > 1e12 => ts * 1e-9,
                Some(ts) => ts,
                None => index as f64 / NOMINAL_FPS,
            };
            let motion_time = num(fv, &["time"]).map(|t| t as f32);
            let distortion = distortion_of(fv, &top, &path, &what)?;
            let frame = Frame {
                index,
                timestamp_s,
                motion_time,
                phase: if motion_time.is_some() { Phase::Motion } else { Phase::Scan },
                intrinsics,
                world_to_camera: opencv_world_to_camera_from_blender(c2w),
                image: Arc::new(image),
                depth,
                source: img_path.display().to_string(),
            };
            Ok((frame, distortion))
        })
        .collect::<Result<_>>()?;
    let (frames, distortion) = loaded.into_iter().unzip();
    Ok(NerfstudioDataset { path, frames, distortion })
}
