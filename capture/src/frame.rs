//! The unit every source produces: an undistorted, posed, time-stamped image.
//!
//! Conventions (shared with the reconstruction crate): OpenCV camera axes
//! (x right, y down, z forward), `world_to_camera` maps world points into that
//! frame, and pixel (i, j) has its centre at (i + 0.5, j + 0.5) in intrinsics
//! coordinates (gsplat's convention).

use std::sync::Arc;

use glam::{Mat3, Mat4, Vec3};
use serde::{Deserialize, Serialize};

/// A linear (pinhole) camera's intrinsics in pixels.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Intrinsics {
    pub width: u32,
    pub height: u32,
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
}

impl Intrinsics {
    /// Intrinsics from a horizontal field of view (Blender/NeRF `camera_angle_x`),
    /// square pixels, principal point at the image centre.
    pub fn from_fov_x(width: u32, height: u32, camera_angle_x: f32) -> Self {
        let fx = 0.5 * width as f32 / (0.5 * camera_angle_x).tan();
        Self { width, height, fx, fy: fx, cx: 0.5 * width as f32, cy: 0.5 * height as f32 }
    }

    /// Horizontal field of view in radians (inverse of [`Intrinsics::from_fov_x`]).
    pub fn fov_x(&self) -> f32 {
        2.0 * (0.5 * self.width as f32 / self.fx).atan()
    }

    /// The same camera at another resolution (pixel-centre convention preserved).
    pub fn scaled(&self, width: u32, height: u32) -> Self {
        let sx = width as f32 / self.width as f32;
        let sy = height as f32 / self.height as f32;
        Self { width, height, fx: self.fx * sx, fy: self.fy * sy, cx: self.cx * sx, cy: self.cy * sy }
    }

    /// Unit-depth direction (camera frame) through the continuous pixel coordinate (u, v).
    pub fn unproject(&self, u: f32, v: f32) -> Vec3 {
        Vec3::new((u - self.cx) / self.fx, (v - self.cy) / self.fy, 1.0)
    }
}

/// Blender/OpenGL camera-to-world (x right, y up, z backward) to OpenCV world-to-camera.
pub fn opencv_world_to_camera_from_blender(c2w_blender: Mat4) -> Mat4 {
    let flip = Mat4::from_diagonal(glam::Vec4::new(1.0, -1.0, -1.0, 1.0));
    (c2w_blender * flip).inverse()
}

/// OpenCV world-to-camera back to a Blender/OpenGL camera-to-world.
pub fn blender_camera_to_world_from_opencv(w2c: Mat4) -> Mat4 {
    let flip = Mat4::from_diagonal(glam::Vec4::new(1.0, -1.0, -1.0, 1.0));
    w2c.inverse() * flip
}

/// True when the upper-left 3x3 is a proper rotation (orthonormal, det +1) within `tol`.
pub fn is_rigid(m: &Mat4, tol: f32) -> bool {
    let r = Mat3::from_mat4(*m);
    let rtr = r.transpose() * r;
    let id_err = (rtr - Mat3::IDENTITY).to_cols_array().iter().map(|x| x.abs()).fold(0.0f32, f32::max);
    m.is_finite() && id_err < tol && (r.determinant() - 1.0).abs() < tol && m.row(3) == glam::Vec4::W
}

/// Where a frame sits relative to the interaction.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Phase {
    /// Before hand-in: the object is static in its start state.
    Scan,
    /// Between hand-in and hand-out: parts are moving.
    Motion,
    /// After hand-out: the object is static in its end state.
    After,
}

/// An undistorted, posed, time-stamped RGBA frame.
#[derive(Clone, Debug)]
pub struct Frame {
    /// Index within its source, in capture order.
    pub index: usize,
    /// Capture time in seconds on the source's clock.
    pub timestamp_s: f64,
    /// Time within the motion window in [0, 1] when known (datasets give it; a live
    /// capture only knows seconds since hand-in).
    pub motion_time: Option<f32>,
    pub phase: Phase,
    pub intrinsics: Intrinsics,
    /// OpenCV world-to-camera.
    pub world_to_camera: Mat4,
    pub image: Arc<image::RgbaImage>,
    /// Optional metric depth in metres (row-major, width*height; 0 = unknown).
    pub depth: Option<Arc<Vec<f32>>>,
    /// Where the image came from, for error messages.
    pub source: String,
}
