//! Content a moving part carries that the start state never saw: a closed
//! drawer's inside, a door's inner face. The start state holds only what the
//! scan saw, so an opened drawer's inside is explained by nothing of its own,
//! and a look-alike part moved onto it (a lower drawer slid up into the open
//! upper one) explains it better than that part's true, hidden, end pose
//! (docs/training.md, "The lower drawer slid shut"). The end scan has seen it: its
//! Gaussians where a part swept, that nothing in the twin explains and that
//! the part's own path brings out of the start state's hidden volume, are
//! bound to that part, at rest where they were hidden. Only with
//! `track.carry_content` (off by default: it finds that drawer and costs
//! storage_complex two doors).

use glam::{Quat, Vec3};
use kiddo::{ImmutableKdTree, SquaredEuclidean};

use super::end_scan::{REACH_SHARE, SURFACE_OPACITY};
use super::NodeTracker;
use crate::camera::Camera;
use crate::splat::{GaussianSet, ParamGroup};
use crate::train::revealed::{hidden_behind_surface, HIDDEN_MARGIN};

/// Poses sampled along a part's path per fitted segment: the path of a point
/// between two samples stays within the reach on the benchmark's fastest parts
/// (a 0.5 m door turning 110 degrees over 30 segments moves its edge 3 cm a
/// segment).
const SAMPLES_PER_SEGMENT: usize = 4;

impl NodeTracker {
    /// Binds to the tracked parts the surface Gaussians of the end scan `scan`
    /// that (a) lie farther than the end scan's reach from every surface
    /// Gaussian of the base and of the part at its end pose (not of the other
    /// parts: a look-alike's wrong end pose may cover them), (b) the part's
    /// Gaussians came within that reach of on their path from rest to the end,
    /// and (c) the part's end pose, undone, puts where every camera of the start
    /// state's scan (`start_cameras`) that has them in frame sees the start
    /// surface in front.
    /// Each is bound to the part's node nearest it at the end, moved back to
    /// rest by that node's end pose. Returns how many were bound.
    pub fn carry_swept_content(&mut self, scan: &GaussianSet, start_cameras: &[Camera]) -> usize {
        let Some(parts) = self.articulation.as_ref() else { return 0 };
        if scan.is_empty() || start_cameras.is_empty() || parts.centres.is_empty() {
            return 0;
        }
        let reach = REACH_SHARE * self.object_size;
        let reach2 = reach * reach;
        let last = self.knots.len() - 1;
        let end_poses = &self.knots[last];
        let at_end = self.deformed(end_poses, &self.gains[last]);
        let label = |i: usize| parts.node_part[self.binding[i] as usize];
        let surface_tree = |label_wanted: usize| {
            let points: Vec<[f32; 3]> = (0..at_end.len())
                .filter(|&i| label(i) == label_wanted && at_end.opacity(i) >= SURFACE_OPACITY)
                .map(|i| at_end.mean(i).to_array())
                .collect();
            (!points.is_empty()).then(|| ImmutableKdTree::new_from_slice(&points))
        };
        let near = |tree: &Option<ImmutableKdTree<f32, 3>>, p: Vec3| {
            tree.as_ref().is_some_and(|t| t.nearest_one::<SquaredEuclidean>(&p.to_array()).distance <= reach2)
        };
        // (a) the end scan's surface the base does not explain.
        let base = surface_tree(0);
        let mut unexplained: Vec<usize> =
            (0..scan.len()).filter(|&i| scan.opacity(i) >= SURFACE_OPACITY && !near(&base, scan.mean(i))).collect();
        let samples = SAMPLES_PER_SEGMENT * last;
        // Per part, the rows it swept (b) and its own end surface does not explain, each with its node.
        let mut claims: Vec<(usize, usize)> = Vec::new();
        for p in 1..=parts.centres.len() {
            let nodes = parts.nodes_labelled(p);
            let rows: Vec<usize> = (0..self.binding.len()).filter(|&i| label(i) == p).collect();
            if nodes.is_empty() || rows.is_empty() || unexplained.is_empty() {
                continue;
            }
            let own = surface_tree(p);
            let mut swept = vec![false; unexplained.len()];
            for k in 1..=samples {
                let t = k as f32 / samples as f32;
                let moved = self.deformed_rows(&rows, &self.poses_at(t), &self.gains_at(t));
                let points: Vec<[f32; 3]> = (0..moved.len()).map(|i| moved.mean(i).to_array()).collect();
                let tree = Some(ImmutableKdTree::new_from_slice(&points));
                for (s, &i) in swept.iter_mut().zip(&unexplained) {
                    *s = *s || near(&tree, scan.mean(i));
                }
            }
            // Each swept row goes with the part's node nearest it at the end.
            let node_ends: Vec<[f32; 3]> = nodes
                .iter()
                .map(|&k| end_poses[k].apply(self.node_centres[k], self.node_centres[k]).to_array())
                .collect();
            let node_tree = ImmutableKdTree::new_from_slice(&node_ends);
            let mut left = Vec::with_capacity(unexplained.len());
            for (&i, s) in unexplained.iter().zip(&swept) {
                if *s && !near(&own, scan.mean(i)) {
                    let nearest = node_tree.nearest_one::<SquaredEuclidean>(&scan.mean(i).to_array()).item as usize;
                    claims.push((i, nodes[nearest]));
                } else {
                    left.push(i);
                }
            }
            unexplained = left;
        }
        // (c) where the claimed content was at rest: hidden from the start state's scan.
        let at_rest: Vec<Vec3> = claims
            .iter()
            .map(|&(i, k)| {
                let (c, pose) = (self.node_centres[k], end_poses[k]);
                pose.rotation.inverse() * (scan.mean(i) - c - pose.translation) + c
            })
            .collect();
        let hidden = hidden_behind_surface(&self.gaussians, start_cameras, &at_rest, HIDDEN_MARGIN * self.object_size);
        let rest_width = self.gaussians.width(ParamGroup::ShRest);
        let scan_rest_width = scan.width(ParamGroup::ShRest);
        let mut per_part = vec![0usize; parts.centres.len()];
        for ((&(i, k), &x), _) in claims.iter().zip(&at_rest).zip(&hidden).filter(|(_, h)| **h) {
            let q: Quat = end_poses[k].rotation.inverse() * scan.rotation(i);
            // The view-dependent colour only where both sets keep the same bands.
            let rest = if rest_width == scan_rest_width {
                scan.sh_rest[i * rest_width..(i + 1) * rest_width].to_vec()
            } else {
                vec![0.0; rest_width]
            };
            let dc = [scan.sh_dc[3 * i], scan.sh_dc[3 * i + 1], scan.sh_dc[3 * i + 2]];
            self.gaussians.push(x, scan.log_scale(i), [q.w, q.x, q.y, q.z], scan.opacity_logits[i], dc, &rest);
            self.binding.push(k as u32);
            per_part[parts.node_part[k] - 1] += 1;
        }
        tracing::info!(
            claimed = claims.len(),
            per_part = ?per_part,
            "stage II: end-scan content the parts swept and the start state hid, carried by them"
        );
        per_part.iter().sum()
    }
}

#[cfg(test)]
pub(super) mod tests {
    use glam::{Quat, Vec3};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    use super::super::{NodePose, NodeTracker, TrackedParts};
    use crate::camera::{Camera, Intrinsics};
    use crate::splat::{logit, GaussianSet};
    use crate::train::dynamic_stage::DynamicConfig;

    /// Flat Gaussians on a grid over the rectangle `from + a u + b v` (a, b in
    /// [0, 1]), `step` apart, each of a random colour from `rng`.
    pub(in crate::train::track) fn face(
        g: &mut GaussianSet,
        from: Vec3,
        u: Vec3,
        v: Vec3,
        step: f32,
        rng: &mut ChaCha8Rng,
    ) {
        let (nu, nv) = ((u.length() / step).round() as usize, (v.length() / step).round() as usize);
        let normal = u.cross(v).normalize();
        let rotation = Quat::from_rotation_arc(Vec3::Z, normal);
        for i in 0..=nu {
            for j in 0..=nv {
                let mean = from + u * (i as f32 / nu as f32) + v * (j as f32 / nv as f32);
                let log_scale = Vec3::new((0.7 * step).ln(), (0.7 * step).ln(), -7.0);
                let dc = [rng.random_range(-1.5..1.5), rng.random_range(-1.5..1.5), rng.random_range(-1.5..1.5)];
                g.push(mean, log_scale, [rotation.w, rotation.x, rotation.y, rotation.z], logit(0.95), dc, &[]);
            }
        }
    }

    #[test]
    fn a_drawer_carries_the_inside_it_brought_out_of_hiding_and_nothing_else() {
        // A closed box 0.4 x 0.1 x 0.2 whose front face (y = 0) slides out 0.2
        // along -y over ten segments; the rest is the base.
        let step = 0.02;
        let rng = &mut ChaCha8Rng::seed_from_u64(7);
        let mut box_set = GaussianSet::new(0);
        let x0 = Vec3::new(-0.2, 0.0, -0.1);
        face(&mut box_set, x0, Vec3::X * 0.4, Vec3::Z * 0.2, step, rng); // front: the drawer
        face(&mut box_set, x0 + Vec3::Y * 0.1, Vec3::X * 0.4, Vec3::Z * 0.2, step, rng); // back
        face(&mut box_set, x0, Vec3::X * 0.4, Vec3::Y * 0.1, step, rng); // bottom
        face(&mut box_set, x0 + Vec3::Z * 0.2, Vec3::X * 0.4, Vec3::Y * 0.1, step, rng); // top
        face(&mut box_set, x0, Vec3::Y * 0.1, Vec3::Z * 0.2, step, rng); // left
        face(&mut box_set, x0 + Vec3::X * 0.4, Vec3::Y * 0.1, Vec3::Z * 0.2, step, rng); // right
        let mut config = DynamicConfig::cpu();
        config.track.nodes = box_set.len();
        config.track.gaussians_per_node = 1;
        config.track.knots = 11;
        let mut tracker = NodeTracker::new(config, &box_set, &[]).expect("tracker");
        let node_part: Vec<usize> = tracker.node_centres.iter().map(|c| usize::from(c.y.abs() < 1e-3)).collect();
        let front: Vec<Vec3> = tracker.node_centres.iter().copied().filter(|c| c.y.abs() < 1e-3).collect();
        let centre = front.iter().copied().sum::<Vec3>() / front.len() as f32;
        let slide =
            |k: usize| NodePose { rotation: Quat::IDENTITY, translation: Vec3::new(0.0, -0.02 * k as f32, 0.0) };
        let parts = TrackedParts {
            node_part: node_part.clone(),
            centres: vec![centre],
            poses: (0..=10).map(|k| vec![slide(k)]).collect(),
            found_on_end_state: Vec::new(),
        };
        let n = tracker.node_centres.len();
        tracker.knots = parts.poses.iter().map(|p| parts.node_poses(&tracker.node_centres, p)).collect();
        tracker.gains = vec![vec![0.0; n]; 11];
        tracker.articulation = Some(parts);
        // The end scan: the front where it ended, the drawer's inside, a point
        // on the base's top face, a point far beside the box.
        let mut scan = GaussianSet::new(0);
        face(&mut scan, x0 - Vec3::Y * 0.2, Vec3::X * 0.4, Vec3::Z * 0.2, step, rng);
        let inside: Vec<Vec3> = [-0.1f32, 0.0, 0.1].iter().map(|&x| Vec3::new(x, -0.15, 0.0)).collect();
        let out_behind: Vec<Vec3> = [-0.1f32, 0.0, 0.1].iter().map(|&x| Vec3::new(x, -0.05, 0.0)).collect();
        for p in inside.iter().chain(&out_behind).chain(&[Vec3::new(0.0, 0.06, 0.1), Vec3::new(0.6, -0.1, 0.0)]) {
            scan.push(*p, Vec3::splat(-5.0), [1.0, 0.0, 0.0, 0.0], logit(0.9), [0.2, -0.3, 0.4], &[]);
        }
        // The start state's scan: a ring about the box and one view from above.
        let k = Intrinsics { width: 64, height: 64, fx: 60.0, fy: 60.0, cx: 32.0, cy: 32.0 };
        let mut cameras: Vec<Camera> = (0..8)
            .map(|i| {
                let a = i as f32 * std::f32::consts::TAU / 8.0 + 0.2;
                Camera::look_at(k, Vec3::new(1.2 * a.cos(), 1.2 * a.sin(), 0.3), Vec3::ZERO, Vec3::NEG_Z)
            })
            .collect();
        cameras.push(Camera::look_at(k, Vec3::new(0.05, 0.1, 1.2), Vec3::ZERO, Vec3::Y));
        let before = tracker.gaussians.len();
        let bound = tracker.carry_swept_content(&scan, &cameras);
        // The inside the front swept and the box hid at rest is the drawer's; the
        // content its path swept that the box's back would not have hidden at
        // rest (0.05 behind it), the base's face and the point beside are not.
        assert_eq!(bound, 3, "bound {bound}");
        assert_eq!(tracker.gaussians.len(), before + 3);
        let end = tracker.deformed(&tracker.knots[10], &tracker.gains[10]);
        for (i, p) in inside.iter().enumerate() {
            let row = before + i;
            let node = tracker.binding[row] as usize;
            assert_eq!(node_part[node], 1, "the inside goes with the drawer's nodes");
            let at_rest = tracker.gaussians.mean(row);
            assert!(at_rest.distance(*p + Vec3::Y * 0.2) < 1e-4, "at rest {at_rest}, expected {}", *p + Vec3::Y * 0.2);
            // Deformed to the end, it is where the end scan saw it.
            assert!(end.mean(row).distance(*p) < 1e-4);
        }
    }
}
