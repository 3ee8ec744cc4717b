//! aim: streaming, incremental reconstruction of articulated objects from AR
//! captures ("Articulation in Motion").
//!
//! One module per pipeline stage; data flows source -> frames -> trainer ->
//! model snapshots -> analysis -> exports.

pub mod batch;
pub mod bench;
pub mod camera;
pub mod deform;
pub mod error;
pub mod eval;
pub mod export;
pub mod mesh;
pub mod motion;
pub mod render;
pub mod splat;
pub mod stream;
pub mod suite;
pub mod synth;
pub mod train;
pub mod viz;

pub use error::{Error, Result};
