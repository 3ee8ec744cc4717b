//! Gaussians a part left in the base. A node binds the Gaussians nearest it,
//! and one that straddles a door's edge and the body the door closes against
//! binds both and stays with the body: the door's edge then stands where the
//! door was closed, a ghost strip in the twin's body (the fridge's door left
//! a fifth of its Gaussians in the base, most along its free edge;
//! docs/training.md, "Gaussians a part left behind"). The end scan tells them
//! apart one by one: the end state shows a moved Gaussian's place empty, and
//! the part's end pose puts it on the end state's surface.

use glam::Vec3;
use kiddo::{ImmutableKdTree, SquaredEuclidean};

use super::end_scan::REACH_SHARE;
use super::NodeTracker;
use crate::camera::Camera;
use crate::splat::GaussianSet;
use crate::train::revealed::{hidden_behind_surface, HIDDEN_MARGIN};

/// A base Gaussian is weighed for a part within this many end-scan reaches of
/// the part's Gaussians at rest (a part grows across the strip it left, not
/// onto content far from it that its pose happens to put on the scan) ...
const NEIGHBOURHOOD_REACHES: f32 = 2.0;
/// ... in rounds, each from the part as the last round left it.
const MAX_ROUNDS: usize = 64;

impl NodeTracker {
    /// Binds to the parts the Gaussians of base nodes that moved with them. A
    /// base Gaussian within `NEIGHBOURHOOD_REACHES` end-scan reaches of a part's
    /// Gaussians (at rest) goes with that part when the end state shows its
    /// place empty (in view of the end scan's cameras `cameras`, off the scan's
    /// surface, and seen by one of them with no surface of `scan` in front) and
    /// the part's end pose puts it on the scan's surface; it is bound to the
    /// part's node nearest it. Rounds until none is given. Needs the end scan
    /// (`end_scan`, of `scan`). Returns how many were given.
    pub fn give_parts_what_moved_with_them(&mut self, scan: &GaussianSet, cameras: &[Camera]) -> usize {
        let (Some(parts), Some(end_scan)) = (self.articulation.as_ref(), self.end_scan.as_ref()) else {
            return 0;
        };
        if parts.centres.is_empty() || cameras.is_empty() {
            return 0;
        }
        let last = parts.poses.len() - 1;
        let means: Vec<Vec3> = (0..self.binding.len()).map(|i| self.gaussians.mean(i)).collect();
        let label = |binding: &[u32], i: usize| parts.node_part[binding[i] as usize];
        let base: Vec<usize> = (0..means.len()).filter(|&i| label(&self.binding, i) == 0).collect();
        let places: Vec<Vec3> = base.iter().map(|&i| means[i]).collect();
        let hidden = hidden_behind_surface(scan, cameras, &places, HIDDEN_MARGIN * self.object_size);
        let empty_at_end: Vec<usize> = base
            .iter()
            .zip(&hidden)
            .filter(|&(&i, &h)| !h && end_scan.in_view(means[i]) && !end_scan.is_near(means[i]))
            .map(|(&i, _)| i)
            .collect();
        let radius2 = (NEIGHBOURHOOD_REACHES * REACH_SHARE * self.object_size).powi(2);
        let mut binding = self.binding.clone();
        let mut given = vec![0usize; parts.centres.len()];
        for _ in 0..MAX_ROUNDS {
            let before: usize = given.iter().sum();
            for (p, count) in given.iter_mut().enumerate() {
                let members: Vec<[f32; 3]> =
                    (0..means.len()).filter(|&i| label(&binding, i) == p + 1).map(|i| means[i].to_array()).collect();
                let nodes = parts.nodes_labelled(p + 1);
                if members.is_empty() || nodes.is_empty() {
                    continue;
                }
                let part_tree = ImmutableKdTree::new_from_slice(&members);
                let node_points: Vec<[f32; 3]> = nodes.iter().map(|&k| self.node_centres[k].to_array()).collect();
                let node_tree = ImmutableKdTree::new_from_slice(&node_points);
                let (c, pose) = (parts.centres[p], parts.poses[last][p]);
                for &i in &empty_at_end {
                    let x = means[i].to_array();
                    if label(&binding, i) == 0
                        && part_tree.nearest_one::<SquaredEuclidean>(&x).distance <= radius2
                        && end_scan.is_near(pose.apply(c, means[i]))
                    {
                        binding[i] = nodes[node_tree.nearest_one::<SquaredEuclidean>(&x).item as usize] as u32;
                        *count += 1;
                    }
                }
            }
            if given.iter().sum::<usize>() == before {
                break;
            }
        }
        let total = given.iter().sum();
        if total > 0 {
            tracing::info!(
                per_part = ?given,
                "stage II: base Gaussians whose place the end state shows empty and that the part's end pose puts on its surface, given to the part"
            );
            self.binding = binding;
        }
        total
    }
}

#[cfg(test)]
mod tests {
    use std::f32::consts::FRAC_PI_2;

    use glam::Vec3;

    use super::super::end_state::tests::{panels, parts_at, turn_about, views_of, Door};
    use super::super::{EndScan, NodeTracker};
    use crate::splat::GaussianSet;

    /// A plate from x = -0.5 to 0.5 whose stretch x in (0, `door_to`] truly
    /// turned a quarter about the y axis through x = 0, scanned at the end
    /// from 16 views; the tracker holds as part 1 the nodes with x in (0, 0.3],
    /// at that end pose. Returns the tracker, the end scan (the truth) and its cameras.
    fn door_held_up_to_x_0_3(door_to: f32) -> (NodeTracker, GaussianSet, Vec<crate::camera::Camera>) {
        let door = Door { from: 0.0, to: door_to, hinge: 0.0, angle: -FRAC_PI_2 };
        let (mut tracker, _, end) = panels(-0.5, 0.5, 1200, 64, &[door], 1.0);
        let cameras: Vec<_> = views_of(&end, 1.0, 16).iter().map(|v| v.camera).collect();
        tracker.end_scan = EndScan::new(&end, tracker.object_size, &cameras);
        let held: Vec<usize> = tracker.node_centres.iter().map(|c| usize::from(c.x > 0.0 && c.x <= 0.3)).collect();
        let c = tracker.labelled_centroid(&held, 1);
        let parts = parts_at(&tracker, &held, &[turn_about(-FRAC_PI_2, Vec3::ZERO, c)]);
        tracker.set_articulation(parts);
        (tracker, end, cameras)
    }

    /// Each Gaussian's part (0 = base) by its node.
    fn labels(tracker: &NodeTracker) -> Vec<usize> {
        let node_part = &tracker.articulation.as_ref().expect("parts").node_part;
        tracker.binding.iter().map(|&k| node_part[k as usize]).collect()
    }

    #[test]
    fn a_door_held_short_of_its_edge_gets_the_edge_and_the_base_stays() {
        let (mut tracker, end, cameras) = door_held_up_to_x_0_3(0.5);
        let before = labels(&tracker);
        // What truly moved: the door's Gaussians (by their nodes, as `panels` cuts it).
        let moved: Vec<bool> = (0..end.len()).map(|i| end.mean(i).distance(tracker.gaussians.mean(i)) > 1e-6).collect();
        let strip: Vec<usize> = (0..moved.len()).filter(|&i| before[i] == 0 && moved[i]).collect();
        assert!(strip.len() >= 100, "the door's Gaussians left in the base: {}", strip.len());
        let given = tracker.give_parts_what_moved_with_them(&end, &cameras);
        let after = labels(&tracker);
        let joined = strip.iter().filter(|&&i| after[i] == 1).count();
        assert!(joined as f32 >= 0.9 * strip.len() as f32, "{joined} of the strip's {} Gaussians given", strip.len());
        assert!((0..moved.len()).filter(|&i| !moved[i]).all(|i| after[i] == 0), "the base plate stays in the base");
        assert!((0..moved.len()).all(|i| before[i] == 0 || after[i] == before[i]), "the part keeps its own");
        assert_eq!(given, after.iter().filter(|&&l| l == 1).count() - before.iter().filter(|&&l| l == 1).count());
    }

    #[test]
    fn the_plate_beyond_a_door_that_ends_where_the_part_does_stays_in_the_base() {
        // The door is only x in (0, 0.3]: the plate beyond it never moved, and
        // the end state shows it in place.
        let (mut tracker, end, cameras) = door_held_up_to_x_0_3(0.3);
        assert_eq!(tracker.give_parts_what_moved_with_them(&end, &cameras), 0);
    }
}
