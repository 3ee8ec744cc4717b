//! The written dataset: layout, loading with aim's loader and with python (json + PIL),
//! determinism, the command line and bad input.

use std::path::{Path, PathBuf};
use std::process::Command;

use aim::camera::Camera;
use aim::synth::dataset::{plan_views, Split, StateFolder};
use aim::synth::{object, write_dataset, SynthConfig};
use aim_capture::dataset::{load_aim, LoadOptions};
use aim_capture::Phase;

fn small() -> SynthConfig {
    SynthConfig {
        resolution: 64,
        scan_views: 7,
        motion_frames: 23,
        end_views: 6,
        test_views: 3,
        motion_test_every: 10,
        samples_per_pixel: 4,
        seed: 5,
        ..SynthConfig::default()
    }
}

fn tmp(name: &str) -> PathBuf {
    let p = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("synth_dataset").join(name);
    let _ = std::fs::remove_dir_all(&p);
    p
}

#[test]
fn written_dataset_loads_with_the_aim_loader_and_matches_the_plan() {
    let out = tmp("load");
    let o = object("storage_door_drawer").unwrap();
    let cfg = small();
    let summary = write_dataset(&o, &out, &cfg, &|_, _| {}).unwrap();
    assert_eq!(summary.views, 7 + 3 + 23 + 6 + 3);
    let ds = load_aim(&out, &LoadOptions::default()).unwrap();
    assert_eq!((ds.start.train.len(), ds.start.test.len()), (7, 3));
    assert_eq!((ds.motion.train.len(), ds.motion.test.len()), (21, 2));
    let end = ds.end.as_ref().unwrap();
    assert_eq!((end.train.len(), end.test.len()), (6, 3));

    // Motion times: i / (N - 1) over train and test together, each exactly once.
    let mut times: Vec<f32> = ds.motion.train.iter().chain(&ds.motion.test).map(|f| f.motion_time.unwrap()).collect();
    times.sort_by(f32::total_cmp);
    for (i, t) in times.iter().enumerate() {
        assert!((t - i as f32 / 22.0).abs() < 1e-6, "time {i}: {t}");
    }
    for f in ds.motion.train.iter().chain(&ds.motion.test) {
        let i = (f.timestamp_s * 30.0).round();
        assert!((f.timestamp_s * 30.0 - i).abs() < 1e-6 && (i as f32 / 22.0 - f.motion_time.unwrap()).abs() < 1e-6);
    }
    assert!(ds.start.train.iter().all(|f| f.motion_time.is_none() && f.phase == Phase::Scan));
    assert!(end.train.iter().all(|f| f.phase == Phase::After));

    // Poses and intrinsics round-trip through the Blender matrices in the json.
    let plan = plan_views(&o, &cfg);
    for v in plan.iter().filter(|v| v.folder == StateFolder::Motion && v.split == Split::Train) {
        let f = &ds.motion.train[v.index];
        assert_eq!(f.intrinsics.width, 64);
        assert!((f.intrinsics.fx - v.camera.intrinsics.fx).abs() < 1e-3);
        assert!((f.intrinsics.cx - 32.0).abs() < 1e-6);
        let diff =
            (f.world_to_camera - v.camera.world_to_camera).to_cols_array().iter().fold(0.0f32, |m, x| m.max(x.abs()));
        assert!(diff < 1e-5, "pose of motion frame {} differs by {diff}", v.index);
        assert_eq!(f.motion_time, v.frame_time);
    }
    // Every camera looks at the object: the origin projects near the image centre.
    for f in ds.start.train.iter().chain(&ds.motion.train).chain(&end.train) {
        let c = Camera::new(f.intrinsics, f.world_to_camera);
        let (u, v, z) = c.project(glam::Vec3::ZERO).unwrap();
        assert!((u - 32.0).abs() < 4.0 && (v - 32.0).abs() < 4.0 && z > 2.0, "{}: ({u}, {v}, {z})", f.source);
        // Upper hemisphere.
        assert!(c.position().z > 0.0);
    }
    // RGBA with a transparent background, an opaque object, and depth in metres.
    let f = &ds.start.train[0];
    let alpha: Vec<u8> = f.image.pixels().map(|p| p[3]).collect();
    assert_eq!(alpha[0], 0);
    assert!(alpha.iter().filter(|&&a| a == 255).count() > 300);
    let depth = f.depth.as_ref().unwrap();
    assert!(depth.iter().zip(&alpha).all(|(&d, &a)| (d == 0.0) == (a == 0) || (a > 0 && a < 255)));
    assert!(depth.iter().filter(|&&d| d > 0.0).all(|&d| d > 1.5 && d < 4.0));
    // synth.json's bounds hold the object at the start and the end.
    let meta: serde_json::Value = serde_json::from_slice(&std::fs::read(out.join("synth.json")).unwrap()).unwrap();
    let corner =
        |k: &str| glam::Vec3::from_slice(&serde_json::from_value::<Vec<f32>>(meta["bounds"][k].clone()).unwrap());
    let (lo, hi) = (corner("min"), corner("max"));
    for state in ["start", "end"] {
        for k in 0..3 {
            let m = aim::mesh::read_obj(&out.join(format!("gt/{state}/part_{k}.obj"))).unwrap();
            assert!(m.vertices.iter().all(|v| v.cmpge(lo - 1e-4).all() && v.cmple(hi + 1e-4).all()));
        }
    }
    assert!((hi - lo).max_element() < 2.0);
    // Ground truth files.
    for p in ["gt/joints.json", "gt/trans.json", "gt/start/part_2.obj", "gt/end/part_0.obj", "synth.json"] {
        assert!(out.join(p).is_file(), "{p} missing");
    }
}

#[test]
fn python_reads_the_dataset_with_json_and_pil() {
    let out = tmp("python");
    write_dataset(&object("fridge").unwrap(), &out, &small(), &|_, _| {}).unwrap();
    let script = r#"
import json, sys, os
import numpy as np
from PIL import Image
root = sys.argv[1]
n = 0
for state in ["start", "motion", "end"]:
    for split in ["train", "test"]:
        meta = json.load(open(os.path.join(root, state, "transforms_%s.json" % split)))
        assert 0.5 < meta["camera_angle_x"] < 0.9
        for fr in meta["frames"]:
            m = np.array(fr["transform_matrix"], dtype=np.float64)
            assert m.shape == (4, 4)
            r = m[:3, :3]
            assert np.allclose(r @ r.T, np.eye(3), atol=1e-5) and abs(np.linalg.det(r) - 1) < 1e-5
            assert (m[3] == [0, 0, 0, 1]).all()
            # Blender camera looks down its -z: the object centre is in front.
            cam_to_origin = -m[:3, 3]
            assert np.dot(cam_to_origin, -m[:3, 2]) > 0.95 * np.linalg.norm(cam_to_origin)
            stem = os.path.join(root, state, fr["file_path"])
            rgba = Image.open(stem + ".png"); rgba.load()
            assert rgba.mode == "RGBA" and rgba.size == (64, 64), (rgba.mode, rgba.size)
            depth = Image.open(os.path.join(root, state, fr["depth_file_path"]) + ".png")
            d = np.array(depth)
            assert depth.mode in ("I;16", "I;16B", "I"), depth.mode
            a = np.array(rgba)[:, :, 3]
            assert d.max() > 1500 and d.max() < 4000, d.max()
            assert ((d > 0) <= (a > 0)).all()
            part = np.array(Image.open(os.path.join(root, state, fr["part_file_path"]) + ".png"))
            assert set(np.unique(part)) <= {0, 1, 255}
            if state == "motion":
                assert 0.0 <= fr["time"] <= 1.0
            n += 1
j = json.load(open(os.path.join(root, "gt", "joints.json")))
assert j["joints"][0]["type"] == "revolute" and j["parts"][1]["name"] == "door"
t = json.load(open(os.path.join(root, "gt", "trans.json")))
assert t["trans_info"]["type"] == "rotate" and abs(t["trans_info"]["rotate"]["r"] - 110) < 1e-3
print("frames", n)
"#;
    let output = Command::new("python3")
        .arg("-c")
        .arg(script)
        .arg(&out)
        .output()
        .expect("python3 is required (CI installs tests/requirements.txt)");
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(output.status.success(), "python failed:\n{stdout}\n{}", String::from_utf8_lossy(&output.stderr));
    assert_eq!(stdout.trim(), format!("frames {}", 7 + 3 + 23 + 6 + 3));
}

fn read(p: &Path) -> Vec<u8> {
    std::fs::read(p).unwrap()
}

#[test]
fn deterministic_for_a_seed() {
    let cfg = SynthConfig { scan_views: 3, motion_frames: 4, end_views: 2, test_views: 1, ..small() };
    let o = object("usb").unwrap();
    let (a, b, c) = (tmp("det_a"), tmp("det_b"), tmp("det_c"));
    write_dataset(&o, &a, &cfg, &|_, _| {}).unwrap();
    write_dataset(&o, &b, &cfg, &|_, _| {}).unwrap();
    write_dataset(&o, &c, &SynthConfig { seed: 6, ..cfg.clone() }, &|_, _| {}).unwrap();
    for p in [
        "start/transforms_train.json",
        "start/train/r_002.png",
        "motion/train/r_001_depth.png",
        "end/train/r_001_part.png",
    ] {
        assert_eq!(read(&a.join(p)), read(&b.join(p)), "{p} differs between runs");
    }
    assert_ne!(read(&a.join("start/transforms_train.json")), read(&c.join("start/transforms_train.json")));
    // The motion path does not depend on the seed.
    assert_eq!(read(&a.join("motion/transforms_train.json")), read(&c.join("motion/transforms_train.json")));
}

#[test]
fn bad_input_is_a_clear_error() {
    let err = object("toaster").unwrap_err().to_string();
    assert!(err.contains("toaster") && err.contains("fridge") && err.contains("table_complex"), "{err}");

    // An output "directory" below a regular file.
    let dir = tmp("bad");
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join("plain_file");
    std::fs::write(&file, b"x").unwrap();
    let err =
        write_dataset(&object("blade").unwrap(), &file.join("out"), &small(), &|_, _| {}).unwrap_err().to_string();
    assert!(err.contains("plain_file"), "{err}");

    let err = write_dataset(
        &object("blade").unwrap(),
        &dir.join("o"),
        &SynthConfig { motion_frames: 1, ..small() },
        &|_, _| {},
    )
    .unwrap_err()
    .to_string();
    assert!(err.contains("motion frames"), "{err}");
}

#[test]
fn command_line_lists_objects_and_rejects_unknown_names() {
    let exe = env!("CARGO_BIN_EXE_aim");
    let out = Command::new(exe).args(["synth", "--list"]).output().unwrap();
    assert!(out.status.success());
    let text = String::from_utf8_lossy(&out.stdout);
    for name in aim::synth::OBJECT_NAMES.into_iter().chain(aim::synth::HELD_OUT_NAMES) {
        assert!(text.contains(name), "--list lacks {name}:\n{text}");
    }
    let out = Command::new(exe).args(["synth", "toaster", "--out", "/nonexistent/never"]).output().unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("valid objects") && err.contains("washer"), "{err}");

    let dir = tmp("cli");
    let out = Command::new(exe)
        .args([
            "synth",
            "scissors",
            "--res",
            "32",
            "--motion-frames",
            "3",
            "--scan-views",
            "2",
            "--end-views",
            "1",
            "--seed",
            "9",
        ])
        .arg("--out")
        .arg(&dir)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let img = image::open(dir.join("motion/train/r_002.png")).unwrap();
    assert_eq!((img.width(), img.height()), (32, 32));
}
