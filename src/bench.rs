//! Benchmarks behind `aim bench ...`: seeded scenes, repeated timings, JSON-ready reports.

use std::time::Instant;

use glam::{Quat, Vec3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::Serialize;

use crate::camera::{Camera, Intrinsics};
use crate::render::lanes::Kernels;
use crate::render::{render, Backend, RenderOptions};
use crate::splat::{logit, GaussianSet};

/// A seeded random scene that covers the view of [`bench_camera`]: Gaussians
/// spread through the frustum at depth 2..4, projected standard deviations of
/// about 0.5..3 px at 256 px, mixed opacities, random rotations, SH degree 3.
pub fn random_scene(n: usize, seed: u64) -> GaussianSet {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut gs = GaussianSet::new(3);
    let tan_half = (bench_fov() * 0.5).tan();
    let focal_256 = 128.0 / tan_half;
    let rest_w = gs.width(crate::splat::ParamGroup::ShRest);
    for _ in 0..n {
        let z: f32 = rng.random_range(2.0..4.0);
        let x = rng.random_range(-1.0..1.0) * tan_half * z;
        let y = rng.random_range(-1.0..1.0) * tan_half * z;
        let sigma_px: f32 = (rng.random_range(0.5f32.ln()..3.0f32.ln())).exp();
        let base = sigma_px * z / focal_256;
        let log_scale = Vec3::new(
            (base * rng.random_range(0.5..2.0)).ln(),
            (base * rng.random_range(0.5..2.0)).ln(),
            (base * rng.random_range(0.5..2.0)).ln(),
        );
        let q = Quat::from_xyzw(
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
        )
        .normalize();
        let dc = [rng.random_range(-1.5..1.5), rng.random_range(-1.5..1.5), rng.random_range(-1.5..1.5)];
        let rest: Vec<f32> = (0..rest_w).map(|_| rng.random_range(-0.1..0.1)).collect();
        gs.push(Vec3::new(x, y, z), log_scale, [q.w, q.x, q.y, q.z], logit(rng.random_range(0.1..0.9)), dc, &rest);
    }
    gs
}

fn bench_fov() -> f32 {
    60f32.to_radians()
}

/// Camera at the origin looking down +z (OpenCV), 60 degree horizontal field of view.
pub fn bench_camera(size: u32) -> Camera {
    Camera::new(Intrinsics::from_fov_x(size, size, bench_fov()), glam::Mat4::IDENTITY)
}

#[derive(Debug, Serialize)]
pub struct RenderBenchRow {
    /// The backend timed (`Backend::describe`).
    pub backend: String,
    pub resolution: u32,
    pub gaussians: usize,
    pub visible: usize,
    pub tile_entries: usize,
    pub forward_ms: f64,
    pub forward_backward_ms: f64,
    /// Gaussian-pixel alpha evaluations in one forward pass.
    pub gaussian_pixel_evals: u64,
    /// Evaluations per second, forward pass.
    pub forward_evals_per_s: f64,
    /// Median time of each stage (project, bin, composite, composite backward,
    /// project backward); CPU backend only.
    pub stages_ms: Option<StageTimes>,
}

#[derive(Debug, Default, Serialize)]
pub struct StageTimes {
    pub project: f64,
    pub bin: f64,
    pub composite: f64,
    pub composite_backward: f64,
    pub project_backward: f64,
}

/// Time each rasterizer stage separately (median of `repeats`).
fn stage_times(gs: &GaussianSet, cam: &Camera, opts: &RenderOptions, grad: &[f32], repeats: usize) -> StageTimes {
    use crate::render::project::{project_backward_all, project_one, ProjectionCamera};
    use crate::render::raster::{bin_tiles, rasterize, rasterize_backward, Background};
    use rayon::prelude::*;
    let pc = ProjectionCamera::new(cam);
    let (w, h) = (cam.width(), cam.height());
    let mut t = [Vec::new(), Vec::new(), Vec::new(), Vec::new(), Vec::new()];
    for _ in 0..repeats {
        let clock = Instant::now();
        let proj: Vec<_> = (0..gs.len()).into_par_iter().map(|i| project_one(gs, i, &pc, gs.sh_degree)).collect();
        t[0].push(clock.elapsed().as_secs_f64() * 1e3);
        let clock = Instant::now();
        let bins = bin_tiles(&proj, w, h);
        t[1].push(clock.elapsed().as_secs_f64() * 1e3);
        let clock = Instant::now();
        let out = rasterize(&bins, w, h, Background::Uniform(opts.background));
        t[2].push(clock.elapsed().as_secs_f64() * 1e3);
        let clock = Instant::now();
        let (pg, _) = rasterize_backward(&bins, w, h, Background::Uniform(opts.background), &out, grad, None, None);
        t[3].push(clock.elapsed().as_secs_f64() * 1e3);
        let clock = Instant::now();
        let raw = project_backward_all(gs, &proj, &pc, gs.sh_degree, &pg, None);
        t[4].push(clock.elapsed().as_secs_f64() * 1e3);
        std::hint::black_box(raw);
    }
    let [a, b, c, d, e] = t.map(median);
    StageTimes { project: a, bin: b, composite: c, composite_backward: d, project_backward: e }
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Time forward and forward+backward (median of `repeats`) for each size and count.
pub fn render_bench(backend: &Backend, sizes: &[u32], counts: &[usize], repeats: usize) -> Vec<RenderBenchRow> {
    let mut rows = Vec::new();
    for &n in counts {
        let gs = random_scene(n, 7);
        for &size in sizes {
            rows.push(time_render(backend, &gs, &bench_camera(size), repeats));
        }
    }
    rows
}

/// Time forward and forward+backward of one scene from one camera on
/// `backend` (medians). The work measures (visible Gaussians, tile entries,
/// evaluations) are the scene's, counted by the CPU backend's binning.
pub fn time_render(backend: &Backend, gs: &GaussianSet, cam: &Camera, repeats: usize) -> RenderBenchRow {
    let opts = RenderOptions::uniform(Vec3::splat(0.2));
    let warm = render(gs, cam, &opts);
    let grad: Vec<f32> = (0..warm.image.color.len()).map(|i| ((i % 7) as f32 - 3.0) * 1e-3).collect();
    // The first render on a GPU also pays for buffer and pipeline warm-up.
    std::hint::black_box(backend.render(gs, cam, &opts));
    let mut fwd = Vec::new();
    let mut both = Vec::new();
    for _ in 0..repeats {
        let t = Instant::now();
        let r = backend.render(gs, cam, &opts);
        fwd.push(t.elapsed().as_secs_f64() * 1e3);
        let t = Instant::now();
        let r2 = backend.render(gs, cam, &opts);
        let g = backend.backward(gs, &r2, &grad, None, None, None);
        both.push(t.elapsed().as_secs_f64() * 1e3);
        std::hint::black_box((r, g));
    }
    let forward_ms = median(fwd);
    let (w, h) = (cam.width(), cam.height());
    let evals = crate::render::raster::pixel_evaluations(&warm.bins, w, h);
    RenderBenchRow {
        backend: backend.describe(),
        resolution: w.max(h),
        gaussians: gs.len(),
        visible: warm.visible_count(),
        tile_entries: warm.bins.entries.len(),
        forward_ms,
        forward_backward_ms: median(both),
        gaussian_pixel_evals: evals,
        forward_evals_per_s: evals as f64 / (forward_ms * 1e-3),
        stages_ms: matches!(backend, Backend::Cpu).then(|| stage_times(gs, cam, &opts, &grad, repeats)),
    }
}

#[derive(Debug, Serialize)]
pub struct DeformBenchRow {
    pub depth: usize,
    pub width: usize,
    pub points: usize,
    pub forward_ms: f64,
    pub forward_backward_ms: f64,
    /// Multiply-adds x 2 of forward + backward (3 GEMMs per layer) per second.
    pub gflops: f64,
}

/// Time the deformation network's forward and forward+backward (median of `repeats`).
pub fn deform_bench(shapes: &[(usize, usize)], counts: &[usize], repeats: usize) -> Vec<DeformBenchRow> {
    use crate::deform::{DeformConfig, DeformNet};
    let mut rows = Vec::new();
    for &(depth, width) in shapes {
        let net = DeformNet::new(DeformConfig { depth, width, ..Default::default() }, 1);
        for &n in counts {
            let mut rng = ChaCha8Rng::seed_from_u64(2);
            let pts: Vec<f32> = (0..3 * n).map(|_| rng.random_range(-0.5..0.5)).collect();
            let gx: Vec<f32> = (0..3 * n).map(|_| rng.random_range(-1.0..1.0)).collect();
            let gr: Vec<f32> = (0..4 * n).map(|_| rng.random_range(-1.0..1.0)).collect();
            let (mut f, mut fb) = (Vec::new(), Vec::new());
            for _ in 0..repeats {
                let t = Instant::now();
                let out = net.forward(&pts, 0.3);
                f.push(t.elapsed().as_secs_f64() * 1e3);
                let t = Instant::now();
                let out2 = net.forward(&pts, 0.3);
                let g = net.backward(&out2.cache, &gx, &gr);
                fb.push(t.elapsed().as_secs_f64() * 1e3);
                std::hint::black_box((out, g));
            }
            let forward_backward_ms = median(fb);
            // Forward 1 GEMM, backward 2 GEMMs per weight matrix.
            let flops = 2.0 * 3.0 * n as f64 * net.parameter_count() as f64;
            rows.push(DeformBenchRow {
                depth,
                width,
                points: n,
                forward_ms: median(f),
                forward_backward_ms,
                gflops: flops / (forward_backward_ms * 1e-3) / 1e9,
            });
        }
    }
    rows
}

/// What a benchmark ran on: numbers from different machines only compare with
/// these beside them (the rasterizer's speed differs between machines more than
/// their raw compute does, docs/benchmark.md).
#[derive(Debug, Serialize)]
pub struct MachineInfo {
    /// /proc/cpuinfo's model name, where there is one.
    pub cpu: Option<String>,
    /// SIMD features the CPU reports at run time.
    pub cpu_features: Vec<&'static str>,
    /// SIMD features the whole binary was compiled to assume (its baseline,
    /// `-C target-cpu` / `target-feature`).
    pub compiled_features: Vec<&'static str>,
    /// The rasterizer's kernel set, chosen at run time from the CPU's features
    /// (`render::lanes::Kernels`): avx512, avx2 or portable.
    pub kernel_set: &'static str,
    /// How that kernel set executes its 8 lanes.
    pub kernel_description: &'static str,
    pub threads: usize,
}

impl MachineInfo {
    pub fn detect() -> Self {
        let cpu = std::fs::read_to_string("/proc/cpuinfo").ok().and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split(':').nth(1))
                .map(|m| m.trim().to_string())
        });
        let kernels = Kernels::active();
        Self {
            cpu,
            cpu_features: runtime_features(),
            compiled_features: compiled_features(),
            kernel_set: kernels.name(),
            kernel_description: kernels.description(),
            threads: rayon::current_num_threads(),
        }
    }
}

#[cfg(target_arch = "x86_64")]
fn runtime_features() -> Vec<&'static str> {
    let mut f = Vec::new();
    macro_rules! check {
        ($($name:tt),*) => { $( if std::arch::is_x86_feature_detected!($name) { f.push($name); } )* };
    }
    check!("sse4.2", "avx", "avx2", "fma", "avx512f", "avx512bw", "avx512vl");
    f
}

#[cfg(target_arch = "aarch64")]
fn runtime_features() -> Vec<&'static str> {
    if std::arch::is_aarch64_feature_detected!("neon") {
        vec!["neon"]
    } else {
        Vec::new()
    }
}

#[cfg(not(any(target_arch = "x86_64", target_arch = "aarch64")))]
fn runtime_features() -> Vec<&'static str> {
    Vec::new()
}

fn compiled_features() -> Vec<&'static str> {
    [
        ("sse4.2", cfg!(target_feature = "sse4.2")),
        ("avx", cfg!(target_feature = "avx")),
        ("avx2", cfg!(target_feature = "avx2")),
        ("fma", cfg!(target_feature = "fma")),
        ("avx512f", cfg!(target_feature = "avx512f")),
        ("neon", cfg!(target_feature = "neon")),
    ]
    .into_iter()
    .filter_map(|(name, on)| on.then_some(name))
    .collect()
}

#[cfg(test)]
mod machine_tests {
    use super::MachineInfo;

    #[test]
    fn the_binary_uses_only_features_the_cpu_has() {
        let m = MachineInfo::detect();
        assert!(m.threads >= 1);
        for f in &m.compiled_features {
            assert!(m.cpu_features.contains(f), "compiled for {f}, which the CPU does not report: {m:?}");
        }
        let json = serde_json::to_value(&m).expect("serialises");
        assert!(json["kernel_description"].as_str().is_some_and(|k| k.contains("8 lanes")), "{json}");
        let set = json["kernel_set"].as_str().expect("a kernel set name");
        assert!(crate::render::lanes::Kernels::named(set).is_ok(), "{json}");
    }
}
