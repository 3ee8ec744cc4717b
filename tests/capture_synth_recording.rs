//! End-to-end capture tests on the synthetic Aria-like recording: fisheye frames,
//! calibration JSON, MPS trajectory and hand tracking written by
//! `aim::synth::recording`, read back by `aim_capture` (undistortion, poses, detection).

use std::path::{Path, PathBuf};

use aim::synth::objects;
use aim::synth::recording::{write_recording, RecordingConfig, RecordingSummary};
use aim_capture::detect::MotionEvent;
use aim_capture::recording::{open_recording, DetectorKind, RecordingOptions};
use aim_capture::undistort::UndistortConfig;
use aim_capture::Phase;

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("aim-capture-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

fn small(hand: bool) -> RecordingConfig {
    RecordingConfig {
        resolution: 352,
        fps: 10.0,
        scan_s: 2.0,
        motion_s: 2.0,
        after_s: 1.5,
        hand,
        ..RecordingConfig::default()
    }
}

fn opts(detector: DetectorKind) -> RecordingOptions {
    RecordingOptions {
        undistort: UndistortConfig { width: 256, height: 256, focal: 110.0, upright: true },
        detector,
        ..RecordingOptions::default()
    }
}

fn window_frames(events: &[MotionEvent]) -> (Option<usize>, Option<usize>) {
    let hin = events.iter().find_map(|e| match e {
        MotionEvent::HandIn { frame, .. } => Some(*frame),
        _ => None,
    });
    let hout = events.iter().find_map(|e| match e {
        MotionEvent::HandOut { frame, .. } => Some(*frame),
        _ => None,
    });
    (hin, hout)
}

fn check_recording_files(dir: &Path, s: &RecordingSummary) {
    for f in [
        "calibration.json",
        "frames/timestamps.csv",
        "frames/frame_00000.png",
        "mps/slam/closed_loop_trajectory.csv",
        "mps/hand_tracking/wrist_and_palm_poses.csv",
        "object_region.json",
        "gt/joints.json",
        "gt/window.json",
    ] {
        assert!(dir.join(f).is_file(), "missing {f}");
    }
    assert_eq!(s.frames, 55);
    assert_eq!((s.hand_in_frame, s.hand_out_frame), (20, 40));
}

#[test]
fn synthetic_recording_hand_window_within_two_frames() {
    let dir = tmp("synth-hand");
    let fridge = objects::object("fridge").unwrap();
    let s = write_recording(&fridge, &small(true), &dir).unwrap();
    check_recording_files(&dir, &s);

    // MPS hand tracking + trajectory + object region, all found beside the recording.
    let opened = open_recording(&dir, &opts(DetectorKind::Mps)).unwrap();
    assert!(opened.trajectory_path.is_some() && opened.hands_path.is_some() && opened.region.is_some());
    let (frames, events, stats) = opened.collect();
    assert_eq!(stats.corrupt, 0);
    assert_eq!(frames.len(), s.frames, "{stats:?}");
    let (hin, hout) = window_frames(&events);
    let (hin, hout) = (hin.expect("hand-in detected"), hout.expect("hand-out detected"));
    assert!(hin.abs_diff(s.hand_in_frame) <= 2, "hand-in {hin} vs truth {}", s.hand_in_frame);
    assert!(hout.abs_diff(s.hand_out_frame) <= 2, "hand-out {hout} vs truth {}", s.hand_out_frame);
    assert_eq!(frames[hin].phase, Phase::Motion);
    assert_eq!(frames[hin - 1].phase, Phase::Scan);
    assert_eq!(frames[hout].phase, Phase::After);
    // Batch use knows the whole window: motion frames get a motion time in [0, 1], increasing.
    let mt: Vec<f32> = frames.iter().filter(|f| f.phase == Phase::Motion).map(|f| f.motion_time.unwrap()).collect();
    assert_eq!(mt[0], 0.0);
    assert!(mt.windows(2).all(|w| w[0] < w[1]) && *mt.last().unwrap() < 1.0, "{mt:?}");
    assert!(frames.iter().filter(|f| f.phase != Phase::Motion).all(|f| f.motion_time.is_none()));
    // Frames are posed: the object's centre projects inside every undistorted image.
    let c = glam::Vec3::new(0.0, 0.0, 0.0);
    for f in &frames {
        let p = f.world_to_camera.transform_point3(c);
        assert!(p.z > 0.5, "object in front of frame {}", f.index);
        let u = f.intrinsics.fx * p.x / p.z + f.intrinsics.cx;
        let v = f.intrinsics.fy * p.y / p.z + f.intrinsics.cy;
        assert!(u > 0.0 && v > 0.0 && u < 256.0 && v < 256.0, "frame {}: ({u}, {v})", f.index);
    }

    // Skin colour in the object's image region, from the images alone.
    let (_, events, _) = open_recording(&dir, &opts(DetectorKind::Skin)).unwrap().collect();
    let (hin_s, hout_s) = window_frames(&events);
    let (hin_s, hout_s) = (hin_s.expect("skin hand-in"), hout_s.expect("skin hand-out"));
    eprintln!("skin window: frames {hin_s}..{hout_s}, truth {}..{}", s.hand_in_frame, s.hand_out_frame);
    assert!(hin_s.abs_diff(s.hand_in_frame) <= 5, "skin hand-in {hin_s} vs {}", s.hand_in_frame);
    assert!(hout_s.abs_diff(s.hand_out_frame) <= 5, "skin hand-out {hout_s} vs {}", s.hand_out_frame);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn synthetic_recording_without_hand_has_no_window() {
    let dir = tmp("synth-nohand");
    let fridge = objects::object("fridge").unwrap();
    let s = write_recording(&fridge, &small(false), &dir).unwrap();
    check_recording_files(&dir, &s);
    for det in [DetectorKind::Mps, DetectorKind::Skin] {
        let (frames, events, _) = open_recording(&dir, &opts(det)).unwrap().collect();
        assert_eq!(frames.len(), s.frames);
        assert!(events.is_empty(), "{det:?}: {events:?}");
        assert!(frames.iter().all(|f| f.phase == Phase::Scan));
    }
    let _ = std::fs::remove_dir_all(&dir);
}
