// Backward compositing, one 16x16 workgroup per tile and one thread per pixel,
// as render::raster's backward pass: each tile's list is walked back to front
// from the last position any of its pixels composited; per Gaussian the
// pixels' contributions (moments of dL/d(power), colour and depth weights)
// are summed over the tile in workgroup memory and added to the Gaussian's
// gradient with a float atomic (a compare-exchange loop on the bits: WGSL has
// no float atomics), one per tile.

@group(0) @binding(0) var<uniform> frame: Frame;
@group(0) @binding(1) var<storage, read> splats: array<f32>;
@group(0) @binding(2) var<storage, read> depth_order: array<u32>;
@group(0) @binding(3) var<storage, read> tile_values: array<u32>;
@group(0) @binding(4) var<storage, read> ranges: array<u32>;
// The forward pass's per-pixel alpha, depth, final transmittance, last.
@group(0) @binding(5) var<storage, read> pixel_state: array<f32>;
// Per pixel: dL/d(colour) rgb, dL/d(alpha) x final T, dL/d(depth), and
// dL/d(colour) . background x final T (what lies behind every Gaussian).
@group(0) @binding(6) var<storage, read> pixel_grads: array<f32>;
@group(0) @binding(7) var<storage, read_write> projected_grads: array<atomic<u32>>;

const BATCH: u32 = 64u;
// Summed per Gaussian: p, p dx, p dy, p dx^2, p dx dy, p dy^2 (p = dL/d(power)),
// colour weight rgb, depth weight.
const MOMENTS: u32 = 10u;
var<workgroup> batch: array<f32, 640>;
var<workgroup> batch_ids: array<u32, 64>;
var<workgroup> sums: array<f32, 2560>;
var<workgroup> last_max: atomic<u32>;
// Whether any pixel of the tile took a contribution from the current Gaussian:
// most of a tile's list reaches few of its pixels, and one that reaches none
// skips the reduction (two barriers instead of ten).
var<workgroup> any_pixel: atomic<u32>;
var<workgroup> any_snapshot: u32;
var<workgroup> last_snapshot: u32;
var<workgroup> range_start: u32;

fn atomic_add_f32(i: u32, v: f32) {
    var old = atomicLoad(&projected_grads[i]);
    loop {
        let swapped = atomicCompareExchangeWeak(&projected_grads[i], old, bitcast<u32>(bitcast<f32>(old) + v));
        if swapped.exchanged {
            break;
        }
        old = swapped.old_value;
    }
}

@compute @workgroup_size(16, 16)
fn main(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(local_invocation_id) local: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let tile = wid.y * frame.image.z + wid.x;
    let px = wid.x * TILE + local.x;
    let py = wid.y * TILE + local.y;
    let inside = px < frame.image.x && py < frame.image.y;
    let pixel = py * frame.image.x + px;
    if lid == 0u {
        atomicStore(&last_max, 0u);
        atomicStore(&any_pixel, 0u);
        range_start = ranges[2u * tile];
    }
    workgroupBarrier();
    var transmittance = 0.0;
    var last = 0u;
    var grad_color = vec3<f32>(0.0);
    var grad_alpha_t = 0.0;
    var grad_depth = 0.0;
    var behind = 0.0;
    if inside {
        transmittance = pixel_state[4u * pixel + 2u];
        last = u32(pixel_state[4u * pixel + 3u]);
        let g = 6u * pixel;
        grad_color = vec3<f32>(pixel_grads[g], pixel_grads[g + 1u], pixel_grads[g + 2u]);
        grad_alpha_t = pixel_grads[g + 3u];
        grad_depth = pixel_grads[g + 4u];
        behind = pixel_grads[g + 5u];
        atomicMax(&last_max, last);
    }
    workgroupBarrier();
    if lid == 0u {
        last_snapshot = atomicLoad(&last_max);
    }
    let list_len = workgroupUniformLoad(&last_snapshot);
    let start = workgroupUniformLoad(&range_start);
    let centre = vec2<f32>(f32(px) + 0.5, f32(py) + 0.5);

    var batch_end = list_len;
    while batch_end > 0u {
        let count = min(BATCH, batch_end);
        let batch_start = batch_end - count;
        workgroupBarrier();
        if lid < count {
            let g = depth_order[tile_values[start + batch_start + lid]];
            batch_ids[lid] = g;
            for (var f = 0u; f < SPLAT_STRIDE; f++) {
                batch[lid * SPLAT_STRIDE + f] = splats[g * SPLAT_STRIDE + f];
            }
        }
        workgroupBarrier();
        for (var jj = 0u; jj < count; jj++) {
            let j = count - 1u - jj;
            let k = batch_start + j;
            var m = array<f32, 10>();
            if k < last {
                let o = j * SPLAT_STRIDE;
                let d = vec2<f32>(batch[o], batch[o + 1u]) - centre;
                let opacity = batch[o + 5u];
                let power = gaussian_power(d, vec3<f32>(batch[o + 2u], batch[o + 3u], batch[o + 4u]));
                if power <= 0.0 {
                    let gauss = exp_nonpositive(power);
                    let alpha = min(opacity * gauss, ALPHA_MAX);
                    if alpha >= ALPHA_MIN {
                        let inv_one_minus = 1.0 / (1.0 - alpha);
                        let t_before = transmittance * inv_one_minus;
                        let w = alpha * t_before;
                        let color = vec3<f32>(batch[o + 6u], batch[o + 7u], batch[o + 8u]);
                        let value = dot(grad_color, color) + grad_depth * batch[o + 9u];
                        // d(out)/d(alpha) = value T - (what lies behind) / (1 - alpha).
                        let dl_da = value * t_before - behind * inv_one_minus + grad_alpha_t * inv_one_minus;
                        behind = fma(value, w, behind);
                        transmittance = t_before;
                        // Where alpha was clamped at ALPHA_MAX it depends on nothing.
                        if opacity * gauss <= ALPHA_MAX {
                            let p = dl_da * alpha;
                            m[0] = p;
                            m[1] = p * d.x;
                            m[2] = p * d.y;
                            m[3] = p * d.x * d.x;
                            m[4] = p * d.x * d.y;
                            m[5] = p * d.y * d.y;
                        }
                        m[6] = grad_color.x * w;
                        m[7] = grad_color.y * w;
                        m[8] = grad_color.z * w;
                        m[9] = grad_depth * w;
                        atomicStore(&any_pixel, 1u);
                    }
                }
            }
            for (var q = 0u; q < MOMENTS; q++) {
                sums[q * 256u + lid] = m[q];
            }
            workgroupBarrier();
            if lid == 0u {
                any_snapshot = atomicExchange(&any_pixel, 0u);
            }
            if workgroupUniformLoad(&any_snapshot) == 0u {
                continue;
            }
            for (var stride = 128u; stride > 0u; stride >>= 1u) {
                if lid < stride {
                    for (var q = 0u; q < MOMENTS; q++) {
                        sums[q * 256u + lid] += sums[q * 256u + lid + stride];
                    }
                }
                workgroupBarrier();
            }
            if lid < GRAD_STRIDE {
                // power = -(a dx^2 + c dy^2) / 2 - b dx dy with (dx, dy) = mean - pixel.
                let o = j * SPLAT_STRIDE;
                let a = batch[o + 2u];
                let bb = batch[o + 3u];
                let c = batch[o + 4u];
                let mx = sums[256u];
                let my = sums[2u * 256u];
                var v = 0.0;
                switch lid {
                    case 0u: { v = -(a * mx + bb * my); }
                    case 1u: { v = -(c * my + bb * mx); }
                    case 2u: { v = -0.5 * sums[3u * 256u]; }
                    case 3u: { v = -sums[4u * 256u]; }
                    case 4u: { v = -0.5 * sums[5u * 256u]; }
                    case 5u: { v = sums[6u * 256u]; }
                    case 6u: { v = sums[7u * 256u]; }
                    case 7u: { v = sums[8u * 256u]; }
                    case 8u: { v = sums[0u] / batch[o + 5u]; }
                    default: { v = sums[9u * 256u]; }
                }
                if v != 0.0 {
                    atomic_add_f32(batch_ids[j] * GRAD_STRIDE + lid, v);
                }
            }
            workgroupBarrier();
        }
        batch_end = batch_start;
    }
}
