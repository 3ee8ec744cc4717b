//! The GPU backend against the CPU backend on seeded scenes: images to 1e-4,
//! gradients to 1e-3 of each parameter group's largest, from 10 to 100k
//! Gaussians, with the edge cases (behind the camera, huge, tiny, many per
//! tile, empty tiles, image sizes that are no multiple of the tile); a scene too
//! large for the device runs on the CPU backend.
//!
//! Without a GPU adapter (a Vulkan driver; lavapipe counts) these tests skip
//! with a message, unless AIM_REQUIRE_GPU=1 (set by tests/run, which installs
//! lavapipe), where a missing adapter fails them.

use std::sync::{Arc, OnceLock};

use aim::bench::{bench_camera, random_scene};
use aim::camera::{Camera, Intrinsics};
use aim::render::gpu::{AdapterKind, GpuContext};
use aim::render::{backward_sets, render_sets, Backend, Gradients, RenderOptions, View};
use aim::splat::{logit, GaussianSet, ParamGroup};
use glam::{Mat4, Vec3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn gpu() -> Option<Arc<GpuContext>> {
    static CONTEXT: OnceLock<Option<Arc<GpuContext>>> = OnceLock::new();
    CONTEXT
        .get_or_init(|| match GpuContext::new(AdapterKind::Any) {
            Ok(ctx) => {
                eprintln!("GPU parity tests on {}", ctx.describe());
                Some(Arc::new(ctx))
            }
            Err(e) if std::env::var("AIM_REQUIRE_GPU").is_ok_and(|v| v == "1") => {
                panic!("AIM_REQUIRE_GPU=1 but {e}")
            }
            Err(e) => {
                eprintln!("skipping the GPU parity tests: {e}");
                None
            }
        })
        .clone()
}

fn max_abs_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0, f32::max)
}

/// Images agree to 1e-4, except that a contribution whose alpha lies within
/// float rounding of the 1/255 threshold may be kept by one backend and skipped
/// by the other (their exp, sigmoid and pixel offsets round differently): such a
/// flip moves a pixel by at most about 1/255 of a colour. At most one value in
/// 10,000 may differ by more than 1e-4, and none by more than 0.01.
fn assert_images_match(what: &str, name: &str, a: &[f32], b: &[f32]) {
    assert_eq!(a.len(), b.len());
    let off: Vec<f32> = a.iter().zip(b).map(|(x, y)| (x - y).abs()).filter(|d| *d > 1e-4).collect();
    let worst = off.iter().fold(0.0f32, |m, d| m.max(*d));
    assert!(
        off.len() * 10_000 <= a.len() && worst <= 0.01,
        "{what}: {name}: {} of {} values differ by more than 1e-4, the most by {worst}",
        off.len(),
        a.len()
    );
}

/// Seeded per-pixel loss gradients for colour, alpha and depth.
fn pixel_gradients(pixels: usize, seed: u64) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut draw = |n: usize| -> Vec<f32> { (0..n).map(|_| rng.random_range(-1.0..1.0)).collect() };
    (draw(3 * pixels), draw(pixels), draw(pixels))
}

/// Render and differentiate `gs` on both backends and compare.
fn assert_parity(gs: &GaussianSet, camera: &Camera, options: &RenderOptions, region: Option<[u32; 4]>) {
    assert_sets_parity(&[gs], camera, options, region.unwrap_or([0, 0, camera.width(), camera.height()]));
}

/// Render several sets as one scene and differentiate them on both backends and compare.
fn assert_sets_parity(sets: &[&GaussianSet], camera: &Camera, options: &RenderOptions, region: [u32; 4]) {
    let Some(ctx) = gpu() else { return };
    let cpu = render_sets(sets, camera, region, options);
    let gpu = ctx.render_sets(sets, camera, region, options).expect("the scene fits the device");
    assert_eq!((gpu.width, gpu.height), (cpu.width, cpu.height));
    let n: usize = sets.iter().map(|s| s.len()).sum();
    let what = format!("{n} Gaussians in {} sets, {}x{}", sets.len(), cpu.width, cpu.height);
    for (name, a, b) in [
        ("colour", &gpu.image.color, &cpu.image.color),
        ("alpha", &gpu.image.alpha, &cpu.image.alpha),
        ("final transmittance", &gpu.image.final_t, &cpu.image.final_t),
    ] {
        assert_images_match(&what, name, a, b);
    }
    let depth_scale = cpu.image.depth.iter().fold(1.0f32, |m, v| m.max(v.abs()));
    let d = max_abs_diff(&gpu.image.depth, &cpu.image.depth);
    assert!(d <= 1e-4 * depth_scale, "{what}: accumulated depth differs by {d} (largest {depth_scale})");

    let (gc, ga, gd) = pixel_gradients((cpu.width * cpu.height) as usize, 7);
    let cpu_sets = backward_sets(sets, &cpu, &gc, Some(&ga), Some(&gd));
    let gpu_sets = ctx.backward_sets(sets, &gpu, &gc, Some(&ga), Some(&gd));
    assert_eq!(gpu_sets.len(), sets.len());
    for (cpu_grads, gpu_grads) in cpu_sets.iter().zip(&gpu_sets) {
        assert_gradients_match(&what, cpu_grads, gpu_grads);
    }
}

fn assert_gradients_match(what: &str, cpu_grads: &Gradients, gpu_grads: &Gradients) {
    for group in ParamGroup::ALL {
        let (a, b) = (gpu_grads.params.group(group), cpu_grads.params.group(group));
        let scale = b.iter().fold(0.0f32, |m, v| m.max(v.abs()));
        let d = max_abs_diff(a, b);
        assert!(d <= 1e-3 * scale + 1e-7, "{what}: {group:?} gradients differ by {d} (largest {scale})");
    }
    let bg = (gpu_grads.background - cpu_grads.background).abs().max_element();
    assert!(
        bg <= 1e-3 * cpu_grads.background.abs().max_element().max(1.0),
        "{what}: background gradient differs by {bg}"
    );
    assert_eq!(gpu_grads.visible, cpu_grads.visible, "{what}: visibility");
    let scale = cpu_grads.mean2d_grad_norm.iter().fold(0.0f32, |m, v| m.max(*v));
    let d = max_abs_diff(&gpu_grads.mean2d_grad_norm, &cpu_grads.mean2d_grad_norm);
    assert!(d <= 1e-3 * scale + 1e-7, "{what}: mean2d gradient norms differ by {d} (largest {scale})");
    let d = max_abs_diff(&gpu_grads.radius, &cpu_grads.radius);
    assert!(d <= 1e-3, "{what}: screen radii differ by {d} px");
}

#[test]
fn random_scenes_from_ten_to_a_hundred_thousand_gaussians_match_the_cpu_backend() {
    for (n, size, seed) in [(10, 64, 1), (1_000, 128, 2), (10_000, 256, 3), (100_000, 256, 4)] {
        let gs = random_scene(n, seed);
        assert_parity(&gs, &bench_camera(size), &RenderOptions::uniform(Vec3::new(0.1, 0.2, 0.3)), None);
    }
}

#[test]
fn sets_rendered_together_match() {
    let (a, b) = (random_scene(3_000, 8), random_scene(500, 9));
    let camera = bench_camera(128);
    assert_sets_parity(&[&a, &b], &camera, &RenderOptions::uniform(Vec3::splat(0.3)), [0, 0, 128, 128]);
    assert_sets_parity(&[&b, &a, &b], &camera, &RenderOptions::uniform(Vec3::ZERO), [20, 30, 100, 90]);
}

#[test]
fn image_sizes_that_are_no_multiple_of_the_tile_and_regions_match() {
    let gs = random_scene(3_000, 5);
    let k = Intrinsics::from_fov_x(203, 117, 60f32.to_radians());
    let camera = Camera::new(k, Mat4::IDENTITY);
    let options = RenderOptions::uniform(Vec3::ZERO);
    assert_parity(&gs, &camera, &options, None);
    assert_parity(&gs, &camera, &options, Some([37, 11, 150, 100]));
}

#[test]
fn a_background_image_and_low_sh_degrees_match() {
    let gs = random_scene(2_000, 6);
    let camera = bench_camera(96);
    let pixels: Vec<f32> = (0..96 * 96 * 3).map(|i| (i % 7) as f32 / 7.0).collect();
    for degree in [0, 1, 2] {
        let options = RenderOptions {
            background: Vec3::ZERO,
            sh_degree: Some(degree),
            background_image: Some(Arc::from(pixels.clone())),
        };
        assert_parity(&gs, &camera, &options, None);
    }
}

/// Gaussians behind the camera, straddling the near plane, off the image,
/// huge (covering every tile), tiny (under a pixel), a deep stack in one tile
/// (many per tile, early termination) and nothing in most tiles.
#[test]
fn edge_cases_match() {
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let mut gs = GaussianSet::new(1);
    let rest = |rng: &mut ChaCha8Rng| -> Vec<f32> { (0..9).map(|_| rng.random_range(-0.2..0.2)).collect() };
    // Anisotropic, so that the rotation gradients are not rounding noise.
    let push = |gs: &mut GaussianSet, rng: &mut ChaCha8Rng, mean: Vec3, log_scale: f32, opacity: f32| {
        let r = rest(rng);
        let log_scale = Vec3::new(log_scale, log_scale - 0.7, log_scale + 0.4);
        let q = [rng.random_range(0.5..1.0), rng.random_range(-0.5..0.5), rng.random_range(-0.5..0.5), 0.1];
        let dc = [rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0)];
        gs.push(mean, log_scale, q, logit(opacity), dc, &r);
    };
    push(&mut gs, &mut rng, Vec3::new(0.0, 0.0, -1.0), -2.0, 0.9); // behind
    push(&mut gs, &mut rng, Vec3::new(0.0, 0.0, 0.005), -3.0, 0.9); // before the near plane
    push(&mut gs, &mut rng, Vec3::new(50.0, 0.0, 2.0), -2.0, 0.9); // off the image
    push(&mut gs, &mut rng, Vec3::new(0.1, -0.1, 3.0), 1.0, 0.3); // huge
    push(&mut gs, &mut rng, Vec3::new(0.3, 0.2, 2.5), -9.0, 0.9); // tiny
    push(&mut gs, &mut rng, Vec3::new(-0.2, 0.3, 2.0), -2.5, 0.002); // too transparent
    for k in 0..400 {
        // A deep stack around one point: hundreds per tile, pixels terminate early.
        let jitter = Vec3::new(rng.random_range(-0.02..0.02), rng.random_range(-0.02..0.02), 0.0);
        push(&mut gs, &mut rng, Vec3::new(-0.5, -0.5, 1.5 + 0.002 * k as f32) + jitter, -3.5, 0.6);
    }
    assert_parity(&gs, &bench_camera(160), &RenderOptions::uniform(Vec3::new(0.5, 0.5, 0.5)), None);
    // Nothing visible at all.
    let mut hidden = GaussianSet::new(0);
    hidden.push(Vec3::new(0.0, 0.0, -2.0), Vec3::splat(-2.0), [1.0, 0.0, 0.0, 0.0], logit(0.5), [0.2; 3], &[]);
    assert_parity(&hidden, &bench_camera(48), &RenderOptions::uniform(Vec3::ONE), None);
}

/// A scene whose buffers exceed the device's largest (here an image whose
/// per-pixel state needs more than lavapipe's 128 MiB) is refused by the GPU
/// context, naming the buffer, and the GPU backend renders it and its backward
/// pass on the CPU instead: the CPU backend's image and gradients, no panic.
#[test]
fn a_scene_too_large_for_the_device_runs_on_the_cpu_backend() {
    let Some(ctx) = gpu() else { return };
    // A square image of more pixels than the largest buffer holds 16-byte states.
    let side = ((ctx.largest_buffer() / 16) as f64).sqrt().ceil() as u32 + 16;
    if side > 4096 {
        eprintln!("skipping: {} holds the state of a {side}x{side} image", ctx.describe());
        return;
    }
    let gs = random_scene(100, 12);
    let camera = bench_camera(side);
    let options = RenderOptions::uniform(Vec3::splat(0.2));
    let err = ctx.render_sets(&[&gs], &camera, [0, 0, side, side], &options).err().expect("too large");
    assert!(err.to_string().contains("per-pixel state"), "{err}");
    let backend = Backend::Gpu(ctx);
    let view = backend.render(&gs, &camera, &options);
    assert!(matches!(view, View::Cpu(_)), "rendered by the CPU backend");
    let cpu = aim::render::render(&gs, &camera, &options);
    assert!(view.image().color == cpu.image.color, "the CPU backend's image");
    let (gc, ga, _) = pixel_gradients((side * side) as usize, 13);
    let grads = backend.backward(&gs, &view, &gc, Some(&ga), None, None);
    let cpu_grads = aim::render::backward(&gs, &cpu, &gc, Some(&ga), None);
    for group in ParamGroup::ALL {
        assert!(grads.params.group(group) == cpu_grads.params.group(group), "{group:?} gradients");
    }
}

/// Stage I and a short stage II (node tracking's fitting steps) trained through
/// the CLI with `--backend gpu` track the same runs with `--backend cpu`: test
/// PSNR within 0.5 dB after the same iterations.
#[test]
fn training_on_the_gpu_backend_tracks_the_cpu_backend() {
    use std::process::Command;

    use aim::synth::dataset::{write_dataset, SynthConfig};
    if gpu().is_none() {
        return;
    }
    let root = std::env::temp_dir().join(format!("aim-test-{}-gpu-training", std::process::id()));
    let _ = std::fs::remove_dir_all(&root);
    let data = root.join("data");
    let cfg = SynthConfig {
        resolution: 32,
        scan_views: 12,
        motion_frames: 12,
        end_views: 1,
        test_views: 2,
        motion_test_every: 6,
        samples_per_pixel: 1,
        ..Default::default()
    };
    write_dataset(&aim::synth::object("storage").expect("object"), &data, &cfg, &|_, _| {}).expect("written");
    let aim = || {
        // AIM_BIN: the binary beside a test binary carried to another machine (tests/gpu_check).
        let mut c = Command::new(std::env::var("AIM_BIN").unwrap_or_else(|_| env!("CARGO_BIN_EXE_aim").into()));
        c.env("XDG_RUNTIME_DIR", std::env::var("XDG_RUNTIME_DIR").unwrap_or_else(|_| "/tmp".into()));
        c
    };
    let metric = |file: std::path::PathBuf, key: &str| -> f64 {
        let text = std::fs::read_to_string(&file).unwrap_or_else(|e| panic!("{}: {e}", file.display()));
        let json: serde_json::Value = serde_json::from_str(&text).expect("metrics.json parses");
        json[key].as_f64().unwrap_or_else(|| panic!("{}: no {key}", file.display()))
    };
    let mut stage_one = Vec::new();
    for backend in ["cpu", "gpu"] {
        let out = root.join(format!("static_{backend}"));
        let st = aim()
            .arg("train-static")
            .arg(&data)
            .arg("--out")
            .arg(&out)
            .args(["--iterations", "100", "--backend", backend])
            .output()
            .expect("runs");
        assert!(st.status.success(), "{}", String::from_utf8_lossy(&st.stderr));
        stage_one.push(metric(out.join("metrics.json"), "mean_psnr"));
    }
    eprintln!("stage I test PSNR: cpu {:.3} dB, gpu {:.3} dB", stage_one[0], stage_one[1]);
    assert!((stage_one[0] - stage_one[1]).abs() <= 0.5, "stage I test PSNR cpu {} gpu {}", stage_one[0], stage_one[1]);
    assert!(stage_one[0] > 15.0, "stage I learnt something: {} dB", stage_one[0]);
    // Stage II from the CPU's stage I on each backend, `extra` arguments added.
    let stage_two_psnr = |name: &str, backend: &str, extra: &[&std::ffi::OsStr]| -> f64 {
        let out = root.join(format!("{name}_{backend}"));
        let clock = std::time::Instant::now();
        let st = aim()
            .arg("train-dynamic")
            .arg(&data)
            .arg("--static")
            .arg(root.join("static_cpu").join("static.ply"))
            .arg("--out")
            .arg(&out)
            .args(extra)
            .args(["--backend", backend])
            .output()
            .expect("runs");
        assert!(st.status.success(), "{}", String::from_utf8_lossy(&st.stderr));
        eprintln!("{name} on {backend}: {:.1} s", clock.elapsed().as_secs_f64());
        metric(out.join("metrics.json"), "motion_test_psnr")
    };
    // A short end scan: it is stage I's trainer, whose parity is checked above, and
    // lavapipe runs the preset's 3000 iterations in many minutes.
    let tracking = root.join("tracking.toml");
    std::fs::write(&tracking, "preset = \"cpu\"\n[track]\nend_scan_iterations = 20\n").expect("config written");
    let tracking_args =
        [std::ffi::OsStr::new("--config"), tracking.as_os_str(), "--iterations".as_ref(), "60".as_ref()];
    let stage_two: Vec<f64> = ["cpu", "gpu"].iter().map(|b| stage_two_psnr("dynamic", b, &tracking_args)).collect();
    eprintln!("stage II motion PSNR: cpu {:.3} dB, gpu {:.3} dB", stage_two[0], stage_two[1]);
    assert!(
        (stage_two[0] - stage_two[1]).abs() <= 0.5,
        "stage II motion PSNR cpu {} gpu {}",
        stage_two[0],
        stage_two[1]
    );
    // The paper preset's dual field: the deformation network on the GPU as well.
    let paper = root.join("paper.toml");
    // A small network: lavapipe runs the paper's 8 x 256 at a few GFLOP/s.
    let toml = "preset = \"paper\"\nwarmup_iterations = 5\nstatic_opacity_only_iterations = 10\n\
                time_curriculum_iterations = 0\n[deform]\ndepth = 4\nwidth = 32\nxyz_frequencies = 4\n\
                time_frequencies = 3\n";
    std::fs::write(&paper, toml).expect("config written");
    let paper_args = [std::ffi::OsStr::new("--config"), paper.as_os_str(), "--iterations".as_ref(), "40".as_ref()];
    let dual_field: Vec<f64> = ["cpu", "gpu"].iter().map(|b| stage_two_psnr("paper", b, &paper_args)).collect();
    eprintln!("dual field motion PSNR: cpu {:.3} dB, gpu {:.3} dB", dual_field[0], dual_field[1]);
    // Looser than node tracking's: 40 steps of Adam on the network's near-zero
    // gradients turn rounding differences (the GPU sums in another order) into
    // different steps, so the two runs drift apart (12.60 against 12.12 dB when
    // measured); a broken network on either side lands far below.
    assert!(
        (dual_field[0] - dual_field[1]).abs() <= 1.5,
        "dual field motion PSNR cpu {} gpu {}",
        dual_field[0],
        dual_field[1]
    );
    let _ = std::fs::remove_dir_all(&root);
}

/// The deformation field's network on the GPU gives the CPU's offsets and
/// parameter gradients (every layer, both heads, with and without the output
/// scale), on a small network and on the paper's 8 x 256.
#[test]
fn the_deformation_network_matches_the_cpu() {
    use aim::deform::gpu::GpuDeformNet;
    use aim::deform::{DeformConfig, DeformNet};
    let Some(ctx) = gpu() else { return };
    let gpu_net = GpuDeformNet::new(ctx);
    let mut rng = ChaCha8Rng::seed_from_u64(21);
    let small = DeformConfig { depth: 4, width: 24, xyz_frequencies: 3, time_frequencies: 2, zero_at_start: false };
    for (config, points) in
        [(small.clone(), 1_000), (DeformConfig { zero_at_start: true, ..small }, 77), (DeformConfig::default(), 2_000)]
    {
        let mut net = DeformNet::new(config.clone(), 3);
        // The heads (the last 7 x width + 7 parameters) at full scale, so every
        // layer's gradient is well above rounding.
        let heads = net.params.len() - (7 * config.width + 7);
        net.params[heads..].iter_mut().for_each(|v| *v *= 1000.0);
        let means: Vec<f32> = (0..3 * points).map(|_| rng.random_range(-0.6..0.6)).collect();
        let (gx, gr): (Vec<f32>, Vec<f32>) = (
            (0..3 * points).map(|_| rng.random_range(-1.0..1.0)).collect(),
            (0..4 * points).map(|_| rng.random_range(-1.0..1.0)).collect(),
        );
        let cpu = net.forward(&means, 0.4);
        let (d_xyz, d_rot, cache) = gpu_net.forward(&net, &means, 0.4);
        let what = format!("{config:?}, {points} points");
        for (name, a, b) in [("position offsets", &d_xyz, &cpu.d_xyz), ("rotation offsets", &d_rot, &cpu.d_rot)] {
            let scale = b.iter().fold(0.0f32, |m, v| m.max(v.abs()));
            let d = max_abs_diff(a, b);
            assert!(scale > 0.0 && d <= 1e-4 * scale, "{what}: {name} differ by {d} (largest {scale})");
        }
        let cpu_grads = net.backward(&cpu.cache, &gx, &gr);
        let gpu_grads = gpu_net.backward(&net, &cache, &gx, &gr);
        for (name, range) in [("hidden layers", 0..heads), ("heads", heads..net.params.len())] {
            let (a, b) = (&gpu_grads[range.clone()], &cpu_grads[range]);
            let scale = b.iter().fold(0.0f32, |m, v| m.max(v.abs()));
            let d = max_abs_diff(a, b);
            assert!(scale > 0.0 && d <= 1e-3 * scale, "{what}: {name}' gradients differ by {d} (largest {scale})");
        }
    }
}
