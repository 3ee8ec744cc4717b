//! The deformation field on the GPU backend: the network of [`super::DeformNet`]
//! as WGSL kernels (shaders/matmul.wgsl for the dense layers and their backward
//! pass, shaders/mlp.wgsl for the encoding, biases, ReLUs and bias gradients).
//! The forward pass keeps its activations on the device for the backward pass;
//! only the parameters and points go up and the offsets and gradients come back.

use std::sync::Arc;

use bytemuck::{Pod, Zeroable};

use super::{DeformNet, Layer};
use crate::render::gpu::{compute_pipeline, groups_1d, shader_module, GpuContext, COMMON_WGSL};

/// The `Gemm` uniform of matmul.wgsl.
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct GemmUniform {
    m: u32,
    k: u32,
    n: u32,
    accumulate: u32,
    a_offset: u32,
    a_row: u32,
    a_col: u32,
    unused0: u32,
    b_offset: u32,
    b_row: u32,
    b_col: u32,
    unused1: u32,
    c_offset: u32,
    unused2: [u32; 3],
}

/// The `Elementwise` uniform of mlp.wgsl.
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable, Default)]
struct ElementwiseUniform {
    rows: u32,
    cols: u32,
    offset: u32,
    xyz_frequencies: u32,
    time_frequencies: u32,
    unused0: u32,
    scale: f32,
    time: f32,
}

/// One operand of a product: a row-major matrix at `offset` (floats) in
/// `buffer`, read transposed when `transposed`.
#[derive(Clone, Copy)]
struct Operand<'a> {
    buffer: &'a wgpu::Buffer,
    offset: usize,
    transposed: bool,
}

impl<'a> Operand<'a> {
    fn plain(buffer: &'a wgpu::Buffer, offset: usize) -> Self {
        Self { buffer, offset, transposed: false }
    }
    fn transposed(buffer: &'a wgpu::Buffer, offset: usize) -> Self {
        Self { buffer, offset, transposed: true }
    }
}

/// The deformation network's kernels on one GPU.
pub struct GpuDeformNet {
    ctx: Arc<GpuContext>,
    gemm: wgpu::ComputePipeline,
    encode: wgpu::ComputePipeline,
    bias_relu: wgpu::ComputePipeline,
    bias_scale: wgpu::ComputePipeline,
    relu_mask: wgpu::ComputePipeline,
    column_sums: wgpu::ComputePipeline,
}

/// A forward pass's activations, on the device, for its backward pass.
pub struct GpuDeformCache {
    n: usize,
    output_scale: f32,
    params: wgpu::Buffer,
    input: wgpu::Buffer,
    hidden: Vec<wgpu::Buffer>,
}

impl GpuDeformNet {
    pub fn new(ctx: Arc<GpuContext>) -> Self {
        let device = ctx.device();
        let matmul = shader_module(device, "matmul", &[include_str!("../../shaders/matmul.wgsl")]);
        let mlp = shader_module(device, "mlp", &[COMMON_WGSL, include_str!("../../shaders/mlp.wgsl")]);
        let pipeline = |module: &wgpu::ShaderModule, entry: &str| compute_pipeline(device, module, entry);
        Self {
            gemm: pipeline(&matmul, "main"),
            encode: pipeline(&mlp, "encode"),
            bias_relu: pipeline(&mlp, "bias_relu"),
            bias_scale: pipeline(&mlp, "bias_scale"),
            relu_mask: pipeline(&mlp, "relu_mask"),
            column_sums: pipeline(&mlp, "column_sums"),
            ctx,
        }
    }

    /// Offsets (N x 3, N x 4) of `net` for the points `means` (N x 3) at time
    /// `t`, as [`DeformNet::forward`], and the activations for the backward pass.
    pub fn forward(&self, net: &DeformNet, means: &[f32], t: f32) -> (Vec<f32>, Vec<f32>, GpuDeformCache) {
        let ctx = &self.ctx;
        let n = means.len() / 3;
        let (w, d_in) = (net.config.width, net.config.input_dims());
        let (layers, head_xyz, head_rot) = net.layout();
        let params = ctx.storage_init("deformation parameters", bytemuck::cast_slice(&net.params));
        let points = ctx.storage_init("points", bytemuck::cast_slice(means));
        let input = ctx.storage("encoded input", (4 * n * d_in) as u64);
        let mut enc = ctx.encoder();
        let encoding = ElementwiseUniform {
            rows: n as u32,
            cols: d_in as u32,
            xyz_frequencies: net.config.xyz_frequencies as u32,
            time_frequencies: net.config.time_frequencies as u32,
            time: t,
            ..Default::default()
        };
        self.elementwise(&mut enc, &self.encode, &encoding, &points, &input, n);
        let mut hidden: Vec<wgpu::Buffer> = Vec::with_capacity(layers.len());
        for (i, l) in layers.iter().enumerate() {
            let out = ctx.storage("hidden layer", (4 * n * w) as u64);
            let weights = Operand::plain(&params, l.offset);
            match hidden.last() {
                None => self.gemm(&mut enc, Operand::plain(&input, 0), weights, (&out, 0), [n, d_in, w], false),
                Some(prev) if i == net.config.skip() + 1 => {
                    // [input, h] . W = input . W[..d_in] + h . W[d_in..]
                    self.gemm(&mut enc, Operand::plain(&input, 0), weights, (&out, 0), [n, d_in, w], false);
                    let rest = Operand::plain(&params, l.offset + d_in * w);
                    self.gemm(&mut enc, Operand::plain(prev, 0), rest, (&out, 0), [n, w, w], true);
                }
                Some(prev) => self.gemm(&mut enc, Operand::plain(prev, 0), weights, (&out, 0), [n, w, w], false),
            }
            let bias = ElementwiseUniform {
                rows: n as u32,
                cols: w as u32,
                offset: l.biases().start as u32,
                ..Default::default()
            };
            self.elementwise(&mut enc, &self.bias_relu, &bias, &params, &out, n * w);
            hidden.push(out);
        }
        let last = hidden.last().expect("depth >= 1");
        let output_scale = net.output_scale(t);
        let head = |enc: &mut wgpu::CommandEncoder, l: &Layer| {
            let out = ctx.storage("head", (4 * n * l.outputs) as u64);
            self.gemm(
                enc,
                Operand::plain(last, 0),
                Operand::plain(&params, l.offset),
                (&out, 0),
                [n, w, l.outputs],
                false,
            );
            let bias = ElementwiseUniform {
                rows: n as u32,
                cols: l.outputs as u32,
                offset: l.biases().start as u32,
                scale: output_scale,
                ..Default::default()
            };
            self.elementwise(enc, &self.bias_scale, &bias, &params, &out, n * l.outputs);
            out
        };
        let (d_xyz, d_rot) = (head(&mut enc, &head_xyz), head(&mut enc, &head_rot));
        let mut out = ctx.read_f32s(enc, &[(&d_xyz, 0, 3 * n as u64), (&d_rot, 0, 4 * n as u64)]);
        let d_rot = out.pop().expect("two buffers read");
        let d_xyz = out.pop().expect("two buffers read");
        (d_xyz, d_rot, GpuDeformCache { n, output_scale, params, input, hidden })
    }

    /// Gradient of the loss with respect to every parameter of `net`, from
    /// dL/d(d_xyz) and dL/d(d_rot) of the forward pass that left `cache`, as
    /// [`DeformNet::backward`].
    pub fn backward(&self, net: &DeformNet, cache: &GpuDeformCache, grad_xyz: &[f32], grad_rot: &[f32]) -> Vec<f32> {
        let ctx = &self.ctx;
        let n = cache.n;
        assert_eq!((grad_xyz.len(), grad_rot.len()), (3 * n, 4 * n), "one gradient per offset");
        let (w, d_in) = (net.config.width, net.config.input_dims());
        let (layers, head_xyz, head_rot) = net.layout();
        let scaled = |g: &[f32]| -> Vec<f32> { g.iter().map(|v| v * cache.output_scale).collect() };
        let grads = ctx.storage("deformation gradients", (4 * net.params.len()) as u64);
        let mut enc = ctx.encoder();
        let mut dh = ctx.storage("hidden gradient", (4 * n * w) as u64);
        let last = cache.hidden.last().expect("depth >= 1");
        for (l, g) in [(head_xyz, scaled(grad_xyz)), (head_rot, scaled(grad_rot))] {
            let g = ctx.storage_init("head gradient", bytemuck::cast_slice(&g));
            // dW = h^T g, db = column sums of g, dh += g W^T.
            self.gemm(
                &mut enc,
                Operand::transposed(last, 0),
                Operand::plain(&g, 0),
                (&grads, l.offset),
                [w, n, l.outputs],
                false,
            );
            self.column_sums(&mut enc, &g, &grads, n, l.outputs, l.biases().start);
            let weights_t = Operand::transposed(&cache.params, l.offset);
            self.gemm(&mut enc, Operand::plain(&g, 0), weights_t, (&dh, 0), [n, l.outputs, w], true);
        }
        // The first layer's and the skip layer's weights on the encoded input: dW = x^T dh.
        let input_weight_gradients = |enc: &mut wgpu::CommandEncoder, dh: &wgpu::Buffer, offset: usize| {
            let x_t = Operand::transposed(&cache.input, 0);
            self.gemm(enc, x_t, Operand::plain(dh, 0), (&grads, offset), [d_in, n, w], false);
        };
        for i in (0..layers.len()).rev() {
            let l = layers[i];
            // Through the ReLU: zero where the output was clamped.
            let mask = ElementwiseUniform { rows: n as u32, cols: w as u32, ..Default::default() };
            self.elementwise(&mut enc, &self.relu_mask, &mask, &cache.hidden[i], &dh, n * w);
            self.column_sums(&mut enc, &dh, &grads, n, w, l.biases().start);
            if i == 0 {
                input_weight_gradients(&mut enc, &dh, l.offset);
                break;
            }
            let prev = &cache.hidden[i - 1];
            let dprev = ctx.storage("hidden gradient", (4 * n * w) as u64);
            let hidden_weights = if i == net.config.skip() + 1 {
                input_weight_gradients(&mut enc, &dh, l.offset);
                l.offset + d_in * w
            } else {
                l.offset
            };
            self.gemm(
                &mut enc,
                Operand::transposed(prev, 0),
                Operand::plain(&dh, 0),
                (&grads, hidden_weights),
                [w, n, w],
                false,
            );
            self.gemm(
                &mut enc,
                Operand::plain(&dh, 0),
                Operand::transposed(&cache.params, hidden_weights),
                (&dprev, 0),
                [n, w, w],
                false,
            );
            dh = dprev;
        }
        ctx.read_f32s(enc, &[(&grads, 0, net.params.len() as u64)]).pop().expect("one buffer read")
    }

    /// C (m x n, at `c.1` floats into `c.0`) = A (m x k) B (k x n) (+ C).
    fn gemm(
        &self,
        enc: &mut wgpu::CommandEncoder,
        a: Operand,
        b: Operand,
        c: (&wgpu::Buffer, usize),
        [m, k, n]: [usize; 3],
        accumulate: bool,
    ) {
        // A stored m x k (or k x m when transposed), B k x n (or n x k).
        let (a_row, a_col) = if a.transposed { (1, m) } else { (k, 1) };
        let (b_row, b_col) = if b.transposed { (1, k) } else { (n, 1) };
        let uniform = GemmUniform {
            m: m as u32,
            k: k as u32,
            n: n as u32,
            accumulate: u32::from(accumulate),
            a_offset: a.offset as u32,
            a_row: a_row as u32,
            a_col: a_col as u32,
            unused0: 0,
            b_offset: b.offset as u32,
            b_row: b_row as u32,
            b_col: b_col as u32,
            unused1: 0,
            c_offset: c.1 as u32,
            unused2: [0; 3],
        };
        let u = self.ctx.uniform(&uniform);
        let groups = ((n as u32).div_ceil(16), (m as u32).div_ceil(16));
        self.ctx.dispatch_bound(enc, &self.gemm, &[(0, &u), (1, a.buffer), (2, b.buffer), (3, c.0)], groups);
    }

    /// One of mlp.wgsl's element-wise kernels over `threads` threads.
    fn elementwise(
        &self,
        enc: &mut wgpu::CommandEncoder,
        kernel: &wgpu::ComputePipeline,
        uniform: &ElementwiseUniform,
        src: &wgpu::Buffer,
        dst: &wgpu::Buffer,
        threads: usize,
    ) {
        let u = self.ctx.uniform(uniform);
        self.ctx.dispatch_bound(enc, kernel, &[(0, &u), (1, src), (2, dst)], groups_1d(threads as u32));
    }

    /// `dst[offset..offset + cols]` = the column sums of `src` (rows x cols).
    fn column_sums(
        &self,
        enc: &mut wgpu::CommandEncoder,
        src: &wgpu::Buffer,
        dst: &wgpu::Buffer,
        rows: usize,
        cols: usize,
        offset: usize,
    ) {
        let sums =
            ElementwiseUniform { rows: rows as u32, cols: cols as u32, offset: offset as u32, ..Default::default() };
        self.elementwise(enc, &self.column_sums, &sums, src, dst, cols);
    }
}
