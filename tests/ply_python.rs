//! PLY interoperability with python `plyfile` (the library the original 3DGS code
//! uses): our files load there with the standard property names, and files it
//! writes in the 3DGS layout load here. Needs `python3` with `plyfile` and
//! `numpy` (installed by `.ci/run`); the tests fail, not skip, without them.

use std::path::{Path, PathBuf};
use std::process::Command;

use aim::splat::ply::{read_ply, write_ply};
use aim::splat::{GaussianSet, ParamGroup};
use glam::Vec3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde_json::Value;

fn temp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("aim-ply-python-{}-{name}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// Run a python script with arguments; returns its stdout parsed as JSON.
fn python(script: &str, args: &[&Path]) -> Value {
    let out = Command::new("python3")
        .arg("-c")
        .arg(script)
        .args(args)
        .output()
        .expect("python3 is required for this test (with plyfile and numpy: pip install plyfile numpy)");
    assert!(
        out.status.success(),
        "python failed (needs plyfile and numpy: pip install plyfile numpy):\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).expect("python printed JSON")
}

fn standard_names(degree: u32) -> Vec<String> {
    let n_rest = ((degree + 1) * (degree + 1) - 1) * 3;
    let mut names: Vec<String> = ["x", "y", "z", "nx", "ny", "nz"].map(String::from).into();
    names.extend((0..3).map(|i| format!("f_dc_{i}")));
    names.extend((0..n_rest).map(|i| format!("f_rest_{i}")));
    names.push("opacity".into());
    names.extend((0..3).map(|i| format!("scale_{i}")));
    names.extend((0..4).map(|i| format!("rot_{i}")));
    names
}

/// The value a standard-layout file holds for property `name` of Gaussian `i`.
fn expected(set: &GaussianSet, i: usize, name: &str) -> f32 {
    let rest_k = set.width(ParamGroup::ShRest) / 3;
    let idx = |prefix: &str| name.strip_prefix(prefix).map(|s| s.parse::<usize>().unwrap());
    match name {
        "x" | "y" | "z" => set.means[3 * i + (name.as_bytes()[0] - b'x') as usize],
        "nx" | "ny" | "nz" => 0.0,
        "opacity" => set.opacity_logits[i],
        _ => {
            if let Some(j) = idx("f_dc_") {
                set.sh_dc[3 * i + j]
            } else if let Some(j) = idx("f_rest_") {
                // Channel-major in the file: j = c * rest_k + k.
                set.sh_rest[3 * rest_k * i + 3 * (j % rest_k) + j / rest_k]
            } else if let Some(j) = idx("scale_") {
                set.log_scales[3 * i + j]
            } else if let Some(j) = idx("rot_") {
                set.rotations[4 * i + j]
            } else {
                panic!("unexpected property {name}")
            }
        }
    }
}

const DUMP: &str = r#"
import json, sys
from plyfile import PlyData
ply = PlyData.read(sys.argv[1])
v = ply["vertex"]
print(json.dumps({
    "binary_le": (not ply.text) and ply.byte_order in ("<", "="),
    "elements": [e.name for e in ply.elements],
    "names": [p.name for p in v.properties],
    "types": [v.data.dtype[p.name].str for p in v.properties],
    "rows": [[float(x) for x in row] for row in v.data.tolist()],
}))
"#;

#[test]
fn aim_ply_loads_in_plyfile() {
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let mut set = GaussianSet::new(2);
    let rest_w = set.width(ParamGroup::ShRest);
    for _ in 0..6 {
        let mut r = || rng.random_range(-3.0f32..3.0);
        let rest: Vec<f32> = (0..rest_w).map(|_| r()).collect();
        set.push(Vec3::new(r(), r(), r()), Vec3::new(r(), r(), r()), [r(), r(), r(), r()], r(), [r(), r(), r()], &rest);
    }
    let dir = temp_dir("aim-to-plyfile");
    let path = dir.join("splats.ply");
    write_ply(&path, &set).unwrap();

    let dump = python(DUMP, &[&path]);
    assert_eq!(dump["binary_le"], Value::Bool(true));
    assert_eq!(dump["elements"], serde_json::json!(["vertex"]));
    let names: Vec<String> = serde_json::from_value(dump["names"].clone()).unwrap();
    assert_eq!(names, standard_names(2));
    assert!(dump["types"].as_array().unwrap().iter().all(|t| t == "<f4"), "{}", dump["types"]);
    let rows = dump["rows"].as_array().unwrap();
    assert_eq!(rows.len(), set.len());
    for (i, row) in rows.iter().enumerate() {
        for (name, v) in names.iter().zip(row.as_array().unwrap()) {
            assert_eq!(v.as_f64().unwrap() as f32, expected(&set, i, name), "vertex {i} {name}");
        }
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Writes a degree-3 file exactly as the original 3DGS `save_ply` does, with
/// plyfile, and dumps the values it wrote.
const WRITE_3DGS: &str = r#"
import json, sys
import numpy as np
from plyfile import PlyData, PlyElement
n = 5
attrs = ["x", "y", "z", "nx", "ny", "nz"] + [f"f_dc_{i}" for i in range(3)] \
    + [f"f_rest_{i}" for i in range(45)] + ["opacity"] + [f"scale_{i}" for i in range(3)] \
    + [f"rot_{i}" for i in range(4)]
rng = np.random.default_rng(7)
values = rng.uniform(-2, 2, size=(n, len(attrs))).astype(np.float32)
values[:, 3:6] = 0
elements = np.empty(n, dtype=[(a, "f4") for a in attrs])
elements[:] = list(map(tuple, values))
PlyData([PlyElement.describe(elements, "vertex")]).write(sys.argv[1])
print(json.dumps({"names": attrs, "rows": [[float(x) for x in row] for row in values]}))
"#;

#[test]
fn plyfile_3dgs_ply_loads_in_aim() {
    let dir = temp_dir("plyfile-to-aim");
    let path = dir.join("point_cloud.ply");
    let dump = python(WRITE_3DGS, &[&path]);
    let set = read_ply(&path).unwrap();
    assert_eq!(set.sh_degree, 3);
    assert_eq!(set.len(), 5);
    set.check_shapes().unwrap();
    let names: Vec<String> = serde_json::from_value(dump["names"].clone()).unwrap();
    for (i, row) in dump["rows"].as_array().unwrap().iter().enumerate() {
        for (name, v) in names.iter().zip(row.as_array().unwrap()) {
            assert_eq!(expected(&set, i, name), v.as_f64().unwrap() as f32, "vertex {i} {name}");
        }
    }
    std::fs::remove_dir_all(&dir).unwrap();
}
