//! The twin in simulators, checked by independent readers: the URDF loads in
//! python `yourdfpy` and in MuJoCo, the MJCF in MuJoCo, with the joints of
//! articulation.json; MuJoCo moving the exported fridge's door to the end of its
//! range puts the door mesh on the ground truth's end-state door. The twins are
//! built from the ground truth (Gaussians on the GT surfaces, the GT joints), so
//! what is tested is the export, not stage II. Needs `python3` with numpy,
//! mujoco and yourdfpy (tests/requirements.txt; tests/run installs them).

use std::path::{Path, PathBuf};
use std::process::Command;

use aim::export::{write_twin, ExportConfig, TwinPart};
use aim::mesh::tsdf::TsdfConfig;
use aim::motion::JointEstimate;
use aim::synth::gt::write_ground_truth;
use aim::synth::object;
use serde_json::Value;

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("aim-sim-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).expect("temp dir");
    d
}

/// Opaque flat Gaussians tiling a mesh's triangles (discs tangent to the
/// surface, about 4 mm apart), as a trained 3DGS puts them on a surface.
fn surface_gaussians(mesh: &aim::mesh::MeshData) -> aim::splat::GaussianSet {
    const SPACING: f32 = 0.004;
    let mut gs = aim::splat::GaussianSet::new(0);
    for t in &mesh.triangles {
        let [a, b, c] = t.map(|i| mesh.vertices[i as usize]);
        let normal = (b - a).cross(c - a);
        let area = 0.5 * normal.length();
        if area <= 0.0 {
            continue;
        }
        let q = glam::Quat::from_rotation_arc(glam::Vec3::Z, normal.normalize());
        let log_scale = glam::Vec3::new(SPACING, SPACING, 0.0005).map(f32::ln);
        // Points on a regular barycentric lattice of the triangle.
        let steps = ((area.sqrt() * std::f32::consts::SQRT_2) / SPACING).ceil().max(1.0) as usize;
        for i in 0..=steps {
            for j in 0..=steps - i {
                let (u, v) = (i as f32 / steps as f32, j as f32 / steps as f32);
                let p = a + u * (b - a) + v * (c - a);
                gs.push(p, log_scale, [q.w, q.x, q.y, q.z], aim::splat::logit(0.95), [0.0; 3], &[]);
            }
        }
    }
    gs
}

/// gt/ of object `name` and a twin of it from its GT surfaces, under `root`.
fn ground_truth_twin(root: &Path, name: &str) -> (PathBuf, PathBuf) {
    let obj = object(name).expect("object");
    let gt = root.join("data").join("gt");
    write_ground_truth(&obj, &gt).expect("gt written");
    let sets: Vec<_> = obj.meshes_at(0.0, 64).iter().map(surface_gaussians).collect();
    let mut parts = vec![TwinPart { gaussians: &sets[0], joint: None }];
    for j in &obj.joints {
        let joint = JointEstimate {
            kind: j.kind,
            axis: j.axis.as_dvec3(),
            origin: j.origin.as_dvec3(),
            amount: f64::from(j.range[1] - j.range[0]),
            translation_along_axis: 0.0,
        };
        parts.push(TwinPart { gaussians: &sets[j.part], joint: Some(joint) });
    }
    let twin = root.join("twin");
    let mesh = TsdfConfig { views: 40, ..TsdfConfig::default() };
    write_twin(&twin, &parts, &mesh, &ExportConfig::default()).expect("twin written");
    (twin, gt)
}

const CHECK: &str = r#"
import json, sys
import numpy as np
import mujoco, yourdfpy

twin, gt = sys.argv[1], sys.argv[2]
art = json.load(open(f"{twin}/articulation.json"))
out = {"joints": []}

def load_obj(path):
    v, f = [], []
    for line in open(path):
        if line.startswith("v "):
            v.append([float(x) for x in line.split()[1:4]])
        elif line.startswith("f "):
            f.append([int(x.split("/")[0]) - 1 for x in line.split()[1:4]])
    return np.array(v), np.array(f)

def sample(v, f, n, rng):
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    area = np.linalg.norm(np.cross(b - a, c - a), axis=1)
    i = rng.choice(len(f), n, p=area / area.sum())
    u, w = rng.random((n, 1)), rng.random((n, 1))
    flip = (u + w) > 1
    u[flip], w[flip] = 1 - u[flip], 1 - w[flip]
    return a[i] + u * (b[i] - a[i]) + w * (c[i] - a[i])

def nearest(x, y, chunk=256):
    return np.concatenate([np.sqrt(((x[i:i + chunk, None] - y[None]) ** 2).sum(-1)).min(1) for i in range(0, len(x), chunk)])

def chamfer(x, y):
    return 0.5 * (nearest(x, y).mean() + nearest(y, x).mean())

urdf = yourdfpy.URDF.load(f"{twin}/object.urdf", load_meshes=False)
models = {"urdf": mujoco.MjModel.from_xml_path(f"{twin}/object.urdf"),
          "mjcf": mujoco.MjModel.from_xml_path(f"{twin}/object.xml")}
rng = np.random.default_rng(0)
for j in art["joints"]:
    name, lo, hi = f"joint_{j['part']}", min(j["range"]), max(j["range"])
    uj = urdf.joint_map[name]
    row = {"part": j["part"], "yourdfpy": {"type": uj.type, "axis": list(uj.axis), "origin": list(uj.origin[:3, 3]),
           "limits": [uj.limit.lower, uj.limit.upper]}}
    truth_end = sample(*load_obj(f"{gt}/end/part_{j['part']}.obj"), 3000, rng)
    truth_start = sample(*load_obj(f"{gt}/start/part_{j['part']}.obj"), 3000, rng)
    # The twin's own mesh moved by articulation.json's joint to the end of its range.
    own_v, own_f = load_obj(f"{twin}/meshes/part_{j['part']}.obj")
    axis, origin, q = np.array(j["axis"]), np.array(j["origin"]), j["range"][1]
    if j["type"] == "revolute":
        k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
        rot = np.eye(3) + np.sin(q) * k + (1 - np.cos(q)) * k @ k
        own_end = (own_v - origin) @ rot.T + origin
    else:
        own_end = own_v + q * axis
    row["mesh_start_chamfer"] = float(chamfer(sample(own_v, own_f, 3000, rng), truth_start))
    for kind, m in models.items():
        jid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, name)
        body = m.jnt_bodyid[jid]
        d = mujoco.MjData(m)
        mujoco.mj_forward(m, d)
        origin = d.xpos[body].tolist()
        d.qpos[m.jnt_qposadr[jid]] = j["range"][1]
        mujoco.mj_forward(m, d)
        # The part's visual mesh: its body's mesh geom with the most vertices (the hull has fewer).
        geoms = [g for g in range(m.ngeom) if m.geom_bodyid[g] == body and m.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH]
        g = max(geoms, key=lambda g: m.mesh_vertnum[m.geom_dataid[g]])
        mid = m.geom_dataid[g]
        verts = m.mesh_vert[m.mesh_vertadr[mid]:m.mesh_vertadr[mid] + m.mesh_vertnum[mid]]
        world = d.geom_xpos[g] + verts @ d.geom_xmat[g].reshape(3, 3).T
        pick = world[rng.choice(len(world), min(3000, len(world)), replace=False)]
        faces = m.mesh_face[m.mesh_faceadr[mid]:m.mesh_faceadr[mid] + m.mesh_facenum[mid]]
        moved = f"{twin}/mujoco_{kind}_part_{j['part']}_end.obj"
        with open(moved, "w") as f:
            f.writelines(f"v {x} {y} {z}\n" for x, y, z in world)
            f.writelines(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in faces)
        row[kind] = {"type": int(m.jnt_type[jid]), "axis": (d.xaxis[jid]).tolist(), "origin": origin,
                     "limits": m.jnt_range[jid].tolist(), "chamfer_end": float(chamfer(pick, truth_end)),
                     "off_own_end": float(nearest(pick[:300], own_end, 8).max()), "moved_mesh": moved}
    out["joints"].append(row)
print(json.dumps(out))
"#;

fn check(twin: &Path, gt: &Path) -> Value {
    let out = Command::new("python3")
        .arg("-c")
        .arg(CHECK)
        .arg(twin)
        .arg(gt)
        .output()
        .expect("python3 is required for this test (with numpy, mujoco and yourdfpy: tests/run installs them)");
    assert!(out.status.success(), "python failed:\n{}", String::from_utf8_lossy(&out.stderr));
    serde_json::from_slice(&out.stdout).expect("python printed JSON")
}

fn close(a: &Value, b: &[f32], tol: f64, what: &str) {
    let a: Vec<f64> = a.as_array().expect("array").iter().map(|x| x.as_f64().expect("number")).collect();
    assert_eq!(a.len(), b.len(), "{what}: {a:?} vs {b:?}");
    for (x, y) in a.iter().zip(b) {
        assert!((x - f64::from(*y)).abs() < tol, "{what}: {a:?} vs {b:?}");
    }
}

/// Every reader sees articulation.json's joints, and MuJoCo's end state is the ground truth's.
fn joints_agree(name: &str) {
    let root = tmp(name);
    let (written, gt) = ground_truth_twin(&root, name);
    // Checked as `aim export` writes it again elsewhere (meshes copied, hulls recomputed).
    let twin = root.join("exported");
    let o = Command::new(env!("CARGO_BIN_EXE_aim"))
        .args(["--log", "warn", "export"])
        .arg(&written)
        .args(["--to", "all", "--out"])
        .arg(&twin)
        .output()
        .expect("runs");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(twin.join("object.ply").is_file() && twin.join("parts/part_1.ply").is_file());
    let art = aim::export::read_articulation(&twin.join("articulation.json")).expect("articulation");
    let report = check(&twin, &gt);
    let rows = report["joints"].as_array().expect("joints");
    assert_eq!(rows.len(), art.joints.len());
    for (row, j) in rows.iter().zip(&art.joints) {
        let (lo, hi) = aim::export::sim::limits(j);
        let revolute = j.kind == aim::motion::JointKind::Revolute;
        let y = &row["yourdfpy"];
        assert_eq!(y["type"], if revolute { "revolute" } else { "prismatic" }, "{row}");
        close(&y["axis"], &j.axis, 1e-5, "yourdfpy axis");
        close(&y["origin"], &j.origin, 1e-5, "yourdfpy origin");
        close(&y["limits"], &[lo, hi], 1e-5, "yourdfpy limits");
        for kind in ["urdf", "mjcf"] {
            let m = &row[kind];
            // mjJNT_SLIDE = 2, mjJNT_HINGE = 3.
            assert_eq!(m["type"], if revolute { 3 } else { 2 }, "{kind}: {row}");
            close(&m["axis"], &j.axis, 1e-5, "mujoco axis");
            close(&m["origin"], &j.origin, 1e-5, "mujoco origin");
            close(&m["limits"], &[lo, hi], 1e-5, "mujoco limits");
            // MuJoCo moves the mesh exactly as the joint says: its vertices land
            // on the twin's own mesh vertices moved by the joint.
            let off = m["off_own_end"].as_f64().expect("distance");
            assert!(off < 1e-4, "{name} {kind}: a vertex {off} m off the joint's motion");
            // Against gt/end: `aim eval`'s Chamfer distance (the paper's form, both
            // directions' mean distances added, on the visible surfaces), from 100k
            // samples a side: at eval's 10k the sampling alone adds ~8 mm on a door.
            let moved = aim::mesh::read_obj(Path::new(m["moved_mesh"].as_str().expect("path"))).expect("moved mesh");
            let truth = aim::mesh::read_obj(&gt.join(format!("end/part_{}.obj", j.part))).expect("gt mesh");
            let samples = |m: &aim::mesh::MeshData| m.sample_outer_surface(100_000, 0);
            let cd = aim::eval::shape::chamfer_points(&samples(&moved), &samples(&truth)).expect("surfaces").l2_mm;
            eprintln!("{name} {kind}: part {} at the end of its range: {cd:.1} mm (Chamfer) from gt/end", j.part);
            assert!(cd < 10.0, "{name} {kind}: {cd} mm (Chamfer) from gt/end");
        }
    }
    let _ = std::fs::remove_dir_all(&root);
}

#[test]
fn the_fridge_twin_opens_in_mujoco_as_in_the_ground_truth() {
    joints_agree("fridge");
}

#[test]
fn the_storage_twin_slides_in_mujoco_as_in_the_ground_truth() {
    joints_agree("storage");
}

#[test]
fn export_settings_with_an_unknown_key_name_the_file() {
    let root = tmp("bad-config");
    let (twin, _) = ground_truth_twin(&root, "storage");
    let config = root.join("export.toml");
    std::fs::write(&config, "density = 200.0\nefort = 5.0\n").expect("written");
    let o = Command::new(env!("CARGO_BIN_EXE_aim"))
        .args(["--log", "warn", "export"])
        .arg(&twin)
        .args(["--to", "urdf", "--out"])
        .arg(root.join("out"))
        .arg("--config")
        .arg(&config)
        .output()
        .expect("runs");
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && e.contains("export.toml") && e.contains("efort") && !e.contains("panicked"), "{e}");
    let _ = std::fs::remove_dir_all(&root);
}

#[test]
fn render_twin_draws_a_turntable_and_names_a_part_without_a_joint() {
    let root = tmp("render");
    let (twin, _) = ground_truth_twin(&root, "storage");
    let camera = aim::camera::Camera::look_at(
        aim::camera::Intrinsics::from_fov_x(64, 64, 0.8),
        glam::Vec3::new(0.0, -3.0, 1.0),
        glam::Vec3::ZERO,
        glam::Vec3::Z,
    );
    let camera_file = root.join("camera.json");
    std::fs::write(&camera_file, serde_json::to_vec(&aim::camera::CameraFile::from_camera(&camera)).unwrap()).unwrap();
    let render = |extra: &[&str], out: &Path| {
        Command::new(env!("CARGO_BIN_EXE_aim"))
            .args(["--log", "warn", "render-twin"])
            .arg(&twin)
            .arg("--camera")
            .arg(&camera_file)
            .arg("--out")
            .arg(out)
            .args(extra)
            .output()
            .expect("runs")
    };
    let frames = root.join("turntable");
    let o = render(&["--turntable", "3"], &frames);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let images: Vec<_> =
        (0..3).map(|k| image::open(frames.join(format!("frame_{k:04}.png"))).expect("frame").to_rgb8()).collect();
    assert_ne!(images[0], images[2], "the camera turns and the drawer slides");
    // The drawer opened towards the camera covers more of the image than closed.
    let covered = |img: &image::RgbImage| img.pixels().filter(|p| p.0 != [255, 255, 255]).count();
    let (closed, open) = (root.join("closed.png"), root.join("open.png"));
    assert!(render(&[], &closed).status.success() && render(&["--state", "1=0.35"], &open).status.success());
    let (c, o) = (covered(&image::open(&closed).unwrap().to_rgb8()), covered(&image::open(&open).unwrap().to_rgb8()));
    assert!(o > c, "open {o} px, closed {c} px");
    let bad = render(&["--state", "7=1.0"], &root.join("bad.png"));
    let e = String::from_utf8_lossy(&bad.stderr);
    assert!(!bad.status.success() && e.contains("part 7 has no joint") && !e.contains("panicked"), "{e}");
    let _ = std::fs::remove_dir_all(&root);
}
