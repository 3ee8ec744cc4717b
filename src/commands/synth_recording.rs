//! `aim synth-recording OBJECT[,OBJECT...] --out DIR`: a synthetic Aria-like
//! recording (fisheye frames, calibration JSON, MPS trajectory and hand tracking,
//! ground truth), one interaction per object.

use std::path::PathBuf;

use aim::synth::objects;
use aim::synth::recording::{write_recording, RecordingConfig};

#[derive(clap::Args)]
pub struct Args {
    /// Object (see `aim synth --list`), or several separated by commas: they stand
    /// in a row and the wearer opens each in turn (one interaction each).
    pub object: String,
    #[arg(long)]
    pub out: PathBuf,
    /// Frame size in pixels (square; Aria RGB records 1408).
    #[arg(long, default_value_t = 704)]
    pub resolution: u32,
    #[arg(long, default_value_t = 15.0)]
    pub fps: f64,
    /// Seconds of scanning before the hand touches the part.
    #[arg(long, default_value_t = 3.0)]
    pub scan: f64,
    /// Seconds of motion.
    #[arg(long, default_value_t = 2.5)]
    pub motion: f64,
    /// Seconds after the hand lets go.
    #[arg(long, default_value_t = 2.0)]
    pub after: f64,
    /// Leave the hand out (a recording without interaction).
    #[arg(long)]
    pub no_hand: bool,
}

pub fn run(a: Args) -> anyhow::Result<()> {
    let objects = a.object.split(',').map(objects::object).collect::<Result<Vec<_>, _>>()?;
    let cfg = RecordingConfig {
        resolution: a.resolution,
        fps: a.fps,
        scan_s: a.scan,
        motion_s: a.motion,
        after_s: a.after,
        hand: !a.no_hand,
        ..RecordingConfig::default()
    };
    let t = std::time::Instant::now();
    let s = write_recording(&objects, &cfg, &a.out)?;
    eprintln!("wrote {} frames to {} in {:.1} s", s.frames, a.out.display(), t.elapsed().as_secs_f64());
    println!("{}", serde_json::to_string_pretty(&s)?);
    Ok(())
}
