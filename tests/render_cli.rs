//! `aim render`: a PLY and a camera file in, the same image the library renders
//! out; bad camera and PLY files fail with the file named and a non-zero exit.

use std::path::{Path, PathBuf};
use std::process::Command;

use aim::camera::{Camera, CameraFile};
use aim::render::{render, RenderOptions};

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("aim-render-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).expect("temp dir");
    d
}

fn aim_render(ply: &Path, camera: &Path, out: &Path, extra: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_aim"))
        .args(["--log", "error", "render"])
        .arg(ply)
        .arg("--camera")
        .arg(camera)
        .arg("--out")
        .arg(out)
        .args(extra)
        .output()
        .expect("aim runs")
}

fn write_camera(path: &Path, cam: &CameraFile) {
    std::fs::write(path, serde_json::to_string(cam).expect("json")).expect("write");
}

#[test]
fn render_command_writes_the_library_render() {
    let dir = tmp("ok");
    let gs = aim::bench::random_scene(3000, 11);
    let ply = dir.join("scene.ply");
    aim::splat::ply::write_ply(&ply, &gs).expect("written");
    let cam = aim::bench::bench_camera(64);
    let cam_path = dir.join("camera.json");
    write_camera(&cam_path, &CameraFile::from_camera(&cam));
    let out = dir.join("image.png");
    let o = aim_render(&ply, &cam_path, &out, &["--background", "0.2,0.4,0.6"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let img = image::open(&out).expect("png").into_rgb8();
    let expected = render(&gs, &cam, &RenderOptions::uniform(glam::Vec3::new(0.2, 0.4, 0.6)));
    assert_eq!(img, expected.to_rgb8());
    // The camera file round-trips through the loader.
    assert_eq!(Camera::load_json(&cam_path).expect("loads"), cam);
}

#[test]
fn bad_camera_and_ply_files_name_the_file() {
    let dir = tmp("bad");
    let gs = aim::bench::random_scene(100, 1);
    let ply = dir.join("scene.ply");
    aim::splat::ply::write_ply(&ply, &gs).expect("written");
    let good = CameraFile::from_camera(&aim::bench::bench_camera(32));
    let out = dir.join("image.png");

    let mut singular = good.clone();
    singular.world_to_camera[1] = [0.0, 0.0, 0.0, 0.0];
    let p = dir.join("singular.json");
    write_camera(&p, &singular);
    let o = aim_render(&ply, &p, &out, &[]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("singular.json") && err.contains("rigid"), "{err}");

    let mut empty = good.clone();
    empty.width = 0;
    let p = dir.join("empty.json");
    write_camera(&p, &empty);
    let o = aim_render(&ply, &p, &out, &[]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("empty.json") && err.contains("1 to 65535 px"), "{err}");

    let mut huge = good.clone();
    huge.height = 70_000;
    let p = dir.join("huge.json");
    write_camera(&p, &huge);
    let o = aim_render(&ply, &p, &out, &[]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("huge.json") && err.contains("x70000"), "{err}");

    let cam = dir.join("camera.json");
    write_camera(&cam, &good);
    let bytes = std::fs::read(&ply).expect("read");
    let truncated = dir.join("truncated.ply");
    std::fs::write(&truncated, &bytes[..bytes.len() - 10]).expect("write");
    let o = aim_render(&truncated, &cam, &out, &[]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("truncated.ply"), "{err}");
    assert!(!out.exists(), "no output on failure");
}

#[test]
fn render_bench_times_a_given_ply_and_camera() {
    let dir = tmp("bench");
    let gs = aim::bench::random_scene(2000, 3);
    let ply = dir.join("scene.ply");
    aim::splat::ply::write_ply(&ply, &gs).expect("written");
    let cam_path = dir.join("camera.json");
    write_camera(&cam_path, &CameraFile::from_camera(&aim::bench::bench_camera(48)));
    let o = Command::new(env!("CARGO_BIN_EXE_aim"))
        .args(["--log", "error", "bench", "render", "--json", "--repeats", "1", "--ply"])
        .arg(&ply)
        .arg("--camera")
        .arg(&cam_path)
        .output()
        .expect("aim runs");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).expect("JSON");
    let row = &v["rows"][0];
    assert_eq!(row["gaussians"], 2000);
    assert_eq!(row["resolution"], 48);
    assert!(row["forward_backward_ms"].as_f64().expect("time") > 0.0);
}

/// `aim render --backend gpu` draws the image `--backend cpu` does (PSNR >= 50 dB
/// between the two PNGs). Without a GPU adapter it is skipped with a message,
/// unless AIM_REQUIRE_GPU=1 (tests/run), where the missing adapter fails it.
#[test]
fn render_command_on_the_gpu_backend_matches_the_cpu_backend() {
    let dir = tmp("gpu");
    let gs = aim::bench::random_scene(20_000, 12);
    let ply = dir.join("scene.ply");
    aim::splat::ply::write_ply(&ply, &gs).expect("written");
    let cam_path = dir.join("camera.json");
    write_camera(&cam_path, &CameraFile::from_camera(&aim::bench::bench_camera(256)));
    let (cpu, gpu) = (dir.join("cpu.png"), dir.join("gpu.png"));
    let o = aim_render(&ply, &cam_path, &cpu, &["--backend", "cpu"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let o = aim_render(&ply, &cam_path, &gpu, &["--backend", "gpu"]);
    let stderr = String::from_utf8_lossy(&o.stderr);
    if !o.status.success()
        && stderr.contains("no GPU adapter")
        && std::env::var("AIM_REQUIRE_GPU").as_deref() != Ok("1")
    {
        eprintln!("skipping: {stderr}");
        return;
    }
    assert!(o.status.success(), "{stderr}");
    let (a, b) = (image::open(&cpu).expect("png").into_rgb8(), image::open(&gpu).expect("png").into_rgb8());
    let mse = a.as_raw().iter().zip(b.as_raw()).map(|(x, y)| ((*x as f64 - *y as f64) / 255.0).powi(2)).sum::<f64>()
        / a.as_raw().len() as f64;
    let psnr = if mse == 0.0 { f64::INFINITY } else { -10.0 * mse.log10() };
    assert!(psnr >= 50.0, "gpu vs cpu render: {psnr:.1} dB");
}
