//! Any text as Aria calibration JSON (calib_json) and as online_calibration.jsonl.
#![no_main]

use std::path::Path;

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let s = String::from_utf8_lossy(data);
    if let Ok(d) = aim_capture::calib::DeviceCalibration::from_json_str(Path::new("fuzz.json"), &s) {
        for c in &d.cameras {
            if let Ok(r) = c.rescaled_to(1408, 1408) {
                if let Some(px) = r.project(glam::DVec3::new(0.1, -0.2, 1.0)) {
                    let _ = r.unproject(px);
                }
            }
        }
    }
    let _ = aim_capture::calib::parse_online_calibration(Path::new("fuzz.jsonl"), &s);
});
