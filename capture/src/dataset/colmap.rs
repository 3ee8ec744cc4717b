//! COLMAP sparse models (to be completed).
pub struct ColmapCamera;
pub struct ColmapImage;
pub struct ColmapModel;
pub struct ColmapPoint;
pub fn load_colmap_frames() {}
pub fn read_colmap_model() {}
