//! aim-capture: everything between a recording and an undistorted, posed,
//! time-stamped frame. It does not depend on the reconstruction code.

pub mod aria;
pub mod bench;
pub mod calib;
pub mod crop;
pub mod dataset;
pub mod detect;
pub mod error;
pub mod frame;
pub mod ingest;
pub mod io;
pub mod mps;
pub mod pipeline;
pub mod recording;
pub mod source;
pub mod undistort;
#[cfg(feature = "video")]
pub mod video;
pub mod vrs;

pub use error::{Error, Result};
pub use frame::{Frame, Intrinsics, Phase};
