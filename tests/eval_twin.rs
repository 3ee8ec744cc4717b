//! `aim eval` on twins with known answers: a twin built from the ground truth
//! itself (Gaussians sampled on the GT part surfaces, the GT joints) scores
//! near-perfect joints, millimetre Chamfer distances and high IoU; a twin with a
//! wrong joint and an extra part is reported as such; bad input names the file.

use std::path::{Path, PathBuf};
use std::process::Command;

use aim::export::{write_twin, TwinPart};
use aim::mesh::tsdf::TsdfConfig;
use aim::motion::{JointEstimate, JointKind};
use aim::synth::gt::write_ground_truth;
use aim::synth::object;
use glam::DVec3;

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("aim-eval-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).expect("temp dir");
    d
}

/// A coarser mesh extraction than the default (twice the voxel), to keep the test short.
fn quick_mesh() -> TsdfConfig {
    TsdfConfig { voxel_fraction: 0.008, views: 40, ..TsdfConfig::default() }
}

fn joint_of(j: &aim::synth::Joint, scale: f64) -> JointEstimate {
    JointEstimate {
        kind: j.kind,
        axis: j.axis.as_dvec3(),
        origin: j.origin.as_dvec3(),
        amount: scale * f64::from(j.range[1] - j.range[0]),
        translation_along_axis: 0.0,
    }
}

/// Write (under a temp folder named `label`) the dataset's gt/ and a twin of `name` from its GT surfaces; `scale` scales
/// the joint amounts, `extra` adds a spurious moving part.
fn setup(label: &str, name: &str, scale: f64, extra: bool) -> (PathBuf, PathBuf) {
    let root = tmp(label);
    let obj = object(name).expect("object");
    let data = root.join("data");
    write_ground_truth(&obj, &data.join("gt")).expect("gt written");
    let meshes = obj.meshes_at(0.0, 64);
    let sets: Vec<_> = meshes
        .iter()
        .enumerate()
        .map(|(k, m)| aim::train::init::gaussians_from_points(&m.sample_surface(60_000, k as u64), None, 0.95, 0))
        .collect();
    let mut parts = vec![TwinPart { gaussians: &sets[0], joint: None }];
    for j in &obj.joints {
        parts.push(TwinPart { gaussians: &sets[j.part], joint: Some(joint_of(j, scale)) });
    }
    let spurious = JointEstimate {
        kind: JointKind::Revolute,
        axis: DVec3::X,
        origin: DVec3::new(3.0, 3.0, 3.0),
        amount: 0.5,
        translation_along_axis: 0.0,
    };
    if extra {
        parts.push(TwinPart { gaussians: &sets[obj.joints[0].part], joint: Some(spurious) });
    }
    let run = root.join("run");
    write_twin(&run.join("twin"), &parts, &quick_mesh(), &aim::export::ExportConfig::default()).expect("twin written");
    (run, data)
}

fn eval_json(run: &Path, data: &Path) -> serde_json::Value {
    let o = Command::new(env!("CARGO_BIN_EXE_aim"))
        .args(["--log", "warn", "eval"])
        .arg(run)
        .arg("--gt")
        .arg(data)
        .arg("--json")
        .output()
        .expect("runs");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    serde_json::from_slice(&o.stdout).expect("json report")
}

#[test]
fn a_twin_made_of_the_ground_truth_scores_near_perfect() {
    let (run, data) = setup("perfect", "scissors", 1.0, false);
    let r = eval_json(&run, &data);
    assert_eq!(r["failures"], 0, "{r:#}");
    let m = &r["joints"]["matched"][0];
    assert!(m["axis_angle_deg"].as_f64().unwrap() < 1e-3, "{m}");
    assert!(m["part_motion"].as_f64().unwrap() < 1e-5, "{m}");
    // Meshes fused from Gaussians on the surface, at a voxel of 0.008 of the object's
    // size here (7.6 mm): measured 9-10 mm of Chamfer distance (about 4 mm of it the
    // 10k-sample floor) and 58-71 % IoU on the 2 cm thin blades, where a voxel of
    // swelling on each side costs a third of the volume.
    let cd_s = r["static_part"]["chamfer"]["l2_mm"].as_f64().unwrap();
    let cd_m = r["moving_parts"][0]["chamfer"]["l2_mm"].as_f64().unwrap();
    let cd_w = r["whole"]["l2_mm"].as_f64().unwrap();
    assert!(cd_s < 15.0 && cd_m < 15.0 && cd_w < 15.0, "CD-s {cd_s} CD-m {cd_m} CD-w {cd_w}");
    let iou_s = r["static_part"]["iou_percent"].as_f64().unwrap();
    let iou_m = r["moving_parts"][0]["iou_percent"].as_f64().unwrap();
    assert!(iou_s > 50.0 && iou_m > 50.0, "IoU static {iou_s} moving {iou_m}");
    // The twin lists its meshes, as OBJ and PLY.
    let art: serde_json::Value =
        serde_json::from_slice(&std::fs::read(run.join("twin/articulation.json")).unwrap()).unwrap();
    assert_eq!(art["parts"][1]["mesh"], "meshes/part_1.obj");
    assert!(run.join("twin/meshes/part_1.ply").is_file());
}

#[test]
fn wrong_motion_and_an_extra_part_are_reported() {
    let (run, data) = setup("wrong", "fridge", 0.5, true);
    let r = eval_json(&run, &data);
    assert_eq!(r["failures"], 1, "{r:#}");
    assert_eq!(r["joints"]["extra"], serde_json::json!([2]));
    // Half the door's 110 degrees: 55 degrees of part motion error, axis still right.
    let m = &r["joints"]["matched"][0];
    assert!((m["part_motion"].as_f64().unwrap() - 55.0).abs() < 0.1, "{m}");
    assert!(m["axis_angle_deg"].as_f64().unwrap() < 1e-3, "{m}");
    assert_eq!(m["predicted"], 1);
}

fn eval_error(run: &Path, data: &Path) -> String {
    let o = Command::new(env!("CARGO_BIN_EXE_aim"))
        .args(["--log", "error", "eval"])
        .arg(run)
        .arg("--gt")
        .arg(data)
        .output()
        .expect("runs");
    assert!(!o.status.success(), "bad input must fail");
    let e = String::from_utf8_lossy(&o.stderr).into_owned();
    assert!(!e.contains("panicked"), "{e}");
    e
}

#[test]
fn bad_input_names_the_file() {
    let (run, data) = setup("bad", "storage", 1.0, false);
    let empty = tmp("empty");
    assert!(eval_error(&empty, &data).contains("no twin here"));
    assert!(eval_error(&run, &empty).contains("joints.json"));
    std::fs::write(run.join("twin/meshes/part_1.obj"), "v 0 0 zero\n").unwrap();
    let e = eval_error(&run, &data);
    assert!(e.contains("part_1.obj") && e.contains("line 1"), "{e}");
    std::fs::write(data.join("gt/start/part_0.obj"), "f 1 2 3\n").unwrap();
    assert!(eval_error(&run, &data).contains("part_0.obj"));
}
