//! nerfstudio transforms.json (to be completed).
pub struct NerfstudioDataset;
pub enum Distortion {}
pub fn load_nerfstudio() {}
