//! "Fuzz" on stable: property tests that feed mutated and truncated bytes to every
//! parser of outside data (VRS, calibration JSON, MPS CSVs) and require an Ok or an
//! Err, never a panic. The seed is fixed (ChaCha, [7; 32]) so runs are reproducible.

use std::path::{Path, PathBuf};

use aim_capture::aria::{decode_jpeg, AriaRecording};
use aim_capture::calib::{parse_online_calibration, DeviceCalibration};
use aim_capture::mps::{HandTracking, Trajectory};
use aim_capture::vrs::{self, DataLayout, RecordFormat};
use proptest::prelude::*;
use proptest::test_runner::{Config, RngAlgorithm, TestRng, TestRunner};

fn gen1(rel: &str) -> PathBuf {
    PathBuf::from(std::env::var_os("CARGO_MANIFEST_DIR").expect("cargo sets CARGO_MANIFEST_DIR"))
        .join("../../shared/reference/aria/gen1")
        .join(rel)
}

fn runner(cases: u32) -> TestRunner {
    let cfg = Config { cases, failure_persistence: None, ..Config::default() };
    TestRunner::new_with_rng(cfg, TestRng::from_seed(RngAlgorithm::ChaCha, &[7u8; 32]))
}

/// Mutations: (position fraction, new byte) pairs plus an optional truncation fraction.
fn mutations() -> impl Strategy<Value = (Vec<(f64, u8)>, Option<f64>)> {
    (prop::collection::vec((0.0f64..1.0, any::<u8>()), 0..8), prop::option::of(0.0f64..1.0))
}

fn mutate(base: &[u8], region: usize, m: &(Vec<(f64, u8)>, Option<f64>)) -> Vec<u8> {
    let mut b = base.to_vec();
    let region = region.min(b.len()).max(1);
    for &(f, v) in &m.0 {
        let i = ((f * region as f64) as usize).min(b.len() - 1);
        b[i] = v;
    }
    if let Some(t) = m.1 {
        b.truncate((t * b.len() as f64) as usize);
    }
    b
}

#[test]
fn vrs_parsers_never_panic_on_mutated_headers() {
    let file = std::fs::read(gen1("aria_everyday_activities_test_data/recording.vrs")).unwrap();
    let p = Path::new("fuzz.vrs");
    // Description record payload and index record payload from the real file.
    let desc = &file[0x50 + 32..0x50 + 0x7f5d];
    runner(2000)
        .run(&mutations(), |m| {
            let _ = vrs::parse_file_header(p, &mutate(&file[..80], 80, &m));
            let _ = vrs::parse_record_header(p, &mutate(&file[0x50..0x70], 32, &m));
            let _ = vrs::parse_description(p, &mutate(desc, desc.len(), &m));
            let entries = mutate(&[0u8; 19 * 4], 76, &m);
            let _ = vrs::parse_index(p, &[], &entries, 1000, 5000);
            let _ =
                vrs::decompress(p, vrs::Compression::Zstd, &mutate(&file[0x7fad + 32 + 62..0x9652], 200, &m), 785 * 19);
            let _ = vrs::decompress(p, vrs::Compression::Lz4, &mutate(&[4, 34, 77, 24, 64, 112, 0, 0], 8, &m), 64);
            let s =
                String::from_utf8_lossy(&mutate(b"data_layout/size=84+image/jpg+custom/size=3", 40, &m)).into_owned();
            let _ = RecordFormat::parse(&s).split(p, &[0u8; 100]);
            Ok(())
        })
        .unwrap();
}

#[test]
fn datalayout_json_never_panics() {
    let json = r#"{"data_layout":[{"name":"a","type":"DataPieceValue<uint32_t>","offset":0},{"name":"s","type":"DataPieceString","index":0},{"name":"arr","type":"DataPieceArray<double>","offset":4,"size":3}]}"#;
    runner(1000)
        .run(&(mutations(), prop::collection::vec(any::<u8>(), 0..64)), |(m, block)| {
            let s = String::from_utf8_lossy(&mutate(json.as_bytes(), json.len(), &m)).into_owned();
            if let Ok(l) = DataLayout::from_json(&s) {
                let _ = l.block_size(Path::new("x"), &block);
                let _ = l.get_u32(&block, "a");
                let _ = l.get_string(&block, "s");
                let _ = l.get_f64(&block, "arr");
            }
            Ok(())
        })
        .unwrap();
}

#[test]
fn whole_vrs_files_mutated_or_truncated_give_errors_not_panics() {
    let file = std::fs::read(gen1("aria_everyday_activities_test_data/recording.vrs")).unwrap();
    let opened = std::cell::Cell::new(0);
    // Mutate the head (header, description, index, first records) of the file, in memory.
    runner(150)
        .run(&mutations(), |m| {
            let b = mutate(&file, 0x9652 + 4096, &m);
            if let Ok(mut rec) = AriaRecording::from_bytes("mutated.vrs", b) {
                opened.set(opened.get() + 1);
                let _ = rec.rgb_calibration();
                for i in 0..rec.frame_count() {
                    if let Ok(f) = rec.read_frame(i) {
                        let _ = decode_jpeg(&f.jpeg[..f.jpeg.len().min(4096)]);
                    }
                }
            }
            Ok(())
        })
        .unwrap();
    assert!(opened.get() > 0, "some mutations leave the file readable");
    // A file cut in the middle of frame 4: index entries past the end are dropped and the
    // frames before it still read.
    let mut rec = AriaRecording::from_bytes("cut.vrs", file[..1_500_000].to_vec()).unwrap();
    assert!(rec.frame_count() >= 2 && rec.frame_count() < 8, "{}", rec.frame_count());
    for i in 0..rec.frame_count() {
        assert!(decode_jpeg(&rec.read_frame(i).unwrap().jpeg).is_ok());
    }
    // Without its index (offset zeroed) the index is rebuilt by walking the records.
    let mut b = file.clone();
    b[24..32].fill(0);
    let rec = AriaRecording::from_bytes("noindex.vrs", b).unwrap();
    assert!(rec.vrs.index_rebuilt);
    assert_eq!(rec.frame_count(), 8);
    // A corrupt JPEG is an error for that frame only.
    assert!(decode_jpeg(&[0xff, 0xd8, 0xff, 0x00, 1, 2, 3]).is_err());
    // Errors name the file.
    let e = AriaRecording::from_bytes("named.vrs", file[..40].to_vec()).unwrap_err();
    assert!(e.to_string().contains("named.vrs"), "{e}");
}

#[test]
fn calibration_json_never_panics() {
    let file = std::fs::read(gen1("aria_everyday_activities_test_data/recording.vrs")).unwrap();
    let rec = AriaRecording::open(gen1("aria_everyday_activities_test_data/recording.vrs")).unwrap();
    let calib = rec.vrs.file_tags.get("calib_json").unwrap().clone();
    drop(file);
    let i = calib.find("camera-rgb").unwrap();
    let online = std::fs::read_to_string(gen1("mps_sample/trajectory/online_calibration.jsonl")).unwrap();
    let line = online.lines().next().unwrap().to_string();
    runner(500)
        .run(&mutations(), |m| {
            // Mutate around the RGB camera's entry so that parameters and structure change.
            let mut b = calib.as_bytes().to_vec();
            let region = &mut b[i.saturating_sub(200)..(i + 800).min(calib.len())];
            let mutated = mutate(region, region.len(), &(m.0.clone(), None));
            region.copy_from_slice(&mutated);
            let s = String::from_utf8_lossy(&b).into_owned();
            if let Ok(d) = DeviceCalibration::from_json_str(Path::new("c.json"), &s) {
                for c in &d.cameras {
                    if let Ok(r) = c.rescaled_to(1408, 1408) {
                        let _ = r.project(glam::DVec3::new(0.1, 0.2, 1.0)).map(|px| r.unproject(px));
                    }
                }
            }
            let l = String::from_utf8_lossy(&mutate(line.as_bytes(), line.len(), &m)).into_owned();
            let _ = parse_online_calibration(Path::new("o.jsonl"), &l);
            Ok(())
        })
        .unwrap();
}

#[test]
fn mps_csvs_never_panic() {
    let traj = std::fs::read_to_string(gen1("mps_sample/trajectory/closed_loop_trajectory.csv")).unwrap();
    let traj: String = traj.lines().take(20).collect::<Vec<_>>().join("\n");
    let hands = std::fs::read_to_string(gen1("mps_sample/hand_tracking/hand_tracking_results_v2.csv")).unwrap();
    runner(500)
        .run(&mutations(), |m| {
            let t = String::from_utf8_lossy(&mutate(traj.as_bytes(), traj.len(), &m)).into_owned();
            if let Ok(t) = Trajectory::parse(Path::new("t.csv"), &t) {
                let _ = t.interpolate(149_202_610_000 + 500_000, 1_000_000);
            }
            let h = String::from_utf8_lossy(&mutate(hands.as_bytes(), hands.len(), &m)).into_owned();
            if let Ok(h) = HandTracking::parse(Path::new("h.csv"), &h) {
                let _ = h.nearest(1_762_609_162_000, 1_000_000);
            }
            Ok(())
        })
        .unwrap();
}

#[test]
fn fisheye_model_never_panics_on_random_parameters() {
    use aim_capture::calib::CameraModel;
    runner(2000)
        .run(&(prop::collection::vec(-1e3f64..1e3, 15), -5.0f64..5.0, -5.0f64..5.0, -1.0f64..3.0), |(p, x, y, z)| {
            if let Ok(m) = CameraModel::from_name("FisheyeRadTanThinPrism", &p) {
                if let Some(px) = m.project(glam::DVec3::new(x, y, z)) {
                    let _ = m.unproject(px);
                }
                let _ = m.unproject(glam::DVec2::new(x * 100.0, y * 100.0));
            }
            Ok(())
        })
        .unwrap();
}
