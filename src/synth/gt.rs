//! Ground truth: `gt/joints.json`, the AiM/PARIS-style `gt/trans.json`, and per-part
//! OBJ meshes at the start and end states.
//!
//! `joints.json`:
//! ```json
//! {"object": "fridge",
//!  "joints": [{"part": 1, "type": "revolute", "axis": [0,0,1], "origin": [0.3,-0.3,0],
//!              "range": [0.0, 1.9199], "parent": 0}],
//!  "parts": [{"id": 0, "name": "body", "mesh_start": "start/part_0.obj", "mesh_end": "end/part_0.obj"}, ...]}
//! ```
//! Ranges are radians (revolute) or metres (prismatic); `range[0]` is the state at t = 0.
//! A part at motion time t is its start-state mesh moved by
//! `T(q(t)) * T(q(0))^-1`, with `T(q)` the rotation by `q` about the axis line (or the
//! translation `q * axis`) and `q(t) = range[0] + t * (range[1] - range[0])`.
//!
//! `trans.json` follows PARIS (`trans_info` with `axis.o`, `axis.d`, `type`
//! rotate|translate, `rotate.l/r` in degrees, `translate.l/r` in metres). For a single
//! moving part `trans_info` is one object, exactly as PARIS reads it; for several it is a
//! list of such objects, each with its `part` id.
//!
//! Meshes are unions of closed components (boxes, 64-sided cylinders, prisms), which may
//! overlap inside a part; voxelise them by inside-any-component, not by ray parity.

use std::path::Path;

use glam::{Affine3A, Vec3};
use serde::{Deserialize, Serialize};

use super::scene::{ArticulatedObject, Joint};
use crate::error::{write_atomic, Error, Result};
use crate::motion::JointKind;

/// Cylinder tessellation used for the ground-truth meshes.
pub const GT_CYLINDER_SEGMENTS: u32 = 64;

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct JointRecord {
    pub part: usize,
    #[serde(rename = "type")]
    pub kind: JointKind,
    pub axis: [f32; 3],
    pub origin: [f32; 3],
    pub range: [f32; 2],
    pub parent: usize,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PartRecord {
    pub id: usize,
    pub name: String,
    #[serde(default)]
    pub mesh_start: Option<String>,
    #[serde(default)]
    pub mesh_end: Option<String>,
}

/// The contents of `gt/joints.json`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct JointsFile {
    #[serde(default)]
    pub object: String,
    pub joints: Vec<JointRecord>,
    pub parts: Vec<PartRecord>,
}

impl JointRecord {
    pub fn from_joint(j: &Joint) -> Self {
        Self {
            part: j.part,
            kind: j.kind,
            axis: j.axis.to_array(),
            origin: j.origin.to_array(),
            range: j.range,
            parent: j.parent,
        }
    }

    pub fn to_joint(&self) -> Joint {
        Joint {
            part: self.part,
            kind: self.kind,
            axis: Vec3::from(self.axis).normalize_or_zero(),
            origin: Vec3::from(self.origin),
            range: self.range,
            parent: self.parent,
        }
    }

    /// Motion of the part from its start state (t = 0) to time `t`, in world coordinates.
    pub fn motion_from_start(&self, t: f32) -> Affine3A {
        self.motion_to_state(self.to_joint().state(t))
    }

    /// Motion of the part from its start state (`range[0]`) to joint state `q`
    /// (radians or metres), in world coordinates.
    pub fn motion_to_state(&self, q: f32) -> Affine3A {
        let j = self.to_joint();
        j.transform_at_state(q) * j.transform_at_state(self.range[0]).inverse()
    }
}

impl JointsFile {
    pub fn from_object(object: &ArticulatedObject) -> Self {
        Self {
            object: object.name.clone(),
            joints: object.joints.iter().map(JointRecord::from_joint).collect(),
            parts: object
                .parts
                .iter()
                .enumerate()
                .map(|(id, p)| PartRecord {
                    id,
                    name: p.name.clone(),
                    mesh_start: Some(format!("start/part_{id}.obj")),
                    mesh_end: Some(format!("end/part_{id}.obj")),
                })
                .collect(),
        }
    }

    /// Read and validate a joints.json.
    pub fn load(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        let f: JointsFile =
            serde_json::from_str(&text).map_err(|e| Error::bad_file(path, format!("not a joints file: {e}")))?;
        validate_joints(path, &f.joints, &f.parts.iter().map(|p| p.id).collect::<Vec<_>>())?;
        Ok(f)
    }
}

/// Check joint records read from `path`: unit axes, and parts among `part_ids`.
pub fn validate_joints(path: &Path, joints: &[JointRecord], part_ids: &[usize]) -> Result<()> {
    for j in joints {
        let a = Vec3::from(j.axis);
        if !a.is_finite() || (a.length() - 1.0).abs() > 1e-3 {
            return Err(Error::bad_file(path, format!("joint of part {}: axis {a} is not a unit vector", j.part)));
        }
        if !part_ids.contains(&j.part) {
            return Err(Error::bad_file(path, format!("joint refers to unknown part {}", j.part)));
        }
        if !(j.range[0].is_finite() && j.range[1].is_finite() && Vec3::from(j.origin).is_finite()) {
            return Err(Error::bad_file(path, format!("joint of part {}: non-finite origin or range", j.part)));
        }
    }
    Ok(())
}

#[derive(Serialize)]
struct LR {
    l: f32,
    r: f32,
}

#[derive(Serialize)]
struct AxisOD {
    o: [f32; 3],
    d: [f32; 3],
}

#[derive(Serialize)]
struct TransInfo {
    #[serde(skip_serializing_if = "Option::is_none")]
    part: Option<usize>,
    axis: AxisOD,
    #[serde(rename = "type")]
    kind: &'static str,
    rotate: LR,
    translate: LR,
}

fn trans_info(j: &Joint, with_part: bool) -> TransInfo {
    let (rotate, translate, kind) = match j.kind {
        JointKind::Revolute => {
            (LR { l: j.range[0].to_degrees(), r: j.range[1].to_degrees() }, LR { l: 0.0, r: 0.0 }, "rotate")
        }
        JointKind::Prismatic => (LR { l: 0.0, r: 0.0 }, LR { l: j.range[0], r: j.range[1] }, "translate"),
    };
    TransInfo {
        part: with_part.then_some(j.part),
        axis: AxisOD { o: j.origin.to_array(), d: j.axis.to_array() },
        kind,
        rotate,
        translate,
    }
}

fn json_bytes(v: &serde_json::Value) -> Vec<u8> {
    serde_json::to_vec_pretty(v).unwrap_or_default()
}

/// Write joints.json, trans.json and the per-part meshes into `dir` (created if needed).
pub fn write_ground_truth(object: &ArticulatedObject, dir: &Path) -> Result<()> {
    for sub in ["start", "end"] {
        std::fs::create_dir_all(dir.join(sub)).map_err(|e| Error::io(dir.join(sub), e))?;
    }
    let joints = JointsFile::from_object(object);
    let path = dir.join("joints.json");
    let value = serde_json::to_value(&joints).map_err(|e| Error::Other(format!("{}: {e}", path.display())))?;
    write_atomic(&path, &json_bytes(&value))?;

    let info: serde_json::Value = if object.joints.len() == 1 {
        serde_json::to_value(trans_info(&object.joints[0], false))
    } else {
        serde_json::to_value(object.joints.iter().map(|j| trans_info(j, true)).collect::<Vec<_>>())
    }
    .map_err(|e| Error::Other(format!("trans.json: {e}")))?;
    let path = dir.join("trans.json");
    write_atomic(&path, &json_bytes(&serde_json::json!({ "trans_info": info })))?;

    for (state, t) in [("start", 0.0f32), ("end", 1.0)] {
        for (k, mesh) in object.meshes_at(t, GT_CYLINDER_SEGMENTS).iter().enumerate() {
            let path = dir.join(state).join(format!("part_{k}.obj"));
            let comment = format!(
                "aim synth ground truth: object {}, part {k} ({}), {state} state (t = {t}); world frame z up",
                object.name, object.parts[k].name
            );
            write_atomic(&path, mesh.to_obj(&comment).as_bytes())?;
        }
    }
    Ok(())
}
