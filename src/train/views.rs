//! Training views: a camera plus its target image as premultiplied linear
//! floats, resized to the training resolution, ready to composite over any
//! background.

use std::sync::Arc;

use aim_capture::Frame;
use glam::Vec3;
use rayon::prelude::*;

use crate::camera::Camera;
use crate::error::{Error, Result};
use crate::render::RenderOptions;

/// One posed target image.
#[derive(Clone, Debug)]
pub struct TrainView {
    pub name: String,
    pub camera: Camera,
    /// RGB premultiplied by alpha, row-major, 3 per pixel, in [0, 1].
    pub premultiplied: Vec<f32>,
    /// Coverage per pixel; None when the image is opaque.
    pub alpha: Option<Vec<f32>>,
    /// Time within the motion in [0, 1], when the frame has one.
    pub time: Option<f32>,
    /// Metric z-depth per pixel (metres, 0 = unknown), when the dataset has it and
    /// it was asked for; resized by nearest pixel (depths must not blend across edges).
    pub depth: Option<Vec<f32>>,
    /// What the view shows behind the object (row-major RGB), when that is a
    /// fixed scene rather than one colour: the room of a raw recording,
    /// rendered from the room's own Gaussians.
    pub backdrop: Option<Arc<[f32]>>,
    /// World positions of the palms the capture's hand tracking saw at this
    /// frame (a recording's MPS hands; empty when none): the hand holding a part
    /// tells where it is in 3D (`train::contact`).
    pub palms: Vec<Vec3>,
}

impl TrainView {
    /// Build from a frame, resizing to `width` pixels wide (0 = keep) with an
    /// area-weighted filter applied to premultiplied colour (no dark fringes).
    pub fn from_frame(frame: &Frame, width: u32) -> Result<Self> {
        let img = &frame.image;
        let k = frame.intrinsics;
        if img.width() != k.width || img.height() != k.height {
            return Err(Error::bad_file(
                &frame.source,
                format!("image is {}x{} but its camera says {}x{}", img.width(), img.height(), k.width, k.height),
            ));
        }
        let (w, h) = if width == 0 || width >= k.width {
            (k.width, k.height)
        } else {
            (width, ((k.height as f64 * width as f64 / k.width as f64).round() as u32).max(1))
        };
        let mut premul = image::Rgba32FImage::new(img.width(), img.height());
        let mut opaque = true;
        for (src, dst) in img.pixels().zip(premul.pixels_mut()) {
            let a = src[3] as f32 / 255.0;
            opaque &= src[3] == 255;
            *dst = image::Rgba([src[0] as f32 / 255.0 * a, src[1] as f32 / 255.0 * a, src[2] as f32 / 255.0 * a, a]);
        }
        let resized = if (w, h) == (k.width, k.height) {
            premul
        } else {
            image::imageops::resize(&premul, w, h, image::imageops::FilterType::Triangle)
        };
        let mut premultiplied = Vec::with_capacity((3 * w * h) as usize);
        let mut alpha = Vec::with_capacity((w * h) as usize);
        for p in resized.pixels() {
            let a = p[3].clamp(0.0, 1.0);
            premultiplied.extend_from_slice(&[p[0].clamp(0.0, a), p[1].clamp(0.0, a), p[2].clamp(0.0, a)]);
            alpha.push(a);
        }
        if !frame.world_to_camera.is_finite() || !aim_capture::frame::is_rigid(&frame.world_to_camera, 1e-3) {
            return Err(Error::bad_file(&frame.source, "camera pose is not an invertible rigid transform"));
        }
        let depth = frame.depth.as_ref().map(|d| {
            let (sw, sh) = (k.width as usize, k.height as usize);
            (0..h as usize)
                .flat_map(|y| {
                    let sy = ((y as f64 + 0.5) * sh as f64 / f64::from(h)) as usize;
                    (0..w as usize)
                        .map(move |x| (sy.min(sh - 1), ((x as f64 + 0.5) * sw as f64 / f64::from(w)) as usize))
                })
                .map(|(sy, sx)| d[sy * sw + sx.min(sw - 1)])
                .collect()
        });
        Ok(Self {
            name: frame.source.clone(),
            camera: Camera::new(k.scaled(w, h), frame.world_to_camera),
            premultiplied,
            alpha: (!opaque).then_some(alpha),
            time: frame.motion_time,
            depth,
            backdrop: None,
            palms: Vec::new(),
        })
    }

    pub fn width(&self) -> u32 {
        self.camera.width()
    }

    pub fn height(&self) -> u32 {
        self.camera.height()
    }

    /// The depth loss of a render's accumulated depth `rendered` against this
    /// view's depth map at `weight` ([`crate::train::loss::depth_loss_and_grad`]):
    /// the loss and its gradient, None without a depth map or at weight 0.
    pub fn depth_loss(&self, rendered: &[f32], weight: f32) -> Option<(f32, Vec<f32>)> {
        let target = self.depth.as_ref().filter(|_| weight > 0.0)?;
        Some(crate::train::loss::depth_loss_and_grad(rendered, target, weight))
    }

    /// How to render the object for this view: over its backdrop when it has one,
    /// else over `background`.
    pub fn render_options(&self, background: Vec3) -> RenderOptions {
        RenderOptions { background_image: self.backdrop.clone(), ..RenderOptions::uniform(background) }
    }

    /// The target composited over `background`.
    pub fn target(&self, background: Vec3) -> Vec<f32> {
        match &self.alpha {
            None => self.premultiplied.clone(),
            Some(alpha) => self
                .premultiplied
                .chunks_exact(3)
                .zip(alpha)
                .flat_map(|(c, a)| {
                    let t = 1.0 - a;
                    [c[0] + background.x * t, c[1] + background.y * t, c[2] + background.z * t]
                })
                .collect(),
        }
    }
}

/// Convert frames to training views in parallel; errors name the frame's file.
pub fn views_from_frames(frames: &[Frame], width: u32) -> Result<Vec<TrainView>> {
    frames.par_iter().map(|f| TrainView::from_frame(f, width)).collect()
}

/// Scene extent as 3DGS computes it: 1.1 times the largest distance of a camera
/// centre from the cameras' mean centre (sets the mean learning rate and the
/// clone/split and prune sizes).
pub fn camera_extent(views: &[TrainView]) -> f32 {
    if views.is_empty() {
        return 1.0;
    }
    let centres: Vec<Vec3> = views.iter().map(|v| v.camera.position()).collect();
    let mean = centres.iter().copied().sum::<Vec3>() / centres.len() as f32;
    let r = centres.iter().map(|c| c.distance(mean)).fold(0.0f32, f32::max);
    (1.1 * r).max(1e-3)
}

/// Load the train and test views of one phase folder of an AiM-layout dataset
/// (`start` for Phase::Scan, `motion` for Phase::Motion, `end` for Phase::After),
/// checking that the training images agree in size; no test list = no test views.
/// With `depth`, the depth maps the dataset lists are read too.
pub fn load_phase_views(
    dataset: &std::path::Path,
    phase: aim_capture::Phase,
    width: u32,
    depth: bool,
) -> Result<(Vec<TrainView>, Vec<TrainView>)> {
    use aim_capture::dataset::{load_aim_transforms, LoadOptions};
    let folder = match phase {
        aim_capture::Phase::Scan => "start",
        aim_capture::Phase::Motion => "motion",
        aim_capture::Phase::After => "end",
    };
    let opts = LoadOptions { depth };
    let train_path = dataset.join(folder).join("transforms_train.json");
    let frames = load_aim_transforms(&train_path, phase, &opts)?;
    let Some(first) = frames.first() else {
        return Err(Error::bad_file(&train_path, "the frame list is empty"));
    };
    let (w0, h0) = (first.image.width(), first.image.height());
    if let Some(bad) = frames.iter().find(|f| (f.image.width(), f.image.height()) != (w0, h0)) {
        return Err(Error::bad_file(
            &bad.source,
            format!(
                "image is {}x{} but the other training images are {w0}x{h0}",
                bad.image.width(),
                bad.image.height()
            ),
        ));
    }
    let test_path = dataset.join(folder).join("transforms_test.json");
    let test_frames = if test_path.exists() { load_aim_transforms(&test_path, phase, &opts)? } else { Vec::new() };
    Ok((views_from_frames(&frames, width)?, views_from_frames(&test_frames, width)?))
}
