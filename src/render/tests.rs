//! Rasterizer tests: the tiled renderer against a per-pixel reference, and
//! every gradient group against central finite differences.

use glam::{Mat4, Vec3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::lanes::{dispatch, Kernels, Lanes};
use super::project::{project_one, ProjectionCamera, ALPHA_MIN};
use super::raster::{ALPHA_MAX, TRANSMITTANCE_MIN};
use super::*;
use crate::camera::{Camera, Intrinsics};
use crate::splat::{logit, ParamGroup};

fn camera(w: u32, h: u32) -> Camera {
    let k = Intrinsics {
        width: w,
        height: h,
        fx: 0.9 * w as f32,
        fy: 0.95 * w as f32,
        cx: 0.52 * w as f32,
        cy: 0.47 * h as f32,
    };
    // A camera a little off-axis so every rotation entry matters.
    Camera::look_at(k, Vec3::new(0.3, -0.2, -3.0), Vec3::new(0.05, 0.02, 0.0), Vec3::new(0.1, -1.0, 0.0))
}

fn random_set(
    rng: &mut ChaCha8Rng,
    n: usize,
    degree: u32,
    spread: f32,
    scale: (f32, f32),
    opacity: (f32, f32),
) -> GaussianSet {
    let mut gs = GaussianSet::new(degree);
    let rest_w = gs.width(ParamGroup::ShRest);
    for _ in 0..n {
        let mean = Vec3::new(
            rng.random_range(-spread..spread),
            rng.random_range(-spread..spread),
            rng.random_range(-0.5..0.5),
        );
        let ls = Vec3::new(
            rng.random_range(scale.0..scale.1),
            rng.random_range(scale.0..scale.1),
            rng.random_range(scale.0..scale.1),
        );
        let q = [
            rng.random_range(0.5..1.0),
            rng.random_range(-0.5..0.5),
            rng.random_range(-0.5..0.5),
            rng.random_range(-0.5..0.5),
        ];
        let dc = [rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0)];
        let rest: Vec<f32> = (0..rest_w).map(|_| rng.random_range(-0.3..0.3)).collect();
        gs.push(mean, ls.exp().map(f32::ln), q, logit(rng.random_range(opacity.0..opacity.1)), dc, &rest);
    }
    gs
}

/// The obviously correct renderer: every pixel composites every projected
/// Gaussian in (depth, index) order with the stated rules; no tiles, no boxes.
fn reference_render(gs: &GaussianSet, cam: &Camera, bg: Vec3) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
    let pc = ProjectionCamera::new(cam);
    let mut proj: Vec<(usize, project::Projected)> =
        (0..gs.len()).filter_map(|i| project_one(gs, i, &pc, gs.sh_degree).map(|p| (i, p))).collect();
    proj.sort_by(|a, b| a.1.depth.total_cmp(&b.1.depth).then(a.0.cmp(&b.0)));
    let (w, h) = (cam.width(), cam.height());
    let mut color = vec![0.0; (3 * w * h) as usize];
    let mut alpha = vec![0.0; (w * h) as usize];
    let mut depth = vec![0.0; (w * h) as usize];
    for py in 0..h {
        for px in 0..w {
            let (mut t, mut c, mut d) = (1.0f32, Vec3::ZERO, 0.0f32);
            for (_, p) in &proj {
                let dx = p.mean2d.x - (px as f32 + 0.5);
                let dy = p.mean2d.y - (py as f32 + 0.5);
                let power = -0.5 * (p.conic[0] * dx * dx + p.conic[2] * dy * dy) - p.conic[1] * dx * dy;
                if power > 0.0 {
                    continue;
                }
                let a = (p.opacity * power.exp()).min(ALPHA_MAX);
                if a < ALPHA_MIN {
                    continue;
                }
                if t * (1.0 - a) < TRANSMITTANCE_MIN {
                    break;
                }
                c += p.color * a * t;
                d += p.depth * a * t;
                t *= 1.0 - a;
            }
            let o = (py * w + px) as usize;
            color[3 * o..3 * o + 3].copy_from_slice(&(c + bg * t).to_array());
            alpha[o] = 1.0 - t;
            depth[o] = d;
        }
    }
    (color, alpha, depth)
}

fn max_abs_diff(a: &[f32], b: &[f32]) -> f32 {
    a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0, f32::max)
}

/// A scene of small and large Gaussians, some partly off-image, dense enough
/// that pixels terminate early and opaque ones hit the 0.99 clamp.
fn dense_scene() -> (GaussianSet, Camera, Vec3) {
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let mut gs = random_set(&mut rng, 400, 3, 1.3, (-4.5, -2.0), (0.05, 0.99));
    let dense = random_set(&mut rng, 300, 3, 0.3, (-3.0, -2.0), (0.9, 0.999));
    for g in ParamGroup::ALL {
        let extra = dense.group(g).clone();
        gs.group_mut(g).extend(extra);
    }
    (gs, camera(75, 53), Vec3::new(0.1, 0.6, 0.3)) // not a multiple of the tile size
}

#[test]
fn tiled_renderer_matches_per_pixel_reference_with_every_kernel_set() {
    let (gs, cam, bg) = dense_scene();
    let r = render(&gs, &cam, &RenderOptions::uniform(bg));
    let (c, a, d) = reference_render(&gs, &cam, bg);
    assert!(r.visible_count() > 500, "scene should be mostly visible, got {}", r.visible_count());
    assert!(a.iter().any(|v| *v > 1.0 - 2.0 * TRANSMITTANCE_MIN), "some pixels should terminate early");
    assert!(a.iter().any(|v| *v < 0.5), "some pixels should be thin");
    for k in Kernels::available() {
        let img = raster::rasterize_with(k, &r.bins, cam.width(), cam.height(), raster::Background::Uniform(bg));
        let name = k.name();
        assert!(max_abs_diff(&img.color, &c) < 1e-5, "{name}: colour differs by {}", max_abs_diff(&img.color, &c));
        assert!(max_abs_diff(&img.alpha, &a) < 1e-5, "{name}: alpha differs by {}", max_abs_diff(&img.alpha, &a));
        assert!(max_abs_diff(&img.depth, &d) < 1e-5, "{name}: depth differs by {}", max_abs_diff(&img.depth, &d));
    }
}

#[test]
fn every_kernel_set_gives_the_portable_gradients() {
    let (gs, cam, bg) = dense_scene();
    let r = render(&gs, &cam, &RenderOptions::uniform(bg));
    let n = (cam.width() * cam.height()) as usize;
    let w = weights(n);
    let (w_alpha, w_depth): (Vec<f32>, Vec<f32>) =
        (0..n).map(|i| ((i as f32 * 0.37).sin(), (i as f32 * 0.11).cos())).unzip();
    let grads = raster::TileGrads { color: &w.c, alpha: Some(&w_alpha), depth: Some(&w_depth), wanted: None };
    let run = |k| {
        raster::rasterize_backward_with(
            k,
            &r.bins,
            cam.width(),
            cam.height(),
            raster::Background::Uniform(bg),
            &r.image,
            &grads,
        )
    };
    let portable = Kernels::named("portable").expect("the portable kernels run everywhere");
    let (want, want_bg) = run(portable);
    let flat = |g: &[super::project::ProjectedGrad]| -> Vec<f32> {
        g.iter()
            .flat_map(|g| {
                [
                    g.mean2d.x, g.mean2d.y, g.conic[0], g.conic[1], g.conic[2], g.color.x, g.color.y, g.color.z,
                    g.opacity, g.depth,
                ]
            })
            .collect()
    };
    let want_flat = flat(&want);
    let scale = want_flat.iter().fold(0.0f32, |m, v| m.max(v.abs()));
    assert!(scale > 0.0);
    for k in Kernels::available() {
        let (got, got_bg) = run(k);
        let err = max_abs_diff(&flat(&got), &want_flat) / scale;
        assert!(
            err < 1e-4,
            "{}: gradients differ from the portable kernels' by {err} (relative to the largest)",
            k.name()
        );
        assert!((got_bg - want_bg).abs().max_element() < 1e-4 * want_bg.abs().max_element().max(1.0), "{}", k.name());
    }
}

#[test]
fn the_active_kernel_set_is_the_fastest_this_cpu_runs() {
    let all = Kernels::available();
    assert_eq!(all.last().map(|k| k.name()), Some("portable"), "{all:?}");
    assert_eq!(Kernels::active(), all[0]);
    assert!(Kernels::named("no-such-set").is_err());
}

#[test]
fn gaussian_behind_camera_or_off_image_is_culled() {
    let mut gs = GaussianSet::new(0);
    let cam = Camera::new(Intrinsics::from_fov_x(32, 32, 1.0), Mat4::IDENTITY);
    gs.push(Vec3::new(0.0, 0.0, -1.0), Vec3::splat(-2.0), [1.0, 0.0, 0.0, 0.0], 2.0, [1.0; 3], &[]);
    gs.push(Vec3::new(50.0, 0.0, 1.0), Vec3::splat(-2.0), [1.0, 0.0, 0.0, 0.0], 2.0, [1.0; 3], &[]);
    gs.push(Vec3::new(0.0, 0.0, 2.0), Vec3::splat(-2.0), [1.0, 0.0, 0.0, 0.0], 2.0, [1.0; 3], &[]);
    let r = render(&gs, &cam, &RenderOptions::default());
    assert!(r.projected[0].is_none() && r.projected[1].is_none());
    assert!(r.projected[2].is_some());
    // The visible one sits at the image centre: pixel (15/16, 15/16) region is bright.
    let centre = (16 * 32 + 16) as usize;
    assert!(r.image.alpha[centre] > 0.5);
}

/// A smooth scene for finite differences: few large Gaussians whose 1/255
/// cut-off ellipses enclose the whole (small) image, so no pixel crosses the
/// skip threshold or the transmittance stop under a small perturbation.
fn smooth_scene(degree: u32) -> (GaussianSet, Camera) {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let gs = random_set(&mut rng, 6, degree, 0.08, (-0.25, -0.05), (0.25, 0.5));
    let cam = camera(16, 14);
    (gs, cam)
}

/// Weights defining L = sum w_c C + w_a A + w_d D (accumulated in f64).
struct Weights {
    c: Vec<f32>,
    a: Vec<f32>,
    d: Vec<f32>,
}

fn weights(n: usize) -> Weights {
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    Weights {
        c: (0..3 * n).map(|_| rng.random_range(-1.0..1.0)).collect(),
        a: (0..n).map(|_| rng.random_range(-1.0..1.0)).collect(),
        d: (0..n).map(|_| rng.random_range(-0.3..0.3)).collect(),
    }
}

fn loss(gs: &GaussianSet, cam: &Camera, opts: &RenderOptions, w: &Weights) -> f64 {
    let r = render(gs, cam, opts);
    let dot = |a: &[f32], b: &[f32]| a.iter().zip(b).map(|(x, y)| *x as f64 * *y as f64).sum::<f64>();
    dot(&r.image.color, &w.c) + dot(&r.image.alpha, &w.a) + dot(&r.image.depth, &w.d)
}

/// Central-difference step. The renders are f32: with eps = 1e-3 rounding
/// noise (~1e-6 of the loss) gives ~2e-3 relative error in the difference,
/// while at 1e-2 the truncation error (O(eps^2) on this smooth scene) stays
/// below 1e-4, so 1e-2 is the step at which a 1e-3 tolerance is meaningful.
const FD_EPS: f32 = 1e-2;

/// Central differences with eps = FD_EPS on every parameter of `group`; the
/// group's gradient vector must match to 1e-3 relative (in norm) and each
/// entry to 1e-3 absolute or 1e-2 relative.
fn check_group(group: ParamGroup, degree: u32) {
    check_group_with(group, degree, |_| RenderOptions::uniform(Vec3::new(0.3, 0.2, 0.7)));
}

/// [`check_group`] with the render options `options(camera)` gives.
fn check_group_with(group: ParamGroup, degree: u32, options: impl Fn(&Camera) -> RenderOptions) {
    let (gs, cam) = smooth_scene(degree);
    let opts = options(&cam);
    let n = (cam.width() * cam.height()) as usize;
    let w = weights(n);
    let r = render(&gs, &cam, &opts);
    assert_eq!(r.visible_count(), gs.len());
    let g = backward(&gs, &r, &w.c, Some(&w.a), Some(&w.d));
    let analytic = g.params.group(group).clone();
    let eps = FD_EPS;
    let mut fd = vec![0.0f64; analytic.len()];
    for (j, slot) in fd.iter_mut().enumerate() {
        let mut p = gs.clone();
        p.group_mut(group)[j] += eps;
        let lp = loss(&p, &cam, &opts, &w);
        p.group_mut(group)[j] -= 2.0 * eps;
        let lm = loss(&p, &cam, &opts, &w);
        *slot = (lp - lm) / (2.0 * eps as f64);
    }
    let diff: f64 = fd.iter().zip(&analytic).map(|(f, a)| (f - *a as f64).powi(2)).sum::<f64>().sqrt();
    let norm: f64 = fd.iter().map(|f| f * f).sum::<f64>().sqrt();
    assert!(norm > 1e-3, "{group:?}: gradient too small to test ({norm})");
    assert!(diff / norm < 1e-3, "{group:?}: relative error {} (fd {fd:?} analytic {analytic:?})", diff / norm);
    for (j, (f, a)) in fd.iter().zip(&analytic).enumerate() {
        let err = (f - *a as f64).abs();
        assert!(err < 1e-3 || err < 1e-2 * f.abs(), "{group:?}[{j}]: fd {f} analytic {a}");
    }
}

#[test]
fn gradient_means_matches_finite_differences() {
    check_group(ParamGroup::Means, 3);
}

#[test]
fn gradient_log_scales_matches_finite_differences() {
    check_group(ParamGroup::LogScales, 3);
}

#[test]
fn gradient_rotations_matches_finite_differences() {
    check_group(ParamGroup::Rotations, 3);
}

#[test]
fn gradient_opacity_matches_finite_differences() {
    check_group(ParamGroup::OpacityLogits, 3);
}

#[test]
fn gradient_sh_dc_matches_finite_differences() {
    check_group(ParamGroup::ShDc, 3);
}

#[test]
fn gradient_sh_rest_matches_finite_differences() {
    check_group(ParamGroup::ShRest, 3);
}

/// A background per pixel: a smooth colour ramp across the image.
fn ramp_background(cam: &Camera) -> RenderOptions {
    let (w, h) = (cam.width() as usize, cam.height() as usize);
    let img: Vec<f32> = (0..w * h)
        .flat_map(|o| {
            let (x, y) = ((o % w) as f32 / w as f32, (o / w) as f32 / h as f32);
            [0.2 + 0.6 * x, 0.8 - 0.5 * y, 0.3 + 0.4 * x * y]
        })
        .collect();
    RenderOptions { background_image: Some(img.into()), ..RenderOptions::uniform(Vec3::ZERO) }
}

#[test]
fn gradient_means_with_a_background_image_matches_finite_differences() {
    check_group_with(ParamGroup::Means, 1, ramp_background);
}

#[test]
fn gradient_opacity_with_a_background_image_matches_finite_differences() {
    check_group_with(ParamGroup::OpacityLogits, 1, ramp_background);
}

/// A background image shows through exactly as much as the Gaussians leave
/// transparent, and a region of the image sees its own pixels of it.
#[test]
fn a_background_image_shows_where_the_gaussians_are_transparent() {
    let (gs, cam) = smooth_scene(1);
    let opts = ramp_background(&cam);
    let plate = opts.background_image.clone().unwrap();
    let with = render(&gs, &cam, &opts);
    let without = render(&gs, &cam, &RenderOptions::uniform(Vec3::ZERO));
    for o in 0..without.image.alpha.len() {
        let t = 1.0 - without.image.alpha[o];
        for c in 0..3 {
            let expected = without.image.color[3 * o + c] + t * plate[3 * o + c];
            assert!((with.image.color[3 * o + c] - expected).abs() < 1e-6, "pixel {o}");
        }
    }
    assert!(without.image.alpha.iter().any(|&a| a < 0.5), "the scene must leave some background visible");
    let (w, region) = (cam.width() as usize, [3, 5, 15, 12]);
    let part = crate::render::render_region(&gs, &cam, region, &opts);
    for y in 5..12 {
        for x in 3..15 {
            let (o, r) = (y * w + x, (y - 5) * 12 + (x - 3));
            for c in 0..3 {
                let d = (part.image.color[3 * r + c] - with.image.color[3 * o + c]).abs();
                assert!(d < 1e-5, "pixel ({x}, {y}): {d}");
            }
        }
    }
}

#[test]
fn gradient_background_matches_finite_differences() {
    let (gs, cam) = smooth_scene(1);
    let n = (cam.width() * cam.height()) as usize;
    let w = weights(n);
    let bg = Vec3::new(0.3, 0.2, 0.7);
    let r = render(&gs, &cam, &RenderOptions::uniform(bg));
    let g = backward(&gs, &r, &w.c, Some(&w.a), Some(&w.d));
    for c in 0..3 {
        let mut e = Vec3::ZERO;
        e[c] = 1e-3;
        let lp = loss(&gs, &cam, &RenderOptions::uniform(bg + e), &w);
        let lm = loss(&gs, &cam, &RenderOptions::uniform(bg - e), &w);
        let fd = (lp - lm) / 2e-3;
        assert!(
            (fd - g.background[c] as f64).abs() < 1e-3 * fd.abs().max(1.0),
            "bg[{c}]: fd {fd} analytic {}",
            g.background[c]
        );
    }
}

#[test]
fn mean2d_gradient_norm_is_the_ndc_screen_gradient() {
    // Differentiate the compositing stage alone with respect to one Gaussian's
    // 2D mean; the reported norm is that gradient scaled by half the image size.
    let (gs, cam) = smooth_scene(0);
    let n = (cam.width() * cam.height()) as usize;
    let w = weights(n);
    let opts = RenderOptions::default();
    let r = render(&gs, &cam, &opts);
    let g = backward(&gs, &r, &w.c, Some(&w.a), Some(&w.d));
    let (width, height) = (cam.width(), cam.height());
    let stage_loss = |proj: &[Option<project::Projected>]| {
        // Same tile lists (the perturbation leaves boxes and depths alone), new positions.
        let bins = raster::bin_tiles(proj, width, height);
        assert_eq!(bins.entries, r.bins.entries);
        let out = raster::rasterize(&bins, width, height, raster::Background::Uniform(opts.background));
        let dot = |a: &[f32], b: &[f32]| a.iter().zip(b).map(|(x, y)| *x as f64 * *y as f64).sum::<f64>();
        dot(&out.color, &w.c) + dot(&out.alpha, &w.a) + dot(&out.depth, &w.d)
    };
    for i in 0..gs.len() {
        let mut grad_px = [0.0f64; 2];
        for (axis, slot) in grad_px.iter_mut().enumerate() {
            let eps = 1e-2f32;
            let mut proj = r.projected.clone();
            proj[i].as_mut().expect("visible").mean2d[axis] += eps;
            let lp = stage_loss(&proj);
            proj[i].as_mut().expect("visible").mean2d[axis] -= 2.0 * eps;
            let lm = stage_loss(&proj);
            *slot = (lp - lm) / (2.0 * eps as f64);
        }
        let ndc = ((grad_px[0] * 0.5 * width as f64).powi(2) + (grad_px[1] * 0.5 * height as f64).powi(2)).sqrt();
        let reported = g.mean2d_grad_norm[i] as f64;
        assert!((ndc - reported).abs() < 1e-3 * ndc.max(1.0), "gaussian {i}: ndc {ndc} reported {reported}");
    }
}

#[test]
fn colour_only_backward_equals_backward_with_zero_aux_gradients() {
    let mut rng = ChaCha8Rng::seed_from_u64(2);
    let gs = random_set(&mut rng, 300, 2, 1.0, (-4.0, -2.5), (0.1, 0.95));
    let cam = camera(40, 33);
    let r = render(&gs, &cam, &RenderOptions::uniform(Vec3::splat(0.4)));
    let n = (cam.width() * cam.height()) as usize;
    let w = weights(n);
    let zeros = vec![0.0; n];
    let a = backward(&gs, &r, &w.c, None, None);
    let b = backward(&gs, &r, &w.c, Some(&zeros), Some(&zeros));
    assert!(a.params.means.iter().any(|v| *v != 0.0));
    assert_eq!(a.params, b.params);
    assert_eq!(a.background, b.background);
}

#[test]
fn a_region_renders_and_differentiates_as_those_pixels_of_the_whole_image() {
    let (gs, cam, bg) = dense_scene();
    let opts = RenderOptions::uniform(bg);
    let full = render(&gs, &cam, &opts);
    let [x0, y0, x1, y1] = [9u32, 5, 50, 40];
    let part = render_region(&gs, &cam, [x0, y0, x1, y1], &opts);
    assert_eq!((part.width, part.height), (x1 - x0, y1 - y0));
    let (w, rw) = (cam.width() as usize, (x1 - x0) as usize);
    let crop = |img: &[f32], ch: usize| -> Vec<f32> {
        (y0 as usize..y1 as usize)
            .flat_map(|y| img[ch * (y * w + x0 as usize)..ch * (y * w + x1 as usize)].to_vec())
            .collect()
    };
    assert!(max_abs_diff(&part.image.color, &crop(&full.image.color, 3)) < 1e-5);
    assert!(max_abs_diff(&part.image.alpha, &crop(&full.image.alpha, 1)) < 1e-5);
    // A loss on the region's pixels: its weights, and zero outside in the whole image.
    let n = (cam.width() * cam.height()) as usize;
    let weights = weights(n).c;
    let mut outside_zero = vec![0.0; 3 * n];
    for y in y0 as usize..y1 as usize {
        let row = 3 * (y * w + x0 as usize)..3 * (y * w + x1 as usize);
        outside_zero[row.clone()].copy_from_slice(&weights[row]);
    }
    let a = backward(&gs, &full, &outside_zero, None, None);
    let b = backward(&gs, &part, &crop(&outside_zero, 3), None, None);
    assert_eq!(rw * (y1 - y0) as usize * 3, crop(&outside_zero, 3).len());
    assert!(a.params.means.iter().any(|v| *v != 0.0));
    for g in ParamGroup::ALL {
        let (ga, gb) = (a.params.group(g), b.params.group(g));
        let scale = ga.iter().fold(0.0f32, |m, v| m.max(v.abs())).max(1e-6);
        assert!(max_abs_diff(ga, gb) <= 1e-4 * scale, "{g:?}: {} against {scale}", max_abs_diff(ga, gb));
    }
}

#[test]
fn sets_rendered_together_equal_their_union_and_each_gets_its_rows_gradients() {
    let (gs, cam, bg) = dense_scene();
    let opts = RenderOptions::uniform(bg);
    let split = gs.len() / 3;
    let (a, b) = (gs.rows(0..split), gs.rows(split..gs.len()));
    let whole = [0, 0, cam.width(), cam.height()];
    let together = render_sets(&[&a, &b], &cam, whole, &opts);
    let union = render(&gs, &cam, &opts);
    assert_eq!(together.image.color, union.image.color);
    assert_eq!(together.image.depth, union.image.depth);
    let w = weights((cam.width() * cam.height()) as usize);
    let per_set = backward_sets(&[&a, &b], &together, &w.c, Some(&w.a), Some(&w.d));
    let all = backward(&gs, &union, &w.c, Some(&w.a), Some(&w.d));
    assert_eq!(per_set.len(), 2);
    assert!(all.params.means.iter().any(|v| *v != 0.0));
    assert_eq!(per_set[0].params, all.params.rows(0..split));
    assert_eq!(per_set[1].params, all.params.rows(split..gs.len()));
    assert_eq!(per_set[1].radius, all.radius[split..]);
    assert_eq!(per_set[0].visible, all.visible[..split]);
    assert_eq!(per_set[1].mean2d_grad_norm, all.mean2d_grad_norm[split..]);
    assert_eq!(per_set[0].background, all.background);
}

#[test]
fn gradients_of_the_wanted_gaussians_alone_are_the_full_passes_to_the_bit() {
    let (gs, cam, bg) = dense_scene();
    let r = render(&gs, &cam, &RenderOptions::uniform(bg));
    let w = weights((cam.width() * cam.height()) as usize);
    // Every third Gaussian not wanted: wanted ones in front of, between and behind them.
    let wanted: Vec<bool> = (0..gs.len()).map(|i| i % 3 != 1).collect();
    for aux in [false, true] {
        let (a, d) = if aux { (Some(&w.a[..]), Some(&w.d[..])) } else { (None, None) };
        let mut all = backward(&gs, &r, &w.c, a, d);
        let only = backward_wanted(&gs, &r, &w.c, a, d, &wanted);
        let skipped_visible = (0..gs.len()).filter(|&i| !wanted[i] && all.visible[i]).count();
        assert!(skipped_visible > 10, "{skipped_visible} Gaussians not wanted in view");
        assert!((0..gs.len()).any(|i| !wanted[i] && all.params.means[3 * i] != 0.0));
        // What a backend that computes every row leaves after keeping the wanted ones.
        all.keep_wanted(&wanted);
        assert_eq!(only.params, all.params, "aux {aux}");
        assert_eq!(only.mean2d_grad_norm, all.mean2d_grad_norm);
        assert_eq!(only.visible, all.visible);
        assert_eq!(only.radius, all.radius);
        assert_eq!(only.background, all.background);
    }
    // Each kernel set, against its own full pass.
    for kernels in Kernels::available() {
        let run = |wanted: Option<&[bool]>| {
            let grads = raster::TileGrads { color: &w.c, alpha: Some(&w.a), depth: None, wanted };
            let background = raster::Background::Uniform(bg);
            raster::rasterize_backward_with(kernels, &r.bins, cam.width(), cam.height(), background, &r.image, &grads)
        };
        let ((full, full_bg), (only, only_bg)) = (run(None), run(Some(&wanted)));
        assert_eq!(full_bg, only_bg);
        for (i, (f, o)) in full.iter().zip(&only).enumerate() {
            let bits = |g: &super::project::ProjectedGrad| {
                let mut v = vec![g.mean2d.x, g.mean2d.y, g.opacity, g.depth, g.color.x, g.color.y, g.color.z];
                v.extend(g.conic);
                v.into_iter().map(f32::to_bits).collect::<Vec<_>>()
            };
            let want = if wanted[i] { bits(f) } else { bits(&Default::default()) };
            assert_eq!(bits(o), want, "Gaussian {i}, {}", kernels.name());
        }
    }
}

#[test]
fn a_repaint_gives_the_whole_render_of_the_changed_set_to_the_bit() {
    let (gs, _, bg) = dense_scene();
    // A larger image than the scene's, so most tiles are far from what changes.
    let cam = camera(170, 121);
    for opts in [RenderOptions::uniform(bg), ramp_background(&cam)] {
        let mut painted = Repaintable::new(&gs, &cam, &opts);
        assert_eq!(painted.color(), render(&gs, &cam, &opts).image.color);
        let mut now = gs.clone();
        // Two rounds, the second on the first's result: small Gaussians moved
        // (one behind the camera) and made more opaque.
        for (round, rows) in [vec![3usize, 17, 40, 41, 250], vec![17, 99, 410, 650]].into_iter().enumerate() {
            let keep: Vec<bool> = (0..gs.len()).map(|i| rows.contains(&i)).collect();
            let mut changed = now.subset(&keep);
            for (j, m) in changed.means.chunks_mut(3).enumerate() {
                m[0] += 0.15 * (j as f32 + 1.0) * if round == 0 { 1.0 } else { -1.0 };
                m[1] -= 0.1;
                if round == 1 && j == 0 {
                    m[2] -= 10.0;
                }
            }
            changed.opacity_logits.iter_mut().for_each(|o| *o += 1.0);
            let repaint = painted.repaint(&rows, &changed);
            for (j, &i) in rows.iter().enumerate() {
                for g in ParamGroup::ALL {
                    let w = now.width(g);
                    now.group_mut(g)[w * i..w * i + w].copy_from_slice(&changed.group(g)[w * j..w * j + w]);
                }
            }
            let whole = render(&now, &cam, &opts).image.color;
            let pixels = (cam.width() * cam.height()) as usize;
            assert!(
                !repaint.pixels.is_empty() && repaint.pixels.len() < pixels / 2,
                "{} of {pixels}",
                repaint.pixels.len()
            );
            for (&o, rgb) in repaint.pixels.iter().zip(&repaint.colors) {
                assert_eq!(rgb[..], whole[3 * o..3 * o + 3], "pixel {o}");
            }
            painted.apply(&repaint);
            assert_eq!(painted.color(), whole, "round {round}");
            assert_ne!(whole, render(&gs, &cam, &opts).image.color);
        }
    }
}

#[test]
fn fast_exp_matches_f64_exp_on_nonpositive_arguments_with_every_kernel_set() {
    for k in Kernels::available() {
        let exp = |x: f32| dispatch!(k, |L; x: f32| -> f32 { raster::exp_nonpositive(L::splat(x)).to_array()[0] });
        let mut worst = 0.0f64;
        for i in 0..=200_000 {
            let x = -87.0 * i as f32 / 200_000.0;
            let want = (x as f64).exp();
            worst = worst.max((exp(x) as f64 / want - 1.0).abs());
        }
        assert!(worst < 4e-7, "{}: relative error {worst}", k.name());
        let below = exp(-1e4);
        assert!(below < 1e-37, "{}: far below the range the result is ~0, got {below}", k.name());
    }
}

#[test]
fn depth_keys_order_as_depth_then_index() {
    let depths =
        [f32::NEG_INFINITY, -3.5, -1e-30, -0.0, 0.0, 1e-30, 0.25, 0.25, 7.0, f32::MAX, f32::INFINITY, f32::NAN];
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let mut pairs: Vec<(f32, u32)> =
        (0..400).map(|_| (depths[rng.random_range(0..depths.len())], rng.random_range(0..50u32))).collect();
    pairs.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    let mut keys: Vec<u64> = pairs.iter().map(|&(d, i)| raster::depth_key(d, i)).collect();
    let by_pair = keys.clone();
    keys.sort_unstable();
    assert_eq!(keys, by_pair, "integer keys sort as (depth by total_cmp, index)");
    // Distinct pairs give distinct keys; equal pairs equal ones.
    for (w, k) in pairs.windows(2).zip(by_pair.windows(2)) {
        let same = w[0].0.to_bits() == w[1].0.to_bits() && w[0].1 == w[1].1;
        assert_eq!(same, k[0] == k[1]);
    }
}
