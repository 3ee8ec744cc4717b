//! Tests against the real Aria sample recordings in ../shared/reference/aria.

use std::path::PathBuf;

use aim_capture::aria::{decode_jpeg, AriaRecording};
use aim_capture::calib::CameraModel;
use aim_capture::undistort::{UndistortConfig, UndistortMap};

fn sample(rel: &str) -> PathBuf {
    PathBuf::from(std::env::var_os("CARGO_MANIFEST_DIR").expect("cargo sets CARGO_MANIFEST_DIR"))
        .join("../../shared/reference/aria/gen1")
        .join(rel)
}

#[test]
fn recording_vrs_has_8_rgb_frames_with_timestamps() {
    let mut rec = AriaRecording::open(sample("aria_everyday_activities_test_data/recording.vrs")).unwrap();
    assert_eq!(rec.frame_count(), 8);
    assert_eq!(rec.config.width, Some(1408));
    assert_eq!(rec.config.height, Some(1408));
    let mut last = i64::MIN;
    for i in 0..8 {
        let f = rec.read_frame(i).unwrap();
        assert!(f.capture_timestamp_ns > last, "timestamps increase");
        // Aria RGB at 20 Hz in this sample: 50 ms apart, close to the record timestamp.
        if i > 0 {
            let dt = (f.capture_timestamp_ns - last) as f64 * 1e-9;
            assert!((dt - 0.05).abs() < 0.005, "frame {i}: dt {dt}");
        }
        assert!((f.capture_timestamp_ns as f64 * 1e-9 - f.record_timestamp_s).abs() < 0.1);
        last = f.capture_timestamp_ns;
        let img = decode_jpeg(&f.jpeg).unwrap();
        assert_eq!(img.dimensions(), (1408, 1408));
    }
    let f0 = rec.read_frame(0).unwrap();
    assert_eq!(f0.capture_timestamp_ns, 86_385_246_037, "record 0 capture time (ns)");
}

#[test]
fn calibration_is_fisheye624_at_1408() {
    let rec = AriaRecording::open(sample("aria_everyday_activities_test_data/recording.vrs")).unwrap();
    let cal = rec.rgb_calibration().unwrap();
    assert_eq!(cal.model.name(), "FisheyeRadTanThinPrism");
    assert!(matches!(cal.model, CameraModel::Fisheye624(_)));
    assert_eq!((cal.width, cal.height), (1408, 1408));
    let (f, _) = cal.model.focal();
    let (cx, cy) = cal.model.principal_point();
    assert!((f - 607.0).abs() < 0.5, "f = {f}");
    assert!((cx - 718.5).abs() < 0.5 && (cy - 703.0).abs() < 0.5, "c = ({cx}, {cy})");
    assert_eq!(cal.valid_radius, Some(707.5));
    // T_Device_Camera of the RGB camera: a few mm from the device origin.
    assert!(cal.t_device_camera.translation.length() < 0.05);
}

#[test]
fn undistorted_frame_is_mostly_valid_and_not_black() {
    let mut rec = AriaRecording::open(sample("aria_everyday_activities_test_data/recording.vrs")).unwrap();
    let cal = rec.rgb_calibration().unwrap();
    let map = UndistortMap::new(&cal, &UndistortConfig::aria_default());
    assert!(map.valid_fraction() > 0.95, "valid {}", map.valid_fraction());
    let img = decode_jpeg(&rec.read_frame(3).unwrap().jpeg).unwrap();
    let out = map.apply_rgb(&img).unwrap();
    assert_eq!(out.dimensions(), (704, 704));
    let mean: f64 =
        out.pixels().map(|p| p.0[0] as f64 + p.0[1] as f64 + p.0[2] as f64).sum::<f64>() / (3.0 * 704.0 * 704.0);
    assert!(mean > 10.0 && mean < 245.0, "mean {mean}");
}

#[test]
fn adt_video_vrs_opens() {
    let mut rec = AriaRecording::open(sample("aria_digital_twin_test_data/video.vrs")).unwrap();
    assert!(rec.frame_count() > 0);
    let f = rec.read_frame(0).unwrap();
    assert!(decode_jpeg(&f.jpeg).is_ok());
    assert!(rec.rgb_calibration().is_ok());
}

/// Reference produced with projectaria_tools (PyPI projectaria-tools, Python):
/// `lin = calibration.get_linear_camera_calibration(512, 512, 150, "camera-rgb", T_device_camera)`,
/// `distort_by_calibration(frame3, lin, rgb_calib)` on recording.vrs; saved as PNG.
#[test]
fn undistortion_matches_projectaria_tools() {
    let mut rec = AriaRecording::open(sample("aria_everyday_activities_test_data/recording.vrs")).unwrap();
    let cal = rec.rgb_calibration().unwrap();
    let f3 = rec.read_frame(3).unwrap();
    assert_eq!(f3.capture_timestamp_ns, 86_535_221_450, "projectaria_tools' capture_timestamp_ns of frame 3");
    let map = UndistortMap::new(&cal, &UndistortConfig { width: 512, height: 512, focal: 150.0, upright: false });
    let ours = map.apply_rgb(&decode_jpeg(&f3.jpeg).unwrap()).unwrap();
    let refp = PathBuf::from(std::env::var_os("CARGO_MANIFEST_DIR").expect("cargo sets CARGO_MANIFEST_DIR"))
        .join("tests/data/projectaria_undistort_frame3_512_f150.png");
    let reference = image::open(refp).unwrap().to_rgb8();
    let (mut valid_mismatch, mut sum, mut n, mut max) = (0usize, 0u64, 0u64, 0u8);
    for (o, r) in ours.pixels().zip(reference.pixels()) {
        let ref_valid = r.0 != [0, 0, 0];
        if ref_valid != (o.0[3] == 255) {
            valid_mismatch += 1;
        }
        if ref_valid && o.0[3] == 255 {
            for c in 0..3 {
                let d = o.0[c].abs_diff(r.0[c]);
                sum += d as u64;
                n += 1;
                max = max.max(d);
            }
        }
    }
    let mean = sum as f64 / n as f64;
    // Same valid region (image circle of radius 707.5 px around the principal point);
    // values differ only by JPEG decoder and bilinear rounding.
    assert!(valid_mismatch <= 16, "{valid_mismatch} pixels differ in validity");
    assert!(mean < 1.0 && max <= 8, "mean {mean}, max {max}");
}

#[test]
fn projection_matches_projectaria_tools() {
    let rec = AriaRecording::open(sample("aria_everyday_activities_test_data/recording.vrs")).unwrap();
    let cal = rec.rgb_calibration().unwrap();
    // projectaria_tools CameraCalibration.project_no_checks at 1408 px.
    for (p, want) in
        [([0.3, -0.2, 1.0], [900.56390094, 581.58708393]), ([-0.9, 0.7, 1.1], [272.05146597, 1049.45161001])]
    {
        let got = cal.model.project(glam::DVec3::from_array(p)).unwrap();
        assert!((got.x - want[0]).abs() < 1e-6 && (got.y - want[1]).abs() < 1e-6, "{got} vs {want:?}");
    }
}
