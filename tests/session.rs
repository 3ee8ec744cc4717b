//! Sessions (`aim::stream`, `aim run`): a dataset fed through the ingestion
//! thread and the session's router gives exactly what the stage commands give
//! on it for one seed (the same frames in the same order through the same stage
//! code); input without an interaction, and input `aim run` cannot train on,
//! get a message naming it and a non-zero exit.

mod common;

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::atomic::AtomicBool;

use aim::stream::{run_session, Reference, SessionConfig, SessionControl, SessionOutcome};
use aim::synth::recording::{write_recording, RecordingConfig, RecordingSummary};
use aim::train::dynamic_run::{run_dynamic, DynamicOutcome, RunControl, StageTwoInput};
use aim::train::static_stage::{run_static, RunOutcome, RunSetup};
use aim::train::views::load_phase_views;
use aim::viz::Viz;
use aim_capture::recording::{open_recording, RecordingOptions};
use aim_capture::Phase;

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("aim-session-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).expect("temp dir");
    d
}

/// A scratch folder `name` with the tiny fridge dataset in it (root, dataset), and
/// the cpu presets with `seed` and the stages' iterations.
fn tiny_fridge_session(name: &str, seed: u64, stage_one: u32, stage_two: u32) -> (PathBuf, PathBuf, SessionConfig) {
    let root = tmp(name);
    let data = root.join("data");
    common::tiny_dataset("fridge", &data);
    let mut cfg = SessionConfig::cpu(seed);
    cfg.stage_one.iterations = stage_one;
    cfg.stage_two.iterations = stage_two;
    (root, data, cfg)
}

fn read(path: &Path) -> Vec<u8> {
    std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

#[test]
fn a_session_on_a_dataset_gives_the_stage_commands_result() {
    let (root, data, cfg) = tiny_fridge_session("parity", 3, 40, 60);
    let never = AtomicBool::new(false);
    let viz = Viz::disabled();

    // The stage commands' path: stage I on the scan's views, stage II on the dataset.
    let (train, scan_test) = load_phase_views(&data, Phase::Scan, cfg.stage_one.resolution, false).expect("scan");
    let batch = root.join("batch");
    let setup = RunSetup {
        run_dir: &batch.join("static"),
        resume: false,
        init: None,
        arriving: None,
        backend: aim::render::Backend::Cpu,
    };
    let RunOutcome::Finished(batch_one) =
        run_static(cfg.stage_one.clone(), &train, &scan_test, &setup, &never, &viz, |_| {}).expect("stage I")
    else {
        panic!("stage I interrupted")
    };
    let control = RunControl { resume: false, interrupt: &never, viz: &viz, backend: aim::render::Backend::Cpu };
    let static_ply = batch.join("static").join("static.ply");
    let DynamicOutcome::Finished { metrics: batch_two, .. } = run_dynamic(
        StageTwoInput::load(&data, &cfg.stage_two).expect("dataset"),
        &static_ply,
        &batch.join("dynamic"),
        cfg.stage_two.clone(),
        &cfg.mesh,
        &control,
        |_| {},
    )
    .expect("stage II") else {
        panic!("stage II interrupted")
    };

    // The session: the same dataset through the ingestion thread.
    let reference = Reference {
        scan_test,
        motion_test: load_phase_views(&data, Phase::Motion, cfg.stage_two.resolution, false).expect("motion").1,
        ground_truth: vec![data.clone()],
    };
    let opened = open_recording(&data, &RecordingOptions::default()).expect("opens");
    let session = root.join("session");
    let control = SessionControl { interrupt: &never, viz: &viz, backend: aim::render::Backend::Cpu, resume: false };
    let SessionOutcome::Finished { report, .. } =
        run_session(opened, reference, &session, &cfg, &control, &|_| {}).expect("session")
    else {
        panic!("session interrupted")
    };

    assert_eq!(report.events.len(), 2, "hand-in and hand-out: {:?}", report.events);
    assert_eq!(report.ingest.dropped, 0, "replay drops nothing");
    let [interaction] = report.interactions.as_slice() else { panic!("one interaction: {:?}", report.interactions) };
    assert_eq!((interaction.dir.as_str(), interaction.object, interaction.events.len()), ("interaction_1", 0, 2));
    let frames = interaction.frames;
    assert_eq!((frames.scan, frames.motion, frames.after), (6, 10, 2));
    assert_eq!(interaction.stage_one.mean_psnr, batch_one.mean_psnr);
    assert_eq!(interaction.stage_one.gaussians, batch_one.gaussians);
    let session_dir = session.join("interaction_1");
    assert_eq!(read(&session_dir.join("static/static.ply")), read(&static_ply), "stage I differs");
    for f in ["dynamic/track.bin", "dynamic/moving.ply", "dynamic/twin/articulation.json"] {
        assert_eq!(read(&session_dir.join(f)), read(&batch.join(f)), "{f} differs");
    }
    assert_eq!(interaction.stage_two.motion_test_psnr, batch_two.motion_test_psnr);
    assert_eq!(
        serde_json::to_value(&interaction.stage_two.gt_report).expect("json"),
        serde_json::to_value(&batch_two.gt_report).expect("json")
    );
    let written: serde_json::Value = serde_json::from_slice(&read(&session.join("session.json"))).expect("json");
    assert_eq!(written["interactions"][0]["frames"]["motion"], 10);
}

fn aim() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_aim"));
    c.args(["--log", "error"]);
    c
}

#[test]
fn input_without_an_interaction_is_refused_by_name() {
    let root = tmp("refused");
    let data = root.join("data");
    common::tiny_dataset("fridge", &data);
    // Only the scan: the hand never comes, nothing moves.
    let frames = aim_capture::dataset::load_aim(&data, &aim_capture::dataset::LoadOptions { depth: false })
        .expect("loads")
        .start
        .train;
    let opened = aim_capture::recording::Opened {
        source: Box::new(aim_capture::source::DatasetSource::from_frames("scan-only", frames)),
        processor: aim_capture::pipeline::Processor::new(
            None,
            &aim_capture::undistort::UndistortConfig::aria_default(),
            None,
        ),
        tagger: aim_capture::pipeline::PhaseTagger::none(),
        camera: None,
        trajectory_path: None,
        hands_path: None,
        points_path: None,
        regions: Vec::new(),
    };
    let never = AtomicBool::new(false);
    let viz = Viz::disabled();
    let control = SessionControl { interrupt: &never, viz: &viz, backend: aim::render::Backend::Cpu, resume: false };
    let err = run_session(opened, Reference::default(), &root.join("out"), &SessionConfig::cpu(0), &control, &|_| {})
        .err()
        .expect("no interaction is an error");
    let msg = err.to_string();
    assert!(msg.contains("scan-only") && msg.contains("no interaction"), "{msg}");

    // `aim run` on a recording without what training on it needs: said with the
    // input's name and what is missing.
    let rec = root.join("recording");
    let small =
        RecordingConfig { resolution: 128, fps: 5.0, scan_s: 1.0, motion_s: 1.0, after_s: 0.6, ..Default::default() };
    write_recording(&[aim::synth::object("fridge").expect("object")], &small, &rec).expect("written");
    let stderr = |rec: &Path| {
        let out = aim().arg("run").arg(rec).arg("--out").arg(root.join("run")).output().expect("runs");
        assert!(!out.status.success());
        String::from_utf8_lossy(&out.stderr).into_owned()
    };
    for (file, needed) in [
        ("mps/slam/semidense_points.csv.gz", "semidense"),
        ("object_region.json", "region"),
        ("mps/slam/closed_loop_trajectory.csv", "camera poses"),
    ] {
        std::fs::remove_file(rec.join(file)).expect("removed");
        let e = stderr(&rec);
        assert!(e.contains(&rec.display().to_string()) && e.contains(needed), "{file}: {e}");
        if needed == "semidense" {
            // A region on the command line, negative corners included, is read as
            // given (the points are still what is missing); a malformed one is named.
            let with_region = |r: &str| {
                let out = aim().arg("run").arg(&rec).arg("--out").arg(root.join("run")).args(["--region", r]).output();
                String::from_utf8_lossy(&out.expect("runs").stderr).into_owned()
            };
            let e = with_region("-2,-2,-1,2,2,3");
            assert!(e.contains("semidense"), "{e}");
            let e = with_region("1,2");
            assert!(e.contains("--region") && e.contains("x0,y0,z0,x1,y1,z1"), "{e}");
        }
    }
    let missing = aim().arg("run").arg(root.join("nothing")).arg("--out").arg(root.join("run")).output().expect("runs");
    assert!(!missing.status.success());
    assert!(String::from_utf8_lossy(&missing.stderr).contains("no such file"));
}

#[test]
fn aim_run_logs_the_session_to_rerun() {
    let root = tmp("rerun");
    let data = root.join("data");
    common::tiny_dataset("fridge", &data);
    let rrd = root.join("session.rrd");
    let out = aim()
        .arg("run")
        .arg(&data)
        .arg("--out")
        .arg(root.join("run"))
        .args(["--static-iterations", "20", "--dynamic-iterations", "30", "--rrd"])
        .arg(&rrd)
        .output()
        .expect("runs");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(stdout.contains("moving part(s) found") && stdout.contains("session.json"), "{stdout}");
    // rerun's own CLI checks the file and lists the documented entities (docs/session.md).
    let verify = Command::new("python3").args(["-m", "rerun", "rrd", "verify"]).arg(&rrd).output().expect("rerun");
    assert!(verify.status.success(), "{}", String::from_utf8_lossy(&verify.stderr));
    let print =
        Command::new("python3").args(["-m", "rerun", "rrd", "print", "--verbose"]).arg(&rrd).output().expect("rerun");
    assert!(print.status.success(), "{}", String::from_utf8_lossy(&print.stderr));
    let listing = String::from_utf8_lossy(&print.stdout);
    for entity in [
        "/session/events",
        "/session/input/scan",
        "/session/input/motion",
        "/session/input/after",
        "/train/psnr",
        "/stage2/psnr",
        "/stage2/tracked/t1",
        "/stage2/preview/render",
        "/stage3/joints",
    ] {
        assert!(listing.contains(entity), "{entity} missing from the recording");
    }
    // The session's layout travels with it: a blueprint store with its viewport and views.
    for blueprint in ["/viewport@ViewportBlueprint:root_container", "ViewBlueprint:class_identifier"] {
        assert!(listing.contains(blueprint), "no {blueprint} in the recording's blueprint");
    }
}

/// `aim run` on a recording (the synthetic Aria-like one): the frames are cut to
/// the object region, stage I learns the object and the room around it from the
/// SLAM points, the object is what lies in the region, and stages II and III run
/// on it with the room as each view's backdrop.
/// A small synthetic fridge recording (`resolution` px, 6 fps, 1.5 s of scan,
/// 1 s of motion, 1 s after) through `aim run` with `args`: the recording's
/// folder and summary, the run's folder and its session.json.
fn run_on_small_recording(
    name: &str,
    resolution: u32,
    args: &[&str],
) -> (PathBuf, RecordingSummary, PathBuf, serde_json::Value) {
    let root = tmp(name);
    let rec = root.join("recording");
    let small =
        RecordingConfig { resolution, fps: 6.0, scan_s: 1.5, motion_s: 1.0, after_s: 1.0, ..Default::default() };
    let summary = write_recording(&[aim::synth::object("fridge").expect("object")], &small, &rec).expect("written");
    let run = root.join("run");
    let out = aim().arg("run").arg(&rec).arg("--out").arg(&run).args(args).output().expect("runs");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let report: serde_json::Value = serde_json::from_slice(&read(&run.join("session.json"))).expect("json");
    (rec, summary, run, report)
}

#[test]
fn aim_run_trains_on_a_recording_with_the_room_kept_out_of_the_object() {
    let (rec, _, run, report) =
        run_on_small_recording("recording-run", 256, &["--static-iterations", "200", "--dynamic-iterations", "60"]);
    let interaction = &report["interactions"][0];
    assert_eq!(report["interactions"].as_array().map(Vec::len), Some(1), "{report}");
    for phase in ["scan", "motion", "after"] {
        assert!(interaction["frames"][phase].as_u64().expect("count") > 0, "no {phase} frames: {report}");
    }
    assert!(interaction["stage_one"]["mean_psnr"].as_f64().expect("psnr") > 20.0, "{}", interaction["stage_one"]);
    let run = run.join("interaction_1");
    let region: aim_capture::detect::ObjectRegion =
        serde_json::from_slice(&read(&rec.join("object_region.json"))).expect("region");
    let all = aim::splat::ply::read_ply(&run.join("static/static.ply")).expect("stage I");
    let object = aim::splat::ply::read_ply(&run.join("static/object.ply")).expect("the object");
    // The object: inside the region grown by 5 % of its largest side (docs/session.md).
    let side = (0..3).map(|a| region.max[a] - region.min[a]).fold(0.0, f64::max);
    let inside = |i: usize, set: &aim::splat::GaussianSet| {
        let p = set.mean(i).as_dvec3();
        (0..3).all(|a| p[a] >= region.min[a] - 0.05 * side - 1e-6 && p[a] <= region.max[a] + 0.05 * side + 1e-6)
    };
    assert!((0..object.len()).all(|i| inside(i, &object)), "an object Gaussian outside the region");
    let room = (0..all.len()).filter(|&i| !inside(i, &all)).count();
    assert_eq!(object.len() + room, all.len());
    assert!(object.len() > 100 && room > 100, "{} object and {room} room Gaussians", object.len());
    assert!(run.join("dynamic/twin/articulation.json").is_file());
    // The door, moved as the hand tracking saw the palm move (docs/session.md).
    let gt = &interaction["stage_two"]["gt_report"];
    let matched = gt["matched"].as_array().expect("matched parts");
    assert_eq!(matched.len(), 1, "{gt}");
    assert!(gt["extra"].as_array().expect("extra").is_empty(), "{gt}");
    let door = &matched[0];
    assert_eq!(door["kind"], "revolute", "{gt}");
    assert!(door["axis_angle_deg"].as_f64().expect("axis") < 3.0, "{gt}");
    assert!(door["part_motion"].as_f64().expect("motion") < 5.0, "{gt}");
}

/// Two objects in one recording (`aim synth-recording fridge,storage`): the
/// wearer opens the fridge's door, walks over and pulls the storage unit's
/// drawer. Each window gives its own interaction, on its own object, with its
/// own twin and ground truth.
#[test]
fn aim_run_gives_a_twin_per_interaction() {
    let root = tmp("two-objects");
    let rec = root.join("recording");
    let small = RecordingConfig {
        resolution: 256,
        fps: 6.0,
        scan_s: 1.5,
        motion_s: 1.0,
        after_s: 2.0,
        walk_s: 1.0,
        ..Default::default()
    };
    let objects = ["fridge", "storage"].map(|o| aim::synth::object(o).expect("object"));
    let summary = write_recording(&objects, &small, &rec).expect("written");
    assert_eq!(summary.interactions.len(), 2);
    let run = root.join("run");
    // Stage I learns the room of two objects from the crops around one: at 200
    // iterations (the one-object test's) the fridge's start state is too sparse
    // for the palm to touch it before t = 0.86.
    let args = ["--static-iterations", "600", "--dynamic-iterations", "60"];
    let out = aim().arg("run").arg(&rec).arg("--out").arg(&run).args(args).output().expect("runs");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let report: serde_json::Value = serde_json::from_slice(&read(&run.join("session.json"))).expect("json");
    assert_eq!(report["events"].as_array().map(Vec::len), Some(4), "{}", report["events"]);
    let interactions = report["interactions"].as_array().expect("interactions");
    assert_eq!(interactions.len(), 2, "{report}");
    for (k, (interaction, kind)) in interactions.iter().zip(["revolute", "prismatic"]).enumerate() {
        assert_eq!(interaction["object"], k, "{interaction}");
        assert_eq!(interaction["dir"], format!("interaction_{}", k + 1));
        assert!(run.join(format!("interaction_{}/dynamic/twin/articulation.json", k + 1)).is_file());
        // Each against its own object's ground truth: one part, the right joint.
        let gt = &interaction["stage_two"]["gt_report"];
        let matched = gt["matched"].as_array().expect("matched parts");
        assert!(matched.len() == 1 && gt["extra"].as_array().expect("extra").is_empty(), "{gt}");
        let part = &matched[0];
        assert_eq!(part["kind"], kind, "{gt}");
        assert!(part["axis_angle_deg"].as_f64().expect("axis") < 3.0, "{gt}");
        let motion = part["part_motion"].as_f64().expect("motion");
        assert!(if kind == "revolute" { motion < 5.0 } else { motion < 0.03 }, "{gt}");
    }
}

#[test]
fn aim_run_live_paces_the_recording_and_reports_how_far_the_twin_lags() {
    let live = ["--live", "--static-iterations", "60", "--dynamic-iterations", "30"];
    let (_, summary, _, report) = run_on_small_recording("recording-live", 128, &live);
    let interaction = &report["interactions"][0];
    let wall = report["wall_s"].as_f64().expect("wall time");
    let lag = interaction["hand_out_to_twin_s"].as_f64().expect("a hand-out");
    let articulated = interaction["hand_out_to_articulation_s"].as_f64().expect("a hand-out");
    let timing = format!("wall {wall} s, lag {lag} s, articulation after {articulated} s");
    // The articulation is known before the meshes and the export that make the twin.
    assert!(articulated > 0.0 && articulated <= lag, "{timing}");
    // Paced: the frames arrive over the recording's own length, so the session
    // cannot end sooner; the twin follows the hand-out, within the session.
    let recorded = (summary.frames - 1) as f64 / summary.fps;
    assert!(wall >= recorded, "{wall} s for {recorded} s of frames: {timing}");
    assert!(lag > 0.0 && lag < wall, "{timing}");
    // Every frame the ingestion delivered and did not drop reached a phase (or was
    // cut away for want of the object in view).
    let count = |v: &serde_json::Value| v.as_u64().expect("a count");
    let ingest = &report["ingest"];
    let frames = &interaction["frames"];
    let used = count(&frames["scan"]) + count(&frames["motion"]) + count(&frames["after"]);
    let reached = used + count(&report["frames_without_object"]);
    assert_eq!(reached, count(&ingest["delivered"]) - count(&ingest["dropped"]), "{ingest} {frames}");
}

/// A recording that ends while the hand still holds the part (a capture cut
/// short): `aim run` says so and exits non-zero, and keeps what it made: stage I
/// of the interaction, and session.json naming the interaction that failed.
#[test]
fn a_recording_cut_before_the_hand_lets_go_keeps_what_was_made() {
    let root = tmp("cut-recording");
    let rec = root.join("recording");
    let small =
        RecordingConfig { resolution: 128, fps: 6.0, scan_s: 1.5, motion_s: 1.0, after_s: 1.0, ..Default::default() };
    let summary = write_recording(&[aim::synth::object("fridge").expect("object")], &small, &rec).expect("written");
    // Cut half-way through the motion: the frames after it are gone from the folder.
    let cut = (summary.interactions[0].hand_in_frame + summary.interactions[0].hand_out_frame) / 2;
    let list = rec.join("frames").join("timestamps.csv");
    let text = String::from_utf8(read(&list)).expect("utf-8");
    let mut kept = Vec::new();
    for (k, line) in text.lines().enumerate() {
        let frame = line.split(',').next().expect("a file name");
        if k == 0 || k <= cut + 1 {
            kept.push(line);
        } else {
            std::fs::remove_file(rec.join("frames").join(frame)).expect("a frame file");
        }
    }
    std::fs::write(&list, kept.join("\n") + "\n").expect("written");
    let run = root.join("run");
    let out =
        aim().arg("run").arg(&rec).arg("--out").arg(&run).args(["--static-iterations", "40"]).output().expect("runs");
    assert!(!out.status.success(), "a motion without an end is not a twin");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("never left") && stderr.contains("interaction_1"), "{stderr}");
    assert!(run.join("interaction_1/static/static.ply").is_file(), "stage I's result is kept");
    let report: serde_json::Value = serde_json::from_slice(&read(&run.join("session.json"))).expect("json");
    assert_eq!(report["failed"][0]["dir"], "interaction_1", "{report}");
    assert_eq!(report["interactions"].as_array().map(Vec::len), Some(0), "{report}");
}

/// `inner`'s frames, then records that will not read (a recording damaged from
/// some point on).
struct UnreadableTail {
    inner: Box<dyn aim_capture::source::FrameSource>,
    bad: usize,
}

impl aim_capture::source::FrameSource for UnreadableTail {
    fn describe(&self) -> String {
        self.inner.describe()
    }
    fn len_hint(&self) -> Option<usize> {
        None
    }
    fn camera(&self) -> Option<aim_capture::calib::CameraCalibration> {
        self.inner.camera()
    }
    fn next_frame(&mut self) -> Option<aim_capture::Result<aim_capture::source::RawFrame>> {
        self.inner.next_frame().or_else(|| {
            self.bad = self.bad.checked_sub(1)?;
            Some(Err(aim_capture::Error::Other("damaged record".into())))
        })
    }
}

/// A stream that fails after an interaction is whole ends there: that
/// interaction's twin is made, session.json records the error, and the session
/// returns it.
#[test]
fn a_stream_failing_after_an_interaction_keeps_its_twin() {
    let (root, data, cfg) = tiny_fridge_session("stream-error", 0, 30, 30);
    let mut opened = open_recording(&data, &RecordingOptions::default()).expect("opens");
    let tolerated = cfg.ingest.max_consecutive_errors;
    opened.source = Box::new(UnreadableTail { inner: opened.source, bad: tolerated + 4 });
    let (never, viz) = (AtomicBool::new(false), Viz::disabled());
    let control = SessionControl { interrupt: &never, viz: &viz, backend: aim::render::Backend::Cpu, resume: false };
    let out = root.join("session");
    let reference = Reference { ground_truth: vec![data.clone()], ..Reference::default() };
    let err = run_session(opened, reference, &out, &cfg, &control, &|_| {}).err().expect("the stream's error");
    let msg = err.to_string();
    assert!(msg.contains("damaged record") && msg.contains("1 interaction(s) gave their twin"), "{msg}");
    assert!(out.join("interaction_1/dynamic/twin/articulation.json").is_file());
    let written: serde_json::Value = serde_json::from_slice(&read(&out.join("session.json"))).expect("json");
    assert!(written["stream_error"].as_str().is_some_and(|e| e.contains("damaged record")), "{written}");
    assert_eq!(written["interactions"].as_array().map(Vec::len), Some(1), "{written}");
}
