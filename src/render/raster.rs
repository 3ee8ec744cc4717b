//! Tile binning and front-to-back alpha compositing on the CPU, forward and
//! backward. Each 16x16 tile is one unit of rayon work; inside a tile the loop
//! runs Gaussian-outer, pixel-inner over the Gaussian's exact pixel box, so a
//! Gaussian only touches the pixels it can reach.

use glam::{Vec2, Vec3};
use rayon::prelude::*;

use super::project::{Projected, ProjectedGrad, ALPHA_MIN};

pub const TILE: u32 = 16;
const TILE_PIXELS: usize = (TILE * TILE) as usize;
/// Compositing stops once transmittance would fall below this.
pub const TRANSMITTANCE_MIN: f32 = 1e-4;
/// Alpha is clamped here so (1 - alpha) never vanishes in the backward division.
pub const ALPHA_MAX: f32 = 0.99;

/// Per-tile lists of Gaussian indices, each in front-to-back order.
#[derive(Clone, Debug, Default)]
pub struct TileBins {
    pub tiles_x: u32,
    pub tiles_y: u32,
    /// `entries[offsets[t]..offsets[t + 1]]` are tile t's Gaussians.
    pub offsets: Vec<u32>,
    pub entries: Vec<u32>,
}

impl TileBins {
    pub fn tile(&self, t: usize) -> &[u32] {
        &self.entries[self.offsets[t] as usize..self.offsets[t + 1] as usize]
    }

    fn tile_count(&self) -> usize {
        (self.tiles_x * self.tiles_y) as usize
    }

    /// Pixel rectangle [x0, x1) x [y0, y1) of tile t.
    fn tile_rect(&self, t: usize, width: u32, height: u32) -> [u32; 4] {
        let tx = t as u32 % self.tiles_x;
        let ty = t as u32 / self.tiles_x;
        [tx * TILE, ty * TILE, ((tx + 1) * TILE).min(width), ((ty + 1) * TILE).min(height)]
    }
}

/// Bin visible Gaussians (`proj[i]` is Some) into tiles, front to back.
pub fn bin_tiles(proj: &[Option<Projected>], width: u32, height: u32) -> TileBins {
    let tiles_x = width.div_ceil(TILE);
    let tiles_y = height.div_ceil(TILE);
    let mut order: Vec<(f32, u32)> =
        proj.iter().enumerate().filter_map(|(i, p)| p.as_ref().map(|p| (p.depth, i as u32))).collect();
    // Unique keys (depth, index): the order is deterministic whatever the sort does.
    order.par_sort_unstable_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));

    let ntiles = (tiles_x * tiles_y) as usize;
    let mut counts = vec![0u32; ntiles + 1];
    let tile_span = |p: &Projected| (p.bbox[0] / TILE, p.bbox[1] / TILE, p.bbox[2] / TILE, p.bbox[3] / TILE);
    for &(_, i) in &order {
        let (tx0, ty0, tx1, ty1) = tile_span(proj[i as usize].as_ref().expect("visible"));
        for ty in ty0..=ty1 {
            for tx in tx0..=tx1 {
                counts[(ty * tiles_x + tx) as usize + 1] += 1;
            }
        }
    }
    for t in 0..ntiles {
        counts[t + 1] += counts[t];
    }
    let offsets = counts;
    let mut fill = offsets.clone();
    let mut entries = vec![0u32; offsets[ntiles] as usize];
    for &(_, i) in &order {
        let (tx0, ty0, tx1, ty1) = tile_span(proj[i as usize].as_ref().expect("visible"));
        for ty in ty0..=ty1 {
            for tx in tx0..=tx1 {
                let t = (ty * tiles_x + tx) as usize;
                entries[fill[t] as usize] = i;
                fill[t] += 1;
            }
        }
    }
    TileBins { tiles_x, tiles_y, offsets, entries }
}

/// Composited images plus what the backward pass needs.
#[derive(Clone, Debug, Default)]
pub struct RasterOutput {
    /// Row-major RGB, background included.
    pub color: Vec<f32>,
    /// 1 - final transmittance.
    pub alpha: Vec<f32>,
    /// Accumulated depth sum_i w_i z_i (divide by alpha for the expected depth of the hit).
    pub depth: Vec<f32>,
    /// Final transmittance per pixel.
    pub final_t: Vec<f32>,
    /// Per pixel: one past the position (in its tile's list) of the last Gaussian composited.
    pub last: Vec<u32>,
}

struct TileResult {
    rect: [u32; 4],
    color: [Vec3; TILE_PIXELS],
    depth: [f32; TILE_PIXELS],
    t: [f32; TILE_PIXELS],
    last: [u32; TILE_PIXELS],
}

/// The pixel range of Gaussian box `bbox` inside tile rect `r` (exclusive ends); None if empty.
#[inline]
fn clip(bbox: &[u32; 4], r: &[u32; 4]) -> Option<(u32, u32, u32, u32)> {
    let x0 = bbox[0].max(r[0]);
    let y0 = bbox[1].max(r[1]);
    let x1 = (bbox[2] + 1).min(r[2]);
    let y1 = (bbox[3] + 1).min(r[3]);
    (x0 < x1 && y0 < y1).then_some((x0, y0, x1, y1))
}

/// alpha of Gaussian `p` at pixel (px, py) before the skip test, or None when it is skipped.
#[inline(always)]
fn alpha_at(p: &Projected, px: u32, py: u32) -> Option<(f32, f32, f32, f32)> {
    let dx = p.mean2d.x - (px as f32 + 0.5);
    let dy = p.mean2d.y - (py as f32 + 0.5);
    let power = -0.5 * (p.conic[0] * dx * dx + p.conic[2] * dy * dy) - p.conic[1] * dx * dy;
    if power > 0.0 {
        return None;
    }
    let g = power.exp();
    let a = (p.opacity * g).min(ALPHA_MAX);
    (a >= ALPHA_MIN).then_some((a, g, dx, dy))
}

/// Forward compositing over all tiles.
pub fn rasterize(proj: &[Option<Projected>], bins: &TileBins, width: u32, height: u32, background: Vec3) -> RasterOutput {
    let results: Vec<TileResult> = (0..bins.tile_count())
        .into_par_iter()
        .map(|t| {
            let rect = bins.tile_rect(t, width, height);
            let mut res = TileResult {
                rect,
                color: [Vec3::ZERO; TILE_PIXELS],
                depth: [0.0; TILE_PIXELS],
                t: [1.0; TILE_PIXELS],
                last: [0; TILE_PIXELS],
            };
            let npix = ((rect[2] - rect[0]) * (rect[3] - rect[1])) as usize;
            let mut done = [false; TILE_PIXELS];
            let mut ndone = 0usize;
            for (k, &gi) in bins.tile(t).iter().enumerate() {
                let p = proj[gi as usize].as_ref().expect("binned Gaussians are visible");
                let Some((x0, y0, x1, y1)) = clip(&p.bbox, &rect) else { continue };
                for py in y0..y1 {
                    let row = ((py - rect[1]) * TILE) as usize;
                    for px in x0..x1 {
                        let l = row + (px - rect[0]) as usize;
                        if done[l] {
                            continue;
                        }
                        let Some((a, _, _, _)) = alpha_at(p, px, py) else { continue };
                        let t_now = res.t[l];
                        let t_next = t_now * (1.0 - a);
                        if t_next < TRANSMITTANCE_MIN {
                            done[l] = true;
                            ndone += 1;
                            continue;
                        }
                        let w = a * t_now;
                        res.color[l] += p.color * w;
                        res.depth[l] += p.depth * w;
                        res.t[l] = t_next;
                        res.last[l] = k as u32 + 1;
                    }
                }
                if ndone == npix {
                    break;
                }
            }
            res
        })
        .collect();

    let n = (width * height) as usize;
    let mut out = RasterOutput {
        color: vec![0.0; 3 * n],
        alpha: vec![0.0; n],
        depth: vec![0.0; n],
        final_t: vec![1.0; n],
        last: vec![0; n],
    };
    for res in &results {
        let r = res.rect;
        for py in r[1]..r[3] {
            for px in r[0]..r[2] {
                let l = ((py - r[1]) * TILE + (px - r[0])) as usize;
                let o = (py * width + px) as usize;
                let c = res.color[l] + background * res.t[l];
                out.color[3 * o..3 * o + 3].copy_from_slice(&c.to_array());
                out.alpha[o] = 1.0 - res.t[l];
                out.depth[o] = res.depth[l];
                out.final_t[o] = res.t[l];
                out.last[o] = res.last[l];
            }
        }
    }
    out
}

/// Backward compositing: per-Gaussian gradients of the projected quantities and
/// the background gradient, from dL/d(colour, alpha, depth) images.
#[allow(clippy::too_many_arguments)]
pub fn rasterize_backward(
    proj: &[Option<Projected>],
    bins: &TileBins,
    width: u32,
    height: u32,
    background: Vec3,
    fwd: &RasterOutput,
    grad_color: &[f32],
    grad_alpha: Option<&[f32]>,
    grad_depth: Option<&[f32]>,
) -> (Vec<ProjectedGrad>, Vec3) {
    // One gradient slot per tile entry, so tiles write disjoint memory and the
    // per-Gaussian sum below runs in a fixed order (reproducible results).
    let mut entry_grads = vec![ProjectedGrad::default(); bins.entries.len()];
    let mut slices: Vec<&mut [ProjectedGrad]> = Vec::with_capacity(bins.tile_count());
    let mut rest: &mut [ProjectedGrad] = &mut entry_grads;
    for t in 0..bins.tile_count() {
        let len = (bins.offsets[t + 1] - bins.offsets[t]) as usize;
        let (head, tail) = rest.split_at_mut(len);
        slices.push(head);
        rest = tail;
    }
    let bg_grads: Vec<Vec3> = slices
        .into_par_iter()
        .enumerate()
        .map(|(t, grads)| {
            let rect = bins.tile_rect(t, width, height);
            let list = bins.tile(t);
            // Per-pixel state, back to front.
            let mut t_cur = [0.0f32; TILE_PIXELS];
            let mut behind_c = [Vec3::ZERO; TILE_PIXELS];
            let mut behind_d = [0.0f32; TILE_PIXELS];
            let mut last = [0u32; TILE_PIXELS];
            let mut gc = [Vec3::ZERO; TILE_PIXELS];
            let mut ga = [0.0f32; TILE_PIXELS];
            let mut gd = [0.0f32; TILE_PIXELS];
            let mut t_final = [0.0f32; TILE_PIXELS];
            let mut bg_grad = Vec3::ZERO;
            let mut max_last = 0u32;
            for py in rect[1]..rect[3] {
                for px in rect[0]..rect[2] {
                    let l = ((py - rect[1]) * TILE + (px - rect[0])) as usize;
                    let o = (py * width + px) as usize;
                    t_cur[l] = fwd.final_t[o];
                    t_final[l] = fwd.final_t[o];
                    behind_c[l] = background * fwd.final_t[o];
                    last[l] = fwd.last[o];
                    max_last = max_last.max(last[l]);
                    gc[l] = Vec3::from_slice(&grad_color[3 * o..3 * o + 3]);
                    ga[l] = grad_alpha.map_or(0.0, |g| g[o]);
                    gd[l] = grad_depth.map_or(0.0, |g| g[o]);
                    bg_grad += gc[l] * fwd.final_t[o];
                }
            }
            for k in (0..max_last as usize).rev() {
                let p = proj[list[k] as usize].as_ref().expect("binned Gaussians are visible");
                let Some((x0, y0, x1, y1)) = clip(&p.bbox, &rect) else { continue };
                let mut g = ProjectedGrad::default();
                for py in y0..y1 {
                    let row = ((py - rect[1]) * TILE) as usize;
                    for px in x0..x1 {
                        let l = row + (px - rect[0]) as usize;
                        if k as u32 >= last[l] {
                            continue;
                        }
                        let Some((a, gauss, dx, dy)) = alpha_at(p, px, py) else { continue };
                        let one_minus = 1.0 - a;
                        let t_before = t_cur[l] / one_minus;
                        let w = a * t_before;
                        // d(colour)/d(alpha) = c T - (what lies behind) / (1 - alpha); same for depth.
                        let dl_da = gc[l].dot(p.color * t_before - behind_c[l] / one_minus)
                            + gd[l] * (p.depth * t_before - behind_d[l] / one_minus)
                            + ga[l] * t_final[l] / one_minus;
                        g.color += gc[l] * w;
                        g.depth += gd[l] * w;
                        behind_c[l] += p.color * w;
                        behind_d[l] += p.depth * w;
                        t_cur[l] = t_before;
                        if p.opacity * gauss > ALPHA_MAX {
                            continue; // clamped: no gradient to opacity or shape
                        }
                        g.opacity += dl_da * gauss;
                        let dl_dpower = dl_da * a;
                        g.mean2d += dl_dpower * Vec2::new(-p.conic[0] * dx - p.conic[1] * dy, -p.conic[2] * dy - p.conic[1] * dx);
                        g.conic[0] += dl_dpower * (-0.5 * dx * dx);
                        g.conic[1] += dl_dpower * (-dx * dy);
                        g.conic[2] += dl_dpower * (-0.5 * dy * dy);
                    }
                }
                grads[k] = g;
            }
            bg_grad
        })
        .collect();

    let mut per_gaussian = vec![ProjectedGrad::default(); proj.len()];
    for (&gi, g) in bins.entries.iter().zip(&entry_grads) {
        let acc = &mut per_gaussian[gi as usize];
        acc.mean2d += g.mean2d;
        for c in 0..3 {
            acc.conic[c] += g.conic[c];
        }
        acc.color += g.color;
        acc.opacity += g.opacity;
        acc.depth += g.depth;
    }
    let bg = bg_grads.iter().fold(Vec3::ZERO, |a, b| a + *b);
    (per_gaussian, bg)
}
