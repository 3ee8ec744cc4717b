//! Gaussian sets: parameters stored raw, as the original 3DGS stores them, in
//! structure-of-arrays form with one flat `Vec<f32>` per parameter group so the
//! optimizer and density control treat every group the same way (rows of a
//! fixed width).

use glam::{Affine3A, Mat3, Quat, Vec3};

pub mod ply;
mod sh_rotation;

/// Number of SH coefficients per colour channel for a degree (0..=3).
pub const fn sh_coeffs(degree: u32) -> usize {
    ((degree + 1) * (degree + 1)) as usize
}

/// One parameter group; each has a fixed number of floats per Gaussian.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum ParamGroup {
    /// Mean xyz.
    Means,
    /// log of the per-axis standard deviations.
    LogScales,
    /// Quaternion w, x, y, z (normalised at use).
    Rotations,
    /// Opacity before the sigmoid.
    OpacityLogits,
    /// SH degree-0 coefficients, 3 per Gaussian (rgb).
    ShDc,
    /// Higher SH coefficients, (K-1)*3 per Gaussian, coefficient-major: `[k][rgb]`.
    ShRest,
}

impl ParamGroup {
    pub const ALL: [ParamGroup; 6] = [
        ParamGroup::Means,
        ParamGroup::LogScales,
        ParamGroup::Rotations,
        ParamGroup::OpacityLogits,
        ParamGroup::ShDc,
        ParamGroup::ShRest,
    ];
}

/// A set of 3D Gaussians with raw (pre-activation) parameters.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct GaussianSet {
    /// Highest SH degree stored (0..=3); `sh_rest` holds `(sh_coeffs(deg)-1)*3` per row.
    pub sh_degree: u32,
    pub means: Vec<f32>,
    pub log_scales: Vec<f32>,
    pub rotations: Vec<f32>,
    pub opacity_logits: Vec<f32>,
    pub sh_dc: Vec<f32>,
    pub sh_rest: Vec<f32>,
}

/// Colour `c` in [0, 1] to the SH DC coefficient that renders it (colour = C0*dc + 0.5).
pub fn rgb_to_sh_dc(c: f32) -> f32 {
    (c - 0.5) / crate::render::sh::SH_C0
}

pub fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

pub fn logit(p: f32) -> f32 {
    let p = p.clamp(1e-6, 1.0 - 1e-6);
    (p / (1.0 - p)).ln()
}

impl GaussianSet {
    pub fn new(sh_degree: u32) -> Self {
        Self { sh_degree, ..Default::default() }
    }

    pub fn len(&self) -> usize {
        self.opacity_logits.len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Floats per Gaussian in `group`.
    pub fn width(&self, group: ParamGroup) -> usize {
        match group {
            ParamGroup::Means | ParamGroup::LogScales | ParamGroup::ShDc => 3,
            ParamGroup::Rotations => 4,
            ParamGroup::OpacityLogits => 1,
            ParamGroup::ShRest => (sh_coeffs(self.sh_degree) - 1) * 3,
        }
    }

    pub fn group(&self, group: ParamGroup) -> &Vec<f32> {
        match group {
            ParamGroup::Means => &self.means,
            ParamGroup::LogScales => &self.log_scales,
            ParamGroup::Rotations => &self.rotations,
            ParamGroup::OpacityLogits => &self.opacity_logits,
            ParamGroup::ShDc => &self.sh_dc,
            ParamGroup::ShRest => &self.sh_rest,
        }
    }

    pub fn group_mut(&mut self, group: ParamGroup) -> &mut Vec<f32> {
        match group {
            ParamGroup::Means => &mut self.means,
            ParamGroup::LogScales => &mut self.log_scales,
            ParamGroup::Rotations => &mut self.rotations,
            ParamGroup::OpacityLogits => &mut self.opacity_logits,
            ParamGroup::ShDc => &mut self.sh_dc,
            ParamGroup::ShRest => &mut self.sh_rest,
        }
    }

    /// Append one Gaussian. `sh_rest` must have `width(ShRest)` entries.
    #[allow(clippy::too_many_arguments)]
    pub fn push(
        &mut self,
        mean: Vec3,
        log_scale: Vec3,
        rotation_wxyz: [f32; 4],
        opacity_logit: f32,
        sh_dc: [f32; 3],
        sh_rest: &[f32],
    ) {
        debug_assert_eq!(sh_rest.len(), self.width(ParamGroup::ShRest));
        self.means.extend_from_slice(&mean.to_array());
        self.log_scales.extend_from_slice(&log_scale.to_array());
        self.rotations.extend_from_slice(&rotation_wxyz);
        self.opacity_logits.push(opacity_logit);
        self.sh_dc.extend_from_slice(&sh_dc);
        self.sh_rest.extend_from_slice(sh_rest);
    }

    pub fn mean(&self, i: usize) -> Vec3 {
        Vec3::from_slice(&self.means[3 * i..3 * i + 3])
    }

    pub fn log_scale(&self, i: usize) -> Vec3 {
        Vec3::from_slice(&self.log_scales[3 * i..3 * i + 3])
    }

    /// Normalised rotation (identity for a degenerate quaternion).
    pub fn rotation(&self, i: usize) -> Quat {
        let r = &self.rotations[4 * i..4 * i + 4];
        let q = Quat::from_xyzw(r[1], r[2], r[3], r[0]);
        let n = q.length();
        if n > 1e-12 {
            q / n
        } else {
            Quat::IDENTITY
        }
    }

    pub fn opacity(&self, i: usize) -> f32 {
        sigmoid(self.opacity_logits[i])
    }

    /// Append every Gaussian of `other` (same SH degree).
    pub fn extend_from(&mut self, other: &GaussianSet) {
        assert_eq!(self.sh_degree, other.sh_degree, "SH degrees must match");
        for g in ParamGroup::ALL {
            self.group_mut(g).extend_from_slice(other.group(g));
        }
    }

    /// A copy of the rows where `keep[i]` is true.
    pub fn subset(&self, keep: &[bool]) -> GaussianSet {
        let mut out = self.clone();
        out.retain(keep);
        out
    }

    /// Rows `range` of this set's groups as a new set.
    pub fn rows(&self, range: std::ops::Range<usize>) -> GaussianSet {
        let mut out = GaussianSet::new(self.sh_degree);
        for g in ParamGroup::ALL {
            let w = self.width(g);
            *out.group_mut(g) = self.group(g)[range.start * w..range.end * w].to_vec();
        }
        out
    }

    /// Keep only the rows where `keep[i]` is true, in every group.
    pub fn retain(&mut self, keep: &[bool]) {
        assert_eq!(keep.len(), self.len());
        for g in ParamGroup::ALL {
            let w = self.width(g);
            retain_rows(self.group_mut(g), w, keep);
        }
    }

    /// The set moved by the rigid motion `m` (a rotation and a translation): means
    /// and orientations moved, view-dependent colour (SH) turned with them.
    pub fn transformed(&self, m: &Affine3A) -> GaussianSet {
        let mut g = self.clone();
        let r = Quat::from_mat3(&Mat3::from(m.matrix3)).normalize();
        for (mean, q) in g.means.chunks_exact_mut(3).zip(g.rotations.chunks_exact_mut(4)) {
            mean.copy_from_slice(&m.transform_point3(Vec3::from_slice(mean)).to_array());
            let turned = r * Quat::from_xyzw(q[1], q[2], q[3], q[0]);
            q.copy_from_slice(&[turned.w, turned.x, turned.y, turned.z]);
        }
        sh_rotation::rotate_sh_rest(&mut g.sh_rest, g.sh_degree, Mat3::from_quat(r));
        g
    }

    /// Check every value is finite; returns the first offending (group, gaussian index).
    pub fn first_non_finite(&self) -> Option<(ParamGroup, usize)> {
        ParamGroup::ALL.into_iter().find_map(|g| {
            let w = self.width(g).max(1);
            self.group(g).iter().position(|v| !v.is_finite()).map(|p| (g, p / w))
        })
    }

    /// Consistency of the group lengths.
    pub fn check_shapes(&self) -> Result<(), String> {
        let n = self.len();
        for g in ParamGroup::ALL {
            let want = n * self.width(g);
            if self.group(g).len() != want {
                return Err(format!("{g:?} has {} values, expected {want} for {n} Gaussians", self.group(g).len()));
            }
        }
        Ok(())
    }
}

/// Keep rows (of `width` floats) of a flat buffer where `keep` is true, in order.
pub fn retain_rows(buf: &mut Vec<f32>, width: usize, keep: &[bool]) {
    if width == 0 {
        return;
    }
    let mut write = 0;
    for (row, &k) in keep.iter().enumerate() {
        if k {
            if write != row {
                buf.copy_within(row * width..(row + 1) * width, write * width);
            }
            write += 1;
        }
    }
    buf.truncate(write * width);
}
