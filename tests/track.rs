//! Stage II by node tracking on the benchmark's fridge (stage I and II at the cpu
//! presets, about three minutes): the one door must be found with its joint and
//! motion (a stage II that learns no motion, or the wrong one, fails here).

use std::path::PathBuf;
use std::process::Command;

use aim::synth::dataset::{write_dataset, SynthConfig};

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("aim-track-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).expect("temp dir");
    d
}

fn aim() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_aim"));
    c.args(["--log", "error"]);
    c
}

#[test]
fn node_tracking_recovers_a_revolute_door() {
    let root = tmp("fridge");
    let data = root.join("data");
    // The benchmark's fridge as `aim synth` writes it (stage II is judged at this size).
    let cfg = SynthConfig::default();
    write_dataset(&aim::synth::object("fridge").expect("object"), &data, &cfg, &|_, _| {}).expect("written");
    let st = aim().arg("train-static").arg(&data).arg("--out").arg(root.join("s")).output().expect("runs");
    assert!(st.status.success(), "{}", String::from_utf8_lossy(&st.stderr));
    let dy = aim()
        .arg("train-dynamic")
        .arg(&data)
        .arg("--static")
        .arg(root.join("s").join("static.ply"))
        .arg("--out")
        .arg(root.join("d"))
        .output()
        .expect("runs");
    assert!(dy.status.success(), "{}", String::from_utf8_lossy(&dy.stderr));
    let metrics: aim::train::dynamic_run::DynamicMetrics =
        serde_json::from_slice(&std::fs::read(root.join("d").join("metrics.json")).expect("metrics")).expect("json");
    let report = metrics.gt_report.expect("the dataset has ground truth");
    assert!(report.missing.is_empty() && report.extra.is_empty(), "one door, one part: {report:?}");
    let door = &report.matched[0];
    // The door turns 110 degrees about z through (0.3, -0.3).
    assert!(door.axis_angle_deg < 2.0, "axis {} deg off", door.axis_angle_deg);
    assert!(door.axis_position.expect("revolute") < 0.2, "pivot {:?} (0.1 m) off", door.axis_position);
    assert!(door.part_motion < 3.0, "motion {} deg off", door.part_motion);
}
