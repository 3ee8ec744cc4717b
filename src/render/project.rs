//! Per-Gaussian projection to the image plane (EWA splatting) and its exact
//! backward pass: 3D mean, scale, rotation, SH -> 2D mean, conic, colour, depth.

use glam::{Mat2, Mat3, Quat, Vec2, Vec3};

use crate::camera::Camera;
use crate::render::sh;
use crate::splat::{sh_coeffs, sigmoid, GaussianSet};

/// Screen-space dilation added to the 2D covariance (pixels^2), as in 3DGS.
pub const COV2D_DILATION: f32 = 0.3;
/// Gaussians closer than this (camera z) are culled.
pub const NEAR_PLANE: f32 = 0.01;
/// Contributions with alpha below this are skipped.
pub const ALPHA_MIN: f32 = 1.0 / 255.0;
/// The 3DGS/gsplat limit on tan(angle) used in the projection Jacobian, in
/// units of the half field of view, so far-off-screen Gaussians stay stable.
const JACOBIAN_FOV_CLAMP: f32 = 1.3;

/// A Gaussian as the rasterizer sees it.
#[derive(Clone, Copy, Debug, Default)]
pub struct Projected {
    pub mean2d: Vec2,
    /// Inverse 2D covariance (a, b, c) of [[a, b], [b, c]].
    pub conic: [f32; 3],
    pub depth: f32,
    pub color: Vec3,
    pub opacity: f32,
    /// Inclusive pixel bounding box [x0, x1] x [y0, y1] of every pixel whose
    /// alpha can reach ALPHA_MIN, clipped to the image.
    pub bbox: [u32; 4],
    /// A lower bound on the Gaussian exponent ("power") below which alpha is
    /// surely under ALPHA_MIN: ln(ALPHA_MIN / opacity) less a small margin.
    pub power_cut: f32,
    /// 3 sigma of the major axis in pixels (the screen size density control prunes on).
    pub radius: f32,
    /// Row-chord coefficients of the ellipse power >= power_cut: for a row at
    /// vertical offset dy the reachable dx are -s0 dy +- sqrt(s1 dy^2 + s2).
    pub span: [f32; 3],
}

/// Everything about the camera the projection needs, computed once per render.
#[derive(Clone, Copy, Debug)]
pub struct ProjectionCamera {
    pub rot: Mat3,
    pub trans: Vec3,
    pub position: Vec3,
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
    pub width: u32,
    pub height: u32,
    lim_x: f32,
    lim_y: f32,
}

impl ProjectionCamera {
    pub fn new(cam: &Camera) -> Self {
        let k = cam.intrinsics;
        // Same limits as gsplat: the visible tan-range extended by 30% on each side.
        let lim_x_pos = (k.width as f32 - k.cx) / k.fx + JACOBIAN_FOV_CLAMP * 0.5 * k.width as f32 / k.fx;
        let lim_y_pos = (k.height as f32 - k.cy) / k.fy + JACOBIAN_FOV_CLAMP * 0.5 * k.height as f32 / k.fy;
        let lim_x_neg = k.cx / k.fx + JACOBIAN_FOV_CLAMP * 0.5 * k.width as f32 / k.fx;
        let lim_y_neg = k.cy / k.fy + JACOBIAN_FOV_CLAMP * 0.5 * k.height as f32 / k.fy;
        Self {
            rot: cam.rotation(),
            trans: cam.translation(),
            position: cam.position(),
            fx: k.fx,
            fy: k.fy,
            cx: k.cx,
            cy: k.cy,
            width: k.width,
            height: k.height,
            lim_x: lim_x_pos.max(lim_x_neg),
            lim_y: lim_y_pos.max(lim_y_neg),
        }
    }

    /// The same projection onto the pixels `region` = [x0, y0, x1, y1) of the
    /// image: pixel (x0, y0) becomes (0, 0). The Jacobian's limits stay the whole
    /// image's, so every Gaussian projects as it does for the whole image.
    pub fn region(mut self, region: [u32; 4]) -> Self {
        let [x0, y0, x1, y1] = region;
        self.cx -= x0 as f32;
        self.cy -= y0 as f32;
        self.width = x1 - x0;
        self.height = y1 - y0;
        self
    }

    /// The tan(angle) limits (x, y) of the projection Jacobian.
    pub fn limits(&self) -> (f32, f32) {
        (self.lim_x, self.lim_y)
    }

    /// The projection Jacobian at camera point `t`, and whether x / y were clamped.
    fn jacobian(&self, t: Vec3) -> (Mat3, bool, bool) {
        let rz = 1.0 / t.z;
        let (ux, uy) = (t.x * rz, t.y * rz);
        let (cx, cy) = (ux.clamp(-self.lim_x, self.lim_x), uy.clamp(-self.lim_y, self.lim_y));
        let j = Mat3::from_cols(
            Vec3::new(self.fx * rz, 0.0, 0.0),
            Vec3::new(0.0, self.fy * rz, 0.0),
            Vec3::new(-self.fx * cx * rz, -self.fy * cy * rz, 0.0),
        );
        (j, cx != ux, cy != uy)
    }
}

/// Rotation matrix of a unit quaternion.
fn rotation_matrix(q: Quat) -> Mat3 {
    Mat3::from_quat(q)
}

/// The 3D covariance factor M = R S (so Sigma = M M^T).
fn cov_factor(rot: Mat3, scale: Vec3) -> Mat3 {
    Mat3::from_cols(rot.x_axis * scale.x, rot.y_axis * scale.y, rot.z_axis * scale.z)
}

/// The upper-left 2x2 block of a 3x3 matrix whose third row is zero.
fn top2x2(m: Mat3) -> Mat2 {
    Mat2::from_cols(m.x_axis.truncate(), m.y_axis.truncate())
}

/// Project Gaussian `i`; `None` when it is culled (behind the near plane,
/// degenerate, invisible or entirely off-image).
pub fn project_one(gs: &GaussianSet, i: usize, cam: &ProjectionCamera, sh_degree: u32) -> Option<Projected> {
    let mean = gs.mean(i);
    let t = cam.rot * mean + cam.trans;
    if t.z < NEAR_PLANE {
        return None;
    }
    let opacity = sigmoid(gs.opacity_logits[i]);
    if opacity < ALPHA_MIN {
        return None;
    }
    let m = cov_factor(rotation_matrix(gs.rotation(i)), gs.log_scale(i).exp());
    let (j, _, _) = cam.jacobian(t);
    let tw = j * cam.rot; // rows 0..2 used
    let tm = tw * m;
    let full = tm * tm.transpose();
    let cov = top2x2(full) + Mat2::from_diagonal(Vec2::splat(COV2D_DILATION));
    let det = cov.determinant();
    if det.is_nan() || det <= 0.0 {
        return None;
    }
    let inv = cov.inverse();
    let conic = [inv.x_axis.x, inv.y_axis.x, inv.y_axis.y];
    let mean2d = Vec2::new(cam.fx * t.x / t.z + cam.cx, cam.fy * t.y / t.z + cam.cy);

    // Exact extent: alpha >= ALPHA_MIN needs the Mahalanobis distance^2 <= 2 ln(opacity / ALPHA_MIN);
    // an ellipse x^T C^-1 x <= r^2 has half-widths r sqrt(C_xx), r sqrt(C_yy).
    let r2 = 2.0 * (opacity / ALPHA_MIN).ln();
    let hx = (r2 * cov.x_axis.x).sqrt();
    let hy = (r2 * cov.y_axis.y).sqrt();
    // Pixel i's centre is i + 0.5; one pixel of margin keeps rounding from ever excluding a pixel.
    let x0 = (mean2d.x - hx - 0.5).floor() - 1.0;
    let x1 = (mean2d.x + hx - 0.5).ceil() + 1.0;
    let y0 = (mean2d.y - hy - 0.5).floor() - 1.0;
    let y1 = (mean2d.y + hy - 0.5).ceil() + 1.0;
    if !(x1 >= 0.0 && y1 >= 0.0 && x0 < cam.width as f32 && y0 < cam.height as f32) {
        return None;
    }
    let bbox = [
        x0.max(0.0) as u32,
        y0.max(0.0) as u32,
        x1.min(cam.width as f32 - 1.0) as u32,
        y1.min(cam.height as f32 - 1.0) as u32,
    ];

    let color = eval_color(gs, i, cam.position, sh_degree);
    let power_cut = (ALPHA_MIN / opacity).ln() - 1e-3;
    let mid = 0.5 * (cov.x_axis.x + cov.y_axis.y);
    let radius = 3.0 * (mid + (mid * mid - det).max(0.0).sqrt()).sqrt();
    // a dx^2 + 2 b dy dx + c dy^2 + 2 power_cut <= 0, divided through by a.
    let [a, b, c] = conic;
    let span = [b / a, (b * b - a * c) / (a * a), -2.0 * power_cut / a];
    Some(Projected { mean2d, conic, depth: t.z, color, opacity, bbox, power_cut, radius, span })
}

/// View-dependent colour (SH + 0.5, clamped at 0).
fn eval_color(gs: &GaussianSet, i: usize, cam_pos: Vec3, sh_degree: u32) -> Vec3 {
    let dir = (gs.mean(i) - cam_pos).normalize_or_zero();
    let y = sh::basis(sh_degree, dir);
    let mut c = Vec3::from_slice(&gs.sh_dc[3 * i..3 * i + 3]) * y[0];
    let rest_w = (sh_coeffs(gs.sh_degree) - 1) * 3;
    let rest = &gs.sh_rest[i * rest_w..(i + 1) * rest_w];
    for (k, yk) in y.iter().enumerate().take(sh_coeffs(sh_degree)).skip(1) {
        c += Vec3::from_slice(&rest[3 * (k - 1)..3 * k]) * *yk;
    }
    (c + Vec3::splat(0.5)).max(Vec3::ZERO)
}

/// Gradient of the loss with respect to one Gaussian's projected quantities.
#[derive(Clone, Copy, Debug, Default)]
pub struct ProjectedGrad {
    pub mean2d: Vec2,
    pub conic: [f32; 3],
    pub color: Vec3,
    pub opacity: f32,
    pub depth: f32,
}

/// Gradient for one Gaussian's raw parameters (the SH rest coefficients are
/// written to a caller-provided row instead, to avoid an allocation per Gaussian).
#[derive(Clone, Copy, Debug, Default)]
pub struct RawGrad {
    pub mean: Vec3,
    pub log_scale: Vec3,
    /// w, x, y, z of the raw (unnormalised) quaternion.
    pub rotation: [f32; 4],
    pub opacity_logit: f32,
    pub sh_dc: Vec3,
}

/// Backward of [`project_one`] for a Gaussian that was not culled: `proj` is
/// its forward result, `sh_rest` receives dL/d(SH rest) (coefficient-major
/// `[k][rgb]`, the stored degree's width; entries above the active degree stay 0).
pub fn project_one_backward(
    gs: &GaussianSet,
    i: usize,
    cam: &ProjectionCamera,
    sh_degree: u32,
    proj: &Projected,
    g: &ProjectedGrad,
    sh_rest: &mut [f32],
) -> RawGrad {
    let mean = gs.mean(i);
    let t = cam.rot * mean + cam.trans;
    let scale = gs.log_scale(i).exp();
    let r = &gs.rotations[4 * i..4 * i + 4];
    let q_raw = glam::Vec4::new(r[0], r[1], r[2], r[3]);
    let q = gs.rotation(i);
    let rot = rotation_matrix(q);
    let m = cov_factor(rot, scale);
    let (j, clamped_x, clamped_y) = cam.jacobian(t);
    let tw = j * cam.rot;
    let tm = tw * m;
    let cov = top2x2(tm * tm.transpose()) + Mat2::from_diagonal(Vec2::splat(COV2D_DILATION));
    let inv = cov.inverse();

    let mut out = RawGrad::default();

    // Opacity: sigmoid'.
    let op = sigmoid(gs.opacity_logits[i]);
    out.opacity_logit = g.opacity * op * (1.0 - op);

    // Conic -> 2D covariance: dL/dC = -C^-1 G C^-1, with G the symmetric matrix gradient
    // (the off-diagonal b appears twice in x^T Q x, hence the halving).
    let gq = Mat2::from_cols(Vec2::new(g.conic[0], 0.5 * g.conic[1]), Vec2::new(0.5 * g.conic[1], g.conic[2]));
    let gcov = -(inv * gq * inv);
    // 2D covariance = (T M)(T M)^T restricted to rows 0..2, T = J W.
    let gcov3 = Mat3::from_cols(gcov.x_axis.extend(0.0), gcov.y_axis.extend(0.0), Vec3::ZERO);
    // d/dA of (A A^T) with symmetric G: 2 G A.
    let g_tm = 2.0 * gcov3 * tm;
    let g_m = tw.transpose() * g_tm;
    let g_tw = g_tm * m.transpose();
    let g_j = g_tw * cam.rot.transpose();

    // Scale and rotation from M = R diag(s).
    let g_s = Vec3::new(g_m.x_axis.dot(rot.x_axis), g_m.y_axis.dot(rot.y_axis), g_m.z_axis.dot(rot.z_axis));
    out.log_scale = g_s * scale;
    let g_rot = Mat3::from_cols(g_m.x_axis * scale.x, g_m.y_axis * scale.y, g_m.z_axis * scale.z);
    let g_qn = quat_matrix_backward(q, g_rot);
    // Through the normalisation q / |q|.
    let qn = glam::Vec4::new(q.w, q.x, q.y, q.z);
    let norm = q_raw.length().max(1e-12);
    let g_q = (g_qn - qn * qn.dot(g_qn)) / norm;
    out.rotation = g_q.to_array();

    // Camera-space point t: through the mean2d, the depth and the Jacobian J(t).
    let rz = 1.0 / t.z;
    let rz2 = rz * rz;
    let mut g_t = Vec3::new(
        g.mean2d.x * cam.fx * rz,
        g.mean2d.y * cam.fy * rz,
        -g.mean2d.x * cam.fx * t.x * rz2 - g.mean2d.y * cam.fy * t.y * rz2 + g.depth,
    );
    // J = [[fx/z, 0, -fx ux], [0, fy/z, -fy uy]] with u = clamp(t.xy / z).
    let (j00, j11, j02, j12) = (g_j.x_axis.x, g_j.y_axis.y, g_j.z_axis.x, g_j.z_axis.y);
    g_t.z += -cam.fx * rz2 * j00 - cam.fy * rz2 * j11;
    // J02 = -fx ux / z where ux = x/z unless clamped (then ux is a constant).
    if clamped_x {
        let ux = j.z_axis.x / (-cam.fx * rz);
        g_t.z += j02 * cam.fx * ux * rz2;
    } else {
        g_t.x += j02 * (-cam.fx * rz2);
        g_t.z += j02 * 2.0 * cam.fx * t.x * rz2 * rz;
    }
    if clamped_y {
        let uy = j.z_axis.y / (-cam.fy * rz);
        g_t.z += j12 * cam.fy * uy * rz2;
    } else {
        g_t.y += j12 * (-cam.fy * rz2);
        g_t.z += j12 * 2.0 * cam.fy * t.y * rz2 * rz;
    }
    out.mean = cam.rot.transpose() * g_t;

    // Colour through SH, including the view direction's dependence on the mean.
    let v = mean - cam.position;
    let vlen = v.length();
    if vlen > 0.0 {
        let dir = v / vlen;
        // The clamp at 0 passes no gradient.
        let gc = Vec3::select(proj.color.cmpgt(Vec3::ZERO), g.color, Vec3::ZERO);
        let y = sh::basis(sh_degree, dir);
        let dy = sh::basis_grad(sh_degree, dir);
        out.sh_dc = gc * y[0];
        let rest_w = sh_rest.len();
        let rest = &gs.sh_rest[i * rest_w..(i + 1) * rest_w];
        let mut g_dir = Vec3::ZERO;
        for k in 1..sh_coeffs(sh_degree) {
            let coeff = Vec3::from_slice(&rest[3 * (k - 1)..3 * k]);
            let gk = gc * y[k];
            sh_rest[3 * (k - 1)..3 * k].copy_from_slice(&gk.to_array());
            g_dir += dy[k] * coeff.dot(gc);
        }
        out.mean += (g_dir - dir * dir.dot(g_dir)) / vlen;
    }
    out
}

/// Gradient of a loss with respect to a unit quaternion (w, x, y, z) given the
/// gradient with respect to its rotation matrix.
fn quat_matrix_backward(q: Quat, g: Mat3) -> glam::Vec4 {
    let (w, x, y, z) = (q.w, q.x, q.y, q.z);
    // g.col(c).row(r) = dL/dR[r][c]
    let gr = |r: usize, c: usize| g.col(c)[r];
    // R = [[1-2(yy+zz), 2(xy-wz), 2(xz+wy)], [2(xy+wz), 1-2(xx+zz), 2(yz-wx)], [2(xz-wy), 2(yz+wx), 1-2(xx+yy)]]
    let gw = 2.0 * (-z * gr(0, 1) + y * gr(0, 2) + z * gr(1, 0) - x * gr(1, 2) - y * gr(2, 0) + x * gr(2, 1));
    let gx = 2.0
        * (y * gr(0, 1) + z * gr(0, 2) + y * gr(1, 0) - 2.0 * x * gr(1, 1) - w * gr(1, 2)
            + z * gr(2, 0)
            + w * gr(2, 1)
            - 2.0 * x * gr(2, 2));
    let gy = 2.0
        * (-2.0 * y * gr(0, 0) + x * gr(0, 1) + w * gr(0, 2) + x * gr(1, 0) + z * gr(1, 2) - w * gr(2, 0)
            + z * gr(2, 1)
            - 2.0 * y * gr(2, 2));
    let gz = 2.0
        * (-2.0 * z * gr(0, 0) - w * gr(0, 1) + x * gr(0, 2) + w * gr(1, 0) - 2.0 * z * gr(1, 1)
            + y * gr(1, 2)
            + x * gr(2, 0)
            + y * gr(2, 1));
    glam::Vec4::new(gw, gx, gy, gz)
}

/// [`project_one_backward`] for every Gaussian that `projected` kept and
/// `wanted` asks for (None: all), in parallel. Returns the per-Gaussian
/// gradients (None where culled or not wanted) and the SH rest gradients as one
/// flat buffer in the set's layout (zero where None).
pub fn project_backward_all(
    gs: &GaussianSet,
    projected: &[Option<Projected>],
    cam: &ProjectionCamera,
    sh_degree: u32,
    grads: &[ProjectedGrad],
    wanted: Option<&[bool]>,
) -> (Vec<Option<RawGrad>>, Vec<f32>) {
    use rayon::prelude::*;
    let n = gs.len();
    let rest_w = gs.width(crate::splat::ParamGroup::ShRest);
    // Rows of at least one float so the chunked iteration also works at degree 0.
    let row = rest_w.max(1);
    let mut sh_rest = vec![0.0; row * n];
    let raw = sh_rest
        .par_chunks_mut(row)
        .enumerate()
        .map(|(i, rest)| {
            projected[i]
                .as_ref()
                .filter(|_| wanted.is_none_or(|w| w[i]))
                .map(|p| project_one_backward(gs, i, cam, sh_degree, p, &grads[i], &mut rest[..rest_w]))
        })
        .collect();
    sh_rest.truncate(rest_w * n);
    (raw, sh_rest)
}
