//! Tile binning and front-to-back alpha compositing on the CPU, forward and
//! backward. Each 16x16 tile is one unit of rayon work; inside a tile the loop
//! runs Gaussian-outer, pixel-inner over the Gaussian's exact pixel box, so a
//! Gaussian only touches the pixels it can reach.

use glam::{Vec2, Vec3};
use rayon::prelude::*;
use wide::{f32x8, CmpGe, CmpGt, CmpLe, CmpLt};

/// SIMD lanes: adjacent pixels of one tile row.
type Lanes = f32x8;
const LANES: u32 = 8;

use super::project::{Projected, ProjectedGrad, ALPHA_MIN};

pub const TILE: u32 = 16;
const TILE_PIXELS: usize = (TILE * TILE) as usize;
/// Compositing stops once transmittance would fall below this.
pub const TRANSMITTANCE_MIN: f32 = 1e-4;
/// Alpha is clamped here so (1 - alpha) never vanishes in the backward division.
pub const ALPHA_MAX: f32 = 0.99;

/// What compositing reads of one visible Gaussian.
#[derive(Clone, Copy, Debug)]
pub struct Splat {
    mean: Vec2,
    conic: [f32; 3],
    opacity: f32,
    color: Vec3,
    depth: f32,
    bbox: [u32; 4],
    span: [f32; 3],
}

impl Splat {
    fn new(p: &Projected) -> Self {
        let Projected { mean2d, conic, depth, color, opacity, bbox, span, .. } = *p;
        Self { mean: mean2d, conic, opacity, color, depth, bbox, span }
    }
}

/// The visible Gaussians in front-to-back order and per-tile lists into them.
#[derive(Clone, Debug, Default)]
pub struct TileBins {
    pub tiles_x: u32,
    pub tiles_y: u32,
    /// Number of Gaussians rendered (visible or not): the length of gradient outputs.
    pub gaussian_count: usize,
    /// `splats[r]` is the r-th nearest visible Gaussian, `order[r]` its index in the set.
    /// Tile lists hold these ranks, so each list reads `splats` front to back.
    pub order: Vec<u32>,
    splats: Vec<Splat>,
    /// `entries[offsets[t]..offsets[t + 1]]` are tile t's ranks, ascending.
    pub offsets: Vec<u32>,
    pub entries: Vec<u32>,
}

impl TileBins {
    fn tile(&self, t: usize) -> &[u32] {
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

/// Sort visible Gaussians (`proj[i]` is Some) front to back and bin them into tiles.
pub fn bin_tiles(proj: &[Option<Projected>], width: u32, height: u32) -> TileBins {
    let tiles_x = width.div_ceil(TILE);
    let tiles_y = height.div_ceil(TILE);
    let mut by_depth: Vec<(f32, u32)> =
        proj.iter().enumerate().filter_map(|(i, p)| p.as_ref().map(|p| (p.depth, i as u32))).collect();
    // Unique keys (depth, index): the order is deterministic whatever the sort does.
    by_depth.par_sort_unstable_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    let order: Vec<u32> = by_depth.iter().map(|&(_, i)| i).collect();
    let splats: Vec<Splat> = order
        .par_iter()
        .map(|&i| Splat::new(proj[i as usize].as_ref().expect("sorted Gaussians are visible")))
        .collect();

    let ntiles = (tiles_x * tiles_y) as usize;
    let mut counts = vec![0u32; ntiles + 1];
    let tile_span = |s: &Splat| (s.bbox[0] / TILE, s.bbox[1] / TILE, s.bbox[2] / TILE, s.bbox[3] / TILE);
    for s in &splats {
        let (tx0, ty0, tx1, ty1) = tile_span(s);
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
    for (rank, s) in splats.iter().enumerate() {
        let (tx0, ty0, tx1, ty1) = tile_span(s);
        for ty in ty0..=ty1 {
            for tx in tx0..=tx1 {
                let t = (ty * tiles_x + tx) as usize;
                entries[fill[t] as usize] = rank as u32;
                fill[t] += 1;
            }
        }
    }
    TileBins { tiles_x, tiles_y, gaussian_count: proj.len(), order, splats, offsets, entries }
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

/// The rows of Gaussian box `bbox` inside tile rect `r` (exclusive end); None if empty.
#[inline]
fn clip_rows(bbox: &[u32; 4], r: &[u32; 4]) -> Option<(u32, u32)> {
    let y0 = bbox[1].max(r[1]);
    let y1 = (bbox[3] + 1).min(r[3]);
    (bbox[0] < r[2] && bbox[2] >= r[0] && y0 < y1).then_some((y0, y1))
}

const LANE_IDX: Lanes = Lanes::new([0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0]);

/// Up to eight consecutive tile rows of one Gaussian: for each row (lane) the
/// tile-local pixels [lo, hi) it can reach, i.e. the row's chord of the
/// conservative ellipse power >= power_cut. Bit j of `rows` is set when row
/// `row0 + j` has a non-empty chord.
struct ChordBatch {
    row0: u32,
    rows: u32,
    lo: [f32; LANES as usize],
    hi: [f32; LANES as usize],
}

impl ChordBatch {
    /// Rows `row0 + j` for the set bits j of `mask`, with their chords.
    #[inline(always)]
    fn each(&self, mut mask: u32, mut f: impl FnMut(u32, f32, f32)) {
        while mask != 0 {
            let j = mask.trailing_zeros() as usize;
            mask &= mask - 1;
            f(self.row0 + j as u32, self.lo[j], self.hi[j]);
        }
    }
}

/// Call `f` with the chord batches of Gaussian `p` in tile rect `r`, top to bottom.
#[inline(always)]
fn for_each_chord_batch(p: &Splat, r: &[u32; 4], mut f: impl FnMut(&ChordBatch, Lanes, Lanes)) {
    let Some((y0, y1)) = clip_rows(&p.bbox, r) else { return };
    let [s0, s1, s2] = p.span;
    let x0 = Lanes::splat(r[0] as f32);
    let x1 = Lanes::splat(r[2] as f32);
    let mut y = y0;
    while y < y1 {
        let dy = Lanes::splat(p.mean.y) - ((Lanes::splat(y as f32) + LANE_IDX) + Lanes::splat(0.5));
        let disc = Lanes::splat(s1) * dy * dy + Lanes::splat(s2);
        let root = disc.fast_max(Lanes::ZERO).sqrt();
        let centre = Lanes::splat(-s0) * dy;
        // dx = mean.x - (px + 0.5) ranges over centre -+ root; lo = ceil, hi = floor + 1
        // (hi + 1 >= 0 after the clamp, so rounding down is floor).
        let mx = Lanes::splat(p.mean.x);
        let lo = (mx - (centre + root) - Lanes::splat(0.5)).fast_max(x0).fast_min(x1).ceil() - x0;
        let hi = ((mx - (centre - root) - Lanes::splat(0.5)).fast_max(x0 - Lanes::ONE).fast_min(x1 - Lanes::ONE)
            + Lanes::ONE)
            .floor()
            - x0;
        let rows = disc.cmp_ge(Lanes::ZERO) & hi.cmp_gt(lo) & LANE_IDX.cmp_lt(Lanes::splat((y1 - y) as f32));
        let batch = ChordBatch { row0: y - r[1], rows: rows.move_mask() as u32, lo: lo.to_array(), hi: hi.to_array() };
        if batch.rows != 0 {
            f(&batch, lo, hi);
        }
        y += LANES;
    }
}

/// Call `f(row, lo, hi)` for each tile row of rect `r` that Gaussian `p` can
/// reach, with the row's chord (see [`ChordBatch`]).
#[inline(always)]
fn for_each_chord(p: &Splat, r: &[u32; 4], mut f: impl FnMut(u32, f32, f32)) {
    for_each_chord_batch(p, r, |batch, _, _| batch.each(batch.rows, &mut f));
}

/// How many Gaussian-pixel evaluations a forward pass makes before early
/// termination (the work measure the benchmark reports).
pub fn pixel_evaluations(bins: &TileBins, width: u32, height: u32) -> u64 {
    (0..bins.tile_count())
        .into_par_iter()
        .map(|t| {
            let rect = bins.tile_rect(t, width, height);
            let mut n = 0u64;
            for &rank in bins.tile(t) {
                for_each_chord(&bins.splats[rank as usize], &rect, |_, lo, hi| n += (hi - lo) as u64);
            }
            n
        })
        .sum()
}

impl Splat {
    /// Gaussian exponent on a lane group at offsets (dx, dy) from the mean.
    #[inline(always)]
    fn power(&self, dx: Lanes, dy: Lanes) -> Lanes {
        let [a, b, c] = self.conic;
        Lanes::splat(-0.5) * (Lanes::splat(a) * dx * dx + Lanes::splat(c) * dy * dy) - Lanes::splat(b) * dx * dy
    }

    /// The alpha on a lane group, the raw Gaussian value, and the lanes that
    /// pass the skip rules (`live`, power <= 0, alpha >= ALPHA_MIN); None when
    /// no lane passes (checked before the exp).
    #[inline(always)]
    fn alpha(&self, power: Lanes, live: Lanes) -> Option<(Lanes, Lanes, Lanes)> {
        let live = live & power.cmp_le(Lanes::ZERO);
        if live.none() {
            return None;
        }
        let g = exp_nonpositive(power);
        let alpha = (Lanes::splat(self.opacity) * g).min(Lanes::splat(ALPHA_MAX));
        let valid = live & alpha.cmp_ge(Lanes::splat(ALPHA_MIN));
        (!valid.none()).then_some((alpha, g, valid))
    }
}

/// exp(x) for x <= 0, to a relative error under 4e-7 (above e^-87; 0 below).
/// Cheaper than a general exp: no overflow handling, and a degree-5 fit of
/// e^r on [-ln2/2, ln2/2] (coefficients fitted for this crate, relative error 1.7e-7).
#[inline(always)]
pub(crate) fn exp_nonpositive(x: Lanes) -> Lanes {
    const C: [f32; 5] = [0.999_999_5, 0.499_991_42, 0.166_681_14, 0.041_898_73, 0.008_261_531];
    // Cody-Waite: x = n ln2 + r with ln2 split in two so r keeps its precision.
    const LN2_HI: f32 = 0.693_359_4;
    const LN2_LO: f32 = -2.121_944_4e-4;
    let x = x.fast_max(Lanes::splat(-87.0));
    let n = (x * Lanes::splat(std::f32::consts::LOG2_E)).round();
    let r = n.mul_neg_add(Lanes::splat(LN2_LO), n.mul_neg_add(Lanes::splat(LN2_HI), x));
    // Estrin's scheme: a shorter dependency chain than Horner's.
    let r2 = r * r;
    let lo = Lanes::splat(C[1]).mul_add(r, Lanes::splat(C[0]));
    let mid = Lanes::splat(C[3]).mul_add(r, Lanes::splat(C[2]));
    let poly = Lanes::splat(C[4]).mul_add(r2, mid).mul_add(r2, lo);
    let e_r = poly.mul_add(r, Lanes::ONE);
    // 2^n from the float's exponent bits (n >= -126 after the clamp).
    let scale: Lanes = bytemuck::cast((n.fast_round_int() + wide::i32x8::splat(127)) << 23);
    e_r * scale
}

/// Visit the lane groups of tile row `row` that cover the chord [lo, hi) of
/// Gaussian `p`: `f(l, in_span, dx, dy)` gets the group's first index in the
/// tile's pixel arrays, the lanes inside the chord, and the offsets
/// mean - pixel centre per lane.
#[inline(always)]
fn for_each_lane_group(
    p: &Splat,
    rect: &[u32; 4],
    row: u32,
    lo: f32,
    hi: f32,
    mut f: impl FnMut(usize, Lanes, Lanes, Lanes),
) {
    let dy = Lanes::splat(p.mean.y - ((rect[1] + row) as f32 + 0.5));
    let mut x0 = lo as u32 & !(LANES - 1);
    while (x0 as f32) < hi {
        let lane_x = Lanes::splat(x0 as f32) + LANE_IDX;
        let in_span = lane_x.cmp_ge(Lanes::splat(lo)) & lane_x.cmp_lt(Lanes::splat(hi));
        let dx = Lanes::splat(p.mean.x) - (Lanes::splat((rect[0] + x0) as f32) + LANE_IDX + Lanes::splat(0.5));
        f((row * TILE + x0) as usize, in_span, dx, dy);
        x0 += LANES;
    }
}

#[inline(always)]
fn ld(a: &[f32; TILE_PIXELS], l: usize) -> Lanes {
    let v: [f32; LANES as usize] = a[l..l + LANES as usize].try_into().expect("a full lane group");
    Lanes::new(v)
}

#[inline(always)]
fn st(a: &mut [f32; TILE_PIXELS], l: usize, v: Lanes) {
    a[l..l + LANES as usize].copy_from_slice(&v.to_array());
}

#[inline(always)]
fn add(a: &mut [f32; TILE_PIXELS], l: usize, v: Lanes) {
    let sum = ld(a, l) + v;
    st(a, l, sum);
}

/// One tile's forward state, structure of arrays over its 16x16 pixels.
struct TileResult {
    rect: [u32; 4],
    color: [[f32; TILE_PIXELS]; 3],
    depth: [f32; TILE_PIXELS],
    t: [f32; TILE_PIXELS],
    /// One past the last composited list position (as f32: exact below 2^24).
    last: [f32; TILE_PIXELS],
}

/// Forward compositing over all tiles.
pub fn rasterize(bins: &TileBins, width: u32, height: u32, background: Vec3) -> RasterOutput {
    let results: Vec<TileResult> = (0..bins.tile_count())
        .into_par_iter()
        .map(|t| {
            let rect = bins.tile_rect(t, width, height);
            let mut res = TileResult {
                rect,
                color: [[0.0; TILE_PIXELS]; 3],
                depth: [0.0; TILE_PIXELS],
                t: [1.0; TILE_PIXELS],
                last: [0.0; TILE_PIXELS],
            };
            let npix = (rect[2] - rect[0]) * (rect[3] - rect[1]);
            let mut ndone = 0u32;
            // Pixels still compositing in each row, so finished rows are skipped whole.
            let mut row_live = [rect[2] - rect[0]; TILE as usize];
            for (k, &rank) in bins.tile(t).iter().enumerate() {
                let p = &bins.splats[rank as usize];
                let (cr, cg, cb, z) =
                    (Lanes::splat(p.color.x), Lanes::splat(p.color.y), Lanes::splat(p.color.z), Lanes::splat(p.depth));
                let k_next = Lanes::splat((k + 1) as f32);
                for_each_chord(p, &rect, |row, lo, hi| {
                    if row_live[row as usize] == 0 {
                        return;
                    }
                    for_each_lane_group(p, &rect, row, lo, hi, |l, in_span, dx, dy| {
                        // A finished pixel keeps its transmittance negated (see below).
                        let t_now = ld(&res.t, l);
                        let live = in_span & t_now.cmp_gt(Lanes::ZERO);
                        let Some((alpha, _, valid)) = p.alpha(p.power(dx, dy), live) else { return };
                        let t_next = t_now * (Lanes::ONE - alpha);
                        let term = valid & t_next.cmp_lt(Lanes::splat(TRANSMITTANCE_MIN));
                        let contrib = valid & !term;
                        let finished = term.move_mask().count_ones();
                        ndone += finished;
                        row_live[row as usize] -= finished;
                        let w = contrib.blend(alpha * t_now, Lanes::ZERO);
                        for (acc, c) in res.color.iter_mut().zip([cr, cg, cb]) {
                            add(acc, l, c * w);
                        }
                        add(&mut res.depth, l, z * w);
                        // Finished pixels store -T: the sign is the "done" flag, |T| the result.
                        st(&mut res.t, l, contrib.blend(t_next, term.blend(-t_now, t_now)));
                        let last_now = ld(&res.last, l);
                        st(&mut res.last, l, contrib.blend(k_next, last_now));
                    });
                });
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
                let tl = res.t[l].abs();
                for c in 0..3 {
                    out.color[3 * o + c] = res.color[c][l] + background[c] * tl;
                }
                out.alpha[o] = 1.0 - tl;
                out.depth[o] = res.depth[l];
                out.final_t[o] = tl;
                out.last[o] = res.last[l] as u32;
            }
        }
    }
    out
}

/// Backward compositing: per-Gaussian gradients of the projected quantities and
/// the background gradient, from dL/d(colour, alpha, depth) images.
#[allow(clippy::too_many_arguments)]
pub fn rasterize_backward(
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
            let g = TileGrads { color: grad_color, alpha: grad_alpha, depth: grad_depth };
            let tile = TileInput { t, bins, width, height, background, fwd };
            if grad_alpha.is_some() || grad_depth.is_some() {
                backward_tile::<true>(&tile, grads, &g)
            } else {
                backward_tile::<false>(&tile, grads, &g)
            }
        })
        .collect();

    let mut per_gaussian = vec![ProjectedGrad::default(); bins.gaussian_count];
    for (&rank, g) in bins.entries.iter().zip(&entry_grads) {
        let acc = &mut per_gaussian[bins.order[rank as usize] as usize];
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

/// One tile of a backward pass and the forward state it reads.
#[derive(Clone, Copy)]
struct TileInput<'a> {
    t: usize,
    bins: &'a TileBins,
    width: u32,
    height: u32,
    background: Vec3,
    fwd: &'a RasterOutput,
}

/// The image-space gradients the backward pass consumes.
struct TileGrads<'a> {
    color: &'a [f32],
    alpha: Option<&'a [f32]>,
    depth: Option<&'a [f32]>,
}

/// Backward of one tile, writing its list entries' gradients; returns its share
/// of the background gradient. `AUX` = alpha or depth gradients are present
/// (training from colour alone skips that arithmetic).
fn backward_tile<const AUX: bool>(tile: &TileInput, grads: &mut [ProjectedGrad], g: &TileGrads) -> Vec3 {
    let TileInput { t, bins, width, height, background, fwd } = *tile;
    let rect = bins.tile_rect(t, width, height);
    let list = bins.tile(t);
    // Per-pixel state, back to front: transmittance before the current
    // Gaussian, last composited position, and dL/d(outputs). The colour and
    // depth gradients are fixed per pixel, so what lies behind the current
    // Gaussian enters only through its dot product with them:
    // behind = sum_c dL/dC_c (colour behind)_c + dL/dD (depth behind).
    let mut t_cur = [0.0f32; TILE_PIXELS];
    let mut behind = [0.0f32; TILE_PIXELS];
    let mut last = [0.0f32; TILE_PIXELS];
    let mut gc = [[0.0f32; TILE_PIXELS]; 3];
    let mut gd = [0.0f32; TILE_PIXELS];
    // dL/d(alpha) times the final transmittance: d(alpha)/d(alpha_k) = T_final / (1 - alpha_k).
    let mut ga_t = [0.0f32; TILE_PIXELS];
    let mut bg_grad = Vec3::ZERO;
    let mut max_last = 0u32;
    // Per row, one past the last list position any of its pixels composited.
    let mut row_last = [0u32; TILE as usize];
    for py in rect[1]..rect[3] {
        for px in rect[0]..rect[2] {
            let l = ((py - rect[1]) * TILE + (px - rect[0])) as usize;
            let o = (py * width + px) as usize;
            let tf = fwd.final_t[o];
            t_cur[l] = tf;
            last[l] = fwd.last[o] as f32;
            max_last = max_last.max(fwd.last[o]);
            let row = (py - rect[1]) as usize;
            row_last[row] = row_last[row].max(fwd.last[o]);
            for c in 0..3 {
                gc[c][l] = g.color[3 * o + c];
                behind[l] += g.color[3 * o + c] * background[c] * tf;
                bg_grad[c] += g.color[3 * o + c] * tf;
            }
            ga_t[l] = g.alpha.map_or(0.0, |a| a[o]) * tf;
            gd[l] = g.depth.map_or(0.0, |d| d[o]);
        }
    }
    for k in (0..max_last as usize).rev() {
        let sp = &bins.splats[list[k] as usize];
        let col = [Lanes::splat(sp.color.x), Lanes::splat(sp.color.y), Lanes::splat(sp.color.z)];
        let z = Lanes::splat(sp.depth);
        let kf = Lanes::splat(k as f32);
        let mut acc_col = [Lanes::ZERO; 3];
        let (mut acc_d, mut acc_op) = (Lanes::ZERO, Lanes::ZERO);
        // Moments of dL/d(power) over the pixels (offsets dx, dy): the conic
        // and 2D-mean gradients are linear in them.
        let (mut m_x, mut m_y) = (Lanes::ZERO, Lanes::ZERO);
        let (mut m_xx, mut m_xy, mut m_yy) = (Lanes::ZERO, Lanes::ZERO, Lanes::ZERO);
        for_each_chord(sp, &rect, |row, lo, hi| {
            if k as u32 >= row_last[row as usize] {
                return;
            }
            for_each_lane_group(sp, &rect, row, lo, hi, |l, in_span, dx, dy| {
                let composited = in_span & kf.cmp_lt(ld(&last, l));
                let Some((alpha, gauss, valid)) = sp.alpha(sp.power(dx, dy), composited) else { return };
                let inv_one_minus = Lanes::ONE / (Lanes::ONE - alpha);
                let t_now = ld(&t_cur, l);
                let t_before = t_now * inv_one_minus;
                let w = valid.blend(alpha * t_before, Lanes::ZERO);
                let gcol = [ld(&gc[0], l), ld(&gc[1], l), ld(&gc[2], l)];
                // dL/d(this Gaussian's colour and depth values) . (colour, depth).
                let mut value = gcol[0] * col[0] + gcol[1] * col[1] + gcol[2] * col[2];
                if AUX {
                    let g_d = ld(&gd, l);
                    value += g_d * z;
                    acc_d += g_d * w;
                }
                for c in 0..3 {
                    acc_col[c] += gcol[c] * w;
                }
                // d(out)/d(alpha) = value * T - (what lies behind) / (1 - alpha).
                let behind_now = ld(&behind, l);
                let mut dl_da = value * t_before - behind_now * inv_one_minus;
                if AUX {
                    dl_da += ld(&ga_t, l) * inv_one_minus;
                }
                st(&mut behind, l, value.mul_add(w, behind_now));
                st(&mut t_cur, l, valid.blend(t_before, t_now));
                // Where alpha was clamped at ALPHA_MAX it does not depend on opacity or shape.
                let free = valid & (Lanes::splat(sp.opacity) * gauss).cmp_le(Lanes::splat(ALPHA_MAX));
                let dl_da = free.blend(dl_da, Lanes::ZERO);
                acc_op += dl_da * gauss;
                let dl_dpower = dl_da * alpha;
                let (u, v) = (dl_dpower * dx, dl_dpower * dy);
                m_x += u;
                m_y += v;
                m_xx = u.mul_add(dx, m_xx);
                m_xy = u.mul_add(dy, m_xy);
                m_yy = v.mul_add(dy, m_yy);
            });
        });
        // power = -(a dx^2 + c dy^2) / 2 - b dx dy with (dx, dy) = mean - pixel.
        let [a, b, c] = sp.conic;
        let (mx, my) = (m_x.reduce_add(), m_y.reduce_add());
        grads[k] = ProjectedGrad {
            mean2d: Vec2::new(-(a * mx + b * my), -(c * my + b * mx)),
            conic: [-0.5 * m_xx.reduce_add(), -m_xy.reduce_add(), -0.5 * m_yy.reduce_add()],
            color: Vec3::new(acc_col[0].reduce_add(), acc_col[1].reduce_add(), acc_col[2].reduce_add()),
            opacity: acc_op.reduce_add(),
            depth: acc_d.reduce_add(),
        };
    }
    bg_grad
}
