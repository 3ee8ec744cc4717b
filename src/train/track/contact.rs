//! The hand as a 3D tracker of the part it holds.
//!
//! An egocentric capture films a door from where the wearer stands, and the
//! door swings mostly along the line of sight, showing a face the start state
//! never saw: on the synthetic recording the node tracking followed the door to
//! 15 of its 44 degrees at t = 0.4 with every segment fitting its frames at
//! 28-30 dB, and held to the palm by a contact term, the door's other nodes
//! still did not follow (docs/session.md). The glasses' hand tracking sees the
//! palm in 3D, and a palm that holds a part moves with it: the first palm that
//! comes within reach of the start state is the touch, and the path it then
//! traces (an arc about the hinge, or a line along the slide) is the part's
//! motion, one degree of freedom sampled at every frame.

use glam::Vec3;
use kiddo::{ImmutableKdTree, SquaredEuclidean};
use serde::{Deserialize, Serialize};

use super::{principal_axes, NodePose};
use crate::motion::JointKind;
use crate::splat::GaussianSet;
use crate::train::views::TrainView;

/// A palm this far (metres) off an arc or line is not on it (the hand arriving
/// or leaving, or tracked that far off).
const OUTLIER_FLOOR: f32 = 0.02;
const OUTLIER_PASSES: usize = 4;
/// Palms the consensus draws its candidate lines and circles from (evenly spread).
const CONSENSUS_POINTS: usize = 40;
/// A palm that turns less than this (radians) about its arc's centre moved along a line.
const MIN_ARC: f32 = 0.2;
/// A palm that moves less than this (metres) did not move the object.
const MIN_TRAVEL: f32 = 0.03;

/// The one-degree-of-freedom motion the holding palm traced: a turn about an
/// axis (the palm's arc) or a slide along one (its line), with the angle or
/// distance reached at each motion time the palm was seen.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct HandMotion {
    pub kind: JointKind,
    /// Unit axis; a point on it (revolute).
    pub axis: Vec3,
    pub origin: Vec3,
    /// (motion time, angle in radians or distance in metres), in time order.
    pub samples: Vec<(f32, f32)>,
    /// The arc's radius (0 for a line).
    pub radius: f32,
    /// RMS distance of the palms fitted from the arc or line (metres).
    pub residual: f32,
}

impl HandMotion {
    /// Fit the palm positions `(time, position)` (time order) with an arc or a
    /// line, leaving out palms off it (arriving, leaving); None when the palm
    /// moved less than `MIN_TRAVEL` or too few palms were seen.
    pub fn fit(track: &[(f32, Vec3)]) -> Option<Self> {
        let first = track.first()?.1;
        let travel = track.iter().map(|(_, p)| p.distance(first)).fold(0.0f32, f32::max);
        if track.len() < 4 || travel < MIN_TRAVEL {
            return None;
        }
        // Each shape is found by consensus (the most palms within the outlier
        // floor of a line through two palms or a circle through three: the hand
        // arriving and leaving would bend a least-squares fit of a short arc the
        // wrong way) and refitted on its palms; the one more palms lie on wins, an
        // arc only when it turns at least `MIN_ARC`.
        let points: Vec<Vec3> = track.iter().map(|(_, p)| *p).collect();
        let line = Self::consensus(track, Self::fit_line, &Self::line_candidates(&points));
        let arc = Self::consensus(track, Self::fit_arc, &Self::arc_candidates(&points))
            .filter(|(arc, _)| arc.samples.iter().map(|s| s.1.abs()).fold(0.0f32, f32::max) >= MIN_ARC);
        match (arc, line) {
            (Some((arc, a)), Some((line, l))) if (a, -arc.residual) >= (l, -line.residual) => Some(arc),
            (arc, line) => line.or(arc).map(|(m, _)| m),
        }
    }

    /// At most `CONSENSUS_POINTS` of `points`, evenly spread, for candidates.
    fn spread(points: &[Vec3]) -> Vec<Vec3> {
        let step = points.len().div_ceil(CONSENSUS_POINTS).max(1);
        points.iter().step_by(step).copied().collect()
    }

    /// Lines through every two palms at least `MIN_TRAVEL` apart.
    fn line_candidates(points: &[Vec3]) -> Vec<Self> {
        let p = Self::spread(points);
        let mut out = Vec::new();
        for i in 0..p.len() {
            for j in i + 1..p.len() {
                if p[i].distance(p[j]) >= MIN_TRAVEL {
                    out.push(HandMotion::shape(JointKind::Prismatic, (p[j] - p[i]).normalize(), p[i], 0.0));
                }
            }
        }
        out
    }

    /// Circles through every three palms that are not in a line.
    fn arc_candidates(points: &[Vec3]) -> Vec<Self> {
        let p = Self::spread(points);
        let mut out = Vec::new();
        for i in 0..p.len() {
            for j in i + 1..p.len() {
                for k in j + 1..p.len() {
                    let (a, b) = (p[i] - p[k], p[j] - p[k]);
                    let n = a.cross(b);
                    if n.length_squared() < 1e-10 {
                        continue;
                    }
                    let centre =
                        p[k] + (a.length_squared() * b - b.length_squared() * a).cross(n) / (2.0 * n.length_squared());
                    out.push(HandMotion::shape(JointKind::Revolute, n.normalize(), centre, centre.distance(p[k])));
                }
            }
        }
        out
    }

    /// A shape only (no samples), to measure distances from.
    fn shape(kind: JointKind, axis: Vec3, origin: Vec3, radius: f32) -> Self {
        HandMotion { kind, axis, origin, samples: Vec::new(), radius, residual: 0.0 }
    }

    /// The candidate most palms lie on (within `OUTLIER_FLOOR`), refitted by
    /// `fit` on those palms until they stay the same; with their count.
    fn consensus(
        track: &[(f32, Vec3)],
        fit: fn(&[(f32, Vec3)]) -> Option<Self>,
        candidates: &[Self],
    ) -> Option<(Self, usize)> {
        let on = |m: &Self| -> Vec<(f32, Vec3)> {
            track.iter().filter(|&&(_, p)| m.distance(p) <= OUTLIER_FLOOR).copied().collect()
        };
        let best = candidates.iter().max_by_key(|m| on(m).len())?;
        let mut kept = on(best);
        let mut fitted = fit(&kept)?;
        for _ in 0..OUTLIER_PASSES {
            let now = on(&fitted);
            if now.len() < 4 || now.len() == kept.len() {
                break;
            }
            kept = now;
            fitted = fit(&kept)?;
        }
        Some((fitted, kept.len()))
    }

    /// The line through the palms (their principal axis).
    fn fit_line(track: &[(f32, Vec3)]) -> Option<Self> {
        let points: Vec<Vec3> = track.iter().map(|(_, p)| *p).collect();
        let p0 = *points.first()?;
        let mean = points.iter().copied().sum::<Vec3>() / points.len() as f32;
        let [major, _, _] = principal_axes(&points);
        let residual = rms(&points, |p| (p - mean - major * major.dot(p - mean)).length());
        Some(HandMotion {
            kind: JointKind::Prismatic,
            axis: major,
            origin: mean,
            samples: track.iter().map(|&(t, p)| (t, major.dot(p - p0))).collect(),
            radius: 0.0,
            residual,
        })
    }

    /// The circle through the palms in their plane (algebraic fit:
    /// x^2 + y^2 = a x + b y + c), with the angles turned from the first palm.
    fn fit_arc(track: &[(f32, Vec3)]) -> Option<Self> {
        if track.len() < 4 {
            return None;
        }
        let points: Vec<Vec3> = track.iter().map(|(_, p)| *p).collect();
        let mean = points.iter().copied().sum::<Vec3>() / points.len() as f32;
        // The normal from the two in-plane axes: `principal_axes`' third axis
        // follows rounding when the palms lie exactly in a plane.
        let [major, minor, _] = principal_axes(&points);
        let normal = major.cross(minor).normalize_or(Vec3::Z);
        let (mut ata, mut atb) = (glam::DMat3::ZERO, glam::DVec3::ZERO);
        for &p in &points {
            let (x, y) = (f64::from(major.dot(p - mean)), f64::from(minor.dot(p - mean)));
            let row = glam::DVec3::new(x, y, 1.0);
            ata += glam::DMat3::from_cols(row * x, row * y, row);
            atb += row * (x * x + y * y);
        }
        if ata.determinant().abs() <= 1e-18 {
            return None;
        }
        let abc = ata.inverse() * atb;
        let (cx, cy) = (abc.x / 2.0, abc.y / 2.0);
        let radius = (abc.z + cx * cx + cy * cy).max(0.0).sqrt() as f32;
        let centre = mean + major * cx as f32 + minor * cy as f32;
        // Angles about the normal from the first palm, unwrapped.
        let r0 = points[0] - centre;
        let mut samples: Vec<(f32, f32)> = Vec::with_capacity(track.len());
        for &(t, p) in track {
            let v = p - centre;
            let mut a = normal.dot(r0.cross(v)).atan2(r0.dot(v) - normal.dot(r0) * normal.dot(v));
            let last = samples.last().map_or(0.0, |s| s.1);
            while a - last > std::f32::consts::PI {
                a -= std::f32::consts::TAU;
            }
            while a - last < -std::f32::consts::PI {
                a += std::f32::consts::TAU;
            }
            samples.push((t, a));
        }
        let mut arc =
            HandMotion { kind: JointKind::Revolute, axis: normal, origin: centre, samples, radius, residual: 0.0 };
        arc.residual = rms(&points, |p| arc.distance(p));
        Some(arc)
    }

    /// Distance of `p` from the fitted arc's circle or the line.
    fn distance(&self, p: Vec3) -> f32 {
        let v = p - self.origin;
        let along = self.axis * self.axis.dot(v);
        let radial = (v - along).length() - self.radius;
        match self.kind {
            JointKind::Prismatic => radial,
            JointKind::Revolute => (along.length_squared() + radial * radial).sqrt(),
        }
    }

    /// The angle or distance at motion time `t`: linear between the palms
    /// fitted, 0 before the first and the last one's after it.
    pub fn amount_at(&self, t: f32) -> f32 {
        let s = &self.samples;
        let j = s.partition_point(|&(ts, _)| ts <= t);
        match (j.checked_sub(1).map(|i| s[i]), s.get(j)) {
            (Some((ta, a)), Some(&(tb, b))) if tb > ta => a + (b - a) * (t - ta) / (tb - ta),
            (Some((_, a)), _) => a,
            (None, _) => 0.0,
        }
    }

    /// The motion at time `t` as a pose about centre `c`.
    pub fn pose_about(&self, c: Vec3, t: f32) -> NodePose {
        self.pose_at_amount(c, self.amount_at(t))
    }

    /// The pose about centre `c` after turning or sliding by `amount`.
    pub fn pose_at_amount(&self, c: Vec3, amount: f32) -> NodePose {
        match self.kind {
            JointKind::Prismatic => NodePose { rotation: glam::Quat::IDENTITY, translation: self.axis * amount },
            JointKind::Revolute => {
                let rotation = glam::Quat::from_axis_angle(self.axis, amount);
                NodePose { rotation, translation: rotation * (c - self.origin) + self.origin - c }
            }
        }
    }
}

impl HandMotion {
    /// The same motion stopped at `end` (an amount between 0 and the palm's
    /// last): the part goes no further than that, whatever the palm did after.
    pub fn stopped_at(&self, end: f32) -> Self {
        let beyond = |a: f32| a * end.signum() > end.abs();
        let samples = self.samples.iter().map(|&(t, a)| (t, if beyond(a) { end } else { a })).collect();
        HandMotion { samples, ..self.clone() }
    }
}

/// Root mean square of `d` over `points`.
fn rms(points: &[Vec3], d: impl Fn(Vec3) -> f32) -> f32 {
    (points.iter().map(|&p| d(p).powi(2)).sum::<f32>() / points.len().max(1) as f32).sqrt()
}

/// Where the hand took hold of the object.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct HandContact {
    /// The palm at the touch, in start-state coordinates.
    pub point: Vec3,
    /// Motion time of the touch: the term applies from then on.
    pub time: f32,
    /// The node nearest to the point; once the part the hand moved is found,
    /// that part's node nearest to it. The held part is the one it belongs to.
    pub node: u32,
    /// The motion the palm traced from the touch on, when it moved.
    pub motion: Option<HandMotion>,
}

impl HandContact {
    /// The first palm (in time order over `frames`) within `reach` of a
    /// start-state Gaussian; None when no frame's palm comes that close.
    pub fn find(frames: &[TrainView], start: &GaussianSet, node_centres: &[Vec3], reach: f32) -> Option<Self> {
        let means: Vec<[f32; 3]> = (0..start.len()).map(|i| start.mean(i).to_array()).collect();
        if means.is_empty() || node_centres.is_empty() {
            return None;
        }
        let gaussians: ImmutableKdTree<f32, 3> = ImmutableKdTree::new_from_slice(&means);
        let mut timed: Vec<&TrainView> = frames.iter().filter(|v| v.time.is_some() && !v.palms.is_empty()).collect();
        timed.sort_by(|a, b| a.time.unwrap_or(0.0).total_cmp(&b.time.unwrap_or(0.0)));
        let (time, point) = timed.iter().find_map(|v| {
            v.palms
                .iter()
                .map(|p| (gaussians.nearest_one::<SquaredEuclidean>(&p.to_array()).distance.sqrt(), *p))
                .filter(|(d, _)| *d <= reach)
                .min_by(|a, b| a.0.total_cmp(&b.0))
                .map(|(_, p)| (v.time.unwrap_or(0.0), p))
        })?;
        let node = (0..node_centres.len())
            .min_by(|&a, &b| node_centres[a].distance(point).total_cmp(&node_centres[b].distance(point)))?
            as u32;
        // The holding palm from the touch on: at each frame, the palm nearest the last one.
        let mut last = point;
        let track: Vec<(f32, Vec3)> = timed
            .iter()
            .filter(|v| v.time.is_some_and(|t| t >= time))
            .filter_map(|v| {
                let palm = v.palms.iter().copied().min_by(|a, b| a.distance(last).total_cmp(&b.distance(last)))?;
                last = palm;
                Some((v.time.unwrap_or(0.0), palm))
            })
            .collect();
        let motion = HandMotion::fit(&track);
        Some(HandContact { point, time, node, motion })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Quat;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn plate() -> GaussianSet {
        // A 1 m x 1 m plate of Gaussians in the plane x = 0.
        let mut set = GaussianSet::new(0);
        for i in 0..11 {
            for j in 0..11 {
                let mean = Vec3::new(0.0, i as f32 * 0.1, j as f32 * 0.1);
                set.push(mean, Vec3::splat(-4.0), [1.0, 0.0, 0.0, 0.0], 2.0, [0.0; 3], &[]);
            }
        }
        set
    }

    fn view_at(t: f32, palms: Vec<Vec3>) -> TrainView {
        let camera = crate::camera::Camera::look_at(
            crate::camera::Intrinsics::from_fov_x(8, 8, 0.8),
            Vec3::new(3.0, 0.5, 0.5),
            Vec3::new(0.0, 0.5, 0.5),
            Vec3::Z,
        );
        TrainView {
            name: format!("t{t}"),
            camera,
            premultiplied: vec![0.0; 3 * 64],
            alpha: None,
            time: Some(t),
            depth: None,
            backdrop: None,
            palms,
        }
    }

    #[test]
    fn the_first_palm_within_reach_is_the_contact_and_its_nearest_node_holds_it() {
        let start = plate();
        let nodes = vec![Vec3::new(0.0, 0.0, 0.0), Vec3::new(0.0, 0.9, 0.5), Vec3::new(0.0, 1.0, 0.5)];
        // Sorted by time on the way in: 30 cm off at t = 0, 5.4 cm off at t = 0.05.
        let frames = vec![
            view_at(0.3, vec![Vec3::new(0.01, 0.9, 0.4)]),
            view_at(0.05, vec![Vec3::new(0.02, 0.95, 0.5), Vec3::new(2.0, 2.0, 2.0)]),
            view_at(0.0, vec![Vec3::new(0.3, 0.95, 0.5)]),
        ];
        let c = HandContact::find(&frames, &start, &nodes, 0.06).expect("a contact");
        assert_eq!(c.time, 0.05);
        assert_eq!(c.point, Vec3::new(0.02, 0.95, 0.5));
        assert_eq!(c.node, 1, "the door-edge node nearest the palm");
        assert!(HandContact::find(&frames[2..], &start, &nodes, 0.05).is_none(), "30 cm is out of reach");
    }

    /// Palms on an arc of radius 0.6 about the vertical axis through (0.3, -0.3),
    /// turning 0 -> 1.9 rad over t in [0.1, 0.9], arriving (before) and leaving
    /// (after) along straight lines, with 5 mm of noise.
    fn door_palms() -> Vec<(f32, Vec3)> {
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        let (hinge, start) = (Vec3::new(0.3, -0.3, 0.0), Vec3::new(-0.3, -0.315, 0.02));
        let on_arc = |a: f32| Quat::from_rotation_z(-a) * (start - hinge) + hinge;
        (0..=40)
            .map(|i| {
                let t = i as f32 / 40.0;
                let noise = Vec3::new(rng.random(), rng.random(), rng.random()) * 0.01 - Vec3::splat(0.005);
                let p = if t < 0.1 {
                    start + Vec3::new(-1.0, 0.0, 0.0) * (0.1 - t) * 1.5
                } else if t > 0.9 {
                    on_arc(1.9) + Vec3::new(0.0, -1.0, 0.0) * (t - 0.9) * 1.5
                } else {
                    on_arc(1.9 * (t - 0.1) / 0.8)
                };
                (t, p + noise)
            })
            .collect()
    }

    #[test]
    fn a_palm_on_an_arc_gives_the_doors_hinge_and_angle() {
        let m = HandMotion::fit(&door_palms()).expect("a motion");
        assert_eq!(m.kind, JointKind::Revolute, "{m:?}");
        assert!(m.axis.dot(Vec3::Z).abs() > 0.999, "axis {:?}", m.axis);
        let off_axis =
            (m.origin - Vec3::new(0.3, -0.3, 0.0)) - m.axis * m.axis.dot(m.origin - Vec3::new(0.3, -0.3, 0.0));
        assert!(off_axis.length() < 0.02, "origin {:?} ({m:?})", m.origin);
        assert!((m.amount_at(0.9).abs() - 1.9).abs() < 0.05, "angle at the end {} ({m:?})", m.amount_at(0.9));
        assert!((m.amount_at(0.5).abs() - 0.95).abs() < 0.05, "angle halfway {}", m.amount_at(0.5));
        assert!(m.residual < 0.01, "residual {}", m.residual);
        // The turn as a pose moves the handle's start point along the arc.
        let handle = Vec3::new(-0.3, -0.315, 0.02);
        let at_end = m.pose_about(Vec3::new(0.1, -0.4, 0.0), 0.9).apply(Vec3::new(0.1, -0.4, 0.0), handle);
        let truth = Quat::from_rotation_z(-1.9) * (handle - Vec3::new(0.3, -0.3, 0.0)) + Vec3::new(0.3, -0.3, 0.0);
        assert!(at_end.distance(truth) < 0.03, "{at_end:?} against {truth:?}");
    }

    #[test]
    fn a_short_arc_between_an_arrival_and_a_departure_is_still_an_arc() {
        // The synthetic recording's washer, every third hand sample: the palm arrives
        // along +x, turns the door 60 degrees about (-0.24, -0.27), leaves along -y.
        let xy = [
            (0.311, -0.345),
            (0.198, -0.345),
            (0.194, -0.363),
            (0.185, -0.399),
            (0.173, -0.434),
            (0.158, -0.468),
            (0.14, -0.501),
            (0.119, -0.532),
            (0.096, -0.561),
            (0.07, -0.588),
            (0.043, -0.613),
            (0.013, -0.635),
            (-0.019, -0.655),
            (-0.052, -0.672),
            (-0.086, -0.687),
            (-0.086, -0.799),
        ];
        let track: Vec<(f32, Vec3)> =
            xy.iter().enumerate().map(|(i, &(x, y))| (i as f32 / 15.0, Vec3::new(x, y, -0.02))).collect();
        let m = HandMotion::fit(&track).expect("a motion");
        assert_eq!(m.kind, JointKind::Revolute, "{m:?}");
        let hinge = Vec3::new(-0.24, -0.27, 0.0);
        let off = (m.origin - hinge) - m.axis * m.axis.dot(m.origin - hinge);
        assert!(off.length() < 0.02, "origin {:?}", m.origin);
        let turned = m.amount_at(1.0).abs().max(m.amount_at(14.0 / 15.0).abs());
        assert!((turned - 60f32.to_radians()).abs() < 3f32.to_radians(), "{} deg", turned.to_degrees());
    }

    #[test]
    fn a_motion_stopped_short_holds_still_from_there() {
        let drawer = HandMotion {
            kind: JointKind::Prismatic,
            axis: -Vec3::Y,
            origin: Vec3::ZERO,
            samples: (0..=10).map(|i| (i as f32 / 10.0, 0.042 * i as f32)).collect(),
            radius: 0.0,
            residual: 0.0,
        };
        let stopped = drawer.stopped_at(0.35);
        assert_eq!(stopped.amount_at(0.5), drawer.amount_at(0.5), "before the stop, as the palm");
        assert_eq!((stopped.amount_at(0.9), stopped.amount_at(1.0)), (0.35, 0.35));
        assert!(drawer.amount_at(0.9) > 0.35);
        let c = Vec3::new(0.0, 0.1, 0.2);
        assert!(stopped.pose_about(c, 1.0).translation.distance(Vec3::new(0.0, -0.35, 0.0)) < 1e-6);
        // A turn the other way (negative angles) stops at its own end.
        let door = HandMotion {
            kind: JointKind::Revolute,
            samples: drawer.samples.iter().map(|&(t, a)| (t, -5.0 * a)).collect(),
            ..drawer.clone()
        };
        assert_eq!(door.stopped_at(-1.9).amount_at(1.0), -1.9);
        assert_eq!(door.stopped_at(-1.9).amount_at(0.5), door.amount_at(0.5));
    }

    #[test]
    fn palms_exactly_in_a_plane_still_give_the_arcs_axis() {
        // Hand tracking at one height (a synthetic recording's palm): no noise across the plane.
        let flat: Vec<(f32, Vec3)> = door_palms().into_iter().map(|(t, p)| (t, Vec3::new(p.x, p.y, 0.02))).collect();
        let m = HandMotion::fit(&flat).expect("a motion");
        assert_eq!(m.kind, JointKind::Revolute, "{m:?}");
        assert!(m.axis.dot(Vec3::Z).abs() > 0.9999, "axis {:?}", m.axis);
    }

    #[test]
    fn a_palm_on_a_line_gives_a_slide_and_a_still_palm_nothing() {
        let track: Vec<(f32, Vec3)> = (0..=20)
            .map(|i| (i as f32 / 20.0, Vec3::new(0.1, 0.2, 0.3) + Vec3::new(0.0, -0.35, 0.0) * (i as f32 / 20.0)))
            .collect();
        let m = HandMotion::fit(&track).expect("a motion");
        assert_eq!(m.kind, JointKind::Prismatic);
        assert!(
            (m.axis.dot(Vec3::Y).abs() - 1.0).abs() < 1e-4 && (m.amount_at(1.0).abs() - 0.35).abs() < 1e-3,
            "{m:?}"
        );
        let still: Vec<(f32, Vec3)> =
            (0..=20).map(|i| (i as f32 / 20.0, Vec3::splat(0.001 * (i % 3) as f32))).collect();
        assert!(HandMotion::fit(&still).is_none());
    }
}
