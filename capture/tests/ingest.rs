//! The ingestion thread on the real Aria sample: throughput, policies, shutdown.

use std::path::PathBuf;
use std::time::Duration;

use aim_capture::detect::{ExplicitEvidence, MotionEvent};
use aim_capture::ingest::{Ingest, IngestConfig, Message, Policy};
use aim_capture::pipeline::{PhaseTagger, Processor};
use aim_capture::source::{FrameSource, RepeatSource, VrsSource};
use aim_capture::undistort::UndistortConfig;
use aim_capture::Phase;

fn vrs() -> PathBuf {
    PathBuf::from(std::env::var_os("CARGO_MANIFEST_DIR").expect("cargo sets CARGO_MANIFEST_DIR"))
        .join("../../shared/reference/aria/gen1/aria_everyday_activities_test_data/recording.vrs")
}

fn setup(repeat: usize) -> (Box<dyn FrameSource>, Processor) {
    let src = VrsSource::open(vrs()).unwrap();
    let cam = src.camera().unwrap();
    let cfg = UndistortConfig { width: 352, height: 352, focal: 150.0, upright: true };
    let p = Processor::new(Some(&cam), &cfg, None);
    (Box::new(RepeatSource::new(Box::new(src), repeat).unwrap()), p)
}

#[test]
fn replay_delivers_every_frame_in_order_with_explicit_window() {
    let (src, p) = setup(3); // 24 frames, 50 ms apart within each repeat
    let t0 = 86.385246037;
    // Window covering frames 5..=12 of the 24 (times within the repeated clock).
    let tagger = PhaseTagger::new(Box::new(ExplicitEvidence { hand_in_s: t0 + 0.24, hand_out_s: t0 + 0.64 }));
    let ingest = Ingest::spawn(src, p, tagger, IngestConfig { capacity: 2, ..IngestConfig::default() }).unwrap();
    let mut frames = Vec::new();
    let mut events = Vec::new();
    for m in &ingest {
        match m {
            Message::Frame(f) => {
                std::thread::sleep(Duration::from_millis(2)); // a slow consumer
                frames.push(f)
            }
            Message::Event(e) => events.push((frames.len(), e)),
            Message::Error(e) => panic!("{e}"),
        }
    }
    let (stats, ev) = ingest.stop();
    assert_eq!(frames.len(), 24);
    assert_eq!(stats.dropped, 0);
    assert_eq!(stats.delivered, 24);
    assert!(frames.windows(2).all(|w| w[0].index + 1 == w[1].index));
    assert_eq!(frames[0].image.dimensions(), (352, 352));
    let phases: Vec<Phase> = frames.iter().map(|f| f.phase).collect();
    let first_motion = phases.iter().position(|&p| p == Phase::Motion).unwrap();
    let first_after = phases.iter().position(|&p| p == Phase::After).unwrap();
    assert_eq!((first_motion, first_after), (5, 13), "{phases:?}");
    // Events arrive right before the first frame of their phase.
    assert_eq!(events.len(), 2);
    assert_eq!(events[0].0, 5);
    assert!(matches!(events[0].1, MotionEvent::HandIn { frame: 5, .. }));
    assert!(matches!(events[1].1, MotionEvent::HandOut { frame: 13, .. }));
    assert_eq!(ev.len(), 2);
    // Upright output: the principal point is swapped, T_device_camera rotated.
    assert!((frames[0].intrinsics.cx - 176.0).abs() < 1e-3);
}

#[test]
fn live_drops_oldest_frames_but_never_events() {
    let (src, p) = setup(4); // 32 frames
    let t0 = 86.385246037;
    let tagger = PhaseTagger::new(Box::new(ExplicitEvidence { hand_in_s: t0 + 0.09, hand_out_s: t0 + 1.0 }));
    let cfg = IngestConfig { policy: Policy::Live, capacity: 2, ..IngestConfig::default() };
    let ingest = Ingest::spawn(src, p, tagger, cfg).unwrap();
    // Consumer arrives late: the producer has to drop.
    std::thread::sleep(Duration::from_millis(1500));
    let mut n = 0u64;
    let mut events = 0;
    for m in &ingest {
        match m {
            Message::Frame(_) => n += 1,
            Message::Event(_) => events += 1,
            Message::Error(e) => panic!("{e}"),
        }
    }
    let (stats, _) = ingest.stop();
    assert_eq!(stats.read, 32);
    assert!(stats.dropped > 0, "{stats:?}");
    assert_eq!(n + stats.dropped, 32, "{stats:?}");
    assert_eq!(events, 2, "both events survive the drops");
}

#[test]
fn stop_while_producer_is_blocked_is_clean() {
    let (src, p) = setup(20);
    let ingest =
        Ingest::spawn(src, p, PhaseTagger::none(), IngestConfig { capacity: 1, ..IngestConfig::default() }).unwrap();
    let first = ingest.recv();
    assert!(matches!(first, Some(Message::Frame(_))));
    let t = std::time::Instant::now();
    let (stats, _) = ingest.stop();
    assert!(t.elapsed() < Duration::from_secs(5));
    assert!(stats.read < 160, "stopped early: {stats:?}");
}

#[test]
fn missing_file_is_an_error_naming_it() {
    let e = VrsSource::open("/nonexistent/rec.vrs").err().unwrap();
    assert!(e.to_string().contains("/nonexistent/rec.vrs"));
}

#[test]
fn realtime_replay_paces_frames_at_the_recorded_rate() {
    let (src, p) = setup(1); // 8 frames, 50 ms apart: 350 ms span
    let cfg = IngestConfig { realtime: true, ..IngestConfig::default() };
    let t = std::time::Instant::now();
    let ingest = Ingest::spawn(src, p, PhaseTagger::none(), cfg).unwrap();
    let mut arrivals = Vec::new();
    for m in &ingest {
        if let Message::Frame(f) = m {
            arrivals.push((t.elapsed().as_secs_f64(), f.timestamp_s));
        }
    }
    assert_eq!(arrivals.len(), 8);
    let (a0, t0) = arrivals[0];
    for &(a, ts) in &arrivals {
        // Never early relative to the recording's clock.
        assert!(a - a0 >= (ts - t0) - 0.02, "frame at {ts} arrived {a}");
    }
    assert!(arrivals[7].0 - a0 >= 0.33);
}

/// `inner`'s frames with the clock set back by `back_ns` from frame `from` on.
struct ClockJumpsBack {
    inner: Box<dyn FrameSource>,
    from: usize,
    back_ns: i64,
}

impl FrameSource for ClockJumpsBack {
    fn describe(&self) -> String {
        format!("{} (clock set back)", self.inner.describe())
    }
    fn len_hint(&self) -> Option<usize> {
        self.inner.len_hint()
    }
    fn camera(&self) -> Option<aim_capture::calib::CameraCalibration> {
        self.inner.camera()
    }
    fn next_frame(&mut self) -> Option<aim_capture::Result<aim_capture::source::RawFrame>> {
        self.inner.next_frame().map(|r| {
            r.map(|mut f| {
                if f.index >= self.from {
                    f.timestamp_ns -= self.back_ns;
                }
                f
            })
        })
    }
}

#[test]
fn frames_where_the_clock_jumps_back_are_skipped_and_counted() {
    // 24 frames, 50 ms apart. From frame 12 on the clock reads 200 ms early (4
    // frames' worth): frames 12-15 fall at or before frame 11's time and are
    // skipped; frame 16 is after it.
    let (src, p) = setup(3);
    let src = Box::new(ClockJumpsBack { inner: src, from: 12, back_ns: 200_000_000 });
    let ingest = Ingest::spawn(src, p, PhaseTagger::none(), IngestConfig::default()).unwrap();
    let frames: Vec<_> = (&ingest)
        .filter_map(|m| match m {
            Message::Frame(f) => Some(f),
            _ => None,
        })
        .collect();
    let (stats, _) = ingest.stop();
    assert_eq!((stats.read, stats.delivered, stats.out_of_order), (24, 20, 4), "{stats:?}");
    let indices: Vec<usize> = frames.iter().map(|f| f.index).collect();
    assert!(!indices.iter().any(|i| (12..16).contains(i)), "{indices:?}");
    assert!(frames.windows(2).all(|w| w[1].timestamp_s > w[0].timestamp_s), "the frames go on in time order");
    // The batch path checks the same way.
    let (src, p) = setup(3);
    let mut src = ClockJumpsBack { inner: src, from: 12, back_ns: 200_000_000 };
    let (batch, _, batch_stats) = aim_capture::ingest::collect_all(&mut src, &p, &mut PhaseTagger::none());
    assert_eq!((batch.len(), batch_stats.out_of_order), (20, 4), "{batch_stats:?}");
}
