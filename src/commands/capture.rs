//! `aim capture inspect|undistort`: look into a recording (Aria VRS, synthetic Aria-like
//! recording folder, image folder, AiM dataset). The work is done by `aim_capture`.

use std::path::PathBuf;

use aim_capture::detect::{MotionEvent, ObjectRegion};
use aim_capture::recording::{cropped_frame, inspect, undistort_frame, DetectorKind, RecordingOptions};
use aim_capture::undistort::UndistortConfig;
use anyhow::Context;

#[derive(clap::Subcommand)]
pub enum Capture {
    /// Streams, frames, resolution, calibration, timestamps and the detected motion window.
    Inspect {
        recording: PathBuf,
        /// Print JSON.
        #[arg(long)]
        json: bool,
        #[command(flatten)]
        common: Common,
    },
    /// Undistort one frame to a linear camera (projectaria_tools'
    /// get_linear_camera_calibration(W, H, F) + distort_by_calibration).
    Undistort {
        recording: PathBuf,
        #[arg(long, default_value_t = 0)]
        frame: usize,
        #[arg(long, default_value_t = 704)]
        width: u32,
        #[arg(long, default_value_t = 704)]
        height: u32,
        /// Focal length of the linear camera in output pixels.
        #[arg(long, default_value_t = 300.0)]
        focal: f64,
        /// Rotate clockwise by 90 degrees (Aria RGB is mounted sideways).
        #[arg(long)]
        upright: bool,
        /// Vignetting mask PNG at the recorded resolution (e.g. rgb_vignetting_half_reso_mask.png).
        #[arg(long)]
        vignetting: Option<PathBuf>,
        /// Keep the alpha channel (0 where the fisheye does not see) instead of writing RGB.
        #[arg(long)]
        alpha: bool,
        #[arg(long)]
        out: PathBuf,
    },
    /// Cut one frame to the object region as `aim run` trains on it (undistorted,
    /// posed, square around the region; alpha 0 where rays miss the region).
    Crop {
        recording: PathBuf,
        #[arg(long, default_value_t = 0)]
        frame: usize,
        /// Output size in pixels (square).
        #[arg(long, default_value_t = 256)]
        crop_size: u32,
        /// Which object region (0-based, in object_region.json's order).
        #[arg(long, default_value_t = 0)]
        object: usize,
        #[command(flatten)]
        common: Common,
        #[arg(long)]
        out: PathBuf,
        /// Also write the crop's camera as `aim render` reads it (to compare a
        /// model rendered from it with the crop).
        #[arg(long)]
        camera_out: Option<PathBuf>,
    },
}

#[derive(clap::Args)]
pub struct Common {
    /// MPS output folder (slam/, hand_tracking/) with the recording's trajectory,
    /// hand tracking and semidense points (default: mps/ beside the recording, or
    /// the files themselves beside it).
    #[arg(long)]
    mps: Option<PathBuf>,
    /// MPS closed_loop_trajectory.csv (default: found in --mps or beside the recording).
    #[arg(long)]
    trajectory: Option<PathBuf>,
    /// MPS wrist_and_palm_poses.csv or hand_tracking_results.csv (default: beside the recording).
    #[arg(long)]
    hands: Option<PathBuf>,
    /// MPS semidense_points.csv.gz (default: beside the recording).
    #[arg(long)]
    points: Option<PathBuf>,
    /// Object region in world coordinates: x0,y0,z0,x1,y1,z1 (default: object_region.json beside the recording).
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    region: Option<Vec<f64>>,
    /// MPS online_calibration.jsonl to use instead of the recording's factory calibration.
    #[arg(long)]
    online_calibration: Option<PathBuf>,
    /// auto | mps | skin | none | HAND_IN_S,HAND_OUT_S
    #[arg(long, default_value = "auto")]
    detector: String,
    /// Output size (square) of the undistorted frames (default: 352 to inspect,
    /// 704 to train on).
    #[arg(long)]
    size: Option<u32>,
    /// Focal length of the undistorted frames in their pixels (default: 150 to
    /// inspect, 300 to train on: the same field of view).
    #[arg(long)]
    focal: Option<f64>,
}

/// Undistorted frames for the motion-window detection alone: small is enough.
pub const INSPECT_UNDISTORT: UndistortConfig =
    UndistortConfig { width: 352, height: 352, focal: 150.0, upright: false };

impl Common {
    /// The recording's options, undistorting to `default` where no size or focal is given.
    pub fn options(&self, default: UndistortConfig) -> anyhow::Result<RecordingOptions> {
        let detector: DetectorKind = self.detector.parse().map_err(anyhow::Error::msg)?;
        let region = self
            .region
            .as_deref()
            .map(ObjectRegion::from_corners)
            .transpose()
            .map_err(|e| anyhow::anyhow!("--region: {e}"))?;
        let size = self.size.unwrap_or(default.width);
        let focal = self.focal.unwrap_or(default.focal);
        Ok(RecordingOptions {
            undistort: UndistortConfig { width: size, height: size, focal, upright: false },
            trajectory: self.trajectory.clone(),
            hands: self.hands.clone(),
            points: self.points.clone(),
            mps: self.mps.clone(),
            online_calibration: self.online_calibration.clone(),
            region,
            detector,
            ..RecordingOptions::default()
        })
    }
}

pub fn run(c: Capture) -> anyhow::Result<()> {
    match c {
        Capture::Inspect { recording, json, common } => {
            let report = inspect(&recording, &common.options(INSPECT_UNDISTORT)?)?;
            if json {
                println!("{}", serde_json::to_string_pretty(&report)?);
                return Ok(());
            }
            println!("recording   {}", report.recording);
            println!("source      {}", report.source);
            for s in &report.streams {
                println!("stream      {:>8}  {:>6} records  {}", s.id, s.records, s.name.as_deref().unwrap_or(""));
            }
            println!("frames      {}", report.frame_count);
            if let (Some(w), Some(h)) = (report.width, report.height) {
                println!("resolution  {w} x {h}");
            }
            match &report.calibration {
                Some(c) => {
                    println!("camera      {} {} at {} x {}", c.label, c.model, c.width, c.height);
                    println!("params      {:?}", c.params);
                    println!(
                        "T_Dev_Cam   t = {:?}, q(xyzw) = {:?}",
                        c.t_device_camera_translation, c.t_device_camera_quaternion_xyzw
                    );
                }
                None => println!("camera      (no fisheye calibration: frames are used as they are)"),
            }
            if let (Some(a), Some(b)) = (report.timestamps_ns.first(), report.timestamps_ns.last()) {
                println!("timestamps  {a} .. {b} ns ({:.3} s)", report.time_span_s.unwrap_or(0.0));
            }
            println!("trajectory  {}", report.trajectory.as_deref().unwrap_or("none"));
            println!("hands       {}", report.hand_tracking.as_deref().unwrap_or("none"));
            println!("detector    {}", report.detector);
            if report.events.is_empty() {
                println!("window      none detected");
            }
            for window in report.events.chunks(2) {
                match window {
                    [MotionEvent::HandIn { timestamp_s: a, .. }, MotionEvent::HandOut { timestamp_s: b, .. }] => {
                        println!("window      hand-in {a:.3} s, hand-out {b:.3} s")
                    }
                    _ => println!("window      {window:?}, no hand-out before the end"),
                }
            }
            if !report.evidence.is_empty() {
                let ev: Vec<String> = report.evidence.iter().map(|e| format!("{e:.2}")).collect();
                println!("evidence    {}", ev.join(" "));
            }
            println!(
                "phases      scan {}, motion {}, after {}; skipped: {} corrupt, {} without pose, {} out of time order",
                report.phase_counts[0],
                report.phase_counts[1],
                report.phase_counts[2],
                report.stats.corrupt,
                report.stats.unposed,
                report.stats.out_of_order
            );
        }
        Capture::Crop { recording, frame, crop_size, object, common, out, camera_out } => {
            let opts = common.options(aim::stream::TRAIN_UNDISTORT)?;
            let f = cropped_frame(&recording, frame, object, &opts, crop_size, aim_capture::crop::DEFAULT_MARGIN)?;
            let mut bytes = Vec::new();
            image::DynamicImage::ImageRgba8((*f.image).clone())
                .write_to(&mut std::io::Cursor::new(&mut bytes), image::ImageFormat::Png)
                .context("encoding PNG")?;
            aim_capture::io::write_atomic(&out, &bytes)?;
            if let Some(path) = &camera_out {
                let camera = aim::camera::Camera::new(f.intrinsics, f.world_to_camera);
                let json = serde_json::to_vec_pretty(&aim::camera::CameraFile::from_camera(&camera))?;
                aim_capture::io::write_atomic(path, &json)?;
            }
            let k = f.intrinsics;
            println!(
                "wrote {} ({} x {}, f = ({:.1}, {:.1}), c = ({:.1}, {:.1}), {:?} at {:.3} s)",
                out.display(),
                k.width,
                k.height,
                k.fx,
                k.fy,
                k.cx,
                k.cy,
                f.phase,
                f.timestamp_s
            );
        }
        Capture::Undistort { recording, frame, width, height, focal, upright, vignetting, alpha, out } => {
            let cfg = UndistortConfig { width, height, focal, upright };
            let (img, cam) = undistort_frame(&recording, frame, &cfg, vignetting.as_deref())?;
            let dynimg = if alpha {
                image::DynamicImage::ImageRgba8(img)
            } else {
                image::DynamicImage::ImageRgb8(image::DynamicImage::ImageRgba8(img).to_rgb8())
            };
            let mut bytes = Vec::new();
            dynimg.write_to(&mut std::io::Cursor::new(&mut bytes), image::ImageFormat::Png).context("encoding PNG")?;
            aim_capture::io::write_atomic(&out, &bytes)?;
            eprintln!(
                "wrote {} ({} x {}, linear f = {focal}, c = {:?}{})",
                out.display(),
                cam.width,
                cam.height,
                cam.model.principal_point(),
                if upright { ", upright" } else { "" }
            );
        }
    }
    Ok(())
}
