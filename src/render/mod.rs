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
mod repaint;
pub mod sh;

pub use backend::{Backend, BackendChoice, View};
use project::ProjectionCamera;
pub use repaint::{Repaint, Repaintable};

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

impl Gradients {
    /// Zero the rows `wanted` does not mark and count them not visible: what
    /// [`backward_wanted`] leaves in them (a backend that computes every row
    /// applies this after).
    pub fn keep_wanted(&mut self, wanted: &[bool]) {
        for group in crate::splat::ParamGroup::ALL {
            let width = self.params.width(group);
            let values = self.params.group_mut(group);
            for (i, _) in wanted.iter().enumerate().filter(|(_, w)| !**w) {
                values[width * i..width * (i + 1)].fill(0.0);
            }
        }
        for (i, _) in wanted.iter().enumerate().filter(|(_, w)| !**w) {
            (self.mean2d_grad_norm[i], self.visible[i], self.radius[i]) = (0.0, false, 0.0);
        }
    }
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
    render_sets(&[gs], camera, region, options)
}

/// What both backends settle before rendering `sets` (one scene, the sets one
/// after another) on the pixels `region` of `camera`'s image.
pub(crate) struct Prepared {
    pub projection: ProjectionCamera,
    /// The region's camera.
    pub camera: Camera,
    pub sh_degree: u32,
    /// The background image's pixels of the region, when there is one.
    pub background_pixels: Option<Arc<[f32]>>,
}

impl Prepared {
    pub(crate) fn new(sets: &[&GaussianSet], camera: &Camera, region: [u32; 4], options: &RenderOptions) -> Self {
        let [x0, y0, x1, y1] = region;
        assert!(
            x0 < x1 && y0 < y1 && x1 <= camera.width() && y1 <= camera.height(),
            "region {region:?} outside the {}x{} image",
            camera.width(),
            camera.height()
        );
        let stored = sets.first().expect("at least one Gaussian set").sh_degree;
        assert!(sets.iter().all(|s| s.sh_degree == stored), "the sets rendered together share one SH degree");
        let sh_degree = options.sh_degree.map_or(stored, |d| d.min(stored));
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
        let mut region_camera = *camera;
        region_camera.intrinsics.width = x1 - x0;
        region_camera.intrinsics.height = y1 - y0;
        region_camera.intrinsics.cx -= x0 as f32;
        region_camera.intrinsics.cy -= y0 as f32;
        Self {
            projection: ProjectionCamera::new(camera).region(region),
            camera: region_camera,
            sh_degree,
            background_pixels,
        }
    }
}

/// Render several Gaussian sets as one scene (the sets share an SH degree) on
/// the pixels `region` of `camera`'s image, without copying them into one set:
/// rendered Gaussian `o_k + i` is row i of set k, o_k the rows of the sets before
/// it. [`backward_sets`] gives each set its gradients.
pub fn render_sets(sets: &[&GaussianSet], camera: &Camera, region: [u32; 4], options: &RenderOptions) -> Render {
    let prep = Prepared::new(sets, camera, region, options);
    let (projection, deg) = (prep.projection, prep.sh_degree);
    let mut projected = Vec::with_capacity(sets.iter().map(|s| s.len()).sum());
    for gs in sets {
        projected.par_extend((0..gs.len()).into_par_iter().map(|i| project::project_one(gs, i, &projection, deg)));
    }
    let (w, h) = (projection.width, projection.height);
    let bins = raster::bin_tiles(&projected, w, h);
    let image = raster::rasterize(&bins, w, h, background_of(options, prep.background_pixels.as_deref()));
    Render {
        width: w,
        height: h,
        camera: prep.camera,
        projection,
        options: options.clone(),
        background_pixels: prep.background_pixels,
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
fn region_rows(image: &[f32], width: u32, channels: usize, region: [u32; 4]) -> impl Iterator<Item = &[f32]> {
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
    backward_sets(&[gs], fwd, grad_color, grad_alpha, grad_depth).pop().expect("one set")
}

/// Backward pass of a [`render_sets`] render: one [`Gradients`] per set, in
/// order (the background gradient is the whole render's, in each).
pub fn backward_sets(
    sets: &[&GaussianSet],
    fwd: &Render,
    grad_color: &[f32],
    grad_alpha: Option<&[f32]>,
    grad_depth: Option<&[f32]>,
) -> Vec<Gradients> {
    backward_sets_of(
        sets,
        fwd,
        &raster::TileGrads { color: grad_color, alpha: grad_alpha, depth: grad_depth, wanted: None },
    )
}

/// [`backward`] computing only the gradients of the Gaussians `wanted` marks:
/// the others' rows are zero and not visible ([`Gradients::keep_wanted`]), the
/// wanted ones' as a full pass gives them, to the bit, for less work (a tracker
/// fitting moving parts over a base that stands still).
pub fn backward_wanted(
    gs: &GaussianSet,
    fwd: &Render,
    grad_color: &[f32],
    grad_alpha: Option<&[f32]>,
    grad_depth: Option<&[f32]>,
    wanted: &[bool],
) -> Gradients {
    assert_eq!(wanted.len(), gs.len(), "one flag per Gaussian");
    let grads = raster::TileGrads { color: grad_color, alpha: grad_alpha, depth: grad_depth, wanted: Some(wanted) };
    backward_sets_of(&[gs], fwd, &grads).pop().expect("one set")
}

/// [`backward_sets`] from the image-space gradients `g` (`g.wanted`, when
/// given, over the sets one after another).
fn backward_sets_of(sets: &[&GaussianSet], fwd: &Render, g: &raster::TileGrads) -> Vec<Gradients> {
    let (w, h) = (fwd.width, fwd.height);
    assert_eq!(g.color.len(), (3 * w * h) as usize, "colour gradient must match the image");
    assert_eq!(sets.iter().map(|s| s.len()).sum::<usize>(), fwd.projected.len(), "the rendered sets");
    let (proj_grads, bg) = raster::rasterize_backward_with(
        lanes::Kernels::active(),
        &fwd.bins,
        w,
        h,
        background_of(&fwd.options, fwd.background_pixels.as_deref()),
        &fwd.image,
        g,
    );
    let ndc_scale = glam::Vec2::new(0.5 * w as f32, 0.5 * h as f32);
    let mut first = 0;
    sets.iter()
        .map(|gs| {
            let rows = first..first + gs.len();
            first = rows.end;
            let (projected, grads) = (&fwd.projected[rows.clone()], &proj_grads[rows.clone()]);
            let wanted = g.wanted.map(|all| &all[rows.clone()]);
            let (raw, sh_rest) =
                project::project_backward_all(gs, projected, &fwd.projection, fwd.sh_degree, grads, wanted);
            let n = gs.len();
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
            for (i, g) in raw.into_iter().enumerate() {
                let (Some(g), Some(p)) = (g, &projected[i]) else { continue };
                visible[i] = true;
                params.means[3 * i..3 * i + 3].copy_from_slice(&g.mean.to_array());
                params.log_scales[3 * i..3 * i + 3].copy_from_slice(&g.log_scale.to_array());
                params.rotations[4 * i..4 * i + 4].copy_from_slice(&g.rotation);
                params.opacity_logits[i] = g.opacity_logit;
                params.sh_dc[3 * i..3 * i + 3].copy_from_slice(&g.sh_dc.to_array());
                norms[i] = (grads[i].mean2d * ndc_scale).length();
                radius[i] = p.radius;
            }
            Gradients { params, background: bg, mean2d_grad_norm: norms, visible, radius }
        })
        .collect()
}

#[cfg(test)]
mod tests;
