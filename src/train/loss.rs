//! Photometric loss of 3DGS: `L = (1 - λ) L1 + λ (1 - SSIM)` with λ = 0.2, and its
//! exact gradient with respect to the rendered image.
//!
//! SSIM is computed as the original 3DGS `ssim()`: an 11-tap Gaussian window
//! (σ = 1.5) applied per channel as a "same"-size convolution with zero padding,
//! C1 = 0.01², C2 = 0.03², averaged over every pixel and channel. The 2D window
//! is the outer product of the 1D one, so each convolution is two 1D passes;
//! with a symmetric window and zero padding the convolution is self-adjoint,
//! so the backward pass uses the same blur.
//!
//! Images are row-major `H x W x 3` f32 slices with values in [0, 1].

use rayon::prelude::*;

use crate::render::lanes::{dispatch, Kernels};

/// Weight of the D-SSIM term (3DGS `lambda_dssim`).
pub const LAMBDA_DSSIM: f32 = 0.2;
const C1: f32 = 0.01 * 0.01;
const C2: f32 = 0.03 * 0.03;
const RADIUS: usize = 5;
const TAPS: usize = 2 * RADIUS + 1;
const SIGMA: f32 = 1.5;

/// The loss value, its parts, and dL/d(rendered image) in the image layout.
#[derive(Clone, Debug)]
pub struct LossOutput {
    pub loss: f32,
    pub l1: f32,
    pub ssim: f32,
    pub grad: Vec<f32>,
}

/// Normalised 1D Gaussian window, as 3DGS `gaussian(window_size, sigma)`.
fn window() -> [f32; TAPS] {
    let mut w = [0.0f32; TAPS];
    for (i, v) in w.iter_mut().enumerate() {
        let d = i as f32 - RADIUS as f32;
        *v = (-d * d / (2.0 * SIGMA * SIGMA)).exp();
    }
    let sum: f32 = w.iter().sum();
    w.map(|v| v / sum)
}

/// Rows per rayon task: keeps tasks around 16k pixels so small images stay serial.
fn rows_per_task(width: usize) -> usize {
    (16_384 / width.max(1)).max(1)
}

/// Separable Gaussian blur of one `h x w` plane, "same" size, zero padding. Taps
/// are paired by symmetry (`k[5-j] == k[5+j]`) to halve the multiplies. The
/// loops run with the CPU's widest kernel set (`Kernels::active`): the same
/// arithmetic per pixel, more pixels per instruction.
fn blur(src: &[f32], w: usize, h: usize, k: &[f32; TAPS]) -> Vec<f32> {
    let kernels = Kernels::active();
    let rows = rows_per_task(w);
    let mut tmp = vec![0.0f32; w * h];
    tmp.par_chunks_mut(rows * w).zip(src.par_chunks(rows * w)).for_each(|(out_rows, in_rows)| {
        dispatch!(kernels, |_L; out_rows: &mut [f32], in_rows: &[f32], w: usize, k: &[f32; TAPS]| -> () {
            blur_rows(out_rows, in_rows, w, k)
        })
    });
    let mut dst = vec![0.0f32; w * h];
    dst.par_chunks_mut(rows * w).enumerate().for_each(|(ci, out_rows)| {
        let (tmp, first) = (&tmp[..], ci * rows);
        dispatch!(kernels, |_L; out_rows: &mut [f32], tmp: &[f32], first: usize, w: usize, h: usize, k: &[f32; TAPS]| -> () {
            blur_columns(out_rows, tmp, first, w, h, k)
        })
    });
    dst
}

/// The horizontal pass of [`blur`] over whole rows `in_rows` into `out_rows`.
#[inline(always)]
fn blur_rows(out_rows: &mut [f32], in_rows: &[f32], w: usize, k: &[f32; TAPS]) {
    let mut pad = vec![0.0f32; w + 2 * RADIUS];
    for (out, row) in out_rows.chunks_mut(w).zip(in_rows.chunks(w)) {
        pad[RADIUS..RADIUS + w].copy_from_slice(row);
        for (o, &p) in out.iter_mut().zip(row) {
            *o = k[RADIUS] * p;
        }
        for j in 1..=RADIUS {
            let (left, right) = (&pad[RADIUS - j..RADIUS - j + w], &pad[RADIUS + j..RADIUS + j + w]);
            for ((o, &a), &b) in out.iter_mut().zip(left).zip(right) {
                *o += k[RADIUS + j] * (a + b);
            }
        }
    }
}

/// The vertical pass of [`blur`] over the horizontal pass `tmp` (`h` rows of
/// `w`), into `out_rows`, whole rows from row `first` on.
#[inline(always)]
fn blur_columns(out_rows: &mut [f32], tmp: &[f32], first: usize, w: usize, h: usize, k: &[f32; TAPS]) {
    let row = |y: usize| &tmp[y * w..(y + 1) * w];
    for (r, out) in out_rows.chunks_mut(w).enumerate() {
        let y = first + r;
        for (o, &t) in out.iter_mut().zip(row(y)) {
            *o = k[RADIUS] * t;
        }
        for j in 1..=RADIUS {
            let kj = k[RADIUS + j];
            match (y.checked_sub(j), Some(y + j).filter(|&b| b < h)) {
                (Some(a), Some(b)) => {
                    for ((o, &ta), &tb) in out.iter_mut().zip(row(a)).zip(row(b)) {
                        *o += kj * (ta + tb);
                    }
                }
                (Some(e), None) | (None, Some(e)) => {
                    for (o, &t) in out.iter_mut().zip(row(e)) {
                        *o += kj * t;
                    }
                }
                (None, None) => {}
            }
        }
    }
}

/// Sum of the SSIM map over one channel plane and, if `grad_scale` is given,
/// `grad_scale * d(sum)/dx` as a plane.
fn ssim_plane(x: &[f32], y: &[f32], w: usize, h: usize, grad_scale: Option<f32>) -> (f64, Option<Vec<f32>>) {
    let k = window();
    let xx: Vec<f32> = x.iter().map(|v| v * v).collect();
    let yy: Vec<f32> = y.iter().map(|v| v * v).collect();
    let xy: Vec<f32> = x.iter().zip(y).map(|(a, b)| a * b).collect();
    let [mu1, mu2, m11, m22, m12] = [x, y, &xx[..], &yy[..], &xy[..]].map(|s| blur(s, w, h, &k));
    let n = w * h;
    let Some(scale) = grad_scale else {
        let sum = (0..n)
            .into_par_iter()
            .with_min_len(4096)
            .map(|p| {
                let (a1, a2, b1, b2) = terms(mu1[p], mu2[p], m11[p], m22[p], m12[p]);
                ((a1 * a2) / (b1 * b2)) as f64
            })
            .sum();
        return (sum, None);
    };
    // Pointwise partials of the map with respect to mu1, E[x^2] and E[xy], and the map.
    let kernels = Kernels::active();
    let [mut g_mu1, mut g_m11, mut g_m12, mut map] = [(); 4].map(|_| vec![0.0f32; n]);
    (g_mu1.par_chunks_mut(POINTWISE), g_m11.par_chunks_mut(POINTWISE), g_m12.par_chunks_mut(POINTWISE))
        .into_par_iter()
        .zip(map.par_chunks_mut(POINTWISE))
        .enumerate()
        .for_each(|(c, ((gm, g11, g12), map))| {
            let r = c * POINTWISE..c * POINTWISE + gm.len();
            let stats = [&mu1[r.clone()], &mu2[r.clone()], &m11[r.clone()], &m22[r.clone()], &m12[r]];
            let out = [gm, g11, g12, map];
            dispatch!(kernels, |_L; stats: [&[f32]; 5], scale: f32, out: [&mut [f32]; 4]| -> () {
                ssim_partials(stats, scale, out)
            });
        });
    let sum = map.par_chunks(POINTWISE).map(|c| c.iter().map(|&s| f64::from(s)).sum::<f64>()).sum();
    let [b_mu1, b_m11, b_m12] = [g_mu1, g_m11, g_m12].map(|g| blur(&g, w, h, &k));
    let blurred = [&b_mu1[..], &b_m11[..], &b_m12[..]];
    let grad = dispatch!(kernels, |_L; blurred: [&[f32]; 3], x: &[f32], y: &[f32]| -> Vec<f32> {
        ssim_gradient(blurred, x, y)
    });
    (sum, Some(grad))
}

/// dSSIM/dx from the blurred partials (`blurred`: with respect to mu1, E[x^2]
/// and E[xy]) and the images `x`, `y`.
#[inline(always)]
fn ssim_gradient(blurred: [&[f32]; 3], x: &[f32], y: &[f32]) -> Vec<f32> {
    let n = x.len();
    let (b_mu1, b_m11, b_m12, y) = (&blurred[0][..n], &blurred[1][..n], &blurred[2][..n], &y[..n]);
    let mut grad = vec![0.0f32; n];
    for p in 0..n {
        grad[p] = b_mu1[p] + 2.0 * x[p] * b_m11[p] + y[p] * b_m12[p];
    }
    grad
}

/// Pixels per task of the SSIM map's pointwise stage.
const POINTWISE: usize = 4096;

/// The SSIM map's pointwise stage over one run of pixels: from the blurred
/// statistics (mu1, mu2, E[x^2], E[y^2], E[xy]), `scale` times the map's
/// partials with respect to mu1, E[x^2] and E[xy], and the map itself.
#[inline(always)]
fn ssim_partials(stats: [&[f32]; 5], scale: f32, out: [&mut [f32]; 4]) {
    let [mu1, mu2, m11, m22, m12] = stats;
    let [g_mu1, g_m11, g_m12, map] = out;
    let n = g_mu1.len();
    let (mu1, mu2, m11, m22, m12) = (&mu1[..n], &mu2[..n], &m11[..n], &m22[..n], &m12[..n]);
    let (g_m11, g_m12, map) = (&mut g_m11[..n], &mut g_m12[..n], &mut map[..n]);
    for p in 0..n {
        let (u1, u2) = (mu1[p], mu2[p]);
        let (a1, a2, b1, b2) = terms(u1, u2, m11[p], m22[p], m12[p]);
        let inv_b = 1.0 / (b1 * b2);
        let s = a1 * a2 * inv_b;
        // A1 = 2 u1 u2 + C1, A2 = 2 (m12 - u1 u2) + C2, B1 = u1² + u2² + C1, B2 = m11 - u1² + m22 - u2² + C2.
        g_mu1[p] = scale * ((2.0 * u2 * a2 - 2.0 * u2 * a1) * inv_b - s * (2.0 * u1 / b1 - 2.0 * u1 / b2));
        g_m11[p] = scale * (-s / b2);
        g_m12[p] = scale * (2.0 * a1 * inv_b);
        map[p] = s;
    }
}

/// Numerator and denominator factors (A1, A2, B1, B2) of the SSIM map at a pixel.
#[inline]
fn terms(mu1: f32, mu2: f32, m11: f32, m22: f32, m12: f32) -> (f32, f32, f32, f32) {
    let mu12 = mu1 * mu2;
    let (s1, s2) = (mu1 * mu1, mu2 * mu2);
    (2.0 * mu12 + C1, 2.0 * (m12 - mu12) + C2, s1 + s2 + C1, (m11 - s1) + (m22 - s2) + C2)
}

fn check_dims(a: &[f32], b: &[f32], width: usize, height: usize) {
    assert_eq!(a.len(), width * height * 3, "image is not {width}x{height}x3");
    assert_eq!(b.len(), a.len(), "images differ in size");
}

fn channel(img: &[f32], c: usize) -> Vec<f32> {
    img.iter().skip(c).step_by(3).copied().collect()
}

/// SSIM over sums per channel; `grad_scale` scales each channel's gradient plane.
fn ssim_channels(
    a: &[f32],
    b: &[f32],
    width: usize,
    height: usize,
    grad_scale: Option<f32>,
) -> Vec<(f64, Option<Vec<f32>>)> {
    (0..3).into_par_iter().map(|c| ssim_plane(&channel(a, c), &channel(b, c), width, height, grad_scale)).collect()
}

/// Mean SSIM of two images (3DGS `ssim()`), no gradient.
pub fn ssim(a: &[f32], b: &[f32], width: usize, height: usize) -> f32 {
    check_dims(a, b, width, height);
    let sum: f64 = ssim_channels(a, b, width, height, None).iter().map(|(s, _)| s).sum();
    (sum / a.len().max(1) as f64) as f32
}

/// `(1 - lambda) * L1 + lambda * (1 - SSIM)` of `rendered` against `target`, with
/// the gradient with respect to `rendered`. The L1 subgradient at equality is 0.
pub fn loss_and_grad(rendered: &[f32], target: &[f32], width: usize, height: usize, lambda: f32) -> LossOutput {
    check_dims(rendered, target, width, height);
    let total = rendered.len().max(1) as f32;
    let planes = ssim_channels(rendered, target, width, height, Some(-lambda / total));
    let ssim_sum: f64 = planes.iter().map(|(s, _)| s).sum();
    let l1_w = (1.0 - lambda) / total;
    let mut grad = vec![0.0f32; rendered.len()];
    let l1_sum: f64 = grad
        .par_chunks_mut(3)
        .zip(rendered.par_chunks(3).zip(target.par_chunks(3)))
        .enumerate()
        .with_min_len(4096)
        .map(|(p, (g, (r, t)))| {
            let mut s = 0.0f64;
            for c in 0..3 {
                let d = r[c] - t[c];
                s += d.abs() as f64;
                let l1_grad = if d > 0.0 {
                    l1_w
                } else if d < 0.0 {
                    -l1_w
                } else {
                    0.0
                };
                g[c] = l1_grad + planes[c].1.as_ref().map_or(0.0, |plane| plane[p]);
            }
            s
        })
        .sum();
    let l1 = (l1_sum / total as f64) as f32;
    let ssim = (ssim_sum / total as f64) as f32;
    LossOutput { loss: (1.0 - lambda) * l1 + lambda * (1.0 - ssim), l1, ssim, grad }
}

/// Peak signal-to-noise ratio in dB for images in [0, 1]; infinite for equal images.
pub fn psnr(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len(), "images differ in size");
    let se: f64 = a.par_iter().zip(b).with_min_len(4096).map(|(x, y)| ((x - y) as f64).powi(2)).sum();
    let mse = se / a.len().max(1) as f64;
    (10.0 * (1.0 / mse).log10()) as f32
}

#[cfg(test)]
mod depth_tests {
    use super::depth_loss_and_grad;

    #[test]
    fn depth_loss_gradient_matches_finite_differences_and_skips_unknown_pixels() {
        let target = [1.0, 0.0, 2.5, 0.7];
        let rendered = [1.3, 0.4, 2.0, 0.7001];
        let (loss, grad) = depth_loss_and_grad(&rendered, &target, 2.0);
        let expect = 2.0 / 3.0 * (0.3f32.ln_1p() + 0.5f32.ln_1p() + 0.0001f32.ln_1p());
        assert!((loss - expect).abs() < 1e-5, "{loss} vs {expect}");
        assert_eq!(grad[1], 0.0, "depth 0 is unknown");
        for k in [0, 2] {
            let h = 1e-3;
            let mut p = rendered;
            p[k] += h;
            let mut m = rendered;
            m[k] -= h;
            let fd = (depth_loss_and_grad(&p, &target, 2.0).0 - depth_loss_and_grad(&m, &target, 2.0).0) / (2.0 * h);
            assert!((fd - grad[k]).abs() < 1e-3, "pixel {k}: {fd} vs {}", grad[k]);
        }
        assert_eq!(depth_loss_and_grad(&rendered, &[0.0; 4], 1.0).0, 0.0);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn window64() -> Vec<f64> {
        let w: Vec<f64> = (0..TAPS).map(|i| (-((i as f64 - 5.0).powi(2)) / (2.0 * 1.5 * 1.5)).exp()).collect();
        let s: f64 = w.iter().sum();
        w.iter().map(|v| v / s).collect()
    }

    /// Obviously correct f64 reference: direct 2D windowed sums with zero padding.
    fn reference_loss(x: &[f64], y: &[f64], w: usize, h: usize, lambda: f64) -> (f64, f64) {
        let k = window64();
        let blur = |f: &dyn Fn(usize) -> f64, c: usize, px: usize, py: usize| {
            let mut s = 0.0;
            for dy in 0..TAPS {
                for dx in 0..TAPS {
                    let (qx, qy) = ((px + dx) as isize - 5, (py + dy) as isize - 5);
                    if qx >= 0 && qy >= 0 && (qx as usize) < w && (qy as usize) < h {
                        s += k[dx] * k[dy] * f(3 * (qy as usize * w + qx as usize) + c);
                    }
                }
            }
            s
        };
        let (c1, c2) = (1e-4, 9e-4);
        let mut ssim_sum = 0.0;
        for c in 0..3 {
            for py in 0..h {
                for px in 0..w {
                    let mu1 = blur(&|i| x[i], c, px, py);
                    let mu2 = blur(&|i| y[i], c, px, py);
                    let s11 = blur(&|i| x[i] * x[i], c, px, py) - mu1 * mu1;
                    let s22 = blur(&|i| y[i] * y[i], c, px, py) - mu2 * mu2;
                    let s12 = blur(&|i| x[i] * y[i], c, px, py) - mu1 * mu2;
                    ssim_sum +=
                        ((2.0 * mu1 * mu2 + c1) * (2.0 * s12 + c2)) / ((mu1 * mu1 + mu2 * mu2 + c1) * (s11 + s22 + c2));
                }
            }
        }
        let n = x.len() as f64;
        let ssim = ssim_sum / n;
        let l1 = x.iter().zip(y).map(|(a, b)| (a - b).abs()).sum::<f64>() / n;
        ((1.0 - lambda) * l1 + lambda * (1.0 - ssim), ssim)
    }

    /// Smooth random image plus a target differing by at least 0.05 everywhere
    /// (so L1 stays differentiable under the finite-difference steps).
    fn image_pair(w: usize, h: usize, seed: u64) -> (Vec<f32>, Vec<f32>) {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let x: Vec<f32> = (0..w * h * 3)
            .map(|i| {
                let (p, c) = (i / 3, i % 3);
                let (px, py) = ((p % w) as f32, (p / w) as f32);
                0.5 + 0.3 * (0.4 * px + 0.7 * py + c as f32).sin() + rng.random_range(-0.1..0.1)
            })
            .collect();
        let y = x
            .iter()
            .map(|v| {
                let d = rng.random_range(0.05f32..0.2);
                if rng.random_bool(0.5) {
                    v + d
                } else {
                    v - d
                }
            })
            .collect();
        (x, y)
    }

    #[test]
    fn ssim_of_an_image_with_itself_is_one() {
        let (x, _) = image_pair(40, 23, 1);
        assert!((ssim(&x, &x, 40, 23) - 1.0).abs() < 1e-5);
        let out = loss_and_grad(&x, &x, 40, 23, LAMBDA_DSSIM);
        assert!(out.loss.abs() < 1e-5 && out.l1 == 0.0);
        // SSIM is maximal at x = y, so its gradient vanishes there.
        assert!(out.grad.iter().all(|g| g.abs() < 1e-6));
    }

    /// Constant images have a closed form: with window mass s inside the image at a
    /// pixel, mu = a s, sigma² = a² s (1 - s), sigma12 = a b s (1 - s).
    #[test]
    fn ssim_of_constant_images_matches_closed_form() {
        let (w, h, a, b) = (17usize, 12usize, 0.3f64, 0.7f64);
        let k = window64();
        let mass = |i: usize, n: usize| (0..TAPS).filter(|&d| (i + d) >= 5 && i + d - 5 < n).map(|d| k[d]).sum::<f64>();
        let mut sum = 0.0;
        for py in 0..h {
            for px in 0..w {
                let s = mass(px, w) * mass(py, h);
                let v = s * (1.0 - s);
                sum += ((2.0 * a * b * s * s + 1e-4) * (2.0 * a * b * v + 9e-4))
                    / (((a * a + b * b) * s * s + 1e-4) * ((a * a + b * b) * v + 9e-4));
            }
        }
        let want = sum / (w * h) as f64;
        let x = vec![a as f32; w * h * 3];
        let y = vec![b as f32; w * h * 3];
        let got = ssim(&x, &y, w, h) as f64;
        assert!((got - want).abs() < 1e-5, "{got} vs {want}");
        // Interior pixels alone would give (2ab + C1) / (a² + b² + C1) ≈ 0.724; borders differ.
        assert!(want > 0.5 && want < 0.95);
    }

    #[test]
    fn matches_the_direct_reference() {
        let (w, h) = (19, 14);
        let (x, y) = image_pair(w, h, 2);
        let to64 = |v: &[f32]| v.iter().map(|&a| a as f64).collect::<Vec<_>>();
        let (want_loss, want_ssim) = reference_loss(&to64(&x), &to64(&y), w, h, 0.2);
        let out = loss_and_grad(&x, &y, w, h, LAMBDA_DSSIM);
        assert!((out.loss as f64 - want_loss).abs() < 1e-6, "{} vs {want_loss}", out.loss);
        assert!((out.ssim as f64 - want_ssim).abs() < 1e-6);
        assert!((ssim(&x, &y, w, h) as f64 - want_ssim).abs() < 1e-6);
    }

    /// Central differences of the f64 reference loss, eps = 1e-4, at every pixel of a
    /// 13x9 image (small enough that every pixel feels the border padding). The
    /// analytic gradient is f32; tolerance |analytic - fd| <= 1e-5 * max|fd| (observed
    /// worst: 5e-7 * max|fd|).
    #[test]
    fn gradient_matches_central_differences_of_the_reference() {
        let (w, h, eps) = (13, 9, 1e-4);
        let (x, y) = image_pair(w, h, 3);
        let out = loss_and_grad(&x, &y, w, h, LAMBDA_DSSIM);
        let mut x64: Vec<f64> = x.iter().map(|&a| a as f64).collect();
        let y64: Vec<f64> = y.iter().map(|&a| a as f64).collect();
        let fd: Vec<f64> = (0..x.len())
            .map(|i| {
                let x0 = x64[i];
                x64[i] = x0 + eps;
                let plus = reference_loss(&x64, &y64, w, h, 0.2).0;
                x64[i] = x0 - eps;
                let minus = reference_loss(&x64, &y64, w, h, 0.2).0;
                x64[i] = x0;
                (plus - minus) / (2.0 * eps)
            })
            .collect();
        let scale = fd.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        for (i, (&a, &f)) in out.grad.iter().zip(&fd).enumerate() {
            let err = (a as f64 - f).abs();
            assert!(err <= 1e-5 * scale, "pixel value {i}: analytic {a} vs fd {f}");
        }
    }

    /// The SSIM part alone (lambda = 1), checked by central differences of the f32
    /// implementation itself: eps = 1e-2 (f32 rounding in the loss is ~1e-8 per pixel
    /// term), tolerance 0.5% of the largest gradient (observed worst: 0.06%).
    #[test]
    fn ssim_gradient_matches_central_differences_of_the_implementation() {
        let (w, h, eps) = (24, 20, 1e-2f32);
        let (mut x, y) = image_pair(w, h, 4);
        let out = loss_and_grad(&x, &y, w, h, 1.0);
        let scale = out.grad.iter().fold(0.0f32, |m, v| m.max(v.abs()));
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        for _ in 0..40 {
            let i = rng.random_range(0..x.len());
            let x0 = x[i];
            x[i] = x0 + eps;
            let plus = loss_and_grad(&x, &y, w, h, 1.0).loss;
            x[i] = x0 - eps;
            let minus = loss_and_grad(&x, &y, w, h, 1.0).loss;
            x[i] = x0;
            let fd = (plus - minus) / (2.0 * eps);
            assert!((fd - out.grad[i]).abs() <= 5e-3 * scale, "value {i}: analytic {} vs fd {fd}", out.grad[i]);
        }
    }

    #[test]
    fn psnr_known_values() {
        let a = vec![0.5f32; 300];
        let b = vec![0.6f32; 300];
        assert!((psnr(&a, &b) - 20.0).abs() < 1e-3);
        assert_eq!(psnr(&a, &a), f32::INFINITY);
    }
}

/// The official AiM code's depth loss, `weight` x mean over the pixels with a known
/// depth (`target` > 0) of log(1 + |D - D_gt|), on the rendered accumulated depth
/// `rendered` (metres); returns the loss and its gradient with respect to `rendered`.
pub fn depth_loss_and_grad(rendered: &[f32], target: &[f32], weight: f32) -> (f32, Vec<f32>) {
    let known = target.iter().filter(|&&d| d > 0.0).count();
    if known == 0 || weight == 0.0 {
        return (0.0, vec![0.0; rendered.len()]);
    }
    let scale = weight / known as f32;
    let mut loss = 0.0;
    let grad = rendered
        .iter()
        .zip(target)
        .map(|(&d, &t)| {
            if t <= 0.0 {
                return 0.0;
            }
            let r = d - t;
            loss += scale * r.abs().ln_1p();
            scale * r.signum() / (1.0 + r.abs())
        })
        .collect();
    (loss, grad)
}
