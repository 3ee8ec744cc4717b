// The deformation field's element-wise stages (src/deform): the input encoding,
// bias + ReLU, the heads' bias and output scale, and in the backward pass the
// ReLU mask and the bias gradients (column sums). The host prepends common.wgsl.

struct Elementwise {
    rows: u32,
    cols: u32,
    // Where the bias (forward) or the column sums (backward) live, in floats.
    offset: u32,
    xyz_frequencies: u32,
    time_frequencies: u32,
    unused0: u32,
    scale: f32,
    time: f32,
}

@group(0) @binding(0) var<uniform> e: Elementwise;
@group(0) @binding(1) var<storage, read> src: array<f32>;
@group(0) @binding(2) var<storage, read_write> dst: array<f32>;

// One input row per point: [x, sin(2^k x), cos(2^k x) for k < F] for the mean,
// then the same of the time (Deformable-3DGS's encoding). src = means.
@compute @workgroup_size(256)
fn encode(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let i = flat_block(wid, nwg) * 256u + lid;
    if i >= e.rows {
        return;
    }
    let x = vec3<f32>(src[3u * i], src[3u * i + 1u], src[3u * i + 2u]);
    var o = i * e.cols;
    dst[o] = x.x;
    dst[o + 1u] = x.y;
    dst[o + 2u] = x.z;
    o += 3u;
    for (var k = 0u; k < e.xyz_frequencies; k++) {
        let f = f32(1u << k);
        let s = sin(x * f);
        let c = cos(x * f);
        dst[o] = s.x;
        dst[o + 1u] = s.y;
        dst[o + 2u] = s.z;
        dst[o + 3u] = c.x;
        dst[o + 4u] = c.y;
        dst[o + 5u] = c.z;
        o += 6u;
    }
    dst[o] = e.time;
    o += 1u;
    for (var k = 0u; k < e.time_frequencies; k++) {
        let f = f32(1u << k);
        dst[o] = sin(e.time * f);
        dst[o + 1u] = cos(e.time * f);
        o += 2u;
    }
}

// dst (rows x cols) = max(dst + bias, 0); src = the parameters.
@compute @workgroup_size(256)
fn bias_relu(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let i = flat_block(wid, nwg) * 256u + lid;
    if i < e.rows * e.cols {
        dst[i] = max(dst[i] + src[e.offset + i % e.cols], 0.0);
    }
}

// dst = (dst + bias) * scale (the heads); src = the parameters.
@compute @workgroup_size(256)
fn bias_scale(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let i = flat_block(wid, nwg) * 256u + lid;
    if i < e.rows * e.cols {
        dst[i] = (dst[i] + src[e.offset + i % e.cols]) * e.scale;
    }
}

// dst (a gradient) = 0 where src (the layer's ReLU output) is not positive.
@compute @workgroup_size(256)
fn relu_mask(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let i = flat_block(wid, nwg) * 256u + lid;
    if i < e.rows * e.cols && src[i] <= 0.0 {
        dst[i] = 0.0;
    }
}

// dst[offset + col] = sum over rows of src (rows x cols), rows in order.
@compute @workgroup_size(256)
fn column_sums(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let col = flat_block(wid, nwg) * 256u + lid;
    if col >= e.cols {
        return;
    }
    var sum = 0.0;
    for (var r = 0u; r < e.rows; r++) {
        sum += src[r * e.cols + col];
    }
    dst[e.offset + col] = sum;
}
