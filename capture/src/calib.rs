//! Aria device calibration: camera models (Fisheye624 = projectaria_tools'
//! FisheyeRadTanThinPrism with one focal length, KannalaBrandtK3, linear), rescaling to
//! the recorded resolution, and T_Device_Camera extrinsics.
//!
//! Pixel convention inside this module follows projectaria_tools: the centre of pixel
//! (i, j) is at (i, j) (so a W-wide linear camera has its principal point at (W-1)/2).
//! [`CameraCalibration::to_intrinsics`] and the undistortion convert to the library's
//! convention (centre at i + 0.5) when they hand frames out.

use std::path::Path;

use glam::{DMat4, DQuat, DVec2, DVec3};
use serde::Serialize;

use crate::error::{Error, Result};
use crate::frame::Intrinsics;

/// Newton iteration cap and convergence threshold for unprojection.
const NEWTON_ITERS: usize = 50;
const NEWTON_EPS: f64 = 1e-12;

/// A camera projection model and its parameters (pixels, projectaria convention).
#[derive(Clone, Debug, PartialEq, Serialize)]
#[serde(tag = "name", content = "params")]
pub enum CameraModel {
    /// FisheyeRadTanThinPrism, single focal length: [f, cx, cy, k0..k5, p0, p1, s0..s3].
    Fisheye624([f64; 15]),
    /// KannalaBrandtK3: [fx, fy, cx, cy, k0..k3].
    KannalaBrandtK3([f64; 8]),
    /// Pinhole: [fx, fy, cx, cy].
    Linear([f64; 4]),
}

impl CameraModel {
    /// The projectaria_tools name of the model.
    pub fn name(&self) -> &'static str {
        match self {
            CameraModel::Fisheye624(_) => "FisheyeRadTanThinPrism",
            CameraModel::KannalaBrandtK3(_) => "KannalaBrandtK3",
            CameraModel::Linear(_) => "Linear",
        }
    }

    pub fn params(&self) -> &[f64] {
        match self {
            CameraModel::Fisheye624(p) => p,
            CameraModel::KannalaBrandtK3(p) => p,
            CameraModel::Linear(p) => p,
        }
    }

    /// Focal lengths (fx, fy).
    pub fn focal(&self) -> (f64, f64) {
        match self {
            CameraModel::Fisheye624(p) => (p[0], p[0]),
            CameraModel::KannalaBrandtK3(p) => (p[0], p[1]),
            CameraModel::Linear(p) => (p[0], p[1]),
        }
    }

    /// Principal point (cx, cy).
    pub fn principal_point(&self) -> (f64, f64) {
        match self {
            CameraModel::Fisheye624(p) => (p[1], p[2]),
            CameraModel::KannalaBrandtK3(p) => (p[2], p[3]),
            CameraModel::Linear(p) => (p[2], p[3]),
        }
    }

    /// Build from a projectaria_tools name and parameter list, checking counts and values.
    pub fn from_name(name: &str, params: &[f64]) -> std::result::Result<Self, String> {
        if params.iter().any(|v| !v.is_finite()) {
            return Err(format!("{name}: non-finite parameter"));
        }
        let m = match name {
            "FisheyeRadTanThinPrism" | "Fisheye624" | "FISHEYE624" => {
                let p: [f64; 15] =
                    params.try_into().map_err(|_| format!("{name}: {} params, want 15", params.len()))?;
                CameraModel::Fisheye624(p)
            }
            "KannalaBrandtK3" => {
                let p: [f64; 8] = params.try_into().map_err(|_| format!("{name}: {} params, want 8", params.len()))?;
                CameraModel::KannalaBrandtK3(p)
            }
            "Linear" | "Pinhole" => {
                let p: [f64; 4] = params.try_into().map_err(|_| format!("{name}: {} params, want 4", params.len()))?;
                CameraModel::Linear(p)
            }
            other => return Err(format!("unsupported camera model {other:?}")),
        };
        let (fx, fy) = m.focal();
        if fx <= 0.0 || fy <= 0.0 {
            return Err(format!("{name}: focal length must be positive, got ({fx}, {fy})"));
        }
        Ok(m)
    }

    /// Project a camera-frame point to pixels. None behind the camera (z <= 0).
    pub fn project(&self, p: DVec3) -> Option<DVec2> {
        if p.z <= 0.0 || !p.is_finite() {
            return None;
        }
        let a = p.x / p.z;
        let b = p.y / p.z;
        match self {
            CameraModel::Linear(k) => Some(DVec2::new(k[0] * a + k[2], k[1] * b + k[3])),
            CameraModel::KannalaBrandtK3(k) => {
                let r = (a * a + b * b).sqrt();
                let th = r.atan();
                let th2 = th * th;
                let thd = th * (1.0 + th2 * (k[4] + th2 * (k[5] + th2 * (k[6] + th2 * k[7]))));
                let s = if r < f64::EPSILON { 1.0 } else { thd / r };
                Some(DVec2::new(k[0] * s * a + k[2], k[1] * s * b + k[3]))
            }
            CameraModel::Fisheye624(k) => {
                let r = (a * a + b * b).sqrt();
                let th = r.atan();
                let xr = DVec2::new(a, b) * (radial_624(k, th) * if r < f64::EPSILON { 1.0 } else { th / r });
                let uv = distort_tangential_prism(k, xr);
                Some(DVec2::new(k[0] * uv.x + k[1], k[0] * uv.y + k[2]))
            }
        }
    }

    /// Unproject a pixel to a ray direction with z = 1 (Newton iterations for fisheye models).
    /// None when the iterations do not converge or the ray leaves the 180-degree field.
    pub fn unproject(&self, px: DVec2) -> Option<DVec3> {
        match self {
            CameraModel::Linear(k) => Some(DVec3::new((px.x - k[2]) / k[0], (px.y - k[3]) / k[1], 1.0)),
            CameraModel::KannalaBrandtK3(k) => {
                let m = DVec2::new((px.x - k[2]) / k[0], (px.y - k[3]) / k[1]);
                let thd = m.length();
                if thd == 0.0 {
                    return Some(DVec3::Z);
                }
                let coeffs = [k[4], k[5], k[6], k[7], 0.0, 0.0];
                let th = solve_theta(&coeffs, thd)?;
                let s = th.tan() / thd;
                Some(DVec3::new(m.x * s, m.y * s, 1.0))
            }
            CameraModel::Fisheye624(k) => {
                let uvd = DVec2::new((px.x - k[1]) / k[0], (px.y - k[2]) / k[0]);
                // Invert the tangential + thin-prism terms by Newton on xr.
                let mut xr = uvd;
                let mut converged = false;
                for _ in 0..NEWTON_ITERS {
                    let est = distort_tangential_prism(k, xr);
                    let j = jacobian_tangential_prism(k, xr);
                    let det = j[0][0] * j[1][1] - j[0][1] * j[1][0];
                    if det.abs() < 1e-15 || !det.is_finite() {
                        return None;
                    }
                    let e = uvd - est;
                    let step =
                        DVec2::new((j[1][1] * e.x - j[0][1] * e.y) / det, (-j[1][0] * e.x + j[0][0] * e.y) / det);
                    xr += step;
                    if step.length_squared() < NEWTON_EPS * NEWTON_EPS {
                        converged = true;
                        break;
                    }
                }
                if !converged || !xr.is_finite() {
                    return None;
                }
                let thd = xr.length();
                if thd == 0.0 {
                    return Some(DVec3::Z);
                }
                let coeffs = [k[3], k[4], k[5], k[6], k[7], k[8]];
                let th = solve_theta(&coeffs, thd)?;
                let s = th.tan() / thd;
                Some(DVec3::new(xr.x * s, xr.y * s, 1.0))
            }
        }
    }

    /// The model for an image scaled by `scale` after cropping `offset` pixels from the
    /// top-left (projectaria_tools: subtractFromOrigin then scaleParams):
    /// c' = scale * (c - offset + 0.5) - 0.5, f' = scale * f.
    pub fn crop_and_scale(&self, offset: DVec2, scale: f64) -> Self {
        let mut m = self.clone();
        let (fi, ci): (&[usize], [usize; 2]) = match &m {
            CameraModel::Fisheye624(_) => (&[0], [1, 2]),
            CameraModel::KannalaBrandtK3(_) | CameraModel::Linear(_) => (&[0, 1], [2, 3]),
        };
        let p: &mut [f64] = match &mut m {
            CameraModel::Fisheye624(p) => p,
            CameraModel::KannalaBrandtK3(p) => p,
            CameraModel::Linear(p) => p,
        };
        for &i in fi {
            p[i] *= scale;
        }
        p[ci[0]] = scale * (p[ci[0]] - offset.x + 0.5) - 0.5;
        p[ci[1]] = scale * (p[ci[1]] - offset.y + 0.5) - 0.5;
        m
    }
}

/// theta * (1 + k0 theta^2 + ... + k5 theta^12) / theta, i.e. the radial factor.
fn radial_624(k: &[f64; 15], th: f64) -> f64 {
    let t2 = th * th;
    let mut acc = 0.0;
    for i in (3..9).rev() {
        acc = (acc + k[i]) * t2;
    }
    1.0 + acc
}

/// xr -> xr + tangential + thin prism (normalised coordinates).
fn distort_tangential_prism(k: &[f64; 15], xr: DVec2) -> DVec2 {
    let (p0, p1) = (k[9], k[10]);
    let r2 = xr.length_squared();
    let temp = 2.0 * (xr.x * p0 + xr.y * p1);
    let mut uv = xr + xr * temp + DVec2::new(p0, p1) * r2;
    let r4 = r2 * r2;
    uv.x += k[11] * r2 + k[12] * r4;
    uv.y += k[13] * r2 + k[14] * r4;
    uv
}

/// d(uv)/d(xr) of [`distort_tangential_prism`] as rows [[du/dx, du/dy], [dv/dx, dv/dy]].
fn jacobian_tangential_prism(k: &[f64; 15], xr: DVec2) -> [[f64; 2]; 2] {
    let (p0, p1) = (k[9], k[10]);
    let (x, y) = (xr.x, xr.y);
    let r2 = x * x + y * y;
    // u = x + 2x(x p0 + y p1) + p0 r2 + s0 r2 + s1 r2^2
    let du_dx = 1.0 + 6.0 * p0 * x + 2.0 * p1 * y + (k[11] + 2.0 * k[12] * r2) * 2.0 * x;
    let du_dy = 2.0 * p1 * x + 2.0 * p0 * y + (k[11] + 2.0 * k[12] * r2) * 2.0 * y;
    // v = y + 2y(x p0 + y p1) + p1 r2 + s2 r2 + s3 r2^2
    let dv_dx = 2.0 * p0 * y + 2.0 * p1 * x + (k[13] + 2.0 * k[14] * r2) * 2.0 * x;
    let dv_dy = 1.0 + 2.0 * p0 * x + 6.0 * p1 * y + (k[13] + 2.0 * k[14] * r2) * 2.0 * y;
    [[du_dx, du_dy], [dv_dx, dv_dy]]
}

/// Solve theta (1 + c0 theta^2 + c1 theta^4 + ...) = thd for theta in [0, pi/2) by Newton.
fn solve_theta(c: &[f64; 6], thd: f64) -> Option<f64> {
    let mut th = thd;
    for _ in 0..NEWTON_ITERS {
        let t2 = th * th;
        let mut poly = 0.0;
        let mut dpoly = 0.0;
        let mut t2i = t2;
        for (i, ci) in c.iter().enumerate() {
            poly += ci * t2i;
            dpoly += (2 * i + 3) as f64 * ci * t2i;
            t2i *= t2;
        }
        let f = th * (1.0 + poly) - thd;
        let df = 1.0 + dpoly;
        if df.abs() < 1e-12 {
            return None;
        }
        let step = f / df;
        th -= step;
        if th.abs() >= std::f64::consts::FRAC_PI_2 {
            th = 0.999 * std::f64::consts::FRAC_PI_2;
        }
        if step.abs() < NEWTON_EPS {
            return (0.0..std::f64::consts::FRAC_PI_2).contains(&th).then_some(th);
        }
    }
    None
}

/// A rigid transform (rotation then translation), f64.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Se3 {
    pub rotation: DQuat,
    pub translation: DVec3,
}

impl Se3 {
    pub const IDENTITY: Se3 = Se3 { rotation: DQuat::IDENTITY, translation: DVec3::ZERO };

    pub fn new(rotation: DQuat, translation: DVec3) -> Self {
        Se3 { rotation: rotation.normalize(), translation }
    }
    pub fn to_mat4(&self) -> DMat4 {
        DMat4::from_rotation_translation(self.rotation, self.translation)
    }
    pub fn inverse(&self) -> Se3 {
        let r = self.rotation.inverse();
        Se3 { rotation: r, translation: -(r * self.translation) }
    }
    pub fn transform_point(&self, p: DVec3) -> DVec3 {
        self.rotation * p + self.translation
    }
    /// self * other.
    pub fn compose(&self, other: &Se3) -> Se3 {
        Se3 {
            rotation: (self.rotation * other.rotation).normalize(),
            translation: self.transform_point(other.translation),
        }
    }
    /// Linear interpolation of translation and slerp of rotation.
    pub fn interpolate(&self, other: &Se3, s: f64) -> Se3 {
        Se3 {
            rotation: self.rotation.slerp(other.rotation, s).normalize(),
            translation: self.translation.lerp(other.translation, s),
        }
    }
}

/// One camera's calibration: model at a given image size, and its pose on the device.
#[derive(Clone, Debug, Serialize)]
pub struct CameraCalibration {
    pub label: String,
    pub model: CameraModel,
    pub width: u32,
    pub height: u32,
    pub t_device_camera: Se3,
    /// Largest field angle (radians from the optical axis) that is considered valid;
    /// projections beyond it are rejected (the polynomial is not calibrated there).
    pub max_theta: f64,
    /// Radius (pixels, at this resolution) around the image centre ((W-1)/2, (H-1)/2)
    /// outside which pixels are not valid (projectaria_tools' valid radius: the lens's
    /// image circle). None: the whole image.
    pub valid_radius: Option<f64>,
}

/// Aria RGB factory calibration from the public sample recording (native 2880 px):
/// [f, cx, cy, k0..k5, p0, p1, s0..s3].
pub const ARIA_RGB_PARAMS: [f64; 15] = [
    1214.025993758243,
    1469.535869576514,
    1438.595858396595,
    0.4049855059199108,
    -0.4960655170834019,
    0.2366889743579386,
    0.9948191490966187,
    -1.573948083968366,
    0.6086728193625544,
    -0.0003672190538065101,
    -0.0007413905358394097,
    -0.0005839984838196491,
    -0.0002193412417918993,
    0.0001936268547567258,
    -0.0002042473404798113,
];
/// T_Device_Camera of that RGB camera: translation (m) and quaternion (w, x, y, z).
pub const ARIA_RGB_T_DEVICE_CAMERA: ([f64; 3], [f64; 4]) = (
    [-0.004554731980229378, -0.01169138077305146, -0.004918788973669208],
    [0.9433499277148367, 0.3278414140126585, 0.03839318577298367, 0.03371771677908019],
);

/// Valid image-circle radius of Aria cameras at native resolution (projectaria_tools
/// uses 1415 px for the 2880 px RGB sensor: 707.5 px at 1408).
pub fn aria_valid_radius(label: &str) -> Option<f64> {
    match label {
        "camera-rgb" => Some(1415.0),
        _ => None,
    }
}

/// Native sensor size for Aria cameras, which calib_json does not store.
pub fn aria_native_size(label: &str) -> Option<(u32, u32)> {
    match label {
        "camera-rgb" => Some((2880, 2880)),
        "camera-slam-left" | "camera-slam-right" => Some((640, 480)),
        "camera-et-left" | "camera-et-right" => Some((640, 480)),
        _ => None,
    }
}

impl CameraCalibration {
    /// Project a camera-frame point; None if behind, beyond the valid field, or off-image.
    pub fn project(&self, p: DVec3) -> Option<DVec2> {
        if p.z <= 0.0 {
            return None;
        }
        let theta = (p.x * p.x + p.y * p.y).sqrt().atan2(p.z);
        if theta > self.max_theta {
            return None;
        }
        let px = self.model.project(p)?;
        self.is_visible(px).then_some(px)
    }

    /// Pixel inside the image (projectaria convention: [-0.5, W - 0.5)) and inside the
    /// valid radius, if any.
    pub fn is_visible(&self, px: DVec2) -> bool {
        let inside = px.x >= -0.5 && px.y >= -0.5 && px.x < self.width as f64 - 0.5 && px.y < self.height as f64 - 0.5;
        let (cx, cy) = self.model.principal_point();
        let centre = DVec2::new(cx, cy);
        inside && self.valid_radius.is_none_or(|r| (px - centre).length_squared() <= r * r)
    }

    pub fn unproject(&self, px: DVec2) -> Option<DVec3> {
        self.model.unproject(px)
    }

    /// The calibration for images of `width` x `height` recorded from this sensor:
    /// integer downscale k = floor(native / size), centred crop of the remainder (Aria RGB
    /// 2880 -> 1408: k = 2, crop 32 px, so c' = 0.5 (c - 32 + 0.5) - 0.5).
    pub fn rescaled_to(&self, width: u32, height: u32) -> Result<Self, String> {
        if width == 0 || height == 0 {
            return Err("zero image size".into());
        }
        if width == self.width && height == self.height {
            return Ok(self.clone());
        }
        let kx = (self.width / width).max(1);
        let ky = (self.height / height).max(1);
        if kx != ky {
            return Err(format!(
                "cannot map {}x{} calibration to {width}x{height}: different x and y scale",
                self.width, self.height
            ));
        }
        let k = kx as f64;
        let offset =
            DVec2::new((self.width as f64 - k * width as f64) / 2.0, (self.height as f64 - k * height as f64) / 2.0);
        Ok(CameraCalibration {
            model: self.model.crop_and_scale(offset, 1.0 / k),
            width,
            height,
            valid_radius: self.valid_radius.map(|r| r / k),
            ..self.clone()
        })
    }

    /// Pinhole intrinsics in the library's pixel convention (centres at i + 0.5), for
    /// linear models only.
    pub fn to_intrinsics(&self) -> Option<Intrinsics> {
        match self.model {
            CameraModel::Linear(p) => Some(Intrinsics {
                width: self.width,
                height: self.height,
                fx: p[0] as f32,
                fy: p[1] as f32,
                cx: (p[2] + 0.5) as f32,
                cy: (p[3] + 0.5) as f32,
            }),
            _ => None,
        }
    }

    /// projectaria_tools get_linear_camera_calibration(W, H, f): principal point at
    /// ((W-1)/2, (H-1)/2), same extrinsics as `self`.
    pub fn linear(&self, width: u32, height: u32, focal: f64) -> Self {
        CameraCalibration {
            label: self.label.clone(),
            model: CameraModel::Linear([focal, focal, (width as f64 - 1.0) / 2.0, (height as f64 - 1.0) / 2.0]),
            width,
            height,
            t_device_camera: self.t_device_camera,
            max_theta: std::f64::consts::FRAC_PI_2,
            valid_radius: None,
        }
    }

    /// The same camera with its image rotated clockwise by 90 degrees (Aria's RGB sensor
    /// is mounted sideways). Only for linear models: x' = -y, y' = x in camera axes.
    pub fn rotated_cw90(&self) -> Option<Self> {
        let CameraModel::Linear(p) = self.model else { return None };
        // Integer-centre convention: u' = H - 1 - v, v' = u.
        let model = CameraModel::Linear([p[1], p[0], self.height as f64 - 1.0 - p[3], p[2]]);
        let r = DQuat::from_rotation_z(std::f64::consts::FRAC_PI_2);
        Some(CameraCalibration {
            model,
            width: self.height,
            height: self.width,
            // T_device_camera' = T_device_camera * T_camera_camera'; camera' axes in camera frame:
            // p_cam' = R p_cam with R = rot_z(+90) (x' = -y, y' = x), so T_cam_cam' = R^-1.
            t_device_camera: self.t_device_camera.compose(&Se3::new(r.inverse(), DVec3::ZERO)),
            ..self.clone()
        })
    }
}

fn parse_se3(v: &serde_json::Value) -> std::result::Result<Se3, String> {
    let t = v.get("Translation").and_then(|t| t.as_array()).ok_or("T_Device_Camera without Translation")?;
    let q = v.get("UnitQuaternion").and_then(|t| t.as_array()).ok_or("T_Device_Camera without UnitQuaternion")?;
    let num = |x: &serde_json::Value| x.as_f64().ok_or("non-numeric transform value".to_string());
    if t.len() != 3 || q.len() != 2 {
        return Err("malformed T_Device_Camera".into());
    }
    let w = num(&q[0])?;
    let xyz = q[1].as_array().filter(|a| a.len() == 3).ok_or("malformed UnitQuaternion")?;
    let quat = DQuat::from_xyzw(num(&xyz[0])?, num(&xyz[1])?, num(&xyz[2])?, w);
    let tr = DVec3::new(num(&t[0])?, num(&t[1])?, num(&t[2])?);
    if !quat.is_finite() || !tr.is_finite() || (quat.length() - 1.0).abs() > 1e-3 {
        return Err("T_Device_Camera is not a valid rigid transform".into());
    }
    Ok(Se3::new(quat, tr))
}

/// Parse one entry of a "CameraCalibrations" array.
pub fn parse_camera(v: &serde_json::Value) -> std::result::Result<CameraCalibration, String> {
    let label = v.get("Label").and_then(|l| l.as_str()).ok_or("camera without Label")?.to_string();
    let proj = v.get("Projection").ok_or("camera without Projection")?;
    let name = proj.get("Name").and_then(|n| n.as_str()).ok_or("projection without Name")?;
    let params: Vec<f64> = proj
        .get("Params")
        .and_then(|p| p.as_array())
        .ok_or("projection without Params")?
        .iter()
        .map(|x| x.as_f64().ok_or("non-numeric projection parameter"))
        .collect::<std::result::Result<_, _>>()?;
    let model = CameraModel::from_name(name, &params).map_err(|e| format!("{label}: {e}"))?;
    let t_device_camera = v.get("T_Device_Camera").map(parse_se3).transpose()?.unwrap_or(Se3::IDENTITY);
    let (width, height) = aria_native_size(&label).unwrap_or_else(|| {
        let (cx, cy) = model.principal_point();
        ((2.0 * cx + 1.0).round().max(1.0) as u32, (2.0 * cy + 1.0).round().max(1.0) as u32)
    });
    let valid_radius = aria_valid_radius(&label);
    Ok(CameraCalibration {
        label,
        model,
        width,
        height,
        t_device_camera,
        max_theta: default_max_theta(&params, name),
        valid_radius,
    })
}

/// Aria's RGB lens covers about 110 degrees diagonally; beyond ~ 1.2 rad the distortion
/// polynomial is extrapolated. Linear models accept up to 90 degrees.
fn default_max_theta(_params: &[f64], name: &str) -> f64 {
    match name {
        "Linear" | "Pinhole" => std::f64::consts::FRAC_PI_2,
        _ => 1.4,
    }
}

/// A device calibration: all cameras found in a calib_json / online calibration line.
#[derive(Clone, Debug, Serialize)]
pub struct DeviceCalibration {
    pub cameras: Vec<CameraCalibration>,
    /// Cameras that were present but could not be parsed, with the reason.
    pub skipped: Vec<String>,
}

impl DeviceCalibration {
    /// Parse a calibration JSON (Aria factory calib_json or one online_calibration.jsonl line).
    pub fn from_json_str(path: &Path, s: &str) -> Result<Self> {
        let v: serde_json::Value =
            serde_json::from_str(s).map_err(|e| Error::bad_file(path, format!("calibration JSON: {e}")))?;
        Self::from_json(path, &v)
    }

    pub fn from_json(path: &Path, v: &serde_json::Value) -> Result<Self> {
        let cams = v
            .get("CameraCalibrations")
            .and_then(|c| c.as_array())
            .ok_or_else(|| Error::bad_file(path, "calibration JSON has no CameraCalibrations array"))?;
        let mut cameras = Vec::new();
        let mut skipped = Vec::new();
        for c in cams {
            match parse_camera(c) {
                Ok(cal) => cameras.push(cal),
                Err(e) => skipped.push(e),
            }
        }
        Ok(DeviceCalibration { cameras, skipped })
    }

    pub fn camera(&self, label: &str) -> Option<&CameraCalibration> {
        self.cameras.iter().find(|c| c.label == label)
    }

    /// The RGB camera, at its native (2880 px) resolution.
    pub fn rgb(&self, path: &Path) -> Result<&CameraCalibration> {
        self.camera("camera-rgb").ok_or_else(|| Error::bad_file(path, "calibration has no camera-rgb"))
    }
}

/// One line of MPS online_calibration.jsonl: a time-stamped device calibration.
#[derive(Clone, Debug)]
pub struct OnlineCalibration {
    pub tracking_timestamp_us: i64,
    pub calibration: DeviceCalibration,
}

/// Parse MPS online_calibration.jsonl text. Bad lines are errors naming the line.
pub fn parse_online_calibration(path: &Path, text: &str) -> Result<Vec<OnlineCalibration>> {
    let mut out = Vec::new();
    for (i, line) in text.lines().enumerate() {
        if line.trim().is_empty() {
            continue;
        }
        let v: serde_json::Value =
            serde_json::from_str(line).map_err(|e| Error::bad_file(path, format!("line {}: {e}", i + 1)))?;
        let t = v
            .get("tracking_timestamp_us")
            .and_then(|t| t.as_i64())
            .ok_or_else(|| Error::bad_file(path, format!("line {}: no tracking_timestamp_us", i + 1)))?;
        let calibration = DeviceCalibration::from_json(path, &v)
            .map_err(|e| Error::bad_file(path, format!("line {}: {e}", i + 1)))?;
        out.push(OnlineCalibration { tracking_timestamp_us: t, calibration });
    }
    Ok(out)
}

/// Load online_calibration.jsonl from disk.
pub fn load_online_calibration(path: &Path) -> Result<Vec<OnlineCalibration>> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    parse_online_calibration(path, &text)
}

#[cfg(test)]
mod tests {
    use super::*;

    pub(crate) fn sample_rgb() -> CameraModel {
        CameraModel::Fisheye624(ARIA_RGB_PARAMS)
    }

    #[test]
    fn fisheye624_matches_the_published_formula() {
        // Independent evaluation of the formula in ARCHITECTURE.md / FisheyeRadTanThinPrism.h.
        let m = sample_rgb();
        let k = m.params().to_vec();
        for p in [DVec3::new(0.3, -0.2, 1.0), DVec3::new(-0.9, 0.7, 1.1), DVec3::new(0.01, 0.02, 2.0)] {
            let (a, b) = (p.x / p.z, p.y / p.z);
            let r = (a * a + b * b).sqrt();
            let th = r.atan();
            let mut thd = th;
            for i in 0..6 {
                thd += k[3 + i] * th.powi(3 + 2 * i as i32);
            }
            let (xr, yr) = (thd / r * a, thd / r * b);
            let rd2 = xr * xr + yr * yr;
            let u = xr + (2.0 * xr * xr + rd2) * k[9] + 2.0 * xr * yr * k[10] + k[11] * rd2 + k[12] * rd2 * rd2;
            let v = yr + (2.0 * yr * yr + rd2) * k[10] + 2.0 * xr * yr * k[9] + k[13] * rd2 + k[14] * rd2 * rd2;
            let want = DVec2::new(k[0] * u + k[1], k[0] * v + k[2]);
            let got = m.project(p).unwrap();
            assert!((got - want).length() < 1e-9, "{got} vs {want}");
        }
    }

    #[test]
    fn fisheye624_round_trip_1e6() {
        let m = sample_rgb();
        let mut worst: f64 = 0.0;
        for i in 0..40 {
            for j in 0..40 {
                let a = -1.2 + 2.4 * i as f64 / 39.0;
                let b = -1.2 + 2.4 * j as f64 / 39.0;
                let x = DVec3::new(a, b, 1.0);
                let px = m.project(x).unwrap();
                let y = m.unproject(px).unwrap();
                worst = worst.max((y - x).length());
                // and pixel -> ray -> pixel
                let px2 = m.project(y).unwrap();
                worst = worst.max((px2 - px).length() * 1e-3);
            }
        }
        assert!(worst < 1e-6, "worst round-trip error {worst}");
    }

    #[test]
    fn kb3_round_trip() {
        let m = CameraModel::KannalaBrandtK3([556.96, 555.98, 319.5, 239.5, 0.0398, -0.0398, 0.1244, -0.278]);
        for (a, b) in [(0.1, 0.2), (-0.5, 0.4), (0.0, 0.0)] {
            let x = DVec3::new(a, b, 1.0);
            let y = m.unproject(m.project(x).unwrap()).unwrap();
            assert!((x - y).length() < 1e-9);
        }
    }

    #[test]
    fn rescale_rgb_to_1408() {
        let cal = CameraCalibration {
            label: "camera-rgb".into(),
            model: sample_rgb(),
            width: 2880,
            height: 2880,
            t_device_camera: Se3::IDENTITY,
            max_theta: 1.4,
            valid_radius: None,
        };
        let r = cal.rescaled_to(1408, 1408).unwrap();
        let (f, _) = r.model.focal();
        let (cx, cy) = r.model.principal_point();
        assert!((f - 607.013).abs() < 1e-2, "{f}");
        assert!((cx - (0.5 * (1469.535869576514 - 32.0 + 0.5) - 0.5)).abs() < 1e-9);
        assert!((cx - 718.518).abs() < 1e-2 && (cy - 703.048).abs() < 1e-2, "{cx} {cy}");
    }

    #[test]
    fn rotated_cw90_maps_pixels_consistently() {
        let cal = CameraCalibration {
            label: "x".into(),
            model: CameraModel::Linear([300.0, 310.0, 351.5, 340.0]),
            width: 704,
            height: 680,
            t_device_camera: Se3::IDENTITY,
            max_theta: 1.5,
            valid_radius: None,
        };
        let rot = cal.rotated_cw90().unwrap();
        let p_dev = DVec3::new(0.1, -0.3, 1.2);
        let px = cal.project(p_dev).unwrap();
        let p_cam2 = rot.t_device_camera.inverse().transform_point(p_dev);
        let px2 = rot.model.project(p_cam2).unwrap();
        // Clockwise rotation: u' = H - 1 - v, v' = u.
        assert!((px2.x - (680.0 - 1.0 - px.y)).abs() < 1e-9 && (px2.y - px.x).abs() < 1e-9, "{px} {px2}");
    }

    #[test]
    fn bad_params_are_rejected() {
        assert!(CameraModel::from_name("FisheyeRadTanThinPrism", &[1.0; 14]).is_err());
        assert!(CameraModel::from_name("FisheyeRadTanThinPrism", &[f64::NAN; 15]).is_err());
        assert!(CameraModel::from_name("Mystery", &[1.0; 4]).is_err());
        let mut p = [0.0; 15];
        p[0] = -1.0;
        assert!(CameraModel::from_name("FisheyeRadTanThinPrism", &p).is_err());
    }
}
