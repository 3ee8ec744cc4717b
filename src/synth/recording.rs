//! A synthetic Aria-like recording for end-to-end tests of the capture stage: one or
//! more benchmark objects ray-cast through the Aria RGB Fisheye624 model along a
//! head-motion path, with a simple skin-coloured hand (palm box, finger and forearm
//! cylinders) that reaches a moving part, moves with it and leaves. With several
//! objects they stand in a row on one floor and the wearer deals with them in turn:
//! walks over (after the first), scans, opens, lets go and looks on, so each object
//! gives one interaction. Written as MPS-style files:
//!
//! ```text
//! OUT/frames/frame_00000.png ...     raw fisheye RGB frames (sensor orientation, not upright)
//! OUT/frames/timestamps.csv          file,timestamp_ns (device clock)
//! OUT/calibration.json               calib_json layout: camera-rgb at native 2880 px,
//!                                    plus ImageWidth/ImageHeight of the frames
//! OUT/mps/slam/closed_loop_trajectory.csv      T_world_device at 1 kHz (MPS columns)
//! OUT/mps/hand_tracking/wrist_and_palm_poses.csv  30 Hz, confidence -1 when no hand
//! OUT/object_region.json             world box swept by the object (a list of boxes,
//!                                    one per object, when there are several)
//! OUT/gt/joints.json, trans.json, start|end/part_k.obj   as in the synthetic benchmark
//!                                    (with several objects: OUT/object_K/gt/..., K from 1)
//! OUT/gt/window.json                 true hand-in / hand-out of each interaction (ns, s, frame)
//! ```
//!
//! The true hand-in is the moment the hand touches the part (its motion starts); the
//! true hand-out is the moment it lets go (the motion ends).

use std::path::Path;
use std::sync::Arc;

use glam::{DQuat, DVec2, DVec3, Mat3, Quat, Vec3};
use rayon::prelude::*;
use serde::Serialize;

use aim_capture::calib::{CameraCalibration, CameraModel, Se3};

use super::geometry::{Aabb, Ray, Shape};
use super::gt::write_ground_truth;
use super::render::Lighting;
use super::scene::{ArticulatedObject, Part, PosedScene, Primitive};
use super::texture::{Material, Pattern};
use crate::error::{write_atomic, Error, Result};
use crate::motion::JointKind;

pub use aim_capture::calib::{ARIA_RGB_PARAMS, ARIA_RGB_T_DEVICE_CAMERA};
/// Hand id in ray hits.
pub const HAND_ID: u32 = 200;
/// Device clock at the first frame.
pub const START_NS: i64 = 10_000_000_000;

/// How to record.
#[derive(Clone, Debug, PartialEq)]
pub struct RecordingConfig {
    /// Frame width and height (square, like Aria RGB); the calibration is rescaled from
    /// 2880 px with an integer factor and a centred crop, as the real sensor modes are.
    pub resolution: u32,
    pub fps: f64,
    /// Seconds of scanning before hand-in.
    pub scan_s: f64,
    /// Seconds of motion (hand on the part).
    pub motion_s: f64,
    /// Seconds after hand-out.
    pub after_s: f64,
    /// Seconds the hand takes to reach the part and to leave it.
    pub approach_s: f64,
    /// Seconds the wearer takes to walk from one object to the next.
    pub walk_s: f64,
    /// Render the hand and write it to the hand-tracking CSV.
    pub hand: bool,
    /// Camera distance from the object centre, metres (default from the object's view hint).
    pub distance: Option<f32>,
}

impl Default for RecordingConfig {
    fn default() -> Self {
        RecordingConfig {
            resolution: 704,
            fps: 15.0,
            scan_s: 3.0,
            motion_s: 2.5,
            after_s: 2.0,
            approach_s: 0.4,
            walk_s: 2.0,
            hand: true,
            distance: None,
        }
    }
}

/// What was written.
#[derive(Clone, Debug, Serialize)]
pub struct RecordingSummary {
    pub objects: Vec<String>,
    pub frames: usize,
    pub resolution: u32,
    pub fps: f64,
    pub hand: bool,
    /// One per object, in time order.
    pub interactions: Vec<InteractionSummary>,
}

/// When the hand held one object's part.
#[derive(Clone, Debug, Serialize)]
pub struct InteractionSummary {
    pub object: String,
    pub touched_part: usize,
    pub hand_in_ns: i64,
    pub hand_out_ns: i64,
    pub hand_in_s: f64,
    pub hand_out_s: f64,
    /// First frame at or after hand-in / hand-out.
    pub hand_in_frame: usize,
    pub hand_out_frame: usize,
}

/// The hand's rigid pose (palm centre, local x towards the forearm) and visibility at time `s`.
#[derive(Clone, Copy, Debug)]
struct HandState {
    pose: glam::Affine3A,
}

/// The scripted interaction: where the hand touches, how it comes and goes.
struct Script {
    t_in: f64,
    t_out: f64,
    approach: f64,
    part: usize,
    /// Hand pose at contact (t = 0 world).
    contact: glam::Affine3A,
    /// Approach and leave directions (unit, world).
    d_in: Vec3,
    d_out: Vec3,
    travel: f32,
    /// +1: right arm, -1: left arm (the side the hand comes from, seen from the head).
    side: f32,
}

fn frame_from_x(x: Vec3) -> Mat3 {
    let up = if x.z.abs() < 0.9 { Vec3::Z } else { Vec3::X };
    let y = up.cross(x).normalize();
    let z = x.cross(y);
    Mat3::from_cols(x, y, z)
}

impl Script {
    fn motion_time(&self, s: f64) -> f32 {
        ((s - self.t_in) / (self.t_out - self.t_in)).clamp(0.0, 1.0) as f32
    }

    fn hand(&self, obj: &ArticulatedObject, s: f64) -> Option<HandState> {
        if s < self.t_in - self.approach || s > self.t_out + self.approach {
            return None;
        }
        let delta = |t: f32| obj.part_transform(self.part, t) * obj.part_transform(self.part, 0.0).inverse();
        let pose = if s < self.t_in {
            let k = ((self.t_in - s) / self.approach) as f32; // 1 -> 0
            glam::Affine3A::from_translation(self.d_in * self.travel * k) * self.contact
        } else if s <= self.t_out {
            delta(self.motion_time(s)) * self.contact
        } else {
            let k = ((s - self.t_out) / self.approach) as f32; // 0 -> 1
            glam::Affine3A::from_translation(self.d_out * self.travel * k) * delta(1.0) * self.contact
        };
        Some(HandState { pose })
    }
}

/// The hand: palm box, four fingers, thumb, forearm (local x towards the elbow).
fn hand_part() -> Arc<Part> {
    let skin = skin();
    let mut prims = vec![Primitive {
        shape: Shape::oriented_box(Vec3::new(0.01, 0.0, 0.0), Vec3::new(0.045, 0.04, 0.013), Mat3::IDENTITY),
        material: skin,
    }];
    for y in [-0.027f32, -0.009, 0.009, 0.027] {
        prims.push(Primitive {
            shape: Shape::cylinder(Vec3::new(-0.065, y, 0.0), Vec3::X, 0.009, 0.06),
            material: skin,
        });
    }
    prims.push(Primitive {
        shape: Shape::cylinder(Vec3::new(-0.01, 0.05, 0.0), Vec3::new(-1.0, 1.0, 0.0), 0.01, 0.06),
        material: skin,
    });
    prims.push(Primitive { shape: Shape::cylinder(Vec3::new(0.08, 0.0, 0.0), Vec3::X, 0.028, 0.08), material: skin });
    Arc::new(Part::new("hand", prims))
}

fn skin() -> Material {
    Material::new(Pattern::Plain, Vec3::new(0.87, 0.63, 0.5), Vec3::new(0.8, 0.55, 0.45), 6.0)
}

/// The arm from the wrist to the shoulder (world frame), so that, as in a real
/// egocentric view, skin always reaches the hand from the edge of the image.
fn arm_part(wrist: Vec3, shoulder: Vec3) -> Arc<Part> {
    let axis = shoulder - wrist;
    let len = axis.length().max(1e-3);
    Arc::new(Part::new(
        "arm",
        vec![Primitive { shape: Shape::cylinder(0.5 * (wrist + shoulder), axis / len, 0.035, len), material: skin() }],
    ))
}

/// World box of the object over its whole motion.
pub fn swept_bounds(obj: &ArticulatedObject) -> Aabb {
    let mut b = obj.posed(0.0).bounds();
    for k in 1..=20 {
        b = b.union(obj.posed(k as f32 / 20.0).bounds());
    }
    b
}

/// Exit distance from `p` (inside `b`) along unit `d`.
fn exit_distance(b: &Aabb, p: Vec3, d: Vec3) -> f32 {
    let mut t = f32::INFINITY;
    for a in 0..3 {
        if d[a] > 1e-6 {
            t = t.min((b.max[a] - p[a]) / d[a]);
        } else if d[a] < -1e-6 {
            t = t.min((b.min[a] - p[a]) / d[a]);
        }
    }
    t.max(0.0)
}

fn plan(obj: &ArticulatedObject, t_in: f64, t_out: f64, approach: f64) -> Result<Script> {
    let joint = obj.joints.first().ok_or_else(|| Error::Config(format!("{} has no joint", obj.name)))?;
    let part = joint.part;
    let az = obj.view.front_azimuth_deg.to_radians();
    let f = Vec3::new(az.cos(), az.sin(), 0.0);
    let e2 = f.cross(Vec3::Z).normalize();
    let posed = obj.posed(0.0);
    let pb = obj.parts[part].bounds().transformed(&obj.part_transform(part, 0.0));
    let c = pb.center();
    let ext = pb.extent();
    let half_w = 0.5 * (ext.x * e2.x.abs() + ext.y * e2.y.abs());
    let mut best: Option<(f32, Vec3)> = None;
    for i in 0..9 {
        for j in 0..9 {
            let a = -0.9 + 1.8 * i as f32 / 8.0;
            let b = -0.9 + 1.8 * j as f32 / 8.0;
            let o = c + e2 * (a * half_w) + Vec3::Z * (b * 0.5 * ext.z) + f * 3.0;
            let Some(hit) = posed.intersect(&Ray::new(o, -f), f32::INFINITY) else { continue };
            if hit.part as usize != part {
                continue;
            }
            let p = hit.position;
            let score = match joint.kind {
                JointKind::Revolute => {
                    let v = p - joint.origin;
                    (v - joint.axis * v.dot(joint.axis)).length()
                }
                JointKind::Prismatic => -(p - c).length(),
            } - 0.3 * (p.z - c.z).abs();
            if best.is_none_or(|(s, _)| score > s) {
                best = Some((score, p));
            }
        }
    }
    let (_, touch) =
        best.ok_or_else(|| Error::Config(format!("{}: the moving part is not visible from the front", obj.name)))?;
    let region = swept_bounds(obj);
    // Approach from whichever side leaves the swept box soonest (short time near the object
    // before contact), never from inside the object.
    let choose = |p: Vec3| -> Vec3 {
        let mut cands = [f, e2, -e2, Vec3::Z];
        cands.sort_by(|a, b| exit_distance(&region, p, *a).total_cmp(&exit_distance(&region, p, *b)));
        cands[0]
    };
    let d_in = choose(touch);
    let palm = touch + f * 0.015;
    let contact = glam::Affine3A::from_mat3_translation(frame_from_x(d_in), palm);
    let delta1 = obj.part_transform(part, 1.0) * obj.part_transform(part, 0.0).inverse();
    let palm1 = delta1.transform_point3(palm);
    let d_out = choose(palm1);
    // The arm on the side the hand comes from, as seen by a camera in front of the object.
    let cam_right = Vec3::Z.cross(f).normalize(); // looking along -f, right = (-f) x z = z x f
    let side = if d_in.dot(cam_right) < 0.0 { -1.0 } else { 1.0 };
    Ok(Script { t_in, t_out, approach, part, contact, d_in, d_out, travel: 0.45, side })
}

/// Where the wearer's head goes: while scanning, a walk along a wide arc in front
/// of the object (out to about 60 degrees each side and up and down, so the scan
/// sees the object from where the rest of the recording will), then a narrow
/// arc while the hand is busy and after.
struct HeadPath {
    target: Vec3,
    distance: f32,
    /// The object's front azimuth (radians).
    front: f64,
    scan_s: f64,
    total: f64,
}

impl HeadPath {
    /// Eye and the point looked at, at time `s` from the start of its scan.
    fn eye_and_look(&self, s: f64) -> (Vec3, Vec3) {
        use std::f64::consts::PI;
        let u = s / self.total;
        // The scan's extra sweep is zero at its start and end, so the path is continuous.
        let scan = (s / self.scan_s).clamp(0.0, 1.0);
        let sweep = SCAN_SWEEP * (2.0 * PI * scan).sin();
        let az = self.front + 0.44 * (PI * (2.0 * u - 0.5)).sin() + sweep;
        let el = (18.0 + 6.0 * (2.0 * PI * 1.7 * u).sin() + SCAN_RISE_DEG * (PI * scan).sin()).to_radians();
        let (az, el) = (az as f32, el as f32);
        let bob = 0.01 * (2.0 * PI * 1.9 * s).sin() as f32;
        let eye =
            self.target + self.distance * Vec3::new(el.cos() * az.cos(), el.cos() * az.sin(), el.sin()) + Vec3::Z * bob;
        let look = self.target + Vec3::new(0.03 * (3.1 * s).sin() as f32, 0.0, 0.03 * (2.3 * s).cos() as f32);
        (eye, look)
    }
}

/// An upright OpenCV camera at `eye` looking at `look` (camera to world rotation).
fn look_at(eye: Vec3, look: Vec3) -> Mat3 {
    let z = (look - eye).normalize();
    let x = z.cross(Vec3::Z).normalize();
    let y = z.cross(x);
    Mat3::from_cols(x, y, z)
}

/// One object's part of a recording: the walk to it (after the first), its scan,
/// the motion and the time after; times in seconds from the recording's start.
struct Segment {
    object: ArticulatedObject,
    head: HeadPath,
    start: f64,
    walk: f64,
    script: Script,
}

impl Segment {
    /// When its scan starts.
    fn scan_start(&self) -> f64 {
        self.start + self.walk
    }

    fn end(&self) -> f64 {
        self.scan_start() + self.head.total
    }
}

/// The whole recording: the objects' segments one after another.
struct Choreography {
    segments: Vec<Segment>,
}

impl Choreography {
    /// The segment under way at time `s`.
    fn segment_at(&self, s: f64) -> usize {
        self.segments.iter().rposition(|g| g.start <= s).unwrap_or(0)
    }

    fn duration(&self) -> f64 {
        self.segments.last().map_or(0.0, Segment::end)
    }

    /// Head pose (OpenCV camera, upright) at time `s`: on a segment's own path, or
    /// walking from where the last one ended to where this one's scan starts.
    fn camera(&self, s: f64) -> (Vec3, Mat3) {
        let k = self.segment_at(s);
        let g = &self.segments[k];
        let (eye, look) = if s < g.scan_start() && k > 0 {
            let prev = &self.segments[k - 1];
            let (e0, l0) = prev.head.eye_and_look(prev.head.total);
            let (e1, l1) = g.head.eye_and_look(0.0);
            // Smooth start and stop.
            let w = ((s - g.start) / g.walk).clamp(0.0, 1.0);
            let w = (w * w * (3.0 - 2.0 * w)) as f32;
            (e0.lerp(e1, w), l0.lerp(l1, w))
        } else {
            g.head.eye_and_look(s - g.scan_start())
        };
        (eye, look_at(eye, look))
    }

    /// Raw Aria RGB camera-to-world at time `s` (sensor mounted 90 degrees from
    /// upright) and the device pose.
    fn poses(&self, s: f64) -> (Se3, Se3) {
        let (eye, r_upright) = self.camera(s);
        // p_upright = Rz(90) p_raw.
        let r_raw = r_upright * Mat3::from_rotation_z(std::f32::consts::FRAC_PI_2);
        let t_world_camera = Se3::new(to_dquat(r_raw), eye.as_dvec3());
        let (t, q) = ARIA_RGB_T_DEVICE_CAMERA;
        let t_device_camera = Se3::new(DQuat::from_xyzw(q[1], q[2], q[3], q[0]), DVec3::from_array(t));
        (t_world_camera, t_world_camera.compose(&t_device_camera.inverse()))
    }

    /// Every object at its state at time `s` (before its interaction at rest, after it
    /// where the hand left it), without the hand.
    fn scene(&self, s: f64) -> PosedScene {
        let mut scene = PosedScene::default();
        for g in &self.segments {
            let t = g.script.motion_time(s);
            for (i, part) in g.object.parts.iter().enumerate() {
                scene.push(part.clone(), i as u32, g.object.part_transform(i, t));
            }
        }
        scene
    }

    /// The hand at time `s`, if one is out, with the segment it belongs to.
    fn hand(&self, s: f64) -> Option<(HandState, &Script)> {
        self.segments.iter().find_map(|g| g.script.hand(&g.object, s).map(|h| (h, &g.script)))
    }

    /// Whether `s` falls in a walk or a scan, before the segment's hand-in.
    fn scanning(&self, s: f64) -> bool {
        self.segments.iter().any(|g| s >= g.start && s < g.script.t_in)
    }

    /// The segments laid out: each object placed in a row (along x, on the first
    /// one's floor, `OBJECT_GAP` apart), its window in time after the previous one.
    fn plan(objects: &[ArticulatedObject], cfg: &RecordingConfig) -> Result<Self> {
        let mut segments: Vec<Segment> = Vec::new();
        let mut start = 0.0;
        let mut row_end: Option<f32> = None;
        let floor = objects.first().map_or(0.0, |o| swept_bounds(o).min.z);
        for obj in objects {
            let swept = swept_bounds(obj);
            let offset = match row_end {
                None => Vec3::ZERO,
                Some(x) => {
                    let rest = obj.posed(0.0).bounds().center();
                    Vec3::new(x + OBJECT_GAP - swept.min.x, -rest.y, floor - swept.min.z)
                }
            };
            let object = obj.translated(offset);
            let swept = swept_bounds(&object);
            row_end = Some(swept.max.x);
            let walk = if segments.is_empty() { 0.0 } else { cfg.walk_s };
            let t_in = start + walk + cfg.scan_s;
            let script = plan(&object, t_in, t_in + cfg.motion_s, cfg.approach_s)?;
            let head = HeadPath {
                target: object.posed(0.0).bounds().center(),
                distance: cfg.distance.unwrap_or(object.view.distance * 0.6),
                front: f64::from(object.view.front_azimuth_deg.to_radians()),
                scan_s: cfg.scan_s,
                total: cfg.scan_s + cfg.motion_s + cfg.after_s,
            };
            let segment = Segment { object, head, start, walk, script };
            start = segment.end();
            segments.push(segment);
        }
        Ok(Choreography { segments })
    }
}

/// Space between neighbouring objects' swept boxes (metres).
const OBJECT_GAP: f32 = 1.2;

/// The scan's sweep beyond the narrow arc, each way (radians).
const SCAN_SWEEP: f64 = 0.6;
/// How much higher the head goes mid-scan (degrees).
const SCAN_RISE_DEG: f64 = 12.0;

fn to_dquat(m: Mat3) -> DQuat {
    let q = Quat::from_mat3(&m).normalize();
    DQuat::from_xyzw(q.x as f64, q.y as f64, q.z as f64, q.w as f64).normalize()
}

/// The RGB calibration at native resolution, as Aria stores it.
pub fn aria_rgb_native() -> CameraCalibration {
    let (t, q) = ARIA_RGB_T_DEVICE_CAMERA;
    CameraCalibration {
        label: "camera-rgb".into(),
        model: CameraModel::Fisheye624(ARIA_RGB_PARAMS),
        width: 2880,
        height: 2880,
        t_device_camera: Se3::new(DQuat::from_xyzw(q[1], q[2], q[3], q[0]), DVec3::from_array(t)),
        max_theta: 1.4,
        valid_radius: aim_capture::calib::aria_valid_radius("camera-rgb"),
    }
}

fn background(dir: Vec3, origin: Vec3, floor_z: f32) -> Vec3 {
    if dir.z < -1e-4 {
        let t = (floor_z - origin.z) / dir.z;
        if t > 0.0 {
            let p = origin + dir * t;
            let check = ((p.x * 2.0).floor() + (p.y * 2.0).floor()) as i32 & 1;
            let fade = (-t * 0.15).exp();
            let c = if check == 0 { 0.42 } else { 0.5 };
            return Vec3::new(c, c * 1.02, c * 1.08) * (0.6 + 0.4 * fade);
        }
    }
    Vec3::new(0.32, 0.36, 0.42) + Vec3::splat(0.08 * dir.z.clamp(-1.0, 1.0))
}

fn render_fisheye(
    scene: &PosedScene,
    cam: &CameraCalibration,
    t_world_camera: &Se3,
    floor_z: f32,
    lighting: &Lighting,
) -> image::RgbImage {
    let (w, h) = (cam.width, cam.height);
    let rot = t_world_camera.rotation.as_quat();
    let origin = t_world_camera.translation.as_vec3();
    let mut buf = vec![0u8; (w * h * 3) as usize];
    buf.par_chunks_mut(w as usize * 3).enumerate().for_each(|(v, row)| {
        for u in 0..w as usize {
            let Some(ray_cam) = cam.model.unproject(DVec2::new(u as f64, v as f64)) else { continue };
            let theta = (ray_cam.x * ray_cam.x + ray_cam.y * ray_cam.y).sqrt().atan();
            if theta > cam.max_theta {
                continue;
            }
            let dir = (rot * ray_cam.as_vec3()).normalize();
            let ray = Ray::new(origin, dir);
            let c = match scene.intersect(&ray, f32::INFINITY) {
                Some(hit) => lighting.shade(&hit),
                None => background(dir, origin, floor_z),
            };
            for k in 0..3 {
                row[u * 3 + k] = (c[k].clamp(0.0, 1.0) * 255.0 + 0.5) as u8;
            }
        }
    });
    image::RgbImage::from_raw(w, h, buf).unwrap_or_default()
}

/// Points on what the scans see (the objects as they stand then, and the floor), as MPS's
/// semidense_points.csv.gz holds them: each the surface along a random ray of a
/// scan frame, displaced along the ray by noise of `SEMIDENSE_DIST_STD` of its
/// distance (the SLAM's depth uncertainty grows with distance), with that
/// standard deviation written beside it.
fn write_semidense_points(
    plan: &Choreography,
    cam: &CameraCalibration,
    cfg: &RecordingConfig,
    floor_z: f32,
    dir: &Path,
) -> Result<()> {
    use rand::{Rng, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(SEMIDENSE_SEED);
    let mut csv = String::from("uid,graph_uid,px_world,py_world,pz_world,inv_dist_std,dist_std\n");
    let frames = (plan.duration() * cfg.fps).floor() as usize;
    let mut uid = 0u64;
    for k in 0..frames {
        let s = k as f64 / cfg.fps;
        if !plan.scanning(s) {
            continue;
        }
        let scene = plan.scene(s);
        let (t_wc, _) = plan.poses(s);
        let (rot, origin) = (t_wc.rotation.as_quat(), t_wc.translation.as_vec3());
        for _ in 0..SEMIDENSE_RAYS_PER_FRAME {
            let pixel = DVec2::new(rng.random_range(0.0..cam.width as f64), rng.random_range(0.0..cam.height as f64));
            let Some(ray_cam) = cam.model.unproject(pixel) else { continue };
            let dir = (rot * ray_cam.as_vec3()).normalize();
            let depth = match scene.intersect(&Ray::new(origin, dir), f32::INFINITY) {
                Some(hit) => hit.t,
                None if dir.z < -1e-3 => (floor_z - origin.z) / dir.z,
                None => continue,
            };
            if !(depth > 0.0 && depth < SEMIDENSE_MAX_DISTANCE) {
                continue;
            }
            let std = SEMIDENSE_DIST_STD * depth;
            let noise: f32 = rng.sample::<f32, _>(rand_distr::StandardNormal) * std;
            let p = origin + dir * (depth + noise);
            csv.push_str(&format!(
                "{uid},0,{:.6},{:.6},{:.6},{:.6},{:.6}\n",
                p.x,
                p.y,
                p.z,
                1.0 / (depth * depth) * std,
                std
            ));
            uid += 1;
        }
    }
    let mut gz = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
    std::io::Write::write_all(&mut gz, csv.as_bytes()).map_err(|e| Error::Other(format!("gzip: {e}")))?;
    let bytes = gz.finish().map_err(|e| Error::Other(format!("gzip: {e}")))?;
    write_atomic(&dir.join("semidense_points.csv.gz"), &bytes)
}

/// Rays cast per scan frame for the semidense points.
const SEMIDENSE_RAYS_PER_FRAME: usize = 400;
/// Depth noise of a semidense point, relative to its distance.
const SEMIDENSE_DIST_STD: f32 = 0.004;
/// Farther surfaces give no point (SLAM tracks little beyond a room's size).
const SEMIDENSE_MAX_DISTANCE: f32 = 6.0;
const SEMIDENSE_SEED: u64 = 17;

fn se3_row(t_us: i64, p: &Se3) -> String {
    let (t, q) = (p.translation, p.rotation);
    let mut s = format!(
        "synthetic,{t_us},{},{:.9},{:.9},{:.9},{:.12},{:.12},{:.12},{:.12}",
        t_us * 1000,
        t.x,
        t.y,
        t.z,
        q.x,
        q.y,
        q.z,
        q.w
    );
    s.push_str(",0,0,0,0,0,0,0,0,-9.81,1,0,0,0,0,0,0,0,1\n");
    s
}

/// Write a synthetic Aria-like recording of `objects` (one interaction each, in
/// order) into `out`.
pub fn write_recording(objects: &[ArticulatedObject], cfg: &RecordingConfig, out: &Path) -> Result<RecordingSummary> {
    if !(cfg.fps > 0.0 && cfg.scan_s > cfg.approach_s && cfg.motion_s > 0.0 && cfg.after_s > cfg.approach_s) {
        return Err(Error::Config("recording needs fps > 0, scan and after longer than the approach".into()));
    }
    let walks = cfg.walk_s > 0.0;
    if objects.is_empty() || (objects.len() > 1 && !walks) {
        return Err(Error::Config("recording needs an object (and a walk between several)".into()));
    }
    for d in ["frames", "mps/slam", "mps/hand_tracking", "gt"] {
        std::fs::create_dir_all(out.join(d)).map_err(|e| Error::io(out.join(d), e))?;
    }
    let native = aria_rgb_native();
    let cam = native.rescaled_to(cfg.resolution, cfg.resolution).map_err(Error::Config)?;
    let plan = Choreography::plan(objects, cfg)?;
    let total = plan.duration();
    let regions: Vec<Aabb> = plan.segments.iter().map(|g| swept_bounds(&g.object)).collect();
    let floor_z = regions[0].min.z;
    let hand = hand_part();
    let lighting = Lighting::default();

    // Frames.
    let n = (total * cfg.fps).floor() as usize;
    let mut ts_csv = String::from("file,timestamp_ns\n");
    for k in 0..n {
        let s = k as f64 / cfg.fps;
        let (t_wc, _) = plan.poses(s);
        let mut scene = plan.scene(s);
        if cfg.hand {
            if let Some((h, script)) = plan.hand(s) {
                scene.push(hand.clone(), HAND_ID, h.pose);
                let (eye, r_up) = plan.camera(s);
                let shoulder = eye + r_up * Vec3::new(0.2 * script.side, 0.3, -0.05);
                let wrist = h.pose.transform_point3(Vec3::new(0.1, 0.0, 0.0));
                scene.push(arm_part(wrist, shoulder), HAND_ID, glam::Affine3A::IDENTITY);
            }
        }
        let img = render_fisheye(&scene, &cam, &t_wc, floor_z, &lighting);
        let name = format!("frame_{k:05}.png");
        let mut bytes = Vec::new();
        image::DynamicImage::ImageRgb8(img)
            .write_to(&mut std::io::Cursor::new(&mut bytes), image::ImageFormat::Png)
            .map_err(|e| Error::Other(format!("encoding {name}: {e}")))?;
        write_atomic(&out.join("frames").join(&name), &bytes)?;
        ts_csv.push_str(&format!("{name},{}\n", START_NS + (s * 1e9).round() as i64));
    }
    write_atomic(&out.join("frames/timestamps.csv"), ts_csv.as_bytes())?;

    // Calibration (calib_json layout, native resolution) + frame size.
    let (t, q) = ARIA_RGB_T_DEVICE_CAMERA;
    let calib = serde_json::json!({
        "CalibrationSource": "aim synth-recording (Aria RGB factory calibration of the public sample)",
        "CameraCalibrations": [{
            "Calibrated": true,
            "Label": "camera-rgb",
            "Projection": {"Name": "FisheyeRadTanThinPrism", "Description": "see FisheyeRadTanThinPrism.h", "Params": ARIA_RGB_PARAMS.to_vec()},
            "T_Device_Camera": {"Translation": t.to_vec(), "UnitQuaternion": [q[0], [q[1], q[2], q[3]]]}
        }],
        "ImageWidth": cfg.resolution,
        "ImageHeight": cfg.resolution,
    });
    write_atomic(&out.join("calibration.json"), &serde_json::to_vec_pretty(&calib).unwrap_or_default())?;

    // Trajectory at 1 kHz, a little beyond the frames at both ends.
    let mut traj = String::from(
        "graph_uid,tracking_timestamp_us,utc_timestamp_ns,tx_world_device,ty_world_device,tz_world_device,qx_world_device,qy_world_device,qz_world_device,qw_world_device,device_linear_velocity_x_device,device_linear_velocity_y_device,device_linear_velocity_z_device,angular_velocity_x_device,angular_velocity_y_device,angular_velocity_z_device,gravity_x_world,gravity_y_world,gravity_z_world,quality_score,geo_available,tx_ecef_device,ty_ecef_device,tz_ecef_device,qx_ecef_device,qy_ecef_device,qz_ecef_device,qw_ecef_device\n",
    );
    let start_us = START_NS / 1000;
    let steps = ((total + 0.1) * 1000.0) as i64;
    for k in -50..steps {
        let s = k as f64 / 1000.0;
        let (_, t_wd) = plan.poses(s);
        traj.push_str(&se3_row(start_us + k * 1000, &t_wd));
    }
    write_atomic(&out.join("mps/slam/closed_loop_trajectory.csv"), traj.as_bytes())?;

    // Hand tracking at 30 Hz (right hand; left always missing).
    let mut ht = String::from(
        "tracking_timestamp_us,left_tracking_confidence,tx_left_wrist_device,ty_left_wrist_device,tz_left_wrist_device,tx_left_palm_device,ty_left_palm_device,tz_left_palm_device,right_tracking_confidence,tx_right_wrist_device,ty_right_wrist_device,tz_right_wrist_device,tx_right_palm_device,ty_right_palm_device,tz_right_palm_device\n",
    );
    let hsteps = (total * 30.0).ceil() as i64;
    for k in 0..=hsteps {
        let s = k as f64 / 30.0;
        let t_us = start_us + (s * 1e6).round() as i64;
        let hand_now = if cfg.hand { plan.hand(s) } else { None };
        match hand_now {
            Some((h, _)) => {
                let (_, t_wd) = plan.poses(s);
                let t_dw = t_wd.inverse();
                let palm = t_dw.transform_point(h.pose.transform_point3(Vec3::ZERO).as_dvec3());
                let wrist = t_dw.transform_point(h.pose.transform_point3(Vec3::new(0.07, 0.0, 0.0)).as_dvec3());
                ht.push_str(&format!(
                    "{t_us},-1,0,0,0,0,0,0,0.97,{:.6},{:.6},{:.6},{:.6},{:.6},{:.6}\n",
                    wrist.x, wrist.y, wrist.z, palm.x, palm.y, palm.z
                ));
            }
            None => ht.push_str(&format!("{t_us},-1,0,0,0,0,0,0,-1,0,0,0,0,0,0\n")),
        }
    }
    write_atomic(&out.join("mps/hand_tracking/wrist_and_palm_poses.csv"), ht.as_bytes())?;

    write_semidense_points(&plan, &cam, cfg, floor_z, &out.join("mps/slam"))?;

    let region_json = |b: &Aabb| serde_json::json!({ "min": b.min.to_array(), "max": b.max.to_array() });
    let region_json = match regions.as_slice() {
        [one] => region_json(one),
        several => serde_json::Value::Array(several.iter().map(region_json).collect()),
    };
    write_atomic(&out.join("object_region.json"), &serde_json::to_vec_pretty(&region_json).unwrap_or_default())?;

    if let [one] = plan.segments.as_slice() {
        write_ground_truth(&one.object, &out.join("gt"))?;
    } else {
        for (k, g) in plan.segments.iter().enumerate() {
            write_ground_truth(&g.object, &object_ground_truth(out, k).join("gt"))?;
        }
    }
    let frame_at = |t: f64| ((t * cfg.fps - 1e-9).ceil().max(0.0)) as usize;
    let interactions = plan
        .segments
        .iter()
        .map(|g| InteractionSummary {
            object: g.object.name.clone(),
            touched_part: g.script.part,
            hand_in_ns: START_NS + (g.script.t_in * 1e9).round() as i64,
            hand_out_ns: START_NS + (g.script.t_out * 1e9).round() as i64,
            hand_in_s: START_NS as f64 * 1e-9 + g.script.t_in,
            hand_out_s: START_NS as f64 * 1e-9 + g.script.t_out,
            hand_in_frame: frame_at(g.script.t_in),
            hand_out_frame: frame_at(g.script.t_out),
        })
        .collect();
    let summary = RecordingSummary {
        objects: objects.iter().map(|o| o.name.clone()).collect(),
        frames: n,
        resolution: cfg.resolution,
        fps: cfg.fps,
        hand: cfg.hand,
        interactions,
    };
    let window = serde_json::to_vec_pretty(&summary).unwrap_or_default();
    write_atomic(&out.join("gt/window.json"), &window)?;
    Ok(summary)
}

/// Where a recording of several objects keeps object `k`'s (0-based) ground truth:
/// a folder with gt/ inside, as a synthetic dataset has.
pub fn object_ground_truth(recording: &Path, k: usize) -> std::path::PathBuf {
    recording.join(format!("object_{}", k + 1))
}
