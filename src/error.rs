//! The library's error type. Every error about a file names the file.

use std::path::PathBuf;

#[derive(Debug, thiserror::Error)]
pub enum Error {
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    /// A file whose contents are wrong: names the file and what is wrong.
    #[error("{path}: {message}")]
    BadFile { path: PathBuf, message: String },
    /// A configuration value or argument that is out of range or unknown.
    #[error("invalid configuration: {0}")]
    Config(String),
    #[error(transparent)]
    Capture(#[from] aim_capture::Error),
    #[error("{0}")]
    Other(String),
}

pub type Result<T, E = Error> = std::result::Result<T, E>;

impl Error {
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Error::Io { path: path.into(), source }
    }

    pub fn bad_file(path: impl Into<PathBuf>, message: impl Into<String>) -> Self {
        Error::BadFile { path: path.into(), message: message.into() }
    }
}

/// Write a file atomically: write a temporary file beside it, then rename.
pub fn write_atomic(path: &std::path::Path, bytes: &[u8]) -> Result<()> {
    aim_capture::io::write_atomic(path, bytes).map_err(Error::from)
}
