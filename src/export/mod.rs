//! The articulated twin as files for viewers and simulators, written into one
//! folder:
//!
//! - `articulation.json`: the parts (each a 3DGS PLY in its start-state pose)
//!   and the joints in the same form as the benchmark's `gt/joints.json`
//!   (type, unit axis, a point on the axis, range with `range[0]` the state at
//!   the start of the motion), so the two compare directly;
//! - `parts/part_K.ply`: part 0 is the static base, parts 1.. move;
//! - `meshes/part_K.obj` and `.ply`: each part's surface at the start state,
//!   extracted from its Gaussians by TSDF fusion ([`crate::mesh::tsdf`]), all
//!   parts with one voxel size (a fraction of the whole twin's size);
//! - `meshes/part_K_collision.obj`: each part's convex hull (its collision shape);
//! - `object.urdf` and `object.xml` (MJCF): the kinematic tree for simulators
//!   ([`sim`]): one link/body per part with its visual mesh, hull and inertial
//!   properties ([`physics`]), a revolute or prismatic joint per moving part
//!   with its observed range as limits.
//!
//! Every file is written atomically.

pub mod physics;
pub mod sim;
mod twin;

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::error::{write_atomic, Error, Result};
use crate::mesh::tsdf::{mesh_gaussians, object_size, TsdfConfig};
use crate::mesh::MeshData;
use crate::motion::JointEstimate;
use crate::splat::GaussianSet;
use crate::synth::JointRecord;
pub use physics::{ExportConfig, Inertial};
pub use twin::{turntable, Twin};

/// One part of the twin.
pub struct TwinPart<'a> {
    /// The part's Gaussians in the start-state pose.
    pub gaussians: &'a GaussianSet,
    /// How it moves relative to the base; None for the base itself.
    pub joint: Option<JointEstimate>,
}

/// A part as listed in articulation.json.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PartEntry {
    pub id: usize,
    pub name: String,
    /// The part's Gaussians, relative to the file.
    pub gaussians: String,
    pub count: usize,
    /// The part's surface mesh (OBJ, a PLY beside it), relative to the file; None
    /// when no surface could be extracted (too few opaque Gaussians).
    #[serde(default)]
    pub mesh: Option<String>,
    /// The convex hull of the mesh (OBJ), relative to the file: the collision shape.
    #[serde(default)]
    pub collision: Option<String>,
    /// Mass properties of the hull at `ExportConfig::density` (world frame, start state).
    #[serde(default)]
    pub inertial: Option<Inertial>,
}

/// articulation.json.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Articulation {
    pub format: String,
    pub parts: Vec<PartEntry>,
    pub joints: Vec<JointRecord>,
}

const FORMAT: &str = "aim-articulation/1";

/// The joint record of moving part `part` (child of the base, part 0).
fn joint_record(part: usize, j: &JointEstimate) -> JointRecord {
    JointRecord {
        part,
        kind: j.kind,
        axis: j.axis.as_vec3().to_array(),
        origin: j.origin.as_vec3().to_array(),
        range: [0.0, j.amount as f32],
        parent: 0,
    }
}

pub(crate) fn part_name(id: usize) -> String {
    if id == 0 {
        "base".into()
    } else {
        format!("part_{id}")
    }
}

/// Write the twin into `dir`: `parts[0]` is the base, the others move. Meshes
/// are extracted with `mesh` (a part that gives none is logged and recorded as
/// `mesh: None`); the simulator files follow `export`.
pub fn write_twin(dir: &Path, parts: &[TwinPart], mesh: &TsdfConfig, export: &ExportConfig) -> Result<Articulation> {
    if parts.first().is_none_or(|p| p.joint.is_some()) {
        return Err(Error::Other("a twin needs its base (a part without a joint) first".into()));
    }
    for sub in ["parts", "meshes"] {
        std::fs::create_dir_all(dir.join(sub)).map_err(|e| Error::io(dir.join(sub), e))?;
    }
    let size = object_size(parts.iter().map(|p| p.gaussians), mesh.min_opacity);
    let mut entries = Vec::new();
    let mut joints = Vec::new();
    for (id, p) in parts.iter().enumerate() {
        let file = format!("parts/part_{id}.ply");
        crate::splat::ply::write_ply(&dir.join(&file), p.gaussians)?;
        let surface = size
            .ok_or_else(|| Error::Other("no opaque Gaussians".into()))
            .and_then(|s| mesh_gaussians(p.gaussians, s, mesh));
        let mesh_file = match &surface {
            Ok(m) => {
                let stem = format!("meshes/part_{id}");
                let comment = format!("aim twin: part {id} ({}) at the start state", part_name(id));
                m.write_obj_and_ply(&dir.join(&stem), &comment)?;
                Some(format!("{stem}.obj"))
            }
            Err(e) => {
                tracing::warn!("twin part {id}: no mesh ({e})");
                None
            }
        };
        entries.push(PartEntry {
            id,
            name: part_name(id),
            gaussians: file,
            count: p.gaussians.len(),
            mesh: mesh_file,
            collision: None,
            inertial: None,
        });
        if let Ok(m) = &surface {
            add_physics(dir, entries.last_mut().expect("pushed"), m, export)?;
        }
        if let Some(j) = &p.joint {
            joints.push(joint_record(id, j));
        }
    }
    let art = Articulation { format: FORMAT.into(), parts: entries, joints };
    write_articulation(dir, &art)?;
    write_simulator_files(dir, &art, export)?;
    Ok(art)
}

/// Write `art` as `dir`/articulation.json.
fn write_articulation(dir: &Path, art: &Articulation) -> Result<()> {
    let json = serde_json::to_vec_pretty(art).map_err(|e| Error::Other(e.to_string()))?;
    write_atomic(&dir.join("articulation.json"), &json)
}

/// Compute part `entry`'s convex hull from its `mesh`, write it beside the mesh
/// and record it with the hull's inertial properties (none for a flat hull).
fn add_physics(dir: &Path, entry: &mut PartEntry, mesh: &MeshData, export: &ExportConfig) -> Result<()> {
    let Some(hull) = physics::convex_hull(mesh) else {
        tracing::warn!("twin part {}: no convex hull (flat or too few vertices)", entry.id);
        return Ok(());
    };
    let file = format!("meshes/part_{}_collision.obj", entry.id);
    let comment = format!("aim twin: convex hull of part {} ({}) at the start state", entry.id, entry.name);
    write_atomic(&dir.join(&file), hull.to_obj(&comment).as_bytes())?;
    entry.collision = Some(file);
    entry.inertial = physics::inertial_of_hull(&hull, export.density);
    Ok(())
}

/// Write `object.urdf` and `object.xml` (MJCF) of `art` into its folder `dir`.
pub fn write_simulator_files(dir: &Path, art: &Articulation, export: &ExportConfig) -> Result<()> {
    write_atomic(&dir.join("object.urdf"), sim::urdf(art, export).as_bytes())?;
    write_atomic(&dir.join("object.xml"), sim::mjcf(art, export).as_bytes())
}

/// What `export_twin` writes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Format {
    /// object.urdf with its meshes and hulls.
    Urdf,
    /// object.xml (MJCF) with its meshes and hulls.
    Mjcf,
    /// The whole object's 3DGS PLY (object.ply) beside the parts' (always
    /// written), for splat viewers.
    Ply,
}

/// Write `twin` into `out` in `formats` with the simulator settings `cfg`
/// (collision hulls and inertials recomputed from the meshes at its density),
/// with an articulation.json that lists what is there. `out` may be the twin's
/// own folder.
pub fn export_twin(twin: &Twin, out: &Path, formats: &[Format], cfg: &ExportConfig) -> Result<Articulation> {
    let mut art = twin.articulation.clone();
    let copy = |file: &str| -> Result<()> {
        let (from, to) = (twin.dir.join(file), out.join(file));
        if from != to {
            if let Some(parent) = to.parent() {
                std::fs::create_dir_all(parent).map_err(|e| Error::io(parent, e))?;
            }
            let bytes = std::fs::read(&from).map_err(|e| Error::io(&from, e))?;
            write_atomic(&to, &bytes)?;
        }
        Ok(())
    };
    std::fs::create_dir_all(out).map_err(|e| Error::io(out, e))?;
    // The parts' Gaussians always: they are the twin (articulation.json lists them).
    for p in &art.parts {
        copy(&p.gaussians)?;
    }
    if formats.contains(&Format::Ply) {
        let parts = twin.part_gaussians()?;
        crate::splat::ply::write_ply(&out.join("object.ply"), &twin.gaussians_at(&parts, &[])?)?;
    }
    if formats.iter().any(|f| matches!(f, Format::Urdf | Format::Mjcf)) {
        std::fs::create_dir_all(out.join("meshes")).map_err(|e| Error::io(out.join("meshes"), e))?;
        for entry in &mut art.parts {
            entry.collision = None;
            entry.inertial = None;
            // A part without a mesh file has no visual or collision geometry to export.
            if let Some(file) = entry.mesh.clone() {
                let mesh = crate::mesh::read_obj(&twin.dir.join(&file))?;
                copy(&file)?;
                add_physics(out, entry, &mesh, cfg)?;
            }
        }
        if formats.contains(&Format::Urdf) {
            write_atomic(&out.join("object.urdf"), sim::urdf(&art, cfg).as_bytes())?;
        }
        if formats.contains(&Format::Mjcf) {
            write_atomic(&out.join("object.xml"), sim::mjcf(&art, cfg).as_bytes())?;
        }
    }
    write_articulation(out, &art)?;
    Ok(art)
}

/// A part's mesh moved from the start state (`range[0]`) to joint state `q`
/// (radians or metres) by its joint.
pub fn mesh_at_state(mesh: &MeshData, joint: &JointRecord, q: f32) -> MeshData {
    mesh.transformed(&joint.motion_to_state(q))
}

/// Read a twin's articulation.json and check it.
pub fn read_articulation(path: &Path) -> Result<Articulation> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    let art: Articulation =
        serde_json::from_slice(&bytes).map_err(|e| Error::bad_file(path, format!("not an articulation file: {e}")))?;
    if art.parts.first().is_none_or(|p| art.joints.iter().any(|j| j.part == p.id)) {
        return Err(Error::bad_file(path, "the first part must be the base (a part without a joint)"));
    }
    crate::synth::gt::validate_joints(path, &art.joints, &art.parts.iter().map(|p| p.id).collect::<Vec<_>>())?;
    Ok(art)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::motion::JointKind;
    use glam::DVec3;

    #[test]
    fn twin_files_round_trip() {
        let dir = std::env::temp_dir().join(format!("aim-export-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let pts = crate::train::init::random_points(20, glam::Vec3::splat(-0.5), glam::Vec3::splat(0.5), 1);
        let base = crate::train::init::gaussians_from_points(&pts[..12], None, 0.5, 0);
        let door = crate::train::init::gaussians_from_points(&pts[12..], None, 0.5, 0);
        let joint = JointEstimate {
            kind: JointKind::Revolute,
            axis: DVec3::Z,
            origin: DVec3::new(0.3, -0.3, 0.0),
            amount: 1.5,
            translation_along_axis: 0.0,
        };
        let art = write_twin(
            &dir,
            &[TwinPart { gaussians: &base, joint: None }, TwinPart { gaussians: &door, joint: Some(joint) }],
            // A coarse volume: these few random Gaussians only need some mesh, fast.
            &TsdfConfig { voxel_fraction: 0.02, ..TsdfConfig::default() },
            &ExportConfig::default(),
        )
        .expect("written");
        let back: Articulation =
            serde_json::from_slice(&std::fs::read(dir.join("articulation.json")).expect("read")).expect("json");
        assert_eq!(back, art);
        assert_eq!(back.joints[0].range, [0.0, 1.5]);
        assert_eq!(crate::splat::ply::read_ply(&dir.join("parts/part_1.ply")).expect("ply").len(), door.len());
        let urdf = std::fs::read_to_string(dir.join("object.urdf")).expect("urdf");
        assert!(urdf.contains("type=\"revolute\"") && urdf.contains("<origin xyz=\"0.3 -0.3 0\""), "{urdf}");
        // The base must come first.
        let only_door = [TwinPart { gaussians: &door, joint: Some(joint) }];
        assert!(write_twin(&dir, &only_door, &TsdfConfig::default(), &ExportConfig::default()).is_err());
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_part_mesh_moved_to_the_end_state_is_the_ground_truth_end_mesh() {
        for name in ["fridge", "storage"] {
            let obj = crate::synth::object(name).expect("object");
            let (start, end) = (obj.meshes_at(0.0, 16), obj.meshes_at(1.0, 16));
            let j = &obj.joints[0];
            let record = JointRecord::from_joint(j);
            let moved = mesh_at_state(&start[j.part], &record, j.range[1]);
            let worst =
                moved.vertices.iter().zip(&end[j.part].vertices).map(|(a, b)| (*a - *b).length()).fold(0.0, f32::max);
            assert!(worst < 1e-5, "{name}: {worst}");
        }
    }
}
