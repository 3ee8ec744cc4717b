//! `aim run INPUT --out RUN`: one session from a dataset's or a recording's
//! frames to a twin per interaction (`aim::stream`): the ingestion thread reads
//! and tags the frames, each interaction's stage I trains on its object's scan
//! while the motion frames arrive, its stages II and III run when its
//! after-phase is over.

use std::path::PathBuf;

use aim::stream::{open_input, run_session, SessionConfig, SessionControl, SessionEvent, SessionOutcome};
use aim::train::config::{StageConfig, StaticConfig};
use aim::train::dynamic_stage::DynamicConfig;

#[derive(clap::Args)]
pub struct Args {
    /// An AiM-layout dataset (start/, motion/, end/), a nerfstudio folder
    /// (transforms.json) or a COLMAP folder (sparse/ + images/).
    pub input: PathBuf,
    /// Output folder: interaction_K/static/ (stage I), interaction_K/dynamic/
    /// (stages II and III, the twin) for each interaction K = 1, 2, ...; session.json.
    #[arg(long)]
    pub out: PathBuf,
    /// Preset of both stages: cpu or paper.
    #[arg(long, default_value = "cpu")]
    pub preset: String,
    /// TOML over the preset for stage I (keys of docs/training.md's stage I table).
    #[arg(long)]
    pub static_config: Option<PathBuf>,
    /// TOML over the preset for stage II.
    #[arg(long)]
    pub dynamic_config: Option<PathBuf>,
    #[arg(long)]
    pub seed: Option<u64>,
    /// Stage I iterations (default: the preset's).
    #[arg(long)]
    pub static_iterations: Option<u32>,
    /// Stage II iterations (default: the preset's).
    #[arg(long)]
    pub dynamic_iterations: Option<u32>,
    /// Emulate a live capture: frames are handed over at their recorded rate,
    /// the oldest buffered frame is dropped when training falls behind (counted
    /// in session.json), stage I runs 80 % of the preset's schedule (for a
    /// sooner articulation; --static-iterations or --static-config are kept as
    /// given), and the time from hand-out to the articulation and to the twin is
    /// reported. Without it, a replay never drops a frame.
    #[arg(long)]
    pub live: bool,
    /// Continue an interrupted or killed session in --out: each stage from its
    /// checkpoint (same input and configuration; another configuration is refused).
    #[arg(long)]
    pub resume: bool,
    /// Where stages I and II render (and the paper preset's deformation network
    /// runs): cpu, gpu or auto (see `aim render --help`).
    #[arg(long, default_value = "cpu")]
    pub backend: aim::render::BackendChoice,
    #[command(flatten)]
    pub rerun: super::train_static::RerunArgs,
    /// A recording's files and detector (ignored for datasets).
    #[command(flatten)]
    pub recording: super::capture::Common,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let mut cfg = SessionConfig::cpu(0);
    cfg.stage_one =
        StaticConfig::resolve(args.static_config.as_deref(), &args.preset, args.seed, args.static_iterations)?;
    cfg.stage_two =
        DynamicConfig::resolve(args.dynamic_config.as_deref(), &args.preset, args.seed, args.dynamic_iterations)?;
    if args.live {
        let asked = cfg.stage_one.clone();
        cfg.go_live();
        // A schedule asked for on the command line is trained as asked.
        if args.static_iterations.is_some() || args.static_config.is_some() {
            cfg.stage_one = asked;
        }
    }
    let (opened, reference) =
        open_input(&args.input, &args.recording.options(aim::stream::TRAIN_UNDISTORT)?, &mut cfg)?;
    let interrupt = super::progress::interrupt_on_ctrl_c();
    let viz = args.rerun.open()?;
    let control = SessionControl {
        interrupt: &interrupt,
        viz: &viz,
        backend: aim::render::Backend::open(args.backend)?,
        resume: args.resume,
    };
    let progress = super::progress::SessionProgress::new();
    let on_event = |e: SessionEvent| progress.on_event(e);
    match run_session(opened, reference, &args.out, &cfg, &control, &on_event)? {
        SessionOutcome::Finished { parts, report } => {
            progress.finish();
            for (interaction, parts) in report.interactions.iter().zip(&parts) {
                println!(
                    "{} (object {}): stage I {} Gaussians, PSNR {:.2} dB; frames: {} scan, {} motion, {} after",
                    interaction.dir,
                    interaction.object,
                    interaction.stage_one.gaussians,
                    interaction.stage_one.mean_psnr,
                    interaction.frames.scan,
                    interaction.frames.motion,
                    interaction.frames.after
                );
                super::train_dynamic::print_joints(parts, interaction.stage_two.gt_report.as_ref());
                let after = |s: Option<f64>| s.map_or("(no hand-out)".into(), |s| format!("{s:.1} s"));
                println!(
                    "  the articulation {} and the twin {} after hand-out, in {}",
                    after(interaction.hand_out_to_articulation_s),
                    after(interaction.hand_out_to_twin_s),
                    args.out.join(&interaction.dir).join("dynamic/twin").display()
                );
            }
            if report.log_items_dropped > 0 {
                println!("{} rerun log item(s) dropped (the logging thread fell behind)", report.log_items_dropped);
            }
            let i = &report.ingest;
            let skipped =
                [(i.corrupt, "unreadable"), (i.unposed, "without a pose"), (i.out_of_order, "out of time order")]
                    .iter()
                    .filter(|(n, _)| *n > 0)
                    .map(|(n, why)| format!("; {n} skipped {why}"))
                    .collect::<String>();
            println!(
                "{:.1} s in all; {} frame(s) dropped{skipped}; wrote {}",
                report.wall_s,
                i.dropped,
                args.out.join("session.json").display()
            );
        }
        SessionOutcome::Interrupted => {
            println!(
                "interrupted; the stage that was running wrote its checkpoint in {}: the same command with --resume continues",
                args.out.display()
            )
        }
    }
    Ok(())
}
