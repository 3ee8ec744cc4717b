//! Folder and dataset sources through `open_recording`.

use std::path::PathBuf;

use aim_capture::recording::{open_recording, DetectorKind, RecordingOptions};
use aim_capture::Phase;

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("aim-src-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn opts(detector: DetectorKind) -> RecordingOptions {
    RecordingOptions { detector, ..RecordingOptions::default() }
}

/// A folder of `count` frames img_0.png, img_1.png, ... (names unpadded), 100 ms
/// apart from 5 s on, listed in timestamps.csv.
fn numbered_frames(name: &str, count: u32) -> PathBuf {
    let d = tmp(name);
    let mut csv = String::from("file,timestamp_ns\n");
    for k in 0..count {
        let name = format!("img_{k}.png");
        image::RgbImage::from_pixel(32, 24, image::Rgb([k as u8 * 10, 50, 90])).save(d.join(&name)).unwrap();
        csv.push_str(&format!("{name},{}\n", 5_000_000_000u64 + k as u64 * 100_000_000));
    }
    std::fs::write(d.join("timestamps.csv"), csv).unwrap();
    d
}

#[test]
fn image_folder_with_timestamps_csv_and_explicit_window() {
    let d = numbered_frames("folder", 6);
    let (frames, events, stats) = open_recording(&d, &opts(DetectorKind::Explicit(5.15, 5.35))).unwrap().collect();
    assert_eq!(frames.len(), 6, "{stats:?}");
    assert!((frames[3].timestamp_s - 5.3).abs() < 1e-9);
    assert_eq!(frames[2].image.get_pixel(0, 0).0, [20, 50, 90, 255]);
    let phases: Vec<Phase> = frames.iter().map(|f| f.phase).collect();
    assert_eq!(phases, [Phase::Scan, Phase::Scan, Phase::Motion, Phase::Motion, Phase::After, Phase::After]);
    assert_eq!(events.len(), 2);
    // A folder without timestamps.csv uses the frame rate.
    std::fs::remove_file(d.join("timestamps.csv")).unwrap();
    let (frames, _, _) = open_recording(&d, &opts(DetectorKind::None)).unwrap().collect();
    assert!((frames[3].timestamp_s - 0.1).abs() < 1e-9, "{}", frames[3].timestamp_s);
    let _ = std::fs::remove_dir_all(&d);
}

#[test]
fn nerfstudio_folder_frames_pass_through_posed() {
    let d = tmp("ns");
    std::fs::create_dir_all(d.join("images")).unwrap();
    let mut frames_json = Vec::new();
    for k in 0..3 {
        image::RgbImage::from_pixel(40, 30, image::Rgb([200, 10, 10])).save(d.join(format!("images/{k}.png"))).unwrap();
        frames_json.push(serde_json::json!({
            "file_path": format!("images/{k}.png"),
            "transform_matrix": [[1.0, 0.0, 0.0, k as f64], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 2.0], [0.0, 0.0, 0.0, 1.0]],
        }));
    }
    let tj = serde_json::json!({"fl_x": 30.0, "fl_y": 30.0, "cx": 20.0, "cy": 15.0, "w": 40, "h": 30, "camera_model": "PINHOLE", "frames": frames_json});
    std::fs::write(d.join("transforms.json"), serde_json::to_string(&tj).unwrap()).unwrap();
    let (frames, events, _) = open_recording(&d, &opts(DetectorKind::None)).unwrap().collect();
    assert_eq!(frames.len(), 3);
    assert!(events.is_empty());
    assert_eq!(frames[0].intrinsics.width, 40);
    assert!((frames[0].intrinsics.fx - 30.0).abs() < 1e-6);
    // Camera centres differ along x as in the transforms.
    let c0 = frames[0].world_to_camera.inverse().w_axis;
    let c2 = frames[2].world_to_camera.inverse().w_axis;
    assert!(((c2.x - c0.x) - 2.0).abs() < 1e-5, "{c0} {c2}");
    let _ = std::fs::remove_dir_all(&d);
}

/// Frame files numbered without padding (img_2 before img_10) come in the order of
/// their numbers, which is their capture order: none is taken for a clock jumping back.
#[test]
fn image_folder_frames_come_in_the_order_of_their_numbers() {
    let d = numbered_frames("unpadded", 12);
    let (frames, _, stats) = open_recording(&d, &opts(DetectorKind::None)).unwrap().collect();
    assert_eq!((frames.len(), stats.out_of_order), (12, 0), "{stats:?}");
    assert!(frames.windows(2).all(|w| w[1].timestamp_s > w[0].timestamp_s));
}
