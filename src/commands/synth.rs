//! `aim synth --list` and `aim synth OBJECT --out DIR [--res 256] [--motion-frames 200] [--scan-views 100] [--seed N]`

use std::path::PathBuf;

use anyhow::Context;

use aim::synth::{objects, write_dataset, SynthConfig, HELD_OUT_NAMES, OBJECT_NAMES};

#[derive(clap::Args)]
pub struct Args {
    /// Object to generate (see --list).
    #[arg(required_unless_present_any = ["list", "contact_sheet", "all"])]
    pub object: Option<String>,
    /// List the objects and their joints, then exit.
    #[arg(long)]
    pub list: bool,
    /// Generate every benchmark object (not the held-out ones), each into OUT/OBJECT.
    #[arg(long, conflicts_with = "object")]
    pub all: bool,
    /// Output directory (default: out/synth/OBJECT; with --all the parent, default out/synth).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Image width and height in pixels.
    #[arg(long, default_value_t = 256)]
    pub res: u32,
    /// Motion video frames.
    #[arg(long, default_value_t = 200)]
    pub motion_frames: usize,
    /// Start-state training views.
    #[arg(long, default_value_t = 100)]
    pub scan_views: usize,
    /// End-state training views.
    #[arg(long, default_value_t = 100)]
    pub end_views: usize,
    /// Colour samples per pixel (rounded to a square: 1, 4, 9, ...).
    #[arg(long, default_value_t = 4)]
    pub spp: u32,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Write a contact sheet PNG of every object at start and end to this path, then exit.
    #[arg(long)]
    pub contact_sheet: Option<PathBuf>,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    if args.list {
        let held_out = HELD_OUT_NAMES.iter().map(|n| (n, " (held out of the benchmark)"));
        for (name, note) in OBJECT_NAMES.iter().map(|n| (n, "")).chain(held_out) {
            let o = objects::object(name)?;
            let joints: Vec<String> = o
                .joints
                .iter()
                .map(|j| match j.kind {
                    aim::synth::JointKind::Revolute => format!(
                        "{} revolute {:.0}..{:.0} deg",
                        o.parts[j.part].name,
                        j.range[0].to_degrees(),
                        j.range[1].to_degrees()
                    ),
                    aim::synth::JointKind::Prismatic => {
                        format!("{} prismatic {}..{} m", o.parts[j.part].name, j.range[0], j.range[1])
                    }
                })
                .collect();
            println!("{name:<20} {} parts: {}{note}", o.parts.len(), joints.join("; "));
        }
        return Ok(());
    }
    if let Some(path) = &args.contact_sheet {
        let sheet = aim::synth::contact_sheet::contact_sheet(192)?;
        super::save_png(path, &image::DynamicImage::ImageRgba8(sheet))
            .with_context(|| format!("writing {}", path.display()))?;
        println!("wrote {}", path.display());
        return Ok(());
    }
    let cfg = SynthConfig {
        resolution: args.res,
        scan_views: args.scan_views,
        motion_frames: args.motion_frames,
        end_views: args.end_views,
        samples_per_pixel: args.spp,
        seed: args.seed,
        ..SynthConfig::default()
    };
    let jobs: Vec<(String, PathBuf)> = if args.all {
        let root = args.out.clone().unwrap_or_else(|| PathBuf::from("out/synth"));
        OBJECT_NAMES.iter().map(|n| (n.to_string(), root.join(n))).collect()
    } else {
        let name = args.object.clone().unwrap_or_default();
        let out = args.out.clone().unwrap_or_else(|| PathBuf::from("out/synth").join(&name));
        vec![(name, out)]
    };
    for (name, out) in jobs {
        let object = objects::object(&name)?;
        let t = std::time::Instant::now();
        let bar = indicatif::ProgressBar::new(0);
        bar.set_style(
            indicatif::ProgressStyle::with_template("{prefix} [{bar:40}] {pos}/{len} views {elapsed}")
                .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
        );
        bar.set_prefix(name.clone());
        let summary = write_dataset(&object, &out, &cfg, &|done, total| {
            bar.set_length(total as u64);
            bar.set_position(done as u64);
        })?;
        bar.finish_and_clear();
        println!(
            "wrote {} ({} views, {} parts) to {} in {:.1} s",
            summary.object,
            summary.views,
            summary.parts,
            summary.out.display(),
            t.elapsed().as_secs_f64()
        );
    }
    Ok(())
}
