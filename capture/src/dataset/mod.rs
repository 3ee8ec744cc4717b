//! Dataset folders: the AiM layout, nerfstudio transforms.json, COLMAP sparse models.
//!
//! Every loader returns [`crate::Frame`] values in the library's conventions:
//! OpenCV world-to-camera (Blender/OpenGL camera-to-world matrices are converted
//! with [`crate::frame::opencv_world_to_camera_from_blender`]), pinhole
//! [`crate::Intrinsics`] with pixel centres at (i + 0.5, j + 0.5), RGBA images and,
//! where the dataset has it, metric depth in metres.
//!
//! - [`aim`]: `{start,motion,end}/transforms_{train,test}.json` (the AiM paper's data and
//!   the synthetic benchmark written by `aim synth`).
//! - [`nerfstudio`]: a nerfstudio `transforms.json` (global or per-frame intrinsics,
//!   distortion parameters reported, not applied).
//! - [`colmap`]: COLMAP sparse models (`cameras`, `images`, `points3D`, `.bin` or `.txt`).
//!
//! Datasets carry no capture clock: `timestamp_s` is the frame's index over a nominal
//! 30 fps clock ([`NOMINAL_FPS`]); `motion_time` carries a dataset's normalised `time`.

use std::path::{Path, PathBuf};

use glam::Mat4;

use crate::error::{Error, Result};

pub mod aim;
pub mod colmap;
pub mod nerfstudio;

pub use aim::{load_aim, load_aim_transforms, AimDataset, AimPhase, TransformsFile, TransformsFrame};
pub use colmap::{
    load_colmap_frames, read_colmap_model, write_colmap_bin, write_colmap_text, ColmapCamera, ColmapImage, ColmapModel,
    ColmapPoint,
};
pub use nerfstudio::{load_nerfstudio, Distortion, NerfstudioDataset};

/// The clock datasets are given when they have none: frame index / 30 s.
pub const NOMINAL_FPS: f64 = 30.0;

/// What to read besides poses.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct LoadOptions {
    /// Read the depth maps a dataset references (uint16 PNG, millimetres).
    pub depth: bool,
}

impl Default for LoadOptions {
    fn default() -> Self {
        Self { depth: true }
    }
}

/// Read an image file as RGBA8 (opaque when it has no alpha).
pub fn read_rgba(path: &Path) -> Result<image::RgbaImage> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    let img =
        image::load_from_memory(&bytes).map_err(|e| Error::bad_file(path, format!("not a readable image: {e}")))?;
    Ok(img.into_rgba8())
}

/// Read a 16-bit depth PNG in millimetres into metres (0 stays 0 = unknown).
pub fn read_depth_mm(path: &Path, width: u32, height: u32) -> Result<Vec<f32>> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    let img =
        image::load_from_memory(&bytes).map_err(|e| Error::bad_file(path, format!("not a readable image: {e}")))?;
    let img = match img {
        image::DynamicImage::ImageLuma16(g) => g,
        other => {
            return Err(Error::bad_file(
                path,
                format!("depth must be a 16-bit grayscale PNG in millimetres, found {:?}", other.color()),
            ))
        }
    };
    if img.width() != width || img.height() != height {
        return Err(Error::bad_file(
            path,
            format!("depth is {}x{} but its image is {width}x{height}", img.width(), img.height()),
        ));
    }
    Ok(img.into_raw().into_iter().map(|mm| mm as f32 / 1000.0).collect())
}

/// Resolve a `file_path` from a transforms file: relative to `dir`, a leading `./`
/// dropped, and `.png` appended when the path has no extension and does not exist as given.
pub fn resolve_image_path(dir: &Path, file_path: &str) -> PathBuf {
    let rel = file_path.strip_prefix("./").unwrap_or(file_path);
    let p = dir.join(rel);
    if p.extension().is_none() && !p.exists() {
        let mut s = p.into_os_string();
        s.push(".png");
        PathBuf::from(s)
    } else {
        p
    }
}

/// A 4x4 matrix given as a list of rows; checks it is finite and rigid.
pub(crate) fn matrix_from_rows(rows: &[[f32; 4]; 4], path: &Path, what: &str) -> Result<Mat4> {
    let mut m = Mat4::from_cols_array_2d(rows).transpose();
    // Writers that invert matrices leave ~1e-8 residue in the last row: snap it.
    if (m.row(3) - glam::Vec4::W).abs().max_element() < 1e-5 {
        m = Mat4::from_cols(
            m.x_axis.truncate().extend(0.0),
            m.y_axis.truncate().extend(0.0),
            m.z_axis.truncate().extend(0.0),
            m.w_axis.truncate().extend(1.0),
        );
    }
    if !m.is_finite() {
        return Err(Error::bad_file(path, format!("{what}: transform_matrix has non-finite entries")));
    }
    if !crate::frame::is_rigid(&m, 1e-3) {
        return Err(Error::bad_file(
            path,
            format!(
                "{what}: transform_matrix is not rigid (rotation must be orthonormal with det +1, last row 0 0 0 1)"
            ),
        ));
    }
    Ok(m)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scratch(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("aim_capture_dataset_{}_{name}", std::process::id()));
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    #[test]
    fn image_paths_resolve_with_or_without_extension() {
        let d = scratch("paths");
        std::fs::write(d.join("a.png"), b"").unwrap();
        assert_eq!(resolve_image_path(&d, "./a"), d.join("a.png"));
        assert_eq!(resolve_image_path(&d, "a.png"), d.join("a.png"));
        assert_eq!(resolve_image_path(&d, "b.jpg"), d.join("b.jpg"));
    }

    #[test]
    fn matrices_snap_residue_and_reject_non_rigid() {
        let p = Path::new("t.json");
        let mut rows = [[1.0, 0.0, 0.0, 0.5], [0.0, 0.0, -1.0, 1.0], [0.0, 1.0, 0.0, 2.0], [1e-8, 0.0, -1e-8, 1.0]];
        let m = matrix_from_rows(&rows, p, "f").unwrap();
        assert_eq!(m.row(3), glam::Vec4::W);
        assert_eq!(m.w_axis.truncate(), glam::Vec3::new(0.5, 1.0, 2.0));
        rows[0][0] = 1.1;
        let e = matrix_from_rows(&rows, p, "frame 3").unwrap_err().to_string();
        assert!(e.contains("t.json") && e.contains("frame 3") && e.contains("not rigid"), "{e}");
    }

    #[test]
    fn depth_must_be_16_bit_millimetres() {
        let d = scratch("depth");
        let p16 = d.join("d16.png");
        image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_raw(2, 1, vec![0, 1234]).unwrap().save(&p16).unwrap();
        assert_eq!(read_depth_mm(&p16, 2, 1).unwrap(), vec![0.0, 1.234]);
        assert!(read_depth_mm(&p16, 3, 1).unwrap_err().to_string().contains("d16.png"));
        let p8 = d.join("d8.png");
        image::GrayImage::from_raw(2, 1, vec![0, 12]).unwrap().save(&p8).unwrap();
        let e = read_depth_mm(&p8, 2, 1).unwrap_err().to_string();
        assert!(e.contains("d8.png") && e.contains("16-bit"), "{e}");
    }
}
