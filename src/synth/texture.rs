//! Procedural solid textures: albedo as a function of a point in a part's rest frame,
//! so texture moves rigidly with its part. Band-limited value noise (no aliasing at
//! a few samples per pixel for the scales used), with enough fine detail for
//! photometric training.

use glam::Vec3;

/// How a surface's albedo varies.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Pattern {
    /// Slight mottling.
    Plain,
    /// Rings around the local z axis with grain.
    Wood,
    /// Mottled plastic with coloured dots.
    Speckle,
    /// Brushed metal: noise stretched along x.
    Brushed,
    /// Tiles with grout lines and per-tile tint.
    Tiles,
    /// Veins.
    Marble,
}

/// A surface's appearance: a pattern mixing `base` and `accent`, at a spatial frequency `scale` (per unit).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Material {
    pub base: Vec3,
    pub accent: Vec3,
    pub pattern: Pattern,
    pub scale: f32,
}

impl Material {
    pub const fn new(pattern: Pattern, base: Vec3, accent: Vec3, scale: f32) -> Self {
        Self { base, accent, pattern, scale }
    }

    /// Albedo in [0, 1] at a rest-frame point.
    pub fn albedo(&self, p: Vec3) -> Vec3 {
        let q = p * self.scale;
        let c = match self.pattern {
            Pattern::Plain => self.base * (0.85 + 0.3 * fbm(q, 3)),
            Pattern::Wood => {
                let warp = 1.5 * fbm(q * 0.5, 2);
                let r = (q.x * q.x + q.y * q.y).sqrt() * 2.0 + warp;
                let ring = (r - r.floor() - 0.5).abs() * 2.0;
                let ring = smooth(0.55, 0.95, ring);
                let grain = fbm(Vec3::new(q.x * 1.5, q.y * 1.5, q.z * 12.0), 3);
                self.base.lerp(self.accent, ring * 0.8) * (0.8 + 0.4 * grain)
            }
            Pattern::Speckle => {
                let mott = fbm(q, 3);
                let dots = value_noise(q * 6.0);
                let dot = smooth(0.72, 0.78, dots);
                (self.base * (0.8 + 0.4 * mott)).lerp(self.accent, dot)
            }
            Pattern::Brushed => {
                let streak = fbm(Vec3::new(q.x * 0.2, q.y * 18.0, q.z * 18.0), 3);
                let blotch = fbm(q * 0.7, 2);
                self.base * (0.75 + 0.35 * streak) + self.accent * (0.25 * blotch)
            }
            Pattern::Tiles => {
                let cell = q.floor();
                let f = q - cell;
                let edge = f.min(Vec3::ONE - f);
                // Grout on the two smallest distances only (the surface's in-plane axes).
                let mut e = [edge.x, edge.y, edge.z];
                e.sort_by(f32::total_cmp);
                let grout = 1.0 - smooth(0.02, 0.06, e[1]);
                let tint = hash3(cell.x as i32, cell.y as i32, cell.z as i32) as f32 / u32::MAX as f32;
                let tile = self.base * (0.75 + 0.4 * tint) * (0.9 + 0.2 * fbm(q * 4.0, 2));
                tile.lerp(self.accent, grout)
            }
            Pattern::Marble => {
                let v = (q.x * 2.0 + q.z + 5.0 * fbm(q * 0.8, 4)).sin();
                let vein = smooth(0.75, 1.0, v.abs());
                self.base.lerp(self.accent, vein) * (0.9 + 0.2 * fbm(q * 3.0, 2))
            }
        };
        c.clamp(Vec3::ZERO, Vec3::ONE)
    }
}

fn smooth(e0: f32, e1: f32, x: f32) -> f32 {
    let t = ((x - e0) / (e1 - e0)).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

/// Integer lattice hash (a few rounds of multiply-xorshift).
#[inline]
pub fn hash3(x: i32, y: i32, z: i32) -> u32 {
    let mut h = (x as u32).wrapping_mul(0x8da6_b343)
        ^ (y as u32).wrapping_mul(0xd816_3841)
        ^ (z as u32).wrapping_mul(0xcb1a_b31f);
    h ^= h >> 15;
    h = h.wrapping_mul(0x2c1b_3c6d);
    h ^= h >> 12;
    h = h.wrapping_mul(0x297a_2d39);
    h ^= h >> 15;
    h
}

/// Trilinear value noise in [0, 1] with smooth interpolation.
#[inline]
pub fn value_noise(p: Vec3) -> f32 {
    let i = p.floor();
    let f = p - i;
    let u = f * f * (Vec3::splat(3.0) - 2.0 * f);
    let (x, y, z) = (i.x as i32, i.y as i32, i.z as i32);
    let v = |dx: i32, dy: i32, dz: i32| hash3(x + dx, y + dy, z + dz) as f32 * (1.0 / u32::MAX as f32);
    let x00 = v(0, 0, 0) + (v(1, 0, 0) - v(0, 0, 0)) * u.x;
    let x10 = v(0, 1, 0) + (v(1, 1, 0) - v(0, 1, 0)) * u.x;
    let x01 = v(0, 0, 1) + (v(1, 0, 1) - v(0, 0, 1)) * u.x;
    let x11 = v(0, 1, 1) + (v(1, 1, 1) - v(0, 1, 1)) * u.x;
    let y0 = x00 + (x10 - x00) * u.y;
    let y1 = x01 + (x11 - x01) * u.y;
    y0 + (y1 - y0) * u.z
}

/// Fractal sum of `octaves` value-noise octaves, normalised to [0, 1].
pub fn fbm(p: Vec3, octaves: u32) -> f32 {
    let mut sum = 0.0;
    let mut amp = 0.5;
    let mut norm = 0.0;
    let mut q = p;
    for _ in 0..octaves {
        sum += amp * value_noise(q);
        norm += amp;
        amp *= 0.5;
        q = q * 2.03 + Vec3::splat(17.1);
    }
    sum / norm
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn textures_vary_and_stay_in_range() {
        for pattern in
            [Pattern::Plain, Pattern::Wood, Pattern::Speckle, Pattern::Brushed, Pattern::Tiles, Pattern::Marble]
        {
            let m = Material::new(pattern, Vec3::new(0.6, 0.5, 0.4), Vec3::new(0.2, 0.3, 0.1), 8.0);
            let vals: Vec<Vec3> =
                (0..400).map(|i| m.albedo(Vec3::new(i as f32 * 0.013, 0.3, i as f32 * 0.007))).collect();
            let mean = vals.iter().copied().sum::<Vec3>() / vals.len() as f32;
            let var = vals.iter().map(|v| (*v - mean).length_squared()).sum::<f32>() / vals.len() as f32;
            assert!(var > 1e-4, "{pattern:?} is too flat: variance {var}");
            assert!(vals.iter().all(|v| v.min_element() >= 0.0 && v.max_element() <= 1.0));
        }
    }
}
