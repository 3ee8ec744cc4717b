//! Metrics as the field reports them (paper Appendix B; ARCHITECTURE.md).

use glam::{DMat3, DVec3};
use serde::{Deserialize, Serialize};

use crate::motion::{JointEstimate, JointKind};

pub mod shape;
pub mod tracking;
pub mod twin;

/// Axis angle error in degrees, orientation-invariant: min(theta, 180 - theta).
pub fn axis_angle_error_deg(a: DVec3, b: DVec3) -> f64 {
    let c = a.normalize().dot(b.normalize()).clamp(-1.0, 1.0);
    let theta = c.acos().to_degrees();
    theta.min(180.0 - theta)
}

/// Shortest distance between two axis lines, times 10 (units of 0.1 m).
pub fn axis_position_error(o_p: DVec3, a_p: DVec3, o_g: DVec3, a_g: DVec3) -> f64 {
    let (a_p, a_g) = (a_p.normalize(), a_g.normalize());
    let n = a_p.cross(a_g);
    let d = if n.length() < 1e-6 {
        // (Nearly) parallel: distance of a point of one line to the other.
        (o_g - o_p).cross(a_p).length()
    } else {
        n.dot(o_p - o_g).abs() / n.length()
    };
    10.0 * d
}

/// Geodesic angle (degrees) between two relative rotations.
pub fn rotation_error_deg(r_p: DMat3, r_g: DMat3) -> f64 {
    let m = r_p * r_g.transpose();
    ((m.x_axis.x + m.y_axis.y + m.z_axis.z - 1.0) * 0.5).clamp(-1.0, 1.0).acos().to_degrees()
}

/// A ground-truth joint: type, unit axis, a point on it, states at t = 0 and 1.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct GtJoint {
    pub part: usize,
    pub kind: JointKind,
    pub axis: DVec3,
    pub origin: DVec3,
    pub range: [f64; 2],
}

impl GtJoint {
    /// Relative motion from t = 0 to t = 1: (rotation, translation of the axis point's frame).
    pub(crate) fn relative(&self) -> (DMat3, DVec3) {
        let d = self.range[1] - self.range[0];
        match self.kind {
            JointKind::Revolute => {
                let r = DMat3::from_axis_angle(self.axis.normalize(), d);
                (r, self.origin - r * self.origin)
            }
            JointKind::Prismatic => (DMat3::IDENTITY, self.axis.normalize() * d),
        }
    }
}

/// A predicted joint with its part's relative motion t = 0 -> 1.
#[derive(Clone, Copy, Debug)]
pub struct PredictedJoint {
    pub joint: JointEstimate,
    pub rotation: DMat3,
    pub translation: DVec3,
}

impl PredictedJoint {
    /// A part's joint, fitted from its motion `motion`, as a prediction: the
    /// twin's motion along it. A prismatic part slides along its axis unturned
    /// (what leftover rotation the fit had is not the joint's); a revolute one
    /// moves as fitted.
    pub fn of_part(joint: JointEstimate, motion: &crate::motion::Rigid) -> Self {
        match joint.kind {
            JointKind::Revolute => Self { joint, rotation: motion.r, translation: motion.t },
            JointKind::Prismatic => Self { joint, rotation: DMat3::IDENTITY, translation: joint.axis * joint.amount },
        }
    }
}

/// Errors of one matched joint.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct JointErrors {
    pub gt_part: usize,
    pub predicted: usize,
    pub kind: JointKind,
    pub axis_angle_deg: f64,
    /// Revolute only (0.1 m units).
    pub axis_position: Option<f64>,
    /// Degrees (revolute) or metres (prismatic).
    pub part_motion: f64,
}

/// Matching of predicted to ground-truth joints.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ArticulationReport {
    pub matched: Vec<JointErrors>,
    /// GT parts with no predicted joint of the same type (a failure, reported).
    pub missing: Vec<usize>,
    /// Predicted joints matched to nothing.
    pub extra: Vec<usize>,
}

fn errors(p: &PredictedJoint, g: &GtJoint, pi: usize) -> Option<JointErrors> {
    if p.joint.kind != g.kind {
        return None;
    }
    let (rg, tg) = g.relative();
    let axis_angle_deg = axis_angle_error_deg(p.joint.axis, g.axis);
    let (axis_position, part_motion) = match g.kind {
        JointKind::Revolute => (
            Some(axis_position_error(p.joint.origin, p.joint.axis, g.origin, g.axis)),
            rotation_error_deg(p.rotation, rg),
        ),
        JointKind::Prismatic => (None, (p.translation - tg).length()),
    };
    Some(JointErrors { gt_part: g.part, predicted: pi, kind: g.kind, axis_angle_deg, axis_position, part_motion })
}

/// The cost the assignment minimises: axis angle (degrees) + axis position
/// (1 per cm) + part motion (degrees, or 1 per cm), so identical axis
/// directions (all doors of a cabinet) are told apart by position and motion.
fn match_cost(e: &JointErrors) -> f64 {
    let motion = match e.kind {
        JointKind::Revolute => e.part_motion,
        JointKind::Prismatic => 100.0 * e.part_motion,
    };
    e.axis_angle_deg + 10.0 * e.axis_position.unwrap_or(0.0) + motion
}

/// Assign predicted joints to GT joints with the least total error (types must
/// agree; see `match_cost`) by the Hungarian method (`pathfinding`'s
/// Kuhn-Munkres) on a square matrix: a pair of other types and a padding row or
/// column cost more than any set of real pairs, so the assignment has the most
/// matches first, then the least cost.
pub fn match_joints(pred: &[PredictedJoint], gt: &[GtJoint]) -> ArticulationReport {
    use pathfinding::prelude::{kuhn_munkres_min, Matrix};
    // Costs in micro-units as integers (the solver needs an exact ordered sum);
    // one real pair costs at most REAL_CAP, and UNMATCHED exceeds any sum of them.
    const SCALE: f64 = 1e6;
    const REAL_CAP: i64 = 1_000_000_000_000;
    let n = pred.len().max(gt.len());
    let unmatched = REAL_CAP * (n as i64 + 1);
    let mut report = ArticulationReport::default();
    if n == 0 {
        return report;
    }
    let cost = |g: usize, p: usize| -> i64 {
        match (gt.get(g), pred.get(p)) {
            (Some(gj), Some(pj)) => errors(pj, gj, p)
                .map(|e| match_cost(&e))
                .filter(|c| c.is_finite())
                .map_or(unmatched, |c| ((c * SCALE).round() as i64).min(REAL_CAP)),
            _ => unmatched,
        }
    };
    let weights = Matrix::from_fn(n, n, |(g, p)| cost(g, p));
    let (_, assignment) = kuhn_munkres_min(&weights);
    let mut used = vec![false; pred.len()];
    for (g, gj) in gt.iter().enumerate() {
        let p = assignment[g];
        match (cost(g, p) < unmatched).then(|| errors(&pred[p], gj, p)).flatten() {
            Some(e) => {
                used[p] = true;
                report.matched.push(e);
            }
            None => report.missing.push(gj.part),
        }
    }
    report.extra = (0..pred.len()).filter(|&p| !used[p]).collect();
    report
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn axis_angle_error_ignores_orientation() {
        assert!((axis_angle_error_deg(DVec3::Z, -DVec3::Z)).abs() < 1e-9);
        assert!((axis_angle_error_deg(DVec3::Z, DVec3::X) - 90.0).abs() < 1e-9);
        let tilted = DVec3::new(0.0, (10f64).to_radians().sin(), (10f64).to_radians().cos());
        assert!((axis_angle_error_deg(tilted, -DVec3::Z) - 10.0).abs() < 1e-9);
    }

    #[test]
    fn axis_position_error_is_line_distance_in_decimetres() {
        // Skew lines: z axis through the origin and x axis through (0, 0.3, 0): distance 0.3 m.
        let e = axis_position_error(DVec3::ZERO, DVec3::Z, DVec3::new(5.0, 0.3, 0.0), DVec3::X);
        assert!((e - 3.0).abs() < 1e-9, "{e}");
        // Parallel lines 0.05 m apart; the point along the line does not matter.
        let e = axis_position_error(DVec3::ZERO, DVec3::Z, DVec3::new(0.05, 0.0, 7.0), -DVec3::Z);
        assert!((e - 0.5).abs() < 1e-9, "{e}");
    }

    #[test]
    fn rotation_error_is_the_geodesic_angle() {
        let a = DMat3::from_rotation_z(0.3);
        let b = DMat3::from_rotation_z(0.1);
        assert!((rotation_error_deg(a, b) - 0.2f64.to_degrees()).abs() < 1e-9);
    }

    #[test]
    fn type_mismatch_is_reported_as_missing_and_extra() {
        let gt =
            [GtJoint { part: 1, kind: JointKind::Revolute, axis: DVec3::Z, origin: DVec3::ZERO, range: [0.0, 1.0] }];
        let pred = [PredictedJoint {
            joint: JointEstimate {
                kind: JointKind::Prismatic,
                axis: DVec3::Z,
                origin: DVec3::ZERO,
                amount: 0.3,
                translation_along_axis: 0.3,
            },
            rotation: DMat3::IDENTITY,
            translation: DVec3::Z * 0.3,
        }];
        let r = match_joints(&pred, &gt);
        assert!(r.matched.is_empty());
        assert_eq!(r.missing, vec![1]);
        assert_eq!(r.extra, vec![0]);
    }

    fn revolute(origin: DVec3, amount: f64) -> PredictedJoint {
        let rotation = DMat3::from_axis_angle(DVec3::Z, amount);
        PredictedJoint {
            joint: JointEstimate {
                kind: JointKind::Revolute,
                axis: DVec3::Z,
                origin,
                amount,
                translation_along_axis: 0.0,
            },
            rotation,
            translation: origin - rotation * origin,
        }
    }

    #[test]
    fn assignment_tells_parallel_doors_apart_and_reports_the_extra_one() {
        // Two doors on parallel vertical hinges 0.6 m apart; three predictions given in
        // another order, one of them far from both hinges.
        let gt = [
            GtJoint {
                part: 1,
                kind: JointKind::Revolute,
                axis: DVec3::Z,
                origin: DVec3::new(0.3, 0.0, 0.0),
                range: [0.0, 1.5],
            },
            GtJoint {
                part: 2,
                kind: JointKind::Revolute,
                axis: DVec3::Z,
                origin: DVec3::new(-0.3, 0.0, 0.0),
                range: [0.0, -1.5],
            },
        ];
        let pred = [
            revolute(DVec3::new(2.0, 2.0, 0.0), 0.5),
            revolute(DVec3::new(-0.31, 0.0, 0.0), -1.49),
            revolute(DVec3::new(0.3, 0.01, 0.0), 1.5),
        ];
        let r = match_joints(&pred, &gt);
        let by_gt: Vec<(usize, usize)> = r.matched.iter().map(|e| (e.gt_part, e.predicted)).collect();
        assert_eq!(by_gt, vec![(1, 2), (2, 1)]);
        assert_eq!(r.extra, vec![0]);
        assert!(r.missing.is_empty());
        assert!((r.matched[1].axis_position.unwrap() - 0.1).abs() < 1e-9);
        assert!((r.matched[1].part_motion - 0.01f64.to_degrees()).abs() < 1e-6);
        // Fewer predictions than parts: the unmatched part is missing.
        let r = match_joints(&pred[2..], &gt);
        assert_eq!(r.missing, vec![2]);
        assert!(r.extra.is_empty());
    }
}
