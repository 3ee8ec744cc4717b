//! One interface over the two rasterizers: the CPU backend (this module's
//! parent) and the GPU backend ([`super::gpu`]). Commands and trainers hold a
//! [`Backend`] and render, and differentiate, through it.

use std::sync::Arc;

use super::gpu::{AdapterKind, GpuContext, GpuError, GpuRender};
use super::raster::RasterOutput;
use super::{Gradients, Render, RenderOptions};
use crate::camera::Camera;
use crate::splat::GaussianSet;

/// Which backend a command asked for (`--backend`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum BackendChoice {
    /// The CPU rasterizer.
    #[default]
    Cpu,
    /// The GPU rasterizer on any adapter, a software one (lavapipe) included; an
    /// error when there is none.
    Gpu,
    /// A hardware GPU when there is one, else the CPU.
    Auto,
}

impl std::str::FromStr for BackendChoice {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "cpu" => Ok(Self::Cpu),
            "gpu" => Ok(Self::Gpu),
            "auto" => Ok(Self::Auto),
            _ => Err(format!("unknown backend {s:?}: cpu, gpu or auto")),
        }
    }
}

/// A rasterizer to render and differentiate with.
#[derive(Clone, Default)]
pub enum Backend {
    #[default]
    Cpu,
    Gpu(Arc<GpuContext>),
}

impl std::fmt::Debug for Backend {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.describe())
    }
}

/// A view rendered by a [`Backend`], with what its backward pass needs.
pub enum View {
    Cpu(Render),
    Gpu(GpuRender),
}

impl Backend {
    /// Open the backend `choice` names.
    pub fn open(choice: BackendChoice) -> Result<Self, GpuError> {
        match choice {
            BackendChoice::Cpu => Ok(Backend::Cpu),
            BackendChoice::Gpu => Ok(Backend::Gpu(Arc::new(GpuContext::new(AdapterKind::Any)?))),
            BackendChoice::Auto => match GpuContext::new(AdapterKind::Hardware) {
                Ok(ctx) => Ok(Backend::Gpu(Arc::new(ctx))),
                Err(e) => {
                    tracing::info!("using the CPU backend: {e}");
                    Ok(Backend::Cpu)
                }
            },
        }
    }

    /// The backend in words (the GPU's name and API).
    pub fn describe(&self) -> String {
        match self {
            Backend::Cpu => format!("cpu ({} kernels)", super::lanes::Kernels::active().name()),
            Backend::Gpu(ctx) => format!("gpu: {}", ctx.describe()),
        }
    }

    /// Render `gs` from `camera`.
    pub fn render(&self, gs: &GaussianSet, camera: &Camera, options: &RenderOptions) -> View {
        self.render_region(gs, camera, [0, 0, camera.width(), camera.height()], options)
    }

    /// Render the pixels `region` = [x0, y0, x1, y1) of `camera`'s image (see
    /// [`super::render_region`]).
    pub fn render_region(&self, gs: &GaussianSet, camera: &Camera, region: [u32; 4], options: &RenderOptions) -> View {
        self.render_sets(&[gs], camera, region, options)
    }

    /// Render several sets as one scene without copying them into one (see
    /// [`super::render_sets`]).
    pub fn render_sets(
        &self,
        sets: &[&GaussianSet],
        camera: &Camera,
        region: [u32; 4],
        options: &RenderOptions,
    ) -> View {
        match self {
            Backend::Cpu => View::Cpu(super::render_sets(sets, camera, region, options)),
            Backend::Gpu(ctx) => match ctx.render_sets(sets, camera, region, options) {
                Ok(view) => View::Gpu(view),
                // Too large for the device: the CPU backend renders it (and its
                // backward pass), the same image more slowly.
                Err(limit) => {
                    static WARNED: std::sync::Once = std::sync::Once::new();
                    WARNED.call_once(|| tracing::warn!("{limit}: such renders run on the CPU backend"));
                    View::Cpu(super::render_sets(sets, camera, region, options))
                }
            },
        }
    }

    /// Backward pass of `view`, a render of `gs` by this backend (see
    /// [`super::backward`]); with `wanted`, only those Gaussians' gradients (see
    /// [`super::backward_wanted`]: the GPU computes every row and zeroes the rest).
    pub fn backward(
        &self,
        gs: &GaussianSet,
        view: &View,
        grad_color: &[f32],
        grad_alpha: Option<&[f32]>,
        grad_depth: Option<&[f32]>,
        wanted: Option<&[bool]>,
    ) -> Gradients {
        match (view, wanted) {
            (View::Cpu(r), Some(wanted)) => super::backward_wanted(gs, r, grad_color, grad_alpha, grad_depth, wanted),
            _ => {
                let mut grads =
                    self.backward_sets(&[gs], view, grad_color, grad_alpha, grad_depth).pop().expect("one set");
                if let Some(wanted) = wanted {
                    grads.keep_wanted(wanted);
                }
                grads
            }
        }
    }

    /// Backward pass of a [`Self::render_sets`] view: one [`Gradients`] per set.
    pub fn backward_sets(
        &self,
        sets: &[&GaussianSet],
        view: &View,
        grad_color: &[f32],
        grad_alpha: Option<&[f32]>,
        grad_depth: Option<&[f32]>,
    ) -> Vec<Gradients> {
        match (self, view) {
            // The CPU's renders: the CPU backend's, and the GPU backend's scenes too large for the device.
            (_, View::Cpu(r)) => super::backward_sets(sets, r, grad_color, grad_alpha, grad_depth),
            (Backend::Gpu(ctx), View::Gpu(r)) => ctx.backward_sets(sets, r, grad_color, grad_alpha, grad_depth),
            (Backend::Cpu, View::Gpu(_)) => panic!("a GPU render is differentiated by the GPU backend that made it"),
        }
    }
}

impl View {
    pub fn width(&self) -> u32 {
        match self {
            View::Cpu(r) => r.width,
            View::Gpu(r) => r.width,
        }
    }

    pub fn height(&self) -> u32 {
        match self {
            View::Cpu(r) => r.height,
            View::Gpu(r) => r.height,
        }
    }

    /// Colour (background included), alpha, accumulated depth and the
    /// compositing state, per pixel.
    pub fn image(&self) -> &RasterOutput {
        match self {
            View::Cpu(r) => &r.image,
            View::Gpu(r) => &r.image,
        }
    }

    /// The images, the view consumed.
    pub fn into_image(self) -> RasterOutput {
        match self {
            View::Cpu(r) => r.image,
            View::Gpu(r) => r.image,
        }
    }

    /// The colour image as 8-bit RGB.
    pub fn to_rgb8(&self) -> image::RgbImage {
        self.image().to_rgb8(self.width(), self.height())
    }
}
