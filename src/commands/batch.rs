//! `aim batch MANIFEST --out ROOT [--index I | --all]`: one capture of a
//! manifest per worker of a distributed engine, or every capture in turn;
//! `aim batch --summary ROOT`: the table over a batch's captures (`aim::batch`,
//! docs/scale.md).

use std::path::PathBuf;
use std::sync::atomic::Ordering;

use aim::batch::{summarize, task_index_from_env, CaptureOutcome, Failure, Manifest, State, Summary, Worker};
use aim::render::BackendChoice;
use serde::Serialize;

#[derive(clap::Args)]
pub struct Args {
    /// One input per line (a dataset or a recording, as `aim run` takes), or a
    /// JSON array of {"input", "name", "preset", "seed", "static_iterations", ...}
    /// objects (docs/scale.md); paths relative to the manifest's folder.
    #[arg(required_unless_present = "summary")]
    pub manifest: Option<PathBuf>,
    /// The batch's folder: ROOT/NAME/ per capture (status.json, session/).
    #[arg(long, required_unless_present_any = ["summary", "list"])]
    pub out: Option<PathBuf>,
    /// The capture to run (0-based). Default: SLURM_ARRAY_TASK_ID,
    /// JOB_COMPLETION_INDEX or AWS_BATCH_JOB_ARRAY_INDEX, whichever is set.
    #[arg(long, conflicts_with = "all")]
    pub index: Option<usize>,
    /// Run every capture in turn (those done are skipped, the others resumed).
    #[arg(long)]
    pub all: bool,
    /// Print the manifest's captures (index, name, input) as JSON and stop.
    #[arg(long, conflicts_with_all = ["index", "all"])]
    pub list: bool,
    /// Print a table of the captures in ROOT and write ROOT/summary.json.
    #[arg(long, value_name = "ROOT", conflicts_with_all = ["out", "index", "all", "list"])]
    pub summary: Option<PathBuf>,
    /// With --summary: print the summary's JSON instead of the table.
    #[arg(long, requires = "summary")]
    pub json: bool,
    /// Preset of the captures that name none: cpu or paper.
    #[arg(long, default_value = "cpu")]
    pub preset: String,
    /// This worker's threads (default: one per core), so that several workers
    /// share a machine. RAYON_NUM_THREADS does the same.
    #[arg(long)]
    pub threads: Option<usize>,
    /// Frames kept per phase of an interaction (default 512): past it every
    /// other frame is dropped. The main lever on a worker's memory.
    #[arg(long)]
    pub max_frames_per_phase: Option<usize>,
    /// Where the stages render: cpu, gpu or auto (see `aim render --help`).
    #[arg(long, default_value = "cpu")]
    pub backend: BackendChoice,
}

/// `aim batch`'s exit code (`CaptureOutcome::exit_code`; 3 also for a manifest
/// that cannot be read, 5 for a batch folder that cannot be written).
pub fn run(args: Args) -> u8 {
    match batch(args) {
        Ok(code) => code,
        Err((code, e)) => {
            eprintln!("error: {e:#}");
            code
        }
    }
}

const INPUT_UNUSABLE: u8 = 3;
const INTERNAL: u8 = 5;

fn batch(args: Args) -> Result<u8, (u8, anyhow::Error)> {
    let internal = |e: anyhow::Error| (INTERNAL, e);
    if let Some(root) = &args.summary {
        let summary = summarize(root).map_err(|e| internal(e.into()))?;
        if args.json {
            println!("{}", serde_json::to_string_pretty(&summary).map_err(|e| internal(e.into()))?);
        } else {
            print_summary(&summary);
        }
        return Ok(0);
    }
    let manifest_path = args.manifest.as_deref().expect("clap requires a manifest without --summary");
    let manifest = Manifest::read(manifest_path).map_err(|e| (INPUT_UNUSABLE, e.into()))?;
    if args.list {
        #[derive(Serialize)]
        struct Listed<'a> {
            index: usize,
            name: &'a str,
            input: &'a std::path::Path,
        }
        let listed: Vec<Listed> = (manifest.captures.iter().enumerate())
            .map(|(index, c)| Listed { index, name: &c.name, input: &c.spec.input })
            .collect();
        println!("{}", serde_json::to_string_pretty(&listed).map_err(|e| internal(e.into()))?);
        return Ok(0);
    }
    let usage = |e: anyhow::Error| (2, e);
    let indices: Vec<usize> = if args.all {
        (0..manifest.captures.len()).collect()
    } else {
        let index = match args.index {
            Some(i) => i,
            None => match task_index_from_env(|k| std::env::var(k).ok()).map_err(|e| usage(e.into()))? {
                Some((i, var)) => {
                    tracing::info!("task index {i} from {var}");
                    i
                }
                None => {
                    return Err(usage(anyhow::anyhow!(
                        "no capture chosen: give --index I or --all, or run as an array task ({})",
                        aim::batch::INDEX_VARIABLES.join(", ")
                    )))
                }
            },
        };
        manifest.capture(index).map_err(|e| usage(e.into()))?;
        vec![index]
    };
    if let Some(n) = args.threads {
        rayon::ThreadPoolBuilder::new()
            .num_threads(n)
            .build_global()
            .map_err(|e| usage(anyhow::anyhow!("--threads {n}: {e}")))?;
    }
    let root = args.out.expect("clap requires --out");
    std::fs::create_dir_all(&root).map_err(|e| internal(anyhow::anyhow!("{}: {e}", root.display())))?;
    // Absolute, so that a failure is told apart as the input's or the output's by its path.
    let root = std::fs::canonicalize(&root).map_err(|e| internal(anyhow::anyhow!("{}: {e}", root.display())))?;
    let interrupt = super::progress::interrupt_on_ctrl_c();
    let worker = Worker {
        root,
        preset: args.preset,
        backend: aim::render::Backend::open(args.backend).map_err(|e| usage(e.into()))?,
        max_frames_per_phase: args.max_frames_per_phase,
        interrupt: &interrupt,
    };
    let mut worst = CaptureOutcome::Done;
    for index in indices {
        let capture = &manifest.captures[index];
        println!("capture {index} ({}): {}", capture.name, capture.spec.input.display());
        let progress = super::progress::SessionProgress::new();
        let outcome = worker.run(capture, &|e| progress.on_event(e)).map_err(|e| internal(e.into()))?;
        progress.finish();
        let dir = worker.root.join(&capture.name);
        match outcome {
            CaptureOutcome::Done => println!("capture {index} ({}): done, in {}", capture.name, dir.display()),
            CaptureOutcome::AlreadyDone => println!("capture {index} ({}): already done", capture.name),
            CaptureOutcome::Busy => println!("capture {index} ({}): another worker is running it", capture.name),
            CaptureOutcome::Interrupted => {
                println!("capture {index} ({}): interrupted; run again to resume it", capture.name)
            }
            CaptureOutcome::Failed(kind) => println!(
                "capture {index} ({}): failed ({}), see {}",
                capture.name,
                match kind {
                    Failure::Input => "input unusable",
                    Failure::Internal => "internal error",
                },
                dir.join(aim::batch::STATUS_FILE).display()
            ),
        }
        worst = worst.worst(outcome);
        if interrupt.load(Ordering::SeqCst) {
            break;
        }
    }
    Ok(worst.exit_code())
}

fn print_summary(summary: &Summary) {
    let opt = |v: Option<f64>, digits: usize| v.map_or("-".to_string(), |v| format!("{v:.digits$}"));
    println!(
        "{:<24} {:<12} {:>5} {:>9} {:>5} {:>8} {:>6} {:>8} {:>8} {:>8} {:>3}  error",
        "capture", "state", "parts", "gt found", "extra", "axis deg", "pos", "rot deg", "trans m", "wall s", "try"
    );
    for row in &summary.captures {
        let state = match (row.state, row.failure) {
            (None, _) => "unreadable".to_string(),
            (Some(State::Failed), Some(Failure::Input)) => "failed/input".into(),
            (Some(State::Failed), _) => "failed".into(),
            (Some(s), _) => s.name().into(),
        };
        let found = match (row.matched, row.ground_truth_parts) {
            (Some(m), Some(n)) => format!("{m}/{n}"),
            _ => "-".into(),
        };
        // The error, or where a running capture is.
        let error = row.error.as_deref().or(row.stage.as_deref()).unwrap_or("").replace('\n', " ");
        println!(
            "{:<24} {:<12} {:>5} {:>9} {:>5} {:>8} {:>6} {:>8} {:>8} {:>8.1} {:>3}  {error}",
            row.name,
            state,
            row.parts.map_or("-".into(), |p| p.to_string()),
            found,
            row.extra.map_or("-".into(), |p| p.to_string()),
            opt(row.worst_axis_angle_deg, 2),
            opt(row.worst_axis_position, 3),
            opt(row.worst_rotation_deg, 2),
            opt(row.worst_translation_m, 4),
            row.total_wall_s,
            row.attempts
        );
    }
    let counts: Vec<String> = summary.counts.iter().map(|(k, n)| format!("{n} {k}")).collect();
    println!("{} capture(s): {}", summary.captures.len(), counts.join(", "));
}
