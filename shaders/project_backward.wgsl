// Backward of the projection for every Gaussian the forward pass kept, as
// render::project::project_one_backward: from the gradients of the projected
// quantities to those of the raw parameters (mean, log-scale, raw quaternion,
// opacity logit, SH), written in the params buffer's layout, and the
// densification statistic |dL/d(mean2d)| in NDC units.

@group(0) @binding(0) var<uniform> frame: Frame;
@group(0) @binding(1) var<storage, read> params: array<f32>;
@group(0) @binding(2) var<storage, read> splats: array<f32>;
@group(0) @binding(3) var<storage, read> tile_counts: array<u32>;
@group(0) @binding(4) var<storage, read> projected_grads: array<f32>;
@group(0) @binding(5) var<storage, read_write> param_grads: array<f32>;
// Per Gaussian: the NDC mean2d gradient norm, 1 (it was visible), and its
// screen radius (3 sigma of the major axis, pixels).
@group(0) @binding(6) var<storage, read_write> screen_stats: array<f32>;

// dL/d(unit quaternion (w, x, y, z)) from dL/d(its rotation matrix); g[c][r] = dL/dR[r][c].
fn quat_matrix_backward(q: vec4<f32>, g: mat3x3<f32>) -> vec4<f32> {
    let w = q.x;
    let x = q.y;
    let y = q.z;
    let z = q.w;
    let gw = 2.0 * (-z * g[1][0] + y * g[2][0] + z * g[0][1] - x * g[2][1] - y * g[0][2] + x * g[1][2]);
    let gx = 2.0 * (y * g[1][0] + z * g[2][0] + y * g[0][1] - 2.0 * x * g[1][1] - w * g[2][1] + z * g[0][2]
        + w * g[1][2] - 2.0 * x * g[2][2]);
    let gy = 2.0 * (-2.0 * y * g[0][0] + x * g[1][0] + w * g[2][0] + x * g[0][1] + z * g[2][1] - w * g[0][2]
        + z * g[1][2] - 2.0 * y * g[2][2]);
    let gz = 2.0 * (-2.0 * z * g[0][0] - w * g[1][0] + x * g[2][0] + w * g[0][1] - 2.0 * z * g[1][1]
        + y * g[2][1] + x * g[0][2] + y * g[1][2]);
    return vec4<f32>(gw, gx, gy, gz);
}

fn write3(offset: u32, i: u32, v: vec3<f32>) {
    let o = offset + 3u * i;
    param_grads[o] = v.x;
    param_grads[o + 1u] = v.y;
    param_grads[o + 2u] = v.z;
}

@compute @workgroup_size(256)
fn main(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let i = flat_block(wid, nwg) * 256u + lid;
    if i >= frame.sizes.x || tile_counts[i] == 0u {
        return;
    }
    let pg = i * GRAD_STRIDE;
    let g_mean2d = vec2<f32>(projected_grads[pg], projected_grads[pg + 1u]);
    let g_conic = vec3<f32>(projected_grads[pg + 2u], projected_grads[pg + 3u], projected_grads[pg + 4u]);
    let g_color = vec3<f32>(projected_grads[pg + 5u], projected_grads[pg + 6u], projected_grads[pg + 7u]);
    let g_opacity = projected_grads[pg + 8u];
    let g_depth = projected_grads[pg + 9u];

    let fx = frame.intrinsics.x;
    let fy = frame.intrinsics.y;
    let w_rot = camera_rotation();
    let mean = mean_of(i);
    let t = w_rot * mean + frame.trans.xyz;
    let scale = scale_of(i);
    let q_raw = raw_rotation_of(i);
    let q = rotation_of(i);
    let rot = quat_to_matrix(q);
    let m = cov_factor(rot, scale);
    let jac = jacobian(t);
    let tw = jac.j * w_rot;
    let tm = tw * m;
    let cov = covariance_2d(tm);
    let inv = (1.0 / determinant(cov)) * mat2x2<f32>(vec2<f32>(cov[1][1], -cov[0][1]), vec2<f32>(-cov[1][0], cov[0][0]));

    // Opacity: sigmoid'.
    let op = opacity_of(i);
    param_grads[frame.offsets.w + i] = g_opacity * op * (1.0 - op);

    // Conic -> 2D covariance: dL/dC = -C^-1 G C^-1 (the off-diagonal appears twice).
    let gq = mat2x2<f32>(vec2<f32>(g_conic.x, 0.5 * g_conic.y), vec2<f32>(0.5 * g_conic.y, g_conic.z));
    let gcov = -1.0 * (inv * gq * inv);
    let gcov3 = mat3x3<f32>(vec3<f32>(gcov[0], 0.0), vec3<f32>(gcov[1], 0.0), vec3<f32>(0.0));
    let g_tm = 2.0 * gcov3 * tm;
    let g_m = transpose(tw) * g_tm;
    let g_tw = g_tm * transpose(m);
    let g_j = g_tw * transpose(w_rot);

    // Scale and rotation from M = R diag(s).
    let g_s = vec3<f32>(dot(g_m[0], rot[0]), dot(g_m[1], rot[1]), dot(g_m[2], rot[2]));
    write3(frame.offsets.y, i, g_s * scale);
    let g_rot = mat3x3<f32>(g_m[0] * scale.x, g_m[1] * scale.y, g_m[2] * scale.z);
    let g_qn = quat_matrix_backward(q, g_rot);
    let norm = max(length(q_raw), 1e-12);
    let g_q = (g_qn - q * dot(q, g_qn)) / norm;
    let ro = frame.offsets.z + 4u * i;
    param_grads[ro] = g_q.x;
    param_grads[ro + 1u] = g_q.y;
    param_grads[ro + 2u] = g_q.z;
    param_grads[ro + 3u] = g_q.w;

    // The camera-space point: through mean2d, depth and the Jacobian J(t).
    let rz = 1.0 / t.z;
    let rz2 = rz * rz;
    var g_t = vec3<f32>(
        g_mean2d.x * fx * rz,
        g_mean2d.y * fy * rz,
        -g_mean2d.x * fx * t.x * rz2 - g_mean2d.y * fy * t.y * rz2 + g_depth,
    );
    let j00 = g_j[0][0];
    let j11 = g_j[1][1];
    let j02 = g_j[2][0];
    let j12 = g_j[2][1];
    g_t.z += -fx * rz2 * j00 - fy * rz2 * j11;
    if jac.clamped_x {
        let ux = jac.j[2][0] / (-fx * rz);
        g_t.z += j02 * fx * ux * rz2;
    } else {
        g_t.x += j02 * (-fx * rz2);
        g_t.z += j02 * 2.0 * fx * t.x * rz2 * rz;
    }
    if jac.clamped_y {
        let uy = jac.j[2][1] / (-fy * rz);
        g_t.z += j12 * fy * uy * rz2;
    } else {
        g_t.y += j12 * (-fy * rz2);
        g_t.z += j12 * 2.0 * fy * t.y * rz2 * rz;
    }
    var g_mean = transpose(w_rot) * g_t;

    // Colour through SH, with the view direction's dependence on the mean.
    let view = view_direction(mean);
    if view.w > 0.0 {
        let dir = view.xyz;
        let so = i * SPLAT_STRIDE;
        let color = vec3<f32>(splats[so + 6u], splats[so + 7u], splats[so + 8u]);
        // The clamp at 0 passes no gradient.
        let gc = select(vec3<f32>(0.0), g_color, color > vec3<f32>(0.0));
        let degree = frame.sizes.y;
        let y = sh_basis(degree, dir);
        let dy = sh_basis_grad(degree, dir);
        write3(frame.offsets2.x, i, gc * y[0]);
        var g_dir = vec3<f32>(0.0);
        for (var k = 1u; k < sh_coeffs(degree); k++) {
            let o = frame.offsets2.y + i * frame.sizes.z + 3u * (k - 1u);
            let gk = gc * y[k];
            param_grads[o] = gk.x;
            param_grads[o + 1u] = gk.y;
            param_grads[o + 2u] = gk.z;
            g_dir += dy[k] * dot(sh_rest_of(i, k), gc);
        }
        g_mean += (g_dir - dir * dot(dir, g_dir)) / view.w;
    }
    write3(frame.offsets.x, i, g_mean);
    let ndc = vec2<f32>(0.5 * f32(frame.image.x), 0.5 * f32(frame.image.y));
    screen_stats[3u * i] = length(g_mean2d * ndc);
    screen_stats[3u * i + 1u] = 1.0;
    let mid = 0.5 * (cov[0][0] + cov[1][1]);
    screen_stats[3u * i + 2u] = 3.0 * sqrt(mid + sqrt(max(mid * mid - determinant(cov), 0.0)));
}
