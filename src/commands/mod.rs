//! One file per subcommand: argument parsing and progress display only; the work
//! is done by library functions.

pub mod batch;
pub mod bench;
pub mod capture;
pub mod demo;
pub mod eval;
pub mod export;
pub mod mesh;
pub mod progress;
pub mod render;
pub mod render_twin;
pub mod run;
pub mod synth;
pub mod synth_recording;
pub mod train_dynamic;
pub mod train_static;

use std::path::Path;

/// Parse "r,g,b" with components in [0, 1].
pub fn parse_rgb(s: &str) -> Result<glam::Vec3, String> {
    let parts: Vec<f32> = s
        .split(',')
        .map(|p| p.trim().parse::<f32>().map_err(|e| format!("'{p}' is not a number: {e}")))
        .collect::<Result<_, _>>()?;
    match parts[..] {
        [r, g, b] if parts.iter().all(|v| (0.0..=1.0).contains(v)) => Ok(glam::Vec3::new(r, g, b)),
        _ => Err(format!("expected r,g,b with each in [0, 1], got '{s}'")),
    }
}

/// Encode an image as PNG and write it atomically.
pub fn save_png(path: &Path, img: &image::DynamicImage) -> anyhow::Result<()> {
    let mut bytes = Vec::new();
    img.write_to(&mut std::io::Cursor::new(&mut bytes), image::ImageFormat::Png)?;
    aim::error::write_atomic(path, &bytes)?;
    Ok(())
}
