//! The object's crop of a frame: a raw recording's undistorted frame shows the
//! whole room with the object a fraction of it; the trainers model one object
//! against a known background. [`ObjectCrop`] cuts each frame to the square
//! around the object region's image rectangle (the principal point shifted, the
//! focal length scaled: still an exact pinhole camera) and resamples it to a
//! fixed size. With `mask_outside` it marks as background (alpha 0) every pixel
//! whose ray misses the region (nothing of the object can be seen there; what
//! `aim capture crop` shows); without, every pixel keeps what it shows (the
//! session learns the room around the object too).

use glam::{Mat4, Vec3};

use crate::detect::ObjectRegion;
use crate::frame::{Frame, Intrinsics};

/// Border around the region's image rectangle, as a fraction of its larger side:
/// the SSIM windows and the tracker's footprints reach a little past the object.
pub const DEFAULT_MARGIN: f32 = 0.1;

/// How frames are cut to the object.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ObjectCrop {
    pub region: ObjectRegion,
    /// Output width and height in pixels.
    pub size: u32,
    /// Extra border around the region's rectangle, as a fraction of its larger side.
    pub margin: f32,
    /// Pixels whose rays miss the region become background (alpha 0); otherwise
    /// every pixel keeps what it shows (the room is learnt around the object).
    pub mask_outside: bool,
}

impl ObjectCrop {
    /// The crop of `frame`, or None when the region is not in its view.
    pub fn apply(&self, frame: &Frame) -> Option<Frame> {
        let k = frame.intrinsics;
        let (x0, y0, x1, y1) = self.region.image_rect(&frame.world_to_camera, &k)?;
        let side = ((x1 - x0).max(y1 - y0) as f32 * (1.0 + self.margin)).min(k.width.min(k.height) as f32);
        // The square centred on the rectangle, shifted to stay inside the image:
        // pixels off the image are unknown, not background.
        let centre = [(x0 + x1) as f32 * 0.5, (y0 + y1) as f32 * 0.5];
        let origin = [
            (centre[0] - side * 0.5).clamp(0.0, k.width as f32 - side),
            (centre[1] - side * 0.5).clamp(0.0, k.height as f32 - side),
        ];
        let scale = self.size as f32 / side;
        let cropped = Intrinsics {
            width: self.size,
            height: self.size,
            fx: k.fx * scale,
            fy: k.fy * scale,
            cx: (k.cx - origin[0]) * scale,
            cy: (k.cy - origin[1]) * scale,
        };
        let c2w = frame.world_to_camera.inverse();
        let eye = c2w.transform_point3(Vec3::ZERO);
        let (lo, hi) = (Vec3::from(self.region.min.map(|v| v as f32)), Vec3::from(self.region.max.map(|v| v as f32)));
        // Supersampling enough for the output pixel to cover its source pixels.
        let taps = (1.0 / scale).ceil().max(2.0) as u32;
        let src = &frame.image;
        let mut out = image::RgbaImage::new(self.size, self.size);
        for (i, j, px) in out.enumerate_pixels_mut() {
            let mut sum = [0.0f32; 4];
            for sy in 0..taps {
                for sx in 0..taps {
                    let u = i as f32 + (sx as f32 + 0.5) / taps as f32;
                    let v = j as f32 + (sy as f32 + 0.5) / taps as f32;
                    if self.mask_outside && !ray_hits_box(eye, ray_direction(&c2w, &cropped, u, v), lo, hi) {
                        continue;
                    }
                    let s = bilinear(src, origin[0] + u / scale, origin[1] + v / scale);
                    for c in 0..3 {
                        sum[c] += s[c] * s[3];
                    }
                    sum[3] += s[3];
                }
            }
            let n = (taps * taps) as f32;
            let a = sum[3] / n;
            *px = if sum[3] > 0.0 {
                image::Rgba([
                    (sum[0] / sum[3]).round().clamp(0.0, 255.0) as u8,
                    (sum[1] / sum[3]).round().clamp(0.0, 255.0) as u8,
                    (sum[2] / sum[3]).round().clamp(0.0, 255.0) as u8,
                    (a * 255.0).round() as u8,
                ])
            } else {
                image::Rgba([0, 0, 0, 0])
            };
        }
        Some(Frame { intrinsics: cropped, image: std::sync::Arc::new(out), depth: None, ..frame.clone() })
    }
}

/// World-frame direction of the ray through continuous pixel (u, v).
fn ray_direction(c2w: &Mat4, k: &Intrinsics, u: f32, v: f32) -> Vec3 {
    c2w.transform_vector3(k.unproject(u, v))
}

/// Whether the ray from `origin` along `dir` (forward only) crosses the box.
fn ray_hits_box(origin: Vec3, dir: Vec3, lo: Vec3, hi: Vec3) -> bool {
    let (mut t0, mut t1) = (0.0f32, f32::INFINITY);
    for a in 0..3 {
        if dir[a].abs() < 1e-12 {
            if origin[a] < lo[a] || origin[a] > hi[a] {
                return false;
            }
            continue;
        }
        let (ta, tb) = ((lo[a] - origin[a]) / dir[a], (hi[a] - origin[a]) / dir[a]);
        t0 = t0.max(ta.min(tb));
        t1 = t1.min(ta.max(tb));
    }
    t0 <= t1
}

/// RGBA (0-255, alpha as a weight in [0, 1]) at continuous coordinate (x, y),
/// pixel centres at +0.5; alpha 0 off the image.
fn bilinear(img: &image::RgbaImage, x: f32, y: f32) -> [f32; 4] {
    let (w, h) = (img.width() as i64, img.height() as i64);
    let (fx, fy) = (x - 0.5, y - 0.5);
    let (ix, iy) = (fx.floor() as i64, fy.floor() as i64);
    let (ax, ay) = (fx - ix as f32, fy - iy as f32);
    let mut acc = [0.0f32; 4];
    for (dy, wy) in [(0, 1.0 - ay), (1, ay)] {
        for (dx, wx) in [(0, 1.0 - ax), (1, ax)] {
            let (px, py) = ((ix + dx).clamp(0, w - 1), (iy + dy).clamp(0, h - 1));
            let p = img.get_pixel(px as u32, py as u32);
            let wgt = wx * wy;
            for c in 0..3 {
                acc[c] += p[c] as f32 * wgt;
            }
            acc[3] += p[3] as f32 / 255.0 * wgt;
        }
    }
    acc
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::Phase;

    /// A camera at (0, 0, -3) looking along +z at a unit box around the origin.
    fn frame_of(image: image::RgbaImage) -> Frame {
        let k = Intrinsics { width: 200, height: 100, fx: 100.0, fy: 100.0, cx: 100.0, cy: 50.0 };
        Frame {
            index: 0,
            timestamp_s: 0.0,
            motion_time: None,
            phase: Phase::Scan,
            intrinsics: k,
            world_to_camera: Mat4::from_translation(Vec3::new(0.0, 0.0, 3.0)),
            image: std::sync::Arc::new(image),
            depth: None,
            source: "test".into(),
        }
    }

    #[test]
    fn the_crop_is_the_same_camera_cut_and_scaled_and_misses_are_background() {
        // Pixel colour encodes the pixel, so a crop pixel says where it was read.
        let img = image::RgbaImage::from_fn(200, 100, |x, y| image::Rgba([x as u8, y as u8, 7, 255]));
        let frame = frame_of(img);
        let region = ObjectRegion { min: [-0.5, -0.5, -0.5], max: [0.5, 0.5, 0.5] };
        let crop = ObjectCrop { region, size: 64, margin: 0.25, mask_outside: true }.apply(&frame).unwrap();
        let k = crop.intrinsics;
        assert_eq!((k.width, k.height, crop.image.width()), (64, 64, 64));
        // The box's near face spans 0.5 / 2.5 * 100 = 20 px each side of the centre.
        // Every crop pixel whose ray hits the box reads the source pixel its
        // camera maps it to; a corner pixel's ray misses: background.
        let mut hits = 0;
        for (i, j, p) in crop.image.enumerate_pixels() {
            let dir = k.unproject(i as f32 + 0.5, j as f32 + 0.5);
            let (su, sv) = (100.0 * dir.x / dir.z + 100.0, 100.0 * dir.y / dir.z + 50.0);
            let through_box = (dir.x / dir.z * 3.5).abs() < 0.5 && (dir.y / dir.z * 3.5).abs() < 0.5
                || (dir.x / dir.z * 2.5).abs() < 0.5 && (dir.y / dir.z * 2.5).abs() < 0.5;
            if p[3] == 255 {
                hits += 1;
                assert!(through_box, "pixel ({i}, {j}) is object but its ray misses the box");
                assert!((p[0] as f32 - (su - 0.5)).abs() <= 1.0, "x read at {} for {su}", p[0]);
                assert!((p[1] as f32 - (sv - 0.5)).abs() <= 1.0, "y read at {} for {sv}", p[1]);
            } else if p[3] == 0 {
                assert!(!through_box, "pixel ({i}, {j}) is background but its ray crosses the box");
            }
        }
        assert!(hits > 64 * 64 / 3, "{hits} object pixels");
        assert_eq!(crop.image.get_pixel(0, 0)[3], 0);
    }

    #[test]
    fn a_region_out_of_view_gives_no_crop() {
        let frame = frame_of(image::RgbaImage::new(200, 100));
        let behind = ObjectRegion { min: [-0.5, -0.5, -6.0], max: [0.5, 0.5, -5.0] };
        assert!(ObjectCrop { region: behind, size: 32, margin: 0.1, mask_outside: true }.apply(&frame).is_none());
    }
}
