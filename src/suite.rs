//! The benchmark suite: every synthetic object, several trials (trial k uses
//! seed k for the data and the training), stages I-III at a preset, evaluated
//! with the paper's metrics, and tables shaped like the paper's Tables 1-4.
//!
//! Each (object, trial, variant) result is saved as JSON when it is done, and
//! stage runs checkpoint, so an interrupted suite resumes where it stopped.
//! Variants other than the full method are the paper's Table 4 ablations, run
//! on the complex objects.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::time::Instant;

use serde::{Deserialize, Serialize};

use crate::error::{write_atomic, Error, Result};
use crate::eval::twin::{evaluate_twin, EvalConfig, EvalReport, GroundTruth};
use crate::mesh::tsdf::TsdfConfig;
use crate::motion::JointKind;
use crate::synth::{object, write_dataset, SynthConfig};
use crate::train::config::{StageConfig, StaticConfig};
use crate::train::dynamic_run::{run_dynamic, DynamicOutcome, RunControl, StageTwoInput};
use crate::train::dynamic_stage::DynamicConfig;
use crate::train::static_stage::{run_static, RunOutcome, RunSetup};
use crate::train::views::load_phase_views;
use crate::viz::Viz;

/// The method as configured, or one of the paper's Table 4 ablations.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Variant {
    Full,
    /// No static-during-motion detection.
    NoSdmd,
    /// One deformable set for everything ("Ours-b").
    SingleSet,
    /// Random Gaussians as the static set instead of the start-state scan.
    RandomStatic,
    /// K-means with the true part count instead of sequential RANSAC.
    Kmeans,
}

impl Variant {
    pub const ABLATIONS: [Variant; 4] = [Variant::NoSdmd, Variant::SingleSet, Variant::RandomStatic, Variant::Kmeans];

    pub fn name(self) -> &'static str {
        match self {
            Variant::Full => "full",
            Variant::NoSdmd => "no_sdmd",
            Variant::SingleSet => "single_set",
            Variant::RandomStatic => "random_static",
            Variant::Kmeans => "kmeans",
        }
    }

    fn label(self) -> &'static str {
        match self {
            Variant::Full => "Ours (full)",
            Variant::NoSdmd => "w/o SDMD",
            Variant::SingleSet => "single deformable set (Ours-b)",
            Variant::RandomStatic => "random static initialisation",
            Variant::Kmeans => "K-means (true K) instead of sequential RANSAC",
        }
    }

    /// Stage II settings of this variant; `moving_parts` is the true count (for K-means).
    fn configure(self, cfg: &mut DynamicConfig, moving_parts: usize) {
        match self {
            Variant::Full | Variant::RandomStatic => {}
            Variant::NoSdmd => cfg.sdmd_interval = 0,
            Variant::SingleSet => cfg.single_deformable_set = true,
            Variant::Kmeans => cfg.kmeans_parts = moving_parts,
        }
    }
}

/// The paper's object categories, by the number of moving parts.
pub fn category(moving_parts: usize) -> &'static str {
    match moving_parts {
        0 | 1 => "two-part",
        2 => "three-part",
        _ => "complex",
    }
}

/// What to run.
#[derive(Clone, Debug)]
pub struct SuiteOptions {
    pub objects: Vec<String>,
    pub trials: u32,
    pub preset: String,
    /// Run the Table 4 ablations on the complex objects.
    pub ablations: bool,
    pub out: PathBuf,
    /// The dataset settings (the seed is set per trial).
    pub synth: SynthConfig,
}

/// One finished (object, trial, variant).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct TrialRecord {
    pub object: String,
    pub category: String,
    pub trial: u32,
    pub variant: Variant,
    pub stage1_psnr: Option<f32>,
    pub stage1_wall_s: f64,
    pub stage2_wall_s: f64,
    /// Stage I + II + III + evaluation of this record (stage I counted for every variant).
    pub wall_s: f64,
    pub report: Option<EvalReport>,
    /// The error that stopped this run (a failure, listed in the tables).
    pub error: Option<String>,
}

impl TrialRecord {
    pub fn failed(&self) -> bool {
        self.error.is_some() || self.report.as_ref().is_none_or(|r| r.failures > 0)
    }
}

/// One planned run.
#[derive(Clone, Debug)]
pub struct PlannedRun {
    pub object: String,
    pub trial: u32,
    pub variant: Variant,
}

impl SuiteOptions {
    pub fn plan(&self) -> Result<Vec<PlannedRun>> {
        let mut runs = Vec::new();
        for name in &self.objects {
            let moving = object(name)?.joints.len();
            let variants: Vec<Variant> = if self.ablations && category(moving) == "complex" {
                std::iter::once(Variant::Full).chain(Variant::ABLATIONS).collect()
            } else {
                vec![Variant::Full]
            };
            for trial in 0..self.trials {
                for &variant in &variants {
                    runs.push(PlannedRun { object: name.clone(), trial, variant });
                }
            }
        }
        Ok(runs)
    }

    fn record_path(&self, r: &PlannedRun) -> PathBuf {
        self.out.join("results").join(format!("{}_t{}_{}.json", r.object, r.trial, r.variant.name()))
    }
}

/// A saved record, if this run is done.
pub fn load_record(path: &Path) -> Result<Option<TrialRecord>> {
    if !path.exists() {
        return Ok(None);
    }
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    serde_json::from_slice(&bytes).map(Some).map_err(|e| Error::bad_file(path, format!("not a suite record: {e}")))
}

/// Stage I of one trial (resumed or reused when already done): the static.ply and its test PSNR.
fn stage_one(
    data: &Path,
    run_dir: &Path,
    preset: &str,
    seed: u64,
    interrupt: &AtomicBool,
) -> Result<Option<(PathBuf, f32, f64)>> {
    let metrics_path = run_dir.join("metrics.json");
    if let Ok(bytes) = std::fs::read(&metrics_path) {
        if let Ok(m) = serde_json::from_slice::<crate::train::static_stage::StaticMetrics>(&bytes) {
            return Ok(Some((run_dir.join("static.ply"), m.mean_psnr, m.wall_time_s)));
        }
    }
    let cfg = StaticConfig::resolve(None, preset, Some(seed), None)?;
    let (train, test) = load_phase_views(data, aim_capture::Phase::Scan, cfg.resolution, cfg.depth_weight > 0.0)?;
    let setup = RunSetup { run_dir, resume: true, init: None, arriving: None, backend: crate::render::Backend::Cpu };
    match run_static(cfg, &train, &test, &setup, interrupt, &Viz::disabled(), |_| {})? {
        RunOutcome::Finished(m) => Ok(Some((run_dir.join("static.ply"), m.mean_psnr, m.wall_time_s))),
        RunOutcome::Interrupted(_) => Ok(None),
    }
}

/// The ablation's static set: random Gaussians in the stage I init box (as its random init).
fn random_static(run_dir: &Path, preset: &str, seed: u64) -> Result<PathBuf> {
    let cfg = StaticConfig::resolve(None, preset, Some(seed), None)?;
    let pts = crate::train::init::random_points(
        cfg.init.points,
        glam::Vec3::from(cfg.init.box_min),
        glam::Vec3::from(cfg.init.box_max),
        seed ^ 0xab1a,
    );
    let gs = crate::train::init::gaussians_from_points(&pts, None, cfg.init.opacity, cfg.sh_degree);
    std::fs::create_dir_all(run_dir).map_err(|e| Error::io(run_dir, e))?;
    let path = run_dir.join("random_static.ply");
    crate::splat::ply::write_ply(&path, &gs)?;
    Ok(path)
}

/// Run one planned (object, trial, variant); None when interrupted.
fn run_one(opts: &SuiteOptions, run: &PlannedRun, interrupt: &AtomicBool) -> Result<Option<TrialRecord>> {
    let started = Instant::now();
    let obj = object(&run.object)?;
    let seed = u64::from(run.trial);
    let data = opts.out.join("data").join(format!("{}_t{}", run.object, run.trial));
    if !crate::eval::twin::has_ground_truth(&data) {
        let synth = SynthConfig { seed, ..opts.synth.clone() };
        write_dataset(&obj, &data, &synth, &|_, _| {})?;
    }
    let trial_dir = opts.out.join("runs").join(format!("{}_t{}", run.object, run.trial));
    let mut record = TrialRecord {
        object: run.object.clone(),
        category: category(obj.joints.len()).into(),
        trial: run.trial,
        variant: run.variant,
        stage1_psnr: None,
        stage1_wall_s: 0.0,
        stage2_wall_s: 0.0,
        wall_s: 0.0,
        report: None,
        error: None,
    };
    let static_ply = if run.variant == Variant::RandomStatic {
        random_static(&trial_dir.join(run.variant.name()), &opts.preset, seed)?
    } else {
        let Some((ply, psnr, wall)) = stage_one(&data, &trial_dir.join("static"), &opts.preset, seed, interrupt)?
        else {
            return Ok(None);
        };
        record.stage1_psnr = Some(psnr);
        record.stage1_wall_s = wall;
        ply
    };
    let mut cfg = DynamicConfig::resolve(None, &opts.preset, Some(seed), None)?;
    run.variant.configure(&mut cfg, obj.joints.len());
    let out = trial_dir.join(run.variant.name());
    let viz = Viz::disabled();
    let control = RunControl { resume: true, interrupt, viz: &viz, backend: crate::render::Backend::Cpu };
    let input = StageTwoInput::load(&data, &cfg)?;
    match run_dynamic(input, &static_ply, &out, cfg, &TsdfConfig::default(), &control, |_| {}) {
        Ok(DynamicOutcome::Interrupted(_)) => return Ok(None),
        Ok(DynamicOutcome::Finished { metrics, .. }) => {
            record.stage2_wall_s = metrics.wall_time_s;
            let gt = GroundTruth::load(&data)?;
            match evaluate_twin(&out, &gt, &EvalConfig { seed, ..EvalConfig::default() }) {
                Ok(r) => record.report = Some(r),
                Err(e) => record.error = Some(format!("evaluation: {e}")),
            }
        }
        Err(e) => record.error = Some(format!("stages II-III: {e}")),
    }
    record.wall_s = record.stage1_wall_s + started.elapsed().as_secs_f64();
    Ok(Some(record))
}

/// Run (or resume) the suite; `progress(done, total, record)` after each run.
/// Returns every record, or None when interrupted (what is done is saved).
pub fn run_suite(
    opts: &SuiteOptions,
    interrupt: &AtomicBool,
    mut progress: impl FnMut(usize, usize, &TrialRecord),
) -> Result<Option<Vec<TrialRecord>>> {
    let plan = opts.plan()?;
    let mut records = Vec::new();
    for (k, run) in plan.iter().enumerate() {
        let path = opts.record_path(run);
        let record = match load_record(&path)? {
            Some(r) => r,
            None => {
                let Some(r) = run_one(opts, run, interrupt)? else { return Ok(None) };
                let json = serde_json::to_vec_pretty(&r).map_err(|e| Error::Other(e.to_string()))?;
                std::fs::create_dir_all(path.parent().unwrap_or(&opts.out)).map_err(|e| Error::io(&opts.out, e))?;
                write_atomic(&path, &json)?;
                r
            }
        };
        progress(k + 1, plan.len(), &record);
        records.push(record);
    }
    let tables = tables_markdown(&records, opts);
    write_atomic(&opts.out.join("tables.md"), tables.as_bytes())?;
    Ok(Some(records))
}

/// mean +- std of `values` ("-" when empty).
fn mean_std(values: &[f64], digits: usize) -> String {
    if values.is_empty() {
        return "-".into();
    }
    let n = values.len() as f64;
    let mean = values.iter().sum::<f64>() / n;
    let std = (values.iter().map(|v| (v - mean) * (v - mean)).sum::<f64>() / n).sqrt();
    if values.len() == 1 {
        format!("{mean:.digits$}")
    } else {
        format!("{mean:.digits$} ± {std:.digits$}")
    }
}

/// One metric of a record (None where it does not apply or is missing).
type Metric = fn(&EvalReport) -> Option<f64>;

fn avg(values: impl Iterator<Item = f64>) -> Option<f64> {
    let v: Vec<f64> = values.collect();
    (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
}

fn metric_rows() -> Vec<(&'static str, &'static str, Metric, usize)> {
    vec![
        ("3D IoU (%)", "static", |r| r.static_part.iou_percent, 2),
        ("3D IoU (%)", "dynamic (avg)", |r| r.moving_iou_percent(), 2),
        ("3D IoU (%)", "mean", |r| r.mean_iou_percent, 2),
        ("Chamfer (mm, L2)", "CD-s", |r| r.static_part.chamfer.map(|c| c.l2_mm), 2),
        (
            "Chamfer (mm, L2)",
            "CD-m (avg)",
            |r| avg(r.moving_parts.iter().filter_map(|p| p.chamfer.map(|c| c.l2_mm))),
            2,
        ),
        ("Chamfer (mm, L2)", "CD-w", |r| r.whole.map(|c| c.l2_mm), 2),
        ("Chamfer (squared x1000)", "CD-w", |r| r.whole.map(|c| c.squared_l2_x1000), 4),
        ("Articulation", "axis angle (deg)", |r| avg(r.joints.matched.iter().map(|e| e.axis_angle_deg)), 2),
        ("Articulation", "axis position (0.1 m)", |r| avg(r.joints.matched.iter().filter_map(|e| e.axis_position)), 3),
        (
            "Articulation",
            "part motion, revolute (deg)",
            |r| avg(r.joints.matched.iter().filter(|e| e.kind == JointKind::Revolute).map(|e| e.part_motion)),
            2,
        ),
        (
            "Articulation",
            "part motion, prismatic (m)",
            |r| avg(r.joints.matched.iter().filter(|e| e.kind == JointKind::Prismatic).map(|e| e.part_motion)),
            4,
        ),
        ("Parts", "moving parts found", |r| Some(r.predicted_moving_parts as f64), 1),
    ]
}

/// A cell: mean ± std over the trials where it is defined, and "F k/K" when k of
/// the K trials failed (a missing or extra part, or an error).
fn cell(records: &[&TrialRecord], metric: Metric, digits: usize) -> String {
    let values: Vec<f64> = records.iter().filter_map(|r| r.report.as_ref().and_then(metric)).collect();
    let failed = records.iter().filter(|r| r.failed()).count();
    let mut s = mean_std(&values, digits);
    if failed > 0 {
        let _ = write!(s, " (F {failed}/{})", records.len());
    }
    s
}

/// The tables (Markdown): per category the paper's Tables 1-3 as rows of one
/// table per category, wall times, and Table 4 on the complex objects.
pub fn tables_markdown(records: &[TrialRecord], opts: &SuiteOptions) -> String {
    let mut s = String::new();
    let trials = opts.trials;
    let _ = writeln!(s, "Preset `{}`, {trials} trial(s) per object (trial k: seed k). Cells: mean ± std over trials; (F k/K): k of K trials failed (a missing or extra part, or an error), their matched parts still counted.\n", opts.preset);
    for cat in ["two-part", "three-part", "complex"] {
        let objects: Vec<&str> = opts
            .objects
            .iter()
            .map(String::as_str)
            .filter(|o| records.iter().any(|r| r.object == *o && r.category == cat))
            .collect();
        if objects.is_empty() {
            continue;
        }
        let of = |o: &str| -> Vec<&TrialRecord> {
            records.iter().filter(|r| r.object == o && r.variant == Variant::Full).collect()
        };
        let _ = writeln!(s, "### {cat} objects\n");
        let _ = writeln!(s, "| metric | | {} |", objects.join(" | "));
        let _ = writeln!(s, "|---|---|{}", "---|".repeat(objects.len()));
        for (group, name, metric, digits) in metric_rows() {
            let cells: Vec<String> = objects.iter().map(|o| cell(&of(o), metric, digits)).collect();
            let _ = writeln!(s, "| {group} | {name} | {} |", cells.join(" | "));
        }
        let psnr: Vec<String> = objects
            .iter()
            .map(|o| mean_std(&of(o).iter().filter_map(|r| r.stage1_psnr.map(f64::from)).collect::<Vec<_>>(), 2))
            .collect();
        let _ = writeln!(s, "| Stage I | test PSNR (dB) | {} |", psnr.join(" | "));
        let walls: Vec<String> =
            objects.iter().map(|o| mean_std(&of(o).iter().map(|r| r.wall_s).collect::<Vec<_>>(), 0)).collect();
        let _ = writeln!(s, "| Wall | stages I-III + eval (s) | {} |\n", walls.join(" | "));
    }
    let complex: Vec<&str> = opts
        .objects
        .iter()
        .map(String::as_str)
        .filter(|o| records.iter().any(|r| r.object == *o && r.category == "complex" && r.variant != Variant::Full))
        .collect();
    if !complex.is_empty() {
        let _ = writeln!(s, "### Ablations on the complex objects ({})\n", complex.join(", "));
        let cols = [
            ("Ang avg (deg)", 7usize),
            ("Pos avg (0.1 m)", 8),
            ("Motion r avg (deg)", 9),
            ("Motion p avg (m)", 10),
            ("CD-m avg (mm)", 4),
            ("IoU D avg (%)", 1),
        ];
        let rows = metric_rows();
        let _ = writeln!(s, "| variant | {} |", cols.iter().map(|c| c.0).collect::<Vec<_>>().join(" | "));
        let _ = writeln!(s, "|---|{}", "---|".repeat(cols.len()));
        for v in std::iter::once(Variant::Full).chain(Variant::ABLATIONS) {
            let rs: Vec<&TrialRecord> =
                records.iter().filter(|r| r.variant == v && complex.contains(&r.object.as_str())).collect();
            if rs.is_empty() {
                continue;
            }
            let cells: Vec<String> = cols.iter().map(|&(_, row)| cell(&rs, rows[row].2, rows[row].3)).collect();
            let _ = writeln!(s, "| {} | {} |", v.label(), cells.join(" | "));
        }
    }
    s
}
