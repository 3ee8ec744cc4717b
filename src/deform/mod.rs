//! The deformation field of the moving Gaussian set (paper Eq. 3, the
//! Deformable-3DGS network): F(gamma(sg(mu)), gamma(t)) -> (d_mu, d_rot).
//!
//! An MLP of `depth` ReLU layers of `width` units, the encoded input
//! concatenated again after layer `depth / 2`, and two linear heads (position
//! offset, quaternion offset) initialised near zero so training starts from the
//! canonical set. The encoding is Deformable-3DGS's: the input itself followed
//! by sin and cos of 2^k times it, k < frequencies. The backward pass is
//! written by hand over sgemm (matrixmultiply), in parallel over row blocks;
//! the input is not differentiated (stop-gradient on the means, fixed time).

pub mod gpu;

use std::sync::Arc;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// Network shape (paper / official defaults: 8 x 256, frequencies 10 and 6).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DeformConfig {
    pub depth: usize,
    pub width: usize,
    pub xyz_frequencies: usize,
    pub time_frequencies: usize,
    /// Multiply both offsets by t, so the field is exactly zero at t = 0 and the
    /// canonical set is the state at the start of the motion (docs/training.md).
    #[serde(default)]
    pub zero_at_start: bool,
}

impl Default for DeformConfig {
    fn default() -> Self {
        Self { depth: 8, width: 256, xyz_frequencies: 10, time_frequencies: 6, zero_at_start: false }
    }
}

impl DeformConfig {
    fn xyz_dims(&self) -> usize {
        3 * (1 + 2 * self.xyz_frequencies)
    }
    fn time_dims(&self) -> usize {
        1 + 2 * self.time_frequencies
    }
    pub(crate) fn input_dims(&self) -> usize {
        self.xyz_dims() + self.time_dims()
    }
    /// Layer index after which the encoded input is concatenated again.
    pub(crate) fn skip(&self) -> usize {
        self.depth / 2
    }
}

/// Encode `x` (`x.len()` values) as [x, sin(2^0 x), cos(2^0 x), ...] like Deformable-3DGS.
fn encode(x: &[f32], freqs: usize, out: &mut Vec<f32>) {
    out.extend_from_slice(x);
    for k in 0..freqs {
        let f = (1u32 << k) as f32;
        out.extend(x.iter().map(|v| (v * f).sin()));
        out.extend(x.iter().map(|v| (v * f).cos()));
    }
}

/// One dense layer's place in the flat parameter vector: weights (in x out,
/// row-major) then biases (out).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub(crate) struct Layer {
    pub(crate) offset: usize,
    pub(crate) inputs: usize,
    pub(crate) outputs: usize,
}

impl Layer {
    pub(crate) fn weights(&self) -> std::ops::Range<usize> {
        self.offset..self.offset + self.inputs * self.outputs
    }
    pub(crate) fn biases(&self) -> std::ops::Range<usize> {
        let b = self.offset + self.inputs * self.outputs;
        b..b + self.outputs
    }
    fn len(&self) -> usize {
        self.inputs * self.outputs + self.outputs
    }
}

/// The network: its shape and all parameters in one flat vector (one Adam buffer).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DeformNet {
    pub config: DeformConfig,
    pub params: Vec<f32>,
    layers: Vec<Layer>,
    head_xyz: Layer,
    head_rot: Layer,
}

/// Row-major C (m x n) = A (m x k) . B (k x n) (+ C when `accumulate`), with
/// optional transposes given as strides. Safe wrapper: dimensions are checked.
#[allow(clippy::too_many_arguments)]
fn gemm(a: &[f32], a_t: bool, b: &[f32], b_t: bool, c: &mut [f32], m: usize, k: usize, n: usize, accumulate: bool) {
    assert!(a.len() >= m * k && b.len() >= k * n && c.len() >= m * n, "gemm dimensions");
    let (rsa, csa) = if a_t { (1, m) } else { (k, 1) };
    let (rsb, csb) = if b_t { (1, k) } else { (n, 1) };
    // SAFETY: the asserts above keep every access inside the slices for these
    // strides; c does not alias a or b (distinct borrows).
    unsafe {
        matrixmultiply::sgemm(
            m,
            k,
            n,
            1.0,
            a.as_ptr(),
            rsa as isize,
            csa as isize,
            b.as_ptr(),
            rsb as isize,
            csb as isize,
            if accumulate { 1.0 } else { 0.0 },
            c.as_mut_ptr(),
            n as isize,
            1,
        );
    }
}

/// Rows per parallel block.
const BLOCK: usize = 512;

/// Forward activations kept for the backward pass, where the forward pass ran.
pub struct DeformCache(CachedOn);

enum CachedOn {
    Cpu(CpuActivations),
    Gpu(Arc<gpu::GpuDeformNet>, gpu::GpuDeformCache),
}

struct CpuActivations {
    n: usize,
    /// What the heads' outputs were multiplied by (t with `zero_at_start`, else 1).
    output_scale: f32,
    /// Encoded input per row.
    input: Vec<f32>,
    /// Post-ReLU output of every hidden layer.
    hidden: Vec<Vec<f32>>,
}

/// Where the network runs: the CPU, or a GPU backend's device.
#[derive(Clone, Default)]
pub enum FieldDevice {
    #[default]
    Cpu,
    Gpu(Arc<gpu::GpuDeformNet>),
}

impl FieldDevice {
    /// `backend`'s device: its GPU (the network's kernels compiled for it), or the CPU.
    pub fn of(backend: &crate::render::Backend) -> Self {
        match backend {
            crate::render::Backend::Cpu => FieldDevice::Cpu,
            crate::render::Backend::Gpu(ctx) => FieldDevice::Gpu(Arc::new(gpu::GpuDeformNet::new(ctx.clone()))),
        }
    }
}

impl std::fmt::Debug for FieldDevice {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            FieldDevice::Cpu => "cpu",
            FieldDevice::Gpu(_) => "gpu",
        })
    }
}

/// Offsets for N points at one time.
pub struct DeformOutput {
    /// N x 3.
    pub d_xyz: Vec<f32>,
    /// N x 4 (w, x, y, z added to the raw quaternion).
    pub d_rot: Vec<f32>,
    pub cache: DeformCache,
}

impl DeformOutput {
    /// Deform `g` (the set whose means were the input): means + d_xyz, raw quaternions + d_rot.
    pub fn apply(&self, g: &mut crate::splat::GaussianSet) {
        for (m, dm) in g.means.iter_mut().zip(&self.d_xyz) {
            *m += dm;
        }
        for (r, dr) in g.rotations.iter_mut().zip(&self.d_rot) {
            *r += dr;
        }
    }
}

impl DeformNet {
    /// A network with PyTorch's default initialisation (uniform +-1/sqrt(fan_in))
    /// and heads scaled by 1e-3, seeded.
    pub fn new(config: DeformConfig, seed: u64) -> Self {
        let mut layers = Vec::new();
        let mut offset = 0;
        let (w, d_in) = (config.width, config.input_dims());
        for i in 0..config.depth {
            let inputs = if i == 0 {
                d_in
            } else if i == config.skip() + 1 {
                w + d_in
            } else {
                w
            };
            let l = Layer { offset, inputs, outputs: w };
            offset += l.len();
            layers.push(l);
        }
        let head_xyz = Layer { offset, inputs: w, outputs: 3 };
        offset += head_xyz.len();
        let head_rot = Layer { offset, inputs: w, outputs: 4 };
        offset += head_rot.len();
        let mut params = vec![0.0; offset];
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        for (l, scale) in layers.iter().map(|l| (l, 1.0)).chain([(&head_xyz, 1e-3), (&head_rot, 1e-3)]) {
            let bound = scale / (l.inputs as f32).sqrt();
            for v in &mut params[l.offset..l.offset + l.len()] {
                *v = rng.random_range(-bound..bound);
            }
        }
        Self { config, params, layers, head_xyz, head_rot }
    }

    pub fn parameter_count(&self) -> usize {
        self.params.len()
    }

    /// The hidden layers, then the position and rotation heads.
    pub(crate) fn layout(&self) -> (&[Layer], Layer, Layer) {
        (&self.layers, self.head_xyz, self.head_rot)
    }

    /// What the heads' outputs are multiplied by at time `t`.
    pub(crate) fn output_scale(&self, t: f32) -> f32 {
        if self.config.zero_at_start {
            t
        } else {
            1.0
        }
    }

    /// The encoded network input of `means` (N x 3) at time `t`.
    fn encode_inputs(&self, means: &[f32], t: f32) -> Vec<f32> {
        let d_in = self.config.input_dims();
        let mut t_enc = Vec::with_capacity(self.config.time_dims());
        encode(&[t], self.config.time_frequencies, &mut t_enc);
        let mut input = Vec::with_capacity(means.len() / 3 * d_in);
        for p in means.chunks_exact(3) {
            encode(p, self.config.xyz_frequencies, &mut input);
            input.extend_from_slice(&t_enc);
        }
        input
    }

    /// Offsets for the Gaussians at `means` (N x 3) at time `t`.
    pub fn forward(&self, means: &[f32], t: f32) -> DeformOutput {
        let n = means.len() / 3;
        let (w, d_in) = (self.config.width, self.config.input_dims());
        let input = self.encode_inputs(means, t);
        let mut hidden: Vec<Vec<f32>> = Vec::with_capacity(self.layers.len());
        for (i, l) in self.layers.iter().enumerate() {
            let mut out = vec![0.0f32; n * w];
            let prev = if i == 0 { None } else { Some(&hidden[i - 1]) };
            let skip_in = i == self.config.skip() + 1;
            out.par_chunks_mut(BLOCK * w).enumerate().for_each(|(blk, o)| {
                let rows = o.len() / w;
                let r0 = blk * BLOCK;
                let wts = &self.params[l.weights()];
                match prev {
                    None => gemm(&input[r0 * d_in..], false, wts, false, o, rows, d_in, w, false),
                    Some(h) if skip_in => {
                        // [input, h] . W = input . W[..d_in] + h . W[d_in..]
                        gemm(&input[r0 * d_in..], false, &wts[..d_in * w], false, o, rows, d_in, w, false);
                        gemm(&h[r0 * w..], false, &wts[d_in * w..], false, o, rows, w, w, true);
                    }
                    Some(h) => gemm(&h[r0 * w..], false, wts, false, o, rows, w, w, false),
                }
                let b = &self.params[l.biases()];
                for row in o.chunks_exact_mut(w) {
                    for (v, bias) in row.iter_mut().zip(b) {
                        *v = (*v + bias).max(0.0);
                    }
                }
            });
            hidden.push(out);
        }
        let last = hidden.last().expect("depth >= 1");
        let head = |l: &Layer| {
            let mut out = vec![0.0f32; n * l.outputs];
            gemm(last, false, &self.params[l.weights()], false, &mut out, n, w, l.outputs, false);
            let b = &self.params[l.biases()];
            for row in out.chunks_exact_mut(l.outputs) {
                for (v, bias) in row.iter_mut().zip(b) {
                    *v += bias;
                }
            }
            out
        };
        let output_scale = self.output_scale(t);
        let scaled = |mut v: Vec<f32>| {
            if output_scale != 1.0 {
                v.iter_mut().for_each(|x| *x *= output_scale);
            }
            v
        };
        let d_xyz = scaled(head(&self.head_xyz));
        let d_rot = scaled(head(&self.head_rot));
        DeformOutput {
            d_xyz,
            d_rot,
            cache: DeformCache(CachedOn::Cpu(CpuActivations { n, output_scale, input, hidden })),
        }
    }

    /// [`Self::forward`] on `device`; the output's backward pass runs there too.
    pub fn forward_on(&self, device: &FieldDevice, means: &[f32], t: f32) -> DeformOutput {
        match device {
            FieldDevice::Cpu => self.forward(means, t),
            FieldDevice::Gpu(kernels) => {
                let (d_xyz, d_rot, cache) = kernels.forward(self, means, t);
                DeformOutput { d_xyz, d_rot, cache: DeformCache(CachedOn::Gpu(kernels.clone(), cache)) }
            }
        }
    }

    /// Gradient of the loss with respect to every parameter, from dL/d(d_xyz)
    /// and dL/d(d_rot) of the forward pass that produced `cache`.
    pub fn backward(&self, cache: &DeformCache, grad_xyz: &[f32], grad_rot: &[f32]) -> Vec<f32> {
        match &cache.0 {
            CachedOn::Cpu(activations) => self.backward_cpu(activations, grad_xyz, grad_rot),
            CachedOn::Gpu(kernels, cache) => kernels.backward(self, cache, grad_xyz, grad_rot),
        }
    }

    fn backward_cpu<'a>(&self, cache: &CpuActivations, grad_xyz: &'a [f32], grad_rot: &'a [f32]) -> Vec<f32> {
        let n = cache.n;
        let (w, d_in) = (self.config.width, self.config.input_dims());
        assert_eq!(grad_xyz.len(), 3 * n);
        assert_eq!(grad_rot.len(), 4 * n);
        let mut grads = vec![0.0f32; self.params.len()];
        let last = cache.hidden.last().expect("depth >= 1");
        // Through the output scale (a copy only when there is one).
        let scaled = |g: &'a [f32]| -> std::borrow::Cow<'a, [f32]> {
            if cache.output_scale == 1.0 {
                g.into()
            } else {
                g.iter().map(|v| v * cache.output_scale).collect::<Vec<f32>>().into()
            }
        };
        let (grad_xyz, grad_rot) = (scaled(grad_xyz), scaled(grad_rot));
        // Heads: dW = h^T g, db = sum g, dh = g W^T.
        let mut dh = vec![0.0f32; n * w];
        for (l, g) in [(&self.head_xyz, &grad_xyz[..]), (&self.head_rot, &grad_rot[..])] {
            weight_gradient(last, g, n, w, l.outputs, &mut grads[l.weights()]);
            let db = column_sums(g, l.outputs);
            grads[l.biases()].copy_from_slice(&db);
            gemm(g, false, &self.params[l.weights()], true, &mut dh, n, l.outputs, w, true);
        }
        for i in (0..self.layers.len()).rev() {
            let l = self.layers[i];
            // Through the ReLU: zero where the output was clamped.
            dh.par_iter_mut().zip(cache.hidden[i].par_iter()).for_each(|(g, h)| {
                if *h <= 0.0 {
                    *g = 0.0;
                }
            });
            let db = column_sums(&dh, w);
            grads[l.biases()].copy_from_slice(&db);
            let skip_in = i == self.config.skip() + 1;
            if i == 0 {
                weight_gradient(&cache.input, &dh, n, d_in, w, &mut grads[l.weights()]);
                break;
            }
            let prev = &cache.hidden[i - 1];
            let wts = &self.params[l.weights()];
            let mut dprev = vec![0.0f32; n * w];
            if skip_in {
                let gw = &mut grads[l.weights()];
                let (g_in, g_h) = gw.split_at_mut(d_in * w);
                weight_gradient(&cache.input, &dh, n, d_in, w, g_in);
                weight_gradient(prev, &dh, n, w, w, g_h);
                dprev.par_chunks_mut(BLOCK * w).enumerate().for_each(|(blk, o)| {
                    let rows = o.len() / w;
                    gemm(&dh[blk * BLOCK * w..], false, &wts[d_in * w..], true, o, rows, w, w, false);
                });
            } else {
                weight_gradient(prev, &dh, n, w, w, &mut grads[l.weights()]);
                dprev.par_chunks_mut(BLOCK * w).enumerate().for_each(|(blk, o)| {
                    let rows = o.len() / w;
                    gemm(&dh[blk * BLOCK * w..], false, wts, true, o, rows, w, w, false);
                });
            }
            dh = dprev;
        }
        grads
    }
}

/// X^T . dY for row-major X (rows x k) and dY (rows x n), written into `out`
/// (k x n): partial products over row blocks in parallel, summed in block order
/// so the result does not depend on thread timing.
fn weight_gradient(x: &[f32], dy: &[f32], rows: usize, k: usize, n: usize, out: &mut [f32]) {
    const ROWS: usize = 4 * BLOCK;
    let blocks = rows.div_ceil(ROWS).max(1);
    let partials: Vec<Vec<f32>> = (0..blocks)
        .into_par_iter()
        .map(|b| {
            let (r0, r1) = (b * ROWS, ((b + 1) * ROWS).min(rows));
            let mut p = vec![0.0f32; k * n];
            gemm(&x[r0 * k..r1 * k], true, &dy[r0 * n..r1 * n], false, &mut p, k, r1 - r0, n, false);
            p
        })
        .collect();
    out.copy_from_slice(&partials[0]);
    for p in &partials[1..] {
        for (o, v) in out.iter_mut().zip(p) {
            *o += v;
        }
    }
}

/// Sum over rows of an (rows x cols) row-major matrix.
fn column_sums(m: &[f32], cols: usize) -> Vec<f32> {
    let mut s = vec![0.0f32; cols];
    for row in m.chunks_exact(cols) {
        for (a, v) in s.iter_mut().zip(row) {
            *a += v;
        }
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    fn small() -> DeformNet {
        let mut net = DeformNet::new(
            DeformConfig { depth: 4, width: 12, xyz_frequencies: 3, time_frequencies: 2, zero_at_start: false },
            7,
        );
        // Heads at full scale so every layer's gradient is well above f32 noise.
        let (hx, hr) = (net.head_xyz, net.head_rot);
        for l in [hx, hr] {
            for v in &mut net.params[l.weights()] {
                *v *= 1000.0;
            }
        }
        net
    }

    fn points() -> Vec<f32> {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        (0..3 * 37).map(|_| rng.random_range(-0.6..0.6)).collect()
    }

    fn weights(n: usize, seed: u64) -> Vec<f32> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        (0..n).map(|_| rng.random_range(-1.0..1.0)).collect()
    }

    fn loss(net: &DeformNet, pts: &[f32], gx: &[f32], gr: &[f32]) -> f64 {
        let o = net.forward(pts, 0.4);
        let dot = |a: &[f32], b: &[f32]| a.iter().zip(b).map(|(x, y)| *x as f64 * *y as f64).sum::<f64>();
        dot(&o.d_xyz, gx) + dot(&o.d_rot, gr)
    }

    #[test]
    fn parameter_gradients_match_central_differences() {
        for zero_at_start in [false, true] {
            let mut net = small();
            net.config.zero_at_start = zero_at_start;
            let pts = points();
            let n = pts.len() / 3;
            let (gx, gr) = (weights(3 * n, 1), weights(4 * n, 2));
            let out = net.forward(&pts, 0.4);
            let analytic = net.backward(&out.cache, &gx, &gr);
            // Every parameter of every layer, eps 1e-3 on O(0.3) weights, loss summed in
            // f64. (At eps 1e-2 ReLU kinks flip inside the step and the hidden layers
            // disagree by a few per cent; at 1e-3 every layer agrees within 0.3%.)
            let eps = 1e-3f32;
            let fd: Vec<f64> = (0..net.params.len())
                .map(|j| {
                    let mut p = net.clone();
                    p.params[j] += eps;
                    let lp = loss(&p, &pts, &gx, &gr);
                    p.params[j] -= 2.0 * eps;
                    let lm = loss(&p, &pts, &gx, &gr);
                    (lp - lm) / (2.0 * eps as f64)
                })
                .collect();
            for l in net.layers.iter().chain([&net.head_xyz, &net.head_rot]) {
                let range = l.offset..l.offset + l.len();
                let err: f64 = range.clone().map(|j| (fd[j] - analytic[j] as f64).powi(2)).sum::<f64>().sqrt();
                let norm: f64 = range.map(|j| fd[j] * fd[j]).sum::<f64>().sqrt();
                assert!(norm > 1e-3, "{l:?}: gradient too small to test");
                assert!(
                    err / norm < 3e-3,
                    "{l:?} (zero_at_start {zero_at_start}): relative gradient error {}",
                    err / norm
                );
            }
        }
    }

    #[test]
    fn zero_at_start_leaves_the_start_state_in_place() {
        let mut net = small();
        net.config.zero_at_start = true;
        let out = net.forward(&points(), 0.0);
        assert!(out.d_xyz.iter().chain(&out.d_rot).all(|v| *v == 0.0));
        let later = net.forward(&points(), 0.5);
        assert!(later.d_xyz.iter().any(|v| *v != 0.0));
    }

    #[test]
    fn default_network_has_the_deformable_3dgs_shape_and_starts_near_identity() {
        let net = DeformNet::new(DeformConfig::default(), 0);
        // 76 inputs; layer 5 takes 256 + 76; heads 3 and 4.
        // Layers 1-4 and 6-7 are 256 -> 256.
        let expected =
            (76 * 256 + 256) + 6 * (256 * 256 + 256) + ((256 + 76) * 256 + 256) + (256 * 3 + 3) + (256 * 4 + 4);
        assert_eq!(net.parameter_count(), expected);
        let out = net.forward(&points(), 0.5);
        assert!(out.d_xyz.iter().chain(&out.d_rot).all(|v| v.abs() < 0.05), "heads start near zero");
    }

    #[test]
    fn blocks_do_not_change_the_result() {
        // More rows than one parallel block: the same as evaluating rows one by one.
        let net = small();
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let pts: Vec<f32> = (0..3 * (BLOCK + 77)).map(|_| rng.random_range(-0.6..0.6)).collect();
        let all = net.forward(&pts, 0.25);
        for i in [0, BLOCK - 1, BLOCK, BLOCK + 76] {
            let one = net.forward(&pts[3 * i..3 * i + 3], 0.25);
            for c in 0..3 {
                assert!((one.d_xyz[c] - all.d_xyz[3 * i + c]).abs() < 1e-5);
            }
        }
    }

    #[test]
    fn blocked_weight_gradient_equals_one_product() {
        let mut rng = ChaCha8Rng::seed_from_u64(8);
        let (rows, k, n) = (4 * BLOCK * 2 + 123, 9, 5);
        let x: Vec<f32> = (0..rows * k).map(|_| rng.random_range(-1.0..1.0)).collect();
        let dy: Vec<f32> = (0..rows * n).map(|_| rng.random_range(-1.0..1.0)).collect();
        let mut blocked = vec![0.0; k * n];
        weight_gradient(&x, &dy, rows, k, n, &mut blocked);
        for i in 0..k {
            for j in 0..n {
                let direct: f64 = (0..rows).map(|r| x[r * k + i] as f64 * dy[r * n + j] as f64).sum();
                assert!((blocked[i * n + j] as f64 - direct).abs() < 1e-3, "({i},{j})");
            }
        }
    }
}
