// C = op(A) op(B) (+ C), row-major C (m x n), A and B read through strides
// (a transpose is a swap of the strides) from offsets in their buffers: the
// deformation field's dense layers and their backward pass. 16 x 16 output
// tiles, the shared dimension walked in 16-wide slabs through workgroup memory.

struct Gemm {
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
    unused2: u32,
    unused3: u32,
    unused4: u32,
}

@group(0) @binding(0) var<uniform> gemm: Gemm;
@group(0) @binding(1) var<storage, read> a: array<f32>;
@group(0) @binding(2) var<storage, read> b: array<f32>;
@group(0) @binding(3) var<storage, read_write> c: array<f32>;

var<workgroup> tile_a: array<f32, 256>;
var<workgroup> tile_b: array<f32, 256>;

@compute @workgroup_size(16, 16)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_id) local: vec3<u32>) {
    let row = wid.y * 16u + local.y;
    let col = wid.x * 16u + local.x;
    var acc = 0.0;
    for (var k0 = 0u; k0 < gemm.k; k0 += 16u) {
        let ka = k0 + local.x;
        var va = 0.0;
        if row < gemm.m && ka < gemm.k {
            va = a[gemm.a_offset + row * gemm.a_row + ka * gemm.a_col];
        }
        tile_a[local.y * 16u + local.x] = va;
        let kb = k0 + local.y;
        var vb = 0.0;
        if kb < gemm.k && col < gemm.n {
            vb = b[gemm.b_offset + kb * gemm.b_row + col * gemm.b_col];
        }
        tile_b[local.y * 16u + local.x] = vb;
        workgroupBarrier();
        for (var kk = 0u; kk < 16u; kk++) {
            acc = fma(tile_a[local.y * 16u + kk], tile_b[kk * 16u + local.x], acc);
        }
        workgroupBarrier();
    }
    if row < gemm.m && col < gemm.n {
        let o = gemm.c_offset + row * gemm.n + col;
        if gemm.accumulate == 1u {
            c[o] += acc;
        } else {
            c[o] = acc;
        }
    }
}
