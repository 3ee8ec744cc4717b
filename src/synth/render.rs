//! The exact ray-cast renderer: RGBA (several stratified samples per pixel), z-depth
//! and part ids (one ray through each pixel centre).

use glam::{Vec3, Vec4};
use rayon::prelude::*;

use super::geometry::Ray;
use super::scene::{Hit, PosedScene};
use super::texture::hash3;
use crate::camera::Camera;

/// Part-id value of background pixels.
pub const BACKGROUND_ID: u8 = 255;

/// Lambertian shading with a fixed world-space light (z up) plus ambient.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Lighting {
    /// Unit direction towards the light.
    pub direction: Vec3,
    pub ambient: f32,
    pub diffuse: f32,
}

impl Default for Lighting {
    fn default() -> Self {
        Self { direction: Vec3::new(0.35, -0.55, 0.75).normalize(), ambient: 0.38, diffuse: 0.62 }
    }
}

impl Lighting {
    pub fn shade(&self, hit: &Hit) -> Vec3 {
        // Half-Lambert-ish wrap keeps faces turned away from the light readable.
        let ndl = hit.normal.dot(self.direction);
        let d = if ndl > 0.0 { ndl } else { 0.25 * ndl.abs() };
        hit.albedo * (self.ambient + self.diffuse * d)
    }
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RenderOptions {
    /// Colour samples per pixel, rounded to a square grid (1, 4, 9, ...), jittered.
    pub samples_per_pixel: u32,
    /// Seed of the sample jitter.
    pub seed: u64,
    pub lighting: Lighting,
}

impl Default for RenderOptions {
    fn default() -> Self {
        Self { samples_per_pixel: 4, seed: 0, lighting: Lighting::default() }
    }
}

/// One rendered view.
#[derive(Clone, Debug, PartialEq)]
pub struct RenderOutput {
    pub width: u32,
    pub height: u32,
    /// Straight (not premultiplied) RGB of the covered samples, alpha = coverage; row-major.
    pub rgba: Vec<Vec4>,
    /// Z-depth (along the optical axis) at the pixel centre; 0 for background.
    pub depth: Vec<f32>,
    /// Part id at the pixel centre; [`BACKGROUND_ID`] for background.
    pub part_id: Vec<u8>,
}

impl RenderOutput {
    pub fn to_rgba8(&self) -> image::RgbaImage {
        let px = |v: f32| (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8;
        let data: Vec<u8> = self.rgba.iter().flat_map(|c| [px(c.x), px(c.y), px(c.z), px(c.w)]).collect();
        image::RgbaImage::from_raw(self.width, self.height, data).unwrap_or_default()
    }

    /// Depth in millimetres (clamped to u16).
    pub fn depth_mm(&self) -> image::ImageBuffer<image::Luma<u16>, Vec<u16>> {
        let data = self.depth.iter().map(|&d| (d * 1000.0).round().clamp(0.0, 65535.0) as u16).collect();
        image::ImageBuffer::from_raw(self.width, self.height, data).unwrap_or_default()
    }

    pub fn part_image(&self) -> image::GrayImage {
        image::GrayImage::from_raw(self.width, self.height, self.part_id.clone()).unwrap_or_default()
    }
}

/// World ray through the continuous pixel coordinate (u, v) (pixel (i, j) has its centre at
/// (i + 0.5, j + 0.5)). `dir` has unit z in camera coordinates, so the ray parameter of a
/// hit is its z-depth.
pub fn camera_ray(camera: &Camera, u: f32, v: f32) -> Ray {
    let d_cam = camera.intrinsics.unproject(u, v);
    let r_t = camera.rotation().transpose();
    Ray::new(camera.position(), r_t * d_cam)
}

fn jitter(seed: u64, pixel: u32, sample: u32) -> (f32, f32) {
    let s = (seed ^ (seed >> 32)) as i32;
    let a = hash3(pixel as i32, sample as i32, s);
    let b = hash3(a as i32, s.wrapping_add(7), pixel as i32);
    ((a >> 8) as f32 / (1u32 << 24) as f32, (b >> 8) as f32 / (1u32 << 24) as f32)
}

/// Render `scene` from `camera`, in parallel over rows. Deterministic for a seed.
pub fn render(scene: &PosedScene, camera: &Camera, opts: &RenderOptions) -> RenderOutput {
    let (w, h) = (camera.width(), camera.height());
    let n = ((opts.samples_per_pixel.max(1) as f32).sqrt().round() as u32).max(1);
    let rows: Vec<(Vec<Vec4>, Vec<f32>, Vec<u8>)> = (0..h)
        .into_par_iter()
        .map(|j| {
            let mut rgba = Vec::with_capacity(w as usize);
            let mut depth = Vec::with_capacity(w as usize);
            let mut ids = Vec::with_capacity(w as usize);
            for i in 0..w {
                let pixel = j * w + i;
                let centre = scene.intersect(&camera_ray(camera, i as f32 + 0.5, j as f32 + 0.5), f32::INFINITY);
                depth.push(centre.map(|h| h.t).unwrap_or(0.0));
                ids.push(centre.map(|h| h.part.min(254) as u8).unwrap_or(BACKGROUND_ID));
                let mut sum = Vec3::ZERO;
                let mut covered = 0u32;
                if n == 1 {
                    if let Some(hit) = centre {
                        sum += opts.lighting.shade(&hit);
                        covered = 1;
                    }
                } else {
                    for sy in 0..n {
                        for sx in 0..n {
                            let (jx, jy) = jitter(opts.seed, pixel, sy * n + sx);
                            let u = i as f32 + (sx as f32 + jx) / n as f32;
                            let v = j as f32 + (sy as f32 + jy) / n as f32;
                            if let Some(hit) = scene.intersect(&camera_ray(camera, u, v), f32::INFINITY) {
                                sum += opts.lighting.shade(&hit);
                                covered += 1;
                            }
                        }
                    }
                }
                let alpha = covered as f32 / (n * n) as f32;
                let rgb = if covered > 0 { sum / covered as f32 } else { Vec3::ZERO };
                rgba.push(rgb.extend(alpha));
            }
            (rgba, depth, ids)
        })
        .collect();
    let mut out = RenderOutput {
        width: w,
        height: h,
        rgba: Vec::with_capacity((w * h) as usize),
        depth: Vec::with_capacity((w * h) as usize),
        part_id: Vec::with_capacity((w * h) as usize),
    };
    for (c, d, p) in rows {
        out.rgba.extend(c);
        out.depth.extend(d);
        out.part_id.extend(p);
    }
    out
}
