//! Undistortion of fisheye frames to a linear (pinhole) camera through a precomputed
//! lookup table with bilinear sampling, as projectaria_tools'
//! `distort_by_calibration(image, get_linear_camera_calibration(W, H, f), src)` does:
//! for every output pixel, unproject through the linear camera, project through the
//! source model, and sample the source bilinearly (pixel centres at integer coordinates).
//! Optional: clockwise-90 upright output, vignetting correction.

use glam::DVec2;
use rayon::prelude::*;

use crate::calib::CameraCalibration;

/// Fixed-point bits of the bilinear weights.
const WBITS: u32 = 8;
const WONE: u32 = 1 << WBITS;

/// How to undistort.
#[derive(Clone, Debug, PartialEq)]
pub struct UndistortConfig {
    pub width: u32,
    pub height: u32,
    /// Focal length of the linear camera in output pixels.
    pub focal: f64,
    /// Rotate the output clockwise by 90 degrees (Aria RGB is mounted sideways).
    pub upright: bool,
}

impl UndistortConfig {
    /// Default output for Aria RGB: 704 x 704, focal 300 px (about 99 degrees field of view,
    /// inside the calibrated fisheye field), upright off.
    pub fn aria_default() -> Self {
        UndistortConfig { width: 704, height: 704, focal: 300.0, upright: false }
    }
}

/// One output pixel's source: top-left source pixel index and fixed-point weights.
#[derive(Clone, Copy, Debug)]
struct Tap {
    /// Index of the top-left source pixel (y * w + x), u32::MAX when invalid.
    idx: u32,
    fx: u16,
    fy: u16,
    /// Vignetting gain in 8.8 fixed point (256 = 1.0).
    gain: u16,
}

/// A precomputed undistortion map from one source calibration to a linear camera.
#[derive(Clone, Debug)]
pub struct UndistortMap {
    pub src_width: u32,
    pub src_height: u32,
    /// The output camera (linear model, projectaria convention, upright applied).
    pub target: CameraCalibration,
    taps: Vec<Tap>,
}

impl UndistortMap {
    /// Build the map. `src` must describe images of `src.width` x `src.height`.
    pub fn new(src: &CameraCalibration, cfg: &UndistortConfig) -> Self {
        Self::with_vignetting(src, cfg, None)
    }

    /// Build the map with a vignetting mask (source resolution, grey 0..255, 255 = no
    /// falloff). Output = input / mask, with the gain capped at 4 and pixels whose mask is
    /// below 1/16 marked invalid.
    pub fn with_vignetting(src: &CameraCalibration, cfg: &UndistortConfig, mask: Option<&image::GrayImage>) -> Self {
        let linear = src.linear(cfg.width, cfg.height, cfg.focal);
        let (sw, sh) = (src.width, src.height);
        let mask = mask.filter(|m| m.width() == sw && m.height() == sh);
        if mask.is_none() {
            tracing::debug!("no vignetting correction");
        }
        // Taps of the unrotated linear image.
        let (w, h) = (cfg.width as usize, cfg.height as usize);
        let mut taps = vec![Tap { idx: u32::MAX, fx: 0, fy: 0, gain: 0 }; w * h];
        taps.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
            for (x, t) in row.iter_mut().enumerate() {
                if sw < 2 || sh < 2 {
                    continue;
                }
                let Some(ray) = linear.unproject(DVec2::new(x as f64, y as f64)) else { continue };
                let Some(p) = src.project(ray) else { continue };
                // Bilinear footprint must lie inside the source.
                if p.x < 0.0 || p.y < 0.0 || p.x > (sw - 1) as f64 || p.y > (sh - 1) as f64 {
                    continue;
                }
                let x0 = (p.x.floor() as u32).min(sw.saturating_sub(2));
                let y0 = (p.y.floor() as u32).min(sh.saturating_sub(2));
                let fx = ((p.x - x0 as f64) * WONE as f64).round().clamp(0.0, WONE as f64) as u16;
                let fy = ((p.y - y0 as f64) * WONE as f64).round().clamp(0.0, WONE as f64) as u16;
                let gain = match mask {
                    None => 256u16,
                    Some(m) => {
                        let v = m.get_pixel(p.x.round() as u32, p.y.round() as u32).0[0] as f64 / 255.0;
                        if v < 1.0 / 16.0 {
                            continue;
                        }
                        ((256.0 / v).min(4.0 * 256.0)).round() as u16
                    }
                };
                *t = Tap { idx: y0 * sw + x0, fx, fy, gain };
            }
        });
        let (target, taps) = if cfg.upright {
            // Output (u', v') shows unrotated (u, v) = (v', H - 1 - u'); output is h wide, w tall.
            let mut rot = vec![Tap { idx: u32::MAX, fx: 0, fy: 0, gain: 0 }; w * h];
            for vp in 0..w {
                for up in 0..h {
                    rot[vp * h + up] = taps[(h - 1 - up) * w + vp];
                }
            }
            (linear.rotated_cw90().unwrap_or(linear), rot)
        } else {
            (linear, taps)
        };
        UndistortMap { src_width: sw, src_height: sh, target, taps }
    }

    pub fn width(&self) -> u32 {
        self.target.width
    }
    pub fn height(&self) -> u32 {
        self.target.height
    }

    /// Fraction of output pixels that see the source.
    pub fn valid_fraction(&self) -> f64 {
        self.taps.iter().filter(|t| t.idx != u32::MAX).count() as f64 / self.taps.len().max(1) as f64
    }

    /// Undistort packed RGB8 to RGBA8; alpha is 255 where the source is seen and 0 where the
    /// output ray falls outside the fisheye image. Panics never: a source of the wrong size
    /// gives an error.
    pub fn apply_rgb(&self, src: &image::RgbImage) -> Result<image::RgbaImage, String> {
        if src.width() != self.src_width || src.height() != self.src_height {
            return Err(format!(
                "image is {}x{}, calibration is for {}x{}",
                src.width(),
                src.height(),
                self.src_width,
                self.src_height
            ));
        }
        let (w, h) = (self.width() as usize, self.height() as usize);
        let s = src.as_raw();
        let stride = self.src_width as usize * 3;
        let mut out = vec![0u8; w * h * 4];
        out.par_chunks_mut(w * 4).zip(self.taps.par_chunks(w)).for_each(|(orow, trow)| {
            for (o, t) in orow.chunks_exact_mut(4).zip(trow) {
                if t.idx == u32::MAX {
                    continue;
                }
                let i = t.idx as usize * 3;
                let (fx, fy) = (t.fx as u32, t.fy as u32);
                let w00 = (WONE - fx) * (WONE - fy);
                let w10 = fx * (WONE - fy);
                let w01 = (WONE - fx) * fy;
                let w11 = fx * fy;
                for c in 0..3 {
                    let v = w00 * s[i + c] as u32
                        + w10 * s[i + 3 + c] as u32
                        + w01 * s[i + stride + c] as u32
                        + w11 * s[i + stride + 3 + c] as u32;
                    // v has 2*WBITS fractional bits; gain has 8.
                    let v = ((v as u64 * t.gain as u64) + (1 << (2 * WBITS + 7))) >> (2 * WBITS + 8);
                    o[c] = v.min(255) as u8;
                }
                o[3] = 255;
            }
        });
        image::RgbaImage::from_raw(w as u32, h as u32, out).ok_or_else(|| "bad output buffer".to_string())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::calib::{CameraModel, Se3};

    fn linear_src(w: u32, f: f64) -> CameraCalibration {
        CameraCalibration {
            label: "src".into(),
            model: CameraModel::Linear([f, f, (w as f64 - 1.0) / 2.0, (w as f64 - 1.0) / 2.0]),
            width: w,
            height: w,
            t_device_camera: Se3::IDENTITY,
            max_theta: 1.5,
            valid_radius: None,
        }
    }

    #[test]
    fn identity_map_reproduces_the_image() {
        let src = linear_src(64, 50.0);
        let map = UndistortMap::new(&src, &UndistortConfig { width: 64, height: 64, focal: 50.0, upright: false });
        let img = image::RgbImage::from_fn(64, 64, |x, y| image::Rgb([x as u8 * 3, y as u8 * 2, 7]));
        let out = map.apply_rgb(&img).unwrap();
        for y in 0..63 {
            for x in 0..63 {
                let a = img.get_pixel(x, y).0;
                let b = out.get_pixel(x, y).0;
                assert_eq!(&a[..], &b[..3], "at {x},{y}");
                assert_eq!(b[3], 255);
            }
        }
    }

    #[test]
    fn upright_rotates_clockwise() {
        let src = linear_src(32, 30.0);
        let map = UndistortMap::new(&src, &UndistortConfig { width: 32, height: 32, focal: 30.0, upright: true });
        let img = image::RgbImage::from_fn(32, 32, |x, y| image::Rgb([x as u8, y as u8, 0]));
        let out = map.apply_rgb(&img).unwrap();
        // Clockwise: output (u', v') shows input (v', H-1-u').
        for (u, v) in [(3u32, 5u32), (10, 20), (30, 1)] {
            let o = out.get_pixel(u, v).0;
            assert_eq!((o[0], o[1]), (v as u8, (31 - u) as u8), "at {u},{v}");
        }
    }

    #[test]
    fn wrong_size_is_an_error() {
        let src = linear_src(32, 30.0);
        let map = UndistortMap::new(&src, &UndistortConfig { width: 16, height: 16, focal: 15.0, upright: false });
        assert!(map.apply_rgb(&image::RgbImage::new(31, 32)).is_err());
    }
}
