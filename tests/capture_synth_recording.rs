//! End-to-end capture tests on the synthetic Aria-like recording: fisheye frames,
//! calibration JSON, MPS trajectory and hand tracking written by
//! `aim::synth::recording`, read back by `aim_capture` (undistortion, poses, detection).

use std::path::{Path, PathBuf};

use aim::synth::objects;
use aim::synth::recording::{write_recording, InteractionSummary, RecordingConfig, RecordingSummary};
use aim_capture::crop::DEFAULT_MARGIN;
use aim_capture::detect::MotionEvent;
use aim_capture::recording::{cropped_frame, open_recording, DetectorKind, RecordingOptions};
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

/// The detected window `(hand-in, hand-out)` frames within `frames` of the truth.
fn assert_window_near(detected: (usize, usize), truth: &InteractionSummary, frames: usize, detector: &str) {
    let (hin, hout) = detected;
    eprintln!("{detector} window: frames {hin}..{hout}, truth {}..{}", truth.hand_in_frame, truth.hand_out_frame);
    assert!(hin.abs_diff(truth.hand_in_frame) <= frames, "{detector} hand-in {hin} vs {}", truth.hand_in_frame);
    assert!(hout.abs_diff(truth.hand_out_frame) <= frames, "{detector} hand-out {hout} vs {}", truth.hand_out_frame);
}

fn check_recording_files(dir: &Path, s: &RecordingSummary) {
    for f in [
        "calibration.json",
        "frames/timestamps.csv",
        "frames/frame_00000.png",
        "mps/slam/closed_loop_trajectory.csv",
        "mps/hand_tracking/wrist_and_palm_poses.csv",
        "object_region.json",
        "mps/slam/semidense_points.csv.gz",
        "gt/joints.json",
        "gt/window.json",
    ] {
        assert!(dir.join(f).is_file(), "missing {f}");
    }
    assert_eq!(s.frames, 55);
    let window = &s.interactions[0];
    assert_eq!((s.interactions.len(), window.hand_in_frame, window.hand_out_frame), (1, 20, 40));
    check_semidense_points(dir);
}

/// The semidense points lie on what the scan saw: the object at rest (inside its
/// region) or the floor, to within their stated uncertainty, and both are there.
fn check_semidense_points(dir: &Path) {
    let path = dir.join("mps/slam/semidense_points.csv.gz");
    let pts = aim_capture::mps::SemidensePoints::load(&path).unwrap();
    let region: aim_capture::detect::ObjectRegion =
        serde_json::from_str(&std::fs::read_to_string(dir.join("object_region.json")).unwrap()).unwrap();
    let (mut on_object, mut on_floor) = (0, 0);
    for (p, &std) in pts.points.iter().zip(&pts.dist_std) {
        let slack = 4.0 * std + 1e-3;
        if (p.z - region.min[2]).abs() <= slack {
            on_floor += 1;
        } else {
            assert!(region.distance(*p) <= slack, "{p} ({std}) is neither on the floor nor in the object's region");
            on_object += 1;
        }
    }
    assert!(on_object > 200 && on_floor > 1000, "{on_object} points on the object, {on_floor} on the floor");
}

#[test]
fn two_objects_give_two_windows_each_at_its_object() {
    let dir = tmp("synth-two");
    let objects = [objects::object("fridge").unwrap(), objects::object("storage").unwrap()];
    let cfg = RecordingConfig { resolution: 128, walk_s: 1.0, ..small(true) };
    let s = write_recording(&objects, &cfg, &dir).unwrap();
    assert_eq!(s.interactions.len(), 2);
    assert_eq!(s.frames, ((2.0 * (2.0 + 2.0 + 1.5) + 1.0) * 10.0) as usize);
    // One region and one ground truth per object; the objects stand apart.
    let opened = open_recording(&dir, &opts(DetectorKind::Mps)).unwrap();
    let [a, b] = opened.regions.as_slice() else { panic!("{:?}", opened.regions) };
    assert!(b.min[0] > a.max[0] + 1.0, "{a:?} {b:?}");
    for k in 0..2 {
        let gt = aim::synth::recording::object_ground_truth(&dir, k).join("gt/joints.json");
        assert!(gt.is_file(), "{}", gt.display());
    }
    // The MPS hands give both windows, each within two frames of the truth.
    let (frames, events, _) = opened.collect();
    assert_eq!(frames.len(), s.frames);
    assert_eq!(events.len(), 4, "{events:?}");
    for (window, truth) in events.chunks(2).zip(&s.interactions) {
        let [MotionEvent::HandIn { frame: hin, .. }, MotionEvent::HandOut { frame: hout, .. }] = window else {
            panic!("{window:?}")
        };
        assert_window_near((*hin, *hout), truth, 2, "mps");
    }
    // Between the windows the frames are after the first and before the second.
    let (first_out, second_in) = (s.interactions[0].hand_out_frame + 3, s.interactions[1].hand_in_frame - 3);
    assert!(frames[first_out..second_in].iter().all(|f| f.phase == Phase::After));
}

#[test]
fn synthetic_recording_hand_window_within_two_frames() {
    let dir = tmp("synth-hand");
    let fridge = objects::object("fridge").unwrap();
    let s = write_recording(std::slice::from_ref(&fridge), &small(true), &dir).unwrap();
    check_recording_files(&dir, &s);

    // MPS hand tracking + trajectory + object region, all found beside the recording.
    let opened = open_recording(&dir, &opts(DetectorKind::Mps)).unwrap();
    assert!(opened.trajectory_path.is_some() && opened.hands_path.is_some() && opened.regions.len() == 1);
    let (frames, events, stats) = opened.collect();
    assert_eq!(stats.corrupt, 0);
    assert_eq!(frames.len(), s.frames, "{stats:?}");
    let (hin, hout) = window_frames(&events);
    let (hin, hout) = (hin.expect("hand-in detected"), hout.expect("hand-out detected"));
    assert_window_near((hin, hout), &s.interactions[0], 2, "mps");
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
    assert_window_near((hin_s, hout_s), &s.interactions[0], 5, "skin");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn synthetic_recording_without_hand_has_no_window() {
    let dir = tmp("synth-nohand");
    let fridge = objects::object("fridge").unwrap();
    let s = write_recording(std::slice::from_ref(&fridge), &small(false), &dir).unwrap();
    check_recording_files(&dir, &s);
    for det in [DetectorKind::Mps, DetectorKind::Skin] {
        let (frames, events, _) = open_recording(&dir, &opts(det)).unwrap().collect();
        assert_eq!(frames.len(), s.frames);
        assert!(events.is_empty(), "{det:?}: {events:?}");
        assert!(frames.iter().all(|f| f.phase == Phase::Scan));
    }
    // The MPS output kept elsewhere (`--mps DIR`): found there, and only there.
    let elsewhere = tmp("synth-nohand-mps");
    std::fs::rename(dir.join("mps"), &elsewhere).unwrap();
    let found = |mps: Option<PathBuf>| {
        let o = open_recording(&dir, &RecordingOptions { mps, ..opts(DetectorKind::None) }).unwrap();
        [o.trajectory_path.is_some(), o.hands_path.is_some(), o.points_path.is_some()]
    };
    assert_eq!(found(None), [false; 3], "nothing beside the recording any more");
    assert_eq!(found(Some(elsewhere.clone())), [true; 3]);
    let missing = elsewhere.join("nope");
    let e = open_recording(&dir, &RecordingOptions { mps: Some(missing.clone()), ..opts(DetectorKind::None) });
    assert!(e.err().is_some_and(|e| e.to_string().contains(&missing.display().to_string())));
    let _ = std::fs::remove_dir_all(&dir);
    let _ = std::fs::remove_dir_all(&elsewhere);
}

/// `aim capture crop`'s frame: the undistorted frame cut to the object region is
/// the same pinhole camera (a crop pixel shows what the whole frame shows along
/// its ray), the object is in it, and only rays that miss the region are background.
#[test]
fn the_object_crop_is_the_frame_seen_through_the_region() {
    let dir = tmp("crop");
    write_recording(&[objects::fridge()], &small(false), &dir).unwrap();
    let options = opts(DetectorKind::None);
    let index = 7;
    let crop = cropped_frame(&dir, index, 0, &options, 96, DEFAULT_MARGIN).unwrap();
    let (whole, _, _) = open_recording(&dir, &options).unwrap().collect();
    let whole = &whole[index];
    assert_eq!(crop.world_to_camera, whole.world_to_camera);
    let (k, kw) = (crop.intrinsics, whole.intrinsics);
    assert_eq!((k.width, k.height, crop.image.width(), crop.image.height()), (96, 96, 96, 96));
    let region: aim_capture::detect::ObjectRegion =
        serde_json::from_str(&std::fs::read_to_string(dir.join("object_region.json")).unwrap()).unwrap();
    let c2w = crop.world_to_camera.inverse();
    let eye = c2w.transform_point3(glam::Vec3::ZERO);
    let (lo, hi) = (glam::Vec3::from(region.min.map(|v| v as f32)), glam::Vec3::from(region.max.map(|v| v as f32)));
    let hits_region = |dir: glam::Vec3| {
        let (mut t0, mut t1) = (0.0f32, f32::INFINITY);
        for a in 0..3 {
            let (ta, tb) = ((lo[a] - eye[a]) / dir[a], (hi[a] - eye[a]) / dir[a]);
            (t0, t1) = (t0.max(ta.min(tb)), t1.min(ta.max(tb)));
        }
        t0 <= t1
    };
    let (mut object, mut background, mut compared, mut difference) = (0, 0, 0, 0.0f32);
    for (i, j, p) in crop.image.enumerate_pixels() {
        let ray = k.unproject(i as f32 + 0.5, j as f32 + 0.5);
        let hit = hits_region(c2w.transform_vector3(ray));
        match p[3] {
            255 => {
                object += 1;
                assert!(hit, "pixel ({i}, {j}) kept, but its ray misses the region");
            }
            0 => {
                background += 1;
                assert!(!hit, "pixel ({i}, {j}) is background, but its ray crosses the region");
            }
            _ => {}
        }
        // A kept pixel shows what the whole frame shows along its ray.
        let (u, v) = (kw.fx * ray.x / ray.z + kw.cx, kw.fy * ray.y / ray.z + kw.cy);
        if p[3] == 255 && u >= 1.0 && v >= 1.0 && u < kw.width as f32 - 1.0 && v < kw.height as f32 - 1.0 {
            let (x, y) = (u - 0.5, v - 0.5);
            let (x0, y0) = (x.floor(), y.floor());
            let (ax, ay) = (x - x0, y - y0);
            let at = |dx: u32, dy: u32| whole.image.get_pixel(x0 as u32 + dx, y0 as u32 + dy)[1] as f32;
            let seen =
                (1.0 - ay) * ((1.0 - ax) * at(0, 0) + ax * at(1, 0)) + ay * ((1.0 - ax) * at(0, 1) + ax * at(1, 1));
            difference += (p[1] as f32 - seen).abs();
            compared += 1;
        }
    }
    let mean_difference = difference / compared as f32;
    assert!(mean_difference < 2.0, "crop and frame differ by {mean_difference} levels on average");
    assert!(compared > 96 * 96 / 4, "{compared} pixels compared");
    assert!(object > 96 * 96 / 4 && background > 0, "{object} object, {background} background pixels");
    // The object's centre is in the crop and not background.
    let c = crop.world_to_camera.transform_point3(glam::Vec3::ZERO);
    let (u, v) = (k.fx * c.x / c.z + k.cx, k.fy * c.y / c.z + k.cy);
    assert!((0.0..96.0).contains(&u) && (0.0..96.0).contains(&v), "centre at ({u}, {v})");
    assert_eq!(crop.image.get_pixel(u as u32, v as u32)[3], 255);
    let _ = std::fs::remove_dir_all(&dir);
}
