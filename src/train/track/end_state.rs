//! Parts the tracking missed, found on the end state.
//!
//! Free tracking groups nodes by their motion up to `discovery_time`, and a part
//! that has moved little by then, or that the first (grazing) frames lose, is
//! never grouped (docs/training.md). The end state, seen from around the object,
//! does not lag: start-state content that moved shows as residual where it was.
//! Base nodes whose Gaussians are visible and wrong in most end-state views are
//! grouped by the node graph into candidates; each candidate's end pose is
//! searched globally as a tracked part's is, and it becomes a part only when a
//! searched pose explains the end state clearly better than rest. Its path
//! between rest and that pose is then fitted along the same screw motion.

use glam::{DMat3, DQuat, Vec3};

use super::{evenly_spread, NodePose, NodeTracker, TrackedParts};
use crate::motion::Rigid;
use crate::render::render;
use crate::train::views::TrainView;

/// End-state views each candidate node's residual is measured on.
const VIEWS: usize = 16;
/// A node is a candidate when its median residual over the views that see it is
/// above this (mean absolute error per channel) ...
const MIN_RESIDUAL: f32 = 0.04;
/// ... and this many times the median over all seen base nodes.
const RESIDUAL_RATIO: f32 = 3.0;
/// Candidates searched per call, largest first (each search costs ~40 s).
const MAX_CANDIDATES: usize = 4;
/// Steps of the path fit between rest and the found end pose.
const PATH_STEPS: usize = 10;

impl NodeTracker {
    /// Look for parts among the base's nodes on `end_views` (time 1) and add
    /// those whose searched end pose explains the end state; returns how many
    /// were added or grown. Needs end-state views and the global search (`search_step`).
    /// `returned`: nodes of tracked parts dropped back to the base
    /// (`drop_parts_that_look_wrong`), left out of the base's residual statistics.
    /// Not when the hand held a part: one interaction moves the part the hand
    /// holds, and what else the end state shows differently is content the start
    /// state lacked (an oven's inside, measured: an 11-degree extra part).
    pub fn discover_on_end_state(&mut self, frames: &[TrainView], end_views: &[TrainView], returned: &[bool]) -> usize {
        if end_views.is_empty()
            || self.config.track.search_step <= 0.0
            || self.config.track.end_iterations == 0
            || self.held_part().is_some()
        {
            return 0;
        }
        let last = self.knots.len() - 1;
        let tracked = (self.articulation.clone(), self.knots.clone());
        let parts = self.articulation.clone().unwrap_or_else(|| TrackedParts {
            node_part: vec![0; self.node_centres.len()],
            centres: Vec::new(),
            poses: vec![Vec::new(); self.knots.len()],
        });
        self.set_articulation(parts);
        let views = evenly_spread(&end_views.iter().collect::<Vec<_>>(), VIEWS);
        // One candidate at a time, the residuals measured again after each: a
        // part found changes what the end state still shows unexplained.
        let mut tried = vec![false; self.node_centres.len()];
        let mut added = 0;
        for _ in 0..MAX_CANDIDATES {
            let mut trial = self.articulation.clone().expect("parts set above");
            let residual = self.node_residuals(&trial, 0, &views, false);
            let (groups, threshold) = self.candidate_groups(&trial, &residual, &tried, returned);
            let Some(nodes) = groups.into_iter().next() else {
                break;
            };
            nodes.iter().for_each(|&k| tried[k] = true);
            let p = trial.centres.len();
            nodes.iter().for_each(|&k| trial.node_part[k] = p + 1);
            trial.centres.push(self.labelled_centroid(&trial.node_part, p + 1));
            trial.poses.iter_mut().for_each(|k| k.push(NodePose::IDENTITY));
            let before = (self.articulation.clone(), self.knots[last].clone());
            self.set_articulation(trial);
            if self.search_part_end_pose(p, end_views, true)
                && self.looks_right_where_moved(p, nodes.len(), threshold, &views)
            {
                if let Some(q) = self.joins_a_part(p, &views) {
                    // A piece of a part already found (its edge, seen moved): no new part.
                    let mut parts = before.0.expect("parts set above");
                    nodes.iter().for_each(|&k| parts.node_part[k] = q + 1);
                    self.knots[last] = before.1;
                    self.set_articulation(parts);
                    tracing::info!(
                        part = q + 1,
                        nodes = nodes.len(),
                        "stage II: nodes found on the end state join a part"
                    );
                    added += 1;
                    continue;
                }
                self.fit_path(p, frames);
                tracing::info!(part = p + 1, nodes = nodes.len(), "stage II: a part found on the end state");
                added += 1;
            } else {
                let parts = before.0.expect("parts set above");
                self.knots[last] = before.1;
                self.set_articulation(parts);
            }
        }
        if added == 0 {
            // Nothing found: the free trajectories stay for stage III when no part was tracked.
            (self.articulation, self.knots) = tracked;
        }
        added
    }

    /// Per node labelled `label` (0 = base, p + 1 = part p), the median over
    /// `views` (at the last knot) of the mean residual (mean absolute error per
    /// channel, capped as the validation loss caps it) at the pixels where its
    /// Gaussians are the visible surface; NaN for other nodes and for nodes seen
    /// in fewer than two views. `relit`: each node's colours first scaled by the
    /// gain in [0.5, 2] that fits them best in that view (a panel turned towards
    /// or away from the light is itself, shaded differently).
    fn node_residuals(&self, parts: &TrackedParts, label: usize, views: &[&TrainView], relit: bool) -> Vec<f32> {
        let last = self.knots.len() - 1;
        let poses = parts.node_poses(&self.node_centres, &parts.poses[last]);
        let g = self.revealed.with(self.deformed(&poses, &self.gains[last]));
        let bg = Vec3::from(self.config.eval_background);
        let cap = self.config.track.validation_residual_cap;
        let tolerance = 0.02 * self.object_size;
        let n = self.node_centres.len();
        let mut seen: Vec<Vec<f32>> = vec![Vec::new(); n];
        for v in views {
            let r = render(&g, &v.camera, &v.render_options(bg));
            let target = v.target(bg);
            let depth = r.expected_depth();
            let w = r.width as usize;
            // The pixel where each of the node's Gaussians is the visible surface.
            let visible: Vec<(usize, usize)> = self
                .binding
                .iter()
                .enumerate()
                .filter(|(_, &k)| parts.node_part[k as usize] == label)
                .filter_map(|(i, &k)| {
                    let (x, y, z) = v.camera.project(g.mean(i))?;
                    if x < 0.0 || y < 0.0 || x >= w as f32 || y >= r.height as f32 {
                        return None;
                    }
                    let px = y as usize * w + x as usize;
                    // The surface within 2 % of the object or two pixels' width at that depth.
                    let tolerance = tolerance.max(2.0 * z / v.camera.intrinsics.fx);
                    (r.image.alpha[px] >= 0.5 && (depth[px] - z).abs() <= tolerance).then_some((k as usize, px))
                })
                .collect();
            let pixel = |px: usize| (&r.image.color[3 * px..3 * px + 3], &target[3 * px..3 * px + 3]);
            let mut gain = vec![1.0f32; n];
            if relit {
                let (mut xy, mut xx) = (vec![0.0f32; n], vec![0.0f32; n]);
                for &(k, px) in &visible {
                    let (a, b) = pixel(px);
                    (0..3).for_each(|c| {
                        xy[k] += a[c] * b[c];
                        xx[k] += a[c] * a[c];
                    });
                }
                (0..n).filter(|&k| xx[k] > 0.0).for_each(|k| gain[k] = (xy[k] / xx[k]).clamp(0.5, 2.0));
            }
            let (mut sum, mut count) = (vec![0.0f32; n], vec![0u32; n]);
            for &(k, px) in &visible {
                let (a, b) = pixel(px);
                let e = (0..3).map(|c| (gain[k] * a[c] - b[c]).abs()).sum::<f32>() / 3.0;
                sum[k] += e.min(cap);
                count[k] += 1;
            }
            for k in 0..n {
                if count[k] > 0 {
                    seen[k].push(sum[k] / count[k] as f32);
                }
            }
        }
        seen.into_iter()
            .map(|mut s| {
                if s.len() < 2 {
                    return f32::NAN;
                }
                s.sort_by(f32::total_cmp);
                s[s.len() / 2]
            })
            .collect()
    }

    /// Groups of base nodes (not `tried` before) whose residual is high, each of
    /// at least 1 % of the nodes, connected in the node graph, largest first.
    ///
    /// The threshold scales with the base's own residual, measured without the
    /// `returned` nodes: a wrong part dropped back to the base is still wrong
    /// there, and when it is large its residual is the base's median (scissors
    /// seed 2: 0.14, a threshold of 0.42 that no group passed).
    fn candidate_groups(
        &self,
        parts: &TrackedParts,
        residual: &[f32],
        tried: &[bool],
        returned: &[bool],
    ) -> (Vec<Vec<usize>>, f32) {
        let finite = |k: &usize| residual[*k].is_finite();
        let mut seen: Vec<f32> =
            (0..residual.len()).filter(finite).filter(|&k| !returned[k]).map(|k| residual[k]).collect();
        if seen.is_empty() {
            seen = (0..residual.len()).filter(finite).map(|k| residual[k]).collect();
        }
        if seen.is_empty() {
            return (Vec::new(), 0.0);
        }
        seen.sort_by(f32::total_cmp);
        let threshold = residual_threshold(&seen);
        let n = self.node_centres.len();
        let high: Vec<bool> = (0..n).map(|k| parts.node_part[k] == 0 && !tried[k] && residual[k] > threshold).collect();
        let mut graph = vec![Vec::new(); n];
        for &(a, b) in &self.edges {
            graph[a as usize].push(b as usize);
            graph[b as usize].push(a as usize);
        }
        let mut group = vec![usize::MAX; n];
        let mut groups: Vec<Vec<usize>> = Vec::new();
        for start in (0..n).filter(|&k| high[k]) {
            if group[start] != usize::MAX {
                continue;
            }
            let id = groups.len();
            let mut members = vec![start];
            group[start] = id;
            let mut i = 0;
            while i < members.len() {
                for &b in &graph[members[i]] {
                    if high[b] && group[b] == usize::MAX {
                        group[b] = id;
                        members.push(b);
                    }
                }
                i += 1;
            }
            groups.push(members);
        }
        let min_nodes = (n / 100).max(8);
        groups.retain(|g| g.len() >= min_nodes);
        groups.sort_by_key(|g| std::cmp::Reverse(g.len()));
        tracing::info!(
            seen = seen.len(),
            median = seen[seen.len() / 2],
            threshold,
            high = high.iter().filter(|h| **h).count(),
            groups = ?groups.iter().map(Vec::len).collect::<Vec<_>>(),
            "stage II: base nodes the end state shows moved"
        );
        (groups, threshold)
    }

    /// The part (other than the last, `p`) whose motion carries part `p`'s nodes
    /// to explain `views` as well as `p`'s own end pose does (within
    /// `merge_tolerance`), the best such; Occam's test on the end state, before
    /// `p` gets a path of its own.
    fn joins_a_part(&self, p: usize, views: &[&TrainView]) -> Option<usize> {
        let parts = self.articulation.as_ref().expect("the part searched");
        let own = self.articulated_loss(parts, &parts.node_part, views);
        (0..p)
            .map(|q| {
                let trial: Vec<usize> = parts.node_part.iter().map(|&l| if l == p + 1 { q + 1 } else { l }).collect();
                (q, self.articulated_loss(parts, &trial, views))
            })
            .filter(|(_, loss)| *loss <= own * (1.0 + self.config.track.merge_tolerance))
            .min_by(|a, b| a.1.total_cmp(&b.1))
            .map(|(q, _)| q)
    }

    /// Whether part `p` (found from a group of `candidate_nodes` nodes whose
    /// residual was above `threshold`) shows its own content where its end pose
    /// put it: at least half its nodes seen there, at a median residual (relit)
    /// below the threshold. A pose that lowers the loss by moving content the start state
    /// had wrong (the unseen inside of a closed body, revealed by the motion) out
    /// of sight, or onto other wrong content, does not pass.
    fn looks_right_where_moved(&self, p: usize, candidate_nodes: usize, threshold: f32, views: &[&TrainView]) -> bool {
        let (seen, median) = self.residual_where_moved(p, views);
        let passes = 2 * seen >= candidate_nodes && median < threshold;
        tracing::info!(part = p + 1, seen, median, threshold, passes, "stage II: the searched part where it moved");
        passes
    }

    /// How many of part `p`'s nodes `views` see at the last knot, and the median
    /// of their residuals (relit, see `node_residuals`).
    fn residual_where_moved(&self, p: usize, views: &[&TrainView]) -> (usize, f32) {
        let parts = self.articulation.as_ref().expect("the part judged");
        let residual = self.node_residuals(parts, p + 1, views, true);
        let mut seen: Vec<f32> = residual.into_iter().filter(|r| r.is_finite()).collect();
        seen.sort_by(f32::total_cmp);
        (seen.len(), seen.get(seen.len() / 2).copied().unwrap_or(f32::INFINITY))
    }

    /// The tracked parts judged on the end state as a part found there is
    /// (`looks_right_where_moved`), after their end poses were searched: a part
    /// most of whose nodes `end_views` do not see where it moved, or whose seen
    /// nodes' median residual (relit) is above the threshold the base's residual
    /// sets, moved content the start state had wrong out of sight or onto content
    /// it lacked (the inside of a body the motion revealed), or is a piece whose
    /// motion no end pose explains; its nodes go back to the base (and may be
    /// found on the end state as a part of their own). Returns the nodes it gave back to the base.
    pub fn drop_parts_that_look_wrong(&mut self, end_views: &[TrainView]) -> Vec<bool> {
        let mut returned = vec![false; self.node_centres.len()];
        let Some(parts) = self.articulation.clone() else {
            return returned;
        };
        if end_views.is_empty() || parts.centres.is_empty() {
            return returned;
        }
        let views = evenly_spread(&end_views.iter().collect::<Vec<_>>(), VIEWS);
        let mut base: Vec<f32> =
            self.node_residuals(&parts, 0, &views, false).into_iter().filter(|r| r.is_finite()).collect();
        if base.is_empty() {
            return returned;
        }
        base.sort_by(f32::total_cmp);
        let threshold = residual_threshold(&base);
        let mut node_part = parts.node_part.clone();
        let held = self.held_part();
        for p in (0..parts.centres.len()).filter(|&p| Some(p) != held) {
            let nodes = parts.node_part.iter().filter(|&&l| l == p + 1).count();
            let (seen, median) = self.residual_where_moved(p, &views);
            // The test a part found on the end state passes (`looks_right_where_moved`).
            let wrong = 2 * seen < nodes || median >= threshold;
            tracing::info!(
                part = p + 1,
                nodes,
                seen,
                median,
                threshold,
                wrong,
                "stage II: a tracked part where it moved"
            );
            if wrong {
                for (l, r) in node_part.iter_mut().zip(returned.iter_mut()).filter(|(l, _)| **l == p + 1) {
                    (*l, *r) = (0, true);
                }
            }
        }
        if returned.contains(&true) {
            self.set_articulation(parts.relabelled(node_part));
        }
        returned
    }

    /// Part `p`'s poses at the knots between rest and its end pose, each the
    /// fraction (in tenths) of the screw motion from rest to the end pose that
    /// best explains the motion frame nearest the knot's time.
    fn fit_path(&mut self, p: usize, frames: &[TrainView]) {
        let mut parts = self.articulation.clone().expect("a part to fit");
        let last = parts.poses.len() - 1;
        let c = parts.centres[p];
        let end = parts.poses[last][p].to_rigid(c);
        for k in 1..last {
            let t = self.knot_time(k);
            let Some(frame) = frames
                .iter()
                .filter(|v| v.time.is_some())
                .min_by(|a, b| (a.time.unwrap_or(0.0) - t).abs().total_cmp(&(b.time.unwrap_or(0.0) - t).abs()))
            else {
                break;
            };
            // The frame's time may fall between knots: judge the knot's pose on its own.
            let mut at_knot = frame.clone();
            at_knot.time = Some(t);
            let mut best = (f32::INFINITY, NodePose::IDENTITY);
            for s in 0..=PATH_STEPS {
                let pose = NodePose::from_rigid(&screw_fraction(&end, s as f64 / PATH_STEPS as f64), c);
                parts.poses[k][p] = pose;
                let loss = self.articulated_loss(&parts, &parts.node_part, &[&at_knot]);
                if loss < best.0 {
                    best = (loss, pose);
                }
            }
            parts.poses[k][p] = best.1;
        }
        self.set_articulation(parts);
    }
}

/// The residual above which a node is wrong: `MIN_RESIDUAL`, or `RESIDUAL_RATIO`
/// times the median of `sorted` (the seen base nodes' residuals, ascending).
fn residual_threshold(sorted: &[f32]) -> f32 {
    MIN_RESIDUAL.max(RESIDUAL_RATIO * sorted[sorted.len() / 2])
}

/// The rigid motion a fraction `f` of the way along the screw motion from rest to `m`.
fn screw_fraction(m: &Rigid, f: f64) -> Rigid {
    let (axis, angle) = DQuat::from_mat3(&m.r).to_axis_angle();
    if angle.abs() < 1e-9 {
        return Rigid { r: DMat3::IDENTITY, t: m.t * f };
    }
    let along = axis.dot(m.t);
    // A point q on the screw axis: (I - R) q = t - along u, with q . u = 0.
    let a = DMat3::IDENTITY - m.r;
    let b = m.t - axis * along;
    let ata = a.transpose() * a + DMat3::from_cols(axis * axis.x, axis * axis.y, axis * axis.z);
    let q = ata.inverse() * (a.transpose() * b);
    let r = DMat3::from_axis_angle(axis, angle * f);
    Rigid { r, t: (DMat3::IDENTITY - r) * q + axis * (along * f) }
}

#[cfg(test)]
mod tests {
    use glam::{DVec3, Quat};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    use super::*;
    use crate::camera::{Camera, Intrinsics};
    use crate::render::Render;
    use crate::render::RenderOptions;
    use crate::splat::{logit, GaussianSet};
    use crate::train::dynamic_stage::DynamicConfig;

    /// A base plate and a door plate side by side in z = 0, textured at random,
    /// no part tracked; the door truly turns 90 degrees about the y axis through
    /// their common edge (`turn` of the way at time t). Returns the tracker (two
    /// segments, everything at rest), the door's Gaussians and the truth at `turn`.
    fn plates(turn: f32) -> (NodeTracker, Vec<usize>, GaussianSet) {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let mut gs = GaussianSet::new(0);
        for _ in 0..1200 {
            let (x, y) = (rng.random_range(-0.5..0.5f32), rng.random_range(-0.3..0.3f32));
            let dc = [rng.random_range(-1.5..1.5), rng.random_range(-1.5..1.5), rng.random_range(-1.5..1.5)];
            gs.push(Vec3::new(x, y, 0.0), Vec3::new(-3.3, -3.3, -5.0), [1.0, 0.0, 0.0, 0.0], logit(0.9), dc, &[]);
        }
        let mut config = DynamicConfig::cpu();
        config.track.nodes = 64;
        config.track.gaussians_per_node = 1;
        config.track.end_iterations = 200;
        config.track.search_step = std::f32::consts::PI / 12.0;
        config.eval_background = [0.0; 3];
        let mut tracker = NodeTracker::new(config, &gs, &[]).expect("tracker");
        let n = tracker.node_centres.len();
        tracker.knots = vec![vec![NodePose::IDENTITY; n]; 3];
        tracker.gains = vec![vec![0.0; n]; 3];
        let door: Vec<usize> =
            (0..gs.len()).filter(|&i| tracker.node_centres[tracker.binding[i] as usize].x > 0.0).collect();
        let r = Quat::from_rotation_y(-std::f32::consts::FRAC_PI_2 * turn);
        let mut truth = tracker.gaussians.clone();
        for &i in &door {
            let m = r * tracker.gaussians.mean(i);
            truth.means[3 * i..3 * i + 3].copy_from_slice(&m.to_array());
        }
        (tracker, door, truth)
    }

    fn views_of(set: &GaussianSet, time: f32, count: usize) -> Vec<TrainView> {
        let k = Intrinsics { width: 64, height: 64, fx: 58.0, fy: 58.0, cx: 32.0, cy: 32.0 };
        (0..count)
            .map(|i| {
                let a = 0.3 + i as f32 * std::f32::consts::TAU / count as f32;
                let camera = Camera::look_at(k, Vec3::new(1.6 * a.cos(), 1.2, 1.6 * a.sin()), Vec3::ZERO, Vec3::Y);
                let r: Render = render(set, &camera, &RenderOptions::uniform(Vec3::ZERO));
                TrainView {
                    name: String::new(),
                    camera,
                    premultiplied: r.image.color,
                    alpha: Some(r.image.alpha),
                    time: Some(time),
                    depth: None,
                    backdrop: None,
                    palms: Vec::new(),
                }
            })
            .collect()
    }

    /// Median distance of `members` between the tracker's state at time `t` and `truth`.
    fn median_error(tracker: &NodeTracker, members: &[usize], truth: &GaussianSet, t: f32) -> f32 {
        let now = tracker.deformed_at(t);
        let mut d: Vec<f32> = members.iter().map(|&i| now.mean(i).distance(truth.mean(i))).collect();
        d.sort_by(f32::total_cmp);
        d[d.len() / 2]
    }

    #[test]
    fn a_door_no_tracked_part_holds_is_found_on_the_end_state() {
        let (mut tracker, door, end) = plates(1.0);
        let (_, _, half) = plates(0.5);
        let end_views = views_of(&end, 1.0, 16);
        let frames = views_of(&half, 0.5, 1);
        let none = vec![false; tracker.node_centres.len()];
        assert_eq!(tracker.discover_on_end_state(&frames, &end_views, &none), 1, "one part found");
        let parts = tracker.articulation.clone().expect("parts");
        assert_eq!(parts.centres.len(), 1);
        let members = tracker.gaussians_labelled(&parts.node_part, 1);
        let on_door = members.iter().filter(|i| door.contains(i)).count();
        assert!(on_door as f32 >= 0.9 * members.len() as f32, "{on_door} of the part's {} on the door", members.len());
        assert!(on_door as f32 >= 0.6 * door.len() as f32, "{on_door} of the door's {} in the part", door.len());
        let c = parts.centres[0];
        let joint = |pose: NodePose| crate::motion::extract_joint(&pose.to_rigid(c), c.as_dvec3());
        let open = joint(parts.poses[2][0]);
        assert!(open.axis.dot(DVec3::Y).abs() > 5f64.to_radians().cos(), "axis {:?}", open.axis);
        // 15 degrees: at 64 px a sixth of the door (the strip by the hinge, which
        // barely moves) stays in the base, and the fit settles at 78 degrees.
        assert!((open.amount.to_degrees() - 90.0).abs() < 15.0, "opened {} deg", open.amount.to_degrees());
        // The hinge is the plates' common edge, x = 0, z = 0.
        let pivot = open.origin - open.axis * open.origin.dot(open.axis);
        assert!(DVec3::new(pivot.x, 0.0, pivot.z).length() < 0.1, "pivot {pivot:?}");
        // The path: the knot at t = 0.5 half way round (the fit steps in tenths).
        let halfway = joint(parts.poses[1][0]).amount.to_degrees();
        assert!(
            (halfway - 0.5 * open.amount.to_degrees()).abs() <= 0.1 * open.amount.to_degrees() + 0.5,
            "half way: {halfway} deg"
        );
        let base: Vec<usize> = (0..end.len()).filter(|i| !door.contains(i)).collect();
        assert!(median_error(&tracker, &base, &end, 1.0) < 1e-6, "the base stays put");
    }

    #[test]
    fn nothing_is_found_when_the_end_state_is_the_start_state() {
        let (mut tracker, _, rest) = plates(0.0);
        let end_views = views_of(&rest, 1.0, 16);
        let none = vec![false; tracker.node_centres.len()];
        assert_eq!(tracker.discover_on_end_state(&views_of(&rest, 0.5, 1), &end_views, &none), 0);
        assert!(tracker.articulation.is_none(), "no part, and the free trajectories kept");
    }

    #[test]
    fn a_tracked_part_that_looks_wrong_where_it_moved_goes_back_to_the_base() {
        let (mut tracker, _, end) = plates(1.0);
        let n = tracker.node_centres.len();
        // Part 1: the door, at its true end pose (a quarter turn about the y axis
        // through the origin). Part 2: a strip of the base, given a turn it never made.
        let node_part: Vec<usize> = tracker
            .node_centres
            .iter()
            .map(|c| {
                if c.x > 0.0 {
                    1
                } else if c.x < -0.3 {
                    2
                } else {
                    0
                }
            })
            .collect();
        let centre = |p: usize| {
            let (sum, count) = (0..n)
                .filter(|&k| node_part[k] == p)
                .fold((Vec3::ZERO, 0), |(s, c), k| (s + tracker.node_centres[k], c + 1));
            sum / count as f32
        };
        let turn = |angle: f32, pivot: Vec3, c: Vec3| {
            let rotation = Quat::from_rotation_y(angle);
            NodePose { rotation, translation: rotation * (c - pivot) + pivot - c }
        };
        let (door, strip) = (centre(1), centre(2));
        let poses = vec![
            vec![NodePose::IDENTITY; 2],
            vec![NodePose::IDENTITY; 2],
            vec![turn(-std::f32::consts::FRAC_PI_2, Vec3::ZERO, door), turn(1.0, Vec3::new(-0.3, 0.0, 0.0), strip)],
        ];
        let door_nodes = node_part.iter().filter(|&&l| l == 1).count();
        tracker.set_articulation(TrackedParts { node_part, centres: vec![door, strip], poses });
        let strip_nodes: Vec<bool> =
            tracker.articulation.as_ref().expect("set").node_part.iter().map(|&l| l == 2).collect();
        let returned = tracker.drop_parts_that_look_wrong(&views_of(&end, 1.0, 16));
        assert_eq!(returned, strip_nodes, "the strip dropped, and only it");
        let parts = tracker.articulation.clone().expect("parts");
        assert_eq!(parts.centres.len(), 1, "the door kept");
        assert_eq!(parts.node_part.iter().filter(|&&l| l == 1).count(), door_nodes, "the door's nodes unchanged");
        assert_eq!(parts.node_part.iter().filter(|&&l| l > 1).count(), 0);
    }

    #[test]
    fn screw_fraction_runs_from_rest_to_the_motion_along_its_axis() {
        let pivot = DVec3::new(0.3, -0.2, 0.5);
        let axis = DVec3::new(0.2, 1.0, -0.1).normalize();
        let at = |angle: f64, slide: f64| {
            let r = DMat3::from_axis_angle(axis, angle);
            Rigid { r, t: pivot - r * pivot + axis * slide }
        };
        let m = at(1.9, 0.12);
        for f in [0.0, 0.25, 0.5, 1.0] {
            let got = screw_fraction(&m, f);
            let want = at(1.9 * f, 0.12 * f);
            for x in [DVec3::ZERO, DVec3::new(1.0, 2.0, -0.5)] {
                assert!(
                    got.apply(x).distance(want.apply(x)) < 1e-9,
                    "f = {f}: {:?} vs {:?}",
                    got.apply(x),
                    want.apply(x)
                );
            }
        }
        let slide = Rigid { r: DMat3::IDENTITY, t: DVec3::new(0.0, -0.35, 0.0) };
        assert!(screw_fraction(&slide, 0.5).t.distance(DVec3::new(0.0, -0.175, 0.0)) < 1e-12);
    }
}
