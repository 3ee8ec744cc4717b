//! A CPU render kept so that it can be rendered again, with a few of its
//! Gaussians changed, at the cost of the pixels they reach. A pixel's value
//! depends only on the Gaussians whose pixel boxes hold it, in depth order (the
//! compositing applies each Gaussian to its exact box, in the whole image's
//! tiles), so compositing again the tiles the changed Gaussians reach, where
//! they were or where they are now, and keeping every other pixel gives the
//! image a whole render of the changed set gives, to the bit.

use std::sync::Arc;

use rayon::prelude::*;

use super::project::{project_one, Projected, ProjectionCamera};
use super::raster::{self, TILE};
use super::{background_of, render_sets, RenderOptions};
use crate::camera::Camera;
use crate::splat::GaussianSet;

/// A whole render of a Gaussian set: every Gaussian's projection and the colour image.
#[derive(Clone, Debug)]
pub struct Repaintable {
    projection: ProjectionCamera,
    sh_degree: u32,
    options: RenderOptions,
    background_pixels: Option<Arc<[f32]>>,
    projected: Vec<Option<Projected>>,
    color: Vec<f32>,
}

/// What changing some rows of a [`Repaintable`]'s set changes: the rows' new
/// projections and the new colours of the pixels composited again.
#[derive(Clone, Debug)]
pub struct Repaint {
    rows: Vec<usize>,
    projected: Vec<Option<Projected>>,
    /// Row-major indices of the pixels composited again (every pixel that can
    /// have changed, and some that did not), and their colours.
    pub pixels: Vec<usize>,
    pub colors: Vec<[f32; 3]>,
}

impl Repaintable {
    /// Render `gs` from `camera`, the whole image (the CPU rasterizer).
    pub fn new(gs: &GaussianSet, camera: &Camera, options: &RenderOptions) -> Self {
        let r = render_sets(&[gs], camera, [0, 0, camera.width(), camera.height()], options);
        Self {
            projection: r.projection,
            sh_degree: r.sh_degree,
            options: r.options,
            background_pixels: r.background_pixels,
            projected: r.projected,
            color: r.image.color,
        }
    }

    /// Row-major RGB, background included.
    pub fn color(&self) -> &[f32] {
        &self.color
    }

    /// The render with rows `rows` (ascending) of the set replaced by the rows
    /// of `replacement`, in order; the set's other rows as they were.
    pub fn repaint(&self, rows: &[usize], replacement: &GaussianSet) -> Repaint {
        assert_eq!(rows.len(), replacement.len(), "one replacement row per changed row");
        assert!(rows.windows(2).all(|w| w[0] < w[1]), "changed rows ascending");
        let projected: Vec<Option<Projected>> = (0..rows.len())
            .into_par_iter()
            .map(|j| project_one(replacement, j, &self.projection, self.sh_degree))
            .collect();
        let (width, height) = (self.projection.width, self.projection.height);
        let tiles_x = width.div_ceil(TILE);
        let mut touched = vec![false; (tiles_x * height.div_ceil(TILE)) as usize];
        for p in rows.iter().map(|&i| &self.projected[i]).chain(&projected).flatten() {
            raster::tiles_reached(&p.bbox, tiles_x).for_each(|t| touched[t] = true);
        }
        let tiles: Vec<usize> = (0..touched.len()).filter(|&t| touched[t]).collect();
        let (mut pixels, mut colors) = (Vec::new(), Vec::new());
        if !tiles.is_empty() {
            let now = |i: usize| match rows.binary_search(&i) {
                Ok(j) => projected[j].as_ref(),
                Err(_) => self.projected[i].as_ref(),
            };
            let by_depth = (0..self.projected.len())
                .into_par_iter()
                .filter_map(|i| {
                    let p = now(i)?;
                    raster::tiles_reached(&p.bbox, tiles_x)
                        .any(|t| touched[t])
                        .then(|| raster::depth_key(p.depth, i as u32))
                })
                .collect();
            let visible = |i: u32| now(i as usize).expect("binned Gaussians are visible");
            let bins = raster::bin_sorted(by_depth, visible, self.projected.len(), width, height, |t| touched[t]);
            let background = background_of(&self.options, self.background_pixels.as_deref());
            raster::rasterize_tiles(&bins, &tiles, width, height, background, |o, rgb| {
                pixels.push(o);
                colors.push(rgb);
            });
        }
        Repaint { rows: rows.to_vec(), projected, pixels, colors }
    }

    /// Take `repaint` (one of this render's) as the render.
    pub fn apply(&mut self, repaint: &Repaint) {
        for (&i, p) in repaint.rows.iter().zip(&repaint.projected) {
            self.projected[i] = *p;
        }
        for (&o, rgb) in repaint.pixels.iter().zip(&repaint.colors) {
            self.color[3 * o..3 * o + 3].copy_from_slice(rgb);
        }
    }
}
