// Project every Gaussian (EWA splatting), as render::project::project_one:
// the splat record the rasterizer reads, its tile span and count, and its
// depth key for the front-to-back sort. Culled Gaussians get no tiles and the
// largest key.

@group(0) @binding(0) var<uniform> frame: Frame;
@group(0) @binding(1) var<storage, read> params: array<f32>;
@group(0) @binding(2) var<storage, read_write> splats: array<f32>;
@group(0) @binding(3) var<storage, read_write> tile_spans: array<vec4<u32>>;
@group(0) @binding(4) var<storage, read_write> tile_counts: array<u32>;
@group(0) @binding(5) var<storage, read_write> depth_keys: array<u32>;
@group(0) @binding(6) var<storage, read_write> depth_order: array<u32>;

// View-dependent colour: SH + 0.5, clamped at 0.
fn eval_color(i: u32, dir: vec3<f32>) -> vec3<f32> {
    let degree = frame.sizes.y;
    let y = sh_basis(degree, dir);
    var c = sh_dc_of(i) * y[0];
    for (var k = 1u; k < sh_coeffs(degree); k++) {
        c += sh_rest_of(i, k) * y[k];
    }
    return max(c + vec3<f32>(0.5), vec3<f32>(0.0));
}

@compute @workgroup_size(256)
fn main(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let i = flat_block(wid, nwg) * 256u + lid;
    if i >= frame.sizes.x {
        return;
    }
    depth_order[i] = i;
    depth_keys[i] = 0xffffffffu;
    tile_counts[i] = 0u;
    // An empty span: the intersection emitter loops over nothing.
    tile_spans[i] = vec4<u32>(1u, 1u, 0u, 0u);

    let mean = mean_of(i);
    let w = camera_rotation();
    let t = w * mean + frame.trans.xyz;
    if t.z < NEAR_PLANE {
        return;
    }
    let opacity = opacity_of(i);
    if opacity < ALPHA_MIN {
        return;
    }
    let m = cov_factor(quat_to_matrix(rotation_of(i)), scale_of(i));
    let jac = jacobian(t);
    let tm = (jac.j * w) * m;
    let cov = covariance_2d(tm);
    let det = cov[0][0] * cov[1][1] - cov[0][1] * cov[1][0];
    if !(det > 0.0) {
        return;
    }
    let inv_det = 1.0 / det;
    let conic = vec3<f32>(cov[1][1] * inv_det, -cov[1][0] * inv_det, cov[0][0] * inv_det);
    let fx = frame.intrinsics.x;
    let fy = frame.intrinsics.y;
    let mean2d = vec2<f32>(fx * t.x / t.z + frame.intrinsics.z, fy * t.y / t.z + frame.intrinsics.w);

    // alpha >= ALPHA_MIN needs Mahalanobis^2 <= 2 ln(opacity / ALPHA_MIN); one
    // pixel of margin, as the CPU backend.
    let r2 = 2.0 * log(opacity / ALPHA_MIN);
    let hx = sqrt(r2 * cov[0][0]);
    let hy = sqrt(r2 * cov[1][1]);
    let x0 = floor(mean2d.x - hx - 0.5) - 1.0;
    let x1 = ceil(mean2d.x + hx - 0.5) + 1.0;
    let y0 = floor(mean2d.y - hy - 0.5) - 1.0;
    let y1 = ceil(mean2d.y + hy - 0.5) + 1.0;
    let width = f32(frame.image.x);
    let height = f32(frame.image.y);
    if !(x1 >= 0.0 && y1 >= 0.0 && x0 < width && y0 < height) {
        return;
    }
    let bbox = vec4<u32>(
        u32(max(x0, 0.0)),
        u32(max(y0, 0.0)),
        u32(min(x1, width - 1.0)),
        u32(min(y1, height - 1.0)),
    );
    let color = eval_color(i, view_direction(mean).xyz);

    let o = i * SPLAT_STRIDE;
    splats[o] = mean2d.x;
    splats[o + 1u] = mean2d.y;
    splats[o + 2u] = conic.x;
    splats[o + 3u] = conic.y;
    splats[o + 4u] = conic.z;
    splats[o + 5u] = opacity;
    splats[o + 6u] = color.x;
    splats[o + 7u] = color.y;
    splats[o + 8u] = color.z;
    splats[o + 9u] = t.z;
    let span = bbox / TILE;
    tile_spans[i] = span;
    tile_counts[i] = (span.z - span.x + 1u) * (span.w - span.y + 1u);
    // Positive floats order as their bit patterns.
    depth_keys[i] = bitcast<u32>(t.z);
}
