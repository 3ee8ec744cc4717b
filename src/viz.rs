//! Logging intermediate state to the rerun viewer (feature `rerun`): training
//! scalars, the Gaussians as coloured points, cameras and renders. A disabled
//! [`Viz`] costs nothing, so every stage takes one and logs unconditionally.
//! Logging never makes a trainer wait: what it logs is handed to a logging
//! thread, and dropped (counted, [`Viz::dropped_items`]) when more than
//! 256 MB of it is waiting there.

use std::path::PathBuf;

use crate::camera::Camera;
use crate::error::{Error, Result};
use crate::motion::JointEstimate;
#[cfg(feature = "rerun")]
use crate::motion::JointKind;
use crate::splat::GaussianSet;

/// Where the log goes.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub enum VizTarget {
    #[default]
    Off,
    /// Write an .rrd file (open it later with `rerun FILE`).
    File(PathBuf),
    /// Stream to a running viewer (`rerun` listens on rerun+http://127.0.0.1:9876/proxy).
    Connect(String),
}

/// A rerun recording, or nothing.
pub struct Viz {
    #[cfg(feature = "rerun")]
    logger: Option<Logger>,
}

/// What is logged, as the logging thread takes it.
#[cfg(feature = "rerun")]
enum Item {
    /// Components for `path`, at the iteration the logging thread had set (None:
    /// off the iteration timeline); `bytes` of Arrow data.
    Log { path: String, iteration: Option<i64>, batches: Vec<rerun::SerializedComponentBatch>, bytes: usize },
    /// Write out everything before it, then say so.
    Flush(crossbeam_channel::Sender<()>),
}

/// Log items waiting for the logging thread may hold at most this many bytes;
/// past it an item is dropped (and counted) rather than wait or grow memory.
#[cfg(feature = "rerun")]
const MAX_QUEUED_BYTES: usize = 256 << 20;

/// The rerun stream, fed by its own thread: a trainer serialises what it logs
/// and hands it over without waiting (rerun then batches and writes on threads
/// of its own).
#[cfg(feature = "rerun")]
struct Logger {
    rec: rerun::RecordingStream,
    queue: Option<crossbeam_channel::Sender<Item>>,
    thread: Option<std::thread::JoinHandle<()>>,
    queued_bytes: std::sync::Arc<std::sync::atomic::AtomicUsize>,
    max_queued_bytes: usize,
    dropped: std::sync::atomic::AtomicU64,
    /// Each logging thread's iteration (rerun's own time is per thread; the
    /// logging thread sets it per item).
    iterations: std::sync::Mutex<std::collections::HashMap<std::thread::ThreadId, i64>>,
}

#[cfg(feature = "rerun")]
impl Logger {
    /// Start the logging thread on `rec`, holding at most `max_queued_bytes` waiting.
    fn start(rec: rerun::RecordingStream, max_queued_bytes: usize) -> Result<Self> {
        use std::sync::atomic::Ordering;
        let (queue, items) = crossbeam_channel::unbounded::<Item>();
        let queued_bytes = std::sync::Arc::new(std::sync::atomic::AtomicUsize::new(0));
        let (stream, queued) = (rec.clone(), queued_bytes.clone());
        let thread = std::thread::Builder::new()
            .name("aim-rerun".into())
            .spawn(move || {
                for item in items {
                    match item {
                        Item::Log { path, iteration, batches, bytes } => {
                            match iteration {
                                Some(i) => stream.set_time_sequence("iteration", i),
                                None => stream.disable_timeline("iteration"),
                            }
                            log_or_warn(stream.log(path, &batches));
                            queued.fetch_sub(bytes, Ordering::Relaxed);
                        }
                        Item::Flush(done) => {
                            let _ = stream.flush_blocking();
                            let _ = done.send(());
                        }
                    }
                }
            })
            .map_err(|e| Error::Other(format!("starting the rerun logging thread: {e}")))?;
        Ok(Logger {
            rec,
            queue: Some(queue),
            thread: Some(thread),
            queued_bytes,
            max_queued_bytes,
            dropped: std::sync::atomic::AtomicU64::new(0),
            iterations: Default::default(),
        })
    }

    /// Hand `what` for `path` to the logging thread, or drop it when the queue is full.
    fn log(&self, path: &str, what: &dyn rerun::AsComponents) {
        use rerun::external::arrow::array::Array;
        use std::sync::atomic::Ordering;
        let batches = what.as_serialized_batches();
        let bytes = batches.iter().map(|b| b.array.get_array_memory_size()).sum();
        if self.queued_bytes.fetch_add(bytes, Ordering::Relaxed) + bytes > self.max_queued_bytes {
            self.queued_bytes.fetch_sub(bytes, Ordering::Relaxed);
            self.dropped.fetch_add(1, Ordering::Relaxed);
            return;
        }
        let iteration = self.lock_iterations().get(&std::thread::current().id()).copied();
        let item = Item::Log { path: path.to_string(), iteration, batches, bytes };
        if let Some(queue) = &self.queue {
            let _ = queue.send(item);
        }
    }

    fn lock_iterations(&self) -> std::sync::MutexGuard<'_, std::collections::HashMap<std::thread::ThreadId, i64>> {
        // A poisoned map of plain integers is still a map of plain integers.
        self.iterations.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Wait until everything handed over so far is written.
    fn flush(&self) {
        let (done, wait) = crossbeam_channel::bounded(1);
        if let Some(queue) = &self.queue {
            if queue.send(Item::Flush(done)).is_ok() {
                let _ = wait.recv();
            }
        }
    }
}

#[cfg(feature = "rerun")]
impl Drop for Logger {
    fn drop(&mut self) {
        // Closing the queue lets the thread write what is left and end.
        drop(self.queue.take());
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
        let dropped = self.dropped.load(std::sync::atomic::Ordering::Relaxed);
        if dropped > 0 {
            tracing::warn!("{dropped} rerun log item(s) dropped: the logging thread fell behind");
        }
    }
}

impl Viz {
    pub fn disabled() -> Self {
        Self {
            #[cfg(feature = "rerun")]
            logger: None,
        }
    }

    /// Open a recording named `app` at `target`.
    pub fn new(app: &'static str, target: &VizTarget) -> Result<Self> {
        if *target == VizTarget::Off {
            return Ok(Self::disabled());
        }
        #[cfg(feature = "rerun")]
        {
            let builder = rerun::RecordingStreamBuilder::new(app);
            let rec = match target {
                VizTarget::Off => unreachable!("handled above"),
                VizTarget::File(path) => builder.save(path).map_err(|e| Error::bad_file(path, e.to_string()))?,
                VizTarget::Connect(url) => builder
                    .connect_grpc_opts(url.clone())
                    .map_err(|e| Error::Other(format!("rerun viewer at {url}: {e}")))?,
            };
            Ok(Self { logger: Some(Logger::start(rec, MAX_QUEUED_BYTES)?) })
        }
        #[cfg(not(feature = "rerun"))]
        {
            let _ = app;
            Err(Error::Config("this build has no rerun support (enable the `rerun` feature)".into()))
        }
    }

    pub fn is_enabled(&self) -> bool {
        #[cfg(feature = "rerun")]
        {
            self.logger.is_some()
        }
        #[cfg(not(feature = "rerun"))]
        {
            false
        }
    }

    /// Log items dropped so far because the logging thread fell behind.
    pub fn dropped_items(&self) -> u64 {
        #[cfg(feature = "rerun")]
        if let Some(logger) = &self.logger {
            return logger.dropped.load(std::sync::atomic::Ordering::Relaxed);
        }
        0
    }

    /// Set the `iteration` timeline for what this thread logs next.
    pub fn set_iteration(&self, iteration: u32) {
        #[cfg(feature = "rerun")]
        if let Some(logger) = &self.logger {
            logger.lock_iterations().insert(std::thread::current().id(), i64::from(iteration));
        }
        #[cfg(not(feature = "rerun"))]
        let _ = iteration;
    }

    /// A scalar time series (loss, PSNR, counts).
    pub fn scalar(&self, path: &str, value: f64) {
        #[cfg(feature = "rerun")]
        if let Some(logger) = &self.logger {
            logger.log(path, &rerun::Scalars::single(value));
        }
        #[cfg(not(feature = "rerun"))]
        let _ = (path, value);
    }

    /// A line of text (events: hand-in, hand-out, a stage starting).
    pub fn text(&self, path: &str, message: &str) {
        #[cfg(feature = "rerun")]
        if let Some(logger) = &self.logger {
            logger.log(path, &rerun::TextLog::new(message));
        }
        #[cfg(not(feature = "rerun"))]
        let _ = (path, message);
    }

    /// Gaussians as points: centre, base colour (SH DC), radius = largest scale.
    pub fn gaussians(&self, path: &str, gs: &GaussianSet) {
        #[cfg(feature = "rerun")]
        if let Some(logger) = &self.logger {
            let c0 = crate::render::sh::SH_C0;
            let positions: Vec<[f32; 3]> = (0..gs.len()).map(|i| gs.mean(i).to_array()).collect();
            let colors: Vec<rerun::Color> = (0..gs.len())
                .map(|i| {
                    let c = |k: usize| ((gs.sh_dc[3 * i + k] * c0 + 0.5).clamp(0.0, 1.0) * 255.0) as u8;
                    let a = (gs.opacity(i) * 255.0) as u8;
                    rerun::Color::from_unmultiplied_rgba(c(0), c(1), c(2), a)
                })
                .collect();
            let radii: Vec<f32> = (0..gs.len()).map(|i| gs.log_scale(i).exp().max_element()).collect();
            logger.log(path, &rerun::Points3D::new(positions).with_colors(colors).with_radii(radii));
        }
        #[cfg(not(feature = "rerun"))]
        let _ = (path, gs);
    }

    /// Joints as arrows, labelled with their type and amount: a revolute axis as
    /// a 0.5 m arrow centred on its pivot, a prismatic joint as its travel from
    /// the part's centre.
    pub fn joints(&self, path: &str, joints: &[JointEstimate]) {
        #[cfg(feature = "rerun")]
        if let Some(logger) = &self.logger {
            const REVOLUTE_ARROW: f64 = 0.5;
            let (origins, vectors): (Vec<[f32; 3]>, Vec<[f32; 3]>) = joints
                .iter()
                .map(|j| match j.kind {
                    JointKind::Revolute => (j.origin - j.axis * (REVOLUTE_ARROW / 2.0), j.axis * REVOLUTE_ARROW),
                    JointKind::Prismatic => (j.origin, j.axis * j.amount),
                })
                .map(|(o, v)| (o.as_vec3().to_array(), v.as_vec3().to_array()))
                .unzip();
            let labels: Vec<String> = joints
                .iter()
                .enumerate()
                .map(|(k, j)| match j.kind {
                    JointKind::Revolute => format!("part {}: revolute {:.1} deg", k + 1, j.amount.to_degrees()),
                    JointKind::Prismatic => format!("part {}: prismatic {:.3} m", k + 1, j.amount),
                })
                .collect();
            logger.log(path, &rerun::Arrows3D::from_vectors(vectors).with_origins(origins).with_labels(labels));
        }
        #[cfg(not(feature = "rerun"))]
        let _ = (path, joints);
    }

    /// A camera: its pose (camera-to-world) and pinhole, OpenCV axes.
    pub fn camera(&self, path: &str, camera: &Camera) {
        #[cfg(feature = "rerun")]
        if let Some(logger) = &self.logger {
            let k = camera.intrinsics;
            let c2w_rot = camera.rotation().transpose();
            let pose =
                rerun::Transform3D::from_translation_mat3x3(camera.position().to_array(), c2w_rot.to_cols_array_2d());
            let pinhole =
                rerun::Pinhole::from_focal_length_and_resolution([k.fx, k.fy], [k.width as f32, k.height as f32])
                    .with_principal_point([k.cx, k.cy]);
            logger.log(path, &[&pose as &dyn rerun::AsComponents, &pinhole]);
        }
        #[cfg(not(feature = "rerun"))]
        let _ = (path, camera);
    }

    /// An RGB image from floats in [0, 1] (row-major, 3 per pixel).
    pub fn image_rgb(&self, path: &str, width: u32, height: u32, rgb: &[f32]) {
        #[cfg(feature = "rerun")]
        if let Some(logger) = &self.logger {
            let bytes: Vec<u8> = rgb.iter().map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8).collect();
            logger.log(path, &rerun::Image::from_rgb24(bytes, [width, height]));
        }
        #[cfg(not(feature = "rerun"))]
        let _ = (path, width, height, rgb);
    }

    /// The viewer's layout for a session (`aim run`, docs/session.md): the scene in
    /// 3D (input cameras by phase, stage I's Gaussians, the tracked and final
    /// parts), stage I's and stage II's scalars, and the session's events. Sent
    /// once, as the viewer's default, so a recording opens on it.
    pub fn send_session_blueprint(&self) {
        #[cfg(feature = "rerun")]
        if let Some(logger) = &self.logger {
            use rerun::blueprint::{
                Blueprint, BlueprintActivation, Horizontal, Spatial3DView, TextLogView, TimeSeriesView, Vertical,
            };
            let scene = Spatial3DView::new("scene").with_origin("/").with_contents([
                "/session/input/**",
                "/world/**",
                "/stage2/**",
                "/stage3/**",
            ]);
            let charts = Vertical::new([
                TimeSeriesView::new("stage I").with_contents(["/train/**"]).into(),
                TimeSeriesView::new("stage II").with_contents(["/stage2/loss", "/stage2/psnr"]).into(),
                TextLogView::new("events").with_contents(["/session/events"]).into(),
            ]);
            let layout = Blueprint::new(Horizontal::new([scene.into(), charts.into()]).with_column_shares([2.0, 1.0]));
            log_or_warn(layout.send(&logger.rec, BlueprintActivation { make_active: true, make_default: true }));
        }
    }

    /// Write out everything logged so far (before the program exits or a file is read).
    pub fn flush(&self) {
        #[cfg(feature = "rerun")]
        if let Some(logger) = &self.logger {
            logger.flush();
        }
    }
}

/// Logging is a side channel: a failure is reported, never fatal to the run.
#[cfg(feature = "rerun")]
fn log_or_warn(r: rerun::RecordingStreamResult<()>) {
    if let Err(e) = r {
        tracing::warn!("rerun logging failed: {e}");
    }
}

#[cfg(all(test, feature = "rerun"))]
mod tests {
    use super::*;

    /// What would not fit in the logging thread's queue is dropped and counted,
    /// never waited for; what fits is logged.
    #[test]
    fn items_past_the_queues_budget_are_dropped_and_counted() {
        let path = std::env::temp_dir().join(format!("aim-viz-budget-{}.rrd", std::process::id()));
        let rec = rerun::RecordingStreamBuilder::new("aim-test").save(&path).expect("an rrd file");
        // A 100 x 100 RGB image is 30 kB: never fits in 16 kB; a scalar does.
        let viz = Viz { logger: Some(Logger::start(rec, 16 << 10).expect("logging thread")) };
        let image = vec![0.5; 100 * 100 * 3];
        for _ in 0..5 {
            viz.image_rgb("big", 100, 100, &image);
        }
        viz.scalar("small", 1.0);
        viz.flush();
        assert_eq!(viz.dropped_items(), 5);
        drop(viz);
        let written = std::fs::metadata(&path).expect("the file").len();
        assert!(written > 0 && written < 30_000, "the scalar and not the images: {written} bytes");
        let _ = std::fs::remove_file(&path);
    }
}
