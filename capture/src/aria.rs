//! Aria recordings: the RGB stream (214-1) of a VRS file, its JPEG frames with
//! `capture_timestamp_ns`, and the device calibration from the `calib_json` file tag.

use std::path::Path;

use crate::calib::{CameraCalibration, DeviceCalibration};
use crate::error::{Error, Result};
use crate::vrs::{BlockKind, RecordInfo, RecordType, StreamId, VrsFile};

/// One encoded RGB frame as stored in the recording.
#[derive(Clone, Debug)]
pub struct EncodedFrame {
    /// Index among the stream's data records.
    pub index: usize,
    /// VRS record timestamp (seconds, device clock).
    pub record_timestamp_s: f64,
    /// Exposure-centre capture time on the device clock (the MPS time base, in ns).
    pub capture_timestamp_ns: i64,
    pub frame_number: Option<u64>,
    pub exposure_s: Option<f64>,
    pub gain: Option<f64>,
    /// JPEG bytes.
    pub jpeg: Vec<u8>,
}

/// The RGB stream's configuration record.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct RgbConfig {
    pub width: Option<u32>,
    pub height: Option<u32>,
    pub nominal_rate_hz: Option<f64>,
    pub sensor_model: Option<String>,
    pub device_serial: Option<String>,
}

/// An Aria VRS recording opened for its RGB stream.
#[derive(Debug)]
pub struct AriaRecording {
    pub vrs: VrsFile,
    pub stream: StreamId,
    pub rgb_records: Vec<RecordInfo>,
    pub config: RgbConfig,
    /// The factory calibration from `calib_json`, if present and parseable.
    pub calibration: Option<DeviceCalibration>,
    /// Why the calibration is missing, if it is.
    pub calibration_error: Option<String>,
}

impl AriaRecording {
    pub fn open(path: impl AsRef<Path>) -> Result<Self> {
        let vrs = VrsFile::open(path)?;
        Self::from_vrs(vrs, StreamId::ARIA_RGB)
    }

    /// From bytes in memory (tests, fuzzing); `name` appears in errors.
    pub fn from_bytes(name: &str, bytes: Vec<u8>) -> Result<Self> {
        Self::from_vrs(VrsFile::from_bytes(name, bytes)?, StreamId::ARIA_RGB)
    }

    pub fn from_vrs(mut vrs: VrsFile, stream: StreamId) -> Result<Self> {
        if !vrs.streams.contains_key(&stream) {
            return Err(Error::bad_file(vrs.path(), format!("no stream {stream} (Aria RGB camera) in the recording")));
        }
        let rgb_records = vrs.records(stream, RecordType::Data);
        let mut config = RgbConfig::default();
        if let Some(info) = vrs.records(stream, RecordType::Configuration).first().copied() {
            match vrs.read_blocks(&info) {
                Ok(content) => {
                    let fmt = vrs.record_format(stream, RecordType::Configuration, content.header.format_version);
                    let layout = fmt.and_then(|f| f.blocks.into_iter().find_map(|b| b.layout));
                    if let (Some(l), Some(b)) = (layout, content.block(|k| *k == BlockKind::DataLayout)) {
                        config.width = l.get_u32(b, "image_width");
                        config.height = l.get_u32(b, "image_height");
                        config.nominal_rate_hz = l.get_f64(b, "nominal_rate");
                        config.sensor_model = l.get_string(b, "sensor_model");
                        config.device_serial = l.get_string(b, "device_serial");
                    }
                }
                Err(e) => tracing::warn!("RGB configuration record unreadable: {e}"),
            }
        }
        let (calibration, calibration_error) = match vrs.file_tags.get("calib_json") {
            Some(s) => match DeviceCalibration::from_json_str(vrs.path(), s) {
                Ok(c) => (Some(c), None),
                Err(e) => (None, Some(e.to_string())),
            },
            None => (None, Some("no calib_json file tag".to_string())),
        };
        Ok(AriaRecording { vrs, stream, rgb_records, config, calibration, calibration_error })
    }

    pub fn path(&self) -> &Path {
        self.vrs.path()
    }

    pub fn frame_count(&self) -> usize {
        self.rgb_records.len()
    }

    /// Read and parse RGB frame `i` (the JPEG bytes are not decoded here).
    pub fn read_frame(&mut self, i: usize) -> Result<EncodedFrame> {
        let info = *self.rgb_records.get(i).ok_or_else(|| {
            Error::bad_file(self.vrs.path(), format!("frame {i} out of range ({})", self.frame_count()))
        })?;
        let content = self.vrs.read_blocks(&info)?;
        let fmt = self.vrs.record_format(self.stream, RecordType::Data, content.header.format_version);
        let layout = fmt.and_then(|f| f.blocks.into_iter().find_map(|b| b.layout));
        let meta = content.block(|k| *k == BlockKind::DataLayout).unwrap_or(&[]);
        let jpeg = content
            .block(|k| matches!(k, BlockKind::Image(f) if f == "jpg"))
            .ok_or_else(|| Error::bad_file(self.vrs.path(), format!("RGB record {i} has no JPEG block")))?
            .to_vec();
        let capture_timestamp_ns = layout
            .as_ref()
            .and_then(|l| l.get_i64(meta, "capture_timestamp_ns"))
            .unwrap_or((info.timestamp * 1e9).round() as i64);
        Ok(EncodedFrame {
            index: i,
            record_timestamp_s: info.timestamp,
            capture_timestamp_ns,
            frame_number: layout.as_ref().and_then(|l| l.get_u64(meta, "frame_number")),
            exposure_s: layout.as_ref().and_then(|l| l.get_f64(meta, "exposure_duration_s")),
            gain: layout.as_ref().and_then(|l| l.get_f64(meta, "gain")),
            jpeg,
        })
    }

    /// The RGB camera calibration at the recorded resolution (from the configuration
    /// record; 1408 x 1408 if it is missing).
    pub fn rgb_calibration(&self) -> Result<CameraCalibration> {
        let dev = self.calibration.as_ref().ok_or_else(|| {
            Error::bad_file(self.vrs.path(), self.calibration_error.clone().unwrap_or_else(|| "no calibration".into()))
        })?;
        let native = dev.rgb(self.vrs.path())?;
        let w = self.config.width.unwrap_or(1408);
        let h = self.config.height.unwrap_or(w);
        native.rescaled_to(w, h).map_err(|e| Error::bad_file(self.vrs.path(), e))
    }
}

/// Decode a JPEG into packed RGB8. Errors are plain strings (the caller names the frame).
pub fn decode_jpeg(bytes: &[u8]) -> std::result::Result<image::RgbImage, String> {
    use zune_core::bytestream::ZCursor;
    use zune_core::colorspace::ColorSpace;
    use zune_core::options::DecoderOptions;
    let opts = DecoderOptions::default()
        .jpeg_set_out_colorspace(ColorSpace::RGB)
        .set_max_width(1 << 14)
        .set_max_height(1 << 14);
    let mut d = zune_jpeg::JpegDecoder::new_with_options(ZCursor::new(bytes), opts);
    let pixels = d.decode().map_err(|e| format!("JPEG: {e:?}"))?;
    let (w, h) = d.dimensions().ok_or("JPEG: no dimensions")?;
    let expected = w * h * 3;
    if pixels.len() != expected {
        return Err(format!("JPEG: {} bytes decoded for {w}x{h} RGB", pixels.len()));
    }
    image::RgbImage::from_raw(w as u32, h as u32, pixels).ok_or_else(|| "JPEG: bad buffer".to_string())
}
