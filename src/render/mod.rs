//! The differentiable Gaussian rasterizer (CPU reference backend).
//!
//! Stages, as in gsplat: project every Gaussian ([`project`]), bin them into
//! 16x16 tiles in depth order and composite front to back ([`raster`]). The
//! backward pass runs the same stages in reverse. Conventions: OpenCV camera,
//! pixel centres at (i + 0.5, j + 0.5), colour = SH + 0.5 clamped at 0,
//! alpha = min(0.99, opacity * exp(-power)), skip alpha < 1/255, stop when
//! transmittance would fall below 1e-4, 0.3 px^2 covariance dilation.

use std::sync::Arc;

use glam::Vec3;
use rayon::prelude::*;

use crate::camera::Camera;
use crate::splat::GaussianSet;

mod backend;
pub mod gpu;
pub mod lanes;
pub mod project;
pub mod raster;
pub mod sh;

pub use backend::{Backend, BackendChoice, View};
use project::ProjectionCamera;

/// What to render.
#[derive(Clone, Debug)]
pub struct RenderOptions {
    pub background: Vec3,
    /// SH degree used for colour (at most the set's stored degree); None = all stored.
    pub sh_degree: Option<u32>,
    /// A background per pixel of the whole image (row-major RGB) instead of
    /// `background`: a fixed scene behind the Gaussians.
    pub background_image: Option<Arc<[f32]>>,
}

impl RenderOptions {
    /// One background colour, all stored SH degrees.
    pub fn uniform(background: Vec3) -> Self {
        Self { background, sh_degree: None, background_image: None }
    }
}

impl Default for RenderOptions {
    fn default() -> Self {
        Self::uniform(Vec3::ZERO)
    }
}

/// A rendered view plus the intermediate state its backward pass reuses.
#[derive(Clone, Debug)]
pub struct Render {
    pub width: u32,
    pub height: u32,
    pub camera: Camera,
    /// The projection the pixels were rendered with (the backward pass reuses it).
    pub projection: ProjectionCamera,
    pub options: RenderOptions,
    /// The background image's pixels of this render (its region), when it has one.
    pub background_pixels: Option<Arc<[f32]>>,
    pub sh_degree: u32,
    /// Row-major RGB (background included), alpha, accumulated depth (see [`raster::RasterOutput`]).
    pub image: raster::RasterOutput,
    pub projected: Vec<Option<project::Projected>>,
    pub bins: raster::TileBins,
}

impl Render {
    /// Expected depth of the visible surface per pixel (accumulated depth / alpha; 0 where empty).
    pub fn expected_depth(&self) -> Vec<f32> {
        self.image.expected_depth()
    }

    /// Number of Gaussians that survived culling.
    pub fn visible_count(&self) -> usize {
        self.projected.iter().filter(|p| p.is_some()).count()
    }

    /// The colour image as 8-bit RGB.
    pub fn to_rgb8(&self) -> image::RgbImage {
        self.image.to_rgb8(self.width, self.height)
    }
}

/// Gradients of a loss with respect to everything the render depends on.
#[derive(Clone, Debug)]
pub struct Gradients {
    /// Same layout as the rendered [`GaussianSet`]; every group filled.
    pub params: GaussianSet,
    pub background: Vec3,
    /// Per Gaussian, |dL/d(mean2d)| in NDC units (pixel gradient times half the
    /// image size), the statistic 3DGS densification accumulates; 0 if culled.
    pub mean2d_grad_norm: Vec<f32>,
    /// Whether the Gaussian was visible in this view (counted for densification).
    pub visible: Vec<bool>,
    /// Per Gaussian, 3 sigma of its projected major axis in pixels (the screen
    /// size densification prunes on); 0 if culled.
    pub radius: Vec<f32>,
}

pub(crate) fn active_degree(gs: &GaussianSet, opts: &RenderOptions) -> u32 {
    opts.sh_degree.map_or(gs.sh_degree, |d| d.min(gs.sh_degree))
}

/// Render `gs` from `camera`.
pub fn render(gs: &GaussianSet, camera: &Camera, options: &RenderOptions) -> Render {
    render_region(gs, camera, [0, 0, camera.width(), camera.height()], options)
}

/// Render the pixels [x0, x1) x [y0, y1) of `camera`'s image (`region` = [x0, y0,
/// x1, y1], inside the image): the values `render` gives those pixels, at the
/// cost of the region. The result is the region's image (its `camera` the
/// region's), and its backward pass gives the gradients of a loss on those pixels.
pub fn render_region(gs: &GaussianSet, camera: &Camera, region: [u32; 4], options: &RenderOptions) -> Render {
    let [x0, y0, x1, y1] = region;
    assert!(
        x0 < x1 && y0 < y1 && x1 <= camera.width() && y1 <= camera.height(),
        "region {region:?} outside the {}x{} image",
        camera.width(),
        camera.height()
    );
    let projection = ProjectionCamera::new(camera).region(region);
    let deg = active_degree(gs, options);
    let projected: Vec<_> =
        (0..gs.len()).into_par_iter().map(|i| project::project_one(gs, i, &projection, deg)).collect();
    let (w, h) = (x1 - x0, y1 - y0);
    let bins = raster::bin_tiles(&projected, w, h);
    let background_pixels = options.background_image.as_ref().map(|img| {
        assert_eq!(
            img.len(),
            3 * (camera.width() * camera.height()) as usize,
            "background image must match the camera"
        );
        if region == [0, 0, camera.width(), camera.height()] {
            img.clone()
        } else {
            crop(img, camera.width(), 3, region).into()
        }
    });
    let image = raster::rasterize(&bins, w, h, background_of(options, background_pixels.as_deref()));
    let mut camera = *camera;
    camera.intrinsics.width = w;
    camera.intrinsics.height = h;
    camera.intrinsics.cx -= x0 as f32;
    camera.intrinsics.cy -= y0 as f32;
    Render {
        width: w,
        height: h,
        camera,
        projection,
        options: options.clone(),
        background_pixels,
        sh_degree: deg,
        image,
        projected,
        bins,
    }
}

fn background_of<'a>(options: &RenderOptions, pixels: Option<&'a [f32]>) -> raster::Background<'a> {
    match pixels {
        Some(p) => raster::Background::Image(p),
        None => raster::Background::Uniform(options.background),
    }
}

/// The pixels `region` = [x0, y0, x1, y1) of a row-major image `width` pixels
/// wide with `channels` values per pixel.
pub fn crop(image: &[f32], width: u32, channels: usize, region: [u32; 4]) -> Vec<f32> {
    region_rows(image, width, channels, region).flatten().copied().collect()
}

/// The rows of `region` in such an image, top to bottom.
pub fn region_rows(image: &[f32], width: u32, channels: usize, region: [u32; 4]) -> impl Iterator<Item = &[f32]> {
    let [x0, y0, x1, y1] = region.map(|v| v as usize);
    let w = width as usize;
    (y0..y1).map(move |y| &image[channels * (y * w + x0)..channels * (y * w + x1)])
}

/// Backward pass: `grad_color` is dL/d(RGB) (row-major, 3 per pixel); optional
/// dL/d(alpha) and dL/d(accumulated depth) per pixel.
pub fn backward(
    gs: &GaussianSet,
    fwd: &Render,
    grad_color: &[f32],
    grad_alpha: Option<&[f32]>,
    grad_depth: Option<&[f32]>,
) -> Gradients {
    let (w, h) = (fwd.width, fwd.height);
    assert_eq!(grad_color.len(), (3 * w * h) as usize, "colour gradient must match the image");
    let (proj_grads, bg) = raster::rasterize_backward(
        &fwd.bins,
        w,
        h,
        background_of(&fwd.options, fwd.background_pixels.as_deref()),
        &fwd.image,
        grad_color,
        grad_alpha,
        grad_depth,
    );
    let pc = fwd.projection;
    let n = gs.len();
    let (raw, sh_rest) = project::project_backward_all(gs, &fwd.projected, &pc, fwd.sh_degree, &proj_grads);

    let mut params = GaussianSet::new(gs.sh_degree);
    params.sh_rest = sh_rest;
    params.means = vec![0.0; 3 * n];
    params.log_scales = vec![0.0; 3 * n];
    params.rotations = vec![0.0; 4 * n];
    params.opacity_logits = vec![0.0; n];
    params.sh_dc = vec![0.0; 3 * n];
    let mut norms = vec![0.0; n];
    let mut visible = vec![false; n];
    let mut radius = vec![0.0; n];
    let ndc_scale = glam::Vec2::new(0.5 * w as f32, 0.5 * h as f32);
    for (i, g) in raw.into_iter().enumerate() {
        let Some(g) = g else { continue };
        visible[i] = true;
        params.means[3 * i..3 * i + 3].copy_from_slice(&g.mean.to_array());
        params.log_scales[3 * i..3 * i + 3].copy_from_slice(&g.log_scale.to_array());
        params.rotations[4 * i..4 * i + 4].copy_from_slice(&g.rotation);
        params.opacity_logits[i] = g.opacity_logit;
        params.sh_dc[3 * i..3 * i + 3].copy_from_slice(&g.sh_dc.to_array());
        norms[i] = (proj_grads[i].mean2d * ndc_scale).length();
        radius[i] = fwd.projected[i].as_ref().map_or(0.0, |p| p.radius);
    }
    Gradients { params, background: bg, mean2d_grad_norm: norms, visible, radius }
}

#[cfg(test)]
mod tests;
