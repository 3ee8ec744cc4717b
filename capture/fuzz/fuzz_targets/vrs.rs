//! Any bytes as a VRS file: open, read the RGB calibration and every RGB frame.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(mut rec) = aim_capture::aria::AriaRecording::from_bytes("fuzz.vrs", data.to_vec()) {
        let _ = rec.rgb_calibration();
        for i in 0..rec.frame_count().min(16) {
            if let Ok(f) = rec.read_frame(i) {
                let _ = aim_capture::aria::decode_jpeg(&f.jpeg);
            }
        }
    }
});
