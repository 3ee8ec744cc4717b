//! The twin for simulators: URDF (ROS, PyBullet, Isaac Sim, SAPIEN, Genesis,
//! MuJoCo's importer) and MJCF (MuJoCo). Both describe one fixed base and one
//! revolute/hinge or prismatic/slide joint per moving part, each part with its
//! visual mesh, a convex collision hull and inertial properties of that hull.
//!
//! Frames: a moving part's frame sits at its joint's origin (URDF puts the child
//! link's frame at the joint origin), axes parallel to the world's; the meshes,
//! written in world coordinates at the start state, are placed with the opposite
//! offset. Joint value 0 is the start state; the limits span the observed motion.

use std::fmt::Write as _;

use super::physics::{ExportConfig, Inertial};
use super::{part_name, Articulation, PartEntry};
use crate::motion::JointKind;
use crate::synth::JointRecord;

fn xyz(a: [f32; 3]) -> String {
    format!("{} {} {}", a[0], a[1], a[2])
}

/// The offset of part `p`'s frame from the world's: its joint's origin (the base: 0).
fn frame_origin(art: &Articulation, p: &PartEntry) -> [f32; 3] {
    art.joints.iter().find(|j| j.part == p.id).map_or([0.0; 3], |j| j.origin)
}

fn minus(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

/// A part's inertial properties; a moving part without a hull (no mesh) gets a
/// token gram at its frame, since simulators refuse massless moving bodies.
fn part_inertial(art: &Articulation, p: &PartEntry) -> Option<Inertial> {
    let moving = art.joints.iter().any(|j| j.part == p.id);
    p.inertial.or_else(|| {
        moving.then(|| Inertial { mass: 1e-3, com: frame_origin(art, p), inertia: [1e-6, 1e-6, 1e-6, 0.0, 0.0, 0.0] })
    })
}

/// A joint's limits: the observed range, lower first.
pub fn limits(j: &JointRecord) -> (f32, f32) {
    (j.range[0].min(j.range[1]), j.range[0].max(j.range[1]))
}

/// The URDF of a twin (mesh paths relative to the twin folder, where it is written).
pub fn urdf(art: &Articulation, cfg: &ExportConfig) -> String {
    let mut s = String::from("<?xml version=\"1.0\"?>\n<robot name=\"aim_twin\">\n");
    // MuJoCo's URDF importer: keep the mesh paths and the visual geometry.
    s.push_str("  <mujoco>\n    <compiler strippath=\"false\" discardvisual=\"false\" balanceinertia=\"true\"/>\n  </mujoco>\n");
    for p in &art.parts {
        let offset = minus([0.0; 3], frame_origin(art, p));
        let _ = writeln!(s, "  <link name=\"{}\">", p.name);
        if let Some(mesh) = &p.mesh {
            let _ = writeln!(
                s,
                "    <visual>\n      <origin xyz=\"{}\" rpy=\"0 0 0\"/>\n      <geometry><mesh filename=\"{mesh}\"/></geometry>\n    </visual>",
                xyz(offset)
            );
        }
        if let Some(hull) = &p.collision {
            let _ = writeln!(
                s,
                "    <collision>\n      <origin xyz=\"{}\" rpy=\"0 0 0\"/>\n      <geometry><mesh filename=\"{hull}\"/></geometry>\n    </collision>",
                xyz(offset)
            );
        }
        if let Some(i) = &part_inertial(art, p) {
            let com = minus(i.com, frame_origin(art, p));
            let [ixx, iyy, izz, ixy, ixz, iyz] = i.inertia;
            let _ = writeln!(
                s,
                "    <inertial>\n      <origin xyz=\"{}\" rpy=\"0 0 0\"/>\n      <mass value=\"{}\"/>\n      \
                 <inertia ixx=\"{ixx}\" ixy=\"{ixy}\" ixz=\"{ixz}\" iyy=\"{iyy}\" iyz=\"{iyz}\" izz=\"{izz}\"/>\n    </inertial>",
                xyz(com),
                i.mass
            );
        }
        s.push_str("  </link>\n");
    }
    for j in &art.joints {
        let kind = match j.kind {
            JointKind::Revolute => "revolute",
            JointKind::Prismatic => "prismatic",
        };
        let (lo, hi) = limits(j);
        let _ = write!(
            s,
            "  <joint name=\"joint_{part}\" type=\"{kind}\">\n    <parent link=\"{parent}\"/>\n    <child link=\"{child}\"/>\n    \
             <origin xyz=\"{origin}\" rpy=\"0 0 0\"/>\n    <axis xyz=\"{axis}\"/>\n    \
             <limit lower=\"{lo}\" upper=\"{hi}\" effort=\"{effort}\" velocity=\"{velocity}\"/>\n  </joint>\n",
            part = j.part,
            parent = part_name(j.parent),
            child = part_name(j.part),
            origin = xyz(frame_origin_of_joint(art, j)),
            axis = xyz(j.axis),
            effort = cfg.effort,
            velocity = cfg.velocity,
        );
    }
    s.push_str("</robot>\n");
    s
}

/// A joint's origin relative to its parent's frame.
fn frame_origin_of_joint(art: &Articulation, j: &JointRecord) -> [f32; 3] {
    let parent = art.parts.iter().find(|p| p.id == j.parent).map_or([0.0; 3], |p| frame_origin(art, p));
    minus(j.origin, parent)
}

fn mjcf_inertial(i: &Inertial, frame: [f32; 3]) -> String {
    let [ixx, iyy, izz, ixy, ixz, iyz] = i.inertia;
    format!(
        "<inertial pos=\"{}\" mass=\"{}\" fullinertia=\"{ixx} {iyy} {izz} {ixy} {ixz} {iyz}\"/>",
        xyz(minus(i.com, frame)),
        i.mass
    )
}

/// The MJCF (MuJoCo) model of a twin, mesh paths relative to the twin folder.
/// Visual meshes are geoms of group 1 without contacts, hulls of group 3 with.
pub fn mjcf(art: &Articulation, cfg: &ExportConfig) -> String {
    let mut s = String::from("<mujoco model=\"aim_twin\">\n  <compiler angle=\"radian\" meshdir=\".\"/>\n  <asset>\n");
    for p in &art.parts {
        if let Some(mesh) = &p.mesh {
            let _ = writeln!(s, "    <mesh name=\"{}_visual\" file=\"{mesh}\"/>", p.name);
        }
        if let Some(hull) = &p.collision {
            let _ = writeln!(s, "    <mesh name=\"{}_collision\" file=\"{hull}\"/>", p.name);
        }
    }
    s.push_str("  </asset>\n  <worldbody>\n");
    let geoms = |s: &mut String, p: &PartEntry, indent: &str| {
        let offset = xyz(minus([0.0; 3], frame_origin(art, p)));
        if p.mesh.is_some() {
            let _ = writeln!(
                s,
                "{indent}<geom name=\"{n}_visual\" type=\"mesh\" mesh=\"{n}_visual\" pos=\"{offset}\" group=\"1\" contype=\"0\" conaffinity=\"0\" mass=\"0\"/>",
                n = p.name
            );
        }
        if p.collision.is_some() {
            let _ = writeln!(
                s,
                "{indent}<geom name=\"{n}_collision\" type=\"mesh\" mesh=\"{n}_collision\" pos=\"{offset}\" group=\"3\" mass=\"0\"/>",
                n = p.name
            );
        }
    };
    let Some(base) = art.parts.first() else {
        s.push_str("  </worldbody>\n</mujoco>\n");
        return s;
    };
    let _ = writeln!(s, "    <body name=\"{}\">", base.name);
    if let Some(i) = &base.inertial {
        let _ = writeln!(s, "      {}", mjcf_inertial(i, [0.0; 3]));
    }
    geoms(&mut s, base, "      ");
    for j in art.joints.iter().filter(|j| j.parent == base.id) {
        let Some(p) = art.parts.iter().find(|p| p.id == j.part) else { continue };
        let (kind, (lo, hi)) = match j.kind {
            JointKind::Revolute => ("hinge", limits(j)),
            JointKind::Prismatic => ("slide", limits(j)),
        };
        let _ = writeln!(s, "      <body name=\"{}\" pos=\"{}\">", p.name, xyz(j.origin));
        if let Some(i) = &part_inertial(art, p) {
            let _ = writeln!(s, "        {}", mjcf_inertial(i, j.origin));
        }
        let _ = writeln!(
            s,
            "        <joint name=\"joint_{}\" type=\"{kind}\" axis=\"{}\" limited=\"true\" range=\"{lo} {hi}\" actuatorfrcrange=\"{} {}\" actuatorfrclimited=\"true\"/>",
            j.part,
            xyz(j.axis),
            -cfg.effort,
            cfg.effort
        );
        geoms(&mut s, p, "        ");
        s.push_str("      </body>\n");
    }
    s.push_str("    </body>\n  </worldbody>\n</mujoco>\n");
    s
}
