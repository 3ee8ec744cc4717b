//! Replay an Aria recording (VRS or frames, with its MPS folder and
//! object_region.json beside it) to its twin, never dropping a frame:
//!
//! ```sh
//! cargo run --release --example aria_replay [RECORDING [OUT]]
//! ```
//!
//! Without arguments it writes the built-in synthetic fridge recording first.

#[path = "common/mod.rs"]
mod common;

use aim::stream::SessionEvent;

fn main() -> anyhow::Result<()> {
    let (recording, out) = common::input_and_output("aim-example-aria-replay")?;
    common::run(&recording, &out, |_| {}, &aim::viz::Viz::disabled(), &|e| match e {
        SessionEvent::Window(w) => println!("motion window: {w:?}"),
        SessionEvent::StageOneStarted { views, .. } => println!("stage I on {views} scan frames"),
        SessionEvent::StageTwoStarted { motion, end, .. } => {
            println!("stages II and III on {motion} motion and {end} end-state frames")
        }
        SessionEvent::StageOne(_) | SessionEvent::StageTwo(_) | SessionEvent::Articulated { .. } => {}
    })
}
