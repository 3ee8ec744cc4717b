//! A contact sheet: every object at its start and end state, one row per object.

use glam::Vec3;
use rayon::prelude::*;

use super::objects::{object, OBJECT_NAMES};
use super::render::{render, RenderOptions};
use crate::camera::Camera;
use crate::error::Result;

/// Render each object at t = 0 and t = 1 from a three-quarter front view, tiles of
/// `tile` pixels, composited over a light grey background. Rows follow
/// [`OBJECT_NAMES`]; columns are start, end.
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
    let mut sheet =
        image::RgbaImage::from_pixel(2 * tile, OBJECT_NAMES.len() as u32 * tile, image::Rgba([235, 235, 235, 255]));
    for (row, col, img) in tiles {
        for (x, y, p) in img.enumerate_pixels() {
            let a = p[3] as f32 / 255.0;
            let dst = sheet.get_pixel_mut(col as u32 * tile + x, row as u32 * tile + y);
            for c in 0..3 {
                dst[c] = (p[c] as f32 * a + dst[c] as f32 * (1.0 - a)).round() as u8;
            }
        }
    }
    Ok(sheet)
}
