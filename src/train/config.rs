//! Stage I configuration: every value of the schedule, density control and
//! initialisation, read from TOML with unknown keys rejected, plus the presets.
//!
//! Presets (docs/training.md says what each costs):
//! - `paper`: the official AiM code's stage I (20k iterations at full resolution,
//!   100k random initial points, densify every 100 from 500 to 20k at 3e-4).
//! - `cpu`: chosen by measurement to reach >= 30 dB on the synthetic benchmark in
//!   a few minutes on two cores (lower resolution, fewer iterations and points, a
//!   cap on the Gaussian count).

use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};

/// Learning rates (3DGS names; means are multiplied by the scene extent).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LrConfig {
    pub means_init: f32,
    pub means_final: f32,
    pub means_delay_mult: f32,
    pub sh_dc: f32,
    /// SH rest coefficients (3DGS: sh_dc / 20).
    pub sh_rest: f32,
    pub opacity: f32,
    pub scale: f32,
    pub rotation: f32,
}

impl LrConfig {
    /// The learning rates at iteration `it` of `max_steps`: the mean rate decays
    /// exponentially (3DGS) and is scaled by the scene extent; the others are constant.
    pub fn rates(&self, it: u32, max_steps: u32, extent: f32) -> crate::train::optim::LearningRates {
        let means = crate::train::optim::ExponLr {
            lr_init: self.means_init * extent,
            lr_final: self.means_final * extent,
            delay_steps: 0,
            delay_mult: self.means_delay_mult,
            max_steps: u64::from(max_steps),
        };
        crate::train::optim::LearningRates {
            means: means.at(u64::from(it)),
            log_scales: self.scale,
            rotations: self.rotation,
            opacity_logits: self.opacity,
            sh_dc: self.sh_dc,
            sh_rest: self.sh_rest,
        }
    }
}

/// Adaptive density control (3DGS).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DensityConfig {
    pub from_iter: u32,
    pub until_iter: u32,
    pub interval: u32,
    /// Threshold on the mean NDC screen-space gradient norm.
    pub grad_threshold: f32,
    /// Gaussians larger than this fraction of the scene extent are split, smaller cloned.
    pub percent_dense: f32,
    pub opacity_reset_interval: u32,
    pub min_opacity: f32,
    /// Prune Gaussians whose screen radius exceeds this many pixels (after the first opacity reset).
    pub max_screen_size: f32,
    /// Prune Gaussians larger than this fraction of the scene extent (after the first opacity reset).
    pub max_world_size: f32,
    /// Stop densifying once this many Gaussians exist (0 = no cap).
    pub max_gaussians: usize,
}

impl DensityConfig {
    /// Limits of a densify-and-prune step at iteration `it` in a scene of `extent`:
    /// the size-based pruning starts after the first opacity reset (3DGS).
    pub fn densify_params(&self, it: u32, extent: f32) -> crate::train::density::DensifyParams {
        let size_limits = it > self.opacity_reset_interval;
        crate::train::density::DensifyParams {
            grad_threshold: self.grad_threshold,
            dense_size: self.percent_dense * extent,
            min_opacity: self.min_opacity,
            max_screen_size: size_limits.then_some(self.max_screen_size),
            max_world_size: size_limits.then_some(self.max_world_size * extent),
            max_gaussians: self.max_gaussians,
        }
    }
}

/// How the start-state Gaussians are created.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct InitConfig {
    /// Random points when no point cloud is given.
    pub points: usize,
    pub box_min: [f32; 3],
    pub box_max: [f32; 3],
    pub opacity: f32,
}

/// Stage I: the start-state 3DGS.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StaticConfig {
    pub preset: String,
    pub iterations: u32,
    /// Train (and evaluate) at this image width, keeping the aspect; 0 = as recorded.
    pub resolution: u32,
    pub seed: u64,
    pub sh_degree: u32,
    /// Raise the active SH degree by one every this many iterations.
    pub sh_increase_interval: u32,
    pub lambda_dssim: f32,
    /// Weight of the depth loss log(1 + |D - D_gt|) (the official code's, on the
    /// rendered accumulated depth, metres) on pixels where the dataset's depth map is
    /// known; 0 = RGB only (both presets: an Aria RGB camera has no depth). The
    /// depth maps are read only when this is positive.
    #[serde(default)]
    pub depth_weight: f32,
    /// Composite RGBA targets over a random colour each iteration (official --random_bg_color).
    pub random_background: bool,
    /// Background for evaluation renders and targets.
    pub eval_background: [f32; 3],
    /// Write a checkpoint every this many iterations (0 = only at the end and on Ctrl-C).
    pub checkpoint_interval: u32,
    /// Log the Gaussians and an evaluation render to rerun every this many iterations
    /// (scalars are logged every 10); only when a rerun target is given.
    pub viz_interval: u32,
    pub lr: LrConfig,
    pub density: DensityConfig,
    pub init: InitConfig,
}

impl StaticConfig {
    /// The official AiM code's stage I.
    pub fn paper() -> Self {
        Self {
            preset: "paper".into(),
            iterations: 20_000,
            resolution: 0,
            seed: 0,
            sh_degree: 0,
            sh_increase_interval: 1000,
            lambda_dssim: 0.2,
            depth_weight: 0.0,
            random_background: true,
            eval_background: [1.0, 1.0, 1.0],
            checkpoint_interval: 2000,
            viz_interval: 500,
            lr: LrConfig {
                means_init: 1.6e-4,
                means_final: 1.6e-6,
                means_delay_mult: 0.01,
                sh_dc: 0.0025,
                sh_rest: 0.0025 / 20.0,
                opacity: 0.05,
                scale: 0.005,
                rotation: 0.001,
            },
            density: DensityConfig {
                from_iter: 500,
                until_iter: 20_000,
                interval: 100,
                grad_threshold: 3e-4,
                percent_dense: 0.01,
                opacity_reset_interval: 3000,
                min_opacity: 0.005,
                max_screen_size: 20.0,
                max_world_size: 0.1,
                max_gaussians: 0,
            },
            init: InitConfig { points: 100_000, box_min: [-0.5; 3], box_max: [0.5; 3], opacity: 0.1 },
        }
    }

    /// This schedule ending at `fraction` of its iterations: the densification
    /// window and the opacity resets end and recur proportionally sooner (the
    /// learning rates already decay over `iterations`); the warm-up before the
    /// first densification and the densification and SH intervals are rates and
    /// stay.
    pub fn compressed(&self, fraction: f64) -> Self {
        // 0 (never) stays 0; anything else stays at least 1.
        let scale = |n: u32| if n == 0 { 0 } else { ((f64::from(n) * fraction).round() as u32).max(1) };
        let mut c = self.clone();
        c.iterations = scale(self.iterations);
        c.density.until_iter = scale(self.density.until_iter);
        c.density.opacity_reset_interval = scale(self.density.opacity_reset_interval);
        c
    }

    /// Practical on two CPU cores (see docs/training.md for the measurements behind it).
    pub fn cpu() -> Self {
        let mut c = Self::paper();
        c.preset = "cpu".into();
        c.iterations = 3000;
        c.resolution = 256;
        c.checkpoint_interval = 500;
        c.viz_interval = 250;
        c.density.from_iter = 300;
        c.density.until_iter = 2400;
        c.density.interval = 100;
        c.density.grad_threshold = 2e-4;
        c.density.opacity_reset_interval = 1500;
        c.density.max_gaussians = 60_000;
        c.lr.means_init = 4e-4;
        c.init.points = 10_000;
        c
    }
}

impl StageConfig for StaticConfig {
    fn presets() -> [Preset<Self>; 2] {
        [("paper", Self::paper), ("cpu", Self::cpu)]
    }

    fn run_settings(&mut self) -> (&mut u64, &mut u32) {
        (&mut self.seed, &mut self.iterations)
    }

    fn validate(&self) -> std::result::Result<(), String> {
        let positive = [
            ("lr.means_init", self.lr.means_init),
            ("lr.sh_dc", self.lr.sh_dc),
            ("lr.opacity", self.lr.opacity),
            ("lr.scale", self.lr.scale),
            ("lr.rotation", self.lr.rotation),
            ("density.grad_threshold", self.density.grad_threshold),
            ("density.percent_dense", self.density.percent_dense),
        ];
        for (k, v) in positive {
            if !(v.is_finite() && v > 0.0) {
                return Err(format!("{k} must be a positive number, got {v}"));
            }
        }
        for (k, v) in [("lr.means_final", self.lr.means_final), ("lr.sh_rest", self.lr.sh_rest)] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(format!("{k} must be >= 0, got {v}"));
            }
        }
        if self.iterations == 0 {
            return Err("iterations must be at least 1".into());
        }
        if self.sh_degree > 3 {
            return Err(format!("sh_degree must be 0..=3, got {}", self.sh_degree));
        }
        if !(self.depth_weight.is_finite() && self.depth_weight >= 0.0) {
            return Err(format!("depth_weight must be >= 0, got {}", self.depth_weight));
        }
        if !(0.0..=1.0).contains(&self.lambda_dssim) {
            return Err(format!("lambda_dssim must be in [0, 1], got {}", self.lambda_dssim));
        }
        if !(self.init.opacity > 0.0 && self.init.opacity < 1.0) {
            return Err(format!("init.opacity must be in (0, 1), got {}", self.init.opacity));
        }
        if !(0.0..1.0).contains(&self.density.min_opacity) {
            return Err(format!("density.min_opacity must be in [0, 1), got {}", self.density.min_opacity));
        }
        if self.density.interval == 0 {
            return Err("density.interval must be at least 1".into());
        }
        if self.init.points == 0 {
            return Err("init.points must be at least 1".into());
        }
        for i in 0..3 {
            if self.init.box_min[i].partial_cmp(&self.init.box_max[i]) != Some(std::cmp::Ordering::Less) {
                return Err(format!("init.box_min[{i}] must be below init.box_max[{i}]"));
            }
        }
        if self.eval_background.iter().any(|c| !(0.0..=1.0).contains(c)) {
            return Err("eval_background components must be in [0, 1]".into());
        }
        Ok(())
    }
}

/// A named preset and its constructor.
pub type Preset<T> = (&'static str, fn() -> T);

/// What the stage configurations share: named presets (paper, cpu), TOML over a
/// preset, range checks, and the run settings a command line may override.
pub trait StageConfig: Serialize + serde::de::DeserializeOwned {
    /// The named presets.
    fn presets() -> [Preset<Self>; 2];

    /// The seed and the iteration count.
    fn run_settings(&mut self) -> (&mut u64, &mut u32);

    /// Range checks, naming the key.
    fn validate(&self) -> std::result::Result<(), String>;

    fn preset(name: &str) -> Result<Self> {
        let presets = Self::presets();
        match presets.iter().find(|(n, _)| *n == name) {
            Some((_, make)) => Ok(make()),
            None => {
                let valid: Vec<&str> = presets.iter().map(|(n, _)| *n).collect();
                Err(Error::Config(format!("unknown preset '{name}' (valid: {})", valid.join(", "))))
            }
        }
    }

    /// Parse TOML over a preset: the file names its `preset` (default cpu) and
    /// overrides any key; unknown keys are rejected with their name, and values
    /// out of range with their key.
    fn from_toml(text: &str, path: &std::path::Path) -> Result<Self> {
        let value: toml::Value = toml::from_str(text).map_err(|e| Error::bad_file(path, e.to_string()))?;
        let name = value.get("preset").and_then(|v| v.as_str()).unwrap_or("cpu");
        let mut base = toml::Value::try_from(Self::preset(name)?).map_err(|e| Error::Other(e.to_string()))?;
        merge(&mut base, value);
        let cfg: Self = base.try_into().map_err(|e: toml::de::Error| Error::bad_file(path, e.to_string()))?;
        cfg.validate().map_err(|e| Error::bad_file(path, e))?;
        Ok(cfg)
    }

    /// A command line's configuration: `file` (TOML over a preset) or else the
    /// preset named, then the seed and iteration overrides, checked again.
    fn resolve(
        file: Option<&std::path::Path>,
        preset: &str,
        seed: Option<u64>,
        iterations: Option<u32>,
    ) -> Result<Self> {
        let mut cfg = match file {
            Some(p) => Self::from_toml(&std::fs::read_to_string(p).map_err(|e| Error::io(p, e))?, p)?,
            None => Self::preset(preset)?,
        };
        let (s, n) = cfg.run_settings();
        *s = seed.unwrap_or(*s);
        *n = iterations.unwrap_or(*n);
        cfg.validate().map_err(Error::Config)?;
        Ok(cfg)
    }
}

/// Overlay `over` onto `base` table by table (keys absent from `base` stay, so
/// deserialisation can name them as unknown).
fn merge(base: &mut toml::Value, over: toml::Value) {
    match (base, over) {
        (toml::Value::Table(b), toml::Value::Table(o)) => {
            for (k, v) in o {
                match b.get_mut(&k) {
                    Some(slot) => merge(slot, v),
                    None => {
                        b.insert(k, v);
                    }
                }
            }
        }
        (slot, v) => *slot = v,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;

    #[test]
    fn toml_overrides_a_preset() {
        let c = StaticConfig::from_toml(
            "preset = \"paper\"\niterations = 7\n[density]\nmin_opacity = 0.01\n",
            Path::new("x.toml"),
        )
        .expect("valid");
        assert_eq!(c.iterations, 7);
        assert_eq!(c.density.min_opacity, 0.01);
        assert_eq!(c.density.interval, 100);
        assert_eq!(c.preset, "paper");
    }

    #[test]
    fn unknown_key_is_rejected_by_name() {
        let e =
            StaticConfig::from_toml("[density]\nmin_opacty = 0.01\n", Path::new("cfg.toml")).unwrap_err().to_string();
        assert!(e.contains("min_opacty") && e.contains("cfg.toml"), "{e}");
    }

    #[test]
    fn out_of_range_value_is_rejected_by_name() {
        let e = StaticConfig::from_toml("[lr]\nscale = -1.0\n", Path::new("cfg.toml")).unwrap_err().to_string();
        assert!(e.contains("lr.scale"), "{e}");
        let e = StaticConfig::from_toml("sh_degree = 4\n", Path::new("cfg.toml")).unwrap_err().to_string();
        assert!(e.contains("sh_degree"), "{e}");
    }

    #[test]
    fn a_compressed_schedule_ends_its_windows_proportionally_sooner() {
        let cpu = StaticConfig::cpu();
        let live = cpu.compressed(0.8);
        assert_eq!((live.iterations, live.density.until_iter, live.density.opacity_reset_interval), (2400, 1920, 1200));
        // Rates stay, and so does everything else.
        let rates = |c: &StaticConfig| (c.density.from_iter, c.density.interval, c.sh_increase_interval, c.lr.clone());
        assert_eq!(rates(&live), rates(&cpu));
        assert!(live.validate().is_ok());
        let mut never_reset = cpu.clone();
        never_reset.density.opacity_reset_interval = 0;
        assert_eq!(never_reset.compressed(0.5).density.opacity_reset_interval, 0, "no reset stays no reset");
    }

    #[test]
    fn presets_round_trip_through_toml() {
        for p in [StaticConfig::paper(), StaticConfig::cpu()] {
            let text = toml::to_string(&p).expect("serialises");
            assert_eq!(StaticConfig::from_toml(&text, Path::new("p.toml")).expect("parses"), p);
        }
    }
}
