// Front-to-back alpha compositing, one 16x16 workgroup per tile and one thread
// per pixel, as render::raster's forward pass: the tile's list is read in
// batches of 256 splats through workgroup memory; a pixel stops where its
// transmittance would fall below TRANSMITTANCE_MIN, the tile when all have.

@group(0) @binding(0) var<uniform> frame: Frame;
@group(0) @binding(1) var<storage, read> splats: array<f32>;
@group(0) @binding(2) var<storage, read> depth_order: array<u32>;
@group(0) @binding(3) var<storage, read> tile_values: array<u32>;
@group(0) @binding(4) var<storage, read> ranges: array<u32>;
@group(0) @binding(5) var<storage, read> background_image: array<f32>;
@group(0) @binding(6) var<storage, read_write> out_color: array<f32>;
// Per pixel: alpha, accumulated depth, final transmittance, one past the
// tile-list position of the last Gaussian composited.
@group(0) @binding(7) var<storage, read_write> out_state: array<f32>;

const BATCH: u32 = 256u;
var<workgroup> batch: array<f32, 2560>;
var<workgroup> done_count: atomic<u32>;
var<workgroup> done_snapshot: u32;
var<workgroup> range_start: u32;
var<workgroup> range_end: u32;

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
    if lid == 0u {
        atomicStore(&done_count, 0u);
        range_start = ranges[2u * tile];
        range_end = ranges[2u * tile + 1u];
    }
    let start = workgroupUniformLoad(&range_start);
    let end = workgroupUniformLoad(&range_end);
    var done = !inside;
    if done {
        atomicAdd(&done_count, 1u);
    }
    let centre = vec2<f32>(f32(px) + 0.5, f32(py) + 0.5);
    var transmittance = 1.0;
    var color = vec3<f32>(0.0);
    var depth = 0.0;
    var last = 0u;
    for (var b = start; b < end; b += BATCH) {
        workgroupBarrier();
        if b + lid < end {
            let src = depth_order[tile_values[b + lid]] * SPLAT_STRIDE;
            for (var f = 0u; f < SPLAT_STRIDE; f++) {
                batch[lid * SPLAT_STRIDE + f] = splats[src + f];
            }
        }
        workgroupBarrier();
        let count = min(BATCH, end - b);
        if !done {
            for (var j = 0u; j < count; j++) {
                let o = j * SPLAT_STRIDE;
                let d = vec2<f32>(batch[o], batch[o + 1u]) - centre;
                let power = gaussian_power(d, vec3<f32>(batch[o + 2u], batch[o + 3u], batch[o + 4u]));
                if power > 0.0 {
                    continue;
                }
                let alpha = min(batch[o + 5u] * exp_nonpositive(power), ALPHA_MAX);
                if alpha < ALPHA_MIN {
                    continue;
                }
                let t_next = transmittance * (1.0 - alpha);
                if t_next < TRANSMITTANCE_MIN {
                    done = true;
                    atomicAdd(&done_count, 1u);
                    break;
                }
                let w = alpha * transmittance;
                color += vec3<f32>(batch[o + 6u], batch[o + 7u], batch[o + 8u]) * w;
                depth += batch[o + 9u] * w;
                transmittance = t_next;
                last = b + j - start + 1u;
            }
        }
        workgroupBarrier();
        if lid == 0u {
            done_snapshot = atomicLoad(&done_count);
        }
        if workgroupUniformLoad(&done_snapshot) == TILE * TILE {
            break;
        }
    }
    if !inside {
        return;
    }
    let pixel = py * frame.image.x + px;
    var background = frame.background.xyz;
    if frame.background.w > 0.5 {
        background = vec3<f32>(
            background_image[3u * pixel],
            background_image[3u * pixel + 1u],
            background_image[3u * pixel + 2u],
        );
    }
    out_color[3u * pixel] = color.x + background.x * transmittance;
    out_color[3u * pixel + 1u] = color.y + background.y * transmittance;
    out_color[3u * pixel + 2u] = color.z + background.z * transmittance;
    out_state[4u * pixel] = 1.0 - transmittance;
    out_state[4u * pixel + 1u] = depth;
    out_state[4u * pixel + 2u] = transmittance;
    out_state[4u * pixel + 3u] = f32(last);
}
