//! `aim batch` as a worker of a distributed engine (docs/scale.md): Ray runs two
//! captures in parallel through examples/ray_batch.py (needs `python3` with
//! `ray`, installed by tests/run); a worker killed mid-capture is finished from
//! its checkpoints by the next run, exactly as an uninterrupted run, while the
//! other capture stays untouched; bad manifests and inputs get the documented
//! exit codes and statuses.

mod common;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant, SystemTime};

use aim::synth::recording::{write_recording, RecordingConfig};
use serde_json::Value;

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("aim-batch-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).expect("temp dir");
    d
}

fn aim() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_aim"));
    c.args(["--log", "warn"]);
    // The tests choose their captures themselves, whatever engine runs them.
    for var in aim::batch::INDEX_VARIABLES {
        c.env_remove(var);
    }
    c
}

fn json(path: &Path) -> Value {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    serde_json::from_slice(&bytes).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

fn text(out: &Output) -> String {
    format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr))
}

fn write(path: &Path, contents: &str) {
    std::fs::write(path, contents).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
}

#[test]
fn ray_runs_two_captures_in_parallel_and_the_summary_reports_them() {
    let root = tmp("ray");
    // Two small synthetic Aria-like recordings, the hand in view: the hand leads
    // the moving part, so each gives its joint (docs/session.md).
    let small =
        RecordingConfig { resolution: 128, fps: 6.0, scan_s: 1.5, motion_s: 1.0, after_s: 1.0, ..Default::default() };
    for object in ["fridge", "storage"] {
        let dir = root.join("data").join(object);
        write_recording(&[aim::synth::object(object).expect("object")], &small, &dir).expect("written");
    }
    let manifest = root.join("captures.json");
    write(
        &manifest,
        r#"[{"input": "data/fridge", "static_iterations": 200, "dynamic_iterations": 60},
            {"input": "data/storage", "static_iterations": 200, "dynamic_iterations": 60}]"#,
    );
    let batch = root.join("batch");
    let out = Command::new("python3")
        .arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("examples/ray_batch.py"))
        .arg(&manifest)
        .arg("--out")
        .arg(&batch)
        .args(["--aim", env!("CARGO_BIN_EXE_aim"), "--num-cpus", "2", "--cpus-per-capture", "1"])
        .output()
        .expect("python3 is required for this test (with ray: pip install ray)");
    assert!(out.status.success(), "ray_batch.py failed:\n{}", text(&out));
    assert!(text(&out).contains("2 capture(s): 2 done"), "{}", text(&out));

    let status: BTreeMap<&str, Value> =
        ["fridge", "storage"].into_iter().map(|n| (n, json(&batch.join(n).join("status.json")))).collect();
    for (name, s) in &status {
        assert_eq!(s["state"], "done", "{name}: {s}");
        assert_eq!(s["attempts"], 1, "{name}: {s}");
        assert_eq!(s["threads"], 1, "{name}: one CPU per capture: {s}");
        assert!(batch.join(name).join("session/interaction_1/dynamic/twin/articulation.json").is_file());
        assert!(!batch.join(name).join("partial").exists(), "{name}: the session folder was renamed");
    }
    // Two workers at once: each started before the other finished, in processes of their own.
    let (f, s) = (&status["fridge"], &status["storage"]);
    let t = |v: &Value, k: &str| v[k].as_f64().unwrap_or_else(|| panic!("{k}: {v}"));
    assert!(t(f, "started_unix_s") < t(s, "finished_unix_s") && t(s, "started_unix_s") < t(f, "finished_unix_s"));
    assert_ne!(f["pid"], s["pid"]);

    // The summary (written by ray_batch.py's `aim batch --summary`) against the statuses.
    let summary = json(&batch.join("summary.json"));
    let rows = summary["captures"].as_array().expect("rows");
    assert_eq!(rows.len(), 2, "{summary}");
    assert_eq!(summary["counts"]["done"], 2, "{summary}");
    let expected_kind = [("fridge", "revolute"), ("storage", "prismatic")];
    for (row, (name, kind)) in rows.iter().zip(expected_kind) {
        assert_eq!(row["name"], name);
        assert_eq!(row["state"], "done");
        let interactions = status[name]["interactions"].as_array().expect("interactions");
        let parts: Vec<&Value> = interactions.iter().flat_map(|i| i["parts"].as_array().expect("parts")).collect();
        assert_eq!(row["parts"], parts.len(), "{row}");
        assert_eq!(parts.len(), 1, "{name}: {row}");
        assert_eq!(parts[0]["kind"], kind, "{name}");
        let truth = &interactions[0]["ground_truth"];
        assert_eq!(row["matched"], 1, "{row}");
        assert_eq!(row["ground_truth_parts"], 1, "{row}");
        assert_eq!(row["extra"], 0, "{row}");
        assert_eq!(row["worst_axis_angle_deg"], truth["matched"][0]["axis_angle_deg"], "{row}");
        assert!(row["worst_axis_angle_deg"].as_f64().expect("axis") < 2.0, "{row}");
        assert_eq!(row["total_wall_s"], status[name]["total_wall_s"]);
    }
}

/// Every file under `dir` (relative path) with its bytes and modification time.
fn snapshot(dir: &Path) -> BTreeMap<PathBuf, (Vec<u8>, SystemTime)> {
    let mut files = BTreeMap::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for entry in std::fs::read_dir(&d).expect("readable").flatten() {
            let path = entry.path();
            if path.is_dir() {
                stack.push(path);
            } else {
                let modified = entry.metadata().and_then(|m| m.modified()).expect("mtime");
                let bytes = std::fs::read(&path).expect("readable");
                files.insert(path.strip_prefix(dir).expect("under").to_path_buf(), (bytes, modified));
            }
        }
    }
    files
}

/// Wait (up to a minute) until `ready` holds, failing if `child` exits first.
fn wait_for(child: &mut Child, what: &str, ready: impl Fn() -> bool) {
    let started = Instant::now();
    while !ready() {
        if let Some(status) = child.try_wait().expect("child") {
            panic!("the worker exited ({status}) before {what}");
        }
        assert!(started.elapsed() < Duration::from_secs(60), "no {what} after a minute");
        std::thread::sleep(Duration::from_millis(5));
    }
}

#[test]
fn a_killed_worker_resumes_its_capture_from_its_checkpoints_and_leaves_the_other_untouched() {
    let root = tmp("resume");
    common::tiny_dataset("fridge", &root.join("data/fridge"));
    common::tiny_dataset("storage", &root.join("data/storage"));
    let manifest = root.join("captures.json");
    write(
        &manifest,
        r#"[{"input": "data/fridge", "static_iterations": 200, "dynamic_iterations": 100},
            {"input": "data/storage", "static_iterations": 200, "dynamic_iterations": 100}]"#,
    );
    let batch = root.join("batch");
    let worker = |index: &str| {
        let mut c = aim();
        c.arg("batch").arg(&manifest).arg("--out").arg(&batch).args(["--index", index]);
        c.stdout(Stdio::null());
        c
    };
    let status = |name: &str| json(&batch.join(name).join("status.json"));
    let fridge = batch.join("fridge");

    // The other capture, done first.
    let out = worker("1").output().expect("runs");
    assert!(out.status.success(), "{}", text(&out));
    let storage_before = snapshot(&batch.join("storage"));

    // SIGTERM (what Kubernetes and Slurm send first) while it runs: it checkpoints and stops, exit 4.
    let mut first = worker("0").spawn().expect("starts");
    wait_for(&mut first, "its status says running", || fridge.join("status.json").is_file());
    let kill = |signal: &str, child: &Child| {
        let ok = Command::new("kill").args([signal, &child.id().to_string()]).status().expect("kill");
        assert!(ok.success());
    };
    kill("-TERM", &first);
    let code = first.wait().expect("exits").code();
    assert_eq!(code, Some(4), "interrupted");
    let status_after_sigterm = status("fridge");
    assert_eq!(status_after_sigterm["state"], "interrupted");

    // Run again; while it runs, a second worker on the same capture is turned away
    // (exit 6); then it is killed outright once stage II has checkpointed.
    let mut second = worker("0").spawn().expect("starts");
    let stage_two_checkpoint = fridge.join("partial/interaction_1/dynamic/checkpoint.bin");
    wait_for(&mut second, "stage II's first checkpoint", || stage_two_checkpoint.is_file());
    let busy = worker("0").output().expect("runs");
    assert_eq!(busy.status.code(), Some(6), "{}", text(&busy));
    second.kill().expect("killed");
    second.wait().expect("reaped");
    let killed = status("fridge");
    assert_eq!(killed["state"], "running", "the kill came mid-capture: {killed}");
    assert_eq!(killed["attempts"], 2);
    assert_eq!(killed["stage"], "interaction 1: stages II and III", "where it was killed");
    let first_wall = status_after_sigterm["total_wall_s"].as_f64().expect("wall");
    assert!(killed["total_wall_s"].as_f64().expect("wall") > first_wall, "the killed attempt's time counts: {killed}");
    let summary = aim().args(["batch", "--summary"]).arg(&batch).output().expect("runs");
    assert!(summary.status.success(), "{}", text(&summary));
    let row = |name: &str| {
        let s = json(&batch.join("summary.json"));
        s["captures"].as_array().expect("rows").iter().find(|r| r["name"] == name).cloned().expect("row")
    };
    assert_eq!(row("fridge")["state"], "abandoned", "nobody holds its lock");
    assert_eq!(row("fridge")["stage"], "interaction 1: stages II and III");
    assert_eq!(row("storage")["state"], "done");

    // The whole batch again: the killed capture is finished from its checkpoints,
    // the other skipped.
    let all = aim().arg("batch").arg(&manifest).arg("--out").arg(&batch).arg("--all").output().expect("runs");
    assert!(all.status.success(), "{}", text(&all));
    assert!(text(&all).contains("capture 1 (storage): already done"), "{}", text(&all));
    let done = status("fridge");
    assert_eq!(done["state"], "done", "{done}");
    assert_eq!(done["attempts"], 3);
    assert!(done["stage"].is_null(), "{done}");
    let resumed: Vec<&str> = done["resumed_from"].as_array().expect("list").iter().filter_map(Value::as_str).collect();
    assert_eq!(resumed, ["interaction_1/dynamic/checkpoint.bin", "interaction_1/static/checkpoint.bin"]);
    assert!(snapshot(&batch.join("storage")) == storage_before, "the other capture was touched");

    // What the interrupted, killed and resumed capture made is what one
    // uninterrupted run makes.
    let reference = root.join("reference");
    let out = aim()
        .arg("run")
        .arg(root.join("data/fridge"))
        .arg("--out")
        .arg(&reference)
        .args(["--static-iterations", "200", "--dynamic-iterations", "100"])
        .output()
        .expect("runs");
    assert!(out.status.success(), "{}", text(&out));
    for file in ["static/static.ply", "dynamic/track.bin", "dynamic/twin/articulation.json"] {
        let a = std::fs::read(fridge.join("session/interaction_1").join(file)).expect("resumed");
        let b = std::fs::read(reference.join("interaction_1").join(file)).expect("reference");
        assert!(a == b, "{file} differs from the uninterrupted run's");
    }
}

#[test]
fn bad_manifests_and_inputs_get_their_exit_codes_and_statuses() {
    let root = tmp("bad");
    let batch = root.join("batch");
    let run = |manifest: &Path, args: &[&str]| {
        aim().arg("batch").arg(manifest).arg("--out").arg(&batch).args(args).output().expect("runs")
    };

    // A manifest with an unknown option: input unusable (3), naming the file and the key.
    let typo = root.join("typo.json");
    write(&typo, r#"[{"input": "data/x", "iteratoins": 5}]"#);
    let out = run(&typo, &["--index", "0"]);
    assert_eq!(out.status.code(), Some(3), "{}", text(&out));
    assert!(text(&out).contains("typo.json") && text(&out).contains("iteratoins"), "{}", text(&out));

    // An input that does not exist: the capture fails as unusable input, and says why.
    let manifest = root.join("captures.txt");
    write(&manifest, "# one capture\nmissing/fridge\n");
    let out = run(&manifest, &["--index", "0"]);
    assert_eq!(out.status.code(), Some(3), "{}", text(&out));
    let s = json(&batch.join("fridge/status.json"));
    assert_eq!((s["state"].as_str(), s["failure"].as_str()), (Some("failed"), Some("input")), "{s}");
    let error = s["error"].as_str().expect("error");
    assert!(error.contains("missing/fridge") && error.contains("no such file"), "{error}");

    // An index past the manifest's end, or none at all: usage errors (2).
    let out = run(&manifest, &["--index", "1"]);
    assert_eq!(out.status.code(), Some(2), "{}", text(&out));
    assert!(text(&out).contains("task index 1") && text(&out).contains("1 capture(s)"), "{}", text(&out));
    let out = run(&manifest, &[]);
    assert_eq!(out.status.code(), Some(2), "{}", text(&out));
    assert!(text(&out).contains("SLURM_ARRAY_TASK_ID"), "{}", text(&out));
    // The index from an engine's variable.
    let out = aim()
        .arg("batch")
        .arg(&manifest)
        .arg("--out")
        .arg(&batch)
        .env("JOB_COMPLETION_INDEX", "0")
        .output()
        .expect("runs");
    assert_eq!(out.status.code(), Some(3), "{}", text(&out));
    assert_eq!(json(&batch.join("fridge/status.json"))["attempts"], 2);

    // The summary shows it as failed on its input.
    let out = aim().args(["batch", "--summary"]).arg(&batch).output().expect("runs");
    assert!(out.status.success(), "{}", text(&out));
    let line = String::from_utf8_lossy(&out.stdout).lines().find(|l| l.starts_with("fridge")).map(String::from);
    assert!(line.as_deref().is_some_and(|l| l.contains("failed/input") && l.contains("no such file")), "{line:?}");
}
