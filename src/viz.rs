//! Logging intermediate state to the rerun viewer (feature `rerun`): training
//! scalars, the Gaussians as coloured points, cameras and renders. A disabled
//! [`Viz`] costs nothing, so every stage takes one and logs unconditionally.

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
    rec: Option<rerun::RecordingStream>,
}

impl Viz {
    pub fn disabled() -> Self {
        Self {
            #[cfg(feature = "rerun")]
            rec: None,
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
            Ok(Self { rec: Some(rec) })
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
            self.rec.is_some()
        }
        #[cfg(not(feature = "rerun"))]
        {
            false
        }
    }

    /// Set the `iteration` timeline for what follows.
    pub fn set_iteration(&self, iteration: u32) {
        #[cfg(feature = "rerun")]
        if let Some(rec) = &self.rec {
            rec.set_time_sequence("iteration", i64::from(iteration));
        }
        #[cfg(not(feature = "rerun"))]
        let _ = iteration;
    }

    /// A scalar time series (loss, PSNR, counts).
    pub fn scalar(&self, path: &str, value: f64) {
        #[cfg(feature = "rerun")]
        if let Some(rec) = &self.rec {
            log_or_warn(rec.log(path, &rerun::Scalars::single(value)));
        }
        #[cfg(not(feature = "rerun"))]
        let _ = (path, value);
    }

    /// A line of text (events: hand-in, hand-out, a stage starting).
    pub fn text(&self, path: &str, message: &str) {
        #[cfg(feature = "rerun")]
        if let Some(rec) = &self.rec {
            log_or_warn(rec.log(path, &rerun::TextLog::new(message)));
        }
        #[cfg(not(feature = "rerun"))]
        let _ = (path, message);
    }

    /// Gaussians as points: centre, base colour (SH DC), radius = largest scale.
    pub fn gaussians(&self, path: &str, gs: &GaussianSet) {
        #[cfg(feature = "rerun")]
        if let Some(rec) = &self.rec {
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
            log_or_warn(rec.log(path, &rerun::Points3D::new(positions).with_colors(colors).with_radii(radii)));
        }
        #[cfg(not(feature = "rerun"))]
        let _ = (path, gs);
    }

    /// Joints as arrows, labelled with their type and amount: a revolute axis as
    /// a 0.5 m arrow centred on its pivot, a prismatic joint as its travel from
    /// the part's centre.
    pub fn joints(&self, path: &str, joints: &[JointEstimate]) {
        #[cfg(feature = "rerun")]
        if let Some(rec) = &self.rec {
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
            log_or_warn(
                rec.log(path, &rerun::Arrows3D::from_vectors(vectors).with_origins(origins).with_labels(labels)),
            );
        }
        #[cfg(not(feature = "rerun"))]
        let _ = (path, joints);
    }

    /// A camera: its pose (camera-to-world) and pinhole, OpenCV axes.
    pub fn camera(&self, path: &str, camera: &Camera) {
        #[cfg(feature = "rerun")]
        if let Some(rec) = &self.rec {
            let k = camera.intrinsics;
            let c2w_rot = camera.rotation().transpose();
            log_or_warn(rec.log(
                path,
                &rerun::Transform3D::from_translation_mat3x3(camera.position().to_array(), c2w_rot.to_cols_array_2d()),
            ));
            log_or_warn(
                rec.log(
                    path,
                    &rerun::Pinhole::from_focal_length_and_resolution([k.fx, k.fy], [k.width as f32, k.height as f32])
                        .with_principal_point([k.cx, k.cy]),
                ),
            );
        }
        #[cfg(not(feature = "rerun"))]
        let _ = (path, camera);
    }

    /// An RGB image from floats in [0, 1] (row-major, 3 per pixel).
    pub fn image_rgb(&self, path: &str, width: u32, height: u32, rgb: &[f32]) {
        #[cfg(feature = "rerun")]
        if let Some(rec) = &self.rec {
            let bytes: Vec<u8> = rgb.iter().map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8).collect();
            log_or_warn(rec.log(path, &rerun::Image::from_rgb24(bytes, [width, height])));
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
        if let Some(rec) = &self.rec {
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
            log_or_warn(layout.send(rec, BlueprintActivation { make_active: true, make_default: true }));
        }
    }

    /// Flush pending data (before the program exits or a file is read).
    pub fn flush(&self) {
        #[cfg(feature = "rerun")]
        if let Some(rec) = &self.rec {
            let _ = rec.flush_blocking();
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
