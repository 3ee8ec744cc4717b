// One Gaussian's parameters, read from the params buffer (the GaussianSet's
// groups one after another, at the offsets the frame gives), and the
// projection's shared pieces. Prepended to the projection kernels.

fn camera_rotation() -> mat3x3<f32> {
    return mat3x3<f32>(frame.rot0.xyz, frame.rot1.xyz, frame.rot2.xyz);
}

fn mean_of(i: u32) -> vec3<f32> {
    let o = frame.offsets.x + 3u * i;
    return vec3<f32>(params[o], params[o + 1u], params[o + 2u]);
}

fn scale_of(i: u32) -> vec3<f32> {
    let o = frame.offsets.y + 3u * i;
    return exp(vec3<f32>(params[o], params[o + 1u], params[o + 2u]));
}

// The raw quaternion (w, x, y, z).
fn raw_rotation_of(i: u32) -> vec4<f32> {
    let o = frame.offsets.z + 4u * i;
    return vec4<f32>(params[o], params[o + 1u], params[o + 2u], params[o + 3u]);
}

// The normalised quaternion (w, x, y, z); identity when degenerate.
fn rotation_of(i: u32) -> vec4<f32> {
    let q = raw_rotation_of(i);
    let n = length(q);
    if n > 1e-12 {
        return q / n;
    }
    return vec4<f32>(1.0, 0.0, 0.0, 0.0);
}

fn opacity_of(i: u32) -> f32 {
    return sigmoid(params[frame.offsets.w + i]);
}

fn sh_dc_of(i: u32) -> vec3<f32> {
    let o = frame.offsets2.x + 3u * i;
    return vec3<f32>(params[o], params[o + 1u], params[o + 2u]);
}

// SH rest coefficient k >= 1 of Gaussian i (rgb).
fn sh_rest_of(i: u32, k: u32) -> vec3<f32> {
    let o = frame.offsets2.y + i * frame.sizes.z + 3u * (k - 1u);
    return vec3<f32>(params[o], params[o + 1u], params[o + 2u]);
}

// Rotation matrix of a unit quaternion (w, x, y, z), as glam's Mat3::from_quat.
fn quat_to_matrix(q: vec4<f32>) -> mat3x3<f32> {
    let w = q.x;
    let x = q.y;
    let y = q.z;
    let z = q.w;
    let x2 = x + x;
    let y2 = y + y;
    let z2 = z + z;
    let xx = x * x2;
    let xy = x * y2;
    let xz = x * z2;
    let yy = y * y2;
    let yz = y * z2;
    let zz = z * z2;
    let wx = w * x2;
    let wy = w * y2;
    let wz = w * z2;
    return mat3x3<f32>(
        vec3<f32>(1.0 - (yy + zz), xy + wz, xz - wy),
        vec3<f32>(xy - wz, 1.0 - (xx + zz), yz + wx),
        vec3<f32>(xz + wy, yz - wx, 1.0 - (xx + yy)),
    );
}

// The 3D covariance factor M = R diag(s), so Sigma = M M^T.
fn cov_factor(rot: mat3x3<f32>, s: vec3<f32>) -> mat3x3<f32> {
    return mat3x3<f32>(rot[0] * s.x, rot[1] * s.y, rot[2] * s.z);
}

// The projection Jacobian at camera point t (third row zero), and whether
// x / y were clamped to the limits.
struct Jacobian {
    j: mat3x3<f32>,
    clamped_x: bool,
    clamped_y: bool,
}

fn jacobian(t: vec3<f32>) -> Jacobian {
    let fx = frame.intrinsics.x;
    let fy = frame.intrinsics.y;
    let rz = 1.0 / t.z;
    let ux = t.x * rz;
    let uy = t.y * rz;
    let cx = clamp(ux, -frame.limits.x, frame.limits.x);
    let cy = clamp(uy, -frame.limits.y, frame.limits.y);
    let j = mat3x3<f32>(
        vec3<f32>(fx * rz, 0.0, 0.0),
        vec3<f32>(0.0, fy * rz, 0.0),
        vec3<f32>(-fx * cx * rz, -fy * cy * rz, 0.0),
    );
    return Jacobian(j, cx != ux, cy != uy);
}

// The dilated 2D covariance [[xx, xy], [xy, yy]] of T M (rows 0..2).
fn covariance_2d(tm: mat3x3<f32>) -> mat2x2<f32> {
    let full = tm * transpose(tm);
    return mat2x2<f32>(
        vec2<f32>(full[0][0] + COV2D_DILATION, full[0][1]),
        vec2<f32>(full[1][0], full[1][1] + COV2D_DILATION),
    );
}
