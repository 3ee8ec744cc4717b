//! `aim export RUN --to urdf|mjcf|ply|all --out DIR [--config EXPORT.toml]`:
//! write an existing run's twin again, in the formats asked for.

use std::path::PathBuf;

use anyhow::Context;

use aim::export::{export_twin, ExportConfig, Format, Twin};

#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Target {
    Urdf,
    Mjcf,
    Ply,
    All,
}

#[derive(clap::Args)]
pub struct Args {
    /// A run folder with twin/ in it, or a twin folder.
    pub run: PathBuf,
    /// Formats to write (repeatable).
    #[arg(long = "to", value_enum, required = true)]
    pub to: Vec<Target>,
    /// Output folder (may be the twin folder itself).
    #[arg(long)]
    pub out: PathBuf,
    /// TOML with the simulator settings (density, effort, velocity; docs/export.md).
    #[arg(long)]
    pub config: Option<PathBuf>,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let cfg = match &args.config {
        Some(path) => {
            let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
            let cfg: ExportConfig =
                toml::from_str(&text).with_context(|| format!("{}: not an export config", path.display()))?;
            cfg.validate().map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
            cfg
        }
        None => ExportConfig::default(),
    };
    let mut formats = Vec::new();
    for t in &args.to {
        match t {
            Target::Urdf => formats.push(Format::Urdf),
            Target::Mjcf => formats.push(Format::Mjcf),
            Target::Ply => formats.push(Format::Ply),
            Target::All => formats.extend([Format::Urdf, Format::Mjcf, Format::Ply]),
        }
    }
    let twin = Twin::open(&args.run)?;
    let art = export_twin(&twin, &args.out, &formats, &cfg)?;
    println!("{} parts, {} joints -> {} ({:?})", art.parts.len(), art.joints.len(), args.out.display(), formats);
    Ok(())
}
