//! `aim render-twin RUN --camera CAMERA.json --out IMAGE.png [--state PART=VALUE ...]`
//! and `--turntable N` (frames into the folder `--out`).

use std::path::PathBuf;

use anyhow::Context;

use aim::camera::Camera;
use aim::export::{turntable, Twin};
use aim::render::{render, RenderOptions};

#[derive(clap::Args)]
pub struct Args {
    /// A run folder with twin/ in it, or a twin folder.
    pub run: PathBuf,
    /// Camera JSON: {"width","height","fx","fy","cx","cy","world_to_camera": 4x4 rows} (OpenCV).
    #[arg(long)]
    pub camera: PathBuf,
    /// Output PNG; with --turntable, a folder for frame_0000.png, ...
    #[arg(long)]
    pub out: PathBuf,
    /// A moving part's joint state: PART=VALUE (part id from articulation.json,
    /// radians or metres); parts not named stay at their start state.
    #[arg(long = "state", value_parser = parse_state)]
    pub states: Vec<(usize, f32)>,
    /// Render N frames with every joint sweeping its range and the camera
    /// circling the object once about +z (--state is then not used).
    #[arg(long)]
    pub turntable: Option<usize>,
    /// Background colour r,g,b in [0, 1].
    #[arg(long, value_parser = super::parse_rgb, default_value = "1,1,1")]
    pub background: glam::Vec3,
}

fn parse_state(s: &str) -> Result<(usize, f32), String> {
    let (part, value) = s.split_once('=').ok_or_else(|| format!("expected PART=VALUE, got '{s}'"))?;
    let part = part.trim().parse::<usize>().map_err(|e| format!("part '{part}' is not an id: {e}"))?;
    let value = value.trim().parse::<f32>().map_err(|e| format!("state '{value}' is not a number: {e}"))?;
    if !value.is_finite() {
        return Err(format!("state '{value}' is not finite"));
    }
    Ok((part, value))
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let twin = Twin::open(&args.run)?;
    let parts = twin.part_gaussians()?;
    let camera = Camera::load_json(&args.camera)?;
    let options = RenderOptions::uniform(args.background);
    let Some(frames) = args.turntable else {
        let gs = twin.gaussians_at(&parts, &args.states)?;
        let r = render(&gs, &camera, &options);
        super::save_png(&args.out, &image::DynamicImage::ImageRgb8(r.to_rgb8()))
            .with_context(|| format!("writing {}", args.out.display()))?;
        println!("{}", args.out.display());
        return Ok(());
    };
    std::fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
    let views = turntable(&twin, &parts, &camera, frames)?;
    let progress = super::progress::Progress::new("turntable", views.len() as u32);
    for (k, (gs, view)) in views.iter().enumerate() {
        let path = args.out.join(format!("frame_{k:04}.png"));
        let r = render(gs, view, &options);
        super::save_png(&path, &image::DynamicImage::ImageRgb8(r.to_rgb8()))
            .with_context(|| format!("writing {}", path.display()))?;
        progress.update(k as u32 + 1, || format!("frame {k}"));
    }
    progress.finish();
    println!("{} frames in {}", views.len(), args.out.display());
    Ok(())
}
