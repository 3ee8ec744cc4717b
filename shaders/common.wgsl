// Shared by every render kernel: the per-render uniforms and the numeric rules of
// the CPU backend (src/render/project.rs, src/render/raster.rs), so that both
// backends draw the same pixels. The host prepends this file to each kernel's.

const TILE: u32 = 16u;
const ALPHA_MIN: f32 = 1.0 / 255.0;
const ALPHA_MAX: f32 = 0.99;
const TRANSMITTANCE_MIN: f32 = 1e-4;
const NEAR_PLANE: f32 = 0.01;
const COV2D_DILATION: f32 = 0.3;
// A projected Gaussian: mean2d (2), conic a b c (3), opacity, colour (3), depth.
const SPLAT_STRIDE: u32 = 10u;
// Per-Gaussian gradient of the projected quantities: mean2d (2), conic (3),
// colour (3), opacity, depth.
const GRAD_STRIDE: u32 = 10u;

// One render: the camera (world_to_camera columns, translation, centre), the
// image and the layout of the Gaussian parameters in the params buffer.
struct Frame {
    rot0: vec4<f32>,
    rot1: vec4<f32>,
    rot2: vec4<f32>,
    trans: vec4<f32>,
    position: vec4<f32>,
    // fx, fy, cx, cy
    intrinsics: vec4<f32>,
    // The projection Jacobian's tan limits x, y.
    limits: vec4<f32>,
    // Uniform background rgb; w = 1 where a per-pixel background image is bound.
    background: vec4<f32>,
    // width, height, tiles_x, tiles_y
    image: vec4<u32>,
    // Gaussians, active SH degree, SH rest floats per Gaussian, unused.
    sizes: vec4<u32>,
    // Offsets (floats) of means, log_scales, rotations, opacity_logits.
    offsets: vec4<u32>,
    // Offsets of sh_dc, sh_rest; unused.
    offsets2: vec4<u32>,
}

// The sizes of one sort, scan or range pass.
struct Pass {
    count: u32,
    shift: u32,
    blocks: u32,
    unused: u32,
}

// Flat index of a thread in a 1D problem dispatched as a 2D grid of 256-wide
// workgroups (a grid dimension holds at most 65535 workgroups).
fn flat_block(wid: vec3<u32>, nwg: vec3<u32>) -> u32 {
    return wid.x + wid.y * nwg.x;
}

fn sigmoid(x: f32) -> f32 {
    return 1.0 / (1.0 + exp(-x));
}

// The Gaussian's exponent at offset d = mean2d - pixel centre, conic (a, b, c):
// -(a dx^2 + c dy^2) / 2 - b dx dy, in the CPU backend's order (raster.rs's lane
// groups), so that both backends make the same skip decisions.
fn gaussian_power(d: vec2<f32>, conic: vec3<f32>) -> f32 {
    return fma(d.x, fma(-0.5 * conic.x, d.x, -conic.y * d.y), -0.5 * conic.z * d.y * d.y);
}

// exp(x) for x <= 0 with the CPU backend's polynomial (raster::exp_nonpositive),
// so that both backends make the same alpha-threshold decisions.
fn exp_nonpositive(x_in: f32) -> f32 {
    let x = max(x_in, -87.0);
    let n = round(x * 1.442695);
    let r = fma(-n, -2.1219444e-4, fma(-n, 0.6933594, x));
    let r2 = r * r;
    let lo = fma(0.49999142, r, 0.9999995);
    let mid = fma(0.04189873, r, 0.16668114);
    let poly = fma(fma(0.008261531, r2, mid), r2, lo);
    let e_r = fma(poly, r, 1.0);
    return e_r * exp2(n);
}
