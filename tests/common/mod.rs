//! What several integration tests share.

use std::path::Path;

use aim::synth::dataset::{write_dataset, SynthConfig};

/// A tiny synthetic dataset of `object` in `dir` (32 px, 6 scan views, 12
/// motion frames, 2 end-state views): stages I to III run on it in seconds.
pub fn tiny_dataset(object: &str, dir: &Path) {
    let cfg = SynthConfig {
        resolution: 32,
        scan_views: 6,
        motion_frames: 12,
        end_views: 2,
        test_views: 1,
        motion_test_every: 6,
        samples_per_pixel: 1,
        ..Default::default()
    };
    write_dataset(&aim::synth::object(object).expect("object"), dir, &cfg, &|_, _| {}).expect("written");
}
