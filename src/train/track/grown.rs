//! Gaussians a part left in the base, and the body's a part took. A node binds
//! the Gaussians nearest it, and one that straddles a door's edge and the body
//! the door closes against binds both and goes with one of them: with the body,
//! the door's edge stands where the door was closed, a ghost strip in the
//! twin's body (the fridge's door left a fifth of its Gaussians in the base,
//! most along its free edge); with the door, a strip of the body swings out
//! with it (docs/training.md, "Gaussians a part left behind"). The end scan
//! tells them apart one by one: it shows a Gaussian's place empty where its
//! node put it at the end, and its surface where the other would have.

use glam::Vec3;
use kiddo::{ImmutableKdTree, SquaredEuclidean};

use super::end_scan::REACH_SHARE;
use super::NodeTracker;
use crate::splat::GaussianSet;
use crate::train::revealed::{hidden_behind_surface, HIDDEN_MARGIN};

/// A Gaussian is weighed for a part (or the base) within this many end-scan
/// reaches of its Gaussians at rest (a part grows across the strip it left,
/// not onto content far from it that its pose happens to put on the scan) ...
const NEIGHBOURHOOD_REACHES: f32 = 2.0;
/// ... in rounds, each from the part as the last round left it.
const MAX_ROUNDS: usize = 64;

impl NodeTracker {
    /// Moves Gaussians between the base and the parts on the end scan's
    /// evidence (`end_scan`, of `scan`, and the views it was trained on). Each
    /// Gaussian's place at the end (at rest for the base's, at its part's end
    /// pose for a part's) is seen empty when it is in view of those views, off
    /// the scan's surface, and one of them sees it with no surface of `scan` in
    /// front. A part's Gaussian whose place is seen empty and that lies on the
    /// scan's surface at rest goes to the base; then a base Gaussian whose
    /// place is seen empty and that the part's end pose puts on the scan's
    /// surface goes to that part. Either only within `NEIGHBOURHOOD_REACHES`
    /// end-scan reaches of the Gaussians it goes to, in rounds, bound to their
    /// node nearest it. Returns (given to the parts, taken back by the base).
    pub fn settle_gaussians_on_end_scan(&mut self, scan: &GaussianSet) -> (usize, usize) {
        let (Some(parts), Some(end_scan)) = (self.articulation.as_ref(), self.end_scan.as_ref()) else {
            return (0, 0);
        };
        if parts.centres.is_empty() {
            return (0, 0);
        }
        let last = parts.poses.len() - 1;
        let means: Vec<Vec3> = (0..self.binding.len()).map(|i| self.gaussians.mean(i)).collect();
        let label: Vec<usize> = self.binding.iter().map(|&k| parts.node_part[k as usize]).collect();
        let moved_by = |p: usize, x: Vec3| parts.poses[last][p].apply(parts.centres[p], x);
        let end_places: Vec<Vec3> =
            (0..means.len()).map(|i| if label[i] == 0 { means[i] } else { moved_by(label[i] - 1, means[i]) }).collect();
        let hidden = hidden_behind_surface(scan, &end_scan.cameras, &end_places, HIDDEN_MARGIN * self.object_size);
        let seen_empty: Vec<bool> = (0..means.len())
            .map(|i| !hidden[i] && end_scan.in_view(end_places[i]) && !end_scan.is_near(end_places[i]))
            .collect();
        let mut binding = self.binding.clone();
        let stayed: Vec<usize> =
            (0..means.len()).filter(|&i| label[i] > 0 && seen_empty[i] && end_scan.is_near(means[i])).collect();
        let taken = self.grow_label(&mut binding, 0, &stayed, |l| l > 0);
        let left: Vec<usize> = (0..means.len()).filter(|&i| label[i] == 0 && seen_empty[i]).collect();
        let mut given = vec![0usize; parts.centres.len()];
        for (p, count) in given.iter_mut().enumerate() {
            let went: Vec<usize> = left.iter().copied().filter(|&i| end_scan.is_near(moved_by(p, means[i]))).collect();
            *count = self.grow_label(&mut binding, p + 1, &went, |l| l == 0);
        }
        let given_total = given.iter().sum();
        if given_total + taken > 0 {
            tracing::info!(
                given = ?given,
                taken,
                "stage II: Gaussians whose place at the end the end state shows empty, where the other side would put them on its surface, moved between the base and the parts"
            );
            self.binding = binding;
        }
        (given_total, taken)
    }

    /// Binds to the nodes labelled `to` (0 = the base, p + 1 = part p) those of
    /// `candidates` whose label (by `binding`) is still one `from` accepts and
    /// that lie within `NEIGHBOURHOOD_REACHES` end-scan reaches (at rest) of a
    /// Gaussian labelled `to`, each to its node nearest it; in rounds, each from
    /// the label as the last left it. Returns how many were bound.
    fn grow_label(&self, binding: &mut [u32], to: usize, candidates: &[usize], from: impl Fn(usize) -> bool) -> usize {
        let node_part = &self.articulation.as_ref().expect("parts").node_part;
        let nodes: Vec<usize> = (0..node_part.len()).filter(|&k| node_part[k] == to).collect();
        if nodes.is_empty() || candidates.is_empty() {
            return 0;
        }
        let node_points: Vec<[f32; 3]> = nodes.iter().map(|&k| self.node_centres[k].to_array()).collect();
        let node_tree = ImmutableKdTree::new_from_slice(&node_points);
        let radius2 = (NEIGHBOURHOOD_REACHES * REACH_SHARE * self.object_size).powi(2);
        let mut bound = 0;
        for _ in 0..MAX_ROUNDS {
            let members: Vec<[f32; 3]> = (0..binding.len())
                .filter(|&i| node_part[binding[i] as usize] == to)
                .map(|i| self.gaussians.mean(i).to_array())
                .collect();
            if members.is_empty() {
                break;
            }
            let tree = ImmutableKdTree::new_from_slice(&members);
            let mut this_round = 0;
            for &i in candidates {
                let x = self.gaussians.mean(i).to_array();
                let now = node_part[binding[i] as usize];
                if now != to && from(now) && tree.nearest_one::<SquaredEuclidean>(&x).distance <= radius2 {
                    binding[i] = nodes[node_tree.nearest_one::<SquaredEuclidean>(&x).item as usize] as u32;
                    this_round += 1;
                }
            }
            bound += this_round;
            if this_round == 0 {
                break;
            }
        }
        bound
    }
}

#[cfg(test)]
mod tests {
    use std::f32::consts::FRAC_PI_2;

    use glam::{Quat, Vec3};

    use super::super::end_state::tests::{panels, parts_at, turn_about, views_of, Door};
    use super::super::{EndScan, NodeTracker};
    use crate::splat::GaussianSet;

    /// A plate from x = -0.5 to 0.5 whose stretch x in (0, `door_to`] truly
    /// turned a quarter about the y axis through x = 0, scanned at the end
    /// from 16 views; the tracker holds as part 1 the nodes with x in (0, 0.3],
    /// at that end pose. Returns the tracker and the end scan (the truth).
    fn door_held_up_to_x_0_3(door_to: f32) -> (NodeTracker, GaussianSet) {
        let door = Door { from: 0.0, to: door_to, hinge: 0.0, angle: -FRAC_PI_2 };
        let (mut tracker, _, end) = panels(-0.5, 0.5, 1200, 64, &[door], 1.0);
        let cameras: Vec<_> = views_of(&end, 1.0, 16).iter().map(|v| v.camera).collect();
        tracker.end_scan = EndScan::new(&end, tracker.object_size, &cameras);
        let held: Vec<usize> = tracker.node_centres.iter().map(|c| usize::from(c.x > 0.0 && c.x <= 0.3)).collect();
        let c = tracker.labelled_centroid(&held, 1);
        let parts = parts_at(&tracker, &held, &[turn_about(-FRAC_PI_2, Vec3::ZERO, c)]);
        tracker.set_articulation(parts);
        (tracker, end)
    }

    /// Each Gaussian's part (0 = base) by its node.
    fn labels(tracker: &NodeTracker) -> Vec<usize> {
        let node_part = &tracker.articulation.as_ref().expect("parts").node_part;
        tracker.binding.iter().map(|&k| node_part[k as usize]).collect()
    }

    #[test]
    fn a_door_held_short_of_its_edge_gets_the_edge_and_the_base_stays() {
        let (mut tracker, end) = door_held_up_to_x_0_3(0.5);
        let before = labels(&tracker);
        // What truly moved: the door's Gaussians (by their nodes, as `panels` cuts it).
        let moved: Vec<bool> = (0..end.len()).map(|i| end.mean(i).distance(tracker.gaussians.mean(i)) > 1e-6).collect();
        let strip: Vec<usize> = (0..moved.len()).filter(|&i| before[i] == 0 && moved[i]).collect();
        assert!(strip.len() >= 100, "the door's Gaussians left in the base: {}", strip.len());
        let (given, taken) = tracker.settle_gaussians_on_end_scan(&end);
        assert_eq!(taken, 0, "the part holds none of the base's");
        let after = labels(&tracker);
        let joined = strip.iter().filter(|&&i| after[i] == 1).count();
        assert!(joined as f32 >= 0.9 * strip.len() as f32, "{joined} of the strip's {} Gaussians given", strip.len());
        assert!((0..moved.len()).filter(|&i| !moved[i]).all(|i| after[i] == 0), "the base plate stays in the base");
        assert!((0..moved.len()).all(|i| before[i] == 0 || after[i] == before[i]), "the part keeps its own");
        assert_eq!(given, after.iter().filter(|&&l| l == 1).count() - before.iter().filter(|&&l| l == 1).count());
    }

    /// The plate cut at x = 0 Gaussian by Gaussian (not by node): the door, x in
    /// (0, 0.5], hinged at its far edge, truly turned a quarter, scanned at the
    /// end from 16 views; the tracker's part is the nodes whose centre lies
    /// beyond x = `part_from`, at the door's end pose. Returns the tracker, the
    /// end scan (the truth), which Gaussians are the door's, and the end scan's
    /// reach (within it of the cut, the scan cannot tell).
    fn door_cut_between_nodes(part_from: f32) -> (NodeTracker, GaussianSet, Vec<bool>, f32) {
        let (mut tracker, _, mut end) = panels(-0.5, 0.5, 1200, 64, &[], 1.0);
        let hinge = Vec3::new(0.5, 0.0, 0.0);
        let turn = Quat::from_rotation_y(FRAC_PI_2);
        let door: Vec<bool> = (0..end.len()).map(|i| end.mean(i).x > 0.0).collect();
        for i in (0..end.len()).filter(|&i| door[i]) {
            let m = turn * (end.mean(i) - hinge) + hinge;
            end.means[3 * i..3 * i + 3].copy_from_slice(&m.to_array());
        }
        let cameras: Vec<_> = views_of(&end, 1.0, 16).iter().map(|v| v.camera).collect();
        tracker.end_scan = EndScan::new(&end, tracker.object_size, &cameras);
        let held: Vec<usize> = tracker.node_centres.iter().map(|c| usize::from(c.x > part_from)).collect();
        let c = tracker.labelled_centroid(&held, 1);
        tracker.set_articulation(parts_at(&tracker, &held, &[turn_about(FRAC_PI_2, hinge, c)]));
        let reach = super::REACH_SHARE * tracker.object_size;
        (tracker, end, door, reach)
    }

    #[test]
    fn a_doors_free_edge_at_the_bodys_nodes_goes_with_the_door() {
        // The part stops short of the cut: the nodes there, the body's, hold the door's free edge (the fridge's).
        let (mut tracker, end, door, reach) = door_cut_between_nodes(0.08);
        let before = labels(&tracker);
        let x: Vec<f32> = (0..door.len()).map(|i| tracker.gaussians.mean(i).x).collect();
        let edge: Vec<usize> = (0..door.len()).filter(|&i| door[i] && before[i] == 0 && x[i] > reach).collect();
        assert!(edge.len() >= 30, "the door's Gaussians at the body's nodes: {}", edge.len());
        assert_eq!(tracker.settle_gaussians_on_end_scan(&end).1, 0, "none taken back");
        let after = labels(&tracker);
        assert!(edge.iter().all(|&i| after[i] == 1), "the door's edge given to the door");
        assert!((0..door.len()).filter(|&i| !door[i]).all(|i| after[i] == 0), "the body's Gaussians stay");
    }

    #[test]
    fn a_strip_of_the_body_a_door_took_goes_back_to_the_body() {
        // The part reaches past the cut: its nodes there hold a strip of the body.
        let (mut tracker, end, door, reach) = door_cut_between_nodes(-0.08);
        let before = labels(&tracker);
        let x: Vec<f32> = (0..door.len()).map(|i| tracker.gaussians.mean(i).x).collect();
        let strip: Vec<usize> = (0..door.len()).filter(|&i| !door[i] && before[i] == 1 && x[i] < -reach).collect();
        assert!(strip.len() >= 30, "the body's Gaussians at the door's nodes: {}", strip.len());
        assert_eq!(tracker.settle_gaussians_on_end_scan(&end).0, 0, "none given");
        let after = labels(&tracker);
        assert!(strip.iter().all(|&i| after[i] == 0), "the body's strip given back to the body");
        assert!((0..door.len()).filter(|&i| door[i]).all(|i| after[i] == 1), "the door's Gaussians stay");
    }

    #[test]
    fn the_plate_beyond_a_door_that_ends_where_the_part_does_stays_in_the_base() {
        // The door is only x in (0, 0.3]: the plate beyond it never moved, and
        // the end state shows it in place.
        let (mut tracker, end) = door_held_up_to_x_0_3(0.3);
        assert_eq!(tracker.settle_gaussians_on_end_scan(&end), (0, 0));
    }
}
