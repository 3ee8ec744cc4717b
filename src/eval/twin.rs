//! Evaluate an exported twin against a dataset's ground truth (gt/joints.json
//! and the per-part start-state meshes): joints matched by least error, then
//! per matched part the Chamfer distance and 3D IoU of its mesh, the static
//! part's, and the whole object's Chamfer distance.

use std::path::Path;

use serde::{Deserialize, Serialize};

use super::shape::{chamfer_meshes, iou_meshes, ChamferDistance};
use super::{match_joints, ArticulationReport, GtJoint, PredictedJoint};
use crate::error::{Error, Result};
use crate::export::Twin;
use crate::mesh::tsdf::TsdfConfig;
use crate::mesh::{read_obj, MeshData};
use crate::motion::{JointEstimate, JointKind};
use crate::synth::{JointRecord, JointsFile};

/// How shapes are compared.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EvalConfig {
    /// For twins whose parts have no mesh file: how to extract one.
    pub mesh: TsdfConfig,
    /// 3D IoU voxel edge as a fraction of the ground-truth object's size.
    pub iou_voxel_fraction: f32,
    /// Seed of the Chamfer surface samples.
    pub seed: u64,
}

impl Default for EvalConfig {
    fn default() -> Self {
        Self { mesh: TsdfConfig::default(), iou_voxel_fraction: 0.004, seed: 0 }
    }
}

/// Shape metrics of one ground-truth part against its matched prediction.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PartShape {
    pub gt_part: usize,
    /// Twin part id matched to it; None: missing (a failure).
    pub predicted: Option<usize>,
    pub chamfer: Option<ChamferDistance>,
    pub iou_percent: Option<f64>,
}

/// Everything `aim eval` reports for one twin.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EvalReport {
    pub object: String,
    /// Moving parts in the ground truth and in the twin.
    pub gt_moving_parts: usize,
    pub predicted_moving_parts: usize,
    /// Joint errors of matched parts; missing GT parts and extra twin parts (by twin part id).
    pub joints: ArticulationReport,
    /// The static part(s): CD-s and static IoU.
    pub static_part: PartShape,
    /// Each GT moving part: CD-m and IoU (None where missing).
    pub moving_parts: Vec<PartShape>,
    /// The whole object at the start state: CD-w.
    pub whole: Option<ChamferDistance>,
    /// Mean IoU over the static and every moving GT part, a missing one counted as 0.
    pub mean_iou_percent: Option<f64>,
    /// Missing plus extra moving parts: any is a failure of the trial.
    pub failures: usize,
}

impl EvalReport {
    /// Mean IoU over the moving GT parts (missing as 0); None without moving parts.
    pub fn moving_iou_percent(&self) -> Option<f64> {
        (!self.moving_parts.is_empty()).then(|| {
            self.moving_parts.iter().map(|p| p.iou_percent.unwrap_or(0.0)).sum::<f64>() / self.moving_parts.len() as f64
        })
    }
}

/// A ground-truth joint as the metrics take it.
pub fn gt_joint(j: &JointRecord) -> GtJoint {
    GtJoint {
        part: j.part,
        kind: j.kind,
        axis: glam::Vec3::from(j.axis).as_dvec3(),
        origin: glam::Vec3::from(j.origin).as_dvec3(),
        range: [f64::from(j.range[0]), f64::from(j.range[1])],
    }
}

/// A twin joint as a prediction: its relative motion from t = 0 to t = 1 is the
/// rotation (or translation) by `range[1] - range[0]` about (along) its axis.
fn predicted_joint(j: &JointRecord) -> PredictedJoint {
    let g = gt_joint(j);
    let amount = g.range[1] - g.range[0];
    let (rotation, translation) = g.relative();
    let translation_along_axis = if g.kind == JointKind::Prismatic { amount } else { 0.0 };
    PredictedJoint {
        joint: JointEstimate { kind: g.kind, axis: g.axis, origin: g.origin, amount, translation_along_axis },
        rotation,
        translation,
    }
}

/// The ground truth of a dataset: joints and start-state meshes per part id.
pub struct GroundTruth {
    pub joints: JointsFile,
    pub meshes: Vec<(usize, MeshData)>,
}

/// Whether `dataset` has ground truth (a synthetic dataset's gt/joints.json).
pub fn has_ground_truth(dataset: &Path) -> bool {
    dataset.join("gt").join("joints.json").exists()
}

impl GroundTruth {
    pub fn load(dataset: &Path) -> Result<Self> {
        let gt = dataset.join("gt");
        let joints = JointsFile::load(&gt.join("joints.json"))?;
        let meshes = joints
            .parts
            .iter()
            .map(|p| {
                let file = p.mesh_start.as_ref().ok_or_else(|| {
                    Error::bad_file(gt.join("joints.json"), format!("part {} has no mesh_start", p.id))
                })?;
                Ok((p.id, read_obj(&gt.join(file))?))
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(Self { joints, meshes })
    }

    fn mesh(&self, part: usize) -> Option<&MeshData> {
        self.meshes.iter().find(|(id, _)| *id == part).map(|(_, m)| m)
    }

    /// The parts no joint moves, as one mesh.
    fn static_mesh(&self) -> MeshData {
        MeshData::merged(
            self.meshes.iter().filter(|(id, _)| !self.joints.joints.iter().any(|j| j.part == *id)).map(|(_, m)| m),
        )
    }
}

fn shape(
    gt_part: usize,
    predicted: Option<usize>,
    p: Option<&MeshData>,
    g: &MeshData,
    voxel: f32,
    seed: u64,
) -> PartShape {
    let (chamfer, iou_percent) = match p {
        Some(p) if !p.is_empty() => (chamfer_meshes(p, g, seed), iou_meshes(p, g, voxel)),
        _ => (None, None),
    };
    PartShape { gt_part, predicted, chamfer, iou_percent }
}

/// Evaluate the twin of `run` (a run folder or its twin/ folder) against `gt`.
pub fn evaluate_twin(run: &Path, gt: &GroundTruth, cfg: &EvalConfig) -> Result<EvalReport> {
    let twin = Twin::open(run)?;
    let meshes = twin.meshes(&cfg.mesh)?;
    let art = &twin.articulation;
    let mesh_of = |part: usize| art.parts.iter().position(|p| p.id == part).and_then(|k| meshes[k].as_ref());

    let pred: Vec<PredictedJoint> = art.joints.iter().map(predicted_joint).collect();
    let gt_joints: Vec<GtJoint> = gt.joints.joints.iter().map(gt_joint).collect();
    let mut joints = match_joints(&pred, &gt_joints);
    // Report twin part ids, not positions in the joint list.
    for e in &mut joints.matched {
        e.predicted = art.joints[e.predicted].part;
    }
    joints.extra = joints.extra.iter().map(|&k| art.joints[k].part).collect();

    let gt_static = gt.static_mesh();
    let all_gt = MeshData::merged(gt.meshes.iter().map(|(_, m)| m));
    let size = all_gt.bounds().map_or(1.0, |(lo, hi)| (hi - lo).max_element());
    let voxel = cfg.iou_voxel_fraction * size;

    let base = art.parts[0].id;
    let static_part = shape(0, Some(base), mesh_of(base), &gt_static, voxel, cfg.seed);
    let moving_parts: Vec<PartShape> = gt
        .joints
        .joints
        .iter()
        .map(|j| {
            let predicted = joints.matched.iter().find(|e| e.gt_part == j.part).map(|e| e.predicted);
            let g = gt.mesh(j.part).cloned().unwrap_or_default();
            shape(j.part, predicted, predicted.and_then(mesh_of), &g, voxel, cfg.seed)
        })
        .collect();
    let whole_pred = MeshData::merged(meshes.iter().flatten());
    let whole = (!whole_pred.is_empty()).then(|| chamfer_meshes(&whole_pred, &all_gt, cfg.seed)).flatten();
    let ious: Vec<f64> =
        std::iter::once(&static_part).chain(&moving_parts).map(|p| p.iou_percent.unwrap_or(0.0)).collect();
    let mean_iou_percent = Some(ious.iter().sum::<f64>() / ious.len() as f64);
    Ok(EvalReport {
        object: gt.joints.object.clone(),
        gt_moving_parts: gt.joints.joints.len(),
        predicted_moving_parts: art.joints.len(),
        failures: joints.missing.len() + joints.extra.len(),
        joints,
        static_part,
        moving_parts,
        whole,
        mean_iou_percent,
    })
}
