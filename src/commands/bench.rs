//! `aim bench ...`: benchmarks that print JSON so numbers compare across commits.

#[derive(clap::Subcommand)]
pub enum Bench {
    /// Rasterizer forward and forward+backward timings.
    Render {
        /// Print JSON only.
        #[arg(long)]
        json: bool,
        /// Timed repetitions per case (the median is reported).
        #[arg(long, default_value_t = 7)]
        repeats: usize,
        /// Image sizes (square), comma-separated.
        #[arg(long, value_delimiter = ',', default_values_t = [256u32, 512])]
        sizes: Vec<u32>,
        /// Gaussian counts, comma-separated.
        #[arg(long, value_delimiter = ',', default_values_t = [10_000usize, 50_000, 200_000])]
        counts: Vec<usize>,
        /// Time this 3DGS PLY instead of the random scenes (with --camera).
        #[arg(long, requires = "camera")]
        ply: Option<std::path::PathBuf>,
        /// Camera JSON for --ply (the `aim render` format).
        #[arg(long, requires = "ply")]
        camera: Option<std::path::PathBuf>,
        /// Rasterizer: cpu, gpu or auto (see `aim render --help`).
        #[arg(long, default_value = "cpu")]
        backend: aim::render::BackendChoice,
    },
    /// Deformation network forward and forward+backward timings.
    Deform {
        /// Print JSON only.
        #[arg(long)]
        json: bool,
        #[arg(long, default_value_t = 5)]
        repeats: usize,
        /// Moving Gaussians per evaluation, comma-separated.
        #[arg(long, value_delimiter = ',', default_values_t = [5_000usize, 20_000])]
        counts: Vec<usize>,
    },
    /// The accuracy suite: every object x trials, stages I-III, the paper's metrics and
    /// tables (OUT/tables.md); each result is saved, so a rerun resumes.
    Suite {
        /// Objects (default: all of `aim synth --list`), comma-separated.
        #[arg(long, value_delimiter = ',')]
        objects: Vec<String>,
        /// Trials per object; trial k uses seed k for the data and the training.
        #[arg(long, default_value_t = 3)]
        trials: u32,
        #[arg(long, default_value = "cpu")]
        preset: String,
        /// Also run the paper's Table 4 ablations on the complex objects.
        #[arg(long)]
        ablations: bool,
        /// Suite folder: data/, runs/, results/*.json, tables.md.
        #[arg(long, default_value = "out/suite")]
        out: std::path::PathBuf,
        /// Print every record as JSON at the end instead of the tables.
        #[arg(long)]
        json: bool,
    },
    /// Ingestion throughput: 1408 x 1408 Aria JPEG decode + undistortion to 704 x 704 + detection.
    Ingest {
        /// Print JSON only.
        #[arg(long)]
        json: bool,
        /// Aria VRS recording (default: the sample in ../shared/reference).
        #[arg(long)]
        recording: Option<std::path::PathBuf>,
        /// Frames to push through (the recording's frames are repeated).
        #[arg(long, default_value_t = 240)]
        frames: usize,
        /// Ingestion threads (default: all cores).
        #[arg(long)]
        threads: Option<usize>,
    },
}

/// Print a report as one JSON line (`--json`) or indented JSON.
fn print_report(report: &serde_json::Value, one_line: bool) -> anyhow::Result<()> {
    let text = if one_line { serde_json::to_string(report)? } else { serde_json::to_string_pretty(report)? };
    println!("{text}");
    Ok(())
}

fn suite(opts: aim::suite::SuiteOptions, json: bool) -> anyhow::Result<()> {
    let total = opts.plan()?.len();
    println!(
        "benchmark suite: {total} run(s) ({} object(s) x {} trial(s), preset {}) -> {}",
        opts.objects.len(),
        opts.trials,
        opts.preset,
        opts.out.display()
    );
    let interrupt = super::progress::interrupt_on_ctrl_c();
    let bar = indicatif::ProgressBar::new(total as u64);
    bar.set_style(
        indicatif::ProgressStyle::with_template("{bar:30} {pos}/{len} runs [{elapsed_precise}<{eta_precise}] {msg}")
            .expect("valid template"),
    );
    let terminal = std::io::IsTerminal::is_terminal(&std::io::stderr());
    let started = std::time::Instant::now();
    let records = aim::suite::run_suite(&opts, &interrupt, |done, total, r| {
        bar.set_position(done as u64);
        let status = match (&r.error, &r.report) {
            (Some(e), _) => format!("error: {e}"),
            (None, Some(rep)) => format!(
                "{} of {} moving parts, {} failure(s)",
                rep.predicted_moving_parts, rep.gt_moving_parts, rep.failures
            ),
            (None, None) => "no report".into(),
        };
        let line = format!("{} trial {} {}: {status}, {:.0} s", r.object, r.trial, r.variant.name(), r.wall_s);
        if terminal {
            bar.println(line);
        } else {
            let elapsed = started.elapsed().as_secs_f64();
            let eta = elapsed / done as f64 * (total - done) as f64;
            tracing::info!(
                "suite {done}/{total} ({:.0} %, ETA {:.0} s): {line}",
                100.0 * done as f64 / total as f64,
                eta
            );
        }
    })?;
    bar.finish_and_clear();
    let Some(records) = records else {
        println!(
            "interrupted; finished runs are saved in {} (run the same command to resume)",
            opts.out.join("results").display()
        );
        return Ok(());
    };
    if json {
        println!("{}", serde_json::to_string_pretty(&records)?);
    } else {
        println!("{}", aim::suite::tables_markdown(&records, &opts));
        println!("tables written to {}", opts.out.join("tables.md").display());
    }
    Ok(())
}

pub fn run(b: Bench) -> anyhow::Result<()> {
    match b {
        Bench::Suite { objects, trials, preset, ablations, out, json } => {
            let objects = if objects.is_empty() {
                aim::synth::OBJECT_NAMES.iter().map(|s| s.to_string()).collect()
            } else {
                objects
            };
            let opts = aim::suite::SuiteOptions {
                objects,
                trials,
                preset,
                ablations,
                out,
                synth: aim::synth::SynthConfig::default(),
            };
            suite(opts, json)?;
        }
        Bench::Deform { json, repeats, counts } => {
            let rows = aim::bench::deform_bench(&[(8, 256), (4, 128)], &counts, repeats.max(1));
            let report = serde_json::json!({
                "bench": "deform",
                "threads": rayon::current_num_threads(),
                "machine": aim::bench::MachineInfo::detect(),
                "rows": rows,
            });
            print_report(&report, json)?;
        }
        Bench::Ingest { json, recording, frames, threads } => {
            let recording = recording.unwrap_or_else(|| {
                std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR"))
                    .join("../shared/reference/aria/gen1/aria_everyday_activities_test_data/recording.vrs")
            });
            let threads = threads.unwrap_or_else(|| std::thread::available_parallelism().map(|n| n.get()).unwrap_or(2));
            let r = aim_capture::bench::bench_ingest(&recording, frames, threads)?;
            let report = serde_json::json!({ "bench": "ingest", "result": r });
            print_report(&report, json)?;
        }
        Bench::Render { json, repeats, sizes, counts, ply, camera, backend } => {
            let backend = aim::render::Backend::open(backend)?;
            let rows = match (ply, camera) {
                (Some(ply), Some(camera)) => {
                    let gs = aim::splat::ply::read_ply(&ply)?;
                    let cam = aim::camera::Camera::load_json(&camera)?;
                    vec![aim::bench::time_render(&backend, &gs, &cam, repeats.max(1))]
                }
                _ => aim::bench::render_bench(&backend, &sizes, &counts, repeats.max(1)),
            };
            let report = serde_json::json!({
                "bench": "render",
                "threads": rayon::current_num_threads(),
                "machine": aim::bench::MachineInfo::detect(),
                "rows": rows,
            });
            print_report(&report, json)?;
        }
    }
    Ok(())
}
