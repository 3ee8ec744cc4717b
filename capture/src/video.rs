//! Video files through ffmpeg (feature `video`; needs the system FFmpeg libraries:
//! Debian libavcodec-dev libavformat-dev libavutil-dev libswscale-dev libavdevice-dev
//! libavfilter-dev, plus pkg-config and clang for the bindings).
//!
//! Frames are decoded on the ingestion thread (the source is sequential by nature) and
//! converted to RGB24; timestamps are the stream's presentation times in ns.

use std::collections::VecDeque;
use std::path::{Path, PathBuf};

use ffmpeg_next as ffmpeg;

use crate::calib::CameraCalibration;
use crate::error::{Error, Result};
use crate::source::{FrameSource, RawFrame, RawImage};

struct Inner {
    input: ffmpeg::format::context::Input,
    stream_index: usize,
    decoder: ffmpeg::decoder::Video,
    scaler: ffmpeg::software::scaling::Context,
    time_base: f64,
}

// SAFETY: the FFmpeg contexts are owned exclusively by this value and only ever used by
// the one thread that owns the source at a time (a source is moved into the ingestion
// thread, never shared); FFmpeg's demuxer, decoder and scaler contexts have no thread
// affinity.
unsafe impl Send for Inner {}

/// A video file as a frame source.
pub struct VideoSource {
    path: PathBuf,
    inner: Inner,
    camera: Option<CameraCalibration>,
    pending: VecDeque<RawFrame>,
    next_index: usize,
    eof: bool,
    frame_count: Option<usize>,
}

fn ff(path: &Path, what: &str, e: ffmpeg::Error) -> Error {
    Error::bad_file(path, format!("{what}: {e}"))
}

impl VideoSource {
    /// Open `path`; `camera` is the lens model of the video's frames (None: use as is).
    pub fn open(path: &Path, camera: Option<CameraCalibration>) -> Result<Self> {
        ffmpeg::init().map_err(|e| ff(path, "initialising ffmpeg", e))?;
        let input = ffmpeg::format::input(path).map_err(|e| ff(path, "opening video", e))?;
        let stream =
            input.streams().best(ffmpeg::media::Type::Video).ok_or_else(|| Error::bad_file(path, "no video stream"))?;
        let stream_index = stream.index();
        let tb = stream.time_base();
        let time_base = if tb.denominator() != 0 { tb.numerator() as f64 / tb.denominator() as f64 } else { 0.0 };
        let frames = stream.frames();
        let ctx = ffmpeg::codec::context::Context::from_parameters(stream.parameters())
            .map_err(|e| ff(path, "codec parameters", e))?;
        let decoder = ctx.decoder().video().map_err(|e| ff(path, "opening decoder", e))?;
        let scaler = ffmpeg::software::scaling::Context::get(
            decoder.format(),
            decoder.width(),
            decoder.height(),
            ffmpeg::format::Pixel::RGB24,
            decoder.width(),
            decoder.height(),
            ffmpeg::software::scaling::Flags::BILINEAR,
        )
        .map_err(|e| ff(path, "creating the RGB converter", e))?;
        Ok(VideoSource {
            path: path.to_path_buf(),
            inner: Inner { input, stream_index, decoder, scaler, time_base },
            camera,
            pending: VecDeque::new(),
            next_index: 0,
            eof: false,
            frame_count: (frames > 0).then_some(frames as usize),
        })
    }

    fn drain_decoder(&mut self) -> Result<()> {
        let mut decoded = ffmpeg::frame::Video::empty();
        while self.inner.decoder.receive_frame(&mut decoded).is_ok() {
            let mut rgb = ffmpeg::frame::Video::empty();
            self.inner.scaler.run(&decoded, &mut rgb).map_err(|e| ff(&self.path, "converting to RGB", e))?;
            let (w, h) = (rgb.width(), rgb.height());
            let stride = rgb.stride(0);
            let data = rgb.data(0);
            let mut buf = Vec::with_capacity((w * h * 3) as usize);
            for y in 0..h as usize {
                let row = data
                    .get(y * stride..y * stride + w as usize * 3)
                    .ok_or_else(|| Error::bad_file(&self.path, "decoded frame smaller than its size"))?;
                buf.extend_from_slice(row);
            }
            let img = image::RgbImage::from_raw(w, h, buf)
                .ok_or_else(|| Error::bad_file(&self.path, "decoded frame has a bad size"))?;
            let pts = decoded.timestamp().or(decoded.pts()).unwrap_or(self.next_index as i64);
            let timestamp_ns = (pts as f64 * self.inner.time_base * 1e9).round() as i64;
            let i = self.next_index;
            self.next_index += 1;
            self.pending.push_back(RawFrame {
                index: i,
                timestamp_ns,
                image: RawImage::Rgb(img),
                label: format!("{} frame {i}", self.path.display()),
            });
        }
        Ok(())
    }

    fn fill(&mut self) -> Result<()> {
        while self.pending.is_empty() && !self.eof {
            let mut packet = ffmpeg::Packet::empty();
            match packet.read(&mut self.inner.input) {
                Ok(()) => {
                    if packet.stream() == self.inner.stream_index {
                        if let Err(e) = self.inner.decoder.send_packet(&packet) {
                            tracing::warn!("{}: skipping a corrupt packet: {e}", self.path.display());
                            continue;
                        }
                        self.drain_decoder()?;
                    }
                }
                Err(ffmpeg::Error::Eof) => {
                    self.eof = true;
                    let _ = self.inner.decoder.send_eof();
                    self.drain_decoder()?;
                }
                Err(e) => {
                    tracing::warn!("{}: read error, skipping: {e}", self.path.display());
                }
            }
        }
        Ok(())
    }
}

impl FrameSource for VideoSource {
    fn describe(&self) -> String {
        format!("video {}", self.path.display())
    }
    fn len_hint(&self) -> Option<usize> {
        self.frame_count
    }
    fn camera(&self) -> Option<CameraCalibration> {
        self.camera.clone()
    }
    fn next_frame(&mut self) -> Option<Result<RawFrame>> {
        if let Err(e) = self.fill() {
            return Some(Err(e));
        }
        self.pending.pop_front().map(Ok)
    }
}
