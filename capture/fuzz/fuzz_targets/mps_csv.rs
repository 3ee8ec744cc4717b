//! Any text as MPS closed_loop_trajectory.csv and hand-tracking CSVs.
#![no_main]

use std::path::Path;

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let s = String::from_utf8_lossy(data);
    if let Ok(t) = aim_capture::mps::Trajectory::parse(Path::new("t.csv"), &s) {
        if let Some((a, b)) = t.span_us() {
            let _ = t.interpolate(a.saturating_add(b) / 2 * 1000, 1_000_000);
        }
    }
    if let Ok(h) = aim_capture::mps::HandTracking::parse(Path::new("h.csv"), &s) {
        let _ = h.nearest(0, i64::MAX);
    }
});
