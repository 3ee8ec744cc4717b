//! The end state scanned as the start state was: stage I's trainer on the
//! end-state views. A texture-independent judge of where a part's end pose puts
//! it: a part moved to its true end pose lands on the end scan's surface, a part
//! moved wrong lands off it (docs/training.md, "The end state as a second scan").
//! Photometric judgements cannot see a wrong piece on plain paint; geometry can.

use glam::Vec3;
use kiddo::{ImmutableKdTree, SquaredEuclidean};

use super::{NodeTracker, TrackedParts};
use crate::camera::Camera;
use crate::splat::GaussianSet;

/// Gaussians at this opacity or above are the scans' surface.
pub(super) const SURFACE_OPACITY: f32 = 0.5;
/// A part's Gaussian agrees with the end scan when it lies within this share
/// of the object's size of a surface Gaussian of the scan (the scans' own
/// error: a median of 6-9 mm on objects of about 1 m, measured).
pub(super) const REACH_SHARE: f32 = 0.02;
/// A point is judged only where at least this many end-state views have it in
/// frame: the scan knows nothing of what the end views never pointed at (a
/// capture's end state may be seen from a narrow arc), and a part's piece there
/// agrees with it nowhere.
const MIN_VIEWS: usize = 2;

/// The end scan's surface, for nearest-neighbour queries, and the views it was trained on.
#[derive(Clone, Debug)]
pub struct EndScan {
    tree: ImmutableKdTree<f32, 3>,
    /// The distance within which a point agrees with the surface (world units).
    reach: f32,
    pub(super) cameras: Vec<Camera>,
}

/// How start-state Gaussians moved by a part's end pose agree with the end scan:
/// the share of their surface Gaussians within reach of the scan's surface at
/// that pose and at rest.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EndScanAgreement {
    pub at_end_pose: f32,
    pub at_rest: f32,
}

impl EndScanAgreement {
    /// The end pose agrees with the end state no better than rest does: the part
    /// moved content to where the end state has none (or has other content), or
    /// left behind what the end state still shows in place.
    pub fn contradicts_end_pose(&self) -> bool {
        self.at_end_pose <= self.at_rest
    }
}

impl EndScan {
    /// The surface of `scan` (an end-state 3DGS trained on views from `cameras`),
    /// `object_size` the start state's size; None when it has no surface Gaussian.
    pub fn new(scan: &GaussianSet, object_size: f32, cameras: &[Camera]) -> Option<Self> {
        let surface: Vec<[f32; 3]> =
            (0..scan.len()).filter(|&i| scan.opacity(i) >= SURFACE_OPACITY).map(|i| scan.mean(i).to_array()).collect();
        if surface.is_empty() {
            return None;
        }
        let tree = ImmutableKdTree::new_from_slice(&surface);
        Some(Self { tree, reach: REACH_SHARE * object_size, cameras: cameras.to_vec() })
    }

    /// Whether at least `MIN_VIEWS` of the scan's views have `p` in frame.
    pub(super) fn in_view(&self, p: Vec3) -> bool {
        self.cameras.iter().filter(|c| c.pixel_of(p).is_some()).take(MIN_VIEWS).count() >= MIN_VIEWS
    }

    /// Whether `p` lies within reach of the scan's surface.
    pub(super) fn is_near(&self, p: Vec3) -> bool {
        self.tree.nearest_one::<SquaredEuclidean>(&p.to_array()).distance <= self.reach * self.reach
    }

    /// The share of those of `points` the views see that lie within reach of the
    /// surface; None when the views see none of them.
    fn share_near(&self, points: impl Iterator<Item = Vec3>) -> Option<f32> {
        let (mut seen, mut near) = (0usize, 0usize);
        for p in points.filter(|&p| self.in_view(p)) {
            seen += 1;
            near += usize::from(self.is_near(p));
        }
        (seen > 0).then(|| near as f32 / seen as f32)
    }
}

impl NodeTracker {
    /// How the Gaussians of `nodes` agree with the end scan moved by part `p`'s
    /// end pose in `parts` (the last knot) and at rest; None without an end scan,
    /// when they have no surface Gaussian, when the pose moves their surface by
    /// less than the reach at the median (then the scan cannot tell the two poses
    /// apart), or when the scan's views see none of it at one of the two poses.
    pub(super) fn end_scan_agreement(
        &self,
        parts: &TrackedParts,
        p: usize,
        nodes: &[usize],
    ) -> Option<EndScanAgreement> {
        let scan = self.end_scan.as_ref()?;
        let mut member = vec![false; self.node_centres.len()];
        nodes.iter().for_each(|&k| member[k] = true);
        let surface: Vec<Vec3> = (0..self.binding.len())
            .filter(|&i| member[self.binding[i] as usize] && self.gaussians.opacity(i) >= SURFACE_OPACITY)
            .map(|i| self.gaussians.mean(i))
            .collect();
        if surface.is_empty() {
            return None;
        }
        let (c, pose) = (parts.centres[p], parts.poses[parts.poses.len() - 1][p]);
        let moved: Vec<Vec3> = surface.iter().map(|&x| pose.apply(c, x)).collect();
        let mut shift: Vec<f32> = surface.iter().zip(&moved).map(|(a, b)| a.distance(*b)).collect();
        shift.sort_by(f32::total_cmp);
        if shift[shift.len() / 2] < scan.reach {
            return None;
        }
        Some(EndScanAgreement {
            at_end_pose: scan.share_near(moved.into_iter())?,
            at_rest: scan.share_near(surface.into_iter())?,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Intrinsics;
    use crate::splat::logit;

    /// A unit square of surface points in the plane z = `z`, 1 cm apart.
    fn plate(z: f32) -> GaussianSet {
        let mut g = GaussianSet::new(0);
        for i in 0..100 {
            for j in 0..100 {
                let mean = Vec3::new(i as f32 * 0.01, j as f32 * 0.01, z);
                g.push(mean, Vec3::splat(-5.0), [1.0, 0.0, 0.0, 0.0], logit(0.9), [0.0; 3], &[]);
            }
        }
        g
    }

    /// Two cameras 2 m above (`x`, 0.5, 0), looking down with a `fov` (radians) wide view.
    fn cameras_over(x: f32, fov: f32) -> Vec<Camera> {
        let k = Intrinsics::from_fov_x(64, 64, fov);
        [-0.05f32, 0.05]
            .iter()
            .map(|dx| Camera::look_at(k, Vec3::new(x + dx, 0.5, 2.0), Vec3::new(x, 0.5, 0.0), Vec3::Y))
            .collect()
    }

    #[test]
    fn points_on_the_scan_agree_and_points_off_it_do_not() {
        let scan = EndScan::new(&plate(0.0), 1.0, &cameras_over(0.5, 1.2)).expect("a surface");
        let on = (0..10).map(|i| Vec3::new(0.1 * i as f32, 0.5, 0.01));
        let off = (0..10).map(|i| Vec3::new(0.1 * i as f32, 0.5, 0.05));
        assert_eq!(scan.share_near(on), Some(1.0));
        assert_eq!(scan.share_near(off), Some(0.0));
        let half = (0..10).map(|i| Vec3::new(0.1 * i as f32, 0.5, if i < 5 { 0.0 } else { 0.3 }));
        assert_eq!(scan.share_near(half), Some(0.5));
    }

    #[test]
    fn only_what_the_views_saw_is_judged() {
        // Narrow views over the plate's left edge: its right half was never in frame.
        let scan = EndScan::new(&plate(0.0), 1.0, &cameras_over(0.1, 0.3)).expect("a surface");
        let unseen = (0..10).map(|i| Vec3::new(0.9, 0.05 + 0.1 * i as f32, 0.3));
        assert_eq!(scan.share_near(unseen), None);
        let seen_and_unseen = [Vec3::new(0.1, 0.5, 0.0), Vec3::new(0.1, 0.5, 0.3), Vec3::new(0.9, 0.5, 0.3)];
        assert_eq!(scan.share_near(seen_and_unseen.into_iter()), Some(0.5));
    }

    #[test]
    fn a_scan_with_no_surface_is_none() {
        let mut faint = GaussianSet::new(0);
        faint.push(Vec3::ZERO, Vec3::splat(-5.0), [1.0, 0.0, 0.0, 0.0], logit(0.1), [0.0; 3], &[]);
        assert!(EndScan::new(&faint, 1.0, &cameras_over(0.0, 1.0)).is_none());
    }
}
