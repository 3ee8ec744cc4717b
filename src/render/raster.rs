//! Tile binning and front-to-back alpha compositing on the CPU, forward and
//! backward. Each 16x16 tile is one unit of rayon work; inside a tile the loop
//! runs Gaussian-outer, pixel-inner over the Gaussian's exact pixel box, so a
//! Gaussian only touches the pixels it can reach.

use super::lanes::{dispatch, prefetch, Block, Kernels, Lanes, Portable, LANES};
use super::project::{Projected, ProjectedGrad, ALPHA_MIN};
use glam::{Vec2, Vec3};
use rayon::prelude::*;

/// Lanes per vector, as a pixel coordinate step.
const LANE_STEP: u32 = LANES as u32;

pub const TILE: u32 = 16;
/// The largest image side the rasterizer renders (pixel boxes are stored as u16).
pub const MAX_IMAGE_SIDE: u32 = u16::MAX as u32;
const TILE_PIXELS: usize = (TILE * TILE) as usize;
/// Compositing stops once transmittance would fall below this.
pub const TRANSMITTANCE_MIN: f32 = 1e-4;
/// Alpha is clamped here so (1 - alpha) never vanishes in the backward division.
pub const ALPHA_MAX: f32 = 0.99;

/// How many list entries ahead the compositing loops prefetch the Gaussian they
/// will read (about one memory latency of work ahead).
const PREFETCH_AHEAD: usize = 8;

/// What compositing reads of one visible Gaussian: one 64-byte cache line.
#[derive(Clone, Copy, Debug)]
#[repr(C, align(64))]
pub struct Splat {
    mean: Vec2,
    conic: [f32; 3],
    opacity: f32,
    color: Vec3,
    depth: f32,
    /// Pixel box [x0, y0, x1, y1] (inclusive), inside the image.
    bbox: [u16; 4],
    span: [f32; 3],
}

impl Splat {
    fn new(p: &Projected) -> Self {
        let Projected { mean2d, conic, depth, color, opacity, bbox, span, .. } = *p;
        // Boxes lie inside the image, at most MAX_IMAGE_SIDE px on a side.
        Self { mean: mean2d, conic, opacity, color, depth, bbox: bbox.map(|v| v as u16), span }
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
    let by_depth =
        proj.iter().enumerate().filter_map(|(i, p)| p.as_ref().map(|p| depth_key(p.depth, i as u32))).collect();
    let projected = |i: u32| proj[i as usize].as_ref().expect("sorted Gaussians are visible");
    bin_sorted(by_depth, projected, proj.len(), width, height, |_| true)
}

/// The sort key of a Gaussian at `depth` with index `index`: keys order as
/// (depth by `f32::total_cmp`, then index). Comparing one integer instead of a
/// float pair makes the per-render sort several times cheaper, in the same order.
pub(crate) fn depth_key(depth: f32, index: u32) -> u64 {
    let bits = depth.to_bits();
    // total_cmp's order as unsigned integers: a negative value's bits all
    // flipped, a positive value's sign bit set.
    let ordered = if bits >> 31 == 1 { !bits } else { bits | 0x8000_0000 };
    (u64::from(ordered) << 32) | u64::from(index)
}

/// Bin the Gaussians `by_depth` lists (`depth_key`s; `projected(index)` each
/// one's projection) of a set of `gaussian_count` into the tiles `keep` holds,
/// the other tiles' lists left empty. Every kept tile's list is the one
/// `bin_tiles` gives it when `by_depth` holds all the Gaussians that reach it:
/// the same Gaussians in the same order, so compositing it gives the same pixels.
pub(crate) fn bin_sorted<'a>(
    mut by_depth: Vec<u64>,
    projected: impl Fn(u32) -> &'a Projected + Sync,
    gaussian_count: usize,
    width: u32,
    height: u32,
    keep: impl Fn(usize) -> bool,
) -> TileBins {
    assert!(
        width <= MAX_IMAGE_SIDE && height <= MAX_IMAGE_SIDE,
        "{width}x{height} px: the rasterizer renders at most {MAX_IMAGE_SIDE} px on a side"
    );
    let tiles_x = width.div_ceil(TILE);
    let tiles_y = height.div_ceil(TILE);
    // Unique keys (depth, index): the order is deterministic whatever the sort does.
    by_depth.par_sort_unstable();
    let order: Vec<u32> = by_depth.iter().map(|&key| key as u32).collect();
    let splats: Vec<Splat> = order.par_iter().map(|&i| Splat::new(projected(i))).collect();

    let ntiles = (tiles_x * tiles_y) as usize;
    let mut counts = vec![0u32; ntiles + 1];
    for s in &splats {
        for t in tiles_reached(&s.bbox.map(u32::from), tiles_x).filter(|&t| keep(t)) {
            counts[t + 1] += 1;
        }
    }
    for t in 0..ntiles {
        counts[t + 1] += counts[t];
    }
    let offsets = counts;
    let mut fill = offsets.clone();
    let mut entries = vec![0u32; offsets[ntiles] as usize];
    for (rank, s) in splats.iter().enumerate() {
        for t in tiles_reached(&s.bbox.map(u32::from), tiles_x).filter(|&t| keep(t)) {
            entries[fill[t] as usize] = rank as u32;
            fill[t] += 1;
        }
    }
    TileBins { tiles_x, tiles_y, gaussian_count, order, splats, offsets, entries }
}

/// The tiles (row-major in a grid `tiles_x` wide) a Gaussian's inclusive pixel box `bbox` reaches.
pub(crate) fn tiles_reached(bbox: &[u32; 4], tiles_x: u32) -> impl Iterator<Item = usize> {
    let [tx0, ty0, tx1, ty1] = bbox.map(|v| v / TILE);
    (ty0..=ty1).flat_map(move |ty| (tx0..=tx1).map(move |tx| (ty * tiles_x + tx) as usize))
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

impl RasterOutput {
    /// Expected depth of the visible surface per pixel (accumulated depth / alpha; 0 where empty).
    pub fn expected_depth(&self) -> Vec<f32> {
        self.depth.iter().zip(&self.alpha).map(|(d, a)| if *a > 1e-6 { d / a } else { 0.0 }).collect()
    }

    /// The colour image (`width` x `height`) as 8-bit RGB.
    pub fn to_rgb8(&self, width: u32, height: u32) -> image::RgbImage {
        let bytes = self.color.iter().map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8).collect();
        image::RgbImage::from_raw(width, height, bytes).expect("buffer matches image size")
    }
}

/// The rows of Gaussian box `bbox` inside tile rect `r` (exclusive end); None if empty.
#[inline]
fn clip_rows(bbox: &[u16; 4], r: &[u32; 4]) -> Option<(u32, u32)> {
    let [x0, y0, x1, y1] = bbox.map(u32::from);
    let y0 = y0.max(r[1]);
    let y1 = (y1 + 1).min(r[3]);
    (x0 < r[2] && x1 >= r[0] && y0 < y1).then_some((y0, y1))
}

/// Call `f(row, lo, hi)` for each tile row of rect `r` that Gaussian `p` can
/// reach, top to bottom, with the row's chord: the tile-local pixels [lo, hi)
/// inside the conservative ellipse power >= power_cut. Chords are solved in
/// closed form for eight rows at a time (one row per lane).
#[inline(always)]
fn for_each_chord<L: Lanes>(p: &Splat, r: &[u32; 4], mut f: impl FnMut(u32, f32, f32)) {
    let Some((y0, y1)) = clip_rows(&p.bbox, r) else { return };
    let [s0, s1, s2] = p.span;
    let x0 = L::splat(r[0] as f32);
    let x1 = L::splat(r[2] as f32);
    let mut y = y0;
    while y < y1 {
        let dy = L::splat(p.mean.y) - ((L::splat(y as f32) + L::INDEX) + L::splat(0.5));
        let disc = L::splat(s1) * dy * dy + L::splat(s2);
        let root = disc.max(L::ZERO).sqrt();
        let centre = L::splat(-s0) * dy;
        // dx = mean.x - (px + 0.5) ranges over centre -+ root; lo = ceil, hi = floor + 1
        // (hi + 1 >= 0 after the clamp, so rounding down is floor).
        let mx = L::splat(p.mean.x);
        let lo = (mx - (centre + root) - L::splat(0.5)).max(x0).min(x1).ceil() - x0;
        let hi = ((mx - (centre - root) - L::splat(0.5)).max(x0 - L::ONE).min(x1 - L::ONE) + L::ONE).floor() - x0;
        let mut rows = (disc.cmp_ge(L::ZERO) & hi.cmp_gt(lo) & L::INDEX.cmp_lt(L::splat((y1 - y) as f32))).move_mask();
        let (lo, hi) = (lo.to_array(), hi.to_array());
        // The closure is called here, not through a forwarding `&mut f`: every
        // call on the way must inline into the kernel's #[target_feature] entry.
        while rows != 0 {
            let j = rows.trailing_zeros() as usize;
            rows &= rows - 1;
            f(y - r[1] + j as u32, lo[j], hi[j]);
        }
        y += LANE_STEP;
    }
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
                for_each_chord::<Portable>(&bins.splats[rank as usize], &rect, |_, lo, hi| n += (hi - lo) as u64);
            }
            n
        })
        .sum()
}

impl Splat {
    /// dy = mean.y - pixel centre on tile row `row` of rect `rect`.
    #[inline(always)]
    fn row_dy(&self, rect: &[u32; 4], row: u32) -> f32 {
        self.mean.y - ((rect[1] + row) as f32 + 0.5)
    }

    /// The alpha on a lane group, the raw Gaussian value, and the lanes that
    /// pass the skip rules (`live`, power <= 0, alpha >= ALPHA_MIN); None when
    /// no lane passes (checked before the exp).
    #[inline(always)]
    fn alpha<L: Lanes>(&self, power: L, live: L) -> Option<(L, L, L)> {
        let live = live & power.cmp_le(L::ZERO);
        if live.none() {
            return None;
        }
        let g = exp_nonpositive(power);
        let alpha = (L::splat(self.opacity) * g).min(L::splat(ALPHA_MAX));
        let valid = live & alpha.cmp_ge(L::splat(ALPHA_MIN));
        (!valid.none()).then_some((alpha, g, valid))
    }
}

/// exp(x) for x <= 0, to a relative error under 4e-7 (above e^-87; 0 below).
/// Cheaper than a general exp: no overflow handling, and a degree-5 fit of
/// e^r on [-ln2/2, ln2/2] (coefficients fitted for this crate, relative error 1.7e-7).
#[inline(always)]
pub(crate) fn exp_nonpositive<L: Lanes>(x: L) -> L {
    const C: [f32; 5] = [0.999_999_5, 0.499_991_42, 0.166_681_14, 0.041_898_73, 0.008_261_531];
    // Cody-Waite: x = n ln2 + r with ln2 split in two so r keeps its precision.
    const LN2_HI: f32 = 0.693_359_4;
    const LN2_LO: f32 = -2.121_944_4e-4;
    let x = x.max(L::splat(-87.0));
    let n = (x * L::splat(std::f32::consts::LOG2_E)).round();
    let r = n.mul_neg_add(L::splat(LN2_LO), n.mul_neg_add(L::splat(LN2_HI), x));
    // Estrin's scheme: a shorter dependency chain than Horner's.
    let r2 = r * r;
    let lo = L::splat(C[1]).mul_add(r, L::splat(C[0]));
    let mid = L::splat(C[3]).mul_add(r, L::splat(C[2]));
    let poly = L::splat(C[4]).mul_add(r2, mid).mul_add(r2, lo);
    let e_r = poly.mul_add(r, L::ONE);
    // 2^n from the float's exponent bits (n >= -126 after the clamp).
    e_r * n.exp2_integral()
}

/// Visit the lane groups of tile row `row` that cover the chord [lo, hi) of
/// Gaussian `p`: `f(l, in_span, dx, power)` gets the group's first index in the
/// tile's pixel arrays, the lanes inside the chord, the offsets dx = mean.x -
/// pixel centre, and the Gaussian's exponent per lane.
#[inline(always)]
fn for_each_lane_group<L: Lanes>(
    p: &Splat,
    rect: &[u32; 4],
    row: u32,
    lo: f32,
    hi: f32,
    mut f: impl FnMut(usize, L, L, L),
) {
    // power = -(a dx^2 + c dy^2) / 2 - b dx dy = dx (-a/2 dx - b dy) - c/2 dy^2,
    // with dy one value for the row: two FMAs per lane group.
    let [a, b, c] = p.conic;
    let dy = p.row_dy(rect, row);
    let (half_a, linear, constant) = (L::splat(-0.5 * a), L::splat(-b * dy), L::splat(-0.5 * c * dy * dy));
    let dx_at_0 = L::splat(p.mean.x - rect[0] as f32 - 0.5) - L::INDEX;
    let (lo_lanes, hi_lanes) = (L::splat(lo), L::splat(hi));
    let mut x0 = (lo as u32 & !(LANE_STEP - 1)) as f32;
    while x0 < hi {
        let x = L::splat(x0);
        let lane_x = x + L::INDEX;
        let in_span = lane_x.cmp_ge(lo_lanes) & lane_x.cmp_lt(hi_lanes);
        let dx = dx_at_0 - x;
        let power = dx.mul_add(half_a.mul_add(dx, linear), constant);
        f((row * TILE) as usize + x0 as usize, in_span, dx, power);
        x0 += LANES as f32;
    }
}

/// One value per pixel of a tile, in lane groups aligned for whole-vector access.
#[derive(Clone, Copy)]
struct Plane([Block; TILE_PIXELS / LANES]);

impl Plane {
    fn filled(v: f32) -> Self {
        Self([Block([v; LANES]); TILE_PIXELS / LANES])
    }
}

impl std::ops::Index<usize> for Plane {
    type Output = f32;
    fn index(&self, l: usize) -> &f32 {
        &self.0[l / LANES].0[l % LANES]
    }
}

impl std::ops::IndexMut<usize> for Plane {
    fn index_mut(&mut self, l: usize) -> &mut f32 {
        &mut self.0[l / LANES].0[l % LANES]
    }
}

/// The lane group starting at pixel `l` (a multiple of [`LANES`]).
#[inline(always)]
fn ld<L: Lanes>(a: &Plane, l: usize) -> L {
    L::load(&a.0[l / LANES])
}

#[inline(always)]
fn st<L: Lanes>(a: &mut Plane, l: usize, v: L) {
    v.store(&mut a.0[l / LANES]);
}

#[inline(always)]
fn add<L: Lanes>(a: &mut Plane, l: usize, v: L) {
    let sum = ld::<L>(a, l) + v;
    st(a, l, sum);
}

/// One tile's forward state, structure of arrays over its 16x16 pixels.
struct TileResult {
    rect: [u32; 4],
    color: [Plane; 3],
    depth: Plane,
    t: Plane,
    /// One past the last composited list position (as f32: exact below 2^24).
    last: Plane,
}

/// Forward compositing over all tiles, with the fastest kernel set this CPU runs.
pub fn rasterize(bins: &TileBins, width: u32, height: u32, background: Background) -> RasterOutput {
    rasterize_with(Kernels::active(), bins, width, height, background)
}

/// What shows where the Gaussians leave the pixel transparent.
#[derive(Clone, Copy, Debug)]
pub enum Background<'a> {
    /// One colour everywhere.
    Uniform(Vec3),
    /// A colour per pixel (row-major RGB of the rendered image): a fixed scene
    /// behind the Gaussians, e.g. the room behind an object.
    Image(&'a [f32]),
}

impl Background<'_> {
    #[inline]
    fn at(&self, pixel: usize) -> Vec3 {
        match self {
            Background::Uniform(c) => *c,
            Background::Image(img) => Vec3::new(img[3 * pixel], img[3 * pixel + 1], img[3 * pixel + 2]),
        }
    }
}

/// Forward compositing over all tiles with kernel set `kernels`.
pub fn rasterize_with(
    kernels: Kernels,
    bins: &TileBins,
    width: u32,
    height: u32,
    background: Background,
) -> RasterOutput {
    if let Background::Image(img) = background {
        assert_eq!(img.len(), (3 * width * height) as usize, "background image must match the render");
    }
    let results = composite_tiles(kernels, bins, (0..bins.tile_count()).into_par_iter(), width, height);

    let n = (width * height) as usize;
    let mut out = RasterOutput {
        color: vec![0.0; 3 * n],
        alpha: vec![0.0; n],
        depth: vec![0.0; n],
        final_t: vec![1.0; n],
        last: vec![0; n],
    };
    for res in &results {
        res.for_each_pixel(width, &background, |o, l, color| {
            let tl = res.t[l].abs();
            out.color[3 * o..3 * o + 3].copy_from_slice(&color);
            out.alpha[o] = 1.0 - tl;
            out.depth[o] = res.depth[l];
            out.final_t[o] = tl;
            out.last[o] = res.last[l] as u32;
        });
    }
    out
}

/// Forward compositing of the tiles `tiles` only, with the fastest kernel set
/// this CPU runs: calls `f(pixel, rgb)` for each of their pixels (row-major
/// index in the image, colour with the background), the value `rasterize` gives it.
pub fn rasterize_tiles(
    bins: &TileBins,
    tiles: &[usize],
    width: u32,
    height: u32,
    background: Background,
    mut f: impl FnMut(usize, [f32; 3]),
) {
    for res in &composite_tiles(Kernels::active(), bins, tiles.par_iter().copied(), width, height) {
        res.for_each_pixel(width, &background, |o, _, rgb| f(o, rgb));
    }
}

/// Forward compositing of the tiles `tiles`, in their order.
fn composite_tiles(
    kernels: Kernels,
    bins: &TileBins,
    tiles: impl IndexedParallelIterator<Item = usize>,
    width: u32,
    height: u32,
) -> Vec<TileResult> {
    tiles
        .map(|t| {
            dispatch!(kernels, |L; bins: &TileBins, t: usize, width: u32, height: u32| -> TileResult {
                forward_tile::<L>(bins, t, width, height)
            })
        })
        .collect()
}

impl TileResult {
    /// Calls `f(pixel, l, rgb)` for each pixel of the tile: its row-major index
    /// in an image `width` wide, its index in the tile's planes, and its colour
    /// with `background` showing through the final transmittance.
    fn for_each_pixel(&self, width: u32, background: &Background, mut f: impl FnMut(usize, usize, [f32; 3])) {
        let r = self.rect;
        for py in r[1]..r[3] {
            for px in r[0]..r[2] {
                let l = ((py - r[1]) * TILE + (px - r[0])) as usize;
                let o = (py * width + px) as usize;
                let tl = self.t[l].abs();
                let bg = background.at(o);
                f(o, l, [0, 1, 2].map(|c| self.color[c][l] + bg[c] * tl));
            }
        }
    }
}

/// Forward compositing of tile t.
#[inline(always)]
fn forward_tile<L: Lanes>(bins: &TileBins, t: usize, width: u32, height: u32) -> TileResult {
    let rect = bins.tile_rect(t, width, height);
    let mut res = TileResult {
        rect,
        color: [Plane::filled(0.0); 3],
        depth: Plane::filled(0.0),
        t: Plane::filled(1.0),
        last: Plane::filled(0.0),
    };
    let npix = (rect[2] - rect[0]) * (rect[3] - rect[1]);
    let mut ndone = 0u32;
    // Pixels still compositing in each row, so finished rows are skipped whole.
    let mut row_live = [rect[2] - rect[0]; TILE as usize];
    let list = bins.tile(t);
    for (k, &rank) in list.iter().enumerate() {
        if let Some(&ahead) = list.get(k + PREFETCH_AHEAD) {
            prefetch(&bins.splats[ahead as usize]);
        }
        let p = &bins.splats[rank as usize];
        let (cr, cg, cb, z) = (L::splat(p.color.x), L::splat(p.color.y), L::splat(p.color.z), L::splat(p.depth));
        let k_next = L::splat((k + 1) as f32);
        for_each_chord::<L>(
            p,
            &rect,
            #[inline(always)]
            |row, lo, hi| {
                if row_live[row as usize] == 0 {
                    return;
                }
                for_each_lane_group(
                    p,
                    &rect,
                    row,
                    lo,
                    hi,
                    #[inline(always)]
                    |l, in_span, _, power| {
                        // A finished pixel keeps its transmittance negated (see below).
                        let t_now: L = ld(&res.t, l);
                        let live = in_span & t_now.cmp_gt(L::ZERO);
                        let Some((alpha, _, valid)) = p.alpha(power, live) else { return };
                        let t_next = t_now * (L::ONE - alpha);
                        let term = valid & t_next.cmp_lt(L::splat(TRANSMITTANCE_MIN));
                        let contrib = valid & !term;
                        let finished = term.move_mask().count_ones();
                        ndone += finished;
                        row_live[row as usize] -= finished;
                        let w = contrib.select(alpha * t_now, L::ZERO);
                        for (acc, c) in res.color.iter_mut().zip([cr, cg, cb]) {
                            add(acc, l, c * w);
                        }
                        add(&mut res.depth, l, z * w);
                        // Finished pixels store -T: the sign is the "done" flag, |T| the result.
                        st(&mut res.t, l, contrib.select(t_next, term.select(-t_now, t_now)));
                        // Positions only grow, so max() is the masked update; a select
                        // against the loaded value would become a masked store, which
                        // AVX2 CPUs (Zen 3) execute slowly.
                        let last_now: L = ld(&res.last, l);
                        st(&mut res.last, l, last_now.max(contrib & k_next));
                    },
                );
            },
        );
        if ndone == npix {
            break;
        }
    }
    res
}

/// Backward compositing: per-Gaussian gradients of the projected quantities and
/// the background gradient, from dL/d(colour, alpha, depth) images, with the
/// fastest kernel set this CPU runs.
#[allow(clippy::too_many_arguments)]
pub fn rasterize_backward(
    bins: &TileBins,
    width: u32,
    height: u32,
    background: Background,
    fwd: &RasterOutput,
    grad_color: &[f32],
    grad_alpha: Option<&[f32]>,
    grad_depth: Option<&[f32]>,
) -> (Vec<ProjectedGrad>, Vec3) {
    let grads = TileGrads { color: grad_color, alpha: grad_alpha, depth: grad_depth, wanted: None };
    rasterize_backward_with(Kernels::active(), bins, width, height, background, fwd, &grads)
}

/// [`rasterize_backward`] with kernel set `kernels`.
pub fn rasterize_backward_with(
    kernels: Kernels,
    bins: &TileBins,
    width: u32,
    height: u32,
    background: Background,
    fwd: &RasterOutput,
    g: &TileGrads,
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
    let wanted_by_rank: Option<Vec<bool>> = g.wanted.map(|w| bins.order.iter().map(|&i| w[i as usize]).collect());
    let wanted = wanted_by_rank.as_deref();
    let bg_grads: Vec<Vec3> = slices
        .into_par_iter()
        .enumerate()
        .map(|(t, grads)| {
            let tile = &TileInput { t, bins, width, height, background, fwd, wanted };
            dispatch!(kernels, |L; tile: &TileInput, grads: &mut [ProjectedGrad], g: &TileGrads| -> Vec3 {
                if g.alpha.is_some() || g.depth.is_some() {
                    backward_tile::<true, L>(tile, grads, g)
                } else {
                    backward_tile::<false, L>(tile, grads, g)
                }
            })
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
    background: Background<'a>,
    fwd: &'a RasterOutput,
    /// Per rank: whether its gradients are wanted (None: all are).
    wanted: Option<&'a [bool]>,
}

/// The image-space gradients the backward pass consumes: dL/d(colour, alpha,
/// depth), and which Gaussians' gradients are wanted (per Gaussian of the set;
/// None: all). The others get zero gradients: their compositing is still
/// undone, so every wanted gradient is the one a full pass gives, to the bit,
/// but their own gradient arithmetic is skipped (a tracker fitting the moving
/// parts of a scene whose base stands still).
pub struct TileGrads<'a> {
    pub color: &'a [f32],
    pub alpha: Option<&'a [f32]>,
    pub depth: Option<&'a [f32]>,
    pub wanted: Option<&'a [bool]>,
}

/// A tile's per-pixel state in the backward pass, back to front: transmittance
/// before the current Gaussian, last composited position, and dL/d(outputs).
/// The colour and depth gradients are fixed per pixel, so what lies behind the
/// current Gaussian enters only through its dot product with them:
/// behind = sum_c dL/dC_c (colour behind)_c + dL/dD (depth behind).
struct BackwardPixels {
    t_cur: Plane,
    behind: Plane,
    last: Plane,
    gc: [Plane; 3],
    gd: Plane,
    /// dL/d(alpha) times the final transmittance: d(alpha)/d(alpha_k) = T_final / (1 - alpha_k).
    ga_t: Plane,
    /// Per row, one past the last list position any of its pixels composited.
    row_last: [u32; TILE as usize],
}

/// Backward of one tile, writing its list entries' gradients; returns its share
/// of the background gradient. `AUX` = alpha or depth gradients are present
/// (training from colour alone skips that arithmetic).
#[inline(always)]
fn backward_tile<const AUX: bool, L: Lanes>(tile: &TileInput, grads: &mut [ProjectedGrad], g: &TileGrads) -> Vec3 {
    let TileInput { t, bins, width, height, background, fwd, wanted } = *tile;
    let rect = bins.tile_rect(t, width, height);
    let list = bins.tile(t);
    let mut px_state = BackwardPixels {
        t_cur: Plane::filled(0.0),
        behind: Plane::filled(0.0),
        last: Plane::filled(0.0),
        gc: [Plane::filled(0.0); 3],
        gd: Plane::filled(0.0),
        ga_t: Plane::filled(0.0),
        row_last: [0u32; TILE as usize],
    };
    let s = &mut px_state;
    let mut bg_grad = Vec3::ZERO;
    let mut max_last = 0u32;
    for py in rect[1]..rect[3] {
        for px in rect[0]..rect[2] {
            let l = ((py - rect[1]) * TILE + (px - rect[0])) as usize;
            let o = (py * width + px) as usize;
            let tf = fwd.final_t[o];
            let background = background.at(o);
            s.t_cur[l] = tf;
            s.last[l] = fwd.last[o] as f32;
            max_last = max_last.max(fwd.last[o]);
            let row = (py - rect[1]) as usize;
            s.row_last[row] = s.row_last[row].max(fwd.last[o]);
            for c in 0..3 {
                s.gc[c][l] = g.color[3 * o + c];
                s.behind[l] += g.color[3 * o + c] * background[c] * tf;
                bg_grad[c] += g.color[3 * o + c] * tf;
            }
            s.ga_t[l] = g.alpha.map_or(0.0, |a| a[o]) * tf;
            s.gd[l] = g.depth.map_or(0.0, |d| d[o]);
        }
    }
    for k in (0..max_last as usize).rev() {
        if let Some(ahead) = k.checked_sub(PREFETCH_AHEAD) {
            prefetch(&bins.splats[list[ahead] as usize]);
        }
        let rank = list[k] as usize;
        let sp = &bins.splats[rank];
        if wanted.is_none_or(|w| w[rank]) {
            grads[k] = splat_backward::<AUX, true, L>(sp, k, &rect, s);
        } else {
            splat_backward::<AUX, false, L>(sp, k, &rect, s);
        }
    }
    bg_grad
}

/// Undo the compositing of the splat at list position `k` over the tile's
/// pixels `s` and, when `GRAD`, return its gradients (zero otherwise).
#[inline(always)]
fn splat_backward<const AUX: bool, const GRAD: bool, L: Lanes>(
    sp: &Splat,
    k: usize,
    rect: &[u32; 4],
    s: &mut BackwardPixels,
) -> ProjectedGrad {
    let col = [L::splat(sp.color.x), L::splat(sp.color.y), L::splat(sp.color.z)];
    let z = L::splat(sp.depth);
    let kf = L::splat(k as f32);
    let mut acc_col = [L::ZERO; 3];
    let mut acc_d = L::ZERO;
    // Moments of p = dL/d(power) over the pixels (offsets dx, dy): the
    // conic, 2D-mean and opacity gradients are linear in them. dy is one
    // value per row, so the lane groups sum only p, p dx and p dx^2 (a
    // small live set: AVX2 has 16 vector registers), and each row folds
    // its sums into the dy moments.
    let (mut m_1, mut m_x, mut m_xx) = (L::ZERO, L::ZERO, L::ZERO);
    let (mut m_y, mut m_xy, mut m_yy) = (L::ZERO, L::ZERO, L::ZERO);
    for_each_chord::<L>(
        sp,
        rect,
        #[inline(always)]
        |row, lo, hi| {
            if k as u32 >= s.row_last[row as usize] {
                return;
            }
            let (mut row_1, mut row_x) = (L::ZERO, L::ZERO);
            for_each_lane_group(
                sp,
                rect,
                row,
                lo,
                hi,
                #[inline(always)]
                |l, in_span, dx, power| {
                    let composited = in_span & kf.cmp_lt(ld::<L>(&s.last, l));
                    let Some((alpha, gauss, valid)) = sp.alpha(power, composited) else { return };
                    let inv_one_minus = L::ONE / (L::ONE - alpha);
                    let t_now: L = ld(&s.t_cur, l);
                    let t_before = t_now * inv_one_minus;
                    let w = valid.select(alpha * t_before, L::ZERO);
                    let gcol: [L; 3] = [ld(&s.gc[0], l), ld(&s.gc[1], l), ld(&s.gc[2], l)];
                    // dL/d(this Gaussian's colour and depth values) . (colour, depth).
                    let mut value = gcol[0] * col[0] + gcol[1] * col[1] + gcol[2] * col[2];
                    if AUX {
                        let g_d: L = ld(&s.gd, l);
                        value += g_d * z;
                        if GRAD {
                            acc_d += g_d * w;
                        }
                    }
                    let behind_now: L = ld(&s.behind, l);
                    st(&mut s.behind, l, value.mul_add(w, behind_now));
                    // t_before >= t_now where valid (it divides by 1 - alpha), and
                    // T >= 0: max() is the masked update without a masked store.
                    st(&mut s.t_cur, l, t_now.max(valid & t_before));
                    if !GRAD {
                        return;
                    }
                    for c in 0..3 {
                        acc_col[c] += gcol[c] * w;
                    }
                    // d(out)/d(alpha) = value * T - (what lies behind) / (1 - alpha).
                    let mut dl_da = value * t_before - behind_now * inv_one_minus;
                    if AUX {
                        dl_da += ld::<L>(&s.ga_t, l) * inv_one_minus;
                    }
                    // Where alpha was clamped at ALPHA_MAX it does not depend on opacity or shape.
                    let free = valid & (L::splat(sp.opacity) * gauss).cmp_le(L::splat(ALPHA_MAX));
                    let dl_dpower = free & (dl_da * alpha);
                    let u = dl_dpower * dx;
                    row_1 += dl_dpower;
                    row_x += u;
                    m_xx = u.mul_add(dx, m_xx);
                },
            );
            if !GRAD {
                return;
            }
            let dy = L::splat(sp.row_dy(rect, row));
            m_1 += row_1;
            m_x += row_x;
            let row_y = row_1 * dy;
            m_y += row_y;
            m_yy = row_y.mul_add(dy, m_yy);
            m_xy = row_x.mul_add(dy, m_xy);
        },
    );
    if !GRAD {
        return ProjectedGrad::default();
    }
    // power = -(a dx^2 + c dy^2) / 2 - b dx dy with (dx, dy) = mean - pixel,
    // and dL/d(opacity) = sum dL/d(alpha) gauss = sum p / opacity where alpha is free
    // (visible Gaussians have opacity >= ALPHA_MIN).
    let [a, b, c] = sp.conic;
    let (mx, my) = (m_x.reduce_add(), m_y.reduce_add());
    ProjectedGrad {
        mean2d: Vec2::new(-(a * mx + b * my), -(c * my + b * mx)),
        conic: [-0.5 * m_xx.reduce_add(), -m_xy.reduce_add(), -0.5 * m_yy.reduce_add()],
        color: Vec3::new(acc_col[0].reduce_add(), acc_col[1].reduce_add(), acc_col[2].reduce_add()),
        opacity: m_1.reduce_add() / sp.opacity,
        depth: acc_d.reduce_add(),
    }
}
