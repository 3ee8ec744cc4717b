//! `aim eval RUN --gt DATASET [--json]`: the paper's metrics for an exported twin.

use std::path::PathBuf;

use aim::eval::twin::{evaluate_twin, EvalConfig, EvalReport, GroundTruth};
use aim::motion::JointKind;

#[derive(clap::Args)]
pub struct Args {
    /// A train-dynamic output folder (with twin/) or a twin folder.
    pub run: PathBuf,
    /// The dataset with the ground truth (gt/joints.json and the gt/start meshes).
    #[arg(long)]
    pub gt: PathBuf,
    /// Print the report as JSON.
    #[arg(long)]
    pub json: bool,
}

fn opt(v: Option<f64>, digits: usize) -> String {
    v.map_or("-".into(), |v| format!("{v:.digits$}"))
}

/// The report as text, one line per part.
pub fn print_report(r: &EvalReport) {
    println!(
        "{}: {} moving part(s) in the ground truth, {} in the twin",
        r.object, r.gt_moving_parts, r.predicted_moving_parts
    );
    let cd = |c: Option<aim::eval::shape::ChamferDistance>| {
        c.map_or("-".into(), |c| format!("{:.2} mm (squared x1000: {:.4})", c.l2_mm, c.squared_l2_x1000))
    };
    println!("    static: CD-s {}, IoU {} %", cd(r.static_part.chamfer), opt(r.static_part.iou_percent, 2));
    for p in &r.moving_parts {
        let Some(pred) = p.predicted else {
            println!("    GT part {}: MISSING (a failure)", p.gt_part);
            continue;
        };
        let j = r.joints.matched.iter().find(|e| e.gt_part == p.gt_part);
        let joint = j.map_or(String::new(), |e| {
            let motion = match e.kind {
                JointKind::Revolute => format!("{:.2} deg", e.part_motion),
                JointKind::Prismatic => format!("{:.4} m", e.part_motion),
            };
            format!(
                "axis angle {:.2} deg, axis position {} (0.1 m), part motion {motion}, ",
                e.axis_angle_deg,
                opt(e.axis_position, 3)
            )
        });
        println!(
            "    GT part {} <- twin part {pred}: {joint}CD-m {}, IoU {} %",
            p.gt_part,
            cd(p.chamfer),
            opt(p.iou_percent, 2)
        );
    }
    for p in &r.joints.extra {
        println!("    twin part {p}: EXTRA (matches no ground-truth part; a failure)");
    }
    println!("    whole: CD-w {}; mean IoU {} %; failures {}", cd(r.whole), opt(r.mean_iou_percent, 2), r.failures);
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let gt = GroundTruth::load(&args.gt)?;
    let report = evaluate_twin(&args.run, &gt, &EvalConfig::default())?;
    if args.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        print_report(&report);
    }
    Ok(())
}
