//! A written twin opened again: what `aim eval`, `aim render-twin` and
//! `aim export` read, so all three see the same parts, joints and meshes.

use std::path::{Path, PathBuf};

use super::{read_articulation, Articulation};
use crate::error::{Error, Result};
use crate::mesh::tsdf::{mesh_gaussians, object_size, TsdfConfig};
use crate::mesh::{read_obj, MeshData};
use crate::splat::GaussianSet;
use crate::synth::JointRecord;

/// A twin folder and its articulation.json.
pub struct Twin {
    pub dir: PathBuf,
    pub articulation: Articulation,
}

impl Twin {
    /// The twin of `run`: a run folder with twin/ in it, or a twin folder.
    pub fn open(run: &Path) -> Result<Twin> {
        let dir = [run.join("twin"), run.to_path_buf()]
            .into_iter()
            .find(|d| d.join("articulation.json").is_file())
            .ok_or_else(|| {
                Error::bad_file(run, "no twin here (neither articulation.json nor twin/articulation.json)")
            })?;
        let articulation = read_articulation(&dir.join("articulation.json"))?;
        Ok(Twin { dir, articulation })
    }

    /// Each part's Gaussians (start state), in articulation.json's order.
    pub fn part_gaussians(&self) -> Result<Vec<GaussianSet>> {
        self.articulation.parts.iter().map(|p| crate::splat::ply::read_ply(&self.dir.join(&p.gaussians))).collect()
    }

    /// The joint that moves part `id` (None for the base or an unknown id).
    pub fn joint(&self, id: usize) -> Option<&JointRecord> {
        self.articulation.joints.iter().find(|j| j.part == id)
    }

    /// Each part's start-state mesh: its mesh file, or extracted from its
    /// Gaussians with `cfg` (a part that gives no surface is logged and has None).
    pub fn meshes(&self, cfg: &TsdfConfig) -> Result<Vec<Option<MeshData>>> {
        let parts = &self.articulation.parts;
        let sets = if parts.iter().any(|p| p.mesh.is_none()) { self.part_gaussians()? } else { Vec::new() };
        let size = object_size(&sets, cfg.min_opacity);
        parts
            .iter()
            .enumerate()
            .map(|(k, p)| match (&p.mesh, size) {
                (Some(file), _) => read_obj(&self.dir.join(file)).map(Some),
                (None, Some(size)) => {
                    tracing::info!("twin part {}: no mesh file, extracting one from {}", p.id, p.gaussians);
                    Ok(mesh_gaussians(&sets[k], size, cfg)
                        .inspect_err(|e| tracing::warn!("twin part {}: no mesh ({e})", p.id))
                        .ok())
                }
                (None, None) => Ok(None),
            })
            .collect()
    }

    /// The whole object with each moving part at a joint state (radians or
    /// metres, on the scale of the joint's `range`): `states` names parts by id,
    /// the others stay at their start state (`range[0]`). `parts` are
    /// `part_gaussians()`. A state for a part without a joint is an error.
    pub fn gaussians_at(&self, parts: &[GaussianSet], states: &[(usize, f32)]) -> Result<GaussianSet> {
        for (id, _) in states {
            if self.joint(*id).is_none() {
                let ids: Vec<usize> = self.articulation.joints.iter().map(|j| j.part).collect();
                return Err(Error::Config(format!("part {id} has no joint (the moving parts are {ids:?})")));
            }
        }
        let mut out = GaussianSet::new(parts.first().map_or(0, |g| g.sh_degree));
        for (p, g) in self.articulation.parts.iter().zip(parts) {
            match self.joint(p.id) {
                None => out.extend_from(g),
                Some(j) => {
                    let q = states.iter().rev().find(|(id, _)| *id == p.id).map_or(j.range[0], |s| s.1);
                    out.extend_from(&g.transformed(&j.motion_to_state(q)));
                }
            }
        }
        Ok(out)
    }
}

/// The turntable of a twin: `frames` views, frame k with every joint at
/// `range[0] + k / (frames - 1) * (range[1] - range[0])` and `camera` turned
/// `k / frames` of a full circle about the vertical (+z) through the twin's
/// centre (the mean of its Gaussians). Returns each frame's Gaussians and camera.
pub fn turntable(
    twin: &Twin,
    parts: &[GaussianSet],
    camera: &crate::camera::Camera,
    frames: usize,
) -> Result<Vec<(GaussianSet, crate::camera::Camera)>> {
    use glam::{Mat4, Vec3};
    if frames == 0 {
        return Err(Error::Config("a turntable needs at least one frame".into()));
    }
    let total: usize = parts.iter().map(|g| g.len()).sum();
    let centre = parts.iter().flat_map(|g| (0..g.len()).map(|i| g.mean(i))).sum::<Vec3>() / total.max(1) as f32;
    (0..frames)
        .map(|k| {
            let s = if frames > 1 { k as f32 / (frames - 1) as f32 } else { 1.0 };
            let states: Vec<(usize, f32)> =
                twin.articulation.joints.iter().map(|j| (j.part, j.range[0] + s * (j.range[1] - j.range[0]))).collect();
            let angle = std::f32::consts::TAU * k as f32 / frames as f32;
            // Turning the camera by +angle about the centre = the world by -angle under it.
            let turn = Mat4::from_translation(centre) * Mat4::from_rotation_z(-angle) * Mat4::from_translation(-centre);
            let view = crate::camera::Camera::new(camera.intrinsics, camera.world_to_camera * turn);
            Ok((twin.gaussians_at(parts, &states)?, view))
        })
        .collect()
}
