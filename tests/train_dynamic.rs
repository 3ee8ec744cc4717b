//! `aim train-dynamic` end to end: on a tiny synthetic dataset it runs from a
//! stage I result, writes its outputs and resumes exactly; bad input names the
//! file; on the benchmark's fridge (stages I and II at the cpu presets, about
//! three minutes) it finds the one door with its joint and motion, so a stage II
//! that learns no motion, or the wrong one, fails here; and its twin, rendered
//! by `aim render-twin` with the door at the end of its range, shows the
//! dataset's end-state test views.

use std::path::PathBuf;
use std::process::Command;

use aim::synth::dataset::{write_dataset, SynthConfig};

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("aim-dyn-cli-{}-{name}", std::process::id()));
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
fn train_dynamic_runs_from_a_stage_one_result_and_writes_its_outputs() {
    let root = tmp("run");
    let data = root.join("data");
    let cfg = SynthConfig {
        resolution: 32,
        scan_views: 6,
        motion_frames: 10,
        end_views: 1,
        test_views: 1,
        motion_test_every: 5,
        samples_per_pixel: 1,
        ..Default::default()
    };
    write_dataset(&aim::synth::object("fridge").expect("object"), &data, &cfg, &|_, _| {}).expect("written");
    let st =
        aim().arg("train-static").arg(&data).arg("--out").arg(root.join("s")).args(["--iterations", "20"]).output();
    let st = st.expect("runs");
    assert!(st.status.success(), "{}", String::from_utf8_lossy(&st.stderr));
    let dy = aim()
        .arg("train-dynamic")
        .arg(&data)
        .arg("--static")
        .arg(root.join("s").join("static.ply"))
        .arg("--out")
        .arg(root.join("d"))
        .args(["--iterations", "30"])
        .arg("--rrd")
        .arg(root.join("d.rrd"))
        .output()
        .expect("runs");
    assert!(dy.status.success(), "{}", String::from_utf8_lossy(&dy.stderr));
    // The rerun log holds stage II's scalars and sets (rerun's own CLI reads it).
    let print = Command::new("python3")
        .args(["-m", "rerun", "rrd", "print", "--verbose"])
        .arg(root.join("d.rrd"))
        .output()
        .expect("rerun CLI runs");
    assert!(print.status.success(), "{}", String::from_utf8_lossy(&print.stderr));
    let listing = String::from_utf8_lossy(&print.stdout);
    for entity in ["/stage2/psnr", "/stage2/tracked/t0", "/stage2/tracked/t1"] {
        assert!(listing.contains(entity), "{entity} missing from the recording");
    }
    let stdout = String::from_utf8_lossy(&dy.stdout);
    assert!(stdout.contains("motion test PSNR") && stdout.contains("moving part(s) found"), "{stdout}");
    for f in ["moving.ply", "static_pruned.ply", "track.bin", "checkpoint.bin", "twin/object.urdf"] {
        assert!(root.join("d").join(f).exists(), "missing {f}");
    }
    let twin = root.join("d").join("twin");
    let art: aim::export::Articulation =
        serde_json::from_slice(&std::fs::read(twin.join("articulation.json")).expect("read")).expect("json");
    assert_eq!(art.parts[0].name, "base");
    assert_eq!(art.joints.len() + 1, art.parts.len(), "one joint per moving part");
    for p in &art.parts {
        let g = aim::splat::ply::read_ply(&twin.join(&p.gaussians)).expect("part reloads");
        assert_eq!(g.len(), p.count);
    }
    // The URDF parses as XML with one joint per moving part (Python's own parser).
    let check = Command::new("python3")
        .arg("-c")
        .arg("import sys, xml.etree.ElementTree as E; r = E.parse(sys.argv[1]).getroot(); print(len(r.findall('link')), len(r.findall('joint')))")
        .arg(twin.join("object.urdf"))
        .output()
        .expect("python3 runs");
    assert!(check.status.success(), "{}", String::from_utf8_lossy(&check.stderr));
    assert_eq!(String::from_utf8_lossy(&check.stdout).trim(), format!("{} {}", art.parts.len(), art.joints.len()));
    aim::splat::ply::read_ply(&root.join("d").join("moving.ply")).expect("moving set reloads");

    // The paper's dual field refuses to resume a checkpoint of another configuration.
    let paper = |iterations: u32, resume: bool| {
        let config = root.join(format!("paper_{iterations}.toml"));
        let toml = format!("preset = \"paper\"\niterations = {iterations}\nwarmup_iterations = 1\nstatic_opacity_only_iterations = 2\ntime_curriculum_iterations = 0\n");
        std::fs::write(&config, toml).expect("config written");
        let mut c = aim();
        c.arg("train-dynamic")
            .arg(&data)
            .arg("--static")
            .arg(root.join("s").join("static.ply"))
            .arg("--out")
            .arg(root.join("p"))
            .arg("--config")
            .arg(&config);
        if resume {
            c.arg("--resume");
        }
        c.output().expect("runs")
    };
    let first = paper(4, false);
    assert!(first.status.success(), "{}", String::from_utf8_lossy(&first.stderr));
    let other = paper(6, true);
    let e = String::from_utf8_lossy(&other.stderr);
    assert!(!other.status.success() && e.contains("another configuration") && !e.contains("panicked"), "{e}");

    // A missing static file is named.
    let bad = aim()
        .arg("train-dynamic")
        .arg(&data)
        .arg("--static")
        .arg(root.join("missing.ply"))
        .arg("--out")
        .arg(root.join("x"))
        .output()
        .expect("runs");
    assert!(!bad.status.success() && String::from_utf8_lossy(&bad.stderr).contains("missing.ply"));
}

#[test]
fn interrupted_tracking_resumes_to_the_uninterrupted_result() {
    use std::sync::atomic::{AtomicBool, Ordering};

    use aim::mesh::tsdf::TsdfConfig;
    use aim::render::Backend;
    use aim::train::config::StageConfig;
    use aim::train::dynamic_run::{run_dynamic, DynamicOutcome, RunControl, StageTwoInput, StageTwoProgress};
    use aim::train::dynamic_stage::DynamicConfig;

    let root = tmp("resume");
    let data = root.join("data");
    let cfg = SynthConfig {
        resolution: 32,
        scan_views: 6,
        motion_frames: 12,
        end_views: 1,
        test_views: 1,
        motion_test_every: 6,
        samples_per_pixel: 1,
        ..Default::default()
    };
    write_dataset(&aim::synth::object("storage").expect("object"), &data, &cfg, &|_, _| {}).expect("written");
    let st =
        aim().arg("train-static").arg(&data).arg("--out").arg(root.join("s")).args(["--iterations", "30"]).output();
    assert!(st.expect("runs").status.success());
    let static_ply = root.join("s").join("static.ply");
    let dyn_cfg = DynamicConfig::resolve(None, "cpu", Some(0), Some(60)).expect("config");
    let viz = aim::viz::Viz::disabled();
    let mesh = TsdfConfig { max_voxels_per_axis: 24, views: 8, ..TsdfConfig::default() };
    let never = AtomicBool::new(false);
    let run = |out: &str, control: &RunControl, stop_after: Option<u32>| {
        let input = StageTwoInput::load(&data, &dyn_cfg).expect("dataset");
        run_dynamic(input, &static_ply, &root.join(out), dyn_cfg.clone(), &mesh, control, |p| {
            let stop = matches!(p, StageTwoProgress::Step(s) if stop_after.is_some_and(|k| s.iteration >= k));
            if stop {
                control.interrupt.store(true, Ordering::SeqCst);
            }
        })
        .expect("stage II runs")
    };
    let full = run("full", &RunControl { resume: false, interrupt: &never, viz: &viz, backend: Backend::Cpu }, None);
    assert!(matches!(full, DynamicOutcome::Finished { .. }));
    let stop = AtomicBool::new(false);
    let first = run("cut", &RunControl { resume: false, interrupt: &stop, viz: &viz, backend: Backend::Cpu }, Some(20));
    assert!(matches!(first, DynamicOutcome::Interrupted(it) if it < 60), "the run stops early");
    let go_on = AtomicBool::new(false);
    let second = run("cut", &RunControl { resume: true, interrupt: &go_on, viz: &viz, backend: Backend::Cpu }, None);
    assert!(matches!(second, DynamicOutcome::Finished { .. }));
    let a = std::fs::read(root.join("full").join("track.bin")).expect("track");
    let b = std::fs::read(root.join("cut").join("track.bin")).expect("track");
    assert_eq!(a, b, "a resumed run must repeat the uninterrupted one exactly");
    // Interrupted once the tracking is done (during the end scan or the end
    // phase), it stops there too, and its resumption ends as the uninterrupted run.
    let late = AtomicBool::new(false);
    let stopped =
        run("late", &RunControl { resume: false, interrupt: &late, viz: &viz, backend: Backend::Cpu }, Some(60));
    assert!(matches!(stopped, DynamicOutcome::Interrupted(60)), "the end phase stops on the interrupt");
    assert!(!root.join("late").join("track.bin").exists(), "an interrupted end phase writes no result");
    let go_on = AtomicBool::new(false);
    let resumed = run("late", &RunControl { resume: true, interrupt: &go_on, viz: &viz, backend: Backend::Cpu }, None);
    assert!(matches!(resumed, DynamicOutcome::Finished { .. }));
    let c = std::fs::read(root.join("late").join("track.bin")).expect("track");
    assert_eq!(a, c, "a run resumed in its end phase must repeat the uninterrupted one exactly");
    // A new run in a used folder trains its own end scan: the one there may be
    // of another dataset (here: the start state's scan planted in its place).
    let scan_path = root.join("full").join("end_scan.ply");
    let scan = std::fs::read(&scan_path).expect("the end scan");
    std::fs::copy(&static_ply, &scan_path).expect("planted");
    let again = run("full", &RunControl { resume: false, interrupt: &never, viz: &viz, backend: Backend::Cpu }, None);
    assert!(matches!(again, DynamicOutcome::Finished { .. }));
    assert_eq!(std::fs::read(&scan_path).expect("the end scan"), scan, "a new run must scan the end state again");
    // Resuming with another configuration is refused, naming the checkpoint.
    let mut other = dyn_cfg.clone();
    other.track.nodes += 1;
    let err = run_dynamic(
        StageTwoInput::load(&data, &other).expect("dataset"),
        &static_ply,
        &root.join("cut"),
        other,
        &mesh,
        &RunControl { resume: true, interrupt: &never, viz: &viz, backend: Backend::Cpu },
        |_| {},
    )
    .err()
    .expect("refused");
    assert!(err.to_string().contains("checkpoint.bin"), "{err}");
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
    // Free tracking as it was when the door was found (t <= 0.4), measured
    // 2026-12-03: the door's nodes 14, 26, 49, 88 mm off at t = 0.1-0.4 (the door
    // has turned 11-44 degrees), the body's 1.4, 1.7, 7.9, 33 mm (it drifts late).
    let free = metrics.tracking_error_at_discovery.as_ref().expect("recorded at discovery");
    let times: Vec<f32> = free.iter().map(|e| e.time).collect();
    assert_eq!(times, vec![0.1, 0.2, 0.3, 0.4]);
    let median = |k: usize, part: usize| free[k].parts.iter().find(|p| p.gt_part == part).expect("part").median;
    assert!(median(0, 1) < 0.03, "door nodes {} off at t = 0.1", median(0, 1));
    assert!(median(0, 0) < 0.005, "body nodes {} off at t = 0.1", median(0, 0));
    let report = metrics.gt_report.expect("the dataset has ground truth");
    assert!(report.missing.is_empty() && report.extra.is_empty(), "one door, one part: {report:?}");
    let door = &report.matched[0];
    // The door turns 110 degrees about z through (0.3, -0.3).
    assert!(door.axis_angle_deg < 2.0, "axis {} deg off", door.axis_angle_deg);
    assert!(door.axis_position.expect("revolute") < 0.2, "pivot {:?} (0.1 m) off", door.axis_position);
    assert!(door.part_motion < 3.0, "motion {} deg off", door.part_motion);
    // What the base and the part are made of: mostly the body and the door.
    let composition = metrics.composition.expect("the dataset has ground truth");
    assert_eq!(composition.len(), 2);
    for (part, c) in composition.iter().enumerate() {
        let total: usize = c.gt_parts.iter().map(|g| g.1).sum();
        let (gt, most) = c.gt_parts[0];
        assert!(gt == part && 2 * most > total, "part {part}: {:?}", c.gt_parts);
    }
    twin_renders_the_end_state(&data, &root.join("d"), &root);
}

/// `aim render-twin` with every joint at the end of its range against the
/// dataset's end-state test views (white background), and at the start state:
/// measured 17.5-30.0 dB (mean about 22) at the end state and 2.6-6.5 dB less at the
/// start on this fridge (2026-12-02); what is missing is the inside the door
/// reveals, which the start state never saw.
fn twin_renders_the_end_state(data: &std::path::Path, run: &std::path::Path, root: &std::path::Path) {
    let twin = aim::export::Twin::open(run).expect("twin");
    let (_, tests) =
        aim::train::views::load_phase_views(data, aim_capture::Phase::After, 256, false).expect("end-state test views");
    assert!(!tests.is_empty());
    let states: Vec<String> = twin.articulation.joints.iter().map(|j| format!("{}={}", j.part, j.range[1])).collect();
    let white = glam::Vec3::ONE;
    let (mut end, mut start) = (0.0, 0.0);
    for (k, view) in tests.iter().enumerate() {
        let camera = root.join(format!("camera_{k}.json"));
        let json = serde_json::to_vec(&aim::camera::CameraFile::from_camera(&view.camera)).expect("json");
        std::fs::write(&camera, json).expect("camera written");
        let psnr = |state_args: &[String], name: &str| {
            let out = root.join(format!("{name}_{k}.png"));
            let mut cmd = aim();
            cmd.arg("render-twin").arg(run).arg("--camera").arg(&camera).arg("--out").arg(&out);
            for s in state_args {
                cmd.arg("--state").arg(s);
            }
            let o = cmd.output().expect("runs");
            assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
            let img = image::open(&out).expect("png").to_rgb32f();
            aim::train::loss::psnr(img.as_raw(), &view.target(white))
        };
        end += psnr(&states, "end") / tests.len() as f32;
        start += psnr(&[], "start") / tests.len() as f32;
    }
    assert!(end > 20.0, "end state {end} dB");
    assert!(
        end > start + 2.0,
        "end state {end} dB, start state {start} dB: the door did not move to where the views show it"
    );
}
