//! Stage I end to end on a small synthetic dataset: training improves the
//! start-state renders, a killed run resumes to the same result, static.ply
//! reloads (in aim and in python plyfile) and reproduces the reported PSNR, and
//! bad datasets fail with errors naming the file.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::atomic::AtomicBool;

use aim::synth::dataset::{write_dataset, SynthConfig};
use aim::train::config::StaticConfig;
use aim::train::static_stage::{evaluate, run_static, RunOutcome, RunSetup};
use aim::viz::{Viz, VizTarget};
use aim_capture::dataset::{load_aim_transforms, LoadOptions};
use aim_capture::Phase;

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("aim-test-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).expect("temp dir");
    d
}

fn small_dataset(dir: &Path) {
    let cfg = SynthConfig {
        resolution: 48,
        scan_views: 24,
        motion_frames: 2,
        end_views: 1,
        test_views: 3,
        motion_test_every: 0,
        samples_per_pixel: 1,
        ..Default::default()
    };
    let obj = aim::synth::objects::object("storage").expect("known object");
    write_dataset(&obj, dir, &cfg, &|_, _| {}).expect("dataset written");
}

fn small_config() -> StaticConfig {
    let mut c = StaticConfig::cpu();
    c.iterations = 240;
    c.resolution = 0;
    c.checkpoint_interval = 60;
    c.init.points = 1500;
    c.density.from_iter = 40;
    c.density.until_iter = 200;
    c.density.interval = 40;
    c.density.opacity_reset_interval = 120;
    c
}

fn views(dataset: &Path, file: &str) -> Vec<aim::train::views::TrainView> {
    let frames = load_aim_transforms(&dataset.join("start").join(file), Phase::Scan, &LoadOptions { depth: false })
        .expect("loads");
    aim::train::views::views_from_frames(&frames, 0).expect("views")
}

fn setup(dir: &Path, resume: bool) -> RunSetup<'_> {
    RunSetup { run_dir: dir, resume, init: None, arriving: None, backend: aim::render::Backend::Cpu }
}

fn finished(outcome: RunOutcome) -> aim::train::static_stage::StaticMetrics {
    match outcome {
        RunOutcome::Finished(m) => *m,
        RunOutcome::Interrupted(i) => panic!("unexpected interruption at {i}"),
    }
}

#[test]
fn interrupted_run_resumes_to_the_uninterrupted_result_and_outputs_reload() {
    let root = tmp("resume");
    let data = root.join("data");
    small_dataset(&data);
    let (train, test) = (views(&data, "transforms_train.json"), views(&data, "transforms_test.json"));
    let cfg = small_config();
    let never = AtomicBool::new(false);
    // The uninterrupted run also logs to rerun; logging must not change the result.
    let rrd = root.join("full.rrd");
    let viz = Viz::new("aim-test", &VizTarget::File(rrd.clone())).expect("rrd opens");

    // Before training: random initial Gaussians render poorly.
    let init = aim::train::static_stage::GaussianTrainer::new(cfg.clone(), &train, None).expect("trainer");
    let psnr_init = evaluate(&init.gaussians, &test, glam::Vec3::ONE).iter().map(|m| m.psnr).sum::<f32>() / 3.0;

    let full = finished(
        run_static(cfg.clone(), &train, &test, &setup(&root.join("full"), false), &never, &viz, |_| {}).expect("runs"),
    );
    assert!(full.mean_psnr > psnr_init + 5.0, "training should help: {psnr_init} -> {}", full.mean_psnr);

    // Interrupt after iteration 100 (between a densification and an opacity reset), then resume.
    let stop = AtomicBool::new(false);
    let out =
        run_static(cfg.clone(), &train, &test, &setup(&root.join("split"), false), &stop, &Viz::disabled(), |r| {
            if r.iteration == 100 {
                stop.store(true, std::sync::atomic::Ordering::SeqCst);
            }
        })
        .expect("runs");
    assert!(matches!(out, RunOutcome::Interrupted(100)));
    let resumed = finished(
        run_static(cfg.clone(), &train, &test, &setup(&root.join("split"), true), &never, &Viz::disabled(), |_| {})
            .expect("resumes"),
    );
    assert!((resumed.mean_psnr - full.mean_psnr).abs() < 0.2, "{} vs {}", resumed.mean_psnr, full.mean_psnr);
    let a = aim::splat::ply::read_ply(&root.join("full").join("static.ply")).expect("reads");
    let b = aim::splat::ply::read_ply(&root.join("split").join("static.ply")).expect("reads");
    assert_eq!(a, b, "a resumed run must repeat the uninterrupted one exactly");

    // static.ply reproduces the reported PSNR when rendered from the test poses.
    let again = evaluate(&a, &test, glam::Vec3::from(cfg.eval_background));
    for (m, r) in again.iter().zip(&full.test_views) {
        assert!((m.psnr - r.psnr).abs() < 1e-3, "{} vs reported {}", m.psnr, r.psnr);
    }
    // ... and loads in python plyfile with the same count.
    let py = Command::new("python3")
        .args(["-c", "import sys, plyfile; print(plyfile.PlyData.read(sys.argv[1])['vertex'].count)"])
        .arg(root.join("full").join("static.ply"))
        .output()
        .expect("python3 runs");
    assert!(py.status.success(), "plyfile failed: {}", String::from_utf8_lossy(&py.stderr));
    assert_eq!(String::from_utf8_lossy(&py.stdout).trim(), a.len().to_string());
    // The rerun log is a valid recording (checked by rerun's own CLI from the python SDK)
    // holding the training scalars, the Gaussians and the cameras.
    drop(viz);
    // `python3 -m rerun`: the SDK's CLI without relying on a console-script shim.
    let verify =
        Command::new("python3").args(["-m", "rerun", "rrd", "verify"]).arg(&rrd).output().expect("rerun CLI runs");
    assert!(verify.status.success(), "rerun rrd verify: {}", String::from_utf8_lossy(&verify.stderr));
    let print = Command::new("python3")
        .args(["-m", "rerun", "rrd", "print", "--verbose"])
        .arg(&rrd)
        .output()
        .expect("rerun CLI runs");
    let listing = String::from_utf8_lossy(&print.stdout);
    for entity in ["/train/loss", "/world/gaussians", "/world/train_cameras/000", "/eval/render"] {
        assert!(listing.contains(entity), "{entity} missing from the recording");
    }
    // The run folder has everything the CLI promises.
    for f in ["config.toml", "metrics.json", "checkpoint.bin", "test/000.png"] {
        assert!(root.join("full").join(f).exists(), "missing {f}");
    }
}

#[test]
fn killed_cli_run_resumes_from_its_last_checkpoint() {
    let root = tmp("kill");
    let data = root.join("data");
    small_dataset(&data);
    let mut cfg = small_config();
    cfg.iterations = 400;
    cfg.checkpoint_interval = 50;
    let cfg_path = root.join("cfg.toml");
    std::fs::write(&cfg_path, toml::to_string(&cfg).expect("toml")).expect("write");
    let bin = env!("CARGO_BIN_EXE_aim");
    let run = |out: &str, resume: bool| {
        let mut c = Command::new(bin);
        c.args(["--log", "warn", "train-static"])
            .arg(&data)
            .arg("--out")
            .arg(root.join(out))
            .arg("--config")
            .arg(&cfg_path);
        if resume {
            c.arg("--resume");
        }
        c
    };
    let full = run("full", false).output().expect("runs");
    assert!(full.status.success(), "{}", String::from_utf8_lossy(&full.stderr));

    let mut child = run("killed", false).spawn().expect("spawns");
    let ck = root.join("killed").join("checkpoint.bin");
    let start = std::time::Instant::now();
    while !ck.exists() {
        assert!(start.elapsed().as_secs() < 120, "no checkpoint appeared");
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
    child.kill().expect("killed");
    let _ = child.wait();
    assert!(!root.join("killed").join("metrics.json").exists(), "the run was killed before finishing");
    let resumed = run("killed", true).output().expect("runs");
    assert!(resumed.status.success(), "{}", String::from_utf8_lossy(&resumed.stderr));
    let metric = |dir: &str| -> f64 {
        let v: serde_json::Value =
            serde_json::from_slice(&std::fs::read(root.join(dir).join("metrics.json")).expect("metrics"))
                .expect("json");
        v["mean_psnr"].as_f64().expect("psnr")
    };
    assert!((metric("full") - metric("killed")).abs() < 0.2, "{} vs {}", metric("full"), metric("killed"));
}

fn cli_error(dataset: &Path) -> String {
    let out = Command::new(env!("CARGO_BIN_EXE_aim"))
        .args(["--log", "error", "train-static"])
        .arg(dataset)
        .arg("--out")
        .arg(dataset.join("run"))
        .output()
        .expect("runs");
    assert!(!out.status.success(), "a bad dataset must fail");
    String::from_utf8_lossy(&out.stderr).into_owned()
}

#[test]
fn bad_datasets_are_reported_with_the_file() {
    let root = tmp("bad");
    let data = root.join("data");
    small_dataset(&data);
    let transforms = data.join("start").join("transforms_train.json");
    let original = std::fs::read_to_string(&transforms).expect("reads");
    let mut json: serde_json::Value = serde_json::from_str(&original).expect("json");

    // Missing image.
    std::fs::remove_file(data.join("start").join("train").join("r_003.png")).expect("removed");
    let e = cli_error(&data);
    assert!(e.contains("r_003"), "{e}");
    small_dataset(&data);

    // Image of the wrong size.
    image::RgbaImage::new(20, 20).save(data.join("start").join("train").join("r_004.png")).expect("saved");
    let e = cli_error(&data);
    assert!(e.contains("r_004") && e.contains("20x20"), "{e}");
    small_dataset(&data);

    // Non-invertible pose.
    json["frames"][2]["transform_matrix"] = serde_json::json!([[0, 0, 0, 1], [0, 0, 0, 1], [0, 0, 0, 1], [0, 0, 0, 1]]);
    std::fs::write(&transforms, json.to_string()).expect("write");
    let e = cli_error(&data);
    assert!(e.contains("transforms_train.json") && e.contains("frame 2"), "{e}");

    // Empty frame list.
    json["frames"] = serde_json::json!([]);
    std::fs::write(&transforms, json.to_string()).expect("write");
    let e = cli_error(&data);
    assert!(e.contains("transforms_train.json") && e.contains("empty"), "{e}");
}

#[test]
fn training_starts_from_a_given_point_cloud_in_ply_or_colmap_form() {
    let root = tmp("init");
    let data = root.join("data");
    small_dataset(&data);
    // A point cloud written by python plyfile (an independent writer): points on the
    // storage object's ground-truth start meshes, coloured, as uchar red/green/blue.
    let mesh_dir = data.join("gt").join("start");
    let mut pts = Vec::new();
    for entry in std::fs::read_dir(&mesh_dir).expect("gt meshes") {
        let mesh = aim::mesh::read_obj(&entry.expect("entry").path()).expect("obj");
        pts.extend(mesh.vertices);
    }
    assert!(pts.len() > 50);
    let xyz = pts.iter().map(|p| format!("({},{},{},200,100,50)", p.x, p.y, p.z)).collect::<Vec<_>>().join(",");
    let ply = root.join("cloud.ply");
    let script = format!(
        "import numpy as np, plyfile, sys\n\
         v = np.array([{xyz}], dtype=[('x','f4'),('y','f4'),('z','f4'),('red','u1'),('green','u1'),('blue','u1')])\n\
         plyfile.PlyData([plyfile.PlyElement.describe(v, 'vertex')]).write(sys.argv[1])"
    );
    let py = Command::new("python3").arg("-c").arg(&script).arg(&ply).output().expect("python3 runs");
    assert!(py.status.success(), "{}", String::from_utf8_lossy(&py.stderr));
    let cloud = aim::splat::ply::read_point_cloud(&ply).expect("reads");
    assert_eq!(cloud.points.len(), pts.len());
    assert!((cloud.points[7] - pts[7]).length() < 1e-6);
    let c = cloud.colors.as_ref().expect("colours")[0];
    assert!((c - glam::Vec3::new(200.0, 100.0, 50.0) / 255.0).length() < 1e-6);

    // The trainer starts from exactly those points, coloured.
    let train = views(&data, "transforms_train.json");
    let t = aim::train::static_stage::GaussianTrainer::new(small_config(), &train, Some(&cloud)).expect("trainer");
    assert_eq!(t.gaussians.len(), pts.len());
    assert_eq!(t.gaussians.mean(3), cloud.points[3]);
    let rendered_dc = t.gaussians.sh_dc[0] * aim::render::sh::SH_C0 + 0.5;
    assert!((rendered_dc - 200.0 / 255.0).abs() < 1e-5);

    // The CLI takes the PLY, and a COLMAP model folder; a missing file is named.
    let mut cfg = small_config();
    cfg.iterations = 20;
    let cfg_path = root.join("cfg.toml");
    std::fs::write(&cfg_path, toml::to_string(&cfg).expect("toml")).expect("write");
    let colmap = root.join("sparse");
    std::fs::create_dir_all(&colmap).expect("dir");
    let model = aim_capture::dataset::ColmapModel {
        cameras: Default::default(),
        images: Vec::new(),
        points: pts
            .iter()
            .enumerate()
            .map(|(i, p)| aim_capture::dataset::ColmapPoint {
                id: i as u64 + 1,
                xyz: p.as_dvec3().to_array(),
                rgb: [10, 20, 30],
                error: 0.5,
                track: Vec::new(),
            })
            .collect(),
    };
    aim_capture::dataset::write_colmap_text(&model, &colmap).expect("colmap written");
    for (init, out) in [(ply.clone(), "from_ply"), (colmap.clone(), "from_colmap")] {
        let o = Command::new(env!("CARGO_BIN_EXE_aim"))
            .args(["--log", "warn", "train-static"])
            .arg(&data)
            .arg("--out")
            .arg(root.join(out))
            .arg("--config")
            .arg(&cfg_path)
            .arg("--init-points")
            .arg(&init)
            .output()
            .expect("runs");
        assert!(o.status.success(), "{out}: {}", String::from_utf8_lossy(&o.stderr));
    }
    let missing = root.join("nope.ply");
    let o = Command::new(env!("CARGO_BIN_EXE_aim"))
        .args(["--log", "error", "train-static"])
        .arg(&data)
        .arg("--out")
        .arg(root.join("x"))
        .arg("--init-points")
        .arg(&missing)
        .output()
        .expect("runs");
    assert!(!o.status.success() && String::from_utf8_lossy(&o.stderr).contains("nope.ply"));
}

/// Written to a pipe (a log file, CI), the CLI's output is plain text: no colour
/// escapes from the log formatter, no progress-bar redraws, and progress still
/// reported as log lines.
#[test]
fn output_to_a_pipe_is_plain_text_with_progress_lines() {
    let root = tmp("plain");
    let data = root.join("data");
    small_dataset(&data);
    let o = Command::new(env!("CARGO_BIN_EXE_aim"))
        .args(["--log", "info", "train-static"])
        .arg(&data)
        .arg("--out")
        .arg(root.join("run"))
        .args(["--iterations", "40"])
        .env_remove("NO_COLOR")
        .output()
        .expect("runs");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let text = [o.stdout, o.stderr].concat();
    let text = String::from_utf8_lossy(&text);
    assert!(!text.contains('\u{1b}'), "escape sequences in non-terminal output:\n{text}");
    assert!(!text.contains('\r'), "carriage returns (bar redraws) in non-terminal output:\n{text}");
    assert!(text.contains("stage I 40/40"), "no progress line in:\n{text}");
}
