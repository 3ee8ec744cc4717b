//! Dataset loaders: nerfstudio transforms.json and COLMAP sparse models (.txt and .bin),
//! checked against the AiM-layout loader on a synthetic dataset, plus bad input.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use aim::camera::Camera;
use aim::synth::{object, write_dataset, SynthConfig};
use aim_capture::dataset::colmap::{image_from_pose, parse_cameras_bin, parse_images_bin, parse_points_bin};
use aim_capture::dataset::{
    load_aim, load_colmap_frames, load_nerfstudio, read_colmap_model, write_colmap_bin, write_colmap_text,
    ColmapCamera, ColmapModel, ColmapPoint, Distortion, LoadOptions,
};
use aim_capture::Frame;
use glam::Mat4;
use serde_json::json;

fn dataset() -> &'static PathBuf {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let root = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("dataset_loaders").join("oven");
        let _ = std::fs::remove_dir_all(&root);
        let cfg = SynthConfig {
            resolution: 48,
            scan_views: 5,
            motion_frames: 4,
            end_views: 2,
            test_views: 1,
            samples_per_pixel: 1,
            seed: 2,
            ..SynthConfig::default()
        };
        write_dataset(&object("oven").unwrap(), &root, &cfg, &|_, _| {}).unwrap();
        root
    })
}

fn start_frames() -> Vec<Frame> {
    load_aim(dataset(), &LoadOptions::default()).unwrap().start.train
}

fn max_diff(a: &Mat4, b: &Mat4) -> f32 {
    (*a - *b).to_cols_array().iter().fold(0.0f32, |m, x| m.max(x.abs()))
}

fn scratch(name: &str) -> PathBuf {
    let p = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("dataset_loaders").join(name);
    let _ = std::fs::remove_dir_all(&p);
    std::fs::create_dir_all(&p).unwrap();
    p
}

fn blender_rows(f: &Frame) -> serde_json::Value {
    let c2w = aim::camera::blender_camera_to_world_from_opencv(f.world_to_camera);
    json!(c2w.transpose().to_cols_array_2d())
}

#[test]
fn nerfstudio_matches_the_aim_loader() {
    let frames = start_frames();
    let dir = dataset().join("start");
    let k = frames[0].intrinsics;
    let mut list: Vec<serde_json::Value> = frames
        .iter()
        .enumerate()
        .map(|(i, f)| json!({"file_path": format!("train/r_{i:03}.png"), "transform_matrix": blender_rows(f)}))
        .collect();
    // Per-frame override, a mask and the egocentric_splats spelling.
    list[1]["fl_x"] = json!(k.fx * 1.5);
    list[2]["mask_path"] = json!("train/r_002_part.png");
    list[3] = json!({"image_path": "train/r_003.png", "fx": k.fx, "fy": k.fy, "cx": k.cx, "cy": k.cy,
                     "transform_matrix": blender_rows(&frames[3]), "timestamp": 1_500_000_000_000u64, "time": 0.25});
    list[4]["depth_file_path"] = json!("train/r_004_depth.png");
    let file = json!({"camera_model": "OPENCV", "fl_x": k.fx, "fl_y": k.fy, "cx": k.cx, "cy": k.cy, "w": 48, "h": 48,
                      "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0, "frames": list});
    let path = dir.join("transforms.json");
    std::fs::write(&path, serde_json::to_vec_pretty(&file).unwrap()).unwrap();
    let ns = load_nerfstudio(&path, &LoadOptions::default()).unwrap();
    assert_eq!(ns.frames.len(), frames.len());
    for (a, b) in ns.frames.iter().zip(&frames) {
        assert!(max_diff(&a.world_to_camera, &b.world_to_camera) < 1e-5);
        assert_eq!(a.image.dimensions(), b.image.dimensions());
    }
    assert!(ns.distortion.iter().all(|d| *d == Distortion::None));
    assert!((ns.frames[0].intrinsics.fx - k.fx).abs() < 1e-4);
    assert!((ns.frames[1].intrinsics.fx - 1.5 * k.fx).abs() < 1e-3);
    // Mask = part ids (255 background, 0 and 1 object): background alpha survives only where
    // the mask is 255, so alpha must not grow and must vanish where the mask is 0.
    let masked = &ns.frames[2].image;
    let part = image::open(dir.join("train/r_002_part.png")).unwrap().into_luma8();
    for (p, m) in masked.pixels().zip(part.pixels()) {
        if m[0] == 0 {
            assert_eq!(p[3], 0);
        }
    }
    assert!((ns.frames[3].timestamp_s - 1500.0).abs() < 1e-6);
    assert_eq!(ns.frames[3].motion_time, Some(0.25));
    assert!(ns.frames[4].depth.is_some() && ns.frames[0].depth.is_none());
    assert_eq!(ns.frames[4].depth, frames[4].depth);

    // Fisheye models are reported, not applied.
    let mut fish = file.clone();
    fish["camera_model"] = json!("FISHEYE624");
    fish["fisheye624_params"] = json!([300.0, 24.0, 24.0, 0.1, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]);
    let fpath = dir.join("transforms_fisheye.json");
    std::fs::write(&fpath, serde_json::to_vec(&fish).unwrap()).unwrap();
    let ns = load_nerfstudio(&fpath, &LoadOptions { depth: false }).unwrap();
    match &ns.distortion[0] {
        Distortion::Fisheye624 { params } => assert_eq!(params.len(), 15),
        other => panic!("{other:?}"),
    }
}

#[test]
fn nerfstudio_bad_input_names_the_file() {
    let dir = scratch("ns_bad");
    let path = dir.join("transforms.json");
    let cases: [(&str, &str); 4] = [
        ("{not json", "transforms.json"),
        ("{\"fl_x\": 10}", "frames"),
        ("{\"fl_x\": 10, \"frames\": [{\"file_path\": \"a.png\", \"transform_matrix\": [[1,0,0]]}]}", "transform_matrix"),
        ("{\"fl_x\": 10, \"frames\": [{\"file_path\": \"missing.png\", \"transform_matrix\": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]}", "missing.png"),
    ];
    for (text, needle) in cases {
        std::fs::write(&path, text).unwrap();
        let err = load_nerfstudio(&path, &LoadOptions::default()).unwrap_err().to_string();
        assert!(err.contains(needle), "{text}: {err}");
        assert!(err.contains("missing.png") || err.contains("transforms.json"), "{err}");
    }
}

#[test]
fn aim_loader_bad_input_names_the_file() {
    let dir = scratch("aim_bad");
    let err = load_aim(&dir, &LoadOptions::default()).unwrap_err().to_string();
    assert!(err.contains("start") && err.contains("transforms_train.json"), "{err}");
    std::fs::create_dir_all(dir.join("start")).unwrap();
    std::fs::create_dir_all(dir.join("motion")).unwrap();
    std::fs::write(
        dir.join("start/transforms_train.json"),
        "{\"camera_angle_x\": 0.7, \"frames\": [{\"file_path\": 3}]}",
    )
    .unwrap();
    let err = load_aim(&dir, &LoadOptions::default()).unwrap_err().to_string();
    assert!(err.contains("start/transforms_train.json") && err.contains("not a transforms file"), "{err}");
    let rows = "[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]";
    std::fs::write(
        dir.join("start/transforms_train.json"),
        format!(
            "{{\"camera_angle_x\": 0.7, \"frames\": [{{\"file_path\": \"./nope\", \"transform_matrix\": {rows}}}]}}"
        ),
    )
    .unwrap();
    let err = load_aim(&dir, &LoadOptions::default()).unwrap_err().to_string();
    assert!(err.contains("nope.png"), "{err}");
    std::fs::write(
        dir.join("start/transforms_train.json"),
        "{\"camera_angle_x\": 0.7, \"frames\": [{\"file_path\": \"x\", \"transform_matrix\": [[2,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]}",
    )
    .unwrap();
    let err = load_aim(&dir, &LoadOptions::default()).unwrap_err().to_string();
    assert!(err.contains("not rigid"), "{err}");
}

/// A COLMAP model of the synthetic start views with GT surface points.
fn colmap_model(frames: &[Frame]) -> ColmapModel {
    let k = frames[0].intrinsics;
    let mut m = ColmapModel::default();
    m.cameras.insert(
        1,
        ColmapCamera {
            id: 1,
            model: "PINHOLE".into(),
            width: k.width,
            height: k.height,
            params: vec![k.fx as f64, k.fy as f64, k.cx as f64, k.cy as f64],
        },
    );
    for (i, f) in frames.iter().enumerate() {
        let mut img = image_from_pose(i as u32 + 1, 1, &format!("train/r_{i:03}.png"), &f.world_to_camera);
        img.points2d = vec![(1.5, 2.25, -1), (3.0, 4.0, 7)];
        m.images.push(img);
    }
    let mesh = aim::mesh::read_obj(&dataset().join("gt/start/part_0.obj")).unwrap();
    for (i, v) in mesh.vertices.iter().enumerate().step_by(3) {
        m.points.push(ColmapPoint {
            id: i as u64 + 1,
            xyz: v.as_dvec3().to_array(),
            rgb: [10, 20, (i % 255) as u8],
            error: 0.5,
            track: vec![(1, 0), (2, 1)],
        });
    }
    m
}

#[test]
fn colmap_text_and_binary_round_trip_and_match_the_aim_poses() {
    let frames = start_frames();
    let model = colmap_model(&frames);
    for (name, binary) in [("colmap_txt", false), ("colmap_bin", true)] {
        let dir = scratch(name);
        if binary {
            write_colmap_bin(&model, &dir).unwrap();
        } else {
            write_colmap_text(&model, &dir).unwrap();
        }
        let back = read_colmap_model(&dir).unwrap();
        assert_eq!(back, model, "{name} round trip");
        let (_, loaded) = load_colmap_frames(&dir, &dataset().join("start"), &LoadOptions::default()).unwrap();
        assert_eq!(loaded.len(), frames.len());
        for (a, b) in loaded.iter().zip(&frames) {
            assert!(max_diff(&a.world_to_camera, &b.world_to_camera) < 1e-5, "{name}: {}", a.source);
            assert_eq!(a.intrinsics, b.intrinsics);
            // Every surface point of the object projects onto the object's silhouette.
            let cam = Camera::new(a.intrinsics, a.world_to_camera);
            let (mut inside, mut total) = (0, 0);
            for p in back.point_positions() {
                if let Some((u, v, _)) = cam.project(p) {
                    if u >= 0.0 && v >= 0.0 && u < 48.0 && v < 48.0 {
                        total += 1;
                        // Vertices sit on edges: allow the silhouette's one-pixel border.
                        let (i, j) = (u as i32, v as i32);
                        let near = (-1..=1).any(|dy| {
                            (-1..=1).any(|dx| {
                                let (x, y) = ((i + dx).clamp(0, 47) as u32, (j + dy).clamp(0, 47) as u32);
                                a.image.get_pixel(x, y)[3] > 0
                            })
                        });
                        inside += near as usize;
                    }
                }
            }
            assert!(total > 20 && inside == total, "{name}: {inside}/{total} on the silhouette");
        }
        assert!(back.cameras[&1].is_pinhole());
    }
}

#[test]
fn colmap_bad_input_is_an_error_naming_the_file_never_a_panic() {
    let frames = start_frames();
    let model = colmap_model(&frames);
    let dir = scratch("colmap_fuzz");
    write_colmap_bin(&model, &dir).unwrap();
    type Parser = fn(&[u8], &Path) -> aim_capture::Result<()>;
    let parsers: [(&str, Parser); 3] = [
        ("cameras.bin", |b, p| parse_cameras_bin(b, p).map(|_| ())),
        ("images.bin", |b, p| parse_images_bin(b, p).map(|_| ())),
        ("points3D.bin", |b, p| parse_points_bin(b, p).map(|_| ())),
    ];
    let mut state = 0x1234_5678u64;
    let mut next = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        state
    };
    for (file, parse) in parsers {
        let path = dir.join(file);
        let bytes = std::fs::read(&path).unwrap();
        parse(&bytes, &path).unwrap();
        // Every truncation is an error naming the file.
        for cut in (0..bytes.len()).step_by(7) {
            let err = parse(&bytes[..cut], &path).unwrap_err().to_string();
            assert!(err.contains(file), "{err}");
        }
        // Random byte changes: errors or (for harmless changes) a model, never a panic.
        for _ in 0..400 {
            let mut b = bytes.clone();
            for _ in 0..1 + next() % 4 {
                let i = (next() % b.len() as u64) as usize;
                b[i] = next() as u8;
            }
            if let Err(e) = parse(&b, &path) {
                assert!(e.to_string().contains(file));
            }
        }
        // A huge count must not allocate.
        let mut b = bytes.clone();
        b[..8].copy_from_slice(&u64::MAX.to_le_bytes());
        assert!(parse(&b, &path).unwrap_err().to_string().contains("cannot fit"));
    }
    // Text: unknown model and wrong parameter counts name the file and line.
    let tdir = scratch("colmap_bad_txt");
    write_colmap_text(&model, &tdir).unwrap();
    std::fs::write(tdir.join("cameras.txt"), "# c\n1 WEIRD 48 48 1 2 3\n").unwrap();
    let err = read_colmap_model(&tdir).unwrap_err().to_string();
    assert!(err.contains("cameras.txt") && err.contains("line 2") && err.contains("WEIRD"), "{err}");
    std::fs::write(tdir.join("cameras.txt"), "1 PINHOLE 48 48 40 40 24\n").unwrap();
    let err = read_colmap_model(&tdir).unwrap_err().to_string();
    assert!(err.contains("needs 4 parameters"), "{err}");
    std::fs::write(tdir.join("cameras.txt"), "2 PINHOLE 48 48 40 40 24 24\n").unwrap();
    let err = read_colmap_model(&tdir).unwrap_err().to_string();
    assert!(err.contains("images.txt") && err.contains("unknown camera 1"), "{err}");
    let empty = scratch("colmap_empty");
    let err = read_colmap_model(&empty).unwrap_err().to_string();
    assert!(err.contains("cameras.bin") && err.contains("missing"), "{err}");
}

#[test]
fn transforms_parsers_survive_mutated_bytes() {
    let dir = dataset().join("start");
    let good = std::fs::read(dir.join("transforms_test.json")).unwrap();
    let path = dir.join("transforms_fuzz.json");
    let mut state = 0x9e37_79b9u64;
    let mut next = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        state
    };
    let (mut ok, mut err) = (0, 0);
    for round in 0..300 {
        let mut b = good.clone();
        if round % 3 == 0 {
            b.truncate((next() % b.len() as u64) as usize);
        } else {
            for _ in 0..1 + next() % 3 {
                let i = (next() % b.len() as u64) as usize;
                b[i] = b"0123456789-.eE,:[]{}\"x "[(next() % 23) as usize];
            }
        }
        std::fs::write(&path, &b).unwrap();
        match aim_capture::dataset::load_aim_transforms(&path, aim_capture::Phase::Scan, &LoadOptions::default()) {
            Ok(frames) => {
                ok += 1;
                assert!(frames.iter().all(|f| aim_capture::frame::is_rigid(&f.world_to_camera, 1e-3)));
            }
            Err(e) => {
                err += 1;
                let s = e.to_string();
                assert!(s.contains("transforms_fuzz.json") || s.contains(".png"), "{s}");
            }
        }
        if let Err(e) = load_nerfstudio(&path, &LoadOptions::default()) {
            let s = e.to_string();
            assert!(s.contains("transforms_fuzz.json") || s.contains(".png"), "{s}");
        }
    }
    assert!(err > 100, "mutations were too mild: {ok} loaded, {err} rejected");
}
