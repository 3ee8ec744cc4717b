//! The library's error type. Every error about a file names the file; file
//! errors are the capture crate's (one definition of "this file, this problem"
//! for the whole workspace).

use std::path::PathBuf;

pub use aim_capture::Error as FileError;

#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A file that cannot be read or written, or whose contents are wrong.
    #[error(transparent)]
    File(#[from] FileError),
    /// A configuration value or argument that is out of range or unknown.
    #[error("invalid configuration: {0}")]
    Config(String),
    /// Input that is readable but holds nothing to learn from (nothing moved,
    /// the hand never let go, no motion frames): the input, not the program, is at fault.
    #[error("{0}")]
    Unusable(String),
    #[error("{0}")]
    Other(String),
}

pub type Result<T, E = Error> = std::result::Result<T, E>;

impl Error {
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Error::File(FileError::io(path, source))
    }

    pub fn bad_file(path: impl Into<PathBuf>, message: impl Into<String>) -> Self {
        Error::File(FileError::bad_file(path, message))
    }
}

/// Write a file atomically: write a temporary file beside it, then rename.
pub fn write_atomic(path: &std::path::Path, bytes: &[u8]) -> Result<()> {
    aim_capture::io::write_atomic(path, bytes).map_err(Error::from)
}
