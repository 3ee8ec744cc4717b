//! A contact sheet: every object at its start and end state, one row per object.

use glam::Vec3;
use rayon::prelude::*;

use super::objects::{object, OBJECT_NAMES};
use super::render::{render, RenderOptions};
use crate::camera::Camera;
use crate::error::Result;

/// Objects per row of the sheet (each object takes two tiles: start, end).
pub const OBJECTS_PER_ROW: usize = 2;

/// Render each object at t = 0 and t = 1 from a three-quarter front view, tiles of
/// `tile` pixels, composited over a light grey background. Objects follow
/// [`OBJECT_NAMES`] left to right, top to bottom, [`OBJECTS_PER_ROW`] per row, each as a
/// (start, end) pair of tiles; alternate pairs have a slightly darker background.
pub fn contact_sheet(tile: u32) -> Result<image::RgbaImage> {
    let objects = OBJECT_NAMES.iter().map(|n| object(n)).collect::<Result<Vec<_>>>()?;
    let tiles: Vec<(usize, usize, image::RgbaImage)> = objects
        .par_iter()
        .enumerate()
        .flat_map(|(row, o)| {
            [0usize, 1].into_par_iter().map(move |col| {
                let k = crate::camera::Intrinsics::from_fov_x(tile, tile, 0.6911);
                let (az, el) = (
                    (o.view.front_azimuth_deg - 35.0).to_radians(),
                    28f32.max(o.view.motion_elevation_deg).to_radians(),
                );
                let d = o.view.distance * 1.05;
                let eye = d * Vec3::new(el.cos() * az.cos(), el.cos() * az.sin(), el.sin());
                let cam = Camera::look_at(k, eye, Vec3::ZERO, Vec3::Z);
                let r =
                    render(&o.posed(col as f32), &cam, &RenderOptions { samples_per_pixel: 9, ..Default::default() });
                (row, col, r.to_rgba8())
            })
        })
        .collect();
    let rows = OBJECT_NAMES.len().div_ceil(OBJECTS_PER_ROW) as u32;
    let cols = 2 * OBJECTS_PER_ROW as u32;
    let mut sheet = image::RgbaImage::from_pixel(cols * tile, rows * tile, image::Rgba([255, 255, 255, 255]));
    for (index, state, img) in tiles {
        let gx = ((index % OBJECTS_PER_ROW) * 2 + state) as u32 * tile;
        let gy = (index / OBJECTS_PER_ROW) as u32 * tile;
        let shade = if (index / OBJECTS_PER_ROW + index % OBJECTS_PER_ROW).is_multiple_of(2) { 236.0 } else { 218.0 };
        for (x, y, p) in img.enumerate_pixels() {
            let a = p[3] as f32 / 255.0;
            let dst = sheet.get_pixel_mut(gx + x, gy + y);
            for c in 0..3 {
                dst[c] = (p[c] as f32 * a + shade * (1.0 - a)).round() as u8;
            }
        }
    }
    Ok(sheet)
}
