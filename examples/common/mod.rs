//! What the examples share: the built-in synthetic recording, and a session on
//! a recording set up as `aim run RECORDING` sets it up.

use std::path::{Path, PathBuf};

use aim::stream::{open_input, run_session, SessionConfig, SessionControl, SessionEvent, SessionOutcome};
use aim_capture::recording::RecordingOptions;

/// The recording named as the first argument, or the built-in synthetic fridge
/// recording (`aim synth-recording fridge`) written under `scratch`; the output
/// folder, the second argument or `scratch/run`.
pub fn input_and_output(scratch: &str) -> anyhow::Result<(PathBuf, PathBuf)> {
    let mut args = std::env::args().skip(1);
    let root = std::env::temp_dir().join(scratch);
    let recording = match args.next() {
        Some(path) => PathBuf::from(path),
        None => {
            let path = root.join("recording");
            if !path.join("frames").is_dir() {
                println!("writing the built-in synthetic fridge recording to {}", path.display());
                let fridge = aim::synth::object("fridge")?;
                aim::synth::recording::write_recording(std::slice::from_ref(&fridge), &Default::default(), &path)?;
            }
            path
        }
    };
    let out = args.next().map_or_else(|| root.join("run"), PathBuf::from);
    Ok((recording, out))
}

/// Run `recording` (with its MPS files and object region beside it) through the
/// session to its twin in `out`, as `aim run` does with the cpu preset; `cfg`
/// changes the session's settings, `on_event` sees what happens as it happens.
pub fn run(
    recording: &Path,
    out: &Path,
    cfg: impl FnOnce(&mut SessionConfig),
    viz: &aim::viz::Viz,
    on_event: &(dyn Fn(SessionEvent) + Sync),
) -> anyhow::Result<()> {
    // The frames undistorted as `aim run` trains on them (704 px, focal 300).
    let options = RecordingOptions { undistort: aim::stream::TRAIN_UNDISTORT, ..Default::default() };
    let mut config = SessionConfig::cpu(0);
    let (opened, reference) = open_input(recording, &options, &mut config)?;
    cfg(&mut config);
    let interrupt = std::sync::atomic::AtomicBool::new(false);
    let control = SessionControl { interrupt: &interrupt, viz, backend: aim::render::Backend::Cpu, resume: false };
    match run_session(opened, reference, out, &config, &control, on_event)? {
        SessionOutcome::Finished { parts, report } => {
            for (interaction, parts) in report.interactions.iter().zip(&parts) {
                println!("{} (object {}):", interaction.dir, interaction.object);
                for (k, p) in parts.iter().enumerate() {
                    println!("  part {k}: {:?}, axis {:?}, amount {:.3}", p.joint.kind, p.joint.axis, p.joint.amount);
                }
                if let Some(gt) = &interaction.stage_two.gt_report {
                    println!("  against the ground truth: {}", serde_json::to_string(gt)?);
                }
                if let (Some(joints), Some(twin)) =
                    (interaction.hand_out_to_articulation_s, interaction.hand_out_to_twin_s)
                {
                    println!("  its joints {joints:.1} s and its twin {twin:.1} s after its hand-out");
                }
            }
            println!("{:.1} s in all; the twins in {}", report.wall_s, out.display());
        }
        SessionOutcome::Interrupted => println!("interrupted"),
    }
    Ok(())
}
