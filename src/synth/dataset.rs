//! Writing a benchmark dataset in the AiM layout.
//!
//! ```text
//! OUT/
//!   synth.json                      what was generated (object, seed, config, conventions)
//!   start/transforms_{train,test}.json, start/{train,test}/r_000.png (+ _depth.png, _part.png)
//!   motion/transforms_{train,test}.json (frames carry "time" = i / (N - 1)), motion/{train,test}/...
//!   end/transforms_{train,test}.json, end/{train,test}/...
//!   gt/joints.json, gt/trans.json, gt/start/part_K.obj, gt/end/part_K.obj
//! ```
//!
//! Images are RGBA PNGs (straight alpha = pixel coverage), depth PNGs are uint16
//! z-depth in millimetres (0 = background), part PNGs are 8-bit part ids (255 =
//! background). transforms files hold Blender camera-to-world matrices (rows) and
//! `camera_angle_x`. Motion frame `i` of `N` is at time `i / (N - 1)`; every
//! `motion_test_every`-th frame (offset by half that) is held out in transforms_test.json,
//! keeping its time.

use std::f32::consts::PI;
use std::io::Cursor;
use std::path::{Path, PathBuf};

use aim_capture::dataset::{TransformsFile, TransformsFrame};
use glam::Vec3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::Serialize;

use super::gt::write_ground_truth;
use super::render::{render, RenderOptions};
use super::scene::ArticulatedObject;
use crate::camera::{blender_camera_to_world_from_opencv, Camera, Intrinsics};
use crate::error::{write_atomic, Error, Result};

/// What to generate.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct SynthConfig {
    /// Square image size in pixels.
    pub resolution: u32,
    /// Horizontal field of view (radians).
    pub camera_angle_x: f32,
    /// Start-state training views (random upper hemisphere).
    pub scan_views: usize,
    /// Motion video frames (time i / (N - 1)).
    pub motion_frames: usize,
    /// End-state training views.
    pub end_views: usize,
    /// Test views on a ring, for the start and end states each.
    pub test_views: usize,
    /// Every this-many motion frames one is held out for testing (0 = none).
    pub motion_test_every: usize,
    pub samples_per_pixel: u32,
    pub seed: u64,
}

impl Default for SynthConfig {
    fn default() -> Self {
        Self {
            resolution: 256,
            camera_angle_x: 0.691_111_1,
            scan_views: 100,
            motion_frames: 200,
            end_views: 100,
            test_views: 5,
            motion_test_every: 10,
            samples_per_pixel: 4,
            seed: 0,
        }
    }
}

impl SynthConfig {
    pub fn validate(&self) -> Result<()> {
        if !(8..=4096).contains(&self.resolution) {
            return Err(Error::Config(format!("resolution must be in 8..=4096, got {}", self.resolution)));
        }
        if !(self.camera_angle_x > 0.05 && self.camera_angle_x < 3.0) {
            return Err(Error::Config(format!(
                "camera_angle_x must be in (0.05, 3.0) rad, got {}",
                self.camera_angle_x
            )));
        }
        if self.motion_frames < 2 {
            return Err(Error::Config(format!("motion frames must be at least 2, got {}", self.motion_frames)));
        }
        if self.scan_views == 0 {
            return Err(Error::Config("scan views must be at least 1".into()));
        }
        if !(1..=64).contains(&self.samples_per_pixel) {
            return Err(Error::Config(format!("samples per pixel must be in 1..=64, got {}", self.samples_per_pixel)));
        }
        Ok(())
    }

    pub fn intrinsics(&self) -> Intrinsics {
        Intrinsics::from_fov_x(self.resolution, self.resolution, self.camera_angle_x)
    }
}

/// The three folders of the layout.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum StateFolder {
    Start,
    Motion,
    End,
}

impl StateFolder {
    pub fn dir(self) -> &'static str {
        match self {
            StateFolder::Start => "start",
            StateFolder::Motion => "motion",
            StateFolder::End => "end",
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Split {
    Train,
    Test,
}

impl Split {
    pub fn dir(self) -> &'static str {
        match self {
            Split::Train => "train",
            Split::Test => "test",
        }
    }
}

/// One view to render.
#[derive(Clone, Debug, PartialEq)]
pub struct PlannedView {
    pub folder: StateFolder,
    pub split: Split,
    /// Index within its transforms file.
    pub index: usize,
    /// Motion time of the object's state (0 for start, 1 for end).
    pub time: f32,
    /// `Some(time)` for motion frames (written to the transforms file).
    pub frame_time: Option<f32>,
    pub camera: Camera,
}

impl PlannedView {
    /// Path stem relative to the folder, e.g. `train/r_007`.
    pub fn stem(&self) -> String {
        format!("{}/r_{:03}", self.split.dir(), self.index)
    }
}

fn camera_at(k: Intrinsics, azimuth_deg: f32, elevation_deg: f32, distance: f32, target: Vec3) -> Camera {
    let (a, e) = (azimuth_deg.to_radians(), elevation_deg.to_radians());
    let eye = target + distance * Vec3::new(e.cos() * a.cos(), e.cos() * a.sin(), e.sin());
    Camera::look_at(k, eye, target, Vec3::Z)
}

/// Random views on the upper hemisphere (uniform in azimuth and in height), looking at
/// the object's centre with a small jitter.
fn hemisphere_views(object: &ArticulatedObject, cfg: &SynthConfig, n: usize, rng: &mut ChaCha8Rng) -> Vec<Camera> {
    let k = cfg.intrinsics();
    (0..n)
        .map(|_| {
            let az = rng.random_range(0.0..360.0f32);
            let h = rng.random_range((8.0f32).to_radians().sin()..(72.0f32).to_radians().sin());
            let el = h.asin().to_degrees();
            let d = object.view.distance * rng.random_range(0.92..1.08f32);
            let target =
                Vec3::new(rng.random_range(-0.04..0.04), rng.random_range(-0.04..0.04), rng.random_range(-0.04..0.04));
            camera_at(k, az, el, d, target)
        })
        .collect()
}

/// Evenly spaced test views on a ring at 30 degrees elevation.
fn ring_views(object: &ArticulatedObject, cfg: &SynthConfig, n: usize) -> Vec<Camera> {
    let k = cfg.intrinsics();
    (0..n)
        .map(|i| {
            let az = object.view.front_azimuth_deg + 36.0 + 360.0 * i as f32 / n as f32;
            camera_at(k, az, 30.0, object.view.distance, Vec3::ZERO)
        })
        .collect()
}

/// The motion video's camera at normalised time `s`: a smooth arc around the front.
pub fn motion_camera(object: &ArticulatedObject, cfg: &SynthConfig, s: f32) -> Camera {
    let v = &object.view;
    let az = v.front_azimuth_deg - 70.0 + 140.0 * s;
    let el = v.motion_elevation_deg + 8.0 * (2.0 * PI * s).sin();
    let d = v.distance * (1.0 + 0.05 * (2.0 * PI * s).cos());
    camera_at(cfg.intrinsics(), az, el, d, Vec3::ZERO)
}

/// Every view of the dataset, in a fixed order. Deterministic for `cfg.seed`.
pub fn plan_views(object: &ArticulatedObject, cfg: &SynthConfig) -> Vec<PlannedView> {
    let mut views = Vec::new();
    for (folder, count, time, salt) in
        [(StateFolder::Start, cfg.scan_views, 0.0f32, 0x5ca7u64), (StateFolder::End, cfg.end_views, 1.0, 0xe17d)]
    {
        let mut rng = ChaCha8Rng::seed_from_u64(cfg.seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) ^ salt);
        for (index, camera) in hemisphere_views(object, cfg, count, &mut rng).into_iter().enumerate() {
            views.push(PlannedView { folder, split: Split::Train, index, time, frame_time: None, camera });
        }
        for (index, camera) in ring_views(object, cfg, cfg.test_views).into_iter().enumerate() {
            views.push(PlannedView { folder, split: Split::Test, index, time, frame_time: None, camera });
        }
    }
    let n = cfg.motion_frames;
    let (mut train_i, mut test_i) = (0, 0);
    for i in 0..n {
        let s = i as f32 / (n - 1) as f32;
        let held_out = cfg.motion_test_every > 0 && i % cfg.motion_test_every == cfg.motion_test_every / 2;
        let (split, index) = if held_out {
            test_i += 1;
            (Split::Test, test_i - 1)
        } else {
            train_i += 1;
            (Split::Train, train_i - 1)
        };
        views.push(PlannedView {
            folder: StateFolder::Motion,
            split,
            index,
            time: s,
            frame_time: Some(s),
            camera: motion_camera(object, cfg, s),
        });
    }
    views
}

/// Summary of a written dataset.
#[derive(Clone, Debug, Serialize)]
pub struct DatasetSummary {
    pub object: String,
    pub out: PathBuf,
    pub views: usize,
    pub parts: usize,
}

#[derive(Serialize)]
struct SynthMeta<'a> {
    generator: &'static str,
    version: &'static str,
    object: &'a str,
    config: &'a SynthConfig,
    /// World box containing the object at every time of the motion (for initialising
    /// random points inside the object's region).
    bounds: BoundsJson,
    conventions: Conventions,
}

#[derive(Serialize)]
struct BoundsJson {
    min: [f32; 3],
    max: [f32; 3],
}

#[derive(Serialize)]
struct Conventions {
    world: &'static str,
    transform_matrix: &'static str,
    depth: &'static str,
    part: &'static str,
    time: &'static str,
}

fn png_bytes(img: image::DynamicImage, path: &Path) -> Result<Vec<u8>> {
    let mut buf = Cursor::new(Vec::new());
    img.write_to(&mut buf, image::ImageFormat::Png)
        .map_err(|e| Error::Other(format!("{}: cannot encode PNG: {e}", path.display())))?;
    Ok(buf.into_inner())
}

fn create_dir(path: &Path) -> Result<()> {
    std::fs::create_dir_all(path).map_err(|e| Error::io(path, e))
}

/// Render and write one view's three PNGs.
fn write_view(
    object: &ArticulatedObject,
    view: &PlannedView,
    out: &Path,
    opts: &RenderOptions,
    global: usize,
) -> Result<()> {
    let scene = object.posed(view.time);
    let opts = RenderOptions { seed: opts.seed.wrapping_add(global as u64 * 0x1000_0001), ..*opts };
    let r = render(&scene, &view.camera, &opts);
    let dir = out.join(view.folder.dir());
    let stem = view.stem();
    let rgba = dir.join(format!("{stem}.png"));
    write_atomic(&rgba, &png_bytes(image::DynamicImage::ImageRgba8(r.to_rgba8()), &rgba)?)?;
    let depth = dir.join(format!("{stem}_depth.png"));
    write_atomic(&depth, &png_bytes(image::DynamicImage::ImageLuma16(r.depth_mm()), &depth)?)?;
    let part = dir.join(format!("{stem}_part.png"));
    write_atomic(&part, &png_bytes(image::DynamicImage::ImageLuma8(r.part_image()), &part)?)?;
    Ok(())
}

fn transforms_json(cfg: &SynthConfig, views: &[&PlannedView]) -> TransformsFile {
    let frames = views
        .iter()
        .map(|v| {
            let c = blender_camera_to_world_from_opencv(v.camera.world_to_camera);
            // Exact last row (the inverse leaves ~1e-8 residue).
            let c2w = glam::Mat4::from_cols(
                c.x_axis.truncate().extend(0.0),
                c.y_axis.truncate().extend(0.0),
                c.z_axis.truncate().extend(0.0),
                c.w_axis.truncate().extend(1.0),
            );
            let stem = v.stem();
            TransformsFrame {
                file_path: format!("./{stem}"),
                transform_matrix: c2w.transpose().to_cols_array_2d(),
                time: v.frame_time,
                depth_file_path: Some(format!("./{stem}_depth")),
                part_file_path: Some(format!("./{stem}_part")),
            }
        })
        .collect();
    TransformsFile { camera_angle_x: cfg.camera_angle_x, frames }
}

fn to_json<T: Serialize>(v: &T, path: &Path) -> Result<Vec<u8>> {
    serde_json::to_vec_pretty(v).map_err(|e| Error::Other(format!("{}: cannot serialise: {e}", path.display())))
}

/// Render every view of `object` and write the dataset and its ground truth under `out`.
/// `progress` is called after each rendered view with (done, total).
pub fn write_dataset(
    object: &ArticulatedObject,
    out: &Path,
    cfg: &SynthConfig,
    progress: &(dyn Fn(usize, usize) + Sync),
) -> Result<DatasetSummary> {
    cfg.validate()?;
    create_dir(out)?;
    let views = plan_views(object, cfg);
    for folder in [StateFolder::Start, StateFolder::Motion, StateFolder::End] {
        for split in [Split::Train, Split::Test] {
            create_dir(&out.join(folder.dir()).join(split.dir()))?;
        }
    }
    let opts = RenderOptions { samples_per_pixel: cfg.samples_per_pixel, seed: cfg.seed, ..Default::default() };
    let done = std::sync::atomic::AtomicUsize::new(0);
    views.par_iter().enumerate().try_for_each(|(g, v)| {
        write_view(object, v, out, &opts, g)?;
        let d = done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
        progress(d, views.len());
        Ok::<(), Error>(())
    })?;
    for folder in [StateFolder::Start, StateFolder::Motion, StateFolder::End] {
        for split in [Split::Train, Split::Test] {
            let sel: Vec<&PlannedView> = views.iter().filter(|v| v.folder == folder && v.split == split).collect();
            let path = out.join(folder.dir()).join(format!("transforms_{}.json", split.dir()));
            write_atomic(&path, &to_json(&transforms_json(cfg, &sel), &path)?)?;
        }
    }
    write_ground_truth(object, &out.join("gt"))?;
    let meta = SynthMeta {
        generator: "aim synth",
        version: env!("CARGO_PKG_VERSION"),
        object: &object.name,
        config: cfg,
        bounds: {
            let b = object.swept_bounds(32);
            BoundsJson { min: b.min.to_array(), max: b.max.to_array() }
        },
        conventions: Conventions {
            world: "z up, object front faces -y, units are metres",
            transform_matrix: "Blender/OpenGL camera-to-world (x right, y up, z backward), list of rows",
            depth: "uint16 PNG, z-depth along the optical axis in millimetres, 0 = background",
            part: "8-bit PNG, value = part id (gt/joints.json parts), 255 = background",
            time: "motion frame i of N at time i/(N-1); joint state q(t) = range[0] + t (range[1] - range[0])",
        },
    };
    let meta_path = out.join("synth.json");
    write_atomic(&meta_path, &to_json(&meta, &meta_path)?)?;
    Ok(DatasetSummary {
        object: object.name.clone(),
        out: out.to_path_buf(),
        views: views.len(),
        parts: object.parts.len(),
    })
}
