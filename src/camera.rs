//! The pinhole camera the renderer uses (OpenCV convention, world-to-camera).

use std::path::Path;

use glam::{Mat3, Mat4, Vec3};
use serde::{Deserialize, Serialize};

pub use aim_capture::frame::{blender_camera_to_world_from_opencv, opencv_world_to_camera_from_blender, Intrinsics};

use crate::error::{Error, Result};

/// A linear camera: intrinsics plus an OpenCV world-to-camera transform.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    pub intrinsics: Intrinsics,
    pub world_to_camera: Mat4,
}

impl Camera {
    pub fn new(intrinsics: Intrinsics, world_to_camera: Mat4) -> Self {
        Self { intrinsics, world_to_camera }
    }

    /// From a Blender/OpenGL camera-to-world matrix (as in transforms.json).
    pub fn from_blender_c2w(intrinsics: Intrinsics, c2w: Mat4) -> Self {
        Self::new(intrinsics, opencv_world_to_camera_from_blender(c2w))
    }

    /// A camera at `eye` looking at `target`, with `up` roughly up in the image.
    pub fn look_at(intrinsics: Intrinsics, eye: Vec3, target: Vec3, up: Vec3) -> Self {
        let z = (target - eye).normalize();
        let x = z.cross(up).normalize();
        let y = z.cross(x);
        // Rows of the rotation are the camera axes expressed in world coordinates.
        let r = Mat3::from_cols(x, y, z).transpose();
        let t = -(r * eye);
        Self::new(
            intrinsics,
            Mat4::from_cols(r.x_axis.extend(0.0), r.y_axis.extend(0.0), r.z_axis.extend(0.0), t.extend(1.0)),
        )
    }

    pub fn width(&self) -> u32 {
        self.intrinsics.width
    }

    pub fn height(&self) -> u32 {
        self.intrinsics.height
    }

    pub fn rotation(&self) -> Mat3 {
        Mat3::from_mat4(self.world_to_camera)
    }

    pub fn translation(&self) -> Vec3 {
        self.world_to_camera.w_axis.truncate()
    }

    /// Camera centre in world coordinates.
    pub fn position(&self) -> Vec3 {
        -(self.rotation().transpose() * self.translation())
    }

    /// World point to camera coordinates.
    pub fn to_camera(&self, p: Vec3) -> Vec3 {
        self.world_to_camera.transform_point3(p)
    }

    /// World point to continuous pixel coordinates and depth (z), if in front.
    pub fn project(&self, p: Vec3) -> Option<(f32, f32, f32)> {
        let c = self.to_camera(p);
        if c.z <= 0.0 {
            return None;
        }
        let (x, y) = self.image_point(c);
        Some((x, y, c.z))
    }

    /// Camera coordinates `c` to continuous pixel coordinates (meaningful for c.z > 0).
    #[inline]
    fn image_point(&self, c: Vec3) -> (f32, f32) {
        let k = &self.intrinsics;
        (k.fx * c.x / c.z + k.cx, k.fy * c.y / c.z + k.cy)
    }

    /// The row-major index of the pixel world point `p` falls in and its depth,
    /// when it lies in front of the camera and inside the image.
    pub fn pixel_of(&self, p: Vec3) -> Option<(usize, f32)> {
        let (inside, pixel, z) = self.landing(p);
        inside.then_some((pixel, z))
    }

    /// `pixel_of` without branches, for loops over many points: whether `p`
    /// lands in the image in front of the camera, the row-major pixel index
    /// (meaningful only then) and the depth.
    #[inline]
    pub fn landing(&self, p: Vec3) -> (bool, usize, f32) {
        let c = self.to_camera(p);
        let k = &self.intrinsics;
        let (x, y) = self.image_point(c);
        // `&`, not `&&`: every test is evaluated, none is a branch.
        let inside = (c.z > 0.0) & (x >= 0.0) & (y >= 0.0) & (x < k.width as f32) & (y < k.height as f32);
        (inside, (y as u32).wrapping_mul(k.width).wrapping_add(x as u32) as usize, c.z)
    }

    /// Load a camera file (see [`CameraFile`]), validating it.
    pub fn load_json(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        let file: CameraFile =
            serde_json::from_str(&text).map_err(|e| Error::bad_file(path, format!("not a camera file: {e}")))?;
        file.to_camera().map_err(|m| Error::bad_file(path, m))
    }
}

/// `{"width", "height", "fx", "fy", "cx", "cy", "world_to_camera": [[4 rows of 4]]}`,
/// OpenCV convention, row-major.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraFile {
    pub width: u32,
    pub height: u32,
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
    pub world_to_camera: [[f32; 4]; 4],
}

impl CameraFile {
    pub fn from_camera(c: &Camera) -> Self {
        let k = c.intrinsics;
        let m = c.world_to_camera.transpose().to_cols_array_2d();
        Self { width: k.width, height: k.height, fx: k.fx, fy: k.fy, cx: k.cx, cy: k.cy, world_to_camera: m }
    }

    pub fn to_camera(&self) -> std::result::Result<Camera, String> {
        let max = crate::render::raster::MAX_IMAGE_SIDE;
        if self.width == 0 || self.height == 0 || self.width > max || self.height > max {
            return Err(format!("image size must be 1 to {max} px on a side, got {}x{}", self.width, self.height));
        }
        for (name, v) in [("fx", self.fx), ("fy", self.fy)] {
            if !(v.is_finite() && v > 0.0) {
                return Err(format!("{name} must be a positive number, got {v}"));
            }
        }
        if !(self.cx.is_finite() && self.cy.is_finite()) {
            return Err("cx and cy must be finite".into());
        }
        // Rows given; glam stores columns.
        let m = Mat4::from_cols_array_2d(&self.world_to_camera).transpose();
        if !m.is_finite() {
            return Err("world_to_camera has non-finite entries".into());
        }
        if !aim_capture::frame::is_rigid(&m, 1e-3) {
            return Err("world_to_camera is not a rigid transform (its rotation must be orthonormal with determinant +1, last row 0 0 0 1)".into());
        }
        let k =
            Intrinsics { width: self.width, height: self.height, fx: self.fx, fy: self.fy, cx: self.cx, cy: self.cy };
        Ok(Camera::new(k, m))
    }
}

#[cfg(test)]
mod tests {
    use glam::Vec3;

    use super::{Camera, Intrinsics};

    #[test]
    fn a_point_has_a_pixel_only_in_front_of_the_camera_and_inside_the_image() {
        let k = Intrinsics { width: 40, height: 30, fx: 50.0, fy: 50.0, cx: 20.0, cy: 15.0 };
        let camera = Camera::look_at(k, Vec3::new(0.0, 0.0, 2.0), Vec3::ZERO, Vec3::Y);
        let (pixel, depth) = camera.pixel_of(Vec3::ZERO).expect("the target is in view");
        assert_eq!(pixel, 15 * 40 + 20, "the principal point's pixel");
        assert!((depth - 2.0).abs() < 1e-5, "depth {depth}");
        // 0.9 m to a side at 2 m is 22.5 px from the centre: past the 20 px half-width.
        assert!(camera.pixel_of(Vec3::new(0.9, 0.0, 0.0)).is_none(), "outside the image");
        assert!(camera.pixel_of(Vec3::new(0.7, 0.0, 0.0)).is_some(), "17.5 px from the centre: inside");
        assert!(camera.pixel_of(Vec3::new(0.0, 0.0, 3.0)).is_none(), "behind the camera");
    }
}
