//! Stage II's tracking against ground truth: how far tracked points are from
//! where the true joints carry them, per ground-truth part and time. Joint
//! errors only say that the end result is wrong; this says when and on which
//! part the motion was lost.

use glam::Vec3;
use kiddo::{ImmutableKdTree, SquaredEuclidean};
use serde::{Deserialize, Serialize};

use super::twin::GroundTruth;

/// Surface samples per ground-truth part for labelling the tracked points.
const LABEL_SAMPLES: usize = 20_000;

/// One ground-truth part's tracking error at one time.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PartTrackingError {
    pub gt_part: usize,
    /// Tracked points nearest to this part's start-state surface.
    pub points: usize,
    /// Median and 90th percentile distance to the true position (world units).
    pub median: f64,
    pub p90: f64,
}

/// All parts' tracking errors at one time of the motion.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TrackingError {
    pub time: f32,
    pub parts: Vec<PartTrackingError>,
}

/// The ground-truth part of each start-state point: the part whose start mesh is nearest.
pub fn gt_labels(gt: &GroundTruth, points: &[Vec3], seed: u64) -> Vec<usize> {
    let mut samples = Vec::new();
    let mut owner = Vec::new();
    for (id, mesh) in &gt.meshes {
        for p in mesh.sample_surface(LABEL_SAMPLES, seed) {
            samples.push(p.to_array());
            owner.push(*id);
        }
    }
    if samples.is_empty() {
        return vec![0; points.len()];
    }
    let tree: ImmutableKdTree<f32, 3> = ImmutableKdTree::new_from_slice(&samples);
    points.iter().map(|p| owner[tree.nearest_one::<SquaredEuclidean>(&p.to_array()).item as usize]).collect()
}

/// Tracking errors at `times`: `start` are the tracked points at t = 0, `at(t)`
/// the same points at time t. Parts without a joint stay where they are.
pub fn tracking_errors(
    gt: &GroundTruth,
    start: &[Vec3],
    at: impl Fn(f32) -> Vec<Vec3>,
    times: &[f32],
    seed: u64,
) -> Vec<TrackingError> {
    let labels = gt_labels(gt, start, seed);
    let mut ids: Vec<usize> = gt.meshes.iter().map(|(id, _)| *id).collect();
    ids.sort_unstable();
    times
        .iter()
        .map(|&t| {
            let now = at(t);
            let parts = ids
                .iter()
                .filter_map(|&id| {
                    let motion = gt.joints.joints.iter().find(|j| j.part == id).map(|j| j.motion_from_start(t));
                    let mut d: Vec<f64> = labels
                        .iter()
                        .zip(start.iter().zip(&now))
                        .filter(|(&l, _)| l == id)
                        .map(|(_, (&p0, &p))| {
                            let truth = motion.map_or(p0, |m| m.transform_point3(p0));
                            f64::from((p - truth).length())
                        })
                        .collect();
                    if d.is_empty() {
                        return None;
                    }
                    d.sort_by(f64::total_cmp);
                    let q = |f: f64| d[((d.len() - 1) as f64 * f).round() as usize];
                    Some(PartTrackingError { gt_part: id, points: d.len(), median: q(0.5), p90: q(0.9) })
                })
                .collect();
            TrackingError { time: t, parts }
        })
        .collect()
}

/// One predicted part's make-up against ground truth: how many of its start-state
/// Gaussians lie nearest each ground-truth part (`gt_labels`). Joint errors say
/// a part moves wrongly; this says what the part is made of (a door found as a
/// fifth of its panel, a drawer holding pieces of three doors).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PartComposition {
    /// 0 is the static base.
    pub part: usize,
    /// (ground-truth part, Gaussians), largest first.
    pub gt_parts: Vec<(usize, usize)>,
}

/// The make-up of each predicted part: `sets[0]` is the static base, `sets[k]`
/// part k, each the start-state centres of its Gaussians.
pub fn part_composition(gt: &GroundTruth, sets: &[Vec<Vec3>], seed: u64) -> Vec<PartComposition> {
    // One labelling of all the points: the meshes are sampled and indexed once.
    let all: Vec<Vec3> = sets.iter().flatten().copied().collect();
    let mut labels = gt_labels(gt, &all, seed).into_iter();
    sets.iter()
        .enumerate()
        .map(|(part, points)| {
            let mut counts: Vec<(usize, usize)> = Vec::new();
            for label in labels.by_ref().take(points.len()) {
                match counts.iter_mut().find(|(id, _)| *id == label) {
                    Some((_, n)) => *n += 1,
                    None => counts.push((label, 1)),
                }
            }
            counts.sort_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(&b.0)));
            PartComposition { part, gt_parts: counts }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::MeshData;
    use crate::synth::gt::PartRecord;
    use crate::synth::{JointKind, JointRecord, JointsFile};

    fn cube(lo: Vec3, hi: Vec3) -> MeshData {
        let mut m = MeshData::default();
        crate::synth::Shape::cuboid(lo, hi).tessellate(8, &mut m);
        m
    }

    /// A base cube and a lid that slides 0.5 along +x: points that follow the lid
    /// exactly score 0; points left behind score the slide at t = 1, half at t = 0.5.
    #[test]
    fn points_left_behind_score_the_true_motion() {
        let joints = JointsFile {
            object: "test".into(),
            joints: vec![JointRecord {
                part: 1,
                kind: JointKind::Prismatic,
                axis: [1.0, 0.0, 0.0],
                origin: [0.0; 3],
                range: [0.0, 0.5],
                parent: 0,
            }],
            parts: [0, 1]
                .map(|id| PartRecord { id, name: format!("p{id}"), mesh_start: None, mesh_end: None })
                .to_vec(),
        };
        let gt = GroundTruth {
            joints,
            meshes: vec![
                (0, cube(Vec3::ZERO, Vec3::ONE)),
                (1, cube(Vec3::new(0.0, 0.0, 2.0), Vec3::new(1.0, 1.0, 2.2))),
            ],
        };
        let start = vec![Vec3::new(0.5, 0.5, 0.0), Vec3::new(0.5, 0.5, 2.2), Vec3::new(0.2, 0.8, 2.0)];
        assert_eq!(gt_labels(&gt, &start, 1), vec![0, 1, 1]);
        // The lid's first point follows the slide, the second stays put.
        let at = |t: f32| vec![start[0], start[1] + Vec3::X * 0.5 * t, start[2]];
        let e = tracking_errors(&gt, &start, at, &[0.5, 1.0], 1);
        assert_eq!(e.len(), 2);
        let lid = |k: usize| e[k].parts.iter().find(|p| p.gt_part == 1).unwrap().clone();
        assert_eq!(lid(1).points, 2);
        assert!((lid(1).p90 - 0.5).abs() < 1e-6, "{:?}", lid(1));
        assert!((lid(0).p90 - 0.25).abs() < 1e-6, "{:?}", lid(0));
        assert!(e[1].parts.iter().find(|p| p.gt_part == 0).unwrap().median < 1e-9);
    }

    /// A predicted part holding two lid points and one base point, and a base of one
    /// base point: each part's count per ground-truth part, largest first.
    #[test]
    fn a_part_is_counted_by_the_ground_truth_parts_its_points_lie_on() {
        let gt = GroundTruth {
            joints: JointsFile { object: "test".into(), joints: Vec::new(), parts: Vec::new() },
            meshes: vec![
                (0, cube(Vec3::ZERO, Vec3::ONE)),
                (1, cube(Vec3::new(0.0, 0.0, 2.0), Vec3::new(1.0, 1.0, 2.2))),
            ],
        };
        let base = vec![Vec3::new(0.5, 0.5, 0.0)];
        let part = vec![Vec3::new(0.5, 0.5, 2.2), Vec3::new(0.5, 0.5, 1.0), Vec3::new(0.2, 0.8, 2.0)];
        let c = part_composition(&gt, &[base, part], 1);
        assert_eq!(c[0], PartComposition { part: 0, gt_parts: vec![(0, 1)] });
        assert_eq!(c[1], PartComposition { part: 1, gt_parts: vec![(1, 2), (0, 1)] });
    }
}
