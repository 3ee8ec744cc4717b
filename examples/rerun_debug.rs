//! A recording's session logged to rerun for visual debugging: input frames'
//! cameras by phase, the motion window, losses, stage I's Gaussians, stage
//! II's tracked states and the final parts (entity paths in docs/session.md).
//! Written to an .rrd file to open with `rerun FILE`:
//!
//! ```sh
//! cargo run --release --example rerun_debug [RECORDING [OUT]]
//! ```

#[path = "common/mod.rs"]
mod common;

use aim::viz::{Viz, VizTarget};

fn main() -> anyhow::Result<()> {
    let (recording, out) = common::input_and_output("aim-example-rerun-debug")?;
    std::fs::create_dir_all(&out)?;
    let rrd = out.join("session.rrd");
    let viz = Viz::new("aim", &VizTarget::File(rrd.clone()))?;
    common::run(&recording, &out, |_| {}, &viz, &|_| {})?;
    viz.flush();
    println!("open it with: rerun {}", rrd.display());
    Ok(())
}
