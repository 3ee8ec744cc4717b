//! `aim bench ingest`: frames per second through the ingestion thread for 1408 x 1408
//! Aria frames (JPEG decode + undistortion to 704 x 704 + skin-colour detection), read
//! from a VRS recording and repeated to get a stable number.

use std::path::Path;
use std::time::Instant;

use serde::Serialize;

use crate::detect::SkinEvidence;
use crate::error::{Error, Result};
use crate::ingest::{Ingest, IngestConfig, IngestStats, Message, Policy};
use crate::pipeline::{PhaseTagger, Processor};
use crate::source::{FrameSource, RawFrame, VrsSource};
use crate::undistort::UndistortConfig;

#[derive(Clone, Debug, Serialize)]
pub struct IngestBench {
    pub recording: String,
    pub source_width: u32,
    pub source_height: u32,
    pub output_width: u32,
    pub output_height: u32,
    pub frames: u64,
    pub seconds: f64,
    pub frames_per_second: f64,
    /// Single-thread cost of each stage on one frame, milliseconds (median of the sample).
    /// Reading one RGB record from the VRS file, decompression included.
    pub read_ms: f64,
    pub decode_ms: f64,
    pub undistort_ms: f64,
    pub detect_ms: f64,
    /// Building the undistortion lookup table once.
    pub map_build_ms: f64,
    pub threads: usize,
    pub stats: IngestStats,
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    v.get(v.len() / 2).copied().unwrap_or(0.0)
}

/// Re-reads the VRS file (index, zstd record, JPEG bytes) on every pass, so that the
/// timing includes reading the recording, with timestamps shifted to keep increasing.
struct VrsLoop {
    path: std::path::PathBuf,
    src: VrsSource,
    total: usize,
    served: usize,
    n: usize,
    period_ns: i64,
    first_ns: Option<(i64, i64)>,
}

impl FrameSource for VrsLoop {
    fn describe(&self) -> String {
        format!("{} looped to {} frames", self.src.describe(), self.total)
    }
    fn len_hint(&self) -> Option<usize> {
        Some(self.total)
    }
    fn camera(&self) -> Option<crate::calib::CameraCalibration> {
        self.src.camera()
    }
    fn next_frame(&mut self) -> Option<Result<RawFrame>> {
        if self.served >= self.total {
            return None;
        }
        if self.served > 0 && self.served.is_multiple_of(self.n) {
            match VrsSource::open(&self.path) {
                Ok(s) => self.src = s,
                Err(e) => return Some(Err(e)),
            }
        }
        let rep = (self.served / self.n) as i64;
        let mut f = match self.src.next_frame()? {
            Ok(f) => f,
            Err(e) => return Some(Err(e)),
        };
        let (first, _) = *self.first_ns.get_or_insert((f.timestamp_ns, 0));
        if rep == 0 {
            self.period_ns = self.period_ns.max(f.timestamp_ns - first + 50_000_000);
        }
        f.timestamp_ns += rep * self.period_ns;
        f.index = self.served;
        self.served += 1;
        Some(Ok(f))
    }
}

/// Run the benchmark on `vrs` (its RGB frames repeated until `frames` have passed).
pub fn bench_ingest(vrs: &Path, frames: usize, threads: usize) -> Result<IngestBench> {
    let src = VrsSource::open(vrs)?;
    let cam = src.camera().ok_or_else(|| Error::bad_file(vrs, "no RGB calibration"))?;
    let n = src.len_hint().unwrap_or(0).max(1);
    let cfg = UndistortConfig::aria_default();
    let t0 = Instant::now();
    let processor = Processor::new(Some(&cam), &cfg, None);
    let map_build_ms = t0.elapsed().as_secs_f64() * 1e3;

    // Per-stage single-thread timings on the recording's frames.
    let mut rec = crate::aria::AriaRecording::open(vrs)?;
    let (mut rd, mut dec, mut und, mut det) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    let map = processor.map.as_ref().ok_or_else(|| Error::Other("no undistortion map".into()))?;
    let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build().map_err(|e| Error::Other(e.to_string()))?;
    for i in 0..rec.frame_count() {
        let t = Instant::now();
        let f = rec.read_frame(i)?;
        rd.push(t.elapsed().as_secs_f64() * 1e3);
        pool.install(|| -> Result<()> {
            let t = Instant::now();
            let rgb = crate::aria::decode_jpeg(&f.jpeg).map_err(Error::Other)?;
            dec.push(t.elapsed().as_secs_f64() * 1e3);
            let t = Instant::now();
            let out = map.apply_rgb(&rgb).map_err(Error::Other)?;
            und.push(t.elapsed().as_secs_f64() * 1e3);
            let t = Instant::now();
            let (w, h) = out.dimensions();
            std::hint::black_box(SkinEvidence::default().score(&out, (w / 4, h / 4, 3 * w / 4, 3 * h / 4)));
            det.push(t.elapsed().as_secs_f64() * 1e3);
            Ok(())
        })?;
    }

    let repeat = frames.div_ceil(n).max(1);
    let source =
        VrsLoop { path: vrs.to_path_buf(), src, total: repeat * n, served: 0, n, period_ns: 0, first_ns: None };
    let tagger = PhaseTagger::new(Box::new(SkinEvidence::default()));
    let icfg = IngestConfig { policy: Policy::Replay, threads, batch: 2 * threads, ..IngestConfig::default() };
    let start = Instant::now();
    let ingest = Ingest::spawn(Box::new(source), processor, tagger, icfg).map_err(|e| Error::Other(e.to_string()))?;
    let mut count = 0u64;
    for m in &ingest {
        match m {
            Message::Frame(f) => {
                std::hint::black_box(&f);
                count += 1;
            }
            Message::Event(_) => {}
            Message::Error(e) => return Err(e),
        }
    }
    let seconds = start.elapsed().as_secs_f64();
    let (stats, _) = ingest.stop();
    Ok(IngestBench {
        recording: vrs.display().to_string(),
        source_width: cam.width,
        source_height: cam.height,
        output_width: cfg.width,
        output_height: cfg.height,
        frames: count,
        seconds,
        frames_per_second: count as f64 / seconds.max(1e-9),
        read_ms: median(rd),
        decode_ms: median(dec),
        undistort_ms: median(und),
        detect_ms: median(det),
        map_build_ms,
        threads,
        stats,
    })
}
