// Real spherical harmonics up to degree 3, as src/render/sh.rs (the original
// 3DGS constants and signs).

const SH_C0: f32 = 0.2820948;
const SH_C1: f32 = 0.4886025;
const SH_C2_0: f32 = 1.0925484;
const SH_C2_1: f32 = -1.0925484;
const SH_C2_2: f32 = 0.31539157;
const SH_C2_3: f32 = -1.0925484;
const SH_C2_4: f32 = 0.5462742;
const SH_C3_0: f32 = -0.5900436;
const SH_C3_1: f32 = 2.8906114;
const SH_C3_2: f32 = -0.4570458;
const SH_C3_3: f32 = 0.37317633;
const SH_C3_4: f32 = -0.4570458;
const SH_C3_5: f32 = 1.4453057;
const SH_C3_6: f32 = -0.5900436;

fn sh_coeffs(degree: u32) -> u32 {
    return (degree + 1u) * (degree + 1u);
}

// Basis values Y_k(d), k < (degree + 1)^2, at unit direction d; the rest 0.
fn sh_basis(degree: u32, d: vec3<f32>) -> array<f32, 16> {
    var y: array<f32, 16>;
    y[0] = SH_C0;
    if degree == 0u {
        return y;
    }
    let x = d.x;
    let yy = d.y;
    let z = d.z;
    y[1] = -SH_C1 * yy;
    y[2] = SH_C1 * z;
    y[3] = -SH_C1 * x;
    if degree == 1u {
        return y;
    }
    let xx = x * x;
    let y2 = yy * yy;
    let zz = z * z;
    y[4] = SH_C2_0 * x * yy;
    y[5] = SH_C2_1 * yy * z;
    y[6] = SH_C2_2 * (2.0 * zz - xx - y2);
    y[7] = SH_C2_3 * x * z;
    y[8] = SH_C2_4 * (xx - y2);
    if degree == 2u {
        return y;
    }
    y[9] = SH_C3_0 * yy * (3.0 * xx - y2);
    y[10] = SH_C3_1 * x * yy * z;
    y[11] = SH_C3_2 * yy * (4.0 * zz - xx - y2);
    y[12] = SH_C3_3 * z * (2.0 * zz - 3.0 * xx - 3.0 * y2);
    y[13] = SH_C3_4 * x * (4.0 * zz - xx - y2);
    y[14] = SH_C3_5 * z * (xx - y2);
    y[15] = SH_C3_6 * x * (xx - 3.0 * y2);
    return y;
}

// dY_k/dd, the direction's components taken as independent.
fn sh_basis_grad(degree: u32, d: vec3<f32>) -> array<vec3<f32>, 16> {
    var g: array<vec3<f32>, 16>;
    if degree == 0u {
        return g;
    }
    let x = d.x;
    let y = d.y;
    let z = d.z;
    g[1] = vec3<f32>(0.0, -SH_C1, 0.0);
    g[2] = vec3<f32>(0.0, 0.0, SH_C1);
    g[3] = vec3<f32>(-SH_C1, 0.0, 0.0);
    if degree == 1u {
        return g;
    }
    let xx = x * x;
    let yy = y * y;
    let zz = z * z;
    g[4] = SH_C2_0 * vec3<f32>(y, x, 0.0);
    g[5] = SH_C2_1 * vec3<f32>(0.0, z, y);
    g[6] = SH_C2_2 * vec3<f32>(-2.0 * x, -2.0 * y, 4.0 * z);
    g[7] = SH_C2_3 * vec3<f32>(z, 0.0, x);
    g[8] = SH_C2_4 * vec3<f32>(2.0 * x, -2.0 * y, 0.0);
    if degree == 2u {
        return g;
    }
    g[9] = SH_C3_0 * vec3<f32>(6.0 * x * y, 3.0 * xx - 3.0 * yy, 0.0);
    g[10] = SH_C3_1 * vec3<f32>(y * z, x * z, x * y);
    g[11] = SH_C3_2 * vec3<f32>(-2.0 * x * y, 4.0 * zz - xx - 3.0 * yy, 8.0 * y * z);
    g[12] = SH_C3_3 * vec3<f32>(-6.0 * x * z, -6.0 * y * z, 6.0 * zz - 3.0 * xx - 3.0 * yy);
    g[13] = SH_C3_4 * vec3<f32>(4.0 * zz - 3.0 * xx - yy, -2.0 * x * y, 8.0 * x * z);
    g[14] = SH_C3_5 * vec3<f32>(2.0 * x * z, -2.0 * y * z, xx - yy);
    g[15] = SH_C3_6 * vec3<f32>(3.0 * xx - 3.0 * yy, -6.0 * x * y, 0.0);
    return g;
}

// The direction from the camera centre to Gaussian i's mean, normalised
// (zero when they coincide), and the distance.
fn view_direction(mean: vec3<f32>) -> vec4<f32> {
    let v = mean - frame.position.xyz;
    let len = length(v);
    if len > 0.0 {
        return vec4<f32>(v / len, len);
    }
    return vec4<f32>(0.0);
}
