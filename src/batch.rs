//! Many captures as independent jobs for the workers of a distributed engine
//! (Ray, Kubernetes indexed Jobs, Slurm job arrays, AWS Batch array jobs): aim
//! schedules nothing itself. A manifest lists the captures; a worker takes one
//! by its task index and runs it as `aim run` does, into ROOT/NAME/:
//!
//! - `status.json`: running, done, failed (input unusable or internal, with the
//!   error) or interrupted; attempts, timings, versions, the configuration, and
//!   the parts and joint errors once done;
//! - `partial/`: the session's folder while it runs, with its stages' checkpoints;
//! - `session/`: the same folder, renamed there when the session finished, so a
//!   reader sees a whole result or none;
//! - `.lock`: held by the worker running the capture (an advisory file lock,
//!   released by the kernel when the worker dies).
//!
//! Running a capture again skips it when done and otherwise resumes it from its
//! checkpoints (docs/scale.md).

use std::collections::BTreeMap;
use std::fs::File;
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::time::{Instant, SystemTime, UNIX_EPOCH};

use aim_capture::detect::ObjectRegion;
use aim_capture::recording::{DetectorKind, RecordingOptions};
use serde::{Deserialize, Serialize};

use crate::error::{write_atomic, Error, Result};
use crate::eval::ArticulationReport;
use crate::render::Backend;
use crate::stream::{open_input, run_session, SessionConfig, SessionControl, SessionEvent, SessionOutcome};
use crate::train::config::{StageConfig, StaticConfig};
use crate::train::dynamic_run::PartSummary;
use crate::train::dynamic_stage::DynamicConfig;
use crate::viz::Viz;

/// A capture's status file, in ROOT/NAME/.
pub const STATUS_FILE: &str = "status.json";
/// A finished capture's session folder (what `aim run --out` writes), in ROOT/NAME/.
pub const SESSION_DIR: &str = "session";
/// The session folder while it runs.
const PARTIAL_DIR: &str = "partial";
const LOCK_FILE: &str = ".lock";
/// The batch's summary, in ROOT.
pub const SUMMARY_FILE: &str = "summary.json";

/// The environment variables engines give an array task's index in, read in
/// this order: Slurm job arrays, Kubernetes indexed Jobs, AWS Batch array jobs.
/// Indices are 0-based (a Slurm array is then `--array=0-(N-1)`).
pub const INDEX_VARIABLES: [&str; 3] = ["SLURM_ARRAY_TASK_ID", "JOB_COMPLETION_INDEX", "AWS_BATCH_JOB_ARRAY_INDEX"];

/// One line of a manifest: the input and, in a JSON manifest, its own options
/// (those left out take the batch's). Paths are relative to the manifest's folder.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CaptureSpec {
    /// A dataset or a recording, as `aim run` takes.
    pub input: PathBuf,
    /// Its folder's name under ROOT (default: the input's file name without its extension).
    pub name: Option<String>,
    /// cpu or paper (default: the batch's preset).
    pub preset: Option<String>,
    pub seed: Option<u64>,
    pub static_iterations: Option<u32>,
    pub dynamic_iterations: Option<u32>,
    /// TOML over the preset for stage I.
    pub static_config: Option<PathBuf>,
    /// TOML over the preset for stage II.
    pub dynamic_config: Option<PathBuf>,
    /// A recording's MPS output folder and files (default: found beside it).
    pub mps: Option<PathBuf>,
    pub trajectory: Option<PathBuf>,
    pub hands: Option<PathBuf>,
    pub points: Option<PathBuf>,
    /// A recording's object region: x0, y0, z0, x1, y1, z1 (default: object_region.json beside it).
    pub region: Option<Vec<f64>>,
    /// auto, mps, skin, none or "HAND_IN_S,HAND_OUT_S".
    pub detector: Option<String>,
}

/// A capture of the manifest: its folder's name and its options, with paths resolved.
#[derive(Clone, Debug, PartialEq)]
pub struct Capture {
    pub name: String,
    pub spec: CaptureSpec,
}

/// The captures of a batch, in the manifest's order (the task index is the position).
#[derive(Clone, Debug)]
pub struct Manifest {
    pub path: PathBuf,
    pub captures: Vec<Capture>,
}

impl Manifest {
    /// Read a manifest: a JSON array of [`CaptureSpec`] objects, or text with one
    /// input per line (blank lines and lines starting with # left out).
    pub fn read(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        // Absolute, so that statuses name inputs whatever folder a worker starts in.
        let path = std::path::absolute(path).map_err(|e| Error::io(path, e))?;
        Self::parse(&path, &text)
    }

    /// [`Manifest::read`] on `text`, the contents of `path`.
    pub fn parse(path: &Path, text: &str) -> Result<Self> {
        let specs: Vec<CaptureSpec> = if text.trim_start().starts_with('[') {
            serde_json::from_str(text).map_err(|e| Error::bad_file(path, format!("not a JSON manifest: {e}")))?
        } else {
            (text.lines().map(str::trim))
                .filter(|l| !l.is_empty() && !l.starts_with('#'))
                .map(|l| CaptureSpec { input: PathBuf::from(l), ..CaptureSpec::default() })
                .collect()
        };
        if specs.is_empty() {
            return Err(Error::bad_file(path, "lists no capture"));
        }
        let base = path.parent().unwrap_or(Path::new(""));
        let mut names = BTreeMap::new();
        let captures = specs
            .into_iter()
            .enumerate()
            .map(|(k, mut spec)| {
                let name = match &spec.name {
                    Some(n) => n.clone(),
                    None => spec.input.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default(),
                };
                let safe = |c: char| c.is_ascii_alphanumeric() || "._-".contains(c);
                if name.is_empty() || name.starts_with('.') || !name.chars().all(safe) {
                    return Err(Error::bad_file(
                        path,
                        format!("capture {k}: '{name}' cannot name its folder (letters, digits, '.', '_' and '-', not first '.'); give it a \"name\""),
                    ));
                }
                if let Some(first) = names.insert(name.clone(), k) {
                    return Err(Error::bad_file(
                        path,
                        format!("captures {first} and {k} are both named '{name}': give each a \"name\" (a JSON manifest)"),
                    ));
                }
                for p in [
                    Some(&mut spec.input),
                    spec.static_config.as_mut(),
                    spec.dynamic_config.as_mut(),
                    spec.mps.as_mut(),
                    spec.trajectory.as_mut(),
                    spec.hands.as_mut(),
                    spec.points.as_mut(),
                ]
                .into_iter()
                .flatten()
                {
                    *p = base.join(&*p);
                }
                Ok(Capture { name, spec })
            })
            .collect::<Result<_>>()?;
        Ok(Manifest { path: path.to_path_buf(), captures })
    }

    /// The capture with task index `index`.
    pub fn capture(&self, index: usize) -> Result<&Capture> {
        self.captures.get(index).ok_or_else(|| {
            Error::Config(format!(
                "task index {index}, but {} lists {} capture(s) (indices 0 to {})",
                self.path.display(),
                self.captures.len(),
                self.captures.len() - 1
            ))
        })
    }
}

/// The task index an engine set in the environment (`get` reads a variable),
/// with the variable's name; None when none of [`INDEX_VARIABLES`] is set.
pub fn task_index_from_env(get: impl Fn(&str) -> Option<String>) -> Result<Option<(usize, &'static str)>> {
    for var in INDEX_VARIABLES {
        if let Some(value) = get(var) {
            let index = value
                .trim()
                .parse()
                .map_err(|_| Error::Config(format!("{var}={value} is not a task index (0, 1, 2, ...)")))?;
            return Ok(Some((index, var)));
        }
    }
    Ok(None)
}

/// Where a capture's run stands.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum State {
    Running,
    Done,
    Failed,
    /// Stopped by SIGINT / SIGTERM after its running stage checkpointed: run again to resume.
    Interrupted,
    /// Said to be running, but no worker holds its lock: the worker died (killed,
    /// out of memory, machine lost). Run again to resume. Only in summaries.
    Abandoned,
}

impl State {
    /// Its name in status.json.
    pub fn name(self) -> &'static str {
        match self {
            State::Running => "running",
            State::Done => "done",
            State::Failed => "failed",
            State::Interrupted => "interrupted",
            State::Abandoned => "abandoned",
        }
    }
}

/// Whose fault a failure is.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Failure {
    /// The input (or its options) cannot give a twin: missing or malformed
    /// files, nothing moved, a hand that never let go. Running again gives the same.
    Input,
    /// Anything else (a bug, the output disk): running again may succeed.
    Internal,
}

/// One interaction's result, in status.json.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct InteractionResult {
    /// Its folder under the session's (interaction_K).
    pub dir: String,
    pub stage_one_psnr: f32,
    pub motion_psnr: Option<f32>,
    pub parts: Vec<PartSummary>,
    /// Against ground truth, when the input carries it.
    pub ground_truth: Option<ArticulationReport>,
    pub stage_one_wall_s: f64,
    pub stage_two_wall_s: f64,
}

/// What produced a status.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Versions {
    pub aim: String,
    /// The CPU rasterizer's kernel set.
    pub kernels: String,
    pub backend: String,
}

/// ROOT/NAME/status.json.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Status {
    pub name: String,
    pub input: PathBuf,
    pub state: State,
    pub failure: Option<Failure>,
    pub error: Option<String>,
    /// Runs of this capture so far, this one included.
    pub attempts: u32,
    /// What a running attempt is doing ("interaction 1: stage I", ...); None once it ended.
    #[serde(default)]
    pub stage: Option<String>,
    /// Checkpoints this attempt resumed from (paths under the session folder).
    pub resumed_from: Vec<String>,
    /// Seconds since the Unix epoch.
    pub started_unix_s: f64,
    pub finished_unix_s: Option<f64>,
    /// This attempt's wall time, and all attempts' (a killed attempt's up to
    /// the start of its last stage).
    pub wall_s: f64,
    pub total_wall_s: f64,
    pub peak_rss_mib: Option<f64>,
    pub host: String,
    pub pid: u32,
    pub threads: usize,
    pub versions: Versions,
    /// Both stages' configurations as trained (presets resolved).
    pub config: Option<serde_json::Value>,
    /// Each interaction's parts and joint errors, once done.
    pub interactions: Vec<InteractionResult>,
}

/// How running one capture ended; [`CaptureOutcome::exit_code`] is what `aim batch` exits with.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CaptureOutcome {
    Done,
    /// Done by an earlier run: nothing was touched.
    AlreadyDone,
    Failed(Failure),
    Interrupted,
    /// Another worker holds its lock.
    Busy,
}

impl CaptureOutcome {
    /// 0 done, 3 input unusable, 4 interrupted (run again to resume), 5 internal
    /// error (run again may succeed), 6 busy (another worker runs it); clap's
    /// usage errors are 2.
    pub fn exit_code(self) -> u8 {
        match self {
            CaptureOutcome::Done | CaptureOutcome::AlreadyDone => 0,
            CaptureOutcome::Failed(Failure::Input) => 3,
            CaptureOutcome::Interrupted => 4,
            CaptureOutcome::Failed(Failure::Internal) => 5,
            CaptureOutcome::Busy => 6,
        }
    }

    /// Of several captures' outcomes, the one a batch reports: internal errors
    /// first, then unusable input, then busy captures.
    pub fn worst(self, other: CaptureOutcome) -> CaptureOutcome {
        let rank = |o: CaptureOutcome| match o {
            CaptureOutcome::Done | CaptureOutcome::AlreadyDone => 0,
            CaptureOutcome::Busy => 1,
            CaptureOutcome::Failed(Failure::Input) => 2,
            CaptureOutcome::Failed(Failure::Internal) => 3,
            CaptureOutcome::Interrupted => 4,
        };
        if rank(other) > rank(self) {
            other
        } else {
            self
        }
    }
}

/// What a worker runs its captures with (the same for every capture it runs).
pub struct Worker<'a> {
    /// The batch's folder (ROOT), created if missing.
    pub root: PathBuf,
    /// Preset of captures that name none.
    pub preset: String,
    pub backend: Backend,
    /// The session's frame stores' bound (`SessionConfig::max_frames_per_phase`),
    /// the main lever on a worker's memory; None: the session's default.
    pub max_frames_per_phase: Option<usize>,
    /// Raised by SIGINT / SIGTERM: the running stage checkpoints and the capture stops.
    pub interrupt: &'a AtomicBool,
}

impl Worker<'_> {
    /// Run `capture` into ROOT/NAME (see the module's documentation); `on_event`
    /// sees its session's progress. An error is about ROOT itself (its status
    /// cannot be written); the capture's own failures are in the outcome and its
    /// status.json.
    pub fn run(&self, capture: &Capture, on_event: &(dyn Fn(SessionEvent) + Sync)) -> Result<CaptureOutcome> {
        let dir = self.root.join(&capture.name);
        std::fs::create_dir_all(&dir).map_err(|e| Error::io(&dir, e))?;
        let lock_path = dir.join(LOCK_FILE);
        // Not truncated: a capture that is done is left untouched, its lock file included.
        let lock = File::options()
            .create(true)
            .truncate(false)
            .write(true)
            .open(&lock_path)
            .map_err(|e| Error::io(&lock_path, e))?;
        match lock.try_lock() {
            Ok(()) => {}
            Err(std::fs::TryLockError::WouldBlock) => return Ok(CaptureOutcome::Busy),
            Err(std::fs::TryLockError::Error(e)) => return Err(Error::io(&lock_path, e)),
        }
        let status_path = dir.join(STATUS_FILE);
        let previous = read_status(&status_path).ok();
        let finished = dir.join(SESSION_DIR);
        if finished.is_dir() {
            // A worker that died between the rename and its last status left it running.
            if let Some(mut status) = previous.filter(|p| p.state != State::Done) {
                status.state = State::Done;
                status.stage = None;
                write_status(&status_path, &status)?;
            }
            return Ok(CaptureOutcome::AlreadyDone);
        }
        let partial = dir.join(PARTIAL_DIR);
        let mut status = Status {
            name: capture.name.clone(),
            input: capture.spec.input.clone(),
            state: State::Running,
            failure: None,
            error: None,
            attempts: previous.as_ref().map_or(0, |p| p.attempts) + 1,
            stage: None,
            resumed_from: checkpoints_under(&partial),
            started_unix_s: unix_now(),
            finished_unix_s: None,
            wall_s: 0.0,
            total_wall_s: previous.as_ref().map_or(0.0, |p| p.total_wall_s),
            peak_rss_mib: None,
            host: host_name(),
            pid: std::process::id(),
            threads: rayon::current_num_threads(),
            versions: Versions {
                aim: env!("CARGO_PKG_VERSION").into(),
                kernels: crate::render::lanes::Kernels::active().name().into(),
                backend: self.backend.describe(),
            },
            config: None,
            interactions: Vec::new(),
        };
        let started = Instant::now();
        let earlier_wall_s = status.total_wall_s;
        let outcome = match self.session_config(capture) {
            Err(e) => Err(e),
            Ok(cfg) => {
                status.config =
                    serde_json::to_value(StagesConfig { stage_one: &cfg.stage_one, stage_two: &cfg.stage_two }).ok();
                write_status(&status_path, &status)?;
                // Each stage's start is written to the status with the time so far:
                // the summary says where a running capture is, and a killed
                // attempt's time counts up to its last stage.
                let running = std::sync::Mutex::new(&mut status);
                let heartbeat = |e: SessionEvent| {
                    let stage = match &e {
                        SessionEvent::StageOneStarted { interaction, .. } => {
                            Some(format!("interaction {}: stage I", interaction + 1))
                        }
                        SessionEvent::StageTwoStarted { interaction, .. } => {
                            Some(format!("interaction {}: stages II and III", interaction + 1))
                        }
                        SessionEvent::Articulated { interaction, .. } => {
                            Some(format!("interaction {}: meshes and export", interaction + 1))
                        }
                        _ => None,
                    };
                    if let Some(stage) = stage {
                        let mut s = running.lock().unwrap_or_else(|e| e.into_inner());
                        s.stage = Some(stage);
                        s.wall_s = started.elapsed().as_secs_f64();
                        s.total_wall_s = earlier_wall_s + s.wall_s;
                        if let Err(e) = write_status(&status_path, &s) {
                            tracing::warn!("{e}");
                        }
                    }
                    on_event(e)
                };
                // A bug in one capture must not take the batch's status with it.
                std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                    self.session(capture, cfg, &partial, &heartbeat)
                }))
                .unwrap_or_else(|panic| {
                    let message = panic
                        .downcast_ref::<String>()
                        .cloned()
                        .or_else(|| panic.downcast_ref::<&str>().map(|s| s.to_string()))
                        .unwrap_or_default();
                    Err(Error::Other(format!("internal error (panic): {message}")))
                })
            }
        };
        status.stage = None;
        status.wall_s = started.elapsed().as_secs_f64();
        status.total_wall_s = earlier_wall_s + status.wall_s;
        status.peak_rss_mib = crate::train::static_stage::peak_rss_mib();
        let result = match outcome {
            Ok(Some(interactions)) => {
                std::fs::rename(&partial, &finished).map_err(|e| Error::io(&finished, e))?;
                status.state = State::Done;
                status.interactions = interactions;
                CaptureOutcome::Done
            }
            Ok(None) => {
                status.state = State::Interrupted;
                CaptureOutcome::Interrupted
            }
            Err(e) => {
                let failure = self.failure(&e);
                status.state = State::Failed;
                status.failure = Some(failure);
                status.error = Some(e.to_string());
                CaptureOutcome::Failed(failure)
            }
        };
        if result != CaptureOutcome::Interrupted {
            status.finished_unix_s = Some(unix_now());
        }
        write_status(&status_path, &status)?;
        drop(lock);
        Ok(result)
    }

    /// Both stages' configurations for `capture`: its options over the batch's.
    fn session_config(&self, capture: &Capture) -> Result<SessionConfig> {
        let spec = &capture.spec;
        let preset = spec.preset.as_deref().unwrap_or(&self.preset);
        let mut cfg = SessionConfig::cpu(0);
        cfg.stage_one =
            StaticConfig::resolve(spec.static_config.as_deref(), preset, spec.seed, spec.static_iterations)?;
        cfg.stage_two =
            DynamicConfig::resolve(spec.dynamic_config.as_deref(), preset, spec.seed, spec.dynamic_iterations)?;
        if let Some(n) = self.max_frames_per_phase {
            cfg.max_frames_per_phase = n;
        }
        Ok(cfg)
    }

    /// The capture's session in `partial`, resuming what is there; None: interrupted.
    fn session(
        &self,
        capture: &Capture,
        mut cfg: SessionConfig,
        partial: &Path,
        on_event: &(dyn Fn(SessionEvent) + Sync),
    ) -> Result<Option<Vec<InteractionResult>>> {
        let spec = &capture.spec;
        let detector: DetectorKind = match &spec.detector {
            Some(d) => d.parse().map_err(|e: String| Error::Config(format!("capture {}: {e}", capture.name)))?,
            None => DetectorKind::Auto,
        };
        let region = (spec.region.as_deref().map(ObjectRegion::from_corners).transpose())
            .map_err(|e| Error::Config(format!("capture {}: {e}", capture.name)))?;
        let recording = RecordingOptions {
            undistort: crate::stream::TRAIN_UNDISTORT,
            trajectory: spec.trajectory.clone(),
            hands: spec.hands.clone(),
            points: spec.points.clone(),
            mps: spec.mps.clone(),
            region,
            detector,
            ..RecordingOptions::default()
        };
        let (opened, reference) = open_input(&spec.input, &recording, &mut cfg)?;
        let viz = Viz::disabled();
        let control =
            SessionControl { interrupt: self.interrupt, viz: &viz, backend: self.backend.clone(), resume: true };
        Ok(match run_session(opened, reference, partial, &cfg, &control, on_event)? {
            SessionOutcome::Interrupted => None,
            SessionOutcome::Finished { report, .. } => Some(
                report
                    .interactions
                    .into_iter()
                    .map(|i| InteractionResult {
                        dir: i.dir,
                        stage_one_psnr: i.stage_one.mean_psnr,
                        motion_psnr: i.stage_two.motion_test_psnr,
                        parts: i.stage_two.parts,
                        ground_truth: i.stage_two.gt_report,
                        stage_one_wall_s: i.stage_one.wall_time_s,
                        stage_two_wall_s: i.stage_two.wall_time_s,
                    })
                    .collect(),
            ),
        })
    }

    /// Whose fault `e` is: a file outside the batch's folder is the input's, one
    /// inside it (the output) is not.
    fn failure(&self, e: &Error) -> Failure {
        match e {
            Error::Config(_) | Error::Unusable(_) => Failure::Input,
            Error::File(f) => match f.path() {
                Some(p) if !p.starts_with(&self.root) => Failure::Input,
                _ => Failure::Internal,
            },
            Error::Other(_) => Failure::Internal,
        }
    }
}

#[derive(Serialize)]
struct StagesConfig<'a> {
    stage_one: &'a StaticConfig,
    stage_two: &'a DynamicConfig,
}

fn read_status(path: &Path) -> Result<Status> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    serde_json::from_slice(&bytes).map_err(|e| Error::bad_file(path, format!("not a capture status: {e}")))
}

fn write_status(path: &Path, status: &Status) -> Result<()> {
    let json = serde_json::to_vec_pretty(status).map_err(|e| Error::Other(e.to_string()))?;
    write_atomic(path, &json)
}

/// The stage checkpoints under `dir`, relative to it, sorted.
fn checkpoints_under(dir: &Path) -> Vec<String> {
    fn walk(dir: &Path, base: &Path, found: &mut Vec<String>) {
        let Ok(entries) = std::fs::read_dir(dir) else { return };
        for entry in entries.flatten() {
            let path = entry.path();
            if path.is_dir() {
                walk(&path, base, found);
            } else if path.file_name().is_some_and(|n| n == "checkpoint.bin") {
                found.push(path.strip_prefix(base).unwrap_or(&path).to_string_lossy().into_owned());
            }
        }
    }
    let mut found = Vec::new();
    walk(dir, dir, &mut found);
    found.sort();
    found
}

fn unix_now() -> f64 {
    SystemTime::now().duration_since(UNIX_EPOCH).map_or(0.0, |d| d.as_secs_f64())
}

fn host_name() -> String {
    std::fs::read_to_string("/proc/sys/kernel/hostname")
        .ok()
        .or_else(|| std::env::var("HOSTNAME").ok())
        .map_or_else(|| "unknown".into(), |h| h.trim().to_string())
}

/// One capture in a batch's summary.
#[derive(Clone, Debug, Default, Serialize)]
pub struct SummaryRow {
    pub name: String,
    /// None: its status.json could not be read (`error` says why).
    pub state: Option<State>,
    pub failure: Option<Failure>,
    pub error: Option<String>,
    /// Where a running (or abandoned) capture is.
    pub stage: Option<String>,
    pub attempts: u32,
    /// Moving parts found, over all its interactions.
    pub parts: Option<usize>,
    /// Against ground truth, over all its interactions: parts in the truth,
    /// matched, missing and extra, and the worst matched errors.
    pub ground_truth_parts: Option<usize>,
    pub matched: Option<usize>,
    pub missing: Option<usize>,
    pub extra: Option<usize>,
    pub worst_axis_angle_deg: Option<f64>,
    /// 0.1 m units (revolute joints).
    pub worst_axis_position: Option<f64>,
    pub worst_rotation_deg: Option<f64>,
    pub worst_translation_m: Option<f64>,
    pub total_wall_s: f64,
}

/// A batch folder's summary: one row per capture folder with a status.json.
#[derive(Clone, Debug, Serialize)]
pub struct Summary {
    pub root: PathBuf,
    pub captures: Vec<SummaryRow>,
    /// Captures per state (and "unreadable").
    pub counts: BTreeMap<String, usize>,
}

/// Summarise the batch folder `root` and write ROOT/summary.json.
pub fn summarize(root: &Path) -> Result<Summary> {
    let entries = std::fs::read_dir(root).map_err(|e| Error::io(root, e))?;
    let mut dirs: Vec<PathBuf> =
        entries.flatten().map(|e| e.path()).filter(|p| p.join(STATUS_FILE).is_file()).collect();
    dirs.sort();
    let captures: Vec<SummaryRow> = dirs.iter().map(|dir| summary_row(dir)).collect();
    let mut counts = BTreeMap::new();
    for row in &captures {
        *counts.entry(row.state.map_or("unreadable", State::name).to_string()).or_insert(0) += 1;
    }
    let summary = Summary { root: root.to_path_buf(), captures, counts };
    let json = serde_json::to_vec_pretty(&summary).map_err(|e| Error::Other(e.to_string()))?;
    write_atomic(&root.join(SUMMARY_FILE), &json)?;
    Ok(summary)
}

fn summary_row(dir: &Path) -> SummaryRow {
    let name = dir.file_name().map_or_else(String::new, |n| n.to_string_lossy().into_owned());
    let status = match read_status(&dir.join(STATUS_FILE)) {
        Ok(s) => s,
        Err(e) => return SummaryRow { name, error: Some(e.to_string()), ..SummaryRow::default() },
    };
    let mut state = status.state;
    // Running, but nobody holds its lock: its worker is gone.
    if state == State::Running {
        let lock = File::open(dir.join(LOCK_FILE));
        if lock.is_ok_and(|l| l.try_lock().is_ok()) {
            state = State::Abandoned;
        }
    }
    let done = state == State::Done;
    let reports: Vec<&ArticulationReport> =
        status.interactions.iter().filter_map(|i| i.ground_truth.as_ref()).collect();
    let with_truth = done && !reports.is_empty();
    let count = |f: &dyn Fn(&ArticulationReport) -> usize| with_truth.then(|| reports.iter().map(|r| f(r)).sum());
    let matched = || reports.iter().flat_map(|r| r.matched.iter());
    let worst = |f: &dyn Fn(&crate::eval::JointErrors) -> Option<f64>| {
        matched().filter_map(f).fold(None, |m: Option<f64>, v| Some(m.map_or(v, |m| m.max(v))))
    };
    use crate::motion::JointKind;
    SummaryRow {
        name,
        state: Some(state),
        failure: status.failure,
        error: status.error,
        stage: status.stage,
        attempts: status.attempts,
        parts: done.then(|| status.interactions.iter().map(|i| i.parts.len()).sum()),
        ground_truth_parts: count(&|r| r.matched.len() + r.missing.len()),
        matched: count(&|r| r.matched.len()),
        missing: count(&|r| r.missing.len()),
        extra: count(&|r| r.extra.len()),
        worst_axis_angle_deg: worst(&|e| Some(e.axis_angle_deg)),
        worst_axis_position: worst(&|e| e.axis_position),
        worst_rotation_deg: worst(&|e| (e.kind == JointKind::Revolute).then_some(e.part_motion)),
        worst_translation_m: worst(&|e| (e.kind == JointKind::Prismatic).then_some(e.part_motion)),
        total_wall_s: status.total_wall_s,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn manifests_name_their_captures_and_resolve_paths_against_their_folder() {
        let text = "# two captures\n\ndata/fridge\n/abs/oven.vrs\n";
        let m = Manifest::parse(Path::new("/batch/list.txt"), text).expect("parsed");
        let names: Vec<&str> = m.captures.iter().map(|c| c.name.as_str()).collect();
        assert_eq!(names, ["fridge", "oven"]);
        assert_eq!(m.captures[0].spec.input, Path::new("/batch/data/fridge"));
        assert_eq!(m.captures[1].spec.input, Path::new("/abs/oven.vrs"));

        let json = r#"[{"input": "a/recording", "name": "a", "seed": 3, "static_config": "s.toml"},
                       {"input": "b/recording", "name": "b", "region": [0, 0, 0, 1, 1, 1]}]"#;
        let m = Manifest::parse(Path::new("/batch/m.json"), json).expect("parsed");
        assert_eq!(m.captures[0].spec.seed, Some(3));
        assert_eq!(m.captures[0].spec.static_config.as_deref(), Some(Path::new("/batch/s.toml")));
        assert_eq!(m.captures[1].name, "b");
        assert!(m.capture(1).is_ok());
        let err = m.capture(2).expect_err("out of range").to_string();
        assert!(err.contains("task index 2") && err.contains("2 capture(s)"), "{err}");
    }

    #[test]
    fn bad_manifests_are_refused_naming_the_file_and_the_problem() {
        let path = Path::new("/batch/m.json");
        let cases = [
            ("a/recording\nb/recording\n", "both named 'recording'"),
            ("\n# nothing\n", "lists no capture"),
            (r#"[{"input": "x", "sed": 3}]"#, "unknown field `sed`"),
            (r#"[{"input": "x", "name": "../up"}]"#, "cannot name its folder"),
            ("[{\"input\": ", "not a JSON manifest"),
        ];
        for (text, expected) in cases {
            let err = Manifest::parse(path, text).expect_err(text).to_string();
            assert!(err.contains("/batch/m.json") && err.contains(expected), "{text}: {err}");
        }
    }

    #[test]
    fn the_task_index_comes_from_the_engines_variables() {
        let env = |pairs: &'static [(&'static str, &'static str)]| {
            move |k: &str| pairs.iter().find(|(n, _)| *n == k).map(|(_, v)| v.to_string())
        };
        assert_eq!(task_index_from_env(env(&[])).expect("ok"), None);
        assert_eq!(
            task_index_from_env(env(&[("JOB_COMPLETION_INDEX", "4")])).expect("ok"),
            Some((4, "JOB_COMPLETION_INDEX"))
        );
        // Slurm's comes first when several are set.
        let both = env(&[("AWS_BATCH_JOB_ARRAY_INDEX", "1"), ("SLURM_ARRAY_TASK_ID", "7")]);
        assert_eq!(task_index_from_env(both).expect("ok"), Some((7, "SLURM_ARRAY_TASK_ID")));
        let err = task_index_from_env(env(&[("SLURM_ARRAY_TASK_ID", "x")])).expect_err("bad").to_string();
        assert!(err.contains("SLURM_ARRAY_TASK_ID=x"), "{err}");
    }

    #[test]
    fn a_batch_reports_its_worst_outcome() {
        use CaptureOutcome::*;
        let input = Failed(Failure::Input);
        let internal = Failed(Failure::Internal);
        // In increasing severity: each beats everything before it, from either side.
        let order = [Done, Busy, input, internal, Interrupted];
        for (k, later) in order.iter().enumerate() {
            for earlier in &order[..k] {
                assert_eq!(earlier.worst(*later), *later, "{earlier:?} then {later:?}");
                assert_eq!(later.worst(*earlier), *later, "{later:?} then {earlier:?}");
            }
        }
        assert_eq!(AlreadyDone.worst(Done).exit_code(), 0);
        let codes: Vec<u8> = order.iter().map(|o| o.exit_code()).collect();
        assert_eq!(codes, [0, 6, 3, 5, 4]);
    }
}
