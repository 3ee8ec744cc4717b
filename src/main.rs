//! The `aim` command line. Each subcommand lives in `commands/` and calls the
//! same library functions that batch use and tests call.

use std::process::ExitCode;

use clap::{Parser, Subcommand};

mod commands;

#[derive(Parser)]
#[command(name = "aim", version, about = "Articulated digital twins from AR captures (Articulation in Motion)")]
struct Cli {
    /// Log filter (tracing env-filter syntax), e.g. "info" or "aim=debug".
    #[arg(long, global = true, default_value = "info")]
    log: String,
    /// The CPU rasterizer's kernel set: avx512, avx2 or portable (default: the
    /// fastest this CPU runs, detected at start).
    #[arg(long, global = true)]
    kernels: Option<String>,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// The built-in end-to-end job on a synthetic object with ground truth.
    Demo(commands::demo::Args),
    /// One session from a dataset's frames to the twin (stage I while the motion arrives, then stages II and III).
    Run(commands::run::Args),
    /// Many captures, one per worker of a distributed engine (Ray, Kubernetes, Slurm, AWS Batch), or all in turn; --summary.
    Batch(commands::batch::Args),
    /// Render a 3DGS PLY from a camera to a PNG.
    Render(commands::render::Args),
    /// Benchmarks that print JSON.
    #[command(subcommand)]
    Bench(commands::bench::Bench),
    /// Synthetic articulated-object benchmark datasets (AiM layout, exact ground truth).
    Synth(commands::synth::Args),
    /// Look into recordings: inspect, undistort a frame.
    #[command(subcommand)]
    Capture(commands::capture::Capture),
    /// Write a synthetic Aria-like recording (fisheye frames, MPS trajectory and hand tracking, GT).
    SynthRecording(commands::synth_recording::Args),
    /// Stage I: train the start-state 3DGS from a dataset's scan views.
    TrainStatic(commands::train_static::Args),
    /// Stages II and III: dual Gaussians on the motion video, then parts and joints.
    TrainDynamic(commands::train_dynamic::Args),
    /// The paper's metrics (joints, Chamfer distance, 3D IoU) of a twin against ground truth.
    Eval(commands::eval::Args),
    /// A Gaussian set's surface mesh by TSDF fusion (OBJ + PLY), optionally compared with a reference.
    Mesh(commands::mesh::Args),
    /// Render a twin with its parts at given joint states, or a turntable of its joints sweeping.
    RenderTwin(commands::render_twin::Args),
    /// Write a run's twin again as URDF, MJCF and/or splat PLYs.
    Export(commands::export::Args),
}

/// Keep freed buffers in the process instead of handing them back to the OS.
/// Every render and backward pass allocates a few MB per buffer; glibc's
/// defaults return such blocks with munmap/trim on free, so each training
/// iteration page-faults its buffers anew. Measured at 256 px / 50k Gaussians:
/// forward+backward 29 ms with this, 32-38 ms without (docs/benchmark.md).
#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn keep_freed_memory() {
    // 32 MiB is glibc's largest allowed mmap threshold; trimming only past 4 GiB free.
    // SAFETY: mallopt only changes allocator parameters; called before any threads exist.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, 32 << 20);
        libc::mallopt(libc::M_TRIM_THRESHOLD, i32::MAX);
    }
}

#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
fn keep_freed_memory() {}

fn main() -> ExitCode {
    keep_freed_memory();
    let cli = Cli::parse();
    let filter =
        tracing_subscriber::EnvFilter::try_new(&cli.log).unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    // Colour only for a person at a terminal: logs in files and pipes stay plain text.
    let colour = std::io::IsTerminal::is_terminal(&std::io::stderr()) && std::env::var_os("NO_COLOR").is_none();
    tracing_subscriber::fmt().with_env_filter(filter).with_writer(std::io::stderr).with_ansi(colour).init();
    if let Some(name) = &cli.kernels {
        let chosen = aim::render::lanes::Kernels::named(name)
            .and_then(|k| k.make_active().map_err(|used| format!("kernel set already chosen: {}", used.name())));
        if let Err(e) = chosen {
            eprintln!("error: --kernels: {e}");
            return ExitCode::from(2);
        }
    }
    let result = match cli.command {
        // Its exit code says what happened to the capture (docs/scale.md).
        Command::Batch(args) => return ExitCode::from(commands::batch::run(args)),
        Command::Render(args) => commands::render::run(args),
        Command::Bench(b) => commands::bench::run(b),
        Command::Synth(args) => commands::synth::run(args),
        Command::Capture(c) => commands::capture::run(c),
        Command::SynthRecording(a) => commands::synth_recording::run(a),
        Command::TrainStatic(args) => commands::train_static::run(args),
        Command::TrainDynamic(args) => commands::train_dynamic::run(args),
        Command::Demo(args) => commands::demo::run(args),
        Command::Run(args) => commands::run::run(args),
        Command::Eval(args) => commands::eval::run(args),
        Command::Mesh(args) => commands::mesh::run(args),
        Command::RenderTwin(args) => commands::render_twin::run(args),
        Command::Export(args) => commands::export::run(args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}
