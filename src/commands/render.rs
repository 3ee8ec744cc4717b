//! `aim render SPLATS.ply --camera CAMERA.json --out IMAGE.png`

use std::path::PathBuf;

use anyhow::Context;

use aim::camera::Camera;
use aim::render::{Backend, BackendChoice, RenderOptions};

#[derive(clap::Args)]
pub struct Args {
    /// A 3DGS PLY (original layout).
    pub splats: PathBuf,
    /// Camera JSON: {"width","height","fx","fy","cx","cy","world_to_camera": 4x4 rows} (OpenCV).
    #[arg(long)]
    pub camera: PathBuf,
    /// Output PNG.
    #[arg(long)]
    pub out: PathBuf,
    /// Background colour r,g,b in [0, 1].
    #[arg(long, value_parser = super::parse_rgb, default_value = "0,0,0")]
    pub background: glam::Vec3,
    /// Rasterizer: cpu, gpu (any Vulkan/Metal/DX12 adapter, lavapipe included)
    /// or auto (a hardware GPU if present, else cpu).
    #[arg(long, default_value = "cpu")]
    pub backend: BackendChoice,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let gs = aim::splat::ply::read_ply(&args.splats)?;
    let camera = Camera::load_json(&args.camera)?;
    let backend = Backend::open(args.backend)?;
    let t = std::time::Instant::now();
    let r = backend.render(&gs, &camera, &RenderOptions::uniform(args.background));
    tracing::info!(
        gaussians = gs.len(),
        backend = backend.describe(),
        ms = t.elapsed().as_secs_f64() * 1e3,
        "rendered {}x{}",
        r.width(),
        r.height()
    );
    super::save_png(&args.out, &image::DynamicImage::ImageRgb8(r.to_rgb8()))
        .with_context(|| format!("writing {}", args.out.display()))
}
