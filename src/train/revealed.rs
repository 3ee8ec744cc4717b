//! Content the start state never saw (a fridge's inside, a drawer's body): a
//! static set of Gaussians seeded in the start state's hidden volume, trained on
//! colour and opacity alongside the node tracking.
//!
//! Without it the tracker prefers the wrong motion: where the opened door
//! reveals the inside, the start state renders the background, and a door that
//! lags behind its true pose covers that hole with something closer in colour,
//! so the photometric loss is lower there than at the true pose (measured on the
//! fridge: lower at every time up to t = 0.4). Seeded only where every scan view
//! sees the start surface in front, these Gaussians are invisible in the start
//! state and cannot take over a moving part's appearance outside the object; once
//! revealed, they learn what is there, and the true motion is the best fit again.

use glam::Vec3;
use rand::Rng;
use serde::{Deserialize, Serialize};

use super::optim::{Adam, LearningRates};
use crate::camera::Camera;
use crate::render::{render, RenderOptions};
use crate::splat::{logit, GaussianSet};

/// Candidate points drawn per kept Gaussian (most of a box is seen free or lies outside).
const CANDIDATES_PER_GAUSSIAN: usize = 16;
/// Coverage above which a scan pixel counts as showing the start surface.
const SURFACE_ALPHA: f32 = 0.5;
/// A point this far (times the object size) behind a view's surface counts as hidden
/// from that view (stage I's depth on textureless walls spreads by a few centimetres).
pub const HIDDEN_MARGIN: f32 = 0.03;
/// Starting opacity: faint, so what is revealed is first seen through.
const START_OPACITY: f32 = 0.1;
/// Adam steps of the trained groups (3DGS's colour and opacity rates).
const LR_COLOUR: f32 = 0.0025;
const LR_OPACITY: f32 = 0.05;

/// The revealed-content set and its optimizer state.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct RevealedContent {
    pub gaussians: GaussianSet,
    adam: Adam,
}

impl RevealedContent {
    /// Up to `count` Gaussians in the volume that every scan camera sees behind the
    /// start state's surface (`start` rendered from `scan`), within the start state's
    /// bounds of size `size`. None seen hidden gives an empty set.
    pub fn seed(start: &GaussianSet, scan: &[Camera], count: usize, size: f32, seed: u64) -> Self {
        let mut gaussians = GaussianSet::new(start.sh_degree);
        if count > 0 && !start.is_empty() && !scan.is_empty() {
            let (lo, hi) = bounds(start);
            let mut rng = super::static_stage::rng_for(seed, STREAM_REVEALED, 0);
            let candidates: Vec<Vec3> = (0..count * CANDIDATES_PER_GAUSSIAN)
                .map(|_| lo + (hi - lo) * Vec3::new(rng.random(), rng.random(), rng.random()))
                .collect();
            let kept: Vec<Vec3> = hidden_behind_surface(start, scan, &candidates, HIDDEN_MARGIN * size)
                .into_iter()
                .zip(&candidates)
                .filter(|(h, _)| *h)
                .map(|(_, p)| *p)
                .take(count)
                .collect();
            // Spheres that together about fill the hidden volume.
            let volume = (hi - lo).x * (hi - lo).y * (hi - lo).z;
            let radius = 0.5 * (volume * kept.len() as f32 / candidates.len() as f32 / kept.len().max(1) as f32).cbrt();
            let rest = vec![0.0; gaussians.width(crate::splat::ParamGroup::ShRest)];
            for p in kept {
                gaussians.push(
                    p,
                    Vec3::splat(radius.max(1e-4).ln()),
                    [1.0, 0.0, 0.0, 0.0],
                    logit(START_OPACITY),
                    [0.0; 3],
                    &rest,
                );
            }
        }
        let adam = Adam::new(&gaussians);
        Self { gaussians, adam }
    }

    pub fn len(&self) -> usize {
        self.gaussians.len()
    }

    pub fn is_empty(&self) -> bool {
        self.gaussians.is_empty()
    }

    /// `moving` with the revealed content appended (rendered together: the
    /// revealed Gaussians are the rows after `moving.len()`).
    pub fn with(&self, mut moving: GaussianSet) -> GaussianSet {
        moving.extend_from(&self.gaussians);
        moving
    }

    /// One Adam step on colour and opacity; `grads` holds the revealed rows' gradients.
    pub fn step(&mut self, grads: &GaussianSet) {
        let lrs = LearningRates {
            means: 0.0,
            log_scales: 0.0,
            rotations: 0.0,
            opacity_logits: LR_OPACITY,
            sh_dc: LR_COLOUR,
            sh_rest: 0.0,
        };
        self.adam.step(&mut self.gaussians, grads, &lrs);
    }
}

/// Random stream of the candidate points.
const STREAM_REVEALED: u64 = 23;

/// Per point of `points`: whether some camera of `cameras` has it in frame and
/// every one that does sees the surface of `set` at least `margin` in front of
/// it (a scan of `set` from those cameras could not have shown it).
pub fn hidden_behind_surface(set: &GaussianSet, cameras: &[Camera], points: &[Vec3], margin: f32) -> Vec<bool> {
    let mut hidden = vec![true; points.len()];
    let mut seen = vec![false; points.len()];
    for camera in cameras {
        let r = render(set, camera, &RenderOptions::uniform(Vec3::ZERO));
        for (k, p) in points.iter().enumerate() {
            let Some((pixel, z)) = camera.pixel_of(*p) else { continue };
            let alpha = r.image.alpha[pixel];
            seen[k] = true;
            if alpha < SURFACE_ALPHA || z < r.image.depth[pixel] / alpha + margin {
                hidden[k] = false;
            }
        }
    }
    hidden.iter().zip(&seen).map(|(h, s)| *h && *s).collect()
}

fn bounds(g: &GaussianSet) -> (Vec3, Vec3) {
    (0..g.len()).fold((Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)), |(lo, hi), i| {
        (lo.min(g.mean(i)), hi.max(g.mean(i)))
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Intrinsics;
    use crate::mesh::tsdf::sphere_directions;

    /// A closed spherical shell seen from all around: its inside is the hidden
    /// volume, so every seeded Gaussian lies inside the shell, and the box corners
    /// outside it (seen free) get none.
    #[test]
    fn seeds_only_inside_a_closed_shell() {
        let r = 0.25;
        let mut shell = GaussianSet::new(0);
        let n = 6000;
        let spacing = (4.0 * std::f32::consts::PI * r * r / n as f32).sqrt();
        for d in sphere_directions(n) {
            let q = glam::Quat::from_rotation_arc(Vec3::Z, d);
            let log_scale = Vec3::new(spacing, spacing, 0.001).map(f32::ln);
            shell.push(d * r, log_scale, [q.w, q.x, q.y, q.z], logit(0.95), [0.0; 3], &[]);
        }
        let k = Intrinsics::from_fov_x(96, 96, 50f32.to_radians());
        let scan: Vec<Camera> = sphere_directions(24)
            .into_iter()
            .map(|d| Camera::look_at(k, d * 1.2, Vec3::ZERO, if d.z.abs() > 0.95 { Vec3::X } else { Vec3::Z }))
            .collect();
        let revealed = RevealedContent::seed(&shell, &scan, 800, 2.0 * r, 3);
        assert!(revealed.len() > 400, "only {} seeded", revealed.len());
        let deepest_allowed = r - HIDDEN_MARGIN * 2.0 * r * 0.5;
        for i in 0..revealed.len() {
            let p = revealed.gaussians.mean(i);
            assert!(p.length() < deepest_allowed, "seeded at radius {} (shell {r})", p.length());
        }
        // Nothing seeded without views (nothing is known to be hidden).
        assert!(RevealedContent::seed(&shell, &[], 800, 2.0 * r, 3).is_empty());
    }
}
