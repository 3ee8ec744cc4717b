//! MPS sample files from ../shared/reference/aria/gen1/mps_sample.

use std::path::PathBuf;

use aim_capture::calib::{load_online_calibration, CameraModel};
use aim_capture::mps::{HandTracking, Trajectory};

fn mps(rel: &str) -> PathBuf {
    PathBuf::from(std::env::var_os("CARGO_MANIFEST_DIR").expect("cargo sets CARGO_MANIFEST_DIR"))
        .join("../../shared/reference/aria/gen1/mps_sample")
        .join(rel)
}

#[test]
fn closed_loop_trajectory_parses_and_interpolates() {
    let t = Trajectory::load(&mps("trajectory/closed_loop_trajectory.csv")).unwrap();
    assert_eq!(t.samples.len(), 11517);
    let (a, b) = t.span_us().unwrap();
    assert_eq!(a, 149202610);
    assert!(b > a);
    // First row: t = (0.000292, -0.006405, 0.000467), q(xyzw) = (0.500638545, 0.496952726, -0.477400195, 0.523916109).
    let p = t.interpolate(149_202_610_000, 0).unwrap();
    assert!((p.translation.x - 0.000292).abs() < 1e-9 && (p.translation.y + 0.006405).abs() < 1e-9);
    assert!((p.rotation.w - 0.523916109).abs() < 1e-6);
    // Midway between the first two samples (849 us apart, within a 1 ms tolerance)
    // the translation is the mean.
    let s0 = t.samples[0];
    let s1 = t.samples[1];
    let mid_ns = (s0.t_us + s1.t_us) * 500;
    let m = t.interpolate(mid_ns, 1_000_000).unwrap();
    let want = (s0.t_world_device.translation + s1.t_world_device.translation) / 2.0;
    assert!((m.translation - want).length() < 1e-6);
    // Interpolated rotations stay unit and between the two.
    assert!((m.rotation.length() - 1.0).abs() < 1e-9);
    assert!(t.interpolate((a - 1_000_000) * 1000, 1_000_000).is_none());
}

#[test]
fn hand_tracking_v1_v2_and_results_parse() {
    let v1 = HandTracking::load(&mps("hand_tracking/wrist_and_palm_poses.csv")).unwrap();
    let v2 = HandTracking::load(&mps("hand_tracking/wrist_and_palm_poses_v2.csv")).unwrap();
    let r = HandTracking::load(&mps("hand_tracking/hand_tracking_results_v2.csv")).unwrap();
    assert_eq!(v1.samples.len(), 122);
    assert_eq!(v2.samples.len(), 122);
    assert_eq!(r.samples.len(), 8);
    // First rows have both hands missing (confidence -1).
    assert!(v1.samples[0].left.is_none() && v1.samples[0].right.is_none());
    let with_hands = v1.samples.iter().filter(|s| s.left.is_some() || s.right.is_some()).count();
    assert_eq!(with_hands, 6, "rows with a hand");
    let s = v1.samples.iter().find(|s| s.right.is_some()).unwrap();
    assert_eq!(s.t_us, 159402529);
    let h = s.right.unwrap();
    assert!((h.confidence - 0.996126).abs() < 1e-9);
    assert!((h.wrist_device.x - 0.244013).abs() < 1e-9 && (h.palm_device.z + 0.100652).abs() < 1e-9);
    // hand_tracking_results first row: left present (0.999299), right missing (-1).
    let s = &r.samples[0];
    assert!(s.left.is_some() && s.right.is_none());
    let l = s.left.unwrap();
    assert!((l.confidence - 0.999299).abs() < 1e-9);
    assert!((l.wrist_device.x - 0.187311).abs() < 1e-9);
    // Hands are within arm's reach of the device.
    for s in &v1.samples {
        for h in s.hands() {
            assert!(h.palm_device.length() < 1.5, "{:?}", h);
        }
    }
}

#[test]
fn online_calibration_lines_have_rgb_fisheye() {
    let lines = load_online_calibration(&mps("trajectory/online_calibration.jsonl")).unwrap();
    assert_eq!(lines.len(), 122);
    let rgb = lines[0].calibration.camera("camera-rgb").unwrap();
    assert!(matches!(rgb.model, CameraModel::Fisheye624(_)));
    let r = rgb.rescaled_to(1408, 1408).unwrap();
    let (f, _) = r.model.focal();
    assert!((f - 610.0).abs() < 1.0, "{f}");
    assert_eq!(lines[0].tracking_timestamp_us, 148502610);
}
