//! A recording played as a live capture: frames arrive at their recorded rate,
//! the oldest buffered frame is dropped when training falls behind, and each
//! stage's progress is printed as it goes, with how long after the hand let go
//! the twin was ready:
//!
//! ```sh
//! cargo run --release --example live_preview [RECORDING [OUT]]
//! ```

#[path = "common/mod.rs"]
mod common;

use aim::stream::SessionEvent;

fn main() -> anyhow::Result<()> {
    let (recording, out) = common::input_and_output("aim-example-live-preview")?;
    let live = |cfg: &mut aim::stream::SessionConfig| cfg.go_live();
    common::run(&recording, &out, live, &aim::viz::Viz::disabled(), &|e| match e {
        SessionEvent::Window(w) => println!("live: {w:?}"),
        SessionEvent::StageOneStarted { views, .. } => println!("live: stage I starts on {views} scan frames"),
        SessionEvent::StageOne(r) if r.iteration % 500 == 0 => {
            println!("live: stage I {} PSNR {:.2} dB, {} Gaussians", r.iteration, r.psnr, r.gaussians)
        }
        SessionEvent::StageTwoStarted { motion, end, .. } => println!("live: stage II on {motion} + {end} frames"),
        SessionEvent::StageTwo(s) if s.iteration % 720 == 0 => {
            println!("live: stage II {} PSNR {:.2} dB", s.iteration, s.psnr)
        }
        SessionEvent::Articulated { parts, hand_out_to_articulation_s: Some(lag), .. } => {
            println!("live: {} part(s) and their joints {lag:.1} s after hand-out", parts.len())
        }
        _ => {}
    })
}
